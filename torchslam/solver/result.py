"""What a solve returns: per-problem status, reason, costs and histories."""

from __future__ import annotations

import enum
import warnings
from dataclasses import dataclass, field

from torch import Tensor

from torchslam._checks import validation
from torchslam.lie import se3

__all__ = ["IterationInfo", "SolveResult", "Status"]


class Status(enum.IntEnum):
    """Why the solve of one problem stopped (or that it is still running)."""

    RUNNING = 0
    CONVERGED_FUNCTION = 1
    CONVERGED_GRADIENT = 2
    CONVERGED_PARAMETER = 3
    MAX_ITERATIONS = 4
    DAMPING_LIMIT = 5
    LINEAR_SOLVE_FAILED = 6
    NON_FINITE = 7

    @property
    def converged(self) -> bool:
        return self in (
            Status.CONVERGED_FUNCTION,
            Status.CONVERGED_GRADIENT,
            Status.CONVERGED_PARAMETER,
        )


REASONS = {
    Status.RUNNING: "still running",
    Status.CONVERGED_FUNCTION: "converged: relative cost decrease below function_tolerance",
    Status.CONVERGED_GRADIENT: "converged: max |gradient| below gradient_tolerance",
    Status.CONVERGED_PARAMETER: "converged: step norm below parameter_tolerance",
    Status.MAX_ITERATIONS: "not converged: reached max_iterations",
    Status.DAMPING_LIMIT: "not converged: damping λ exceeded max_lambda without a cost decrease",
    Status.LINEAR_SOLVE_FAILED: "not converged: normal equations not positive definite "
    "(Gauss-Newton has no damping to fall back on; use Levenberg-Marquardt)",
    Status.NON_FINITE: "not converged: cost or step became non-finite",
}


@dataclass
class SolveResult:
    """Outcome of a batched solve; every per-problem field has leading dim B."""

    # Optimized pose tangents ξ = (ω, v), (B, m, 6).
    pose_tangent: Tensor
    # Optimized world points, (B, n, 3).
    points: Tensor
    # Why each problem stopped.
    status: list[Status]
    # Iterations (linearizations) used per problem, long (B,).
    iterations: Tensor
    # Cost ½ Σ ρ(s) at the start, (B,).
    initial_cost: Tensor
    # Cost at the end, (B,).
    final_cost: Tensor
    # Cost after each iteration, (B, K + 1) with K = max iterations run; entry 0 is the
    # initial cost, entries after a problem stopped repeat its final cost.
    cost_history: Tensor
    # Damping λ after each iteration, (B, K + 1) (zeros for Gauss-Newton, α for descent).
    lambda_history: Tensor
    # Max |gradient| at the final linearization, (B,).
    gradient_norm: Tensor
    # Wall-clock seconds of the whole solve.
    time_seconds: float
    # Norm of the step tried in each iteration (accepted or not), (B, K); zero after a
    # problem stopped.
    step_norm_history: Tensor | None = None
    # Seconds of the solve spent linearizing (residuals, Jacobians, blocks) and in the
    # linear solves (assembly, factorization, back-substitution).
    linearize_seconds: float = 0.0
    linear_solve_seconds: float = 0.0
    # Linearizations (Jacobian evaluations) per problem, long (B,): the start and every
    # evaluated candidate step (one fewer than iterations + 1 where the last step was not
    # evaluated: SolverConfig.take_negligible_steps).
    linearizations: Tensor | None = None
    # Optimized parameter blocks by group, {name: (B, q, d)} (empty without parameter blocks).
    parameters: dict[str, Tensor] = field(default_factory=dict)

    @property
    def poses(self) -> Tensor:
        """Optimized poses T_i0 = Exp(ξ_i), (B, m, 4, 4)."""
        with validation(False):
            return se3.exp(self.pose_tangent, form="fast")

    @property
    def reason(self) -> list[str]:
        """A sentence per problem saying why it stopped."""
        return [REASONS[s] for s in self.status]

    @property
    def converged(self) -> list[bool]:
        return [s.converged for s in self.status]

    def summary(self) -> str:
        lines = []
        for b, s in enumerate(self.status):
            lines.append(
                f"problem {b}: {s.name} after {int(self.iterations[b])} iterations, cost "
                f"{float(self.initial_cost[b]):.6g} -> {float(self.final_cost[b]):.6g} "
                f"({REASONS[s]})"
            )
        return "\n".join(lines)


# Keys of the dict that callbacks received before IterationInfo was a dataclass.
_LEGACY_KEYS = {"lambda": "damping"}


@dataclass(frozen=True)
class IterationInfo:
    """Progress after one iteration, passed to a solve's ``callback`` (B problems)."""

    # Iterations run so far (1 after the first).
    iteration: int
    # Cost ½ Σ ρ(s) at the kept estimate, (B,).
    cost: Tensor
    # Damping λ for the next iteration (0 for Gauss-Newton, α for descent), (B,).
    damping: Tensor
    # Norm of the step tried, (B,); whether it was accepted, bool (B,).
    step_norm: Tensor
    accepted: Tensor
    # Problems still running after this iteration, bool (B,).
    active: Tensor
    # Max |gradient| at the kept estimate, (B,).
    gradient_norm: Tensor
    # Seconds since the solve started.
    seconds: float

    def __getitem__(self, key: str):
        """Deprecated dict access (``info["cost"]``, ``info["lambda"]``): use attributes."""
        warnings.warn(
            f"IterationInfo[{key!r}] is deprecated and will be removed in the next release; "
            f"use the attribute info.{_LEGACY_KEYS.get(key, key)}",
            DeprecationWarning,
            stacklevel=2,
        )
        try:
            return getattr(self, _LEGACY_KEYS.get(key, key))
        except AttributeError:
            raise KeyError(key) from None
