"""A settled start: the deformation that carries each layer's own weight from frame 0.

A stress-free layer (sand, snow, clay, mud, water) laid on the terrain first falls under gravity
and then rings, while an episode is already being scored. Here every layer particle starts at
the geostatic state instead: at depth d below the layer's top the vertical Cauchy stress is
-rho g d, and the lateral stress is what the material would carry at rest, on or inside its
yield surface:

- water: the pressure K (1 - J) = rho g d gives J = 1 - rho g d / K and F = J^(1/3) I;
- sand (Drucker-Prager in Hencky strain): lateral over vertical Kirchhoff stress K0 = 1 - sin(phi)
  (Jaky's coefficient of earth pressure at rest), F = diag(a, s, a); measured inside the cone for
  every friction angle (0.57 to 0.72 of its radius at 20 to 45 degrees, nu 0.2), where the laterally
  confined state (a = 1, K0 = nu / (1 - nu)) lies outside it below about 37 degrees;
- clay, mud (von Mises in Hencky strain): laterally confined (a = 1) while that is inside the yield
  surface, else the lateral strain that puts the state on it;
- snow: laterally confined neo-Hookean while the vertical stretch stays above 1 - theta_c; beyond,
  the elastic stretch sits at the clamp 1 - theta_c and the plastic volume ratio J_p is the one
  whose hardening exp(xi (1 - J_p)) carries the load there (within the hardening bound);
- elastic layers (neo-Hookean, corotated, StVK): laterally confined, each model's own law.

The vertical strain is found by bisection on each model's vertical Cauchy stress. Gravity must
point along -y (the terrain's up axis).

A robot's body has no such closed form (its shape, its contact with the terrain, the cover it
presses into), so `relax` finds its rest by dynamic relaxation instead
(`environment.robot.settled`): the scene stepped with no action, every velocity zeroed whenever the
kinetic energy has just passed a peak (kinetic damping), until it is at rest. Started stress-free,
an animal sags and then rocks on its belly for longer than an episode (the baby seal: its centre of
mass 5 mm forward in 0.24 s, docs/materials.md), which a task would score as locomotion.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codesign_mpm.engine import Simulator
from codesign_mpm.materials import ID, MIN_HARDENING, lame
from codesign_mpm.scene.sampling import Particles
from codesign_mpm.scene.spec import Scene, SceneError

SETTLING = ("water", "sand", "snow", "clay", "mud")
"""Materials that start settled in any body shape (layers of any material do too)."""
INSIDE = 1.0 - 1e-6  # states put on a yield surface are put this fraction of the way to it
REST_SPEED = 1e-3  # m/s: the RMS speed of all particles under which a relaxed scene is at rest
ROBOT_REST_SPEED = 2e-4  # m/s: the robot's own RMS speed under which it is at rest (0.05 mm drift in 0.24 s)
RELAX_FRAMES = 250  # the most frames a relaxation takes (2 s at 8 ms)
RELAX_CACHE_FILES = 64  # relaxed starts kept on disk (`relax_scene`), the least recently used dropped


def _bisect(stress, pressure: np.ndarray, lo: float = -3.0) -> np.ndarray:
    """e in [lo, 0] with stress(e) = -pressure, for a vertical Cauchy stress increasing in the log
    vertical stretch e (stress(0) = 0 >= -pressure)."""
    a, b = np.full_like(pressure, lo), np.zeros_like(pressure)
    for _ in range(60):
        mid = 0.5 * (a + b)
        below = stress(mid) < -pressure
        a, b = np.where(below, mid, a), np.where(below, b, mid)
    return 0.5 * (a + b)


def _hencky_lateral(model: int, mu, la, params, e_v):
    """The lateral log stretch that goes with the vertical one e_v (< 0) for a Hencky model."""
    if model == ID["sand"]:
        alpha = params[:, 0]
        sin_phi = 3 * alpha / (2 * math.sqrt(2 / 3) + alpha)  # materials.drucker_prager_alpha, inverted
        k0 = 1 - sin_phi
        return e_v * (k0 * (2 * mu + la) - la) / (2 * mu + 2 * la * (1 - k0))
    # von Mises: |e_v - e_h| <= yield / (2 mu) keeps |dev tau| within sqrt(2/3) yield
    return np.minimum(0.0, e_v + INSIDE * params[:, 0] / (2 * mu))


def _settle_model(model: int, particles: Particles, sel: np.ndarray, pressure: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(F (n, 3, 3), J_p (n,)) of the particles `sel` of one material model under `pressure`."""
    mu, la = lame(particles.youngs_modulus[sel], particles.poisson_ratio[sel])
    params = particles.params[sel]
    n = len(sel)
    F = np.tile(np.eye(3), (n, 1, 1))
    jp = np.ones(n)
    if model == ID["water"]:
        J = 1 - pressure / params[:, 0]
        return np.cbrt(J)[:, None, None] * np.eye(3), jp
    if model in (ID["sand"], ID["clay"], ID["mud"]):
        def stress(e_v):
            e_h = _hencky_lateral(model, mu, la, params, e_v)
            return (2 * mu * e_v + la * (e_v + 2 * e_h)) * np.exp(-(e_v + 2 * e_h))
        e_v = _bisect(stress, pressure)
        e_h = np.exp(_hencky_lateral(model, mu, la, params, e_v))
        F[:, 0, 0] = F[:, 2, 2] = e_h
        F[:, 1, 1] = np.exp(e_v)
        return F, jp
    vertical = {  # Cauchy sigma_yy of diag(1, s, 1), s = exp(e), laterally confined
        ID["neo_hookean"]: lambda s, mu, la: (mu * (s * s - 1) + la * np.log(s)) / s,
        ID["snow"]: lambda s, mu, la: (mu * (s * s - 1) + la * np.log(s)) / s,
        ID["corotated"]: lambda s, mu, la: (2 * mu + la) * (s - 1),
        ID["stvk"]: lambda s, mu, la: s * (2 * mu + la) * (s * s - 1) / 2,
    }[model]
    s = np.exp(_bisect(lambda e: vertical(np.exp(e), mu, la), pressure))
    if model == ID["snow"]:  # beyond the clamp the rest is plastic compaction, which hardens
        clamp = 1 - params[:, 0]
        beyond = s < clamp
        carried = -vertical(clamp, mu, la)  # what the clamped elastic stretch carries, unhardened
        hardening = np.clip(pressure / carried, MIN_HARDENING, params[:, 3])
        jp = np.where(beyond, 1 - np.log(hardening) / np.maximum(params[:, 2], 1e-12), 1.0)
        jp = np.where(beyond & (params[:, 2] > 0), jp, 1.0)
        s = np.where(beyond, clamp, s)
    F[:, 1, 1] = s
    return F, jp


def settled_state(scene: Scene, particles: Particles) -> tuple[np.ndarray, np.ndarray]:
    """((N, 3, 3) initial F, (N,) initial J_p): geostatic for every layer and every body of water,
    sand, snow, clay or mud (the depth of a particle is measured from the top of its body in its
    grid column), identity and 1 for the rest (elastic bodies, the robot)."""
    F = np.tile(np.eye(3), (particles.n, 1, 1))
    jp = np.ones(particles.n)
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
        F[sel], jp[sel] = _settle_model(int(particles.material[sel[0]]), particles, sel, pressure)
    return F, jp


@dataclass
class Relaxed:
    """What `relax` found."""

    state: dict[str, np.ndarray]
    """`Simulator.set_initial_state` keywords: x, F, Jp where it ended, v and C zero."""
    frames: int
    """Frames it took."""
    speed: float
    """All the particles' RMS speed at its last frame's end (before the velocities were zeroed)."""
    robot_speed: float
    """The robot's own RMS speed then (0 without a robot)."""

    @property
    def at_rest(self) -> bool:
        """Whether both were under their rest speeds."""
        return _at_rest(self.speed, self.robot_speed)


def _at_rest(speed: float, robot_speed: float) -> bool:
    return speed < REST_SPEED and robot_speed < ROBOT_REST_SPEED


def relax(sim: Simulator, mass: np.ndarray, robot: np.ndarray | None = None, frames: int = RELAX_FRAMES) -> Relaxed:
    """Dynamic relaxation with kinetic damping (Cundall's): step `sim` with no action, zero every
    velocity (and the affine C) after each frame whose kinetic energy is below the frame's before (a
    peak has passed: the energy is nearest its potential minimum there), and stop after the first
    frame at rest, or after `frames`. At rest: the RMS speed of all particles (weighed by `mass`, (N,))
    under REST_SPEED and, where `robot` (N,) marks a body among them, the body's own under
    ROBOT_REST_SPEED (in the ocean the water's mass would otherwise hide a body still rising or
    drifting, which a task would score). What is left is a static equilibrium of the scene under
    gravity on the terrain (forward only: no gradient reaches the start through it)."""
    robot = robot if robot is not None and robot.any() else None
    total, robot_mass = mass.sum(), None if robot is None else mass[robot]
    before, frame, speed, robot_speed = np.inf, 0, math.inf, math.inf
    while frame < frames and not _at_rest(speed, robot_speed):
        sim.step(None)
        frame += 1
        x, v, C, F = sim.particles_state()
        energy = 0.5 * float(mass @ (v * v).sum(1))
        speed = math.sqrt(2 * energy / total)
        robot_speed = 0.0 if robot is None else math.sqrt(float(robot_mass @ (v[robot] ** 2).sum(1)) / robot_mass.sum())
        if energy < before or _at_rest(speed, robot_speed):
            sim.set_initial_state(x=x, v=np.zeros_like(v), C=np.zeros_like(C), F=F, Jp=sim.plastic_volume_ratio())
            energy = 0.0
        before = energy
    x, v, C, F = sim.particles_state()
    state = {"x": x, "v": np.zeros_like(v), "C": np.zeros_like(C), "F": F, "Jp": sim.plastic_volume_ratio()}
    return Relaxed(state, frame, speed, robot_speed)


def relax_cache_dir() -> Path:
    """Where `relax_scene` keeps relaxed starts: $CODESIGN_CACHE/relaxed (default ~/.cache/codesign)."""
    return Path(os.environ.get("CODESIGN_CACHE") or Path.home() / ".cache" / "codesign") / "relaxed"


@functools.cache
def _engine_digest() -> str:
    """A digest of this package's source: a relaxed start computed by other physics is not reused."""
    package = Path(__file__).parent
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        digest.update(path.relative_to(package).as_posix().encode() + path.read_bytes())
    return digest.hexdigest()


def _relax_key(scene: Scene, particles: Particles, start: dict[str, np.ndarray]) -> str:
    digest = hashlib.sha256(f"{_engine_digest()} {scene!r} {REST_SPEED} {ROBOT_REST_SPEED} {RELAX_FRAMES}".encode())
    arrays = [getattr(particles, f.name) for f in dataclasses.fields(particles)] + [start[k] for k in sorted(start)]
    for array in arrays:
        array = np.ascontiguousarray(array)
        digest.update(f"{array.dtype} {array.shape}".encode() + array.tobytes())
    return digest.hexdigest()


def relax_scene(scene: Scene, particles: Particles, start: dict[str, np.ndarray], capacity: int | None = None) -> Relaxed:
    """`relax` the scene's particles from `start` (`Simulator.set_initial_state` keywords), the robot's
    own speed included in the rest test, or load the result of an identical relaxation (same scene,
    particles, start and engine source) from `relax_cache_dir()`: a study relaxes each body once,
    not once per task, method and seed (in the ocean 250 frames, half a minute at dx 1/48)."""
    path = relax_cache_dir() / f"{_relax_key(scene, particles, start)}.npz"
    if path.is_file():
        with np.load(path) as saved:
            path.touch()  # recently used
            return Relaxed({k: saved[k] for k in ("x", "v", "C", "F", "Jp")}, int(saved["frames"]),
                           float(saved["speed"]), float(saved["robot_speed"]))
    sim = Simulator(scene, particles, capacity=capacity)
    try:
        sim.set_initial_state(**start)
        relaxed = relax(sim, particles.volume * particles.density, robot=particles.robot)
    finally:
        sim.close()
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f"{path.name}.{os.getpid()}.tmp")  # not *.npz: the pruning below leaves it alone
    with partial.open("wb") as file:
        np.savez(file, **relaxed.state, frames=relaxed.frames, speed=relaxed.speed, robot_speed=relaxed.robot_speed)
    partial.replace(path)  # whole or absent, also with two runs relaxing the same body at once
    for old in sorted(path.parent.glob("*.npz"), key=lambda p: p.stat().st_mtime)[:-RELAX_CACHE_FILES]:
        old.unlink(missing_ok=True)
    return relaxed
