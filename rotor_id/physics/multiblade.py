"""
Multiblade coordinates of an N-bladed rotor (MODELS.md §0): the one place they are defined.

Blade k (k = 1..N) sits at ψ_k = ψ + (k − 1)·2π/N, ψ the azimuth of blade 1 (= the report's
nondimensional time t).

    β0  = (1/N) Σ β_k                       collective
    βI  = (2/N) Σ β_k cos ψ_k               cos   (forward tilt of the tip-path plane)
    βII = (2/N) Σ β_k sin ψ_k               sin   (left tilt)
    βd  = (1/N) Σ (−1)^k β_k   (N even)     differential (reactionless)

and for N = 4 exactly  β_k = β0 + βI cos ψ_k + βII sin ψ_k + (−1)^k βd.

For pitch (report Ch.2 eq. 3), θ_k = θ0 − θI sin ψ_k + θII cos ψ_k, so the 'cos' coordinate of
the blade pitches is the lateral cyclic θII and the 'sin' coordinate is −θI.
"""

import numpy as np

TWO_PI = 2.0 * np.pi


def blade_azimuths(psi, n_blades):
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


def _check_blades(values, psi):
    values = np.asarray(values, dtype=float)
    psi = np.asarray(psi, dtype=float)
    if values.ndim != 2 or psi.shape != values.shape[:1]:
        raise ValueError(f'values must be (n, N) and psi (n,); got {values.shape} and {psi.shape}')
    if values.shape[1] < 3:
        raise ValueError(f'multiblade coordinates need at least 3 blades, got {values.shape[1]}')
    return values, psi


def multiblade_coordinates(values, psi):
    """
    Transform blade quantities to multiblade coordinates (MODELS.md §0).

    Parameters
    ----------
    values
        (n, N) per-blade flap (or pitch), N ≥ 3.
    psi
        (n,) azimuth of blade 1 (the nondimensional time t).

    Returns
    -------
    Dict with (n,) arrays 'collective' (β0), 'cos' (βI), 'sin' (βII) and, for even N,
    'differential' (βd).

    """
    values, psi = _check_blades(values, psi)
    n_blades = values.shape[1]
    azimuths = blade_azimuths(psi, n_blades)
    coords = {
        'collective': values.mean(axis=1),
        'cos': 2.0 / n_blades * np.sum(values * np.cos(azimuths), axis=1),
        'sin': 2.0 / n_blades * np.sum(values * np.sin(azimuths), axis=1),
    }
    if n_blades % 2 == 0:
        sign = (-1.0) ** np.arange(1, n_blades + 1)
        coords['differential'] = values @ sign / n_blades
    return coords


def blade_values(coords, psi, n_blades=4):
    """
    Inverse of :func:`multiblade_coordinates`: β_k = β0 + βI cos ψ_k + βII sin ψ_k + (−1)^k βd.

    Exact for N = 3 and N = 4 (where the coordinates span all blade motions).

    Parameters
    ----------
    coords
        Dict as returned by :func:`multiblade_coordinates`; 'differential' optional.
    psi
        (n,) azimuth of blade 1.
    n_blades
        Number of blades N.

    Returns
    -------
    (n, N) per-blade values.

    """
    psi = np.asarray(psi, dtype=float)
    azimuths = blade_azimuths(psi, n_blades)
    values = (np.asarray(coords['collective'], dtype=float)[:, None]
              + np.asarray(coords['cos'], dtype=float)[:, None] * np.cos(azimuths)
              + np.asarray(coords['sin'], dtype=float)[:, None] * np.sin(azimuths))
    if 'differential' in coords:
        sign = (-1.0) ** np.arange(1, n_blades + 1)
        values = values + np.asarray(coords['differential'], dtype=float)[:, None] * sign
    return values
