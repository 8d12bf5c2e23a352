"""
Bode plots of a directional frequency response, measured and modelled (matplotlib, Agg).

:func:`draw_frequency_response` draws on axes the caller owns (the diagnosis figures use it);
:func:`bode_figure` makes the figure of ``rotor-id frequency-response``: magnitude (dB) and
phase over one signed frequency axis (− regressing, + progressing, per rev), coherence below.
"""

from typing import Any, TYPE_CHECKING

import numpy as np

from rotor_id.estimation.frequency_response import COHERENCE_MIN, DB, FrequencyResponse

if TYPE_CHECKING:
    import os

    from matplotlib.axes import Axes


def _db(values):
    return DB * np.log(np.maximum(np.abs(values), 1e-300))


def draw_frequency_response(ax_magnitude: 'Axes', ax_phase: 'Axes', estimate: FrequencyResponse,
                            overlay: Any = None, ax_coherence: 'Axes | None' = None,
                            sidebands: bool = True) -> None:
    """
    Draw a dFRF estimate and optionally a model on the given axes.

    Parameters
    ----------
    ax_magnitude, ax_phase
        Axes for |H| (dB re 1 rad/rad) and ∠H (deg) against frequency (per rev, signed).
    estimate
        :class:`rotor_id.estimation.frequency_response.FrequencyResponse`.
    overlay
        ``pipeline.ModelOverlay`` (anything with ``transfer_function``,
        ``as_estimated`` and ``name``), or None.
    ax_coherence
        Axes for γ² (with CIFER's 0.6 line), or None.
    sidebands
        Draw the magnitude of the periodic model's sidebands H_n (output at ω + n per rev).

    """
    f = estimate.frequency_per_rev
    good = estimate.usable()
    eps = estimate.random_error
    for mask, style in ((good, {'color': 'k', 'alpha': 1.0}),
                        (~good, {'color': '0.6', 'alpha': 0.8})):
        if not np.any(mask):
            continue
        label = 'measured' if mask is good else f'measured, γ² < {COHERENCE_MIN:g}'
        # (style: matplotlib keyword arguments, inferred as dict[str, object] by mypy)
        ax_magnitude.errorbar(f[mask], _db(estimate.response[mask]),
                              yerr=DB * np.minimum(eps[mask], 3.0), fmt='o', ms=3, lw=0.8,
                              label=label, **style)  # type: ignore[arg-type]
        ax_phase.errorbar(f[mask], estimate.phase_deg[mask],
                          yerr=np.degrees(np.minimum(eps[mask], np.pi)), fmt='o', ms=3,
                          lw=0.8, **style)  # type: ignore[arg-type]
    if overlay is not None:
        tf = overlay.transfer_function
        for side in (tf.frequency < 0, tf.frequency > 0):
            if not np.any(side):
                continue
            first = not np.any(tf.frequency[:np.argmax(side)] != 0) or side[0]
            ax_magnitude.plot(tf.frequency[side], _db(tf.principal[side]), '-', color='C0',
                              lw=1.4, label=f'{overlay.name}: transfer function'
                              if first else None)
            ax_phase.plot(tf.frequency[side], np.degrees(np.angle(tf.principal[side])), '-',
                          color='C0', lw=1.4)
            if sidebands:
                for n, response in sorted(tf.sidebands.items()):
                    peak = np.max(np.abs(response[side]), initial=0.0)
                    if peak < 0.01 * np.max(np.abs(tf.principal)):
                        continue
                    ax_magnitude.plot(tf.frequency[side], _db(response[side]), ':', lw=0.9,
                                      color='C2', label=f'sideband {n:+d}/rev' if first
                                      else None)
        ax_magnitude.plot(f, _db(overlay.as_estimated), 's', mfc='none', ms=5, color='C1',
                          label=f'{overlay.name} through the same estimate')
        ratios = getattr(overlay, 'sideband_ratios', {})
        if ratios:
            n, ratio = max(ratios.items(), key=lambda item: item[1])
            ax_magnitude.text(0.01, 0.02, f'periodic model: largest sideband {n:+d}/rev, '
                              f'{100 * ratio:.2g} % of the principal response',
                              transform=ax_magnitude.transAxes, fontsize=7, color='C2')
        ax_phase.plot(f, np.degrees(np.angle(overlay.as_estimated)), 's', mfc='none', ms=5,
                      color='C1')
    ax_magnitude.set_ylabel('|β_c/θ_c| [dB]')
    ax_phase.set_ylabel('∠β_c/θ_c [deg]')
    for ax in (ax_magnitude, ax_phase):
        ax.axvline(0.0, color='0.8', lw=0.8)
        ax.grid(True, lw=0.3)
    if ax_coherence is not None:
        ax_coherence.plot(f, estimate.coherence, 'o-', ms=3, lw=0.8, color='k')
        ax_coherence.axhline(COHERENCE_MIN, color='C3', lw=0.8, ls='--')
        ax_coherence.axvline(0.0, color='0.8', lw=0.8)
        ax_coherence.set_ylim(0.0, 1.05)
        ax_coherence.set_ylabel('coherence γ²')
        ax_coherence.grid(True, lw=0.3)


def bode_figure(analysis: Any, path: 'str | os.PathLike[str]', title: str = '') -> None:
    """Write the Bode figure of a ``pipeline.FrequencyAnalysis`` (PNG) to ``path``."""
    # the figure without pyplot: its import is most of a short command's time
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(8.0, 7.5))
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(3, 1, height_ratios=[3, 3, 1.6], left=0.1, right=0.97,
                            bottom=0.07, top=0.92, hspace=0.08)
    axes = [fig.add_subplot(grid[0])]
    axes += [fig.add_subplot(grid[k], sharex=axes[0]) for k in (1, 2)]
    draw_frequency_response(axes[0], axes[1], analysis.estimate, analysis.overlay, axes[2])
    for ax in axes[:2]:
        ax.tick_params(labelbottom=False)
    axes[2].set_xlabel('stirring frequency [per rev]  (− regressing, + progressing)')
    axes[0].legend(fontsize=7, loc='best')
    heading = title
    if analysis.overlay is not None:
        heading += (f'\nJ = {analysis.overlay.cost:.3g} (same estimate), '
                    f'{analysis.overlay.cost_transfer_function:.3g} (transfer function); '
                    'J ≤ 100 acceptable')
    axes[0].set_title(heading, fontsize=9)
    fig.savefig(path, dpi=80)
