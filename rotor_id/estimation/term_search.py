"""
Which term of the flap equation do the data want? A search by equation error.

When no model of a catalogue explains a recording, the mismatch may still be structured
dynamics. Which small physical term, added to every blade's flapping equation alike, do the
data want? (The diagnosis's out-of-catalogue proposal, ``explanation.proposal``.)

1. Reconstruct the states with the baseline model: the iterated equation error's Kalman filter
   and RTS smoother, process noise on the parameter-dependent rows chosen by likelihood, so the
   smoothed states follow the data where the model is wrong (one pass of
   :func:`rotor_id.estimation.equation_error.fit_equation_error`).
2. Regress the equation error of those rows, e = x′ − F x − g, on the baseline's own regressors
   (always in: a term is judged for what it adds beyond re-estimating the baseline's unknowns)
   and a library of per-blade terms φ_k carried into the rows by the model's blade-force matrix
   G (x′ += ξ G φ, i.e. β_k″ += ξ φ_k): β_k, β_k′, θ_k (measured), 1, each alone and times
   cos ψ_k and sin ψ_k.
3. Forward stepwise, validated on :data:`N_BLOCKS` held-out contiguous time blocks: a term is
   kept only if it lowers the held-out error in a one-sided t-test of the blocks' log ratios
   at level :data:`ALPHA` (Bonferroni over the terms tried at that step), and by at least
   :data:`MIN_IMPROVEMENT` in all.
4. The kept terms' regression coefficients, σ by a cluster sandwich over :data:`N_CLUSTERS`
   contiguous clusters (the smoothed states are serially correlated). Equation error attenuates
   a coefficient where the smoothed states lean on the wrong model (bench/results/proposal.md),
   so the baseline with the kept terms (:class:`rotor_id.physics.augmented.LibraryTerm`) is
   fitted by output-error ML: that coefficient and its Cramér-Rao σ are the proposal's.

The result is labelled ``proposal``, a hypothesis for the experimenter, never a catalogue
verdict. Terms whose held-out error is not worse beyond chance (one-sided 5 %, uncorrected) are
listed as ``alternatives``: β cos ψ and θ cos ψ are nearly collinear where the coning dominates.
"""

from dataclasses import dataclass, field
from functools import partial
import math
from typing import Any, Protocol, Sequence

import numpy as np

from rotor_id.estimation.equation_error import fit_equation_error, regression
from rotor_id.estimation.output_error import (
    augment_runs, Estimate, Experiment, FIT_FAILURES, fit_output_error, split_values)
from rotor_id.estimation.validation import student_t_isf
from rotor_id.physics.augmented import library, LibraryTerm, term_names

#: Contiguous time blocks of the held-out validation.
N_BLOCKS = 8
#: Family-wise level of the held-out test at each step (Bonferroni over the terms tried).
ALPHA = 0.01
#: Smallest relative reduction of the held-out equation error a proposed term must bring.
MIN_IMPROVEMENT = 0.02
#: A block's log ratio of held-out errors this small is rounding (the two least-squares
#: solutions agree to twelve digits: a term the blocks cannot see), and counts as zero.
ROUNDING_LOG_RATIO = 1e-12
#: Most terms proposed.
MAX_TERMS = 2
#: Contiguous clusters of the robust coefficient covariance.
N_CLUSTERS = 32


class Baseline(Protocol):
    """The fit a term is searched beside (e.g. :class:`rotor_id.pipeline.Identification`)."""

    experiments: Sequence[Experiment]   # its runs
    unknowns: Sequence[str]             # re-estimated beside every term
    estimate: Estimate


@dataclass
class Regressors:
    """The weighted equation-error regression e = A δθ + L ξ, rows flattened over (time, row)."""

    e: np.ndarray            # (n,) weighted equation error
    A: np.ndarray            # (n, k) baseline unknowns' regressors
    L: np.ndarray            # (n, M) library terms
    block: np.ndarray        # (n,) held-out block of each row
    cluster: np.ndarray      # (n,) covariance cluster of each row
    process_noise_std: float
    rows: list


def build_regressors(baseline: Baseline) -> Regressors:
    """Reconstruct the states and build :class:`Regressors` for the baseline fit's runs."""
    experiments, unknowns = baseline.experiments, list(baseline.unknowns)
    values, known = split_values(baseline.estimate, unknowns)
    result = fit_equation_error(experiments, unknowns, guess=values, known=known, max_iter=1)
    model = experiments[0].model
    p = model.parameter_vector({**known, **dict(zip(result.names, result.values))})
    idx = [model.parameter_names.index(n) for n in unknowns]
    parts = []
    for exp, rec in zip(experiments, result.reconstructions):
        t = exp.t
        x, xdot = rec.x_smoothed, rec.derivatives
        reg = regression(exp.model, p, exp.inputs, t, x, xdot, idx)
        e = reg.zeta - reg.A @ p[idx]                                  # (T, r)
        rotor: Any = exp.model                                           # a rotor model
        G = rotor.blade_force_matrix(t)[:, reg.rows]                   # (T, r, N_b)
        Lt = np.einsum('trk,tkm->trm', G, library(exp.model, t, x, exp.inputs(t)))
        frac = (t - t[0]) / max(t[-1] - t[0], 1e-12)
        parts.append((e, reg.A, Lt, reg.weights, frac))
    rows = reg.rows
    # weight each row by 1/(its residual variance after the baseline's own regressors)
    e_all = np.concatenate([e for e, _, _, _, _ in parts])
    A_all = np.concatenate([A for _, A, _, _, _ in parts])
    row_var = np.empty(len(rows))
    for r in range(len(rows)):
        coef = np.linalg.lstsq(A_all[:, r, :], e_all[:, r], rcond=None)[0]
        row_var[r] = max(float(np.mean((e_all[:, r] - A_all[:, r, :] @ coef)**2)), 1e-300)
    es, As, Ls, blocks = [], [], [], []
    clusters: list[np.ndarray] = []
    for e, A, Lt, w, frac in parts:
        scale = np.sqrt(w[:, None] / row_var[None, :])                # (T, r)
        es.append((e * scale).reshape(-1))
        As.append((A * scale[:, :, None]).reshape(-1, A.shape[2]))
        Ls.append((Lt * scale[:, :, None]).reshape(-1, Lt.shape[2]))
        b = np.minimum((frac * N_BLOCKS).astype(int), N_BLOCKS - 1)
        c = np.minimum((frac * N_CLUSTERS).astype(int), N_CLUSTERS - 1)
        blocks.append(np.repeat(b, len(rows)))
        clusters.append(np.repeat(c + N_CLUSTERS * len(clusters), len(rows)))
    return Regressors(np.concatenate(es), np.concatenate(As), np.concatenate(Ls),
                      np.concatenate(blocks), np.concatenate(clusters),
                      float(result.process_noise_std), rows)


def _design(reg, terms):
    return np.concatenate([reg.A, reg.L[:, list(terms)]], axis=1)


def heldout_errors(reg: Regressors, terms: Sequence[int]) -> np.ndarray:
    """Return the held-out weighted squared equation error of every block, (N_BLOCKS,)."""
    X = _design(reg, terms)
    out = np.empty(N_BLOCKS)
    for b in range(N_BLOCKS):
        test = reg.block == b
        coef = np.linalg.lstsq(X[~test], reg.e[~test], rcond=None)[0]
        out[b] = float(np.sum((reg.e[test] - X[test] @ coef)**2))
    return out


def robust_fit(reg: Regressors, terms: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients of [baseline unknowns, terms] and their cluster-sandwich covariance."""
    X = _design(reg, terms)
    coef, *_ = np.linalg.lstsq(X, reg.e, rcond=None)
    res = reg.e - X @ coef
    bread = np.linalg.pinv(X.T @ X)
    meat = np.zeros((X.shape[1], X.shape[1]))
    for c in np.unique(reg.cluster):
        s = X[reg.cluster == c].T @ res[reg.cluster == c]
        meat += np.outer(s, s)
    n_c = np.unique(reg.cluster).size
    cov = bread @ meat @ bread * n_c / max(n_c - 1, 1)
    return coef, cov


@dataclass
class Proposal:
    """Terms proposed for every blade's flap equation (or none), with their evidence."""

    terms: list = field(default_factory=list)
    library: list = field(default_factory=list)
    heldout_rms_before: float | None = None
    heldout_rms_after: float | None = None
    steps: list = field(default_factory=list)
    reason: str = ''

    def as_json(self) -> dict[str, Any]:
        """JSON under ``explanation.proposal``."""
        return {'label': 'proposal', 'terms': list(self.terms), 'library': list(self.library),
                'equation': "beta_k'' += coefficient * term_k on every blade k",
                'heldout_error_before': self.heldout_rms_before,
                'heldout_error_after': self.heldout_rms_after,
                'steps': list(self.steps), 'reason': self.reason,
                'method': f'equation error of the Kalman-smoothed states (held-out errors: RMS '
                          f'of the row-normalised equation error); forward stepwise '
                          f'regression, a term kept when it lowers the held-out error of '
                          f'{N_BLOCKS} time blocks (t-test of the log ratios, level {ALPHA} '
                          f'over the terms tried, and by >= {MIN_IMPROVEMENT:.0%} in all); '
                          f'coefficient and σ from the output-error ML fit with the term'}


def summary_line(proposal: dict[str, Any]) -> str:
    """One line of the text report from ``explanation.proposal`` (JSON)."""
    if not proposal['terms']:
        why = f' ({proposal["reason"]})' if proposal.get('reason') else ''
        return f'proposal: no library term improves the held-out equation error beyond ' \
               f'chance{why}'
    parts = [f"beta_k'' += ({t['coefficient']:.4g} ± {t['std']:.2g}) · {t['term']} "
             f"(held-out equation error −{t['heldout_improvement']:.0%}"
             + (f"; as good within chance: {', '.join(t['alternatives'])}"
                if t.get('alternatives') else '') + ')'
             for t in proposal['terms']]
    return 'proposal (a hypothesis, not a catalogue verdict): ' + '; '.join(parts)


def refine(baseline: Baseline, terms: Sequence[str]) -> tuple[Estimate, list[str]]:
    """
    Fit the baseline with the proposed terms by output-error ML; return the estimate.

    The runs are the baseline fit's with every term stacked on the model
    (:func:`~rotor_id.estimation.output_error.augment_runs`).
    """
    runs: Sequence[Experiment] = baseline.experiments
    for term in terms:
        runs, _ = augment_runs(runs, partial(LibraryTerm, term=term))
    extra = [f'xi[{term}]' for term in terms]
    values, known = split_values(baseline.estimate, baseline.unknowns)
    guess = {**values, **dict.fromkeys(extra, 0.0)}
    return fit_output_error(runs, list(baseline.unknowns) + extra, guess=guess, known=known,
                            max_iter=30), extra


def _log_ratio_t(before, after):
    """
    Return the t statistic of the blocks' log ratios of held-out errors (before/after), and them.

    Per block log ratio: scale-free, so the blocks of a quiet trim and of the stirring count
    alike; a ratio at rounding level is zero (without, a term that changes nothing gets the
    t of rounding noise, of order one).
    """
    ratio = np.log(np.maximum(before, 1e-300) / np.maximum(after, 1e-300))
    ratio = np.where(np.abs(ratio) <= ROUNDING_LOG_RATIO, 0.0, ratio)
    spread = float(np.std(ratio, ddof=1))
    if not spread > 0:
        return (math.inf if np.mean(ratio) > 0 else 0.0), ratio
    return float(np.mean(ratio)) / (spread / math.sqrt(ratio.size)), ratio


def propose(baseline: Baseline) -> Proposal:
    """
    Propose up to :data:`MAX_TERMS` library terms of the flap equation: :class:`Proposal`.

    ``baseline``: the fit searched beside (:class:`Baseline`), its unknowns re-estimated
    beside every term. The method is the module docstring's.
    """
    names = term_names()
    try:
        reg = build_regressors(baseline)
    except FIT_FAILURES as exc:
        return Proposal(library=names, reason=f'equation error failed: {exc}')
    current: list[int] = []
    sse = heldout_errors(reg, current)
    before = float(math.sqrt(np.sum(sse) / reg.e.size))
    steps = []
    for _ in range(MAX_TERMS):
        step, best, trial = _forward_step(reg, current, sse, names)
        steps.append(step)
        if not step['kept']:
            break
        current.append(best)
        sse = trial
    terms, reason = _proposed_terms(reg, current, steps, names, baseline)
    after = float(math.sqrt(np.sum(sse) / reg.e.size))
    return Proposal(terms=terms, library=names, heldout_rms_before=before,
                    heldout_rms_after=after, steps=steps, reason=reason)


def _forward_step(reg, current, sse, names):
    """Try each term left beside ``current``; return (step record, best term, its errors)."""
    left = [m for m in range(len(names)) if m not in current]
    trials = {m: heldout_errors(reg, current + [m]) for m in left}
    best = min(trials, key=lambda m: float(np.sum(trials[m])))
    t_stat, gain = _log_ratio_t(sse, trials[best])
    t_crit = student_t_isf(ALPHA / len(left), N_BLOCKS - 1)
    # a rival term is as good within chance unless worse at the one-sided 5 % level
    t_alternative = student_t_isf(0.05, N_BLOCKS - 1)
    improvement = float(1.0 - np.sum(trials[best]) / np.sum(sse))
    kept = bool(t_stat > t_crit and improvement >= MIN_IMPROVEMENT)
    step = {'term': names[best], 'heldout_improvement': improvement,
            't_statistic': t_stat, 't_critical': t_crit,
            'blocks_improved': int(np.sum(gain > 0)), 'kept': kept,
            'tried': {names[m]: float(1.0 - np.sum(trials[m]) / np.sum(sse)) for m in left},
            'alternatives': [names[m] for m in left if m != best
                             and not _log_ratio_t(trials[m], trials[best])[0] > t_alternative]}
    return step, best, trials[best]


def _proposed_terms(reg, current, steps, names, baseline):
    """Return (the kept terms with their coefficients, reason the ML refit failed or '')."""
    terms, reason = [], ''
    if not current:
        return terms, reason
    coef, cov = robust_fit(reg, current)
    k = reg.A.shape[1]
    try:
        est, extra = refine(baseline, [names[m] for m in current])
        ml = {n: (est.value(n), est.std_of(n)) for n in extra}
    except FIT_FAILURES as exc:
        ml, reason = {}, f'output-error refit failed: {exc}'
    for i, m in enumerate(current):
        step = next(s for s in steps if s['term'] == names[m])
        ee = (float(coef[k + i]), float(math.sqrt(max(cov[k + i, k + i], 0.0))))
        value, std = ml.get(f'xi[{names[m]}]', ee)
        terms.append({'term': names[m], 'coefficient': float(value), 'std': float(std),
                      'coefficient_from': 'output-error ML' if ml else 'equation error',
                      'equation_error_coefficient': ee[0], 'equation_error_std': ee[1],
                      'heldout_improvement': step['heldout_improvement'],
                      't_statistic': step['t_statistic'],
                      'alternatives': step['alternatives'], 'label': 'proposal'})
    return terms, reason
