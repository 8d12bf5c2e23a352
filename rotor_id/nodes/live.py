"""
ROS-free pieces of the live nodes: the plant's stepping, sample checks, buffers, the verdict.

Everything here is plain numpy on top of the library (one simulator, one estimator, one time
base), so the nodes stay one screen each and this module is tested without rclpy.
"""

import math

import numpy as np

from rotor_id.estimation import kernels
from rotor_id.estimation.information import information_history
from rotor_id.estimation.kalman import default_noise_rows, DiscreteModel, discretize, kalman_filter
from rotor_id.estimation.simulate import simulate
from rotor_id.io.record import Record
from rotor_id.io.timebase import (AzimuthUnwrapper, interpolate_columns,
                                  nondimensional_time, TWO_PI, wrap_azimuth)
from rotor_id.physics.blades import blade_flap_from_states
from rotor_id.physics.models import build_model, RotorConstants
from rotor_id.physics.stirring import blade_pitch_from_multiblade

NS = 1_000_000_000
_NOISE_BLOCK = 1024
#: Revolutions simulated at collective pitch before the run to reach the periodic trim.


# ------------------------------------------------------------------------------ the plant
class PlantStepper:
    """
    The simulated rotor of the plant node, advanced sample by sample in real time.

    The truth is one library model (or one ``single_blade`` model per blade), simulated with
    :func:`rotor_id.estimation.simulate.simulate`; the swashplate input u = [θ0, θI, θII]
    (report eq. 3) follows the commands linearly from one to the next (a servo; a zero-order
    hold would lag the stirring by half a command interval and bias A by ~2 %), holding the
    last one; system noise (report eq. 29a) enters as a piecewise-constant forcing of chosen
    states.

    Parameters
    ----------
    model_name : str
        'multiblade_wake' | 'multiblade' | 'multiblade_constant' | 'single_blade'.
    rotor : RotorConstants
    true_values : dict
        Parameter values of the truth (names as in the models; others are ignored).
    omega_rad_s, rate_hz : float
        Rotor speed Ω and sample rate: one sample advances t by Ω / rate.
    collective : float
        θ0 (rad) until the first command arrives; the rotor starts in trim at it.
    flap_noise_std, pitch_noise_std : float
        Measurement noise σ (rad) of each blade's flap and pitch sensor.
    process_noise_std : float
        System-noise intensity q: the forcing of each noisy state over a sample interval Δt is
        N(0, q²/Δt) (white noise of spectral density q² per unit t).
    process_noise_states : sequence of str, optional
        States driven by system noise; default the wake inflow (λI, λII) for the wake model and
        the flap rates otherwise.
    seed : int
    inflow : str
        Wake model only: 'cyclic' (the report's) or 'three_state' (docs/models.md §9). Any
        number of blades N ≥ 2, advance ratio and pitch-flap coupling (``rotor``); the wake
        model carries every blade's coordinates when it must (two blades, or the uniform
        inflow, which moves the coning), otherwise the report's tilt states plus the coning.

    """

    def __init__(self, model_name, rotor, true_values, omega_rad_s, rate_hz, collective,
                 flap_noise_std=0.0, pitch_noise_std=0.0, process_noise_std=0.0,
                 process_noise_states=None, seed=0, t_start=0.0, inflow='cyclic'):
        if not omega_rad_s > 0 or not rate_hz > 0:
            raise ValueError('rotor speed and sample rate must be positive')
        if model_name == 'single_blade':
            self.models = [build_model('single_blade', rotor, blade=k)
                           for k in range(1, rotor.n_blades + 1)]
        elif model_name == 'multiblade_wake':
            every_blade = rotor.n_blades < 3 or inflow == 'three_state'
            self.models = [build_model(model_name, rotor, inflow=inflow,
                                       **({'outputs': 'blades'} if every_blade else {}))]
        else:
            self.models = [build_model(model_name, rotor)]
        model = self.models[0]
        self.rotor = rotor
        self.p = model.parameter_vector({k: v for k, v in true_values.items()
                                         if k in model.parameter_names})
        self.step = omega_rad_s / rate_hz
        self.seed = int(seed)
        self._blocks = {}
        self.flap_noise_std = float(flap_noise_std)
        self.pitch_noise_std = float(pitch_noise_std)
        self.process_noise_std = float(process_noise_std)
        if process_noise_states is None:
            process_noise_states = (('lambda_I', 'lambda_II') if model.name == 'multiblade_wake'
                                    else [s for s in model.state_names if s.endswith('_dot')])
        unknown = [s for s in process_noise_states if s not in model.state_names]
        if unknown:
            raise ValueError(f'process_noise_states {unknown} are not states of {model.name}; '
                             f'its states are {", ".join(model.state_names)}')
        self.noisy = [model.state_names.index(s) for s in process_noise_states]
        self.t = float(t_start)
        self.cmd_t = np.array([self.t])
        self.cmd_u = np.array([[collective, 0.0, 0.0]])
        self.samples = 0
        self.x = [self._trim(m, collective) for m in self.models]

    def _normal(self, stream, first, n, width):
        """
        Draw standard normal values for samples first..first+n-1 of a noise stream.

        Drawn in blocks keyed by (seed, stream, block), so a run's noise depends on the seed
        and the sample index only, not on how the samples were batched in real time.
        """
        rows = np.arange(first, first + n)
        out = np.empty((n, width))
        for block in np.unique(rows // _NOISE_BLOCK):
            key = (stream, int(block))
            if key not in self._blocks:
                rng = np.random.default_rng([self.seed, stream, int(block)])
                self._blocks = {k: v for k, v in self._blocks.items() if k[1] >= block - 1}
                self._blocks[key] = rng.standard_normal((_NOISE_BLOCK, width))
            inside = rows // _NOISE_BLOCK == block
            out[inside] = self._blocks[key][rows[inside] % _NOISE_BLOCK]
        return out

    def _parameters(self, collective):
        p = self.p.copy()
        names = self.models[0].parameter_names
        if 'theta0' in names:
            p[names.index('theta0')] = collective
        return p

    def _trim(self, model, collective):
        """Trim at collective only: the model's equilibrium or periodic trim."""
        return model.trim_state(self._parameters(collective), collective, t=self.t)

    @property
    def coning(self):
        """Steady coning added to the blades of a model without a β0 state (the report's wake)."""
        collective = self.cmd_u[-1, 0]
        return self.models[0].coning(self._parameters(collective), collective)

    def command(self, t_cmd, u):
        """Hold the multiblade pitch ``u`` = [θ0, θI, θII] from nondimensional time ``t_cmd``."""
        if not t_cmd > self.cmd_t[-1]:
            return False
        if self.cmd_t[-1] < self.t < t_cmd:      # held until now, then ramps to the command
            self.cmd_t = np.append(self.cmd_t, self.t)
            self.cmd_u = np.vstack([self.cmd_u, self.cmd_u[-1:]])
        self.cmd_t = np.append(self.cmd_t, float(t_cmd))
        self.cmd_u = np.vstack([self.cmd_u, np.asarray(u, dtype=float)[None, :3]])
        return True

    def inputs(self, t):
        """Commanded u at times t (linear between commands, held after the last), (len(t), 3)."""
        t = np.atleast_1d(t)
        return np.column_stack([np.interp(t, self.cmd_t, self.cmd_u[:, j]) for j in range(3)])

    def advance(self, n):
        """Advance ``n`` samples; return t (n,), measured flap (n, N) and pitch (n, N), rad."""
        grid = self.t + self.step * np.arange(n + 1)
        u_end = self.inputs(grid[-1:])[0]
        p = self._parameters(u_end[0])
        states = []
        for i, model in enumerate(self.models):
            forcing = None
            if self.process_noise_std > 0 and self.noisy:
                forcing = np.zeros((n, model.n_states))
                forcing[:, self.noisy] = (self.process_noise_std / math.sqrt(self.step) *
                                          self._normal(2 + i, self.samples, n, len(self.noisy)))
            sim = simulate(model, p, self.inputs, grid, self.x[i], forcing=forcing)
            self.x[i] = sim.x[-1]
            states.append(sim.x[1:])
        t = grid[1:]
        flap = blade_flap_from_states(self.models, t, states, self.coning)
        pitch = blade_pitch_from_multiblade(t, self.inputs(t), self.rotor.n_blades)
        flap = flap + self.flap_noise_std * self._normal(0, self.samples, n, flap.shape[1])
        pitch = pitch + self.pitch_noise_std * self._normal(1, self.samples, n, pitch.shape[1])
        self.t = float(grid[-1])
        self.samples += n
        keep = max(0, int(np.searchsorted(self.cmd_t, self.t, side='right')) - 1)
        self.cmd_t, self.cmd_u = self.cmd_t[keep:], self.cmd_u[keep:]
        return t, flap, pitch


def rotor_constants(n_blades, advance_ratio, flap_frequency, tip_loss, pitch_flap_coupling=0.0):
    """Return the RotorConstants of node parameters (checked like a run description)."""
    if n_blades < 1:
        raise ValueError(f'n_blades must be at least 1, got {n_blades}')
    return RotorConstants(int(n_blades), float(advance_ratio), float(flap_frequency),
                          float(tip_loss), float(pitch_flap_coupling)).check()


# ------------------------------------------------------------------------------ Kalman, streaming
class StreamingKalman:
    """
    The library's Kalman filter (:mod:`rotor_id.estimation.kalman`) fed batch by batch.

    Each batch of new samples is discretised together with the previous sample time
    (:func:`~rotor_id.estimation.kalman.discretize`, the simulator's RK4 maps), the filtered
    state is predicted across that first interval (eqs 27-28) and
    :func:`~rotor_id.estimation.kalman.kalman_filter` runs over the batch from there. Parameters
    can change between batches (the report's iterated filter/identification loop).

    Parameters
    ----------
    model : LinearModel
    p : array_like, shape (P,)
    noise_std : array_like, shape (m,)
        Measurement-noise σ of the model's output channels.
    x0, P0 : ndarray, shapes (n,), (n, n)
        Prior state and covariance at the first sample.
    process_noise_std : float
        √q on the default noise rows (wake inflow, or the flap rates), white-noise model.

    """

    def __init__(self, model, p, noise_std, x0, P0, process_noise_std=0.0):
        self.model = model
        self.p = np.asarray(p, dtype=float)
        self.R = np.broadcast_to(np.asarray(noise_std, dtype=float)**2,
                                 (model.n_outputs,)).copy()
        self.rows = default_noise_rows(model)
        self.q = float(process_noise_std)
        self.t = None
        self.x = np.asarray(x0, dtype=float)
        self.P = np.asarray(P0, dtype=float)

    def update(self, t, inputs, y):
        """Filter the batch (t (k,), y (k, m)); return filtered x (k, n) and P (k, n, n)."""
        t = np.asarray(t, dtype=float)
        if self.t is None:
            grid = t
            dm = discretize(self.model, self.p, inputs, grid, self.rows, self.q) \
                if t.size > 1 else None
            x, P = self.x, self.P
            sub = dm
        else:
            grid = np.concatenate([[self.t], t])
            dm = discretize(self.model, self.p, inputs, grid, self.rows, self.q)
            # predict the last filtered state across the first interval (eqs 27-28)
            x = dm.Phi[0] @ self.x + dm.c[0]
            P = dm.Phi[0] @ self.P @ dm.Phi[0].T + dm.Q[0]
            sub = DiscreteModel(t=grid[1:], Phi=dm.Phi[1:], c=dm.c[1:], Q=dm.Q[1:],
                                H=dm.H[1:], d=dm.d[1:])
        if sub is None:                   # a single first sample: filter it with H, d alone
            H = self.model.output_matrix(t)
            sub = DiscreteModel(t=t, Phi=np.zeros((0,) + P.shape), c=np.zeros((0, x.size)),
                                Q=np.zeros((0,) + P.shape), H=H,
                                d=self.model.output_offset(t, self.p))
        result = kalman_filter(sub, y, x, P, self.R)
        self.t, self.x, self.P = float(t[-1]), result.x_filt[-1], result.P_filt[-1]
        return result.x_filt, result.P_filt

    def advance(self, t, inputs, y):
        """
        Filter the batch as :meth:`update` does; return the state x (n,) and P (n, n) after it.

        The live node publishes only the state after each batch, so the batch goes through the
        compiled filter scan (one call, :mod:`rotor_id.estimation.kernels`) when it is loaded;
        its covariance update is P − K B Kᵀ where :func:`kalman_filter` takes the Joseph form
        (equal to rounding). Without the compiled kernels this is :meth:`update`.
        """
        scan = kernels.filter_kernel()
        t = np.asarray(t, dtype=float)
        if scan is None or self.t is None:          # the first batch: the library's filter
            x, P = self.update(t, inputs, y)
            return x[-1], P[-1]
        grid = np.concatenate([[self.t], t])
        dm = discretize(self.model, self.p, inputs, grid, self.rows, self.q)
        # predict the last filtered state across the first interval (eqs 27-28)
        x = dm.Phi[0] @ self.x + dm.c[0]
        P = dm.Phi[0] @ self.P @ dm.Phi[0].T + dm.Q[0]
        T, m, n = t.size, y.shape[1], x.size
        x_last, P_last = np.empty((1, n)), np.empty((1, n, n))
        # (the scan takes its inputs C-contiguous and writable, copying views as needed)
        scan(dm.Phi[1:, None], dm.c[1:, None], dm.Q[1:, None], dm.H[1:, None], dm.d[1:, None],
             y, x[None], np.diag(self.R)[None], P[None], False, np.empty((1, T, m)),
             np.empty((1, T, m, m)), np.empty((1, T, n, m)), np.empty(1), x_last, P_last)
        self.t, self.x, self.P = float(t[-1]), x_last[0], P_last[0]
        return self.x, self.P


# ------------------------------------------------------------------------------ sample checks
class BadSample(ValueError):
    """A received sample was rejected; ``kind`` is the diagnostics counter it goes to."""

    def __init__(self, kind, message):
        super().__init__(message)
        self.kind = kind


#: Diagnostics counters of rejected samples, in the order they are reported.
BAD_KINDS = ('non_finite', 'wrong_names', 'wrong_count', 'degrees', 'out_of_order', 'duplicate',
             'bad_speed')


def check_joint_sample(names, position, expected, stamp_ns, last_stamp_ns,
                       max_abs_rad=None, extra_joints=False):
    """
    Validate one JointState sample and return its positions in the order of ``expected``.

    Parameters
    ----------
    names, position : sequence
        The message's joint names and positions.
    expected : sequence of str
        The joints wanted (e.g. blade_1..blade_N).
    extra_joints : bool
        Whether the message may carry other joints too (a sensor topic such as a rig's
        joint_states: only the wanted ones are read); False: other joints are a wrong count
        (a command must name exactly the joints it drives).
    stamp_ns, last_stamp_ns : int
        This message's header.stamp and the last accepted one (None for the first).
    max_abs_rad : float, optional
        Largest plausible |angle|: a larger value is taken for degrees.

    Raises
    ------
    BadSample

    """
    names = list(names)
    position = np.asarray(position, dtype=float)
    if (position.size != len(names) or len(names) < len(expected)
            or (not extra_joints and len(names) != len(expected))):
        raise BadSample('wrong_count', f'{len(names)} names and {position.size} positions, '
                        f'expected {len(expected)} ({", ".join(expected)})')
    try:
        order = [names.index(n) for n in expected]
    except ValueError:
        raise BadSample('wrong_names', f'joint names {names}, expected {list(expected)}') from None
    values = position[order]
    if not np.all(np.isfinite(values)):
        raise BadSample('non_finite', f'non-finite position {values.tolist()}')
    if max_abs_rad is not None and np.any(np.abs(values) > max_abs_rad):
        raise BadSample('degrees', f'|angle| {np.max(np.abs(values)):.4g} above {max_abs_rad} '
                        'rad: degrees sent where radians are expected?')
    if last_stamp_ns is not None:
        if stamp_ns == last_stamp_ns:
            raise BadSample('duplicate', f'stamp {stamp_ns} ns repeated')
        if stamp_ns < last_stamp_ns:
            raise BadSample('out_of_order', f'stamp {stamp_ns} ns before the previous '
                            f'{last_stamp_ns} ns')
    return values


def check_azimuth_sample(names, position, velocity, joint, stamp_ns, last_stamp_ns,
                         convention='wrapped'):
    """
    Validate one azimuth sample; return (ψ in [0, 2π), Ω > 0). Raises BadSample.

    ``convention`` is the run description's azimuth_convention: 'wrapped' positions must lie in
    [0, 2π) or, as many encoders give them, [-π, π) (else: degrees?); both, and 'unwrapped'
    ones, are returned wrapped to [0, 2π).
    """
    psi = check_joint_sample(names, position, [joint], stamp_ns, last_stamp_ns,
                             extra_joints=True)[0]
    velocity = np.asarray(velocity, dtype=float)
    names = list(names)
    if velocity.size != len(names):
        raise BadSample('bad_speed', f'rotor speed (velocity) {velocity.tolist()} is not one '
                        f'value per joint ({len(names)})')
    velocity = velocity[names.index(joint):][:1]
    if not np.isfinite(velocity[0]):
        raise BadSample('bad_speed', f'rotor speed (velocity) {velocity.tolist()} is not one '
                        'finite value')
    if convention == 'unwrapped':
        psi = wrap_azimuth(psi)
    elif -math.pi <= psi < 0.0:                 # an encoder's [-π, π)
        psi = wrap_azimuth(psi)
    elif not 0.0 <= psi < TWO_PI + 1e-9:
        raise BadSample('degrees', f'azimuth {psi:.4g} rad outside [0, 2π) and [-π, π): '
                        'degrees?')
    if not velocity[0] > 0:
        raise BadSample('bad_speed', f'rotor speed {velocity[0]:.4g} rad/s is not positive')
    return psi, float(velocity[0])


def _batch_values(names, positions, expected, n, max_abs_rad=None, extra_joints=False):
    """Positions (n, len(expected)) in the order of ``expected``, and which pass the checks."""
    names = list(names)
    positions = np.asarray(positions, dtype=float).reshape(n, -1)
    if ((len(names) != len(expected) and not extra_joints) or positions.shape[1] != len(names)
            or not set(expected) <= set(names)):
        return np.full((n, len(expected)), np.nan), np.zeros(n, dtype=bool)
    values = positions[:, [names.index(j) for j in expected]]
    passing = np.isfinite(values).all(axis=1)
    if max_abs_rad is not None:
        passing &= (np.abs(values) <= max_abs_rad).all(axis=1)
    return values, passing


def _in_stamp_order(stamps, passing, last_stamp_ns):
    """
    Which of the ``passing`` samples are stamped after the last accepted one, taken in order.

    A passing sample refused for its stamp is not later than an accepted one, so it changes no
    running maximum: the maximum over the passing samples is the one over the accepted ones.
    """
    floor = np.iinfo(np.int64).min if last_stamp_ns is None else int(last_stamp_ns)
    running = np.maximum.accumulate(np.where(passing, stamps, floor))
    before = np.concatenate([[floor], np.maximum(running[:-1], floor)])
    return passing & (stamps > before)


def check_joint_batch(names, positions, expected, stamps_ns, last_stamp_ns,
                      max_abs_rad=None, extra_joints=False):
    """
    Validate many samples of one joint layout at once; return (values, accepted).

    ``values`` (n, len(expected)) are the positions in the order of ``expected``; ``accepted``
    (n,) says which samples :func:`check_joint_sample`, applied to them one after the other
    (each accepted stamp becoming the last one), would accept. Why one is rejected is that
    function's answer for it (call it on that sample).
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    values, passing = _batch_values(names, positions, expected, stamps.size, max_abs_rad,
                                    extra_joints)
    return values, _in_stamp_order(stamps, passing, last_stamp_ns)


def check_azimuth_batch(names, positions, velocities, joint, stamps_ns, last_stamp_ns,
                        convention='wrapped'):
    """
    :func:`check_azimuth_sample` of many samples of one layout; return (ψ, Ω, accepted).

    ``velocities`` (n, k), NaN where a message sent none; ψ in [0, 2π) and Ω > 0 where
    accepted. Why one is rejected is :func:`check_azimuth_sample`'s answer for it.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    psi, passing = _batch_values(names, positions, [joint], stamps.size, extra_joints=True)
    psi = psi[:, 0]
    velocities = np.asarray(velocities, dtype=float).reshape(stamps.size, -1)
    names = list(names)
    if velocities.shape[1] != len(names) or joint not in names:
        return psi, np.full(stamps.size, np.nan), np.zeros(stamps.size, dtype=bool)
    omega = velocities[:, names.index(joint)]
    with np.errstate(invalid='ignore'):
        if convention == 'unwrapped':
            psi = wrap_azimuth(psi)
        else:                                    # [0, 2π), or an encoder's [-π, π)
            passing &= (psi >= -math.pi) & (psi < TWO_PI + 1e-9)
            psi = np.where(psi < 0.0, wrap_azimuth(psi), psi)
        passing &= np.isfinite(omega) & (omega > 0)
    return psi, omega, _in_stamp_order(stamps, passing, last_stamp_ns)


# ------------------------------------------------------------------------------ buffers
class StampedSeries:
    """
    (stamp_ns, values) arrays of one topic, in arrival (= stamp) order, optionally bounded.

    ``append(..., keep_from_ns)`` first forgets the samples stamped before ``keep_from_ns`` when
    the arrays are full, and grows them only when that frees less than a quarter: the memory
    follows the span the caller needs (a window), not the length of the run.
    """

    def __init__(self, width, capacity=1024):
        self.width = width
        self._stamps = np.empty(capacity, dtype=np.int64)
        self._values = np.empty((capacity, width))
        self.size = 0

    def append(self, stamp_ns, values, keep_from_ns=None):
        """Add one accepted sample (forgetting those before ``keep_from_ns`` if full)."""
        if self.size == self._stamps.size:
            if keep_from_ns is not None:
                self.drop_before(keep_from_ns)
            if self.size > 0.75 * self._stamps.size:
                self._stamps = np.concatenate([self._stamps, np.empty_like(self._stamps)])
                self._values = np.concatenate([self._values, np.empty_like(self._values)])
        self._stamps[self.size] = stamp_ns
        self._values[self.size] = values
        self.size += 1

    def extend(self, stamps_ns, values, keep_from_ns=None):
        """
        Add accepted samples (k,), (k, width) in stamp order, in one copy.

        As :meth:`append` of each in turn, except that, when the arrays are full, the samples
        before ``keep_from_ns`` (the one bound of the whole batch) are forgotten at once.
        """
        k = len(stamps_ns)
        if self.size + k > self._stamps.size:
            if keep_from_ns is not None:
                self.drop_before(keep_from_ns)
            capacity = self._stamps.size
            while self.size + k > 0.75 * capacity:
                capacity *= 2
            if capacity > self._stamps.size:
                stamps, vals = self._stamps, self._values
                self._stamps = np.empty(capacity, dtype=np.int64)
                self._values = np.empty((capacity, self.width))
                self._stamps[:self.size] = stamps[:self.size]
                self._values[:self.size] = vals[:self.size]
        self._stamps[self.size:self.size + k] = stamps_ns
        self._values[self.size:self.size + k] = values
        self.size += k

    def drop_before(self, stamp_ns):
        """Forget the samples stamped before ``stamp_ns``; return how many."""
        cut = int(np.searchsorted(self._stamps[:self.size], stamp_ns, side='left'))
        if cut:
            keep = self.size - cut
            self._stamps[:keep] = self._stamps[cut:self.size]
            self._values[:keep] = self._values[cut:self.size]
            self.size = keep
        return cut

    @property
    def capacity(self):
        """Return how many samples the arrays hold before they are trimmed or grown."""
        return self._stamps.size

    @property
    def last_stamp(self):
        """Stamp of the newest sample (None when empty)."""
        return int(self._stamps[self.size - 1]) if self.size else None

    @property
    def first_stamp(self):
        """Stamp of the oldest sample kept (None when empty)."""
        return int(self._stamps[0]) if self.size else None

    @property
    def stamps(self):
        """Stamps (ns), a view of the filled part."""
        return self._stamps[:self.size]

    @property
    def values(self):
        """Values (size, width), a view of the filled part."""
        return self._values[:self.size]

    def clear(self):
        """Forget every sample."""
        self.size = 0


class AzimuthTracker:
    """
    Unwrapped azimuth of blade 1 (the report's t) from wrapped samples, as they arrive.

    The unwrapping is :class:`rotor_id.io.timebase.AzimuthUnwrapper` (the rule of
    :func:`~rotor_id.io.timebase.unwrap_azimuth`, so it stays right across gaps). The first
    sample's wrapped ψ is the origin, as in a recording (t = Ω·(stamp − first) + ψ(first)).
    ``series`` holds (stamp, (ψ wrapped, Ω, ψ unwrapped)): the azimuth series that
    :func:`record_from_series` takes.
    """

    def __init__(self):
        self.series = StampedSeries(3)        # (ψ wrapped, Ω, ψ unwrapped)
        self.unwrapper = AzimuthUnwrapper()

    def add(self, stamp_ns, psi, omega, keep_from_ns=None):
        """Add one accepted sample (ψ in [0, 2π), Ω > 0); return its unwrapped ψ."""
        value = self.unwrapper.add(stamp_ns, psi, omega)
        self.series.append(stamp_ns, (psi, omega, value), keep_from_ns)
        return value

    def add_batch(self, stamps_ns, psi, omega, keep_from_ns=None):
        """Add accepted samples (k,) each, in stamp order: :meth:`add` of each, one copy."""
        unwrapped = [self.unwrapper.add(stamp, p, w)
                     for stamp, p, w in zip(stamps_ns.tolist(), psi.tolist(), omega.tolist())]
        self.series.extend(stamps_ns, np.column_stack([psi, omega, unwrapped]), keep_from_ns)

    @property
    def ready(self):
        """Say whether a sample arrived."""
        return self.series.size > 0

    def t_at(self, stamps_ns):
        """Return t at the given stamps: interpolated, or extrapolated with the last Ω."""
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        s = self.series
        last, (_, omega_last, psi_last) = s.last_stamp, s.values[-1]
        t = psi_last + omega_last * (stamps - last) / NS
        later = stamps > last
        if np.all(later):
            return t
        i0 = max(0, int(np.searchsorted(s.stamps, stamps.min())) - 1)
        ref = s.stamps[i0]
        t = np.interp((stamps - ref) / NS, (s.stamps[i0:] - ref) / NS, s.values[i0:, 2])
        t[later] = psi_last + omega_last * (stamps[later] - last) / NS
        return t

    @property
    def omega(self):
        """Latest rotor speed Ω (rad/s)."""
        return float(self.series.values[-1, 1])


def _bracket(stamps, lo, hi):
    """Index range of the stamps in [lo, hi] plus one neighbour each side (for interpolation)."""
    return (max(0, int(np.searchsorted(stamps, lo, side='left')) - 1),
            int(np.searchsorted(stamps, hi, side='right')) + 1)


def record_from_series(flap, pitch, azimuth, blade_names, stamp0_ns, source='live topics',
                       span_ns=None):
    """
    Form a Record on the flap stamps, as :func:`rotor_id.io.bag.read_record` forms it from a bag.

    Parameters
    ----------
    flap, pitch : StampedSeries
        Per-blade flap and pitch (rad).
    azimuth : StampedSeries
        ψ of blade 1 wrapped to [0, 2π), Ω (rad/s) and, in a third column, ψ unwrapped as it
        arrived (:class:`AzimuthTracker`'s series); without that column the azimuth is
        unwrapped here from its first sample.
    blade_names : list of str
        Joint of each blade column.
    stamp0_ns : int
        Origin of ``time_s`` (the first flap stamp received), so that window_s keeps its meaning.
    source : str
        Where the data came from (for messages).
    span_ns : (int, int), optional
        Keep only the flap samples stamped in this range (and the pitch and azimuth samples
        around them): the record of a window without copying the whole buffer. Needs the
        unwrapped column; the samples kept are exactly those of the whole record.

    Raises
    ------
    ValueError
        Not enough overlapping data yet.

    """
    if min(flap.size, pitch.size, azimuth.size) < 2:
        raise ValueError(f'not enough data yet: {flap.size} flap, {pitch.size} pitch and '
                         f'{azimuth.size} azimuth samples')
    lo = max(pitch.stamps[0], azimuth.stamps[0])
    hi = min(pitch.stamps[-1], azimuth.stamps[-1])
    flap_part, pitch_part, az_part = slice(None), slice(None), slice(None)
    if span_ns is not None:
        if azimuth.width < 3:
            raise ValueError('a span of the buffer needs the azimuth unwrapped as it arrived')
        lo, hi = max(lo, span_ns[0]), min(hi, span_ns[1])
        flap_part = slice(int(np.searchsorted(flap.stamps, lo, side='left')),
                          int(np.searchsorted(flap.stamps, hi, side='right')))
        pitch_part = slice(*_bracket(pitch.stamps, lo, hi))
        az_part = slice(*_bracket(azimuth.stamps, lo, hi))
    flap_stamps = flap.stamps[flap_part]
    inside = (flap_stamps >= lo) & (flap_stamps <= hi)
    if np.count_nonzero(inside) < 2:
        raise ValueError('flap, pitch and azimuth samples do not overlap in time yet')
    stamps = flap_stamps[inside]
    time_s = (stamps - stamp0_ns) / NS
    az_time = (azimuth.stamps[az_part] - stamp0_ns) / NS
    az_values = azimuth.values[az_part]
    if azimuth.width >= 3:
        psi_unwrapped = az_values[:, 2]
    else:
        psi_unwrapped = nondimensional_time(az_time, az_values[:, 0], az_values[:, 1])
    return Record(time_s=time_s, t=np.interp(time_s, az_time, psi_unwrapped),
                  rotor_speed_rad_s=np.interp(time_s, az_time, az_values[:, 1]),
                  blade_flap=flap.values[flap_part][inside].copy(),
                  blade_pitch=interpolate_columns(
                      time_s, (pitch.stamps[pitch_part] - stamp0_ns) / NS,
                      pitch.values[pitch_part]),
                  blade_names=list(blade_names), source=source, stamp0_ns=int(stamp0_ns))


# ------------------------------------------------------------------------------ Ch.3 verdict
def bound_history(identification):
    """
    Cramér-Rao σ of the unknowns for every record end t_f of the window (Ch.3 eq. 19).

    Evaluated at the estimate with its estimated noise, marginal over each run's initial states
    (runs combined by adding their marginal information). Returns (t (T,), std (T, k)).
    """
    est = identification.estimate
    unknowns = list(identification.unknowns)
    k = len(unknowns)
    p_full = identification.model.parameter_vector(
        dict(est.model_parameters))
    blocks = []
    t = None
    for r, exp in enumerate(identification.experiments):
        hist = information_history(exp, p_full, unknowns, noise_std=est.noise_std,
                                   x0=est.initial_states[r])
        blocks.append(hist.covariance[:, :k, :k])
        t = hist.t
    if len(blocks) == 1:
        # one run: its marginal covariance block is the answer (pinv(pinv(B)) = B; the two
        # batched pseudo-inverses were a third of the live final's verdict CPU)
        cov = blocks[0]
    else:
        info = None
        for block in blocks:
            marginal = np.full_like(block, np.nan)
            good = np.all(np.isfinite(block), axis=(1, 2))
            if np.any(good):
                marginal[good] = np.linalg.pinv(block[good])
            info = marginal if info is None else info + marginal
        cov = np.full_like(info, np.nan)
        good = np.all(np.isfinite(info), axis=(1, 2))
        if np.any(good):
            cov[good] = np.linalg.pinv(info[good])
    std = np.full((t.size, k), np.nan)
    good = np.all(np.isfinite(cov), axis=(1, 2))
    if np.any(good):
        std[good] = np.sqrt(np.clip(np.einsum('tii->ti', cov[good]), 0, None))
    return t, std


def data_length_verdict(std_now, target_std, t=None, std_history=None, omega_rad_s=None):
    """
    Has each bound reached its target (Ch.3 eq. 23), else how much more data is needed.

    The extrapolation fits σ²(t_f) ∝ (t_f − t_0)^b to the second half of the bound history
    (b ≈ −1 once the transient's information rate is steady; steeper early on) and solves for
    the record end at which the slowest parameter meets its target.

    Parameters
    ----------
    std_now : array_like, shape (k,)
        Current Cramér-Rao σ of the unknowns.
    target_std : array_like, shape (k,)
        Target σ per unknown; 0 or negative = no target.
    t, std_history : ndarray, shapes (T,), (T, k), optional
        Bound history over the window (from :func:`bound_history`).
    omega_rad_s : float, optional
        Rotor speed, to turn nondimensional time into seconds.

    Returns
    -------
    (target_met, additional_data_s): additional_data_s is 0 when met, −1 when unknown.

    """
    std_now = np.asarray(std_now, dtype=float)
    target = np.broadcast_to(np.asarray(target_std, dtype=float), std_now.shape)
    active = target > 0
    if not np.any(active):
        return True, 0.0
    if np.all(std_now[active] <= target[active]):
        return True, 0.0
    if t is None or std_history is None or not omega_rad_s:
        return False, -1.0
    span = t - t[0]
    need = 0.0
    for i in np.flatnonzero(active & (std_now > target)):
        ok = np.isfinite(std_history[:, i]) & (span > 0)
        idx = np.flatnonzero(ok)
        idx = idx[idx.size // 2:]
        if idx.size < 3:
            return False, -1.0
        slope, intercept = np.polyfit(np.log(span[idx]), np.log(std_history[idx, i]**2), 1)
        if not slope < -0.05:
            return False, -1.0
        span_needed = math.exp((math.log(target[i]**2) - intercept) / slope)
        need = max(need, span_needed - span[-1])
    return False, max(need, 0.0) / omega_rad_s
