"""The back end: a robust pose graph over the keyframes, then the joint ICP-SLAM refinement.

1. **Pose graph.** Vertices: the keyframes' poses T_wk (frame → world), keyframe 0 fixed (the
   gauge). Edges: odometry between consecutive keyframes (Z = T_a⁻¹ T_b, the tracking
   alignment's information) and the accepted loop closures (:mod:`torchslam.slam.loops`),
   residual r = Log(Z⁻¹ T_a⁻¹ T_b), cost ½ Σ rᵀΩr (the :mod:`torchslam.posegraph` objective),
   solved by Levenberg-Marquardt (the library's solver). Two χ² tests with the bound
   ``loop_max_chi2`` judge the loops first (:func:`_consistent_loops`):

   - **against the odometry**: each loop alone, the Mahalanobis distance νᵀ(Σ_chain +
     Σ_loop)⁻¹ν of its innovation ν = Log(Z⁻¹ T_a⁻¹ T_b) from the odometry chain's
     prediction (:func:`_odometry_chi2`); a loop above the bound is dropped. Without it a
     lone wrong closure would pass the second test, the chain bending to fit it;
   - **against the other loops**: the graph in least squares from the odometry poses; while
     a loop edge's χ² = rᵀΩr exceeds the bound the worst one is dropped and the graph solved
     again (a closure that contradicts the others cannot bend the map).

   Then the remaining loop edges get a Cauchy kernel ρ(s) = a² log(1 + s/a²),
   a = ``loop_kernel_scale``, for a last solve from there.
2. **Joint refinement** (``refine_rounds`` > 0): the seed's multiview ICP-SLAM least squares
   over the keyframes, poses and points together
   (:func:`torchslam.registration.pipeline.refine`, the one solver), on the keyframe pairs
   within ``refine_neighbors`` of each other plus the kept loop pairs.
3. **Covariances** of the keyframe poses: the marginals of the final pose graph
   (:func:`torchslam.posegraph.covariance.marginal_covariances`), (K, 6, 6), (ω, v), right
   perturbation T_k·Exp(δ), relative to keyframe 0.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3, so3
from torchslam.losses import CauchyLoss
from torchslam.objective import PointMapData
from torchslam.objective.terms import RelativePoseTerm
from torchslam.slam.config import SLAMConfig
from torchslam.slam.loops import LoopClosure
from torchslam.slam.odometry import Keyframe
from torchslam.solver import SolverConfig, SolveResult, Status, solve_tensors

__all__ = ["BackendResult", "optimize_keyframes"]


@dataclass
class BackendResult:
    """Keyframe poses after the back end, and what each stage did."""

    # T_wk after the pose graph, (K, 4, 4)
    graph_poses: Tensor
    # T_wk after the joint refinement (= graph_poses when it did not run), (K, 4, 4)
    poses: Tensor
    # ½ Σ ρ(rᵀΩr) of the pose graph before and after its (last) solve
    graph_initial_cost: float
    graph_final_cost: float
    graph_iterations: int
    # joint refinement: rounds run, final cost (NaN when none ran)
    refine_rounds: int
    refine_cost: float
    # marginal covariances of the keyframe poses (K, 6, 6), or None (singular / not asked)
    covariances: Tensor | None
    seconds: dict[str, float]
    # the pose graph's solver status (a torchslam.solver.Status name); None when no graph was
    # solved (no accepted loop closure: the odometry chain is already its optimum)
    graph_status: str | None = None


def _information(omega: Tensor) -> Tensor:
    """Symmetrized, with a tiny ridge so that a degenerate alignment stays positive definite."""
    omega = 0.5 * (omega + omega.transpose(-1, -2))
    scale = omega.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-12)
    return omega + 1e-9 * scale[..., None, None] * torch.eye(6, dtype=omega.dtype)


def _graph_data(
    poses: Tensor,
    keyframes: list[Keyframe],
    loops: list[LoopClosure],
    kernel_scale: float | None,
) -> PointMapData:
    K = poses.shape[0]
    terms = []
    if K > 1:
        a = torch.arange(K - 1)
        odometry_z = se3.compose(
            se3.inverse(torch.stack([kf.pose for kf in keyframes[:-1]])),
            torch.stack([kf.pose for kf in keyframes[1:]]),
        )
        odometry_info = _information(torch.stack([kf.information for kf in keyframes[1:]]))
        terms.append(
            RelativePoseTerm(
                torch.stack((a, a + 1), -1),
                odometry_z,
                information=odometry_info,
                convention="frame_to_world",
            )
        )
    if loops:
        terms.append(
            RelativePoseTerm(
                torch.tensor([[c.first, c.second] for c in loops], dtype=torch.int64),
                torch.stack([c.measurement for c in loops]),
                information=_information(torch.stack([c.information for c in loops])),
                convention="frame_to_world",
                loss=None if kernel_scale is None else CauchyLoss(kernel_scale),
            )
        )
    fixed = torch.zeros(1, K, dtype=torch.bool)
    fixed[0, 0] = True
    none = torch.zeros(1, 0, dtype=torch.int64)
    empty = poses.new_zeros(1, 0, 3)
    return PointMapData(
        pose_index=none,
        point_index=none,
        observations=empty,
        valid=torch.zeros(1, 0, dtype=torch.bool),
        weights=None,
        information=None,
        fixed_poses=fixed,
        fixed_points=torch.zeros(1, 0, dtype=torch.bool),
        loss=None,
        terms=tuple(term.bind(1, K, empty) for term in terms),
    )


def _odometry_chi2(start: Tensor, keyframes: list[Keyframe], loops: list[LoopClosure]) -> Tensor:
    """χ² of each loop against the odometry chain alone, (L,): the Mahalanobis distance
    νᵀ(Σ_chain + Σ_loop)⁻¹ν of the innovation ν = Log(Z⁻¹ T_a⁻¹ T_b) (T the odometry poses).

    With odometry edges T_{e−1}⁻¹T_e = Z_e Exp(n_e), n_e ~ N(0, Ω_e⁻¹), the chain's
    T_a⁻¹T_b = Π_{e=a+1..b} Z_e Exp(n_e) = T_a⁻¹T_b · Exp(Σ_e Ad(T_b⁻¹T_e) n_e) to first order,
    so Σ_chain = Σ_e Ad(T_b⁻¹T_e) Ω_e⁻¹ Ad(T_b⁻¹T_e)ᵀ; Σ_loop = Ω_loop⁻¹. To first order it is
    2× the least-squares cost of the graph of the chain and that one loop (the chain alone
    costs 0)."""
    odometry = _information(torch.stack([kf.information for kf in keyframes[1:]]))
    eye = torch.eye(6, dtype=start.dtype)
    sigma = torch.linalg.solve(odometry, eye.expand_as(odometry))  # edge e at e − 1
    nu, omega = _loop_residuals(start, loops)  # the innovations at the odometry poses
    S = torch.linalg.solve(omega, eye.expand_as(omega))  # Σ_loop, then + Σ_chain
    for row, c in enumerate(loops):
        a, b = c.first, c.second
        A = se3.adjoint(
            se3.compose(se3.inverse(start[b]).expand(b - a, 4, 4), start[a + 1 : b + 1])
        )
        S[row] += (A @ sigma[a:b] @ A.mT).sum(0)
    S = 0.5 * (S + S.mT)
    return (nu[:, None, :] @ torch.linalg.solve(S, nu[:, :, None]))[:, 0, 0]


def _loop_residuals(poses: Tensor, loops: list[LoopClosure]) -> tuple[Tensor, Tensor]:
    """The loop edges' residuals r = Log(Z⁻¹ T_a⁻¹ T_b) at ``poses`` (L, 6) and their
    information (L, 6, 6)."""
    i = torch.tensor([c.first for c in loops])
    k = torch.tensor([c.second for c in loops])
    Z = torch.stack([c.measurement for c in loops])
    r = se3.log(se3.compose(se3.inverse(Z), se3.compose(se3.inverse(poses[i]), poses[k])))
    return r, _information(torch.stack([c.information for c in loops]))


def _loop_chi2(poses: Tensor, loops: list[LoopClosure]) -> Tensor:
    r, omega = _loop_residuals(poses, loops)
    return (r[:, None, :] @ omega @ r[:, :, None])[:, 0, 0]


def _solve_graph(
    start: Tensor,
    keyframes: list[Keyframe],
    loops: list[LoopClosure],
    config: SLAMConfig,
    *,
    robust: bool,
):
    data = _graph_data(start, keyframes, loops, config.loop_kernel_scale if robust else None)
    solver = SolverConfig(max_iterations=50, function_tolerance=1e-10)
    result = solve_tensors(se3.log(start)[None], start.new_zeros(1, 0, 3), data, solver)
    poses = se3.exp(result.pose_tangent[0])
    return poses, result


def _consistent_loops(
    start: Tensor, keyframes: list[Keyframe], loops: list[LoopClosure], config: SLAMConfig
) -> tuple[list[LoopClosure], Tensor, SolveResult | None]:
    """The loops that pass both χ² tests (module docstring), and the least-squares graph
    solved with them (poses (K, 4, 4) and the solver's result; None when none passes).

    First each loop against the odometry chain alone: without this test a lone wrong
    closure would pass the second, the chain bending to fit it. Then, in least squares (a
    kernel would ignore a correct loop whose error the odometry has not yet absorbed), the
    most inconsistent loop is dropped while any loop's χ² exceeds the bound."""
    if len(keyframes) < 2 or not loops:
        return [], start, None
    kept = []
    for c, value in zip(loops, _odometry_chi2(start, keyframes, loops).tolist(), strict=True):
        c.odometry_chi2 = value
        if value > config.loop_max_chi2:
            c.chi2, c.contradicts_odometry = value, True
        else:
            kept.append(c)
    if not kept:
        return [], start, None
    poses, result = _solve_graph(start, keyframes, kept, config, robust=False)
    while kept:
        chi2 = _loop_chi2(poses, kept)
        worst = int(chi2.argmax())
        if float(chi2[worst]) <= config.loop_max_chi2:
            break
        kept[worst].chi2 = float(chi2[worst])
        del kept[worst]
        if kept:
            poses, result = _solve_graph(start, keyframes, kept, config, robust=False)
    return kept, poses, result


def optimize_keyframes(
    keyframes: list[Keyframe], loops: list[LoopClosure], config: SLAMConfig
) -> BackendResult:
    """Run the back end (module docstring) on the keyframes and the accepted loop closures;
    sets each closure's ``kept`` and ``chi2``."""
    seconds: dict[str, float] = {}
    tic = time.perf_counter()
    start = torch.stack([kf.pose for kf in keyframes])
    accepted = [c for c in loops if c.accepted]
    K = len(keyframes)
    with _checks.validation(False):
        kept, poses, result = _consistent_loops(start, keyframes, accepted, config)
        if kept:
            poses, result = _solve_graph(poses, keyframes, kept, config, robust=True)
            for c, value in zip(kept, _loop_chi2(poses, kept).tolist(), strict=True):
                c.kept, c.chi2 = True, value
            initial, final = float(result.initial_cost[0]), float(result.final_cost[0])
            iterations = int(result.iterations[0])
            status = Status(int(result.status[0])).name
        else:  # the odometry chain is its own optimum
            poses, initial, final, iterations, status = start.clone(), 0.0, 0.0, 0, None
        poses = se3.from_rotation_translation(so3.project(poses[:, :3, :3]), poses[:, :3, 3])
    seconds["pose_graph"] = time.perf_counter() - tic
    kept = [c for c in accepted if c.kept]

    tic = time.perf_counter()
    refined, rounds, refine_cost = poses, 0, float("nan")
    if config.refine_rounds > 0 and K > 2:
        refined, rounds, refine_cost = _refine(keyframes, poses, kept, config)
    seconds["refine"] = time.perf_counter() - tic

    tic = time.perf_counter()
    covariances = _covariances(refined, keyframes, kept)
    seconds["covariance"] = time.perf_counter() - tic
    return BackendResult(
        poses, refined, initial, final, iterations, rounds, refine_cost, covariances, seconds,
        status,
    )  # fmt: skip


def _refine(
    keyframes: list[Keyframe], poses: Tensor, loops: list[LoopClosure], config: SLAMConfig
) -> tuple[Tensor, int, float]:
    from torchslam.registration.config import RegisterConfig
    from torchslam.registration.pipeline import refine

    K = len(keyframes)
    pairs = {
        (i, j) for i in range(K) for j in range(i + 1, min(K, i + config.refine_neighbors + 1))
    }
    pairs |= {(c.first, c.second) for c in loops}
    register_config = RegisterConfig(
        voxel_size=config.voxel,
        rounds=config.refine_rounds,
        normal_neighbors=config.normal_neighbors,
        max_iterations=config.refine_iterations,
    )
    clouds = [kf.points for kf in keyframes]
    # the keyframes' normals are those of their clouds already; the pose covariances come
    # from the pose graph (step 3)
    result = refine(
        clouds,
        poses,
        register_config,
        pairs=sorted(pairs),
        normals=[kf.normals for kf in keyframes],
        covariances=False,
        # the boundary test made with the normals (the same neighbourhoods), when every
        # keyframe has it
        interior=None
        if any(kf.interior is None for kf in keyframes)
        else [kf.interior for kf in keyframes],
    )
    if not result.rounds:
        return poses, 0, float("nan")
    refined = result.poses
    if not bool(torch.isfinite(refined).all()):
        return poses, len(result.rounds), float("nan")
    # refine returns poses relative to keyframe 0; keyframe 0 is the world frame already.
    refined = se3.compose(poses[0:1].expand_as(refined), refined)
    refined = se3.from_rotation_translation(so3.project(refined[:, :3, :3]), refined[:, :3, 3])
    return refined, len(result.rounds), result.rounds[-1].final_cost


def _covariances(
    poses: Tensor, keyframes: list[Keyframe], loops: list[LoopClosure]
) -> Tensor | None:
    from torchslam.posegraph.covariance import marginal_covariances
    from torchslam.posegraph.graph import PoseGraph

    K = len(keyframes)
    if K < 2:
        return None
    a = torch.arange(K - 1)
    edges = [torch.stack((a, a + 1), -1)]
    measurements = [
        se3.compose(
            se3.inverse(torch.stack([kf.pose for kf in keyframes[:-1]])),
            torch.stack([kf.pose for kf in keyframes[1:]]),
        )
    ]
    information = [torch.stack([kf.information for kf in keyframes[1:]])]
    if loops:
        edges.append(torch.tensor([[c.first, c.second] for c in loops], dtype=torch.int64))
        measurements.append(torch.stack([c.measurement for c in loops]))
        information.append(torch.stack([c.information for c in loops]))
    with _checks.validation(False):
        graph = PoseGraph(
            torch.arange(K),
            poses,
            torch.cat(edges),
            torch.cat(measurements),
            _information(torch.cat(information)),
        )
        try:
            covariances = marginal_covariances(graph, poses)
        except (ValueError, RuntimeError):
            return None
    return covariances.vertices
