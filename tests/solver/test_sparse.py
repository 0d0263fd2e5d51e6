"""The sparse reduced pose system: the block pattern assembles the matrix it is given and its
factorization solves it (every ordering, several problems, failures reported); the sparse
Schur path gives the dense one's steps for every linearization form, pose terms, fixed
variables, damping and batch; whole solves and implicit gradients agree between the two
reduced solvers; "auto" picks by size and pattern; the configuration is validated."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse
import torch

import torchslam
from torchslam import PointMapProblem, SolverConfig, solve_differentiable
from torchslam.data.loop import make_loop_scene
from torchslam.data.synthetic import make_scene
from torchslam.initialization import average_points, chain_relative_poses
from torchslam.lie import se3
from torchslam.objective.terms import PosePriorTerm, RelativePoseTerm
from torchslam.solver import plan as plan_module
from torchslam.solver import sparse
from torchslam.solver.differentiable import ImplicitConfig
from torchslam.solver.linearize import (
    BlockLinearization,
    StructuredLinearization,
    linearize,
    whitening_factors,
)
from torchslam.solver.sparse import BlockPattern, fill_reducing_order

from . import factorize, solve_step

F64 = torch.float64
ORDERINGS = ("mmd", "colamd", "natural")
STEP_TOL = 1e-10


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """These problems are tiny: one intra-op thread. With two on a loaded two-core machine,
    each small op waits at OpenMP barriers and the module ran 20-50x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ------------------------------------------------------------------------------------------
# Block-sparse SPD systems built by hand


def _random_system(m: int, edges: list[list[tuple[int, int]]], seed: int):
    """Upper block contributions of B block-sparse SPD systems and their dense matrices.

    ``edges[b]`` lists the (i, k), i < k, blocks of problem b (repeats add up). Returns
    (keys (T,), contributions (T, 6, 6), diagonal blocks (B, m, 6, 6), dense (B, 6m, 6m)).
    """
    gen = torch.Generator().manual_seed(seed)
    B = len(edges)
    keys, contributions = [], []
    dense = torch.zeros(B, 6 * m, 6 * m, dtype=F64)
    for b, pairs in enumerate(edges):
        for i, k in pairs:
            C = torch.randn(6, 6, generator=gen, dtype=F64)
            keys.append((b * m + i) * m + k)
            contributions.append(C)
            dense[b, 6 * i : 6 * i + 6, 6 * k : 6 * k + 6] += C
            dense[b, 6 * k : 6 * k + 6, 6 * i : 6 * i + 6] += C.T
    # Diagonal blocks A Aᵀ + c I with c above each row's off-diagonal absolute sum: SPD.
    A = torch.randn(B, m, 6, 6, generator=gen, dtype=F64)
    row_sum = dense.abs().sum(-1).reshape(B, m, 6).amax(-1)
    diagonal = A @ A.transpose(-1, -2) + (row_sum + 1.0)[..., None, None] * torch.eye(6, dtype=F64)
    for i in range(m):
        dense[:, 6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += diagonal[:, i]
    return torch.tensor(keys, dtype=torch.long), torch.stack(contributions), diagonal, dense


def _values(pattern: BlockPattern, slot, contributions, diagonal):
    """The pattern's unique upper blocks (Q, 6, 6) from the contributions and diagonal."""
    B, m = diagonal.shape[:2]
    values = torch.zeros(pattern.num_unique, 6, 6, dtype=F64).index_add_(0, slot, contributions)
    diag_keys = torch.arange(B * m) * m + torch.arange(m).repeat(B)
    diag_slot = torch.searchsorted(pattern.keys, diag_keys)
    assert torch.equal(pattern.keys[diag_slot], diag_keys)
    return values.index_add_(0, diag_slot, diagonal.reshape(-1, 6, 6))


def _assembled(pattern: BlockPattern, values) -> torch.Tensor:
    """The B matrices the pattern's CSC layouts hold, back in the original order."""
    flat = values.numpy().reshape(-1, 36)
    out = []
    for layout in pattern.layouts:
        size = layout.indptr.shape[0] - 1
        data = flat[layout.start : layout.stop].ravel()[layout.source]
        permuted = scipy.sparse.csc_matrix((data, layout.indices, layout.indptr), (size, size))
        assert permuted.has_canonical_format  # sorted indices, no duplicates
        # Entry (u, v) of S sits at (position[u], position[v]) of P S Pᵀ.
        full = permuted.toarray()[layout.position][:, layout.position]
        out.append(torch.from_numpy(full))
    return torch.stack(out)


def _random_edges(m: int, count: int, gen: torch.Generator) -> list[tuple[int, int]]:
    i = torch.randint(0, m, (count,), generator=gen)
    k = torch.randint(0, m, (count,), generator=gen)
    keep = i != k
    lo, hi = torch.minimum(i, k)[keep], torch.maximum(i, k)[keep]
    return list(zip(lo.tolist(), hi.tolist(), strict=True))


@pytest.mark.parametrize("ordering", ORDERINGS)
def test_block_pattern_assembles_the_dense_matrix_and_solves_it(ordering):
    m = 9
    gen = torch.Generator().manual_seed(5)
    # Two problems with different patterns; repeated blocks (the chain twice) add up.
    chain = [(i, i + 1) for i in range(m - 1)]
    edges = [chain + chain + [(0, m - 1)], _random_edges(m, 14, gen)]
    keys, contributions, diagonal, dense = _random_system(m, edges, seed=1)
    shuffle = torch.randperm(keys.numel(), generator=gen)  # any order of the keys
    keys, contributions = keys[shuffle], contributions[shuffle]
    pattern, slot = BlockPattern.build(keys, 2, m, ordering)

    # The unique blocks: every problem's diagonal plus the given upper blocks, sorted.
    expected = set(keys.tolist()) | {(b * m + i) * m + i for b in range(2) for i in range(m)}
    assert pattern.keys.tolist() == sorted(expected)
    assert torch.equal(pattern.keys[slot], keys)
    counts = [layout.stop - layout.start for layout in pattern.layouts]
    assert counts[0] != counts[1]  # the two problems really have different patterns
    for layout, q in zip(pattern.layouts, counts, strict=True):
        assert sorted(layout.position.tolist()) == list(range(6 * m))
        assert layout.indices.shape[0] == 36 * (2 * q - m)  # no duplicate, no missing entry
        if ordering == "natural":
            assert layout.position.tolist() == list(range(6 * m))

    values = _values(pattern, slot, contributions, diagonal)
    assert torch.equal(_assembled(pattern, values), dense)

    factor = pattern.factor(values)
    assert factor.ok.tolist() == [True, True]
    rhs = torch.randn(2, 6 * m, generator=gen, dtype=F64)
    x = factor.solve(rhs)
    reference = torch.linalg.solve(dense, rhs)
    torch.testing.assert_close(x, reference, rtol=0, atol=1e-10)
    assert float((dense @ x[..., None])[..., 0].sub(rhs).abs().max()) <= 1e-10
    # Repeated solves with the same factors.
    rhs2 = torch.randn(2, 6 * m, generator=gen, dtype=F64)
    torch.testing.assert_close(
        factor.solve(rhs2), torch.linalg.solve(dense, rhs2), rtol=0, atol=1e-10
    )
    assert torch.equal(factor.solve(rhs), x)


def test_orderings_give_the_same_solution_and_mmd_reduces_fill():
    # An arrow: block 0 couples with every other block. In the natural order its elimination
    # fills the whole matrix; a minimum-degree order eliminates it last, with no fill.
    m = 12
    edges = [[(0, k) for k in range(1, m)] + [(k, k + 1) for k in range(1, m - 1)]]
    keys, contributions, diagonal, dense = _random_system(m, edges, seed=2)
    rhs = torch.randn(1, 6 * m, generator=torch.Generator().manual_seed(3), dtype=F64)
    reference = torch.linalg.solve(dense, rhs)
    fill = {}
    for ordering in ORDERINGS:
        pattern, slot = BlockPattern.build(keys, 1, m, ordering)
        values = _values(pattern, slot, contributions, diagonal)
        assert torch.equal(_assembled(pattern, values), dense)
        factor = pattern.factor(values)
        assert bool(factor.ok.all())
        torch.testing.assert_close(factor.solve(rhs), reference, rtol=0, atol=1e-10)
        lu = factor.factors[0]
        fill[ordering] = lu.L.nnz + lu.U.nnz
        nonzeros = pattern.layouts[0].indices.shape[0]
    # L and U both hold the diagonal: without fill, nnz(L) + nnz(U) = nnz(S) + 6m.
    assert fill["mmd"] == nonzeros + 6 * m, fill
    assert fill["natural"] == (6 * m) * (6 * m + 1), fill  # dense triangles
    # The hub is not eliminated first by mmd.
    i = np.array([0] * (m - 1))
    order = fill_reducing_order(m, i, np.arange(1, m), "mmd")
    assert sorted(order.tolist()) == list(range(m))
    assert order[0] != 0


def test_indefinite_or_singular_matrix_is_reported_not_raised():
    m = 5
    chain = [(i, i + 1) for i in range(m - 1)]
    keys, contributions, diagonal, dense = _random_system(m, [chain, chain, chain], seed=4)
    # Problem 1: a negative diagonal block (indefinite); problem 2: a zero pose (singular).
    diagonal[1, 2] = -diagonal[1, 2]
    dense_1 = dense[1].clone()
    dense_1[12:18, 12:18] = diagonal[1, 2]
    assert float(torch.linalg.eigvalsh(dense_1).min()) < 0
    diagonal[2, 3] = 0.0
    contributions = contributions.clone()
    contributions[2 * (m - 1) + 2 : 2 * (m - 1) + 4] = 0.0  # blocks (2, 3) and (3, 4) of problem 2
    pattern, slot = BlockPattern.build(keys, 3, m)
    factor = pattern.factor(_values(pattern, slot, contributions, diagonal))
    assert factor.ok.tolist() == [True, False, False]
    rhs = torch.randn(3, 6 * m, generator=torch.Generator().manual_seed(0), dtype=F64)
    x = factor.solve(rhs)
    assert torch.equal(x[1:], torch.zeros_like(x[1:]))
    torch.testing.assert_close(x[0], torch.linalg.solve(dense[0], rhs[0]), rtol=0, atol=1e-10)
    # The dense path agrees on which systems fail.
    _, info = torch.linalg.cholesky_ex(torch.stack((dense[0], dense_1)))
    assert info.tolist()[0] == 0 and info.tolist()[1] != 0


def test_indefinite_matrix_with_a_zero_pivot_is_reported():
    A = torch.eye(6, dtype=F64)
    A[0, 0] = A[1, 1] = 0.0
    A[0, 1] = A[1, 0] = 1.0  # eigenvalues −1, 1, 1, …: indefinite
    assert int(torch.linalg.cholesky_ex(A).info) != 0
    pattern, _ = BlockPattern.build(torch.zeros(0, dtype=torch.long), 1, 1)
    assert pattern.factor(A[None]).ok.tolist() == [False]


# ------------------------------------------------------------------------------------------
# Loop problems: local co-visibility, odometry and loop terms


def _pad(x: torch.Tensor, length: int, value=0) -> torch.Tensor:
    """(1, E_b, ...) → (1, length, ...) padded with ``value``."""
    shape = (1, length - x.shape[1], *x.shape[2:])
    return torch.cat((x, torch.full(shape, value, dtype=x.dtype)), dim=1)


def _loop_problem(
    windows=(3, 5),
    *,
    num_poses: int = 20,
    points_per_frame: int = 4,
    weighting: str = "scalar",
    terms: bool = True,
    fixed: bool = False,
    duplicates: bool = False,
    odometry: torch.Tensor | None = None,
    observations: torch.Tensor | None = None,
) -> PointMapProblem:
    """B = len(windows) loop scenes with different co-visibility windows (so different
    observation patterns) as one padded batch, started from the chained odometry.

    With ``terms``: odometry and loop :class:`RelativePoseTerm` with information, one extra
    relative term (i, j) that differs per problem and a :class:`PosePriorTerm`. With
    ``fixed``: poses 0 and 5 + b and every 7th point held fixed. With ``duplicates``: every
    5th observation is repeated (perturbed) at the end, so that a pose sees a point twice
    (same-pose observation pairs) and the edge list is not sorted. ``odometry`` (B, m − 1, 4, 4)
    and ``observations`` (B, E, 3) replace the scenes' (to carry gradients)."""
    loops = [
        make_loop_scene(
            num_poses=num_poses,
            points_per_frame=points_per_frame,
            window=w,
            noise_std=0.02,
            odometry_rotation_deg=2.0,
            odometry_translation=0.05,
            seed=b,
        )
        for b, w in enumerate(windows)
    ]
    B, m = len(loops), num_poses
    n = loops[0].scene.num_points
    edges = [
        [lp.scene.pose_index, lp.scene.point_index, lp.scene.valid, lp.scene.observations]
        for lp in loops
    ]
    if duplicates:
        gen = torch.Generator().manual_seed(3)
        for edge in edges:
            copies = [x[:, ::5] for x in edge]
            copies[3] = copies[3] + 0.01 * torch.randn(copies[3].shape, generator=gen, dtype=F64)
            edge[:] = [torch.cat((x, c), dim=1) for x, c in zip(edge, copies, strict=True)]
    E = max(edge[0].shape[1] for edge in edges)
    pose_index = torch.cat([_pad(edge[0], E) for edge in edges])
    point_index = torch.cat([_pad(edge[1], E) for edge in edges])
    valid = torch.cat([_pad(edge[2], E, False) for edge in edges])
    if observations is None:
        observations = torch.cat([_pad(edge[3], E) for edge in edges])
    odo = torch.stack([lp.odometry for lp in loops])
    if odometry is None:
        odometry = odo
    poses = chain_relative_poses(se3.inverse(odo.detach()))
    points = average_points(poses, pose_index, point_index, observations.detach(), n, valid=valid)

    gen = torch.Generator().manual_seed(7)
    if weighting == "scalar":
        weights = 0.5 + torch.rand(B, E, generator=gen, dtype=F64)
    elif weighting == "information":
        A = torch.randn(B, E, 3, 3, generator=gen, dtype=F64)
        weights = A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=F64)
    else:
        weights = None
    weights = None if weights is None else weights * 0.02**-2

    term_list = []
    if terms:
        info_odo = loops[0].odometry_information().expand(B, m - 1, 6, 6)
        pairs = torch.stack([lp.odometry_pairs for lp in loops])
        term_list.append(RelativePoseTerm(pairs, odometry, information=info_odo))
        term_list.append(
            RelativePoseTerm(
                torch.stack([lp.loop_pairs for lp in loops]),
                torch.stack([lp.loop for lp in loops]),
                information=loops[0].loop_information().expand(B, 1, 6, 6),
            )
        )
        # A long-range relative pose, different per problem, and a prior.
        extra = torch.tensor([[[2, 7 + b]] for b in range(B)])
        gt = torch.stack([lp.scene.poses_gt[0] for lp in loops])
        b_idx = torch.arange(B)[:, None]
        Z = gt[b_idx, extra[..., 0]] @ se3.inverse(gt[b_idx, extra[..., 1]])
        term_list.append(RelativePoseTerm(extra, Z, weight=torch.full((B, 1), 50.0, dtype=F64)))
        prior = torch.full((B, 1), m // 2)
        term_list.append(
            PosePriorTerm(prior, gt[b_idx, prior], weight=torch.full((B, 1), 10.0, dtype=F64))
        )
    fixed_poses = fixed_points = None
    if fixed:
        fixed_poses = torch.zeros(B, m, dtype=torch.bool)
        fixed_poses[:, 0] = True
        for b in range(B):
            fixed_poses[b, 5 + b] = True
        fixed_points = torch.zeros(B, n, dtype=torch.bool)
        fixed_points[:, ::7] = True
    return PointMapProblem(
        poses,
        points,
        pose_index,
        point_index,
        observations,
        valid=valid,
        weights=weights,
        fixed_poses=fixed_poses,
        fixed_points=fixed_points,
        terms=term_list,
    )


LINEARIZATIONS = {
    # name: (weighting, jacobian mode, expected form)
    "structured": ("scalar", "analytic", StructuredLinearization),
    "information": ("information", "analytic", BlockLinearization),
    "jacrev": ("scalar", "jacrev", BlockLinearization),
}
VARIANTS = {
    "points-only": {"terms": False},
    "terms": {"terms": True},
    "terms-fixed": {"terms": True, "fixed": True},
    "duplicates": {"terms": True, "duplicates": True},
}


def _linearized(linearization: str, variant: str):
    weighting, mode, form = LINEARIZATIONS[linearization]
    problem = _loop_problem(weighting=weighting, **VARIANTS[variant])
    data = problem.data
    xi, X = problem.pose_tangent.detach(), problem.points.detach()
    lin = linearize(xi, X, data, whitening_factors(data), mode)
    assert isinstance(lin, form)
    return problem, data, lin


@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("linearization", list(LINEARIZATIONS))
@pytest.mark.parametrize("damping", ["marquardt", "levenberg"])
def test_sparse_and_dense_reduced_systems_give_the_same_step(linearization, variant, damping):
    problem, data, lin = _linearized(linearization, variant)
    B, m = problem.batch_size, problem.num_poses
    plan = plan_module.LinearPlan.build(data, SolverConfig(reduced_solver="sparse"))
    same_pose_pairs = int((plan.pairs.same_pose & ~plan.pairs.self_pair).sum())
    assert (same_pose_pairs > 0) == (variant == "duplicates")
    # The pattern is sparse and differs between the two problems.
    sizes = [layout.stop - layout.start for layout in plan.reduced.pattern.layouts]
    assert sizes[0] != sizes[1]
    assert max(sizes) < m * (m + 1) // 4
    for value in (0.0, 1e-3, 10.0):
        lam = torch.full((B,), value, dtype=F64)
        dp_d, dl_d, ok_d = solve_step(lin, data, lam, damping)
        dp_s, dl_s, ok_s = solve_step(lin, data, lam, damping, reduced_solver="sparse")
        assert ok_d.tolist() == ok_s.tolist() == [True] * B
        scale = max(float(dp_d.abs().max()), float(dl_d.abs().max()))
        assert scale > 1e-3  # a real step
        torch.testing.assert_close(dp_s, dp_d, rtol=0, atol=STEP_TOL * scale)
        torch.testing.assert_close(dl_s, dl_d, rtol=0, atol=STEP_TOL * scale)
        # Fixed variables do not move.
        assert torch.all(dp_s[data.fixed_poses] == 0)
        assert torch.all(dl_s[data.fixed_points] == 0)
        if isinstance(lin, BlockLinearization) and variant != "points-only":
            # An independent reference: the full (6m + 3n)² system with the terms' blocks.
            dp_f, dl_f, ok_f = solve_step(lin, data, lam, damping, "dense")
            assert bool(ok_f.all())
            torch.testing.assert_close(dp_s, dp_f, rtol=0, atol=STEP_TOL * scale)
            torch.testing.assert_close(dl_s, dl_f, rtol=0, atol=STEP_TOL * scale)


@pytest.mark.parametrize("linearization", ["structured", "information"])
def test_factorization_solves_repeatedly_for_any_gradient(linearization):
    problem, data, lin = _linearized(linearization, "terms-fixed")
    B = problem.batch_size
    lam = torch.full((B,), 1e-2, dtype=F64)
    factored = {
        "sparse": factorize(lin, data, lam, "marquardt", reduced_solver="sparse"),
        "dense": factorize(lin, data, lam, "marquardt"),
    }
    gen = torch.Generator().manual_seed(9)
    first = None
    for _ in range(3):
        gp = torch.randn(lin.pose_gradient.shape, generator=gen, dtype=F64)
        gl = torch.randn(lin.point_gradient.shape, generator=gen, dtype=F64)
        gp[data.fixed_poses] = 0.0
        gl[data.fixed_points] = 0.0
        fresh = solve_step(
            dataclasses.replace(lin, pose_gradient=gp, point_gradient=gl),
            data,
            lam,
            "marquardt",
            reduced_solver="sparse",
        )
        for f in factored.values():
            dp, dl = f.solve(gp, gl)
            scale = float(dp.abs().max())
            torch.testing.assert_close(dp, fresh[0], rtol=0, atol=STEP_TOL * scale)
            torch.testing.assert_close(dl, fresh[1], rtol=0, atol=STEP_TOL * scale)
        if first is None:
            first = (gp, gl, factored["sparse"].solve(gp, gl))
    # Solving again for the first gradient reproduces it exactly: the factors are unchanged.
    dp, dl = factored["sparse"].solve(first[0], first[1])
    assert torch.equal(dp, first[2][0]) and torch.equal(dl, first[2][1])
    assert factored["sparse"].ok.tolist() == [True] * B


# ------------------------------------------------------------------------------------------
# Whole solves and the automatic choice


def _count_sparse_builds(monkeypatch) -> list[int]:
    calls = []
    build = plan_module.SparseReduced.build

    def spy(*args, **kwargs):
        calls.append(1)
        return build(*args, **kwargs)

    monkeypatch.setattr(plan_module.SparseReduced, "build", staticmethod(spy))
    return calls


def test_sparse_and_dense_reduced_solvers_reach_the_same_solution(monkeypatch):
    calls = _count_sparse_builds(monkeypatch)
    results = {}
    for name, options in (
        ("dense", {"reduced_solver": "dense"}),
        ("sparse", {"reduced_solver": "sparse"}),
        ("auto", {"reduced_solver": "auto", "dense_max_variables": 300}),
    ):
        before = len(calls)
        problem = _loop_problem((3,), num_poses=80, points_per_frame=3)
        results[name] = torchslam.solve(problem, SolverConfig(**options))
        assert all(results[name].converged), results[name].summary()
        assert len(calls) - before == (0 if name == "dense" else 1), name
    dense = results["dense"]
    for name in ("sparse", "auto"):
        r = results[name]
        assert r.iterations.tolist() == dense.iterations.tolist()
        assert r.status == dense.status
        torch.testing.assert_close(r.cost_history, dense.cost_history, rtol=1e-10, atol=0)
        torch.testing.assert_close(r.final_cost, dense.final_cost, rtol=1e-12, atol=0)
        torch.testing.assert_close(r.poses, dense.poses, rtol=0, atol=1e-9)
        torch.testing.assert_close(r.points, dense.points, rtol=0, atol=1e-9)
    assert float(dense.initial_cost[0]) > 10 * float(dense.final_cost[0])


def test_auto_picks_sparse_for_large_sparse_problems_only():
    choose = plan_module.choose_reduced_solver
    # Local co-visibility: m = 150 poses, 3 points per frame seen by 3 frames.
    loop = _loop_problem((3,), num_poses=150, points_per_frame=3, terms=False).data
    assert choose(loop, "auto", 6 * 150 - 1) == "sparse"
    assert choose(loop, "auto", 6 * 150) == "dense"  # small enough for the dense factorization
    assert choose(loop, "auto", SolverConfig().dense_max_variables) == "sparse"
    # Many views per point, but local: still a band, sparse.
    wide = _loop_problem((12,), num_poses=150, points_per_frame=12, terms=False).data
    assert choose(wide, "auto", 6 * 150 - 1) == "sparse"
    assert choose(wide, "auto", 6 * 150 - 1, max_pairs=10) == "dense"  # too many pairs to form
    # Dense co-visibility: every point seen by every frame.
    scene = make_scene(200, 30, visible_fraction=1.0, seed=2)
    covisible = PointMapProblem(
        scene.poses_gt, scene.points_gt, scene.pose_index, scene.point_index, scene.observations
    ).data
    assert choose(covisible, "auto", 60) == "dense"
    # Few blocks but in random places: the factor fills in, dense.
    scattered = make_scene(200, 400, visible_fraction=0.02, seed=3)
    data = PointMapProblem(
        scattered.poses_gt,
        scattered.points_gt,
        scattered.pose_index,
        scattered.point_index,
        scattered.observations,
    ).data
    assert choose(data, "auto", 60) == "dense"
    # An explicit choice is kept.
    for data in (loop, covisible):
        assert choose(data, "sparse", 0) == "sparse"
        assert choose(data, "dense", 0) == "dense"


def test_factorization_work_of_a_band_and_of_a_dense_pattern():
    n = 50
    chain = np.arange(n - 1)
    # A chain factors without fill: column counts 2 (1 at the end).
    assert sparse.factorization_work(n, chain, chain + 1, "mmd") == 4.0 * (n - 1) + 1.0
    i, k = np.triu_indices(n, 1)
    assert sparse.factorization_work(n, i, k, "mmd") == sum(c * c for c in range(1, n + 1))


# ------------------------------------------------------------------------------------------
# Implicit gradients


@pytest.mark.parametrize("hessian", ["exact", "gauss_newton"])
def test_implicit_gradients_agree_between_sparse_and_dense(hessian, monkeypatch):
    calls = _count_sparse_builds(monkeypatch)
    grads = {}
    for reduced in ("sparse", "dense"):
        before = len(calls)
        base = _loop_problem((3,), num_poses=16, points_per_frame=4)
        odometry = base.data.terms[0].constants["measurements"].detach().clone()
        observations = base.data.observations.detach().clone()
        odometry.requires_grad_(True)
        observations.requires_grad_(True)
        problem = _loop_problem(
            (3,), num_poses=16, points_per_frame=4, odometry=odometry, observations=observations
        )
        config = SolverConfig(reduced_solver=reduced, function_tolerance=1e-14)
        result = solve_differentiable(
            problem.pose_tangent.detach(),
            problem.points.detach(),
            problem.data,
            config,
            backward="implicit",
            implicit=ImplicitConfig(hessian=hessian),
        )
        assert all(result.converged), result.summary()
        gen = torch.Generator().manual_seed(1)
        c = torch.randn(result.pose_tangent.shape, generator=gen, dtype=F64)
        d = torch.randn(result.points.shape, generator=gen, dtype=F64)
        loss = (c * result.pose_tangent).sum() + (d * result.points).sum()
        grads[reduced] = torch.autograd.grad(loss, (odometry, observations))
        # The sparse structure is built for the forward solve and for the backward's factor.
        assert len(calls) - before == (2 if reduced == "sparse" else 0)
    for g_sparse, g_dense in zip(grads["sparse"], grads["dense"], strict=True):
        assert float(g_dense.norm()) > 1e-3
        error = float((g_sparse - g_dense).norm() / g_dense.norm())
        assert error <= 1e-8, error


@pytest.mark.parametrize("backward", ["unrolled", "truncated"])
def test_unrolled_and_truncated_refuse_the_sparse_reduced_solver(backward):
    problem = _loop_problem((3,), num_poses=8, points_per_frame=3, terms=False)
    with pytest.raises(ValueError, match="reduced_solver"):
        solve_differentiable(
            problem.pose_tangent.detach().requires_grad_(),
            problem.points.detach(),
            problem.data,
            SolverConfig(reduced_solver="sparse"),
            backward=backward,
        )


# ------------------------------------------------------------------------------------------
# Configuration


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("reduced_solver", "cholmod"),
        ("reduced_solver", None),
        ("ordering", "amd"),
        ("ordering", "MMD"),
        ("dense_max_variables", -1),
        ("dense_max_variables", 1.5),
        ("dense_max_variables", "1200"),
    ],
)
def test_config_rejects_bad_reduced_solver_options(field, value):
    with pytest.raises(ValueError, match=f"'{field}'"):
        SolverConfig(**{field: value})


def test_config_accepts_every_reduced_solver_and_ordering():
    for reduced in ("auto", "dense", "sparse"):
        for ordering in ORDERINGS:
            config = SolverConfig(reduced_solver=reduced, ordering=ordering, dense_max_variables=0)
            assert (config.reduced_solver, config.ordering) == (reduced, ordering)


def test_a_non_finite_solution_is_reported_not_ok():
    A = torch.eye(6, dtype=F64)[None].expand(2, 6, 6) * 2.0
    pattern, _ = BlockPattern.build(torch.zeros(0, dtype=torch.long), 2, 1)
    factor = pattern.factor(A.reshape(-1, 6, 6))
    assert factor.ok.tolist() == [True, True]
    rhs = torch.ones(2, 6, dtype=F64)
    rhs[1, 3] = float("nan")
    x = factor.solve(rhs)
    assert torch.equal(x[0], torch.full((6,), 0.5, dtype=F64))
    assert torch.equal(x[1], torch.zeros(6, dtype=F64))
    assert factor.ok.tolist() == [True, False]
