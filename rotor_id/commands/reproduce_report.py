"""
``rotor-id reproduce-report``: the report's numbers beside ours (NASA CR-137965).

Prints every M⁻¹ of Ch.2 and Ch.3 Table 1, the iterations from the report's starting values
(noise-free, and one seeded noisy draw, labelled as such), the Ch.2 summary table with CPU
times, and the report's initial states; ``--json`` and ``--figure`` write them to files.
All numbers are in the report's units (degrees; t in rad of azimuth). Exit code 0 when every
M⁻¹ and initial state agrees (documented report typos excepted), 1 otherwise.
"""

import argparse
import json
from pathlib import Path
import sys
import time
from typing import Sequence, TextIO

import numpy as np

from rotor_id.report import cases as C
from rotor_id.report import reproduce as R


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``reproduce-report``."""
    parser.add_argument('--json', metavar='OUT', type=Path,
                        help='write all numbers as JSON: {"cases": [{"name", "report_minv", '
                             '"ours_minv", ...}], "iterations", "summary", "initial_states"}')
    parser.add_argument('--figure', metavar='OUT.png', type=Path,
                        help='write M⁻¹(γ), M⁻¹(δ) against the record end (Ch.3 figs 2-3)')
    parser.add_argument('--seed', type=int, default=R.DEFAULT_SEED,
                        help='seed of the one noisy draw per case (default %(default)s); the '
                             "report's own noise draws cannot be reproduced")
    parser.add_argument('--quiet', action='store_true', help='no progress lines on stderr')


def _matrix_text(a, width=8):
    return ['[' + ' '.join(f'{v:{width}.4f}' for v in row) + ' ]' for row in np.asarray(a)]


def print_matrices(results: Sequence[R.MatrixResult], out: TextIO) -> None:
    """Print each printed M⁻¹ beside ours."""
    out.write('\n== Information matrices M⁻¹ (report | ours)\n')
    for res in results:
        case = res.case
        status = 'ok' if res.passed else 'DIFFERS'
        where = ', '.join(f'{k}={v:.4g}' for k, v in case.evaluated_at.items())
        r_text = 'R = 0.04' if case.kind == 'table1' else 'R = I'
        out.write(f'\n-- {case.title} [{case.source}]\n   at {where}, {r_text}, '
                  f'θ = ({", ".join(case.block)})\n')
        if case.kind == 'table1':
            d_r, d_o = np.diag(res.report), np.diag(res.ours)
            out.write(f'   M⁻¹(γ): report {d_r[0]:g}  ours {d_o[0]:.4g}    '
                      f'M⁻¹(δ): report {d_r[1]:g}  ours {d_o[1]:.4g}\n')
        elif case.kind == 'diagonal':
            out.write('   diag report: ' + ' '.join(f'{v:.3f}' for v in np.diag(res.report))
                      + '\n   diag ours:   ' + ' '.join(f'{v:.3f}' for v in np.diag(res.ours))
                      + '\n')
        else:
            for left, right in zip(_matrix_text(res.report), _matrix_text(res.ours)):
                out.write(f'   {left}   {right}\n')
        out.write(f'   {status}: max deviation {res.deviation:.3g} (tolerance {res.tolerance:g}, '
                  f'{res.rule})\n')
        if case.note:
            out.write(f'   note: {case.note}\n')


def print_iterations(results: Sequence[R.IterationResult], out: TextIO) -> None:
    """Print the iterates from the report's start: report, ours noise-free, ours noisy."""
    out.write("\n== Estimates per iteration from the report's starting values\n"
              '   (report: its own noise draw; ours: noise-free data, and one seeded noisy '
              "draw that cannot match the report's)\n")
    by_case: dict[str, list[R.IterationResult]] = {}
    for res in results:
        by_case.setdefault(res.case.name, []).append(res)
    for name, runs in by_case.items():
        case = runs[0].case
        cols = case.columns
        out.write(f'\n-- {case.title} [{case.source}]\n')
        out.write('   ' + 'iter'.ljust(6) + ''.join(c.rjust(14) for c in cols) + '\n')
        out.write('   ' + 'start'.ljust(6) + ''.join(
            f'{v:14.4f}' for v in runs[0].start[[runs[0].names.index(c) for c in cols]]) + '\n')
        if case.report:
            out.write('   report\n')
            for k, row in enumerate(case.report, 1):
                out.write('   ' + str(k).ljust(6) + ''.join(f'{v:14.3f}' for v in row) + '\n')
        for res in runs:
            est = res.estimate
            out.write(f'   ours, {res.data}: {est.iterations} iterations, '
                      f'{"converged" if est.converged else est.message}, '
                      f'{res.cpu_s:.2f} s CPU\n')
            for k, row in enumerate(res.columns, 1):
                line = '   ' + str(k).ljust(6) + ''.join(f'{v:14.4f}' for v in row)
                if res.minv_previous:
                    mg, md = res.minv_previous[k - 1]
                    line += f'    M⁻¹(γ) {mg:.4g}  M⁻¹(δ) {md:.4g} (R = .04, at previous row)'
                out.write(line + '\n')
            idx = [res.names.index(c) for c in cols]
            out.write('   σ_CRB ' + ''.join(f'{est.std[i]:14.4f}' for i in idx) + '\n')
        if case.noise_free_limit:
            out.write('   noise-free limit (modelling-error bias, docs/models.md §2.3): '
                      + ', '.join(f'{v:g}' for v in case.noise_free_limit) + '\n')


def print_gradient(res: R.GradientResult, out: TextIO) -> None:
    """Print the report's eq. 22 gradient at the initial estimate beside ours."""
    case = res.case
    out.write(f'\n== Gradient ∂J/∂Θ at the initial estimate (4, 8), R = I [{case.source}]\n')
    for name, rep, ours, sd, z in zip(case.at, case.report, res.ours_noise_free,
                                      res.noise_std, res.z):
        out.write(f'   ∂J/∂{name:6s} report {rep:7.2f} (noisy)   ours {ours:7.3f} (noise-free)'
                  f'   noise sd {sd:.3f}   z = {z:+.2f}\n')


def print_summary(results: Sequence[R.SummaryResult], out: TextIO) -> None:
    """Print the Ch.2 summary table, report | ours (σ = 0.2, variances = M⁻¹·0.04)."""
    out.write('\n== Ch.2 summary table (σ = 0.2; variances = Cramér-Rao bound with R = 0.04; '
              'ours from the seeded noisy draw)\n')
    head = f'   {"":52s}{"iter":>6}{"γ":>9}{"δ":>9}{"var γ":>9}{"var δ":>9}{"CPU s":>9}\n'
    out.write(head)
    for res in results:
        r = res.row
        out.write(f'   {r.label[:44] + " report":52s}{r.iterations:6d}{r.gamma:9.2f}'
                  f'{r.delta:9.2f}{r.var_gamma:9.4f}{r.var_delta:9.4f}{r.cpu_s:9.1f}\n')
        if res.iterations is None:
            out.write(f'   {r.label[:44] + " ours":52s}  {res.note}\n')
            continue
        out.write(f'   {r.label[:44] + " ours":52s}{res.iterations:6d}{res.gamma:9.2f}'
                  f'{res.delta:9.2f}{res.var_gamma:9.4f}{res.var_delta:9.4f}'
                  f'{res.cpu_s:9.3f}\n')
        if r.note:
            out.write(f'   note: {r.note}\n')
    out.write('   (iterations: until every later iterate moves less than 0.01 σ; report CPU '
              'times are 1975 mainframe seconds)\n')


def print_validation(results: Sequence[R.ValidationResult], out: TextIO) -> None:
    """Print the residual checks of the seeded noisy fits."""
    out.write('\n== Validation of the seeded noisy fits (residual RMS, Theil U, Ljung-Box p of '
              'whiteness, largest |input cross-correlation| vs its 95 % limit over all lags)\n')
    for res in results:
        out.write(f'\n-- {res.label}\n')
        for c in res.run.channels:
            verdict = 'white' if c.white() else 'NOT white'
            inputs = 'input-uncorrelated' if c.uncorrelated_with_input() else \
                'CORRELATED with input'
            out.write(f'   {c.channel:10s} rms {c.rms:7.4f}  U {c.theil:5.3f}  '
                      f'Q {c.ljung_box_q:6.1f} (L = {c.ljung_box_dof}, p = {c.ljung_box_p:.3f}, '
                      f'{verdict})  xcorr {c.max_cross_correlation:5.3f} '
                      f'(limit {c.cross_correlation_limit():.3f}, {inputs})\n')


def print_initial_states(results: Sequence[R.InitialStateResult], out: TextIO) -> None:
    """Print the report's initial states beside ours."""
    out.write('\n== Initial states (report | ours; checked to the printed digits)\n')
    for res in results:
        case = res.case
        out.write(f'\n-- {case.title} [{case.source}]\n')
        for state, rep, ours, ok in zip(case.states, case.report, res.ours, res.passed):
            flag = 'ok' if ok else ('known report discrepancy' if state in case.exceptions
                                    else 'DIFFERS')
            out.write(f'   {state:12s} report {rep:8.3f}   ours {ours:9.4f}   {flag}\n')
        for state, why in case.exceptions.items():
            out.write(f'   note: {state}: {why}\n')


def run(args: argparse.Namespace) -> int:
    """Run every report case, print the comparison, write JSON/figure if asked."""
    t_start = time.perf_counter()

    def progress(message):
        if not args.quiet:
            print(f'[{time.perf_counter() - t_start:6.1f} s] {message}', file=sys.stderr,
                  flush=True)

    for target in (args.json, args.figure):
        if target is not None and not target.parent.exists():
            raise FileNotFoundError(f'directory {target.parent} does not exist; create it or '
                                    'choose another output path')
    result = R.reproduce(seed=args.seed, progress=progress)
    out = sys.stdout
    out.write(f'NASA CR-137965 reproduced ({C.report_units_note()})\n')
    print_matrices(result.matrices, out)
    print_iterations(result.iterations, out)
    print_gradient(result.gradient, out)
    print_summary(result.summary, out)
    print_validation(result.validation, out)
    print_initial_states(result.initial_states, out)
    n_ok = sum(m.passed for m in result.matrices)
    init_ok = all(ok or state in r.case.exceptions for r in result.initial_states
                  for state, ok in zip(r.case.states, r.passed))
    out.write(f'\n{n_ok} of {len(result.matrices)} printed M⁻¹ agree; the initial states '
              f'{"agree" if init_ok else "DIFFER"} to the printed digits (bar the report\'s '
              'βI(70) = .601, docs/models.md §5.9).\n')
    if args.json is not None:
        args.json.write_text(json.dumps(result.as_json(), indent=1) + '\n')
        progress(f'wrote {args.json}')
    if args.figure is not None:
        R.write_figure(args.figure)
        progress(f'wrote {args.figure}')
    return 0 if result.passed else 1
