"""Config schemas, kept apart from the implementations so validating a recipe does not import torch."""

from dataclasses import dataclass, field


@dataclass
class ParticleConfig:
    init_occupancy_logit: float = field(
        default=3.0, metadata={"help": "initial geometry logit; sigmoid(3) = 0.95 keeps every particle"}
    )
    min_stiffness_ratio: float = field(
        default=0.5, metadata={"gt": 0, "help": "stiffness at logit -inf, as a multiple of the default"}
    )
    max_stiffness_ratio: float = field(
        default=1.5, metadata={"gt": 0, "help": "stiffness at logit +inf; the midpoint is the stiffness at logit 0"}
    )
    muscle_init: str = field(
        default="grid",
        metadata={"choices": ["grid", "random"], "help": "grid: a near-cubic block grid of K muscles; random: N(0, 1)"},
    )
    muscle_sharpness: float = field(
        default=5.0, metadata={"ge": 0, "help": "grid init: logit of a particle's own muscle (others 0)"}
    )
    fiber: list[float] = field(
        default_factory=lambda: [1.0, 0.0, 0.0],
        metadata={"min_len": 3, "help": "fixed muscle direction (the canonical heading), normalised"},
    )
