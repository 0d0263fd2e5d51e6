"""The solve entry points: argument checks, then the one loop of :mod:`.loop`.

:func:`solve` solves a :class:`PointMapProblem` in place, :func:`solve_tensors` B problems
given as tensors; both run without gradients, in ``torch.inference_mode`` (cheaper per tensor
operation than ``torch.no_grad``; the tensors they return, and those a callback receives, are
normal tensors: :mod:`torchslam._inference`). :func:`torchslam.solve_differentiable` runs the
same loop with gradients. The path of one call: problem → linearize (:mod:`.linearize`) →
plan.factorize (:mod:`.plan`) → solve → retract (:mod:`.loop`).
"""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Callable, Mapping

import torch
from torch import Tensor

from torchslam import _checks, _inference, losses
from torchslam._threads import threads_for
from torchslam.objective.data import PointMapData, check_data_values
from torchslam.objective.parameters import pack_values
from torchslam.problem import PointMapProblem
from torchslam.solver import loop
from torchslam.solver.config import SolverConfig
from torchslam.solver.result import IterationInfo, SolveResult

__all__ = ["IterationInfo", "check_solve_inputs", "solve", "solve_tensors"]

logger = logging.getLogger("torchslam.solver")


def check_solve_inputs(
    fn: str,
    pose_tangent: object,
    points: object,
    data: object,
    config: object = None,
) -> SolverConfig:
    """Validate the arguments of a solve entry point; returns the config (default filled in).

    Checks (TypeError for types and dtypes, ValueError for shapes and values, each naming
    ``fn`` and the argument): ``data`` a :class:`PointMapData` (not the problem itself),
    ``pose_tangent`` (B, m, 6) and ``points`` (B, n, 3) matching it, in its dtype and device,
    ``config`` None or a :class:`SolverConfig`. When value checks are active
    (:func:`torchslam.validation`): finite starting values, and once per ``data`` its indices,
    observations and weights at the valid slots.
    """
    if isinstance(data, PointMapProblem) or isinstance(pose_tangent, PointMapProblem):
        raise TypeError(
            f"{fn}: got a PointMapProblem where tensors and its data are expected; pass "
            "(problem.pose_tangent, problem.points, problem.data), or call "
            "torchslam.solve(problem)"
        )
    if not isinstance(data, PointMapData):
        raise TypeError(
            f"{fn}: argument 'data' must be a torchslam.PointMapData (e.g. problem.data), got "
            f"{_checks.describe(data)}"
        )
    B, m, n = data.valid.shape[0], data.num_poses, data.num_points
    _checks.check_batched(
        fn, "pose_tangent", pose_tangent, ("B", "m"), (6,), (B, m), against="'data'"
    )
    _checks.check_batched(fn, "points", points, ("B", "n"), (3,), (B, n), against="'data'")
    _checks.check_same_kind(
        fn, observations=data.observations, pose_tangent=pose_tangent, points=points
    )
    if m == 0:
        raise ValueError(f"{fn}: 'data' has no poses (m = 0); there is nothing to solve")
    if config is None:
        config = SolverConfig()
    elif not isinstance(config, SolverConfig):
        raise TypeError(
            f"{fn}: argument 'config' must be a torchslam.SolverConfig or None, got "
            f"{_checks.describe(config)}; e.g. SolverConfig(algorithm='gauss_newton')"
        )
    if _checks.value_checks_active():
        _checks.check_finite(fn, "pose_tangent", pose_tangent)
        _checks.check_finite(fn, "points", points)
        check_data_values(fn, data)
        losses.check_loss_values(fn, data.loss, "data.loss")
        for k, term in enumerate(data.terms):
            losses.check_loss_values(fn, term.loss, f"data.terms[{k}].loss")
    return config


def _check_callback(fn: str, callback: object) -> None:
    if callback is not None and not callable(callback):
        raise TypeError(
            f"{fn}: argument 'callback' must be callable or None, got {_checks.describe(callback)}"
        )


def solve_tensors(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig | None = None,
    callback: Callable[[IterationInfo], None] | None = None,
    parameters: Mapping[str, Tensor] | None = None,
) -> SolveResult:
    """Solve B problems given as tensors; returns new tensors (the inputs are not modified).

    Runs without gradients, in ``torch.inference_mode``; the returned tensors are normal ones
    (:func:`torchslam.solve_differentiable` runs the same loop with gradients).

    Args:
        pose_tangent: initial ξ = (ω, v), (B, m, 6).
        points: initial world points, (B, n, 3).
        data: observations and structure (:class:`torchslam.problem.PointMapData`).
        config: solver options; default :class:`SolverConfig()`.
        callback: called after every iteration with an :class:`IterationInfo`.
        parameters: initial parameter blocks {group: (B, q, d)}, every group of ``data``
            (:mod:`torchslam.objective.parameters`); the result's ``parameters`` holds the
            optimized ones.
    """
    config = check_solve_inputs("solve_tensors", pose_tangent, points, data, config)
    _check_callback("solve_tensors", callback)
    slots = pack_values("solve_tensors", data.parameters, parameters, pose_tangent)
    return _solve_tensors(pose_tangent, points, data, config, callback, slots)


def _solve_tensors(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig,
    callback: Callable[[IterationInfo], None] | None,
    slots: Tensor | None = None,
) -> SolveResult:
    """:func:`solve_tensors` after its argument checks (``slots``: the parameter blocks'
    packed values (B, S, 6), or None); all of it under the thread policy of
    :mod:`torchslam._threads` (the loop's, extended to the result's copies)."""
    with threads_for(data):
        return _solve_tensors_threaded(pose_tangent, points, data, config, callback, slots)


def _solve_tensors_threaded(pose_tangent, points, data, config, callback, slots) -> SolveResult:
    start = time.perf_counter()
    count = [0]

    def report(state: loop.State) -> None:
        count[0] += 1
        if callback is None and not logger.isEnabledFor(logging.INFO):
            return
        # The callback runs outside the loop's inference mode (without gradients, as before
        # it): what it keeps or computes are normal tensors.
        with _inference.outside():
            info = _inference.plain(loop.iteration_info(state, count[0], start))
            if callback is not None:
                callback(info)
        logger.info(
            "iter %3d  cost %.6e  lambda %.2e  |step| %.2e  accepted %d",
            count[0],
            float(state.cost.sum()),
            float(state.lam.max()),
            float(state.step_norm.max()),
            int(state.last_accepted.sum()),
        )

    # Inference mode: fewer costs per tensor operation than no_grad; nothing made in it leaves
    # (the result's tensors are cloned, the callback's too).
    with torch.inference_mode(), _checks.validation(False):
        state, history = loop.run(
            pose_tangent.detach().clone(),
            points.detach().clone(),
            data,
            config,
            report,
            False,
            parameters=None if slots is None else slots.clone(),
        )
    with torch.no_grad():
        return _inference.plain(loop.result(state, history, start, data.parameters))


def solve(
    problem: PointMapProblem,
    config: SolverConfig | None = None,
    callback: Callable[[IterationInfo], None] | None = None,
) -> SolveResult:
    """Solve a :class:`PointMapProblem` in place: its parameters are set to the solution.

    Args:
        problem: the batched problem; its current parameters are the initial guess.
        config: solver options (algorithm, damping, tolerances, Jacobian mode, linear solver).
        callback: called after each iteration with progress (see :data:`IterationInfo`).

    Returns:
        A :class:`SolveResult` with per-problem status, reason, iterations, costs and history.
    """
    fn = "solve"
    if isinstance(problem, PointMapData):
        raise TypeError(
            f"{fn}: argument 'problem' must be a torchslam.PointMapProblem, got a PointMapData; "
            "solve tensors with torchslam.solve_tensors(pose_tangent, points, data)"
        )
    if not isinstance(problem, PointMapProblem):
        raise TypeError(
            f"{fn}: argument 'problem' must be a torchslam.PointMapProblem, got "
            f"{_checks.describe(problem)}"
        )
    config = check_solve_inputs(fn, problem.pose_tangent, problem.points, problem.data, config)
    _check_callback(fn, callback)
    blocks = dict(problem.parameter_blocks.items())
    slots = pack_values(fn, problem.data.parameters, blocks, problem.pose_tangent)
    result = _solve_tensors(
        problem.pose_tangent, problem.points, problem.data, config, callback, slots
    )
    with torch.no_grad():
        problem.pose_tangent.copy_(result.pose_tangent)
        problem.points.copy_(result.points)
        for name, value in result.parameters.items():
            problem.parameter_blocks[name].copy_(value)
    wanted = _gradient_wanted(problem.data)
    if wanted is not None:
        # The result's tensors stay plain (they warm-start a differentiable solve, convert to
        # numpy, feed covariances); the hint comes now, before a backward would fail with
        # torch's generic "does not require grad".
        warnings.warn(
            f"solve: {wanted} requires grad, but solve iterates on detached values: its result "
            "carries no gradient. To backpropagate through the solve use torchslam."
            "solve_differentiable(problem.pose_tangent, problem.points, problem.data); to "
            "silence this, solve under torch.no_grad()",
            UserWarning,
            stacklevel=2,
        )
    return result


def _gradient_wanted(data: PointMapData) -> str | None:
    """The name of a constant of ``data`` that requires grad (observations, weights,
    information, a term's tensors) when grad mode is on: the caller may expect gradients of
    the solution with respect to it; None otherwise."""
    if not torch.is_grad_enabled():
        return None
    constants = {
        "data.observations": data.observations,
        "data.weights": data.weights,
        "data.information": data.information,
    }
    for k, term in enumerate(data.terms):
        constants.update({f"data.terms[{k}] {n!r}": t for n, t in term.tensors().items()})
    return next((n for n, t in constants.items() if t is not None and t.requires_grad), None)
