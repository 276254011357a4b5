"""Registers this package's representations; imports nothing heavy (see codesign.hookspecs)."""

from codesign.hookspecs import hookimpl
from codesign.registry import PluginRegistrar


@hookimpl
def codesign_register(registry: PluginRegistrar) -> None:
    registry.add(
        "representation",
        "particle",
        "codesign_designs.particle:ParticleRepresentation",
        "codesign_designs.config:ParticleConfig",
        "Per-particle logits (SoftZoo PBR): sigmoid occupancy and stiffness, softmax muscle membership.",
    )
