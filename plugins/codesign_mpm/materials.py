"""Constitutive models known to the engine, with the numbers the time step depends on.

Each model has a small integer id used inside the kernels; a scene compiles only the models
its bodies use (see `Simulator`). Lamé parameters follow the usual isotropic relations.

Models beyond the elastic ones read a few extra per-particle parameters, packed into a
vector of `N_PARAMS` numbers whose meaning depends on the model (`pack_params`):

=========  ==========================================================================
sand       Drucker-Prager in Hencky strain (Klar et al. 2016): [alpha, cohesion]
snow       Stomakhin et al. 2013: [theta_c, theta_s, hardening xi, max stiffening]
clay       von Mises in Hencky strain: [yield stress]
mud        Bingham-like saturated soil (von Mises + viscosity): [yield stress, viscosity]
water      weakly compressible fluid: [bulk modulus, viscosity]
=========  ==========================================================================
"""
from __future__ import annotations

import math
from dataclasses import dataclass

N_PARAMS = 4
"""Per-particle parameters of the non-elastic models (see the module docstring)."""
MIN_HARDENING = 0.1
"""Snow: the hardening factor exp(xi (1 - J_p)) is kept in [MIN_HARDENING, max_hardening]."""


@dataclass(frozen=True)
class MaterialModel:
    id: int
    name: str
    description: str
    plastic: bool = False
    """True if the model changes F beyond (I + dt C) F (return mapping or fluid reset)."""


MATERIALS: dict[str, MaterialModel] = {
    m.name: m
    for m in (
        MaterialModel(0, "neo_hookean", "compressible neo-Hookean elastomer (no SVD; robots' default)"),
        MaterialModel(1, "corotated", "fixed-corotated elasticity (needs a polar decomposition)"),
        MaterialModel(2, "stvk", "St. Venant-Kirchhoff (Green strain; softens under strong compression)"),
        MaterialModel(3, "sand", "Drucker-Prager granular material in Hencky strain; no tension", True),
        MaterialModel(4, "snow", "Stomakhin snow: clamped principal stretches, hardening with compaction", True),
        MaterialModel(5, "clay", "von Mises elastoplastic (Hencky); permanent set above the yield stress", True),
        MaterialModel(6, "water", "weakly compressible fluid, pressure K (1 - J), optional viscosity", True),
        MaterialModel(7, "mud", "saturated soil: nearly incompressible, von Mises yield plus viscosity", True),
    )
}
ID = {name: m.id for name, m in MATERIALS.items()}


def material_names() -> list[str]:
    return sorted(MATERIALS)


def lame(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """(mu, lambda) from Young's modulus and Poisson's ratio."""
    mu = youngs_modulus / (2 * (1 + poisson_ratio))
    lam = youngs_modulus * poisson_ratio / ((1 + poisson_ratio) * (1 - 2 * poisson_ratio))
    return mu, lam


def drucker_prager_alpha(friction_angle_deg: float) -> float:
    """Cone slope alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) (Klar et al. 2016, eq. 27)."""
    s = math.sin(math.radians(friction_angle_deg))
    return math.sqrt(2 / 3) * 2 * s / (3 - s)


def pack_params(kind: str, friction_angle: float = 30.0, cohesion: float = 0.0, yield_stress: float = 200.0,
                critical_compression: float = 2.5e-2, critical_stretch: float = 7.5e-3, hardening: float = 10.0,
                max_hardening: float = 10.0, bulk_modulus: float = 1.0e5, viscosity: float = 0.0
                ) -> tuple[float, ...]:
    """The `N_PARAMS` per-particle numbers a model reads (zeros for elastic models)."""
    values: tuple[float, ...] = {
        "sand": (drucker_prager_alpha(friction_angle), cohesion),
        "snow": (critical_compression, critical_stretch, hardening, max_hardening),
        "clay": (yield_stress,),
        "mud": (yield_stress, viscosity),
        "water": (bulk_modulus, viscosity),
    }.get(kind, ())
    return values + (0.0,) * (N_PARAMS - len(values))


MUSCLE_MODELS = ("active", "energy")
"""How actuation a = u . r_p acts along the unit fibre f (Kirchhoff stress added to the body's):

- ``active`` (default; the released SoftZoo code, Genesis): tau += s a (F f)(F f)^T, linear in
  the action and force-free at a = 0; a > 0 is a tension along the fibre, so it contracts.
- ``energy`` (the paper's formula): the energy s (|F f|^2 - 1 + a)^2 gives
  tau += 4 s (|F f|^2 - 1 + a)(F f)(F f)^T, a passive fibre that also contracts for a > 0
  (its rest length is sqrt(1 - a)) and adds 8 s to the axial modulus.
"""


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


def wave_speed(youngs_modulus: float, poisson_ratio: float, density: float, added_modulus: float = 0.0) -> float:
    """Fastest elastic (P-)wave speed, sqrt((lambda + 2 mu + added) / rho); muscles add to the modulus."""
    mu, lam = lame(youngs_modulus, poisson_ratio)
    return math.sqrt((lam + 2 * mu + added_modulus) / density)


def model_wave_speed(model: int, youngs_modulus: float, poisson_ratio: float, density: float,
                     added_modulus: float, params: tuple[float, ...]) -> float:
    """Fastest wave speed a particle of this model can carry, for the CFL condition.

    Water: sqrt(K / rho) from its bulk modulus. Snow: the elastic speed at the largest
    hardening factor allowed (`max_hardening` scales both Lamé parameters).
    """
    if model == ID["water"]:
        return math.sqrt(params[0] / density)
    stiffening = max(params[3], 1.0) if model == ID["snow"] else 1.0
    return wave_speed(youngs_modulus * stiffening, poisson_ratio, density, added_modulus)


def viscosity(model: int, params: tuple[float, ...]) -> float:
    """Dynamic viscosity of a particle (0 for the models without a viscous term)."""
    return params[1] if model in (ID["water"], ID["mud"]) else 0.0
