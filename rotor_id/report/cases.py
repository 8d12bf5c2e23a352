"""
The report's test cases and printed numbers, in one place (NASA CR-137965; docs/models.md).

Everything the report prints that we reproduce is data in this module, with the report location
and the docs/models.md section that explains how it was obtained:

* :data:`SCENARIOS`: the three simulated test configurations (truth model, stirring, noise σ).
* :data:`MATRIX_CASES`: every printed M⁻¹ (R = I) of Ch.2, and Ch.3 Table 1's nine rows
  (R = 0.04, diagonal only).
* :data:`ITERATION_CASES`: the iteration tables (report starting values and printed iterates).
* :data:`SUMMARY_ROWS`: the Ch.2 summary table (iterations, estimates, variances, CPU time).
* :data:`INITIAL_STATES`: the report's initial states (state at t0 of the truth run, and the
  equilibria of the wake case).

All report cases use the report's units: angles in degrees, parameters (γ, δ = γθ0) for models
1-2 (``angle_unit='deg'``, ``collective='delta'``) and (A, AL/τ, 1/τ) for model 3. Time is the
nondimensional azimuth t; samples are t0 + 0.1·j, end points included (docs/models.md §0.1).
"""

from dataclasses import dataclass, field

import numpy as np

from rotor_id.estimation.output_error import Experiment
from rotor_id.estimation.simulate import simulate
from rotor_id.physics.models import build_model, RotorConstants
from rotor_id.physics.stirring import PROGRESSING_OMEGADOT, StirringSchedule

#: Sampling interval Δt of every report case (docs/models.md §0.1 and §4).
SAMPLE_INTERVAL = 0.1
#: Record length t_f − t0 of the Ch.2 cases (two revolutions).
RECORD_LENGTH = 12.0


#: The models and noise-free truth runs of the scenarios, once per process: a Monte Carlo
#: draws a thousand noisy records of one scenario, and rebuilding both for every draw was
#: three quarters of its CPU time (bench/monte_carlo_speed.py).
_BUILT = {}
_TRUTH = {}


@dataclass(frozen=True)
class Scenario:
    """
    A simulated test of the report: which rotor, which truth, which stirring, which noise.

    Attributes
    ----------
    name : str
    model : str
        Identification model (``build_model`` name).
    truth_model : str
        Model that makes the data: the periodic multiblade model for the constant-coefficient
        identification (modelling error, docs/models.md §2.2), else the identification model.
    advance_ratio : float
    t0 : float
        Stirring start = identification start.
    omegadot : float
        ω̇ of the stirring law (negative: progressing).
    truth : dict
        True parameter values (report units).
    truth_start : str
        'rest' (from zero state at t = 0 with collective and lateral cyclic switched on,
        docs/models.md §1.1, §2.1) or 'equilibrium' (steady state before stirring, §3.3).
    noise_std : float
        Measurement σ of the report's noisy runs (deg).
    source : str

    """

    name: str
    model: str
    truth_model: str
    advance_ratio: float
    t0: float
    omegadot: float
    truth: dict
    truth_start: str
    noise_std: float
    source: str

    def rotor(self):
        """RotorConstants: 4 blades, P = 1.2, B = 0.97 (docs/models.md §0)."""
        return RotorConstants(n_blades=4, advance_ratio=self.advance_ratio,
                              flap_frequency=1.2, tip_loss=0.97)

    def build(self, which='model'):
        """Return the identification model (``which='model'``) or the truth model, in degrees."""
        name = self.model if which == 'model' else self.truth_model
        key = (name, self.advance_ratio)
        if key not in _BUILT:
            _BUILT[key] = build_model(name, self.rotor(), collective='delta', angle_unit='deg')
        return _BUILT[key]

    def stirring(self):
        """Pitch input: θ0 = 2°, 1.5° lateral cyclic stepped at t = 0, stirring from t0."""
        return StirringSchedule(collective=2.0, amplitude=1.5, omegadot=self.omegadot,
                                t0=self.t0, t_step=0.0)

    def truth_vector(self, which='model'):
        """Full parameter vector of the truth for the identification or the truth model."""
        return self.build(which).parameter_vector(self.truth)


def sample_times(t0, t_end, dt=SAMPLE_INTERVAL):
    """t0, t0 + Δt, …, t_end (both ends included), rounded so windows line up exactly."""
    n = int(round((t_end - t0) / dt))
    return np.round(t0 + dt * np.arange(n + 1), 10)


def truth_state(scenario, t):
    """Truth-model states at sample times ``t`` (all ≥ t0); shape (T, n_truth)."""
    t = np.asarray(t, dtype=float)
    key = (scenario.truth_model, scenario.advance_ratio, scenario.t0, scenario.omegadot,
           tuple(sorted(scenario.truth.items())), scenario.truth_start, t.tobytes())
    if key not in _TRUTH:
        if len(_TRUTH) >= 64:
            _TRUTH.clear()
        _TRUTH[key] = _truth_state(scenario, t)
    return _TRUTH[key].copy()


def _truth_state(scenario, t):
    model = scenario.build('truth')
    p = scenario.truth_vector('truth')
    inputs = scenario.stirring()
    t = np.asarray(t, dtype=float)
    if scenario.truth_start == 'rest':
        grid = sample_times(0.0, float(t[-1]))
        sim = simulate(model, p, inputs, grid, np.zeros(model.n_states))
        idx = np.searchsorted(grid, t - 1e-9)
        return sim.x[idx]
    x0 = model.equilibrium(t[:1], p, inputs(t[:1]))
    return simulate(model, p, inputs, t, x0).x


def truth_outputs(scenario, t):
    """
    Noise-free measurements in the identification model's channels at ``t``, shape (T, m).

    For the constant-coefficient multiblade model these are β0, βI, βII of the periodic truth.
    """
    x = truth_state(scenario, t)
    model = scenario.build('model')
    if scenario.truth_model == scenario.model:
        H = model.output_matrix(t)
        return np.einsum('tij,tj->ti', H, x)
    return x[:, :model.n_outputs]


def truth_initial_state(scenario):
    """Identification-model state at t0 of the truth run (the report's 'correct' ICs)."""
    x = truth_state(scenario, np.array([scenario.t0]))[0]
    if scenario.truth_model == scenario.model:
        return x
    # periodic truth [β0 βI βII βd, rates] -> constant model [β0 βI βII, rates]
    return np.concatenate([x[:3], x[4:7]])


def noisy_outputs(scenario, t, seed, noise_std=None):
    """Truth outputs plus white Gaussian noise (σ of the scenario unless given), seeded."""
    y = truth_outputs(scenario, t)
    sigma = scenario.noise_std if noise_std is None else noise_std
    return y + sigma * np.random.default_rng(seed).standard_normal(y.shape)


def make_experiment(scenario, t_end=None, y=None, initial_state='truth', x0_guess=None,
                    name=None):
    """
    Experiment of the report over t0 … t_end (default t0 + 12).

    ``initial_state`` is an Experiment mode, or 'truth' (fixed at the truth's state at t0).
    """
    t_end = scenario.t0 + RECORD_LENGTH if t_end is None else t_end
    t = sample_times(scenario.t0, t_end)
    mode = truth_initial_state(scenario) if isinstance(initial_state, str) and \
        initial_state == 'truth' else initial_state
    return Experiment(scenario.build('model'), scenario.stirring(), t, y, initial_state=mode,
                      x0_guess=x0_guess, name=name or scenario.name)


SCENARIOS = {
    'single_blade': Scenario(
        name='single_blade', model='single_blade', truth_model='single_blade',
        advance_ratio=0.4, t0=12.0, omegadot=PROGRESSING_OMEGADOT,
        truth={'gamma': 5.0, 'delta': 10.0}, truth_start='rest', noise_std=0.2,
        source='Ch.2 single-blade ML, Ch.3; docs/models.md §1'),
    'multiblade_periodic': Scenario(
        name='multiblade_periodic', model='multiblade', truth_model='multiblade',
        advance_ratio=0.4, t0=12.0, omegadot=PROGRESSING_OMEGADOT,
        truth={'gamma': 5.0, 'delta': 10.0}, truth_start='rest', noise_std=0.2,
        source='Ch.2 multiblade truth (periodic); docs/models.md §2.1'),
    'multiblade_constant': Scenario(
        name='multiblade_constant', model='multiblade_constant', truth_model='multiblade',
        advance_ratio=0.4, t0=12.0, omegadot=PROGRESSING_OMEGADOT,
        truth={'gamma': 5.0, 'delta': 10.0}, truth_start='rest', noise_std=0.2,
        source='Ch.2 multiblade ML (constant-coefficient model); docs/models.md §2.2-2.3'),
    'wake_progressing': Scenario(
        name='wake_progressing', model='multiblade_wake', truth_model='multiblade_wake',
        advance_ratio=0.0, t0=70.0, omegadot=PROGRESSING_OMEGADOT,
        truth={'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}, truth_start='equilibrium',
        noise_std=0.1, source='Ch.2 dynamic wake, progressing; docs/models.md §3'),
    'wake_regressing': Scenario(
        name='wake_regressing', model='multiblade_wake', truth_model='multiblade_wake',
        advance_ratio=0.0, t0=70.0, omegadot=-PROGRESSING_OMEGADOT,
        truth={'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}, truth_start='equilibrium',
        noise_std=0.1, source='Ch.2 dynamic wake, regressing; docs/models.md §3'),
}

SB = ('gamma', 'delta')
WAKE = ('A', 'AL_over_tau', 'inv_tau')
#: the report's 7-parameter wake start: A = .4, L = 2, τ = 12 (docs/models.md §3.3)
WAKE_START_7 = {'A': 0.4, 'AL_over_tau': 0.4 * 2.0 / 12.0, 'inv_tau': 1.0 / 12.0}


@dataclass(frozen=True)
class MatrixCase:
    """
    One M⁻¹ printed in the report, and how to evaluate ours.

    Attributes
    ----------
    name : str
        Stable key (JSON).
    title : str
    source : str
        Report location and docs/models.md section.
    scenario : str
    unknowns : tuple of str
    evaluated_at : dict
        Parameter values at which the report's M⁻¹ was evaluated (docs/models.md §0.1).
    initial_state : str or tuple
        'truth' (fixed, the truth's state at t0), 'zero', 'estimate', 'positions'.
    x0 : tuple, optional
        Identification-model state at t0 at which free initial states are evaluated.
    report : tuple of tuples
        The printed matrix (for ``kind='table1'`` the 2x2 diagonal matrix [[γ, 0], [0, δ]]).
    kind : str
        'full' (printed block of M⁻¹, R = I), 'diagonal' (printed diagonal, R = I) or
        'table1' (Ch.3 Table 1 row: diagonal, R = σ² = 0.04, printed with 1-2 digits).
    block : tuple of str
        θ names of the printed block (the rest of θ is inverted but not printed).
    t_end : float
    note : str

    """

    name: str
    title: str
    source: str
    scenario: str
    unknowns: tuple
    evaluated_at: dict
    initial_state: object
    report: tuple
    kind: str = 'full'
    block: tuple = ()
    x0: tuple = None
    t_end: float = None
    noise_std: float = 1.0
    note: str = ''


def _wake_x0(beta_i, beta_ii, lambda_i, lambda_ii):
    return (beta_i, 0.0, beta_ii, 0.0, lambda_i, lambda_ii)


def _table1(window, iteration, at, report):
    t_end = 12.0 + window
    return MatrixCase(
        name=f'table1_12_{int(t_end)}_iter{iteration}',
        title=f'Ch.3 Table 1, data t = 12-{int(t_end)}, iteration {iteration}',
        source='Ch.3 Table 1; docs/models.md §1.4', scenario='single_blade', unknowns=SB,
        evaluated_at={'gamma': at[0], 'delta': at[1]}, initial_state='truth',
        report=((report[0], 0.0), (0.0, report[1])), kind='table1', block=SB, t_end=t_end,
        noise_std=0.2,
        note='evaluated at the estimate of the previous row; printed values look truncated')


MATRIX_CASES = (
    MatrixCase(
        name='single_blade_2par', title='Single blade, correct initial conditions',
        source='Ch.2 p.23 (single blade ML); docs/models.md §1.4', scenario='single_blade',
        unknowns=SB, evaluated_at={'gamma': 4.91, 'delta': 9.82}, initial_state='truth',
        report=((0.211, -0.036), (-0.036, 0.365)), block=SB),
    MatrixCase(
        name='single_blade_4par', title='Single blade, identified initial conditions',
        source='Ch.2 p.23; docs/models.md §1.4', scenario='single_blade', unknowns=SB,
        evaluated_at={'gamma': 4.90, 'delta': 9.85}, initial_state='estimate', x0=(-0.89, 1.01),
        report=((0.230, -0.059, -0.048, 0.023), (-0.059, 0.405, 0.058, 0.022),
                (-0.048, 0.058, 0.130, -0.066), (0.023, 0.022, -0.066, 0.228)),
        block=SB + ('beta(t0)', 'beta_dot(t0)')),
    MatrixCase(
        name='multiblade_a', title='Multiblade (a), correct initial states',
        source='Ch.2 p.25; docs/models.md §2.3-2.4', scenario='multiblade_constant', unknowns=SB,
        evaluated_at={'gamma': 5.0, 'delta': 10.0},
        initial_state=(0.880, -0.983, 1.698, 0.038, 0.034, 0.03),
        report=((0.125, 0.003), (0.003, 0.269)), block=SB,
        note='reproduced at the true parameters, not at the printed 3rd iterate (4.99, 9.65) '
             '(docs/models.md §2.4, unresolved)'),
    MatrixCase(
        name='multiblade_b', title='Multiblade (b), zero initial states',
        source='Ch.2 p.25; docs/models.md §2.3', scenario='multiblade_constant', unknowns=SB,
        evaluated_at={'gamma': 4.92, 'delta': 10.26}, initial_state='zero',
        report=((0.151, 0.043), (0.043, 0.278)), block=SB),
    MatrixCase(
        name='multiblade_c', title='Multiblade (c), identified deflections, zero rates',
        source='Ch.2 p.26; docs/models.md §2.3', scenario='multiblade_constant', unknowns=SB,
        evaluated_at={'gamma': 5.00, 'delta': 9.98}, initial_state='positions',
        x0=(0.920, -0.984, 1.730, 0.0, 0.0, 0.0),
        report=((0.133, -0.006), (-0.006, 0.304)), block=SB,
        note='printed non-symmetric ([.006] below the diagonal): read as −.006 '
             '(docs/models.md §5.6)'),
    MatrixCase(
        name='wake_progressing', title='Dynamic wake, progressing stirring',
        source='Ch.2 p.34; docs/models.md §3.3', scenario='wake_progressing', unknowns=WAKE,
        evaluated_at={'A': 0.487, 'AL_over_tau': 0.255, 'inv_tau': 0.128},
        initial_state='truth',
        report=((0.052, 0.059, 0.013), (0.059, 0.094, 0.023), (0.013, 0.023, 0.010)),
        block=WAKE),
    MatrixCase(
        name='wake_regressing', title='Dynamic wake, regressing stirring',
        source='Ch.2 p.35; docs/models.md §3.3', scenario='wake_regressing', unknowns=WAKE,
        evaluated_at={'A': 0.536, 'AL_over_tau': 0.264, 'inv_tau': 0.139},
        initial_state='truth',
        report=((0.167, 0.179, 0.029), (0.179, 0.256, 0.045), (0.029, 0.045, 0.013)),
        block=WAKE),
    MatrixCase(
        name='wake_7par', title='Dynamic wake, 7 parameters (diagonal), progressing',
        source='Ch.2 p.36; docs/models.md §3.3', scenario='wake_progressing', unknowns=WAKE,
        evaluated_at={'A': 0.474, 'AL_over_tau': 0.236, 'inv_tau': 0.120},
        initial_state='positions', x0=_wake_x0(0.497, 0.211, -0.871, -0.327),
        report=tuple(tuple(v if i == j else 0.0 for j in range(7)) for i, v in enumerate(
            (0.121, 0.184, 0.055, 0.088, 0.095, 1.069, 0.796))),
        kind='diagonal',
        block=WAKE + ('beta_I(t0)', 'beta_II(t0)', 'lambda_I(t0)', 'lambda_II(t0)')),
    _table1(2.0, 1, (4.00, 8.00), (48.0, 6.5)),
    _table1(2.0, 2, (4.29, 9.73), (37.0, 8.1)),
    _table1(2.0, 3, (4.17, 9.71), (37.0, 8.0)),
    _table1(6.0, 1, (4.00, 8.00), (0.096, 0.032)),
    _table1(6.0, 2, (5.36, 9.67), (0.100, 0.035)),
    _table1(6.0, 3, (5.23, 9.73), (0.094, 0.035)),
    _table1(12.0, 1, (4.00, 8.00), (0.007, 0.013)),
    _table1(12.0, 2, (4.94, 9.69), (0.008, 0.015)),
    _table1(12.0, 3, (4.91, 9.85), (0.008, 0.015)),
)

#: Decimal places the report prints in Ch.3 Table 1 (by record end): 12-14 as integers / one
#: decimal, the others to three decimals.
TABLE1_DECIMALS = {14.0: (0, 1), 18.0: (3, 3), 24.0: (3, 3)}


@dataclass(frozen=True)
class IterationCase:
    """
    An iteration table of the report: start, printed iterates and what converges where.

    Attributes
    ----------
    name, title, source, scenario : str
    unknowns : tuple of str
    start : dict
        The report's initial parameter estimates.
    initial_state : str or tuple
        'truth', 'zero', 'estimate', 'positions' (see :class:`MatrixCase`).
    x0_start : tuple, optional
        Initial estimate of the state at t0 when initial states are free; 'equilibrium'
        means the equilibrium at the starting parameters (wake 7-parameter case).
    columns : tuple of str
        θ names of the printed columns.
    report : tuple of tuples
        Printed iterates, one row per iteration.
    t_end : float, optional
    noise_free_limit : tuple, optional
        Where noise-free Gauss-Newton converges when that is not the truth (modelling-error
        bias, docs/models.md §2.3), in the order of ``columns``.

    """

    name: str
    title: str
    source: str
    scenario: str
    unknowns: tuple
    start: dict
    initial_state: object
    columns: tuple
    report: tuple
    x0_start: object = None
    t_end: float = None
    noise_free_limit: tuple = None


ITERATION_CASES = (
    IterationCase(
        name='single_blade_2par', title='Single blade, correct initial conditions',
        source='Ch.2 p.23; docs/models.md §1.4', scenario='single_blade', unknowns=SB,
        start={'gamma': 4.0, 'delta': 8.0}, initial_state='truth', columns=SB,
        report=((4.94, 9.70), (4.91, 9.82), (4.91, 9.82))),
    IterationCase(
        name='single_blade_4par', title='Single blade, identified initial conditions',
        source='Ch.2 p.23; docs/models.md §1.4', scenario='single_blade', unknowns=SB,
        start={'gamma': 4.0, 'delta': 8.0}, initial_state='estimate', x0_start=(-0.75, 1.2),
        columns=SB + ('beta(t0)', 'beta_dot(t0)'),
        report=((4.96, 9.68, -0.89, 1.02), (4.90, 9.85, -0.89, 1.01),
                (4.90, 9.85, -0.89, 1.01))),
    IterationCase(
        name='multiblade_periodic', title='Multiblade, periodic model (convergence check)',
        source='docs/models.md §2.1 (not in the report: the model of the truth)',
        scenario='multiblade_periodic', unknowns=SB, start={'gamma': 2.5, 'delta': 5.0},
        initial_state='truth', columns=SB, report=()),
    IterationCase(
        name='multiblade_a', title='Multiblade (a), correct initial states',
        source='Ch.2 p.25; docs/models.md §2.3', scenario='multiblade_constant', unknowns=SB,
        start={'gamma': 2.5, 'delta': 5.0},
        initial_state=(0.880, -0.983, 1.698, 0.038, 0.034, 0.03), columns=SB,
        report=((4.97, 8.46), (5.00, 9.62), (4.99, 9.65)), noise_free_limit=(4.941, 10.095)),
    IterationCase(
        name='multiblade_b', title='Multiblade (b), zero initial states',
        source='Ch.2 p.25; docs/models.md §2.3', scenario='multiblade_constant', unknowns=SB,
        start={'gamma': 2.5, 'delta': 5.0}, initial_state='zero', columns=SB,
        report=((5.68, 9.45), (4.87, 10.27), (4.92, 10.26)), noise_free_limit=(4.855, 10.374)),
    IterationCase(
        name='multiblade_c', title='Multiblade (c), identified deflections, zero rates',
        source='Ch.2 p.26; docs/models.md §2.3', scenario='multiblade_constant', unknowns=SB,
        start={'gamma': 2.5, 'delta': 5.0}, initial_state='positions',
        x0_start=(1.0, -1.0, 2.0, 0.0, 0.0, 0.0),
        columns=SB + ('beta_0(t0)', 'beta_I(t0)', 'beta_II(t0)'),
        report=((4.94, 8.25, 0.979, -1.039, 1.826), (5.01, 9.97, 0.920, -0.985, 1.732),
                (5.00, 9.98, 0.920, -0.984, 1.730)),
        noise_free_limit=(4.936, 10.113, 0.898, -0.977, 1.708)),
    IterationCase(
        name='wake_progressing', title='Dynamic wake, progressing stirring',
        source='Ch.2 p.34; docs/models.md §3.3', scenario='wake_progressing', unknowns=WAKE,
        start={'A': 0.4, 'AL_over_tau': 0.2, 'inv_tau': 0.25}, initial_state='truth',
        columns=WAKE,
        report=((0.500, 0.290, 0.086), (0.485, 0.253, 0.125), (0.487, 0.255, 0.128),
                (0.487, 0.255, 0.128))),
    IterationCase(
        name='wake_regressing', title='Dynamic wake, regressing stirring',
        source='Ch.2 p.35; docs/models.md §3.3', scenario='wake_regressing', unknowns=WAKE,
        start={'A': 0.4, 'AL_over_tau': 0.2, 'inv_tau': 0.25}, initial_state='truth',
        columns=WAKE,
        report=((0.524, 0.252, 0.087), (0.540, 0.264, 0.134), (0.536, 0.264, 0.139),
                (0.536, 0.264, 0.139))),
    IterationCase(
        name='wake_7par', title='Dynamic wake, 7 parameters, progressing',
        source='Ch.2 p.36; docs/models.md §3.3', scenario='wake_progressing', unknowns=WAKE,
        start=WAKE_START_7, initial_state='positions', x0_start='equilibrium',
        columns=WAKE + ('beta_I(t0)', 'beta_II(t0)', 'lambda_I(t0)', 'lambda_II(t0)'),
        report=((0.443, 0.184, 0.150, 0.500, 0.211, -0.864, -0.309),
                (0.471, 0.233, 0.115, 0.497, 0.210, -0.859, -0.322),
                (0.474, 0.235, 0.119, 0.497, 0.211, -0.870, -0.327),
                (0.474, 0.236, 0.120, 0.497, 0.211, -0.871, -0.327))),
    IterationCase(
        name='table1_12_14', title='Ch.3 Table 1, data t = 12-14', source='Ch.3 Table 1',
        scenario='single_blade', unknowns=SB, start={'gamma': 4.0, 'delta': 8.0},
        initial_state='truth', columns=SB, t_end=14.0,
        report=((4.29, 9.73), (4.17, 9.71), (4.10, 9.67))),
    IterationCase(
        name='table1_12_18', title='Ch.3 Table 1, data t = 12-18', source='Ch.3 Table 1',
        scenario='single_blade', unknowns=SB, start={'gamma': 4.0, 'delta': 8.0},
        initial_state='truth', columns=SB, t_end=18.0,
        report=((5.36, 9.67), (5.23, 9.73), (5.23, 9.73))),
    IterationCase(
        name='table1_12_24', title='Ch.3 Table 1, data t = 12-24', source='Ch.3 Table 1',
        scenario='single_blade', unknowns=SB, start={'gamma': 4.0, 'delta': 8.0},
        initial_state='truth', columns=SB, t_end=24.0,
        report=((4.94, 9.69), (4.91, 9.85), (4.91, 9.83))),
)


@dataclass(frozen=True)
class SummaryRow:
    """
    A row of the Ch.2 summary table (method comparison, σ = 0.2, variances = M⁻¹·0.04).

    ``iteration_case`` names the :data:`ITERATION_CASES` entry it corresponds to, or
    'equation_error' for the iterated equation-error row.
    """

    label: str
    iteration_case: str
    iterations: int
    gamma: float
    delta: float
    var_gamma: float
    var_delta: float
    cpu_s: float
    note: str = ''


SUMMARY_ROWS = (
    SummaryRow('Iterated equation error, single blade', 'equation_error', 3, 4.52, 10.09,
               0.073, 0.111, 4.8),
    SummaryRow('ML single blade, correct initial conditions', 'single_blade_2par', 2, 4.91,
               9.82, 0.0085, 0.0146, 5.2),
    SummaryRow('ML single blade, identified initial conditions', 'single_blade_4par', 2, 4.90,
               9.85, 0.0092, 0.0162, 8.6),
    SummaryRow('ML multiblade, zero initial values', 'multiblade_b', 2, 4.87, 10.27, 0.0060,
               0.0111, 8.0),
    SummaryRow('ML multiblade, zero rates, identified deflections', 'multiblade_c', 2, 5.01,
               9.97, 0.0053, 0.0210, 12.0,
               note='report var δ .0210 is a typo for .0122 = .304 × .04 (docs/models.md §5.5)'),
)


@dataclass(frozen=True)
class InitialStateCase:
    """
    Initial states printed in the report (to the printed digits).

    ``how`` is 'truth' (state at t0 of the truth run from rest at t = 0), 'equilibrium_true'
    or 'equilibrium_start' (wake steady state before stirring at the true / the 7-parameter
    starting parameters). ``exceptions`` maps a state name to why it is not reproduced.
    """

    name: str
    title: str
    source: str
    scenario: str
    how: str
    states: tuple
    report: tuple
    exceptions: dict = field(default_factory=dict)


INITIAL_STATES = (
    InitialStateCase(
        'single_blade_t12', 'Single blade at t = 12', 'Ch.2 p.23; docs/models.md §1.1',
        'single_blade', 'truth', ('beta', 'beta_dot'), (-0.921, 0.986)),
    InitialStateCase(
        'multiblade_t12', 'Multiblade (periodic truth) at t = 12',
        'Ch.2 p.24; docs/models.md §2.1',
        'multiblade_periodic', 'truth',
        ('beta_0', 'beta_I', 'beta_II', 'beta_d', 'beta_0_dot', 'beta_I_dot', 'beta_II_dot',
         'beta_d_dot'), (0.880, -0.983, 1.698, 0.060, 0.038, 0.034, 0.03, -0.030)),
    InitialStateCase(
        'wake_true_t70', 'Wake equilibrium at t = 70, true parameters',
        'Ch.2 p.36; docs/models.md §3.3', 'wake_progressing', 'equilibrium_true',
        ('beta_I', 'beta_II', 'lambda_I', 'lambda_II'), (0.497, 0.188, -0.874, -0.331)),
    InitialStateCase(
        'wake_start_t70', 'Wake equilibrium at t = 70, starting parameters (.4, .0667, .0833)',
        'Ch.2 p.36; docs/models.md §3.3', 'wake_progressing', 'equilibrium_start',
        ('beta_I', 'beta_II', 'lambda_I', 'lambda_II'), (0.601, 0.305, -0.531, -0.268),
        exceptions={'beta_I': 'report .601, stated procedure gives .6036 (docs/models.md §5.9)'}),
)


def report_units_note():
    """One line on units for printed tables."""
    return ('angles in degrees, t in rad of azimuth (2π per revolution), '
            f'Δt = {SAMPLE_INTERVAL}, R = I unless stated')


def wake_equilibrium(scenario, values):
    """Wake-model steady state before stirring (θII = 1.5°) at parameters ``values``."""
    model = scenario.build('model')
    p = model.parameter_vector(values)
    t = np.array([scenario.t0])
    return model.equilibrium(t, p, scenario.stirring()(t))


#: Rotor speed the report-case run descriptions (config/report_*.yaml) assume: 15 rev/s.
REPORT_OMEGA_RAD_S = 2.0 * np.pi * 15.0


def report_record(scenario_name, t_end=None, dt=SAMPLE_INTERVAL, omega_rad_s=REPORT_OMEGA_RAD_S,
                  blade_noise_std_deg=0.0, seed=None):
    """
    Return a test-stand record (radians, seconds) of a report scenario, t = 0 … ``t_end``.

    The per-blade flap of the truth: at μ = 0.4 the periodic multiblade model measured on each
    blade (from rest at t = 0); at μ = 0 the wake model's tilt modes in equilibrium until t0,
    β_k = βI cos ψ_k + βII sin ψ_k. Pitch is the stirring schedule on each blade. Samples are
    ``dt`` apart in azimuth at constant rotor speed, the first at t = 0 (time_s = t/Ω), so the
    windows of config/report_*.yaml select t0 … t0 + 12. Optional white per-blade flap noise
    (deg, seeded) is added before the conversion to radians.
    """
    from rotor_id.io.record import Record
    from rotor_id.physics.multiblade import blade_azimuths

    scenario = SCENARIOS[scenario_name]
    t_end = scenario.t0 + RECORD_LENGTH if t_end is None else t_end
    t = sample_times(0.0, t_end, dt)
    stirring = scenario.stirring()
    if scenario.advance_ratio > 0:
        model = build_model('multiblade', scenario.rotor(), collective='delta',
                            angle_unit='deg', outputs='blades')
        p = model.parameter_vector(scenario.truth)
        flap = simulate(model, p, stirring, t, np.zeros(model.n_states)).y
    else:
        model = scenario.build('model')
        p = scenario.truth_vector()
        x0 = model.equilibrium(t[:1], p, stirring(t[:1]))
        x = simulate(model, p, stirring, t, x0).x
        psi = blade_azimuths(t, 4)
        flap = x[:, [0]] * np.cos(psi) + x[:, [2]] * np.sin(psi)
    if blade_noise_std_deg:
        flap = flap + blade_noise_std_deg * np.random.default_rng(seed).standard_normal(
            flap.shape)
    deg = np.pi / 180.0
    return Record(time_s=t / omega_rad_s, t=t, rotor_speed_rad_s=np.full(t.size, omega_rad_s),
                  blade_flap=flap * deg, blade_pitch=stirring.blade_pitch(t) * deg,
                  blade_names=[f'blade_{k}' for k in range(1, 5)],
                  source=f'report scenario {scenario_name} (rotor_id.report.cases)')


@dataclass(frozen=True)
class GradientCase:
    """
    The Ch.2 eq. 22 gradient column of the single-blade ML table at the initial estimate.

    ∂J/∂Θ = Σ νᵀR⁻¹ ∂ν/∂Θ = −Σ νᵀR⁻¹ H S with R = I (docs/models.md §0.1 sign note), at (4, 8). The
    report's value comes from its noisy data; ours noise-free differs by the noise term, whose
    standard deviation σ·√diag(M) (M with R = I) is known, so the two can be compared.
    """

    name: str
    source: str
    scenario: str
    at: dict
    report: tuple


GRADIENT = GradientCase(
    name='single_blade_gradient_iter1', source='Ch.2 p.23 (∂J/∂γ, ∂J/∂δ); docs/models.md §1.4',
    scenario='single_blade', at={'gamma': 4.0, 'delta': 8.0}, report=(-6.11, -5.84))
