"""Gradients through the solver are never silently wrong: unconverged problems (the
``on_unconverged`` policy of the implicit backward), second derivatives (refused by the implicit
backward; finite and exact through the unrolled one, also at an identity gauge pose, which needs
the SO(3) log's double backward at R = I) and data reused across training steps.

Every gradient is compared with central finite differences of the function actually computed,
in float64, on problems of 3 poses and 8 points.
"""

from __future__ import annotations

import dataclasses
import warnings

import pytest
import torch
from torch import Tensor

from torchslam import PointMapProblem, SolverConfig, solve_tensors
from torchslam.data import make_scene
from torchslam.initialization import initialize_scene
from torchslam.lie import se3, so3
from torchslam.solver.differentiable import solve_differentiable
from torchslam.solver.result import Status

from . import downstream_objective

F64 = torch.float64
# Converged solves run to round-off (as test_gradients.CONVERGED).
TIGHT = {"function_tolerance": 1e-14, "gradient_tolerance": 1e-14}
# The truncated forward solve: 2 iterations. Problem 0 (started at its minimum) converges
# within them, problem 1 (started far away) does not.
TRUNCATED = SolverConfig(max_iterations=2, **TIGHT)


def _scene():
    return make_scene(3, 8, batch_size=2, visible_fraction=0.9, noise_std=0.01, seed=5)


def _weights(scene) -> Tensor:
    gen = torch.Generator().manual_seed(0)
    return 0.5 + torch.rand(scene.valid.shape, generator=gen, dtype=F64)


def _problem(scene, observations, weights, poses: Tensor, points: Tensor) -> PointMapProblem:
    return PointMapProblem(
        poses,
        points,
        scene.pose_index,
        scene.point_index,
        observations,
        valid=scene.valid,
        weights=weights,
    )


def _far_start(scene) -> tuple[Tensor, Tensor]:
    """Initial poses and points drifted by 40° and 0.5 m per odometry step."""
    far = initialize_scene(
        scene, method="odometry", rotation_noise_deg=40.0, translation_noise=0.5, seed=5
    )
    return far.poses, far.points


def _mixed_start(scene, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Initial (pose_tangent, points): problem 0 at its own minimum, problem 1 far (its
    gradients after 2 iterations are ~50% off the implicit ones)."""
    p = _problem(scene, scene.observations, weights, *_far_start(scene))
    solved = solve_tensors(p.pose_tangent, p.points, p.data, SolverConfig(**TIGHT))
    xi0 = torch.cat((solved.pose_tangent[:1], p.pose_tangent.detach()[1:]))
    X0 = torch.cat((solved.points[:1], p.points.detach()[1:]))
    return xi0, X0


def _central_differences(
    scene, inputs, b: int, entries, h: float, stencil: int, config, polish: bool = False
):
    """Central differences of the objective of problem b along single entries of its inputs,
    as the forward pass computes it (solve_tensors with ``config``): 2-point (error
    h²|f'''|/6 + ε|f|/h) or 4-point (error h⁴|f⁽⁵⁾|/30 + ε|f|/h) stencils.

    One batched solve: problem b is repeated once per (entry, step), perturbed there (the
    problems of a batch are independent)."""
    steps = (-1.0, 1.0) if stencil == 2 else (-2.0, -1.0, 1.0, 2.0)
    cases = [(which, index, step) for which, index in entries for step in steps]
    P = len(cases)
    rows = [t[b : b + 1].repeat(P, *([1] * (t.dim() - 1))) for t in inputs]
    for k, (which, index, step) in enumerate(cases):
        rows[which][(k, *index)] += step * h
    observations, weights, xi0, X0 = rows
    problem = PointMapProblem(
        se3.exp(xi0),
        X0,
        scene.pose_index[b : b + 1].repeat(P, 1),
        scene.point_index[b : b + 1].repeat(P, 1),
        observations,
        valid=scene.valid[b : b + 1].repeat(P, 1),
        weights=weights,
    )
    result = solve_tensors(xi0, X0, problem.data, config)
    if polish:
        # A converged solve stops where LM's cost comparisons (the machine's rounding) say;
        # Gauss-Newton steps (no comparisons) then take each perturbed solve to its minimizer
        # within round-off, so the stencil sees the function, not the stopping noise.
        gauss_newton = SolverConfig(
            algorithm="gauss_newton",
            max_iterations=12,
            function_tolerance=0.0,
            gradient_tolerance=0.0,
            parameter_tolerance=0.0,
        )
        result = solve_tensors(result.pose_tangent, result.points, problem.data, gauss_newton)
    values = downstream_objective(result.pose_tangent, result.points).reshape(
        len(entries), len(steps)
    )
    if stencil == 2:
        return (values[:, 1] - values[:, 0]) / (2 * h)
    return (8 * (values[:, 2] - values[:, 1]) - (values[:, 3] - values[:, 0])) / (12 * h)


def _analytic(scene, inputs, config: SolverConfig, **options) -> tuple[Tensor, ...]:
    leaves = [t.clone().requires_grad_(True) for t in inputs]
    observations, weights, xi0, X0 = leaves
    p = _problem(scene, observations, weights, se3.exp(xi0.detach()), X0.detach())
    result = solve_differentiable(xi0, X0, p.data, config, **options)
    loss = downstream_objective(result.pose_tangent, result.points).sum()
    return torch.autograd.grad(loss, leaves)


# ------------------------------------------------------------------------------------------
# Unconverged problems


def test_unconverged_problems_get_the_gradient_of_the_iterations_run():
    scene = _scene()
    weights = _weights(scene)
    xi0, X0 = _mixed_start(scene, weights)
    inputs = [scene.observations.clone(), weights, xi0, X0]
    forward = solve_tensors(xi0, X0, _problem(scene, *inputs[:2], se3.exp(xi0), X0).data, TRUNCATED)
    assert forward.status[0].converged and forward.status[1] == Status.MAX_ITERATIONS

    with pytest.warns(UserWarning, match=r"problem 1 \(MAX_ITERATIONS\) of 2 did not converge"):
        analytic = _analytic(scene, inputs, TRUNCATED)
    opted_out = _analytic(scene, inputs, TRUNCATED, on_unconverged="implicit")

    # Problem 1 against the truncated solve itself (the same 2 iterations; its accept/reject
    # decisions do not flip under ±h). h = 1e-6 in float64: error ≈ h²|f'''|/6 + ε|f|/h ≈
    # 1e-12 + 1e-10 relative to O(1) values; 1e-7 leaves room for the conditioning of two
    # Levenberg-Marquardt steps.
    entries = [(0, (4, 2)), (0, (17, 0)), (1, (3,)), (1, (20,)), (2, (0, 1)), (2, (2, 4))]
    entries += [(3, (5, 1))]
    numeric = _central_differences(scene, inputs, 1, entries, 1e-6, 2, TRUNCATED)
    for (which, index), fd in zip(entries, numeric.tolist(), strict=True):
        exact = float(analytic[which][(1, *index)])
        assert abs(fd - exact) <= 1e-7 * max(abs(exact), 1.0), (which, index, fd, exact)
    # The implicit gradient would have been far off there (not a minimum yet).
    assert float((opted_out[1][1] - analytic[1][1]).norm() / analytic[1][1].norm()) > 0.05
    # The unrolled problem depends on its free initial guess; the converged one does not.
    assert analytic[3][1].abs().amax() > 1e-3 and analytic[3][0].abs().amax() == 0.0

    # Problem 0 against the converged solve. Converged solves repeat only to ~1e-10 under
    # perturbations of the data (test_gradients.CONVERGED), hence the 4-point stencil with
    # h = 1e-3 (noise 1e-10/h = 1e-7, truncation h⁴ = 1e-12) and a 1e-6 tolerance.
    entries = [(0, (5, 0)), (1, (9,)), (2, (0, 2))]
    numeric = _central_differences(
        scene, inputs, 0, entries, 1e-3, 4, SolverConfig(**TIGHT), polish=True
    )
    for (which, index), fd in zip(entries, numeric.tolist(), strict=True):
        exact = float(analytic[which][(0, *index)])
        assert abs(fd - exact) <= 1e-6 * max(abs(exact), 1.0), (which, index, fd, exact)
    # ... and it keeps the implicit gradient: the same as when every problem is implicit, up
    # to the conjugate-gradient tolerance (1e-10; the runs differ only in how many CG
    # iterations problem 0 gets beyond it).
    for a, b in zip(analytic, opted_out, strict=True):
        assert torch.allclose(a[0], b[0], rtol=1e-8, atol=1e-12)


def test_on_unconverged_policies():
    scene = _scene()
    weights = _weights(scene)
    xi0, X0 = _mixed_start(scene, weights)
    inputs = [scene.observations.clone(), weights, xi0, X0]
    with pytest.raises(RuntimeError, match=r"problem 1 \(MAX_ITERATIONS\) of 2 did not conv"):
        _analytic(scene, inputs, TRUNCATED, on_unconverged="raise")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        unrolled = _analytic(scene, inputs, TRUNCATED, on_unconverged="unroll")
        # Nothing to differentiate, or every problem converged: no warning, no error.
        p = _problem(scene, *inputs[:2], se3.exp(xi0), X0)
        solve_differentiable(xi0, X0, p.data, TRUNCATED, on_unconverged="raise")
        _analytic(scene, inputs, SolverConfig(**TIGHT), on_unconverged="raise")
    with pytest.warns(UserWarning, match="did not converge"):
        warned = _analytic(scene, inputs, TRUNCATED)
    for a, b in zip(unrolled, warned, strict=True):
        assert torch.equal(a, b)
    # Every problem unconverged: the whole batch is unrolled, equal to backward="unrolled".
    far = _problem(scene, *inputs[:2], *_far_start(scene))
    inputs[2:] = [far.pose_tangent.detach(), far.points.detach()]
    one_step = SolverConfig(max_iterations=1, **TIGHT)
    every = _analytic(scene, inputs, one_step, on_unconverged="unroll")
    reference = _analytic(scene, inputs, one_step, backward="unrolled")
    for a, b in zip(every, reference, strict=True):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="'on_unconverged' must be one of"):
        solve_differentiable(xi0, X0, p.data, on_unconverged="ignore")


# ------------------------------------------------------------------------------------------
# Second derivatives


def test_implicit_backward_refuses_second_derivatives():
    scene = _scene()
    weights = _weights(scene).requires_grad_(True)
    xi0, X0 = _mixed_start(scene, weights.detach())
    p = _problem(scene, scene.observations, weights, se3.exp(xi0), X0)
    config = SolverConfig(**TIGHT)

    def loss_of(w: Tensor, use_cost: bool = False) -> Tensor:
        data = dataclasses.replace(p.data, weights=w)
        result = solve_differentiable(xi0, X0, data, config)
        if use_cost:
            return result.final_cost.sum()
        return downstream_objective(result.pose_tangent, result.points).sum()

    message = r"solve_differentiable: backward='implicit' provides first derivatives only.*"
    message += r"backward='unrolled'"
    for use_cost in (False, True):
        with pytest.raises(RuntimeError, match=message):
            torch.autograd.grad(loss_of(weights, use_cost), weights, create_graph=True)
        with pytest.raises(RuntimeError, match=message), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch's note on backward(create_graph=True)
            loss_of(weights, use_cost).backward(create_graph=True)
        weights.grad = None
    with pytest.raises(RuntimeError, match=message):
        torch.autograd.functional.hvp(loss_of, weights.detach(), torch.ones_like(weights))
    # First derivatives are unaffected.
    assert torch.isfinite(torch.autograd.grad(loss_of(weights), weights)[0]).all()


@pytest.mark.parametrize("omega_norm", [0.0, 1e-12, 1e-6, 0.15, 0.3, 1.0])
@pytest.mark.parametrize("group", ["so3", "se3"])
def test_log_exp_second_derivatives_at_and_near_identity(group, omega_norm):
    # L(ω) = Log(Exp(ω)) = ω for |ω| < π, so f(ω) = Σ sin(L) + (a·L)² has the Hessian
    # diag(−sin ω) + 2aaᵀ: the double backward through log and exp must give it, finite at
    # ω = 0 (R = I) where the log's rotation angle |v| has no derivative.
    dim = 3 if group == "so3" else 6
    gen = torch.Generator().manual_seed(dim)
    direction = torch.randn(dim, generator=gen, dtype=F64)
    a = torch.randn(dim, generator=gen, dtype=F64)
    u = torch.randn(dim, generator=gen, dtype=F64)
    x = direction / direction[:3].norm() * omega_norm
    log_exp = (lambda w: so3.log(so3.exp(w))) if group == "so3" else (lambda w: se3.log(se3.exp(w)))

    def f(w: Tensor) -> Tensor:
        L = log_exp(w)
        return torch.sin(L).sum() + (a @ L) ** 2

    def gradient(w: Tensor) -> Tensor:
        w = w.detach().requires_grad_(True)
        return torch.autograd.grad(f(w), w)[0]

    exact = -torch.sin(x) * u + 2 * a * (a @ u)
    # Double backward (the usual Hessian-vector product) and torch.autograd.functional.hvp
    # (which takes a different route through the same graph); exact to round-off: every
    # coefficient is accurate to a few ulps on its branch.
    w = x.clone().requires_grad_(True)
    g = torch.autograd.grad(f(w), w, create_graph=True)[0]
    hvp = torch.autograd.grad(g @ u, w)[0]
    assert torch.isfinite(hvp).all()
    assert torch.allclose(hvp, exact, rtol=1e-12, atol=1e-12), (hvp, exact)
    assert torch.allclose(torch.autograd.functional.hvp(f, x, u)[1], exact, rtol=1e-12, atol=1e-12)
    # And the finite difference of the gradient, h = 1e-6: error ≈ h²|f⁗| + ε|∇f|/h ≈ 1e-10.
    h = 1e-6
    numeric = (gradient(x + h * u) - gradient(x - h * u)) / (2 * h)
    assert torch.allclose(hvp, numeric, rtol=1e-8, atol=1e-8)


def test_unrolled_hessian_vector_product_with_an_identity_gauge_pose():
    # A fixed number of iterations (no tolerance can stop it early), so that the solution is
    # a smooth function of the data and the initial guess.
    scene = make_scene(3, 8, batch_size=1, visible_fraction=0.9, noise_std=0.01, seed=5)
    init = initialize_scene(
        scene, method="odometry", rotation_noise_deg=5.0, translation_noise=0.05, seed=5
    )
    config = SolverConfig(
        max_iterations=3, function_tolerance=0.0, gradient_tolerance=0.0, parameter_tolerance=0.0
    )
    weights = _weights(scene)
    p = _problem(scene, scene.observations, weights, init.poses, init.points)
    xi0 = p.pose_tangent.detach()
    assert torch.equal(xi0[:, 0], torch.zeros_like(xi0[:, 0]))  # the gauge pose is I

    def f(w: Tensor, xi: Tensor) -> Tensor:
        data = dataclasses.replace(p.data, weights=w)
        result = solve_differentiable(xi, p.points.detach(), data, config, backward="unrolled")
        assert int(result.iterations.min()) == 3
        return downstream_objective(result.pose_tangent, result.points).sum()

    def gradient(w: Tensor, xi: Tensor) -> tuple[Tensor, Tensor]:
        w, xi = w.detach().requires_grad_(True), xi.detach().requires_grad_(True)
        return torch.autograd.grad(f(w, xi), (w, xi))

    gen = torch.Generator().manual_seed(11)
    u = (
        torch.randn(weights.shape, generator=gen, dtype=F64),
        torch.randn(xi0.shape, generator=gen, dtype=F64),
    )
    # Double backward: the gradient with create_graph=True, then the gradient of its inner
    # product with u.
    leaves = (weights.clone().requires_grad_(True), xi0.clone().requires_grad_(True))
    g = torch.autograd.grad(f(*leaves), leaves, create_graph=True)
    hvp = torch.autograd.grad(sum((a * b).sum() for a, b in zip(g, u, strict=True)), leaves)
    # h = 1e-5 on O(1) inputs: error ≈ h²|f⁗| + ε|∇f|/h ≈ 1e-10 + 1e-11 relative; the three
    # damped Gauss-Newton steps are well conditioned (the problem is well posed), so 1e-6.
    h = 1e-5
    plus = gradient(weights + h * u[0], xi0 + h * u[1])
    minus = gradient(weights - h * u[0], xi0 - h * u[1])
    for exact, g_plus, g_minus in zip(hvp, plus, minus, strict=True):
        assert torch.isfinite(exact).all()
        numeric = (g_plus - g_minus) / (2 * h)
        assert float((exact - numeric).norm() / numeric.norm()) <= 1e-6
    # The gauge pose's direction is a real part of it (moving pose 0 moves the solution).
    assert hvp[1][:, 0].abs().amax() > 1e-3


# ------------------------------------------------------------------------------------------
# Data reused across training steps


@pytest.mark.parametrize("backward", ["implicit", "unrolled"])
def test_data_reused_after_backward_is_refused_with_the_pattern_that_works(backward):
    scene = _scene()
    init = initialize_scene(scene, method="odometry", seed=5)
    logits = torch.zeros(scene.valid.shape, dtype=F64, requires_grad=True)
    problem = _problem(scene, scene.observations, torch.sigmoid(logits), init.poses, init.points)

    def step(data) -> Tensor:
        result = solve_differentiable(problem.pose_tangent, problem.points, data, backward=backward)
        logits.grad = None
        downstream_objective(result.pose_tangent, result.points).sum().backward()
        return logits.grad.clone()

    first = step(problem.data)
    # The weights' graph (sigmoid) was freed by that backward: a second solve says so, and how.
    with pytest.raises(ValueError, match=r"'data\.weights'.*freed.*dataclasses\.replace"):
        step(problem.data)
    # The pattern: recompute the weights for every solve (same logits, same gradient).
    for _ in range(2):
        again = step(dataclasses.replace(problem.data, weights=torch.sigmoid(logits)))
        assert torch.equal(again, first)
    # A graph kept alive (retain_graph=True) is no false alarm.
    data = dataclasses.replace(problem.data, weights=torch.sigmoid(logits))
    for _ in range(2):
        result = solve_differentiable(problem.pose_tangent, problem.points, data, backward=backward)
        downstream_objective(result.pose_tangent, result.points).sum().backward(retain_graph=True)
    # The initial guess is checked too.
    offset = torch.zeros((), dtype=F64, requires_grad=True)
    X0 = problem.points.detach() * torch.exp(offset)
    X0.sum().backward()
    with pytest.raises(ValueError, match="'points' was computed by an autograd graph"):
        solve_differentiable(problem.pose_tangent, X0, problem.data, backward=backward)


def test_the_graph_check_never_unpacks_saved_tensors():
    # Unpacking a live saved tensor would run its hooks (save_on_cpu copies, checkpointing's
    # recomputation): the check reads the raw saved tensors only.
    scene = _scene()
    init = initialize_scene(scene, method="odometry", seed=5)
    problem = _problem(scene, scene.observations, None, init.poses, init.points)
    logits = torch.zeros(scene.valid.shape, dtype=F64, requires_grad=True)
    unpacked = []

    def unpack(t: Tensor) -> Tensor:
        unpacked.append(t.shape)
        return t

    with torch.autograd.graph.saved_tensors_hooks(lambda t: t, unpack):
        weights = torch.sigmoid(logits).exp()
    data = dataclasses.replace(problem.data, weights=weights)
    config = SolverConfig(max_iterations=2)
    result = solve_differentiable(
        problem.pose_tangent, problem.points, data, config, on_unconverged="unroll"
    )
    assert unpacked == []
    result.final_cost.sum().backward()
    assert unpacked and torch.isfinite(logits.grad).all()
