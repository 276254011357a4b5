"""Clay: von Mises plasticity in principal Hencky strain; permanent set above the yield stress.

|dev tau| = 2 mu |dev eps| <= sqrt(2/3) yield stress. Parameter vector: [yield stress]."""
from codesign_mpm.materials.base import MaterialModel, Parameter, func, ti

YIELD_STRESS = Parameter("yield_stress", 200.0, lambda v: v > 0, "must be > 0",
                         "von Mises yield stress (mud: undrained shear strength)")


@func
def return_map(eps, tr, dev, n2, prm, mu, la):
    """(eps_new, alpha): the trial strain's deviator scaled back onto the yield surface, if outside.
    Branch-free (masks select the case): Taichi's reverse mode turns locals assigned in branches
    into stacks."""
    radius = ti.sqrt(2.0 / 3.0) * prm[0] / (2.0 * mu)
    outside = ti.cast(n2 > radius * radius, float)
    shrink = radius / ti.sqrt(ti.max(n2, radius * radius))
    eps_new = eps + outside * (tr / 3.0 + shrink * dev - eps)
    alpha = 1.0 + outside * (shrink - 1.0)
    return eps_new, alpha


MODEL = MaterialModel("clay", "von Mises elastoplastic (Hencky); permanent set above the yield stress", kind="hencky",
                      parameters=(YIELD_STRESS,), return_map=return_map)
