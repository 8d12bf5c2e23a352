"""
Run descriptions: what the experimenter knows about a recording (YAML).

The schema (docs/run_description.md, with the recording convention)::

    rotor: {blades: 4, advance_ratio: 0.0, flap_frequency: 1.2, tip_loss: 0.97,
            pitch_flap_coupling: 0.0}          # optional, tan δ3 (default 0)
    topics: {blade_pitch: /rotor/blade_pitch, blade_flap: /rotor/blade_flap,
             azimuth: /rotor/azimuth}
    model: multiblade_wake
    unknowns: [A, AL_over_tau, inv_tau]
    window_s: [0.809, 0.937]

extended, without breaking it, by optional keys::

    joint_names: [b1, b2, b3, b4]        # or {blade_1: b1, ...} or {blade_pitch: [...],
                                         #    blade_flap: [...], azimuth: hub}; joint of each
                                         #    blade, and the azimuth topic's joint (rotor)
    azimuth_convention: wrapped          # wrapped: ψ in [0, 2π) or [-π, π) | unwrapped:
                                         #    continuous ψ
    known: {gamma: 5.0}                  # parameters held fixed
    initial_guess: {gamma: 4.0}          # start of the iteration
    initial_state: estimate              # estimate | equilibrium | zero
    noise_std_rad: 0.0017                # known flap-sensor noise, rad
    method: output-error
    measurement: blades                  # blades | multiblade | eq30 (default: model's)
    lock_number: 4.52                    # γ of the wake model (same as known: {gamma: ...})
    conditions: {collective_deg: 4, tunnel_speed_m_s: 20, run: 17}
                                         # the test point's conditions (numbers or text),
                                         # reported by ``rotor-id campaign``
    inflow: cyclic                       # wake model: cyclic (report) | three_state

The same file describes the rig to the live nodes (parameter ``run_description``): ``topics``
may also name ``pitch_command``, ``stirring``, ``estimate``, ``progress`` and ``state``, and topic
names may be relative (``rotor/blade_flap``), so that a node's namespace (``-r __ns:=/rig2``)
moves the whole rig. Offline, a relative name is the bag's topic of that name in the root
namespace, else in the one namespace that has it (:func:`recorded_topic`).

Errors raise :class:`RunDescriptionError` naming the file, the line and what to do. An
unknown key that looks like a misspelt known one (``knwon:``) is an error with the suggestion,
because ignoring it would change the answer silently; other unknown keys only warn
(:class:`RunDescriptionWarning`), so that newer files still load.
"""

from dataclasses import dataclass, field
import difflib
import math
import os
from pathlib import Path
import re
from typing import Any, Collection, Iterable, TYPE_CHECKING
import warnings

from rotor_id.io.errors import RunDescriptionError, RunDescriptionWarning
from rotor_id.physics.aerodynamics import flap_damping
import yaml

if TYPE_CHECKING:
    from rotor_id.io.record import Record

MODEL_PARAMETERS = {
    'single_blade': ('gamma', 'theta0', 'delta'),
    'multiblade': ('gamma', 'theta0', 'delta'),
    'multiblade_constant': ('gamma', 'theta0', 'delta'),
    'multiblade_wake': ('A', 'AL_over_tau', 'inv_tau', 'gamma', 'theta0', 'AL0_over_tau0',
                        'inv_tau0'),
}
MODELS = tuple(MODEL_PARAMETERS)
POSITIVE_PARAMETERS = ('gamma', 'A', 'AL_over_tau', 'inv_tau', 'AL0_over_tau0', 'inv_tau0')
ANGLE_PARAMETERS = ('theta0',)  # radians: a value above MAX_ANGLE_RAD is taken for degrees
MAX_ANGLE_RAD = 1.0
INITIAL_STATES = ('estimate', 'equilibrium', 'zero')
METHODS = ('output-error', 'filter-error', 'equation-error')
MEASUREMENTS = ('blades', 'multiblade', 'eq30')
INFLOWS = ('cyclic', 'three_state')
TOPIC_ROLES = ('blade_pitch', 'blade_flap', 'azimuth')      # recorded: read from bags
#: Topics only the live nodes use (commands and results), default names relative.
NODE_TOPIC_ROLES = ('pitch_command', 'stirring', 'estimate', 'progress', 'state')
DEFAULT_NODE_TOPICS = {
    'pitch_command': 'rotor/pitch_command',
    'stirring': 'rotor/stirring',
    'estimate': 'rotor_id/estimate',
    'progress': 'rotor_id/progress',
    'state': 'rotor_id/state',
}
#: wrapped: the azimuth joint's position is ψ of blade 1 in [0, 2π); unwrapped: it is continuous
#: (an encoder count turned into radians); either way ψ of blade 1, rad, increasing.
AZIMUTH_CONVENTIONS = ('wrapped', 'unwrapped')
DEFAULT_AZIMUTH_JOINT = 'rotor'
_TOPIC_NAME = re.compile(r'/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*')
#: The recorded topics of the test-stand convention (absolute: as they appear in a bag); a run
#: description without ``topics`` means the same names relative to the node's namespace.
DEFAULT_TOPICS = {
    'blade_pitch': '/rotor/blade_pitch',
    'blade_flap': '/rotor/blade_flap',
    'azimuth': '/rotor/azimuth',
}
ROTOR_KEYS = ('blades', 'advance_ratio', 'flap_frequency', 'tip_loss', 'pitch_flap_coupling')
#: Largest plausible value of each rotor constant: beyond it the number is in another unit (the
#: flap frequency P is per rev, ≈ 1-1.5 for test-stand rotors, not Hz or rad/s; μ is a ratio,
#: not a percentage), and the model's coefficients (P², μ³) would overflow.
ROTOR_LIMITS = {'blades': 64, 'advance_ratio': 2.0, 'flap_frequency': 10.0}
#: An unknown key this similar (difflib ratio, case-insensitive) to a known one is a typo.
TYPO_SIMILARITY = 0.75
TOP_LEVEL_KEYS = (
    'rotor', 'topics', 'model', 'unknowns', 'window_s', 'joint_names', 'known',
    'initial_guess', 'initial_state', 'noise_std_rad', 'method', 'measurement', 'lock_number',
    'conditions', 'run', 'inflow', 'azimuth_convention',
)
BLADE_JOINT_ROLES = ('blade_pitch', 'blade_flap')


@dataclass(frozen=True)
class RotorSpec:
    """
    The rotor of the test stand.

    Attributes
    ----------
    blades
        Number of blades N.
    advance_ratio
        μ.
    flap_frequency
        P, rotating flap natural frequency, per rev.
    tip_loss
        B.
    pitch_flap_coupling
        K_P = tan δ3 (0 unless the description says).

    """

    blades: int
    advance_ratio: float
    flap_frequency: float
    tip_loss: float
    pitch_flap_coupling: float = 0.0


@dataclass(frozen=True)
class RunDescription:
    """
    A validated run description. Treat the dict fields as read-only.

    Attributes
    ----------
    rotor
        RotorSpec.
    topics
        Role ('blade_pitch', 'blade_flap', 'azimuth') -> topic name (relative or absolute).
    model
        One of :data:`MODELS`.
    unknowns
        Parameters to identify, in the file's order.
    window_s
        (t0, t1), seconds after the first flap stamp (of the chosen run).
    run
        Which run of a bag holding several (its stamps jump back: a clock reset), 1-based
        in recording order; None when the bag holds one.
    joint_names
        None, or role ('blade_pitch', 'blade_flap') -> tuple of joint names in
        blade order.
    known
        Parameter -> value held fixed (``lock_number`` is merged in as 'gamma').
    initial_guess
        Parameter -> starting value.
    initial_state
        'estimate' | 'equilibrium' | 'zero'.
    noise_std_rad
        Known flap-measurement noise, or None.
    method
        Estimation method, 'output-error' by default.
    measurement
        'blades' | 'multiblade' | 'eq30', or None for the model's default.
    lock_number
        γ for the wake model, or None.
    conditions
        Name -> number or text: the test point's conditions (tunnel speed, run number ...).
    inflow
        Wake model's inflow: 'cyclic' (the report's) or 'three_state'; None for the default.
    node_topics
        Role (:data:`NODE_TOPIC_ROLES`) -> topic name, for the live nodes.
    azimuth_joint
        Joint name on the azimuth topic ('rotor' unless ``joint_names.azimuth``).
    azimuth_convention
        'wrapped' (ψ in [0, 2π)) or 'unwrapped' (continuous ψ).
    path
        File the description was read from ('<string>' if parsed from text).
    warnings
        Non-fatal remarks (unknown keys).
    extra
        Unknown top-level keys and their values, kept for newer tools.
    lines
        Key path (tuple, e.g. ('rotor', 'blades')) -> 1-based line in the file, for messages
        about the description found later (e.g. against the bag, :func:`check_against_record`).

    """

    rotor: RotorSpec
    topics: dict
    model: str
    unknowns: tuple
    window_s: tuple
    run: int | None = None
    joint_names: dict[str, tuple[str, ...]] | None = None
    known: dict = field(default_factory=dict)
    initial_guess: dict = field(default_factory=dict)
    initial_state: str = 'estimate'
    noise_std_rad: float | None = None
    method: str = 'output-error'
    measurement: str | None = None
    lock_number: float | None = None
    conditions: dict = field(default_factory=dict)
    inflow: str | None = None
    node_topics: dict = field(default_factory=lambda: dict(DEFAULT_NODE_TOPICS))
    azimuth_joint: str = DEFAULT_AZIMUTH_JOINT
    azimuth_convention: str = 'wrapped'
    path: str = '<string>'
    warnings: tuple = ()
    extra: dict = field(default_factory=dict)
    lines: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def parameters(self) -> tuple[str, ...]:
        """Return the parameter names of the model."""
        return MODEL_PARAMETERS[self.model]

    def record_options(self) -> dict[str, Any]:
        """
        Keyword arguments of :func:`rotor_id.io.bag.read_record` for this rig.

        The blade count is not among them: :func:`check_against_record` compares it with the
        bag's joints afterwards, naming the line of ``rotor.blades``.
        """
        return {'topics': dict(self.topics), 'joint_names': self.joint_names,
                'run': self.run, 'window_s': self.window_s,
                'azimuth_joint': self.azimuth_joint,
                'azimuth_convention': self.azimuth_convention}

    def blade_joints(self, role: str) -> list[str]:
        """Joint names of ``role`` ('blade_flap' | 'blade_pitch'), blade 1 first."""
        if self.joint_names is not None:
            return list(self.joint_names[role])
        return [f'blade_{k}' for k in range(1, self.rotor.blades + 1)]

    def bag_path(self) -> Path:
        """Return the conventional bag of this description: NAME/ beside NAME.yaml."""
        if self.path == '<string>':
            raise ValueError('a description parsed from text has no bag beside it')
        return Path(self.path).with_suffix('')


def normalize_joint_names(value: object, n_blades: int | None = None
                          ) -> dict[str, tuple[str, ...]]:
    """
    Bring the accepted forms of ``joint_names`` to {role: tuple of names in blade order}.

    Accepted forms: a list (blade 1 first), a mapping blade -> name with keys 'blade_<k>' or
    integers k, or a mapping with keys 'blade_pitch' / 'blade_flap' whose values are either of
    the former (a role not given uses the other role's names).

    Parameters
    ----------
    value
        The ``joint_names`` value.
    n_blades
        Expected number of blades, or None.

    Returns
    -------
    Dict with keys 'blade_pitch' and 'blade_flap'.

    Raises
    ------
    ValueError
        Malformed value (the message says which form is expected).

    """
    if isinstance(value, dict) and value and set(value) <= set(BLADE_JOINT_ROLES):
        roles = {role: _joint_list(names, n_blades, role) for role, names in value.items()}
        for role in BLADE_JOINT_ROLES:
            roles.setdefault(role, next(iter(roles.values())))
        return roles
    names = _joint_list(value, n_blades, 'joint_names')
    return {role: names for role in BLADE_JOINT_ROLES}


def recorded_topic(name: str | None, available: Collection[str]) -> str | None:
    """
    Return the topic of a bag that a run description's topic ``name`` means.

    An absolute name is itself. A relative one is the same name in the root namespace if the
    bag has it, else the one topic ``/<namespace>/<name>`` of the bag (a rig recorded under
    ``-r __ns:=/rig2``); None if none or several match.
    """
    if name is None or name.startswith('/'):
        return name
    if '/' + name in available:
        return '/' + name
    matches = [topic for topic in available if topic.endswith('/' + name)]
    return matches[0] if len(matches) == 1 else None


def _joint_list(value, n_blades, what):
    if isinstance(value, dict):
        blades = {}
        for key, name in value.items():
            match = re.fullmatch(r'blade_(\d+)', key) if isinstance(key, str) else None
            number = int(match.group(1)) if match else key
            if isinstance(number, bool) or not isinstance(number, int):
                raise ValueError(
                    f'{what}: key {key!r} is not a blade; use blade_1..blade_N or 1..N')
            blades[number] = name
        if sorted(blades) != list(range(1, len(blades) + 1)):
            raise ValueError(f'{what}: blades {sorted(blades)} are not 1..{len(blades)}')
        value = [blades[k] for k in range(1, len(blades) + 1)]
    if not isinstance(value, (list, tuple)) or not value:
        raise ValueError(
            f'{what} must be a non-empty list of joint names (blade 1 first) or a mapping '
            'blade_k: name')
    if not all(isinstance(name, str) and name for name in value):
        raise ValueError(f'{what}: every joint name must be a non-empty string, got {value!r}')
    if len(set(value)) != len(value):
        raise ValueError(f'{what}: joint names repeat: {list(value)}')
    if n_blades is not None and len(value) != n_blades:
        raise ValueError(f'{what}: {len(value)} joint names for {n_blades} blades')
    return tuple(value)


class SourceLines:
    """Line numbers of the keys and items of a composed YAML document, by path."""

    def __init__(self, node):
        self.lines = {}
        self.duplicates = []
        self._walk(node, ())

    def _walk(self, node, path):
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key_node, value_node in node.value:
                key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                if key in seen:
                    self.duplicates.append((path + (key,), seen[key], _line(key_node)))
                seen[key] = _line(key_node)
                self.lines[path + (key,)] = _line(key_node)
                self._walk(value_node, path + (key,))
        elif isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                self.lines[path + (index,)] = _line(item)
                self._walk(item, path + (index,))

    def __call__(self, *path):
        """Line of ``path``, else of its nearest ancestor that has one."""
        while path:
            if path in self.lines:
                return self.lines[path]
            path = path[:-1]
        return 1


def _line(node):
    return node.start_mark.line + 1


class _Parser:
    """Validate a loaded document, raising errors that point at the file and line."""

    def __init__(self, data, lines, path):
        self.data = data
        self.lines = lines
        self.path = path
        self.warnings = []

    def fail(self, message, *path):
        line = self.lines(*path) if path else None
        where = f'{self.path}:{line}' if line else self.path
        raise RunDescriptionError(f'{where}: {message}', self.path, line)

    def unknown_key(self, key, valid, *path, note=''):
        """Unknown key: an error when it looks like a typo of a valid key, else a warning."""
        lowered = {v.lower(): v for v in valid}
        close = difflib.get_close_matches(str(key).lower(), list(lowered), n=1,
                                          cutoff=TYPO_SIMILARITY)
        name = '.'.join(str(p) for p in path)
        if close:
            self.fail(f'unknown key {name!r}; did you mean `{lowered[close[0]]}`? (fix the '
                      'spelling: as written the key would be ignored)', *path)
        self.warn(f'unknown key {name!r} ignored{note}', *path)

    def warn(self, message, *path):
        text = f'{self.path}:{self.lines(*path)}: {message}'
        self.warnings.append(text)
        warnings.warn(text, RunDescriptionWarning, stacklevel=4)

    def mapping(self, value, *path):
        if not isinstance(value, dict):
            name = '.'.join(str(p) for p in path) or 'the document'
            self.fail(f'{name} must be a mapping (key: value), got {_kind(value)}', *path)
        for key in value:
            if not isinstance(key, str):
                self.fail(f'key {key!r} must be a string', *path)
        return value

    def require(self, mapping, key, *path):
        if key not in mapping:
            name = '.'.join(str(p) for p in path + (key,))
            self.fail(f'missing required key {name!r}; see the run-description schema in '
                      'docs/run_description.md', *path)
        return mapping[key]

    def number(self, value, *path, minimum=None, positive=False, integer=False):
        name = '.'.join(str(p) for p in path)
        kind = 'an integer' if integer else 'a number'
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (
                integer and not isinstance(value, int)):
            self.fail(f'{name} must be {kind}, got {value!r}', *path)
        try:
            finite = math.isfinite(value)
        except OverflowError:
            finite = False
        if not finite:
            self.fail(f'{name} must be a finite number, got {value!r}', *path)
        if positive and value <= 0:
            self.fail(f'{name} must be positive, got {value!r}', *path)
        if minimum is not None and value < minimum:
            self.fail(f'{name} must be at least {minimum}, got {value!r}; negative values '
                      'have no meaning here', *path)
        return value if integer else float(value)

    def choice(self, value, options, *path):
        if not isinstance(value, str) or value not in options:
            name = '.'.join(str(p) for p in path)
            self.fail(f'unknown {name} {value!r}; valid: {", ".join(options)}', *path)
        return value

    def parameter_values(self, key, model):
        """Validate a {parameter: value} mapping such as ``known``."""
        values = self.mapping(self.data[key], key)
        out = {}
        for name, value in values.items():
            self.parameter_name(name, model, key, name)
            out[name] = self.parameter_value(name, value, key, name)
        return out

    def parameter_name(self, name, model, *path):
        valid = MODEL_PARAMETERS[model]
        if name not in valid:
            close = difflib.get_close_matches(str(name), valid, n=1, cutoff=TYPO_SIMILARITY)
            hint = f'did you mean `{close[0]}`? ' if close else ''
            self.fail(f'unknown parameter {name!r} for model {model}; {hint}valid: '
                      f'{", ".join(valid)}', *path)

    def parameter_value(self, name, value, *path):
        value = self.number(value, *path, positive=name in POSITIVE_PARAMETERS)
        if name in ANGLE_PARAMETERS and abs(value) > MAX_ANGLE_RAD:
            self.fail(f'{name} = {value} rad is implausibly large: angles are in radians '
                      f'(the value looks like degrees; use {math.radians(value):.6g})', *path)
        return value


def _kind(value):
    return 'nothing' if value is None else type(value).__name__


def parse_run_description(text: str, path: str | os.PathLike = '<string>',
                          extra_keys: Iterable[str] = ()) -> RunDescription:
    """
    Parse and validate a run description.

    Parameters
    ----------
    text
        The YAML text.
    path
        Name of its file, used in messages.
    extra_keys
        Further top-level keys the caller reads itself (e.g. the plan's ``rate_hz``): neither
        warned about nor kept in ``extra``, and misspellings of them are caught too.

    Returns
    -------
    RunDescription.

    Raises
    ------
    RunDescriptionError
        Malformed YAML or invalid content.

    """
    path = str(path)
    try:
        loader = yaml.SafeLoader(text)
        try:
            node = loader.get_single_node()
            data = loader.construct_document(node) if node is not None else None
        finally:
            loader.dispose()
        lines = SourceLines(node if node is not None else yaml.ScalarNode('', ''))
    except yaml.YAMLError as err:
        mark = getattr(err, 'problem_mark', None)
        line = mark.line + 1 if mark is not None else None
        where = f'{path}:{line}' if line else path
        raise RunDescriptionError(
            f'{where}: malformed YAML ({err}); fix the syntax', path, line) from None
    except (ValueError, TypeError, RecursionError) as err:  # e.g. bad dates, deep nesting
        raise RunDescriptionError(f'{path}: unreadable YAML ({err})', path) from None
    return _validate(_Parser(data, lines, path), tuple(extra_keys))


def load_run_description(path: str | os.PathLike) -> RunDescription:
    """
    Read and validate the run description in file ``path`` (see module docstring).

    Raises
    ------
    RunDescriptionError
        File unreadable, malformed YAML or invalid content.

    """
    try:
        text = Path(path).read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as err:
        raise RunDescriptionError(
            f'{path}: cannot read the run description ({err}); give the path of a YAML file',
            str(path)) from None
    return parse_run_description(text, path)


def _validate(parser, extra_keys=()):
    data = parser.mapping(parser.data)
    if parser.lines.duplicates:
        where, first, second = parser.lines.duplicates[0]
        parser.fail(f'key {".".join(str(p) for p in where)!r} is given twice (lines {first} '
                    f'and {second}); keep one', *where)
    valid_keys = TOP_LEVEL_KEYS + tuple(extra_keys)
    for key in data:
        if key not in valid_keys:
            parser.unknown_key(key, valid_keys, key,
                               note=f' (known keys: {", ".join(valid_keys)})')

    rotor = parser.mapping(parser.require(data, 'rotor'), 'rotor')
    for key in rotor:
        if key not in ROTOR_KEYS:
            parser.unknown_key(key, ROTOR_KEYS, 'rotor', key)
    spec = RotorSpec(
        blades=parser.number(parser.require(rotor, 'blades', 'rotor'), 'rotor', 'blades',
                             integer=True, minimum=1),
        advance_ratio=parser.number(parser.require(rotor, 'advance_ratio', 'rotor'),
                                    'rotor', 'advance_ratio', minimum=0),
        flap_frequency=parser.number(parser.require(rotor, 'flap_frequency', 'rotor'),
                                     'rotor', 'flap_frequency', positive=True),
        tip_loss=parser.number(parser.require(rotor, 'tip_loss', 'rotor'),
                               'rotor', 'tip_loss', positive=True),
        pitch_flap_coupling=parser.number(rotor.get('pitch_flap_coupling', 0.0), 'rotor',
                                          'pitch_flap_coupling'),
    )
    if spec.tip_loss > 1:
        parser.fail(f'rotor.tip_loss must be in (0, 1], got {spec.tip_loss}', 'rotor', 'tip_loss')
    for key, limit in ROTOR_LIMITS.items():
        value = getattr(spec, key)
        if value > limit:
            unit = {'flap_frequency': ' (per rev: P ≈ 1-1.5, not Hz or rad/s)',
                    'advance_ratio': ' (a ratio V/ΩR, not a percentage or a speed)'}.get(key, '')
            parser.fail(f'rotor.{key} = {value:g} is implausibly large{unit}; the largest value '
                        f'accepted is {limit:g}', 'rotor', key)

    options = {}
    topics = {role: name[1:] for role, name in DEFAULT_TOPICS.items()}   # relative by default
    node_topics = dict(DEFAULT_NODE_TOPICS)
    if 'topics' in data:
        roles = TOPIC_ROLES + NODE_TOPIC_ROLES
        for role, topic in parser.mapping(data['topics'], 'topics').items():
            if role not in roles:
                parser.unknown_key(role, roles, 'topics', role,
                                   note=f' (roles: {", ".join(roles)})')
                continue
            if role == 'azimuth' and topic is None:
                topics[role] = None  # azimuth not recorded: t from the rotor speed
                continue
            if not isinstance(topic, str) or not _TOPIC_NAME.fullmatch(topic):
                parser.fail(f'topics.{role} must be a ROS topic name such as '
                            f'{DEFAULT_TOPICS.get(role, "")[1:] or DEFAULT_NODE_TOPICS[role]} '
                            "(relative: moves with the node's namespace) or /rig/"
                            f'{role} (absolute), got {topic!r}', 'topics', role)
            (topics if role in TOPIC_ROLES else node_topics)[role] = topic
    options['node_topics'] = node_topics
    if 'azimuth_convention' in data:
        options['azimuth_convention'] = parser.choice(
            data['azimuth_convention'], AZIMUTH_CONVENTIONS, 'azimuth_convention')

    model = parser.choice(parser.require(data, 'model'), MODELS, 'model')

    unknowns = parser.require(data, 'unknowns')
    if isinstance(unknowns, str):
        unknowns = [unknowns]
    if not isinstance(unknowns, list) or not unknowns:
        parser.fail('unknowns must be a non-empty list of parameter names, valid for model '
                    f'{model}: {", ".join(MODEL_PARAMETERS[model])}', 'unknowns')
    for index, name in enumerate(unknowns):
        parser.parameter_name(name, model, 'unknowns', index)
    if len(set(unknowns)) != len(unknowns):
        parser.fail(f'unknowns repeat a parameter: {unknowns}', 'unknowns')

    window = parser.require(data, 'window_s')
    if not isinstance(window, list) or len(window) != 2:
        parser.fail(f'window_s must be two numbers [t0, t1] (seconds after the first stamp), '
                    f'got {window!r}', 'window_s')
    t0 = parser.number(window[0], 'window_s', 0, minimum=0)
    t1 = parser.number(window[1], 'window_s', 1, minimum=0)
    if not t1 > t0:
        parser.fail(f'window_s must be increasing [t0, t1] with t1 > t0, got {window}',
                    'window_s')

    if 'run' in data:
        options['run'] = parser.number(data['run'], 'run', integer=True, minimum=1)
    joint_names = data.get('joint_names')
    if isinstance(joint_names, dict) and 'azimuth' in joint_names:
        joint_names = dict(joint_names)
        azimuth = joint_names.pop('azimuth')
        if not isinstance(azimuth, str) or not azimuth:
            parser.fail(f'joint_names.azimuth must be the joint name on the azimuth topic, '
                        f'got {azimuth!r}', 'joint_names', 'azimuth')
        options['azimuth_joint'] = azimuth
    if joint_names:
        try:
            options['joint_names'] = normalize_joint_names(joint_names, spec.blades)
        except ValueError as err:
            parser.fail(str(err), 'joint_names')
    _check_rig_names(parser, spec.blades, options, {**topics, **node_topics})
    for key in ('known', 'initial_guess'):
        if key in data:
            options[key] = parser.parameter_values(key, model)
    known = options.setdefault('known', {})
    if 'lock_number' in data:
        gamma = parser.number(data['lock_number'], 'lock_number', positive=True)
        if known.get('gamma', gamma) != gamma:
            parser.fail(f'lock_number {gamma} contradicts known.gamma {known["gamma"]}; '
                        'give one of them', 'lock_number')
        options['lock_number'] = known['gamma'] = gamma
    collective = sorted({'theta0', 'delta'} & (set(known) | set(unknowns)))
    if len(collective) == 2:
        parser.fail('theta0 and delta (δ = γθ0) are one parameter in two forms; give one of '
                    'them, as unknown or known', 'known' if 'known' in data else 'unknowns')
    both = sorted(set(known) & set(unknowns))
    if both:
        parser.fail(f'parameters {both} are both unknown and known; remove them from one '
                    'list', 'known' if 'known' in data else 'lock_number')
    if model == 'multiblade_wake':
        _check_wake_gain(parser, spec, unknowns, known, data)
    if 'initial_state' in data:
        options['initial_state'] = parser.choice(data['initial_state'], INITIAL_STATES,
                                                 'initial_state')
    if 'noise_std_rad' in data:
        noise = parser.number(data['noise_std_rad'], 'noise_std_rad', positive=True)
        if noise > MAX_ANGLE_RAD:
            parser.fail(f'noise_std_rad = {noise} rad is implausibly large: the unit is '
                        'radians (degrees?)', 'noise_std_rad')
        options['noise_std_rad'] = noise
    if 'method' in data:
        options['method'] = parser.choice(data['method'], METHODS, 'method')
    if 'measurement' in data:
        options['measurement'] = parser.choice(data['measurement'], MEASUREMENTS,
                                               'measurement')
    if 'conditions' in data:
        conditions = parser.mapping(data['conditions'], 'conditions')
        for name, value in conditions.items():
            if isinstance(value, bool) or not isinstance(value, (int, float, str)):
                parser.fail(f'conditions.{name} must be a number or a text, got {value!r}',
                            'conditions', name)
        options['conditions'] = dict(conditions)
    if 'inflow' in data:
        if model != 'multiblade_wake':
            parser.fail(f'inflow applies to the wake model only (model: {model}); remove it or '
                        'use model: multiblade_wake', 'inflow')
        options['inflow'] = parser.choice(data['inflow'], INFLOWS, 'inflow')

    return RunDescription(
        rotor=spec, topics=topics, model=model, unknowns=tuple(unknowns), window_s=(t0, t1),
        path=parser.path, warnings=tuple(parser.warnings),
        extra={k: v for k, v in data.items() if k not in valid_keys},
        lines=dict(parser.lines.lines), **options)


def _check_rig_names(parser, blades, options, topics):
    """
    Refuse a rig whose names cannot be told apart (one clear line each).

    The azimuth joint must not also be a blade's joint (its samples would be taken for a
    blade's, or a blade's for the azimuth), and no two topic roles may share a topic: a sensor
    topic that is also the pitch-command topic would feed the commands back as measured pitch,
    and the nodes read exactly one joint per blade (or the azimuth's) from each message.
    """
    azimuth = options.get('azimuth_joint', DEFAULT_AZIMUTH_JOINT)
    joints = options.get('joint_names') or {
        role: tuple(f'blade_{k}' for k in range(1, blades + 1)) for role in BLADE_JOINT_ROLES}
    for role in ('blade_flap', 'blade_pitch'):
        if azimuth in joints[role]:
            parser.fail(f'joint_names.azimuth {azimuth!r} is also the {role} joint of blade '
                        f'{joints[role].index(azimuth) + 1}: the azimuth joint is the rotor '
                        "shaft's, on the azimuth topic; give it a name no blade has",
                        'joint_names', 'azimuth')
    seen = {}
    given = parser.data.get('topics') or {}
    for role, topic in topics.items():
        if topic is None:
            continue
        key = topic.lstrip('/')
        if key in seen:
            parser.fail(f'topics.{role} and topics.{seen[key]} are both {topic!r}: every role '
                        'needs its own topic (a node reads one joint per blade, or the '
                        "azimuth's, from each message, and commands must not reach a sensor "
                        'topic)', 'topics', role if role in given else seen[key])
        seen[key] = role


def _check_wake_gain(parser, rotor, unknowns, known, data):
    # The wake model's A is γB⁴/8 (Ch.2 eq. 27): γ and A are one parameter, given once.
    where = ('lock_number',) if 'lock_number' in data else ('known',)
    if 'gamma' in unknowns and 'A' in unknowns:
        parser.fail('unknowns has both A and gamma, but A = γB⁴/8 in the wake model; identify '
                    'one of them', 'unknowns')
    if 'gamma' in known and 'A' in unknowns:
        parser.fail('A is unknown but fixed by the known γ (A = γB⁴/8 in the wake model); '
                    'remove A from unknowns or drop the known γ', *where)
    if 'A' in known and 'gamma' in unknowns:
        parser.fail('gamma is unknown but fixed by the known A (A = γB⁴/8 in the wake model); '
                    'remove gamma from unknowns or drop the known A', 'known')
    if 'gamma' in known and 'A' in known:
        implied = flap_damping(known['gamma'], rotor.tip_loss)
        if not math.isclose(known['A'], implied, rel_tol=1e-6):
            parser.fail(f'known A = {known["A"]} contradicts γ = {known["gamma"]} '
                        f'(A = γB⁴/8 = {implied:.6g}); give one of them', *where)


def validate_window(description: RunDescription, record: 'Record') -> None:
    """
    Check that the description's window lies inside the record.

    The ends may overshoot the record by up to one sample period (a window written as a time
    rounded up, as in the recordings, whose window ends 0.6 ms after the last 1 kHz sample).

    Parameters
    ----------
    description
        RunDescription.
    record
        Record read from the bag.

    Raises
    ------
    RunDescriptionError
        The window is not inside the record's span.

    """
    t0, t1 = description.window_s
    first, last = float(record.time_s[0]), float(record.time_s[-1])
    tolerance = record.sample_period_s if len(record) > 1 else 0.0
    if t0 < first - tolerance or t1 > last + tolerance:
        raise RunDescriptionError(
            f'{description.path}: window_s [{t0}, {t1}] s is outside the record, which spans '
            f'[{first:.6f}, {last:.6f}] s after the first flap stamp ({record.source}); '
            'shorten the window or check that the description belongs to this bag',
            description.path)


def check_against_record(description: RunDescription, record: 'Record') -> None:
    """
    Check a run description against the record read from its bag, before any fitting.

    The blade count ``rotor.blades`` must equal the number of blades whose joints the bag's
    flap topic carries (a 3-blade description of a 4-blade recording would otherwise be fitted
    with the wrong multiblade transform), and the window must lie inside the record
    (:func:`validate_window`).

    Parameters
    ----------
    description
        RunDescription.
    record
        Record read from the bag.

    Raises
    ------
    RunDescriptionError
        Naming the file and line of the key, what the bag holds and what to do.

    """
    blades = description.rotor.blades
    line = description.lines.get(('rotor', 'blades'))
    where = f'{description.path}:{line}' if line else description.path
    topic = description.topics['blade_flap']
    in_bag = getattr(record, 'bag_blade_count', None)       # every joint the bag carries
    if record.n_blades != blades:
        seen = ', '.join(record.blade_names)
        raise RunDescriptionError(
            f'{where}: rotor.blades = {blades}, but {topic} carries {record.n_blades} blade '
            f'joints ({seen}); set rotor.blades: {record.n_blades}, or name the joints of your '
            'blades in joint_names', description.path, line)
    if in_bag is not None and in_bag != blades:
        seen = ', '.join(record.flap_joints)
        message = (f'{where}: rotor.blades = {blades}, but {topic} carries {in_bag} joints '
                   f'({seen})')
        if description.joint_names is None:
            raise RunDescriptionError(f'{message}; set rotor.blades: {in_bag}',
                                      description.path, line)
        record.warnings.append(f'{message}; joint_names selects {blades} of them: check that '
                               'the others are not blades')
    validate_window(description, record)
