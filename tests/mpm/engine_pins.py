"""Pinned trajectories and gradients of a few small scenes, so that moving the engine's code can be
checked to change nothing (tests/mpm/test_engine_pins.py).

Run as a script to (re)generate tests/mpm/data/engine_pins.npz from the engine as it is, or to
compare the engine on another backend with the stored values (within the test's tolerances):

    PYTHONPATH=.:plugins python tests/mpm/engine_pins.py
    PYTHONPATH=.:plugins python tests/mpm/engine_pins.py --compare --arch cuda

Scenes (dx 1/32, a few hundred particles per body, 3 frames):

- ``mixed_f64``: a muscled neo-Hookean robot on Perlin terrain with blocks of sand, snow, clay,
  mud, water and StVK around it, float64, differentiable: final state and the gradients of a
  scalar loss (centre of mass and final positions) with respect to every input of the rollout;
- ``flip_f64``: the robot with a water block and the FLIP share (flip 0.99), the same;
- ``mixed_f32``: the mixed scene plus a corotated block stepped forward in float32 (the separate
  stress kernels), its stress at an action;
- ``elastic_f32``: elastic bodies only (the stress fused into p2g), energy muscles, float32;
- ``flip_f32``: the FLIP scene stepped forward in float32.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from codesign_mpm import BodySpec, MaterialSpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles

DATA = Path(__file__).parent / "data" / "engine_pins.npz"
DX = 1 / 32
T = 3  # frames
STATE_TOLERANCE = 1e-5
GRADIENT_TOLERANCE = 1e-3
ROUNDOFF_GRADIENT = 1e-18  # an array of gradients this small everywhere is zero up to round-off (mixed_f64's J_p: 3e-22)
ARCH = "cpu"  # the backend `compute` runs on (`--arch`)
GRADIENT_FIELDS = ("actions", "volume", "youngs_modulus", "muscle", "fiber", "x0", "v0", "C0", "F0", "Jp0")


def _block(name: str, kind: str, center, **material) -> BodySpec:
    return BodySpec(name=name, shape=ShapeSpec(size=[0.07, 0.05, 0.07]), center=list(center),
                    material=MaterialSpec(kind=kind, **material))


def _robot(**material) -> BodySpec:
    return BodySpec(name="robot", shape=ShapeSpec(size=[0.12, 0.06, 0.08]), center=[0.5, 0.19, 0.25], robot=True,
                    material=MaterialSpec(youngs_modulus=2e4, **material), muscles=MuscleSpec(groups=[2, 1, 2]),
                    velocity=[0.3, -0.2, 0.1])


def _scene(bodies, **kw) -> Scene:
    return Scene(size=[1.0, 0.5, 0.5], dx=DX, bodies=bodies, arch=ARCH,
                 terrain=TerrainSpec(kind="perlin", height=0.1, amplitude=0.02, friction=0.4), **kw)


def mixed_scene(dtype: str, corotated: bool = False) -> Scene:
    bodies = [_robot(),
              _block("sand", "sand", [0.15, 0.17, 0.14], friction_angle=35.0, cohesion=5.0),
              _block("snow", "snow", [0.15, 0.17, 0.36]),
              _block("clay", "clay", [0.30, 0.17, 0.14], yield_stress=300.0),
              _block("mud", "mud", [0.30, 0.17, 0.36], yield_stress=100.0, viscosity=0.5),
              _block("water", "water", [0.75, 0.17, 0.14], bulk_modulus=2e4, viscosity=0.05),
              _block("stvk", "stvk", [0.75, 0.17, 0.36])]
    if corotated:
        bodies.append(_block("corotated", "corotated", [0.88, 0.17, 0.25]))
    return _scene(bodies, dtype=dtype)


def flip_scene(dtype: str) -> Scene:
    return _scene([_robot(), _block("water", "water", [0.75, 0.17, 0.25], bulk_modulus=2e4)], dtype=dtype, flip=0.99)


def elastic_scene() -> Scene:
    return _scene([_robot(), _block("stvk", "stvk", [0.2, 0.17, 0.25]),
                   _block("corotated", "corotated", [0.8, 0.17, 0.25], youngs_modulus=3e4)],
                  dtype="float32", muscle_model="energy")


def _actions(n_actuators: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.3, 0.3, size=(T, n_actuators))


def differentiable(scene: Scene) -> dict[str, np.ndarray]:
    """Final state and every input's gradient of loss = w . com_x + wx . x_final (float64)."""
    from codesign_mpm.engine import Simulator

    particles = build_particles(scene)
    rng = np.random.default_rng(7)
    w_com, wx = rng.normal(size=(T + 1, 3)), rng.normal(size=(particles.n, 3)) / particles.n
    sim = Simulator(scene, particles, requires_grad=True, max_frames=T, checkpoint_every=5)
    try:
        out = sim.rollout(_actions(particles.n_actuators, 1))
        g = sim.backward(com_x=w_com, x=wx)
        result = {"com_x": out.com_x, "x": out.final.x, "v": out.final.v, "F": out.final.F, "Jp": out.final.Jp}
        result.update({f"grad_{name}": getattr(g, name) for name in GRADIENT_FIELDS})
        return result
    finally:
        sim.close()


def forward(scene: Scene) -> dict[str, np.ndarray]:
    """Final state after T frames of `step` (one action per frame) and the stress at the last action."""
    from codesign_mpm.engine import Simulator

    particles = build_particles(scene)
    sim = Simulator(scene, particles)
    try:
        actions = _actions(particles.n_actuators, 2)
        for a in actions:
            sim.step(a)
        x, v, C, F = sim.particles_state()
        return {"x": x, "v": v, "C": C, "F": F, "Jp": sim.plastic_volume_ratio(),
                "stress": sim.stress(actions[-1]), "substeps": np.array(sim.frame_substeps)}
    finally:
        sim.close()


def compute() -> dict[str, np.ndarray]:
    """Every pinned array, keyed 'scene/name' (computed in a fixed order: field ids, and so the
    compiled kernels, depend on what was built before in the process)."""
    cases = {"mixed_f64": lambda: differentiable(mixed_scene("float64")),
             "flip_f64": lambda: differentiable(flip_scene("float64")),
             "mixed_f32": lambda: forward(mixed_scene("float32", corotated=True)),
             "elastic_f32": lambda: forward(elastic_scene()),
             "flip_f32": lambda: forward(flip_scene("float32"))}
    return {f"{case}/{name}": value for case, run in cases.items() for name, value in run().items()}


def compare(stored: dict[str, np.ndarray], now: dict[str, np.ndarray]) -> list[str]:
    """The keys whose arrays differ at all; raises AssertionError where one differs beyond the
    tolerances (states 1e-5, gradients 1e-3 of the array's largest magnitude) or in substeps."""
    assert sorted(now) == sorted(stored)
    different = []
    for key, expected in stored.items():
        got = now[key]
        assert got.shape == expected.shape and got.dtype == expected.dtype, key
        if np.array_equal(got, expected):
            continue
        different.append(key)
        if key.endswith("substeps"):
            raise AssertionError(f"{key}: substeps {got.tolist()} != {expected.tolist()}")
        gradient = key.split("/")[1].startswith("grad_")
        tolerance = GRADIENT_TOLERANCE if gradient else STATE_TOLERANCE
        scale = float(np.abs(expected).max(initial=0.0))
        error = float(np.abs(got.astype(np.float64) - expected).max())
        assert error <= tolerance * scale + (ROUNDOFF_GRADIENT if gradient else 0.0), (key, error, scale)
    return different


if __name__ == "__main__":
    if "--arch" in sys.argv:
        ARCH = sys.argv[sys.argv.index("--arch") + 1]
    pins = compute()
    if "--compare" in sys.argv:
        different = compare(dict(np.load(DATA)), pins)
        print(f"engine pins on {ARCH}: {len(pins) - len(different)} of {len(pins)} arrays bitwise equal, "
              f"the rest within tolerance: {', '.join(different)}")
    else:
        DATA.parent.mkdir(exist_ok=True)
        np.savez_compressed(DATA, **pins)
        print(f"wrote {DATA} ({DATA.stat().st_size / 1024:.0f} KiB, {len(pins)} arrays)", file=sys.stderr)
