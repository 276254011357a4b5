"""A design with one trainable number: a wedge whose top falls from the back of the workspace to the
front, `slope` setting how far. Smooth in its parameter, so differentiable physics can train it."""

from dataclasses import dataclass, field

import numpy as np

from codesign.interfaces import DesignFields, DesignSpace, Representation


@dataclass
class WedgeConfig:
    slope: float = field(default=0.5, metadata={"ge": 0, "le": 1, "help": "how much of the height the top loses from back to front"})
    edge: float = field(default=0.05, metadata={"gt": 0, "help": "width of the occupancy's edge, in shares of the height"})


class Wedge(Representation):
    """occupancy = sigmoid((top(x) - y) / edge) over the workspace scaled to [0, 1]^3, with
    top(x) = 1 - slope x; the environment's own muscles and fibres; the default stiffness."""

    def __init__(self, config: WedgeConfig) -> None:
        self.config = config

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        import torch  # heavy: imported when a recipe builds the component, not when plugins load

        lo, hi = space.box()
        unit = (space.points - lo) / np.maximum(hi - lo, 1e-12)
        dtype = torch.get_default_dtype()
        self.x, self.y = (torch.tensor(unit[:, i], dtype=dtype) for i in (0, 1))
        self.slope = torch.tensor(self.config.slope, dtype=dtype, requires_grad=True)
        n, k = len(space.points), space.n_actuators
        muscle = space.muscle if space.muscle is not None else np.eye(k)[np.minimum((unit[:, 0] * k).astype(int), k - 1)]
        fiber = space.fiber if space.fiber is not None else np.tile([1.0, 0.0, 0.0], (n, 1))
        self.muscle, self.fiber = torch.tensor(muscle, dtype=dtype), torch.tensor(fiber, dtype=dtype)
        self.stiffness = torch.full((n,), space.default_stiffness, dtype=dtype)

    def parameters(self) -> list:
        return [self.slope]  # what a gradient-based optimizer trains (optimize: design)

    def __call__(self) -> DesignFields:
        import torch

        top = 1.0 - self.slope.clamp(0.0, 1.0) * self.x
        return DesignFields(occupancy=torch.sigmoid((top - self.y) / self.config.edge), stiffness=self.stiffness,
                            muscle=self.muscle, fiber=self.fiber)
