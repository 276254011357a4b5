"""The paper's observations: proprioception (centroids), environment (semantic occupancy) and
task information, each part switched on or off in the recipe (`environment.observation`).

Parts, in this order when on, with their sizes (K muscles, C = prod(occupancy_cells)):

==================  ======  =============================================================
com                 3       robot centre of mass
velocity            3       its velocity
muscle_centroids    6 K     each muscle's membership-weighted centroid: position, velocity
occupancy           3 C     cells around the robot holding terrain / cover / robot (0 or 1)
task                3       the task's information (direction, up axis, next waypoint, ...)
time                1       control step / horizon
==================  ======  =============================================================

Everything but the occupancy map is a torch expression of the robot's particles, so a
closed-loop controller's gradient flows through its observations; the occupancy map is a
piecewise-constant function of positions (no gradient).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from codesign_mpm.environment.config import ObservationConfig
from codesign_mpm.environment.tasks import Task


@dataclass
class Observer:
    config: ObservationConfig
    task: Task
    n_actuators: int
    horizon: int
    dx: float
    heights: np.ndarray  # terrain height per (x, z) grid node

    def parts(self) -> list[tuple[str, int]]:
        """(name, size) of each observed part, in order."""
        c = self.config
        sizes = {"com": 3, "velocity": 3, "muscle_centroids": 6 * self.n_actuators,
                 "occupancy": 3 * int(np.prod(c.occupancy_cells)), "task": self.task.info_dim, "time": 1}
        return [(name, size) for name, size in sizes.items() if getattr(c, name)]

    @property
    def dim(self) -> int:
        return sum(size for _, size in self.parts())

    def space(self):
        """The observation as a `gymnasium.spaces.Box` (float32, unbounded but the occupancy map)."""
        from gymnasium import spaces

        low = np.concatenate([np.zeros(size) if name == "occupancy" else np.full(size, -np.inf)
                              for name, size in self.parts()])
        high = np.concatenate([np.ones(size) if name == "occupancy" else np.full(size, np.inf)
                               for name, size in self.parts()])
        return spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)

    def __call__(self, step: int, x: torch.Tensor, v: torch.Tensor, mass: torch.Tensor, muscle: torch.Tensor,
                 cover_x: np.ndarray | None = None) -> torch.Tensor:
        """Observation before control step `step` from the robot's particles (x, v, mass, muscle
        membership) and, for the occupancy map, the cover's positions."""
        w = mass / mass.sum()
        com, com_v = w @ x, w @ v
        values = []
        for name, _ in self.parts():
            if name == "com":
                values.append(com)
            elif name == "velocity":
                values.append(com_v)
            elif name == "muscle_centroids":
                weights = mass[:, None] * muscle.abs()
                weights = weights / (weights.sum(0, keepdim=True) + 1e-12)
                values.append(torch.cat([weights.T @ x, weights.T @ v], dim=1).reshape(-1))
            elif name == "occupancy":
                values.append(torch.as_tensor(self.occupancy(com.detach().cpu().numpy(), x.detach().cpu().numpy(),
                                                             cover_x), dtype=x.dtype).reshape(-1))
            elif name == "task":
                values.append(torch.as_tensor(self.task.info(step), dtype=x.dtype))
            else:
                values.append(torch.tensor([step / self.horizon], dtype=x.dtype))
        return torch.cat(values)

    def occupancy(self, center: np.ndarray, robot_x: np.ndarray, cover_x: np.ndarray | None) -> np.ndarray:
        """(3, cx, cy, cz) cells of the MPM grid centred on `center`: terrain below the height map,
        any cover particle, any robot particle."""
        cells = np.asarray(self.config.occupancy_cells)
        origin = np.floor(center / self.dx).astype(int) - cells // 2
        grid = np.zeros((3, *cells), dtype=np.float64)
        index = np.stack(np.meshgrid(*[np.arange(c) for c in cells], indexing="ij"), axis=-1) + origin
        hx = np.clip(index[..., 0], 0, self.heights.shape[0] - 1)
        hz = np.clip(index[..., 2], 0, self.heights.shape[1] - 1)
        grid[0] = (index[..., 1] + 0.5) * self.dx < self.heights[hx, hz]
        for channel, points in ((1, cover_x), (2, robot_x)):
            if points is None or len(points) == 0:
                continue
            local = np.floor(points / self.dx).astype(int) - origin
            inside = ((local >= 0) & (local < cells)).all(1)
            grid[channel][tuple(local[inside].T)] = 1.0
        return grid
