/* main.c — closed loop of the exported MPC against the generated discrete model (100 steps). */
#define _POSIX_C_SOURCE 199309L /* clock_gettime under -std=c99 */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "mpc.h"

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

static int cmp(const void* a, const void* b) {
  double d = *(const double*) a - *(const double*) b;
  return (d > 0) - (d < 0);
}

int main(void) {
  static mpc_memory mem;
  double x[MPC_NX] = {0.43027783071234316, -0.7232363687981893, -1.4420742050052617, -1.51887322843726, 0.9841674820598931, 1.2967098893039046, 0.33500616976002084, 0.7209847100114515, 0.13705195270068993, 1.3668203303511577, 0.9922832052384316, -1.5621930747785049, 1.1228186496890822, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
  const double goal[MPC_NX] = {-1.465284130148663, 0.7214838633611964, -1.0189579195481413, 1.1409602343930616, 0.13025426494341485, -0.6292236532891403, -0.2428852579140488, -1.4818274559722313, -1.1803488983797976, 0.5360324077245675, 0.4624094882471339, 0.3624930185631463, -0.3654377409784644, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
  double u[MPC_NU], x_next[MPC_NX], times[100];
  int k, i, status, failures = 0;
  if (mpc_init(&mem)) { fprintf(stderr, "init failed\n"); return 1; }
  /* warm-up, as a real-time loop does at start-up: the first step's page faults and first allocation are
     not part of the timed loop; reset forgets the plan, so the loop starts cold all the same */
  mpc_step(&mem, x, goal, u, &status);
  mpc_reset(&mem);
  for (k = 0; k < 100; ++k) {
    double t0 = now();
    mpc_step(&mem, x, goal, u, &status);
    times[k] = now() - t0;
    failures += status != MPC_SUCCESS;
    if (mpc_model_step(&mem, x, u, x_next)) { fprintf(stderr, "model failed\n"); return 1; }
    for (i = 0; i < MPC_NX; ++i) x[i] = x_next[i];
  }
  qsort(times, 100, sizeof(double), cmp);
  printf("steps %d (%.3f s)  failures %d  median step %.1f us  worst %.1f us\n", 100, 100 * 0.01,
         failures, 1e6 * times[100 / 2], 1e6 * times[100 - 1]);
  printf("x_final");
  for (i = 0; i < MPC_NX; ++i) printf(" %.6f", x[i]);
  printf("\ngoal   ");
  for (i = 0; i < MPC_NX; ++i) printf(" %.6f", goal[i]);
  printf("\n");
  mpc_free(&mem);
  return failures == 100;
}
