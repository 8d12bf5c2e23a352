"""
Model-mismatch diagnosis of one recording: fit, locate, explain, judge, show.

1. Fit the run description's model (:func:`rotor_id.pipeline.identify`, output-error ML).
2. Locate (:mod:`rotor_id.residuals`): per channel RMS against a model-free noise floor,
   whiteness, correlation with the pitch input, spectrum per rev, energy over time.
3. Explain (:mod:`rotor_id.diagnosis.selection`): explanations (sets of catalogue effects) are
   searched by score tests and fits, output error or filter error alike
   (:mod:`rotor_id.diagnosis.likelihood`), each with a posterior probability.
4. Judge (:mod:`rotor_id.diagnosis.verdict`): the most probable explanation, its probability,
   the effects the record cannot tell apart, the detection limits of the others; ``unexplained``
   when its residuals are not noise.
5. Show: :class:`rotor_id.diagnosis.result.Diagnosis` (JSON, text) and
   :mod:`rotor_id.commands.diagnose_figures`. The rules are stated in docs/diagnosis.md.
"""

from dataclasses import dataclass
import math
import time

import numpy as np

from rotor_id import residuals as rs
from rotor_id.diagnosis.catalogue import applicable, EFFECTS, NOISE, record_step, Setting
from rotor_id.diagnosis.likelihood import FilterError, ModelSpace, OutputError
from rotor_id.diagnosis.policy import DEFAULT_POLICY
from rotor_id.diagnosis.result import Diagnosis
from rotor_id.diagnosis.selection import Prior, search
from rotor_id.diagnosis.verdict import explain
from rotor_id.estimation import kernels
from rotor_id.estimation.simulate import simulate
from rotor_id.estimation.term_search import propose, summary_line
from rotor_id.estimation.workers import Workers
from rotor_id.physics.augmented import BladeView
from rotor_id.physics.multiblade import coordinate_names, multiblade_from_blade_matrix
from rotor_id.pipeline import identify


@dataclass
class Channel:
    """A residual series of the baseline fit, with its noise floor."""

    name: str
    residual: np.ndarray
    measured: np.ndarray
    fitted: np.ndarray
    floor: float
    n_blades: int
    model_channel: bool


def baseline_channels(ident, part, blade_sigma):
    """
    Return the residual channels of the baseline.

    The model's own, plus the multiblade coordinates it predicts and, when it predicts all
    four, each blade.
    """
    est = ident.estimate
    channels = []
    runs = ident.experiments
    for r, exp in enumerate(runs):
        view = BladeView(exp.model)
        floors = rs.channel_floor(view.channels(exp.t),
                                  blade_sigma[[b - 1 for b in view.blades]])
        for j, name in enumerate(exp.model.output_names):
            label = name if len(runs) == 1 or name.startswith('beta_') else f'{name}[{exp.name}]'
            channels.append(Channel(label, est.residuals[r][:, j], exp.y[:, j],
                                    est.fitted[r][:, j], float(floors[j]),
                                    len(view.blades), True))
    model = ident.model
    if model.name == 'single_blade':
        return channels
    exp = runs[0]
    p = np.array([est.model_parameters[n] for n in model.parameter_names])
    sim = simulate(model, p, exp.inputs, exp.t, est.initial_states[0])
    view = BladeView(model)
    pred_blades = np.einsum('tkn,tn->tk', view.flap(exp.t), sim.x)
    meas_blades = part.blade_flap
    n_blades = model.rotor.n_blades
    coordinates = coordinate_names(n_blades)
    to_mbc = multiblade_from_blade_matrix(exp.t, n_blades)         # the one transform, any N
    pred_mbc = np.einsum('tij,tj->ti', to_mbc, pred_blades)
    meas_mbc = np.einsum('tij,tj->ti', to_mbc, meas_blades)
    predicted = [s for s in coordinates if s in model.state_names]
    have = {c.name for c in channels}
    for i, name in enumerate(coordinates):
        if name in predicted and name not in have:
            floor = rs.channel_floor(to_mbc[:, i:i + 1, :], blade_sigma)[0]
            channels.append(Channel(name, meas_mbc[:, i] - pred_mbc[:, i], meas_mbc[:, i],
                                    pred_mbc[:, i], float(floor), n_blades, False))
    if len(predicted) == n_blades:
        for k in range(n_blades):
            name = f'beta_{k + 1}'
            if name not in have:
                channels.append(Channel(name, meas_blades[:, k] - pred_blades[:, k],
                                        meas_blades[:, k], pred_blades[:, k],
                                        float(blade_sigma[k]), 1, False))
    return channels


def _location(base, mismatch):
    """Return where the baseline's misfit is: flagged channels, band per rev, time window."""
    channels, t, part = base.channels, base.t, base.part
    flagged = [c for c, s in zip(channels, base.stats) if s.flagged(len(base.stats))]
    if not flagged and mismatch:
        order = sorted(zip(channels, base.stats), key=lambda cs: -cs[1].z_excess)
        flagged = [c for c, s in order if s.z_excess > 2.0][:4] or [order[0][0]]
    use = flagged or [c for c in channels if c.model_channel]
    dt = float(np.median(np.diff(t)))
    band = rs.band_of_excess([c.residual for c in use], [c.floor for c in use], dt)
    t0, t1 = rs.span_of_excess([c.residual for c in use], [c.floor for c in use], t)
    window_s = [float(np.interp(t0, part.t, part.time_s)),
                float(np.interp(t1, part.t, part.time_s))]
    return {'channels': [c.name for c in flagged], 'band_per_rev': [band[0], band[1]],
            'window_s': window_s}


@dataclass
class Baseline:
    """The baseline fit's residual channels, their statistics and the data they came from."""

    ident: object
    part: object
    blade_sigma: np.ndarray
    channels: list
    stats: list
    t: np.ndarray
    u: np.ndarray

    @property
    def model_stats(self):
        """Return the statistics of the model's own channels."""
        return [s for s, c in zip(self.stats, self.channels) if c.model_channel]

    @property
    def floors(self):
        """Return the noise floor of each model channel."""
        return [c.floor for c in self.channels if c.model_channel]


def _overall(values):
    return float(math.sqrt(np.mean(np.square(values))))


def _residual_matrix(est):
    """Return the residuals of an estimate as (T, channels) (several runs: a column each)."""
    if len(est.residuals) > 1:
        return np.column_stack([r[:, 0] for r in est.residuals])
    return est.residuals[0]


def residual_stats(result, base):
    """Return the channel statistics of a fitted explanation's residuals (model channels)."""
    res = _residual_matrix(result.estimate)
    names = [c.name for c in base.channels if c.model_channel]
    return [rs.channel_stats(n, res[:, j], base.floors[j], base.u,
                             base.channels[j].n_blades, base.t) for j, n in enumerate(names)]


def residuals_are_noise(result, base, policy):
    """
    Return whether a fit's residuals are noise at the policy's levels.

    Output error: white (Ljung-Box, Bonferroni over channels, p above the level) and no
    channel's RMS above its floor by the policy's z. Filter error: the innovations white (a
    filter's one-step prediction error is above the floor by the process noise).
    """
    stats = residual_stats(result, base)
    white = rs.combined_whiteness_p(stats) > policy.adequacy_level
    if result.likelihood != 'output error':
        return bool(white)
    return bool(white and max(s.z_excess for s in stats) < policy.adequacy_excess_z)


def misfit_removed(result, base):
    """Return the share of the baseline's mean square above the floor that a fit removes."""
    res = _residual_matrix(result.estimate)
    floors2 = np.square(base.floors)
    before = sum(s.rms**2 / f2 - 1.0 for s, f2 in zip(base.model_stats, floors2))
    after = sum(float(np.mean(res[:, j]**2)) / f2 - 1.0 for j, f2 in enumerate(floors2))
    return float((before - after) / before) if before > 0.0 else 0.0


def _baseline(record, description, window_s, say, policy):
    def base_progress(info):
        rms = math.sqrt(float(np.mean(np.square(info['noise_std']))))
        say(f'baseline: iteration {info["iteration"]}, residual RMS {rms:.5g} rad')
    # converged as every explanation of the table is (the policy's fit tolerance: its log L
    # within a few hundredths of the optimum); the residuals are judged here (channel
    # statistics, :func:`residuals_are_noise`), so the identification's own adequacy check
    # would be computed and never read
    ident = identify(record, description, progress=base_progress, window_s=window_s,
                     step_tol=policy.fit_tolerance, check_adequacy=False)
    part = record.window(*window_s)
    blade_sigma = rs.blade_noise_floor(part.blade_flap)
    exp0 = ident.experiments[0]
    u = exp0.inputs(exp0.t)
    channels = baseline_channels(ident, part, blade_sigma)
    stats = [rs.channel_stats(c.name, c.residual, c.floor, u, c.n_blades, exp0.t)
             for c in channels]
    return Baseline(ident, part, blade_sigma, channels, stats, exp0.t, u)


def _space(record, base, effects, workers, verbose, policy):
    """Return the model space (output error, filter error) and the effects it may use."""
    ident = base.ident
    est = ident.estimate
    unknowns = list(ident.unknowns)
    setting = Setting.of(record, ident, verbose=verbose, fit_tolerance=policy.fit_tolerance,
                         max_step=record_step(ident, policy.integration_error))
    n_obs = sum(e.t.size * e.model.n_outputs for e in ident.experiments)
    not_tried = {e: applicable(e, ident.model.name, ident.model.rotor, unknowns)
                 for e in effects if e != NOISE}
    usable = [e for e in effects if e != NOISE and not not_tried[e]]
    noise, pool = None, Workers(workers)
    if NOISE in effects:
        noise = FilterError(setting, n_obs, est.names, pool)
        usable.append(NOISE)
    space = ModelSpace(OutputError(setting, ident, n_obs, pool), noise, usable)
    return space, usable, {e: why for e, why in not_tried.items() if why}


def _parameters(ident, chosen):
    """Return the run's unknowns, baseline and corrected (the verdict's model) ± σ."""
    est = ident.estimate
    out = {}
    for n in ident.unknowns:
        entry = {'baseline_value': est.value(n), 'baseline_std': est.std_of(n)}
        if chosen is not None and n in chosen.estimate.names:
            entry.update(value=chosen.estimate.value(n), std=chosen.estimate.std_of(n))
        else:
            entry.update(value=entry['baseline_value'], std=entry['baseline_std'])
        out[n] = entry
    return out


def _fit_block(base, stats_aug):
    model_stats = base.model_stats
    return {
        'noise_floor': _overall([s.floor for s in model_stats]),
        'baseline_rms': _overall([s.rms for s in model_stats]),
        'augmented_rms': _overall([s.rms for s in stats_aug]),
        'whiteness_p_baseline': rs.combined_whiteness_p(model_stats),
        'whiteness_p_augmented': rs.combined_whiteness_p(stats_aug),
        'channels': [s.name for s in model_stats],
        'noise_floor_per_channel': [s.floor for s in model_stats],
        'baseline_rms_per_channel': [s.rms for s in model_stats],
        'augmented_rms_per_channel': [s.rms for s in stats_aug],
    }


def _proposal(explanation, base, say, started=None):
    """
    Return the equation-error proposal of an out-of-catalogue verdict (or random inflow).

    ``started``: the proposal submitted to the workers while the search went on.
    """
    if explanation.effect != 'unexplained' and explanation.names != (NOISE,):
        if started is not None:
            started.cancel()
        return None
    say('proposal: stepwise regression of the equation error on a library of flap-equation '
        'terms, validated on held-out time blocks')
    proposal = started() if started is not None else propose(base.ident)
    say(summary_line(proposal.as_json()))
    return proposal


def _path(selection, chosen):
    """Return the fits along the search to the verdict's model: [(effect added, FitResult)]."""
    if chosen is None:
        return []
    path = []
    for step in selection.steps:
        cand = selection.candidates.get(step.effects)
        if step.action == 'add' and set(step.effects) <= set(chosen.effects) \
                and cand is not None and cand.fitted:
            path.append((step.effect, cand.result))
    if not path or path[-1][1].effects != chosen.effects:
        path = [(' + '.join(chosen.names), chosen)]
    return path


def diagnose(record, description, progress=None, workers=2, effects=EFFECTS, window_s=None,
             verbose_fits=False, policy=DEFAULT_POLICY):
    """
    Diagnose the mismatch between a recording (rad, s) and the run description's model.

    ``progress`` is called with one line of text per step; ``workers``: processes for the
    candidate fits (1: all in this process); ``effects``: the catalogue ids to try;
    ``window_s`` overrides the description's window; ``verbose_fits``: the workers print every
    Gauss-Newton iteration to stderr; ``policy``: the selection's and the verdict's thresholds.
    """
    t_start = time.perf_counter()
    window_s = tuple(window_s or description.window_s)

    def say(text):
        if progress is not None:
            progress(f'{text} ({time.perf_counter() - t_start:.1f} s)')
    say(f'baseline: fitting {description.model} ({", ".join(description.unknowns)})')
    kernels.prefer()                # every candidate simulates: the compiled path from the start
    base = _baseline(record, description, window_s, say, policy)
    space, usable, not_tried = _space(record, base, effects, workers, verbose_fits, policy)
    mu = base.ident.model.rotor.advance_ratio
    prior = Prior(usable, policy.max_effects, record.n_blades, mu)

    def adequate(result):
        return residuals_are_noise(result, base, policy)
    started = {}

    def on_fit(explanations):
        # random inflow alone, if the verdict, asks for the proposal (below): from its fit on
        # the proposal fills a worker that the search leaves idle (given up if not asked for)
        if ((NOISE, ''),) in explanations and not started:
            started['proposal'] = space.output_error.workers.submit(propose, base.ident,
                                                                    filler=True)
    try:
        selection = search(space, usable, prior, policy, mu, say, adequate, on_fit)
        explanation, top, table = explain(space, selection, prior, policy, adequate,
                                          lambda r: misfit_removed(r, base))
        proposal = _proposal(explanation, base, say, started.get('proposal'))
    except BaseException:
        # (Ctrl-C among them: the workers were interrupted too) stopped, not waited for
        space.output_error.workers.close(stop=True)
        raise
    space.output_error.workers.close()
    if proposal is not None and proposal.terms and explanation.names == (NOISE,):
        # a deterministic term that predicts held-out blocks is not random inflow: a filter
        # tracks any unmodelled dynamics, so the verdict is out of catalogue
        explanation.effect, explanation.confidence = 'unexplained', 'low'
        explanation.reason = (f'random inflow alone, and a deterministic term '
                              f'({proposal.terms[0]["term"]}) predicts held-out blocks')
        explanation.effects = []
    chosen = top.result if top.effects else None
    stats_aug = residual_stats(chosen, base) if chosen is not None else base.model_stats
    mismatch = explanation.effect != 'none'
    location = _location(base, mismatch)
    elapsed = time.perf_counter() - t_start
    say(f'diagnosis: {explanation.effect} ({explanation.confidence} confidence, '
        f'p = {explanation.probability:.3f})')
    return Diagnosis(mismatch=mismatch, explanation=explanation, location=location,
                     fit=_fit_block(base, stats_aug), candidates=table,
                     parameters=_parameters(base.ident, chosen), baseline=base.ident,
                     chosen=chosen, channels=base.channels, stats_baseline=base.stats,
                     stats_augmented=stats_aug, blade_floor=base.blade_sigma,
                     record_window=base.part, elapsed_s=elapsed, steps=selection.steps,
                     path=_path(selection, chosen),
                     proposal=None if proposal is None else proposal.as_json(), policy=policy,
                     not_tried=not_tried)
