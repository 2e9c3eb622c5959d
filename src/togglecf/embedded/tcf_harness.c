/* tcf_harness.c: host program that runs the exported filter over a CSV file (C99).
 *
 *   tcf_harness [--fs HZ] [--no-mag] [--diag] [--time] [--features feat.csv] [--pred pred.csv] in.csv out.csv
 *
 * in.csv: a header line, then one row per sample at the rate --fs (default TCF_DEFAULT_FS of
 * tcf_config.h) with the columns
 *   gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z   (rad/s, m/s^2, uT)
 * or only the six gyr/acc columns (no magnetometer: mag = NULL), either optionally with a last
 * column dt [s]: the time step of each sample (tcf_filter_update_dt; without it
 * tcf_filter_update, dt = 1 / fs). An empty field, "nan" or "inf" makes a bad sample (handled
 * by the filter's bad-sample policy).
 * out.csv: a header line, then w,x,y,z per sample (sensor -> ENU).
 * Options:
 *   --fs HZ          the rate passed to tcf_filter_init (an error above TCF_MAX_FS);
 *   --no-mag         pass mag = NULL even when the file has mag columns;
 *   --diag           add the held prediction (p_<class>..., eta_acc_xyz, eta_mag_xyz), the
 *                    gains used (alpha_acc, alpha_mag) and fallback (1: the held window was out
 *                    of the training range, no prediction) to out.csv;
 *   --time           print the filter's time per sample (the update calls only, clock()) to stderr;
 *   --features F     write the feature row of every window end (sample index, TCF_N_FEATURES
 *                    values) to F (slows the loop: do not combine with --time);
 *   --pred P         drive the toggling step with the predictions of P (header + one row of
 *                    TCF_N_PRED values per sample) instead of the trees (tcf_filter_update_pred):
 *                    checks the filter arithmetic on its own.
 * Exit status: 0 ok, 1 bad input/output file, 2 bad usage.
 *
 * The filter itself needs no heap; this harness allocates the input and output arrays.
 */
#define TCF_CSV_LEARNED_INPUTS /* tcf_csv_learned_begin */
#include "tcf_csv.h"
#include "tcf_filter.h"

#define PROG "tcf_harness"
#define N_DIAG (TCF_N_PRED + 3)

static const char *const class_names[TCF_N_CLASSES] = TCF_CLASS_NAMES_INIT;

int main(int argc, char **argv) {
  const char *feat_path = NULL, *fs_arg = NULL;
  const tcf_csv_option_t opts[2] = {{"--features", NULL, &feat_path}, {"--fs", NULL, &fs_arg}};
  float fs = (float)TCF_DEFAULT_FS;
  int status, k;
  long s;
  FILE *ffeat = NULL;
  tcf_csv_learned_t h;
  static tcf_filter_t f;
  clock_t t0, t1;

  h.n_diag = N_DIAG;
  status = tcf_csv_learned_begin(PROG, argc, argv, opts, 2, "[--fs HZ] [--no-mag] [--diag] [--time] [--features "
                                 "feat.csv] [--pred pred.csv] in.csv out.csv", (double)TCF_DEFAULT_FS, TCF_N_PRED, &h);
  if (status) return status;
  if (fs_arg) fs = strtof(fs_arg, NULL);
  status = tcf_filter_init(&f, fs);
  if (status != TCF_OK) {
    tcf_csv_learned_free(&h);
    fprintf(stderr, PROG ": tcf_filter_init(fs = %g Hz) returned %d (%s)\n", (double)fs, status,
            status == TCF_ERR_RATE_MAX ? "above TCF_MAX_FS" : status == TCF_ERR_RATE ? "not a rate" : "1/fs > TCF_MAX_DT");
    return 1;
  }
  if (feat_path) {
    ffeat = fopen(feat_path, "w");
    if (!ffeat) {
      tcf_csv_learned_free(&h);
      return tcf_csv_fail(PROG, feat_path, 0, "cannot write:", strerror(errno));
    }
  }

  t0 = clock();
  for (s = 0; s < h.n; ++s) {
    const float *r = h.x + 9 * s;
    if (h.px)
      tcf_filter_update_pred(&f, r, r + 3, h.no_mag ? NULL : r + 6, h.dt ? h.dt[s] : f.c.ts,
                             h.px + (long)TCF_N_PRED * s);
    else if (h.dt)
      tcf_filter_update_dt(&f, r, r + 3, h.no_mag ? NULL : r + 6, h.dt[s]);
    else
      tcf_filter_update(&f, r, r + 3, h.no_mag ? NULL : r + 6);
    tcf_filter_quat(&f, h.qo + 4 * s);
    if (ffeat && !h.px && f.feat.n_filled == f.feat.rate.window && f.feat.hop_phase == 1u % f.feat.rate.hop) {  /* a window end */
      float feat[TCF_N_FEATURES];
      tcf_filter_features(&f, feat);
      fprintf(ffeat, "%ld", s);
      for (k = 0; k < TCF_N_FEATURES; ++k) fprintf(ffeat, ",%.9g", (double)feat[k]);
      fputc('\n', ffeat);
    }
    if (h.diag) {
      float *d = h.dg + N_DIAG * s;
      tcf_filter_prediction(&f, d);
      d[TCF_N_PRED] = f.alpha_acc;
      d[TCF_N_PRED + 1] = f.alpha_mag;
      d[TCF_N_PRED + 2] = (float)tcf_features_fallback(&f.feat);
    }
  }
  t1 = clock();
  if (h.timing) tcf_csv_print_time(PROG, "tcf_filter_update", h.n, t0, t1, (unsigned)sizeof(tcf_filter_t));
  if (ffeat && fclose(ffeat) != 0) {
    tcf_csv_learned_free(&h);
    return tcf_csv_fail(PROG, feat_path, 0, "write failed:", strerror(errno));
  }
  return tcf_csv_learned_end(PROG, &h, class_names, TCF_N_CLASSES,
                             ",eta_acc_x,eta_acc_y,eta_acc_z,eta_mag_x,eta_mag_y,eta_mag_z,alpha_acc,alpha_mag,fallback");
}
