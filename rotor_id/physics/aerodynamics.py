"""
The flapping blade's aerodynamics: the one place the blade equation's coefficients are written.

docs/models.md §7 derives them. A rigid, centrally hinged blade (flap frequency P per rev, Lock
number γ, tip loss B, no reversed flow, no root cut-out) at azimuth ψ in forward flight at advance
ratio μ sees, at radius x (fraction of R), the velocities (per ΩR)

    U_T = x + μ sin ψ,        U_P = −λ0 − x λ_h(ψ) + x β′ + μ β cos ψ

with the inflow in the report's sign (up positive): λ0 uniform, λ_h = λI cos ψ + λII sin ψ the
first-harmonic (linearly varying) inflow. Strip theory integrated to x = B gives the flapping
moment and the lift, both divided by γ/2:

    moment  m = m_θ θ − m_rate β′ − m_flap β + m_λ0 λ0 + m_λ1 λ_h    (∫ x (U_T² θ − U_T U_P) dx)
    lift    l = l_θ θ − l_rate β′ − l_flap β + l_λ0 λ0 + l_λ1 λ_h    (∫ (U_T² θ − U_T U_P) dx)

and the blade equation (report Ch.3 eq. 24, corrected: docs/models.md §5 item 1)

    β″ + P² β = (γ/2) m,     θ = θ_control − K_P β  (pitch-flap coupling K_P = tan δ3)

With K_P = 0 and λ = 0 the moment coefficients are the report's C(ψ), K(ψ), m_θ(ψ) and m_λ(ψ)
(Ch.3 eqs 25-28): m_rate = C, m_flap = K, m_λ0 = m_λ, and m_λ1 = C.
"""

import numpy as np
import numpy.typing as npt


def blade_aerodynamics(psi: npt.ArrayLike, tip_loss: float,
                       advance_ratio: float) -> dict[str, np.ndarray]:
    """
    Return the moment and lift coefficients of the blade at azimuths ``psi`` (module docstring).

    Parameters
    ----------
    psi : array_like
        Blade azimuth(s), rad (any shape).
    tip_loss : float
        B, the radius (fraction of R) up to which the blade lifts.
    advance_ratio : float
        μ.

    Returns
    -------
    dict of arrays shaped like ``psi``: 'm_theta', 'm_rate', 'm_flap', 'm_lambda0', 'm_lambda1'
    (moment / (γ/2)) and 'l_theta', 'l_rate', 'l_flap', 'l_lambda0', 'l_lambda1' (lift / (γ/2)).

    """
    psi = np.asarray(psi, dtype=float)
    B, mu = float(tip_loss), float(advance_ratio)
    s1, c1 = np.sin(psi), np.cos(psi)
    c2 = np.cos(2 * psi)
    # ∫0^B x^n U_T^k dx, U_T = x + μ sin ψ
    x_ut = B**3 / 3 + (B**2 * mu / 2) * s1                                   # ∫ x U_T
    x2_ut = B**4 / 4 + (B**3 * mu / 3) * s1                                  # ∫ x² U_T
    x_ut2 = (B**4 + B**2 * mu**2) / 4 + (2.0 / 3.0) * B**3 * mu * s1 - (B**2 * mu**2 / 4) * c2
    ut = B**2 / 2 + B * mu * s1                                              # ∫ U_T
    ut2 = B**3 / 3 + B**2 * mu * s1 + B * mu**2 * (1 - c2) / 2               # ∫ U_T²
    return {
        'm_theta': x_ut2,                                     # report m_θ(ψ), Ch.3 eq. 27
        'm_rate': x2_ut,                                      # report C(ψ), eq. 25
        'm_flap': mu * c1 * x_ut,                             # report K(ψ), eq. 26
        'm_lambda0': x_ut,                                    # report m_λ(ψ), eq. 28
        'm_lambda1': x2_ut,
        'l_theta': ut2,
        'l_rate': x_ut,
        'l_flap': mu * c1 * ut,
        'l_lambda0': ut,
        'l_lambda1': x_ut,
    }


def flap_damping(lock_number: float, tip_loss: float) -> float:
    """Return A = γB⁴/8, the hover flap damping per unit rate and pitch gain (Ch.2 eq. 27)."""
    return lock_number * tip_loss**4 / 8.0


def lock_number_from_damping(damping: float, tip_loss: float) -> float:
    """Invert :func:`flap_damping`: γ = 8A/B⁴."""
    return 8.0 * damping / tip_loss**4


def hover_coning(lock_number: float, collective: float, flap_frequency: float, tip_loss: float,
                 pitch_flap_coupling: float = 0.0) -> float:
    """
    Steady coning of the hovering rotor without inflow: β0 = Aθ0 / (P² + A K_P), A = γB⁴/8.

    The blade equation at μ = 0 with constant pitch, β″ + Aβ′ + P²β = A(θ0 − K_P β), at rest.
    """
    A = flap_damping(lock_number, tip_loss)
    return A * collective / (flap_frequency**2 + A * pitch_flap_coupling)
