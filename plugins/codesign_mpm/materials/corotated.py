"""Fixed-corotated elasticity (Stomakhin et al. 2012): tau = 2 mu (F - R) F^T + lambda (J - 1) J I,
with R the rotation of F's polar decomposition. Forward only: Taichi has no reverse mode of
its polar decomposition."""
from codesign_mpm.materials.base import MaterialModel, func, ti


@func
def stress(F, mu, la):
    """Kirchhoff stress tau = P F^T."""
    I = ti.Matrix.identity(float, 3)
    J = F.determinant()
    R, _ = ti.polar_decompose(F)
    return 2.0 * mu * (F - R) @ F.transpose() + la * (J - 1.0) * J * I


MODEL = MaterialModel("corotated", "fixed-corotated elasticity (needs a polar decomposition)", stress=stress,
                      differentiable=False)
