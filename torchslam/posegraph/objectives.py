"""Pose-graph objectives: the standard weighted cost and the SE-Sync objective, vectorized.

Conventions: a vertex pose T_i = [[R_i, t_i], [0, 1]] maps body-i points into the world; an
edge (i, j) measures Z_ij = [[R̃_ij, t̃_ij], [0, 1]] ≈ T_i⁻¹ T_j with information Ω_ij in
ξ = (ω, v) order (rotation first), as stored in :class:`PoseGraph`.

- Standard cost (what a Gauss-Newton/LM solve minimizes; GTSAM's ``graph.error``):

      F(T) = ½ Σ_(i,j) r_ijᵀ Ω_ij r_ij,   r_ij = Log(Z_ij⁻¹ T_i⁻¹ T_j).

- SE-Sync objective (Rosen, Carlone, Bandeira, Leonard, IJRR 2019, Problem 1, eq. 12), the
  value of Table 2's f* (sphere2500: 1687, parking-garage: 1.263):

      f(T) = Σ_(i,j) κ_ij ‖R_j − R_i R̃_ij‖_F² + τ_ij ‖t_j − t_i − R_i t̃_ij‖²,

  no ½, chordal (Frobenius) rotation error, isotropic weights from Ω's diagonal blocks as in
  SE-Sync's ``SESync_utils.cpp``: τ = 3 / tr(Ω_tt⁻¹), κ = 3 / (2 tr(Ω_RR⁻¹)); the cross blocks
  are ignored.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.posegraph.between import _between, weighted_cost
from torchslam.posegraph.graph import PoseGraph

__all__ = ["edge_residuals", "sesync_objective", "sesync_weights", "standard_cost"]


def _graph_poses(fn: str, graph: PoseGraph, poses: Tensor | None, *, rigid: bool = True) -> Tensor:
    if not isinstance(graph, PoseGraph):
        raise TypeError(
            f"{fn}: argument 'graph' must be a PoseGraph, got {_checks.describe(graph)}"
        )
    if poses is None:
        return graph.poses
    _checks.check_tensor(fn, "poses", poses, (graph.num_vertices, 4, 4))
    _checks.check_same_kind(fn, poses=poses, measurements=graph.measurements)
    if rigid:
        _checks.check_pose_matrix(fn, "poses", poses)
    else:
        _checks.check_finite(fn, "poses", poses)
    return poses


def _first_not_positive_definite(information: Tensor) -> int | None:
    """Index of the first (K, 6, 6) matrix whose rotation block Ω_RR or translation block Ω_tt
    is not positive definite (Cholesky fails), or None."""
    blocks = torch.stack((information[..., :3, :3], information[..., 3:, 3:]), dim=-3)
    _, info = torch.linalg.cholesky_ex(blocks.detach().reshape(-1, 2, 3, 3))
    bad = (info > 0).any(-1)
    return int(bad.nonzero()[0, 0]) if bool(bad.any()) else None


def edge_residuals(graph: PoseGraph, poses: Tensor | None = None) -> Tensor:
    """Between residuals r_ij = Log(Z_ij⁻¹ T_i⁻¹ T_j) of every edge, ξ = (ω, v): rotation first.

    Args:
        graph: the pose graph (edges, measurements).
        poses: vertex poses to evaluate, shape (..., N, 4, 4); ``graph.poses`` when None.

    Returns:
        Residuals, shape (..., E, 6).
    """
    T = _graph_poses("edge_residuals", graph, poses)
    return _edge_residuals(graph, T)


def _edge_residuals(graph: PoseGraph, T: Tensor) -> Tensor:
    i, j = graph.edges[:, 0], graph.edges[:, 1]
    return _between(T[..., i, :, :], T[..., j, :, :], graph.measurements)


def standard_cost(graph: PoseGraph, poses: Tensor | None = None) -> Tensor:
    """Standard pose-graph cost ½ Σ r_ijᵀ Ω_ij r_ij (module docstring).

    Args:
        graph: the pose graph (edges, measurements, information in (ω, v) order).
        poses: vertex poses to evaluate, shape (..., N, 4, 4); ``graph.poses`` when None.

    Returns:
        Costs, shape (...) (a 0-dim tensor for a single set of poses).
    """
    r = _edge_residuals(graph, _graph_poses("standard_cost", graph, poses))
    return weighted_cost(r, graph.information).sum(-1)


def sesync_weights(information: Tensor) -> tuple[Tensor, Tensor]:
    """SE-Sync's isotropic weights κ = 3 / (2 tr(Ω_RR⁻¹)) and τ = 3 / tr(Ω_tt⁻¹).

    Ω_RR = information[..., :3, :3] and Ω_tt = information[..., 3:, 3:] in (ω, v) order (g2o's
    rotation and translation blocks); the cross blocks are ignored, as in SE-Sync.

    Args:
        information: information matrices, shape (..., 6, 6), (ω, v) order.

    Returns:
        ``(kappa, tau)``, each of shape (...).
    """
    fn = "sesync_weights"
    _checks.check_tensor(fn, "information", information, (6, 6))
    _checks.check_finite(fn, "information", information)
    if _checks.value_checks_active() and information.numel():
        bad = _first_not_positive_definite(information)
        if bad is not None:
            index = tuple(
                int(i) for i in torch.unravel_index(torch.tensor(bad), information.shape[:-2])
            )
            raise ValueError(
                f"{fn}: argument 'information' must have positive-definite rotation and "
                f"translation blocks (Ω[:3, :3], Ω[3:, 3:]); at batch index {index} one is not"
            )
    trace_RR = torch.linalg.inv(information[..., :3, :3]).diagonal(dim1=-2, dim2=-1).sum(-1)
    trace_tt = torch.linalg.inv(information[..., 3:, 3:]).diagonal(dim1=-2, dim2=-1).sum(-1)
    return 3.0 / (2.0 * trace_RR), 3.0 / trace_tt


def sesync_objective(graph: PoseGraph, poses: Tensor | None = None) -> Tensor:
    """SE-Sync objective Σ κ ‖R_j − R_i R̃_ij‖_F² + τ ‖t_j − t_i − R_i t̃_ij‖² (eq. 12, no ½).

    Args:
        graph: the pose graph (edges, measurements, information in (ω, v) order).
        poses: vertex poses to evaluate, shape (..., N, 4, 4); ``graph.poses`` when None.
            Rotations are used as given (not projected onto SO(3)); they must be finite.

    Returns:
        Objective values, shape (...).
    """
    fn = "sesync_objective"
    T = _graph_poses(fn, graph, poses, rigid=False)
    if _checks.value_checks_active() and graph.information.numel():
        bad = _first_not_positive_definite(graph.information)
        if bad is not None:
            raise ValueError(
                f"{fn}: the SE-Sync weights need positive-definite rotation and translation "
                f"blocks of 'graph.information'; those of edge {bad} are not"
            )
    kappa, tau = sesync_weights(graph.information)
    i, j = graph.edges[:, 0], graph.edges[:, 1]
    R_i, R_j = T[..., i, :3, :3], T[..., j, :3, :3]
    t_i, t_j = T[..., i, :3, 3], T[..., j, :3, 3]
    R_meas, t_meas = graph.measurements[:, :3, :3], graph.measurements[:, :3, 3]
    rotation = (R_j - R_i @ R_meas).square().sum((-1, -2))
    translation = (t_j - t_i - (R_i @ t_meas[:, :, None]).squeeze(-1)).square().sum(-1)
    return (kappa * rotation + tau * translation).sum(-1)
