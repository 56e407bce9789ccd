/* The task's obstacles as hard rows of the QP (ocpkit.qp.task_rows.TaskRows.add and .select). At each state x̄_k of
   the plan (k = 1 … HORIZON, as task_terms runs them) the clearances d − margin of the robot spheres (their centres
   and Jacobians generated, {{ name }}_spheres) to the stage's obstacles (NOB x 4: centre, radius; OBSTACLES, the
   exported ones, or row k of an obstacle window): the pairs within
   ACTIVATION of the margin, each sphere's ROWS_PER_SPHERE closest, and of those the stage's NOS closest, become
   rows d + ∂d/∂x S_k (z − z̄) >= 0, stage by stage and in pair order (sphere, then obstacle) after the state-bound
   rows. The rows a step does not use are zero with infinite bounds: DAQP leaves zero rows out. */
#define NK {{ N }}_NK
#define NOB {{ N }}_NOB
#define NOS {{ N }}_NOS
#define OROW0 (NB * {{ N }}_HORIZON)  /* the first obstacle row */

/* The stage's candidate pairs in m->cand_*, sphere by sphere: each robot sphere's ROWS_PER_SPHERE closest obstacles
   within ACTIVATION of the margin, the closer first (ties: the obstacle listed first). Returns their count. */
static int obstacle_candidates(mem_t* m, const double* obs) {
  int i, j, q, n = 0;
  for (i = 0; i < NK; ++i) {
    const double* c = m->oc + 3 * i;
    const int first = n;
    for (j = 0; j < NOB; ++j) {
      const double* o = obs + 4 * j;
      const double dx = c[0] - o[0], dy = c[1] - o[1], dz = c[2] - o[2];
      const double d = sqrt(dx * dx + dy * dy + dz * dz) - (SPHERE_REACH[i] + o[3]);
      int at = n;
      if (!(d < ACTIVATION)) continue;
      while (at > first && d < m->cand_d[at - 1]) --at;
      if (at - first == ROWS_PER_SPHERE) continue;
      if (n - first == ROWS_PER_SPHERE) --n;  /* the farthest kept so far makes room */
      for (q = n; q > at; --q) { m->cand_d[q] = m->cand_d[q - 1]; m->cand_j[q] = m->cand_j[q - 1]; }
      m->cand_d[at] = d;
      m->cand_j[at] = j;
      ++n;
    }
    for (q = first; q < n; ++q) m->cand_i[q] = i;
  }
  return n;
}

/* The stage's rows in m->oi, oj, od: of the n candidates the NOS closest (ties: the earlier candidate), in pair
   order. Returns their count. */
static int obstacle_select(mem_t* m, int n) {
  int order[{{ N }}_NOC], q, r, kept;
  for (q = 0; q < n; ++q) {  /* the candidates by distance, stably */
    for (r = q; r > 0 && m->cand_d[q] < m->cand_d[order[r - 1]]; --r) order[r] = order[r - 1];
    order[r] = q;
  }
  kept = n < NOS ? n : NOS;
  for (q = 0; q < kept; ++q) {  /* the kept ones by pair (sphere, then obstacle) */
    const int o = order[q], key = m->cand_i[o] * NOB + m->cand_j[o];
    for (r = q; r > 0 && key < m->oi[r - 1] * NOB + m->oj[r - 1]; --r) {
      m->oi[r] = m->oi[r - 1]; m->oj[r] = m->oj[r - 1]; m->od[r] = m->od[r - 1];
    }
    m->oi[r] = m->cand_i[o]; m->oj[r] = m->cand_j[o]; m->od[r] = m->cand_d[o];
  }
  return kept;
}

/* The clearance rows of the state x̄_k in m->tx to the obstacles obs appended to the QP (L: its Λ_s; prev, cp, phi,
   del, c: its piece's R, as in task_stage): ∂d/∂x = eᵀ/|e| ∂c/∂x (e from the obstacle's centre to the sphere's; none where they
   coincide), the row ∂d/∂x S_k = (∂d/∂x Λ_s) R and its bound ∂d/∂x S_k z̄ − d. Returns nonzero if the spheres'
   evaluation failed. */
static int obstacle_rows(mem_t* m, const double* L, const double* prev, int cp, const double* phi, const double* del,
                         int c, const double* obs) {
  int q, a, b, col, n;
  m->arg[0] = m->tx;
  m->res[0] = m->oc; m->res[1] = m->ocx;
  if ({{ name }}_spheres(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
  n = obstacle_select(m, obstacle_candidates(m, obs));
  if (!n) return 0;
  for (q = 0; q < n; ++q) {
    const int i = m->oi[q];
    const double* o = obs + 4 * m->oj[q];
    double e[3], norm;
    for (a = 0; a < 3; ++a) e[a] = m->oc[3 * i + a] - o[a];
    norm = sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);
    if (norm < 1e-12) norm = 1e-12;
    for (a = 0; a < 3; ++a) e[a] /= norm;
    for (b = 0; b < NX; ++b) {
      const double* jb = m->ocx + 3 * (i * NX + b);  /* ∂c_i/∂x_b */
      m->og[q * NX + b] = e[0] * jb[0] + e[1] * jb[1] + e[2] * jb[2];
    }
  }
  for (q = 0; q < n * NL; ++q) m->oJL[q] = 0;
  gemm_nx(n, NL, m->og, NX, 1, L, NL, m->oJL, NL, 0);
  times_r(m->oJL, n, NL, prev, cp, phi, del, c, m->oGX, NZ1);
  for (q = 0; q < n; ++q) {
    const int r = OROW0 + m->n_orows++;
    const double* row = m->oGX + q * NZ1 + 1;
    double s = 0;
    for (col = 0; col < NZ; ++col) {
      const double v = col < c ? row[col] : 0.0;
      m->a[r + NA * col] = v;
      s += v * m->zbar[col];
    }
    m->lba[r] = s - m->od[q];
    m->uba[r] = INFINITY;
  }
  return 0;
}

/* The obstacle rows this step did not fill: zero, unbounded. */
static void obstacle_rows_unused(mem_t* m) {
  int r, col;
  for (r = OROW0 + m->n_orows; r < NA; ++r) {
    for (col = 0; col < NZ; ++col) m->a[r + NA * col] = 0;
    m->lba[r] = -INFINITY;
    m->uba[r] = INFINITY;
  }
}
