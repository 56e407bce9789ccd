/* main.c — closed loop of the exported MPC against the generated discrete model ({{ steps }} steps){{ ", following the
   reference in reference.csv: row k the goal at step k, each step's window its rows k … k + HORIZON" if reference }}. */
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

{% set NG = N ~ ("_NG" if task else "_NX") %}
{% if reference %}
#define REF_ROWS {{ reference }}  /* steps + HORIZON + 1 */
static double ref[REF_ROWS * {{ NG }}];

/* The reference's rows from path (a header line of the goal's names, then REF_ROWS lines of {{ NG }} numbers):
   0, or 1 where the file cannot be read or holds fewer numbers. */
static int read_reference(const char* path) {
  FILE* f = fopen(path, "r");
  int c, i = 0;
  if (!f) return 1;
  while ((c = fgetc(f)) != '\n' && c != EOF) {}
  while (i < REF_ROWS * {{ NG }} && fscanf(f, " %lf%*[,]", ref + i) == 1) ++i;
  fclose(f);
  return i < REF_ROWS * {{ NG }};
}

{% endif %}
int main(void) {
  static {{ name }}_memory mem;
  double x[{{ N }}_NX] = {{ x0 }};
{% if reference %}
  const double* goal = ref + {{ steps }} * {{ NG }};  /* the reference at the end */
{% else %}
  const double goal[{{ NG }}] = {{ goal }};
{% endif %}
  double u[{{ N }}_NU], x_next[{{ N }}_NX], times[{{ steps }}];
  int k, i, status, failures = 0, first_failure = -1, first_status = {{ N }}_SUCCESS, first_reason = {{ N }}_REASON_NONE;
{% if reference %}
  if (read_reference("reference.csv")) { fprintf(stderr, "reference.csv: expected %d rows\n", REF_ROWS); return 1; }
{% endif %}
  if ({{ name }}_init(&mem)) { fprintf(stderr, "init failed\n"); return 1; }
  /* warm-up, as a real-time loop does at start-up: the first step's page faults and first allocation are
     not part of the timed loop; reset forgets the plan, so the loop starts cold all the same */
{% if reference %}
  {{ name }}_step_window(&mem, x, ref, {{ "NULL, " if obstacles }}u, &status);
{% else %}
  {{ name }}_step(&mem, x, goal, u, &status);
{% endif %}
  {{ name }}_reset(&mem);
  for (k = 0; k < {{ steps }}; ++k) {
    double t0 = now();
{% if reference %}
    {{ name }}_step_window(&mem, x, ref + k * {{ NG }}, {{ "NULL, " if obstacles }}u, &status);
{% else %}
    {{ name }}_step(&mem, x, goal, u, &status);
{% endif %}
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
{% if reference %}
  printf("following reference.csv (%d rows)\n", REF_ROWS);
{% endif %}
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
