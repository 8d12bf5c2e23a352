"""
The report's three flapping models transcribed entry by entry, as the report printed them.

This is the reference the general :class:`rotor_id.physics.models.RotorModel` is checked against
(test_rotor_model.py): an independent transcription of report Ch.3 eq. 24 (corrected), the
four-blade multiblade matrices (docs/models.md §2.1) and Ch.2 eq. 29 (docs/models.md §3.2). It is
test code only; the library builds every model from the one blade equation.
"""

from dataclasses import replace
import math

import numpy as np

from rotor_id.physics.models import (_collective_parameter, GAMMA, LinearModel, Parameter,
                                     RotorConstants)
from rotor_id.physics.multiblade import blade_azimuths

# ------------------------------------------------------------------------------------------------
# Models 1 and 2: second-order flapping with parameters (γ, δ = γθ0) or (γ, θ0)
# ------------------------------------------------------------------------------------------------


class _SecondOrderGammaModel(LinearModel):
    """
    Flapping q″ + D q′ + K q = f with D, K, f affine in γ and δ (models 1 and 2).

    Subclasses return, at times t, the pieces ``D = D0 + γ D1``, ``K = K0 + γ K1`` and
    ``f = δ f_δ + γ f_u`` from :meth:`_pieces`. With the θ0 parametrisation δ = γθ0 and the
    chain rule gives the derivatives.
    """

    def __init__(self, rotor, collective='theta0', angle_unit='rad'):
        self.rotor = rotor
        self.collective = collective
        gamma = GAMMA
        coll = _collective_parameter(collective)
        if collective == 'theta0' and angle_unit == 'rad':
            coll = replace(coll, nominal=math.radians(2.0), lower=-math.pi / 4,
                           upper=math.pi / 4, unit='rad')
        elif collective == 'delta' and angle_unit == 'rad':
            coll = replace(coll, nominal=10.0 * math.pi / 180.0, lower=-4.0, upper=4.0,
                           unit='rad')
        else:
            coll = replace(coll, unit='deg')
        self.parameters = (gamma, coll)

    def _gamma_delta(self, p):
        gamma = p[0]
        delta = p[1] if self.collective == 'delta' else gamma * p[1]
        return gamma, delta

    def _pieces(self, t, u):
        raise NotImplementedError

    def system(self, t, p, u):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        gamma, delta = self._gamma_delta(p)
        D0, D1, K0, K1, f_delta, f_u = self._pieces(t, u)
        nq = D0.shape[1]
        F = np.zeros((t.size, 2 * nq, 2 * nq))
        F[:, :nq, nq:] = np.eye(nq)
        F[:, nq:, :nq] = -(K0 + gamma * K1)
        F[:, nq:, nq:] = -(D0 + gamma * D1)
        g = np.zeros((t.size, 2 * nq))
        g[:, nq:] = delta * f_delta + gamma * f_u
        return F, g

    def system_jacobian(self, t, p, u):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        gamma, delta = self._gamma_delta(p)
        D0, D1, K0, K1, f_delta, f_u = self._pieces(t, u)
        nq = D0.shape[1]
        dF = np.zeros((t.size, 2, 2 * nq, 2 * nq))
        dF[:, 0, nq:, :nq] = -K1
        dF[:, 0, nq:, nq:] = -D1
        dg = np.zeros((t.size, 2, 2 * nq))
        if self.collective == 'delta':
            dg[:, 0, nq:] = f_u
            dg[:, 1, nq:] = f_delta
        else:                                   # δ = γθ0
            dg[:, 0, nq:] = f_u + p[1] * f_delta
            dg[:, 1, nq:] = gamma * f_delta
        return dF, dg


class SingleBlade(_SecondOrderGammaModel):
    """
    Model 1: one rigid centrally hinged blade with periodic coefficients (docs/models.md §1.1).

    Corrected Ch.3 eq. 24:  β″ + (γ/2) C β′ + [P² + (γ/2) K] β = (γ/2) m_θ θ

        C   = B⁴/4 + (B³μ/3) sin ψ
        K   = (B³μ/3) cos ψ + (B²μ²/4) sin 2ψ
        m_θ = (B⁴ + B²μ²)/4 + (2/3) B³μ sin ψ − (B²μ²/4) cos 2ψ

    ψ = t + ``blade_offset`` is the azimuth of the modelled blade; θ = θ0 + θ_c with the cyclic
    part θ_c = −θI sin ψ + θII cos ψ (eq. 3). States x = [β, β′], output y = β.
    """

    name = 'single_blade'
    state_names = ('beta', 'beta_dot')
    output_names = ('beta',)

    def __init__(self, rotor=RotorConstants(), collective='theta0', angle_unit='rad',
                 blade=1):
        super().__init__(rotor, collective, angle_unit)
        self.blade = blade
        self.blade_offset = 2.0 * math.pi * (blade - 1) / rotor.n_blades
        self.output_names = (f'beta_{blade}',)

    def _pieces(self, t, u):
        B, mu, P = self.rotor.tip_loss, self.rotor.advance_ratio, self.rotor.flap_frequency
        psi = t + self.blade_offset
        s1, c1, s2, c2 = np.sin(psi), np.cos(psi), np.sin(2 * psi), np.cos(2 * psi)
        damping = B**4 / 4 + (B**3 * mu / 3) * s1                               # C(t)
        stiffness = (B**3 * mu / 3) * c1 + (B**2 * mu**2 / 4) * s2              # K(t)
        m_theta = ((B**4 + B**2 * mu**2) / 4 + (2.0 / 3.0) * B**3 * mu * s1
                   - (B**2 * mu**2 / 4) * c2)                                   # m_θ(t)
        u = np.asarray(u, dtype=float)
        theta_cyclic = -u[:, 1] * s1 + u[:, 2] * c1
        one = np.ones((t.size, 1, 1))
        return (0.0 * one, 0.5 * damping[:, None, None], P**2 * one,
                0.5 * stiffness[:, None, None], 0.5 * m_theta[:, None],
                (0.5 * m_theta * theta_cyclic)[:, None])

    def output_matrix(self, t):
        H = np.zeros((np.size(t), 1, 2))
        H[:, 0, 0] = 1.0
        return H

    def observe_blades(self, t, blade_flap):
        return np.asarray(blade_flap, dtype=float)[:, self.blade - 1:self.blade]


class Multiblade(_SecondOrderGammaModel):
    """
    Model 2: four blades in multiblade coordinates, μ > 0, periodic coefficients (§2.1).

    q = [β0, βI, βII, βd], x = [q, q′]; q″ + D(t) q′ + K(t) q = f(t) with D, K, f as printed in
    docs/models.md §2.1 (a = γB⁴/8, b3 = γB³μ, b2 = γB²μ²). ``outputs='multiblade'`` measures
    [β0, βI, βII, βd]; ``outputs='blades'`` measures each blade, β_k = β0 + βI cos ψ_k +
    βII sin ψ_k + (−1)^k βd.
    """

    name = 'multiblade'
    state_names = ('beta_0', 'beta_I', 'beta_II', 'beta_d',
                   'beta_0_dot', 'beta_I_dot', 'beta_II_dot', 'beta_d_dot')

    def __init__(self, rotor=RotorConstants(), collective='theta0', angle_unit='rad',
                 outputs='multiblade'):
        if rotor.n_blades != 4:
            raise ValueError('the multiblade model is written for 4 blades '
                             f'(got {rotor.n_blades}); use single_blade for other rotors')
        super().__init__(rotor, collective, angle_unit)
        self.outputs = outputs
        if outputs == 'multiblade':
            self.output_names = ('beta_0', 'beta_I', 'beta_II', 'beta_d')
        elif outputs == 'blades':
            self.output_names = tuple(f'beta_{k}' for k in range(1, 5))
        else:
            raise ValueError(f"outputs must be 'multiblade' or 'blades', not {outputs!r}")

    def _pieces(self, t, u):
        B, mu, P = self.rotor.tip_loss, self.rotor.advance_ratio, self.rotor.flap_frequency
        s2, c2, s4, c4 = np.sin(2 * t), np.cos(2 * t), np.sin(4 * t), np.cos(4 * t)
        T = t.size
        u = np.asarray(u, dtype=float)
        th_i, th_ii = u[:, 1], u[:, 2]
        a1 = B**4 / 8          # a / γ
        b3 = B**3 * mu         # b3 / γ
        b2 = B**2 * mu**2      # b2 / γ
        g16 = B**2 / 16        # (γB²/16) / γ
        D0 = np.zeros((T, 4, 4))
        D0[:, 1, 2], D0[:, 2, 1] = 2.0, -2.0
        D1 = np.zeros((T, 4, 4))
        D1[:, [0, 1, 2, 3], [0, 1, 2, 3]] = a1
        D1[:, 0, 2] = b3 / 12
        D1[:, 1, 3] = -(b3 / 6) * s2
        D1[:, 2, 0] = b3 / 6
        D1[:, 2, 3] = (b3 / 6) * c2
        D1[:, 3, 1] = -(b3 / 12) * s2
        D1[:, 3, 2] = (b3 / 12) * c2
        K0 = np.zeros((T, 4, 4))
        K0[:, [0, 1, 2, 3], [0, 1, 2, 3]] = [P**2, P**2 - 1, P**2 - 1, P**2]
        K1 = np.zeros((T, 4, 4))
        K1[:, 0, 3] = -(b2 / 8) * s2
        K1[:, 1, 0] = b3 / 6
        K1[:, 1, 1] = (b2 / 16) * s4
        K1[:, 1, 2] = g16 * (2 * B**2 + mu**2 - mu**2 * c4)
        K1[:, 1, 3] = -(b3 / 6) * c2
        K1[:, 2, 1] = -g16 * (2 * B**2 - mu**2 + mu**2 * c4)
        K1[:, 2, 2] = -(b2 / 16) * s4
        K1[:, 2, 3] = -(b3 / 6) * s2
        K1[:, 3, 0] = -(b2 / 8) * s2
        K1[:, 3, 1] = -(b3 / 6) * c2
        K1[:, 3, 2] = -(b3 / 6) * s2
        f_delta = np.column_stack([np.full(T, (B**2 / 8) * (B**2 + mu**2)), np.zeros(T),
                                   np.full(T, B**3 * mu / 3), (B**2 * mu**2 / 8) * c2])
        f_u = np.column_stack([
            -(b3 / 6) * th_i,
            (b2 / 16) * s4 * th_i + g16 * (2 * B**2 + mu**2 - mu**2 * c4) * th_ii,
            -g16 * (2 * B**2 + 3 * mu**2 + mu**2 * c4) * th_i - (b2 / 16) * s4 * th_ii,
            -(b3 / 6) * (c2 * th_i + s2 * th_ii)])
        return D0, D1, K0, K1, f_delta, f_u

    def output_matrix(self, t):
        T = np.size(t)
        if self.outputs == 'multiblade':
            H = np.zeros((T, 4, 8))
            H[:, [0, 1, 2, 3], [0, 1, 2, 3]] = 1.0
            return H
        psi = blade_azimuths(t, 4)
        H = np.zeros((T, 4, 8))
        H[:, :, 0] = 1.0
        H[:, :, 1] = np.cos(psi)
        H[:, :, 2] = np.sin(psi)
        H[:, :, 3] = (-1.0) ** np.arange(1, 5)
        return H

    def observe_blades(self, t, blade_flap):
        blade_flap = np.asarray(blade_flap, dtype=float)
        if self.outputs == 'blades':
            return blade_flap
        raise NotImplementedError


class MultibladeConstant(_SecondOrderGammaModel):
    """
    Model 2 with all periodic terms omitted; βd decouples and is dropped (docs/models.md §2.2).

    x = [β0, βI, βII, β0′, βI′, βII′]; y = [β0, βI, βII]. Time-invariant.
    """

    name = 'multiblade_constant'
    state_names = ('beta_0', 'beta_I', 'beta_II', 'beta_0_dot', 'beta_I_dot', 'beta_II_dot')
    output_names = ('beta_0', 'beta_I', 'beta_II')
    time_invariant = True

    def __init__(self, rotor=RotorConstants(), collective='theta0', angle_unit='rad'):
        if rotor.n_blades != 4:
            raise ValueError('the multiblade model is written for 4 blades '
                             f'(got {rotor.n_blades}); use single_blade for other rotors')
        super().__init__(rotor, collective, angle_unit)

    def _pieces(self, t, u):
        B, mu, P = self.rotor.tip_loss, self.rotor.advance_ratio, self.rotor.flap_frequency
        T = t.size
        u = np.asarray(u, dtype=float)
        th_i, th_ii = u[:, 1], u[:, 2]
        a1, b3, g16 = B**4 / 8, B**3 * mu, B**2 / 16
        D0 = np.zeros((T, 3, 3))
        D0[:, 1, 2], D0[:, 2, 1] = 2.0, -2.0
        D1 = np.zeros((T, 3, 3))
        D1[:, [0, 1, 2], [0, 1, 2]] = a1
        D1[:, 0, 2] = b3 / 12
        D1[:, 2, 0] = b3 / 6
        K0 = np.zeros((T, 3, 3))
        K0[:, [0, 1, 2], [0, 1, 2]] = [P**2, P**2 - 1, P**2 - 1]
        K1 = np.zeros((T, 3, 3))
        K1[:, 1, 0] = b3 / 6
        K1[:, 1, 2] = g16 * (2 * B**2 + mu**2)
        K1[:, 2, 1] = -g16 * (2 * B**2 - mu**2)
        f_delta = np.tile([(B**2 / 8) * (B**2 + mu**2), 0.0, B**3 * mu / 3], (T, 1))
        f_u = np.column_stack([-(b3 / 6) * th_i, g16 * (2 * B**2 + mu**2) * th_ii,
                               -g16 * (2 * B**2 + 3 * mu**2) * th_i])
        return D0, D1, K0, K1, f_delta, f_u

    def output_matrix(self, t):
        H = np.zeros((np.size(t), 3, 6))
        H[:, [0, 1, 2], [0, 1, 2]] = 1.0
        return H

    def observe_blades(self, t, blade_flap):
        raise NotImplementedError


class MultibladeWake(LinearModel):
    """
    Model 3: μ = 0 tilt modes with the two-parameter dynamic wake (docs/models.md §3, Ch.2 eq. 29).

    x = [βI, βI′, βII, βII′, λI, λII], p = [A, AL/τ, 1/τ] with A = γB⁴/8 (Ch.2 eq. 27); λ is the
    report's inflow sign (up positive). Output (Ch.2 eq. 30): β_m1 = (β1 − β3)/2 =
    cos t βI + sin t βII and β_m2 = (β2 − β4)/2 = −sin t βI + cos t βII.
    """

    name = 'multiblade_wake'
    state_names = ('beta_I', 'beta_I_dot', 'beta_II', 'beta_II_dot', 'lambda_I', 'lambda_II')
    output_names = ('beta_m1', 'beta_m2')
    time_invariant = True

    def __init__(self, rotor=RotorConstants(advance_ratio=0.0)):
        if rotor.n_blades != 4:
            raise ValueError(f'the wake model is written for 4 blades (got {rotor.n_blades})')
        if rotor.advance_ratio != 0.0:
            raise ValueError('the wake model holds at advance ratio 0 only '
                             f'(got mu = {rotor.advance_ratio})')
        self.rotor = rotor
        self.parameters = (
            Parameter('A', 'A = γB⁴/8', '-', 0.5, 1e-3, 10.0, 'flap damping (Ch.2 eq. 27)'),
            Parameter('AL_over_tau', 'AL/τ', '-', 0.25, 0.0, 50.0,
                      'wake gain over wake time constant'),
            Parameter('inv_tau', '1/τ', '-', 0.125, 1e-4, 50.0, 'inverse wake time constant'),
        )

    def system(self, t, p, u):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        A, c, r = p
        k = self.rotor.flap_frequency**2 - 1.0
        u = np.asarray(u, dtype=float)
        th_i, th_ii = u[:, 1], u[:, 2]
        F1 = np.array([[0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
                       [-k, -A, -A, -2.0, A, 0.0],
                       [0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
                       [A, 2.0, -k, -A, 0.0, A],
                       [0.0, c, c, 0.0, -(c + r), 0.0],
                       [-c, 0.0, 0.0, c, 0.0, -(c + r)]])
        F = np.broadcast_to(F1, (t.size, 6, 6)).copy()
        zero = np.zeros(t.size)
        g = np.column_stack([zero, A * th_ii, zero, -A * th_i, -c * th_ii, c * th_i])
        return F, g

    def system_jacobian(self, t, p, u):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        u = np.asarray(u, dtype=float)
        th_i, th_ii = u[:, 1], u[:, 2]
        dF1 = np.zeros((3, 6, 6))
        dF1[0, 1, [1, 2, 4]] = [-1.0, -1.0, 1.0]             # ∂/∂A
        dF1[0, 3, [0, 3, 5]] = [1.0, -1.0, 1.0]
        dF1[1, 4, [1, 2, 4]] = [1.0, 1.0, -1.0]              # ∂/∂(AL/τ)
        dF1[1, 5, [0, 3, 5]] = [-1.0, 1.0, -1.0]
        dF1[2, 4, 4] = dF1[2, 5, 5] = -1.0                   # ∂/∂(1/τ)
        dF = np.broadcast_to(dF1, (t.size, 3, 6, 6)).copy()
        dg = np.zeros((t.size, 3, 6))
        dg[:, 0, 1], dg[:, 0, 3] = th_ii, -th_i
        dg[:, 1, 4], dg[:, 1, 5] = -th_ii, th_i
        return dF, dg

    def output_matrix(self, t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        H = np.zeros((t.size, 2, 6))
        H[:, 0, 0], H[:, 0, 2] = np.cos(t), np.sin(t)
        H[:, 1, 0], H[:, 1, 2] = -np.sin(t), np.cos(t)
        return H

    def observe_blades(self, t, blade_flap):
        blade_flap = np.asarray(blade_flap, dtype=float)
        return np.column_stack([(blade_flap[:, 0] - blade_flap[:, 2]) / 2,
                                (blade_flap[:, 1] - blade_flap[:, 3]) / 2])
