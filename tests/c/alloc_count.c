/* Heap use inside the exported step after init (issue 33): linked into the exported example with
 *   -Wl,--wrap=malloc,--wrap=calloc,--wrap=realloc,--wrap=free,--wrap=mpc_step
 * it counts the allocator calls made while mpc_step runs and the seconds spent in them, and prints at exit
 *   steps N allocations A frees F allocator_seconds S
 * on stderr. Init, reset and free are not counted: they may allocate. */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "mpc.h"

void* __real_malloc(size_t n);
void* __real_calloc(size_t k, size_t n);
void* __real_realloc(void* p, size_t n);
void __real_free(void* p);
int __real_mpc_step(mpc_memory* mem, const double* x, const double* goal, double* u_out, int* status);

static int in_step;
static long steps, allocations, frees;
static double allocator_seconds;

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

static void report(void) {
  fprintf(stderr, "steps %ld allocations %ld frees %ld allocator_seconds %.9f\n", steps, allocations, frees,
          allocator_seconds);
}

/* Each wrapper times the real call while a step runs. */
#define COUNTED(counter, call)               \
  do {                                       \
    double t0 = in_step ? now() : 0.0;       \
    call;                                    \
    if (in_step) {                           \
      ++counter;                             \
      allocator_seconds += now() - t0;       \
    }                                        \
  } while (0)

void* __wrap_malloc(size_t n) {
  void* p;
  COUNTED(allocations, p = __real_malloc(n));
  return p;
}

void* __wrap_calloc(size_t k, size_t n) {
  void* p;
  COUNTED(allocations, p = __real_calloc(k, n));
  return p;
}

void* __wrap_realloc(void* q, size_t n) {
  void* p;
  COUNTED(allocations, p = __real_realloc(q, n));
  return p;
}

void __wrap_free(void* p) {
  COUNTED(frees, __real_free(p));
}

int __wrap_mpc_step(mpc_memory* mem, const double* x, const double* goal, double* u_out, int* status) {
  int rc;
  if (!steps) atexit(report);
  ++steps;
  in_step = 1;
  rc = __real_mpc_step(mem, x, goal, u_out, status);
  in_step = 0;
  return rc;
}
