"""Config schemas, kept apart from the implementations so validating a recipe imports no torch."""

from dataclasses import dataclass, field
from typing import Optional

MODES = ["control", "design", "both"]


@dataclass
class DiffPhysicsConfig:
    optimize: str = field(default="both", metadata={"choices": MODES, "help": "which parameters to train"})
    iterations: int = field(default=30, metadata={"ge": 1, "help": "gradient steps per restart"})
    lr_control: float = field(default=0.01, metadata={"gt": 0, "help": "Adam learning rate of the controller"})
    lr_design: float = field(default=0.01, metadata={"gt": 0, "help": "Adam learning rate of the design"})
    clip_grad_norm: Optional[float] = field(default=None, metadata={
        "gt": 0, "help": "clip each group's gradient norm to this (null: no clipping)"})
    restarts: int = field(default=1, metadata={
        "ge": 1, "help": "independent random initialisations, run one after the other; the best is kept"})
    checkpoint_every: Optional[int] = field(default=None, metadata={
        "ge": 1, "help": "substeps between stored states in the backward pass (null: memory-optimal)"})


@dataclass
class CMAESConfig:
    optimize: str = field(default="control", metadata={"choices": MODES, "help": "which parameters to evolve"})
    generations: int = field(default=20, metadata={"ge": 1, "help": "generations in all, restarts included"})
    population: Optional[int] = field(default=None, metadata={
        "ge": 2, "help": "candidates per generation (CMA's popsize; null: pycma's 4 + 3 ln n for n parameters)"})
    sigma0: float = field(default=0.1, metadata={
        "gt": 0, "help": "initial step size (of the controller's parameters when both groups are searched)"})
    design_scale: Optional[float] = field(default=None, metadata={
        "gt": 0, "help": "optimize: both: the design parameters' initial step over the controller's (CMA_stds; "
                         "null: the ratio of the groups' RMS initial values)"})
    diagonal_above: int = field(default=500, metadata={
        "ge": 0, "help": "above this many parameters the covariance is diagonal (separable CMA-ES, pycma's "
                         "CMA_diagonal): memory and time per generation linear in n, not quadratic"})
    restarts: int = field(default=0, metadata={
        "ge": 0, "help": "IPOP restarts when pycma's termination criteria stop a search: each starts again from "
                         "the initial parameters with twice the population; with none left the run ends there"})
    lower: Optional[float] = field(default=None, metadata={"help": "lower bound on every parameter (null: none)"})
    upper: Optional[float] = field(default=None, metadata={"help": "upper bound on every parameter (null: none)"})
    batch: int = field(default=0, metadata={
        "ge": 0, "help": "episodes simulated together where the environment can batch them (0: the whole "
                         "population; 1: one at a time)"})


@dataclass
class PPOConfig:
    """The paper's PPO settings (appendix "Reinforcement Learning") as defaults."""

    optimize: str = field(default="control", metadata={
        "choices": ["control"], "help": "PPO trains the controller only; the design stays as the representation "
                                        "makes it (co-design it with diff_physics, cma_es or cppn_neat)"})
    total_timesteps: int = field(default=100_000, metadata={
        "ge": 1, "help": "environment steps in all (SB3 rounds the last iteration up to whole rollouts)"})
    timesteps_per_iteration: int = field(default=2048, metadata={
        "ge": 1, "help": "environment steps per logged, checkpointed iteration; a multiple of n_steps"})
    n_steps: int = field(default=2048, metadata={"ge": 2, "help": "rollout steps per episode of a rollout"})
    n_envs: int = field(default=1, metadata={
        "ge": 1, "help": "episodes played together; > 1 needs an environment that simulates populations (the MPM "
                         "ones, in one batched simulator); a rollout holds n_steps x n_envs steps"})
    batch_size: int = field(default=32, metadata={"ge": 2})
    gae_lambda: float = field(default=0.95, metadata={"ge": 0, "le": 1})
    gamma: float = field(default=0.98, metadata={"gt": 0, "le": 1})
    n_epochs: int = field(default=20, metadata={"ge": 1})
    ent_coef: float = field(default=0.001, metadata={"ge": 0})
    learning_rate: float = field(default=1e-4, metadata={"gt": 0})
    clip_range: float = field(default=0.2, metadata={"gt": 0})
    policy: str = field(default="mlp", metadata={
        "choices": ["mlp", "sine"],
        "help": "mlp: needs the mlp controller (output: action); sine: needs the sine controller"})
    normalize: str = field(default="none", metadata={
        "choices": ["none", "observations", "rewards", "both"],
        "help": "running normalisation (SB3's VecNormalize) of what PPO trains on; observations are folded into "
                "the controller's first layer, so it still acts on raw ones (not with policy: sine, which sees "
                "only the time)"})


@dataclass
class CPPNNEATConfig:
    """The paper's ES co-design baseline (appendix "Evolution Strategy") as defaults: population 10,
    100 generations, CMA-ES on the controller with initial step 0.1. The genome's settings are
    the neat_cppn representation's; these are NEAT's population settings."""

    optimize: str = field(default="both", metadata={
        "choices": MODES, "help": "design: NEAT on the body alone (the controller stays); control: the brain alone "
                                  "(the design stays); both: body and brain, one population shared (genome i plays "
                                  "brain candidate i). The brain: CMA-ES on the controller's parameters, or NEAT on "
                                  "the hyperneat controller's CPPN"})
    generations: int = field(default=100, metadata={"ge": 1})
    population: int = field(default=10, metadata={"ge": 2, "help": "NEAT's pop_size, also CMA-ES's popsize"})
    sigma0: float = field(default=0.1, metadata={
        "gt": 0, "help": "CMA-ES initial step size on the controller (unused for a hyperneat controller)"})
    batch: int = field(default=0, metadata={
        "ge": 0, "help": "episodes simulated together where the environment can batch them (0: the whole "
                         "population; 1: one at a time)"})
    compatibility_threshold: float = field(default=3.0, metadata={
        "gt": 0, "help": "genomic distance under which two genomes share a species"})
    elitism: int = field(default=1, metadata={"ge": 0, "help": "best genomes of each species kept unchanged"})
    survival_threshold: float = field(default=0.2, metadata={
        "gt": 0, "le": 1, "help": "fraction of each species allowed to reproduce"})
    max_stagnation: int = field(default=15, metadata={
        "ge": 1, "help": "generations a species may go without improving before it is removed"})
    species_elitism: int = field(default=1, metadata={"ge": 0, "help": "species protected from stagnation"})
