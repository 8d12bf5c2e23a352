"""
``rotor-id plan --config PLAN.yaml [--json OUT.json] [--figure OUT.png]``.

Predicts, before a run, the Cramér-Rao σ each candidate stirring transient would give the
configured unknowns (initial states at the window start free, as ``identify`` faces them), the
shortest record meeting ``target_std`` (report Ch.3 eq. 23) and which candidate to fly; the
figure shows σ against record length like the report's Ch.3 figs 2-3. PLAN.yaml is a run
description plus ``guess``, ``noise_std_rad``, ``rate_hz``, ``omega_rad_s``, ``target_std`` and
``candidates`` (see :func:`rotor_id.planning.parse_plan` and config/plan_*.yaml).

Exit code 0 when the recommended candidate meets every stipulated σ (or none is stipulated),
1 when no candidate meets them (the table and JSON still say how close each comes).
"""

import argparse
import json
import math
from pathlib import Path
import sys

from rotor_id import planning
from rotor_id.commands.common import check_output_paths, print_warnings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``rotor-id plan``."""
    parser.add_argument('--config', required=True,
                        help='plan YAML: a run description plus guess, noise_std_rad, rate_hz, '
                             'omega_rad_s, target_std, candidates (see config/plan_*.yaml)')
    parser.add_argument('--json', dest='json_out', help='write the result as JSON here')
    parser.add_argument('--figure', help='write σ vs record length (PNG) here')
    parser.add_argument('--quiet', action='store_true', help='no progress lines')


def format_table(result: planning.PlanResult) -> str:
    """Plain-text table: one row per candidate, the recommended one marked with '*'."""
    plan = result.plan
    names = plan.unknowns
    width = max(11, *(len(n) + 4 for n in names))
    head = (f'{"":1} {"#":>3} {"direction":<11} {"ω̇":>8} {"amp°":>5} {"t0":>6} {"rev":>5} '
            + ''.join(f'{"σ " + n:>{width}}' for n in names)
            + f' {"meets":>6} {"shortest":>9}')
    lines = [head]
    if plan.target_std:
        lines.append(f'{"":1} {"":>3} {"target_std":<11} {"":>8} {"":>5} {"":>6} {"":>5} '
                     + ''.join(f'{plan.target_std[n]:>{width}.3g}' if n in plan.target_std
                               else f'{"-":>{width}}' for n in names))
    for i, r in enumerate(result.candidates):
        c = r.candidate
        shortest = ('-' if r.shortest_duration_rev is None
                    else f'{r.shortest_duration_rev:.2f} rev')
        meets = ('yes' if r.meets_target else 'no') if plan.target_std else '-'
        lines.append(
            f'{"*" if i == result.recommended else "":1} {i:>3} {c.direction:<11} '
            f'{c.omegadot:>8.4f} {math.degrees(c.amplitude_rad):>5.2f} {c.t0:>6g} '
            f'{c.duration_rev:>5g} '
            + ''.join(f'{r.std[n]:>{width}.3g}' for n in names)
            + f' {meets:>6} {shortest:>9}')
    return '\n'.join(lines)


def format_recommendation(result: planning.PlanResult) -> str:
    """One paragraph: what to fly, its window for the run description, and why."""
    plan = result.plan
    best = result.candidates[result.recommended]
    c = best.candidate
    window = best.window_s
    sigmas = ', '.join(f'{n} ± {best.std[n]:.3g} ({best.relative_std[n]:.1%})'
                       for n in plan.unknowns)
    if plan.target_std and best.meets_target:
        why = 'meets every target_std with the shortest record'
    elif plan.target_std:
        why = (f'meets no target: closest, {best.worst_ratio:.2f}× the target of '
               f'{best.limiting}')
    else:
        why = 'best relative accuracy (no target_std given)'
    return (f'recommended: #{result.recommended} {c.label()}, {c.duration_rev:g} rev '
            f'({why})\n  predicted σ: {sigmas}\n  run description window_s: '
            f'[{window[0]:.6f}, {window[1]:.6f}] (record starting in trim, cyclic step one '
            f'revolution later); {best.n_samples} samples')


def run(args: argparse.Namespace) -> int:
    """Plan and report; exit 0 when the recommendation meets the targets, else 1."""
    check_output_paths(json=args.json_out, figure=args.figure)
    plan = planning.load_plan(args.config)
    print_warnings(plan.warnings)
    n_transients = len({c.transient for c in plan.candidates})
    if not args.quiet:
        print(f'planning {len(plan.candidates)} candidates ({n_transients} transients) for '
              f'{plan.description.model} ({", ".join(plan.unknowns)}), noise '
              f'{plan.noise_std_rad:.3g} rad per blade, {plan.rate_hz:g} Hz, '
              f'Ω = {plan.omega_rad_s:g} rad/s', file=sys.stderr, flush=True)

    def show(info):
        print(f'  M⁻¹(t_f) {info["index"]}/{info["of"]}: {info["label"]} '
              f'({info["elapsed"]:.2f} s)', file=sys.stderr, flush=True)

    result = planning.evaluate_plan(plan, progress=None if args.quiet else show)
    print(format_table(result))
    print(format_recommendation(result))
    print_warnings(result.warnings)
    data = result.as_json()
    data['config'] = str(args.config)
    if args.json_out:
        Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json_out).write_text(json.dumps(data, indent=1))
        print(f'JSON: {args.json_out}')
    if args.figure:
        planning.write_figure(result, args.figure)
        print(f'figure: {args.figure}')
    if not args.quiet:
        print(f'{len(plan.candidates)} candidates in {result.elapsed_s:.2f} s', file=sys.stderr)
    met = result.candidates[result.recommended].meets_target
    return 0 if (met or not plan.target_std) else 1
