"""Config schemas, kept apart from the implementations so validating a recipe does not import torch."""

from dataclasses import dataclass, field
from typing import Optional

from codesign_basics.config import NeatGenomeSettings


def _symmetric():
    return field(default=False, metadata={
        "help": "bilateral designs: occupancy, stiffness and muscles mirrored across the workspace's sagittal "
                "plane (the mid-plane of z), each muscle onto its mirror image's actuator"})


@dataclass
class FixedConfig:
    """No options: the body is the environment's (robot.body and its labels)."""


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
        default="environment",
        metadata={"choices": ["grid", "environment", "uniform", "random"],
                  "help": "environment: the environment's own muscles (an animal's groups; a box's grid of "
                          "robot.muscle_groups), material outside every group in each alike (representation "
                          "fixed keeps it passive); grid: a near-cubic block grid of K "
                          "muscles; uniform: equal logits, every particle in every muscle alike (the released "
                          "SoftZoo's start for design optimisation); random: N(0, 1)"},
    )
    muscle_sharpness: float = field(
        default=5.0, metadata={"ge": 0, "help": "grid, environment init: logit of a particle's own muscle (others 0)"}
    )
    fiber: Optional[list[float]] = field(
        default=None,
        metadata={"min_len": 3, "help": "fixed muscle direction, normalised; null: the environment's own fibres "
                                        "(an animal's, +x for a box)"},
    )
    symmetric: bool = _symmetric()


# The occupancy, stiffness and fibre options every per-point representation shares.
def _occupancy_logit():
    return field(default=3.0, metadata={
        "help": "initial occupancy logit (the networks: an output bias); sigmoid(3) = 0.95 keeps every particle"})


def _muscle_scale():
    """The networks (implicit, diff_cppn): how much larger their muscle logits' weights start."""
    return field(default=3.0, metadata={
        "ge": 0, "help": "the muscle logits' weights start this much larger, so the first design has distinct "
                         "muscle regions rather than one muscle everywhere"})


def _min_stiffness_ratio():
    return field(default=0.5, metadata={"gt": 0, "help": "stiffness at logit -inf, as a multiple of the default"})


def _max_stiffness_ratio():
    return field(default=1.5, metadata={
        "gt": 0, "help": "stiffness at logit +inf; the midpoint is the stiffness at logit 0"})


def _fiber():
    return field(default=None, metadata={
        "min_len": 3, "help": "fixed muscle direction, normalised; null: the environment's own fibres "
                              "(an animal's or annotated body's; the heading +x for a box)"})


ACTIVATIONS = ["sin", "sigmoid", "gaussian", "abs", "tanh", "selu", "identity"]
FISH_PRIMITIVES = ["fish_slender", "fish_deep", "fish_long_tail", "fish_flat", "fish_round"]


@dataclass
class VoxelConfig:
    resolution: int = field(default=8, metadata={
        "ge": 1, "le": 128, "help": "voxels along the workspace's longest side; the other sides in proportion"})
    interpolation: str = field(default="trilinear", metadata={
        "choices": ["trilinear", "nearest"],
        "help": "how particles read voxel logits: trilinear between voxel centres, or their own voxel's (the paper)"})
    muscle_init: str = field(default="environment", metadata={
        "choices": ["environment", "uniform", "random"],
        "help": "environment: each voxel's mean of the environment's own muscles (a box's grid, an animal's groups) "
                "times muscle_sharpness; uniform: equal logits (the released SoftZoo's start); random: N(0, 1)"})
    muscle_sharpness: float = field(default=5.0, metadata={"ge": 0, "help": "environment init: logit scale"})
    init_occupancy_logit: float = _occupancy_logit()
    min_stiffness_ratio: float = _min_stiffness_ratio()
    max_stiffness_ratio: float = _max_stiffness_ratio()
    fiber: Optional[list[float]] = _fiber()
    symmetric: bool = _symmetric()


@dataclass
class ImplicitConfig:
    hidden: list[int] = field(default_factory=lambda: [32, 32], metadata={
        "ge": 1, "min_len": 1, "help": "widths of the hidden layers (the paper: two of 32)"})
    activation: str = field(default="tanh", metadata={"choices": ["tanh", "sin", "softplus"]})
    init_scale: float = field(default=1.0, metadata={
        "gt": 0, "help": "weights start as N(0, init_scale^2 / fan_in); larger gives more varied first designs"})
    muscle_scale: float = _muscle_scale()
    init_occupancy_logit: float = _occupancy_logit()
    min_stiffness_ratio: float = _min_stiffness_ratio()
    max_stiffness_ratio: float = _max_stiffness_ratio()
    fiber: Optional[list[float]] = _fiber()
    symmetric: bool = _symmetric()


@dataclass
class DiffCPPNConfig:
    hidden_layers: int = field(default=3, metadata={"ge": 1, "help": "layers of graph nodes (the paper: 3)"})
    nodes: int = field(default=20, metadata={"ge": 1, "help": "nodes per layer (the paper: 20)"})
    activations: list[str] = field(default_factory=lambda: ["sin", "sigmoid"], metadata={
        "choices": ACTIVATIONS, "min_len": 1,
        "help": "node j of layer l uses activations[(j + l) % len]: a fixed, mixed topology (default: SoftZoo's "
                "sin and sigmoid)"})
    connection_density: float = field(default=0.5, metadata={
        "gt": 0, "le": 1, "help": "fraction of connections that start switched on (gate logit +gate_logit)"})
    gate_logit: float = field(default=2.0, metadata={
        "ge": 0, "help": "initial |gate logit|; a connection's weight is w sigmoid(gate), the softened NEAT edge"})
    weight_scale: float = field(default=2.0, metadata={
        "gt": 0, "help": "weights start as N(0, weight_scale^2 / fan_in); CPPN patterns need a scale above 1"})
    muscle_scale: float = _muscle_scale()
    init_occupancy_logit: float = _occupancy_logit()
    min_stiffness_ratio: float = _min_stiffness_ratio()
    max_stiffness_ratio: float = _max_stiffness_ratio()
    fiber: Optional[list[float]] = _fiber()
    symmetric: bool = _symmetric()


@dataclass
class NeatCPPNConfig(NeatGenomeSettings):
    """The genome settings (NeatGenomeSettings: neat-python's [DefaultGenome]) and how a genome's
    CPPN becomes a body."""

    min_body_fraction: float = field(default=0.05, metadata={
        "ge": 0, "lt": 1, "help": "a genome whose connected body keeps fewer of the workspace's particles is "
                                  "invalid (ranked below every valid one, never simulated)"})
    min_stiffness_ratio: float = _min_stiffness_ratio()
    max_stiffness_ratio: float = _max_stiffness_ratio()
    fiber: Optional[list[float]] = _fiber()


@dataclass
class SdfLerpConfig:
    primitives: list[str] = field(default_factory=lambda: list(FISH_PRIMITIVES), metadata={
        "min_len": 1, "help": "design primitives: library bodies (fish_*, seal, caterpillar, fish, panda) or body "
                              "files, each fitted into the workspace (proportions kept) on its floor"})
    temperature: float = field(default=0.005, metadata={
        "gt": 0, "help": "width of the occupancy sigmoid over the blended SDF, as a fraction of the workspace's "
                         "longest side (the paper: 1/1000 of a unit domain)"})
    init_noise: float = field(default=0.0, metadata={
        "ge": 0, "help": "initial weight logits are N(0, init_noise^2); 0: every primitive weighted equally"})


@dataclass
class WassersteinConfig:
    primitives: list[str] = field(default_factory=lambda: list(FISH_PRIMITIVES), metadata={
        "min_len": 1, "help": "design primitives, as for sdf_lerp"})
    resolution: int = field(default=24, metadata={
        "ge": 4, "le": 64, "help": "voxels along the workspace's longest side of the barycenter's grid"})
    blur: float = field(default=0.7, metadata={
        "gt": 0, "help": "entropic regularisation as the Gibbs kernel's Gaussian width, in voxels; larger is "
                         "smoother but reproduces primitives less sharply"})
    iterations: int = field(default=60, metadata={"ge": 1, "help": "Sinkhorn iterations (unrolled for gradients)"})
    init_noise: float = field(default=0.0, metadata={
        "ge": 0, "help": "initial weight logits are N(0, init_noise^2); 0: every primitive weighted equally"})
