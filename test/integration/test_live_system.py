"""
The five nodes as separate processes on the report's mu = 0 dynamic-wake case (real DDS).

One run (module fixture, ~20-60 s depending on the machine's load) of plant, stirring input,
identifier, state estimator and recorder with config/nodes_wake.yaml; this process listens to
every topic and calls the Identify service. What it proves: every message type crosses process
boundaries; the live estimate is within 3σ of the plant's truth with a consistent covariance;
the service identifies the buffered data; the state estimator tracks the flapping; the recorded
bag holds every sample the plant published, is decoded by mcap + mcap-ros2-support (custom types
included) and, identified offline, agrees with the live result; every node exits with 0.
"""

import math
import os
import warnings

from live_helpers import (CpuUse, domain_id, mcap_messages, require_workspace, RosClient,
                          starved, within_sigma)
import numpy as np
import pytest

TRUTH = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}


@pytest.fixture(scope='module')
def live_run(tmp_path_factory):
    """Run the wake case once; return what the tests look at."""
    require_workspace()
    from rotor_id.commands.demo import case_files
    from rotor_id.io.run_description import load_run_description
    from rotor_id.nodes.processes import isolated_env, NodeProcesses
    from rotor_id.nodes.watch import RESULT_KINDS, RunWatcher
    from rotor_id_msgs.msg import ParameterEstimate
    from rotor_id_msgs.srv import Identify

    params_file, description_path, _ = case_files('wake')
    description = load_run_description(description_path)
    import time
    t0 = time.monotonic()

    def mark(what):
        print(f'{time.monotonic() - t0:6.1f} s {what}', flush=True)

    # DDS discovery under CI load: in about one full-suite run in three the test's own
    # watcher never received the estimates that the identifier published (the recorder had
    # them). Probably the late endpoint match now waited for below (wait_for_publishers; the
    # same was seen for the states); the one retry in a fresh domain stays, every assertion
    # unchanged.
    for attempt in (1, 2):
        cpu, load = CpuUse(), os.getloadavg()[0]
        tmp = tmp_path_factory.mktemp('live')
        domain = domain_id()
        ros = RosClient(domain)
        watcher = RunWatcher(ros.node, sensors=True)
        env = isolated_env(domain, tmp / 'ros_log')
        procs = NodeProcesses(env, tmp / 'logs')
        bag = tmp / 'bag'
        run = {'bag': bag, 'watcher': watcher, 'description': description, 'procs': procs}
        procs.start('identifier', params_file, {'target_std': [0.02, 0.02, 0.01]})
        procs.start('state_estimator', params_file)
        procs.start('recorder', params_file, {'output': str(bag)})
        procs.start('stirring_input', params_file)
        # this process hears every node's outputs before the rotor starts: a late match heard
        # only the last states (or none: the run is 1 s, the fixture over 4 s later)
        late = watcher.wait_for_publishers(RESULT_KINDS, 60.0, alive=lambda: not procs.dead())
        assert not late, f'no {late} publisher matched; exited: {procs.dead()}'
        # the stirring input holds trim until asked: the test point starts with the rotor
        started = watcher.trigger('/stirring_input/start', 60.0, alive=lambda: not procs.dead())
        assert started is not None and started.success, (started, procs.dead())
        # 5 subscribers of the azimuth: the four nodes and this test
        procs.start('rotor_plant', params_file, {'duration_s': description.window_s[1] + 0.05,
                                                 'wait_for_subscribers': 5, 'seed': 7})
        done = watcher.spin_until(lambda: watcher.final_estimate() is not None, 150.0,
                                  alive=lambda: not procs.dead())
        run['load'], run['busy'] = max(load, os.getloadavg()[0]), cpu.busy_share()
        mark(f'final estimate (attempt {attempt}): {done}')
        # a run the machine starved into a safety stop (the plant behind the clock, the
        # stirring node ramping down on a stale azimuth: test point 1 aborted) is run again
        aborted = done and watcher.final_estimate().status == ParameterEstimate.STATUS_ABORTED
        if (done and not aborted) or attempt == 2:
            break
        print(f'{"test point 1 aborted" if aborted else "no final estimate reached the test"}'
              '; identifier log:\n' + procs.log('identifier'), flush=True)
        procs.stop_all()
        ros.close()
    try:
        assert done, f'no final estimate; exited: {procs.dead()}\n' + procs.log('identifier')
        client = ros.node.create_client(Identify, '/identifier/identify')
        assert client.wait_for_service(timeout_sec=20.0), 'no Identify service'
        answers = []
        for start, end in ((description.window_s[0], description.window_s[1]), (0.5, 99.0)):
            future = client.call_async(Identify.Request(window_start_s=start,
                                                        window_end_s=end))
            watcher.spin_until(future.done, 60.0)
            answers.append(future.result())
        run['service'] = answers
        mark('service')
        # the state estimator reports the adopted parameters on its next /diagnostics
        watcher.spin_until(lambda: any(v.key == 'parameter_updates' for s in
                                       watcher.diagnostics('state_estimator') for v in s.values),
                           10.0)
        mark('states')
        # every node reports on /diagnostics once a period (1 s); a run shorter than a couple
        # of periods after discovery can end before the first report of each has arrived
        watcher.spin_until(lambda: NODES <= _reporters(watcher.messages), 10.0)
        mark('diagnostics')
    finally:
        run['codes'] = procs.stop_all()
        run['exits'] = procs.exit_summary()
        mark('stopped')
        run['logs'] = {name: procs.log(name) for name in procs.procs}
        ros.close()
    return run


def _stamp(msg):
    """(sec, nanosec) of a message's header: the key that pairs a state with its flap sample."""
    return msg.header.stamp.sec, msg.header.stamp.nanosec


NODES = {'rotor_plant', 'stirring_input', 'identifier', 'state_estimator', 'recorder'}


def _reporters(messages):
    """Names of the nodes heard on /diagnostics."""
    return {s.name.split(':')[0] for a in messages['diagnostics'] for s in a.status}


def test_every_message_type_crosses_processes(live_run):
    messages = live_run['watcher'].messages
    for kind in ('estimate', 'progress', 'state', 'stirring', 'diagnostics', 'blade_flap',
                 'blade_pitch', 'azimuth', 'pitch_command'):
        assert messages[kind], f'no {kind} message received'
    assert NODES <= _reporters(messages)


def test_live_estimate_within_3_sigma_with_a_consistent_covariance(live_run):
    from rotor_id_msgs.msg import ParameterEstimate
    final = live_run['watcher'].final_estimate()
    assert final.status == ParameterEstimate.STATUS_CONVERGED, final.message
    assert list(final.names) == ['A', 'AL_over_tau', 'inv_tau']
    ok, text = within_sigma(final.values, final.std, TRUTH, final.names)
    assert ok, text
    cov = np.array(final.covariance).reshape(3, 3)
    assert np.allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.allclose(np.sqrt(np.diag(cov)), final.std)
    # the report's progressing wake case, angles in degrees: M⁻¹(A, A) = .052 for R = I, Δt = .1
    # and known initial states (docs/models.md §3.3). M⁻¹ scales with Δt (here Ω/1 kHz = .094),
    # with the channel variance (σ²/2 per eq.-30 channel) and with (1 rad / 1°)²; estimating the
    # six initial states as well can only raise it (the report's 7-parameter case: ×1.53 in σ)
    sigma_channel = math.radians(0.05) / math.sqrt(2)
    bound = math.sqrt(0.052 * 0.094 / 0.1) * math.degrees(sigma_channel)
    assert 1.0 < final.std[0] / bound < 2.5, (final.std[0], bound, final.message,
                                              live_run['logs'].get('identifier', '')[-3000:])
    assert final.window_s == pytest.approx(12.0 / (30 * math.pi), abs=0.002)


def test_growing_window_estimates_and_progress(live_run):
    watcher = live_run['watcher']
    estimates = watcher.messages['estimate']
    provisional = [m for m in estimates if m.status == 0]
    assert provisional, 'no growing-window estimate before the final one'
    assert all(p.window_s < watcher.final_estimate().window_s for p in provisional)
    iterations = [m.iteration for m in watcher.messages['progress']]
    assert 1 in iterations and max(iterations) >= 2
    assert all(list(m.names)[:3] == ['A', 'AL_over_tau', 'inv_tau']
               for m in watcher.messages['progress'])
    final = watcher.final_estimate()
    assert final.target_met == bool(np.all(np.array(final.std) <= [0.02, 0.02, 0.01]))


def test_identify_service(live_run):
    final = live_run['watcher'].final_estimate()
    good, bad = live_run['service']
    assert good.success, good.message
    z = (np.array(good.estimate.values) - final.values) / final.std
    assert np.max(np.abs(z)) < 0.01, z
    assert not bad.success and 'not inside' in bad.message


def test_state_estimator_tracks_the_flapping(live_run):
    watcher = live_run['watcher']
    states = watcher.messages['state']
    last = states[-1]
    assert list(last.names) == ['beta_I', 'beta_I_dot', 'beta_II', 'beta_II_dot', 'lambda_I',
                                'lambda_II']
    assert last.units[1] == 'rad/s' and last.rotor_speed == pytest.approx(30 * math.pi)
    cov = np.array(last.covariance).reshape(6, 6)
    assert np.all(np.linalg.eigvalsh(0.5 * (cov + cov.T)) > -1e-15)
    # compare the filtered tilt with the measured flap of the same stamp, as recorded: the
    # recorder takes every flap sample (test_recorded_bag_is_complete...), where this test's
    # best-effort reader drops many on a loaded machine (CI: 1 of ~20 states found its flap).
    # The states are those this process received and those the recorder wrote, by stamp: under
    # load this process's reader can match the state estimator late and hear only the last
    # few states (a CI run compared 1), where the recorder, matched before the plant starts,
    # has them all; the second half by time, the filter's start-up being over by then.
    recorded = mcap_messages(live_run['bag'])
    flaps = {_stamp(m): m for m in recorded['/rotor/blade_flap']}
    heard = {_stamp(m): m for m in recorded.get('/rotor_id/state', []) + states}
    stray = sorted(set(heard) - set(flaps))
    assert not stray, f'{len(stray)} states stamped with no recorded flap sample: {stray[:3]}'
    first, final = min(flaps), max(flaps)
    half = (first[0] + final[0]) / 2 + (first[1] + final[1]) / 2e9
    compared = 0
    for key, msg in heard.items():
        if key[0] + key[1] * 1e-9 < half:
            continue
        flap = flaps[key]
        psi = msg.azimuth
        b1 = (flap.position[0] - flap.position[2]) / 2      # eq. 30: cos ψ βI + sin ψ βII
        predicted = math.cos(psi) * msg.values[0] + math.sin(psi) * msg.values[2]
        assert abs(predicted - b1) < 5 * math.radians(0.05), (predicted, b1)
        compared += 1
    published = live_run['logs']['state_estimator'].split('published ')[-1].split(' state')[0]
    # a state estimator starved of CPU ticks seldom (each tick publishes its last state): a CI
    # run with both cores saturated heard 22 states, 1 of them in the second half
    load, busy = live_run['load'], live_run['busy']
    measured = (f'{compared} states in the second half; the state estimator published '
                f'{published}, this process heard {len(states)}, the bag holds '
                f'{len(recorded.get("/rotor_id/state", []))}; load {load:.1f}, CPU '
                f'{100 * busy:.0f} % busy on {os.cpu_count()} cores')
    if not starved(load, busy):
        assert compared >= 3, measured
    else:
        assert compared >= 1, measured
        if compared < 3:
            warnings.warn(f'{measured} (no CPU to spare: 1 is enough)')
    adopted = {v.key: v.value for s in watcher.diagnostics('state_estimator') for v in s.values}
    assert 'parameter_updates' in adopted, 'the state estimator never adopted the estimate'
    final = watcher.final_estimate()
    assert f'A={final.values[0]:.4g}' in adopted['parameters']


def test_recorded_bag_is_complete_and_decoded_by_mcap(live_run):
    decoded = mcap_messages(live_run['bag'])
    plant_log = live_run['logs']['rotor_plant']
    published = int(plant_log.split('run complete: ')[1].split()[0])
    for topic in ('/rotor/blade_flap', '/rotor/blade_pitch', '/rotor/azimuth'):
        assert len(decoded[topic]) == published, topic
    for topic in ('/rotor_id/estimate', '/rotor_id/progress', '/rotor_id/state',
                  '/rotor/stirring'):
        assert decoded.get(topic), f'{topic} missing from the bag'
    estimate = decoded['/rotor_id/estimate'][-1]
    assert list(estimate.names) == ['A', 'AL_over_tau', 'inv_tau']
    assert len(estimate.covariance) == 9


def test_estimates_are_stamped_with_their_data_time(live_run):
    # pins #35: header.stamp = the window's end, a flap sample of the recording; computed_at,
    # the identifier's clock when it was made, comes after it
    decoded = mcap_messages(live_run['bag'])
    flap_stamps = {_stamp(m) for m in decoded['/rotor/blade_flap']}
    final = live_run['watcher'].final_estimate()
    assert _stamp(final) == (final.window_end.sec, final.window_end.nanosec)
    assert _stamp(final) in flap_stamps
    for estimate in decoded['/rotor_id/estimate']:
        assert _stamp(estimate) in flap_stamps
        delay = ((estimate.computed_at.sec - estimate.header.stamp.sec)
                 + (estimate.computed_at.nanosec - estimate.header.stamp.nanosec) * 1e-9)
        assert 0 < delay < 60, delay


def test_offline_identification_of_the_bag_agrees(live_run):
    from rotor_id.io.bag import read_record
    from rotor_id.pipeline import identify
    record = read_record(live_run['bag'])
    offline = identify(record, live_run['description']).as_json()['parameters']
    final = live_run['watcher'].final_estimate()
    for name, value, std in zip(final.names, final.values, final.std):
        assert abs(value - offline[name]['value']) < 0.2 * std, name


def test_every_node_exits_cleanly(live_run):
    assert live_run['codes'] == dict.fromkeys(live_run['codes'], 0), live_run['exits']
    for name, log in live_run['logs'].items():
        assert 'Traceback' not in log, f'{name}:\n{log}'
