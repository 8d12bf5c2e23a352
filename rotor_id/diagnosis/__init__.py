"""
Model-mismatch diagnosis: locate, explain and prove what a model leaves out.

``diagnose(record, description)`` is the library entry; ``rotor-id diagnose`` is its command.

* :mod:`.catalogue`: building, fitting and score-testing one candidate (output error);
* :mod:`.noisy`: the same with random inflow (filter error);
* :mod:`.likelihood`: both behind one interface (fit → FitResult, score test → ScoreTest);
* :mod:`.selection`: the search and the posterior over explanations;
* :mod:`.policy`: every threshold, with its statistical reason;
* :mod:`.verdict`: probability, shares, detection limits, ``unexplained``;
* :mod:`.result`: the typed result (Diagnosis, Explanation, Effect, ...);
* :mod:`.diagnose`: the procedure (its figures render in
  :mod:`rotor_id.commands.diagnose_figures`);
* :mod:`.proposal`: an out-of-catalogue term proposed from the equation error.

The catalogue's physics, the augmented models (each a LinearModel wrapping the baseline, with
analytic derivatives), lives with the other models in :mod:`rotor_id.physics.augmented`.
The selection and its statistics are stated in docs/diagnosis.md.
"""

from rotor_id.diagnosis.catalogue import EFFECTS, EQUIVALENT
from rotor_id.diagnosis.diagnose import diagnose
from rotor_id.diagnosis.policy import SelectionPolicy
from rotor_id.diagnosis.result import Diagnosis

__all__ = ['Diagnosis', 'EFFECTS', 'EQUIVALENT', 'SelectionPolicy', 'diagnose']
