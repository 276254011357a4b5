"""Snow (Stomakhin et al. 2013): principal stretches clamped to [1 - theta_c, 1 + theta_s], the
rest plastic; both moduli hardened by exp(xi (1 - J_p)) with the plastic volume ratio J_p (state).
Parameter vector: [theta_c, theta_s, hardening xi, max stiffening]."""
from codesign_mpm.materials.base import MaterialModel, Parameter, elastic_wave_speed, func, ti

MIN_HARDENING = 0.1
"""The hardening factor exp(xi (1 - J_p)) is kept in [MIN_HARDENING, max_hardening]."""


@func
def return_map(eps, tr, dev, n2, prm, mu, la):
    """(eps_new, alpha): the principal Hencky strains clamped to the stretch bounds."""
    eps_new = ti.min(ti.max(eps, ti.log(1.0 - prm[0])), ti.log(1.0 + prm[1]))
    return eps_new, 1.0


@func
def projection_slope(eps, eps_new, scale, a):
    """(inside, the projection's scale's slope in a): a clamped stretch's scale has the slope
    -scale / (2 a), an unclamped one none."""
    inside = ti.cast(eps == eps_new, float)
    return inside, -(1.0 - inside) * scale / (2.0 * a)


@func
def principal_stress(eps_new, inside, jp, prm, mu, la):
    """(k, k_slope): neo-Hookean in the clamped stretches (F_new F_new^T has the eigenvalues
    exp(2 eps_new)) with both moduli hardened by exp(xi (1 - J_p)), the hardening bounded to keep
    the wave speed (and so the time step) and the gradients bounded."""
    h = ti.min(ti.max(ti.exp(prm[2] * (1.0 - jp)), MIN_HARDENING), prm[3])
    k = h * (mu * (ti.exp(2.0 * eps_new) - 1.0) + la * eps_new.sum())
    k_slope = h * mu * inside
    return k, k_slope


def wave_speed(youngs_modulus, poisson_ratio, density, added_modulus, params) -> float:
    """The elastic speed at the largest hardening factor allowed (it scales both Lame parameters)."""
    return elastic_wave_speed(youngs_modulus * max(params[3], 1.0), poisson_ratio, density, added_modulus)


MODEL = MaterialModel(
    "snow", "Stomakhin snow: clamped principal stretches, hardening with compaction", kind="hencky",
    parameters=(Parameter("critical_compression", 2.5e-2, lambda v: 0 < v < 1, "must be in (0, 1)",
                          "theta_c: principal stretches stay >= 1 - theta_c"),
                Parameter("critical_stretch", 7.5e-3, lambda v: v > 0, "must be > 0",
                          "theta_s: principal stretches stay <= 1 + theta_s"),
                Parameter("hardening", 10.0, lambda v: v >= 0, "must be >= 0",
                          "xi: stiffness grows as exp(xi (1 - J_p)) with compaction"),
                Parameter("max_hardening", 10.0, lambda v: 1 <= v <= 100, "must be in [1, 100]",
                          "bound on that factor (keeps the step and gradients bounded)")),
    wave_speed=wave_speed, return_map=return_map, projection_slope=projection_slope,
    principal_stress=principal_stress, plastic_volume=True)
