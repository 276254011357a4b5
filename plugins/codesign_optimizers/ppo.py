"""PPO (stable-baselines3) on the controller of a fixed design (SoftZoo appendix "Reinforcement Learning").

SB3 trains a Gaussian policy whose *mean* is, by construction, exactly the recipe's controller:

- ``policy: mlp`` needs the ``mlp`` controller (``output: action``). SB3's actor has the same widths
  and activation, and a :class:`TanhSquash` wrapper maps its sample ``a`` to ``bound * tanh(a)``,
  the controller's output layer, so the deterministic policy is ``bound * tanh(MLP(obs))``.
- ``policy: sine`` needs the ``sine`` controller. The policy sees the time ``t = step * control_dt``
  only; its features extractor computes the controller's basis ``sin(omega_i t + phi_j)`` and a
  linear head (no hidden layer) holds ``alpha`` (weights) and ``sum_ij beta`` (bias).

PPO starts from the controller's (seeded) initial weights and, after every iteration, the actor's
weights are copied back into the controller, so `best/controller.pt` and ``codesign eval`` replay
the deterministic policy PPO learned, not an approximation of it.

``normalize`` wraps the episodes in SB3's ``VecNormalize``. Its observation statistics are folded
into the controller's first layer when the actor is copied (:class:`_Actor`), so the controller
still acts on raw observations and equals the policy mean on normalised ones. That fold is affine,
so observations are not clipped (``clip_obs=inf``; VecNormalize's default clips at 10 sigma, which
no controller layer could reproduce): an observation far outside the statistics so far reaches
the policy as a large input instead of a clipped one. Rewards are normalised (and clipped) as SB3
does; they never reach the controller.
"""

from __future__ import annotations

import contextlib
import copy
import math
import random
from collections.abc import Iterator
from pathlib import Path

import gymnasium
import numpy as np
import torch
from stable_baselines3 import PPO as SB3PPO
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from codesign.artifacts import BestKeeper, play
from codesign.errors import RecipeError
from codesign.interfaces import Controller, DesignFields, Environment, Optimizer, Representation
from codesign_optimizers.common import parameter_groups
from codesign_optimizers.config import PPOConfig

LOSSES = ("policy_gradient_loss", "value_loss", "entropy_loss", "approx_kl", "clip_fraction", "explained_variance",
          "std")
PRE_TANH_LIMIT = 100.0
NORMALIZE_OBSERVATIONS = ("observations", "both")
NORMALIZE_REWARDS = ("rewards", "both")


def action_bound(controller: Controller, environment: Environment) -> float:
    """The controller config's `bound`, else the scene's `max_action`, else 1."""
    bound = getattr(getattr(controller, "config", None), "bound", None)
    if bound is None:
        bound = getattr(getattr(environment, "scene", None), "max_action", None)
    return float(bound if bound is not None else 1.0)


class EpisodesVecEnv(VecEnv):
    """`n_envs` episodes of one fixed design as SB3's vectorised environment.

    With more than one, the episodes run as a population (`Environment.reset_population`,
    `step_population`): the MPM environments simulate them in one batched simulator, so a
    rollout step costs one launch of each kernel for all of them. They start together and, all
    reaching the horizon together, end together; the next ones start at once (SB3's auto-reset,
    the last observation in `info["terminal_observation"]`).

    Actions are SB3's Gaussian samples a, applied as bound * tanh(a): the controllers' own output
    layer, so the policy's mean passes through exactly the function the controller applies at
    evaluation. SB3 clips samples to the finite Box +-PRE_TANH_LIMIT, where tanh is 1 in float64.

    Episode seeds come from the env's own generator (``episodes``), not from SB3's reset seeds, so
    episodes are reproducible and checkpointable (``episodes.bit_generator.state``); each reset
    draws one per episode, so the members of a population differ where seeds matter. Reaching the
    horizon is a truncation; an earlier `done` a termination. Returns of finished episodes
    accumulate in ``returns``. With ``time_observation`` the observation is the time
    ``[step * control_dt]`` (open-loop policies).
    """

    render_mode = None

    def __init__(self, environment: Environment, design: DesignFields | None, bound: float, n_envs: int = 1,
                 episode_seed: int = 0, time_observation: bool = False) -> None:
        if time_observation:
            observation_space = gymnasium.spaces.Box(0.0, np.inf, (1,), dtype=np.float32)
        elif getattr(environment, "observation_space", None) is not None:
            observation_space = environment.observation_space
        else:
            observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (environment.observation_dim,), dtype=np.float32)
        action_space = gymnasium.spaces.Box(-PRE_TANH_LIMIT, PRE_TANH_LIMIT, (environment.action_dim,),
                                            dtype=np.float32)
        super().__init__(n_envs, observation_space, action_space)
        self.env, self.design, self.bound, self.time_observation = environment, design, bound, time_observation
        self.episodes = np.random.default_rng(episode_seed)
        self.returns: list[float] = []
        self.t = 0
        self.totals = np.zeros(n_envs)
        self._actions = np.zeros((n_envs, environment.action_dim))

    def _observe(self, observations: list[np.ndarray]) -> np.ndarray:
        if self.time_observation:
            return np.full((self.num_envs, 1), self.t * self.env.control_dt, dtype=np.float32)
        return np.stack([np.asarray(o, dtype=np.float32) for o in observations])

    def reset(self) -> np.ndarray:
        self.t = 0
        self.totals[:] = 0.0
        seeds = [int(s) for s in self.episodes.integers(2**31, size=self.num_envs)]
        if self.num_envs == 1:
            return self._observe([self.env.reset(self.design, seed=seeds[0])])
        return self._observe(self.env.reset_population([self.design] * self.num_envs, seed=seeds))

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = self.bound * np.tanh(np.asarray(actions, dtype=np.float64))

    def step_wait(self):
        if self.num_envs == 1:
            results = [self.env.step(self._actions[0])]
        else:
            results = self.env.step_population(self._actions)
        self.t += 1
        rewards = np.array([r.reward for r in results], dtype=np.float64)
        self.totals += rewards
        truncated = self.t >= self.env.horizon
        terminated = np.array([bool(r.done) and not truncated for r in results])
        if not truncated and terminated.any() and not terminated.all():
            raise RuntimeError(f"{type(self.env).__name__}: the episodes of a population ended at different steps "
                               f"({int(terminated.sum())} of {self.num_envs} at step {self.t}); "
                               "optimizer.n_envs > 1 needs episodes that end together")
        observations = self._observe([r.observation for r in results])
        infos = [dict(r.info) for r in results]
        dones = np.full(self.num_envs, truncated or terminated.any())
        if dones.all():
            self.returns.extend(self.totals.tolist())
            for info, last, ended in zip(infos, observations, terminated):
                info["terminal_observation"] = last
                info["TimeLimit.truncated"] = truncated and not ended
            observations = self.reset()
        return observations, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        """The run closes the environment itself."""

    def get_attr(self, attr_name: str, indices=None) -> list:
        return [getattr(self, attr_name)] * len(self._indices(indices))

    def set_attr(self, attr_name: str, value, indices=None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list:
        return [getattr(self, method_name)(*method_args, **method_kwargs) for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False] * len(self._indices(indices))

    def _indices(self, indices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)


class SineBasis(BaseFeaturesExtractor):
    """Time observation [t] -> sin(omega_i t + phi_j), flattened (I, J) as in `SineController`."""

    def __init__(self, observation_space: gymnasium.spaces.Box, frequencies: list[float], phases: int) -> None:
        super().__init__(observation_space, len(frequencies) * phases)
        self.register_buffer("omega", torch.tensor(frequencies, dtype=torch.float32))
        self.register_buffer("phi", torch.arange(phases, dtype=torch.float32) * (2 * math.pi / phases))

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        t = observations[:, :1, None]  # (B, 1, 1)
        return torch.sin(self.omega[None, :, None] * t + self.phi[None, None, :]).flatten(1)


class PPO(Optimizer):
    """One iteration = `timesteps_per_iteration` environment steps of SB3's PPO, then a deterministic
    evaluation episode through the recipe's controller (with the seed `codesign eval` uses first, the
    same every iteration so iterations compare on equal terms); the best one goes to `best/`.

    Every iteration starts a fresh episode and collects whole rollouts (`timesteps_per_iteration`
    must be a multiple of `n_steps`), so nothing lives between iterations except the policy, Adam,
    the counters, the normalisation statistics and the random generators: a resumed run continues
    exactly.

    SB3 draws from the global generators (python's `random`, numpy's, torch's) and its `seed=`
    reseeds them all. PPO passes no seed; it keeps its own states of those generators (``random``,
    seeded from the run's generator as SB3 would seed them) and swaps them in only around SB3's
    calls (:meth:`_sb3_random`), so the caller's global generators are left as they were.
    """

    def __init__(self, config: PPOConfig) -> None:
        rollout = config.n_steps * config.n_envs
        if config.timesteps_per_iteration % rollout:
            size = (f"optimizer.n_steps ({config.n_steps})" if config.n_envs == 1 else
                    f"optimizer.n_steps x optimizer.n_envs ({config.n_steps} x {config.n_envs} = {rollout})")
            raise RecipeError(f"invalid recipe: optimizer.timesteps_per_iteration: {config.timesteps_per_iteration} "
                              f"is not a multiple of {size}; iterations must end on rollout boundaries so a "
                              "resumed run continues exactly")
        if config.policy == "sine" and config.normalize in NORMALIZE_OBSERVATIONS:
            raise RecipeError(f"invalid recipe: optimizer.normalize: {config.normalize!r} normalises observations, "
                              "but optimizer.policy 'sine' observes only the time (allowed with it: none, rewards)")
        self.config = config
        self.iterations = math.ceil(config.total_timesteps / config.timesteps_per_iteration)
        self.iteration = 0

    def setup(self, environment: Environment, representation: Representation, controller: Controller, *,
              rng: np.random.Generator, run_dir: Path) -> None:
        cfg = self.config  # checked before anything simulates: PPO trains the controller only
        parameter_groups(cfg.optimize, representation, controller, supported=("control",))
        if cfg.n_envs > 1 and not environment.batched:
            raise RecipeError(f"invalid recipe: optimizer.n_envs: {cfg.n_envs} needs an environment that simulates "
                              f"populations of episodes together; {type(environment).__name__} plays one at a time "
                              "(allowed here: 1)")
        self.environment, self.controller = environment, controller
        self.actor, policy_kwargs = _policy(cfg.policy, controller)
        self.eval_seed = int(rng.integers(2**31))  # first draw: the seed `codesign eval` plays its first episode with
        ppo_seed, episode_seed = (int(s) for s in rng.integers(2**31, size=2))
        self.design = representation()
        self.gym = EpisodesVecEnv(environment, self.design, action_bound(controller, environment), cfg.n_envs,
                                  episode_seed, time_observation=cfg.policy == "sine")
        self.normalizer = None if cfg.normalize == "none" else VecNormalize(
            self.gym, norm_obs=cfg.normalize in NORMALIZE_OBSERVATIONS, norm_reward=cfg.normalize in NORMALIZE_REWARDS,
            clip_obs=np.inf, gamma=cfg.gamma)  # no clipping: the fold into the controller is affine
        self.random = {"python": random.Random(ppo_seed).getstate(),  # what SB3's seed=ppo_seed would set
                       "numpy": np.random.RandomState(ppo_seed).get_state(),
                       "torch": torch.Generator().manual_seed(ppo_seed).get_state()}
        with self._sb3_random():
            self.model = SB3PPO("MlpPolicy", self.gym if self.normalizer is None else self.normalizer,
                                n_steps=cfg.n_steps, batch_size=cfg.batch_size, n_epochs=cfg.n_epochs, gamma=cfg.gamma,
                                gae_lambda=cfg.gae_lambda, ent_coef=cfg.ent_coef, learning_rate=cfg.learning_rate,
                                clip_range=cfg.clip_range, policy_kwargs=policy_kwargs, device="cpu", verbose=0)
        self.model.set_logger(Logger(folder=None, output_formats=[]))
        with torch.no_grad():  # PPO starts from the controller's own (seeded) initialisation
            for dst, src in zip(self._sb3_params(), self.actor.to_sb3(self._observation_stats())):
                dst.copy_(src)
        self.best = BestKeeper(environment, controller, run_dir)

    def _sb3_params(self) -> list[torch.Tensor]:
        layers = [m for m in self.model.policy.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)]
        return [p for m in [*layers, self.model.policy.action_net] for p in (m.weight, m.bias)]

    @contextlib.contextmanager
    def _sb3_random(self) -> Iterator[None]:
        """PPO's own generator states in the global generators for an SB3 call, the caller's back after."""
        caller = random.getstate(), np.random.get_state(), torch.get_rng_state()
        random.setstate(self.random["python"])
        np.random.set_state(self.random["numpy"])
        torch.set_rng_state(self.random["torch"])
        try:
            yield
        finally:
            self.random = {"python": random.getstate(), "numpy": np.random.get_state(),
                           "torch": torch.get_rng_state()}
            random.setstate(caller[0])
            np.random.set_state(caller[1])
            torch.set_rng_state(caller[2])

    def _observation_stats(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(mean, std) VecNormalize scales observations with before the policy sees them; None: raw."""
        if self.normalizer is None or not self.normalizer.norm_obs:
            return None
        rms = self.normalizer.obs_rms
        return (torch.as_tensor(rms.mean, dtype=torch.float64),
                torch.as_tensor(np.sqrt(rms.var + self.normalizer.epsilon), dtype=torch.float64))

    def _copy_back(self) -> None:
        """The actor's weights into the controller, the observation statistics folded in."""
        with torch.no_grad():
            self.actor.from_sb3([p.detach() for p in self._sb3_params()], self._observation_stats())

    def step(self) -> dict[str, float]:
        cfg, model = self.config, self.model
        self.gym.returns.clear()
        model._last_obs = None  # a fresh episode per iteration: nothing mid-episode outlives an iteration
        remaining = cfg.total_timesteps - model.num_timesteps
        with self._sb3_random():
            model.learn(min(cfg.timesteps_per_iteration, remaining), reset_num_timesteps=False, log_interval=None)
        self._copy_back()
        # raw observations, past VecNormalize: its statistics stay as training left them
        record = play(self.environment, self.design, self.controller, seed=self.eval_seed)
        self.best.offer(record.episode_return, self.design, record, self.iteration)
        self.iteration += 1
        metrics = {"episode_return": record.episode_return, "best_return": self.best.best_return,
                   "timesteps": float(model.num_timesteps), "train_episodes": float(len(self.gym.returns)),
                   **record.metrics}
        if self.gym.returns:
            metrics["train_return"] = float(np.mean(self.gym.returns))
        logged = model.logger.name_to_value
        metrics.update({k: float(logged[f"train/{k}"]) for k in LOSSES if f"train/{k}" in logged})
        return metrics

    def state_dict(self) -> dict:
        model, norm = self.model, self.normalizer
        return copy.deepcopy({
            "iteration": self.iteration, "best_return": self.best.best_return, "policy": model.policy.state_dict(),
            "adam": model.policy.optimizer.state_dict(), "num_timesteps": model.num_timesteps,
            "n_updates": model._n_updates, "episode_num": model._episode_num,
            "episodes": self.gym.episodes.bit_generator.state, "random": self.random,
            "normalize": None if norm is None else {
                "obs_rms": _rms_state(norm.obs_rms) if norm.norm_obs else None, "ret_rms": _rms_state(norm.ret_rms),
                "returns": norm.returns}})

    def load_state_dict(self, state: dict) -> None:
        model = self.model
        self.iteration, self.best.best_return = state["iteration"], state["best_return"]
        model.policy.load_state_dict(state["policy"])
        model.policy.optimizer.load_state_dict(state["adam"])
        model.num_timesteps, model._n_updates, model._episode_num = (
            state["num_timesteps"], state["n_updates"], state["episode_num"])
        self.gym.episodes.bit_generator.state = state["episodes"]
        self.random = copy.deepcopy(state["random"])
        if self.normalizer is not None:
            norm = state["normalize"]
            if self.normalizer.norm_obs:
                _load_rms(self.normalizer.obs_rms, norm["obs_rms"])
            _load_rms(self.normalizer.ret_rms, norm["ret_rms"])
            self.normalizer.returns = np.array(norm["returns"])
        self._copy_back()


def _rms_state(rms: RunningMeanStd) -> dict:
    """VecNormalize's running statistics as plain values, for checkpoints."""
    return {"mean": rms.mean, "var": rms.var, "count": rms.count}


def _load_rms(rms: RunningMeanStd, state: dict) -> None:
    rms.mean, rms.var, rms.count = np.array(state["mean"]), np.array(state["var"]), state["count"]


class _Actor:
    """Maps the controller's parameters to SB3's actor ([W, b] per layer) and back.

    With observation statistics ``(mean, std)`` SB3's actor sees ``(obs - mean) / std`` and the
    controller raw ``obs``, so the first layer is folded on the way back, ``W' = W / std`` (column
    by column) and ``b' = b - W' @ mean``, and unfolded on the way in; both compute the same.
    (Only ``policy: mlp``, whose first layer reads the observation, normalises observations.)
    """

    def __init__(self, params: list[torch.Tensor], to_sb3, from_sb3) -> None:
        self.params, self._to, self._from = params, to_sb3, from_sb3

    def to_sb3(self, stats: tuple[torch.Tensor, torch.Tensor] | None = None) -> list[torch.Tensor]:
        sb3 = self._to(self.params)
        if stats is None:
            return sb3
        mean, std = stats
        w = sb3[0].double()
        return [w * std, sb3[1].double() + w @ mean, *sb3[2:]]

    def from_sb3(self, sb3: list[torch.Tensor], stats: tuple[torch.Tensor, torch.Tensor] | None = None) -> None:
        if stats is not None:
            mean, std = stats
            w = sb3[0].double() / std
            sb3 = [w, sb3[1].double() - w @ mean, *sb3[2:]]
        for p, v in zip(self.params, self._from(sb3)):
            p.copy_(v.to(p.dtype))


def _policy(policy: str, controller: Controller) -> tuple[_Actor, dict]:
    """Check the recipe's controller fits `optimizer.policy`; return the weight mapping and SB3 policy kwargs."""
    from codesign_basics.mlp import ACTIVATIONS, MLPController
    from codesign_basics.sine import SineController

    if policy == "mlp":
        if not isinstance(controller, MLPController) or controller.config.output != "action":
            raise RecipeError(f"invalid recipe: controller.name: optimizer.policy 'mlp' needs the 'mlp' controller "
                              f"with output: action (so `codesign eval` replays the learned policy); got "
                              f"{type(controller).__name__}{_output(controller)}")
        cfg = controller.config
        kwargs = {"net_arch": {"pi": list(cfg.hidden), "vf": list(cfg.hidden)},
                  "activation_fn": ACTIVATIONS[cfg.activation]}
        same = lambda ps: [p.detach().float() for p in ps]  # noqa: E731 - Linear weights map one to one
        return _Actor(controller.parameters(), same, lambda ps: ps), kwargs
    if not isinstance(controller, SineController):
        raise RecipeError(f"invalid recipe: controller.name: optimizer.policy 'sine' needs the 'sine' controller "
                          f"(so `codesign eval` replays the learned policy); got {type(controller).__name__}")
    cfg, (alpha, beta) = controller.config, controller.parameters()
    n_basis = alpha.shape[1] * alpha.shape[2]
    per_basis = beta.dim() == 3  # sine's bias: per_basis, beta (K, I, J) summed like alpha's terms; per_actuator (K,)
    kwargs = {"net_arch": {"pi": [], "vf": [64, 64]}, "features_extractor_class": SineBasis,
              "features_extractor_kwargs": {"frequencies": list(cfg.frequencies), "phases": cfg.phases}}

    def to_sb3(ps: list[torch.Tensor]) -> list[torch.Tensor]:
        bias = ps[1].detach().sum(dim=(1, 2)) if per_basis else ps[1].detach()
        return [ps[0].detach().reshape(len(ps[0]), -1).float(), bias.float()]

    def from_sb3(ps: list[torch.Tensor]) -> list[torch.Tensor]:  # per_basis: the bias spread evenly over beta
        return [ps[0].reshape(alpha.shape), (ps[1] / n_basis)[:, None, None].expand(beta.shape) if per_basis else ps[1]]

    return _Actor([alpha, beta], to_sb3, from_sb3), kwargs


def _output(controller: Controller) -> str:
    output = getattr(getattr(controller, "config", None), "output", None)
    return f" (output: {output})" if output is not None else ""
