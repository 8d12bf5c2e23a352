"""
``rotor-id diagnose BAG --config RUN.yaml [--json OUT.json] [--report DIR] [--workers N]``.

Fits the run description's model, locates where the residuals depart from the model-free noise
floor (channels, band per rev, time span), searches the catalogue of missing physics for the
explanation (a set of effects) of highest posterior probability (docs/diagnosis.md), and
prints what it found: the effect (or ``none`` / ``unexplained``) with its probability, the
effects the record cannot tell apart, its parameters with Cramér-Rao bounds, the corrected
original parameters, the alternatives, and the detection limits of the effects not named.
``--json`` writes the same as JSON, ``--report`` the figures.
"""

import argparse
import json
import math
from pathlib import Path
import sys
from typing import cast, TYPE_CHECKING

from rotor_id import pipeline
from rotor_id.commands.common import check_output_paths, print_warnings, repairs_json
from rotor_id.commands.identify import load_inputs
from rotor_id.diagnosis.catalogue import EFFECTS
from rotor_id.diagnosis.diagnose import diagnose
from rotor_id.estimation.term_search import summary_line

if TYPE_CHECKING:
    from rotor_id.diagnosis.policy import SelectionPolicy
    from rotor_id.diagnosis.result import Diagnosis


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``rotor-id diagnose``."""
    parser.add_argument('bag', help='rosbag2 directory (or its .mcap/.db3 file)')
    parser.add_argument('--config', required=True,
                        help='run description YAML (see docs/run_description.md)')
    parser.add_argument('--json', dest='json_out', help='write the diagnosis as JSON here')
    parser.add_argument('--report', help='write the figures (fits, residual spectra, residual '
                                         'energy over time) into this directory')
    parser.add_argument('--workers', type=int, default=2,
                        help='processes for the candidate fits (default 2)')
    parser.add_argument('--effects', nargs='+', choices=EFFECTS, default=list(EFFECTS),
                        metavar='EFFECT', help='catalogue ids to try (default: all): '
                        + ', '.join(EFFECTS))
    parser.add_argument('--quiet', action='store_true', help='no progress lines')
    parser.add_argument('--verbose', action='store_true',
                        help='also print every Gauss-Newton iteration of every candidate')


def _fmt(value, spec='.4g'):
    return 'n/a' if value is None else format(value, spec)


def _effect_lines(explanation):
    lines = []
    for e in explanation.effects:
        name = e.effect + (f' ({e.variant})' if e.variant else '')
        gain = '' if e.two_delta_loglik is None else f', 2Δlog L {e.two_delta_loglik:.1f}'
        lines.append(f'  {name}: inclusion probability {e.inclusion_probability:.3f}{gain}'
                     + (f'; at its range limit: {", ".join(e.at_bound)}' if e.at_bound else ''))
        if len(e.shares) > 1:
            lines.append('    the record cannot tell it from: ' + ', '.join(
                f'{s.effect} {s.share:.0%}' for s in e.shares if s.effect != e.effect)
                + f' (itself {e.shares[0].share:.0%})')
        for pname, (value, std) in e.parameters.items():
            lines.append(f'    {pname:<16} {value:12.5g} ± {std:.3g}')
    return lines


def _limit_lines(explanation, power):
    limits = [d for d in explanation.detection_limits if d.limits]
    if not limits:
        return []
    said = '"none"' if explanation.effect == 'none' else 'no further effect'
    lines = [f'detection limits (the size this record would have revealed with power {power:g}; '
             f'{said} means nothing above these limits):']
    for d in limits:
        lines.append(f'  {d.effect:<22} ' + ', '.join(
            f'|{n}| {v:.3g}' if math.isfinite(v) else f'|{n}| any (not informed)'
            for n, v in d.limits.items()))
    return lines


def format_summary(diagnosis: 'Diagnosis') -> str:
    """Plain-text summary of a diagnosis."""
    ex = diagnosis.explanation
    fit = diagnosis.fit
    loc = diagnosis.location
    lines = [f'effect: {ex.effect} ({ex.confidence} confidence, probability '
             f'{ex.probability:.3f}); mismatch: {"yes" if diagnosis.mismatch else "no"}']
    if ex.reason:
        lines.append(f'why: {ex.reason}')
    if diagnosis.mismatch:
        lines.append(f'location: channels {", ".join(loc["channels"]) or "(none singly)"}; '
                     f'band {loc["band_per_rev"][0]:.2f}-{loc["band_per_rev"][1]:.2f} per rev; '
                     f'time {loc["window_s"][0]:.3f}-{loc["window_s"][1]:.3f} s')
    if diagnosis.proposal is not None:
        lines.append(summary_line(diagnosis.proposal))
    lines.append(f'residual RMS [rad]: baseline {fit["baseline_rms"]:.4g}, augmented '
                 f'{fit["augmented_rms"]:.4g}, noise floor {fit["noise_floor"]:.4g} '
                 f'(baseline {fit["baseline_rms"] / fit["noise_floor"] - 1:+.1%}, augmented '
                 f'{fit["augmented_rms"] / fit["noise_floor"] - 1:+.1%} of the floor)')
    lines.append(f'whiteness p (Ljung-Box, Bonferroni): baseline '
                 f'{fit["whiteness_p_baseline"]:.2g}, augmented '
                 f'{fit["whiteness_p_augmented"]:.2g}')
    lines += _effect_lines(ex)
    lines.append('original parameters: baseline -> corrected (σ)')
    for name, p in diagnosis.parameters.items():
        lines.append(f'  {name:<14} {p["baseline_value"]:12.5g} ± {p["baseline_std"]:.2g}  ->  '
                     f'{p["value"]:12.5g} ± {p["std"]:.2g}')
    lines.append(f'{"explanation":<44} {"probability":>11} {"2Δlog L":>9} {"k":>3} '
                 f'{"misfit removed":>14}')
    for a in diagnosis.candidates:
        if a.probability < 1e-4 and a.effects:
            continue
        name = ' + '.join(a.effects) or '(none)'
        lines.append(f'{name:<44} {a.probability:11.4f} {a.two_delta_loglik:9.1f} '
                     f'{a.n_params:3d} {_fmt(a.misfit_explained, ".0%"):>14}'
                     + ('' if a.fitted else '  (score test)'))
    policy = cast('SelectionPolicy', diagnosis.policy)     # (the field is typed object)
    lines += _limit_lines(ex, policy.detection_power)
    lines.append(f'probability: BIC evidence at the autocorrelation-corrected sample size, '
                 f'temperature-scaled (η = {policy.evidence_tempering:g}), '
                 f'prior uniform over sizes then sets; high confidence from '
                 f'{policy.high_confidence:g}; {diagnosis.elapsed_s:.1f} s')
    return '\n'.join(lines)


def run(args: argparse.Namespace) -> int:
    """Diagnose and report; exit 0 (a diagnosis was made, whatever it says)."""
    if args.workers < 1:
        raise ValueError(f'--workers must be at least 1, got {args.workers}')
    check_output_paths(json=args.json_out, report_dir=args.report)
    description, record = load_inputs(args.bag, args.config)
    print_warnings(list(description.warnings) + list(record.warnings))
    defaults, sources = pipeline.defaults_for(record, description)
    print_warnings(w for w in [pipeline.defaults_warning(defaults, sources)] if w)

    def progress(text):
        print(f'  {text}', file=sys.stderr, flush=True)

    result = diagnose(record, description, progress=None if args.quiet else progress,
                      workers=args.workers, effects=tuple(args.effects),
                      verbose_fits=args.verbose and not args.quiet)
    print(format_summary(result))
    data = result.as_json()
    data['bag'] = str(args.bag)
    data['repairs'] = repairs_json([record])
    data['defaults_used'] = {k: float(v) for k, v in defaults.items()}
    if args.json_out:
        Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json_out).write_text(json.dumps(data, indent=1, default=float))
        print(f'JSON: {args.json_out}')
    if args.report:
        from rotor_id.commands.diagnose_figures import write_report
        for path in write_report(result, args.report, record, description):
            print(f'figure: {path}')
    return 0
