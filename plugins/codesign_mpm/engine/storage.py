"""Particle storage: the Taichi fields of one layout, its slots and their checkpoints' kernels,
and the pool that shares compiled storages between simulators.

Particle state lives in `slots`: two (ping-pong) for plain simulation, or S + 1 for a
differentiable segment of S substeps. A differentiable rollout stores the state only at
segment starts (checkpoints, `codesign_mpm.engine.checkpoints`) and recomputes each segment in the
backward pass, so memory grows with T/S + S rather than T substeps. That recompute keeps each
substep's grid (the touched box, `grid._store_grid`) for the reverse pass, which then runs only
the stress and grid_op again.

`_Storage` is one class (Taichi compiles kernels per object) assembled from the engine's parts:
`transfer._Transfers` (p2g, g2p, adjoints), `contact._Contact` (the surface contact at the particles),
`grid._Grid` (grid update, terrain, walls),
`eigen._Eigen` (eigenframes) and `constitutive._Constitutive` (materials, muscles); it
allocates every field they use, here, in one order (field ids key Taichi's offline cache).
"""
# (no `from __future__ import annotations`: Taichi reads kernel annotations at runtime)

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import taichi as ti
from taichi.lang import impl

from codesign_mpm import runtime
from codesign_mpm.runtime import FOLD_THREADS
from codesign_mpm.engine.constitutive import _Constitutive
from codesign_mpm.engine.contact import _Contact
from codesign_mpm.engine.eigen import JACOBI_TOL_ULPS, _Eigen
from codesign_mpm.engine.grid import _Grid
from codesign_mpm.engine.transfer import _Transfers
from codesign_mpm.materials import N_PARAMS, material

CAPACITY_STEP = 1024  # particle storage is allocated in these steps so similar scenes share kernels
MAX_FREE_STORAGES = 16  # compiled storages kept for reuse after their simulators close; older ones are freed
FREE_STORAGE_BYTES = 2 * 1024**3
"""The fields' memory the released storages may keep beyond the newest one. A storage rebuilt after
eviction pays Taichi's frontend again (and a compile, when its field ids differ from the first
build's): small scenes keep many; at the paper's scale a forward storage takes about 140 MB, a
differentiable one of 200 frames about 570 MB, so four of those stay as before the budget."""
MAX_DEAD_STORAGES = 32  # freed storages (their kernels stay compiled) before an idle program is recycled


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
    folded: bool = False  # reductions fold per thread first (runtime.fold_reductions)
    serial: bool = False  # loops on the launching thread: too little work for the thread pool (runtime.serial_loops)
    members: int = 1  # scenes simulated side by side (codesign_mpm.engine.batch); 1: a plain simulator
    has_flip: bool = False  # FLIP's share in the elastic bodies' velocity update (scene.flip > 0)
    surface_contact: bool = False  # the terrain's contact at its exact surface (terrain.contact: surface, spring)
    contact_memory: bool = False  # the surface contact as springs whose friction remembers (terrain.contact: spring)

    @property
    def has_params(self) -> bool:
        """Per-particle parameter vectors: the non-elastic models', and a plugin's elastic model with parameters."""
        return any(material(m).plastic or material(m).parameters for m in self.models)

    def slot_bytes(self, real_bytes: int) -> int:
        """The fields' memory of one slot of particle state (x, v, C, F; J_p beside parameters; the
        springs), gradients included: what each substep of a differentiable segment costs."""
        values = 3 + 3 + 9 + 9 + self.has_params + 3 * self.contact_memory
        return self.capacity * values * real_bytes * (2 if self.requires_grad else 1)


@runtime.data_oriented
class _Storage(_Transfers, _Contact, _Grid, _Eigen, _Constitutive):
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
        self.has_params = layout.has_params
        # the stress in kernels of its own ahead of p2g: plastic models (one small kernel per model
        # compiles far faster than all of them fused into the scatter) and every differentiable
        # layout (p2g's adjoint is then the scatter's alone, differentiated plane by plane)
        self.separate_stress = self.has_params or layout.requires_grad
        # a differentiable layout of one model whose stress adjoint is written by hand (neo-Hookean
        # robots) computes the stress again inside p2g's adjoint and runs the stress's adjoint there
        # too: one pass over the particles in the reverse substep where there were three
        self.stress_in_adjoint = (layout.requires_grad and len(layout.models) == 1
                                  and material(layout.models[0]).hand_adjoint)
        self.has_jp = any(material(m).plastic_volume for m in layout.models)  # snow's J_p is part of the state
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
        self.folded = layout.folded  # reductions into one value fold per thread first (runtime.FOLD_THREADS)
        self.serial = layout.serial  # each kernel's loops run serially (ti.loop_config), runtime.serial_loops
        self.has_flip = layout.has_flip
        self.surface_contact = layout.surface_contact
        self.contact_memory = layout.contact_memory
        # a private grid node: momentum, mass (with FLIP the momentum before forces; with the surface
        # contact the mass in contact, last)
        self.part_width = 4 + 3 * layout.has_flip + layout.surface_contact
        # a batch's member grids lie side by side along x: member b owns nodes [b nx, (b + 1) nx)
        self.grid_total = (layout.grid_shape[0] * layout.members,) + tuple(layout.grid_shape[1:])
        n, K, gs, grad = layout.capacity, max(layout.n_actuators, 1), layout.grid_shape, layout.requires_grad
        slots, rows = layout.slots, layout.rows
        builder = ti.FieldsBuilder()
        real_bytes = 8 if impl.current_cfg().default_fp == ti.f64 else 4
        self.nbytes = 0  # the fields' memory, which a released storage keeps while pooled (FREE_STORAGE_BYTES)

        def placed(make, shape, values, differentiable=False, item_bytes=real_bytes):
            """A field of `shape` in this storage's tree (with its gradient if asked and grad is on)."""
            f = make(needs_grad=grad and differentiable)
            node = builder.dense(ti.axes(*range(len(shape))), shape) if shape else builder
            node.place(f, f.grad) if grad and differentiable else node.place(f)
            self.nbytes += int(np.prod(shape)) * values * item_bytes * (2 if grad and differentiable else 1)
            return f

        def vec(k, shape, differentiable=False):
            return placed(lambda **kw: ti.Vector.field(k, float, **kw), shape, k, differentiable)

        def mat(shape, differentiable=False):
            return placed(lambda **kw: ti.Matrix.field(3, 3, float, **kw), shape, 9, differentiable)

        def scalar(shape, differentiable=False, dtype=float):
            return placed(lambda **kw: ti.field(dtype, **kw), shape, 1, differentiable,
                          real_bytes if dtype is float else 4)

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
        self.probe_origin = vec(3, ())  # the probe sums m (x - origin): float32 keeps the motion's digits
        self.act = vec(K, (rows,), True)
        self.com_x = vec(3, (rows,), True)
        self.com_v = vec(3, (rows,), True)
        self.grid_v_in = vec(3, self.grid_total, True)
        self.grid_m = scalar(self.grid_total, True)
        self.grid_v_out = vec(3, self.grid_total, True)
        if self.private_scatter:  # p2g's chunk c of the particles scatters into copy c; _sum_copies_loop adds them
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
            self.member_flip = scalar((layout.members,))  # FLIP's share at each member's own step (pic_time)
        if self.has_flip:  # last, as the batch's fields
            self.grid_q = vec(3, self.grid_total, True)  # momentum before forces: sum w m (v + C (x_i - x_p))
            self.grid_v_old = vec(3, self.grid_total, True)  # its velocity, grid_q / m (grid_op)
            self.flip_ratio = scalar(())
        if self.surface_contact:  # last, as FLIP's (contact.py)
            self.in_contact = scalar((n,), dtype=ti.i32)  # whether a particle takes part (contact._takes_part)
            self.impulse = vec(3, (n,), True)  # each particle's contact impulse (contact._contact_impulse)
            self.grid_contact = scalar(self.grid_total, True)  # a node's mass in contact
        if self.contact_memory:  # last, as the surface contact's (contact._spring_impulse)
            self.u = vec(3, (slots, n), True)  # each particle's tangential spring: its displacement from its anchor
            self.contact_stiffness = scalar(())
            self.contact_damping = scalar(())
        self._tree = runtime.fields_tree(builder)

    @ti.kernel
    def _forward_substep(self, s: ti.i32, so: ti.i32, t: ti.i32, n: ti.i32, j: ti.i32, full_grid: ti.template()):
        """One substep of a layout whose stress p2g computes, from slot s into slot so, in one launch:
        each stage's loop runs after the one before as the separate kernels would, over the same
        per-particle or per-node functions (the same arithmetic in the same order), without a
        launch and a return to Python each (issue 48). The kernels that Taichi differentiates
        (grid_op, the contact's) keep their loops in the kernel itself, as its reverse mode needs."""
        if ti.static(full_grid):
            for d in ti.static(range(3)):
                self.lo[d][None] = 0
                self.hi[d][None] = self.grid_shape[d]
        else:
            self._bounds_loop(s, n)
        if ti.static(not self.private_scatter):
            self._clear_grid_loop()
        self._p2g_loop(s, so, t, n, j)
        if ti.static(self.private_scatter):
            self._sum_copies_loop(False)
        ti.loop_config(serialize=self.serial)
        for b, i, k, l in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            self._grid_op_at(b, i, k, l)
        if ti.static(self.surface_contact):
            # parallel even in a serial storage: a kernel's serial loops compile into one function,
            # and sharing it with the grid update, fast-math rounded the spring's impulse an ulp
            # away from `_spring_impulse`'s (13 of 975 values), whose loop is its kernel's alone;
            # a parallel loop is a function of its own
            for p in range(n):
                if ti.static(self.contact_memory):
                    self._spring_impulse_of(p, s, so)
                else:
                    self._contact_impulse_of(p, s)
            ti.loop_config(serialize=self.serial)
            for p in range(n):
                self._contact_scatter_of(p, s, 1.0)
        self._g2p_loop(s, so, n, j)

    def free(self) -> None:
        """Give the fields' memory back; the storage is unusable afterwards."""
        self._tree.destroy()

    @ti.kernel
    def _load_state(self, s: ti.i32, n: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(),
                    C: ti.types.ndarray(), F: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
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
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            for i in ti.static(range(3)):
                x[p, i] = self.x[s, p][i]
                v[p, i] = self.v[s, p][i]
                for j in ti.static(range(3)):
                    C[p, i, j] = self.C[s, p][i, j]
                    F[p, i, j] = self.F[s, p][i, j]

    @ti.kernel
    def _save_x(self, s: ti.i32, n: ti.i32, x: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            for i in ti.static(range(3)):
                x[p, i] = self.x[s, p][i]

    @ti.kernel
    def _save_grad(self, s: ti.i32, n: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(),
                   C: ti.types.ndarray(), F: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            for i in ti.static(range(3)):
                x[p, i] = self.x.grad[s, p][i]
                v[p, i] = self.v.grad[s, p][i]
                for j in ti.static(range(3)):
                    C[p, i, j] = self.C.grad[s, p][i, j]
                    F[p, i, j] = self.F.grad[s, p][i, j]

    @ti.kernel
    def _set_grad(self, s: ti.i32, n: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(),
                  C: ti.types.ndarray(), F: ti.types.ndarray()):
        """The gradients of slot s's state (a segment's last: its first substep's reverse assigns
        those of each earlier slot)."""
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            for i in ti.static(range(3)):
                self.x.grad[s, p][i] = x[p, i]
                self.v.grad[s, p][i] = v[p, i]
                for j in ti.static(range(3)):
                    self.C.grad[s, p][i, j] = C[p, i, j]
                    self.F.grad[s, p][i, j] = F[p, i, j]

    @ti.kernel
    def _load_jp(self, s: ti.i32, n: ti.i32, jp: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            self.Jp[s, p] = jp[p]

    @ti.kernel
    def _save_jp(self, s: ti.i32, n: ti.i32, jp: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            jp[p] = self.Jp[s, p]

    @ti.kernel
    def _save_jp_grad(self, s: ti.i32, n: ti.i32, jp: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            jp[p] = self.Jp.grad[s, p]

    @ti.kernel
    def _set_jp_grad(self, s: ti.i32, n: ti.i32, jp: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            self.Jp.grad[s, p] = jp[p]

    @ti.kernel
    def _load_u(self, s: ti.i32, n: ti.i32, u: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            for i in ti.static(range(3)):
                self.u[s, p][i] = u[p, i]

    @ti.kernel
    def _save_u(self, s: ti.i32, n: ti.i32, u: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            for i in ti.static(range(3)):
                u[p, i] = self.u[s, p][i]

    @ti.kernel
    def _save_u_grad(self, s: ti.i32, n: ti.i32, u: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            for i in ti.static(range(3)):
                u[p, i] = self.u.grad[s, p][i]

    @ti.kernel
    def _set_u_grad(self, s: ti.i32, n: ti.i32, u: ti.types.ndarray()):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            for i in ti.static(range(3)):
                self.u.grad[s, p][i] = u[p, i]

    @ti.kernel
    def _copy_slot(self, src: ti.i32, dst: ti.i32, n: ti.i32):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            self.x[dst, p] = self.x[src, p]
            self.v[dst, p] = self.v[src, p]
            self.C[dst, p] = self.C[src, p]
            self.F[dst, p] = self.F[src, p]
            if ti.static(self.has_jp):
                self.Jp[dst, p] = self.Jp[src, p]
            if ti.static(self.contact_memory):
                self.u[dst, p] = self.u[src, p]

    @ti.kernel
    def _probe(self, s: ti.i32, t: ti.i32, n: ti.i32):
        """Mass-weighted sums of the tracked particles' x - probe_origin and v (divided by their mass
        and the origin added back later, in float64)."""
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            m = self.probe_w[p] * self.vol[p]
            self.com_x[t] += m * (self.x[s, p] - self.probe_origin[None])
            self.com_v[t] += m * self.v[s, p]

    @ti.kernel
    def _check(self, s: ti.i32, n: ti.i32):
        """Count particles that are non-finite or outside the grid (remember the first one), and
        find the fastest particle and the fastest wave plus particle speed of this state."""
        self.n_bad[None] = 0
        self.first_bad[None] = n
        self.max_speed[None] = 0.0
        self.max_wave[None] = 0.0
        if ti.static(self.batched):
            ti.loop_config(serialize=self.serial)
            for b in range(self.members):
                self.member_speed[b] = 0.0
                self.member_wave[b] = 0.0
        if ti.static(self.folded and not self.batched):  # a GPU: FOLD_THREADS threads, each folds its particles first
            for t in range(FOLD_THREADS):
                bad, first, speed, wave = 0, n, 0.0, 0.0
                p = t
                while p < n:
                    p_bad, p_speed, p_wave = self._checked(s, p)
                    if p_bad:
                        bad += 1
                        first = ti.min(first, p)
                    speed, wave = ti.max(speed, p_speed), ti.max(wave, p_wave)
                    p += FOLD_THREADS
                self.n_bad[None] += bad
                ti.atomic_min(self.first_bad[None], first)
                ti.atomic_max(self.max_speed[None], speed)
                ti.atomic_max(self.max_wave[None], wave)
        else:
            ti.loop_config(serialize=self.serial)
            for p in range(n):
                bad, speed, wave = self._checked(s, p)
                if bad:
                    self.n_bad[None] += 1
                    ti.atomic_min(self.first_bad[None], p)
                if ti.static(self.batched):  # each member is checked against its own time step
                    ti.atomic_max(self.member_speed[self.member[p]], speed)
                    ti.atomic_max(self.member_wave[self.member[p]], wave)
                else:
                    ti.atomic_max(self.max_speed[None], speed)
                    ti.atomic_max(self.max_wave[None], wave)

    @ti.func
    def _checked(self, s, p):
        """Particle p of slot s: whether it is non-finite or outside the grid, its speed, and its
        fastest wave plus its speed."""
        x, v, F = self.x[s, p], self.v[s, p], self.F[s, p]
        size = self.dx[None] * ti.Vector([self.grid_shape[0] - 1, self.grid_shape[1] - 1,
                                          self.grid_shape[2] - 1])
        magnitude = x.norm_sqr() + v.norm_sqr() + F.norm_sqr()
        inside = (x >= 0).all() and (x <= size).all()
        speed = v.norm()
        return not (magnitude < 1e30) or not inside, speed, speed + self._wave_speed(p, F)


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
    """Keep a closed simulator's storage for reuse, freeing the oldest beyond MAX_FREE_STORAGES or,
    the newest one aside, beyond FREE_STORAGE_BYTES of fields."""
    _in_use.pop(id(storage), None)
    if generation != runtime.generation:
        return
    _free[id(storage)] = ((generation, storage.layout), storage)
    while len(_free) > MAX_FREE_STORAGES or (
            len(_free) > 1 and sum(kept.nbytes for _, kept in _free.values()) > FREE_STORAGE_BYTES):
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

