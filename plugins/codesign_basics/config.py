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


# neat-python's names; the paper's set for its CPPN-NEAT baseline (appendix "Evolution Strategy")
NEAT_ACTIVATIONS = ["sigmoid", "tanh", "sin", "gauss", "selu", "abs", "log", "exp", "identity"]


@dataclass
class NeatGenomeSettings:
    """The genome half of NEAT's settings (neat-python's [DefaultGenome]) of an evolved CPPN; the
    population half is the cppn_neat optimizer's. Shared by the neat_cppn representation and the
    hyperneat controller (codesign_basics.cppn.genome_section)."""

    activations: list[str] = field(default_factory=lambda: NEAT_ACTIVATIONS[:8], metadata={
        "choices": NEAT_ACTIVATIONS, "min_len": 1, "help": "activations a node may take (mutated at activation_mutate_rate)"})
    activation_mutate_rate: float = field(default=0.1, metadata={"ge": 0, "le": 1})
    initial_connection: str = field(default="full_direct", metadata={
        "choices": ["full_direct", "full_nodirect", "fs_neat_nohidden"],
        "help": "neat-python's initial_connection (full_nodirect needs num_hidden > 0)"})
    num_hidden: int = field(default=0, metadata={"ge": 0, "help": "hidden nodes of the first genomes"})
    conn_add_prob: float = field(default=0.3, metadata={"ge": 0, "le": 1})
    conn_delete_prob: float = field(default=0.1, metadata={"ge": 0, "le": 1})
    node_add_prob: float = field(default=0.2, metadata={"ge": 0, "le": 1})
    node_delete_prob: float = field(default=0.05, metadata={"ge": 0, "le": 1})
    weight_init_stdev: float = field(default=1.0, metadata={"gt": 0})
    weight_mutate_rate: float = field(default=0.8, metadata={"ge": 0, "le": 1})
    weight_mutate_power: float = field(default=0.5, metadata={"ge": 0})
    bias_mutate_rate: float = field(default=0.7, metadata={"ge": 0, "le": 1})


@dataclass
class HyperNEATConfig(NeatGenomeSettings):
    """The genome settings of the CPPN (6 inputs, 4 outputs) and the substrate it is queried on."""

    frequencies: list[float] = field(default_factory=lambda: [20.0, 80.0], metadata={
        "gt": 0, "min_len": 1, "help": "angular frequencies omega_i of the sine basis inputs, rad/s"})
    phases: int = field(default=4, metadata={"ge": 1, "help": "phase offsets phi_j = 2 pi j / phases per frequency"})
    observation: bool = field(default=True, metadata={
        "help": "closed loop: the observation's entries are inputs too; false: the sine basis only (open loop)"})
    hidden: int = field(default=0, metadata={"ge": 0, "help": "hidden substrate nodes (a grid at layer 0); 0: none"})
    weight_threshold: float = field(default=0.2, metadata={
        "ge": 0, "lt": 1, "help": "a CPPN weight output under this magnitude expresses no connection"})
    max_weight: float = field(default=3.0, metadata={
        "gt": 0, "help": "largest connection weight and bias magnitude (a CPPN output of magnitude 1 or more)"})
    bound: float = field(default=0.3, metadata={"gt": 0, "help": "actions lie in [-bound, bound]"})
