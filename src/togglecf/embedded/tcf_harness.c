/* tcf_harness.c: host program that runs the exported filter over a CSV file (C99).
 *
 *   tcf_harness [--no-mag] [--diag] [--time] [--features feat.csv] [--pred pred.csv] in.csv out.csv
 *
 * in.csv: a header line, then one row per sample at TCF_FS Hz with the columns
 *   gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z   (rad/s, m/s^2, uT)
 * or only the six gyr/acc columns (no magnetometer: mag = NULL). An empty field, "nan" or
 * "inf" makes a bad sample (handled by the filter's bad-sample policy).
 * out.csv: a header line, then w,x,y,z per sample (sensor -> ENU).
 * Options:
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
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#define TCF_CSV_READ /* tcf_csv_read */
#include "tcf_csv.h"
#include "tcf_filter.h"

#define N_DIAG (TCF_N_PRED + 3)

static const char *class_names[TCF_N_CLASSES] = TCF_CLASS_NAMES_INIT;

int main(int argc, char **argv) {
  const char *in_path = NULL, *out_path = NULL, *feat_path = NULL, *pred_path = NULL;
  int no_mag = 0, diag = 0, timing = 0, i, k;
  long n = 0, s;
  float *x = NULL, *px = NULL, *qo = NULL, *dg = NULL;
  FILE *fout, *ffeat = NULL;
  tcf_filter_t f;
  clock_t t0, t1;

  for (i = 1; i < argc; ++i) {
    if (strcmp(argv[i], "--no-mag") == 0) no_mag = 1;
    else if (strcmp(argv[i], "--diag") == 0) diag = 1;
    else if (strcmp(argv[i], "--time") == 0) timing = 1;
    else if (strcmp(argv[i], "--features") == 0 && i + 1 < argc) feat_path = argv[++i];
    else if (strcmp(argv[i], "--pred") == 0 && i + 1 < argc) pred_path = argv[++i];
    else if (argv[i][0] == '-' && argv[i][1] != '\0') {
      fprintf(stderr, "tcf_harness: unknown option %s (or its argument is missing)\n", argv[i]);
      return 2;
    } else if (!in_path) in_path = argv[i];
    else if (!out_path) out_path = argv[i];
    else {
      fprintf(stderr, "tcf_harness: too many arguments\n");
      return 2;
    }
  }
  if (!in_path || !out_path) {
    fprintf(stderr, "usage: tcf_harness [--no-mag] [--diag] [--time] [--features feat.csv] [--pred pred.csv] "
                    "in.csv out.csv\n  in.csv: header + gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z[,mag_x,mag_y,mag_z] per "
                    "sample (rad/s, m/s^2, uT) at %g Hz\n", (double)TCF_FS);
    return 2;
  }

  if (tcf_csv_read_learned_inputs("tcf_harness", in_path, pred_path, TCF_N_PRED, &x, &n, &no_mag, &px)) return 1;
  qo = (float *)malloc(sizeof(float) * 4 * (size_t)(n ? n : 1));
  dg = (float *)malloc(sizeof(float) * N_DIAG * (size_t)(n ? n : 1));
  if (!qo || !dg) {
    free(x); free(px); free(qo); free(dg);
    return tcf_csv_fail("tcf_harness", in_path, 0, "out of memory", NULL);
  }
  if (feat_path) {
    ffeat = fopen(feat_path, "w");
    if (!ffeat) {
      free(x); free(px); free(qo); free(dg);
      return tcf_csv_fail("tcf_harness", feat_path, 0, "cannot write:", strerror(errno));
    }
  }

  tcf_filter_init(&f);
  t0 = clock();
  for (s = 0; s < n; ++s) {
    const float *r = x + 9 * s;
    if (px)
      tcf_filter_update_pred(&f, r, r + 3, no_mag ? NULL : r + 6, TCF_DT, px + (long)TCF_N_PRED * s);
    else
      tcf_filter_update(&f, r, r + 3, no_mag ? NULL : r + 6);
    tcf_filter_quat(&f, qo + 4 * s);
    if (ffeat && !px && f.feat.n_filled == TCF_WINDOW && f.feat.hop_phase == 1u % TCF_HOP) {  /* a window end */
      float feat[TCF_N_FEATURES];
      tcf_filter_features(&f, feat);
      fprintf(ffeat, "%ld", s);
      for (k = 0; k < TCF_N_FEATURES; ++k) fprintf(ffeat, ",%.9g", (double)feat[k]);
      fputc('\n', ffeat);
    }
    if (diag) {
      float *d = dg + N_DIAG * s;
      tcf_filter_prediction(&f, d);
      d[TCF_N_PRED] = f.alpha_acc;
      d[TCF_N_PRED + 1] = f.alpha_mag;
      d[TCF_N_PRED + 2] = (float)tcf_features_fallback(&f.feat);
    }
  }
  t1 = clock();
  if (timing)
    fprintf(stderr, "tcf_harness: %ld samples, %.1f ns/sample (tcf_filter_update, clock()), state %u bytes\n", n,
            n ? 1e9 * (double)(t1 - t0) / CLOCKS_PER_SEC / (double)n : 0.0, (unsigned)sizeof(tcf_filter_t));
  if (ffeat && fclose(ffeat) != 0) {
    free(x); free(px); free(qo); free(dg);
    return tcf_csv_fail("tcf_harness", feat_path, 0, "write failed:", strerror(errno));
  }

  fout = fopen(out_path, "w");
  if (!fout) {
    free(x); free(px); free(qo); free(dg);
    return tcf_csv_fail("tcf_harness", out_path, 0, "cannot write:", strerror(errno));
  }
  fputs("w,x,y,z", fout);
  if (diag) {
    for (k = 0; k < TCF_N_CLASSES; ++k) fprintf(fout, ",p_%s", class_names[k]);
    fputs(",eta_acc_x,eta_acc_y,eta_acc_z,eta_mag_x,eta_mag_y,eta_mag_z,alpha_acc,alpha_mag,fallback", fout);
  }
  fputc('\n', fout);
  tcf_csv_write_rows(fout, qo, dg, n, N_DIAG, diag);
  free(x); free(px); free(qo); free(dg);
  if (fclose(fout) != 0) return tcf_csv_fail("tcf_harness", out_path, 0, "write failed:", strerror(errno));
  return 0;
}
