"""
"Never confidently wrong" on messy recordings: one lab fault at a time, through the CLI.

A clean 4-blade recording of the μ = 0 wake rotor is simulated by the library's planning path
(test/commands/campaign_helpers.write_test_point: trim, cyclic step, stirring, 0.05° sensor
noise); each fault below is injected into a copy of it, the copy written as a bag, and
``rotor-id identify`` run on it (cli.main: exit code, stderr, JSON). Every outcome is put in one
class:

(a) ``error``: exit 2 with one line, before any fitting;
(b) ``warned``: exit 0 with a warning (or an inadequate adequacy verdict) that the clean record
    does not have;
(c) ``within``: exit 0 and every estimate within 3σ (its Cramér-Rao bound) of the truth;
(b') ``not_converged``: exit 1 with a warning: no estimate offered as usable;
(d) ``confidently_wrong``: exit 0, no new warning, some estimate outside 3σ: a bug.

Each fault is asserted to end in its expected class (never (d)). ``python
test/io/test_messy_recordings.py`` prints the sweep's table (bench/results/messy_sweep.md).
"""

from contextlib import redirect_stderr, redirect_stdout
from dataclasses import replace
import io
import json
from pathlib import Path
import sys

import numpy as np
import pytest
from rotor_id import cli
from rotor_id.io.bag import read_record, write_record_bag
import yaml

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / 'test' / 'commands'))
from campaign_helpers import write_test_point  # noqa: E402,I100

TRUTH = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}    # the plan's values (simulated)
NOISE_DEG = 0.05
NOISE_RAD = np.radians(NOISE_DEG)
SEED = 3
ERROR, WARNED, WITHIN, WRONG = 'error', 'warned', 'within', 'confidently_wrong'
NOT_CONVERGED = 'not_converged'


def _in_window(record, window_s):
    """Return the indices of the record's samples inside window_s."""
    return np.flatnonzero((record.time_s >= window_s[0]) & (record.time_s <= window_s[1]))


def _flap(record, change):
    flap = record.blade_flap.copy()
    change(flap)
    return replace(record, blade_flap=flap)


def _pitch(record, change):
    pitch = record.blade_pitch.copy()
    change(pitch)
    return replace(record, blade_pitch=pitch)


def _spike(size):
    def inject(record, window_s):
        i = _in_window(record, window_s)[40]
        return _flap(record, lambda f: f.__setitem__((i, 1), f[i, 1] + size))
    return inject


def _dropped_to_zero(record, window_s):
    # where blade 3's flap is largest: a reading dropped to 0.0 within ~10σ of zero is noise
    inside = _in_window(record, window_s)
    i = inside[np.argmax(np.abs(record.blade_flap[inside, 2]))]
    return _flap(record, lambda f: f.__setitem__((i, 2), 0.0))


def _pitch_stuck(samples):
    def inject(record, window_s):
        i = _in_window(record, window_s)[30]
        return _pitch(record, lambda p: p.__setitem__((slice(i, i + samples), 0), p[i, 0]))
    return inject


def _flap_dead(record, window_s):
    return _flap(record, lambda f: f.__setitem__((slice(None), 2), f[0, 2]))


def _flap_zero(record, window_s):
    return _flap(record, lambda f: f.__setitem__((slice(None), 3), 0.0))


def _flap_sign(record, window_s):
    return _flap(record, lambda f: f.__setitem__((slice(None), 1), -f[:, 1]))


def _joints_swapped(record, window_s):
    names = list(record.blade_names)
    names[0], names[1] = names[1], names[0]
    return replace(record, blade_names=names)


def _offset_all(size):
    def inject(record, window_s):
        return replace(record, blade_flap=record.blade_flap + size)
    return inject


def _speed_scaled(factor):
    def inject(record, window_s):
        return replace(record, rotor_speed_rad_s=record.rotor_speed_rad_s * factor)
    return inject


def _short(record, window_s):
    keep = record.time_s <= window_s[0] + 0.3 * (window_s[1] - window_s[0])
    return record.window(record.time_s[0], record.time_s[keep][-1])


def _pitch_spike(record, window_s):
    i = _in_window(record, window_s)[70]
    return _pitch(record, lambda p: p.__setitem__((i, 3), p[i, 3] + 0.2))


def _flap_stuck(samples):
    def inject(record, window_s):
        i = _in_window(record, window_s)[50]
        return _flap(record, lambda f: f.__setitem__((slice(i, i + samples), 1), f[i, 1]))
    return inject


def _offset_one(size):
    def inject(record, window_s):
        return _flap(record, lambda f: f.__setitem__((slice(None), 0), f[:, 0] + size))
    return inject


def _omega_in_description(record, window_s):
    """Return the record and a run description stating a rotor speed 15 % below the bag's."""
    omega = float(np.mean(record.rotor_speed_rad_s))
    return record, {'omega_rad_s': round(0.85 * omega, 2)}


def _short_window_stuck(record, window_s):
    """Return blade 2's flap held for 15 samples, and a window of 70 samples (< 80) over it."""
    inside = _in_window(record, window_s)
    window = [float(record.time_s[inside[0]]), float(record.time_s[inside[69]])]
    return _flap_stuck(15)(record, window_s), {'window_s': window}


def _nan_message(record, window_s):
    i = _in_window(record, window_s)[50]
    return _flap(record, lambda f: f.__setitem__((i, 0), np.nan))


def _flap_late(samples):
    def inject(record, window_s):
        late = np.roll(record.blade_flap, samples, axis=0)
        late[:samples] = record.blade_flap[0]
        return replace(record, blade_flap=late)
    return inject


def _lost(samples):
    def inject(record, window_s):
        i = _in_window(record, window_s)[40]
        keep = np.delete(np.arange(record.time_s.size), np.arange(i, i + samples))
        return replace(record, time_s=record.time_s[keep], t=record.t[keep],
                       rotor_speed_rad_s=record.rotor_speed_rad_s[keep],
                       blade_flap=record.blade_flap[keep], blade_pitch=record.blade_pitch[keep])
    return inject


#: name -> (what it is, injection, class, text the warning or error must contain or None)
FAULTS = {
    'flap_spike_20sigma': ('one flap sample of blade 2 +20σ (0.017 rad)',
                           _spike(20 * NOISE_RAD), WITHIN, 'blade_2: 1,'),
    'flap_spike_0.2rad': ('one flap sample of blade 2 +0.2 rad', _spike(0.2), WITHIN,
                          'blade_2: 1,'),
    'flap_dropped_to_zero': ('blade 3 flap reads 0.0 at its largest sample', _dropped_to_zero,
                             WITHIN, 'blade_3: 1, e.g. 0 rad'),
    'pitch_stuck_5': ('blade 1 pitch held for 5 samples', _pitch_stuck(5), WITHIN, None),
    'pitch_stuck_60': ('blade 1 pitch held for 60 samples', _pitch_stuck(60), NOT_CONVERGED,
                       'not noise'),
    'flap_dead': ('blade 3 flap constant (first value) throughout', _flap_dead, ERROR,
                  'flap of blade_3 reads exactly'),
    'flap_zero': ('blade 4 flap exactly 0.0 throughout (disconnected)', _flap_zero, ERROR,
                  'flap of blade_4 reads exactly 0 rad'),
    'flap_sign_flipped': ('blade 2 flap with the sign flipped', _flap_sign, WITHIN,
                          'not noise'),
    'joints_swapped': ('joint names of blades 1 and 2 swapped in the bag', _joints_swapped,
                       NOT_CONVERGED, 'not noise'),
    'offset_all_blades': ("+0.01 rad on every blade's flap", _offset_all(0.01), WITHIN, None),
    'speed_10pct_high': ('rotor speed (velocity) 10 % above the azimuth rate',
                         _speed_scaled(1.1), ERROR, 'rotor speed (velocity) says 103.7'),
    'speed_in_rpm': ('rotor speed written in rpm', _speed_scaled(60 / (2 * np.pi)), ERROR,
                     'rotor speed (velocity) says 900'),
    'record_short': ('record ends 30 % into the window', _short, ERROR, 'outside the record'),
    'pitch_spike_0.2rad': ('one pitch sample of blade 4 +0.2 rad', _pitch_spike, WITHIN,
                           'blade_4: 1,'),
    'flap_stuck_30': ('blade 2 flap held for 30 samples', _flap_stuck(30), WITHIN, 'not noise'),
    'offset_one_blade': ('+0.005 rad on blade 1 flap only', _offset_one(0.005), WITHIN,
                         'not noise'),
    'flap_late_1': ('flap read 1 sample late (all blades)', _flap_late(1), WITHIN, None),
    'omega_in_description': ('run description says omega_rad_s 15 % below the bag',
                             _omega_in_description, WITHIN, "unknown key 'omega_rad_s' ignored"),
    'short_window_stuck': ('70-sample window (adequacy untested), blade 2 flap held 15',
                           _short_window_stuck, WITHIN, 'adequacy was not checked'),
    'nan_in_one_message': ('blade 1 flap NaN in one message', _nan_message, WITHIN,
                           'position is NaN'),
    'samples_lost_30': ('30 samples of every topic lost inside the window (a recorder stall)',
                        _lost(30), WITHIN, 'gap(s) in the samples'),
    'flap_late_2': ('flap read 2 samples late (all blades)', _flap_late(2), WRONG, None),
}
#: Faults still confidently wrong, with the reason (asserted to stay so: xfail strict)
KNOWN_WRONG = {
    'flap_late_2': 'a common flap delay is a phase lag, which the fit absorbs into A, '
                   'AL_over_tau and inv_tau; the residuals stay white (identify prints the '
                   'shift per sample of delay on its "timing:" line, not as a warning)',
}


@pytest.fixture(scope='module')
def clean(tmp_path_factory):
    """Return (directory, clean Record, run-description dict) of the simulated test point."""
    root = tmp_path_factory.mktemp('messy')
    return _clean(root)


def _clean(root):
    bag = write_test_point(root, 'clean', seed=SEED, noise_deg=NOISE_DEG)
    description = yaml.safe_load((root / 'clean.yaml').read_text())
    return root, read_record(bag), description


def identify(root, name, record, description):
    """Write ``record`` as bag NAME and run ``rotor-id identify`` on it: (rc, stderr, JSON)."""
    bag = write_record_bag(root / name, record)
    config = root / f'{name}.yaml'
    config.write_text(yaml.safe_dump(description, sort_keys=False))
    out = root / f'{name}.json'
    err, std = io.StringIO(), io.StringIO()
    with redirect_stderr(err), redirect_stdout(std):
        rc = cli.main(['identify', str(bag), '--config', str(config), '--json', str(out),
                       '--quiet'])
    data = json.loads(out.read_text()) if rc == 0 and out.is_file() else None
    return rc, err.getvalue().strip().splitlines(), data


def classify(rc, err, data, truth=None):
    """
    Return (class, worst |estimate − truth|/σ, warnings) of one identify run.

    The warnings are the ``warning:`` lines on stderr (the reader's and the fit's) and the
    JSON's; the clean record has none.
    """
    said = [line[len('warning: '):] for line in err if line.startswith('warning: ')]
    if rc == 1:                  # not converged: no estimate offered as usable
        return NOT_CONVERGED, None, said
    if rc != 0:
        return (ERROR if rc == 2 and len(err) == 1 else f'exit {rc}'), None, err
    truth = TRUTH if truth is None else truth
    worst = max(abs(p['value'] - truth[name]) / p['std']
                for name, p in data['parameters'].items())
    said = list(dict.fromkeys(said + data['warnings']))
    if worst <= 3.0:
        return WITHIN, worst, said
    if said or data['adequacy']['verdict'] == 'inadequate':
        return WARNED, worst, said
    return WRONG, worst, said


def run_fault(root, record, description, name):
    """Inject fault ``name`` into the clean record, identify, classify."""
    faulty = FAULTS[name][1](record, description['window_s'])
    if isinstance(faulty, tuple):            # (record, changes of the run description)
        faulty, changes = faulty
        description = {**description, **changes}
    return classify(*identify(root, name, faulty, description))


def test_clean_record_is_within_its_bounds(clean):
    root, record, description = clean
    kind, worst, said = classify(*identify(root, 'again', record, description))
    assert kind == WITHIN and not said, (kind, worst, said)


@pytest.mark.parametrize('name', [pytest.param(name, marks=pytest.mark.xfail(
    reason=KNOWN_WRONG[name], strict=True)) if name in KNOWN_WRONG else name for name in FAULTS])
def test_fault_is_never_confidently_wrong(clean, name):
    root, record, description = clean
    kind, worst, said = run_fault(root, record, description, name)
    assert kind != WRONG, (name, worst, said)
    expected, text = FAULTS[name][2:]
    assert kind == expected, (name, kind, worst, said)
    if text is not None:
        assert any(text in line for line in said), (name, said)
    if kind == WITHIN and text is None:       # nothing to say, and nothing said
        assert not said, (name, said)


@pytest.mark.parametrize('rate_hz', [1000.0, 300.0])
def test_value_spikes_found_where_injected_and_nowhere_else(rate_hz):
    """
    streams.value_spikes on planned records (the lateral-cyclic step, stirring, 0.1° noise).

    Clean: nothing flagged on any channel (the step of the pitch and the flap's peaks are
    signal, also at 300 Hz where a revolution is 20 samples). Injected: exactly the samples of
    a 0.2 rad spike, of a reading dropped to 0.0 and of a 3-sample burst.
    """
    from rotor_id import planning
    from rotor_id.io.streams import value_spikes
    plan = planning.load_plan(REPO / 'config' / 'plan_wake.yaml')
    plan = replace(plan, rate_hz=rate_hz)
    checked = 0
    for seed in range(4):
        candidate = plan.candidates[seed % len(plan.candidates)]
        record = planning.simulate_run(plan, candidate, rng=np.random.default_rng(seed)).record
        for values in (record.blade_flap, record.blade_pitch):
            assert not any(found.size for found in value_spikes(values)), seed
        flap = record.blade_flap.copy()
        n = len(flap)
        flap[n // 3, 0] += 0.2
        dropped = n // 4 + int(np.argmax(np.abs(flap[n // 4:n // 2, 1])))   # largest |flap|
        flap[dropped, 1] = 0.0
        flap[2 * n // 3:2 * n // 3 + 3, 2] -= 0.05
        found = value_spikes(flap)
        assert found[0].tolist() == [n // 3]
        # (a reading dropped to 0.0 where the flap is within 10σ of zero is harmless, and not
        # told from the noise: the check is where it is largest; at 300 Hz the flap moves
        # ~0.005 rad a sample, and a spike must exceed 5 such steps)
        if rate_hz >= 1000 and abs(record.blade_flap[dropped, 1]) > 12 * plan.noise_std_rad:
            assert found[1].tolist() == [dropped]
            checked += 1
        assert found[2].tolist() == list(range(2 * n // 3, 2 * n // 3 + 3))
        assert found[3].size == 0
    assert checked >= 2 or rate_hz < 1000


def test_fast_stirring_peaks_are_signal_not_spikes():
    """
    Fast stirring: the peaks of the pitch are signal, not spikes.

    The demo plant stirred on past its window (the progressing stirring reaches ~7/rev, blade
    pitch 85-115 Hz, 9-12 samples a cycle at 1 kHz, after 1.85 s): its pitch peaks leave the
    running median every half cycle and are signal (they were taken for spikes,
    70-85 a blade in 3 s, and flattened). A 0.5 rad pitch spike among them is still found (a
    spike must leave the running median by 10 times the signal's spread about it).
    """
    from rotor_id.io.streams import value_spikes
    from rotor_id.nodes.live import PlantStepper, rotor_constants
    from rotor_id.physics.stirring import StirringSchedule
    omega, theta0 = 2 * np.pi * 15, np.radians(2.0)
    stepper = PlantStepper('multiblade_wake', rotor_constants(4, 0.0, 1.2, 0.97),
                           {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}, omega, 1000.0,
                           theta0, flap_noise_std=np.radians(0.05),
                           pitch_noise_std=np.radians(0.005), seed=3)
    schedule = StirringSchedule(theta0, np.radians(1.5), -0.1 / np.pi,
                                stepper.step + 2 * np.pi + 70.0, stepper.step + 2 * np.pi)
    parts = []
    for _ in range(3000 // 5):
        for j in range(5):
            tc = stepper.t + stepper.step * (j + 1)
            stepper.command(tc, schedule([tc])[0])
        parts.append(stepper.advance(5))
    _, flap, pitch = (np.concatenate(p) for p in zip(*parts))
    for values in (flap, pitch):
        assert not any(found.size for found in value_spikes(values))
    pitch[2500, 1] += 0.5
    found = value_spikes(pitch)
    assert 2500 in found[1].tolist() and found[1].size <= 3
    assert not any(found[k].size for k in (0, 2, 3))


def test_short_multiblade_window_with_a_held_flap_is_not_silent(tmp_path):
    """
    A 67-sample multiblade test point (μ = 0.4, 1 rev) is too short for the adequacy tests.

    With blade 2's flap held for 30 samples the estimate is tens of σ off the truth; before the
    "not checked" warning it came with exit 0 and no warning at all.
    """
    from rotor_id import planning
    plan_path = REPO / 'config' / 'plan_multiblade.yaml'
    plan = replace(planning.load_plan(plan_path), noise_std_rad=NOISE_RAD)
    candidate = next(c for c in plan.candidates
                     if c.duration_rev == 1.0 and c.amplitude_rad > 0.05)
    run = planning.simulate_run(plan, candidate, rng=np.random.default_rng(SEED))
    write_record_bag(tmp_path / 'point', replace(run.record,
                                                 stamp0_ns=1_763_700_000_000_000_000))
    description = yaml.safe_load(plan_path.read_text())
    for key in planning.PLAN_KEYS:
        description.pop(key, None)
    description['window_s'] = [float(v) for v in candidate.window_s(plan.omega_rad_s)]
    description['initial_guess'] = dict(plan.guess)
    record = read_record(tmp_path / 'point')
    faulty = _flap_stuck(30)(record, description['window_s'])
    rc, err, data = identify(tmp_path, 'held', faulty, description)
    kind, worst, said = classify(rc, err, data, truth=dict(plan.guess))
    assert kind != WRONG, (worst, said)
    assert any('adequacy was not checked' in line and '67 samples' in line
               for line in said), said


def main(argv=None):
    """Print the sweep as a markdown table; ``--seeds N``: classes over N noise seeds."""
    import argparse
    import collections
    import tempfile
    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument('--seeds', type=int, default=1)
    seeds = range(SEED, SEED + parser.parse_args(argv).seeds)
    with tempfile.TemporaryDirectory() as directory:
        rows = collections.defaultdict(list)
        for seed in seeds:
            root = Path(directory) / f'seed{seed}'
            root.mkdir()
            bag = write_test_point(root, 'clean', seed=seed, noise_deg=NOISE_DEG)
            description = yaml.safe_load((root / 'clean.yaml').read_text())
            record = read_record(bag)
            rows['clean'].append(classify(*identify(root, 'again', record, description)))
            for name in FAULTS:
                rows[name].append(run_fault(root, record, description, name))
            print(f'seed {seed} done', file=sys.stderr, flush=True)
        print('| fault | outcome(s) | worst \\|error\\|/σ | first warning / error (first seed) |')
        print('|---|---|---|---|')
        for name, outcomes in rows.items():
            what = FAULTS[name][0] if name in FAULTS else 'no fault'
            counts = collections.Counter(kind for kind, _, _ in outcomes)
            kinds = ', '.join(f'{kind} {count}/{len(outcomes)}' if len(outcomes) > 1 else kind
                              for kind, count in counts.items())
            worst = [w for _, w, _ in outcomes if w is not None]
            shown = f'{max(worst):.1f}' if worst else ''
            said = (outcomes[0][2][0] if outcomes[0][2] else '').replace('|', '/')
            said = said.replace('rotor-id identify: error: ', 'error: ')
            print(f'| {name}: {what} | {kinds} | {shown} | {said[:150]} |', flush=True)


if __name__ == '__main__':
    main()


def test_every_repair_is_listed_in_the_json(clean):
    """
    The identify JSON lists each replaced reading (topic, blade, time, old, new, why).

    One flap sample of blade 2 and one pitch sample of blade 4 +0.2 rad (bit flips) in the
    window: exactly those two in ``repairs``, old as received, new within 5 noise σ of the
    clean reading. The clean record lists none.
    """
    root, record, description = clean
    rc, _, data = identify(root, 'clean_json', record, description)
    assert rc == 0 and data['repairs'] == []
    inside = _in_window(record, description['window_s'])
    flap_at, pitch_at = inside[40], inside[70]
    flap, pitch = record.blade_flap.copy(), record.blade_pitch.copy()
    flap[flap_at, 1] += 0.2
    pitch[pitch_at, 3] += 0.2
    rc, _, data = identify(root, 'two_spikes', replace(record, blade_flap=flap,
                                                       blade_pitch=pitch), description)
    assert rc == 0
    got = sorted(data['repairs'], key=lambda r: r['topic'])
    assert [(r['topic'], r['blade'], r['why']) for r in got] == [
        ('/rotor/blade_flap', 'blade_2', 'value_spike'),
        ('/rotor/blade_pitch', 'blade_4', 'value_spike')]
    for repair, (values, at, column) in zip(got, ((flap, flap_at, 1), (pitch, pitch_at, 3))):
        clean_values = record.blade_flap if values is flap else record.blade_pitch
        assert repair['time'] == pytest.approx(record.time_s[at], abs=1e-9)
        assert repair['old'] == values[at, column]
        assert abs(repair['new'] - clean_values[at, column]) < 5 * NOISE_RAD
