"""`codesign bench engine` (throughput, backward cost, memory, batches), `codesign bench environments`
and `codesign bench compile` (cold compile time per material), as JSON lines.

Every measurement runs in its own subprocess, so Taichi initialises with the requested
precision and the peak resident memory (ru_maxrss) belongs to that measurement alone.
Timings are medians over repeats; compare runs on the same machine only.
"""
from __future__ import annotations

import json
import os
import platform
import re
import resource
import sys
import time
from dataclasses import dataclass, replace

import numpy as np

from codesign_mpm.reports.machine import run_module

SCALES = {
    # the scene (a): about 60k particles, dx 1/128 in the unit cube
    "paper": dict(dx=1 / 128, robot=[0.25, 0.12, 0.12], terrain=0.05),
    # a CPU-friendly default: 7,200 particles, dx 1/64
    "small": dict(dx=1 / 64, robot=[0.25, 0.12, 0.12], terrain=0.1),
    # the quick start's grid (dx 1/32) with scene (a)'s box: 1,024 particles (populations of small scenes)
    "tiny": dict(dx=1 / 32, robot=[0.25, 0.12, 0.12], terrain=0.1),
    # a GPU's size: scene (a)'s robot twice as large each way, 476,288 particles, dx 1/128
    "large": dict(dx=1 / 128, robot=[0.5, 0.24, 0.24], terrain=0.05),
}
ENGINE_MEASURES = ("forward", "float64", "dense", "backward", "batch", "scatter", "adaptive", "flip", "contact")
"""What `codesign bench engine` measures per scale: forward float32 with the grid over the particles'
box, in float64, over the dense grid; then (float32) the differentiable episode, a batch against the
same episodes one after the other, and the three variants timed against their alternative."""


@dataclass
class Case:
    scale: str
    dtype: str
    grid_region: str = "bbox"
    arch: str = "cpu"


def robot_scene(case: Case):
    from codesign_mpm import BodySpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec

    s = SCALES[case.scale]
    return Scene(size=[1.0, 1.0, 1.0], dx=s["dx"], dtype=case.dtype, grid_region=case.grid_region, arch=case.arch,
                 terrain=TerrainSpec(kind="flat", height=s["terrain"], friction=0.5),
                 bodies=[BodySpec(name="robot", robot=True, shape=ShapeSpec(size=s["robot"]),
                                  center=[0.5, 0.0, 0.5], rest_on_terrain=True, muscles=MuscleSpec(groups=[2, 2, 1]))])


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def measure_forward(case: Case, repeats: int = 5, frames: int = 3) -> dict:
    from codesign_mpm import build_particles
    from codesign_mpm.engine import Simulator

    scene = robot_scene(case)
    particles = build_particles(scene)
    t0 = time.perf_counter()
    sim = Simulator(scene, particles)
    sim.step(np.zeros(sim.n_actuators))  # compiles (or loads from the offline cache)
    first = time.perf_counter() - t0
    rates = []
    for r in range(repeats):
        t0 = time.perf_counter()
        sim.step(np.full(sim.n_actuators, 0.1 * (-1) ** r), frames=frames)
        rates.append(sim.n * sum(sim.frame_substeps[-frames:]) / (time.perf_counter() - t0))
    return dict(measure="forward", particles=sim.n, substeps_per_frame=sim.timestep.substeps,
                dt=sim.timestep.dt, first_frame_s=round(first, 3),
                particle_substeps_per_s=float(np.median(rates)), repeats=[round(r) for r in rates])


def measure_backward(case: Case, frames: int = 200, repeats: int = 1) -> dict:
    """(forward + backward) / forward for one differentiable episode, and its peak memory."""
    from codesign_mpm import build_particles
    from codesign_mpm.engine import Simulator
    from codesign_mpm.engine.simulator import segment_memory_bytes

    scene = robot_scene(case)
    particles = build_particles(scene)
    t0 = time.perf_counter()
    sim = Simulator(scene, particles, requires_grad=True, max_frames=frames)
    warm = np.zeros((1, sim.n_actuators))
    sim.rollout(warm)
    sim.backward(com_v=np.ones((2, 3)))
    first = time.perf_counter() - t0
    actions = 0.1 * np.sin(np.arange(frames)[:, None] * 0.3 + np.arange(sim.n_actuators))
    fwd, total = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = sim.rollout(actions)
        t1 = time.perf_counter()
        sim.backward(com_v=np.tile([1.0, 0.0, 0.0], (frames + 1, 1)) / frames)
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        total.append(t2 - t0)
    assert np.isfinite(out.com_x).all()
    substeps = sum(sim.frame_substeps)
    return dict(measure="backward", particles=sim.n, frames=frames, substeps=substeps,
                segment_memory_mb=segment_memory_bytes() // 2**20, checkpoint_every=sim.segment,
                recomputed_substeps=sim.recomputed_substeps,
                storage_mb=round(sim.k.nbytes / 2**20, 1), first_call_s=round(first, 3),
                forward_s=float(np.median(fwd)), forward_backward_s=float(np.median(total)),
                backward_over_forward=float(np.median(total) / np.median(fwd)), repeats=repeats,
                peak_rss_mb=round(_peak_rss_mb(), 1))


KERNEL_TASK = re.compile(r"(?P<kernel>.+?)_c\d+_\d+_kernel_(?P<task>\d+)_")
FIELD_ACCESS = re.compile(r"snode_(reader|writer)_\d+")


def _kernel_profile(substeps: int, wall_s: float) -> dict:
    """Taichi's kernel profiler records since its last clear, per substep: launches (a kernel's
    first offloaded task), the fields read or written one element at a time from Python (each a
    launch and a host round trip), kernel time, and the rest of the wall time (Python, launching,
    synchronising); the kernels by their share of the kernel time."""
    from taichi.profiler import kernel_profiler

    profiler = kernel_profiler.get_default_kernel_profiler()
    profiler._update_records()  # Taichi's own accessor for the backend's records
    kernels: dict[str, list] = {}
    launches = accesses = 0
    kernel_ms = 0.0
    for record in profiler._traced_records:
        kernel_ms += record.kernel_time
        if FIELD_ACCESS.match(record.name):
            accesses += 1
            continue
        match = KERNEL_TASK.match(record.name)
        name = match["kernel"] if match else record.name
        entry = kernels.setdefault(name, [0, 0.0])
        entry[1] += record.kernel_time
        if match is None or match["task"] == "0":
            entry[0] += 1
            launches += 1
    wall_ms = 1e3 * wall_s
    top = sorted(kernels.items(), key=lambda item: -item[1][1])
    return dict(substeps=substeps, launches_per_substep=launches / substeps,
                field_accesses_per_substep=accesses / substeps, wall_ms_per_substep=wall_ms / substeps,
                kernel_ms_per_substep=kernel_ms / substeps, other_share=1 - kernel_ms / wall_ms,
                kernels={name: dict(share=round(ms / kernel_ms, 4), launches_per_substep=round(n / substeps, 2))
                         for name, (n, ms) in top})


def _profile_forward(sim, action: np.ndarray, frames: int) -> dict:
    """`_kernel_profile` of `frames` control steps holding `action`, after one that compiles."""
    import taichi as ti

    sim.step(np.zeros_like(action))  # compiles (or loads from the offline cache)
    ti.profiler.clear_kernel_profiler_info()
    t0 = time.perf_counter()
    sim.step(action, frames=frames)
    profile = _kernel_profile(sum(sim.frame_substeps[-frames:]), time.perf_counter() - t0)
    sim.close()
    return profile


def measure_profile(case: Case, frames: int = 5, backward_frames: int = 20, members: int = 0) -> dict:
    """Where a substep's time goes (`codesign bench engine --profile`), forward, forward + backward
    and, with `members`, forward in a BatchSimulator of that many copies of the scene's robot, under
    Taichi's kernel profiler (`CODESIGN_KERNEL_PROFILER=1`, set by the caller: it must be on when
    Taichi starts). The profiler synchronises around every kernel, so its wall times are upper
    bounds; `forward` measures the unprofiled throughput."""
    import taichi as ti

    from codesign_mpm import build_particles
    from codesign_mpm.engine import Simulator
    from codesign_mpm.engine.batch import BatchSimulator

    scene = robot_scene(case)
    particles = build_particles(scene)
    forward = _profile_forward(Simulator(scene, particles), np.full(particles.n_actuators, 0.1), frames)
    batch = None
    if members:
        batch = _profile_forward(BatchSimulator(scene, [particles] * members),
                                 np.full((members, particles.n_actuators), 0.1), frames)
        batch.update(members=members)
    sim = Simulator(scene, particles, requires_grad=True, max_frames=backward_frames)
    actions = 0.1 * np.sin(np.arange(backward_frames)[:, None] * 0.3 + np.arange(sim.n_actuators))
    seed = np.tile([1.0, 0.0, 0.0], (backward_frames + 1, 1)) / backward_frames
    sim.rollout(actions)
    sim.backward(com_v=seed)  # compiles
    ti.profiler.clear_kernel_profiler_info()
    t0 = time.perf_counter()
    sim.rollout(actions)
    sim.backward(com_v=seed)
    both = _kernel_profile(sum(sim.frame_substeps), time.perf_counter() - t0)
    return dict(measure="profile", arch=case.arch, particles=sim.n, forward=forward, forward_backward=both,
                **({"batch": batch} if batch else {}))


def measure_batch(case: Case, members: int = 8, frames: int = 5, repeats: int = 5) -> dict:
    """Throughput of `members` episodes in one BatchSimulator against the same episodes one after
    the other in one Simulator (reset between them, as `play` does), timed alternately."""
    from codesign_mpm import build_particles
    from codesign_mpm.engine.batch import BatchSimulator
    from codesign_mpm.engine import Simulator

    scene = robot_scene(case)
    particles = build_particles(scene)
    batch = BatchSimulator(scene, [particles] * members)
    alone = Simulator(scene, particles)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.3, 0.3, (frames, members, particles.n_actuators))
    batch.step(actions[0])  # compile (or load from the offline cache)
    alone.step(actions[0, 0])
    together, sequential = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        batch.reset()
        for a in actions:
            batch.step(a)
        together.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        for b in range(members):
            alone.reset()
            for a in actions:
                alone.step(a[b])
        sequential.append(time.perf_counter() - t0)
    work = members * particles.n * frames * alone.timestep.substeps
    return dict(measure="batch", members=members, particles_per_member=particles.n,
                substeps_per_frame=alone.timestep.substeps, frames=frames,
                batch_particle_substeps_per_s=work / float(np.median(together)),
                sequential_particle_substeps_per_s=work / float(np.median(sequential)),
                speedup=float(np.median(np.asarray(sequential) / np.asarray(together))))


def measure_scatter(case: Case, frames: int = 3, repeats: int = 5) -> dict:
    """Forward throughput with p2g's private grids (the CPU default) against one grid with atomic
    adds, in one process, timed alternately."""
    from codesign_mpm import build_particles, runtime
    from codesign_mpm.engine import Simulator

    scene = robot_scene(case)
    particles = build_particles(scene)
    private = Simulator(scene, particles)
    os.environ["CODESIGN_SCATTER_COPIES"] = "1"
    try:
        atomic = Simulator(scene, particles)
    finally:
        del os.environ["CODESIGN_SCATTER_COPIES"]
    times: dict[str, list[float]] = {"private": [], "atomic": []}
    for sim in (private, atomic):
        sim.step(np.zeros(sim.n_actuators))  # compile (or load from the offline cache)
    for r in range(repeats):
        for name, sim in (("private", private), ("atomic", atomic)):
            t0 = time.perf_counter()
            sim.step(np.full(sim.n_actuators, 0.1 * (-1) ** r), frames=frames)
            times[name].append(time.perf_counter() - t0)
    work = particles.n * frames * private.timestep.substeps
    return dict(measure="scatter", particles=particles.n, copies=runtime.scatter_copies(),
                private_particle_substeps_per_s=work / float(np.median(times["private"])),
                atomic_particle_substeps_per_s=work / float(np.median(times["atomic"])),
                speedup=float(np.median(np.asarray(times["atomic"]) / np.asarray(times["private"]))))


def measure_adaptive(case: Case, frames: int = 3, repeats: int = 5) -> dict:
    """Wall time per frame with the state-following time step (`scene.adaptive_dt`, the default)
    against the step at rest throughout, in one process, timed alternately; the robot driven at
    the action bound, so the guard has something to follow."""
    from codesign_mpm import build_particles
    from codesign_mpm.engine import Simulator

    scene = robot_scene(case)
    particles = build_particles(scene)
    sims = {"adaptive": Simulator(scene, particles), "fixed": Simulator(replace(scene, adaptive_dt=False), particles)}
    times: dict[str, list[float]] = {name: [] for name in sims}
    for sim in sims.values():
        sim.step(np.zeros(sim.n_actuators))  # compile (or load from the offline cache)
    for r in range(repeats):
        for name, sim in sims.items():
            t0 = time.perf_counter()
            sim.step(np.full(sim.n_actuators, 0.3 * (-1) ** r), frames=frames)
            times[name].append(time.perf_counter() - t0)
    adaptive = sims["adaptive"].frame_substeps[1:]
    return dict(measure="adaptive", particles=particles.n, substeps_at_rest=sims["fixed"].timestep.substeps,
                adaptive_substeps_mean=float(np.mean(adaptive)), adaptive_substeps_max=int(max(adaptive)),
                adaptive_s_per_frame=float(np.median(times["adaptive"])) / frames,
                fixed_s_per_frame=float(np.median(times["fixed"])) / frames,
                cost=float(np.median(np.asarray(times["adaptive"]) / np.asarray(times["fixed"]))))


FLIP_MEASURED = 0.99  # the share docs/log/contact.md measured converging in time


def _timed_pair(variants: dict, frames: int, repeats: int, backward_frames: int) -> dict:
    """Wall time per frame forward and per differentiable episode (forward + backward) of two
    scene variants (name -> Scene, the measured one first), in one process, timed alternately;
    the costs are the medians of the first's time over the second's."""
    from codesign_mpm import build_particles
    from codesign_mpm.engine import Simulator

    particles = build_particles(next(iter(variants.values())))
    sims = {name: Simulator(v, particles) for name, v in variants.items()}
    grads = {name: Simulator(v, particles, requires_grad=True, max_frames=backward_frames)
             for name, v in variants.items()}
    actions = 0.1 * np.sin(np.arange(backward_frames)[:, None] * 0.3 + np.arange(particles.n_actuators))
    for name in variants:  # compile (or load from the offline cache)
        sims[name].step(np.zeros(particles.n_actuators))
        grads[name].rollout(actions[:1])
        grads[name].backward(com_v=np.ones((2, 3)))
    forward: dict[str, list[float]] = {name: [] for name in variants}
    backward: dict[str, list[float]] = {name: [] for name in variants}
    for r in range(repeats):
        for name in variants:
            t0 = time.perf_counter()
            sims[name].step(np.full(particles.n_actuators, 0.3 * (-1) ** r), frames=frames)
            forward[name].append((time.perf_counter() - t0) / frames)
            t0 = time.perf_counter()
            grads[name].rollout(actions)
            grads[name].backward(com_v=np.tile([1.0, 0.0, 0.0], (backward_frames + 1, 1)))
            backward[name].append(time.perf_counter() - t0)
    first, second = variants
    ratio = lambda d: float(np.median(np.asarray(d[first]) / np.asarray(d[second])))  # noqa: E731
    return {"particles": particles.n, f"{first}_s_per_frame": float(np.median(forward[first])),
            f"{second}_s_per_frame": float(np.median(forward[second])), "forward_cost": ratio(forward),
            "episode_frames": backward_frames, f"{first}_episode_s": float(np.median(backward[first])),
            f"{second}_episode_s": float(np.median(backward[second])), "forward_backward_cost": ratio(backward)}


def measure_flip(case: Case, frames: int = 3, repeats: int = 5, backward_frames: int = 20) -> dict:
    """What the FLIP share of the velocity update costs (docs/log/contact.md section 10): `scene.flip`
    0.99 against APIC alone (flip 0, a bare scene's default)."""
    scene = robot_scene(case)
    variants = {"flip": replace(scene, flip=FLIP_MEASURED), "apic": replace(scene, flip=0.0)}
    return dict(measure="flip", flip=FLIP_MEASURED, **_timed_pair(variants, frames, repeats, backward_frames))


def measure_contact(case: Case, frames: int = 3, repeats: int = 5, backward_frames: int = 20) -> dict:
    """What the surface contact costs (docs/log/contact.md section 15): `terrain.contact: surface`
    against the node contact, both with the FLIP share of a recipe."""
    scene = replace(robot_scene(case), flip=FLIP_MEASURED)
    variants = {"surface": replace(scene, terrain=replace(scene.terrain, contact="surface")), "nodes": scene}
    return dict(measure="contact", **_timed_pair(variants, frames, repeats, backward_frames))


COVERS = ("none", "sand", "snow", "clay", "mud", "water")
"""What `measure_compile` puts under the robot: each material's own backward kernels."""


def measure_compile(cover: str, dtype: str = "float32") -> dict:
    """Seconds to compile a new scene's kernels with an empty offline cache: the muscle-actuated
    robot of scale `tiny` on a layer of `cover` ("none": bare ground), forward (first frame of a
    rollout) and backward (its first backward pass)."""
    import tempfile

    os.environ["CODESIGN_TAICHI_CACHE"] = tempfile.mkdtemp(prefix="codesign-bench-cache-")  # cold
    from codesign_mpm import BodySpec, MaterialSpec, ShapeSpec, build_particles
    from codesign_mpm.engine import Simulator

    scene = robot_scene(Case("tiny", dtype))
    if cover != "none":
        scene.bodies.append(BodySpec(name="cover", shape=ShapeSpec(kind="layer", thickness=0.05),
                                     material=MaterialSpec(kind=cover)))
    t0 = time.perf_counter()
    sim = Simulator(scene, build_particles(scene), requires_grad=True, max_frames=1)
    sim.rollout(np.zeros((1, sim.n_actuators)))
    forward = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim.backward(com_v=np.ones((2, 3)))
    backward = time.perf_counter() - t0
    return dict(measure="compile", cover=cover, dtype=dtype, forward_s=round(forward, 1), backward_s=round(backward, 1),
                total_s=round(forward + backward, 1))


def run_compile_bench(covers: list[str], dtype: str, emit, progress: bool = True) -> None:
    """Emit one JSON object per cover, each compiled cold in its own process."""
    from codesign.progress import progress_bar

    machine = _machine()
    for cover in progress_bar(covers, desc="bench compile", unit="scene", show=progress):
        emit(dict(**{"measure": "compile", "cover": cover, **_in_subprocess("compile", cover, dtype)}, **machine))


def _machine() -> dict:
    return dict(machine=platform.machine(), cpus=os.cpu_count(), python=platform.python_version())


def _in_subprocess(*args: str, environment: dict | None = None) -> dict:
    """Run `python -m codesign_mpm.reports.bench ARGS` and return its JSON record (or the error line)."""
    record, error = run_module("codesign_mpm.reports.bench", *args, environment=environment)
    return dict(error=error) if error else record


def _run_isolated(kind: str, case: Case, environment: dict | None = None, **kwargs) -> dict:
    return {"measure": kind, **_in_subprocess(kind, case.scale, case.dtype, case.grid_region, case.arch,
                                              json.dumps(kwargs), environment=environment)}


def run_profile_bench(scales: list[str], arch: str, emit, progress: bool = True, members: int = 0) -> None:
    """Emit, per scale, where a substep's time goes (`measure_profile`, with a batch of `members`
    if given), on `arch`."""
    from codesign.progress import progress_bar

    machine = _machine()
    with progress_bar(total=len(scales), desc="bench engine --profile", unit="scale", show=progress) as bar:
        for scale in scales:
            emit(dict(scale=scale, dtype="float32", **_run_isolated(
                "profile", Case(scale, "float32", arch=arch), environment={"CODESIGN_KERNEL_PROFILER": "1"},
                members=members),
                **machine))
            bar.update(1)


def run_engine_bench(scales: list[str], frames: int, emit, progress: bool = True, arch: str = "cpu",
                     measures: tuple[str, ...] = ENGINE_MEASURES, members: int = 8,
                     segment_memory_mb: tuple[int, ...] = ()) -> None:
    """Emit one JSON object per measurement (see docs/performance.md for what each means); the
    backward one at each of `segment_memory_mb` (the differentiable episode's budget for its states,
    CODESIGN_SEGMENT_MEMORY_MB; none given: the engine's default): memory against time."""
    from codesign.progress import progress_bar

    machine = _machine()
    options = {"backward": dict(frames=frames, repeats=3), "batch": dict(members=members)}
    budgets = {"backward": [{"CODESIGN_SEGMENT_MEMORY_MB": str(mb)} for mb in segment_memory_mb] or [None]}
    runs = [(scale, measure, environment) for scale in scales for measure in measures
            for environment in budgets.get(measure, [None])]
    with progress_bar(total=len(runs), desc="bench engine", unit="measure", show=progress) as bar:
        for scale, measure, environment in runs:
            dtype = "float64" if measure == "float64" else "float32"
            case = Case(scale, dtype, "full" if measure == "dense" else "bbox", arch)
            kind = "forward" if measure in ("float64", "dense") else measure
            emit(dict(scale=scale, dtype=dtype, grid_region=case.grid_region, arch=arch,
                      **_run_isolated(kind, case, environment=environment, **options.get(measure, {})), **machine))
            bar.update(1)


# `codesign bench environments`: one scene per environment preset, forward throughput.
ENV_SCALES = {
    # the paper's scale: dx 1/128 and about 144k particles; the cover's thickness is solved for
    # that count (the ocean's water instead covers the robot, at one particle per cell)
    "paper": dict(dx=1 / 128, particles=144_000),
    "small": dict(dx=1 / 64, particles=18_000),
}
OLD_MS_PER_SUBSTEP = {"ocean": 208.0, "desert": 245.0, "snow": 245.0, "clay": 245.0, "wetland": 245.0}
"""The old SoftZoo code at the paper's scale (41 substeps per control step), for comparison."""


def environment_particles(name: str, scale: str, arch: str = "cpu"):
    """The preset's scene and particles at `scale`, with the cover thick enough for its count."""
    from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS, RobotConfig, TerrainConfig
    from codesign_mpm.environment.env import LocomotionEnv

    s, preset = ENV_SCALES[scale], PRESETS[name]
    target = s["particles"]
    config = PRESET_CONFIGS[name](dx=s["dx"], size=[1.0, 0.5, 0.5], arch=arch, terrain=TerrainConfig(
        height=0.05, friction=preset.friction), robot=RobotConfig(size=[0.25, 0.12, 0.12], position=[0.5, 0.25],
                                                                 youngs_modulus=preset.robot_youngs_modulus))
    if name == "ocean":  # water deep enough to cover the robot, one particle per cell
        config.cover.thickness, config.cover.particles_per_cell = 0.14, 1
    env = LocomotionEnv(config, preset)
    if config.cover.kind != "none" and name != "ocean":
        # the count grows linearly with the thickness (less the robot's cells): one secant step
        for _ in range(2):
            per_thickness = env.cover_particles.n / config.cover.thickness
            config.cover.thickness += (target - env.particles.n) / per_thickness
            env = LocomotionEnv(config, preset)
    return env.scene, env.particles


def measure_environment(name: str, scale: str, arch: str = "cpu", frames: int = 3, repeats: int = 3) -> dict:
    """Forward particle-substeps/s, substeps per control step and ms per substep of one preset."""
    from codesign_mpm.engine import Simulator

    from codesign_mpm.environment.settle import settled_state

    scene, particles = environment_particles(name, scale, arch)
    t0 = time.perf_counter()
    F, jp = settled_state(scene, particles)  # the environments' default start: its whole cost
    settle_s = time.perf_counter() - t0
    sim = Simulator(scene, particles)
    sim.set_initial_state(F=F, Jp=jp)
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    sim.step(rng.uniform(-0.3, 0.3, sim.n_actuators))  # compiles (or loads from the offline cache)
    first = time.perf_counter() - t0
    seconds = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(frames):
            sim.step(rng.uniform(-0.3, 0.3, sim.n_actuators))
        seconds.append((time.perf_counter() - t0) / (frames * sim.timestep.substeps))
    per_substep = float(np.median(seconds))
    record = dict(measure="environment", environment=name, arch=arch, particles=sim.n,
                  materials=sorted({b.material.kind for b in scene.bodies}),
                  substeps_per_control_step=sim.timestep.substeps, dt=sim.timestep.dt,
                  ms_per_substep=round(1e3 * per_substep, 3), particle_substeps_per_s=sim.n / per_substep,
                  wall_s_per_simulated_s=round(per_substep * sim.timestep.substeps / scene.frame_dt, 2),
                  first_frame_s=round(first, 3), settled_start_s=round(settle_s, 4))
    if scale == "paper" and name in OLD_MS_PER_SUBSTEP:
        record["old_ms_per_substep"] = OLD_MS_PER_SUBSTEP[name]
    sim.close()
    return record


def run_environment_bench(scales: list[str], names: list[str], emit, progress: bool = True,
                          arch: str = "cpu") -> None:
    """Emit one JSON object per (scale, environment), each measured in its own process."""
    from codesign.progress import progress_bar

    machine = _machine()
    cases = [(scale, name) for scale in scales for name in names]
    for scale, name in progress_bar(cases, desc="bench environments", unit="env", show=progress):
        record = {"measure": "environment", "environment": name, **_in_subprocess("environment", name, scale, arch)}
        emit(dict(scale=scale, **record, **machine))


if __name__ == "__main__":  # one isolated measurement, used by _run_isolated / run_environment_bench
    if sys.argv[1] == "environment":
        print(json.dumps(measure_environment(*sys.argv[2:5])))
    elif sys.argv[1] == "compile":
        print(json.dumps(measure_compile(sys.argv[2], sys.argv[3])))
    else:
        kind, scale, dtype, region, arch, kwargs = sys.argv[1:7]
        measure = {"forward": measure_forward, "backward": measure_backward, "batch": measure_batch,
                   "scatter": measure_scatter, "adaptive": measure_adaptive, "flip": measure_flip,
                   "contact": measure_contact, "profile": measure_profile}[kind]
        print(json.dumps(measure(Case(scale, dtype, region, arch), **json.loads(kwargs))))
