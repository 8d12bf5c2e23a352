"""
``rotor-id frequency-response BAG [BAG ...] --config RUN.yaml [--window-s A B] [--out DIR]``.

Estimates the directional frequency response of the fixed-frame cyclic flap β_c = βI + iβII
to the cyclic pitch θ_c = θI + iθII from the stirring of one or more runs (progressing
stirring: positive, regressing: negative frequencies), with its coherence and random error,
overlays the run description's model (at the values of ``--model-json`` or ``--parameters``,
else its known values and guesses) with CIFER's cost J per band, and writes
``frequency_response.json`` and ``frequency_response.png`` into ``--out``
(docs/frequency_response.md).
"""

import argparse
import json
import os
from pathlib import Path
import time
from typing import Iterable, TYPE_CHECKING

import numpy as np

from rotor_id import pipeline
from rotor_id.commands.common import check_output_paths, print_warnings
from rotor_id.commands.identify import configs_for, load_inputs, run_names

if TYPE_CHECKING:
    from multiprocessing.process import BaseProcess


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``rotor-id frequency-response``."""
    parser.add_argument('bag', nargs='+', help='rosbag2 directories (or .mcap/.db3 files) of '
                        'stirring runs: progressing and regressing together give both signs '
                        'of frequency')
    parser.add_argument('--config', required=True, action='append',
                        help='run description YAML: one for all bags, or one per bag')
    parser.add_argument('--window-s', dest='window_s', nargs=2, type=float, metavar=('A', 'B'),
                        help='seconds after the first flap sample to transform (default: the '
                        'whole record, which starts in trim and holds the stirring)')
    source = parser.add_mutually_exclusive_group()
    source.add_argument('--model-json', dest='model_json',
                        help='draw the model at the parameters of this identify JSON')
    source.add_argument('--parameters', nargs='+', metavar='NAME=VALUE',
                        help="draw the run description's model at these values")
    parser.add_argument('--out', default='.', help='directory for frequency_response.json and '
                        'frequency_response.png (default: here)')
    parser.add_argument('--quiet', action='store_true', help='no summary table')


def parse_parameters(items: Iterable[str] | None) -> dict[str, float]:
    """Return {name: value} from NAME=VALUE words; ValueError names a malformed one."""
    out = {}
    for item in items or ():
        name, sep, value = item.partition('=')
        try:
            if not sep or not name:
                raise ValueError
            out[name.strip()] = float(value)
        except ValueError:
            raise ValueError(f'--parameters {item!r}: give NAME=VALUE with a number, e.g. '
                             'A=0.5') from None
    return out


def parameters_from_json(path: str | os.PathLike) -> dict[str, float]:
    """Return the parameter values of an identify JSON; ValueError says what is wrong."""
    try:
        data = json.loads(Path(path).read_text())
        return {name: float(entry['value']) for name, entry in data['parameters'].items()}
    except FileNotFoundError:
        raise ValueError(f'--model-json {path}: no such file') from None
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError):
        raise ValueError(f'--model-json {path}: not the JSON of rotor-id identify (it needs '
                         '"parameters": {name: {"value": ...}})') from None


def format_table(analysis: pipeline.FrequencyAnalysis) -> str:
    """Plain-text table: one line per point, then J per band."""
    est = analysis.estimate
    lines = [f'{"f [per rev]":>11} {"f [Hz]":>8} {"|H| [rad/rad]":>13} {"phase [deg]":>11} '
             f'{"coherence":>9} {"rand. err":>9}']
    for i in range(est.frequency_per_rev.size):
        lines.append(f'{est.frequency_per_rev[i]:+11.4f} {est.frequency_hz[i]:+8.3f} '
                     f'{est.magnitude[i]:13.4g} {est.phase_deg[i]:11.2f} '
                     f'{est.coherence[i]:9.3f} {est.random_error[i]:9.3g}')
    overlay = analysis.overlay
    if overlay is not None:
        lines.append(f'model {overlay.name} at {", ".join(f"{k} = {v:.4g}" for k, v in overlay.parameters.items())} ({overlay.source})')   # noqa: E501
        for b in overlay.bands:
            lines.append(f'  J {b.low:+.3f}..{b.high:+.3f} per rev ({b.points} points): '
                         f'{b.cost:.3g}{"" if b.acceptable else "  > 100"}')
        lines.append(f'  J over all usable points: {overlay.cost:.3g} (model through the same '
                     f'estimate); {overlay.cost_transfer_function:.3g} (transfer function)')
    return '\n'.join(lines)


def _figure_worker(connection):
    """Import matplotlib, draw the figure sent through ``connection``, answer None or the error."""
    from rotor_id.estimation.frequency_response_plot import bode_figure
    import matplotlib.backends.backend_agg  # noqa: F401  (the import is the slow part)
    try:
        job = connection.recv()
        if job is not None:
            bode_figure(*job)
        connection.send((None, time.process_time()))
    except Exception as error:  # noqa: B902 - handed back to the command, which reports it
        connection.send((f'{type(error).__name__}: {error}', time.process_time()))
    finally:
        connection.close()


class FigureProcess:
    """
    A forked process that imports matplotlib while the command reads and estimates.

    On two cores the plotting library's import (most of a short command's time) then runs
    beside the work instead of after it; without fork (or if it fails) the figure is drawn
    here.
    """

    def __init__(self) -> None:
        import multiprocessing
        self.process: 'BaseProcess | None' = None
        try:
            context = multiprocessing.get_context('fork')
            self.connection, child = context.Pipe()
            self.process = context.Process(target=_figure_worker, args=(child,), daemon=True)
            self.process.start()
            child.close()
        except (ValueError, OSError):
            self.process = None

    def draw(self, analysis: pipeline.FrequencyAnalysis, path: str | os.PathLike,
             title: str) -> float:
        """
        Draw the figure (in the process when it runs); raise RuntimeError on a failure.

        Returns the figure process's CPU time, s (0 when drawn here).
        """
        if self.process is None:
            from rotor_id.estimation.frequency_response_plot import bode_figure
            bode_figure(analysis, path, title)
            return 0.0
        self.connection.send((analysis, path, title))
        error, cpu = self.connection.recv()
        self.process.join()
        if error is not None:
            raise RuntimeError(f'the figure {path} could not be drawn: {error}')
        return cpu

    def cancel(self) -> None:
        """End the process without a figure (the command failed before it)."""
        if self.process is not None and self.process.is_alive():
            try:
                self.connection.send(None)
                self.connection.recv()
            except (OSError, EOFError, ValueError):
                pass
            self.process.join(timeout=5)


def run(args: argparse.Namespace) -> int:
    """Estimate, overlay, write; exit 0 (1 when the model's J exceeds 100)."""
    started = time.perf_counter()
    figure_process = FigureProcess()
    try:
        return _run(args, started, figure_process)
    finally:
        figure_process.cancel()


def _run(args, started, figure_process):
    configs = configs_for(args.bag, args.config)
    parameters = parse_parameters(args.parameters)
    source = '--parameters' if parameters else None
    if args.model_json:
        parameters = parameters_from_json(args.model_json)
        source = args.model_json
    if args.window_s is not None and not args.window_s[1] > args.window_s[0]:
        raise ValueError(f'--window-s {args.window_s[0]:g} {args.window_s[1]:g}: the end must '
                         'come after the start')
    check_output_paths(out_dir=args.out)
    names = run_names(args.bag)
    loaded = [load_inputs(bag, config) for bag, config in zip(args.bag, configs)]
    for (description, record), name in zip(loaded, names):
        print_warnings(f'{name}: {w}' for w in list(description.warnings) + list(record.warnings))
    runs = [(record, desc, name) for (desc, record), name in zip(loaded, names)]
    analysis = pipeline.frequency_analysis(runs, window_s=args.window_s,
                                           parameters=parameters or None, source=source)
    if not args.quiet:
        print(format_table(analysis))
    print_warnings(analysis.warnings)
    out = Path(args.out)
    data = analysis.as_json()
    data['bags'] = [str(b) for b in args.bag]
    data['elapsed_s'] = time.perf_counter() - started
    figure = out / 'frequency_response.png'
    data['figure_process_cpu_s'] = figure_process.draw(analysis, figure, ', '.join(names))
    data['elapsed_s'] = time.perf_counter() - started
    data['cpu_s'] = time.process_time()
    (out / 'frequency_response.json').write_text(json.dumps(data, indent=1))
    print(f'JSON: {out / "frequency_response.json"}')
    print(f'figure: {figure}')
    overlay = analysis.overlay
    return 1 if overlay is not None and np.isfinite(overlay.cost) and overlay.cost > 100 else 0
