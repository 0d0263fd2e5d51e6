"""Linear algebra and linearization paths: the Schur steps (structured and block) equal the
dense step and solve the damped normal equations of the dense Jacobian; analytic and jacrev
Jacobians give the same iterates; scalar and information weights agree."""

from __future__ import annotations

import pytest
import torch

import torchslam
from torchslam import SolverConfig
from torchslam.solver import plan as plan_module
from torchslam.solver.linearize import (
    BlockLinearization,
    StructuredLinearization,
    linearize,
    whitening_factors,
)

from . import (
    TIGHT,
    drifted,
    ground_truth_errors,
    problem_from,
    solution_distance,
    solution_distance_bound,
    solve_step,
)

LAMBDAS = (0.0, 1e-3, 10.0)
STEP_TOL = 1e-10


def _problem(weighting: str, *, loss=None, fixed_points: bool = False, noise_std: float = 0.01):
    """A noisy, drifted batch of two problems with the requested weighting."""
    scene, init = drifted(6, 40, noise_std=noise_std, outlier_fraction=0.05, seed=7)
    gen = torch.Generator().manual_seed(11)
    shape = scene.valid.shape
    weights = None
    if weighting == "scalar":
        weights = 0.5 + torch.rand(shape, generator=gen, dtype=torch.float64)
    elif weighting == "information":
        A = torch.randn(*shape, 3, 3, generator=gen, dtype=torch.float64)
        weights = A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=torch.float64)
    fixed = None
    if fixed_points:
        fixed = torch.zeros(scene.batch_size, scene.num_points, dtype=torch.bool)
        fixed[:, ::7] = True
    problem = problem_from(
        scene, init.poses, init.points, weights=weights, fixed_points=fixed, loss=loss
    )
    return scene, init, problem


def _lam(value: float, batch_size: int) -> torch.Tensor:
    return torch.full((batch_size,), value, dtype=torch.float64)


CASES = [
    pytest.param("unit", None, False, id="unit"),
    pytest.param("scalar", None, False, id="scalar"),
    pytest.param("unit", None, True, id="fixed-points"),
    pytest.param("unit", torchslam.HuberLoss(0.02), False, id="huber"),
    pytest.param("scalar", torchslam.CauchyLoss(0.02), False, id="cauchy"),
    pytest.param("unit", torchslam.TukeyLoss(0.05), False, id="tukey"),
    pytest.param("information", None, False, id="information"),
]


@pytest.mark.parametrize(("weighting", "loss", "fixed_points"), CASES)
@pytest.mark.parametrize("damping", ["marquardt", "levenberg"])
def test_schur_and_dense_paths_give_the_same_step(weighting, loss, fixed_points, damping):
    _, _, problem = _problem(weighting, loss=loss, fixed_points=fixed_points)
    data = problem.data
    xi, X = problem.pose_tangent.detach(), problem.points.detach()
    factor = whitening_factors(data)
    block = linearize(xi, X, data, factor, structured=False)
    assert isinstance(block, BlockLinearization)
    structured = linearize(xi, X, data, factor, structured=True)
    # The fast path is taken exactly when the weights are scalar.
    assert isinstance(structured, StructuredLinearization) == (weighting != "information")
    torch.testing.assert_close(structured.cost, block.cost, rtol=1e-13, atol=0)
    for value in LAMBDAS:
        lam = _lam(value, problem.batch_size)
        dp_d, dl_d, ok_d = solve_step(block, data, lam, damping, "dense")
        # Undamped Tukey systems are singular here (a point whose views are all beyond the
        # scale has ρ' = 0 everywhere); every other system is positive definite.
        assert bool(ok_d.all()) or (value == 0 and isinstance(loss, torchslam.TukeyLoss))
        if bool(ok_d.any()):
            assert float(dp_d[ok_d].abs().max()) > 1e-3  # a real step, not a trivial one
        for lin in (block, structured):
            dp, dl, ok = solve_step(lin, data, lam, damping, "schur")
            assert torch.equal(ok, ok_d)
            torch.testing.assert_close(dp[ok], dp_d[ok], rtol=0, atol=STEP_TOL)
            torch.testing.assert_close(dl[ok], dl_d[ok], rtol=0, atol=STEP_TOL)
        # Fixed variables do not move.
        assert torch.all(dp_d[data.fixed_poses] == 0)
        assert torch.all(dl_d[data.fixed_points] == 0)


@pytest.mark.parametrize("weighting", ["unit", "scalar", "information"])
@pytest.mark.parametrize("damping", ["marquardt", "levenberg"])
def test_step_solves_the_damped_normal_equations_of_the_dense_jacobian(weighting, damping):
    # An independent reference: H = JᵀJ and g = Jᵀr from problem.dense_jacobian() and
    # problem.residuals() (whitened), restricted to the free variables (pose 0 is the gauge).
    _, _, problem = _problem(weighting)
    data = problem.data
    J = problem.dense_jacobian().detach()
    r = problem.residuals().detach().reshape(problem.batch_size, -1)
    factor = whitening_factors(data)
    lin = linearize(problem.pose_tangent.detach(), problem.points.detach(), data, factor)
    m = problem.num_poses
    for b in range(problem.batch_size):
        free = torch.cat(
            (
                (~data.fixed_poses[b]).repeat_interleave(6),
                (~data.fixed_points[b]).repeat_interleave(3),
            )
        )
        Jb = J[b][:, free]
        H = Jb.T @ Jb
        g = Jb.T @ r[b]
        for value in LAMBDAS:
            lam = _lam(value, problem.batch_size)
            if damping == "levenberg":
                D = torch.eye(H.shape[0], dtype=H.dtype)
            else:
                D = torch.diag(H.diagonal().clamp(1e-6, 1e32))
            for solver in ("schur", "dense"):
                dp, dl, ok = solve_step(
                    lin
                    if solver == "schur"
                    else linearize(
                        problem.pose_tangent.detach(),
                        problem.points.detach(),
                        data,
                        factor,
                        structured=False,
                    ),
                    data,
                    lam,
                    damping,
                    solver,
                )
                assert bool(ok.all())
                delta = torch.cat((dp[b].reshape(-1), dl[b].reshape(-1)))[free]
                residual = (H + value * D) @ delta + g
                assert float(residual.abs().max()) <= 1e-10 * float(g.abs().max())
        # The solver's gradient is Jᵀr of the dense Jacobian.
        gradient = torch.cat((lin.pose_gradient[b].reshape(-1), lin.point_gradient[b].reshape(-1)))
        torch.testing.assert_close(gradient[free], g, rtol=0, atol=1e-11 * float(g.abs().max()))
        assert torch.all(gradient[: 6 * m][~free[: 6 * m]] == 0)


def test_block_schur_chunking_does_not_change_the_step():
    _, _, problem = _problem("information")
    data = problem.data
    lin = linearize(
        problem.pose_tangent.detach(), problem.points.detach(), data, whitening_factors(data)
    )
    structure = plan_module.PairStructure.build(
        plan_module.coupling_edges(data), data.num_poses, data.num_points
    )
    lam = _lam(1e-3, problem.batch_size)
    whole = solve_step(lin, data, lam, "marquardt", chunk_size=1 << 20)
    chunked = solve_step(lin, data, lam, "marquardt", chunk_size=7)
    assert structure.num_pairs > 7
    for a, b in zip(whole, chunked, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-13)


@pytest.mark.parametrize("weighting", ["unit", "information"])
def test_schur_and_dense_solvers_reach_the_same_solution(weighting):
    results, problems = {}, {}
    for solver in ("schur", "dense"):
        problem = problems[solver] = _problem(weighting)[2]
        results[solver] = torchslam.solve(problem, SolverConfig(linear_solver=solver, **TIGHT))
        assert all(results[solver].converged), results[solver].summary()
    schur, dense = results["schur"], results["dense"]
    # Same iterates while the cost is far above round-off, same minimum at the end.
    torch.testing.assert_close(
        schur.cost_history[:, :4], dense.cost_history[:, :4], rtol=1e-10, atol=0
    )
    torch.testing.assert_close(schur.final_cost, dense.final_cost, rtol=1e-12, atol=0)
    # Same minimizer, to the accuracy the problem's conditioning defines it: each solution is
    # within a Newton step plus the gradient's round-off floor of x* (solution_distance_bound),
    # so they are within the sum of both bounds of each other, on any machine.
    for b in range(problems["schur"].batch_size):
        bound = solution_distance_bound(problems["schur"], b) + solution_distance_bound(
            problems["dense"], b
        )
        # LM stops where its accept test can no longer see a decrease (ΔF ≈ ε·F), about a
        # Newton step (~1e-7 here) short of x*, at a point the machine's rounding decides:
        # the two solutions agree to that bound, not to round-off.
        assert bound < 1e-5  # still a meaningful comparison (poses and points are O(1))
        assert solution_distance(problems["schur"], problems["dense"], b) <= bound


@pytest.mark.parametrize("weighting", ["unit", "information"])
def test_analytic_and_jacrev_jacobians_give_the_same_iterates(weighting):
    # With unit weights the analytic mode takes the structured path and jacrev the block
    # path; with information matrices both take the block path.
    problem = _problem(weighting)[2]
    for iterations in (1, 2, 3):
        results = {
            mode: torchslam.solve_tensors(
                problem.pose_tangent,
                problem.points,
                problem.data,
                SolverConfig(jacobian=mode, max_iterations=iterations, **_stop_never()),
            )
            for mode in ("analytic", "jacrev")
        }
        analytic, jacrev = results["analytic"], results["jacrev"]
        assert analytic.iterations.tolist() == [iterations] * problem.batch_size
        torch.testing.assert_close(analytic.cost_history, jacrev.cost_history, rtol=1e-12, atol=0)
        torch.testing.assert_close(
            analytic.lambda_history, jacrev.lambda_history, rtol=1e-12, atol=0
        )
        torch.testing.assert_close(analytic.pose_tangent, jacrev.pose_tangent, rtol=0, atol=1e-12)
        torch.testing.assert_close(analytic.points, jacrev.points, rtol=0, atol=1e-12)
    final = {
        mode: torchslam.solve_tensors(
            problem.pose_tangent, problem.points, problem.data, SolverConfig(jacobian=mode)
        )
        for mode in ("analytic", "jacrev")
    }
    assert all(final["jacrev"].converged), final["jacrev"].summary()
    torch.testing.assert_close(
        final["analytic"].final_cost, final["jacrev"].final_cost, rtol=1e-12, atol=0
    )
    torch.testing.assert_close(
        final["analytic"].pose_tangent, final["jacrev"].pose_tangent, rtol=0, atol=1e-8
    )


def _stop_never() -> dict:
    return {"function_tolerance": 0.0, "gradient_tolerance": 0.0, "parameter_tolerance": 0.0}


def test_information_weights_take_the_block_path_and_converge_to_ground_truth():
    scene, init = drifted(8, 60, rotation_noise_deg=8.0)
    gen = torch.Generator().manual_seed(3)
    A = torch.randn(*scene.valid.shape, 3, 3, generator=gen, dtype=torch.float64)
    information = A @ A.transpose(-1, -2) + 0.1 * torch.eye(3, dtype=torch.float64)
    problem = problem_from(scene, init.poses, init.points, weights=information)
    lin = linearize(
        problem.pose_tangent.detach(),
        problem.points.detach(),
        problem.data,
        whitening_factors(problem.data),
    )
    assert isinstance(lin, BlockLinearization)
    result = torchslam.solve(problem, SolverConfig())
    assert all(result.converged), result.summary()
    rotation, translation, point = ground_truth_errors(result.pose_tangent, result.points, scene)
    assert max(rotation, translation, point) <= 1e-8


def test_scalar_weights_and_isotropic_information_give_the_same_solution():
    scene, init = drifted(6, 40, noise_std=0.01, rotation_noise_deg=3.0)
    gen = torch.Generator().manual_seed(4)
    w = 0.2 + 2 * torch.rand(scene.valid.shape, generator=gen, dtype=torch.float64)
    results = {}
    for name, weights in (
        ("scalar", w),
        ("information", w[..., None, None] * torch.eye(3, dtype=torch.float64)),
    ):
        problem = problem_from(scene, init.poses, init.points, weights=weights)
        results[name] = torchslam.solve(problem, SolverConfig(**TIGHT))
        assert all(results[name].converged), results[name].summary()
    scalar, information = results["scalar"], results["information"]
    torch.testing.assert_close(scalar.initial_cost, information.initial_cost, rtol=1e-14, atol=0)
    torch.testing.assert_close(
        scalar.cost_history[:, :3], information.cost_history[:, :3], rtol=1e-10, atol=0
    )
    torch.testing.assert_close(scalar.final_cost, information.final_cost, rtol=1e-12, atol=0)
    torch.testing.assert_close(scalar.poses, information.poses, rtol=0, atol=1e-9)
    torch.testing.assert_close(scalar.points, information.points, rtol=0, atol=1e-9)
    # The weights matter: unit weights give another minimum.
    unit = torchslam.solve(problem_from(scene, init.poses, init.points), SolverConfig(**TIGHT))
    assert float((unit.points - scalar.points).abs().max()) > 1e-4


@pytest.mark.parametrize("weighting", ["unit", "information"])
def test_one_gauss_newton_iteration_is_the_seed_step_on_the_manifold(weighting):
    # The seed: δ = −(JᵀJ)⁻¹Jᵀr from the dense Jacobian, poses updated as T ← T·Exp(δ)
    # (seed eq. L1), points as X ← X + δX.
    _, _, problem = _problem(weighting)
    data = problem.data
    J = problem.dense_jacobian().detach()
    r = problem.residuals().detach().reshape(problem.batch_size, -1)
    m, n = problem.num_poses, problem.num_points
    result = torchslam.solve_tensors(
        problem.pose_tangent,
        problem.points,
        data,
        SolverConfig(algorithm="gauss_newton", max_iterations=1),
    )
    for b in range(problem.batch_size):
        free = torch.cat(
            (
                (~data.fixed_poses[b]).repeat_interleave(6),
                (~data.fixed_points[b]).repeat_interleave(3),
            )
        )
        Jb = J[b][:, free]
        delta = torch.zeros(6 * m + 3 * n, dtype=torch.float64)
        delta[free] = -torch.linalg.solve(Jb.T @ Jb, Jb.T @ r[b])
        poses = problem.poses.detach()[b] @ torchslam.se3.exp(delta[: 6 * m].reshape(m, 6))
        points = problem.points.detach()[b] + delta[6 * m :].reshape(n, 3)
        torch.testing.assert_close(result.poses[b], poses, rtol=0, atol=1e-10)
        torch.testing.assert_close(result.points[b], points, rtol=0, atol=1e-10)
        assert float(delta.abs().max()) > 1e-2


@pytest.mark.parametrize("entries", [10 * 12 * 3 * 7, 10 * 12 * 3])
@pytest.mark.parametrize("small_poses", [plan_module.SMALL_POSES, 0])
def test_structured_schur_chunked_over_points_equals_one_chunk(monkeypatch, entries, small_poses):
    # Chunks of several points and of one (memory cap) give the step of the single chunk, with
    # either GEMM layout (one P Pᵀ for few poses, four products otherwise).
    from torchslam.solver.linearize import linearize

    monkeypatch.setattr(plan_module, "SMALL_POSES", small_poses)

    scene = torchslam.data.make_scene(12, 300, batch_size=3, seed=1, noise_std=0.01)
    generator = torch.Generator().manual_seed(0)
    noise = 0.02 * torch.randn(3, 12, 6, dtype=torch.float64, generator=generator)
    problem = torchslam.PointMapProblem.from_scene(
        scene, scene.poses_gt @ torchslam.se3.exp(noise), scene.points_gt + 0.01
    )
    data = problem.data
    lin = linearize(problem.pose_tangent.detach(), problem.points.detach(), data, None)
    lam = torch.full((3,), 1e-3, dtype=torch.float64)
    reference = solve_step(lin, data, lam, "marquardt")
    monkeypatch.setattr(plan_module, "STRUCTURED_CHUNK_ENTRIES", entries)
    chunked = solve_step(lin, data, lam, "marquardt")
    assert chunked[2].all()
    torch.testing.assert_close(chunked[0], reference[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(chunked[1], reference[1], rtol=0, atol=1e-12)


def test_point_block_inverse_matches_lapack_and_flags_failures():
    """The 3×3 point-block inverse (adjugate over determinant) against LAPACK's inverse on
    SPD blocks of condition up to ~1e8, and Sylvester's test against Cholesky's verdict on
    indefinite, singular and non-finite blocks (their inverse is then I)."""
    generator = torch.Generator().manual_seed(3)
    A = torch.randn(500, 3, 3, dtype=torch.float64, generator=generator)
    Q = torch.linalg.qr(A).Q
    scales = torch.logspace(0, -8, 500, dtype=torch.float64)  # smallest eigenvalue 1 … 1e-8
    eig = torch.stack((torch.ones(500, dtype=torch.float64), 0.5 + 0 * scales, scales), -1)
    V = Q @ torch.diag_embed(eig) @ Q.transpose(-1, -2)
    V = 0.5 * (V + V.transpose(-1, -2))
    V_inv, ok = plan_module.spd_inverse_3x3(V)
    reference = torch.linalg.inv(V)
    assert bool(ok.all())
    # Both inverses are accurate to ~cond·eps relative to ‖V⁻¹‖ (cond ≤ 1e8, eps 2.2e-16):
    # 1e-6 leaves two decades of margin on any IEEE machine.
    error = (V_inv - reference).abs().amax((-1, -2)) / reference.abs().amax((-1, -2))
    assert float(error.max()) < 1e-6
    assert torch.equal(V_inv, V_inv.transpose(-1, -2))  # symmetric by construction
    eye = torch.eye(3, dtype=torch.float64)
    bad = torch.stack(
        (
            -eye,
            torch.diag(torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)),
            torch.zeros(3, 3, dtype=torch.float64),
            torch.diag(torch.tensor([1.0, 1.0, float("nan")], dtype=torch.float64)),
            torch.diag(torch.tensor([1.0, 1.0, float("inf")], dtype=torch.float64)),
            2 * eye,
        )
    )
    V_inv, ok = plan_module.spd_inverse_3x3(bad)
    cholesky_ok = torch.linalg.cholesky_ex(bad[:4])[1] == 0
    assert ok.tolist() == [False, False, False, False, False, True]
    assert not bool(cholesky_ok.any())
    assert torch.equal(V_inv[:5], eye.expand(5, 3, 3))
    assert torch.allclose(V_inv[5], 0.5 * eye, rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    ("dtype", "scale"),
    [
        (torch.float32, 1e-14),
        (torch.float32, 1e13),
        (torch.float64, 1e-150),
        (torch.float64, 1e150),
    ],
)
def test_point_block_inverse_does_not_depend_on_the_blocks_scale(dtype, scale):
    """A well-conditioned SPD block scaled far from 1 (its determinant, the cube of the scale,
    would underflow or overflow the dtype): the inverse is still found and equals LAPACK's to
    the dtype's accuracy (condition ≈ 10: 1e3·eps leaves ample margin)."""
    V = torch.tensor([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]], dtype=torch.float64)
    V = (V * scale).to(dtype)
    V_inv, ok = plan_module.spd_inverse_3x3(V[None])
    reference = torch.linalg.inv(V.double())
    assert bool(ok.all())
    error = (V_inv[0].double() - reference).abs().max() / reference.abs().max()
    assert float(error) < 1e3 * torch.finfo(dtype).eps
