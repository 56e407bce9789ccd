/* Tutorial "Export to C": your own program calling the exported MPC step. It swings the pendulum from
   x0 = (q, q̇) to the goal angle given on the command line, against the generated model, and prints the first
   input and the final state. Build: cc -std=c99 pendulum_loop.c -I DIR -L DIR -lmpc -Wl,-rpath,DIR -lm */
#include <stdio.h>
#include <stdlib.h>
#include "mpc.h"

int main(int argc, char** argv) {
  static mpc_memory mem; /* one controller: all its memory in this struct */
  double x[MPC_NX] = {0.0, 0.0}, goal[MPC_NX] = {0.0, 0.0}, u[MPC_NU], x_next[MPC_NX];
  int k, i, status, failures = 0;
  if (argc != 4) {
    fprintf(stderr, "usage: %s Q0 QD0 Q_GOAL\n", argv[0]);
    return 2;
  }
  x[0] = atof(argv[1]);
  x[1] = atof(argv[2]);
  goal[0] = atof(argv[3]);
  if (mpc_init(&mem)) return 1;
  for (k = 0; k < 100; ++k) { /* one second at dt = 0.01 s */
    mpc_step(&mem, x, goal, u, &status);
    if (status != MPC_SUCCESS) {
      ++failures;
      fprintf(stderr, "step %d: %s (%s)\n", k, mpc_status_string(status), mpc_reason_string(mpc_last_reason(&mem)));
    }
    if (k == 0) printf("u0 %.6f\n", u[0]);
    if (mpc_model_step(&mem, x, u, x_next)) return 1; /* the plant: here the controller's own model */
    for (i = 0; i < MPC_NX; ++i) x[i] = x_next[i];
  }
  printf("x_final %.6f %.6f  goal %.6f  failures %d\n", x[0], x[1], goal[0], failures);
  mpc_free(&mem);
  return failures > 0;
}
