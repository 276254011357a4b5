"""The MLS-MPM physics plugin: scenes, materials, terrain and the differentiable simulator.

Usable as a library without the registry::

    from codesign_mpm import Scene, BodySpec, build_particles, Simulator
    scene = Scene(bodies=[BodySpec(center=[0.5, 0.2, 0.5])])
    sim = Simulator(scene, build_particles(scene))
    sim.step(frames=10)

Importing this package does not import Taichi; `Simulator` is loaded on first use.
"""
import sys

from codesign_mpm.scene.sampling import Particles, build_particles
from codesign_mpm.scene.spec import BodySpec, MaterialSpec, MuscleSpec, Scene, SceneError, ShapeSpec, TerrainSpec

if "gymnasium" in sys.modules:  # register the Gymnasium ids now; otherwise `import codesign_mpm.environment.gym` does
    import codesign_mpm.environment.gym  # noqa: F401

__all__ = ["BodySpec", "MaterialSpec", "MuscleSpec", "Particles", "Scene", "SceneError", "ShapeSpec",
           "Simulator", "SimulationError", "TerrainSpec", "build_particles"]


def __getattr__(name: str):
    if name in ("Simulator", "SimulationError", "Gradients", "Rollout", "State", "time_step"):
        from codesign_mpm import engine

        return getattr(engine, name)
    raise AttributeError(name)
