"""Sand: Drucker-Prager plasticity in principal Hencky strain (Klar et al. 2016); no tension.

|dev tau| <= -alpha tr(tau) around the apex set by the cohesion; expansion beyond the apex loses
all elastic strain. Parameter vector: [alpha, cohesion] (alpha from the friction angle)."""
import math

from codesign_mpm.materials.base import MaterialModel, Parameter, func, ti

NORM_FLOOR = 1e-30  # |dev eps|^2 below this is treated as this (only reached where the result is masked off)


def drucker_prager_alpha(friction_angle_deg: float) -> float:
    """Cone slope alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) (Klar et al. 2016, eq. 27)."""
    s = math.sin(math.radians(friction_angle_deg))
    return math.sqrt(2 / 3) * 2 * s / (3 - s)


@func
def return_map(eps, tr, dev, n2, prm, mu, la):
    """(eps_new, alpha): the trial strain projected onto the cone, or to its apex."""
    tip = 3.0 * prm[1] / (3.0 * la + 2.0 * mu)  # tr(eps) at the apex
    slope = prm[0] * (3.0 * la + 2.0 * mu) / (2.0 * mu)
    apex = ti.cast(tr > tip, float)
    cone = (1.0 - apex) * ti.cast(n2 > (slope * (tip - tr)) ** 2, float)
    shrink = slope * (tip - tr) / ti.sqrt(ti.max(n2, NORM_FLOOR))
    eps_new = eps + apex * (tip / 3.0 - eps) + cone * (tr / 3.0 + shrink * dev - eps)
    alpha = 1.0 - apex + cone * (shrink - 1.0)
    return eps_new, alpha


MODEL = MaterialModel(
    "sand", "Drucker-Prager granular material in Hencky strain; no tension", kind="hencky",
    parameters=(Parameter("friction_angle", 30.0, lambda v: 0 <= v <= 80, "must be in [0, 80] degrees",
                          "Drucker-Prager friction angle, degrees"),
                Parameter("cohesion", 0.0, lambda v: v >= 0, "must be >= 0",
                          "tensile strength (mean Kirchhoff stress at the cone apex)")),
    pack=lambda v: (drucker_prager_alpha(v["friction_angle"]), v["cohesion"]),
    return_map=return_map)
