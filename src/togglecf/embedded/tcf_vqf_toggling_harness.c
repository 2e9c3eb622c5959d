/* tcf_vqf_toggling_harness.c: host program that runs the exported learned VQF filter
 * (tcf_vqf_toggling.c) over a CSV file (C99).
 *
 *   tcf_vqf_toggling_harness [--no-mag] [--diag] [--time] [--pred pred.csv] in.csv out.csv
 *
 * in.csv: the format of tcf_harness.c: a header line, then one row per sample at TCF_FS Hz
 *   gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z   (rad/s, m/s^2, uT)
 * or only the six gyr/acc columns (mag = NULL). An empty field, "nan" or "inf" makes a bad sample.
 * out.csv: a header line, then w,x,y,z per sample (sensor -> ENU).
 * Options:
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
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#define TCF_CSV_READ /* tcf_csv_read */
#include "tcf_csv.h"
#include "tcf_vqf_toggling.h"

#define PROG "tcf_vqf_toggling_harness"
#define N_DIAG (TCF_N_PRED + 6)

static const char *class_names[TCF_N_CLASSES] = TCF_CLASS_NAMES_INIT;

int main(int argc, char **argv) {
  const char *in_path = NULL, *out_path = NULL, *pred_path = NULL;
  int no_mag = 0, diag = 0, timing = 0, i, k;
  long n = 0, s;
  float *x = NULL, *px = NULL, *qo = NULL, *dg = NULL;
  FILE *fout;
  static tcf_vqft_t f;
  clock_t t0, t1;

  for (i = 1; i < argc; ++i) {
    if (strcmp(argv[i], "--no-mag") == 0) no_mag = 1;
    else if (strcmp(argv[i], "--diag") == 0) diag = 1;
    else if (strcmp(argv[i], "--time") == 0) timing = 1;
    else if (strcmp(argv[i], "--pred") == 0 && i + 1 < argc) pred_path = argv[++i];
    else if (argv[i][0] == '-' && argv[i][1] != '\0') {
      fprintf(stderr, PROG ": unknown option %s (or its argument is missing)\n", argv[i]);
      return 2;
    } else if (!in_path) in_path = argv[i];
    else if (!out_path) out_path = argv[i];
    else {
      fprintf(stderr, PROG ": too many arguments\n");
      return 2;
    }
  }
  if (!in_path || !out_path) {
    fprintf(stderr, "usage: " PROG " [--no-mag] [--diag] [--time] [--pred pred.csv] in.csv out.csv\n  in.csv: header + "
                    "gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z[,mag_x,mag_y,mag_z] per sample (rad/s, m/s^2, uT) at %g Hz\n",
            (double)TCF_FS);
    return 2;
  }
  if (tcf_csv_read_learned_inputs(PROG, in_path, pred_path, TCF_N_PRED, &x, &n, &no_mag, &px)) return 1;
  qo = (float *)malloc(sizeof(float) * 4 * (size_t)(n ? n : 1));
  dg = (float *)malloc(sizeof(float) * N_DIAG * (size_t)(n ? n : 1));
  if (!qo || !dg) {
    free(x); free(px); free(qo); free(dg);
    return tcf_csv_fail(PROG, in_path, 0, "out of memory", NULL);
  }
  if (tcf_vqft_init(&f) != 0) {
    free(x); free(px); free(qo); free(dg);
    fprintf(stderr, PROG ": the core refused the settings of tcf_vqf_config.h\n");
    return 1;
  }
  t0 = clock();
  for (s = 0; s < n; ++s) {
    const float *r = x + 9 * s;
    if (px)
      tcf_vqft_update_pred(&f, r, r + 3, no_mag ? NULL : r + 6, TCF_DT, px + (long)TCF_N_PRED * s);
    else
      tcf_vqft_update(&f, r, r + 3, no_mag ? NULL : r + 6);
    tcf_vqft_quat(&f, qo + 4 * s);
    if (diag) {
      float *d = dg + N_DIAG * s;
      tcf_vqft_prediction(&f, d);
      d[TCF_N_PRED] = f.tau_acc;
      d[TCF_N_PRED + 1] = f.tau_mag;
      d[TCF_N_PRED + 2] = f.trust;
      d[TCF_N_PRED + 3] = (float)tcf_features_fallback(&f.feat);
      d[TCF_N_PRED + 4] = (float)tcf_vqf_rest(&f.core);
      d[TCF_N_PRED + 5] = (float)tcf_vqf_mag_disturbed(&f.core);
    }
  }
  t1 = clock();
  if (timing)
    fprintf(stderr, PROG ": %ld samples, %.1f ns/sample (tcf_vqft_update, clock()), state %u bytes\n", n,
            n ? 1e9 * (double)(t1 - t0) / CLOCKS_PER_SEC / (double)n : 0.0, (unsigned)sizeof(tcf_vqft_t));
  fout = fopen(out_path, "w");
  if (!fout) {
    free(x); free(px); free(qo); free(dg);
    return tcf_csv_fail(PROG, out_path, 0, "cannot write:", strerror(errno));
  }
  fputs("w,x,y,z", fout);
  if (diag) {
    for (k = 0; k < TCF_N_CLASSES; ++k) fprintf(fout, ",p_%s", class_names[k]);
    fputs(",eta_acc_x,eta_acc_y,eta_acc_z,eta_mag_x,eta_mag_y,eta_mag_z,tau_acc,tau_mag,trust,fallback,rest,mag_dist",
          fout);
  }
  fputc('\n', fout);
  tcf_csv_write_rows(fout, qo, dg, n, N_DIAG, diag);
  free(x); free(px); free(qo); free(dg);
  if (fclose(fout) != 0) return tcf_csv_fail(PROG, out_path, 0, "write failed:", strerror(errno));
  return 0;
}
