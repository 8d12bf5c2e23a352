"""
The numba kernel behind :mod:`rotor_id.estimation.kernels` (imported only from there).

One RK4 step of x′ = F x + g and of its sensitivities S′ = F S + (∂F/∂p) x + ∂g/∂p, step
after step, both through the same stages (no transition matrices). F and ∂F/∂p enter as their
non-zero entries.

Time-invariant records (:class:`rotor_id.estimation.simulate.TimeInvariantPlan`) take
:func:`affine_run` instead: one affine map per sample interval, formed with its parameter
derivatives from F, B, e once per parameter vector (:func:`interval_map`), then states,
sensitivities, outputs and per-channel residual sums (:func:`affine_scan`); and output error's
Gauss-Newton iteration on such a record runs whole in :func:`gn_iteration`, its whole fit (for
a caller without a progress callback) in :func:`gn_fit`.
"""

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic
import numpy as np


@njit(cache=True, nogil=True)
def _sensitivity_stage(F_val, F_i, F_j, dF_val, dF_p, dF_i, dF_j, dg, x, S, prev, scale, work,
                       out):
    """
    Set out = F (S + scale · prev) + (∂F/∂p) x + ∂g/∂p.

    S, prev, work (scratch) and out are (n, k); the forcing (∂F/∂p) x + ∂g/∂p enters the first
    kp columns only (dg is (kp, n); the other columns, e.g. initial states, have none). prev is
    unused at scale 0.
    """
    n, k = out.shape
    kp = dg.shape[0]
    if scale == 0.0:
        stage = S
    else:
        stage = work
        for j in range(n):
            for q in range(k):
                stage[j, q] = S[j, q] + scale * prev[j, q]
    out[:, :] = 0.0
    for q in range(kp):
        for i in range(n):
            out[i, q] = dg[q, i]
    for e in range(dF_p.shape[0]):
        out[dF_i[e], dF_p[e]] += dF_val[e] * x[dF_j[e]]
    for e in range(F_i.shape[0]):
        f = F_val[e]
        i = F_i[e]
        j = F_j[e]
        for q in range(k):
            out[i, q] += f * stage[j, q]


@njit(cache=True, nogil=True)
def _state_stage(F_val, F_i, F_j, g, x, out):
    """Set out = F x + g (F sparse)."""
    for i in range(x.shape[0]):
        out[i] = g[i]
    for e in range(F_i.shape[0]):
        out[F_i[e]] += F_val[e] * x[F_j[e]]


@njit(cache=True, nogil=True)
def rk4_scan(F_val, F_i, F_j, g, dF_val, dF_p, dF_i, dF_j, dg, h, substeps, x0, S0, xs, Ss):
    """
    Run M = len(h) RK4 steps from (x0, S0); store every ``substeps``-th in xs[1:], Ss[1:].

    F and g (2M+1, n) at the start, middle and end of every step (shared with the next step),
    as :func:`rotor_id.estimation.simulate.fine_grid` lays them out; F as its non-zero entries
    F_val (1 or 2M+1, nnz) at (F_i, F_j), ∂F/∂p as its non-zero entries dF_val
    (1 or 2M+1, nnz) at (dF_p, dF_i, dF_j); ∂g/∂p as dg (2M+1, kp, n) for the first kp of the
    k sensitivity columns (the others, e.g. initial states, have no forcing). The
    sensitivities S′ = F S + (∂F/∂p) x + ∂g/∂p take the same RK4 stages as the state, which is
    the parameter derivative of the state's RK4 step (the step is linear in x and in S). xs
    (M/substeps + 1, n) and Ss (…, n, k) receive the samples.
    """
    n = x0.shape[0]
    k = S0.shape[1]
    x = x0.copy()
    S = S0.copy()
    xs[0] = x
    Ss[0] = S0
    xt = np.empty(n)
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    d1 = np.empty((n, k))
    d2 = np.empty((n, k))
    d3 = np.empty((n, k))
    d4 = np.empty((n, k))
    work = np.empty((n, k))
    const_F = F_val.shape[0] == 1
    const_dF = dF_val.shape[0] == 1
    for s in range(h.shape[0]):
        a = 2 * s
        b = a + 1
        c = a + 2
        fa = 0 if const_F else a
        fb = 0 if const_F else b
        fc = 0 if const_F else c
        da = 0 if const_dF else a
        db = 0 if const_dF else b
        dc = 0 if const_dF else c
        hs = h[s]
        # the stages of the state and of its sensitivities
        _state_stage(F_val[fa], F_i, F_j, g[a], x, k1)
        _sensitivity_stage(F_val[fa], F_i, F_j, dF_val[da], dF_p, dF_i, dF_j, dg[a], x, S,
                           d1, 0.0, work, d1)
        for i in range(n):
            xt[i] = x[i] + 0.5 * hs * k1[i]
        _state_stage(F_val[fb], F_i, F_j, g[b], xt, k2)
        _sensitivity_stage(F_val[fb], F_i, F_j, dF_val[db], dF_p, dF_i, dF_j, dg[b], xt, S,
                           d1, 0.5 * hs, work, d2)
        for i in range(n):
            xt[i] = x[i] + 0.5 * hs * k2[i]
        _state_stage(F_val[fb], F_i, F_j, g[b], xt, k3)
        _sensitivity_stage(F_val[fb], F_i, F_j, dF_val[db], dF_p, dF_i, dF_j, dg[b], xt, S,
                           d2, 0.5 * hs, work, d3)
        for i in range(n):
            xt[i] = x[i] + hs * k3[i]
        _state_stage(F_val[fc], F_i, F_j, g[c], xt, k4)
        _sensitivity_stage(F_val[fc], F_i, F_j, dF_val[dc], dF_p, dF_i, dF_j, dg[c], xt, S,
                           d3, hs, work, d4)
        w = hs / 6.0
        for i in range(n):
            x[i] += w * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
            for q in range(k):
                S[i, q] += w * (d1[i, q] + 2.0 * d2[i, q] + 2.0 * d3[i, q] + d4[i, q])
        if (s + 1) % substeps == 0:
            j = (s + 1) // substeps
            xs[j] = x
            Ss[j] = S


def rk4_scan_example():
    """Return arguments of the types simulate passes to rk4_scan (its one signature)."""
    n, k, kp = 2, 2, 1
    idx = np.zeros(1, dtype=np.int64)
    return (np.zeros((1, 1)), idx, idx, np.zeros((3, n)), np.zeros((1, 1)), idx, idx, idx,
            np.zeros((3, kp, n)), np.ones(1), 1, np.zeros(n), np.zeros((n, k)),
            np.empty((2, n)), np.empty((2, n, k)))


def warm_up():
    """Compile (or load from the cache) for the argument types simulate passes."""
    rk4_scan(*rk4_scan_example())


@njit(cache=True, nogil=True)
def invert_in_place(A, inverse):
    """Set inverse = A⁻¹ (Gauss-Jordan, partial pivoting); return log|det A| (-inf: singular)."""
    m = A.shape[0]
    work = A.copy()
    for i in range(m):
        for j in range(m):
            inverse[i, j] = 1.0 if i == j else 0.0
    logdet = 0.0
    for col in range(m):
        pivot = col
        for r in range(col + 1, m):
            if abs(work[r, col]) > abs(work[pivot, col]):
                pivot = r
        if work[pivot, col] == 0.0:
            return -np.inf
        if pivot != col:
            for j in range(m):
                tmp = work[col, j]
                work[col, j] = work[pivot, j]
                work[pivot, j] = tmp
                tmp = inverse[col, j]
                inverse[col, j] = inverse[pivot, j]
                inverse[pivot, j] = tmp
        p = work[col, col]
        logdet += np.log(abs(p))
        for j in range(m):
            work[col, j] /= p
            inverse[col, j] /= p
        for r in range(m):
            if r != col:
                f = work[r, col]
                if f != 0.0:
                    for j in range(m):
                        work[r, j] -= f * work[col, j]
                        inverse[r, j] -= f * inverse[col, j]
    return logdet


@njit(cache=True, nogil=True)
def innovation_gain(P, Ht, R, PHT, B, Binv, K):
    """
    Kalman innovation covariance and gain, in place; return log det B.

    PHT = P Hᵀ, B = H P Hᵀ + R (symmetrised), Binv = B⁻¹ and K = P Hᵀ B⁻¹: the one copy of
    these products for the filter scan here and the filter-sensitivity scan
    (_filter_kernels_numba, which compiles it into its own cache).
    """
    n, m = P.shape[0], Ht.shape[0]
    for i in range(n):
        for a in range(m):
            acc = 0.0
            for j in range(n):
                acc += P[i, j] * Ht[a, j]
            PHT[i, a] = acc
    for a in range(m):
        for b in range(m):
            acc = R[a, b]
            for i in range(n):
                acc += Ht[a, i] * PHT[i, b]
            B[a, b] = acc
    for a in range(m):
        for b in range(a + 1, m):
            sym = 0.5 * (B[a, b] + B[b, a])
            B[a, b] = sym
            B[b, a] = sym
    logdet = invert_in_place(B, Binv)
    for i in range(n):
        for b in range(m):
            acc = 0.0
            for a in range(m):
                acc += PHT[i, a] * Binv[a, b]
            K[i, b] = acc
    return logdet


@njit(cache=True, nogil=True)
def filter_scan(Phi, c, Q, H, d, y, x0, R, P0, steady, nu, B, gains, cost, x_last, P_last,
                x_pred, P_pred, x_filt, P_filt):
    """
    Kalman filters of K stacked discrete models, the equations of filter_error.filter_batch.

    Phi (T-1, K, n, n), c (T-1, K, n), Q (T-1, K, n, n), H (T, K, m, n), d (T, K, m), y (T, m),
    x0 (K, n), R (K, m, m), P0 (K, n, n) the covariance of x0 (filter error: zero), or with
    ``steady`` the steady-state covariance used throughout. Fills nu (K, T, m),
    B (K, T, m, m), gains (K, T, n, m), cost (K,) (Σ νᵀB⁻¹ν + log|B|), and the filtered
    state x_last (K, n) and covariance P_last (K, n, n) after the last sample (the live
    state estimator's batch, :meth:`rotor_id.nodes.live.StreamingKalman.advance`). Where
    x_pred (K, T, n) has the T samples (not 0) and the gain is time-varying, also every
    predicted and filtered state and covariance: x_pred, x_filt (K, T, n), P_pred, P_filt
    (K, T, n, n) (:func:`rotor_id.estimation.kalman.kalman_filter`'s).
    """
    T = y.shape[0]
    m = y.shape[1]
    K_ = x0.shape[0]
    n = x0.shape[1]
    x = np.empty(n)
    xn = np.empty(n)
    P = np.empty((n, n))
    PHT = np.empty((n, m))
    Bj = np.empty((m, m))
    Binv = np.empty((m, m))
    Kj = np.empty((n, m))
    KB = np.empty((n, m))
    PP = np.empty((n, n))
    v = np.empty(m)
    keep = x_pred.shape[1] > 0
    for kk in range(K_):
        for i in range(n):
            x[i] = x0[kk, i]
            for j in range(n):
                P[i, j] = P0[kk, i, j]
        total = 0.0
        for t in range(T):
            Ht = H[t, kk]
            if keep:
                for i in range(n):
                    x_pred[kk, t, i] = x[i]
                    for j in range(n):
                        P_pred[kk, t, i, j] = P[i, j]
            for a in range(m):
                acc = y[t, a] - d[t, kk, a]
                for i in range(n):
                    acc -= Ht[a, i] * x[i]
                v[a] = acc
                nu[kk, t, a] = acc
            logdet = innovation_gain(P, Ht, R[kk], PHT, Bj, Binv, Kj)
            quad = 0.0
            for a in range(m):
                for b in range(m):
                    quad += v[a] * Binv[a, b] * v[b]
                    B[kk, t, a, b] = Bj[a, b]
            for i in range(n):
                for a in range(m):
                    gains[kk, t, i, a] = Kj[i, a]
            total += quad + logdet
            for i in range(n):
                acc = x[i]
                for a in range(m):
                    acc += Kj[i, a] * v[a]
                x[i] = acc
            if not steady:
                for i in range(n):
                    for b in range(m):
                        acc = 0.0
                        for a in range(m):
                            acc += Kj[i, a] * Bj[a, b]
                        KB[i, b] = acc
                for i in range(n):
                    for j in range(n):
                        acc = 0.0
                        for b in range(m):
                            acc += KB[i, b] * Kj[j, b]
                        P[i, j] -= acc
            if keep:
                for i in range(n):
                    x_filt[kk, t, i] = x[i]
                    for j in range(n):
                        P_filt[kk, t, i, j] = P[i, j]
            if t < T - 1:
                F = Phi[t, kk]
                for i in range(n):
                    acc = c[t, kk, i]
                    for j in range(n):
                        acc += F[i, j] * x[j]
                    xn[i] = acc
                for i in range(n):
                    x[i] = xn[i]
                if not steady:
                    for i in range(n):
                        for j in range(n):
                            acc = 0.0
                            for q in range(n):
                                acc += F[i, q] * P[q, j]
                            PP[i, j] = acc
                    for i in range(n):
                        for j in range(n):
                            acc = Q[t, kk, i, j]
                            for q in range(n):
                                acc += PP[i, q] * F[j, q]
                            P[i, j] = acc
                    for i in range(n):
                        for j in range(i + 1, n):
                            s = 0.5 * (P[i, j] + P[j, i])
                            P[i, j] = s
                            P[j, i] = s
        cost[kk] = total
        for i in range(n):
            x_last[kk, i] = x[i]
            for j in range(n):
                P_last[kk, i, j] = P[i, j]


def filter_scan_example():
    """Return arguments of the types filter_batch passes to filter_scan (its one signature)."""
    K_, T, n, m = 1, 2, 2, 1
    return (np.zeros((T - 1, K_, n, n)), np.zeros((T - 1, K_, n)), np.zeros((T - 1, K_, n, n)),
            np.ones((T, K_, m, n)), np.zeros((T, K_, m)), np.zeros((T, m)), np.zeros((K_, n)),
            np.ones((K_, m, m)), np.zeros((K_, n, n)), False, np.empty((K_, T, m)),
            np.empty((K_, T, m, m)), np.empty((K_, T, n, m)), np.empty(K_), np.empty((K_, n)),
            np.empty((K_, n, n)), np.empty((K_, T, n)), np.empty((K_, T, n, n)),
            np.empty((K_, T, n)), np.empty((K_, T, n, n)))


def initial_state_innovations_example():
    """Return arguments of the types filter error passes to initial_state_innovations."""
    T, n, m = 2, 2, 1
    return (np.zeros((T - 1, n, n)), np.zeros((T, n, m)), np.ones((T, m, n)), np.eye(n),
            np.empty((T, m, n)))


def warm_up_filter():
    """Compile (or load from the cache) the filter for the argument types filter_batch passes."""
    filter_scan(*filter_scan_example())
    initial_state_innovations(*initial_state_innovations_example())


@njit(cache=True, nogil=True)
def initial_state_innovations(Phi, gains, H, Psi, out):
    """
    ∂ν_j/∂x(t0) at fixed gains: out[j] = −H_j Ψ_j, Ψ_{j+1} = Φ_j (Ψ_j − K_j H_j Ψ_j).

    Phi (T-1, n, n), gains (T, n, m), H (T, m, n), Psi (n, f) the selection of the free
    states (overwritten), out (T, m, f).
    """
    T = H.shape[0]
    m = H.shape[1]
    n = Psi.shape[0]
    f = Psi.shape[1]
    HP = np.empty((m, f))
    A = np.empty((n, f))
    for t in range(T):
        for a in range(m):
            for c in range(f):
                acc = 0.0
                for i in range(n):
                    acc += H[t, a, i] * Psi[i, c]
                HP[a, c] = acc
                out[t, a, c] = -acc
        if t < T - 1:
            for i in range(n):
                for c in range(f):
                    acc = Psi[i, c]
                    for a in range(m):
                        acc -= gains[t, i, a] * HP[a, c]
                    A[i, c] = acc
            for i in range(n):
                for c in range(f):
                    acc = 0.0
                    for j in range(n):
                        acc += Phi[t, i, j] * A[j, c]
                    Psi[i, c] = acc


# -- time-invariant systems: one affine map per sample interval, prepared once per p ---------

@njit(cache=True, nogil=True)
def _mm(A, B, out):
    """Set out = A @ B for small dense matrices (out must not alias A or B)."""
    for i in range(A.shape[0]):
        for j in range(B.shape[1]):
            out[i, j] = 0.0
        for r in range(A.shape[1]):
            a = A[i, r]
            if a != 0.0:                    # ∂F/∂p is sparse
                for j in range(B.shape[1]):
                    out[i, j] += a * B[r, j]


@njit(cache=True, nogil=True)
def _mm_add(A, B, out):
    """Add A @ B to out."""
    for i in range(A.shape[0]):
        for r in range(A.shape[1]):
            a = A[i, r]
            if a != 0.0:
                for j in range(B.shape[1]):
                    out[i, j] += a * B[r, j]


@njit(cache=True, nogil=True)
def _add_stage(P, dP, Sx, dSx, c0, C, dC, block):
    """C[:, c0:c0+q] += P Sx and dC[p, :, c0:c0+q] += dP[p] Sx + P dSx[p] (one stage's inputs)."""
    q = Sx.shape[1]
    _mm(P, Sx, block)
    for i in range(block.shape[0]):
        for a in range(q):
            C[i, c0 + a] += block[i, a]
    for p in range(dP.shape[0]):
        _mm(dP[p], Sx, block)
        _mm_add(P, dSx[p], block)
        for i in range(block.shape[0]):
            for a in range(q):
                dC[p, i, c0 + a] += block[i, a]


@njit(cache=True, nogil=True)
def interval_map(F, B, e, dF, dB, de, h, substeps, Phi, dPhi, C, dC, ce, dce):
    """
    Form the affine map of a sample interval of ``substeps`` equal RK4 steps and its derivatives.

    For x′ = F x + B u + e with F, B, e constant, one RK4 step of length h with the input at
    the step's start, middle and end (u₀, u_m, u₁) is x⁺ = Φ₁ x + Γ₀ g₀ + Γ_m g_m + Γ₁ g₁,
    g = B u + e, with (expanding simulate.rk4_maps)

        Φ₁ = I + h/6 (A₁ + 2A₂ + 2A₃ + A₄),  A₁ = F, A₂ = F + h/2 F A₁, A₃ = F + h/2 F A₂,
        A₄ = F + h F A₃;
        Γ₀ = h/6 (I + hF + h²/2 F² + h³/4 F³),  Γ_m = h/6 (4I + 2hF + h²/2 F²),  Γ₁ = h/6 I.

    Composing the ``substeps`` steps gives x_{j+1} = Φ x_j + C U_j + c_e, U_j the inputs at
    the interval's 2·substeps + 1 stage times (stage-major, input-minor), and the derivatives
    of Φ, C, c_e with respect to the kp parameters whose ∂F, ∂B, ∂e are dF (kp, n, n),
    dB (kp, n, q), de (kp, n). Outputs: Phi (n, n), dPhi (kp, n, n), C (n, L), dC (kp, n, L),
    ce (n,), dce (kp, n), L = (2·substeps + 1)·q.
    """
    n = F.shape[0]
    q = B.shape[1]
    kp = dF.shape[0]
    w = h / 6.0
    h2 = 0.5 * h * h
    h3 = 0.25 * h * h * h
    A2 = np.empty((n, n))
    A3 = np.empty((n, n))
    A4 = np.empty((n, n))
    F2 = np.empty((n, n))
    F3 = np.empty((n, n))
    _mm(F, F, F2)                       # F A₁
    _mm(F, F2, F3)
    Phi1 = np.empty((n, n))
    G0 = np.empty((n, n))
    Gm = np.empty((n, n))
    Gsum = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            A2[i, j] = F[i, j] + 0.5 * h * F2[i, j]
    _mm(F, A2, A3)
    for i in range(n):
        for j in range(n):
            A3[i, j] = F[i, j] + 0.5 * h * A3[i, j]
    _mm(F, A3, A4)
    for i in range(n):
        for j in range(n):
            A4[i, j] = F[i, j] + h * A4[i, j]
            d = 1.0 if i == j else 0.0
            Phi1[i, j] = d + w * (F[i, j] + 2.0 * A2[i, j] + 2.0 * A3[i, j] + A4[i, j])
            G0[i, j] = w * (d + h * F[i, j] + h2 * F2[i, j] + h3 * F3[i, j])
            Gm[i, j] = w * (4.0 * d + 2.0 * h * F[i, j] + h2 * F2[i, j])
            Gsum[i, j] = G0[i, j] + Gm[i, j] + w * d
    # their derivatives, one parameter at a time
    dPhi1 = np.empty((kp, n, n))
    dG0 = np.empty((kp, n, n))
    dGm = np.empty((kp, n, n))
    tmp = np.empty((n, n))
    dA2 = np.empty((n, n))
    dA3 = np.empty((n, n))
    dF2 = np.empty((n, n))
    dF3 = np.empty((n, n))
    for p in range(kp):
        D = dF[p]
        _mm(D, F, dF2)                  # ∂(F A₁) = ∂(F²)
        _mm_add(F, D, dF2)
        for i in range(n):
            for j in range(n):
                dA2[i, j] = D[i, j] + 0.5 * h * dF2[i, j]
        _mm(D, A2, tmp)
        _mm_add(F, dA2, tmp)
        for i in range(n):
            for j in range(n):
                dA3[i, j] = D[i, j] + 0.5 * h * tmp[i, j]
        _mm(D, A3, tmp)
        _mm_add(F, dA3, tmp)
        _mm(D, F2, dF3)
        _mm_add(F, dF2, dF3)
        for i in range(n):
            for j in range(n):
                dA4 = D[i, j] + h * tmp[i, j]
                dPhi1[p, i, j] = w * (D[i, j] + 2.0 * dA2[i, j] + 2.0 * dA3[i, j] + dA4)
                dG0[p, i, j] = w * (h * D[i, j] + h2 * dF2[i, j] + h3 * dF3[i, j])
                dGm[p, i, j] = w * (2.0 * h * D[i, j] + h2 * dF2[i, j])
    # per step: input coefficients of the three stages and the constant term
    S0 = np.empty((n, q))
    Sm = np.empty((n, q))
    S1 = np.empty((n, q))
    _mm(G0, B, S0)
    _mm(Gm, B, Sm)
    se = np.zeros(n)
    for i in range(n):
        for a in range(q):
            S1[i, a] = w * B[i, a]
        for j in range(n):
            se[i] += Gsum[i, j] * e[j]
    dS0 = np.empty((kp, n, q))
    dSm = np.empty((kp, n, q))
    dS1 = np.empty((kp, n, q))
    dse = np.zeros((kp, n))
    for p in range(kp):
        _mm(dG0[p], B, dS0[p])
        _mm_add(G0, dB[p], dS0[p])
        _mm(dGm[p], B, dSm[p])
        _mm_add(Gm, dB[p], dSm[p])
        for i in range(n):
            for a in range(q):
                dS1[p, i, a] = w * dB[p, i, a]
            acc = 0.0
            for j in range(n):
                acc += (dG0[p, i, j] + dGm[p, i, j]) * e[j] + Gsum[i, j] * de[p, j]
            dse[p, i] = acc
    # compose the steps: step s reaches the interval's end through P = Φ₁^(substeps-1-s)
    C[:, :] = 0.0
    dC[:, :, :] = 0.0
    ce[:] = 0.0
    dce[:, :] = 0.0
    P = np.eye(n)
    dP = np.zeros((kp, n, n))
    Pnext = np.empty((n, n))
    dPnext = np.empty((kp, n, n))
    block = np.empty((n, q))
    for s in range(substeps - 1, -1, -1):
        _add_stage(P, dP, S0, dS0, 2 * s * q, C, dC, block)
        _add_stage(P, dP, Sm, dSm, (2 * s + 1) * q, C, dC, block)
        _add_stage(P, dP, S1, dS1, (2 * s + 2) * q, C, dC, block)
        for i in range(n):
            for j in range(n):
                ce[i] += P[i, j] * se[j]
                for p in range(kp):
                    dce[p, i] += dP[p, i, j] * se[j] + P[i, j] * dse[p, j]
        # P ← P Φ₁, dP ← dP Φ₁ + P dΦ₁
        for p in range(kp):
            _mm(dP[p], Phi1, dPnext[p])
            _mm_add(P, dPhi1[p], dPnext[p])
        _mm(P, Phi1, Pnext)
        P[:, :] = Pnext
        dP[:, :, :] = dPnext
    Phi[:, :] = P
    dPhi[:, :, :] = dP


@njit(cache=True, nogil=True, fastmath={'contract'})
def affine_scan(Phi, dPhi, W, ce, dce, x0, S0, H, d, dd, y, xs, Ss, yhat, dyhat, res, sq, gc,
                Mc):
    """
    States, sensitivities and outputs of x_{j+1} = Φ x_j + W_j; residuals and their sums.

    Φ (n, n) and its derivatives dPhi (kp, n, n) from :func:`interval_map`; W (T-1, kp+1, n)
    the input forcing of every interval, then its derivatives, without the constant terms
    ce (n,) and dce (kp, n): x_{j+1} = Φ x_j + W[j, 0] + ce.
    S0 (n, k): the first kp columns are the parameters, the rest (e.g. initial states) have no
    forcing. H (T or 1, m, n); output offset d (T, m) and its derivatives dd (T, m, kp), or
    arrays with 0 rows when there is none. y (T, m) measured outputs, or 0 rows for a plain
    simulation. Fills xs (T, n), Ss (T, n, k), yhat (T, m), dyhat (T, m, k) and, with y,
    res = y − ŷ (T, m), sq = Σ res² (m,), gc = Σ ∂ŷᵀ res (m, k), Mc = Σ ∂ŷᵀ ∂ŷ (m, k, k),
    per channel (so the caller can weight them by any R⁻¹). xs, Ss and dyhat with 0 rows: they
    are not stored (a fit that needs only ŷ, the residuals and their sums).

    One pass over the samples. States and sensitivities travel as one block Z = [x S]
    (n × (1+k), rows contiguous), so a step is, per pair of rows (i, r), one contiguous update
    Z⁺[i] += Φ[i, r] Z[r] + x_r G[i, r] with G[i, r, 1+p] = ∂Φ_p[i, r] (S⁺ = Φ S + ∂Φ x + ∂W)
    that the compiler vectorises; each sample's outputs v = H_j Z_j (ŷ and ∂ŷ) and, with y,
    the outer product of u = [res, ∂ŷ] (whose entries are sq, gc and Mc) are formed in the same
    pass.
    """
    T = W.shape[0] + 1
    n = x0.shape[0]
    k = S0.shape[1]
    K = k + 1
    kp = dPhi.shape[0]
    m = yhat.shape[1]
    const_H = H.shape[0] == 1
    has_d = d.shape[0] > 0
    fit = y.shape[0] > 0
    store = xs.shape[0] > 0             # xs, Ss, dyhat with 0 rows: only ŷ, res and the sums
    G = np.zeros((n, n, K))
    for p in range(kp):
        for i in range(n):
            for r in range(n):
                G[i, r, 1 + p] = dPhi[p, i, r]
    Z = np.empty((n, K))
    Zn = np.empty((n, K))
    for i in range(n):
        Z[i, 0] = x0[i]
        for c in range(k):
            Z[i, 1 + c] = S0[i, c]
    outer = np.zeros((m, K, K))
    v = np.empty(K)
    for j in range(T):
        # sample j: states, sensitivities, outputs, residuals and their products
        if store:
            for i in range(n):
                xs[j, i] = Z[i, 0]
                for c in range(k):
                    Ss[j, i, c] = Z[i, 1 + c]
        Hj = H[0] if const_H else H[j]
        for a in range(m):
            for c in range(K):
                v[c] = 0.0
            if has_d:
                v[0] = d[j, a]
                for c in range(kp):
                    v[1 + c] = dd[j, a, c]
            for i in range(n):
                hv = Hj[a, i]
                if hv != 0.0:               # H is sparse (a channel reads few states)
                    for c in range(K):
                        v[c] += hv * Z[i, c]
            yhat[j, a] = v[0]
            if store:
                for c in range(k):
                    dyhat[j, a, c] = v[1 + c]
            if fit:
                r_ = y[j, a] - v[0]
                res[j, a] = r_
                v[0] = r_
                for c in range(K):
                    vc = v[c]
                    for c2 in range(K):
                        outer[a, c, c2] += vc * v[c2]
        if j == T - 1:
            break
        # the step to sample j + 1
        for i in range(n):
            Zn[i, 0] = W[j, 0, i] + ce[i]
            for p in range(kp):
                Zn[i, 1 + p] = W[j, 1 + p, i] + dce[p, i]
            for c in range(1 + kp, K):
                Zn[i, c] = 0.0
        for r in range(n):
            xr = Z[r, 0]
            for i in range(n):
                a = Phi[i, r]
                for c in range(K):
                    Zn[i, c] += a * Z[r, c] + xr * G[i, r, c]
        Z, Zn = Zn, Z
    if fit:
        for a in range(m):
            sq[a] = outer[a, 0, 0]
            for c in range(k):
                gc[a, c] = outer[a, 0, 1 + c]
                for c2 in range(c, k):
                    Mc[a, c, c2] = outer[a, 1 + c, 1 + c2]
                    Mc[a, c2, c] = outer[a, 1 + c, 1 + c2]


@njit(cache=True, nogil=True)
def affine_run(F_probe, g_probe, dF_probe, dg_probe, shift, param_index, h, substeps, U, x0,
               S0, H, d, dd, y, xs, Ss, yhat, dyhat, res, sq, gc, Mc):
    """
    Simulate a time-invariant model from its values at unit inputs (one call).

    F_probe (q+1, n, n), g_probe (q+1, n): F and g at input 0 and at every unit input (so
    B = g(e_a) − g(0), e = g(0)); dF_probe (q+1, P, n, n), dg_probe (q+1, P, n) their
    parameter derivatives (0 parameters: no sensitivities), of which ``param_index`` are
    wanted. ``shift`` (P or 0,): parameter change from the probes' point along which F and g
    are affine (F + Σ shift·∂F, likewise g; 0 entries: the probes are at the point itself).
    U (T-1, L) the stage inputs of every interval; the rest, and the outputs xs … Mc that it
    fills, as :func:`affine_scan` (outputs passed in: boxing returned arrays costs more than
    this whole call's arithmetic).
    """
    q = g_probe.shape[0] - 1
    n = g_probe.shape[1]
    kp = param_index.shape[0]
    L = U.shape[1]
    T = U.shape[0] + 1
    F = F_probe[0].copy()
    g = g_probe.copy()
    for ip in range(shift.shape[0]):
        dp = shift[ip]
        if dp != 0.0:
            for i in range(n):
                for j in range(n):
                    F[i, j] += dp * dF_probe[0, ip, i, j]
                for a in range(q + 1):
                    g[a, i] += dp * dg_probe[a, ip, i]
    e = g[0].copy()
    B = np.empty((n, q))
    dF = np.empty((kp, n, n))
    dB = np.empty((kp, n, q))
    de = np.empty((kp, n))
    for i in range(n):
        for a in range(q):
            B[i, a] = g[1 + a, i] - e[i]
    for p in range(kp):
        ip = param_index[p]
        for i in range(n):
            de[p, i] = dg_probe[0, ip, i]
            for a in range(q):
                dB[p, i, a] = dg_probe[1 + a, ip, i] - dg_probe[0, ip, i]
            for j in range(n):
                dF[p, i, j] = dF_probe[0, ip, i, j]
    Phi = np.empty((n, n))
    dPhi = np.empty((kp, n, n))
    C = np.empty((n, L))
    dC = np.empty((kp, n, L))
    ce = np.empty(n)
    dce = np.empty((kp, n))
    interval_map(F, B, e, dF, dB, de, h, substeps, Phi, dPhi, C, dC, ce, dce)
    # the input forcing of every interval, C U_j and dC U_j, as one matrix product (BLAS)
    Ccat = np.empty((L, (kp + 1) * n))
    for col in range(L):
        for i in range(n):
            Ccat[col, i] = C[i, col]
            for p in range(kp):
                Ccat[col, (1 + p) * n + i] = dC[p, i, col]
    W = np.dot(U, Ccat).reshape((T - 1, kp + 1, n))
    affine_scan(Phi, dPhi, W, ce, dce, x0, S0, H, d, dd, y, xs, Ss, yhat, dyhat, res, sq, gc,
                Mc)


def affine_run_example(samples=2):
    """Return arguments of the types simulate passes to affine_run (0 samples: no data)."""
    n, q, P, k, m, T = 2, 1, 1, 2, 1, 2
    L = 3 * q
    return (np.zeros((q + 1, n, n)), np.zeros((q + 1, n)), np.zeros((q + 1, P, n, n)),
            np.zeros((q + 1, P, n)), np.zeros(P), np.zeros(1, dtype=np.int64), 0.1, 1,
            np.zeros((T - 1, L)), np.zeros(n), np.zeros((n, k)), np.ones((1, m, n)),
            np.zeros((0, m)), np.zeros((0, m, P)), np.zeros((samples, m)), np.empty((T, n)),
            np.empty((T, n, k)), np.empty((T, m)), np.empty((T, m, k)),
            np.empty((samples, m)), np.empty(m), np.empty((m, k)), np.empty((m, k, k)))


def warm_up_affine():
    """Compile (or load from the cache) the time-invariant kernel for the types simulate uses."""
    for samples in (2, 0):
        affine_run(*affine_run_example(samples))


# -- the Gauss-Newton iteration of output error on one prepared record -----------------------

@njit(cache=True, nogil=True)
def _fit_point(theta, p_base, param_index, p_ref, x0_base, free_states, shift, x0):
    """Parameter shift p(θ) − p_ref and initial state x0(θ) of one run."""
    kp = param_index.shape[0]
    for i in range(shift.shape[0]):
        shift[i] = p_base[i] - p_ref[i]
    for c in range(kp):
        shift[param_index[c]] = theta[c] - p_ref[param_index[c]]
    for i in range(x0.shape[0]):
        x0[i] = x0_base[i]
    for c in range(free_states.shape[0]):
        x0[free_states[c]] = theta[kp + c]


@njit(cache=True, nogil=True)
def _fit_cost(sq, var, theta, prior_info, prior_mean):
    """½ Σ_c sq_c / var_c + ½ Σ prior_info (θ − prior_mean)² (output_error's cost_of)."""
    data = 0.0
    for c in range(sq.shape[0]):
        data += sq[c] * (1.0 / var[c])
    prior = 0.0
    for i in range(theta.shape[0]):
        prior += prior_info[i] * (theta[i] - prior_mean[i]) ** 2
    return 0.5 * data + 0.5 * prior


@njit(cache=True, nogil=True)
def _inverse_diagonal(M, out):
    """
    Set out = diag(M⁻¹) by Cholesky where M is safely well conditioned; else return False.

    Safely: every diagonal entry within 1e4 of the largest, and every Cholesky pivot of the
    diagonally scaled M at least 1e-4 (each parameter keeps 1e-4 of its information after the
    ones before it). Then M's condition number stays many decades below pinv's 1e-15 cutoff
    and M⁻¹ is pinv(M) to rounding, at a fraction of an SVD's cost; otherwise the caller
    takes pinv, as the Python iteration does.
    """
    k = M.shape[0]
    dmax = 0.0
    for j in range(k):
        dmax = max(dmax, M[j, j])
    L = np.zeros((k, k))
    for j in range(k):
        if not M[j, j] >= 1e-4 * dmax or not dmax > 0.0:
            return False
        acc = M[j, j]
        for r in range(j):
            acc -= L[j, r] * L[j, r]
        if not acc >= 1e-4 * M[j, j]:
            return False
        ljj = np.sqrt(acc)
        L[j, j] = ljj
        for i in range(j + 1, k):
            acc = M[i, j]
            for r in range(j):
                acc -= L[i, r] * L[j, r]
            L[i, j] = acc / ljj
    # diag(M⁻¹)_a = ‖L⁻¹ e_a‖²: the columns of the triangular inverse
    Linv = np.zeros((k, k))
    for c in range(k):
        Linv[c, c] = 1.0 / L[c, c]
        for i in range(c + 1, k):
            acc = 0.0
            for r in range(c, i):
                acc -= L[i, r] * Linv[r, c]
            Linv[i, c] = acc / L[i, i]
    for a in range(k):
        acc = 0.0
        for i in range(a, k):
            acc += Linv[i, a] * Linv[i, a]
        out[a] = acc
    return True


@njit(cache=True, nogil=True)
def _information(Mc, var, prior_info, out):
    """Set out = M = Σ_c Mc[c]/var_c + diag(prior_info) (output_error._weighted_sums + prior)."""
    k = out.shape[0]
    for a in range(k):
        for b in range(k):
            acc = 0.0
            for c in range(var.shape[0]):
                acc += (1.0 / var[c]) * Mc[c, a, b]
            out[a, b] = acc
        out[a, a] += prior_info[a]


@njit(cache=True, nogil=True)
def gn_iteration(F_probe, g_probe, dF_probe, dg_probe, p_ref, p_base, param_index, h, substeps,
                 U, x0_base, free_states, S0, H, y, theta, cost, lm, var, estimate_noise,
                 floor, prior_info, prior_mean, lo, hi, step_tol, cur_sq, cur_gc, cur_Mc,
                 xs, Ss, yhat, dyhat, res, sq, gc, Mc, out_theta, out_var, out_M, out_grad,
                 out_sigma, out_scalars):
    """
    One iteration of output_error.fit_output_error for a single run with a prepared plan.

    The same steps as the Python loop: M and the gradient from the current per-channel sums
    (cur_sq, cur_gc, cur_Mc) weighted by 1/var plus the prior; the damped, scaled Gauss-Newton
    step of output_error.damped_gauss_newton_step (λ, 12 dampings × 6 halvings, bounds), each
    trial simulated by :func:`affine_run` into the trial buffers (xs … Mc); on acceptance the
    noise variance re-estimated (``estimate_noise``), the cost at the new point, σ from
    pinv(M) (by Cholesky where that is the same to rounding, :func:`_inverse_diagonal`) and
    the step-size convergence test. Writes out_theta, out_var, out_M, out_grad, out_sigma and
    out_scalars = [cost, λ, all steps small (1/0), Σ res², the accepted point on a bound
    (1/0)]. Returns 1 when a step
    was accepted, 0 when none lowers the cost, −1 when the step equations could not be solved
    (the caller then takes this iteration in Python).
    """
    k = theta.shape[0]
    m = var.shape[0]
    T = y.shape[0]
    # M = Σ_c Mc/var_c + diag(prior), gradient = −Σ_c gc/var_c + prior (θ − mean)
    _information(cur_Mc, var, prior_info, out_M)
    for a in range(k):
        acc = 0.0
        for c in range(m):
            acc += (1.0 / var[c]) * cur_gc[c, a]
        out_grad[a] = -acc + prior_info[a] * (theta[a] - prior_mean[a])
    scale = np.empty(k)
    for a in range(k):
        scale[a] = np.sqrt(max(out_M[a, a], 1e-300))
    Ms = np.empty((k, k))
    for a in range(k):
        for b in range(k):
            Ms[a, b] = out_M[a, b] / (scale[a] * scale[b])
    rhs = out_grad / scale
    shift = np.empty(p_base.shape[0])
    x0 = np.empty(x0_base.shape[0])
    trial = np.empty(k)
    d = np.zeros((0, yhat.shape[1]))
    dd = np.zeros((0, yhat.shape[1], param_index.shape[0]))
    accepted = False
    new_cost = cost
    for _attempt in range(12):
        A = Ms + lm * np.eye(k)
        solved = True
        step = np.empty(k)
        try:
            step[:] = -np.linalg.solve(A, rhs) / scale
        except Exception:  # noqa: B902 - singular: the caller's Python path takes over
            solved = False
        if not solved:
            return -1
        for _halving in range(6):
            for a in range(k):
                trial[a] = min(max(theta[a] + step[a], lo[a]), hi[a])
            _fit_point(trial, p_base, param_index, p_ref, x0_base, free_states, shift, x0)
            affine_run(F_probe, g_probe, dF_probe, dg_probe, shift, param_index, h, substeps,
                       U, x0, S0, H, d, dd, y, xs, Ss, yhat, dyhat, res, sq, gc, Mc)
            new_cost = _fit_cost(sq, var, trial, prior_info, prior_mean)
            if np.isfinite(new_cost) and new_cost <= cost + 1e-12 * abs(cost):
                accepted = True
                break
            step *= 0.5
        if accepted:
            lm = lm / 10.0 if lm > 1e-6 else 0.0
            break
        lm = max(1e-3, 10.0 * lm)
    out_scalars[1] = lm
    if not accepted:
        out_scalars[0] = cost
        return 0
    for c in range(m):
        out_var[c] = max(sq[c] / T, floor) if estimate_noise else var[c]
    out_scalars[0] = _fit_cost(sq, out_var, trial, prior_info, prior_mean)
    if not _inverse_diagonal(out_M, out_sigma):
        P = np.linalg.pinv(out_M)
        for a in range(k):
            out_sigma[a] = P[a, a]
    small = 1.0
    total = 0.0
    for a in range(k):
        out_sigma[a] = np.sqrt(max(out_sigma[a], 0.0))
        applied = trial[a] - theta[a]
        if abs(applied) > max(step_tol * out_sigma[a], 1e-12 * abs(trial[a])):
            small = 0.0
        out_theta[a] = trial[a]
    for c in range(m):
        total += sq[c]
    bound = 0.0
    for a in range(k):
        if trial[a] <= lo[a] or trial[a] >= hi[a]:
            bound = 1.0
    out_scalars[2] = small
    out_scalars[3] = total
    out_scalars[4] = bound
    return 1


@intrinsic
def _clock_ns(typingctx, clock_id):
    """Read libc's clock_gettime(clock_id) in nanoseconds (by symbol name: the cache keeps it)."""
    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        timespec = ir.LiteralStructType([i64, i64])
        function = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.IntType(32), [ir.IntType(32),
                                                             timespec.as_pointer()]),
            'clock_gettime')
        ts = cgutils.alloca_once(builder, timespec)
        builder.call(function, [builder.trunc(args[0], ir.IntType(32)), ts])
        seconds = builder.load(cgutils.gep_inbounds(builder, ts, 0, 0))
        nanoseconds = builder.load(cgutils.gep_inbounds(builder, ts, 0, 1))
        return builder.add(builder.mul(seconds, ir.Constant(i64, 1_000_000_000)), nanoseconds)
    return types.int64(types.int64), codegen


@njit(cache=True, nogil=True)
def clock_ns(clock_id):
    """Return clock_gettime(clock_id) in ns, as gn_fit reads it (compared with time's clocks)."""
    return _clock_ns(clock_id)


#: gn_fit's stop reasons (out_scalars[3]): the iteration limit, no step lowers the cost, every
#: step small (converged), singular step equations (the caller fits again in Python), a
#: response at the start that is not finite.
FIT_MAX_ITER, FIT_NO_STEP, FIT_CONVERGED, FIT_SINGULAR, FIT_NOT_FINITE = 0, 1, 2, -1, -2


@njit(cache=True, nogil=True)
def gn_fit(F_probe, g_probe, dF_probe, dg_probe, p_ref, p_base, param_index, h, substeps, U,
           x0_base, free_states, S0, H, y, theta0, var0, estimate_noise, floor, prior_info,
           prior_mean, lo, hi, step_tol, max_iter, dependence_threshold, clock_id, res, yhat, sq,
           gc, Mc, hist_theta, hist_var, hist_scalars, out_theta, out_var, out_M, out_grad,
           out_cov, out_scalars):
    """
    Run a whole output-error fit of a single prepared run in one call (no progress callback).

    The steps of output_error.fit_output_error's loop with :func:`gn_iteration`: the start
    simulated (noise estimated from it when ``estimate_noise``, else var0), then up to
    ``max_iter`` iterations of :func:`gn_iteration`; afterwards M = Σ_c Mc/var_c + diag(prior)
    at the final point, the Cholesky pre-test of output_error.dependence_warnings
    (``dependence_threshold``) and M⁻¹. Fills the final point's res, yhat, sq, gc, Mc (T, m),
    (T, m), (m,), (m, k), (m, k, k); per accepted iteration i hist_theta[i] (k,),
    hist_var[i] (m,) and hist_scalars[i] = [cost, rms, at a bound (1/0), clock_gettime(clock_id)
    in ns when the iteration ended (NaN for clock_id < 0)]; out_theta, out_var,
    out_M, out_grad (the gradient of the last iteration's step), out_cov = M⁻¹, and
    out_scalars = [cost, data cost ½Σ sq/var, accepted iterations, stop reason (FIT_*),
    iteration count as fit_output_error reports it, pre-test passed (1/0),
    M⁻¹ valid (1/0)]. Returns the stop reason.
    """
    k = theta0.shape[0]
    m = y.shape[1]
    T = y.shape[0]
    n = x0_base.shape[0]
    kp = param_index.shape[0]
    no_x = np.empty((0, n))
    no_S = np.empty((0, n, k))
    no_dy = np.empty((0, m, k))
    d = np.zeros((0, m))
    dd = np.zeros((0, m, kp))
    shift = np.empty(p_base.shape[0])
    x0 = np.empty(n)
    theta = theta0.copy()
    var = var0.copy()
    # the start, into the current buffers (res, yhat, sq, gc, Mc); trials into the spare ones
    _fit_point(theta, p_base, param_index, p_ref, x0_base, free_states, shift, x0)
    affine_run(F_probe, g_probe, dF_probe, dg_probe, shift, param_index, h, substeps, U, x0,
               S0, H, d, dd, y, no_x, no_S, yhat, no_dy, res, sq, gc, Mc)
    if estimate_noise:
        for c in range(m):
            var[c] = max(sq[c] / T, floor)
    cost = _fit_cost(sq, var, theta, prior_info, prior_mean)
    for i in range(out_scalars.shape[0]):
        out_scalars[i] = 0.0
    if not np.isfinite(cost):
        out_scalars[3] = FIT_NOT_FINITE
        return FIT_NOT_FINITE
    cur = (res, yhat, sq, gc, Mc)
    spare = (np.empty_like(res), np.empty_like(yhat), np.empty_like(sq), np.empty_like(gc),
             np.empty_like(Mc))
    new_theta = np.empty(k)
    new_var = np.empty(m)
    sigma = np.empty(k)
    scalars = np.empty(5)
    lm = 0.0
    reason = FIT_MAX_ITER
    accepted = 0
    in_spare = False                    # the current point is in the second set of buffers
    iteration = 0
    for it in range(1, max_iter + 1):
        iteration = it
        status = gn_iteration(
            F_probe, g_probe, dF_probe, dg_probe, p_ref, p_base, param_index, h, substeps, U,
            x0_base, free_states, S0, H, y, theta, cost, lm, var, estimate_noise, floor,
            prior_info, prior_mean, lo, hi, step_tol, cur[2], cur[3], cur[4], no_x, no_S,
            spare[1], no_dy, spare[0], spare[2], spare[3], spare[4], new_theta, new_var, out_M,
            out_grad, sigma, scalars)
        lm = scalars[1]
        if status < 0:
            out_scalars[3] = FIT_SINGULAR
            return FIT_SINGULAR
        if status == 0:
            reason = FIT_NO_STEP
            break
        cur, spare = spare, cur
        in_spare = not in_spare
        for a in range(k):
            theta[a] = new_theta[a]
            hist_theta[accepted, a] = new_theta[a]
        for c in range(m):
            var[c] = new_var[c]
            hist_var[accepted, c] = new_var[c]
        cost = scalars[0]
        hist_scalars[accepted, 0] = cost
        hist_scalars[accepted, 1] = np.sqrt(scalars[3] / (T * m))
        hist_scalars[accepted, 2] = scalars[4]
        hist_scalars[accepted, 3] = float(_clock_ns(clock_id)) if clock_id >= 0 else np.nan
        accepted += 1
        if scalars[2] != 0.0:
            reason = FIT_CONVERGED
            break
    # the final point's sums into the caller's buffers (the last accepted trial's may be spare)
    if in_spare:
        res[:, :] = cur[0]
        yhat[:, :] = cur[1]
        sq[:] = cur[2]
        gc[:, :] = cur[3]
        Mc[:, :, :] = cur[4]
    for a in range(k):
        out_theta[a] = theta[a]
    for c in range(m):
        out_var[c] = var[c]
    data = 0.0
    for c in range(m):
        data += sq[c] * (1.0 / var[c])
    # M at the final point (output_error._weighted_sums + prior; after "no step" the step's M)
    M = out_M
    _information(Mc, var, prior_info, M)
    # dependence_warnings' pre-test: Cholesky of the scaled M − threshold·k·I
    passed = True
    for a in range(k):
        if not M[a, a] > 0.0:
            passed = False
    if passed:
        shifted = np.empty((k, k))
        for a in range(k):
            da = np.sqrt(M[a, a])
            for b in range(k):
                shifted[a, b] = M[a, b] / (da * np.sqrt(M[b, b]))
            shifted[a, a] -= dependence_threshold * k
        try:
            np.linalg.cholesky(shifted)
        except Exception:  # noqa: B902 - not positive definite: the caller's eigen-analysis
            passed = False
    valid = True
    try:
        inverse = np.linalg.inv(M)
        for a in range(k):
            if inverse[a, a] < 0.0:
                valid = False
            for b in range(k):
                if not np.isfinite(inverse[a, b]):
                    valid = False
                out_cov[a, b] = inverse[a, b]
    except Exception:  # noqa: B902 - singular: the caller takes pinv
        valid = False
    out_scalars[0] = cost
    out_scalars[1] = 0.5 * data
    out_scalars[2] = accepted
    out_scalars[3] = reason
    out_scalars[4] = iteration
    out_scalars[5] = 1.0 if passed else 0.0
    out_scalars[6] = 1.0 if valid else 0.0
    return reason


def clock_ns_example():
    """Return arguments of clock_ns's one signature."""
    return (1,)


#: sizes of the Gauss-Newton kernels' example arguments: states, intervals, parameters,
#: unknowns, channels, samples
_GN_SIZES = (2, 1, 1, 2, 1, 3)


def _gn_prepared_record():
    """Return the leading arguments gn_iteration and gn_fit share: one prepared record."""
    n, q, P, k, m, T = _GN_SIZES
    i64 = np.zeros(1, dtype=np.int64)
    return (np.zeros((q + 1, n, n)), np.zeros((q + 1, n)), np.zeros((q + 1, P, n, n)),
            np.zeros((q + 1, P, n)), np.zeros(P), np.zeros(P), i64, 0.1, 1,
            np.zeros((T - 1, 3 * q)), np.zeros(n), i64, np.eye(n, k), np.ones((1, m, n)),
            np.zeros((T, m)), np.zeros(k))


def gn_iteration_example():
    """Return arguments of the types output error passes to gn_iteration."""
    n, _, _, k, m, T = _GN_SIZES
    return _gn_prepared_record() + (
        1.0, 0.0, np.ones(m), True, 1e-24, np.zeros(k), np.zeros(k), -np.ones(k), np.ones(k),
        1e-6, np.zeros(m), np.zeros((m, k)), np.eye(k)[None], np.empty((T, n)),
        np.empty((T, n, k)), np.empty((T, m)), np.empty((T, m, k)), np.empty((T, m)),
        np.empty(m), np.empty((m, k)), np.empty((m, k, k)), np.empty(k), np.empty(m),
        np.empty((k, k)), np.empty(k), np.empty(k), np.empty(5))


def gn_fit_example():
    """Return arguments of the types output error passes to gn_fit."""
    _, _, _, k, m, T = _GN_SIZES
    return _gn_prepared_record() + (
        np.ones(m), True, 1e-24, np.zeros(k), np.zeros(k), -np.ones(k), np.ones(k), 1e-6, 1,
        1e-7, -1, np.empty((T, m)), np.empty((T, m)), np.empty(m), np.empty((m, k)),
        np.empty((m, k, k)), np.empty((1, k)), np.empty((1, m)), np.empty((1, 4)),
        np.empty(k), np.empty(m), np.empty((k, k)), np.empty(k), np.empty((k, k)),
        np.empty(7))


def warm_up_gn():
    """Compile (or load from the cache) gn_iteration and gn_fit for output error's types."""
    clock_ns(*clock_ns_example())
    gn_iteration(*gn_iteration_example())
    gn_fit(*gn_fit_example())
