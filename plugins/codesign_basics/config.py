"""Config schemas, kept apart from the implementations so validating a recipe does not import torch."""

from dataclasses import dataclass, field


@dataclass
class SineConfig:
    frequencies: list[float] = field(
        default_factory=lambda: [20.0, 80.0],
        metadata={"gt": 0, "min_len": 1, "help": "angular frequencies omega_i of the basis, rad/s"},
    )
    phases: int = field(default=4, metadata={"ge": 1, "help": "number of phase offsets phi_j = 2 pi j / phases"})
    bound: float = field(default=0.3, metadata={"gt": 0, "help": "actions lie in [-bound, bound]"})
    init_std: float = field(default=0.1, metadata={"ge": 0, "help": "std of the initial basis weights alpha"})
    bias: str = field(default="per_basis", metadata={
        "choices": ["per_basis", "per_actuator"],
        "help": "per_basis: the paper's beta_kij, one per basis term (only their sum acts, so a gradient moves the "
                "effective bias I x J times faster); per_actuator: one beta_k per actuator, no redundant parameters"})


@dataclass
class EvaluateConfig:
    episodes: int = field(default=1, metadata={"ge": 1, "help": "episodes to run, one per iteration"})


@dataclass
class MLPConfig:
    hidden: list[int] = field(default_factory=lambda: [64, 64], metadata={"ge": 1, "help": "hidden layer widths"})
    activation: str = field(default="tanh", metadata={"choices": ["tanh", "relu", "elu"]})
    bound: float = field(default=0.3, metadata={"gt": 0, "help": "actions lie in [-bound, bound]"})
    output: str = field(default="action", metadata={
        "choices": ["action", "sine_weights"],
        "help": "action: bound * tanh(MLP(obs)); sine_weights: the MLP sets the sine basis weights"})
    frequencies: list[float] = field(default_factory=lambda: [20.0, 80.0], metadata={
        "gt": 0, "min_len": 1, "help": "sine_weights: angular frequencies of the basis, rad/s"})
    phases: int = field(default=4, metadata={"ge": 1, "help": "sine_weights: phase offsets per frequency"})
    init_std: float = field(default=0.1, metadata={"ge": 0, "help": "std of the last layer's initial weights"})


@dataclass
class TrajectoryConfig:
    steps: int = field(default=100, metadata={
        "ge": 1, "help": "actions stored; at least environment.horizon (e.g. steps: ${environment.horizon})"})
    bound: float = field(default=0.3, metadata={"gt": 0, "help": "actions lie in [-bound, bound]"})
    init_std: float = field(default=0.1, metadata={"ge": 0, "help": "std of the initial logits"})
