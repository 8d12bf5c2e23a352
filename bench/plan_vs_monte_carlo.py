#!/usr/bin/env python3
"""
Check that ``rotor-id plan`` predicts the accuracy ``rotor-id identify`` achieves.

For the report's dynamic-wake (μ = 0) and multiblade (μ = 0.4) cases, the report's transient
(progressing stirring, ω̇ = 0.1/π, 1.5°, the report's t0, 12 units of t = 1.91 revolutions) is
planned with :mod:`rotor_id.planning` (config/plan_wake.yaml, config/plan_multiblade.yaml) and
then run N times in simulation with independent per-blade sensor noise; each noisy record is
identified by :func:`rotor_id.pipeline.identify`. The spread of the estimates is compared with
the predicted Cramér-Rao σ, per unknown (ratio and its 95 % interval) and pooled over all
unknowns (χ² statistic of the predicted covariance).

    source tools/env.sh && python bench/plan_vs_monte_carlo.py [--seeds 200]
        [--json OUT.json] [--figure OUT.png] [--markdown OUT.md]

Writes bench/results/plan_vs_monte_carlo.{md,json,png} by default (machine, date, numbers).
"""

import argparse
import contextlib
import datetime
import io
import json
import math
import os
from pathlib import Path
import platform
import sys
import time

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
from rotor_id import planning  # noqa: E402
from scipy import stats  # noqa: E402

CASES = {
    'wake': 'config/plan_wake.yaml',
    'multiblade': 'config/plan_multiblade.yaml',
}
REPORT_DURATION_REV = 12.0 / (2.0 * math.pi)     # the report's record t0 … t0 + 12
TOLERANCE = 0.15     # predicted σ within 15 % of the Monte Carlo's sample σ


def report_candidate(plan):
    """Return the report's transient: progressing, ω̇ = 0.1/π, 1.5°, report t0, 12 units."""
    return planning.Candidate('progressing', planning.PROGRESSING_OMEGADOT,
                              planning.DEFAULT_AMPLITUDE_RAD,
                              planning.default_t0(plan.description.rotor.advance_ratio),
                              REPORT_DURATION_REV)


def ratio_interval(n, level=0.95):
    """Interval of spread/σ for N Gaussian samples when the prediction is right (χ²(N−1))."""
    lo, hi = stats.chi2.ppf([(1 - level) / 2, (1 + level) / 2], n - 1)
    return math.sqrt(lo / (n - 1)), math.sqrt(hi / (n - 1))


def run_case(name, seeds):
    """Plan, Monte Carlo, comparison for one case; returns a JSON-ready dict."""
    plan = planning.load_plan(REPO / CASES[name])
    cand = report_candidate(plan)
    started = time.perf_counter()

    def show(info):
        if info['index'] % 25 == 0 or info['index'] == info['of']:
            print(f'  {name}: identify {info["index"]}/{info["of"]} '
                  f'({info["elapsed"]:.1f} s)', file=sys.stderr, flush=True)

    mc = planning.monte_carlo(plan, cand, range(seeds), progress=show)
    n = int(mc.converged.sum())
    ratio = mc.ratio()
    lo, hi = ratio_interval(n)
    d, dof = mc.pooled_statistic()
    bias = (mc.estimates[mc.converged].mean(axis=0) - mc.truth) / mc.predicted_std
    out = {
        'case': name, 'config': CASES[name], 'candidate': cand.as_json(),
        'seeds': seeds, 'converged': n, 'unknowns': mc.names,
        'truth': mc.truth.tolist(),
        'predicted_std': mc.predicted_std.tolist(),
        'monte_carlo_std': mc.spread().tolist(),
        'ratio': ratio.tolist(),
        'ratio_95_interval_if_exact': [lo, hi],
        'within_15_percent': bool(np.all(np.abs(ratio - 1) <= TOLERANCE)),
        'mean_bias_in_predicted_std': bias.tolist(),
        'pooled_chi2': d, 'pooled_dof': dof,
        'pooled_variance_ratio': d / dof,
        'pooled_p_value_two_sided': float(2 * min(stats.chi2.cdf(d, dof),
                                                  stats.chi2.sf(d, dof))),
        'elapsed_s': time.perf_counter() - started,
        'estimates': mc.estimates.tolist(),
    }
    return out


def print_case(res):
    """Plain-text table of one case."""
    print(f'\n{res["case"]}: {res["converged"]}/{res["seeds"]} runs converged, '
          f'{res["elapsed_s"]:.1f} s; if the prediction is exact the ratio lies in '
          f'[{res["ratio_95_interval_if_exact"][0]:.3f}, '
          f'{res["ratio_95_interval_if_exact"][1]:.3f}] with 95 % probability')
    print(f'{"unknown":<12} {"truth":>10} {"predicted σ":>12} {"MC spread":>12} {"ratio":>7} '
          f'{"bias/σ":>7}')
    for i, n in enumerate(res['unknowns']):
        print(f'{n:<12} {res["truth"][i]:10.5g} {res["predicted_std"][i]:12.4g} '
              f'{res["monte_carlo_std"][i]:12.4g} {res["ratio"][i]:7.3f} '
              f'{res["mean_bias_in_predicted_std"][i]:7.3f}')
    print(f'pooled: χ² = {res["pooled_chi2"]:.1f} on {res["pooled_dof"]} dof '
          f'(variance ratio {res["pooled_variance_ratio"]:.3f}, two-sided p = '
          f'{res["pooled_p_value_two_sided"]:.3f}); every σ within 15 %: '
          f'{res["within_15_percent"]}')


def write_figure(results, path):
    """Histograms of the estimates with the predicted Gaussian (σ from the plan)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    n_cols = max(len(r['unknowns']) for r in results)
    fig, axes = plt.subplots(len(results), n_cols, figsize=(4 * n_cols, 3.2 * len(results)),
                             squeeze=False, constrained_layout=True)
    for row, res in zip(axes, results):
        est = np.array(res['estimates'])
        for i, name in enumerate(res['unknowns']):
            ax = row[i]
            x = est[:, i]
            ax.hist(x, bins=25, density=True, color='0.75', label='identify (MC)')
            s = res['predicted_std'][i]
            grid = np.linspace(x.mean() - 4 * s, x.mean() + 4 * s, 200)
            ax.plot(grid, stats.norm.pdf(grid, x.mean(), s), 'C0', label='plan: CRB σ')
            ax.axvline(res['truth'][i], color='k', lw=0.8, ls=':')
            ax.set_title(f'{res["case"]}: {name}\nMC/predicted σ = {res["ratio"][i]:.3f}',
                         fontsize=9)
        row[0].legend(fontsize=7)
        for ax in row[len(res['unknowns']):]:
            ax.axis('off')
    fig.suptitle(f'identify spread vs planned Cramér-Rao σ ({results[0]["seeds"]} seeds)',
                 fontsize=10)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    """Run the comparison; exit 1 when a σ disagrees by more than 15 %."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seeds', type=int, default=200, help='noisy runs per case (≥ 100)')
    parser.add_argument('--cases', nargs='+', choices=sorted(CASES), default=list(CASES))
    out = REPO / 'bench' / 'results'
    parser.add_argument('--json', default=str(out / 'plan_vs_monte_carlo.json'))
    parser.add_argument('--figure', default=str(out / 'plan_vs_monte_carlo.png'))
    parser.add_argument('--markdown', default=str(out / 'plan_vs_monte_carlo.md'))
    args = parser.parse_args(argv)
    results = [run_case(name, args.seeds) for name in args.cases]
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        for res in results:
            print_case(res)
    print(text.getvalue())
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(results, indent=1))
    Path(args.markdown).write_text(
        f'# plan vs Monte Carlo of identify (bench/plan_vs_monte_carlo.py)\n\n'
        f'{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, '
        f'{platform.node()}, {platform.processor() or platform.machine()}, '
        f'{os.cpu_count()} cores; `python bench/plan_vs_monte_carlo.py --seeds {args.seeds}`'
        f'\n\n```{text.getvalue()}```\n')
    write_figure(results, args.figure)
    print(f'JSON: {args.json}\nfigure: {args.figure}\nsummary: {args.markdown}')
    return 0 if all(r['within_15_percent'] for r in results) else 1


if __name__ == '__main__':
    sys.exit(main())
