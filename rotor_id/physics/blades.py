"""
Per-blade flap angles from the state of any library model (what a flap sensor on blade k sees).

The model owns the transform (:meth:`~rotor_id.physics.models.RotorModel.blade_flap_matrix`,
docs/models.md §8): β_k = β0 + Σ_h (β_hc cos hψ_k + β_hs sin hψ_k) + (−1)^k βd.

* a multiblade model carries the coordinates its inputs drive (the report's constant model drops
  βd, which decouples);
* the report's wake model carries the tilt modes βI, βII only: coning and λ0 decouple at μ = 0
  (docs/models.md §3.1), so a constant ``coning`` (rad) is added to every blade. Eq. 30's outputs
  (β1 − β3)/2 and (β2 − β4)/2 do not see it;
* ``single_blade`` models one blade: a rotor of N such blades is N states, one per blade
  (see :func:`blade_flap_from_states`).
"""

from typing import Sequence, TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from rotor_id.physics.models import RotorModel


def blade_flap_from_multiblade_state(model: 'RotorModel', t: npt.ArrayLike, x: npt.ArrayLike,
                                     coning: float = 0.0) -> np.ndarray:
    """Per-blade flap (T, N) of a multiblade model's state ``x`` (T, n) at times ``t``."""
    if getattr(model, 'blade', 1) is not None or not hasattr(model, 'blade_flap_matrix'):
        raise ValueError(f'model {model.name!r} has no multiblade state')
    x = np.atleast_2d(np.asarray(x, dtype=float))
    flap = np.einsum('tkn,tn->tk', model.blade_flap_matrix(t), x)
    if 'beta_0' not in model.state_names:
        flap = flap + coning
    return flap


def blade_flap_from_states(models: Sequence['RotorModel'], t: npt.ArrayLike,
                           states: Sequence[npt.ArrayLike], coning: float = 0.0) -> np.ndarray:
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
        Constant coning added by models without a β0 state (the report's wake model).

    """
    if len(models) == 1 and models[0].name != 'single_blade':
        return blade_flap_from_multiblade_state(models[0], t, states[0], coning)
    if any(m.name != 'single_blade' for m in models):
        raise ValueError('a rotor of several models must be single_blade models, one per blade')
    return np.column_stack([np.asarray(x, dtype=float)[:, 0] for x in states])
