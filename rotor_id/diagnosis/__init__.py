"""
Model-mismatch diagnosis (issue 4): locate, explain and prove what a model leaves out.

``diagnose(record, description)`` is the library entry (also for the identifier node on a
live window: pass ``window_s`` and ``workers=1``); ``rotor-id diagnose`` is its command.

* :mod:`.residuals`: model-free noise floor and residual tests (whiteness, input correlation,
  spectrum per rev, energy over time) that locate a mismatch;
* :mod:`.augmentations`: the catalogue's augmented models (each a LinearModel wrapping the
  baseline, with analytic derivatives);
* :mod:`.catalogue`: building and fitting the candidates, cross-validation;
* :mod:`.diagnose`: the procedure and the choice (autocorrelation-corrected BIC + validation);
* :mod:`.figures`: the report's figures.
"""

from rotor_id.diagnosis.catalogue import EFFECTS, EQUIVALENT
from rotor_id.diagnosis.diagnose import diagnose, Diagnosis

__all__ = ['Diagnosis', 'EFFECTS', 'EQUIVALENT', 'diagnose']
