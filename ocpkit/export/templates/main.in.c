/* main.c — closed loop of the exported MPC against the generated discrete model ({{ steps }} steps). */
#define _POSIX_C_SOURCE 199309L /* clock_gettime under -std=c99 */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "{{ name }}.h"

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
  static {{ name }}_memory mem;
  double x[{{ N }}_NX] = {{ x0 }};
  const double goal[{{ N }}_{{ "NG" if task else "NX" }}] = {{ goal }};
  double u[{{ N }}_NU], x_next[{{ N }}_NX], times[{{ steps }}];
  int k, i, status, failures = 0, first_failure = -1, first_status = {{ N }}_SUCCESS, first_reason = {{ N }}_REASON_NONE;
  if ({{ name }}_init(&mem)) { fprintf(stderr, "init failed\n"); return 1; }
  /* warm-up, as a real-time loop does at start-up: the first step's page faults and first allocation are
     not part of the timed loop; reset forgets the plan, so the loop starts cold all the same */
  {{ name }}_step(&mem, x, goal, u, &status);
  {{ name }}_reset(&mem);
  for (k = 0; k < {{ steps }}; ++k) {
    double t0 = now();
    {{ name }}_step(&mem, x, goal, u, &status);
    times[k] = now() - t0;
    if (status != {{ N }}_SUCCESS && !failures++) {
      first_failure = k;
      first_status = status;
      first_reason = {{ name }}_last_reason(&mem);
    }
    if ({{ name }}_model_step(&mem, x, u, x_next)) { fprintf(stderr, "model failed\n"); return 1; }
    for (i = 0; i < {{ N }}_NX; ++i) x[i] = x_next[i];
  }
  qsort(times, {{ steps }}, sizeof(double), cmp);
  printf("steps %d (%.3f s)  failures %d  median step %.1f us  worst %.1f us\n", {{ steps }}, {{ steps }} * {{ dt }},
         failures, 1e6 * times[{{ steps }} / 2], 1e6 * times[{{ steps }} - 1]);
  if (failures)
    printf("first failure: step %d, %s (%s)\n", first_failure, {{ name }}_status_string(first_status),
           {{ name }}_reason_string(first_reason));
  printf("x_final");
  for (i = 0; i < {{ N }}_NX; ++i) printf(" %.6f", x[i]);
  printf("\ngoal   ");
  for (i = 0; i < {{ N }}_NX; ++i) printf(" %.6f", goal[i]);
  printf("\n");
  {{ name }}_free(&mem);
  return failures == {{ steps }};
}
