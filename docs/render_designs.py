"""Draw the pictures of docs/designs.md (headless) and print its parameter-count table.

Run from the repository root: ``python docs/render_designs.py``. It writes small PNGs to
docs/images/designs/: each animal coloured by muscle group, the fish primitives, and each
representation's initial design on the default workspace (the `ground` environment's box robot
at dx = 1/48, K = 4, seed 0), particles with occupancy >= 0.5 coloured by their strongest
muscle (grey: passive).
"""

from __future__ import annotations

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


def scatter(ax, points: np.ndarray, groups: np.ndarray, size: float) -> None:
    """Points in 3-D, x along the page, y up, coloured by group (grey: -1)."""
    colors = np.where(groups[:, None] >= 0, COLORS(np.maximum(groups, 0) % 10), (0.75, 0.75, 0.75, 1.0))
    ax.scatter(points[:, 0], points[:, 2], points[:, 1], c=colors, s=size, linewidths=0, depthshade=True)
    lo, hi = points.min(0), points.max(0)
    half = (hi - lo).max() / 2
    middle = (lo + hi) / 2
    ax.set_xlim(middle[0] - half, middle[0] + half)
    ax.set_ylim(middle[2] - half, middle[2] + half)
    ax.set_zlim(middle[1] - half, middle[1] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=20, azim=-60)
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


def ground_space():
    """The default ground environment's design space (builds particles only, no simulation)."""
    from codesign_mpm.config import PRESET_CONFIGS, PRESETS
    from codesign_mpm.env import LocomotionEnv

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
    counts = render_representations()
    print("| representation | parameters (default ground workspace, K = 4) |\n| --- | --- |")
    for name, count in counts:
        print(f"| {name} | {count} |")


if __name__ == "__main__":
    main()
