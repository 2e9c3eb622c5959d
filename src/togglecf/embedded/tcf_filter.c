/* tcf_filter.c: the toggling-gain CF of togglecf in C99, float32 (API in tcf_filter.h).
 *
 * Line-by-line port of (togglecf/...):
 *   toggling/inloop.py     toggling_inloop_batch (one sample) -> tcf_filter_update_dt (the models:
 *                                                               tcf_features_push, tcf_features.c)
 *   filters/toggling.py    _gains, toggle_step               -> tcf_gains, tcf_toggle_step
 *                          TogglingFilter._coefficients, reset -> tcf_coefficients, tcf_filter_init
 *   filters/timeconst.py   gain                              -> tcf_gain
 *   filters/prediction.py  switch_status (the toggling CF's own fallback rule) -> tcf_switch_status; the
 *                          shared steps (class_evidence, remove_noise, predicted_disturbance, back_off):
 *                          tcf_prediction.h
 *   filters/base.py        gyro_increment, acc_mag_quaternion (vector_ok: tcf_math.h)
 *   quaternion.py          from_matrix/from_acc_mag (_scalar); multiply/normalize/rotate/from_rotvec
 *                          (_scalar) are in tcf_math.h
 * The comments "step N" refer to the steps of the module docstring of filters/toggling.py.
 */
#include <math.h>
#include <stddef.h>
#include "tcf_filter.h"
#include "tcf_prediction.h"  /* the prediction row as named fields, steps 1, 3, 4 */
#include "tcf_math.h"  /* tcf_q_mul, tcf_q_normalize, tcf_q_rotate, tcf_q_from_rotvec, tcf_vec_ok, tcf_gyro_ok,
                          tcf_field_agrees */

/* compile-time check of the documented state size (C99: a negative array size is an error) */
typedef char tcf_state_bytes_check[(sizeof(tcf_filter_t) == TCF_STATE_BYTES) ? 1 : -1];

#if defined(__FAST_MATH__)
#error "tcf_filter.c must not be compiled with -ffast-math: the no-prediction (NaN) tests would be removed"
#endif

#if !defined(TCF_TAU_ACC_INIT) || !defined(TCF_OUTPUT_TAU) || !defined(TCF_BIAS_TAU)
#error "tcf_config.h must define the time constants TCF_TAU_ACC_INIT, TCF_TAU_MAG_INIT, TCF_OUTPUT_TAU, TCF_BIAS_TAU (re-export it)"
#endif

/* the learned time constants [s], per state in class order (tcf_config.h; physical: rate-free) */
static const float tcf_tau_acc[TCF_N_CLASSES] = TCF_TAU_ACC_INIT;
static const float tcf_tau_mag[TCF_N_CLASSES] = TCF_TAU_MAG_INIT;

/* ------------------------------------------------------------------ quaternion.py (_scalar) */

/* Shepperd's method on a row-major rotation matrix, w >= 0 (from_matrix_scalar) */
static void q_from_matrix(const float r[9], float q[4]) {
  float tr = r[0] + r[4] + r[8];
  if (tr >= r[0] && tr >= r[4] && tr >= r[8]) {
    q[0] = 1.0f + tr; q[1] = r[7] - r[5]; q[2] = r[2] - r[6]; q[3] = r[3] - r[1];
  } else if (r[0] >= r[4] && r[0] >= r[8]) {
    q[0] = r[7] - r[5]; q[1] = 1.0f + r[0] - r[4] - r[8]; q[2] = r[1] + r[3]; q[3] = r[2] + r[6];
  } else if (r[4] >= r[8]) {
    q[0] = r[2] - r[6]; q[1] = r[1] + r[3]; q[2] = 1.0f - r[0] + r[4] - r[8]; q[3] = r[5] + r[7];
  } else {
    q[0] = r[3] - r[1]; q[1] = r[2] + r[6]; q[2] = r[5] + r[7]; q[3] = 1.0f - r[0] - r[4] + r[8];
  }
  tcf_q_normalize(q);
  if (q[0] < 0.0f) { q[0] = -q[0]; q[1] = -q[1]; q[2] = -q[2]; q[3] = -q[3]; }
}

/* sensor -> ENU from one acc and one mag vector; 0 for zero-norm or parallel inputs
   (from_acc_mag_scalar) */
static int q_from_acc_mag(const float a[3], const float m[3], float q[4]) {
  float r[9], ne, na = sqrtf(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
  float ux, uy, uz, ex, ey, ez;
  q[0] = 1.0f; q[1] = 0.0f; q[2] = 0.0f; q[3] = 0.0f;
  if (!(na > 1e-9f)) return 0;
  ux = a[0] / na; uy = a[1] / na; uz = a[2] / na;
  ex = m[1] * uz - m[2] * uy; ey = m[2] * ux - m[0] * uz; ez = m[0] * uy - m[1] * ux;  /* east = mag x up */
  ne = sqrtf(ex * ex + ey * ey + ez * ez);
  if (!(ne > 1e-9f)) return 0;
  ex /= ne; ey /= ne; ez /= ne;
  r[0] = ex; r[1] = ey; r[2] = ez;
  r[3] = uy * ez - uz * ey; r[4] = uz * ex - ux * ez; r[5] = ux * ey - uy * ex;  /* north = up x east */
  r[6] = ux; r[7] = uy; r[8] = uz;
  q_from_matrix(r, q);
  return 1;
}

/* ------------------------------------------------------------------ filters/base.py */

/* exp(w dt / 2), 0 (dq = identity) for a non-finite or saturated w or an invalid dt
   (gyro_increment; the comparisons are false for NaN) */
static int gyro_increment(const float w[3], float dt, float dq[4]) {
  float rv[3];
  dq[0] = 1.0f; dq[1] = 0.0f; dq[2] = 0.0f; dq[3] = 0.0f;
  if (!tcf_gyro_ok(w)) return 0;
  if (!(isfinite(dt) && dt > 0.0f && dt <= TCF_MAX_DT)) return 0;
  rv[0] = w[0] * dt; rv[1] = w[1] * dt; rv[2] = w[2] * dt;
  tcf_q_from_rotvec(rv, dq);
  return 1;
}

/* acc/mag orientation (9D), or q_ref tilted onto the measured up direction (6D, or mag not
   valid); returned in the hemisphere of q_ref (acc_mag_quaternion) */
static int acc_mag_quaternion(const float q_ref[4], const float acc[3], const float mag[3], int mag_ok,
                              float q[4]) {
  int ok;
  if (mag_ok) {
    ok = q_from_acc_mag(acc, mag, q);
  } else {
    float g[3] = {0.0f, 0.0f, 1.0f}, dq[4];
    float na = sqrtf(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2]);
    ok = na > 1e-9f;
    if (ok) {
      float u[3];
      u[0] = acc[0] / na; u[1] = acc[1] / na; u[2] = acc[2] / na;
      tcf_q_rotate(q_ref, 0, u, g);
    }
    if (1.0f + g[2] > 1e-9f) {  /* rotation taking g onto +z */
      dq[0] = 1.0f + g[2]; dq[1] = g[1]; dq[2] = -g[0]; dq[3] = 0.0f;
      tcf_q_normalize(dq);
    } else {  /* measured up is predicted down: any horizontal axis will do */
      dq[0] = 0.0f; dq[1] = 1.0f; dq[2] = 0.0f; dq[3] = 0.0f;
    }
    tcf_q_mul(dq, q_ref, q);
  }
  if (q[0] * q_ref[0] + q[1] * q_ref[1] + q[2] * q_ref[2] + q[3] * q_ref[3] < 0.0f) {
    q[0] = -q[0]; q[1] = -q[1]; q[2] = -q[2]; q[3] = -q[3];
  }
  return ok;
}

/* ------------------------------------------------------------------ filters/toggling.py */

/* The per-sample gain of time constant tau [s] at sampling time ts [s] (timeconst.gain): 1 - exp(-ts/tau),
   1 for tau = 0, 0 for tau < 0 (off); -expm1f: exact for ts << tau */
static float tcf_gain(float tau, float ts) {
  if (tau < 0.0f) return 0.0f;
  return tau == 0.0f ? 1.0f : -expm1f(-ts / tau);
}

/* TogglingFilter._coefficients at sampling time ts [s]: the per-state gains, the fallback's cautious
   ones (per sensor the smallest), the output blend and the bias gain */
static void tcf_coefficients(float ts, tcf_filter_coeffs_t *c) {
  int s;
  c->ts = ts;
  for (s = 0; s < TCF_N_CLASSES; ++s) {
    c->alpha_acc[s] = tcf_gain(tcf_tau_acc[s], ts);
    c->alpha_mag[s] = tcf_gain(tcf_tau_mag[s], ts);
  }
  c->alpha_fallback_acc = c->alpha_acc[0];
  c->alpha_fallback_mag = c->alpha_mag[0];
  for (s = 1; s < TCF_N_CLASSES; ++s) {
    if (c->alpha_acc[s] < c->alpha_fallback_acc) c->alpha_fallback_acc = c->alpha_acc[s];
    if (c->alpha_mag[s] < c->alpha_fallback_mag) c->alpha_fallback_mag = c->alpha_mag[s];
  }
  c->gamma = tcf_gain(TCF_OUTPUT_TAU, ts);
  c->bias_gain = tcf_gain(TCF_BIAS_TAU, ts);
  c->tan_mag_step = tanf(TCF_MAG_RATE_LIMIT * ts);
  c->mag_ref_gain = tcf_gain(TCF_MAG_REF_TAU, ts);
}

/* Step 5's gain alpha, lowered where the vector CF step v_new = (1 - alpha) v + alpha m would turn v by
   more than the angle whose tangent is tan_step (0: no bound; rate_bounded_gain): tan theta =
   alpha |v x m| / (v . v_new), solved for alpha at the bound. */
static float tcf_rate_bounded_gain(float alpha, const float v[3], const float m[3], float tan_step) {
  float cx, cy, cz, cross, vv, vm, along, denominator;
  if (tan_step <= 0.0f || alpha <= 0.0f) return alpha;
  cx = v[1] * m[2] - v[2] * m[1];
  cy = v[2] * m[0] - v[0] * m[2];
  cz = v[0] * m[1] - v[1] * m[0];
  cross = sqrtf(cx * cx + cy * cy + cz * cz);
  vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  vm = v[0] * m[0] + v[1] * m[1] + v[2] * m[2];
  along = (1.0f - alpha) * vv + alpha * vm;
  denominator = cross + tan_step * (vv - vm);
  if (alpha * cross <= tan_step * along || denominator <= 0.0f) return alpha;
  return tan_step * vv / denominator;
}

/* Step 5's follow (turn_as): w turned in place by the shortest-arc rotation that takes u's direction to v's
   (Rodrigues, k = u^ x v^, c = u^ . v^: R w = c w + k x w + k (k . w) / (1 + c)); unchanged where u or v
   is zero or not finite, or where they are 90 degrees or more apart. */
static void tcf_turn_as(const float u[3], const float v[3], float w[3]) {
  float nu = sqrtf(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
  float nv = sqrtf(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  float ux, uy, uz, vx, vy, vz, c, kx, ky, kz, kw, w0, w1, w2;
  if (!(nu > 0.0f && nv > 0.0f && isfinite(nu) && isfinite(nv))) return;
  ux = u[0] / nu; uy = u[1] / nu; uz = u[2] / nu;
  vx = v[0] / nv; vy = v[1] / nv; vz = v[2] / nv;
  c = ux * vx + uy * vy + uz * vz;
  if (!(c > 0.0f)) return;
  kx = uy * vz - uz * vy; ky = uz * vx - ux * vz; kz = ux * vy - uy * vx;
  kw = (kx * w[0] + ky * w[1] + kz * w[2]) / (1.0f + c);
  w0 = c * w[0] + ky * w[2] - kz * w[1] + kw * kx;
  w1 = c * w[1] + kz * w[0] - kx * w[2] + kw * ky;
  w2 = c * w[2] + kx * w[1] - ky * w[0] + kw * kz;
  w[0] = w0; w[1] = w1; w[2] = w2;
}

/* Step 5b's field check (_field_accepted, VQF's): m's norm and dip asin(-m^ . up) (positive where the field points
   down, as the features' dip) against the reference (set from the first field, at initialisation), which follows
   an accepted field */
static int tcf_field_accepted(tcf_filter_t *f, const float up[3], const float m[3]) {
  float norm = sqrtf(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]);
  float dip = asinf(fmaxf(-1.0f, fminf(1.0f, -(m[0] * up[0] + m[1] * up[1] + m[2] * up[2]) / norm)));
  int accepted;
  if (!(f->mag_ref_norm > 0.0f)) {
    f->mag_ref_norm = norm;
    f->mag_ref_dip = dip;
  }
  accepted = tcf_field_agrees(f->mag_ref_norm, f->mag_ref_dip, norm, dip, TCF_MAG_NORM_THRESHOLD,
                              TCF_MAG_DIP_THRESHOLD);
  if (accepted) {
    f->mag_ref_norm += f->c.mag_ref_gain * (norm - f->mag_ref_norm);
    f->mag_ref_dip += f->c.mag_ref_gain * (dip - f->mag_ref_dip);
  }
  return accepted;
}

/* Step 5b (heading_bias_step): the bias fed with the heading correction that turned m_before into m_after about
   the vertical of a_pred, where the field m_d and the accelerometer a_d pass their checks; the feed never takes
   |bias| above TCF_HEADING_BIAS_CLIP */
static void tcf_heading_bias_step(tcf_filter_t *f, const float a_d[3], const float m_before[3],
                                  const float m_after[3], const float m_d[3]) {
  const float *a = f->a_pred;
  float na, up[3], g, d0, d1, h0[3], h1[3], n01, sin_turn, v, nb[3], new_norm2;
  int j, field_ok;
  if (!(TCF_HEADING_BIAS_RATE > 0.0f) || !tcf_vec_ok(a)) return;
  na = sqrtf(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
  for (j = 0; j < 3; ++j) up[j] = a[j] / na;
  field_ok = tcf_field_accepted(f, up, m_d);  /* first: the reference follows the field either way */
  g = sqrtf(a_d[0] * a_d[0] + a_d[1] * a_d[1] + a_d[2] * a_d[2]);
  if (!(field_ok && fabsf(g - TCF_GRAVITY) < TCF_ACC_NORM_THRESHOLD * TCF_GRAVITY)) return;
  d0 = m_before[0] * up[0] + m_before[1] * up[1] + m_before[2] * up[2];
  d1 = m_after[0] * up[0] + m_after[1] * up[1] + m_after[2] * up[2];
  for (j = 0; j < 3; ++j) {
    h0[j] = m_before[j] - d0 * up[j];
    h1[j] = m_after[j] - d1 * up[j];
  }
  n01 = sqrtf((h0[0] * h0[0] + h0[1] * h0[1] + h0[2] * h0[2]) * (h1[0] * h1[0] + h1[1] * h1[1] + h1[2] * h1[2]));
  if (!(n01 > 0.0f)) return;
  sin_turn = ((h0[1] * h1[2] - h0[2] * h1[1]) * up[0] + (h0[2] * h1[0] - h0[0] * h1[2]) * up[1]
              + (h0[0] * h1[1] - h0[1] * h1[0]) * up[2]) / n01;  /* the turn about the vertical */
  v = sin_turn * TCF_HEADING_BIAS_RATE;
  for (j = 0; j < 3; ++j) nb[j] = f->bias[j] + v * up[j];
  new_norm2 = nb[0] * nb[0] + nb[1] * nb[1] + nb[2] * nb[2];
  if (new_norm2 > TCF_HEADING_BIAS_CLIP * TCF_HEADING_BIAS_CLIP
      && new_norm2 > f->bias[0] * f->bias[0] + f->bias[1] * f->bias[1] + f->bias[2] * f->bias[2]) return;
  for (j = 0; j < 3; ++j) f->bias[j] = nb[j];
}

/* Step 4, the toggling CF's fallback rule (prediction.switch_status: a hard switch, unlike the learned
   VQF's blend in tcf_vqf_toggling.c; prediction.py's docstring says why): TCF_LEARNED when the
   probabilities are valid and max p >= c0 sum p, else TCF_NO_PREDICTION / TCF_LOW_CONFIDENCE. */
static int tcf_switch_status(int valid, float top, float total) {
  if (!valid) return TCF_NO_PREDICTION;
  if (top < TCF_CONFIDENCE_FLOOR * total) return TCF_LOW_CONFIDENCE;
  return TCF_LEARNED;
}

/* Step 4 on a used prediction (_gains): the probability-weighted gains, total = sum p_s. */
static void tcf_gains(const tcf_filter_coeffs_t *c, const tcf_prediction_t *p, float total, float *aa, float *am) {
  int s;
  *aa = 0.0f;
  *am = 0.0f;
  for (s = 0; s < TCF_N_CLASSES; ++s) {
    *aa += p->probabilities[s] * c->alpha_acc[s];
    *am += p->probabilities[s] * c->alpha_mag[s];
  }
  *aa /= total;
  *am /= total;
}

/* One sample of the toggling CF (toggle_step, steps 1-7) with the held prediction f->feat.pred. */
static void tcf_toggle_step(tcf_filter_t *f, const float gyr[3], const float acc[3], const float mag[3],
                            float dt) {
  tcf_prediction_t pred;
  float a_d[3], m_d[3], alpha_a, alpha_m, p_static, q_am[4], dq[4], w[3], top, total;
  int j, valid, learned, eta_ok, acc_ok, mag_ok, g_ok;
  tcf_prediction_from_row(f->feat.pred, &pred);
  /* step 4 first: the fallback (the cautious gains) also stops steps 1 and 3 */
  valid = tcf_class_evidence(&pred, &top, &total);  /* step 1 */
  learned = tcf_switch_status(valid, top, total) == TCF_LEARNED;
  if (learned) {
    tcf_gains(&f->c, &pred, total, &alpha_a, &alpha_m);
  } else {
    alpha_a = f->c.alpha_fallback_acc;
    alpha_m = f->c.alpha_fallback_mag;
  }
  eta_ok = tcf_remove_noise(&pred, acc, mag, TCF_NOISE_WEIGHT_ACC, TCF_NOISE_WEIGHT_MAG, learned, a_d, m_d);  /* step 3 */
  acc_ok = tcf_vec_ok(a_d);
  mag_ok = TCF_USE_MAG && tcf_vec_ok(m_d);
  if (TCF_MAG_DISTURBANCE_SCALE > 0.0f && eta_ok) {  /* step 4: trust the magnetometer less when a disturbance is
                                                       * predicted, by at most the rejection factor */
    float e = tcf_predicted_disturbance(&pred, TCF_MAG_DISTURBANCE_SCALE);
    alpha_m = tcf_back_off(alpha_m, fminf(e, TCF_MAG_REJECTION_FACTOR - 1.0f));
  }
  p_static = learned ? pred.probabilities[TCF_STATIC_INDEX] : 0.0f;
  f->alpha_acc = 0.0f;
  f->alpha_mag = 0.0f;
  f->p_static = p_static;
  if (!f->initialized) {  /* initialise orientation and vectors from the first valid sample */
    static const float identity[4] = {1.0f, 0.0f, 0.0f, 0.0f};
    float q0[4];
    if (acc_ok && acc_mag_quaternion(identity, a_d, m_d, mag_ok, q0)) {
      static const float north[3] = {0.0f, 1.0f, 0.0f};
      f->quat[0] = q0[0]; f->quat[1] = q0[1]; f->quat[2] = q0[2]; f->quat[3] = q0[3];
      f->initialized = 1u;
      f->a_pred[0] = a_d[0]; f->a_pred[1] = a_d[1]; f->a_pred[2] = a_d[2];
      if (mag_ok) {
        float na = sqrtf(a_d[0] * a_d[0] + a_d[1] * a_d[1] + a_d[2] * a_d[2]);
        float up[3];
        up[0] = a_d[0] / na; up[1] = a_d[1] / na; up[2] = a_d[2] / na;
        f->m_pred[0] = m_d[0]; f->m_pred[1] = m_d[1]; f->m_pred[2] = m_d[2];
        (void)tcf_field_accepted(f, up, m_d);  /* step 5b's field reference, from the first field */
      } else {
        tcf_q_rotate(q0, 1, north, f->m_pred);  /* in 6D m_pred is unused */
      }
    }
    return;
  }
  g_ok = tcf_gyro_ok(gyr);
  if (g_ok && f->c.bias_gain > 0.0f && p_static > 0.0f) {  /* step 1: gyro bias at rest */
    float rx = gyr[0] - f->bias[0], ry = gyr[1] - f->bias[1], rz = gyr[2] - f->bias[2];
    if (rx * rx + ry * ry + rz * rz < TCF_BIAS_GATE * TCF_BIAS_GATE) {
      float k = f->c.bias_gain * p_static;
      f->bias[0] += k * rx; f->bias[1] += k * ry; f->bias[2] += k * rz;
    }
  }
  w[0] = gyr[0] - f->bias[0]; w[1] = gyr[1] - f->bias[1]; w[2] = gyr[2] - f->bias[2];
  if (gyro_increment(w, dt, dq) && g_ok) {  /* step 2: gyro propagation */
    tcf_q_mul(f->quat, dq, f->quat);
    tcf_q_normalize(f->quat);
    tcf_q_rotate(dq, 1, f->a_pred, f->a_pred);  /* earth-fixed directions rotate opposite to the body */
    tcf_q_rotate(dq, 1, f->m_pred, f->m_pred);
  }
  if (acc_ok) {  /* step 5: vector CF step */
    float a_corrected[3];
    for (j = 0; j < 3; ++j) a_corrected[j] = (1.0f - alpha_a) * f->a_pred[j] + alpha_a * a_d[j];
    if (TCF_USE_MAG) tcf_turn_as(f->a_pred, a_corrected, f->m_pred);  /* the tilt correction turns the frame:
                                                                        * the field follows */
    for (j = 0; j < 3; ++j) f->a_pred[j] = a_corrected[j];
    f->alpha_acc = alpha_a;
  }
  if (mag_ok) {  /* the heading correction turns m_pred at most TCF_MAG_RATE_LIMIT */
    float m_corrected[3];
    alpha_m = tcf_rate_bounded_gain(alpha_m, f->m_pred, m_d, f->c.tan_mag_step);
    for (j = 0; j < 3; ++j) m_corrected[j] = (1.0f - alpha_m) * f->m_pred[j] + alpha_m * m_d[j];
    if (acc_ok) tcf_heading_bias_step(f, a_d, f->m_pred, m_corrected, m_d);  /* step 5b: heading bias in motion */
    for (j = 0; j < 3; ++j) f->m_pred[j] = m_corrected[j];
    f->alpha_mag = alpha_m;
  }
  if (acc_mag_quaternion(f->quat, f->a_pred, f->m_pred, TCF_USE_MAG, q_am)) {  /* step 6 */
    const float gamma = f->c.gamma, c = 1.0f - gamma;  /* step 7: output blend (LERP on the short arc) */
    for (j = 0; j < 4; ++j) f->quat[j] = c * f->quat[j] + gamma * q_am[j];
    tcf_q_normalize(f->quat);
  }
}

/* ------------------------------------------------------------------ API */

int tcf_filter_init(tcf_filter_t *f, float fs) {
  tcf_features_rate_t r;
  int j, rc = tcf_features_rate(fs, &r);
  if (rc != TCF_OK) return rc;  /* fs not a rate, or above TCF_MAX_FS */
  if (!(1.0f / fs <= TCF_MAX_DT)) return TCF_ERR_SETTINGS;  /* the gyro would never be integrated */
  tcf_coefficients(1.0f / fs, &f->c);
  f->quat[0] = 1.0f; f->quat[1] = 0.0f; f->quat[2] = 0.0f; f->quat[3] = 0.0f;
  for (j = 0; j < 3; ++j) {
    f->bias[j] = 0.0f; f->a_pred[j] = 0.0f; f->m_pred[j] = 0.0f;
  }
  f->mag_ref_norm = 0.0f;
  f->mag_ref_dip = 0.0f;
  f->initialized = 0u;
  (void)tcf_features_init(&f->feat, fs);  /* TCF_OK: the checks of tcf_features_rate above */
  f->alpha_acc = 0.0f;
  f->alpha_mag = 0.0f;
  f->p_static = 0.0f;
  return TCF_OK;
}

/* toggling_inloop_batch, one sample: push the features; at a window end (every hop samples once the window is
   full) evaluate the trees into f->feat.pred (held until the next one; NaN when the window is
   out of the training range); then the toggling step. */
void tcf_filter_update_dt(tcf_filter_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt) {
  static const float zeros[3] = {0.0f, 0.0f, 0.0f};
  if (mag == NULL) mag = zeros;
  tcf_features_push(&f->feat, gyr, acc, mag);
  tcf_toggle_step(f, gyr, acc, mag, dt);
}

void tcf_filter_update_pred(tcf_filter_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt,
                            const float pred[TCF_N_PRED]) {
  static const float zeros[3] = {0.0f, 0.0f, 0.0f};
  int k;
  for (k = 0; k < TCF_N_PRED; ++k) f->feat.pred[k] = pred[k];
  tcf_toggle_step(f, gyr, acc, mag == NULL ? zeros : mag, dt);
}

void tcf_filter_update(tcf_filter_t *f, const float gyr[3], const float acc[3], const float mag[3]) {
  tcf_filter_update_dt(f, gyr, acc, mag, f->c.ts);
}

void tcf_filter_quat(const tcf_filter_t *f, float q[4]) {
  q[0] = f->quat[0]; q[1] = f->quat[1]; q[2] = f->quat[2]; q[3] = f->quat[3];
}

int tcf_filter_features(const tcf_filter_t *f, float feat[TCF_N_FEATURES]) {
  return tcf_features_row(&f->feat, feat);
}

int tcf_filter_prediction(const tcf_filter_t *f, float pred[TCF_N_PRED]) {
  int k;
  for (k = 0; k < TCF_N_PRED; ++k) pred[k] = f->feat.pred[k];
  return isfinite(f->feat.pred[0]) ? 1 : 0;
}
