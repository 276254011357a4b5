"""Robot bodies and design representations on the engine: animals and body files as robots, every
representation in every environment, and one end-to-end gradient per representation.

Forward runs use dx = 1/32 in float32. The gradient checks share one float64 simulator (the ground
scene of gradient_checks.py) and feed each representation's
fields to it through the torch bridge without dropping particles: volume = base volume x
occupancy keeps the particle layout whatever the design.
"""
import warnings

import numpy as np
import pytest
import torch
import trimesh

from codesign.errors import RecipeError
from codesign.plugins import get_registry
from codesign_mpm.environment.bridge import simulate
from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS, RobotConfig, TaskConfig, TerrainConfig
from codesign_mpm.engine import Simulator
from codesign_mpm.engine.time_step import time_step
from codesign_mpm.scene.sampling import build_particles
from codesign_mpm.environment.env import LocomotionEnv
from codesign_mpm.scene.spec import BodySpec, MuscleSpec, Scene, SceneError, ShapeSpec, validate_scene
from test_environments import ENVIRONMENTS  # same folder: pytest puts it on sys.path

REPRESENTATIONS = ["particle", "voxel", "implicit", "diff_cppn", "sdf_lerp", "wasserstein"]
ANIMALS = ["seal", "caterpillar", "fish", "panda"]
ANIMAL_SIZE = [0.3, 0.15, 0.15]


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Design tensors are small: on two shared cores a second torch thread only waits."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def make_env(name: str = "ground", dtype: str = "float32", task: str = "movement_speed", **robot) -> LocomotionEnv:
    preset = PRESETS[name]
    config = PRESET_CONFIGS[name](dx=1 / 32, horizon=50, dtype=dtype, terrain=TerrainConfig(
        height=0.1, friction=preset.friction), robot=RobotConfig(youngs_modulus=preset.robot_youngs_modulus, **robot),
        task=TaskConfig(name=task))
    return LocomotionEnv(config, preset)


def gait(env: LocomotionEnv, t: int, amplitude: float = 0.3) -> np.ndarray:
    """A travelling wave over the actuators, one period every 10 control steps."""
    k = env.action_dim
    return amplitude * np.sin(2 * np.pi * (t / 10 - np.arange(k) / k))


def displacement(env: LocomotionEnv, steps: int, amplitude: float) -> np.ndarray:
    start = env.reset()[:3]
    for t in range(steps):
        observation = env.step(gait(env, t, amplitude)).observation
    assert np.isfinite(env.sim.particles_state()[0]).all()
    return observation[:3] - start


@pytest.mark.slow
@pytest.mark.parametrize("environment", ["ground", "ocean"])
@pytest.mark.parametrize("animal", ANIMALS)
def test_each_animal_moves_with_its_muscles(animal, environment):
    env = make_env(environment, body=animal, size=ANIMAL_SIZE)
    try:
        k = {"caterpillar": 12}.get(animal, 4)
        assert env.action_dim == k and env.design_space.muscle.shape[1] == k
        moved, still = displacement(env, 20, 0.3), displacement(env, 20, 0.0)
    finally:
        env.close()
    # beyond settling under gravity (float32: ~1e-7); measured in 20 steps: the seal 2.8e-4 in the ocean and
    # 4.6e-4 on the ground, the others 1.8e-3 to 6.3e-3
    assert np.linalg.norm(moved - still) > 1e-4, (moved, still)


def test_the_caterpillar_turns_by_its_sides_and_a_mirrored_gait_turns_it_the_other_way():
    """The body and the scene are mirror-symmetric about the caterpillar's midplane: driving both sides
    alike cannot turn it (the reason each segment has a left and a right muscle), driving one side
    turns it, and driving the other side alike turns it as fast the other way."""
    env = make_env(body="caterpillar", size=ANIMAL_SIZE, task="turning")

    def turning(left: float, right: float) -> float:
        env.reset()
        total = 0.0
        for t in range(20):
            wave = 0.3 * np.sin(2 * np.pi * (t / 10 - np.arange(6) / 6))  # tail to head, segment by segment
            total += env.step(np.stack([left * wave, right * wave], 1).ravel()).reward  # groups: left, right
        return total / 20

    try:
        assert env.action_dim == 12
        left, right, both = turning(1, 0), turning(0, 1), turning(1, 1)
    finally:
        env.close()
    assert abs(left) > 2e-4  # a measurable turn in 20 control steps (about 9e-4 per step)
    assert right == pytest.approx(-left, rel=1e-3)
    assert abs(both) < 1e-3 * abs(left)


def test_an_animal_is_sampled_with_its_groups_fibres_and_stiffness():
    env = make_env(body="panda", size=ANIMAL_SIZE)
    base, space = env.base_particles, env.design_space
    lo, hi = space.bounds
    assert (hi - lo).max() <= 0.3 + 1e-9 and (hi - lo)[1] == pytest.approx(0.15, abs=1 / 64)
    rise = np.diff(np.unique(base.x[:, 1].round(12))).min()  # the lattice's vertical spacing, about dx / 2
    assert base.x[:, 1].min() == pytest.approx(0.1 + rise / 2)  # resting on the terrain
    legs = base.muscle.sum(1) > 0
    np.testing.assert_allclose(base.fiber[legs], np.tile([0.0, 1.0, 0.0], (legs.sum(), 1)))
    np.testing.assert_allclose(base.youngs_modulus[legs], 1.2e4)  # the legs are stiffer
    np.testing.assert_array_equal(space.muscle, base.muscle)


def test_the_fixed_representation_is_the_labelled_body_with_its_passive_material_passive():
    """The panda (legs muscled, the rest passive) with the released SoftZoo's passive material: a fifth
    of the density, 10 times the stiffness; the fixed body keeps it, and its wave sets the time step."""
    plain, light = make_env(body="panda", size=ANIMAL_SIZE), make_env(body="panda", size=ANIMAL_SIZE,
                                                                      passive_density=0.2, passive_stiffness=10.0)
    try:
        passive = light.base_particles.muscle.sum(1) == 0
        assert 0.5 < passive.mean() < 0.9
        for name, factor in (("density", 0.2), ("youngs_modulus", 10.0)):
            before, after = getattr(plain.base_particles, name), getattr(light.base_particles, name)
            np.testing.assert_allclose(after[passive], factor * before[passive])
            np.testing.assert_array_equal(after[~passive], before[~passive])
        design = build_representation("fixed", light)()
        assert build_representation("fixed", light).parameters() == []
        kept = light.design_mask(design.occupancy)  # parts under 2 cells thick at dx 1/32 are dropped
        particles = light.design_particles(design)
        for name in ("density", "youngs_modulus", "muscle", "volume"):
            np.testing.assert_array_equal(getattr(particles, name)[particles.robot],
                                          getattr(light.base_particles, name)[kept], err_msg=name)
        assert (particles.muscle[particles.robot][passive[kept]] == 0).all()  # no actuation outside the groups
        # the CFL step from the passive material's P-wave, c = sqrt((lambda + 2 mu) / rho), now the fastest
        E, nu, rho = 10.0 * plain.base_particles.youngs_modulus[passive][0], 0.2, 0.2 * 1e3
        c = np.sqrt(E * (1 - nu) / ((1 + nu) * (1 - 2 * nu) * rho))
        step = time_step(light.scene, light.design_particles(design))
        assert step.stable_dt == pytest.approx(light.scene.cfl * light.scene.dx / c, rel=1e-9)
    finally:
        plain.close()
        light.close()
    with pytest.raises(RecipeError, match=r"environment.robot.passive_density: 0.2 would do nothing: robot.body 'box' "
                                          r"has no passive material"):
        make_env(passive_density=0.2)


def test_box_workspaces_are_unchanged_and_say_their_bounds():
    env = make_env()
    lo, hi = env.design_space.bounds
    np.testing.assert_allclose(hi - lo, [0.2, 0.08, 0.08], atol=1 / 64)  # the lattice cells of its particles
    assert env.action_dim == 4 and (env.design_space.muscle.sum(1) == 1).all()
    ellipsoid = make_env(body="ellipsoid")
    assert ellipsoid.base_particles.n < 0.6 * env.base_particles.n and ellipsoid.action_dim == 4


def capsule_file(tmp_path, suffix: str = ".obj"):
    path = tmp_path / f"capsule{suffix}"
    mesh = trimesh.creation.capsule(height=0.2, radius=0.05)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    mesh.export(path)
    return path


def test_a_mesh_body_from_a_file_simulates(tmp_path):
    env = make_env(body="file", body_file=str(capsule_file(tmp_path)), size=[0.24, 0.1, 0.1])
    try:
        assert env.action_dim == 4  # an unannotated file gets the grid of muscles
        lo, hi = env.design_space.bounds
        np.testing.assert_allclose(hi - lo, [0.24, 0.08, 0.08], atol=1 / 32)
        moved = displacement(env, 20, 0.3)
    finally:
        env.close()
    assert np.linalg.norm(moved) > 1e-3


def test_an_annotated_body_file_brings_its_muscles(tmp_path, cli):
    annotated = tmp_path / "capsule.npz"
    assert cli("annotate", str(capsule_file(tmp_path, ".stl")), "--groups", "5", "--merge", "3,4", "--resolution", "16",
               "--out", str(annotated))[0] == 0
    env = make_env(body="file", body_file=str(annotated), size=[0.24, 0.1, 0.1])
    try:
        assert env.action_dim == 4
        assert np.isfinite(displacement(env, 5, 0.3)).all()
    finally:
        env.close()


def test_bad_robot_bodies_are_recipe_errors_naming_the_file(tmp_path):
    broken = trimesh.creation.box()
    broken.update_faces(np.arange(len(broken.faces)) > 0)
    broken.export(tmp_path / "broken.obj")
    with pytest.raises(RecipeError, match=r"environment.robot.body_file: body file .*broken.obj: the mesh is not "
                                          r"watertight"):
        make_env(body="file", body_file=str(tmp_path / "broken.obj"))
    trimesh.creation.box(extents=[1.0, 1.0, 0.02]).export(tmp_path / "sheet.stl")
    with pytest.raises(RecipeError, match=r"shape.file = '.*sheet.stl' is invalid: fitted to size \[0.2, 0.08, 0.08\] "
                                          r"the body is 0.0016 thick along z, under one grid cell"):
        make_env(body="file", body_file=str(tmp_path / "sheet.stl"))
    with pytest.raises(RecipeError, match=r"environment.robot.body_file: None: robot.body: file needs the path"):
        make_env(body="file")
    with pytest.raises(RecipeError, match=r"environment.robot.body_file: '.*sheet.stl' is set but robot.body is 'box'"):
        make_env(body_file=str(tmp_path / "sheet.stl"))
    with pytest.raises(RecipeError, match=r"shape.body = 'panda' is invalid: its muscle group \d \(\w+ \w+ leg\) holds "
                                          r"no particle at dx = 0.03125"):
        make_env(body="panda", size=[0.08, 0.08, 0.08])


def test_a_body_thinner_than_two_grid_cells_warns_naming_dx(tmp_path):
    """A plate 1.6 cells thick (over one cell, so not refused) is sampled with a warning that names the
    file, its thinnest part, dx and the remedy; a slab 4.8 cells thick, or a ball 3.2 cells wide (whose
    curved surface steps on the lattice are not thin parts), is sampled silently."""
    trimesh.creation.box(extents=[0.3, 0.05, 0.3]).export(tmp_path / "plate.stl")
    trimesh.creation.box(extents=[0.3, 0.15, 0.3]).export(tmp_path / "slab.stl")
    trimesh.creation.icosphere(subdivisions=3).export(tmp_path / "ball.stl")

    def scene(name: str, size: float = 0.3) -> Scene:
        return Scene(size=[0.6, 0.5, 0.6], dx=1 / 32, bodies=[BodySpec(
            shape=ShapeSpec(kind="body", file=str(tmp_path / name), size=[size] * 3), center=[0.3, 0.25, 0.3])])

    with pytest.warns(UserWarning, match="dx") as caught:
        build_particles(scene("plate.stl"))
    assert [str(w.message) for w in caught if "plate.stl" in str(w.message)] == [
        f"bodies[0].shape.file = '{tmp_path / 'plate.stl'}': fitted to size [0.3, 0.3, 0.3], its thinnest part is 1.5 "
        "grid cells thick at dx = 0.03125, under the 2 cells the grid carries without tearing; give the body a larger "
        "size or the grid a finer dx"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_particles(scene("slab.stl"))
        build_particles(scene("ball.stl", size=0.1))
        build_particles(Scene(size=[0.6, 0.5, 0.6], dx=1 / 32, bodies=[BodySpec(  # boxes are not checked
            shape=ShapeSpec(kind="box", size=[0.3, 0.05, 0.3]), center=[0.3, 0.25, 0.3])]))


@pytest.mark.parametrize("shape, muscles, message", [
    (ShapeSpec(kind="body"), None, r"shape.body = None is invalid: a body shape needs a library body or a body file"),
    (ShapeSpec(kind="body", body="walrus"), None, r"shape.body = 'walrus' is invalid: one of seal, caterpillar"),
    (ShapeSpec(kind="body", body="seal", file="seal.obj"), None, r"shape.body = 'seal' is invalid: give a library body or a body file .*, not both"),
    (ShapeSpec(kind="box"), MuscleSpec(layout="body"), r"muscles.layout = 'body' is invalid: only a body shape"),
    (ShapeSpec(kind="body", body="seal"), MuscleSpec(layout="rings"), r"muscles.layout = 'rings' is invalid: one of"),
])
def test_body_shapes_in_scenes_are_validated(shape, muscles, message):
    with pytest.raises(SceneError, match=r"bodies\[0\]\." + message):
        validate_scene(Scene(bodies=[BodySpec(shape=shape, muscles=muscles)]))


def build_representation(name: str, env: LocomotionEnv, **config):
    entry = get_registry().get("representation", name)
    representation = entry.load_factory()(entry.load_config()(**config))
    representation.setup(env.design_space, np.random.default_rng(0))
    return representation


def representations_in(environment: str) -> list[str]:
    """Every representation on ground; one in each other environment, in turn, so that each also runs
    beside a cover. A design's fields enter every scene by the same path (`design_particles`); what
    an environment adds is its cover around the robot."""
    if environment == "ground":
        return REPRESENTATIONS
    return [REPRESENTATIONS[(ENVIRONMENTS.index(environment) - 1) % len(REPRESENTATIONS)]]


def test_each_representation_runs_beside_a_cover():
    covered = {name for environment in ENVIRONMENTS[1:] for name in representations_in(environment)}
    assert covered == set(REPRESENTATIONS)


@pytest.mark.slow
@pytest.mark.parametrize("environment", ENVIRONMENTS)
def test_representations_run_in_every_environment(environment):
    env = make_env(environment, size=ANIMAL_SIZE)  # the blends' primitives are at least 2 cells thick in it
    try:
        for name in representations_in(environment):
            env.reset(build_representation(name, env)())
            for t in range(3):
                result = env.step(gait(env, t))
            assert np.isfinite(result.observation).all(), name
            assert np.isfinite(env.sim.particles_state()[0]).all(), name
    finally:
        env.close()


T = 3  # frames of the differentiable rollout
MAX_FRAMES, SEGMENT = 12, 64  # as gradient_checks.py: one layout, compiled once for all representations
CASES = {"particle": {}, "voxel": {}, "implicit": {}, "diff_cppn": {},
         "sdf_lerp": dict(temperature=0.05, init_noise=0.3),  # a wider sigmoid: more particles feel the weights
         "wasserstein": dict(resolution=12, init_noise=0.3)}


@pytest.fixture(scope="module")
def differentiable():
    """One float64 ground scene and simulator shared by every representation's gradient check."""
    env = make_env(dtype="float64")
    sim = Simulator(env.scene, env.particles, requires_grad=True, max_frames=MAX_FRAMES, checkpoint_every=SEGMENT)
    yield env, sim
    sim.close()


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_gradient_from_a_short_simulation_to_the_design_parameters(differentiable, name):
    env, sim = differentiable
    dtype = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        representation = build_representation(name, env, **CASES[name])
    finally:
        torch.set_default_dtype(dtype)
    base = env.base_particles
    rng = np.random.default_rng(1)
    actions = torch.tensor(rng.uniform(-0.3, 0.3, (T, env.action_dim)))
    w_com, w_x = torch.tensor(rng.normal(size=(T + 1, 3))), torch.tensor(rng.normal(size=(base.n, 3)) / base.n)

    def loss() -> torch.Tensor:
        d = representation()
        com_x, _, x, _ = simulate(sim, actions, volume=torch.tensor(base.volume) * d.occupancy,
                                  youngs_modulus=d.stiffness, muscle=d.muscle, fiber=d.fiber)
        return (w_com * com_x).sum() + (w_x * x).sum()

    loss().backward()
    for tensor in representation.parameters():
        grad = tensor.grad.reshape(-1)
        index, eps = int(grad.abs().argmax()), 1e-5
        flat = tensor.data.reshape(-1)
        with torch.no_grad():
            flat[index] += eps
            up = loss().item()
            flat[index] -= 2 * eps
            down = loss().item()
            flat[index] += eps
        assert grad[index].item() == pytest.approx((up - down) / (2 * eps), rel=1e-4, abs=1e-10), tensor.shape
