/* {{ name }}.c — one MPC step: the affine model (generated, {{ name }}_casadi.c), the condensed QP built by the
 * loops below (ocpkit.qp.transcription.CondensedQP.build in C), the QP solve (generated) and the first input. */
#if !defined(_WIN32) && !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 199309L /* clock_gettime for {{ name }}_step_timed */
#endif
#include <float.h>
#include <math.h>
#include <string.h>
#include <time.h>
#include "{{ name }}.h"
#include "{{ name }}_casadi.h"

#define NX {{ N }}_NX
#define NU {{ N }}_NU
#define NP {{ N }}_KNOTS
#define NZ {{ N }}_NZ
#define NZ1 {{ N }}_NZ1
#define NA {{ N }}_NA
#define NL {{ N }}_NL
#define LMAX {{ N }}_LMAX
#define NLEN {{ N }}_NLEN
#define NG {{ N }}_{{ "NG" if task else "NX" }}  /* a goal's entries: a goal window's row */
typedef {{ name }}_memory mem_t;

{{ constants }}

int {{ name }}_init(mem_t* m) {
  m->solver_mem = {{ name }}_qp_solve_checkout();
  if (m->solver_mem < 0) return 1;
  {{ name }}_reset(m);
  return 0;
}

void {{ name }}_reset(mem_t* m) {
  int i;
  for (i = 0; i < NZ; ++i) m->plan[i] = m->z[i] = m->lam_x[i] = 0;
  for (i = 0; i < {{ N }}_NA1; ++i) m->lam_a[i] = 0;
  m->has_plan = m->warm = 0;
#if LIN_TRAJ
  m->has_xplan = 0;
#endif
  m->solver_rc = 0;
  m->reason = {{ N }}_REASON_NONE;
}

/* CasADi's decref frees every slot (even ones still on its free list) once the count reaches zero, so the
   slots stay allocated for the library's lifetime and are reused by later inits. */
void {{ name }}_free(mem_t* m) {
  if (m->solver_mem >= 0) {{ name }}_qp_solve_release(m->solver_mem);
  m->solver_mem = -1;
}

static int all_finite(const double* v, int n) {
  int i;
  for (i = 0; i < n; ++i) if (!isfinite(v[i])) return 0;
  return 1;
}

static int any_nan(const double* v, int n) {
  int i;
  for (i = 0; i < n; ++i) if (isnan(v[i])) return 1;
  return 0;
}

static int any_above(const double* lo, const double* hi, int n) {
  int i;
  for (i = 0; i < n; ++i) if (lo[i] > hi[i]) return 1;
  return 0;
}

static double clip(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* A failure's status, its reason ({{ N }}_REASON_...) kept for {{ name }}_last_reason. */
static int fail(mem_t* m, int status, int reason) {
  m->reason = reason;
  return status;
}

/* The input goal u_g = u_goal + K goal (+ h(goal)): the input the cost pulls towards. */
#if HAS_K
/* ug += K goal */
static void add_goal_gain(const double* goal, double* ug) {
  int i, j;
  for (i = 0; i < NU; ++i)
    for (j = 0; j < NX; ++j) ug[i] += K_GOAL[i * NX + j] * goal[j];
}
#endif
#if HAS_GOAL_INPUT
/* ug += h(goal), the problem's goal input (gravity compensation). Returns nonzero if h failed. */
static int add_goal_input(mem_t* m, const double* goal, double* ug) {
  double h[NU];
  int i;
  m->arg[0] = goal; m->res[0] = h;
  if ({{ name }}_goal_input(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
  for (i = 0; i < NU; ++i) ug[i] += h[i];
  return 0;
}
#endif

/* u = Σ_j w_j z_j, the knots z (NP x NU, row-major) weighted by w: the input at a stage of the basis (w = φ_k). */
static void knot_sum(const double* w, const double* z, double* u) {
  int i, j;
  for (i = 0; i < NU; ++i) {
    double s = 0;
    for (j = 0; j < NP; ++j) s += w[j] * z[j * NU + i];
    u[i] = s;
  }
}

/* z = the plan's knots shifted a step (Parameterization.shift), the input goal at every knot where there is no plan. */
static void shifted_knots(const mem_t* m, double* z) {
  int j, l, i;
  for (j = 0; j < NP; ++j)
    for (i = 0; i < NU; ++i) {
      double s = 0;
      if (m->has_plan) for (l = 0; l < NP; ++l) s += SHIFT[j * NP + l] * m->plan[l * NU + i];
      else s = m->ug[i];
      z[j * NU + i] = s;
    }
}

/* The QP's answer (z_new and its multipliers) made the plan and the next solve's warm start. */
static void commit_plan(mem_t* m) {
  int i;
  for (i = 0; i < NZ; ++i) { m->plan[i] = m->z[i] = m->z_new[i]; m->lam_x[i] = m->lam_x_new[i]; }
  for (i = 0; i < NA; ++i) m->lam_a[i] = m->lam_a_new[i];
  m->has_plan = m->warm = 1;
}

/* Controller.fallback: previous plan shifted (input goal at a cold start), clipped; the next step starts cold.
   Python twin: ocpkit.controller.Controller.fallback ("plan"), Parameterization.shift (tests/test_twins.py). */
static int fallback(mem_t* m, double* u_out, int status) {
  int i;
  shifted_knots(m, m->z_new);
  for (i = 0; i < NZ; ++i) m->z_new[i] = clip(m->z_new[i], LBX[i], UBX[i]);
  knot_sum(PHI0, m->z_new, u_out);
  for (i = 0; i < NU; ++i) u_out[i] = clip(u_out[i], LBX[i], UBX[i]);
  for (i = 0; i < NZ; ++i) m->plan[i] = m->z_new[i];
  m->has_plan = 1;
  m->warm = 0;
#if LIN_TRAJ
  m->has_xplan = 0;  /* the next step linearizes along the fallback plan, x held */
#endif
  return status;
}

/* The products over the inner dimension NX (the state's size): C += A B for an M x NX matrix A with A(i, k) =
   A[i * ars + k * aks] (row-major: ars = lda, aks = 1; its transpose: ars = 1, aks = lda), row-major B (NX x N)
   and C (M x N). With upper set, tiles wholly below C's diagonal are skipped (the lower triangle is then left
   partial, and is never read). Each entry of C gets its own sum over k in order, added to C at the end, on every
   path below. Tiles of MR rows x 8 (or 4) columns of C stay in vector registers while B's rows, contiguous, stream
   through: GCC/Clang vector extensions, SSE2 (any x86-64: MR = 2) and, on x86 CPUs that have them, AVX2 and FMA
   (MR = 4; chosen once at run time; no build flag, the library stays portable). */
#if defined(__GNUC__) || defined(__clang__)
#define INLINE static inline __attribute__((always_inline)) /* compiled for each instruction set's caller */
#else
#define INLINE static inline
#endif
#ifndef OCPKIT_SIMD
#define OCPKIT_SIMD 2 /* the Makefile's SIMD: 2 auto (AVX2 where the CPU has it), 1 no AVX2 path, 0 plain C */
#endif
#if (defined(__GNUC__) || defined(__clang__)) && OCPKIT_SIMD >= 1
#define VECTOR_EXT 1
#if (defined(__x86_64__) || defined(__i386__)) && OCPKIT_SIMD >= 2
#define HAVE_AVX2_PATH 1
#define AVX2 __attribute__((target("avx2,fma")))
#endif
#endif

{% for isa, w, mr in [("sse2", 2, 2), ("avx2", 4, 4)] %}
#if {{ "VECTOR_EXT" if isa == "sse2" else "HAVE_AVX2_PATH" }}
/* {{ isa | upper }}: vectors of {{ w }} doubles (one register), blocks of {{ mr }} rows. */
typedef double vec{{ w }} __attribute__((vector_size({{ 8 * w }}), aligned(8), may_alias));

/* C[0:rows, 0:{{ w }} nv] += A[0:rows, :] B[:, 0:{{ w }} nv] (nv <= {{ 8 // w }} vectors a row, rows <= {{ mr }}), the block of C
   in registers; rows and nv are constants after inlining, or rows the last block's height. */
INLINE void gemm_nx_tile_{{ isa }}(int rows, int nv, const double* restrict A, int ars, int aks,
                                const double* restrict B, int ldb, double* restrict C, int ldc) {
  vec{{ w }} c[{{ mr }}][{{ 8 // w }}], b[{{ 8 // w }}];
  int r, v, k;
  for (r = 0; r < rows; ++r)
    for (v = 0; v < nv; ++v) c[r][v] = (vec{{ w }}){0};
  for (k = 0; k < NX; ++k) {
    for (v = 0; v < nv; ++v) b[v] = *(const vec{{ w }}*) (B + k * ldb + {{ w }} * v);
    for (r = 0; r < rows; ++r) {
      const double a = A[r * ars + k * aks];
      for (v = 0; v < nv; ++v) c[r][v] += a * b[v];
    }
  }
  for (r = 0; r < rows; ++r)
    for (v = 0; v < nv; ++v) *(vec{{ w }}*) (C + r * ldc + {{ w }} * v) += c[r][v];
}

/* A tile of mr rows ({{ mr }}, a constant, or the last block's fewer) and {{ w }} nv columns. */
INLINE void gemm_nx_rows_{{ isa }}(int mr, int nv, const double* restrict A, int ars, int aks,
                                const double* restrict B, int ldb, double* restrict C, int ldc) {
  if (mr == {{ mr }}) gemm_nx_tile_{{ isa }}({{ mr }}, nv, A, ars, aks, B, ldb, C, ldc);
  else gemm_nx_tile_{{ isa }}(mr, nv, A, ars, aks, B, ldb, C, ldc);
}

/* C += A B by blocks of {{ mr }} rows: tiles of 8 columns, one of 4, and the last N mod 4 columns through a
   zero-padded copy of B's columns (so that they too run in registers, not as latency-bound dot products). */
{{ "AVX2 " if isa == "avx2" }}static void gemm_nx_{{ isa }}(int M, int N, const double* restrict A, int ars, int aks,
                         const double* restrict B, int ldb, double* restrict C, int ldc, int upper) {
  const int n8 = N - N % 8, n4 = N - N % 4, nrem = N - n4;
  double Bp[NX * 4], Cp[{{ mr }} * 4];
  int i, j, k, r;
  for (k = 0; nrem && k < NX; ++k)
    for (j = 0; j < 4; ++j) Bp[k * 4 + j] = j < nrem ? B[k * ldb + n4 + j] : 0.0;
  for (i = 0; i < M; i += {{ mr }}) {
    const int mr = M - i < {{ mr }} ? M - i : {{ mr }};
    for (j = upper ? (i / 8) * 8 : 0; j < n8; j += 8)
      gemm_nx_rows_{{ isa }}(mr, {{ 8 // w }}, A + i * ars, ars, aks, B + j, ldb, C + i * ldc + j, ldc);
    if (n4 > n8) gemm_nx_rows_{{ isa }}(mr, {{ 4 // w }}, A + i * ars, ars, aks, B + n8, ldb, C + i * ldc + n8, ldc);
    if (nrem) {
      for (j = 0; j < {{ mr }} * 4; ++j) Cp[j] = 0;
      gemm_nx_rows_{{ isa }}(mr, {{ 4 // w }}, A + i * ars, ars, aks, Bp, 4, Cp, 4);
      for (r = 0; r < mr; ++r)
        for (j = 0; j < nrem; ++j) C[(i + r) * ldc + n4 + j] += Cp[r * 4 + j];
    }
  }
}
#endif

{% endfor %}
#if HAVE_AVX2_PATH
static int use_avx2(void) {
  static int avx2 = -1;  /* an idempotent race at worst: every thread writes the same value */
  if (avx2 < 0) avx2 = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return avx2;
}
#endif

static void gemm_nx(int M, int N, const double* restrict A, int ars, int aks, const double* restrict B, int ldb,
                    double* restrict C, int ldc, int upper) {
#if HAVE_AVX2_PATH
  if (use_avx2()) { gemm_nx_avx2(M, N, A, ars, aks, B, ldb, C, ldc, upper); return; }
#endif
#if VECTOR_EXT
  gemm_nx_sse2(M, N, A, ars, aks, B, ldb, C, ldc, upper);
#else
  int i, j, k;
  for (i = 0; i < M; ++i)
    for (j = upper ? i : 0; j < N; ++j) {
      double s = 0;
      for (k = 0; k < NX; ++k) s += A[i * ars + k * aks] * B[k * ldb + j];
      C[i * ldc + j] += s;
    }
#endif
}

/* The upper triangle of a row-major n x n matrix copied into its lower one. */
static void symmetrize(double* X, int n) {
  int i, j;
  for (i = 0; i < n; ++i)
    for (j = 0; j < i; ++j) X[i * n + j] = X[j * n + i];
}

/* The augmented state ζ = [x; v; d; 1] of a piece (input v_t = v + t d, d constant) moves by
   ζ_{s+1} = Â ζ_s, and Λ_s = [A^s E_s F_s e_s] = C Â^s (C picks x). out = X Â^b for X (rows x NL, row stride
   ldx) from Λ_b, the x rows of Â^b, whose other rows are [0 I bI 0; 0 0 I 0; 0 0 0 1]. */
static void times_ahat(const double* X, int rows, int ldx, const double* Lb, int b, double* out) {
  int r, u;
  for (r = 0; r < rows; ++r) {
    const double* xr = X + r * ldx;
    double* o = out + r * NL;
    for (u = 0; u < NX; ++u) o[u] = 0;
    for (u = 0; u < NU; ++u) {
      o[NX + u] = xr[NX + u];
      o[NX + NU + u] = b * xr[NX + u] + xr[NX + NU + u];
    }
    o[NL - 1] = xr[NL - 1];
  }
  gemm_nx(rows, NL, X, ldx, 1, Lb, NL, out, NL, 0);
}

/* G += Wᵀ W (upper triangle; row stride ldg) with W = Q^½ (X − x_goal e_oneᵀ) over the first cols columns of X
   (row stride ldx; column one multiplies 1): the stage cost (x_s − x_goal)ᵀ Q (x_s − x_goal) as a form in the
   coordinates of X — ζ for Λ_s, [1; z] for the rows [v S] of the real-time iteration. */
static void add_stage(mem_t* m, const double* X, int cols, int ldx, int one, const double* xg, double* G, int ldg) {
  double* W = m->W;
  int i;
#if DIAG_Q
  for (i = 0; i < NX; ++i) {
    int j;
    for (j = 0; j < cols; ++j) W[i * cols + j] = QH[i] * X[i * ldx + j];
    W[i * cols + one] -= QH[i] * xg[i];
  }
#else
  for (i = 0; i < NX * cols; ++i) W[i] = 0;
  gemm_nx(NX, cols, QH, NX, 1, X, ldx, W, cols, 0);
  for (i = 0; i < NX; ++i) {
    double gx = 0;
    int k;
    for (k = 0; k < NX; ++k) gx += QH[i * NX + k] * xg[k];
    W[i * cols + one] -= gx;
  }
#endif
  gemm_nx(cols, cols, W, 1, cols, W, cols, G, ldg, 1);
}

/* Γ += the stage cost of Λ (add_stage), both triangles: the doublings read Γ whole. */
static void add_stage_gram(mem_t* m, const double* Lam, const double* xg, double* Gam) {
  add_stage(m, Lam, NL, NL, NL - 1, xg, Gam, NL);
  symmetrize(Gam, NL);
}

/* Γ_L = Σ_{s≤L} Λ_sᵀ Q Λ_s (goal folded in) and Λ_L for each piece length, by the schedule GRAM_OPS: doublings
   Γ_2s = Γ_s + (Â^s)ᵀ Γ_s Â^s, Λ_2s = Λ_s Â^s and single stages, O(log L) products instead of L. */
static void grams(mem_t* m, const double* xg) {
  double *Lam = m->LamS, *tmp = m->LamT, *Gam = m->GamS, *sw;
  int op, i, s = 1;
  for (i = 0; i < NL * NL; ++i) m->Gam1[i] = 0;
  add_stage_gram(m, m->Lam1, xg, m->Gam1);
  memcpy(Lam, m->Lam1, sizeof m->Lam1);
  memcpy(Gam, m->Gam1, sizeof m->Gam1);
  for (op = 0; op < NGRAM_OPS; ++op) {
    const int code = GRAM_OPS[op];
    if (code == GRAM_DOUBLE) {
      times_ahat(Gam, NL, NL, Lam, s, m->Y);
      for (i = 0; i < NU; ++i) {
        double* gv = Gam + (NX + i) * NL;
        double* gd = Gam + (NX + NU + i) * NL;
        const double* yv = m->Y + (NX + i) * NL;
        const double* yd = m->Y + (NX + NU + i) * NL;
        int j;
        for (j = 0; j < NL; ++j) { gv[j] += yv[j]; gd[j] += s * yv[j] + yd[j]; }
      }
      for (i = 0; i < NL; ++i) Gam[(NL - 1) * NL + i] += m->Y[(NL - 1) * NL + i];
      gemm_nx(NL, NL, Lam, 1, NL, m->Y, NL, Gam, NL, 1);
      symmetrize(Gam, NL);
      times_ahat(Lam, NX, NL, Lam, s, tmp);
      s *= 2;
    } else if (code == GRAM_INC) {  /* one more stage */
      times_ahat(Lam, NX, NL, m->Lam1, 1, tmp);
      add_stage_gram(m, tmp, xg, Gam);
      s += 1;
    } else if (code == GRAM_RESET) {  /* restart from s = 1 */
      memcpy(Lam, m->Lam1, sizeof m->Lam1);
      memcpy(Gam, m->Gam1, sizeof m->Gam1);
      s = 1;
      continue;
    } else {  /* GRAM_SAVE + i: save as length i */
      memcpy(m->GamL + (code - GRAM_SAVE) * NL * NL, Gam, sizeof m->GamS);
      memcpy(m->LamL + (code - GRAM_SAVE) * NX * NL, Lam, sizeof m->LamS);
      continue;
    }
    sw = Lam; Lam = tmp; tmp = sw;
  }
}

/* out (rows x (c+1), row stride ldo) = X R for X (rows x NL, stride ldx) and the piece's
   R = [prev; φ_a ⊗ I; Δ ⊗ I; (1, 0 … 0)]; prev's columns past cp are zero (knots not yet active). */
static void times_r(const double* X, int rows, int ldx, const double* prev, int cp, const double* phi,
                    const double* del, int c, double* out, int ldo) {
  int r, j, u, col;
  for (r = 0; r < rows; ++r) {
    const double* xr = X + r * ldx;
    double* o = out + r * ldo;
    o[0] = xr[NL - 1];
    for (j = 0, col = 1; col <= c; ++j)
      for (u = 0; u < NU; ++u, ++col) o[col] = phi[j] * xr[NX + u] + del[j] * xr[NX + NU + u];
  }
  gemm_nx(rows, cp + 1, X, ldx, 1, prev, NZ1, out, ldo, 0);
}

#if NB > 0
/* Row ri of the QP: state bound b, XB_LO[b] <= row[0] + row[1:] z <= XB_HI[b] for a row of [v S] whose knot
   columns past c are zero (not read). */
static void state_bound_row(mem_t* m, int ri, int b, const double* row, int c) {
  int col;
  for (col = 0; col < NZ; ++col) m->a[ri + NA * col] = col < c ? row[col + 1] : 0.0;
  m->lba[ri] = XB_LO[b] - row[0];
  m->uba[ri] = XB_HI[b] - row[0];
}

/* The bounded rows of Λ_1 … Λ_LMAX (row b of Λ_s at LamB[(s-1) NB + b]). */
static void bounded_rows(mem_t* m) {
  int b, s;
  for (b = 0; b < NB; ++b) memcpy(m->LamB + b * NL, m->Lam1 + XB_COMP[b] * NL, NL * sizeof(double));
  for (s = 1; s < LMAX; ++s) times_ahat(m->LamB + (s - 1) * NB * NL, NB, NL, m->Lam1, 1, m->LamB + s * NB * NL);
}

/* The state-bound rows of a piece's states x_{a+1} … x_{a+Lp} (prev, cp, phi, del, c: its R as in condense): row
   (k, b) at k*NB + b. */
static void piece_bound_rows(mem_t* m, int a, int Lp, const double* prev, int cp, const double* phi,
                             const double* del, int c) {
  int s, b;
  times_r(m->LamB, Lp * NB, NL, prev, cp, phi, del, c, m->RB, NZ1);
  for (s = 0; s < Lp; ++s)
    for (b = 0; b < NB; ++b) state_bound_row(m, (a + s) * NB + b, b, m->RB + (s * NB + b) * NZ1, c);
}
#endif

#if HAS_DQT
/* Pq += the terminal weight's extra (Q_T − Q) on [v − x_goal, S] at x_T (prev = [v_T S_T], x_goal subtracted here). */
static void add_terminal_weight(mem_t* m, double* prev, const double* xg) {
  int i;
  for (i = 0; i < NX; ++i) prev[i * NZ1] -= xg[i];
#if DIAG_Q
  for (i = 0; i < NX; ++i) {
    int col;
    for (col = 0; col < NZ1; ++col) m->E2[i * NZ1 + col] = DQT[i] * prev[i * NZ1 + col];
  }
#else
  for (i = 0; i < NX * NZ1; ++i) m->E2[i] = 0;
  gemm_nx(NX, NZ1, DQT, NX, 1, prev, NZ1, m->E2, NZ1, 0);
#endif
  gemm_nx(NZ1, NZ1, prev, 1, NZ1, m->E2, NZ1, m->Pq, NZ1, 1);
}
#endif

/* The QP from Pq (the upper triangle of Σ_s [1; z]ᵀ[v_s − x_goal, S_s]ᵀ Q [v_s − x_goal, S_s], the terminal weight
   added): P = S'QS + φᵀφ ⊗ R, q = S'Q(v − x_goal) − φᵀ1 ⊗ R u_g and the knot bounds. */
static void finish_qp(mem_t* m) {
  const double* Pq = m->Pq;
  int i, j, k;
  /* P = S'QS + φᵀφ ⊗ R (symmetric by construction), q = S'Q(v − x_goal) − φᵀ1 ⊗ R u_g */
  for (i = 0; i < NZ; ++i)
    for (j = i; j < NZ; ++j) {
      double v = Pq[(1 + i) * NZ1 + 1 + j] + R_KNOTS[i * NZ + j];
      m->h[i + NZ * j] = m->h[j + NZ * i] = v;
    }
  for (i = 0; i < NZ; ++i) {
    const int jk = i / NU, u = i % NU;
    double ru = 0;
    for (k = 0; k < NU; ++k) ru += R_IN[u * NU + k] * m->ug[k];
    m->g[i] = Pq[1 + i] - PHI_SUM[jk] * ru;
    m->lbx[i] = LBX[i];
    m->ubx[i] = UBX[i];
  }
}

/* The condensed QP about the affine model Λ_1 (CondensedQP.build): h, g, state-bound rows a, lba, uba.
   Python twin: ocpkit.qp.transcription.CondensedQP._cost_lti (a backward pass) (tests/test_twins.py). */
static void condense(mem_t* m, const double* x, const double* xg) {
  double *prev = m->prev, *next = m->next, *Pq = m->Pq, *Y = m->Y, *sw;
  int pc, i, r, col;
  grams(m, xg);
#if NB > 0
  bounded_rows(m);
#endif
  for (i = 0; i < NX * NZ1; ++i) prev[i] = 0;
  for (i = 0; i < NX; ++i) prev[i * NZ1] = x[i];
  for (i = 0; i < NZ1 * NZ1; ++i) Pq[i] = 0;
  for (pc = 0; pc < NPIECE; ++pc) {
    const int c = PIECE_C[pc], cp = PIECE_CP[pc];
    const double *phi = PIECE_PHI + pc * NP, *del = PIECE_DELTA + pc * NP;
    /* Pq[:c+1, :c+1] += Rᵀ (Γ R) (upper half) */
    times_r(m->GamL + PIECE_LEN[pc] * NL * NL, NL, NL, prev, cp, phi, del, c, Y, NZ1);
    for (r = 0; r <= c; ++r) {
      double* pr = Pq + r * NZ1;
      if (r == 0) {
        for (col = 0; col <= c; ++col) pr[col] += Y[(NL - 1) * NZ1 + col];
      } else {
        const int jr = (r - 1) / NU, ur = r - 1 - jr * NU;
        const double f = phi[jr], d = del[jr];
        const double *y1 = Y + (NX + ur) * NZ1, *y2 = Y + (NX + NU + ur) * NZ1;
        if (f != 0 || d != 0) for (col = r; col <= c; ++col) pr[col] += f * y1[col] + d * y2[col];
      }
    }
    gemm_nx(cp + 1, c + 1, prev, 1, NZ1, Y, NZ1, Pq, NZ1, 1);
#if NB > 0
    piece_bound_rows(m, PIECE_A[pc], PIECE_L[pc], prev, cp, phi, del, c);
#endif
    /* [v S] at the piece's end: Λ_Lp R */
    times_r(m->LamL + PIECE_LEN[pc] * NX * NL, NX, NL, prev, cp, phi, del, c, next, NZ1);
    for (i = 0; i < NX; ++i)
      for (col = c + 1; col < NZ1; ++col) next[i * NZ1 + col] = 0;
    sw = prev; prev = next; next = sw;
  }
#if HAS_DQT
  add_terminal_weight(m, prev, xg);
#endif
  finish_qp(m);
}

/* A goal window (row k = stage k's goal, rows NG apart) whose x_goal moves: the step condenses towards row 0 held
   (condense, finish_qp: the held step's arithmetic) and adds what the other rows change, linear in the goals. */

/* g −= Σ_{k<HORIZON} Φ_kᵀ R (u_g,k − u_g,0): each stage's input term towards its own input goal u_g(x_goal,k)
   (m->ug holds row 0's; φ_k = φ_a + s Δ in its piece). Returns nonzero where an input goal is not finite. */
static int window_inputs(mem_t* m, const double* goals) {
  double* su = m->wsu;  /* Σ_k φ_kj (u_g,k − u_g,0), NP x NU */
  double* du = m->wdu;
  int pc, s, i, j, failed = 0;
  for (i = 0; i < NZ; ++i) su[i] = 0;
  for (i = 0; i < NU; ++i) du[i] = 0;
  for (pc = 0; pc < NPIECE; ++pc)
    for (s = 0; s < PIECE_L[pc]; ++s) {
      const int k = PIECE_A[pc] + s;
      const double* gk = goals + k * NG;
      if (!k) continue;  /* row 0's own */
      for (i = 0; i < NX && gk[i] == gk[i - NG]; ++i) {}
      if (i < NX) {  /* x_goal moved since the last stage: its input goal */
        memcpy(du, U_GOAL, sizeof m->wdu);
#if HAS_K
        add_goal_gain(gk, du);
#endif
#if HAS_GOAL_INPUT
        failed |= add_goal_input(m, gk, du);
#endif
        for (i = 0; i < NU; ++i) du[i] -= m->ug[i];
      }
      for (j = 0; j < NP; ++j) {
        const double f = PIECE_PHI[pc * NP + j] + s * PIECE_DELTA[pc * NP + j];
        if (f != 0) for (i = 0; i < NU; ++i) su[j * NU + i] += f * du[i];
      }
    }
  if (failed || !all_finite(su, NZ)) return 1;
  for (j = 0; j < NP; ++j)
    for (i = 0; i < NU; ++i) {
      double r = 0;
      int l;
      for (l = 0; l < NU; ++l) r += R_IN[i * NU + l] * su[j * NU + l];
      m->g[j * NU + i] -= r;
    }
  return 0;
}

#if !LIN_TRAJ
/* out = Q (x_goal,0 − x_goal,k) for the goals g0, gk. */
static void window_weight(const double* g0, const double* gk, double* out) {
  double d[NX];
  int i;
  for (i = 0; i < NX; ++i) d[i] = g0[i] - gk[i];
#if DIAG_Q
  for (i = 0; i < NX; ++i) out[i] = QH[i] * QH[i] * d[i];
#else
  {
    double e[NX];
    int k;
    for (i = 0; i < NX; ++i) {
      double v = 0;
      for (k = 0; k < NX; ++k) v += QH[i * NX + k] * d[k];
      e[i] = v;
    }
    for (i = 0; i < NX; ++i) {
      double v = 0;
      for (k = 0; k < NX; ++k) v += QH[k * NX + i] * e[k];
      out[i] = v;
    }
  }
#endif
}

/* The goal window's terms about the one model Λ_1 = [A_d B_d 0 w_d]: window_inputs, and g += Σ_{k=1…HORIZON} S_kᵀ Q_k
   (x_goal,0 − x_goal,k), each state's term towards its own x_goal,k, by the adjoint of x_{k+1} = A_d x_k + B_d Φ_k z:
   λ_T = Q_T d_T, λ_k = Q d_k + A_dᵀ λ_{k+1}, Σ_k S_kᵀ Q_k d_k = (I ⊗ B_dᵀ) Σ_k (φ_k ⊗ λ_{k+1}) — HORIZON NX² products,
   beside the condensing's Γ_L products of NL² NX. Returns nonzero where an input goal is not finite. */
static int window_terms(mem_t* m, const double* goals) {
  double *lam = m->wlam, *nl = m->wnl, *mu = m->wmu, *sw;
  int pc, s, i, j;
  if (window_inputs(m, goals)) return 1;
  for (i = 0; i < NP * NX; ++i) mu[i] = 0;
  window_weight(goals, goals + {{ N }}_HORIZON * NG, lam);
#if HAS_DQT
  for (i = 0; i < NX; ++i) {  /* Q_T = Q + (Q_T − Q) */
    const double di = goals[i] - goals[{{ N }}_HORIZON * NG + i];
#if DIAG_Q
    lam[i] += DQT[i] * di;
#else
    for (j = 0; j < NX; ++j) lam[j] += DQT[j * NX + i] * di;
#endif
  }
#endif
  for (pc = NPIECE - 1; pc >= 0; --pc)
    for (s = PIECE_L[pc] - 1; s >= 0; --s) {  /* stage k = a + s, lam = λ_{k+1} */
      const int k = PIECE_A[pc] + s;
      for (j = 0; j < NP; ++j) {
        const double f = PIECE_PHI[pc * NP + j] + s * PIECE_DELTA[pc * NP + j];
        if (f != 0) for (i = 0; i < NX; ++i) mu[j * NX + i] += f * lam[i];
      }
      if (!k) break;
      window_weight(goals, goals + k * NG, nl);
      for (i = 0; i < NX; ++i) {
        const double* ai = m->Lam1 + i * NL;
        const double li = lam[i];
        int c;
        for (c = 0; c < NX; ++c) nl[c] += ai[c] * li;
      }
      sw = lam; lam = nl; nl = sw;
    }
  for (j = 0; j < NP; ++j)
    for (i = 0; i < NU; ++i) {
      double v = 0;
      int r;
      for (r = 0; r < NX; ++r) v += m->Lam1[r * NL + NX + i] * mu[j * NX + r];
      m->g[j * NU + i] += v;
    }
  return 0;
}
#endif

{% if task %}

{% if obstacles %}
{% include 'obstacles.in.c' %}

{% endif %}
{% include 'task.in.c' %}
{% endif %}

#if MODEL_RK4
/* D = J_x S + [0 J_u] with the Jacobians' nonzeros (fx, fu) at (FX_I, FX_J), (FU_I, FU_J); S, D row-major
   NX x (NX + NU): a row of S, contiguous, per nonzero (compiled for SSE2 and AVX2 like gemm_nx). */
INLINE void sensitivity_rate_of(const mem_t* m, const double* restrict S, double* restrict D) {
  int q, j;
  for (q = 0; q < NX * (NX + NU); ++q) D[q] = 0;
  for (q = 0; q < {{ N }}_NNZ_FX; ++q) {
    const double v = m->fx[q];
    const double* restrict sk = S + FX_J[q] * (NX + NU);
    double* restrict di = D + FX_I[q] * (NX + NU);
    for (j = 0; j < NX + NU; ++j) di[j] += v * sk[j];
  }
  for (q = 0; q < {{ N }}_NNZ_FU; ++q) D[FU_I[q] * (NX + NU) + NX + FU_J[q]] += m->fu[q];
}
#if HAVE_AVX2_PATH

AVX2 static void sensitivity_rate_avx2(const mem_t* m, const double* restrict S, double* restrict D) {
  sensitivity_rate_of(m, S, D);
}
#endif

static void sensitivity_rate(const mem_t* m, const double* restrict S, double* restrict D) {
#if HAVE_AVX2_PATH
  if (use_avx2()) { sensitivity_rate_avx2(m, S, D); return; }
#endif
  sensitivity_rate_of(m, S, D);
}

/* D = [J_x J_u] scattered: the rate at the step's start, where S = [I 0] (no products). */
static void jacobian_rate(const mem_t* m, double* restrict D) {
  int q;
  for (q = 0; q < NX * (NX + NU); ++q) D[q] = 0;
  for (q = 0; q < {{ N }}_NNZ_FX; ++q) D[FX_I[q] * (NX + NU) + FX_J[q]] = m->fx[q];
  for (q = 0; q < {{ N }}_NNZ_FU; ++q) D[FU_I[q] * (NX + NU) + NX + FU_J[q]] += m->fu[q];
}
#endif

/* L = [A_d B_d 0 w_d] (row-major, NX x NL) of the affine model about (x, ū): RK4 over SUBSTEPS with its
   sensitivities (the generated f, ∂f/∂x, ∂f/∂u at each stage), or the generated constant model of a linear one.
   Python twin: ocpkit.model.dynamics._affine (RK4 or Euler on tangents) (tests/test_twins.py). */
static int affine_model(mem_t* m, const double* x, const double* u, double* L) {
  int i, j;
#if MODEL_RK4 && EULER
  /* Euler over SUBSTEPS (integrator "euler"), its sensitivities S = ∂x/∂(x_0, u) alongside: semi-implicit for
     x = [q, q̇] (EULER_NQ = nq entries of q), q̇⁺ = q̇ + h q̈(x, u), q⁺ = q + h q̇⁺; explicit (EULER_NQ = 0),
     x⁺ = x + h f(x, u). One f, ∂f/∂x, ∂f/∂u a substep instead of RK4's four. */
  const int nS = NX * (NX + NU), w = NX + NU;
  int sub;
  for (i = 0; i < NX; ++i) m->xk[i] = x[i];
  for (i = 0; i < nS; ++i) m->S[i] = 0;
  for (i = 0; i < NX; ++i) m->S[i * w + i] = 1;
  for (sub = 0; sub < SUBSTEPS; ++sub) {
    m->arg[0] = m->xk; m->arg[1] = u;
    m->res[0] = m->kq; m->res[1] = m->fx; m->res[2] = m->fu;
    if ({{ name }}_fjac(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
    if (sub) sensitivity_rate(m, m->S, m->D);
    else jacobian_rate(m, m->D);
    for (i = EULER_NQ; i < NX; ++i) {
      m->xk[i] += RK_H * m->kq[i];
      for (j = 0; j < w; ++j) m->S[i * w + j] += RK_H * m->D[i * w + j];
    }
    for (i = 0; i < EULER_NQ; ++i) {  /* with the new q̇ */
      m->xk[i] += RK_H * m->xk[EULER_NQ + i];
      for (j = 0; j < w; ++j) m->S[i * w + j] += RK_H * m->S[(EULER_NQ + i) * w + j];
    }
  }
#elif MODEL_RK4
  static const double C_STAGE[4] = {0.0, 0.5 * RK_H, 0.5 * RK_H, RK_H}, W_STAGE[4] = {1.0, 2.0, 2.0, 1.0};
  const int nS = NX * (NX + NU);
  int sub, q;
  for (i = 0; i < NX; ++i) m->xk[i] = x[i];
  for (i = 0; i < nS; ++i) m->S[i] = 0;
  for (i = 0; i < NX; ++i) m->S[i * (NX + NU) + i] = 1;
  for (sub = 0; sub < SUBSTEPS; ++sub) {
    for (i = 0; i < NX; ++i) m->kacc[i] = 0;
    for (i = 0; i < nS; ++i) m->Dacc[i] = 0;
    for (q = 0; q < 4; ++q) {
      const double cq = C_STAGE[q], wq = W_STAGE[q];
      for (i = 0; i < NX; ++i) m->xs[i] = q ? m->xk[i] + cq * m->kq[i] : m->xk[i];
      for (i = 0; i < nS; ++i) m->Ss[i] = q ? m->S[i] + cq * m->D[i] : m->S[i];
      m->arg[0] = m->xs; m->arg[1] = u;
      m->res[0] = m->kq; m->res[1] = m->fx; m->res[2] = m->fu;
      if ({{ name }}_fjac(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
      if (sub || q) sensitivity_rate(m, m->Ss, m->D);
      else jacobian_rate(m, m->D);
      for (i = 0; i < NX; ++i) m->kacc[i] += wq * m->kq[i];
      for (i = 0; i < nS; ++i) m->Dacc[i] += wq * m->D[i];
    }
    for (i = 0; i < NX; ++i) m->xk[i] += RK_H / 6 * m->kacc[i];
    for (i = 0; i < nS; ++i) m->S[i] += RK_H / 6 * m->Dacc[i];
  }
#endif
#if MODEL_RK4
  for (i = 0; i < NX; ++i) {
    const double* si = m->S + i * (NX + NU);
    double* Li = L + i * NL;
    double wi = m->xk[i];
    for (j = 0; j < NX + NU; ++j) { Li[j] = si[j]; wi -= si[j] * (j < NX ? x[j] : u[j - NX]); }
    for (j = 0; j < NU; ++j) Li[NX + NU + j] = 0;
    Li[NL - 1] = wi;
  }
#else
  m->arg[0] = x; m->arg[1] = u;
  m->res[0] = m->Ad; m->res[1] = m->Bd; m->res[2] = m->wd;
  if ({{ name }}_affine(m->arg, m->res, (casadi_int*) m->iw, m->w, 0)) return 1;
  for (i = 0; i < NX; ++i) {  /* Ad, Bd come column-major from CasADi */
    double* Li = L + i * NL;
    for (j = 0; j < NX; ++j) Li[j] = m->Ad[i + NX * j];
    for (j = 0; j < NU; ++j) { Li[NX + j] = m->Bd[i + NX * j]; Li[NX + NU + j] = 0; }
    Li[NL - 1] = m->wd[i];
  }
#endif
  return 0;
}

static double amax(double a, double b) { return a > b ? a : b; }

/* One bound row l <= v <= u with multiplier lam (> 0 at an active upper bound): its primal scale, violation,
   complementarity gap and wrong-sign multiplier folded into s[0..3]. */
static void bound_row(double v, double l, double u, double lam, double* s) {
  if (isfinite(l) || isfinite(u)) s[0] = amax(s[0], fabs(v));
  if (isfinite(l)) { s[0] = amax(s[0], fabs(l)); s[1] = amax(s[1], l - v); }
  if (isfinite(u)) { s[0] = amax(s[0], fabs(u)); s[1] = amax(s[1], v - u); }
  if (lam > 0) { if (isfinite(u)) s[2] = amax(s[2], lam * fabs(u - v)); else s[3] = amax(s[3], lam); }
  if (lam < 0) { if (isfinite(l)) s[2] = amax(s[2], -lam * fabs(v - l)); else s[3] = amax(s[3], -lam); }
}

/* The KKT certificate of the QP's answer (z_new, lam_x_new, lam_a_new), as ocpkit.qp.certificate computes it, in
   CasADi's multiplier convention h z + g + aᵀ lam_a + lam_x = 0: m->cert = the relative residuals of
   stationarity, primal feasibility, complementarity and dual sign; returns the code of the first one above
   CERT_TOL (or NaN), 0 when all hold. A stale or zero answer fails stationarity.
   Python twin: ocpkit.qp.certificate.certify (tests/test_twins.py). */
static int certify(mem_t* m) {
  const double *z = m->z_new, *lx = m->lam_x_new, *la = m->lam_a_new;
  double s[4] = {0, 0, 0, 0}, norms[4] = {0, 0, 0, 0}, stat = 0, s_d, s_p;
  int i, j, r;
  for (i = 0; i < NZ; ++i) {
    double hz = 0, al = 0;
    for (j = 0; j < NZ; ++j) hz += m->h[i + NZ * j] * z[j];
    for (r = 0; r < NA; ++r) al += m->a[r + NA * i] * la[r];
    norms[0] = amax(norms[0], fabs(hz)); norms[1] = amax(norms[1], fabs(m->g[i]));
    norms[2] = amax(norms[2], fabs(al)); norms[3] = amax(norms[3], fabs(lx[i]));
    stat = amax(stat, fabs(hz + m->g[i] + al + lx[i]));
    bound_row(z[i], m->lbx[i], m->ubx[i], lx[i], s);
  }
  for (r = 0; r < NA; ++r) {
    double az = 0;
    for (j = 0; j < NZ; ++j) az += m->a[r + NA * j] * z[j];
    bound_row(az, m->lba[r], m->uba[r], la[r], s);
  }
  s_d = 1 + amax(amax(norms[0], norms[1]), amax(norms[2], norms[3]));
  s_p = 1 + s[0];
  m->cert[0] = stat / s_d;
  m->cert[1] = s[1] / s_p;
  m->cert[2] = s[2] / (s_d * s_p);
  m->cert[3] = s[3] / s_d;
  for (i = 0; i < {{ N }}_NCERT; ++i) if (!(m->cert[i] <= {{ N }}_CERT_TOL)) return {{ N }}_CERT_{{ cert_names[0] }} + i;
  return 0;
}

/* Rounding in h (NZ ε max h_ii) beyond ROUNDING_MARGIN of the curvature h has in exact arithmetic (φᵀφ⊗R): the
   prediction model diverges over the horizon and no solver's answer means anything (QP.not_definite).
   Python twin: ocpkit.qp.quadratic_program.QP.not_definite (tests/test_twins.py). */
static int ill_conditioned(const mem_t* m) {
  double big = 0;
  int i;
  for (i = 0; i < NZ; ++i) big = amax(big, fabs(m->h[i * (NZ + 1)]));
  return !(NZ * DBL_EPSILON * big <= ROUNDING_MARGIN * CURVATURE);
}

{% if failures %}
/* The status of the QP solver's nonzero return and its reason
   ({{ failures_source }}). */
static int status_of_return(mem_t* m, int rc) {
  enum {
{% for rc, (flag, _, _) in failures.items() %}
    {{ flag }} = {{ rc }}{{ "," if not loop.last }}
{% endfor %}
  };
  switch (rc) {
{% for rc, (flag, status, reason) in failures.items() %}
  case {{ flag }}: return fail(m, {{ N }}_{{ status | upper }}, {{ N }}_REASON_{{ reason }});
{% endfor %}
  default: return fail(m, {{ N }}_LIMITED, {{ N }}_REASON_NONE);
  }
}
{% endif %}

/* The QP in m (h, g, a, lba, uba, lbx, ubx) checked, solved (warm-started from the last solution where m->warm)
   and certified: its status. On a success z_new and the multipliers hold the answer; otherwise
   m->solver_rc says why (the solver's return, or a certificate code). */
static int solve_qp(mem_t* m) {
  int rc;
  m->solver_rc = 0;
  m->reason = {{ N }}_REASON_NONE;
  if (!all_finite(m->h, NZ * NZ) || !all_finite(m->g, NZ) || !all_finite(m->a, NA * NZ)
      || any_nan(m->lba, NA) || any_nan(m->uba, NA) || any_nan(m->lbx, NZ) || any_nan(m->ubx, NZ))
    return fail(m, {{ N }}_NAN, {{ N }}_REASON_QP_DATA);
  if (any_above(m->lba, m->uba, NA) || any_above(m->lbx, m->ubx, NZ))
    return fail(m, {{ N }}_INFEASIBLE, {{ N }}_REASON_BOUNDS_CROSSED);
  if (ill_conditioned(m)) {
    m->solver_rc = {{ N }}_ILL_CONDITIONED;
    return fail(m, {{ N }}_EXCEPTION, {{ N }}_REASON_ILL_CONDITIONED);
  }
  m->arg[0] = m->h; m->arg[1] = m->g; m->arg[2] = m->a; m->arg[3] = m->lba; m->arg[4] = m->uba;
  m->arg[5] = m->lbx; m->arg[6] = m->ubx;
  m->arg[7] = m->warm ? m->z : 0; m->arg[8] = m->warm ? m->lam_x : 0; m->arg[9] = m->warm ? m->lam_a : 0;
  m->arg[10] = 0; m->arg[11] = 0;
  m->res[0] = m->z_new; m->res[1] = 0; m->res[2] = m->lam_a_new; m->res[3] = m->lam_x_new;
  rc = {{ name }}_qp_solve(m->arg, m->res, (casadi_int*) m->iw, m->w, m->solver_mem);
  m->solver_rc = rc;
  if (rc) return {{ "status_of_return(m, rc)" if failures else "fail(m, " ~ N ~ "_LIMITED, " ~ N ~ "_REASON_NONE)" }};
  if (!all_finite(m->z_new, NZ)) return fail(m, {{ N }}_NAN, {{ N }}_REASON_NON_FINITE_SOLUTION);
  rc = certify(m);
  if (rc) {
    m->solver_rc = rc;
    return fail(m, {{ N }}_LIMITED, {{ N }}_REASON_CERTIFICATE_FAILED);
  }
  return {{ N }}_SUCCESS;
}

int {{ name }}_solve_qp(mem_t* m, const double* h, const double* g, const double* a, const double* lba,
                     const double* uba, const double* lbx, const double* ubx, double* z, int* status) {
  memcpy(m->h, h, sizeof m->h);
  memcpy(m->g, g, sizeof m->g);
  if (NA) {
    memcpy(m->a, a, NA * NZ * sizeof(double));
    memcpy(m->lba, lba, NA * sizeof(double));
    memcpy(m->uba, uba, NA * sizeof(double));
  }
  memcpy(m->lbx, lbx, sizeof m->lbx);
  memcpy(m->ubx, ubx, sizeof m->ubx);
  m->warm = 0;
  *status = solve_qp(m);
  memcpy(z, m->z_new, sizeof m->z_new);
  return *status;
}

void {{ name }}_certificate(const mem_t* m, double* residuals) {
  memcpy(residuals, m->cert, sizeof m->cert);
}

/* Seconds on a monotonic clock (0 where there is none: the split then reads 0). */
static double seconds(void) {
#if defined(CLOCK_MONOTONIC)
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
#else
  return 0.0;
#endif
}

#if LIN_TRAJ
/* The real-time iteration (ocpkit.solvers.rti.RealTimeIteration, LinearMPC's "trajectory" linearization): the
   model linearized stage by stage along the shifted plan, the condensed QP of these time-varying models, and
   ITERATIONS Gauss–Newton steps, each linearizing along the last one's solution. */

/* ū_k = Σ_j φ_kj z_j for the stages k = 0 … HORIZON−1 (HORIZON x NU, row-major). */
static void stage_inputs(const double* z, double* u) {
  int k;
  for (k = 0; k < {{ N }}_HORIZON; ++k) knot_sum(PHI_ALL + k * NP, z, u + k * NU);
}

/* The trajectory of the first iteration (LinearMPC.shifted_plan): knots z̄ = the plan shifted a step (the input goal
   at a cold start), ū_k = Φ_k z̄, x̄_0 = x and x̄_k the plan's predicted x_{k+1} (x held where there is none). */
static void shifted_plan(mem_t* m, const double* x) {
  int k;
  shifted_knots(m, m->zlin);
  stage_inputs(m->zlin, m->ubark);
  for (k = 0; k < {{ N }}_HORIZON; ++k)
    memcpy(m->xbar + k * NX, k && m->has_xplan ? m->xplan + (k + 1) * NX : x, NX * sizeof(double));
}

/* out = L [x; u; 0; 1] = A x + B u + w: the affine model's step. */
static void affine_step(const double* L, const double* x, const double* u, double* out) {
  int i, j;
  for (i = 0; i < NX; ++i) {
    const double* Li = L + i * NL;
    double s = Li[NL - 1];
    for (j = 0; j < NX; ++j) s += Li[j] * x[j];
    for (j = 0; j < NU; ++j) s += Li[NX + j] * u[j];
    out[i] = s;
  }
}

/* Λ_k of every stage about (x̄_k, ū_k). Returns a status (its reason in m->reason). */
static int stage_models(mem_t* m) {
  int k;
  for (k = 0; k < {{ N }}_HORIZON; ++k) {
    double* L = m->LamK + k * NX * NL;
    if (!all_finite(m->xbar + k * NX, NX) || !all_finite(m->ubark + k * NU, NU))
      return fail(m, {{ N }}_NAN, {{ N }}_REASON_NON_FINITE_MODEL);
    if (affine_model(m, m->xbar + k * NX, m->ubark + k * NU, L))
      return fail(m, {{ N }}_EXCEPTION, {{ N }}_REASON_NON_FINITE_MODEL);
    if (!all_finite(L, NX * NL)) return fail(m, {{ N }}_NAN, {{ N }}_REASON_NON_FINITE_MODEL);
  }
  return {{ N }}_SUCCESS;
}

/* The condensed QP of the stage models (CondensedQP.build with one model per stage): the rows [v_k S_k] of
   x_k = S_k z + v_k (prev, NX x NZ1: column 0 is v_k) advance by x_{k+1} = A_k x_k + B_k Φ_k z + w_k, only over the
   columns of the knots active so far (ACTIVE), and each adds its stage cost to Pq, towards x_goal,k at xg + k gs
   (gs = 0: one goal held).
   Python twin: ocpkit.qp.transcription.CondensedQP._predict_ltv and _cost_ltv (tests/test_twins.py). */
static void condense_ltv(mem_t* m, const double* x, const double* xg, int gs) {
  double *prev = m->prev, *next = m->next, *sw;
  int i, j, k, u, cols = 0;
  for (i = 0; i < NX * NZ1; ++i) prev[i] = next[i] = 0;
  for (i = 0; i < NX; ++i) prev[i * NZ1] = x[i];
  for (i = 0; i < NZ1 * NZ1; ++i) m->Pq[i] = 0;
  for (k = 0; k < {{ N }}_HORIZON; ++k) {
    const double* L = m->LamK + k * NX * NL;
    const int c = ACTIVE[k];
    for (i = 0; i < NX; ++i) {
      double* nr = next + i * NZ1;
      for (j = 0; j <= c; ++j) nr[j] = 0;
      nr[0] = L[i * NL + NL - 1];
      for (j = 0; j < NP; ++j) {
        const double f = PHI_ALL[k * NP + j];
        if (f != 0) for (u = 0; u < NU; ++u) nr[1 + j * NU + u] += f * L[i * NL + NX + u];
      }
    }
    gemm_nx(NX, cols + 1, L, NL, 1, prev, NZ1, next, NZ1, 0);
    add_stage(m, next, c + 1, NZ1, 0, xg + (k + 1) * gs, m->Pq, NZ1);
#if NB > 0
    for (j = 0; j < NB; ++j) state_bound_row(m, k * NB + j, j, next + XB_COMP[j] * NZ1, NZ);  /* x_{k+1}'s */
#endif
    cols = c;
    sw = prev; prev = next; next = sw;
  }
#if HAS_DQT
  add_terminal_weight(m, prev, xg + {{ N }}_HORIZON * gs);
#endif
  finish_qp(m);
}

static double max_change(const double* a, const double* b, int n) {
  double d = 0;
  int i;
  for (i = 0; i < n; ++i) d = amax(d, fabs(a[i] - b[i]));
  return d;
}

/* The iterations of one step towards the goals at goal + k gs (moving: a goal window whose x_goal moves): their
   summed split in t (where given; the first model's time from t0). Returns the status; on success the plan, its
   predicted states and the warm start hold the last good iterate.
   Python twin: ocpkit.solvers.rti.RealTimeIteration._solve (tests/test_twins.py). */
static int rti(mem_t* m, const double* x, const double* goal, int gs, int moving, double* u_out, double* t, double t0) {
  const int nxs = ({{ N }}_HORIZON + 1) * NX;
  int it, k, rc, done = 0;
  double t1 = 0, moved = INFINITY;
  shifted_plan(m, x);
  for (it = 0; it < ITERATIONS; ++it) {
    if (t && it) t0 = seconds();
    rc = stage_models(m);
    if (t) { t1 = seconds(); t[0] += t1 - t0; }
    if (rc == {{ N }}_SUCCESS) {
      condense_ltv(m, x, goal, gs);
      if (moving && window_inputs(m, goal)) return fallback(m, u_out, fail(m, {{ N }}_NAN, {{ N }}_REASON_NON_FINITE_MODEL));
      if (t) { t0 = seconds(); t[1] += t0 - t1; }
      rc = solve_qp(m);
      if (t) t[2] += seconds() - t0;
    }
    if (rc != {{ N }}_SUCCESS) {
      if (!done) return fallback(m, u_out, rc);
      /* the last good iterate stays the plan; the next step starts the QP cold, as after any failure */
      memcpy(m->plan, m->zgood, sizeof m->zgood);
      memcpy(m->xplan, m->xgood, sizeof m->xgood);
      m->warm = 0;
      m->reason = {{ N }}_REASON_NONE;  /* a success */
      break;
    }
    commit_plan(m);
    /* the predicted states x_0 … x_T through the stage models */
    memcpy(m->xplan, x, NX * sizeof(double));
    stage_inputs(m->plan, m->ubark);
    for (k = 0; k < {{ N }}_HORIZON; ++k)
      affine_step(m->LamK + k * NX * NL, m->xplan + k * NX, m->ubark + k * NU, m->xplan + (k + 1) * NX);
    m->has_xplan = 1;
    if (done) moved = amax(max_change(m->plan, m->zgood, NZ), max_change(m->xplan, m->xgood, nxs));
    memcpy(m->zgood, m->plan, sizeof m->zgood);
    memcpy(m->xgood, m->xplan, sizeof m->xgood);
    done = it + 1;
    if (moved <= RTI_TOL) break;
    /* the next iteration linearizes along this one: x̄ = [x; x_1 … x_{T−1}], ū = Φ z (ubark, set above) */
    memcpy(m->xbar + NX, m->xplan + NX, ({{ N }}_HORIZON - 1) * NX * sizeof(double));
  }
  knot_sum(PHI0, m->plan, u_out);
  return {{ N }}_SUCCESS;
}

int {{ name }}_states(const mem_t* m, double* x_pred) {
  if (!m->has_xplan) return 1;
  memcpy(x_pred, m->xplan, sizeof m->xplan);
  return 0;
}
#endif

#if !LIN_TRAJ
/* The step about one affine model (linearization "goal" or "plan"): the model about (x, ū), the condensed QP and its
   solve, their split in t (where given; the model's time from t0). Stage k's goal at goal + k gs (moving: a goal
   window whose x_goal moves{{ "; stage k's obstacles at obs + k os" if obstacles }}). Returns the status. */
static int step_about_one_model(mem_t* m, const double* x, const double* goal, {{ "int gs, " if task }}int moving,
                                {{ "const double* obs, int os, " if obstacles }}double* u_out, double* t, double t0) {
  double t1 = 0, t2 = 0;
  int rc;
  memcpy(m->ubar, m->ug, sizeof m->ubar);
#if LIN_PLAN
  if (m->has_plan) knot_sum(W0, m->plan, m->ubar);
#endif
  if (affine_model(m, x, m->ubar, m->Lam1))
    return fallback(m, u_out, fail(m, {{ N }}_EXCEPTION, {{ N }}_REASON_NON_FINITE_MODEL));
  if (!all_finite(m->Lam1, NX * NL)) return fallback(m, u_out, fail(m, {{ N }}_NAN, {{ N }}_REASON_NON_FINITE_MODEL));
  if (t) { t1 = seconds(); t[0] = t1 - t0; }
  condense(m, x, goal);
  if (moving && window_terms(m, goal))
    return fallback(m, u_out, fail(m, {{ N }}_NAN, {{ N }}_REASON_NON_FINITE_MODEL));
{% if task %}
  if (task_terms(m, x, goal, gs{{ ", obs, os" if obstacles }}))  /* a residual's evaluation failed */
    return fallback(m, u_out, fail(m, {{ N }}_EXCEPTION, {{ N }}_REASON_NON_FINITE_MODEL));
{% endif %}
  if (t) { t2 = seconds(); t[1] = t2 - t1; }
  rc = solve_qp(m);
  if (t) t[2] = seconds() - t2;
  if (rc != {{ N }}_SUCCESS) return fallback(m, u_out, rc);
  commit_plan(m);
  knot_sum(PHI0, m->plan, u_out);
  return {{ N }}_SUCCESS;
}
#endif

/* One step from x towards the goals at goal + k gs (gs = 0: one goal held; NG: a goal window, moving where its x_goal
   moves{{ "; obstacles at obs + k os" if obstacles }}): the input goal u_g of row 0, then the step. */
static int step(mem_t* m, const double* x, const double* goal, int gs,
                {{ "const double* obs, int os, " if obstacles }}double* u_out, int* status, double* t) {
  double t0 = 0;
  int i, failed = 0, moving = 0;
  for (i = gs; i < ({{ N }}_HORIZON + 1) * gs && !moving; ++i) moving = i % gs < NX && goal[i] != goal[i % gs];
  if (t) { t[0] = t[1] = t[2] = 0; t0 = seconds(); }
  m->solver_rc = 0;
  m->reason = {{ N }}_REASON_NONE;
  memcpy(m->ug, U_GOAL, sizeof m->ug);
#if HAS_K
  add_goal_gain(goal, m->ug);
#endif
#if HAS_GOAL_INPUT
  failed = add_goal_input(m, goal, m->ug);
#endif
  if (failed || !all_finite(m->ug, NU)) {
    for (i = 0; i < NU; ++i) if (!isfinite(m->ug[i])) m->ug[i] = 0;  /* the cold fallback's input, as in Python */
    *status = fallback(m, u_out, fail(m, {{ N }}_NAN, {{ N }}_REASON_NON_FINITE_MODEL));
    return *status;
  }
#if LIN_TRAJ
  *status = rti(m, x, goal, gs, moving, u_out, t, t0);
#else
  *status = step_about_one_model(m, x, goal, {{ "gs, " if task }}moving, {{ "obs, os, " if obstacles }}u_out, t, t0);
#endif
  return *status;
}

int {{ name }}_step(mem_t* m, const double* x, const double* goal, double* u_out, int* status) {
  return {{ name }}_step_timed(m, x, goal, u_out, status, 0);
}

int {{ name }}_step_timed(mem_t* m, const double* x, const double* goal, double* u_out, int* status, double* t) {
  return step(m, x, goal, 0, {{ "OBSTACLES, 0, " if obstacles }}u_out, status, t);
}
{% set obs_arg = "const double* obstacles, " if obstacles else "" %}

int {{ name }}_step_window(mem_t* m, const double* x, const double* goals, {{ obs_arg }}double* u_out, int* status) {
  return {{ name }}_step_window_timed(m, x, goals, {{ "obstacles, " if obstacles }}u_out, status, 0);
}

int {{ name }}_step_window_timed(mem_t* m, const double* x, const double* goals, {{ obs_arg }}double* u_out,
                               int* status, double* t) {
{% if obstacles %}
  return step(m, x, goals, NG, obstacles ? obstacles : OBSTACLES, obstacles ? 4 * {{ N }}_NOB : 0, u_out, status, t);
{% else %}
  return step(m, x, goals, NG, u_out, status, t);
{% endif %}
}

void {{ name }}_knots(const mem_t* m, double* knots) {
  int i;
  for (i = 0; i < NZ; ++i) knots[i] = m->plan[i];
}
{% if obstacles %}

void {{ name }}_set_plan(mem_t* m, const double* knots) {
  int i;
  m->has_plan = knots != 0;
  for (i = 0; i < NZ; ++i) m->plan[i] = knots ? knots[i] : 0;
}
{% endif %}

int {{ name }}_solver_return(const mem_t* m) { return m->solver_rc; }

int {{ name }}_last_reason(const mem_t* m) { return m->reason; }

const char* {{ name }}_qp_solver(void) { return "{{ qp }}"; }

const char* {{ name }}_status_string(int status) {
  static const char* const names[] = { {% for status in statuses %}"{{ status }}"{{ ", " if not loop.last }}{% endfor %} };
  return status >= 0 && status < (int) (sizeof names / sizeof names[0]) ? names[status] : "unknown";
}

const char* {{ name }}_reason_string(int reason) {
  static const char* const names[{{ N }}_NREASONS] = {
    "none",
{% for reason in reasons %}
    "{{ reason }}"{{ "," if not loop.last }}
{% endfor %}
  };
  return reason >= 0 && reason < {{ N }}_NREASONS ? names[reason] : "unknown";
}

const char* {{ name }}_ocp_digest(void) {
  return
{% for entry in digest %}
    "{{ entry }}{{ "; " if not loop.last }}"{{ ";" if loop.last }}
{% endfor %}
}

int {{ name }}_model_step(mem_t* m, const double* x, const double* u, double* x_next) {
  m->arg[0] = x; m->arg[1] = u; m->res[0] = x_next;
  return {{ name }}_model(m->arg, m->res, (casadi_int*) m->iw, m->w, 0);
}

size_t {{ name }}_memory_size(void) { return sizeof(mem_t); }

void {{ name }}_dims(int* nx, int* nu, int* knots, int* horizon) {
  *nx = NX; *nu = NU; *knots = NP; *horizon = {{ N }}_HORIZON;
}
