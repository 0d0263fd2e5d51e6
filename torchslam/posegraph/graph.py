"""The pose-graph container: vertices (poses) and relative-pose edges with information matrices.

Conventions (g2o's meaning, in torchslam's tangent order):
- A vertex pose T_i = [[R_i, t_i], [0, 1]] maps points of body frame i into the world frame,
  p_world = R_i p_i + t_i (g2o's and GTSAM's convention for pose graphs).
- An edge (i, j) carries the measurement Z_ij ≈ T_i⁻¹ T_j (pose of j seen from i) and a 6 × 6
  information matrix Ω_ij in torchslam's tangent order ξ = (ω, v): rotation first. g2o files
  store it in the order [translation, rotation]; :mod:`torchslam.io.g2o` reorders it.
- The residual of an edge is r_ij = Log(Z_ij⁻¹ T_i⁻¹ T_j) (see :mod:`torchslam.posegraph.between`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3
from torchslam.terms import RelativePoseTerm

__all__ = ["PoseGraph"]


@dataclass(frozen=True)
class PoseGraph:
    """A pose graph: N vertices, E relative-pose edges (see the module docstring).

    Vertices are stored sorted by id, so that index k is the k-th smallest id; ``edges`` hold
    indices into ``poses`` (not ids). 2D (SE(2)) graphs are lifted into SE(3) with z = 0 (see
    :mod:`torchslam.io.g2o` for the rule); ``dimension`` remembers which file type they came from.
    """

    # Vertex ids as in the file, ascending, shape (N,), int64.
    ids: Tensor
    # Vertex poses T_i (body i → world), shape (N, 4, 4), float64 by default.
    poses: Tensor
    # Edges as indices (i, j) into ``poses``, shape (E, 2), int64.
    edges: Tensor
    # Measurements Z_ij ≈ T_i⁻¹ T_j, shape (E, 4, 4), same dtype as ``poses``.
    measurements: Tensor
    # Information matrices Ω_ij in (ω, v) order, symmetric, shape (E, 6, 6).
    information: Tensor
    # 3 for SE(3) graphs, 2 for SE(2) graphs lifted into SE(3).
    dimension: int = 3
    # Indices of vertices fixed by the file (g2o ``FIX`` lines), shape (F,), int64.
    fixed: Tensor = dataclasses.field(default_factory=lambda: torch.zeros(0, dtype=torch.int64))

    def __post_init__(self) -> None:
        fn = "PoseGraph"
        _checks.check_tensor(fn, "poses", self.poses, (4, 4), min_batch_dims=1)
        n = self.poses.shape[-3]
        _checks.check_tensor(fn, "measurements", self.measurements, (4, 4), min_batch_dims=1)
        _checks.check_tensor(fn, "information", self.information, (6, 6), min_batch_dims=1)
        _checks.check_same_kind(
            fn, poses=self.poses, measurements=self.measurements, information=self.information
        )
        for name, value, shape in (
            ("ids", self.ids, (n,)),
            ("edges", self.edges, (self.measurements.shape[0], 2)),
            ("fixed", self.fixed, None),
        ):
            _checks.check_tensor(fn, name, value, floating=False)
            if value.dtype != torch.int64:
                raise TypeError(f"{fn}: argument '{name}' must be int64, got {value.dtype}")
            if shape is not None and tuple(value.shape) != shape:
                raise ValueError(
                    f"{fn}: argument '{name}' must have shape {shape}, got {tuple(value.shape)}"
                )
        if self.poses.dim() != 3 or self.measurements.dim() != 3 or self.information.dim() != 3:
            raise ValueError(
                f"{fn}: 'poses', 'measurements' and 'information' must have shapes (N, 4, 4), "
                f"(E, 4, 4), (E, 6, 6); got {tuple(self.poses.shape)}, "
                f"{tuple(self.measurements.shape)}, {tuple(self.information.shape)}"
            )
        if self.information.shape[0] != self.measurements.shape[0]:
            raise ValueError(
                f"{fn}: 'information' has {self.information.shape[0]} edges but "
                f"'measurements' has {self.measurements.shape[0]}"
            )
        if self.dimension not in (2, 3):
            raise ValueError(f"{fn}: 'dimension' must be 2 or 3, got {self.dimension}")

    @property
    def num_vertices(self) -> int:
        """Number of vertices N."""
        return self.poses.shape[0]

    @property
    def num_edges(self) -> int:
        """Number of edges E."""
        return self.edges.shape[0]

    def odometry_mask(self) -> Tensor:
        """Boolean mask (E,) of the odometry edges: from vertex index k to k + 1.

        With contiguous ids (as in the benchmark files) that is id_j = id_i + 1; the other
        edges are loop closures.
        """
        return self.edges[:, 1] == self.edges[:, 0] + 1

    def frame_poses(self) -> Tensor:
        """The vertices as ICP-SLAM poses T_i0 = T_i⁻¹ (world → frame i), (N, 4, 4)."""
        return se3.inverse(self.poses)

    def relative_pose_term(self) -> RelativePoseTerm:
        """The edges as one :class:`torchslam.RelativePoseTerm` on the poses T_i0 = T_i⁻¹.

        g2o's Z_ij ≈ T_i⁻¹ T_j equals T_i0 T_j0⁻¹, the term's measurement, and both residuals
        are Log(Z_ij⁻¹ T_i⁻¹ T_j): the same cost, so a pose graph can join point observations
        in one :class:`torchslam.PointMapProblem` (with :meth:`frame_poses` as its poses).
        The file's ``FIX`` vertices are not carried: pass them as ``fixed_poses`` (the
        problem fixes pose 0 by default).
        """
        return RelativePoseTerm(self.edges, self.measurements, information=self.information)

    def with_poses(self, poses: Tensor) -> PoseGraph:
        """A copy of the graph with new vertex poses (N, 4, 4); everything else is shared."""
        return dataclasses.replace(self, poses=poses)
