"""
Multiblade coordinates of an N-bladed rotor (docs/models.md §8): the one place they are defined.

Blade k (k = 1..N) sits at ψ_k = ψ + (k − 1)·2π/N, ψ the azimuth of blade 1 (= the report's
nondimensional time t). The N blade flaps β_k and N multiblade coordinates q are related by

    β_k = β0 + Σ_h (β_hc cos hψ_k + β_hs sin hψ_k) + βd (−1)^k,      h = 1 .. ⌊(N − 1)/2⌋

    β0   = (1/N) Σ β_k                      collective (coning)
    β_hc = (2/N) Σ β_k cos hψ_k             cyclic cos of harmonic h (h = 1: βI, forward tilt)
    β_hs = (2/N) Σ β_k sin hψ_k             cyclic sin of harmonic h (h = 1: βII, left tilt)
    βd   = (1/N) Σ (−1)^k β_k   (N even)     differential (reactionless)

N = 2 has β0 and βd only, N = 3 has β0, βI, βII, N = 4 adds βd (the report's four coordinates),
N = 5 adds β2c, β2s, and so on: always N coordinates, so the transform is exact and invertible.

For pitch (report Ch.2 eq. 3), θ_k = θ0 − θI sin ψ_k + θII cos ψ_k, so the 'cos' coordinate of
the blade pitches is the lateral cyclic θII and the 'sin' coordinate is −θI.
"""

from typing import Mapping

import numpy as np
import numpy.typing as npt

TWO_PI = 2.0 * np.pi


def blade_azimuths(psi: npt.ArrayLike, n_blades: int) -> np.ndarray:
    """
    Return the azimuth of every blade.

    Parameters
    ----------
    psi
        (n,) azimuth of blade 1, rad.
    n_blades
        Number of blades N.

    Returns
    -------
    (n, N) array, column k−1 is ψ_k = ψ + (k − 1)·2π/N.

    """
    psi = np.atleast_1d(np.asarray(psi, dtype=float))
    return psi[:, None] + TWO_PI * np.arange(n_blades) / n_blades


def coordinate_harmonics(n_blades: int) -> tuple[tuple[str, str, int, str], ...]:
    """
    Return the multiblade coordinates of an N-bladed rotor as (name, key, harmonic, kind) tuples.

    ``kind`` is 'collective', 'cos', 'sin' or 'differential'; ``key`` is the dictionary key of
    :func:`multiblade_coordinates` ('collective', 'cos', 'sin', 'cos2', 'sin2', ...,
    'differential') and ``name`` the state name ('beta_0', 'beta_I', 'beta_II', 'beta_2c',
    'beta_2s', ..., 'beta_d').
    """
    n_blades = int(n_blades)
    if n_blades < 2:
        raise ValueError(f'a rotor needs at least 2 blades for multiblade coordinates, '
                         f'got {n_blades}')
    coords = [('beta_0', 'collective', 0, 'collective')]
    for h in range(1, (n_blades - 1) // 2 + 1):
        if h == 1:
            coords += [('beta_I', 'cos', 1, 'cos'), ('beta_II', 'sin', 1, 'sin')]
        else:
            coords += [(f'beta_{h}c', f'cos{h}', h, 'cos'), (f'beta_{h}s', f'sin{h}', h, 'sin')]
    if n_blades % 2 == 0:
        coords.append(('beta_d', 'differential', n_blades // 2, 'differential'))
    return tuple(coords)


def coordinate_names(n_blades: int) -> tuple[str, ...]:
    """State names of the N multiblade coordinates, in transform order (β0, βI, βII, ..., βd)."""
    return tuple(c[0] for c in coordinate_harmonics(n_blades))


def blade_from_multiblade_matrix(psi: npt.ArrayLike, n_blades: int,
                                 derivative: int = 0) -> np.ndarray:
    """
    Return T (n, N, N) with β = T q (blade flaps from multiblade coordinates), or its d/dψ.

    ``derivative`` = 1 or 2 gives dT/dψ and d²T/dψ² (needed to transform the equations of
    motion: β′ = T q′ + T′ q, β″ = T q″ + 2T′ q′ + T″ q).
    """
    azimuths = blade_azimuths(psi, n_blades)
    k = np.arange(1, n_blades + 1)
    columns = []
    for _, _, h, kind in coordinate_harmonics(n_blades):
        if kind == 'collective':
            col = np.full(azimuths.shape, 1.0 if derivative == 0 else 0.0)
        elif kind == 'differential':
            col = np.broadcast_to(((-1.0) ** k) * (1.0 if derivative == 0 else 0.0),
                                  azimuths.shape)
        else:
            phase = h * azimuths + 0.5 * np.pi * ((kind == 'cos') + derivative)
            col = h**derivative * np.sin(phase)     # d^n/dψ^n of sin(hψ) or cos(hψ)
        columns.append(col)
    return np.stack(columns, axis=2)


def multiblade_from_blade_matrix(psi: npt.ArrayLike, n_blades: int) -> np.ndarray:
    """Return T⁻¹ (n, N, N) with q = T⁻¹ β: (1/N) rows for β0 and βd, (2/N) cos/sin rows."""
    azimuths = blade_azimuths(psi, n_blades)
    k = np.arange(1, n_blades + 1)
    rows = []
    for _, _, h, kind in coordinate_harmonics(n_blades):
        if kind == 'collective':
            row = np.full(azimuths.shape, 1.0 / n_blades)
        elif kind == 'differential':
            row = np.broadcast_to((-1.0) ** k / n_blades, azimuths.shape)
        elif kind == 'cos':
            row = (2.0 / n_blades) * np.cos(h * azimuths)
        else:
            row = (2.0 / n_blades) * np.sin(h * azimuths)
        rows.append(row)
    return np.stack(rows, axis=1)


def _check_blades(values, psi):
    values = np.asarray(values, dtype=float)
    psi = np.asarray(psi, dtype=float)
    if values.ndim != 2 or psi.shape != values.shape[:1]:
        raise ValueError(f'values must be (n, N) and psi (n,); got {values.shape} and {psi.shape}')
    if values.shape[1] < 2:
        raise ValueError(f'multiblade coordinates need at least 2 blades, got {values.shape[1]}')
    return values, psi


def multiblade_coordinates(values: npt.ArrayLike, psi: npt.ArrayLike) -> dict[str, np.ndarray]:
    """
    Transform blade quantities to multiblade coordinates (docs/models.md §8).

    Parameters
    ----------
    values
        (n, N) per-blade flap (or pitch), N ≥ 2.
    psi
        (n,) azimuth of blade 1 (the nondimensional time t).

    Returns
    -------
    Dict with (n,) arrays 'collective' (β0), for N ≥ 3 'cos' (βI) and 'sin' (βII), for N ≥ 5
    'cos2', 'sin2', ... (higher cyclics) and, for even N, 'differential' (βd).

    """
    values, psi = _check_blades(values, psi)
    n_blades = values.shape[1]
    q = np.einsum('tij,tj->ti', multiblade_from_blade_matrix(psi, n_blades), values)
    return {key: q[:, i] for i, (_, key, _, _) in enumerate(coordinate_harmonics(n_blades))}


def blade_values(coords: Mapping[str, npt.ArrayLike], psi: npt.ArrayLike,
                 n_blades: int = 4) -> np.ndarray:
    """
    Inverse of :func:`multiblade_coordinates`: β_k = β0 + Σ_h (...) + (−1)^k βd.

    Exact when every coordinate of the N-bladed rotor is given; missing coordinates count as 0.

    Parameters
    ----------
    coords
        Dict as returned by :func:`multiblade_coordinates` (any coordinate may be left out).
    psi
        (n,) azimuth of blade 1.
    n_blades
        Number of blades N.

    Returns
    -------
    (n, N) per-blade values.

    """
    psi = np.atleast_1d(np.asarray(psi, dtype=float))
    T = blade_from_multiblade_matrix(psi, n_blades)
    values = np.zeros((psi.size, n_blades))
    for i, (_, key, _, _) in enumerate(coordinate_harmonics(n_blades)):
        if key in coords:
            value = np.asarray(coords[key], dtype=float).reshape(-1)
            values = values + value[:, None] * T[:, :, i]
    return values


def azimuth_offset_matrix(n_blades: int, offset: float) -> np.ndarray:
    """
    Return S (N, N): multiblade coordinates referred to an azimuth read ``offset`` ahead.

    A rig whose azimuth reads ψ + Δψ (encoder index off the reference blade) forms the
    coordinates with the wrong ψ_k: q_read = T⁻¹(ψ + Δψ) T(ψ) q = S q. S is constant (the
    transforms above, evaluated at ψ = 0): the collective and differential are unchanged and
    every cyclic pair of harmonic h turns by hΔψ,

        β_hc,read = β_hc cos hΔψ − β_hs sin hΔψ,   β_hs,read = β_hs cos hΔψ + β_hc sin hΔψ.
    """
    zero = np.zeros(1)
    return (multiblade_from_blade_matrix(zero + float(offset), n_blades)[0]
            @ blade_from_multiblade_matrix(zero, n_blades)[0])
