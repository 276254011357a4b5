"""The environment's own body as it is: the fixed designs of the paper's Table 1 (its animals)."""

from __future__ import annotations

import numpy as np

from codesign.interfaces import DesignFields, DesignSpace, Representation
from codesign_designs.common import environment_muscle, fixed_fibers
from codesign_designs.config import FixedConfig


class FixedRepresentation(Representation):
    """Every particle kept, with the environment's stiffness, muscles and fibres; nothing to optimise.

    Unlike the particle representation started from the environment's muscles, whose softmax puts a
    labelled body's passive material in every muscle alike, passive material stays passive here (the
    released SoftZoo's annotated animals: actuation only in the labelled groups)."""

    def __init__(self, config: FixedConfig) -> None:
        self.config = config
        self._fields: DesignFields | None = None

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        n = len(space.points)
        stiffness = (np.full(n, float(space.default_stiffness)) if space.stiffness is None
                     else np.asarray(space.stiffness, dtype=float).copy())
        self._fields = DesignFields(occupancy=np.ones(n), stiffness=stiffness, muscle=environment_muscle(space).copy(),
                                    fiber=fixed_fibers(space, None))

    def __call__(self) -> DesignFields:
        if self._fields is None:
            raise RuntimeError("FixedRepresentation.setup() must be called before use")
        return self._fields
