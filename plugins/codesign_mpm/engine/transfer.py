"""The two transfers between particles and grid, each beside its hand-written adjoint.

    p2g -> scatter m v and the MLS force/affine term (the Kirchhoff stress from
           `constitutive`) to each particle's 27 nodes (quadratic B-splines, APIC)
    g2p -> gather v and C; x <- x + dt v; with `scene.flip` > 0 (0.99 in recipes) an elastic body's
           particle keeps that share of its own velocity plus the grid's change (FLIP)

Why FLIP: APIC hands each particle the grid's velocity, which keeps the particles' affine
motion and filters away the rest, at every substep: a damping whose rate is the number of
substeps per second. A robot on terrain, whose velocity near a stuck contact is not affine
within a cell, lost its progress as the step shrank (docs/log/contact.md sections 8-10). With the
FLIP share, a particle keeps its own velocity and adds the grid's change over the substep,
`v_p' = V_p + flip (v_p - V_p^old)` (V_p: the grid's new velocity at p, V_p^old: the grid's
velocity before forces, both gathered with p's weights); positions move with the grid (V_p),
as F does, so the deformation stays that of the grid's field. A particle crushed below `J_FLIP`
takes APIC's velocity alone: there the kept velocities created energy (docs/log/contact.md section 11).
A bare `Scene` defaults to flip 0; the locomotion environment to 0.99.

Scatters without atomics: on a CPU a float atomic add is a compare-and-swap loop, and p2g's
108 of them per particle bound the whole substep. There, each thread scatters its chunk of
particles into a private grid with plain adds (`grid_part`) and `grid._sum_copies_loop` adds the copies
(and leaves them zero for the next substep); g2p's adjoint scatters the same way. On a GPU,
whose atomic adds are native, both scatter into the grid directly.

Adjoints: p2g's and g2p's are written by hand (`_p2g_adjoint`, a gather; `_g2p_adjoint`, a
scatter, private per thread as p2g's) and checked against finite differences by the gradient
tests. Taichi's reverse mode of the 27-node stencils compiled for minutes (its passes grow with
a kernel's statements squared) and scattered with atomic adds; hand-written, they compile as
forward kernels.

`_Transfers` is a part of the engine's storage class (`storage._Storage`): its kernels read the
fields that class allocates.
"""
# (no `from __future__ import annotations`: Taichi reads kernel annotations at runtime)

import taichi as ti

from codesign_mpm.materials import MATERIALS
from codesign_mpm.runtime import FOLD_THREADS

# a particle compressed below this volume ratio takes APIC's velocity alone, whatever the FLIP share:
# crushed bodies (a drop faster than the body's wave speed, J -> 0.01) otherwise gain energy
# (docs/log/contact.md section 11); locomotion stays above J = 0.5
J_FLIP = 0.5


def flip_models() -> tuple[int, ...]:
    """The elastic models, whose bodies scene.flip applies to (plugins' included)."""
    return tuple(m.id for m in MATERIALS.values() if not m.plastic)


class _Transfers:
    """p2g, g2p and their adjoints (a mixin of `storage._Storage`)."""

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
        self._bounds_loop(s, n)

    @ti.func
    def _bounds_loop(self, s, n):
        for d in ti.static(range(3)):
            self.lo[d][None] = self.grid_shape[d]
            self.hi[d][None] = 0
        if ti.static(self.folded):  # a GPU: FOLD_THREADS threads, each folds its particles first
            for t in range(FOLD_THREADS):
                lo = ti.Vector([self.grid_shape[0], self.grid_shape[1], self.grid_shape[2]])
                hi = ti.Vector([0, 0, 0])
                p = t
                while p < n:
                    base = self._base(self.x[s, p])
                    lo, hi = ti.min(lo, base), ti.max(hi, base + 3)
                    p += FOLD_THREADS
                for d in ti.static(range(3)):
                    ti.atomic_min(self.lo[d][None], lo[d])
                    ti.atomic_max(self.hi[d][None], hi[d])
        else:
            ti.loop_config(serialize=self.serial)
            for p in range(n):
                base = self._base(self.x[s, p])
                for d in ti.static(range(3)):
                    ti.atomic_min(self.lo[d][None], base[d])
                    ti.atomic_max(self.hi[d][None], base[d] + 3)

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
    def _part(self, momentum, mass, before, in_contact):
        """A private grid node's entry (grid._sum_copies_loop reads it): momentum and mass, with FLIP the
        momentum before forces, with the surface contact the mass in contact."""
        m = momentum
        if ti.static(self.has_flip and self.surface_contact):
            return ti.Vector([m[0], m[1], m[2], mass, before[0], before[1], before[2], in_contact])
        elif ti.static(self.has_flip):
            return ti.Vector([m[0], m[1], m[2], mass, before[0], before[1], before[2]])
        elif ti.static(self.surface_contact):
            return ti.Vector([m[0], m[1], m[2], mass, in_contact])
        else:
            return ti.Vector([m[0], m[1], m[2], mass])

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
        in_contact = 0.0  # the mass taking part in the surface contact (contact.py)
        if ti.static(self.surface_contact):
            taking_part = self._takes_part(p, s)
            self.in_contact[p] = taking_part
            in_contact = mass * ti.cast(taking_part, float)
        # node n = (i, j, k) gets w_n (m v + A (n - fx) dx) = w_n (q0 + dx A n): A's columns added for
        # the offsets that are not 0, no 3x3 product per node (27 of them cost Taichi's frontend)
        a_dx, i_dx = dx * affine, dx * inertia
        q0 = mass * self.v[s, p] - a_dx @ fx
        q0_old = mass * self.v[s, p] - i_dx @ fx
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            o = ti.static((i, j, k))
            weight = w[i][0] * w[j][1] * w[k][2]
            momentum = weight * self._at_node(q0, a_dx, o)
            I = node + ti.Vector(o)
            before = ti.Vector.zero(float, 3)
            if ti.static(self.has_flip):
                before = weight * self._at_node(q0_old, i_dx, o)  # without the force
            if ti.static(self.private_scatter):  # plain adds: a float atomic add is a compare-and-swap loop
                c = self.grid_part[copy, I[0], I[1], I[2]]
                self.grid_part[copy, I[0], I[1], I[2]] = c + self._part(momentum, weight * mass, before,
                                                                         weight * in_contact)
            else:
                self.grid_v_in[I] += momentum
                self.grid_m[I] += weight * mass
                if ti.static(self.has_flip):
                    self.grid_q[I] += before
                if ti.static(self.surface_contact):
                    self.grid_contact[I] += weight * in_contact

    @ti.func
    def _p2g_adjoint_particle(self, p, s, tau):
        """p2g's adjoint, written by hand (differentiable layouts, whose stress tau is an input): from
        the grid's momentum and mass gradients at p's nodes to v, C, the volume and x at slot s, and
        the gradient of p's stress tau, returned.

        Node n = (i, j, k) gets w_n q_n and w_n m, with q_n = m v + A (n - fx) dx = c + dx A n,
        c = m v - dx A fx and A = -4 dt vol / dx^2 tau + m C. With g_n, h_n the momentum and mass
        gradients, S0 = sum w_n g_n and S1 = sum w_n g_n n^T: A's gradient is dx (S1 - S0 fx^T),
        fx's is sum (dw_n / dfx) (g_n . q_n + m h_n) - dx A^T S0 (n enters as constants, so the
        loop over nodes has no 3x3 products). With FLIP, node n also gets w_n (m v + m C (n - fx) dx)
        (the momentum before forces), whose gradient enters the same way with A = m C. With the
        surface contact, node n also gets w_n m b (b: 1 if p takes part, else 0; a switch)."""
        dt, dx = self._dt(p), self.dx[None]
        inv_dx = 1.0 / dx
        node, fx, w = self._stencil(p, s)
        dw = [fx - 1.5, 2.0 * (1.0 - fx), fx - 0.5]  # d w / d fx, per axis
        vol, v = self.vol[p], self.v[s, p]
        mass = self.rho[p] * vol
        stress_scale = -dt * 4.0 * inv_dx * inv_dx
        affine = stress_scale * vol * tau + mass * self.C[s, p]
        a_dx = dx * affine
        c = mass * v - a_dx @ fx
        taking_part = 0.0
        if ti.static(self.surface_contact):
            taking_part = ti.cast(self.in_contact[p], float)
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
            if ti.static(self.surface_contact):  # the mass in contact enters as the mass does
                h += taking_part * self.grid_contact.grad[node + ti.Vector(o)]
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
        self.vol.grad[p] = self.vol.grad[p] + self.rho[p] * mass_bar + stress_scale * (tau * affine_bar).sum()
        self.x.grad[s, p] = self.x.grad[s, p] + inv_dx * fx_bar
        return stress_scale * vol * affine_bar

    @ti.func
    def _p2g_one(self, p, s, so, t, j, copy):
        if ti.static(self.batched):
            if self._active(p, j):
                self._p2g_particle(p, s, so, t, copy)
            else:
                if ti.static(not self.separate_stress):  # else _constitutive_update held it
                    self._hold_deformation(p, s, so)
                if ti.static(self.surface_contact):  # sitting out, it takes no part in the contact
                    self.in_contact[p] = 0
        else:
            self._p2g_particle(p, s, so, t, copy)

    @ti.kernel
    def _p2g(self, s: ti.i32, so: ti.i32, t: ti.i32, n: ti.i32, j: ti.i32):
        self._p2g_loop(s, so, t, n, j)

    @ti.func
    def _p2g_loop(self, s, so, t, n, j):
        if ti.static(self.private_scatter):
            ti.loop_config(serialize=self.serial)
            for c in range(self.copies):  # one chunk of particles per thread, each into its own grid
                for p in range(c * n // self.copies, (c + 1) * n // self.copies):
                    self._p2g_one(p, s, so, t, j, c)
        else:
            ti.loop_config(serialize=self.serial)
            for p in range(n):
                self._p2g_one(p, s, so, t, j, -1)

    @ti.kernel
    def _p2g_adjoint(self, s: ti.i32, t: ti.i32, n: ti.i32):
        """Reverse of p2g for substep s (differentiable layouts; action row t): a gather per particle,
        no atomics. Written by hand, it compiles as a forward kernel (Taichi's reverse mode of the
        27-node scatter took minutes to compile). A `stress_in_adjoint` layout computes the stress
        here again and runs its adjoint too; the others leave the stress's gradient in tau.grad for
        the stress kernels' adjoints."""
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            if ti.static(self.stress_in_adjoint):
                F, tau = self._stress_again(p, s, t)
                tau_bar = self._p2g_adjoint_particle(p, s, tau)
                self._elastic_adjoint_particle(self.models[0], p, s, s + 1, t, F, tau_bar)
            else:
                self.tau.grad[p] = self._p2g_adjoint_particle(p, s, self.tau[p])

    @ti.func
    def _flip_share(self, p, s):
        """scene.flip for the elastic bodies, 0 (APIC alone) for the covers (with FLIP, a water column's
        mean pressure gradient fell 10% below rho g: docs/log/contact.md section 10) and for a particle
        crushed below J_FLIP in slot s. The switch is piecewise constant, so the adjoint needs no term
        for it."""
        share = 0.0
        for model in ti.static(flip_models()):
            if self.material[p] == model and self.F[s, p].determinant() > J_FLIP:
                share = self.flip_ratio[None]
                if ti.static(self.batched):  # each member at its own step (time_step.flip_share)
                    share = self.member_flip[self.member[p]]
        return share

    @ti.func
    def _g2p_particle(self, p, s, so):
        """Gather particle p's new velocity (with FLIP's share of its own) and affine velocity C from
        its 27 nodes; move it with the grid's velocity."""
        inv_dx = 1.0 / self.dx[None]
        node, fx, w = self._stencil(p, s)
        new_v = ti.Vector.zero(float, 3)
        old_v = ti.Vector.zero(float, 3)
        moment = ti.Matrix.zero(float, 3, 3)  # sum w_n v_n n^T: C = 4 / dx (moment - new_v fx^T)
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            o = ti.static((i, j, k))
            g_v = self.grid_v_out[node + ti.Vector(o)]
            weight = w[i][0] * w[j][1] * w[k][2]
            w_v = weight * g_v
            new_v += w_v
            for d in ti.static(range(3)):  # only the offsets that are not 0: no 3x3 product per node
                if ti.static(o[d]):
                    for e in ti.static(range(3)):
                        moment[e, d] += o[d] * w_v[e]
            if ti.static(self.has_flip):
                old_v += weight * self.grid_v_old[node + ti.Vector(o)]
        new_C = 4.0 * inv_dx * (moment - new_v.outer_product(fx))
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
            self.grid_part[copy, I[0], I[1], I[2]] = part + self._part(g, 0.0, g_old, 0.0)
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
        # the reverse substep's first writes to slot s's gradients, so assignments (p is this thread's
        # alone): the kernels after this one add to them, and no pass need clear the segment's slots
        self.x.grad[s, p] = x_bar + inv_dx * fx_bar
        self.v.grad[s, p] = kept
        self.C.grad[s, p] = ti.Matrix.zero(float, 3, 3)
        self.F.grad[s, p] = ti.Matrix.zero(float, 3, 3)
        if ti.static(self.has_jp):
            self.Jp.grad[s, p] = 0.0
        if ti.static(self.contact_memory):
            self.u.grad[s, p] = ti.Vector.zero(float, 3)

    @ti.kernel
    def _g2p_adjoint(self, s: ti.i32, n: ti.i32):
        """Reverse of g2p for substep s -> s + 1 (differentiable layouts): a scatter into the grid's
        velocity gradient, private per thread as p2g's (Taichi's own adjoint of the gather uses
        atomic adds and cost 5x the forward gather), the private grids summed in the same launch."""
        if ti.static(self.private_scatter):
            ti.loop_config(serialize=self.serial)
            for c in range(self.copies):
                for p in range(c * n // self.copies, (c + 1) * n // self.copies):
                    self._g2p_adjoint_particle(p, s, c)
            self._sum_copies_loop(True)
        else:
            ti.loop_config(serialize=self.serial)
            for p in range(n):
                self._g2p_adjoint_particle(p, s, -1)

    @ti.kernel
    def _g2p(self, s: ti.i32, so: ti.i32, n: ti.i32, j: ti.i32):
        self._g2p_loop(s, so, n, j)

    @ti.func
    def _g2p_loop(self, s, so, n, j):
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            if ti.static(self.batched):
                if self._active(p, j):
                    self._g2p_particle(p, s, so)
                else:
                    self.x[so, p] = self.x[s, p]
                    self.v[so, p] = self.v[s, p]
                    self.C[so, p] = self.C[s, p]
                    if ti.static(self.contact_memory):  # sitting out, it keeps its springs
                        self.u[so, p] = self.u[s, p]
            else:
                self._g2p_particle(p, s, so)
