"""A material model from a plugin: compressible Mooney-Rivlin elasticity (a toy, for docs/plugins.md).

W = c1 (I1 - 3) + c2 (I2 - 3) - (2 c1 + 4 c2) log J + lambda log(J)^2 / 2 in b = F F^T, with
c1 = mu (1 - r) / 2 and c2 = mu r / 2 so that the shear modulus is mu whatever the Mooney ratio r
(r = 0 is neo-Hookean). Its Kirchhoff stress, stress-free at F = I:

    tau = mu (1 - r) b + mu r (I1 b - b^2) - mu (1 + r) I + lambda log(J) I

Taichi's reverse mode differentiates it (no `stress_adjoint`). Scenes use it as
`material: {kind: mooney_rivlin, parameters: {mooney_ratio: 0.3}}`.
"""
import math

from codesign_mpm.materials import MaterialModel, Parameter, func, lame, ti


@func
def stress(F, mu, la, prm):
    """Kirchhoff stress tau = P F^T; prm[0] is the Mooney ratio r."""
    r = prm[0]
    I = ti.Matrix.identity(float, 3)
    b = F @ F.transpose()
    J = F.determinant()
    return (mu * (1.0 - r)) * b + (mu * r) * (b.trace() * b - b @ b) - (mu * (1.0 + r)) * I \
        + la * ti.log(ti.max(J, 1e-6)) * I


def wave_speed(youngs_modulus, poisson_ratio, density, added_modulus, params) -> float:
    """At rest the model is linear elastic with mu and lambda + 2 mu r: P-waves at
    sqrt((lambda + 2 mu (1 + r) + added) / rho)."""
    mu, la = lame(youngs_modulus, poisson_ratio)
    return math.sqrt((la + 2.0 * mu * (1.0 + params[0]) + added_modulus) / density)


MODEL = MaterialModel(
    "mooney_rivlin", "compressible Mooney-Rivlin elastomer (example plugin)",
    parameters=(Parameter("mooney_ratio", 0.3, lambda r: 0 <= r < 1, "must be in [0, 1)",
                          "r = c2 / (c1 + c2): the share of the shear modulus from the second invariant"),),
    stress=stress, wave_speed=wave_speed)
