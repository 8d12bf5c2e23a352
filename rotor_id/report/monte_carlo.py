"""
Monte Carlo of the report's cases: the ML estimate's scatter against the Cramér-Rao bound.

For each case, measurement noise of the report's σ (0.2 deg at μ = 0.4, 0.1 deg for the wake) is
drawn with seeds 0 … n−1 and output-error ML (R known) is fitted to each draw. Compared with the
bound at the reference point (the truth, or for the constant-coefficient multiblade model the
noise-free estimate, i.e. the modelling-error bias of docs/models.md §2.3):

* **bias**: (mean estimate − reference) / σ_CRB per parameter;
* **scatter**: sample σ / σ_CRB;
* **coverage**: fraction of draws whose 95 % interval estimate ± 1.96 σ_CRB(estimate) holds the
  reference.

Every fit starts at the reference point (the estimate does not depend on the start once
Gauss-Newton has converged; starting there keeps the run short). Used by
``bench/monte_carlo.py`` (full run) and ``test/estimation/test_monte_carlo.py`` (CI run).
"""

from dataclasses import dataclass
import time

import numpy as np

from rotor_id.estimation.output_error import fit_output_error
from rotor_id.report import cases as C
from rotor_id.report.reproduce import case_data, iteration_experiment, run_iteration_case

#: Report cases of the Monte Carlo (ITERATION_CASES names).
MONTE_CARLO_CASES = ('single_blade_2par', 'single_blade_4par', 'multiblade_a', 'multiblade_b',
                     'multiblade_c', 'wake_progressing', 'wake_regressing', 'wake_7par')
Z95 = 1.959963984540054


@dataclass
class Reference:
    """Where the estimates should centre, and the bound there."""

    case: object
    names: list
    values: np.ndarray
    crb_std: np.ndarray
    kind: str            # 'truth' or 'modelling-error bias'


def reference(case_name):
    """Return the reference point and σ_CRB of a case: noise-free estimate (= truth or bias)."""
    case = next(c for c in C.ITERATION_CASES if c.name == case_name)
    noise_free = run_iteration_case(case, seed=None)
    est = noise_free.estimate
    scenario = C.SCENARIOS[case.scenario]
    kind = 'truth' if scenario.truth_model == scenario.model else 'modelling-error bias'
    # est.std is the bound at the reference with R = σ² (noise σ fixed in the fit)
    return Reference(case, list(est.names), est.values.copy(), est.std.copy(), kind)


def fit_draw(case_name, seed, ref_values):
    """
    Fit one noisy draw of a case, starting at the reference point.

    Returns (estimate values (k,), σ_CRB at the estimate (k,), iterations, converged).
    """
    case = next(c for c in C.ITERATION_CASES if c.name == case_name)
    scenario = C.SCENARIOS[case.scenario]
    k_par = len(case.unknowns)
    exp = iteration_experiment(case, case_data(case, seed))
    if exp.free_states():
        x0 = np.asarray(exp.x0_guess if exp.x0_guess is not None
                        else np.zeros(exp.model.n_states), dtype=float).copy()
        x0[exp.free_states()] = ref_values[k_par:]
        exp.x0_guess = x0
    est = fit_output_error([exp], list(case.unknowns),
                           guess=dict(zip(case.unknowns, ref_values[:k_par])),
                           noise_std=scenario.noise_std, max_iter=30, step_tol=1e-4)
    return est.values, est.std, est.iterations, est.converged


@dataclass
class MonteCarloResult:
    """Estimates of n noisy draws of one case and their statistics against the bound."""

    reference: Reference
    seeds: np.ndarray
    estimates: np.ndarray        # (n, k)
    crb_std_each: np.ndarray     # (n, k): σ_CRB at each estimate
    iterations: np.ndarray
    converged: np.ndarray
    seconds: float

    @property
    def n(self):
        """Return the number of draws."""
        return len(self.seeds)

    @property
    def bias_in_sigma(self):
        """(mean − reference) / σ_CRB per parameter."""
        return (self.estimates.mean(axis=0) - self.reference.values) / self.reference.crb_std

    @property
    def std_ratio(self):
        """Sample σ (n − 1 denominator) / σ_CRB per parameter."""
        return self.estimates.std(axis=0, ddof=1) / self.reference.crb_std

    @property
    def coverage(self):
        """Fraction of draws with |estimate − reference| ≤ 1.96 σ_CRB(estimate)."""
        inside = np.abs(self.estimates - self.reference.values) <= Z95 * self.crb_std_each
        return inside.mean(axis=0)

    def rows(self):
        """One table row per parameter: name, reference, σ_CRB, bias/σ, σ ratio, coverage."""
        return [(name, float(v), float(s), float(b), float(r), float(c))
                for name, v, s, b, r, c in zip(self.reference.names, self.reference.values,
                                               self.reference.crb_std, self.bias_in_sigma,
                                               self.std_ratio, self.coverage)]


def run_case(case_name, seeds, pool=None, progress=None):
    """Monte Carlo of one case over ``seeds`` (optionally on a multiprocessing pool)."""
    ref = reference(case_name)
    seeds = np.asarray(list(seeds), dtype=int)
    start = time.perf_counter()
    args = [(case_name, int(s), ref.values) for s in seeds]
    results = []
    if pool is None:
        for i, a in enumerate(args, 1):
            results.append(fit_draw(*a))
            if progress and (i % 50 == 0 or i == len(args)):
                progress(case_name, i, len(args), time.perf_counter() - start)
    else:
        # 16 tasks keep two to four workers evenly busy; much smaller chunks spend a large
        # part of the CPU on passing tasks
        chunk = max(8, len(args) // 16)
        for i, r in enumerate(pool.imap(_fit_draw_star, args, chunksize=chunk), 1):
            results.append(r)
            if progress and (i % 50 == 0 or i == len(args)):
                progress(case_name, i, len(args), time.perf_counter() - start)
    values = np.array([r[0] for r in results])
    std = np.array([r[1] for r in results])
    return MonteCarloResult(ref, seeds, values, std, np.array([r[2] for r in results]),
                            np.array([r[3] for r in results]), time.perf_counter() - start)


def _fit_draw_star(args):
    return fit_draw(*args)
