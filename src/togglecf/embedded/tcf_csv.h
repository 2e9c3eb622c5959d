/* The shared part of the host harnesses (tcf_harness.c, tcf_vqf_harness.c, tcf_vqf_toggling_harness.c):
   command line, CSV input and output, timing. Host only, not firmware. Every function is static:
   include this header in one translation unit, after defining the input layout the harness reads:
   TCF_CSV_LEARNED_INPUTS (tcf_csv_read_learned_inputs) or TCF_CSV_IMU_DT_INPUTS (tcf_csv_read_imu_dt);
   both read through tcf_csv_read. */
#ifndef TCF_CSV_H
#define TCF_CSV_H

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <errno.h>
#include <string.h>
#include <time.h>

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

/* A command-line option of a harness: a flag (value == NULL: sets *flag to 1) or, with value, an
   option taking the next argument (*value). */
typedef struct tcf_csv_option {
  const char *name;
  int *flag;
  const char **value;
} tcf_csv_option_t;

/* Parse the command line "prog [options] in.csv out.csv" with the n_opts options of opts.
   Returns 0, or 2 (the exit status for bad usage) after printing the problem; without the two
   paths, the usage: "usage: prog <usage>" and the input format (columns, at fs Hz). */
static int tcf_csv_args(const char *prog, int argc, char **argv, const tcf_csv_option_t *opts, int n_opts,
                        const char *usage, const char *columns, double fs, const char **in_path, const char **out_path) {
  int i, k;
  *in_path = NULL;
  *out_path = NULL;
  for (i = 1; i < argc; ++i) {
    for (k = 0; k < n_opts; ++k)
      if (strcmp(argv[i], opts[k].name) == 0 && (opts[k].value == NULL || i + 1 < argc)) break;
    if (k < n_opts) {
      if (opts[k].value) *opts[k].value = argv[++i];
      else *opts[k].flag = 1;
    } else if (argv[i][0] == '-' && argv[i][1] != '\0') {
      fprintf(stderr, "%s: unknown option %s (or its argument is missing)\n", prog, argv[i]);
      return 2;
    } else if (!*in_path) *in_path = argv[i];
    else if (!*out_path) *out_path = argv[i];
    else {
      fprintf(stderr, "%s: too many arguments\n", prog);
      return 2;
    }
  }
  if (!*in_path || !*out_path) {
    fprintf(stderr, "usage: %s %s\n  in.csv: header + %s per sample (rad/s, m/s^2, uT) at %g Hz\n", prog, usage,
            columns, fs);
    return 2;
  }
  return 0;
}

/* The output arrays of n samples: *qo (4 floats per sample) and *dg (n_diag per sample). Returns 0,
   or 1 after printing the error (nothing allocated). */
static int tcf_csv_alloc_out(const char *prog, const char *in_path, long n, int n_diag, float **qo, float **dg) {
  *qo = (float *)malloc(sizeof(float) * 4 * (size_t)(n ? n : 1));
  *dg = (float *)malloc(sizeof(float) * (size_t)n_diag * (size_t)(n ? n : 1));
  if (*qo && *dg) return 0;
  free(*qo);
  free(*dg);
  *qo = *dg = NULL;
  return tcf_csv_fail(prog, in_path, 0, "out of memory", NULL);
}

/* --time: the filter's time per sample over n samples (clock() readings t0, t1 around the update calls
   named by what) and its state size, to stderr */
static void tcf_csv_print_time(const char *prog, const char *what, long n, clock_t t0, clock_t t1, unsigned state_bytes) {
  fprintf(stderr, "%s: %ld samples, %.1f ns/sample (%s, clock()), state %u bytes\n", prog, n,
          n ? 1e9 * (double)(t1 - t0) / CLOCKS_PER_SEC / (double)n : 0.0, what, state_bytes);
}

/* Write out.csv: the header "w,x,y,z" (with diag: then ",p_<name>" for the n_classes class_names and
   diag_tail), then the rows of tcf_csv_write_rows. Returns 0, or 1 after printing the error. */
static int tcf_csv_write_output(const char *prog, const char *path, const char *const *class_names, int n_classes,
                                const char *diag_tail, const float *qo, const float *dg, long n, int n_diag, int diag) {
  int k;
  FILE *fout = fopen(path, "w");
  if (!fout) return tcf_csv_fail(prog, path, 0, "cannot write:", strerror(errno));
  fputs("w,x,y,z", fout);
  if (diag) {
    for (k = 0; k < n_classes; ++k) fprintf(fout, ",p_%s", class_names[k]);
    fputs(diag_tail, fout);
  }
  fputc('\n', fout);
  tcf_csv_write_rows(fout, qo, dg, n, n_diag, diag);
  if (fclose(fout) != 0) return tcf_csv_fail(prog, path, 0, "write failed:", strerror(errno));
  return 0;
}

#if defined(TCF_CSV_LEARNED_INPUTS) || defined(TCF_CSV_IMU_DT_INPUTS)

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
#endif /* tcf_csv_read */

#ifdef TCF_CSV_LEARNED_INPUTS
/* The inputs of a learned filter's harness: the IMU CSV (9 columns, or 6 without mag: then
   *no_mag = 1; rows of 9 floats in *x; a last column dt [s] makes 10 or 7: then *dt holds it per
   sample, else *dt = NULL) and, with pred_path, the prediction CSV of n_pred columns with one row
   per sample (*px; NULL without pred_path). Returns 0, or 1 after printing the error (nothing
   left allocated). */
static int tcf_csv_read_learned_inputs(const char *prog, const char *in_path, const char *pred_path, int n_pred,
                                       float **x, long *n, int *no_mag, float **dt, float **px) {
  static const int imu_cols[4] = {6, 7, 9, 10};
  int n_cols, n_pcols, k;
  long n_rows, s;
  *px = NULL;
  *dt = NULL;
  if (tcf_csv_read(prog, in_path, imu_cols, 4, "9 (gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z) or 6 "
                   "(no mag), optionally + dt", x, n, &n_cols))
    return 1;
  if (n_cols == 6 || n_cols == 7) *no_mag = 1;
  if (n_cols == 7 || n_cols == 10) {  /* the dt column */
    *dt = (float *)malloc(sizeof(float) * (size_t)(*n ? *n : 1));
    if (!*dt) {
      free(*x);
      return tcf_csv_fail(prog, in_path, 0, "out of memory", NULL);
    }
  }
  for (s = 0; s < *n; ++s) {  /* rows of 10 (tcf_csv_read's stride) -> gyr, acc, mag (0 without) in rows of 9 */
    const float *r = *x + 10 * s;
    float *o = *x + 9 * s, d = r[n_cols - 1];  /* forward and in place: o[k] overwrites nothing unread */
    for (k = 0; k < 9; ++k) o[k] = (k < 6 || n_cols >= 9) ? r[k] : 0.0f;
    if (*dt) (*dt)[s] = d;
  }
  if (pred_path) {
    if (tcf_csv_read(prog, pred_path, &n_pred, 1, "TCF_N_PRED (class probabilities, eta_acc xyz, eta_mag xyz)", px,
                     &n_rows, &n_pcols)) {
      free(*x); free(*dt);
      return 1;
    }
    if (n_rows != *n) {
      char msg[96];
      sprintf(msg, "has %ld prediction rows for %ld samples", n_rows, *n);
      free(*x); free(*px); free(*dt);
      return tcf_csv_fail(prog, pred_path, 0, msg, NULL);
    }
  }
  return 0;
}


/* A learned filter's harness run (tcf_harness.c, tcf_vqf_toggling_harness.c): its command line
   "[--no-mag] [--diag] [--time] [--pred pred.csv] [its own options] in.csv out.csv", the inputs and
   the output arrays. */
typedef struct tcf_csv_learned {
  const char *in_path, *out_path, *pred_path;
  int no_mag, diag, timing;
  int n_diag;    /* diagnostics per sample after w,x,y,z (set before tcf_csv_learned_begin) */
  long n;        /* samples */
  float *x;      /* inputs, 9 per sample: gyr, acc, mag (0 without; then no_mag = 1) */
  float *dt;     /* time step [s] per sample (the input's dt column; NULL without: the nominal step) */
  float *px;     /* predictions, n_pred per sample (NULL without --pred) */
  float *qo;     /* output quaternions, 4 per sample */
  float *dg;     /* output diagnostics, n_diag per sample */
} tcf_csv_learned_t;

#define TCF_CSV_MAX_OPTIONS 8

static void tcf_csv_learned_free(tcf_csv_learned_t *h) {
  free(h->x); free(h->px); free(h->qo); free(h->dg); free(h->dt);
  h->x = h->px = h->qo = h->dg = h->dt = NULL;
}

/* Parse the command line (the common options and the n_extra of extra; usage: its synopsis), read
   the inputs (n_pred prediction columns), allocate the outputs. Returns 0, or the exit status
   after printing the problem (nothing left allocated). */
static int tcf_csv_learned_begin(const char *prog, int argc, char **argv, const tcf_csv_option_t *extra, int n_extra,
                                 const char *usage, double fs, int n_pred, tcf_csv_learned_t *h) {
  tcf_csv_option_t opts[TCF_CSV_MAX_OPTIONS];
  int k, n_opts = 4, status;
  h->pred_path = NULL;
  h->no_mag = h->diag = h->timing = 0;
  h->x = h->px = h->qo = h->dg = h->dt = NULL;
  opts[0].name = "--no-mag"; opts[0].flag = &h->no_mag; opts[0].value = NULL;
  opts[1].name = "--diag"; opts[1].flag = &h->diag; opts[1].value = NULL;
  opts[2].name = "--time"; opts[2].flag = &h->timing; opts[2].value = NULL;
  opts[3].name = "--pred"; opts[3].flag = NULL; opts[3].value = &h->pred_path;
  for (k = 0; k < n_extra && n_opts < TCF_CSV_MAX_OPTIONS; ++k) opts[n_opts++] = extra[k];
  status = tcf_csv_args(prog, argc, argv, opts, n_opts, usage,
                        "gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z[,mag_x,mag_y,mag_z][,dt]", fs, &h->in_path, &h->out_path);
  if (status) return status;
  if (tcf_csv_read_learned_inputs(prog, h->in_path, h->pred_path, n_pred, &h->x, &h->n, &h->no_mag, &h->dt, &h->px))
    return 1;
  if (tcf_csv_alloc_out(prog, h->in_path, h->n, h->n_diag, &h->qo, &h->dg)) {
    tcf_csv_learned_free(h);
    return 1;
  }
  return 0;
}

/* Write out.csv (tcf_csv_write_output with the class names and diag_tail) and free the run's
   arrays; returns the exit status. */
static int tcf_csv_learned_end(const char *prog, tcf_csv_learned_t *h, const char *const *class_names, int n_classes,
                               const char *diag_tail) {
  int status = tcf_csv_write_output(prog, h->out_path, class_names, n_classes, diag_tail, h->qo, h->dg, h->n,
                                    h->n_diag, h->diag);
  tcf_csv_learned_free(h);
  return status;
}
#endif /* TCF_CSV_LEARNED_INPUTS */

#ifdef TCF_CSV_IMU_DT_INPUTS
/* The input of the VQF core's harness: the IMU CSV of 6 (gyr, acc) or 9 (gyr, acc, mag) columns,
   optionally with a last column dt [s] (7 or 10 columns), as rows of 10 floats in *x: gyr, acc,
   mag (0 without), dt (NaN without). Returns 0, or 1 after printing the error. */
static int tcf_csv_read_imu_dt(const char *prog, const char *path, float **x, long *n, int *has_mag, int *has_dt) {
  static const int imu_cols[4] = {6, 7, 9, 10};
  int n_cols;
  long s;
  if (tcf_csv_read(prog, path, imu_cols, 4, "6 (gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z) or 9 (+ mag_x,mag_y,mag_z), "
                   "optionally + dt", x, n, &n_cols))
    return 1;
  *has_dt = n_cols == 7 || n_cols == 10;
  *has_mag = n_cols >= 9;
  for (s = 0; s < *n; ++s) {  /* tcf_csv_read leaves the columns after n_cols at 0 */
    float *r = *x + 10 * s, dt = *has_dt ? r[n_cols - 1] : NAN;
    if (!*has_mag) r[6] = r[7] = r[8] = 0.0f;
    r[9] = dt;
  }
  return 0;
}

#endif /* TCF_CSV_IMU_DT_INPUTS */

#endif /* TCF_CSV_H */
