"""The recording of one test-stand run as plain numpy arrays (no ROS)."""

from dataclasses import dataclass, field, replace

import numpy as np

from rotor_id.io.streams import repair_value_spikes, SpikeRepair, stuck_channels
from rotor_id.io.timebase import blade_azimuths, multiblade_coordinates

# Window ends are inclusive; this absorbs float rounding of a stamp written as seconds.
_WINDOW_TOL_S = 1e-9


@dataclass(frozen=True)
class Repair:
    """
    One reading that was replaced before the fit: where, what it read, what replaced it, why.

    Attributes
    ----------
    topic
        Topic of the reading (a role such as 'blade_flap' when no bag was read).
    blade
        Joint name of the reading (blade_k, or the azimuth joint).
    time_s
        Record time of the sample, s after the first flap stamp.
    old, new
        The reading as received and its replacement (rad, or rad/s for a rotor speed).
    why
        'value_spike' (a flap or pitch sample of one blade out and back: a bit flip or a
        dropped reading), 'speed_spike' (a rotor-speed sample out and back) or
        'azimuth_glitch' (an azimuth sample off the phase the rotor speed predicts, and back).

    """

    topic: str
    blade: str
    time_s: float
    old: float
    new: float
    why: str

    def as_json(self) -> dict:
        """Return the repair as the commands' JSON lists it."""
        return {'topic': self.topic, 'blade': self.blade, 'time': self.time_s,
                'old': self.old, 'new': self.new, 'why': self.why}


@dataclass
class Record:
    """
    Blade pitch and flap of a rotor on the test stand, on the flap sensors' time base.

    Attributes
    ----------
    time_s
        (n,) seconds since the first flap stamp of the recording (a window keeps the
        recording's origin).
    t
        (n,) nondimensional time: unwrapped azimuth of blade 1, rad (docs/models.md §0).
    rotor_speed_rad_s
        (n,) measured rotor speed Ω.
    blade_flap
        (n, N) flap angle of each blade, up positive, rad.
    blade_pitch
        (n, N) pitch of each blade, rad, interpolated onto the flap stamps.
    blade_names
        Joint name of each column (blade_1..blade_N).
    source
        Where the data came from (bag path, topics).
    warnings
        Non-fatal problems met while reading (dropped samples, gaps, ...).
    stamp0_ns
        Absolute ``header.stamp`` of the first flap sample, ns.
    flap_joints
        Joint names the bag's flap messages carry, in message order (empty when the record
        did not come from a bag). With :attr:`pitch_joints` this is what the bag says about
        the blades, whatever joint_names selected.
    pitch_joints
        Joint names the bag's pitch messages carry, in message order.
    read_around_window
        True when only the part of the bag around a window was read (a long bag, see
        :func:`rotor_id.io.bag.read_record`), False when the whole recording was read.
    repairs
        Every reading replaced by the reader or by :meth:`repair_value_spikes`
        (:class:`Repair`, in the order made); the commands list them in their JSON.

    """

    time_s: np.ndarray
    t: np.ndarray
    rotor_speed_rad_s: np.ndarray
    blade_flap: np.ndarray
    blade_pitch: np.ndarray
    blade_names: list
    source: str = ''
    warnings: list = field(default_factory=list)
    stamp0_ns: int = 0
    flap_joints: tuple = ()
    pitch_joints: tuple = ()
    read_around_window: bool = False
    repairs: list = field(default_factory=list)

    def __post_init__(self) -> None:
        """Convert to float arrays and check that the shapes agree."""
        for name in ('time_s', 't', 'rotor_speed_rad_s', 'blade_flap', 'blade_pitch'):
            setattr(self, name, np.asarray(getattr(self, name), dtype=float))
        n = self.time_s.shape[0]
        if self.blade_flap.ndim != 2:
            raise ValueError(f'blade_flap must be (n, N), got shape {self.blade_flap.shape}')
        shapes = {
            'time_s': (self.time_s.shape, (n,)),
            't': (self.t.shape, (n,)),
            'rotor_speed_rad_s': (self.rotor_speed_rad_s.shape, (n,)),
            'blade_flap': (self.blade_flap.shape, (n, self.n_blades)),
            'blade_pitch': (self.blade_pitch.shape, (n, self.n_blades)),
        }
        for name, (shape, expected) in shapes.items():
            if shape != expected:
                raise ValueError(f'Record.{name} has shape {shape}, expected {expected}')
        self.blade_names = list(self.blade_names)
        self.flap_joints = tuple(self.flap_joints)
        self.pitch_joints = tuple(self.pitch_joints)
        if len(self.blade_names) != self.n_blades:
            raise ValueError(f'{len(self.blade_names)} blade names for {self.n_blades} blades')

    def __len__(self) -> int:
        """Return the number of samples."""
        return self.time_s.shape[0]

    @property
    def n_blades(self) -> int:
        """Return the number of blades N."""
        return self.blade_flap.shape[1]

    @property
    def bag_blade_count(self) -> int | None:
        """
        Return the number of blade joints the bag carries, or None if unknown.

        That is the number of joints on the flap topic when the flap and pitch topics carry
        the same number (a bag's JointState messages hold one joint per blade); None when
        the record did not come from a bag or the two topics disagree.
        """
        if not self.flap_joints or len(self.flap_joints) != len(self.pitch_joints):
            return None
        return len(self.flap_joints)

    @property
    def omega_mean(self) -> float:
        """Return the mean rotor speed, rad/s."""
        return float(np.mean(self.rotor_speed_rad_s))

    @property
    def duration_s(self) -> float:
        """Return the time from the first to the last sample, s."""
        return float(self.time_s[-1] - self.time_s[0]) if len(self) else 0.0

    @property
    def sample_period_s(self) -> float:
        """Return the median sampling interval, s."""
        return float(np.median(np.diff(self.time_s))) if len(self) > 1 else float('nan')

    def azimuths(self) -> np.ndarray:
        """Return the (n, N) blade azimuths ψ_k = t + (k − 1)·2π/N."""
        return blade_azimuths(self.t, self.n_blades)

    def t_at(self, time_s: float | np.ndarray) -> float | np.ndarray:
        """Nondimensional time at ``time_s`` (seconds since the first stamp), interpolated."""
        return np.interp(time_s, self.time_s, self.t)

    def multiblade(self, quantity: str = 'flap') -> dict[str, np.ndarray]:
        """Multiblade coordinates of 'flap' or 'pitch' (see :mod:`rotor_id.io.timebase`)."""
        values = {'flap': self.blade_flap, 'pitch': self.blade_pitch}[quantity]
        return multiblade_coordinates(values, self.t)

    def repair_value_spikes(self) -> list[tuple[str, str, SpikeRepair]]:
        """
        Replace the flap and pitch spikes in place (:func:`rotor_id.io.streams.value_spikes`).

        Returns [(quantity, blade name, :class:`~rotor_id.io.streams.SpikeRepair`)], quantity
        'flap' or 'pitch'. The bag reader repairs each topic on its own stamps before a Record
        is formed; the live identifier calls this on each window's record.
        """
        both = np.hstack([self.blade_flap, self.blade_pitch])    # one call: half the CPU
        blades = list(range(self.n_blades))
        repairs = repair_value_spikes(self.time_s, both,
                                      [blades, [k + self.n_blades for k in blades]])
        if repairs:
            self.blade_flap[:] = both[:, :self.n_blades]
            self.blade_pitch[:] = both[:, self.n_blades:]
        found = []
        for r in repairs:
            quantity, blade = divmod(r.column, self.n_blades)
            found.append((('flap', 'pitch')[quantity], self.blade_names[blade], replace(
                r, column=blade)))
            self.repairs.extend(
                Repair(f'blade_{("flap", "pitch")[quantity]}', self.blade_names[blade],
                       float(self.time_s[i]), float(old), float(new), 'value_spike')
                for i, old, new in zip(r.indices, r.old, r.new))
        return found

    def stuck_flap_blades(self, t0_s: float, t1_s: float) -> list[tuple[str, float]]:
        """
        Return the blades whose flap reads one exact value throughout [t0_s, t1_s] s.

        [(blade name, value)]: dead sensors (:func:`rotor_id.io.streams.stuck_channels`).
        """
        keep = (self.time_s >= t0_s - _WINDOW_TOL_S) & (self.time_s <= t1_s + _WINDOW_TOL_S)
        flap = self.blade_flap[keep]
        return [(self.blade_names[k], float(flap[0, k])) for k in stuck_channels(flap)]

    def window(self, t0_s: float, t1_s: float) -> 'Record':
        """
        Return the samples with t0_s ≤ time_s ≤ t1_s (seconds since the first stamp).

        The sub-record keeps the recording's time origin, so a run description's window_s
        means the same in both.

        Raises
        ------
        ValueError
            The window is reversed or holds no sample.

        """
        if not t1_s >= t0_s:
            raise ValueError(f'window end {t1_s} s is before its start {t0_s} s')
        keep = (self.time_s >= t0_s - _WINDOW_TOL_S) & (self.time_s <= t1_s + _WINDOW_TOL_S)
        if not keep.any():
            raise ValueError(
                f'window [{t0_s}, {t1_s}] s holds no sample; the record spans '
                f'[{self.time_s[0]:.6f}, {self.time_s[-1]:.6f}] s')
        return replace(
            self,
            time_s=self.time_s[keep], t=self.t[keep],
            rotor_speed_rad_s=self.rotor_speed_rad_s[keep],
            blade_flap=self.blade_flap[keep], blade_pitch=self.blade_pitch[keep],
            source=f'{self.source} [window {t0_s}..{t1_s} s]',
            warnings=list(self.warnings), repairs=list(self.repairs))
