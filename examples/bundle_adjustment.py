"""Bundle adjustment with a user term that writes only its residual.

A pinhole camera with known intrinsics (fx, fy, cx, cy) observes world points X_j from poses
T_i0 (world → camera i, the problem's convention: X_c = R X + t with T_i0 = [R | t]). The
reprojection residual of the observation of point j in camera i is

    r_ij = u_ij − π(K (R X_j + t)),    π(x, y, z) = (x / z, y / z),

two entries in pixels. The term below writes only :meth:`ReprojectionTerm.residual`:
``torch.func.jacrev`` gives its blocks w.r.t. the right perturbation of the pose
(T ← T·Exp(δ), δ = (ω, v)) and the Euclidean increment of the point, and the solver
eliminates the points by the Schur complement (``linear_solver="schur"``) like the
ICP-SLAM point observations.

Monocular bundle adjustment has a 7-dof gauge (a similarity: rotation, translation, scale).
The first camera is held fixed (6 dof) and so is one surveyed point (which fixes the scale).

Run: ``python examples/bundle_adjustment.py``.
"""

from __future__ import annotations

import torch
from torch import Tensor

import torchslam
from torchslam.lie import se3


class ReprojectionTerm(torchslam.Term):
    """Pinhole reprojection r = u − π(K (R X + t)) of K observations, two entries each.

    Args:
        pose_index: observing camera i of each observation, integer (K,).
        point_index: observed world point j, integer (K,).
        pixels: observed pixels u = (column, row), (K, 2).
        intrinsics: (fx, fy, cx, cy) in pixels, known.
        weight: scalar weights (K,), 1/σ² for pixel noise σ; default 1.
    """

    def __init__(
        self,
        pose_index: Tensor,
        point_index: Tensor,
        pixels: Tensor,
        intrinsics: tuple[float, float, float, float],
        *,
        weight: Tensor | None = None,
    ) -> None:
        super().__init__(
            pose_index[:, None], {"pixels": pixels}, point_index=point_index, weight=weight
        )
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in intrinsics)

    def residual(self, poses: Tensor, points: Tensor, pixels: Tensor) -> Tensor:
        T = poses[..., 0, :, :]  # (..., 4, 4), world → camera
        Xc = (T[..., :3, :3] @ points[..., None])[..., 0] + T[..., :3, 3]
        u = self.fx * Xc[..., 0] / Xc[..., 2] + self.cx
        v = self.fy * Xc[..., 1] / Xc[..., 2] + self.cy
        return pixels - torch.stack((u, v), dim=-1)


INTRINSICS = (500.0, 500.0, 320.0, 240.0)


def make_scene(
    num_cameras: int = 5, num_points: int = 40, noise: float = 0.5, seed: int = 0
) -> dict[str, Tensor]:
    """A synthetic scene: cameras on an arc 6 m from a cloud of points, every point seen by
    every camera, pixels with Gaussian noise (σ = ``noise`` px); the initial guess perturbs
    the cameras (≈ 2°, 10 cm) and the points (10 cm). float64."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    points = torch.rand(num_points, 3, generator=g, dtype=f64) * 2 - 1  # in [-1, 1]³
    poses = []
    for i in range(num_cameras):
        angle = torch.tensor(0.15 * (i - (num_cameras - 1) / 2), dtype=f64)
        # Camera at (6 sin a, 0, −6 cos a) looking at the origin: its z axis points inward.
        R_cw = torch.tensor(
            [[angle.cos(), 0, angle.sin()], [0, 1, 0], [-angle.sin(), 0, angle.cos()]], dtype=f64
        )
        center = torch.stack((6 * angle.sin(), torch.zeros((), dtype=f64), -6 * angle.cos()))
        T = torch.eye(4, dtype=f64)
        T[:3, :3] = R_cw.T  # world → camera rotation
        T[:3, 3] = -R_cw.T @ center
        poses.append(T)
    poses = torch.stack(poses)
    fx, fy, cx, cy = INTRINSICS
    cam, pt = torch.meshgrid(torch.arange(num_cameras), torch.arange(num_points), indexing="ij")
    cam, pt = cam.reshape(-1), pt.reshape(-1)
    Xc = (poses[cam, :3, :3] @ points[pt, :, None])[..., 0] + poses[cam, :3, 3]
    pixels = torch.stack((fx * Xc[:, 0] / Xc[:, 2] + cx, fy * Xc[:, 1] / Xc[:, 2] + cy), -1)
    pixels = pixels + noise * torch.randn(pixels.shape, generator=g, dtype=f64)
    twist = torch.randn(num_cameras, 6, generator=g, dtype=f64)
    twist[:, :3] *= 0.035
    twist[:, 3:] *= 0.1
    twist[0] = 0  # the first camera is held fixed at its true pose
    initial_poses = poses @ se3.exp(twist)
    initial_points = points + 0.1 * torch.randn(points.shape, generator=g, dtype=f64)
    initial_points[0] = points[0]  # the surveyed point, held fixed
    return dict(
        poses=poses,
        points=points,
        pose_index=cam,
        point_index=pt,
        pixels=pixels,
        initial_poses=initial_poses,
        initial_points=initial_points,
    )


def build_problem(scene: dict[str, Tensor]) -> torchslam.PointMapProblem:
    """The bundle adjustment as a PointMapProblem without point observations: only the
    reprojection term; camera 0 and point 0 held fixed."""
    m, n = scene["initial_poses"].shape[0], scene["initial_points"].shape[0]
    fixed_poses = torch.zeros(1, m, dtype=torch.bool)
    fixed_poses[0, 0] = True
    fixed_points = torch.zeros(1, n, dtype=torch.bool)
    fixed_points[0, 0] = True
    term = ReprojectionTerm(scene["pose_index"], scene["point_index"], scene["pixels"], INTRINSICS)
    empty = torch.zeros(1, 0, dtype=torch.long)
    return torchslam.PointMapProblem(
        scene["initial_poses"][None],
        scene["initial_points"][None],
        empty,
        empty,
        torch.zeros(1, 0, 3, dtype=torch.float64),
        fixed_poses=fixed_poses,
        fixed_points=fixed_points,
        terms=[term],
    )


def main() -> None:
    scene = make_scene()
    problem = build_problem(scene)
    initial = float(problem.cost().detach())
    result = torchslam.solve(problem, torchslam.SolverConfig(linear_solver="schur"))
    K = scene["pixels"].shape[0]
    rms = (2 * float(result.final_cost[0]) / (2 * K)) ** 0.5
    error = (problem.points.detach()[0] - scene["points"]).norm(dim=-1).max()
    print(
        f"cost {initial:.1f} → {float(result.final_cost[0]):.3f} in {int(result.iterations[0])} "
        f"iterations ({result.status[0].name}); reprojection rms {rms:.3f} px; "
        f"max point error {float(error) * 1000:.1f} mm"
    )


if __name__ == "__main__":
    main()
