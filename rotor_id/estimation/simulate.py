"""
The one simulator: linear time-varying models, with exact discrete sensitivities.

Integration is classical fourth-order Runge-Kutta with ``substeps`` equal steps between samples.
For a linear system one RK4 step is an affine map ``x⁺ = Φ x + c`` whose Φ and c are polynomials
in F and g at the step's start, middle and end. The sensitivities S = ∂x/∂p are propagated with
the derivative of that same map,

    S⁺ = Φ S + (∂Φ/∂p) x + ∂c/∂p,

which is what the report's sensitivity equations (MODELS.md §0.1, S′ = F S + (∂F/∂p) x + ∂g/∂p)
become under RK4; so the sensitivities are the exact derivatives of the simulated samples, and
agree with finite differences of :func:`simulate` to rounding. All Φ, c and their derivatives are
built vectorised over time; only the recursion itself is sequential, one matrix-vector product
per step on the stacked state z = [x, S₁, …, S_k].
"""

from dataclasses import dataclass
import math

import numpy as np

#: Longest RK4 step (nondimensional time). 0.05 keeps the truncation error of a 2/rev mode at
#: about 1e-7 per revolution, far below any measurement noise.
DEFAULT_MAX_STEP = 0.05
_CHUNK = 4096          # RK4 steps whose transition matrices are held in memory at once


@dataclass
class Simulation:
    """
    Result of :func:`simulate` at the sample times.

    Attributes
    ----------
    t : ndarray, shape (T,)
    x : ndarray, shape (T, n)
        States.
    y : ndarray, shape (T, m)
        Noise-free outputs H x + d.
    dx : ndarray, shape (T, n, k) or None
        Sensitivities ∂x/∂θ for the k requested directions.
    dy : ndarray, shape (T, m, k) or None
        Output sensitivities H ∂x/∂θ + ∂d/∂θ.

    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    dx: np.ndarray = None
    dy: np.ndarray = None


def substeps_for(t, max_step=DEFAULT_MAX_STEP):
    """Return the number of equal RK4 steps per sample interval so no step exceeds ``max_step``."""
    dt = np.diff(np.asarray(t, dtype=float))
    if dt.size == 0:
        return 1
    return max(1, int(math.ceil(float(dt.max()) / max_step - 1e-9)))


def _fine_grid(t, substeps):
    """Stage times: for every RK4 step its start, middle and end (shared with the next step)."""
    t = np.asarray(t, dtype=float)
    frac = np.arange(2 * substeps) / (2 * substeps)
    inner = (t[:-1, None] + np.diff(t)[:, None] * frac[None, :]).ravel()
    return np.concatenate([inner, t[-1:]])


def _rk4_maps(F, g, h, dF=None, dg=None):
    """
    Affine RK4 step maps from stage values (see the module docstring).

    ``F`` (2M+1, n, n) and ``g`` (2M+1, n) hold start/middle/end values of M steps of length
    ``h`` (M,); ``dF`` (2M+1, k, n, n) and ``dg`` (2M+1, k, n) their parameter derivatives.
    Returns Φ (M, n, n), c (M, n) and, when derivatives are given, ∂Φ (M, k, n, n), ∂c (M, k, n).
    """
    F0, Fm, F1 = F[0:-1:2], F[1::2], F[2::2]
    g0, gm, g1 = g[0:-1:2], g[1::2], g[2::2]
    hh = h[:, None, None]
    eye = np.eye(F.shape[-1])
    # stage matrices: k_i = A_i x + b_i
    A1 = F0
    A2 = Fm + 0.5 * hh * (Fm @ A1)
    A3 = Fm + 0.5 * hh * (Fm @ A2)
    A4 = F1 + hh * (F1 @ A3)
    Phi = eye + hh / 6.0 * (A1 + 2.0 * A2 + 2.0 * A3 + A4)
    hv = h[:, None]
    b1 = g0
    b2 = gm + 0.5 * hv * np.einsum('tij,tj->ti', Fm, b1)
    b3 = gm + 0.5 * hv * np.einsum('tij,tj->ti', Fm, b2)
    b4 = g1 + hv * np.einsum('tij,tj->ti', F1, b3)
    c = hv / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
    if dF is None:
        return Phi, c
    dF0, dFm, dF1 = dF[0:-1:2], dF[1::2], dF[2::2]
    dg0, dgm, dg1 = dg[0:-1:2], dg[1::2], dg[2::2]
    h4 = h[:, None, None, None]
    Fm_, F1_ = Fm[:, None], F1[:, None]
    dA1 = dF0
    dA2 = dFm + 0.5 * h4 * (dFm @ A1[:, None] + Fm_ @ dA1)
    dA3 = dFm + 0.5 * h4 * (dFm @ A2[:, None] + Fm_ @ dA2)
    dA4 = dF1 + h4 * (dF1 @ A3[:, None] + F1_ @ dA3)
    dPhi = h4 / 6.0 * (dA1 + 2.0 * dA2 + 2.0 * dA3 + dA4)
    h3 = h[:, None, None]
    db1 = dg0
    db2 = dgm + 0.5 * h3 * (np.einsum('tkij,tj->tki', dFm, b1)
                            + np.einsum('tij,tkj->tki', Fm, db1))
    db3 = dgm + 0.5 * h3 * (np.einsum('tkij,tj->tki', dFm, b2)
                            + np.einsum('tij,tkj->tki', Fm, db2))
    db4 = dg1 + h3 * (np.einsum('tkij,tj->tki', dF1, b3) + np.einsum('tij,tkj->tki', F1, db3))
    dc = h3 / 6.0 * (db1 + 2.0 * db2 + 2.0 * db3 + db4)
    return Phi, c, dPhi, dc


def simulate(model, p, inputs, t, x0, param_index=(), x0_jacobian=None,
             max_step=DEFAULT_MAX_STEP, forcing=None):
    """
    Simulate ``model`` at sample times ``t`` from ``x0`` = x(t[0]), optionally with sensitivities.

    Parameters
    ----------
    model : LinearModel
        The model to simulate.
    p : array_like, shape (P,)
        Full parameter vector of the model.
    inputs : callable
        ``u = inputs(t)`` of shape (len(t), 3), e.g. a StirringSchedule or SampledInput.
    t : array_like, shape (T,)
        Increasing sample times (nondimensional).
    x0 : array_like, shape (n,)
        State at t[0].
    param_index : sequence of int
        Model parameters whose sensitivities are wanted (the first columns of ``dx``).
    x0_jacobian : array_like, shape (n, k), optional
        ∂x0/∂θ for all k sensitivity directions; k ≥ len(param_index). Columns past
        ``len(param_index)`` are directions with no model forcing (e.g. initial states).
    max_step : float
        Longest RK4 step.
    forcing : array_like, shape (T-1, n), optional
        Extra input held constant over each sample interval, added to g (system noise of
        report eq. 29a). Only for plain simulation (no sensitivities).

    Returns
    -------
    Simulation

    """
    t = np.asarray(t, dtype=float)
    p = np.asarray(p, dtype=float)
    if t.ndim != 1 or t.size < 1:
        raise ValueError('simulate needs a 1-D array of at least one sample time')
    if t.size > 1 and np.any(np.diff(t) <= 0):
        raise ValueError('sample times must be strictly increasing')
    x0 = np.asarray(x0, dtype=float)
    n = model.n_states
    param_index = [int(i) for i in param_index]
    want_sens = x0_jacobian is not None or len(param_index) > 0
    if want_sens:
        k = len(param_index) if x0_jacobian is None else np.shape(x0_jacobian)[1]
        if k < len(param_index):
            raise ValueError('x0_jacobian needs at least one column per parameter in param_index')
        S0 = np.zeros((n, k)) if x0_jacobian is None else np.asarray(x0_jacobian, dtype=float)
    else:
        k = 0
    T = t.size
    m = substeps_for(t, max_step)
    xs = np.empty((T, n))
    xs[0] = x0
    Ss = np.empty((T, n, k)) if want_sens else None
    if want_sens:
        Ss[0] = S0
    z = np.concatenate([x0, S0.T.ravel()]) if want_sens else x0.copy()
    # process the record in chunks of whole sample intervals to bound memory
    per_chunk = max(1, _CHUNK // m)
    for start in range(0, T - 1, per_chunk):
        stop = min(T - 1, start + per_chunk)
        ts = t[start:stop + 1]
        tf = _fine_grid(ts, m)
        u = inputs(tf)
        F, g = model.system(tf, p, u)
        h = np.repeat(np.diff(ts) / m, m)
        if want_sens:
            dF, dg = model.system_jacobian(tf, p, u)
            dF = dF[:, param_index]
            dg = dg[:, param_index]
            if forcing is not None:
                raise ValueError('forcing is for plain simulation only')
            Phi, c, dPhi, dc = _rk4_maps(F, g, h, dF, dg)
            z = _propagate_sensitivities(Phi, c, dPhi, dc, z, n, k, m, xs, Ss, start)
        else:
            Phi, c = _rk4_maps(F, g, h)
            if forcing is not None:
                w = np.repeat(np.asarray(forcing, dtype=float)[start:stop], m, axis=0)
                c = c + _rk4_constant_forcing(F, w, h)
            z = _propagate(Phi, c, z, m, xs, start)
    H = model.output_matrix(t)
    y = np.einsum('tij,tj->ti', H, xs) + model.output_offset(t, p)
    if not want_sens:
        return Simulation(t, xs, y)
    dy = H @ Ss
    dd = model.output_offset_jacobian(t, p)[:, :, param_index]
    dy[:, :, :len(param_index)] += dd
    return Simulation(t, xs, y, Ss, dy)


def _rk4_constant_forcing(F, w, h):
    """Contribution to c of an input w (M, n) held constant over each RK4 step."""
    Fm, F1 = F[1::2], F[2::2]
    hv = h[:, None]
    b2 = w + 0.5 * hv * np.einsum('tij,tj->ti', Fm, w)
    b3 = w + 0.5 * hv * np.einsum('tij,tj->ti', Fm, b2)
    b4 = w + hv * np.einsum('tij,tj->ti', F1, b3)
    return hv / 6.0 * (w + 2.0 * b2 + 2.0 * b3 + b4)


def _propagate(Phi, c, x, m, xs, start):
    for j in range(Phi.shape[0]):
        x = Phi[j] @ x + c[j]
        if (j + 1) % m == 0:
            xs[start + (j + 1) // m] = x
    return x


def _propagate_sensitivities(Phi, c, dPhi, dc, z, n, k, m, xs, Ss, start):
    steps = Phi.shape[0]
    nk = len(dc[0])            # parameters with model forcing
    size = n * (1 + k)
    big = np.zeros((steps, size, size))
    for i in range(1 + k):
        big[:, i * n:(i + 1) * n, i * n:(i + 1) * n] = Phi
    for i in range(nk):
        big[:, (1 + i) * n:(2 + i) * n, :n] = dPhi[:, i]
    cz = np.zeros((steps, size))
    cz[:, :n] = c
    cz[:, n:n * (1 + nk)] = dc.reshape(steps, nk * n)
    for j in range(steps):
        z = big[j] @ z + cz[j]
        if (j + 1) % m == 0:
            s = start + (j + 1) // m
            xs[s] = z[:n]
            Ss[s] = z[n:].reshape(k, n).T
    return z
