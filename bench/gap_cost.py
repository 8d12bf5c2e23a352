"""
Lost samples: the cost of a fit over a record with a gap, against the same record without it.

A record at 1 kHz and Ω = 2π·15 rad/s (0.094 rad of azimuth a sample) of the μ = 0 wake model
(A, AL/τ, 1/τ unknown, initial states estimated), stirring amplitude 0.03 rad, 0.05°
measurement noise, 450 samples. From it a run of samples is removed at a third of the record (a
recorder stall or a network loss of ``GAPS`` samples). Output error and filter error (σ_V and
the measurement σ's estimated) are timed interleaved on each record; the ratio is a fit's time
with the gap over its time on the whole record (the peer). The same fits with every interval
given the gap's RK4 substeps (``gap_refinement`` off: the lost samples do not get steps of
their own) are timed once for the smallest gap, as a second peer.

Run: ``python bench/gap_cost.py [--repeat N]``.
"""

import argparse
import math
import os
import sys

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

from common import fmt_time, markdown_table, say, time_interleaved, write_results  # noqa: E402
import numpy as np  # noqa: E402

from rotor_id.estimation import kalman, simulate as simulation  # noqa: E402
from rotor_id.estimation.filter_error import fit_filter_error_ml  # noqa: E402
from rotor_id.estimation.output_error import Experiment, fit_output_error  # noqa: E402
from rotor_id.physics.models import MultibladeWake, RotorConstants  # noqa: E402
from rotor_id.physics.stirring import StirringSchedule  # noqa: E402

UNKNOWNS = ['A', 'AL_over_tau', 'inv_tau']
NOISE = math.radians(0.05)
STEP = 2 * math.pi * 15 / 1000          # rad of azimuth per sample at 1 kHz, 15 Hz
SAMPLES = 450
GAPS = (10, 50, 200)


def experiments():
    """Whole record and one per gap: {label: Experiment}."""
    model = MultibladeWake(RotorConstants(advance_ratio=0.0))
    stirring = StirringSchedule(collective=0.0, amplitude=0.03, omegadot=-0.1 / math.pi, t0=2.0)
    t = 2.0 + STEP * np.arange(SAMPLES)
    p = model.nominal()
    x0 = model.equilibrium(t[:1], p, stirring(t[:1]))
    y = simulation.simulate(model, p, stirring, t, x0).y
    y = y + np.random.default_rng(7).normal(0.0, NOISE, y.shape)
    out = {'whole record': Experiment(model, stirring, t, y, initial_state='estimate')}
    for gap in GAPS:
        keep = np.delete(np.arange(SAMPLES), np.arange(SAMPLES // 3, SAMPLES // 3 + gap))
        out[f'{gap} samples lost'] = Experiment(model, stirring, t[keep], y[keep],
                                                initial_state='estimate')
    return out


def fits(exp):
    """Return the two fits of one record as callables."""
    guess = {'A': 0.45, 'AL_over_tau': 0.2, 'inv_tau': 0.1}
    return {'output error': lambda: fit_output_error([exp], UNKNOWNS, guess=guess,
                                                     noise_std=NOISE),
            'filter error': lambda: fit_filter_error_ml([exp], UNKNOWNS, guess=guess)}


def main(argv=None):
    """Time the fits, write bench/results/gap_cost.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    records = experiments()
    functions = {(label, kind): fn for label, exp in records.items()
                 for kind, fn in fits(exp).items()}
    say(f'timing {len(functions)} fits interleaved, {args.repeat} round(s)')
    timed = time_interleaved({f'{a} | {b}': f for (a, b), f in functions.items()}, args.repeat)
    # peer: every interval given the gap's substeps, once (it is slow)
    smallest = f'{GAPS[0]} samples lost'
    saved = simulation.gap_refinement
    simulation.gap_refinement = kalman.gap_refinement = lambda *a: None
    try:
        before = time_interleaved(dict(fits(records[smallest])), 1, warmup=0)
    finally:
        simulation.gap_refinement = kalman.gap_refinement = saved
    rows = []
    for kind in ('output error', 'filter error'):
        peer = timed[f'whole record | {kind}']
        for label in records:
            run = timed[f'{label} | {kind}']
            est = run['result']
            rows.append([kind, label, fmt_time(run['median']), fmt_time(run['cpu']),
                         f'{run["cpu"] / peer["cpu"]:.2f}',
                         f'{est.model_parameters["A"]:.4f} ± {est.std[0]:.4f}'])
        old = before[kind]
        rows.append([kind, f'{smallest}, peer: gap substeps everywhere',
                     fmt_time(old['median']), fmt_time(old['cpu']),
                     f'{old["cpu"] / peer["cpu"]:.2f}',
                     f'{old["result"].model_parameters["A"]:.4f} ± {old["result"].std[0]:.4f}'])
    body = ('A 450-sample record (0.45 s at 1 kHz, μ = 0 wake model, A, AL/τ, 1/τ and the '
            'initial states estimated) with a run of samples removed at a third of it. '
            '"ratio" is the median CPU time of a fit over that of the same fit on the whole '
            f'record, timed interleaved ({args.repeat} rounds); "peer" rows are one run each '
            'of fits that give every interval the RK4 substeps of the gap. The estimates on '
            'a record with a gap are those of its samples (fewer samples: a larger σ).\n\n'
            + markdown_table(['fit', 'record', 'wall', 'CPU', 'ratio (CPU)', 'A ± σ'], rows))
    print(body)
    if not args.no_write:
        write_results('gap_cost', 'Lost samples: fit cost with a gap in the record', body,
                      f'python bench/gap_cost.py --repeat {args.repeat}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
