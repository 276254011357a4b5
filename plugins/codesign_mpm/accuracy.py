"""What accuracy costs in time: error of a known answer against wall time, per setting.

The known answer is the fundamental of a free-free elastic bar: with Poisson's ratio 0 the
bar is exactly one-dimensional in the small-strain limit, and its first longitudinal mode
rings at f = sqrt(E / rho) / (2 L). The bar starts in that mode (v = v0 cos(pi x / L)); we
measure its length oscillation and compare the frequency. Sweeps vary one setting at a time
around a reference (dx 1/32, 8 particles per cell, cfl 0.4, float32).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

LENGTH, SECTION, E, RHO, V0 = 0.4, 0.1, 1.0e4, 1.0e3, 0.05
EXACT_HZ = math.sqrt(E / RHO) / (2 * LENGTH)


@dataclass(frozen=True)
class Setting:
    dx: float = 1 / 32
    particles_per_cell: int = 8
    cfl: float = 0.4
    dtype: str = "float32"


REFERENCE = Setting()
SWEEPS = {
    "dx": [Setting(dx=d) for d in (1 / 20, 1 / 24, 1 / 32, 1 / 48, 1 / 64)],
    "particles_per_cell": [Setting(particles_per_cell=n) for n in (1, 8, 27)],
    "cfl": [Setting(cfl=c) for c in (0.1, 0.2, 0.4, 0.8)],
    "dtype": [Setting(dtype="float64")],  # compare with the float32 reference of the other sweeps
}


def bar_scene(s: Setting):
    from codesign_mpm import BodySpec, MaterialSpec, Scene, ShapeSpec, TerrainSpec

    return Scene(size=[1.0, 0.5, 0.5], dx=s.dx, gravity=[0.0, 0.0, 0.0], cfl=s.cfl, dtype=s.dtype,
                 terrain=TerrainSpec(kind="none"),
                 bodies=[BodySpec(name="bar", shape=ShapeSpec(size=[LENGTH, SECTION, SECTION]),
                                  center=[0.5, 0.25, 0.25], particles_per_cell=s.particles_per_cell,
                                  material=MaterialSpec(youngs_modulus=E, poisson_ratio=0.0, density=RHO))])


def ringing_frequency(lengths: np.ndarray, frame_dt: float) -> float:
    """Frequency from the mean spacing of zero crossings of the length oscillation."""
    signal = lengths - lengths.mean()
    i = np.nonzero(np.signbit(signal[:-1]) != np.signbit(signal[1:]))[0]
    crossings = (i + signal[i] / (signal[i] - signal[i + 1])) * frame_dt  # linear interpolation
    if len(crossings) < 3:
        raise RuntimeError("too few oscillations to measure a frequency")
    return 1.0 / (2 * np.diff(crossings).mean())


def measure(s: Setting, periods: float = 2.6) -> dict:
    from codesign_mpm import build_particles
    from codesign_mpm.engine import Simulator

    scene = bar_scene(s)
    particles = build_particles(scene)
    xi = (particles.x[:, 0] - scene.bodies[0].center[0]) / LENGTH + 0.5  # 0 .. 1 along the bar
    particles.v[:, 0] = V0 * np.cos(np.pi * xi)
    sim = Simulator(scene, particles)
    left, right = xi < 0.1, xi > 0.9
    frames = int(math.ceil(periods / EXACT_HZ / scene.frame_dt))
    lengths = [LENGTH]
    sim.step()  # compiles or loads the kernels; not part of the timing
    t0 = time.perf_counter()
    for _ in range(frames):
        sim.step()
        x = sim.particles_state()[0][:, 0]
        lengths.append(x[right].mean() - x[left].mean())
    wall = time.perf_counter() - t0
    sim.close()
    freq = ringing_frequency(np.asarray(lengths[1:]), scene.frame_dt)
    return dict(dx=s.dx, particles_per_cell=s.particles_per_cell, cfl=s.cfl, dtype=s.dtype, particles=sim.n,
                substeps_per_frame=sim.timestep.substeps, frames=frames, frequency_hz=freq, exact_hz=EXACT_HZ,
                relative_error=abs(freq - EXACT_HZ) / EXACT_HZ, wall_s=wall,
                wall_s_per_simulated_s=wall / (frames * scene.frame_dt))


def run_accuracy_bench(sweeps: list[str], emit, progress: bool = True) -> None:
    """Emit one JSON object per setting of each requested sweep (float64 last: it re-initialises Taichi)."""
    from codesign.progress import progress_bar

    cases = [(name, setting) for name in sorted(sweeps, key=lambda n: n == "dtype") for setting in SWEEPS[name]]
    for name, setting in progress_bar(cases, desc="bench accuracy", unit="setting", show=progress):
        emit(dict(measure="accuracy", sweep=name, **measure(setting)))
