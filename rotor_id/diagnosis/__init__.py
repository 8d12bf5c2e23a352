"""
Model-mismatch diagnosis: locate, explain and prove what a model leaves out.

``diagnose(record, description)`` (:mod:`.diagnose`) is the library entry; ``rotor-id diagnose``
is its command. The search (:mod:`.selection`) sees output error (:mod:`.catalogue`) and filter
error (:mod:`.noisy`) through one interface (:mod:`.likelihood`); :mod:`.verdict` judges,
:mod:`.result` is the typed result, :mod:`.policy` holds every threshold with its reason, and
:mod:`.proposal` proposes an out-of-catalogue term. The catalogue's physics lives in
:mod:`rotor_id.physics.augmented`; the rules are stated in docs/diagnosis.md.
"""

from rotor_id.diagnosis.catalogue import EFFECTS, EQUIVALENT
from rotor_id.diagnosis.diagnose import diagnose
from rotor_id.diagnosis.policy import SelectionPolicy
from rotor_id.diagnosis.result import Diagnosis

__all__ = ['Diagnosis', 'EFFECTS', 'EQUIVALENT', 'SelectionPolicy', 'diagnose']
