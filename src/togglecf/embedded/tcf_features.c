/* tcf_features.c: streaming features, range check and trees of togglecf in C99, float32 (API in
 * tcf_features.h); shared by tcf_filter.c and tcf_vqf_toggling.c.
 *
 * Line-by-line port of (togglecf/...):
 *   features/streaming.py  push_sample, window_features -> tcf_push_sample, tcf_window_features
 *   learn/ranges.py        window_out_of_range          -> tcf_out_of_range
 *   toggling/inloop.py     run_inloop (the model part) -> tcf_features_push
 */
#include <math.h>
#include <stddef.h>
#include <string.h>
#include "tcf_features.h"
#include "tcf_math.h"  /* tcf_field_agrees */

#if defined(__FAST_MATH__)
#error "tcf_features.c must not be compiled with -ffast-math: the missing-value (NaN) tests would be removed"
#endif

/* compile-time checks of the documented state size and the feature count (C99: a negative array
   size is an error) */
typedef char tcf_features_bytes_check[(sizeof(tcf_features_t) == TCF_FEATURES_STATE_BYTES) ? 1 : -1];
typedef char tcf_n_features_check[(TCF_N_FEATURES == 4 * (TCF_RING_COLS - 1) + 1 + TCF_N_LAST) ? 1 : -1];

/* ------------------------------------------------------------------ streaming_features.py */

/* Exponential moving average r <- lam r + (1 - lam) x = r + c (x - r), c = 1 - lam, kept as an
   unevaluated sum hi + lo (compensated, as Kahan summation). A plain float32 EMA with c ~ 3.5e-4
   loses up to half an ulp of r per sample against c (x - r) (a dead band of up to
   ulp(r) / (2 c), ~5e-3 uT at |m| ~ 50 uT); measured on BROAD trial 05 the plain form puts
   mag_norm_dev up to 1.4e-4 uT off the float64 reference, hi + lo 5e-6 uT (dip_dev 3.6e-6 vs
   1.2e-6 rad, acc_hp 8.8e-6 vs 6.1e-7 m/s^2). Costs 5 floats of state. */
static void ema_update(float *hi, float *lo, float c, float x) {
  float y = *lo + c * ((x - *hi) - *lo);  /* the amount to add to hi */
  float t = *hi + y;
  float yv = t - *hi;
  *lo = (*hi - (t - yv)) + (y - yv);  /* exact rounding error of hi + y (TwoSum) */
  *hi = t;
}

/* The field reference after sample k (togglecf.features.windows.mag_reference_step; VQF's
   eqs. M2-M3 in the sensor frame): the reference follows |m| and the dip only while they agree
   with it; a candidate that has agreed with itself for rate.ref_new_n rotating samples replaces a
   reference the field disagrees with. The helpers are shared by reference and candidate (code
   size: every float operation is a call on a soft-float target). */
#if defined(__GNUC__)
#define TCF_NOINLINE __attribute__((noinline))
#else
#define TCF_NOINLINE
#endif

static void field_set(tcf_field_t *r, float mn, float dip) {
  r->mag = mn; r->dip = dip; r->mag_lo = 0.0f; r->dip_lo = 0.0f;
}

/* the gate against hi alone: lo (< 1 ulp of hi) cannot matter at a 10 % / 10 degree threshold */
static TCF_NOINLINE int field_agrees(const tcf_field_t *r, float mn, float dip) {
  return tcf_field_agrees(r->mag, r->dip, mn, dip, TCF_REF_NORM_TH, TCF_REF_DIP_TH);
}

static TCF_NOINLINE void field_follow(tcf_field_t *r, float c, float mn, float dip) {
  ema_update(&r->mag, &r->mag_lo, c, mn);
  ema_update(&r->dip, &r->dip_lo, c, dip);
}

/* before sample k's deviations: with no reference yet (NaN, or 0 after tcf_features_init; a
   reference is otherwise a positive norm) and a usable sample, reference and candidate start at
   it (mag_reference_start) */
static void mag_reference_start(tcf_features_t *f, float mn, float dip) {
  if (!(f->ref.mag > 0.0f)) {
    field_set(&f->ref, mn, dip);
    field_set(&f->cand, mn, dip);
    f->cand_n = 0u;
  }
}

/* after them (mag_reference_step; dip is finite by construction) */
static void mag_reference_update(tcf_features_t *f, float mn, float dip, float gn2) {
  int agree = field_agrees(&f->ref, mn, dip);  /* (M2) */
  if (agree) field_follow(&f->ref, f->rate.lam_ref_c, mn, dip);
  if (field_agrees(&f->cand, mn, dip)) {  /* (M3) */
    if (gn2 >= TCF_REF_MIN_GYR_SQ && f->cand_n < f->rate.ref_new_n) f->cand_n++;
    field_follow(&f->cand, f->rate.lam_ref_c, mn, dip);
    if (!agree && f->cand_n >= f->rate.ref_new_n) f->ref = f->cand;  /* a new field becomes the reference */
  } else {
    field_set(&f->cand, mn, dip);
    f->cand_n = 0u;
  }
}

/* Append one sample's channels (push_sample; definitions in togglecf.features). Ring columns:
   0-2 gyr, 3 |gyr|, 4-6 acc, 7 |acc| - g, 8 jerk, 9 mag_norm_dev, 10 dip_dev, 11 |gyr|^2
   (gyr_energy). The magnetometer enters only relative to its own gated reference of the undisturbed
   field (never as raw components or norm; togglecf.features.windows). */
static void tcf_push_sample(tcf_features_t *f, const float gyr[3], const float acc[3], const float mag[3]) {
  float *row = f->ring[f->pos];
  float gn2 = gyr[0] * gyr[0] + gyr[1] * gyr[1] + gyr[2] * gyr[2];
  float an = sqrtf(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2]);
  float mn = sqrtf(mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2]);
  float cosang = an * mn > 0.0f ? (acc[0] * mag[0] + acc[1] * mag[1] + acc[2] * mag[2]) / (an * mn) : 0.0f;
  float dip, jerk, c;
  int i, usable;
  if (!isfinite(cosang)) cosang = 0.0f;  /* nan_to_num, as the vectorised version */
  c = -cosang;
  c = c < -1.0f ? -1.0f : (c > 1.0f ? 1.0f : c);
  dip = asinf(c);
  if (f->n_filled == 0) {  /* the low-pass starts at the first sample, p_{-1} = a_0 */
    for (i = 0; i < 3; ++i) {
      f->acc_lp[i] = acc[i];
      f->acc_lp_lo[i] = 0.0f;
      f->prev_acc[i] = acc[i];
    }
    jerk = 0.0f;
  } else {
    float dx = acc[0] - f->prev_acc[0], dy = acc[1] - f->prev_acc[1], dz = acc[2] - f->prev_acc[2];
    jerk = sqrtf(dx * dx + dy * dy + dz * dz) * f->rate.fs;
  }
  usable = mn > 0.0f && isfinite(mn);  /* a bad or zero-norm sample says nothing about the field */
  if (usable) mag_reference_start(f, mn, dip);
  row[0] = gyr[0]; row[1] = gyr[1]; row[2] = gyr[2];
  row[3] = sqrtf(gn2);
  row[4] = acc[0]; row[5] = acc[1]; row[6] = acc[2];
  row[7] = an - TCF_GRAVITY;
  row[8] = jerk;
  row[9] = (mn - f->ref.mag) - f->ref.mag_lo;  /* uses r_{k-1} */
  row[10] = (dip - f->ref.dip) - f->ref.dip_lo;
  row[11] = gn2;
  /* LAST_CHANNELS: gyr_norm, acc_x/y/z, acc_norm_dev, mag_norm_dev, dip_dev, acc_hp_x/y/z */
  f->last[0] = row[3];
  f->last[1] = row[4]; f->last[2] = row[5]; f->last[3] = row[6];
  f->last[4] = row[7];
  f->last[5] = row[9];
  f->last[6] = row[10];
  for (i = 0; i < 3; ++i) f->last[7 + i] = (acc[i] - f->acc_lp[i]) - f->acc_lp_lo[i];  /* uses p_{k-1} */
  /* update the field reference with sample k (only from usable samples) */
  if (usable) mag_reference_update(f, mn, dip, gn2);
  if (isfinite(an)) {
    if (isfinite(f->acc_lp[0]) && isfinite(f->acc_lp[1]) && isfinite(f->acc_lp[2])) {
      for (i = 0; i < 3; ++i) ema_update(&f->acc_lp[i], &f->acc_lp_lo[i], f->rate.lam_lp_c, acc[i]);
    } else {
      for (i = 0; i < 3; ++i) { f->acc_lp[i] = acc[i]; f->acc_lp_lo[i] = 0.0f; }
    }
  }
  /* jerk next to a bad sample is missing, as in togglecf.features */
  f->prev_acc[0] = acc[0]; f->prev_acc[1] = acc[1]; f->prev_acc[2] = acc[2];
  if (f->n_filled < f->rate.window) f->n_filled++;
  f->pos = (f->pos + 1u) % f->rate.window;
}

/* Feature row of the window ending at the last pushed sample (window_features): mean, std,
   min, max of ring columns 0-10, mean of column 11, then the 10 *_last values. A column with a
   non-finite value in the window gives NaN (missing) stats, as the numba and vectorised code. */
static void tcf_window_features(const tcf_features_t *f, float out[TCF_N_FEATURES]) {
  int c, j;
  uint32_t i, L = f->rate.window;
  float e = 0.0f;
  for (c = 0; c < TCF_RING_COLS - 1; ++c) {
    float s = 0.0f, ss = 0.0f, lo = f->ring[0][c], hi = f->ring[0][c], mean;
    for (i = 0; i < L; ++i) {
      float v = f->ring[i][c];
      s += v;
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
    if (!isfinite(s)) {  /* a non-finite value in the window: this channel's stats are missing */
      out[4 * c] = out[4 * c + 1] = out[4 * c + 2] = out[4 * c + 3] = NAN;
      continue;
    }
    mean = s / (float)L;
    for (i = 0; i < L; ++i) {
      float d = f->ring[i][c] - mean;
      ss += d * d;
    }
    out[4 * c] = mean;
    out[4 * c + 1] = sqrtf(ss / (float)L);
    out[4 * c + 2] = lo;
    out[4 * c + 3] = hi;
  }
  for (i = 0; i < L; ++i) e += f->ring[i][TCF_RING_COLS - 1];
  out[4 * (TCF_RING_COLS - 1)] = isfinite(e) ? e / (float)L : NAN;
  for (j = 0; j < TCF_N_LAST; ++j) out[4 * (TCF_RING_COLS - 1) + 1 + j] = f->last[j];
}

/* ------------------------------------------------------------------ learn/ranges.py */

#if TCF_N_BOUNDED > 0
/* the features with finite training bounds (0.5 % / 99.5 % quantiles, rounded to float32): their
   indices (TCF_BOUNDED_INIT; left out of tcf_config.h when every feature is bounded) and bounds */
#ifdef TCF_BOUNDED_INIT
static const uint8_t tcf_bounded[TCF_N_BOUNDED] = TCF_BOUNDED_INIT;
typedef char tcf_bounded_index_check[(TCF_N_FEATURES <= 256) ? 1 : -1];
#define TCF_BOUNDED(j) tcf_bounded[j]
#else
typedef char tcf_bounded_all_check[(TCF_N_BOUNDED == TCF_N_FEATURES) ? 1 : -1];
#define TCF_BOUNDED(j) (j)
#endif
static const float tcf_low[TCF_N_BOUNDED] = TCF_FEATURE_LOW_INIT;
static const float tcf_high[TCF_N_BOUNDED] = TCF_FEATURE_HIGH_INIT;

/* window_out_of_range: more than TCF_MAX_OUT (= floor(max_out_of_range * TCF_N_BOUNDED)) of the
   bounded features finite and outside [low, high] (a missing feature is not out of range) */
static int tcf_out_of_range(const float feat[TCF_N_FEATURES]) {
  int j, n_out = 0;
  for (j = 0; j < TCF_N_BOUNDED; ++j) {
    float v = feat[TCF_BOUNDED(j)];
    if (isfinite(v) && (v < tcf_low[j] || v > tcf_high[j])) ++n_out;
  }
  return n_out > TCF_MAX_OUT;
}
#endif

/* ------------------------------------------------------------------ API */

/* Python's int(round(x)) for 0 <= x < 2^32: half to even on the exact double */
static uint32_t round_half_even(double x) {
  uint32_t r = (uint32_t)x;
  double frac = x - (double)r;  /* exact */
  if (frac > 0.5 || (frac == 0.5 && (r & 1u))) ++r;
  return r;
}

/* max(lo, round(seconds fs)) in double, as togglecf.features.windows (window_length, hop_length,
   feature_coefficients) */
static uint32_t samples_of(double seconds, float fs, uint32_t lo) {
  uint32_t n = round_half_even(seconds * (double)fs);
  return n > lo ? n : lo;
}

int tcf_features_rate(float fs, tcf_features_rate_t *r) {
  uint32_t window;
  if (!(fs > 0.0f && fs < INFINITY)) return TCF_ERR_RATE;
  if (fs > (float)TCF_MAX_FS) return TCF_ERR_RATE_MAX;
  window = samples_of(TCF_WINDOW_S, fs, 2u);
  if (window > TCF_WINDOW_MAX) return TCF_ERR_RATE_MAX;  /* only if TCF_MAX_FS was edited without TCF_WINDOW_MAX */
  r->fs = fs;
  r->window = window;
  r->hop = samples_of(TCF_HOP_S, fs, 1u);
  r->ref_new_n = samples_of(TCF_REF_NEW_S, fs, 1u);
  /* 1 - lambda = -expm1(-1 / (tau fs)): no cancellation (tau fs >> 1) */
  r->lam_ref_c = -expm1f(-1.0f / ((float)TCF_REF_TAU_S * fs));
  r->lam_lp_c = -expm1f(-1.0f / ((float)TCF_LP_TAU_S * fs));
  return TCF_OK;
}

int tcf_features_init(tcf_features_t *f, float fs) {
  int j;
  tcf_features_rate_t r;
  j = tcf_features_rate(fs, &r);
  if (j != TCF_OK) return j;
  memset(f, 0, sizeof *f);  /* empty window, low-pass and counters (all-zero bits are 0.0f) */
  f->rate = r;
  f->ref.mag = f->ref.dip = NAN;  /* no field reference: it starts at the first usable sample (NaN deviations before) */
  for (j = 0; j < TCF_N_PRED; ++j) f->pred[j] = NAN;  /* no prediction before the first full window */
  return TCF_OK;
}

/* run_inloop, the model part of one sample: push the features; at a window end (every rate.hop samples once
   the window is full) check the range, evaluate the trees into f->pred (held until the next one). */
int tcf_features_push(tcf_features_t *f, const float gyr[3], const float acc[3], const float mag[3]) {
  int renewed = 0;
  tcf_push_sample(f, gyr, acc, mag);
  if (f->n_filled == f->rate.window) {
    if (f->hop_phase == 0u) {
      float feat[TCF_N_FEATURES], margin[TCF_N_OUTPUTS];
      int k;
      tcf_window_features(f, feat);
#if TCF_N_BOUNDED > 0
      if (tcf_out_of_range(feat)) {  /* no prediction: the filter's default until the next window end */
        for (k = 0; k < TCF_N_PRED; ++k) f->pred[k] = NAN;
      } else
#endif
      {
        tcf_predict(feat, margin);
        tcf_softmax(margin);  /* class margins -> probabilities; eta_a, eta_m stay raw */
        for (k = 0; k < TCF_N_PRED; ++k) f->pred[k] = margin[k];
      }
      renewed = 1;
    }
    f->hop_phase = (f->hop_phase + 1u) % f->rate.hop;
  }
  return renewed;
}

int tcf_features_row(const tcf_features_t *f, float feat[TCF_N_FEATURES]) {
  if (f->n_filled < f->rate.window) return 0;
  tcf_window_features(f, feat);
  return 1;
}

int tcf_features_fallback(const tcf_features_t *f) {
  return (f->n_filled == f->rate.window && isnan(f->pred[0])) ? 1 : 0;
}
