"""Several particle sets (designs) of one scene simulated together: a batch axis for populations.

Evolutionary and RL optimizers evaluate a population of designs or controllers on one scene.
Run one after the other, a small scene pays each kernel's launch and thread synchronisation
once per individual per substep. A `BatchSimulator` puts the members' particles into one
particle array and their grids side by side into one grid (member b owns the nodes
[b nx, (b + 1) nx) along x), so every substep launches each kernel once for the population.

Members never interact and each keeps its own CFL time step (following its own state, frame by
frame): the batch runs as many substeps per control step as its most demanding member, and a
member with a larger step sits out the substeps it does not need. A member's trajectory is therefore the one a plain `Simulator`
gives its particles (up to the order of floating-point atomic additions). Forward only:
differentiable rollouts use `Simulator`.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from codesign_mpm.engine import Layout, Rollout, Simulator, TimeStep, time_step
from codesign_mpm.engine.time_step import flip_share
from codesign_mpm.scene.sampling import Particles
from codesign_mpm.scene.spec import Scene


def stack(members: Sequence[Particles]) -> Particles:
    """The members' particles in one set, member after member."""
    return Particles(**{name: np.concatenate([getattr(m, name) for m in members])
                        for name in Particles.__dataclass_fields__})


class BatchSimulator(Simulator):
    """B particle sets of one scene stepped together, each with its own actions and time step.

    `capacity` is per member (particles of the largest design the batch will hold), so that
    batches of different designs share one compiled layout. Arrays that the plain simulator
    takes or returns per particle (`set_initial_state`, `particles_state`, `stress`) hold the
    members one after the other; `split` cuts them per member. `step` takes one action row per
    member.
    """

    def __init__(self, scene: Scene, members: Sequence[Particles], *, capacity: int | None = None) -> None:
        if not members:
            raise ValueError("a batch needs at least one member")
        actuators = sorted({m.n_actuators for m in members})
        if len(actuators) > 1:
            raise ValueError(f"every member needs the same number of actuators, got {actuators}")
        self.counts = [m.n for m in members]
        self.starts = np.r_[0, np.cumsum(self.counts)]
        self.member_steps: list[TimeStep] = []
        super().__init__(scene, stack(members), capacity=None if capacity is None else capacity * len(members))

    @property
    def size(self) -> int:
        """B, the number of members."""
        return len(self.counts)

    def _layout(self, layout: Layout) -> Layout:
        if self.size == 1:  # a batch of one is a plain simulator: share its compiled kernels
            return layout
        return replace(layout, members=self.size, rows=self.size)

    def split(self, values: np.ndarray) -> list[np.ndarray]:
        """Per-particle values of the whole batch, cut into one array per member."""
        return [values[a:b] for a, b in zip(self.starts[:-1], self.starts[1:])]

    def _members(self, particles: Particles) -> list[Particles]:
        return [Particles(**{name: getattr(particles, name)[a:b] for name in Particles.__dataclass_fields__})
                for a, b in zip(self.starts[:-1], self.starts[1:])]

    def _time_step(self, particles: Particles) -> TimeStep:
        # each member keeps its own step; the batch runs as many substeps as the most demanding one
        self.member_steps = [time_step(self.scene, member) for member in self._members(particles)]
        return max(self.member_steps, key=lambda step: step.substeps)

    def _use(self, particles: Particles) -> None:
        super()._use(particles)
        k = self.k
        if k.batched:
            self._put(k.member, np.repeat(np.arange(self.size, dtype=np.int32), self.counts))
            self._member_substeps: list[int] = []
            self._set_member_substeps([t.substeps for t in self.member_steps])

    def _set_member_substeps(self, substeps: list[int]) -> None:
        """Each member's substeps for the next frame (and so its dt), written only when they change."""
        if substeps != self._member_substeps:
            self._member_substeps = substeps
            dts = [self.scene.frame_dt / n for n in substeps]
            self.k.member_dt.from_numpy(np.array(dts, self.np_real))
            self.k.member_flip.from_numpy(np.array([flip_share(self.scene, dt) for dt in dts], self.np_real))
            self.k.member_substeps.from_numpy(np.array(substeps, np.int32))

    def _plan_frame(self) -> int:
        """Each member's substeps from its own state; the batch runs the most demanding member's."""
        if not self.k.batched:
            return super()._plan_frame()
        waves = self.k.member_wave.to_numpy()
        self._set_member_substeps([self._substeps_for(float(w), at_rest)
                                   for w, at_rest in zip(waves, self.member_steps)])
        return max(self._member_substeps)

    def reset_members(self, members: Sequence[Particles]) -> None:
        """Load new designs with the same particle count per member (else build a new batch)."""
        counts = [m.n for m in members]
        if counts != self.counts:
            raise ValueError(f"reset_members() needs members of {self.counts} particles, got {counts}; "
                             "build a new BatchSimulator (it reuses the compiled kernels)")
        self.reset(stack(members))

    def _hold(self, action, row: int) -> None:
        """Write one action row per member ((B, K); default zeros), checking shape and bound."""
        if not self.n_actuators:
            return
        shape = (self.size, self.n_actuators)
        a = np.zeros(shape) if action is None else np.asarray(action, dtype=np.float64)
        if a.shape != shape:
            raise ValueError(f"actions must have shape {shape} (one row per member), got {a.shape}")
        self._check_bound(a)
        if self.k.batched:
            self.k.act.from_numpy(a.astype(self.np_real))
        else:
            self.k.act[row] = a[0].astype(self.np_real)

    def _speeds(self) -> list[tuple[float, float, str]]:
        if not self.k.batched:
            return super()._speeds()
        speeds = self.k.member_speed.to_numpy()
        return [(float(v), self.scene.frame_dt / n, f" of member {b}")
                for b, (v, n) in enumerate(zip(speeds, self._member_substeps))]

    def _where(self, p: int) -> str:
        b = int(np.searchsorted(self.starts, p, side="right")) - 1
        return f"particle {p - self.starts[b]} of member {b}"

    def rollout(self, actions: np.ndarray, checkpoint_every: int | None = None, start=None) -> Rollout:
        raise NotImplementedError("BatchSimulator steps forward only; differentiable rollouts use Simulator")
