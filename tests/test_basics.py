import math

import numpy as np
import pytest
import torch

from codesign_basics.config import EvaluateConfig, SineConfig
from codesign_basics.evaluate import Evaluate
from codesign_basics.sine import SineController
from toy_plugin import ConstantConfig, ConstantRepresentation, ToyEnvConfig, ToyEnvironment


def sine(seed=0, action_dim=3, control_dt=0.01, **config) -> SineController:
    controller = SineController(SineConfig(**config))
    controller.setup(action_dim, observation_dim=5, control_dt=control_dt, rng=np.random.default_rng(seed))
    return controller


def test_sine_actions_stay_within_bound_even_when_saturated():
    controller = sine(bound=0.25, init_std=50.0)
    actions = torch.stack([controller(None, t) for t in range(200)])
    assert actions.shape == (200, 3)
    assert actions.abs().max() <= 0.25
    assert actions.abs().max() > 0.24  # large weights saturate tanh near the bound


def test_sine_is_periodic_in_the_common_period_of_its_frequencies():
    # omega = 2 pi and 4 pi rad/s share a 1 s period = 100 control steps of 0.01 s
    controller = sine(frequencies=[2 * math.pi, 4 * math.pi], init_std=1.0)
    for t in (0, 7, 33):
        torch.testing.assert_close(controller(None, t), controller(None, t + 100), atol=1e-5, rtol=0)
    assert not torch.allclose(controller(None, 0), controller(None, 25))


def test_sine_matches_the_papers_formula():
    """u = bound * tanh(sum_ij alpha_ij sin(omega_i t + phi_j) + beta_ij), a weight and bias per basis."""
    controller = sine(frequencies=[3.0], phases=2, bound=0.3, init_std=1.0, action_dim=2)
    with torch.no_grad():
        controller.beta.copy_(torch.tensor([[[0.1, 0.05]], [[-0.2, 0.0]]]))
    t = 5 * 0.01
    alpha, beta = controller.alpha.detach().numpy(), controller.beta.detach().numpy()
    basis = np.array([[math.sin(3.0 * t), math.sin(3.0 * t + math.pi)]])  # (I=1, J=2)
    expected = 0.3 * np.tanh((alpha * basis + beta).sum(axis=(1, 2)))
    np.testing.assert_allclose(controller(None, 5).detach().numpy(), expected, rtol=1e-5)


def test_a_bias_per_actuator_acts_as_the_papers_biases_summed_and_learns_at_its_own_rate():
    """per_actuator's beta_k is the per_basis beta_kij summed: the same actions, and the gradient
    of a per_basis entry is that of the sum, so one Adam step moves the sum I x J times further."""
    paper, lean = sine(init_std=1.0), sine(init_std=1.0, bias="per_actuator")
    assert lean.beta.shape == (3,) and paper.beta.shape == (3, 2, 4)
    with torch.no_grad():
        paper.beta.copy_(torch.linspace(-0.3, 0.3, 24).reshape(3, 2, 4))
        lean.beta.copy_(paper.beta.sum(dim=(1, 2)))
    for t in (0, 3, 11):
        torch.testing.assert_close(paper(None, t), lean(None, t), rtol=1e-6, atol=1e-7)
    for controller in (paper, lean):
        before = controller.beta.detach().clone()
        adam = torch.optim.Adam([controller.beta], lr=0.01)
        controller(None, 2).sum().backward()
        adam.step()
        controller.moved = (controller.beta.detach() - before).reshape(3, -1).sum(1)
    torch.testing.assert_close(paper.moved, 8 * lean.moved, rtol=1e-4, atol=1e-7)


def test_sine_gradients_flow_to_its_parameters():
    controller = sine(init_std=0.1)
    alpha, beta = controller.parameters()
    assert alpha.requires_grad and beta.requires_grad
    assert alpha.shape == beta.shape == (3, 2, 4)
    loss = sum(controller(None, t).sum() for t in range(10))
    loss.backward()
    assert alpha.grad is not None and alpha.grad.abs().sum() > 0
    assert beta.grad is not None and beta.grad.abs().sum() > 0


def test_sine_initialisation_comes_from_the_given_generator():
    torch.testing.assert_close(sine(seed=1).alpha, sine(seed=1).alpha)
    assert not torch.equal(sine(seed=1).alpha, sine(seed=2).alpha)
    assert torch.count_nonzero(sine(init_std=0.0).alpha) == 0


def test_sine_must_be_set_up_before_use():
    with pytest.raises(RuntimeError, match="setup"):
        SineController(SineConfig())(None, 0)


def make_evaluate(episodes=2, horizon=4, seed=0):
    env = ToyEnvironment(ToyEnvConfig(horizon=horizon))
    rep = ConstantRepresentation(ConstantConfig())
    rep.setup(env.design_space, np.random.default_rng(seed))
    ctrl = sine(seed=seed, action_dim=env.action_dim)
    optimizer = Evaluate(EvaluateConfig(episodes=episodes))
    optimizer.setup(env, rep, ctrl, rng=np.random.default_rng(seed), run_dir=None)
    return optimizer, ctrl


def test_evaluate_runs_one_full_episode_per_step_without_changing_parameters():
    optimizer, controller = make_evaluate(episodes=2, horizon=4)
    before = [p.detach().clone() for p in controller.parameters()]
    assert optimizer.iterations == 2
    metrics = optimizer.step()
    assert metrics["episode_length"] == 4
    assert metrics["episode_return"] < 0
    assert metrics["mean_reward"] == pytest.approx(metrics["episode_return"] / 4)
    for old, new in zip(before, controller.parameters()):
        assert torch.equal(old, new)


def test_evaluate_is_reproducible_from_its_generator():
    assert make_evaluate(seed=3)[0].step() == make_evaluate(seed=3)[0].step()
