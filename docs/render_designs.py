"""Draw the pictures of docs/designs.md (headless) and print its parameter-count table.

Run from the repository root: ``python docs/render_designs.py``. It writes small PNGs to
docs/images/designs/: each animal coloured by muscle group (and from the side, the top and the
front), the fish primitives, each representation's initial design on the default workspace (the
`ground` environment's box robot at dx = 1/48, K = 4, seed 0), particles with occupancy >= 0.5
coloured by their strongest muscle (grey: passive), and an SDF-Lerp blend series from the seal
to the fish.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from codesign.bodies import ANIMALS, FISH_FAMILY, library_body  # noqa: E402
from codesign.plugins import get_registry  # noqa: E402

OUT = Path(__file__).resolve().parent / "images" / "designs"
REPRESENTATIONS = ["particle", "voxel", "implicit", "diff_cppn", "sdf_lerp", "wasserstein", "neat_cppn"]
COLORS = plt.get_cmap("tab10")
PAIRED_COLORS = plt.get_cmap("tab20")


VIEWS = {"side": (0, -90), "top": (90, -90), "front": (0, 0)}  # (elevation, azimuth) of the camera


def scatter(ax, points: np.ndarray, groups: np.ndarray, size: float, view: tuple[float, float] = (20, -60)) -> None:
    """Points in 3-D, x along the page, y up, coloured by group (grey: -1)."""
    colors = COLORS if groups.max() < 10 else PAIRED_COLORS  # a left and right pair: one hue, dark and light
    colors = np.where(groups[:, None] >= 0, colors(np.maximum(groups, 0) % colors.N), (0.75, 0.75, 0.75, 1.0))
    ax.scatter(points[:, 0], points[:, 2], points[:, 1], c=colors, s=size, linewidths=0, depthshade=True)
    lo, hi = points.min(0), points.max(0)
    half = (hi - lo).max() / 2
    middle = (lo + hi) / 2
    ax.set_xlim(middle[0] - half, middle[0] + half)
    ax.set_ylim(middle[2] - half, middle[2] + half)
    ax.set_zlim(middle[1] - half, middle[1] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=view[0], azim=view[1])
    ax.set_axis_off()


def figure(title: str, points: np.ndarray, groups: np.ndarray, path: Path, size: float = 3.0) -> None:
    fig = plt.figure(figsize=(2.6, 2.2), dpi=90)
    ax = fig.add_subplot(projection="3d")
    scatter(ax, points, groups, size)
    fig.suptitle(title, fontsize=8, y=0.97)
    fig.subplots_adjust(0, 0, 1, 1)
    fig.savefig(path)
    plt.close(fig)


def render_bodies() -> None:
    for name in (*ANIMALS, *FISH_FAMILY):
        body = library_body(name)
        points = body.sample(0.02)
        groups = body.labels(points).groups
        figure(f"{name} ({body.n_groups} muscles)", points, groups, OUT / f"body_{name}.png")


def render_animal_views() -> None:
    """Each animal from the side, the top and the front, coloured by muscle group."""
    for name in ANIMALS:
        body = library_body(name)
        points = body.sample(0.015)
        groups = body.labels(points).groups
        fig = plt.figure(figsize=(6.6, 2.2), dpi=90)
        for i, (view, angles) in enumerate(VIEWS.items()):
            ax = fig.add_subplot(1, 3, i + 1, projection="3d")
            scatter(ax, points, groups, 2.0, angles)
            ax.set_title(view, fontsize=8, y=0.92)
        fig.suptitle(textwrap.fill(f"{name}: {', '.join(body.group_names)}", 120), fontsize=7, y=0.99)
        fig.subplots_adjust(0, 0, 1, 0.92, wspace=0)
        fig.savefig(OUT / f"body_{name}_views.png")
        plt.close(fig)


def render_blend_series(space, first: str = "seal", second: str = "fish", steps: int = 5) -> None:
    """SDF-Lerp between two primitives: every weight (geometry, stiffness, muscle, fibre) at 1 - t, t."""
    entry = get_registry().get("representation", "sdf_lerp")
    representation = entry.load_factory()(entry.load_config()(primitives=[first, second], init_noise=0.0))
    representation.setup(space, np.random.default_rng(0))
    fig = plt.figure(figsize=(2.0 * steps, 2.0), dpi=90)
    for i, t in enumerate(np.linspace(0.0, 1.0, steps)):
        with torch.no_grad():
            for logits in representation.parameters():
                logits.copy_(torch.log(torch.tensor([1 - t, t], dtype=logits.dtype).clamp_min(1e-12)))
            design = representation()
        kept = np.asarray(design.occupancy) >= 0.5
        muscle = np.asarray(design.muscle)[kept]
        ax = fig.add_subplot(1, steps, i + 1, projection="3d")
        scatter(ax, space.points[kept], np.where(muscle.max(1) > 1e-6, muscle.argmax(1), -1), 3.0)
        ax.set_title(f"t = {t:.2f}", fontsize=8, y=0.9)
    fig.suptitle(f"sdf_lerp from {first} (t = 0) to {second} (t = 1)", fontsize=8, y=0.99)
    fig.subplots_adjust(0, 0, 1, 0.9, wspace=0)
    fig.savefig(OUT / f"blend_{first}_{second}.png")
    plt.close(fig)


def ground_space():
    """The default ground environment's design space (builds particles only, no simulation)."""
    from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS
    from codesign_mpm.environment.env import LocomotionEnv

    return LocomotionEnv(PRESET_CONFIGS["ground"](), PRESETS["ground"]).design_space


def render_representations() -> list[tuple[str, int]]:
    torch.set_num_threads(1)
    space = ground_space()
    counts = []
    for name in REPRESENTATIONS:
        entry = get_registry().get("representation", name)
        representation = entry.load_factory()(entry.load_config()())
        representation.setup(space, np.random.default_rng(0))
        counts.append((name, sum(t.numel() for t in representation.parameters())))
        with torch.no_grad():
            design = representation()
        kept = np.asarray(design.occupancy) >= 0.5
        muscle = np.asarray(design.muscle)[kept]
        groups = np.where(muscle.max(1) > 1e-6, muscle.argmax(1), -1)
        figure(f"{name}: {kept.sum()} of {len(kept)} particles", space.points[kept], groups,
               OUT / f"representation_{name}.png", size=4.0)
    return counts


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    render_bodies()
    render_animal_views()
    counts = render_representations()
    render_blend_series(ground_space())
    print("| representation | parameters (default ground workspace, K = 4) |\n| --- | --- |")
    for name, count in counts:
        print(f"| {name} | {count} |")


if __name__ == "__main__":
    main()
