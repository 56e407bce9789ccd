/* The task's cost terms, Gauss–Newton about the plan (ocpkit.qp.task_rows.TaskRows.add).
   The plan: knots z̄, the previous plan shifted a step (at a cold start the input goal at every knot, clipped to
   the input bounds); its states x̄_k = S_k z̄ + v_k from the QP's own [v S] rows (x̄_0 = x) and inputs
   ū_k = Φ_k z̄ (Φ_k = φ_k ⊗ I). Each residual r_k (weights w) enters as r_k + G_k (z − z̄),
   G_k = ∂r/∂x S_k + ∂r/∂u Φ_k: h += G_kᵀ W G_k, g += G_kᵀ W (r_k − G_k z̄) (h, g: the QP of the cost itself,
   as condense builds them). */

/* The upper triangle of h (column-major) += Gᵀ W G and g += Gᵀ W (r − G z̄) for G (nr x NZ, row-major, zero past
   its first ncol columns) in m->G and r in m->tr. */
static void task_add(mem_t* m, const double* w, int nr, int ncol) {
  double we[{{ N }}_NR1], wg[{{ N }}_NR1];
  int k, i, j;
  for (k = 0; k < nr; ++k) {
    const double* gk = m->G + k * NZ;
    double e = m->tr[k];
    for (j = 0; j < ncol; ++j) e -= gk[j] * m->zbar[j];
    we[k] = w[k] * e;
  }
  for (j = 0; j < ncol; ++j) {
    double* hj = m->h + NZ * j;
    double gj = 0;
    for (k = 0; k < nr; ++k) {
      wg[k] = w[k] * m->G[k * NZ + j];
      gj += m->G[k * NZ + j] * we[k];
    }
    m->g[j] += gj;
    for (i = 0; i <= j; ++i) {
      double v = 0;
      for (k = 0; k < nr; ++k) v += m->G[k * NZ + i] * wg[k];
      hj[i] += v;
    }
  }
}

/* G[:, :c] = ∂r/∂x S for S = Λ_s R, the rows of [v S] at a piece's state s (L: Λ_s; prev, cp, phi, del, c: the
   piece's R as in condense) computed as (∂r/∂x Λ_s) R: nr rows through R instead of NX. */
static void task_jacobian_x(mem_t* m, int nr, const double* L, const double* prev, int cp, const double* phi,
                            const double* del, int c) {
  int a, b, l, col;
  for (a = 0; a < nr; ++a) {
    double* jl = m->JL + a * NL;
    for (l = 0; l < NL; ++l) jl[l] = 0;
    for (b = 0; b < NX; ++b) {
      const double v = m->trx[a + nr * b];
      if (v != 0) for (l = 0; l < NL; ++l) jl[l] += v * L[b * NL + l];
    }
  }
  times_r(m->JL, nr, NL, prev, cp, phi, del, c, m->GX, NZ1);
  for (a = 0; a < nr; ++a)
    for (col = 0; col < c; ++col) m->G[a * NZ + col] += m->GX[a * NZ1 + 1 + col];
}

#if TASK_STAGE
/* Stage k's residual at (x̄_k, ū_k) and its terms; L: Λ_s of x_k in its piece (with prev, cp, p, d, c: the
   piece's R), none at k = 0 (x_0 is given). Returns nonzero if the residual's evaluation failed. */
static int task_stage(mem_t* m, int k, const double* xk, const double* L, const double* prev, int cp,
                      const double* p, const double* d, int c, const double* targets) {
  const double* phi = TASK_PHI + k * NP;
  int a, i, j, col, ncol = L ? c : 0;
  knot_sum(phi, m->zbar, m->tu);
  m->arg[0] = xk; m->arg[1] = m->tu; m->arg[2] = targets;
  m->res[0] = m->tr; m->res[1] = m->trx; m->res[2] = m->tru;
  if ({{ name }}_task_stage(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
  for (a = 0; a < {{ N }}_NRS; ++a) {
    double* ga = m->G + a * NZ;
    for (col = 0; col < NZ; ++col) ga[col] = 0;
    for (j = 0; j < NP; ++j)
      if (phi[j] != 0) {
        for (i = 0; i < NU; ++i) ga[j * NU + i] += phi[j] * m->tru[a + {{ N }}_NRS * i];
        if (ncol < (j + 1) * NU) ncol = (j + 1) * NU;
      }
  }
  if (L) task_jacobian_x(m, {{ N }}_NRS, L, prev, cp, p, d, c);
  task_add(m, TASK_WS, {{ N }}_NRS, ncol);
  return 0;
}
#endif

#if TASK_TERMINAL
/* The terminal residual at x̄_T and its terms; L, prev, cp, p, d, c as in task_stage. */
static int task_terminal(mem_t* m, const double* xT, const double* L, const double* prev, int cp, const double* p,
                         const double* d, int c, const double* targets) {
  int col;
  m->arg[0] = xT; m->arg[1] = targets;
  m->res[0] = m->tr; m->res[1] = m->trx;
  if ({{ name }}_task_terminal(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
  for (col = 0; col < {{ N }}_NRT * NZ; ++col) m->G[col] = 0;
  task_jacobian_x(m, {{ N }}_NRT, L, prev, cp, p, d, c);
  task_add(m, TASK_WT, {{ N }}_NRT, c);
  return 0;
}
#endif

/* The task's terms added to the QP condense built (goal: x_goal, then the targets; stage k's goal at goal + k gs:
   gs = 0 a held goal, NG a goal window{{ ", and stage k's obstacles at obs + k os" if obstacles }}). The plan's states
   run forward piece by piece as in condense: x̄ = Λ_s y with y = R [1; z̄] the piece's augmented state [x̄_a; v; d; 1]
   (Λ_1 … Λ_LMAX of all states; m->prev holds [v S] at the piece's start). Returns nonzero if a residual's
   evaluation failed. */
static int task_terms(mem_t* m, const double* x, const double* goal, int gs{{ ", const double* obs, int os" if obstacles }}) {
  const double* targets = goal + NX;
  double *prev = m->prev, *y = m->ty;
  int pc, i, j, l, s, col;
  shifted_knots(m, m->zbar);
  if (!m->has_plan)
    for (i = 0; i < NZ; ++i) m->zbar[i] = clip(m->zbar[i], LBX[i], UBX[i]);
{% if obstacles %}
  m->n_orows = 0;
{% endif %}
  memcpy(m->LamA, m->Lam1, sizeof m->Lam1);
  for (s = 1; s < LMAX; ++s) times_ahat(m->LamA + (s - 1) * NX * NL, NX, NL, m->Lam1, 1, m->LamA + s * NX * NL);
#if TASK_STAGE
  if (task_stage(m, 0, x, 0, 0, 0, 0, 0, 0, targets)) return 1;
#endif
  for (i = 0; i < NX * NZ1; ++i) prev[i] = 0;
  for (i = 0; i < NX; ++i) prev[i * NZ1] = x[i];
  for (pc = 0; pc < NPIECE; ++pc) {
    const int a = PIECE_A[pc], Lp = PIECE_L[pc], c = PIECE_C[pc], cp = PIECE_CP[pc];
    const double *phi = PIECE_PHI + pc * NP, *del = PIECE_DELTA + pc * NP;
    for (i = 0; i < NX; ++i) {
      double v = prev[i * NZ1];
      for (col = 0; col < cp; ++col) v += prev[i * NZ1 + 1 + col] * m->zbar[col];
      y[i] = v;
    }
    for (i = 0; i < NU; ++i) {
      double v = 0, dv = 0;
      for (j = 0; j < NP; ++j) { v += phi[j] * m->zbar[j * NU + i]; dv += del[j] * m->zbar[j * NU + i]; }
      y[NX + i] = v;
      y[NX + NU + i] = dv;
    }
    y[NL - 1] = 1;
    for (s = 0; s < Lp; ++s) {
      const double* L = m->LamA + s * NX * NL;  /* Λ_{s+1}: x_{a+s+1} = Λ_{s+1} y */
      for (i = 0; i < NX; ++i) {
        double v = 0;
        for (l = 0; l < NL; ++l) v += L[i * NL + l] * y[l];
        m->tx[i] = v;
      }
{% if obstacles %}
      if (obstacle_rows(m, L, prev, cp, phi, del, c, obs + (a + s + 1) * os)) return 1;
{% endif %}
      if (a + s + 1 < {{ N }}_HORIZON) {
#if TASK_STAGE
        if (task_stage(m, a + s + 1, m->tx, L, prev, cp, phi, del, c, targets + (a + s + 1) * gs)) return 1;
#endif
      } else {
#if TASK_TERMINAL
        if (task_terminal(m, m->tx, L, prev, cp, phi, del, c, targets + {{ N }}_HORIZON * gs)) return 1;
#endif
      }
    }
    /* [v S] at the piece's end: Λ_Lp R */
    times_r(m->LamA + (Lp - 1) * NX * NL, NX, NL, prev, cp, phi, del, c, m->next, NZ1);
    for (i = 0; i < NX; ++i)
      for (col = 0; col < NZ1; ++col) prev[i * NZ1 + col] = col <= c ? m->next[i * NZ1 + col] : 0.0;
  }
  for (j = 0; j < NZ; ++j)  /* the lower triangle from the upper */
    for (i = 0; i < j; ++i) m->h[j + NZ * i] = m->h[i + NZ * j];
{% if obstacles %}
  obstacle_rows_unused(m);
{% endif %}
  return 0;
}
