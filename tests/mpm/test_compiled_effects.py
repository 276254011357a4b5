"""A scene pays only for the effects it has: the substep is specialised with `ti.static`, so the
code of a material, of plastic return mappings and of muscles is traced into the kernels only
when the scene has it. We record every Taichi function traced while the kernels of one step are
built (tracing happens on every compile, offline-cache hits included, since the cache key is
computed from the traced code)."""
import pytest
from taichi.lang import kernel_impl

from codesign_mpm import BodySpec, MaterialSpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine import MODEL_NAMES, Simulator

MATERIAL_FUNCS = ("_constitutive", "_plastic", "_elastic_stress")


@pytest.fixture
def traced(monkeypatch):
    """(function name, material model name or None) of every Taichi function traced."""
    calls: set[tuple[str, str | None]] = set()
    original = kernel_impl.Func.__call__

    def spy(self, *args, **kwargs):
        name = self.func.__name__
        calls.add((name, MODEL_NAMES[args[1]] if name in MATERIAL_FUNCS else None))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(kernel_impl.Func, "__call__", spy)
    return calls


def step_once(*kinds: str, muscles: bool = False) -> None:
    bodies = [BodySpec(name=f"b{i}", shape=ShapeSpec(size=[0.1, 0.1, 0.1]), center=[0.3, 0.15 + 0.13 * i, 0.3],
                       material=MaterialSpec(kind=kind), robot=muscles and i == 0,
                       muscles=MuscleSpec(groups=[2, 1, 1]) if muscles and i == 0 else None)
              for i, kind in enumerate(kinds)]
    scene = Scene(size=[0.6, 0.6, 0.6], dx=1 / 24, terrain=TerrainSpec(kind="none"), bodies=bodies)
    sim = Simulator(scene, build_particles(scene))
    sim.step()
    sim.close()


def materials(calls) -> set[str]:
    return {model for name, model in calls if name == "_constitutive"}


def test_an_elastic_scene_traces_no_plastic_water_or_muscle_code(traced):
    step_once("neo_hookean")
    assert materials(traced) == {"neo_hookean"}
    assert not {name for name, _ in traced} & {"_plastic", "_spectral", "_frame", "_muscle_stress"}


def test_each_material_brings_its_own_code_and_only_its_own(traced):
    step_once("sand", "water", "neo_hookean")
    assert materials(traced) == {"sand", "water", "neo_hookean"}  # no snow, clay or mud
    assert {model for name, model in traced if name == "_plastic"} == {"sand"}  # water has no return mapping
    assert ("_elastic_stress", "neo_hookean") in traced


def test_muscle_code_is_traced_only_for_a_scene_with_muscles(traced):
    step_once("neo_hookean", muscles=True)
    assert "_muscle_stress" in {name for name, _ in traced}
