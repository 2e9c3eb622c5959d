/* tcf_vqf.c: the VQF-class core filter in C99, float32 (API and design notes in tcf_vqf.h).
 *
 * Line-by-line port of togglecf/filters/vqf_core.py (core_update and its parts update_gyr,
 * update_acc, update_bias, update_mag, update_output; _bias_update, ...,
 * core_coefficients and reset_core_state); the comments (R1)...(M5), (B1)...(B5) and
 * "Alg. 1 l. N" refer to that module's docstring. The second-order low-passes run in the same
 * "delta" form as the Python's _lp (lp_step below), in float32 instead of float64.
 */
#include <math.h>
#include <stddef.h>
#include "tcf_vqf.h"
#include "tcf_math.h"  /* tcf_q_mul, tcf_q_unit, tcf_q_rotate, tcf_q_from_rotvec, tcf_vec_ok, tcf_gyro_ok */

#if defined(__FAST_MATH__)
#error "tcf_vqf.c must not be compiled with -ffast-math: the bad-sample (NaN/inf) tests would be removed"
#endif

/* compile-time check of the documented state size (C99: a negative array size is an error) */
typedef char tcf_vqf_state_bytes_check[(sizeof(tcf_vqf_t) == TCF_VQF_STATE_BYTES) ? 1 : -1];

#define TCF_VQF_PI 3.14159265358979f
#define TCF_VQF_DEG (TCF_VQF_PI / 180.0f)
#define TCF_VQF_SQRT2 1.41421356237310f
/* VQF's bias random-walk scale [deg/s] within bias_forgetting_time (B5) */
#define TCF_VQF_BIAS_DRIFT 0.1f

/* ------------------------------------------------------------------ small helpers */

static float clipf(float x, float lim) { return x < -lim ? -lim : (x > lim ? lim : x); }

static float wrapf(float a) {
  if (a > TCF_VQF_PI) return a - 2.0f * TCF_VQF_PI;
  if (a < -TCF_VQF_PI) return a + 2.0f * TCF_VQF_PI;
  return a;
}

/* rotate v from sensor to earth by unit q (rotate_scalar); tcf_vqf.h */
void tcf_vqf_rotate(const float q[4], const float v[3], float out[3]) { tcf_q_rotate(q, 0, v, out); }

/* row-major rotation matrix of unit q (_matrix) */
static void q_matrix(const float q[4], float r[9]) {
  float w = q[0], x = q[1], y = q[2], z = q[3];
  r[0] = 1.0f - 2.0f * (y * y + z * z); r[1] = 2.0f * (x * y - w * z); r[2] = 2.0f * (x * z + w * y);
  r[3] = 2.0f * (x * y + w * z); r[4] = 1.0f - 2.0f * (x * x + z * z); r[5] = 2.0f * (y * z - w * x);
  r[6] = 2.0f * (x * z - w * y); r[7] = 2.0f * (y * z + w * x); r[8] = 1.0f - 2.0f * (x * x + y * y);
}

/* out = A B^T (row-major 3x3, _mmt) */
static void m_mmt(const float a[9], const float b[9], float out[9]) {
  int i, j;
  for (i = 0; i < 3; ++i)
    for (j = 0; j < 3; ++j)
      out[3 * i + j] = a[3 * i] * b[3 * j] + a[3 * i + 1] * b[3 * j + 1] + a[3 * i + 2] * b[3 * j + 2];
}

/* out = A B (row-major 3x3, _mm) */
static void m_mm(const float a[9], const float b[9], float out[9]) {
  int i, j;
  for (i = 0; i < 3; ++i)
    for (j = 0; j < 3; ++j)
      out[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
}

/* ------------------------------------------------------------------ second-order low-pass */

/* Butterworth LP_2 with time constant tau at sampling time ts (butterworth_lp_coefficients):
   C = tan(pi fc ts) with fc = sqrt(2) / (2 pi tau), D = 1 + sqrt(2) C + C^2, b0 = C^2 / D,
   a2 = (1 - sqrt(2) C + C^2) / D; stored as k = 4 b0 = 1 + a1 + a2 and one_minus_decay = 1 - a2 =
   2 sqrt(2) C / D (the Python LowPass keeps decay = a2 itself). */
static tcf_vqf_lp_coef_t lp_coef(float tau, float ts) {
  tcf_vqf_lp_coef_t c;
  float cc = tanf(ts / (TCF_VQF_SQRT2 * tau));  /* pi fc ts = ts / (sqrt(2) tau) */
  float d = 1.0f + TCF_VQF_SQRT2 * cc + cc * cc;
  c.k = 4.0f * cc * cc / d;
  c.one_minus_decay = 2.0f * TCF_VQF_SQRT2 * cc / d;
  return c;
}

/* Start a sample of a bank (_lp_begin): returns ready, counts the sample while averaging. */
static int lp_begin(tcf_vqf_lp_head_t *h) {
  if (h->ready) return 1;
  h->n += 1u;
  return 0;
}

/* One channel s = {v, dv}: the output for input x (_lp). With w the all-pole part of H(z) =
   b0 (1 + z^-1)^2 / (1 + a1 z^-1 + a2 z^-2) scaled to unit DC gain, v_k = 4 b0 w_k and
   dv_k = v_k - v_{k-1}:
     dv_k = (1 - one_minus_decay) dv_{k-1} + k (x_k - v_{k-1}),   v_k = v_{k-1} + dv_k,
     y_k  = v_{k-1} + (dv_k - dv_{k-1}) / 4             (= b0 (w_k + 2 w_{k-1} + w_{k-2}))
   All increments are small numbers added to a level, so float32 keeps the pole positions
   and the DC gain exact. The state is the signal itself (level and increment), not a
   coefficient-dependent mix as in the direct form II transposed, so when the learned filter
   changes the tau_acc coefficients *c between samples the same state simply runs on with the
   new ones and the output stays continuous (as the Python filter). Averaging phase: s[0] is
   the running sum, the output the mean. */
static float lp_step(float s[2], float x, int ready, uint32_t n, const tcf_vqf_lp_coef_t *c) {
  if (ready) {
    float dv = (s[1] - c->one_minus_decay * s[1]) + c->k * (x - s[0]);
    float y = s[0] + 0.25f * (dv - s[1]);
    s[0] += dv;
    s[1] = dv;
    return y;
  }
  s[0] += x;
  return s[0] / (float)n;
}

/* End of the averaging phase after tau (_lp_end): every channel starts in the steady state
   of its mean (v = mean, dv = 0: the next output is mean + b0 (x - mean), as VQF's DF2T started in the
   steady state of the mean). */
static void lp_end(tcf_vqf_lp_head_t *h, float (*s)[2], int nch, int ready, float tau, float ts) {
  int i;
  if (!ready && (float)h->n * ts >= tau) {
    for (i = 0; i < nch; ++i) {
      s[i][0] = s[i][0] / (float)h->n;
      s[i][1] = 0.0f;
    }
    h->ready = 1u;
  }
}

/* ------------------------------------------------------------------ bias estimation */

/* (B1): P_ii <- P_ii + V while P_ii < P0 */
static void bias_predict(tcf_vqf_t *f) {
  int i;
  for (i = 0; i < 3; ++i)
    if (f->bias_p[4 * i] < f->c.bias_p0) f->bias_p[4 * i] += f->c.bias_v;
}

/* (B4) with pmt = P M^T and s = M P M^T + W (s symmetric): K = P M^T S^-1, b <- b + K e
   (e clipped to +-b_clip), P <- P - K (P M^T)^T (_bias_update) */
static void bias_update(tcf_vqf_t *f, float ex, float ey, float ez, const float pmt[9], const float s[9]) {
  float c00 = s[4] * s[8] - s[5] * s[5];
  float c01 = s[5] * s[2] - s[1] * s[8];
  float c02 = s[1] * s[5] - s[4] * s[2];
  float det = s[0] * c00 + s[1] * c01 + s[2] * c02, d, si[9], k[9], kmp[9], e0, e1, e2, clip = f->c.bias_clip;
  int i;
  if (!(det > 0.0f && isfinite(det))) return;
  d = 1.0f / det;
  si[0] = c00 * d; si[1] = c01 * d; si[2] = c02 * d;
  si[4] = (s[0] * s[8] - s[2] * s[2]) * d;
  si[5] = (s[2] * s[1] - s[0] * s[5]) * d;
  si[8] = (s[0] * s[4] - s[1] * s[1]) * d;
  si[3] = si[1]; si[6] = si[2]; si[7] = si[5];
  m_mmt(pmt, si, k);  /* P M^T S^-1 (S^-1 symmetric) */
  e0 = clipf(ex, clip); e1 = clipf(ey, clip); e2 = clipf(ez, clip);
  f->bias[0] += k[0] * e0 + k[1] * e1 + k[2] * e2;
  f->bias[1] += k[3] * e0 + k[4] * e1 + k[5] * e2;
  f->bias[2] += k[6] * e0 + k[7] * e1 + k[8] * e2;
  m_mmt(k, pmt, kmp);  /* K M P */
  for (i = 0; i < 9; ++i) f->bias_p[i] -= kmp[i];
}

/* ------------------------------------------------------------------ set-up */

/* 1 - exp(-ts / tau), 1 for tau = 0 (gain_from_tau; expm1f keeps it exact for ts << tau) */
static float gain_from_tau(float tau, float ts) { return tau == 0.0f ? 1.0f : -expm1f(-ts / tau); }

static int params_ok(const tcf_vqf_params_t *p) {
  const float pos[] = {p->fs, p->max_dt, p->tau_acc, p->rest_filter_tau, p->bias_sigma_init,
                       p->bias_forgetting_time, p->bias_sigma_motion, p->bias_sigma_rest, p->mag_rejection_factor};
  const float nonneg[] = {p->tau_mag, p->bias_clip, p->bias_vertical_forgetting_factor, p->rest_min_t,
                          p->rest_th_gyr, p->rest_th_acc, p->mag_current_tau, p->mag_ref_tau, p->mag_norm_th,
                          p->mag_dip_th, p->mag_new_time, p->mag_new_first_time, p->mag_new_min_gyr,
                          p->mag_min_undisturbed_time, p->mag_max_rejection_time};
  size_t i;
  for (i = 0; i < sizeof pos / sizeof pos[0]; ++i)
    if (!(pos[i] > 0.0f && isfinite(pos[i]))) return 0;
  for (i = 0; i < sizeof nonneg / sizeof nonneg[0]; ++i)
    if (!(nonneg[i] >= 0.0f && isfinite(nonneg[i]))) return 0;
  return 1.0f / p->fs <= p->max_dt;
}

int tcf_vqf_init(tcf_vqf_t *f, const tcf_vqf_params_t *p) {
  tcf_vqf_coef_t *c = &f->c;
  float ts, p_motion, p_rest, v, ffv;
  if (p == NULL || !params_ok(p)) return -1;
  ts = 1.0f / p->fs;
  c->ts = ts;
  c->inv_ts = p->fs;
  c->max_dt = p->max_dt;
  c->use_mag = p->use_mag ? 1u : 0u;
  c->motion_bias = p->motion_bias_est_enabled ? 1u : 0u;
  c->rest_bias = p->rest_bias_est_enabled ? 1u : 0u;
  c->mag_rejection = p->mag_dist_rejection_enabled ? 1u : 0u;
  c->tau_acc = p->tau_acc;
  c->acc_lp = lp_coef(p->tau_acc, ts);
  c->tau_mag = p->tau_mag;
  c->k_mag = gain_from_tau(p->tau_mag, ts);
  /* (B5): variances in (rad/s)^2; W = sigma^4 / V + sigma^2 */
  p_motion = (p->bias_sigma_motion * TCF_VQF_DEG) * (p->bias_sigma_motion * TCF_VQF_DEG);
  p_rest = (p->bias_sigma_rest * TCF_VQF_DEG) * (p->bias_sigma_rest * TCF_VQF_DEG);
  v = (TCF_VQF_BIAS_DRIFT * TCF_VQF_DEG) * (TCF_VQF_BIAS_DRIFT * TCF_VQF_DEG) * ts / p->bias_forgetting_time;
  c->bias_p0 = (p->bias_sigma_init * TCF_VQF_DEG) * (p->bias_sigma_init * TCF_VQF_DEG);
  c->bias_v = v;
  c->bias_w_motion = p_motion * (p_motion / v) + p_motion;
  ffv = p->bias_vertical_forgetting_factor > 1e-10f ? p->bias_vertical_forgetting_factor : 1e-10f;
  c->bias_w_vertical = c->bias_w_motion / ffv;
  c->bias_w_rest = p_rest * (p_rest / v) + p_rest;
  c->bias_clip = p->bias_clip * TCF_VQF_DEG;
  c->rest_tau = p->rest_filter_tau;
  c->rest_lp = lp_coef(p->rest_filter_tau, ts);
  c->rest_th_gyr_sq = (p->rest_th_gyr * TCF_VQF_DEG) * (p->rest_th_gyr * TCF_VQF_DEG);
  c->rest_th_acc_sq = p->rest_th_acc * p->rest_th_acc;
  c->rest_min_t = p->rest_min_t;
  c->mag_cur_tau = p->mag_current_tau;
  if (p->mag_current_tau > 0.0f) {
    c->mag_lp = lp_coef(p->mag_current_tau, ts);
  } else {
    c->mag_lp.k = 0.0f;
    c->mag_lp.one_minus_decay = 0.0f;
  }
  c->k_mag_ref = gain_from_tau(p->mag_ref_tau, ts);
  c->mag_norm_th = p->mag_norm_th;
  c->mag_dip_th = p->mag_dip_th * TCF_VQF_DEG;
  c->mag_new_time = p->mag_new_time;
  c->mag_new_first_time = p->mag_new_first_time;
  c->mag_new_min_gyr_sq = (p->mag_new_min_gyr * TCF_VQF_DEG) * (p->mag_new_min_gyr * TCF_VQF_DEG);
  c->mag_min_undisturbed_t = p->mag_min_undisturbed_time;
  c->mag_max_rejection_t = p->mag_max_rejection_time;
  c->mag_rejection_factor = p->mag_rejection_factor;
  tcf_vqf_reset(f);
  return 0;
}

/* VQFCoreFilter.reset: identity q_gyr, q_acc; delta = 0; bias 0 with P = P0 I; field taken as
   disturbed with no reference yet; every low-pass back in its averaging phase. */
void tcf_vqf_reset(tcf_vqf_t *f) {
  tcf_vqf_coef_t c = f->c;
  unsigned char *b = (unsigned char *)f;
  size_t i;
  for (i = 0; i < sizeof *f; ++i) b[i] = 0u;  /* all-bits-zero is 0.0f for IEEE floats */
  f->c = c;
  f->quat[0] = 1.0f;
  f->q_gyr[0] = 1.0f;
  f->q_acc[0] = 1.0f;
  f->bias_p[0] = f->bias_p[4] = f->bias_p[8] = c.bias_p0;
  f->mag_dist_detected = 1u;
  f->mag_reject_t = c.mag_max_rejection_t;
  f->mag_cand_norm = -1.0f;
  f->k_mag_init = 1.0f;
}

void tcf_vqf_base_mod(const tcf_vqf_t *f, tcf_vqf_mod_t *m) {
  m->acc_lp = f->c.acc_lp;
  m->k_mag = f->c.k_mag;
  m->bias_w_motion = f->c.bias_w_motion;
  m->bias_w_vertical = f->c.bias_w_vertical;
  m->rest_th_gyr_sq = f->c.rest_th_gyr_sq;
  m->rest_th_acc_sq = f->c.rest_th_acc_sq;
}

tcf_vqf_lp_coef_t tcf_vqf_acc_lp_from(const tcf_vqf_t *f, float tau_acc) { return lp_coef(tau_acc, f->c.ts); }

float tcf_vqf_k_mag_from(const tcf_vqf_t *f, float tau_mag) { return gain_from_tau(tau_mag, f->c.ts); }

/* modulate, step 3 (filters/vqf_toggling.py): the coefficients of blended time constants */
void tcf_vqf_mod_from(const tcf_vqf_t *f, float tau_acc, float tau_mag, float sigma_motion, tcf_vqf_mod_t *m) {
  const tcf_vqf_coef_t *c = &f->c;
  float s2 = sigma_motion * sigma_motion;
  m->acc_lp = tcf_vqf_acc_lp_from(f, tau_acc);
  m->k_mag = tcf_vqf_k_mag_from(f, tau_mag);
  m->bias_w_motion = s2 * (s2 / c->bias_v) + s2;  /* (B5), bias_noise_w */
  m->bias_w_vertical = m->bias_w_motion * (c->bias_w_vertical / c->bias_w_motion);
  m->rest_th_gyr_sq = c->rest_th_gyr_sq;
  m->rest_th_acc_sq = c->rest_th_acc_sq;
}

/* ------------------------------------------------------------------ the step
 * One sample as VQF (dlaidig/vqf updateGyr, updateAcc, updateMag) and the Python core
 * (filters/vqf_core.py core_update: update_gyr, update_acc, update_bias, update_mag,
 * update_output): gyroscope, then accelerometer (with the bias estimation), then magnetometer,
 * then the output. *m holds the coefficients a learned filter modulates. */

/* update_gyr: a valid gyro sample [rad/s] over dt [s]: rest detection (R1), then Alg. 1 l. 8 */
static void tcf_vqf_update_gyr(tcf_vqf_t *f, const tcf_vqf_mod_t *m, const float gyr[3], float dt) {
  const tcf_vqf_coef_t *p = &f->c;
  float rv[3], dq[4];
  int ready, i;
  if (p->rest_bias || p->mag_rejection) {  /* (R1); the rest low-pass also feeds (M3) */
    float g[3], d2 = 0.0f;
    ready = lp_begin(&f->rest_gyr_bank_head);
    for (i = 0; i < 3; ++i) g[i] = lp_step(f->rest_gyr_bank[i], gyr[i], ready, f->rest_gyr_bank_head.n, &p->rest_lp);
    lp_end(&f->rest_gyr_bank_head, f->rest_gyr_bank, 3, ready, p->rest_tau, p->ts);
    for (i = 0; i < 3; ++i) {
      float d = gyr[i] - g[i];
      f->rest_gyr_lp[i] = g[i];
      d2 += d * d;
    }
    if (d2 >= m->rest_th_gyr_sq || fabsf(g[0]) > p->bias_clip || fabsf(g[1]) > p->bias_clip ||
        fabsf(g[2]) > p->bias_clip) {
      f->rest_t = 0.0f;
      f->rest_detected = 0u;
    } else {
      f->rest_t += p->ts;
      if (f->rest_t >= p->rest_min_t) f->rest_detected = 1u;
    }
  }
  /* Alg. 1 l. 8: strapdown integration of the bias-corrected rate over the actual dt */
  for (i = 0; i < 3; ++i) rv[i] = (gyr[i] - f->bias[i]) * dt;
  tcf_q_from_rotvec(rv, dq);
  tcf_q_mul(f->q_gyr, dq, f->q_gyr);
  tcf_q_unit(f->q_gyr);
}

/* update_acc: a valid accelerometer sample [m/s^2]: rest detection (R2), then the inclination
   correction (Alg. 1 l. 9-14). Returns 1 when q_acc was corrected, with *ax, *ay the normalised
   low-passed acceleration in the 6D earth frame (l. 12) that the bias estimation (B3) uses. */
static int tcf_vqf_update_acc(tcf_vqf_t *f, const tcf_vqf_mod_t *m, const float acc[3], float *ax, float *ay) {
  const tcf_vqf_coef_t *p = &f->c;
  float ai[3], fl[3], ae[3], na, rn, az, qw2, qw, corr[4];
  int ready, i;
  if (p->rest_bias) {  /* (R2) */
    float l[3], d2 = 0.0f;
    ready = lp_begin(&f->rest_acc_bank_head);
    for (i = 0; i < 3; ++i) l[i] = lp_step(f->rest_acc_bank[i], acc[i], ready, f->rest_acc_bank_head.n, &p->rest_lp);
    lp_end(&f->rest_acc_bank_head, f->rest_acc_bank, 3, ready, p->rest_tau, p->ts);
    for (i = 0; i < 3; ++i) d2 += (acc[i] - l[i]) * (acc[i] - l[i]);
    if (d2 >= m->rest_th_acc_sq) {
      f->rest_t = 0.0f;
      f->rest_detected = 0u;
    }
  }
  tcf_vqf_rotate(f->q_gyr, acc, ai);  /* Alg. 1 l. 9 */
  ready = lp_begin(&f->acc_lp_head);  /* Alg. 1 l. 10 */
  for (i = 0; i < 3; ++i) fl[i] = lp_step(f->acc_lp[i], ai[i], ready, f->acc_lp_head.n, &m->acc_lp);
  lp_end(&f->acc_lp_head, f->acc_lp, 3, ready, p->tau_acc, p->ts);
  tcf_vqf_rotate(f->q_acc, fl, ae);  /* Alg. 1 l. 11 */
  na = sqrtf(ae[0] * ae[0] + ae[1] * ae[1] + ae[2] * ae[2]);
  if (!(na > 0.0f && na < INFINITY)) return 0;
  rn = 1.0f / na;
  *ax = ae[0] * rn; *ay = ae[1] * rn; az = ae[2] * rn;  /* Alg. 1 l. 12 */
  qw2 = 0.5f * (az + 1.0f);
  qw = sqrtf(qw2 > 0.0f ? qw2 : 0.0f);  /* Alg. 1 l. 13 */
  if (qw > 1e-6f) {  /* Alg. 1 l. 14 */
    float h = 0.5f / qw;
    corr[0] = qw; corr[1] = *ay * h; corr[2] = -*ax * h; corr[3] = 0.0f;
  } else {  /* a points down: the 180 deg correction about any horizontal axis */
    corr[0] = 0.0f; corr[1] = 1.0f; corr[2] = 0.0f; corr[3] = 0.0f;
  }
  tcf_q_mul(corr, f->q_acc, f->q_acc);
  tcf_q_unit(f->q_acc);
  f->initialized = 1u;
  return 1;
}

/* update_bias: gyro bias estimation (B1)-(B5) after an inclination correction with the
   normalised low-passed acceleration (ax, ay) in the 6D earth frame; q6 = q_6D (Alg. 1 l. 15) */
static void tcf_vqf_update_bias(tcf_vqf_t *f, const tcf_vqf_mod_t *m, float ax, float ay, float q6[4]) {
  const tcf_vqf_coef_t *p = &f->c;
  float b0 = f->bias[0], b1 = f->bias[1], b2 = f->bias[2], r[9], rl[9], rb[2], P[9], s[9];
  int ready, i;
  tcf_q_mul(f->q_acc, f->q_gyr, q6);  /* Alg. 1 l. 15 */
  q_matrix(q6, r);  /* R(q_6D) */
  rb[0] = r[0] * b0 + r[1] * b1 + r[2] * b2;
  rb[1] = r[3] * b0 + r[4] * b1 + r[5] * b2;
  ready = lp_begin(&f->bias_r_lp_head);  /* R_bar = LP_2(R; tau_acc) */
  for (i = 0; i < 9; ++i) rl[i] = lp_step(f->bias_r_lp[i], r[i], ready, f->bias_r_lp_head.n, &m->acc_lp);
  lp_end(&f->bias_r_lp_head, f->bias_r_lp, 9, ready, p->tau_acc, p->ts);
  ready = lp_begin(&f->bias_rb_lp_head);  /* (R b)_bar = LP_2(R b; tau_acc), x and y */
  for (i = 0; i < 2; ++i) rb[i] = lp_step(f->bias_rb_lp[i], rb[i], ready, f->bias_rb_lp_head.n, &m->acc_lp);
  lp_end(&f->bias_rb_lp_head, f->bias_rb_lp, 2, ready, p->tau_acc, p->ts);
  bias_predict(f);  /* (B1) */
  for (i = 0; i < 9; ++i) P[i] = f->bias_p[i];
  if (p->rest_bias && f->rest_detected) {  /* (B2): y = rest LP of the gyro, M = I, P M^T = P */
    float w = p->bias_w_rest;
    for (i = 0; i < 9; ++i) s[i] = P[i];
    s[0] += w; s[4] += w; s[8] += w;
    bias_update(f, f->rest_gyr_lp[0] - b0, f->rest_gyr_lp[1] - b1, f->rest_gyr_lp[2] - b2, P, s);
  } else if (p->motion_bias) {  /* (B3): M = R_bar */
    float ex = -ay * p->inv_ts + rb[0] - (rl[0] * b0 + rl[1] * b1 + rl[2] * b2);
    float ey = ax * p->inv_ts + rb[1] - (rl[3] * b0 + rl[4] * b1 + rl[5] * b2);
    float ez = -(rl[6] * b0 + rl[7] * b1 + rl[8] * b2);
    float pmt[9];
    m_mmt(P, rl, pmt);  /* P M^T */
    m_mm(rl, pmt, s);   /* M P M^T */
    s[0] += m->bias_w_motion; s[4] += m->bias_w_motion; s[8] += m->bias_w_vertical;
    bias_update(f, ex, ey, ez, pmt, s);
  }
  for (i = 0; i < 3; ++i) f->bias[i] = clipf(f->bias[i], p->bias_clip);
}

/* _mag_disturbance: magnetic disturbance detection (M1)-(M3) from the field me in the 6D earth frame */
static void tcf_vqf_mag_disturbance(tcf_vqf_t *f, const float me[3]) {
  const tcf_vqf_coef_t *p = &f->c;
  float nrm = sqrtf(me[0] * me[0] + me[1] * me[1] + me[2] * me[2]);  /* (M1) */
  float dip = -asinf(clipf(me[2] / nrm, 1.0f)), ref_n, cand_n;
  if (p->mag_cur_tau > 0.0f) {
    int ready = lp_begin(&f->mag_nd_lp_head);
    nrm = lp_step(f->mag_nd_lp[0], nrm, ready, f->mag_nd_lp_head.n, &p->mag_lp);
    dip = lp_step(f->mag_nd_lp[1], dip, ready, f->mag_nd_lp_head.n, &p->mag_lp);
    lp_end(&f->mag_nd_lp_head, f->mag_nd_lp, 2, ready, p->mag_cur_tau, p->ts);
  }
  ref_n = f->mag_ref_norm;  /* (M2) */
  if (fabsf(nrm - ref_n) < p->mag_norm_th * ref_n && fabsf(dip - f->mag_ref_dip) < p->mag_dip_th) {
    f->mag_undisturbed_t += p->ts;
    if (f->mag_undisturbed_t >= p->mag_min_undisturbed_t) {
      f->mag_dist_detected = 0u;
      f->mag_ref_norm += p->k_mag_ref * (nrm - ref_n);
      f->mag_ref_dip += p->k_mag_ref * (dip - f->mag_ref_dip);
    }
  } else {
    f->mag_undisturbed_t = 0.0f;
    f->mag_dist_detected = 1u;
  }
  cand_n = f->mag_cand_norm;  /* (M3) */
  if (fabsf(nrm - cand_n) < p->mag_norm_th * cand_n && fabsf(dip - f->mag_cand_dip) < p->mag_dip_th) {
    const float *g = f->rest_gyr_lp;
    if (g[0] * g[0] + g[1] * g[1] + g[2] * g[2] >= p->mag_new_min_gyr_sq) f->mag_cand_t += p->ts;
    f->mag_cand_norm += p->k_mag_ref * (nrm - cand_n);
    f->mag_cand_dip += p->k_mag_ref * (dip - f->mag_cand_dip);
    if (f->mag_dist_detected && (f->mag_cand_t >= p->mag_new_time ||
                        (f->mag_ref_norm == 0.0f && f->mag_cand_t >= p->mag_new_first_time))) {
      f->mag_ref_norm = f->mag_cand_norm;
      f->mag_ref_dip = f->mag_cand_dip;
      f->mag_dist_detected = 0u;
      f->mag_undisturbed_t = p->mag_min_undisturbed_t;
    }
  } else {
    f->mag_cand_t = 0.0f;
    f->mag_cand_norm = nrm;
    f->mag_cand_dip = dip;
  }
}

/* update_mag: a valid magnetometer sample (9D) with the current q_6D: disturbance detection
   (M1)-(M3), then the heading correction (Alg. 1 l. 17-19, (M4), (M5)). Returns the gain used. */
static float tcf_vqf_update_mag(tcf_vqf_t *f, const tcf_vqf_mod_t *m, const float mag[3], const float q6[4]) {
  const tcf_vqf_coef_t *p = &f->c;
  float me[3], dis, kinit, k;
  tcf_vqf_rotate(q6, mag, me);  /* Alg. 1 l. 17 */
  if (p->mag_rejection) tcf_vqf_mag_disturbance(f, me);
  dis = wrapf(atan2f(me[0], me[1]) - f->delta);  /* Alg. 1 l. 18-19 */
  k = m->k_mag;
  if (p->mag_rejection) {  /* (M4) */
    if (f->mag_dist_detected) {
      if (f->mag_reject_t <= p->mag_max_rejection_t) {
        f->mag_reject_t += p->ts;
        k = 0.0f;
      } else {
        k = k / p->mag_rejection_factor;
      }
    } else {
      float t = f->mag_reject_t - p->mag_rejection_factor * p->ts;
      f->mag_reject_t = t > 0.0f ? t : 0.0f;
    }
  }
  kinit = f->k_mag_init;  /* (M5): k >= 1/N for the N-th sample while 1/N tau_mag >= Ts */
  if (kinit != 0.0f) {
    if (kinit > k) k = kinit;
    kinit = kinit / (kinit + 1.0f);
    f->k_mag_init = kinit * p->tau_mag < p->ts ? 0.0f : kinit;
  }
  f->delta = wrapf(f->delta + k * dis);  /* Alg. 1 l. 19 */
  return k;
}

/* update_output: the output orientation, Alg. 1 l. 21 in 9D, q_6D in 6D */
static void tcf_vqf_update_output(tcf_vqf_t *f, const float q6[4]) {
  int i;
  if (f->c.use_mag) {  /* Alg. 1 l. 21: q_9D = [cos delta/2, 0, 0, sin delta/2] (x) q_6D */
    float h = 0.5f * f->delta, c = cosf(h), s = sinf(h);
    f->quat[0] = c * q6[0] - s * q6[3];
    f->quat[1] = c * q6[1] - s * q6[2];
    f->quat[2] = c * q6[2] + s * q6[1];
    f->quat[3] = c * q6[3] + s * q6[0];
  } else {
    for (i = 0; i < 4; ++i) f->quat[i] = q6[i];
  }
}

/* core_update: vqf_core_step with the modulated coefficients *m. Bad samples (tcf_vqf.h): an
   invalid gyro sample or dt skips update_gyr, an invalid acc sample update_acc and update_bias,
   an invalid or missing mag sample update_mag. */
void tcf_vqf_update_mod(tcf_vqf_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt,
                        const tcf_vqf_mod_t *m) {
  const tcf_vqf_coef_t *p = &f->c;
  float q6[4], ax, ay, k = 0.0f;
  int have_q6 = 0;  /* q_6D is computed once per sample, in the bias estimation when it runs */
  if (tcf_gyro_ok(gyr) && isfinite(dt) && dt > 0.0f && dt <= p->max_dt) tcf_vqf_update_gyr(f, m, gyr, dt);
  if (acc != NULL && tcf_vec_ok(acc) && tcf_vqf_update_acc(f, m, acc, &ax, &ay) && (p->rest_bias || p->motion_bias)) {
    tcf_vqf_update_bias(f, m, ax, ay, q6);
    have_q6 = 1;
  }
  if (!have_q6) tcf_q_mul(f->q_acc, f->q_gyr, q6);  /* Alg. 1 l. 15 */
  if (p->use_mag && mag != NULL && tcf_vec_ok(mag)) k = tcf_vqf_update_mag(f, m, mag, q6);
  f->k_mag_last = k;
  tcf_vqf_update_output(f, q6);
}

/* ------------------------------------------------------------------ getters */

void tcf_vqf_quat(const tcf_vqf_t *f, float q[4]) {
  q[0] = f->quat[0]; q[1] = f->quat[1]; q[2] = f->quat[2]; q[3] = f->quat[3];
}

int tcf_vqf_rest(const tcf_vqf_t *f) { return f->rest_detected ? 1 : 0; }

int tcf_vqf_mag_disturbed(const tcf_vqf_t *f) { return (f->c.use_mag && f->mag_dist_detected) ? 1 : 0; }

