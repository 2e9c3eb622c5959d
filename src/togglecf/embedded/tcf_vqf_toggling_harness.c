/* tcf_vqf_toggling_harness.c: host program that runs the exported learned VQF filter
 * (tcf_vqf_toggling.c) over a CSV file (C99).
 *
 *   tcf_vqf_toggling_harness [--fs HZ] [--no-mag] [--diag] [--time] [--pred pred.csv] in.csv out.csv
 *
 * in.csv: the format of tcf_harness.c: a header line, then one row per sample at the rate --fs
 *   (default TCF_DEFAULT_FS of tcf_config.h)
 *   gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z   (rad/s, m/s^2, uT)
 * or only the six gyr/acc columns (mag = NULL), either optionally with a last column dt [s]: the
 * time step of each sample (tcf_vqft_update_dt; without it tcf_vqft_update, dt = 1 / fs).
 * An empty field, "nan" or "inf" makes a bad sample.
 * out.csv: a header line, then w,x,y,z per sample (sensor -> ENU).
 * Options:
 *   --fs HZ    the rate passed to tcf_vqft_init (an error above TCF_MAX_FS);
 *   --no-mag   pass mag = NULL even when the file has mag columns;
 *   --diag     add the held prediction (p_<class>..., eta_acc_xyz, eta_mag_xyz), tau_acc, tau_mag,
 *              trust (lambda), fallback (1: the held window was out of the training range), rest
 *              and mag_dist to out.csv;
 *   --time     print the filter's time per sample (the update calls only, clock()) to stderr;
 *   --pred P   drive steps 1-5 with the predictions of P (header + one row of TCF_N_PRED values
 *              per sample) instead of the trees (tcf_vqft_update_pred).
 * Exit status: 0 ok, 1 bad input/output file, 2 bad usage.
 *
 * The filter itself needs no heap; this harness allocates the input and output arrays.
 */
#define TCF_CSV_LEARNED_INPUTS /* tcf_csv_learned_begin */
#include "tcf_csv.h"
#include "tcf_vqf_toggling.h"

#define PROG "tcf_vqf_toggling_harness"
#define N_DIAG (TCF_N_PRED + 6)

static const char *const class_names[TCF_N_CLASSES] = TCF_CLASS_NAMES_INIT;

int main(int argc, char **argv) {
  const char *fs_arg = NULL;
  const tcf_csv_option_t fs_opt = {"--fs", NULL, &fs_arg};
  float fs = (float)TCF_DEFAULT_FS;
  int status;
  long s;
  tcf_csv_learned_t h;
  static tcf_vqft_t f;
  clock_t t0, t1;

  h.n_diag = N_DIAG;
  status = tcf_csv_learned_begin(PROG, argc, argv, &fs_opt, 1, "[--fs HZ] [--no-mag] [--diag] [--time] [--pred "
                                 "pred.csv] in.csv out.csv", (double)TCF_DEFAULT_FS, TCF_N_PRED, &h);
  if (status) return status;
  if (fs_arg) fs = strtof(fs_arg, NULL);
  status = tcf_vqft_init(&f, fs);
  if (status != TCF_OK) {
    tcf_csv_learned_free(&h);
    fprintf(stderr, PROG ": tcf_vqft_init(fs = %g Hz) returned %d (%s)\n", (double)fs, status,
            status == TCF_ERR_RATE_MAX ? "above TCF_MAX_FS" : status == TCF_ERR_RATE ? "not a rate" : "settings");
    return 1;
  }
  t0 = clock();
  for (s = 0; s < h.n; ++s) {
    const float *r = h.x + 9 * s;
    if (h.px)
      tcf_vqft_update_pred(&f, r, r + 3, h.no_mag ? NULL : r + 6, h.dt ? h.dt[s] : f.core.c.ts,
                           h.px + (long)TCF_N_PRED * s);
    else if (h.dt)
      tcf_vqft_update_dt(&f, r, r + 3, h.no_mag ? NULL : r + 6, h.dt[s]);
    else
      tcf_vqft_update(&f, r, r + 3, h.no_mag ? NULL : r + 6);
    tcf_vqft_quat(&f, h.qo + 4 * s);
    if (h.diag) {
      float *d = h.dg + N_DIAG * s;
      tcf_vqft_prediction(&f, d);
      d[TCF_N_PRED] = f.tau_acc_now;
      d[TCF_N_PRED + 1] = f.tau_mag_now;
      d[TCF_N_PRED + 2] = f.trust_now;
      d[TCF_N_PRED + 3] = (float)tcf_features_fallback(&f.feat);
      d[TCF_N_PRED + 4] = (float)tcf_vqf_rest(&f.core);
      d[TCF_N_PRED + 5] = (float)tcf_vqf_mag_disturbed(&f.core);
    }
  }
  t1 = clock();
  if (h.timing) tcf_csv_print_time(PROG, "tcf_vqft_update", h.n, t0, t1, (unsigned)sizeof(tcf_vqft_t));
  return tcf_csv_learned_end(PROG, &h, class_names, TCF_N_CLASSES,
                             ",eta_acc_x,eta_acc_y,eta_acc_z,eta_mag_x,eta_mag_y,eta_mag_z,tau_acc,tau_mag,trust,"
                             "fallback,rest,mag_dist");
}
