"""The paper's two analyses as studies (`codesign study loss_landscape`, `codesign study
muscle_ambiguity`): not tables of arms but measurements of one robot, run by `codesign.study`.

Each takes the study (its base recipe gives the environment and the controller; `study.parameters`
the rest) and the study's directory, appends one JSON line per measured point to `points.jsonl`
(a killed analysis continues after the last point written), draws its chart and returns the
Markdown of its findings.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from codesign.artifacts import play
from codesign.errors import RecipeError
from codesign.interfaces import DesignFields
from codesign.progress import progress_bar
from codesign.recipe import resolve_recipe
from codesign.runner import build_parts, seed_everything

POINTS = "points.jsonl"


def _points(root: Path) -> list[dict]:
    path = root / POINTS
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()] if path.is_file() else []


def _measure(root: Path, keys: list[Any], measure: Callable[[Any], dict], progress: bool, desc: str) -> list[dict]:
    """`measure(key)` for every key not yet in points.jsonl (appended as it goes); all points, in key order."""
    done = {json.dumps(p["key"]): p for p in _points(root)}
    todo = [k for k in keys if json.dumps(k) not in done]
    root.mkdir(parents=True, exist_ok=True)
    with progress_bar(total=len(keys), initial=len(keys) - len(todo), desc=desc, unit="point", show=progress) as bar:
        for key in todo:
            point = {"key": key, **measure(key)}
            with open(root / POINTS, "a", encoding="utf-8") as f:
                f.write(json.dumps(point) + "\n")
            done[json.dumps(key)] = point
            bar.update(1)
    return [done[json.dumps(k)] for k in keys]


def _setup(study) -> tuple[Any, Any, DesignFields]:
    """The study's environment and controller (seeded as a run of its recipe would be), and the
    full workspace as a design: every particle occupied, the workspace's own stiffness and muscles."""
    recipe = resolve_recipe({**study.recipe, "optimizer": {"name": "evaluate"}}, default_name=study.name)
    parts = build_parts(recipe)
    rng = seed_everything(recipe.seed)
    env, controller = parts.environment, parts.controller
    controller.setup(env.action_dim, env.observation_dim, env.control_dt, rng)
    space = env.design_space
    n = len(space.points)
    full = DesignFields(np.ones(n), np.full(n, space.default_stiffness), space.muscle.copy(), space.fiber.copy())
    return env, controller, full


def _voxels(space, shape: list[int]) -> np.ndarray:
    """(N, 3) the voxel of each workspace particle, on a grid of `shape` over the workspace's
    bounds (its faces, which the workspace's own muscle grid splits too)."""
    lo, hi = space.box()
    cells = np.floor((space.points - lo) / (hi - lo) * np.asarray(shape)).astype(int)
    return np.minimum(cells, np.asarray(shape) - 1)


def _plot(path: Path, title: str, draw: Callable[[Any], None]) -> None:
    from codesign.plots import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.2), constrained_layout=True)
    draw(ax)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def loss_landscape(study, root: Path, progress: bool = True) -> str:
    """The loss (minus the return) along actuator-placement parameters, and against the size of a
    corner cut from the body.

    Placement: the particles of one voxel of the workspace (a cell of a `voxels` grid) keep their
    own muscle membership with weight 1 - s and join another actuator with weight s (soft
    placement, as in the paper); s runs over [0, 1], for every voxel and every actuator but the
    voxel's own. Shape: a cube of
    edge c (a fraction of the workspace's height) is removed from the workspace's `corner`.
    """
    params = study.parameters
    env, controller, full = _setup(study)
    points = env.design_space.points
    cells = _voxels(env.design_space, params["voxels"])
    voxels = [tuple(int(i) for i in v) for v in np.unique(cells, axis=0)]
    members = {v: np.all(cells == np.asarray(v), axis=1) for v in voxels}
    own = {v: int(np.bincount(full.muscle[members[v]].argmax(1), minlength=env.action_dim).argmax()) for v in voxels}
    curves = [(v, to) for v in voxels for to in range(env.action_dim) if to != own[v]]

    def placement(key: list) -> dict:
        *v, to, s = key
        v = tuple(v)
        muscle = full.muscle.copy()  # s = 0 is the workspace's own design, exactly
        muscle[members[v]] = (1.0 - s) * muscle[members[v]] + s * np.eye(env.action_dim)[to]
        record = play(env, DesignFields(full.occupancy, full.stiffness, muscle, full.fiber), controller)
        return {"loss": -record.episode_return, "torn": record.metrics.get("torn_fraction", float("nan"))}

    lo, hi = points.min(0), points.max(0)
    corner = np.asarray(params["corner"], dtype=float)  # 0 or 1 per axis: which corner of the workspace

    def cut(c: float) -> dict:
        edge = c * (hi[1] - lo[1])
        near = np.where(corner > 0, hi - points < edge, points - lo < edge)
        occupancy = np.where(near.all(axis=1), 0.0, 1.0)
        record = play(env, DesignFields(occupancy, full.stiffness, full.muscle, full.fiber), controller)
        return {"loss": -record.episode_return, "removed": float(1.0 - occupancy.mean()),
                "com": record.com.tolist(), "torn": record.metrics.get("torn_fraction", float("nan"))}

    s_values = [round(float(s), 6) for s in np.linspace(0.0, 1.0, params["points"])]
    c_values = [round(float(c), 6) for c in params["corners"]]
    keys = [["placement", *v, to, s] for v, to in curves for s in s_values] + [["corner", c] for c in c_values]
    try:  # one points.jsonl, as every analysis keeps (what `codesign study --docs` commits)
        measured = _measure(root, keys, lambda key: placement(key[1:]) if key[0] == "placement" else cut(key[1]),
                            progress, "point")
    finally:
        env.close()
    placed = [p for p in measured if p["key"][0] == "placement"]
    cuts = [p for p in measured if p["key"][0] == "corner"]
    losses = np.array([p["loss"] for p in placed]).reshape(len(curves), len(s_values))

    def local_minima(loss: np.ndarray) -> list[int]:
        """Interior and end points lower than their neighbours (by more than float32 noise)."""
        tol = 1e-6 * max(1.0, float(np.abs(loss).max()))
        return [i for i in range(len(loss)) if (i == 0 or loss[i] < loss[i - 1] - tol)
                and (i == len(loss) - 1 or loss[i] < loss[i + 1] - tol)]

    minima = [local_minima(loss) for loss in losses]
    several = [i for i, m in enumerate(minima) if len(m) > 1]
    shown = max(range(len(curves)), key=lambda i: (len(minima[i]), np.ptp(losses[i])))

    def draw_placement(ax) -> None:
        for loss in losses:
            ax.plot(s_values, loss, color="tab:gray", linewidth=0.5, alpha=0.5)
        (v, to) = curves[shown]
        ax.plot(s_values, losses[shown], color="tab:blue", marker=".",
                label=f"voxel {list(v)}: actuator {own[v]} -> {to}")
        ax.scatter([s_values[i] for i in minima[shown]], losses[shown][minima[shown]], color="tab:red", zorder=3,
                   label="its local minima")
        ax.set_xlabel("s: a voxel's membership moved from its own actuator to another")
        ax.set_ylabel("loss (minus return)")
        ax.legend(fontsize=8)

    def draw_corner(ax) -> None:
        for point in cuts:
            com = np.asarray(point["com"])
            ax.plot(np.arange(1, len(com) + 1) * env.control_dt, com[:, 0] - com[0, 0],
                    label=f"corner {point['key'][1]:.2f} ({point['removed']:.1%} removed)")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("centre of mass x - x(first step)")
        ax.legend(fontsize=7)

    _plot(root / f"{study.name}.png", "loss along actuator-placement parameters", draw_placement)
    _plot(root / f"{study.name}_corner.png", "a box and the same box missing a corner", draw_corner)
    full_loss = cuts[0]["loss"]
    corner_rows = "\n".join(f"| {p['key'][1]:.2f} | {p['removed']:.1%} | {p['loss']:.4f} | {p['loss'] - full_loss:+.4f} |"
                            for p in cuts)
    v, to = curves[shown]
    return "\n\n".join([
        f"Placement: {len(curves)} parameters (each of the {len(voxels)} voxels of a {params['voxels']} grid moved "
        f"from its own actuator to each other one), {len(s_values)} values of s each. {len(several)} of them have "
        f"more than one local minimum; drawn in blue, voxel {list(v)} moved from actuator {own[v]} to {to} "
        f"({len(minima[shown])} minima, loss {losses[shown].min():.4f} to {losses[shown].max():.4f}). Along a "
        "parameter with several minima, gradient descent ends in the basin it starts in.",
        f"![placement]({study.name}.png)",
        "Shape: a cube cut from the workspace's corner " + str(params["corner"]) + ", its edge a fraction of the "
        "workspace's height (the same gait):",
        "| corner edge | mass removed | loss | against the full box |\n| --- | --- | --- | --- |\n" + corner_rows,
        f"![corner]({study.name}_corner.png)",
    ])


def muscle_ambiguity(study, root: Path, progress: bool = True) -> str:
    """Can control make up for stiffness, or for where the muscles are? (the paper's analysis)

    A target robot acts a random gait: the workspace with every particle's stiffness times m (for
    each multiplier m), or with its muscles placed at random over `target_actuators` actuators (each
    cell of a `voxels` grid given to one). A robot of the original stiffness, or with its own random
    placement of k actuators (for each k of `actuators`), then fits its actions from a fresh start
    (trajectory optimisation: per-step actions drawn anew, Adam through the differentiable simulator)
    on the earth mover's distance between its final particles and the target's (no correspondence
    used: POT's exact EMD, whose gradient is the optimal plan's), keeping the best iterate. Reported:
    that EMD relative to the distance the target's particles moved (EMD of its start and end frames),
    per target and seed."""
    import ot
    import torch

    from codesign_mpm.environment.bridge import simulate
    from codesign_mpm.environment.episode import design_inputs

    params = study.parameters
    env, _, full = _setup(study)
    T, K, bound = env.horizon, env.action_dim, params["bound"]
    if max(params["actuators"] + [params["target_actuators"]]) > K:
        raise RecipeError(f"invalid study '{study.name}': study.parameters.actuators and target_actuators go up to "
                         f"{max(params['actuators'] + [params['target_actuators']])}, the robot has {K} "
                         f"(environment.robot.muscle_groups)")
    n_robot = len(full.occupancy)  # the full workspace: no particle is dropped
    w = torch.full((n_robot,), 1.0 / n_robot, dtype=torch.float64)

    def final_x(design: DesignFields, actions: np.ndarray) -> np.ndarray:
        env.reset(design=design)
        for action in actions:
            env.step(action)
        return env.sim.particles_state()[0][:n_robot].astype(np.float64)

    def emd(a, b) -> torch.Tensor:
        """W2 distance of two equal-mass particle sets (POT's exact EMD; differentiable in torch inputs)."""
        return ot.emd2(w, w, ot.dist(torch.as_tensor(a), torch.as_tensor(b))) ** 0.5

    points = env.design_space.points
    cell_id = np.unique(_voxels(env.design_space, params["voxels"]), axis=0, return_inverse=True)[1].ravel()

    def placed(k: int, rng: np.random.Generator) -> DesignFields:
        """The workspace with each voxel's particles given to one of k actuators (of the robot's K)."""
        owner = rng.integers(0, k, cell_id.max() + 1)[cell_id]
        return DesignFields(full.occupancy, full.stiffness, np.eye(K)[owner], full.fiber)

    def fit(key: list) -> dict:
        kind, value, seed = key
        rng = np.random.default_rng(seed)
        if kind == "stiffness":
            target_design = DesignFields(full.occupancy, full.stiffness * value, full.muscle, full.fiber)
            design = full
        else:
            target_design = placed(params["target_actuators"], rng)
            design = placed(int(value), np.random.default_rng([seed, int(value)]))  # its own placement
        target_actions = bound * np.tanh(rng.normal(0.0, 1.0, (T, K)))
        target = final_x(target_design, target_actions)
        particles, inputs = design_inputs(env, design)
        fresh = np.random.default_rng([seed, 1_000 + int(1_000 * value)]).normal(0.0, 1.0, (T, K))
        raw = torch.tensor(fresh, requires_grad=True)  # a fresh controller, not the target's actions
        adam = torch.optim.Adam([raw], lr=params["lr"])
        goal = torch.as_tensor(target)
        best = (math.inf, raw.detach().clone())  # the fit keeps its best iterate (Adam's steps do not shrink)
        for _ in range(params["iterations"]):
            adam.zero_grad()
            sim = env.grad_simulator(particles)  # back to the design's initial state
            x = simulate(sim, bound * torch.tanh(raw), volume=inputs[0], youngs_modulus=inputs[1],
                         muscle=inputs[2], fiber=inputs[3])[2][:n_robot]
            loss = emd(x, goal)
            if loss.item() < best[0]:
                best = (loss.item(), raw.detach().clone())
            loss.backward()
            adam.step()
        fitted = final_x(design, (bound * torch.tanh(best[1])).numpy())
        return {"emd": float(emd(fitted, target)), "moved": float(emd(points, target)),
                "unfitted": float(emd(final_x(design, bound * np.tanh(fresh)), target))}

    keys = [["stiffness", float(m), s] for m in params["multipliers"] for s in range(params["seeds"])]
    keys += [["placement", float(k), s] for k in params["actuators"] for s in range(params["seeds"])]
    try:
        measured = _measure(root, keys, fit, progress, "fit")
    finally:
        env.close()

    def relative(p: dict, what: str) -> float:
        return p[what] / p["moved"] if p["moved"] > 0 else float("nan")

    def by(kind: str) -> dict[float, list[dict]]:
        groups: dict[float, list[dict]] = {}
        for p in measured:
            if p["key"][0] == kind:
                groups.setdefault(p["key"][1], []).append(p)
        return groups

    def band(ax, groups: dict[float, list[dict]], xlabel: str) -> None:
        xs = list(groups)
        for what, colour, label in (("emd", "tab:blue", "fitted"), ("unfitted", "tab:gray", "fresh start, not fitted")):
            v = np.array([[relative(p, what) for p in groups[x]] for x in xs])
            mean, std = v.mean(1), v.std(1, ddof=1) if v.shape[1] > 1 else np.zeros(len(xs))
            ax.plot(xs, mean, marker="o", color=colour, label=label)
            ax.fill_between(xs, mean - std, mean + std, color=colour, alpha=0.2)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("EMD of final frames / target's motion")
        ax.legend(fontsize=8)

    stiffness, placement = by("stiffness"), by("placement")
    _plot(root / f"{study.name}.png", "fitting control to other stiffness",
          lambda ax: band(ax, stiffness, "target's stiffness multiplier"))
    _plot(root / f"{study.name}_placement.png",
          f"fitting control to another muscle placement ({params['target_actuators']} actuators)",
          lambda ax: band(ax, placement, "actuators of the fitted robot"))

    def spread(v: list[float]) -> str:
        return f"{np.std(v, ddof=1):.3f}" if len(v) > 1 else "-"

    def table(groups: dict[float, list[dict]], name: Callable[[float], str], header: str) -> str:
        rows = [f"| {name(x)} | {np.mean([relative(p, 'emd') for p in ps]):.3f} | "
                f"{spread([relative(p, 'emd') for p in ps])} | {np.mean([relative(p, 'unfitted') for p in ps]):.3f} | "
                f"{len(ps)} |" for x, ps in groups.items()]
        return f"| {header} | fitted: mean | std | fresh start: mean | seeds |\n| --- | --- | --- | --- | --- |\n" + \
            "\n".join(rows)

    return "\n\n".join([
        "Relative matching error: the earth mover's distance between the fitted robot's and the target's final "
        "particles, divided by how far the target's particles moved from the start (EMD of its start and end). "
        "'Fresh start' plays the fit's starting actions, the error before fitting.",
        "Stiffness: the original robot fits a target whose every particle is m times as stiff.",
        table(stiffness, lambda m: f"x{m:g}", "target stiffness"),
        f"![ambiguity]({study.name}.png)",
        f"Muscle placement: a robot with k actuators placed at random fits a target with "
        f"{params['target_actuators']} placed at random (its own placement, per seed).",
        table(placement, lambda k: f"{k:g}", "actuators"),
        f"![placement]({study.name}_placement.png)",
    ])
