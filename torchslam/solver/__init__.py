"""The hand-written damped Gauss-Newton / Levenberg-Marquardt solver (see :mod:`.solve`)."""

from torchslam.solver.config import SolverConfig
from torchslam.solver.result import SolveResult, Status
from torchslam.solver.solve import solve, solve_tensors

__all__ = ["SolveResult", "SolverConfig", "Status", "solve", "solve_tensors"]
