/* tcf_vqf_harness.c: host program that runs the C VQF core (tcf_vqf.c) over a CSV file (C99).
 *
 *   tcf_vqf_harness [--6d] [--no-mag] [--diag] [--time] in.csv out.csv
 *
 * in.csv: the format of tcf_harness.c: a header line, then one row per sample at TCF_VQF_FS Hz
 *   gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z   (rad/s, m/s^2, uT)
 * or only the six gyr/acc columns (mag = NULL); optionally a last column "dt" [s] (the 7th or
 * 10th) with each sample's time step (tcf_vqf_update_dt; otherwise tcf_vqf_update). An empty field, "nan"
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
#define TCF_CSV_IMU_DT_INPUTS /* tcf_csv_read_imu_dt */
#include "tcf_csv.h"
#include "tcf_vqf.h"
#include "tcf_vqf_config.h"

#define PROG "tcf_vqf_harness"
#define N_COLS 10 /* gyr, acc, mag, dt per sample (tcf_csv_read_imu_dt) */
#define N_DIAG 8

int main(int argc, char **argv) {
  static const tcf_vqf_params_t config = TCF_VQF_PARAMS_INIT;
  const char *in_path, *out_path;
  int six_d = 0, no_mag = 0, diag = 0, timing = 0, has_mag, has_dt, status;
  const tcf_csv_option_t opts[] = {{"--6d", &six_d, NULL}, {"--no-mag", &no_mag, NULL}, {"--diag", &diag, NULL},
                                   {"--time", &timing, NULL}};
  long n = 0, s;
  float *x = NULL, *qo = NULL, *dg = NULL;
  tcf_vqf_params_t params = config;
  tcf_vqf_t f;
  clock_t t0, t1;

  status = tcf_csv_args(PROG, argc, argv, opts, (int)(sizeof opts / sizeof opts[0]),
                        "[--6d] [--no-mag] [--diag] [--time] in.csv out.csv",
                        "gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z[,mag_x,mag_y,mag_z][,dt]", (double)TCF_VQF_FS, &in_path,
                        &out_path);
  if (status) return status;
  if (six_d) params.use_mag = 0;
  if (tcf_vqf_init(&f, &params) != 0) {
    fprintf(stderr, PROG ": tcf_vqf_init rejected the settings of tcf_vqf_config.h\n");
    return 1;
  }
  if (tcf_csv_read_imu_dt(PROG, in_path, &x, &n, &has_mag, &has_dt)) return 1;
  if (!has_mag) no_mag = 1;
  if (tcf_csv_alloc_out(PROG, in_path, n, N_DIAG, &qo, &dg)) {
    free(x);
    return 1;
  }

  t0 = clock();
  for (s = 0; s < n; ++s) {
    const float *r = x + N_COLS * s;
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
  if (timing) tcf_csv_print_time(PROG, "tcf_vqf_update", n, t0, t1, (unsigned)sizeof(tcf_vqf_t));
  status = tcf_csv_write_output(PROG, out_path, NULL, 0, ",rest,mag_dist,bias_x,bias_y,bias_z,bias_sigma,delta,k_mag",
                                qo, dg, n, N_DIAG, diag);
  free(x); free(qo); free(dg);
  return status;
}
