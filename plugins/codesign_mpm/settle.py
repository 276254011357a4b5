"""A settled start: the deformation that carries each layer's own weight from frame 0.

A stress-free layer (sand, snow, clay, mud, water) laid on the terrain first falls under gravity
and then rings, while an episode is already being scored. Here every layer particle starts at
the geostatic state instead: at depth d below the layer's top the vertical Cauchy stress is
-rho g d, with no lateral strain (a layer wall to wall cannot widen), so

- water: the pressure K (1 - J) = rho g d gives J = 1 - rho g d / K and F = J^(1/3) I;
- the Hencky models (sand, clay, mud): F = diag(1, s, 1) with (lambda + 2 mu) log(s) / s = -rho g d;
- neo-Hookean-based ones (snow, elastic layers): (mu (s^2 - 1) + lambda log s) / s = -rho g d.

The vertical stretch s is found by Newton's method. Lateral stresses follow from the model (for
the plastic ones the first substep projects any state outside the yield surface onto it).
Gravity must point along -y (the terrain's up axis).
"""
from __future__ import annotations

import numpy as np

from codesign_mpm.materials import ID, lame
from codesign_mpm.sampling import Particles
from codesign_mpm.scene import Scene, SceneError

HENCKY = (ID["sand"], ID["clay"], ID["mud"])
SETTLING = ("water", "sand", "snow", "clay", "mud")
"""Materials that start settled in any body shape (layers of any material do too)."""


def _vertical_stretch(model: int, E: np.ndarray, nu: np.ndarray, pressure: np.ndarray) -> np.ndarray:
    """s with sigma_yy(diag(1, s, 1)) = -pressure, by Newton's method from s = 1."""
    mu, la = lame(E, nu)
    s = np.ones_like(pressure)
    for _ in range(30):
        log_s = np.log(s)
        if model in HENCKY:  # tau_yy = (lambda + 2 mu) log s, sigma = tau / s
            f = (la + 2 * mu) * log_s / s + pressure
            df = (la + 2 * mu) * (1 - log_s) / s ** 2
        else:  # tau_yy = mu (s^2 - 1) + lambda log s
            f = (mu * (s * s - 1) + la * log_s) / s + pressure
            df = mu * (1 + 1 / (s * s)) + la * (1 - log_s) / s ** 2
        s = s - f / df
    return s


def settled_deformation(scene: Scene, particles: Particles) -> np.ndarray:
    """(N, 3, 3) initial F: geostatic for every layer and every body of water, sand, snow, clay or
    mud (the depth of a particle is measured from the top of its body in its grid column),
    identity for the rest (elastic bodies, the robot)."""
    F = np.tile(np.eye(3), (particles.n, 1, 1))
    g = np.asarray(scene.gravity, dtype=float)
    if not np.allclose(g[[0, 2]], 0.0) or g[1] > 0:
        raise SceneError(f"gravity = {list(scene.gravity)} is invalid for a settled start: it must point "
                         "along -y (the terrain's up axis)")
    for i, body in enumerate(scene.bodies):
        if body.robot or not (body.shape.kind == "layer" or body.material.kind in SETTLING):
            continue
        sel = np.flatnonzero(particles.body == i)
        x = particles.x[sel]
        column = np.unique(np.floor(x[:, [0, 2]] / scene.dx).astype(int), axis=0, return_inverse=True)[1].ravel()
        top = np.full(column.max() + 1, -np.inf)
        np.maximum.at(top, column, x[:, 1])
        spacing = scene.dx / round(body.particles_per_cell ** (1 / 3))
        depth = top[column] + spacing / 2 - x[:, 1]  # the body's top face lies half a spacing above its last particles
        pressure = particles.density[sel] * -g[1] * depth
        model = int(particles.material[sel[0]])
        if model == ID["water"]:
            J = 1 - pressure / particles.params[sel, 0]
            F[sel] = np.cbrt(J)[:, None, None] * np.eye(3)
        else:
            F[sel, 1, 1] = _vertical_stretch(model, particles.youngs_modulus[sel], particles.poisson_ratio[sel],
                                             pressure)
    return F
