"""Registers this package's optimizers; imports nothing heavy (see codesign.hookspecs)."""

from codesign.hookspecs import hookimpl
from codesign.registry import PluginRegistrar


@hookimpl
def codesign_register(registry: PluginRegistrar) -> None:
    registry.add("optimizer", "diff_physics", "codesign_optimizers.diff_physics:DiffPhysics",
                 "codesign_optimizers.config:DiffPhysicsConfig",
                 "Adam on controller and/or design parameters through differentiable episodes (SoftZoo).")
    registry.add("optimizer", "cma_es", "codesign_optimizers.cma_es:CMAES", "codesign_optimizers.config:CMAESConfig",
                 "CMA-ES (the cma library) on the flattened controller and/or design parameters.")
    registry.add("optimizer", "ppo", "codesign_optimizers.ppo:PPO", "codesign_optimizers.config:PPOConfig",
                 "PPO (stable-baselines3) on the controller of a fixed design; the policy mean is the controller.")
    registry.add("optimizer", "cppn_neat", "codesign_optimizers.cppn_neat:CPPNNEAT",
                 "codesign_optimizers.config:CPPNNEATConfig",
                 "CPPN-NEAT (neat-python) on the neat_cppn design, CMA-ES on the controller, one population.")
