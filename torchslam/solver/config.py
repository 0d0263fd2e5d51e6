"""Solver configuration: one frozen dataclass, one comment per field."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

__all__ = ["SolverConfig"]

_ALGORITHMS = ("levenberg_marquardt", "gauss_newton", "gradient_descent")
_DAMPINGS = ("marquardt", "levenberg")
_JACOBIANS = ("analytic", "jacrev")
_LINEAR_SOLVERS = ("schur", "dense")
_REDUCED_SOLVERS = ("auto", "dense", "sparse")
_ORDERINGS = ("mmd", "colamd", "natural")


@dataclass(frozen=True)
class SolverConfig:
    """Options of :func:`torchslam.solve`. Defaults suit float64 ICP-SLAM problems.

    Tolerances follow Ceres: the solve of a problem stops when its accepted step decreases
    the cost by less than ``function_tolerance`` relative to the cost, when the largest
    gradient entry falls below ``gradient_tolerance``, or when the step is shorter than
    ``parameter_tolerance`` · (‖x‖ + parameter_tolerance).
    """

    # "levenberg_marquardt", "gauss_newton" or "gradient_descent" (the seed's δ = −α Jᵀr).
    algorithm: Literal["levenberg_marquardt", "gauss_newton", "gradient_descent"] = (
        "levenberg_marquardt"
    )
    # LM damping matrix: "marquardt" λ·diag(H) (scale invariant) or "levenberg" λ·I.
    damping: Literal["marquardt", "levenberg"] = "marquardt"
    # Initial LM damping λ₀ (Ceres uses 1e4 as 1/initial_trust_region_radius; small λ₀ lets
    # well-conditioned problems take Gauss-Newton steps from the first iteration).
    initial_lambda: float = 1e-4
    # λ above which a problem gives up (no step decreases the cost): status DAMPING_LIMIT.
    max_lambda: float = 1e16
    # λ never goes below this (keeps the damped system positive definite in float64).
    min_lambda: float = 1e-16
    # Jacobian blocks: "analytic" (default) or "jacrev" (torch.func.jacrev; same iterates).
    jacobian: Literal["analytic", "jacrev"] = "analytic"
    # Linear solver: "schur" (eliminate points, Cholesky of the 6m × 6m pose system) or
    # "dense" (the full (6m + 3n)² system; small problems and cross-checks only).
    linear_solver: Literal["schur", "dense"] = "schur"
    # Factorization of the reduced 6m × 6m pose system of "schur": "dense" (batched
    # Cholesky, any device, differentiable), "sparse" (SciPy SuperLU with a fill-reducing
    # ordering, :mod:`torchslam.solver.sparse`; for hundreds to thousands of poses with local
    # co-visibility and relative-pose terms) or "auto": sparse when 6m > dense_max_variables
    # and the symbolic factorization of S's block pattern predicts far less work than dense
    # (linear.choose_reduced_solver).
    reduced_solver: Literal["auto", "dense", "sparse"] = "auto"
    # Largest reduced system 6m that "auto" always factors densely.
    dense_max_variables: int = 600
    # Fill-reducing ordering of the pose-block graph for "sparse".
    ordering: Literal["mmd", "colamd", "natural"] = "mmd"
    # Maximum number of iterations (linearizations) per solve.
    max_iterations: int = 100
    # Stop when |ΔF| ≤ function_tolerance · F after an accepted step.
    function_tolerance: float = 1e-10
    # Stop when max |∇F| ≤ gradient_tolerance.
    gradient_tolerance: float = 1e-12
    # Stop when ‖δ‖ ≤ parameter_tolerance · (‖x‖ + parameter_tolerance).
    parameter_tolerance: float = 1e-12
    # Gradient descent step size α (halved per problem after a step that increases the cost).
    step_size: float = 1e-3
    # Pairs of observations processed at once when forming the Schur complement (memory cap).
    schur_chunk_size: int = 1 << 20

    def __post_init__(self) -> None:
        _choice("algorithm", self.algorithm, _ALGORITHMS)
        _choice("damping", self.damping, _DAMPINGS)
        _choice("jacobian", self.jacobian, _JACOBIANS)
        _choice("linear_solver", self.linear_solver, _LINEAR_SOLVERS)
        _choice("reduced_solver", self.reduced_solver, _REDUCED_SOLVERS)
        _choice("ordering", self.ordering, _ORDERINGS)
        if (
            not isinstance(self.dense_max_variables, int)
            or isinstance(self.dense_max_variables, bool)
            or self.dense_max_variables < 0
        ):
            raise ValueError(
                "SolverConfig: 'dense_max_variables' must be an int ≥ 0, "
                f"got {self.dense_max_variables!r}"
            )
        if not isinstance(self.max_iterations, int) or self.max_iterations < 0:
            raise ValueError(
                f"SolverConfig: 'max_iterations' must be an int ≥ 0, got {self.max_iterations!r}"
            )
        for name in (
            "initial_lambda",
            "max_lambda",
            "min_lambda",
            "function_tolerance",
            "gradient_tolerance",
            "parameter_tolerance",
            "step_size",
        ):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not value >= 0:
                raise ValueError(f"SolverConfig: '{name}' must be a number ≥ 0, got {value!r}")
        if self.schur_chunk_size < 1:
            raise ValueError(
                f"SolverConfig: 'schur_chunk_size' must be ≥ 1, got {self.schur_chunk_size}"
            )


def _choice(name: str, value: object, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"SolverConfig: '{name}' must be one of {allowed}, got {value!r}")
