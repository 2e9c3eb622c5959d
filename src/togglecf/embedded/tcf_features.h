/* tcf_features.h: the models of togglecf in the loop, C99 float32: streaming features and the
 * tree ensemble, shared by the exported filters (tcf_filter.c: the toggling CF;
 * tcf_vqf_toggling.c: the VQF core with learned time constants).
 *
 * A port of the model part of togglecf.toggling.inloop.run_inloop: per sample, the 12 feature
 * channels are pushed into a ring buffer of the last L samples
 * (togglecf.features.streaming); at every window end (once the window is full, then every
 * H samples) the TCF_N_FEATURES window features are checked against their training range
 * (togglecf.learn.ranges: more than TCF_MAX_OUT of the TCF_N_BOUNDED bounded features outside
 * -> no prediction, NaN, the filter's default) and otherwise go through the generated tree
 * ensemble (tcf_forest.c: class margins -> softmax, plus the predicted acc/mag noise eta_a,
 * eta_m); the prediction is held until the next window end.
 *
 * Units: gyr rad/s, acc m/s^2, mag uT (the features use its norm and dip only relative to their
 * running references, see togglecf.features.windows). Non-finite samples
 * enter the window as NaN (a window holding one gives missing stats of that channel; the trees
 * follow their default branches) and do not update the references, which start at the
 * first finite sample (the field reference: the first with a finite, non-zero |m|).
 *
 * Rate at init: tcf_features_init(s, fs) turns the feature settings of tcf_config.h, in
 * seconds (TCF_WINDOW_S, TCF_HOP_S, TCF_REF_TAU_S, TCF_LP_TAU_S, TCF_REF_NEW_S), into the
 * per-sample constants at fs [Hz] (tcf_features_rate_t), as
 * togglecf.features.windows.feature_coefficients does: window L = max(2, round(TCF_WINDOW_S fs)),
 * hop H = max(1, round(TCF_HOP_S fs)), round(TCF_REF_NEW_S fs) rotating samples (at least 1),
 * all three with Python's round (half to even) of the double product; EMA gains
 * 1 - exp(-1 / (tau fs)). The features count samples: they run at the nominal rate fs
 * (jerk = |delta a| fs), never at a per-sample dt, as the Python features.
 *
 * Memory: all in tcf_features_t (fixed size, TCF_FEATURES_STATE_BYTES; no heap, no globals
 * written). The ring holds TCF_WINDOW_MAX rows, the window at the largest supported rate
 * TCF_MAX_FS [Hz] (tcf_config.h; the export's max_fs): tcf_features_init refuses a higher rate
 * (TCF_ERR_RATE_MAX); a lower rate uses the first L rows. At a window end tcf_features_push
 * keeps the feature row and the tree outputs on the stack (TCF_N_FEATURES + TCF_N_OUTPUTS
 * floats). Configuration: tcf_config.h of the export (feature settings in seconds,
 * TCF_MAX_FS, TCF_WINDOW_MAX, the field-reference gates, TCF_GRAVITY, the feature ranges).
 *
 * Do not compile with -ffast-math (the NaN tests would be removed).
 */
#ifndef TCF_FEATURES_H
#define TCF_FEATURES_H

#include <stdint.h>
#include "tcf_config.h"
#include "tcf_forest.h"
#include "tcf_prediction.h" /* TCF_N_PRED: the row the trees write, as the filters read it */

#ifdef __cplusplus
extern "C" {
#endif

/* per-sample channels kept in the ring (togglecf.features.WINDOW_CHANNELS + gyr_energy) */
#define TCF_RING_COLS 12
/* channels whose current value is a feature (togglecf.features.LAST_CHANNELS) */
#define TCF_N_LAST 10

/* out-of-range fallback (togglecf.learn.ranges), set by the export in tcf_config.h: the number
   of features with finite training bounds (0: the rule is compiled out) and the most of them
   that may lie outside while the trees are still trusted */
#ifndef TCF_N_BOUNDED
#define TCF_N_BOUNDED 0
#endif
#ifndef TCF_MAX_OUT
#define TCF_MAX_OUT 0
#endif

/* return codes of the init functions (tcf_features_init, tcf_vqft_init) */
#define TCF_OK 0
#define TCF_ERR_SETTINGS (-1)  /* the core refuses its settings (tcf_vqf_config.h), or 1/fs > max_dt */
#define TCF_ERR_RATE (-2)      /* fs not a finite number > 0 */
#define TCF_ERR_RATE_MAX (-3)  /* fs > TCF_MAX_FS: the window would not fit the ring (re-export with a larger max_fs) */

/* the per-sample constants of the features at the rate of tcf_features_init
   (togglecf.features.windows.FeatureCoefficients) */
typedef struct tcf_features_rate {
  float fs;            /* nominal rate [Hz] (jerk = |delta a| fs) */
  float lam_ref_c;     /* 1 - exp(-1 / (TCF_REF_TAU_S fs)): gain of the field reference and candidate */
  float lam_lp_c;      /* 1 - exp(-1 / (TCF_LP_TAU_S fs)): gain of the acc low-pass behind acc_hp */
  uint32_t window;     /* L = max(2, round(TCF_WINDOW_S fs)) <= TCF_WINDOW_MAX: samples per window */
  uint32_t hop;        /* H = max(1, round(TCF_HOP_S fs)): samples between window ends */
  uint32_t ref_new_n;  /* max(1, round(TCF_REF_NEW_S fs)): rotating samples to take a new field */
} tcf_features_rate_t;

/* a field's |m| [uT] and dip angle [rad], each as hi + lo (compensated EMA, see tcf_features.c) */
typedef struct tcf_field {
  float mag, mag_lo;
  float dip, dip_lo;
} tcf_field_t;

typedef struct tcf_features {
  tcf_features_rate_t rate;  /* per-sample constants at the init rate */
  float ring[TCF_WINDOW_MAX][TCF_RING_COLS];  /* the last rate.window rows are used */
  tcf_field_t ref;     /* reference (r_{k-1}, d_{k-1}) of the undisturbed field */
  tcf_field_t cand;    /* candidate new field */
  uint32_t cand_n;     /* rotating samples the candidate has agreed with itself (saturates at rate.ref_new_n) */
  float acc_lp[3], acc_lp_lo[3];  /* EMA p_{k-1} of acc [m/s^2], hi + lo */
  float prev_acc[3];   /* previous acc sample (for the jerk; missing next to a bad sample) */
  float last[TCF_N_LAST];  /* the *_last features of the newest sample */
  uint32_t n_filled;   /* samples in the ring (saturates at rate.window) */
  uint32_t pos;        /* ring row of the next sample */
  uint32_t hop_phase;  /* samples since the last window end, modulo rate.hop */
  /* held prediction row (tcf_prediction.h; NaN before the first full window, and after a window out
     of range) */
  float pred[TCF_N_PRED];
} tcf_features_t;

/* sizeof(tcf_features_t): 4-byte members only, no padding (checked at compile time) */
#define TCF_FEATURES_STATE_BYTES (4 * (33 + TCF_N_LAST + TCF_RING_COLS * TCF_WINDOW_MAX + TCF_N_CLASSES))

/* The per-sample constants at fs [Hz] (see "Rate at init" above) into *r. Returns TCF_OK, or
   TCF_ERR_RATE / TCF_ERR_RATE_MAX (*r untouched). */
int tcf_features_rate(float fs, tcf_features_rate_t *r);

/* Reset at rate fs [Hz]: the per-sample constants (tcf_features_rate), empty window, no
   prediction. Returns TCF_OK, or TCF_ERR_RATE / TCF_ERR_RATE_MAX (s untouched). */
int tcf_features_init(tcf_features_t *s, float fs);

/* One sample at the init rate (mag: never NULL here; the filters pass zeros without a magnetometer).
   At a window end the prediction s->pred is renewed (trees, or NaN when out of range);
   returns 1 then, else 0. */
int tcf_features_push(tcf_features_t *s, const float gyr[3], const float acc[3], const float mag[3]);

/* Feature row feat[TCF_N_FEATURES] (names: togglecf.features.feature_schema) of the window
   ending at the last sample. Returns 0 (feat untouched) until the window is full. */
int tcf_features_row(const tcf_features_t *s, float feat[TCF_N_FEATURES]);

/* 1 when the held prediction is the out-of-range fallback (a window end passed and its features
   were out of the training range: pred is NaN), else 0 (the Python filter's "fallback"). The
   trees never give NaN, so this needs no extra state. */
int tcf_features_fallback(const tcf_features_t *s);

#ifdef __cplusplus
}
#endif

#endif /* TCF_FEATURES_H */
