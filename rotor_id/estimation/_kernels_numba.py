"""
The numba kernel behind :mod:`rotor_id.estimation.kernels` (imported only from there).

One RK4 step of x′ = F x + g and of its sensitivities, step after step. The sensitivities take
the step map S⁺ = Φ S + (∂Φ/∂p) x + ∂c/∂p of :mod:`rotor_id.estimation.simulate`: Φ comes in
precomputed (once for a time-invariant system, per step otherwise), and the forcing
(∂Φ/∂p) x + ∂c/∂p is carried through the RK4 stages as vectors, one per parameter, at the
state's stages (no ∂Φ/∂p matrices). F and ∂F/∂p enter as their non-zero entries.
"""

from numba import njit
import numpy as np


@njit(cache=True, nogil=True)
def _derivative_stage(F_val, F_i, F_j, dF_val, dF_p, dF_i, dF_j, dg, x, prev, scale, out):
    """Set out = (∂F/∂p) x + ∂g/∂p + scale · F prev, a row per parameter (prev unused at 0)."""
    kp = dg.shape[0]
    n = x.shape[0]
    for q in range(kp):
        for i in range(n):
            out[q, i] = dg[q, i]
    for e in range(dF_p.shape[0]):
        out[dF_p[e], dF_i[e]] += dF_val[e] * x[dF_j[e]]
    if scale != 0.0:
        for e in range(F_i.shape[0]):
            f = scale * F_val[e]
            i = F_i[e]
            j = F_j[e]
            for q in range(kp):
                out[q, i] += f * prev[q, j]


@njit(cache=True, nogil=True)
def _state_stage(F_val, F_i, F_j, g, x, out):
    """Set out = F x + g (F sparse)."""
    for i in range(x.shape[0]):
        out[i] = g[i]
    for e in range(F_i.shape[0]):
        out[F_i[e]] += F_val[e] * x[F_j[e]]


@njit(cache=True, nogil=True)
def rk4_scan(Phi, F_val, F_i, F_j, g, dF_val, dF_p, dF_i, dF_j, dg, h, substeps, x0, S0,
             xs, Ss):
    """
    Run M = len(h) RK4 steps from (x0, S0); store every ``substeps``-th in xs[1:], Ss[1:].

    Phi (1 or M, n, n): the steps' transition matrices. F and g (2M+1, n) at the start, middle
    and end of every step (shared with the next step), as
    :func:`rotor_id.estimation.simulate._fine_grid` lays them out; F as its non-zero entries
    F_val (1 or 2M+1, nnz) at (F_i, F_j), ∂F/∂p as its non-zero entries dF_val
    (1 or 2M+1, nnz) at (dF_p, dF_i, dF_j); ∂g/∂p as dg (2M+1, kp, n) for the first kp of the
    k sensitivity columns (the others, e.g. initial states, have no forcing). xs (M/substeps
    + 1, n) and Ss (…, n, k) receive the samples.
    """
    n = x0.shape[0]
    k = S0.shape[1]
    kp = dg.shape[1]
    x = x0.copy()
    S = S0.copy()
    S_next = np.empty((n, k))
    xs[0] = x
    Ss[0] = S
    xt = np.empty(n)
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    d1 = np.empty((kp, n))
    d2 = np.empty((kp, n))
    d3 = np.empty((kp, n))
    d4 = np.empty((kp, n))
    const_Phi = Phi.shape[0] == 1
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
        # the state's stages, and the parameter derivatives of the stages at fixed x
        _state_stage(F_val[fa], F_i, F_j, g[a], x, k1)
        _derivative_stage(F_val[fa], F_i, F_j, dF_val[da], dF_p, dF_i, dF_j, dg[a], x, d1,
                          0.0, d1)
        for i in range(n):
            xt[i] = x[i] + 0.5 * hs * k1[i]
        _state_stage(F_val[fb], F_i, F_j, g[b], xt, k2)
        _derivative_stage(F_val[fb], F_i, F_j, dF_val[db], dF_p, dF_i, dF_j, dg[b], xt, d1,
                          0.5 * hs, d2)
        for i in range(n):
            xt[i] = x[i] + 0.5 * hs * k2[i]
        _state_stage(F_val[fb], F_i, F_j, g[b], xt, k3)
        _derivative_stage(F_val[fb], F_i, F_j, dF_val[db], dF_p, dF_i, dF_j, dg[b], xt, d2,
                          0.5 * hs, d3)
        for i in range(n):
            xt[i] = x[i] + hs * k3[i]
        _state_stage(F_val[fc], F_i, F_j, g[c], xt, k4)
        _derivative_stage(F_val[fc], F_i, F_j, dF_val[dc], dF_p, dF_i, dF_j, dg[c], xt, d3,
                          hs, d4)
        w = hs / 6.0
        P = Phi[0] if const_Phi else Phi[s]
        for i in range(n):
            x[i] += w * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
            for q in range(k):
                acc = 0.0
                for j in range(n):
                    acc += P[i, j] * S[j, q]
                if q < kp:
                    acc += w * (d1[q, i] + 2.0 * d2[q, i] + 2.0 * d3[q, i] + d4[q, i])
                S_next[i, q] = acc
        S[:, :] = S_next
        if (s + 1) % substeps == 0:
            j = (s + 1) // substeps
            xs[j] = x
            Ss[j] = S


def warm_up():
    """Compile (or load from the cache) for the argument types simulate passes."""
    n, k, kp = 2, 2, 1
    Phi = np.eye(n)[None]
    F_val = np.zeros((1, 1))
    g = np.zeros((3, n))
    dF_val = np.zeros((1, 1))
    idx = np.zeros(1, dtype=np.int64)
    dg = np.zeros((3, kp, n))
    h = np.ones(1)
    xs = np.empty((2, n))
    Ss = np.empty((2, n, k))
    rk4_scan(Phi, F_val, idx, idx, g, dF_val, idx, idx, idx, dg, h, 1, np.zeros(n),
             np.zeros((n, k)), xs, Ss)


@njit(cache=True, nogil=True)
def _invert(A, inverse):
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
def filter_scan(Phi, c, Q, H, d, y, x0, R, P_steady, steady, nu, B, gains, cost):
    """
    Kalman filters of K stacked discrete models, the equations of filter_error.filter_batch.

    Phi (T-1, K, n, n), c (T-1, K, n), Q (T-1, K, n, n), H (T, K, m, n), d (T, K, m), y (T, m),
    x0 (K, n), R (K, m, m), P_steady (K, n, n) used when ``steady``. Fills nu (K, T, m),
    B (K, T, m, m), gains (K, T, n, m) and cost (K,) (Σ νᵀB⁻¹ν + log|B|).
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
    for kk in range(K_):
        for i in range(n):
            x[i] = x0[kk, i]
            for j in range(n):
                P[i, j] = P_steady[kk, i, j] if steady else 0.0
        total = 0.0
        for t in range(T):
            Ht = H[t, kk]
            for a in range(m):
                acc = y[t, a] - d[t, kk, a]
                for i in range(n):
                    acc -= Ht[a, i] * x[i]
                v[a] = acc
                nu[kk, t, a] = acc
            for i in range(n):
                for a in range(m):
                    acc = 0.0
                    for j in range(n):
                        acc += P[i, j] * Ht[a, j]
                    PHT[i, a] = acc
            for a in range(m):
                for b in range(m):
                    acc = R[kk, a, b]
                    for i in range(n):
                        acc += Ht[a, i] * PHT[i, b]
                    Bj[a, b] = acc
            for a in range(m):
                for b in range(a + 1, m):
                    s = 0.5 * (Bj[a, b] + Bj[b, a])
                    Bj[a, b] = s
                    Bj[b, a] = s
            logdet = _invert(Bj, Binv)
            for i in range(n):
                for b in range(m):
                    acc = 0.0
                    for a in range(m):
                        acc += PHT[i, a] * Binv[a, b]
                    Kj[i, b] = acc
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


def warm_up_filter():
    """Compile (or load from the cache) the filter for the argument types filter_batch passes."""
    K_, T, n, m = 1, 2, 2, 1
    Phi = np.zeros((T - 1, K_, n, n))
    c = np.zeros((T - 1, K_, n))
    H = np.ones((T, K_, m, n))
    d = np.zeros((T, K_, m))
    R = np.ones((K_, m, m))
    filter_scan(Phi, c, Phi.copy(), H, d, np.zeros((T, m)), np.zeros((K_, n)), R,
                np.zeros((K_, n, n)), False, np.empty((K_, T, m)), np.empty((K_, T, m, m)),
                np.empty((K_, T, n, m)), np.empty(K_))
    initial_state_innovations(Phi[:, 0], np.zeros((T, n, m)), H[:, 0], np.eye(n),
                              np.empty((T, m, n)))


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
