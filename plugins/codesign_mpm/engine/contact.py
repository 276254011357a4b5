"""The surface contact (`terrain.contact: surface`): each particle's contact with the terrain's
exact surface, handed to p2g, and the node holding it feeds (`grid._grid_op`).

    contact -> j_n = max(0, allowed - v_n), v = v_p + dt g (per unit mass),
               allowed = -phi / dt above the surface (approach at most to it within the step),
                         PUSH_OUT (-phi) / dt below it (a share of the depth undone per substep);
               the particle's normal impulse m j_n n, its friction budget mu m j_n, and its share in
               contact min(1, j_n / (|g . n| dt)) (1 for a particle the terrain carries)
    p2g     -> scatters the impulse with the momentum, the budget and m times the share to the nodes
    grid_op -> a node's share in contact (its contact mass over its mass) loses its approach
               velocity; Coulomb friction stops its sliding within mu times that impulse plus the
               budget; the node contact holds only nodes BACKSTOP cells below the surface

Why: the default node contact (`nodes`) holds whole layers of nodes, the ones below the surface,
and a body grips through the particles whose stencils reach them, so where the surface falls
within a cell moved a gait's distance by 14 to 31% at every dx (docs/contact.md section 13).
Here what is held, and how much, follows the particles at the surface: a node is held in
proportion to the mass the contact carries there, whatever its own height. Why the node holds
too: a particle's impulse stops only its own approach, so alone it is a soft contact (a body
rang on it and slid on a slope within the friction cone); a node held by its share stops the
mass above as well, and friction bounded by the normal impulse sticks a body exactly.
Measured in docs/contact.md section 14 (also what it costs: its time-step dependence at dx 1/32).

`_Contact` is a part of the engine's storage class (`storage._Storage`). The kernel's adjoint is
Taichi's (`_terrain_contact.grad`): it is per particle, without a stencil, and compiles quickly.
"""
# (no `from __future__ import annotations`: Taichi reads kernel annotations at runtime)

import taichi as ti

PUSH_OUT = 0.1  # share of a particle's depth below the surface undone per substep (1 made bodies bounce)
BACKSTOP = 1.5  # cells below the surface from which the node contact holds material whole


class _Contact:
    """The particles' surface contact (a mixin of `storage._Storage`)."""

    @ti.func
    def _bilinear(self, field: ti.template(), i0, k0, fu, fw):
        """`field` (per (x, z) node column) between the four columns around a point."""
        return ((1 - fu) * (1 - fw) * field[i0, k0] + fu * (1 - fw) * field[i0 + 1, k0]
                + (1 - fu) * fw * field[i0, k0 + 1] + fu * fw * field[i0 + 1, k0 + 1])

    @ti.kernel
    def _terrain_contact(self, s: ti.i32, n: ti.i32):
        """Each particle's normal impulse, friction budget and share in contact at slot s (zero away
        from the terrain) into `contact`. Branch-free (select, min, max) for Taichi's reverse mode."""
        for p in range(n):
            dt, dx = self._dt(p), self.dx[None]
            xp = self.x[s, p]
            u, w = xp[0] / dx, xp[2] / dx
            i0 = ti.min(ti.max(ti.cast(ti.floor(u), ti.i32), 0), self.grid_shape[0] - 2)
            k0 = ti.min(ti.max(ti.cast(ti.floor(w), ti.i32), 0), self.grid_shape[2] - 2)
            fu, fw = u - i0, w - k0
            nrm = self._bilinear(self.normal, i0, k0, fu, fw)
            nrm = nrm / ti.sqrt(nrm.dot(nrm))
            phi = (xp[1] - self._bilinear(self.height, i0, k0, fu, fw)) * nrm[1]  # height above, to first order
            v = self.v[s, p] + dt * self.gravity[None]
            vn = v.dot(nrm)
            jn = ti.max(0.0, ti.select(phi > 0, -phi / dt, -PUSH_OUT * phi / dt) - vn)
            impulse = self.rho[p] * self.vol[p] * jn
            share = ti.min(1.0, jn / ti.max(ti.abs(self.gravity[None].dot(nrm)) * dt, 1e-12))
            self.contact[p] = ti.Vector([impulse * nrm[0], impulse * nrm[1], impulse * nrm[2],
                                         self.friction[None] * impulse, share])
