"""The four component contracts a recipe wires together.

An environment offers a :class:`DesignSpace`; a representation turns its own
parameters into :class:`DesignFields` over that space; a controller turns
observations into actions; an optimizer runs episodes and updates whatever it
trains. The runner builds each part from the registry as ``Factory(config)``,
where ``config`` is the validated instance of the entry's config dataclass.

Constructors must not draw random numbers: randomness comes from the
``rng`` given to ``setup`` (and the seed given to ``Environment.reset``), so a
run is reproducible from its recipe seed.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar

import numpy as np


@dataclass
class DesignSpace:
    """What an environment offers a representation to shape."""

    points: np.ndarray
    """(N, 3) base particle positions of the robot's workspace, in scene units."""
    n_actuators: int
    """K, the largest number of muscles the robot may have."""
    default_stiffness: float
    """Young's modulus of the robot material when a design does not say otherwise."""
    stiffness: np.ndarray | None = None
    """(N,) the environment's own Young's modulus per point (a labelled body's parts, its passive
    material); None: `default_stiffness` everywhere."""
    bounds: np.ndarray | None = None
    """(2, 3) lower and upper corner of the workspace's box; None: the points' bounding box."""
    muscle: np.ndarray | None = None
    """(N, K) the environment's own muscle membership (a box's grid, an animal's groups); None: not given."""
    fiber: np.ndarray | None = None
    """(N, 3) the environment's own unit fibre directions; None: the heading +x."""
    keep: Callable[[np.ndarray], np.ndarray] | None = None
    """What the environment simulates of a set of occupied points ((N,) bool -> (N,) bool), e.g.
    only parts thick enough for its grid, in one connected body; None: all of them."""

    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) corners of the workspace: `bounds`, or else the points' bounding box."""
        if self.bounds is not None:
            return np.asarray(self.bounds[0], dtype=float), np.asarray(self.bounds[1], dtype=float)
        return self.points.min(0).astype(float), self.points.max(0).astype(float)


@dataclass
class DesignFields:
    """A design, per base particle; numpy arrays or (differentiable) torch tensors."""

    occupancy: Any
    """(N,) in [0, 1]; multiplies mass, and particles under a threshold are removed."""
    stiffness: Any
    """(N,) Young's modulus."""
    muscle: Any
    """(N, K) membership r_p of each particle in each muscle."""
    fiber: Any
    """(N, 3) unit fiber direction f_p."""


@dataclass
class StepResult:
    """What one control step of an environment returns."""

    observation: np.ndarray
    """(observation_dim,) what the controller sees next."""
    reward: float
    """The task's reward for this step."""
    done: bool
    """True once the episode is over (its horizon reached, or the environment ended it)."""
    info: dict = field(default_factory=dict)
    """Anything else the environment reports of the step (e.g. the robot's centre of mass, "com")."""


class Environment(ABC):
    """A scene plus a task.

    Consumes a design (at reset) and one action per control step; produces
    observations and rewards. Subclasses set the attributes below in their
    constructor.
    """

    design_space: DesignSpace
    """What a representation may shape."""
    action_dim: int
    """K, the length of an action (one value per muscle)."""
    observation_dim: int
    """The length of an observation."""
    horizon: int
    """Control steps per episode."""
    control_dt: float
    """Simulated seconds between two control steps."""
    batched: ClassVar[bool] = False
    """True if the environment simulates a population of episodes together
    (:meth:`reset_population`, :meth:`step_population`); else they run one at a time."""

    @abstractmethod
    def reset(self, design: DesignFields | None = None, seed: int | None = None) -> np.ndarray:
        """Start an episode with ``design`` (or the current one); return the first observation."""

    @abstractmethod
    def step(self, action: np.ndarray) -> StepResult:
        """Apply ``action`` (shape ``(action_dim,)``) for one control step."""

    def reset_population(self, designs: list[DesignFields | None],
                         seed: int | list[int] | None = None) -> list[np.ndarray]:
        """Start one episode per design (None: the current one), simulated together; return their
        first observations. Only where :attr:`batched` is true.

        ``seed``: a list holds one seed per design, episode ``b`` starting as ``reset(designs[b],
        seed[b])`` would; a single int (or None) is every episode's seed, so each starts as
        ``reset(design, seed)`` would (`play_population` compares with `play` that way)."""
        raise NotImplementedError(f"{type(self).__name__} simulates one episode at a time")

    def step_population(self, actions: np.ndarray) -> list[StepResult]:
        """Apply ``actions`` (shape ``(B, action_dim)``, one row per episode) for one control step."""
        raise NotImplementedError(f"{type(self).__name__} simulates one episode at a time")

    def close(self) -> None:
        """Release resources (fields, windows, files); called once at the end of a run."""


class Representation(ABC):
    """Design parameters -> :class:`DesignFields` over an environment's design space."""

    @abstractmethod
    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        """Size and initialise the parameters for ``space``."""

    def parameters(self) -> list:
        """Trainable torch tensors, for gradient-based optimizers; none by default."""
        return []

    @abstractmethod
    def __call__(self) -> DesignFields:
        """Produce the design from the current parameters."""


class Controller(ABC):
    """(observation, control step index) -> action in ``[-bound, bound]^K``."""

    open_loop: ClassVar[bool] = False
    """True if the action never depends on the observation (lets episodes precompute all actions)."""

    @abstractmethod
    def setup(
        self, action_dim: int, observation_dim: int, control_dt: float, rng: np.random.Generator
    ) -> None:
        """Size and initialise the parameters for an environment's action and observation."""

    def parameters(self) -> list:
        """Trainable torch tensors, for gradient-based optimizers; none by default."""
        return []

    def reset(self) -> None:
        """Clear per-episode state (e.g. a recurrent memory) before an episode."""

    @abstractmethod
    def __call__(self, observation: Any, step: int) -> Any:
        """Return the action (numpy array or torch tensor of shape ``(action_dim,)``)."""


class Optimizer(ABC):
    """Drives episodes and updates design and/or controller parameters.

    The runner owns the loop: it calls :meth:`step` ``iterations`` times, logs
    what each call returns and checkpoints :meth:`state_dict` after each one.
    The state must hold everything needed to continue, including any
    representation or controller parameters the optimizer changes.
    """

    iterations: int
    """How many times the runner calls :meth:`step`."""
    maximize: ClassVar[dict[str, bool]] = {}
    """Metrics for which lower is better map to False; any other metric's best value is its max."""
    stopped: str | None = None
    """Why the search ended before ``iterations`` (e.g. CMA-ES's termination criteria), else None:
    the runner stops calling :meth:`step` and writes the reason to summary.json. Part of the state."""

    @abstractmethod
    def setup(
        self,
        environment: Environment,
        representation: Representation,
        controller: Controller,
        *,
        rng: np.random.Generator,
        run_dir: Path,
    ) -> None:
        """Receive the (already set up) parts; ``run_dir`` is where artifacts may be written."""

    @abstractmethod
    def step(self) -> dict[str, float]:
        """Run one iteration and return the metrics to log."""

    def state_dict(self) -> dict:
        """Everything needed to resume after the last completed iteration (picklable)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` returned."""
