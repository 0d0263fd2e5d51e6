"""Gradients through the solver (issue 5): gradcheck, implicit = unrolled = finite differences,
batching, the truncated and none modes, information matrices and a weight model."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from torchslam import HuberLoss, PointMapProblem, SolverConfig, solve_tensors
from torchslam.data import make_scene
from torchslam.initialization import initialize_scene
from torchslam.solver.differentiable import ImplicitConfig, solve_differentiable
from torchslam.solver.hessian import dense_hessian, exact_hessian

from . import CONVERGED, POLISH

# Solves run to round-off: Levenberg-Marquardt then stops at ‖∇F‖ ≈ 1e-10 (its cost-based
# acceptance cannot verify smaller steps), so solutions repeat to ~1e-10 under perturbations of
# the data and central differences need a step h ≈ 1e-3 (noise ~1e-10/h, truncation ~h⁴ for
# the 4-point stencil) to resolve gradients to ~1e-7 (CONVERGED and POLISH in tests.solver).
# Huber at 5σ of the synthetic noise (0.01 m): inliers stay quadratic, outliers go linear, so
# the Gauss-Newton fixed-point iteration contracts fast and the unrolled derivative converges.
HUBER_SCALE = 0.05


def _setup(
    num_poses: int = 4,
    num_points: int = 12,
    batch_size: int = 2,
    outlier_fraction: float = 0.0,
    noise_std: float = 0.01,
    seed: int = 3,
):
    scene = make_scene(
        num_poses,
        num_points,
        batch_size=batch_size,
        visible_fraction=0.75,
        outlier_fraction=outlier_fraction,
        noise_std=noise_std,
        seed=seed,
    )
    init = initialize_scene(
        scene, method="odometry", rotation_noise_deg=3.0, translation_noise=0.03, seed=seed
    )
    gen = torch.Generator().manual_seed(seed)
    weights = 0.5 + torch.rand(scene.valid.shape, generator=gen, dtype=torch.float64)
    return scene, init, weights


def _problem(scene, init, observations, weights, loss=None, sl=slice(None)) -> PointMapProblem:
    return PointMapProblem(
        init.poses[sl],
        init.points[sl],
        scene.pose_index[sl],
        scene.point_index[sl],
        observations[sl],
        valid=scene.valid[sl],
        weights=None if weights is None else weights[sl],
        loss=loss,
    )


def _objective(pose_tangent: Tensor, points: Tensor) -> Tensor:
    """A downstream loss of the solution, per problem (B,): nonlinear in every entry."""
    coefficients = torch.linspace(-1.0, 1.0, 6, dtype=pose_tangent.dtype)
    return (
        (pose_tangent * coefficients).sum((-1, -2))
        + (points**2).sum((-1, -2))
        + (pose_tangent**2).sum((-1, -2))
    )


def _relative(a: Tensor, b: Tensor) -> float:
    return float((a - b).norm() / b.norm())


def _gradients(problem, inputs, backward, config=CONVERGED, **options) -> tuple[Tensor, ...]:
    result = solve_differentiable(
        problem.pose_tangent, problem.points, problem.data, config, backward=backward, **options
    )
    loss = _objective(result.pose_tangent, result.points).sum()
    return torch.autograd.grad(loss, inputs, allow_unused=True)


def test_gradcheck_implicit():
    scene, init, weights = _setup(num_poses=3, num_points=8, batch_size=1)
    problem = _problem(scene, init, scene.observations, weights)

    def solution(observations: Tensor, w: Tensor):
        data = _problem(scene, init, observations, w).data
        # LM to convergence, then Gauss-Newton to the minimizer within round-off (POLISH: no
        # cost comparisons, so no rounding-dependent stopping point), then the implicit
        # gradient there. It does not depend on the start, and the polished point is a
        # minimum, so the implicit theory holds although POLISH stops at its iteration count.
        with torch.no_grad():
            start = solve_tensors(problem.pose_tangent, problem.points, data, CONVERGED)
        result = solve_differentiable(
            start.pose_tangent,
            start.points,
            data,
            POLISH,
            backward="implicit",
            on_unconverged="implicit",
        )
        return result.pose_tangent, result.points

    inputs = (
        scene.observations.clone().requires_grad_(True),
        weights.clone().requires_grad_(True),
    )
    # eps = 1e-3: see CONVERGED (the solution is repeatable to ~1e-10, not to round-off).
    assert torch.autograd.gradcheck(solution, inputs, eps=1e-3, atol=1e-6, rtol=1e-4)


def test_gradcheck_unrolled():
    # A fixed number of Levenberg-Marquardt iterations, still far from round-off, so that no
    # accept/reject decision flips under the ±eps perturbations.
    scene, init, weights = _setup(num_poses=3, num_points=8, batch_size=1, outlier_fraction=0.1)
    config = SolverConfig(
        max_iterations=4, function_tolerance=0.0, gradient_tolerance=0.0, parameter_tolerance=0.0
    )
    problem = _problem(scene, init, scene.observations, weights)

    def solution(observations, w, scale, pose_tangent):
        data = _problem(scene, init, observations, w, HuberLoss(scale)).data
        result = solve_differentiable(
            pose_tangent, problem.points, data, config, backward="unrolled"
        )
        assert int(result.iterations.min()) == 4
        return result.pose_tangent, result.points

    inputs = (
        scene.observations.clone().requires_grad_(True),
        weights.clone().requires_grad_(True),
        torch.tensor(HUBER_SCALE, dtype=torch.float64, requires_grad=True),
        problem.pose_tangent.detach().clone().requires_grad_(True),
    )
    assert torch.autograd.gradcheck(solution, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("robust", [False, True], ids=["least-squares", "huber"])
def test_implicit_equals_unrolled_at_convergence(robust):
    scene, init, weights = _setup(outlier_fraction=0.05)
    observations = scene.observations.clone().requires_grad_(True)
    weights.requires_grad_(True)
    scale = torch.tensor(HUBER_SCALE, dtype=torch.float64, requires_grad=True)
    problem = _problem(scene, init, observations, weights, HuberLoss(scale) if robust else None)
    inputs = [observations, weights, problem.pose_tangent] + ([scale] if robust else [])
    implicit = _gradients(problem, inputs, "implicit")
    unrolled = _gradients(problem, inputs, "unrolled")
    names = ["observations", "weights", "pose_tangent", "scale"][: len(inputs)]
    for name, a, b in zip(names, implicit, unrolled, strict=True):
        assert _relative(a, b) <= 1e-6, name
    # Moving the gauge pose 0 moves the whole solution; the free initial poses do not matter.
    assert implicit[2][:, 0].abs().amax() > 1.0
    assert implicit[2][:, 1:].abs().amax() == 0.0


@pytest.mark.parametrize("backward", ["implicit", "unrolled"])
def test_gradients_equal_central_differences(backward):
    scene, init, weights = _setup(outlier_fraction=0.05)
    observations = scene.observations.clone().requires_grad_(True)
    weights.requires_grad_(True)
    scale = torch.tensor(HUBER_SCALE, dtype=torch.float64, requires_grad=True)
    problem = _problem(scene, init, observations, weights, HuberLoss(scale))
    grad_obs, grad_w, grad_scale = _gradients(problem, [observations, weights, scale], backward)

    def objective(obs: Tensor, w: Tensor, a: Tensor) -> float:
        p = _problem(scene, init, obs, w, HuberLoss(a))
        result = solve_tensors(p.pose_tangent, p.points, p.data, CONVERGED)
        # Where LM stops is decided by its cost comparisons, i.e. by the machine's rounding
        # (a last step from 1e-4 or from 1e-6 away lands 1e-8 or 1e-12 from x*); a few
        # Gauss-Newton steps (no comparisons; contraction ≤ 1/3 per step here) take every
        # perturbed solve to x* within ~1e-12, so the stencil below sees only the function.
        result = solve_tensors(result.pose_tangent, result.points, p.data, POLISH)
        return float(_objective(result.pose_tangent, result.points).sum())

    h = 1e-3  # see CONVERGED
    base = (observations.detach(), weights.detach(), scale.detach())
    checks = [(0, (0, 5, 0)), (0, (1, 17, 2)), (1, (0, 3)), (1, (1, 20)), (2, ())]
    analytic = (grad_obs, grad_w, grad_scale)
    for which, index in checks:
        values = {}
        for step in (-2, -1, 1, 2):
            args = [t.clone() for t in base]
            args[which][index] += step * h
            values[step] = objective(*args)
        numeric = (8 * (values[1] - values[-1]) - (values[2] - values[-2])) / (12 * h)
        exact = float(analytic[which][index])
        assert abs(numeric - exact) <= 1e-6 * max(abs(exact), 1.0), (which, index, numeric, exact)


@pytest.mark.parametrize("backward", ["implicit", "unrolled"])
def test_batched_gradient_equals_per_problem(backward):
    scene, init, weights = _setup(batch_size=3, outlier_fraction=0.05)
    observations = scene.observations.clone().requires_grad_(True)
    weights.requires_grad_(True)
    loss = HuberLoss(HUBER_SCALE)
    batched = _gradients(
        _problem(scene, init, observations, weights, loss), [observations, weights], backward
    )
    for b in range(3):
        # Problem b alone (B = 1); its gradient lands in row b of full-size leaves.
        obs = scene.observations.clone().requires_grad_(True)
        w = weights.detach().clone().requires_grad_(True)
        single = _problem(scene, init, obs, w, loss, slice(b, b + 1))
        grad_obs, grad_w = _gradients(single, [obs, w], backward)
        assert torch.allclose(batched[0][b], grad_obs[b], rtol=1e-8, atol=1e-10)
        assert torch.allclose(batched[1][b], grad_w[b], rtol=1e-8, atol=1e-10)


def test_none_mode_returns_detached_results():
    scene, init, weights = _setup()
    weights.requires_grad_(True)
    problem = _problem(scene, init, scene.observations, weights)
    result = solve_differentiable(
        problem.pose_tangent, problem.points, problem.data, backward="none"
    )
    for t in (result.pose_tangent, result.points, result.final_cost):
        assert not t.requires_grad and t.grad_fn is None
    reference = solve_tensors(problem.pose_tangent, problem.points, problem.data)
    assert torch.equal(result.pose_tangent, reference.pose_tangent)


def test_truncated_with_every_iteration_equals_unrolled():
    scene, init, weights = _setup(outlier_fraction=0.05)
    weights.requires_grad_(True)
    problem = _problem(scene, init, scene.observations, weights, HuberLoss(HUBER_SCALE))
    inputs = [weights, problem.pose_tangent, problem.points]
    config = SolverConfig()
    unrolled = _gradients(problem, inputs, "unrolled", config)
    truncated = _gradients(problem, inputs, "truncated", config, truncate_steps=10**6)
    for a, b in zip(truncated, unrolled, strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-14)
    # Fewer steps: no gradient to the (free) initial guess, and the weight gradient approaches
    # the implicit one as the window grows.
    implicit = _gradients(problem, inputs, "implicit", config)
    errors = []
    for k in (1, 3, 6):
        grad_w, _, grad_points = _gradients(problem, inputs, "truncated", config, truncate_steps=k)
        assert grad_points is None or grad_points.abs().amax() == 0.0
        errors.append(_relative(grad_w, implicit[0]))
    assert errors[0] > errors[1] > errors[2]


def test_unrolled_forward_matches_the_solver():
    scene, init, weights = _setup(outlier_fraction=0.05)
    problem = _problem(scene, init, scene.observations, weights, HuberLoss(HUBER_SCALE))
    for config in (SolverConfig(), SolverConfig(algorithm="gauss_newton"), CONVERGED):
        reference = solve_tensors(problem.pose_tangent, problem.points, problem.data, config)
        result = solve_differentiable(
            problem.pose_tangent, problem.points, problem.data, config, backward="unrolled"
        )
        assert result.status == reference.status
        assert torch.equal(result.iterations, reference.iterations)
        assert torch.allclose(result.cost_history, reference.cost_history, rtol=1e-12, atol=0)
        # The unrolled loop runs torch's products (autograd), the solver NumPy's: round-off
        # apart. Stopped at the default tolerances the steps are still far above that noise,
        # so the iterates agree to it. Run to convergence (CONVERGED) the last steps are the
        # noise itself: both iterates lie where the cost is flat to its round-off, within
        # √(ε·F/λ_min(H)) of the minimizer (H the exact Hessian there).
        bound = torch.full_like(reference.final_cost, 1e-12)
        if config is CONVERGED:
            with torch.no_grad():
                lin = exact_hessian(reference.pose_tangent, reference.points, problem.data)
                lam_min = torch.linalg.eigvalsh(dense_hessian(lin, problem.data))[:, 0]
            eps = torch.finfo(torch.float64).eps
            bound = 4 * torch.sqrt(eps * reference.final_cost / lam_min)
        difference = (result.pose_tangent - reference.pose_tangent).abs().flatten(1).amax(-1)
        assert bool((difference <= bound).all())


def test_information_matrices_implicit_equals_unrolled():
    # Full 3×3 information goes through the block linearization and the pair-wise Schur path.
    scene, init, _ = _setup(outlier_fraction=0.0)
    gen = torch.Generator().manual_seed(7)
    A = torch.randn(*scene.valid.shape, 3, 3, generator=gen, dtype=torch.float64)
    information = (A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=torch.float64)).div(3.0)
    information.requires_grad_(True)
    problem = _problem(scene, init, scene.observations, information)
    assert problem.data.information is not None
    implicit = _gradients(problem, [information], "implicit")[0]
    unrolled = _gradients(problem, [information], "unrolled")[0]
    assert _relative(implicit, unrolled) <= 1e-6


def test_implicit_and_unrolled_backward_with_the_dense_solver():
    # The dense linear solver is a cross-check of the Schur path, in the backward too.
    scene, init, weights = _setup(outlier_fraction=0.05)
    weights.requires_grad_(True)
    problem = _problem(scene, init, scene.observations, weights, HuberLoss(HUBER_SCALE))
    dense = SolverConfig(linear_solver="dense", function_tolerance=1e-14, gradient_tolerance=1e-14)
    forward, implicit = {}, {}
    for name, config in (("schur", CONVERGED), ("dense", dense)):
        result = solve_differentiable(
            problem.pose_tangent, problem.points, problem.data, config, backward="implicit"
        )
        loss = _objective(result.pose_tangent, result.points).sum()
        implicit[name] = torch.autograd.grad(loss, [weights])[0]
        forward[name] = torch.cat(
            (result.pose_tangent.detach().flatten(1), result.points.detach().flatten(1)), 1
        )
    # The two forward solves stop where LM's accept test stops seeing decreases, at points a
    # machine's rounding decides (~1e-10 apart relative; identical on some CPUs). The implicit
    # gradient −∂L/∂x·H⁻¹·∂g/∂w at x moves with x by up to cond(H) times the relative change
    # of x (through H⁻¹), so that is the accuracy to which the two backward passes can agree.
    dx = float((forward["dense"] - forward["schur"]).norm() / forward["schur"].norm())
    at_solution = _problem(scene, init, scene.observations, weights.detach(), loss=None)
    with torch.no_grad():
        at_solution.pose_tangent.copy_(
            forward["schur"][:, : 6 * scene.num_poses].view_as(at_solution.pose_tangent)
        )
        at_solution.points.copy_(
            forward["schur"][:, 6 * scene.num_poses :].view_as(at_solution.points)
        )
        J = at_solution.dense_jacobian()
    free = torch.ones(J.shape[-1], dtype=torch.bool)
    free[:6] = False  # the gauge pose
    H = J[..., free].transpose(-1, -2) @ J[..., free]
    eigenvalues = torch.linalg.eigvalsh(H)
    condition = float((eigenvalues[..., -1] / eigenvalues[..., 0]).max())
    assert condition < 1e6  # a well-posed problem: the bound below stays meaningful
    assert _relative(implicit["dense"], implicit["schur"]) <= 1e-9 + condition * dx
    unrolled_schur = _gradients(problem, [weights], "unrolled")[0]
    unrolled_dense = _gradients(problem, [weights], "unrolled", dense)[0]
    # Unrolled: the same iteration map, but whether a last round-off-sized step is accepted is
    # decided by the machine's rounding, and each extra iteration moves the unrolled derivative
    # toward the implicit one (a contraction). So the two differ by at most their own distance
    # to the implicit gradient (~7e-7 here), plus round-off.
    gap = max(
        _relative(unrolled_schur, implicit["schur"]), _relative(unrolled_dense, implicit["dense"])
    )
    assert gap < 1e-5  # the unrolled derivative has converged: a meaningful comparison
    assert _relative(unrolled_dense, unrolled_schur) <= 1e-8 + gap


def test_gradients_reach_a_weight_model():
    scene, init, _ = _setup(outlier_fraction=0.05)
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 1, dtype=torch.float64)
    params = list(model.parameters())

    def model_gradients(backward: str) -> tuple[Tensor, ...]:
        weights = torch.nn.functional.softplus(model(scene.observations))[..., 0]
        problem = _problem(scene, init, scene.observations, weights)
        return _gradients(problem, params, backward)

    implicit = model_gradients("implicit")
    unrolled = model_gradients("unrolled")
    for a, b in zip(implicit, unrolled, strict=True):
        assert b.abs().amax() > 0
        assert _relative(a, b) <= 1e-6


def test_gauss_newton_hessian_is_exact_without_residuals():
    # With zero residuals at the solution JᵀJ is the exact Hessian; with noise it is not.
    for noise, exact in ((0.0, True), (0.01, False)):
        scene, init, weights = _setup(noise_std=noise)
        observations = scene.observations.clone().requires_grad_(True)
        problem = _problem(scene, init, observations, weights)
        full = _gradients(problem, [observations], "implicit")[0]
        gn = _gradients(
            problem,
            [observations],
            "implicit",
            implicit=ImplicitConfig(hessian="gauss_newton"),
        )[0]
        assert (_relative(gn, full) <= 1e-9) == exact


def test_final_cost_is_differentiable():
    scene, init, weights = _setup()
    weights.requires_grad_(True)
    problem = _problem(scene, init, scene.observations, weights)
    grads = []
    for backward in ("implicit", "unrolled"):
        result = solve_differentiable(
            problem.pose_tangent, problem.points, problem.data, CONVERGED, backward=backward
        )
        grads.append(torch.autograd.grad(result.final_cost.sum(), weights)[0])
    # Envelope theorem: dF*/dw = ∂F/∂w = ½ ‖r*‖² per observation.
    assert _relative(grads[0], grads[1]) <= 1e-6


def test_bad_arguments():
    scene, init, weights = _setup()
    problem = _problem(scene, init, scene.observations, weights)
    args = (problem.pose_tangent, problem.points, problem.data)
    with pytest.raises(ValueError, match="'backward' must be one of"):
        solve_differentiable(*args, backward="adjoint")
    with pytest.raises(ValueError, match="'truncate_steps' must be ≥ 1"):
        solve_differentiable(*args, backward="truncated", truncate_steps=0)
    with pytest.raises(ValueError, match="to match 'data'"):
        solve_differentiable(problem.pose_tangent[:, :2], problem.points, problem.data)
    with pytest.raises(ValueError, match="'hessian' must be one of"):
        ImplicitConfig(hessian="bfgs")
