"""Body integrity: numerical fracture and features below the grid's resolution.

MPM has no notion of a body's connectivity: particles interact only through the grid nodes
their quadratic B-spline stencils share. Two particles share a node exactly when their base
cells (floor(x / dx - 1/2)) are at most 2 apart along every axis; a piece of the body whose
particles share no node with the rest no longer feels it. That piece has torn off, and a
robot that throws one forward gains reward from an artifact, not a gait: `torn_fraction` is
the robot mass outside its largest such piece.

A feature thinner than about two cells is carried by one or two rows of nodes and tears at
small strains; `thinnest_cells` measures a design's thinnest part at rest, on the particle
lattice it was sampled on, as the largest cube (in grid cells) that fits around every part.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

STENCIL_REACH = 2
"""Base cells at most this far apart (per axis) share a node of their 3x3x3 stencils."""
MIN_THICKNESS_CELLS = 2.0
"""Designs thinner than this (in grid cells) tear under actuation; the representations keep above it."""


def pieces(x: np.ndarray, dx: float) -> np.ndarray:
    """(N,) label of each particle's piece: particles are joined when their stencils share a node."""
    if len(x) == 0:
        return np.zeros(0, dtype=np.int64)
    base = np.floor(np.asarray(x, dtype=np.float64) / dx - 0.5).astype(np.int64)
    cells, of_particle = np.unique(base, axis=0, return_inverse=True)
    pairs = cKDTree(cells).query_pairs(STENCIL_REACH, p=np.inf, output_type="ndarray")
    n = len(cells)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, cell_label = connected_components(graph, directed=False)
    return cell_label[of_particle.reshape(-1)]


def torn_fraction(x: np.ndarray, mass: np.ndarray, dx: float) -> float:
    """Fraction of the mass outside the largest connected piece (0: whole)."""
    mass = np.asarray(mass, dtype=np.float64)
    total = mass.sum()
    if len(x) == 0 or total <= 0:
        return 0.0
    per_piece = np.bincount(pieces(x, dx), weights=mass)
    return float(1.0 - per_piece.max() / total)


def lattice_occupancy(points: np.ndarray, spacing: float) -> np.ndarray:
    """Boolean voxel grid with one voxel per lattice point (padded by one empty voxel)."""
    index = np.rint((points - points.min(0)) / spacing).astype(np.int64) + 1
    grid = np.zeros(index.max(0) + 2, dtype=bool)
    grid[tuple(index.T)] = True
    return grid


def thinnest_cells(points: np.ndarray, spacing: float, dx: float, max_cells: float = 4.0) -> float:
    """Thinnest part of a body at rest, in grid cells: the largest k such that every occupied
    lattice voxel lies in a k x k x k cube of occupied voxels (a morphological opening),
    converted from lattice spacings to cells; at most `max_cells` is looked for.

    `points` lie on a lattice of `spacing` (the sampling lattice: dx / ppc^(1/3))."""
    if len(points) == 0:
        return 0.0
    grid = lattice_occupancy(np.asarray(points, dtype=np.float64), spacing)
    largest = max(1, int(round(max_cells * dx / spacing)))
    fits = 1
    for k in range(2, largest + 1):
        opened = ndimage.binary_opening(grid, structure=np.ones((k, k, k), dtype=bool))
        if (opened != grid).any():
            break
        fits = k
    return fits * spacing / dx
