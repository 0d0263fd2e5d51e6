"""Parameter blocks (variables beyond poses and points) and bundle adjustment with them.

Covers the reprojection terms' Jacobians over poses, points and intrinsics blocks (analytic
against ``jacrev`` and central differences, at the image centre and edge, tiny and large
depths), intrinsics blocks fixed and free, shared and per camera, of 3 and of 8 entries (two
slots), batched = solo, Schur = full system, the covariance of the intrinsics against the
dense inverse of the Gauss-Newton Hessian, the BAL adapters, and the errors.

Tolerances: the solves here are float64 least squares whose Hessians have condition numbers
below ~1e10 (focal lengths of ~600 px against unit-scale poses); two solvers that reach the
same minimum agree there to ~1e-8 relative in the variables, so 1e-6 relative is a safe bar
on any IEEE machine. Central differences with step 1e-6 on O(1..600)-scaled functions carry
O(h²·f''') + O(ε·f/h) ≈ 1e-7 relative error, hence rtol 1e-5 for them; jacrev and the analytic
blocks are the same derivative evaluated in different orders: 1e-10 relative.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

import torchslam
from torchslam.bundle_adjustment import BA_CONFIG, bal_from_problem, problem_from_bal
from torchslam.covariance import marginal_covariances
from torchslam.data.bal_scene import make_bal_scene
from torchslam.io.bal import read_bal, write_bal
from torchslam.lie import se3, so3
from torchslam.objective.reprojection import ReprojectionTerm
from torchslam.objective.terms import term_blocks, term_parameters, term_points, term_poses

F64 = torch.float64
TIGHT = dataclasses.replace(
    BA_CONFIG, function_tolerance=1e-14, gradient_tolerance=1e-11, parameter_tolerance=1e-14,
    max_iterations=200,
)  # fmt: skip


def _scene(C=4, N=30, views=3, seed=0, perturbation=1.0):
    return make_bal_scene(C, N, views=views, seed=seed, perturbation=perturbation).problem


def _gauge_fixed(problem_bal, intrinsics="free", **kwargs):
    """The BAL problem with camera 0 and point 0 held fixed (the similarity gauge)."""
    p = problem_from_bal(problem_bal, intrinsics=intrinsics, **kwargs)
    C, N = problem_bal.cameras.shape[0], problem_bal.points.shape[0]
    fixed_poses = torch.zeros(1, C, dtype=torch.bool)
    fixed_poses[0, 0] = True
    fixed_points = torch.zeros(1, N, dtype=torch.bool)
    fixed_points[0, 0] = True
    return torchslam.PointMapProblem(
        p.poses.detach(),
        p.points.detach(),
        torch.zeros(1, 0, dtype=torch.long),
        torch.zeros(1, 0, dtype=torch.long),
        torch.zeros(1, 0, 3, dtype=F64),
        fixed_poses=fixed_poses,
        fixed_points=fixed_points,
        terms=[_bal_term(problem_bal)],
        parameters={"intrinsics": problem_bal.cameras[:, 6:9]},
        fixed_parameters={"intrinsics": torch.full((C,), intrinsics == "fixed")},
    )


def _bal_term(b, **kwargs):
    return ReprojectionTerm(
        b.camera_index, b.point_index, b.observations, intrinsics_index=b.camera_index, **kwargs
    )


# ------------------------------------------------------------------------------------------
# Jacobians


def _instances(model: str, d: int):
    """Poses (1, K, 1, 4, 4), points (1, K, 3) and intrinsics (1, K, d) at hard and random
    inputs: a point on the optical axis (image centre), one at the edge of a wide view, tiny
    (1e-3) and large (1e3) depths, rotations of angle 0 and ≈ π."""
    g = torch.Generator().manual_seed(3)
    sign = -1.0 if model == "snavely" else 1.0  # Snavely looks down −z, pinhole down +z
    P = torch.tensor(
        [[0.0, 0.0, 5.0], [4.0, -3.0, 5.0], [1e-4, 2e-4, 1e-3], [30.0, -20.0, 1e3],
         [0.3, 0.2, 2.0], [-0.5, 0.7, 3.0]], dtype=F64,
    )  # fmt: skip
    P[:, 2] *= sign
    K = P.shape[0]
    angles = torch.randn(K, 3, generator=g, dtype=F64)
    angles[0] = 0.0
    angles[1] = angles[1] / angles[1].norm() * (torch.pi - 1e-7)
    R = so3.exp(angles)
    X = torch.randn(K, 3, generator=g, dtype=F64)
    t = P - (R @ X[..., None])[..., 0]  # so that R X + t = P
    T = se3.from_rotation_translation(R, t)
    if model == "snavely":
        c = torch.stack(
            (
                600.0 + 10 * torch.randn(K, generator=g, dtype=F64),
                -0.05 * torch.ones(K, dtype=F64),
                0.004 * torch.ones(K, dtype=F64),
            ),
            -1,
        )
    else:
        base = torch.tensor([520.0, 515.0, 320.0, 240.0, -0.1, 0.02, 1e-3, -2e-3], dtype=F64)
        c = base[:d].expand(K, d).clone()
    return T[None, :, None], X[None], c[None]  # fmt: skip


@pytest.mark.parametrize("model, d", [("snavely", 3), ("pinhole", 4), ("pinhole", 8)])
def test_reprojection_jacobians_match_jacrev_and_central_differences(model, d):
    T, X, c = _instances(model, d)
    K = X.shape[1]
    pixels = torch.zeros(K, 2, dtype=F64)
    term = ReprojectionTerm(
        torch.arange(K), torch.arange(K), pixels, model=model, intrinsics_index=torch.arange(K)
    )
    layout_problem = torchslam.PointMapProblem(
        T[:, :, 0], X, torch.zeros(1, 0, dtype=torch.long), torch.zeros(1, 0, dtype=torch.long),
        torch.zeros(1, 0, 3, dtype=F64), terms=[term], parameters={"intrinsics": c[0]},
    )  # fmt: skip
    bound = layout_problem.data.terms[0]
    layout = layout_problem.data.parameters
    slots = layout.pack({"intrinsics": c})
    values = term_parameters(bound, layout, slots)
    poses = term_poses(bound, se3.exp(layout_problem.pose_tangent.detach()))
    points = term_points(bound, X)
    r_a, J_a, Jp_a = term_blocks(bound, poses, points, "analytic", values)
    r_j, J_j, Jp_j = term_blocks(bound, poses, points, "jacrev", values)
    # the same derivative in another order of operations
    torch.testing.assert_close(r_a, r_j, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(J_a, J_j, rtol=1e-10, atol=1e-7)
    torch.testing.assert_close(Jp_a, Jp_j, rtol=1e-10, atol=1e-7)
    # slots: the pose, then ⌈d/6⌉ slots of the intrinsics with zero columns past d
    assert J_a.shape == (1, K, 2, 1 + -(-d // 6), 6)
    flat = J_a[..., 1:, :].flatten(-2)
    assert bool((flat[..., d:] == 0).all())
    # central differences in the intrinsics (relative step)
    h = 1e-6
    for k in range(d):
        step = torch.zeros(d, dtype=F64)
        step[k] = h * max(1.0, float(c[0, 0, k].abs()))
        plus = bound.residual(poses, points, pixels=pixels[None], intrinsics=c + step)
        minus = bound.residual(poses, points, pixels=pixels[None], intrinsics=c - step)
        numeric = (plus - minus) / (2 * step[k])
        scale = J_a[..., 1:, :].flatten(-2)[..., k].abs().amax() + 1.0
        assert float((numeric - flat[..., k]).abs().amax()) <= 1e-5 * float(scale)


# ------------------------------------------------------------------------------------------
# Solves


def test_full_bal_minimum_and_fixed_intrinsics_are_kept():
    b = _scene(C=5, N=60, seed=1)
    free = problem_from_bal(b)
    fixed = problem_from_bal(b, intrinsics="fixed")
    r_free = torchslam.solve(free, TIGHT)
    r_fixed = torchslam.solve(fixed, TIGHT)
    assert r_free.converged[0] and r_fixed.converged[0]
    # fixed blocks are kept bit for bit; free ones move and lower the cost
    assert torch.equal(fixed.parameter_blocks["intrinsics"][0], b.cameras[:, 6:9])
    assert not torch.equal(free.parameter_blocks["intrinsics"][0], b.cameras[:, 6:9])
    assert float(r_free.final_cost) < float(r_fixed.final_cost)
    # at the minimum the gradient w.r.t. every variable vanishes (relative to its scale)
    assert float(r_free.gradient_norm) < 1e-6 * float(r_free.initial_cost)
    # the written BAL file holds the solution: its cost is the solve's
    written = bal_from_problem(free, b)
    assert written.cost() == pytest.approx(float(r_free.final_cost), rel=1e-10)


def test_fixed_intrinsics_equal_known_constants():
    """Intrinsics as fixed parameter blocks and as the term's constants: the same problem."""
    b = _scene(C=4, N=40, seed=2)
    as_blocks = problem_from_bal(b, intrinsics="fixed")
    term = ReprojectionTerm(
        b.camera_index, b.point_index, b.observations, intrinsics=b.cameras[b.camera_index, 6:9]
    )
    empty = torch.zeros(1, 0, dtype=torch.long)
    as_constants = torchslam.PointMapProblem(
        b.poses[None], b.points[None], empty, empty, torch.zeros(1, 0, 3, dtype=F64),
        fixed_poses=torch.zeros(1, 4, dtype=torch.bool), terms=[term],
    )  # fmt: skip
    assert float(as_blocks.cost()) == pytest.approx(float(as_constants.cost()), rel=1e-14)
    r1 = torchslam.solve(as_blocks, TIGHT)
    r2 = torchslam.solve(as_constants, TIGHT)
    assert float(r1.final_cost) == pytest.approx(float(r2.final_cost), rel=1e-9)
    torch.testing.assert_close(as_blocks.points, as_constants.points, rtol=1e-6, atol=1e-6)


def test_jacrev_mode_gives_the_same_solve():
    b = _scene(C=4, N=30, seed=4)
    p1, p2 = problem_from_bal(b), problem_from_bal(b)
    r1 = torchslam.solve(p1, TIGHT)
    r2 = torchslam.solve(p2, dataclasses.replace(TIGHT, jacobian="jacrev"))
    assert float(r1.final_cost) == pytest.approx(float(r2.final_cost), rel=1e-9)
    torch.testing.assert_close(
        p1.parameter_blocks["intrinsics"], p2.parameter_blocks["intrinsics"], rtol=1e-6, atol=1e-8
    )


def test_schur_equals_full_system():
    b = _scene(C=4, N=25, seed=5)
    p1, p2 = _gauge_fixed(b), _gauge_fixed(b)
    r1 = torchslam.solve(p1, TIGHT)
    r2 = torchslam.solve(p2, dataclasses.replace(TIGHT, linear_solver="dense"))
    assert float(r1.final_cost) == pytest.approx(float(r2.final_cost), rel=1e-10)
    torch.testing.assert_close(
        p1.parameter_blocks["intrinsics"], p2.parameter_blocks["intrinsics"], rtol=1e-6, atol=1e-8
    )


def test_batched_equals_solo():
    scenes = [_scene(C=4, N=30, seed=s) for s in (6, 7)]
    solo = []
    for b in scenes:
        p = problem_from_bal(b)
        solo.append((torchslam.solve(p, TIGHT), p))
    # one batch of two problems: a batched term (B, K), per-problem parameter blocks (B, q, d)
    cams = torch.stack([b.camera_index for b in scenes])
    term = ReprojectionTerm(
        cams, torch.stack([b.point_index for b in scenes]),
        torch.stack([b.observations for b in scenes]), intrinsics_index=cams,
    )  # fmt: skip
    empty = torch.zeros(2, 0, dtype=torch.long)
    batched = torchslam.PointMapProblem(
        torch.stack([b.poses for b in scenes]), torch.stack([b.points for b in scenes]),
        empty, empty, torch.zeros(2, 0, 3, dtype=F64),
        fixed_poses=torch.zeros(2, 4, dtype=torch.bool), terms=[term],
        parameters={"intrinsics": torch.stack([b.cameras[:, 6:9] for b in scenes])},
    )  # fmt: skip
    rb = torchslam.solve(batched, TIGHT)
    for k, (r, p) in enumerate(solo):
        assert rb.status[k] == r.status[0]
        assert float(rb.final_cost[k]) == pytest.approx(float(r.final_cost), rel=1e-9)
        torch.testing.assert_close(
            batched.parameter_blocks["intrinsics"][k], p.parameter_blocks["intrinsics"][0],
            rtol=1e-6, atol=1e-8,
        )  # fmt: skip


def _pinhole_problem(shared: bool, d: int = 8, seed: int = 8):
    """A pinhole BA whose cameras share one intrinsics block (q = 1) or have one each."""
    g = torch.Generator().manual_seed(seed)
    C, N = 4, 40
    X = torch.randn(N, 3, generator=g, dtype=F64)
    angles = torch.linspace(-0.3, 0.3, C, dtype=F64)
    R = so3.exp(torch.stack((torch.zeros(C), angles, torch.zeros(C)), -1).to(F64))
    t = torch.tensor([0.0, 0.0, 6.0], dtype=F64).expand(C, 3).clone()
    T = se3.from_rotation_translation(R, t)
    truth = torch.tensor([520.0, 515.0, 320.0, 240.0, -0.1, 0.02, 1e-3, -2e-3], dtype=F64)[:d]
    cam = torch.arange(C).repeat_interleave(N)
    pt = torch.arange(N).repeat(C)
    from torchslam.cameras import pinhole_project

    pixels = pinhole_project(T[cam], X[pt], truth.expand(C * N, d))
    pixels = pixels + 0.3 * torch.randn(pixels.shape, generator=g, dtype=F64)
    index = torch.zeros_like(cam) if shared else cam
    q = 1 if shared else C
    start = truth * torch.tensor([1.02, 0.98, 1.01, 0.99, 0, 0, 0, 0], dtype=F64)[:d]
    term = ReprojectionTerm(cam, pt, pixels, model="pinhole", intrinsics_index=index)
    fixed_points = torch.zeros(1, N, dtype=torch.bool)
    fixed_points[0, :1] = True
    fixed_poses = torch.zeros(1, C, dtype=torch.bool)
    fixed_poses[0, 0] = True
    empty = torch.zeros(1, 0, dtype=torch.long)
    return torchslam.PointMapProblem(
        T[None], (X + 0.02)[None], empty, empty, torch.zeros(1, 0, 3, dtype=F64),
        fixed_poses=fixed_poses, fixed_points=fixed_points, terms=[term],
        parameters={"intrinsics": start.expand(q, d).clone()},
    )  # fmt: skip


@pytest.mark.parametrize("shared", [True, False])
def test_pinhole_intrinsics_of_two_slots_converge(shared):
    p = _pinhole_problem(shared)
    r = torchslam.solve(p, TIGHT)
    assert r.converged[0], r.reason
    # at the noise floor: ½ σ² per residual entry (σ = 0.3 px, 4 × 40 × 2 entries) at most
    assert float(r.final_cost) < 0.5 * 0.3**2 * 320
    # the fixed point and pose keep their values; every block of 8 moved from its start
    assert p.parameter_blocks["intrinsics"].shape == (1, 1 if shared else 4, 8)
    assert bool((p.parameter_blocks["intrinsics"][..., 4:] != 0).all())


def _dense_hessian(problem):
    """J̃ᵀJ̃ of the whole problem over its free variables, from jacrev of the residual vector
    w.r.t. (δ poses (right), δ points, δ intrinsics), by brute force."""
    data = problem.data
    term = data.terms[0]
    T0 = problem.poses.detach()[0]
    X0 = problem.points.detach()[0]
    c0 = problem.parameter_blocks["intrinsics"].detach()[0]
    C, N, q = T0.shape[0], X0.shape[0], c0.shape[0]
    d = c0.shape[1]
    pixels = term.constants["pixels"][0]
    cam, pt = term.pose_index[0, :, 0], term.point_index[0]
    cidx = term.parameter_index["intrinsics"][0]

    def residuals(v):
        dp = v[: 6 * C].reshape(C, 6)
        dX = v[6 * C : 6 * C + 3 * N].reshape(N, 3)
        dc = v[6 * C + 3 * N :].reshape(q, d)
        T = T0 @ se3.exp(dp)
        out = term.residual(
            T[cam][:, None], X0[pt] + dX[pt], pixels=pixels, intrinsics=(c0 + dc)[cidx]
        )
        return out.reshape(-1)

    v = torch.zeros(6 * C + 3 * N + q * d, dtype=F64)
    J = torch.func.jacrev(residuals)(v)
    free = torch.cat(
        (
            (~data.fixed_poses[0]).repeat_interleave(6),
            (~data.fixed_points[0]).repeat_interleave(3),
            (~data.parameters.fixed[0][0]).repeat_interleave(d),
        )
    )
    return J.T @ J, free, (6 * C + 3 * N, q, d)


@pytest.mark.parametrize("reduced", ["dense", "sparse"])
@pytest.mark.parametrize("kind", ["bal", "pinhole"])
def test_intrinsics_covariance_matches_the_dense_inverse(kind, reduced):
    # the sparse reduced solver (SciPy, selected inverse) gives the same blocks; the pinhole
    # blocks (8 values) span two slots, whose cross blocks it reads too
    if kind == "bal":
        p = _gauge_fixed(_scene(C=4, N=30, seed=9))
    else:
        p = _pinhole_problem(shared=True)
    r = torchslam.solve(p, TIGHT)
    config = dataclasses.replace(TIGHT, reduced_solver=reduced)
    cov = marginal_covariances(p, r, points=False, config=config).check()
    assert cov.method == reduced
    H, free, (offset, q, d) = _dense_hessian(p)
    Hf = H[free][:, free]
    inverse = torch.linalg.inv(Hf)
    full = torch.zeros_like(H)
    idx = free.nonzero()[:, 0]
    full[idx[:, None], idx[None, :]] = inverse
    expected = torch.stack(
        [full[offset + k * d : offset + (k + 1) * d, offset + k * d : offset + (k + 1) * d]
         for k in range(q)]
    )  # fmt: skip
    got = cov.parameters["intrinsics"][0]
    # H⁻¹ by two factorizations of a matrix of condition ≲ 1e12: 1e-6 relative to its norm
    scale = float(expected.abs().amax())
    assert float((got - expected).abs().amax()) <= 1e-6 * scale


def test_differentiable_solve_with_known_intrinsics_matches_finite_differences():
    """Gradients of the solution w.r.t. known intrinsics (a term's constants) by the implicit
    backward, against central differences of the whole solve."""
    b = _scene(C=3, N=20, seed=10, perturbation=0.5)
    f = b.cameras[:, 6:7].clone().requires_grad_(True)

    def solution(focal, backward="implicit"):
        c = torch.cat((focal, b.cameras[:, 7:9]), -1)[b.camera_index]
        term = ReprojectionTerm(b.camera_index, b.point_index, b.observations, intrinsics=c)
        fixed_poses = torch.tensor([[True, False, False]])
        fixed_points = torch.zeros(1, 20, dtype=torch.bool)
        fixed_points[0, 0] = True
        empty = torch.zeros(1, 0, dtype=torch.long)
        p = torchslam.PointMapProblem(
            b.poses[None], b.points[None], empty, empty, torch.zeros(1, 0, 3, dtype=F64),
            fixed_poses=fixed_poses, fixed_points=fixed_points, terms=[term],
        )  # fmt: skip
        return torchslam.solve_differentiable(
            p.pose_tangent, p.points, p.data, TIGHT, backward=backward
        )

    def solution_unrolled(focal):
        return solution(focal, "unrolled")

    result = solution(f)
    loss = result.points[0, 1:].sum()
    (grad,) = torch.autograd.grad(loss, f)
    # Focal lengths ~600 px: a step of 1e-2 (relative 2e-5) keeps the truncation error O(h²)
    # negligible, while the solves' stopping tolerance (solution errors ~1e-9) divided by 2h
    # stays ~1e-7 of the derivative: rel 1e-3 is a safe bar.
    h = 1e-2
    for k in range(3):
        e = torch.zeros_like(f)
        e[k] = h
        with torch.no_grad():
            plus = solution(f.detach() + e).points[0, 1:].sum()
            minus = solution(f.detach() - e).points[0, 1:].sum()
        numeric = float((plus - minus) / (2 * h))
        assert float(grad[k]) == pytest.approx(numeric, rel=1e-3, abs=1e-8)
    # the unrolled backward differentiates the same solve
    unrolled = solution_unrolled(f)
    (grad_unrolled,) = torch.autograd.grad(unrolled.points[0, 1:].sum(), f)
    torch.testing.assert_close(grad_unrolled, grad, rtol=1e-4, atol=1e-9)


# ------------------------------------------------------------------------------------------
# Adapters, the command line, errors


def test_bal_problem_round_trip(tmp_path):
    b = _scene(C=3, N=10, seed=11)
    path = tmp_path / "scene.txt"
    write_bal(path, b)
    back = bal_from_problem(problem_from_bal(read_bal(path)), read_bal(path))
    torch.testing.assert_close(back.cameras, read_bal(path).cameras, rtol=1e-12, atol=1e-12)
    assert back.cost() == pytest.approx(read_bal(path).cost(), rel=1e-12)


def test_ba_command(tmp_path, capsys):
    from torchslam import cli

    b = _scene(C=4, N=30, seed=12)
    path = tmp_path / "scene.txt"
    write_bal(path, b)
    out = tmp_path / "solved.txt"
    assert cli.main(["ba", str(path), "--out", str(out), "--loss", "huber:2"]) == 0
    text = capsys.readouterr().out
    for fragment in ("4 cameras, 30 points", "initial cost", "final cost", "iterations",
                     "status", "linear solves", f"wrote {out}"):  # fmt: skip
        assert fragment in text
    final = float(text.split("final cost")[1].split()[0])
    assert read_bal(out).cost() < b.cost()
    assert final > 0
    assert cli.main(["ba", str(tmp_path / "missing.txt")]) == 2
    assert cli.main(["ba", str(path), "--loss", "huber"]) == 2
    assert "NAME:SCALE" in capsys.readouterr().err


def test_bad_parameter_blocks_are_clear_errors():
    b = _scene(C=3, N=10, seed=13)
    empty = torch.zeros(1, 0, dtype=torch.long)
    args = (b.poses[None], b.points[None], empty, empty, torch.zeros(1, 0, 3, dtype=F64))
    term = _bal_term(b)
    with pytest.raises(ValueError, match="parameter group 'intrinsics'"):
        torchslam.PointMapProblem(*args, terms=[term])
    with pytest.raises(ValueError, match=r"parameters\['intrinsics'\] must have shape"):
        torchslam.PointMapProblem(*args, terms=[term], parameters={"intrinsics": torch.zeros(3)})
    with pytest.raises(ValueError, match="takes 3 intrinsics values"):
        torchslam.PointMapProblem(
            *args, terms=[term], parameters={"intrinsics": torch.zeros(3, 4, dtype=F64)}
        )
    far = ReprojectionTerm(
        b.camera_index, b.point_index, b.observations, intrinsics_index=b.camera_index + 5
    )
    with pytest.raises(ValueError, match="index out of range"):
        torchslam.PointMapProblem(*args, terms=[far], parameters={"intrinsics": b.cameras[:, 6:]})
    with pytest.raises(ValueError, match="not a parameter group"):
        torchslam.PointMapProblem(
            *args, terms=[term], parameters={"intrinsics": b.cameras[:, 6:]},
            fixed_parameters={"focal": torch.zeros(3, dtype=torch.bool)},
        )  # fmt: skip
    with pytest.raises(ValueError, match="exactly one of"):
        ReprojectionTerm(b.camera_index, b.point_index, b.observations)
    with pytest.raises(ValueError, match="'model' must be one of"):
        ReprojectionTerm(
            b.camera_index, b.point_index, b.observations, model="fisheye",
            intrinsics_index=b.camera_index,
        )  # fmt: skip
    with pytest.raises(TypeError, match="must be a mapping"):
        torchslam.PointMapProblem(*args, terms=[term], parameters=[b.cameras[:, 6:]])
    p = problem_from_bal(b)
    with pytest.raises(ValueError, match="every parameter group"):
        torchslam.solve_tensors(p.pose_tangent, p.points, p.data, parameters={})
    with pytest.raises(TypeError, match="BALProblem"):
        problem_from_bal("scene.txt")


def test_solve_tensors_returns_the_parameter_blocks():
    b = _scene(C=3, N=15, seed=14)
    p = problem_from_bal(b)
    start = {"intrinsics": p.parameter_blocks["intrinsics"].detach().clone()}
    r = torchslam.solve_tensors(p.pose_tangent, p.points, p.data, TIGHT, parameters=start)
    assert set(r.parameters) == {"intrinsics"}
    assert r.parameters["intrinsics"].shape == (1, 3, 3)
    assert torch.equal(start["intrinsics"], p.parameter_blocks["intrinsics"].detach())  # unchanged
    torchslam.solve(p, TIGHT)
    torch.testing.assert_close(
        r.parameters["intrinsics"], p.parameter_blocks["intrinsics"].detach()
    )


@pytest.mark.parametrize("backward", ["unrolled", "truncated", "implicit"])
def test_differentiable_bundle_adjustment_with_free_intrinsics(backward):
    """Gradients of the solved focal lengths w.r.t. the observed pixels (unrolled through the
    solve, whose iterations run to convergence, or implicit at its minimum) against central
    differences of the whole solve. Step 1e-3 px on pixels of ~100 px: truncation O(h²)
    negligible, the solves' stopping noise (~1e-9) over 2h well below the 1e-4 relative
    bar."""
    b = _scene(C=3, N=15, seed=15, perturbation=0.5)
    pixels = b.observations.clone().requires_grad_(True)

    def focal(px, backward=backward):
        bb = dataclasses.replace(b, observations=px)
        p = _gauge_fixed(bb)
        blocks = {"intrinsics": p.parameter_blocks["intrinsics"].detach()}
        r = torchslam.solve_differentiable(
            p.pose_tangent, p.points, p.data, TIGHT, backward=backward, parameters=blocks,
            truncate_steps=100,
        )  # fmt: skip
        assert r.converged[0]
        return r.parameters["intrinsics"][0, :, 0].sum()

    (grad,) = torch.autograd.grad(focal(pixels), pixels)
    h = 1e-3
    g = torch.Generator().manual_seed(0)
    for flat in torch.randperm(pixels.numel(), generator=g)[:4].tolist():
        e = torch.zeros_like(pixels).reshape(-1)
        e[flat] = h
        e = e.reshape(pixels.shape)
        with torch.no_grad():
            numeric = focal(pixels.detach() + e, "none") - focal(pixels.detach() - e, "none")
        numeric = float(numeric) / (2 * h)
        got = float(grad.reshape(-1)[flat])
        assert got == pytest.approx(numeric, rel=1e-4, abs=1e-6 * float(grad.abs().max()))


def test_implicit_gradient_of_the_initial_parameter_blocks():
    # At a minimum the free blocks do not depend on their starting values (gradient 0) and a
    # fixed block is its starting value (gradient 1); the solution's other variables depend
    # on a fixed block's value, which the implicit function theorem gives: checked against
    # central differences of the whole solve (step 1e-3 on focal lengths of ~600: relative
    # 2e-6, truncation negligible; stopping noise ~1e-9 / 2h well below the 1e-4 bar).
    b = _scene(C=3, N=15, seed=16, perturbation=0.5)
    p = _gauge_fixed(b)
    fixed = {"intrinsics": torch.tensor([False, True, False])}
    problem = torchslam.PointMapProblem(
        p.poses.detach(), p.points.detach(), torch.zeros(1, 0, dtype=torch.long),
        torch.zeros(1, 0, dtype=torch.long), torch.zeros(1, 0, 3, dtype=F64),
        fixed_poses=p.data.fixed_poses, fixed_points=p.data.fixed_points,
        terms=[_bal_term(b)], parameters={"intrinsics": b.cameras[:, 6:9]},
        fixed_parameters=fixed,
    )  # fmt: skip
    start = problem.parameter_blocks["intrinsics"].detach().clone()

    def solve(blocks, backward="implicit"):
        r = torchslam.solve_differentiable(
            problem.pose_tangent.detach(), problem.points.detach(), problem.data, TIGHT,
            backward=backward, parameters={"intrinsics": blocks},
        )  # fmt: skip
        assert r.converged[0]
        return r

    blocks = start.clone().requires_grad_(True)
    r = solve(blocks)
    focal = r.parameters["intrinsics"][0, :, 0]
    (grad,) = torch.autograd.grad(focal[1], blocks, retain_graph=True)
    assert float(grad[0, 1, 0]) == 1.0  # the fixed block is its start
    assert float(grad[0, [0, 2]].abs().max()) == 0.0
    # free blocks: the minimum does not move with their start
    (grad,) = torch.autograd.grad(focal.sum(), blocks, retain_graph=True)
    assert float(grad[0, [0, 2]].abs().max()) == 0.0
    # the free focal lengths move with the fixed one: implicit vs central differences
    (grad,) = torch.autograd.grad(focal[[0, 2]].sum(), blocks)
    h = 1e-3
    e = torch.zeros_like(start)
    e[0, 1, 0] = h
    with torch.no_grad():
        plus = solve(start + e, "none").parameters["intrinsics"][0, [0, 2], 0].sum()
        minus = solve(start - e, "none").parameters["intrinsics"][0, [0, 2], 0].sum()
    numeric = float(plus - minus) / (2 * h)
    assert float(grad[0, 1, 0]) == pytest.approx(numeric, rel=1e-4, abs=1e-8)


@pytest.mark.parametrize("reduced", ["dense", "sparse"])
def test_intrinsics_covariance_of_a_free_gauge_is_nan(reduced):
    # no camera and no point fixed: the similarity gauge is free, H singular; the problem is
    # reported and every block, parameter blocks included, is NaN on either reduced solver
    p = problem_from_bal(_scene(C=4, N=30, seed=9))
    r = torchslam.solve(p, TIGHT)
    config = dataclasses.replace(TIGHT, reduced_solver=reduced)
    cov = marginal_covariances(p, r, points=False, config=config)
    assert not bool(cov.ok[0]) and "rank deficient" in cov.reason[0]
    assert bool(cov.poses[0, 1:].isnan().all())
    assert bool(cov.parameters["intrinsics"][0].isnan().all())
