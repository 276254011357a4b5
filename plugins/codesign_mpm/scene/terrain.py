"""Terrain height maps on the grid's (x, z) nodes, and their outward normals."""
from __future__ import annotations

import math

import numpy as np

from codesign_mpm.scene.spec import Scene, TerrainSpec


def _perlin(nx: int, nz: int, dx: float, frequency: float, rng: np.random.Generator) -> np.ndarray:
    """One octave of 2-D gradient noise sampled at node positions, values in about [-0.7, 0.7]."""
    cells = max(1, int(math.ceil(frequency * max(nx, nz) * dx)))
    angles = rng.uniform(0, 2 * np.pi, size=(cells + 2, cells + 2))
    grads = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    u = np.arange(nx)[:, None] * dx * frequency + np.zeros((1, nz))
    w = np.arange(nz)[None, :] * dx * frequency + np.zeros((nx, 1))
    i0, k0 = np.floor(u).astype(int), np.floor(w).astype(int)
    fu, fw = u - i0, w - k0

    def corner(di: int, dk: int) -> np.ndarray:
        g = grads[i0 + di, k0 + dk]
        return g[..., 0] * (fu - di) + g[..., 1] * (fw - dk)

    def fade(t: np.ndarray) -> np.ndarray:
        return t * t * t * (t * (t * 6 - 15) + 10)

    su, sw = fade(fu), fade(fw)
    bottom = corner(0, 0) * (1 - su) + corner(1, 0) * su
    top = corner(0, 1) * (1 - su) + corner(1, 1) * su
    return bottom * (1 - sw) + top * sw


def height_map(scene: Scene) -> np.ndarray:
    """Terrain height at every (x, z) grid node, shape (nx, nz), in scene units."""
    nx, _, nz = scene.grid_shape
    t: TerrainSpec = scene.terrain
    if t.kind == "none":
        return np.full((nx, nz), -1.0)
    if t.kind == "flat":
        return np.full((nx, nz), t.height)
    if t.kind == "incline":
        x = np.arange(nx) * scene.dx
        return np.repeat((t.height + math.tan(math.radians(t.slope_deg)) * x)[:, None], nz, axis=1)
    rng = np.random.default_rng(t.seed)
    noise = np.zeros((nx, nz))
    weight, freq = 1.0, t.frequency
    for _ in range(t.octaves):
        noise += weight * _perlin(nx, nz, scene.dx, freq, rng)
        weight *= t.roughness
        freq *= 2
    span = noise.max() - noise.min()
    noise = (noise - noise.min()) / span if span > 0 else noise * 0
    return t.height + t.amplitude * noise


def normals(heights: np.ndarray, dx: float) -> np.ndarray:
    """Unit outward normals (nx, nz, 3) of y = h(x, z) by central differences."""
    hx = np.gradient(heights, dx, axis=0)
    hz = np.gradient(heights, dx, axis=1)
    n = np.stack([-hx, np.ones_like(heights), -hz], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)
