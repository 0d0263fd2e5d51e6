"""Marginal covariances of the vertices of a solved pose graph.

The graph is the solver's objective of :func:`torchslam.posegraph.solve.solve_pose_graph`
(:func:`~torchslam.posegraph.solve.graph_data`: the poses are the body → world vertices T_i
themselves), so the covariances of :mod:`torchslam.covariance` are directly those of the
vertices: per vertex the 6 × 6 block Cov(δ_i) of the right perturbation T_i·Exp(δ_i),
δ = (ω, v) rotation first, the convention of g2o and GTSAM's ``Marginals`` (GTSAM's Pose3
tangent is (ω, v) too). The Gauss-Newton Hessian is JᵀΩJ of the chi² objective ½ Σ rᵀΩr at the given
poses (λ = 0), also after ``objective="sesync"`` (the information matrices are the noise
model; SE-Sync's isotropic weights are not);
covariances are relative to the fixed vertices (the solve's gauge), which have zero blocks.
Large graphs go through the sparse factor's selected inverse (all 2,500 vertices of
sphere2500 in about a second), never a dense inverse.

A 2D graph (``graph.dimension == 2``, read from ``VERTEX_SE2``/``EDGE_SE2``) is solved lifted to
SE(3) with out-of-plane terms of the lifting's own weights; at a planar solution its Hessian
does not couple the plane's directions (x, y, θ) = (v_x, v_y, ω_z) with the others (by the
mirror symmetry z → −z), so their marginal is the planar graph's own. Its blocks are 3 × 3 in
GTSAM's Pose2 order (x, y, θ), body frame (the right perturbation T·Exp(δ) of SE(2)), and
nothing of the invented out-of-plane directions is returned.

``torchslam posegraph FILE --covariance OUT.txt`` writes them (:func:`write_covariances`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.covariance import marginal_covariances_tensors
from torchslam.lie import se3
from torchslam.posegraph.graph import PoseGraph
from torchslam.posegraph.solve import (
    PoseGraphSolverConfig,
    PoseGraphSolveResult,
    PosePriors,
    _solver_config,
    graph_data,
)

__all__ = ["VertexCovariances", "marginal_covariances", "write_covariances"]


@dataclass
class VertexCovariances:
    """Marginal covariances of pose-graph vertices (right perturbation T_i·Exp(δ)): (ω, v)
    6 × 6 blocks for a 3D graph, (x, y, θ) 3 × 3 blocks for a 2D one (module doc)."""

    # Cov(δ_i) of the vertices ``vertex_index`` (indices into graph.poses), (V, 6, 6) or, for
    # a 2D graph, (V, 3, 3).
    vertices: Tensor
    vertex_index: Tensor
    # Cov(δ_i, δ_k) of the vertex pairs ``pair_index`` (R, 2), (R, 6, 6) or (R, 3, 3).
    pairs: Tensor
    pair_index: Tensor
    # "dense" or "sparse": how the inverse's blocks were formed.
    method: str
    # 3 (blocks in (ω, v)) or 2 (blocks in (x, y, θ)), the graph's.
    dimension: int = 3


# The (x, y, θ) entries of an SE(3) tangent (ω, v): v_x, v_y, ω_z.
PLANAR = (3, 4, 2)


def marginal_covariances(
    graph: PoseGraph,
    result: PoseGraphSolveResult | Tensor,
    *,
    vertices: bool | Sequence[int] | Tensor = True,
    pairs: Sequence[Sequence[int]] | Tensor | None = None,
    priors: PosePriors | None = None,
    fixed: Tensor | None = None,
    config: PoseGraphSolverConfig | None = None,
) -> VertexCovariances:
    """Marginal covariances of the vertices of ``graph`` at the solution (module doc).

    Pass the same ``priors``, ``fixed`` and ``config`` as to
    :func:`~torchslam.posegraph.solve.solve_pose_graph` (the same defaults: the file's
    ``FIX`` vertices, else vertex 0).

    Args:
        graph: the pose graph.
        result: the :class:`PoseGraphSolveResult` of the solve, or the poses (N, 4, 4).
        vertices: True (all, default), False or vertex indices (V,) (positions in
            ``graph.poses``, not ids).
        pairs: vertex pairs (i, k), (R, 2), whose cross-covariances to return; default none.
        priors, fixed, config: as for the solve.

    Returns:
        :class:`VertexCovariances`.

    Raises:
        ValueError: bad arguments, or a Hessian singular to working precision (a free gauge
            or a vertex the edges do not determine), naming the vertex.
        TypeError: arguments of the wrong type.
    """
    fn = "posegraph.marginal_covariances"
    if not isinstance(graph, PoseGraph):
        raise TypeError(
            f"{fn}: argument 'graph' must be a PoseGraph, got {_checks.describe(graph)}"
        )
    N = graph.num_vertices
    if isinstance(result, PoseGraphSolveResult):
        poses = result.poses
    elif isinstance(result, Tensor):
        poses = result
    else:
        raise TypeError(
            f"{fn}: argument 'result' must be the PoseGraphSolveResult of the solve or the "
            f"poses (N, 4, 4), got {_checks.describe(result)}"
        )
    _checks.check_tensor(fn, "poses", poses, (4, 4), min_batch_dims=1, dims="N")
    if poses.dim() != 3 or poses.shape[0] != N:
        raise ValueError(
            f"{fn}: the poses must have shape ({N}, 4, 4) (the graph's vertices), got "
            f"{tuple(poses.shape)}"
        )
    _checks.check_same_kind(fn, poses=poses, measurements=graph.measurements)
    config = PoseGraphSolverConfig() if config is None else config
    if not isinstance(config, PoseGraphSolverConfig):
        raise TypeError(
            f"{fn}: argument 'config' must be a PoseGraphSolverConfig or None, got "
            f"{_checks.describe(config)}"
        )
    if priors is not None and not isinstance(priors, PosePriors):
        raise TypeError(f"{fn}: argument 'priors' must be PosePriors or None, got {priors!r}")
    if fixed is None:
        fixed = graph.fixed if graph.fixed.numel() else graph.edges.new_zeros(1)
    _checks.check_tensor(fn, "fixed", fixed, floating=False)
    if fixed.dim() != 1 or (fixed.numel() and (int(fixed.min()) < 0 or int(fixed.max()) >= N)):
        raise ValueError(
            f"{fn}: argument 'fixed' must be vertex indices (F,) in [0, {N}), got shape "
            f"{tuple(fixed.shape)}"
        )
    solver_config = _solver_config(config)
    if config.linear_solver == "auto":  # the rule of solve_pose_graph
        free = N - int(torch.unique(fixed).numel())
        reduced = "dense" if 6 * free <= config.dense_max_variables else "sparse"
        solver_config = dataclasses.replace(solver_config, reduced_solver=reduced)
    # Always the chi² objective: the information matrices are the noise model, whatever
    # objective the solve minimized (config.objective chooses only where the poses came from).
    data = graph_data(graph, priors, fixed.to(torch.int64))
    with torch.no_grad():  # the pose-graph solve is not differentiable either
        xi = se3.log(poses.detach())[None]
        covariances = marginal_covariances_tensors(
            xi,
            xi.new_zeros(1, 0, 3),
            data,
            solver_config,
            poses=vertices,
            point_selection=False,
            pairs=pairs,
        )
    if not bool(covariances.ok[0]):
        raise ValueError(f"{fn}: {covariances.reason[0].replace('pose ', 'vertex index ')}")
    blocks, cross = covariances.poses[0], covariances.pairs[0]
    if graph.dimension == 2:
        planar = torch.tensor(PLANAR, device=blocks.device)
        blocks = blocks[:, planar][:, :, planar]
        cross = cross[:, planar][:, :, planar]
    return VertexCovariances(
        vertices=blocks,
        vertex_index=covariances.pose_index,
        pairs=cross,
        pair_index=covariances.pair_index,
        method=covariances.method,
        dimension=graph.dimension,
    )


def write_covariances(path: str | Path, graph: PoseGraph, covariances: VertexCovariances) -> None:
    """Write one line per vertex: its id and the entries of its covariance, row-major, right
    perturbation of the body → world vertex pose: ``id c11 c12 … c66`` in (ω, v) order for a
    3D graph, ``id c11 … c33`` in (x, y, θ) order for a 2D one (``%.17g``, exact float64
    round trip)."""
    ids = graph.ids[covariances.vertex_index].tolist()
    size = covariances.vertices.shape[-1]
    rows = covariances.vertices.detach().cpu().double().reshape(-1, size * size).tolist()
    lines = [
        " ".join([str(i)] + [f"{c:.17g}" for c in row]) for i, row in zip(ids, rows, strict=True)
    ]
    Path(path).write_text("\n".join(lines) + ("\n" if lines else ""), encoding="utf-8")
