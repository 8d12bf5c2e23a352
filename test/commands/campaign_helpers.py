"""
Small simulated test campaigns: bags and their run descriptions side by side.

Each test point is a planned run of the μ = 0 wake rotor (config/plan_wake.yaml) simulated by
the library's planning path (:func:`rotor_id.planning.simulate_run`, the test-stand convention:
trim, cyclic step, stirring, sensor noise), written as an MCAP bag NAME/ with NAME.yaml beside
it. Used by test_campaign.py and bench/campaign.py.
"""

from dataclasses import replace
import math
from pathlib import Path

import numpy as np
from rotor_id import planning
from rotor_id.io.bag import write_record_bag
import yaml

REPO = Path(__file__).resolve().parents[2]
PLAN = REPO / 'config' / 'plan_wake.yaml'
STAMP0_NS = 1_763_700_000_000_000_000
OMEGADOT = 0.1 / math.pi                  # the report's stirring law constant


def write_test_point(directory, name, direction='progressing', truth=None, noise_deg=0.1,
                     seed=0, duration_rev=2.0, conditions=None, guess=True, custom_data=None,
                     flap_delay_samples=0, flap_bias_rad=None):
    """
    Simulate one test point into ``directory``: bag NAME/ and run description NAME.yaml.

    ``truth`` overrides the plan's parameter values (A, AL_over_tau, inv_tau); ``conditions``
    goes into the run description's ``conditions:``; ``guess`` gives the nominal values as
    ``initial_guess`` (no start-value grid); ``custom_data`` (text values) goes into the bag's
    metadata.yaml as a recorder's ``--custom-data`` would put it. ``flap_delay_samples`` reads
    the flap sensors that many samples late, ``flap_bias_rad`` (one per blade) offsets them:
    physics the model lacks.
    """
    directory = Path(directory)
    plan = planning.load_plan(PLAN)
    plan = replace(plan, noise_std_rad=math.radians(noise_deg),
                   guess={**plan.guess, **(truth or {})})
    sign = -1.0 if direction == 'progressing' else 1.0
    candidate = planning.Candidate(direction=direction, omegadot=sign * OMEGADOT,
                                   amplitude_rad=planning.DEFAULT_AMPLITUDE_RAD, t0=70.0,
                                   duration_rev=duration_rev)
    run = planning.simulate_run(plan, candidate, rng=np.random.default_rng(seed))
    record = replace(run.record, stamp0_ns=STAMP0_NS)
    if flap_delay_samples:
        late = np.roll(record.blade_flap, flap_delay_samples, axis=0)
        late[:flap_delay_samples] = record.blade_flap[0]
        record = replace(record, blade_flap=late)
    if flap_bias_rad is not None:
        record = replace(record, blade_flap=record.blade_flap + np.asarray(flap_bias_rad))
    bag = write_record_bag(directory / name, record)
    if custom_data:
        meta = bag / 'metadata.yaml'
        info = yaml.safe_load(meta.read_text())
        info['rosbag2_bagfile_information']['custom_data'] = dict(custom_data)
        meta.write_text(yaml.safe_dump(info, sort_keys=False))
    data = yaml.safe_load(PLAN.read_text())
    for key in planning.PLAN_KEYS + ('noise_std_rad',):
        data.pop(key, None)
    data['window_s'] = [float(v) for v in candidate.window_s(plan.omega_rad_s)]
    if guess:
        data['initial_guess'] = dict(planning.load_plan(PLAN).guess)
    if conditions:
        data['conditions'] = dict(conditions)
    (directory / f'{name}.yaml').write_text(yaml.safe_dump(data, sort_keys=False))
    return directory / name
