"""
One general rotor model, and the report's flapping models as special cases (docs/models.md).

Every model is a linear state-space system in the report's nondimensional time t:

    x′ = F(t, p) x + g(t, p, u),        y = H(t) x + d(t, p) + v

with ``u = [θ0, θI, θII]`` the multiblade pitch (:mod:`rotor_id.physics.stirring`). A model gives
F, g, their derivatives with respect to every parameter, H and the optional output offset d, all
vectorised over an array of times. The estimators need nothing else, so models added later
(the augmented models of :mod:`rotor_id.physics.augmented`, per-blade simulations) work with
every estimator unchanged.

The collective pitch enters through the parameter θ0 (or δ = γθ0, the report's choice), not through
``u[0]``: the identified collective is the aerodynamic one, which a pitch sensor does not know.

:class:`RotorModel` builds every model from one blade equation
(:mod:`rotor_id.physics.aerodynamics`) for any number of blades N ≥ 2, pitch-flap coupling and
advance ratio, in the blade's rotating frame or in multiblade coordinates
(:mod:`rotor_id.physics.multiblade`), with periodic or averaged coefficients and optionally a
dynamic inflow (the report's two-state cyclic wake or a three-state uniform + first-harmonic
inflow). The report's four models are instances with the report's choices (:func:`build_model`).
"""

import copy
from dataclasses import dataclass, replace
import math
from typing import Any, Callable, Mapping, TypeVar

import numpy as np
import numpy.typing as npt

from rotor_id.physics.aerodynamics import blade_aerodynamics, flap_damping, hover_coning
from rotor_id.physics.multiblade import (blade_from_multiblade_matrix, coordinate_harmonics,
                                         multiblade_coordinates, multiblade_from_blade_matrix)


@dataclass(frozen=True)
class Parameter:
    """A named model parameter with its unit, nominal (report true) value and physical bounds."""

    name: str
    symbol: str
    unit: str
    nominal: float
    lower: float
    upper: float
    description: str


@dataclass(frozen=True)
class RotorConstants:
    """
    Known rotor data (docs/models.md §0): blades N, advance ratio μ, flap frequency P, tip loss B.

    ``pitch_flap_coupling`` is K_P = tan δ3: the blade pitch falls by K_P β when the blade
    flaps up by β (θ_effective = θ − K_P β).
    """

    n_blades: int = 4
    advance_ratio: float = 0.4
    flap_frequency: float = 1.2
    tip_loss: float = 0.97
    pitch_flap_coupling: float = 0.0

    def check(self) -> 'RotorConstants':
        """Raise ValueError naming the first rotor constant no model can be built for."""
        if int(self.n_blades) != self.n_blades or self.n_blades < 2:
            raise ValueError(f'a rotor needs a whole number of blades >= 2, got {self.n_blades}')
        if not 0.0 < self.tip_loss <= 1.0:
            raise ValueError(f'tip_loss must be in (0, 1], got {self.tip_loss}')
        if not self.flap_frequency > 0.0:
            raise ValueError(f'flap_frequency must be > 0 per rev, got {self.flap_frequency}')
        if not 0.0 <= self.advance_ratio < 1.0:
            raise ValueError(f'advance_ratio must be in [0, 1) (no reversed-flow model), '
                             f'got {self.advance_ratio}')
        if not math.isfinite(self.pitch_flap_coupling):
            raise ValueError(f'pitch_flap_coupling must be finite, got {self.pitch_flap_coupling}')
        return self


_Method = TypeVar('_Method', bound=Callable[..., Any])


def via_compact(method: _Method) -> _Method:
    """
    Mark a ``system`` or ``system_jacobian`` computed as its ``*_compact`` form, broadcast.

    :func:`compact` calls the compact form only where the model's class computes the method
    that way: a subclass that overrides ``system`` gets its own, full arrays.
    """
    method.via_compact = True  # type: ignore[attr-defined]
    return method


def full_along_time(A: np.ndarray, T: int) -> np.ndarray:
    """Return A (F or ∂F of :func:`compact`) with T entries along time (a copy if it had one)."""
    if A.shape[0] == T:
        return A
    return np.broadcast_to(A, (T,) + A.shape[1:]).copy()


def compact(model: 'LinearModel', method: str, t: npt.ArrayLike, p: np.ndarray,
            u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """
    Return ``model.system`` or ``system_jacobian`` (``method``), constant F of length 1 in time.

    F (∂F/∂p) has length 1 along time where the model knows it is constant; g (∂g/∂p) has
    every time. The values are the method's; only the copies of a constant F to every time
    are left out (for a record of T stage times they were most of an augmented model's cost).
    """
    if getattr(getattr(type(model), method), 'via_compact', False):
        return getattr(model, f'{method}_compact')(t, p, u)
    return getattr(model, method)(t, p, u)


class LinearModel:
    """
    Interface of a linear flapping model (see the module docstring).

    Subclasses set ``name``, ``state_names``, ``output_names``, ``parameters`` and implement
    :meth:`system`, :meth:`system_jacobian` and :meth:`output_matrix`.
    """

    name = 'linear'
    state_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    parameters: tuple[Parameter, ...] = ()
    #: True when F and g do not depend on t for constant u (allows equilibrium starts).
    time_invariant = False

    # -- parameters ---------------------------------------------------------------------------
    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of all parameters, in the order of the vector ``p``."""
        return tuple(par.name for par in self.parameters)

    def parameter(self, name: str) -> Parameter:
        """Return the :class:`Parameter` called ``name``."""
        for par in self.parameters:
            if par.name == name:
                return par
        raise KeyError(f'model {self.name!r} has no parameter {name!r}; '
                       f'its parameters are {", ".join(self.parameter_names)}')

    def nominal(self) -> np.ndarray:
        """Vector of nominal parameter values."""
        return np.array([par.nominal for par in self.parameters], dtype=float)

    def parameter_vector(self, values: Mapping[str, float] | None = None) -> np.ndarray:
        """Full parameter vector from a mapping of overrides on the nominal values."""
        p = self.nominal()
        for name, value in (values or {}).items():
            p[self.parameter_names.index(self.parameter(name).name)] = float(value)
        return p

    @property
    def n_states(self) -> int:
        """Dimension of x."""
        return len(self.state_names)

    @property
    def n_outputs(self) -> int:
        """Dimension of y."""
        return len(self.output_names)

    # -- dynamics -----------------------------------------------------------------------------
    def system(self, t: npt.ArrayLike, p: np.ndarray,
               u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Return ``F`` of shape (T, n, n) and ``g`` of shape (T, n) at times t."""
        raise NotImplementedError

    def system_jacobian(self, t: npt.ArrayLike, p: np.ndarray,
                        u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Return ``dF`` (T, P, n, n) and ``dg`` (T, P, n): derivatives w.r.t. every parameter."""
        raise NotImplementedError

    def output_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """Return ``H`` of shape (T, m, n)."""
        raise NotImplementedError

    def output_offset(self, t: npt.ArrayLike, p: np.ndarray) -> np.ndarray:
        """Return the output offset ``d`` (T, m) (zero unless a model adds sensor biases)."""
        return np.zeros((np.size(t), self.n_outputs))

    def output_offset_jacobian(self, t: npt.ArrayLike, p: np.ndarray) -> np.ndarray:
        """Return ``∂d/∂p`` of shape (T, m, P)."""
        return np.zeros((np.size(t), self.n_outputs, len(self.parameters)))

    def observe_blades(self, t: npt.ArrayLike, blade_flap: npt.ArrayLike) -> np.ndarray:
        """Map measured per-blade flap (T, N) to this model's output channels (T, m)."""
        raise NotImplementedError

    def equilibrium(self, t: npt.ArrayLike, p: np.ndarray, u: npt.ArrayLike) -> np.ndarray:
        """Steady state x = −F⁻¹ g at one time for a held input (time-invariant models only)."""
        F, g = self.system(np.atleast_1d(t)[:1], p, np.atleast_2d(u)[:1])
        return -np.linalg.solve(F[0], g[0])

    def equilibrium_jacobian(self, t: npt.ArrayLike, p: np.ndarray,
                             u: npt.ArrayLike) -> np.ndarray:
        """∂x_eq/∂p = −F⁻¹ (∂F/∂p x_eq + ∂g/∂p), shape (n, P)."""
        t1 = np.atleast_1d(t)[:1]
        u1 = np.atleast_2d(u)[:1]
        F, _ = self.system(t1, p, u1)
        dF, dg = self.system_jacobian(t1, p, u1)
        x_eq = self.equilibrium(t1, p, u1)
        rhs = np.einsum('kij,j->ik', dF[0], x_eq) + dg[0].T
        return -np.linalg.solve(F[0], rhs)

    def describe(self):
        """One-line description for tables and logs."""
        return f'{self.name}: states {", ".join(self.state_names)}'


# ------------------------------------------------------------------------------------------------
# Parameters
# ------------------------------------------------------------------------------------------------

def _collective_parameter(collective, angle_unit='rad'):
    if collective == 'delta':
        par = Parameter('delta', 'δ = γθ0', 'angle', 10.0, -200.0, 200.0,
                        'Lock number times collective pitch (report Ch.2 parameter 2)')
        if angle_unit == 'rad':
            return replace(par, nominal=10.0 * math.pi / 180.0, lower=-4.0, upper=4.0, unit='rad')
        return replace(par, unit='deg')
    if collective == 'theta0':
        par = Parameter('theta0', 'θ0', 'angle', 2.0, -45.0, 45.0,
                        'collective pitch (aerodynamic, from flapping)')
        if angle_unit == 'rad':
            return replace(par, nominal=math.radians(2.0), lower=-math.pi / 4,
                           upper=math.pi / 4, unit='rad')
        return replace(par, unit='deg')
    raise ValueError(f"collective must be 'delta' or 'theta0', not {collective!r}")


GAMMA = Parameter('gamma', 'γ', '-', 5.0, 0.05, 50.0, 'blade Lock number')
DAMPING = Parameter('A', 'A = γB⁴/8', '-', 0.5, 1e-3, 10.0, 'flap damping (Ch.2 eq. 27)')
#: the report's two-parameter cyclic wake (Ch.2 eq. 29): gain over time constant, 1/τ
CYCLIC_INFLOW = (
    Parameter('AL_over_tau', 'AL/τ', '-', 0.25, 0.0, 50.0, 'wake gain over wake time constant'),
    Parameter('inv_tau', '1/τ', '-', 0.125, 1e-4, 50.0, 'inverse wake time constant'),
)
#: the uniform inflow of the three-state inflow, normalised like the cyclic wake
UNIFORM_INFLOW = (
    Parameter('AL0_over_tau0', 'AL0/τ0', '-', 0.25, 0.0, 50.0,
              'uniform-inflow gain over its time constant'),
    Parameter('inv_tau0', '1/τ0', '-', 0.125, 1e-4, 50.0, 'inverse uniform-inflow time constant'),
)
INFLOW_STATES = {None: (), 'cyclic': ('lambda_I', 'lambda_II'),
                 'three_state': ('lambda_0', 'lambda_I', 'lambda_II')}
OUTPUTS = ('multiblade', 'blades', 'eq30')


# ------------------------------------------------------------------------------------------------
# The general rotor model
# ------------------------------------------------------------------------------------------------

class RotorModel(LinearModel):
    """
    N rigid flapping blades from one blade equation, with optional dynamic inflow (docs/models.md).

    Per blade k at ψ_k (module :mod:`rotor_id.physics.aerodynamics`):

        β_k″ + P² β_k = (γ/2) m_k(β_k, β_k′, θ_k − K_P β_k, λ0, λ_h)

    written either for one blade in its rotating frame (``blade=k``) or, with β = T(t) q, for
    the N multiblade coordinates q (``blade=None``): q″ = T⁻¹[β″ − 2T′q′ − T″q]. The optional
    inflow states (report sign, up positive) follow the aerodynamic load they are driven by:

        λ_h′ = −(1/τ) λ_h − (AL/τ)(4/B⁴) (2/N) Σ_k m_k (cos ψ_k, sin ψ_k)      h = I, II
        λ0′  = −(1/τ0) λ0 − (AL0/τ0)(4/B⁴) (1/N) Σ_k l_k                       (three_state)

    with l_k the blade's lift per γ/2. At μ = 0 the cyclic rows are exactly the report's
    Ch.2 eq. 29 (docs/models.md §9 gives the mapping).

    Parameters
    ----------
    rotor : RotorConstants
        N, μ, P, B, K_P.
    blade : int, optional
        Model this blade alone (1..N) in its rotating frame (the report's model 1).
    periodic : bool
        Keep the periodic coefficients (True) or average them over a revolution (the report's
        "omitting all periodic terms", model 2 constant).
    inflow : None, 'cyclic' or 'three_state'
        Dynamic inflow states.
    collective : 'theta0', 'delta' or None
        How the collective enters: parameter θ0, parameter δ = γθ0 (report Ch.2) or not at all
        (None: only when no retained state is driven by it, as in the report's wake model).
    damping_parameter : bool
        Parametrise the blade aerodynamics by A = γB⁴/8 (the wake model, Ch.2 eq. 27) instead of γ.
    outputs : 'multiblade', 'blades' or 'eq30'
        Measured channels: the multiblade coordinates the inputs drive, every blade's flap, or
        the report's eq. 30 tilt in blade 1's frame ((β1 − β3)/2, (β2 − β4)/2 for N = 4).
    interleave : bool
        State order [q1, q1′, q2, q2′, ...] with the tilt first (report's wake) instead of
        [q, q′] (report's multiblade); inflow states last.
    all_coordinates : bool
        Keep all N multiblade coordinates (the report's periodic model 2), not only those the
        measurement sees, the inputs drive or that feed those (below).
    angle_unit : 'rad' or 'deg'
        Unit of the collective parameter's nominal value and bounds.
    name : str
        Model name.

    Only coordinates that the measurement sees, the inputs drive, or that feed those are kept:
    the report's constant model drops βd (it decouples) and the report's wake keeps the tilt.

    """

    def __init__(self, rotor: RotorConstants = RotorConstants(), *, blade: int | None = None,
                 periodic: bool = True, inflow: str | None = None, collective: str = 'theta0',
                 damping_parameter: bool = False, outputs: str = 'multiblade',
                 interleave: bool = False, all_coordinates: bool = False,
                 angle_unit: str = 'rad', name: str = 'rotor') -> None:
        self.rotor = rotor.check()
        self.all_coordinates = bool(all_coordinates)
        self.name = name
        self.periodic = bool(periodic)
        self.inflow = inflow
        self.outputs = outputs
        self.damping_parameter = bool(damping_parameter)
        N = int(rotor.n_blades)
        if inflow not in INFLOW_STATES:
            raise ValueError(f"inflow must be None, 'cyclic' or 'three_state', not {inflow!r}")
        if blade is not None:
            if not 1 <= int(blade) <= N:
                raise ValueError(f'blade {blade} is not one of the blades 1..{N} of the rotor')
            if inflow is not None:
                raise ValueError('a dynamic inflow couples all blades: model the rotor in '
                                 'multiblade coordinates (blade=None)')
            self.blade: int | None = int(blade)
            self.blade_offset = 2.0 * math.pi * (int(blade) - 1) / N
            self.blades: tuple[int, ...] = (int(blade),)
            self._coords: tuple[tuple[str, str, int, str], ...] = (('beta', 'blade', 0, 'blade'),)
        else:
            if outputs not in OUTPUTS:
                raise ValueError(f"outputs must be one of {', '.join(OUTPUTS)}, not {outputs!r}")
            if outputs == 'eq30' and N < 3:
                raise ValueError(f'a {N}-bladed rotor has no cyclic flap: measure its blades '
                                 '(measurement: blades)')
            self.blade = None
            self.blades = tuple(range(1, N + 1))
            self._coords = coordinate_harmonics(N)
        self._inflow_names = INFLOW_STATES[inflow]
        nq, ni = len(self._coords), len(self._inflow_names)
        self._nq, self._nf = nq, 2 * nq + ni
        self._cache: dict[Any, Any] = {}
        self._constant = None
        self._harmonics = None
        self._build_parameters(collective, angle_unit)
        self._select_states(interleave)
        self._build_terms()
        self._build_outputs()

    # -- construction -------------------------------------------------------------------------
    def _build_parameters(self, collective, angle_unit):
        B = self.rotor.tip_loss
        if self.damping_parameter:
            aero = DAMPING
            self._aero_factor = 4.0 / B**4              # γ/2 = 4A/B⁴
        else:
            aero = GAMMA
            self._aero_factor = 0.5
        params = [aero]
        if self.inflow is not None:
            params += list(CYCLIC_INFLOW)
        if self.inflow == 'three_state':
            params += list(UNIFORM_INFLOW)
        self.collective = None
        if collective is not None:
            if collective == 'delta' and self.damping_parameter:
                raise ValueError('with A = γB⁴/8 the collective is the parameter theta0, '
                                 'not delta')
            params.append(_collective_parameter(collective, angle_unit))
            self.collective = collective
        self.parameters = tuple(params)

    def _index(self, name):
        return self.parameter_names.index(name)

    def _full_pieces(self, t):
        """Parameter-free building blocks over the full internal state [q, q′, λ]."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        rotor = self.rotor
        N, nq, nf = int(rotor.n_blades), self._nq, self._nf
        B, P, KP = rotor.tip_loss, rotor.flap_frequency, rotor.pitch_flap_coupling
        T = t.size
        if self.blade is not None:
            psi = t[:, None] + self.blade_offset
            Tb = np.ones((T, 1, 1))
            T1 = T2 = np.zeros((T, 1, 1))
            Tinv = np.ones((T, 1, 1))
        else:
            psi = t[:, None] + 2.0 * math.pi * np.arange(N) / N
            Tb = blade_from_multiblade_matrix(t, N)
            T1 = blade_from_multiblade_matrix(t, N, 1)
            T2 = blade_from_multiblade_matrix(t, N, 2)
            Tinv = multiblade_from_blade_matrix(t, N)
        Nb = psi.shape[1]
        q, qd = slice(0, nq), slice(nq, 2 * nq)
        Eb = np.zeros((T, Nb, nf))
        Eb[:, :, q] = Tb
        Ebr = np.zeros((T, Nb, nf))
        Ebr[:, :, q], Ebr[:, :, qd] = T1, Tb
        El0 = np.zeros((T, Nb, nf))
        Elh = np.zeros((T, Nb, nf))
        for i, lname in enumerate(self._inflow_names):
            col = 2 * nq + i
            if lname == 'lambda_0':
                El0[:, :, col] = 1.0
            elif lname == 'lambda_I':
                Elh[:, :, col] = np.cos(psi)
            else:
                Elh[:, :, col] = np.sin(psi)
        aero = blade_aerodynamics(psi, B, rotor.advance_ratio)
        pitch = np.stack([-np.sin(psi), np.cos(psi)], axis=-1)       # ∂θ_k/∂(θI, θII), eq. 3

        def load(kind):
            c = {key: aero[f'{kind}_{key}'][:, :, None]
                 for key in ('theta', 'rate', 'flap', 'lambda0', 'lambda1')}
            x_row = (-(KP * c['theta'] + c['flap']) * Eb - c['rate'] * Ebr
                     + c['lambda0'] * El0 + c['lambda1'] * Elh)
            return x_row, c['theta'] * pitch, c['theta'][:, :, 0]

        Mx, Mu, M0 = load('m')
        pieces = {'moment': (Mx, Mu, M0), 'Eb': Eb, 'Ebr': Ebr, 'Elh': Elh, 'Tinv': Tinv}
        F_const = np.zeros((T, nf, nf))
        F_const[:, q, qd] = np.eye(nq)
        F_const[:, qd, q] = Tinv @ (-P**2 * Tb - T2)
        F_const[:, qd, qd] = Tinv @ (-2.0 * T1)
        aero_F = np.zeros((T, nf, nf))
        aero_G = np.zeros((T, nf, 2))
        aero_g0 = np.zeros((T, nf))
        aero_F[:, qd] = Tinv @ Mx
        aero_G[:, qd] = Tinv @ Mu
        aero_g0[:, qd] = np.einsum('tij,tj->ti', Tinv, M0)
        pieces.update(F_const=F_const, aero=(aero_F, aero_G, aero_g0))
        if self.inflow is not None:
            scale = -4.0 / B**4
            wake = (np.zeros((T, nf, nf)), np.zeros((T, nf, 2)), np.zeros((T, nf)))
            decay = np.zeros((T, nf, nf))
            wake0 = (np.zeros((T, nf, nf)), np.zeros((T, nf, 2)), np.zeros((T, nf)))
            decay0 = np.zeros((T, nf, nf))
            Lx, Lu, L0 = load('l')
            for i, lname in enumerate(self._inflow_names):
                row = 2 * nq + i
                if lname == 'lambda_0':
                    w, (x_row, u_row, c_row), out, dec = np.full((T, Nb), 1.0 / N), \
                        (Lx, Lu, L0), wake0, decay0
                else:
                    trig = np.cos(psi) if lname == 'lambda_I' else np.sin(psi)
                    w, (x_row, u_row, c_row), out, dec = (2.0 / N) * trig, (Mx, Mu, M0), \
                        wake, decay
                out[0][:, row] = scale * np.einsum('tk,tkj->tj', w, x_row)
                out[1][:, row] = scale * np.einsum('tk,tkj->tj', w, u_row)
                out[2][:, row] = scale * np.einsum('tk,tk->t', w, c_row)
                dec[:, row, row] = -1.0
            pieces.update(wake=wake, decay=decay, wake0=wake0, decay0=decay0)
        for key in self._SYSTEM_KEYS:
            if key in pieces:
                value = pieces[key]
                for block in (value if isinstance(value, tuple) else (value,)):
                    _drop_rounding(block)
        return pieces

    def _sample_times(self):
        n = 8 * int(self.rotor.n_blades) + 32          # > every harmonic of the coefficients
        return 2.0 * math.pi * np.arange(n) / n

    def _select_states(self, interleave):
        """Keep the coordinates measured, driven, or feeding those (class docstring)."""
        nq, nf = self._nq, self._nf
        full = self._full_pieces(self._sample_times())
        coupling = np.abs(full['F_const']).max(axis=0) + np.abs(full['aero'][0]).max(axis=0)
        driven = np.abs(full['aero'][1]).max(axis=(0, 2))
        if self.collective is not None:
            driven = driven + np.abs(full['aero'][2]).max(axis=0)
        if self.inflow is not None:
            for key in ('wake', 'decay', 'wake0', 'decay0'):
                block = full[key] if key.startswith('decay') else full[key][0]
                coupling = coupling + np.abs(block).max(axis=0)
            for key in ('wake', 'wake0'):
                driven = driven + np.abs(full[key][1]).max(axis=(0, 2))
        if not self.periodic:
            coupling = np.abs(full['F_const'].mean(axis=0) + full['aero'][0].mean(axis=0))
            if self.inflow is not None:
                for key in ('wake', 'decay', 'wake0', 'decay0'):
                    block = full[key] if key.startswith('decay') else full[key][0]
                    coupling = coupling + np.abs(block.mean(axis=0))
            driven = np.abs(full['aero'][1].mean(axis=0)).max(axis=1)
            if self.collective is not None:
                driven = driven + np.abs(full['aero'][2].mean(axis=0))
        tol = 1e-12

        def node(i):        # state index -> graph node: coordinate index or inflow
            return i % nq if i < 2 * nq else i - nq

        n_nodes = nq + len(self._inflow_names)
        edge = np.zeros((n_nodes, n_nodes), dtype=bool)      # edge[i, j]: j feeds i
        for i in range(nf):
            for j in range(nf):
                if coupling[i, j] > tol:
                    edge[node(i), node(j)] = True
        forced = {node(i) for i in range(nf) if driven[i] > tol}
        names = [c[0] for c in self._coords]
        if self.blade is not None or self.outputs == 'blades' or self.all_coordinates:
            measured = set(range(nq))
        elif self.outputs == 'eq30':
            measured = {names.index('beta_I'), names.index('beta_II')}
        else:                                   # the coordinates the inputs reach
            measured, frontier = set(forced), list(forced)
            while frontier:
                j = frontier.pop()
                for i in np.flatnonzero(edge[:, j]):
                    if i not in measured:
                        measured.add(int(i))
                        frontier.append(int(i))
            measured = {i for i in measured if i < nq}
        keep, frontier = set(measured), list(measured)
        while frontier:                         # everything that feeds the measured states
            i = frontier.pop()
            for j in np.flatnonzero(edge[i]):
                if j not in keep:
                    keep.add(int(j))
                    frontier.append(int(j))
        missing = [name for i, name in enumerate(self._inflow_names) if nq + i not in keep]
        if missing:
            raise ValueError(f'the inflow states {", ".join(missing)} do not reach the measured '
                             'flap here (at advance ratio 0 the uniform inflow only moves the '
                             'coning): measure every blade (measurement: blades) or use '
                             'inflow: cyclic')
        coords = sorted(i for i in keep if i < nq)
        self._measured = sorted(measured)
        if interleave:
            tilt = [i for i in coords if names[i] in ('beta_I', 'beta_II')]
            coords = tilt + [i for i in coords if i not in tilt]
            order = [s for i in coords for s in (i, nq + i)]
        else:
            order = coords + [nq + i for i in coords]
        order += [2 * nq + i for i in range(len(self._inflow_names))]
        self._keep = np.array(order, dtype=int)
        self._kept_coords = coords
        self.state_names = tuple(
            (names[s] if s < nq else f'{names[s - nq]}_dot') if s < 2 * nq
            else self._inflow_names[s - 2 * nq] for s in order)
        # the collective is a parameter only if it drives a kept state (always for γ models)
        if self.collective is not None and self.damping_parameter:
            g0 = np.abs(full['aero'][2]).max(axis=0)
            if self.inflow is not None:
                g0 = (g0 + np.abs(full['wake'][2]).max(axis=0)
                      + np.abs(full['wake0'][2]).max(axis=0))
            if not np.any(g0[self._keep] > tol):
                self.parameters = tuple(par for par in self.parameters
                                        if par.name not in ('theta0', 'delta'))
                self.collective = None
        # time invariance: every kept block the same at every sample time
        sub = self._restrict(full)
        self.time_invariant = not self.periodic or all(
            np.allclose(block, block[:1], rtol=0.0, atol=1e-12) for block in self._blocks(sub))

    def _blocks(self, pieces):
        for key in ('F_const', 'aero', 'wake', 'decay', 'wake0', 'decay0'):
            if key in pieces:
                value = pieces[key]
                yield from (value if isinstance(value, tuple) else (value,))

    def _restrict(self, full):
        k = self._keep
        out = {}
        for key, value in full.items():
            if key in ('F_const', 'decay', 'decay0'):
                out[key] = value[:, k][:, :, k]
            elif key in ('aero', 'wake', 'wake0'):
                F, G, g0 = value
                out[key] = (F[:, k][:, :, k], G[:, k], g0[:, k])
            elif key == 'moment':
                Mx, Mu, M0 = value
                out[key] = (Mx[:, :, k], Mu, M0)
            elif key in ('Eb', 'Ebr', 'Elh'):
                out[key] = value[:, :, k]
            else:
                out[key] = value
        return out

    def _build_terms(self):
        """List the terms of F = F_const + Σ c·Πp·F_k and g = Σ c·Πp·(G_k u + g0_k)."""
        ia = 0
        terms = [((ia,), self._aero_factor, 'aero', 'F'), ((ia,), self._aero_factor, 'aero', 'G')]
        if self.collective == 'theta0':
            terms.append(((ia, self._index('theta0')), self._aero_factor, 'aero', 'g0'))
        elif self.collective == 'delta':
            terms.append(((self._index('delta'),), 0.5, 'aero', 'g0'))     # (γ/2)θ0 = δ/2
        if self.inflow is not None:
            ic, ir = self._index('AL_over_tau'), self._index('inv_tau')
            terms += [((ic,), 1.0, 'wake', 'F'), ((ic,), 1.0, 'wake', 'G'),
                      ((ir,), 1.0, 'decay', 'F')]
            if self.collective == 'theta0':
                terms.append(((ic, self._index('theta0')), 1.0, 'wake', 'g0'))
        if self.inflow == 'three_state':
            ic0, ir0 = self._index('AL0_over_tau0'), self._index('inv_tau0')
            terms += [((ic0,), 1.0, 'wake0', 'F'), ((ic0,), 1.0, 'wake0', 'G'),
                      ((ir0,), 1.0, 'decay0', 'F')]
            if self.collective == 'theta0':
                terms.append(((ic0, self._index('theta0')), 1.0, 'wake0', 'g0'))
        self._terms = terms

    def _build_outputs(self):
        N = int(self.rotor.n_blades)
        names = [c[0] for c in self._coords]
        if self.blade is not None:
            self.outputs = 'blade'
            self.output_names = (f'beta_{self.blade}',)
        elif self.outputs == 'blades':
            self.output_names = tuple(f'beta_{k}' for k in range(1, N + 1))
        elif self.outputs == 'eq30':
            self.output_names = ('beta_m1', 'beta_m2')
        else:
            self.output_names = tuple(names[i] for i in self._kept_coords
                                      if i in self._measured)

    def with_rotor(self, **constants: Any) -> 'RotorModel':
        """
        Return a copy with some rotor constants changed (e.g. ``flap_frequency``).

        The copy computes its own parameter-free blocks: a shallow copy would share this
        model's caches and go on returning blocks built with the old constants.
        """
        model = copy.copy(self)
        model.rotor = replace(self.rotor, **constants).check()
        model._cache, model._constant, model._harmonics = {}, None, None
        return model

    def __getstate__(self) -> dict[str, Any]:
        """Pickle without the per-grid blocks: a fit's model travels between processes."""
        state = self.__dict__.copy()
        state['_cache'] = {}
        return state

    # -- evaluation ---------------------------------------------------------------------------
    _SYSTEM_KEYS = ('F_const', 'aero', 'wake', 'decay', 'wake0', 'decay0')

    def _cached(self, kind, t, compute):
        key = (kind, t.size, hash(t.tobytes()))
        hit = self._cache.get(key)
        if hit is None:
            if len(self._cache) > 8:
                self._cache.clear()
            hit = self._cache[key] = compute()
        return hit

    def _pieces(self, t):
        """
        Return the parameter-free blocks of F and g at times t (computed once per time grid).

        A time-invariant model's blocks are computed once and have length 1 along time.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if self.time_invariant:
            if self._constant is None:
                if self.periodic:
                    one = self._restrict(self._full_pieces(np.zeros(1)))
                else:
                    one = _mean_pieces(self._restrict(self._full_pieces(self._sample_times())))
                self._constant = {k: v for k, v in one.items() if k in self._SYSTEM_KEYS}
            return self._constant

        if self._harmonics is None:
            full = self._restrict(self._full_pieces(self._sample_times()))
            self._harmonics = _Harmonics({k: v for k, v in full.items()
                                          if k in self._SYSTEM_KEYS})
        return self._cached('system', t, lambda: self._harmonics.at(t))

    def _blade_pieces(self, t):
        """Return the blade matrices (flap, rate, inflow, moment, T⁻¹) at times t, periodic."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return self._cached('blades', t, lambda: self._restrict(self._full_pieces(t)))

    def _term_value(self, params, factor, p):
        value = factor
        for i in params:
            value = value * p[i]
        return value

    def _block(self, pieces, key, part):
        if part == 'F':
            return pieces[key] if key.startswith('decay') else pieces[key][0]
        return pieces[key][1 if part == 'G' else 2]

    def _input_term(self, pieces, key, part, ucyc):
        """Return the g term of one block: G u_cyclic (T, n) or the collective column (L, n)."""
        if part == 'G':
            return np.matmul(pieces[key][1], ucyc[:, :, None])[:, :, 0]
        return pieces[key][2]

    @via_compact
    def system(self, t: npt.ArrayLike, p: np.ndarray,
               u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        F, g = self.system_compact(t, p, u)
        return full_along_time(F, g.shape[0]), g

    def system_compact(self, t: npt.ArrayLike, p: np.ndarray,
                       u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`system` with F of length 1 along time where it is constant (time-invariant)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        p = np.asarray(p, dtype=float)
        ucyc = np.asarray(u, dtype=float)[:, 1:3]
        pieces = self._pieces(t)
        F = pieces['F_const'].copy()                  # length 1 along time if time-invariant
        g = np.zeros((t.size, self.n_states))
        for params, factor, key, part in self._terms:
            c = self._term_value(params, factor, p)
            if part == 'F':
                F += c * self._block(pieces, key, part)
            else:
                g += c * self._input_term(pieces, key, part, ucyc)
        return F, g

    @via_compact
    def system_jacobian(self, t: npt.ArrayLike, p: np.ndarray,
                        u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        dF, dg = self.system_jacobian_compact(t, p, u)
        return full_along_time(dF, dg.shape[0]), dg

    def system_jacobian_compact(self, t: npt.ArrayLike, p: np.ndarray,
                                u: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`system_jacobian` with ∂F/∂p of length 1 along time where F is constant."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        p = np.asarray(p, dtype=float)
        ucyc = np.asarray(u, dtype=float)[:, 1:3]
        pieces = self._pieces(t)
        n, P = self.n_states, len(self.parameters)
        dF = np.zeros((pieces['F_const'].shape[0], P, n, n))
        dg = np.zeros((t.size, P, n))
        for params, factor, key, part in self._terms:
            for pos, i in enumerate(params):
                c = self._term_value(params[:pos] + params[pos + 1:], factor, p)
                if part == 'F':
                    dF[:, i] += c * self._block(pieces, key, part)
                else:
                    dg[:, i] += c * self._input_term(pieces, key, part, ucyc)
        return dF, dg

    # -- blades and channels ------------------------------------------------------------------
    def lock_number(self, p: np.ndarray) -> tuple[float, np.ndarray]:
        """γ at the parameter vector p, and ∂γ/∂p."""
        d = np.zeros(len(self.parameters))
        scale = 2.0 * self._aero_factor                # γ = 2·(γ/2)
        d[0] = scale
        return scale * float(p[0]), d

    def blade_azimuth(self, t: npt.ArrayLike) -> np.ndarray:
        """(T, Nb) azimuths of the modelled blades."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if self.blade is not None:
            return t[:, None] + self.blade_offset
        N = int(self.rotor.n_blades)
        return t[:, None] + 2.0 * math.pi * np.arange(N) / N

    def blade_flap_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """Hb (T, Nb, n): flap of each modelled blade, β_k = Hb x."""
        return self._blade_pieces(t)['Eb'].copy()

    def blade_flap_rate_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """Hbr (T, Nb, n): flap rate of each modelled blade, β_k′ = Hbr x."""
        return self._blade_pieces(t)['Ebr'].copy()

    def blade_inflow_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """Hl (T, Nb, n): first-harmonic inflow at each blade, λ_k = λI cos ψ_k + λII sin ψ_k."""
        return self._blade_pieces(t)['Elh'].copy()

    def blade_force_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """G (T, n, Nb): change of x′ for a unit flapping acceleration of blade k alone."""
        Tinv = self._blade_pieces(t)['Tinv']
        nq = self._nq
        full = np.zeros((Tinv.shape[0], self._nf, Tinv.shape[2]))
        full[:, nq:2 * nq] = Tinv
        return full[:, self._keep]

    def blade_moment(self, t: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Return the blades' aerodynamic moment per γ/2 (module aerodynamics): linear in x, u, θ0.

        Returns ``(Mx (T, Nb, n), Mu (T, Nb, 2), M0 (T, Nb))``: m_k = Mx x + Mu [θI, θII] + M0 θ0.
        """
        Mx, Mu, M0 = self._blade_pieces(t)['moment']
        return Mx.copy(), Mu.copy(), M0.copy()

    def channel_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        """C (T, m, N): the model's output channels from the N blades' flap, y = C β."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        N = int(self.rotor.n_blades)
        if self.blade is not None:
            C = np.zeros((t.size, 1, N))
            C[:, 0, self.blade - 1] = 1.0
            return C
        if self.outputs == 'blades':
            return np.broadcast_to(np.eye(N), (t.size, N, N)).copy()
        if self.outputs == 'eq30':
            offsets = 2.0 * math.pi * np.arange(N) / N        # ψ_k − t
            rows = (2.0 / N) * np.stack([np.cos(offsets), np.sin(offsets)])
            return np.broadcast_to(rows, (t.size, 2, N)).copy()
        Tinv = multiblade_from_blade_matrix(t, N)
        names = [c[0] for c in self._coords]
        return Tinv[:, [names.index(n) for n in self.output_names]]

    def output_matrix(self, t: npt.ArrayLike) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if self.outputs in ('blade', 'blades'):
            return self.blade_flap_matrix(t)
        H = np.zeros((t.size, self.n_outputs, self.n_states))
        if self.outputs == 'eq30':                  # report eq. 30: the tilt in blade 1's frame
            iI, iII = self.state_names.index('beta_I'), self.state_names.index('beta_II')
            H[:, 0, iI], H[:, 0, iII] = np.cos(t), np.sin(t)
            H[:, 1, iI], H[:, 1, iII] = -np.sin(t), np.cos(t)
            return H
        for row, name in enumerate(self.output_names):
            H[:, row, self.state_names.index(name)] = 1.0
        return H

    def observe_blades(self, t: npt.ArrayLike, blade_flap: npt.ArrayLike) -> np.ndarray:
        blade_flap = np.asarray(blade_flap, dtype=float)
        if self.outputs == 'blade':
            return blade_flap[:, self.blade - 1:self.blade]  # type: ignore[operator, index]
        if self.outputs == 'blades':
            return blade_flap
        return np.einsum('tij,tj->ti', self.channel_matrix(t), blade_flap)

    # -- trim ---------------------------------------------------------------------------------
    def trim_state(self, p: np.ndarray, collective: float, t: float = 0.0,
                   steps_per_rev: int = 512) -> np.ndarray:
        """
        State at time t of the rotor trimmed at collective pitch only (no cyclic).

        The equilibrium of a time-invariant model; otherwise the periodic response, found exactly
        (to the RK4 error of ``steps_per_rev`` steps) from the one-revolution map x(t + 2π) =
        Φ x(t) + c as x = (I − Φ)⁻¹ c (Floquet), so that no settling length is needed.
        """
        u = np.array([[float(collective), 0.0, 0.0]])
        if self.time_invariant:
            return self.equilibrium(np.array([float(t)]), p, u)
        h = 2.0 * math.pi / steps_per_rev
        grid = float(t) + 0.5 * h * np.arange(2 * steps_per_rev + 1)
        F, g = self.system(grid, p, np.repeat(u, grid.size, axis=0))
        n = self.n_states
        # propagate [Φ | c] as the augmented system z′ = [[F, g], [0, 0]] z
        A = np.zeros((grid.size, n + 1, n + 1))
        A[:, :n, :n], A[:, :n, n] = F, g
        Z = np.eye(n + 1)
        for i in range(steps_per_rev):
            a0, a1, a2 = A[2 * i], A[2 * i + 1], A[2 * i + 2]
            k1 = a0 @ Z
            k2 = a1 @ (Z + 0.5 * h * k1)
            k3 = a1 @ (Z + 0.5 * h * k2)
            k4 = a2 @ (Z + h * k3)
            Z = Z + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        return np.linalg.solve(np.eye(n) - Z[:n, :n], Z[:n, n])

    def coning(self, p: np.ndarray, collective: float) -> float:
        """
        Steady coning β0 = Aθ0/(P² + A K_P) to add to blades of a model without a β0 state.

        Zero for models that carry β0 (or a single blade). The report's wake model drops the
        coning, which decouples at μ = 0 (docs/models.md §3.1); a flap sensor still sees it.
        """
        if 'beta_0' in self.state_names or self.blade is not None:
            return 0.0
        r = self.rotor
        return hover_coning(self.lock_number(p)[0], collective, r.flap_frequency, r.tip_loss,
                            r.pitch_flap_coupling)

    def describe(self) -> str:
        """One-line description for tables and logs."""
        r = self.rotor
        return (f'{self.name}: N = {r.n_blades}, mu = {r.advance_ratio:g}, '
                f'P = {r.flap_frequency:g}, B = {r.tip_loss:g}, K_P = {r.pitch_flap_coupling:g}; '
                f'states {", ".join(self.state_names)}')


def _drop_rounding(block):
    """
    Zero in place the entries of a coefficient block that are rounding residue of exact zeros.

    Sums such as Σ_k cos ψ_k sin ψ_k vanish exactly but come out as 1e-17; left in, they make
    an exactly dependent parameter combination look merely ill-conditioned. A physical
    coefficient 1e-14 times the block's largest (μ² below 1e-14) is negligible anyway.
    """
    scale = np.max(np.abs(block)) if block.size else 0.0
    block[np.abs(block) < 1e-14 * scale] = 0.0


class _Harmonics:
    """
    Periodic coefficient blocks as trigonometric polynomials in ψ, evaluated on any time grid.

    Every block is a finite Fourier series in ψ: the blade coefficients are polynomials in
    μ sin ψ and cos ψ (rotor_id.physics.aerodynamics) and the multiblade transforms are first
    harmonics of the blade azimuths. So the series found from one revolution of samples
    (:meth:`RotorModel._sample_times`, more samples than twice the highest harmonic) is the
    block itself at every ψ, and evaluating it costs a product with a few harmonics instead of
    rebuilding every blade's matrices: an azimuth-offset fit evaluates the rotor on a newly
    shifted grid at every iteration. Coefficients that are rounding residue of exact zeros
    are zeroed, per block as in :func:`_drop_rounding` and below 1e-14 of the largest of all
    blocks, so an exact zero stays exactly zero.
    """

    def __init__(self, pieces: Mapping[str, np.ndarray]) -> None:
        self._layout, columns = [], []
        for key, value in pieces.items():
            blocks = value if isinstance(value, tuple) else (value,)
            self._layout.append((key, isinstance(value, tuple),
                                 [block.shape[1:] for block in blocks]))
            columns += [block.reshape(block.shape[0], -1) for block in blocks]
        samples = columns[0].shape[0]
        spectra = []
        for column in columns:               # c_h = (1/n) Σ_k x(2πk/n) e^{-ihψ_k}
            spectrum = np.fft.rfft(column, axis=0) / samples
            _drop_rounding(spectrum)
            spectra.append(spectrum)
        spectrum = np.concatenate(spectra, axis=1)
        # and a block that is all rounding residue (a sum that vanishes for this N) is zero
        spectrum[np.abs(spectrum) < 1e-14 * np.max(np.abs(spectrum), initial=0.0)] = 0.0
        present = np.flatnonzero(np.any(spectrum != 0.0, axis=1))
        if present.size and present[-1] >= samples // 4:
            raise ValueError(f'a coefficient block has harmonic {present[-1]} of ψ, too close '
                             f'to the {samples} samples per revolution to be resolved')
        self._orders = present[present > 0]
        # x(ψ) = c_0 + Σ_h 2 Re(c_h) cos hψ − 2 Im(c_h) sin hψ
        rows = [spectrum[0].real] if 0 in present else [np.zeros(spectrum.shape[1])]
        for h in self._orders:
            rows += [2.0 * spectrum[h].real, -2.0 * spectrum[h].imag]
        coefficients = np.array(rows)
        self._columns = np.flatnonzero(np.any(coefficients != 0.0, axis=0))
        self._coefficients = coefficients[:, self._columns]
        self._width = spectrum.shape[1]

    def at(self, t: np.ndarray) -> dict[str, Any]:
        """Return the blocks at times t (dict like the pieces given, arrays of length t.size)."""
        angle = np.multiply.outer(t, self._orders)
        basis = np.empty((t.size, 1 + 2 * self._orders.size))
        basis[:, 0] = 1.0
        basis[:, 1::2], basis[:, 2::2] = np.cos(angle), np.sin(angle)
        flat = np.zeros((t.size, self._width))
        flat[:, self._columns] = basis @ self._coefficients
        out, start = {}, 0
        for key, is_tuple, shapes in self._layout:
            blocks = []
            for shape in shapes:
                size = int(np.prod(shape))
                blocks.append(flat[:, start:start + size].reshape((t.size,) + shape))
                start += size
            out[key] = tuple(blocks) if is_tuple else blocks[0]
        return out


def _mean_pieces(pieces):
    out = {}
    for key, value in pieces.items():
        if isinstance(value, tuple):
            out[key] = tuple(v.mean(axis=0, keepdims=True) for v in value)
        else:
            out[key] = value.mean(axis=0, keepdims=True)
        for block in (out[key] if isinstance(out[key], tuple) else (out[key],)):
            _drop_rounding(block)
    return out


# ------------------------------------------------------------------------------------------------
# The report's models (docs/models.md §1-3) as special cases
# ------------------------------------------------------------------------------------------------

class SingleBlade(RotorModel):
    """
    Model 1: one blade in its rotating frame, periodic coefficients (report Ch.3 eq. 24).

    States x = [β, β′], output y = β of blade ``blade``; parameters γ and θ0 (or δ = γθ0).
    """

    def __init__(self, rotor: RotorConstants = RotorConstants(), collective: str = 'theta0',
                 angle_unit: str = 'rad', blade: int = 1) -> None:
        super().__init__(rotor, blade=blade, collective=collective, angle_unit=angle_unit,
                         name='single_blade')
        self.state_names = ('beta', 'beta_dot')


class Multiblade(RotorModel):
    """
    Model 2: the rotor in multiblade coordinates with periodic coefficients (report Ch.2 §2.1).

    For N = 4: q = [β0, βI, βII, βd], x = [q, q′]. ``outputs='multiblade'`` measures q,
    ``outputs='blades'`` every blade's flap, ``outputs='eq30'`` the tilt in blade 1's frame.
    """

    def __init__(self, rotor: RotorConstants = RotorConstants(), collective: str = 'theta0',
                 angle_unit: str = 'rad', outputs: str = 'multiblade') -> None:
        super().__init__(rotor, collective=collective, angle_unit=angle_unit, outputs=outputs,
                         all_coordinates=True, name='multiblade')


class MultibladeConstant(RotorModel):
    """
    Model 2 with its periodic coefficients averaged over a revolution.

    The report's "omitting all periodic terms".

    For N = 4: x = [β0, βI, βII, β0′, βI′, βII′] (βd decouples and is dropped), y = [β0, βI, βII].
    Time-invariant.
    """

    def __init__(self, rotor: RotorConstants = RotorConstants(), collective: str = 'theta0',
                 angle_unit: str = 'rad', outputs: str = 'multiblade') -> None:
        super().__init__(rotor, periodic=False, collective=collective, angle_unit=angle_unit,
                         outputs=outputs, name='multiblade_constant')


class MultibladeWake(RotorModel):
    """
    Model 3: the rotor with a dynamic inflow, parametrised by A = γB⁴/8 (report Ch.2 eq. 29).

    With the defaults (μ = 0, ``inflow='cyclic'``, ``outputs='eq30'``) this is the report's model:
    x = [βI, βI′, βII, βII′, λI, λII], p = [A, AL/τ, 1/τ], y = report eq. 30. Any N ≥ 3, any μ,
    ``inflow='three_state'`` (adds λ0 with AL0/τ0, 1/τ0) and ``outputs='blades'`` or
    ``'multiblade'`` generalise it (docs/models.md §9); the collective θ0 becomes a parameter
    whenever it reaches a modelled state (μ > 0, or coning measured).
    """

    def __init__(self, rotor: RotorConstants = RotorConstants(advance_ratio=0.0),
                 collective: str = 'theta0', angle_unit: str = 'rad', outputs: str = 'eq30',
                 inflow: str = 'cyclic') -> None:
        if inflow not in ('cyclic', 'three_state'):
            raise ValueError(f"inflow must be 'cyclic' or 'three_state', not {inflow!r}")
        super().__init__(rotor, inflow=inflow, collective=collective, damping_parameter=True,
                         outputs=outputs, interleave=True, angle_unit=angle_unit,
                         name='multiblade_wake')


def multiblade_from_blade_flap(t: npt.ArrayLike, blade_flap: npt.ArrayLike) -> np.ndarray:
    """Return the multiblade coordinates (T, N) of N blade flap angles (docs/models.md §8)."""
    coords = multiblade_coordinates(blade_flap, np.atleast_1d(np.asarray(t, dtype=float)))
    return np.column_stack(list(coords.values()))


def lock_number_from_known(known: Mapping[str, float], model: RotorModel) -> dict[str, float]:
    """Translate a known Lock number into the model's aerodynamic parameter (γ, or A = γB⁴/8)."""
    known = dict(known)
    if getattr(model, 'damping_parameter', False) and 'gamma' in known and 'A' not in known:
        known['A'] = flap_damping(known.pop('gamma'), model.rotor.tip_loss)    # Ch.2 eq. 27
    return known


MODEL_NAMES = ('single_blade', 'multiblade', 'multiblade_constant', 'multiblade_wake')


def build_model(name: str, rotor: RotorConstants = RotorConstants(), collective: str = 'theta0',
                angle_unit: str = 'rad', **options: Any) -> RotorModel:
    """
    Model by its run-description name (docs/run_description.md).

    Options: ``blade`` (single_blade), ``outputs`` ('multiblade' | 'blades', and 'eq30' for
    the wake), ``inflow`` ('cyclic' | 'three_state', wake only).
    """
    if name == 'single_blade':
        return SingleBlade(rotor, collective, angle_unit, **options)
    if name == 'multiblade':
        return Multiblade(rotor, collective, angle_unit, **options)
    if name == 'multiblade_constant':
        return MultibladeConstant(rotor, collective, angle_unit, **options)
    if name == 'multiblade_wake':
        return MultibladeWake(rotor, 'theta0', angle_unit, **options)
    raise ValueError(f'unknown model {name!r}; choose one of {", ".join(MODEL_NAMES)}')


# ------------------------------------------------------------------------------------------------
# Directional frequency response (harmonic transfer function) of the cyclic flapping
# ------------------------------------------------------------------------------------------------

#: Fourier orders of the periodic coefficients kept on each side of the input frequency: the
#: periodic terms of a flapping rotor are N/2 or N per rev and their couplings fall fast with
#: the order (μ² per step), so six steps either side converge to rounding for μ < 1.
HARMONIC_ORDERS = 6


@dataclass(frozen=True)
class DirectionalResponse:
    """
    The directional frequency response of the fixed-frame cyclic flap to the cyclic pitch.

    In complex coordinates β_c = βI + iβII and θ_c = θI + iθII (θI forward, θII lateral
    cyclic, the report's eq. 3, docs/models.md §0), a cyclic pitch θ_c = e^{iωt} (ω in per
    rev, signed: ω > 0 rotates with the rotor, progressing stirring) gives the flap

        β_c(t) = Σ_n H_n(ω) e^{i(ω + n)t} + Σ_n M_n(ω) e^{-i(ω + n)t}

    ``principal`` is H_0(ω) (what a frequency-response estimate at ω measures), ``sidebands``
    the H_n for the orders n the periodic coefficients produce (none for a time-invariant
    model: every μ = 0 rotor and the averaged models), ``mirrors`` the M_n (the response at
    the mirrored frequency, zero for an axisymmetric rotor). ``jacobian`` is ∂H_0/∂p (F, P)
    when asked for, else None.
    """

    frequency: np.ndarray
    principal: np.ndarray
    sidebands: dict
    mirrors: dict
    jacobian: object = None


def _fourier_blocks(model, p, with_jacobian):
    """
    F, G (cyclic input columns) and their parameter derivatives as Fourier series in t.

    Returns ``(orders, F_k, G_k, dF_k, dG_k)`` with F_k (K, n, n) the coefficients of
    e^{i·orders[k]·t}; the dynamics of every model here are trigonometric polynomials of the
    azimuth of period 2π, so the series from one revolution of samples is exact.
    """
    N = int(getattr(getattr(model, 'rotor', None), 'n_blades', 4))
    samples = 8 * N + 32
    t = 2.0 * math.pi * np.arange(samples) / samples
    zero = np.zeros((samples, 3))
    unit_I, unit_II = zero.copy(), zero.copy()
    unit_I[:, 1], unit_II[:, 2] = 1.0, 1.0
    F, g0 = model.system(t, p, zero)
    G = np.stack([model.system(t, p, unit_I)[1] - g0,
                  model.system(t, p, unit_II)[1] - g0], axis=-1)          # (T, n, 2)
    blocks = [F, G]
    if with_jacobian:
        dF, dg0 = model.system_jacobian(t, p, zero)
        dG = np.stack([model.system_jacobian(t, p, unit_I)[1] - dg0,
                       model.system_jacobian(t, p, unit_II)[1] - dg0], axis=-1)   # (T, P, n, 2)
        blocks += [dF, dG]
    spectra = [np.fft.fft(b, axis=0) / samples for b in blocks]
    scale = max(np.max(np.abs(s)) for s in spectra[:2])
    present = np.zeros(samples, dtype=bool)
    for s in spectra:
        present |= np.any(np.abs(s.reshape(samples, -1)) > 1e-12 * scale, axis=1)
    orders = np.fft.fftfreq(samples, 1.0 / samples).astype(int)
    keep = np.flatnonzero(present & (np.abs(orders) < samples // 4))
    out = [orders[keep]] + [s[keep] for s in spectra]
    return tuple(out) + ((None, None) if not with_jacobian else ())


def directional_frequency_response(model: LinearModel, p: np.ndarray, frequency: npt.ArrayLike,
                                   jacobian: bool = False,
                                   orders: int = HARMONIC_ORDERS) -> DirectionalResponse:
    """
    Return the directional FRF β_c/θ_c of ``model`` at ``p`` (see :class:`DirectionalResponse`).

    ``frequency`` is the input frequency in per rev (signed). A time-invariant model gives the
    transfer function ½[1, i] C (iωI − F)⁻¹ G [1, −i]ᵀ exactly; a periodic model its harmonic
    transfer function (Wereley), the state expanded as Σ_n X_n e^{i(ω + n)t} over the orders
    n = d·(−orders … orders), d the base order of its periodic coefficients. The model must
    carry βI and βII (every multiblade model of N ≥ 3 blades).
    """
    names = list(model.state_names)
    if 'beta_I' not in names or 'beta_II' not in names:
        raise ValueError(f'{model.name} has no fixed-frame cyclic flap states (beta_I, '
                         'beta_II): its directional frequency response is not defined; use a '
                         'multiblade model of a rotor with 3 or more blades')
    p = np.asarray(p, dtype=float)
    omega = np.atleast_1d(np.asarray(frequency, dtype=float))
    k_orders, Fk, Gk, dFk, dGk = _fourier_blocks(model, p, jacobian)
    periodic = k_orders[k_orders != 0]
    base = int(np.gcd.reduce(np.abs(periodic))) if periodic.size else 0
    shifts = base * np.arange(-orders, orders + 1) if base else np.zeros(1, dtype=int)
    n, S = len(names), shifts.size
    v = 0.5 * np.array([1.0, -1.0j])               # θ_c = e^{iωt}: [θI, θII] = v e^{iωt} + c.c.
    lookup = {int(k): i for i, k in enumerate(k_orders)}

    def toeplitz(blocks):                           # block (a, b) = blocks of order a − b
        out = np.zeros((S * n, S * n) + blocks.shape[3:], dtype=complex)
        for a, sa in enumerate(shifts):
            for b, sb in enumerate(shifts):
                k = lookup.get(int(sa - sb))
                if k is not None:
                    out[a * n:(a + 1) * n, b * n:(b + 1) * n] = blocks[k]
        return out

    def column(blocks):                             # forcing of harmonic s: order s
        out = np.zeros((S * n,) + blocks.shape[2:], dtype=complex)
        for a, sa in enumerate(shifts):
            k = lookup.get(int(sa))
            if k is not None:
                out[a * n:(a + 1) * n] = blocks[k]
        return out

    F_big = toeplitz(Fk)
    B = column(Gk) @ v
    if jacobian:
        P = dFk.shape[1]
        dF_big = [toeplitz(dFk[:, j]) for j in range(P)]
        dB = [column(dGk[:, j]) @ v for j in range(P)]
    iI, iII = names.index('beta_I'), names.index('beta_II')
    X = np.empty((omega.size, S, n), dtype=complex)
    dH = np.empty((omega.size, len(p)), dtype=complex) if jacobian else None
    centre = int(np.flatnonzero(shifts == 0)[0])
    for f, w in enumerate(omega):
        A = np.diag(np.repeat(1j * (w + shifts), n)) - F_big
        lu = np.linalg.solve(A, np.column_stack([B] + ([] if not jacobian else [])))
        x = lu[:, 0]
        X[f] = x.reshape(S, n)
        if jacobian:
            rhs = np.column_stack([dF_big[j] @ x + dB[j] for j in range(len(p))])
            dx = np.linalg.solve(A, rhs)[centre * n:(centre + 1) * n]
            dH[f] = dx[iI] + 1j * dx[iII]  # type: ignore[index]
    principal = X[:, centre, iI] + 1j * X[:, centre, iII]
    sidebands, mirrors = {}, {}
    for a, s in enumerate(shifts):
        mirrors[int(s)] = np.conj(X[:, a, iI]) + 1j * np.conj(X[:, a, iII])
        if s != 0:
            sidebands[int(s)] = X[:, a, iI] + 1j * X[:, a, iII]
    return DirectionalResponse(frequency=omega, principal=principal, sidebands=sidebands,
                               mirrors=mirrors, jacobian=dH)
