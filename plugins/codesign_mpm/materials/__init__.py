"""Constitutive models known to the engine: one module per model in this package, and the table
of them that scenes, the engine and the docs read.

Each module defines `MODEL`, a `base.MaterialModel`: its parameters (defaults, valid ranges), its
wave speed for the time step, and its Taichi functions (stress, return mapping or update), which
the engine compiles only into the kernels of scenes that use the model. Registering a model gives
it a small integer id, the kernels' dispatch key: the built-in ones below keep theirs (0-7),
models from plugins (`codesign_register_materials`, docs/plugins.md) follow in name order.

==============  ======  ==========================================================================
neo_hookean     0       compressible neo-Hookean elastomer (robots' default)
corotated       1       fixed-corotated elasticity (forward only)
stvk            2       St. Venant-Kirchhoff
sand            3       Drucker-Prager in Hencky strain (Klar et al. 2016): [alpha, cohesion]
snow            4       Stomakhin et al. 2013: [theta_c, theta_s, hardening xi, max stiffening]
clay            5       von Mises in Hencky strain: [yield stress]
water           6       weakly compressible fluid: [bulk modulus, viscosity]
mud             7       Bingham-like saturated soil (von Mises + viscosity): [yield stress, viscosity]
==============  ======  ==========================================================================

The bracketed lists are the per-particle parameter vectors (`N_PARAMS` numbers, `pack_params`).
Lame parameters follow the usual isotropic relations (`lame`). `muscle` holds the muscles' stress.
"""
from __future__ import annotations

import importlib
from dataclasses import replace
from typing import Any

from codesign_mpm.materials.base import KINDS, MaterialModel, Parameter, cofactor, func, lame, ti  # noqa: F401
from codesign_mpm.materials.base import elastic_wave_speed as wave_speed
from codesign_mpm.materials.muscle import (MAX_ACTIVE_STRESS_RATIO, MUSCLE_MODELS, active_stress_ratio,  # noqa: F401
                                           max_stiffness_ratio, muscle_modulus)
from codesign_mpm.materials.sand import drucker_prager_alpha  # noqa: F401
from codesign_mpm.materials.snow import MIN_HARDENING  # noqa: F401

N_PARAMS = 4
"""Per-particle parameters of the non-elastic models (see the module docstring)."""
BUILTIN = ("neo_hookean", "corotated", "stvk", "sand", "snow", "clay", "water", "mud")
"""The engine's own models, in the order of their ids."""

MATERIALS: dict[str, MaterialModel] = {}
"""Every registered model by name (plugins' included once `load_plugin_materials` ran)."""
ID: dict[str, int] = {}
MODEL_NAMES: dict[int, str] = {}


def register(model: MaterialModel) -> MaterialModel:
    """Add a model to the table with the next free id; returns it with that id."""
    if not isinstance(model, MaterialModel):
        raise TypeError(f"a material model must be a codesign_mpm.materials.MaterialModel, got {type(model).__name__}")
    if model.name in MATERIALS:
        raise ValueError(f"material '{model.name}' is registered twice")
    if len(model.packed({p.name: p.default for p in model.parameters})) > N_PARAMS:
        raise ValueError(f"material '{model.name}' packs more than N_PARAMS = {N_PARAMS} numbers per particle")
    registered = replace(model, id=len(MATERIALS))
    MATERIALS[model.name] = registered
    ID[model.name] = registered.id
    MODEL_NAMES[registered.id] = model.name
    return registered


for _name in BUILTIN:
    register(importlib.import_module(f"codesign_mpm.materials.{_name}").MODEL)

_loaded_from: Any = None


def load_plugin_materials() -> None:
    """Add the models that plugins register (`codesign_register_materials`), in name order; the
    registry is asked again only when it was rebuilt. Called when a scene names a model the table
    lacks (`validate_scene`, `build_particles`): scenes of the engine's own models never load plugins."""
    global _loaded_from
    from codesign.plugins import get_registry

    registry = get_registry()
    if registry is _loaded_from:
        return
    _loaded_from = registry
    for entry in registry.entries("material"):
        if entry.name in MATERIALS:
            continue
        model = entry.load_factory()
        if getattr(model, "name", None) != entry.name:
            raise ValueError(f"material '{entry.name}' of plugin '{entry.plugin}': its MODEL is named "
                             f"{getattr(model, 'name', None)!r}")
        register(model)


def material(model_id: int) -> MaterialModel:
    """The registered model with this id."""
    return MATERIALS[MODEL_NAMES[model_id]]


def material_names() -> list[str]:
    return sorted(MATERIALS)


def parameters() -> dict[str, Parameter]:
    """Every registered model's parameters by name (first definition wins), in registration order."""
    table: dict[str, Parameter] = {}
    for model in MATERIALS.values():
        for p in model.parameters:
            table.setdefault(p.name, p)
    return table


def pack_params(kind: str, **values: float) -> tuple[float, ...]:
    """The `N_PARAMS` per-particle numbers model `kind` reads (zeros for elastic models), from its
    parameters' values (defaults where not given)."""
    model = MATERIALS[kind]
    packed = model.packed({p.name: values.get(p.name, p.default) for p in model.parameters})
    return tuple(packed) + (0.0,) * (N_PARAMS - len(packed))


def spec_params(spec: Any) -> tuple[float, ...]:
    """`pack_params` for a scene's `MaterialSpec`: built-in parameters are its fields, a plugin
    model's are keys of its `parameters` mapping."""
    model = MATERIALS[spec.kind]
    extra = dict(getattr(spec, "parameters", None) or {})
    return pack_params(spec.kind, **{p.name: getattr(spec, p.name) if hasattr(spec, p.name) else
                                     extra.get(p.name, p.default) for p in model.parameters})


def model_wave_speed(model: int, youngs_modulus: float, poisson_ratio: float, density: float,
                     added_modulus: float, params: tuple[float, ...]) -> float:
    """Fastest wave speed a particle of this model can carry, for the CFL condition (the model's
    `wave_speed`: water's from its bulk modulus, snow's at its largest hardening)."""
    return material(model).wave_speed(youngs_modulus, poisson_ratio, density, added_modulus, params)


def viscosity(model: int, params: tuple[float, ...]) -> float:
    """Dynamic viscosity of a particle (0 for the models without a viscous term)."""
    return material(model).viscosity(params)
