"""
`rotor-id identify BAG BAG ... --config ...`: several recordings in one estimate (pins #17).

Two stirring transients of the μ = 0 wake rotor, progressing and regressing, are simulated by
the planning module (the library's simulator, the test-stand convention) at different sensor
noise, written as bags and identified alone and together. The report's Ch.3 information
argument says the information matrices of the runs add: with each run's initial states its own,
the parameters' information of the pair is the sum of each run's Schur complement (the
initial states eliminated). So the joint σ must come out below either run's alone, and at the
σ that sum predicts (estimation/information.py via planning.predict_transient).
"""

from dataclasses import replace
import json
from pathlib import Path

import numpy as np
import pytest
from rotor_id import cli
from rotor_id import planning
from rotor_id.io.bag import write_record_bag
import yaml

REPO = Path(__file__).resolve().parents[2]
PLAN = REPO / 'config' / 'plan_wake.yaml'
NOISE_RAD = {'progressing': np.radians(0.1), 'regressing': np.radians(0.2)}


def _run_description(plan, candidate):
    """Return the run description of a candidate's bag: the plan without planning keys."""
    data = yaml.safe_load(PLAN.read_text())
    for key in planning.PLAN_KEYS + ('noise_std_rad',):
        data.pop(key, None)
    data['window_s'] = [float(v) for v in candidate.window_s(plan.omega_rad_s)]
    return data


def _schur(information, k):
    """Information on the first k parameters with the rest (initial states) eliminated."""
    a, b, d = information[:k, :k], information[:k, k:], information[k:, k:]
    return a - b @ np.linalg.solve(d, b.T)


@pytest.fixture(scope='module')
def two_runs(tmp_path_factory):
    """Progressing and regressing bags (2 rev of stirring each) and their YAMLs."""
    root = tmp_path_factory.mktemp('runs')
    base = planning.load_plan(PLAN)
    runs = {}
    for seed, direction in enumerate(('progressing', 'regressing')):
        plan = replace(base, noise_std_rad=float(NOISE_RAD[direction]))
        candidate = next(c for c in plan.candidates
                         if c.direction == direction and abs(c.omegadot) > 0.03)
        candidate = replace(candidate, duration_rev=2.0)
        run = planning.simulate_run(plan, candidate, rng=np.random.default_rng(100 + seed))
        record = replace(run.record, stamp0_ns=1_763_700_000_000_000_000)   # stamps not zero
        bag = write_record_bag(root / direction, record)
        config = root / f'{direction}.yaml'
        config.write_text(yaml.safe_dump(_run_description(plan, candidate)))
        runs[direction] = {'bag': bag, 'config': config, 'plan': plan, 'candidate': candidate}
    return runs, base.unknowns, base.guess


def _predicted_information(run, values, channel_noise):
    """
    Parameter information of one run predicted by the planning path (information.py).

    At ``values`` and the run's channel noise (the eq.-30 channel σ is the blade σ/√2).
    """
    plan = replace(run['plan'], guess=dict(values),
                   noise_std_rad=float(np.sqrt(np.mean(np.square(channel_noise)) * 2.0)))
    prediction = planning.predict_transient(plan, run['candidate'])
    return _schur(prediction.history.information[-1], len(plan.unknowns))


def _identify(tmp_path, bags, configs, name):
    out = tmp_path / f'{name}.json'
    args = ['identify', *map(str, bags)]
    for config in configs:
        args += ['--config', str(config)]
    rc = cli.main(args + ['--json', str(out), '--quiet'])
    assert rc == 0
    return json.loads(out.read_text())


def test_joint_sigma_shrinks_as_the_information_of_the_runs_adds(two_runs, tmp_path, capsys):
    runs, unknowns, truth = two_runs
    alone = {d: _identify(tmp_path, [r['bag']], [r['config']], d) for d, r in runs.items()}
    joint = _identify(tmp_path, [r['bag'] for r in runs.values()],
                      [r['config'] for r in runs.values()], 'joint')
    figure = tmp_path / 'joint.png'
    table = capsys.readouterr().out
    assert 'progressing' in table and 'regressing' in table      # the per-run table
    values = {n: joint['parameters'][n]['value'] for n in unknowns}
    sections = {r['name']: r for r in joint['runs']}
    predicted_joint = np.sqrt(np.diag(np.linalg.inv(sum(
        _predicted_information(run, values, sections[d]['noise_std'])
        for d, run in runs.items()))))
    for i, name in enumerate(unknowns):
        sigma = joint['parameters'][name]['std']
        # the joint bound is the inverse of the summed information, predicted independently
        # (from the trajectory simulated at the estimate, not the fitted one: within 10 %)
        assert sigma == pytest.approx(predicted_joint[i], rel=0.1), name
        for direction, result in alone.items():
            single = result['parameters'][name]['std']
            assert sigma < single, (direction, name, sigma, single)
        value = joint['parameters'][name]['value']
        assert abs(value - truth[name]) < 3.5 * sigma, (name, value, sigma)
    for direction, result in alone.items():               # and each run alone likewise
        own = {n: result['parameters'][n]['value'] for n in unknowns}
        predicted = np.sqrt(np.diag(np.linalg.inv(_predicted_information(
            runs[direction], own, result['noise_std']))))
        for i, name in enumerate(unknowns):
            assert result['parameters'][name]['std'] == pytest.approx(predicted[i], rel=0.15), \
                (direction, name)
    # today's keys plus one section per run, each with its own noise and window
    assert {'model', 'parameters', 'covariance', 'noise_std', 'iterations', 'converged',
            'window_s'} <= set(joint)
    assert [r['name'] for r in joint['runs']] == ['progressing', 'regressing']
    for section, (direction, run) in zip(joint['runs'], runs.items()):
        channel_sigma = NOISE_RAD[direction] / np.sqrt(2.0)          # (β1 − β3)/2
        assert np.allclose(section['noise_std'], channel_sigma, rtol=0.1), section
        assert np.allclose(section['residual_rms'], section['noise_std'], rtol=1e-6)
        config = yaml.safe_load(run['config'].read_text())
        assert section['window_s'] == pytest.approx(config['window_s'])
        assert len(section['initial_states']) == 6      # βI, βII, their rates, λI, λII
    rc = cli.main(['identify', *(str(r['bag']) for r in runs.values()),
                   '--config', str(runs['progressing']['config']), '--figure', str(figure),
                   '--quiet'])
    assert rc == 0 and figure.stat().st_size > 20_000


def test_runs_that_disagree_are_refused_in_one_line(two_runs, tmp_path, capsys):
    runs, _, _ = two_runs
    bags = [str(r['bag']) for r in runs.values()]
    rc = cli.main(['identify', *bags, '--config', str(runs['progressing']['config']),
                   '--config', str(runs['regressing']['config']), '--config',
                   str(runs['regressing']['config'])])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and '2 bags but 3 --config' in err[0]
    other = yaml.safe_load(runs['regressing']['config'].read_text())
    other['unknowns'] = ['A', 'inv_tau']
    config = tmp_path / 'other.yaml'
    config.write_text(yaml.safe_dump(other))
    rc = cli.main(['identify', *bags, '--config', str(runs['progressing']['config']),
                   '--config', str(config)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and 'disagree on unknowns' in err[0], err
    one = str(runs['progressing']['bag'])
    rc = cli.main(['identify', one, one, '--config', str(runs['progressing']['config'])])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and 'overlapping windows' in err[0], err
