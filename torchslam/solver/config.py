"""Solver configuration: one frozen dataclass, one comment per field."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Literal

__all__ = ["SolverConfig", "check_implicit_config", "check_int", "check_number"]

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
    # (plan.choose_reduced_solver).
    reduced_solver: Literal["auto", "dense", "sparse"] = "auto"
    # Largest reduced system 6m that "auto" always factors densely.
    dense_max_variables: int = 600
    # Fill-reducing ordering of the pose-block graph for "sparse".
    ordering: Literal["mmd", "colamd", "natural"] = "mmd"
    # Maximum number of iterations (linearizations) per solve.
    max_iterations: int = 100
    # Stop when |ΔF| ≤ function_tolerance · F after an accepted step.
    function_tolerance: float = 1e-10
    # Levenberg-Marquardt: with False, a problem whose step the model predicts to decrease
    # the cost by at most function_tolerance · F stops there (CONVERGED_FUNCTION) without
    # evaluating or taking that step, as Ceres takes no step whose cost change is below its
    # function tolerance (one linearization fewer per solve). True takes it: the iterate is
    # one step closer to the minimum, which derivatives of the solution want.
    take_negligible_steps: bool = True
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
        for name, low in (
            ("dense_max_variables", 0),
            ("max_iterations", 0),
            ("schur_chunk_size", 1),
        ):
            object.__setattr__(
                self, name, check_int("SolverConfig", name, getattr(self, name), low)
            )
        # (name, lowest value, whether the lowest value itself is allowed, whether +inf is).
        for name, low, closed, infinite in (
            ("initial_lambda", 0.0, False, False),
            ("max_lambda", 0.0, False, True),
            ("min_lambda", 0.0, True, False),
            ("function_tolerance", 0.0, True, False),
            ("gradient_tolerance", 0.0, True, False),
            ("parameter_tolerance", 0.0, True, False),
            ("step_size", 0.0, False, False),
        ):
            value = check_number("SolverConfig", name, getattr(self, name), low, closed, infinite)
            object.__setattr__(self, name, value)
        if not isinstance(self.take_negligible_steps, bool):
            raise ValueError(
                "SolverConfig: 'take_negligible_steps' must be a bool, got "
                f"{type(self.take_negligible_steps).__name__} {self.take_negligible_steps!r}"
            )
        if self.linear_solver == "dense" and self.reduced_solver == "sparse":
            raise ValueError(
                "SolverConfig: 'reduced_solver' = 'sparse' factors the reduced pose system of "
                "linear_solver='schur'; with linear_solver='dense' leave it 'auto' or 'dense'"
            )
        if self.min_lambda > self.max_lambda:
            raise ValueError(
                f"SolverConfig: 'min_lambda' ({self.min_lambda!r}) must not exceed 'max_lambda' "
                f"({self.max_lambda!r})"
            )


def _choice(name: str, value: object, allowed: tuple[str, ...]) -> None:
    if not isinstance(value, str):
        raise ValueError(
            f"SolverConfig: '{name}' must be one of {allowed}, got {type(value).__name__} {value!r}"
        )
    if value not in allowed:
        raise ValueError(f"SolverConfig: '{name}' must be one of {allowed}, got {value!r}")


def check_int(owner: str, name: str, value: object, low: int) -> int:
    """An integer option ≥ ``low``, as an int; bools, floats and other types are refused
    with a ValueError (the options' convention: any unusable value is a ValueError)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(
            f"{owner}: '{name}' must be an int ≥ {low}, got {type(value).__name__} {value!r}"
        )
    if value < low:
        raise ValueError(f"{owner}: '{name}' must be an int ≥ {low}, got {value!r}")
    return int(value)


def check_number(
    owner: str, name: str, value: object, low: float, closed: bool, infinite: bool = False
) -> float:
    """A real option > ``low`` (≥ when ``closed``), finite unless ``infinite`` allows +inf;
    NaN and non-numbers are refused (ValueError). Returns it as a float."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(
            f"{owner}: '{name}' must be a number, got {type(value).__name__} {value!r}"
        )
    try:
        value = float(value)
    except OverflowError:  # an int beyond the float range
        value = math.inf
    relation = "≥" if closed else ">"
    ok = value >= low if closed else value > low
    if not ok or math.isnan(value) or (math.isinf(value) and not infinite):
        finite = "a finite number" if not infinite else "a number"
        raise ValueError(f"{owner}: '{name}' must be {finite} {relation} {low:g}, got {value!r}")
    return value


_HESSIANS = ("exact", "gauss_newton")


def check_implicit_config(config: object) -> None:
    """Validate the fields of an ``ImplicitConfig`` (:mod:`.differentiable`) at construction:
    ``hessian`` one of ("exact", "gauss_newton"), ``tolerance`` a finite number ≥ 0,
    ``max_iterations`` an int ≥ 1 (ValueError otherwise)."""
    owner = "ImplicitConfig"
    hessian = getattr(config, "hessian", None)
    if not isinstance(hessian, str):
        raise ValueError(
            f"{owner}: 'hessian' must be one of {_HESSIANS}, got {type(hessian).__name__} "
            f"{hessian!r}"
        )
    if hessian not in _HESSIANS:
        raise ValueError(f"{owner}: 'hessian' must be one of {_HESSIANS}, got {hessian!r}")
    tolerance = check_number(owner, "tolerance", getattr(config, "tolerance", None), 0.0, True)
    object.__setattr__(config, "tolerance", tolerance)
    iterations = check_int(owner, "max_iterations", getattr(config, "max_iterations", None), 1)
    object.__setattr__(config, "max_iterations", iterations)
