"""Bundle adjustment: a BAL problem as a :class:`torchslam.PointMapProblem`, solved, written back.

A BAL camera (:mod:`torchslam.io.bal`) is 9 values, angle-axis r, translation t (world →
camera: P = R(r) X + t) and the Snavely intrinsics (f, k1, k2). Here it is a **pose** T_i0 =
[R(r) | t] (the problem's convention, world → camera) plus an **intrinsics block** (f, k1,
k2) of the parameter group ``"intrinsics"`` (:mod:`torchslam.objective.parameters`); each
observation is an instance of :class:`torchslam.ReprojectionTerm` (``model="snavely"``),
whose residual predicted − observed pixels gives BAL's and Ceres' cost ½Σ‖r‖². The points are
eliminated by the Schur complement, the poses and intrinsics stay in the reduced system.

Like Ceres on BAL, nothing is held fixed: the 7-dof gauge of bundle adjustment (a similarity)
is left to the damping.

The term's instances are the file's observations in camera-major order (stable: by camera,
then as in the file): the per-camera sums of a linearization then read consecutive instances
(BAL files list them by point; 5% faster on Ladybug). The cost, the solution and the
BAL file :func:`bal_from_problem` writes do not depend on that order.
"""

from __future__ import annotations

import dataclasses

import torch

from torchslam import _checks
from torchslam.io.bal import BALProblem
from torchslam.lie import so3
from torchslam.objective.reprojection import ReprojectionTerm
from torchslam.problem import PointMapProblem
from torchslam.solver.config import SolverConfig

__all__ = ["BA_CONFIG", "bal_from_problem", "problem_from_bal"]

# Ceres' defaults for bundle adjustment (its solver_options: function_tolerance 1e-6,
# gradient_tolerance 1e-10, parameter_tolerance 1e-8, 50 iterations; LM; Schur; and, as
# Ceres, no step taken whose cost change is within the function tolerance), used by
# ``torchslam ba`` and the benchmark, so that both solvers stop by the same rules.
BA_CONFIG = SolverConfig(
    linear_solver="schur",
    reduced_solver="dense",
    function_tolerance=1e-6,
    gradient_tolerance=1e-10,
    parameter_tolerance=1e-8,
    max_iterations=50,
    take_negligible_steps=False,
)


def problem_from_bal(
    bal: BALProblem,
    *,
    intrinsics: str = "free",
    loss: object | None = None,
    dtype: torch.dtype = torch.float64,
) -> PointMapProblem:
    """The :class:`PointMapProblem` of a BAL problem (module doc), batch B = 1.

    Args:
        bal: the problem (:func:`torchslam.io.read_bal`).
        intrinsics: ``"free"`` (default: f, k1, k2 of every camera are variables, BAL's full
            problem) or ``"fixed"`` (held at the file's values: the group is still there,
            its blocks fixed).
        loss: robust kernel of :mod:`torchslam.losses` on s = ‖r‖² (pixels²), e.g.
            ``HuberLoss(1.0)``; default none.
        dtype: of the problem's tensors (float64 recommended).
    """
    fn = "problem_from_bal"
    if not isinstance(bal, BALProblem):
        raise TypeError(
            f"{fn}: argument 'bal' must be a torchslam.io.BALProblem (read_bal), got "
            f"{_checks.describe(bal)}"
        )
    if intrinsics not in ("free", "fixed"):
        raise ValueError(
            f"{fn}: argument 'intrinsics' must be 'free' or 'fixed', got {intrinsics!r}"
        )
    C = bal.cameras.shape[0]
    cameras = bal.cameras.to(dtype)
    poses = bal.poses.to(dtype)
    order = torch.argsort(bal.camera_index, stable=True)  # camera-major (module doc)
    camera_index = bal.camera_index[order]
    term = ReprojectionTerm(
        camera_index,
        bal.point_index[order],
        bal.observations[order].to(dtype),
        model="snavely",
        intrinsics_index=camera_index,
        loss=loss,
    )
    empty = torch.zeros(1, 0, dtype=torch.long)
    return PointMapProblem(
        poses[None],
        bal.points.to(dtype)[None],
        empty,
        empty,
        torch.zeros(1, 0, 3, dtype=dtype),
        fixed_poses=torch.zeros(1, C, dtype=torch.bool),
        terms=[term],
        parameters={"intrinsics": cameras[:, 6:9]},
        fixed_parameters={"intrinsics": torch.full((C,), intrinsics == "fixed")},
    )


def bal_from_problem(problem: PointMapProblem, bal: BALProblem, index: int = 0) -> BALProblem:
    """``bal`` with the cameras and points of problem ``index`` of ``problem`` (one built by
    :func:`problem_from_bal`): r = Log(R), t, (f, k1, k2), the points; same observations."""
    with torch.no_grad():
        T = problem.poses[index].to(bal.cameras.dtype)
        r = so3.log(T[:, :3, :3])
        cameras = torch.cat(
            (r, T[:, :3, 3], problem.parameter_blocks["intrinsics"][index].to(r.dtype)), -1
        )
        points = problem.points[index].detach().to(bal.points.dtype)
    return dataclasses.replace(bal, cameras=cameras.clone(), points=points.clone())
