"""Geometry helpers shared by plugins (numpy only, no physics)."""
from __future__ import annotations

import numpy as np


def grid_partition(points: np.ndarray, groups) -> np.ndarray:
    """Index (N,) of the block each point falls in when its bounding box is cut into a
    `groups` = (gx, gy, gz) grid of blocks, numbered x-major: how muscles are laid out by default."""
    lo, hi = points.min(0), points.max(0)
    g = np.asarray(groups)
    cell = np.minimum(((points - lo) / np.maximum(hi - lo, 1e-12) * g).astype(int), g - 1)
    return (cell[:, 0] * g[1] + cell[:, 1]) * g[2] + cell[:, 2]
