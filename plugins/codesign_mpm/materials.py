"""Constitutive models known to the engine, with the numbers the time step depends on.

Each model has a small integer id used inside the kernels; a scene compiles only the models
its bodies use (see `Simulator`). Lamé parameters follow the usual isotropic relations.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class MaterialModel:
    id: int
    name: str
    description: str


MATERIALS: dict[str, MaterialModel] = {
    m.name: m
    for m in (
        MaterialModel(0, "neo_hookean", "compressible neo-Hookean elastomer (no SVD; robots' default)"),
        MaterialModel(1, "corotated", "fixed-corotated elasticity (needs a polar decomposition)"),
        MaterialModel(2, "stvk", "St. Venant-Kirchhoff (Green strain; softens under strong compression)"),
    )
}


def material_names() -> list[str]:
    return sorted(MATERIALS)


def lame(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """(mu, lambda) from Young's modulus and Poisson's ratio."""
    mu = youngs_modulus / (2 * (1 + poisson_ratio))
    lam = youngs_modulus * poisson_ratio / ((1 + poisson_ratio) * (1 - 2 * poisson_ratio))
    return mu, lam


def wave_speed(youngs_modulus: float, poisson_ratio: float, density: float,
               muscle_stiffness: float = 0.0) -> float:
    """Fastest elastic (P-)wave speed, sqrt((lambda + 2 mu + 8 s) / rho).

    The muscle energy s (|Ff|^2 - 1 - a)^2 adds 8 s to the axial modulus at rest (second
    derivative in the fibre stretch), so actuated bodies need a proportionally smaller step.
    """
    mu, lam = lame(youngs_modulus, poisson_ratio)
    return math.sqrt((lam + 2 * mu + 8 * muscle_stiffness) / density)
