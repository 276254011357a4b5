"""Semi-automatic muscle annotation (SoftZoo section 5.1): sample the solid, cluster it, fibre = PCA axis.

`codesign annotate BODY --groups K` samples a body (file or library name) on a lattice, splits
the samples into K groups by k-means, takes each group's principal axis as its fibre, applies
the user's merges and passive groups, and writes an annotated ``.npz`` that a recipe can use
(``robot.body: file``) plus, optionally, a picture coloured by group. k-means groups are
numbered by their centre along x, from the tail (-x) to the head (+x), so a first run's
picture tells which numbers to merge or make passive in a second run. ``--symmetric`` clusters
the body folded across its sagittal plane (the mid-plane of z, heading +x and up +y) and splits
every muscle into a left (z below the plane) and a right one, mirror images with mirrored
fibres: paired limbs get a muscle each.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codesign.bodies import Body
from codesign.errors import CodesignError
from codesign_designs.rotations import facing_heading


class AnnotationError(CodesignError):
    """Options the annotator cannot honour; the message names the option and what is allowed."""


@dataclass
class Annotation:
    """A sampled body with muscle labels, in the body's canonical frame."""

    points: np.ndarray
    """(N, 3) lattice samples filling the solid."""
    groups: np.ndarray
    """(N,) final muscle group, -1 passive, numbered 0..K'-1."""
    fibers: np.ndarray
    """(N, 3) unit fibre: the principal axis of the point's group."""
    clusters: np.ndarray
    """(N,) the k-means group each point fell in, before merges and passive groups."""
    spacing: float
    group_names: list[str]

    @property
    def axes(self) -> np.ndarray:
        """(K', 3) the fibre of each final group."""
        return np.stack([self.fibers[self.groups == g][0] for g in range(len(self.group_names))])


def _plan(k: int, merge: list[list[int]], passive: list[int]) -> list[list[int]]:
    """The k-means groups that make up each final muscle, in order; checks the options."""
    seen: dict[int, str] = {}
    for option, members in [("--merge " + ",".join(map(str, m)), m) for m in merge] + \
                           [(f"--passive {p}", [p]) for p in passive]:
        if option.startswith("--merge") and len(set(members)) < 2:
            raise AnnotationError(f"{option}: a merge needs at least two different groups")
        for g in members:
            if not 0 <= g < k:
                raise AnnotationError(f"{option}: group {g} does not exist; groups are 0..{k - 1}")
            if g in seen and seen[g] != option:
                raise AnnotationError(f"{option}: group {g} is already used by {seen[g]}")
            seen[g] = option
    muscles = [sorted(set(m)) for m in merge]
    merged = {g for m in muscles for g in m}
    muscles += [[g] for g in range(k) if g not in merged and g not in passive]
    if not muscles:
        raise AnnotationError(f"--passive {','.join(map(str, passive))}: every group is passive; "
                              "a robot needs a muscle")
    return sorted(muscles)


def principal_axis(points: np.ndarray) -> np.ndarray:
    """The unit direction of largest variance (PCA), with the sign that faces +x."""
    from sklearn.decomposition import PCA

    if len(points) < 2:
        return np.array([1.0, 0.0, 0.0])
    return facing_heading(PCA(n_components=1).fit(points).components_[0])


def annotate(body: Body, groups: int, merge: list[list[int]] = (), passive: list[int] = (),
             resolution: int = 48, seed: int = 0, symmetric: bool = False) -> Annotation:
    """Sample `body` with `resolution` lattice points along its longest side, cluster the samples
    into `groups` by k-means, merge and passivate groups, and give each muscle its PCA axis;
    `symmetric`: cluster the body folded across its sagittal plane and split each muscle into
    a left and a right one."""
    from sklearn.cluster import KMeans

    if groups < 1:
        raise AnnotationError(f"--groups {groups}: must be at least 1")
    lo, hi = body.bounds
    spacing = float((hi - lo).max()) / resolution
    points = body.sample(spacing)
    if len(points) < max(groups, 2):
        raise AnnotationError(f"--groups {groups}: the body holds only {len(points)} samples at --resolution "
                              f"{resolution}; raise the resolution or ask for fewer groups")
    plan = _plan(groups, [list(m) for m in merge], list(passive))
    mid = (lo[2] + hi[2]) / 2
    right = points[:, 2] >= mid
    folded = points.copy()  # the left half mirrored onto the right: clusters come in mirror pairs
    folded[:, 2] = mid + np.abs(points[:, 2] - mid)
    kmeans = KMeans(n_clusters=groups, n_init=10, random_state=seed).fit(folded if symmetric else points)
    order = np.lexsort(kmeans.cluster_centers_.T[::-1])  # by centre x, then y, then z
    clusters = np.argsort(order)[kmeans.labels_]
    labels = np.full(len(points), -1)
    fibers = np.tile([1.0, 0.0, 0.0], (len(points), 1))
    names = []
    for members in plan:
        mine = np.isin(clusters, members)
        name = f"k-means group{'s' if len(members) > 1 else ''} {'+'.join(map(str, members))}"
        if not symmetric:
            labels[mine] = len(names)
            fibers[mine] = principal_axis(points[mine])
            names.append(name)
            continue
        axis = principal_axis(folded[mine])  # the right side's; the left's is its mirror image
        for side, on_side, fiber in (("left", ~right, axis * [1.0, 1.0, -1.0]), ("right", right, axis)):
            labels[mine & on_side] = len(names)
            fibers[mine & on_side] = facing_heading(fiber)
            names.append(f"{name} {side}")
    return Annotation(points, labels, fibers, clusters, spacing, names)


def save_annotation(annotation: Annotation, path: Path) -> None:
    """Write the annotated body file (`codesign.bodies.load_body` reads it)."""
    np.savez_compressed(path, points=annotation.points, groups=annotation.groups, fibers=annotation.fibers,
                        spacing=annotation.spacing, group_names=np.array(annotation.group_names))


def render_annotation(annotation: Annotation, path: Path, title: str = "") -> None:
    """A side (x-y) and top (x-z) view of the samples coloured by muscle, passive in grey, with each
    muscle's fibre drawn through its centre (headless: matplotlib's Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = plt.get_cmap("tab10" if len(annotation.group_names) <= 10 else "tab20")
    fig, axes = plt.subplots(1, 2, figsize=(6.4, 2.6), dpi=100)
    for ax, (a, b), label in zip(axes, ((0, 1), (0, 2)), ("side (x, y)", "top (x, z)")):
        p, g = annotation.points, annotation.groups
        ax.scatter(p[g < 0, a], p[g < 0, b], s=2, c="0.8", linewidths=0)
        for muscle in range(len(annotation.group_names)):
            mine = g == muscle
            ax.scatter(p[mine, a], p[mine, b], s=2, color=colors(muscle % colors.N), linewidths=0,
                       label=str(muscle))
            centre, axis = p[mine].mean(0), annotation.fibers[mine][0] * 0.12
            ax.plot([centre[a] - axis[a], centre[a] + axis[a]], [centre[b] - axis[b], centre[b] + axis[b]],
                    color="k", lw=1)
        ax.set_aspect("equal")
        ax.set_title(label, fontsize=8)
        ax.tick_params(labelsize=6)
    axes[1].legend(fontsize=6, markerscale=3, loc="center left", bbox_to_anchor=(1.0, 0.5), frameon=False)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
