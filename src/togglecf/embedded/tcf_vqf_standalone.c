/* tcf_vqf_standalone.c: the parts of the VQF core API (tcf_vqf.h) that only a standalone use needs:
 * default parameters, the update at the settings' own coefficients (tcf_vqf_update,
 * tcf_vqf_update_dt) and the bias and heading-offset getters. A separate file so that a firmware
 * build of the learned filter (tcf_vqf_toggling.c: it sets the parameters from its generated config,
 * updates with modulated coefficients and reads the orientation, rest and disturbance flags)
 * compiles only tcf_vqf.c.
 */
#include <math.h>
#include "tcf_vqf.h"

void tcf_vqf_params_default(tcf_vqf_params_t *p, float fs) {
  p->fs = fs;
  p->max_dt = 0.1f;
  p->use_mag = 1;
  p->tau_acc = 3.0f;
  p->tau_mag = 9.0f;
  p->motion_bias_est_enabled = 1;
  p->rest_bias_est_enabled = 1;
  p->mag_dist_rejection_enabled = 1;
  p->bias_sigma_init = 0.5f;
  p->bias_forgetting_time = 100.0f;
  p->bias_clip = 2.0f;
  p->bias_sigma_motion = 0.1f;
  p->bias_vertical_forgetting_factor = 0.0001f;
  p->bias_sigma_rest = 0.03f;
  p->rest_min_t = 1.5f;
  p->rest_filter_tau = 0.5f;
  p->rest_th_gyr = 2.0f;
  p->rest_th_acc = 0.5f;
  p->mag_current_tau = 0.05f;
  p->mag_ref_tau = 20.0f;
  p->mag_norm_th = 0.1f;
  p->mag_dip_th = 10.0f;
  p->mag_new_time = 20.0f;
  p->mag_new_first_time = 5.0f;
  p->mag_new_min_gyr = 20.0f;
  p->mag_min_undisturbed_time = 0.5f;
  p->mag_max_rejection_time = 60.0f;
  p->mag_rejection_factor = 2.0f;
}

float tcf_vqf_bias(const tcf_vqf_t *f, float b[3]) {
  float m = f->bias_p[0];
  if (f->bias_p[4] > m) m = f->bias_p[4];
  if (f->bias_p[8] > m) m = f->bias_p[8];
  b[0] = f->bias[0]; b[1] = f->bias[1]; b[2] = f->bias[2];
  return sqrtf(m > 0.0f ? m : 0.0f);
}

float tcf_vqf_delta(const tcf_vqf_t *f) { return f->delta; }

void tcf_vqf_update(tcf_vqf_t *f, const float gyr[3], const float acc[3], const float mag[3]) {
  tcf_vqf_update_dt(f, gyr, acc, mag, f->c.ts);
}

void tcf_vqf_update_dt(tcf_vqf_t *f, const float gyr[3], const float acc[3], const float mag[3], float dt) {
  tcf_vqf_mod_t m;
  tcf_vqf_base_mod(f, &m);
  tcf_vqf_update_mod(f, gyr, acc, mag, dt, &m);
}
