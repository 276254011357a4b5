"""HyperNEAT (Stanley, D'Ambrosio & Gauci 2009), beyond the paper: a CPPN (a neat-python genome)
queried on a substrate gives the weights of a closed-loop network, so the controller's geometry
(where each input and actuator lies) shapes its weights and a small genome can wire many actuators.

Substrate: every node is a 3-D point (a, b, layer).

- inputs, layer -1: the sine controller's time basis sin(omega_i t + phi_j) at
  (r_i cos phi_j, r_i sin phi_j, -1), r_i = (i + 1) / I, phi_j = 2 pi j / J: each frequency a
  ring, each phase an angle on it, all inside the unit disk; with `observation: true` also the
  observation's D entries, in order, evenly on the segment a in [-1, 1] at b = -1.25 (just below
  the disk, so no entry shares a basis node's coordinates);
- hidden, layer 0 (`hidden` > 0): a near-square grid of ceil(sqrt(H)) columns spanning
  [-1, 1]^2, filled row by row;
- outputs, layer +1: the K actuators at (a_k, b_k, 1), (a_k, b_k) given by `set_substrate` (the
  caller passes muscle centroids' (x, z), normalised over the workspace); until then evenly on
  the segment a in [-1, 1] at b = 0.

The CPPN takes (source a, b, layer, target a, b, layer) and has four outputs, two competing
pairs: an output node's activation is drawn from all of NEAT's, and sigmoid, gauss, exp and abs
are never negative, so one output's value would give an all-positive network for a quarter of
the fresh genomes (measured); a difference of two is signed whatever the activations (as the
neat_cppn body's occupancy is two competing scores). Outputs 0 - 1 is the weight of the
connection source -> target: clipped to [-1, 1] as HyperNEAT's bounded CPPN outputs are, a
magnitude under `weight_threshold` expresses no connection and larger ones map linearly onto
(0, max_weight] with their sign. Outputs 2 - 3, queried with the source at zeros (the
substrate's centre), is the target's bias: clipped to [-1, 1] and scaled by max_weight (no
threshold: a bias is always expressed).

The network u = bound * tanh(W_out tanh(W_in x + b_in) + b_out) (no hidden layer:
u = bound * tanh(W x + b)) holds its weights in torch tensors: the run saves them as the
controller's parameters and replays them without the genome, and a gradient optimizer may
fine-tune them. The `cppn_neat` optimizer sets genomes through `set_genome`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from codesign.interfaces import Controller
from codesign_basics.config import HyperNEATConfig
from codesign_basics.cppn import evaluate_cppn, genome_section, random_genome

if TYPE_CHECKING:
    from neat.genome import DefaultGenome, DefaultGenomeConfig

CPPN_INPUTS, CPPN_OUTPUTS = 6, 4  # (source a, b, layer, target a, b, layer) -> (weight +, -, bias +, -)
OBSERVATION_B = -1.25  # the observation entries' line, below the time basis's unit disk


def _spread(n: int) -> np.ndarray:
    """n evenly spaced values spanning [-1, 1] (one: the centre)."""
    return np.linspace(-1.0, 1.0, n) if n > 1 else np.zeros(n)


class HyperNEATController(Controller):
    """A network whose weights a CPPN paints on a substrate (see the module docstring). Setup
    draws a first random genome from the run's generator, so the controller also plays alone."""

    def __init__(self, config: HyperNEATConfig) -> None:
        self.config = config
        self.open_loop = not config.observation  # lets episodes precompute the actions
        self.genome: DefaultGenome | None = None
        self.substrate: list[np.ndarray] = []  # node coordinates (n, 3) of each layer: inputs, [hidden,] outputs
        self.weights: list[torch.Tensor] = []  # W, b of each pair of consecutive layers

    def setup(self, action_dim: int, observation_dim: int, control_dt: float, rng: np.random.Generator) -> None:
        cfg = self.config
        n_freq, n_phase = len(cfg.frequencies), cfg.phases
        dtype = torch.get_default_dtype()
        self._omega = torch.tensor(cfg.frequencies, dtype=dtype)
        self._phi = torch.arange(n_phase, dtype=dtype) * (2 * math.pi / n_phase)
        self._control_dt = control_dt
        radius = np.repeat(np.arange(1, n_freq + 1) / n_freq, n_phase)  # node (i, j) at row i * J + j
        angle = np.tile(2 * np.pi * np.arange(n_phase) / n_phase, n_freq)
        inputs = [np.stack([radius * np.cos(angle), radius * np.sin(angle), -np.ones(n_freq * n_phase)], axis=1)]
        if cfg.observation:
            d = observation_dim
            inputs.append(np.stack([_spread(d), np.full(d, OBSERVATION_B), -np.ones(d)], axis=1))
        layers = [np.concatenate(inputs)]
        if cfg.hidden:
            cols = math.ceil(math.sqrt(cfg.hidden))
            a, b = _spread(cols), _spread(math.ceil(cfg.hidden / cols))
            k = np.arange(cfg.hidden)
            layers.append(np.stack([a[k % cols], b[k // cols], np.zeros(cfg.hidden)], axis=1))
        layers.append(np.zeros((action_dim, 3)))
        self.substrate = layers
        self.weights = [torch.zeros(shape, dtype=dtype, requires_grad=True)
                        for source, target in zip(layers[:-1], layers[1:])
                        for shape in ((len(target), len(source)), (len(target),))]
        self.set_substrate(None)
        self.set_genome(*random_genome(self.genome_section(), rng))

    def genome_section(self) -> dict[str, str]:
        """neat-python's [DefaultGenome] settings of this controller's CPPN (6 inputs, 4 outputs)."""
        return genome_section(self.config, CPPN_INPUTS, CPPN_OUTPUTS)

    def set_genome(self, genome: DefaultGenome, genome_config: DefaultGenomeConfig) -> None:
        """Make `genome` (a neat DefaultGenome of `genome_config`) the CPPN and write the weights it paints."""
        self.genome, self.genome_config = genome, genome_config
        self._paint()

    def set_substrate(self, positions: np.ndarray | None) -> None:
        """Place the actuators at `positions` ((K, 2) in [-1, 1]^2; None: evenly on b = 0) and
        repaint the weights with the current genome."""
        if not self.substrate:
            raise RuntimeError("HyperNEATController.setup() must be called before set_substrate()")
        k = len(self.substrate[-1])
        if positions is None:
            positions = np.stack([_spread(k), np.zeros(k)], axis=1)
        positions = np.asarray(positions, dtype=float)
        if positions.shape != (k, 2) or not np.all(np.abs(positions) <= 1.0 + 1e-9):
            raise ValueError(f"actuator positions must be a ({k}, 2) array in [-1, 1]^2, got {positions!r}")
        self.substrate[-1] = np.concatenate([positions, np.ones((k, 1))], axis=1)
        if self.genome is not None:
            self._paint()

    def _paint(self) -> None:
        """Query the CPPN for every pair of consecutive layers and copy the weights into the tensors."""
        cfg = self.config
        for i, (source, target) in enumerate(zip(self.substrate[:-1], self.substrate[1:])):
            pairs = np.concatenate([np.tile(source, (len(target), 1)), np.repeat(target, len(source), axis=0)], axis=1)
            centre = np.concatenate([np.zeros((len(target), 3)), target], axis=1)
            out = evaluate_cppn(self.genome, self.genome_config, np.concatenate([pairs, centre]))
            w = np.clip(out[:len(pairs), 0] - out[:len(pairs), 1], -1.0, 1.0)
            magnitude = np.maximum(np.abs(w) - cfg.weight_threshold, 0.0) / (1.0 - cfg.weight_threshold)
            weight = (np.sign(w) * magnitude * cfg.max_weight).reshape(len(target), len(source))
            bias = np.clip(out[len(pairs):, 2] - out[len(pairs):, 3], -1.0, 1.0) * cfg.max_weight
            with torch.no_grad():
                self.weights[2 * i].copy_(torch.as_tensor(weight))
                self.weights[2 * i + 1].copy_(torch.as_tensor(bias))

    def parameters(self) -> list[torch.Tensor]:
        return list(self.weights)

    def __call__(self, observation: Any, step: int) -> torch.Tensor:
        if self.genome is None:
            raise RuntimeError("HyperNEATController.setup() must be called before use")
        dtype = self.weights[0].dtype
        t = step * self._control_dt
        x = torch.sin(self._omega[:, None] * t + self._phi[None, :]).reshape(-1).to(dtype)
        if self.config.observation:
            x = torch.cat([x, torch.as_tensor(observation).to(dtype).reshape(-1)])
        for weight, bias in zip(self.weights[::2], self.weights[1::2]):
            x = torch.tanh(weight @ x + bias)
        return self.config.bound * x
