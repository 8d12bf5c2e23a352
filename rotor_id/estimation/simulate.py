"""
The one simulator: linear time-varying models, with exact discrete sensitivities.

Integration is classical fourth-order Runge-Kutta with ``substeps`` equal steps between samples.
For a linear system one RK4 step is an affine map ``x⁺ = Φ x + c`` whose Φ and c are polynomials
in F and g at the step's start, middle and end. The sensitivities S = ∂x/∂p are propagated with
the derivative of that same map,

    S⁺ = Φ S + (∂Φ/∂p) x + ∂c/∂p,

which is what the report's sensitivity equations (docs/models.md §0.1,
S′ = F S + (∂F/∂p) x + ∂g/∂p) become under RK4; so the sensitivities are the exact derivatives
of the simulated samples, and agree with finite differences of :func:`simulate` to rounding.

Everything is vectorised over time (bench/iteration_cost.py measured the gain):

* the step maps Φ, c, and the sensitivity forcing (∂Φ/∂p) x + ∂c/∂p carried through the RK4
  stages as vectors once the states are known (no (∂Φ/∂p) matrices are formed);
* the RK4 steps of one sample interval are composed into one map per interval;
* the two linear recursions, first x, then S with its now known forcing, run as doubling scans
  (log₂ T vectorised passes with products of 1, 2, 4, … successive maps) instead of a Python
  loop over steps;
* a time-invariant system (F constant, equal steps: the wake and constant-coefficient models)
  builds Φ once instead of once per step.

With the compiled kernels loaded, a time-invariant record with g = B u + e goes through
:class:`TimeInvariantPlan` instead: the RK4 steps of a sample interval composed into one
affine map of the stage inputs, prepared once per parameter vector with its derivatives, and
one compiled pass for states, sensitivities, outputs and residual sums. A model keeps the
plans of its records (input schedules that are immutable only), so a refit of a record, or
a finite-difference peer's next simulation, prepares nothing again.
"""

from dataclasses import dataclass
import math
import time
from typing import Any, Callable, Sequence, TYPE_CHECKING
import weakref

import numpy as np
import numpy.typing as npt

from rotor_id.estimation import kernels
from rotor_id.physics.revolution import entries_on_record

if TYPE_CHECKING:
    from rotor_id.physics.models import LinearModel

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
    dx: np.ndarray | None = None
    dy: np.ndarray | None = None
    #: With measurements (:meth:`TimeInvariantPlan.run`): residuals y − ŷ (T, m) and their
    #: per-channel sums (Σ r² (m,), Σ ∂ŷᵀ r (m, k), Σ ∂ŷᵀ ∂ŷ (m, k, k)); otherwise None.
    residual: np.ndarray | None = None
    residual_sums: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def substeps_for(t: npt.ArrayLike, max_step: float = DEFAULT_MAX_STEP) -> int:
    """Return the number of equal RK4 steps per sample interval so no step exceeds ``max_step``."""
    dt = np.diff(np.asarray(t, dtype=float))
    if dt.size == 0:
        return 1
    return _substeps(dt.max(), max_step)


def _substeps(longest_interval, max_step):
    """Equal RK4 steps that divide an interval this long into steps of at most ``max_step``."""
    return max(1, int(math.ceil(float(longest_interval) / max_step - 1e-9)))


#: A sample interval longer than this many median intervals is a gap (samples lost).
GAP_INTERVALS = 1.5


def gap_refinement(t: npt.ArrayLike, max_step: float = DEFAULT_MAX_STEP
                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """
    Return (times with the gaps filled, index of ``t`` in them), or None where there is no gap.

    :func:`substeps_for` gives every interval the RK4 substeps of the longest, so one gap of
    lost samples, n periods long, would multiply the cost of the whole record by about n.
    Instead each gap (an interval longer than :data:`GAP_INTERVALS` median intervals)
    is divided into equal parts about one median interval long, none longer than the regular
    intervals' substeps allow, so the substep count is the regular intervals'. The values at
    ``t`` are the same integration to the RK4 truncation error (steps no longer than
    ``max_step`` either way). None when the record has no gap that raises the substeps.
    """
    t = np.asarray(t, dtype=float)
    dt = np.diff(t)
    if dt.size < 2 or dt.max() <= GAP_INTERVALS * dt.min():
        return None                     # no gap (the cheap test: this runs in every simulation)
    median = float(np.median(dt))
    regular = dt <= GAP_INTERVALS * median
    regular_substeps = _substeps(dt[regular].max(), max_step)
    if regular.all() or _substeps(dt.max(), max_step) <= regular_substeps:
        return None                     # no gap, or none that raises the substep count
    longest = regular_substeps * max_step
    pieces = np.maximum(np.rint(dt / median), np.ceil(dt / longest - 1e-9)).astype(int)
    pieces[regular] = 1
    index = np.concatenate([[0], np.cumsum(pieces)])
    owner = np.repeat(np.arange(dt.size), pieces)
    part = np.arange(index[-1]) - index[:-1][owner]
    fine = np.concatenate([t[:-1][owner] + dt[owner] * (part / pieces[owner]), t[-1:]])
    return fine, index


def fine_grid(t, substeps):
    """Stage times: for every RK4 step its start, middle and end (shared with the next step)."""
    t = np.asarray(t, dtype=float)
    frac = np.arange(2 * substeps) / (2 * substeps)
    inner = (t[:-1, None] + np.diff(t)[:, None] * frac[None, :]).ravel()
    return np.concatenate([inner, t[-1:]])


def _stages(a):
    """Start, middle and end values of every RK4 step; a constant (1, ...) array is all three."""
    if a.shape[0] == 1:
        return a, a, a
    return a[0:-1:2], a[1::2], a[2::2]


def _mv(A, x):
    """Batched matrix-vector product A (..., n, n) · x (..., n) with broadcasting."""
    if A.shape[0] == 1 and all(s == 1 for s in A.shape[1:-2]):
        return x @ A.reshape(A.shape[-2:]).T            # one matrix for all: a single GEMM
    if A.shape[0] == 1 and A.ndim == 4 and x.ndim == 3 and x.shape[1] == 1:
        k, n = A.shape[1], A.shape[2]                   # constant (1, k, n, n) on (M, 1, n)
        return (x[:, 0] @ A[0].reshape(k * n, -1).T).reshape(-1, k, n)
    if A.ndim == 4 and A.shape[1] == 1 and x.ndim == 3:
        return x @ np.swapaxes(A[:, 0], -1, -2)         # one matrix a step on k vectors
    if A.ndim == 4 and x.ndim == 3 and x.shape[1] == 1 and A.shape[0] == x.shape[0]:
        M, k, n = A.shape[:3]                           # k matrices a step on one vector
        return (A.reshape(M, k * n, -1) @ x[:, 0, :, None])[..., 0].reshape(M, k, n)
    return (A @ x[..., None])[..., 0]


def rk4_maps(F, g, h):
    """
    Affine RK4 step maps x⁺ = Φ x + c from stage values (see the module docstring).

    ``F`` (2M+1, n, n) and ``g`` (2M+1, n) hold start/middle/end values of M steps of length
    ``h`` (M,). Returns Φ (M, n, n) and c (M, n). A time-invariant system may pass F (1, n, n)
    and one step length h (1,): then Φ (1, n, n) is computed once, c still per step.
    """
    Phi = rk4_transition(F, h)
    _, Fm, F1 = _stages(F)
    g0, gm, g1 = _stages(g)
    hv = h[:, None]
    b1 = g0
    b2 = gm + 0.5 * hv * _mv(Fm, b1)
    b3 = gm + 0.5 * hv * _mv(Fm, b2)
    b4 = g1 + hv * _mv(F1, b3)
    c = hv / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
    return Phi, c


def rk4_transition(F, h):
    """Φ (M, n, n) of the affine RK4 step maps of :func:`rk4_maps` (F and h shaped as there)."""
    return rk4_step_transition(*_stages(F), h)


def rk4_step_transition(F0, Fm, F1, h):
    """Φ (M, n, n) of M RK4 steps of lengths h from F at their start, middle and end."""
    hh = h[:, None, None]
    # stage matrices: k_i = A_i x + b_i
    A1 = F0
    A2 = Fm + 0.5 * hh * (Fm @ A1)
    A3 = Fm + 0.5 * hh * (Fm @ A2)
    A4 = F1 + hh * (F1 @ A3)
    return np.eye(F0.shape[-1]) + hh / 6.0 * (A1 + 2.0 * A2 + 2.0 * A3 + A4)


def rk4_transition_derivative(F, dF, h):
    """
    ∂Φ/∂p (M, k, n, n) of the RK4 step maps of :func:`rk4_transition` along dF (…, k, n, n).

    The stage matrices of :func:`rk4_transition` differentiated by the product rule, as
    matrices: ∂Φ e_c for every c at once, where :func:`_rk4_step_derivative` takes one pass
    per state column. Shapes as in :func:`_rk4_step_derivative`.
    """
    return rk4_step_transition_derivative(*_stages(F), *_stages(dF), h)


def rk4_step_transition_derivative(F0, Fm, F1, dF0, dFm, dF1, h):
    """∂Φ/∂p (M, k, n, n) of M RK4 steps from F and ∂F at their start, middle and end."""
    h3, h4 = h[:, None, None], h[:, None, None, None]
    A2 = Fm + 0.5 * h3 * (Fm @ F0)
    A3 = Fm + 0.5 * h3 * (Fm @ A2)
    Fm_, F1_ = Fm[:, None], F1[:, None]
    dA2 = dFm + 0.5 * h4 * (dFm @ F0[:, None] + Fm_ @ dF0)
    dA3 = dFm + 0.5 * h4 * (dFm @ A2[:, None] + Fm_ @ dA2)
    dA4 = dF1 + h4 * (dF1 @ A3[:, None] + F1_ @ dA3)
    return h4 / 6.0 * (dF0 + 2.0 * dA2 + 2.0 * dA3 + dA4)


def _rk4_step_derivative(F, g, h, dF, dg, x):
    """
    ∂Φ x + ∂c of every RK4 step at its start state x (M, n): the sensitivity forcing.

    The derivative of one RK4 step x⁺ = x + h/6 (k₁ + 2k₂ + 2k₃ + k₄) with respect to the
    parameters at fixed x, carried through the stages as vectors (shapes as in
    :func:`rk4_maps`; dF (2M+1 or 1, k, n, n), dg (2M+1, k, n)). Returns (M, k, n).
    """
    F0, Fm, F1 = _stages(F)
    g0, gm, g1 = _stages(g)
    dF0, dFm, dF1 = _stages(dF)
    dg0, dgm, dg1 = _stages(dg)
    hv = h[:, None]
    h3 = h[:, None, None]
    Fm_, F1_ = Fm[:, None], F1[:, None]
    # stages and the points they are evaluated at
    k1 = _mv(F0, x) + g0
    x2 = x + 0.5 * hv * k1
    k2 = _mv(Fm, x2) + gm
    x3 = x + 0.5 * hv * k2
    k3 = _mv(Fm, x3) + gm
    x4 = x + hv * k3
    # their parameter derivatives (x fixed)
    dk1 = _mv(dF0, x[:, None]) + dg0
    dk2 = _mv(dFm, x2[:, None]) + 0.5 * h3 * _mv(Fm_, dk1) + dgm
    dk3 = _mv(dFm, x3[:, None]) + 0.5 * h3 * _mv(Fm_, dk2) + dgm
    dk4 = _mv(dF1, x4[:, None]) + h3 * _mv(F1_, dk3) + dg1
    return h3 / 6.0 * (dk1 + 2.0 * dk2 + 2.0 * dk3 + dk4)


def simulate(model: 'LinearModel', p: npt.ArrayLike, inputs: Callable[[np.ndarray], np.ndarray],
             t: npt.ArrayLike, x0: npt.ArrayLike, param_index: Sequence[int] = (),
             x0_jacobian: npt.ArrayLike | None = None, max_step: float = DEFAULT_MAX_STEP,
             forcing: npt.ArrayLike | None = None) -> Simulation:
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
    refined = gap_refinement(t, max_step)
    if refined is not None:
        # lost samples: integrate over the gaps' filled grid, report at the samples
        fine, index = refined
        if forcing is not None:
            forcing = np.repeat(np.asarray(forcing, dtype=float), np.diff(index), axis=0)
        sim = simulate(model, p, inputs, fine, x0, param_index, x0_jacobian, max_step, forcing)
        return Simulation(t, sim.x[index], sim.y[index],
                          None if sim.dx is None else sim.dx[index],
                          None if sim.dy is None else sim.dy[index])
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
    if forcing is None:
        plan = TimeInvariantPlan.prepare(model, inputs, t, max_step, p)
        if plan is not None:
            return plan.run(p, x0, param_index, S0 if want_sens else None)
    T = t.size
    m = substeps_for(t, max_step)
    xs = np.empty((T, n))
    xs[0] = x0
    # an array exactly when want_sens (every use below is under that test)
    Ss: Any = np.empty((T, n, k)) if want_sens else None
    if want_sens:
        Ss[0] = S0
        if forcing is not None:
            raise ValueError('forcing is for plain simulation only')
    x, S = x0.copy(), (S0.copy() if want_sens else None)
    kernel = kernels.rk4_kernel() if forcing is None else None
    clock = time.process_time()
    # process the record in chunks of whole sample intervals to bound memory
    per_chunk = max(1, _CHUNK // m)
    for start in range(0, T - 1, per_chunk):
        stop = min(T - 1, start + per_chunk)
        ts = t[start:stop + 1]
        tf = fine_grid(ts, m)
        u = inputs(tf)
        h = np.repeat(np.diff(ts) / m, m)
        if kernel is not None:
            x, S = _compiled_chunk(kernel, model, p, tf, u, h, m, param_index,
                                   x, S if want_sens else np.zeros((n, 0)),
                                   xs[start:stop + 1],
                                   Ss[start:stop + 1] if want_sens else None)
            continue
        F, g = model.system(tf, p, u)
        if time_invariant_steps(F, h, ts):
            # one Φ for every step; c still follows the input step by step
            F_maps, h_maps = F[:1], h[:1]
        else:
            F_maps, h_maps = F, h
        Phi_s, c_s = rk4_maps(F_maps, g, h_maps)
        if forcing is not None:
            w = np.repeat(np.asarray(forcing, dtype=float)[start:stop], m, axis=0)
            c_s = c_s + rk4_constant_forcing(F_maps, w, h_maps)
        # maps from one sample to the next (the m RK4 steps of each interval composed)
        Phi, c = _per_interval(m, Phi_s, c_s)
        levels = _doubling_products(Phi, stop - start)
        X = _recursion(levels, c[:, :, None], x[:, None])[:, :, 0]
        xs[start:stop + 1] = X
        x = X[-1]
        if want_sens and not param_index:
            Sc = _recursion(levels, np.zeros((stop - start, n, k)), S)
            Ss[start:stop + 1] = Sc
            S = Sc[-1]
        elif want_sens:
            dF, dg = model.system_jacobian(tf, p, u)
            if F_maps.shape[0] == 1 and np.all(dF == dF[:1]):
                dF = dF[:1]
            dF, dg = dF[:, param_index], dg[:, param_index]
            # S⁺ = Φ S + ∂Φ x + ∂c per step; the forcing is known once the states are
            x_steps = _step_states(m, Phi_s, c_s, X[:-1])
            W_steps = _rk4_step_derivative(F_maps, g, h_maps, dF, dg, x_steps)
            W = np.zeros((stop - start, n, k))
            W[:, :, :W_steps.shape[1]] = np.swapaxes(_interval_forcing(m, Phi_s, W_steps), 1, 2)
            Sc = _recursion(levels, W, S)
            Ss[start:stop + 1] = Sc
            S = Sc[-1]
    if kernel is None and want_sens:
        kernels.note_numpy_seconds(time.process_time() - clock)
    H = model.output_matrix(t)
    y = np.einsum('tij,tj->ti', H, xs) + model.output_offset(t, p)
    if not want_sens:
        return Simulation(t, xs, y)
    dy = H @ Ss
    dd = model.output_offset_jacobian(t, p)[:, :, param_index]
    dy[:, :, :len(param_index)] += dd
    return Simulation(t, xs, y, Ss, dy)


#: Most stage-input values (samples × stages × inputs) a :class:`TimeInvariantPlan` holds;
#: longer records run through the chunked RK4 kernel instead (bounded memory).
PLAN_MAX_VALUES = 1 << 19
#: Azimuths (rad) at which :func:`affine_time_invariant` probes a model: arbitrary, so that
#: no periodic coefficient (period 2π/N) takes the same value at all three.
_CHECK_TIMES = (0.5, 2.1, 3.9)
# model -> {number of inputs: verdict}
_verdicts: 'weakref.WeakKeyDictionary[LinearModel, dict[int, bool]]' = (
    weakref.WeakKeyDictionary())
# model -> {(unknowns, fixed p): mask}
_affine_masks: 'weakref.WeakKeyDictionary[LinearModel, dict[tuple, np.ndarray]]' = (
    weakref.WeakKeyDictionary())
#: model -> {(id(inputs), max_step, T): (inputs, t, plan or None)}: the records prepared for
#: a model (see :meth:`TimeInvariantPlan.prepare`); a plan refers to its model weakly, so the
#: entries go with the model.
_record_plans: 'weakref.WeakKeyDictionary[LinearModel, dict[tuple, tuple]]' = (
    weakref.WeakKeyDictionary())
#: Most records remembered per model object (a diagnosis refits a handful per record).
RECORD_PLANS_PER_MODEL = 8


def affine_time_invariant(model: 'LinearModel', p: npt.ArrayLike, n_inputs: int) -> bool:
    """
    Tell whether F is constant and g = B u + e (B, e constant), and so their derivatives.

    That is the condition for :class:`TimeInvariantPlan`.

    Checked numerically, once per model object and input width, at the parameters ``p`` of
    the first call: F and ∂F/∂p equal at three azimuths, and g, ∂g/∂p at every unit input and
    at a mixed one equal to the affine reconstruction, all to 1e-11 of their largest entry.
    (Every model here is linear in its inputs; the check guards against a periodic or
    input-scheduled model, whose ``time_invariant`` flag alone is not trusted.)
    """
    try:
        cache = _verdicts.setdefault(model, {})
    except TypeError:                           # not weakly referenceable: check every time
        cache = {}
    if n_inputs not in cache:
        try:
            cache[n_inputs] = _check_affine(model, np.asarray(p, dtype=float), n_inputs)
        except Exception:  # noqa: B902 - a model that cannot be probed so takes the general path
            cache[n_inputs] = False
    return cache[n_inputs]


def _unit_inputs(q, mixed=False):
    """Input probes: zero, then every unit input (then, if ``mixed``, one mixed input)."""
    u = np.zeros((q + 1 + int(mixed), q))
    u[1:q + 1] = np.eye(q)
    if mixed:
        u[-1] = np.linspace(0.7, -1.3, q)
    return u


def _same(a, b, rtol=1e-11):
    """Tell whether arrays a and b agree to ``rtol`` of their largest entry."""
    scale = max(float(np.max(np.abs(a), initial=0.0)), float(np.max(np.abs(b), initial=0.0)),
                1e-300)
    return bool(np.max(np.abs(a - b), initial=0.0) <= rtol * scale)


def _check_affine(model, p, q):
    # F alone at zero input first: a periodic model fails there, before the probes of every
    # input and the parameter derivatives are computed
    F, _ = model.system(np.asarray(_CHECK_TIMES), p, np.zeros((len(_CHECK_TIMES), q)))
    if not _same(F, np.broadcast_to(F[:1], F.shape)):
        return False
    u1 = _unit_inputs(q, mixed=True)
    probes = u1.shape[0]
    t = np.repeat(np.asarray(_CHECK_TIMES), probes)
    u = np.tile(u1, (len(_CHECK_TIMES), 1))
    F, g = model.system(t, p, u)
    dF, dg = model.system_jacobian(t, p, u)

    same = _same

    if not (same(F, np.broadcast_to(F[:1], F.shape)) and
            same(dF, np.broadcast_to(dF[:1], dF.shape))):
        return False
    for values in (g, dg):                      # (3·probes, n) and (3·probes, P, n)
        v = values.reshape((len(_CHECK_TIMES), probes) + values.shape[1:])
        if not same(v, np.broadcast_to(v[:1], v.shape)):
            return False
        e = v[0, 0]
        B = v[0, 1:q + 1] - e
        mixed = e + np.tensordot(u1[-1], B, axes=1)
        if not same(v[0, -1], mixed):
            return False
    return True


class TimeInvariantPlan:
    """
    A record of a time-invariant model prepared for repeated simulation with sensitivities.

    When F is constant, g = B u + e (:func:`affine_time_invariant`) and the RK4 steps are equal,
    every sample interval is the same affine map x_{j+1} = Φ x_j + C U_j + c_e of the stage
    inputs U_j, with Φ, C, c_e polynomials in F, B, e (the expansion of :func:`rk4_maps`,
    composed over the interval's steps). Per parameter vector, the model is evaluated once at
    its unit inputs (not at every stage time), the interval map and its parameter derivatives
    are formed once, and one compiled pass propagates the states and sensitivities, forms the
    outputs and, given measurements, the residuals and their weighted sums. The result is the
    same RK4 step map as :func:`simulate`'s chunked paths, up to rounding (test_kernels.py).

    What is prepared here depends on the record only (sample times, stage inputs, H), so an
    estimator builds one plan per run and calls :meth:`run` every iteration; the structural
    check is cached per model object, and so are the plans of records whose input schedule
    is immutable (:meth:`prepare`), with their reference point (:meth:`_probes`): a refit of
    the same record with the same model evaluates neither inputs nor model again. Built only
    where the compiled kernels are loaded.
    """

    def __init__(self, model: 'LinearModel', t: np.ndarray, substeps: int, u: np.ndarray,
                 module: Any) -> None:
        """Hold the record: times, stage inputs u (at fine_grid), H; see :meth:`prepare`."""
        T = t.size
        # a weak reference to the model, or a holder where it cannot be referenced weakly
        self._model: Callable[[], LinearModel | None]
        try:
            self._model = weakref.ref(model)
        except TypeError:                       # not weakly referenceable: held (not cached)
            self._model = lambda: model
        self.t = t
        self.substeps = substeps
        self.step = float(t[1] - t[0]) / substeps      # as the numpy path: h of the first step
        self.n_inputs = u.shape[1]
        stages = 2 * substeps + 1
        index = 2 * substeps * np.arange(T - 1)[:, None] + np.arange(stages)[None, :]
        self.U = np.ascontiguousarray(u[index].reshape(T - 1, stages * self.n_inputs))
        H = np.asarray(model.output_matrix(t), dtype=float)
        self.H = np.ascontiguousarray(H[:1] if np.all(H == H[:1]) else H)
        from rotor_id.physics.models import LinearModel
        self.has_offset = (type(model).output_offset is not LinearModel.output_offset
                           or type(model).output_offset_jacobian is not
                           LinearModel.output_offset_jacobian)
        self.kernels = module
        self.probe_t = np.full(self.n_inputs + 1, float(t[0]))
        self.probe_u = _unit_inputs(self.n_inputs)
        #: (p_ref, F, g, ∂F, ∂g at the unit inputs, mask of affine parameters); see _probes
        self.reference: tuple | None = None
        #: (reference, its p, its affine mask, the checked parameters) as lists (:meth:`_lists`)
        self._reference_lists: tuple | None = None
        #: (free states, x0_base, S0) of the compiled fits of this record, by initial-state
        #: mode and θ's layout (output_error._CompiledIteration._initial_state_map)
        self.initial_state_maps: dict[tuple, tuple] = {}
        #: parameters whose affinity the reference's mask has checked (P,)
        self.checked = np.zeros(len(model.parameters), dtype=bool)

    @property
    def model(self) -> 'LinearModel':
        """Return the model this record was prepared for."""
        # None only once the model is gone, and a plan is used by a caller that holds it
        return self._model()  # type: ignore[return-value]

    @classmethod
    def prepare(cls, model: 'LinearModel', inputs: Callable[[np.ndarray], np.ndarray],
                t: npt.ArrayLike, max_step: float, p: npt.ArrayLike
                ) -> 'TimeInvariantPlan | None':
        """
        Return a plan for this record, or None where it does not apply (then simulate).

        Remembered per model object for inputs that are immutable (a frozen dataclass such as
        :class:`~rotor_id.physics.stirring.StirringSchedule`): the same model, the same input
        object, equal sample times and step give the same plan, not a new one.
        """
        module = kernels.affine_kernels()
        t = np.asarray(t, dtype=float)
        if module is None or t.size < 2:
            return None
        cache = _record_cache(model, inputs)
        key = (id(inputs), float(max_step), t.size)
        if cache is not None:
            hit = cache.get(key)
            if (hit is not None and hit[0] is inputs and hit[1].shape == t.shape
                    and (hit[1] == t).all()):
                return hit[2]
        plan = cls._build(model, inputs, t, max_step, p, module)
        if cache is not None:
            if len(cache) >= RECORD_PLANS_PER_MODEL:
                cache.clear()
            cache[key] = (inputs, t.copy() if plan is None else plan.t, plan)
        return plan

    @classmethod
    def _build(cls, model, inputs, t, max_step, p, module):
        m = substeps_for(t, max_step)
        if (2 * m * (t.size - 1) + 1) * 3 > PLAN_MAX_VALUES:
            return None
        if not equal_steps(np.diff(t) / m, t):
            return None
        u = np.asarray(inputs(fine_grid(t, m)), dtype=float)
        if u.ndim != 2 or not affine_time_invariant(model, p, u.shape[1]):
            return None
        t = t.copy()
        t.setflags(write=False)                 # shared by every fit of this record
        return cls(model, t, m, u, module)

    def run(self, p: npt.ArrayLike, x0: npt.ArrayLike, param_index: npt.ArrayLike = (),
            S0: npt.ArrayLike | None = None, y: npt.ArrayLike | None = None) -> Simulation:
        """
        Simulate from x0 with sensitivities to ``param_index`` and the columns of ``S0``.

        ``S0`` (n, k), k ≥ len(param_index): ∂x0/∂θ, as ``x0_jacobian`` of :func:`simulate`
        (None: no sensitivities). With measurements ``y`` (T, m) the returned
        :class:`Simulation` also carries the residuals and their per-channel sums.
        """
        model = self.model
        p = np.asarray(p, dtype=float)
        x0 = np.asarray(x0, dtype=float)
        n, m = model.n_states, model.n_outputs
        index = np.asarray(param_index, dtype=np.int64).reshape(-1)
        S0 = self.no_sensitivity(n) if S0 is None else np.ascontiguousarray(S0, dtype=float)
        fit = y is not None
        # the compiled code does not check indices: shapes are checked here
        if (x0.shape != (n,) or S0.ndim != 2 or S0.shape[0] != n or S0.shape[1] < index.size
                or p.shape != (len(model.parameters),)
                or (index.size and (index.min() < 0 or index.max() >= p.size))
                or (fit and np.shape(y) != (self.t.size, m))):  # type: ignore[arg-type]
            raise ValueError('TimeInvariantPlan.run: x0 needs shape (n,), S0 (n, k ≥ '
                             'len(param_index)), p one value per model parameter, y (T, m)')
        F, g, dF, dg, shift = self._probes(p, index)
        if self.has_offset:
            d = np.ascontiguousarray(model.output_offset(self.t, p), dtype=float)
            dd = np.ascontiguousarray(model.output_offset_jacobian(self.t, p)[:, :, index])
        else:
            d, dd = np.zeros((0, m)), np.zeros((0, m, index.size))
        y = np.ascontiguousarray(y, dtype=float) if fit else np.zeros((0, m))
        T, k = self.t.size, S0.shape[1]
        xs, Ss = np.empty((T, n)), np.empty((T, n, k))
        yhat, dyhat = np.empty((T, m)), np.empty((T, m, k))
        res = np.empty((y.shape[0], m))
        sq, gc, Mc = np.empty(m), np.empty((m, k)), np.empty((m, k, k))
        self.kernels.affine_run(
            np.ascontiguousarray(F, dtype=float), np.ascontiguousarray(g, dtype=float),
            np.ascontiguousarray(dF, dtype=float), np.ascontiguousarray(dg, dtype=float),
            shift, index, self.step, self.substeps, self.U, np.ascontiguousarray(x0, dtype=float),
            S0, self.H, d, dd, y, xs, Ss, yhat, dyhat, res, sq, gc, Mc)
        sums = (sq, gc, Mc) if fit else None
        if not S0.shape[1]:
            return Simulation(self.t, xs, yhat, residual=res if fit else None,
                              residual_sums=sums)
        return Simulation(self.t, xs, yhat, Ss, dyhat, residual=res if fit else None,
                          residual_sums=sums)

    def reference_at(self, p: npt.ArrayLike, index: np.ndarray) -> tuple:
        """
        Return the reference point (as :attr:`reference`) that serves p with sensitivities.

        It is the kept one where p is on it along every parameter that is not affine and
        ``index`` (int64 array) was checked; otherwise a new one at p (the model evaluated).
        """
        ref = self.reference
        if ref is not None and self._on_reference(p, ref, index.tolist()):
            return ref
        self._probes(np.asarray(p, dtype=float), index)
        return self.reference  # type: ignore[return-value]  # _probes has just set it

    def _lists(self, ref):
        """Return (reference, its p, its affine mask, the checked parameters) as lists."""
        if self._reference_lists is None or self._reference_lists[0] is not ref:
            self._reference_lists = (ref, ref[0].tolist(), ref[5].tolist(),
                                     self.checked.tolist())
        return self._reference_lists

    def _on_reference(self, p, ref, indices):
        """
        Tell whether the reference serves p with sensitivities to ``indices`` (a list).

        As ``checked[indices].all() and not np.any((p != p_ref) & ~affine)``, on Python lists:
        a refit of a record runs this once, and its few numpy calls on a few values cost more
        than the lists, most of all where the refit's Python runs cold (between other work).
        """
        _, values, affine, checked = self._lists(ref)
        return all(checked[i] for i in indices) and all(
            a == b for a, b, free in zip(np.asarray(p).tolist(), values, affine) if not free)

    def affine_along(self, ref: tuple, indices: Sequence[int]) -> bool:
        """Tell whether F and g of the reference ``ref`` are affine along ``indices`` (a list)."""
        affine = self._lists(ref)[2]
        return all(affine[i] for i in indices)

    def _probes(self, p, index):
        """
        F, g (and ∂F, ∂g for sensitivities to ``index``) at the unit inputs, and the shift.

        The model is evaluated here at its unit inputs, or not at all: after the first
        evaluation with parameter sensitivities (the reference point p_ref), the parameters
        of ``index`` along which ∂F/∂p and ∂g/∂p do not change (:meth:`_affine_parameters`,
        once) enter exactly as F(p) = F(p_ref) + Σ (p − p_ref) ∂F/∂p, likewise g; a p that
        differs from p_ref in any other parameter is evaluated afresh. So a Gauss-Newton fit
        evaluates the model two or three times in all, not at every iteration.
        """
        ref = self.reference
        if ref is not None and self.checked[index].all():
            shift = p - ref[0]
            if not np.any(shift[~ref[5]]):
                return ref[1], ref[2], ref[3], ref[4], shift
        model = self.model
        F, g = model.system(self.probe_t, p, self.probe_u)
        if not index.size:                      # no parameter sensitivities wanted
            q1 = self.n_inputs + 1
            n = model.n_states
            return F, g, np.zeros((q1, 0, n, n)), np.zeros((q1, 0, n)), np.zeros(0)
        dF, dg = model.system_jacobian(self.probe_t, p, self.probe_u)
        # a new reference: the first, or (a plan kept from another fit of this record) one
        # that p left along a parameter that is not affine or was not among its unknowns
        checked = self.checked.copy()
        checked[index] = True
        self.reference = (p.copy(), F, g, dF, dg,
                          self._affine_mask(p, dF, dg, np.flatnonzero(checked)))
        self.checked = checked
        return F, g, dF, dg, np.zeros(0)

    def _affine_mask(self, p, dF, dg, index):
        """
        :meth:`_affine_parameters`, remembered per model object, unknowns and fixed values.

        Affinity along the unknowns holds on the whole subspace they span, so it depends on
        the values of the other parameters only (a refit of the same model skips the check).
        """
        fixed = p.copy()
        fixed[index] = 0.0
        key = (tuple(int(i) for i in index), fixed.tobytes())
        try:
            cache = _affine_masks.setdefault(self.model, {})
        except TypeError:
            cache = {}
        if key not in cache:
            if len(cache) > 16:
                cache.clear()
            cache[key] = self._affine_parameters(p, dF, dg, index)
        return cache[key].copy()

    def _affine_parameters(self, p, dF, dg, candidates):
        """
        Mask of the ``candidates`` along which F and g are affine (the others fixed at p).

        ∂F/∂p_i and ∂g/∂p_i of every candidate must come out the same (to 1e-12 of their
        largest entry) after all candidates moved by distinct steps; those that change drop
        out and the rest are checked again (for polynomial coefficients, as every model's,
        constant derivatives at a generic second point mean constant on the whole subspace).
        """
        mask = np.zeros(p.size, dtype=bool)
        mask[np.asarray(candidates, dtype=np.int64)] = True
        spread = 0.01 * (1.0 + np.abs(p)) * np.linspace(1.0, 1.7, p.size)
        while mask.any():
            dF2, dg2 = self.model.system_jacobian(self.probe_t, p + np.where(mask, spread, 0.0),
                                                  self.probe_u)
            changed = np.zeros(p.size, dtype=bool)
            for a, b in ((dF, dF2), (dg, dg2)):      # per parameter: (probes, P, ...)
                a = np.moveaxis(a, 1, 0).reshape(p.size, -1)
                b = np.moveaxis(b, 1, 0).reshape(p.size, -1)
                scale = np.maximum(np.maximum(np.abs(a).max(axis=1), np.abs(b).max(axis=1)),
                                   1e-300)
                changed |= np.abs(a - b).max(axis=1) > 1e-11 * scale
            changed &= mask
            if not changed.any():
                break
            mask &= ~changed
        return mask

    @staticmethod
    def no_sensitivity(n: int) -> np.ndarray:
        """∂x0/∂θ with no columns."""
        return np.zeros((n, 0))


def _record_cache(model, inputs):
    """Return the per-model dict of prepared records, or None where plans are not kept."""
    params = getattr(type(inputs), '__dataclass_params__', None)
    if params is None or not params.frozen:
        return None
    try:
        return _record_plans.setdefault(model, {})
    except TypeError:                           # not weakly referenceable
        return None


def _compiled_chunk(kernel, model, p, tf, u, h, m, param_index, x, S, xs, Ss):
    """
    One chunk through the compiled RK4 scan (:mod:`rotor_id.estimation.kernels`).

    Writes the samples into the views ``xs`` (L+1, n) and ``Ss`` (L+1, n, k) or None (plain
    simulation, S of shape (n, 0)); returns the last state and sensitivities. F and ∂F/∂p
    enter as their non-zero entries, constant ones once (:func:`entries_on_record`).
    """
    n = x.shape[0]
    (F_val, (F_i, F_j)), g = entries_on_record(model, 'system', tf, p, u)
    if param_index:
        (dF_val, (dF_p, dF_i, dF_j)), dg = entries_on_record(model, 'system_jacobian', tf, p, u,
                                                             param_index)
    else:
        dF_p = dF_i = dF_j = np.zeros(0, dtype=np.int64)
        dF_val = np.zeros((1, 0))
        dg = np.zeros((g.shape[0], 0, n))
    S_out = np.empty((xs.shape[0], n, S.shape[1])) if Ss is None else Ss
    kernel(F_val, F_i, F_j, np.ascontiguousarray(g, dtype=float),
           dF_val, dF_p, dF_i, dF_j, np.ascontiguousarray(dg, dtype=float),
           np.ascontiguousarray(h, dtype=float), m, x, np.ascontiguousarray(S, dtype=float), xs,
           S_out)
    return xs[-1].copy(), S_out[-1].copy()


def time_invariant_steps(F, h, ts):
    """
    Return True when F is the same at every stage time and all steps are equally long.

    Step lengths that differ by the rounding of the sample times ``ts`` only (e.g.
    ``round(t0 + 0.1 j, 10)``, whose differences carry errors of a few ulp of t, i.e. 1e-13
    of a step at t ≈ 1000) count as equal; anything larger (time-stamp jitter) does not.
    """
    return bool(np.all(F == F[:1])) and equal_steps(h, ts)


def equal_steps(h, ts):
    """Tell whether the steps h are equal to the rounding of the times ts (see above)."""
    rounding = 8.0 * np.finfo(float).eps * float(np.max(np.abs(ts)))
    return bool(np.ptp(h) <= 1e-12 * abs(h[0]) + rounding)


def rk4_constant_forcing(F, w, h):
    """Contribution to c of an input w (M, n) held constant over each RK4 step."""
    _, Fm, F1 = _stages(F)
    hv = h[:, None]
    b2 = w + 0.5 * hv * _mv(Fm, w)
    b3 = w + 0.5 * hv * _mv(Fm, b2)
    b4 = w + hv * _mv(F1, b3)
    return hv / 6.0 * (w + 2.0 * b2 + 2.0 * b3 + b4)


def _substep(a, s, m):
    """Select the s-th of the m RK4 steps of every sample interval (a constant (1, ...) stays)."""
    return a if a.shape[0] == 1 else a.reshape((a.shape[0] // m, m) + a.shape[1:])[:, s]


def _per_interval(m, Phi, c):
    """Compose the m RK4 steps of each sample interval: (Φ₂, c₂)∘(Φ₁, c₁) = (Φ₂Φ₁, Φ₂c₁ + c₂)."""
    P, cc = _substep(Phi, 0, m), _substep(c, 0, m)
    for s in range(1, m):
        A = _substep(Phi, s, m)
        cc = _mv(A, cc) + _substep(c, s, m)
        P = A @ P
    return P, cc


def _step_states(m, Phi, c, X):
    """State at the start of every RK4 step (M, n) from the states at the samples X (L, n)."""
    if m == 1:
        return X
    steps = [X]
    for s in range(m - 1):
        steps.append(_mv(_substep(Phi, s, m), steps[-1]) + _substep(c, s, m))
    return np.stack(steps, axis=1).reshape(-1, X.shape[1])


def _interval_forcing(m, Phi, W):
    """Carry a per-step forcing W (M, k, n) to the end of each interval: (L, k, n)."""
    w = _substep(W, 0, m)
    for s in range(1, m):
        w = _mv(_substep(Phi, s, m)[:, None], w) + _substep(W, s, m)
    return w


def _doubling_products(Phi, L):
    """
    Products of 1, 2, 4, … successive maps, for the doubling scan of :func:`_recursion`.

    Returns [(d, A_d)] for d = 1, 2, 4, … ≤ L, where A_d[i] = Φ_{j−1} ⋯ Φ_{j−d} is the product
    of the d maps that end at sample j = d + i (shape (L+1−d, n, n)); for a constant Φ
    (``Phi`` of shape (1, n, n)) simply Φ^d (n, n).
    """
    levels = []
    d = 1
    A = Phi[0] if Phi.shape[0] == 1 else Phi
    while d <= L:
        levels.append((d, A))
        if 2 * d <= L:
            A = A @ A if A.ndim == 2 else A[d:] @ A[:-d]
        d *= 2
    return levels


def _recursion(levels, c, y0):
    """
    All states of the linear recursion Y₀ = y0, Y_{j+1} = Φ_j Y_j + c_j, j = 0 … L−1.

    ``levels`` from :func:`_doubling_products`; ``c`` (L, n, q); ``y0`` (n, q). Returns
    (L+1, n, q). Doubling scan: after the pass with the d-products, Y_j holds the sum over the
    last 2d inputs, so log₂ L vectorised products replace L sequential small ones.
    """
    Y = np.empty((c.shape[0] + 1,) + y0.shape)
    Y[0] = y0
    Y[1:] = c
    for d, A in levels:
        Y[d:] += A @ Y[:-d]
    return Y
