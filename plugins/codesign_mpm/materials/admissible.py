"""Admissible ranges that involve several recipe keys, checked when a recipe is read (`codesign
show`, `run`, `sweep`, `study`) as well as when a simulator is built; free of Taichi, so reading a
recipe stays light."""
from __future__ import annotations


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
