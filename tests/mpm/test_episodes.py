"""Differentiable episodes (float64): the loss is minus the episode's summed reward, and its
gradient with respect to controller and design parameters matches central differences for
an open-loop (`sine`, `trajectory`: one checkpointed rollout) and a closed-loop controller
(`mlp`: one autograd node per control step). Also the Gymnasium wrapper.

One small scene layout throughout, so the backward kernels compile once.
"""
from dataclasses import replace

import numpy as np
import pytest
import torch

from codesign.errors import RecipeError
from codesign_basics.config import MLPConfig, SineConfig, TrajectoryConfig
from codesign_basics.mlp import MLPController
from codesign_basics.sine import SineController
from codesign_basics.trajectory import TrajectoryController
from codesign_designs.config import ParticleConfig
from codesign_designs.particle import ParticleRepresentation
from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS, RobotConfig, TaskConfig, TerrainConfig
from codesign_mpm.environment.env import LocomotionEnv
from codesign_mpm.environment.episode import design_inputs

pytestmark = pytest.mark.slow
HORIZON = 4


def make_env(task: str = "movement_speed", settled: bool = False) -> LocomotionEnv:
    config = PRESET_CONFIGS["ground"](dx=1 / 32, horizon=HORIZON, dtype="float64",
                                      terrain=TerrainConfig(height=0.1, friction=0.5),
                                      robot=RobotConfig(size=[0.16, 0.08, 0.08], settled=settled),
                                      task=TaskConfig(name=task))
    return LocomotionEnv(config, PRESETS["ground"])


@pytest.fixture(scope="module")
def env():
    environment = make_env()
    yield environment
    environment.close()


def parts(env, controller, seed=0):
    rep = ParticleRepresentation(ParticleConfig())
    rep.setup(env.design_space, np.random.default_rng(seed))
    controller.setup(env.action_dim, env.observation_dim, env.control_dt, np.random.default_rng(seed + 1))
    return rep, controller


CONTROLLERS = {
    "sine": lambda: SineController(SineConfig(init_std=1.0)),
    "mlp": lambda: MLPController(MLPConfig(hidden=[16], init_std=1.0)),
    "trajectory": lambda: TrajectoryController(TrajectoryConfig(steps=HORIZON, init_std=1.0)),
}


def stepped_return(env, rep, controller) -> float:
    """The same episode through reset/step, as an RL algorithm would see it."""
    total = 0.0
    with torch.no_grad():
        observation = env.reset(rep())
        controller.reset()
        for t in range(env.horizon):
            result = env.step(controller(observation, t).numpy())
            total, observation = total + result.reward, result.observation
    return total


@pytest.mark.parametrize("name", list(CONTROLLERS))
def test_loss_is_minus_the_return_and_its_gradient_matches_finite_differences(env, name):
    torch.set_default_dtype(torch.float64)
    try:
        rep, controller = parts(env, CONTROLLERS[name]())
        episode = env.differentiable_episode(rep(), controller)
        assert float(episode.loss) == pytest.approx(-stepped_return(env, rep, controller), rel=1e-9, abs=1e-12)
        episode.loss.backward()
        probes = [(controller.parameters()[0], (0,) * controller.parameters()[0].dim()), (rep.stiffness, (3,)),
                  (rep.geometry, (5,)), (rep.muscle, (7, 1))]
        for tensor, index in probes:
            analytic = tensor.grad[index].item()

            def loss(eps):
                with torch.no_grad():
                    tensor[index] += eps
                    value = float(env.differentiable_episode(rep(), controller).loss)
                    tensor[index] -= eps
                return value

            # the return is a difference of positions (a distance over the time): below a step of 1e-4 their
            # round-off shows (sine, geometry[5]: 1.80177e-5, 1.80193e-5, 1.80099e-5, 1.75381e-5 at 1e-4 .. 1e-7
            # against the adjoint's 1.80172e-5)
            numeric = (loss(1e-4) - loss(-1e-4)) / 2e-4
            scale = tensor.grad.abs().max().item()  # tiny entries are judged against their tensor's scale
            assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-4 * scale), (name, index)
    finally:
        torch.set_default_dtype(torch.float32)


class PerStepSine(SineController):
    open_loop = False  # the same gait forced onto the per-step path


def test_a_sine_episode_is_one_rollout_with_the_per_step_paths_loss_and_gradient(env):
    torch.set_default_dtype(torch.float64)
    try:
        rep, sine = parts(env, SineController(SineConfig(init_std=1.0)))
        _, per_step = parts(env, PerStepSine(SineConfig(init_std=1.0)))
        runs = []
        for controller in (sine, per_step):
            before = env._grad_sim.rollouts if env._grad_sim is not None else 0
            episode = env.differentiable_episode(rep(), controller)
            episode.loss.backward()
            runs.append((float(episode.loss), controller.alpha.grad.clone(), env._grad_sim.rollouts - before))
        (loss, grad, rollouts), (per_step_loss, per_step_grad, per_step_rollouts) = runs
        assert rollouts == 1 and per_step_rollouts >= HORIZON  # one a step, more where backward replays
        assert loss == pytest.approx(per_step_loss, rel=1e-9, abs=1e-12)
        assert torch.allclose(grad, per_step_grad, rtol=1e-7, atol=1e-9 * per_step_grad.abs().max().item())
    finally:
        torch.set_default_dtype(torch.float32)


def test_a_task_that_reads_particles_takes_the_per_step_path_with_an_open_loop_controller():
    env = make_env("turning")
    torch.set_default_dtype(torch.float64)
    try:
        rep, controller = parts(env, SineController(SineConfig(init_std=1.0)), seed=3)
        episode = env.differentiable_episode(rep(), controller)
        assert float(episode.loss) == pytest.approx(-stepped_return(env, rep, controller), rel=1e-9, abs=1e-12)
        episode.loss.backward()
        analytic = controller.alpha.grad[1, 0, 2].item()
        values = []
        for eps in (1e-6, -1e-6):
            with torch.no_grad():
                controller.alpha[1, 0, 2] += eps
                values.append(float(env.differentiable_episode(rep(), controller).loss))
                controller.alpha[1, 0, 2] -= eps
        assert analytic == pytest.approx((values[0] - values[1]) / 2e-6, rel=1e-4, abs=1e-10)
    finally:
        torch.set_default_dtype(torch.float32)
        env.close()


def still_motion(env, rep) -> float:
    """How far (m) the robot's centre of mass moves over an episode with no action."""
    with torch.no_grad():
        env.reset(rep())
        coms = [env.step(np.zeros(env.action_dim)).info["com"] for _ in range(env.horizon)]
    return float(np.linalg.norm(np.array(coms) - coms[0], axis=1).max())


def test_a_settled_robot_starts_at_rest_and_its_episodes_stay_differentiable(env):
    settled = make_env(settled=True)
    torch.set_default_dtype(torch.float64)
    try:
        rep, controller = parts(settled, MLPController(MLPConfig(hidden=[16], init_std=1.0)))
        # stress-free, the box sags onto the ground (its centre of mass falls ~0.3 mm in 4 frames);
        # relaxed, it is where its weight holds it
        assert still_motion(settled, rep) < 0.05 * still_motion(env, rep)
        assert settled._relaxed[1].frames > 1
        for make in (lambda: SineController(SineConfig(init_std=1.0)), lambda: controller):  # open and closed loop
            control = make()
            if control is not controller:
                control.setup(settled.action_dim, settled.observation_dim, settled.control_dt, np.random.default_rng(2))
            episode = settled.differentiable_episode(rep(), control)
            assert float(episode.loss) == pytest.approx(-stepped_return(settled, rep, control), rel=1e-9, abs=1e-12)
        episode.loss.backward()
        weight = controller.parameters()[0]
        values = []
        for eps in (1e-4, -1e-4):
            with torch.no_grad():
                weight[0, 0] += eps
                values.append(float(settled.differentiable_episode(rep(), controller).loss))
                weight[0, 0] -= eps
        assert weight.grad[0, 0].item() == pytest.approx((values[0] - values[1]) / 2e-4, rel=1e-4, abs=1e-10)
        with torch.no_grad():
            rep.stiffness[3] += 1.0  # another body: its rest is not the one found
        with pytest.raises(RecipeError, match="environment.robot.settled"):
            settled.reset(rep())
    finally:
        torch.set_default_dtype(torch.float32)
        settled.close()


@pytest.mark.parametrize("env_id", ["codesign/Ground-MovementSpeed-v0", "codesign/Ocean-WaypointFollowing-v0"])
def test_gymnasium_environments_pass_the_checker(env_id):
    gymnasium = pytest.importorskip("gymnasium")
    from gymnasium.utils.env_checker import check_env

    env = gymnasium.make(f"codesign_mpm.environment.gym:{env_id}", environment={"dx": 1 / 24, "horizon": 5, "terrain": {"height": 0.13},
                         "observation": {"muscle_centroids": True, "time": True}})
    try:
        check_env(env.unwrapped, skip_render_check=True)
        observation, _ = env.reset(seed=1)
        assert observation.shape == env.observation_space.shape == (3 + 3 + 6 * 4 + 3 + 1,)
        assert np.isfinite(observation).all()
        first = env.step(env.action_space.sample())[0]
        again, _ = env.reset(seed=1)
        np.testing.assert_array_equal(again, observation)
        np.testing.assert_array_equal(env.step(np.zeros(4, np.float32))[0].shape, first.shape)
    finally:
        env.close()


def test_every_designs_differentiable_simulator_takes_the_first_ones_compiled_storage():
    """A design with fewer particles gets a simulator of its own, and a stiffer one a finer time step,
    which would change the default segment; both keep the first design's capacity and segment, so
    the next simulator takes the same compiled storage (no compile, no frontend)."""
    env = make_env()  # its own: the module's may predate a Taichi program of another precision
    try:
        rep, _ = parts(env, SineController(SineConfig()))
        design = rep()
        first = env.grad_simulator(design_inputs(env, design)[0])
        storage, substeps = first.k, first.timestep.substeps
        n = env.base_particles.n
        occupancy = torch.as_tensor(design.occupancy).detach().clone().reshape(n)
        occupancy[: n // 4] = 0.0
        stiffer = replace(design, occupancy=occupancy, stiffness=torch.as_tensor(design.stiffness).detach() * 4)
        second = env.grad_simulator(design_inputs(env, stiffer)[0])
        assert second.n < first.n and second.timestep.substeps > substeps
        assert second.k is storage
    finally:
        env.close()


def test_an_environment_builds_its_simulators_again_after_another_precision_took_taichi():
    """Two environments of different precisions used in turn: a simulator of the other precision
    re-initialises Taichi, which frees the first environment's fields; it builds its simulators
    again and gives the same episode."""
    first = make_env()  # float64
    second = LocomotionEnv(PRESET_CONFIGS["ground"](dx=1 / 32, horizon=HORIZON, dtype="float32",
                                                    terrain=TerrainConfig(height=0.1, friction=0.5),
                                                    robot=RobotConfig(size=[0.16, 0.08, 0.08])), PRESETS["ground"])
    try:
        rep, controller = parts(first, SineController(SineConfig(init_std=1.0)))
        before = first.differentiable_episode(rep(), controller).episode_return
        first.reset(rep())
        second.reset()  # a float32 simulator: a new Taichi program
        assert not first.sim.alive
        assert first.differentiable_episode(rep(), controller).episode_return == before
        first.reset(rep())
        assert first.sim.alive
        assert np.isfinite(first.step(np.zeros(first.action_dim)).reward)
    finally:
        first.close()
        second.close()
