/* Prints "<code> <name>" for each status code from -1 to MPC_EXCEPTION + 1 as mpc_status_string names it, then
 * "reason <code> <words>" for each reason code from -1 to MPC_NREASONS as mpc_reason_string names it (the exported
 * library linked with -lmpc): tests/test_export.py compares them with ocpkit.status.STATUSES and REASONS. */
#include <stdio.h>
#include "mpc.h"

int main(void) {
  int code;
  for (code = -1; code <= MPC_EXCEPTION + 1; ++code) printf("%d %s\n", code, mpc_status_string(code));
  for (code = -1; code <= MPC_NREASONS; ++code) printf("reason %d %s\n", code, mpc_reason_string(code));
  printf("reason MPC_REASON_ITERATION_LIMIT %d\n", MPC_REASON_ITERATION_LIMIT);
  return 0;
}
