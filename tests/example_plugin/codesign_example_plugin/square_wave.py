from dataclasses import dataclass, field

import numpy as np

from codesign.interfaces import Controller


@dataclass
class SquareWaveConfig:
    frequency: float = field(default=1.0, metadata={"gt": 0, "help": "cycles per simulated second"})
    amplitude: float = field(default=0.3, metadata={"gt": 0})


class SquareWave(Controller):
    """u_k(t) = amplitude * sign(sin(2 pi f t + 2 pi k / K)); ignores observations."""

    def __init__(self, config: SquareWaveConfig) -> None:
        self.config = config

    def setup(self, action_dim, observation_dim, control_dt, rng) -> None:
        self.offsets = 2 * np.pi * np.arange(action_dim) / action_dim
        self.control_dt = control_dt

    def __call__(self, observation, step: int) -> np.ndarray:
        t = step * self.control_dt
        return self.config.amplitude * np.sign(np.sin(2 * np.pi * self.config.frequency * t + self.offsets))
