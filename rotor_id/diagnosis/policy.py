"""
Every threshold of the model selection, each with its statistical reason.

The selection (:mod:`rotor_id.diagnosis.selection`) compares explanations (sets of catalogue
effects) by an approximate posterior probability; the values here are levels, prior weights
and budgets, never tuned to a particular record. ``docs/diagnosis.md`` states the rules.
"""

from dataclasses import dataclass


@dataclass(frozen=True)
class SelectionPolicy:
    """The thresholds of the selection and the verdict, each with its reason."""

    #: Most effects in one explanation. The prior is uniform over the sizes 0 … max_effects,
    #: then uniform over the sets of each size, so a set of two among m effects starts with
    #: prior weight 1/C(m, 2) of its size's share: the multiplicity of pairs is paid for.
    max_effects: int = 3
    #: Posterior probability of the top explanation that a verdict calls "high confidence".
    high_confidence: float = 0.95
    #: An explanation is listed among the alternatives (and an effect that can stand in for
    #: a named one is named beside it, with its share) from this posterior probability on.
    alternative_share: float = 0.01
    #: The stated probabilities are the posterior's, temperature-scaled (p ∝ posterior^η, the
    #: standard recalibration of a classifier's odds; the ranking, and so every name, stays):
    #: likelihood ratios between the catalogue's misspecified forms overstate the evidence (at
    #: η = 1, verdicts stated at ≥ 0.95 were right 94-95 %, bench/results/verdict_rules.md). η
    #: maximises the log score (a proper scoring rule) of the stated probability on the tables
    #: the search records (bench/verdict_rules.py): 0.7 on the even seeds and on all, 0.75 on
    #: the odd; the smaller is taken, a rig being further from the catalogue's forms than the
    #: generator. The search keeps η = 1.
    evidence_tempering: float = 0.7
    #: Power at which a detection limit is stated: an effect of that size would have been
    #: added by the search in this share of records like this one.
    detection_power: float = 0.95
    #: A candidate is fitted when its score test says it could hold at least this posterior
    #: probability against the current model: a fifth of the 5 % that separates a
    #: high-confidence verdict from a low one. Below it, it still enters the normalisation by
    #: its score-test approximation.
    fit_share: float = 0.01
    #: The score statistic is the Gauss-Newton (quadratic) prediction of 2Δlog L; where the
    #: effect is not small the fit gains more. A candidate is fitted when this multiple of its
    #: score statistic could reach ``fit_share``.
    score_allowance: float = 2.0
    #: Level of the whiteness test (Ljung-Box, Bonferroni over channels) at which the best
    #: explanation's residuals are judged not noise: the verdict is then ``unexplained``.
    adequacy_level: float = 1e-3
    #: ... or when a channel's residual RMS exceeds its model-free noise floor by this many
    #: standard errors (a one-sided z; 4 is a level of 3e-5 per channel).
    adequacy_excess_z: float = 4.0
    #: A first-order equivalent whose fit ends below the other's log-likelihood by more than
    #: half the χ²₁ 5 % point (1.92) is at a worse optimum of the same physics and is restarted
    #: from the other's values (a lag τ is a delay d = τ to first order).
    restart_margin: float = 1.92
    #: Explanations of each size extended at the next step. Greedy forward selection (one)
    #: can keep first an effect that stands in for parts of two others, and then neither of
    #: them passes beside it; the second most probable explanation is extended too.
    beam_width: int = 2
    #: Candidate fits of one step done in full when more pass the screen (a compute budget:
    #: the others enter the posterior by their score-test approximation).
    max_fits_per_step: int = 6
    #: A fit (the baseline's, a candidate's) has converged when every Gauss-Newton step is
    #: below this fraction of its parameter's Cramér-Rao σ (output error), or when a further
    #: scoring step would gain less than this in log-likelihood (filter error, whose scoring
    #: can zigzag about a flat optimum). Either way the log-likelihood is within a few
    #: hundredths of its optimum (½·k·0.05² ≤ 0.02 for k ≤ 16 parameters): the posterior odds
    #: within 5 %, the estimate within 0.05 σ, inside the digits the verdict prints.
    fit_tolerance: float = 0.05
    #: The RK4 error allowed in the diagnosis's fits, as a fraction of each channel's noise σ:
    #: every fit takes one RK4 step per sample where the baseline model, so integrated, stays
    #: within it of its integration at the default step (:func:`catalogue.record_step`). An
    #: output error δ ≤ 1e-3 σ moves 2 log L by about 2√N·δ/σ ≈ 0.1 at N = 4000 samples ×
    #: channels, far below the ½·log(Nρ) ≈ 4 each parameter is charged; and every explanation
    #: of the record, the baseline included, is integrated alike.
    integration_error: float = 1e-3


DEFAULT_POLICY = SelectionPolicy()
