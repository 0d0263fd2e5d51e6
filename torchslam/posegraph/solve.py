"""Pose-graph optimization: an adapter from a :class:`PoseGraph` onto the one solver loop.

Problem. Over the free vertex poses T_i (body i → world), minimize the standard cost

    F(T) = ½ Σ_(i,j) r_ijᵀ Ω_ij r_ij + ½ Σ_p r_pᵀ Ω_p r_p,
    r_ij = Log(Z_ij⁻¹ T_i⁻¹ T_j)   (between, :mod:`torchslam.posegraph.between`),
    r_p  = Log(Z_p⁻¹ T_(k_p))        (optional pose priors, :class:`PosePriors`),

ξ = (ω, v) rotation first, Ω in (ω, v) order — or, with ``PoseGraphSolverConfig(objective=
"sesync")``, the SE-Sync objective f(T) = Σ κ‖R_j − R_i R̃_ij‖_F² + τ‖t_j − t_i − R_i t̃_ij‖²
(:class:`torchslam.posegraph.objectives.SESyncTerm`, the loop's cost equals f; priors keep
their ½ r_pᵀΩ_p r_p), whose global optimum :mod:`torchslam.posegraph.certification`
certifies. The gauge: the vertices in ``fixed`` keep their
poses (default: the file's ``FIX`` vertices, or vertex 0 when it fixes none).

:func:`solve_pose_graph` turns the graph into the solver's objective (:func:`graph_data`: one
problem whose poses are the vertices T_i, the edges a :class:`torchslam.RelativePoseTerm` with
``convention="frame_to_world"``, the priors a :class:`torchslam.PosePriorTerm`) and runs
:func:`torchslam.solver.loop.run` on it:
the same Levenberg-Marquardt, stopping rules (:func:`torchslam.solver.loop.update_status`)
and planned linear solve (:class:`torchslam.solver.plan.LinearPlan`: the reduced system is
the whole pose system here, factored densely or by SuperLU in a fill-reducing order) as every
other solve, with the solver's retraction T_i ← T_i·Exp(δ) on the vertices (as g2o and GTSAM).

:class:`PoseGraphSolverConfig` keeps the defaults that suit pose graphs (λ₀ = 1e-9: the gauge
is fixed, so Gauss-Newton steps are taken from the start); ``linear_solver`` there names the
reduced solver ("auto", "sparse", "dense"). On a CPU shared with other processes keep torch at
one thread (``torch.set_num_threads(1)``): the per-edge tensors are too small to gain from
more. The solve is not differentiable (it runs under ``torch.no_grad``).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3
from torchslam.objective.data import PointMapData
from torchslam.objective.terms import PosePriorTerm, RelativePoseTerm
from torchslam.posegraph import objectives
from torchslam.posegraph.graph import PoseGraph, check_information, check_vertex_indices
from torchslam.solver import loop
from torchslam.solver.config import SolverConfig, check_int, check_number
from torchslam.solver.plan import LinearPlan
from torchslam.solver.result import REASONS, IterationInfo, SolveResult, Status

__all__ = [
    "IterationInfo",
    "PoseGraphSolveResult",
    "PoseGraphSolverConfig",
    "PosePriors",
    "initial_poses",
    "solve_pose_graph",
]

logger = logging.getLogger("torchslam.posegraph")

_DAMPINGS = ("marquardt", "levenberg")
_JACOBIANS = ("analytic", "jacrev")
_LINEAR_SOLVERS = ("auto", "sparse", "dense")
_ORDERINGS = ("mmd", "colamd", "natural")
_OBJECTIVES = ("chi2", "sesync")


@dataclass(frozen=True)
class PoseGraphSolverConfig:
    """Options of :func:`solve_pose_graph`. Defaults suit float64 pose graphs.

    Tolerances follow Ceres: the solve stops when an accepted step decreases the cost by less
    than ``function_tolerance`` relative to the cost (or the model predicts less than that),
    when the largest gradient entry falls below ``gradient_tolerance``, or when the step is
    shorter than ``parameter_tolerance`` · (‖x‖ + ``parameter_tolerance``), ‖x‖ the Frobenius
    norm of the free poses' top 3 × 4 rows.
    """

    # Maximum number of iterations (linear solves, accepted or not).
    max_iterations: int = 100
    # Stop when |ΔF| ≤ function_tolerance · F after an accepted step.
    function_tolerance: float = 1e-10
    # Stop when max |∇F| ≤ gradient_tolerance.
    gradient_tolerance: float = 1e-10
    # Stop when ‖δ‖ ≤ parameter_tolerance · (‖x‖ + parameter_tolerance).
    parameter_tolerance: float = 1e-12
    # Initial damping λ₀. Tiny: pose graphs (gauge fixed) are well posed, so Gauss-Newton
    # steps are taken from the start and rejections raise λ; with Nielsen's update λ falls at
    # most 3× per iteration, so Ceres' 1e-4 costs sphere2500/garage 2-9 extra iterations.
    initial_lambda: float = 1e-9
    # λ above which the solve gives up (no step decreases the cost): DAMPING_LIMIT.
    max_lambda: float = 1e16
    # λ never goes below this.
    min_lambda: float = 1e-16
    # Damping matrix: "marquardt" λ·diag(H) (scale invariant) or "levenberg" λ·I.
    damping: Literal["marquardt", "levenberg"] = "marquardt"
    # Jacobian blocks: "analytic" (between.between_jacobians) or "jacrev" (torch.func).
    jacobian: Literal["analytic", "jacrev"] = "analytic"
    # Linear solver: "auto" (dense up to dense_max_variables), "sparse" or "dense".
    linear_solver: Literal["auto", "sparse", "dense"] = "auto"
    # Largest system size 6n solved densely by "auto".
    dense_max_variables: int = 1200
    # Fill-reducing ordering of the vertex graph for "sparse": "mmd", "colamd" or "natural".
    ordering: Literal["mmd", "colamd", "natural"] = "mmd"
    # Objective of the edges: "chi2" (½ Σ rᵀΩr, r = Log(Z⁻¹ T_i⁻¹ T_j)) or "sesync" (the
    # SE-Sync objective of Rosen et al., objectives.SESyncTerm).
    objective: Literal["chi2", "sesync"] = "chi2"

    def __post_init__(self) -> None:
        fn = "PoseGraphSolverConfig"
        for name, allowed in (
            ("damping", _DAMPINGS),
            ("jacobian", _JACOBIANS),
            ("linear_solver", _LINEAR_SOLVERS),
            ("ordering", _ORDERINGS),
            ("objective", _OBJECTIVES),
        ):
            value = getattr(self, name)
            if not isinstance(value, str) or value not in allowed:
                raise ValueError(
                    f"{fn}: '{name}' must be one of {allowed}, got {_checks.describe(value)}"
                )
        for name in ("max_iterations", "dense_max_variables"):
            object.__setattr__(self, name, check_int(fn, name, getattr(self, name), 0))
        # Every real option is a finite number ≥ 0 (an infinite λ or tolerance stops nothing
        # or everything at once).
        for name in (
            "function_tolerance",
            "gradient_tolerance",
            "parameter_tolerance",
            "initial_lambda",
            "max_lambda",
            "min_lambda",
        ):
            object.__setattr__(self, name, check_number(fn, name, getattr(self, name), 0.0, True))
        if self.min_lambda > self.max_lambda:
            raise ValueError(
                f"{fn}: 'min_lambda' ({self.min_lambda!r}) must not exceed 'max_lambda' "
                f"({self.max_lambda!r})"
            )
        if self.initial_lambda > self.max_lambda:
            raise ValueError(
                f"{fn}: 'initial_lambda' ({self.initial_lambda!r}) must not exceed 'max_lambda' "
                f"({self.max_lambda!r})"
            )


@dataclass(frozen=True)
class PosePriors:
    """Pose priors r_p = Log(Z_p⁻¹ T_(k_p)) with information Ω_p, ξ = (ω, v) order."""

    # Vertex indices k_p (into graph.poses, not ids), shape (P,), int64.
    indices: Tensor
    # Prior poses Z_p (body → world), shape (P, 4, 4).
    poses: Tensor
    # Information matrices Ω_p in (ω, v) order, symmetric positive definite, shape (P, 6, 6).
    information: Tensor

    def __post_init__(self) -> None:
        fn = "PosePriors"
        _checks.check_tensor(fn, "poses", self.poses, (4, 4), min_batch_dims=1, dims="K")
        _checks.check_tensor(
            fn, "information", self.information, (6, 6), min_batch_dims=1, dims="K"
        )
        _checks.check_tensor(fn, "indices", self.indices, floating=False)
        _checks.check_same_kind(fn, poses=self.poses, information=self.information)
        if self.indices.dtype != torch.int64:
            raise TypeError(f"{fn}: argument 'indices' must be int64, got {self.indices.dtype}")
        count = self.indices.shape[0] if self.indices.dim() == 1 else -1
        if (
            self.poses.dim() != 3
            or self.information.dim() != 3
            or count < 0
            or self.poses.shape[0] != count
            or self.information.shape[0] != count
        ):
            raise ValueError(
                f"{fn}: 'indices', 'poses' and 'information' must have shapes (P,), "
                f"(P, 4, 4), (P, 6, 6); got {tuple(self.indices.shape)}, "
                f"{tuple(self.poses.shape)}, {tuple(self.information.shape)}"
            )
        check_information(fn, "information", self.information, "prior")
        _checks.check_pose_matrix(fn, "poses", self.poses)
        if _checks.value_checks_active() and self.indices.numel():
            negative = self.indices < 0
            if bool(negative.any()):
                p = int(negative.nonzero()[0, 0])
                raise ValueError(
                    f"{fn}: argument 'indices' must hold vertex indices ≥ 0 (positions in the "
                    f"graph's poses), got indices[{p}] = {int(self.indices[p])}"
                )

    @property
    def num_priors(self) -> int:
        """Number of priors P."""
        return self.indices.shape[0]


@dataclass
class PoseGraphSolveResult:
    """Outcome of :func:`solve_pose_graph` (one graph)."""

    # Optimized poses T_i (body i → world), (N, 4, 4); fixed vertices unchanged.
    poses: Tensor
    # Why the solve stopped (the statuses of torchslam.solver).
    status: Status
    # Iterations (linear solves, accepted or rejected).
    iterations: int
    # The objective at the start and at the end: ½ Σ rᵀΩr ("chi2") or the SE-Sync objective
    # f ("sesync"), plus ½ Σ r_pᵀΩ_p r_p of the priors.
    initial_cost: float
    final_cost: float
    # Cost after each iteration, (K + 1,), float64 on the CPU; entry 0 is the initial cost.
    cost_history: Tensor
    # Damping λ after each iteration, (K + 1,); entry 0 is the initial λ.
    lambda_history: Tensor
    # Norm ‖δ‖ of the step tried in each iteration, (K,).
    step_norm_history: Tensor
    # Max |gradient| at the final estimate, w.r.t. the vertices' right perturbations.
    gradient_norm: float
    # The linear solver used: "sparse" or "dense".
    linear_solver: str
    # Wall-clock seconds of the whole solve, and of its parts: linearization (residuals,
    # Jacobians, block products, assembly) and linear solves (factorization and solve).
    time_seconds: float
    linearize_seconds: float
    linear_solve_seconds: float
    # The loop's own result for the graph as one problem (poses as ξ of the vertices T_i).
    solve_result: SolveResult | None = None
    # Where the solve started: "chordal", "odometry", "file" (the graph's vertices) or
    # "given" (the ``poses`` argument).
    initialization: str = "given"

    @property
    def reason(self) -> str:
        """A sentence saying why the solve stopped."""
        return REASONS[self.status]

    @property
    def converged(self) -> bool:
        return self.status.converged

    def summary(self) -> str:
        return (
            f"{self.status.name} after {self.iterations} iterations, cost "
            f"{self.initial_cost:.6g} -> {self.final_cost:.6g} in {self.time_seconds:.3f} s "
            f"({self.linear_solver} solver; {self.reason})"
        )


def _check_inputs(
    graph: PoseGraph,
    poses: Tensor,
    priors: PosePriors | None,
    fixed: Tensor,
    config: PoseGraphSolverConfig,
    callback: object,
) -> None:
    fn = "solve_pose_graph"
    if not isinstance(config, PoseGraphSolverConfig):
        raise TypeError(
            f"{fn}: argument 'config' must be a PoseGraphSolverConfig or None, got "
            f"{_checks.describe(config)}"
        )
    if callback is not None and not callable(callback):
        raise TypeError(
            f"{fn}: argument 'callback' must be callable (called with an IterationInfo dict "
            f"after every iteration) or None, got {_checks.describe(callback)}"
        )
    N = graph.num_vertices
    _checks.check_tensor(fn, "poses", poses, (N, 4, 4), min_batch_dims=0)
    if poses.dim() != 3:
        raise ValueError(
            f"{fn}: argument 'poses' must have shape ({N}, 4, 4), got {tuple(poses.shape)}"
        )
    _checks.check_same_kind(fn, poses=poses, measurements=graph.measurements)
    _checks.check_pose_matrix(fn, "poses", poses)
    _checks.check_tensor(fn, "fixed", fixed, floating=False)
    if fixed.dtype != torch.int64:
        raise TypeError(f"{fn}: argument 'fixed' must be an int64 tensor, got {fixed.dtype}")
    if fixed.dim() != 1:
        raise ValueError(f"{fn}: argument 'fixed' must have shape (F,), got {tuple(fixed.shape)}")
    # The graph checked its edges when it was built, unless validation was off then.
    check_vertex_indices(fn, "graph.edges", graph.edges, N)
    indices = [("fixed", fixed)]
    if priors is not None:
        if not isinstance(priors, PosePriors):
            raise TypeError(
                f"{fn}: argument 'priors' must be PosePriors or None, got {type(priors).__name__}"
            )
        _checks.check_same_kind(fn, poses=poses, priors=priors.poses)
        _checks.check_pose_matrix(fn, "priors.poses", priors.poses)
        indices.append(("priors.indices", priors.indices))
    for name, index in indices:
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= N):
            raise ValueError(
                f"{fn}: '{name}' must hold vertex indices in [0, {N}), got values in "
                f"[{int(index.min())}, {int(index.max())}]"
            )
    if fixed.numel() == 0 and (priors is None or priors.num_priors == 0):
        raise ValueError(
            f"{fn}: the gauge is free: no vertex is fixed and there are no priors; fix a "
            "vertex (argument 'fixed') or add a PosePriors"
        )


def _check_information(
    graph: PoseGraph, priors: PosePriors | None, objective: str = "chi2"
) -> None:
    """ValueError naming the first edge or prior whose information is not positive definite
    (when validation is on); the terms whiten with the same matrices. The SE-Sync objective
    needs only the blocks its weights use (objectives.graph_sesync_weights)."""
    information = graph.information.detach()
    edges = graph.num_edges
    if objective == "sesync":
        objectives.graph_sesync_weights(graph, "solve_pose_graph")
        information, edges = information[:0], 0
    if priors is not None:
        information = torch.cat((information, priors.information.detach()))
    if not _checks.value_checks_active() or information.numel() == 0:
        return
    info = torch.linalg.cholesky_ex(information)[1]
    if bool((info > 0).any()):
        k = int((info > 0).nonzero()[0, 0])
        where = (
            f"'graph.information' of edge {k}"
            if k < edges
            else f"'priors.information' of prior {k - edges}"
        )
        raise ValueError(
            f"solve_pose_graph: the information matrices must be symmetric positive definite "
            f"(Cholesky factorization); {where} is not (a singular or indefinite matrix)"
        )


def _solver_config(config: PoseGraphSolverConfig | SolverConfig) -> SolverConfig:
    """The loop's configuration for a pose-graph configuration (a SolverConfig is kept)."""
    if isinstance(config, SolverConfig):
        return config
    return SolverConfig(
        algorithm="levenberg_marquardt",
        damping=config.damping,
        initial_lambda=config.initial_lambda,
        max_lambda=config.max_lambda,
        min_lambda=config.min_lambda,
        jacobian=config.jacobian,
        linear_solver="schur",
        reduced_solver=config.linear_solver,
        dense_max_variables=config.dense_max_variables,
        ordering=config.ordering,
        max_iterations=config.max_iterations,
        function_tolerance=config.function_tolerance,
        gradient_tolerance=config.gradient_tolerance,
        parameter_tolerance=config.parameter_tolerance,
    )


def graph_data(
    graph: PoseGraph,
    priors: PosePriors | None = None,
    fixed: Tensor | None = None,
    objective: str = "chi2",
) -> PointMapData:
    """The graph as the solver's objective: B = 1 problem whose m = N poses are the body →
    world vertices T_i themselves (so the loop's right perturbation T_i·Exp(δ) is the one
    g2o and GTSAM use), no points, the edges as one :class:`torchslam.RelativePoseTerm`
    with ``convention="frame_to_world"`` (r = Log(Z_ij⁻¹ T_i⁻¹ T_j)) and the priors as a
    :class:`torchslam.PosePriorTerm` (r_p = Log(Z_p⁻¹ T_k)), the vertices ``fixed`` (F,)
    held. With ``objective="sesync"`` the edges are an
    :class:`torchslam.posegraph.objectives.SESyncTerm` instead (SE-Sync's weights).
    """
    N = graph.num_vertices
    if objective == "sesync":
        terms = [objectives.SESyncTerm.from_graph(graph)]
    else:
        terms = [
            RelativePoseTerm(
                graph.edges,
                graph.measurements,
                information=graph.information,
                convention="frame_to_world",
            )
        ]
    if priors is not None and priors.num_priors:
        terms.append(PosePriorTerm(priors.indices, priors.poses, information=priors.information))
    fixed_poses = torch.zeros(1, N, dtype=torch.bool, device=graph.poses.device)
    if fixed is not None:
        fixed_poses[0, fixed] = True
    none = graph.edges.new_zeros(1, 0)
    empty = graph.poses.new_zeros(1, 0, 3)
    return PointMapData(
        pose_index=none,
        point_index=none,
        observations=empty,
        valid=torch.zeros(1, 0, dtype=torch.bool, device=graph.poses.device),
        weights=None,
        information=None,
        fixed_poses=fixed_poses,
        fixed_points=torch.zeros(1, 0, dtype=torch.bool, device=graph.poses.device),
        loss=None,
        terms=tuple(term.bind(1, N, empty) for term in terms),
    )


def initial_poses(graph: PoseGraph, init: str = "chordal", fixed: Tensor | None = None) -> Tensor:
    """The initial poses (N, 4, 4) that ``init`` names ("chordal", "odometry", "file"), moved
    rigidly so that the first fixed vertex (``fixed``, default as :func:`solve_pose_graph`'s)
    is where the graph puts it; every fixed vertex is set at its vertex (they are held there)."""
    from torchslam.posegraph import initialization as _init

    if init not in ("chordal", "odometry", "file"):
        raise ValueError(
            "initial_poses: argument 'init' must be 'chordal', 'odometry' or 'file', got "
            f"{_checks.describe(init)}"
        )
    if fixed is None:
        fixed = graph.fixed if graph.fixed.numel() else graph.edges.new_zeros(1)

    if init == "file":
        return graph.poses
    with torch.no_grad(), _checks.validation(False):
        if init == "odometry":
            poses = _init.odometry_initialization(graph)
        else:
            poses = _init.chordal_initialization(graph)
        index = fixed.reshape(-1).to(torch.int64)
        if index.numel():
            anchor = int(index[0])
            S = se3.compose(graph.poses[anchor], se3.inverse(poses[anchor]))
            poses = se3.compose(S.expand_as(poses), poses)
            poses[index] = graph.poses[index]
    return poses


def solve_pose_graph(
    graph: PoseGraph,
    poses: Tensor | None = None,
    *,
    config: PoseGraphSolverConfig | None = None,
    priors: PosePriors | None = None,
    fixed: Tensor | None = None,
    callback: Callable[[IterationInfo], None] | None = None,
    init: Literal["chordal", "odometry", "file"] = "chordal",
) -> PoseGraphSolveResult:
    """Minimize ½ Σ rᵀΩr (or the SE-Sync objective, ``config.objective``) over the free
    vertex poses by Levenberg-Marquardt (module docstring).

    Conventions: T_i maps body-i points into the world; r_ij = Log(Z_ij⁻¹ T_i⁻¹ T_j) and
    r_p = Log(Z_p⁻¹ T_k), ξ = (ω, v) rotation first, Ω in (ω, v) order; the retraction is
    T ← T·Exp(δ).

    Args:
        graph: the pose graph (edges, measurements Z_ij ≈ T_i⁻¹ T_j, information (E, 6, 6)).
        poses: initial poses, shape (N, 4, 4); when None, those ``init`` names.
        config: solver options; default :class:`PoseGraphSolverConfig()`.
        priors: optional pose priors (:class:`PosePriors`).
        fixed: indices (F,) int64 of vertices held at their initial poses (the gauge); when
            None, ``graph.fixed`` if the graph has any, else vertex 0. An empty tensor fixes
            nothing (then the priors must fix the gauge).
        callback: called after every iteration with an :data:`IterationInfo` dict.
        init: the initial poses when ``poses`` is None: ``"chordal"`` (default, as the
            command line: the chordal relaxation, from which LM reaches the optimum where the
            file's vertices can leave it in a local minimum: MIT.g2o ½χ² 20.60 against 385.1),
            ``"odometry"`` (the odometry chain) or ``"file"`` (``graph.poses``).

    Returns:
        A :class:`PoseGraphSolveResult` (poses, status and reason, costs, histories, times;
        ``initialization`` says where it started).

    Raises:
        ValueError, TypeError: for inconsistent shapes, dtypes, indices, non-positive-definite
            information, or a free gauge. Non-convergence is reported by ``status``.
    """
    if not isinstance(graph, PoseGraph):
        raise TypeError(
            f"solve_pose_graph: argument 'graph' must be a PoseGraph, got {_checks.describe(graph)}"
        )
    config = PoseGraphSolverConfig() if config is None else config
    if init not in ("chordal", "odometry", "file"):
        raise ValueError(
            "solve_pose_graph: argument 'init' must be 'chordal', 'odometry' or 'file', got "
            f"{_checks.describe(init)}"
        )
    initialization = "given" if poses is not None else init
    if fixed is None:
        fixed = graph.fixed if graph.fixed.numel() else graph.edges.new_zeros(1)
    _check_inputs(graph, graph.poses if poses is None else poses, priors, fixed, config, callback)
    start = time.perf_counter()  # the initialization counts in the solve's time
    with torch.no_grad():
        _check_information(graph, priors, getattr(config, "objective", "chi2"))
    if poses is None:
        poses = initial_poses(graph, init, fixed)
    solver_config = _solver_config(config)
    if isinstance(config, PoseGraphSolverConfig) and config.linear_solver == "auto":
        # The pose-graph rule: dense up to dense_max_variables free unknowns, else sparse
        # (a graph's pattern is sparse; no need for the general rule's work estimate).
        free = graph.num_vertices - int(torch.unique(fixed).numel())
        reduced = "dense" if 6 * free <= config.dense_max_variables else "sparse"
        solver_config = dataclasses.replace(solver_config, reduced_solver=reduced)
    with torch.no_grad(), _checks.validation(False):
        T = poses.detach()
        data = graph_data(graph, priors, fixed, getattr(config, "objective", "chi2"))
        xi = se3.log(T)[None]
        plan = LinearPlan.build(data, solver_config)

        def report(state: loop.State) -> None:
            if callback is None and not logger.isEnabledFor(logging.INFO):
                return
            info = loop.iteration_info(state, int(state.iterations.max()), start)
            if callback is not None:
                callback(info)
            logger.info(
                "iter %3d  cost %.6e  lambda %.2e  |step| %.2e  %s",
                info.iteration,
                float(info.cost[0]),
                float(info.damping[0]),
                float(info.step_norm[0]),
                "accepted" if bool(info.accepted[0]) else "rejected",
            )

        state, history = loop.run(
            xi, xi.new_zeros(1, 0, 3), data, solver_config, report, False, plan=plan
        )
        solved = loop.result(state, history, start)
        optimized = se3.exp(solved.pose_tangent[0])
        # The gauge vertices keep their poses bit for bit (no Log∘Exp round trip).
        optimized = torch.where(data.fixed_poses[0][:, None, None], T, optimized)
        g = state.lin.pose_gradient[0]
        gradient_norm = float(g.abs().max()) if g.numel() else 0.0
    return PoseGraphSolveResult(
        poses=optimized,
        status=solved.status[0],
        iterations=int(solved.iterations[0]),
        initial_cost=float(solved.initial_cost[0]),
        final_cost=float(solved.final_cost[0]),
        cost_history=solved.cost_history[0].detach().cpu().to(torch.float64),
        lambda_history=solved.lambda_history[0].detach().cpu().to(torch.float64),
        step_norm_history=solved.step_norm_history[0].detach().cpu().to(torch.float64),
        gradient_norm=gradient_norm,
        linear_solver="sparse" if plan.sparse else "dense",
        time_seconds=time.perf_counter() - start,
        linearize_seconds=solved.linearize_seconds,
        linear_solve_seconds=solved.linear_solve_seconds,
        solve_result=solved,
        initialization=initialization,
    )
