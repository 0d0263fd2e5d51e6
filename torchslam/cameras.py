"""Camera models: projections, reprojection residuals and their analytic Jacobians.

Conventions (written once):

- The camera pose is T_c (4, 4), **world → camera** (the library's T_i0): P = R X + t is the
  world point X in the camera frame. Pose Jacobians are for the right perturbation
  T ← T·Exp(δ), δ = (ω, v): ∂P/∂ω = −R [X]×, ∂P/∂v = R; point Jacobians for X ← X + δX.
- **Snavely / BAL** (Bundler, "Bundle Adjustment in the Large"): the camera looks down −z;
  p = −P_xy / P_z, ρ = 1 + k1‖p‖² + k2‖p‖⁴, predicted = f·ρ·p, in pixels with the origin at
  the image centre (x right, y up). Intrinsics (f, k1, k2).
- **Pinhole** (OpenCV): the camera looks down +z; x' = P_xy / P_z, radial-tangential
  distortion (k1, k2, p1, p2): r² = ‖x'‖², x'' = x'(1 + k1 r² + k2 r⁴) + (2 p1 x y + p2 (r² +
  2x²), p1 (r² + 2y²) + 2 p2 x y), u = (fx x''_x + cx, fy x''_y + cy), pixels with the origin at
  the top-left pixel's centre (u column, v row). Intrinsics (fx, fy, cx, cy[, k1, k2, p1, p2]).

Residuals are predicted − observed (2 values). Every function is batched over leading dims.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import so3

__all__ = [
    "pinhole_jacobians",
    "pinhole_project",
    "snavely_jacobians",
    "snavely_project",
]


def _camera_point(T: Tensor, X: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """P = R X + t (..., 3), and ∂P/∂δ (..., 3, 6), ∂P/∂X (..., 3, 3) = R."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    P = (R @ X[..., None]).squeeze(-1) + t
    dP_dxi = torch.cat((-(R @ so3._hat(X)), R), dim=-1)
    return P, dP_dxi, R


def _columns(x: Tensor, shape: torch.Size, k: int) -> tuple[Tensor, ...]:
    """The k components of ``x`` (..., k) broadcast to ``shape``, each a contiguous (*shape)
    tensor: elementwise kernels on whole columns run several times faster than on the strided
    entries of (..., k) views."""
    return tuple(x.expand(*shape, k).movedim(-1, 0).contiguous().unbind(0))


def _snavely_prediction(T: Tensor, X: Tensor, intrinsics: Tensor):
    """The columns of the Snavely projection (each (...,)): R (3 × 3 nested, by row), X, 1/z,
    p, f, k1, k2, r², ρ, f ρ, for P = R X + t and the pixels u = f ρ p; one formula for
    :func:`snavely_project` and :func:`snavely_jacobians` (the same bits). Written on
    contiguous columns (:func:`_columns`)."""
    shape = _checks.broadcast_shapes(T.shape[:-2], X.shape[:-1], intrinsics.shape[:-1])
    if T.shape[:-2] == shape:  # all 16 entries at once: a plain transpose, 2.5× faster
        rows = _columns(T.reshape(*shape, 16), shape, 16)
    else:
        rows = _columns(T[..., :3, :].reshape(*T.shape[:-2], 12), shape, 12)
    R = [rows[4 * k : 4 * k + 3] for k in range(3)]
    x0, x1, x2 = _columns(X, shape, 3)
    P = [R[k][0] * x0 + R[k][1] * x1 + R[k][2] * x2 + rows[4 * k + 3] for k in range(3)]
    inv = 1.0 / P[2]
    px, py = -P[0] * inv, -P[1] * inv
    f, k1, k2 = _columns(intrinsics, shape, 3)
    r2 = px * px + py * py
    rho = 1.0 + r2 * (k1 + k2 * r2)
    f_rho = f * rho
    return R, (x0, x1, x2), inv, px, py, f, k1, k2, r2, rho, f_rho


def snavely_project(T: Tensor, X: Tensor, intrinsics: Tensor) -> Tensor:
    """Snavely/BAL projection (module docstring): T (..., 4, 4) world → camera, X (..., 3),
    intrinsics (f, k1, k2) (..., 3) → pixels (..., 2)."""
    *_, px, py, _f, _k1, _k2, _r2, _rho, f_rho = _snavely_prediction(T, X, intrinsics)
    return torch.stack((f_rho * px, f_rho * py), -1)


def snavely_jacobians(
    T: Tensor, X: Tensor, intrinsics: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(predicted (..., 2), ∂/∂δ (..., 2, 6), ∂/∂X (..., 2, 3), ∂/∂(f, k1, k2) (..., 2, 3)).

    Derivation (row i of each block): with u = f ρ p, ∂u/∂p = f (ρ I + p ∂ρ/∂pᵀ) = A,
    ∂ρ/∂p = 2 (k1 + 2 k2 r²) p, and p = −P_xy/z, the row g_i = ∂u_i/∂P · R of ∂u/∂X is
    −(A_i1 R_0 + A_i2 R_1 + (A_i1 p_x + A_i2 p_y) R_2) / z (R_k the rows of R); then
    ∂u_i/∂δ = (X × g_i, g_i), since ∂P/∂δ = [−R [X]× | R] and −g [X]× = (X × g)ᵀ; and
    ∂u/∂(f, k1, k2) = (ρ p, f r² p, f r⁴ p).
    """
    R, (x0, x1, x2), inv, px, py, f, k1, k2, r2, rho, f_rho = _snavely_prediction(T, X, intrinsics)
    dd = 2.0 * (k1 + 2.0 * k2 * r2)  # ∂ρ/∂p = dd · p
    f_px, f_py = f * px, f * py
    a11, a12 = f_rho + f_px * dd * px, f_px * dd * py
    a21, a22 = f_py * dd * px, f_rho + f_py * dd * py
    rows = []
    for a1, a2 in ((a11, a12), (a21, a22)):
        c = a1 * px + a2 * py
        g = [-(a1 * R[0][k] + a2 * R[1][k] + c * R[2][k]) * inv for k in range(3)]
        cross = (x1 * g[2] - x2 * g[1], x2 * g[0] - x0 * g[2], x0 * g[1] - x1 * g[0])
        rows.append((*cross, *g))
    shape = px.shape
    J_pose = torch.stack(rows[0] + rows[1], -1).reshape(*shape, 2, 6)
    J_point = J_pose[..., 3:]
    f_r2 = f * r2
    d_intrinsics = torch.stack(
        (rho * px, f_r2 * px, f_r2 * r2 * px, rho * py, f_r2 * py, f_r2 * r2 * py), -1
    ).reshape(*shape, 2, 3)
    predicted = torch.stack((f_rho * px, f_rho * py), -1)
    return predicted, J_pose, J_point, d_intrinsics


def pinhole_project(T: Tensor, X: Tensor, intrinsics: Tensor) -> Tensor:
    """Pinhole projection (module docstring): intrinsics (fx, fy, cx, cy) (..., 4) or with
    radial-tangential distortion (fx, fy, cx, cy, k1, k2, p1, p2) (..., 8) → pixels (..., 2)."""
    return pinhole_jacobians(T, X, intrinsics)[0]


def pinhole_jacobians(
    T: Tensor, X: Tensor, intrinsics: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(predicted (..., 2), ∂/∂δ (..., 2, 6), ∂/∂X (..., 2, 3), ∂/∂intrinsics (..., 2, n)),
    n = 4 or 8 as ``intrinsics``."""
    n = intrinsics.shape[-1]
    if n not in (4, 8):
        raise ValueError(
            f"pinhole_jacobians: 'intrinsics' must end in 4 (fx, fy, cx, cy) or 8 (… k1, k2, "
            f"p1, p2) values, got shape {tuple(intrinsics.shape)}"
        )
    P, dP_dxi, dP_dX = _camera_point(T, X)
    z = P[..., 2:]
    inv = 1.0 / z
    q = P[..., :2] * inv  # x' = P_xy / z
    zero = torch.zeros_like(inv)
    dq_dP = torch.stack(
        (
            torch.cat((inv, zero, -q[..., :1] * inv), -1),
            torch.cat((zero, inv, -q[..., 1:] * inv), -1),
        ),
        dim=-2,
    )
    fx, fy, cx, cy = (intrinsics[..., k : k + 1] for k in range(4))
    x, y = q[..., :1], q[..., 1:]
    eye = torch.eye(2, dtype=P.dtype, device=P.device).expand(*q.shape[:-1], 2, 2)
    if n == 8:
        k1, k2, p1, p2 = (intrinsics[..., k : k + 1] for k in range(4, 8))
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + k2 * r2)
        d = torch.cat(
            (
                x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
            ),
            -1,
        )
        dradial = 2.0 * (k1 + 2.0 * k2 * r2)  # ∂radial/∂q = dradial · q
        dd_dq = torch.stack(
            (
                torch.cat(
                    (
                        radial + x * dradial * x + 2.0 * p1 * y + 6.0 * p2 * x,
                        x * dradial * y + 2.0 * p1 * x + 2.0 * p2 * y,
                    ),
                    -1,
                ),
                torch.cat(
                    (
                        y * dradial * x + 2.0 * p1 * x + 2.0 * p2 * y,
                        radial + y * dradial * y + 6.0 * p1 * y + 2.0 * p2 * x,
                    ),
                    -1,
                ),
            ),
            dim=-2,
        )
        dd_ddist = torch.stack(
            (
                torch.cat((x * r2, x * r2 * r2, 2.0 * x * y, r2 + 2.0 * x * x), -1),
                torch.cat((y * r2, y * r2 * r2, r2 + 2.0 * y * y, 2.0 * x * y), -1),
            ),
            dim=-2,
        )
    else:
        d, dd_dq = q, eye
    focal = torch.cat((fx, fy), -1)
    predicted = focal * d + torch.cat((cx, cy), -1)
    du_dq = focal[..., :, None] * dd_dq
    du_dP = du_dq @ dq_dP
    zero2 = torch.zeros_like(d[..., :1])
    one = torch.ones_like(zero2)
    d_linear = torch.stack(
        (
            torch.cat((d[..., :1], zero2, one, zero2), -1),
            torch.cat((zero2, d[..., 1:], zero2, one), -1),
        ),
        dim=-2,
    )
    d_intrinsics = d_linear
    if n == 8:
        d_intrinsics = torch.cat((d_linear, focal[..., :, None] * dd_ddist), -1)
    return predicted, du_dP @ dP_dxi, du_dP @ dP_dX, d_intrinsics
