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


@dataclass
class EvaluateConfig:
    episodes: int = field(default=1, metadata={"ge": 1, "help": "episodes to run, one per iteration"})
