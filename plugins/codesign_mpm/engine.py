"""Differentiable 3-D MLS-MPM (APIC, quadratic B-splines) in Taichi.

One substep is four kernels, each close to its equation:

    bounds   -> the box of grid nodes the particles touch (only those are cleared and updated)
    p2g      -> F <- (I + dt C) F; Kirchhoff stress (elastic model + muscle); scatter m v and
                the MLS force/affine term to 27 nodes. Scenes with non-elastic materials and
                differentiable layouts first run one small kernel per material run
                (`_constitutive_update`: return mapping, stress, muscle), and p2g only scatters
    grid_op  -> v = p / m + dt g; terrain (height-map SDF, Coulomb friction); domain walls
    g2p      -> gather v and C; x <- x + dt v; with `scene.flip` > 0 (opt-in) an elastic body's
                particle keeps that share of its own velocity plus the grid's change (FLIP)

Why FLIP (opt-in): APIC hands each particle the grid's velocity, which keeps the particles' affine
motion and filters away the rest, at every substep: a damping whose rate is the number of
substeps per second. A robot on terrain, whose velocity near a stuck contact is not affine
within a cell, lost its progress as the step shrank (docs/contact.md sections 8-10). With the
FLIP share, a particle keeps its own velocity and adds the grid's change over the substep,
`v_p' = V_p + flip (v_p - V_p^old)` (V_p: the grid's new velocity at p, V_p^old: the grid's
velocity before forces, both gathered with p's weights); positions move with the grid (V_p),
as F does, so the deformation stays that of the grid's field. Not the default: a robot dropped
onto the ground at 8 units/s gains energy with it (docs/contact.md section 10).

Scatters without atomics: on a CPU a float atomic add is a compare-and-swap loop, and p2g's
108 of them per particle bound the whole substep. There, each thread scatters its chunk of
particles into a private grid with plain adds (`grid_part`) and `_sum_copies` adds the copies
(and leaves them zero for the next substep); g2p's adjoint scatters the same way. On a GPU,
whose atomic adds are native, both scatter into the grid directly.

Particle state lives in `slots`: two (ping-pong) for plain simulation, or S + 1 for a
differentiable segment of S substeps. A differentiable rollout stores the state only at
segment starts (checkpoints) and recomputes each segment in the backward pass, so memory
grows with T/S + S rather than T substeps. That recompute keeps each substep's grid (the touched
box, `_store_grid`) for the reverse pass, which then runs only the stress and grid_op again.

Adjoints: p2g's and g2p's are written by hand (`_p2g_adjoint`, a gather; `_g2p_adjoint`, a
scatter, private per thread as p2g's) and checked against finite differences by the gradient
tests. Taichi's reverse mode of the 27-node stencils compiled for minutes (its passes grow with
a kernel's statements squared) and scattered with atomic adds; hand-written, they compile as
forward kernels. The plastic models' return mapping is split the same way: its eigenframe
algebra (3x3 products, which Taichi's reverse mode took over a minute to compile) has a
hand-written adjoint (`_plastic_adjoint_front/back`), and Taichi differentiates only each model's
small map of principal values (`_spectral_map`). The neo-Hookean stress (the robots' default,
muscle included) has one too (`_neo_hookean_adjoint`). Taichi differentiates the rest: the other
elastic models' and water's stresses (their own kernel in differentiable layouts), grid_op and
the probe.

Only what the scene uses is compiled: the material models present (their return mappings,
the plastic volume ratio J_p of snow), the muscle term when the scene has actuators, the
terrain projection when there is terrain (`ti.static`).

Plastic models (sand, snow, clay, mud) work in principal Hencky strain of b = F F^T. Its
eigenvectors Q0 come from a forward-only Jacobi solver (`_eigen_frames`) and are a constant
of the differentiable kernel: in that frame A = Q0^T b Q0 is diagonal up to round-off, and
an isotropic function G(b) = sum_i g(lambda_i) n_i n_i^T (the stress, the projection's
scale) is, to first order in A's off-diagonal entries,

    G = Q0 (diag g(a) + A_pq [g]_pq) Q0^T,   [g]_pq = (g_q - g_p) / (a_q - a_p),

the Daleckii-Krein form of its derivative. The divided difference is written branch-free as
((g_q - g_p) d + g'_pq eps^2) / (d^2 + eps^2) with d = a_q - a_p and g'_pq the slope at
coincidence (`_divided`), so the adjoint keeps its full shear stiffness where eigenvalues
coincide: at rest, and in layers loaded by gravity alone.
"""
# (no `from __future__ import annotations`: Taichi reads kernel annotations at runtime)

import math
import weakref
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import taichi as ti
from taichi.lang import impl

from codesign_mpm import runtime
from codesign_mpm.checkpoints import CheckpointStore
from codesign_mpm.materials import (ID, MATERIALS, MAX_ACTIVE_STRESS_RATIO, MIN_HARDENING, N_PARAMS, active_stress_ratio,
                                    max_stiffness_ratio, model_wave_speed, muscle_modulus, viscosity)
from codesign_mpm.sampling import Particles
from codesign_mpm.scene import Scene, SceneError, validate_scene
from codesign_mpm.terrain import height_map, normals

MODEL_NAMES = {m.id: m.name for m in MATERIALS.values()}
J_MIN = 0.1  # below this, neo-Hookean log(J) continues linearly (finite for J <= 0)
# a particle compressed below this volume ratio takes APIC's velocity alone, whatever the FLIP share:
# crushed bodies (a drop faster than the body's wave speed, J -> 0.01) otherwise gain energy
# (docs/contact.md section 11); locomotion stays above J = 0.5
J_FLIP = 0.5
MASS_EPS = 1e-12  # grid nodes lighter than this are treated as empty
CAPACITY_STEP = 1024  # particle storage is allocated in these steps so similar scenes share kernels
JACOBI_SWEEPS = 4  # at most this many cyclic sweeps of the 3x3 eigen-solver (b = F F^T stays near I)
JACOBI_TOL_ULPS = 64
"""Jacobi stops once b's off-diagonal is below this many round-offs of its trace (7.6e-6 in float32):
`_plastic` takes what is left to first order. Most particles of a settled cover then need no sweep
(desert, paper scale: the eigen-solve 11.7 -> 2.2 ms per substep). Over 10 frames of each cover the
trajectories moved from the full sweeps' by 1/5 to 1/15 of float32's own error (its rms distance from
float64); in the desert a bound of 3e-5 moved them by up to 0.7 of it, 1e-4 by 3 to 10 times it."""
HENCKY_PLASTIC = (ID["sand"], ID["snow"], ID["clay"], ID["mud"])  # models with a return mapping in log strain
FLIP_MODELS = tuple(m.id for m in MATERIALS.values() if not m.plastic)  # the elastic bodies: scene.flip applies to them
JACOBI_EPS = 1e-6  # eigenvalue gaps below this count as coincident (the scale of b's round-off in float32)
ADAPTIVE_CFL_FACTOR = 2.0
"""A frame takes more substeps than at rest once its state's CFL number (particle speed plus the
stretch-stiffened wave speed, `_wave_speed`) would exceed this many times scene.cfl: a guard against
instability, not a finer accuracy target (at 1x, the quick start's gait took 32% more substeps; at 2x,
none, while the stability cases that blew up at the rest step run finite)."""
MAX_ADAPTIVE_CFL = 0.8  # nor above this CFL number, whatever scene.cfl (measured stable in docs/stability.md)
MAX_FREE_STORAGES = 4  # compiled storages kept for reuse after their simulators close; older ones are freed
MAX_DEAD_STORAGES = 32  # freed storages (their kernels stay compiled) before an idle program is recycled
DRIVE_CHUNK = 256  # particles whose action gradients one thread adds up before its one atomic add
GRID_STORE_BYTES = 256 * 1024**2  # at most this much keeps a segment's grids for the reverse pass
GRID_STORE_MARGIN = 2.0  # a rollout's grid records hold this times the particles' box at its start (or the largest seen)
CHECKPOINT_MEMORY_BYTES = 128 * 1024**2  # a rollout's checkpoints beyond this go to a temporary file
NORM_FLOOR = 1e-30  # |dev eps|^2 below this is treated as this (only reached where the result is masked off)


def _plane(p: int, q: int) -> tuple:
    """(p, q, D, S): a rotation in the (p, q) plane is I + (c - 1) D + s S."""
    D = [[float(i == j and i in (p, q)) for j in range(3)] for i in range(3)]
    S = [[float(i == p and j == q) - float(i == q and j == p) for j in range(3)] for i in range(3)]
    return p, q, D, S


JACOBI_PLANES = (_plane(0, 1), _plane(0, 2), _plane(1, 2))  # rotation regulariser: |d tan(theta) / d b| <= 2 / JACOBI_EPS at repeated eigenvalues


class SimulationError(RuntimeError):
    """The state went non-finite or left the domain; the message says where and when."""


@dataclass(frozen=True)
class TimeStep:
    dt: float  # the substep actually used
    substeps: int  # per frame (control step), exact: substeps * dt == frame_dt
    stable_dt: float  # the CFL bound for this scene


def wave_speeds(scene: Scene, particles: Particles) -> tuple[np.ndarray, np.ndarray]:
    """(N,) fastest wave speed of each particle at rest, and (N,) the axial modulus its muscle adds
    (`materials.muscle_modulus`; 0 without muscle membership), computed once per distinct material."""
    actuated = (np.abs(particles.muscle).sum(1) > 0) & (particles.muscle_ratio > 0)
    added = np.where(actuated, muscle_modulus(scene.muscle_model, particles.muscle_ratio * particles.youngs_modulus,
                                              scene.max_action), 0.0)
    table = np.column_stack([particles.material, particles.youngs_modulus, particles.poisson_ratio,
                             particles.density, added, particles.params])
    kinds, of_particle = np.unique(table, axis=0, return_inverse=True)  # distinct materials
    speeds = np.array([model_wave_speed(int(row[0]), *row[1:5], tuple(row[5:])) for row in kinds])
    return speeds[of_particle.reshape(-1)], added


def time_step(scene: Scene, particles: Particles) -> TimeStep:
    """Substep from the CFL condition with the stiffest material and fastest initial speed.

    dt <= cfl * dx / (c_p + |v|max), c_p = sqrt((lambda + 2 mu + m) / rho) with m what the
    scene's muscle model adds to the axial modulus (`materials.muscle_modulus`; particles
    without muscle membership add nothing), water's sqrt(K / rho), snow's speed at its largest
    hardening; for viscous materials also the explicit diffusion limit dt <= cfl * rho dx^2 /
    (6 eta). A forced `dt` above that bound is refused unless `allow_unstable_dt` is set.

    This is the step at rest; with `scene.adaptive_dt` each frame takes at least as many substeps
    as its current state needs (`Simulator`: speeds and stretch-dependent stiffness).
    """
    actuated = (np.abs(particles.muscle).sum(1) > 0) & (particles.muscle_ratio > 0)
    if scene.muscle_model == "active":
        _check_muscle_stability(scene, particles, actuated)
    speeds, _ = wave_speeds(scene, particles)
    fastest = float(speeds.max(initial=0.0))
    vmax = float(np.linalg.norm(particles.v, axis=1).max(initial=0.0))
    stable = scene.cfl * scene.dx / (fastest + vmax)
    for row in np.unique(np.column_stack([particles.material, particles.density, particles.params]), axis=0):
        eta = viscosity(int(row[0]), tuple(row[2:]))
        if eta > 0:
            stable = min(stable, scene.cfl * row[1] * scene.dx ** 2 / (6 * eta))
    target = stable
    if scene.dt is not None:
        if scene.dt > stable and not scene.allow_unstable_dt:
            raise SceneError(
                f"dt = {scene.dt!r} is invalid: the CFL bound for this scene is {stable:.4g} "
                f"(cfl {scene.cfl}, dx {scene.dx:.4g}, wave speed {fastest:.4g}, speed {vmax:.4g}); "
                "use a smaller dt, leave dt null, or set allow_unstable_dt: true")
        target = scene.dt
    substeps = max(1, math.ceil(scene.frame_dt / target - 1e-9))
    return TimeStep(scene.frame_dt / substeps, substeps, stable)


def _check_muscle_stability(scene: Scene, particles: Particles, actuated: np.ndarray) -> None:
    """Refuse active muscles stronger than the material can carry (`materials.MAX_ACTIVE_STRESS_RATIO`):
    s max_action above that fraction of the shear modulus stretches fibres without bound near
    s max_action = mu, and tears thin bodies (numerical fracture) well before it."""
    ratio = active_stress_ratio(particles.muscle_ratio, scene.max_action, particles.poisson_ratio)
    bad = np.flatnonzero(actuated & (ratio > MAX_ACTIVE_STRESS_RATIO * (1 + 1e-9)))
    if len(bad):
        p = bad[0]
        raise SceneError(
            f"muscles.stiffness_ratio = {particles.muscle_ratio[p]:.4g} is invalid with max_action = "
            f"{scene.max_action!r} for body {int(particles.body[p])}: at the bound the active stress is "
            f"{ratio[p]:.3g} x the shear modulus; admissible: <= {MAX_ACTIVE_STRESS_RATIO}, i.e. stiffness_ratio <= "
            f"{max_stiffness_ratio(scene.max_action, particles.poisson_ratio[p]):.4g} for Poisson's ratio "
            f"{particles.poisson_ratio[p]:.4g} (or a smaller max_action)")


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


@dataclass
class State:
    """The particle state between two frames: what a rollout may start from and ends in."""

    x: np.ndarray  # (N, 3)
    v: np.ndarray  # (N, 3)
    C: np.ndarray  # (N, 3, 3)
    F: np.ndarray  # (N, 3, 3)
    Jp: np.ndarray  # (N,) snow's plastic volume ratio (ones elsewhere)


@dataclass
class Rollout:
    """What a differentiable rollout returns: robot centre of mass per frame, final particles."""

    com_x: np.ndarray  # (T+1, 3), frame 0 is the initial state
    com_v: np.ndarray  # (T+1, 3)
    x: np.ndarray  # (N, 3) after T frames
    v: np.ndarray  # (N, 3)
    final: State  # the whole state after T frames (float64)


@dataclass(frozen=True)
class Layout:
    """Everything the compiled kernels depend on. Simulators with equal layouts share them."""

    capacity: int  # particle slots (the live count is a kernel argument)
    n_actuators: int
    slots: int  # particle states kept: 2 (ping-pong) or segment + 1 (differentiable)
    rows: int  # action / probe rows: max_frames + 1
    grid_shape: tuple[int, int, int]
    models: tuple[int, ...]  # material models compiled in (ids of materials.MATERIALS)
    has_muscles: bool
    muscle_model: str
    has_terrain: bool
    boundary_cells: int
    requires_grad: bool
    scatter_copies: int = 1  # private grids p2g scatters into without atomics (runtime.scatter_copies)
    members: int = 1  # scenes simulated side by side (codesign_mpm.batch); 1: a plain simulator
    has_flip: bool = False  # FLIP's share in the elastic bodies' velocity update (scene.flip > 0)


@ti.data_oriented
class _Storage:
    """Taichi fields and kernels for one layout.

    Taichi compiles kernels per set of fields, so a fresh storage costs a compile (about 3 s
    forward, about 2 minutes for the backward kernels on 2 CPU cores when the offline cache is
    cold). Storages are therefore pooled by layout and handed to the next simulator that needs
    the same one (see `_acquire`). Their fields live in one SNode tree of their own, so a
    storage evicted from the pool gives its memory back (`free`).
    """

    def __init__(self, layout: Layout) -> None:
        self.layout = layout
        self.grid_shape = layout.grid_shape
        self.models = layout.models
        self.has_params = any(MATERIALS[MODEL_NAMES[m]].plastic for m in layout.models)
        # the stress in kernels of its own ahead of p2g: plastic models (one small kernel per model
        # compiles far faster than all of them fused into the scatter) and every differentiable
        # layout (p2g's adjoint is then the scatter's alone, differentiated plane by plane)
        self.separate_stress = self.has_params or layout.requires_grad
        self.has_jp = ID["snow"] in layout.models  # snow's plastic volume ratio is part of the state
        self.jacobi_tol = JACOBI_TOL_ULPS * float(np.finfo(np.float64 if impl.current_cfg().default_fp == ti.f64
                                                           else np.float32).eps)
        self.has_muscles = layout.has_muscles
        self.muscle_model = layout.muscle_model
        self.has_terrain = layout.has_terrain
        self.boundary_cells = layout.boundary_cells
        self.members = layout.members
        self.batched = layout.members > 1
        self.copies = layout.scatter_copies
        self.private_scatter = layout.scatter_copies > 1
        self.has_flip = layout.has_flip
        # a private grid node: momentum, mass (and with FLIP the momentum before forces)
        self.part_width = 7 if layout.has_flip else 4
        # a batch's member grids lie side by side along x: member b owns nodes [b nx, (b + 1) nx)
        self.grid_total = (layout.grid_shape[0] * layout.members,) + tuple(layout.grid_shape[1:])
        n, K, gs, grad = layout.capacity, max(layout.n_actuators, 1), layout.grid_shape, layout.requires_grad
        slots, rows = layout.slots, layout.rows
        builder = ti.FieldsBuilder()

        def placed(make, shape, differentiable=False):
            """A field of `shape` in this storage's tree (with its gradient if asked and grad is on)."""
            f = make(needs_grad=grad and differentiable)
            node = builder.dense(ti.axes(*range(len(shape))), shape) if shape else builder
            node.place(f, f.grad) if grad and differentiable else node.place(f)
            return f

        def vec(k, shape, differentiable=False):
            return placed(lambda **kw: ti.Vector.field(k, float, **kw), shape, differentiable)

        def mat(shape, differentiable=False):
            return placed(lambda **kw: ti.Matrix.field(3, 3, float, **kw), shape, differentiable)

        def scalar(shape, differentiable=False, dtype=float):
            return placed(lambda **kw: ti.field(dtype, **kw), shape, differentiable)

        self.x = vec(3, (slots, n), True)
        self.v = vec(3, (slots, n), True)
        self.C = mat((slots, n), True)
        self.F = mat((slots, n), True)
        self.vol = scalar((n,), True)
        self.E = scalar((n,), True)
        self.nu = scalar((n,))
        self.rho = scalar((n,))
        self.material = scalar((n,), dtype=ti.i32)
        self.muscle = vec(K, (n,), True)
        self.fiber = vec(3, (n,), True)
        self.muscle_ratio = scalar((n,))
        self.drive_bar = scalar((n,))  # d loss / d activation of each particle's muscle (the hand adjoints)
        self.probe_w = scalar((n,))
        self.act = vec(K, (rows,), True)
        self.com_x = vec(3, (rows,), True)
        self.com_v = vec(3, (rows,), True)
        self.grid_v_in = vec(3, self.grid_total, True)
        self.grid_m = scalar(self.grid_total, True)
        self.grid_v_out = vec(3, self.grid_total, True)
        if self.private_scatter:  # p2g's chunk c of the particles scatters into copy c; _sum_copies adds them
            self.grid_part = vec(self.part_width, (self.copies,) + self.grid_total)
        self.height = scalar((gs[0], gs[2]))
        self.normal = vec(3, (gs[0], gs[2]))
        # the node box touched by particles; scalar fields so the reduction stays thread-local
        self.lo = [scalar((), dtype=ti.i32) for _ in range(3)]
        self.hi = [scalar((), dtype=ti.i32) for _ in range(3)]
        self.dt = scalar(())
        self.dx = scalar(())
        self.gravity = vec(3, ())
        self.friction = scalar(())
        self.n_bad = scalar((), dtype=ti.i32)
        self.first_bad = scalar((), dtype=ti.i32)
        self.max_speed = scalar(())
        self.wave0 = scalar((n,))  # wave speed at rest (materials.model_wave_speed)
        self.wave_added = scalar((n,))  # the axial modulus the muscle adds at rest
        self.max_wave = scalar(())  # the largest wave speed plus particle speed of the current state
        self.work = scalar(())  # the muscles' work since the reset (`Simulator.audit_work`)
        if self.has_params:  # every non-elastic scene gets the same fields, so they share compiled kernels
            self.params = vec(N_PARAMS, (n,))
        if self.separate_stress:
            self.tau = mat((n,), True)  # stress of the current substep, muscle included
        if self.has_params:
            self.frame = mat((n,))  # eigenvectors of b (no gradient)
            self.Jp = scalar((slots, n), True)  # snow's plastic volume ratio
        if self.has_params and grad:  # the plastic adjoint's hand-written and Taichi-differentiated parts meet here
            self.strain = vec(3, (n,), True)  # b's principal values a, the input of _spectral_map
            self.spectral = vec(12, (n,), True)  # its outputs (g, g', k, k')
            self.F_bar_part = mat((n,))  # F's gradient from the eigenframe algebra, less the part through A
            self.A_off_bar = vec(3, (n,))  # the gradient of A's off-diagonal (01, 02, 12)
        if self.batched:  # last, so the fields above keep the ids (and cached kernels) of a plain layout
            self.member = scalar((n,), dtype=ti.i32)  # which member each particle belongs to
            self.member_dt = scalar((layout.members,))
            self.member_substeps = scalar((layout.members,), dtype=ti.i32)  # per control step
            self.member_speed = scalar((layout.members,))
            self.member_wave = scalar((layout.members,))
        if self.has_flip:  # last, as the batch's fields
            self.grid_q = vec(3, self.grid_total, True)  # momentum before forces: sum w m (v + C (x_i - x_p))
            self.grid_v_old = vec(3, self.grid_total, True)  # its velocity, grid_q / m (grid_op)
            self.flip_ratio = scalar(())
        self._tree = builder.finalize()

    def free(self) -> None:
        """Give the fields' memory back; the storage is unusable afterwards."""
        self._tree.destroy()

    @ti.kernel
    def _load_state(self, s: ti.i32, n: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(),
                    C: ti.types.ndarray(), F: ti.types.ndarray()):
        for p in range(n):
            for i in ti.static(range(3)):
                self.x[s, p][i] = x[p, i]
                self.v[s, p][i] = v[p, i]
                for j in ti.static(range(3)):
                    self.C[s, p][i, j] = C[p, i, j]
                    self.F[s, p][i, j] = F[p, i, j]

    @ti.kernel
    def _save_state(self, s: ti.i32, n: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(),
                    C: ti.types.ndarray(), F: ti.types.ndarray()):
        for p in range(n):
            for i in ti.static(range(3)):
                x[p, i] = self.x[s, p][i]
                v[p, i] = self.v[s, p][i]
                for j in ti.static(range(3)):
                    C[p, i, j] = self.C[s, p][i, j]
                    F[p, i, j] = self.F[s, p][i, j]

    @ti.kernel
    def _save_x(self, s: ti.i32, n: ti.i32, x: ti.types.ndarray()):
        for p in range(n):
            for i in ti.static(range(3)):
                x[p, i] = self.x[s, p][i]

    @ti.kernel
    def _save_grad(self, s: ti.i32, n: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(),
                   C: ti.types.ndarray(), F: ti.types.ndarray()):
        for p in range(n):
            for i in ti.static(range(3)):
                x[p, i] = self.x.grad[s, p][i]
                v[p, i] = self.v.grad[s, p][i]
                for j in ti.static(range(3)):
                    C[p, i, j] = self.C.grad[s, p][i, j]
                    F[p, i, j] = self.F.grad[s, p][i, j]

    @ti.kernel
    def _add_grad(self, s: ti.i32, n: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(),
                  C: ti.types.ndarray(), F: ti.types.ndarray()):
        for p in range(n):
            for i in ti.static(range(3)):
                self.x.grad[s, p][i] += x[p, i]
                self.v.grad[s, p][i] += v[p, i]
                for j in ti.static(range(3)):
                    self.C.grad[s, p][i, j] += C[p, i, j]
                    self.F.grad[s, p][i, j] += F[p, i, j]

    @ti.kernel
    def _load_jp(self, s: ti.i32, n: ti.i32, jp: ti.types.ndarray()):
        for p in range(n):
            self.Jp[s, p] = jp[p]

    @ti.kernel
    def _save_jp(self, s: ti.i32, n: ti.i32, jp: ti.types.ndarray()):
        for p in range(n):
            jp[p] = self.Jp[s, p]

    @ti.kernel
    def _save_jp_grad(self, s: ti.i32, n: ti.i32, jp: ti.types.ndarray()):
        for p in range(n):
            jp[p] = self.Jp.grad[s, p]

    @ti.kernel
    def _add_jp_grad(self, s: ti.i32, n: ti.i32, jp: ti.types.ndarray()):
        for p in range(n):
            self.Jp.grad[s, p] += jp[p]

    @ti.func
    def _base(self, xp):
        """Lowest of the 27 nodes a particle touches, clamped inside the grid."""
        hi = ti.Vector([self.grid_shape[0] - 3, self.grid_shape[1] - 3, self.grid_shape[2] - 3])
        return ti.min(ti.max(ti.cast(xp / self.dx[None] - 0.5, ti.i32), 0), hi)

    @ti.func
    def _offset(self, p):
        """Where particle p's grid starts in the grid fields: member b's nodes are shifted b nx along x."""
        offset = ti.Vector([0, 0, 0])
        if ti.static(self.batched):
            offset[0] = self.member[p] * self.grid_shape[0]
        return offset

    @ti.func
    def _dt(self, p):
        """Particle p's time step: its member's in a batch (members keep their own CFL step)."""
        dt = self.dt[None]
        if ti.static(self.batched):
            dt = self.member_dt[self.member[p]]
        return dt

    @ti.func
    def _active(self, p, j):
        """Whether particle p takes substep j of the control step: a batch runs as many substeps as
        its most demanding member, and a member with a larger step sits out the last ones."""
        return j < self.member_substeps[self.member[p]]

    @ti.kernel
    def _bounds(self, s: ti.i32, n: ti.i32):
        """The node box the particles touch, in their own scene's grid coordinates: a batch's grid
        kernels visit that box in every member's grid, not the span of all members."""
        for d in ti.static(range(3)):
            self.lo[d][None] = self.grid_shape[d]
            self.hi[d][None] = 0
        for p in range(n):
            base = self._base(self.x[s, p])
            for d in ti.static(range(3)):
                ti.atomic_min(self.lo[d][None], base[d])
                ti.atomic_max(self.hi[d][None], base[d] + 3)

    @ti.func
    def _elastic_stress(self, model: ti.template(), F, mu, la):
        """Kirchhoff stress tau = P F^T of one elastic model."""
        I = ti.Matrix.identity(float, 3)
        J = F.determinant()
        tau = ti.Matrix.zero(float, 3, 3)
        if ti.static(model == MATERIALS["neo_hookean"].id):
            # volumetric Kirchhoff stress J psi'(J) with psi = lambda log(J)^2 / 2; below J_MIN psi
            # continues as its quadratic Taylor polynomial, so J psi'(J) turns tensile for J < 0 and
            # an inverted element is pulled back through J = 0 instead of pushed further
            dpsi, _ = self._volumetric(J)
            tau = mu * (F @ F.transpose() - I) + la * J * dpsi * I
        elif ti.static(model == MATERIALS["corotated"].id):
            R, _ = ti.polar_decompose(F)
            tau = 2.0 * mu * (F - R) @ F.transpose() + la * (J - 1.0) * J * I
        elif ti.static(model == MATERIALS["stvk"].id):
            G = 0.5 * (F.transpose() @ F - I)
            tau = F @ (2.0 * mu * G + la * G.trace() * I) @ F.transpose()
        return tau

    @ti.func
    def _rotate(self, A, Q, plane: ti.template()):
        """One regularised Jacobi rotation in `plane` (index into JACOBI_PLANES): (G^T A G, Q G)."""
        p, q, D, S = ti.static(JACOBI_PLANES[plane])
        d = A[q, q] - A[p, p]
        sign = ti.select(d >= 0.0, 1.0, -1.0)
        t = 2.0 * A[p, q] * sign / (d * sign + ti.sqrt(d * d + 4.0 * A[p, q] ** 2 + JACOBI_EPS ** 2))
        c = 1.0 / ti.sqrt(1.0 + t * t)
        G = ti.Matrix.identity(float, 3) + (c - 1.0) * ti.Matrix(D) + t * c * ti.Matrix(S)
        return G.transpose() @ A @ G, Q @ G

    @ti.func
    def _divided(self, g, slope, a, p: ti.template(), q: ti.template()):
        """(g_q - g_p) / (a_q - a_p), continued by the mean slope where the eigenvalues coincide."""
        d = a[q] - a[p]
        return ((g[q] - g[p]) * d + 0.5 * (slope[p] + slope[q]) * JACOBI_EPS ** 2) / (d * d + JACOBI_EPS ** 2)

    @ti.func
    def _principal(self, A, a, g, slope):
        """The isotropic function of b = Q0 A Q0^T with eigenvalue function g (values at a = diag A,
        slopes dg_i/da_i at coincidence), to first order in A's off-diagonal round-off, in the
        frame Q0: the function is Q0 M Q0^T."""
        g01 = A[0, 1] * self._divided(g, slope, a, 0, 1)
        g02 = A[0, 2] * self._divided(g, slope, a, 0, 2)
        g12 = A[1, 2] * self._divided(g, slope, a, 1, 2)
        return ti.Matrix([[g[0], g01, g02], [g01, g[1], g12], [g02, g12, g[2]]])

    @ti.func
    def _lame(self, p):
        """Particle p's Lame parameters (mu, lambda) from its Young's modulus and Poisson's ratio."""
        E, nu = self.E[p], self.nu[p]
        return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @ti.func
    def _eigenframe(self, p, F):
        """(Q0, P = Q0^T F, A = P P^T, a): b = F F^T in the frame of its eigenvectors Q0 (from
        _eigen_frames, a constant of the adjoint), where A is diagonal up to round-off, and A's
        diagonal floored at J_MIN^2 (the principal values the models map)."""
        Q0 = self.frame[p]
        P = Q0.transpose() @ F  # F in that frame (fewer products)
        A = P @ P.transpose()
        return Q0, P, A, ti.max(ti.Vector([A[0, 0], A[1, 1], A[2, 2]]), J_MIN * J_MIN)

    @ti.func
    def _plastic(self, model: ti.template(), p, s, so, F, mu, la):
        """Return mapping of one plastic model in principal Hencky strain (see `_spectral`):
        the projected F and its Kirchhoff stress, assembled in the eigenframe."""
        Q0, P, A, a = self._eigenframe(p, F)
        g, g_slope, k, k_slope = self._spectral(model, p, s, so, a, mu, la, True)
        F_new = F + Q0 @ (self._principal(A, a, g, g_slope) @ P)
        return F_new, Q0 @ self._principal(A, a, k, k_slope) @ Q0.transpose()

    @ti.func
    def _spectral(self, model: ti.template(), p, s, so, a, mu, la, write_jp: ti.template()):
        """One plastic model's map of b's principal values a: (g, g', k, k'), with g = exp(eps_new -
        eps) - 1 the projection's scale less one and k the principal Kirchhoff stress, each with its
        slope in a_i (used where eigenvalues coincide). Snow also updates J_p (written to slot so
        if `write_jp`). The eigenframe algebra around it has a hand-written adjoint
        (`_plastic_adjoint_front/back`); Taichi differentiates only this map (`_spectral_map`).

        Works in principal Hencky strain eps = log(sigma). F changes only when the trial
        state lies outside the model's elastic region (for snow: a stretch outside its
        bounds), so a body loaded below yield springs back without permanent set. Written
        without branches or reassigned locals (masks select the case): Taichi's reverse mode
        turns locals assigned in branches into stacks.

        The Hencky models map eps affinely per particle, eps_new = alpha eps + beta (alpha = 1
        inside the yield surface, |radius| / |dev eps| on it, 0 at the apex), so the stress
        k_i = 2 mu eps_new_i + lambda tr(eps_new) has the slope mu alpha / a_i and the
        projection's scale exp(eps_new_i - eps_i) the slope scale_i (alpha - 1) / (2 a_i).
        """
        eps = 0.5 * ti.log(a)
        tr = eps.sum()
        dev = eps - tr / 3.0
        n2 = dev.dot(dev)
        prm = self.params[p]
        eps_new = eps
        alpha = 1.0
        if ti.static(model == ID["sand"]):
            # Drucker-Prager (Klar et al. 2016): |dev tau| <= -alpha tr(tau) around the apex set by
            # the cohesion; expansion beyond the apex loses all elastic strain (no tension).
            tip = 3.0 * prm[1] / (3.0 * la + 2.0 * mu)  # tr(eps) at the apex
            slope = prm[0] * (3.0 * la + 2.0 * mu) / (2.0 * mu)
            apex = ti.cast(tr > tip, float)
            cone = (1.0 - apex) * ti.cast(n2 > (slope * (tip - tr)) ** 2, float)
            shrink = slope * (tip - tr) / ti.sqrt(ti.max(n2, NORM_FLOOR))
            eps_new = eps + apex * (tip / 3.0 - eps) + cone * (tr / 3.0 + shrink * dev - eps)
            alpha = 1.0 - apex + cone * (shrink - 1.0)
        elif ti.static(model == ID["clay"] or model == ID["mud"]):
            # von Mises: |dev tau| = 2 mu |dev eps| <= sqrt(2/3) yield stress
            radius = ti.sqrt(2.0 / 3.0) * prm[0] / (2.0 * mu)
            outside = ti.cast(n2 > radius * radius, float)
            shrink = radius / ti.sqrt(ti.max(n2, radius * radius))
            eps_new = eps + outside * (tr / 3.0 + shrink * dev - eps)
            alpha = 1.0 + outside * (shrink - 1.0)
        elif ti.static(model == ID["snow"]):
            # Stomakhin et al. 2013: principal stretches clamped to [1 - theta_c, 1 + theta_s]
            eps_new = ti.min(ti.max(eps, ti.log(1.0 - prm[0])), ti.log(1.0 + prm[1]))
        # exp(0) - 1 == 0 exactly (with zero slope): an unprojected F is stored unchanged, bit for bit
        scale = ti.exp(eps_new - eps)
        scale_slope = scale * (alpha - 1.0) / (2.0 * a)
        k = ti.Vector.zero(float, 3)
        k_slope = mu * alpha / a
        if ti.static(model == ID["snow"]):
            # neo-Hookean with both moduli hardened by exp(xi (1 - J_p)), bounded to keep the
            # wave speed (and so the time step) and the gradients bounded; F_new F_new^T has
            # the clamped eigenvalues exp(2 eps_new)
            inside = ti.cast(eps == eps_new, float)
            scale_slope = -(1.0 - inside) * scale / (2.0 * a)
            jp = self.Jp[s, p] * ti.exp((eps - eps_new).sum())
            if ti.static(write_jp):
                self.Jp[so, p] = jp
            h = ti.min(ti.max(ti.exp(prm[2] * (1.0 - jp)), MIN_HARDENING), prm[3])
            k = h * (mu * (ti.exp(2.0 * eps_new) - 1.0) + la * eps_new.sum())
            k_slope = h * mu * inside
        else:  # Hencky: tau = 2 mu eps + lambda tr(eps) I, in the principal frame
            k = 2.0 * mu * eps_new + la * eps_new.sum()
        return scale - 1.0, scale_slope, k, k_slope

    @ti.func
    def _constitutive(self, model: ti.template(), p, s, so):
        """(F to store, Kirchhoff stress without muscle) of particle p of `model`, from slot s."""
        C = self.C[s, p]
        F = self._trial(p, s)
        mu, la = self._lame(p)
        F_new = F
        tau = ti.Matrix.zero(float, 3, 3)
        if ti.static(not MATERIALS[MODEL_NAMES[model]].plastic):
            tau = self._elastic_stress(model, F, mu, la)
        elif ti.static(model == ID["water"]):
            # weakly compressible: Cauchy pressure K (1 - J); only J is state, so F is reset to
            # the isotropic J^(1/3) I (shear would otherwise accumulate without any stress)
            J = F.determinant()
            tau = self.params[p][0] * J * (J - 1.0) * ti.Matrix.identity(float, 3)
            F_new = ti.exp(ti.log(ti.max(J, J_MIN)) / 3.0) * ti.Matrix.identity(float, 3)
        else:
            F_new, tau = self._plastic(model, p, s, so, F, mu, la)
        if ti.static(model == ID["water"] or model == ID["mud"]):
            # Newtonian viscosity, tau = J eta (grad v + grad v^T), with the APIC C as grad v
            tau += F.determinant() * self.params[p][1] * (C + C.transpose())
        return F_new, tau

    @ti.func
    def _update(self, p, s, so):
        """Elastic-only scenes: (new F, stress) with the model chosen per particle."""
        F_new = ti.Matrix.zero(float, 3, 3)
        tau = ti.Matrix.zero(float, 3, 3)
        if ti.static(len(self.models) == 1):
            F_new, tau = self._constitutive(self.models[0], p, s, so)
        else:
            for model in ti.static(self.models):
                if self.material[p] == model:
                    F_new, tau = self._constitutive(model, p, s, so)
        return F_new, tau

    @ti.func
    def _muscle_stress(self, p, F, t):
        """Kirchhoff stress of particle p's muscle at action row t (materials.MUSCLE_MODELS)."""
        Ff = F @ self.fiber[p]
        row = t
        if ti.static(self.batched):  # forward only: one action row per member
            row = self.member[p]
        a = self.act[row].dot(self.muscle[p])
        s = self.muscle_ratio[p] * self.E[p]
        tau = s * a * Ff.outer_product(Ff)
        if ti.static(self.muscle_model == "energy"):
            tau = 4.0 * s * (Ff.dot(Ff) - 1.0 + a) * Ff.outer_product(Ff)
        return tau

    @ti.kernel
    def _stress(self, model: ti.template(), s: ti.i32, scratch: ti.i32, t: ti.i32, start: ti.i32, end: ti.i32,
                out: ti.types.ndarray()):
        """Kirchhoff stress that the next substep applies to particles [start, end) of one model
        (constitutive at the trial F, plus the muscle at action row t); forward only. State a
        plastic model writes (snow's J_p) goes to the `scratch` slot."""
        for p in range(start, end):
            if ti.static(MATERIALS[MODEL_NAMES[model]].plastic and model != ID["water"]):
                self.frame[p] = self._frame(s, p)
            F, tau = self._constitutive(model, p, s, scratch)
            if ti.static(self.has_muscles):
                tau += self._muscle_stress(p, F, t)
            for i, j in ti.static(ti.ndrange(3, 3)):
                out[p, i, j] = tau[i, j]

    @ti.func
    def _frame(self, s, p):
        """Eigenvectors of the trial b = F F^T of particle p in slot s (cyclic Jacobi, up to
        JACOBI_SWEEPS sweeps, none once b is diagonal to JACOBI_TOL_ULPS)."""
        F = self._trial(p, s)
        A = F @ F.transpose()
        Q = ti.Matrix.identity(float, 3)
        for _ in range(JACOBI_SWEEPS):
            if A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2 <= (ti.static(self.jacobi_tol) * A.trace()) ** 2:
                break
            for plane in ti.static(range(3)):
                A, Q = self._rotate(A, Q, plane)
        return Q

    @ti.kernel
    def _eigen_frames(self, s: ti.i32, start: ti.i32, end: ti.i32):
        """Eigenvectors of b = F F^T (trial F) of particles [start, end); never differentiated.

        Their derivative is taken by one Jacobi sweep inside `_plastic`: the whole iteration
        differentiated in reverse mode is far too slow for Taichi to compile.
        """
        for p in range(start, end):
            self.frame[p] = self._frame(s, p)

    @ti.func
    def _constitutive_particle(self, model: ti.template(), p, s, so, t):
        F, tau = self._constitutive(model, p, s, so)
        if ti.static(self.has_muscles):
            tau += self._muscle_stress(p, F, t)
        self.F[so, p] = F
        self.tau[p] = tau

    @ti.func
    def _principal_adjoint(self, M_bar, A, a, g, slope):
        """Adjoint of `_principal`: from M's gradient to those of g, its slopes, a and A's
        off-diagonal (01, 02, 12). M_pq = A_pq D_pq with D_pq = (dg d + s e^2) / (d^2 + e^2), d =
        a_q - a_p, dg = g_q - g_p, s the mean slope and e = JACOBI_EPS; dD/dd = (dg - 2 d D) / (d^2 + e^2)."""
        g_bar = ti.Vector([M_bar[0, 0], M_bar[1, 1], M_bar[2, 2]])
        slope_bar = ti.Vector.zero(float, 3)
        a_bar = ti.Vector.zero(float, 3)
        off_bar = ti.Vector.zero(float, 3)
        for pair in ti.static(range(3)):
            p, q = ti.static(((0, 1), (0, 2), (1, 2))[pair])
            m = M_bar[p, q] + M_bar[q, p]
            d = a[q] - a[p]
            den = d * d + JACOBI_EPS ** 2
            D = self._divided(g, slope, a, p, q)
            off_bar[pair] = m * D
            D_bar = m * A[p, q]
            g_bar[q] += D_bar * d / den
            g_bar[p] -= D_bar * d / den
            slope_bar[p] += D_bar * 0.5 * JACOBI_EPS ** 2 / den
            slope_bar[q] += D_bar * 0.5 * JACOBI_EPS ** 2 / den
            a_bar[q] += D_bar * (g[q] - g[p] - 2.0 * d * D) / den
            a_bar[p] -= D_bar * (g[q] - g[p] - 2.0 * d * D) / den
        return g_bar, slope_bar, a_bar, off_bar

    @ti.func
    def _muscle_adjoint(self, p, F, t, tau_bar):
        """Adjoint of `_muscle_stress` (action row t): adds the gradients of the fibre, the muscle
        membership, E and the action row, and returns F's. With u = F f, a the activation, s the
        stiffness and T the stress's gradient: active (s a u u^T) gives u: s a (T + T^T) u, a: s u.T u,
        s: a u.T u; energy (4 s c u u^T, c = |u|^2 - 1 + a) gives u: 4 s (c (T + T^T) u + 2 (u.T u) u),
        a: 4 s u.T u, s: 4 c u.T u."""
        f = self.fiber[p]
        u = F @ f
        act = self.act[t]
        a = act.dot(self.muscle[p])
        s = self.muscle_ratio[p] * self.E[p]
        q = u.dot(tau_bar @ u)
        sym_u = (tau_bar + tau_bar.transpose()) @ u
        u_bar = s * a * sym_u
        a_bar = s * q
        s_bar = a * q
        if ti.static(self.muscle_model == "energy"):
            c = u.dot(u) - 1.0 + a
            u_bar = 4.0 * s * (c * sym_u + 2.0 * q * u)
            a_bar = 4.0 * s * q
            s_bar = 4.0 * c * q
        if s != 0.0:  # particles without muscle contribute nothing
            self.fiber.grad[p] = self.fiber.grad[p] + F.transpose() @ u_bar
            self.muscle.grad[p] = self.muscle.grad[p] + a_bar * act
            self.E.grad[p] = self.E.grad[p] + self.muscle_ratio[p] * s_bar
        self.drive_bar[p] = a_bar  # the action row's gradient sums these (`_add_drive_grad`)
        return u_bar.outer_product(f)

    @ti.kernel
    def _add_drive_grad(self, t: ti.i32, start: ti.i32, end: ti.i32):
        """Action row t's gradient from the muscles of particles [start, end): sum_p drive_bar_p m_p,
        added up in chunks of DRIVE_CHUNK particles, one atomic add per chunk (an atomic add per
        particle onto one row serialises every thread on it)."""
        for c in range((end - start + DRIVE_CHUNK - 1) // DRIVE_CHUNK):
            total = ti.Vector.zero(float, ti.static(self.act.n))
            for p in range(start + c * DRIVE_CHUNK, ti.min(end, start + (c + 1) * DRIVE_CHUNK)):
                total += self.drive_bar[p] * self.muscle[p]
            self.act.grad[t] += total

    @ti.kernel
    def _plastic_adjoint_front(self, model: ti.template(), s: ti.i32, so: ti.i32, t: ti.i32, start: ti.i32,
                               end: ti.i32):
        """Reverse of a Hencky model's `_constitutive_update` (written by hand, as a forward kernel),
        first part: from the gradients of the stored F (slot so) and of the stress (muscle included)
        to those of the model's map (`spectral.grad`), part of its input's (`strain.grad`, which
        `_spectral_map.grad` completes) and of the trial F (`F_bar_part`, `A_off_bar`).

        F_new = F + Q0 M1 P and tau = Q0 M2 Q0^T: with G = Q0^T dL/dF_new, M1's gradient is G P^T,
        P's gets M1 G, and M2's is Q0^T dL/dtau Q0."""
        for p in range(start, end):
            F = self._trial(p, s)
            mu, la = self._lame(p)
            Q0, P, A, a = self._eigenframe(p, F)
            g, g_slope, k, k_slope = self._spectral(model, p, s, so, a, mu, la, False)
            M1 = self._principal(A, a, g, g_slope)
            tau_bar = self.tau.grad[p]
            Fn_bar = self.F.grad[so, p]
            if ti.static(self.has_muscles):
                Fn_bar += self._muscle_adjoint(p, F + Q0 @ (M1 @ P), t, tau_bar)
            G = Q0.transpose() @ Fn_bar
            g_bar, g_slope_bar, a_bar, off_bar = self._principal_adjoint(G @ P.transpose(), A, a, g, g_slope)
            k_bar, k_slope_bar, a_bar2, off_bar2 = self._principal_adjoint(Q0.transpose() @ tau_bar @ Q0, A, a, k,
                                                                           k_slope)
            self.strain[p] = a
            self.strain.grad[p] = a_bar + a_bar2
            self.spectral.grad[p] = self._stack(g_bar, g_slope_bar, k_bar, k_slope_bar)
            self.F_bar_part[p] = Fn_bar + Q0 @ (M1 @ G)
            self.A_off_bar[p] = off_bar + off_bar2

    @ti.kernel
    def _spectral_map(self, model: ti.template(), s: ti.i32, so: ti.i32, start: ti.i32, end: ti.i32):
        """A Hencky model's map (`_spectral`) from `strain` to `spectral`, in a kernel of its own so
        that Taichi's reverse mode differentiates it alone: the eigenframe algebra around it took
        over a minute to compile in reverse mode, the map well under a second."""
        for p in range(start, end):
            mu, la = self._lame(p)
            g, g_slope, k, k_slope = self._spectral(model, p, s, so, self.strain[p], mu, la, True)
            self.spectral[p] = self._stack(g, g_slope, k, k_slope)

    @ti.kernel
    def _plastic_adjoint_back(self, model: ti.template(), s: ti.i32, start: ti.i32, end: ti.i32):
        """Last part of the hand-written reverse (after `_spectral_map.grad`): through A = P P^T and
        a = max(diag A, J_MIN^2) to P, then to the trial F = (I + dt C) F_s and on to F_s and C
        (mud's viscous stress J eta (C + C^T) included)."""
        for p in range(start, end):
            C, F = self.C[s, p], self._trial(p, s)
            Q0, P, A, a = self._eigenframe(p, F)
            a_bar = self.strain.grad[p]
            off = self.A_off_bar[p]
            A_bar = ti.Matrix([[a_bar[0] * ti.cast(A[0, 0] > J_MIN * J_MIN, float), off[0], off[1]],
                               [0.0, a_bar[1] * ti.cast(A[1, 1] > J_MIN * J_MIN, float), off[2]],
                               [0.0, 0.0, a_bar[2] * ti.cast(A[2, 2] > J_MIN * J_MIN, float)]])
            F_bar = self.F_bar_part[p] + Q0 @ ((A_bar + A_bar.transpose()) @ P)
            C_bar = ti.Matrix.zero(float, 3, 3)
            if ti.static(model == ID["mud"]):
                tau_bar, eta = self.tau.grad[p], self.params[p][1]
                F_bar += eta * ((C + C.transpose()) * tau_bar).sum() * self._cofactor(F)
                C_bar += F.determinant() * eta * (tau_bar + tau_bar.transpose())
            self._add_trial_grad(p, s, F_bar, C_bar)

    @ti.kernel
    def _neo_hookean_adjoint(self, s: ti.i32, so: ti.i32, t: ti.i32, start: ti.i32, end: ti.i32):
        """Reverse of `_constitutive_update` for neo-Hookean particles (the robots' default), written by
        hand like the plastic one: tau = mu (F F^T - I) + lambda h(J) I (+ the muscle) at the trial
        F = (I + dt C) F_s, with h(J) = J psi'(J) = log J above J_MIN and its quadratic continuation
        below (`_elastic_stress`)."""
        for p in range(start, end):
            F = self._trial(p, s)
            tau_bar = self.tau.grad[p]
            F_bar = self.F.grad[so, p]
            if ti.static(self.has_muscles):
                F_bar += self._muscle_adjoint(p, F, t, tau_bar)
            mu, la = self._lame(p)
            J = F.determinant()
            dpsi, dh = self._volumetric(J)
            trace_bar = tau_bar.trace()
            F_bar += mu * (tau_bar + tau_bar.transpose()) @ F + la * dh * trace_bar * self._cofactor(F)
            mu_bar = ((F @ F.transpose() - ti.Matrix.identity(float, 3)) * tau_bar).sum()
            nu = self.nu[p]
            self.E.grad[p] = self.E.grad[p] + mu_bar / (2.0 * (1.0 + nu)) + J * dpsi * trace_bar * nu / (
                (1.0 + nu) * (1.0 - 2.0 * nu))
            self._add_trial_grad(p, s, F_bar, ti.Matrix.zero(float, 3, 3))

    @ti.func
    def _trial(self, p, s):
        """Particle p's trial deformation (I + dt C) F from slot s, before any return mapping."""
        return (ti.Matrix.identity(float, 3) + self._dt(p) * self.C[s, p]) @ self.F[s, p]

    @ti.func
    def _add_trial_grad(self, p, s, F_bar, C_bar):
        """Adjoint of `_trial`: add the trial F's gradient F_bar to F's and C's at slot s, and C_bar
        (C's gradient through other terms) to C's; p is this iteration's alone (plain adds)."""
        C, F_s = self.C[s, p], self.F[s, p]
        dt = self._dt(p)
        self.F.grad[s, p] = self.F.grad[s, p] + (ti.Matrix.identity(float, 3) + dt * C).transpose() @ F_bar
        self.C.grad[s, p] = self.C.grad[s, p] + C_bar + dt * F_bar @ F_s.transpose()

    @ti.func
    def _volumetric(self, J):
        """Neo-Hookean's psi'(J) with psi = log(J)^2 / 2, continued below J_MIN by its quadratic Taylor
        polynomial (see `_elastic_stress`), and the derivative of h(J) = J psi'(J) for the adjoint."""
        slope = (1.0 - ti.log(J_MIN)) / J_MIN ** 2
        dpsi = ti.log(ti.max(J, J_MIN)) / ti.max(J, J_MIN) + slope * ti.min(J - J_MIN, 0.0)
        dh = ti.select(J > J_MIN, 1.0 / ti.max(J, J_MIN), ti.log(J_MIN) / J_MIN + slope * (2.0 * J - J_MIN))
        return dpsi, dh

    @ti.func
    def _stack(self, g, g_slope, k, k_slope):
        """The four 3-vectors of a Hencky model's map as one 12-vector (the `spectral` field)."""
        return ti.Vector([g[0], g[1], g[2], g_slope[0], g_slope[1], g_slope[2],
                          k[0], k[1], k[2], k_slope[0], k_slope[1], k_slope[2]])

    @ti.func
    def _cofactor(self, F):
        """d det(F) / dF, the cofactor matrix (defined for singular F too)."""
        cof = ti.Matrix.zero(float, 3, 3)
        for i, j in ti.static(ti.ndrange(3, 3)):
            cof[i, j] = (F[(i + 1) % 3, (j + 1) % 3] * F[(i + 2) % 3, (j + 2) % 3]
                         - F[(i + 1) % 3, (j + 2) % 3] * F[(i + 2) % 3, (j + 1) % 3])
        return cof

    @ti.kernel
    def _constitutive_update(self, model: ti.template(), s: ti.i32, so: ti.i32, t: ti.i32, start: ti.i32,
                             end: ti.i32, j: ti.i32):
        """Scenes with plastic models and differentiable layouts (`separate_stress`): F and stress
        (muscle included, at action row t) of the particles [start, end) of one model, in their own
        kernel ahead of p2g (one small kernel per model compiles far faster than all of them fused
        into the 27-node scatter). `j`: the substep within the control step."""
        for p in range(start, end):
            if ti.static(self.batched):
                if self._active(p, j):
                    self._constitutive_particle(model, p, s, so, t)
                else:
                    self._hold_deformation(p, s, so)
            else:
                self._constitutive_particle(model, p, s, so, t)

    @ti.func
    def _hold_deformation(self, p, s, so):
        """A batch member sitting out a substep carries its deformation into the next slot."""
        self.F[so, p] = self.F[s, p]
        if ti.static(self.has_jp):
            self.Jp[so, p] = self.Jp[s, p]

    @ti.func
    def _stencil(self, p, s):
        """Particle p's 3x3x3 stencil: its lowest node in the grid fields, its position in cells
        relative to the scene-local lowest node, and the quadratic B-spline weights per axis."""
        base = self._base(self.x[s, p])
        fx = self.x[s, p] * (1.0 / self.dx[None]) - ti.cast(base, float)
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
        return base + self._offset(p), fx, w

    @ti.func
    def _weight_and_slope(self, w, dw, i: ti.template(), j: ti.template(), k: ti.template()):
        """Node (i, j, k)'s weight and its derivative with respect to fx, from the per-axis weights w
        and their derivatives dw (the adjoints' stencil)."""
        weight = w[i][0] * w[j][1] * w[k][2]
        return weight, ti.Vector([dw[i][0] * w[j][1] * w[k][2], w[i][0] * dw[j][1] * w[k][2],
                                  w[i][0] * w[j][1] * dw[k][2]])

    @ti.func
    def _at_node(self, c, M, o: ti.template()):
        """c + M n for a stencil offset n = o, constant: at most three column adds, no 3x3 product."""
        q = c
        for d in ti.static(range(3)):
            if ti.static(o[d]):
                q += o[d] * ti.Vector([M[0, d], M[1, d], M[2, d]])
        return q

    @ti.func
    def _p2g_particle(self, p, s, so, t, copy):
        """Scatter particle p's momentum, mass and MLS force to its 27 nodes: into private grid
        `copy` with plain adds where the scatter is private (its chunk of particles is one thread's),
        else with atomic adds into the grid."""
        dt, dx = self._dt(p), self.dx[None]
        inv_dx = 1.0 / dx
        node, fx, w = self._stencil(p, s)
        F = ti.Matrix.zero(float, 3, 3)
        tau = ti.Matrix.zero(float, 3, 3)
        if ti.static(self.separate_stress):  # computed by _constitutive_update, muscle included
            tau = self.tau[p]
        else:
            F, tau = self._update(p, s, so)
            self.F[so, p] = F
            if ti.static(self.has_muscles):
                tau += self._muscle_stress(p, F, t)
        vol = self.vol[p]
        mass = self.rho[p] * vol
        affine = (-dt * vol * 4.0 * inv_dx * inv_dx) * tau + mass * self.C[s, p]
        inertia = mass * self.C[s, p]
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            offset = ti.Vector([i, j, k])
            dpos = (ti.cast(offset, float) - fx) * dx
            weight = w[i][0] * w[j][1] * w[k][2]
            momentum = weight * (mass * self.v[s, p] + affine @ dpos)
            I = node + offset
            if ti.static(self.has_flip):
                before = weight * (mass * self.v[s, p] + inertia @ dpos)  # without the force
                if ti.static(self.private_scatter):
                    c = self.grid_part[copy, I[0], I[1], I[2]]
                    self.grid_part[copy, I[0], I[1], I[2]] = c + ti.Vector(
                        [momentum[0], momentum[1], momentum[2], weight * mass, before[0], before[1], before[2]])
                else:
                    self.grid_v_in[I] += momentum
                    self.grid_m[I] += weight * mass
                    self.grid_q[I] += before
            elif ti.static(self.private_scatter):  # plain adds: a float atomic add is a compare-and-swap loop
                c = self.grid_part[copy, I[0], I[1], I[2]]
                self.grid_part[copy, I[0], I[1], I[2]] = c + ti.Vector(
                    [momentum[0], momentum[1], momentum[2], weight * mass])
            else:
                self.grid_v_in[I] += momentum
                self.grid_m[I] += weight * mass

    @ti.func
    def _p2g_adjoint_particle(self, p, s):
        """p2g's adjoint, written by hand (differentiable layouts, whose stress tau is an input): from
        the grid's momentum and mass gradients at p's nodes to v, C, tau, the volume and x at slot s.

        Node n = (i, j, k) gets w_n q_n and w_n m, with q_n = m v + A (n - fx) dx = c + dx A n,
        c = m v - dx A fx and A = -4 dt vol / dx^2 tau + m C. With g_n, h_n the momentum and mass
        gradients, S0 = sum w_n g_n and S1 = sum w_n g_n n^T: A's gradient is dx (S1 - S0 fx^T),
        fx's is sum (dw_n / dfx) (g_n . q_n + m h_n) - dx A^T S0 (n enters as constants, so the
        loop over nodes has no 3x3 products). With FLIP, node n also gets w_n (m v + m C (n - fx) dx)
        (the momentum before forces), whose gradient enters the same way with A = m C."""
        dt, dx = self._dt(p), self.dx[None]
        inv_dx = 1.0 / dx
        node, fx, w = self._stencil(p, s)
        dw = [fx - 1.5, 2.0 * (1.0 - fx), fx - 0.5]  # d w / d fx, per axis
        tau, vol, v = self.tau[p], self.vol[p], self.v[s, p]
        mass = self.rho[p] * vol
        stress_scale = -dt * 4.0 * inv_dx * inv_dx
        affine = stress_scale * vol * tau + mass * self.C[s, p]
        a_dx = dx * affine
        c = mass * v - a_dx @ fx
        i_dx = dx * mass * self.C[s, p]  # FLIP's momentum before forces: its affine part has no stress
        c_old = mass * v - i_dx @ fx
        S0 = ti.Vector.zero(float, 3)
        S1 = ti.Matrix.zero(float, 3, 3)
        S0_old = ti.Vector.zero(float, 3)
        S1_old = ti.Matrix.zero(float, 3, 3)
        h_sum = 0.0
        fx_bar = ti.Vector.zero(float, 3)
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            o = ti.static((i, j, k))
            weight, d_weight = self._weight_and_slope(w, dw, i, j, k)
            g, h = self.grid_v_in.grad[node + ti.Vector(o)], self.grid_m.grad[node + ti.Vector(o)]
            q = self._at_node(c, a_dx, o)
            for d in ti.static(range(3)):
                if ti.static(o[d]):
                    for e in ti.static(range(3)):
                        S1[e, d] += (o[d] * weight) * g[e]
            fx_bar += d_weight * (g.dot(q) + mass * h)
            S0 += weight * g
            h_sum += weight * h
            if ti.static(self.has_flip):
                g_old = self.grid_q.grad[node + ti.Vector(o)]
                for d in ti.static(range(3)):
                    if ti.static(o[d]):
                        for e in ti.static(range(3)):
                            S1_old[e, d] += (o[d] * weight) * g_old[e]
                fx_bar += d_weight * g_old.dot(self._at_node(c_old, i_dx, o))
                S0_old += weight * g_old
        affine_bar = dx * (S1 - S0.outer_product(fx))
        fx_bar -= a_dx.transpose() @ S0
        mass_bar = v.dot(S0) + h_sum + (self.C[s, p] * affine_bar).sum()
        v_bar = mass * S0
        C_bar = mass * affine_bar
        if ti.static(self.has_flip):
            inertia_bar = dx * (S1_old - S0_old.outer_product(fx))
            fx_bar -= i_dx.transpose() @ S0_old
            mass_bar += v.dot(S0_old) + (self.C[s, p] * inertia_bar).sum()
            v_bar += mass * S0_old
            C_bar += mass * inertia_bar
        # plain read-modify-writes: p is this iteration's alone (a += would be an atomic add)
        self.v.grad[s, p] = self.v.grad[s, p] + v_bar
        self.C.grad[s, p] = self.C.grad[s, p] + C_bar
        self.tau.grad[p] = stress_scale * vol * affine_bar  # its only writer: _constitutive_update's adjoint reads it
        self.vol.grad[p] = self.vol.grad[p] + self.rho[p] * mass_bar + stress_scale * (tau * affine_bar).sum()
        self.x.grad[s, p] = self.x.grad[s, p] + inv_dx * fx_bar

    @ti.func
    def _p2g_one(self, p, s, so, t, j, copy):
        if ti.static(self.batched):
            if self._active(p, j):
                self._p2g_particle(p, s, so, t, copy)
            elif ti.static(not self.separate_stress):  # else _constitutive_update held it
                self._hold_deformation(p, s, so)
        else:
            self._p2g_particle(p, s, so, t, copy)

    @ti.kernel
    def _p2g(self, s: ti.i32, so: ti.i32, t: ti.i32, n: ti.i32, j: ti.i32):
        if ti.static(self.private_scatter):
            for c in range(self.copies):  # one chunk of particles per thread, each into its own grid
                for p in range(c * n // self.copies, (c + 1) * n // self.copies):
                    self._p2g_one(p, s, so, t, j, c)
        else:
            for p in range(n):
                self._p2g_one(p, s, so, t, j, -1)

    @ti.kernel
    def _p2g_adjoint(self, s: ti.i32, n: ti.i32):
        """Reverse of p2g for substep s (differentiable layouts): a gather per particle, no atomics.
        Written by hand, it compiles as a forward kernel (Taichi's reverse mode of the 27-node
        scatter took minutes to compile)."""
        for p in range(n):
            self._p2g_adjoint_particle(p, s)

    @ti.func
    def _node(self, b, i, j, k):
        """Node (i, j, k) of member b's grid in the grid fields (members side by side along x); the
        grid kernels visit the touched box (`_bounds`) in every member's grid."""
        return ti.Vector([b * self.grid_shape[0] + i, j, k])

    @ti.kernel
    def _clear_grid(self):
        for b, i, j, k in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            I = self._node(b, i, j, k)
            self.grid_v_in[I] = ti.Vector.zero(float, 3)
            self.grid_m[I] = 0.0
            if ti.static(self.has_flip):
                self.grid_q[I] = ti.Vector.zero(float, 3)

    @ti.kernel
    def _sum_copies(self, adjoint: ti.template()):
        """Sum the private grids, and leave them zero for their next use: into the grid's momentum and
        mass (and momentum before forces) after p2g, or into grid_v_out's (and grid_v_old's) gradient
        after g2p's adjoint."""
        for b, i, j, k in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            I = self._node(b, i, j, k)
            total = ti.Vector.zero(float, self.part_width)
            for c in range(self.copies):
                total += self.grid_part[c, I[0], I[1], I[2]]
                self.grid_part[c, I[0], I[1], I[2]] = ti.Vector.zero(float, self.part_width)
            if ti.static(adjoint):
                self.grid_v_out.grad[I] = ti.Vector([total[0], total[1], total[2]])
                if ti.static(self.has_flip):
                    self.grid_v_old.grad[I] = ti.Vector([total[4], total[5], total[6]])
            else:
                self.grid_v_in[I] = ti.Vector([total[0], total[1], total[2]])
                self.grid_m[I] = total[3]
                if ti.static(self.has_flip):
                    self.grid_q[I] = ti.Vector([total[4], total[5], total[6]])

    @ti.kernel
    def _store_grid(self, k: ti.i32, store: ti.types.ndarray(), box: ti.types.ndarray()):
        """Keep this substep's grid momentum and mass (with FLIP, the momentum before forces too) over
        the touched box as record k of `store` ((records, nodes, part_width)) for the reverse pass,
        which then need not run p2g again. box[k] holds the box (lo, hi) and whether it fit
        (box[k, 6]); the reverse pass recomputes a substep whose box was larger than a record, and
        the next rollout's records grow to the largest box seen."""
        lo = ti.Vector([self.lo[0][None], self.lo[1][None], self.lo[2][None]])
        extent = ti.Vector([self.hi[0][None], self.hi[1][None], self.hi[2][None]]) - lo
        fits = self.members * extent[0] * extent[1] * extent[2] <= store.shape[1]
        for d in ti.static(range(3)):
            box[k, d] = lo[d]
            box[k, 3 + d] = lo[d] + extent[d]
        box[k, 6] = ti.cast(fits, ti.i32)
        for b, i, j, l in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            if fits:
                I = self._node(b, i, j, l)
                index = ((b * extent[0] + i - lo[0]) * extent[1] + j - lo[1]) * extent[2] + l - lo[2]
                for c in ti.static(range(3)):
                    store[k, index, c] = self.grid_v_in[I][c]
                store[k, index, 3] = self.grid_m[I]
                if ti.static(self.has_flip):
                    for c in ti.static(range(3)):
                        store[k, index, 4 + c] = self.grid_q[I][c]

    @ti.kernel
    def _load_box(self, k: ti.i32, box: ti.types.ndarray()):
        for d in ti.static(range(3)):
            self.lo[d][None] = box[k, d]
            self.hi[d][None] = box[k, 3 + d]

    @ti.kernel
    def _load_grid(self, k: ti.i32, store: ti.types.ndarray()):
        """The grid momentum and mass `_store_grid` kept as record k (after `_load_box`)."""
        lo = ti.Vector([self.lo[0][None], self.lo[1][None], self.lo[2][None]])
        extent = ti.Vector([self.hi[0][None], self.hi[1][None], self.hi[2][None]]) - lo
        for b, i, j, l in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            I = self._node(b, i, j, l)
            index = ((b * extent[0] + i - lo[0]) * extent[1] + j - lo[1]) * extent[2] + l - lo[2]
            self.grid_v_in[I] = ti.Vector([store[k, index, 0], store[k, index, 1], store[k, index, 2]])
            self.grid_m[I] = store[k, index, 3]
            if ti.static(self.has_flip):
                self.grid_q[I] = ti.Vector([store[k, index, 4], store[k, index, 5], store[k, index, 6]])

    @ti.kernel
    def _clear_grid_grad(self):
        for b, i, j, k in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            I = self._node(b, i, j, k)
            self.grid_v_in.grad[I] = ti.Vector.zero(float, 3)
            self.grid_m.grad[I] = 0.0
            self.grid_v_out.grad[I] = ti.Vector.zero(float, 3)
            if ti.static(self.has_flip):
                self.grid_q.grad[I] = ti.Vector.zero(float, 3)
                self.grid_v_old.grad[I] = ti.Vector.zero(float, 3)

    @ti.kernel
    def _grid_op(self):
        bc = ti.static(self.boundary_cells)
        for b, i, j, k in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            I = self._node(b, i, j, k)
            dt, dx, mu = self.dt[None], self.dx[None], self.friction[None]
            local = ti.Vector([i, j, k])  # the node's index in its own scene's grid
            if ti.static(self.batched):
                dt = self.member_dt[b]
            m = self.grid_m[I]
            v = ti.Vector.zero(float, 3)
            v_old = ti.Vector.zero(float, 3)
            if m > MASS_EPS:
                if ti.static(self.has_flip):
                    v_old = self.grid_q[I] / m
                v = self.grid_v_in[I] / m + dt * self.gravity[None]
                if ti.static(self.has_terrain):
                    nrm = self.normal[local[0], local[2]]
                    if (ti.cast(I[1], float) * dx - self.height[local[0], local[2]]) * nrm[1] < 0:
                        vn = v.dot(nrm)
                        if vn < 0:
                            vt = v - vn * nrm
                            vt_norm = ti.sqrt(vt.dot(vt) + 1e-30)
                            if vt_norm <= -mu * vn:
                                v = ti.Vector.zero(float, 3)
                            else:
                                v = vt * (1.0 + mu * vn / vt_norm)
                # walls: no outward velocity near the domain edge (branch-free: a component assigned
                # in a branch becomes an uninitialised load in Taichi's reverse mode)
                top = ti.Vector([self.grid_shape[0], self.grid_shape[1], self.grid_shape[2]]) - 1 - bc
                blocked = ((local < bc) & (v < 0)) | ((local > top) & (v > 0))
                v = ti.select(blocked, 0.0, v)
            self.grid_v_out[I] = v
            if ti.static(self.has_flip):
                self.grid_v_old[I] = v_old

    @ti.func
    def _flip_share(self, p, s):
        """scene.flip for the elastic bodies, 0 (APIC alone) for the covers (with FLIP, a water column's
        mean pressure gradient fell 10% below rho g: docs/contact.md section 10) and for a particle
        crushed below J_FLIP in slot s. The switch is piecewise constant, so the adjoint needs no term
        for it."""
        share = 0.0
        for model in ti.static(FLIP_MODELS):
            if self.material[p] == model and self.F[s, p].determinant() > J_FLIP:
                share = self.flip_ratio[None]
        return share

    @ti.func
    def _g2p_particle(self, p, s, so):
        """Gather particle p's new velocity (with FLIP's share of its own) and affine velocity C from
        its 27 nodes; move it with the grid's velocity."""
        inv_dx = 1.0 / self.dx[None]
        node, fx, w = self._stencil(p, s)
        new_v = ti.Vector.zero(float, 3)
        new_C = ti.Matrix.zero(float, 3, 3)
        old_v = ti.Vector.zero(float, 3)
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            offset = ti.Vector([i, j, k])
            g_v = self.grid_v_out[node + offset]
            weight = w[i][0] * w[j][1] * w[k][2]
            new_v += weight * g_v
            new_C += 4.0 * inv_dx * weight * g_v.outer_product(ti.cast(offset, float) - fx)
            if ti.static(self.has_flip):
                old_v += weight * self.grid_v_old[node + offset]
        if ti.static(self.has_flip):
            self.v[so, p] = new_v + self._flip_share(p, s) * (self.v[s, p] - old_v)
        else:
            self.v[so, p] = new_v
        self.C[so, p] = new_C
        self.x[so, p] = self.x[s, p] + self._dt(p) * new_v

    @ti.func
    def _scatter_grad(self, I, g, g_old, copy):
        """Add g to grid_v_out's gradient at node I (and with FLIP g_old to grid_v_old's): into private
        grid `copy` with plain adds where the scatter is private, else with an atomic add (as p2g
        scatters)."""
        if ti.static(self.private_scatter):
            part = self.grid_part[copy, I[0], I[1], I[2]]
            if ti.static(self.has_flip):
                part += ti.Vector([g[0], g[1], g[2], 0.0, g_old[0], g_old[1], g_old[2]])
            else:
                part += ti.Vector([g[0], g[1], g[2], 0.0])
            self.grid_part[copy, I[0], I[1], I[2]] = part
        else:
            self.grid_v_out.grad[I] += g
            if ti.static(self.has_flip):
                self.grid_v_old.grad[I] += g_old

    @ti.func
    def _g2p_adjoint_particle(self, p, s, copy):
        """g2p's adjoint, written by hand: with a = dL/dv' + dt dL/dx' and B = 4/dx dL/dC' at slot
        s + 1, node n gets w_n h_n, h_n = a + B (n - fx), and x gets dL/dx' + (1/dx) dL/dfx with
        dL/dfx = sum (dw_n / dfx) (g_n . h_n) - B^T sum w_n g_n (fx enters through the weights and
        through n - fx; g_n is the node's velocity). With FLIP, v' also holds flip (v - sum w_n u_n)
        (u_n: the node's velocity before forces): v gets flip dL/dv', node n's u_n gets
        -w_n flip dL/dv', and fx gets its weights' share."""
        inv_dx = 1.0 / self.dx[None]
        node, fx, w = self._stencil(p, s)
        dw = [fx - 1.5, 2.0 * (1.0 - fx), fx - 0.5]  # d w / d fx, per axis
        x_bar = self.x.grad[s + 1, p]
        B = 4.0 * inv_dx * self.C.grad[s + 1, p]
        h0 = self.v.grad[s + 1, p] + self._dt(p) * x_bar - B @ fx
        kept = ti.Vector.zero(float, 3)  # FLIP: the share of v' that is v_p - V_p^old
        if ti.static(self.has_flip):
            kept = self._flip_share(p, s) * self.v.grad[s + 1, p]
        S0 = ti.Vector.zero(float, 3)
        fx_bar = ti.Vector.zero(float, 3)
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            o = ti.static((i, j, k))
            weight, d_weight = self._weight_and_slope(w, dw, i, j, k)
            h = self._at_node(h0, B, o)
            g = self.grid_v_out[node + ti.Vector(o)]
            self._scatter_grad(node + ti.Vector(o), weight * h, -weight * kept, copy)
            fx_bar += d_weight * g.dot(h)
            if ti.static(self.has_flip):
                fx_bar -= d_weight * kept.dot(self.grid_v_old[node + ti.Vector(o)])
            S0 += weight * g
        fx_bar -= B.transpose() @ S0
        self.x.grad[s, p] = self.x.grad[s, p] + x_bar + inv_dx * fx_bar  # p is this thread's alone
        if ti.static(self.has_flip):
            self.v.grad[s, p] = self.v.grad[s, p] + kept

    @ti.kernel
    def _g2p_adjoint(self, s: ti.i32, n: ti.i32):
        """Reverse of g2p for substep s -> s + 1 (differentiable layouts): a scatter into the grid's
        velocity gradient, private per thread as p2g's (Taichi's own adjoint of the gather uses
        atomic adds and cost 5x the forward gather)."""
        if ti.static(self.private_scatter):
            for c in range(self.copies):
                for p in range(c * n // self.copies, (c + 1) * n // self.copies):
                    self._g2p_adjoint_particle(p, s, c)
        else:
            for p in range(n):
                self._g2p_adjoint_particle(p, s, -1)

    @ti.kernel
    def _g2p(self, s: ti.i32, so: ti.i32, n: ti.i32, j: ti.i32):
        for p in range(n):
            if ti.static(self.batched):
                if self._active(p, j):
                    self._g2p_particle(p, s, so)
                else:
                    self.x[so, p] = self.x[s, p]
                    self.v[so, p] = self.v[s, p]
                    self.C[so, p] = self.C[s, p]
            else:
                self._g2p_particle(p, s, so)

    @ti.kernel
    def _probe(self, s: ti.i32, t: ti.i32, n: ti.i32):
        """Mass-weighted sums of the tracked particles' x and v (divided by their mass later)."""
        for p in range(n):
            m = self.probe_w[p] * self.vol[p]
            self.com_x[t] += m * self.x[s, p]
            self.com_v[t] += m * self.v[s, p]

    @ti.kernel
    def _copy_slot(self, src: ti.i32, dst: ti.i32, n: ti.i32):
        for p in range(n):
            self.x[dst, p] = self.x[src, p]
            self.v[dst, p] = self.v[src, p]
            self.C[dst, p] = self.C[src, p]
            self.F[dst, p] = self.F[src, p]
            if ti.static(self.has_jp):
                self.Jp[dst, p] = self.Jp[src, p]

    @ti.func
    def _wave_speed(self, p, F):
        """The fastest wave particle p carries in its current deformation F, for the CFL condition.

        On the grid a particle's stiffness and mass both scale with its reference volume, so the
        speed is sqrt(k / rho0) with k the tangent of its Kirchhoff stress in the velocity gradient.
        Elastic models stiffen as they stretch: mu (F F^T - I)'s tangent (and the muscle's, of
        s a (F f)(F f)^T) grows with b = F F^T's largest eigenvalue (StVK's with its square), and
        lambda log J adds its tension: k = lambda (1 + max(log J, 0)) + (2 mu + m) lambda_max(b).
        lambda_max(b) is bounded above by the smaller of Gershgorin's bound and
        tr(b) / 3 + sqrt(2/3) |dev b| (exact at rest and in uniaxial states). At rest this is
        the speed the scene's time step uses (`wave0`); plastic models and water keep that one
        (their stresses are capped by their yield surfaces, hardening and bulk modulus)."""
        speed = self.wave0[p]
        model = self.material[p]
        if model <= ti.static(ID["stvk"]):  # the elastic models
            b = F @ F.transpose()
            mean = b.trace() / 3.0
            dev = b - mean * ti.Matrix.identity(float, 3)
            gershgorin = 0.0
            for i in ti.static(range(3)):
                gershgorin = ti.max(gershgorin, ti.abs(b[i, 0]) + ti.abs(b[i, 1]) + ti.abs(b[i, 2]))
            largest = ti.min(mean + ti.sqrt(2.0 / 3.0 * (dev * dev).sum()), gershgorin)
            if model == ti.static(ID["stvk"]):
                largest = largest * largest
            mu, la = self._lame(p)
            modulus = la * (1.0 + ti.max(ti.log(ti.max(F.determinant(), J_MIN)), 0.0)) + \
                (2.0 * mu + self.wave_added[p]) * ti.max(largest, 1.0)
            speed = ti.sqrt(modulus / self.rho[p])
        return speed

    @ti.kernel
    def _muscle_work(self, s: ti.i32, so: ti.i32, t: ti.i32, n: ti.i32):
        """Add the work the muscles did in substep s -> so: the force their stress put on the grid
        nodes, f_i = -sum_p V_p tau_p (4 / dx^2) (x_i - x_p) w_ip, times the nodes' new velocities,
        which is -dt sum_p V_p tau_p : C'_p with C' the velocity gradient g2p gathered (forward only)."""
        for p in range(n):
            tau = self._muscle_stress(p, self._trial(p, s), t)
            self.work[None] += -self._dt(p) * self.vol[p] * (tau * self.C[so, p]).sum()

    @ti.kernel
    def _check(self, s: ti.i32, n: ti.i32):
        """Count particles that are non-finite or outside the grid (remember the first one), and
        find the fastest particle and the fastest wave plus particle speed of this state."""
        self.n_bad[None] = 0
        self.first_bad[None] = n
        self.max_speed[None] = 0.0
        self.max_wave[None] = 0.0
        if ti.static(self.batched):
            for b in range(self.members):
                self.member_speed[b] = 0.0
                self.member_wave[b] = 0.0
        for p in range(n):
            x, v, F = self.x[s, p], self.v[s, p], self.F[s, p]
            size = self.dx[None] * ti.Vector([self.grid_shape[0] - 1, self.grid_shape[1] - 1,
                                              self.grid_shape[2] - 1])
            magnitude = x.norm_sqr() + v.norm_sqr() + F.norm_sqr()
            inside = (x >= 0).all() and (x <= size).all()
            if not (magnitude < 1e30) or not inside:
                self.n_bad[None] += 1
                ti.atomic_min(self.first_bad[None], p)
            wave = v.norm() + self._wave_speed(p, F)
            if ti.static(self.batched):  # each member is checked against its own time step
                ti.atomic_max(self.member_speed[self.member[p]], v.norm())
                ti.atomic_max(self.member_wave[self.member[p]], wave)
            else:
                ti.atomic_max(self.max_speed[None], v.norm())
                ti.atomic_max(self.max_wave[None], wave)



def _model_runs(material: np.ndarray) -> list[tuple[int, int, int]]:
    """(model, start, end) of each run of equal models in particle order (bodies are contiguous)."""
    edges = np.flatnonzero(np.diff(material)) + 1
    starts, ends = np.r_[0, edges], np.r_[edges, len(material)]
    return [(int(material[a]), int(a), int(b)) for a, b in zip(starts, ends)]


_free: "OrderedDict[int, tuple[tuple[int, Layout], _Storage]]" = OrderedDict()  # released storages, oldest first
_freed: list[tuple[int, _Storage]] = []  # (generation, storage) freed in this Taichi program
_in_use: dict[int, int] = {}  # id -> generation of the storages of live simulators


def _acquire(layout: Layout) -> _Storage:
    """A storage for `layout`: a released one if there is one (no compile), else a new one."""
    for key in [k for k, (wanted, _) in _free.items() if wanted[0] != runtime.generation]:
        del _free[key]  # fields of an earlier Taichi program: already gone
    for key, (wanted, storage) in reversed(_free.items()):
        if wanted == (runtime.generation, layout):
            del _free[key]
            break
    else:
        storage = _Storage(layout)
    _in_use[id(storage)] = runtime.generation
    return storage


def _release(generation: int, storage: _Storage) -> None:
    """Keep a closed simulator's storage for reuse, freeing the oldest beyond MAX_FREE_STORAGES."""
    _in_use.pop(id(storage), None)
    if generation != runtime.generation:
        return
    _free[id(storage)] = ((generation, storage.layout), storage)
    while len(_free) > MAX_FREE_STORAGES:
        _, (_, oldest) = _free.popitem(last=False)
        oldest.free()
        # Taichi keys a data-oriented object's compiled kernels by the object's id(): keep the
        # (now empty) object alive so no new storage can take its id and run its stale kernels
        _freed.append((generation, oldest))


def _recycle_program() -> None:
    """Start a fresh Taichi program once more than MAX_DEAD_STORAGES storages were freed in this
    one and no simulator is alive: Taichi keeps every storage's compiled kernels until a reset,
    so without this a long sweep over many layouts would grow without bound."""
    _freed[:] = [entry for entry in _freed if entry[0] == runtime.generation]
    if len(_freed) > MAX_DEAD_STORAGES and runtime.generation not in _in_use.values():
        runtime.reset()
        _freed.clear()


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
    with a checkpoint every `checkpoint_every` substeps (default: the memory-optimal
    sqrt(total / 2)). Without it, `step` advances the scene frame by frame at full speed.
    Compiled kernels are reused from any earlier simulator of the same layout that has been
    closed or garbage-collected; `capacity` (particles) lets simulators of designs with
    different particle counts share one layout.
    """

    def __init__(self, scene: Scene, particles: Particles, *, requires_grad: bool = False,
                 max_frames: int = 1, checkpoint_every: int | None = None, capacity: int | None = None) -> None:
        validate_scene(scene)
        _recycle_program()
        if requires_grad and ID["corotated"] in set(particles.material.tolist()):
            raise SceneError("material kind 'corotated' is invalid in a differentiable simulator (requires_grad): "
                             "its polar decomposition has no reverse mode in Taichi; use neo_hookean (the "
                             "robots' default) or stvk, or simulate it without gradients")
        runtime.init_taichi(scene.arch, scene.dtype)
        self.scene = scene
        self.np_real = np.float64 if scene.dtype == "float64" else np.float32
        self.timestep = self._time_step(particles)
        self.n = particles.n
        self.n_actuators = particles.n_actuators
        self.requires_grad = requires_grad
        self.max_frames = max_frames
        self.segment = checkpoint_every or max(1, math.ceil(math.sqrt(max_frames * self.timestep.substeps / 2)))
        self.body_names = [b.name for b in scene.bodies]
        models = tuple(sorted(set(int(m) for m in particles.material)))
        self.layout = self._layout(Layout(
            capacity=-(-max(particles.n, capacity or 0) // CAPACITY_STEP) * CAPACITY_STEP,
            n_actuators=particles.n_actuators,
            slots=self.segment + 1 if requires_grad else 2,
            rows=max_frames + 1,
            grid_shape=scene.grid_shape,
            models=models,
            has_muscles=particles.n_actuators > 0 and bool(np.any(particles.muscle_ratio > 0)),
            muscle_model=scene.muscle_model,
            has_terrain=scene.terrain.kind != "none",
            boundary_cells=scene.boundary_cells,
            requires_grad=requires_grad,
            scatter_copies=runtime.scatter_copies(),
            has_flip=scene.flip > 0 and any(m in FLIP_MODELS for m in models),
        ))
        self.k = _acquire(self.layout)
        self._generation = runtime.generation
        self._finalizer = weakref.finalize(self, _release, self._generation, self.k)
        self._initial_CF: tuple[np.ndarray, np.ndarray] | None = None
        self._initial_jp: np.ndarray | None = None
        self.rollouts = 0
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
        if k.has_flip:
            k.flip_ratio[None] = s.flip
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
            self._initial_jp = None
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
        wave0, added = wave_speeds(self.scene, p)
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
        self.timestep = timestep
        self._set_dt(timestep.dt)

    def set_initial_state(self, x=None, v=None, C=None, F=None, Jp=None) -> None:
        """Replace parts of the initial state (numpy, live particles only) and reset to it.

        Positions and velocities default to the particles'; C to zero, F to identity and the
        plastic volume ratio `Jp` (snow only; all ones is accepted anywhere) to one. A faster start
        gets a smaller time step.
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
        return self.particles, self._initial_CF, self._initial_jp

    def restore(self, snapshot: tuple) -> None:
        """Return to a `snapshot`: its design and initial state, with their time step."""
        particles, self._initial_CF, self._initial_jp = snapshot
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

    def _check_alive(self) -> None:
        if self.k is None:
            raise RuntimeError("this simulator was closed")
        if self._generation != runtime.generation:
            raise RuntimeError("Taichi was re-initialised (another arch or dtype) after this simulator "
                               "was built; build a new Simulator")

    # ------------------------------------------------------------------ stepping
    def _substep(self, s: int, so: int, t: int, j: int = 0, keep_grid: bool = False) -> None:
        """One substep from slot s into slot so, holding action row t; j: the substep's index within
        its control step (a batch member whose step is larger sits out the last ones). `keep_grid`:
        store the grid for the reverse pass (record s of the segment)."""
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
            self.k._sum_copies(False)
        self.k._grid_op()

    def _stress_update(self, s: int, so: int, t: int, j: int = 0) -> None:
        """The stress (muscle included) of substep s, and the plastic models' return-mapped F in slot so."""
        for model, start, end in self._runs:
            if model in HENCKY_PLASTIC:
                self.k._eigen_frames(s, start, end)
            self.k._constitutive_update(model, s, so, t, start, end, j)

    def _substep_grad(self, s: int, t: int, kept: bool) -> None:
        """Reverse of substep s -> s + 1: its grid (kept from the segment's recompute, or recomputed),
        then the adjoint kernels."""
        if kept:
            self.k._load_box(s, self._grid_boxes)
            self.k._load_grid(s, self._grid_store)
            self._stress_update(s, s + 1, t)
            self.k._grid_op()
        else:
            self._grid_update(s, s + 1, t)
        self.k._clear_grid_grad()
        self.k._g2p_adjoint(s, self.n)
        if self.k.private_scatter:
            self.k._sum_copies(True)
        self.k._grid_op.grad()
        self.k._p2g_adjoint(s, self.n)
        for model, start, end in self._runs:
            if model in HENCKY_PLASTIC:  # the eigenframe algebra by hand, the model's map by Taichi
                self.k._plastic_adjoint_front(model, s, s + 1, t, start, end)
                self.k._spectral_map.grad(model, s, s + 1, start, end)
                self.k._plastic_adjoint_back(model, s, start, end)
            elif model == ID["neo_hookean"]:
                self.k._neo_hookean_adjoint(s, s + 1, t, start, end)
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
        out[self.particles.material != ID["snow"]] = 1.0  # only snow particles keep J_p up to date
        return out

    def _state(self, slot: int) -> tuple[np.ndarray, ...]:
        """Everything a checkpoint must hold: (x, v, C, F) and, with snow, J_p."""
        return self.particles_state(slot) + ((self.plastic_volume_ratio(slot),) if self.k.has_jp else ())

    def _load(self, slot: int, state: tuple[np.ndarray, ...]) -> None:
        self.k._load_state(slot, self.n, *state[:4])
        if self.k.has_jp:
            self.k._load_jp(slot, self.n, state[4])

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
        self._rollout_segment = S
        self.rollouts += 1  # lets callers (the torch bridge) tell whether backward() is still theirs
        self.reset()
        if start is not None:
            self._load(0, tuple(np.ascontiguousarray(a, dtype=self.np_real) for a in
                                (start.x, start.v, start.C, start.F, start.Jp)))
        act = np.zeros((self.max_frames + 1, max(self.n_actuators, 1)))
        act[:T, :self.n_actuators] = actions
        self.k.act.from_numpy(act.astype(self.np_real))
        self.k.com_x.fill(0)
        self.k.com_v.fill(0)
        self._T = T
        self._checkpoints.clear()
        self._checkpoints.memory_bytes = CHECKPOINT_MEMORY_BYTES  # read per rollout, as GRID_STORE_BYTES is
        self._prepare_grid_store()
        self.k._probe(0, 0, self.n)
        self.k._check(0, self.n)
        # the substeps of each frame follow its starting state; the backward pass replays them
        self._substep_frame: list[int] = []  # frame (action row) of every substep
        s, keep = S, False  # slot within the segment; whether this segment keeps its grids
        for t in range(T):
            substeps = self._plan_frame()
            self.frame_substeps.append(substeps)
            for j in range(substeps):
                if s == S:  # a new segment: checkpoint its first state
                    if self._checkpoints:
                        self.k._copy_slot(S, 0, self.n)
                    self._checkpoints.append(self._state(0))
                    s = 0
                    # probably the last segment, still in the slots for backward: keep its grids too
                    keep = (substeps - j) + (T - 1 - t) * substeps <= S
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
        final = State(*(a.astype(np.float64) for a in (*self._final[:4], self.plastic_volume_ratio(self._slot))))
        self._rollout_changes = self._changes
        self.frame = T
        self._tracked_mass = float(self._probe_density @ self.particles.volume)
        self._com = (self.k.com_x.to_numpy()[:T + 1] / self._tracked_mass,
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
            self._grid_store = ti.ndarray(ti.f64 if self.np_real is np.float64 else ti.f32, shape)
            self._grid_boxes = ti.ndarray(ti.i32, (self.segment, 7))

    @property
    def rollout_is_current(self) -> bool:
        """True while nothing changed the simulator since the last rollout, so backward() may run."""
        return self._changes == self._rollout_changes

    def backward(self, com_x=None, com_v=None, x=None, v=None, C=None, F=None, Jp=None) -> Gradients:
        """Back-propagate d loss / d outputs of the last `rollout` to its inputs (repeatable).

        `com_x`, `com_v` (T+1, 3) and the final particles' `x`, `v` (N, 3), `C`, `F` (N, 3, 3)
        and `Jp` (N,) are the loss's gradients with respect to those outputs (None: zero). Each segment is
        recomputed from its checkpoint, then differentiated substep by substep in reverse; the
        gradient of a segment's first state carries into the previous one.
        """
        self._check_alive()
        if not self._checkpoints:
            raise RuntimeError("backward() needs a preceding rollout()")
        if not self.rollout_is_current:
            raise RuntimeError("the simulator changed since the last rollout() (step, reset, set_design, "
                               "set_initial_state or stress overwrite what backward() replays); run rollout() again")
        T, S, n, r = self._T, self._rollout_segment, self.n, self.np_real
        frame_of, substeps = self._substep_frame, self.frame_substeps
        for f in (self.k.vol, self.k.E, self.k.muscle, self.k.fiber, self.k.act, self.k.com_x, self.k.com_v):
            f.grad.fill(0)
        # com = S / M with S the probe's mass-weighted sum and M the tracked mass:
        # dL/dS = g / M goes through the probe kernel, dL/dM = -sum(g . com) / M is added below
        rows, M = self.max_frames + 1, self._tracked_mass
        dL_dM = 0.0
        for field, g, com in ((self.k.com_x, com_x, self._com[0]), (self.k.com_v, com_v, self._com[1])):
            full = np.zeros((rows, 3), r)
            if g is not None:
                g = np.asarray(g, dtype=np.float64).reshape(T + 1, 3)
                full[:T + 1] = g / M
                dL_dM -= float((g * com).sum()) / M
            field.grad.from_numpy(full)
        def seed(g, shape):
            return np.ascontiguousarray(np.zeros(shape) if g is None else np.reshape(g, shape), dtype=r)

        carry = (seed(x, (n, 3)), seed(v, (n, 3)), seed(C, (n, 3, 3)), seed(F, (n, 3, 3)), seed(Jp, (n,)))
        total = len(frame_of)
        last_of_frame = set(np.cumsum(substeps) - 1)  # substeps after which a frame's probe ran
        starts = list(range(0, total, S))
        for k in reversed(range(len(starts))):
            g0 = starts[k]
            L = min(S, total - g0)
            if self._segment_in_slots != k:  # recompute the segment's states, keeping their grids
                self._load(0, self._checkpoints[k])
                for s in range(L):
                    self._set_dt(self.scene.frame_dt / substeps[frame_of[g0 + s]])
                    self._substep(s, s + 1, frame_of[g0 + s], keep_grid=True)
                self._segment_in_slots = k
            boxes = self._grid_boxes.to_numpy()[:L]
            kept = boxes[:, 6] == 1
            self._largest_box = max(self._largest_box, int(np.prod(boxes[:, 3:6] - boxes[:, :3], axis=1).max()))
            for f in (self.k.x, self.k.v, self.k.C, self.k.F) + ((self.k.Jp,) if self.k.has_jp else ()):
                f.grad.fill(0)
            self.k._add_grad(L, n, *carry[:4])
            if self.k.has_jp:
                self.k._add_jp_grad(L, n, carry[4])
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
                     np.zeros(n, r))
            self.k._save_grad(0, n, *carry[:4])
            if self.k.has_jp:
                self.k._save_jp_grad(0, n, carry[4])
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
            F0=carry[3].astype(np.float64), Jp0=carry[4].astype(np.float64))
        for name, value in vars(grads).items():
            if not np.isfinite(value).all():
                raise SimulationError(f"the backward pass produced non-finite gradients for {name}")
        return grads
