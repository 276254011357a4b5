"""The spring contact on an architecture (cuda where there is one) against the CPU (issue 47):
1. a block at 35 degrees (mu 0.5) slides at g (sin - mu cos), float32;
2. a float64 rollout's gradients (actions, volume, the springs' initial values) equal the CPU's;
3. forward cost: particle-substeps/s of the nodes, surface and spring contacts on the quick start's
   box at dx 1/64 (40 frames after 5; the median of --repeats).
Writes $OUT/spring_<arch>.json (or ./); docs/log/contact.md section 24 reads it.

    python benchmarks/contact_devices.py cuda
    python benchmarks/contact_devices.py cpu --repeats 5
"""
import json
import math
import os
import sys
import time

import numpy as np

from codesign_mpm import BodySpec, MaterialSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.reports.accuracy import Setting, robot_env
from codesign_mpm.engine import Simulator

ARCH = sys.argv[1] if len(sys.argv) > 1 else "cuda"
REPEATS = int(sys.argv[sys.argv.index("--repeats") + 1]) if "--repeats" in sys.argv else 1
OUT = os.environ.get("OUT", ".")
results = {"arch": ARCH}


def com(sim):
    p = sim.particles
    m = p.volume * p.density
    return (m[:, None] * sim.particles_state()[0]).sum(0) / m.sum()


def incline(arch):
    dx, theta_deg, mu, h0, xc, half = 1 / 32, 35.0, 0.5, 0.1, 0.6, 0.04
    theta = math.radians(theta_deg)
    normal = np.array([-math.sin(theta), math.cos(theta), 0.0])
    center = np.array([xc, h0 + math.tan(theta) * xc, 0.25]) + normal * (half + dx / 8)
    scene = Scene(size=[1.0, 1.0, 0.5], dx=dx, arch=arch, flip=0.99, pic_time=0.265,
                  terrain=TerrainSpec(kind="incline", height=h0, slope_deg=theta_deg, friction=mu, contact="spring"),
                  bodies=[BodySpec(shape=ShapeSpec(size=[0.16, 0.08, 0.08]), center=center.tolist(),
                                   rotation=[0.0, 0.0, theta_deg], material=MaterialSpec(youngs_modulus=1e5))])
    sim = Simulator(scene, build_particles(scene))
    downhill = np.array([-math.cos(theta), -math.sin(theta), 0.0])
    start, travel = com(sim), []
    for _ in range(60):
        sim.step()
        travel.append((com(sim) - start) @ downhill)
    sim.close()
    t = np.arange(1, 61) * scene.frame_dt
    return 2 * np.polyfit(t[20:], np.array(travel)[20:], 2)[0], 3.8 * (math.sin(theta) - mu * math.cos(theta))


def gradients(arch):
    env = robot_env("ground", Setting(dx=1 / 32, dtype="float64"), 6, arch=arch, contact="spring", pic_time=0.265,
                    terrain_height=0.1)
    sim = Simulator(env.scene, env.particles, requires_grad=True, max_frames=6, checkpoint_every=4)
    actions = np.random.default_rng(1).uniform(-0.3, 0.3, (6, sim.n_actuators))
    w = np.random.default_rng(2).normal(size=(7, 3))
    out = sim.rollout(actions, checkpoint_every=4)
    g = sim.backward(com_x=w)
    value = float((w * out.com_x).sum())
    sim.close()
    env.close()
    return value, g.actions, g.volume, g.u0


def cost(arch, contact):
    env = robot_env("ground", Setting(dx=1 / 64), 60, arch=arch, contact=contact,
                    pic_time=0.265 if contact == "spring" else None)
    env.reset()
    sim, k = env.sim, env.action_dim
    for f in range(5):
        env.step(np.full(k, 0.1))
    steps0, t0 = sum(sim.frame_substeps), time.perf_counter()
    for f in range(40):
        env.step(np.full(k, 0.3 * math.sin(f / 3)))
    elapsed = time.perf_counter() - t0
    substeps = sum(sim.frame_substeps) - steps0
    n = sim.n
    env.close()
    return {"particles": n, "substeps": substeps, "seconds": elapsed, "particle_substeps_per_s": n * substeps / elapsed}


try:
    accel, expected = incline(ARCH)
    results["incline_35"] = {"accel": accel, "expected": expected}
    print("incline", accel, expected, flush=True)
    v_dev, a_dev, vol_dev, u_dev = gradients(ARCH)
    v_cpu, a_cpu, vol_cpu, u_cpu = gradients("cpu")
    results["gradients"] = {"loss": [v_dev, v_cpu],
                            "actions_max_rel": float(np.abs(a_dev - a_cpu).max() / np.abs(a_cpu).max()),
                            "volume_max_rel": float(np.abs(vol_dev - vol_cpu).max() / np.abs(vol_cpu).max()),
                            "u0_max_rel": float(np.abs(u_dev - u_cpu).max() / max(np.abs(u_cpu).max(), 1e-30)),
                            "u0_max": float(np.abs(u_cpu).max())}
    print("gradients", results["gradients"], flush=True)
    results["cost"] = {}
    for contact in ("nodes", "surface", "spring"):
        runs = [cost(ARCH, contact) for _ in range(REPEATS)]
        results["cost"][contact] = {**runs[0], "particle_substeps_per_s": float(np.median(
            [r["particle_substeps_per_s"] for r in runs])), "repeats": REPEATS}
    print("cost", results["cost"], flush=True)
finally:
    with open(os.path.join(OUT, f"spring_{ARCH}.json"), "w") as f:
        json.dump(results, f, indent=1, default=float)
