"""Marginal covariances (torchslam.covariance, torchslam.posegraph.covariance) on small problems.

Properties: equal to the blocks of the dense inverse of JᵀJ (fixed variables removed) for
point observations, relative-pose terms and robust losses on every path of the plan; fixed
variables have zero blocks; a rank-deficient system is reported, never returned; batches
equal their problems solved alone; the selected inverse equals the dense inverse on the
factor's pattern; the pose-graph API and the CLI's file; NEES on seeded scenes; gradients
with respect to the weights.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.linalg
import torch

import torchslam as ts
from torchslam import cli, covariance
from torchslam.io import g2o
from torchslam.lie import se3
from torchslam.solver.sparse import selected_inverse

F64 = torch.float64
PATHS = {
    "dense": ts.SolverConfig(reduced_solver="dense"),
    "sparse": ts.SolverConfig(reduced_solver="sparse"),
    "full": ts.SolverConfig(linear_solver="dense"),
}
# Relative agreement with the dense reference: both are backward stable, so they differ by
# ~ κ(H)·ε; these problems have κ ≤ ~1e4 (unit-scale poses and points, weights in [0.5, 1.5],
# information 10-100), so 1e-10 leaves two orders of margin on every machine.
EXACT = 1e-10


def _perturbed(T, gen, scale):
    return T @ se3.exp(scale * torch.randn(*T.shape[:-2], 6, generator=gen, dtype=F64))


def _problem(seed: int, robust: bool = False, terms: bool = True, B: int = 2, **kwargs):
    """B small problems (5 poses, 24 points) with relative-pose terms and, when
    ``robust``, Huber on the observations (with outliers) and Cauchy on the terms."""
    gen = torch.Generator().manual_seed(seed)
    scene = ts.data.make_scene(
        5, 24, batch_size=B, noise_std=0.02, outlier_fraction=0.1 if robust else 0.0, seed=seed
    )
    E = scene.valid.shape[1]
    weights = 0.5 + torch.rand(B, E, generator=gen, dtype=F64)
    spec = []
    term_list = []
    if terms:
        pairs = torch.tensor([[0, 1], [1, 2], [2, 3], [3, 4], [0, 4]])
        Z = _perturbed(
            scene.poses_gt[:, pairs[:, 0]] @ se3.inverse(scene.poses_gt[:, pairs[:, 1]]), gen, 0.02
        )
        A = torch.randn(B, len(pairs), 6, 6, generator=gen, dtype=F64)
        info = 10 * (A @ A.transpose(-1, -2) / 6 + torch.eye(6, dtype=F64))
        loss = ts.CauchyLoss(1.0) if robust else None
        index = pairs.expand(B, -1, 2)
        term_list.append(ts.RelativePoseTerm(index, Z, information=info, loss=loss))
        spec.append((index, Z, info, loss))
    problem = ts.PointMapProblem(
        scene.poses_gt,
        scene.points_gt,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        valid=scene.valid,
        weights=weights,
        loss=ts.HuberLoss(0.05) if robust else None,
        terms=term_list,
        **kwargs,
    )
    # Not solved: the blocks need no optimum, and the noisy observations, perturbed
    # measurements and outliers give nonzero residuals (and ρ' < 1) at the true values.
    return problem, spec


def _reference(problem, spec, b: int):
    """Blocks of H⁻¹ of problem b, H = Σ ρ'(s) Jᵀ Ω J with J by jacfwd of the residuals written
    out (right perturbations; Ceres' corrector for ρ'' ≤ 0 kernels: √ρ' only), fixed removed:
    (poses (m, m, 6, 6), points (n, 3, 3))."""
    data = problem.data
    xi, X = problem.pose_tangent.detach()[b], problem.points.detach()[b]
    m, n = xi.shape[0], X.shape[0]
    valid = data.valid[b]
    i_obs, j_obs, obs = (
        data.pose_index[b][valid],
        data.point_index[b][valid],
        data.observations[b][valid],
    )
    w = data.weights[b][valid]

    def residuals(delta):
        T = se3.exp(xi) @ se3.exp(delta[: 6 * m].reshape(m, 6))
        P = X + delta[6 * m :].reshape(n, 3)
        parts = [(obs - se3.act(T[i_obs], P[j_obs])).reshape(-1)]
        for index, Z, _, _ in spec:
            E = se3.inverse(Z[b]) @ T[index[b, :, 0]] @ se3.inverse(T[index[b, :, 1]])
            parts.append(se3.log(E).reshape(-1))
        return torch.cat(parts)

    zero = xi.new_zeros(6 * m + 3 * n)
    with ts.validation(False):  # forward mode: fewer inputs than residuals
        r, J = residuals(zero), torch.func.jacfwd(residuals)(zero)
    blocks = [(3, w[:, None, None] * torch.eye(3, dtype=F64), data.loss, len(obs))]
    blocks += [(6, info[b], loss, index.shape[1]) for index, _, info, loss in spec]
    H = xi.new_zeros(6 * m + 3 * n, 6 * m + 3 * n)
    row = 0
    for d, omega, loss, count in blocks:
        rk = r[row : row + d * count].reshape(count, d)
        Jk = J[row : row + d * count].reshape(count, d, -1)
        s = torch.einsum("ka,kab,kb->k", rk, omega, rk)
        rho1 = loss(s)[1] if loss is not None else torch.ones_like(s)
        H = H + torch.einsum("k,kai,kab,kbj->ij", rho1, Jk, omega, Jk)
        row += d * count
    fixed = torch.cat(
        (data.fixed_poses[b].repeat_interleave(6), data.fixed_points[b].repeat_interleave(3))
    )
    keep = (~fixed).nonzero().squeeze(1)
    inverse = torch.zeros_like(H)
    inverse[keep[:, None], keep] = torch.linalg.inv(H[keep][:, keep])
    poses = inverse[: 6 * m, : 6 * m].reshape(m, 6, m, 6).transpose(1, 2)
    points = inverse[6 * m :, 6 * m :].reshape(n, 3, n, 3).transpose(1, 2)
    return poses, points[torch.arange(n), torch.arange(n)]


def _relative(a, b):
    return float((a - b).abs().max() / b.abs().max())


@pytest.mark.parametrize("robust", [False, True], ids=["least_squares", "huber_cauchy"])
def test_equal_to_the_dense_inverse_on_every_path(robust):
    problem, spec = _problem(seed=11 if robust else 12, robust=robust)
    if robust:  # the kernels do down-weight something, or the test would not test them
        s = problem.raw_residuals().square().sum(-1) * problem.data.weights
        assert bool((s[problem.data.valid] > 0.05**2).any())
    pairs = [(1, 2), (1, 4), (2, 3), (0, 3)]
    refs = [_reference(problem, spec, b) for b in range(2)]
    m = problem.num_poses
    for config in PATHS.values():
        cov = ts.marginal_covariances(problem, config=config, pairs=pairs).check()
        for b, (ref_poses, ref_points) in enumerate(refs):
            assert _relative(cov.poses[b], ref_poses[torch.arange(m), torch.arange(m)]) < EXACT
            assert _relative(cov.points[b], ref_points) < EXACT
            ref_pairs = ref_poses[[i for i, _ in pairs], [k for _, k in pairs]]
            assert _relative(cov.pairs[b], ref_pairs) < EXACT


def test_fixed_variables_have_zero_blocks_and_the_others_are_relative_to_them():
    fixed_poses = torch.zeros(2, 5, dtype=torch.bool)
    fixed_poses[:, [0, 3]] = True
    fixed_points = torch.zeros(2, 24, dtype=torch.bool)
    fixed_points[:, [1, 7]] = True
    problem, spec = _problem(
        seed=13, terms=True, fixed_poses=fixed_poses, fixed_points=fixed_points
    )
    for config in PATHS.values():
        cov = ts.marginal_covariances(problem, config=config, pairs=[(0, 1), (2, 3), (1, 2)])
        assert bool(cov.ok.all())
        assert bool((cov.poses[:, [0, 3]] == 0).all())
        assert bool((cov.points[:, [1, 7]] == 0).all())
        assert bool((cov.pairs[:, :2] == 0).all())
        assert bool((cov.pairs[:, 2] != 0).any())
        ref_poses, ref_points = _reference(problem, spec, 1)
        assert _relative(cov.poses[1, 1], ref_poses[1, 1]) < EXACT
        assert _relative(cov.points[1], ref_points) < EXACT


@pytest.mark.parametrize("path", ["dense", "sparse", "full"])
def test_a_free_gauge_is_reported_not_returned(path):
    scene = ts.data.make_scene(4, 20, batch_size=2, seed=3)
    free = torch.zeros(2, 4, dtype=torch.bool)
    free[1, 0] = True  # problem 1 keeps the gauge; problem 0 has none
    problem = ts.PointMapProblem.from_scene(scene)
    problem.data = dataclasses.replace(problem.data, fixed_poses=free)
    cov = ts.marginal_covariances(problem, config=PATHS[path])
    assert cov.ok.tolist() == [False, True]
    assert cov.reason[0].startswith("rank deficient")
    assert cov.reason[1] == "ok"
    assert bool(cov.poses[0].isnan().all()) and bool(cov.points[0].isnan().all())
    assert bool(cov.poses[1, 1:].isfinite().all())
    with pytest.raises(ValueError, match="problem 0: rank deficient"):
        cov.check()


def test_an_unobserved_free_point_is_reported():
    scene = ts.data.make_scene(4, 20, seed=4)
    valid = scene.valid & (scene.point_index != 5)
    with ts.validation(False):  # validation would hold the unobserved point fixed
        problem = ts.PointMapProblem(
            scene.poses_gt,
            scene.points_gt,
            scene.pose_index,
            scene.point_index,
            scene.observations,
            valid=valid,
        )
    cov = ts.marginal_covariances(problem)
    assert not bool(cov.ok[0])
    assert "point 5" in cov.reason[0]


def test_a_batch_equals_its_problems_alone():
    problem, spec = _problem(seed=14, B=3)
    together = ts.marginal_covariances(problem, pairs=[(1, 3)])
    for b in range(3):
        alone = ts.PointMapProblem(
            problem.poses[b : b + 1].detach(),
            problem.points[b : b + 1].detach(),
            problem.data.pose_index[b : b + 1],
            problem.data.point_index[b : b + 1],
            problem.data.observations[b : b + 1],
            valid=problem.data.valid[b : b + 1],
            weights=problem.data.weights[b : b + 1],
            terms=[
                ts.RelativePoseTerm(
                    index[b : b + 1], Z[b : b + 1], information=info[b : b + 1], loss=loss
                )
                for index, Z, info, loss in spec
            ],
        )
        single = ts.marginal_covariances(alone, pairs=[(1, 3)])
        # Exp∘Log of the poses moves them by ~1e-16: agreement to round-off times κ.
        assert _relative(single.poses[0], together.poses[b]) < EXACT
        assert _relative(single.points[0], together.points[b]) < EXACT
        assert _relative(single.pairs[0], together.pairs[b]) < EXACT


def test_selected_inverse_equals_the_dense_inverse_on_the_pattern():
    rng = np.random.default_rng(0)
    n, k = 30, 6
    blocks = {(i, i) for i in range(n)} | {(i, i + 1) for i in range(n - 1)}
    blocks |= {tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(15)}
    A = np.zeros((n * k, n * k))
    for i, j in blocks:
        B = rng.standard_normal((k, k))
        A[i * k : i * k + k, j * k : j * k + k] += B
        A[j * k : j * k + k, i * k : i * k + k] += B.T if i != j else B
    A = A @ A.T + np.eye(n * k)  # SPD with the fill of the product
    lu = scipy.sparse.linalg.splu(
        scipy.sparse.csc_matrix(A),
        permc_spec="NATURAL",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )
    inverse = selected_inverse(lu.L, lu.U.diagonal())
    dense = np.linalg.inv(A)
    rows, cols = inverse.keys % n, inverse.keys // n
    expected = dense.reshape(n, k, n, k).transpose(0, 2, 1, 3)[rows, cols]
    # κ(A) ≲ 1e5 here: both inverses agree to ~1e-11 relative.
    assert np.abs(inverse.blocks - expected).max() < 1e-9 * np.abs(dense).max()
    got, found = inverse.lookup(cols[:5], rows[:5])  # transposed lookups
    assert found.all() and np.allclose(got, expected[:5].transpose(0, 2, 1), rtol=0, atol=1e-12)


def test_nees_is_consistent_over_seeded_scenes():
    """Mean NEES over 60 scenes with Gaussian noise σ and weights 1/σ²: 6 per pose, 3 per
    point. The per-scene averages are independent across scenes, each with variance at most
    that of one χ² sample (12 for 6 dof, 6 for 3; an average of correlated terms never
    exceeds it), so the mean over 60 scenes has a standard deviation ≤ √(12/60) = 0.45
    (poses) and √(6/60) = 0.32 (points): |mean − 6| ≤ 2 and |mean − 3| ≤ 1.4 are ≥ 4.4 σ,
    while covariances off by a factor 2 would give 3 or 12, 1.5 or 6."""
    sigma, scenes = 0.01, 60
    scene = ts.data.make_scene(
        5, 40, batch_size=scenes, visible_fraction=0.6, noise_std=sigma, seed=99
    )
    B, E = scene.valid.shape
    problem = ts.PointMapProblem(
        scene.poses_gt,
        scene.points_gt,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        valid=scene.valid,
        weights=torch.full((B, E), sigma**-2, dtype=F64),
    )
    result = ts.solve(problem)
    cov = ts.marginal_covariances(problem, result).check()
    e = se3.log(se3.inverse(scene.poses_gt[:, 1:]) @ result.poses[:, 1:])
    pose_nees = (e[..., None, :] @ torch.linalg.solve(cov.poses[:, 1:], e[..., None]))[..., 0, 0]
    d = result.points - scene.points_gt
    point_nees = (d[..., None, :] @ torch.linalg.solve(cov.points, d[..., None]))[..., 0, 0]
    assert abs(float(pose_nees.mean()) - 6) <= 2.0
    assert abs(float(point_nees.mean()) - 3) <= 1.4


def test_gradient_with_respect_to_the_weights():
    problem, _ = _problem(seed=15, terms=False, B=1)
    weights = problem.data.weights.clone().requires_grad_(True)

    def pose_variance(w):
        data = dataclasses.replace(problem.data, weights=w)
        cov = covariance.marginal_covariances_tensors(
            problem.pose_tangent.detach(),
            problem.points.detach(),
            data,
            PATHS["dense"],
            point_selection=[3],
        )
        return cov.poses[0, 2].trace() + cov.points[0, 0].trace()

    value = pose_variance(weights)
    (grad,) = torch.autograd.grad(value, weights)
    direction = torch.randn(weights.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    h = 1e-6
    with torch.no_grad():
        numeric = pose_variance(weights + h * direction) - pose_variance(weights - h * direction)
    numeric = numeric / (2 * h)
    # Central differences: error O(h²)·|f'''| + ε|f|/h ≈ 1e-10 relative here.
    assert math.isclose(float((grad * direction).sum()), float(numeric), rel_tol=1e-6)
    with pytest.raises(ValueError, match="sparse reduced solver"):
        data = dataclasses.replace(problem.data, weights=weights)
        covariance.marginal_covariances_tensors(
            problem.pose_tangent.detach(), problem.points.detach(), data, PATHS["sparse"]
        )


def test_bad_arguments_raise_clear_errors():
    problem, _ = _problem(seed=16, terms=False, B=1)
    with pytest.raises(TypeError, match="marginal_covariances: argument 'problem'"):
        ts.marginal_covariances(problem.data)
    with pytest.raises(ValueError, match="argument 'poses' must hold indices in \\[0, 5\\)"):
        ts.marginal_covariances(problem, poses=[0, 5])
    with pytest.raises(TypeError, match="argument 'points' must hold integer indices"):
        ts.marginal_covariances(problem, points=torch.tensor([0.5]))
    with pytest.raises(ValueError, match="argument 'pairs' must have shape \\(R, 2\\)"):
        ts.marginal_covariances(problem, pairs=torch.zeros(3, dtype=torch.long))
    with pytest.raises(TypeError, match="argument 'result'"):
        ts.marginal_covariances(problem, result="x")
    with pytest.raises(ValueError, match="'rank_tolerance'"):
        ts.marginal_covariances(problem, rank_tolerance=2.0)
    with pytest.raises(ValueError, match="'convention'"):
        covariance.position_covariance(torch.eye(6, dtype=F64), torch.eye(4, dtype=F64), "x")


def test_position_covariance_and_pose_uncertainty():
    gen = torch.Generator().manual_seed(5)
    T = se3.exp(torch.randn(6, generator=gen, dtype=F64))
    A = torch.randn(6, 6, generator=gen, dtype=F64)
    sigma = A @ A.T

    def centre(delta):  # world position of the frame of T_i0·Exp(δ)
        return se3.inverse(T @ se3.exp(delta))[:3, 3]

    J = torch.func.jacrev(centre)(torch.zeros(6, dtype=F64))
    expected = J @ sigma @ J.T
    got = covariance.position_covariance(sigma, T)
    assert torch.allclose(got, expected, rtol=1e-12, atol=1e-12)
    J = torch.func.jacrev(lambda d: (T @ se3.exp(d))[:3, 3])(torch.zeros(6, dtype=F64))
    got = covariance.position_covariance(sigma, T, "frame_to_world")
    assert torch.allclose(got, J @ sigma @ J.T, rtol=1e-12, atol=1e-12)
    rotation, translation = covariance.pose_uncertainty(sigma, T)
    assert math.isclose(
        float(rotation), math.degrees(float(torch.linalg.eigvalsh(sigma[:3, :3])[-1]) ** 0.5)
    )
    assert math.isclose(float(translation), float(torch.linalg.eigvalsh(expected)[-1]) ** 0.5)


# ------------------------------------------------------------------------------------------
# Pose graphs


def _ring(n: int = 8):
    gen = torch.Generator().manual_seed(21)
    truth = se3.exp(torch.randn(n, 6, generator=gen, dtype=F64))
    edges = torch.tensor([[k, k + 1] for k in range(n - 1)] + [[0, n - 1], [2, 6]])
    Z = _perturbed(se3.inverse(truth[edges[:, 0]]) @ truth[edges[:, 1]], gen, 0.03)
    A = torch.randn(len(edges), 6, 6, generator=gen, dtype=F64)
    info = 20 * (A @ A.transpose(-1, -2) / 6 + torch.eye(6, dtype=F64))
    return ts.posegraph.PoseGraph(torch.arange(10, 10 + n), truth, edges, Z, info)


def test_pose_graph_vertices_equal_the_dense_inverse():
    graph = _ring()
    result = ts.posegraph.solve.solve_pose_graph(graph)
    N = graph.num_vertices

    def residuals(delta):  # r = Log(Z⁻¹ T_i⁻¹ T_j), vertices body → world, T·Exp(δ)
        T = result.poses @ se3.exp(delta.reshape(N, 6))
        E = se3.inverse(graph.measurements) @ se3.inverse(T[graph.edges[:, 0]])
        return se3.log(E @ T[graph.edges[:, 1]]).reshape(-1)

    J = torch.func.jacrev(residuals)(torch.zeros(6 * N, dtype=F64)).reshape(-1, 6, 6 * N)
    H = torch.einsum("kai,kab,kbj->ij", J, graph.information, J)[6:, 6:]
    inverse = torch.linalg.inv(H).reshape(N - 1, 6, N - 1, 6).transpose(1, 2)
    for linear_solver in ("dense", "sparse"):
        config = ts.posegraph.solve.PoseGraphSolverConfig(linear_solver=linear_solver)
        cov = ts.posegraph.marginal_covariances(graph, result, pairs=[(3, 5)], config=config)
        assert cov.method == linear_solver
        assert bool((cov.vertices[0] == 0).all())
        diagonal = inverse[torch.arange(N - 1), torch.arange(N - 1)]
        assert _relative(cov.vertices[1:], diagonal) < EXACT
        assert _relative(cov.pairs[0], inverse[2, 4]) < EXACT
    with pytest.raises(ValueError, match="rank deficient"):
        ts.posegraph.marginal_covariances(graph, result, fixed=torch.zeros(0, dtype=torch.long))


def test_cli_writes_the_covariance_file(tmp_path, capsys):
    graph = _ring()
    path, out = tmp_path / "ring.g2o", tmp_path / "sub" / "cov.txt"
    g2o.write_g2o(path, graph)
    # --init file: the same start as solve_pose_graph(read) below, hence the same solution.
    code = cli.main(["posegraph", str(path), "--init", "file", "--covariance", str(out)])
    assert code == 0
    assert f"wrote {out}" in capsys.readouterr().out
    rows = np.loadtxt(out)
    assert rows.shape == (graph.num_vertices, 37)
    assert rows[:, 0].tolist() == graph.ids.tolist()  # the file's ids, in order
    read = g2o.read_g2o(path)
    result = ts.posegraph.solve.solve_pose_graph(read, init="file")
    expected = ts.posegraph.marginal_covariances(read, result).vertices.reshape(-1, 36)
    assert np.allclose(rows[:, 1:], expected.numpy(), rtol=1e-9, atol=0)  # %.17g round trip
    assert (rows[0, 1:] == 0).all()  # the fixed vertex
    matrices = rows[:, 1:].reshape(-1, 6, 6)
    assert np.allclose(matrices, matrices.transpose(0, 2, 1), rtol=1e-12, atol=0)
    code = cli.main(["posegraph", str(path), "--covariance", str(tmp_path)])
    assert code == 2 and "--covariance" in capsys.readouterr().err


def _se2_exp(d):
    x, y, th = d[..., 0], d[..., 1], d[..., 2]
    small = th.abs() < 1e-9
    t = torch.where(small, torch.ones_like(th), th)
    a = torch.where(small, 1 - th**2 / 6, torch.sin(t) / t)
    b = torch.where(small, th / 2, (1 - torch.cos(t)) / t)
    c, s = torch.cos(th), torch.sin(th)
    T = torch.zeros(*d.shape[:-1], 3, 3, dtype=d.dtype)
    T[..., 0, 0], T[..., 0, 1], T[..., 1, 0], T[..., 1, 1] = c, -s, s, c
    T[..., 0, 2], T[..., 1, 2], T[..., 2, 2] = a * x - b * y, b * x + a * y, 1.0
    return T


def _se2_log(T):
    th = torch.atan2(T[..., 1, 0], T[..., 0, 0])
    small = th.abs() < 1e-9
    t = torch.where(small, torch.ones_like(th), th)
    a = torch.where(small, 1 - th**2 / 6, torch.sin(t) / t)
    b = torch.where(small, th / 2, (1 - torch.cos(t)) / t)
    det = a * a + b * b
    px, py = T[..., 0, 2], T[..., 1, 2]
    return torch.stack(((a * px + b * py) / det, (-b * px + a * py) / det, th), -1)


def test_2d_graph_covariances_are_planar_and_match_the_2d_hessian(tmp_path):
    """A VERTEX_SE2/EDGE_SE2 graph yields 3 × 3 (x, y, θ) blocks (GTSAM's Pose2 convention,
    body frame) equal to the inverse of the planar Gauss-Newton Hessian built here by
    brute force on SE(2); the --covariance file holds 9 values per vertex. Tolerance: both
    invert a ~1e4-conditioned 12 × 12 matrix in float64: 1e-8 relative is far above
    round-off."""
    g = torch.Generator().manual_seed(0)
    n = 5
    truth = torch.cumsum(torch.tensor([[1.0, 0.2, 0.3]] * n, dtype=torch.float64), 0)
    truth[0] = 0
    edges = [(i, i + 1) for i in range(n - 1)] + [(0, 3), (1, 4)]
    info = "300 20 5 200 -3 900"  # upper triangle of (x, y, θ), g2o's order
    lines = [f"VERTEX_SE2 {i} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f}" for i, p in enumerate(truth)]
    Ts = torch.stack([_T2(p) for p in truth])
    for i, j in edges:  # g2o's (x, y, θ): the relative pose's translation and angle
        rel = torch.linalg.inv(Ts[i]) @ Ts[j]
        z = torch.stack((rel[0, 2], rel[1, 2], torch.atan2(rel[1, 0], rel[0, 0])))
        z = z + 0.02 * torch.randn(3, generator=g, dtype=torch.float64)
        lines.append(f"EDGE_SE2 {i} {j} {z[0]:.9f} {z[1]:.9f} {z[2]:.9f} {info}")
    path = tmp_path / "planar.g2o"
    path.write_text("\n".join(lines) + "\n")
    graph = ts.io.g2o.read_g2o(path)
    result = ts.posegraph.solve.solve_pose_graph(graph)
    cov = ts.posegraph.marginal_covariances(graph, result)
    assert cov.dimension == 2 and cov.vertices.shape == (n, 3, 3)
    # the planar Hessian by brute force: residual Log(Z⁻¹ T_i⁻¹ T_j), T ← T·Exp(δ), (x, y, θ)
    P = result.poses
    T2 = torch.zeros(n, 3, 3, dtype=torch.float64)
    T2[:, :2, :2], T2[:, :2, 2], T2[:, 2, 2] = P[:, :2, :2], P[:, :2, 3], 1.0
    Z = torch.stack(
        [_T2(torch.tensor([float(v) for v in ln.split()[3:6]], dtype=torch.float64))
         for ln in lines if ln.startswith("EDGE")]
    )  # fmt: skip
    u = torch.tensor([float(v) for v in info.split()], dtype=torch.float64)
    Omega = torch.tensor([[u[0], u[1], u[2]], [u[1], u[3], u[4]], [u[2], u[4], u[5]]])

    def residuals(d):
        T = T2 @ _se2_exp(d.reshape(n, 3))
        out = [_se2_log(torch.linalg.inv(Z[k]) @ torch.linalg.inv(T[i]) @ T[j])
               for k, (i, j) in enumerate(edges)]  # fmt: skip
        return torch.stack(out)

    J = torch.func.jacrev(residuals)(torch.zeros(3 * n, dtype=torch.float64))  # (E, 3, 3n)
    H = torch.einsum("eai,ab,ebj->ij", J, Omega, J)[3:, 3:]  # vertex 0 fixed
    expected = torch.linalg.inv(H).reshape(n - 1, 3, n - 1, 3).diagonal(0, 0, 2).permute(2, 0, 1)
    torch.testing.assert_close(cov.vertices[1:], expected, rtol=1e-8, atol=1e-12)
    assert bool((cov.vertices[0] == 0).all())
    out = tmp_path / "cov.txt"
    assert cli.main(["posegraph", str(path), "--covariance", str(out), "-q"]) == 0
    rows = [line.split() for line in out.read_text().splitlines()]
    assert len(rows) == n and all(len(r) == 10 for r in rows)


def _T2(p):
    c, s = torch.cos(p[2]), torch.sin(p[2])
    return torch.tensor([[c, -s, p[0]], [s, c, p[1]], [0.0, 0.0, 1.0]], dtype=torch.float64)
