"""Stress and deformation update of every particle: the materials' Taichi functions called per
model, the muscles, and the hand-written adjoints of the neo-Hookean stress, the plastic return
mapping and the muscle.

Only what the scene uses is compiled: the material models present (their return mappings,
the plastic volume ratio J_p of snow), the muscle term when the scene has actuators, the
terrain projection when there is terrain (`ti.static`).

Scenes with non-elastic materials and differentiable layouts first run one small kernel per
material run (`_constitutive_update`: return mapping, stress, muscle), and p2g only scatters;
elastic-only forward scenes compute the stress inside p2g (`_update`). Adjoints: the neo-Hookean
stress (the robots' default, muscle included) has a hand-written one (`_elastic_adjoint` with
`materials.neo_hookean.stress_adjoint`; in a scene of that model alone, run inside p2g's adjoint
with the stress computed again by `_stress_again`),
and so have the plastic models' eigenframe algebra (`_plastic_adjoint_front/back`, with
Taichi's reverse mode of `_spectral_map` between them). Taichi differentiates the rest: the
other elastic models' and water's stresses (`_constitutive_update.grad`).

`_Constitutive` is a part of the engine's storage class (`storage._Storage`).
"""
# (no `from __future__ import annotations`: Taichi reads kernel annotations at runtime)

import taichi as ti

from codesign_mpm.materials import ID, MODEL_NAMES, cofactor, material, muscle  # noqa: F401 (MODEL_NAMES: re-exported)
from codesign_mpm.materials.neo_hookean import J_MIN

DRIVE_CHUNK = 256  # particles whose action gradients one thread adds up before its one atomic add


class _Constitutive:
    """Stress, return mapping, muscles and their adjoints (a mixin of `storage._Storage`)."""

    @ti.func
    def _lame(self, p):
        """Particle p's Lame parameters (mu, lambda) from its Young's modulus and Poisson's ratio."""
        E, nu = self.E[p], self.nu[p]
        return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

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
    def _cofactor(self, F):
        """d det(F) / dF (`materials.base.cofactor`)."""
        return cofactor(F)

    @ti.func
    def _elastic_stress(self, model: ti.template(), F, mu, la):
        """Kirchhoff stress tau = P F^T of one elastic model (its module's `stress`)."""
        return ti.static(material(model).stress)(F, mu, la)

    @ti.kernel
    def _elastic_adjoint(self, model: ti.template(), s: ti.i32, so: ti.i32, t: ti.i32, start: ti.i32, end: ti.i32):
        """Reverse of `_constitutive_update` for an elastic model whose module writes its stress's adjoint
        by hand (`stress_adjoint`; neo-Hookean, the robots' default), at the trial F = (I + dt C) F_s,
        the muscle's included."""
        ti.loop_config(serialize=self.serial)
        for p in range(start, end):
            self._elastic_adjoint_particle(model, p, s, so, t, self._trial(p, s), self.tau.grad[p])

    @ti.func
    def _elastic_adjoint_particle(self, model: ti.template(), p, s, so, t, F, tau_bar):
        """Particle p's stress adjoint, muscle included, at its trial F, from its stress's gradient tau_bar."""
        F_bar = self.F.grad[so, p]
        if ti.static(self.has_muscles):
            F_bar += self._muscle_adjoint(p, F, t, tau_bar)
        mu, la = self._lame(p)
        F_bar, self.E.grad[p] = ti.static(material(model).stress_adjoint)(F, mu, la, self.nu[p], tau_bar, F_bar,
                                                                          self.E.grad[p])
        self._add_trial_grad(p, s, F_bar, ti.Matrix.zero(float, 3, 3))

    @ti.func
    def _stress_again(self, p, s, t):
        """(trial F, stress with the muscle at action row t) of particle p at substep s, computed again
        for a `stress_in_adjoint` layout's reverse pass (its one elastic model: nothing is written)."""
        F, tau = self._update(p, s, s + 1)
        if ti.static(self.has_muscles):
            tau += self._muscle_stress(p, F, t)
        return F, tau

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

        Works in principal Hencky strain eps = log(sigma), projected by the model's `return_map`
        (materials/sand.py, clay.py, snow.py, ...). F changes only when the trial state lies
        outside the model's elastic region (for snow: a stretch outside its bounds), so a body
        loaded below yield springs back without permanent set. Written without branches (masks
        select the case): Taichi's reverse mode turns locals assigned in branches into stacks.

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
        eps_new, alpha = ti.static(material(model).return_map)(eps, tr, dev, n2, prm, mu, la)
        # exp(0) - 1 == 0 exactly (with zero slope): an unprojected F is stored unchanged, bit for bit
        scale = ti.exp(eps_new - eps)
        scale_slope = scale * (alpha - 1.0) / (2.0 * a)
        k = ti.Vector.zero(float, 3)
        k_slope = mu * alpha / a
        if ti.static(material(model).plastic_volume):  # snow: J_p is state, and its own principal stress
            inside, scale_slope = ti.static(material(model).projection_slope)(eps, eps_new, scale, a)
            jp = self.Jp[s, p] * ti.exp((eps - eps_new).sum())
            if ti.static(write_jp):
                self.Jp[so, p] = jp
            k, k_slope = ti.static(material(model).principal_stress)(eps_new, inside, jp, prm, mu, la)
        else:  # Hencky: tau = 2 mu eps + lambda tr(eps) I, in the principal frame
            k = 2.0 * mu * eps_new + la * eps_new.sum()
        return scale - 1.0, scale_slope, k, k_slope

    @ti.kernel
    def _spectral_map(self, model: ti.template(), s: ti.i32, so: ti.i32, start: ti.i32, end: ti.i32):
        """A Hencky model's map (`_spectral`) from `strain` to `spectral`, in a kernel of its own so
        that Taichi's reverse mode differentiates it alone: the eigenframe algebra around it took
        over a minute to compile in reverse mode, the map well under a second."""
        ti.loop_config(serialize=self.serial)
        for p in range(start, end):
            mu, la = self._lame(p)
            g, g_slope, k, k_slope = self._spectral(model, p, s, so, self.strain[p], mu, la, True)
            self.spectral[p] = self._stack(g, g_slope, k, k_slope)

    @ti.kernel
    def _plastic_adjoint_front(self, model: ti.template(), s: ti.i32, so: ti.i32, t: ti.i32, start: ti.i32,
                               end: ti.i32):
        """Reverse of a Hencky model's `_constitutive_update` (written by hand, as a forward kernel),
        first part: from the gradients of the stored F (slot so) and of the stress (muscle included)
        to those of the model's map (`spectral.grad`), part of its input's (`strain.grad`, which
        `_spectral_map.grad` completes) and of the trial F (`F_bar_part`, `A_off_bar`).

        F_new = F + Q0 M1 P and tau = Q0 M2 Q0^T: with G = Q0^T dL/dF_new, M1's gradient is G P^T,
        P's gets M1 G, and M2's is Q0^T dL/dtau Q0."""
        ti.loop_config(serialize=self.serial)
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
    def _plastic_adjoint_back(self, model: ti.template(), s: ti.i32, start: ti.i32, end: ti.i32):
        """Last part of the hand-written reverse (after `_spectral_map.grad`): through A = P P^T and
        a = max(diag A, J_MIN^2) to P, then to the trial F = (I + dt C) F_s and on to F_s and C
        (mud's viscous stress J eta (C + C^T) included)."""
        ti.loop_config(serialize=self.serial)
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
            if ti.static(material(model).viscous):  # mud
                tau_bar, eta = self.tau.grad[p], self.params[p][ti.static(material(model).viscosity_index)]
                F_bar += eta * ((C + C.transpose()) * tau_bar).sum() * self._cofactor(F)
                C_bar += F.determinant() * eta * (tau_bar + tau_bar.transpose())
            self._add_trial_grad(p, s, F_bar, C_bar)

    @ti.func
    def _constitutive(self, model: ti.template(), p, s, so):
        """(F to store, Kirchhoff stress without muscle) of particle p of `model`, from slot s."""
        C = self.C[s, p]
        F = self._trial(p, s)
        mu, la = self._lame(p)
        F_new = F
        tau = ti.Matrix.zero(float, 3, 3)
        if ti.static(material(model).elastic_with_parameters):  # a plugin's: its stress reads them too
            tau = ti.static(material(model).stress)(F, mu, la, self.params[p])
        elif ti.static(material(model).kind == "elastic"):
            tau = self._elastic_stress(model, F, mu, la)
        elif ti.static(material(model).kind == "fluid"):  # water: the model resets F itself
            F_new, tau = ti.static(material(model).update)(F, self.params[p])
        else:
            F_new, tau = self._plastic(model, p, s, so, F, mu, la)
        if ti.static(material(model).viscous):  # water, mud
            # Newtonian viscosity, tau = J eta (grad v + grad v^T), with the APIC C as grad v
            tau += F.determinant() * self.params[p][ti.static(material(model).viscosity_index)] * (C + C.transpose())
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

    @ti.kernel
    def _stress(self, model: ti.template(), s: ti.i32, scratch: ti.i32, t: ti.i32, start: ti.i32, end: ti.i32,
                out: ti.types.ndarray()):
        """Kirchhoff stress that the next substep applies to particles [start, end) of one model
        (constitutive at the trial F, plus the muscle at action row t); forward only. State a
        plastic model writes (snow's J_p) goes to the `scratch` slot."""
        ti.loop_config(serialize=self.serial)
        for p in range(start, end):
            if ti.static(material(model).kind == "hencky"):
                self.frame[p] = self._frame(s, p)
            F, tau = self._constitutive(model, p, s, scratch)
            if ti.static(self.has_muscles):
                tau += self._muscle_stress(p, F, t)
            for i, j in ti.static(ti.ndrange(3, 3)):
                out[p, i, j] = tau[i, j]

    @ti.func
    def _constitutive_particle(self, model: ti.template(), p, s, so, t):
        F, tau = self._constitutive(model, p, s, so)
        if ti.static(self.has_muscles):
            tau += self._muscle_stress(p, F, t)
        self.F[so, p] = F
        self.tau[p] = tau

    @ti.kernel
    def _constitutive_update(self, model: ti.template(), s: ti.i32, so: ti.i32, t: ti.i32, start: ti.i32,
                             end: ti.i32, j: ti.i32):
        """Scenes with plastic models and differentiable layouts (`separate_stress`): F and stress
        (muscle included, at action row t) of the particles [start, end) of one model, in their own
        kernel ahead of p2g (one small kernel per model compiles far faster than all of them fused
        into the 27-node scatter). `j`: the substep within the control step."""
        ti.loop_config(serialize=self.serial)
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
    def _muscle_stress(self, p, F, t):
        """Kirchhoff stress of particle p's muscle at action row t (materials/muscle.py)."""
        Ff = F @ self.fiber[p]
        row = t
        if ti.static(self.batched):  # forward only: one action row per member
            row = self.member[p]
        a = self.act[row].dot(self.muscle[p])
        s = self.muscle_ratio[p] * self.E[p]
        return ti.static(muscle.STRESS[self.muscle_model])(Ff, a, s)

    @ti.func
    def _muscle_adjoint(self, p, F, t, tau_bar):
        """Adjoint of `_muscle_stress` (action row t): adds the gradients of the fibre, the muscle
        membership, E and the action row, and returns F's; u = F f's, the activation's and the
        stiffness's come from the muscle model's adjoint (materials/muscle.py)."""
        f = self.fiber[p]
        u = F @ f
        act = self.act[t]
        a = act.dot(self.muscle[p])
        s = self.muscle_ratio[p] * self.E[p]
        u_bar, a_bar, s_bar = ti.static(muscle.ADJOINT[self.muscle_model])(u, a, s, tau_bar)
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
        ti.loop_config(serialize=self.serial)
        for c in range((end - start + DRIVE_CHUNK - 1) // DRIVE_CHUNK):
            total = ti.Vector.zero(float, ti.static(self.act.n))
            for p in range(start + c * DRIVE_CHUNK, ti.min(end, start + (c + 1) * DRIVE_CHUNK)):
                total += self.drive_bar[p] * self.muscle[p]
            self.act.grad[t] += total

    @ti.kernel
    def _muscle_work(self, s: ti.i32, so: ti.i32, t: ti.i32, n: ti.i32):
        """Add the work the muscles did in substep s -> so: the force their stress put on the grid
        nodes, f_i = -sum_p V_p tau_p (4 / dx^2) (x_i - x_p) w_ip, times the nodes' new velocities,
        which is -dt sum_p V_p tau_p : C'_p with C' the velocity gradient g2p gathered (forward only)."""
        ti.loop_config(serialize=self.serial)
        for p in range(n):
            tau = self._muscle_stress(p, self._trial(p, s), t)
            self.work[None] += -self._dt(p) * self.vol[p] * (tau * self.C[so, p]).sum()

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
        if model <= ti.static(ID["stvk"]):  # the built-in elastic models (a plugin's keeps wave0)
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
