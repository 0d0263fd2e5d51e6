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
from torchslam.objective.terms import RelativePoseTerm

__all__ = ["GraphSource", "PoseGraph"]


@dataclass(frozen=True)
class GraphSource:
    """How :mod:`torchslam.io.g2o` built a :class:`PoseGraph` from a file.

    The reader's rules are in :mod:`torchslam.io.g2o` ("Edge-only files", "Information
    matrices that are not positive semidefinite").
    """

    # The file (or ``parse_g2o``'s ``source`` name).
    path: str
    # False for an edge-only file (no VERTEX lines): the vertices are the ids the edges name,
    # and ``PoseGraph.poses`` chain the measurements along a spanning tree of the edges.
    has_vertices: bool = True
    # The handling of information matrices that are not positive semidefinite: "repair",
    # "nearest" or "strict" (torchslam.io.g2o.INFORMATION_HANDLINGS).
    information: str = "repair"
    # Indices of the edges whose information matrix was replaced (empty under "strict").
    adjusted_edges: tuple[int, ...] = ()
    # Their line numbers in the file, in the same order.
    adjusted_lines: tuple[int, ...] = ()


@dataclass(frozen=True)
class PoseGraph:
    """A pose graph: N vertices, E relative-pose edges (see the module docstring).

    Vertices are stored sorted by id, so that index k is the k-th smallest id; ``edges`` hold
    indices into ``poses`` (not ids). 2D (SE(2)) graphs are lifted into SE(3) with z = 0 (see
    :mod:`torchslam.io.g2o` for the rule); ``dimension`` remembers which file type they came from.

    Construction checks the types and shapes below (TypeError/ValueError naming ``PoseGraph``
    and the field) and, when validation is on (:func:`torchslam._checks.value_checks_active`),
    the values: ``ids`` strictly increasing, ``edges`` and ``fixed`` in [0, N), ``poses`` and
    ``measurements`` finite rigid transforms, ``information`` finite, symmetric and positive
    semidefinite (relative tolerances; the solver needs positive definite ones).
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
    # How the graph was read from a file (set by torchslam.io.g2o), or None.
    source: GraphSource | None = None

    def __post_init__(self) -> None:
        fn = "PoseGraph"
        if self.source is not None and not isinstance(self.source, GraphSource):
            raise TypeError(
                f"{fn}: argument 'source' must be a GraphSource or None, got "
                f"{_checks.describe(self.source)}"
            )
        _checks.check_tensor(fn, "poses", self.poses, (4, 4), min_batch_dims=1, dims="N")
        n = self.poses.shape[-3]
        _checks.check_tensor(
            fn, "measurements", self.measurements, (4, 4), min_batch_dims=1, dims="E"
        )
        _checks.check_tensor(
            fn, "information", self.information, (6, 6), min_batch_dims=1, dims="E"
        )
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
        if self.fixed.dim() != 1:
            raise ValueError(
                f"{fn}: argument 'fixed' must have shape (F,), got {tuple(self.fixed.shape)}"
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
        if n == 0:
            raise ValueError(f"{fn}: argument 'poses' must hold at least one vertex, got (0, 4, 4)")
        if not isinstance(self.dimension, int) or isinstance(self.dimension, bool):
            raise TypeError(
                f"{fn}: argument 'dimension' must be the int 2 or 3, got "
                f"{_checks.describe(self.dimension)}"
            )
        if self.dimension not in (2, 3):
            raise ValueError(f"{fn}: 'dimension' must be 2 or 3, got {self.dimension}")
        if not _checks.value_checks_active():
            return
        ids = self.ids.detach()
        decreasing = ~(ids[1:] > ids[:-1])
        if bool(decreasing.any()):
            k = int(decreasing.nonzero()[0, 0])
            raise ValueError(
                f"{fn}: argument 'ids' must be strictly increasing (vertices are stored sorted "
                f"by id, and 'edges' index them); got ids[{k}] = {int(ids[k])} followed by "
                f"ids[{k + 1}] = {int(ids[k + 1])}: sort the vertices (and renumber the edges) "
                "or remove the duplicate"
            )
        check_vertex_indices(fn, "edges", self.edges, n)
        check_vertex_indices(fn, "fixed", self.fixed, n)
        _checks.check_pose_matrix(fn, "poses", self.poses)
        _checks.check_pose_matrix(fn, "measurements", self.measurements)
        check_information(fn, "information", self.information, "edge")

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
        """A copy of the graph with new vertex poses (N, 4, 4); everything else is shared.

        ``poses`` must have the shape, dtype and device of ``self.poses`` and hold rigid
        transforms (checked when validation is on).
        """
        fn = "PoseGraph.with_poses"
        _checks.check_tensor(fn, "poses", poses, (4, 4))
        if tuple(poses.shape) != tuple(self.poses.shape):
            raise ValueError(
                f"{fn}: argument 'poses' must have shape {tuple(self.poses.shape)} (one pose per "
                f"vertex), got {tuple(poses.shape)}"
            )
        _checks.check_same_kind(fn, poses=poses, measurements=self.measurements)
        _checks.check_pose_matrix(fn, "poses", poses)
        # Everything else was checked when this graph was built.
        with _checks.validation(False):
            return dataclasses.replace(self, poses=poses)


# Relative tolerances of the information checks. An asymmetry |Ω − Ωᵀ| up to this multiple of
# max|Ω| is round-off (Ω = inv(Σ) computed in floating point is symmetric to ~cond(Σ)·eps: the
# float64 bound admits cond(Σ) up to ~1e7). A negative eigenvalue down to −(multiple) · max|λ|
# is round-off too (a singular PSD matrix written with 17 digits, or cast to float32, has
# eigenvalues of a few ulps of its scale around 0), as in torchslam.io.g2o's reader.
_SYMMETRY_TOLERANCE = {torch.float64: 1e-8, torch.float32: 1e-4}
_PSD_TOLERANCE = {torch.float64: 1e-9, torch.float32: 1e-5}


def check_vertex_indices(fn: str, name: str, index: Tensor, num_vertices: int) -> None:
    """Raise ValueError unless the int64 tensor ``index`` holds indices in [0, num_vertices).

    Only when value checks are active (it needs a host sync). Negative indices are refused
    (torch would wrap them silently to the last vertices).
    """
    if not _checks.value_checks_active() or index.numel() == 0:
        return
    bad = (index < 0) | (index >= num_vertices)
    if bool(bad.any()):
        where = tuple(int(i) for i in bad.nonzero()[0].tolist())
        row = index[where[0]].tolist() if index.dim() == 2 else int(index[where])
        label = f"{name}[{where[0]}] = {row}"
        raise ValueError(
            f"{fn}: argument '{name}' must hold vertex indices in [0, {num_vertices}) "
            f"(positions in 'poses', not vertex ids), got {label}"
        )


def check_information(fn: str, name: str, information: Tensor, item: str) -> None:
    """Raise ValueError unless the (K, k, k) ``information`` matrices are finite, symmetric
    (relative tolerance) and positive semidefinite; the message names ``item`` k (e.g. "edge").

    Only when value checks are active (eigenvalues and a host sync).
    """
    _checks.check_finite(fn, name, information)
    if not _checks.value_checks_active() or information.numel() == 0:
        return
    omega = information.detach().to(torch.float64)
    scale = omega.abs().amax(dim=(-2, -1))
    safe = torch.where(scale > 0, scale, torch.ones_like(scale))[:, None, None]
    omega = omega / safe  # entries in [-1, 1]: no overflow below
    asymmetry = (omega - omega.transpose(-1, -2)).abs().amax(dim=(-2, -1))
    tolerance = _SYMMETRY_TOLERANCE[information.dtype]
    bad = asymmetry > tolerance
    if bool(bad.any()):
        k = int(bad.nonzero()[0, 0])
        raise ValueError(
            f"{fn}: argument '{name}' must hold symmetric matrices; {item} {k} has "
            f"max|Ω − Ωᵀ| = {float(asymmetry[k] * scale[k]):.3g} relative to max|Ω| = "
            f"{float(scale[k]):.3g} (tolerance {tolerance:g} relative)"
        )
    eigenvalues = torch.linalg.eigvalsh(0.5 * (omega + omega.transpose(-1, -2)))
    largest = eigenvalues.abs().amax(dim=-1)
    bad = eigenvalues[:, 0] < -_PSD_TOLERANCE[information.dtype] * largest
    if bool(bad.any()):
        k = int(bad.nonzero()[0, 0])
        raise ValueError(
            f"{fn}: argument '{name}' must hold positive semidefinite matrices; {item} {k} "
            f"has the eigenvalue {float(eigenvalues[k, 0] * scale[k]):.6g} (largest magnitude "
            f"{float(largest[k] * scale[k]):.6g})"
        )
