"""The SE-Sync objective as a term (3D and 2D) and SE-Sync's certificate of global optimality.

Reference values are built independently of the sparse code: the data matrix M is half the
Hessian of the SE-Sync objective of one row of X = [t R] (the objective separates over the
d rows of X), the rotation-only form Q its Schur complement with a dense pseudo-inverse.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchslam.io import g2o
from torchslam.lie import se3
from torchslam.manifold import right_jacobian_jacrev
from torchslam.objective.terms import term_blocks, term_poses, terms_cost
from torchslam.posegraph import PoseGraph, certification, objectives
from torchslam.posegraph.solve import PoseGraphSolverConfig, graph_data, solve_pose_graph

D = torch.float64


def _graph_3d(generator, n=5, loops=4, noise=0.05):
    """A connected 3D graph: odometry chain + random loop closures over random true poses,
    measurements with noise, anisotropic information with cross terms."""
    xi = torch.randn(n, 6, generator=generator, dtype=D)
    xi[:, 3:] *= 3.0
    truth = se3.exp(xi)
    truth[0] = torch.eye(4, dtype=D)
    chain = torch.stack((torch.arange(n - 1), torch.arange(1, n)), dim=-1)
    extra = torch.stack(
        (
            torch.randint(0, n // 2, (loops,), generator=generator),
            torch.randint(n // 2, n, (loops,), generator=generator),
        ),
        dim=-1,
    )
    edges = torch.cat((chain, extra))
    E = edges.shape[0]
    Z = se3.inverse(truth[edges[:, 0]]) @ truth[edges[:, 1]]
    Z = Z @ se3.exp(noise * torch.randn(E, 6, generator=generator, dtype=D))
    A = torch.randn(E, 6, 6, generator=generator, dtype=D)
    information = A @ A.transpose(-1, -2) + 4 * torch.eye(6, dtype=D)
    start = truth @ se3.exp(0.05 * torch.randn(n, 6, generator=generator, dtype=D))
    start[0] = truth[0]
    return PoseGraph(
        ids=torch.arange(n), poses=start, edges=edges, measurements=Z, information=information
    )


def _graph_2d(generator, n=5, noise=0.05):
    """A connected 2D graph as g2o text (odometry + loop closures), read by parse_g2o."""
    rng = np.random.default_rng(int(torch.randint(0, 2**31, (1,), generator=generator)))
    truth = np.column_stack((rng.normal(0, 3, n), rng.normal(0, 3, n), rng.uniform(-3, 3, n)))
    pairs = [(k, k + 1) for k in range(n - 1)] + [(0, n - 1), (1, n - 2), (0, 2)]
    lines = [
        f"VERTEX_SE2 {k} {x + 0.1:.17g} {y - 0.1:.17g} {th + 0.05:.17g}"
        for k, (x, y, th) in enumerate(truth)
    ]
    for a, b in pairs:
        xa, ya, ta = truth[a]
        xb, yb, tb = truth[b]
        c, s = math.cos(ta), math.sin(ta)
        dx, dy = c * (xb - xa) + s * (yb - ya), -s * (xb - xa) + c * (yb - ya)
        dt = tb - ta
        dx, dy, dt = (v + noise * rng.standard_normal() for v in (dx, dy, dt))
        i11, i22, i33 = rng.uniform(5, 20, 3)
        i12, i13, i23 = rng.uniform(-1, 1, 3)
        lines.append(
            f"EDGE_SE2 {a} {b} {dx:.17g} {dy:.17g} {dt:.17g} "
            f"{i11:.17g} {i12:.17g} {i13:.17g} {i22:.17g} {i23:.17g} {i33:.17g}"
        )
    return g2o.parse_g2o("\n".join(lines) + "\n")


def _dense_data(graph):
    """(M, Q, d, n) built from the objective's Hessian (module docstring)."""
    d = 2 if graph.dimension == 2 else 3
    n = graph.num_vertices
    kappa, tau = objectives.graph_sesync_weights(graph)
    Z = graph.measurements

    def one_row(x):  # x = [t (n), R-row blocks (d n)]
        t, R = x[:n], x[n:].reshape(n, d)
        total = x.new_zeros(())
        for e, (i, j) in enumerate(graph.edges.tolist()):
            Rm, tm = Z[e, :d, :d], Z[e, :d, 3]
            total = total + kappa[e] * (R[j] - R[i] @ Rm).square().sum()
            total = total + tau[e] * (t[j] - t[i] - R[i] @ tm).square()
        return total

    H = torch.autograd.functional.hessian(one_row, torch.zeros(n + d * n, dtype=D))
    M = 0.5 * H.numpy()
    M_tt, M_tR, M_RR = M[:n, :n], M[:n, n:], M[n:, n:]
    Q = M_RR - M_tR.T @ np.linalg.pinv(M_tt) @ M_tR
    return M, 0.5 * (Q + Q.T), d, n


def _rotation_row(poses, d):
    R = poses[:, :d, :d].numpy()
    return R.transpose(1, 0, 2).reshape(d, -1)


def _dense_certificate(graph, poses):
    M, Q, d, n = _dense_data(graph)
    R = _rotation_row(poses, d)
    QRt = (Q @ R.T).reshape(n, d, d)
    P = QRt @ R.reshape(d, n, d).transpose(1, 0, 2)
    Lam = np.zeros_like(Q)
    for i in range(n):
        Lam[d * i : d * i + d, d * i : d * i + d] = 0.5 * (P[i] + P[i].T)
    S = Q - Lam
    return np.linalg.eigvalsh(S)[0], float(np.trace(R @ Q @ R.T)), M, Q, R


# ----------------------------------------------------------------------------------------
# The SE-Sync term


def test_sesync_term_jacobians_match_jacrev_and_central_differences(generator):
    graph = _graph_3d(generator, n=6, loops=5, noise=0.3)
    term = objectives.SESyncTerm.from_graph(graph).bind(1, graph.num_vertices, graph.poses)
    T = term_poses(term, graph.poses[None])
    r, J, _ = term_blocks(term, T, mode="analytic")
    r2, J2, _ = term_blocks(term, T, mode="jacrev")
    # float64 and O(1) poses: analytic and autodiff blocks agree to round-off.
    assert torch.allclose(r, r2, atol=1e-13) and torch.allclose(J, J2, atol=1e-12)
    assert r.shape[-1] == 12 and J.shape[-3:] == (12, 2, 6)
    # Central differences, step 1e-6: truncation O(h²) ≈ 1e-12, round-off O(ε/h) ≈ 1e-10.
    h = 1e-6
    constants = {k: v for k, v in term.constants.items()}
    for a in range(2):
        for k in range(6):
            delta = torch.zeros(6, dtype=D)
            delta[k] = h
            plus, minus = T.clone(), T.clone()
            plus[..., a, :, :] = T[..., a, :, :] @ se3.exp(delta)
            minus[..., a, :, :] = T[..., a, :, :] @ se3.exp(-delta)
            numeric = (term.residual(plus, **constants) - term.residual(minus, **constants)) / (
                2 * h
            )
            assert torch.allclose(numeric, J[..., :, a, k], atol=1e-8)
    (J3,) = right_jacobian_jacrev(
        lambda P, **c: term.residual(P, **c), (T,), constants=constants, batch_dims=2
    )
    assert torch.allclose(J3, J, atol=1e-12)


@pytest.mark.parametrize("dimension", [3, 2])
def test_loop_cost_is_the_sesync_objective(generator, dimension):
    graph = _graph_3d(generator, noise=0.3) if dimension == 3 else _graph_2d(generator)
    data = graph_data(graph, objective="sesync")
    cost = terms_cost(data.terms, graph.poses[None])
    expected = objectives.sesync_objective(graph)
    # Same sums in a different order: round-off only.
    assert float(cost[0]) == pytest.approx(float(expected), rel=1e-12)


def test_2d_objective_by_hand():
    # Three poses, three edges; SE-Sync's 2D weights τ = 2 / tr(I_tt⁻¹), κ = I_θθ.
    text = (
        "VERTEX_SE2 0 0 0 0\n"
        "VERTEX_SE2 1 1 0 0.5\n"
        "VERTEX_SE2 2 1 1 1.5\n"
        "EDGE_SE2 0 1 1 0.1 0.4  4 1 0 2 0 10\n"
        "EDGE_SE2 1 2 1 -0.1 1  2 0 0.5 8 0 20\n"
        "EDGE_SE2 0 2 1 1 1.5  1 0 0 1 0 1\n"
    )
    graph = g2o.parse_g2o(text)
    assert graph.dimension == 2
    poses = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.5), (1.0, 1.0, 1.5)]
    edges = [
        (0, 1, (1.0, 0.1, 0.4), [[4, 1], [1, 2]], 10.0),
        (1, 2, (1.0, -0.1, 1.0), [[2, 0], [0, 8]], 20.0),
        (0, 2, (1.0, 1.0, 1.5), [[1, 0], [0, 1]], 1.0),
    ]

    def rot(a):
        return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])

    expected = 0.0
    for i, j, (dx, dy, dt), I_tt, I_33 in edges:
        tau = 2.0 / np.trace(np.linalg.inv(np.array(I_tt, dtype=float)))
        kappa = I_33
        (xi, yi, ti), (xj, yj, tj) = poses[i], poses[j]
        R_i, R_j = rot(ti), rot(tj)
        rotation = np.sum((R_j - R_i @ rot(dt)) ** 2)
        translation = np.sum(
            (np.array([xj, yj]) - np.array([xi, yi]) - R_i @ np.array([dx, dy])) ** 2
        )
        expected += kappa * rotation + tau * translation
    value = float(objectives.sesync_objective(graph))
    assert value == pytest.approx(expected, rel=1e-13)
    kappa, tau = objectives.graph_sesync_weights(graph)
    assert kappa.tolist() == [10.0, 20.0, 1.0]
    assert float(tau[2]) == pytest.approx(1.0, rel=1e-15)


def test_sesync_solve_reaches_a_certified_optimum_3d(generator):
    graph = _graph_3d(generator, n=6, loops=5, noise=0.1)
    result = solve_pose_graph(graph, config=PoseGraphSolverConfig(objective="sesync"))
    assert result.converged
    assert result.final_cost == pytest.approx(
        float(objectives.sesync_objective(graph, result.poses)), rel=1e-12
    )
    certificate = certification.certify(graph, result.poses)
    assert certificate.certified
    assert certificate.objective == pytest.approx(result.final_cost, rel=1e-9)
    assert certificate.suboptimality_bound <= 1e-6 * certificate.objective


def test_sesync_solve_of_a_2d_graph_stays_planar(generator):
    graph = _graph_2d(generator, n=7, noise=0.2)
    result = solve_pose_graph(graph, config=PoseGraphSolverConfig(objective="sesync"))
    assert result.converged
    # Planar start, no out-of-plane gradient or coupling: the out-of-plane entries stay 0
    # up to round-off of the exponential map.
    planar = torch.tensor([0.0, 0.0, 1.0, 0.0], dtype=D)
    assert (result.poses[:, 2, :] - planar).abs().max() <= 1e-14
    assert result.poses[:, :2, 2].abs().max() <= 1e-14
    assert result.final_cost == pytest.approx(
        float(objectives.sesync_objective(graph, result.poses)), rel=1e-12
    )
    certificate = certification.certify(graph, result.poses)
    assert certificate.dimension == 2 and certificate.certified


# ----------------------------------------------------------------------------------------
# The certificate against dense linear algebra


@pytest.mark.parametrize("dimension", [3, 2])
@pytest.mark.parametrize("at", ["optimum", "perturbed"])
def test_certificate_matches_dense_eigendecomposition(generator, dimension, at):
    graph = _graph_3d(generator, noise=0.2) if dimension == 3 else _graph_2d(generator)
    poses = solve_pose_graph(graph, config=PoseGraphSolverConfig(objective="sesync")).poses
    if at == "perturbed":
        delta = torch.zeros(graph.num_vertices, 6, dtype=D)
        delta[:, 2 if dimension == 2 else slice(0, 3)] = 0.8 * torch.randn(
            graph.num_vertices, 1 if dimension == 2 else 3, generator=generator, dtype=D
        ).squeeze(-1)
        poses = poses @ se3.exp(delta)
    lam_dense, objective_dense, M, Q, R = _dense_certificate(graph, poses)
    certificate = certification.certify(graph, poses)
    # The sparse matrices are the dense M (assembled from the objective's Hessian).
    matrices = certification.sesync_matrices(graph)
    assert np.abs(matrices.full.toarray() - M).max() <= 1e-12 * np.abs(M).max()
    # Q from sparse products equals the dense Schur complement.
    dn = Q.shape[0]
    Qx = matrices.q_product(np.eye(dn))
    assert np.abs(Qx - Q).max() <= 1e-10 * np.abs(Q).max()
    # λ_min: shift-invert Lanczos vs LAPACK on a ≤ 15 × 15 matrix with entries O(10²):
    # both accurate to ~1e-12 relative to ‖S‖.
    scale = np.abs(Q).max()
    assert abs(certificate.lambda_min - lam_dense) <= 1e-10 * scale
    assert certificate.objective == pytest.approx(objective_dense, rel=1e-10)
    if at == "optimum":
        assert certificate.certified and lam_dense >= -1e-9 * scale
    else:
        assert not certificate.certified and lam_dense < -1e-3
    # f(R, t*(R)) = tr(R Q Rᵀ): the objective at the optimal translations.
    d, n = certificate.dimension, graph.num_vertices
    t = matrices.translations(R)
    T = poses.clone()
    T[:, :d, 3] = torch.from_numpy(t.T)
    assert float(objectives.sesync_objective(graph, T)) == pytest.approx(
        certificate.objective, rel=1e-10
    )
    # The dense optimal translations (t_0 = 0) agree.
    M_tt, M_tR = M[:n, :n], M[:n, n:]
    t_dense = -R @ M_tR.T @ np.linalg.pinv(M_tt)
    t_dense -= t_dense[:, :1]
    assert np.abs(t - t_dense).max() <= 1e-9 * max(1.0, np.abs(t).max())
    # The dual bound holds: lower ≤ objective, and a certified optimum has a tiny gap.
    assert certificate.lower_bound <= certificate.objective


def test_certificate_is_invariant_to_the_gauge(generator):
    graph = _graph_3d(generator)
    poses = solve_pose_graph(graph, config=PoseGraphSolverConfig(objective="sesync")).poses
    G = se3.exp(torch.tensor([0.3, -1.0, 2.0, 5.0, 1.0, -2.0], dtype=D))
    a = certification.certify(graph, poses)
    b = certification.certify(graph, G @ poses)
    assert a.certified and b.certified
    assert b.objective == pytest.approx(a.objective, rel=1e-10)


def test_certify_rejects_bad_input(generator):
    graph = _graph_3d(generator)
    with pytest.raises(TypeError, match="certify: argument 'graph'"):
        certification.certify("graph")
    with pytest.raises(ValueError, match="certify: argument 'tolerance'"):
        certification.certify(graph, tolerance=-1.0)
    with pytest.raises(ValueError, match="certify: argument 'poses'"):
        certification.certify(graph, graph.poses[:2])
    nan = graph.poses.clone()
    nan[1, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"certify: .*poses"):
        certification.certify(graph, nan)
    split = PoseGraph(
        ids=torch.arange(4),
        poses=se3.identity(4, dtype=D),
        edges=torch.tensor([[0, 1], [2, 3]]),
        measurements=se3.identity(2, dtype=D),
        information=torch.eye(6, dtype=D).expand(2, 6, 6).clone(),
    )
    with pytest.raises(ValueError, match="certify: the graph must be connected"):
        certification.certify(split)
    with pytest.raises(ValueError, match="PoseGraphSolverConfig: 'objective'"):
        PoseGraphSolverConfig(objective="l2")


@pytest.mark.parametrize("objective", ["chi2", "sesync"])
def test_cli_certifies(generator, tmp_path, objective):
    from torchslam.cli.posegraph import PoseGraphOptions, run_posegraph

    path = tmp_path / "tiny.g2o"
    g2o.write_g2o(path, _graph_3d(generator, n=6, loops=5, noise=0.1))
    lines = []
    run_posegraph(
        PoseGraphOptions(path=path, objective=objective, certify=True, init="chordal"),
        echo=lines.append,
    )
    text = "\n".join(lines)
    assert "certified global optimum: yes (λ_min = " in text
    assert f"(minimized: {objective})" in text
    assert ("SE-Sync refinement of the chi2 solution" in text) == (objective == "chi2")
