"""Muscle: the active stress a muscle adds to its body's (any elastic or plastic model), and the
numbers that bound it.

How actuation a = u . r_p acts along the unit fibre f (Kirchhoff stress added to the body's), for
the scene's `muscle_model`:

- ``active`` (default; the released SoftZoo code, Genesis): tau += s a (F f)(F f)^T, linear in
  the action and force-free at a = 0; a > 0 is a tension along the fibre, so it contracts.
- ``energy`` (the paper's formula): the energy s (|F f|^2 - 1 + a)^2 gives
  tau += 4 s (|F f|^2 - 1 + a)(F f)(F f)^T, a passive fibre that also contracts for a > 0
  (its rest length is sqrt(1 - a)) and adds 8 s to the axial modulus.
"""
from codesign_mpm.materials.base import func

MUSCLE_MODELS = ("active", "energy")


MAX_ACTIVE_STRESS_RATIO = 0.3
"""Admissible active muscles: s * max_action <= this times the shear modulus mu.

A fibre driven at -max_action carries a compressive stress s a (F f)(F f)^T that grows with its
stretch as fast as the neo-Hookean shear stress mu (F F^T - I) resists it: uniaxially the fibre
settles at a stretch of 1 / sqrt(1 - s |a| / mu), and at s |a| = mu it has no equilibrium at all.
Measured with a 4-muscle box driven bang-bang at the bound for 250 frames on frictional ground
(dx 1/32 to 1/96, float32): at 0.72 (stiffness_ratio 1, the old default) it inverted, tore off
2-8% of its mass and blew up; at 0.5, 1.7% tore off at dx 1/48; at 0.3 and below nothing tore
at any dx and min J stayed above 0.3. At 0.3 a fibre stretches by at most 20% and shortens
by 12%: ample for a gait."""


def active_stress_ratio(stiffness_ratio: float, max_action: float, poisson_ratio: float) -> float:
    """s * max_action / mu for a muscle of stiffness s = stiffness_ratio * E (mu = E / (2 (1 + nu)))."""
    return max_action * stiffness_ratio * 2.0 * (1.0 + poisson_ratio)


def max_stiffness_ratio(max_action: float, poisson_ratio: float) -> float:
    """The largest admissible muscle stiffness_ratio (`MAX_ACTIVE_STRESS_RATIO`)."""
    return MAX_ACTIVE_STRESS_RATIO / (max_action * 2.0 * (1.0 + poisson_ratio))


def muscle_modulus(model: str, stiffness: float, max_action: float) -> float:
    """Largest axial tangent modulus a muscle of stiffness s adds, for the CFL condition.

    Active: tau = s a (F f)(F f)^T stiffens the fibre by 2 s a, at most 2 s max_action.
    Energy: the second derivative of s (|F f|^2 - 1 + a)^2 in the fibre stretch, 8 s at rest.
    """
    return 2.0 * stiffness * max_action if model == "active" else 8.0 * stiffness


@func
def active_stress(u, a, s):
    """tau = s a u u^T with u = F f the stretched fibre, a the activation, s the stiffness."""
    return s * a * u.outer_product(u)


@func
def energy_stress(u, a, s):
    """tau = 4 s (|u|^2 - 1 + a) u u^T."""
    return 4.0 * s * (u.dot(u) - 1.0 + a) * u.outer_product(u)


@func
def active_adjoint(u, a, s, tau_bar):
    """(u's, a's, s's gradients) from the stress's T = tau_bar: u: s a (T + T^T) u, a: s u.T u,
    s: a u.T u."""
    q = u.dot(tau_bar @ u)
    sym_u = (tau_bar + tau_bar.transpose()) @ u
    return s * a * sym_u, s * q, a * q


@func
def energy_adjoint(u, a, s, tau_bar):
    """With c = |u|^2 - 1 + a: u: 4 s (c (T + T^T) u + 2 (u.T u) u), a: 4 s u.T u, s: 4 c u.T u."""
    q = u.dot(tau_bar @ u)
    sym_u = (tau_bar + tau_bar.transpose()) @ u
    c = u.dot(u) - 1.0 + a
    return 4.0 * s * (c * sym_u + 2.0 * q * u), 4.0 * s * q, 4.0 * c * q


STRESS = {"active": active_stress, "energy": energy_stress}
ADJOINT = {"active": active_adjoint, "energy": energy_adjoint}
