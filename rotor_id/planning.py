"""
Test planning: the accuracy candidate stirring transients can reach, before the run.

For each candidate transient the planned run is simulated with the library's one simulator in
the test-stand convention (docs/run_description.md): the rotor in trim at collective pitch,
the lateral cyclic stepped on one revolution after the record starts (t = 2π), pitch stirring
``t0`` later, and the identification window from the stirring start for ``duration_rev``
revolutions. The noise-free record goes through the same path as ``rotor-id identify``
(:func:`rotor_id.pipeline.experiments_from_record`: same model, same channels, same sampling),
with the initial states at the window start treated as unknowns as a window-only estimator
faces them, and the Cramér-Rao bound of the planned noise is evaluated at the guessed
parameters for every record end t_f (report Ch.3 eqs 19-23,
:func:`rotor_id.estimation.information.information_history`). From that M⁻¹(t_f) curve follow
the σ of every candidate's record length, the shortest record meeting the stipulated σ
(Ch.3 eq. 23) and the recommendation.

No ROS here; :mod:`rotor_id.commands.plan` is the command line.

Public API
----------
:func:`load_plan`, :func:`parse_plan`   PLAN.yaml → :class:`Plan` (a run description plus the
                                        planning keys, errors naming file, line and remedy)
:func:`evaluate_plan`                   Plan → :class:`PlanResult` (σ, targets, recommendation)
:func:`predict_transient`               M⁻¹(t_f) of one stirring transient
:func:`simulate_run`                    the planned run as a :class:`~rotor_id.io.record.Record`
                                        (optionally with sensor noise: Monte Carlo checks)
:func:`description_for`                 the run description ``identify`` needs for a candidate
:func:`monte_carlo`                    identify on noisy simulated runs, beside the prediction
:func:`steep_descents`                  where an M⁻¹(t_f) curve stops falling steeply (Ch.3)
:func:`write_figure`                    σ(t_f) curves like Ch.3 figs 2-3
"""

from dataclasses import dataclass, field, replace
import itertools
import math
import os
from pathlib import Path
import time
from typing import Any, Callable, Iterable, NoReturn, Sequence, TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from rotor_id import pipeline
from rotor_id.estimation.information import information_history, InformationHistory, \
    inverse_or_nan, shortest_record
from rotor_id.estimation.simulate import simulate
from rotor_id.io.errors import RunDescriptionError
from rotor_id.io.record import Record
from rotor_id.io.run_description import parse_run_description, SourceLines
from rotor_id.physics.blades import blade_flap_from_states
from rotor_id.physics.models import build_model, lock_number_from_known
from rotor_id.physics.stirring import PROGRESSING_OMEGADOT, StirringSchedule
import yaml

if TYPE_CHECKING:
    from rotor_id.io.run_description import RunDescription
    from rotor_id.physics.models import RotorModel

#: Keys a plan adds to a run description (``noise_std_rad`` is a run-description key already).
PLAN_KEYS = ('guess', 'rate_hz', 'omega_rad_s', 'target_std', 'candidates', 'collective_rad',
             'known_initial_state')
#: Keys of one candidate, as in the JSON.
CANDIDATE_KEYS = ('direction', 'omegadot', 'amplitude_rad', 't0', 'duration_rev')
DIRECTIONS = ('progressing', 'regressing')
#: Defaults when a plan gives no candidates (or leaves keys out): both directions, the report's
#: ω̇ = 0.1/π with half and twice that, the report's 1.5° amplitude, and 1-3 revolutions.
DEFAULT_OMEGADOT = tuple(abs(PROGRESSING_OMEGADOT) * f for f in (0.5, 1.0, 2.0))
DEFAULT_AMPLITUDE_RAD = math.radians(1.5)
DEFAULT_DURATION_REV = (1.0, 2.0, 3.0)
DEFAULT_COLLECTIVE_RAD = math.radians(2.0)
#: The lateral cyclic is stepped one revolution after the record starts (recording convention).
CYCLIC_STEP = 2.0 * math.pi
MAX_CANDIDATES = 500
#: The M⁻¹(t_f) curve of a transient is computed this many times beyond its longest candidate,
#: to say how long a record would have to be when no planned length meets the targets.
HORIZON = 2.0


def default_t0(advance_ratio: float) -> float:
    """Return the report's stirring delay after the cyclic step: 12 at μ > 0, 70 at μ = 0."""
    return 12.0 if advance_ratio > 0 else 70.0


@dataclass(frozen=True)
class Candidate:
    """
    One candidate test: a stirring transient and a record length (the JSON's keys).

    Attributes
    ----------
    direction : str
        'progressing' (ω̇ < 0) or 'regressing' (ω̇ > 0).
    omegadot : float
        ω̇ of the stirring law φ = ω̇ (t − t_s)² (Ch.2 eqs 1-2, docs/models.md §0), signed, per
        unit nondimensional time squared (report: ∓0.1/π).
    amplitude_rad : float
        Cyclic stirring amplitude, rad (report: 1.5° = 0.0262 rad).
    t0 : float
        Delay of the stirring start after the lateral-cyclic step, nondimensional time
        (report: 12 at μ = 0.4, 70 at μ = 0).
    duration_rev : float
        Identification window from the stirring start, revolutions (report: 12/2π = 1.91).

    """

    direction: str
    omegadot: float
    amplitude_rad: float
    t0: float
    duration_rev: float

    @property
    def transient(self) -> tuple[str, float, float, float]:
        """Return the candidate without its record length (candidates sharing it share a run)."""
        return (self.direction, self.omegadot, self.amplitude_rad, self.t0)

    @property
    def stirring_start(self) -> float:
        """Stirring start in the record's nondimensional time (cyclic step + t0)."""
        return CYCLIC_STEP + self.t0

    @property
    def duration(self) -> float:
        """Record length in nondimensional time, 2π per revolution."""
        return 2.0 * math.pi * self.duration_rev

    def schedule(self, collective_rad: float) -> StirringSchedule:
        """Return the pitch input of the planned run (:class:`StirringSchedule`, radians)."""
        return StirringSchedule(collective=collective_rad, amplitude=self.amplitude_rad,
                                omegadot=self.omegadot, t0=self.stirring_start,
                                t_step=CYCLIC_STEP)

    def final_stirring_rate(self) -> float:
        """Stirring rate dφ/dt at the record end, 2|ω̇|·duration (per rev of the rotor)."""
        return 2.0 * abs(self.omegadot) * self.duration

    def window_s(self, omega_rad_s: float) -> tuple[float, float]:
        """Identification window (s after the record's first sample) for the run description."""
        return (self.stirring_start / omega_rad_s,
                (self.stirring_start + self.duration) / omega_rad_s)

    def label(self) -> str:
        """Short text for tables, progress lines and legends."""
        amplitude = math.degrees(self.amplitude_rad)
        return f'{self.direction} ω̇={self.omegadot:+.4g} amp={amplitude:.3g}° t0={self.t0:g}'

    def as_json(self) -> dict[str, Any]:
        """Return the candidate's keys as in the JSON."""
        return {'direction': self.direction, 'omegadot': float(self.omegadot),
                'amplitude_rad': float(self.amplitude_rad), 't0': float(self.t0),
                'duration_rev': float(self.duration_rev)}


@dataclass(frozen=True)
class Plan:
    """
    A validated plan: the run description and what the planning adds.

    Attributes
    ----------
    description : RunDescription
        Model, unknowns, rotor, known values, initial-state mode (its window is replaced by
        each candidate's).
    guess : dict
        Parameter values to plan around (every unknown has one).
    noise_std_rad : float
        Per-blade flap-sensor noise σ, rad.
    rate_hz : float
        Sample rate of the flap sensors.
    omega_rad_s : float
        Rotor speed Ω.
    target_std : dict
        Stipulated σ per unknown (may be empty).
    candidates : tuple of Candidate
    collective_rad : float
        Collective pitch of the run (θ0 of the guess or the known values, else 2°).
    warnings : tuple of str
    path : str
    known_initial_state : bool
        Plan as if the state at the window start were known (report Ch.3 Table 1).
    defaults_used : dict
        Parameters neither unknown, known nor guessed: name -> the value planned with.

    """

    description: 'RunDescription'
    guess: dict
    noise_std_rad: float
    rate_hz: float
    omega_rad_s: float
    target_std: dict
    candidates: tuple
    collective_rad: float
    warnings: tuple = ()
    path: str = '<string>'
    known_initial_state: bool = False
    defaults_used: dict = field(default_factory=dict)

    @property
    def unknowns(self) -> list[str]:
        """Return the unknown model parameters, in the description's order."""
        return list(self.description.unknowns)

    @property
    def sample_interval(self) -> float:
        """Δt of the flap samples in nondimensional time, Ω / rate."""
        return self.omega_rad_s / self.rate_hz


# ------------------------------------------------------------------------------------------------
# PLAN.yaml
# ------------------------------------------------------------------------------------------------

class _PlanParser:
    """Validation of the planning keys with file:line in every message."""

    def __init__(self, data, lines, path):
        self.data = data
        self.lines = lines
        self.path = path

    def fail(self, message: str, *where: Any) -> NoReturn:
        line = self.lines(*where) if where else None
        prefix = f'{self.path}:{line}' if line else self.path
        raise RunDescriptionError(f'{prefix}: {message}', self.path, line)

    def number(self, value, *where, positive=True, maximum=None, hint=''):
        name = '.'.join(str(w) for w in where)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                not math.isfinite(value):
            self.fail(f'{name} must be a finite number, got {value!r}{hint}', *where)
        if positive and value <= 0:
            self.fail(f'{name} must be positive, got {value!r}{hint}', *where)
        if maximum is not None and value > maximum:
            self.fail(f'{name} = {value!r} is implausibly large{hint}', *where)
        return float(value)

    def mapping(self, value, *where):
        if not isinstance(value, dict):
            self.fail(f'{".".join(str(w) for w in where)} must be a mapping (key: value), got '
                      f'{type(value).__name__}', *where)
        return value


def parse_plan(text: str, path: 'str | os.PathLike[str]' = '<string>') -> Plan:
    """
    Parse and validate a plan: a run description plus the planning keys.

    The run description's ``window_s`` may be left out (each candidate sets its own). Planning
    keys: ``guess`` (values to plan around), ``noise_std_rad`` (per-blade flap σ, rad),
    ``rate_hz``, ``omega_rad_s``, ``target_std`` (optional σ per unknown), ``candidates``
    (optional: one mapping or a list of mappings with the keys of :data:`CANDIDATE_KEYS`, each
    value a number or a list; each mapping is expanded to all combinations, keys left out take
    the defaults), ``collective_rad`` (optional) and ``known_initial_state`` (optional, false by
    default: true plans as if the state at the window start were known, the report's "correct
    initial conditions" of Ch.3 Table 1, instead of estimated with the parameters).

    Raises
    ------
    RunDescriptionError
        Malformed YAML or content; the message names the file, line and what to do.

    """
    path = str(path)
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError:
        parse_run_description(text, path)       # raises the run description's precise error
        raise
    if isinstance(data, dict) and 'window_s' not in data:
        text = text.rstrip('\n') + '\nwindow_s: [0.0, 1.0]  # set per candidate by the plan\n'
    description = parse_run_description(text, path, extra_keys=PLAN_KEYS)
    parser = _PlanParser(data, SourceLines(node), path)
    model = pipeline.model_for(description)

    if description.noise_std_rad is None:
        parser.fail('noise_std_rad is missing: give the flap-sensor noise σ of one blade in rad '
                    '(the predicted σ scale with it)')
    for key in ('rate_hz', 'omega_rad_s'):
        if key not in data:
            what = 'flap sample rate in Hz' if key == 'rate_hz' else 'rotor speed in rad/s'
            parser.fail(f'{key} is missing: give the {what} of the planned run')
    rate_hz = parser.number(data['rate_hz'], 'rate_hz')
    omega = parser.number(data['omega_rad_s'], 'omega_rad_s', maximum=1e4,
                          hint=' (rad/s, not rpm?)')
    if omega / rate_hz > 0.5:
        parser.fail(f'{rate_hz:g} Hz gives {omega / rate_hz:.3g} rad of azimuth per sample at '
                    f'Ω = {omega:g} rad/s; sample at least 2π/0.5 ≈ 13 times per revolution',
                    'rate_hz')

    guess = _parse_guess(parser, data, description, model)
    target = {}
    if data.get('target_std') is not None:
        for name, value in parser.mapping(data['target_std'], 'target_std').items():
            if name not in description.unknowns:
                parser.fail(f'target_std.{name}: {name!r} is not an unknown of this plan; '
                            f'the unknowns are {", ".join(description.unknowns)}',
                            'target_std', name)
            target[name] = parser.number(value, 'target_std', name)
    collective = _collective(parser, data, guess, description.known)
    candidates = _parse_candidates(parser, data.get('candidates'), description.rotor)
    known_state = data.get('known_initial_state', False)
    if not isinstance(known_state, bool):
        parser.fail(f'known_initial_state must be true or false, not {known_state!r}',
                    'known_initial_state')
    given_collective = data.get('collective_rad') is not None
    defaults, sources = pipeline.parameter_defaults(
        description, model, collective=collective if given_collective else None,
        collective_source='collective_rad', given=set(guess) | (
            {'theta0'} if given_collective else set()))
    remarks = list(description.warnings)
    note = pipeline.defaults_warning(defaults, sources)
    if note:
        remarks.append(note)
    return Plan(description=description, guess=guess, noise_std_rad=description.noise_std_rad,
                rate_hz=rate_hz, omega_rad_s=omega, target_std=target,
                candidates=candidates, collective_rad=collective,
                warnings=tuple(remarks), path=path,
                known_initial_state=known_state, defaults_used=defaults)


def load_plan(path: 'str | os.PathLike[str]') -> Plan:
    """Read and validate the plan in file ``path`` (see :func:`parse_plan`)."""
    try:
        text = Path(path).read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as err:
        raise RunDescriptionError(f'{path}: cannot read the plan ({err}); give the path of a '
                                  'YAML file', str(path)) from None
    return parse_plan(text, path)


def _parse_guess(parser, data, description, model):
    names = model.parameter_names
    raw = parser.mapping(data['guess'], 'guess') if data.get('guess') is not None else {}
    guess = {}
    for name, value in raw.items():
        if name == 'gamma' and name not in names:
            guess.update(lock_number_from_known({name: parser.number(value, 'guess', name)},
                                                model))
            continue
        if name not in names:
            parser.fail(f'guess.{name}: model {model.name} has no parameter {name!r}; its '
                        f'parameters are {", ".join(names)}', 'guess', name)
        par = model.parameter(name)
        guess[name] = parser.number(value, 'guess', name, positive=par.lower > 0)
        if not par.lower <= guess[name] <= par.upper:
            parser.fail(f'guess.{name} = {value!r} is outside the physical range '
                        f'[{par.lower:g}, {par.upper:g}] {par.unit}', 'guess', name)
    missing = [n for n in description.unknowns if n not in guess]
    if missing:
        parser.fail(f'guess has no value for {", ".join(missing)}: the predicted σ depend on '
                    'the parameter values, so give your best guess of every unknown',
                    'guess' if 'guess' in data else ())
    return guess


def _collective(parser, data, guess, known):
    if data.get('collective_rad') is not None:
        return parser.number(data['collective_rad'], 'collective_rad', positive=False,
                             maximum=1.0, hint=' (radians, not degrees?)')
    values = {**known, **guess}
    if 'theta0' in values:
        return float(values['theta0'])
    if 'delta' in values and 'gamma' in values:
        return float(values['delta'] / values['gamma'])
    return DEFAULT_COLLECTIVE_RAD


def _as_list(value):
    return list(value) if isinstance(value, (list, tuple)) else [value]


def _parse_candidates(parser, spec, rotor):
    groups = [{}] if spec is None else _as_list(spec)
    out = []
    for g, group in enumerate(groups):
        where = ('candidates',) if not isinstance(spec, list) else ('candidates', g)
        group = parser.mapping(group, *where)
        for key in group:
            if key not in CANDIDATE_KEYS:
                parser.fail(f'unknown candidate key {key!r}; valid: {", ".join(CANDIDATE_KEYS)}',
                            *where, key)
        for key, value in group.items():
            if _as_list(value) == []:
                parser.fail(f'{key} is an empty list; give at least one value', *where, key)
        directions = _as_list(group.get('direction', DIRECTIONS if 'omegadot' not in group
                                        else [None]))
        for d in directions:
            if d is not None and d not in DIRECTIONS:
                parser.fail(f'direction must be progressing or regressing, got {d!r}', *where,
                            'direction')
        rates = [parser.number(v, *where, 'omegadot', positive=False, maximum=10.0)
                 for v in _as_list(group.get('omegadot', DEFAULT_OMEGADOT))]
        amps = [parser.number(v, *where, 'amplitude_rad', maximum=0.35,
                              hint=' for a cyclic stirring amplitude (radians, not degrees?)')
                for v in _as_list(group.get('amplitude_rad', DEFAULT_AMPLITUDE_RAD))]
        t0s = [parser.number(v, *where, 't0', positive=False)
               for v in _as_list(group.get('t0', default_t0(rotor.advance_ratio)))]
        if any(t < 0 for t in t0s):
            parser.fail('t0 (stirring delay after the cyclic step) must be ≥ 0', *where, 't0')
        lengths = [parser.number(v, *where, 'duration_rev', maximum=100.0)
                   for v in _as_list(group.get('duration_rev', DEFAULT_DURATION_REV))]
        for d, w, a, t0, n in itertools.product(directions, rates, amps, t0s, lengths):
            if w == 0:
                parser.fail("omegadot = 0 is no stirring; give the report's ω̇ (e.g. 0.0318)",
                            *where, 'omegadot')
            if d is None:
                d = 'progressing' if w < 0 else 'regressing'
            elif d == 'regressing' and w < 0:
                parser.fail(f'omegadot {w} < 0 is progressing stirring but direction says '
                            f'{d}; give |ω̇| with the direction', *where, 'omegadot')
            signed = -abs(w) if d == 'progressing' else abs(w)
            out.append(Candidate(d, signed, a, t0, n))
    unique = list(dict.fromkeys(out))
    if len(unique) > MAX_CANDIDATES:
        parser.fail(f'{len(unique)} candidates; plan at most {MAX_CANDIDATES} at once',
                    'candidates')
    return tuple(unique)


# ------------------------------------------------------------------------------------------------
# The planned run
# ------------------------------------------------------------------------------------------------

@dataclass
class PlannedRun:
    """
    A simulated run of a candidate transient.

    Attributes
    ----------
    record : Record
        Radians and seconds, as read from a bag; blade flap with noise when asked for.
    window_s : tuple
        Identification window of the candidate.
    models : list of LinearModel
        The simulated models (one multiblade model, or one single-blade model per blade).
    states : list of ndarray, shape (T, n)
        Their noise-free states at every record sample.
    p_full : ndarray
        Parameter vector of the simulation (the plan's guess and known values).

    """

    record: Record
    window_s: tuple
    models: list
    states: list
    p_full: np.ndarray


def description_for(plan: Plan, candidate: Candidate) -> 'RunDescription':
    """Return the run description ``identify`` needs for a candidate's record (its window)."""
    return replace(plan.description, window_s=candidate.window_s(plan.omega_rad_s))


def parameter_values(plan: Plan, model: 'RotorModel') -> np.ndarray:
    """Full parameter vector to plan around: nominal < known < guess (radians)."""
    known = lock_number_from_known(plan.description.known, model)
    values = {k: v for k, v in known.items() if k in model.parameter_names}
    if 'theta0' in model.parameter_names and 'theta0' not in plan.guess:
        values.setdefault('theta0', plan.collective_rad)
    values.update(plan.guess)
    return model.parameter_vector(values)


def _simulated_models(plan):
    model = pipeline.model_for(plan.description)
    if model.name != 'single_blade':
        return model, [model]
    rotor = model.rotor
    return model, [build_model('single_blade', rotor, collective=model.collective,
                               angle_unit='rad', blade=k) for k in range(1, rotor.n_blades + 1)]


def _trim_state(model, p, collective):
    """State at the record start: trim at collective pitch only (recording convention)."""
    return model.trim_state(p, collective, t=0.0)


def simulate_run(plan: Plan, candidate: Candidate, rng: np.random.Generator | None = None
                 ) -> PlannedRun:
    """
    Simulate the planned run of ``candidate``: a record, noise-free or with sensor noise.

    The library's simulator and model at the plan's parameter values make the per-blade flap
    (:mod:`rotor_id.physics.blades`); the blade pitch is the exact schedule. With ``rng`` each
    blade's flap gets independent Gaussian noise of σ = ``plan.noise_std_rad``.

    Parameters
    ----------
    plan : Plan
        Rotor, model, parameter values, sampling and noise.
    candidate : Candidate
        The transient and record length.
    rng : numpy.random.Generator, optional
        Source of the sensor noise; None for a noise-free record.

    Returns
    -------
    PlannedRun

    """
    model, models = _simulated_models(plan)
    p = parameter_values(plan, model)
    schedule = candidate.schedule(plan.collective_rad)
    window = candidate.window_s(plan.omega_rad_s)
    n = int(math.floor(window[1] * plan.rate_hz + 1e-9)) + 2
    time_s = np.arange(n) / plan.rate_hz
    t = plan.omega_rad_s * time_s
    states = [simulate(m, p, schedule, t, _trim_state(m, p, plan.collective_rad)).x
              for m in models]
    flap = blade_flap_from_states(models, t, states, model.coning(p, plan.collective_rad))
    if rng is not None:
        flap = flap + plan.noise_std_rad * rng.standard_normal(flap.shape)
    n_blades = plan.description.rotor.blades
    record = Record(time_s=time_s, t=t, rotor_speed_rad_s=np.full(n, plan.omega_rad_s),
                    blade_flap=flap, blade_pitch=schedule.blade_pitch(t, n_blades),
                    blade_names=[f'blade_{k}' for k in range(1, n_blades + 1)],
                    source=f'planned run: {candidate.label()}')
    return PlannedRun(record=record, window_s=window, models=models, states=states, p_full=p)


# ------------------------------------------------------------------------------------------------
# Predicted Cramér-Rao bound
# ------------------------------------------------------------------------------------------------

@dataclass
class TransientPrediction:
    """
    M⁻¹(t_f) of one stirring transient, for every record end t_f in its window.

    Attributes
    ----------
    candidate : Candidate
        The longest candidate of this transient (its window is the one evaluated).
    history : InformationHistory
        Over θ = unknowns + initial states at the window start (per run for single_blade).
    unknowns : list of str
    noise_std : ndarray or float
        σ of the model's channels (from the per-blade σ).
    stirring_start : float
        t of the window start (record time).

    """

    candidate: Candidate
    history: InformationHistory
    unknowns: list
    noise_std: np.ndarray | float
    stirring_start: float

    def record_length_rev(self) -> np.ndarray:
        """Record length t_f − t_start of every t_f, revolutions."""
        return (self.history.t - self.history.t[0]) / (2.0 * math.pi)

    def std(self) -> np.ndarray:
        """Predicted σ of the unknowns for every t_f, shape (T, k)."""
        return self.history.std()[:, :len(self.unknowns)]

    def std_with_samples(self, n_samples: int) -> np.ndarray:
        """σ of every θ name for the first ``n_samples`` samples of the window."""
        return self.history.std()[n_samples - 1]


def _combined_history(histories, k_par):
    """θ = [shared parameters, run 1's initial states, run 2's, …]: M of the runs adds up."""
    if len(histories) == 1:
        return histories[0]
    names = list(histories[0].names[:k_par])
    blocks = []
    for r, h in enumerate(histories):
        start = len(names)
        names += [f'{n}[{r + 1}]' for n in h.names[k_par:]]
        blocks.append(np.r_[0:k_par, start:len(names)])
    T = histories[0].t.size
    M = np.zeros((T, len(names), len(names)))
    for h, idx in zip(histories, blocks):
        M[:, idx[:, None], idx[None, :]] += h.information
    cov = np.array([inverse_or_nan(Mj) for Mj in M])
    return InformationHistory(t=histories[0].t, names=names, information=M, covariance=cov)


def predict_transient(plan: Plan, candidate: Candidate, initial_state: str | None = None,
                      blades: Sequence[int] | None = None) -> TransientPrediction:
    """
    Predicted Cramér-Rao bound M⁻¹(t_f) of a candidate's transient over its window.

    The noise-free planned run (:func:`simulate_run`) is cut to the candidate's window by the
    identification pipeline itself; each experiment's initial state is free as the run
    description says (default 'estimate': all states at the window start unknown) and evaluated
    at the simulated state there; the per-blade noise maps to the model's channels as in
    ``identify``.

    Parameters
    ----------
    plan : Plan
        Rotor, model, guess, sampling and noise.
    candidate : Candidate
        The transient; its window is evaluated (every shorter record comes with it).
    initial_state : str, optional
        Override of the description's mode; 'known' fixes every run's initial state at the
        simulated one (the report's "correct initial conditions", Ch.3 Table 1).
    blades : sequence of int, optional
        single_blade only: the blades whose flap is used (the report's Ch.3 uses blade 1).

    Returns
    -------
    TransientPrediction

    """
    run = simulate_run(plan, candidate)
    description = description_for(plan, candidate)
    if initial_state is not None and initial_state != 'known':
        description = replace(description, initial_state=initial_state)
    model = pipeline.model_for(description)
    experiments = pipeline.experiments_from_record(run.record, description, model)
    pairs = list(zip(experiments, run.states))                # one simulated model per run
    if blades is not None:
        if model.name != 'single_blade':
            raise ValueError('blades selects single-blade runs; the model is ' + model.name)
        pairs = [pairs[b - 1] for b in blades]
    noise = pipeline.channel_noise(model, plan.noise_std_rad)
    unknowns = plan.unknowns
    histories = []
    for exp, states in pairs:
        x0 = states[int(np.searchsorted(run.record.t, exp.t[0]))]
        if initial_state == 'known':
            exp = replace(exp, initial_state=x0)
        histories.append(
            information_history(exp, run.p_full, unknowns, noise_std=noise, x0=x0))
    history = _combined_history(histories, len(unknowns))
    return TransientPrediction(candidate=candidate, history=history, unknowns=unknowns,
                               noise_std=noise, stirring_start=candidate.stirring_start)


# ------------------------------------------------------------------------------------------------
# Candidates, targets and the recommendation
# ------------------------------------------------------------------------------------------------

@dataclass
class CandidateResult:
    """
    Predicted accuracy of one candidate.

    Attributes
    ----------
    candidate : Candidate
    std : dict
        Cramér-Rao σ of every unknown for the candidate's record.
    initial_state_std : dict
        σ of the initial states at the window start (nuisance parameters).
    relative_std : dict
        σ / |guess|.
    meets_target : bool
        Every stipulated σ reached (True when none is stipulated).
    shortest_duration_rev : float or None
        Shortest record of this transient meeting every stipulated σ (Ch.3 eq. 23), looked
        for up to :data:`HORIZON` times the longest record planned for the transient (so it
        may be longer than every candidate: how long a record would have to be); None when
        not met there or no targets.
    limiting : str
        The parameter met last (or furthest from its target, or worst relative σ).
    worst_ratio : float
        max σ_i / target_i over the stipulated σ (max σ_i/|guess_i| without targets).
    window_s : tuple
    n_samples : int
    transient_index : int
        Which :class:`TransientPrediction` it comes from.

    """

    candidate: Candidate
    std: dict
    initial_state_std: dict
    relative_std: dict
    meets_target: bool
    shortest_duration_rev: float | None
    limiting: str
    worst_ratio: float
    window_s: tuple
    n_samples: int
    transient_index: int

    def as_json(self) -> dict[str, Any]:
        """Return the candidate's JSON (the stable keys first)."""
        out = self.candidate.as_json()
        out.update({
            'std': {k: float(v) for k, v in self.std.items()},
            'meets_target': bool(self.meets_target),
            'relative_std': {k: float(v) for k, v in self.relative_std.items()},
            'shortest_duration_rev': (None if self.shortest_duration_rev is None
                                      else float(self.shortest_duration_rev)),
            'limiting_parameter': self.limiting,
            'worst_ratio': float(self.worst_ratio),
            'initial_state_std': {k: float(v) for k, v in self.initial_state_std.items()},
            'window_s': [float(self.window_s[0]), float(self.window_s[1])],
            'n_samples': int(self.n_samples),
            'final_stirring_rate_per_rev': float(self.candidate.final_stirring_rate()),
        })
        return out


@dataclass
class PlanResult:
    """Everything ``rotor-id plan`` reports."""

    plan: Plan
    candidates: list
    transients: list
    recommended: int
    elapsed_s: float
    warnings: list = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        """Return ``{"candidates": [...], "recommended": index, ...}``."""
        plan = self.plan
        return {
            'candidates': [c.as_json() for c in self.candidates],
            'recommended': int(self.recommended),
            'model': plan.description.model,
            'unknowns': plan.unknowns,
            'guess': {k: float(v) for k, v in plan.guess.items()},
            'target_std': {k: float(v) for k, v in plan.target_std.items()},
            'noise_std_rad': float(plan.noise_std_rad),
            'channel_noise_std_rad': [float(v) for v in np.atleast_1d(
                self.transients[0].noise_std)] if self.transients else [],
            'rate_hz': float(plan.rate_hz),
            'omega_rad_s': float(plan.omega_rad_s),
            'initial_state': ('known' if plan.known_initial_state
                              else plan.description.initial_state),
            'elapsed_s': float(self.elapsed_s),
            'warnings': list(self.warnings),
            'defaults_used': {k: float(v) for k, v in plan.defaults_used.items()},
        }


def _worst_ratio(std, plan):
    if plan.target_std:
        ratios = {n: std[n] / s for n, s in plan.target_std.items()}
    else:
        ratios = {n: std[n] / abs(plan.guess[n]) if plan.guess[n] else math.inf for n in std}
    name = max(ratios, key=lambda n: ratios[n])
    return ratios[name], name


def evaluate_plan(plan: Plan, progress: Callable[[dict[str, Any]], Any] | None = None
                  ) -> PlanResult:
    """
    Predict every candidate of a plan and choose the recommendation.

    Candidates sharing a transient (direction, ω̇, amplitude, t0) share one simulation: the
    σ of each record length are read off the transient's M⁻¹(t_f) curve.

    recommended = the candidate meeting every stipulated σ with the shortest record (ties: the
    better worst ratio σ/target); when none meets them, or none is stipulated, the candidate
    with the best worst relative accuracy (max σ_i/target_i, else max σ_i/|guess_i|).

    Parameters
    ----------
    plan : Plan
        From :func:`load_plan`.
    progress : callable, optional
        Called with a dict (index, of, label, elapsed) after each transient.

    Returns
    -------
    PlanResult

    """
    started = time.perf_counter()
    groups: dict[tuple, list[Candidate]] = {}
    for c in plan.candidates:
        groups.setdefault(c.transient, []).append(c)
    transients = []
    for i, members in enumerate(groups.values()):
        longest = max(members, key=lambda c: c.duration_rev)
        horizon = replace(longest, duration_rev=HORIZON * longest.duration_rev)
        transients.append(predict_transient(
            plan, horizon, initial_state='known' if plan.known_initial_state else None))
        if progress is not None:
            progress({'index': i + 1, 'of': len(groups), 'label': longest.label(),
                      'elapsed': time.perf_counter() - started})
    index_of = {key: i for i, key in enumerate(groups)}
    results = []
    k = len(plan.unknowns)
    for c in plan.candidates:
        ti = index_of[c.transient]
        pred = transients[ti]
        window = c.window_s(plan.omega_rad_s)
        # the samples identify will see: the window of the same record, inclusive ends
        rec_t = pred.history.t
        n_samples = int(np.count_nonzero(
            rec_t / plan.omega_rad_s <= window[1] + 1e-9))
        std_all = pred.std_with_samples(n_samples)
        names = pred.history.names
        std = dict(zip(names[:k], std_all[:k]))
        if not all(np.isfinite(list(std.values()))):
            raise ValueError(
                f'{plan.path}: the candidate {c.label()} with {c.duration_rev:g} revolutions '
                f'({n_samples} samples) does not determine {", ".join(plan.unknowns)} and its '
                f'{len(names) - k} initial states; plan a longer record')
        rel = {n: std[n] / abs(plan.guess[n]) if plan.guess[n] else math.inf for n in std}
        meets = all(std[n] <= s for n, s in plan.target_std.items())
        worst, limiting = _worst_ratio(std, plan)
        shortest = None
        if plan.target_std:
            answer = shortest_record(pred.history, plan.target_std)
            if answer.met:                  # (then its duration is a number)
                shortest = answer.duration / (2.0 * math.pi)  # type: ignore[operator]
                limiting = answer.limiting if meets else limiting
        results.append(CandidateResult(
            candidate=c, std=std, initial_state_std=dict(zip(names[k:], std_all[k:])),
            relative_std=rel, meets_target=meets, shortest_duration_rev=shortest,
            limiting=limiting, worst_ratio=worst, window_s=window, n_samples=n_samples,
            transient_index=ti))
    meeting = [i for i, r in enumerate(results) if r.meets_target and plan.target_std]
    if meeting:
        recommended = min(meeting, key=lambda i: (results[i].candidate.duration_rev,
                                                  results[i].shortest_duration_rev,
                                                  results[i].worst_ratio))
    else:
        recommended = min(range(len(results)), key=lambda i: results[i].worst_ratio)
    notes = list(plan.warnings)
    if plan.target_std and not meeting:
        best = results[recommended]
        reach = [r for r in results if r.shortest_duration_rev is not None]
        if reach:
            # (reach: the candidates with a shortest duration)
            quick = min(reach, key=(
                lambda r: r.shortest_duration_rev))  # type: ignore[arg-type,return-value]
            hint = (f'{quick.candidate.label()} would meet them with a record of '
                    f'{quick.shortest_duration_rev:.2f} rev')
        else:
            hint = ('none would within twice the planned records: plan a larger amplitude or '
                    'a quieter sensor')
        notes.append(f'no candidate meets target_std; the best reaches {best.worst_ratio:.2f}× '
                     f'the target of {best.limiting}; {hint}')
    return PlanResult(plan=plan, candidates=results, transients=transients,
                      recommended=recommended, elapsed_s=time.perf_counter() - started,
                      warnings=notes)


# ------------------------------------------------------------------------------------------------
# Checking a prediction: Monte Carlo spread of `identify` on simulated runs
# ------------------------------------------------------------------------------------------------

@dataclass
class MonteCarlo:
    """
    Estimates of ``identify`` on simulated noisy runs of one candidate, beside the prediction.

    Attributes
    ----------
    names : list of str
        The unknowns.
    estimates : ndarray, shape (N, k)
    converged : ndarray of bool, shape (N,)
    seeds : list of int
    predicted_std : ndarray, shape (k,)
    predicted_covariance : ndarray, shape (k, k)
        The unknowns' block of the predicted M⁻¹ (initial states marginalised).
    truth : ndarray, shape (k,)
        The plan's guess, the parameters the runs were simulated with.
    elapsed_s : float

    """

    names: list
    estimates: np.ndarray
    converged: np.ndarray
    seeds: list
    predicted_std: np.ndarray
    predicted_covariance: np.ndarray
    truth: np.ndarray
    elapsed_s: float

    def spread(self) -> np.ndarray:
        """Sample standard deviation of the converged estimates (about their mean)."""
        return np.std(self.estimates[self.converged], axis=0, ddof=1)

    def ratio(self) -> np.ndarray:
        """Monte Carlo spread / predicted σ, per unknown."""
        return self.spread() / self.predicted_std

    def pooled_statistic(self, scale: float = 1.0) -> tuple[float, int]:
        """
        D = Σ_runs (θ̂ − θ̄)ᵀ (scale² C)⁻¹ (θ̂ − θ̄) and its degrees of freedom k (N − 1).

        With C the true covariance of Gaussian estimates, D ~ χ²(k(N − 1)): a test of the
        whole predicted covariance (σ and correlations) against the spread. ``scale`` tries a
        prediction wrong by that factor in σ (to show a test would catch it).
        """
        est = self.estimates[self.converged]
        dev = est - est.mean(axis=0)
        inv = np.linalg.inv(self.predicted_covariance * scale**2)
        value = float(np.einsum('ni,ij,nj->', dev, inv, dev))
        return value, dev.shape[1] * (dev.shape[0] - 1)


def monte_carlo(plan: Plan, candidate: Candidate, seeds: Iterable[int],
                progress: Callable[[dict[str, Any]], Any] | None = None) -> 'MonteCarlo':
    """
    Run ``identify`` on noisy simulated runs of a candidate and collect the estimates.

    Each run is :func:`simulate_run` with ``numpy.random.default_rng(seed)``; identification
    uses the candidate's run description (:func:`description_for`) started at the plan's guess
    (no multi-start grid: the spread, not the search, is under test). The prediction is
    :func:`predict_transient` for the same candidate and record length.
    """
    if plan.known_initial_state:
        raise ValueError(f'{plan.path}: known_initial_state is true, but identify estimates the '
                         'initial state from the window; set it false to compare the plan '
                         'with identify')
    started = time.perf_counter()
    pred = predict_transient(plan, candidate)
    window = candidate.window_s(plan.omega_rad_s)
    n_samples = int(np.count_nonzero(pred.history.t / plan.omega_rad_s <= window[1] + 1e-9))
    k = len(plan.unknowns)
    cov = pred.history.covariance[n_samples - 1][:k, :k]
    description = replace(description_for(plan, candidate), initial_guess=dict(plan.guess))
    estimates, converged = [], []
    seeds = list(seeds)
    for i, seed in enumerate(seeds):
        run = simulate_run(plan, candidate, rng=np.random.default_rng(seed))
        result = pipeline.identify(run.record, description, multi_start=False)
        est = result.estimate
        estimates.append([est.value(n) for n in plan.unknowns])
        converged.append(bool(est.converged))
        if progress is not None:
            progress({'index': i + 1, 'of': len(seeds), 'elapsed': time.perf_counter() - started})
    return MonteCarlo(names=plan.unknowns, estimates=np.array(estimates),
                      converged=np.array(converged), seeds=seeds,
                      predicted_std=np.sqrt(np.diag(cov)), predicted_covariance=cov,
                      truth=np.array([plan.guess[n] for n in plan.unknowns]),
                      elapsed_s=time.perf_counter() - started)


# ------------------------------------------------------------------------------------------------
# Shape of the M⁻¹(t_f) curve (report Ch.3: "steep descent … to about t = 17.5", "another
# descent to t = 23.0")
# ------------------------------------------------------------------------------------------------

def steep_descents(t: npt.ArrayLike, variance: npt.ArrayLike, window: float = 1.0,
                   steep: float | None = None, min_drop: float = 1.25
                   ) -> list[tuple[float, float, float]]:
    """
    Find the ends of the steep descents of an M⁻¹(t_f) curve.

    The descent rate is the slope of log M⁻¹ against t_f over ±window/2 (central difference).
    A descent is a stretch where that rate is steeper than ``steep`` (default: the median rate
    of the curve, i.e. steeper than typical), stretches closer than ``window`` joined, over
    which M⁻¹ falls by at least ``min_drop``; its end is where the curve flattens again: the
    value the report reads off its figs 2-3 ("steep descent of the curves to about t = 17.5
    … another descent to t = 23.0").

    Parameters
    ----------
    t : array_like, shape (T,)
        Record ends t_f.
    variance : array_like, shape (T,)
        M⁻¹(t_f)(i, i) (NaN while M is singular).
    window : float
        Span of the rate, in units of t.
    steep : float, optional
        Rate threshold (negative, per unit t).
    min_drop : float
        Smallest factor by which M⁻¹ must fall over a descent.

    Returns
    -------
    list of (start, end, drop)
        Each steep descent: where it starts and ends and the factor by which M⁻¹ falls over it.

    """
    t = np.asarray(t, dtype=float)
    v = np.asarray(variance, dtype=float)
    ok = np.isfinite(v) & (v > 0)
    t, logv = t[ok], np.log(v[ok])
    if t.size < 3:
        return []
    half = 0.5 * window
    lo = np.searchsorted(t, t - half)
    hi = np.searchsorted(t, t + half, side='right') - 1
    rate = (logv[hi] - logv[lo]) / np.maximum(t[hi] - t[lo], 1e-12)
    threshold = min(float(np.median(rate)) if steep is None else float(steep), 0.0)
    stretches: list[list[int]] = []     # [first, last] sample of each descent
    j = 0
    while j < t.size:
        if rate[j] >= threshold:
            j += 1
            continue
        start = j
        while j + 1 < t.size and rate[j + 1] < threshold:
            j += 1
        if stretches and t[start] - t[stretches[-1][1]] < window:
            stretches[-1][1] = j
        else:
            stretches.append([start, j])
        j += 1
    return [(float(t[a]), float(t[b]), float(np.exp(logv[a] - logv[b])))
            for a, b in stretches if logv[a] - logv[b] >= math.log(min_drop)]


# ------------------------------------------------------------------------------------------------
# Figure
# ------------------------------------------------------------------------------------------------

def write_figure(result: PlanResult, path: 'str | os.PathLike[str]'
                 ) -> 'str | os.PathLike[str]':
    """
    σ of each unknown against record length, one curve per transient (Ch.3 figs 2-3).

    Log scale; progressing solid, regressing dashed; dots at the candidates' record lengths,
    a star at the recommended one; horizontal lines at the stipulated σ.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    plan = result.plan
    names = plan.unknowns
    fig, axes = plt.subplots(1, len(names), figsize=(4.6 * len(names), 4.2), squeeze=False,
                             constrained_layout=True)
    colors = plt.rcParams['axes.prop_cycle'].by_key()['color']
    for ax, name in zip(axes[0], names):
        for ti, pred in enumerate(result.transients):
            c = pred.candidate
            i = pred.unknowns.index(name)
            style = '-' if c.direction == 'progressing' else '--'
            ax.semilogy(pred.record_length_rev(), pred.std()[:, i], style,
                        color=colors[ti % len(colors)], lw=1.2,
                        label=f'{c.direction[:4]}. ω̇={abs(c.omegadot):.3g}, '
                              f'{math.degrees(c.amplitude_rad):.2g}°, t0={c.t0:g}')
        for ci, r in enumerate(result.candidates):
            color = colors[r.transient_index % len(colors)]
            if ci == result.recommended:
                ax.semilogy(r.candidate.duration_rev, r.std[name], '*', ms=14, color=color,
                            markeredgecolor='k', zorder=5)
            else:
                ax.semilogy(r.candidate.duration_rev, r.std[name], 'o', ms=4, color=color)
        marks = [r.std[name] for r in result.candidates]
        marks += [float(np.nanmin(p.std()[:, p.unknowns.index(name)])) for p in result.transients]
        if name in plan.target_std:
            target = plan.target_std[name]
            marks.append(target)
            ax.axhline(target, color='k', lw=0.8, ls=':')
            ax.text(0.02, target, 'target', transform=ax.get_yaxis_transform(), fontsize=8,
                    va='bottom')
        ax.set_ylim(0.5 * min(marks), 50.0 * max(marks))   # the early, singular part is off
        ax.set_xlabel('record length from stirring start [rev]')
        ax.set_ylabel(f'predicted Cramér-Rao σ of {name}')
        ax.grid(True, which='both', alpha=0.3)
    axes[0][0].legend(fontsize=7, loc='upper right')
    best = result.candidates[result.recommended]
    fig.suptitle(f'{plan.description.model}: σ vs record length (√M⁻¹(t_f), Ch.3 figs 2-3); '
                 f'noise {plan.noise_std_rad:.2g} rad/blade, {plan.rate_hz:g} Hz, '
                 f'Ω = {plan.omega_rad_s:g} rad/s\nrecommended (★): {best.candidate.label()}, '
                 f'{best.candidate.duration_rev:g} rev', fontsize=9)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
