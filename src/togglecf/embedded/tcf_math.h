/* tcf_math.h: the quaternion and vector helpers of the exported filters (tcf_filter.c, tcf_vqf.c, tcf_features.c),
 * C99 float32, all static inline (each source compiles its own copy; no symbol is exported).
 *
 * Conventions (as togglecf): quaternion [w, x, y, z], Hamilton product, sensor-to-earth.
 * Ports of togglecf/core/quaternion.py (the *_scalar functions) and filters/base.py.
 */
#ifndef TCF_MATH_H
#define TCF_MATH_H

#include <math.h>
#include <stddef.h>

/* filters/base.py GYRO_FULL_SCALE: a gyro axis at or beyond it is saturated [rad/s] */
#define TCF_GYRO_FULL_SCALE 34.9f

/* 1: every axis of the gyro reading w [rad/s] is below full scale (0 for NaN: comparisons are false) */
static inline int tcf_gyro_ok(const float w[3]) {
  return fabsf(w[0]) < TCF_GYRO_FULL_SCALE && fabsf(w[1]) < TCF_GYRO_FULL_SCALE && fabsf(w[2]) < TCF_GYRO_FULL_SCALE;
}

/* finite, non-zero 3-vector (vector_ok) */
static inline int tcf_vec_ok(const float v[3]) {
  float n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  return isfinite(n2) && n2 > 1e-18f;
}

/* VQF's magnetic disturbance test (field_agrees): the field's norm within norm_th of ref_norm (relative) and its
   dip [rad] within dip_th of ref_dip */
static inline int tcf_field_agrees(float ref_norm, float ref_dip, float norm, float dip, float norm_th, float dip_th) {
  return fabsf(norm - ref_norm) < norm_th * ref_norm && fabsf(dip - ref_dip) < dip_th;
}

/* out = p (x) q (Hamilton; out may alias p or q) (multiply_scalar) */
static inline void tcf_q_mul(const float p[4], const float q[4], float out[4]) {
  float r[4];
  r[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3];
  r[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2];
  r[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1];
  r[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0];
  out[0] = r[0]; out[1] = r[1]; out[2] = r[2]; out[3] = r[3];
}

/* The two normalisations are not interchangeable: each rounds as its Python twin, so the C filter
   follows its own Python filter to float32 rounding. Both give the identity for a zero or
   non-finite norm. */

/* q / |q| with four divisions (quaternion.normalize_scalar; the toggling CF) */
static inline void tcf_q_normalize(float q[4]) {
  float n = sqrtf(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (!(n > 1e-12f) || !isfinite(n)) {
    q[0] = 1.0f; q[1] = 0.0f; q[2] = 0.0f; q[3] = 0.0f;
    return;
  }
  q[0] /= n; q[1] /= n; q[2] /= n; q[3] /= n;
}

/* q * (1 / |q|), one division (vqf_core._unit; the VQF core) */
static inline void tcf_q_unit(float q[4]) {
  float n = sqrtf(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), r;
  if (!(n > 1e-12f && n < INFINITY)) {
    q[0] = 1.0f; q[1] = 0.0f; q[2] = 0.0f; q[3] = 0.0f;
    return;
  }
  r = 1.0f / n;
  q[0] *= r; q[1] *= r; q[2] *= r; q[3] *= r;
}

/* out = v rotated from sensor to earth by unit q (rotate_scalar); conj = 1: by q*, earth to sensor
   (rotate_inverse_scalar). out may alias v. */
static inline void tcf_q_rotate(const float q[4], int conj, const float v[3], float out[3]) {
  float w = q[0], x = conj ? -q[1] : q[1], y = conj ? -q[2] : q[2], z = conj ? -q[3] : q[3];
  float tx = 2.0f * (y * v[2] - z * v[1]);
  float ty = 2.0f * (z * v[0] - x * v[2]);
  float tz = 2.0f * (x * v[1] - y * v[0]);
  float r0 = v[0] + w * tx + y * tz - z * ty;
  float r1 = v[1] + w * ty + z * tx - x * tz;
  float r2 = v[2] + w * tz + x * ty - y * tx;
  out[0] = r0; out[1] = r1; out[2] = r2;
}

/* exponential map of the rotation vector rv [rad] (from_rotvec_scalar; the gyro increment of one
   sample: the rate times dt) */
static inline void tcf_q_from_rotvec(const float rv[3], float q[4]) {
  float angle = sqrtf(rv[0] * rv[0] + rv[1] * rv[1] + rv[2] * rv[2]);
  float k = angle < 1e-6f ? 0.5f - angle * angle / 48.0f : sinf(0.5f * angle) / angle;
  q[0] = cosf(0.5f * angle); q[1] = k * rv[0]; q[2] = k * rv[1]; q[3] = k * rv[2];
}

#endif /* TCF_MATH_H */
