"""
``rotor-id campaign DIR --out OUTDIR [--config RUN.yaml] [--diagnose] [--jobs N]``.

A wind-tunnel entry, not one bag: every bag in DIR (a rosbag2 directory, or a loose
``.mcap`` / ``.db3`` file) is identified with its run description ``NAME.yaml`` beside it (or
the one ``--config``), with identify's adequacy check, and on request diagnosed, in parallel
worker processes. A progress line on stderr counts the bags done, failed and up to date and
estimates the time left. Each bag's results go to ``OUTDIR/points/NAME/`` (identify JSON, fit
figure, diagnosis JSON, and ``result.json`` last, with the key it is valid for). A second run
skips every bag whose ``result.json`` key still matches: the bag's files (names, sizes, mtimes),
the run description's content, the options and the tool (version and the hash of its sources).
A bag that fails is reported in one line and recorded; the others carry on (failures are not
cached: the next run tries them again).

The campaign report: ``OUTDIR/campaign.csv`` (columns ``bag``, ``NAME`` and ``NAME_std`` for
every parameter, then status, convergence, adequacy and diagnosis verdicts, noise, window and
the conditions), ``OUTDIR/campaign.md`` (every test point with its conditions, parameters ± σ,
noise and verdicts; outliers, inadequate fits and failures) and a trend figure per parameter,
``OUTDIR/trend_NAME.png``: value ± σ against a condition (``--trend-against``), with a smooth
weighted trend, inadequate fits and outliers (more than 3 σ from the trend through the others)
flagged.

Conditions of a test point: the run description's ``rotor`` (advance_ratio, flap_frequency,
blades) and ``conditions:`` keys, the bag's ``custom_data`` (rosbag2 metadata), and what the
record says in the window: mean rotor speed, mean collective pitch, stirring direction and rate.
"""

import argparse
from concurrent.futures import as_completed, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
import csv
from dataclasses import dataclass
import hashlib
import importlib.metadata
import json
import math
import os
from pathlib import Path
import sys
import time
from typing import Any, Mapping, Sequence, TextIO, TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from rotor_id.io.record import Record
    from rotor_id.io.run_description import RunDescription

#: Bump when the content of result.json changes meaning (old results are then re-made).
RESULT_FORMAT = 1
BAG_SUFFIXES = ('.mcap', '.db3')
#: Numeric conditions measured or read for every test point, in the order of the CSV.
STANDARD_CONDITIONS = ('advance_ratio', 'collective_rad', 'rotor_speed_rad_s',
                       'stirring_direction', 'stirring_rate_per_rev', 'flap_frequency',
                       'blades')
#: Default trend abscissa: the first of these that varies over the campaign.
TREND_PREFERENCE = ('advance_ratio', 'collective_rad', 'rotor_speed_rad_s',
                    'stirring_rate_per_rev', 'flap_frequency')
#: A point further than this many σ from the trend through the other points is an outlier.
OUTLIER_SIGMA = 3.0
USER_ERRORS = (ValueError, FileNotFoundError, PermissionError, KeyError)
#: One test point's result.json (and a campaign.csv row): a JSON object.
Summary = dict[str, Any]
#: Per parameter: abscissa, values, σ and masks (:func:`analyse`).
Analysis = dict[str, dict[str, np.ndarray]]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``rotor-id campaign``."""
    parser.add_argument('directory', help='directory of bags (rosbag2 directories or .mcap/.db3 '
                        'files), each with its run description NAME.yaml beside it')
    parser.add_argument('--out', required=True, help='output directory (created; results in '
                        'it are reused when up to date)')
    parser.add_argument('--config', help='one run description for every bag (instead of '
                        'NAME.yaml beside each)')
    parser.add_argument('--diagnose', action='store_true',
                        help='also run rotor-id diagnose on every bag (slower)')
    parser.add_argument('--jobs', type=int, default=None,
                        help='worker processes (default: the cores this process may use)')
    parser.add_argument('--trend-against', dest='trend_against', default=None, metavar='KEY',
                        help='condition on the abscissa of the trend plots (default: the '
                        'first that varies of ' + ', '.join(TREND_PREFERENCE) + ')')
    parser.add_argument('--no-figures', dest='figures', action='store_false',
                        help='skip the per-bag fit figures (the trend plots are still made)')
    parser.add_argument('--force', action='store_true',
                        help='redo every bag even when its results are up to date')


# ------------------------------------------------------------------------------------------------
# Test points and their keys
# ------------------------------------------------------------------------------------------------

@dataclass
class TestPoint:
    """One bag of the campaign and the run description it is identified with."""

    name: str
    bag: Path
    config: Path | None = None

    def key(self, options: Mapping[str, Any], tool: str) -> str:
        """Return the key its results are valid for: bag files, description, options, tool."""
        digest = hashlib.sha256()
        files = sorted(p for p in self.bag.rglob('*') if p.is_file()) if self.bag.is_dir() \
            else [self.bag]
        for path in files:
            stat = path.stat()
            digest.update(f'{path.name}\0{stat.st_size}\0{stat.st_mtime_ns}\0'.encode())
        digest.update(self.config.read_bytes() if self.config else b'')
        digest.update(json.dumps(options, sort_keys=True).encode())
        digest.update(tool.encode())
        return digest.hexdigest()


def find_test_points(directory: str | os.PathLike,
                     config: str | os.PathLike | None = None) -> list[TestPoint]:
    """Return the bags in ``directory`` (sorted by name) with their run descriptions."""
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f'{directory} is not a directory; give the directory that holds '
                                "the campaign's bags")
    points = []
    for path in sorted(directory.iterdir()):
        if path.is_dir() and ((path / 'metadata.yaml').is_file()
                              or any(p.suffix in BAG_SUFFIXES for p in path.iterdir())):
            name = path.name
        elif path.is_file() and path.suffix in BAG_SUFFIXES:
            name = path.stem
        else:
            continue
        own = directory / f'{name}.yaml'
        beside = own if own.is_file() else None
        points.append(TestPoint(name=name, bag=path, config=Path(config) if config else beside))
    if not points:
        raise FileNotFoundError(f'no bags in {directory} (rosbag2 directories with '
                                'metadata.yaml, or .mcap/.db3 files)')
    names = [p.name for p in points]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f'{directory}: {", ".join(twice)} appear both as a bag directory and a '
                         'loose bag file; keep one of each name')
    return points


def tool_version() -> str:
    """Return the version of rotor_id and a hash of its Python sources."""
    try:
        version = importlib.metadata.version('rotor_id')
    except importlib.metadata.PackageNotFoundError:
        version = 'unknown'
    digest = hashlib.sha256()
    package = Path(__file__).resolve().parents[1]
    for path in sorted(package.rglob('*.py')):
        digest.update(path.relative_to(package).as_posix().encode() + b'\0')
        digest.update(path.read_bytes())
    return f'rotor_id {version} ({digest.hexdigest()[:12]})'


# ------------------------------------------------------------------------------------------------
# One test point (runs in a worker process)
# ------------------------------------------------------------------------------------------------

def _bag_custom_data(bag):
    """Return the ``custom_data`` of a rosbag2 directory's metadata.yaml (text values), or {}."""
    meta = (bag if bag.is_dir() else bag.parent) / 'metadata.yaml'
    if not meta.is_file():
        return {}
    import yaml
    try:
        info = yaml.safe_load(meta.read_text()) or {}
    except (OSError, yaml.YAMLError):
        return {}
    custom = (info.get('rosbag2_bagfile_information') or {}).get('custom_data') or {}
    out = {}
    for name, value in custom.items():
        try:
            out[str(name)] = float(value)
        except (TypeError, ValueError):
            out[str(name)] = str(value)
    return out


def measured_conditions(record: 'Record',
                        description: 'RunDescription') -> dict[str, float | str]:
    """Conditions of a test point: rotor, record in the window, description, bag metadata."""
    from rotor_id.physics.stirring import measured_stirring, multiblade_from_blade_pitch
    part = record.window(*description.window_s)
    u = multiblade_from_blade_pitch(part.t, part.blade_pitch)
    direction, rate = measured_stirring(part.t, u)
    conditions: dict[str, float | str] = {
        'advance_ratio': float(description.rotor.advance_ratio),
        'collective_rad': float(np.mean(u[:, 0])),
        'rotor_speed_rad_s': float(part.omega_mean),
        'stirring_direction': direction,
        'stirring_rate_per_rev': float(rate),
        'flap_frequency': float(description.rotor.flap_frequency),
        'blades': int(description.rotor.blades),
    }
    return conditions


def _one_line(exc):
    text = ' '.join(str(exc).split()) or type(exc).__name__
    return text if isinstance(exc, USER_ERRORS) else f'unexpected {type(exc).__name__}: {text}'


def _write_json(path, data):
    tmp = path.with_suffix('.tmp')
    tmp.write_text(json.dumps(data, indent=1, default=float))
    tmp.replace(path)              # result.json appears whole or not at all


def process_point(point: TestPoint, out_dir: str | os.PathLike, options: Mapping[str, Any],
                  key: str) -> Summary:
    """
    Identify (and diagnose) one test point; return its summary (also written as result.json).

    Never raises: a failure is the summary's ``status`` 'failed' with a one-line ``error``.
    """
    import warnings
    from rotor_id import pipeline
    from rotor_id.commands.common import repairs_json
    from rotor_id.commands.identify import load_inputs, plot_fit
    started = time.perf_counter()
    folder = Path(out_dir) / 'points' / point.name
    folder.mkdir(parents=True, exist_ok=True)
    summary: Summary = {
        'format': RESULT_FORMAT, 'key': key, 'bag': point.name, 'bag_path': str(point.bag),
        'config': str(point.config) if point.config else None, 'status': 'failed',
        'error': '', 'conditions': _bag_custom_data(point.bag), 'warnings': []}
    try:
        if point.config is None:
            raise FileNotFoundError(f'no run description {point.name}.yaml beside the bag; '
                                    'write one or give --config')
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter('always')
            description, record = load_inputs(point.bag, point.config)
            summary['conditions'].update(description.conditions)
            summary['conditions'].update(measured_conditions(record, description))
            result = pipeline.identify(record, description)
        data = result.as_json()
        data['bag'] = str(point.bag)
        data['repairs'] = repairs_json([record])
        _write_json(folder / 'identify.json', data)
        if options.get('figures', True):
            plot_fit(result, record, folder / 'fit.png', title=f'{point.name}: '
                     f'{description.model} ({", ".join(description.unknowns)})')
        adequacy = data.get('adequacy') or {}
        summary.update({
            'status': 'ok' if data['converged'] else 'not converged',
            'model': data['model'],
            'converged': data['converged'],
            'parameters': data['parameters'],
            'noise_std': data['noise_std'],
            'channels': data['channels'],
            'window_s': data['window_s'],
            'iterations': data['iterations'],
            'adequacy': adequacy.get('verdict', 'not_checked'),
            'warnings': [str(w.message) for w in caught] + list(data.get('warnings', [])),
            'repairs': data['repairs'],
        })
        if options.get('diagnose'):
            from rotor_id.diagnosis.diagnose import diagnose
            diagnosis = diagnose(record, description, workers=1).as_json()
            diagnosis['repairs'] = data['repairs']
            _write_json(folder / 'diagnose.json', diagnosis)
            summary['diagnosis'] = diagnosis['explanation']['effect']
            summary['diagnosis_confidence'] = diagnosis['explanation']['confidence']
    except Exception as exc:  # noqa: B902 - one bag's failure is recorded, the campaign goes on
        summary['status'] = 'failed'
        summary['error'] = _one_line(exc)
    summary['elapsed_s'] = time.perf_counter() - started
    if summary['status'] != 'failed':
        _write_json(folder / 'result.json', summary)
    else:
        (folder / 'result.json').unlink(missing_ok=True)
    return summary


def cached_summary(point: TestPoint, out_dir: str | os.PathLike, key: str) -> Summary | None:
    """Return the point's result.json when its key matches, else None."""
    path = Path(out_dir) / 'points' / point.name / 'result.json'
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if summary.get('key') != key or summary.get('format') != RESULT_FORMAT:
        return None
    return summary


# ------------------------------------------------------------------------------------------------
# Running the campaign
# ------------------------------------------------------------------------------------------------

def _clock(seconds):
    seconds = int(round(seconds))
    return f'{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}'


class Progress:
    """The progress line: done, failed, up to date, elapsed, time left (stderr)."""

    def __init__(self, total: int, stream: TextIO | None = None) -> None:
        self.total = total
        self.stream = stream or sys.stderr
        self.started = time.perf_counter()
        self.done = self.failed = self.cached = 0
        # (hasattr is False for None)
        self.tty = hasattr(stream, 'isatty') and stream.isatty()  # type: ignore[union-attr]

    def point(self, summary: Mapping[str, Any], cached: bool = False) -> None:
        """Count one finished point and show the line."""
        self.done += 1
        self.cached += bool(cached)
        if summary['status'] == 'failed':
            self.failed += 1
            self._clear()
            print(f'campaign: {summary["bag"]} failed: {summary["error"]}', file=self.stream,
                  flush=True)
        self.show()

    def _clear(self):
        if self.tty:
            print('\r\033[K', end='', file=self.stream)

    def show(self) -> None:
        """Print the progress line (rewritten in place on a terminal)."""
        elapsed = time.perf_counter() - self.started
        worked = self.done - self.cached
        left = self.total - self.done
        if left == 0:
            eta = 'finished'
        elif worked:
            eta = f'~{_clock(elapsed / worked * left)} left'
        else:
            eta = 'time left unknown yet'
        line = (f'campaign: {self.done}/{self.total} bags done ({self.failed} failed, '
                f'{self.cached} up to date), {_clock(elapsed)} elapsed, {eta}')
        if self.tty:
            print('\r\033[K' + line, end='' if left else '\n', file=self.stream, flush=True)
        else:
            print(line, file=self.stream, flush=True)


def run_points(points: Sequence[TestPoint], out_dir: str | os.PathLike,
               options: Mapping[str, Any], jobs: int, force: bool = False,
               stream: TextIO | None = None) -> list[Summary]:
    """Process every point (in ``jobs`` processes); return their summaries in point order."""
    tool = tool_version()
    keys = [p.key(options, tool) for p in points]
    summaries: list[Any] = [None] * len(points)     # every entry set below
    progress = Progress(len(points), stream)
    progress.show()
    todo = []
    for i, (point, key) in enumerate(zip(points, keys)):
        cached = None if force else cached_summary(point, out_dir, key)
        if cached is not None:
            summaries[i] = cached
            progress.point(cached, cached=True)
        else:
            todo.append(i)
    if jobs <= 1 or len(todo) <= 1:
        for i in todo:
            summaries[i] = process_point(points[i], out_dir, options, keys[i])
            progress.point(summaries[i])
        return summaries
    with ProcessPoolExecutor(max_workers=min(jobs, len(todo))) as pool:
        futures = {pool.submit(process_point, points[i], out_dir, options, keys[i]): i
                   for i in todo}
        for future in as_completed(futures):
            i = futures[future]
            try:
                summaries[i] = future.result()
            except BrokenProcessPool as exc:       # a worker died (killed, out of memory)
                summaries[i] = {'bag': points[i].name, 'bag_path': str(points[i].bag),
                                'status': 'failed', 'conditions': {},
                                'error': f'worker process died ({exc})'}
            progress.point(summaries[i])
    return summaries


# ------------------------------------------------------------------------------------------------
# The report
# ------------------------------------------------------------------------------------------------

def parameter_names(summaries: list[Summary]) -> list[str]:
    """Every parameter identified in the campaign, in first-seen order."""
    names = []
    for s in summaries:
        for name in s.get('parameters') or {}:
            if name not in names:
                names.append(name)
    return names


def condition_names(summaries: list[Summary]) -> list[str]:
    """Return the standard conditions, then every other condition met, sorted."""
    extra = sorted({k for s in summaries for k in s.get('conditions', {})}
                   - set(STANDARD_CONDITIONS))
    return list(STANDARD_CONDITIONS) + extra


def _numeric(value):
    return isinstance(value, (int, float)) and not isinstance(value, bool) \
        and math.isfinite(value)


def trend_key(summaries: list[Summary], requested: str | None = None) -> str:
    """Return the condition to plot against: the requested one, else the first that varies."""
    names = condition_names(summaries)
    if requested is not None:
        if requested == 'bag':
            return requested
        values = [s.get('conditions', {}).get(requested) for s in summaries]
        if not any(_numeric(v) for v in values):
            numeric = [n for n in names if any(_numeric(s.get('conditions', {}).get(n))
                                               for s in summaries)]
            raise ValueError(f'--trend-against {requested}: no numeric condition of that name; '
                             f'the campaign has {", ".join(numeric + ["bag"])}')
        return requested
    custom = [n for n in names if n not in STANDARD_CONDITIONS]
    for name in custom + list(TREND_PREFERENCE):
        values = {round(s['conditions'][name], 9) for s in summaries
                  if _numeric(s.get('conditions', {}).get(name))}
        if len(values) > 1:
            return name
    return 'bag'


def _abscissa(summaries, key):
    if key == 'bag':
        return np.arange(len(summaries), dtype=float)
    return np.array([float(s['conditions'][key]) if _numeric(s.get('conditions', {}).get(key))
                     else np.nan for s in summaries])


def _weighted_poly(x, y, sigma, degree):
    """Weighted least-squares polynomial: coefficients and their covariance (scaled by χ²)."""
    A = np.vander(x, degree + 1)
    w = 1.0 / sigma
    coef, *_ = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)
    cov = np.linalg.pinv((A * w[:, None]).T @ (A * w[:, None]))
    dof = x.size - degree - 1
    if dof > 0:
        chi2 = float(np.sum(((y - A @ coef) * w) ** 2)) / dof
        cov = cov * max(1.0, chi2)       # scatter beyond the bounds widens the trend's band
    return coef, cov


def _degree(x):
    """Trend degree: at most 2, and at least 2 points more than coefficients beyond a line."""
    distinct = np.unique(np.round(x, 12)).size
    return int(max(0, min(2, distinct - 1, (x.size - 1) // 3)))


def trend_outliers(x: np.ndarray, y: np.ndarray, sigma: np.ndarray,
                   usable: np.ndarray) -> np.ndarray:
    """
    Outliers: more than :data:`OUTLIER_SIGMA` from the smooth trend through the other points.

    The trend is a weighted polynomial (degree ≤ 2, lower with few distinct abscissae) fitted
    without the point tested (leave one out), and the distance counts both the point's σ and
    the trend's own uncertainty there. Returns the z of every usable point (NaN elsewhere).
    """
    z = np.full(x.size, np.nan)
    idx = np.flatnonzero(usable)
    for i in idx:
        others = idx[idx != i]
        degree = _degree(x[others])
        if others.size < degree + 2:
            continue
        coef, cov = _weighted_poly(x[others], y[others], sigma[others], degree)
        a = np.vander([x[i]], degree + 1)[0]
        z[i] = (y[i] - a @ coef) / math.sqrt(sigma[i] ** 2 + float(a @ cov @ a))
    return z


def analyse(summaries: list[Summary], key: str) -> Analysis:
    """Per parameter: abscissa, values, σ, usable/inadequate masks, z and outlier mask."""
    x = _abscissa(summaries, key)
    out = {}
    for name in parameter_names(summaries):
        y = np.array([s['parameters'][name]['value'] if name in (s.get('parameters') or {})
                      else np.nan for s in summaries])
        sigma = np.array([s['parameters'][name]['std'] if name in (s.get('parameters') or {})
                          else np.nan for s in summaries])
        identified = np.isfinite(x) & np.isfinite(y) & np.isfinite(sigma) & (sigma > 0)
        converged = np.array([bool(s.get('converged')) for s in summaries])
        inadequate = np.array([s.get('adequacy') == 'inadequate' for s in summaries])
        usable = identified & converged & ~inadequate
        z = trend_outliers(x, y, sigma, usable)
        out[name] = {'x': x, 'y': y, 'sigma': sigma, 'identified': identified,
                     'usable': usable, 'inadequate': identified & (inadequate | ~converged),
                     'z': z, 'outlier': np.abs(np.nan_to_num(z)) > OUTLIER_SIGMA}
    return out


def plot_trends(summaries: list[Summary], key: str, analysis: Analysis,
                out_dir: str | os.PathLike) -> list[Path]:
    """One figure per parameter: value ± σ against ``key``; return the paths."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    paths = []
    directions = [s.get('conditions', {}).get('stirring_direction', 'none') for s in summaries]
    markers = {'progressing': 'o', 'regressing': 's', 'none': 'D'}
    for name, a in analysis.items():
        fig, ax = plt.subplots(figsize=(7.5, 4.2))
        for direction, marker in markers.items():
            sel = a['identified'] & ~a['inadequate'] & (np.array(directions) == direction)
            if np.any(sel):
                ax.errorbar(a['x'][sel], a['y'][sel], yerr=a['sigma'][sel], fmt=marker, ms=5,
                            color='C0', ecolor='0.45', capsize=2, lw=1,
                            label=f'{direction} (±1σ Cramér-Rao)')
        bad = a['inadequate']
        if np.any(bad):
            ax.errorbar(a['x'][bad], a['y'][bad], yerr=a['sigma'][bad], fmt='s', ms=8,
                        mfc='none', mec='C3', ecolor='C3', capsize=2, lw=1,
                        label='inadequate fit or not converged')
        keep = a['usable'] & ~a['outlier']
        if np.count_nonzero(keep) >= 2:
            degree = _degree(a['x'][keep])
            coef, cov = _weighted_poly(a['x'][keep], a['y'][keep], a['sigma'][keep], degree)
            grid = np.linspace(np.min(a['x'][keep]), np.max(a['x'][keep]), 200)
            A = np.vander(grid, degree + 1)
            band = np.sqrt(np.einsum('ij,jk,ik->i', A, cov, A))
            ax.plot(grid, A @ coef, '-', color='C1', lw=1.2, label=f'weighted trend (degree '
                    f'{degree}) ±1σ')
            ax.fill_between(grid, A @ coef - band, A @ coef + band, color='C1', alpha=0.2)
        if np.any(a['outlier']):
            ax.plot(a['x'][a['outlier']], a['y'][a['outlier']], 'x', color='C3', ms=12, mew=2,
                    label=f'outlier (> {OUTLIER_SIGMA:g}σ from the trend)')
            for i in np.flatnonzero(a['outlier']):
                ax.annotate(summaries[i]['bag'], (a['x'][i], a['y'][i]), fontsize=7,
                            xytext=(4, 4), textcoords='offset points', color='C3')
        ax.set_xlabel('test point (bag order)' if key == 'bag' else key)
        ax.set_ylabel(name)
        ax.set_title(f'{name} against {key}: {int(np.count_nonzero(a["identified"]))} test '
                     f'points', fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc='best')
        fig.tight_layout()
        path = Path(out_dir) / f'trend_{name}.png'
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths


def _cell(value):
    if value is None:
        return ''
    if isinstance(value, float):
        return f'{value:.6g}'
    return str(value)


def csv_rows(summaries: list[Summary]) -> tuple[list[str], list[list[str]]]:
    """Header and rows of campaign.csv."""
    params = parameter_names(summaries)
    conditions = condition_names(summaries)
    header = ['bag']
    for name in params:
        header += [name, f'{name}_std']
    header += ['status', 'converged', 'adequacy', 'diagnosis', 'noise_std_rad',
               'window_start_s', 'window_end_s', 'model'] + conditions + ['error', 'warnings']
    rows = []
    for s in summaries:
        row = [s['bag']]
        for name in params:
            p = (s.get('parameters') or {}).get(name)
            row += [repr(p['value']), repr(p['std'])] if p else ['', '']
        noise = s.get('noise_std')
        window = s.get('window_s') or ['', '']
        row += [s['status'], _cell(s.get('converged')), s.get('adequacy', ''),
                s.get('diagnosis', ''),
                repr(float(np.sqrt(np.mean(np.square(noise))))) if noise else '',
                _cell(window[0]), _cell(window[1]), s.get('model', '')]
        row += [_cell(s.get('conditions', {}).get(c)) for c in conditions]
        row += [s.get('error', ''), ' | '.join(dict.fromkeys(s.get('warnings') or []))]
        rows.append(row)
    return header, rows


def _pm(p):
    return f'{p["value"]:.4g} ± {p["std"]:.2g}'


def markdown_report(summaries: list[Summary], key: str, analysis: Analysis,
                    figures: Sequence[Path], directory: str | os.PathLike,
                    options: Mapping[str, Any], tool: str) -> str:
    """Return the campaign report (Markdown): figures, flags, every test point, failures."""
    params = parameter_names(summaries)
    n = len(summaries)
    failed = [s for s in summaries if s['status'] == 'failed']
    inadequate = [s for s in summaries if s.get('adequacy') == 'inadequate']
    unconverged = [s for s in summaries if s['status'] == 'not converged']
    lines = [f'# Campaign {Path(directory).name}', '',
             f'{n} test points from `{directory}`: {n - len(failed)} identified '
             f'({len(unconverged)} not converged, {len(inadequate)} inadequate fits), '
             f'{len(failed)} failed. Diagnosis: {"yes" if options.get("diagnose") else "not run"}'
             f'. Trends against `{key}`. {tool}; written {time.strftime("%Y-%m-%d %H:%M")}.',
             '', 'Values ± σ are the Cramér-Rao bounds of each fit; noise is the RMS over the '
             "model's channels of the estimated measurement-noise σ (rad). An outlier lies more "
             f'than {OUTLIER_SIGMA:g}σ from the smooth weighted trend through the other '
             "adequate points (its own σ and the trend's combined).", '', '## Trends', '']
    for path in figures:
        lines += [f'![{path.stem}]({path.name})', '']
    flags = []
    for name, a in analysis.items():
        for i in np.flatnonzero(a['outlier']):
            flags.append(f'- outlier: `{summaries[i]["bag"]}` {name} = '
                         f'{_pm(summaries[i]["parameters"][name])}, {a["z"][i]:+.1f}σ from the '
                         'trend through the others')
    for s in inadequate:
        flags.append(f'- inadequate fit: `{s["bag"]}` (residuals are not the noise the bounds '
                     'assume; see its identify.json, or run with --diagnose)')
    for s in unconverged:
        flags.append(f'- not converged: `{s["bag"]}`')
    for s in summaries:
        warned = list(dict.fromkeys(s.get('warnings') or []))
        if warned:
            more = f' (and {len(warned) - 1} more in campaign.csv)' if len(warned) > 1 else ''
            flags.append(f'- warning: `{s["bag"]}`: {warned[0]}{more}')
    lines += ['## Flags', ''] + (flags or ['none']) + ['']
    # the conditions that vary (the constant ones are in the CSV)
    conditions = [c for c in condition_names(summaries)
                  if len({_cell(s['conditions'][c]) for s in summaries
                          if s.get('conditions', {}).get(c) is not None}) > 1]
    conditions = conditions or ['advance_ratio']
    lines += ['## Test points', '',
              '| bag | ' + ' | '.join(conditions + params) + ' | noise σ [rad] | adequacy | '
              'diagnosis | status |',
              '|' + '---|' * (len(conditions) + len(params) + 5)]
    for s in summaries:
        cells = [f'`{s["bag"]}`'] + [_cell(s.get('conditions', {}).get(c)) for c in conditions]
        cells += [_pm(s['parameters'][p]) if p in (s.get('parameters') or {}) else ''
                  for p in params]
        noise = s.get('noise_std')
        cells += [f'{float(np.sqrt(np.mean(np.square(noise)))):.3g}' if noise else '',
                  s.get('adequacy', ''), s.get('diagnosis', '') or '', s['status']]
        lines.append('| ' + ' | '.join(cells) + ' |')
    if failed:
        lines += ['', '## Failures', '']
        lines += [f'- `{s["bag"]}`: {s.get("error", "")}' for s in failed]
    lines += ['', 'Per test point: `points/NAME/` (identify.json, fit.png, diagnose.json, '
              'result.json); all values: `campaign.csv`.', '']
    return '\n'.join(lines)


def write_report(summaries: list[Summary], out_dir: str | os.PathLike,
                 directory: str | os.PathLike, options: Mapping[str, Any],
                 requested_key: str | None = None) -> list[Path]:
    """Write campaign.csv, campaign.md and the trend figures; return their paths."""
    out_dir = Path(out_dir)
    header, rows = csv_rows(summaries)
    with open(out_dir / 'campaign.csv', 'w', newline='') as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)
    try:
        key = trend_key(summaries, requested_key)
    except ValueError as exc:           # checked before the work; only if the bags changed
        print(f'campaign: warning: {exc}; trends against the bag order', file=sys.stderr)
        key = 'bag'
    analysis = analyse(summaries, key)
    figures = plot_trends(summaries, key, analysis, out_dir)
    (out_dir / 'campaign.md').write_text(markdown_report(
        summaries, key, analysis, figures, directory, options, tool_version()))
    return [out_dir / 'campaign.csv', out_dir / 'campaign.md'] + figures


#: Standard conditions that are not numbers (no trend against them).
TEXT_CONDITIONS = ('stirring_direction',)


def _check_trend_key(points, requested):
    """Refuse an unknown or non-numeric --trend-against before any work."""
    standard = [c for c in STANDARD_CONDITIONS if c not in TEXT_CONDITIONS]
    if requested is None or requested == 'bag' or requested in standard:
        return
    from rotor_id.io.run_description import load_run_description
    numeric, text = set(), set()
    for point in points:
        conditions = dict(_bag_custom_data(point.bag))
        if point.config is not None:
            try:
                conditions.update(load_run_description(point.config).conditions)
            except ValueError:
                pass                   # that bag fails later, with its own message
        for name, value in conditions.items():
            (numeric if _numeric(value) else text).add(name)
    choices = ', '.join(standard + sorted(numeric) + ['bag'])
    if requested in numeric:
        return
    what = ('is not a number' if requested in text or requested in TEXT_CONDITIONS
            else 'is not a condition of any test point')
    raise ValueError(f'--trend-against {requested}: {what}; use one of {choices}')


def default_jobs() -> int:
    """Return the number of cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def run(args: argparse.Namespace) -> int:
    """Run the campaign; exit 0 when every bag was identified and converged, else 1."""
    jobs = default_jobs() if args.jobs is None else args.jobs
    if jobs < 1:
        raise ValueError(f'--jobs must be at least 1, got {jobs}')
    points = find_test_points(args.directory, args.config)
    if args.config and not Path(args.config).is_file():
        raise FileNotFoundError(f'--config {args.config} does not exist')
    _check_trend_key(points, args.trend_against)
    out_dir = Path(args.out)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f'--out {out_dir} exists and is not a directory')
    (out_dir / 'points').mkdir(parents=True, exist_ok=True)
    options = {'diagnose': bool(args.diagnose), 'figures': bool(args.figures)}
    print(f'campaign: {len(points)} bags in {args.directory}, {jobs} worker process'
          f'{"es" if jobs > 1 else ""}', file=sys.stderr, flush=True)
    started = time.perf_counter()
    summaries = run_points(points, out_dir, options, jobs, force=args.force)
    paths = write_report(summaries, out_dir, args.directory, options, args.trend_against)
    failed = sum(s['status'] == 'failed' for s in summaries)
    unconverged = sum(s['status'] == 'not converged' for s in summaries)
    print(f'{len(summaries) - failed} of {len(summaries)} bags identified ({unconverged} not '
          f'converged, {failed} failed) in {time.perf_counter() - started:.1f} s')
    for path in paths:
        print(f'report: {path}')
    return 0 if failed == 0 and unconverged == 0 else 1
