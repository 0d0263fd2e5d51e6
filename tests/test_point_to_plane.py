"""examples/point_to_plane.py: a user term of < 30 lines, its jacrev blocks, its solves, its run.

The term r = nᵀ(T X − p) (T = T_i0, X a world point, (p, n) a plane in frame i) has the
blocks ∂r/∂δ = nᵀR [−[X]× | I] for T ← T·Exp(δ), δ = (ω, v): the jacrev blocks torchslam
uses for it are checked against these and against central differences on the manifold.
"""

from __future__ import annotations

import inspect
import math
import re
import runpy
from pathlib import Path

import pytest
import torch

from tests.helpers import load_example
from torchslam import SolverConfig, solve, validation
from torchslam.lie import se3, so3
from torchslam.objective.terms import term_jacobians, term_poses

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "point_to_plane.py"
F64 = torch.float64
FD_STEP = 1e-6
TIGHT = dict(function_tolerance=1e-15, gradient_tolerance=1e-12, parameter_tolerance=1e-15)


example = load_example("point_to_plane")
PointToPlane = example.PointToPlane


def test_term_class_is_short_and_only_a_residual():
    source = inspect.getsource(PointToPlane)
    assert len(source.splitlines()) < 30, source
    assert "jacobians" not in PointToPlane.__dict__  # no analytic blocks: jacrev is used
    assert PointToPlane.residual is not example.Term.residual


def _random_instances(g: torch.Generator, K: int = 32):
    """Poses with rotation angles from 0 to π − 1e-6 and translations from 0 to 1e4, world
    points from 1e-9 to 1e3 m, and planes (p, n) in each frame."""
    angles = torch.tensor([0.0, 1e-9, 1e-5, 0.5, 2.0, math.pi - 1e-3, math.pi - 1e-6, 1.0])
    axis = torch.randn(K, 3, generator=g, dtype=F64)
    omega = axis / axis.norm(dim=-1, keepdim=True) * angles.repeat(K // 8)[:, None].to(F64)
    t_scale = torch.tensor([0.0, 1e-9, 1.0, 1e4], dtype=F64).repeat(K // 4)
    v = torch.randn(K, 3, generator=g, dtype=F64) * t_scale[:, None]
    poses = se3.exp(torch.cat((omega, v), dim=-1))
    x_scale = torch.tensor([1e-9, 1e-3, 1.0, 1e3], dtype=F64).repeat_interleave(K // 4)
    X = torch.randn(K, 3, generator=g, dtype=F64) * x_scale[:, None]
    n = torch.randn(K, 3, generator=g, dtype=F64)
    n = n / n.norm(dim=-1, keepdim=True)
    p = torch.randn(K, 3, generator=g, dtype=F64)
    term = PointToPlane(torch.arange(K), X, p, n).bind(1, K, poses)
    return term, term_poses(term, poses[None]), poses, X, n


def test_jacrev_blocks_match_the_closed_form_and_central_differences(generator):
    term, P, poses, X, n = _random_instances(generator)
    r, J = term_jacobians(term, P, "analytic")  # falls back to jacrev: no analytic blocks
    r_jacrev, J_jacrev = term_jacobians(term, P, "jacrev")
    assert J.shape == (1, 32, 1, 1, 6)
    torch.testing.assert_close(J, J_jacrev, rtol=0, atol=0)
    torch.testing.assert_close(r, r_jacrev, rtol=0, atol=0)
    # Closed form: nᵀR [−[X]× | I].
    R = poses[:, :3, :3]
    nR = (n[:, None, :] @ R)[:, 0]
    closed = torch.cat(((nR[:, None, :] @ -so3.hat(X))[:, 0], nR), dim=-1)
    scale = 1 + X.norm(dim=-1)
    err = (J[0, :, 0, 0] - closed).abs().amax(-1)
    assert bool((err <= 1e-14 * scale).all()), float((err / scale).max())
    # Central differences, T ← T·Exp(±h e_q).
    columns = []
    with validation(False):
        for q in range(6):
            step = torch.zeros(6, dtype=F64)
            step[q] = FD_STEP
            plus = term.residual(P @ se3.exp(step), **term.constants)
            minus = term.residual(P @ se3.exp(-step), **term.constants)
            columns.append((plus - minus)[0, :, 0] / (2 * FD_STEP))
    fd = torch.stack(columns, dim=-1)
    # Round-off of the residual (|t| + |X| + |p| times ε) over the step, and the truncation.
    size = 1 + poses[:, :3, 3].norm(dim=-1) + X.norm(dim=-1) + term.constants["p"][0].norm(dim=-1)
    bound = 1e-6 * fd.norm(dim=-1) + 10 * (2.3e-16 * size / FD_STEP + FD_STEP**2 * scale)
    err = (J[0, :, 0, 0] - fd).norm(dim=-1)
    assert bool((err <= bound).all()), float((err / bound).max())


def test_noise_free_solve_recovers_the_ground_truth():
    """Exact data, a perturbed start: points + odometry + point-to-plane reach the ground
    truth to round-off, with both Schur (dense reduced) and the dense solver."""
    for config in (SolverConfig(**TIGHT), SolverConfig(linear_solver="dense", **TIGHT)):
        scene, problem = example.build_problem(3, planes=True, noise=0.0)
        g = torch.Generator().manual_seed(4)
        with torch.no_grad():
            xi = problem.pose_tangent
            T = se3.exp(xi[:, 1:]) @ se3.exp(
                0.1 * torch.randn(*xi[:, 1:].shape, generator=g, dtype=F64)
            )
            xi[:, 1:] = se3.log(T)
            problem.points.add_(0.1 * torch.randn(*problem.points.shape, generator=g, dtype=F64))
        result = solve(problem, config)
        assert result.converged == [True], result.summary()
        assert float(result.final_cost[0]) <= 1e-16 * float(result.initial_cost[0])
        torch.testing.assert_close(problem.poses.detach(), scene.poses_gt, rtol=0, atol=1e-10)
        torch.testing.assert_close(problem.points.detach(), scene.points_gt, rtol=0, atol=1e-10)


@pytest.mark.parametrize("seed", [0, 1])
def test_planes_reduce_the_pose_error(seed):
    errors = {}
    for planes in (False, True):
        scene, problem = example.build_problem(seed, planes=planes)
        result = solve(problem)
        assert result.converged == [True], result.summary()
        assert bool((result.cost_history.diff(dim=1) <= 0).all())
        errors[planes] = example.pose_error(scene, problem)
    (rot_without, trans_without), (rot_with, trans_with) = errors[False], errors[True]
    assert rot_with < rot_without and trans_with < trans_without, errors


NUMBER = r"([-+0-9.eE]+|nan|inf)"


def test_example_runs_as_a_script(capsys):
    runpy.run_path(str(EXAMPLE), run_name="__main__")
    out = capsys.readouterr().out
    assert "80 point-to-plane" in out, out
    parsed = {}
    for name in ("odometry only", "odometry + planes"):
        line = re.search(
            rf"^{re.escape(name)}: cost {NUMBER} -> {NUMBER}, (\w+) after (\d+) iterations, "
            rf"max pose error {NUMBER} deg, {NUMBER} m$",
            out,
            re.MULTILINE,
        )
        assert line is not None, out
        before, after, rotation, translation = (float(line.group(k)) for k in (1, 2, 5, 6))
        assert all(math.isfinite(x) for x in (before, after, rotation, translation)), line[0]
        assert 0 < after < before, line[0]
        assert line.group(3).startswith("CONVERGED"), line[0]
        parsed[name] = (rotation, translation)
    initial = re.search(rf"odometry initialization: max pose error {NUMBER} deg", out)
    assert initial is not None and float(initial.group(1)) > parsed["odometry only"][0]
    assert parsed["odometry + planes"][0] < parsed["odometry only"][0]
    assert parsed["odometry + planes"][1] < parsed["odometry only"][1]
