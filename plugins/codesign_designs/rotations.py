"""Fibres as rotations, and their weighted average by the special orthogonal Procrustes projection.

A fibre f is stored as the smallest rotation R that takes a reference direction r to f (SDF-Lerp
of the SoftZoo appendix, after Bregier 2021, with r = the heading e_x). Muscle stress is even in
f, so each fibre is first given the sign that faces r: the average of f and -f is then never
asked for. With r = e_x, two fibres a few degrees apart on either side of the yz-plane faced
opposite ways and averaged to +x; blends therefore take, per point, r = the principal axis of
the fibres being blended (`principal_axes`, sign-invariant), fixed at setup so the weights'
gradients are untouched. The average of rotations R_i with weights w_i is the rotation nearest
sum_i w_i R_i in Frobenius norm.
"""

from __future__ import annotations

import numpy as np
import torch

HEADING = np.array([1.0, 0.0, 0.0])


def facing_heading(fibers: np.ndarray) -> np.ndarray:
    """Unit fibres with the sign that faces +x (ties broken by +y, then +z): the same muscle."""
    f = np.asarray(fibers, dtype=float)
    f = f / np.linalg.norm(f, axis=-1, keepdims=True)
    key = np.where(np.abs(f[..., 0]) > 1e-12, f[..., 0], np.where(np.abs(f[..., 1]) > 1e-12, f[..., 1], f[..., 2]))
    return np.where(key[..., None] < 0, -f, f)


def facing(fibers: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Unit fibres with the sign that faces `reference` (a fibre perpendicular to it: `facing_heading`)."""
    f = facing_heading(fibers)
    dot = (f * reference).sum(-1, keepdims=True)
    return np.where(dot < -1e-12, -f, f)


def principal_axes(fibers: np.ndarray) -> np.ndarray:
    """(..., 3) the principal axis of each (..., P, 3) set of fibres: the top eigenvector of
    sum_p f_p f_p^T, the same for f_p and -f_p (signed by `facing_heading`)."""
    f = facing_heading(fibers)
    _, vectors = np.linalg.eigh(np.einsum("...pi,...pj->...ij", f, f))
    return facing_heading(vectors[..., :, -1])


def fiber_rotations(fibers: np.ndarray, reference: np.ndarray = HEADING) -> np.ndarray:
    """(..., 3, 3) the smallest rotation taking the unit `reference` (broadcast against the fibres)
    to each fibre, the fibre signed to face it (`facing`).

    Rodrigues' formula R = I + [v]x + [v]x^2 / (1 + c) with v = r x f, c = r . f >= 0,
    so it never divides by less than 1.
    """
    r = np.broadcast_to(reference, np.shape(fibers))
    f = facing(fibers, r)
    v = np.cross(r, f)
    c = (r * f).sum(-1)
    vx = np.zeros(f.shape[:-1] + (3, 3))
    vx[..., 0, 1], vx[..., 0, 2], vx[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    vx = vx - np.swapaxes(vx, -1, -2)
    return np.eye(3) + vx + vx @ vx / (1 + c)[..., None, None]


class _SpecialProcrustes(torch.autograd.Function):
    """argmin over SO(3) of |R - M|_F, with the closed-form derivative of the rotation factor.

    With M = U' S' V^T its SVD signed so that det(U' V^T) = +1 (the last singular value takes the
    sign), R = U' V^T and dR = U' X V^T with X_ij = (A_ij - A_ji) / (s'_i + s'_j), A = U'^T dM V.
    The denominators are sums, not differences, of singular values, so the derivative is
    finite where autograd through an SVD divides by zero: at repeated singular values, which is
    exactly where M is already a rotation (e.g. one primitive weighted one).
    """

    @staticmethod
    def forward(ctx, m: torch.Tensor) -> torch.Tensor:
        u, s, vh = torch.linalg.svd(m)
        d = torch.sign(torch.linalg.det(u @ vh))
        d = torch.where(d == 0, torch.ones_like(d), d)
        u = torch.cat([u[..., :2], u[..., 2:] * d[..., None, None]], dim=-1)
        s = torch.cat([s[..., :2], s[..., 2:] * d[..., None]], dim=-1)
        ctx.save_for_backward(u, s, vh)
        return u @ vh

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        u, s, vh = ctx.saved_tensors
        g = u.transpose(-1, -2) @ grad @ vh.transpose(-1, -2)
        denominator = s[..., :, None] + s[..., None, :]
        denominator = torch.where(denominator.abs() < 1e-12, torch.full_like(denominator, 1e-12), denominator)
        return u @ ((g - g.transpose(-1, -2)) / denominator) @ vh


def special_procrustes(m: torch.Tensor) -> torch.Tensor:
    """The rotation nearest each (..., 3, 3) matrix `m` (differentiable)."""
    return _SpecialProcrustes.apply(m)


def average_rotations(rotations: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) weighted Procrustes average of (N, P, 3, 3) rotations with (P,) weights summing to 1."""
    return special_procrustes(torch.einsum("npij,p->nij", rotations, weights))
