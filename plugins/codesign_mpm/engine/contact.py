"""The surface contacts (`terrain.contact: surface | spring`) at the terrain's exact surface, solved
on the grid after its update. `surface`: a constraint on the velocity of the particles touching it.

    p2g -> per particle, whether it takes part (it would end the substep within half its own
        spacing of the surface); scatters the mass taking part, so a node knows its share in
        contact s = M_c / M
    _contact_impulse (after the grid update) -> per particle taking part: the surface's normal n
        at it, the normal velocity it may have, a = -phi / dt above the surface (reach it within
        the substep, not pass it) or PUSH_OUT (-phi) / dt below it, and from the grid's velocity at
        it, v = sum w v_i, the normal impulse j_n = max(0, m* (a - v . n)) and Coulomb friction
        j_t = min(m* |v_t|, mu j_n) against its sliding v_t, with m* = m / sum w s_i
    _contact_scatter -> adds each impulse to its nodes' velocities, w j / M_i

Why this form: the constraint is on the particle (where the surface is), its unknowns on the nodes
(where the momentum is). A particle's impulse spread over its nodes changes its own velocity by
j sum w^2 / M_i, and its neighbours' through the nodes they share; m* splits each node's mass
among the particles in contact there (in proportion to their weights), so a layer of particles
that all need the same change gets it in one pass, on the mass that carries them and no more
(one Jacobi pass of a mass-split solve: more passes moved a gait's distance by under 10% and a
block resting on an incline by under 1%). What this fixes, measured in docs/log/contact.md section 15:
- where the surface falls within a cell no longer moves the grip (the node contact holds whole
  layers of nodes, so it did, by 14 to 31% at every dx: section 13);
- the answer converges in time: an earlier surface contact (section 14) took part of the normal
  load as particle impulses before p2g and held nodes by their share after it, a split that
  depended on the step (a gait went 21 -> 31 mm from cfl 0.4 to 0.0125 at dx 1/48); here the
  whole impulse is computed once, from the velocity the substep's forces produced.
The node contact stays as a backstop BACKSTOP cells below the surface (`grid._grid_op`).

`spring` (`_spring_impulse`) keeps the same particles, effective mass m* and scatter, but the
impulse is that of a spring-damper of physical stiffness over the substep, and friction remembers:

    normal: a spring-damper on the depth of the particle's lowest point below the surface (gap =
        phi - spacing / 2) of stiffness k = stiffness x spacing^2 (its share of the contact area: a
        body of weight W resting on area A sinks W / (A stiffness)) and damping c = 2 zeta
        sqrt(k m*), implicit in both (stable at any step, exact at rest):
        v_n' = (v_n - dt k/m* gap) / (1 + dt c/m* + dt^2 k/m*), j_n = m* (v_n' - v_n) >= 0 (it
        pushes, never pulls), while the particle touches at the substep's end
    tangential (Cundall & Strack 1979): a spring u per particle, the displacement since the
        contact point stuck, carried between substeps (particle state, slot to slot) and into the
        current tangent plane; the same implicit spring-damper gives j_t; stick while |j_t| <=
        mu j_n (u follows the contact point: u' = u + dt v_t'), else slip at the bound with the
        spring stretched to it (u' = -j_t / (dt k)); no load, or no contact: u' = 0

Why: a memoryless contact compares a tangential velocity that the particle-grid round trip
rebuilds at every substep (order 1) with a friction bound that a resting contact gains per
substep (order dt), so sticking fades as the step shrinks and a gait's score follows the number of
substeps (docs/log/contact.md sections 16-19). The spring integrates the rebuilt velocity over time
into a displacement that pulls the particle back to where it stuck. What it does not yet remove:
implicit Euler damps a spring by about dt omega / 2 beyond its own damping, comparable with it
at the CFL step (omega dt ~ 0.7 for the default stiffness at dx 1/32) and negligible at a
sixteenth of it; solving the springs exactly over the substep removes that but puts a resting
body's depth off by a third at the default stiffness (docs/log/contact.md section 24).
`_Contact` is a part of the engine's storage class (`storage._Storage`). Its kernels' adjoints are
Taichi's (`.grad`): the reverse pass runs the scatter's adjoint, takes the scatter back (sign -1)
to recover the grid velocity the impulses were computed from, then the impulses' adjoint.
"""
# (no `from __future__ import annotations`: Taichi reads kernel annotations at runtime)

import taichi as ti

PUSH_OUT = 0.1  # share of a particle's depth below the surface undone per substep (1 made bodies bounce)
BACKSTOP = 1.5  # cells below the surface from which the node contact holds material whole
SHARE_MIN = 1e-3  # a particle alone in its nodes' contact mass counts at most 1000 times its mass
MASS_EPS = 1e-12  # grid nodes lighter than this are treated as empty


class _Contact:
    """The particles' surface contact (a mixin of `storage._Storage`)."""

    @ti.func
    def _bilinear(self, field: ti.template(), i0, k0, fu, fw):
        """`field` (per (x, z) node column) between the four columns around a point."""
        return ((1 - fu) * (1 - fw) * field[i0, k0] + fu * (1 - fw) * field[i0 + 1, k0]
                + (1 - fu) * fw * field[i0, k0 + 1] + fu * fw * field[i0 + 1, k0 + 1])

    @ti.func
    def _surface_at(self, p, s):
        """The terrain's unit normal under particle p at slot s and p's height above the surface
        along it (to first order), both bilinear between the node columns around p."""
        dx = self.dx[None]
        xp = self.x[s, p]
        u, w = xp[0] / dx, xp[2] / dx
        i0 = ti.min(ti.max(ti.cast(ti.floor(u), ti.i32), 0), self.grid_shape[0] - 2)
        k0 = ti.min(ti.max(ti.cast(ti.floor(w), ti.i32), 0), self.grid_shape[2] - 2)
        fu, fw = u - i0, w - k0
        nrm = self._bilinear(self.normal, i0, k0, fu, fw)
        nrm = nrm / ti.sqrt(nrm.dot(nrm))
        return nrm, (xp[1] - self._bilinear(self.height, i0, k0, fu, fw)) * nrm[1]

    @ti.func
    def _takes_part(self, p, s):
        """1 if particle p at slot s would end the substep within half its own spacing of the surface
        (spacing^3 = its volume), else 0: a switch, without a gradient. p2g scatters its mass with it;
        the reverse pass recomputes it (`_contact_flags`)."""
        nrm, phi = self._surface_at(p, s)
        reach = phi + self._dt(p) * ti.min(0.0, self.v[s, p].dot(nrm))
        return ti.select((reach < 0) | (reach * reach * reach < 0.125 * self.vol[p]), 1, 0)

    @ti.kernel
    def _contact_flags(self, s: ti.i32, n: ti.i32):
        """Which particles take part at slot s, as p2g found (for a reverse pass that loads the grid)."""
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            self.in_contact[p] = self._takes_part(p, s)

    @ti.func
    def _grid_at(self, p, s):
        """The updated grid velocity at particle p (slot s) and the mass it carries in the contact,
        m* = m / sum w s_i (its share of its nodes' mass in contact)."""
        node, fx, w = self._stencil(p, s)
        v = ti.Vector.zero(float, 3)
        share = 0.0  # sum w s_i: the share in contact of the mass at the particle
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            I = node + ti.Vector([i, j, k])
            weight = w[i][0] * w[j][1] * w[k][2]
            v += weight * self.grid_v_out[I]
            share += weight * self.grid_contact[I] / ti.max(self.grid_m[I], MASS_EPS)
        return v, self.rho[p] * self.vol[p] / ti.max(share, SHARE_MIN)

    @ti.kernel
    def _contact_impulse(self, s: ti.i32, n: ti.i32):
        """The impulse of each particle taking part, from the updated grid velocity (grid_v_out) at
        its position in slot s, into `impulse`."""
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            self._contact_impulse_of(p, s)

    @ti.func
    def _contact_impulse_of(self, p, s):
        if self.in_contact[p] > 0:
            nrm, phi = self._surface_at(p, s)
            dt = self._dt(p)
            allowed = ti.select(phi > 0, -phi / dt, -PUSH_OUT * phi / dt)  # the normal velocity it may have
            v, m_split = self._grid_at(p, s)
            vn = v.dot(nrm)
            jn = ti.max(0.0, m_split * (allowed - vn))
            vt = v - vn * nrm
            vt_norm = ti.sqrt(vt.dot(vt) + 1e-30)
            jt = ti.min(m_split * vt_norm, self.friction[None] * jn)
            self.impulse[p] = jn * nrm - (jt / vt_norm) * vt

    @ti.kernel
    def _spring_impulse(self, s: ti.i32, so: ti.i32, n: ti.i32):
        """The spring contact's impulse of each particle taking part (see `SPRING`), from the updated
        grid velocity at its position in slot s, into `impulse`; its tangential spring from slot s
        into slot so (zero where it takes no part or the contact carries no load)."""
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            self._spring_impulse_of(p, s, so)

    @ti.func
    def _spring_impulse_of(self, p, s, so):
        u = ti.Vector.zero(float, 3)
        if self.in_contact[p] > 0:
            nrm, phi = self._surface_at(p, s)
            dt = self._dt(p)
            v, m = self._grid_at(p, s)
            k = self.contact_stiffness[None] * ti.pow(self.vol[p], 2.0 / 3.0)  # its share of the area
            c = 2.0 * self.contact_damping[None] * ti.sqrt(k * m)
            implicit = 1.0 + dt * c / m + dt * dt * k / m
            gap = phi - 0.5 * ti.pow(self.vol[p], 1.0 / 3.0)  # its lowest point above the surface
            vn = v.dot(nrm)
            jn = ti.max(0.0, m * (vn - dt * k / m * gap) / implicit - m * vn)
            jn = ti.select(gap + dt * (vn + jn / m) < 0, jn, 0.0)  # touching at the substep's end; no pull
            vt = v - vn * nrm
            held = self.u[s, p]
            length = ti.sqrt(held.dot(held) + 1e-30)
            held -= held.dot(nrm) * nrm  # into the current tangent plane, its length kept
            held *= length / ti.sqrt(held.dot(held) + 1e-30)
            jt = m * (vt - dt * k / m * held) / implicit - m * vt
            cap = self.friction[None] * jn
            jt_norm = ti.sqrt(jt.dot(jt) + 1e-30)
            if jt_norm > cap:  # slip: friction at Coulomb's bound, the spring stretched to it
                jt *= cap / jt_norm
                u = -jt / (dt * k)
            else:  # stick: the spring follows the contact point
                u = held + dt * (vt + jt / m)
            self.impulse[p] = jn * nrm + jt
        self.u[so, p] = u

    @ti.kernel
    def _contact_scatter(self, s: ti.i32, n: ti.i32, sign: float):
        """Add sign times each impulse to its nodes' velocities (w j / M_i); sign -1 takes it back."""
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            self._contact_scatter_of(p, s, sign)

    @ti.func
    def _contact_scatter_of(self, p, s, sign):
        if self.in_contact[p] > 0:
            node, fx, w = self._stencil(p, s)
            j = sign * self.impulse[p]
            for i, k, l in ti.static(ti.ndrange(3, 3, 3)):
                I = node + ti.Vector([i, k, l])
                self.grid_v_out[I] += (w[i][0] * w[k][1] * w[l][2] / ti.max(self.grid_m[I], MASS_EPS)) * j

    @ti.kernel
    def _clear_impulse_grad(self, n: ti.i32):
        """Zero the impulses' gradient, which the scatter's adjoint adds to."""
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            self.impulse.grad[p] = ti.Vector.zero(float, 3)
