"""
The two peers our output-error ML is measured against.

(a) ``afternoon``: what a user writes in an afternoon. The right-hand side of each report model is
    typed in again here straight from the equations of docs/models.md (§1.2 single blade, §2.2
    constant-coefficient multiblade, §3.2 dynamic wake), integrated with
    ``scipy.integrate.solve_ivp`` and fitted with ``scipy.optimize.least_squares`` and its
    finite-difference Jacobian. Nothing of rotor_id is used inside the fit, so it also checks
    our models independently: both must land on the same optimum.
(b) ``fd_ours``: the same ``least_squares`` with a finite-difference Jacobian, but the residuals
    come from our own simulator (:func:`rotor_id.estimation.simulate.simulate`, no
    sensitivities). (a) vs (b) is the simulator's share of the gain, (b) vs ours the
    algorithm's (analytic sensitivities + Gauss-Newton).

Both minimise the same cost as ours: ½ Σ ((y − ŷ)/σ)² with σ known.
"""

import math

import numpy as np
from rotor_id.estimation.simulate import simulate
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

# report rotor (docs/models.md §0)
B = 0.97        # tip loss
P = 1.2         # flap frequency, per rev
AMPLITUDE = 1.5  # cyclic amplitude, deg


def stirring(t, t0, omegadot):
    """θI, θII at scalar t: 1.5 sin φ, 1.5 cos φ, φ = ω̇ (t − t0)² after t0 (docs/models.md §0)."""
    phi = omegadot * (t - t0) ** 2 if t > t0 else 0.0
    return AMPLITUDE * math.sin(phi), AMPLITUDE * math.cos(phi)


class SingleBladeRHS:
    """docs/models.md §1.2: x = [β, β′], p = [γ, δ], y = β (μ = 0.4, blade 1: ψ = t)."""

    n_params = 2

    def __init__(self, t0, omegadot, mu=0.4):
        self.t0, self.omegadot, self.mu = t0, omegadot, mu

    def rhs(self, t, x, p):
        """x′ of the single blade."""
        gamma, delta = p
        mu = self.mu
        s1, c1 = math.sin(t), math.cos(t)
        damping = B**4 / 4 + (B**3 * mu / 3) * s1
        stiffness = (B**3 * mu / 3) * c1 + (B**2 * mu**2 / 4) * math.sin(2 * t)
        m_theta = ((B**4 + B**2 * mu**2) / 4 + (2 / 3) * B**3 * mu * s1
                   - (B**2 * mu**2 / 4) * math.cos(2 * t))
        th_i, th_ii = stirring(t, self.t0, self.omegadot)
        theta_c = -th_i * s1 + th_ii * c1                      # = 1.5 cos(t + φ)
        return [x[1], (-(P**2 + gamma / 2 * stiffness) * x[0] - gamma / 2 * damping * x[1]
                       + 0.5 * m_theta * delta + gamma / 2 * m_theta * theta_c)]

    def output(self, t, x):
        """Return y = β, shape (T, 1)."""
        return x[:, :1]


class MultibladeConstantRHS:
    """docs/models.md §2.2: x = [β0, βI, βII, β0′, βI′, βII′], p = [γ, δ], y = [β0, βI, βII]."""

    n_params = 2

    def __init__(self, t0, omegadot, mu=0.4):
        self.t0, self.omegadot, self.mu = t0, omegadot, mu

    def rhs(self, t, x, p):
        """x′ of the three constant-coefficient multiblade equations."""
        gamma, delta = p
        mu = self.mu
        b0, bi, bii, d0, di, dii = x
        a = gamma * B**4 / 8
        c3 = gamma * B**3 * mu
        th_i, th_ii = stirring(t, self.t0, self.omegadot)
        dd0 = (-a * d0 - c3 / 12 * dii - P**2 * b0
               + B**2 / 8 * (B**2 + mu**2) * delta - c3 / 6 * th_i)
        ddi = (-a * di - 2 * dii - c3 / 6 * b0 - (P**2 - 1) * bi
               - gamma * B**2 / 16 * (2 * B**2 + mu**2) * bii
               + gamma * B**2 / 16 * (2 * B**2 + mu**2) * th_ii)
        ddii = (-a * dii + 2 * di - c3 / 6 * d0 + gamma * B**2 / 16 * (2 * B**2 - mu**2) * bi
                - (P**2 - 1) * bii + B**3 * mu / 3 * delta
                - gamma * B**2 / 16 * (2 * B**2 + 3 * mu**2) * th_i)
        return [d0, di, dii, dd0, ddi, ddii]

    def output(self, t, x):
        """Return y = [β0, βI, βII]."""
        return x[:, :3]


class WakeRHS:
    """docs/models.md §3.2: x = [βI, βI′, βII, βII′, λI, λII], p = [A, AL/τ, 1/τ], y = eq. 30."""

    n_params = 3

    def __init__(self, t0, omegadot):
        self.t0, self.omegadot = t0, omegadot

    def rhs(self, t, x, p):
        """x′ of the tilt modes with the two-parameter dynamic wake."""
        A, c, r = p
        k = P**2 - 1
        bi, di, bii, dii, li, lii = x
        th_i, th_ii = stirring(t, self.t0, self.omegadot)
        return [di,
                -k * bi - A * di - A * bii - 2 * dii + A * li + A * th_ii,
                dii,
                A * bi + 2 * di - k * bii - A * dii + A * lii - A * th_i,
                c * di + c * bii - (c + r) * li - c * th_ii,
                -c * bi + c * dii - (c + r) * lii + c * th_i]

    def output(self, t, x):
        """Return β_m1 = cos t βI + sin t βII, β_m2 = −sin t βI + cos t βII (eq. 30)."""
        c, s = np.cos(t), np.sin(t)
        return np.column_stack([c * x[:, 0] + s * x[:, 2], -s * x[:, 0] + c * x[:, 2]])


def afternoon_model(scenario):
    """Return the hand-written RHS of a report scenario (rotor_id.report.cases.Scenario)."""
    if scenario.model == 'single_blade':
        return SingleBladeRHS(scenario.t0, scenario.omegadot, scenario.advance_ratio)
    if scenario.model == 'multiblade_constant':
        return MultibladeConstantRHS(scenario.t0, scenario.omegadot, scenario.advance_ratio)
    if scenario.model == 'multiblade_wake':
        return WakeRHS(scenario.t0, scenario.omegadot)
    raise ValueError(f'no hand-written peer for model {scenario.model!r}')


def _split(theta, n_params, x0_fixed, free):
    x0 = np.array(x0_fixed, dtype=float)
    x0[free] = theta[n_params:]
    return theta[:n_params], x0


def fit_afternoon(rhs_model, t, y, sigma, theta_start, x0_fixed, free, rtol=1e-8, atol=1e-10):
    """
    Peer (a): solve_ivp (RK45) inside least_squares with its 2-point finite differences.

    θ = [model parameters, free initial states]; ``x0_fixed`` gives the other initial states.
    Returns (θ̂, scipy OptimizeResult).
    """
    def residuals(theta):
        p, x0 = _split(theta, rhs_model.n_params, x0_fixed, free)
        sol = solve_ivp(rhs_model.rhs, (t[0], t[-1]), x0, t_eval=t, args=(p,), rtol=rtol,
                        atol=atol)
        if not sol.success:
            return np.full(y.size, 1e6)
        return ((y - rhs_model.output(t, sol.y.T)) / sigma).ravel()

    res = least_squares(residuals, np.asarray(theta_start, dtype=float))
    return res.x, res


def fit_fd_ours(model, p_base, param_index, inputs, t, y, sigma, theta_start, x0_fixed, free):
    """
    Peer (b): our simulator (plain RK4, no sensitivities) inside least_squares with 2-point FD.

    Returns (θ̂, scipy OptimizeResult).
    """
    k = len(param_index)

    def residuals(theta):
        p = np.array(p_base, dtype=float)
        p[param_index] = theta[:k]
        x0 = np.array(x0_fixed, dtype=float)
        x0[free] = theta[k:]
        sim = simulate(model, p, inputs, t, x0)
        return ((y - sim.y) / sigma).ravel()

    res = least_squares(residuals, np.asarray(theta_start, dtype=float))
    return res.x, res
