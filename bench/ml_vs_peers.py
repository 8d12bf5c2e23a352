"""
Output-error ML per report case against the two peers of :mod:`peers`.

For each report case (single blade, constant-coefficient multiblade with identified deflections,
3- and 7-parameter dynamic wake) one seeded noisy data set (σ of the report) is fitted from the
report's starting values by

* ours: :func:`rotor_id.estimation.output_error.fit_output_error` (analytic sensitivities,
  Gauss-Newton, default tolerances);
* peer (b): ``least_squares`` + 2-point finite differences on our simulator;
* peer (a): ``least_squares`` + 2-point finite differences on ``solve_ivp`` of a hand-written
  right-hand side, at rtol 1e-6 / atol 1e-9 (the loosest setting that lands on our optimum to
  1e-4 σ; with solve_ivp's default rtol 1e-3 the optimum moves by several 0.01 σ, timed too).

Every round fits the same record, as every round of the peers does; our simulator keeps the
record's prepared plan (:class:`rotor_id.estimation.simulate.TimeInvariantPlan`) from one fit
to the next, in ours and in peer (b) alike. The first fit of a record (a new, equal input
schedule object each time, so nothing kept from an earlier fit applies) is timed beside it.

The three are timed interleaved (median of ``--repeat`` rounds), wall and CPU time, with one
BLAS thread (OpenBLAS's idle threads spin and would be charged to the next timed call). The
optima must agree: the largest difference, in units of our Cramér-Rao σ, is printed and
checked (< 1e-3 σ).

For the 7-parameter wake case the compiled whole fit (``gn_fit``, one call) is also timed alone
with the arguments our fit passes it, in the same rounds, which splits our time into the compiled
fit and the Python around it.

Our simulator runs its compiled kernel (:mod:`rotor_id.estimation.kernels`, loaded before the
timing, its load time printed), in ours and in peer (b) alike. Beside each of our times stands
the compute limit: the multiply-adds of the sensitivity recursion that the fit needs at the
least (one matrix [x S] product per sample and simulation: (T−1)·n²·(k+1)), at the
multiply-add rate of a 128×128 matrix product (best of 200) measured in the same run.

Run: ``python bench/ml_vs_peers.py [--repeat N] [--seed S]``.
"""

import argparse
import copy
import dataclasses
import os
import sys
import time

# One BLAS thread: every matrix here is tiny, and OpenBLAS's helper threads keep spinning after
# a peer's call, which process_time() then charges to whatever is timed next.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

from common import (figure_path, fmt_time, markdown_table, pyplot, say,  # noqa: E402
                    time_interleaved, write_results)
import numpy as np  # noqa: E402
import peers  # noqa: E402

from rotor_id.estimation import kernels  # noqa: E402
from rotor_id.estimation.output_error import fit_output_error  # noqa: E402
from rotor_id.report import cases as C  # noqa: E402
from rotor_id.report.reproduce import case_data, iteration_experiment  # noqa: E402

#: (label, report iteration case) benchmarked, simplest first.
CASES = (
    ('single blade (γ, δ)', 'single_blade_2par'),
    ('multiblade, const. coeff. (γ, δ, β0, βI, βII at t0)', 'multiblade_c'),
    ('wake, 3 parameters (A, AL/τ, 1/τ)', 'wake_progressing'),
    ('wake, 7 parameters (+ βI, βII, λI, λII at t0)', 'wake_7par'),
)
AGREEMENT_SIGMA = 1e-3
#: Targets of the 7-parameter wake fit: its time, and its speed against the peers.
WAKE7_LIMIT_S = 1e-3
WAKE7_VS_A = 500.0
WAKE7_VS_B = 3.0
AFTERNOON_TOL = (1e-6, 1e-9)
DEFAULT_TOL = (1e-3, 1e-6)


def iteration_case(name):
    """Return the :class:`rotor_id.report.cases.IterationCase` called ``name``."""
    return next(c for c in C.ITERATION_CASES if c.name == name)


def experiment_of(case, y):
    """Experiment and starting θ of an iteration case (report start, report initial states)."""
    exp = iteration_experiment(case, y)
    free = exp.free_states()
    theta0 = [case.start[n] for n in case.unknowns]
    if free:
        theta0 += list(np.asarray(exp.x0_guess)[free])
    x0_fixed = (np.zeros(exp.model.n_states) if isinstance(exp.initial_state, str)
                else np.asarray(exp.initial_state, dtype=float))
    return exp, np.array(theta0, dtype=float), x0_fixed, free


def bench_case(label, case_name, seed, repeat, rate):
    """Time ours and the peers on one case; return a dict of results (rate: multiply-adds/s)."""
    case = iteration_case(case_name)
    scenario = C.SCENARIOS[case.scenario]
    y = case_data(case, seed)
    exp, theta0, x0_fixed, free = experiment_of(case, y)
    model = exp.model
    unknowns = list(case.unknowns)
    param_index = [model.parameter_names.index(n) for n in unknowns]
    sigma = scenario.noise_std
    rhs = peers.afternoon_model(scenario)

    def ours():
        return fit_output_error([exp], unknowns, guess=dict(case.start), noise_std=sigma)

    def ours_first():
        inputs = (dataclasses.replace(exp.inputs) if dataclasses.is_dataclass(exp.inputs)
                  else copy.copy(exp.inputs))
        return fit_output_error([dataclasses.replace(exp, inputs=inputs)], unknowns,
                                guess=dict(case.start), noise_std=sigma)

    def fd_ours():
        return peers.fit_fd_ours(model, model.nominal(), param_index, exp.inputs, exp.t, y,
                                 sigma, theta0, x0_fixed, free)

    def afternoon():
        return peers.fit_afternoon(rhs, exp.t, y, sigma, theta0, x0_fixed, free,
                                   rtol=AFTERNOON_TOL[0], atol=AFTERNOON_TOL[1])

    def afternoon_default():
        return peers.fit_afternoon(rhs, exp.t, y, sigma, theta0, x0_fixed, free,
                                   rtol=DEFAULT_TOL[0], atol=DEFAULT_TOL[1])

    say(f'{label}: {len(theta0)} unknowns, {exp.t.size} samples, {repeat} interleaved rounds')
    n_states, n_sens = model.n_states, len(theta0)
    functions = {'ours': ours, 'ours_first': ours_first, 'fd_ours': fd_ours,
                 'afternoon': afternoon, 'afternoon_default': afternoon_default}
    kernel_call = compiled_fit_call(ours)
    if kernel_call is not None:         # the compiled part of ours alone, timed beside it
        functions['ours_kernel'] = kernel_call
    timing = time_interleaved(functions, repeat=repeat)
    est = timing['ours']['result']
    first = timing['ours_first']['result']
    if not np.array_equal(first.values, est.values):
        raise RuntimeError(f'{case_name}: the first fit of a record and a refit differ')
    sims = {}
    dev = {}
    for name in ('fd_ours', 'afternoon', 'afternoon_default'):
        theta, res = timing[name]['result']
        dev[name] = float(np.max(np.abs(theta - est.values) / est.std))
        sims[name] = res.nfev + res.njev * len(theta0)
    out = {'label': label, 'case': case_name, 'k': len(theta0), 'samples': exp.t.size,
           'names': est.names, 'ours': est.values, 'ours_iterations': est.iterations,
           'ours_converged': est.converged, 'std': est.std,
           'fd_ours_theta': timing['fd_ours']['result'][0],
           'afternoon_theta': timing['afternoon']['result'][0],
           'afternoon_default_theta': timing['afternoon_default']['result'][0],
           'dev': dev, 'sims': sims,
           'time': {k: v['median'] for k, v in timing.items()},
           'spread': {k: (v['min'], v['max']) for k, v in timing.items()},
           'cpu': {k: v['cpu'] for k, v in timing.items()},
           'macs': (est.iterations + 1) * (exp.t.size - 1) * n_states**2 * (n_sens + 1)}
    t = out['time']
    say(f'  ours {fmt_time(t["ours"])} (CPU {fmt_time(out["cpu"]["ours"])}, {est.iterations} it; '
        f'compute limit {fmt_time(out["macs"] / rate)}), (b) {fmt_time(t["fd_ours"])}, '
        f'(a) {fmt_time(t["afternoon"])}: (a)/ours {t["afternoon"] / t["ours"]:.1f}x, '
        f'(b)/ours {t["fd_ours"] / t["ours"]:.1f}x; optima differ by '
        f'{dev["afternoon"]:.1e} σ (a), {dev["fd_ours"]:.1e} σ (b)')
    return out


def compiled_fit_call(fit):
    """
    Return a call of the compiled whole fit (``gn_fit``) with the arguments ``fit()`` gives it.

    None where ``fit`` does not take the one-call path (numpy simulator, or a problem the
    compiled fit does not cover). Timing it beside ``fit`` splits ours into the compiled fit
    (start, iterations, final M and M⁻¹) and the Python around it (set-up, Estimate).
    """
    module = kernels.affine_kernels()
    if module is None:
        return None
    kernel, captured = module.gn_fit, []

    def spy(*args):
        captured.append(args)
        return kernel(*args)
    module.gn_fit = spy
    try:
        fit()
    finally:
        module.gn_fit = kernel
    if not captured:
        return None
    args = captured[0]
    return lambda: kernel(*args)


def multiply_add_rate(size=128, repeat=200):
    """Multiply-adds per second of a size×size matrix product (best of ``repeat``)."""
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((2, size, size))
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return size**3 / best


def report(results, seed, repeat, rate, kernel_status):
    """Markdown body of the results file."""
    rows = []
    for r in results:
        t = r['time']
        f = r['cpu']                                            # CPU-time medians
        rows.append([
            r['label'], r['k'], r['samples'],
            f'{fmt_time(t["ours"])}, CPU {fmt_time(f["ours"])} ({r["ours_iterations"]} it; '
            f'limit {fmt_time(r["macs"] / rate)}, {t["ours"] * rate / r["macs"]:.0f}×); '
            f'first fit of a record {fmt_time(t["ours_first"])}, CPU '
            f'{fmt_time(f["ours_first"])}',
            f'{fmt_time(t["fd_ours"])} ({r["sims"]["fd_ours"]} sims)',
            f'{fmt_time(t["afternoon"])} ({r["sims"]["afternoon"]} solves)',
            f'**{t["afternoon"] / t["ours"]:.1f}×** ({f["afternoon"] / f["ours"]:.1f}×)',
            f'**{t["fd_ours"] / t["ours"]:.2f}×** ({f["fd_ours"] / f["ours"]:.2f}×)',
            f'{fmt_time(t["afternoon_default"])} '
            f'({t["afternoon_default"] / t["ours"]:.1f}×, off by '
            f'{r["dev"]["afternoon_default"]:.2g} σ)'])
    table = markdown_table(
        ['case', 'unknowns', 'samples',
         'ours: output-error ML (compute limit, ours ÷ limit)', '(b) FD on our simulator',
         '(a) solve_ivp + FD', '(a) / ours (CPU time)', '(b) / ours (CPU time)',
         '(a) at solve_ivp default rtol 1e-3 (not the same optimum)'], rows)
    optima = []
    for r in results:
        for i, name in enumerate(r['names']):
            optima.append([r['case'] if i == 0 else '', name, f'{r["ours"][i]:.6f}',
                           f'{r["fd_ours_theta"][i]:.6f}', f'{r["afternoon_theta"][i]:.6f}',
                           f'{r["std"][i]:.4f}'])
        optima.append(['', 'max |Δ| / σ', '', f'{r["dev"]["fd_ours"]:.1e}',
                       f'{r["dev"]["afternoon"]:.1e}', ''])
    opt_table = markdown_table(['case', 'parameter', 'ours', '(b)', '(a)', 'CRB σ'], optima)
    wake7 = next(r for r in results if r['case'] == 'wake_7par')
    ratio_a = wake7['time']['afternoon'] / wake7['time']['ours']
    ratio_b = wake7['time']['fd_ours'] / wake7['time']['ours']
    cpu_a = wake7['cpu']['afternoon'] / wake7['cpu']['ours']
    cpu_b = wake7['cpu']['fd_ours'] / wake7['cpu']['ours']
    ours7 = wake7['time']['ours']
    ours7_cpu = wake7['cpu']['ours']
    if 'ours_kernel' in wake7['cpu']:
        kernel7 = wake7['cpu']['ours_kernel']
        iterations = wake7['ours_iterations']
        split = (f' Of our CPU time, the compiled fit (one call: start, {iterations} iterations, '
                 f'final M and M⁻¹; {iterations + 1} simulations with sensitivities) takes '
                 f'{fmt_time(kernel7)} ({kernel7 / ours7_cpu:.0%}), timed alone beside it; the '
                 'Python around it (problem set-up, the kept plan, Estimate) the other '
                 f'{fmt_time(ours7_cpu - kernel7)}. For ≥ {WAKE7_VS_A:.0f}× (a) at the (a) of '
                 f'this run the whole fit may take '
                 f'{fmt_time(wake7["cpu"]["afternoon"] / WAKE7_VS_A)} CPU.')
    else:
        split = ''
    first7 = wake7['time']['ours_first']
    first7_cpu = wake7['cpu']['ours_first']
    if kernel_status['loaded']:
        kernel_text = f'compiled (numba; loaded in {fmt_time(kernel_status["load_seconds"])})'
    else:
        kernel_text = f'numpy ({kernel_status["error"] or "ROTOR_ID_KERNELS=numpy"})'

    verdict = (f'7-parameter wake case: ours is {ratio_a:.1f}× faster than (a) (target '
               f'≥ 20×: {"met" if ratio_a >= 20 else "MISSED"}) and {ratio_b:.2f}× faster than '
               f'(b) (target > 1: {"met" if ratio_b > 1 else "MISSED"}); on CPU time '
               f'{cpu_a:.1f}× and {cpu_b:.2f}×.\n\n'
               f'Targets of the fit: {fmt_time(ours7)} wall, {fmt_time(ours7_cpu)} CPU '
               f'(≤ {fmt_time(WAKE7_LIMIT_S)}: wall '
               f'{"met" if ours7 <= WAKE7_LIMIT_S else "MISSED"}, CPU '
               f'{"met" if ours7_cpu <= WAKE7_LIMIT_S else "MISSED"}), CPU {cpu_a:.0f}× (a) '
               f'(≥ {WAKE7_VS_A:.0f}×: {"met" if cpu_a >= WAKE7_VS_A else "MISSED"}; wall '
               f'{ratio_a:.0f}×), CPU {cpu_b:.2f}× (b) (≥ {WAKE7_VS_B:.0f}×: '
               f'{"met" if cpu_b >= WAKE7_VS_B else "MISSED"}; wall {ratio_b:.2f}×); the ratios '
               'are judged on CPU time, which a loaded machine does not inflate for the '
               'slower peer as it does wall time. Compute limit '
               f'{fmt_time(wake7["macs"] / rate)} ({wake7["macs"]:,} multiply-adds at '
               f'{rate / 1e9:.1f} G/s, a 128×128 matrix product here, best of 200); ours takes '
               f'{ours7 * rate / wake7["macs"]:.0f}× that. The first fit of a record takes '
               f'{fmt_time(first7)} wall, {fmt_time(first7_cpu)} CPU (≤ '
               f'{fmt_time(WAKE7_LIMIT_S)}: {"met" if first7 <= WAKE7_LIMIT_S else "MISSED"}; '
               f'(a) / first fit {wake7["time"]["afternoon"] / first7:.0f}×, CPU '
               f'{wake7["cpu"]["afternoon"] / first7_cpu:.0f}×).{split}\n\n'
               f'Simulator kernel for ours and (b): {kernel_text}.')
    return (f'## Timings (median of {repeat} interleaved rounds; data: report σ, seed {seed})\n\n'
            f'{table}\n\n{verdict}\n\n'
            '"sims" counts simulations of (b) = residual evaluations + Jacobian evaluations × '
            'unknowns (2-point differences); ours does one simulation with sensitivities per '
            'iteration plus one at the start. Peer (a) is least_squares over solve_ivp (RK45, '
            f'rtol {AFTERNOON_TOL[0]:g}, atol {AFTERNOON_TOL[1]:g}) of the right-hand sides '
            'typed in again from docs/models.md (bench/peers.py).\n\n'
            f'## Optima (they must agree to {AGREEMENT_SIGMA:g} σ)\n\n{opt_table}\n')


def plot(results, path):
    """Bar chart of the three methods' median times per case (log scale)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4))
    labels = [r['case'] for r in results]
    x = np.arange(len(results))
    for i, (key, name) in enumerate((('ours', 'ours: output-error ML'),
                                     ('fd_ours', '(b) least_squares + FD, our simulator'),
                                     ('afternoon', '(a) least_squares + FD, solve_ivp'))):
        ax.bar(x + (i - 1) * 0.27, [r['time'][key] * 1e3 for r in results], 0.27, label=name)
    for xi, r in zip(x, results):
        ax.text(xi + 0.27, r['time']['afternoon'] * 1e3 * 1.1,
                f'{r["time"]["afternoon"] / r["time"]["ours"]:.0f}×', ha='center', fontsize=8)
    ax.set_yscale('log')
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel('time to the optimum [ms] (median)')
    ax.set_title('Identification time per report case (121 samples, same optimum)', fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    """Run the benchmark, print the tables, write bench/results/ml_vs_peers.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--repeat', type=int, default=5, help='interleaved timing rounds')
    parser.add_argument('--seed', type=int, default=1, help='noise seed of the data')
    parser.add_argument('--no-write', action='store_true', help='do not write results/')
    args = parser.parse_args(argv)
    if kernels.mode() != 'numpy':
        kernels.load()
    status = kernels.status()
    say(f'simulator kernel: {status}')
    rate = multiply_add_rate()
    say(f'compute limit: multiply-adds at {rate / 1e9:.1f} G/s (128x128 matrix product, '
        'best of 200)')
    results = [bench_case(label, name, args.seed, args.repeat, rate) for label, name in CASES]
    body = report(results, args.seed, args.repeat, rate, status)
    print(body)
    if not args.no_write:
        plot(results, figure_path('ml_vs_peers'))
        body += '\n![time per case](ml_vs_peers.png)\n'
        write_results('ml_vs_peers', 'Output-error ML against least_squares peers',
                      body, 'python bench/ml_vs_peers.py')
    bad = [r['case'] for r in results
           if max(r['dev']['fd_ours'], r['dev']['afternoon']) > AGREEMENT_SIGMA]
    if bad:
        print(f'ERROR: optima disagree in {", ".join(bad)}', file=sys.stderr)
        return 2
    wake7 = next(r for r in results if r['case'] == 'wake_7par')['time']
    cpu7 = next(r for r in results if r['case'] == 'wake_7par')['cpu']
    met = (wake7['ours'] <= WAKE7_LIMIT_S and wake7['ours_first'] <= WAKE7_LIMIT_S
           and cpu7['afternoon'] >= WAKE7_VS_A * cpu7['ours']
           and cpu7['fd_ours'] >= WAKE7_VS_B * cpu7['ours'])
    return 0 if met else 1


if __name__ == '__main__':
    sys.exit(main())
