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
from codesign_mpm.materials.admissible import MAX_ACTIVE_STRESS_RATIO, active_stress_ratio, max_stiffness_ratio  # noqa: F401
from codesign_mpm.materials.base import func

MUSCLE_MODELS = ("active", "energy")


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
