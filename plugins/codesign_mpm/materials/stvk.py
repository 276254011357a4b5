"""St. Venant-Kirchhoff elasticity: S = 2 mu G + lambda tr(G) I in the Green strain
G = (F^T F - I) / 2; it softens under strong compression. Taichi differentiates it."""
from codesign_mpm.materials.base import MaterialModel, func, ti


@func
def stress(F, mu, la):
    """Kirchhoff stress tau = F S F^T."""
    I = ti.Matrix.identity(float, 3)
    G = 0.5 * (F.transpose() @ F - I)
    return F @ (2.0 * mu * G + la * G.trace() * I) @ F.transpose()


MODEL = MaterialModel("stvk", "St. Venant-Kirchhoff (Green strain; softens under strong compression)", stress=stress)
