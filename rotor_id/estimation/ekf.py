"""
Augmented-state extended Kalman filter: parameters as states (report Ch.1 eq. 49).

The unknown parameters θ join the state as random walks (θ′ = 0, or a small intensity to keep
the filter awake), z = [x, θ]. The augmented system x′ = F(t,θ)x + g(t,θ,u) is bilinear, hence
the *extended* filter: between samples the state is propagated with the simulator's RK4 maps at
the current θ̂, and the transition is linearised with their exact parameter derivatives

    z⁺ = [Φ(θ̂) x + c(θ̂), θ],     ∂z⁺/∂z = [[Φ, ∂(Φx + c)/∂θ], [0, I]]

(the discrete form of the P, P_θx equations of eq. 49). An optional Rauch-Tung-Striebel pass
smooths the augmented trajectory (the "filtering-smoothing" of Lebacqz, Ch.1 ref. 9), and
``passes`` > 1 restarts from the smoothed initial values ("local iteration").

**The covariance of θ̂ is not a confidence measure.** It evolves from the arbitrary a-priori
covariance P_θ(0) and from a linearisation about estimates that are far from the truth early
on (report Ch.1, "Validation of estimates", and Mehra's criticism quoted there). It is returned
because a filter has one, with a warning in every :class:`Estimate`; use output or filter error
for bounds.
"""

from dataclasses import dataclass
import math
import time
from typing import Callable, Sequence, TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from rotor_id.estimation import kalman
from rotor_id.estimation.filter_error import difference_noise_std
from rotor_id.estimation.output_error import (
    Estimate, Experiment, fit_initial_states, IdentificationError, ParameterValues, Problem,
    Progress)
from rotor_id.estimation.simulate import DEFAULT_MAX_STEP, fine_grid, rk4_maps, substeps_for

if TYPE_CHECKING:
    from rotor_id.physics.models import LinearModel

COVARIANCE_WARNING = ('augmented-state EKF: the parameter covariance comes from an arbitrary '
                      'a-priori covariance and a linearisation about early, poor estimates; it '
                      'is NOT a confidence measure (report Ch.1)')


@dataclass
class EKFResult:
    """
    Augmented-state EKF output; z = [x, θ] with θ the unknowns.

    Attributes
    ----------
    t : ndarray, shape (T,)
    names : list of str
        Names of z: the model states, then the unknowns.
    z_filt, P_filt : ndarray, shapes (T, n+k), (T, n+k, n+k)
    z_smooth, P_smooth : ndarray or None
        After the RTS pass (``smooth=True``).
    innovations : ndarray, shape (T, m)
    log_likelihood : float
        Of the innovations (eq. 26), for comparison only.

    """

    t: np.ndarray
    names: list
    z_filt: np.ndarray
    P_filt: np.ndarray
    z_smooth: np.ndarray | None
    P_smooth: np.ndarray | None
    innovations: np.ndarray
    log_likelihood: float
    n_states: int

    @property
    def parameters(self) -> np.ndarray:
        """
        Return the final θ̂: the smoothed value at t0, or the filtered one at the last sample.

        For a random walk without intensity both are the same estimate.
        """
        z = self.z_smooth[0] if self.z_smooth is not None else self.z_filt[-1]
        return z[self.n_states:]

    @property
    def parameter_covariance(self) -> np.ndarray:
        """Covariance block of θ̂ at the same point (NOT a confidence measure)."""
        P = self.P_smooth[0] if self.P_smooth is not None else self.P_filt[-1]
        n = self.n_states
        return P[n:, n:]


def _interval_maps(model, p, idx, inputs, t0, t1, substeps):
    """
    Φ, c of one sample interval at p, and the θ-derivative of Φx + c as D x + e.

    The state and its parameter sensitivities S_k (S_k′ = F S_k + ∂F/∂θ_k x + ∂g/∂θ_k) are
    integrated jointly with the simulator's RK4 maps; RK4 of the joint linear system gives the
    exact derivative of the RK4 state map, so the linearisation is that of the propagation used.
    """
    ts = np.array([t0, t1])
    tf = fine_grid(ts, substeps)
    u = inputs(tf)
    F, g = model.system(tf, p, u)
    dF, dg = model.system_jacobian(tf, p, u)
    n = F.shape[-1]
    k = len(idx)
    size = n * (1 + k)
    Fa = np.zeros((tf.size, size, size))
    ga = np.zeros((tf.size, size))
    Fa[:, :n, :n] = F
    ga[:, :n] = g
    for i, col in enumerate(idx):
        rows = slice(n * (1 + i), n * (2 + i))
        Fa[:, rows, :n] = dF[:, col]
        Fa[:, rows, rows] = F
        ga[:, rows] = dg[:, col]
    h = np.full(substeps, (t1 - t0) / substeps)
    Phi_s, c_s = rk4_maps(Fa, ga, h)
    Phi = np.eye(size)
    c = np.zeros(size)
    for s in range(substeps):
        Phi = Phi_s[s] @ Phi
        c = Phi_s[s] @ c + c_s[s]
    # with S(t0) = 0: x⁺ = Φ_xx x + c_x and S⁺_k = D_k x + e_k
    D = Phi[n:, :n].reshape(k, n, n)
    e = c[n:].reshape(k, n)
    return Phi[:n, :n], c[:n], D, e, F[substeps]


def augmented_ekf(model: 'LinearModel', inputs: Callable[[np.ndarray], np.ndarray],
                  t: npt.ArrayLike, y: npt.ArrayLike, unknowns: Sequence[str],
                  guess: ParameterValues | None = None,
                  known: ParameterValues | None = None, R: npt.ArrayLike | None = None,
                  x0: npt.ArrayLike | None = None, P0_states: npt.ArrayLike | None = None,
                  P0_parameters: npt.ArrayLike | None = None,
                  parameter_noise_std: npt.ArrayLike = 0.0,
                  rows: Sequence[str | int] | None = None, process_noise_std: float = 0.0,
                  smooth: bool = True, max_step: float = DEFAULT_MAX_STEP) -> EKFResult:
    """
    Run the augmented-state EKF over one record.

    Parameters
    ----------
    model : LinearModel
        The flapping model (rotor_id.physics.models).
    inputs : callable
        Input signal, ``u = inputs(t)`` of shape (len(t), 3).
    t : array_like, shape (T,)
        Sample times (nondimensional), strictly increasing.
    y : array_like, shape (T, m)
        Measurements in the model's output channels.
    unknowns : list of str
        Parameters carried as states.
    guess, known : dict, optional
        Starting θ̂ and the fixed parameters (default nominal).
    R : array_like, shape (m,) or (m, m), optional
        Measurement covariance (default from second differences of y).
    x0 : array_like, shape (n,), optional
        Starting state (default: least-squares fit to the data at the guess).
    P0_states : array_like, shape (n, n), optional
        Its covariance (default 10 R̄ I). Arbitrary, like P0_parameters.
    P0_parameters : array_like, shape (k, k), optional
        A-priori covariance of θ (default: (θ_guess/2)², i.e. 50 % one-σ).
    parameter_noise_std : float or array_like
        √intensity of the random walk of θ (0: constant parameters, eq. 41).
    rows, process_noise_std
        State process noise (white, per :mod:`rotor_id.estimation.kalman`).
    smooth : bool
        Run the RTS pass.
    max_step : float
        Longest RK4 step of the propagation.

    Returns
    -------
    EKFResult

    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    names_all = model.parameter_names
    for name in list(unknowns) + list(known or {}) + list(guess or {}):
        if name not in names_all:
            raise IdentificationError(f'unknown parameter {name!r} for model {model.name!r}; '
                                      f'its parameters are {", ".join(names_all)}')
    if y.shape != (t.size, model.n_outputs):
        raise IdentificationError(f'the EKF needs measurements of shape ({t.size}, '
                                  f'{model.n_outputs})')
    idx = [names_all.index(nm) for nm in unknowns]
    p = model.parameter_vector(known)
    for name, value in (guess or {}).items():
        p[names_all.index(name)] = float(value)
    n, k, m = model.n_states, len(idx), model.n_outputs
    T = t.size
    Rm = np.diag(difference_noise_std(y)**2) if R is None else np.asarray(R, dtype=float)
    Rm = np.diag(Rm) if Rm.ndim == 1 else Rm
    if x0 is None:
        prob = Problem([Experiment(model, inputs, t, y, 'estimate')], [], None,
                       dict(zip(names_all, p)))
        x0 = fit_initial_states(prob, np.zeros(n), max_step)
    P0x = np.eye(n) * 10.0 * float(np.mean(np.diag(Rm))) if P0_states is None else P0_states
    P0p = np.diag((0.5 * np.abs(p[idx]) + 1e-12)**2) if P0_parameters is None else \
        np.asarray(P0_parameters, dtype=float)
    rows = kalman.default_noise_rows(model) if rows is None else kalman.noise_rows(model, rows)
    Qc_x = np.zeros((n, n))
    Qc_x[rows, rows] = float(process_noise_std)**2
    q_par = np.broadcast_to(np.asarray(parameter_noise_std, dtype=float)**2, (k,))
    substeps = substeps_for(t, max_step)
    H = model.output_matrix(t)
    N = n + k
    z = np.concatenate([np.asarray(x0, dtype=float), p[idx]])
    P = np.zeros((N, N))
    P[:n, :n] = P0x
    P[n:, n:] = P0p
    z_pred = np.empty((T, N))
    P_pred = np.empty((T, N, N))
    z_filt = np.empty((T, N))
    P_filt = np.empty((T, N, N))
    Jac = np.empty((max(T - 1, 0), N, N))
    nu = np.empty((T, m))
    cost = 0.0
    eye = np.eye(N)
    for j in range(T):
        z_pred[j], P_pred[j] = z, P
        p[idx] = z[n:]
        Ha = np.zeros((m, N))
        Ha[:, :n] = H[j]
        # innovation and its covariance (eqs 23, 32) with the augmented output matrix [H, 0]
        nu[j] = y[j] - H[j] @ z[:n] - model.output_offset(t[j:j + 1], p)[0]
        B = Ha @ P @ Ha.T + Rm
        Kg = np.linalg.solve(B, Ha @ P).T
        cost += float(nu[j] @ np.linalg.solve(B, nu[j])) + float(np.linalg.slogdet(B)[1])
        # update states and parameters together (eq. 49: the θ rows use P_θx)
        z = z + Kg @ nu[j]
        IKH = eye - Kg @ Ha
        P = IKH @ P @ IKH.T + Kg @ Rm @ Kg.T
        z_filt[j], P_filt[j] = z, P
        if j == T - 1:
            break
        # propagate with the RK4 maps at the current θ̂; linearise for the covariance
        p[idx] = z[n:]
        Phi, c, D, e, F_mid = _interval_maps(model, p, idx, inputs, t[j], t[j + 1], substeps)
        x = z[:n]
        J = np.eye(N)
        J[:n, :n] = Phi
        J[:n, n:] = (np.einsum('kab,b->ak', D, x) + e.T)
        Jac[j] = J
        Qa = np.zeros((N, N))
        dt = t[j + 1] - t[j]
        if np.any(Qc_x):
            Qa[:n, :n] = kalman.van_loan(F_mid[None], Qc_x, np.array([dt]))[1][0]
        Qa[n:, n:] = np.diag(q_par * dt)
        z = np.concatenate([Phi @ x + c, z[n:]])
        P = J @ P @ J.T + Qa
        P = 0.5 * (P + P.T)
    loglik = -0.5 * (cost + T * m * math.log(2.0 * math.pi))
    z_s = P_s = None
    if smooth:
        z_s = z_filt.copy()
        P_s = P_filt.copy()
        for j in range(T - 2, -1, -1):
            # extended RTS: gain C = P(j|j) Jᵀ P(j+1|j)⁻¹ with the stored linearisation
            C = np.linalg.lstsq(P_pred[j + 1], Jac[j] @ P_filt[j], rcond=1e-12)[0].T
            z_s[j] = z_filt[j] + C @ (z_s[j + 1] - z_pred[j + 1])
            P_s[j] = P_filt[j] + C @ (P_s[j + 1] - P_pred[j + 1]) @ C.T
            P_s[j] = 0.5 * (P_s[j] + P_s[j].T)
    names = list(model.state_names) + list(unknowns)
    return EKFResult(t, names, z_filt, P_filt, z_s, P_s, nu, loglik, n)


def fit_ekf(experiments: Sequence[Experiment], unknowns: Sequence[str],
            guess: ParameterValues | None = None, known: ParameterValues | None = None,
            noise_std: npt.ArrayLike | None = None,
            progress: Progress | None = None, passes: int = 1,
            smooth: bool = True, parameter_noise_std: npt.ArrayLike = 0.0,
            process_noise_std: float = 0.0, rows: Sequence[str | int] | None = None,
            max_step: float = DEFAULT_MAX_STEP) -> Estimate:
    """
    Augmented-state EKF estimate over one run, as an :class:`Estimate` (method 'ekf').

    ``passes`` > 1 restarts the filter from the previous pass's smoothed (or final) θ̂ and
    initial state, with the same a-priori covariances (local iteration). The covariance in the
    result is the filter's and carries :data:`COVARIANCE_WARNING`.
    """
    if len(experiments) != 1:
        raise IdentificationError('the augmented-state EKF runs over one record; combine runs '
                                  'with output or filter error')
    exp = experiments[0]
    model = exp.model
    m = model.n_outputs
    R = None if noise_std is None else \
        np.broadcast_to(np.asarray(noise_std, dtype=float)**2, (m,)).copy()
    start = dict(guess or {})
    x0 = None
    t_start = time.perf_counter()
    history = []
    for iteration in range(1, passes + 1):
        # (a run fitted has measurements)
        res = augmented_ekf(model, exp.inputs, exp.t, exp.y,  # type: ignore[arg-type]
                            unknowns, start, known, R, x0,
                            parameter_noise_std=parameter_noise_std, rows=rows,
                            process_noise_std=process_noise_std, smooth=smooth,
                            max_step=max_step)
        theta = res.parameters.copy()
        start = dict(zip(unknowns, theta))
        if smooth:                      # (then the RTS pass ran: z_smooth is an array)
            x0 = res.z_smooth[0, :res.n_states]  # type: ignore[index]
        info = {'iteration': iteration, 'cost': -res.log_likelihood,
                'rms': math.sqrt(float(np.mean(res.innovations**2))), 'names': list(unknowns),
                'values': theta.copy(), 'elapsed': time.perf_counter() - t_start,
                'label': 'augmented-state EKF'}
        history.append(info)
        if progress is not None:
            progress(info)
    cov = res.parameter_covariance
    p_final = model.parameter_vector({**(known or {}), **start})
    # (with smooth, the RTS pass ran: z_smooth is an array)
    xs: np.ndarray = res.z_smooth if smooth else res.z_filt  # type: ignore[assignment]
    y_hat = np.einsum('tij,tj->ti', model.output_matrix(exp.t), xs[:, :res.n_states])
    noise = np.sqrt(np.mean((exp.y - y_hat)**2, axis=0))
    return Estimate(
        names=list(unknowns), values=theta, covariance=cov,
        information=np.linalg.pinv(cov), noise_std=noise,
        channel_names=list(model.output_names), cost=-res.log_likelihood,
        neg_log_likelihood=-res.log_likelihood, iterations=passes, converged=True,
        message=f'{passes} filter pass(es)', n_samples=exp.t.size, history=history,
        residuals=[res.innovations], fitted=[y_hat], initial_states=[xs[0, :res.n_states]],
        warnings=[COVARIANCE_WARNING], model_parameters=dict(zip(model.parameter_names,
                                                                 p_final)),
        method='ekf')
