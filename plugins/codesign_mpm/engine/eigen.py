"""The eigenframe algebra of the plastic models, and its adjoint.

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

The eigenframe algebra (3x3 products, which Taichi's reverse mode took over a minute to compile)
has a hand-written adjoint (`_principal_adjoint`, used by `constitutive._plastic_adjoint_front`),
and Taichi differentiates only each model's small map of principal values
(`constitutive._spectral_map`). `_Eigen` is a part of the engine's storage class (`storage._Storage`).
"""
# (no `from __future__ import annotations`: Taichi reads kernel annotations at runtime)

import taichi as ti

from codesign_mpm.engine.constitutive import J_MIN

JACOBI_SWEEPS = 4  # at most this many cyclic sweeps of the 3x3 eigen-solver (b = F F^T stays near I)
JACOBI_TOL_ULPS = 64
"""Jacobi stops once b's off-diagonal is below this many round-offs of its trace (7.6e-6 in float32):
`_plastic` takes what is left to first order. Most particles of a settled cover then need no sweep
(desert, paper scale: the eigen-solve 11.7 -> 2.2 ms per substep). Over 10 frames of each cover the
trajectories moved from the full sweeps' by 1/5 to 1/15 of float32's own error (its rms distance from
float64); in the desert a bound of 3e-5 moved them by up to 0.7 of it, 1e-4 by 3 to 10 times it."""
JACOBI_EPS = 1e-6  # eigenvalue gaps below this count as coincident (the scale of b's round-off in float32)


def _plane(p: int, q: int) -> tuple:
    """(p, q, D, S): a rotation in the (p, q) plane is I + (c - 1) D + s S."""
    D = [[float(i == j and i in (p, q)) for j in range(3)] for i in range(3)]
    S = [[float(i == p and j == q) - float(i == q and j == p) for j in range(3)] for i in range(3)]
    return p, q, D, S


JACOBI_PLANES = (_plane(0, 1), _plane(0, 2), _plane(1, 2))  # rotation regulariser: |d tan(theta) / d b| <= 2 / JACOBI_EPS at repeated eigenvalues


class _Eigen:
    """Jacobi eigenframes, the first-order isotropic functions in them, and their adjoint (a mixin of
    `storage._Storage`)."""

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
    def _eigenframe(self, p, F):
        """(Q0, P = Q0^T F, A = P P^T, a): b = F F^T in the frame of its eigenvectors Q0 (from
        _eigen_frames, a constant of the adjoint), where A is diagonal up to round-off, and A's
        diagonal floored at J_MIN^2 (the principal values the models map)."""
        Q0 = self.frame[p]
        P = Q0.transpose() @ F  # F in that frame (fewer products)
        A = P @ P.transpose()
        return Q0, P, A, ti.max(ti.Vector([A[0, 0], A[1, 1], A[2, 2]]), J_MIN * J_MIN)

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
        ti.loop_config(serialize=self.serial)
        for p in range(start, end):
            self.frame[p] = self._frame(s, p)

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
    def _stack(self, g, g_slope, k, k_slope):
        """The four 3-vectors of a Hencky model's map as one 12-vector (the `spectral` field)."""
        return ti.Vector([g[0], g[1], g[2], g_slope[0], g_slope[1], g_slope[2],
                          k[0], k[1], k[2], k_slope[0], k_slope[1], k_slope[2]])
