"""
Concealed-effect scenarios of the diagnosis study, shared by the tests and the benchmark.

Each scenario is a truth (a :class:`truth_generator.TruthConfig` built from a seed), the run
description's model and unknowns, the effect a correct diagnosis names (and the ids it may
name instead because they are the same physics at this size), and the truth of the extra and
of the original parameters. Effect sizes are set so that the baseline fit's residual RMS is at
most 10 % above the noise floor (measured by the study itself, column ``excess``).
"""

from dataclasses import dataclass, field, replace
import math

from truth_generator import generate, mu04_case, run_description_text, wake_case

WAKE = ('multiblade_wake', ('A', 'AL_over_tau', 'inv_tau'))
MULTIBLADE = ('multiblade', ('gamma', 'theta0'))
CONSTANT = ('multiblade_constant', ('gamma', 'theta0'))
OMEGA = 94.24777960769379
A_TRUE = 0.5
GAMMA_WAKE = 8.0 * A_TRUE / 0.97**4
THETA0 = math.radians(2.0)
WAKE_TRUTH = {'A': A_TRUE, 'AL_over_tau': 0.25, 'inv_tau': 0.125}


def _eq30_bias(b):
    """Return what the (β1−β3)/2, (β2−β4)/2 channels can see of per-blade biases b."""
    d13, d24 = (b[0] - b[2]) / 2, (b[1] - b[3]) / 2
    return {'bias_1': d13, 'bias_2': d24, 'bias_3': -d13, 'bias_4': -d24}


@dataclass
class Scenario:
    """One concealed effect (or none) at a fixed size."""

    name: str
    effect: str
    make: object                       # seed -> TruthConfig
    model: tuple
    accept: tuple = ()
    extra_truth: dict = field(default_factory=dict)
    original_truth: dict = field(default_factory=dict)
    #: several concealed effects: one group of accepted ids per effect (all must be named in
    #: ``explanation.effects``); empty for a single effect
    together: tuple = ()

    def config(self, seed):
        """Return the truth of one seed."""
        return self.make(seed)

    def record_and_description(self, seed):
        """(Record, RunDescription) of one seed."""
        from rotor_id.io.run_description import parse_run_description
        cfg = self.config(seed)
        text = run_description_text(cfg, self.model[0], self.model[1])
        return generate(cfg), parse_run_description(text)

    def accepted(self):
        """Effect ids counted as right."""
        return (self.effect,) + tuple(self.accept)


BIAS = [0.0004, -0.0002, 0.0, 0.0003]

SCENARIOS = [
    Scenario('none_wake', 'none', lambda s: wake_case(seed=s), WAKE,
             original_truth=WAKE_TRUTH),
    Scenario('none_multiblade', 'none', lambda s: wake_case(seed=s, wake=False), MULTIBLADE,
             original_truth={'gamma': GAMMA_WAKE, 'theta0': THETA0}),
    Scenario('none_mu04', 'none', lambda s: mu04_case(seed=s), ('multiblade', ('gamma', 'theta0')),
             original_truth={'gamma': 5.0, 'theta0': THETA0}),
    Scenario('dynamic_inflow', 'dynamic_inflow',
             lambda s: wake_case(seed=s, wake_L=0.85, wake_tau=0.6), MULTIBLADE,
             extra_truth={'A': A_TRUE, 'AL_over_tau': A_TRUE * 0.85 / 0.6,
                          'inv_tau': 1.0 / 0.6},
             original_truth={'gamma': GAMMA_WAKE, 'theta0': THETA0}),
    Scenario('periodic_coefficients', 'periodic_coefficients', lambda s: mu04_case(seed=s),
             CONSTANT, original_truth={'gamma': 5.0, 'theta0': THETA0}),
    Scenario('sensor_lag', 'sensor_lag', lambda s: wake_case(seed=s, sensor_lag=0.05), WAKE,
             accept=('time_delay',), extra_truth={'lag_rad': 0.05},
             original_truth=WAKE_TRUTH),
    Scenario('time_delay', 'time_delay',
             lambda s: wake_case(seed=s, time_delay_s=0.05 / OMEGA), WAKE,
             accept=('sensor_lag',), extra_truth={'delay_rad': 0.05},
             original_truth=WAKE_TRUTH),
    Scenario('sensor_bias', 'sensor_bias', lambda s: wake_case(seed=s, sensor_bias=BIAS), WAKE,
             extra_truth=_eq30_bias(BIAS), original_truth=WAKE_TRUTH),
    # The (β1−β3)/2, (β2−β4)/2 channels see blade j and blade j+2 alike (the mirror blade
    # with the opposite static offset s = (1+ε)Δθ + εθ0): evaluate() checks ε and ±s.
    Scenario('blade_lock_number', 'blade_dissimilarity',
             lambda s: wake_case(seed=s, gamma_scale=[1.0, 1.0, 1.06, 1.0]), WAKE,
             extra_truth={'dgamma_rel': 0.06, 'dtheta_static': 0.06 * THETA0, 'blade': 3.0},
             original_truth=WAKE_TRUTH),
    # At μ = 0 with a constant collective a pitch offset of one blade shifts that blade's trim
    # exactly as a flap-sensor bias would; only the wake's response to the offset's 1/rev
    # moment tells them apart, below the noise at this size: sensor_bias is accepted.
    Scenario('blade_pitch', 'blade_dissimilarity',
             lambda s: wake_case(seed=s, pitch_offset=[0.0, 0.002, 0.0, 0.0]), WAKE,
             accept=('sensor_bias',),
             extra_truth={'dgamma_rel': 0.0, 'dtheta_static': 0.002, 'blade': 2.0},
             original_truth=WAKE_TRUTH),
    # a cubic spring about the steady coning is a flap-frequency change to first order
    # (catalogue.EQUIVALENT): each accepts the other
    Scenario('flap_frequency', 'flap_frequency', lambda s: wake_case(seed=s, flap_freq_error=0.02),
             WAKE, accept=('cubic_stiffness',), extra_truth={'P': 1.22},
             original_truth=WAKE_TRUTH),
    Scenario('cubic_stiffness', 'cubic_stiffness',
             lambda s: wake_case(seed=s, cubic_stiffness=100.0), WAKE, accept=('flap_frequency',),
             extra_truth={'kappa': 100.0}, original_truth=WAKE_TRUTH),
    Scenario('process_noise', 'process_noise',
             lambda s: wake_case(seed=s, turbulence=0.0004, turbulence_corr=2.0), WAKE,
             original_truth=WAKE_TRUTH),
]

LAG = ('sensor_lag', 'time_delay', 'pitch_actuator_lag')
FREQ = ('flap_frequency', 'cubic_stiffness', 'pitch_flap_coupling')
#: The blade dissimilarity's static part is a sensor bias of that blade at μ = 0 (see
#: blade_pitch); its Lock-number part is what tells it apart.
BLADE = ('blade_dissimilarity',)
BIAS_IDS = ('sensor_bias',)
#: Pairs of effects a rig produces together, each at its single-effect size above.
PAIRS = [
    Scenario('lag+bias', 'sensor_lag',
             lambda s: wake_case(seed=s, sensor_lag=0.05, sensor_bias=BIAS), WAKE,
             together=(LAG, BIAS_IDS), original_truth=WAKE_TRUTH),
    Scenario('lag+blade', 'sensor_lag',
             lambda s: wake_case(seed=s, sensor_lag=0.05, gamma_scale=[1.0, 1.0, 1.06, 1.0]),
             WAKE, together=(LAG, BLADE), original_truth=WAKE_TRUTH),
    Scenario('lag+flap_frequency', 'sensor_lag',
             lambda s: wake_case(seed=s, sensor_lag=0.05, flap_freq_error=0.02), WAKE,
             together=(LAG, FREQ), original_truth=WAKE_TRUTH),
    Scenario('bias+blade', 'sensor_bias',
             lambda s: wake_case(seed=s, sensor_bias=BIAS, gamma_scale=[1.0, 1.0, 1.06, 1.0]),
             WAKE, together=(BIAS_IDS, BLADE), original_truth=WAKE_TRUTH),
    Scenario('bias+flap_frequency', 'sensor_bias',
             lambda s: wake_case(seed=s, sensor_bias=BIAS, flap_freq_error=0.02), WAKE,
             together=(BIAS_IDS, FREQ), original_truth=WAKE_TRUTH),
    Scenario('blade+flap_frequency', 'blade_dissimilarity',
             lambda s: wake_case(seed=s, gamma_scale=[1.0, 1.0, 1.06, 1.0], flap_freq_error=0.02),
             WAKE, together=(BLADE, FREQ), original_truth=WAKE_TRUTH),
    Scenario('inflow+bias', 'dynamic_inflow',
             lambda s: wake_case(seed=s, wake_L=0.85, wake_tau=0.6, sensor_bias=BIAS),
             MULTIBLADE, together=(('dynamic_inflow',), BIAS_IDS),
             original_truth={'gamma': GAMMA_WAKE, 'theta0': THETA0}),
    Scenario('inflow+lag', 'dynamic_inflow',
             lambda s: wake_case(seed=s, wake_L=0.85, wake_tau=0.6, sensor_lag=0.05),
             MULTIBLADE, together=(('dynamic_inflow',), LAG),
             original_truth={'gamma': GAMMA_WAKE, 'theta0': THETA0}),
]
GAIN = [0.035, -0.03, 0.0, 0.02]
#: Rig physics, alone and with another effect.
RIG = [
    # ΔP² = (γB⁴/8) K = 0.5 K: K = 0.1 is the flap_frequency scenario's 1.2 → 1.22
    Scenario('pitch_flap_coupling', 'pitch_flap_coupling',
             lambda s: wake_case(seed=s, pitch_flap_coupling=0.1), WAKE, accept=FREQ,
             extra_truth={'pitch_flap_coupling': 0.1}, original_truth=WAKE_TRUTH),
    Scenario('pitch_actuator_lag', 'pitch_actuator_lag',
             lambda s: wake_case(seed=s, actuator_lag=0.05), WAKE, accept=LAG,
             extra_truth={'actuator_lag_rad': 0.05}, original_truth=WAKE_TRUTH),
    Scenario('sensor_gain', 'sensor_gain', lambda s: wake_case(seed=s, sensor_gain=GAIN), WAKE,
             extra_truth={f'gain_{k + 1}': g for k, g in enumerate(GAIN)},
             original_truth=WAKE_TRUTH),
    Scenario('gain+lag', 'sensor_gain',
             lambda s: wake_case(seed=s, sensor_gain=GAIN, sensor_lag=0.05), WAKE,
             together=(('sensor_gain',), LAG), original_truth=WAKE_TRUTH),
    Scenario('actuator_lag+bias', 'pitch_actuator_lag',
             lambda s: wake_case(seed=s, actuator_lag=0.05, sensor_bias=BIAS), WAKE,
             together=(LAG + ('pitch_actuator_lag',), BIAS_IDS), original_truth=WAKE_TRUTH),
    Scenario('coupling+blade', 'pitch_flap_coupling',
             lambda s: wake_case(seed=s, pitch_flap_coupling=0.1,
                                 gamma_scale=[1.0, 1.0, 1.06, 1.0]), WAKE,
             together=(FREQ + ('pitch_flap_coupling',), BLADE), original_truth=WAKE_TRUTH),
    # the encoder's zero 0.03 rad (1.7°) off blade 1: in forward flight the periodic
    # aerodynamics run early in the recording's frame (baseline ~3 % above the floor)
    Scenario('azimuth_offset', 'azimuth_offset',
             lambda s: mu04_case(seed=s, azimuth_offset=0.03), MULTIBLADE,
             extra_truth={'azimuth_offset_rad': 0.03},
             original_truth={'gamma': 5.0, 'theta0': THETA0}),
    # at μ = 0 the rotor is axisymmetric: the same offset (and a ten times larger one) turns
    # flap and pitch alike, is invisible, and leaves the estimates unbiased: 'none' is right
    Scenario('azimuth_offset_hover', 'none',
             lambda s: wake_case(seed=s, azimuth_offset=0.3), WAKE, original_truth=WAKE_TRUTH),
]
SCENARIOS = SCENARIOS + PAIRS + RIG


def effect_classes():
    """
    Catalogue effects grouped by first-order equivalence, in catalogue order.

    Each group is one physics at the sizes a rig shows (catalogue.EQUIVALENT: a sensor lag, a
    time delay and a pitch-actuator lag; a flap-frequency change, a cubic spring and δ3); its
    first id stands for it. A pair inside one group is not two effects: it is excluded from
    the pair study.
    """
    from rotor_id.diagnosis.catalogue import EFFECTS, EQUIVALENT
    groups = []
    for effect in EFFECTS:
        if not any(effect in g for g in groups):
            groups.append((effect,) + tuple(e for e in EFFECTS
                                            if e in EQUIVALENT.get(effect, ())))
    return groups


#: The truth generator's knobs that conceal one effect group at its single-effect size above
#: (baseline residual RMS a few % above the floor); the periodic coefficients are the μ = 0.4
#: record itself (fitted with constant coefficients).
CONCEALED = {
    'dynamic_inflow': {'wake_L': 0.85, 'wake_tau': 0.6},
    'periodic_coefficients': {},
    'sensor_lag': {'sensor_lag': 0.05},
    'sensor_bias': {'sensor_bias': BIAS},
    'blade_dissimilarity': {'gamma_scale': [1.0, 1.0, 1.06, 1.0]},
    'process_noise': {'turbulence': 0.0004, 'turbulence_corr': 2.0},
    'flap_frequency': {'flap_freq_error': 0.02},
    'sensor_gain': {'sensor_gain': GAIN},
    'azimuth_offset': {'azimuth_offset': 0.03},
}
#: Effects seen only in forward flight: a pair with one is made in the μ = 0.4 record (an
#: azimuth offset turns flap and pitch alike in the axisymmetric hover: invisible there).
FORWARD_FLIGHT = ('periodic_coefficients', 'azimuth_offset')
#: The μ = 0.4 record (γ = 5, flap noise 0.1°, 12 rad before the stirring, no wake of its own)
#: shows an effect of a given size differently from the μ = 0 wake record: at the μ = 0 sizes
#: the single-effect baselines sit 2-11 % (a wake gain of 0.85: 228 %) above the floor.
#: Rule: an effect's μ = 0.4 size is its μ = 0 size times k = √(r₀ / r₀.₄), with
#: r = (1 + excess)² − 1 the residual power the effect adds over the noise power, which is
#: quadratic in a small effect's size; r₀ is its single-effect excess in the μ = 0 record
#: (diagnosis.md) and r₀.₄ that of the μ = 0 size in the μ = 0.4 record (mean of seeds 1000
#: and 1001, baseline fit only). Each effect then conceals as it does at μ = 0:
#:
#: effect          excess μ=0 | μ=0.4 at μ=0 size | k     | μ=0.4 size | excess there
#: inflow gain L   0.086      | 2.281             | 0.135 | 0.115      | 0.059
#: sensor lag      0.080      | 0.118             | 0.81  | 0.041      | 0.079
#: sensor bias     0.056      | 0.020             | 1.68  | BIAS·1.69  | 0.046
#: Lock number     0.068      | 0.060             | 1.07  | 1.06 kept  | 0.060
#: flap frequency  0.073      | 0.109             | 0.81  | +0.0163    | 0.078
#: sensor gain     0.080      | 0.104             | 0.87  | GAIN·0.873 | 0.082
#:
#: turbulence σ      0.033      | 0.019             | 1.31  | 5.2e-4     | 0.031
#:
#: The turbulence is random, so its excess varies from seed to seed (μ = 0: 0.008-0.067;
#: μ = 0.4: −0.008-0.042): both of its excesses are means of seeds 1000-1009, not of two
#: seeds. Its correlation time (2 rad) is kept: σ is its size. At its μ = 0 size the μ = 0.4
#: record hides it (excess 0.019).
#: The periodic terms are the record itself (excess 0.096) and the azimuth offset keeps the
#: size of its single-effect scenario (0.03 rad, excess 0.035): both are sized at μ = 0.4
#: already. A pair's excess is about the sum of its two (0.1-0.2).
MU04_SCALE = {'dynamic_inflow': 0.135, 'sensor_lag': 0.81, 'sensor_bias': 1.69,
              'flap_frequency': 0.81, 'sensor_gain': 0.873, 'process_noise': 1.31}
#: Knobs that shape an effect rather than size it: kept at μ = 0.4.
SHAPE_KNOBS = ('wake_tau', 'turbulence_corr')


def _scaled(value, k):
    return [round(v * k, 7) for v in value] if isinstance(value, list) else round(value * k, 7)


#: The knobs of :data:`CONCEALED` at their μ = 0.4 sizes (:data:`SHAPE_KNOBS` kept).
CONCEALED_MU04 = {
    effect: {knob: (_scaled(v, MU04_SCALE[effect])
                    if effect in MU04_SCALE and knob not in SHAPE_KNOBS else v)
             for knob, v in knobs.items()}
    for effect, knobs in CONCEALED.items()}
SHORT = {'dynamic_inflow': 'inflow', 'periodic_coefficients': 'periodic', 'sensor_lag': 'lag',
         'sensor_bias': 'bias', 'blade_dissimilarity': 'blade', 'process_noise': 'noise',
         'flap_frequency': 'flap_frequency', 'sensor_gain': 'gain',
         'azimuth_offset': 'azimuth'}


def _together_scenario(*groups):
    """
    Return a scenario with several effect groups concealed at once, each at its single size.

    In the μ = 0.4 record (when one of them is seen only in forward flight) each at its
    μ = 0.4 size (:data:`CONCEALED_MU04`).
    """
    firsts = [g[0] for g in groups]
    knobs = {k: v for a in firsts for k, v in CONCEALED[a].items()}
    if any(a in FORWARD_FLIGHT for a in firsts):
        from rotor_id.diagnosis.catalogue import equivalent
        knobs = {k: v for a in firsts for k, v in CONCEALED_MU04[a].items()}
        # in forward flight δ3, a cubic spring and a pitch-actuator lag are physics of their
        # own (catalogue.HOVER_ONLY): naming one for a flap-frequency error or a sensor lag
        # is right only with the truth reported as confounded with it
        groups = tuple((g[0],) + equivalent(g[0], 0.4) for g in groups)

        def make(seed):
            return mu04_case(seed=seed, wake='dynamic_inflow' in firsts, **knobs)
        model = CONSTANT if 'periodic_coefficients' in firsts else MULTIBLADE
        original = {'gamma': 5.0, 'theta0': THETA0}
    else:
        def make(seed):
            return wake_case(seed=seed, **knobs)
        model = MULTIBLADE if 'dynamic_inflow' in firsts else WAKE
        original = {'gamma': GAMMA_WAKE, 'theta0': THETA0} if model is MULTIBLADE \
            else WAKE_TRUTH
    return Scenario('+'.join(SHORT[a] for a in firsts), firsts[0], make, model,
                    together=tuple(groups), original_truth=original)


def catalogue_pairs():
    """
    Every pair of effect groups a rig can produce together, as scenarios.

    Pairs within one equivalence group are excluded (the same physics, see
    :func:`effect_classes`); a group the generator cannot conceal (no :data:`CONCEALED` knobs)
    is left out and listed by :func:`groups_without_generator`. A pair that already has a
    scenario above keeps it (and its name).
    """
    groups = [g for g in effect_classes() if g[0] in CONCEALED]
    have = {frozenset(s.name.split('+')): s for s in PAIRS + RIG if s.together}
    out = []
    for i, first in enumerate(groups):
        for second in groups[i + 1:]:
            key = frozenset((SHORT[first[0]], SHORT[second[0]]))
            out.append(have.get(key) or _together_scenario(first, second))
    return out


def groups_without_generator():
    """Effect groups of the catalogue the truth generator has no knob for."""
    return [g for g in effect_classes() if g[0] not in CONCEALED]


#: Random inflow alone in forward flight, at its μ = 0.4 size: the single effect beside which
#: the μ = 0.4 turbulence pairs are judged.
PROCESS_NOISE_MU04 = Scenario(
    'process_noise_mu04', 'process_noise',
    lambda s: mu04_case(seed=s, **CONCEALED_MU04['process_noise']),
    ('multiblade', ('gamma', 'theta0')), original_truth={'gamma': 5.0, 'theta0': THETA0})

PAIR_STUDY = catalogue_pairs()
SCENARIOS = SCENARIOS + [PROCESS_NOISE_MU04] + [s for s in PAIR_STUDY if s not in SCENARIOS]

#: Physics no catalogue candidate models: a once-per-rev flap stiffness
#: β_k″ += −K_1c cos ψ_k β_k at μ = 0 (multiblade model, all four coordinates). The honest
#: verdict is ``unexplained`` (or random inflow, the explanation of last resort) with a
#: proposal of the term ``beta*cos(psi)``, coefficient −K_1c. Not in the study's SCENARIOS: no
#: catalogue verdict is right for it.
K_1C = 0.1
D_1S = 0.1
OUT_OF_CATALOGUE = [
    Scenario('flap_stiffness_1c', 'unexplained',
             lambda s: wake_case(seed=s, wake=False, flap_stiffness_1c=K_1C), MULTIBLADE,
             accept=('process_noise',), extra_truth={'beta*cos(psi)': -K_1C},
             original_truth={'gamma': GAMMA_WAKE, 'theta0': THETA0}),
    # a once-per-rev flap damping, β_k″ += −D_1s sin ψ_k β_k′: the term beta_dot*sin(psi)
    Scenario('flap_damping_1s', 'unexplained',
             lambda s: wake_case(seed=s, wake=False, flap_damping_1s=D_1S), MULTIBLADE,
             accept=('process_noise',), extra_truth={'beta_dot*sin(psi)': -D_1S},
             original_truth={'gamma': GAMMA_WAKE, 'theta0': THETA0}),
]

#: noise+azimuth with the turbulence at its μ = 0 size (σ 4e-4 rad, which the μ = 0.4 record
#: hides: baseline excess 0.019 alone): random inflow is likely beside the offset but not
#: established. Not in the study; tests of how a doubtful verdict is worded use it.
WEAK_NOISE_AZIMUTH = replace(
    next(s for s in PAIR_STUDY if s.name == 'noise+azimuth'), name='weak_noise+azimuth',
    make=lambda s: mu04_case(seed=s, **CONCEALED['process_noise'],
                             **CONCEALED_MU04['azimuth_offset']))


def _triples():
    group = {g[0]: g for g in effect_classes()}
    return [_together_scenario(*(group[e] for e in effects)) for effects in (
        ('dynamic_inflow', 'sensor_lag', 'sensor_bias'),
        ('dynamic_inflow', 'blade_dissimilarity', 'process_noise'),
        ('sensor_lag', 'flap_frequency', 'sensor_gain'),
        ('sensor_lag', 'sensor_gain', 'azimuth_offset'))]


#: Three concealed effects at once, as the issue's rig would make them (a flap sensor with
#: an offset and a lag beside an unmodelled wake; a wake and a blade that differs under
#: turbulence; rig physics in hover and in forward flight). Not in the pair study nor in CI:
#: probes of the forward selection beyond two effects (bench/results/diagnosis_triples.md).
TRIPLES = _triples()

BY_NAME = {s.name: s for s in SCENARIOS + OUT_OF_CATALOGUE + [WEAK_NOISE_AZIMUTH] + TRIPLES}


def evaluate(scenario, result):
    """Check one diagnosis JSON against its scenario; return a dict of outcomes."""
    effect = result['explanation']['effect']
    fit = result['fit']
    out = {
        'scenario': scenario.name,
        'effect': effect,
        'confidence': result['explanation'].get('confidence'),
        'right': effect in scenario.accepted(),
        'excess': fit['baseline_rms'] / fit['noise_floor'] - 1.0,
        'augmented_excess': fit['augmented_rms'] / fit['noise_floor'] - 1.0,
        'within_3sigma': None,
        'original_within_3sigma': None,
        'original_bias_before': None,
        'original_bias_after': None,
    }
    named = [e['effect'] for e in result['explanation'].get('effects', [])]
    out['named'] = named
    # effects the diagnosis reports as indistinguishable from a named one in this record
    confounded = [c for e in result['explanation'].get('effects', [])
                  for c in e.get('confounded_with', [])]
    out['confounded'] = confounded
    if scenario.together:
        accepted = {a for group in scenario.together for a in group}
        out['right_named'] = all(any(a in named for a in group) for group in scenario.together)
        # two effects that are the same physics to first order in the record at
        # hand, said so and both named, is an honest answer, not a miss
        out['right'] = all(any(a in named + confounded for a in group)
                           for group in scenario.together)
    else:
        accepted = set(scenario.accepted())
    # effects named beyond the concealed ones: false alarms of the forward selection
    out['extra_names'] = [e for e in named if e not in accepted]
    if out['right'] and effect == scenario.effect and scenario.extra_truth:
        params = result['explanation']['parameters']
        z = []
        mirror = False
        if 'blade' in scenario.extra_truth and scenario.model[0] == 'multiblade_wake':
            named = params.get('blade', {}).get('value')
            mirror = named is not None and named != scenario.extra_truth['blade'] \
                and abs(named - scenario.extra_truth['blade']) == 2
        for name, truth in scenario.extra_truth.items():
            if name == 'blade':
                continue
            if mirror and name == 'dtheta_static':
                truth = -truth
            p = params.get(name)
            if p is None or not p['std'] > 0:
                z.append(math.inf)
                continue
            z.append(abs(p['value'] - truth) / p['std'])
        out['within_3sigma'] = bool(max(z) <= 3.0) if z else None
        out['extra_z'] = z
        if 'blade' in scenario.extra_truth:
            out['blade_right'] = params.get('blade', {}).get('value') == scenario.extra_truth[
                'blade'] or mirror
    if scenario.original_truth:
        before, after, inside = [], [], []
        for name, truth in scenario.original_truth.items():
            p = result['parameters'].get(name)
            if p is None:
                continue
            before.append(abs(p['baseline_value'] - truth) / p['baseline_std'])
            after.append(abs(p['value'] - truth) / p['std'])
            inside.append(after[-1] <= 3.0)
        out['original_bias_before'] = max(before) if before else None
        out['original_bias_after'] = max(after) if after else None
        out['original_within_3sigma'] = all(inside) if inside else None
    return out


def diagnosed(name, seed, workers=2, effects_figure=None):
    """Diagnose one seed of a scenario: (the diagnosis JSON, its evaluation)."""
    from rotor_id.diagnosis.diagnose import diagnose
    scenario = BY_NAME[name]
    record, description = scenario.record_and_description(seed)
    diagnosis = diagnose(record, description, workers=workers)
    if effects_figure is not None:
        from rotor_id.commands.diagnose_figures import plot_effects
        plot_effects(diagnosis, effects_figure)
    result = diagnosis.as_json()
    return result, evaluate(scenario, result)
