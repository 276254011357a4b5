"""The time step: the CFL condition at rest (`time_step`), each particle's wave speed, the bounds a
frame's state-following step keeps to, and FLIP's share per substep."""

import math
from dataclasses import dataclass

import numpy as np

from codesign_mpm.materials import (MAX_ACTIVE_STRESS_RATIO, active_stress_ratio, max_stiffness_ratio,
                                    model_wave_speed, muscle_modulus, viscosity)
from codesign_mpm.scene.sampling import Particles
from codesign_mpm.scene.spec import Scene, SceneError

ADAPTIVE_CFL_FACTOR = 2.0
"""A frame takes more substeps than at rest once its state's CFL number (particle speed plus the
stretch-stiffened wave speed, `_wave_speed`) would exceed this many times scene.cfl: a guard against
instability, not a finer accuracy target (at 1x, the quick start's gait took 32% more substeps; at 2x,
none, while the stability cases that blew up at the rest step run finite)."""
MAX_ADAPTIVE_CFL = 0.8  # nor above this CFL number, whatever scene.cfl (measured stable in docs/stability.md)


@dataclass(frozen=True)
class TimeStep:
    dt: float  # the substep actually used
    substeps: int  # per frame (control step), exact: substeps * dt == frame_dt
    stable_dt: float  # the CFL bound for this scene


def wave_speeds(scene: Scene, particles: Particles) -> tuple[np.ndarray, np.ndarray]:
    """(N,) fastest wave speed of each particle at rest, and (N,) the axial modulus its muscle adds
    (`materials.muscle_modulus`; 0 without muscle membership), computed once per distinct material."""
    actuated = (np.abs(particles.muscle).sum(1) > 0) & (particles.muscle_ratio > 0)
    added = np.where(actuated, muscle_modulus(scene.muscle_model, particles.muscle_ratio * particles.youngs_modulus,
                                              scene.max_action), 0.0)
    table = np.column_stack([particles.material, particles.youngs_modulus, particles.poisson_ratio,
                             particles.density, added, particles.params])
    kinds, of_particle = distinct_rows(table)  # distinct materials
    speeds = np.array([model_wave_speed(int(row[0]), *row[1:5], tuple(row[5:])) for row in kinds])
    return speeds[of_particle], added


def distinct_rows(table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, C) the distinct rows of an (N, C) table in lexicographic order, and (N,) each row's index
    among them: `np.unique(table, axis=0, return_inverse=True)`, about 15x faster on a robot whose
    every particle has its own stiffness (numpy sorts the rows as opaque records; a lexsort of the
    columns does not). Runs at every design change."""
    if len(table) == 0:
        return table.copy(), np.zeros(0, dtype=np.intp)
    order = np.lexsort(table.T[::-1])
    ordered = table[order]
    starts = np.concatenate([[True], np.any(ordered[1:] != ordered[:-1], axis=1)])
    of_row = np.empty(len(table), dtype=np.intp)
    of_row[order] = np.cumsum(starts) - 1
    return ordered[starts], of_row


def time_step(scene: Scene, particles: Particles) -> TimeStep:
    """Substep from the CFL condition with the stiffest material and fastest initial speed.

    dt <= cfl * dx / (c_p + |v|max), c_p = sqrt((lambda + 2 mu + m) / rho) with m what the
    scene's muscle model adds to the axial modulus (`materials.muscle_modulus`; particles
    without muscle membership add nothing), water's sqrt(K / rho), snow's speed at its largest
    hardening; for viscous materials also the explicit diffusion limit dt <= cfl * rho dx^2 /
    (6 eta). A forced `dt` above that bound is refused unless `allow_unstable_dt` is set.

    This is the step at rest; with `scene.adaptive_dt` each frame takes at least as many substeps
    as its current state needs (`Simulator`: speeds and stretch-dependent stiffness).
    """
    actuated = (np.abs(particles.muscle).sum(1) > 0) & (particles.muscle_ratio > 0)
    if scene.muscle_model == "active":
        _check_muscle_stability(scene, particles, actuated)
    speeds, _ = wave_speeds(scene, particles)
    fastest = float(speeds.max(initial=0.0))
    vmax = float(np.linalg.norm(particles.v, axis=1).max(initial=0.0))
    stable = scene.cfl * scene.dx / (fastest + vmax)
    for row in distinct_rows(np.column_stack([particles.material, particles.density, particles.params]))[0]:
        eta = viscosity(int(row[0]), tuple(row[2:]))
        if eta > 0:
            stable = min(stable, scene.cfl * row[1] * scene.dx ** 2 / (6 * eta))
    target = stable
    if scene.dt is not None:
        if scene.dt > stable and not scene.allow_unstable_dt:
            raise SceneError(
                f"dt = {scene.dt!r} is invalid: the CFL bound for this scene is {stable:.4g} "
                f"(cfl {scene.cfl}, dx {scene.dx:.4g}, wave speed {fastest:.4g}, speed {vmax:.4g}); "
                "use a smaller dt, leave dt null, or set allow_unstable_dt: true")
        target = scene.dt
    substeps = max(1, math.ceil(scene.frame_dt / target - 1e-9))
    return TimeStep(scene.frame_dt / substeps, substeps, stable)


def _check_muscle_stability(scene: Scene, particles: Particles, actuated: np.ndarray) -> None:
    """Refuse active muscles stronger than the material can carry (`materials.MAX_ACTIVE_STRESS_RATIO`):
    s max_action above that fraction of the shear modulus stretches fibres without bound near
    s max_action = mu, and tears thin bodies (numerical fracture) well before it."""
    ratio = active_stress_ratio(particles.muscle_ratio, scene.max_action, particles.poisson_ratio)
    bad = np.flatnonzero(actuated & (ratio > MAX_ACTIVE_STRESS_RATIO * (1 + 1e-9)))
    if len(bad):
        p = bad[0]
        raise SceneError(
            f"muscles.stiffness_ratio = {particles.muscle_ratio[p]:.4g} is invalid with max_action = "
            f"{scene.max_action!r} for body {int(particles.body[p])}: at the bound the active stress is "
            f"{ratio[p]:.3g} x the shear modulus; admissible: <= {MAX_ACTIVE_STRESS_RATIO}, i.e. stiffness_ratio <= "
            f"{max_stiffness_ratio(scene.max_action, particles.poisson_ratio[p]):.4g} for Poisson's ratio "
            f"{particles.poisson_ratio[p]:.4g} (or a smaller max_action)")


def flip_share(scene: Scene, dt: float) -> float:
    """FLIP's share in a substep of `dt`: `scene.flip` per substep, or with `scene.pic_time`
    exp(-dt / pic_time), so the PIC share damps a particle's own velocity at a rate per unit time
    whatever the number of substeps."""
    return scene.flip if scene.pic_time is None else math.exp(-dt / scene.pic_time)
