"""Water: a weakly compressible fluid, Cauchy pressure K (1 - J), optional Newtonian viscosity.
Only J is state: F is reset to the isotropic J^(1/3) I (shear would otherwise accumulate without
any stress). Parameter vector: [bulk modulus K, viscosity]."""
import math

from codesign_mpm.materials.base import MaterialModel, Parameter, func, ti
from codesign_mpm.materials.mud import VISCOSITY
from codesign_mpm.materials.neo_hookean import J_MIN


@func
def update(F, prm):
    """(F to store, Kirchhoff stress J K (J - 1) I)."""
    J = F.determinant()
    tau = prm[0] * J * (J - 1.0) * ti.Matrix.identity(float, 3)
    F_new = ti.exp(ti.log(ti.max(J, J_MIN)) / 3.0) * ti.Matrix.identity(float, 3)
    return F_new, tau


def wave_speed(youngs_modulus, poisson_ratio, density, added_modulus, params) -> float:
    """The sound speed sqrt(K / rho) from the bulk modulus (E and nu do not enter)."""
    return math.sqrt(params[0] / density)


MODEL = MaterialModel(
    "water", "weakly compressible fluid, pressure K (1 - J), optional viscosity", kind="fluid",
    parameters=(Parameter("bulk_modulus", 1.0e5, lambda v: v > 0, "must be > 0",
                          "K: pressure K (1 - J); sound speed sqrt(K / rho)"), VISCOSITY),
    viscosity_index=1, wave_speed=wave_speed, update=update)
