/* tcf_prediction.h: one prediction row and what both learned filters take from it, C99 float32
 * (static inline; the C twin of togglecf/filters/prediction.py, whose module docstring is the
 * reference). Shared by tcf_filter.c (the toggling CF) and tcf_vqf_toggling.c (the learned VQF):
 * each keeps only its own core and its own fallback rule, and calls these for the rest.
 *
 * Row (PredictionLayout): [p_1..p_S, eta_a xyz, eta_m xyz]: the class probabilities of the S
 * = TCF_N_CLASSES motion states (non-negative weights, need not sum to 1), then the predicted acc
 * noise eta_a [m/s^2] and mag noise eta_m [uT] in the sensor frame; NaN probabilities mean "no
 * prediction". The trees write it (tcf_forest.c outputs, tcf_features.c holds it); the filters
 * read it only through tcf_prediction_from_row, as named fields.
 *
 * Steps (prediction.py): 1 confidence (tcf_class_evidence); 2 the fallback, which differs per
 * filter on purpose and is therefore in each filter's .c (tcf_filter.c: the hard switch,
 * prediction.switch_status; tcf_vqf_toggling.c: the blend, prediction.blend_trust); 3 noise
 * removal (tcf_remove_noise); 4 the magnetic back-off (tcf_predicted_disturbance, tcf_back_off).
 *
 * Do not compile with -ffast-math (the NaN tests would be removed).
 */
#ifndef TCF_PREDICTION_H
#define TCF_PREDICTION_H

#include <math.h>
#include "tcf_forest.h" /* TCF_N_CLASSES */

#ifdef __cplusplus
extern "C" {
#endif

/* The row layout (PredictionLayout.of(S)); the only place its offsets are written. */
#define TCF_PRED_ETA_ACC TCF_N_CLASSES       /* row index of eta_a,x (eta_acc_index) */
#define TCF_PRED_ETA_MAG (TCF_N_CLASSES + 3) /* row index of eta_m,x (eta_mag_index) */
#define TCF_N_PRED (TCF_N_CLASSES + 6)       /* the row length (size; N_PRED_NOISE = 6) */

/* switch_status's outcomes (prediction.LEARNED, NO_PREDICTION, LOW_CONFIDENCE) */
#define TCF_LEARNED 0
#define TCF_NO_PREDICTION 1
#define TCF_LOW_CONFIDENCE 2

/* One prediction row as named fields (PredictionLayout's probabilities, eta_acc, eta_mag). */
typedef struct tcf_prediction {
  float probabilities[TCF_N_CLASSES]; /* p_s, class order TCF_CLASS_NAMES */
  float eta_acc[3];                   /* predicted acc noise, sensor frame [m/s^2] */
  float eta_mag[3];                   /* predicted mag noise, sensor frame [uT] */
} tcf_prediction_t;

/* The row row[TCF_N_PRED] as named fields (PredictionLayout's slices). */
static inline void tcf_prediction_from_row(const float *row, tcf_prediction_t *p) {
  int j;
  for (j = 0; j < TCF_N_CLASSES; ++j) p->probabilities[j] = row[j];
  for (j = 0; j < 3; ++j) {
    p->eta_acc[j] = row[TCF_PRED_ETA_ACC + j];
    p->eta_mag[j] = row[TCF_PRED_ETA_MAG + j];
  }
}

/* Step 1 (class_evidence): 1 when the probabilities are valid (every p_s finite and >= 0, and
   sum p_s > 0), else 0; their largest max_s p_s in *top and their sum in *total (class order;
   the confidence is c = top / total). */
static inline int tcf_class_evidence(const tcf_prediction_t *p, float *top, float *total) {
  int s, valid = 1;
  *top = 0.0f;
  *total = 0.0f;
  for (s = 0; s < TCF_N_CLASSES; ++s) {
    float v = p->probabilities[s];
    if (!(v >= 0.0f && v < INFINITY)) {
      valid = 0;
    } else {
      *total += v;
      if (v > *top) *top = v;
    }
  }
  return valid && *total > 0.0f;
}

/* noise_finite: 1 when eta_a and eta_m are all finite. */
static inline int tcf_noise_finite(const tcf_prediction_t *p) {
  int j, ok = 1;
  for (j = 0; j < 3; ++j)
    if (!isfinite(p->eta_acc[j]) || !isfinite(p->eta_mag[j])) ok = 0;
  return ok;
}

/* Step 3 (remove_noise): a_d = a - w_a eta_a, m_d = m - w_m eta_m when use and eta is finite,
   returning 1; else a_d = a, m_d = m, returning 0 (a [m/s^2], m [uT], weights dimensionless).
   The return also says whether eta may drive the back-off (step 4) under the same rule. */
static inline int tcf_remove_noise(const tcf_prediction_t *p, const float acc[3], const float mag[3], float w_a,
                                   float w_m, int use, float a_d[3], float m_d[3]) {
  int j, removed = use && tcf_noise_finite(p);
  for (j = 0; j < 3; ++j) {
    a_d[j] = removed ? acc[j] - w_a * p->eta_acc[j] : acc[j];
    m_d[j] = removed ? mag[j] - w_m * p->eta_mag[j] : mag[j];
  }
  return removed;
}

/* Step 4 (predicted_disturbance): e = |eta_m|^2 / sigma^2 (dimensionless) for sigma = sigma_m
   [uT] > 0; 0 for a NaN eta_m. */
static inline float tcf_predicted_disturbance(const tcf_prediction_t *p, float sigma) {
  const float *em = p->eta_mag;
  float e = (em[0] * em[0] + em[1] * em[1] + em[2] * em[2]) / (sigma * sigma);
  return e >= 0.0f ? e : 0.0f; /* false for NaN */
}

/* Step 4 (back_off): a magnetometer gain lowered by the disturbance e >= 0: k / (1 + e). */
static inline float tcf_back_off(float gain, float e) { return gain / (1.0f + e); }

#ifdef __cplusplus
}
#endif

#endif /* TCF_PREDICTION_H */
