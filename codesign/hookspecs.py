"""Hook specifications: everything a plugin can contribute.

A plugin is a module (or object) with functions decorated by
``codesign.hookspecs.hookimpl`` whose names match the specs below. Arguments
may be left out of an implementation's signature if it does not need them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pluggy

if TYPE_CHECKING:
    import typer

    from codesign.registry import PluginRegistrar

hookspec = pluggy.HookspecMarker("codesign")
hookimpl = pluggy.HookimplMarker("codesign")


@hookspec
def codesign_register(registry: PluginRegistrar) -> None:
    """Add components with ``registry.add(kind, name, factory, config, description)``.

    Called once per plugin when the registry is first built. Keep the plugin
    module light: refer to factories and configs by ``"module:attr"`` strings
    so heavy imports happen only when a recipe uses them.
    """


@hookspec
def codesign_cli(app: typer.Typer) -> None:
    """Add commands (``app.command()``) or command groups (``app.add_typer()``) to the CLI."""


@hookspec
def codesign_seed(seed: int) -> None:
    """Seed random generators the core does not know about (e.g. Taichi's).

    Called by the runner after it has seeded Python, numpy and (if imported)
    torch, and before any component's ``setup``.
    """
