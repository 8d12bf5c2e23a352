"""The effective sample fraction that every diagnosis criterion multiplies 2Δlog L by."""

import numpy as np

from rotor_id import residuals as rs


def _ar1(rng, n, a, burn=200):
    e = rng.standard_normal(n + burn)
    x = np.zeros_like(e)
    for i in range(1, e.size):
        x[i] = a * x[i - 1] + e[i]
    return x[burn:]


def test_white_innovations_count_every_sample():
    # Four white channels of 449 samples (the μ = 0.4 multiblade record): the minimum of the
    # per-channel Geyer fractions averages about 0.85, so a criterion would discount a correct
    # filter's likelihood gain by 15 %. Innovations gated by each channel's whiteness test
    # (5 % family-wise) average within a few per cent of 1.
    rng = np.random.default_rng(11)
    draws = [rng.standard_normal((449, 4)) for _ in range(300)]
    gated = np.array([rs.channels_effective_fraction(x, innovations=True) for x in draws])
    ungated = np.array([rs.channels_effective_fraction(x) for x in draws])
    np.testing.assert_allclose(
        ungated, [min(rs.effective_fraction(x[:, j]) for j in range(4)) for x in draws])
    assert ungated.mean() < 0.9
    assert gated.mean() > 0.97
    # the gate closes only at the test's level: about 5 % of white draws are corrected
    assert 0.01 < np.mean(gated < 1.0) < 0.12


def test_a_correlated_channel_still_sets_the_fraction():
    # one AR(1) channel (a = 0.5, N_eff/N = (1 − a)/(1 + a) = 1/3) among three white ones:
    # the whiteness test rejects and the fraction is that channel's
    rng = np.random.default_rng(12)
    values = []
    for _ in range(100):
        x = rng.standard_normal((449, 4))
        x[:, 2] = _ar1(rng, 449, 0.5)
        values.append(rs.channels_effective_fraction(x, innovations=True))
    assert abs(np.mean(values) - 1.0 / 3.0) < 0.05
    # the output-error residuals of a wrong model are far from white: their fraction is small
    slow = np.column_stack([_ar1(rng, 449, 0.95) for _ in range(4)])
    assert rs.channels_effective_fraction(slow) < 0.1


def test_output_error_residuals_are_not_gated():
    # unmodelled turbulence in output-error residuals: a small first-order component (τ ≈ 20
    # samples, 15 % of the variance; true fraction 1/(1 + 2·0.15·a/(1 − a)) ≈ 0.15) that the
    # whiteness test passes in about one draw of seven. Ungated, the Geyer estimate sees the
    # correlation in every draw (mean about 0.35); gated, those draws would count every sample.
    rng = np.random.default_rng(13)
    a = np.exp(-1.0 / 20.0)
    values, passing = [], []
    for _ in range(100):
        slow = _ar1(rng, 449, a) * np.sqrt((1 - a * a) * 0.15 / 0.85)
        x = rng.standard_normal((449, 1)) + slow[:, None]
        values.append(rs.channels_effective_fraction(x))
        if rs.ljung_box(x[:, 0])[1] >= 0.05:
            passing.append(values[-1])
    assert np.mean(values) < 0.6
    # the draws the test alone would call white (14 of 100) still get their correlation
    # counted: gated, each of them would be 1
    assert len(passing) > 10
    assert np.mean(passing) < 0.8
