"""
Test planning (pins #8): what rotor_id.planning predicts, checked against identify and the report.

* The predicted Cramér-Rao σ agree with the spread of ``pipeline.identify`` on noisy simulated
  runs of the same candidate (report's wake and multiblade cases), judged with limits from the
  sampling distribution that a prediction wrong by 30 % cannot meet.
* The report's findings come out of the tool: progressing beats regressing stirring for the wake
  parameters (Ch.2), the single-blade M⁻¹(t_f) falls steeply until t ≈ 17.5 and again until
  t ≈ 23 (Ch.3 figs 2-3).
* The prediction is the information code of ``identify`` (estimation.information) on the
  pipeline's own experiments; shortest record and recommendation follow the stated rules.
"""

import math
from pathlib import Path
import time

import numpy as np
import pytest
from rotor_id import pipeline, planning
from rotor_id.estimation.information import cramer_rao_bound
from rotor_id.io.errors import RunDescriptionError
from scipy import stats

REPO = Path(__file__).resolve().parents[1]
WAKE = REPO / 'config' / 'plan_wake.yaml'
MULTIBLADE = REPO / 'config' / 'plan_multiblade.yaml'
REPORT_RECORD_REV = 12.0 / (2.0 * math.pi)       # the report's t0 … t0 + 12
SEEDS = 100                                      # the bench runs 200 (bench/plan_vs_monte_carlo)
LEVEL = 0.999                                    # two-sided probability of the accepted band


def _report_candidate(plan, direction='progressing'):
    sign = -1.0 if direction == 'progressing' else 1.0
    return planning.Candidate(direction, sign * abs(planning.PROGRESSING_OMEGADOT),
                              planning.DEFAULT_AMPLITUDE_RAD,
                              planning.default_t0(plan.description.rotor.advance_ratio),
                              REPORT_RECORD_REV)


def _single_blade_plan(gamma, theta0):
    text = MULTIBLADE.read_text().replace('model: multiblade ', 'model: single_blade ')
    text = text.replace('guess: {gamma: 5.0, theta0: 0.0349066}',
                        f'guess: {{gamma: {gamma}, theta0: {theta0}}}')
    return planning.parse_plan(text, 'single_blade_plan.yaml')


# ------------------------------------------------------------------------------------------------
# Prediction vs Monte Carlo spread of identify
# ------------------------------------------------------------------------------------------------

def _chi2_band(dof):
    """Band of χ²/dof holding with probability LEVEL when the prediction is right."""
    lo, hi = stats.chi2.ppf([(1 - LEVEL) / 2, (1 + LEVEL) / 2], dof)
    return lo / dof, hi / dof


def _prediction_passes(mc, scale=1.0):
    """Apply the test to a prediction scaled by ``scale`` in σ: (pooled ok, per-σ ok)."""
    d, dof = mc.pooled_statistic(scale)
    lo, hi = _chi2_band(dof)
    n = int(mc.converged.sum())
    r_lo, r_hi = (math.sqrt(b) for b in _chi2_band(n - 1))
    ratio = mc.ratio() / scale
    return lo <= d / dof <= hi, bool(np.all((ratio >= r_lo) & (ratio <= r_hi)))


@pytest.mark.parametrize('config', [WAKE, MULTIBLADE], ids=['wake', 'multiblade'])
def test_predicted_sigma_matches_identify_spread(config):
    """
    Spread of identify over 100 seeds vs the plan's σ.

    Pooled over the unknowns, D = Σ (θ̂ − θ̄)ᵀ C⁻¹ (θ̂ − θ̄) ~ χ²(k(N−1)) if the predicted
    covariance C is right: D/dof must lie in its 99.9 % band (about ±0.25 around 1 for
    k(N−1) = 200-300). Per unknown, spread/σ must lie in the 99.9 % band of χ²(N−1) (about
    0.79-1.23). The same checks applied to the prediction scaled by 1.3 and 1/1.3 must fail:
    a 30 % error in the predicted σ cannot pass.
    """
    plan = planning.load_plan(config)
    mc = planning.monte_carlo(plan, _report_candidate(plan), range(SEEDS))
    assert mc.converged.all(), f'{np.count_nonzero(~mc.converged)} runs did not converge'
    bias = (mc.estimates.mean(axis=0) - mc.truth) / mc.predicted_std
    assert np.all(np.abs(bias) < 4.0 / math.sqrt(SEEDS) + 0.1), f'biased estimates: {bias}'
    pooled, per_sigma = _prediction_passes(mc)
    d, dof = mc.pooled_statistic()
    assert pooled, f'pooled χ²/dof = {d / dof:.3f} outside {_chi2_band(dof)}'
    assert per_sigma, f'spread/σ = {mc.ratio()} (predicted σ {mc.predicted_std})'
    for wrong in (1.3, 1.0 / 1.3):
        assert _prediction_passes(mc, wrong) != (True, True), \
            f'a prediction wrong by a factor {wrong:.2f} would pass'


# ------------------------------------------------------------------------------------------------
# The report's findings, from the tool
# ------------------------------------------------------------------------------------------------

def test_progressing_beats_regressing_for_the_wake_parameters():
    """
    Ch.2 wake case: regressing stirring identifies the wake parameters worse.

    Regressing stirring crosses the regressing-mode resonance, where the wake effect vanishes
    (report M⁻¹ diagonals .052/.094/.010 progressing vs .167/.256/.013 regressing).

    With the report's known initial conditions the tool must find every σ larger for
    regressing stirring; with the initial states free (what a window-only identify faces) the
    joint uncertainty (det of the covariance of A, AL/τ, 1/τ) and σ of A and AL/τ must be
    larger for regressing stirring; and the plan file's recommendation must be progressing.
    """
    plan = planning.load_plan(WAKE)
    covs = {}
    for mode in ('known', None):
        for direction in planning.DIRECTIONS:
            pred = planning.predict_transient(plan, _report_candidate(plan, direction),
                                              initial_state=mode)
            covs[mode, direction] = pred.history.covariance[-1][:3, :3]
    ratio_known = np.sqrt(np.diag(covs['known', 'regressing'])
                          / np.diag(covs['known', 'progressing']))
    assert np.all(ratio_known > 1.05), ratio_known
    # the report's own ratios: √(.167/.052) = 1.79, √(.256/.094) = 1.65, √(.013/.010) = 1.14
    np.testing.assert_allclose(ratio_known, [1.79, 1.65, 1.14], rtol=0.12)
    free_p, free_r = covs[None, 'progressing'], covs[None, 'regressing']
    assert np.linalg.det(free_r) > 2.0 * np.linalg.det(free_p)
    assert np.all(np.diag(free_r)[:2] > np.diag(free_p)[:2])
    result = planning.evaluate_plan(plan)
    best = result.candidates[result.recommended]
    assert best.meets_target and best.candidate.direction == 'progressing'


def test_plan_file_can_assume_the_report_known_initial_state():
    """
    ``known_initial_state: true`` in PLAN.yaml plans with the report's correct initial conditions.

    The report's progressing and regressing candidates evaluated from the plan file then give
    the report's σ ratios (regressing / progressing, √ of its M⁻¹ diagonals: 1.79, 1.65, 1.14;
    measured 1.66, 1.63, 1.13 as in the test above); without the key the initial states are
    estimated and 1/τ is no longer worse regressing. The JSON says which.
    """
    text = WAKE.read_text().split('candidates:')[0] + (
        'candidates:\n'
        f'  direction: [progressing, regressing]\n'
        f'  omegadot: [{abs(planning.PROGRESSING_OMEGADOT)}]\n'
        f'  duration_rev: [{REPORT_RECORD_REV}]\n')
    sigma = {}
    for known in (True, False):
        plan = planning.parse_plan(text + f'known_initial_state: {str(known).lower()}\n')
        result = planning.evaluate_plan(plan)
        assert result.as_json()['initial_state'] == ('known' if known else 'estimate')
        sigma[known] = {c.candidate.direction: np.array([c.std[n] for n in plan.unknowns])
                        for c in result.candidates}
    ratio = sigma[True]['regressing'] / sigma[True]['progressing']
    np.testing.assert_allclose(ratio, [1.79, 1.65, 1.14], rtol=0.12)
    free = sigma[False]['regressing'] / sigma[False]['progressing']
    assert free[2] < 1.0 < free[0], free
    with pytest.raises(ValueError, match='known_initial_state'):
        planning.monte_carlo(plan_known := planning.parse_plan(
            text + 'known_initial_state: true\n'), plan_known.candidates[0], seeds=[0])


@pytest.mark.parametrize('direction, at, printed', [
    ('progressing', (0.487, 0.255, 0.128),
     ((0.052, 0.059, 0.013), (0.059, 0.094, 0.023), (0.013, 0.023, 0.010))),
    ('regressing', (0.536, 0.264, 0.139),
     ((0.167, 0.179, 0.029), (0.179, 0.256, 0.045), (0.029, 0.045, 0.013))),
])
def test_plan_reproduces_the_report_wake_information_matrices(direction, at, printed):
    """
    Ch.2 wake M⁻¹ (R = I, deg): the tool in the report's configuration gives the printed matrix.

    The report's noise was σ = 0.1° on each eq.-30 channel (β1 − β3)/2, i.e. 0.1°·√2 per blade;
    initial conditions known; M⁻¹ evaluated at the report's 4th-iteration estimates. Our
    samples (1 kHz at 15 rev/s: Δt = 0.094, window starting at the first sample after the
    stirring start) differ from the report's Δt = 0.1 by 2-3 % in M⁻¹; the printed 3 decimals
    of .010/.013 are ±4-5 %: 7 % tolerance.
    """
    text = WAKE.read_text().replace(
        'noise_std_rad: 0.0017453', f'noise_std_rad: {math.radians(0.1) * math.sqrt(2):.8f}')
    text = text.replace('guess: {A: 0.5, AL_over_tau: 0.25, inv_tau: 0.125}',
                        f'guess: {{A: {at[0]}, AL_over_tau: {at[1]}, inv_tau: {at[2]}}}')
    plan = planning.parse_plan(text)
    pred = planning.predict_transient(plan, _report_candidate(plan, direction),
                                      initial_state='known')
    assert pred.history.names == list(planning.load_plan(WAKE).unknowns)
    # A, AL/τ, 1/τ are dimensionless: M⁻¹ for R = I (deg²) is the covariance over (0.1°)²
    ours = pred.history.covariance[-1] / 0.1**2
    np.testing.assert_allclose(ours, printed, rtol=0.07)


@pytest.mark.parametrize('guess', [(4.0, math.radians(2.0)), (4.91, math.radians(9.83 / 4.91))],
                         ids=['initial_4_8', 'final_4.91_9.83'])
def test_single_blade_steep_descents_at_17_5_and_23(guess):
    """
    Ch.3 figs 2-3: "steep descent of the curves to about t = 17.5 … another descent to t = 23.0".

    The report's configuration: blade 1 measured, initial conditions known, stirring at t = 12
    (here 12 after the cyclic step), curves at the initial (4, 8) and final (4.91, 9.83)
    estimates. The descents are located from the tool's own M⁻¹(t_f) (steep_descents).
    """
    plan = _single_blade_plan(*guess)
    cand = planning.Candidate('progressing', planning.PROGRESSING_OMEGADOT,
                              planning.DEFAULT_AMPLITUDE_RAD, 12.0, 2.0)
    pred = planning.predict_transient(plan, cand, initial_state='known', blades=[1])
    t_report = pred.history.t - pred.stirring_start + 12.0
    for name in plan.unknowns:
        descents = planning.steep_descents(t_report, pred.history.variance(name))
        ends = [end for _, end, _ in descents]
        assert len(ends) == 2, f'{name}: descents {descents}'
        assert ends[0] == pytest.approx(17.5, abs=0.5), f'{name}: {descents}'
        assert ends[1] == pytest.approx(23.0, abs=0.5), f'{name}: {descents}'
        assert descents[1][2] > 1.25        # a real second drop, not a wiggle


def test_steep_descents_of_a_known_curve():
    """Two drops between plateaus: both ends found; a small wiggle and a short gap are not."""
    t = np.linspace(12.0, 24.0, 241)
    log_v = (-1.5 * np.clip(t - 12.0, 0, 5.5) - 0.8 * np.clip(t - 21.5, 0, 1.5)
             - 0.02 * (t - 12.0)
             - 0.15 * np.clip(t - 19.0, 0, 0.5)                 # a wiggle: M⁻¹ falls by 8 %
             + 0.05 * np.clip(t - 14.0, 0, 0.1) - 0.05 * np.clip(t - 14.1, 0, 0.1))
    descents = planning.steep_descents(t, np.exp(log_v), steep=-0.3)
    # the rate is averaged over ±window/2 = ±0.5: an end is located to within that
    assert [end for _, end, _ in descents] == pytest.approx([17.5, 23.0], abs=0.5)
    assert descents[0][2] == pytest.approx(math.exp(1.5 * 5.5), rel=0.2)
    assert descents[1][2] == pytest.approx(math.exp(0.8 * 1.5), rel=0.2)
    # by default "steep" is steeper than the curve's median descent rate
    assert len(planning.steep_descents(t, np.exp(log_v))) == 2


# ------------------------------------------------------------------------------------------------
# Same information code as identify; shortest record; recommendation
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize('which', ['wake', 'single_blade'])
def test_prediction_is_identify_s_information_on_the_pipeline_experiments(which):
    """The plan's M⁻¹ at the window end = cramer_rao_bound of identify's own experiments."""
    if which == 'wake':
        plan = planning.load_plan(WAKE)
    else:
        plan = _single_blade_plan(5.0, math.radians(2.0))
    cand = _report_candidate(plan)
    pred = planning.predict_transient(plan, cand)
    run = planning.simulate_run(plan, cand)
    description = planning.description_for(plan, cand)
    model = pipeline.model_for(description)
    experiments = pipeline.experiments_from_record(run.record, description, model)
    assert len(experiments) == (4 if which == 'single_blade' else 1)
    x0 = [states[np.searchsorted(run.record.t, exp.t[0])]
          for exp, states in zip(experiments, run.states)]
    bound = cramer_rao_bound(experiments, run.p_full, plan.unknowns,
                             noise_std=pipeline.channel_noise(model, plan.noise_std_rad), x0=x0)
    assert pred.history.names == bound.names
    np.testing.assert_allclose(pred.history.covariance[-1], bound.covariance, rtol=1e-8,
                               atol=1e-14)
    assert pred.history.t.size == len(run.record.window(*cand.window_s(plan.omega_rad_s)))


def test_shortest_record_and_meets_target_agree_with_the_curve():
    """Candidates at least as long as the shortest record meet the targets, shorter ones do not."""
    plan = planning.load_plan(WAKE)
    result = planning.evaluate_plan(plan)
    for r in result.candidates:
        pred = result.transients[r.transient_index]
        if r.shortest_duration_rev is None:
            assert not r.meets_target
            continue
        assert r.meets_target == (r.candidate.duration_rev >= r.shortest_duration_rev - 1e-9)
        n = int(round(r.shortest_duration_rev * 2 * math.pi / plan.sample_interval)) + 1
        std = pred.std()
        targets = np.array([plan.target_std[u] for u in plan.unknowns])
        assert np.all(std[n - 1] <= targets)            # met at the shortest record …
        assert not np.all(std[n - 2] <= targets)        # … and not one sample earlier


def _plan_text(target):
    text = WAKE.read_text()
    return text.replace('target_std: {A: 0.02, AL_over_tau: 0.025, inv_tau: 0.008}', target)


def test_recommendation_rules():
    """Shortest meeting record; none met → closest to the targets; no targets → best relative."""
    met = planning.evaluate_plan(planning.load_plan(WAKE))
    meeting = [r for r in met.candidates if r.meets_target]
    best = met.candidates[met.recommended]
    assert best.meets_target
    assert best.candidate.duration_rev == min(r.candidate.duration_rev for r in meeting)

    hard = planning.evaluate_plan(planning.parse_plan(_plan_text('target_std: {A: 0.0001}')))
    assert not any(r.meets_target for r in hard.candidates)
    assert hard.recommended == int(np.argmin([r.std['A'] for r in hard.candidates]))
    assert any('no candidate meets target_std' in w for w in hard.warnings)

    longer = planning.evaluate_plan(planning.parse_plan(_plan_text('target_std: {A: 0.005}')))
    assert not any(r.meets_target for r in longer.candidates)
    need = min(r.shortest_duration_rev for r in longer.candidates
               if r.shortest_duration_rev is not None)
    assert 3.0 < need <= 6.0               # beyond the planned 3 rev, within the 2× horizon
    assert any(f'record of {need:.2f} rev' in w for w in longer.warnings)

    free = planning.evaluate_plan(planning.parse_plan(_plan_text('')))
    worst = [max(r.relative_std.values()) for r in free.candidates]
    assert free.recommended == int(np.argmin(worst))
    assert all(r.meets_target for r in free.candidates)


def test_a_dozen_candidates_plan_in_seconds():
    """Smoke bound only (speed is measured in bench/, not here): 12 candidates < 30 s."""
    plan = planning.load_plan(WAKE)
    assert len(plan.candidates) == 12
    started = time.perf_counter()
    result = planning.evaluate_plan(plan)
    assert time.perf_counter() - started < 30.0
    assert len(result.transients) == 4


# ------------------------------------------------------------------------------------------------
# PLAN.yaml
# ------------------------------------------------------------------------------------------------

def test_defaults_when_candidates_are_absent():
    """No candidates: both directions × 3 ω̇ × 3 record lengths at the report's t0 and 1.5°."""
    text = MULTIBLADE.read_text()
    text = text[:text.index('# Candidates:')]
    plan = planning.parse_plan(text)
    assert len(plan.candidates) == 18
    assert {c.direction for c in plan.candidates} == set(planning.DIRECTIONS)
    assert {c.t0 for c in plan.candidates} == {12.0}
    assert {c.amplitude_rad for c in plan.candidates} == {planning.DEFAULT_AMPLITUDE_RAD}
    assert all((c.omegadot < 0) == (c.direction == 'progressing') for c in plan.candidates)
    assert plan.description.window_s == (0.0, 1.0) and not plan.warnings
    wake = planning.parse_plan(WAKE.read_text().split('candidates:')[0])
    assert {c.t0 for c in wake.candidates} == {70.0}


def test_candidate_lists_and_signed_omegadot():
    """A list of candidate groups; a signed ω̇ without direction decides the direction."""
    text = WAKE.read_text().split('candidates:')[0] + (
        'candidates:\n'
        '  - {omegadot: -0.0318, duration_rev: 2}\n'
        '  - {direction: regressing, omegadot: [0.0318], duration_rev: [1.5, 2]}\n')
    plan = planning.parse_plan(text)
    assert [(c.direction, c.omegadot, c.duration_rev) for c in plan.candidates] == [
        ('progressing', -0.0318, 2.0), ('regressing', 0.0318, 1.5), ('regressing', 0.0318, 2.0)]


@pytest.mark.parametrize('edit, message', [
    (('noise_std_rad: 0.0017453 ', '# '), 'noise_std_rad is missing'),
    (('rate_hz: 1000.0', '# '), 'rate_hz is missing'),
    (('inv_tau: 0.008}', 'gamma: 0.1}'), "'gamma' is not an unknown"),
    (('amplitude_rad: [0.0262]', 'amplitude_rad: [1.5]'), 'radians, not degrees'),
    (('direction: [progressing, regressing]', 'direction: [progressing, sideways]'),
     'progressing or regressing'),
    (('omegadot: [0.0159, 0.0318]', 'omegadot: [0.0159, -0.0318]'),
     'give |ω̇| with the direction'),
    (('t0: [70.0]', 'start: [70.0]'), "unknown candidate key 'start'"),
    (('guess: {A: 0.5, AL_over_tau: 0.25, inv_tau: 0.125}', 'guess: {A: 0.5}'),
     'guess has no value for AL_over_tau, inv_tau'),
    (('duration_rev: [1.0, 2.0, 3.0]', 'duration_rev: []'), 'empty list'),
    (('omega_rad_s: 94.2478', 'omega_rad_s: 900.0'), 'sample at least'),
    (('rate_hz: 1000.0', 'rate_hz: 1000.0\nknown_initial_state: yes please'),
     'known_initial_state must be true or false'),
])
def test_bad_plans_name_file_line_and_remedy(edit, message):
    """Each mistake gives one RunDescriptionError naming the file, the line and what to do."""
    old, new = edit
    text = WAKE.read_text()
    assert old in text
    with pytest.raises(RunDescriptionError) as err:
        planning.parse_plan(text.replace(old, new), 'my_plan.yaml')
    assert message in str(err.value)
    assert str(err.value).startswith('my_plan.yaml')
