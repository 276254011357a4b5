"""Body integrity: numerical fracture and features below the grid's resolution.

MPM has no notion of a body's connectivity: particles interact only through the grid nodes
their quadratic B-spline stencils share. Two particles share a node exactly when their base
cells (floor(x / dx - 1/2)) are at most 2 apart along every axis; a piece of the body whose
particles share no node with the rest no longer feels it. That piece has torn off, and a
robot that throws one forward gains reward from an artifact, not a gait: `torn_fraction` is
the robot mass outside its largest such piece.

A feature thinner than about two cells is carried by one or two rows of nodes and tears at
small strains; `thinnest_cells` measures a design's thinnest part at rest, on the particle
lattice it was sampled on, as the largest cube (in grid cells) that fits around every part (up to
the steps of a curved surface).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

STENCIL_REACH = 2
"""Base cells at most this far apart (per axis) share a node of their 3x3x3 stencils (`pieces`)."""
MIN_THICKNESS_CELLS = 2.0
"""Designs thinner than this (in grid cells) tear under actuation; the representations keep above it."""
SURFACE_STEP_CELLS = 0.5
"""How far (in cells) a lattice point may lie from the cubes that measure thickness: the steps a
lattice makes of a curved surface, which no cube covers (without it every curved body read 0.5 cells)."""


def pieces(x: np.ndarray, dx: float) -> np.ndarray:
    """(N,) label of each particle's piece: particles are joined when their stencils share a node.

    Base cells at most `STENCIL_REACH` = 2 apart per axis are exactly those whose 2 x 2 x 2 boxes
    [c, c + 1] touch or overlap, so the pieces are the 26-connected components of the union of
    those boxes on a voxel grid (`ndimage.label`, milliseconds for a paper-scale robot)."""
    if len(x) == 0:
        return np.zeros(0, dtype=np.int64)
    base = np.floor(np.asarray(x, dtype=np.float64) / dx - 0.5).astype(np.int64)
    index = base - base.min(0)
    occupied = np.zeros(index.max(0) + STENCIL_REACH, dtype=bool)
    occupied[tuple(index.T)] = True
    boxes = occupied.copy()
    for shift in np.ndindex(*(STENCIL_REACH,) * 3):  # boxes[c + e] |= occupied[c], e in {0, 1}^3
        if any(shift):
            boxes[shift[0]:, shift[1]:, shift[2]:] |= occupied[:occupied.shape[0] - shift[0],
                                                                :occupied.shape[1] - shift[1],
                                                                :occupied.shape[2] - shift[2]]
    label, _ = ndimage.label(boxes, structure=np.ones((3, 3, 3), dtype=bool))
    return label[tuple(index.T)]


def torn_fraction(x: np.ndarray, mass: np.ndarray, dx: float) -> float:
    """Fraction of the mass outside the largest connected piece (0: whole)."""
    mass = np.asarray(mass, dtype=np.float64)
    total = mass.sum()
    if len(x) == 0 or total <= 0:
        return 0.0
    per_piece = np.bincount(pieces(x, dx), weights=mass)
    return float((per_piece.sum() - per_piece.max()) / per_piece.sum())  # exactly 0 for one piece


def lattice_index(points: np.ndarray, spacing: float) -> np.ndarray:
    """(N, 3) voxel of each lattice point, one empty voxel of padding below."""
    return np.rint((points - points.min(0)) / spacing).astype(np.int64) + 1


def lattice_occupancy(points: np.ndarray, spacing: float) -> np.ndarray:
    """Boolean voxel grid with one voxel per lattice point (padded by one empty voxel)."""
    index = lattice_index(points, spacing)
    grid = np.zeros(index.max(0) + 2, dtype=bool)
    grid[tuple(index.T)] = True
    return grid


def thick_enough(points: np.ndarray, occupied: np.ndarray, spacing: float, dx: float,
                 min_cells: float = MIN_THICKNESS_CELLS) -> np.ndarray:
    """Of the `occupied` points of a sampling lattice of `spacing`, those in parts at least
    `min_cells` grid cells thick (`thinnest_cells`' measure: within `SURFACE_STEP_CELLS` of a cube
    that fits in the occupied set). (N,) bool."""
    occupied = np.asarray(occupied, dtype=bool)
    if not occupied.any():
        return occupied
    index = lattice_index(points, spacing)
    grid = np.zeros(index.max(0) + 2, dtype=bool)
    grid[tuple(index[occupied].T)] = True
    core = _cube_core(grid, max(1, math.ceil(min_cells * dx / spacing - 1e-9)), spacing, dx)
    return occupied & core[tuple(index.T)]


def resolved_body(points: np.ndarray, occupied: np.ndarray, spacing: float, dx: float,
                  min_cells: float = MIN_THICKNESS_CELLS) -> np.ndarray:
    """The part of a design the grid can carry: its points in parts at least `min_cells` grid cells
    thick (`thick_enough`), then only the largest piece their stencils join (`pieces`). (N,) bool;
    all False where nothing is thick enough."""
    kept = thick_enough(points, occupied, spacing, dx, min_cells)
    if kept.any():
        label = pieces(points[kept], dx)
        kept[np.flatnonzero(kept)] = label == np.bincount(label).argmax()
    return kept


def _cube_core(grid: np.ndarray, k: int, spacing: float, dx: float) -> np.ndarray:
    """The voxels of `grid` within `SURFACE_STEP_CELLS` of a k x k x k cube of occupied voxels: the
    parts at least k voxels thick, with the staircase a lattice makes of a curved surface."""
    opened = ndimage.binary_opening(grid, structure=np.ones((k, k, k), dtype=bool))
    step = max(1, math.ceil(SURFACE_STEP_CELLS * dx / spacing - 1e-9))
    return grid & ndimage.binary_dilation(opened, structure=np.ones((2 * step + 1,) * 3, dtype=bool))


def thinnest_cells(points: np.ndarray, spacing: float, dx: float, max_cells: float = 4.0) -> float:
    """Thinnest part of a body at rest, in grid cells: the largest k such that every point of its
    sampling lattice (of `spacing`, dx / ppc^(1/3)) lies within `SURFACE_STEP_CELLS` of a cube of
    k x k x k occupied lattice points (a morphological opening; the tolerance lets a curved surface's
    staircase pass, which no cube covers); at most `max_cells` is looked for."""
    if len(points) == 0:
        return 0.0
    grid = lattice_occupancy(np.asarray(points, dtype=np.float64), spacing)
    fits = 1
    for k in range(2, max(1, round(max_cells * dx / spacing)) + 1):
        if (_cube_core(grid, k, spacing, dx) != grid).any():
            break
        fits = k
    return fits * spacing / dx


@dataclass
class IntegrityWatch:
    """Follows one robot through an episode: `see` the positions after every frame (robot first)."""

    mass: np.ndarray  # (n_robot,) the robot particles' masses
    dx: float
    tolerance: float  # a torn fraction above this counts as torn
    thinnest: float  # the design's thinnest part at rest, in grid cells (`thinnest_cells`)
    torn: float = 0.0  # the largest torn fraction seen so far
    torn_at: int | None = None  # the first frame (1-based) whose torn fraction exceeded the tolerance
    frames: int = 0

    def see(self, x: np.ndarray) -> None:
        f = torn_fraction(x[:len(self.mass)], self.mass, self.dx)
        self.frames += 1
        self.torn = max(self.torn, f)
        if self.torn_at is None and f > self.tolerance:
            self.torn_at = self.frames

    def metrics(self) -> dict[str, float]:
        """What an episode reports: torn_fraction, thinnest_cells and torn_at_frame (0: never torn)."""
        return {"torn_fraction": self.torn, "thinnest_cells": self.thinnest, "torn_at_frame": float(self.torn_at or 0)}
