"""Compiled storages: reused by simulators of the same layout, freed beyond a few or beyond a memory
budget, and a Taichi program with too many freed ones recycled once no simulator is alive (bounded
memory in sweeps)."""
from dataclasses import replace

import numpy as np

from codesign_mpm import BodySpec, Scene, ShapeSpec, build_particles, runtime
from codesign_mpm.engine import storage as engine  # the pool of compiled storages
from codesign_mpm.engine import Simulator
from codesign_mpm.materials import MODEL_NAMES

SCENE = Scene(size=[0.5, 0.5, 0.5], dx=1 / 24, bodies=[BodySpec(shape=ShapeSpec(size=[0.12, 0.12, 0.12]),
                                                                 center=[0.25, 0.2, 0.25])])


def fall(max_frames: int) -> tuple[Simulator, np.ndarray]:
    """A simulator of a layout of its own (its rows follow max_frames) and where its box falls to."""
    sim = Simulator(SCENE, build_particles(SCENE), max_frames=max_frames)
    sim.step(frames=3)
    return sim, sim.particles_state()[0]


def test_a_closed_simulators_storage_serves_the_next_of_its_layout():
    first, x_first = fall(1)
    storage = first.k
    first.close()
    again, x_again = fall(1)
    assert again.k is storage  # no new fields, no compile
    np.testing.assert_array_equal(x_again, x_first)
    again.close()


def test_freed_storages_are_bounded_by_recycling_an_idle_program(monkeypatch):
    monkeypatch.setattr(engine, "MAX_FREE_STORAGES", 0)  # every closed storage is freed at once
    monkeypatch.setattr(engine, "MAX_DEAD_STORAGES", 0)  # and one freed storage is one too many
    generation = runtime.generation
    first, x_first = fall(1)
    first.close()
    second, x_second = fall(2)  # finds a freed storage and no live simulator: a fresh program
    recycled = runtime.generation
    assert recycled > generation and engine._freed == []
    np.testing.assert_array_equal(x_second, x_first)
    Simulator(SCENE, build_particles(SCENE), max_frames=3).close()  # second is alive: no recycling
    Simulator(SCENE, build_particles(SCENE), max_frames=4).close()
    assert runtime.generation == recycled and len(engine._freed) == 2
    second.step(frames=1)  # and it still runs
    assert np.isfinite(second.particles_state()[0]).all()
    second.close()


def test_released_storages_are_kept_within_their_memory_budget_the_newest_always(monkeypatch):
    first, _ = fall(1)
    second, _ = fall(2)  # another layout: its own storage, as large
    storages = first.k, second.k
    state_bytes = first.k.layout.capacity * 2 * 24 * 4  # x, v, C and F in 2 slots, float32
    assert all(s.nbytes > state_bytes for s in storages), [s.nbytes for s in storages]  # the grids come on top
    monkeypatch.setattr(engine, "FREE_STORAGE_BYTES", first.k.nbytes + second.k.nbytes - 1)
    first.close()
    second.close()  # both kept would exceed the budget: the older one goes
    kept = [s for _, s in engine._free.values()]
    assert storages[1] in kept and storages[0] not in kept
    monkeypatch.setattr(engine, "FREE_STORAGE_BYTES", 0)
    third, _ = fall(3)
    newest = third.k
    third.close()  # alone over the budget, the newest is kept all the same
    assert [s for _, s in engine._free.values()] == [newest]


def test_a_slot_of_particle_state_takes_what_its_layout_says():
    """Layout.slot_bytes sizes the default differentiable segment: it must count every field with a
    slot axis (x, v, C, F, J_p beside plastic parameters, the springs) and their gradients."""
    runtime.init_taichi("cpu", "float32")
    snow = next(i for i, name in MODEL_NAMES.items() if name == "snow")
    every = engine.Layout(capacity=1024, n_actuators=2, slots=3, rows=2, grid_shape=(8, 8, 8), models=(0, snow),
                          has_muscles=True, muscle_model="active", has_terrain=True, boundary_cells=3,
                          requires_grad=True, surface_contact=True, contact_memory=True)
    for layout in (every, replace(every, models=(0,), surface_contact=False, contact_memory=False),
                   replace(every, requires_grad=False)):
        three, four = engine._Storage(layout), engine._Storage(replace(layout, slots=4))
        try:
            assert four.nbytes - three.nbytes == layout.slot_bytes(4), layout
        finally:
            three.free()
            four.free()
    assert every.slot_bytes(4) == 1024 * (24 + 1 + 3) * 4 * 2
