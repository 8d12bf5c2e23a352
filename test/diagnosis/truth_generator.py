"""
Independent generator of "real" test-stand recordings with concealed effects.

This is the test suite's stand-in for the rotor. It is written from the blade equations, blade
by blade, with scipy's adaptive integrator, and shares no code with the identification models
of :mod:`rotor_id.physics` or the simulator of :mod:`rotor_id.estimation` (only the Record
container is used, to hand the data over). Each of the N blades, k at azimuth
ψ_k = t + (k−1)2π/N, obeys the Sissingh rigid-blade equation (docs/models.md §7, corrected
Ch.3 eq. 24), with its own Lock number γ_k, pitch θ_k, pitch-flap coupling K_P = tan δ3
(``pitch_flap``) and a cubic flap spring:

    β_k″ + P² β_k + κ β_k³ = M_k
    M_k = (γ_k/2) [m_θ (θ_k − K_P β_k + w_k) + C (λ_h,k − β_k′) − K β_k + m_λ λ0]

with the coefficients of Ch.3 eqs 25-28 (m_λ = B³/3 + (B²μ/2) sin ψ). The wake's inflow
(up positive, the report's sign) varies linearly along the span: its first harmonic
λ_h,k = λ_c cos ψ_k + λ_s sin ψ_k (Crews-Hohenemser-Ormiston gain L, Peters time constant τ)
enters like −β′ (both are x-proportional normal velocities) and is driven by the first
harmonics of the blades' moments,

    τ λ_c′ + λ_c = −L (2/N) Σ M_k cos ψ_k,   τ λ_s′ + λ_s = −L (2/N) Σ M_k sin ψ_k,

and, with ``uniform_inflow``, a uniform inflow λ0 driven by the mean blade lift,

    τ0 λ0′ + λ0 = −L0 (1/N) Σ F_k,
    F_k = (γ_k/2) [f_θ (θ_k − K_P β_k + w_k) + f_r (λ_h,k − β_k′) − f_β β_k + f_λ λ0]
    f_θ = ∫U_T², f_r = ∫x U_T, f_β = μ cos ψ ∫U_T, f_λ = ∫U_T  (x in [0, B], U_T = x + μ sin ψ).

w_k = w_0 + w_c cos ψ_k + w_s sin ψ_k is a random pitch-like inflow angle (turbulence) whose
three components are independent Gauss-Markov processes (σ ``turbulence``, correlation time
``turbulence_corr`` in rad of azimuth). The sensors: each flap sensor lags (first order,
time constant ``sensor_lag`` rad of azimuth), is read ``time_delay_s`` late with respect to
the pitch, has a constant bias, a scale error ``sensor_gain`` and white noise; pitch sensors
have white noise and read the commanded pitch: they see neither a blade's aerodynamic pitch
offset ``pitch_offset``, nor the first-order lag of the blade's pitch behind them
(``actuator_lag``, rad of azimuth). ``pitch_flap_coupling`` is a coupling K_P the run
description does not know (a concealed δ3), added to ``pitch_flap``. The azimuth encoder's
zero may be off: the recording's azimuth of blade 1 reads ``azimuth_offset`` (rad) more than
the blade's true azimuth, on which the rotor, its swashplate and its aerodynamics run.
``flap_stiffness_1c`` is physics no catalogue candidate models: a flap spring
whose stiffness varies once per revolution in the shaft frame (a hub spring with a
shaft-fixed asymmetry), β_k″ += −K_1c cos ψ_k β_k; ``flap_damping_1s`` another, a flap damper
whose damping varies once per revolution, β_k″ += −D_1s sin ψ_k β_k′.

The record starts in trim at collective pitch only (settled over ``t_settle`` from rest), the
lateral cyclic is stepped on at ``t_step``, and pitch stirring θI = a sin φ, θII = a cos φ,
φ = ω̇ (t − t_step − t0)² starts t0 later and lasts ``t_stir`` (recordings README).
"""

from dataclasses import asdict, dataclass, field, replace
import hashlib
import json
import math
import os
from pathlib import Path

import numpy as np
from rotor_id.io.record import Record
from scipy.integrate import solve_ivp


@dataclass
class TruthConfig:
    """The knobs of the generator (the ``truth`` blocks of recordings/answers.json)."""

    mu: float = 0.0
    gamma: float = 8.0 * 0.5 / 0.97**4          # A = γB⁴/8 = 0.5
    theta0: float = math.radians(2.0)
    tip_loss: float = 0.97
    flap_freq: float = 1.2
    cyclic: float = math.radians(1.5)
    t_step: float = 2.0 * math.pi
    t0: float = 70.0
    omegadot: float = -0.1 / math.pi
    t_stir: float = 24.0
    t_settle: float = 80.0
    wake: bool = True
    wake_L: float = 4.0
    wake_tau: float = 8.0
    omega_rad_s: float = 94.24777960769379
    rate_hz: float = 1000.0
    flap_noise: float = math.radians(0.05)
    pitch_noise: float = math.radians(0.005)
    seed: int = 0
    sensor_lag: float = 0.0
    time_delay_s: float = 0.0
    sensor_bias: list = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0])
    gamma_scale: list = field(default_factory=lambda: [1.0, 1.0, 1.0, 1.0])
    pitch_offset: list = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0])
    turbulence: float = 0.0
    turbulence_corr: float = 2.0
    cubic_stiffness: float = 0.0
    #: pitch-flap coupling K = tan δ3: a blade's pitch falls by K β_k as it flaps up (the pitch
    #: sensors read the commanded pitch, before the pitch links)
    pitch_flap_coupling: float = 0.0
    #: first-order lag of each blade's pitch behind the measured pitch, rad of azimuth
    actuator_lag: float = 0.0
    #: flap-sensor scale errors per blade: the sensor reads (1 + s_k) β_k
    sensor_gain: list = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0])
    #: the recorded azimuth of blade 1 minus its true azimuth (encoder index off blade 1), rad
    azimuth_offset: float = 0.0
    #: once-per-rev flap stiffness K_1c (per rev²): β_k″ += −K_1c cos ψ_k β_k (out of catalogue)
    flap_stiffness_1c: float = 0.0
    #: once-per-rev flap damping D_1s (per rev): β_k″ += −D_1s sin ψ_k β_k′ (out of catalogue)
    flap_damping_1s: float = 0.0
    n_blades: int = 4
    pitch_flap: float = 0.0
    #: a flap frequency the run description does not know: the rotor's P is
    #: ``flap_freq + flap_freq_error`` while the description states ``flap_freq``
    flap_freq_error: float = 0.0
    uniform_inflow: bool = False
    wake_L0: float = 2.0
    wake_tau0: float = 4.0

    @property
    def t_end(self):
        """Last nondimensional time of the record."""
        return self.t_step + self.t0 + self.t_stir

    def with_(self, **changes):
        """Return a copy with some knobs changed."""
        return replace(self, **changes)

    def as_dict(self):
        """JSON-ready knobs."""
        return asdict(self)


def wake_case(**changes):
    """Return the report's μ = 0 dynamic-wake case (Ch.2), as the dx_* wake recordings."""
    return TruthConfig(**changes)


def mu04_case(**changes):
    """Return the report's μ = 0.4 multiblade case, no wake, as dx_periodic_coefficients."""
    base = {'mu': 0.4, 'gamma': 5.0, 't0': 12.0, 'wake': False,
            'flap_noise': math.radians(0.1)}
    base.update(changes)
    return TruthConfig(**base)


def _pitch_schedule(cfg, t):
    """Commanded multiblade pitch (θI, θII) at times t: step, then stirring."""
    t = np.asarray(t, dtype=float)
    on = np.where(t >= cfg.t_step, cfg.cyclic, 0.0)
    tau = np.maximum(t - cfg.t_step - cfg.t0, 0.0)
    phi = cfg.omegadot * tau * tau
    return on * np.sin(phi), on * np.cos(phi)


class _GaussMarkov:
    """Three independent first-order Gauss-Markov inflow components on a fine grid."""

    def __init__(self, sigma, corr, t_start, t_end, rng, step=0.02):
        self.t = np.arange(t_start, t_end + 2 * step, step)
        a = math.exp(-step / corr)
        w = np.zeros((self.t.size, 3))
        w[0] = sigma * rng.standard_normal(3)
        kick = sigma * math.sqrt(1.0 - a * a) * rng.standard_normal((self.t.size, 3))
        for j in range(1, self.t.size):
            w[j] = a * w[j - 1] + kick[j]
        self.w = w
        self.step = step

    def __call__(self, t):
        x = (t - self.t[0]) / self.step
        j = min(max(int(x), 0), self.t.size - 2)
        f = x - j
        return (1.0 - f) * self.w[j] + f * self.w[j + 1]


def _rhs_factory(cfg, turbulence):
    n = cfg.n_blades
    B, mu, P = cfg.tip_loss, cfg.mu, cfg.flap_freq + cfg.flap_freq_error
    offsets = 2.0 * math.pi * np.arange(n) / n
    gam = cfg.gamma * np.asarray(cfg.gamma_scale, dtype=float)
    dtheta = np.asarray(cfg.pitch_offset, dtype=float)
    kappa = cfg.cubic_stiffness
    k1c, d1s = cfg.flap_stiffness_1c, cfg.flap_damping_1s
    lag = cfg.sensor_lag
    coupling, act_lag = cfg.pitch_flap_coupling, cfg.actuator_lag
    wake = cfg.wake
    L, tau = cfg.wake_L, cfg.wake_tau
    kp = cfg.pitch_flap
    uniform = cfg.uniform_inflow
    L0, tau0 = cfg.wake_L0, cfg.wake_tau0
    nl = 3 * n + 2                                   # index of λ0 (after the sensor lags)
    na = nl + (1 if uniform else 0)                  # the blades' pitch (actuator lag)

    def rhs(t, s):
        beta, rate = s[:n], s[n:2 * n]
        lam_c, lam_s = s[2 * n], s[2 * n + 1]
        lam0 = s[nl] if uniform else 0.0
        psi = t + offsets
        s1, c1, s2, c2 = np.sin(psi), np.cos(psi), np.sin(2 * psi), np.cos(2 * psi)
        damping = B**4 / 4 + (B**3 * mu / 3) * s1
        stiffness = (B**3 * mu / 3) * c1 + (B**2 * mu**2 / 4) * s2
        m_theta = ((B**4 + B**2 * mu**2) / 4 + (2.0 / 3.0) * B**3 * mu * s1
                   - (B**2 * mu**2 / 4) * c2)
        m_lambda = B**3 / 3 + (B**2 * mu / 2) * s1
        th_i, th_ii = _pitch_schedule(cfg, t)
        measured = cfg.theta0 - th_i * np.sin(psi) + th_ii * np.cos(psi)
        blade_pitch = s[na:na + n] if act_lag > 0 else measured
        theta = blade_pitch + dtheta - (kp + coupling) * beta
        lam = lam_c * c1 + lam_s * s1 if wake else 0.0 * c1
        if turbulence is not None:
            w = turbulence(t)
            theta = theta + w[0] + w[1] * c1 + w[2] * s1
        aero = 0.5 * gam * (m_theta * theta + damping * (lam - rate) - stiffness * beta
                            + m_lambda * lam0)
        accel = aero - P**2 * beta - kappa * beta**3 - k1c * c1 * beta - d1s * s1 * rate
        out = np.zeros_like(s)
        out[:n] = rate
        out[n:2 * n] = accel
        if wake:
            moment_c = (2.0 / n) * np.sum(aero * c1)
            moment_s = (2.0 / n) * np.sum(aero * s1)
            out[2 * n] = (-lam_c - L * moment_c) / tau
            out[2 * n + 1] = (-lam_s - L * moment_s) / tau
        if lag > 0:
            out[2 * n + 2:nl] = (beta - s[2 * n + 2:nl]) / lag
        if uniform:
            f_theta = B**3 / 3 + B**2 * mu * s1 + B * mu**2 * s1 * s1
            f_rate = B**3 / 3 + (B**2 * mu / 2) * s1
            f_beta = mu * c1 * (B**2 / 2 + B * mu * s1)
            f_lambda = B**2 / 2 + B * mu * s1
            lift = 0.5 * gam * (f_theta * theta + f_rate * (lam - rate) - f_beta * beta
                                + f_lambda * lam0)
            out[nl] = (-lam0 - L0 * np.mean(lift)) / tau0
        if act_lag > 0:
            out[na:na + n] = (measured - s[na:na + n]) / act_lag
        return out

    return rhs


def _integrate_between_knots(rhs, s0, t_start, t_end, t_eval, knots):
    """
    States at ``t_eval`` (T, n): DOP853 (rtol 1e-9, atol 1e-12) restarted at every knot.

    The turbulence is piecewise linear between its grid points (``knots``), so the right-hand
    side has a kink at each of them. One adaptive integration across the kinks spends most of
    its steps rejecting and shrinking there (≈ 99 000 steps for a 183 rad record, against
    ≈ 9 000 knots); here each interval between two knots is integrated on its own, where the
    right-hand side is smooth, with the same error control, and the step size carries over.
    """
    from scipy.integrate import DOP853
    cuts = knots[(knots > t_start) & (knots < t_end)]
    bounds = np.concatenate([[t_start], cuts, [t_end]])
    out = np.empty((len(t_eval), len(s0)))
    order = np.argsort(t_eval)
    t_sorted = np.asarray(t_eval)[order]
    i = int(np.searchsorted(t_sorted, t_start, side='left'))
    if i:
        raise ValueError('truth simulation: an output time precedes the start')
    y, step = np.asarray(s0, dtype=float), None
    for a, b in zip(bounds[:-1], bounds[1:]):
        solver = DOP853(rhs, a, y, b, rtol=1e-9, atol=1e-12, max_step=0.05,
                        first_step=None if step is None else min(step, b - a))
        while solver.status == 'running':
            solver.step()
            if solver.status == 'failed':
                raise RuntimeError('truth simulation failed between turbulence knots')
            j = int(np.searchsorted(t_sorted, solver.t, side='right'))
            if j > i:
                dense = solver.dense_output()
                out[order[i:j]] = dense(t_sorted[i:j]).T
                i = j
            step = solver.h_abs          # the step its error control asks for next
        y = solver.y
    if i < len(t_sorted):
        raise RuntimeError('truth simulation ended before the last output time')
    return out


#: Environment variable naming a directory where generated records are kept (off if unset):
#: a record is looked up by a hash of this file's source and of the knobs, so an edit of the
#: generator or another truth makes a new entry. Never a directory inside the repository.
CACHE_ENV = 'ROTOR_ID_TRUTH_CACHE'
_RECORD_ARRAYS = ('time_s', 't', 'rotor_speed_rad_s', 'blade_flap', 'blade_pitch')


def cache_key(cfg):
    """Hash of the generator's source and of the knobs ``cfg``: the name of a cached record."""
    digest = hashlib.sha256(Path(__file__).read_bytes())
    digest.update(json.dumps(cfg.as_dict(), sort_keys=True, default=float).encode())
    return digest.hexdigest()[:32]


def generate(cfg):
    """
    Simulate one recording; return a :class:`rotor_id.io.record.Record` (rad, s).

    With the environment variable ``ROTOR_ID_TRUTH_CACHE`` set to a directory, a record
    generated before from the same source and knobs is read from there instead (bit-equal).
    """
    where = os.environ.get(CACHE_ENV)
    if not where:
        return _simulate(cfg)
    path = Path(where) / f'truth_{cache_key(cfg)}.npz'
    if path.exists():
        with np.load(path) as z:
            return Record(**{k: z[k] for k in _RECORD_ARRAYS},
                          blade_names=[f'blade_{k + 1}' for k in range(cfg.n_blades)],
                          source=f'truth_generator seed {cfg.seed}')
    record = _simulate(cfg)
    path.parent.mkdir(parents=True, exist_ok=True)
    part = path.with_suffix(f'.{os.getpid()}.npz')
    np.savez(part, **{k: getattr(record, k) for k in _RECORD_ARRAYS})
    os.replace(part, path)                   # whole or absent, with several workers
    return record


def _simulate(cfg):
    """Simulate one recording (:func:`generate` without the cache)."""
    rng = np.random.default_rng(cfg.seed)
    n = cfg.n_blades
    omega = cfg.omega_rad_s
    dt_s = 1.0 / cfg.rate_hz
    n_samples = int(math.floor(cfg.t_end / omega / dt_s + 1e-9)) + 1
    time_s = np.arange(n_samples) * dt_s
    t = omega * time_s
    delay = omega * cfg.time_delay_s
    t_start = -cfg.t_settle - max(delay, 0.0)
    turbulence = None
    if cfg.turbulence > 0:
        turbulence = _GaussMarkov(cfg.turbulence, cfg.turbulence_corr, t_start - 1.0,
                                  cfg.t_end + 1.0, rng)
    rhs = _rhs_factory(cfg, turbulence)
    na = 3 * n + 2 + (1 if cfg.uniform_inflow else 0)
    s0 = np.zeros(na + n)
    s0[na:] = cfg.theta0                     # the blades' pitch in trim
    t_read = t - delay                       # flap read late: it shows the rotor at t − delay
    t_last = float(max(t[-1], t_read[-1]))
    if turbulence is None:
        sol = solve_ivp(rhs, (t_start, t_last), s0, method='DOP853', t_eval=t_read,
                        rtol=1e-9, atol=1e-12, max_step=0.5)
        if not sol.success:
            raise RuntimeError(f'truth simulation failed: {sol.message}')
        states = sol.y.T
    else:
        states = _integrate_between_knots(rhs, s0, t_start, t_last, t_read, turbulence.t)
    flap_true = states[:, 2 * n + 2:3 * n + 2] if cfg.sensor_lag > 0 else states[:, :n]
    if any(cfg.sensor_gain):                 # the all-zero default serves any blade count
        flap_true = flap_true * (1.0 + np.asarray(cfg.sensor_gain, dtype=float)[None, :])
    flap = (flap_true + np.asarray(cfg.sensor_bias, dtype=float)[None, :]
            + cfg.flap_noise * rng.standard_normal((n_samples, n)))
    psi = t[:, None] + 2.0 * math.pi * np.arange(n)[None, :] / n
    th_i, th_ii = _pitch_schedule(cfg, t)
    pitch = (cfg.theta0 - th_i[:, None] * np.sin(psi) + th_ii[:, None] * np.cos(psi)
             + cfg.pitch_noise * rng.standard_normal((n_samples, n)))
    # the encoder reads the true azimuth plus its offset; everything above ran on the true one
    return Record(time_s=time_s, t=t + cfg.azimuth_offset,
                  rotor_speed_rad_s=np.full(n_samples, omega),
                  blade_flap=flap, blade_pitch=pitch,
                  blade_names=[f'blade_{k + 1}' for k in range(n)],
                  source=f'truth_generator seed {cfg.seed}')


#: The experimenter's nominal values of the unknowns (the report's true values).
NOMINAL_GUESS = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125, 'gamma': 5.0,
                 'theta0': math.radians(2.0)}


def run_description_text(cfg, model, unknowns, window_s=None, guess=True):
    """
    Return a run description (README schema) for a generated record.

    ``guess``: give the nominal values as ``initial_guess`` (saves the start-value grid).
    """
    window_s = window_s or (0.0, cfg.t_end / cfg.omega_rad_s)
    names = ', '.join(unknowns)
    extra = ''
    if guess:
        extra = 'initial_guess: {' + ', '.join(f'{n}: {NOMINAL_GUESS[n]!r}'
                                               for n in unknowns) + '}\n'
    return (extra + f'rotor:\n  blades: {cfg.n_blades}\n  advance_ratio: {cfg.mu}\n'
            f'  flap_frequency: {cfg.flap_freq}\n  tip_loss: {cfg.tip_loss}\n'
            f'  pitch_flap_coupling: {cfg.pitch_flap}\n'
            'topics: {blade_pitch: /rotor/blade_pitch, blade_flap: /rotor/blade_flap, '
            'azimuth: /rotor/azimuth}\n'
            f'model: {model}\nunknowns: [{names}]\n'
            f'window_s: [{window_s[0]:.6f}, {window_s[1]:.6f}]\n')
