"""
When the identifier asks for fits (rotor_id/nodes/test_points.py, TestPointSequence.due).

What it proves, on the demo's wake window at 1 kHz with the machine fed sample by sample: the
first growing-window fit comes after min_window_rad, then one every update_every_rad; in the
last refit_tail_rad a new one as soon as the worker is free (so the last growing-window iterate
lies close to the window's end); the final fit is asked for exactly once, when the window is
complete, and nothing after it. ROS-free: the node only adapts this machine.
"""

import math

import numpy as np
from rotor_id.nodes.test_points import FitSchedule, TestPointSequence

OMEGA = 30 * math.pi
WINDOW = (0.80939, 0.93671)
PERIOD = 0.001


def _drive(fit_ms, update_every=math.pi / 4, tail=math.pi, min_window=3 * math.pi):
    """Feed 1 s of samples; each fit keeps the worker busy ``fit_ms`` ms."""
    machine = TestPointSequence(
        4, WINDOW, [f'blade_{k}' for k in range(1, 5)], auto_start='data',
        schedule=FitSchedule(update_every_rad=update_every, min_window_rad=min_window,
                             refit_tail_rad=tail))
    asked, busy_until = [], -1.0
    for k in range(int(1.0 / PERIOD)):
        now = k * PERIOD
        stamp = int(round(now * 1e9))
        machine.add_flap(stamp, np.zeros(4))
        machine.add_pitch(stamp, np.zeros(4))
        machine.add_azimuth(stamp, (OMEGA * now) % (2 * math.pi), OMEGA)
        request = machine.due(worker_idle=now >= busy_until)
        if request is not None:
            asked.append((request.window_s, request.final))
            busy_until = now + fit_ms / 1e3
    return asked


def test_growing_windows_then_back_to_back_in_the_tail_then_one_final():
    asked = _drive(fit_ms=3.0, min_window=6.0)
    finals = [w for w, final in asked if final]
    assert finals == [WINDOW]
    assert asked[-1] == (WINDOW, True)
    ends = np.array([w[1] for w, final in asked if not final])
    assert all(w[0] == WINDOW[0] for w, _ in asked)
    first = WINDOW[0] + 6.0 / OMEGA
    assert first <= ends[0] < first + 2 * PERIOD
    tail = WINDOW[1] - math.pi / OMEGA
    before = ends[ends < tail]
    # before the tail: every update_every_rad (pi/4: 8.3 ms)
    assert before.size >= 3
    assert np.all(np.diff(before) >= math.pi / 4 / OMEGA - 1e-12)
    # in the tail: as soon as the 3 ms fit is done, the last one within a fit of the end
    steps = np.diff(ends[ends >= tail])
    assert steps.size >= 5 and np.all(steps <= 3e-3 + PERIOD + 1e-9)
    assert WINDOW[1] - ends[-1] <= 3e-3 + 2 * PERIOD


def test_no_back_to_back_when_the_tail_is_zero_or_the_worker_is_busy():
    ends = [w[1] for w, final in _drive(fit_ms=3.0, tail=0.0) if not final]
    assert np.all(np.diff(ends) >= math.pi / 4 / OMEGA - 1e-12)
    slow = [w[1] for w, final in _drive(fit_ms=50.0) if not final]
    assert len(slow) == len(ends)           # a busy worker gets no extra requests
    assert _drive(fit_ms=3.0, update_every=0.0) == [(WINDOW, True)]
