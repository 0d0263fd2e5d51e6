"""Implicit backward of the TRAIN case: the exact Hessian's one factorization (now) against
the former conjugate-gradient backward (forced through its fallback) and the Gauss-Newton
Hessian, alternated, medians; and the accuracy of exact vs Gauss-Newton against central
differences of the whole solve on a small Huber problem with outliers.

    PYTHONPATH=$PWD .venv/bin/python experiments/implicit_backward.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics

import torch

import torchslam as ts
from torchslam import benchmark
from torchslam.solver import differentiable

_direct = differentiable._exact_solve


def _cg_only(plan, data, xi, X, v, config):
    ok = torch.zeros(xi.shape[0], dtype=torch.bool, device=xi.device)
    return (torch.zeros_like(v[0]), torch.zeros_like(v[1])), ok


def timing(repeats: int) -> None:
    scene, init, _ = benchmark.build("TRAIN")
    modes = {
        "exact, one factorization": ("exact", _direct),
        "exact, conjugate gradients (before)": ("exact", _cg_only),
        "gauss_newton": ("gauss_newton", _direct),
    }
    times = {k: [] for k in modes}
    for rep in range(repeats + 1):
        for name, (hessian, solver) in modes.items():
            differentiable._exact_solve = solver
            _, seconds = benchmark.training_step(scene, init, hessian=hessian)
            if rep:  # the first round warms up
                times[name].append(seconds)
    differentiable._exact_solve = _direct
    print(f"TRAIN backward (B={scene.batch_size}, 1 thread), median of {repeats}:")
    for name, t in times.items():
        print(f"  {name:38s} {statistics.median(t) * 1e3:7.1f} ms  (min {min(t) * 1e3:.1f})")


def accuracy() -> None:
    F64 = torch.float64
    scene = ts.data.make_scene(
        4, 12, batch_size=1, visible_fraction=0.75, outlier_fraction=0.05, seed=3
    )
    init = ts.initialization.initialize_scene(scene, method="odometry", seed=3)
    weights = 0.5 + torch.rand(scene.valid.shape, generator=torch.Generator().manual_seed(3))
    weights = weights.to(F64)
    converged = ts.SolverConfig(function_tolerance=1e-14, gradient_tolerance=1e-14)
    polish = ts.SolverConfig(
        algorithm="gauss_newton",
        max_iterations=12,
        function_tolerance=0.0,
        gradient_tolerance=0.0,
        parameter_tolerance=0.0,
    )
    problem = ts.PointMapProblem(
        init.poses,
        init.points,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        valid=scene.valid,
        weights=weights,
        loss=ts.HuberLoss(0.05),
    )

    def objective(xi, X):
        return (xi * torch.linspace(-1, 1, 6, dtype=F64)).sum() + (X**2).sum() + (xi**2).sum()

    obs = scene.observations.clone().requires_grad_(True)
    data = dataclasses.replace(problem.data, observations=obs)
    grads = {}
    for hessian in ("exact", "gauss_newton"):
        result = ts.solve_differentiable(
            problem.pose_tangent,
            problem.points,
            data,
            converged,
            implicit=ts.ImplicitConfig(hessian=hessian),
        )
        grads[hessian] = torch.autograd.grad(objective(result.pose_tangent, result.points), obs)[0]

    def value(o):
        d = dataclasses.replace(problem.data, observations=o)
        r = ts.solve_tensors(problem.pose_tangent, problem.points, d, converged)
        r = ts.solve_tensors(r.pose_tangent, r.points, d, polish)
        return float(objective(r.pose_tangent, r.points))

    h = 1e-3
    print("gradient w.r.t. observations vs central differences (h = 1e-3, 4-point):")
    print("  index        finite diff.      exact (rel. err)        gauss_newton (rel. err)")
    for index in [(0, 5, 0), (0, 17, 2), (0, 23, 1), (0, 30, 0)]:
        f = {}
        for k in (-2, -1, 1, 2):
            o = scene.observations.clone()
            o[index] += k * h
            f[k] = value(o)
        fd = (8 * (f[1] - f[-1]) - (f[2] - f[-2])) / (12 * h)
        e, g = float(grads["exact"][index]), float(grads["gauss_newton"][index])
        print(
            f"  {index!s:12s} {fd:+.9f}   {e:+.9f} ({abs(e - fd) / abs(fd):.1e})   "
            f"{g:+.9f} ({abs(g - fd) / abs(fd):.1e})"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    accuracy()
    timing(args.repeats)


if __name__ == "__main__":
    main()
