"""What the representations share: workspace coordinates, grid interpolation, stiffness, muscles, fibres."""

from __future__ import annotations

import itertools

import numpy as np
import torch

from codesign.errors import RecipeError
from codesign.geometry import grid_partition
from codesign.interfaces import DesignFields, DesignSpace


def near_cubic_grid(k: int) -> tuple[int, int, int]:
    """Factor ``k`` into (gx, gy, gz), as balanced as possible, largest along x: 4 -> (2, 2, 1)."""
    triples = [(a, b, k // (a * b)) for a, b in itertools.product(range(1, k + 1), repeat=2)
               if k % (a * b) == 0]
    triples = [t for t in triples if t[0] >= t[1] >= t[2]]
    return min(triples, key=lambda t: (t[0] / t[2], t[0]))


def check_stiffness_ratios(config) -> None:
    """The stiffness range must be non-empty (a recipe mistake, so a RecipeError)."""
    if not config.min_stiffness_ratio < config.max_stiffness_ratio:
        raise RecipeError(
            f"invalid recipe: representation.min_stiffness_ratio: {config.min_stiffness_ratio!r} must be "
            f"below max_stiffness_ratio ({config.max_stiffness_ratio!r})")


def check_fiber(fiber: list[float] | None) -> None:
    if fiber is not None and (len(fiber) != 3 or not np.linalg.norm(fiber) > 0):
        raise RecipeError(f"invalid recipe: representation.fiber: {fiber!r} is not a non-zero 3-vector "
                          "(or null for the environment's own fibres)")


def stiffness_map(logit: torch.Tensor, default: float, lo: float, hi: float) -> torch.Tensor:
    """E0 (lo + (hi - lo) sigmoid(logit)): bounded, and the default stiffness at logit 0 when lo + hi = 2."""
    return default * (lo + (hi - lo) * torch.sigmoid(logit))


def standardized(space: DesignSpace) -> np.ndarray:
    """(N, 3) particle positions mapped so the workspace's box is [-1, 1]^3 (the paper's x-hat)."""
    lo, hi = space.box()
    return (space.points - (lo + hi) / 2) / np.maximum((hi - lo) / 2, 1e-12)


def coordinate_features(space: DesignSpace) -> np.ndarray:
    """(N, 7) inputs of the coordinate networks: x, y, z, their distances |x|, |y|, |z| to the
    workspace's mid-planes (yz, xz, xy) and the radius from its centre, all standardized."""
    x = standardized(space)
    return np.concatenate([x, np.abs(x), np.linalg.norm(x, axis=1, keepdims=True)], axis=1)


def environment_muscle(space: DesignSpace) -> np.ndarray:
    """(N, K) the environment's own membership, or a near-cubic grid of K blocks when it gives none."""
    n, k = len(space.points), space.n_actuators
    if space.muscle is not None and np.shape(space.muscle) == (n, k):
        return np.asarray(space.muscle, dtype=float)
    return np.eye(k)[grid_partition(space.points, near_cubic_grid(k))]


class Mirror:
    """The design space's mirror image across its sagittal plane (the workspace's mid-plane of z):
    each point's partner and each actuator's (the one whose muscle holds the mirror images of its
    points: itself for a box's grid without a z split, the other side's for an animal's paired
    limbs). Applied to a design's fields it averages every point with its partner, so designs and
    their gradients are bilateral (the `symmetric` option)."""

    def __init__(self, space: DesignSpace) -> None:
        from scipy.spatial import cKDTree

        lo, hi = space.box()
        mirrored = space.points * np.array([1.0, 1.0, -1.0]) + np.array([0.0, 0.0, lo[2] + hi[2]])
        tree = cKDTree(space.points)
        gap, self.partner = tree.query(mirrored)
        spacing = float(np.median(tree.query(space.points, k=2)[0][:, 1])) if len(space.points) > 1 else 1.0
        if gap.max() > 0.5 * spacing:
            raise RecipeError("invalid recipe: representation.symmetric: the design space is not bilateral: the mirror "
                              f"image of a point lies {gap.max():.3g} from the nearest point (spacing {spacing:.3g}); "
                              "use a workspace symmetric across its mid-plane of z")
        muscle = environment_muscle(space)
        self.actuator = (muscle.T @ muscle[self.partner]).argmax(1) if space.n_actuators else np.zeros(0, int)

    def __call__(self, fields: DesignFields) -> DesignFields:
        p = self.partner
        return DesignFields(occupancy=(fields.occupancy + fields.occupancy[p]) / 2,
                            stiffness=(fields.stiffness + fields.stiffness[p]) / 2,
                            muscle=(fields.muscle + fields.muscle[p][:, self.actuator]) / 2,
                            fiber=fields.fiber)


def mirrored(fields: DesignFields, mirror: Mirror | None) -> DesignFields:
    """`fields` made bilateral by `mirror`, or as they are without one."""
    return fields if mirror is None else mirror(fields)


def fixed_fibers(space: DesignSpace, fiber: list[float] | None) -> np.ndarray:
    """(N, 3) unit fibres: `fiber` everywhere, or the environment's own (else the heading +x)."""
    n = len(space.points)
    if fiber is not None:
        f = np.asarray(fiber, dtype=float)
        return np.tile(f / np.linalg.norm(f), (n, 1))
    if space.fiber is not None:
        f = np.asarray(space.fiber, dtype=float)
        return f / np.linalg.norm(f, axis=1, keepdims=True)
    return np.tile([1.0, 0.0, 0.0], (n, 1))


def grid_counts(space: DesignSpace, resolution: int) -> np.ndarray:
    """Cells per axis of a grid over the workspace with `resolution` cells along its longest side."""
    lo, hi = space.box()
    extent = hi - lo
    return np.maximum(1, np.round(extent / extent.max() * resolution)).astype(int)


def grid_weights(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, counts: np.ndarray,
                 mode: str) -> tuple[np.ndarray, np.ndarray]:
    """(index (N, C), weight (N, C)) that read a value at each point from the cells of a grid
    over [lo, hi] (flat index, C-order): the 8 nearest cell centres (trilinear, constant beyond
    the outermost centres) or the cell the point falls in (nearest, C = 1)."""
    u = (points - lo) / np.maximum(hi - lo, 1e-12) * counts  # cell i spans [i, i + 1)
    if mode == "nearest":
        cell = np.clip(np.floor(u).astype(int), 0, counts - 1)
        return np.ravel_multi_index(cell.T, counts)[:, None], np.ones((len(points), 1))
    c = np.clip(u - 0.5, 0, counts - 1)  # in units of cell centres
    base = np.minimum(np.floor(c).astype(int), np.maximum(counts - 2, 0))
    t = c - base
    index, weight = [], []
    for corner in np.ndindex(2, 2, 2):
        offset = np.asarray(corner)
        cell = np.minimum(base + offset, counts - 1)
        index.append(np.ravel_multi_index(cell.T, counts))
        weight.append(np.prod(np.where(offset, t, 1 - t), axis=1))
    return np.stack(index, 1), np.stack(weight, 1)


def linear_layer(rng: np.random.Generator, fan_in: int, fan_out: int, scale: float, dtype: torch.dtype,
                 random_bias: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """(W (fan_in, fan_out) ~ N(0, scale^2 / fan_in), b = 0 or, with `random_bias`, drawn like W), trainable.

    Random biases keep kinked activations (abs) away from their kink where all inputs vanish
    (the workspace's centre), so the design stays differentiable there."""
    w = rng.normal(0.0, scale / np.sqrt(fan_in), (fan_in, fan_out))
    b = rng.normal(0.0, scale / np.sqrt(fan_in), fan_out) if random_bias else np.zeros(fan_out)
    return (torch.tensor(w, dtype=dtype, requires_grad=True), torch.tensor(b, dtype=dtype, requires_grad=True))


@torch.no_grad()
def centre_output_head(weight: torch.Tensor, bias: torch.Tensor, hidden: torch.Tensor, muscle_scale: float,
                       occupancy_logit: float) -> None:
    """Initialise an output layer of (occupancy, stiffness, K muscle logits): muscle weights scaled
    by `muscle_scale` and each muscle's logit centred over the workspace (else one muscle wins
    everywhere at the start), occupancy starting at `occupancy_logit`."""
    weight[:, 2:] *= muscle_scale
    bias[2:] = -(hidden @ weight[:, 2:]).mean(0)
    bias[0] = occupancy_logit


def fields_from_logits(out: torch.Tensor, default_stiffness: float, config, fiber: torch.Tensor) -> DesignFields:
    """Design fields from an (N, 2 + K) output of logits: occupancy, stiffness, muscles."""
    return DesignFields(
        occupancy=torch.sigmoid(out[:, 0]),
        stiffness=stiffness_map(out[:, 1], default_stiffness, config.min_stiffness_ratio, config.max_stiffness_ratio),
        muscle=torch.softmax(out[:, 2:], dim=1),
        fiber=fiber,
    )
