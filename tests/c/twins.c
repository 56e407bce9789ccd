/* The exported step's internal functions, reachable from Python (ctypes) for tests/test_twins.py: each Python/C
 * twin's C side fed the Python side's inputs. Built in an exported folder in place of mpc.o (it includes mpc.c, so
 * the static functions are in scope): make lib OBJ="twins.o mpc_casadi.o". Arrays as the memory struct holds them
 * (row-major Λ, column-major h and a). */
#include "mpc.c"

/* RK4 sensitivities (ocpkit.model.dynamics._affine): L = [A_d B_d 0 w_d] about (x, u); nonzero if f failed. */
int twins_affine_model(mem_t* m, const double* x, const double* u, double* L) { return affine_model(m, x, u, L); }

/* LTI condensing (CondensedQP._cost_lti) about the model Λ_1 = L with input goal ug: the QP in m (twins_qp). */
void twins_condense_lti(mem_t* m, const double* L, const double* ug, const double* x, const double* goal) {
  memcpy(m->Lam1, L, sizeof m->Lam1);
  memcpy(m->ug, ug, sizeof m->ug);
  condense(m, x, goal);
}

#if LIN_TRAJ
/* LTV condensing (CondensedQP._cost_ltv) of the stage models LamK (HORIZON x NX x NL) with input goal ug. */
void twins_condense_ltv(mem_t* m, const double* LamK, const double* ug, const double* x, const double* goal) {
  memcpy(m->LamK, LamK, sizeof m->LamK);
  memcpy(m->ug, ug, sizeof m->ug);
  condense_ltv(m, x, goal, 0);
}

/* The real-time iteration's first linearization trajectory (LinearMPC.shifted_plan) from the plan (NULL: none)
   and its predicted states (NULL: none, x held): x̄ (HORIZON x NX), ū (HORIZON x NU). */
int twins_shifted_plan(mem_t* m, const double* plan, const double* xplan, const double* ug, const double* x,
                       double* xbar, double* ubar) {
  int rc;
  m->has_plan = plan != 0;
  if (plan) memcpy(m->plan, plan, sizeof m->plan);
  m->has_xplan = xplan != 0;
  if (xplan) memcpy(m->xplan, xplan, sizeof m->xplan);
  memcpy(m->ug, ug, sizeof m->ug);
  shifted_plan(m, x);
  rc = stage_models(m);
  memcpy(xbar, m->xbar, sizeof m->xbar);
  memcpy(ubar, m->ubark, sizeof m->ubark);
  return rc;
}
#endif

/* The QP in m: h (NZ x NZ), g, a (NA x NZ), lba, uba, lbx, ubx. */
void twins_qp(const mem_t* m, double* h, double* g, double* a, double* lba, double* uba, double* lbx, double* ubx) {
  memcpy(h, m->h, sizeof m->h);
  memcpy(g, m->g, sizeof m->g);
  memcpy(a, m->a, sizeof m->a);
  memcpy(lba, m->lba, sizeof m->lba);
  memcpy(uba, m->uba, sizeof m->uba);
  memcpy(lbx, m->lbx, sizeof m->lbx);
  memcpy(ubx, m->ubx, sizeof m->ubx);
}

/* The KKT certificate (ocpkit.qp.certificate.certify) of (z, lam_x, lam_a) for the QP given: its residuals in cert,
   the failed test's code returned. */
int twins_certify(mem_t* m, const double* h, const double* g, const double* a, const double* lba, const double* uba,
                  const double* lbx, const double* ubx, const double* z, const double* lam_x, const double* lam_a,
                  double* cert) {
  int rc;
  memcpy(m->h, h, sizeof m->h);
  memcpy(m->g, g, sizeof m->g);
  memcpy(m->a, a, sizeof m->a);
  memcpy(m->lba, lba, sizeof m->lba);
  memcpy(m->uba, uba, sizeof m->uba);
  memcpy(m->lbx, lbx, sizeof m->lbx);
  memcpy(m->ubx, ubx, sizeof m->ubx);
  memcpy(m->z_new, z, sizeof m->z_new);
  memcpy(m->lam_x_new, lam_x, sizeof m->lam_x_new);
  memcpy(m->lam_a_new, lam_a, sizeof m->lam_a_new);
  rc = certify(m);
  memcpy(cert, m->cert, sizeof m->cert);
  return rc;
}

/* The ill-conditioning test (QP.not_definite without its factorization) of the Hessian h. */
int twins_ill_conditioned(mem_t* m, const double* h) {
  memcpy(m->h, h, sizeof m->h);
  return ill_conditioned(m);
}

/* The fallback (Controller.fallback, "plan") from the plan (NULL: none, the input goal ug): its input u and the
   knots it leaves as the plan. */
void twins_fallback(mem_t* m, const double* plan, const double* ug, double* u, double* knots) {
  m->has_plan = plan != 0;
  if (plan) memcpy(m->plan, plan, sizeof m->plan);
  memcpy(m->ug, ug, sizeof m->ug);
  fallback(m, u, 0);
  memcpy(knots, m->plan, sizeof m->plan);
}
