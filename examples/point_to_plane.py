"""A user-written point-to-plane term, solved together with torchslam's built-in terms.

    .venv/bin/python examples/point_to_plane.py

A synthetic ICP-SLAM scene (8 frames seeing 40 points with 2 cm noise) is solved twice from
the odometry initialization, with

- the point observations r = X_ij − T_i0 X_j (built in, points eliminated by Schur),
- odometry Z_(i,i+1) ≈ T_i0 T_(i+1)0⁻¹ between successive frames (:class:`RelativePoseTerm`),
- and, the second time, :class:`PointToPlane` terms: in each frame, planes of a known map
  (surveyed points X in the world, each on a plane that the frame sees as a point p and a
  unit normal n, in frame coordinates) with r = nᵀ(T_i0 X − p).

The point-to-plane term is only its residual (no Jacobians): torchslam differentiates it with
``torch.func.jacrev``, vmapped over the instances, and folds it into the same Schur solve.
Conventions: T_i0 maps world → frame i; ξ = (ω, v) rotation first; T ← T·Exp(δ).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchslam import PointMapProblem, RelativePoseTerm, Term, solve
from torchslam.data.synthetic import SyntheticScene, make_scene
from torchslam.initialization import average_points, chain_relative_poses, odometry_relative_poses
from torchslam.lie import se3
from torchslam.metrics import pose_errors

F64 = torch.float64
# Noise of the data (standard deviations; the weights are their inverse squares).
POINT_NOISE = 0.02  # metres, per coordinate of a point observation
ODOMETRY_NOISE = (1.0, 0.03)  # per step: rotation (degrees) and translation (metres)
PLANE_NOISE = 0.003  # metres, along the normal
PLANES_PER_FRAME = 10


class PointToPlane(Term):
    """r = nᵀ(T X − p): a known world point X on a plane seen in frame i as (p, n).

    Args:
        pose_index: frame i of each instance, integer (K,).
        X: world points (K, 3); p: plane points (K, 3) and n: unit normals (K, 3), in frame i.
        weight: 1/σ² per instance (K,), optional; loss: a robust kernel, optional.
    """

    def __init__(self, pose_index: Tensor, X: Tensor, p: Tensor, n: Tensor, **kwargs) -> None:
        super().__init__(pose_index[:, None], {"X": X, "p": p, "n": n}, **kwargs)

    def residual(self, poses: Tensor, X: Tensor, p: Tensor, n: Tensor) -> Tensor:
        T = poses[..., 0, :, :]  # the one pose of each instance, T_i0
        TX = (T[..., :3, :3] @ X[..., None])[..., 0] + T[..., :3, 3]
        return ((TX - p) * n).sum(-1, keepdim=True)  # (..., 1)


def make_planes(scene: SyntheticScene, noise: float, seed: int) -> PointToPlane:
    """PLANES_PER_FRAME planes per frame: a world point X within a few metres of the sensor,
    a random normal n in the frame, and p = T_i0 X + (an offset along the plane) + noise·n."""
    g = torch.Generator().manual_seed(seed)
    T = scene.poses_gt[0]
    m, k = T.shape[0], PLANES_PER_FRAME
    frame = torch.arange(m).repeat_interleave(k)
    sensor = se3.inverse(T)[:, :3, 3][frame]  # sensor positions in the world
    X = sensor + 2.0 * torch.randn(m * k, 3, generator=g, dtype=F64)
    n = torch.randn(m * k, 3, generator=g, dtype=F64)
    n = n / n.norm(dim=-1, keepdim=True)
    offset = torch.randn(m * k, 3, generator=g, dtype=F64)
    offset = offset - (offset * n).sum(-1, keepdim=True) * n  # in the plane
    along = noise * PLANE_NOISE * torch.randn(m * k, 1, generator=g, dtype=F64)
    p = se3.act(T[frame], X) + offset + along * n
    weight = torch.full((m * k,), PLANE_NOISE**-2, dtype=F64)
    return PointToPlane(frame, X, p, n, weight=weight)


def build_problem(
    seed: int = 0, *, planes: bool = True, noise: float = 1.0
) -> tuple[SyntheticScene, PointMapProblem]:
    """The scene and its problem: point observations, odometry terms and (``planes``) the
    point-to-plane terms, initialized from the odometry. ``noise`` scales every noise of the
    data (0: exact data, whose solution is the ground truth); the weights stay 1/σ²."""
    scene = make_scene(8, 40, visible_fraction=0.4, noise_std=noise * POINT_NOISE, seed=seed)
    m = scene.poses_gt.shape[1]
    rot_deg, trans = (noise * s for s in ODOMETRY_NOISE)
    # T̂_(i+1)i from the odometry; its inverse is the measurement Z_(i,i+1) ≈ T_i0 T_(i+1)0⁻¹.
    odometry = odometry_relative_poses(
        scene.poses_gt, rotation_noise_deg=rot_deg, translation_noise=trans, seed=seed + 1
    )
    # Each step is off by exactly (θ, τ) in a random direction: σ² = θ²/3, τ²/3 per entry.
    theta, tau = math.radians(ODOMETRY_NOISE[0]), ODOMETRY_NOISE[1]
    sigma = torch.tensor([theta] * 3 + [tau] * 3, dtype=F64)
    information = torch.diag(3.0 / sigma**2).expand(m - 1, 6, 6)
    pairs = torch.stack((torch.arange(m - 1), torch.arange(1, m)), dim=-1)
    terms = [RelativePoseTerm(pairs, se3.inverse(odometry[0]), information=information)]
    if planes:
        terms.append(make_planes(scene, noise, seed + 2))
    poses = chain_relative_poses(odometry)  # T̂_00 = I: the gauge, held fixed
    points = average_points(
        poses,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        scene.num_points,
        valid=scene.valid,
    )
    problem = PointMapProblem(
        poses,
        points,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        valid=scene.valid,
        weights=torch.full(scene.valid.shape, POINT_NOISE**-2, dtype=F64),
        terms=terms,
    )
    return scene, problem


def pose_error(scene: SyntheticScene, problem: PointMapProblem) -> tuple[float, float]:
    """Largest rotation error (degrees) and sensor position error (metres) over the poses."""
    rotation, translation = pose_errors(problem.poses.detach(), scene.poses_gt)
    return float(rotation.max()), float(translation.max())


def main() -> None:
    runs = {
        name: build_problem(0, planes=planes)
        for name, planes in (("odometry only", False), ("odometry + planes", True))
    }
    scene, problem = runs["odometry + planes"]
    odometry, planes = problem.data.terms
    print(
        f"scene: {problem.num_poses} poses, {problem.num_points} points, "
        f"{int(problem.num_observations[0])} point observations; terms: "
        f"{odometry.num_instances} odometry, {planes.num_instances} point-to-plane {planes!r}"
    )
    rotation, translation = pose_error(scene, problem)
    print(f"odometry initialization: max pose error {rotation:.4f} deg, {translation:.5f} m")
    for name, (scene, problem) in runs.items():
        result = solve(problem)
        rotation, translation = pose_error(scene, problem)
        print(
            f"{name}: cost {float(result.initial_cost[0]):.6e} -> "
            f"{float(result.final_cost[0]):.6e}, {result.status[0].name} after "
            f"{int(result.iterations[0])} iterations, max pose error {rotation:.4f} deg, "
            f"{translation:.5f} m"
        )


if __name__ == "__main__":
    main()
