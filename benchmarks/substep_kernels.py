"""Each kernel of a differentiable substep timed alone, forward and reverse: where a gradient's time goes.

    python benchmarks/substep_kernels.py --scale small      # one JSON line: ms per launch, per kernel

The bench scene (`codesign bench engine`'s robot on flat ground) in a differentiable simulator,
after one rollout and backward pass of 40 frames (compiled, or loaded from Taichi's cache); each
kernel is launched 40 times in a row, 5 times over, on the state of substep 3, and the median of
the 5 is reported, Python's launch included. The kernels run out of order on one state, so their
results mean nothing: only their times do. Unlike `codesign bench engine --profile`, no profiler
synchronises around each launch, which overstates small kernels.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np


def kernel_times(scale: str, repeats: int = 5, launches: int = 40) -> dict:
    import taichi as ti

    from codesign_mpm import build_particles
    from codesign_mpm.engine import Simulator
    from codesign_mpm.reports.bench import Case, robot_scene

    scene = robot_scene(Case(scale, "float32"))
    sim = Simulator(scene, build_particles(scene), requires_grad=True, max_frames=40)
    actions = 0.1 * np.sin(np.arange(40)[:, None] * 0.3 + np.arange(sim.n_actuators))
    sim.rollout(actions)
    sim.backward(com_v=np.ones((41, 3)))
    sim.rollout(actions)  # the reverse pass's kernels read the slots and grids a rollout leaves
    k, n, s = sim.k, sim.n, 3
    model, start, end = sim._runs[0]
    store, boxes = sim._grid_store, sim._grid_boxes
    forward = {
        "box": lambda: k._bounds(s, n),
        "stress": lambda: k._constitutive_update(model, s, s + 1, 0, start, end, 0),
        "p2g with its sum": lambda: (k._p2g(s, s + 1, 0, n, 0), k._sum_copies() if k.private_scatter else None),
        "grid update": lambda: k._grid_op(),
        "grid kept": lambda: k._store_grid(s, store, boxes),
        "g2p": lambda: k._g2p(s, s + 1, n, 0),
    }
    reverse = {
        "grid replayed": lambda: k._replay_grid(s, store, boxes),
        "g2p's adjoint": lambda: k._g2p_adjoint(s, n),
        "grid update's adjoint": lambda: k._grid_op.grad(),
        "p2g's adjoint" + (" with the stress's" if k.stress_in_adjoint else ""): lambda: k._p2g_adjoint(s, 0, n),
        "action rows' sum": lambda: k._add_drive_grad(0, start, end),
    }

    def median_ms(launch) -> float:
        launch()
        ti.sync()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            for _ in range(launches):
                launch()
            ti.sync()
            times.append((time.perf_counter() - t0) / launches * 1e3)
        return round(float(np.median(times)), 4)

    timed = {part: {name: median_ms(launch) for name, launch in kernels.items()}
             for part, kernels in (("forward", forward), ("reverse", reverse))}
    return dict(scale=scale, particles=n, stress_in_adjoint=bool(k.stress_in_adjoint), serial=bool(k.serial),
                **{f"{part}_ms": times for part, times in timed.items()},
                **{f"{part}_total_ms": round(sum(times.values()), 3) for part, times in timed.items()})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", action="append", choices=["tiny", "small", "paper", "large"])
    args = parser.parse_args()
    from codesign_mpm.runtime import init_taichi

    init_taichi("cpu", "float32")
    for scale in args.scale or ["small"]:
        print(json.dumps(kernel_times(scale)), flush=True)


if __name__ == "__main__":
    main()
