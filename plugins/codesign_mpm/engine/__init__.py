"""Differentiable 3-D MLS-MPM (APIC, quadratic B-splines) in Taichi: the engine.

Where things live (docs/engine.md has the longer tour):

    simulator.py     `Simulator` (the public API), the substep and its reverse in a few lines each,
                     rollouts with checkpoints and `backward`
    time_step.py     the CFL step at rest (`time_step`), wave speeds, the state-following step's bounds
    checkpoints.py   a rollout's checkpoints, in memory and past a bound in a file
    batch.py         `BatchSimulator`: several scenes side by side in one simulator
    storage.py       `Layout`, `_Storage` (every Taichi field, the slots and their load/save kernels,
                     the guard `_check`) and the pool of compiled storages
    transfer.py      p2g and g2p, each beside its hand-written adjoint; the FLIP share
    grid.py          the grid update: gravity, terrain (height-map SDF, Coulomb friction), walls
    eigen.py         the plastic models' eigenframe algebra (Jacobi, Daleckii-Krein) and its adjoint
    constitutive.py  the per-model stress and deformation update (dispatching to the materials'
                     Taichi functions), muscles, the hand-written stress adjoints
    ../materials/    one module per material model: parameters, defaults, validation, Taichi
                     stress or return mapping, wave speed (plugins add their own)

Importing this package imports Taichi; `codesign_mpm` itself loads it on first use of `Simulator`.
"""
from codesign_mpm.engine.constitutive import J_MIN, MODEL_NAMES
from codesign_mpm.engine.eigen import JACOBI_EPS, JACOBI_SWEEPS, JACOBI_TOL_ULPS
from codesign_mpm.engine.grid import MASS_EPS
from codesign_mpm.engine.simulator import (CHECKPOINT_MEMORY_BYTES, GRID_STORE_BYTES, GRID_STORE_MARGIN, Gradients,
                                           Rollout, SimulationError, Simulator, State)
from codesign_mpm.engine.storage import (CAPACITY_STEP, FREE_STORAGE_BYTES, MAX_DEAD_STORAGES, MAX_FREE_STORAGES,
                                         Layout)
from codesign_mpm.engine.time_step import ADAPTIVE_CFL_FACTOR, MAX_ADAPTIVE_CFL, TimeStep, time_step, wave_speeds
from codesign_mpm.engine.transfer import flip_models

__all__ = ["ADAPTIVE_CFL_FACTOR", "CAPACITY_STEP", "CHECKPOINT_MEMORY_BYTES", "FREE_STORAGE_BYTES",
           "GRID_STORE_BYTES", "GRID_STORE_MARGIN", "Gradients", "JACOBI_EPS", "JACOBI_SWEEPS", "JACOBI_TOL_ULPS",
           "J_MIN", "Layout", "MASS_EPS", "MAX_ADAPTIVE_CFL", "MAX_DEAD_STORAGES", "MAX_FREE_STORAGES", "MODEL_NAMES",
           "Rollout", "SimulationError", "Simulator", "State", "TimeStep", "flip_models", "time_step",
           "wave_speeds"]
