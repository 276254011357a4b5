"""What every optimizer here shares: parameter groups by mode and candidates as frozen copies
(keeping the best is `codesign.artifacts.BestKeeper`, which `evaluate` shares too)."""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch.nn.utils import vector_to_parameters

from codesign.artifacts import to_numpy
from codesign.errors import RecipeError
from codesign.interfaces import Controller, DesignFields, Representation


def parameter_groups(mode: str, representation: Representation, controller: Controller,
                     supported: tuple[str, ...] = ("control", "design", "both")) -> dict[str, list[torch.Tensor]]:
    """{"control": [...], "design": [...]} for `optimizer.optimize` = mode, each group non-empty."""
    if mode not in supported:
        raise RecipeError(f"invalid recipe: optimizer.optimize: {mode!r} is not supported by this optimizer; "
                          f"allowed: {', '.join(supported)}")
    groups = {}
    for name, part, kind in (("control", controller, "controller"), ("design", representation, "representation")):
        if mode in (name, "both"):
            params = list(part.parameters())
            if not params:
                raise RecipeError(f"invalid recipe: optimizer.optimize: {mode!r} trains the {kind}, but "
                                  f"{kind} '{type(part).__name__}' has no trainable parameters")
            groups[name] = params
    return groups


def frozen_design(representation: Representation) -> DesignFields:
    """The representation's current design as numpy arrays that stay as they are when its
    parameters (or genome) change for the next candidate."""
    with torch.no_grad():
        design = representation()
    return DesignFields(**{name: to_numpy(getattr(design, name)).copy() for name in DesignFields.__dataclass_fields__})


def candidate(representation: Representation, controller: Controller, params: list[torch.Tensor],
              x: np.ndarray | None) -> tuple[DesignFields, Controller]:
    """The design and a copy of the controller with the flat parameter vector `x` (None: nothing)
    loaded into `params`; both stay as they are when the parameters change for the next candidate."""
    if x is not None:
        with torch.no_grad():
            vector_to_parameters(torch.as_tensor(x, dtype=params[0].dtype), params)
    return frozen_design(representation), copy.deepcopy(controller)


def fewest_to_tell(es) -> int:
    """The fewest evaluated candidates pycma's `tell` accepts: its mu (the parents of the next
    mean), and never under what its population-size check allows (3 with the mirrored samples)."""
    return max(es.sp.weights.mu, 3 - es.sp.lam_mirr)
