/* CSV helpers of the host harnesses (tcf_harness.c, tcf_vqf_harness.c, tcf_vqf_toggling_harness.c);
   host only, not firmware. Every function is static: include this header in one translation unit;
   define TCF_CSV_READ before it for the whole-file reader tcf_csv_read. */
#ifndef TCF_CSV_H
#define TCF_CSV_H

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* print "<prog>: <path>[:<line>]: <msg> <detail>" to stderr; returns 1 (the exit status) */
static int tcf_csv_fail(const char *prog, const char *path, long line, const char *msg, const char *detail) {
  if (line > 0)
    fprintf(stderr, "%s: %s:%ld: %s%s%s\n", prog, path, line, msg, detail ? " " : "", detail ? detail : "");
  else
    fprintf(stderr, "%s: %s: %s%s%s\n", prog, path, msg, detail ? " " : "", detail ? detail : "");
  return 1;
}

static int tcf_csv_count_fields(const char *s) {
  int n = 1;
  for (; *s; ++s)
    if (*s == ',') ++n;
  return n;
}

static void tcf_csv_strip_eol(char *s) {
  size_t n = strlen(s);
  while (n > 0 && (s[n - 1] == '\n' || s[n - 1] == '\r')) s[--n] = '\0';
}

/* parse one field [b, e): empty -> NaN; returns 0 (and leaves *out) if it is not a number */
static int tcf_csv_parse_field(const char *b, const char *e, float *out) {
  char buf[128], *end;
  size_t n;
  double v;
  while (b < e && (*b == ' ' || *b == '\t')) ++b;
  while (e > b && (e[-1] == ' ' || e[-1] == '\t')) --e;
  n = (size_t)(e - b);
  if (n == 0) {
    *out = NAN;
    return 1;
  }
  if (n >= sizeof buf) return 0;
  memcpy(buf, b, n);
  buf[n] = '\0';
  v = strtod(buf, &end);
  if (*end != '\0') return 0;
  *out = (float)v;
  return 1;
}

/* The output rows of a harness: w,x,y,z (qo: 4 per sample) and, with diag, the sample's n_diag
   diagnostics (dg: n_diag per sample), one line per sample, %.9g (float32 round-trips). */
static void tcf_csv_write_rows(FILE *f, const float *qo, const float *dg, long n, int n_diag, int diag) {
  long s;
  int k;
  for (s = 0; s < n; ++s) {
    const float *q = qo + 4 * s;
    fprintf(f, "%.9g,%.9g,%.9g,%.9g", (double)q[0], (double)q[1], (double)q[2], (double)q[3]);
    if (diag)
      for (k = 0; k < n_diag; ++k) fprintf(f, ",%.9g", (double)dg[(long)n_diag * s + k]);
    fputc('\n', f);
  }
}

#ifdef TCF_CSV_READ
#include <errno.h>

#define TCF_CSV_LINE_MAX 8192

/* Read a CSV file with a header line whose column count is one of allowed[0..n_allowed-1]
   into *rows (stride = the largest allowed count; missing columns are 0). Returns 0 on
   success (*n_rows, *n_cols set) or 1 after printing an error naming the file and line. */
static int tcf_csv_read(const char *prog, const char *path, const int *allowed, int n_allowed, const char *expected,
                        float **rows, long *n_rows, int *n_cols) {
  char line[TCF_CSV_LINE_MAX];
  long lineno = 1, n = 0, cap = 0;
  int stride = 0, i, k, ok = 0;
  float *x = NULL;
  FILE *fin = fopen(path, "r");
  if (!fin) return tcf_csv_fail(prog, path, 0, "cannot open:", strerror(errno));
  if (!fgets(line, sizeof line, fin)) {
    fclose(fin);
    return tcf_csv_fail(prog, path, 0, "empty file: expected a header line such as", expected);
  }
  tcf_csv_strip_eol(line);
  *n_cols = tcf_csv_count_fields(line);
  for (i = 0; i < n_allowed; ++i) {
    if (allowed[i] == *n_cols) ok = 1;
    if (allowed[i] > stride) stride = allowed[i];
  }
  if (!ok) {
    char msg[160];
    sprintf(msg, "header has %d columns, expected %s; header:", *n_cols, expected);
    fclose(fin);
    return tcf_csv_fail(prog, path, 1, msg, line);
  }
  while (fgets(line, sizeof line, fin)) {
    const char *b;
    float *row;
    ++lineno;
    if (strchr(line, '\n') == NULL && !feof(fin)) {
      fclose(fin);
      free(x);
      return tcf_csv_fail(prog, path, lineno, "line too long", NULL);
    }
    tcf_csv_strip_eol(line);
    if (line[0] == '\0') continue;  /* blank lines (e.g. at the end) */
    if (tcf_csv_count_fields(line) != *n_cols) {
      char msg[64];
      sprintf(msg, "expected %d fields, got %d:", *n_cols, tcf_csv_count_fields(line));
      fclose(fin);
      free(x);
      return tcf_csv_fail(prog, path, lineno, msg, line);
    }
    if (n == cap) {
      float *grown;
      cap = cap ? 2 * cap : 4096;
      grown = (float *)realloc(x, sizeof(float) * (size_t)stride * (size_t)cap);
      if (!grown) {
        fclose(fin);
        free(x);
        return tcf_csv_fail(prog, path, lineno, "out of memory", NULL);
      }
      x = grown;
    }
    row = x + (long)stride * n;
    b = line;
    for (k = 0; k < *n_cols; ++k) {
      const char *e = strchr(b, ',');
      if (!e) e = b + strlen(b);
      if (!tcf_csv_parse_field(b, e, row + k)) {
        char msg[64];
        sprintf(msg, "column %d is not a number:", k + 1);
        fclose(fin);
        free(x);
        return tcf_csv_fail(prog, path, lineno, msg, line);
      }
      b = *e ? e + 1 : e;
    }
    for (; k < stride; ++k) row[k] = 0.0f;
    ++n;
  }
  fclose(fin);
  *rows = x;
  *n_rows = n;
  return 0;
}
/* The inputs of a learned filter's harness: the IMU CSV (9 columns, or 6 without mag: then
   *no_mag = 1; rows of 9 floats in *x) and, with pred_path, the prediction CSV of n_pred columns
   with one row per sample (*px; NULL without pred_path). Returns 0, or 1 after printing the
   error (nothing left allocated). */
static int tcf_csv_read_learned_inputs(const char *prog, const char *in_path, const char *pred_path, int n_pred,
                                       float **x, long *n, int *no_mag, float **px) {
  static const int imu_cols[2] = {6, 9};
  int n_cols, n_pcols;
  long n_rows;
  *px = NULL;
  if (tcf_csv_read(prog, in_path, imu_cols, 2, "9 (gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z) or 6 (no mag)",
                   x, n, &n_cols))
    return 1;
  if (n_cols == 6) *no_mag = 1;
  if (pred_path) {
    if (tcf_csv_read(prog, pred_path, &n_pred, 1, "TCF_N_PRED (class probabilities, eta_acc xyz, eta_mag xyz)", px,
                     &n_rows, &n_pcols)) {
      free(*x);
      return 1;
    }
    if (n_rows != *n) {
      char msg[96];
      sprintf(msg, "has %ld prediction rows for %ld samples", n_rows, *n);
      free(*x); free(*px);
      return tcf_csv_fail(prog, pred_path, 0, msg, NULL);
    }
  }
  return 0;
}

#endif /* TCF_CSV_READ */

#endif /* TCF_CSV_H */
