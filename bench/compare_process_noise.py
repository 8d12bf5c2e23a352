#!/usr/bin/env python3
"""
Output error vs filter error vs augmented-state EKF under system noise (report Ch.2 eq. 29a).

The report's μ = 0 dynamic-wake case: progressing stirring from t0 = 70, window 70-82 sampled at
Δt = 0.1 (121 samples), measurement noise σ = 0.05 on β_m1, β_m2 (eq. 30: the report's
value for its system-noise experiment, "more representative of the expected measurement
errors"; ``--sigma-m`` changes it), true A = .5,
AL/τ = .25, 1/τ = .125, starting estimates .4/.2/.25. System noise as the report generated it:
a Gaussian sequence of standard deviation σ_V on the λI′, λII′ rows, held over each sample
interval (``simulate(..., forcing=...)``), σ_V = 0, .05, .1, .2, .3. The rotor is in trim
before stirring, so every method starts from the equilibrium at its current parameters
(output and filter error: ``initial_state='equilibrium'``; EKF: its least-squares start).

For each σ_V and method: bias, scatter and RMS error of each parameter over the seeds, the mean
claimed σ (Cramér-Rao bound, or the EKF's filter covariance, which is not a confidence
measure), the coverage of ±1.96 claimed σ, convergence, and CPU time per fit. Filter error
appears twice: with its default bounds (``bounds='marginal'``: σ_V from the restricted
likelihood and the bounds integrated over it) and as the plain joint ML estimate with the
Cramér-Rao bound at its optimum (``fit_filter_error_ml``, "conditional bound").

    python bench/compare_process_noise.py            # 100 seeds, 2 worker processes
    python bench/compare_process_noise.py --seeds 20 --workers 1
    python bench/compare_process_noise.py --sigma-m 0.01 --out /tmp/pn_001.md

Writes bench/results/process_noise.md, process_noise.json (the summary) and process_noise.png
(RMS error and coverage against σ_V for each method and parameter).
"""

import argparse
import datetime
import json
import math
import multiprocessing
import os
from pathlib import Path
import platform
import sys
import time

# one BLAS thread per worker: the matrices are tiny and threads only contend (2-core machine)
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from rotor_id.estimation import kernels  # noqa: E402
from rotor_id.estimation.ekf import fit_ekf  # noqa: E402
from rotor_id.estimation.filter_error import (fit_filter_error, fit_filter_error_ml,  # noqa: E402,E501
                                              PROCESS_NOISE)
from rotor_id.estimation.output_error import Experiment, fit_output_error  # noqa: E402
from rotor_id.estimation.simulate import simulate  # noqa: E402
from rotor_id.physics.models import MultibladeWake, RotorConstants  # noqa: E402
from rotor_id.physics.stirring import StirringSchedule  # noqa: E402

SIGMA_V = (0.0, 0.05, 0.1, 0.2, 0.3)
SIGMA_M = 0.05
UNKNOWNS = ('A', 'AL_over_tau', 'inv_tau')
GUESS = {'A': 0.4, 'AL_over_tau': 0.2, 'inv_tau': 0.25}
METHODS = ('output error', 'filter error', 'filter error, conditional bound', 'EKF')

MODEL = MultibladeWake(RotorConstants(advance_ratio=0.0))
P_TRUE = MODEL.nominal()
SCHED = StirringSchedule(collective=0.0, amplitude=1.5, omegadot=-0.1 / math.pi, t0=70.0)
T = 70.0 + 0.1 * np.arange(121)
X0 = MODEL.equilibrium(T[:1], P_TRUE, SCHED(T[:1]))


def make_data(seed, sigma_v):
    """One record: held system noise σ_V on the λ rows, measurement noise σ = SIGMA_M."""
    rng = np.random.default_rng([seed, int(round(1000 * sigma_v))])
    forcing = np.zeros((T.size - 1, 6))
    forcing[:, 4:] = sigma_v * rng.standard_normal((T.size - 1, 2))
    y = simulate(MODEL, P_TRUE, SCHED, T, X0, forcing=forcing).y
    return y + SIGMA_M * rng.standard_normal(y.shape)


def run_one(job):
    """Fit one record with the three methods; return errors, claimed σ, convergence, CPU."""
    seed, sigma_v, sigma_m = job
    global SIGMA_M
    SIGMA_M = sigma_m                  # the worker's copy of the module
    y = make_data(seed, sigma_v)
    exp = Experiment(MODEL, SCHED, T, y, initial_state='equilibrium')
    out = {}
    fits = {
        'output error': lambda: fit_output_error([exp], list(UNKNOWNS), guess=GUESS,
                                                 noise_std=SIGMA_M),
        'filter error': lambda: fit_filter_error([exp], list(UNKNOWNS), guess=GUESS,
                                                 noise_std=SIGMA_M, noise_model='held'),
        'filter error, conditional bound': lambda: fit_filter_error_ml(
            [exp], list(UNKNOWNS), guess=GUESS, noise_std=SIGMA_M, noise_model='held'),
        'EKF': lambda: fit_ekf([exp], list(UNKNOWNS), guess=GUESS, noise_std=SIGMA_M),
    }
    for method, fit in fits.items():
        t0 = time.process_time()
        try:
            est = fit()
        except (ValueError, np.linalg.LinAlgError) as exc:       # counted as a failure
            out[method] = {'failed': str(exc), 'cpu': time.process_time() - t0}
            continue
        cpu = time.process_time() - t0
        idx = [est.names.index(n) for n in UNKNOWNS]
        out[method] = {'error': est.values[idx] - P_TRUE, 'std': est.std[idx],
                       'converged': bool(est.converged), 'cpu': cpu,
                       'sigma_v': (est.value(PROCESS_NOISE) if PROCESS_NOISE in est.names
                                   else math.nan)}
    return sigma_v, out


def summarise(results, sigma_v, method):
    """Rows (parameter, bias, scatter, RMS, mean claimed σ, coverage) and totals."""
    runs = [r[method] for s, r in results if s == sigma_v and 'error' in r[method]]
    failed = sum(1 for s, r in results if s == sigma_v and 'error' not in r[method])
    err = np.array([r['error'] for r in runs])
    std = np.array([r['std'] for r in runs])
    rows = []
    for k, name in enumerate(UNKNOWNS):
        rows.append((name, err[:, k].mean(), err[:, k].std(ddof=1),
                     math.sqrt(np.mean(err[:, k]**2)), np.mean(std[:, k]),
                     np.mean(np.abs(err[:, k]) <= 1.96 * std[:, k])))
    conv = np.mean([r['converged'] for r in runs])
    cpu = np.mean([r['cpu'] for r in runs])
    sv = np.nanmean([r['sigma_v'] for r in runs]) if method.startswith('filter') else math.nan
    return rows, conv, cpu, failed, len(runs), sv


def plot(summary, path, sigma_m):
    """RMS error and coverage against σ_V, one column per parameter."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, len(UNKNOWNS), figsize=(12, 6.5), sharex=True)
    for k, name in enumerate(UNKNOWNS):
        for method, marker in zip(METHODS, 'osvd'):
            rows = [summary[f'{sv:g}'][method]['rows'][k] for sv in SIGMA_V]
            axes[0, k].plot(SIGMA_V, [r['rms'] for r in rows], marker=marker, label=method)
            axes[0, k].plot(SIGMA_V, [r['claimed'] for r in rows], marker=marker, ls=':',
                            color=axes[0, k].lines[-1].get_color())
            axes[1, k].plot(SIGMA_V, [r['coverage'] for r in rows], marker=marker,
                            label=method)
        axes[0, k].set_title(f'{name} (true {P_TRUE[k]:g})')
        axes[0, k].set_ylabel('RMS error (solid), claimed σ (dotted)')
        axes[1, k].axhline(0.95, color='k', lw=0.8)
        axes[1, k].set_ylim(0, 1.02)
        axes[1, k].set_ylabel('coverage of ±1.96 claimed σ')
        axes[1, k].set_xlabel('system noise σ_V (report eq. 29a)')
    axes[0, 0].legend()
    fig.suptitle(f'Wake case, measurement σ = {sigma_m:g}: output error vs filter error vs EKF')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def machine():
    """One line describing the machine."""
    cpu = platform.processor() or platform.machine()
    try:
        with open('/proc/cpuinfo') as f:
            names = [ln.split(':', 1)[1].strip() for ln in f if ln.startswith('model name')]
        if names:
            cpu = f'{names[0]} ({len(names)} logical CPUs)'
    except OSError:
        pass
    return (f'{cpu}; Python {platform.python_version()}, numpy {np.__version__}; '
            f'{platform.system()} {platform.release()}')


def main(argv=None):
    """Run the comparison, print the table and write bench/results/process_noise.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--seeds', type=int, default=100)
    parser.add_argument('--workers', type=int, default=2)
    parser.add_argument('--sigma-m', type=float, default=SIGMA_M,
                        help="measurement noise σ (default: the report's .05)")
    parser.add_argument('--out', default=str(REPO / 'bench' / 'results' / 'process_noise.md'))
    args = parser.parse_args(argv)
    jobs = [(seed, sv, args.sigma_m) for sv in SIGMA_V for seed in range(args.seeds)]
    start = time.perf_counter()
    load_start = os.getloadavg()[0]
    results = []
    kernels.prefer()                        # compiled simulator and filter, before the fork
    with multiprocessing.Pool(args.workers) as pool:
        for i, res in enumerate(pool.imap_unordered(run_one, jobs, chunksize=4), 1):
            results.append(res)
            if i % 25 == 0 or i == len(jobs):
                print(f'  {i}/{len(jobs)} records, {len(METHODS)} methods each, '
                      f'{time.perf_counter() - start:.0f} s',
                      file=sys.stderr, flush=True)
    wall = time.perf_counter() - start
    lines = ['# Output error, filter error and augmented-state EKF under system noise', '',
             f'{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, '
             f'`python bench/compare_process_noise.py --seeds {args.seeds} '
             f'--workers {args.workers} --sigma-m {args.sigma_m:g}` ({wall:.0f} s wall).', '',
             f'Machine: {machine()}; load average {load_start:.1f} at the start, '
             f'{os.getloadavg()[0]:.1f} at the end (2 cores shared: CPU times are the '
             f'comparable figures).', '',
             'Report Ch.2 wake case (μ = 0, progressing, t = 70-82, Δt = 0.1, measurement '
             f'σ = {args.sigma_m:g}, true A/AL/τ/1/τ = .5/.25/.125, start .4/.2/.25). '
             'System noise σ_V: '
             'a Gaussian sequence held over each sample interval on the λI′, λII′ rows '
             '(eq. 29a). Initial state: equilibrium at the current parameters. '
             '"claimed σ" is the Cramér-Rao bound (output error; filter error, conditional '
             'bound), the bound integrated over σ_V (filter error, its default) or the EKF '
             'covariance (not a confidence measure); coverage = fraction of |error| ≤ 1.96 '
             'claimed σ; CPU = process time per fit. Both filter-error rows are the same '
             'joint ML estimates; "filter error" has the default bounds (the Cramér-Rao '
             'bounds of a σ_V grid mixed with weights from the restricted likelihood of σ_V), '
             '"conditional bound" the Cramér-Rao bound at the joint optimum. The extended '
             'filter is a biased parameter estimator in general (Ljung 1979); its biases '
             'here are measured, their size not analysed further.',
             '']
    summary = {}
    for sv in SIGMA_V:
        summary[f'{sv:g}'] = {}
        lines += [f'## σ_V = {sv:g}', '',
                  '| method | parameter | bias | scatter | RMS | claimed σ | coverage |',
                  '|---|---|---|---|---|---|---|']
        notes = []
        for method in METHODS:
            rows, conv, cpu, failed, n, sv_hat = summarise(results, sv, method)
            summary[f'{sv:g}'][method] = {
                'rows': [dict(zip(('parameter', 'bias', 'scatter', 'rms', 'claimed',
                                   'coverage'), (r[0],) + tuple(float(v) for v in r[1:])))
                         for r in rows],
                'converged': float(conv), 'cpu_s': float(cpu), 'failed': failed, 'fits': n,
                'sigma_v_hat': None if math.isnan(sv_hat) else float(sv_hat)}
            for name, bias, spread, rms, claimed, cov in rows:
                lines.append(f'| {method} | {name} | {bias:+.4f} | {spread:.4f} | {rms:.4f} | '
                             f'{claimed:.4f} | {cov:.2f} |')
            note = (f'{method}: {n} fits, {conv:.0%} converged, {failed} failed, '
                    f'CPU {1000 * cpu:.0f} ms per fit')
            if method.startswith('filter error'):
                note += f', mean σ̂_V {sv_hat:.3f}'
            notes.append(note)
        lines += [''] + [f'- {n}' for n in notes] + ['']
    out = Path(args.out)
    lines += [f'![RMS error and coverage against σ_V]({out.with_suffix(".png").name})', '']
    text = '\n'.join(lines)
    print(text)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text + '\n')
    out.with_suffix('.json').write_text(json.dumps(summary, indent=1) + '\n')
    plot(summary, out.with_suffix('.png'), args.sigma_m)
    print(f'\nwrote {out}, {out.with_suffix(".json").name}, {out.with_suffix(".png").name}',
          file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
