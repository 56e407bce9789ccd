/* Prints "<code> <name>" for each code from -1 to MPC_EXCEPTION + 1 as mpc_status_string names it (the exported
 * library linked with -lmpc): tests/test_export.py compares the names with ocpkit.status.STATUSES. */
#include <stdio.h>
#include "mpc.h"

int main(void) {
  int code;
  for (code = -1; code <= MPC_EXCEPTION + 1; ++code) printf("%d %s\n", code, mpc_status_string(code));
  return 0;
}
