/* tcf_vqf_harness.c: host program that runs the C VQF core (tcf_vqf.c) over a CSV file (C99).
 *
 *   tcf_vqf_harness [--6d] [--no-mag] [--diag] [--time] in.csv out.csv
 *
 * in.csv: the format of tcf_harness.c: a header line, then one row per sample at TCF_VQF_FS Hz
 *   gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z   (rad/s, m/s^2, uT)
 * or only the six gyr/acc columns (mag = NULL); optionally a last column named "dt" [s] with
 * each sample's time step (tcf_vqf_update_dt; otherwise tcf_vqf_update). An empty field, "nan"
 * or "inf" makes a bad sample (handled by the filter's bad-sample policy).
 * out.csv: a header line, then w,x,y,z per sample (sensor -> ENU).
 * Options:
 *   --6d      use_mag = 0 (6D output; the settings are otherwise those of tcf_vqf_config.h);
 *   --no-mag  pass mag = NULL even when the file has mag columns;
 *   --diag    add rest,mag_dist,bias_x,bias_y,bias_z,bias_sigma,delta,k_mag per sample
 *             (the diagnostics of VQFCoreFilter);
 *   --time    print the filter's time per sample (the update calls only, clock()) to stderr.
 * Exit status: 0 ok, 1 bad input/output file or settings, 2 bad usage.
 *
 * The filter needs no heap; this harness allocates the input and output arrays.
 */
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include "tcf_csv.h"
#include "tcf_vqf.h"
#include "tcf_vqf_config.h"

#define LINE_MAX_CHARS 4096
#define MAX_COLS 10
#define N_DIAG 8

/* rows of MAX_COLS floats: gyr, acc, mag (0 when absent), dt (NaN when absent) */
static int read_imu_csv(const char *path, float **rows, long *n_rows, int *has_mag, int *has_dt) {
  char line[LINE_MAX_CHARS];
  long lineno = 1, n = 0, cap = 0;
  int n_cols, k;
  float *x = NULL;
  const char *last;
  FILE *fin = fopen(path, "r");
  if (!fin) return tcf_csv_fail("tcf_vqf_harness", path, 0, "cannot open:", strerror(errno));
  if (!fgets(line, sizeof line, fin)) {
    fclose(fin);
    return tcf_csv_fail("tcf_vqf_harness", path, 0, "empty file: expected a header line such as", "gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z[,mag_x,"
                "mag_y,mag_z][,dt]");
  }
  tcf_csv_strip_eol(line);
  n_cols = tcf_csv_count_fields(line);
  last = strrchr(line, ',');
  last = last ? last + 1 : line;
  while (*last == ' ') ++last;
  *has_dt = strcmp(last, "dt") == 0;
  *has_mag = n_cols - *has_dt == 9;
  if (n_cols - *has_dt != 6 && n_cols - *has_dt != 9) {
    fclose(fin);
    return tcf_csv_fail("tcf_vqf_harness", path, 1, "expected 6 (gyr, acc) or 9 (gyr, acc, mag) columns, optionally + dt; header:", line);
  }
  while (fgets(line, sizeof line, fin)) {
    const char *b;
    float *row, v[MAX_COLS];
    ++lineno;
    if (strchr(line, '\n') == NULL && !feof(fin)) {
      fclose(fin);
      free(x);
      return tcf_csv_fail("tcf_vqf_harness", path, lineno, "line too long", NULL);
    }
    tcf_csv_strip_eol(line);
    if (line[0] == '\0') continue;
    if (tcf_csv_count_fields(line) != n_cols) {
      fclose(fin);
      free(x);
      return tcf_csv_fail("tcf_vqf_harness", path, lineno, "wrong number of fields:", line);
    }
    b = line;
    for (k = 0; k < n_cols; ++k) {
      const char *e = strchr(b, ',');
      if (!e) e = b + strlen(b);
      if (!tcf_csv_parse_field(b, e, v + k)) {
        fclose(fin);
        free(x);
        return tcf_csv_fail("tcf_vqf_harness", path, lineno, "a field is not a number:", line);
      }
      b = *e ? e + 1 : e;
    }
    if (n == cap) {
      float *grown;
      cap = cap ? 2 * cap : 4096;
      grown = (float *)realloc(x, sizeof(float) * MAX_COLS * (size_t)cap);
      if (!grown) {
        fclose(fin);
        free(x);
        return tcf_csv_fail("tcf_vqf_harness", path, lineno, "out of memory", NULL);
      }
      x = grown;
    }
    row = x + (long)MAX_COLS * n;
    for (k = 0; k < 6; ++k) row[k] = v[k];
    for (k = 6; k < 9; ++k) row[k] = *has_mag ? v[k] : 0.0f;
    row[9] = *has_dt ? v[n_cols - 1] : NAN;
    ++n;
  }
  fclose(fin);
  *rows = x;
  *n_rows = n;
  return 0;
}

int main(int argc, char **argv) {
  static const tcf_vqf_params_t config = TCF_VQF_PARAMS_INIT;
  const char *in_path = NULL, *out_path = NULL;
  int six_d = 0, no_mag = 0, diag = 0, timing = 0, has_mag, has_dt, i;
  long n = 0, s;
  float *x = NULL, *qo = NULL, *dg = NULL;
  tcf_vqf_params_t params = config;
  tcf_vqf_t f;
  FILE *fout;
  clock_t t0, t1;

  for (i = 1; i < argc; ++i) {
    if (strcmp(argv[i], "--6d") == 0) six_d = 1;
    else if (strcmp(argv[i], "--no-mag") == 0) no_mag = 1;
    else if (strcmp(argv[i], "--diag") == 0) diag = 1;
    else if (strcmp(argv[i], "--time") == 0) timing = 1;
    else if (argv[i][0] == '-' && argv[i][1] != '\0') {
      fprintf(stderr, "tcf_vqf_harness: unknown option %s\n", argv[i]);
      return 2;
    } else if (!in_path) in_path = argv[i];
    else if (!out_path) out_path = argv[i];
    else {
      fprintf(stderr, "tcf_vqf_harness: too many arguments\n");
      return 2;
    }
  }
  if (!in_path || !out_path) {
    fprintf(stderr, "usage: tcf_vqf_harness [--6d] [--no-mag] [--diag] [--time] in.csv out.csv\n  in.csv: header + "
                    "gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z[,mag_x,mag_y,mag_z][,dt] per sample (rad/s, m/s^2, uT) "
                    "at %g Hz\n", (double)TCF_VQF_FS);
    return 2;
  }
  if (six_d) params.use_mag = 0;
  if (tcf_vqf_init(&f, &params) != 0) {
    fprintf(stderr, "tcf_vqf_harness: tcf_vqf_init rejected the settings of tcf_vqf_config.h\n");
    return 1;
  }
  if (read_imu_csv(in_path, &x, &n, &has_mag, &has_dt)) return 1;
  if (!has_mag) no_mag = 1;
  qo = (float *)malloc(sizeof(float) * 4 * (size_t)(n ? n : 1));
  dg = (float *)malloc(sizeof(float) * N_DIAG * (size_t)(n ? n : 1));
  if (!qo || !dg) {
    free(x); free(qo); free(dg);
    return tcf_csv_fail("tcf_vqf_harness", in_path, 0, "out of memory", NULL);
  }

  t0 = clock();
  for (s = 0; s < n; ++s) {
    const float *r = x + MAX_COLS * s;
    if (has_dt)
      tcf_vqf_update_dt(&f, r, r + 3, no_mag ? NULL : r + 6, r[9]);
    else
      tcf_vqf_update(&f, r, r + 3, no_mag ? NULL : r + 6);
    tcf_vqf_quat(&f, qo + 4 * s);
    if (diag) {
      float *d = dg + N_DIAG * s;
      d[0] = (float)tcf_vqf_rest(&f);
      d[1] = (float)tcf_vqf_mag_disturbed(&f);
      d[5] = tcf_vqf_bias(&f, d + 2);
      d[6] = tcf_vqf_delta(&f);
      d[7] = f.k_mag_last;
    }
  }
  t1 = clock();
  if (timing)
    fprintf(stderr, "tcf_vqf_harness: %ld samples, %.1f ns/sample (tcf_vqf_update, clock()), state %u bytes\n", n,
            n ? 1e9 * (double)(t1 - t0) / CLOCKS_PER_SEC / (double)n : 0.0, (unsigned)sizeof(tcf_vqf_t));

  fout = fopen(out_path, "w");
  if (!fout) {
    free(x); free(qo); free(dg);
    return tcf_csv_fail("tcf_vqf_harness", out_path, 0, "cannot write:", strerror(errno));
  }
  fputs(diag ? "w,x,y,z,rest,mag_dist,bias_x,bias_y,bias_z,bias_sigma,delta,k_mag\n" : "w,x,y,z\n", fout);
  tcf_csv_write_rows(fout, qo, dg, n, N_DIAG, diag);
  free(x); free(qo); free(dg);
  if (fclose(fout) != 0) return tcf_csv_fail("tcf_vqf_harness", out_path, 0, "write failed:", strerror(errno));
  return 0;
}
