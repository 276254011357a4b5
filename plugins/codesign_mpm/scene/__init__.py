"""Scenes: what is simulated, before anything is.

    spec.py      the scene description (`Scene`, bodies, shapes, materials, muscles, terrain) and its
                 validation, every error naming its key
    sampling.py  particles from a scene (`build_particles`): shapes, body files, layers cut around bodies
    terrain.py   the terrain's height map and normals (flat, incline, Perlin)
    integrity.py whether a body holds together: its pieces, the mass torn off, its thinnest part
    quality.py   the quality presets (dx, particles per cell, CFL number, precision)

The description's names are importable from here (`from codesign_mpm.scene import Scene`).
"""
from codesign_mpm.scene.spec import (ARCHS, DTYPES, GRID_REGIONS, MUSCLE_LAYOUTS, SHAPE_KINDS, TERRAIN_CONTACTS,
                                     TERRAIN_KINDS, BodySpec, MaterialSpec, MuscleSpec, Scene, SceneError,
                                     ShapeSpec, TerrainSpec, validate_scene)

__all__ = ["ARCHS", "DTYPES", "GRID_REGIONS", "MUSCLE_LAYOUTS", "SHAPE_KINDS", "TERRAIN_CONTACTS", "TERRAIN_KINDS",
           "BodySpec", "MaterialSpec", "MuscleSpec", "Scene", "SceneError", "ShapeSpec", "TerrainSpec",
           "validate_scene"]
