"""The hand-written damped Gauss-Newton / Levenberg-Marquardt solver: entry points (:mod:`.solve`),
the one loop (:mod:`.loop`), linearization (:mod:`.linearize`) and the planned linear solve
(:mod:`.plan`, :mod:`.sparse`)."""

from torchslam.solver.config import SolverConfig
from torchslam.solver.differentiable import ImplicitConfig, solve_differentiable
from torchslam.solver.result import IterationInfo, SolveResult, Status
from torchslam.solver.solve import solve, solve_tensors

__all__ = [
    "ImplicitConfig",
    "IterationInfo",
    "SolveResult",
    "SolverConfig",
    "Status",
    "solve",
    "solve_differentiable",
    "solve_tensors",
]
