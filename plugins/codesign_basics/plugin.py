"""Registers this package's components; imports nothing heavy (see codesign.hookspecs)."""

from codesign.hookspecs import hookimpl
from codesign.registry import PluginRegistrar


@hookimpl
def codesign_register(registry: PluginRegistrar) -> None:
    registry.add(
        "controller",
        "sine",
        "codesign_basics.sine:SineController",
        "codesign_basics.config:SineConfig",
        "Open-loop sine-basis controller (SoftZoo): bound * tanh(sum alpha sin(omega t + phi) + beta).",
    )
    registry.add(
        "controller",
        "mlp",
        "codesign_basics.mlp:MLPController",
        "codesign_basics.config:MLPConfig",
        "Closed-loop MLP on observations: bound * tanh(MLP(obs)), or the weights of the sine basis.",
    )
    registry.add(
        "controller",
        "hyperneat",
        "codesign_basics.hyperneat:HyperNEATController",
        "codesign_basics.config:HyperNEATConfig",
        "HyperNEAT: a NEAT genome's CPPN paints the weights of a network on sine basis and observation.",
    )
    registry.add(
        "controller",
        "trajectory",
        "codesign_basics.trajectory:TrajectoryController",
        "codesign_basics.config:TrajectoryConfig",
        "Free per-step actions bound * tanh(logits[t]), for trajectory optimisation (open loop).",
    )
    registry.add(
        "optimizer",
        "evaluate",
        "codesign_basics.evaluate:Evaluate",
        "codesign_basics.config:EvaluateConfig",
        "Runs episodes of the current design and controller without changing them.",
    )
