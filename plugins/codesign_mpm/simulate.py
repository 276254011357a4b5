"""`codesign simulate`: run a scene file headless, report throughput, optionally export states.

Scene files are YAML for the `Scene` dataclass. Bodies are merged one by one into `BodySpec`
so an error inside the list still names its full key (OmegaConf alone drops ``bodies[i]``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from codesign.errors import CodesignError
from codesign_mpm.scene.quality import QUALITY, Quality
from codesign_mpm.scene.sampling import build_particles
from codesign_mpm.scene.spec import BodySpec, Scene, SceneError, validate_scene


class SceneFileError(CodesignError):
    """A scene file that cannot be read, parsed, validated or simulated as written."""


def _structured(schema: type, data: object, prefix: str, source: Path) -> object:
    try:
        return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), OmegaConf.create(data)))
    except OmegaConfBaseException as exc:
        key = f"{prefix}{exc.full_key}" if exc.full_key else prefix.rstrip(".") or "(top level)"
        message = str(getattr(exc, "msg", exc)).splitlines()[0]
        raise SceneFileError(f"{source}: {key}: {message}") from None


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file; every problem becomes one `SceneFileError` line."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise SceneFileError(f"cannot read scene {path}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise SceneFileError(f"{path}: not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise SceneFileError(f"{path}: expected a mapping of scene keys, got {type(data).__name__}")
    bodies = data.pop("bodies", [])
    if not isinstance(bodies, list):
        raise SceneFileError(f"{path}: bodies: expected a list of bodies, got {type(bodies).__name__}")
    if "quality" in data:  # a preset for dx, cfl, dtype and each body's particles_per_cell; explicit keys win
        name = data.pop("quality")
        if name not in QUALITY:
            raise SceneFileError(f"{path}: quality: {name!r} is not a quality preset; allowed: {', '.join(QUALITY)}")
        preset = QUALITY[name]
        data = {"dx": preset.dx, "cfl": preset.cfl, "dtype": preset.dtype, **data}
        bodies = [{"particles_per_cell": _preset_particles_per_cell(preset, body), **body}
                  if isinstance(body, dict) else body for body in bodies]
    scene = _structured(Scene, data, "", path)
    scene.bodies = [_structured(BodySpec, body, f"bodies[{i}].", path) for i, body in enumerate(bodies)]
    try:
        validate_scene(scene)
    except SceneError as exc:
        raise SceneFileError(f"{path}: {exc}") from None
    return scene


def _preset_particles_per_cell(preset: Quality, body: dict) -> int:
    """A layer (a ground cover) takes the preset's cover count, any other body the robot's."""
    shape = body.get("shape")
    is_layer = isinstance(shape, dict) and shape.get("kind") == "layer"
    return preset.cover_particles_per_cell if is_layer else preset.particles_per_cell


@dataclass
class SimulationReport:
    particles: int
    grid: tuple[int, int, int]
    substeps: int
    dt: float
    frames: int
    build_time: float
    """Seconds to sample particles and set up the simulator."""
    first_frame_time: float
    """Seconds of the first frame, which compiles (or loads) the kernels on first use."""
    wall_time: float
    """Seconds spent stepping, all frames."""

    @property
    def particle_substeps_per_second(self) -> float:
        """Throughput after the first frame, so a kernel compile does not distort it."""
        frames, seconds = self.frames - 1, self.wall_time - self.first_frame_time
        if frames < 1:
            frames, seconds = self.frames, self.wall_time
        return self.particles * self.substeps * frames / max(seconds, 1e-9)


def simulate(scene: Scene, frames: int, export: Path | None = None, progress: bool = True) -> SimulationReport:
    """Simulate ``frames`` frames with zero actions; with ``export``, save every frame's x and v."""
    from codesign.progress import progress_bar
    from codesign_mpm.engine import SimulationError, Simulator

    started = time.perf_counter()
    try:
        particles = build_particles(scene)
        sim = Simulator(scene, particles)
    except SceneError as exc:
        raise SceneFileError(str(exc)) from None
    build_time = time.perf_counter() - started
    keep = export is not None
    xs = np.empty((frames + 1, particles.n, 3), np.float32) if keep else None
    vs = np.empty_like(xs) if keep else None
    started = time.perf_counter()
    first_frame_time = 0.0
    try:
        if keep:
            xs[0], vs[0] = sim.particles_state()[:2]
        for frame in progress_bar(range(frames), desc="simulate", unit="frame", show=progress):
            sim.step()
            if keep:
                xs[frame + 1], vs[frame + 1] = sim.particles_state()[:2]
            if frame == 0:
                first_frame_time = time.perf_counter() - started
    except SimulationError as exc:
        raise SceneFileError(f"simulation failed: {exc}") from None
    finally:
        sim.close()
    report = SimulationReport(particles.n, scene.grid_shape, sim.timestep.substeps, sim.timestep.dt, frames,
                              build_time, first_frame_time, time.perf_counter() - started)
    if keep:
        from codesign_mpm.scene.terrain import height_map

        # muscle, robot, actions (all zero here), dx and height_map are for `codesign render`
        np.savez_compressed(export, x=xs, v=vs, material=particles.material.astype(np.int32),
                            body=particles.body.astype(np.int32), frame_dt=np.float64(scene.frame_dt),
                            muscle=particles.muscle.astype(np.float32), robot=particles.robot.astype(bool),
                            actions=np.zeros((frames, particles.n_actuators), np.float32),
                            dx=np.float64(scene.dx), height_map=height_map(scene).astype(np.float32))
    return report
