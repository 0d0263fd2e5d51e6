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


def snavely_project(T: Tensor, X: Tensor, intrinsics: Tensor) -> Tensor:
    """Snavely/BAL projection (module docstring): T (..., 4, 4) world → camera, X (..., 3),
    intrinsics (f, k1, k2) (..., 3) → pixels (..., 2)."""
    P = (T[..., :3, :3] @ X[..., None]).squeeze(-1) + T[..., :3, 3]
    p = -P[..., :2] / P[..., 2:]
    f, k1, k2 = intrinsics[..., 0:1], intrinsics[..., 1:2], intrinsics[..., 2:3]
    r2 = (p * p).sum(-1, keepdim=True)
    return f * (1.0 + r2 * (k1 + k2 * r2)) * p


def snavely_jacobians(
    T: Tensor, X: Tensor, intrinsics: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(predicted (..., 2), ∂/∂δ (..., 2, 6), ∂/∂X (..., 2, 3), ∂/∂(f, k1, k2) (..., 2, 3))."""
    P, dP_dxi, dP_dX = _camera_point(T, X)
    z = P[..., 2:]
    p = -P[..., :2] / z
    f, k1, k2 = intrinsics[..., 0:1], intrinsics[..., 1:2], intrinsics[..., 2:3]
    r2 = (p * p).sum(-1, keepdim=True)
    rho = 1.0 + r2 * (k1 + k2 * r2)
    predicted = f * rho * p
    # ∂p/∂P = [[−1/z, 0, −p_x/z], [0, −1/z, −p_y/z]]  (p = −P_xy/z)
    inv = 1.0 / z
    zero = torch.zeros_like(inv)
    dp_dP = torch.stack(
        (
            torch.cat((-inv, zero, -p[..., :1] * inv), -1),
            torch.cat((zero, -inv, -p[..., 1:] * inv), -1),
        ),
        dim=-2,
    )
    # ∂(f ρ p)/∂p = f (ρ I + p ∂ρ/∂pᵀ), ∂ρ/∂p = 2 (k1 + 2 k2 r²) p
    drho_dp = 2.0 * (k1 + 2.0 * k2 * r2) * p
    eye = torch.eye(2, dtype=P.dtype, device=P.device)
    du_dp = f[..., None] * (rho[..., None] * eye + p[..., :, None] * drho_dp[..., None, :])
    du_dP = du_dp @ dp_dP
    d_intrinsics = torch.stack((rho * p, f * r2 * p, f * r2 * r2 * p), dim=-1)
    return predicted, du_dP @ dP_dxi, du_dP @ dP_dX, d_intrinsics


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
