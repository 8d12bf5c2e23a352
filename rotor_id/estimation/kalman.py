"""
Kalman filter and Rauch-Tung-Striebel smoother for the flapping models (Ch.1 eqs 26-32).

The continuous model x′ = F(t,p) x + g(t,p,u) + Γ w is discretised between samples with the
*same* RK4 step maps as the simulator (:mod:`rotor_id.estimation.simulate`), so the filter's
prediction with zero gain is the simulated response to rounding:

    x_{j+1} = Φ_j x_j + c_j + w_j,        E[w_j w_jᵀ] = Q_j,        y_j = H_j x_j + d_j + v_j

Process noise (report eq. 29a puts it on the λI′, λII′ rows) enters on chosen state rows with
one of two documented noise models:

* ``'white'`` (default): continuous white noise of intensity q = σ² (per unit nondimensional
  time) on the rows, as Ch.1 eq. 28 (Γ Q Γᵀ); Q_j from Van Loan's matrix exponential with F
  frozen at the interval midpoint (exact for time-invariant F, second order in Δt for periodic
  F). A sequence of σ_s held over Δt has the same effect to first order for q = σ_s² Δt.
* ``'held'``: a Gaussian sequence of standard deviation σ held constant over each
  sample interval, which is how the report generated its system noise and exactly what
  ``simulate(..., forcing=...)`` integrates. Q_j = σ² G_j G_jᵀ with G_j the RK4 response of the
  state to a unit held input, so the filter is exact for data made that way.

The filter gives the innovations ν_j and their covariances B_j (eq. 32) and the likelihood of
eq. 26; the smoother reconstructs unmeasured states (rates, inflow) from noisy flapping even
with parameter values that may be wrong (report Ch.2, "updated Kalman filter").
"""

from dataclasses import dataclass
import math
import time
from typing import Callable, Sequence, TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from rotor_id.estimation import kernels
from rotor_id.estimation.simulate import (
    DEFAULT_MAX_STEP, fine_grid, gap_refinement, rk4_constant_forcing, rk4_maps, rk4_transition,
    substeps_for, time_invariant_steps)

if TYPE_CHECKING:
    from rotor_id.physics.models import LinearModel

NOISE_MODELS = ('held', 'white')


@dataclass
class DiscreteModel:
    """
    A model discretised at the sample times.

    Attributes
    ----------
    t : ndarray, shape (T,)
    Phi : ndarray, shape (T-1, n, n)
        State transition over each sample interval.
    c : ndarray, shape (T-1, n)
        Input response over each interval (x_{j+1} = Φ_j x_j + c_j + w_j).
    Q : ndarray, shape (T-1, n, n)
        Covariance of the discrete process noise w_j.
    H : ndarray, shape (T, m, n)
    d : ndarray, shape (T, m)
        Output offset (y = H x + d + v).
    G : ndarray, shape (T-1, n, q) or None
        Response to a unit noise input on each noise row (held model), Q = σ² G Gᵀ.

    """

    t: np.ndarray
    Phi: np.ndarray
    c: np.ndarray
    Q: np.ndarray
    H: np.ndarray
    d: np.ndarray
    G: np.ndarray | None = None

    @property
    def time_invariant(self) -> bool:
        """Tell whether Φ, Q and H are the same at every sample (a steady-state gain exists)."""
        def constant(a):
            return a.shape[0] <= 1 or bool(np.allclose(a, a[:1], rtol=1e-12, atol=1e-14))
        return constant(self.Phi) and constant(self.Q) and constant(self.H)


def noise_rows(model: 'LinearModel', rows: Sequence[str | int]) -> list[int]:
    """State indices of the process-noise rows, from names or indices."""
    out = []
    for row in rows:
        if isinstance(row, str):
            if row not in model.state_names:
                raise ValueError(f'process-noise row {row!r} is not a state of {model.name!r}; '
                                 f'its states are {", ".join(model.state_names)}')
            out.append(model.state_names.index(row))
        else:
            out.append(int(row))
    return out


def default_noise_rows(model: 'LinearModel') -> list[int]:
    """
    Rows driven by system noise when the user does not say (documented choice).

    The inflow rows λI, λII for models with a wake (report eq. 29a); otherwise the flap
    acceleration rows (the ``_dot`` states: unmodelled moments act on the blade there).
    """
    rows = [i for i, s in enumerate(model.state_names) if s.startswith('lambda')]
    if not rows:
        rows = [i for i, s in enumerate(model.state_names) if s.endswith('_dot')]
    return rows


def discretize(model: 'LinearModel', p: npt.ArrayLike, inputs: Callable[[np.ndarray], np.ndarray],
               t: npt.ArrayLike, rows: Sequence[str | int] = (), noise_std: npt.ArrayLike = 0.0,
               noise_model: str = 'white', max_step: float = DEFAULT_MAX_STEP) -> DiscreteModel:
    """
    Discretise ``model`` at the sample times with the simulator's RK4 maps.

    Parameters
    ----------
    model : LinearModel
        The flapping model (rotor_id.physics.models).
    p : array_like, shape (P,)
        Full parameter vector.
    inputs : callable
        ``u = inputs(t)``, shape (len(t), 3).
    t : array_like, shape (T,)
        Sample times (nondimensional), strictly increasing.
    rows : sequence of int or str
        State rows driven by process noise.
    noise_std : float or array_like, shape (len(rows),)
        σ of the held noise sequence (``'held'``) or √q of the white-noise intensity
        (``'white'``) on each row.
    noise_model : {'held', 'white'}
        'white' (intensity) or 'held' (sequence), see the module docstring.
    max_step : float
        Longest RK4 step (as in :func:`~rotor_id.estimation.simulate.simulate`).

    Returns
    -------
    DiscreteModel

    """
    if noise_model not in NOISE_MODELS:
        raise ValueError(f'noise_model must be one of {", ".join(NOISE_MODELS)}, '
                         f'not {noise_model!r}')
    t = np.asarray(t, dtype=float)
    p = np.asarray(p, dtype=float)
    if t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0):
        raise ValueError('the Kalman filter needs at least two strictly increasing sample times')
    refined = gap_refinement(t, max_step)
    if refined is not None:
        # lost samples: discretise over the gaps' filled grid, compose back to the samples
        fine, index = refined
        dm = discretize(model, p, inputs, fine, rows, noise_std, noise_model, max_step)
        return _compose_intervals(dm, index, t, noise_std)
    rows = noise_rows(model, rows)
    sigma = np.broadcast_to(np.asarray(noise_std, dtype=float), (len(rows),))
    n = model.n_states
    T = t.size
    m = substeps_for(t, max_step)
    # stage times of all RK4 steps, and the affine step maps x⁺ = Φ_s x + c_s
    tf = fine_grid(t, m)
    u = inputs(tf)
    F, g = model.system(tf, p, u)
    h = np.repeat(np.diff(t) / m, m)
    constant = time_invariant_steps(F, h, t)
    if constant:
        # one transition for every step (as the simulator does); c still per step
        Phi_s, c_s = rk4_maps(F[:1], g, h[:1])
        Phi_s = np.broadcast_to(Phi_s, (h.size, n, n))
    else:
        Phi_s, c_s = rk4_maps(F, g, h)
    Phi_s = Phi_s.reshape(T - 1, m, n, n)
    c_s = c_s.reshape(T - 1, m, n)
    # compose the m steps of each sample interval (vectorised over intervals)
    Phi = np.broadcast_to(np.eye(n), (T - 1 if not constant else 1, n, n)).copy()
    c = np.zeros((T - 1, n))
    for s in range(m):
        Phi = Phi_s[:Phi.shape[0], s] @ Phi
        if constant:                    # one matrix for all intervals: a single product
            c = c @ Phi_s[0, s].T + c_s[:, s]
        else:
            c = np.einsum('jab,jb->ja', Phi_s[:, s], c) + c_s[:, s]
    if constant:
        Q = np.broadcast_to(_constant_noise_covariance_memo(F[0], np.diff(t)[0], m, rows, sigma,
                                                            noise_model), (T - 1, n, n))
        G = np.broadcast_to(held_noise_response(F[0], np.diff(t)[0], m, rows),
                            (T - 1, n, len(rows))) if noise_model == 'held' else None
    else:
        Fmid = None
        if noise_model == 'white':
            mid = 0.5 * (t[:-1] + t[1:])
            Fmid = model.system(mid, p, inputs(mid))[0]
        Q, G = varying_noise_covariance(F, Fmid, t, m, rows, sigma, noise_model)
    if constant:
        Phi = np.broadcast_to(Phi, (T - 1, n, n))
    H = model.output_matrix(t)
    d = model.output_offset(t, p)
    return DiscreteModel(t=t, Phi=Phi, c=c, Q=Q, H=H, d=d, G=G)


def _compose_intervals(dm, index, t, noise_std):
    """
    Return the DiscreteModel at the samples ``t`` = ``dm.t[index]`` of one over a finer grid.

    The intervals between two samples are composed: Φ = Φ_k ⋯ Φ_1, c and the noise carried
    through them (white noise: Q = Σ Φ_(k..i+1) Q_i Φ_(k..i+1)ᵀ; held noise, one value held
    over the whole sample interval: G = Σ Φ_(k..i+1) G_i, Q = G diag(σ²) Gᵀ).
    """
    Phi = np.array(dm.Phi[index[:-1]])
    c = np.array(dm.c[index[:-1]])
    Q = np.array(dm.Q[index[:-1]])
    G = None if dm.G is None else np.array(dm.G[index[:-1]])
    if G is not None:
        variance = np.broadcast_to(np.asarray(noise_std, dtype=float), (G.shape[-1],))**2
    for j in np.flatnonzero(np.diff(index) > 1):
        for i in range(index[j] + 1, index[j + 1]):
            step = dm.Phi[i]
            Phi[j] = step @ Phi[j]
            c[j] = step @ c[j] + dm.c[i]
            if G is None:
                Q[j] = step @ Q[j] @ step.T + dm.Q[i]
            else:
                G[j] = step @ G[j] + dm.G[i]
        if G is not None:
            Q[j] = (G[j] * variance) @ G[j].T
    return DiscreteModel(t=t, Phi=Phi, c=c, Q=Q, H=np.asarray(dm.H)[index],
                         d=np.asarray(dm.d)[index], G=G)


def varying_noise_covariance(F: np.ndarray, Fmid: np.ndarray | None, t: np.ndarray,
                             substeps: int, rows: Sequence[int], sigma: np.ndarray,
                             noise_model: str) -> tuple[np.ndarray, np.ndarray | None]:
    """
    Return Q (T-1, n, n) and G (T-1, n, q) or None of a model whose F varies (periodic).

    The varying branch of :func:`discretize`: for ``'held'`` the RK4 response G_j of each
    interval to a unit input held on each noise row (F at the stage times, (2M+1, n, n)) and
    Q_j = G_j diag(σ²) G_jᵀ; for ``'white'`` Van Loan's integral with F frozen at the interval
    midpoints (Fmid (T-1, n, n)). A filter's sensitivity differentiates this function along
    ∂F/∂p.
    """
    T = t.size
    n = F.shape[-1]
    sigma = np.broadcast_to(np.asarray(sigma, dtype=float), (len(rows),))
    if noise_model == 'white':
        Qc = np.zeros((n, n))
        Qc[rows, rows] = sigma**2
        assert Fmid is not None                 # discretize gives the midpoints' F for 'white'
        return van_loan(Fmid, Qc, np.diff(t))[1], None
    h = np.repeat(np.diff(t) / substeps, substeps)
    Phi_s = rk4_transition(F, h).reshape(T - 1, substeps, n, n)
    G_s = np.zeros((T - 1, substeps, n, len(rows)))
    for k, row in enumerate(rows):
        w = np.zeros((h.size, n))
        w[:, row] = 1.0
        G_s[:, :, :, k] = rk4_constant_forcing(F, w, h).reshape(T - 1, substeps, n)
    G = np.zeros((T - 1, n, len(rows)))
    for s in range(substeps):
        G = Phi_s[:, s] @ G + G_s[:, s]
    return np.einsum('jak,k,jbk->jab', G, sigma**2, G), G


def held_noise_response(F: np.ndarray, dt: float, substeps: int,
                        rows: Sequence[int]) -> np.ndarray:
    """
    Return G (n, q) of one sample interval of a time-invariant model (``'held'`` noise).

    G is the RK4 response of the state to a unit input held on each noise row over the
    interval. F (n, n) is the constant system matrix, ``substeps`` RK4 steps of dt/substeps each.
    """
    n = F.shape[0]
    h = np.array([dt / substeps])
    F1 = F[None]
    step = rk4_maps(F1, np.zeros((1, n)), h)[0][0]
    G = np.zeros((n, len(rows)))
    for k, row in enumerate(rows):
        w = np.zeros((1, n))
        w[0, row] = 1.0
        G_s = rk4_constant_forcing(F1, w, h)[0]
        g = np.zeros(n)
        for _ in range(substeps):
            g = step @ g + G_s
        G[:, k] = g
    return G


def constant_noise_covariance(F: np.ndarray, dt: float, substeps: int, rows: Sequence[int],
                              sigma: np.ndarray, noise_model: str) -> np.ndarray:
    """
    Return Q (n, n) of one sample interval of a time-invariant model.

    The constant branch of :func:`discretize`: σ² G Gᵀ for ``'held'``, Van Loan's integral
    for ``'white'``.

    Q is linear in σ² and depends on the parameters through F only, so a filter's sensitivity
    needs this function alone (not the whole discretisation) to differentiate Q.
    """
    n = F.shape[0]
    sigma = np.broadcast_to(np.asarray(sigma, dtype=float), (len(rows),))
    if noise_model == 'held':
        G = held_noise_response(F, dt, substeps, rows)
        return np.einsum('ak,k,bk->ab', G, sigma**2, G)
    Qc = np.zeros((n, n))
    Qc[rows, rows] = sigma**2
    return van_loan(F[None], Qc, np.array([dt]))[1][0]


#: Q of the time-invariant discretisations done last, by their exact arguments: a stream cut
#: into batches (the live state estimator, 50 a second) discretises the same F and Δt each
#: time, and Van Loan's exponential was a third of its discretisation.
_Q_MEMO: dict = {}
_Q_MEMO_SIZE = 32


def _constant_noise_covariance_memo(F, dt, substeps, rows, sigma, noise_model):
    """:func:`constant_noise_covariance`, remembered for the same arguments (a read-only Q)."""
    key = (F.tobytes(), F.shape, float(dt), int(substeps), tuple(rows),
           np.asarray(sigma, dtype=float).tobytes(), noise_model)
    Q = _Q_MEMO.get(key)
    if Q is None:
        if len(_Q_MEMO) >= _Q_MEMO_SIZE:
            _Q_MEMO.clear()
        Q = constant_noise_covariance(F, dt, substeps, rows, sigma, noise_model)
        Q.setflags(write=False)
        _Q_MEMO[key] = Q
    return Q


def expm_batch(A: np.ndarray) -> np.ndarray:
    """
    Matrix exponentials of a stack of small matrices (scaling and squaring, Taylor order 12).

    The rows are scaled by 2^-s to a 1-norm ≤ 0.5, where the truncated series has a relative
    error below 1e-17; vectorised over the stack, so it needs no per-matrix library call.

    Parameters
    ----------
    A : ndarray, shape (K, N, N)
        The matrices.

    Returns
    -------
    ndarray, shape (K, N, N)

    """
    A = np.asarray(A, dtype=float)
    norm = np.max(np.sum(np.abs(A), axis=-2), axis=-1)
    squarings = np.maximum(0, np.ceil(np.log2(np.maximum(norm, 1e-300) / 0.5))).astype(int)
    scaled = A / (2.0 ** squarings)[:, None, None]
    # Σ_{k≤12} A^k / k! by Paterson-Stockmeyer: in powers of A⁴ with cubic coefficients in
    # A, five products instead of Horner's twelve
    A2 = scaled @ scaled
    A3 = A2 @ scaled
    A4 = A2 @ A2
    c = [1.0 / math.factorial(k) for k in range(13)]
    diagonal = np.arange(A.shape[-1])

    def block(j, more=None):
        out = c[4 * j + 1] * scaled
        out += c[4 * j + 2] * A2
        out += c[4 * j + 3] * A3
        out[:, diagonal, diagonal] += c[4 * j]
        if more is not None:
            out += more
        return out
    E = block(0, A4 @ block(1, A4 @ block(2, c[12] * A4)))
    for level in range(int(squarings.max(initial=0))):
        more = squarings > level
        E[more] = E[more] @ E[more]
    return E


def van_loan(F: np.ndarray, Qc: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Van Loan (1978): Φ = e^{FΔt} and Q_d = ∫₀^Δt e^{Fs} Qc e^{Fᵀs} ds for F held constant.

    Parameters
    ----------
    F : ndarray, shape (K, n, n)
        F of each interval (frozen, e.g. at its midpoint).
    Qc : ndarray, shape (n, n)
        Continuous white-noise intensity (Γ Q Γᵀ of Ch.1 eq. 28).
    dt : ndarray, shape (K,)
        Interval lengths.

    Returns
    -------
    Phi, Qd : ndarray, shape (K, n, n) each

    """
    F = np.asarray(F, dtype=float)
    K, n = F.shape[0], F.shape[-1]
    # block matrix [[-F, Qc], [0, Fᵀ]]·Δt; its exponential holds Φ⁻¹Q_d and Φᵀ
    big = np.zeros((K, 2 * n, 2 * n))
    big[:, :n, :n] = -F
    big[:, :n, n:] = Qc
    big[:, n:, n:] = np.swapaxes(F, -1, -2)
    E = expm_batch(big * np.asarray(dt, dtype=float)[:, None, None])
    Phi = np.swapaxes(E[:, n:, n:], -1, -2)
    Qd = Phi @ E[:, :n, n:]
    return Phi, 0.5 * (Qd + np.swapaxes(Qd, -1, -2))


@dataclass
class FilterResult:
    """
    Output of :func:`kalman_filter` (sample j: prediction j|j−1, update j|j).

    Attributes
    ----------
    x_pred, P_pred : ndarray, shapes (T, n), (T, n, n)
        Predicted state and covariance before the measurement at t_j (eqs 27-28).
    x_filt, P_filt : ndarray, shapes (T, n), (T, n, n)
        Filtered state and covariance after it (eqs 29-30).
    innovations : ndarray, shape (T, m)
        ν_j = y_j − H_j x̂(j|j−1) − d_j (eq. 23).
    B : ndarray, shape (T, m, m)
        Innovation covariances H P Hᵀ + R (eq. 32).
    K : ndarray, shape (T, n, m)
        Gains (eq. 31).
    cost : float
        Eq. 26: Σ_j [ν_jᵀ B_j⁻¹ ν_j + log|B_j|].
    log_likelihood : float
        −½ (cost + N m log 2π), the Gaussian log-likelihood of the samples.

    """

    x_pred: np.ndarray
    P_pred: np.ndarray
    x_filt: np.ndarray
    P_filt: np.ndarray
    innovations: np.ndarray
    B: np.ndarray
    K: np.ndarray
    cost: float
    log_likelihood: float


def _symmetric(P):
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def steady_state_covariance(dm: DiscreteModel, R: np.ndarray) -> np.ndarray:
    """Predicted covariance P of the steady-state filter (discrete algebraic Riccati equation)."""
    Phi, Q, H = dm.Phi[0], dm.Q[0], dm.H[0]
    n = Phi.shape[0]
    if not np.any(Q):
        return np.zeros((n, n))         # no process noise: the prediction is exact
    import scipy.linalg             # only here: its import is a tenth of a second
    P = scipy.linalg.solve_discrete_are(Phi.T, H.T, Q, R)
    return _symmetric(P)


def kalman_filter(dm: DiscreteModel, y: npt.ArrayLike, x0: npt.ArrayLike, P0: npt.ArrayLike,
                  R: npt.ArrayLike, gain: str = 'time-varying') -> 'FilterResult':
    """
    Kalman filter over the samples of a discretised model.

    Parameters
    ----------
    dm : DiscreteModel
        The model discretised at the sample times.
    y : ndarray, shape (T, m)
        Measurements.
    x0 : ndarray, shape (n,)
        State estimate at t[0] before its measurement.
    P0 : ndarray, shape (n, n)
        Its covariance (zero when x0 is a parameter, as in output error).
    R : ndarray, shape (m, m) or (m,)
        Measurement-noise covariance (a vector is a diagonal).
    gain : {'time-varying', 'steady'}
        'steady' uses the constant gain of the algebraic Riccati equation throughout (Φ, Q and
        H must be time-invariant; P0 is then ignored).

    Returns
    -------
    FilterResult

    Notes
    -----
    The time-varying filter runs in the compiled filter scan where it is loaded
    (:func:`~rotor_id.estimation.kernels.filter_kernel`, one call; its covariance update is
    P − K B Kᵀ, equal to the Joseph form here to rounding); this loop is its reference.

    """
    y = np.asarray(y, dtype=float)
    T, m = y.shape
    n = dm.Phi.shape[1]
    R = np.asarray(R, dtype=float)
    R = np.diag(R) if R.ndim == 1 else R
    if dm.H.shape[0] != T:
        raise ValueError(f'{T} measurements for a model discretised at {dm.H.shape[0]} samples')
    if gain not in ('time-varying', 'steady'):
        raise ValueError(f"gain must be 'time-varying' or 'steady', not {gain!r}")
    x_pred = np.empty((T, n))
    P_pred = np.empty((T, n, n))
    x_filt = np.empty((T, n))
    P_filt = np.empty((T, n, n))
    nu = np.empty((T, m))
    B = np.empty((T, m, m))
    K = np.empty((T, n, m))
    steady = gain == 'steady'
    if steady:
        if not dm.time_invariant:
            raise ValueError('a steady-state gain needs a time-invariant model (constant Φ, Q '
                             "and H); use gain='time-varying' for periodic models")
        P_ss = steady_state_covariance(dm, R)
        B_ss = _symmetric(dm.H[0] @ P_ss @ dm.H[0].T + R)
        K_ss = np.linalg.solve(B_ss, dm.H[0] @ P_ss).T
        P_ss_filt = _symmetric((np.eye(n) - K_ss @ dm.H[0]) @ P_ss)
    x = np.asarray(x0, dtype=float).copy()
    P = np.asarray(P0, dtype=float).copy()
    compiled = None if steady else kernels.filter_kernel()
    if compiled is not None:
        # one model of the stacked filter scan, every state kept (its update P − K B Kᵀ equals
        # the Joseph form below to rounding)
        cost = np.empty(1)
        compiled(dm.Phi[:, None], dm.c[:, None], dm.Q[:, None], dm.H[:, None], dm.d[:, None],
                 y, x[None], R[None], P[None], False, nu[None], B[None], K[None], cost,
                 np.empty((1, n)), np.empty((1, n, n)),
                 states=(x_pred[None], P_pred[None], x_filt[None], P_filt[None]))
        loglik = -0.5 * (float(cost[0]) + T * m * math.log(2.0 * math.pi))
        return FilterResult(x_pred, P_pred, x_filt, P_filt, nu, B, K, float(cost[0]), loglik)
    clock = time.process_time()
    eye = np.eye(n)
    cost = 0.0
    for j in range(T):
        H = dm.H[j]
        if steady:
            P = P_ss
        x_pred[j], P_pred[j] = x, P
        # error (residual) between measurement and prediction (eq. 23)
        nu[j] = y[j] - H @ x - dm.d[j]
        if steady:
            B[j], K[j] = B_ss, K_ss
        else:
            # project system uncertainty into measurement space (eq. 32)
            B[j] = _symmetric(H @ P @ H.T + R)
            # Kalman gain K = P Hᵀ B⁻¹ (eq. 31)
            K[j] = np.linalg.solve(B[j], H @ P).T
        # likelihood term of eq. 26: νᵀB⁻¹ν + log|B|
        chol = np.linalg.cholesky(B[j])
        z = np.linalg.solve(chol, nu[j])
        cost += float(z @ z) + 2.0 * float(np.sum(np.log(np.diag(chol))))
        # update the state with the innovation (eq. 29)
        x = x + K[j] @ nu[j]
        if steady:
            P = P_ss_filt
        else:
            # P = (I−KH) P (I−KH)ᵀ + K R Kᵀ (Joseph form of eq. 30, stays symmetric positive)
            IKH = eye - K[j] @ H
            P = _symmetric(IKH @ P @ IKH.T + K[j] @ R @ K[j].T)
        x_filt[j], P_filt[j] = x, P
        if j < T - 1:
            # predict the state and its covariance to the next sample (eqs 27-28, discrete)
            x = dm.Phi[j] @ x + dm.c[j]
            P = _symmetric(dm.Phi[j] @ P @ dm.Phi[j].T + dm.Q[j])
    kernels.note_numpy_seconds(time.process_time() - clock)
    loglik = -0.5 * (cost + T * m * math.log(2.0 * math.pi))
    return FilterResult(x_pred, P_pred, x_filt, P_filt, nu, B, K, cost, loglik)


@dataclass
class SmootherResult:
    """
    Output of :func:`rts_smoother`.

    Attributes
    ----------
    x : ndarray, shape (T, n)
        Smoothed states E[x_j | all samples].
    P : ndarray, shape (T, n, n)
        Their covariances.
    C : ndarray, shape (T-1, n, n)
        Smoother gains.

    """

    x: np.ndarray
    P: np.ndarray
    C: np.ndarray


def rts_smoother(dm: DiscreteModel, filtered: 'FilterResult') -> 'SmootherResult':
    """
    Rauch-Tung-Striebel fixed-interval smoother (report Ch.1 ref. 8).

    Parameters
    ----------
    dm : DiscreteModel
        The model discretised at the sample times.
    filtered : FilterResult
        Output of :func:`kalman_filter` on ``dm``.

    Returns
    -------
    SmootherResult

    """
    T, n = filtered.x_filt.shape
    xs = filtered.x_filt.copy()
    Ps = filtered.P_filt.copy()
    # smoother gains C_j = P(j|j) Φ_jᵀ P(j+1|j)⁻¹ (pseudo-inverse where P(j+1|j) is singular),
    # all at once: they depend on the filter's covariances alone
    cross = dm.Phi[:T - 1] @ filtered.P_filt[:-1]
    C = np.swapaxes(np.linalg.pinv(filtered.P_pred[1:], rcond=1e-12, hermitian=True) @ cross,
                    -1, -2)
    for j in range(T - 2, -1, -1):
        # correct the filtered estimate with what the later samples say
        xs[j] = filtered.x_filt[j] + C[j] @ (xs[j + 1] - filtered.x_pred[j + 1])
        Ps[j] = _symmetric(filtered.P_filt[j] + C[j] @ (Ps[j + 1] - filtered.P_pred[j + 1])
                           @ C[j].T)
    return SmootherResult(xs, Ps, C)


def state_derivatives(model: 'LinearModel', p: npt.ArrayLike,
                      inputs: Callable[[np.ndarray], np.ndarray], t: npt.ArrayLike,
                      x: np.ndarray) -> np.ndarray:
    """Model state derivatives x′ = F(t,p) x + g(t,p,u) at the samples, shape (T, n)."""
    t = np.asarray(t, dtype=float)
    F, g = model.system(t, np.asarray(p, dtype=float), inputs(t))
    return np.einsum('tij,tj->ti', F, x) + g


@dataclass
class Reconstruction:
    """States reconstructed from measured outputs (see :func:`reconstruct_states`)."""

    t: np.ndarray
    x_filtered: np.ndarray
    x_smoothed: np.ndarray
    P_smoothed: np.ndarray
    derivatives: np.ndarray
    filtered: FilterResult
    discrete: DiscreteModel


def reconstruct_states(model: 'LinearModel', p: npt.ArrayLike,
                       inputs: Callable[[np.ndarray], np.ndarray], t: npt.ArrayLike,
                       y: npt.ArrayLike, R: npt.ArrayLike, x0: npt.ArrayLike,
                       P0: npt.ArrayLike, rows: Sequence[str | int] | None = None,
                       noise_std: npt.ArrayLike = 0.0, noise_model: str = 'white',
                       max_step: float = DEFAULT_MAX_STEP,
                       smooth: bool = True) -> 'Reconstruction':
    """
    Filter and smooth noisy outputs into all states and their derivatives.

    The derivatives are the central differences of the smoothed states (second order,
    ``np.gradient``): they follow the data where the process noise lets the smoothed trajectory
    leave the model, which a model evaluation F x + g at the current parameters would not.

    Returns
    -------
    Reconstruction

    """
    rows = default_noise_rows(model) if rows is None else rows
    dm = discretize(model, p, inputs, t, rows, noise_std, noise_model, max_step)
    filtered = kalman_filter(dm, y, x0, P0, R)
    if smooth:
        sm = rts_smoother(dm, filtered)
        xs, Ps = sm.x, sm.P
    else:
        xs, Ps = filtered.x_filt, filtered.P_filt
    deriv = np.gradient(xs, np.asarray(t, dtype=float), axis=0)
    return Reconstruction(np.asarray(t, dtype=float), filtered.x_filt, xs, Ps, deriv,
                          filtered, dm)
