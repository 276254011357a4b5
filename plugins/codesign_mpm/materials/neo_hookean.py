"""Compressible neo-Hookean elasticity: the robots' default, the one model without an SVD.

tau = mu (F F^T - I) + lambda J psi'(J) I with psi = log(J)^2 / 2; below J_MIN psi continues as
its quadratic Taylor polynomial, so J psi'(J) turns tensile for J < 0 and an inverted element
is pulled back through J = 0 instead of pushed further. Its adjoint is written by hand (Taichi's
reverse mode of the robots' most common kernel compiled far slower)."""
import numpy as np

from codesign_mpm.materials.base import MaterialModel, cofactor, func, ti

J_MIN = 0.1  # below this, neo-Hookean log(J) continues linearly (finite for J <= 0)


@func
def volumetric(J):
    """psi'(J) with psi = log(J)^2 / 2, continued below J_MIN by its quadratic Taylor polynomial,
    and the derivative of h(J) = J psi'(J) for the adjoint."""
    slope = (1.0 - ti.log(J_MIN)) / J_MIN ** 2
    dpsi = ti.log(ti.max(J, J_MIN)) / ti.max(J, J_MIN) + slope * ti.min(J - J_MIN, 0.0)
    dh = ti.select(J > J_MIN, 1.0 / ti.max(J, J_MIN), ti.log(J_MIN) / J_MIN + slope * (2.0 * J - J_MIN))
    return dpsi, dh


def volumetric_energy(J: np.ndarray) -> np.ndarray:
    """psi = log(J)^2 / 2 and below J_MIN its quadratic Taylor continuation (NumPy): the energy whose
    derivative `volumetric` is, for audits of the energy the engine integrates."""
    log_min, slope = np.log(J_MIN), (1.0 - np.log(J_MIN)) / J_MIN ** 2
    d = J - J_MIN
    return np.where(d > 0, 0.5 * np.log(np.maximum(J, J_MIN)) ** 2,
                    0.5 * log_min ** 2 + log_min / J_MIN * d + 0.5 * slope * d ** 2)


@func
def stress(F, mu, la):
    """Kirchhoff stress tau = P F^T."""
    I = ti.Matrix.identity(float, 3)
    J = F.determinant()
    dpsi, _ = volumetric(J)
    return mu * (F @ F.transpose() - I) + la * J * dpsi * I


@func
def stress_adjoint(F, mu, la, nu, tau_bar, F_bar, E_bar):
    """From the stress's gradient tau_bar: F's gradient (added to F_bar) and Young's modulus's
    (added to E_bar), with h(J) = J psi'(J) as in `stress`."""
    J = F.determinant()
    dpsi, dh = volumetric(J)
    trace_bar = tau_bar.trace()
    F_grad = F_bar + (mu * (tau_bar + tau_bar.transpose()) @ F + la * dh * trace_bar * cofactor(F))
    mu_bar = ((F @ F.transpose() - ti.Matrix.identity(float, 3)) * tau_bar).sum()
    E_grad = E_bar + mu_bar / (2.0 * (1.0 + nu)) + J * dpsi * trace_bar * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return F_grad, E_grad


MODEL = MaterialModel("neo_hookean", "compressible neo-Hookean elastomer (no SVD; robots' default)",
                      stress=stress, stress_adjoint=stress_adjoint)
