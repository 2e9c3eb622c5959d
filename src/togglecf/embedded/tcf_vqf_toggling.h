/* tcf_vqf_toggling.h: the VQF core with learned, motion-dependent time constants of togglecf in
 * C99, float32 (port of togglecf.toggling.inloop.ModelVQFTogglingFilter: the models in the loop
 * + togglecf.filters.vqf_toggling.vqf_toggling_step).
 *
 * Per sample: the models (tcf_features.{h,c}, shared with the toggling CF export: streaming
 * features, out-of-range check, the tree ensemble tcf_forest.c every TCF_HOP samples, held
 * prediction pred = [p_1..p_S, eta_a xyz, eta_m xyz]); when the class probabilities change,
 * steps 1-3 of filters/vqf_toggling.py:
 *   confidence      c = max_s p_s / sum_s p_s;  lambda = clip((c - c0) / (1 - c0), 0, 1)
 *   time constants  ln tau = lambda sum_s (p_s / sum p) ln tau_s + (1 - lambda) ln tau_core
 *                   for tau_acc, tau_mag and sigma_motion (per-state values TCF_VQFT_LN_*_INIT)
 *   coefficients    tcf_vqf_mod_from (the core's formulas, float32)
 * (with modulation_tau > 0, TCF_VQFT_FOLLOW: ln tau_acc and ln tau_mag follow these values
 * with a first-order low-pass, gain TCF_VQFT_MODULATION_GAIN per sample)
 * with sigma_f > 0 (TCF_VQFT_FIELD_CHANGE_SCALE, 9D), step 3b: the heading gain also backs off on
 * how much the field changed in the 6D earth frame, e_f = min((|m_E - LP(m_E)| / sigma_f)^2,
 * f_reject - 1), m_E = R(q_acc q_gyr) m, LP a first-order low-pass of TCF_VQFT_FIELD_CHANGE_TAU,
 * updated after each core step (filters/vqf_toggling.py, _field_change);
 * then step 4 (noise removal a - w_a eta_a, m - w_m eta_m) and step 5, the VQF core
 * (tcf_vqf.{h,c}, tcf_vqf_update_mod) with those coefficients. No prediction (NaN: before the
 * first full window, or the window was out of the training range) -> the core's own settings.
 * TCF_LEARNING_OFF 1 (tcf_config.h: every learned value of the exported mode equals the core's):
 * tcf_vqft_update / tcf_vqft_update_dt run the core alone (no features, no trees; the API and
 * tcf_vqft_t stay the same, the prediction stays NaN).
 *
 * Conventions (as togglecf): quaternion [w, x, y, z], Hamilton product, sensor-to-earth, earth
 * frame ENU. Units: gyr rad/s, acc m/s^2, mag uT.
 *
 * Rate at init: tcf_vqft_init(&f, fs) takes the sampling rate fs [Hz] (up to TCF_MAX_FS of
 * tcf_config.h) and derives every per-sample constant from it and the settings, which are
 * physical (time constants in seconds), as the Python filter's _coefficients at that rate:
 * the core's (tcf_vqf_init: Butterworth low-passes of tau_acc, the rest and field filters,
 * 1 - exp(-Ts/tau) gains, bias noises), the learned modulation's (tcf_vqf_mod_from at each
 * probability change, with Ts = 1/fs), the followed modulation's gain 1 - exp(-Ts /
 * modulation_tau), and the features' window, hop and EMA gains (tcf_features.h). Nothing is
 * fixed to the training rate: one build runs a 100, 200 or 400 Hz IMU.
 * Per-sample dt: tcf_vqft_update_dt(&f, gyr, acc, mag, dt) integrates the gyro over the actual
 * dt [s] (as VQFTogglingFilter.update_batch(..., dt=...)); everything else runs at the nominal
 * rate of init, as in VQF and the Python filter: the low-pass filters and gains, the rest and
 * magnetic timers, and the features (which count samples). A dt that is not finite, <= 0 or >
 * max_dt (0.1 s) skips the gyro integration of that sample (lost samples).
 *
 * Memory: all state in one tcf_vqft_t (fixed size, TCF_VQFT_STATE_BYTES; no heap, no globals
 * written; reentrant: one per sensor). Its feature ring is sized for TCF_MAX_FS.
 *
 * Bad samples: the policies of tcf_features.h (features) and tcf_vqf.h (core).
 * Do not compile with -ffast-math (the sources refuse it).
 */
#ifndef TCF_VQF_TOGGLING_H
#define TCF_VQF_TOGGLING_H

#include <stdint.h>
#include "tcf_features.h"
#include "tcf_vqf.h"

#ifdef __cplusplus
extern "C" {
#endif

/* The state: the names of VQFTogglingFilter's state record (filters.vqf_toggling.STATE_FIELDS) and
   coefficients (VQFTogglingCoefficients); tests/test_names.py compares them. */
typedef struct tcf_vqft {
  tcf_vqf_t core;          /* the VQF core: its state and its settings' coefficients */
  tcf_features_t feat;     /* feature window and held prediction (the models, toggling.inloop) */
  tcf_vqf_mod_t mod;       /* coefficients in use (steps 1-3 of the last prediction change) */
  tcf_prediction_t last_p;  /* the prediction the modulation was made from (NaN: none) */
  float tau_acc_now;        /* tau_acc in use [s] (diagnostic) */
  float tau_mag_now;        /* tau_mag in use [s] (diagnostic) */
  float trust_now;          /* lambda in use, in [0, 1] (diagnostic) */
  float ln_tau_acc_target;  /* ln tau_acc [ln s] of the last modulation (step 2) */
  float ln_tau_mag_target;  /* ln tau_mag [ln s] of the last modulation */
  float ln_tau_acc_now;     /* ln tau_acc [ln s] followed towards its target (modulation_tau) */
  float ln_tau_mag_now;     /* ln tau_mag [ln s] likewise */
  float mag_disturbance_predicted;  /* the predicted disturbance (|eta_m| / sigma_m)^2 (step 3) */
  float k_mag_now;          /* 1 - exp(-Ts / tau_mag_now): k_mag before the back-off */
  float modulation_gain;    /* 1 - exp(-Ts / modulation_tau) at the init rate (1: at once) */
  float field_lp[3];        /* step 3b: the low-passed field in the 6D earth frame [uT] */
  float field_lp_t;         /* step 3b: time [s] of valid samples the low-pass has seen (-1: none yet) */
  float field_change_disturbance;  /* step 3b: e_f = (|m_E - LP| / sigma_f)^2 */
  float field_change_gain;  /* 1 - exp(-Ts / field_change_tau) at the init rate */
} tcf_vqft_t;

/* sizeof(tcf_vqft_t): 4-byte members only, no padding (checked at compile time): the core,
   the features, 7 modulation coefficients, the last prediction (S + 6), 3 diagnostics, 6 of the
   followed modulation and the back-off, its gain, 5 of the field change and its gain */
#define TCF_VQFT_STATE_BYTES (TCF_VQF_STATE_BYTES + TCF_FEATURES_STATE_BYTES + 4 * (29 + TCF_N_CLASSES))

/* Reset at the sampling rate fs [Hz]: every per-sample coefficient derived from fs and the
   settings (see "Rate at init"), the core's initial state, empty window, no prediction.
   Returns TCF_OK (0), or (f untouched) TCF_ERR_RATE (fs not finite and > 0), TCF_ERR_RATE_MAX
   (fs > TCF_MAX_FS) or TCF_ERR_SETTINGS (1/fs > max_dt, i.e. fs < 10 Hz, or the core refuses
   the settings of tcf_vqf_config.h). */
int tcf_vqft_init(tcf_vqft_t *f, float fs);

/* One sample at the init rate (dt = 1/fs): gyr [rad/s], acc [m/s^2], mag [uT] (NULL: no
   magnetometer: the features see zeros, and with TCF_USE_MAG == 0 the core ignores mag anyway). */
void tcf_vqft_update(tcf_vqft_t *f, const float gyr[3], const float acc[3], const float mag[3]);

/* Same with the actual time step dt [s] since the previous sample, for the gyro integration
   (see "Per-sample dt"). */
void tcf_vqft_update_dt(tcf_vqft_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt);

/* Steps 1-5 alone with a prediction made elsewhere (VQFTogglingFilter.update with
   prediction=...): pred[TCF_N_PRED] (NaN = none). The feature window and the trees are not
   touched. For checks of the filter arithmetic, or when the models run elsewhere. */
void tcf_vqft_update_pred(tcf_vqft_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt,
                          const float pred[TCF_N_PRED]);

/* Current orientation q[4] = [w x y z], sensor -> ENU. */
void tcf_vqft_quat(const tcf_vqft_t *f, float q[4]);

/* Held prediction pred[TCF_N_PRED]; returns 0 when there is none (NaN), else 1. */
int tcf_vqft_prediction(const tcf_vqft_t *f, float pred[TCF_N_PRED]);

#ifdef __cplusplus
}
#endif

#endif /* TCF_VQF_TOGGLING_H */
