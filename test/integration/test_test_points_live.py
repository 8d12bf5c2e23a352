"""
Three test points in a row through the running nodes, without restarting the identifier.

Plant, stirring input, identifier (its fits in a separate process) and recorder run as separate
processes on the wake case; the stirring input runs three schedules, each on its ``~/start``
(the next once the last one is done; or by a restart of a stirring input without that service),
and the identifier arms a test point on each (StirringCommand phase
TRIM). What
it proves: each test point gets exactly one final estimate, tagged with its number; it is
converged exactly when its window is complete (every sample of every channel received: the
identifier's sensor subscriptions are best effort, and a machine starved of CPU drops samples in
DDS, bench/results/live_latency.md) and then within a Bonferroni bound of the plant's truth
(live_helpers.within_sigma), and at least two of
the three are; its window lies inside its own test point and the windows do not overlap;
identified offline from the recorded bag over the same stamps, each converged one agrees with
the live result to 0.2σ (the live fit used exactly that window's data, nothing of another test
point); every node exits with 0. (The state estimator adopting results: test_live_system.py.)
The multi-point bag is also identified per test point by ``rotor-id identify BAG --test-point all``
(test points found from the recorded stirring phases): each starts at the live test point's first
flap sample and agrees with its live final estimate to 0.2σ where the live window was complete.
On a machine with no CPU to spare for the nodes (its cores 90 % busy over the run, or 1-minute
load above 4 per core: live_helpers.starved) the identifier can fall tens of seconds behind,
the publishers' history no longer holds what it missed, and test points 2 and 3 come out
STATUS_INCOMPLETE, as they must (a test point whose first flap sample was lost starts at a later
one: offline, from the bag, it starts earlier). There every invariant above is still asserted
(one final each, tagged, converged exactly when complete, no window of another test point, a
growing-window estimate before each complete final, offline agreement of the complete ones),
but not that two converge: that is asserted only where the nodes had CPU to spare, and the
load and busy share measured are in the failure text and in a warning when the requirement was
not applied.
A stirring input starved of CPU ramps the cyclic to trim when its azimuth goes stale
(``azimuth_timeout_s``): a test point whose excitation so ended inside its window is
STATUS_ABORTED, without values, and the recorded stirring commands must show that ramp.
"""

import json
import os
import time
import warnings

from live_helpers import CpuUse, domain_id, require_workspace, RosClient, starved, within_sigma
import pytest

pytestmark = pytest.mark.slow
TRUTH = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}
NS = 1_000_000_000
POINTS = 3


def _call_until_accepted(watcher, client, timeout=60.0):
    """Call a Trigger service until it succeeds (the stirring refuses while a schedule runs)."""
    from std_srvs.srv import Trigger
    clock = time.monotonic()
    while time.monotonic() - clock < timeout:
        if not client.wait_for_service(timeout_sec=1.0):
            continue
        future = client.call_async(Trigger.Request())
        if watcher.spin_until(future.done, 10.0) and future.result().success:
            return True
        watcher.spin_until(lambda: False, 0.3)
    return False


def _ns(stamp):
    return stamp.sec * NS + stamp.nanosec


@pytest.fixture(scope='module')
def three_points(tmp_path_factory):
    """Run three test points; return the estimates, the bag and the exit codes."""
    require_workspace()
    from rotor_id.commands.demo import case_files
    from rotor_id.io.run_description import load_run_description
    from rotor_id.nodes.processes import isolated_env, NodeProcesses
    from rotor_id.nodes.watch import RESULT_KINDS, RunWatcher
    from std_srvs.srv import Trigger

    params_file, description_path, _ = case_files('wake')
    tmp = tmp_path_factory.mktemp('points')
    domain = domain_id()
    ros = RosClient(domain)
    watcher = RunWatcher(ros.node)
    procs = NodeProcesses(isolated_env(domain, tmp / 'ros_log'), tmp / 'logs')
    run = {'bag': tmp / 'bag', 'watcher': watcher, 'config': description_path,
           'description': load_run_description(description_path), 'load': os.getloadavg()[0]}
    cpu = CpuUse()
    try:
        procs.start('identifier', params_file, {'target_std': [0.02, 0.02, 0.01]})
        procs.start('recorder', params_file, {'output': str(run['bag'])})
        procs.start('stirring_input', params_file)
        start = ros.node.create_client(Trigger, '/stirring_input/start')
        # a stirring input without ~/start runs one endless schedule: it is restarted for each
        # test point instead, and the rotor holds the last command meanwhile
        restart = not start.wait_for_service(timeout_sec=10.0)
        late = watcher.wait_for_publishers(
            [kind for kind in RESULT_KINDS if kind != 'state'],     # no state estimator here
            60.0, alive=lambda: not procs.dead())
        assert not late, f'no {late} publisher matched; exited: {procs.dead()}'
        procs.start('rotor_plant', params_file, {'duration_s': 300.0, 'seed': 11,
                                                 'wait_for_subscribers': 3,
                                                 'wait_for_commands': not restart})
        for k in range(1, POINTS + 1):
            if k > 1 and restart:
                procs.stop('stirring_input')
                procs.start('stirring_input', params_file)
            elif not restart:     # the stirring node's next schedule, once the last one is done
                assert _call_until_accepted(watcher, start), f'test point {k} never started'
            done = watcher.spin_until(lambda: watcher.final_estimate(k) is not None, 150.0,
                                      alive=lambda: not procs.dead())
            run['load'] = max(run['load'], os.getloadavg()[0])
            assert done, (f'no final estimate of test point {k}; exited: {procs.dead()}\n'
                          + procs.log('identifier')[-4000:])
        run['busy'] = cpu.busy_share()
    finally:
        run['codes'] = procs.stop_all()
        run['exits'] = procs.exit_summary()
        run['logs'] = {name: procs.log(name) for name in procs.procs}
        ros.close()
    return run


def test_each_test_point_is_identified_once(three_points):
    from rotor_id_msgs.msg import ParameterEstimate
    watcher = three_points['watcher']
    finals = [m for m in watcher.messages['estimate'] if m.kind == ParameterEstimate.KIND_FINAL]
    assert [m.test_point for m in finals] == list(range(1, POINTS + 1))
    for final in finals:
        complete = _complete(final)
        assert (final.status == ParameterEstimate.STATUS_CONVERGED) == complete, final.message
        if complete:
            ok, text = within_sigma(final.values, final.std, TRUTH, final.names,
                                    family=POINTS * len(final.names))
            assert ok, f'test point {final.test_point}: {text}'
        elif final.status == ParameterEstimate.STATUS_ABORTED:
            assert _cut_short(three_points, final), final.message
        else:
            assert final.status == ParameterEstimate.STATUS_INCOMPLETE, final.message
    converged = [m for m in finals if m.status == ParameterEstimate.STATUS_CONVERGED]
    load, busy = three_points['load'], three_points.get('busy', 0.0)
    measured = f'load {load:.1f}, CPU {100 * busy:.0f} % busy on {os.cpu_count()} cores'
    if not starved(load, busy):
        assert len(converged) >= 2, f'{measured}: ' + str([m.message for m in finals])
    elif len(converged) < 2:
        warnings.warn(f'{len(converged)} of {POINTS} test points converged at {measured} (no '
                      'CPU to spare: not required); the others were reported incomplete: '
                      + '; '.join(m.message for m in finals if m not in converged))
    # a growing-window estimate precedes every final one whose window was received
    provisional = {m.test_point for m in watcher.messages['estimate']
                   if m.kind == ParameterEstimate.KIND_PROVISIONAL}
    assert {m.test_point for m in finals if _complete(m)} <= provisional <= set(
        range(1, POINTS + 1))


def _complete(final):
    return final.time_base_consistent and not list(final.missing_channels)


def _cut_short(run, final):
    """
    Whether the schedule that armed the test point ramped down or ended before its window's end.

    A schedule starts with PHASE_TRIM after any other phase (or as the first phase seen), as
    the identifier follows it; the test point starts at its first flap sample after that.
    """
    from rotor_id_msgs.msg import StirringCommand
    start = _ns(final.test_point_start)
    phases = [(m.phase, _ns(m.header.stamp)) for m in run['watcher'].messages['stirring']]
    armed = [stamp for i, (phase, stamp) in enumerate(phases) if stamp <= start
             and phase == StirringCommand.PHASE_TRIM
             and (i == 0 or phases[i - 1][0] != StirringCommand.PHASE_TRIM)]
    ends = [stamp for phase, stamp in phases if armed and stamp > armed[-1] and phase in (
        StirringCommand.PHASE_RAMP_DOWN, StirringCommand.PHASE_DONE)]
    return bool(ends) and min(ends) < start + run['description'].window_s[1] * NS


def test_windows_are_their_own_test_points(three_points):
    from rotor_id_msgs.msg import ParameterEstimate
    finals = [three_points['watcher'].final_estimate(k) for k in range(1, POINTS + 1)]
    w0, w1 = three_points['description'].window_s
    for final in finals:
        start = _ns(final.test_point_start)
        assert (final.window_requested_start_s, final.window_requested_end_s) == (w0, w1)
        if _complete(final):          # the samples used are the whole window
            assert start + w0 * NS <= _ns(final.window_start) <= start + w0 * NS + 2e6
            assert start + w1 * NS - 2e6 <= _ns(final.window_end) <= start + w1 * NS
        elif final.status == ParameterEstimate.STATUS_ABORTED:    # its excitation cut short
            assert not list(final.values) and _cut_short(three_points, final), final.message
        elif _ns(final.window_end) == 0:      # not one sample of the window was received
            assert list(final.missing_channels) == ['flap', 'pitch', 'azimuth'], final.message
        else:                         # fewer samples, all inside the window
            assert start + w0 * NS <= _ns(final.window_start) <= _ns(final.window_end) <= (
                start + w1 * NS)
    for before, after in zip(finals, finals[1:]):
        end = _ns(before.test_point_start) + w1 * NS
        assert max(end, _ns(before.window_end)) < _ns(after.test_point_start)
    # every estimate of a test point comes from a window inside that test point
    for msg in three_points['watcher'].messages['estimate']:
        if msg.kind != ParameterEstimate.KIND_ON_DEMAND and _ns(msg.window_end):
            assert _ns(msg.window_start) >= _ns(msg.test_point_start) + w0 * NS


def test_offline_identification_of_each_test_point_agrees(three_points, tmp_path):
    from rotor_id.cli import main
    out = tmp_path / 'points.json'
    code = main(['identify', str(three_points['bag']), '--config', str(three_points['config']),
                 '--test-point', 'all', '--json', str(out), '--quiet'])
    results = {r['test_point']: r for r in json.loads(out.read_text())}
    assert sorted(results) == list(range(1, POINTS + 1)), code
    for k, offline in results.items():
        final = three_points['watcher'].final_estimate(k)
        # found from the recorded stirring phases where the live identifier started it (a
        # starved one may have missed the first flap sample and started later, incomplete)
        assert offline['found_from'].endswith('(stirring phases)')
        if not _complete(final):
            # (an abort before the test point's first flap sample reached the identifier
            # leaves its start unset: 0)
            live_start = _ns(final.test_point_start) or offline['test_point_start_ns']
            assert offline['test_point_start_ns'] <= live_start
            continue                  # the live fit had fewer samples than the bag
        assert offline['test_point_start_ns'] == _ns(final.test_point_start)
        for name, value, std in zip(final.names, final.values, final.std):
            assert abs(value - offline['parameters'][name]['value']) < 0.2 * std, (k, name)


def test_every_node_exits_cleanly(three_points):
    assert three_points['codes'] == dict.fromkeys(three_points['codes'], 0), three_points['exits']
    for name, log in three_points['logs'].items():
        assert 'Traceback' not in log, f'{name}:\n{log}'
