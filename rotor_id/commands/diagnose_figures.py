"""
Figures of a diagnosis (matplotlib, Agg): what a person would rather look at than read.

* ``fits.png``: each model channel, measured vs baseline fit vs augmented fit, and the
  residuals of both against ±σ of the noise floor.
* ``residual_spectra.png``: residual periodograms (per rev) of baseline and augmented model
  relative to the noise floor's flat level, smoothed; the located band shaded.
* ``residual_energy.png``: residual mean square per revolution over time, relative to the
  floor, baseline and augmented; the located time span shaded.
* ``effects.png``: the fit improving effect by effect (forward selection): residual RMS over
  the floor after each added effect, and the residual energy over time of every step.
* ``frequency_response.png`` (records with a stirring sweep): the measured directional
  frequency response β_c/θ_c with its coherence, and the baseline model's, so that the band
  the diagnosis located can be read against frequency.
* ``proposal.png`` (out of catalogue only): how much each library term lowers the held-out
  equation error at every step of the proposal, the kept terms marked.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, TYPE_CHECKING, Union

import numpy as np

from rotor_id import residuals as rs
from rotor_id.estimation.term_search import MIN_IMPROVEMENT

if TYPE_CHECKING:
    from rotor_id.diagnosis.result import Diagnosis
    from rotor_id.io.record import Record
    from rotor_id.io.run_description import RunDescription

#: a file or directory name
PathLike = Union[str, os.PathLike]


def _plt():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def _model_channels(diagnosis):
    return [c for c in diagnosis.channels if c.model_channel]


def _augmented_series(diagnosis):
    """Augmented fitted values and residuals per model channel (None if no candidate)."""
    fit = diagnosis.chosen
    if fit is None:
        return None, None
    est = fit.estimate
    if len(est.fitted) > 1:
        return ([f[:, 0] for f in est.fitted], [r[:, 0] for r in est.residuals])
    return ([est.fitted[0][:, j] for j in range(est.fitted[0].shape[1])],
            [est.residuals[0][:, j] for j in range(est.residuals[0].shape[1])])


def plot_fits(diagnosis: Diagnosis, path: PathLike) -> None:
    """Measured vs both fits, and residuals, per model channel."""
    plt = _plt()
    chans = _model_channels(diagnosis)
    aug_fit, aug_res = _augmented_series(diagnosis)
    ts = diagnosis.record_window.time_s
    fig, axes = plt.subplots(2 * len(chans), 1, figsize=(10, 2.0 * 2 * len(chans)),
                             sharex=True)
    for j, c in enumerate(chans):
        ax, axr = axes[2 * j], axes[2 * j + 1]
        ax.plot(ts, np.degrees(c.measured), '.', ms=2, color='0.6', label='measured')
        ax.plot(ts, np.degrees(c.fitted), '-', lw=1.0, color='C0', label='baseline fit')
        if aug_fit is not None:
            ax.plot(ts, np.degrees(aug_fit[j]), '--', lw=1.0, color='C3',
                    label=f'with {_effect_names(diagnosis)}')
        ax.set_ylabel(f'{c.name}\n[deg]')
        axr.plot(ts, np.degrees(c.residual), lw=0.5, color='C0', label='baseline residual')
        if aug_res is not None:
            axr.plot(ts, np.degrees(aug_res[j]), lw=0.5, color='C3', alpha=0.8,
                     label='augmented residual')
        for sign in (-1, 1):
            axr.axhline(sign * math.degrees(c.floor), color='k', lw=0.6, ls=':')
        axr.set_ylabel('residual\n[deg]')
    axes[0].legend(loc='upper right', fontsize=7)
    axes[1].legend(loc='upper right', fontsize=7)
    axes[-1].set_xlabel('time since first sample [s]  (dotted: ±σ noise floor)')
    fig.suptitle(_title(diagnosis), fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _effect_names(diagnosis):
    return ' + '.join(diagnosis.explanation.names) or diagnosis.effect


def _title(diagnosis):
    fit = diagnosis.fit
    return (f'{diagnosis.baseline.model.name}: {_effect_names(diagnosis)} '
            f'({diagnosis.confidence} confidence) — RMS baseline {fit["baseline_rms"]:.3g}, '
            f'augmented {fit["augmented_rms"]:.3g}, floor {fit["noise_floor"]:.3g} rad')


def plot_spectra(diagnosis: Diagnosis, path: PathLike, smooth: int = 15) -> None:
    """Residual spectra of baseline and augmented model relative to the floor."""
    plt = _plt()
    chans = _model_channels(diagnosis)
    _, aug_res = _augmented_series(diagnosis)
    t = diagnosis.baseline.experiments[0].t
    dt = float(np.median(np.diff(t)))
    kernel = np.ones(smooth) / smooth
    fig, ax = plt.subplots(figsize=(9, 4))
    for label, series, color in (('baseline', [c.residual for c in chans], 'C0'),
                                 ('augmented', aug_res, 'C3')):
        if series is None:
            continue
        spectra = [rs.periodogram(res, dt) for res in series]
        freq = spectra[0][0]
        total = np.sum([spec / c.floor**2 for (_, spec), c in zip(spectra, chans)], axis=0)
        ax.semilogy(freq, np.convolve(total / len(chans), kernel, mode='same'), color=color,
                    label=f'{label} residual')
    ax.axhline(1.0, color='k', ls=':', lw=0.8, label='noise floor')
    lo, hi = diagnosis.location['band_per_rev']
    if diagnosis.mismatch:
        ax.axvspan(lo, hi, color='0.85', label='located band')
    ax.set_xlim(0, min(12.0, float(freq[-1])))
    ax.set_xlabel('frequency [per rev]')
    ax.set_ylabel('residual power / floor')
    ax.legend(fontsize=8)
    ax.set_title(_title(diagnosis), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _energy_over_floor(residuals, floors, t, part):
    """Return (seconds, residual mean square per revolution / floor², averaged over channels)."""
    energies = [rs.windowed_energy(r, t) for r in residuals]
    total = np.sum([ms / f**2 for (_, ms), f in zip(energies, floors)], axis=0)
    return np.interp(energies[0][0], part.t, part.time_s), total / len(residuals)


def plot_energy(diagnosis: Diagnosis, path: PathLike) -> None:
    """Residual mean square per revolution over time, relative to the floor."""
    plt = _plt()
    chans = _model_channels(diagnosis)
    _, aug_res = _augmented_series(diagnosis)
    part = diagnosis.record_window
    t = diagnosis.baseline.experiments[0].t
    fig, ax = plt.subplots(figsize=(9, 3.5))
    for label, series, color in (('baseline', [c.residual for c in chans], 'C0'),
                                 ('augmented', aug_res, 'C3')):
        if series is None:
            continue
        ax.plot(*_energy_over_floor(series, [c.floor for c in chans], t, part), 'o-', ms=3,
                color=color, label=f'{label} residual')
    ax.axhline(1.0, color='k', ls=':', lw=0.8, label='noise floor')
    if diagnosis.mismatch:
        ax.axvspan(*diagnosis.location['window_s'], color='0.85', label='located span')
    ax.set_xlabel('time since first sample [s]')
    ax.set_ylabel('mean square / floor²\n(per revolution)')
    ax.legend(fontsize=8)
    ax.set_title(_title(diagnosis), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_effects(diagnosis: Diagnosis, path: PathLike) -> None:
    """Show the fit improving effect by effect: RMS over the floor per step, energy in time."""
    plt = _plt()
    chans = _model_channels(diagnosis)
    part = diagnosis.record_window
    t = diagnosis.baseline.experiments[0].t
    floors = [c.floor for c in chans]
    floor = math.sqrt(np.mean(np.square(floors)))
    series = [('baseline', [c.residual for c in chans])]
    for added, result in diagnosis.path:
        est = result.estimate
        res = [r[:, 0] for r in est.residuals] if len(est.residuals) > 1 else \
            [est.residuals[0][:, j] for j in range(est.residuals[0].shape[1])]
        series.append((added, res))
    fig, (ax_bar, ax) = plt.subplots(1, 2, figsize=(12, 3.8),
                                     gridspec_kw={'width_ratios': [1, 2]})
    excess = [math.sqrt(np.mean([np.mean(r**2) for r in res])) / floor - 1.0
              for _, res in series]
    ax_bar.bar(range(len(series)), [100 * e for e in excess],
               color=['C0'] + [f'C{i + 1}' for i in range(len(series) - 1)])
    ax_bar.set_xticks(range(len(series)))
    # an effect the record cannot tell from a named one is named under it, with its share
    shares = {e.effect: [s for s in e.shares if s.effect != e.effect]
              for e in diagnosis.explanation.effects}
    ax_bar.set_xticklabels(['baseline'] + [
        f'+ {added}' + ''.join(f'\n(or {s.effect} {s.share:.0%})'
                               for s in shares.get(added, []))
        for added, _ in series[1:]], rotation=20, fontsize=7)
    ax_bar.axhline(0.0, color='k', lw=0.8)
    ax_bar.set_ylabel('residual RMS above the floor [%]')
    for i, (name, res) in enumerate(series):
        ax.plot(*_energy_over_floor(res, floors, t, part), 'o-', ms=3,
                color=f'C{i}', label=name if i == 0 else f'+ {name}')
    ax.axhline(1.0, color='k', ls=':', lw=0.8, label='noise floor')
    ax.set_xlabel('time since first sample [s]')
    ax.set_ylabel('mean square / floor² (per rev)')
    ax.legend(fontsize=7)
    fig.suptitle(_title(diagnosis), fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_proposal(proposal: dict[str, Any], path: PathLike) -> None:
    """Held-out improvement of every library term at each step of a proposal (JSON)."""
    plt = _plt()
    steps = proposal['steps']
    fig, axes = plt.subplots(1, len(steps), figsize=(5.5 * len(steps), 4.5), squeeze=False)
    for ax, step in zip(axes[0], steps):
        names = list(step['tried'])
        gain = [100.0 * step['tried'][n] for n in names]
        colours = ['tab:green' if n == step['term'] and step['kept'] else
                   'tab:orange' if n in step.get('alternatives', ()) else 'tab:gray'
                   for n in names]
        ax.barh(range(len(names)), gain, color=colours)
        ax.set_yticks(range(len(names)), names)
        ax.axvline(100.0 * MIN_IMPROVEMENT, color='k', ls=':', lw=1)
        ax.set_xlabel('held-out equation error reduction [%]')
        verdict = 'kept' if step['kept'] else 'not kept'
        ax.set_title(f"{step['term']}: {verdict} (t = {step['t_statistic']:.1f}, "
                     f"needs {step['t_critical']:.1f})", fontsize=9)
    fig.suptitle("proposal, not a verdict: beta_k'' += ξ·term on every blade "
                 '(green kept, orange as good within chance, dotted: smallest reduction)',
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_frequency_response(diagnosis: Diagnosis, record: Record,
                            description: RunDescription, path: PathLike) -> str | None:
    """
    Draw the record's measured dFRF and the baseline model's; return None or why not drawn.

    The model is drawn at the baseline fit's values: the mismatch the diagnosis explains is
    the one between these two curves.
    """
    from rotor_id import pipeline
    from rotor_id.estimation.frequency_response_plot import bode_figure
    values = {name: p['baseline_value'] for name, p in diagnosis.parameters.items()}
    try:
        analysis = pipeline.frequency_analysis([(record, description, 'record')],
                                               parameters=values, source='the baseline fit')
    except ValueError as exc:             # no stirring sweep, or too short for one
        return str(exc)
    bode_figure(analysis, path, title='diagnosis: measured and baseline model')
    return None


def write_report(diagnosis: Diagnosis, directory: PathLike, record: Record | None = None,
                 description: RunDescription | None = None) -> list[Path]:
    """
    Write the figures into ``directory``; return their paths.

    With the diagnosed ``record`` and its ``description``, the frequency response is drawn too
    where the record has a stirring sweep.
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / 'fits.png', out / 'residual_spectra.png', out / 'residual_energy.png',
             out / 'effects.png']
    plot_fits(diagnosis, paths[0])
    plot_spectra(diagnosis, paths[1])
    plot_energy(diagnosis, paths[2])
    plot_effects(diagnosis, paths[3])
    if getattr(diagnosis, 'proposal', None) and diagnosis.proposal.get('steps'):
        paths.append(out / 'proposal.png')
        plot_proposal(diagnosis.proposal, paths[-1])
    if record is not None and description is not None:
        path = out / 'frequency_response.png'
        if plot_frequency_response(diagnosis, record, description, path) is None:
            paths.append(path)
    return paths
