/* tcf_filter.h: the toggling-gain complementary filter of togglecf in C99 (float32).
 *
 * A port of togglecf.toggling.inloop.toggling_inloop_batch (one sample) with the toggling step: the models in the
 * loop (tcf_features.{h,c}, shared with the learned VQF export: streaming features, the range
 * check of the out-of-range fallback, the generated tree ensemble tcf_forest.c every hop
 * samples, the prediction held until the next window end), then the toggling step (steps 1-7
 * of togglecf.filters.toggling) updates the orientation.
 *
 * Conventions (as togglecf): quaternion [w, x, y, z], Hamilton product, sensor-to-earth,
 * earth frame ENU (x east, y north, z up). Units: gyr rad/s, acc m/s^2, mag uT (only the
 * magnetometer's direction enters the orientation; the features use its norm relative to a
 * running reference).
 *
 * Rate at init (as the learned VQF, tcf_vqf_toggling.h): tcf_filter_init(&f, fs) takes the
 * sampling rate fs [Hz] (up to TCF_MAX_FS of tcf_config.h) and derives every per-sample constant
 * from it and the settings, which are physical (time constants in seconds, TCF_TAU_*), as the
 * Python filter's _coefficients at that rate: the per-state gains k = 1 - exp(-Ts/tau) with
 * Ts = 1/fs, the cautious fallback gains (per sensor the smallest of them), the output blend
 * gamma and the bias gain, and the features' window, hop and EMA gains (tcf_features.h). Nothing is
 * fixed to the training rate: one build runs a 100, 200 or 400 Hz IMU.
 * Per-sample dt: tcf_filter_update_dt(&f, gyr, acc, mag, dt) integrates the gyro over the actual
 * dt [s] (as TogglingFilter.update_batch(..., dt=...)); everything else runs at the nominal rate
 * of init, as in the Python filter: the gains and the features (which count samples). A dt that
 * is not finite, <= 0 or > TCF_MAX_DT skips the gyro integration of that sample (lost samples).
 *
 * Memory: everything lives in tcf_filter_t (fixed size, TCF_STATE_BYTES bytes; no heap,
 * no globals written). Its feature ring is sized for TCF_MAX_FS. At a window end
 * tcf_features_push keeps the feature row and the outputs on the stack (TCF_N_FEATURES +
 * TCF_N_OUTPUTS floats); the deepest chain is tcf_filter_update -> tcf_predict (measure it with
 * togglecf.embedded.toolchain.unit_chain_stack over the three sources as one unit, -Os).
 * Reentrant: one tcf_filter_t per sensor.
 *
 * Bad samples (policy of togglecf.filters.base): non-finite or saturated gyro (|w| >= 34.9
 * rad/s on an axis) -> no propagation; non-finite or zero-norm acc -> no correction; non-finite
 * or zero-norm mag (9D) -> no heading correction. Non-finite samples enter the feature window
 * as NaN (a window holding one gives missing stats of that channel; the trees follow their
 * default branches) and do not update the EMA references, which start at the first finite
 * sample.
 *
 * Do not compile with -ffast-math (the NaN tests would be removed).
 */
#ifndef TCF_FILTER_H
#define TCF_FILTER_H

#include <stdint.h>
#include "tcf_features.h"

#ifdef __cplusplus
extern "C" {
#endif

/* the per-sample constants at the rate of tcf_filter_init (TogglingCoefficients of the Python filter) */
typedef struct tcf_filter_coeffs {
  float ts;                           /* nominal sampling time 1/fs [s] (tcf_filter_update's dt) */
  float alpha_acc[TCF_N_CLASSES];     /* per-state accelerometer gains 1 - exp(-Ts / tau_acc) */
  float alpha_mag[TCF_N_CLASSES];     /* per-state magnetometer gains 1 - exp(-Ts / tau_mag) */
  float alpha_fallback_acc;           /* the cautious gains of the fallback: the smallest per-state ones */
  float alpha_fallback_mag;
  float gamma;                        /* output blend, 1 - exp(-Ts / output_tau) (1: tau 0) */
  float bias_gain;                    /* gyro bias learning, 1 - exp(-Ts / bias_tau) (0: off) */
  float tan_mag_step;                 /* tan(mag_rate_limit * Ts): largest turn of m_pred per sample (0: none) */
  float mag_ref_gain;                 /* step 5b's field reference follows the field, 1 - exp(-Ts / mag_ref_tau) */
} tcf_filter_coeffs_t;

/* The state: the names of TogglingFilter's state (filters.base.COMMON_STATE_FIELDS, then bias, a_pred,
   m_pred of filters.toggling) and of its diagnostics; tests/test_names.py compares them. */
typedef struct tcf_filter {
  tcf_filter_coeffs_t c;  /* per-sample constants at the init rate */
  /* orientation filter (toggle_step) */
  float quat[4];       /* orientation, sensor -> ENU, [w x y z] */
  float bias[3];       /* gyro bias estimate [rad/s] */
  float a_pred[3];     /* gyro-propagated, filtered specific force (sensor frame) [m/s^2] */
  float m_pred[3];     /* gyro-propagated, filtered magnetic field (sensor frame) [uT] */
  float mag_ref_norm;  /* step 5b's reference field norm [uT] (0: not yet set) */
  float mag_ref_dip;   /* and dip [rad], asin(-m^ . up): positive where the field points down */
  uint32_t initialized;  /* 0 until the first valid acc(/mag) sample */
  /* feature window and held prediction (tcf_features.h; NaN before the first full window) */
  tcf_features_t feat;
  /* diagnostics of the last sample */
  float alpha_acc;     /* accelerometer gain used (0: no acc correction) */
  float alpha_mag;     /* magnetometer gain used (0: no heading correction) */
  float p_static;      /* probability of the rest class (bias learning) */
} tcf_filter_t;

/* sizeof(tcf_filter_t): 4-byte members only, no padding (checked at compile time): the coefficients
   (7 + 2 S), the filter (16 + 3 diagnostics), the features (TCF_FEATURES_STATE_BYTES) */
#define TCF_STATE_BYTES (4 * (26 + 2 * TCF_N_CLASSES) + TCF_FEATURES_STATE_BYTES)

/* Reset at the sampling rate fs [Hz]: every per-sample coefficient derived from fs and the
   settings (see "Rate at init"), identity orientation, not initialized, empty window, no
   prediction. Returns TCF_OK (0), or (f untouched) TCF_ERR_RATE (fs not finite and > 0),
   TCF_ERR_RATE_MAX (fs > TCF_MAX_FS) or TCF_ERR_SETTINGS (1/fs > TCF_MAX_DT: the gyro would never
   be integrated). */
int tcf_filter_init(tcf_filter_t *f, float fs);

/* One sample at the init rate (dt = 1/fs): gyr [rad/s], acc [m/s^2], mag [uT] (NULL: no
   magnetometer, the feature channels then see zeros, as the Python filter in 6D). With
   TCF_USE_MAG == 0 the orientation ignores mag (the features still use it when given). */
void tcf_filter_update(tcf_filter_t *f, const float gyr[3], const float acc[3], const float mag[3]);

/* Same with the actual time step dt [s] since the previous sample, for the gyro integration (see
   "Per-sample dt"). */
void tcf_filter_update_dt(tcf_filter_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt);

/* The toggling step alone with a prediction made elsewhere (TogglingFilter.update with
   prediction=...): pred[TCF_N_PRED] as tcf_filter_prediction returns it (NaN = none). The
   feature window and the trees are not touched. For checks of the filter arithmetic, or when
   the models run on another core. */
void tcf_filter_update_pred(tcf_filter_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt,
                            const float pred[TCF_N_PRED]);

/* Current orientation q[4] = [w x y z], sensor -> ENU (identity before initialisation). */
void tcf_filter_quat(const tcf_filter_t *f, float q[4]);

/* Held prediction pred[TCF_N_PRED]: class probabilities (order TCF_CLASS_NAMES), eta_a xyz,
   eta_m xyz (tcf_prediction.h). Returns 0 when there is none (pred is NaN: before the first full
   window, or the window was out of the training range, tcf_features_fallback), 1 otherwise. */
int tcf_filter_prediction(const tcf_filter_t *f, float pred[TCF_N_PRED]);

/* Feature row feat[TCF_N_FEATURES] (names: togglecf.features.feature_schema) of the window
   ending at the last sample, for logging/debugging. Returns 0 (feat untouched) until the
   window is full. */
int tcf_filter_features(const tcf_filter_t *f, float feat[TCF_N_FEATURES]);

#ifdef __cplusplus
}
#endif

#endif /* TCF_FILTER_H */
