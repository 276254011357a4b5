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
        "optimizer",
        "evaluate",
        "codesign_basics.evaluate:Evaluate",
        "codesign_basics.config:EvaluateConfig",
        "Runs episodes of the current design and controller without changing them.",
    )
