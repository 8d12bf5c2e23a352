"""
Out of catalogue (pins #16): a proposed flap-equation term, validated on held-out blocks.

* the proposal's model (baseline + one library term) has exact sensitivities and is the
  baseline at ξ = 0;
* on a recording with a once-per-rev flap stiffness (or damping) no candidate models
  (independent truth generator), the proposal names ``beta*cos(psi)`` (``beta_dot*sin(psi)``)
  with the coefficient −K_1c (−D_1s) within 3σ;
* on effect-free recordings it proposes nothing (the ≥ 20-seed false-proposal rate is measured
  by bench/proposal_stats.py, bench/results/proposal.md);
* diagnose attaches it under ``explanation.proposal`` when the verdict is ``unexplained``, the
  text report has its line and the report its figure; a random-inflow verdict with a
  proposed deterministic term is not confident.
"""

from diagnosis_scenarios import BY_NAME, D_1S, K_1C
import numpy as np
import pytest
from rotor_id.commands.diagnose import format_summary
from rotor_id.commands.diagnose_figures import write_report
from rotor_id.diagnosis.diagnose import diagnose
from rotor_id.estimation.simulate import simulate
from rotor_id.estimation.term_search import propose
from rotor_id.physics.augmented import LibraryTerm, term_names
from rotor_id.pipeline import identify
from test_diagnosis_augmentations import _base, _inputs, check_sensitivities, T

TERMS = ['beta*cos(psi)', 'beta_dot', 'theta*sin(psi)', 'cos(psi)']


def test_library_has_the_first_harmonic_products():
    names = term_names()
    assert len(names) == 12 and len(set(names)) == 12
    for factor in ('beta', 'beta_dot', 'theta'):
        assert {factor, f'{factor}*cos(psi)', f'{factor}*sin(psi)'} <= set(names)
    assert {'1', 'cos(psi)', 'sin(psi)'} <= set(names)


@pytest.mark.parametrize('name,mu', [('multiblade', 0.4), ('multiblade_wake', 0.0)])
def test_library_term_sensitivities_and_neutral_value(name, mu):
    rng = np.random.default_rng(7)
    base = _base(name, mu)
    x0 = 0.01 * np.arange(1, base.n_states + 1)
    ref = simulate(base, base.nominal(), _inputs(), T, x0).y
    for term in TERMS:
        model = LibraryTerm(base, term)
        check_sensitivities(model, _inputs(), rng)
        np.testing.assert_allclose(simulate(model, model.nominal(), _inputs(), T, x0).y, ref,
                                   atol=1e-14)


def _propose(name, seed):
    scenario = BY_NAME[name]
    record, description = scenario.record_and_description(seed)
    return propose(identify(record, description))


@pytest.mark.parametrize('name,truth', [('flap_stiffness_1c', ('beta*cos(psi)', -K_1C)),
                                        ('flap_damping_1s', ('beta_dot*sin(psi)', -D_1S))])
def test_proposal_names_the_term_no_candidate_models(name, truth):
    proposal = _propose(name, 1)
    assert [t['term'] for t in proposal.terms] == [truth[0]], proposal.steps
    term = proposal.terms[0]
    assert term['label'] == 'proposal' and term['coefficient_from'] == 'output-error ML'
    assert abs(term['coefficient'] - truth[1]) <= 3.0 * term['std'], term
    assert term['heldout_improvement'] > 0.1
    # rivals as good within chance are named beside it (β cos ψ ~ θ cos ψ where coning rules)
    assert set(term['alternatives']) <= set(term_names()) - {truth[0]}
    assert proposal.heldout_rms_after < proposal.heldout_rms_before


@pytest.mark.parametrize('name,seed', [('none_multiblade', 1), ('none_wake', 1),
                                       ('none_mu04', 1)])
def test_no_proposal_without_an_effect(name, seed):
    proposal = _propose(name, seed)
    assert proposal.terms == [], proposal.steps
    step = proposal.steps[0]
    assert not step['kept']
    if step['heldout_improvement'] == 0.0:
        # a term the held-out blocks cannot see (β cos ψ beside the wake in hover): its t is
        # zero, not the t of the least-squares solutions' rounding
        assert step['t_statistic'] == 0.0 and step['blocks_improved'] == 0, step


def test_diagnose_attaches_the_proposal_to_an_unexplained_verdict(tmp_path):
    # with only the sensor bias to try, the once-per-rev stiffness stays unexplained
    scenario = BY_NAME['flap_stiffness_1c']
    record, description = scenario.record_and_description(1)
    result = diagnose(record, description, workers=1, effects=('sensor_bias',))
    out = result.as_json()
    assert out['explanation']['effect'] == 'unexplained'
    proposal = out['explanation']['proposal']
    assert proposal['label'] == 'proposal'
    assert proposal['terms'][0]['term'] == 'beta*cos(psi)'
    assert 'proposal (a hypothesis, not a catalogue verdict)' in format_summary(result)
    # and --report draws it: every library term's held-out improvement, the kept one marked
    assert (tmp_path / 'proposal.png') in write_report(result, tmp_path)
    assert (tmp_path / 'proposal.png').stat().st_size > 10000


@pytest.mark.slow
def test_random_inflow_gives_way_to_unexplained_when_a_deterministic_term_predicts():
    # the filter-error fit tracks the once-per-rev stiffness as random inflow; the verdict is
    # out of catalogue (`unexplained`, low confidence), no catalogue name, and the proposal
    # finds the deterministic term on held-out blocks (one filter-error fit)
    scenario = BY_NAME['flap_stiffness_1c']
    record, description = scenario.record_and_description(1)
    out = diagnose(record, description, workers=1, effects=('process_noise',)).as_json()
    assert out['explanation']['effect'] == 'unexplained'
    assert out['explanation']['confidence'] == 'low'
    assert out['explanation']['proposal']['terms'][0]['term'] == 'beta*cos(psi)'
    assert out['explanation']['effects'] == []
