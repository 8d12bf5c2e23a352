"""
The typed result of a diagnosis; the text report, the JSON and the figures render from it.

:class:`Diagnosis` holds the verdict (:class:`Explanation`: the named :class:`Effect` s, the
probability, the alternatives, the detection limits), where the mismatch is (location), the
fits and the moves of the search (:class:`rotor_id.diagnosis.selection.Step`).
"""

from dataclasses import asdict, dataclass, field
import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from rotor_id.diagnosis.likelihood import FitResult
    from rotor_id.diagnosis.policy import SelectionPolicy
    from rotor_id.io.record import Record
    from rotor_id.pipeline import Identification


@dataclass
class Share:
    """An effect that can stand in for a named one, with its share of their probability."""

    effect: str
    share: float


@dataclass
class Effect:
    """One named effect: its parameters ± σ, inclusion probability, what it adds."""

    effect: str
    variant: str
    #: {name: (value, Cramér-Rao σ)} as the augmentation reports them
    parameters: dict
    #: posterior probability that an explanation with this effect is the right one
    inclusion_probability: float
    #: 2Δlog L of the verdict's model against the model without this effect (None: not fitted)
    two_delta_loglik: float = None
    #: effects the record cannot tell from this one, each with its share (this one's first)
    shares: list = field(default_factory=list)
    #: the fit's parameters at a limit of their range (still compared on its likelihood)
    at_bound: list = field(default_factory=list)

    def as_json(self):
        """Return the entry of ``explanation.effects``."""
        return {'effect': self.effect, 'variant': self.variant,
                'parameters': {n: {'value': float(v), 'std': float(s)}
                               for n, (v, s) in self.parameters.items()},
                'inclusion_probability': float(self.inclusion_probability),
                'two_delta_loglik': self.two_delta_loglik,
                'shares': [asdict(s) for s in self.shares],
                'confounded_with': [s.effect for s in self.shares if s.effect != self.effect],
                'at_bound': list(self.at_bound)}


@dataclass
class Alternative:
    """One explanation of the table with its posterior probability."""

    effects: tuple
    probability: float
    #: fitted (else approximated by its score test at the model it extends)
    fitted: bool
    #: 2Δlog L against the baseline, parameters beyond it, likelihood used
    two_delta_loglik: float
    n_params: int
    likelihood: str = ''
    #: share of the baseline's misfit above the noise floor that this explanation removes
    misfit_explained: float = None
    #: the terms of its evidence besides 2Δlog L and n_params: log prior, observations n
    #: and the autocorrelation factor ρ (log evidence = ρ log L − k/2 log(nρ) + log prior),
    #: so that a verdict rule can be re-evaluated on a recorded table
    log_prior: float = math.nan
    n_obs: int = 0
    rho: float = math.nan

    def as_json(self):
        """Return an entry of ``explanation.alternatives`` / ``candidates``."""
        return {'effects': list(self.effects), 'probability': float(self.probability),
                'fitted': self.fitted, 'two_delta_loglik': float(self.two_delta_loglik),
                'n_params': int(self.n_params), 'likelihood': self.likelihood,
                'misfit_explained': self.misfit_explained,
                'log_prior': float(self.log_prior), 'n_obs': int(self.n_obs),
                'rho': float(self.rho)}


@dataclass
class DetectionLimit:
    """The size of an un-named effect that this record would have revealed."""

    effect: str
    #: {parameter: smallest |value| detected with the policy's power}; empty when not nested,
    #: infinite (JSON null) along a direction this record does not inform
    limits: dict
    #: the noncentrality (expected 2Δlog L) at that size, and the score statistic here
    noncentrality: float
    score_statistic: float
    how: str

    def as_json(self):
        """Return an entry of ``explanation.detection_limits``."""
        return {'effect': self.effect,
                'limits': {n: float(v) if math.isfinite(v) else None
                           for n, v in self.limits.items()},
                'noncentrality': float(self.noncentrality),
                'score_statistic': float(self.score_statistic), 'how': self.how}


@dataclass
class Explanation:
    """The verdict: named effects, probability, alternatives and what the record excludes."""

    #: the main effect id, or 'none' / 'unexplained'
    effect: str
    confidence: str
    #: posterior probability of the verdict's explanation (of 'none' for none)
    probability: float
    effects: list
    alternatives: list
    detection_limits: list
    #: the verdict's model leaves residuals that are noise (whiteness, RMS at the floor)
    residuals_are_noise: bool
    #: why not a catalogue name (unexplained), else ''
    reason: str = ''

    @property
    def names(self):
        """Return the named effect ids."""
        return tuple(e.effect for e in self.effects)

    def as_json(self):
        """Return ``explanation`` of the JSON (without the proposal)."""
        main = next((e for e in self.effects if e.effect == self.effect), None)
        return {'effect': self.effect, 'confidence': self.confidence,
                'probability': float(self.probability),
                'parameters': {} if main is None else main.as_json()['parameters'],
                'effects': [e.as_json() for e in self.effects],
                'alternatives': [a.as_json() for a in self.alternatives],
                'detection_limits': {d.effect: d.as_json() for d in self.detection_limits},
                'residuals_are_noise': bool(self.residuals_are_noise),
                'reason': self.reason}


@dataclass
class Diagnosis:
    """Everything the diagnosis found; :meth:`as_json` is the command's JSON."""

    mismatch: bool
    explanation: Explanation
    location: dict
    fit: dict
    #: every explanation fitted or score-tested, with its probability
    candidates: list
    #: the run's unknowns: baseline and corrected values ± σ
    parameters: dict
    baseline: 'Identification'
    #: the verdict's fitted model (a FitResult; None: the baseline)
    chosen: 'FitResult | None'
    channels: list
    stats_baseline: list
    stats_augmented: list
    blade_floor: np.ndarray
    record_window: 'Record'
    elapsed_s: float
    steps: list = field(default_factory=list)
    #: the fits along the search to the verdict's model: [(effect added, FitResult)]
    path: list = field(default_factory=list)
    proposal: dict = None
    policy: 'SelectionPolicy | None' = None
    #: catalogue effects not tried on this record, and why
    not_tried: dict = field(default_factory=dict)

    @property
    def effect(self):
        """Return the verdict's main effect id."""
        return self.explanation.effect

    @property
    def confidence(self):
        """Return 'high' or 'low'."""
        return self.explanation.confidence

    def as_json(self):
        """JSON of ``rotor-id diagnose``."""
        explanation = self.explanation.as_json()
        if self.proposal is not None:
            explanation['proposal'] = self.proposal
        est = self.baseline.estimate
        return {
            'mismatch': bool(self.mismatch),
            'location': self.location,
            'explanation': explanation,
            'fit': self.fit,
            'candidates': [c.as_json() for c in self.candidates],
            'parameters': self.parameters,
            'baseline': {'model': self.baseline.model.name,
                         'unknowns': list(self.baseline.unknowns),
                         'window_s': [float(v) for v in self.baseline.window_s],
                         'neg_log_likelihood': float(est.neg_log_likelihood)},
            'channels_baseline': [s.as_dict() for s in self.stats_baseline],
            'channels_augmented': [s.as_dict() for s in self.stats_augmented],
            'noise_floor_blades_rad': [float(s) for s in self.blade_floor],
            'steps': [asdict(s) for s in self.steps],
            'not_tried': dict(self.not_tried),
            'policy': asdict(self.policy) if self.policy is not None else {},
            'criterion': {'name': 'posterior probability: BIC evidence with the '
                                  'autocorrelation-corrected sample size, prior uniform over '
                                  'sizes then sets',
                          'high_confidence': (self.policy.high_confidence
                                              if self.policy is not None else math.nan)},
            'elapsed_s': float(self.elapsed_s),
        }
