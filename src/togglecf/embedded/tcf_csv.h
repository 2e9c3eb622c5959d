/* CSV helpers of the host harnesses (tcf_harness.c, tcf_vqf_harness.c); host only, not firmware.
   Every function is static: include this header in one translation unit. */
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

#endif /* TCF_CSV_H */
