"""
``rotor-id diagnose BAG --config RUN.yaml [--json OUT.json] [--report DIR] [--workers N]``.

Fits the run description's model, locates where the residuals depart from the model-free noise
floor (channels, band per rev, time span), fits every candidate of the catalogue of missing
physics as an augmented model by the same output-error ML, chooses by an autocorrelation-
corrected BIC difference and cross-validation, and prints what it found: the effect (or
``none`` / ``unexplained``), its parameters with Cramér-Rao bounds, the corrected original
parameters, residual RMS of baseline and augmented model against the floor, whiteness before
and after. ``--json`` writes the stable keys of issue 4, ``--report`` the figures.
"""

import json
from pathlib import Path
import sys

from rotor_id import pipeline
from rotor_id.commands.common import check_output_paths, print_warnings, repairs_json
from rotor_id.commands.identify import load_inputs
from rotor_id.diagnosis.catalogue import EFFECTS
from rotor_id.diagnosis.diagnose import diagnose


def add_arguments(parser):
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


def format_summary(diagnosis):
    """Plain-text summary of a diagnosis."""
    d = diagnosis.as_json()
    fit = d['fit']
    loc = d['location']
    lines = [f'effect: {d["explanation"]["effect"]} ({d["explanation"]["confidence"]} '
             f'confidence); mismatch: {"yes" if d["mismatch"] else "no"}']
    if d['mismatch']:
        lines.append(f'location: channels {", ".join(loc["channels"]) or "(none singly)"}; '
                     f'band {loc["band_per_rev"][0]:.2f}-{loc["band_per_rev"][1]:.2f} per rev; '
                     f'time {loc["window_s"][0]:.3f}-{loc["window_s"][1]:.3f} s')
    if 'proposal' in d['explanation']:
        from rotor_id.diagnosis.proposal import summary_line
        lines.append(summary_line(d['explanation']['proposal']))
    lines.append(f'residual RMS [rad]: baseline {fit["baseline_rms"]:.4g}, augmented '
                 f'{fit["augmented_rms"]:.4g}, noise floor {fit["noise_floor"]:.4g} '
                 f'(baseline {fit["baseline_rms"] / fit["noise_floor"] - 1:+.1%}, augmented '
                 f'{fit["augmented_rms"] / fit["noise_floor"] - 1:+.1%} of the floor)')
    lines.append(f'whiteness p (Ljung-Box, Bonferroni): baseline '
                 f'{fit["whiteness_p_baseline"]:.2g}, augmented '
                 f'{fit["whiteness_p_augmented"]:.2g}')
    effects = d['explanation'].get('effects', [])
    if len(effects) > 1:
        lines.append(f'effects, added one at a time (residual RMS above the floor: baseline '
                     f'{fit["baseline_rms"] / fit["noise_floor"] - 1:+.1%}):')
        for i, e in enumerate(effects, 1):
            name = e['effect'] + (f' ({e["variant"]})' if e.get('variant') else '')
            lines.append(f'  {i}. + {name:<28} Δlog L {e["delta_loglik"]:8.1f}, criterion '
                         f'{e["criterion"]:7.1f}, held-out RMS {_fmt(e["validation_rms"])} rad, '
                         f'residual RMS {e["residual_rms"]:.4g} rad '
                         f'({e["excess_over_floor"]:+.1%} of the floor)')
            if 'test' in e:
                t = e['test']
                lines.append(f'       added by its {t["name"]}: 2ΔJ·ρ {t["statistic"]:.1f} > '
                             f'χ²_{t["parameters"]} {t["critical"]:.1f} (level {t["level"]:.2g})')
            for pname, p in e['parameters'].items():
                lines.append(f'       {pname:<14} {p["value"]:12.5g} ± {p["std"]:.3g}')
    elif d['explanation']['parameters']:
        lines.append('extra parameters (Cramér-Rao σ):')
        for name, p in d['explanation']['parameters'].items():
            lines.append(f'  {name:<14} {p["value"]:12.5g} ± {p["std"]:.3g}')
    lines.append('original parameters: baseline -> corrected (σ)')
    for name, p in d['parameters'].items():
        lines.append(f'  {name:<14} {p["baseline_value"]:12.5g} ± {p["baseline_std"]:.2g}  ->  '
                     f'{p["value"]:12.5g} ± {p["std"]:.2g}')
    lines.append(f'{"candidate":<30} {"Δlog L":>9} {"criterion":>10} {"valid. RMS":>11}  '
                 'eligible')
    for c in d['candidates']:
        name = c['effect'] + (f' ({c["variant"]})' if c.get('variant') else '')
        if not c['available']:
            lines.append(f'{name:<30} {"":>9} {"":>10} {"":>11}  {c.get("reason", "")}')
            continue
        if c.get('bound_limited'):
            lines.append(f'{name:<30} {_fmt(c["delta_loglik"], ".1f"):>9} {"":>10} {"":>11}  '
                         f'no: {c["reason"]}')
            continue
        lines.append(f'{name:<30} {_fmt(c["delta_loglik"], ".1f"):>9} '
                     f'{_fmt(c["criterion"], ".1f"):>10} {_fmt(c["validation_rms"]):>11}  '
                     f'{"yes" if c["eligible"] else "no"}')
    lines.append(f'baseline validation RMS {_fmt(fit["validation_rms_baseline"])} rad; '
                 f'criterion = BIC difference with autocorrelation-corrected sample size, '
                 f'threshold {d["criterion"]["threshold"]:g}; {d["elapsed_s"]:.1f} s')
    for note in d['notes']:
        lines.append(f'note: {note}')
    return '\n'.join(lines)


def run(args):
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
        from rotor_id.diagnosis.figures import write_report
        for path in write_report(result, args.report):
            print(f'figure: {path}')
    return 0
