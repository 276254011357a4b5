"""Design primitives blended by trainable weights: what SDF-Lerp and the Wasserstein barycenter share.

Each primitive (a library body or a body file) is fitted into the workspace's box keeping its
proportions, centred in x and z and resting on the box's floor. Stiffness and muscle
membership are blended linearly (SoftZoo appendix), fibres as rotations with the special
orthogonal Procrustes projection; weights are softmaxes of trainable logits, so they stay
positive and sum to one. Subclasses say how the geometry blends.
"""

from __future__ import annotations

from abc import abstractmethod
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from codesign.bodies import LIBRARY_BODIES, Body, BodyError, get_body
from codesign.errors import RecipeError
from codesign.interfaces import DesignFields, DesignSpace, Representation
from codesign_designs.rotations import average_rotations, fiber_rotations, principal_axes

WEIGHTS = ("geometry", "stiffness", "muscle", "fiber")
"""One logit vector each (alpha, beta, gamma, kappa of the paper): 4 P parameters for P primitives."""


def place(body: Body, lo: np.ndarray, hi: np.ndarray) -> Body:
    """`body` fitted into the box [lo, hi] keeping proportions, centred in x and z, on the box's floor."""
    fitted = body.fitted(hi - lo, center=(lo + hi) / 2)
    return fitted.transformed(1.0, [0.0, lo[1] - fitted.bounds[0][1], 0.0])


def primitive_muscle(groups: np.ndarray, actuator: np.ndarray, k: int) -> np.ndarray:
    """(N, K) one-hot membership of a primitive's groups, group g driving actuator[g]; passive rows 0."""
    muscle = np.zeros((len(groups), k))
    active = groups >= 0
    if k:
        muscle[np.flatnonzero(active), actuator[groups[active]]] = 1.0
    return muscle


def group_centroids(points: np.ndarray, groups: np.ndarray, n_groups: int) -> np.ndarray:
    """(G, 3) the centre of each muscle group's points; NaN for a group with none."""
    return np.stack([points[groups == g].mean(0) if (groups == g).any() else np.full(3, np.nan)
                     for g in range(n_groups)]).reshape(n_groups, 3)


def muscle_correspondence(centroids: list[np.ndarray], k: int) -> list[np.ndarray]:
    """For each primitive, the actuator each of its muscle groups drives: the first primitive's group
    g drives actuator g, and every other primitive's groups take the actuators whose groups in the
    first lie nearest (Hungarian matching of the groups' centres in the shared workspace), so a
    blend lerps a fish's left front flank with the seal's left fore-flipper, not with whatever group
    shares its number. Actuators the first primitive leaves free come last (a large cost); a group
    with no points in the workspace takes whichever actuator is left."""
    reference = centroids[0]
    out = [np.arange(len(reference))]
    free = 1e6  # the cost of an actuator the first primitive does not use
    for mine in centroids[1:]:
        cost = np.full((len(mine), k), free)
        cost[:, :len(reference)] = np.linalg.norm(mine[:, None, :] - reference[None, :, :], axis=-1)
        cost = np.nan_to_num(cost, nan=free)  # a group without points, on either side: a constant row or column
        rows, columns = linear_sum_assignment(cost)
        actuator = np.empty(len(mine), dtype=int)
        actuator[rows] = columns
        out.append(actuator)
    return out


class PrimitiveBlend(Representation):
    """Primitives' stiffness, muscles and fibres blended by softmax weights; geometry by the subclass."""

    def __init__(self, config) -> None:
        self.config = config
        self.bodies = [self._body(i, name) for i, name in enumerate(config.primitives)]
        self.logits: dict[str, torch.Tensor] = {}
        self.actuators: list[np.ndarray] = []
        """Per primitive, the actuator each muscle group drives (`muscle_correspondence`)."""

    @staticmethod
    def _body(i: int, name: str) -> Body:
        if name not in LIBRARY_BODIES and not Path(name).is_file():
            raise RecipeError(f"invalid recipe: representation.primitives[{i}]: {name!r} is neither a library body "
                              f"({', '.join(LIBRARY_BODIES)}) nor an existing body file")
        try:
            return get_body(name)
        except BodyError as exc:
            raise RecipeError(f"invalid recipe: representation.primitives[{i}]: {exc}") from exc

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        lo, hi = space.box()
        self.placed = [place(body, lo, hi) for body in self.bodies]
        labels = [body.labels(space.points) for body in self.placed]
        k = space.n_actuators
        for i, body in enumerate(self.placed):
            if body.n_groups > k:
                raise RecipeError(f"invalid recipe: representation.primitives[{i}]: {self.config.primitives[i]!r} "
                                  f"has {body.n_groups} muscle groups, more than the robot's {k} actuators "
                                  "(environment.robot.muscle_groups): give the robot at least as many, or use "
                                  "another primitive")
        self.actuators = muscle_correspondence(
            [group_centroids(space.points, lab.groups, body.n_groups) for lab, body in zip(labels, self.placed)], k)
        dtype = torch.get_default_dtype()
        self._stiffness = torch.tensor(np.stack([lab.stiffness for lab in labels], 1), dtype=dtype)  # (N, P)
        self._muscle = torch.tensor(np.stack([primitive_muscle(lab.groups, actuator, k)
                                              for lab, actuator in zip(labels, self.actuators)], 1),
                                    dtype=dtype)  # (N, P, K)
        fibers = np.stack([lab.fibers for lab in labels], 1)  # (N, P, 3)
        reference = principal_axes(fibers)  # per point: the blended fibres' common axis, whatever their signs
        self._reference = torch.tensor(reference, dtype=dtype)  # (N, 3)
        self._rotations = torch.tensor(fiber_rotations(fibers, reference[:, None, :]), dtype=dtype)  # (N, P, 3, 3)
        self._default_stiffness = space.default_stiffness
        p, noise = len(self.bodies), self.config.init_noise
        self.logits = {name: torch.tensor(rng.normal(0.0, noise, p) if noise > 0 else np.zeros(p), dtype=dtype,
                                          requires_grad=True) for name in WEIGHTS}
        self._setup_geometry(space)

    @abstractmethod
    def _setup_geometry(self, space: DesignSpace) -> None:
        """Precompute what the geometry needs at the workspace's particles (after `placed` is set)."""

    @abstractmethod
    def _occupancy(self, weights: torch.Tensor) -> torch.Tensor:
        """(N,) occupancy for the (P,) geometry weights."""

    def parameters(self) -> list[torch.Tensor]:
        return [self.logits[name] for name in WEIGHTS]

    def weights(self) -> dict[str, torch.Tensor]:
        """The normalised weights (alpha-hat, ...), each (P,) positive and summing to one."""
        return {name: torch.softmax(logit, 0) for name, logit in self.logits.items()}

    def __call__(self) -> DesignFields:
        if not self.logits:
            raise RuntimeError(f"{type(self).__name__}.setup() must be called before use")
        w = self.weights()
        return DesignFields(
            occupancy=self._occupancy(w["geometry"]),
            stiffness=self._default_stiffness * (self._stiffness @ w["stiffness"]),
            muscle=torch.einsum("npk,p->nk", self._muscle, w["muscle"]),
            fiber=torch.einsum("nij,nj->ni", average_rotations(self._rotations, w["fiber"]), self._reference),
        )
