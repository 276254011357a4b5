"""The public simulator: `Simulator`, its time step, and what its rollouts return.

One substep (`Simulator._substep`; the kernels live in the modules named):

    bounds   -> the box of grid nodes the particles touch (only those are cleared and updated) [transfer]
    stress   -> F <- (I + dt C) F; each material's Kirchhoff stress or return mapping, plus the
                muscle [constitutive, materials/]: in kernels of their own ahead of p2g for scenes
                with non-elastic materials and differentiable layouts, else inside p2g
    p2g      -> scatter m v and the MLS force/affine term (and the mass at the terrain's surface) to 27
                nodes [transfer]
    grid_op  -> v = p / m + dt g; terrain (height-map SDF, Coulomb friction); domain walls [grid]
    contact  -> (terrain.contact: surface, spring) the impulses of the particles at the terrain's
                exact surface, from the updated grid and added to it; spring: each particle's
                tangential spring into the next slot [contact]
    g2p      -> gather v and C; x <- x + dt v (with `scene.flip` or `scene.pic_time`, a FLIP
                share) [transfer]

Where p2g computes the stress and no grid is kept for a reverse pass (a forward step of an elastic
scene), the whole substep is one kernel launch (`_forward_substep` in storage): its loops run the
same per-particle and per-node functions as the stages' own kernels, so both paths give bitwise
the same states.

And its reverse (`Simulator._substep_grad`): the grid kept from the segment's recompute, then
g2p's, the contact's, grid_op's, p2g's and the stress's adjoints. `rollout` stores checkpoints,
`backward` recomputes each segment from its checkpoint and runs the substeps' reverses.
"""
# (no `from __future__ import annotations`: Taichi reads kernel annotations at runtime)

import math
import os
import weakref
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import taichi as ti

from codesign_mpm import runtime
from codesign_mpm.engine.checkpoints import CheckpointStore
from codesign_mpm.engine.storage import CAPACITY_STEP, Layout, _acquire, _recycle_program, _release
from codesign_mpm.engine.time_step import (ADAPTIVE_CFL_FACTOR, MAX_ADAPTIVE_CFL, TimeStep, flip_share,
                                           time_step, wave_speeds)
from codesign_mpm.engine.transfer import flip_models
from codesign_mpm.materials import MODEL_NAMES, material
from codesign_mpm.scene.sampling import Particles
from codesign_mpm.scene.spec import Scene, SceneError, validate_scene
from codesign_mpm.scene.terrain import height_map, normals

GRID_STORE_BYTES = 256 * 1024**2  # at most this much keeps a segment's grids for the reverse pass
GRID_STORE_MARGIN = 2.0  # a rollout's grid records hold this times the particles' box at its start (or the largest seen)
CHECKPOINT_MEMORY_BYTES = 128 * 1024**2  # a rollout's checkpoints beyond this go to a temporary file
SEGMENT_MEMORY_BYTES = 256 * 1024**2
"""A differentiable simulator's segment (its slots of particle state, gradients included) grows to this
much by default: the backward pass recomputes every segment but the last, so an episode whose
states fit is not recomputed at all. The environment variable CODESIGN_SEGMENT_MEMORY_MB overrides
it (a GPU with memory to spare)."""


def segment_memory_bytes() -> int:
    """SEGMENT_MEMORY_BYTES, or CODESIGN_SEGMENT_MEMORY_MB where it is set."""
    forced = os.environ.get("CODESIGN_SEGMENT_MEMORY_MB")
    if not forced:
        return SEGMENT_MEMORY_BYTES
    if not forced.isdigit():
        raise ValueError(f"CODESIGN_SEGMENT_MEMORY_MB must be a whole number of megabytes (0: the "
                         f"memory-optimal segment), got {forced!r}")
    return int(forced) * 1024**2


def default_segment(substeps: int, slot_bytes: int) -> int:
    """Substeps between checkpoints for an episode of `substeps` (at the resting step): the whole
    episode where its states fit in `segment_memory_bytes()`, rounded up to a power of two (the
    slots are part of the compiled layout: designs and runs whose steps differ a little share one),
    else as many as fit, and never fewer than sqrt(substeps / 2), the interval that minimises memory
    (checkpoints plus slots)."""
    fitting = segment_memory_bytes() // max(slot_bytes, 1) - 1
    whole = 1 << max(substeps - 1, 0).bit_length()
    return max(1, math.ceil(math.sqrt(substeps / 2)), min(whole, fitting))


class SimulationError(RuntimeError):
    """The state went non-finite or left the domain; the message says where and when."""


@dataclass
class Gradients:
    """d loss / d inputs of a differentiable rollout (numpy)."""

    actions: np.ndarray  # (T, K)
    volume: np.ndarray  # (N,)   design: occupancy scales the volume (and so the mass)
    youngs_modulus: np.ndarray  # (N,)
    muscle: np.ndarray  # (N, K)
    fiber: np.ndarray  # (N, 3)
    x0: np.ndarray  # (N, 3)
    v0: np.ndarray  # (N, 3)
    F0: np.ndarray  # (N, 3, 3) initial deformation gradient
    C0: np.ndarray  # (N, 3, 3) initial affine velocity (APIC)
    Jp0: np.ndarray  # (N,) initial plastic volume ratio (zeros without snow)
    u0: np.ndarray | None = None  # (N, 3) initial tangential springs of the spring contact (None: another contact)


@dataclass
class State:
    """The particle state between two frames: what a rollout may start from and ends in."""

    x: np.ndarray  # (N, 3)
    v: np.ndarray  # (N, 3)
    C: np.ndarray  # (N, 3, 3)
    F: np.ndarray  # (N, 3, 3)
    Jp: np.ndarray  # (N,) snow's plastic volume ratio (ones elsewhere)
    u: np.ndarray | None = None  # (N, 3) the spring contact's tangential springs (None: none stuck)


@dataclass
class Rollout:
    """What a differentiable rollout returns: robot centre of mass per frame, final particles."""

    com_x: np.ndarray  # (T+1, 3), frame 0 is the initial state
    com_v: np.ndarray  # (T+1, 3)
    x: np.ndarray  # (N, 3) after T frames
    v: np.ndarray  # (N, 3)
    final: State  # the whole state after T frames (float64)



def _model_runs(material: np.ndarray) -> list[tuple[int, int, int]]:
    """(model, start, end) of each run of equal models in particle order (bodies are contiguous)."""
    edges = np.flatnonzero(np.diff(material)) + 1
    starts, ends = np.r_[0, edges], np.r_[edges, len(material)]
    return [(int(material[a]), int(a), int(b)) for a, b in zip(starts, ends)]



def _unit_fibers(fiber: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit fibres, their given lengths); a zero-length fibre is an error naming the particle."""
    length = np.linalg.norm(fiber, axis=1)
    bad = np.flatnonzero(~(length > 1e-12))
    if len(bad):
        raise ValueError(f"fiber of particle {bad[0]} is {fiber[bad[0]].tolist()}: fibres must be non-zero "
                         "directions (they are normalised)")
    return fiber / length[:, None], length


class Simulator:
    """MLS-MPM simulation of one scene.

    `requires_grad=True` allocates gradient storage for rollouts of up to `max_frames` frames
    with a checkpoint every `checkpoint_every` substeps (default: `default_segment`, the whole
    episode where its states fit in SEGMENT_MEMORY_BYTES). Without it, `step` advances the scene
    frame by frame at full speed.
    Compiled kernels are reused from any earlier simulator of the same layout that has been
    closed or garbage-collected; `capacity` (particles) lets simulators of designs with
    different particle counts share one layout.
    """

    def __init__(self, scene: Scene, particles: Particles, *, requires_grad: bool = False,
                 max_frames: int = 1, checkpoint_every: int | None = None, capacity: int | None = None) -> None:
        validate_scene(scene)
        _recycle_program()
        forward_only = [MODEL_NAMES[m] for m in sorted(set(particles.material.tolist())) if not material(m).differentiable]
        if requires_grad and forward_only:
            raise SceneError(f"material kind '{forward_only[0]}' is invalid in a differentiable simulator (requires_grad): "
                             "the model has no reverse mode (corotated: Taichi has none of its polar decomposition); "
                             "use neo_hookean (the "
                             "robots' default) or stvk, or simulate it without gradients")
        runtime.init_taichi(scene.arch, scene.dtype)
        self.scene = scene
        self.np_real = np.float64 if scene.dtype == "float64" else np.float32
        self.timestep = self._time_step(particles)
        self.n = particles.n
        self.n_actuators = particles.n_actuators
        self.requires_grad = requires_grad
        self.max_frames = max_frames
        self.body_names = [b.name for b in scene.bodies]
        models = tuple(sorted(set(int(m) for m in particles.material)))
        allocated = -(-max(particles.n, capacity or 0) // CAPACITY_STEP) * CAPACITY_STEP
        self.layout = self._layout(Layout(
            capacity=allocated,
            n_actuators=particles.n_actuators,
            slots=2,
            rows=max_frames + 1,
            grid_shape=scene.grid_shape,
            models=models,
            has_muscles=particles.n_actuators > 0 and bool(np.any(particles.muscle_ratio > 0)),
            muscle_model=scene.muscle_model,
            has_terrain=scene.terrain.kind != "none",
            boundary_cells=scene.boundary_cells,
            requires_grad=requires_grad,
            scatter_copies=runtime.scatter_copies(), folded=runtime.fold_reductions(),
            serial=runtime.serial_loops(allocated),
            has_flip=(scene.flip > 0 or scene.pic_time is not None) and any(m in flip_models() for m in models),
            surface_contact=scene.terrain.kind != "none" and scene.terrain.contact in ("surface", "spring"),
            contact_memory=scene.terrain.kind != "none" and scene.terrain.contact == "spring",
        ))
        self.segment = checkpoint_every or default_segment(
            max_frames * self.timestep.substeps, self.layout.slot_bytes(np.dtype(self.np_real).itemsize))
        if requires_grad:
            self.layout = replace(self.layout, slots=self.segment + 1)
        self.k = _acquire(self.layout)
        self._generation = runtime.generation
        self._finalizer = weakref.finalize(self, _release, self._generation, self.k)
        self._initial_CF: tuple[np.ndarray, np.ndarray] | None = None
        self._initial_jp: np.ndarray | None = None
        self._initial_u: np.ndarray | None = None
        self.rollouts = 0
        self.recomputed_substeps = 0
        """Substeps the last `backward` recomputed from checkpoints (every segment's but the last)."""
        self._grid_store = self._grid_boxes = None  # the segment's grids, kept for the reverse pass
        self._largest_box = 0  # nodes of the largest box a backward pass saw: the next records hold it
        self._checkpoints = CheckpointStore(CHECKPOINT_MEMORY_BYTES)
        self._changes = 0  # bumped by anything that alters the state a rollout's backward pass replays
        self._measured = (-1, -1)  # (changes, slot) of the state `_check` last measured in `step`
        self._rollout_changes = -1
        self.on_frame: Callable[[np.ndarray], None] | None = None
        """Called with the positions (N, 3) after every frame of `step` and `rollout` (forward only)."""
        self.audit_work = False
        """True: `step` adds up the muscles' work (`muscle_work`), for energy audits (one more kernel per substep)."""
        self._set_constants()
        self.reset(particles)

    def _layout(self, layout: Layout) -> Layout:
        """The storage layout to compile for (a batch adjusts the plain one)."""
        return layout

    def _time_step(self, particles: Particles) -> TimeStep:
        """The CFL step that `particles` need (a batch: its most demanding member's)."""
        return time_step(self.scene, particles)

    def close(self) -> None:
        """Hand the compiled storage back for reuse; the simulator is unusable afterwards."""
        self._finalizer()
        self._checkpoints.close()
        self.k = None

    def _set_constants(self) -> None:
        s, k = self.scene, self.k
        self._set_dt(self.timestep.dt)
        k.dx[None] = s.dx
        k.gravity[None] = s.gravity
        k.friction[None] = s.terrain.friction
        if k.contact_memory:
            k.contact_stiffness[None] = s.terrain.contact_stiffness
            k.contact_damping[None] = s.terrain.contact_damping
        if k.has_flip:
            k.flip_ratio[None] = flip_share(s, self.dt)
        h = height_map(s)
        k.height.from_numpy(h.astype(self.np_real))
        k.normal.from_numpy(normals(h, s.dx).astype(self.np_real))

    def _put(self, field, values: np.ndarray) -> None:
        """Write per-particle values, padded with zeros up to the storage capacity."""
        full = np.zeros((self.layout.capacity,) + values.shape[1:], dtype=values.dtype)
        full[:self.n] = values
        field.from_numpy(full)

    def reset(self, particles: Particles | None = None) -> None:
        """Go back to the initial state, optionally of new particles (which reset C, F and J_p).

        New particles (for the same scene domain and terrain) must have the same count,
        actuators and material models; the CFL time step is recomputed for them. The
        simulator keeps its own copy: later changes to `particles` do not reach it.
        """
        self._check_alive()
        if particles is not None:
            if (particles.n, particles.n_actuators) != (self.n, self.n_actuators) or \
                    not set(particles.material.tolist()) <= set(self.layout.models):
                raise ValueError("reset() needs particles with the same count, actuators and "
                                 "material models as the simulator was built for")
            self._initial_CF = None
            self._initial_jp = self._initial_u = None
            self._use(particles)
        self._changes += 1
        p, r, k = self.particles, self.np_real, self.k
        self._put(k.vol, p.volume.astype(r))
        self._put(k.E, p.youngs_modulus.astype(r))
        self._put(k.nu, p.poisson_ratio.astype(r))
        self._put(k.rho, p.density.astype(r))
        self._put(k.material, p.material.astype(np.int32))
        self._put(k.muscle, (p.muscle if self.n_actuators else np.zeros((self.n, 1))).astype(r))
        self._put(k.fiber, self._unit_fiber.astype(r))
        self._put(k.muscle_ratio, p.muscle_ratio.astype(r))
        wave0, added = self._waves
        self._put(k.wave0, wave0.astype(r))
        self._put(k.wave_added, added.astype(r))
        if k.has_params:
            self._put(k.params, p.params.astype(r))
        self._runs = _model_runs(p.material)
        tracked = p.robot if p.robot.any() else np.ones(self.n, dtype=bool)
        self._probe_density = np.where(tracked, p.density, 0.0)  # mass of particle p = this * volume
        self._put(k.probe_w, self._probe_density.astype(r))
        C0, F0 = self._initial_CF if self._initial_CF is not None else \
            (np.zeros((self.n, 3, 3)), np.tile(np.eye(3), (self.n, 1, 1)))
        k._load_state(0, self.n, *(np.ascontiguousarray(a, dtype=r) for a in (p.x, p.v, C0, F0)))
        if k.has_jp:
            k._load_jp(0, self.n, (np.ones(self.n) if self._initial_jp is None else self._initial_jp).astype(r))
        if k.contact_memory:  # no contact has stuck yet, unless set_initial_state says so
            k._load_u(0, self.n, (np.zeros((self.n, 3)) if self._initial_u is None else self._initial_u).astype(r))
        self.frame = 0
        self.frame_substeps: list[int] = []  # substeps each frame since the reset took
        k.work[None] = 0.0
        self._slot = 0

    def _use(self, particles: Particles) -> None:
        """Take a private copy of `particles` and the CFL time step that they need."""
        timestep = self._time_step(particles)
        self._unit_fiber, self._fiber_length = _unit_fibers(particles.fiber)
        self.particles = replace(particles, **{name: np.array(getattr(particles, name), copy=True)
                                               for name in Particles.__dataclass_fields__})
        self._waves = wave_speeds(self.scene, self.particles)  # once per design, not per reset
        self.timestep = timestep
        self._set_dt(timestep.dt)

    def set_initial_state(self, x=None, v=None, C=None, F=None, Jp=None, u=None) -> None:
        """Replace parts of the initial state (numpy, live particles only) and reset to it.

        Positions and velocities default to the particles'; C to zero, F to identity, the
        plastic volume ratio `Jp` (snow only; all ones is accepted anywhere) to one and the spring
        contact's tangential springs `u` (N, 3) to zero. A faster start gets a smaller time step.
        """
        if Jp is not None and not self.k.has_jp:
            if not np.all(np.asarray(Jp) == 1.0):
                raise ValueError("Jp is state only in scenes with snow")
            Jp = None
        given = {name: np.asarray(value, dtype=np.float64).reshape(self.n, 3)
                 for name, value in (("x", x), ("v", v)) if value is not None}
        if given:  # only positions and velocities enter the particles (and the time step)
            self._use(replace(self.particles, **given))
        if Jp is not None:
            self._initial_jp = np.asarray(Jp, dtype=np.float64).reshape(self.n).copy()
        if u is not None:
            self._initial_u = np.asarray(u, dtype=np.float64).reshape(self.n, 3).copy()
        if C is not None or F is not None:
            C0, F0 = self._initial_CF or (np.zeros((self.n, 3, 3)), np.tile(np.eye(3), (self.n, 1, 1)))
            self._initial_CF = (C0 if C is None else np.asarray(C, dtype=np.float64).reshape(self.n, 3, 3).copy(),
                                F0 if F is None else np.asarray(F, dtype=np.float64).reshape(self.n, 3, 3).copy())
        self.reset()

    def set_design(self, volume=None, youngs_modulus=None, muscle=None, fiber=None) -> None:
        """Overwrite per-particle design fields (numpy) and reset to the initial state.

        The time step is recomputed if anything changed (a stiffer design gets a smaller one). Fibres may have any
        non-zero length: the engine uses their directions, and `backward` returns the gradient
        with respect to the vectors given.
        """
        p = self.particles
        given = {}
        for name, value in (("volume", volume), ("youngs_modulus", youngs_modulus),
                            ("muscle", muscle), ("fiber", fiber)):
            if value is not None:
                value = np.asarray(value, dtype=np.float64)
                if value.shape != getattr(p, name).shape:
                    raise ValueError(f"{name} must have shape {getattr(p, name).shape}, got {value.shape}")
                if not np.array_equal(value, getattr(p, name)):
                    given[name] = value
        if given:  # an unchanged design keeps its particles and time step
            self._use(replace(p, **given))
        self.reset()

    def snapshot(self) -> tuple:
        """Everything a rollout starts from (design, initial state); see `restore`."""
        return self.particles, self._initial_CF, self._initial_jp, self._initial_u

    def restore(self, snapshot: tuple) -> None:
        """Return to a `snapshot`: its design and initial state, with their time step."""
        particles, self._initial_CF, self._initial_jp, self._initial_u = snapshot
        if particles is not self.particles:  # same design: keep its time step (no CFL pass over the particles)
            self._use(particles)
        self.reset()

    def stress(self, action: np.ndarray | None = None) -> np.ndarray:
        """(N, 3, 3) Kirchhoff stress the next substep applies: each particle's model at its trial
        F (plastic models after their return mapping) plus its muscle at `action` (default 0).
        Forward only; the state is unchanged."""
        self._check_alive()
        self._changes += 1  # action row 0 is overwritten
        self._hold(action, 0)
        out = np.zeros((self.n, 3, 3), self.np_real)
        scratch = self._slot + 1 if self._slot + 1 < self.layout.slots else 0
        for model, start, end in self._runs:
            self.k._stress(model, self._slot, scratch, 0, start, end, out)
        return out.astype(np.float64)

    def _hold(self, action, row: int) -> None:
        """Write `action` (default zeros) into action row `row`, checking its shape and bound."""
        if not self.n_actuators:
            return
        a = np.zeros(self.n_actuators) if action is None else np.asarray(action, dtype=np.float64)
        if a.shape != (self.n_actuators,):
            raise ValueError(f"action must have shape ({self.n_actuators},), got {a.shape}")
        self._check_bound(a)
        self.k.act[row] = a.astype(self.np_real)

    def _check_bound(self, actions: np.ndarray) -> None:
        worst = float(np.abs(actions).max(initial=0.0))
        if not worst <= self.scene.max_action * (1 + 1e-6):  # float32 actions at the bound round up
            raise ValueError(f"action {worst:.4g} exceeds scene.max_action = {self.scene.max_action} (the time "
                             "step is sized for it); scale the actions or raise max_action")

    @property
    def alive(self) -> bool:
        """False once closed, or once Taichi was re-initialised (another arch or dtype: a simulator
        of another precision was built) after this one, which took its fields with it."""
        return self.k is not None and self._generation == runtime.generation

    def _check_alive(self) -> None:
        if not self.alive:
            raise RuntimeError("this simulator was closed" if self.k is None else
                               "Taichi was re-initialised (another arch or dtype) after this simulator "
                               "was built; build a new Simulator")

    # ------------------------------------------------------------------ stepping
    def _substep(self, s: int, so: int, t: int, j: int = 0, keep_grid: bool = False) -> None:
        """One substep from slot s into slot so, holding action row t; j: the substep's index within
        its control step (a batch member whose step is larger sits out the last ones). `keep_grid`:
        store the grid for the reverse pass (record s of the segment)."""
        if not keep_grid and not self.k.separate_stress:  # the whole substep in one launch
            self.k._forward_substep(s, so, t, self.n, j, self.scene.grid_region == "full")
            return
        self._grid_update(s, so, t, j)
        if keep_grid:
            self.k._store_grid(s, self._grid_store, self._grid_boxes)
        self.k._g2p(s, so, self.n, j)

    def _grid_update(self, s: int, so: int, t: int, j: int = 0) -> None:
        if self.scene.grid_region == "full":
            for d in range(3):
                self.k.lo[d][None] = 0
                self.k.hi[d][None] = self.k.grid_shape[d]
        else:
            self.k._bounds(s, self.n)
        if not self.k.private_scatter:  # the private grids are left zero by the previous substep's sum
            self.k._clear_grid()
        if self.k.separate_stress:
            self._stress_update(s, so, t, j)
        self.k._p2g(s, so, t, self.n, j)
        if self.k.private_scatter:
            self.k._sum_copies()
        self.k._grid_op()
        if self.k.surface_contact:
            self._surface_contact(s, so)

    def _surface_contact(self, s: int, so: int) -> None:
        """The surface contact's impulses at slot s, from the updated grid and added to it, and the
        spring contact's springs into slot so (contact.py)."""
        if self.k.contact_memory:
            self.k._spring_impulse(s, so, self.n)
        else:
            self.k._contact_impulse(s, self.n)
        self.k._contact_scatter(s, self.n, 1.0)

    def _stress_update(self, s: int, so: int, t: int, j: int = 0) -> None:
        """The stress (muscle included) of substep s, and the plastic models' return-mapped F in slot so."""
        for model, start, end in self._runs:
            if material(model).kind == "hencky":
                self.k._eigen_frames(s, start, end)
            self.k._constitutive_update(model, s, so, t, start, end, j)

    def _substep_grad(self, s: int, t: int, kept: bool) -> None:
        """Reverse of substep s -> s + 1: its grid (kept from the segment's recompute, or recomputed),
        then the adjoint kernels."""
        if kept:
            self.k._replay_grid(s, self._grid_store, self._grid_boxes)  # with the grid update, gradients cleared
            if not self.k.stress_in_adjoint:  # else p2g's adjoint computes the stress itself
                self._stress_update(s, s + 1, t)
            if self.k.surface_contact:
                self.k._contact_flags(s, self.n)
                self._surface_contact(s, s + 1)
        else:
            self._grid_update(s, s + 1, t)
            self.k._clear_grid_grad()
        self.k._g2p_adjoint(s, self.n)
        if self.k.surface_contact:  # the impulses were computed from the grid velocity before their scatter
            self.k._clear_impulse_grad(self.n)
            self.k._contact_scatter.grad(s, self.n, 1.0)
            self.k._contact_scatter(s, self.n, -1.0)
            if self.k.contact_memory:
                self.k._spring_impulse.grad(s, s + 1, self.n)
            else:
                self.k._contact_impulse.grad(s, self.n)
        self.k._grid_op.grad()
        self.k._p2g_adjoint(s, t, self.n)  # with stress_in_adjoint, the stress's adjoint too
        for model, start, end in self._runs:
            if material(model).kind == "hencky":  # the eigenframe algebra by hand, the model's map by Taichi
                self.k._plastic_adjoint_front(model, s, s + 1, t, start, end)
                self.k._spectral_map.grad(model, s, s + 1, start, end)
                self.k._plastic_adjoint_back(model, s, start, end)
            elif material(model).stress_adjoint is not None:  # written by hand (neo-Hookean)
                if not self.k.stress_in_adjoint:  # else p2g's adjoint ran it
                    self.k._elastic_adjoint(model, s, s + 1, t, start, end)
            else:
                self.k._constitutive_update.grad(model, s, s + 1, t, start, end, 0)
                continue
            if self.layout.has_muscles:
                self.k._add_drive_grad(t, start, end)

    def _set_dt(self, dt: float) -> None:
        """The substep the kernels use from now on (written only when it changes)."""
        if getattr(self, "dt", None) != dt:
            self.k.dt[None] = dt
            self.dt = dt
            if self.k.has_flip:
                self.k.flip_ratio[None] = flip_share(self.scene, dt)

    def _substeps_for(self, wave: float, at_rest: TimeStep) -> int:
        """Substeps a frame needs for a state whose fastest wave plus particle speed is `wave`: its CFL
        number may reach ADAPTIVE_CFL_FACTOR x cfl (within the stability limit) before the frame takes
        more than `at_rest`'s (never fewer; a forced dt or adaptive_dt off keeps those)."""
        scene = self.scene
        if not scene.adaptive_dt or scene.dt is not None or not wave > 0:
            return at_rest.substeps
        limit = min(ADAPTIVE_CFL_FACTOR * scene.cfl, MAX_ADAPTIVE_CFL)
        return max(at_rest.substeps, math.ceil(scene.frame_dt * wave / (limit * scene.dx) - 1e-9))

    def _plan_frame(self) -> int:
        """Substeps for the next frame from the state `_check` last looked at; sets their dt."""
        substeps = self._substeps_for(float(self.k.max_wave[None]), self.timestep)
        self._set_dt(self.scene.frame_dt / substeps)
        return substeps

    def _guard(self, slot: int, frame: int) -> None:
        """Stop with a clear error if the state went non-finite, left the grid or broke CFL (the
        `_check` it runs also measures the state for the next frame's `_plan_frame`)."""
        self.k._check(slot, self.n)
        bad = self.k.n_bad[None]
        if bad:
            self._raise_at(self.k.first_bad[None], slot, frame,
                           f"{bad} particle(s) non-finite or outside the domain")
        for speed, dt, where in self._speeds():
            if speed * dt > self.scene.dx:
                raise SimulationError(
                    f"at frame {frame} a particle{where} moves {speed * dt / self.scene.dx:.2f} cells per "
                    f"substep (speed {speed:.4g}): the time step is too large for this motion; lower scene.cfl "
                    "or scene.dt (or leave scene.adaptive_dt on)")

    def _speeds(self) -> list[tuple[float, float, str]]:
        """(fastest particle speed, its time step, where) after `_check`, per independent scene."""
        return [(self.k.max_speed[None], self.dt, "")]

    def _where(self, p: int) -> str:
        """Particle p as the error messages name it."""
        return f"particle {p}"

    def _raise_at(self, p: int, slot: int, frame: int, what: str) -> None:
        body = int(self.particles.body[p])
        model = MODEL_NAMES[int(self.particles.material[p])]
        x = self.particles_state(slot)[0][p]
        raise SimulationError(
            f"{what} at frame {frame}; first: {self._where(p)} "
            f"of body '{self.body_names[body]}' ({model}) at x={np.round(x, 5).tolist()}")

    def step(self, action: np.ndarray | None = None, frames: int = 1) -> None:
        """Advance `frames` control steps holding `action` (K,) over their substeps (no gradients);
        each frame takes the substeps its starting state needs (`scene.adaptive_dt`)."""
        self._check_alive()
        measured = self._measured == (self._changes, self._slot)  # the last step's guard measured this state
        self._changes += 1
        self._hold(action, 0)
        if self._slot > 1:  # after a rollout: continue from its last state
            self.k._copy_slot(self._slot, 0, self.n)
            self._slot = 0
        if not measured:
            self.k._check(self._slot, self.n)
        for _ in range(frames):
            substeps = self._plan_frame()
            for j in range(substeps):
                self._substep(self._slot, 1 - self._slot, 0, j)
                if self.audit_work and self.k.has_muscles:
                    self.k._muscle_work(self._slot, 1 - self._slot, 0, self.n)
                self._slot = 1 - self._slot
            self.frame += 1
            self.frame_substeps.append(substeps)
            self._guard(self._slot, self.frame)
            if self.on_frame is not None:
                self.on_frame(self.positions())
        self._measured = (self._changes, self._slot)

    def particles_state(self, slot: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(x, v, C, F) of the current (or given) slot as numpy arrays."""
        r = self.np_real
        out = (np.empty((self.n, 3), r), np.empty((self.n, 3), r), np.empty((self.n, 3, 3), r),
               np.empty((self.n, 3, 3), r))
        self.k._save_state(self._slot if slot is None else slot, self.n, *out)
        return out

    @property
    def muscle_work(self) -> float:
        """The work the muscles did on the body since the reset, while `audit_work` was on (`step` only)."""
        return float(self.k.work[None])

    def positions(self, slot: int | None = None) -> np.ndarray:
        """(N, 3) positions of the current (or given) slot."""
        x = np.empty((self.n, 3), self.np_real)
        self.k._save_x(self._slot if slot is None else slot, self.n, x)
        return x

    def plastic_volume_ratio(self, slot: int | None = None) -> np.ndarray:
        """Snow's J_p per particle (1 = uncompacted; < 1 compacted, hence hardened); ones without snow."""
        if not self.k.has_jp:
            return np.ones(self.n)
        out = np.empty(self.n, self.np_real)
        self.k._save_jp(self._slot if slot is None else slot, self.n, out)
        tracked = [m for m in self.layout.models if material(m).plastic_volume]
        out[~np.isin(self.particles.material, tracked)] = 1.0  # only snow particles keep J_p up to date
        return out

    def contact_springs(self, slot: int | None = None) -> np.ndarray:
        """(N, 3) the spring contact's tangential springs (each particle's displacement since its
        contact point stuck); zeros with another contact."""
        out = np.zeros((self.n, 3), self.np_real)
        if self.k.contact_memory:
            self.k._save_u(self._slot if slot is None else slot, self.n, out)
        return out

    def _state(self, slot: int) -> tuple[np.ndarray, ...]:
        """Everything a checkpoint must hold: (x, v, C, F), then J_p with snow and the contact's
        springs with the spring contact."""
        return (self.particles_state(slot) + ((self.plastic_volume_ratio(slot),) if self.k.has_jp else ())
                + ((self.contact_springs(slot),) if self.k.contact_memory else ()))

    def _load(self, slot: int, state: tuple[np.ndarray, ...]) -> None:
        """Load a checkpoint (`_state`'s tuple) into `slot`."""
        self.k._load_state(slot, self.n, *state[:4])
        if self.k.has_jp:
            self.k._load_jp(slot, self.n, state[4])
        if self.k.contact_memory:
            self.k._load_u(slot, self.n, state[-1])

    # ------------------------------------------------------------------ differentiable rollout
    def rollout(self, actions: np.ndarray, checkpoint_every: int | None = None, start: State | None = None
                ) -> Rollout:
        """Run len(actions) frames from the initial state (or `start`, a mid-episode state), each
        frame at the substeps its starting state needs, storing checkpoints for `backward`.

        `checkpoint_every` (substeps) may be lowered per rollout, down to 1; it cannot exceed
        the simulator's, which sized the storage.
        """
        self._check_alive()
        if not self.requires_grad:
            raise RuntimeError("rollout() needs Simulator(..., requires_grad=True)")
        S = checkpoint_every or self.segment
        if not 1 <= S <= self.segment:
            raise ValueError(f"checkpoint_every must be in [1, {self.segment}], got {S}")
        actions = np.asarray(actions, dtype=np.float64)
        actions = actions.reshape(len(actions), self.n_actuators) if actions.ndim else actions.reshape(-1, 0)
        T = len(actions)
        if not 1 <= T <= self.max_frames:
            raise ValueError(f"a rollout takes 1 to max_frames={self.max_frames} frames, got {T}")
        self._check_bound(actions)
        self.rollouts += 1  # lets callers (the torch bridge) tell whether backward() is still theirs
        self.reset()
        if start is not None:
            springs = np.zeros((self.n, 3)) if start.u is None else start.u
            self._load(0, tuple(np.ascontiguousarray(a, dtype=self.np_real) for a in
                                (start.x, start.v, start.C, start.F, start.Jp, springs)))
        act = np.zeros((self.max_frames + 1, max(self.n_actuators, 1)))
        act[:T, :self.n_actuators] = actions
        self.k.act.from_numpy(act.astype(self.np_real))
        self.k.com_x.fill(0)
        self.k.com_v.fill(0)
        tracked = self._probe_density > 0
        x0 = (self.particles.x if start is None else start.x)[tracked]
        origin = (0.5 * (x0.min(0) + x0.max(0))).astype(self.np_real)  # near the body: any fixed point will do
        self.k.probe_origin[None] = origin
        self._probe_origin = origin.astype(np.float64)
        self._T = T
        self._checkpoints.clear()
        self._checkpoints.memory_bytes = CHECKPOINT_MEMORY_BYTES  # read per rollout, as GRID_STORE_BYTES is
        self._prepare_grid_store()
        self.k._probe(0, 0, self.n)
        self.k._check(0, self.n)
        # the substeps of each frame follow its starting state; the backward pass replays them
        self._substep_frame: list[int] = []  # frame (action row) of every substep
        self._segment_starts: list[int] = []  # the substep each segment starts at
        s = L = 0  # slot within the segment, and the segment's length
        keep = False  # whether this segment keeps its grids
        for t in range(T):
            substeps = self._plan_frame()
            self.frame_substeps.append(substeps)
            for j in range(substeps):
                if s == L:  # a new segment: checkpoint its first state
                    if self._checkpoints:
                        self.k._copy_slot(L, 0, self.n)
                    self._checkpoints.append(self._state(0))
                    self._segment_starts.append(len(self._substep_frame))
                    s = 0
                    # segments end with the episode (as far as this frame's step foretells it): the
                    # first is the shortest, and the last, which backward need not recompute as it is
                    # still in the slots, is a whole one; it keeps its grids too
                    remaining = (substeps - j) + (T - 1 - t) * substeps
                    keep = remaining <= S
                    L = S if keep else (remaining - 1) % S + 1
                self._substep(s, s + 1, t, keep_grid=keep)
                self._substep_frame.append(t)
                s += 1
            self.k._probe(s, t + 1, self.n)
            self._guard(s, t + 1)
            if self.on_frame is not None:
                self.on_frame(self.positions(s))
        self._slot = s
        self._segment_in_slots = len(self._checkpoints) - 1 if keep else None  # backward need not recompute it
        self._final = self._state(self._slot)  # where backward() leaves the simulator
        final = State(*(a.astype(np.float64) for a in (*self._final[:4], self.plastic_volume_ratio(self._slot),
                                                       self.contact_springs(self._slot))))
        self._rollout_changes = self._changes
        self.frame = T
        self._tracked_mass = float(self._probe_density @ self.particles.volume)
        self._com = (self.k.com_x.to_numpy()[:T + 1] / self._tracked_mass + self._probe_origin,
                     self.k.com_v.to_numpy()[:T + 1] / self._tracked_mass)
        return Rollout(self._com[0].astype(np.float64), self._com[1].astype(np.float64), final.x, final.v, final)

    def _prepare_grid_store(self) -> None:
        """Records for a segment's grids (momentum and mass, with FLIP the momentum before forces, over
        the touched box), sized at twice the volume of the particles' box now, within
        GRID_STORE_BYTES; a substep whose box outgrows its record is recomputed in the reverse pass
        instead. None with a full grid region."""
        nodes = 0
        if self.scene.grid_region != "full":
            self.k._bounds(0, self.n)
            volume = math.prod(self.k.hi[d][None] - self.k.lo[d][None] for d in range(3))
            nodes = min(max(int(GRID_STORE_MARGIN * volume), self._largest_box),
                        GRID_STORE_BYTES // (self.segment * self.k.part_width * np.dtype(self.np_real).itemsize))
        shape = (self.segment, max(nodes, 1), self.k.part_width)
        if self._grid_store is None or self._grid_store.shape != shape:
            self._grid_store = runtime.ndarray(ti.f64 if self.np_real is np.float64 else ti.f32, shape)
            self._grid_boxes = runtime.ndarray(ti.i32, (self.segment, 7))

    @property
    def rollout_is_current(self) -> bool:
        """True while nothing changed the simulator since the last rollout, so backward() may run."""
        return self._changes == self._rollout_changes

    def backward(self, com_x=None, com_v=None, x=None, v=None, C=None, F=None, Jp=None, u=None) -> Gradients:
        """Back-propagate d loss / d outputs of the last `rollout` to its inputs (repeatable).

        `com_x`, `com_v` (T+1, 3) and the final particles' `x`, `v` (N, 3), `C`, `F` (N, 3, 3)
        `Jp` (N,) and the contact's springs `u` (N, 3) are the loss's gradients with respect to those outputs
        (None: zero). Each segment is
        recomputed from its checkpoint, then differentiated substep by substep in reverse; the
        gradient of a segment's first state carries into the previous one.
        """
        self._check_alive()
        if not self._checkpoints:
            raise RuntimeError("backward() needs a preceding rollout()")
        if not self.rollout_is_current:
            raise RuntimeError("the simulator changed since the last rollout() (step, reset, set_design, "
                               "set_initial_state or stress overwrite what backward() replays); run rollout() again")
        T, n, r = self._T, self.n, self.np_real
        frame_of, substeps = self._substep_frame, self.frame_substeps
        for f in (self.k.vol, self.k.E, self.k.muscle, self.k.fiber, self.k.act, self.k.com_x, self.k.com_v):
            f.grad.fill(0)
        # com = S / M (+ the probe's origin for com_x) with S the probe's mass-weighted sum and M the
        # tracked mass: dL/dS = g / M goes through the probe kernel, dL/dM = -sum(g . S / M) / M is added below
        rows, M = self.max_frames + 1, self._tracked_mass
        dL_dM = 0.0
        for field, g, com in ((self.k.com_x, com_x, self._com[0] - self._probe_origin), (self.k.com_v, com_v, self._com[1])):
            full = np.zeros((rows, 3), r)
            if g is not None:
                g = np.asarray(g, dtype=np.float64).reshape(T + 1, 3)
                full[:T + 1] = g / M
                dL_dM -= float((g * com).sum()) / M
            field.grad.from_numpy(full)
        def seed(g, shape):
            return np.ascontiguousarray(np.zeros(shape) if g is None else np.reshape(g, shape), dtype=r)

        carry = (seed(x, (n, 3)), seed(v, (n, 3)), seed(C, (n, 3, 3)), seed(F, (n, 3, 3)), seed(Jp, (n,)),
                 seed(u, (n, 3)))
        total = len(frame_of)
        last_of_frame = set(np.cumsum(substeps) - 1)  # substeps after which a frame's probe ran
        starts = self._segment_starts
        self.recomputed_substeps = 0
        for k in reversed(range(len(starts))):
            g0 = starts[k]
            L = (starts[k + 1] if k + 1 < len(starts) else total) - g0
            if self._segment_in_slots != k:  # recompute the segment's states, keeping their grids
                self._load(0, self._checkpoints[k])
                for s in range(L):
                    self._set_dt(self.scene.frame_dt / substeps[frame_of[g0 + s]])
                    self._substep(s, s + 1, frame_of[g0 + s], keep_grid=True)
                self._segment_in_slots = k
                self.recomputed_substeps += L
            boxes = self._grid_boxes.to_numpy()[:L]
            kept = boxes[:, 6] == 1
            self._largest_box = max(self._largest_box, int(np.prod(boxes[:, 3:6] - boxes[:, :3], axis=1).max()))
            self.k._set_grad(L, n, *carry[:4])
            if self.k.has_jp:
                self.k._set_jp_grad(L, n, carry[4])
            if self.k.contact_memory:
                self.k._set_u_grad(L, n, carry[5])
            for s in reversed(range(L)):
                g = g0 + s
                t = frame_of[g]
                if g in last_of_frame:
                    self.k._probe.grad(s + 1, t + 1, n)
                self._set_dt(self.scene.frame_dt / substeps[t])
                self._substep_grad(s, t, bool(kept[s]))
            if g0 == 0:
                self.k._probe.grad(0, 0, n)
            carry = (np.empty((n, 3), r), np.empty((n, 3), r), np.empty((n, 3, 3), r), np.empty((n, 3, 3), r),
                     np.zeros(n, r), np.zeros((n, 3), r))
            self.k._save_grad(0, n, *carry[:4])
            if self.k.has_jp:
                self.k._save_jp_grad(0, n, carry[4])
            if self.k.contact_memory:
                self.k._save_u_grad(0, n, carry[5])
        if self._segment_in_slots != len(starts) - 1:  # the slots hold an earlier segment's recompute:
            self._load(0, self._final)  # continue (step, particles_state, stress) from the rollout's end
            self._slot, self._segment_in_slots = 0, None
        K = self.n_actuators
        fiber = self.k.fiber.grad.to_numpy()[:n].astype(np.float64)
        unit = self._unit_fiber
        grads = Gradients(
            actions=self.k.act.grad.to_numpy()[:T, :K].astype(np.float64),
            volume=self.k.vol.grad.to_numpy()[:n].astype(np.float64) + dL_dM * self._probe_density,
            youngs_modulus=self.k.E.grad.to_numpy()[:n].astype(np.float64),
            muscle=self.k.muscle.grad.to_numpy()[:n, :K].astype(np.float64),
            # the engine used f / |f|: project out the radial part and divide by |f|
            fiber=(fiber - (fiber * unit).sum(1, keepdims=True) * unit) / self._fiber_length[:, None],
            x0=carry[0].astype(np.float64), v0=carry[1].astype(np.float64), C0=carry[2].astype(np.float64),
            F0=carry[3].astype(np.float64), Jp0=carry[4].astype(np.float64),
            u0=carry[5].astype(np.float64) if self.k.contact_memory else None)
        for name, value in vars(grads).items():
            if value is not None and not np.isfinite(value).all():
                raise SimulationError(f"the backward pass produced non-finite gradients for {name}")
        return grads
