"""The implicit backward's exact Hessian (issue 16): assembled in the forward's block structure
it equals autograd's Hessian of the cost in the chart; its one factorization gives the same
gradient as the former conjugate-gradient backward and as central differences of the whole
solve; a problem whose Hessian does not factor falls back to conjugate gradients on its own."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from torch import Tensor

from torchslam import CauchyLoss, HuberLoss, PointMapProblem, SolverConfig, solve_tensors
from torchslam._checks import validation
from torchslam.data import make_scene
from torchslam.initialization import initialize_scene
from torchslam.lie import se3
from torchslam.losses import RobustLoss
from torchslam.manifold import SE3Matrix
from torchslam.objective.data import PointMapData, cost_from_poses
from torchslam.objective.terms import PointObservationTerm, PosePriorTerm, RelativePoseTerm
from torchslam.solver import differentiable
from torchslam.solver.differentiable import solve_differentiable
from torchslam.solver.hessian import dense_hessian, exact_hessian
from torchslam.solver.plan import LinearPlan

from . import CONVERGED, POLISH, downstream_objective

F64 = torch.float64
# The relative-pose term's kernel (Cauchy: ρ'' ≠ 0 everywhere).
TERM_LOSS = CauchyLoss(0.05)
# CONVERGED and POLISH (tests.solver), as in test_gradients.py: LM to round-off, then
# Gauss-Newton polishing for the finite differences (no cost comparisons, so every perturbed
# solve lands on its minimum).


def _problem(
    loss=None,
    information: bool = False,
    terms: bool = True,
    point_term: bool = True,
    term_loss: RobustLoss | None = TERM_LOSS,
    observations: Tensor | None = None,
    weights: Tensor | None = None,
    batch_size: int = 2,
    seed: int = 3,
) -> PointMapProblem:
    """4 poses, 10 points, 10% outliers; random weights or information matrices; a relative
    pose term (Cauchy), a pose prior and (``point_term``) a point-observation term with point
    5 fixed; the last observation slot of problem 0 is padding holding NaN."""
    scene = make_scene(
        4,
        10,
        batch_size=batch_size,
        visible_fraction=0.75,
        outlier_fraction=0.1,
        noise_std=0.01,
        seed=seed,
    )
    init = initialize_scene(
        scene, method="odometry", rotation_noise_deg=3.0, translation_noise=0.03, seed=seed
    )
    gen = torch.Generator().manual_seed(seed)
    B = batch_size
    obs = scene.observations.clone() if observations is None else observations
    valid = scene.valid.clone()
    valid[0, -1] = False
    if observations is None:
        obs[0, -1] = float("nan")
    if weights is None:
        if information:
            A = torch.randn(*valid.shape, 3, 3, generator=gen, dtype=F64)
            weights = (A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=F64)) / 3.0
        else:
            weights = 0.5 + torch.rand(valid.shape, generator=gen, dtype=F64)
    term_list = []
    if terms:
        noise = se3.exp(0.01 * torch.randn(B, 2, 6, generator=gen, dtype=F64))
        gt = scene.poses_gt
        Z = gt[:, [0, 1]] @ se3.inverse(gt[:, [1, 3]]) @ noise
        term_list = [
            RelativePoseTerm(
                torch.tensor([[0, 1], [1, 3]]).expand(B, 2, 2),
                Z,
                weight=torch.full((B, 2), 5.0, dtype=F64),
                loss=term_loss,
            ),
            PosePriorTerm(torch.tensor([2]).expand(B, 1), scene.poses_gt[:, [2]] @ noise[:, :1]),
        ]
        if point_term:
            term_list.append(
                PointObservationTerm(
                    torch.tensor([1, 2]).expand(B, 2),
                    torch.tensor([3, 4]).expand(B, 2),
                    0.1 * torch.randn(B, 2, 3, generator=gen, dtype=F64),
                    weight=torch.full((B, 2), 2.0, dtype=F64),
                )
            )
    return PointMapProblem(
        init.poses,
        init.points,
        scene.pose_index,
        scene.point_index,
        obs,
        valid=valid,
        weights=weights,
        loss=loss,
        terms=term_list,
        fixed_points=(torch.arange(10).expand(B, 10) == 5) if point_term else None,
    )


def _single(data: PointMapData, b: int) -> PointMapData:
    """Problem b of ``data`` alone (B = 1)."""
    pick = lambda t: t[b : b + 1]  # noqa: E731
    changes = {
        f.name: pick(getattr(data, f.name))
        for f in dataclasses.fields(data)
        if isinstance(getattr(data, f.name), Tensor)
    }
    terms = tuple(t.apply(lambda v: v[b : b + 1] if v.dim() > 0 else v) for t in data.terms)
    return dataclasses.replace(data, terms=terms, **changes)


@pytest.mark.parametrize(
    "loss,information",
    [(HuberLoss(0.02), False), (CauchyLoss(0.02), True), (None, False)],
    ids=["huber-weights", "cauchy-information", "least-squares"],
)
def test_exact_hessian_equals_autograd_hessian_in_the_chart(loss, information):
    problem = _problem(loss, information)
    data = problem.data
    # A few iterations: residuals of every size, Huber/Cauchy beyond their knee.
    result = solve_tensors(
        problem.pose_tangent, problem.points, data, SolverConfig(max_iterations=3)
    )
    xi, X = result.pose_tangent, result.points
    with validation(False):
        lin = exact_hessian(xi, X, data)
        H = dense_hessian(lin, data)
    assert torch.isfinite(H).all()  # the NaN padding stays out
    m, n = data.num_poses, data.num_points
    for b in range(2):
        one = _single(data, b)
        T0 = se3.exp(xi[b : b + 1], form="fast")

        def chart_cost(z: Tensor, one=one, T0=T0, b=b) -> Tensor:
            with validation(False):
                T = SE3Matrix().plus(T0, z[: 6 * m].reshape(1, m, 6))
            return cost_from_poses(T, X[b : b + 1] + z[6 * m :].reshape(1, n, 3), one).sum()

        z0 = torch.zeros(6 * m + 3 * n, dtype=F64)
        _ = one.flat_pose_index, one.flat_point_index  # cached outside the vmap below
        reference = torch.autograd.functional.hessian(chart_cost, z0, vectorize=True)
        gradient = torch.autograd.functional.jacobian(chart_cost, z0)
        free = torch.cat(
            (
                ~data.fixed_poses[b].repeat_interleave(6),
                ~data.fixed_points[b].repeat_interleave(3),
            )
        )
        # Both sides sum the same O(1)-sized products of ~30 terms per entry in float64:
        # they agree to a few ulps of the largest entry (measured ≤ 6e-16 relative).
        scale = float(reference.abs().max())
        error = (H[b][free][:, free] - reference[free][:, free]).abs().max()
        assert float(error) <= 1e-12 * scale
        ours = torch.cat((lin.pose_gradient[b].flatten(), lin.point_gradient[b].flatten()))
        assert float((ours[free] - gradient[free]).abs().max()) <= 1e-12 * scale
        # Fixed variables: identity blocks, no coupling, zero gradient.
        fixed = ~free
        assert torch.equal(H[b][fixed][:, fixed], torch.eye(int(fixed.sum()), dtype=F64))
        assert not H[b][fixed][:, free].any()
        assert not ours[fixed].any()
    if loss is None:
        return
    # ρ'' enters exactly: dropping it (the Triggs corrector's regime) changes H.
    with validation(False):
        H_no_rho2 = dense_hessian(
            exact_hessian(xi, X, dataclasses.replace(data, loss=_WithoutCurvature(loss))), data
        )
    assert float((H_no_rho2 - H).abs().max()) > 1e-6 * float(H.abs().max())


class _WithoutCurvature(RobustLoss):
    """A kernel's ρ and ρ' with ρ'' = 0 (a deliberately wrong second derivative)."""

    def __init__(self, loss: RobustLoss) -> None:
        self.loss = loss

    def _evaluate(self, fn: str, s: Tensor):
        rho, rho1, rho2 = self.loss(s)
        return rho, rho1, torch.zeros_like(rho2)


def test_coupling_gemm_factorization_equals_pair_products():
    # Information matrices and terms (pose pairs, point terms): the general block form.
    problem = _problem(HuberLoss(0.05), information=True)
    data = problem.data
    result = solve_tensors(
        problem.pose_tangent, problem.points, data, SolverConfig(max_iterations=3)
    )
    with validation(False):
        lin = exact_hessian(result.pose_tangent, result.points, data)
        plan = LinearPlan.build(data, SolverConfig(reduced_solver="dense"))
        lam = torch.zeros(2, dtype=F64)
        pairs = plan.factorize(lin, lam)
        gemm = plan.factorize_coupling_gemm(lin, lam)
    assert plan.coupling_gemm_pays()  # 75% co-visibility
    assert bool(pairs.ok.all()) and bool(gemm.ok.all())
    gen = torch.Generator().manual_seed(0)
    g = (
        torch.randn(2, 4, 6, generator=gen, dtype=F64),
        torch.randn(2, 10, 3, generator=gen, dtype=F64),
    )
    for a, b in zip(pairs.solve(*g), gemm.solve(*g), strict=True):
        # The same matrix summed in another order: round-off times cond(H) ≲ 1e4 here.
        assert float((a - b).abs().max()) <= 1e-9 * float(a.abs().max())


def _force_conjugate_gradients(monkeypatch) -> None:
    """The former backward: every problem takes the conjugate-gradient path."""

    def never(plan, data, xi, X, v, config):
        ok = torch.zeros(xi.shape[0], dtype=torch.bool)
        return (torch.zeros_like(v[0]), torch.zeros_like(v[1])), ok

    monkeypatch.setattr(differentiable, "_exact_solve", never)


def _implicit_gradients(information: bool, **options) -> tuple[Tensor, ...]:
    problem = _problem(HuberLoss(0.05), information, point_term=False)
    observations = problem.data.observations.detach().clone().requires_grad_(True)
    weighting = "information" if information else "weights"
    weights = getattr(problem.data, weighting).detach().clone().requires_grad_(True)
    data = dataclasses.replace(problem.data, observations=observations, **{weighting: weights})
    result = solve_differentiable(problem.pose_tangent, problem.points, data, CONVERGED, **options)
    assert all(result.converged)
    loss = downstream_objective(result.pose_tangent, result.points).sum()
    return torch.autograd.grad(loss, (observations, weights))


def test_direct_backward_equals_conjugate_gradients(monkeypatch):
    # (Information matrices: the exact Hessian is checked above; their LM solve of this
    # problem is too slow to converge for a unit test.)
    direct = _implicit_gradients(False)
    _force_conjugate_gradients(monkeypatch)
    cg = _implicit_gradients(False)
    for a, b in zip(direct, cg, strict=True):
        assert torch.isfinite(a).all()
        # CG stops at ‖Hw − v‖ ≤ 1e-10‖v‖, so its w is within cond(H)·1e-10 ≲ 1e-6 (cond(H)
        # ≲ 1e4 for these problems) of the direct solve, which is exact to round-off·cond(H).
        assert float((a - b).norm() / b.norm()) <= 1e-6


def test_direct_backward_equals_central_differences():
    # Weights, Huber on the points, a relative-pose term and a prior. (No Cauchy term here:
    # the Gauss-Newton polish below contracts too slowly on it for the stencil's 1e-12.)
    problem = _problem(HuberLoss(0.05), batch_size=1, seed=5, point_term=False, term_loss=None)
    base_obs = problem.data.observations.detach()
    base_w = problem.data.weights.detach()
    observations = base_obs.clone().requires_grad_(True)
    weights = base_w.clone().requires_grad_(True)
    data = dataclasses.replace(problem.data, observations=observations, weights=weights)
    result = solve_differentiable(problem.pose_tangent, problem.points, data, CONVERGED)
    loss = downstream_objective(result.pose_tangent, result.points).sum()
    grad_obs, grad_w = torch.autograd.grad(loss, (observations, weights))

    def objective(obs: Tensor, w: Tensor) -> float:
        d = dataclasses.replace(problem.data, observations=obs, weights=w)
        r = solve_tensors(problem.pose_tangent, problem.points, d, CONVERGED)
        r = solve_tensors(r.pose_tangent, r.points, d, POLISH)
        return float(downstream_objective(r.pose_tangent, r.points).sum())

    # h = 1e-3 (4-point stencil, truncation ~h⁴, solution noise ~1e-12/h): gradients to ~1e-7.
    h = 1e-3
    for which, index in [(0, (0, 5, 0)), (0, (0, 17, 2)), (1, (0, 3)), (1, (0, 20))]:
        values = {}
        for step in (-2, -1, 1, 2):
            args = [base_obs.clone(), base_w.clone()]
            args[which][index] += step * h
            values[step] = objective(*args)
        numeric = (8 * (values[1] - values[-1]) - (values[2] - values[-2])) / (12 * h)
        exact = float((grad_obs, grad_w)[which][index])
        assert abs(numeric - exact) <= 1e-6 * max(abs(exact), 1.0), (which, index, numeric, exact)


def test_fallback_is_per_problem(monkeypatch):
    # Problem 1 stops after 1 iteration from a far start with Cauchy terms: its exact Hessian
    # is indefinite (no minimum), so it takes the conjugate-gradient fallback; problem 0
    # converges and keeps its direct solve, the same as alone.
    problem = _problem(CauchyLoss(0.02), batch_size=2, point_term=False)
    data = problem.data
    with torch.no_grad():
        start = solve_tensors(problem.pose_tangent, problem.points, data, CONVERGED)
    xi0 = torch.stack((start.pose_tangent[0], problem.pose_tangent[1]))
    X0 = torch.stack((start.points[0], problem.points[1]))
    config = SolverConfig(max_iterations=1, function_tolerance=1e-14, gradient_tolerance=1e-14)
    with validation(False):
        one_step = solve_tensors(xi0, X0, data, config)
        H = exact_hessian(one_step.pose_tangent, one_step.points, data)
        ok = LinearPlan.build(data, config).factorize(H, torch.zeros(2, dtype=F64)).ok
    assert ok.tolist() == [True, False]

    def gradient(d: PointMapData, xi: Tensor, X: Tensor) -> Tensor:
        observations = d.observations.detach().clone().requires_grad_(True)
        d = dataclasses.replace(d, observations=observations)
        result = solve_differentiable(xi, X, d, config, on_unconverged="implicit")
        loss = downstream_objective(result.pose_tangent, result.points).sum()
        return torch.autograd.grad(loss, observations)[0]

    batched = gradient(data, xi0, X0)
    assert torch.isfinite(batched).all()
    alone = gradient(_single(data, 0), xi0[:1], X0[:1])
    assert torch.allclose(batched[0], alone[0], rtol=1e-10, atol=1e-12)
    _force_conjugate_gradients(monkeypatch)
    cg = gradient(data, xi0, X0)
    assert torch.allclose(batched[1], cg[1], rtol=1e-10, atol=1e-12)
    # (Problem 0 through conjugate gradients agrees only to the CG tolerance.)
    assert float((batched[0] - cg[0]).norm() / cg[0].norm()) <= 1e-6
