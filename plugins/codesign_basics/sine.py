"""The open-loop sine-basis controller of the SoftZoo paper."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from codesign.interfaces import Controller
from codesign_basics.config import SineConfig


class SineController(Controller):
    """u_k(t) = bound * tanh(sum_ij (alpha_kij sin(omega_i t + phi_j) + beta_kij)), with t = step * control_dt.

    ``alpha`` (K, I, J) and ``beta`` are torch tensors that require grad, so gradient-based
    optimizers can train them through the action. ``bias: per_basis`` (default) is the paper's
    literal form, ``beta`` (K, I, J): only its sum over (i, j) acts, so Adam moves that effective
    bias up to I x J times its learning rate and CMA-ES searches I x J - 1 dimensions per actuator
    that change nothing. ``bias: per_actuator`` keeps one ``beta`` (K,) per actuator instead. The
    observation is ignored. Calls return a torch tensor of shape (K,).
    """

    open_loop = True  # the observation is ignored: an episode is one checkpointed rollout

    def __init__(self, config: SineConfig) -> None:
        self.config = config
        self.alpha: torch.Tensor | None = None
        self.beta: torch.Tensor | None = None

    def setup(self, action_dim: int, observation_dim: int, control_dt: float, rng: np.random.Generator) -> None:
        cfg = self.config
        shape = (action_dim, len(cfg.frequencies), cfg.phases)
        dtype = torch.get_default_dtype()
        self.alpha = torch.tensor(rng.normal(0.0, cfg.init_std, shape), dtype=dtype, requires_grad=True)
        self.beta = torch.zeros(shape if cfg.bias == "per_basis" else shape[:1], dtype=dtype, requires_grad=True)
        self._omega = torch.tensor(cfg.frequencies, dtype=dtype)
        self._phi = torch.arange(cfg.phases, dtype=dtype) * (2 * math.pi / cfg.phases)
        self._control_dt = control_dt

    def parameters(self) -> list[torch.Tensor]:
        return [self.alpha, self.beta]

    def __call__(self, observation: Any, step: int) -> torch.Tensor:
        if self.alpha is None:
            raise RuntimeError("SineController.setup() must be called before use")
        t = step * self._control_dt
        basis = torch.sin(self._omega[:, None] * t + self._phi[None, :])  # (I, J)
        terms = self.alpha * basis
        if self.beta.dim() == 3:  # per_basis
            return self.config.bound * torch.tanh((terms + self.beta).sum(dim=(1, 2)))
        return self.config.bound * torch.tanh(terms.sum(dim=(1, 2)) + self.beta)
