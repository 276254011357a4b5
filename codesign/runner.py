"""Builds a recipe's parts, runs the optimizer loop and keeps the run directory.

A run directory holds:

- ``config.yaml``: the resolved recipe (defaults filled in, ``run_dir`` set);
- ``metrics.jsonl``: one JSON object per iteration (with ``iteration`` and ``wall_time``);
- ``summary.json``: status, final and best metrics, wall time, versions, seed;
- ``checkpoint.pkl``: optimizer state and RNG state after the last completed
  iteration, from which :func:`resume` continues;
- ``learning_curve.png``: the episode return against iteration and wall time;
- ``best/``: what the optimizer found (see :mod:`codesign.artifacts`), and ``best/episode.mp4``
  when the recipe says ``render.enabled: true``.
"""

from __future__ import annotations

import json
import math
import os
import pickle
import platform
import random
import sys
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from omegaconf import OmegaConf

from codesign.artifacts import load_best_info
from codesign.errors import CodesignError
from codesign.interfaces import Controller, DesignFields, Environment, Optimizer, Representation
from codesign.plots import CURVE_FILE, learning_curve
from codesign.progress import progress_bar
from codesign.plugins import get_plugin_manager, get_registry
from codesign.recipe import ResolvedRecipe, resolve_recipe
from codesign.tracking import JsonlTracker, MultiTracker, Tracker, WandbTracker, wandb_off

if TYPE_CHECKING:
    from codesign.artifacts import EpisodeRecord

CONFIG_FILE = "config.yaml"
METRICS_FILE = "metrics.jsonl"
SUMMARY_FILE = "summary.json"
CHECKPOINT_FILE = "checkpoint.pkl"

_BASES = {
    "environment": Environment,
    "representation": Representation,
    "controller": Controller,
    "optimizer": Optimizer,
}
_RUNNER_KEYS = ("iteration", "wall_time")


@dataclass
class Parts:
    environment: Environment
    representation: Representation
    controller: Controller
    optimizer: Optimizer


def build_parts(recipe: ResolvedRecipe) -> Parts:
    """Construct each part as ``Factory(config)`` from its registry entry."""
    registry = get_registry()
    built = {}
    for kind, base in _BASES.items():
        section = recipe.sections[kind]
        part = registry.get(kind, section.name).load_factory()(section.config)
        if not isinstance(part, base):
            raise CodesignError(
                f"{kind} '{section.name}' built a {type(part).__name__}, which is not a {base.__name__}"
            )
        built[kind] = part
    return Parts(**built)


def seed_everything(seed: int) -> np.random.Generator:
    """Seed Python, numpy, torch (only if already imported) and plugins; return the run's generator."""
    random.seed(seed)
    np.random.seed(seed)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.manual_seed(seed)
    get_plugin_manager().hook.codesign_seed(seed=seed)
    return np.random.default_rng(seed)


def run(recipe: ResolvedRecipe, *, run_dir: str | Path | None = None, progress: bool = True) -> Path:
    """Run a recipe in a new run directory and return that directory."""
    if run_dir is None and recipe.settings.run_dir is None:
        directory = fresh_dir("runs", recipe.name)
    else:
        directory = Path(run_dir if run_dir is not None else recipe.settings.run_dir)
        if directory.exists() and any(directory.iterdir()):
            raise CodesignError(
                f"run directory {directory} is not empty; continue it with --resume {directory} "
                f"or choose another --run-dir"
            )
    directory.mkdir(parents=True, exist_ok=True)
    data = {**recipe.data, "run_dir": str(directory)}
    (directory / CONFIG_FILE).write_text(OmegaConf.to_yaml(OmegaConf.create(data)), encoding="utf-8")
    return _execute(recipe, data, directory, checkpoint=None, progress=progress)


def resume(run_dir: str | Path, *, progress: bool = True) -> Path:
    """Continue a run from its last completed iteration, appending to its metrics."""
    directory = Path(run_dir)
    data, recipe = load_run_data(directory)
    checkpoint_path = directory / CHECKPOINT_FILE
    checkpoint = None
    if checkpoint_path.is_file():
        with checkpoint_path.open("rb") as f:
            checkpoint = pickle.load(f)
    return _execute(recipe, data, directory, checkpoint=checkpoint, progress=progress)


def _execute(
    recipe: ResolvedRecipe, data: dict, run_dir: Path, *, checkpoint: dict | None, progress: bool
) -> Path:
    completed = checkpoint["completed"] if checkpoint else 0
    previous_wall_time = checkpoint["wall_time"] if checkpoint else 0.0
    rows = _kept_metrics(run_dir / METRICS_FILE, completed)
    started = time.perf_counter()

    def wall_time() -> float:
        return previous_wall_time + time.perf_counter() - started

    parts: Parts | None = None
    tracker: Tracker | None = None
    status, error = "failed", None
    env_closed = False
    try:
        tracker = _make_tracker(recipe, data, run_dir)
        parts = build_parts(recipe)
        rng = seed_everything(recipe.seed)
        env, optimizer = parts.environment, parts.optimizer
        parts.representation.setup(env.design_space, rng)
        parts.controller.setup(env.action_dim, env.observation_dim, env.control_dt, rng)
        if recipe.settings.init_controller is not None:
            from codesign.artifacts import load_controller

            load_controller(Path(recipe.settings.init_controller), parts.controller)
        optimizer.setup(env, parts.representation, parts.controller, rng=rng, run_dir=run_dir)
        if checkpoint:
            optimizer.load_state_dict(checkpoint["optimizer"])
            rng.bit_generator.state = checkpoint["rng"]
        with progress_bar(total=optimizer.iterations, initial=completed, desc=recipe.name, unit="iter",
                          show=progress) as bar:
            for iteration in range(completed, optimizer.iterations):
                if getattr(optimizer, "stopped", None):
                    break
                row = {**optimizer.step(), "iteration": iteration, "wall_time": wall_time()}
                tracker.log(row, step=iteration)
                rows.append(row)
                _save_checkpoint(
                    run_dir / CHECKPOINT_FILE,
                    {
                        "completed": iteration + 1,
                        "optimizer": optimizer.state_dict(),
                        "rng": rng.bit_generator.state,
                        "wall_time": wall_time(),
                    },
                )
                bar.update(1)
        if recipe.settings.render.enabled:
            env.close()  # the replay builds its own environment from config.yaml
            env_closed = True
            tracker.log_video("best_episode", render_best(run_dir, recipe, progress))
        status = "completed"
    except BaseException as exc:
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        error = f"{type(exc).__name__}: {exc}"
        raise
    finally:
        maximize = parts.optimizer.maximize if parts else {}
        summary = _summary(recipe, rows, maximize, status, error, wall_time(), load_best_info(run_dir))
        if parts is not None and getattr(parts.optimizer, "stopped", None):
            summary["stopped"] = parts.optimizer.stopped
        (run_dir / SUMMARY_FILE).write_text(json.dumps(summary, indent=2, default=str) + "\n", encoding="utf-8")
        curve = learning_curve(rows, run_dir / CURVE_FILE, recipe.name) if rows else None
        if tracker is not None:
            if curve is not None:
                tracker.log_image("learning_curve", curve)
            tracker.summary(summary)
            tracker.close()
        if parts is not None and not env_closed:
            parts.environment.close()
    return run_dir


def render_best(run_dir: Path, recipe: ResolvedRecipe, progress: bool) -> Path:
    """Render the run's best episode through the plugin that can (core knows no renderer)."""
    render = recipe.settings.render
    video = get_plugin_manager().hook.codesign_render_run(
        run_dir=run_dir, camera=render.camera, fps=render.fps, progress=progress
    )
    if video is None:
        environment = recipe.sections["environment"].name
        raise CodesignError(f"render.enabled: no plugin renders environment '{environment}' "
                            f"(codesign_mpm renders its own); set render.enabled=false")
    return Path(video)


def progress_report(run_dir: Path) -> str:
    """One line on how the run's episode return went: first, best (and when), where the curve is."""
    rows = read_metrics(Path(run_dir) / METRICS_FILE)
    returns = [(r["iteration"], r["episode_return"]) for r in rows if "episode_return" in r]
    if not returns:
        return ""
    played = [item for item in returns if not math.isnan(item[1])]  # nan: a design the environment refused
    if not played:
        return f"episode return: none of the {len(returns)} episodes was playable (the environment refused every design)"
    best_iteration, best = max(played, key=lambda item: item[1])
    curve = Path(run_dir) / CURVE_FILE
    where = f"; learning curve: {curve}" if curve.is_file() else ""
    return (f"episode return: first {returns[0][1]:.4g}, best {best:.4g} (iteration {best_iteration}), "
            f"last {returns[-1][1]:.4g}{where}")


def load_run_data(run_dir: str | Path) -> tuple[dict, ResolvedRecipe]:
    """A run directory's recipe as stored (unresolved interpolations kept) and resolved."""
    directory = Path(run_dir)
    config_path = directory / CONFIG_FILE
    if not config_path.is_file():
        raise CodesignError(f"{directory} is not a run directory (no {CONFIG_FILE})")
    data = OmegaConf.to_container(OmegaConf.load(config_path), resolve=False)
    assert isinstance(data, dict)
    return data, resolve_recipe(data)


@contextmanager
def set_up_parts(recipe: ResolvedRecipe) -> Iterator[tuple[Parts, np.random.Generator]]:
    """A recipe's parts built and set up from its seed, as a run sets them up before its optimizer
    (the representation's and the controller's starting parameters); yields (parts, the run's
    generator) and closes the environment."""
    parts = build_parts(recipe)
    try:
        rng = seed_everything(recipe.seed)
        env = parts.environment
        parts.representation.setup(env.design_space, rng)
        parts.controller.setup(env.action_dim, env.observation_dim, env.control_dt, rng)
        yield parts, rng
    finally:
        parts.environment.close()


@contextmanager
def _set_up_parts(run_dir: str | Path, overrides: dict | None = None
                  ) -> Iterator[tuple[Parts, ResolvedRecipe, np.random.Generator]]:
    """The run's parts rebuilt from its config (with `overrides` merged in) and set up from its seed
    as the run set them up; yields (parts, recipe, the run's generator) and closes the environment."""
    data, recipe = load_run_data(run_dir)
    if overrides:
        recipe = resolve_recipe(OmegaConf.to_container(OmegaConf.merge(OmegaConf.create(data),
                                                                       OmegaConf.create(overrides)), resolve=False))
    with set_up_parts(recipe) as (parts, rng):
        yield parts, recipe, rng


@contextmanager
def best_parts(run_dir: str | Path, overrides: dict | None = None
               ) -> Iterator[tuple[Parts, Any, np.random.Generator]]:
    """The run's parts rebuilt from its config (with `overrides` merged in, e.g.
    {"environment": {"cfl": 0.1}}), set up as the run set them up, holding its best controller;
    yields (parts, best design, the run's generator) and closes the environment."""
    from codesign.artifacts import load_controller, load_design

    with _set_up_parts(run_dir, overrides) as (parts, _, rng):
        env = parts.environment
        design = load_design(Path(run_dir))
        if len(design.occupancy) != len(env.design_space.points):
            raise CodesignError(f"{run_dir}: its best design has {len(design.occupancy)} particles, the environment "
                                f"{'with ' + str(overrides) + ' ' if overrides else ''}samples "
                                f"{len(env.design_space.points)}: a replay keeps the run's design, so change "
                                "settings that keep its sampling (e.g. environment.cfl, not environment.dx)")
        load_controller(Path(run_dir), parts.controller)
        yield parts, design, rng


@contextmanager
def start_parts(run_dir: str | Path) -> Iterator[tuple[Parts, DesignFields, np.random.Generator]]:
    """Iteration 0's design and controller: the run's parts set up from its seed before its first
    update (with its `init_controller`, if any); yields (parts, the design they start from, the
    run's generator) and closes the environment. A run keeps no later iteration's parameters, only
    its best (`best_parts`)."""
    from codesign.artifacts import load_controller

    with _set_up_parts(run_dir) as (parts, recipe, rng):
        if recipe.settings.init_controller is not None:
            load_controller(Path(recipe.settings.init_controller), parts.controller)
        yield parts, parts.representation(), rng


def replay_best(run_dir: str | Path, episodes: int = 1, overrides: dict | None = None) -> list[EpisodeRecord]:
    """Replay a run's best design and controller for `episodes` episodes (with `overrides` merged
    into its config, as `best_parts` takes them); their records (return, trajectory and the
    environment's episode metrics, e.g. an MPM body's torn_fraction)."""
    from codesign.artifacts import play

    with best_parts(run_dir, overrides) as (parts, design, rng):
        return [play(parts.environment, design, parts.controller, seed=int(rng.integers(2**31)))
                for _ in range(episodes)]


def evaluate_best(run_dir: str | Path, episodes: int = 1) -> list[float]:
    """Replay a run's best design and controller for `episodes` episodes; their returns."""
    return [record.episode_return for record in replay_best(run_dir, episodes)]


def _make_tracker(recipe: ResolvedRecipe, data: dict, run_dir: Path) -> Tracker:
    trackers: list[Tracker] = [JsonlTracker(run_dir / METRICS_FILE)]
    tracking = recipe.settings.tracking
    if tracking.wandb and not wandb_off(tracking.wandb_mode):
        trackers.append(
            WandbTracker(
                run_dir,
                mode=tracking.wandb_mode,
                project=tracking.project,
                group=tracking.group,
                name=recipe.name,
                config=data,
            )
        )
    return MultiTracker(trackers)


def best_metrics(rows: list[dict], maximize: Mapping[str, bool], best_episode: Mapping[str, Any]) -> dict[str, float]:
    """summary.json's `best`: each metric's best over the iterations (the highest, or the lowest
    where the optimizer says so, as for a loss), except the figures of the best episode itself
    (`best/info.json`: e.g. the body's torn-off mass), which are that episode's, not the extreme of
    every episode's."""
    best: dict[str, float] = {}
    for row in rows:
        for key, value in row.items():
            if key in _RUNNER_KEYS or isinstance(value, bool) or not isinstance(value, (int, float)):
                continue
            if not math.isfinite(value):
                continue
            better = max if maximize.get(key, True) else min
            best[key] = better(best[key], value) if key in best else value
    best.update({key: value for key, value in best_episode.items()
                 if key in best and key not in ("iteration", "episode_return")})
    return best


def _summary(
    recipe: ResolvedRecipe,
    rows: list[dict],
    maximize: Mapping[str, bool],
    status: str,
    error: str | None,
    wall_time: float,
    best_episode: Mapping[str, Any],
) -> dict[str, Any]:
    summary: dict[str, Any] = {
        "status": status,
        "recipe": recipe.name,
        "seed": recipe.seed,
        "iterations_completed": len(rows),
        "final": {k: v for k, v in rows[-1].items() if k not in _RUNNER_KEYS} if rows else {},
        "best": best_metrics(rows, maximize, best_episode),
        "wall_time": wall_time,
        "versions": _versions(),
    }
    if error is not None:
        summary["error"] = error
    return summary


def _versions() -> dict[str, str]:
    """Versions of the packages that shape results, read from metadata (nothing is imported)."""
    versions = {"python": platform.python_version()}
    for dist in ("codesign", "numpy", "taichi", "torch"):
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    return versions


NON_FINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}
"""How the metrics file writes non-finite numbers (strings, which JSON accepts), read back."""


def read_metrics(path: Path) -> list[dict]:
    """The rows of a metrics.jsonl (none if it does not exist), non-finite numbers as floats again."""
    if not path.exists():
        return []
    return [{k: NON_FINITE.get(v, v) if isinstance(v, str) else v for k, v in json.loads(line).items()}
            for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def _kept_metrics(path: Path, completed: int) -> list[dict]:
    """Rows of iterations covered by the checkpoint; later rows (logged, not checkpointed) are dropped."""
    rows = read_metrics(path)
    kept = [row for row in rows if row.get("iteration", math.inf) < completed]
    if len(kept) != len(rows):
        path.write_text("".join(json.dumps(row) + "\n" for row in kept), encoding="utf-8")
    return kept


def _save_checkpoint(path: Path, state: dict) -> None:
    """Write atomically so a crash mid-write leaves the previous checkpoint intact."""
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as f:
        pickle.dump(state, f)
    os.replace(tmp, path)


def fresh_dir(parent: str, name: str) -> Path:
    """A new directory name ``parent/<name>-<YYYYmmdd-HHMMSS>[-n]`` (not created)."""
    base = Path(parent) / f"{name}-{datetime.now():%Y%m%d-%H%M%S}"
    candidate, n = base, 1
    while candidate.exists():
        candidate, n = Path(f"{base}-{n}"), n + 1
    return candidate
