"""Recordings of stirring sweeps made with the package's simulator, for the frequency tests."""

import math

import numpy as np
from rotor_id.estimation.simulate import simulate
from rotor_id.excitation import StirringTestPoint
from rotor_id.io.record import Record
from rotor_id.physics.blades import blade_flap_from_multiblade_state
from rotor_id.physics.stirring import blade_pitch_from_multiblade, StirringSchedule

OMEGA = 94.24777960769379          # rad/s (15 rev/s)
COLLECTIVE = math.radians(2.0)
CYCLIC = math.radians(1.5)


def sweep_record(model, p, omegadot, t_end, stirring, dt=0.1, noise=0.0, seed=0, t0=20.0,
                 ramp_s=0.05, n_blades=4):
    """
    Return a Record of ``model`` at ``p`` under one stirring test point as a rig runs it.

    Trim, the lateral cyclic stepped on at t = 5, stirring from ``t0`` with ``omegadot`` for
    ``stirring`` rad of azimuth, the cyclic ramped back to trim over ``ramp_s``, then trim until
    ``t_end``. White per-blade flap noise σ = ``noise`` rad (seeded).
    """
    schedule = StirringSchedule(collective=COLLECTIVE, amplitude=CYCLIC, omegadot=omegadot,
                                t0=t0, t_step=5.0)
    point = StirringTestPoint(schedule, OMEGA, duration_rad=stirring,
                              max_stirring_rate_rad_s=1e9, ramp_s=ramp_s,
                              max_amplitude_rad=0.1)
    t = np.arange(0.0, t_end + 0.5 * dt, dt)
    if model.time_invariant:
        x0 = model.equilibrium(t[:1], p, point.inputs(t[:1]))
    else:
        x0 = model.trim_state(p, COLLECTIVE)
    x = simulate(model, p, point.inputs, t, x0).x
    flap = blade_flap_from_multiblade_state(model, t, x)
    if noise:
        flap = flap + noise * np.random.default_rng(seed).standard_normal(flap.shape)
    pitch = blade_pitch_from_multiblade(t, point.inputs(t), n_blades)
    return Record(time_s=t / OMEGA, t=t, rotor_speed_rad_s=np.full(t.size, OMEGA),
                  blade_flap=flap, blade_pitch=pitch,
                  blade_names=[f'blade_{k}' for k in range(1, n_blades + 1)],
                  source='frequency_helpers.sweep_record')
