"""Playing episodes and keeping what a run found: the best design and controller, reloadable.

A run directory's ``best/`` holds

- ``design.npz``: the design fields (occupancy, stiffness, muscle, fiber) over the workspace
  points, which is what an environment consumes, whatever representation or optimizer made it;
- ``design.ply``: the particles the design keeps, coloured by muscle group (any point viewer);
- ``controller.pt``: the controller's parameters (a list of tensors, `torch.save`);
- ``trajectory.npz``: centre of mass and action per step of the best episode;
- ``info.json``: the iteration and return that made it the best.

`codesign eval RUN_DIR` rebuilds the run's parts from its ``config.yaml`` and replays these.
Torch and trimesh are imported inside the functions that need them.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from codesign.errors import CodesignError, DesignError
from codesign.interfaces import Controller, DesignFields, Environment

BEST = "best"
BEST_INFO = Path(BEST) / "info.json"
"""The best episode's iteration, return and figures, in a run directory."""
DESIGN_FIELDS = ("occupancy", "stiffness", "muscle", "fiber")
KEEP_THRESHOLD = 0.5


def to_numpy(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=np.float64)


EPISODE_METRICS = "episode_metrics"
"""The key of a step's `info` under which an environment reports figures of the whole episode so far
(e.g. the mass a body lost to numerical fracture); the last step's are the episode's."""


@dataclass
class EpisodeRecord:
    episode_return: float  # nan: the design could not be played (`DesignError`), it ranks last
    length: int
    com: np.ndarray  # (T, 3) robot centre of mass after each step
    actions: np.ndarray  # (T, K)
    metrics: dict[str, float] = field(default_factory=dict)  # the environment's episode figures

    @property
    def played(self) -> bool:
        return not math.isnan(self.episode_return)


def unplayable() -> EpisodeRecord:
    """The record of a design the environment refused: no return (nan), ranked last."""
    return EpisodeRecord(math.nan, 0, np.zeros((0, 3)), np.zeros((0, 0)), {"unplayable": 1.0})


def play(env: Environment, design: DesignFields | None, controller: Controller, seed: int | None = None
         ) -> EpisodeRecord:
    """One episode without gradients: reset with `design`, act until done or the horizon. A design
    the environment refuses (`DesignError`) gives an unplayed record (return nan)."""
    import torch

    with torch.no_grad():
        try:
            observation = env.reset(design=design, seed=seed)
        except DesignError:
            return unplayable()
        controller.reset()
        total, coms, actions, metrics = 0.0, [], [], {}
        for t in range(env.horizon):
            action = to_numpy(controller(observation, t))
            result = env.step(action)
            total += float(result.reward)
            actions.append(action)
            coms.append(to_numpy(result.info.get("com", np.full(3, np.nan))))
            metrics = result.info.get(EPISODE_METRICS, metrics)
            observation = result.observation
            if result.done:
                break
    return _record(total, coms, actions, metrics)


def _record(total: float, coms: list, actions: list, metrics: dict) -> EpisodeRecord:
    """An episode's record from its summed reward, per-step centres of mass and actions, and figures."""
    return EpisodeRecord(float(total), len(actions), np.array(coms).reshape(-1, 3),
                         np.array(actions).reshape(len(actions), -1), dict(metrics))


def rank_last(returns: list[float]) -> list[float]:
    """Returns with the unplayed ones (nan) just below the worst played one, for rankers."""
    played = [r for r in returns if not math.isnan(r)]
    floor = min(played) - 1.0 if played else 0.0
    return [floor if math.isnan(r) else r for r in returns]


def play_population(env: Environment, designs: list[DesignFields | None], controllers: list[Controller],
                    seed: int | None = None, batch: int = 0) -> list[EpisodeRecord]:
    """Episodes of (design, controller) pairs without gradients, the same as `play` of each pair.

    Where the environment is `batched`, up to `batch` episodes (0: all) are simulated together
    in one launch per substep; elsewhere they run one after the other. An episode that ends
    early is recorded up to its end while the others go on.
    """
    if len(designs) != len(controllers):
        raise ValueError(f"{len(designs)} designs but {len(controllers)} controllers")
    size = batch or len(designs)
    if not env.batched or size == 1:
        return [play(env, design, controller, seed) for design, controller in zip(designs, controllers)]
    records = []
    for first in range(0, len(designs), size):
        group = slice(first, first + size)
        try:
            records += _play_together(env, designs[group], controllers[group], seed)
        except DesignError:  # a refused design in the group: play its members one at a time
            records += [play(env, design, controller, seed) for design, controller in
                        zip(designs[group], controllers[group])]
    return records


def _play_together(env: Environment, designs: list, controllers: list[Controller], seed: int | None
                   ) -> list[EpisodeRecord]:
    import torch

    B = len(designs)
    totals, coms, actions = np.zeros(B), [[] for _ in range(B)], [[] for _ in range(B)]
    metrics: list[dict] = [{} for _ in range(B)]
    running = np.ones(B, dtype=bool)
    with torch.no_grad():
        observations = env.reset_population(designs, seed=seed)
        for controller in controllers:
            controller.reset()
        for t in range(env.horizon):
            step = np.zeros((B, env.action_dim))
            for b in np.flatnonzero(running):
                step[b] = to_numpy(controllers[b](observations[b], t))
            results = env.step_population(step)
            for b in np.flatnonzero(running):
                totals[b] += float(results[b].reward)
                actions[b].append(step[b])
                coms[b].append(to_numpy(results[b].info.get("com", np.full(3, np.nan))))
                metrics[b] = results[b].info.get(EPISODE_METRICS, metrics[b])
                observations[b] = results[b].observation
                running[b] = not results[b].done
            if not running.any():
                break
    return [_record(totals[b], coms[b], actions[b], metrics[b]) for b in range(B)]


def save_best(run_dir: Path, design: DesignFields, points: np.ndarray, controller: Controller,
              record: EpisodeRecord | None, info: dict) -> None:
    """Write the run's best design, controller and episode (replacing the previous best)."""
    import torch

    best = Path(run_dir) / BEST
    best.mkdir(parents=True, exist_ok=True)
    fields = {name: to_numpy(getattr(design, name)) for name in DESIGN_FIELDS}
    np.savez_compressed(best / "design.npz", points=points, **fields)
    write_ply(best / "design.ply", points, fields["occupancy"], fields["muscle"])
    torch.save([p.detach().cpu() for p in controller.parameters()], best / "controller.pt")
    if record is not None:
        np.savez_compressed(best / "trajectory.npz", com=record.com, actions=record.actions,
                            episode_return=record.episode_return)
    (Path(run_dir) / BEST_INFO).write_text(json.dumps(info, indent=2, default=float) + "\n", encoding="utf-8")


class BestKeeper:
    """Remembers the best return so far and writes its design and controller to run_dir/best."""

    def __init__(self, environment: Environment, controller: Controller, run_dir: Path | None) -> None:
        self.environment, self.controller, self.run_dir = environment, controller, run_dir
        self.best_return = -math.inf

    def offer(self, episode_return: float, design: DesignFields, record: EpisodeRecord | None, iteration: int,
              controller: Controller | None = None) -> bool:
        """Keep this episode if it beats the best so far: its `controller` (default: the shared one,
        so call before its parameters change) and design."""
        if not episode_return > self.best_return:
            return False
        self.best_return = episode_return
        if self.run_dir is not None:
            save_best(Path(self.run_dir), design, self.environment.design_space.points, controller or self.controller,
                      record, {"iteration": iteration, "episode_return": episode_return,
                               **(record.metrics if record is not None else {})})
        return True


PALETTE = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                    [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]], dtype=np.uint8)
"""Muscle group colours (matplotlib's tab10), repeated beyond ten groups."""


def write_ply(path: Path, points: np.ndarray, occupancy: np.ndarray, muscle: np.ndarray) -> None:
    """The kept particles as a point cloud, coloured by their strongest muscle (grey: none)."""
    import trimesh

    keep = occupancy.reshape(-1) >= KEEP_THRESHOLD
    colors = np.full((int(keep.sum()), 4), 255, dtype=np.uint8)
    colors[:, :3] = 160
    if muscle.size:
        active = np.abs(muscle[keep]).max(1) > 0
        colors[active, :3] = PALETTE[np.abs(muscle[keep][active]).argmax(1) % len(PALETTE)]
    trimesh.PointCloud(points[keep], colors=colors).export(path)


def load_best_info(run_dir: Path) -> dict:
    """The best episode's iteration, return and figures ({} while the run has saved no best)."""
    path = Path(run_dir) / BEST_INFO
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}


def load_design(run_dir: Path) -> DesignFields:
    path = Path(run_dir) / BEST / "design.npz"
    if not path.is_file():
        raise CodesignError(f"{run_dir} has no {BEST}/design.npz: the run saved no best design yet")
    data = np.load(path)
    return DesignFields(**{name: data[name] for name in DESIGN_FIELDS})


def load_controller(run_dir: Path, controller: Controller) -> None:
    """Copy the saved parameters into an already set-up controller of the same shape."""
    import torch

    path = Path(run_dir) / BEST / "controller.pt"
    if not path.is_file():
        raise CodesignError(f"{run_dir} has no {BEST}/controller.pt: the run saved no best controller yet")
    saved = torch.load(path)
    params = controller.parameters()
    if [tuple(p.shape) for p in params] != [tuple(s.shape) for s in saved]:
        raise CodesignError(f"{path} holds parameters of shapes {[tuple(s.shape) for s in saved]}, but the "
                            f"run's controller has {[tuple(p.shape) for p in params]}")
    with torch.no_grad():
        for p, s in zip(params, saved):
            p.copy_(s)
