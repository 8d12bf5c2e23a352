"""
Per-blade flap angles from the state of any library model (what a flap sensor on blade k sees).

MODELS.md §0:  β_k = β0 + βI cos ψ_k + βII sin ψ_k + (−1)^k βd,   ψ_k = t + (k − 1)·2π/N.

* ``multiblade`` (8 states) carries all four coordinates;
* ``multiblade_constant`` carries β0, βI, βII (βd decouples and is dropped, MODELS.md §2.2);
* ``multiblade_wake`` carries the tilt modes βI, βII only: coning and λ0 decouple at μ = 0
  (MODELS.md §3.1), so a constant ``coning`` (rad) is added to every blade. Eq. 30's outputs
  (β1 − β3)/2 and (β2 − β4)/2 do not see it;
* ``single_blade`` models one blade: a rotor of N such blades is N states, one per blade
  (see :func:`blade_flap_from_states`).
"""

import numpy as np

from rotor_id.physics.multiblade import blade_values

#: Index of β0, βI, βII, βd in each multiblade model's state (None: not a state of the model).
_COORDINATES = {
    'multiblade': (0, 1, 2, 3),
    'multiblade_constant': (0, 1, 2, None),
    'multiblade_wake': (None, 0, 2, None),
}


def blade_flap_from_multiblade_state(model, t, x, coning=0.0):
    """Per-blade flap (T, N) of a multiblade model's state ``x`` (T, n) at times ``t``."""
    if model.name not in _COORDINATES:
        raise ValueError(f'model {model.name!r} has no multiblade state; '
                         f'use one of {", ".join(_COORDINATES)}')
    x = np.atleast_2d(np.asarray(x, dtype=float))
    i0, i_cos, i_sin, i_d = _COORDINATES[model.name]
    coords = {'collective': np.full(len(x), coning) if i0 is None else x[:, i0],
              'cos': x[:, i_cos], 'sin': x[:, i_sin]}
    if i_d is not None:
        coords['differential'] = x[:, i_d]
    return blade_values(coords, t, model.rotor.n_blades)


def blade_flap_from_states(models, t, states, coning=0.0):
    """
    Per-blade flap (T, N) from one multiblade model or N single-blade models.

    Parameters
    ----------
    models : list of LinearModel
        One multiblade model, or one ``single_blade`` model per blade (blade 1 first).
    t : array_like, shape (T,)
        Nondimensional times of the states.
    states : list of ndarray, shape (T, n) each
        The state history of each model.
    coning : float
        Constant coning added by models without a β0 state (the wake model).

    """
    if len(models) == 1 and models[0].name != 'single_blade':
        return blade_flap_from_multiblade_state(models[0], t, states[0], coning)
    if any(m.name != 'single_blade' for m in models):
        raise ValueError('a rotor of several models must be single_blade models, one per blade')
    return np.column_stack([np.asarray(x, dtype=float)[:, 0] for x in states])
