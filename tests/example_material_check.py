"""Run by test_example_plugin.py in a process that sees the installed example plugin: its
Mooney-Rivlin material (a plugin's material model) in a scene, forward in float32, and its
gradients against central finite differences in float64. Prints one JSON line."""
import json
import sys

import numpy as np

from codesign_mpm import BodySpec, MaterialSpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine import Simulator
from codesign_mpm.materials import ID, MATERIALS

T = 3


def scene(dtype: str) -> Scene:
    body = BodySpec(name="block", shape=ShapeSpec(size=[0.1, 0.06, 0.08]), center=[0.3, 0.16, 0.25], robot=True,
                    material=MaterialSpec(kind="mooney_rivlin", youngs_modulus=2e4, parameters={"mooney_ratio": 0.4}),
                    muscles=MuscleSpec(groups=[2, 1, 1]), velocity=[0.2, -0.4, 0.1])
    return Scene(size=[0.6, 0.4, 0.5], dx=1 / 32, dtype=dtype, bodies=[body],
                 terrain=TerrainSpec(kind="flat", height=0.1, friction=0.4))


def forward() -> dict:
    s = scene("float32")
    particles = build_particles(s)
    sim = Simulator(s, particles)
    try:
        sim.step(np.full(particles.n_actuators, 0.2), frames=10)
        x, v, _, F = sim.particles_state()
        J = np.linalg.det(F.astype(np.float64))
        return {"finite": bool(np.isfinite(x).all() and np.isfinite(v).all()), "min_J": float(J.min()),
                "max_J": float(J.max()), "moved": float(np.abs(x - particles.x).max())}
    finally:
        sim.close()


def gradients() -> list[dict]:
    s = scene("float64")
    p = build_particles(s)
    rng = np.random.default_rng(3)
    actions = rng.uniform(-0.3, 0.3, size=(T, p.n_actuators))
    w_com, wx = rng.normal(size=(T + 1, 3)), rng.normal(size=(p.n, 3)) / p.n
    sim = Simulator(s, p, requires_grad=True, max_frames=T)
    try:
        def loss(a=actions) -> float:
            out = sim.rollout(a)
            return float((w_com * out.com_x).sum() + (wx * out.x).sum())

        loss()
        g = sim.backward(com_x=w_com, x=wx)
        start = sim.snapshot()
        foot = int(np.argmin(p.x[:, 1]))
        rows = []
        for field, index, eps in [("actions", (0, 0), 1e-6), ("actions", (T - 1, 1), 1e-6),
                                  ("youngs_modulus", foot, 1e-6 * p.youngs_modulus[foot]),
                                  ("x0", (foot, 0), 1e-6), ("v0", (foot, 1), 1e-6)]:
            values = []
            for sign in (1, -1):
                sim.restore(start)
                if field == "actions":
                    a = actions.copy()
                    a[index] += sign * eps
                    values.append(loss(a))
                    continue
                source = {"x0": "x", "v0": "v"}.get(field, field)
                value = getattr(p, source).copy()
                value[index] += sign * eps
                if field in ("x0", "v0"):
                    sim.set_initial_state(**{source: value})
                else:
                    sim.set_design(**{field: value})
                values.append(loss())
            gradient = getattr(g, field)
            rows.append({"field": field, "analytic": float(gradient[index]),
                         "numeric": (values[0] - values[1]) / (2 * eps), "scale": float(np.abs(gradient).max())})
        return rows
    finally:
        sim.close()


if __name__ == "__main__":
    moved = forward()  # its first scene loads the plugins' models (ids after the engine's own)
    result = {"id": ID["mooney_rivlin"], "kind": MATERIALS["mooney_rivlin"].kind, "forward": moved,
              "gradients": gradients()}
    print(json.dumps(result))
    sys.exit(0)
