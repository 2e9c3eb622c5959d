/* tcf_vqf.h: the VQF-class core filter of togglecf in C99, float32 (port of
 * togglecf.filters.vqf_core, itself written from Laidig & Seel, "VQF: Highly accurate IMU
 * orientation estimation with bias estimation and magnetic disturbance rejection",
 * Information Fusion 91:187-204, 2023; the equation labels (R1)...(M5) and "Alg. 1 l. N" in
 * tcf_vqf.c are those of the Python module's docstring).
 *
 * Conventions (as togglecf): quaternion [w, x, y, z], Hamilton product, sensor-to-earth,
 * earth frame ENU (x east, y north, z up). Units: gyr rad/s, acc m/s^2, mag any unit (only
 * its direction, norm ratio and dip enter). Settings in VQF's units (deg/s, deg, s, m/s^2).
 *
 * Memory: all state in one tcf_vqf_t (fixed size, no heap, no globals written; reentrant,
 * one tcf_vqf_t per sensor). The per-sample coefficients are derived from the settings and
 * Ts = 1/fs by tcf_vqf_init (float32, once; same formulas as vqf_core.core_coefficients)
 * and kept inside tcf_vqf_t, so rate and settings can be chosen at run time.
 * sizeof(tcf_vqf_t) = TCF_VQF_STATE_BYTES = 532 bytes. The object code of tcf_vqf.c (+
 * tcf_vqf_standalone.c) on a Cortex-M4F (hard float), rv32imc (soft float) and the host, and the
 * stack of the deepest tcf_vqf_update call chain (libm routines not counted), are measured and
 * reported by togglecf.embedded.cvqf.export_c_vqf (vqf_report.json) for the compiler at hand.
 *
 * Low-pass filters: the second-order Butterworth LP_2 in the "delta" form of the Python filter
 * (vqf_core.LowPass, _lp_bank; state: output level v and increment dv, coefficients k = 4 b0 and
 * one_minus_decay = 1 - a2, both small and exactly representable) instead of VQF's direct form II transposed: with
 * tau_acc = 3 s at 286 Hz, a1 and a2 are within 2.3e-3 of -2 and 1, and in float32 the DF2T's
 * DC gain (1 + a1 + a2 = 4 b0 = 2.7e-6) would be off by ~5 % and its rounding noise amplified
 * by ~1/(4 b0). Same transfer function, same start-up (running mean for tau, then steady state).
 * The state is the signal, not a coefficient-dependent mix, so a learned filter may change the
 * tau_acc coefficients between samples (tcf_vqf_update_mod) without a kick in the output.
 *
 * Bad samples (policy of togglecf.filters.base): a non-finite or saturated gyro (|w| >= 34.9
 * rad/s on an axis) or an invalid dt (non-finite, <= 0, > max_dt) skips the gyro part (rest
 * low-pass and timer, strapdown integration); a non-finite or zero-norm acc skips the whole
 * accelerometer part (rest LP, inclination correction, bias estimation); a non-finite or
 * zero-norm mag (or mag == NULL) skips the heading part. No invalid value reaches the state.
 *
 * Do not compile with -ffast-math (it removes the NaN tests; tcf_vqf.c refuses it).
 */
#ifndef TCF_VQF_H
#define TCF_VQF_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Physical settings (VQFCoreSettings: same names, defaults and units) + rate and mode. */
typedef struct tcf_vqf_params {
  float fs;                     /* sampling rate [Hz] (no default) */
  float max_dt;                 /* longest dt still integrated [s] (0.1) */
  int use_mag;                  /* 1: 9D output (heading from mag), 0: 6D */
  float tau_acc;                /* [s] (3.0) */
  float tau_mag;                /* [s] (9.0) */
  int motion_bias_est_enabled;  /* (1) */
  int rest_bias_est_enabled;    /* (1) */
  int mag_dist_rejection_enabled;  /* (1) */
  float bias_sigma_init;        /* [deg/s] (0.5) */
  float bias_forgetting_time;   /* [s] (100.0) */
  float bias_clip;              /* [deg/s] (2.0) */
  float bias_sigma_motion;      /* [deg/s] (0.1) */
  float bias_vertical_forgetting_factor;  /* (0.0001) */
  float bias_sigma_rest;        /* [deg/s] (0.03) */
  float rest_min_t;             /* [s] (1.5) */
  float rest_filter_tau;        /* [s] (0.5) */
  float rest_th_gyr;            /* [deg/s] (2.0) */
  float rest_th_acc;            /* [m/s^2] (0.5) */
  float mag_current_tau;        /* [s] (0.05) */
  float mag_ref_tau;            /* [s] (20.0) */
  float mag_norm_th;            /* (0.1) */
  float mag_dip_th;             /* [deg] (10.0) */
  float mag_new_time;           /* [s] (20.0) */
  float mag_new_first_time;     /* [s] (5.0) */
  float mag_new_min_gyr;        /* [deg/s] (20.0) */
  float mag_min_undisturbed_time;  /* [s] (0.5) */
  float mag_max_rejection_time; /* [s] (60.0) */
  float mag_rejection_factor;   /* (2.0) */
} tcf_vqf_params_t;

/* coefficients of one LP_2 in delta form (tcf_vqf.c, lp_step), dimensionless; the fields of
   togglecf.filters.vqf_core.LowPass, except that the C keeps 1 - decay where Python keeps decay:
   near 0 (2.3e-3 at tau 3 s, 286 Hz) it is exact in float32, where a2 = 0.9977 would round */
typedef struct tcf_vqf_lp_coef {
  float k;                /* 4 b0 = 1 + a1 + a2 (LowPass.k) */
  float one_minus_decay;  /* 1 - a2 = 1 - LowPass.decay */
} tcf_vqf_lp_coef_t;

/* per-sample coefficients (derived by tcf_vqf_init; rad, rad/s, (rad/s)^2): the fields of
   VQFCoreCoefficients, with those of its nested CoreModulation (acc_lp, k_mag, bias_w_motion,
   bias_w_vertical, rest_th_gyr_sq, rest_th_acc_sq) in line; flags 1/0 */
typedef struct tcf_vqf_coef {
  float ts, inv_ts, max_dt;
  float tau_acc, tau_mag, rest_tau, mag_cur_tau;
  tcf_vqf_lp_coef_t acc_lp, rest_lp, mag_lp;
  float k_mag, k_mag_ref;
  float bias_p0, bias_v, bias_w_motion, bias_w_vertical, bias_w_rest, bias_clip;
  float rest_th_gyr_sq, rest_th_acc_sq, rest_min_t;
  float mag_norm_th, mag_dip_th, mag_new_time, mag_new_first_time, mag_new_min_gyr_sq;
  float mag_min_undisturbed_t, mag_max_rejection_t, mag_rejection_factor;
  uint32_t use_mag, motion_bias, rest_bias, mag_rejection;
} tcf_vqf_coef_t;

/* the head of a bank of LP_2 channels (the n and ready of a bank record of vqf_core) */
typedef struct tcf_vqf_lp_head {
  uint32_t n;      /* samples so far while averaging */
  uint32_t ready;  /* 0 while averaging, 1 after tau */
} tcf_vqf_lp_head_t;

/* The state: the names of VQFCoreFilter's state record (filters.base.COMMON_STATE_FIELDS and
   vqf_core.CORE_STATE_FIELDS; tests/test_names.py compares them). A low-pass bank B of the Python
   record (n, ready, s) is B_head {n, ready} and the channels B = B.s here, the heads first. */
typedef struct tcf_vqf {
  tcf_vqf_coef_t c;       /* coefficients (the Python filter's params) */
  float quat[4];          /* output orientation, sensor -> ENU (9D) or 6D earth frame */
  float q_gyr[4];         /* sensor -> almost-inertial frame I */
  float q_acc[4];         /* I -> 6D earth frame */
  float delta;            /* heading offset [rad] */
  float bias[3];          /* gyro bias estimate [rad/s] */
  float bias_p[9];        /* its covariance [(rad/s)^2], row-major */
  float rest_t;           /* rest timer [s] */
  float rest_gyr_lp[3];   /* rest LP of the gyro [rad/s] */
  float mag_ref_norm, mag_ref_dip, mag_undisturbed_t, mag_reject_t;
  float mag_cand_norm, mag_cand_dip, mag_cand_t, k_mag_init;
  float k_mag_last;       /* heading gain used in the last sample (diagnostic) */
  uint32_t initialized;   /* 1 after the first inclination correction */
  uint32_t rest_detected;      /* 1 at rest (VQF's restDetected) */
  uint32_t mag_dist_detected;  /* 1 while the magnetic field is taken as disturbed (VQF's magDistDetected) */
  /* low-pass banks: heads, then the channels [channel][v, dv] (while averaging: [channel][sum, 0]) */
  tcf_vqf_lp_head_t acc_lp_head, rest_gyr_bank_head, rest_acc_bank_head, bias_r_lp_head, bias_rb_lp_head,
      mag_nd_lp_head;
  float acc_lp[3][2];         /* [a]_I [m/s^2], tau_acc (Alg. 1 l. 10) */
  float rest_gyr_bank[3][2];  /* gyro [rad/s], tau_rest (R1) */
  float rest_acc_bank[3][2];  /* acc [m/s^2], tau_rest (R2) */
  float bias_r_lp[9][2];      /* R(q_6D), row-major, tau_acc (B3) */
  float bias_rb_lp[2][2];     /* (R b)_xy [rad/s], tau_acc (B3) */
  float mag_nd_lp[2][2];      /* field norm [unit of mag] and dip [rad], tau_mag,current (M1) */
} tcf_vqf_t;

/* The coefficients a learned filter may change from sample to sample (CoreModulation of
   togglecf.filters.vqf_core); tcf_vqf_update_dt runs them at the settings' values
   (tcf_vqf_base_mod). Units of tcf_vqf_coef_t. */
typedef struct tcf_vqf_mod {
  tcf_vqf_lp_coef_t acc_lp;  /* tau_acc low-pass (inclination, R and R b for the bias), delta form */
  float k_mag;               /* heading gain per sample, 1 - exp(-Ts / tau_mag) */
  float bias_w_motion;       /* W_motion of the bias estimation in motion [(rad/s)^2] */
  float bias_w_vertical;     /* its vertical-axis counterpart */
  float rest_th_gyr_sq, rest_th_acc_sq;  /* rest thresholds [(rad/s)^2], [(m/s^2)^2] */
} tcf_vqf_mod_t;

/* sizeof(tcf_vqf_t): 133 four-byte members (36 coefficients, 97 state: quaternions 12, delta 1,
   bias 3 + P 9, rest 4, magnetometer 9, flags 3, low-pass heads 12 + channels 44), no padding
   (checked at compile time in tcf_vqf.c) */
#define TCF_VQF_STATE_BYTES (4 * 133)

/* VQF's default settings at rate fs [Hz], 9D. */
void tcf_vqf_params_default(tcf_vqf_params_t *p, float fs);

/* Derive the coefficients from *p and reset the state (identity orientation, bias 0, field
   taken as disturbed with no reference). Returns 0, or -1 (f untouched) for invalid settings
   (the checks of VQFCoreSettings: fs, max_dt, the taus and sigmas > 0, the rest >= 0, all
   finite, and 1/fs <= max_dt). */
int tcf_vqf_init(tcf_vqf_t *f, const tcf_vqf_params_t *p);

/* Reset the state, keep the coefficients. */
void tcf_vqf_reset(tcf_vqf_t *f);

/* One sample at the nominal rate: gyr [rad/s], acc [m/s^2], mag (NULL: no magnetometer for
   this sample; always NULL gives the 6D result, as delta stays 0). */
void tcf_vqf_update(tcf_vqf_t *f, const float gyr[3], const float acc[3], const float mag[3]);

/* Same with the actual time step dt [s] of the gyro integration (the filters and timers keep
   the nominal Ts, as the Python filter). */
void tcf_vqf_update_dt(tcf_vqf_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt);

/* The modulated coefficients at the settings' values (the core without learning). */
void tcf_vqf_base_mod(const tcf_vqf_t *f, tcf_vqf_mod_t *m);

/* The modulated coefficients for time constants tau_acc, tau_mag [s] (> 0) and the motion-bias
   standard deviation sigma_motion [rad/s] (> 0), with the formulas of tcf_vqf_init (float32):
   the tau_acc Butterworth low-pass, k_mag = 1 - exp(-Ts / tau_mag), W_motion = s^4 / V + s^2
   and W_vertical = W_motion * (W_vertical / W_motion of the settings); rest thresholds as set. */
void tcf_vqf_mod_from(const tcf_vqf_t *f, float tau_acc, float tau_mag, float sigma_motion, tcf_vqf_mod_t *m);
/* Its parts for one time constant [s] (> 0): the tau_acc low-pass, and k_mag = 1 - exp(-Ts / tau_mag) */
tcf_vqf_lp_coef_t tcf_vqf_acc_lp_from(const tcf_vqf_t *f, float tau_acc);
float tcf_vqf_k_mag_from(const tcf_vqf_t *f, float tau_mag);

/* One sample with the coefficients *m instead of the settings' ones (tcf_vqf_update_dt is this
   with tcf_vqf_base_mod). *m may change from one call to the next: the low-pass states (level
   and increment, see "Low-pass filters" above) run on with the new tau_acc coefficients, as in
   the Python filter, so the output stays continuous. */
void tcf_vqf_update_mod(tcf_vqf_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt,
                        const tcf_vqf_mod_t *m);

/* out = v rotated from sensor to earth by the unit quaternion q [w, x, y, z] (out may alias v). */
void tcf_vqf_rotate(const float q[4], const float v[3], float out[3]);

/* Current orientation q[4] = [w x y z], sensor -> ENU (identity before the first sample). */
void tcf_vqf_quat(const tcf_vqf_t *f, float q[4]);

/* Gyro bias estimate b[3] [rad/s]; returns its standard deviation [rad/s] (sqrt of the largest
   variance, the Python filter's bias_sigma). */
float tcf_vqf_bias(const tcf_vqf_t *f, float b[3]);

/* 1 at rest (rest detection enabled and the thresholds held for rest_min_t), else 0. */
int tcf_vqf_rest(const tcf_vqf_t *f);

/* 1 while the magnetic field is taken as disturbed (also before the first reference), 0 in
   6D (use_mag = 0). */
int tcf_vqf_mag_disturbed(const tcf_vqf_t *f);

/* Heading offset delta [rad] between the 6D and the 9D earth frame. */
float tcf_vqf_delta(const tcf_vqf_t *f);

#ifdef __cplusplus
}
#endif

#endif /* TCF_VQF_H */
