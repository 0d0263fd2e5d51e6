"""Jacobians of the ICP-SLAM residual (issue 3): analytic, jacrev, central differences, dense.

Conventions: r = X_ij − T_i0 X_j; the pose is stored as ξ = (ω, v) (rotation first) and
perturbed on the right, T_i0 ← T_i0 · Exp(δ); points are perturbed in R³, X ← X + δX. The
blocks are ∂r/∂δ (3 × 6) and ∂r/∂X (3 × 3) at δ = 0.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from torch import Tensor

from tests.helpers import (
    HARD_ANGLES,
    TOL,
    central_difference,
    twists_with_hard_inputs,
)
from torchslam import jacobians
from torchslam.data.synthetic import make_scene
from torchslam.lie import se3, so3
from torchslam.objective import data as data_module
from torchslam.problem import PointMapProblem

F64 = torch.float64
# Magnitudes of the hard points, from tiny to huge (metres).
POINT_SCALES = (1e-9, 1e-3, 1.0, 1e4)
# Central-difference step, and the relative accuracy asked of analytic vs jacrev (issue 3).
FD_STEP = 1e-6
EXACT_RTOL = 1e-10


# --------------------------------------------------------------------------- problems


def _quiet(build):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every test problem here is well posed
        return build()


def _random_problem(
    seed: int,
    batch_size: int = 3,
    num_poses: int = 8,
    num_points: int = 40,
    *,
    trajectory: str = "loop",
    dtype=F64,
    **kwargs,
) -> PointMapProblem:
    """A synthetic problem with poses and points moved off the ground truth."""
    scene = make_scene(
        num_poses,
        num_points,
        batch_size=batch_size,
        trajectory=trajectory,
        rotation_per_frame_deg=30.0,
        visible_fraction=0.75,
        seed=seed,
    )
    g = torch.Generator().manual_seed(seed + 1000)
    B, m, n = batch_size, num_poses, num_points
    poses = scene.poses_gt @ se3.exp(0.3 * torch.randn(B, m, 6, generator=g, dtype=F64))
    points = scene.points_gt + 0.3 * torch.randn(B, n, 3, generator=g, dtype=F64)
    valid = kwargs.pop("valid", scene.valid)
    return _quiet(
        lambda: PointMapProblem(
            poses.to(dtype),
            points.to(dtype),
            scene.pose_index,
            scene.point_index,
            scene.observations.to(dtype),
            valid=valid,
            **kwargs,
        )
    )


def _hard_problem(generator: torch.Generator) -> PointMapProblem:
    """B = 1: 72 poses over every hard angle × hard translation (HARD_ANGLES, from 0 through
    1e-12 … π − 1e-6 to π; translations 0, 1e-9, 1, 1e4), each seeing 8 points of magnitude
    1e-9, 1e-3, 1 and 1e4 (two each), so E = 576."""
    xi = twists_with_hard_inputs(generator)
    m = xi.shape[0]
    assert m == 2 * len(HARD_ANGLES) * 4
    direction = torch.randn(2 * len(POINT_SCALES), 3, generator=generator, dtype=F64)
    direction = direction / direction.norm(dim=-1, keepdim=True)
    scale = torch.tensor(POINT_SCALES, dtype=F64).repeat_interleave(2)
    points = direction * scale[:, None]
    n = points.shape[0]
    poses = se3.exp(xi)
    pose_index = torch.arange(m).repeat_interleave(n)
    point_index = torch.arange(n).repeat(m)
    observations = se3.act(poses[pose_index], points[point_index])
    observations = observations + 0.01 * torch.randn(m * n, 3, generator=generator, dtype=F64)
    return _quiet(
        lambda: PointMapProblem(
            poses[None], points[None], pose_index[None], point_index[None], observations[None]
        )
    )


def _problem_with_padding_weights_and_fixed(seed: int) -> PointMapProblem:
    """B = 2, m = 4, n = 10 with 3×3 information, padding in problem 1, and point 2 of
    problem 0 held fixed (pose 0 is the default gauge)."""
    scene = make_scene(4, 10, batch_size=2, visible_fraction=0.75, seed=seed)
    valid = scene.valid.clone()
    # Problem 1 loses one observation of each pose, of a point that keeps another view.
    views = torch.bincount(scene.point_index[1][valid[1]], minlength=10)
    for i in range(4):
        for e in (scene.pose_index[1] == i).nonzero()[:, 0].tolist():
            j = int(scene.point_index[1, e])
            if views[j] >= 2:
                valid[1, e] = False
                views[j] -= 1
                break
    g = torch.Generator().manual_seed(seed + 1)
    A = torch.randn(*valid.shape, 3, 3, generator=g, dtype=F64)
    information = A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=F64)
    fixed_points = torch.zeros(2, 10, dtype=torch.bool)
    fixed_points[0, 2] = True
    poses = scene.poses_gt @ se3.exp(0.2 * torch.randn(2, 4, 6, generator=g, dtype=F64))
    points = scene.points_gt + 0.2 * torch.randn(2, 10, 3, generator=g, dtype=F64)
    return _quiet(
        lambda: PointMapProblem(
            poses,
            points,
            scene.pose_index,
            scene.point_index,
            scene.observations,
            valid=valid,
            weights=information,
            fixed_points=fixed_points,
        )
    )


# --------------------------------------------------------------------------- comparisons


def _groups(J_xi: Tensor, J_point: Tensor) -> dict[str, Tensor]:
    """Column groups of the blocks: ∂r/∂δω, ∂r/∂δv (pose) and ∂r/∂X, each (..., 3, 3)."""
    J_xi, J_point = J_xi.detach(), J_point.detach()
    return {"omega": J_xi[..., :3], "v": J_xi[..., 3:], "point": J_point}


def _assert_blocks_close(actual, expected, *, rtol: float, atol: Tensor | float = 0.0):
    """Per observation and per column group (ω, v, X): max|a − e| ≤ rtol · max|e| + atol.

    Relative per group, so a tiny point (∂r/∂δω = R [X]× ~ 1e-9) is held to the same
    relative accuracy as a huge one.
    """
    for name, a in _groups(*actual).items():
        e = _groups(*expected)[name]
        err = (a - e).abs().amax(dim=(-1, -2))
        bound = rtol * e.abs().amax(dim=(-1, -2)) + atol
        worst = int((err - bound).argmax())
        assert bool((err <= bound).all()), (
            f"{name} columns: error {float(err.flatten()[worst]):.3g} > bound "
            f"{float(bound.flatten()[worst]):.3g} at flat observation {worst}"
        )


def _magnitude(problem: PointMapProblem) -> Tensor:
    """M_e = 1 + |X_j| + |t_i| + |X_ij| per observation (B, E): the size of what the
    residual adds up, which sets the round-off of a central difference."""
    data = problem.data
    T = problem.poses.detach()
    X = problem.points.detach()
    b = torch.arange(T.shape[0])[:, None]
    X_e = X[b, data.point_index]
    t_e = T[b, data.pose_index][..., :3, 3]
    return 1 + X_e.norm(dim=-1) + t_e.norm(dim=-1) + data.observations.norm(dim=-1)


def _fd_atol(problem: PointMapProblem) -> Tensor:
    """Natural accuracy of a central difference with step h: round-off ε·M/h plus the
    truncation h²·M (third derivative of R Exp(δ) X is O(|X|)), with a safety factor 10."""
    M = _magnitude(problem)
    eps = torch.finfo(F64).eps
    return 10 * (eps * M / FD_STEP + FD_STEP**2 * M)


def _cd_blocks(problem: PointMapProblem) -> tuple[Tensor, Tensor]:
    data = problem.data
    xi_e = data_module.gather_poses(problem.pose_tangent.detach(), data)
    X_e = data_module.gather_points(problem.points.detach(), data)
    return jacobians.central_difference_blocks(xi_e, X_e, data.observations, eps=FD_STEP)


# --------------------------------------------------------------------------- block agreement


@pytest.mark.parametrize("trajectory", ["loop", "random_walk"])
def test_analytic_equals_jacrev_on_random_problems(trajectory):
    problem = _random_problem(seed=1, trajectory=trajectory)
    analytic = problem.jacobian_blocks("analytic")
    autodiff = problem.jacobian_blocks("jacrev")
    B, E = problem.data.pose_index.shape
    assert analytic[0].shape == autodiff[0].shape == (B, E, 3, 6)
    assert analytic[1].shape == autodiff[1].shape == (B, E, 3, 3)
    _assert_blocks_close(analytic, autodiff, rtol=EXACT_RTOL)


def test_analytic_equals_jacrev_on_hard_inputs(generator):
    problem = _hard_problem(generator)
    _assert_blocks_close(
        problem.jacobian_blocks("analytic"), problem.jacobian_blocks("jacrev"), rtol=EXACT_RTOL
    )


def test_analytic_blocks_match_central_differences_on_random_problems():
    problem = _random_problem(seed=2)
    atol = _fd_atol(problem)
    analytic = problem.jacobian_blocks("analytic")
    _assert_blocks_close(analytic, _cd_blocks(problem), rtol=0, atol=atol)
    # The tolerance is meaningful: a sign flip of the rotation columns is caught.
    flipped = (torch.cat((-analytic[0][..., :3], analytic[0][..., 3:]), -1), analytic[1])
    with pytest.raises(AssertionError):
        _assert_blocks_close(flipped, _cd_blocks(problem), rtol=0, atol=atol)


def test_analytic_blocks_match_central_differences_on_hard_inputs(generator):
    problem = _hard_problem(generator)
    analytic = problem.jacobian_blocks("analytic")
    _assert_blocks_close(analytic, _cd_blocks(problem), rtol=0, atol=_fd_atol(problem))


def test_blocks_by_hand_at_the_identity():
    """R = I, X = (1, 2, 3): ∂r/∂δ = [[X]× | −I], ∂r/∂X = −I (right perturbation, (ω, v))."""
    R = torch.eye(3, dtype=F64)
    X = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    J_xi, J_point = jacobians.analytic_blocks(R, X)
    X_hat = torch.tensor([[0.0, -3.0, 2.0], [3.0, 0.0, -1.0], [-2.0, 1.0, 0.0]], dtype=F64)
    assert torch.equal(J_xi, torch.cat((X_hat, -torch.eye(3, dtype=F64)), dim=-1))
    assert torch.equal(J_point, -torch.eye(3, dtype=F64))
    xi = torch.zeros(6, dtype=F64)
    J_xi_rev, J_point_rev = jacobians.jacrev_blocks(xi, X, torch.zeros(3, dtype=F64))
    torch.testing.assert_close(J_xi_rev, J_xi, atol=1e-15, rtol=0)
    torch.testing.assert_close(J_point_rev, J_point, atol=1e-15, rtol=0)


def test_blocks_are_right_perturbation_not_left(generator):
    """At a rotated, translated pose the right and left perturbation Jacobians differ by the
    adjoint: J_right = J_left · Ad(T). The analytic block must be the right one."""
    xi = torch.tensor([0.3, -0.5, 0.7, 1.0, 2.0, -3.0], dtype=F64)
    T = se3.exp(xi)
    X = torch.randn(3, generator=generator, dtype=F64)
    J_right, _ = jacobians.analytic_blocks(T[:3, :3], X)

    def left(delta):
        return -se3.act(se3.exp(delta) @ T, X)

    J_left = central_difference(left, torch.zeros(6, dtype=F64))
    torch.testing.assert_close(J_right, J_left @ se3.adjoint(T), atol=1e-8, rtol=0)
    assert float((J_right - J_left).abs().max()) > 0.1  # they really differ here


def test_first_order_expansion_on_the_manifold(generator):
    """r(T·Exp(δ), X + dX) = r(T, X) + J_xi δ + J_X dX + O(|δ|²), going through the module's
    storage (ξ ← Log(Exp(ξ)·Exp(δ))) as the solver does. The remainder is bounded by
    ½|δω|²|X| + ½|δω||δv| + |δω||dX| (second-order terms of R Exp(δ)(X + dX))."""
    for problem in (_random_problem(seed=3), _hard_problem(generator)):
        data = problem.data
        B, m, n = problem.batch_size, problem.num_poses, problem.num_points
        h = 1e-4
        delta = h * torch.randn(B, m, 6, generator=generator, dtype=F64)
        dX = h * torch.randn(B, n, 3, generator=generator, dtype=F64)
        r0 = problem.raw_residuals().detach()
        J_xi, J_point = problem.jacobian_blocks()
        delta_e = data_module.gather_poses(delta, data)
        dX_e = data_module.gather_points(dX, data)
        X_e = data_module.gather_points(problem.points.detach(), data)
        linear = (J_xi @ delta_e[..., None] + J_point @ dX_e[..., None])[..., 0]
        with torch.no_grad():
            problem.pose_tangent.copy_(se3.log(problem.poses @ se3.exp(delta)))
            problem.points.add_(dX)
        r1 = problem.raw_residuals().detach()
        remainder = (r1 - r0 - linear).norm(dim=-1)
        d_omega, d_v = delta_e[..., :3].norm(dim=-1), delta_e[..., 3:].norm(dim=-1)
        bound = d_omega * (
            0.5 * d_omega * X_e.norm(dim=-1) + 0.5 * d_v + dX_e.norm(dim=-1)
        ) * 1.01 + 100 * torch.finfo(F64).eps * _magnitude(problem)
        assert bool((remainder <= bound).all())
        assert bool((linear.norm(dim=-1) > 10 * bound).any())  # the linear term is not noise


@pytest.mark.parametrize("mode", ["analytic", "jacrev"])
def test_pose_block_is_point_block_times_generator(mode, generator):
    """J_pose = J_point · [−[X]× | I] (the solver relies on the shared factor −R)."""
    for problem in (_random_problem(seed=4), _hard_problem(generator)):
        J_xi, J_point = problem.jacobian_blocks(mode)
        X_e = data_module.gather_points(problem.points.detach(), problem.data)
        eye = torch.eye(3, dtype=F64).expand(*X_e.shape[:-1], 3, 3)
        G = torch.cat((-so3.hat(X_e), eye), dim=-1)
        _assert_blocks_close((J_point @ G, J_point), (J_xi, J_point), rtol=EXACT_RTOL)
        # and J_point is −R, a rotation: (−J_point)ᵀ(−J_point) = I.
        RtR = J_point.transpose(-1, -2) @ J_point
        torch.testing.assert_close(RtR, eye, atol=1e-12, rtol=0)


def test_jacrev_blocks_keep_batch_shape_and_central_differences_agree(generator):
    xi = twists_with_hard_inputs(generator).reshape(8, 9, 6)
    X = 3 * torch.randn(8, 9, 3, generator=generator, dtype=F64)
    obs = torch.randn(8, 9, 3, generator=generator, dtype=F64)
    J_xi, J_point = jacobians.jacrev_blocks(xi, X, obs)
    assert J_xi.shape == (8, 9, 3, 6) and J_point.shape == (8, 9, 3, 3)
    analytic = jacobians.analytic_blocks(se3.exp(xi)[..., :3, :3], X)
    _assert_blocks_close((J_xi, J_point), analytic, rtol=EXACT_RTOL)
    cd = jacobians.central_difference_blocks(xi, X, obs, eps=FD_STEP)
    assert cd[0].shape == (8, 9, 3, 6) and cd[1].shape == (8, 9, 3, 3)
    M = 1 + X.norm(dim=-1) + xi[..., 3:].norm(dim=-1) + obs.norm(dim=-1)
    atol = 10 * (torch.finfo(F64).eps * M / FD_STEP + FD_STEP**2 * M)
    _assert_blocks_close(cd, analytic, rtol=0, atol=atol)


# --------------------------------------------------------------------------- dense Jacobian


def _whitened_residual_function(problem: PointMapProblem):
    """δ ↦ whitened residual vector, written independently of the library's gathers and
    whitening: δ stacks, per problem b, (δξ_0, …, δξ_{m−1}, δX_0, …, δX_{n−1}), poses perturbed
    T_i0 · Exp(δξ_i), points X_j + δX_j; output (B · 3E,), input (B · (6m + 3n),)."""
    data = problem.data
    T = problem.poses.detach()
    X = problem.points.detach()
    B, m, n = problem.batch_size, problem.num_poses, problem.num_points
    b = torch.arange(B)[:, None]
    L = torch.linalg.cholesky(data.information)
    valid = data.valid[..., None]

    def f(delta: Tensor) -> Tensor:
        d = delta.reshape(B, 6 * m + 3 * n)
        T2 = T @ se3.exp(d[:, : 6 * m].reshape(B, m, 6))
        X2 = X + d[:, 6 * m :].reshape(B, n, 3)
        T_e = T2[b, data.pose_index]
        X_e = X2[b, data.point_index]
        r = data.observations - (T_e[..., :3, :3] @ X_e[..., None])[..., 0] - T_e[..., :3, 3]
        r = torch.where(valid, r, torch.zeros_like(r))
        return (L.transpose(-1, -2) @ r[..., None])[..., 0].reshape(-1)

    return f, B * (6 * m + 3 * n)


def test_dense_jacobian_places_the_whitened_blocks():
    problem = _problem_with_padding_weights_and_fixed(seed=5)
    data = problem.data
    B, E = data.pose_index.shape
    m, n = problem.num_poses, problem.num_points
    J = problem.dense_jacobian().detach()
    assert J.shape == (B, 3 * E, 6 * m + 3 * n)
    J_xi, J_point = problem.jacobian_blocks()
    L = torch.linalg.cholesky(data.information)
    expected = torch.zeros_like(J)
    for b in range(B):
        for e in range(E):
            if not data.valid[b, e]:
                continue  # padding rows stay zero
            i, j = int(data.pose_index[b, e]), int(data.point_index[b, e])
            rows = slice(3 * e, 3 * e + 3)
            expected[b, rows, 6 * i : 6 * i + 6] = L[b, e].T @ J_xi[b, e]
            expected[b, rows, 6 * m + 3 * j : 6 * m + 3 * j + 3] = L[b, e].T @ J_point[b, e]
    torch.testing.assert_close(J, expected, atol=1e-13, rtol=1e-13)


def test_dense_jacobian_has_exactly_the_seed_sparsity_pattern():
    """Each valid row triple has exactly one nonzero 3×6 pose block (its pose) and one
    nonzero 3×3 point block (its point); padding triples are entirely zero.

    Fixed variables are NOT removed: the dense Jacobian is w.r.t. all 6m + 3n variables and
    the columns of the gauge pose 0 and of the fixed point 2 of problem 0 are filled like any
    other; holding variables fixed is the solver's business.
    """
    problem = _problem_with_padding_weights_and_fixed(seed=6)
    data = problem.data
    B, E = data.pose_index.shape
    m, n = problem.num_poses, problem.num_points
    J = problem.dense_jacobian().reshape(B, E, 3, 6 * m + 3 * n)
    pose_blocks = J[..., : 6 * m].reshape(B, E, 3, m, 6).ne(0).any(dim=(2, 4))  # (B, E, m)
    point_blocks = J[..., 6 * m :].reshape(B, E, 3, n, 3).ne(0).any(dim=(2, 4))  # (B, E, n)
    valid = data.valid
    assert bool((~valid).any())  # the problem has padding
    expected_pose = torch.nn.functional.one_hot(data.pose_index, m).bool() & valid[..., None]
    expected_point = torch.nn.functional.one_hot(data.point_index, n).bool() & valid[..., None]
    assert torch.equal(pose_blocks, expected_pose)
    assert torch.equal(point_blocks, expected_point)
    assert torch.equal(pose_blocks.sum(-1), valid.long())
    assert torch.equal(point_blocks.sum(-1), valid.long())
    # Within its block a row triple is dense (whitening by Lᵀ mixes the three rows).
    assert bool(J[valid].ne(0).sum(dim=(-1, -2)).eq(27).all())
    # Fixed variables keep their columns.
    assert data.fixed_poses[:, 0].all() and data.fixed_points[0, 2]
    assert bool(pose_blocks[..., 0].any()) and bool(point_blocks[0, :, 2].any())


def test_dense_jacobian_equals_jacrev_of_the_whitened_residual_vector():
    problem = _problem_with_padding_weights_and_fixed(seed=7)
    B, E = problem.data.pose_index.shape
    cols = 6 * problem.num_poses + 3 * problem.num_points
    f, size = _whitened_residual_function(problem)
    zero = torch.zeros(size, dtype=F64)
    torch.testing.assert_close(f(zero).reshape(B, E, 3), problem.residuals().detach())
    full = torch.func.jacrev(f)(zero).reshape(B, 3 * E, B, cols)
    for mode in ("analytic", "jacrev"):
        J = problem.dense_jacobian(mode).detach()
        scale = float(J.abs().max())
        for b in range(B):
            torch.testing.assert_close(J[b], full[:, :, b][b], atol=EXACT_RTOL * scale, rtol=0)
    # Problems in a batch are independent: cross-problem blocks are exactly zero.
    assert torch.equal(full[0, :, 1], torch.zeros_like(full[0, :, 1]))
    assert torch.equal(full[1, :, 0], torch.zeros_like(full[1, :, 0]))


def test_dense_jacobian_matches_central_differences():
    problem = _problem_with_padding_weights_and_fixed(seed=8)
    B, E = problem.data.pose_index.shape
    cols = 6 * problem.num_poses + 3 * problem.num_points
    f, size = _whitened_residual_function(problem)
    fd = central_difference(f, torch.zeros(size, dtype=F64), eps=FD_STEP)
    fd = fd.reshape(B, 3 * E, B, cols)
    J = problem.dense_jacobian().detach()
    # Natural accuracy of the difference: ε·M/h + h²·M with M the largest value summed
    # (whitened, so times the largest ‖Lᵀ‖), safety factor 10.
    M = float(_magnitude(problem).max()) * float(
        torch.linalg.matrix_norm(problem.data.information, ord=2).max().sqrt()
    )
    atol = 10 * (torch.finfo(F64).eps * M / FD_STEP + FD_STEP**2 * M)
    for b in range(B):
        torch.testing.assert_close(J[b], fd[:, :, b][b], atol=atol, rtol=0)


def test_dense_jacobian_refuses_above_the_documented_size(monkeypatch):
    problem = _problem_with_padding_weights_and_fixed(seed=9)
    B, E = problem.data.pose_index.shape
    cols = 6 * problem.num_poses + 3 * problem.num_points
    entries = B * 3 * E * cols
    assert jacobians.DENSE_JACOBIAN_MAX_ENTRIES == 50_000_000  # the documented limit
    monkeypatch.setattr(jacobians, "DENSE_JACOBIAN_MAX_ENTRIES", entries)
    assert problem.dense_jacobian().shape == (B, 3 * E, cols)  # exactly at the limit: built
    monkeypatch.setattr(jacobians, "DENSE_JACOBIAN_MAX_ENTRIES", entries - 1)

    def no_blocks(*args, **kwargs):
        raise AssertionError("computed the blocks before refusing")

    monkeypatch.setattr(jacobians, "analytic_blocks", no_blocks)
    with pytest.raises(ValueError, match="DENSE_JACOBIAN_MAX_ENTRIES") as info:
        problem.dense_jacobian()
    message = str(info.value)
    assert f"({B}, {3 * E}, {cols})" in message
    assert f"{entries:,} entries" in message and f"limit of {entries - 1:,}" in message
    # The function itself refuses too.
    J_xi, J_point = torch.zeros(B, E, 3, 6), torch.zeros(B, E, 3, 3)
    with pytest.raises(ValueError, match="above the limit"):
        jacobians.dense_jacobian(
            J_xi, J_point, problem.data.pose_index, problem.data.point_index, 4, 10
        )


# --------------------------------------------------------------------------- float32


def test_float32_jacobians():
    """float32 works; tolerance TOL[float32] (2e-5), relative per column group as in float64."""
    p32 = _random_problem(seed=10, dtype=torch.float32)
    p64 = _random_problem(seed=10)
    rtol = TOL[torch.float32]
    analytic32 = p32.jacobian_blocks("analytic")
    jacrev32 = p32.jacobian_blocks("jacrev")
    assert analytic32[0].dtype == jacrev32[0].dtype == torch.float32
    _assert_blocks_close(analytic32, jacrev32, rtol=rtol)
    analytic64 = p64.jacobian_blocks("analytic")
    _assert_blocks_close(tuple(J.double() for J in analytic32), analytic64, rtol=rtol)
    J32 = p32.dense_jacobian().detach()
    assert J32.dtype == torch.float32
    J64 = p64.dense_jacobian().detach()
    torch.testing.assert_close(J32.double(), J64, atol=rtol * float(J64.abs().max()), rtol=0)
