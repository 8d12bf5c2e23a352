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
