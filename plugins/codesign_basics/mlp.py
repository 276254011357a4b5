"""A closed-loop controller: an MLP on the observation."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from codesign.interfaces import Controller
from codesign_basics.config import MLPConfig

ACTIVATIONS = {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU, "elu": torch.nn.ELU}


class MLPController(Controller):
    """``action``: u = bound * tanh(MLP(obs)). ``sine_weights``: the MLP outputs the sine basis
    weights alpha (K, I, J) and biases beta (K,) from the observation, and u = bound *
    tanh(sum_ij alpha sin(omega_i t + phi_j) + beta): a gait whose shape follows the state.

    Weights are initialised from the run's generator (Glorot uniform, last layer scaled by
    init_std), so a seed reproduces them. Observations may be numpy or torch; with torch, the
    action's gradient reaches the observation (closed-loop differentiable episodes).
    """

    def __init__(self, config: MLPConfig) -> None:
        self.config = config
        self.net: torch.nn.Sequential | None = None

    def setup(self, action_dim: int, observation_dim: int, control_dt: float, rng: np.random.Generator) -> None:
        cfg = self.config
        self._k, self._control_dt = action_dim, control_dt
        self._shape = (action_dim, len(cfg.frequencies), cfg.phases)
        out = action_dim if cfg.output == "action" else int(np.prod(self._shape)) + action_dim
        widths = [observation_dim, *cfg.hidden, out]
        layers: list[torch.nn.Module] = []
        for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
            linear = torch.nn.Linear(a, b)
            limit = math.sqrt(6 / (a + b)) * (1.0 if i < len(widths) - 2 else cfg.init_std)
            with torch.no_grad():
                linear.weight.copy_(torch.as_tensor(rng.uniform(-limit, limit, (b, a))))
                linear.bias.zero_()
            layers += [linear, ACTIVATIONS[cfg.activation]()]
        self.net = torch.nn.Sequential(*layers[:-1])
        dtype = torch.get_default_dtype()
        self._omega = torch.tensor(cfg.frequencies, dtype=dtype)
        self._phi = torch.arange(cfg.phases, dtype=dtype) * (2 * math.pi / cfg.phases)

    def parameters(self) -> list[torch.Tensor]:
        return list(self.net.parameters())

    def __call__(self, observation: Any, step: int) -> torch.Tensor:
        if self.net is None:
            raise RuntimeError("MLPController.setup() must be called before use")
        dtype = self.net[0].weight.dtype
        out = self.net(torch.as_tensor(observation).to(dtype))
        if self.config.output == "action":
            return self.config.bound * torch.tanh(out)
        alpha, beta = out[:-self._k].reshape(self._shape), out[-self._k:]
        basis = torch.sin(self._omega[:, None] * (step * self._control_dt) + self._phi[None, :]).to(dtype)
        return self.config.bound * torch.tanh((alpha * basis).sum(dim=(1, 2)) + beta)
