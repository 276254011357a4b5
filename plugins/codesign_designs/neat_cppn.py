"""CPPN-NEAT (Stanley 2007; the paper's evolution-strategy baseline): a NEAT genome's CPPN,
queried at every particle of the workspace, gives occupancy, stiffness and muscle membership.

The genome is evolved by the `cppn_neat` optimizer (neat-python); this representation only
turns one genome into a design. The network is evaluated on all particles at once
(codesign_basics.cppn, shared with the hyperneat controller).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from codesign.interfaces import DesignFields, DesignSpace, Representation
from codesign_basics.cppn import ACTIVATIONS, evaluate_cppn, genome_section, random_genome  # noqa: F401 (re-exported)
from codesign_designs.common import (check_fiber, check_stiffness_ratios, coordinate_features, fixed_fibers,
                                     stiffness_map)
from codesign_designs.config import NeatCPPNConfig

N_INPUTS = 7  # x, y, z, their distances to the mid-planes, radius (codesign_designs.common.coordinate_features)


class NeatCPPNRepresentation(Representation):
    """A NEAT genome's CPPN: inputs the seven coordinate features (the paper's x, y, z, plane
    distances and radius); outputs an occupied and an empty score (a particle is occupied where
    the first is larger, as in SoftZoo's released code), stiffness (as the other representations'
    logit) and K muscle scores (each particle joins its highest). Two competing occupancy scores,
    not one output's sign: an output node's activation is drawn from all of NEAT's, and sigmoid,
    gauss, exp and abs are never negative, so a sign test fills the whole workspace for about half
    of the fresh genomes.

    The paper's connected-body constraint: only the largest connected piece of the occupied
    particles is kept (particles are neighbours within 1.5 times the median spacing), and of that
    what the environment simulates (`DesignSpace.keep`: parts thick enough for its grid). A genome
    whose body keeps under `min_body_fraction` of the workspace is `valid` False: the optimizer
    ranks it last without simulating it. Setup draws a first random genome, so the
    representation also plays alone (e.g. with the evaluate optimizer); it has no torch
    parameters: only the evolution changes it.
    """

    def __init__(self, config: NeatCPPNConfig) -> None:
        check_stiffness_ratios(config)
        check_fiber(config.fiber)
        self.config = config
        self.genome = None

    def setup(self, space: DesignSpace, rng: np.random.Generator) -> None:
        self.space = space
        self.features = coordinate_features(space)
        self.n_outputs = 3 + space.n_actuators  # occupied, empty, stiffness, K muscles
        self._fiber = fixed_fibers(space, self.config.fiber)
        tree = cKDTree(space.points)
        spacing = float(np.median(tree.query(space.points, k=2)[0][:, 1])) if len(space.points) > 1 else 1.0
        self._pairs = tree.query_pairs(1.5 * spacing, output_type="ndarray")
        self.set_genome(*random_genome(self.genome_section(), rng))

    def genome_section(self) -> dict[str, str]:
        """neat-python's [DefaultGenome] settings of this representation (after setup)."""
        return genome_section(self.config, N_INPUTS, self.n_outputs)

    def set_genome(self, genome, genome_config) -> None:
        """Make `genome` (a neat DefaultGenome of `genome_config`) the current design."""
        self.genome, self.genome_config = genome, genome_config
        out = evaluate_cppn(genome, genome_config, self.features)
        self.raw_occupancy = out[:, 0] > out[:, 1]  # what the genome alone says, before the body constraints
        occupied = self.connected_body(self.raw_occupancy)
        if self.space.keep is not None:  # what the environment simulates of it (thick enough for its grid)
            occupied = self.space.keep(occupied)
        self.valid = occupied.mean() >= max(self.config.min_body_fraction, 1e-12)
        muscle = np.eye(self.space.n_actuators)[np.argmax(out[:, 3:], axis=1)]
        self._fields = DesignFields(
            occupancy=occupied.astype(float),
            stiffness=stiffness_map(torch.as_tensor(out[:, 2]), self.space.default_stiffness,
                                    self.config.min_stiffness_ratio, self.config.max_stiffness_ratio).numpy(),
            muscle=muscle, fiber=self._fiber)

    def connected_body(self, occupied: np.ndarray) -> np.ndarray:
        """The largest connected piece of `occupied` (a boolean mask over the workspace's particles)."""
        if not occupied.any():
            return occupied
        pairs = self._pairs[occupied[self._pairs[:, 0]] & occupied[self._pairs[:, 1]]]
        n = len(occupied)
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, label = connected_components(graph, directed=False)
        largest = np.bincount(label[occupied]).argmax()
        return occupied & (label == largest)

    def __call__(self) -> DesignFields:
        if self.genome is None:
            raise RuntimeError("NeatCPPNRepresentation.setup() must be called before use")
        return self._fields
