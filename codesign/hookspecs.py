"""Hook specifications: everything a plugin can contribute.

A plugin is a module (or object) with functions decorated by
``codesign.hookspecs.hookimpl`` whose names match the specs below. Arguments
may be left out of an implementation's signature if it does not need them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
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
def codesign_register_materials() -> list[str]:
    """Return the dotted names of modules that each add one material model to the MPM engine.

    Each module defines ``MODEL``, a ``codesign_mpm.materials.MaterialModel`` (its parameters,
    wave speed and Taichi stress or return mapping; see docs/plugins.md). The models are listed
    with the components (kind ``material``) and named by scenes (``material.kind``); the engine
    gives them ids after its own. Keep the modules light: they are imported when the registry
    is built (``codesign_mpm.materials.ti`` defers Taichi until a kernel is compiled).
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


@hookspec(firstresult=True)
def codesign_render_run(run_dir: Path, camera: str, fps: int, progress: bool) -> Path | None:
    """Render the best episode of the run in ``run_dir`` to ``run_dir/best/episode.mp4``; return it.

    Called by the runner at the end of a run whose recipe says ``render.enabled: true``. Return
    None when this plugin cannot render the run's environment; the first path returned wins.
    """


@dataclass
class ViewRecording:
    """What a plugin's `codesign_view` wrote: a recording that opens later, on this machine or another."""

    path: Path
    """The recording file."""
    how_to_open: str
    """Lines telling a user how to open it (the viewer and its commands)."""
    serve: Callable[[int], None]
    """Serve it to a web browser on this local port, blocking until interrupted (`codesign view --serve`)."""


@hookspec(firstresult=True)
def codesign_view(sources: list[Path], iterations: list[str], out: Path | None) -> ViewRecording | None:
    """Write an interactive 3D recording of ``sources`` for `codesign view`; return what was written.

    ``sources`` are what the user named: run directories (each replayed at ``iterations``, e.g.
    ``["0", "best"]``), directories of runs (a sweep or a study: each run's best), or files a plugin
    knows (an episode export, a design). ``out`` is the recording's path (None: the plugin's
    default). Return None when this plugin cannot view them, so another can; raise
    `codesign.errors.CodesignError` naming the bad input when it can but the input is wrong.
    """
