"""Terms that touch points (Term(point_index=...)): blocks, normal equations, gauge, errors.

Conventions: ξ = (ω, v) rotation first; right perturbation T ← T·Exp(δ) of the poses,
X ← X + δX of the points; T_i0 maps world → frame i. A point term's normal-equation share is
checked against a dense Jacobian of the whitened residual vector from ``torch.func.jacrev``
(U, V, the coupling W on :func:`coupling_edges`, the pose pairs, the gradients and the model
decrease), so the contract the Schur complement builds on is tested here.
"""

from __future__ import annotations

import dataclasses
import warnings

import pytest
import torch
from torch import Tensor

from torchslam import (
    HuberLoss,
    PointMapProblem,
    SolverConfig,
    solve,
    solve_differentiable,
    solve_tensors,
)
from torchslam.data.synthetic import make_scene
from torchslam.lie import se3
from torchslam.objective.data import cost_from_poses
from torchslam.objective.terms import (
    PointObservationTerm,
    Term,
    _call_residual,
    masked_constants,
    term_blocks,
    term_points,
    term_poses,
    term_whitening,
)
from torchslam.solver.linearize import (
    coupling_edges,
    linearize,
    model_decrease,
    term_pair_keys,
    whitening_factors,
)

F64 = torch.float64
FD_STEP = 1e-6
TIGHT = dict(function_tolerance=1e-15, gradient_tolerance=1e-12, parameter_tolerance=1e-15)


class TwoViewTerm(Term):
    """r = T_a X − T_b X − c: a point seen from two poses (arity 2 with a point, d = 3)."""

    def __init__(self, pose_index, point_index, c, **kwargs):
        super().__init__(pose_index, {"c": c}, point_index=point_index, **kwargs)

    def residual(self, poses, points, c):
        return se3._act(poses[..., 0, :, :], points) - se3._act(poses[..., 1, :, :], points) - c


class PointPrior(Term):
    """r = X − X̄: a term on one point and no pose (arity 0)."""

    def __init__(self, point_index, prior, **kwargs):
        super().__init__(None, {"prior": prior}, point_index=point_index, **kwargs)

    def residual(self, poses, points, prior):
        return points - prior


def _mixed_problem(
    g: torch.Generator, loss=None, information=True, noise: float = 1.0
) -> PointMapProblem:
    """4 poses, 6 points: 8 point observations (scalar weights), a PointObservationTerm, a
    two-view term (information matrices, or weights), a point prior (arity 0), pose 0 and
    point 5 held fixed, and one padding instance holding NaN and an out-of-range index. The
    data are the truth plus ``noise`` (a large one: residuals of O(1) for the linearization
    tests), the initial guess the truth perturbed by 0.1·``noise``."""
    m, n = 4, 6
    T = se3.exp(0.3 * torch.randn(m, 6, generator=g, dtype=F64))
    X = torch.randn(n, 3, generator=g, dtype=F64)

    def noisy(x: Tensor) -> Tensor:
        return x + noise * torch.randn(x.shape, generator=g, dtype=F64)

    pose_index = torch.tensor([0, 1, 2, 3, 0, 1, 2, 3])
    point_index = torch.tensor([0, 1, 2, 3, 4, 5, 0, 1])
    observations = noisy(se3.act(T[pose_index], X[point_index]))
    weights = torch.rand(1, 8, generator=g, dtype=F64) + 0.5
    K = 5
    i, j = torch.tensor([1, 2, 3, 1, 2]), torch.tensor([2, 3, 4, 4, 0])
    obs_term = PointObservationTerm(
        i,
        j,
        noisy(se3.act(T[i], X[j])),
        weight=torch.rand(K, generator=g, dtype=F64) + 0.5,
        loss=loss,
    )
    pairs, j = torch.tensor([[1, 2], [2, 3], [0, 3], [3, 1], [0, 0]]), torch.tensor([1, 2, 3, 5, 0])
    c = noisy(se3.act(T[pairs[:, 0]], X[j]) - se3.act(T[pairs[:, 1]], X[j]))
    c[4] = float("nan")  # padding: inert whatever it holds
    j[4] = 99
    A = torch.randn(K, 3, 3, generator=g, dtype=F64)
    weighting = (
        dict(information=A @ A.transpose(-1, -2) + torch.eye(3, dtype=F64))
        if information
        else dict(weight=torch.rand(K, generator=g, dtype=F64) + 0.5)
    )
    two_view = TwoViewTerm(
        pairs, j, c, valid=torch.tensor([True, True, True, True, False]), loss=loss, **weighting
    )
    prior = PointPrior(torch.tensor([2, 4]), noisy(X[[2, 4]]))
    fixed_points = torch.zeros(1, n, dtype=torch.bool)
    fixed_points[0, 5] = True
    twist = 0.1 * noise * torch.randn(m, 6, generator=g, dtype=F64)
    twist[0] = 0
    return PointMapProblem(
        (T @ se3.exp(twist))[None],
        noisy(X)[None] if noise < 1 else torch.randn(1, n, 3, generator=g, dtype=F64),
        pose_index[None],
        point_index[None],
        observations[None],
        weights=weights,
        fixed_points=fixed_points,
        terms=[obs_term, two_view, prior],
    )


def _whitened_residuals(problem: PointMapProblem, delta: Tensor, step: Tensor) -> Tensor:
    """All whitened residuals (no robust kernel) at T·Exp(δ), X + δX: δ (m, 6), δX (n, 3)."""
    data = problem.data
    T = se3._exp(problem.pose_tangent.detach()[0]) @ se3._exp(delta)
    X = problem.points.detach()[0] + step
    T_b, X_b = T[None], X[None]
    r = data.observations[0] - se3._act(T[data.pose_index[0]], X[data.point_index[0]])
    parts = [torch.sqrt(data.weights[0])[:, None] * r]
    for term in data.terms:
        Xk = term_points(term, X_b) if term.has_point else None
        rk = _call_residual(term, term_poses(term, T_b), Xk, masked_constants(term))[0]
        rk = torch.where(term.valid[0, :, None], rk, 0.0)
        U = term_whitening(term)
        if U is not None and U.dim() == 4:
            rk = (U[0] @ rk[..., None])[..., 0]
        elif U is not None:
            rk = U[0, :, None] * rk
        parts.append(rk)
    return torch.cat([p.reshape(-1) for p in parts])


def _dense_normal_equations(lin, data) -> tuple[Tensor, Tensor]:
    """H (6m + 3n)² and g from a block linearization: U, V, W on coupling_edges, pose pairs."""
    m, n = data.num_poses, data.num_points
    N = 6 * m + 3 * n
    H = torch.zeros(N, N, dtype=F64)
    for i in range(m):
        H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += lin.pose_blocks[0, i]
    for j in range(n):
        H[6 * m + 3 * j : 6 * m + 3 * j + 3, 6 * m + 3 * j : 6 * m + 3 * j + 3] += lin.point_blocks[
            0, j
        ]
    edges = coupling_edges(data)
    assert edges.pose_index.shape[1] == lin.coupling.shape[1]
    for e in range(edges.pose_index.shape[1]):
        i, j = int(edges.pose_index[0, e]), int(edges.point_index[0, e])
        rows, cols = slice(6 * i, 6 * i + 6), slice(6 * m + 3 * j, 6 * m + 3 * j + 3)
        H[rows, cols] += lin.coupling[0, e]
        H[cols, rows] += lin.coupling[0, e].T
        if not bool(edges.active[0, e]):
            assert bool((lin.coupling[0, e] == 0).all())
    keys = term_pair_keys(data)[0]
    for p, key in enumerate(keys.tolist()):
        i, k = (key % (m * m)) // m, key % m
        H[6 * i : 6 * i + 6, 6 * k : 6 * k + 6] += lin.terms.pair_blocks[0, p]
    g = torch.cat((lin.pose_gradient[0].reshape(-1), lin.point_gradient[0].reshape(-1)))
    return H, g


def _free_columns(data) -> Tensor:
    free_pose = (~data.fixed_poses[0])[:, None].expand(-1, 6).reshape(-1)
    free_point = (~data.fixed_points[0])[:, None].expand(-1, 3).reshape(-1)
    return torch.cat((free_pose, free_point))


@pytest.mark.parametrize("information", [True, False])
def test_linearization_of_point_terms_equals_the_dense_jacobian(generator, information):
    problem = _mixed_problem(generator, information=information)
    data = problem.data
    m, n = data.num_poses, data.num_points
    xi, X = problem.pose_tangent.detach(), problem.points.detach()
    lin = linearize(xi, X, data, whitening_factors(data), "analytic", True)
    H, g = _dense_normal_equations(lin, data)

    zero = (torch.zeros(m, 6, dtype=F64), torch.zeros(n, 3, dtype=F64))
    r = _whitened_residuals(problem, *zero)
    J_pose, J_point = torch.func.jacrev(
        lambda d, s: _whitened_residuals(problem, d, s), argnums=(0, 1)
    )(*zero)
    J = torch.cat((J_pose.reshape(r.numel(), -1), J_point.reshape(r.numel(), -1)), -1)
    free = _free_columns(data)
    J = J * free
    H_ref, g_ref = J.T @ J, J.T @ r
    # Fixed variables: identity blocks on the diagonal, nothing elsewhere.
    H_ref[~free, ~free] = 1.0
    # Entries are sums of a few products of O(1)-O(10) numbers: round-off ~1e-13 of the scale.
    scale = H_ref.abs().max()
    assert torch.allclose(H, H_ref, rtol=0, atol=1e-12 * scale)
    assert torch.allclose(g, g_ref, rtol=0, atol=1e-12 * scale)
    assert torch.allclose(lin.cost[0], 0.5 * (r * r).sum(), rtol=1e-13, atol=0)

    # The model decrease −(gᵀδ + ½ δᵀHδ) from per-instance blocks equals the dense one.
    dp = torch.randn(1, m, 6, generator=generator, dtype=F64) * ~data.fixed_poses[..., None]
    dl = torch.randn(1, n, 3, generator=generator, dtype=F64) * ~data.fixed_points[..., None]
    delta = torch.cat((dp.reshape(-1), dl.reshape(-1)))
    expected = -(g_ref @ delta + 0.5 * delta @ H_ref @ delta)
    got = model_decrease(lin, data, dp, dl)[0]
    assert torch.allclose(got, expected, rtol=1e-12, atol=1e-12 * scale)


def test_robust_point_terms_gradient_equals_autograd(generator):
    problem = _mixed_problem(generator, loss=HuberLoss(0.3))
    data = problem.data
    m, n = data.num_poses, data.num_points
    xi, X = problem.pose_tangent.detach(), problem.points.detach()
    lin = linearize(xi, X, data, whitening_factors(data), "analytic", True)
    delta = torch.zeros(1, m, 6, dtype=F64, requires_grad=True)
    step = torch.zeros(1, n, 3, dtype=F64, requires_grad=True)
    cost = cost_from_poses(se3._exp(xi) @ se3._exp(delta), X + step, data)
    g_pose, g_point = torch.autograd.grad(cost.sum(), (delta, step))
    g_pose = g_pose * ~data.fixed_poses[..., None]
    g_point = g_point * ~data.fixed_points[..., None]
    assert torch.allclose(lin.cost, cost.detach(), rtol=1e-13, atol=0)
    assert torch.allclose(lin.pose_gradient, g_pose, rtol=0, atol=1e-11)
    assert torch.allclose(lin.point_gradient, g_point, rtol=0, atol=1e-11)


def test_point_observation_term_blocks_match_jacrev_and_central_differences(generator):
    K = 12
    term = PointObservationTerm(
        torch.zeros(K, dtype=torch.long),
        torch.arange(K),
        torch.randn(K, 3, generator=generator, dtype=F64),
    )
    poses = se3.exp(torch.randn(K, 6, generator=generator, dtype=F64))
    bound = term.bind(1, 1, poses, K)
    P, X = poses[None, :, None], torch.randn(1, K, 3, generator=generator, dtype=F64)
    r, J, J_X = term_blocks(bound, P, X, "analytic")
    r_ref, J_ref, J_X_ref = term_blocks(bound, P, X, "jacrev")
    assert torch.allclose(r, r_ref, rtol=0, atol=0)
    # Analytic and jacrev evaluate the same products in different orders: round-off only.
    assert torch.allclose(J, J_ref, rtol=0, atol=1e-13 * (1 + X.abs().max()))
    assert torch.allclose(J_X, J_X_ref, rtol=0, atol=1e-14)
    obs = bound.constants["observations"]
    for k in range(K):

        def f(x, k=k):
            T = poses[k] @ se3.exp(x[:6])
            return obs[0, k] - se3.act(T, X[0, k] + x[6:])

        cd = _central(f, torch.zeros(9, dtype=F64))
        # Central differences: truncation O(h²) and round-off O(ε/h) ≈ 1e-10 at h = 1e-6.
        assert torch.allclose(J[0, k, :, 0], cd[:, :6], rtol=0, atol=1e-8)
        assert torch.allclose(J_X[0, k], cd[:, 6:], rtol=0, atol=1e-8)


def _central(f, x: Tensor, h: float = FD_STEP) -> Tensor:
    columns = []
    for i in range(x.numel()):
        e = torch.zeros_like(x)
        e[i] = h
        columns.append((f(x + e) - f(x - e)) / (2 * h))
    return torch.stack(columns, -1)


def test_point_observations_as_a_term_reach_the_same_optimum():
    scene = make_scene(6, 60, noise_std=0.02, seed=3)
    init = se3.exp(
        0.02 * torch.randn(1, 6, 6, generator=torch.Generator().manual_seed(1), dtype=F64)
    )
    poses0 = scene.poses_gt @ init
    points0 = scene.points_gt + 0.05
    weights = torch.full(scene.valid.shape, 4.0, dtype=F64)
    builtin = PointMapProblem(
        poses0,
        points0,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        valid=scene.valid,
        weights=weights,
    )
    empty = torch.zeros(1, 0, dtype=torch.long)
    term = PointObservationTerm(
        scene.pose_index, scene.point_index, scene.observations, weight=weights, valid=scene.valid
    )
    as_term = PointMapProblem(
        poses0, points0, empty, empty, torch.zeros(1, 0, 3, dtype=F64), terms=[term]
    )
    assert builtin.diagnostics == as_term.diagnostics
    # Same objective, same linearization (block form) at the start.
    data_a, data_b = builtin.data, as_term.data
    xi, X = builtin.pose_tangent.detach(), builtin.points.detach()
    lin_a = linearize(xi, X, data_a, whitening_factors(data_a), "analytic", False)
    lin_b = linearize(xi, X, data_b, whitening_factors(data_b), "analytic", True)
    for name in ("cost", "pose_gradient", "point_gradient", "pose_blocks", "point_blocks"):
        a, b = getattr(lin_a, name), getattr(lin_b, name)
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12 * a.abs().max()), name
    results = [solve(p, SolverConfig(**TIGHT)) for p in (builtin, as_term)]
    assert all(r.converged[0] for r in results)
    cost_a, cost_b = (float(r.final_cost[0]) for r in results)
    # Both stop at the same minimum to round-off of the cost (~1e-14 relative).
    assert abs(cost_a - cost_b) <= 1e-10 * cost_a
    assert torch.allclose(results[0].points, results[1].points, rtol=0, atol=1e-8)
    assert torch.allclose(results[0].pose_tangent, results[1].pose_tangent, rtol=0, atol=1e-8)


def test_point_terms_count_as_observations_for_the_gauge():
    """A point seen by one 2-entry instance and a pose with 2 instances are held fixed; with
    enough instances nothing is."""

    class Pixel(Term):
        def __init__(self, pose_index, point_index, u):
            super().__init__(pose_index[:, None], {"u": u}, point_index=point_index)

        def residual(self, poses, points, u):
            Xc = se3._act(poses[..., 0, :, :], points)
            return u - Xc[..., :2] / Xc[..., 2:]

    g = torch.Generator().manual_seed(0)
    poses = se3.exp(0.1 * torch.randn(1, 3, 6, generator=g, dtype=F64))
    points = torch.randn(1, 5, 3, generator=g, dtype=F64) + torch.tensor([0, 0, 5.0], dtype=F64)
    # Pose 1 sees points 0-4, pose 2 sees points 0-1 only; point 4 is seen once.
    cams = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1, 1, 2, 2])
    pts = torch.tensor([0, 1, 2, 3, 0, 1, 2, 3, 4, 0, 1])
    term = Pixel(cams, pts, torch.zeros(11, 2, dtype=F64))
    empty = torch.zeros(1, 0, dtype=torch.long)
    with pytest.warns(UserWarning) as record:
        problem = PointMapProblem(
            poses, points, empty, empty, torch.zeros(1, 0, 3, dtype=F64), terms=[term]
        )
    assert len(record) == 1
    assert problem.diagnostics == [
        "problem 0: pose 2 has 2 observation(s) (< 3); held fixed at its initial value",
        "problem 0: point 4 has 2 residual entries (< 3); held fixed",
    ]
    assert problem.data.fixed_poses.tolist() == [[True, False, True]]
    assert problem.data.fixed_points.tolist() == [[False, False, False, False, True]]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cams = torch.tensor([0, 0, 0, 1, 1, 1, 2, 2, 2])
        pts = torch.tensor([0, 1, 2, 0, 1, 2, 0, 1, 2])
        PointMapProblem(
            poses,
            points[:, :3],
            empty,
            empty,
            torch.zeros(1, 0, 3, dtype=F64),
            terms=[Pixel(cams, pts, torch.zeros(9, 2, dtype=F64))],
        )


def test_point_term_errors(generator):
    X = torch.randn(3, 3, generator=generator, dtype=F64)
    with pytest.raises(TypeError, match="'point_index' must be an integer tensor"):
        TwoViewTerm(torch.zeros(3, 2, dtype=torch.long), torch.zeros(3), X)
    with pytest.raises(ValueError, match=r"'point_index' must have shape \(3,\)"):
        TwoViewTerm(torch.zeros(3, 2, dtype=torch.long), torch.zeros(3, 1, dtype=torch.long), X)
    with pytest.raises(TypeError, match=r"'point_index' must be a torch\.Tensor or None"):
        TwoViewTerm(torch.zeros(3, 2, dtype=torch.long), [0, 1, 2], X)
    with pytest.raises(ValueError, match="constant name 'points' is taken"):
        Term(torch.zeros(3, 1, dtype=torch.long), {"points": X}, point_index=torch.zeros(3).long())
    term = TwoViewTerm(torch.zeros(3, 2, dtype=torch.long), torch.tensor([0, 1, 7]), X)
    with pytest.raises(ValueError, match="needs 'num_points'"):
        term.bind(1, 2, X)
    with pytest.raises(ValueError, match=r"'point_index' out of range \[0, 4\): problem 0, "):
        term.bind(1, 2, X, 4)
    poses = se3.exp(0.1 * torch.randn(1, 2, 6, generator=generator, dtype=F64))
    with pytest.raises(ValueError, match=r"'point_index' out of range \[0, 4\)"):
        PointMapProblem(
            poses,
            torch.zeros(1, 4, 3, dtype=F64),
            torch.zeros(1, 0, dtype=torch.long),
            torch.zeros(1, 0, dtype=torch.long),
            torch.zeros(1, 0, 3, dtype=F64),
            terms=[term],
        )

    class BadBlocks(TwoViewTerm):
        def jacobians(self, poses, points, c):
            r = self.residual(poses, points, c)
            return r, r.new_zeros(*r.shape, 2, 6)

    bad = BadBlocks(torch.zeros(3, 2, dtype=torch.long), torch.tensor([0, 1, 2]), X)
    bound = bad.bind(1, 2, X, 3)
    with pytest.raises(TypeError, match="must return None or a tuple \\(residuals, pose blocks"):
        term_blocks(bound, term_poses(bound, poses), term_points(bound, X[None]))
    with pytest.raises(TypeError, match="touches points"):
        term_blocks(bound, term_poses(bound, poses))


def test_point_terms_solve_alike_with_every_linear_solver(generator):
    problem = _mixed_problem(generator, information=True, noise=0.01)
    xi0, X0 = problem.pose_tangent.detach().clone(), problem.points.detach().clone()
    results = []
    for config in (
        SolverConfig(linear_solver="schur", **TIGHT),
        SolverConfig(linear_solver="schur", reduced_solver="sparse", **TIGHT),
        SolverConfig(linear_solver="dense", **TIGHT),
        SolverConfig(linear_solver="schur", jacobian="jacrev", **TIGHT),
    ):
        with torch.no_grad():
            problem.pose_tangent.copy_(xi0)
            problem.points.copy_(X0)
        results.append(solve(problem, config))
    costs = [float(r.final_cost[0]) for r in results]
    assert all(r.converged[0] for r in results), [r.reason for r in results]
    # One minimum: the costs agree to round-off of the cost, the variables to what a
    # gradient of ≤ 1e-12 leaves on a system whose curvature is O(1).
    for r, c in zip(results[1:], costs[1:], strict=True):
        assert abs(c - costs[0]) <= 1e-10 * max(costs[0], 1.0)
        assert torch.allclose(r.points, results[0].points, rtol=0, atol=1e-7)
        assert torch.allclose(r.pose_tangent, results[0].pose_tangent, rtol=0, atol=1e-7)


def test_gradients_through_a_point_term_implicit_equal_unrolled(generator):
    """d(solution)/d(constants of a point term): the implicit function theorem at the optimum
    and differentiating the iterations agree (both exact at a converged solve)."""
    problem = _mixed_problem(generator, information=False, noise=0.01)
    data = problem.data
    two_view = data.terms[1]
    c = two_view.constants["c"].clone().requires_grad_(True)
    terms = (data.terms[0], two_view.replace_tensors({"constants.c": c}), data.terms[2])
    data = dataclasses.replace(data, terms=terms)
    xi0, X0 = problem.pose_tangent.detach(), problem.points.detach()
    config = SolverConfig(linear_solver="dense", **TIGHT)
    gradients = []
    for backward in ("implicit", "unrolled"):
        result = solve_differentiable(xi0, X0, data, config, backward=backward)
        assert result.converged[0]
        target = result.points[0, 1:4].sum() + result.pose_tangent[0, 2].sum()
        (g,) = torch.autograd.grad(target, c)
        gradients.append(g)
    # Both differentiate the same stationarity condition; the unrolled derivative converges
    # with the iterates, and the function-tolerance stop (|ΔF| ≤ 1e-15 F, F ≈ 1e-3, curvature
    # O(1)) leaves steps of O(√(1e-18)) = 1e-9, so it is off by ~1e-9 times the O(1)
    # sensitivities (measured 1e-9); 1e-7 leaves two orders for other kernels and orders.
    assert gradients[0][0, 4].abs().max() == 0  # the padding instance gets no gradient
    assert torch.allclose(gradients[0], gradients[1], rtol=0, atol=1e-7)
    assert gradients[0].abs().max() > 1e-3


def test_batched_point_terms_equal_separate_solves():
    """Two bundle-like problems with per-problem (B, K) indices solve in one batch as alone."""
    problems = [_mixed_problem(torch.Generator().manual_seed(s), noise=0.01) for s in (1, 2)]
    config = SolverConfig(**TIGHT)
    alone = [solve(p, config) for p in problems]
    problems = [_mixed_problem(torch.Generator().manual_seed(s), noise=0.01) for s in (1, 2)]
    data = [p.data for p in problems]

    def stack(*xs):
        return torch.cat(xs)

    terms = []
    for k, cls in enumerate((PointObservationTerm, TwoViewTerm, PointPrior)):
        a, b = data[0].terms[k], data[1].terms[k]
        new = Term.__new__(cls)
        new.__dict__.update(a.__dict__)
        new.pose_index = stack(a.pose_index, b.pose_index)
        new.point_index = stack(a.point_index, b.point_index)
        new.valid = stack(a.valid, b.valid)
        new.constants = {n: stack(a.constants[n], b.constants[n]) for n in a.constants}
        for name in ("weight", "information"):
            if getattr(a, name) is not None:
                setattr(new, name, stack(getattr(a, name), getattr(b, name)))
        terms.append(new)
    fields = {
        name: stack(getattr(data[0], name), getattr(data[1], name))
        for name in ("pose_index", "point_index", "observations", "valid", "weights")
    }
    batched_data = dataclasses.replace(
        data[0],
        fixed_poses=stack(data[0].fixed_poses, data[1].fixed_poses),
        fixed_points=stack(data[0].fixed_points, data[1].fixed_points),
        terms=tuple(terms),
        **fields,
    )
    xi = stack(*(p.pose_tangent.detach() for p in problems))
    X = stack(*(p.points.detach() for p in problems))
    batched = solve_tensors(xi, X, batched_data, config)
    for b in range(2):
        # The same iterations on the same numbers, up to the order of batched reductions.
        assert abs(float(batched.final_cost[b]) - float(alone[b].final_cost[0])) <= 1e-12
        assert torch.allclose(batched.points[b], alone[b].points[0], rtol=0, atol=1e-9)
        assert torch.allclose(batched.pose_tangent[b], alone[b].pose_tangent[0], rtol=0, atol=1e-9)


def test_block_linearization_assembles_the_jacobian_in_place_bit_for_bit(generator, monkeypatch):
    """Plain tensors take the in-place [J_ξ | J_X] assembly, tensors that record autograd
    history (or torch.func's) the concatenation: the same bits either way."""
    from torchslam.solver import linearize as module

    problem = _mixed_problem(generator, loss=HuberLoss(0.3))
    data = problem.data
    xi, X = problem.pose_tangent.detach(), problem.points.detach()
    in_place = linearize(xi, X, data, whitening_factors(data), "analytic", False)
    monkeypatch.setattr(module, "_plain", lambda *tensors: False)
    concatenated = linearize(xi, X, data, whitening_factors(data), "analytic", False)
    for name in ("cost", "pose_gradient", "point_gradient", "pose_blocks", "point_blocks"):
        assert torch.equal(getattr(in_place, name), getattr(concatenated, name)), name
    assert not module._plain(xi.clone().requires_grad_())
