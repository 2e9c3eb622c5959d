/* tcf_filter.h: the toggling-gain complementary filter of togglecf in C99 (float32).
 *
 * A port of togglecf.toggling.inloop.inloop_batch (one sample) with the toggling step: the models in the
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
 * Memory: everything lives in tcf_filter_t (fixed size, TCF_STATE_BYTES bytes; no heap,
 * no globals written). At a window end tcf_features_push keeps the feature row and the
 * outputs on the stack (TCF_N_FEATURES + TCF_N_OUTPUTS floats); in all, 560 bytes of stack for
 * a 55-feature export (feature version 2; gcc -fstack-usage -fcallgraph-info, rv32imc -Os, the
 * deepest chain tcf_filter_update -> tcf_predict over the three sources as one unit,
 * togglecf.embedded.toolchain.call_chain_stack).
 * Reentrant: one tcf_filter_t per sensor.
 *
 * Rate: call tcf_filter_update exactly once per sample at TCF_FS Hz (the rate the models and
 * gains were exported for, see tcf_config.h): the per-sample gains are fixed to it, and
 * tcf_filter_init sets the features (window, hop) to it (TCF_MAX_FS = TCF_FS: the ring holds
 * exactly one window). Unlike the learned VQF (tcf_vqf_toggling.h), whose rate is set at init. tcf_filter_update_dt takes another dt for the gyro integration only (lost
 * samples); the features still count samples.
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

typedef struct tcf_filter {
  /* orientation filter (toggle_step) */
  float q[4];          /* orientation, sensor -> ENU, [w x y z] */
  float bias[3];       /* gyro bias estimate [rad/s] */
  float a_pred[3];     /* gyro-propagated, filtered specific force (sensor frame) [m/s^2] */
  float m_pred[3];     /* gyro-propagated, filtered magnetic field (sensor frame) [uT] */
  uint32_t initialised;  /* 0 until the first valid acc(/mag) sample */
  /* feature window and held prediction (tcf_features.h; NaN before the first full window) */
  tcf_features_t feat;
  /* diagnostics of the last sample */
  float alpha_acc;     /* accelerometer gain used (0: no acc correction) */
  float alpha_mag;     /* magnetometer gain used (0: no heading correction) */
  float p_static;      /* probability of the rest class (bias learning) */
} tcf_filter_t;

/* sizeof(tcf_filter_t): 4-byte members only, no padding (checked at compile time) */
#define TCF_STATE_BYTES (4 * (50 + TCF_N_LAST + TCF_RING_COLS * TCF_WINDOW_MAX + TCF_N_CLASSES))

/* Reset: identity orientation, not initialised, empty window, no prediction. */
void tcf_filter_init(tcf_filter_t *f);

/* One sample at TCF_FS: gyr [rad/s], acc [m/s^2], mag [uT] (NULL: no magnetometer, the
   feature channels then see zeros, as the Python filter in 6D). With TCF_USE_MAG == 0 the
   orientation ignores mag (the features still use it when given). */
void tcf_filter_update(tcf_filter_t *f, const float gyr[3], const float acc[3], const float mag[3]);

/* Same with the gyro integration step dt [s] (integrated only when 0 < dt <= TCF_MAX_DT). */
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
   eta_m xyz. Returns 0 when there is none (pred is NaN: before the first full window, or the
   window was out of the training range, tcf_features_fallback), 1 otherwise. */
int tcf_filter_prediction(const tcf_filter_t *f, float pred[TCF_N_PRED]);

/* Feature row feat[TCF_N_FEATURES] (names: togglecf.features.feature_schema) of the window
   ending at the last sample, for logging/debugging. Returns 0 (feat untouched) until the
   window is full. */
int tcf_filter_features(const tcf_filter_t *f, float feat[TCF_N_FEATURES]);

#ifdef __cplusplus
}
#endif

#endif /* TCF_FILTER_H */
