"""Test doubles: a tiny physics-free environment, representation and optimizer.

Loaded as a plugin through ``CODESIGN_PLUGINS=toy_plugin`` (see conftest.py);
never shipped. Class attributes ``fail_at`` let tests make a run fail on purpose.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from codesign.hookspecs import hookimpl
from codesign.interfaces import DesignFields, DesignSpace, Environment, Optimizer, Representation, StepResult


@dataclass
class ToyEnvConfig:
    n_points: int = field(default=8, metadata={"ge": 1})
    n_actuators: int = field(default=2, metadata={"ge": 1})
    horizon: int = field(default=5, metadata={"ge": 1})
    control_dt: float = field(default=0.01, metadata={"gt": 0})
    target_range: float = field(default=0.1, metadata={"ge": 0, "help": "targets are uniform in +-this"})


class ToyEnvironment(Environment):
    """Reward: minus the squared distance between the action and a target drawn at reset."""

    def __init__(self, config: ToyEnvConfig) -> None:
        self.config = config
        self.design_space = DesignSpace(
            points=np.linspace(0.0, 1.0, config.n_points * 3).reshape(-1, 3),
            n_actuators=config.n_actuators,
            default_stiffness=1e4,
        )
        self.action_dim = config.n_actuators
        self.observation_dim = 3
        self.horizon = config.horizon
        self.control_dt = config.control_dt
        self.closed = False

    def reset(self, design: DesignFields | None = None, seed: int | None = None) -> np.ndarray:
        r = self.config.target_range
        self.target = np.random.default_rng(seed).uniform(-r, r, self.action_dim)
        self.t = 0
        return np.zeros(3)

    def step(self, action: np.ndarray) -> StepResult:
        assert action.shape == (self.action_dim,)
        self.t += 1
        reward = -float(np.sum((action - self.target) ** 2))
        return StepResult(np.full(3, self.t, dtype=float), reward, self.t >= self.horizon, {})

    def close(self) -> None:
        self.closed = True


@dataclass
class ConstantConfig:
    occupancy: float = field(default=1.0, metadata={"ge": 0, "le": 1})


class ConstantRepresentation(Representation):
    """Every particle occupied with the same value; one muscle per actuator in turn."""

    def __init__(self, config: ConstantConfig) -> None:
        self.config = config

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        self.space = space

    def __call__(self) -> DesignFields:
        n, k = len(self.space.points), self.space.n_actuators
        return DesignFields(
            occupancy=np.full(n, self.config.occupancy),
            stiffness=np.full(n, self.space.default_stiffness),
            muscle=np.eye(k)[np.arange(n) % k],
            fiber=np.tile([1.0, 0.0, 0.0], (n, 1)),
        )


@dataclass
class CountingConfig:
    iterations: int = field(default=4, metadata={"ge": 1})


class CountingOptimizer(Optimizer):
    """Counts its steps and draws from the run's generator, so resume can be checked exactly."""

    maximize = {"loss": False}
    fail_at: int | None = None  # iteration count at which step() raises

    def __init__(self, config: CountingConfig) -> None:
        self.iterations = config.iterations
        self.count = 0

    def setup(self, environment, representation, controller, *, rng: np.random.Generator, run_dir: Path) -> None:
        self.rng = rng

    def step(self) -> dict[str, float]:
        if self.count + 1 == CountingOptimizer.fail_at:
            raise RuntimeError("planned failure")
        self.count += 1
        return {"count": self.count, "loss": 1.0 / self.count, "draw": float(self.rng.random())}

    def state_dict(self) -> dict:
        return {"count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.count = state["count"]


@hookimpl
def codesign_register(registry) -> None:
    registry.add("environment", "toy", ToyEnvironment, ToyEnvConfig, "test double environment")
    registry.add("representation", "constant", ConstantRepresentation, ConstantConfig, "test double design")
    registry.add("optimizer", "counting", CountingOptimizer, CountingConfig, "test double optimizer")


@hookimpl
def codesign_cli(app) -> None:
    @app.command("toy-hello")
    def toy_hello() -> None:
        """Say hello (shows that plugins can add commands)."""
        print("hello from toy")


seeds: list[int] = []


renders = True  # tests turn it off to see a run with nothing to render it
rendered: list[tuple[Path, str, int]] = []


@hookimpl
def codesign_render_run(run_dir: Path, camera: str, fps: int) -> Path | None:
    """Stands in for the MPM renderer for toy runs: a three-frame GIF in best/."""
    import imageio.v2 as imageio

    from codesign.runner import load_run_data

    if not renders or load_run_data(run_dir)[1].sections["environment"].name != "toy":
        return None

    rendered.append((run_dir, camera, fps))
    out = run_dir / "best" / "episode.gif"
    out.parent.mkdir(exist_ok=True)
    imageio.mimwrite(out, [np.full((16, 16, 3), 80 * i, np.uint8) for i in range(3)], duration=1000 / fps)
    return out


@hookimpl
def codesign_seed(seed: int) -> None:
    seeds.append(seed)
