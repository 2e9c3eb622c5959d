/* tcf_vqf_toggling.c: the VQF core with learned time constants in C99, float32 (API in
 * tcf_vqf_toggling.h). Port of (togglecf/...):
 *   toggling/inloop.py         vqf_toggling_inloop_batch, one sample -> tcf_vqft_update_dt
 *                              (models: tcf_features_push)
 *   filters/vqf_toggling.py    vqf_toggling_step, modulate, reset     -> tcf_vqft_step, tcf_vqft_modulate,
 *                                                                       tcf_vqft_init
 *   filters/prediction.py      blend_trust (the learned VQF's own fallback rule) -> tcf_vqft_blend_trust;
 *                              the shared steps (class_evidence, remove_noise, predicted_disturbance,
 *                              back_off): tcf_prediction.h
 * The core step is tcf_vqf_update_mod (tcf_vqf.c). "step N": the module docstring of
 * filters/vqf_toggling.py.
 */
#include <math.h>
#include <stddef.h>
#include "tcf_vqf_toggling.h"
#include "tcf_vqf_config.h"
#include "tcf_prediction.h"  /* the prediction row as named fields, steps 1, 3, 4 */
#include "tcf_math.h"        /* tcf_q_mul, tcf_vec_ok: step 3b */

#if defined(__FAST_MATH__)
#error "tcf_vqf_toggling.c must not be compiled with -ffast-math: the no-prediction (NaN) tests would be removed"
#endif

#if !defined(TCF_VQFT_FOLLOW) || !defined(TCF_VQFT_MODULATION_TAU)
#error "tcf_config.h must define TCF_VQFT_FOLLOW and TCF_VQFT_MODULATION_TAU (re-export it)"
#endif

#if !defined(TCF_LEARNING_OFF)
#error "tcf_config.h must define TCF_LEARNING_OFF (export it again)"
#endif
#if !defined(TCF_VQFT_MAG_BACKOFF_MEASURED)
#error "tcf_config.h must define TCF_VQFT_MAG_BACKOFF_MEASURED (re-export it)"
#endif

#if !defined(TCF_VQFT_NOISE_ACC) || !defined(TCF_VQFT_NOISE_MAG)
#error "tcf_config.h must define TCF_VQFT_NOISE_ACC and TCF_VQFT_NOISE_MAG (re-export it)"
#endif

typedef char tcf_vqft_bytes_check[(sizeof(tcf_vqft_t) == TCF_VQFT_STATE_BYTES) ? 1 : -1];

/* per-state ln tau_acc [ln s], ln tau_mag [ln s], ln sigma_motion [ln rad/s] (tcf_config.h) */
static const float tcf_ln_tau_acc[TCF_N_CLASSES] = TCF_VQFT_LN_TAU_ACC_INIT;
static const float tcf_ln_tau_mag[TCF_N_CLASSES] = TCF_VQFT_LN_TAU_MAG_INIT;
static const float tcf_ln_sigma[TCF_N_CLASSES] = TCF_VQFT_LN_SIGMA_MOTION_INIT;
/* per-state ln rest thresholds: th_omega [ln rad/s], th_a [ln m/s^2] */
static const float tcf_ln_rest_gyr[TCF_N_CLASSES] = TCF_VQFT_LN_REST_TH_GYR_INIT;
static const float tcf_ln_rest_acc[TCF_N_CLASSES] = TCF_VQFT_LN_REST_TH_ACC_INIT;
/* mag = NULL: the features see zeros (and with TCF_USE_MAG == 0 the core ignores mag) */
static const float tcf_vqft_zeros[3] = {0.0f, 0.0f, 0.0f};

/* a != b, where NaN equals NaN (one entry of _prediction_changed) */
static int tcf_vqft_differ(float a, float b) { return a != b && !(isnan(a) && isnan(b)); }

/* _prediction_changed: the entries of the prediction the modulation depends on differ from the last
   ones (NaN equals NaN): the class probabilities, and eta when the predicted disturbance scales the
   heading gain (step 3) */
static int tcf_vqft_changed(const tcf_vqft_t *f, const tcf_prediction_t *pred) {
  const tcf_prediction_t *last = &f->last_p;
  int s;
  for (s = 0; s < TCF_N_CLASSES; ++s)
    if (tcf_vqft_differ(pred->probabilities[s], last->probabilities[s])) return 1;
  if (TCF_VQFT_MAG_DISTURBANCE_SCALE > 0.0f)
    for (s = 0; s < 3; ++s)
      if (tcf_vqft_differ(pred->eta_acc[s], last->eta_acc[s]) || tcf_vqft_differ(pred->eta_mag[s], last->eta_mag[s]))
        return 1;
  return 0;
}

/* Step 1, the learned VQF's fallback rule (prediction.blend_trust: a blend, unlike the toggling CF's
   hard switch in tcf_filter.c; prediction.py's docstring says why): the trust lambda in [0, 1] of the
   learned values, clip((c - c0) / (1 - c0), 0, 1) with c = top / total; 0 when not valid. */
static float tcf_vqft_blend_trust(int valid, float top, float total) {
  float lam;
  if (!valid) return 0.0f;
  lam = (top / total - TCF_VQFT_CONFIDENCE_FLOOR) / (1.0f - TCF_VQFT_CONFIDENCE_FLOOR);
  return lam < 0.0f ? 0.0f : (lam > 1.0f ? 1.0f : lam);
}

/* modulate, steps 1-3: blend the per-state values with the probabilities, derive the coefficients */
static void tcf_vqft_modulate(tcf_vqft_t *f, const tcf_prediction_t *pred) {
  float total, top, lam;
  float la = TCF_VQFT_LN_TAU_ACC_CORE, lm = TCF_VQFT_LN_TAU_MAG_CORE, ls = TCF_VQFT_LN_SIGMA_MOTION_CORE;
  float lg = TCF_VQFT_LN_REST_TH_GYR_CORE, lc = TCF_VQFT_LN_REST_TH_ACC_CORE;
  int s, valid;
  f->last_p = *pred;
  valid = tcf_class_evidence(pred, &top, &total);
  lam = tcf_vqft_blend_trust(valid, top, total);
  if (valid) {  /* step 2 (lambda = 0 still blends: the core's values times 1, as Python) */
    float ma = 0.0f, mm = 0.0f, msg = 0.0f, mg = 0.0f, mc = 0.0f;
    for (s = 0; s < TCF_N_CLASSES; ++s) {
      float w = pred->probabilities[s] / total;
      ma += w * tcf_ln_tau_acc[s];
      mm += w * tcf_ln_tau_mag[s];
      msg += w * tcf_ln_sigma[s];
      mg += w * tcf_ln_rest_gyr[s];
      mc += w * tcf_ln_rest_acc[s];
    }
    la = lam * ma + (1.0f - lam) * la;
    lm = lam * mm + (1.0f - lam) * lm;
    ls = lam * msg + (1.0f - lam) * ls;
    lg = lam * mg + (1.0f - lam) * lg;
    lc = lam * mc + (1.0f - lam) * lc;
  }
  f->trust_now = lam;
  f->ln_tau_acc_target = la;  /* the targets of tcf_vqft_follow */
  f->ln_tau_mag_target = lm;
  f->mag_disturbance_predicted = 0.0f;
#if TCF_VQFT_FOLLOW
  la = f->ln_tau_acc_now;  /* tau_acc, tau_mag: the followed values (tcf_vqft_follow moves them) */
  lm = f->ln_tau_mag_now;
#endif
  f->tau_acc_now = expf(la);
  f->tau_mag_now = expf(lm);
  tcf_vqf_mod_from(&f->core, f->tau_acc_now, f->tau_mag_now, expf(ls), &f->mod);  /* step 3 */
  f->mod.rest_th_gyr_sq = expf(2.0f * lg);
  f->mod.rest_th_acc_sq = expf(2.0f * lc);
  f->k_mag_now = f->mod.k_mag;
#if TCF_USE_MAG
  if (TCF_VQFT_MAG_DISTURBANCE_SCALE > 0.0f)  /* the predicted disturbance (|eta_m| / sigma_m)^2 (0 for NaN: none) */
    f->mag_disturbance_predicted = tcf_predicted_disturbance(pred, TCF_VQFT_MAG_DISTURBANCE_SCALE);
#endif
}

#if TCF_VQFT_FOLLOW
/* _follow (modulation_tau): ln tau_acc, ln tau_mag one first-order step towards their targets; the
   tau_acc low-pass coefficients recomputed while ln tau_acc moves, k_mag before the back-off
   (tcf_vqft_heading_gain) while ln tau_mag moves (a constant at its target: nothing computed). Without
   the Python filter's snap at 1e-9: in float32 the step stalls within an ulp of the target anyway */
static void tcf_vqft_follow(tcf_vqft_t *f) {
  if (f->ln_tau_acc_now != f->ln_tau_acc_target) {
    f->ln_tau_acc_now += f->modulation_gain * (f->ln_tau_acc_target - f->ln_tau_acc_now);
    f->tau_acc_now = expf(f->ln_tau_acc_now);
    f->mod.acc_lp = tcf_vqf_acc_lp_from(&f->core, f->tau_acc_now);
  }
  if (f->ln_tau_mag_now != f->ln_tau_mag_target) {
    f->ln_tau_mag_now += f->modulation_gain * (f->ln_tau_mag_target - f->ln_tau_mag_now);
    f->tau_mag_now = expf(f->ln_tau_mag_now);
    f->k_mag_now = tcf_vqf_k_mag_from(&f->core, f->tau_mag_now);
  }
}
#endif

#if TCF_USE_MAG
#if TCF_VQFT_MAG_BACKOFF_MEASURED
/* _field_deviation_sq: the disturbance the magnetometer shows [uT^2], the least |m - m_ref|^2 over the
   unknown azimuth: n^2 + n_ref^2 - 2 n n_ref cos(d - d_ref), dip d in the last output's earth frame;
   0 without a reference or for an invalid sample */
static float tcf_vqft_field_deviation_sq(const tcf_vqf_t *c, const float m[3]) {
  float n_ref = c->mag_ref_norm, n2 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2], n, me[3], mz, d2;
  if (!(n_ref > 0.0f && n2 > 0.0f && n2 < INFINITY)) return 0.0f;
  n = sqrtf(n2);
  tcf_vqf_rotate(c->quat, m, me);
  mz = me[2] / n;
  d2 = n2 + n_ref * n_ref - 2.0f * n * n_ref * cosf(-asinf(mz < -1.0f ? -1.0f : (mz > 1.0f ? 1.0f : mz))
                                                       - c->mag_ref_dip);
  return d2 > 0.0f ? d2 : 0.0f;
}
#endif

/* _heading_gain, every sample: k_mag / (1 + e), e the predicted disturbance, at most the core's
   rejection factor - 1 (the learned back-off slows the heading correction no more than the core's
   own), with TCF_VQFT_MAG_BACKOFF_MEASURED at most the one the magnetometer shows instead; then the
   larger of that and step 3b's e_f, itself at most the rejection factor - 1 */
static void tcf_vqft_heading_gain(tcf_vqft_t *f, const float mag[3]) {
  float e = f->mag_disturbance_predicted, e_f = f->field_change_disturbance;
  if (e > 0.0f) {
#if TCF_VQFT_MAG_BACKOFF_MEASURED
    float em = tcf_vqft_field_deviation_sq(&f->core, mag)
               / (TCF_VQFT_MAG_DISTURBANCE_SCALE * TCF_VQFT_MAG_DISTURBANCE_SCALE);
#else
    float em = f->core.c.mag_rejection_factor - 1.0f;
    (void)mag;  /* only the measured law reads the field */
    if (em < 0.0f) em = 0.0f;
#endif
    if (em < e) e = em;
  }
  if (e_f > 0.0f) {
    float cap = f->core.c.mag_rejection_factor - 1.0f;
    if (cap < 0.0f) cap = 0.0f;
    if (e_f > cap) e_f = cap;
    if (e_f > e) e = e_f;
  }
  f->mod.k_mag = tcf_back_off(f->k_mag_now, e);
}

/* _field_change (step 3b), after the core step: the field in the 6D earth frame against its low-pass;
   e_f once the low-pass has seen field_change_tau of valid samples; an invalid sample changes nothing */
static void tcf_vqft_field_change(tcf_vqft_t *f, const float mag[3]) {
  float q6[4], me[3], d[3];
  int i;
  if (!tcf_vec_ok(mag)) return;
  tcf_q_mul(f->core.q_acc, f->core.q_gyr, q6);
  tcf_vqf_rotate(q6, mag, me);
  if (f->field_lp_t < 0.0f) {  /* the first valid sample starts the low-pass */
    for (i = 0; i < 3; ++i) f->field_lp[i] = me[i];
    f->field_lp_t = 0.0f;
    return;
  }
  for (i = 0; i < 3; ++i) d[i] = me[i] - f->field_lp[i];
  f->field_lp_t += f->core.c.ts;
  if (f->field_lp_t >= TCF_VQFT_FIELD_CHANGE_TAU - 0.5f * f->core.c.ts)  /* half a sample, as Python */
    f->field_change_disturbance = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
                                  / (TCF_VQFT_FIELD_CHANGE_SCALE * TCF_VQFT_FIELD_CHANGE_SCALE);
  for (i = 0; i < 3; ++i) f->field_lp[i] += f->field_change_gain * d[i];
}
#endif

/* vqf_toggling_step with the held prediction f->feat.pred */
static void tcf_vqft_step(tcf_vqft_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt) {
  tcf_prediction_t pred;
#if TCF_VQFT_NOISE_ACC || TCF_VQFT_NOISE_MAG
  float a_d[3], m_d[3];
#endif
  tcf_prediction_from_row(f->feat.pred, &pred);
  if (tcf_vqft_changed(f, &pred)) tcf_vqft_modulate(f, &pred);
#if TCF_VQFT_FOLLOW
  tcf_vqft_follow(f);
#endif
#if TCF_USE_MAG
  if (TCF_VQFT_FOLLOW || TCF_VQFT_MAG_DISTURBANCE_SCALE > 0.0f || TCF_VQFT_FIELD_CHANGE_SCALE > 0.0f)
    tcf_vqft_heading_gain(f, mag);
#endif
#if TCF_VQFT_NOISE_ACC || TCF_VQFT_NOISE_MAG
  /* step 4, the learned VQF's rule: whenever eta is finite, whatever the probabilities; a sensor whose
     weight is 0 keeps its sample as is (a - 0 eta = a) */
  (void)tcf_remove_noise(&pred, acc, mag, TCF_VQFT_NOISE_WEIGHT_ACC, TCF_VQFT_NOISE_WEIGHT_MAG, 1, a_d, m_d);
  if (TCF_VQFT_NOISE_ACC) acc = a_d;
  if (TCF_VQFT_NOISE_MAG) mag = m_d;
#endif
  tcf_vqf_update_mod(&f->core, gyr, acc, mag, dt, &f->mod);  /* step 5 */
#if TCF_USE_MAG
  if (TCF_VQFT_FIELD_CHANGE_SCALE > 0.0f) tcf_vqft_field_change(f, mag);  /* step 3b, for the next sample */
#endif
}

int tcf_vqft_init(tcf_vqft_t *f, float fs) {
  static const tcf_vqf_params_t settings = TCF_VQF_PARAMS_INIT;  /* physical: rate-free */
  tcf_vqf_params_t p = settings;
  tcf_features_rate_t r;
  float nan_row[TCF_N_PRED];
  int s = tcf_features_rate(fs, &r);
  if (s != TCF_OK) return s;  /* checks fs before the core sees it */
  p.fs = fs;
  if (tcf_vqf_init(&f->core, &p) != 0) return TCF_ERR_SETTINGS;
  tcf_features_init(&f->feat, fs);  /* TCF_OK: the same checks as tcf_features_rate */
  tcf_vqf_base_mod(&f->core, &f->mod);  /* no prediction seen yet: the core's coefficients */
  for (s = 0; s < TCF_N_PRED; ++s) nan_row[s] = NAN;
  tcf_prediction_from_row(nan_row, &f->last_p);  /* none seen yet */
  f->tau_acc_now = p.tau_acc;
  f->tau_mag_now = p.tau_mag;
  f->trust_now = 0.0f;
  f->ln_tau_acc_target = f->ln_tau_acc_now = TCF_VQFT_LN_TAU_ACC_CORE;
  f->ln_tau_mag_target = f->ln_tau_mag_now = TCF_VQFT_LN_TAU_MAG_CORE;
  f->mag_disturbance_predicted = 0.0f;
  f->k_mag_now = f->mod.k_mag;
  /* gain_from_tau(modulation_tau, Ts) of the Python filter; -expm1f: exact for Ts << tau */
  f->modulation_gain = TCF_VQFT_MODULATION_TAU > 0.0f ? -expm1f(-f->core.c.ts / TCF_VQFT_MODULATION_TAU) : 1.0f;
  f->field_lp[0] = f->field_lp[1] = f->field_lp[2] = 0.0f;
  f->field_lp_t = -1.0f;  /* step 3b: no valid field seen yet */
  f->field_change_disturbance = 0.0f;
  f->field_change_gain = -expm1f(-f->core.c.ts / TCF_VQFT_FIELD_CHANGE_TAU);
  return TCF_OK;
}

void tcf_vqft_update_dt(tcf_vqft_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt) {
  if (mag == NULL) mag = tcf_vqft_zeros;
#if TCF_LEARNING_OFF
  /* every learned value equals the core's: the core alone at its own coefficients (f->mod stays
     tcf_vqf_base_mod), as LearnedVQF; no features pushed, no trees walked */
  tcf_vqf_update_mod(&f->core, gyr, acc, mag, dt, &f->mod);
#else
  tcf_features_push(&f->feat, gyr, acc, mag);
  tcf_vqft_step(f, gyr, acc, mag, dt);
#endif
}

void tcf_vqft_update(tcf_vqft_t *f, const float gyr[3], const float acc[3], const float mag[3]) {
  tcf_vqft_update_dt(f, gyr, acc, mag, f->core.c.ts);
}

void tcf_vqft_update_pred(tcf_vqft_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt,
                          const float pred[TCF_N_PRED]) {
  int k;
  for (k = 0; k < TCF_N_PRED; ++k) f->feat.pred[k] = pred[k];
  tcf_vqft_step(f, gyr, acc, mag == NULL ? tcf_vqft_zeros : mag, dt);
}

void tcf_vqft_quat(const tcf_vqft_t *f, float q[4]) { tcf_vqf_quat(&f->core, q); }

int tcf_vqft_prediction(const tcf_vqft_t *f, float pred[TCF_N_PRED]) {
  int k;
  for (k = 0; k < TCF_N_PRED; ++k) pred[k] = f->feat.pred[k];
  return isfinite(f->feat.pred[0]) ? 1 : 0;
}
