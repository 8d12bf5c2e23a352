r"""
Test points of the live identifier, without ROS: a state machine, bounded buffers, window checks.

A test point is one identification over the run description's ``window_s``, counted from the
test point's first flap sample. Its life::

    IDLE -> ARMED -> RECORDING -> FITTING -> DONE      (reason: converged, not converged,
                 \           \          \                incomplete window, fit failed)
                  +-----------+----------+-> ABORTED   (reason: asked to, superseded by a new
                                                        schedule, excitation ended early)

A test point is armed by a call (the identifier's ``~/start_test_point``: it records from the
next flap sample) or by the excitation (the stirring node's phase: a schedule that starts, phase
TRIM after any other phase, arms a test point from the stamp of that command). While it records,
growing-window fits are asked for (provisional); once every stream covers the window, the final
fit is asked for and the test point is FITTING until the node reports its outcome. The next
test point can be armed meanwhile: every fit request carries a copy of its own window's data.

``window_s`` may change between test points (:meth:`TestPointSequence.set_window`): each test
point keeps the window it was armed with, so a change never moves a window in progress.

The buffers keep what a window needs: the window, 1.5 revolutions either side (the fit's
margin) and ``pre_trigger_s`` for an arming command that arrives after the samples it refers to.

An estimate may claim convergence only from a complete window (:func:`check_window`): every
channel has samples from the window's start to its end with no step longer than 1.5 sample
periods (a gap that covers the start or the end counts), and the azimuth advances as the rotor
speed says between every two samples. The nodes only feed samples and publish what comes back.
"""

from dataclasses import dataclass, field
import enum
import math

import numpy as np
from rotor_id.excitation import (PHASE_CYCLIC_STEP, PHASE_DONE, PHASE_RAMP_DOWN, PHASE_STIRRING,
                                 PHASE_TRIM)
from rotor_id.io.timebase import azimuth_step, predicted_azimuth_step
from rotor_id.nodes.live import AzimuthTracker, record_from_series, StampedSeries

NS = 1_000_000_000


class Phase(enum.IntEnum):
    """State of a test point."""

    IDLE = 0
    ARMED = 1          # waits for its first flap sample
    RECORDING = 2      # the window fills; growing-window fits
    FITTING = 3        # the window is complete; the final fit runs
    DONE = 4
    ABORTED = 5


class Reason(enum.IntEnum):
    """Why a test point ended (DONE or ABORTED)."""

    NONE = 0
    CONVERGED = 1          # done: converged on a complete window
    NOT_CONVERGED = 2      # done: the final fit stopped at its iteration limit
    INCOMPLETE = 3         # done: the window has gaps or an inconsistent time base
    FIT_FAILED = 4         # done: the final fit failed (no estimate)
    ABORT_REQUESTED = 5    # aborted on request (~/abort)
    SUPERSEDED = 6         # aborted: a new excitation schedule started while recording
    EXCITATION_ENDED = 7   # aborted: the excitation ended before the window's end


class Excitation(enum.IntEnum):
    """Phases of the excitation: :mod:`rotor_id.excitation`'s (StirringCommand's PHASE_*)."""

    TRIM = PHASE_TRIM
    CYCLIC_STEP = PHASE_CYCLIC_STEP
    STIRRING = PHASE_STIRRING
    DONE = PHASE_DONE
    RAMP_DOWN = PHASE_RAMP_DOWN   # the cyclic ramps back to trim (end of the stirring, or abort)


#: What the final fit's outcome makes of a test point.
OUTCOMES = {'converged': Reason.CONVERGED, 'not_converged': Reason.NOT_CONVERGED,
            'incomplete': Reason.INCOMPLETE, 'failed': Reason.FIT_FAILED}


def outcome(check, fitted, converged):
    """
    Say what an estimate may claim: 'incomplete', 'failed', 'converged', 'not_converged'.

    An incomplete window (:class:`WindowCheck`) is never 'converged', whatever the fit did;
    ``fitted`` False (no estimate) on a complete window is 'failed'.
    """
    if not check.complete:
        return 'incomplete'
    if not fitted:
        return 'failed'
    return 'converged' if converged else 'not_converged'


# ------------------------------------------------------------------------------ window checks
@dataclass
class ChannelCoverage:
    """How completely one channel's samples cover a window."""

    name: str
    period_ns: float            # sampling period (median step of the kept samples); nan: unknown
    samples: int                # samples inside the window
    missing_start: int          # samples missing between the window's start and the first one
    missing_inside: int         # samples missing in gaps between the first and the last
    missing_end: int            # samples missing between the last one and the window's end
    gaps: int                   # gaps inside (steps longer than the tolerance)
    first_ns: int = None        # first and last sample inside the window (None: none)
    last_ns: int = None

    @property
    def missing(self):
        """Return the number of samples missing in all."""
        return self.missing_start + self.missing_inside + self.missing_end

    @property
    def complete(self):
        """Say whether no sample is missing."""
        return self.samples >= 2 and self.missing == 0

    def describe(self):
        """One short text (empty when complete)."""
        if self.complete:
            return ''
        if self.samples < 2:
            return f'{self.name}: {self.samples} sample(s) in the window'
        ends = ((self.missing_start, 'start'), (self.missing_end, 'end'))
        parts = [f'{n} at the {where}' for n, where in ends if n]
        if self.missing_inside:
            parts.append(f'{self.missing_inside} in {self.gaps} gap(s) inside')
        return f'{self.name}: {self.missing} sample(s) missing ({", ".join(parts)})'


@dataclass
class WindowCheck:
    """Integrity of the data of one window: whether an estimate may claim convergence."""

    lo_ns: int
    hi_ns: int
    channels: list
    azimuth_slips: int = 0          # azimuth steps that disagree with Ω·Δt
    largest_slip_rad: float = 0.0
    notes: list = field(default_factory=list)   # further reasons (e.g. an origin not seen)

    @property
    def time_base_consistent(self):
        """Say whether the azimuth (the record's time) advanced as the rotor speed says."""
        return self.azimuth_slips == 0

    @property
    def complete(self):
        """Say whether every channel is complete and the time base consistent."""
        return (all(c.complete for c in self.channels) and self.time_base_consistent
                and not self.notes)

    @property
    def missing(self):
        """Return the samples missing per channel name (only channels that miss some)."""
        return {c.name: c.missing if c.samples >= 2 else max(c.missing, 1)
                for c in self.channels if not c.complete}

    def describe(self):
        """Say what is missing or inconsistent, in one line (empty when complete)."""
        parts = [c.describe() for c in self.channels if not c.complete]
        if self.azimuth_slips:
            parts.append(f'azimuth: {self.azimuth_slips} step(s) disagree with the rotor speed '
                         f'(largest {self.largest_slip_rad:.3g} rad)')
        return '; '.join(parts + list(self.notes))

    def used_ns(self, channel='flap'):
        """(first, last) stamps of a channel's samples inside the window (None if < 1)."""
        c = next(c for c in self.channels if c.name == channel)
        return c.first_ns, c.last_ns


def sampling_period_ns(stamps):
    """Median step of the last 2001 stamps (nan with fewer than 2)."""
    stamps = np.asarray(stamps)
    if stamps.size < 2:
        return math.nan
    return float(np.median(np.diff(stamps[-min(stamps.size, 2001):])))


def grid_stamp(before_ns, after_ns, at_ns, period_ns, regularity=0.25):
    """
    Stamp of the first sample sent at or after ``at_ns``, from the received ones around it.

    ``before_ns`` < ``at_ns`` <= ``after_ns`` are consecutive received samples of a stream
    sampled every ``period_ns``. When their step is a whole number n >= 2 of periods (within
    ``regularity`` of a period: a regular stream that lost n - 1 samples), the lost samples lay
    evenly between them and the first of them at or after ``at_ns`` is returned; otherwise
    ``after_ns`` (nothing can be inferred about where an irregular stream's samples lay).
    """
    before_ns, after_ns, at_ns = int(before_ns), int(after_ns), int(at_ns)
    if not period_ns > 0:
        return after_ns
    n = round((after_ns - before_ns) / period_ns)
    if n < 2 or abs(after_ns - before_ns - n * period_ns) > regularity * period_ns:
        return after_ns
    step = (after_ns - before_ns) / n
    k = math.ceil((at_ns - before_ns) / step - 1e-6)      # first grid point at or after at_ns
    return min(after_ns, before_ns + int(round(max(k, 1) * step)))


#: A lost sample placed within this many standard deviations of the stamps' jitter of a
#: window bound may have been stamped inside it (4σ: one in ~16 000 for Gaussian jitter, and
#: beyond the worst case of uniform jitter, whose MAD-based σ is 0.61 of its half-width).
JITTER_SIGMAS = 4.0
#: Steps of the newest stamps from which the jitter is judged near a window's end.
JITTER_STEPS = 64


def stamp_jitter_ns(steps: np.ndarray) -> float:
    """Return the robust σ of a stamp about its sampling grid, from the steps between stamps."""
    if steps.size < 3:
        return 0.0
    deviation = np.abs(steps - np.median(steps))
    return float(1.4826 * np.median(deviation) / math.sqrt(2.0))   # a step: two stamps' jitter


def channel_coverage(name, stamps, lo_ns, hi_ns, period_ns=None, factor=1.5):
    """
    Coverage of [lo_ns, hi_ns] by one channel's sorted stamps.

    A step between consecutive samples longer than ``factor`` sampling periods is a gap; the
    steps from the sample before the window and to the one after it count too (the samples of
    such a gap that fall inside the window are missing at its start or end: placed by even
    spacing between the gap's ends, those within the stamps' jitter (JITTER_SIGMAS robust σ, at
    most half a period) of a bound count as inside, so that jitter never hides a loss inside
    the window, at the price of sometimes counting one just outside). Where the buffer
    has no sample before (after) the window, a first (last) sample more than ``factor`` periods
    after ``lo_ns`` (before ``hi_ns``) is a loss at the start (end): a loss that covers the
    window's start or end is never taken for a complete window. The period is the median step
    of the stamps given (scattered losses of fewer than half the samples leave it unchanged)
    unless ``period_ns`` is given.
    """
    stamps = np.asarray(stamps, dtype=np.int64)
    period = sampling_period_ns(stamps) if period_ns is None else float(period_ns)
    i0 = int(np.searchsorted(stamps, lo_ns, side='left'))
    i1 = int(np.searchsorted(stamps, hi_ns, side='right'))
    inside = stamps[i0:i1]
    if not period > 0 or inside.size < 2:     # too few samples to tell: not complete
        lost = int((hi_ns - lo_ns) // period) + 1 if period > 0 and inside.size == 0 else 0
        ends = (int(inside[0]), int(inside[-1])) if inside.size else (None, None)
        return ChannelCoverage(name, period, int(inside.size), lost, 0, 0, 0, *ends)
    limit = factor * period
    steps = np.diff(inside)
    big = steps > limit
    first, last = int(inside[0]), int(inside[-1])
    # a lost sample's stamp is known only as even spacing between its neighbours; one placed
    # within the stamps' jitter of a bound may have been inside: it counts (never the reverse)
    tolerance = min(JITTER_SIGMAS * stamp_jitter_ns(steps[~big]), 0.5 * period)
    if i0 > 0 and first - stamps[i0 - 1] > limit:       # a gap across the start
        before = int(stamps[i0 - 1])
        lost = int(round((first - before) / period)) - 1
        spacing = (first - before) / (lost + 1)
        k_first = max(1, math.ceil((lo_ns - tolerance - before) / spacing))
        missing_start = max(lost - k_first + 1, 0)
    elif i0 == 0 and first - lo_ns > limit:           # nothing before: the bound itself
        missing_start = int((first - lo_ns) // period)
    else:
        missing_start = 0
    if i1 < stamps.size and stamps[i1] - last > limit:  # a gap across the end
        lost = int(round((int(stamps[i1]) - last) / period)) - 1
        spacing = (int(stamps[i1]) - last) / (lost + 1)
        missing_end = min(max(math.floor((hi_ns + tolerance - last) / spacing), 0), lost)
    elif i1 == stamps.size and hi_ns - last > limit:
        missing_end = int((hi_ns - last) // period)
    else:
        missing_end = 0
    return ChannelCoverage(
        name, period, int(inside.size), missing_start=missing_start,
        missing_inside=int(np.sum(np.round(steps[big] / period) - 1)), missing_end=missing_end,
        gaps=int(np.count_nonzero(big)), first_ns=first, last_ns=last)


def azimuth_slips(stamps, psi_wrapped, omega, tolerance_rad):
    """
    Count the azimuth steps that disagree with the rotor speed; return (count, largest, rad).

    Each step of the wrapped azimuth, unwrapped by :func:`rotor_id.io.timebase.azimuth_step`, is
    compared with the step the rotor speed predicts: a disagreement above
    ``tolerance_rad`` is a slip of the record's time base (a wrong stamp, a glitch of the
    encoder, a speed that does not belong to the azimuth).
    """
    stamps = np.asarray(stamps, dtype=np.int64)
    if stamps.size < 2:
        return 0, 0.0
    psi = np.asarray(psi_wrapped, dtype=float)
    omega = np.asarray(omega, dtype=float)
    dt_s = np.diff(stamps) / NS
    error = np.abs(azimuth_step(np.diff(psi), omega[:-1], omega[1:], dt_s)
                   - predicted_azimuth_step(omega[:-1], omega[1:], dt_s))
    bad = error > tolerance_rad
    return int(np.count_nonzero(bad)), float(error.max())


def check_window(flap, pitch, azimuth, lo_ns, hi_ns, factor=1.5, slip_tolerance_rad=0.1):
    """
    Check the data of the window [lo_ns, hi_ns] (StampedSeries; azimuth with ψ, Ω columns).

    Returns a :class:`WindowCheck`: the coverage of every channel and the azimuth's
    consistency with the rotor speed over the window (the steps that lead into it included).
    """
    channels = [channel_coverage(name, series.stamps, lo_ns, hi_ns, factor=factor)
                for name, series in (('flap', flap), ('pitch', pitch), ('azimuth', azimuth))]
    a = max(0, int(np.searchsorted(azimuth.stamps, lo_ns, side='left')) - 1)
    b = int(np.searchsorted(azimuth.stamps, hi_ns, side='right')) + 1
    values = azimuth.values[a:b]
    slips, largest = azimuth_slips(azimuth.stamps[a:b], values[:, 0], values[:, 1],
                                   slip_tolerance_rad)
    return WindowCheck(int(lo_ns), int(hi_ns), channels, slips, largest)


# ------------------------------------------------------------------------------ test points
@dataclass
class FitSchedule:
    """When growing-window fits are asked for while a window fills (rad of azimuth)."""

    update_every_rad: float = math.pi / 4   # one every this much azimuth (0: none)
    min_window_rad: float = 3.0 * math.pi   # the first after this much of the window
    refit_tail_rad: float = math.pi         # back to back in the window's last this much


@dataclass
class TestPoint:
    """One test point: its number, how it was started, its phase and, at the end, why."""

    __test__ = False                 # not a pytest class

    number: int
    source: str                      # 'service' | 'excitation' | 'data'
    window_s: tuple = None           # (start, end) s after stamp0_ns, fixed when armed
    armed_from_ns: int = None        # first flap sample at or after this stamp (None: next)
    phase: Phase = Phase.ARMED
    reason: Reason = Reason.NONE
    detail: str = ''
    stamp0_ns: int = None            # its first flap sample: the origin of window_s (when
    #                                  lost, where the regular sample grid puts it)
    origin_late_ns: int = 0          # its first flap sample's stamp after armed_from_ns
    origin_received_ns: int = None   # the first one received, when that one was not (lost)
    next_update: float = None        # growing-window schedule (s after stamp0)
    first_update: float = None
    requested_until: float = -math.inf
    final_requested: bool = False

    def describe(self):
        """E.g. 'test point 3 (recording)' or 'test point 2 (aborted: abort requested)'."""
        text = f'test point {self.number} ({self.phase.name.lower()}'
        if self.phase in (Phase.DONE, Phase.ABORTED):
            text += f': {self.reason.name.lower().replace("_", " ")}'
        return text + ')'


@dataclass
class FitRequest:
    """A window to fit, with its own copy of the data: what the node hands its fit worker."""

    test_point: int                  # 0: on demand, not a test point
    final: bool
    window_s: tuple                  # requested, s after ``stamp0_ns``
    stamp0_ns: int
    record: object                   # rotor_id.io.record.Record (None: could not be formed)
    check: WindowCheck
    error: str = ''                  # why the record could not be formed


def window_bounds(window_s):
    """(start, end) s of a window as floats; ValueError unless finite and 0 <= start < end."""
    try:
        t0, t1 = (float(v) for v in window_s)
    except (TypeError, ValueError):
        raise ValueError(f'window_s {window_s!r} must be two numbers [start, end] (s after '
                         "the test point's first flap sample)") from None
    if not (math.isfinite(t0) and math.isfinite(t1) and 0.0 <= t0 < t1):
        raise ValueError(f'window_s {list(window_s)} must be 0 <= start < end (s after the '
                         "test point's first flap sample)")
    return t0, t1


class TestPointSequence:
    """
    The test points of one identifier, in sequence, and the buffers they share.

    Parameters
    ----------
    n_blades : int
    window_s : (float, float)
        The identification window, s after a test point's first flap sample.
    blade_names : list of str
        Joint of each blade column (for the Record).
    schedule : FitSchedule
    margin_rad : float
        Data kept and passed to the fit either side of the window (rad of azimuth).
    pre_trigger_s : float
        Data kept before a test point is armed: an arming command may refer to samples this
        old (the excitation's first command is stamped with the azimuth sample it locked on).
    gap_factor : float
        A step longer than this many sampling periods is a gap (:func:`channel_coverage`).
    slip_tolerance_rad : float
        Largest disagreement of an azimuth step with Ω·Δt (:func:`azimuth_slips`).
    auto_start : str
        'excitation' (a starting schedule arms a test point), 'data' (the first test point is
        armed at once; later ones by :meth:`arm`) or 'none' (only :meth:`arm`).

    """

    __test__ = False                 # not a pytest class

    def __init__(self, n_blades, window_s, blade_names, schedule=None, margin_rad=3.0 * math.pi,
                 pre_trigger_s=5.0, gap_factor=1.5, slip_tolerance_rad=0.1,
                 auto_start='excitation'):
        if auto_start not in ('excitation', 'data', 'none'):
            raise ValueError(f"auto_start must be 'excitation', 'data' or 'none', got "
                             f'{auto_start!r}')
        self.window_s = window_bounds(window_s)    # of the next test point armed
        self.blade_names = list(blade_names)
        self.schedule = schedule or FitSchedule()
        self.margin_rad = float(margin_rad)
        self.pre_trigger_ns = int(pre_trigger_s * NS)
        self.gap_factor = float(gap_factor)
        self.slip_tolerance_rad = float(slip_tolerance_rad)
        self.auto_start = auto_start
        self.flap = StampedSeries(n_blades)
        self.pitch = StampedSeries(n_blades)
        self.azimuth = AzimuthTracker()
        self.points = {}                 # number -> TestPoint (the last few)
        self.current = None              # the test point armed or recording (None: idle)
        self.excitation = None           # last excitation phase seen
        self.count = 0
        if auto_start == 'data':
            self.arm('data')

    # -------------------------------------------------------------------------- state
    @property
    def phase(self):
        """Phase of the current test point (IDLE when none is armed or recording)."""
        return self.current.phase if self.current is not None else Phase.IDLE

    @property
    def latest(self):
        """Return the newest test point (None before the first)."""
        return self.points[self.count] if self.count else None

    def arm(self, source='service', from_stamp_ns=None):
        """
        Arm a new test point; return (TestPoint or None, text naming it or why not).

        ``from_stamp_ns`` None: its first flap sample is the next one received; otherwise the
        first one stamped at or after it (from the buffer, if it arrived already).
        """
        if self.current is not None:
            return None, (f'{self.current.describe()} is in progress: abort it first '
                          '(~/abort)')
        self.count += 1
        point = TestPoint(self.count, source, self.window_s, from_stamp_ns)
        self.points[point.number] = point
        for old in [n for n in self.points if n <= self.count - 16]:
            del self.points[old]
        self.current = point
        if from_stamp_ns is not None and self.flap.size:
            self._start(point)
        t0, t1 = point.window_s
        return point, (f'test point {point.number} armed ({source}): window {t0:.4f}-{t1:.4f} s '
                       'from its first flap sample')

    def set_window(self, window_s):
        """
        Set the window of the test points armed from now on; return a text saying so.

        A test point armed, recording or fitting keeps the window it was armed with: a change
        never moves (or cuts short) a window in progress. Raises ValueError for a window that
        is not 0 <= start < end.
        """
        self.window_s = window_bounds(window_s)
        t0, t1 = self.window_s
        text = f'window_s {t0:.4f}-{t1:.4f} s applies from the next test point armed'
        point = self.current
        if point is not None and point.window_s != self.window_s:
            p0, p1 = point.window_s
            text += f'; {point.describe()} keeps its window {p0:.4f}-{p1:.4f} s'
        return text

    def abort(self, reason=Reason.ABORT_REQUESTED, detail=''):
        """Abort the test point armed or recording, else the one fitting; return it (or None)."""
        point = self.current
        if point is None:
            fitting = [p for p in self.points.values() if p.phase == Phase.FITTING]
            point = fitting[-1] if fitting else None
        if point is None:
            return None
        self._end(point, Phase.ABORTED, reason, detail)
        return point

    def _end(self, point, phase, reason, detail=''):
        point.phase, point.reason, point.detail = phase, Reason(reason), detail
        if self.current is point:
            self.current = None

    def finish(self, number, outcome, detail=''):
        """
        Record the final fit's outcome ('converged' | 'not_converged' | 'incomplete' | 'failed').

        Returns the TestPoint, or None when it was aborted meanwhile (its result is dropped).
        """
        point = self.points.get(number)
        if point is None or point.phase != Phase.FITTING:
            return None
        self._end(point, Phase.DONE, OUTCOMES[outcome], detail)
        return point

    def on_excitation(self, phase, stamp_ns):
        """
        Follow the excitation's phase; return the test points this ended (aborted).

        A schedule starts with TRIM after any other phase (or as the first phase seen): with
        ``auto_start`` 'excitation' it arms a test point from ``stamp_ns``, aborting one that
        records (SUPERSEDED). RAMP_DOWN or DONE stamped before the recording test point's
        window end aborts it (EXCITATION_ENDED): the stirring was cut short (aborted, or it
        reached its limits) and the window would not hold the excitation it was planned on.
        """
        phase = Excitation(phase)
        previous, self.excitation = self.excitation, phase
        ended = []
        if self.auto_start != 'excitation':
            return ended
        if phase == Excitation.TRIM and previous != Excitation.TRIM:
            point = self.current
            if point is not None and point.phase == Phase.ARMED and point.stamp0_ns is None:
                point.source, point.armed_from_ns = 'excitation', int(stamp_ns)
                if self.flap.size:
                    self._start(point)
                return ended
            if point is not None:
                ended.append(self.abort(Reason.SUPERSEDED, 'a new excitation schedule started'))
            self.arm('excitation', int(stamp_ns))
        elif (phase in (Excitation.DONE, Excitation.RAMP_DOWN) and
              previous not in (Excitation.DONE, Excitation.RAMP_DOWN)):
            point = self.current
            if point is None:
                return ended
            # not started yet (its first flap sample still queued on a busy machine): it starts
            # at or after the stamp it was armed from, so its window ends no earlier than this
            start = point.stamp0_ns if point.stamp0_ns is not None else point.armed_from_ns
            end = None if start is None else start + int(point.window_s[1] * NS)
            if end is None or stamp_ns < end:
                ended.append(self.abort(Reason.EXCITATION_ENDED,
                                        "the excitation ended before the window's end"))
        return ended

    # -------------------------------------------------------------------------- samples
    def _keep_from(self, newest_ns):
        """Oldest stamp still needed: the window and its margins, or the pre-trigger span."""
        spans = [self.window_s] + ([self.current.window_s] if self.current is not None else [])
        length = max(t1 - t0 for t0, t1 in spans)   # the next window's, or the current one's
        margin = self.margin_rad / self.azimuth.omega if self.azimuth.ready else 0.0
        keep = (length + 2.0 * margin) * NS + self.pre_trigger_ns
        return newest_ns - int(keep)

    def add_flap(self, stamp_ns, values):
        """Take one checked flap sample (blade order)."""
        self.flap.append(stamp_ns, values, self._keep_from(stamp_ns))
        point = self.current
        if point is not None and point.stamp0_ns is None:
            self._start(point)

    def add_pitch(self, stamp_ns, values):
        """Take one checked pitch sample (blade order)."""
        self.pitch.append(stamp_ns, values, self._keep_from(stamp_ns))

    def add_azimuth(self, stamp_ns, psi, omega):
        """Take one checked azimuth sample (ψ in [0, 2π), Ω > 0)."""
        self.azimuth.add(stamp_ns, psi, omega, self._keep_from(stamp_ns))

    def _start(self, point):
        """Start an armed test point at its first flap sample: it records from there."""
        stamps = self.flap.stamps
        if point.armed_from_ns is None:
            first = int(stamps[-1])
        else:
            i = int(np.searchsorted(stamps, point.armed_from_ns, side='left'))
            if i == stamps.size:
                return
            first = int(stamps[i])
            if i > 0:       # its first flap sample lost? the stream's grid says where it lay
                sent = grid_stamp(stamps[i - 1], first, point.armed_from_ns,
                                  sampling_period_ns(stamps[:i]))
                if sent != first:
                    point.origin_received_ns, first = first, sent
            point.origin_late_ns = first - point.armed_from_ns
        point.stamp0_ns = first
        point.phase = Phase.RECORDING

    def covered_s(self, point=None):
        """Seconds after the test point's first flap sample that every stream has reached."""
        point = point or self.current
        if point is None or point.stamp0_ns is None or not (self.pitch.size and
                                                            self.azimuth.ready):
            return None
        last = min(self.flap.last_stamp, self.pitch.last_stamp,
                   self.azimuth.series.last_stamp)
        return (last - point.stamp0_ns) / NS

    # -------------------------------------------------------------------------- fits
    def due(self, worker_idle=True, data_ended=False):
        """
        Return the next fit to ask for (a FitRequest) or None.

        The final fit once every stream has a sample stamped past the window's end, or its next
        one is due past it beyond the stamps' jitter (or, with ``data_ended``, reached it: no
        sample follows); the test point is then FITTING and no longer current. Before that a
        growing-window fit after ``min_window_rad``, then one every ``update_every_rad`` and,
        in the last ``refit_tail_rad``, one whenever the worker is idle, so that the final fit
        starts next to its optimum.
        """
        point = self.current
        covered = self.covered_s(point)
        if covered is None or point.phase != Phase.RECORDING:
            return None
        t0, t1 = point.window_s
        s = self.schedule
        omega = self.azimuth.omega
        reached_ns = point.stamp0_ns + int(round(covered * NS))
        end_ns = point.stamp0_ns + int(round(t1 * NS))
        # final once every sample up to the end (one exactly on it included, as offline) is
        # in: every stream is past the end, or its next sample is due past it beyond the
        # stamps' jitter (on a regular stream, one period after its last; under jitter the
        # next sample can still fall inside the window)
        if reached_ns > end_ns or (data_ended and reached_ns >= end_ns) or \
                self._next_stamp_after(reached_ns, end_ns):
            request = self.request(point, (t0, t1), True)
            point.phase, point.final_requested = Phase.FITTING, True
            self.current = None
            return request
        if s.update_every_rad <= 0:
            return None
        if point.next_update is None:
            point.first_update = point.next_update = t0 + s.min_window_rad / omega
        if covered < point.first_update or covered <= point.requested_until:
            return None
        if covered >= point.next_update:
            point.next_update = covered + s.update_every_rad / omega
        elif covered < t1 - s.refit_tail_rad / omega or not worker_idle:
            return None
        point.requested_until = covered
        return self.request(point, (t0, covered), False)

    def _next_stamp_after(self, reached_ns, end_ns):
        """Say whether a sample after ``reached_ns`` is sure to be stamped after ``end_ns``."""
        stamps = self.flap.stamps
        if stamps.size < 3 or reached_ns + 2 * (stamps[-1] - stamps[-2]) <= end_ns:
            return False                  # too few samples, or far from the end: not yet
        steps = np.diff(stamps[-min(stamps.size, JITTER_STEPS + 1):])
        period = float(np.median(steps))
        margin = min(JITTER_SIGMAS * stamp_jitter_ns(steps), 0.5 * period)
        return reached_ns + period - margin > end_ns

    def request(self, point, window_s, final):
        """Return a FitRequest of a test point's window: its data (± the margin), checked."""
        note = ''
        period = sampling_period_ns(self.flap.stamps)
        if point.origin_late_ns > self.gap_factor * period:
            note = (f'the first flap sample of the test point was not received (the first one '
                    f'is {point.origin_late_ns / 1e6:.1f} ms after the start command, stamped '
                    f'{point.armed_from_ns} ns): its window is shifted by an unknown amount')
        return self.window_request(point.number, point.stamp0_ns, window_s, final, note)

    def window_request(self, number, stamp0_ns, window_s, final, note=''):
        """Return a FitRequest over ``window_s`` s after ``stamp0_ns`` (0: on demand)."""
        lo = stamp0_ns + int(round(window_s[0] * NS))
        hi = stamp0_ns + int(round(window_s[1] * NS))
        check = check_window(self.flap, self.pitch, self.azimuth.series, lo, hi,
                             self.gap_factor, self.slip_tolerance_rad)
        if note:
            check.notes.append(note)
        record, error = None, ''
        try:
            margin = int(self.margin_rad / self.azimuth.omega * NS) if self.azimuth.ready else 0
            record = record_from_series(self.flap, self.pitch, self.azimuth.series,
                                        self.blade_names, stamp0_ns,
                                        span_ns=(lo - margin, hi + margin))
        except ValueError as exc:
            error = str(exc)
        return FitRequest(number, final, tuple(window_s), stamp0_ns, record, check, error)

    def buffered_s(self):
        """(origin ns, start s, end s) of what the buffers hold, relative to the latest origin."""
        point = self.current or self.latest
        origin = (point.stamp0_ns if point is not None and point.stamp0_ns is not None
                  else self.flap.first_stamp)
        if origin is None or not (self.pitch.size and self.azimuth.ready):
            return None
        first = max(self.flap.first_stamp, self.pitch.first_stamp,
                    self.azimuth.series.first_stamp)
        last = min(self.flap.last_stamp, self.pitch.last_stamp,
                   self.azimuth.series.last_stamp)
        return origin, (first - origin) / NS, (last - origin) / NS


# ------------------------------------------------------------------------------ multi-point bags
@dataclass
class RecordedTestPoint:
    """A test point of a multi-point bag: where the live identifier's would have started."""

    __test__ = False                 # not a pytest class

    number: int
    stamp0_ns: int                   # its first flap sample (the origin of its window_s)
    window_s: tuple                  # s after stamp0_ns
    phase: Phase                     # FITTING: its window is in the record (see ``check``);
    reason: Reason = Reason.NONE     # ABORTED (with the reason); RECORDING: the record ends
    detail: str = ''                 # before its window's end
    check: WindowCheck = None        # the record's samples over the window (FITTING only)
    source: str = 'excitation'       # 'excitation' | 'estimates'

    def describe(self):
        """E.g. 'test point 2 (aborted: excitation ended)' or 'test point 1 (in the record)'."""
        if self.phase == Phase.ABORTED:
            reason = self.reason.name.lower().replace('_', ' ')
            return f'test point {self.number} (aborted: {reason})'
        if self.phase == Phase.RECORDING:
            return f"test point {self.number} (the record ends before its window's end)"
        return f'test point {self.number} (in the record)'


def replay_excitation(record, excitation, window_s, gap_factor=1.5, slip_tolerance_rad=0.1):
    """
    Find the test points that excitation phases arm in a multi-point bag, as the live node.

    The record's samples (flap, pitch and azimuth on the flap stamps) and the excitation's
    phases are fed, in stamp order, to a :class:`TestPointSequence` with ``auto_start``
    'excitation', which arms, starts, supersedes and aborts test points as in the live node
    (the same code): a schedule's TRIM arms one from its stamp, its first flap sample at or after
    it is the origin of ``window_s``, and a schedule that ends before the window's end aborts it.

    Parameters
    ----------
    record : rotor_id.io.record.Record
        The whole multi-point record (``stamp0_ns`` + ``time_s`` are the flap stamps).
    excitation : iterable of (stamp_ns, phase)
        The excitation's phases (StirringCommand's ``header.stamp`` and ``phase``).
    window_s : (float, float)
        The identification window of every test point, s after its first flap sample.
    gap_factor, slip_tolerance_rad : float
        The window checks' tolerances (:class:`TestPointSequence`).

    Returns
    -------
    list of :class:`RecordedTestPoint`, numbered 1, 2, ... in order.

    """
    sequence = TestPointSequence(record.n_blades, window_s, record.blade_names,
                                 FitSchedule(update_every_rad=0.0), gap_factor=gap_factor,
                                 slip_tolerance_rad=slip_tolerance_rad, auto_start='excitation')
    stamps = int(record.stamp0_ns) + np.round(record.time_s * NS).astype(np.int64)
    psi = np.mod(record.t, 2.0 * math.pi)
    events = sorted(((int(s), int(p)) for s, p in excitation), key=lambda e: e[0])
    # an event goes in before the first flap sample stamped at or after it
    at = np.searchsorted(stamps, [s for s, _ in events], side='left')
    points, checks, e = [], {}, 0
    for i in range(stamps.size):          # (not stamps.tolist(): ~40 B a sample over an hour)
        stamp = int(stamps[i])
        while e < len(events) and at[e] <= i:
            before = sequence.count
            sequence.on_excitation(events[e][1], events[e][0])
            if sequence.count != before:
                points.append(sequence.latest)
            e += 1
        sequence.add_flap(stamp, record.blade_flap[i])
        sequence.add_pitch(stamp, record.blade_pitch[i])
        sequence.add_azimuth(stamp, psi[i], record.rotor_speed_rad_s[i])
        request = sequence.due()
        if request is not None:
            checks[request.test_point] = request.check
    request = sequence.due(data_ended=True)      # a window ending on the record's last sample
    if request is not None:
        checks[request.test_point] = request.check
    for stamp, phase in events[e:]:                      # stamped after the last flap sample
        sequence.on_excitation(phase, stamp)
    found = []
    for p in points:
        if p.stamp0_ns is None:       # armed after the last flap sample: nothing recorded
            continue
        if p.phase == Phase.ABORTED:
            phase = Phase.ABORTED
        else:                         # FITTING once its window was in the record
            phase = Phase.FITTING if p.number in checks else Phase.RECORDING
        found.append(RecordedTestPoint(p.number, p.stamp0_ns, p.window_s, phase, p.reason,
                                       p.detail, checks.get(p.number)))
    return found
