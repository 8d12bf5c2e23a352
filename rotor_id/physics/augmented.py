"""
The catalogue of candidate physics: each an augmented model built from the baseline.

Every augmentation is a :class:`~rotor_id.physics.models.LinearModel` that wraps the baseline
model, adds states, parameters, inputs or output offsets, and gives analytic derivatives of all
of them, so that :func:`rotor_id.estimation.output_error.fit_output_error` fits it and gives its
Cramér-Rao bounds unchanged. Augmented models measure the baseline's channels, so likelihoods
compare on the same data.

The link between a model's states and the blades is :class:`BladeView`: per blade k the flap
β_k = Hb x, the flap rate β_k′ = Hbr x, the inflow angle λ_k = Hl x (wake model), and the map C
from blade values to the model's output channels (y = C·[β_1..β_N], e.g. report eq. 30 or the
multiblade transform, docs/models.md §0). Extra inputs (measured pitch rates, measured flap for the
cubic spring) ride in extra columns of u after the report's [θ0, θI, θII].

Beyond the catalogue, :class:`LibraryTerm` adds one term of a small library (flap, flap rate,
measured pitch or a constant, each alone or times cos ψ_k or sin ψ_k) to every blade's flap
equation: the models of the out-of-catalogue search (:mod:`rotor_id.estimation.term_search`).
"""

import copy
from dataclasses import replace
import math
from typing import Any, Mapping, Sequence

import numpy as np
import numpy.typing as npt

from rotor_id.physics.aerodynamics import (blade_aerodynamics, flap_damping,
                                           lock_number_from_damping)
from rotor_id.physics.models import (compact, CYCLIC_INFLOW, full_along_time, LinearModel,
                                     Multiblade, Parameter, RotorModel, via_compact)
from rotor_id.physics.multiblade import azimuth_offset_matrix, coordinate_names
from rotor_id.physics.stirring import blade_pitch_from_multiblade, multiblade_from_blade_pitch

#: a rotor model (:class:`~rotor_id.physics.models.RotorModel`) or one of the augmented models
#: wrapping it: both carry the rotor's attributes (rotor, blades, collective, outputs, ...)
#: beyond the LinearModel interface
RotorLike = Any


# ------------------------------------------------------------------------------------------------
# Blades as seen from a model's states
# ------------------------------------------------------------------------------------------------

class BladeView:
    """
    Per-blade flap, flap rate and inflow of a baseline model's state (see module docstring).

    The transform belongs to the model (:class:`~rotor_id.physics.models.RotorModel`, any N):
    this view only names its matrices for the augmentations. Over an augmented model the
    blades are the root model's states, which come first in the state vector; the inner
    augmentations' extra states get zero columns, and a channel subset picks its rows.
    """

    def __init__(self, model: RotorLike) -> None:
        self.n_states = model.n_states
        self.n_outputs = model.n_outputs
        rows = None
        while isinstance(model, (Augmented, ChannelSubset)):
            if isinstance(model, ChannelSubset):
                rows = list(model.rows) if rows is None else [model.rows[i] for i in rows]
                model = model.inner
            else:
                model = model.base
        self._rows = rows
        self.model = model
        self.kind = model.name
        self.blades = tuple(model.blades)
        self.n_blades = len(self.blades)
        #: the blades' values are periodic in ψ (a rotor in multiblade coordinates): a term of
        #: one blade apart from the others makes F or g periodic even in hover
        self.rotating = model.blade is None and self.n_blades > 1

    def azimuth(self, t: npt.ArrayLike) -> np.ndarray:
        """Return every blade's azimuth ψ_k at times t (T, N), as the model defines it."""
        return self.model.blade_azimuth(t)

    def _columns(self, H):
        out = np.zeros(H.shape[:2] + (self.n_states,))
        out[:, :, :H.shape[2]] = H
        return out

    def flap(self, t: npt.ArrayLike) -> np.ndarray:
        """Hb (T, N, n): β_k = Hb x."""
        return self._columns(self.model.blade_flap_matrix(t))

    def flap_rate(self, t: npt.ArrayLike) -> np.ndarray:
        """Hbr (T, N, n): β_k′ = Hbr x (rates are states, so no input enters)."""
        return self._columns(self.model.blade_flap_rate_matrix(t))

    def inflow(self, t: npt.ArrayLike) -> np.ndarray:
        """Return Hl (T, N, n): the wake's inflow angle λ_k = λI cos ψ_k + λII sin ψ_k."""
        return self._columns(self.model.blade_inflow_matrix(t))

    def channels(self, t: npt.ArrayLike) -> np.ndarray:
        """C (T, m, N): the model's output channels from the modelled blades' values."""
        C = self.model.channel_matrix(t)[:, :, [k - 1 for k in self.blades]]
        return C if self._rows is None else C[:, self._rows]

    def force(self, t: npt.ArrayLike) -> np.ndarray:
        """G (T, n, N): change of x′ for a unit flapping acceleration of blade k alone."""
        G = self.model.blade_force_matrix(t)
        out = np.zeros((G.shape[0], self.n_states, G.shape[2]))
        out[:, :G.shape[1]] = G
        return out


# ------------------------------------------------------------------------------------------------
# Base class
# ------------------------------------------------------------------------------------------------

class Augmented(LinearModel):
    """
    Baseline model plus extra states (appended to x) and extra parameters (appended to p).

    Subclasses fill the extra blocks in :meth:`_extra` and :meth:`_extra_jacobian`. The
    baseline's equations are kept: rows of the baseline states get the baseline F and g plus
    whatever the augmentation adds.
    """

    effect = 'augmented'
    extra_parameters: tuple[Parameter, ...] = ()
    extra_states: tuple[str, ...] = ()
    #: extra states whose initial value is estimated when the baseline's are
    free_extra_states: tuple[str, ...] = ()
    #: columns of u beyond [θ0, θI, θII] the augmentation needs (see ExtendedInput)
    extra_inputs: tuple[str, ...] = ()
    #: F or g carries terms of single blades (not the same for every blade), which the
    #: multiblade transform makes periodic in ψ (:attr:`BladeView.rotating`)
    per_blade_terms: bool = False

    def __init__(self, base: RotorLike) -> None:
        self.base = base
        self.view = BladeView(base)
        self.rotor = base.rotor
        self.name = f'{base.name}+{self.effect}'
        self.parameters = tuple(base.parameters) + tuple(self.extra_parameters)
        self.state_names = tuple(base.state_names) + tuple(self.extra_states)
        self.output_names = base.output_names
        self.time_invariant = base.time_invariant and not self.extra_inputs and not (
            self.per_blade_terms and self.view.rotating)
        #: columns of u the base model reads: [θ0, θI, θII] and every inner extra input
        self.n_base_inputs = 3 + len(getattr(base, 'all_extra_inputs', ()))
        self.all_extra_inputs = tuple(getattr(base, 'all_extra_inputs', ())) + \
            tuple(self.extra_inputs)

    def own_inputs(self, u: npt.ArrayLike) -> np.ndarray:
        """Return [θ0, θI, θII, this augmentation's extra inputs] out of the full u."""
        u = np.asarray(u, dtype=float)
        if self.n_base_inputs == 3:
            return u
        return np.concatenate([u[:, :3], u[:, self.n_base_inputs:]], axis=1)

    def base_inputs(self, u: npt.ArrayLike, pitch: np.ndarray | None = None) -> np.ndarray:
        """Return the columns of u the base reads, optionally with [θ0, θI, θII] replaced."""
        u = np.asarray(u, dtype=float)[:, :self.n_base_inputs]
        if pitch is None:
            return u
        return np.concatenate([pitch, u[:, 3:]], axis=1)

    @property
    def effects(self) -> tuple[str, ...]:
        """Return the effects of this model from the innermost to this one."""
        inner = getattr(self.base, 'effects', ())
        return tuple(inner) + (self.effect,)

    @property
    def n_base_states(self) -> int:
        """Return the number of the baseline's states."""
        return self.base.n_states

    @property
    def n_base_parameters(self) -> int:
        """Return the number of the baseline's parameters."""
        return len(self.base.parameters)

    #: extra-parameter bounds that are physics, not a catalogue range: {name: ('lower',...)}
    #: (a fit stopping there has found the physical limit, e.g. no wake gain, and competes on
    #: its likelihood); every other bound is a range the catalogue chose and is widened
    physical_bounds: dict[str, tuple[str, ...]] = {}

    def with_bounds(self, bounds: Mapping[str, tuple[float, float]]) -> 'Augmented':
        """Replace extra-parameter bounds {name: (lower, upper)} (a widened catalogue range)."""
        self.extra_parameters = tuple(
            replace(par, lower=float(bounds[par.name][0]), upper=float(bounds[par.name][1]))
            if par.name in bounds else par for par in self.extra_parameters)
        self.parameters = tuple(self.base.parameters) + tuple(self.extra_parameters)
        return self

    def widened(self, name: str, side: str) -> tuple[float, float] | None:
        """
        Return (lower, upper) of extra parameter ``name`` widened on ``side``, or None.

        None when that side is a physical bound. The range is doubled on the side the fit
        stopped at.
        """
        if side in self.physical_bounds.get(name, ()):
            return None
        par = self.parameter(name)
        span = par.upper - par.lower
        if side == 'lower':
            return par.lower - span, par.upper
        return par.lower, par.upper + span

    def _split(self, p):
        p = np.asarray(p, dtype=float)
        return p[:self.n_base_parameters], p[self.n_base_parameters:]

    def constant_terms(self) -> bool:
        """
        Tell whether this layer's own F and ∂F terms are the same at every time.

        Then, over a base whose F is constant, :meth:`system_compact` keeps F of length 1
        along time (the layer's ``_extra`` adds arrays of length 1 there). Default: no.
        """
        return False

    @via_compact
    def system(self, t: npt.ArrayLike, p: np.ndarray,
               u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """F and g: the baseline's, with the augmentation's blocks added."""
        F, g = self.system_compact(t, p, u)
        return full_along_time(F, g.shape[0]), g

    @via_compact
    def system_jacobian(self, t: npt.ArrayLike, p: np.ndarray,
                        u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """∂F/∂p and ∂g/∂p: the baseline's, with the augmentation's blocks added."""
        dF, dg = self.system_jacobian_compact(t, p, u)
        return full_along_time(dF, dg.shape[0]), dg

    def system_compact(self, t: npt.ArrayLike, p: np.ndarray,
                       u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`system`, F of length 1 along time where it is constant (:func:`compact`)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        u = np.asarray(u, dtype=float)
        pb, pe = self._split(p)
        Fb, gb = compact(self.base, 'system', t, pb, self.base_inputs(u))
        n, nb = self.n_states, self.n_base_states
        F = np.zeros((Fb.shape[0] if self.constant_terms() else t.size, n, n))
        F[:, :nb, :nb] = Fb
        g = np.zeros((t.size, n))
        g[:, :nb] = gb
        self._u_full = u                # for augmentations that call the base (_pitch_gain)
        self._extra(t, pb, pe, self.own_inputs(u), F, g)
        return F, g

    def system_jacobian_compact(self, t: npt.ArrayLike, p: np.ndarray,
                                u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`system_jacobian`, ∂F/∂p of length 1 along time where F is constant."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        u = np.asarray(u, dtype=float)
        pb, pe = self._split(p)
        dFb, dgb = compact(self.base, 'system_jacobian', t, pb, self.base_inputs(u))
        n, nb, P, Pb = self.n_states, self.n_base_states, len(self.parameters), len(pb)
        dF = np.zeros((dFb.shape[0] if self.constant_terms() else t.size, P, n, n))
        dF[:, :Pb, :nb, :nb] = dFb
        dg = np.zeros((t.size, P, n))
        dg[:, :Pb, :nb] = dgb
        self._u_full = u
        self._extra_jacobian(t, pb, pe, self.own_inputs(u), dF, dg)
        return dF, dg

    def _extra(self, t, pb, pe, u, F, g):
        """Add the augmentation's terms to F (T, n, n) and g (T, n) in place."""

    def _extra_jacobian(self, t, pb, pe, u, dF, dg):
        """Add the augmentation's derivative terms in place."""

    def output_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """H: the baseline's, zero on extra states unless a subclass says otherwise."""
        Hb = self.base.output_matrix(t)
        H = np.zeros((Hb.shape[0], Hb.shape[1], self.n_states))
        H[:, :, :self.n_base_states] = Hb
        return H

    def output_offset(self, t: npt.ArrayLike, p: np.ndarray) -> np.ndarray:
        """Return the baseline's output offset (no baseline has one)."""
        pb, _ = self._split(p)
        return self.base.output_offset(t, pb)

    def output_offset_jacobian(self, t: npt.ArrayLike, p: np.ndarray) -> np.ndarray:
        """∂d/∂p, zero for the extra parameters unless a subclass says otherwise."""
        pb, _ = self._split(p)
        d = self.base.output_offset_jacobian(t, pb)
        out = np.zeros((d.shape[0], d.shape[1], len(self.parameters)))
        out[:, :, :d.shape[2]] = d
        return out

    def observe_blades(self, t: npt.ArrayLike, blade_flap: npt.ArrayLike) -> np.ndarray:
        """Return the baseline's channels."""
        return self.base.observe_blades(t, blade_flap)

    def equilibrium(self, t: npt.ArrayLike, p: np.ndarray, u: npt.ArrayLike) -> np.ndarray:
        """Steady state for a held input (extra inputs held at their first value)."""
        return super().equilibrium(t, p, u)

    def report_parameters(self, values: np.ndarray,
                          cov: np.ndarray) -> dict[str, tuple[float, float]]:
        """
        Physical extra parameters {name: (value, std)} from the fitted extra parameters.

        ``values``/``cov``: the extra parameters' estimates and covariance, plus the baseline
        parameters ahead of them (full model parameter vector order).
        """
        names = [par.name for par in self.extra_parameters]
        k = self.n_base_parameters
        return {n: (float(values[k + i]), float(math.sqrt(max(cov[k + i, k + i], 0.0))))
                for i, n in enumerate(names)}


def _gamma_index(base):
    names = base.parameter_names
    return names.index('gamma') if 'gamma' in names else None


# ------------------------------------------------------------------------------------------------
# The catalogue
# ------------------------------------------------------------------------------------------------

class SensorLag(Augmented):
    """
    First-order lag of every flap sensor, time constant τ_s (``lag_rad``, rad of azimuth).

    The sensor reads z_k with τ_s z_k′ = β_k − z_k. With the lag error e_k = z_k − β_k
    (zero when the sensor has settled, as in trim at the start of a record):

        e_k′ = −e_k/τ_s − β_k′ = −e_k/τ_s − Hbr_k x,      y = H x + C e

    Where the model's flap is a constant combination of azimuth functions, β_k = Hb_k(t) q
    with Hb_k′ = Hb_k A and β_k′ = Hb_k(t) W x for constant A, W (the multiblade coordinates
    of identical blades), the errors are carried in the same coordinates, e_k = Hb_k(t) E:

        E′ = −(A + I/τ_s) E − W x,      y = H x + C Hb(t) E

    a time-invariant block over a time-invariant rotor (hover), where the blade form is
    periodic through Hbr_k(t). Both are the same model; the blade form is kept for a flap
    that is not such a combination.
    """

    effect = 'sensor_lag'
    extra_parameters = (Parameter('lag_rad', 'τ_s', 'rad', 0.1, 0.03, 3.0,
                                  'flap-sensor first-order time constant, rad of azimuth'),)
    #: RK4 step that keeps the fastest admissible lag (τ_s = 0.03) stable (|hλ| < 2.78)
    max_step = 0.05
    #: RK4 steps per unit of the smallest admissible τ_s (0.05 at 0.03, |hλ| = 1.67)
    STEP_PER_LAG = 0.05 / 0.03
    #: smallest τ_s the widening goes to. Below it the lag is the delay d = τ_s to first order
    #: (they differ by τ_s²β″/2, under the noise at these sizes) and ``time_delay``, nested at
    #: d = 0 and without a stiff state, measures it; a smaller τ_s would need RK4 steps of
    #: 1.7 τ_s on a time-varying 10-state model (3× the cost per third of τ_s). So a lag fit
    #: stopped here is reported bound-limited, not widened.
    SMALLEST_LAG = 0.03

    def widened(self, name: str, side: str) -> tuple[float, float] | None:
        """Return the upper bound doubled; None at the lower (see :data:`SMALLEST_LAG`)."""
        par = self.parameter(name)
        if side == 'lower':
            if par.lower <= self.SMALLEST_LAG * 1.0001:
                return None
            return max(par.lower / 3.0, self.SMALLEST_LAG), par.upper
        return par.lower, 2.0 * par.upper

    def step(self) -> float:
        """Return the longest stable RK4 step for the smallest admissible τ_s."""
        return self.STEP_PER_LAG * self.parameter('lag_rad').lower

    def __init__(self, base: RotorLike) -> None:
        view = BladeView(base)
        self._basis = flap_basis(view)
        if self._basis is None:
            self.extra_states = tuple(f'lag_error_{k}' for k in view.blades)
        else:
            self.extra_states = tuple(f'lag_error_{base.state_names[j]}'
                                      for j in self._basis[0])
        super().__init__(base)

    def constant_terms(self) -> bool:
        """Tell whether the errors are in the flap's coordinates (then the block is constant)."""
        return self._basis is not None

    def _extra(self, t, pb, pe, u, F, g):
        nb = self.n_base_states
        if self._basis is None:
            F[:, nb:, :nb] = -self.view.flap_rate(t)
            F[:, nb:, nb:] = -np.eye(self.n_states - nb) / pe[0]
            return
        _, A, W = self._basis
        F[:, nb:, :nb] = -W
        F[:, nb:, nb:] = -A - np.eye(A.shape[0]) / pe[0]

    def _extra_jacobian(self, t, pb, pe, u, dF, dg):
        nb = self.n_base_states
        dF[:, -1, nb:, nb:] = np.eye(self.n_states - nb) / pe[0]**2

    def output_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """Return H of y = H x + C e (C Hb(t) E in the flap's coordinates)."""
        H = super().output_matrix(t)
        C = self.view.channels(t)
        if self._basis is None:
            H[:, :, self.n_base_states:] = C
        else:
            H[:, :, self.n_base_states:] = C @ self.view.flap(t)[:, :, self._basis[0]]
        return H


#: azimuths (rad) at which a flap basis is checked to be one constant combination
_BASIS_PROBES = np.array([0.0, 0.4137, 1.9071, 4.4402])


def flap_basis(view: 'BladeView') -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """
    Return (q, A, W) of β_k = Hb_k(t) x[q] with Hb′ = Hb A and β_k′ = Hb W x, or None.

    q: the state columns the blades' flap reads; A (|q|, |q|) and W (|q|, n) constant. For
    the multiblade coordinates of identical blades they exist (cos/sin of ψ_k differentiate
    into each other); None where Hb(t) is not of full column rank or no constant A, W
    reproduce the model's Hb′ and Hbr at every probe azimuth.
    """
    Hb, Hbr = view.flap(_BASIS_PROBES), view.flap_rate(_BASIS_PROBES)
    q = np.flatnonzero(np.any(Hb != 0.0, axis=(0, 1)))
    B = Hb[:, :, q]
    if q.size == 0 or q.size > B.shape[1] or any(
            np.linalg.matrix_rank(b) < q.size for b in B):
        return None
    W = np.linalg.lstsq(B[0], Hbr[0], rcond=None)[0]
    # β′ = Hb′ q + Hb q′: W's columns on q are A, checked against a central difference of Hb
    A = W[:, q]
    h = 1e-5
    dB = (view.flap(_BASIS_PROBES + h)[:, :, q] - view.flap(_BASIS_PROBES - h)[:, :, q]) / (2 * h)
    scale = max(float(np.abs(Hbr).max()), 1.0)
    if (np.abs(B @ W - Hbr).max() > 1e-10 * scale
            or np.abs(B @ A - dB).max() > 1e-6 * scale):
        return None
    return q, A, W


class PitchDelay(Augmented):
    """
    The blades' pitch reaching the rotor d (``pitch_delay_rad``, rad) after it is measured.

    Each blade flaps in response to θ_k(t − d). In multiblade pitch that is a shift and a
    rotation by d:

        θI_d = θI(t−d) cos d − θII(t−d) sin d,   θII_d = θII(t−d) cos d + θI(t−d) sin d,
        θ(t−d) ≈ θ(t) − d θ′(t)   (θ′: measured pitch rate, extra inputs)

    and g is the baseline's g at that pitch. No extra states. It is the first-order
    equivalent of a pitch-actuator lag τ_a = d at any advance ratio (the lag's score test is
    taken here, at d = 0); in hover, where the rotor is axisymmetric, it is also exactly the
    flap read d late (:class:`TimeDelay`).
    """

    effect = 'pitch_delay'
    extra_parameters = (Parameter('pitch_delay_rad', 'd_θ', 'rad', 0.0, -0.6, 0.6,
                                  'blade pitch later than measured, rad of azimuth'),)
    extra_inputs = ('theta_0_rate', 'theta_I_rate', 'theta_II_rate')

    @staticmethod
    def _shifted(u, d):
        th_i = u[:, 1] - d * u[:, 4]
        th_ii = u[:, 2] - d * u[:, 5]
        c, s = math.cos(d), math.sin(d)
        out = u[:, :3].copy()
        out[:, 1] = th_i * c - th_ii * s
        out[:, 2] = th_ii * c + th_i * s
        dout = np.zeros_like(out)
        dout[:, 1] = -u[:, 4] * c - th_i * s + u[:, 5] * s - th_ii * c
        dout[:, 2] = -u[:, 5] * c - th_ii * s - u[:, 4] * s + th_i * c
        return out, dout

    def system(self, t: npt.ArrayLike, p: np.ndarray,
               u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Baseline F, g at the delayed, rotated pitch."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        u = np.asarray(u, dtype=float)
        pb, pe = self._split(p)
        us, _ = self._shifted(self.own_inputs(u), pe[0])
        return self.base.system(t, pb, self.base_inputs(u, us))

    def system_jacobian(self, t: npt.ArrayLike, p: np.ndarray,
                        u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Baseline derivatives at the delayed pitch, and ∂g/∂d = G ∂u/∂d (g affine in u)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        u = np.asarray(u, dtype=float)
        pb, pe = self._split(p)
        us, dus = self._shifted(self.own_inputs(u), pe[0])
        dFb, dgb = self.base.system_jacobian(t, pb, self.base_inputs(u, us))
        T, Pb, n = dgb.shape
        dF = np.zeros((T, Pb + 1, n, n))
        dF[:, :Pb] = dFb
        dg = np.zeros((T, Pb + 1, n))
        dg[:, :Pb] = dgb
        _, g_du = self.base.system(t, pb, self.base_inputs(u, dus))
        _, g_0 = self.base.system(t, pb, self.base_inputs(u, np.zeros_like(us)))
        dg[:, Pb] = g_du - g_0
        return dF, dg


def observable_basis(gram: np.ndarray) -> np.ndarray:
    """Orthonormal directions of a Gram matrix the record can see (eigenvalues above 1e-8)."""
    vals, vecs = np.linalg.eigh(gram)
    return vecs[:, vals > 1e-8 * max(vals.max(), 1e-300)]


class SensorBias(Augmented):
    """
    Constant flap-sensor offsets b_k per blade: y = H x + C(t) b.

    Only the bias patterns the channels can see and the collective pitch does not absorb are
    parameters: b = V c with V an orthonormal basis of the observable patterns (e.g.
    (β1−β3)/2 and (β2−β4)/2 channels see b1−b3 and b2−b4 only). The common offset of all
    blades (the collective pattern) moves β0 alone. In hover a fitted collective pitch
    absorbs it exactly (θ0 only sets the coning there), so it is left out when
    ``collective_fitted`` and μ = 0. In forward flight θ0 also drives the once-per-rev flap
    (the μ terms of the flap moment), so a common offset is a bias of its own there, as it
    is whenever the collective is known; left out, it would bias θ0 and let a pitch-flap
    coupling take its place. The report gives b.
    """

    effect = 'sensor_bias'

    def __init__(self, base: RotorLike, t_window: npt.ArrayLike,
                 collective_fitted: bool = True) -> None:
        view = BladeView(base)
        C = view.channels(t_window)
        N = view.n_blades
        gram = np.einsum('tmi,tmj->ij', C, C)
        absorbed = (collective_fitted and view.model.collective is not None
                    and view.model.rotor.advance_ratio == 0.0)
        if N > 1 and absorbed:
            ones = np.ones((N, 1)) / math.sqrt(N)
            proj = np.eye(N) - ones @ ones.T
            gram = proj @ gram @ proj
        self.basis = observable_basis(gram)
        self.extra_parameters = tuple(
            Parameter(f'bias_pattern_{i + 1}', f'c{i + 1}', 'rad', 0.0, -0.5, 0.5,
                      'flap-sensor bias along an observable pattern')
            for i in range(self.basis.shape[1]))
        super().__init__(base)
        self.blade_numbers = view.blades

    def output_offset(self, t: npt.ArrayLike, p: np.ndarray) -> np.ndarray:
        """
        Return the inner layers' offset plus d = C(t) V c.

        The inner offset matters on a sensor gain (its start offset C diag(s) β(t₀)): left
        out, a bias on top of a gain lost what the gain fitted and gained a negative
        2Δlog L (−38 in bias+azimuth at μ = 0.4).
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        _, pe = self._split(p)
        return super().output_offset(t, p) + np.einsum('tmn,n->tm', self.view.channels(t),
                                                       self.basis @ pe)

    def output_offset_jacobian(self, t: npt.ArrayLike, p: np.ndarray) -> np.ndarray:
        """∂d/∂c = C(t) V."""
        out = super().output_offset_jacobian(t, p)
        out[:, :, self.n_base_parameters:] = np.einsum('tmn,nk->tmk', self.view.channels(t),
                                                       self.basis)
        return out

    def report_parameters(self, values: np.ndarray,
                          cov: np.ndarray) -> dict[str, tuple[float, float]]:
        """Per-blade biases b = V c with their σ (unobservable parts set to zero)."""
        k = self.n_base_parameters
        c = np.asarray(values[k:], dtype=float)
        cc = np.asarray(cov)[k:, k:]
        b = self.basis @ c
        bcov = self.basis @ cc @ self.basis.T
        return {f'bias_{j}': (float(b[i]), float(math.sqrt(max(bcov[i, i], 0.0))))
                for i, j in enumerate(self.blade_numbers)}


class FlapFrequency(Augmented):
    """
    The rotating flap frequency P (per rev) identified instead of taken from the rotor data.

    F is quadratic in P in every baseline, so the central difference of F over ±h is exact.
    """

    effect = 'flap_frequency'

    def __init__(self, base: RotorLike) -> None:
        P = base.rotor.flap_frequency
        self.extra_parameters = (Parameter('P', 'P = ω₁', 'per rev', P, 0.3, 4.0,
                                           'rotating flap natural frequency'),)
        super().__init__(base)
        self._cache: dict[Any, Any] = {}

    #: the rotor constant this augmentation frees
    constant = 'flap_frequency'

    def with_rotor(self, **constants: Any) -> RotorLike:
        """
        Return a copy on a base with some rotor constants changed (fresh caches).

        δ3 freed on top of a freed flap frequency (they are separate physics in forward
        flight) reaches the rotor model through this layer; without it the outer layer only
        replaced this wrapper's ``rotor`` and flap_frequency on δ3 gained 2Δlog L = −17.
        """
        model = copy.copy(self)
        if hasattr(self.base, 'with_rotor'):
            model.base = self.base.with_rotor(**constants)
        else:
            model.base = copy.copy(self.base)
            model.base.rotor = replace(self.base.rotor, **constants)
        model.rotor = model.base.rotor
        model._cache = {}
        return model

    def _with_P(self, P):
        P = float(P)
        if P not in self._cache:
            if len(self._cache) > 8:
                self._cache.clear()
            if hasattr(self.base, 'with_rotor'):         # fresh caches of its blocks
                model = self.base.with_rotor(**{self.constant: P})
            else:
                model = copy.copy(self.base)
                model.rotor = replace(self.base.rotor, **{self.constant: P})
            self._cache[P] = model
        return self._cache[P]

    def system(self, t: npt.ArrayLike, p: np.ndarray,
               u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Return the baseline's F, g with P replaced."""
        pb, pe = self._split(p)
        return self._with_P(pe[0]).system(t, pb, self.base_inputs(u))

    def system_jacobian(self, t: npt.ArrayLike, p: np.ndarray,
                        u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Baseline derivatives at P, and ∂F/∂P by an exact central difference."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        u = self.base_inputs(u)
        pb, pe = self._split(p)
        P = pe[0]
        dFb, dgb = self._with_P(P).system_jacobian(t, pb, u)
        T, Pb, n = dgb.shape
        dF = np.zeros((T, Pb + 1, n, n))
        dF[:, :Pb] = dFb
        h = 1e-3
        Fp, _ = self._with_P(P + h).system(t, pb, u)
        Fm, _ = self._with_P(P - h).system(t, pb, u)
        dF[:, Pb] = (Fp - Fm) / (2 * h)
        dg = np.zeros((T, Pb + 1, n))
        dg[:, :Pb] = dgb
        return dF, dg


class ChannelSubset(LinearModel):
    """A model observed on a subset of its output channels (same parameters)."""

    def __init__(self, model: RotorLike, rows: Sequence[int], effect: str) -> None:
        self.inner = model
        self.rows = list(rows)
        self.effect = effect
        self.rotor = model.rotor
        self.name = f'{model.name}[{effect}]'
        self.parameters = model.parameters
        self.state_names = model.state_names
        self.output_names = tuple(model.output_names[i] for i in self.rows)
        self.time_invariant = model.time_invariant

    def with_rotor(self, **constants: Any) -> RotorLike:
        """
        Return a copy whose inner model has some rotor constants changed.

        A freed flap frequency or δ3 stacked on the periodic model must reach the model that
        computes F: replacing this wrapper's ``rotor`` alone left the inner model's P in place,
        so the pair periodic + flap frequency could never gain from P.
        """
        return ChannelSubset(self.inner.with_rotor(**constants), self.rows, self.effect)

    def system(self, t: npt.ArrayLike, p: np.ndarray,
               u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Return the inner model's F and g."""
        return self.inner.system(t, p, np.asarray(u)[:, :3])

    def system_jacobian(self, t: npt.ArrayLike, p: np.ndarray,
                        u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Return the inner model's derivatives."""
        return self.inner.system_jacobian(t, p, np.asarray(u)[:, :3])

    def output_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """Return the selected rows of the inner H."""
        return self.inner.output_matrix(t)[:, self.rows]

    def observe_blades(self, t: npt.ArrayLike, blade_flap: npt.ArrayLike) -> np.ndarray:
        """Return the selected channels."""
        return self.inner.observe_blades(t, blade_flap)[:, self.rows]

    def report_parameters(self, values: np.ndarray,
                          cov: np.ndarray) -> dict[str, tuple[float, float]]:
        """No extra parameters."""
        return {}


def periodic_coefficients(base: RotorLike) -> RotorLike:
    """Return the periodic model (docs/models.md §2.1) on the constant model's outputs."""
    inner = Multiblade(base.rotor, collective=base.collective, outputs=base.outputs)
    inner.parameters = base.parameters
    rows = [inner.output_names.index(name) for name in base.output_names]
    return ChannelSubset(inner, rows, 'periodic_coefficients')


def _as_index(indices):
    """Return a slice when ``indices`` run contiguously upward (fast), else an index array."""
    a = np.asarray(indices, dtype=np.intp)
    if a.size and np.array_equal(a, np.arange(a[0], a[0] + a.size)):
        return slice(int(a[0]), int(a[0]) + a.size)
    return a


def _grid(states):
    """Return the index of the (states x states) block of a square matrix (last two axes)."""
    if isinstance(states, slice):
        return states, states
    return states[:, None], states[None, :]


class DynamicInflow(Augmented):
    """
    The report's two-parameter cyclic wake (Ch.2 eq. 29) added to a multiblade γ-model.

    The augmented model is the baseline's rotor built again with ``inflow='cyclic'``
    (:class:`~rotor_id.physics.models.RotorModel`, docs/models.md §9): at μ = 0

        βI″ += A λI,   βII″ += A λII,          A = γB⁴/8 (Ch.2 eq. 27)
        λI′  = −(AL/τ + 1/τ) λI  + (AL/τ)(βI′ + βII − θII)
        λII′ = −(AL/τ + 1/τ) λII + (AL/τ)(βII′ − βI + θI)

    and in forward flight the same inflow driven by the blades' full periodic moment.
    Parameters ``AL_over_tau`` and ``inv_tau``; A is reported from γ.
    """

    effect = 'dynamic_inflow'
    extra_parameters = CYCLIC_INFLOW                  # the wake model's AL/τ and 1/τ
    #: no wake gain (AL/τ = 0) and a frozen wake (1/τ → 0) are physical limits
    physical_bounds = {'AL_over_tau': ('lower',), 'inv_tau': ('lower',)}
    extra_states = ('lambda_I', 'lambda_II')
    free_extra_states = ('lambda_I', 'lambda_II')

    def __init__(self, base: RotorLike) -> None:
        super().__init__(base)
        self._gamma = _gamma_index(base)
        self._a1 = flap_damping(1.0, base.rotor.tip_loss)      # A/γ, Ch.2 eq. 27
        root = self.view.model                  # the rotor model under any augmentation
        self.root = root
        self.inner = RotorModel(root.rotor, periodic=root.periodic, inflow='cyclic',
                                collective=root.collective, outputs=root.outputs,
                                all_coordinates=root.all_coordinates, name=root.name)
        missing = set(self.inner.state_names) - set(self.state_names)
        if missing:
            raise ValueError(f'the wake couples {", ".join(sorted(missing))}, which the '
                             f'baseline {base.name} does not carry')
        self._states = np.array([self.state_names.index(n) for n in self.inner.state_names])
        # the root's states within the inner model's, to subtract what the baseline has
        self._root_in_inner = np.array([self.inner.state_names.index(n)
                                        for n in root.state_names])
        names = self.parameter_names
        self._params = [(names.index(n), i) for i, n in enumerate(self.inner.parameter_names)]
        self._root_params = [(names.index(n), i) for i, n in enumerate(root.parameter_names)]
        # where the inner model's and the root's blocks go (see _extra_jacobian): slices
        # where the indices run contiguously (the usual case), index arrays otherwise
        root_of = dict(self._root_params)
        pairs = sorted(self._params)                # by my parameter order: a slice of mine
        self._inner_at = (_as_index([mine for mine, _ in pairs]), _as_index(self._states),
                          _as_index([theirs for _, theirs in pairs]))
        self._root_at = (_as_index([mine for mine, _ in pairs if mine in root_of]),
                         _as_index(self._states[self._root_in_inner]),
                         _as_index([root_of[mine] for mine, _ in pairs if mine in root_of]))

    def constant_terms(self) -> bool:
        """Tell whether the rotor models of the wake are time-invariant (then so are its F, ∂F)."""
        return bool(self.inner.time_invariant and getattr(self.root, 'time_invariant', False))

    def _inner_p(self, pb, pe):
        p = np.concatenate([pb, pe])
        q = np.zeros(len(self.inner.parameters))
        for mine, theirs in self._params:
            q[theirs] = p[mine]
        return q, p[:len(self.root.parameters)]

    def _extra(self, t, pb, pe, u, F, g):
        """Add the wake: the inner model's F, g minus the root's (which the baseline has)."""
        q, pr = self._inner_p(pb, pe)
        # F of length 1 along time where constant: added by broadcasting, not copied T times
        Fi, gi = compact(self.inner, 'system', t, q, u[:, :3])
        Fr, gr = compact(self.root, 'system', t, pr, u[:, :3])
        for sign, (_, states, _), Fx, gx in ((1.0, self._inner_at, Fi, gi),
                                             (-1.0, self._root_at, Fr, gr)):
            F[(slice(None),) + _grid(states)] += sign * Fx
            g[:, states] += sign * gx

    def _extra_jacobian(self, t, pb, pe, u, dF, dg):
        # the same difference as _extra for every parameter: one block add per model when
        # the indices are slices (a loop over parameters with fancy-indexed adds and a copy
        # of the root's derivatives embedded in the inner states was a quarter of diagnose)
        q, pr = self._inner_p(pb, pe)
        dFi, dgi = compact(self.inner, 'system_jacobian', t, q, u[:, :3])
        dFr, dgr = compact(self.root, 'system_jacobian', t, pr, u[:, :3])
        for sign, (mine, states, theirs), dFx, dgx in ((1.0, self._inner_at, dFi, dgi),
                                                       (-1.0, self._root_at, dFr, dgr)):
            dFx, dgx = sign * dFx[:, theirs], sign * dgx[:, theirs]
            if isinstance(mine, slice) and isinstance(states, slice):
                dF[:, mine, states, states] += dFx
                dg[:, mine, states] += dgx
                continue
            rows = np.arange(dF.shape[1])[mine]
            for k, row in enumerate(np.atleast_1d(rows)):
                dF[:, row][(slice(None),) + _grid(states)] += dFx[:, k]
                dg[:, row][:, states] += dgx[:, k]

    def report_parameters(self, values: np.ndarray,
                          cov: np.ndarray) -> dict[str, tuple[float, float]]:
        """Return A = γB⁴/8 with its σ, AL/τ and 1/τ (the answers' names)."""
        out = super().report_parameters(values, cov)
        i = self._gamma
        out = {'A': (float(self._a1 * values[i]),
                     float(self._a1 * math.sqrt(max(cov[i, i], 0.0)))), **out}
        return out


class BladeDissimilarity(Augmented):
    """
    Blade j's Lock number is γ(1+ε) and its aerodynamic pitch θ_j + Δθ (unseen by the sensor).

    The deviation η = β_j − (what the symmetric model predicts for blade j) obeys blade j's
    own flapping equation (single blade, docs/models.md §1.1; at μ = 0 with the wake: A(θ+λ−β′)),
    forced by ε times the symmetric blade's aerodynamic moment M_j and by the pitch offset:

        η″ + (1+ε)(γ/2) C η′ + [P² + (1+ε)(γ/2) K] η = ε M_j(x, t) + (γ/2) m_θ s,
        s = (1+ε)Δθ + εθ0,                                    y += C_{:,j} η

    exact for given inflow (the blades of a rotor couple only through the wake).

    Fitted parameters ``dgamma_rel`` (ε = γ_j/γ − 1) and ``dtheta_static`` = (1+ε)Δθ + εθ0 (rad):
    with a constant collective a Lock-number change and a pitch offset both shift the blade's
    trim by the same kind of constant, so the static part is carried by one parameter and ε by
    the dynamic part only (that keeps the two nearly uncorrelated and Gauss-Newton well
    conditioned); ``dtheta`` = Δθ is reported. With the wake model the
    odd blade's extra aerodynamic moment δM = A[ε(θ_j + λ_j − β_j′) + Δθ − η′] also drives the
    first-harmonic wake (docs/models.md §3.1: τλ′ + λ = −L·M): λI′ += −(AL/τ)(2/N) cos ψ_j δM/A,
    λII′ += −(AL/τ)(2/N) sin ψ_j δM/A, which feeds back on every blade.
    """

    effect = 'blade_dissimilarity'
    per_blade_terms = True
    extra_parameters = (
        Parameter('dgamma_rel', 'ε = γ_j/γ − 1', '-', 0.0, -0.9, 3.0,
                  'relative Lock-number difference of the odd blade'),
        Parameter('dtheta_static', '(1+ε)Δθ_j + εθ0', 'rad', 0.0, -0.2, 0.2,
                  "the odd blade's static pitch-equivalent offset"))
    #: γ_j > 0: ε = −0.9 is close to a blade without aerodynamics
    physical_bounds = {'dgamma_rel': ('lower',)}
    extra_states = ('eta', 'eta_dot')
    free_extra_states = ('eta', 'eta_dot')

    def __init__(self, base: RotorLike, blade: int) -> None:
        if 'lambda_0' in BladeView(base).model.state_names:
            raise ValueError('blade dissimilarity is modelled with the cyclic wake only, not '
                             'with the three-state inflow')
        super().__init__(base)
        self.blade = int(blade)
        self.name = f'{base.name}+{self.effect}[blade {self.blade}]'
        self._j = self.view.blades.index(self.blade)

    def _coefficients(self, t, pb, u):
        """
        Return blade j's flapping coefficients and moment, with their derivatives.

        Damping c, stiffness k, pitch gain m, moment row a (T, n), constant a0 (T,), and their
        derivatives with respect to the baseline parameters. All come from the baseline's one
        blade equation (:meth:`~rotor_id.physics.models.RotorModel.blade_moment` and
        :func:`~rotor_id.physics.aerodynamics.blade_aerodynamics`), for any N, μ and K_P.
        """
        root = self.view.model                   # the rotor model under any augmentation
        rotor = root.rotor
        j = self._j
        gamma, dgamma = root.lock_number(pb)
        dgamma = np.concatenate([dgamma, np.zeros(len(pb) - dgamma.size)])
        half, dhalf = 0.5 * gamma, 0.5 * np.broadcast_to(dgamma, (t.size, len(pb)))
        row, moment_u = self._moment(t, u)
        coef = blade_aerodynamics(self.view.azimuth(t)[:, j], rotor.tip_loss, rotor.advance_ratio)
        damping = coef['m_rate']
        stiff = coef['m_flap'] + rotor.pitch_flap_coupling * coef['m_theta']
        m_theta = coef['m_theta']
        names = root.parameter_names
        if 'theta0' in names:
            self._collective = float(pb[names.index('theta0')])
        elif 'delta' in names:
            self._collective = float(pb[names.index('delta')] / gamma)
        else:
            self._collective = float(np.mean(u[:, 0]))
        da = dhalf[:, :, None] * row[:, None, :]
        da0 = dhalf * moment_u[:, None]
        return (half * damping, rotor.flap_frequency**2 + half * stiff, half * m_theta,
                half * row, half * moment_u, dhalf * damping[:, None], dhalf * stiff[:, None],
                dhalf * m_theta[:, None], da, da0)

    def _wake_feedback(self, t):
        """
        Return the pieces of the odd blade's extra moment seen by the cyclic wake.

        The wake rows of the baseline are λ_h′ = … − (AL/τ)(4/B⁴)(2/N) Σ_k m_k (cos, sin)ψ_k
        with m_k the moment per γ/2 (docs/models.md §9). Blade j adds
        δm_j = ε (r x + q) + m_θ s − (1 + ε)(m_rate η′ + k η): returned are the weights
        w (T, 2) = (4/B⁴)(2/N)(cos ψ_j, sin ψ_j), r (T, n_base), the cyclic-pitch row
        (T, 2) of q, and m_θ, m_rate, k (T,) each.
        """
        rotor = self.view.model.rotor
        j = self._j
        psi = self.view.azimuth(t)[:, j]
        per_damping = 0.5 * lock_number_from_damping(1.0, rotor.tip_loss)    # 4/B⁴ = (γ/2)/A
        w = per_damping * (2.0 / rotor.n_blades) * np.column_stack([np.cos(psi), np.sin(psi)])
        row, _ = self._moment(t, None)
        Mu = self.view.model.blade_moment(t)[1]
        coef = blade_aerodynamics(psi, rotor.tip_loss, rotor.advance_ratio)
        stiff = coef['m_flap'] + rotor.pitch_flap_coupling * coef['m_theta']
        return w, row, Mu[:, j], coef['m_theta'], coef['m_rate'], stiff

    def _moment(self, t, u):
        """Blade j's moment per γ/2: row on the baseline's state (T, n_base), cyclic-pitch part."""
        Mx, Mu, _ = self.view.model.blade_moment(t)
        row = np.zeros((Mx.shape[0], self.n_base_states))
        row[:, :Mx.shape[2]] = Mx[:, self._j]
        moment_u = None if u is None else np.einsum('tk,tk->t', Mu[:, self._j], u[:, 1:3])
        return row, moment_u

    def _wake_rows(self):
        names = self.view.model.state_names           # the root's states come first
        return [names.index('lambda_I'), names.index('lambda_II')]

    def _extra(self, t, pb, pe, u, F, g):
        nb = self.n_base_states
        eps, stat = pe
        c, k, m, a, a0 = self._coefficients(t, pb, u)[:5]
        k_aero = k - self.base.rotor.flap_frequency**2
        F[:, nb, nb + 1] = 1.0
        F[:, nb + 1, nb] = -(k - k_aero) - (1.0 + eps) * k_aero     # blade j's own γ_j
        F[:, nb + 1, nb + 1] = -(1.0 + eps) * c
        F[:, nb + 1, :nb] = eps * a
        g[:, nb + 1] = eps * a0 + m * stat
        if 'lambda_I' in self.view.model.state_names:
            gain = pb[self.view.model.parameter_names.index('AL_over_tau')]
            w, row, qrow, m_th, m_rate, stiff = self._wake_feedback(t)
            q = np.einsum('tk,tk->t', qrow, u[:, 1:3])
            for i, lam in enumerate(self._wake_rows()):
                F[:, lam, :nb] += -gain * w[:, i, None] * eps * row
                F[:, lam, nb] += gain * w[:, i] * (1.0 + eps) * stiff
                F[:, lam, nb + 1] += gain * w[:, i] * (1.0 + eps) * m_rate
                g[:, lam] += -gain * w[:, i] * (eps * q + m_th * stat)

    def _extra_jacobian(self, t, pb, pe, u, dF, dg):
        nb, kb = self.n_base_states, self.n_base_parameters
        eps, stat = pe
        c, k, m, a, a0, dc, dk, dm, da, da0 = self._coefficients(t, pb, u)
        k_aero = k - self.base.rotor.flap_frequency**2
        dF[:, :kb, nb + 1, nb] = -(1.0 + eps) * dk
        dF[:, :kb, nb + 1, nb + 1] = -(1.0 + eps) * dc
        dF[:, :kb, nb + 1, :nb] = eps * da
        dg[:, :kb, nb + 1] = eps * da0 + dm * stat
        dF[:, kb, nb + 1, nb] = -k_aero
        dF[:, kb, nb + 1, nb + 1] = -c
        dF[:, kb, nb + 1, :nb] = a
        dg[:, kb, nb + 1] = a0
        dg[:, kb + 1, nb + 1] = m
        if 'lambda_I' in self.view.model.state_names:
            ig = self.view.model.parameter_names.index('AL_over_tau')
            gain = pb[ig]
            w, row, qrow, m_th, m_rate, stiff = self._wake_feedback(t)
            q = np.einsum('tk,tk->t', qrow, u[:, 1:3])
            for i, lam in enumerate(self._wake_rows()):
                wi = w[:, i]
                dF[:, ig, lam, :nb] += -wi[:, None] * eps * row           # ∂/∂(AL/τ)
                dF[:, ig, lam, nb] += wi * (1.0 + eps) * stiff
                dF[:, ig, lam, nb + 1] += wi * (1.0 + eps) * m_rate
                dg[:, ig, lam] += -wi * (eps * q + m_th * stat)
                dF[:, kb, lam, :nb] += -gain * wi[:, None] * row          # ∂/∂ε
                dF[:, kb, lam, nb] += gain * wi * stiff
                dF[:, kb, lam, nb + 1] += gain * wi * m_rate
                dg[:, kb, lam] += -gain * wi * q
                dg[:, kb + 1, lam] += -gain * wi * m_th                  # ∂/∂(Δθ + εθ0)

    def output_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """Return H of y = H x + C_{:,j} η."""
        H = super().output_matrix(t)
        H[:, :, self.n_base_states] = self.view.channels(t)[:, :, self._j]
        return H

    def report_parameters(self, values: np.ndarray,
                          cov: np.ndarray) -> dict[str, tuple[float, float]]:
        """ε, Δθ = (Δθ + εθ0) − εθ0 (σ by the delta method) and which blade."""
        out = super().report_parameters(values, cov)
        k = self.n_base_parameters
        theta0 = getattr(self, '_collective', 0.0)
        names = self.view.model.parameter_names
        if 'theta0' in names:
            theta0 = values[names.index('theta0')]
        elif 'delta' in names:
            theta0 = values[names.index('delta')] / self.view.model.lock_number(values)[0]
        eps, stat = values[k], values[k + 1]
        # Δθ = (s − εθ0)/(1 + ε), s = (1 + ε)Δθ + εθ0 the fitted static offset
        g_s = 1.0 / (1.0 + eps)
        g_e = -(theta0 + stat) / (1.0 + eps)**2
        var = g_s**2 * cov[k + 1, k + 1] + g_e**2 * cov[k, k] + 2 * g_s * g_e * cov[k, k + 1]
        out['dtheta'] = (float((stat - eps * theta0) / (1.0 + eps)),
                         float(math.sqrt(max(var, 0.0))))
        out['blade'] = (float(self.blade), 0.0)
        return out


#: Time grids (with their measured flap) whose cubic-spring forcing a model keeps: a fit's
#: record, and the halves of the cross-validation.
FORCING_GRIDS_KEPT = 4


class CubicStiffness(Augmented):
    """
    A hardening flap spring κβ³ on every blade (hub spring or elastic-stop nonlinearity).

    β_k″ += −κ β_k³; the cube is taken of the measured flap (extra inputs: the cubes β_k,meas³),
    which is the flap to within the sensor noise, so the model stays linear in its states, in
    κ and in its inputs: x′ += −κ G(t) β_meas³ with G the blade-to-state projection.
    """

    effect = 'cubic_stiffness'
    extra_parameters = (Parameter('kappa', 'κ', 'rad⁻²', 0.0, -1e5, 1e5,
                                  'cubic flap stiffness, per rev² per rad²'),)

    def __init__(self, base: RotorLike) -> None:
        self.extra_inputs = tuple(f'beta_{k}_measured_cubed' for k in BladeView(base).blades)
        super().__init__(base)

    def __getstate__(self):
        """Pickle without the kept forcing (a fit's result travels back from its worker)."""
        state = self.__dict__.copy()
        state.pop('_forcing_memo', None)
        return state

    def _forcing(self, t, u):
        """−G(t) β_meas³ (T, n_base): no parameter enters, so it is kept per time grid."""
        cubes = u[:, 3:3 + self.view.n_blades]
        # a fit evaluates F, g and their derivatives on the same grid and measured flap
        # every time: a copy of them decides a hit (the einsum was a sixth of a diagnosis)
        memo = self.__dict__.setdefault('_forcing_memo', [])
        for t_seen, cubes_seen, forcing in memo:
            if np.array_equal(t_seen, t) and np.array_equal(cubes_seen, cubes):
                return forcing
        forcing = -np.einsum('tnk,tk->tn', self.view.force(t), cubes)
        forcing.setflags(write=False)
        if len(memo) >= FORCING_GRIDS_KEPT:
            memo.pop(0)
        memo.append((np.array(t, dtype=float), np.array(cubes, dtype=float), forcing))
        return forcing

    def constant_terms(self) -> bool:
        """Return True: the spring adds to g only."""
        return True

    def _extra(self, t, pb, pe, u, F, g):
        g[:, :self.n_base_states] += pe[0] * self._forcing(t, u)

    def _extra_jacobian(self, t, pb, pe, u, dF, dg):
        dg[:, self.n_base_parameters, :self.n_base_states] = self._forcing(t, u)


# ------------------------------------------------------------------------------------------------
# Rig physics
# ------------------------------------------------------------------------------------------------

def _pitch_gain(model, t, pb):
    """
    Return G = ∂g/∂[θ0, θI, θII] of ``model.base`` (T, n_base, 3) and ∂G/∂p (T, P_b, n_base, 3).

    The base model's own g is affine in the pitch, so G is the difference of its g at unit
    and zero pitch: the augmentation reads the pitch forcing off the rotor model and never
    re-derives a coefficient.
    """
    base = model.base
    u = model._u_full
    T = t.size
    zero = np.zeros((T, 3))
    _, g0 = base.system(t, pb, model.base_inputs(u, zero))
    dF0, dg0 = base.system_jacobian(t, pb, model.base_inputs(u, zero))
    G = np.zeros((T, base.n_states, 3))
    dG = np.zeros((T, len(pb), base.n_states, 3))
    for j in range(3):
        unit = zero.copy()
        unit[:, j] = 1.0
        _, g1 = base.system(t, pb, model.base_inputs(u, unit))
        _, dg1 = base.system_jacobian(t, pb, model.base_inputs(u, unit))
        G[:, :, j] = g1 - g0
        dG[:, :, :, j] = dg1 - dg0
    return G, dG


class PitchFlapCoupling(FlapFrequency):
    """
    Pitch-flap coupling δ3 identified: the rotor model's own ``pitch_flap_coupling`` freed.

    K = tan δ3 (the blade pitch falls by K β_k as it flaps up) is a constant of the rotor model
    (:class:`~rotor_id.physics.models.RotorConstants`); the candidate frees it, starting from
    the run description's value, exactly as ``flap_frequency`` frees P: no coefficient is
    derived here. F is linear in K, so the central difference is exact. At μ = 0 without a
    wake the coupling is a flap-stiffness change of the tilt modes, the same physics as
    ``flap_frequency``.
    """

    effect = 'pitch_flap_coupling'
    constant = 'pitch_flap_coupling'

    def __init__(self, base: RotorLike) -> None:
        K = base.rotor.pitch_flap_coupling
        self.extra_parameters = (Parameter('pitch_flap_coupling', 'K = tan δ3', 'rad/rad', K,
                                           K - 1.5, K + 1.5,
                                           'pitch change per unit flap (tan δ3)'),)
        Augmented.__init__(self, base)
        self._cache = {}


class PitchActuatorLag(Augmented):
    """
    A first-order lag τ_a (``actuator_lag_rad``) between the measured and the blade's pitch.

    The blade's pitch is the measured one plus the error e_k, τ_a e_k′ = −e_k − τ_a θ_k′
    (zero in trim). In multiblade pitch (rotating frame → first harmonics):

        e0′  = −e0/τ_a − θ0′,
        eI′  = −eI/τ_a − eII − θI′ − θII,      eII′ = −eII/τ_a + eI − θII′ + θI

    and the rotor sees θ + e through its own pitch forcing G (:func:`_pitch_gain`):
    x′ += G e. To first order a lag is the delay d = τ_a (``time_delay``).
    """

    effect = 'pitch_actuator_lag'
    extra_parameters = (Parameter('actuator_lag_rad', 'τ_a', 'rad', 0.1, 0.03, 3.0,
                                  'pitch actuator first-order time constant, rad of azimuth'),)
    extra_states = ('pitch_error_0', 'pitch_error_I', 'pitch_error_II')
    extra_inputs = ('theta_0_rate', 'theta_I_rate', 'theta_II_rate')
    SMALLEST_LAG = SensorLag.SMALLEST_LAG
    STEP_PER_LAG = SensorLag.STEP_PER_LAG
    widened = SensorLag.widened

    def step(self) -> float:
        """Return the longest stable RK4 step for the smallest admissible τ_a."""
        return self.STEP_PER_LAG * self.parameter('actuator_lag_rad').lower

    def _extra(self, t, pb, pe, u, F, g):
        G, _ = _pitch_gain(self, t, pb)
        nb = self.n_base_states
        F[:, :nb, nb:] = G
        F[:, nb:, nb:] = -np.eye(3) / pe[0]
        F[:, nb + 1, nb + 2] = -1.0
        F[:, nb + 2, nb + 1] = 1.0
        g[:, nb] = -u[:, 3]
        g[:, nb + 1] = -u[:, 4] - u[:, 2]
        g[:, nb + 2] = -u[:, 5] + u[:, 1]

    def _extra_jacobian(self, t, pb, pe, u, dF, dg):
        _, dG = _pitch_gain(self, t, pb)
        nb, kb = self.n_base_states, self.n_base_parameters
        dF[:, :kb, :nb, nb:] = dG
        dF[:, kb, nb:, nb:] = np.eye(3) / pe[0]**2


class SensorGain(Augmented):
    """
    Flap-sensor calibration scale per blade: the sensor reads (1 + s_k) β_k.

    The scaled part z_k = s_k (β_k − β_k(t_0)) is carried by extra states driven by the model's
    own flap rate, z_k′ = s_k β_k′ = s_k Hbr_k x (exact, linear in the states, and no measured
    signal multiplies s: a gain on the measured flap would scale its noise too and fit it),
    and the part of the start, s_k β_k(t_0), is an output offset with β_k(t_0) the measured
    flap there, smoothed over ±``SMOOTH`` samples: y += C(t) (z + diag(s) β(t_0)). Only the
    gain patterns the channels can see are parameters (s = V c, V orthonormal, as
    :class:`SensorBias`); the report gives s per blade.
    """

    effect = 'sensor_gain'
    per_blade_terms = True
    #: samples either side averaged for the flap at the start of a run
    SMOOTH = 10

    def __init__(self, base: RotorLike, t_record: npt.ArrayLike,
                 blade_flap: npt.ArrayLike) -> None:
        view = BladeView(base)
        self._t = np.asarray(t_record, dtype=float)
        self._flap = np.asarray(blade_flap, dtype=float)
        self.extra_states = tuple(f'gain_flap_{k}' for k in view.blades)
        C = view.channels(self._t)
        patterns = C * self._flap[:, None, :]
        gram = np.einsum('tmi,tmj->ij', patterns, patterns)
        self.basis = observable_basis(gram)
        self.extra_parameters = tuple(
            Parameter(f'gain_pattern_{i + 1}', f's{i + 1}', '-', 0.0, -0.5, 0.5,
                      'flap-sensor scale error along an observable pattern')
            for i in range(self.basis.shape[1]))
        super().__init__(base)
        self.blade_numbers = view.blades

    def _start_flap(self, t0):
        i = int(np.searchsorted(self._t, t0))
        lo, hi = max(0, i - self.SMOOTH), min(self._t.size, i + self.SMOOTH + 1)
        return np.mean(self._flap[lo:hi], axis=0)

    def _extra(self, t, pb, pe, u, F, g):
        nb = self.n_base_states
        scale = self.basis @ pe
        F[:, nb:, :nb] = scale[None, :, None] * self.view.flap_rate(t)

    def _extra_jacobian(self, t, pb, pe, u, dF, dg):
        nb, kb = self.n_base_states, self.n_base_parameters
        rate = self.view.flap_rate(t)
        for i in range(self.basis.shape[1]):
            dF[:, kb + i, nb:, :nb] = self.basis[:, i][None, :, None] * rate

    def output_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """Return H of y = H x + C z."""
        H = super().output_matrix(t)
        H[:, :, self.n_base_states:] = self.view.channels(t)
        return H

    def output_offset(self, t: npt.ArrayLike, p: np.ndarray) -> np.ndarray:
        """Return the baseline's offset plus C(t) diag(s) β(t_0)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        _, pe = self._split(p)
        start = self._start_flap(t[0]) * (self.basis @ pe)
        return super().output_offset(t, p) + np.einsum('tmn,n->tm', self.view.channels(t),
                                                       start)

    def output_offset_jacobian(self, t: npt.ArrayLike, p: np.ndarray) -> np.ndarray:
        """∂d/∂c = C(t) diag(β(t_0)) V."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        out = super().output_offset_jacobian(t, p)
        out[:, :, self.n_base_parameters:] = np.einsum(
            'tmn,nk->tmk', self.view.channels(t) * self._start_flap(t[0])[None, None, :],
            self.basis)
        return out

    def report_parameters(self, values: np.ndarray,
                          cov: np.ndarray) -> dict[str, tuple[float, float]]:
        """Per-blade scale errors s = V c with their σ."""
        k = self.n_base_parameters
        c = np.asarray(values[k:k + self.basis.shape[1]], dtype=float)
        cc = np.asarray(cov)[k:k + self.basis.shape[1], k:k + self.basis.shape[1]]
        s = self.basis @ c
        scov = self.basis @ cc @ self.basis.T
        return {f'gain_{j}': (float(s[i]), float(math.sqrt(max(scov[i, i], 0.0))))
                for i, j in enumerate(self.blade_numbers)}


class AzimuthOffset(Augmented):
    """
    The rig's azimuth reads Δψ (``azimuth_offset_rad``) ahead of blade 1's true azimuth.

    An encoder index mounted off the reference blade (or a wrong zero in the run description)
    makes the recording's time t = ψ + Δψ. The blades' flap and pitch are measured right, but
    every quantity referred to the azimuth is formed with the wrong ψ_k: the multiblade pitch
    and flap turn by Δψ (:func:`~rotor_id.physics.multiblade.azimuth_offset_matrix`, S) and the
    periodic aerodynamics run Δψ early. With the states in the recording's frame
    (x_read = S x, S on every cyclic pair: flap, flap rate, wake inflow, pitch error):

        x_read′ = S F(t − Δψ) S⁻¹ x_read + S g(t − Δψ, u_true),   y = H(t) x_read

    where u_true is the measured blade pitch (eq. 3 at the recorded azimuth) turned back to the
    true one. At μ = 0 the rotor is axisymmetric, S commutes with F and the offset is exactly
    invisible (and harmless to every estimate): the candidate is tried in forward flight only.
    ∂/∂Δψ is a central difference (step h = 1e-4 rad) of F and g, which are trigonometric
    polynomials of the azimuth of low order n ≤ 8: truncation (h·n)²/6 ≈ 1e-7 relative, and
    rounding of ψ itself (≈ 1e-13 at ψ of a few hundred rad, over 2h) below 1e-8. The
    sensitivities need no more; a five-point difference cost two more evaluations of the
    periodic model on shifted time grids per iteration, for nothing the fit can see.
    """

    effect = 'azimuth_offset'
    extra_parameters = (Parameter('azimuth_offset_rad', 'Δψ', 'rad', 0.0, -0.5, 0.5,
                                  'recorded azimuth minus the true azimuth of blade 1'),)
    #: fixed-frame cyclic states (cos, sin) of inner layers, turned like (β_I, β_II)
    CYCLIC_PAIRS = (('lambda_I', 'lambda_II'), ('pitch_error_II', 'pitch_error_I'))
    #: extra-input triples [θ0, θI, θII]-like (pitch rates) turned like the pitch
    PITCH_INPUTS = ('theta_0_rate', 'theta_I_rate', 'theta_II_rate')
    #: prefix of a sensor lag's error states in the flap's coordinates (:class:`SensorLag`)
    LAG_ERROR = 'lag_error_'
    STEP = 1e-4

    def __init__(self, base: RotorLike) -> None:
        super().__init__(base)
        self._n = int(self.view.model.rotor.n_blades)
        coords = list(coordinate_names(self._n)) if self.view.model.blade is None else []
        self._index = []                  # (state index, coordinate index, sign) of turned states
        for i, name in enumerate(self.state_names):
            stem = name[:-4] if name.endswith('_dot') else name
            for cos_name, sin_name in self.CYCLIC_PAIRS:
                if stem in (cos_name, sin_name) and 'beta_I' in coords:
                    # (θII, −θI) of the pitch error is the (cos, sin) pair of eq. 3
                    sign = -1.0 if stem == 'pitch_error_I' else 1.0
                    stem = 'beta_I' if stem == cos_name else 'beta_II'
                    self._index.append((i, coords.index(stem), sign, name.endswith('_dot'),
                                        name))
                    break
            else:
                if stem in coords:
                    self._index.append((i, coords.index(stem), 1.0, name.endswith('_dot'),
                                        stem))
                elif stem.startswith(self.LAG_ERROR) and stem[len(self.LAG_ERROR):] in coords:
                    # a sensor lag's errors in the flap's multiblade coordinates turn alike
                    self._index.append((i, coords.index(stem[len(self.LAG_ERROR):]), 1.0,
                                        False, self.LAG_ERROR))
        extra = list(self.all_extra_inputs)
        self._pitch_columns = [3 + extra.index(n) for n in self.PITCH_INPUTS] \
            if all(n in extra for n in self.PITCH_INPUTS) else []
        self.rotation(0.1)                # raises now for a state set S does not map onto itself

    def rotation(self, offset: float) -> np.ndarray:
        """S over the state vector: the cyclic pairs turned by hΔψ, everything else kept."""
        out = np.eye(self.n_states)
        if not self._index:
            return out
        S = azimuth_offset_matrix(self._n, offset)
        groups: dict[tuple[bool, ...], list[tuple[int, int, float]]] = {}
        for i, c, sign, rate, key in self._index:
            groups.setdefault((rate, key in ('lambda_I', 'lambda_II'),
                               key.startswith('pitch_error'), key == self.LAG_ERROR),
                              []).append((i, c, sign))
        for members in groups.values():
            for i, ci, si in members:
                for j, cj, sj in members:
                    out[i, j] = si * sj * S[ci, cj]
        if not np.allclose(out @ out.T, np.eye(self.n_states), atol=1e-12):
            raise ValueError(f'the azimuth offset turns cyclic pairs, and {self.base.name} '
                             'carries one half of a pair')
        return out

    def true_inputs(self, t: npt.ArrayLike, u: npt.ArrayLike, offset: float) -> np.ndarray:
        """Return u with [θ0, θI, θII] (and pitch rates) turned to the true azimuth t − Δψ."""
        t = np.asarray(t, dtype=float)
        u = np.array(u, dtype=float)
        for first in [0] + self._pitch_columns[:1]:
            cols = slice(first, first + 3)
            blades = blade_pitch_from_multiblade(t, u[:, cols], self._n)
            u[:, cols] = multiblade_from_blade_pitch(t - offset, blades)
        return u

    def _at(self, t, pb, u, offset, jacobian=False):
        S = self.rotation(offset)
        tt, ut = t - offset, self.base_inputs(self.true_inputs(t, u, offset))
        if jacobian:
            dF, dg = self.base.system_jacobian(tt, pb, ut)
            return S @ dF @ S.T, np.einsum('ij,tpj->tpi', S, dg)
        F, g = self.base.system(tt, pb, ut)
        return S @ F @ S.T, np.einsum('ij,tj->ti', S, g)

    def system(self, t: npt.ArrayLike, p: np.ndarray,
               u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """F and g of the base at the true azimuth, in the recording's frame."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        pb, pe = self._split(p)
        return self._at(t, pb, u, pe[0])

    def system_jacobian(self, t: npt.ArrayLike, p: np.ndarray,
                        u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Return the base's derivatives turned by S, and ∂/∂Δψ by a central difference."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        pb, pe = self._split(p)
        dFb, dgb = self._at(t, pb, u, pe[0], jacobian=True)
        T, Pb, n = dgb.shape
        dF = np.zeros((T, Pb + 1, n, n))
        dg = np.zeros((T, Pb + 1, n))
        dF[:, :Pb], dg[:, :Pb] = dFb, dgb
        h = self.STEP
        for sign in (-1.0, 1.0):
            F, g = self._at(t, pb, u, pe[0] + sign * h)
            dF[:, Pb] += sign * F / (2.0 * h)
            dg[:, Pb] += sign * g / (2.0 * h)
        return dF, dg


class TimeDelay(AzimuthOffset):
    """
    Flap read later than the pitch by d (``delay_rad``, rad of azimuth; d/Ω seconds).

    A flap sample at t shows each blade as it was at t − d: the whole rotor state of that
    instant, with its periodic aerodynamics at azimuth t − d, driven by the pitch of then,
    θ(t − d) ≈ θ(t) − d θ′(t) (θ′: the measured pitch rates, extra inputs). Formed into
    multiblade coordinates with the azimuth of t, that state is turned by d
    (:func:`~rotor_id.physics.multiblade.azimuth_offset_matrix`, S). With x_read = S x(t − d):

        x_read′ = S F(t − d) S⁻¹ x_read + S g(t − d, θ(t) − d θ′(t)),   y = H(t) x_read

    which is :class:`AzimuthOffset`'s frame with the offset d and the pitch of t − d. In
    hover S commutes with the rotor and this is the pitch delayed and turned by d
    (:class:`PitchDelay`), exactly; in forward flight the two differ at first order in μ d,
    and this one is a flap sensor's or a clock's delay, the first-order equivalent of a flap
    sensor lag τ = d at any advance ratio. ∂/∂d as :class:`AzimuthOffset`'s ∂/∂Δψ.
    """

    effect = 'time_delay'
    extra_parameters = (Parameter('delay_rad', 'd', 'rad', 0.0, -0.6, 0.6,
                                  'flap read later than pitch, rad of azimuth'),)
    extra_inputs = PitchDelay.extra_inputs           # the measured pitch rates θ′

    def true_inputs(self, t: npt.ArrayLike, u: npt.ArrayLike, offset: float) -> np.ndarray:
        """Return u with [θ0, θI, θII] as they were at t − d, to first order in d."""
        u = np.array(u, dtype=float)
        u[:, :3] -= offset * self.own_inputs(u)[:, 3:6]
        return u


class PitchLikeRandomInflow(Augmented):
    """
    Random inflow as a pitch-like angle with a first-order spectrum (three Gauss-Markov states).

    Turbulence changes each blade's angle of attack as a pitch change would: w_k = w_0 +
    w_I cos ψ_k + w_II sin ψ_k, with components correlated over a time τ_w (a first-order,
    Dryden-like spectrum). Here w = (w_0, w_I, w_II) are states driven by white noise,

        w′ = −w/τ_w + ξ,     x′ = F x + g + B_θ(t) w,

    where B_θ is the base model's own response to a unit pitch input θ0, θI, θII (its affine
    term differenced in the cyclic u, and in the collective parameter θ0 or δ = γθ0 for w_0:
    the model reads the collective from that parameter, not from u[0]; so every
    augmentation underneath, an azimuth offset or periodic coefficients, acts on w as on the
    pitch). The filter's process noise goes on the w rows only. White noise on the
    flap-acceleration rows (the default of a model without inflow states) has neither the
    spectrum nor the direction of this input; a wake model's λ rows are already first-order
    states on the pitch-like path, and there nothing is gained (measured:
    bench/results/diagnosis_pairs.md).
    """

    effect = 'process_noise'
    extra_parameters = (Parameter('turbulence_corr_rad', 'τ_w', 'rad', 1.0, 0.1, 50.0,
                                  'correlation time of the random inflow, rad of azimuth'),)
    #: the admissible range of τ_w is physics (from white to a quasi-steady drift): a fit
    #: stopping there has found that end, it is not a catalogue range to widen
    physical_bounds = {'turbulence_corr_rad': ('lower', 'upper')}
    extra_states = ('random_inflow_0', 'random_inflow_I', 'random_inflow_II')

    def _pitch_columns(self, t, pb, u, jacobian=False):
        """B_θ's columns [(T, nb)] (or their ∂/∂p, [(T, Pb, nb)]): Δg per unit pitch input."""
        zero = np.zeros_like(np.asarray(u, dtype=float)[:, :self.n_base_inputs])
        evaluate = self.base.system_jacobian if jacobian else self.base.system
        g0 = evaluate(t, pb, zero)[1]
        out = [self._collective_column(t, pb, zero, g0, evaluate, jacobian)]
        for j in (1, 2):
            unit = zero.copy()
            unit[:, j] = 1.0
            out.append(evaluate(t, pb, unit)[1] - g0)
        return out

    def _collective_column(self, t, pb, zero, g0, evaluate, jacobian):
        """
        Δg per unit collective pitch w_0 (or its ∂/∂p): the g term differenced in θ0 (or δ).

        The model's collective is its parameter θ0 (δ = γθ0), which g is affine in; u[0] is not
        read (rotor_id.physics.models), so a unit u[0] would leave w_0 without any effect and
        the coning's response to turbulence unmodelled (measured at μ = 0.4: β0's innovations
        at the true parameters correlated, effective fraction 0.47 of 449 samples).
        """
        root = self.view.model
        if root.collective is None:             # the collective reaches no modelled state
            return np.zeros_like(g0)
        i = list(self.base.parameter_names).index(root.collective)
        gamma, dgamma = root.lock_number(pb)
        step = 1.0 if root.collective == 'theta0' else gamma     # δ changes by γ per radian
        p1 = np.array(pb, dtype=float)
        p1[i] += step
        column = evaluate(t, p1, zero)[1] - g0
        if jacobian and root.collective == 'delta':
            # ∂/∂p of γ·∂g/∂δ: the step itself depends on γ
            d = np.zeros(len(pb))
            d[:dgamma.size] = dgamma
            slope = (self.base.system(t, p1, zero)[1] - self.base.system(t, pb, zero)[1]) / step
            column = column + d[None, :, None] * slope[:, None, :]
        return column

    def _extra(self, t, pb, pe, u, F, g):
        nb = self.n_base_states
        for j, column in enumerate(self._pitch_columns(t, pb, self._u_full)):
            F[:, :nb, nb + j] = column
            F[:, nb + j, nb + j] = -1.0 / pe[0]

    def _extra_jacobian(self, t, pb, pe, u, dF, dg):
        nb, n_pb = self.n_base_states, len(pb)
        for j, column in enumerate(self._pitch_columns(t, pb, self._u_full, jacobian=True)):
            dF[:, :n_pb, :nb, nb + j] = column
            dF[:, -1, nb + j, nb + j] = 1.0 / pe[0]**2


# ------------------------------------------------------------------------------------------------
# Out of catalogue: a library term on every blade's flap equation
# ------------------------------------------------------------------------------------------------

#: Per-blade factors of the out-of-catalogue term library (name, what it is).
FACTORS = (('beta', 'flap β_k'), ('beta_dot', 'flap rate β_k′'),
           ('theta', 'measured blade pitch θ_k'), ('1', 'a constant moment'))
#: First harmonics of the blade's azimuth multiplying each factor.
HARMONICS = (('', None), ('cos(psi)', np.cos), ('sin(psi)', np.sin))


def term_names() -> list[str]:
    """Return the names of the library's terms, in library order."""
    out = []
    for factor, _ in FACTORS:
        for harmonic, _ in HARMONICS:
            if factor == '1':
                out.append(harmonic or '1')
            else:
                out.append(f'{factor}*{harmonic}' if harmonic else factor)
    return out


def _split_term(name: str) -> tuple[str, str]:
    """Return (factor, harmonic) of a term name ('beta*cos(psi)' -> ('beta', 'cos(psi)'))."""
    if name in ('1', 'cos(psi)', 'sin(psi)'):
        return '1', '' if name == '1' else name
    factor, _, harmonic = name.partition('*')
    return factor, harmonic


def term_pieces(view: 'BladeView', term: str, t: np.ndarray, u: np.ndarray,
                ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """
    Return one library term per blade as φ_k = Φ x + φ0: (Φ (T, N_b, n) or None, φ0 or None).

    The one definition of the terms (``view`` a :class:`BladeView` of the model): flap and flap
    rate from the model's own blade matrices (linear in the states), the blade pitch from the
    measured multiblade pitch by eq. 3, the azimuth from the model.
    """
    factor, harmonic = _split_term(term)
    psi = view.azimuth(t)
    trig = dict(HARMONICS)[harmonic]
    h = np.ones_like(psi) if trig is None else trig(psi)
    if factor in ('beta', 'beta_dot'):
        H = view.flap(t) if factor == 'beta' else view.flap_rate(t)
        return h[:, :, None] * H, None
    if factor == 'theta':
        blades = [k - 1 for k in view.blades]
        h = h * blade_pitch_from_multiblade(t, u[:, :3], int(view.model.rotor.n_blades))[
            :, blades]
    return None, h


def library(model: RotorLike, t: np.ndarray, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Return the library's per-blade values φ (T, N_b, M) at states x (T, n) and inputs u."""
    view = BladeView(model)
    columns: list[np.ndarray] = []
    for term in term_names():
        Phi, phi0 = term_pieces(view, term, t, u)
        columns.append(np.einsum('tkn,tn->tk', Phi, x) if Phi is not None
                       else np.asarray(phi0))
    return np.stack(columns, axis=2)


class LibraryTerm(Augmented):
    """
    The baseline with one library term on every blade: β_k″ += ξ φ_k (x′ += ξ G φ).

    φ_k is a flap, flap rate (linear in the states: F += ξ G diag(h) Hb) or measured pitch or
    constant (g += ξ G (h θ_k) or ξ G h), h = 1, cos ψ_k or sin ψ_k. Linear in ξ, so the
    sensitivities are exact; ξ = 0 is the baseline.
    """

    effect = 'proposed_term'

    def __init__(self, base: RotorLike, term: str) -> None:
        self.term = term
        harmonic = _split_term(term)[1]
        self.extra_parameters = (Parameter(f'xi[{term}]', 'ξ', 'per rev²', 0.0, -1e3, 1e3,
                                           f"proposed β'' += ξ·{term}"),)
        super().__init__(base)
        self.name = f'{base.name}+{term}'
        self.time_invariant = base.time_invariant and not harmonic

    def _pieces(self, t, u):
        Phi, phi0 = term_pieces(self.view, self.term, t, u)
        G = self.view.force(t)
        if Phi is not None:
            return np.einsum('tnk,tkm->tnm', G, Phi), None
        return None, np.einsum('tnk,tk->tn', G, phi0)

    def _extra(self, t, pb, pe, u, F, g):
        M, v = self._pieces(t, u)
        if M is not None:
            F += pe[0] * M
        else:
            g += pe[0] * v

    def _extra_jacobian(self, t, pb, pe, u, dF, dg):
        M, v = self._pieces(t, u)
        k = self.n_base_parameters
        if M is not None:
            dF[:, k] = M
        else:
            dg[:, k] = v
