"""
Filter-error maximum likelihood: measurement *and* system noise (Ch.1 eqs 26-32).

With system noise the predicted outputs come from a Kalman filter built from the model, and the
negative log-likelihood of the samples is (Ch.1 eq. 26, halved, without the constant)

    J(θ) = ½ Σ_j [ ν_jᵀ B_j⁻¹ ν_j + log |B_j| ],     ν_j = y_j − H x̂(j|j−1),   B_j = H P Hᵀ + R

θ holds the model unknowns, the free initial states of each run (as in output error: x(t0) is a
parameter, P(t0) = 0), the process-noise σ on the noise rows (``process_noise_std``; report
eq. 29a: the λI′, λII′ rows of the wake model, else the flap-acceleration rows, see
:func:`rotor_id.estimation.kalman.default_noise_rows`) and, unless given, the measurement-noise
σ of each output channel (``noise_std_<channel>``).

Minimisation is Fisher scoring (Gauss-Newton for a likelihood with parameter-dependent
covariance) with the expected information

    M_ik = Σ_j [ ∂_iν_jᵀ B_j⁻¹ ∂_kν_j + ½ tr(B_j⁻¹ ∂_iB_j B_j⁻¹ ∂_kB_j) ]

whose inverse is the Cramér-Rao bound. The process noise is optimised as its variance q = σ²:
∂J/∂σ vanishes at σ = 0 for any data (Q ∝ σ²), so σ = 0 would be a false stationary point,
while ∂J/∂q is not; σ and its bound are reported (M_σ = (2σ)² M_q). The sensitivities:

* analytic (``gradients='analytic'``, the default) for equally spaced samples, with a
  constant system matrix F (H may rotate, as the wake model's eq.-30 measurement does) or a
  periodic one: the filter is differentiated through (Jategaonkar's filter-error method),

      ∂ν = −H ∂x − ∂d,   ∂B = H ∂P Hᵀ + ∂R,   ∂K = (∂P Hᵀ − K ∂B) B⁻¹,
      ∂x⁺ = ∂x + ∂K ν + K ∂ν,   ∂P⁺ = ∂P − ∂K B Kᵀ − K ∂B Kᵀ − K B ∂Kᵀ,
      ∂P′ = ∂Φ P⁺ Φᵀ + Φ P⁺ ∂Φᵀ + Φ ∂P⁺ Φᵀ + ∂Q,

  with ∂x carried through the same RK4 steps as x (their variational equations, the exact
  derivative of the step map), ∂Φ exact, ∂Q = ∂Q/∂F along ∂F/∂p by a central difference of
  that smooth matrix function (≈1e-12 relative), ∂x(t0) from the initial-state model. With the
  steady-state gain, ∂P comes from the Riccati equation's derivative, a discrete Lyapunov
  equation (:func:`steady_gain_sensitivities`). The recursion is compiled
  (``_filter_kernels_numba``) with a numpy twin; test_filter_error_gradient checks the gradient
  against differences of the likelihood.
* otherwise (uneven time stamps, or ``gradients='finite-difference'``): free initial states
  exactly
  (ν is linear in x(t0) at fixed gains, ∂ν_j/∂x0 = −H_j Ψ_j with Ψ_{j+1} = Φ_j (I − K_j H_j)
  Ψ_j), model and noise parameters by central finite differences of the whole filter (ν_j
  and B_j), step 1e-5 relative: truncation O(h²) ≈ 1e-10 relative, rounding ≈ 1e-11, far
  below any statistical spread. ``test_filter_error`` checks them against the analytic
  output-error sensitivities, which they must equal when the process noise is zero.

The time-varying gain is used for periodic models (and for the wake model's rotating eq.-30
measurement); the steady-state gain of the algebraic Riccati equation when Φ, Q and H are
constant (``gain='auto'``).

Bounds. In one 121-sample record σ_V is often barely determined: at the report's measurement
σ .05 and σ_V .1 the joint ML σ̂_V is zero for about a third of the records (for most records
without process noise), and the Cramér-Rao bound taken there is output error's, too small for
parameters whose scatter grows with σ_V. :func:`fit_filter_error` therefore integrates the
bounds over σ_V, weighted by its restricted likelihood (its docstring has the method);
:func:`fit_filter_error_ml` is the plain estimator with the conditional bound. Measured over
100 seeds per level (bench/results/process_noise.md): coverage .94-.98 for σ_V = .1-.3 where
the conditional bound gives .75-.96, and, without process noise, bounds 1.5-1.9 times output
error's (conditional: within 6 %), because such a record cannot exclude σ_V ≈ .1.
"""

from dataclasses import replace
import math
import time
from typing import Any, Sequence

import numpy as np
import numpy.typing as npt

from rotor_id.estimation import kalman, kernels
from rotor_id.estimation.output_error import (
    damped_gauss_newton_step, dependence_warnings, Estimate, Experiment, fit_initial_states,
    IdentificationError, ParameterValues, Problem, Progress, STOP)
from rotor_id.estimation.simulate import (
    DEFAULT_MAX_STEP, equal_steps, fine_grid, rk4_step_transition,
    rk4_step_transition_derivative, rk4_transition, rk4_transition_derivative, substeps_for,
    time_invariant_steps)
from rotor_id.physics.models import full_along_time
from rotor_id.physics.revolution import (agree, on_record, Series, series_at, system_on_record,
                                         values_on)

PROCESS_NOISE = 'process_noise_std'
#: Interval azimuths per revolution from which a periodic model's Φ_j, Q_j and their
#: derivatives are summed as Fourier series (more where fewer do not agree).
PHASES = (32, 64, 128)
#: ... when they equal the intervals' own to this fraction of their largest entry at the
#: checked intervals (rounding ~1e-14; the filter's likelihood moves by less than 1e-6)
PHASE_AGREE = 1e-9
#: ... or, for ∂Q along a parameter of F (a forward difference of Q, :meth:`FilterProblem.
#: _noise_derivatives`), to the difference's own rounding where that is larger: this many
#: roundings of Q over the step (measured: series and exact ∂Q differ by 0.03-0.06 of one)
DIFFERENCE_ROUNDINGS = 100.0
_FD_STEP = 1e-5
#: How the sensitivities of ν and B are computed (see the module docstring).
GRADIENTS = ('analytic', 'finite-difference')
#: One run's filter result: (ν (T, m), B (T, m, m), ∂ν (T, m, k), ∂B (T, m, m, k), cost
#: νᵀB⁻¹ν + log|B| summed over the samples); ∂ν and ∂B are None where no sensitivities were
#: asked for, which the caller knows (Any: the fits read them without a test)
RunInnovations = tuple[np.ndarray, np.ndarray, Any, Any, float]


def measurement_noise_name(channel: str) -> str:
    """Parameter name of the measurement-noise σ of an output channel."""
    return f'noise_std_{channel}'


def difference_noise_std(y: npt.ArrayLike) -> np.ndarray:
    """
    Measurement-noise σ per channel from second differences: var(Δ²v) = 6σ² for white v.

    A smooth signal sampled 30+ times per period contributes little to Δ²y, so this is a
    model-free starting value for the noise (it over-estimates slightly when the signal is fast).
    """
    y = np.asarray(y, dtype=float)
    d2 = np.diff(y, n=2, axis=0)
    return np.sqrt(np.mean(d2**2, axis=0) / 6.0)


class FilterProblem:
    """θ = [model unknowns, free initial states (per run), process σ?, measurement σ's?]."""

    def __init__(self, experiments: Sequence[Experiment], unknowns: Sequence[str],
                 guess: ParameterValues | None, known: ParameterValues | None,
                 noise_std: npt.ArrayLike | None, process_noise_std: float | None,
                 estimate_process_noise: bool, rows: Sequence[str | int] | None,
                 noise_model: str, gain: str, max_step: float,
                 gradients: str = 'analytic') -> None:
        self.base = Problem(experiments, unknowns, guess, known)
        self.gradients = gradients
        self.experiments = experiments
        model = experiments[0].model
        self.model = model
        self.m = model.n_outputs
        self.rows = kalman.default_noise_rows(model) if rows is None else \
            kalman.noise_rows(model, rows)
        if not self.rows:
            raise IdentificationError(f'model {model.name!r} has no state row for process noise; '
                                      'name the rows (e.g. rows=["beta_dot"])')
        self.noise_model = noise_model
        self.gain = gain
        self.max_step = max_step
        self.names = list(self.base.names)
        self.n_base = len(self.names)
        lo = list(self.base.lo)
        hi = list(self.base.hi)
        self.i_process = None
        if estimate_process_noise:
            self.i_process = len(self.names)
            self.names.append(PROCESS_NOISE)
            lo.append(0.0)
            hi.append(np.inf)
        self.fixed_process = None if estimate_process_noise else float(process_noise_std or 0.0)
        self.i_meas = None
        if noise_std is None:
            self.i_meas = slice(len(self.names), len(self.names) + self.m)
            self.names += [measurement_noise_name(c) for c in model.output_names]
            lo += [0.0] * self.m
            hi += [np.inf] * self.m
            self.fixed_meas = None
        else:
            self.fixed_meas = np.broadcast_to(np.asarray(noise_std, dtype=float),
                                              (self.m,)).copy()
            if np.any(self.fixed_meas <= 0):
                raise IdentificationError('measurement noise σ must be positive')
        self.lo = np.array(lo)
        self.hi = np.array(hi)
        # state-parameter columns are handled exactly (linear), the rest by differences
        k_par = len(self.base.param_index)
        self.fd_index = list(range(k_par)) + list(range(self.n_base, len(self.names)))
        #: typical size of each θ component, for finite-difference steps (set by the fit)
        self.scale: np.ndarray

    def split(self, theta: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
        """Model-and-state part, process σ, measurement σ's."""
        # the process noise is optimised as its variance q = σ² (see fit_filter_error)
        sig_p = math.sqrt(max(theta[self.i_process], 0.0)) if self.i_process is not None \
            else self.fixed_process
        sig_m = theta[self.i_meas] if self.i_meas is not None else self.fixed_meas
        # (fixed_process is a number where σ_V is not estimated)
        return (theta[:self.n_base], float(sig_p),  # type: ignore[arg-type]
                np.asarray(sig_m, dtype=float))

    def discretized(self, r: int, theta: np.ndarray
                    ) -> tuple[kalman.DiscreteModel, np.ndarray, np.ndarray]:
        """Discrete model, initial state and R of run r at θ."""
        base, sig_p, sig_m = self.split(theta)
        exp = self.experiments[r]
        p = self.base.full_parameters(base)
        x0, _ = self.base.initial_state(r, base, p)
        dm = kalman.discretize(exp.model, p, exp.inputs, exp.t, self.rows, sig_p,
                               self.noise_model, self.max_step)
        return dm, x0, np.diag(np.maximum(sig_m, 1e-300)**2)

    def gain_mode(self, dm: kalman.DiscreteModel) -> str:
        """'steady' or 'time-varying' for this discretised model."""
        if self.gain == 'auto':
            return 'steady' if dm.time_invariant else 'time-varying'
        return self.gain

    def evaluate(self, theta: np.ndarray, sensitivities: bool = True,
                 columns: Sequence[int] | None = None) -> list[RunInnovations]:
        """
        Per run: (ν (T,m), B (T,m,m), ∂ν (T,m,k) or None, ∂B (T,m,m,k) or None, cost).

        ``columns`` (positions in θ of model parameters, then of initial states): the
        sensitivities along those alone, k = len(columns).
        """
        out = []
        k = len(theta)
        for r, exp in enumerate(self.experiments):
            if self.gradients == 'analytic':
                analytic = self.analytic_sensitivities(r, theta, sensitivities, columns)
                if analytic is not None:
                    out.append(analytic)
                    continue
            # finite differences: 2k+1 filter passes
            # θ and, for the sensitivities, θ ± h_i e_i: one batched filter pass for all
            thetas = [theta]
            spans = []
            if sensitivities:
                for i in self.fd_index:
                    h = _FD_STEP * max(abs(theta[i]), self.scale[i])
                    up, down = theta.copy(), theta.copy()
                    up[i] += h
                    down[i] = max(theta[i] - h, self.lo[i])
                    thetas += [up, down]
                    spans.append(up[i] - down[i])
            parts = [self.discretized(r, th) for th in thetas]
            dms = [dm for dm, _, _ in parts]
            gain = self.gain_mode(dms[0])
            # (a run that is filtered has measurements)
            nu, B, gains, cost = filter_batch(dms, exp.y,  # type: ignore[arg-type]
                                              np.array([x0 for _, x0, _ in parts]),
                                              np.array([R for _, _, R in parts]), gain)
            if not sensitivities:
                out.append((nu[0], B[0], None, None, cost[0]))
                continue
            T = exp.t.size
            dnu = np.zeros((T, self.m, k))
            dB = np.zeros((T, self.m, self.m, k))
            for col, (i, span) in enumerate(zip(self.fd_index, spans)):
                dnu[:, :, i] = (nu[1 + 2 * col] - nu[2 + 2 * col]) / span
                dB[:, :, :, i] = (B[1 + 2 * col] - B[2 + 2 * col]) / span
            # free initial states: ν is linear in x(t0) at fixed gains (exact sensitivity)
            dm = dms[0]
            n = exp.model.n_states
            free = self.base.free_states[r]
            Psi = np.zeros((n, len(free)))
            Psi[free, np.arange(len(free))] = 1.0
            cols = self.base.state_slices[r]
            compiled = kernels.initial_state_kernel()
            if compiled is not None:
                part = np.empty((T, self.m, len(free)))
                compiled(np.ascontiguousarray(dm.Phi), gains[0],
                         np.ascontiguousarray(dm.H, dtype=float), Psi, part)
                dnu[:, :, cols] = part
            else:
                eye = np.eye(n)
                for j in range(T):
                    dnu[j, :, cols] = -dm.H[j] @ Psi
                    if j < T - 1:
                        Psi = dm.Phi[j] @ (eye - gains[0, j] @ dm.H[j]) @ Psi
            out.append((nu[0], B[0], dnu, dB, cost[0]) if columns is None else
                       (nu[0], B[0], dnu[:, :, columns], dB[..., columns], cost[0]))
        return out

    def _noise_derivatives(self, covariance, F, dF, sig_p, directions, kp, steps=None):
        """
        Return Q and its derivatives ∂Q (…, len(directions), n, n) along those of θ.

        ∂Q/∂q = Q at σ_V = 1 (θ holds q = σ_V²); ∂Q/∂p = ∂Q/∂F along ∂F/∂p.

        ``covariance(F, σ)`` is the model's Q as a function of its F (a tuple of arrays);
        ∂Q/∂F along ∂F/∂p is its forward difference with a step 1e-7 of F (Q is linear in σ²,
        so Q at σ_V is σ_V²·Q1): truncation and rounding both ~1e-7 relative, far below what
        moves a scoring step, at one evaluation of Q per parameter. ``steps``: the steps per
        parameter (:func:`_difference_steps`), by default those of F and dF given.
        ``directions`` (:func:`covariant_directions`): model parameters (the first kp), σ_V²,
        the measurement σ's (∂Q = 0).
        """
        if steps is None:
            steps = _difference_steps(F, dF, kp)
        Q1 = covariance(F, 1.0)
        dQ = np.zeros(Q1.shape[:-2] + (len(directions), Q1.shape[-1], Q1.shape[-1]))
        for slot, i in enumerate(directions):
            if i == self.i_process:
                dQ[..., slot, :, :] = Q1
            elif i < kp and sig_p > 0.0:
                up = covariance(tuple(Fx + steps[i] * dFx[..., i, :, :]
                                      for Fx, dFx in zip(F, dF)), 1.0)
                dQ[..., slot, :, :] = sig_p**2 * (up - Q1) / steps[i]
        return sig_p**2 * Q1, dQ

    def _constant_pieces(self, t, substeps, Fs, dF, step, sig_p, directions, kp):
        """Φ, ∂Φ (kp directions), Q, ∂Q (``directions``), leading dimension 1, of a constant F."""
        n = Fs.shape[-1]
        dt = float(t[1] - t[0])
        Phi_s = rk4_transition(Fs, np.array([step]))[0]
        dPhi_s = rk4_transition_derivative(Fs, dF, np.array([step]))[0] if kp \
            else np.zeros((0, n, n))                                        # (kp, n, n)
        Phi = np.eye(n)
        dPhi = np.zeros((kp, n, n))
        for _ in range(substeps):
            dPhi = dPhi_s @ Phi + Phi_s @ dPhi
            Phi = Phi_s @ Phi

        def covariance(F, sigma):
            return kalman.constant_noise_covariance(F[0], dt, substeps, self.rows, sigma,
                                                    self.noise_model)
        Q, dQ = self._noise_derivatives(covariance, (Fs[0],), (dF[0],), sig_p, directions, kp)
        return Phi[None], dPhi[None], Q[None], dQ[None]

    def _varying_pieces(self, t, substeps, Fs, dF, step, sig_p, directions, kp,
                        stage_matrices=None):
        """
        Φ_j, ∂Φ_j, Q_j, ∂Q_j (leading dimension T-1) of a model whose F varies (periodic).

        ∂Φ along the kp model parameters, ∂Q along ``directions`` (:meth:`_noise_derivatives`).

        With equal intervals each is a function of its interval's start azimuth t_j alone, of
        period 2π, smooth: where ``stage_matrices(times)`` gives F and ∂F/∂p at any times,
        they are computed for intervals starting at :data:`PHASES` azimuths of one revolution
        and summed as Fourier series at every t_j, as long as that equals the interval's own
        at checked intervals (a truncated series of an analytic function: its error falls
        geometrically with the samples); else for every interval.
        """
        windows = (_windows(Fs, substeps), _windows(dF, substeps))
        steps = _difference_steps((Fs,), (dF,), kp)      # one ∂Q step for every interval
        if stage_matrices is not None and self.noise_model == 'white':
            pieces = self._phase_series(t, substeps, windows, step, sig_p, directions, kp,
                                        steps, stage_matrices)
            if pieces is not None:
                return pieces
        return self._interval_pieces(*windows, t, substeps, step, sig_p, directions, kp, steps,
                                     Fs, dF)

    def _phase_series(self, t, substeps, windows, step, sig_p, directions, kp, steps,
                      stage_matrices):
        """:meth:`_varying_pieces` from one revolution of interval phases, or None."""
        n_intervals = t.size - 1
        check = np.array([n_intervals // 3, (2 * n_intervals) // 3])
        exact = self._interval_pieces(windows[0][check], windows[1][check], t[:3], substeps,
                                      step, sig_p, directions, kp, steps)
        for phases in PHASES:
            if n_intervals < 2 * phases:
                return None
            starts = float(t[0]) + 2.0 * np.pi * np.arange(phases) / phases
            times = (starts[:, None] + 0.5 * step * np.arange(2 * substeps + 1)).ravel()
            F, dF = stage_matrices(times)
            shape = (phases, 2 * substeps + 1)
            sampled = self._interval_pieces(F.reshape(shape + F.shape[1:]),
                                            dF.reshape(shape + dF.shape[1:]),
                                            t[:3], substeps, step, sig_p, directions, kp,
                                            steps)
            pieces = [series_at(x, float(t[0]), t[:-1]) for x in sampled]
            if all(agree(x[check], e, PHASE_AGREE) for x, e in zip(pieces[:3], exact[:3])) \
                    and _noise_derivatives_agree(pieces[3][check], exact[3], exact[2], steps,
                                                 directions, kp):
                return tuple(np.ascontiguousarray(x) for x in pieces)
        return None

    def _interval_pieces(self, F, dF, t, substeps, step, sig_p, directions, kp, steps,
                         Fs=None, dFs=None):
        """
        Φ_j, ∂Φ_j, Q_j, ∂Q_j of intervals from F (J, 2s+1, n, n), ∂F (J, 2s+1, kp, n, n).

        F at each interval's stage times (:func:`_windows`). ``'held'`` noise needs the record's
        whole stage grid ``Fs``, ``dFs`` (its Q composes the steps' responses); ``t`` gives the
        interval length; ``steps`` the difference steps of ∂Q (:meth:`_noise_derivatives`).
        """
        n_intervals, n = F.shape[0], F.shape[-1]
        h = np.full(n_intervals, step)
        Phi = np.broadcast_to(np.eye(F.shape[-1]), (n_intervals, n, n))
        dPhi = np.zeros((n_intervals, kp, n, n))
        for s in range(substeps):
            F0, Fm, F1 = F[:, 2 * s], F[:, 2 * s + 1], F[:, 2 * s + 2]
            Phi_s = rk4_step_transition(F0, Fm, F1, h)
            if kp:
                dPhi_s = rk4_step_transition_derivative(
                    F0, Fm, F1, dF[:, 2 * s], dF[:, 2 * s + 1], dF[:, 2 * s + 2], h)
                dPhi = dPhi_s @ Phi[:, None] + Phi_s[:, None] @ dPhi
            Phi = Phi_s @ Phi
        # F at the intervals' midpoints (the middle stage of each interval)
        Fmid, dFmid = np.zeros((n_intervals, n, n)), np.zeros((n_intervals, kp, n, n))
        if self.noise_model == 'white':
            Fmid, dFmid = F[:, substeps], dF[:, substeps]
            Fs, dFs = Fmid, dFmid
        times = float(t[1] - t[0]) * np.arange(n_intervals + 1)     # equal intervals

        def covariance(F, sigma):
            return kalman.varying_noise_covariance(F[0], F[1], times, substeps, self.rows,
                                                   sigma, self.noise_model)[0]
        Q, dQ = self._noise_derivatives(covariance, (Fs, Fmid), (dFs, dFmid), sig_p,
                                        directions, kp, steps)
        return np.ascontiguousarray(Phi), dPhi, Q, np.ascontiguousarray(dQ)

    def analytic_sensitivities(self, r: int, theta: np.ndarray, sensitivities: bool = True,
                               columns: Sequence[int] | None = None) -> RunInnovations | None:
        """
        Return (ν, B, ∂ν, ∂B, cost) of run r from the filter's analytic sensitivities.

        ``columns``: along those of θ's model parameters and initial states alone (see
        :meth:`evaluate`).

        For equal sample intervals, with F constant (one Φ, Q; H may rotate, as the wake
        model's eq.-30 measurement does) or varying (periodic models: Φ_j, Q_j per interval);
        None for uneven time stamps (finite differences then). Without ``sensitivities``, ∂ν
        and ∂B are None and only the filter runs. The module docstring has the equations. Φ and
        Q are those of :func:`~rotor_id.estimation.kalman.discretize` (the same RK4 steps
        composed, :func:`~rotor_id.estimation.kalman.constant_noise_covariance` or
        :func:`~rotor_id.estimation.kalman.varying_noise_covariance`); the state is carried
        through the RK4 steps themselves, so the per-interval forcing c_j is never formed.
        """
        exp = self.experiments[r]
        model = exp.model
        base, sig_p, sig_m = self.split(theta)
        p = self.base.full_parameters(base)
        t = exp.t
        substeps = substeps_for(t, self.max_step)
        if not equal_steps(np.diff(t) / substeps, t):
            return None                 # time-stamp jitter or lost samples: uneven steps
        tf = fine_grid(t, substeps)
        u = exp.inputs(tf)
        F_of, g = system_on_record(model, 'system', tf, p, u)
        F = values_on(F_of, tf)                              # F of length 1 where constant
        h = np.repeat(np.diff(t) / substeps, substeps)
        constant = time_invariant_steps(F, h, t)
        n, m, T = model.n_states, self.m, t.size
        n_par = len(self.base.param_index)
        index = list(self.base.param_index) if columns is None else \
            [self.base.param_index[c] for c in columns if c < n_par]
        i_process, i_meas = (self.i_process, self.i_meas) if columns is None else (None, None)
        k = (len(theta) if columns is None else len(columns)) if sensitivities else 0
        kp = len(index) if sensitivities else 0
        if kp:
            dF_of, dg = system_on_record(model, 'system_jacobian', tf, p, u, index)
            dF = np.ascontiguousarray(values_on(dF_of, tf)[:1 if constant else None])
            dg = np.ascontiguousarray(dg)                                  # (2M+1, kp, n)
        else:
            dF = np.zeros((1 if constant else F.shape[0], 0, n, n))
            dg = np.zeros((g.shape[0], 0, n))
        Fs = np.ascontiguousarray(F[:1] if constant else F)
        directions = covariant_directions(dF, k, i_process, i_meas)
        if constant:
            pieces = self._constant_pieces(t, substeps, Fs, dF, h[0], sig_p, directions, kp)
        else:
            def stage_matrices(times):
                # from the record's series where they hold (the model itself otherwise)
                zero = np.zeros((times.size, u.shape[1]))
                F_at = full_along_time(F_of.values(times) if isinstance(F_of, Series) else
                                       on_record(model, 'system', times, p, zero)[0],
                                       times.size)
                if not kp:
                    return F_at, np.zeros((times.size, 0, n, n))
                dF_at = dF_of.values(times) if isinstance(dF_of, Series) else \
                    on_record(model, 'system_jacobian', times, p, zero, index)[0]
                return F_at, full_along_time(dF_at, times.size)
            pieces = self._varying_pieces(t, substeps, Fs, dF, h[0], sig_p, directions, kp,
                                          stage_matrices)
        Phi, dPhi, Q, dQ = pieces
        R = np.diag(np.maximum(sig_m, 1e-300)**2)
        dR = np.zeros((k, m, m))
        if k and i_meas is not None:
            for a, i in enumerate(range(i_meas.start, i_meas.stop)):
                dR[i, a, a] = 2.0 * sig_m[a]
        H = np.ascontiguousarray(model.output_matrix(t), dtype=float)
        d = np.ascontiguousarray(model.output_offset(t, p), dtype=float)
        # (no forcing c: the state is carried through the RK4 steps, not by Φ x + c)
        dm = kalman.DiscreteModel(t=t, Phi=np.broadcast_to(Phi, (T - 1, n, n)),
                                  c=None,  # type: ignore[arg-type]
                                  Q=np.broadcast_to(Q, (T - 1, n, n)), H=H, d=d)
        steady = self.gain_mode(dm) == 'steady' and constant
        if steady:
            _, B_ss, K_ss, dB_ss, dK_ss = steady_gain_sensitivities(
                Phi[0], Q[0], H[0], R, *along_every_direction(dPhi[0], dQ[0], directions, k),
                dR)
        else:
            B_ss, K_ss = np.zeros((m, m)), np.zeros((n, m))
            dB_ss, dK_ss = np.zeros((k, m, m)), np.zeros((k, n, m))
        dd = np.zeros((T, m, k))
        if kp:
            dd[:, :, :kp] = model.output_offset_jacobian(t, p)[:, :, index]
        x0, jac = self.base.initial_state(r, base, p)
        dx0 = np.zeros((n, k))
        if k and columns is not None:
            mine = self.base.state_slices[r]
            for j, c in enumerate(columns):     # (another run's initial state: zero)
                if c < n_par or mine.start <= c < mine.stop:
                    dx0[:, j] = jac[:, c if c < n_par else n_par + c - mine.start]
        elif k:
            dx0[:, :n_par] = jac[:, :n_par]
            dx0[:, self.base.state_slices[r]] = jac[:, n_par:]
        nu, dnu = np.empty((T, m)), np.empty((T, m, k))
        B, dB = np.empty((T, m, m)), np.empty((T, m, m, k))
        args = (Fs, np.ascontiguousarray(g), dF, dg, float(h[0]), substeps, Phi, dPhi,
                np.ascontiguousarray(Q), dQ, R, dR, directions, H, d, dd,
                np.ascontiguousarray(exp.y, dtype=float), np.asarray(x0, dtype=float), dx0,
                steady, B_ss, np.ascontiguousarray(K_ss), dB_ss, np.ascontiguousarray(dK_ss),
                nu, dnu, B, dB)
        compiled = kernels.filter_sensitivity_kernel()
        if compiled is not None:
            cost = compiled(*args)
        else:
            clock = time.process_time()
            cost = sensitivity_scan_numpy(*args)
            kernels.note_numpy_seconds(time.process_time() - clock)
        if not sensitivities:
            return nu, B, None, None, float(cost)
        return nu, B, dnu, dB, float(cost)


def covariant_directions(dF: np.ndarray, k: int, i_process: int | None,
                         i_meas: slice | None) -> np.ndarray:
    """
    Return the k directions of θ along which the filter's covariance P moves (int64).

    The model parameters that move F (dF (…, kp, n, n): they move Φ and Q), σ_V² (Q) and the
    measurement σ's (R). From P(t0) = 0, ∂P stays zero along every other direction (an initial
    state, a forcing or output-offset parameter), and so do ∂B and ∂K: only ∂x carries it.
    """
    if not k:
        return np.zeros(0, dtype=np.int64)
    moves = np.zeros(k, dtype=bool)
    moves[:dF.shape[-3]] = np.any(dF != 0.0, axis=tuple(range(dF.ndim - 3)) + (-2, -1))
    if i_process is not None:
        moves[i_process] = True
    if i_meas is not None:
        moves[i_meas] = True
    return np.flatnonzero(moves).astype(np.int64)


def along_every_direction(dPhi: np.ndarray, dQ: np.ndarray, directions: np.ndarray, k: int
                          ) -> tuple[np.ndarray, np.ndarray]:
    """
    Return ∂Φ and ∂Q along all k directions of θ (…, k, n, n), zero beyond those given.

    ``dPhi`` (…, kp, n, n) along the first kp, ``dQ`` (…, len(directions), n, n) along
    ``directions``, as the filter's pieces carry them.
    """
    lead, n = dPhi.shape[:-3], dPhi.shape[-1]
    full_Phi, full_Q = np.zeros(lead + (k, n, n)), np.zeros(lead + (k, n, n))
    full_Phi[..., :dPhi.shape[-3], :, :] = dPhi
    full_Q[..., directions, :, :] = dQ
    return full_Phi, full_Q


def steady_gain_sensitivities(Phi: np.ndarray, Q: np.ndarray, H: np.ndarray, R: np.ndarray,
                              dPhi: np.ndarray, dQ: np.ndarray, dR: np.ndarray
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                         np.ndarray]:
    """
    Steady-state filter (P, B, K) and the derivatives ∂B, ∂K along k directions.

    P solves the discrete algebraic Riccati equation P = Φ (I − KH) P Φᵀ + Q with
    B = H P Hᵀ + R and K = P Hᵀ B⁻¹ (eqs 31-32 at their fixed point). Differentiating it gives
    a discrete Lyapunov (Stein) equation for each direction,

        ∂P = Ā ∂P Āᵀ + ∂Φ M Φᵀ + Φ M ∂Φᵀ + Φ K ∂R Kᵀ Φᵀ + ∂Q,   Ā = Φ (I − KH), M = (I − KH) P

    solved for all directions at once through (I − Ā⊗Ā) vec ∂P = vec W; then
    ∂B = H ∂P Hᵀ + ∂R and ∂K = (∂P Hᵀ − K ∂B) B⁻¹. dPhi, dQ (k, n, n), dR (k, m, m).
    Returns P (n, n), B (m, m), K (n, m), dB (k, m, m), dK (k, n, m).
    """
    n = Phi.shape[0]
    k = dPhi.shape[0]
    P = kalman.steady_state_covariance(
        # (the steady state needs Φ, Q and H only)
        kalman.DiscreteModel(t=None, Phi=Phi[None], c=None,  # type: ignore[arg-type]
                             Q=Q[None], H=H[None], d=None), R)  # type: ignore[arg-type]
    B = H @ P @ H.T + R
    B = 0.5 * (B + B.T)
    Binv = np.linalg.inv(B)
    K = P @ H.T @ Binv
    IKH = np.eye(n) - K @ H
    A = Phi @ IKH
    M = IKH @ P
    PhiK = Phi @ K
    W = (dPhi @ M @ Phi.T + Phi @ M @ np.swapaxes(dPhi, -1, -2) + PhiK @ dR @ PhiK.T + dQ)
    system = np.eye(n * n) - np.kron(A, A)
    dP = np.linalg.solve(system, W.reshape(k, n * n).T).T.reshape(k, n, n)
    dP = 0.5 * (dP + np.swapaxes(dP, -1, -2))
    dB = H @ dP @ H.T + dR
    dK = (dP @ H.T - K @ dB) @ Binv
    return P, B, K, dB, dK


def sensitivity_scan_numpy(Fs: np.ndarray, g: np.ndarray, dFs: np.ndarray, dg: np.ndarray,
                           h: float, substeps: int, Phis: np.ndarray, dPhis: np.ndarray,
                           Qs: np.ndarray, dQs: np.ndarray, R: np.ndarray, dR: np.ndarray,
                           covariant: np.ndarray, H: np.ndarray, d: np.ndarray,
                           dd: np.ndarray, y: np.ndarray, x0: np.ndarray, dx0: np.ndarray,
                           steady: bool, B_ss: np.ndarray,
                           K_ss: np.ndarray, dB_ss: np.ndarray, dK_ss: np.ndarray,
                           nu: np.ndarray, dnu: np.ndarray, B: np.ndarray,
                           dB: np.ndarray) -> float:
    """
    Numpy twin of ``_filter_kernels_numba.sensitivity_scan`` (same arguments and result).

    It propagates ∂P along every direction, ``covariant`` or not: the others stay exact zeros.
    """
    dPhis, dQs = along_every_direction(dPhis, dQs, covariant, dx0.shape[1])
    T = y.shape[0]
    n, kp = Fs.shape[1], dFs.shape[1]
    varying, per_interval = Fs.shape[0] > 1, Phis.shape[0] > 1
    x = x0.copy()
    S = dx0.copy()
    P = np.zeros((n, n))
    dP = np.zeros((dx0.shape[1], n, n))
    half = 0.5 * h
    total = 0.0
    for t in range(T):
        Ht = H[t]
        if steady:
            Bj, Kj, dBj, dKj = B_ss, K_ss, dB_ss, dK_ss
            Binv = np.linalg.inv(Bj)
        else:
            PHT = P @ Ht.T
            Bj = Ht @ PHT + R
            Bj = 0.5 * (Bj + Bj.T)
            Binv = np.linalg.inv(Bj)
            Kj = PHT @ Binv
            dPHT = dP @ Ht.T
            dBj = Ht @ dPHT + dR
            dKj = (dPHT - Kj @ dBj) @ Binv
        B[t] = Bj
        dB[t] = np.moveaxis(dBj, 0, -1)
        v = y[t] - d[t] - Ht @ x
        dv = -dd[t] - Ht @ S
        nu[t] = v
        dnu[t] = dv
        total += float(v @ Binv @ v) + np.linalg.slogdet(Bj)[1]
        x = x + Kj @ v
        S = S + Kj @ dv + np.einsum('cia,a->ic', dKj, v)
        if t == T - 1:
            break
        iv = t if per_interval else 0
        Phi, dPhi, Q, dQ = Phis[iv], dPhis[iv], Qs[iv], dQs[iv]
        if not steady:
            KB = Kj @ Bj
            dP = (dP - dKj @ KB.T - np.swapaxes(dKj @ KB.T, -1, -2)
                  - Kj @ dBj @ Kj.T)
            P = P - KB @ Kj.T
            W = P @ Phi.T
            dPn = dQ + 2.0 * dPhi @ W + Phi @ (dP @ Phi.T)     # symmetric part: see the kernel
            dP = 0.5 * (dPn + np.swapaxes(dPn, -1, -2))
            Pn = Q + Phi @ W
            P = 0.5 * (Pn + Pn.T)
        for s in range(substeps):
            st = 2 * (t * substeps + s)
            F0, Fm, F1 = (Fs[st], Fs[st + 1], Fs[st + 2]) if varying else (Fs[0],) * 3
            dF0, dFm, dF1 = (dFs[st], dFs[st + 1], dFs[st + 2]) if varying else (dFs[0],) * 3
            k1 = F0 @ x + g[st]
            x2 = x + half * k1
            k2 = Fm @ x2 + g[st + 1]
            x3 = x + half * k2
            k3 = Fm @ x3 + g[st + 1]
            x4 = x + h * k3
            k4 = F1 @ x4 + g[st + 2]
            s1 = F0 @ S
            s1[:, :kp] += (dF0 @ x).T + dg[st].T
            s2 = Fm @ (S + half * s1)
            s2[:, :kp] += (dFm @ x2).T + dg[st + 1].T
            s3 = Fm @ (S + half * s2)
            s3[:, :kp] += (dFm @ x3).T + dg[st + 1].T
            s4 = F1 @ (S + h * s3)
            s4[:, :kp] += (dF1 @ x4).T + dg[st + 2].T
            x = x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            S = S + h / 6.0 * (s1 + 2.0 * s2 + 2.0 * s3 + s4)
    return total


def filter_batch(dms: Sequence[kalman.DiscreteModel], y: np.ndarray, x0: np.ndarray,
                 R: np.ndarray, gain: str = 'time-varying', P0: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """
    Run the Kalman filter of :func:`~rotor_id.estimation.kalman.kalman_filter` on K models.

    Same equations (P(t0) = ``P0``, zero by default), vectorised over a stack of K
    discretised models so the finite-difference sensitivities cost one pass. Only the
    innovations, their covariances, the gains and the eq.-26 cost are kept.

    Parameters
    ----------
    dms : list of DiscreteModel, length K
        Discretised models (the nominal one first).
    y : ndarray, shape (T, m)
        Measurements in the model's output channels.
    x0 : ndarray, shape (K, n)
        Initial states, one per model.
    R : ndarray, shape (K, m, m)
        Measurement covariances, one per model.
    gain : {'time-varying', 'steady'}
        Time-varying or steady-state gain.
    P0 : ndarray, shape (K, n, n), optional
        Covariance of each x0 (time-varying gain only).

    Returns
    -------
    nu : ndarray, shape (K, T, m)
    B : ndarray, shape (K, T, m, m)
    gains : ndarray, shape (K, T, n, m)
    cost : ndarray, shape (K,)
        Σ_j [ν_jᵀ B_j⁻¹ ν_j + log|B_j|] of each model.

    """
    Phi = np.stack([dm.Phi for dm in dms], axis=1)          # (T-1, K, n, n)
    c = np.stack([dm.c for dm in dms], axis=1)              # (T-1, K, n)
    Q = np.stack([dm.Q for dm in dms], axis=1)
    H = np.stack([dm.H for dm in dms], axis=1)              # (T, K, m, n)
    d = np.stack([dm.d for dm in dms], axis=1)
    K_, T, m = len(dms), y.shape[0], y.shape[1]
    n = Phi.shape[-1]
    nu = np.empty((K_, T, m))
    B = np.empty((K_, T, m, m))
    gains = np.empty((K_, T, n, m))
    cost = np.zeros(K_)
    x = np.array(x0, dtype=float)
    P = np.zeros((K_, n, n)) if P0 is None else np.array(P0, dtype=float)
    if gain == 'steady':
        P_ss = np.stack([kalman.steady_state_covariance(dm, R[i]) for i, dm in enumerate(dms)])
    compiled = kernels.filter_kernel()
    if compiled is not None:
        compiled(Phi, c, Q, H, d, y, x, R, P_ss if gain == 'steady' else P,
                 gain == 'steady', nu, B, gains, cost, np.empty((K_, n)), np.empty((K_, n, n)))
        return nu, B, gains, cost
    clock = time.process_time()
    for j in range(T):
        Hj = H[j]
        if gain == 'steady':
            P = P_ss
        HT = np.swapaxes(Hj, -1, -2)
        # innovation, its covariance (eq. 32) and the gain (eq. 31)
        nu[:, j] = y[j] - np.einsum('kmn,kn->km', Hj, x) - d[j]
        PHT = P @ HT
        Bj = Hj @ PHT + R
        Bj = 0.5 * (Bj + np.swapaxes(Bj, -1, -2))
        Binv = np.linalg.inv(Bj)
        Kj = PHT @ Binv
        B[:, j], gains[:, j] = Bj, Kj
        cost += np.einsum('km,kmn,kn->k', nu[:, j], Binv, nu[:, j]) + np.linalg.slogdet(Bj)[1]
        # update (eqs 29-30) and predict (eqs 27-28)
        x = x + np.einsum('knm,km->kn', Kj, nu[:, j])
        if gain != 'steady':
            P = P - Kj @ Bj @ np.swapaxes(Kj, -1, -2)
        if j < T - 1:
            x = np.einsum('kab,kb->ka', Phi[j], x) + c[j]
            if gain != 'steady':
                P = Phi[j] @ P @ np.swapaxes(Phi[j], -1, -2) + Q[j]
                P = 0.5 * (P + np.swapaxes(P, -1, -2))
    kernels.note_numpy_seconds(time.process_time() - clock)
    return nu, B, gains, cost


def _reported(prob, theta):
    """θ with the process-noise variance replaced by its σ."""
    out = theta.copy()
    if prob.i_process is not None:
        out[prob.i_process] = math.sqrt(max(theta[prob.i_process], 0.0))
    return out


def innovations_cost(results: Sequence[RunInnovations]) -> float:
    """½ Σ (νᵀB⁻¹ν + log|B|) over all runs (eq. 26 halved)."""
    return 0.5 * float(sum(r[4] for r in results))


def gradient_information(results: Sequence[RunInnovations], k: int
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Gradient of J and the expected (Fisher) information over all runs."""
    g = np.zeros(k)
    M = np.zeros((k, k))
    for nu, B, dnu, dB, _ in results:
        T, m = nu.shape
        Binv = np.linalg.inv(B)
        a = np.einsum('tab,tb->ta', Binv, nu)                       # B⁻¹ν
        g += np.einsum('ta,tak->k', a, dnu)
        g -= 0.5 * np.einsum('ta,tabk,tb->k', a, dB, a)
        BdB = np.einsum('tab,tbck->tack', Binv, dB)                  # B⁻¹∂B
        g += 0.5 * np.einsum('taak->k', BdB)
        # Σ ∂νᵀB⁻¹∂ν and ½ Σ tr(B⁻¹∂B_i B⁻¹∂B_k) as matrix products over (t, a, b)
        M += dnu.reshape(T * m, k).T @ (Binv @ dnu).reshape(T * m, k)
        M += 0.5 * BdB.reshape(T * m * m, k).T @ \
            np.swapaxes(BdB, 1, 2).reshape(T * m * m, k)
    return g, 0.5 * (M + M.T)


def fit_filter_error_ml(experiments: Sequence[Experiment], unknowns: Sequence[str],
                        guess: ParameterValues | None = None,
                        known: ParameterValues | None = None,
                        noise_std: npt.ArrayLike | None = None, progress: Progress | None = None,
                        max_iter: int = 50, process_noise_std: float | None = None,
                        estimate_process_noise: bool = True,
                        rows: Sequence[str | int] | None = None, noise_model: str = 'white',
                        gain: str = 'auto', step_tol: float = 1e-3,
                        max_step: float = DEFAULT_MAX_STEP, label: str = 'filter-error ML',
                        gradients: str = 'analytic', start_values: ParameterValues | None = None,
                        loglik_tol: float | None = None) -> Estimate:
    """
    Filter-error maximum likelihood over one or more runs; Cramér-Rao bound at the optimum.

    This is the plain estimator: every unknown, the process-noise σ included, at the joint
    maximum of the likelihood, and the bound conditional on that point.
    :func:`fit_filter_error` (the default entry point) builds on it.

    Parameters
    ----------
    experiments : list of Experiment
        Runs sharing the model parameters.
    unknowns : list of str
        Model parameters to identify (initial states follow each run's ``initial_state``).
    guess, known : dict, optional
        Starting values / fixed values of model parameters (default: nominal).
    noise_std : float or array_like, optional
        Measurement-noise σ per channel; estimated (``noise_std_<channel>``) when None.
    progress : callable, optional
        ``progress(info)`` after every iteration (iteration, cost, names, values, elapsed, label);
        if it returns :data:`~rotor_id.estimation.output_error.STOP`, the fit ends there.
    max_iter : int
        Most iterations.
    process_noise_std : float, optional
        Start (or, with ``estimate_process_noise=False``, the fixed value) of the σ of the
        held process-noise sequence on ``rows``. Default start: the best of a coarse grid.
    estimate_process_noise : bool
        Identify the process-noise σ (else hold ``process_noise_std``).
    rows : sequence of str or int, optional
        Process-noise rows (default :func:`~rotor_id.estimation.kalman.default_noise_rows`).
    noise_model : {'white', 'held'}
        See :mod:`rotor_id.estimation.kalman`; with 'white' σ² is the intensity per unit
        nondimensional time.
    gain : {'auto', 'time-varying', 'steady'}
        Time-varying or steady-state gain.
    step_tol : float
        Converged when every step is below ``step_tol`` times its Cramér-Rao σ (0.1 %: the
        likelihood can be flat along σ_V, where scoring creeps; smaller steps are noise).
    max_step : float
        Longest RK4 step of the discretisation.
    label : str
        Name shown by progress reports.
    gradients : {'analytic', 'finite-difference'}
        Sensitivities of ν and B: analytic for equally spaced samples (finite differences
        for uneven time stamps), or finite differences throughout (the reference).
    start_values : dict, optional
        Starting values by θ name (any of model unknowns, free initial states, measurement
        σ's), over the defaults; :func:`fit_filter_error`'s σ_V profile warm-starts with it.
    loglik_tol : float, optional
        Also converged when the Newton decrement ½ gᵀM⁻¹g (the log-likelihood a full scoring
        step would still gain by the quadratic model, over the parameters free to move) is
        below it. Scoring can zigzag about the optimum along a direction where the expected
        information misjudges the curvature: the cost flat to 0.01 while the steps stay above
        ``step_tol`` σ's for tens of iterations (random inflow on the wake record). With it, a
        step that reverses the previous one (cosine < −½ in the coordinates scaled by
        √diag M) is replaced by the midpoint of the two iterates when that is as likely.

    Returns
    -------
    Estimate
        ``method='filter-error'``; names include ``process_noise_std``.

    """
    if gradients not in GRADIENTS:
        raise IdentificationError(f"gradients must be one of {', '.join(GRADIENTS)}, "
                                  f'not {gradients!r}')
    if gain not in ('auto', 'time-varying', 'steady'):
        raise IdentificationError(f"gain must be 'auto', 'time-varying' or 'steady', not {gain!r}")
    for exp in experiments:
        if exp.y is None or exp.y.shape != (exp.t.size, exp.model.n_outputs):
            raise IdentificationError(
                f'run {exp.name!r}: filter error needs measurements of shape '
                f'({exp.t.size}, {exp.model.n_outputs}) = samples x '
                f'({", ".join(exp.model.output_names)})')
        if not np.all(np.isfinite(exp.y)):
            raise IdentificationError(f'run {exp.name!r}: measurements contain NaN or inf; '
                                      'drop those samples before identifying')
    if process_noise_std is not None and process_noise_std < 0:
        raise IdentificationError('process_noise_std must be ≥ 0')
    prob = FilterProblem(experiments, unknowns, guess, known, noise_std, process_noise_std,
                         estimate_process_noise, rows, noise_model, gain, max_step,
                         gradients)
    names = prob.names
    k = len(names)
    base = prob.base
    theta = np.zeros(k)
    theta[:len(base.param_index)] = base.p_base[base.param_index]
    theta[:prob.n_base] = fit_initial_states(base, theta[:prob.n_base].copy(), max_step)
    y_all = np.concatenate([exp.y for exp in experiments])
    meas0 = np.maximum(difference_noise_std(y_all), 1e-6 * max(1e-300, np.abs(y_all).max()))
    if prob.i_meas is not None:
        theta[prob.i_meas] = meas0
    meas_scale = prob.fixed_meas if prob.fixed_meas is not None else meas0
    prob.scale = np.concatenate([np.maximum(np.abs(theta[:prob.n_base]), 1e-3 * float(
        np.abs(y_all).max())), np.full(k - prob.n_base, float(np.mean(meas_scale)))])
    if prob.i_process is not None:
        prob.scale[prob.i_process] = float(np.mean(meas_scale))**2
        if process_noise_std is not None:
            theta[prob.i_process] = process_noise_std**2
        else:
            best = math.inf
            for factor in (0.0, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0):
                trial = theta.copy()
                trial[prob.i_process] = (factor * float(np.mean(meas_scale)))**2
                c = innovations_cost(prob.evaluate(trial, sensitivities=False))
                if c < best:
                    best, theta = c, trial
    for name, value in (start_values or {}).items():
        theta[names.index(name)] = value
    t_start = time.perf_counter()
    history = []
    results = prob.evaluate(theta)
    cost = innovations_cost(results)
    if not math.isfinite(cost):
        raise IdentificationError('the filter likelihood at the starting values is not finite; '
                                  'check the starting values and the run description')
    converged = False
    message = 'maximum iterations reached'
    lm = 0.0

    def trial_cost(trial):
        # a trial is costed by the filter alone, its sensitivities taken once it is accepted:
        # with k directions they cost several filter passes, and a step may halve many times
        return innovations_cost(prob.evaluate(trial, sensitivities=False)), None
    iteration = 0
    previous = None
    for iteration in range(1, max_iter + 1):
        grad, M = gradient_information(results, k)
        # active set: a parameter on a bound that the gradient pushes outwards stays there
        free = ~(((theta <= prob.lo) & (grad > 0)) | ((theta >= prob.hi) & (grad < 0)))
        if loglik_tol is not None and _newton_decrement(grad, M, free) < loglik_tol:
            converged = True
            message = 'converged (the likelihood a further step would gain is below tolerance)'
            iteration -= 1
            break
        accepted, trial, trial_value, _, lm = damped_gauss_newton_step(
            theta, grad, M, prob.lo, prob.hi, cost, trial_cost, lm,
            free=np.flatnonzero(free), attempts=10, halvings=8)
        if not accepted:
            message = 'no step lowers the likelihood any more (a minimum or a bound)'
            converged = True
            break
        applied = trial - theta
        if loglik_tol is not None and _reverses(applied, previous, M):
            # a zigzag across the optimum: the midpoint of the two iterates, if as likely
            mid = theta + 0.5 * applied
            mid_cost, _ = trial_cost(mid)
            if math.isfinite(mid_cost) and mid_cost <= trial_value:
                trial, applied = mid, 0.5 * applied
        previous = applied
        theta = trial
        results = prob.evaluate(theta)
        cost = innovations_cost(results)
        sigma = np.sqrt(np.clip(np.diag(np.linalg.pinv(M)), 0.0, None))
        rms = math.sqrt(np.mean(np.concatenate([r[0] for r in results])**2))
        info = {'iteration': iteration, 'cost': float(cost), 'rms': rms, 'names': names,
                'values': _reported(prob, theta), 'elapsed': time.perf_counter() - t_start,
                'label': label}
        history.append(info)
        if progress is not None and progress(info) is STOP:
            message = 'stopped by the caller'
            break
        if np.all(np.abs(applied) <= np.maximum(step_tol * sigma, 1e-12 * np.abs(theta))):
            converged = True
            message = 'converged'
            break
    grad, M = gradient_information(results, k)
    warnings = []
    # Cramér-Rao bound in the optimised coordinates (q = σ² for the process noise)

    def bound(M):
        d = np.sqrt(np.clip(np.diag(M), 1e-300, None))
        return np.linalg.pinv(M / np.outer(d, d), rcond=1e-13) / np.outer(d, d)
    cov = bound(M)
    # report σ and its bound: σ_σ = σ_q / (2σ). At σ = 0 (an active bound) the delta method
    # fails: the other parameters get the bound with σ held at zero, as for any parameter on
    # a bound, and σ's entry is √σ_q, the smallest resolvable σ (a detection limit)
    if prob.i_process is not None:
        i = prob.i_process
        sigma_hat = math.sqrt(max(theta[i], 0.0))
        if sigma_hat > 1e-6 * math.sqrt(cov[i, i]):
            cov[i, :] /= 2.0 * sigma_hat
            cov[:, i] /= 2.0 * sigma_hat
        else:
            detect = math.sqrt(math.sqrt(cov[i, i]))
            rest = [j for j in range(k) if j != i]
            cov = np.zeros((k, k))
            cov[np.ix_(rest, rest)] = bound(M[np.ix_(rest, rest)])
            cov[i, i] = detect**2
            warnings.append(f'process noise estimated at zero: the data show no system noise; '
                            f'its std {detect:.3g} is the detection limit √(CRB of σ²), not a '
                            'Cramér-Rao σ; the other bounds hold it at zero')
        jac = np.ones(k)
        jac[i] = 2.0 * sigma_hat
        M = M * np.outer(jac, jac)
    kept = [i for i in range(k) if M[i, i] > 0]          # σ at zero carries no information
    if kept:
        dep, _ = dependence_warnings([names[i] for i in kept], M[np.ix_(kept, kept)])
        warnings += dep
    if not converged:
        warnings.append(message)
    base_theta, sig_p, sig_m = prob.split(theta)
    # the innovations of the last evaluation, at θ: those of the likelihood reported
    residuals = [run[0] for run in results]
    theta = _reported(prob, theta)
    p_final = base.full_parameters(base_theta)
    n_total = sum(exp.t.size for exp in experiments)
    nll = cost + 0.5 * n_total * prob.m * math.log(2.0 * math.pi)
    return Estimate(
        names=names, values=theta, covariance=cov, information=M, noise_std=sig_m,
        channel_names=list(prob.model.output_names), cost=float(cost),
        neg_log_likelihood=float(nll), iterations=iteration, converged=converged,
        message=message, n_samples=n_total, history=history,
        residuals=residuals,
        fitted=[exp.y - nu for exp, nu in zip(experiments, residuals)],
        initial_states=[base.initial_state(r, base_theta, p_final)[0]
                        for r in range(len(experiments))],
        warnings=warnings, model_parameters=dict(zip(prob.model.parameter_names, p_final)),
        method='filter-error')


def _newton_decrement(grad, M, free):
    """½ gᵀM⁻¹g over the ``free`` parameters: the cost a full scoring step would still lower."""
    g, Mf = grad[free], M[np.ix_(free, free)]
    d = np.sqrt(np.clip(np.diag(Mf), 1e-300, None))
    gs = g / d
    return 0.5 * float(gs @ np.linalg.pinv(Mf / np.outer(d, d), rcond=1e-13) @ gs)


def _reverses(step, previous, M):
    """Whether ``step`` turns back on ``previous`` (cosine < −½, scaled by √diag M)."""
    if previous is None:
        return False
    d = np.sqrt(np.clip(np.diag(M), 0.0, None))
    a, b = step * d, previous * d
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    return na > 0.0 and nb > 0.0 and float(a @ b) < -0.5 * na * nb


#: Restricted-likelihood rise over its minimum beyond which σ_V carries no weight (e⁻⁸ < 4e-4).
_PROFILE_SPAN = 8.0
#: Grid points from 0 to σ̂_V + 4σ, and the fewest where the weight is (σ_V profile). Six
#: and six gave bounds up to 1.4 % narrower at σ_V = .2-.3 (30 seeds of
#: bench/compare_process_noise.py) for 0.1 s less on the 1065-sample record: kept at 9 and 8.
_PROFILE_POINTS = 9
_PROFILE_LOW_POINTS = 8
#: Convergence of each profile fit: steps below 1 % of its σ's (the joint fit keeps
#: ``step_tol``). Same coverage table to the printed digits as 0.1 % on 30 seeds × 5 σ_V, and
#: the whole-record bounds move by < 1e-5 relative; a third fewer profile iterations.
_PROFILE_STEP_TOL = 1e-2


def _restricted_cost(est):
    """
    Restricted cost of a fixed-σ_V fit: J + ½ log|M_θθ| (Cox-Reid adjusted profile likelihood).

    M_θθ is the information of the structural unknowns (model parameters and free initial
    states, not the noise σ's). For a model linear in them this is exactly the restricted
    (REML) likelihood of the noise intensity; the adjustment removes the downward bias a
    variance gets when the parameters that absorb part of the noise are fitted with it.
    """
    mean = [i for i, n in enumerate(est.names) if not n.startswith('noise_std_')]
    sign, logdet = np.linalg.slogdet(est.information[np.ix_(mean, mean)])
    return est.cost + 0.5 * logdet if sign > 0 else math.inf


def _trapezoid_weights(sigma, f):
    """Weights ∝ exp(−(f − min f)) dσ on a nonuniform grid (trapezoid rule)."""
    width = np.gradient(sigma) if sigma.size > 1 else np.ones(1)
    width[0] = (sigma[1] - sigma[0]) / 2 if sigma.size > 1 else 1.0
    width[-1] = (sigma[-1] - sigma[-2]) / 2 if sigma.size > 1 else 1.0
    w = np.exp(-(f - np.min(f))) * width
    return w / w.sum()


def fit_filter_error(experiments: Sequence[Experiment], unknowns: Sequence[str],
                     guess: ParameterValues | None = None, known: ParameterValues | None = None,
                     noise_std: npt.ArrayLike | None = None, progress: Progress | None = None,
                     max_iter: int = 50, process_noise_std: float | None = None,
                     estimate_process_noise: bool = True, rows: Sequence[str | int] | None = None,
                     noise_model: str = 'white', gain: str = 'auto', step_tol: float = 1e-3,
                     max_step: float = DEFAULT_MAX_STEP, label: str = 'filter-error ML',
                     bounds: str = 'marginal', gradients: str = 'analytic') -> Estimate:
    """
    Filter-error identification with bounds that include the uncertainty of the process noise.

    The process-noise σ_V of a short record is often barely determined: with the report's
    measurement noise (σ = .05) and σ_V = .1, about a third of 121-sample records put the joint
    maximum-likelihood σ_V at zero, and a Cramér-Rao bound taken there (filter error =
    output error) is too small for the parameters, whose scatter grows with σ_V (measured
    coverage .87/.78/.75 for 95 %). So, with ``bounds='marginal'`` (the default):

    1. the joint ML fit (:func:`fit_filter_error_ml`) is the estimate (every value, σ_V
       included, so that without process noise filter error is output error);
    2. σ_V is profiled on a grid: at each σ_V the other unknowns are fitted by ML (started
       from the neighbouring fits, converged to 1 % of a σ), and the restricted cost
       f(σ_V) = J + ½ log|M_θθ| (:func:`_restricted_cost`) is recorded;
       the grid runs from 0 until f has risen by 8 and is refined where f is low;
    3. the covariance is the mixture over the grid about the estimate θ̂, with weights
       w_i ∝ exp(−f_i) dσ_V (the restricted likelihood with a flat prior on σ_V):
       Σ_i w_i [C_i + (θ_i − θ̂)(θ_i − θ̂)ᵀ], C_i the Cramér-Rao bound at σ_V,i; σ_V's own
       variance is Σ_i w_i (σ_V,i − σ̂_V)². The measurement σ's keep their Cramér-Rao bound.

    Where the data fix σ_V the mixture is the Cramér-Rao bound at σ̂_V. Where they do not, the
    bounds widen to cover every σ_V the record allows; that includes records without process
    noise, where they are wider than output error's: the record cannot tell them from records
    with some (``bounds='conditional'`` gives the plain estimator's bound at the joint
    optimum). Measured in bench/compare_process_noise.py: at the report's measurement σ .05
    and σ_V .1, coverage .94/.94/.94 (conditional: .87/.78/.75); at σ_V = 0 the bounds are
    1.5-1.9 times output error's.

    Parameters are those of :func:`fit_filter_error_ml`, plus

    bounds : {'marginal', 'conditional'}
        See above. Without ``estimate_process_noise`` both are the plain estimator.

    Returns
    -------
    Estimate
        ``method='filter-error'``; names include ``process_noise_std``.

    """
    if bounds not in ('marginal', 'conditional'):
        raise IdentificationError(f"bounds must be 'marginal' or 'conditional', not {bounds!r}")
    options: dict[str, Any] = {
        'known': known, 'noise_std': noise_std, 'max_iter': max_iter, 'rows': rows,
        'noise_model': noise_model, 'gain': gain, 'step_tol': step_tol,
        'max_step': max_step, 'gradients': gradients}
    if bounds == 'marginal' and estimate_process_noise and gradients == 'analytic':
        # a dozen fits follow: the compiled filter pays for its loading (kernels.prefer)
        kernels.prefer()
    joint = fit_filter_error_ml(experiments, unknowns, guess=guess, progress=progress,
                                process_noise_std=process_noise_std,
                                estimate_process_noise=estimate_process_noise, label=label,
                                **options)
    if bounds == 'conditional' or not estimate_process_noise:
        return joint
    t_start = time.perf_counter()
    fits: dict[float, Any] = {}         # σ_V -> its Estimate, None where that fit failed

    def warm_start(sigma_v):
        """
        Return the start of the fit at σ_V.

        Every other unknown, interpolated (or extrapolated by at most twice their spacing)
        from the two nearest fits done, else the nearest one.
        """
        done = [(s, fits[s].values) for s in fits if fits[s] is not None]
        if not any(s == s_hat for s, _ in done):
            done.append((s_hat, np.delete(joint.values, at)))
        done.sort(key=lambda item: abs(item[0] - sigma_v))
        values = done[0][1]
        if len(done) > 1 and done[1][0] != done[0][0]:
            (s1, v1), (s2, v2) = done[0], done[1]
            guess = v1 + (v2 - v1) * (sigma_v - s1) / (s2 - s1)
            noise = [i for i, n in enumerate(others) if n.startswith('noise_std_')]
            if abs(sigma_v - s1) <= 2.0 * abs(s2 - s1) and np.all(guess[noise] > 0):
                values = guess
        return dict(zip(others, values))

    def fit_at(sigma_v):
        if sigma_v in fits:
            return fits[sigma_v]
        start = warm_start(sigma_v)
        try:
            est = fit_filter_error_ml(
                experiments, unknowns, guess={n: start[n] for n in unknowns},
                process_noise_std=sigma_v, estimate_process_noise=False,
                label=f'{label}: profile σ_V = {sigma_v:.4g} ({len(fits) + 1})',
                progress=progress, start_values=start,
                **dict(options, step_tol=max(step_tol, _PROFILE_STEP_TOL)))
        except (IdentificationError, np.linalg.LinAlgError, FloatingPointError):
            est = None                 # no fit there: no weight (f = inf)
        fits[sigma_v] = est
        return est

    s_hat = joint.value(PROCESS_NOISE)
    s_std = joint.std_of(PROCESS_NOISE)
    at = joint.names.index(PROCESS_NOISE)       # the structural unknowns come first
    others = [n for n in joint.names if n != PROCESS_NOISE]

    def on_branch(sigma):
        """
        Restricted cost on the grid; inf off the branch of optima through the joint estimate.

        Walking out from σ̂_V, a fit whose structural unknowns jump by more than 3σ (the σ of
        its neighbour already on the branch) has left that branch: at a large σ_V a model
        with a fast enough wake absorbs the process noise, and its undetermined parameters
        lower ½log|M_θθ| without bound. That point and those beyond it carry no weight.
        """
        for s in sorted(sigma, key=lambda s: abs(s - s_hat)):
            fit_at(float(s))           # outward from σ̂_V, so warm starts follow the branch
        ests = [fits[float(s)] for s in sigma]
        keep = np.zeros(sigma.size, dtype=bool)
        anchor = int(np.argmin(np.abs(sigma - s_hat)))
        keep[anchor] = ests[anchor] is not None
        for direction in (1, -1):
            j = anchor
            while keep[j] and 0 <= j + direction < sigma.size:
                a, b = ests[j], ests[j + direction]
                if b is None or np.any(np.abs(a.values[:at] - b.values[:at]) >
                                       3.0 * a.std[:at]):
                    break
                keep[j + direction] = True
                j += direction
        f = np.array([_restricted_cost(e) if k else math.inf for e, k in zip(ests, keep)])
        return f, keep

    reach = max(s_hat + 4.0 * s_std, 2.0 * s_hat, 1e-12)
    sigma = np.unique(np.append(np.linspace(0.0, reach, _PROFILE_POINTS), s_hat))
    f, keep = on_branch(sigma)
    step = reach / (_PROFILE_POINTS - 1)
    while keep[-1] and f[-1] - np.min(f) < _PROFILE_SPAN and sigma.size < 40:
        step *= 1.5                    # geometric: a far tail costs few points
        sigma = np.append(sigma, sigma[-1] + step)
        f, keep = on_branch(sigma)
    for _refine in range(3):           # at least 8 grid points where the weight is
        low = np.flatnonzero(f - np.min(f) < _PROFILE_SPAN)
        if low.size >= _PROFILE_LOW_POINTS:
            break
        lo, hi = max(low[0] - 1, 0), min(low[-1] + 1, sigma.size - 1)
        sigma = np.unique(np.concatenate([sigma, 0.5 * (sigma[lo:hi] + sigma[lo + 1:hi + 1])]))
        f, keep = on_branch(sigma)
    if not np.any(np.isfinite(f)):
        return replace(joint, warnings=joint.warnings + [
            'the process-noise profile failed at every grid point: the bounds are the '
            'Cramér-Rao bound at the joint optimum (conditional on σ_V)'])
    # σ_V at the minimum of f (vertex of the parabola through the lowest point's neighbours)
    i = int(np.argmin(f))
    s_restricted = float(sigma[i])
    if 0 < i < sigma.size - 1 and np.all(np.isfinite(f[i - 1:i + 2])):
        a, b, _ = np.polyfit(sigma[i - 1:i + 2], f[i - 1:i + 2], 2)
        if a > 0:
            s_restricted = float(np.clip(-b / (2 * a), sigma[i - 1], sigma[i + 1]))
    # the mixture covariance about the joint estimate, over σ_V weighted by exp(−f)
    w = _trapezoid_weights(sigma, f)
    cov = np.zeros_like(joint.covariance)
    cov[at + 1:, at + 1:] = joint.covariance[at + 1:, at + 1:]    # measurement σ's
    struct = slice(0, at)
    for weight, s in zip(w, sigma):
        est = fits[float(s)]
        if weight == 0.0:
            continue
        d = np.append(est.values[:at] - joint.values[:at], s - joint.values[at])
        cov[struct, struct] += weight * est.covariance[:at, :at]
        cov[:at + 1, :at + 1] += weight * np.outer(d, d)
    std = np.sqrt(np.diag(cov))
    information = np.linalg.pinv(cov / np.outer(std, std)) / np.outer(std, std)
    warnings = [m for m in joint.warnings if 'process noise estimated at zero' not in m]
    if joint.values[at] == 0.0:
        warnings.append('process noise estimated at zero; the bounds include every '
                        'process-noise σ the record allows (restricted-likelihood σ_V '
                        f'{s_restricted:.3g})')
    done = [fits[s] for s in sorted(fits) if fits[s] is not None]
    message = (f'bounds integrated over σ_V (restricted likelihood on {int(keep.sum())} grid '
               f'points, its minimum at σ_V {s_restricted:.4g}; '
               f'{time.perf_counter() - t_start:.1f} s)')
    if not keep[-1] or not keep[0]:
        cut = sigma[~keep]
        span = f'{cut.min():.3g}' + (f'-{cut.max():.3g}' if cut.size > 1 else '')
        message += (f'; σ_V {span} left out: no fit there, or it jumped off the branch of '
                    'optima through the estimate')
    message = message if joint.converged else f'{joint.message}; {message}'
    return replace(joint, covariance=cov, information=information, warnings=warnings,
                   history=joint.history + [h for e in done for h in e.history],
                   message=message, iterations=joint.iterations + sum(e.iterations for e in done))


def _windows(A, substeps):
    """
    Return A at each interval's stage times (T-1, 2s+1, …), views of A (2M+1, …) or (1, …).

    The stage grid (:func:`~rotor_id.estimation.simulate.fine_grid`) has 2s points per
    interval and shares each interval's end with the next one's start.
    """
    if A.shape[0] == 1:
        return np.broadcast_to(A[:, None], (1, 2 * substeps + 1) + A.shape[1:])
    view = np.lib.stride_tricks.sliding_window_view(A, 2 * substeps + 1, axis=0)
    return np.moveaxis(view[::2 * substeps], -1, 1)


def _noise_derivatives_agree(series, exact, Q, steps, directions, kp):
    """
    Tell whether ∂Q from a series equals the intervals' own (…, len(directions), n, n).

    Along each direction to :data:`PHASE_AGREE` of its largest entry; along a parameter of F,
    where ∂Q is the forward difference (Q(F + step·∂F) − Q)/step, to its own rounding if that
    is larger (:data:`DIFFERENCE_ROUNDINGS` of Q's largest entry over the step): the
    difference of two Q's equal to rounding is not equal to a fraction of the difference.
    """
    eps = np.finfo(float).eps * float(np.max(np.abs(Q), initial=0.0))
    for slot, i in enumerate(directions):
        s, e = series[..., slot, :, :], exact[..., slot, :, :]
        scale = float(np.max(np.abs(e), initial=0.0))
        tolerance = PHASE_AGREE * scale
        if i < kp:
            tolerance = max(tolerance, DIFFERENCE_ROUNDINGS * eps / steps[i])
        if not float(np.max(np.abs(s - e), initial=0.0)) <= tolerance:
            return False
    return True


def _difference_steps(F, dF, kp):
    """
    Return the steps of the forward difference of Q along ∂F/∂p, one per parameter.

    1e-7 of F's largest entry along each ∂F/∂p (F and dF: tuples of arrays, e.g. the stage
    grid and the midpoints): the same for every interval of a record, so that Q's
    derivative is one smooth function of the interval's azimuth.
    """
    size_F = max(max(float(np.max(np.abs(Fx))) for Fx in F), 1e-300)
    return [1e-7 * size_F / max(max(float(np.max(np.abs(dFx[..., i, :, :]))) for dFx in dF),
                                1e-300) for i in range(kp)]
