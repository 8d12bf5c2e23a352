"""
Compiled (numba) Kalman filter with the analytic sensitivities of filter error's likelihood.

Loaded through :func:`rotor_id.estimation.kernels.filter_sensitivity_kernel` only; the numpy
twin is :func:`rotor_id.estimation.filter_error.sensitivity_scan_numpy`, with the same
equations in the same order (test/estimation/test_filter_error_gradient.py checks agreement).

The m×m inverse and the innovation covariance and gain are ``_kernels_numba.invert_in_place`` and
``_kernels_numba.innovation_gain``, compiled into this module's cache: numba does not track
that dependency, so a change to either needs this cache cleared too (``make build`` after
``make clean``, or touch this file).
"""

from numba import njit
import numpy as np
from rotor_id.estimation._kernels_numba import innovation_gain, invert_in_place


@njit(cache=True, nogil=True)
def _stage(F, g_row, x, prev, scale, xs, out):
    """Set the RK4 stage xs = x + scale·prev and out = F xs + g_row."""
    n = x.shape[0]
    for i in range(n):
        xs[i] = x[i] + scale * prev[i]
    for i in range(n):
        acc = g_row[i]
        for j in range(n):
            acc += F[i, j] * xs[j]
        out[i] = acc


@njit(cache=True, nogil=True)
def _sensitivity_stage(F, S, prev, scale, dF, dg_row, xs, out):
    """
    Set out = F (S + scale·prev) + [∂F xs + ∂g] (bracket on the first kp columns only).

    The derivative of the RK4 stage :func:`_stage` along each column of S (n, k); dF (kp, n, n),
    dg_row (kp, n).
    """
    n, k = S.shape
    kp = dF.shape[0]
    for i in range(n):
        # row i of F (S + scale·prev) for every column at once, each summed over j in order
        # (independent sums, which the compiler can vectorise; the same sums as one at a time)
        for c in range(k):
            out[i, c] = 0.0
        for j in range(n):
            f = F[i, j]
            for c in range(k):
                out[i, c] += f * (S[j, c] + scale * prev[j, c])
        for c in range(kp):
            acc = out[i, c] + dg_row[c, i]
            for j in range(n):
                acc += dF[c, i, j] * xs[j]
            out[i, c] = acc


@njit(cache=True, nogil=True)
def sensitivity_scan(Fs, g, dFs, dg, h, substeps, Phis, dPhis, Qs, dQs, R, dR, covariant, H, d,
                     dd, y, x0, dx0, steady, B_ss, K_ss, dB_ss, dK_ss, nu, dnu, B, dB):
    """
    Innovations ν_j, B_j and their derivatives ∂ν_j, ∂B_j along k directions of θ.

    Fs (2M+1, n, n) the system matrix at the RK4 stage times (M = (T-1)·substeps steps of
    length h), or (1, n, n) when it is constant; g (2M+1, n) the forcing there; dFs (2M+1 or 1,
    kp, n, n), dg (2M+1, kp, n) their derivatives along the first kp directions; Phis, Qs
    (T-1 or 1, n, n) of each sample interval and dPhis (T-1 or 1, kp, n, n) along the first
    kp directions (zero beyond); R (m, m), dR (k, m, m); ``covariant`` (int64) the directions
    along which ∂Φ, ∂Q or ∂R may be non-zero, and dQs (T-1 or 1, len(covariant), n, n) along
    them: along every other (an initial state, a forcing parameter) ∂P, ∂B and ∂K stay zero
    from P(t0) = 0 and are not propagated; H (T, m, n); d (T, m), dd (T, m, k); y (T, m);
    x0 (n,), dx0 (n, k). With ``steady`` the gain is B_ss (m, m), K_ss (n, m) with
    derivatives dB_ss (k, m, m), dK_ss (k, n, m) throughout; else P(t0) = 0 and the
    covariance and its derivative are propagated. Fills nu (T, m), dnu (T, m, k),
    B (T, m, m), dB (T, m, m, k); returns Σ_j νᵀB⁻¹ν + log|B_j|.

        ν = y − H x − d                       ∂ν = −H ∂x − ∂d
        B = H P Hᵀ + R                         ∂B = H ∂P Hᵀ + ∂R
        K = P Hᵀ B⁻¹                           ∂K = (∂P Hᵀ − K ∂B) B⁻¹
        x⁺ = x + K ν                           ∂x⁺ = ∂x + ∂K ν + K ∂ν
        P⁺ = P − K B Kᵀ                        ∂P⁺ = ∂P − ∂K B Kᵀ − K ∂B Kᵀ − K B ∂Kᵀ
        x' = RK4 steps from x⁺                 ∂x' = the RK4 variational steps from ∂x⁺
        P' = Φ P⁺ Φᵀ + Q                       ∂P' = ∂Φ P⁺ Φᵀ + Φ ∂P⁺ Φᵀ + Φ P⁺ ∂Φᵀ + ∂Q
    """
    T = y.shape[0]
    m = y.shape[1]
    k = dx0.shape[1]
    kp = dFs.shape[1]
    n = Fs.shape[1]
    varying = Fs.shape[0] > 1
    per_interval = Phis.shape[0] > 1
    x = x0.copy()
    S = dx0.copy()
    P = np.zeros((n, n))
    dP = np.zeros((k, n, n))
    Pn = np.empty((n, n))
    KdB = np.empty((n, m))
    Kj = np.empty((n, m))
    dKj = np.zeros((k, n, m))
    Bj = np.empty((m, m))
    dBj = np.zeros((k, m, m))
    Binv = np.empty((m, m))
    PHT = np.empty((n, m))
    dPHT = np.empty((n, m))
    KB = np.empty((n, m))
    W = np.empty((n, n))
    W2 = np.empty((n, n))
    PhiT = np.empty((n, n))
    row = np.empty(n)
    v = np.empty(m)
    dv = np.empty((m, k))
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    x1 = np.empty(n)
    x2 = np.empty(n)
    x3 = np.empty(n)
    x4 = np.empty(n)
    s1 = np.empty((n, k))
    s2 = np.empty((n, k))
    s3 = np.empty((n, k))
    s4 = np.empty((n, k))
    half = 0.5 * h
    total = 0.0
    for t in range(T):
        Ht = H[t]
        # innovation covariance, gain and their derivatives
        if steady:
            for a in range(m):
                for b in range(m):
                    Bj[a, b] = B_ss[a, b]
                    for c in range(k):
                        dBj[c, a, b] = dB_ss[c, a, b]
                for i in range(n):
                    Kj[i, a] = K_ss[i, a]
                    for c in range(k):
                        dKj[c, i, a] = dK_ss[c, i, a]
            logdet = invert_in_place(Bj, Binv)
        else:
            logdet = innovation_gain(P, Ht, R, PHT, Bj, Binv, Kj)
            for c in covariant:
                for i in range(n):
                    for a in range(m):
                        acc = 0.0
                        for j in range(n):
                            acc += dP[c, i, j] * Ht[a, j]
                        dPHT[i, a] = acc
                for a in range(m):
                    for b in range(m):
                        acc = dR[c, a, b]
                        for i in range(n):
                            acc += Ht[a, i] * dPHT[i, b]
                        dBj[c, a, b] = acc
                # ∂K = (∂P Hᵀ − K ∂B) B⁻¹
                for i in range(n):
                    for a in range(m):
                        acc = dPHT[i, a]
                        for b in range(m):
                            acc -= Kj[i, b] * dBj[c, b, a]
                        KB[i, a] = acc
                for i in range(n):
                    for b in range(m):
                        acc = 0.0
                        for a in range(m):
                            acc += KB[i, a] * Binv[a, b]
                        dKj[c, i, b] = acc
        for a in range(m):
            for b in range(m):
                B[t, a, b] = Bj[a, b]
                for c in range(k):
                    dB[t, a, b, c] = dBj[c, a, b]
        # innovation and its derivative
        for a in range(m):
            acc = y[t, a] - d[t, a]
            for i in range(n):
                acc -= Ht[a, i] * x[i]
            v[a] = acc
            nu[t, a] = acc
            for c in range(k):
                acc = -dd[t, a, c]
                for i in range(n):
                    acc -= Ht[a, i] * S[i, c]
                dv[a, c] = acc
                dnu[t, a, c] = acc
        quad = 0.0
        for a in range(m):
            for b in range(m):
                quad += v[a] * Binv[a, b] * v[b]
        total += quad + logdet
        # measurement update of the state and its derivative
        for i in range(n):
            acc = x[i]
            for a in range(m):
                acc += Kj[i, a] * v[a]
            x[i] = acc
            for c in range(k):
                acc = S[i, c]
                for a in range(m):
                    acc += Kj[i, a] * dv[a, c] + dKj[c, i, a] * v[a]
                S[i, c] = acc
        if t == T - 1:
            break
        iv = t if per_interval else 0
        Phi = Phis[iv]
        dPhi = dPhis[iv]
        Q = Qs[iv]
        dQ = dQs[iv]
        if not steady:
            # P⁺ = P − K B Kᵀ and its derivative (KB = K B)
            for i in range(n):
                for b in range(m):
                    acc = 0.0
                    for a in range(m):
                        acc += Kj[i, a] * Bj[a, b]
                    KB[i, b] = acc
            for c in covariant:
                # K ∂B (n, m), for K ∂B Kᵀ
                for i in range(n):
                    for b in range(m):
                        acc = 0.0
                        for a in range(m):
                            acc += Kj[i, a] * dBj[c, a, b]
                        KdB[i, b] = acc
                # ∂P⁺ = ∂P − ∂K B Kᵀ − K B ∂Kᵀ − K ∂B Kᵀ (symmetric: upper triangle, mirrored)
                for i in range(n):
                    for j in range(i, n):
                        acc = dP[c, i, j]
                        for a in range(m):
                            acc -= (dKj[c, i, a] * KB[j, a] + KB[i, a] * dKj[c, j, a]
                                    + KdB[i, a] * Kj[j, a])
                        dP[c, i, j] = acc
                        dP[c, j, i] = acc
            for i in range(n):
                for j in range(n):
                    acc = P[i, j]
                    for a in range(m):
                        acc -= KB[i, a] * Kj[j, a]
                    P[i, j] = acc
            # predict: P' = Φ P⁺ Φᵀ + Q, ∂P' = ∂Φ P⁺ Φᵀ + Φ P⁺ ∂Φᵀ + Φ ∂P⁺ Φᵀ + ∂Q
            for i in range(n):
                for j in range(n):
                    acc = 0.0
                    for q in range(n):
                        acc += P[i, q] * Phi[j, q]
                    W[i, j] = acc                       # P⁺ Φᵀ
            for i in range(n):
                for j in range(n):
                    PhiT[i, j] = Phi[j, i]
            for ci in range(covariant.shape[0]):
                c = covariant[ci]
                # ∂P⁺ Φᵀ, and Φ times it below, a row at a time: each entry summed over q in
                # order, all of a row's at once
                for i in range(n):
                    for j in range(n):
                        W2[i, j] = 0.0
                    for q in range(n):
                        a = dP[c, i, q]
                        for j in range(n):
                            W2[i, j] += a * PhiT[q, j]
                # ∂P' = ∂Q + ∂Φ P⁺ Φᵀ + (∂Φ P⁺ Φᵀ)ᵀ + Φ ∂P⁺ Φᵀ (upper triangle, mirrored);
                # ∂Φ = 0 beyond the first kp directions
                for i in range(n):
                    for j in range(n):
                        row[j] = dQ[ci, i, j]
                    for q in range(n):
                        a = Phi[i, q]
                        for j in range(n):
                            row[j] += a * W2[q, j]
                    for j in range(i, n):
                        acc = row[j]
                        if c < kp:
                            for q in range(n):
                                acc += dPhi[c, i, q] * W[q, j] + dPhi[c, j, q] * W[q, i]
                        dP[c, i, j] = acc
                        dP[c, j, i] = acc
            for i in range(n):
                for j in range(n):
                    acc = Q[i, j]
                    for q in range(n):
                        acc += Phi[i, q] * W[q, j]
                    Pn[i, j] = acc
            for i in range(n):
                for j in range(n):
                    P[i, j] = 0.5 * (Pn[i, j] + Pn[j, i])
        for s in range(substeps):
            st = 2 * (t * substeps + s)
            # RK4 stages k = F (x + a k_prev) + g and their sensitivities
            # ∂k = F (∂x + a ∂k_prev) + ∂F (x + a k_prev) + ∂g (exact derivative of the step)
            # F and ∂F at the step's start, middle and end (one matrix when constant)
            F0 = Fs[st] if varying else Fs[0]
            Fm = Fs[st + 1] if varying else Fs[0]
            F1 = Fs[st + 2] if varying else Fs[0]
            dF0 = dFs[st] if varying else dFs[0]
            dFm = dFs[st + 1] if varying else dFs[0]
            dF1 = dFs[st + 2] if varying else dFs[0]
            _stage(F0, g[st], x, x, 0.0, x1, k1)
            _sensitivity_stage(F0, S, S, 0.0, dF0, dg[st], x1, s1)
            _stage(Fm, g[st + 1], x, k1, half, x2, k2)
            _sensitivity_stage(Fm, S, s1, half, dFm, dg[st + 1], x2, s2)
            _stage(Fm, g[st + 1], x, k2, half, x3, k3)
            _sensitivity_stage(Fm, S, s2, half, dFm, dg[st + 1], x3, s3)
            _stage(F1, g[st + 2], x, k3, h, x4, k4)
            _sensitivity_stage(F1, S, s3, h, dF1, dg[st + 2], x4, s4)
            for i in range(n):
                x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
                for c in range(k):
                    S[i, c] += h / 6.0 * (s1[i, c] + 2.0 * s2[i, c] + 2.0 * s3[i, c] + s4[i, c])
    return total


def sensitivity_scan_example(steady=True):
    """Return arguments of the types filter_error passes to sensitivity_scan."""
    T, n, m, k, kp, sub = 2, 2, 1, 2, 1, 1
    M = (T - 1) * sub
    return (np.zeros((1, n, n)), np.zeros((2 * M + 1, n)), np.zeros((1, kp, n, n)),
            np.zeros((2 * M + 1, kp, n)), 0.1, sub, np.eye(n)[None], np.zeros((1, kp, n, n)),
            np.zeros((1, n, n)), np.zeros((1, k, n, n)), np.eye(m), np.zeros((k, m, m)),
            np.arange(k), np.ones((T, m, n)), np.zeros((T, m)), np.zeros((T, m, k)),
            np.zeros((T, m)), np.zeros(n), np.zeros((n, k)), steady, np.eye(m),
            np.zeros((n, m)), np.zeros((k, m, m)), np.zeros((k, n, m)), np.empty((T, m)),
            np.empty((T, m, k)), np.empty((T, m, m)), np.empty((T, m, m, k)))


def warm_up():
    """Compile (or load from the cache) the scan for the argument types filter_error passes."""
    for steady in (True, False):
        sensitivity_scan(*sensitivity_scan_example(steady))
