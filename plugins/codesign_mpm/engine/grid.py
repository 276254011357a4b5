"""The grid: clearing the touched box, summing p2g's private copies, keeping a substep's grid for
the reverse pass and replaying it there, and the grid update

    v = p / m + dt g; terrain (height-map SDF, Coulomb friction); domain walls

The terrain holds the nodes below its surface (`terrain.contact: nodes`); with the surface contact
(`contact`, whose impulses the grid takes after this update) only those `contact.BACKSTOP` cells
down.

`_Grid` is a part of the engine's storage class (`storage._Storage`). Its kernels visit only the
box of nodes the particles touch (`transfer._bounds`), in every batch member's grid; the grid
update's adjoint is Taichi's (`_grid_op.grad`).
"""
# (no `from __future__ import annotations`: Taichi reads kernel annotations at runtime)

import taichi as ti

from codesign_mpm.engine.contact import BACKSTOP, MASS_EPS


class _Grid:
    """The grid's kernels (a mixin of `storage._Storage`)."""

    @ti.func
    def _node(self, b, i, j, k):
        """Node (i, j, k) of member b's grid in the grid fields (members side by side along x); the
        grid kernels visit the touched box (`_bounds`) in every member's grid."""
        return ti.Vector([b * self.grid_shape[0] + i, j, k])

    @ti.kernel
    def _clear_grid(self):
        self._clear_grid_loop()

    @ti.func
    def _clear_grid_loop(self):
        ti.loop_config(serialize=self.serial)
        for b, i, j, k in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            I = self._node(b, i, j, k)
            self.grid_v_in[I] = ti.Vector.zero(float, 3)
            self.grid_m[I] = 0.0
            if ti.static(self.has_flip):
                self.grid_q[I] = ti.Vector.zero(float, 3)
            if ti.static(self.surface_contact):
                self.grid_contact[I] = 0.0

    @ti.kernel
    def _sum_copies(self):
        self._sum_copies_loop(False)

    @ti.func
    def _sum_copies_loop(self, adjoint: ti.template()):
        """Sum the private grids, and leave them zero for their next use: into the grid's momentum and
        mass (and momentum before forces) after p2g, or into grid_v_out's (and grid_v_old's) gradient
        after g2p's adjoint."""
        ti.loop_config(serialize=self.serial)
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
                if ti.static(self.surface_contact):
                    self.grid_contact[I] = total[self.part_width - 1]

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
        ti.loop_config(serialize=self.serial)
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
                if ti.static(self.surface_contact):
                    store[k, index, self.part_width - 1] = self.grid_contact[I]

    @ti.kernel
    def _replay_grid(self, k: ti.i32, store: ti.types.ndarray(), box: ti.types.ndarray()):
        """The reverse pass's grid of a kept substep, in one launch: its box and the grid momentum and
        mass `_store_grid` kept as record k, the grid update on them (as `_grid_op`), and the grid's
        gradients cleared; each node is its loop iteration's alone."""
        for d in ti.static(range(3)):
            self.lo[d][None] = box[k, d]
            self.hi[d][None] = box[k, 3 + d]
        lo = ti.Vector([box[k, 0], box[k, 1], box[k, 2]])
        extent = ti.Vector([box[k, 3], box[k, 4], box[k, 5]]) - lo
        ti.loop_config(serialize=self.serial)
        for b, i, j, l in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            I = self._node(b, i, j, l)
            index = ((b * extent[0] + i - lo[0]) * extent[1] + j - lo[1]) * extent[2] + l - lo[2]
            self.grid_v_in[I] = ti.Vector([store[k, index, 0], store[k, index, 1], store[k, index, 2]])
            self.grid_m[I] = store[k, index, 3]
            if ti.static(self.has_flip):
                self.grid_q[I] = ti.Vector([store[k, index, 4], store[k, index, 5], store[k, index, 6]])
            if ti.static(self.surface_contact):
                self.grid_contact[I] = store[k, index, self.part_width - 1]
            self._grid_op_at(b, i, j, l)
            self._clear_grid_grad_at(I)

    @ti.kernel
    def _clear_grid_grad(self):
        ti.loop_config(serialize=self.serial)
        for b, i, j, k in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            self._clear_grid_grad_at(self._node(b, i, j, k))

    @ti.func
    def _clear_grid_grad_at(self, I):
        self.grid_v_in.grad[I] = ti.Vector.zero(float, 3)
        self.grid_m.grad[I] = 0.0
        self.grid_v_out.grad[I] = ti.Vector.zero(float, 3)
        if ti.static(self.has_flip):
            self.grid_q.grad[I] = ti.Vector.zero(float, 3)
            self.grid_v_old.grad[I] = ti.Vector.zero(float, 3)
        if ti.static(self.surface_contact):
            self.grid_contact.grad[I] = 0.0

    @ti.kernel
    def _grid_op(self):
        ti.loop_config(serialize=self.serial)
        for b, i, j, k in ti.ndrange(self.members, (self.lo[0][None], self.hi[0][None]),
                                     (self.lo[1][None], self.hi[1][None]), (self.lo[2][None], self.hi[2][None])):
            self._grid_op_at(b, i, j, k)

    @ti.func
    def _grid_op_at(self, b, i, j, k):
        """Node (i, j, k) of member b: velocity from momentum, gravity, the terrain, the walls."""
        bc = ti.static(self.boundary_cells)
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
                below = 0.0  # how deep below the surface a node is held whole
                if ti.static(self.surface_contact):
                    below = BACKSTOP * dx
                if (ti.cast(I[1], float) * dx - self.height[local[0], local[2]]) * nrm[1] < -below:
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
