"""
``rotor-id identify BAG [BAG ...] --config RUN.yaml [--config ...] [--json OUT] [--figure F]``.

Reads a bag in the test-stand convention (MCAP or sqlite3), converts to the report's
nondimensional time from the measured rotor speed, forms the model's channels (multiblade
coordinates or eq. 30 differences), runs the configured estimator over the configured window,
prints a table (value, Cramér-Rao σ, correlation) and writes the JSON with the stable keys of
:meth:`rotor_id.pipeline.Identification.as_json`.

Several bags are identified together: one estimate of the shared parameters, each
run with its own window (one ``--config`` per bag, or one for all), initial states and noise;
the JSON adds a ``runs`` section and the figure a column per run.

A multi-point bag (several test points recorded straight through) is identified per test point
with ``--test-point K`` or ``--test-point all``: ``window_s`` then counts from test point K's
first flap sample, as in the live identifier. The test points are found in the bag from what
the live identifier follows, by the same code (:func:`rotor_id.nodes.test_points.
replay_excitation`): the stirring node's phases (topic ``stirring``), else the identifier's
estimates tagged with their test point (topic ``estimate``, their ``test_point_start``).
"""

import argparse
from dataclasses import replace
import json
import os
from pathlib import Path
import sys
import time
from typing import Any, Iterator, Mapping, Sequence, TextIO, TYPE_CHECKING

import numpy as np

from rotor_id import pipeline
from rotor_id.commands.common import check_output_paths, print_warnings, repairs_json
from rotor_id.io.bag import may_read_by_parts, read_messages, read_record
from rotor_id.io.errors import BagError
from rotor_id.io.record import Record
from rotor_id.io.run_description import (
    check_against_record, load_run_description, RunDescription)

if TYPE_CHECKING:
    from rotor_id.nodes.test_points import RecordedTestPoint

METHODS = ('output-error', 'filter-error', 'equation-error', 'frequency-response')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``rotor-id identify``."""
    parser.add_argument('bag', nargs='+',
                        help='rosbag2 directory (or its .mcap/.db3 file); several bags are '
                        'identified together (shared parameters, per-run initial states '
                        'and noise)')
    parser.add_argument('--config', required=True, action='append',
                        help='run description YAML (see docs/run_description.md): one for '
                        'all bags, or one per bag in the same order')
    parser.add_argument('--json', dest='json_out', help='write the result as JSON here')
    parser.add_argument('--figure', help='write measured vs fitted flapping (PNG) here')
    parser.add_argument('--method', choices=METHODS, default=None,
                        help="estimator (default: the run description's, else output-error)")
    parser.add_argument('--filter-bounds', choices=('marginal', 'conditional'),
                        default='marginal',
                        help='filter-error only: bounds integrated over the likely '
                        'process-noise sigmas (default) or the Cramer-Rao bound at the joint '
                        'maximum-likelihood optimum')
    parser.add_argument('--quiet', action='store_true', help='no progress lines')
    parser.add_argument('--test-point', dest='test_point', default=None, metavar='K|all',
                        help='a multi-point bag of several test points: identify test point K '
                        '(1, 2, ... as the live identifier numbers them) or all of them, '
                        "window_s counting from the test point's first flap sample; the test "
                        "points are found from the bag's stirring phases, else its estimates")
    parser.add_argument('--csv', dest='csv_out', default=None,
                        help='with --test-point: write one row per test point here (CSV)')


def progress_printer(label: str, stream: TextIO = sys.stderr) -> pipeline.Progress:
    """Return a progress callback printing one line per iteration."""
    def show(info):
        values = ' '.join(f'{n}={v:.5g}' for n, v in zip(info['names'], info['values'])
                          if '(t0)' not in n)
        print(f'  {info.get("label") or label}: iteration {info["iteration"]:2d}  '
              f'residual RMS {info["rms"]:.4g} rad  '
              f'{values}  ({info["elapsed"]:.2f} s)', file=stream, flush=True)
    return show


def load_inputs(bag: str | os.PathLike, config: str | os.PathLike
                ) -> tuple[RunDescription, Record]:
    """
    Run description and record, checked against each other.

    The one path by which identify, diagnose, campaign and demo read their inputs: the
    description is validated (typo keys, ranges), the bag read, and the blade count and window
    checked against what the bag holds, before any fitting. The warnings of both are in their
    ``warnings`` (the caller prints them).
    """
    description = load_run_description(config)
    record = read_record(bag, **description.record_options())   # the rig's names, conventions
    check_against_record(description, record)
    return description, record


def format_table(result: pipeline.Identification) -> str:
    """Plain-text table of the identified parameters, σ and correlations."""
    data = result.as_json()
    names = list(data['parameters'])
    width = max(12, *(len(n) for n in names))
    # output error's σ is the Cramér-Rao bound; the other methods say what theirs is
    sigma = 'σ (CRB)' if data['method'] == 'output-error' else 'σ'
    lines = [f'{"parameter":<{width}} {"value":>13} {sigma:>11} {"σ/|value|":>10}  '
             + ' '.join(f'{n[:8]:>8}' for n in names)]
    corr = data['correlation']
    for i, name in enumerate(names):
        value = data['parameters'][name]['value']
        std = data['parameters'][name]['std']
        rel = std / abs(value) if value else float('inf')
        lines.append(f'{name:<{width}} {value:13.6g} {std:11.3g} {rel:10.2%}  '
                     + ' '.join(f'{corr[i][j]:8.3f}' for j in range(len(names))))
    if 'runs' in data:
        where = f'{len(data["runs"])} runs ({data["n_samples"]} samples; windows below)'
    else:
        where = (f'window {data["window_s"][0]:.4f}-{data["window_s"][1]:.4f} s '
                 f'({data["n_samples"]} samples, Ω = {data["omega_rad_s"]:.2f} rad/s)')
    lines.append(f'model {data["model"]}, method {data["method"]}, {where}, '
                 f'{data["iterations"]} iterations, {_status(data)}')
    noise = ', '.join(f'{c} {s:.3g}' for c, s in zip(data['channels'], data['noise_std']))
    if 'runs' in data:
        noise += ' (pooled over the runs)'
    lines.append(f'noise σ (rad): {noise}')
    timing = (data.get('adequacy') or {}).get('timing')
    if timing and timing['shift_sigma_per_sample']:
        shifts = ', '.join(f'{n} {v:+.1f}σ' for n, v in timing['shift_sigma_per_sample'].items())
        lines.append(f'timing: a flap-sensor delay of one sample '
                     f'({timing["sample_period_s"] * 1e3:.3g} ms) would move {shifts} and '
                     'leave the residuals nearly white (delay score here z = '
                     f'{timing["delay_score_z"]:+.1f}); these bounds assume sensors read on '
                     'time')
    return '\n'.join(lines)


def _status(data):
    if not data['converged']:
        return 'NOT converged: ' + data['message']
    return 'converged' if data['message'] == 'converged' else 'converged, ' + data['message']


def plot_fit(result: pipeline.Identification, record: Record, path: str | os.PathLike,
             title: str = '') -> None:
    """Measured vs fitted channels and residuals, against time in seconds."""
    plot_runs(result, [record], path, title)


def configs_for(bags: Sequence[str], configs: Sequence[str]) -> list[str]:
    """Return one run description path per bag (one for all, or one each)."""
    if len(configs) == 1:
        return list(configs) * len(bags)
    if len(configs) != len(bags):
        raise ValueError(f'{len(bags)} bags but {len(configs)} --config files; give one '
                         '--config for all bags or one per bag, in the same order')
    return list(configs)


def run(args: argparse.Namespace) -> int:
    """Identify and report; exit 0 when converged, 1 when not."""
    configs = configs_for(args.bag, args.config)
    if args.test_point is not None or args.csv_out:
        return run_test_points(args, configs)
    if len(args.bag) > 1:
        return run_several(args, configs)
    args.bag, args.config = args.bag[0], configs[0]
    started = time.perf_counter()
    check_output_paths(json=args.json_out, figure=args.figure)
    description, record = load_inputs(args.bag, args.config)
    print_warnings(list(description.warnings) + list(record.warnings))
    method = args.method or description.method
    label = f'{method} {description.model} ({", ".join(description.unknowns)})'
    if not args.quiet:
        print(f'fitting {label} to {args.bag}, window {description.window_s[0]:.4f}-'
              f'{description.window_s[1]:.4f} s', file=sys.stderr, flush=True)
    result = pipeline.identify(record, description, method=method,
                               progress=None if args.quiet else progress_printer(method),
                               filter_bounds=args.filter_bounds)
    print(format_table(result))
    write_outputs(result, [record], args, str(args.bag), started,
                  title=f'{Path(args.bag).name}: {label}')
    return 0 if result.estimate.converged else 1


def write_outputs(result: pipeline.Identification, records: Sequence[Record],
                  args: argparse.Namespace, bag: str | list[str], started: float,
                  title: str) -> None:
    """Print the result's warnings (once each), write the JSON and the figure when asked."""
    print_warnings(result.warnings)
    data = result.as_json()
    data['bag'] = bag
    data['repairs'] = repairs_json(records)
    data['elapsed_s'] = time.perf_counter() - started
    if args.json_out:
        Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json_out).write_text(json.dumps(data, indent=1))
        print(f'JSON: {args.json_out}')
    if args.figure:
        plot_runs(result, records, args.figure, title=title)
        print(f'figure: {args.figure}')


def run_names(bags: Sequence[str | os.PathLike]) -> list[str]:
    """Short, distinct names of the bags for tables and the JSON."""
    names = [Path(b).name or str(b) for b in bags]
    return names if len(set(names)) == len(names) else [str(b) for b in bags]


def format_runs(result: pipeline.Identification) -> str:
    """Plain-text table of the runs of a multi-run estimate: window, noise, residual RMS."""
    data = result.as_json()
    width = max(8, *(len(r['name']) for r in data['runs']))
    lines = [f'{"run":<{width}} {"window [s]":>17} {"samples":>8}  noise σ / residual RMS '
             f'[rad] ({", ".join(data["channels"])})']
    for r in data['runs']:
        pairs = ', '.join(f'{s:.3g}/{e:.3g}' for s, e in zip(r['noise_std'], r['residual_rms']))
        lines.append(f'{r["name"]:<{width}} {r["window_s"][0]:8.4f}-{r["window_s"][1]:<8.4f} '
                     f'{r["n_samples"]:8d}  {pairs}')
    return '\n'.join(lines)


def check_no_overlap(bags: Sequence[str | os.PathLike],
                     windows: Sequence[Sequence[float]]) -> None:
    """Refuse one bag given twice with overlapping windows (its samples would count twice)."""
    seen: list[tuple[Path, Sequence[float]]] = []
    for bag, window in zip(bags, windows):
        path = Path(bag).resolve()
        for other, other_window in seen:
            if other == path and window[0] < other_window[1] and other_window[0] < window[1]:
                raise ValueError(
                    f'{bag} is given twice with overlapping windows ({other_window[0]:.4g}-'
                    f'{other_window[1]:.4g} s and {window[0]:.4g}-{window[1]:.4g} s): its '
                    'samples would count twice and the bounds come out too small; give each '
                    'bag once, or windows that do not overlap')
        seen.append((path, window))


def run_several(args: argparse.Namespace, configs: Sequence[str]) -> int:
    """Identify several bags together; exit 0 when converged, 1 when not."""
    started = time.perf_counter()
    names = run_names(args.bag)
    check_output_paths(json=args.json_out, figure=args.figure)
    loaded = [load_inputs(bag, config) for bag, config in zip(args.bag, configs)]
    check_no_overlap(args.bag, [desc.window_s for desc, _ in loaded])
    for (description, record), name in zip(loaded, names):
        print_warnings(f'{name}: {warning}'
                       for warning in list(description.warnings) + list(record.warnings))
    pipeline.check_runs_agree([desc for desc, _ in loaded], names)
    description = loaded[0][0]
    method = args.method or 'output-error'
    label = f'{method} {description.model} ({", ".join(description.unknowns)})'
    if not args.quiet:
        print(f'fitting {label} to {len(names)} runs together: {", ".join(names)}',
              file=sys.stderr, flush=True)
    runs = [(record, desc, name) for (desc, record), name in zip(loaded, names)]
    if args.method == 'frequency-response':      # docs/frequency_response.md
        result = pipeline.identify_frequency_response(
            runs, progress=None if args.quiet else progress_printer(method))
    else:
        result = pipeline.identify_runs(
            runs, method=args.method, progress=None if args.quiet else progress_printer(method))
    print(format_table(result))
    print(format_runs(result))
    write_outputs(result, [record for _, record in loaded], args, [str(b) for b in args.bag],
                  started, title=label)
    return 0 if result.estimate.converged else 1


def plot_runs(result: pipeline.Identification, records: Sequence[Record],
              path: str | os.PathLike, title: str = '') -> None:
    """
    Measured vs fitted channels and residuals against time in seconds, a column per run.

    One column for a single recording (all its experiments, e.g. the blades of single_blade);
    with several recordings (``result.runs``) one per recording, headed by its residual RMS.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    est = result.estimate
    columns = result.runs or [pipeline.Run(
        name='', source='', description=result.description, window_s=result.window_s,
        omega_rad_s=result.omega_rad_s, experiments=list(range(len(result.experiments))))]
    n_ch = result.experiments[0].model.n_outputs
    width = 9.0 if len(columns) == 1 else 4.2 * len(columns)
    fig, axes = plt.subplots(n_ch + 1, len(columns), figsize=(width, 1.9 * (n_ch + 1)),
                             sharex='col', squeeze=False)
    for col, (run, record) in enumerate(zip(columns, records)):
        for r in run.experiments:
            exp = result.experiments[r]
            if exp.y is None:           # a run without measurements has nothing to draw
                continue
            ts = (exp.t - record.t[0]) / run.omega_rad_s + record.time_s[0]
            first = r == run.experiments[0]
            for c in range(n_ch):
                ax = axes[c, col]
                ax.plot(ts, np.degrees(exp.y[:, c]), '.', ms=2, color='0.5',
                        label='measured' if first else None)
                ax.plot(ts, np.degrees(est.fitted[r][:, c]), '-', lw=1.2, color='C0',
                        label='fitted' if first else None)
                if col == 0:
                    ax.set_ylabel(f'{exp.model.output_names[c]}\n[deg]')
            axes[-1, col].plot(ts, np.degrees(est.residuals[r]), lw=0.6)
        if run.name:
            residuals = np.concatenate([est.residuals[r] for r in run.experiments])
            rms = ', '.join(f'{v:.3g}' for v in np.degrees(np.sqrt(np.mean(residuals**2, 0))))
            axes[0, col].set_title(f'{run.name}\nresidual RMS {rms} deg', fontsize=8)
        axes[-1, col].set_xlabel('time since first sample [s]')
    axes[0, 0].legend(loc='upper right', fontsize=8)
    axes[-1, 0].set_ylabel('residuals\n[deg]')
    params = ', '.join(f'{n} = {v["value"]:.4g} ± {v["std"]:.2g}'
                       for n, v in result.as_json()['parameters'].items())
    fig.suptitle(f'{title}\n{params}', fontsize=9)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------ multi-point bags
NS = 1_000_000_000
MULTI_POINT_SLICE_S = 30.0      # a long multi-point bag is read this many seconds at a time
CSV_FIXED = ('test_point', 'found_from', 'test_point_start_s', 'window_start_s', 'window_end_s',
             'status', 'converged', 'n_samples')


def parse_test_point(text: str) -> int | None:
    """``--test-point``: a positive integer, or 'all' (None)."""
    if str(text).strip().lower() == 'all':
        return None
    try:
        number = int(text)
    except ValueError:
        number = 0
    if number < 1:
        raise ValueError(f"--test-point {text!r}: give a test point number (1, 2, ...) or 'all'")
    return number


def _stamp_ns(stamp):
    return int(stamp.sec) * NS + int(stamp.nanosec)


class MultiPointRecord:
    """
    A multi-point bag's record, read whole when the bag is small, else slice by slice.

    A long bag is read ``MULTI_POINT_SLICE_S`` at a time with the windowed reader
    (:func:`rotor_id.io.bag.read_record` with ``window_s``), so memory follows a slice and the
    bag's time stamps, not the bag. ``whole`` is the Record when the reader took the
    whole bag (small bags, bags without an index, clock trouble: as the plain read). The
    slices share the recording's origin, so their flap stamps, values and the window checks
    of the replay are those of the whole read; the unwrapped azimuth of each slice counts its
    own revolutions (the replay uses it modulo 2π).
    """

    def __init__(self, bag: str | os.PathLike, options: Mapping[str, Any],
                 slice_s: float | None = None) -> None:
        # slices and windows are read without the reader's dead-sensor check: a blade may
        # read one value between test points; each fitted window is checked by the caller
        self.bag, self.options = bag, {**options, 'window_s': None, 'check_dead_flap': False}
        self.slice_s = float(MULTI_POINT_SLICE_S if slice_s is None else slice_s)
        first = None
        if options.get('run') is None and may_read_by_parts(bag):
            first = self._read(0.0)
        if first is None or not first.read_around_window:
            # the whole bag without a window: a fault anywhere in
            # it is an error (a slice is judged as a window: each fault an error in its slice)
            first = read_record(bag, **self.options)
        self.whole = None if first.read_around_window else first
        self.stamp0_ns, self.blade_names = first.stamp0_ns, first.blade_names
        self.warnings = list(first.warnings)
        self._first = first

    def _read(self, start):
        stop = start + self.slice_s
        try:
            return read_record(self.bag, **{**self.options, 'window_s': (start, stop)})
        except BagError as err:
            raise BagError(f'{err} [window_s here is the slice {start:g}-{stop:g} s of the '
                           f'bag, read {self.slice_s:g} s at a time to find its test '
                           'points]') from None

    def window(self, window_s: Sequence[float]) -> Record:
        """Return the record around ``window_s`` (the whole record when it was read whole)."""
        if self.whole is not None:
            return self.whole
        record = read_record(self.bag, **{**self.options, 'window_s': tuple(window_s)})
        self.warnings += [w for w in record.warnings if w not in self.warnings]
        return record

    def slices(self) -> Iterator[Record]:
        """Yield the samples of [k·slice_s, (k+1)·slice_s) s as Records, k = 0, 1, ..."""
        k, start, part = 0, 0.0, self._first
        while True:
            if not part.read_around_window or part.stamp0_ns != self.stamp0_ns:
                raise _ReadWhole(part)
            stop = start + self.slice_s
            keep = (part.time_s >= start) & (part.time_s < stop)
            yield replace(part, time_s=part.time_s[keep], t=part.t[keep],
                          rotor_speed_rad_s=part.rotor_speed_rad_s[keep],
                          blade_flap=part.blade_flap[keep],
                          blade_pitch=part.blade_pitch[keep])
            if not part.time_s[-1] >= stop:               # the recording ends in this slice
                return
            k += 1
            start = k * self.slice_s
            part = self._read(start)

    def replay_record(self) -> 'Record | _SlicedRecord':
        """
        Return the bag's record as :func:`~rotor_id.nodes.test_points.replay_excitation` takes it.

        The Record when it was read whole, else the bag's stamps and azimuth with its rows
        read slice by slice, forwards (two passes over the slices in all).
        """
        if self.whole is not None:
            return self.whole
        time_s, t, counts = [], [], []
        try:
            for part in self.slices():
                time_s.append(part.time_s)
                t.append(part.t)
                counts.append(len(part))
                self.warnings += [w for w in part.warnings if w not in self.warnings]
        except _ReadWhole as whole:          # the reader took the whole bag after all
            self.whole = whole.record
            return self.whole
        return _SlicedRecord(self, np.concatenate(time_s), np.concatenate(t), counts)


class _ReadWhole(Exception):
    """A slice came back as the whole recording."""

    def __init__(self, record):
        super().__init__('read whole')
        self.record = record


class _SlicedRecord:
    """A multi-point record whose rows are read slice by slice, in index order (for the replay)."""

    def __init__(self, multi_point, time_s, t, counts):
        self.stamp0_ns, self.time_s, self.t = multi_point.stamp0_ns, time_s, t
        self.blade_names = list(multi_point.blade_names)
        self.n_blades = len(self.blade_names)
        self._slices, self._ends = multi_point.slices(), np.cumsum(counts)
        self._part, self._first, self._end = None, 0, 0
        self.blade_flap = _SliceRows(self, 'blade_flap')
        self.blade_pitch = _SliceRows(self, 'blade_pitch')
        self.rotor_speed_rad_s = _SliceRows(self, 'rotor_speed_rad_s')

    def __len__(self):
        """Return the number of samples."""
        return self.time_s.size

    def row(self, name, index):
        """Return row ``index`` of column ``name``; rows are read forwards, a slice at a time."""
        while index >= self._end:
            self._part = next(self._slices)
            self._first, self._end = self._end, self._end + len(self._part)
        if index < self._first:
            raise IndexError(f'row {index} is behind the slice read (rows {self._first}-'
                             f'{self._end - 1}): a sliced record is read forwards only')
        return getattr(self._part, name)[index - self._first]


class _SliceRows:
    """One column of a :class:`_SlicedRecord`, indexed by row."""

    def __init__(self, multi_point, name):
        self.multi_point, self.name = multi_point, name

    def __getitem__(self, index):
        """Return one row."""
        return self.multi_point.row(self.name, int(index))


def find_test_points(bag: str | os.PathLike, description: RunDescription,
                     multi_point: 'MultiPointRecord | Record',
                     found: Mapping[str, tuple[str | None, list[tuple[int, Any]]]] | None = None
                     ) -> tuple[list['RecordedTestPoint'], str, list[str]]:
    """
    Find the test points of a multi-point bag; return (RecordedTestPoints, found from, notes).

    From the stirring phases (``topics.stirring``) by the live identifier's own state machine;
    else from the estimates (``topics.estimate``) tagged with a test point. Where both are in
    the bag, each test point found from the phases takes the live identifier's number (the
    estimates' ``test_point`` with the same first flap sample). Raises ValueError when the bag
    holds neither, saying how to select a time window instead. ``multi_point`` is a
    :class:`MultiPointRecord` (or a Record); ``found`` the bag's messages on the two topics when
    already read.
    """
    from rotor_id.nodes.test_points import Phase, RecordedTestPoint, replay_excitation
    stirring, estimate = description.node_topics['stirring'], description.node_topics['estimate']
    if found is None:
        found = read_messages(bag, [stirring, estimate])
    stirring_topic, commands = found[stirring]
    estimate_topic, estimates = found[estimate]
    tagged: dict[int, list[Any]] = {}                # live number -> its estimates
    for _, msg in estimates:
        if msg.test_point > 0:
            tagged.setdefault(int(msg.test_point), []).append(msg)
    notes = []
    if commands:
        excitation = [(_stamp_ns(m.header.stamp), int(m.phase)) for _, m in commands]
        record = multi_point.replay_record() if isinstance(multi_point, MultiPointRecord) \
            else multi_point
        points = replay_excitation(record, excitation, description.window_s)
        live = {_stamp_ns(ms[0].test_point_start): n for n, ms in tagged.items()}
        for point in points:
            number = live.get(point.stamp0_ns)
            if number is not None and number != point.number:
                notes.append(f'the schedule that started test point {point.number} in this bag '
                             f"is the live identifier's test point {number} (it also started "
                             'test points by its service, or was restarted): numbered '
                             f'{number} here')
                point.number = number
        return points, f'{stirring_topic} (stirring phases)', notes
    if tagged:
        points = []
        for number, msgs in sorted(tagged.items()):
            finals = [m for m in msgs if m.kind == 1]          # KIND_FINAL
            window = tuple(description.window_s)
            point = RecordedTestPoint(number, _stamp_ns(msgs[0].test_point_start), window,
                                      Phase.FITTING, source='estimates')
            if finals and finals[-1].status == 5:             # STATUS_ABORTED
                point.phase, point.detail = Phase.ABORTED, finals[-1].message
            points.append(point)
        return points, f'{estimate_topic} (estimates tagged with their test point)', notes
    raise ValueError(
        f'{bag} holds no test points: no stirring phases on {stirring_topic or stirring} and no '
        f'estimate tagged with a test point on {estimate_topic or estimate} (topics.stirring '
        'and topics.estimate of the run description); identify a time window instead: drop '
        "--test-point and set window_s to seconds after the bag's first flap sample")


def _live_windows(bag, description):
    """{test point: (requested start, end) s of the live final estimate} where the bag has it."""
    topic = description.node_topics['estimate']
    return {int(m.test_point): (m.window_requested_start_s, m.window_requested_end_s)
            for _, m in read_messages(bag, [topic])[topic][1]
            if m.test_point > 0 and m.kind == 1 and m.window_requested_end_s > 0}


def run_test_points(args: argparse.Namespace, configs: Sequence[str]) -> int:
    """Identify test point K (or all) of a multi-point bag; exit 0 when all converged, else 1."""
    from rotor_id.nodes.test_points import Phase
    if args.test_point is None:
        raise ValueError('--csv is written with --test-point (one row per test point); give '
                         '--test-point K or --test-point all')
    wanted = parse_test_point(args.test_point)
    if len(args.bag) > 1:
        raise ValueError('--test-point identifies the test points of one multi-point bag; '
                         'give one bag')
    check_output_paths(json=args.json_out, figure=args.figure, csv=args.csv_out)
    bag, config = args.bag[0], configs[0]
    started = time.perf_counter()
    description = load_run_description(config)
    # the test points are found in the bag first: a small bag is read whole, a long one
    # a slice at a time, and then only each test point's window (memory follows the slice)
    multi_point = MultiPointRecord(bag, description.record_options())
    print_warnings(list(description.warnings) + list(multi_point.warnings))
    printed = len(multi_point.warnings)
    points, source, notes = find_test_points(bag, description, multi_point)
    print_warnings(multi_point.warnings[printed:] + notes)
    printed = len(multi_point.warnings)
    numbers = [p.number for p in points]
    if not args.quiet:
        print(f'{bag}: {len(points)} test point(s) found from {source}: '
              + ', '.join(p.describe() for p in points), file=sys.stderr, flush=True)
    if wanted is not None:
        if wanted not in numbers:
            raise ValueError(f'{bag} has no test point {wanted}: found {numbers or "none"} '
                             f'from {source}')
        points = [p for p in points if p.number == wanted]
    live = _live_windows(bag, description)
    method = args.method or description.method
    results, rows, all_converged = [], [], True

    def not_identified(head, reason):
        results.append({**head, 'status': 'not identified', 'reason': reason})
        rows.append({**head, 'status': 'not identified', 'converged': False})
        print(f'test point {head["test_point"]}: not identified ({reason})')

    for point in points:
        shift = (point.stamp0_ns - multi_point.stamp0_ns) / NS
        head = {'test_point': point.number, 'found_from': source,
                'test_point_start_ns': int(point.stamp0_ns), 'test_point_start_s': shift,
                'window_s_test_point': list(point.window_s)}
        if point.number in live and tuple(live[point.number]) != tuple(point.window_s):
            print_warnings([f'test point {point.number}: the live identifier used window_s '
                            f'{list(live[point.number])}, this run description '
                            f'{list(point.window_s)}: the results differ by that'])
        if point.phase != Phase.FITTING:
            reason = (point.detail or point.describe())
            if wanted is not None:
                raise ValueError(f'{point.describe()}: {reason}; its window does not hold the '
                                 'excitation it was planned on. To fit it anyway, drop '
                                 "--test-point and set window_s to seconds after the bag's "
                                 f'first flap sample (this test point starts at {shift:.4f} s)')
            all_converged = False
            not_identified(head, reason)
            continue
        window = (point.window_s[0] + shift, point.window_s[1] + shift)
        desc_k = replace(description, window_s=window)
        record = multi_point.window(window)
        print_warnings(multi_point.warnings[printed:])
        printed = len(multi_point.warnings)
        dead = record.stuck_flap_blades(*window)
        if dead:
            # a dead sensor spoils this test point only: the others are still identified
            reason = ('dead flap sensor: ' + ', '.join(
                f'{name} reads exactly {value:.6g} rad' for name, value in dead)
                + ' in every sample of the window; check the sensor and its wiring')
            if wanted is not None:
                raise ValueError(f'{point.describe()}: {reason}')
            all_converged = False
            not_identified(head, reason)
            continue
        check_against_record(desc_k, record)
        if point.check is not None and not point.check.complete:
            print_warnings([f'test point {point.number}: the bag misses samples in its window '
                            f'({point.check.describe()}); the live identifier reported it '
                            'incomplete'])
        if not args.quiet:
            print(f'test point {point.number}: fitting {method} {description.model} over '
                  f'{point.window_s[0]:.4f}-{point.window_s[1]:.4f} s after its first flap '
                  f'sample ({window[0]:.4f}-{window[1]:.4f} s into the bag)',
                  file=sys.stderr, flush=True)
        result = pipeline.identify(record, desc_k, method=method,
                                   progress=None if args.quiet else progress_printer(method),
                                   filter_bounds=args.filter_bounds)
        print(f'-- test point {point.number} --')
        print(format_table(result))
        print_warnings(result.warnings)
        data = {**head, **result.as_json(), 'bag': str(bag), 'repairs': repairs_json([record])}
        if point.check is not None:
            data['window_complete_in_bag'] = point.check.complete
        all_converged &= bool(result.estimate.converged)
        results.append(data)
        rows.append({**head, 'status': 'converged' if result.estimate.converged
                     else 'not converged', 'converged': bool(result.estimate.converged),
                     'n_samples': data['n_samples'], 'window_start_s': window[0],
                     'window_end_s': window[1],
                     **{k: v for name, p in data['parameters'].items()
                        for k, v in ((name, p['value']), (f'{name}_std', p['std']))}})
        if args.figure:
            stem = Path(args.figure)           # with 'all': one figure per test point
            path = (stem if wanted is not None
                    else stem.with_name(f'{stem.stem}_tp{point.number}{stem.suffix}'))
            plot_runs(result, [record], path, title=f'{Path(bag).name}: test point '
                      f'{point.number}, {method} {description.model}')
            print(f'figure: {path}')
    if wanted is None:
        print(format_test_points(rows, description.unknowns))
    elapsed = time.perf_counter() - started
    if args.json_out:
        out: Any = results[0] if wanted is not None else results    # a JSON object or list
        if wanted is not None:
            out['elapsed_s'] = elapsed
        Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json_out).write_text(json.dumps(out, indent=1))
        print(f'JSON: {args.json_out}')
    if args.csv_out:
        write_csv(args.csv_out, rows, description.unknowns)
        print(f'CSV: {args.csv_out}')
    return 0 if all_converged else 1


def format_test_points(rows: Sequence[Mapping[str, Any]], unknowns: Sequence[str]) -> str:
    """Plain-text summary of the test points of a multi-point bag: start, status, value ± σ."""
    lines = [f'{"test point":>10} {"start [s]":>10}  {"status":<15} '
             + ' '.join(f'{n:>20}' for n in unknowns)]
    for row in rows:
        values = ' '.join(f'{row[n]:>11.5g} ± {row[n + "_std"]:<6.2g}' if n in row
                          else f'{"-":>20}' for n in unknowns)
        lines.append(f'{row["test_point"]:>10} {row["test_point_start_s"]:>10.4f}  '
                     f'{row["status"]:<15} {values}')
    return '\n'.join(lines)


def write_csv(path: str | os.PathLike, rows: Sequence[Mapping[str, Any]],
              unknowns: Sequence[str]) -> None:
    """One row per test point: CSV_FIXED columns, then each unknown and its σ."""
    import csv
    columns = list(CSV_FIXED) + [c for n in unknowns for c in (n, f'{n}_std')]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, 'w', newline='') as stream:
        writer = csv.DictWriter(stream, columns, extrasaction='ignore')
        writer.writeheader()
        for row in rows:
            writer.writerow(row)
