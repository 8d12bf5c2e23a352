"""
Monte Carlo of the report's cases in CI: the ML scatter is the Cramér-Rao bound.

The full run (``bench/monte_carlo.py``, 1000 seeds per case) checks |bias| ≤ 0.2 σ_CRB,
|σ/σ_CRB − 1| ≤ 15 % and 95 % coverage within 92-98 %. Here N = 100 seeds per case (about
25 s for the eight cases) with limits taken from the sampling distribution of each statistic
under the hypothesis "unbiased, σ = σ_CRB", at two-sided level 0.3 % per statistic:

* bias: mean error / σ_CRB ~ N(0, 1/N) → |bias| ≤ 3/√N = 0.30 σ_CRB. A bias of 0.5 σ_CRB
  fails with probability 98 %.
* scatter: (N−1) s²/σ² ~ χ²(N−1) → s/σ_CRB in [√(χ²_.0015/(N−1)), √(χ²_.9985/(N−1))] =
  [0.79, 1.22]. A bound wrong by 30 % (true ratio 1.3 or 1/1.3) fails with probability
  ≈ 85 % / 90 %.
* coverage: count inside ±1.96 σ_CRB ~ Binomial(N, 0.95) → [Binom_.0015, Binom_.9985] / N.

The reference is the truth, or for the constant-coefficient multiblade model the noise-free
estimate (the modelling-error bias of docs/models.md §2.3). ``test_limits_reject_wrong_bounds``
shows on the same draws that a bound 30 % off or a 0.5 σ bias is rejected.
"""

import math

import numpy as np
import pytest
from rotor_id.report import monte_carlo as M
from scipy.stats import binom, chi2

N_SEEDS = 100
ALPHA = 0.003
BIAS_LIMIT = 3.0 / math.sqrt(N_SEEDS)
STD_LOW, STD_HIGH = np.sqrt(chi2.ppf([ALPHA / 2, 1 - ALPHA / 2], N_SEEDS - 1) / (N_SEEDS - 1))
COV_LOW, COV_HIGH = binom.ppf([ALPHA / 2, 1 - ALPHA / 2], N_SEEDS, 0.95) / N_SEEDS


@pytest.fixture(scope='module')
def results():
    return {name: M.run_case(name, range(N_SEEDS)) for name in M.MONTE_CARLO_CASES}


def test_documented_limits():
    assert BIAS_LIMIT == pytest.approx(0.30)
    assert STD_LOW == pytest.approx(0.79, abs=0.01) and STD_HIGH == pytest.approx(1.22, abs=0.01)
    assert 0.88 <= COV_LOW <= 0.90 and COV_HIGH == 1.0


@pytest.mark.parametrize('name', M.MONTE_CARLO_CASES)
def test_estimates_scatter_as_the_cramer_rao_bound(results, name):
    res = results[name]
    assert res.n == N_SEEDS and np.all(res.converged)
    for pname, _, _, bias, ratio, cov in res.rows():
        assert abs(bias) <= BIAS_LIMIT, f'{name} {pname}: bias {bias:+.3f} σ_CRB'
        assert STD_LOW <= ratio <= STD_HIGH, f'{name} {pname}: σ/σ_CRB = {ratio:.3f}'
        assert COV_LOW <= cov <= COV_HIGH, f'{name} {pname}: coverage {cov:.2f}'


def test_reference_is_truth_or_modelling_bias(results):
    for name, res in results.items():
        expected = 'modelling-error bias' if name.startswith('multiblade') else 'truth'
        assert res.reference.kind == expected
    # docs/models.md §2.3 (b): the constant-coefficient model's noise-free estimate
    np.testing.assert_allclose(results['multiblade_b'].reference.values, [4.855, 10.374],
                               atol=6e-4)
    # the reported report-case bound: single blade σ_γ, σ_δ = .092, .12 (docs/models.md §1.4)
    np.testing.assert_allclose(results['single_blade_2par'].reference.crb_std, [0.092, 0.121],
                               atol=0.002)


def test_limits_reject_wrong_bounds(results):
    """The same draws with σ_CRB scaled by 1.3 or 1/1.3, or shifted by 0.5 σ, are rejected."""
    rejected = {'too large': 0, 'too small': 0, 'biased': 0}
    total = 0
    for res in results.values():
        ratio = res.std_ratio
        bias = res.bias_in_sigma
        total += ratio.size
        rejected['too large'] += np.sum(ratio / 1.3 < STD_LOW)
        rejected['too small'] += np.sum(ratio * 1.3 > STD_HIGH)
        rejected['biased'] += np.sum(np.abs(bias + 0.5) > BIAS_LIMIT)
    assert rejected['biased'] == total
    assert rejected['too large'] >= 0.7 * total and rejected['too small'] >= 0.7 * total, \
        (rejected, total)
