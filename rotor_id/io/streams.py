"""
Faults of one sampled stream as a test stand produces them (no ROS).

A topic's samples, in the order they were recorded, should carry increasing stamps from one
clock, one publisher, and (for the azimuth) a phase that follows the rotor speed. What goes
wrong on a rig, and how each is told from the others:

* clock reset / second run: the stamps jump back by far more than transport reordering
  (``RESET_PERIODS`` sample periods) and continue from there: two runs, the second overlapping or
  preceding the first in stamp time. Sorting by stamp would merge them, so they are separated
  (:func:`split_runs`) and the caller selects one.
* clock glitch: one or two samples whose stamps are far from their neighbours while the samples
  after them continue the earlier ones: dropped.
* several publishers on one topic: the merged stream has a period-2 structure that one sensor
  sampled well above the rotor's harmonics never has: alternate samples differ by a steady
  offset (raw vs. calibrated), or come in near-identical pairs (same noise twice), or the stamp
  steps alternate short/long (:func:`interleaved_streams`).
* azimuth glitch or encoder slip: the measured phase leaves what the rotor speed predicts and
  returns (glitch, repaired) or stays off (slip, reported) (:func:`phase_outliers`).
* value spike of a flap or pitch reading (a bit flip, a sample dropped to zero): one to
  ``REPAIR_MAX_SAMPLES`` samples of one blade leave the cubic through their neighbours by
  ``VALUE_SPIKE_SIGMAS`` robust noise σ and come back (:func:`value_spikes`, repaired by
  :func:`repair_value_spikes` in the reader and in each live window). A change that persists,
  or that other blades show at the same samples (a collective or cyclic step, a stirring
  start), is an input and is never repaired.
* dead flap sensor: one exact value over a whole window (:func:`stuck_channels`).
"""

from dataclasses import dataclass
import functools
from typing import Sequence

import numpy as np
import numpy.typing as npt

NS_PER_S = 1_000_000_000
#: A backward stamp step longer than this many sample periods (and RESET_MIN_S) is a clock
#: reset, not transport reordering (which moves a message by a few periods at most).
RESET_PERIODS = 50
RESET_MIN_S = 0.05
#: Samples delivered late by at most this much (a driver's buffer) fill their run's gap.
REORDER_MAX_S = 1.0
#: A piece of at most this many samples between two jumps, which the next samples do not
#: continue, is a clock glitch, not a run.
GLITCH_MAX_SAMPLES = 2
#: Interleaving test, on blocks of BLOCK samples (at least MIN_BLOCKS): the median block's
#: squared z of the alternate-sample offset must exceed OFFSET_MEDIAN_Z2 (half the blocks at
#: 3σ: for one stream a chance below 1e-4 with 4 blocks, far less with more), and the offset be
#: at least MIN_OFFSET_NOISE_RATIO noise σ; or the step variance must differ by
#: MIN_PAIR_VARIANCE_RATIO between alternate steps, on the same parity in every block.
BLOCK = 128
MIN_BLOCKS = 4
MAX_BLOCKS = 256                  # blocks spread over a long record (a merged stream is in all)
OFFSET_MEDIAN_Z2 = 9.0
MIN_OFFSET_NOISE_RATIO = 0.5
MIN_PAIR_VARIANCE_RATIO = 4.0
CHI2_1_MEDIAN = 0.4549
STEADY_PARITY = 0.9               # the near-duplicates sit at the same parity in 95 % of blocks
#: Phase outliers: robust threshold in noise σ, and how long a repaired stretch may be.
OUTLIER_SIGMAS = 10.0
MEDIAN_SPAN = 11
REPAIR_MAX_SAMPLES = 5


@dataclass
class RunSplit:
    """
    Samples of one topic grouped into runs, in recording order.

    Attributes
    ----------
    labels
        (n,) run number of each sample (0-based, in order of first appearance), or -1 for a
        clock glitch.
    jumps
        Index (in recording order) of every sample where the stamps jump back to start or
        resume another run.
    period_ns
        Median stamp step, ns.

    """

    labels: np.ndarray
    jumps: np.ndarray
    period_ns: float

    @property
    def n_runs(self) -> int:
        """Return the number of runs."""
        return int(self.labels.max()) + 1 if self.labels.size else 0

    def glitches(self) -> np.ndarray:
        """Return the indices of the glitch samples."""
        return np.flatnonzero(self.labels < 0)

    def interleaved(self) -> bool:
        """Return True if samples of different runs alternate (several clocks at once)."""
        runs = self.labels[self.labels >= 0]
        return int(np.count_nonzero(np.diff(runs) != 0)) > 2 * max(self.n_runs - 1, 0)


def split_runs(stamps_ns: npt.ArrayLike, received_ns: npt.ArrayLike | None = None) -> RunSplit:
    """
    Group stamps given in recording order into runs separated by clock resets.

    A jump (backward by more than ``RESET_PERIODS`` periods, or forward by as much) cuts the
    sequence into pieces; each piece joins the earlier run whose last stamp lies closest below
    its first stamp (so a gap, or the return after a glitch, continues the run), else it
    starts a new run. A forward jump of the stamps while the receive times advance less than
    half as much is the sensor's clock stepping, not samples lost: a new run too. Runs of at
    most ``GLITCH_MAX_SAMPLES`` samples are glitches.

    Parameters
    ----------
    stamps_ns
        (n,) int64 stamps in the order the messages were recorded.
    received_ns
        (n,) receive times of the same messages, or None.

    Returns
    -------
    RunSplit.

    """
    stamps: np.ndarray = np.asarray(stamps_ns, dtype=np.int64)
    n = stamps.size
    steps = np.diff(stamps)
    if np.count_nonzero(steps < 0) > 0.1 * steps.size:    # clocks taking turns: steps say nothing
        steps = np.diff(np.sort(stamps))
    positive = steps[steps > 0]
    period = float(np.median(positive)) if positive.size else 0.0
    steps = np.diff(stamps)
    limit = max(RESET_PERIODS * period, RESET_MIN_S * NS_PER_S)
    cuts = np.flatnonzero((steps < -limit) | (steps > limit)) + 1
    labels = np.zeros(n, dtype=np.int64)
    if not cuts.size:
        return RunSplit(labels, cuts, period)
    starts = np.concatenate([[0], cuts])
    ends = np.concatenate([cuts, [n]])
    sizes = ends - starts
    # A short piece is a glitch when the pieces either side of it join up (or it is at an end).
    short = sizes <= GLITCH_MAX_SAMPLES
    glitch_piece = short.copy()
    for j in np.flatnonzero(short):
        if 0 < j < len(starts) - 1:
            bridge = stamps[starts[j + 1]] - stamps[ends[j - 1] - 1]
            # (short pieces on both sides: clocks taking turns, not a glitch)
            glitch_piece[j] = 0 < bridge <= limit and not (short[j - 1] and short[j + 1])
    received = None if received_ns is None else np.asarray(received_ns, dtype=np.int64)
    last: list[int] = []        # last stamp of each run so far
    run_of_piece = []
    previous = None             # last sample of the previous piece that is no glitch
    for start, end, is_glitch in zip(starts, ends, glitch_piece):
        if is_glitch:
            run_of_piece.append(-1)
            continue
        first = stamps[start]
        # the stamps step ahead while the messages keep arriving: the clock stepped
        stepped = previous is not None and received is not None and (
            first - stamps[previous] > limit
            and received[start] - received[previous] < (first - stamps[previous]) // 2)
        previous = end - 1
        # (after a clock step only a run that this piece continues closely can take it)
        below = [(first - stamp, run) for run, stamp in enumerate(last)
                 if stamp < first and (not stepped or first - stamp <= limit)]
        if below:
            run = min(below)[1]
        else:
            run = _hole_filled(stamps, starts, ends, run_of_piece, start, end, period, last)
        if run is None:
            run = len(last)
            last.append(int(stamps[start:end].max()))
        else:
            last[run] = max(last[run], int(stamps[start:end].max()))
        run_of_piece.append(run)
    sizes = np.zeros(len(last), dtype=np.int64)
    for start, end, run in zip(starts, ends, run_of_piece):
        if run >= 0:
            sizes[run] += end - start
    glitch = sizes <= GLITCH_MAX_SAMPLES
    if not len(last) or glitch.all():   # nothing but short pieces: no structure to trust
        return RunSplit(np.zeros(n, dtype=np.int64), np.empty(0, dtype=np.int64), period)
    renumber = np.full(len(last) + 1, -1)          # index -1: glitch pieces
    renumber[:-1][~glitch] = np.arange(np.count_nonzero(~glitch))
    for start, end, run in zip(starts, ends, run_of_piece):
        labels[start:end] = renumber[run]
    # a jump is where a sample's run differs from the previous real sample's run
    real = np.flatnonzero(labels >= 0)
    jumps = real[1:][np.diff(labels[real]) != 0]
    return RunSplit(labels, np.asarray(jumps, dtype=np.int64), period)


def _hole_filled(stamps, starts, ends, run_of_piece, start, end, period, last):
    """
    Return the run whose gap the piece stamps[start:end] fills (samples delivered late), or None.

    A late burst lands where its run has no samples (each of its stamps at least 3/4 of a
    period from the run's), at most REORDER_MAX_S before the run's latest stamp; a second
    run after a clock reset lands on stamps its predecessor already covers (within half a
    period), or outside its recent span.
    """
    piece = stamps[start:end]
    for run, latest in enumerate(last):
        if piece.max() > latest or piece.min() < latest - REORDER_MAX_S * NS_PER_S:
            continue
        own = np.sort(np.concatenate([stamps[a:b] for a, b, r in zip(starts, ends, run_of_piece)
                                      if r == run]))
        if piece.min() < own[0] or piece.max() > own[-1]:
            continue
        at = np.clip(np.searchsorted(own, piece), 1, own.size - 1)
        nearest = np.minimum(np.abs(own[at] - piece), np.abs(piece - own[at - 1]))
        if np.all(nearest >= 0.75 * period):
            return run
    return None


@dataclass
class Interleaving:
    """
    Evidence that a stream is two streams merged (see :func:`interleaved_streams`).

    Attributes
    ----------
    offset
        Mean difference between alternate samples (units of the values), or 0.
    noise
        Sample-to-sample noise σ of the values.
    step_variance_ratio
        Ratio of the squared steps at the two parities (≥ 1).
    stamp_steps_ns
        Median stamp step at the two parities (equal for evenly spaced stamps).
    column
        Value column where the evidence is strongest.

    """

    offset: float
    noise: float
    step_variance_ratio: float
    stamp_steps_ns: tuple
    column: int

    def describe(self, unit: str = 'rad') -> str:
        """One phrase with the figures."""
        parts = []
        if self.offset:
            parts.append(f'alternate samples differ by {self.offset:.3g} {unit} on average '
                         f'(noise σ {self.noise:.3g} {unit})')
        if self.step_variance_ratio >= 1e30:          # (the quiet steps are exactly zero)
            parts.append('samples come in identical pairs (every other step is zero)')
        elif self.step_variance_ratio >= MIN_PAIR_VARIANCE_RATIO:
            parts.append('samples come in near-identical pairs (step variance differs '
                         f'{self.step_variance_ratio:.3g}x between alternate steps)')
        short, long = sorted(self.stamp_steps_ns)
        if long > 1.5 * short:
            parts.append(f'stamp steps alternate {short / 1e6:.4g} ms / {long / 1e6:.4g} ms')
        return '; '.join(parts)


def _blocks(values, block, most):
    """
    Return (K, block + 2, m) stretches of ``values``, at most ``most``, spread over the record.

    Each starts at an even index, so that a sample's parity within its stretch is its parity
    in the record.
    """
    n = values.shape[0]
    count = min((n - 2) // (block + 2), most)
    starts = np.linspace(0, n - block - 2, count).astype(np.int64) & ~1
    return values[starts[:, None] + np.arange(block + 2)]


def interleaved_streams(stamps_ns: npt.ArrayLike, values: npt.ArrayLike) -> Interleaving | None:
    """
    Test whether sorted samples are two interleaved streams (e.g. two publishers).

    One sensor sampled well above the signal's bandwidth gives alternate samples that differ
    only by noise. Two merged streams give, at alternate samples, a steady offset (different
    calibration) or near-duplicate values (the same measurement published twice). Both are
    measured block by block and judged on the median block, so that a pitch step or a short
    burst (one block) does not count, while a merged stream shows in every block.

    Parameters
    ----------
    stamps_ns
        (n,) increasing stamps.
    values
        (n, m) samples.

    Returns
    -------
    Interleaving, or None when the stream looks like one stream.

    """
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        values = values[:, None]
    n = values.shape[0]
    if n < MIN_BLOCKS * (BLOCK + 2) + 2:
        return None
    tiny = np.finfo(float).tiny
    blocks = _blocks(values, BLOCK, MAX_BLOCKS)              # (K, B + 2, m)
    steps = np.diff(blocks, axis=1)                          # (K, B + 1, m)
    curvature = steps[:, 1:] - steps[:, :-1]                 # (K, B, m): 6σ² for white noise
    # Noise σ: robust (median) for white noise, but never below the RMS estimate, which a
    # quantised sensor (most curvatures exactly 0) or a staircase signal (a command held
    # between updates) would otherwise drive to zero.
    noise = np.maximum(np.sqrt(np.median(curvature ** 2, axis=(0, 1)) / CHI2_1_MEDIAN / 6.0),
                       np.sqrt(np.mean(curvature ** 2, axis=(0, 1)) / 6.0))
    # ... nor below the values' floating-point resolution: a noiseless channel (a simulated or
    # computed azimuth, unwrapped to hundreds of rad) has only rounding left, whose pattern can
    # alternate with the sample's parity and is no second stream
    noise = np.maximum(noise, np.maximum(np.spacing(np.max(np.abs(values), axis=0)), tiny))
    # Offset: the detrended x[i] − (x[i−1] + x[i+1])/2 is ±δ at alternate samples for two
    # streams; its (−1)^i block mean is N(0, 3.5σ²/B) for one stream of white noise.
    signs = np.where(np.arange(BLOCK) % 2 == 0, 1.0, -1.0)
    means = np.einsum('kbm,b->km', -0.5 * curvature, signs) / BLOCK
    z2 = (means / noise) ** 2 * (BLOCK / 3.5)      # noise >= tiny: squaring it would underflow
    median_z2 = np.median(z2, axis=0)
    offset = np.sqrt(np.median(means ** 2, axis=0))
    by_offset = (median_z2 > OFFSET_MEDIAN_Z2) & (offset > MIN_OFFSET_NOISE_RATIO * noise)
    # Pairs: the squared steps at even and odd positions differ by a steady factor.
    even, odd = steps[:, 0:BLOCK:2] ** 2, steps[:, 1:BLOCK:2] ** 2
    log_ratio = np.log((even.mean(axis=1) + tiny) / (odd.mean(axis=1) + tiny))   # (K, m)
    pair_ratio = np.exp(np.median(np.abs(log_ratio), axis=0))
    steady = np.abs(np.mean(np.sign(log_ratio), axis=0)) >= STEADY_PARITY   # same parity
    # ... and the other parity changes at nearly every step, as a sensor does: a command held
    # for several samples (steps mostly exactly 0 at both parities) is not a duplicate pair
    loud = np.where((log_ratio > 0)[:, None, :], steps[:, 0:BLOCK:2], steps[:, 1:BLOCK:2])
    changing = np.mean(loud != 0, axis=(0, 1)) >= STEADY_PARITY
    by_pairs = (pair_ratio >= MIN_PAIR_VARIANCE_RATIO) & steady & changing
    flagged = by_offset | by_pairs
    if not flagged.any():
        return None
    strength = np.where(by_offset, offset / noise, 0.0) + np.where(by_pairs, pair_ratio, 0.0)
    column = int(np.argmax(strength))
    stamp_steps = np.diff(np.asarray(stamps_ns, dtype=np.int64))
    parity_steps = (float(np.median(stamp_steps[0::2])), float(np.median(stamp_steps[1::2])))
    return Interleaving(
        offset=float(offset[column]) if by_offset[column] else 0.0,
        noise=float(noise[column]),
        step_variance_ratio=float(pair_ratio[column]) if by_pairs[column] else 1.0,
        stamp_steps_ns=parity_steps, column=column)


@dataclass
class PhaseOutliers:
    """
    Samples whose phase leaves what the rotor speed predicts.

    Attributes
    ----------
    repaired
        Indices of bad samples in stretches of at most REPAIR_MAX_SAMPLES after which the
        phase comes back to the prediction (glitches), or at either end of the stream.
    slips
        (index of the first sample after the step, size in rad) of each lasting step.
    threshold
        Step deviation counted as an outlier, rad.

    """

    repaired: np.ndarray
    slips: list
    threshold: float


def _robust_threshold(residual, floor):
    spread = 1.4826 * np.median(np.abs(residual - np.median(residual)))
    return max(OUTLIER_SIGMAS * spread, float(floor))


def phase_outliers(step_residual: npt.ArrayLike, floor: float) -> PhaseOutliers:
    """
    Find glitches and lasting steps in a phase from its step residuals.

    Parameters
    ----------
    step_residual
        (n − 1,) measured phase step minus the step the rotor speed predicts, each wrapped to
        (−π, π], rad: ``step_residual[i]`` belongs to the step from sample i to i + 1.
    floor
        Smallest deviation worth calling an outlier, rad (e.g. a fraction of a sample's
        advance), used when the noise is tiny or quantised.

    Returns
    -------
    PhaseOutliers. A glitch shows as a step out and a step back (their sum is within the
    threshold); a slip as a step that is not undone.

    """
    residual = np.asarray(step_residual, dtype=float)
    n = residual.size + 1
    if residual.size < MEDIAN_SPAN:
        return PhaseOutliers(np.empty(0, dtype=np.int64), [], float(floor))
    residual = residual - np.median(residual)
    threshold = _robust_threshold(residual, floor)
    bad = np.flatnonzero(np.abs(residual) > threshold)
    repaired, slips = [], []
    if bad.size:
        # bad steps closer than a glitch's length belong to one event
        groups = np.split(bad, np.flatnonzero(np.diff(bad) > REPAIR_MAX_SAMPLES) + 1)
        for group in groups:
            first, last = int(group[0]), int(group[-1])
            net = float(np.sum(residual[first:last + 1]))
            inner = list(range(first + 1, last + 1))       # samples between the steps
            if abs(net) <= threshold and 0 < len(inner) <= REPAIR_MAX_SAMPLES:
                repaired.extend(inner)
            elif last < REPAIR_MAX_SAMPLES:                 # the stream starts off the phase
                repaired.extend(range(0, last + 1))
            elif first >= n - 1 - REPAIR_MAX_SAMPLES:       # ... or ends off it
                repaired.extend(range(first + 1, n))
            else:
                slips.append((first + 1, net))
    return PhaseOutliers(np.asarray(sorted(set(repaired)), dtype=np.int64), slips, threshold)


def spikes(values: npt.ArrayLike, floor: float) -> np.ndarray:
    """
    Find the isolated spikes of a slowly varying signal, each at most REPAIR_MAX_SAMPLES long.

    Parameters
    ----------
    values
        (n,) samples (e.g. the rotor speed).
    floor
        Smallest deviation from the running median worth calling a spike.

    Returns
    -------
    (k,) indices; longer excursions are left alone (they are the signal, or a fault that
    needs more than a repair).

    """
    values = np.asarray(values, dtype=float)
    if values.size < MEDIAN_SPAN:
        return np.empty(0, dtype=np.int64)
    residual = values - _running_median(values, MEDIAN_SPAN)
    threshold = _robust_threshold(residual, floor)
    out = [np.arange(a, b) for a, b in _stretches(np.abs(residual) > threshold)
           if b - a <= REPAIR_MAX_SAMPLES]
    return np.concatenate(out) if out else np.empty(0, dtype=np.int64)


def noise_scale(values: npt.ArrayLike) -> np.ndarray:
    """
    Return the robust noise σ of each column from the MAD of its second differences.

    The second difference of white noise of σ has variance 6σ²; the median absolute deviation
    (×1.4826) ignores the few large ones of a spike or a step, and a smooth signal's own
    curvature enters as noise (so a fast stirring is not taken for spikes). A column that
    moves in quantised steps (most second differences exactly 0) is given the quantisation
    noise q/√12 of its smallest step q: a one-step flicker of an encoder is noise, not a spike.
    """
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        values = values[:, None]
    second = np.diff(values, 2, axis=0)
    centre = np.median(second, axis=0)
    sigma = 1.4826 * np.median(np.abs(second - centre), axis=0) / np.sqrt(6.0)
    steps = np.abs(np.diff(values, axis=0))
    steps = np.where(steps > 0, steps, np.inf)
    smallest = steps.min(axis=0) if steps.size else np.full(values.shape[1], np.inf)
    quantum = np.where(np.isfinite(smallest), smallest / np.sqrt(12.0), 0.0)
    return np.maximum(sigma, quantum)


#: Prediction error of the cubic through two neighbours either side (weights −1/6, 2/3, 2/3,
#: −1/6 at the gap): its variance is (1 + 34/36) σ² for white noise of σ.
CUBIC_ERROR_GAIN = float(np.sqrt(1.0 + 34.0 / 36.0))
#: A value spike leaves that prediction by this many of its σ: a two-sided Gaussian tail of
#: 2.6e-12 a sample, below one false repair in 10⁴ hours of 8 channels at 1 kHz.
VALUE_SPIKE_SIGMAS = 7.0
#: Samples either side of a candidate spike from which its local noise σ is taken.
LOCAL_SPAN = 4 * MEDIAN_SPAN
#: A change of another blade's channel by this many of its σ at the same samples makes an
#: excursion common to the blades: an input (a collective or cyclic step), never a glitch.
#: (Gaussian noise exceeds 5σ once in 3.5 million samples.)
SHARED_SIGMAS = 5.0


def value_spikes(values: npt.ArrayLike,
                 groups: Sequence[Sequence[int]] | None = None) -> list[np.ndarray]:
    """
    Find the isolated spikes of each column of sampled angles (flap or pitch readings).

    A spike is a stretch of at most ``REPAIR_MAX_SAMPLES`` samples that

    * leaves the cubic through its two neighbours either side by more than
      ``VALUE_SPIKE_SIGMAS`` of that cubic's prediction error, from the column's robust noise σ
      (:func:`noise_scale`: MAD of the second differences);
    * comes back: its neighbours either side agree to within half its excursion (a step or a
      ramp that persists is the signal);
    * stands alone in time: no other excursion within ``MEDIAN_SPAN`` samples reaches half its
      size (a fast signal's peaks repeat);
    * stands alone among the blades: no other column of its group moves by ``SHARED_SIGMAS``
      of its own prediction error over the same samples. A change seen on every blade at once
      is an input (a collective or cyclic step, a stirring start), not a fault of one sensor.

    Parameters
    ----------
    values
        (n, m) samples in recording order, m channels.
    groups
        Lists of column indices that measure one quantity on the blades of one rotor (the
        blades' flap, the blades' pitch); default: all columns are one group.

    Returns
    -------
    List of m index arrays, one per column.

    """
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        values = values[:, None]
    n, m = values.shape
    if n < MEDIAN_SPAN:
        return [np.empty(0, dtype=np.int64) for _ in range(m)]
    if groups is None:
        groups = [list(range(m))]
    group_of = {k: [j for j in group if j != k] for group in groups for k in group}
    prediction = CUBIC_ERROR_GAIN * noise_scale(values)
    threshold = VALUE_SPIKE_SIGMAS * prediction
    # candidates: samples far from the running median (every column at once)
    residual = values - _running_median(values, MEDIAN_SPAN)
    outside = np.abs(residual) > threshold
    found = []
    for k in range(m):
        kept = []
        if outside[:, k].any():
            stretches, peaks = _cores(np.abs(residual[:, k]), outside[:, k])
            for j, (a, b) in enumerate(stretches):
                if b - a > REPAIR_MAX_SAMPLES or not _isolated(stretches, peaks, j):
                    continue
                if not _returns(values[:, k], a, b, threshold[k]):
                    continue
                # the noise σ here: a stirring is less predictable than the trim around it
                local = CUBIC_ERROR_GAIN * _local_noise(values[:, k], a, b)
                if local > prediction[k] and not _returns(values[:, k], a, b,
                                                          VALUE_SPIKE_SIGMAS * local):
                    continue
                if any(_shared(values[:, i], a, b, prediction[i]) for i in group_of.get(k, ())):
                    continue
                kept.append(np.arange(a, b))
        found.append(np.concatenate(kept) if kept else np.empty(0, dtype=np.int64))
    return found


@dataclass
class SpikeRepair:
    """The value spikes of one channel, replaced by :func:`repair_value_spikes`."""

    column: int
    indices: np.ndarray               # the samples replaced
    old: np.ndarray                   # their readings, as received
    new: np.ndarray                   # the cubic through their neighbours either side

    @property
    def count(self) -> int:
        """Return the number of samples replaced."""
        return int(self.indices.size)

    @property
    def worst(self) -> int:
        """Return the position (in ``indices``) of the sample that left its neighbours most."""
        return int(np.argmax(np.abs(self.old - self.new)))

    @property
    def index(self) -> int:
        """Return the sample index of the worst replaced sample."""
        return int(self.indices[self.worst])

    @property
    def value(self) -> float:
        """Return the worst replaced sample's reading, as received."""
        return float(self.old[self.worst])

    @property
    def neighbours(self) -> float:
        """Return what the interpolation put in place of the worst sample."""
        return float(self.new[self.worst])


def repair_value_spikes(times: np.ndarray, values: np.ndarray,
                        groups: Sequence[Sequence[int]] | None = None) -> list[SpikeRepair]:
    """
    Replace each column's spikes (:func:`value_spikes`) by the cubic through their neighbours.

    The one repair of flap/pitch readings: the bag reader calls it on each topic's samples, the
    live identifier on each window's record.

    Parameters
    ----------
    times
        (n,) increasing sample times (any unit: stamps in ns, seconds).
    values
        (n, m) float samples, m channels; repaired in place.
    groups
        As for :func:`value_spikes`.

    Returns
    -------
    list of :class:`SpikeRepair`, one per column that had spikes.

    """
    repairs = []
    for column, spiky in enumerate(value_spikes(values, groups)):
        if not spiky.size:
            continue
        mask = np.zeros(len(times), dtype=bool)
        mask[spiky] = True
        # the cubic through the neighbours, as the detection measured the excursion
        smooth = np.concatenate([_cubic_guess(values[:, column], a, b, times)
                                 for a, b in _stretches(mask)])
        repairs.append(SpikeRepair(column, spiky, values[spiky, column].copy(), smooth))
        values[spiky, column] = smooth
    return repairs


def stuck_channels(values: npt.ArrayLike) -> list[int]:
    """
    Return the columns of ``values`` that read one exact value in every row (at least two).

    A flap sensor always shows its noise and the blade's response to the stirring; a reading
    that never changes over a window is a dead or disconnected sensor (0.0 from an unplugged
    amplifier, a held last value). The one such check: the bag reader and the live identifier
    call it on a window's flap samples.
    """
    values = np.asarray(values)
    if values.ndim != 2 or values.shape[0] < 2:
        return []
    return [k for k in range(values.shape[1]) if np.all(values[:, k] == values[0, k])]


def _cores(size, outside):
    """
    Cut the stretches of ``outside`` to their cores; return them and each core's peak.

    A core runs from the first to the last sample of a stretch that reaches half the
    stretch's peak: a spike on a signal whose own excursions about the running median pass
    the threshold (a cyclic at 1/rev) is the spike, not its neighbours. (Vectorised: a fast
    stirring gives hundreds of stretches a second.)
    """
    edges = np.diff(np.concatenate([[0], outside.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    if not starts.size:
        return [], []
    bounds = np.ravel(np.column_stack([starts, ends]))
    padded = np.append(size, 0.0)                  # (a stretch may end at the last sample)
    peaks = np.maximum.reduceat(padded, bounds)[::2]
    stretch = np.cumsum(edges[:-1] == 1) - 1       # the stretch of each sample inside one
    index = np.arange(size.size)
    high = outside & (size >= 0.5 * peaks[np.maximum(stretch, 0)])
    first = np.minimum.reduceat(np.append(np.where(high, index, size.size), 0), bounds)[::2]
    last = np.maximum.reduceat(np.append(np.where(high, index, -1), 0), bounds)[::2]
    return list(zip(first.tolist(), (last + 1).tolist())), peaks.tolist()


def _isolated(stretches, peaks, j):
    """
    Tell whether outlier stretch j stands out from its neighbours.

    No other stretch within ``MEDIAN_SPAN`` samples may reach half its peak (``peaks``: each
    stretch's largest distance from the running median). A spike is an event; a signal
    faster than the running median follows (a stirring near 7/rev at 1 kHz, 9-12 samples a
    cycle) leaves it every half cycle by about as much, and those excursions are the signal,
    not spikes.
    """
    start, end = stretches[j]
    for i in (j - 1, j + 1):
        if 0 <= i < len(stretches) and peaks[i] >= 0.5 * peaks[j]:
            a, b = stretches[i]
            if (start - b if i < j else a - end) < MEDIAN_SPAN:
                return False
    return True


def _cubic_guess(column, start, end, times=None):
    """
    Return the cubic through column's two neighbours either side of [start, end).

    A line between the nearest neighbours at the record's ends.

    On ``times`` (the samples' times) when given, else on the sample numbers.
    """
    if times is None and start >= 2 and end + 2 <= column.size:
        knots = column[[start - 2, start - 1, end, end + 1]]
        return _gap_weights(end - start) @ knots
    at = np.arange(column.size) if times is None else np.asarray(times)
    at = (at - at[start]).astype(float)        # (stamps in ns: difference before rounding)
    first, last = max(start - 2, 0), min(end + 2, column.size)
    knots = np.r_[first:start, end:last]
    if knots.size < 4:
        knots = np.array([start - 1, end])
    return _lagrange(at[knots], column[knots], at[start:end])


def _local_noise(column, start, end):
    """
    Return the robust noise σ of one column around [start, end), the stretch left out.

    :func:`noise_scale` on the second differences within ``LOCAL_SPAN`` samples either side
    that do not touch the stretch.
    """
    first, last = max(0, start - LOCAL_SPAN), min(column.size, end + LOCAL_SPAN)
    second = np.diff(column[first:last], 2)
    at = np.arange(first, first + second.size)
    second = second[(at < start - 2) | (at >= end)]
    if second.size < 3:
        return 0.0
    return float(1.4826 * np.median(np.abs(second - np.median(second))) / np.sqrt(6.0))


def _shared(column, start, end, prediction):
    """Tell whether another blade's column moves over [start, end) beyond its own noise."""
    excursion = _excursion(column, start, end)
    if excursion <= SHARED_SIGMAS * prediction:
        return False
    return excursion > SHARED_SIGMAS * CUBIC_ERROR_GAIN * _local_noise(column, start, end)


def _excursion(column, start, end):
    """Return how far column[start:end] leaves the cubic through its neighbours (0 at ends)."""
    if start == 0 or end >= column.size:
        return 0.0
    return float(np.max(np.abs(column[start:end] - _cubic_guess(column, start, end))))


def _returns(column, start, end, floor):
    """
    Tell whether column[start:end] goes out and comes back (not a step or a peak).

    It must leave the cubic through its two neighbours either side (the line between its
    neighbours at the ends of the record) by more than ``floor``, and the neighbours must agree
    to within half that excursion. The cubic is what tells a spike from a peak of the signal
    sampled at 9-12 samples a cycle: such a peak leaves the line between its neighbours by a
    fifth of its amplitude, the cubic by about 3 % of it.
    """
    if start == 0 or end >= column.size:
        return False                  # at an end: nothing to come back to
    excursion = _excursion(column, start, end)
    return excursion > floor and abs(column[end] - column[start - 1]) < 0.5 * excursion


@functools.lru_cache(maxsize=None)
def _gap_weights(length):
    """Return the (length, 4) weights of the cubic through samples −2, −1, L, L + 1 at 0..L−1."""
    knots = np.array([-2.0, -1.0, length, length + 1.0])
    return np.column_stack([_lagrange(knots, np.eye(4)[j], np.arange(length, dtype=float))
                            for j in range(4)])


def _lagrange(knots, values, at):
    """Return the polynomial through (knots, values) evaluated at ``at``."""
    out = np.zeros_like(at)
    for j, (xj, yj) in enumerate(zip(knots, values)):
        basis = np.ones_like(at)
        for i, xi in enumerate(knots):
            if i != j:
                basis *= (at - xi) / (xj - xi)
        out += yj * basis
    return out


def _running_median(values, span, block=1 << 16):
    """
    Return the median of each sample's ``span`` (odd) neighbours, the edge samples repeated.

    The same numbers as scipy.ndimage.median_filter(values, span, mode='nearest') along the
    first axis (each column of a 2-D array on its own), without importing scipy.ndimage at
    every command's start; ``block`` samples at a time so that memory stays at the
    window's, not span times it.
    """
    half = span // 2
    padded = np.concatenate([np.repeat(values[:1], half, axis=0), values,
                             np.repeat(values[-1:], half, axis=0)])
    windows = np.lib.stride_tricks.sliding_window_view(padded, span, axis=0)
    out = np.empty(values.shape)
    block = max(1, block // max(1, np.size(values[0])))
    exact = np.isnan(values).any()       # np.median's NaN; else the middle of a partition
    for start in range(0, values.shape[0], block):
        part = windows[start:start + block]
        out[start:start + block] = (np.median(part, axis=-1) if exact else
                                    np.partition(part, half, axis=-1)[..., half])
    return out


def _stretches(mask):
    """(start, end) of each run of True in a boolean array."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))
