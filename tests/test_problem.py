"""PointMapProblem (issue 3): residuals, cost, weights, padding, constructors, bad input.

The Jacobians (analytic, jacrev, dense) are tested in tests/test_jacobians.py.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import pytest
import torch
from torch import Tensor, nn

from tests.helpers import TOL
from torchslam.data.synthetic import make_scene
from torchslam.lie import se3
from torchslam.losses import HuberLoss
from torchslam.objective import data as data_module
from torchslam.problem import PointMapProblem

F64 = torch.float64

# --------------------------------------------------------------------------- the hand problem
#
# m = 2 poses, n = 3 points, E = 6 observations (both frames see every point).
# T_00 = I; T_10 = [R | t] with R = Rz(90°): (x, y, z) ↦ (−y, x, z) and t = (1, 2, 3).
# X_0 = (1, 0, 0), X_1 = (0, 1, 0), X_2 = (0, 0, 2), so
#   T_10 X_0 = (0, 1, 0) + t = (1, 3, 3),  T_10 X_1 = (−1, 0, 0) + t = (0, 2, 3),
#   T_10 X_2 = (0, 0, 2) + t = (1, 2, 5),  and T_00 X_j = X_j.
# The observations below differ from these by the residuals r = X_ij − T_i0 X_j in _HAND_R.
_HAND_T1 = [[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0, 0, 0, 1.0]]
_HAND_POINTS = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0]]
_HAND_POSE_INDEX = [0, 0, 0, 1, 1, 1]
_HAND_POINT_INDEX = [0, 1, 2, 0, 1, 2]
_HAND_OBS = [
    [1.0, 0.0, 0.5],
    [0.0, 1.0, 0.0],
    [0.1, 0.0, 2.0],
    [1.5, 3.0, 2.0],
    [0.0, 2.0, 3.0],
    [1.0, 2.2, 5.0],
]
_HAND_R = [
    [0.0, 0.0, 0.5],
    [0.0, 0.0, 0.0],
    [0.1, 0.0, 0.0],
    [0.5, 0.0, -1.0],
    [0.0, 0.0, 0.0],
    [0.0, 0.2, 0.0],
]
# |r|² = 0.25, 0, 0.01, 1.25, 0, 0.04 → Σ = 1.55, cost ½ Σ = 0.775.
_HAND_COST = 0.775


def _hand_inputs(dtype=F64) -> dict[str, Tensor]:
    poses = torch.stack((torch.eye(4, dtype=F64), torch.tensor(_HAND_T1, dtype=F64)))
    return {
        "poses": poses[None].to(dtype),
        "points": torch.tensor([_HAND_POINTS], dtype=dtype),
        "pose_index": torch.tensor([_HAND_POSE_INDEX]),
        "point_index": torch.tensor([_HAND_POINT_INDEX]),
        "observations": torch.tensor([_HAND_OBS], dtype=dtype),
    }


def _hand_problem(**kwargs) -> PointMapProblem:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the hand problem is well posed
        return PointMapProblem(**_hand_inputs(), **kwargs)


def _hand_residuals() -> Tensor:
    return torch.tensor([_HAND_R], dtype=F64)


# --------------------------------------------------------------------------- random problems


def _scene_problem(
    seed: int = 0,
    batch_size: int = 2,
    num_poses: int = 4,
    num_points: int = 12,
    *,
    perturb: float = 0.05,
    dtype=F64,
    **kwargs,
) -> PointMapProblem:
    """A well-posed synthetic problem with its poses and points moved off the ground truth."""
    scene = make_scene(
        num_poses, num_points, batch_size=batch_size, visible_fraction=0.75, seed=seed
    )
    g = torch.Generator().manual_seed(seed + 100)
    B, m, n = batch_size, num_poses, num_points
    delta = perturb * torch.randn(B, m, 6, generator=g, dtype=F64)
    poses = scene.poses_gt @ se3.exp(delta)
    points = scene.points_gt + perturb * torch.randn(B, n, 3, generator=g, dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return PointMapProblem(
            poses.to(dtype),
            points.to(dtype),
            scene.pose_index,
            scene.point_index,
            scene.observations.to(dtype),
            valid=scene.valid,
            **kwargs,
        )


def _random_information(shape: tuple[int, ...], generator: torch.Generator) -> Tensor:
    """Symmetric positive definite 3×3 matrices A Aᵀ + 0.5 I, shape (*shape, 3, 3)."""
    A = torch.randn(*shape, 3, 3, generator=generator, dtype=F64)
    return A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=F64)


# --------------------------------------------------------------------------- values


def test_raw_residuals_and_cost_of_the_hand_problem():
    problem = _hand_problem()
    torch.testing.assert_close(problem.raw_residuals(), _hand_residuals(), atol=1e-12, rtol=0)
    # Unweighted: whitened residuals are the raw ones.
    torch.testing.assert_close(problem.residuals(), _hand_residuals(), atol=1e-12, rtol=0)
    torch.testing.assert_close(problem.cost(), torch.tensor([_HAND_COST], dtype=F64))
    torch.testing.assert_close(problem(), problem.cost())  # forward is the cost
    assert problem.cost().shape == (1,)
    assert problem.residuals().shape == (1, 6, 3)


def test_scalar_weights_scale_the_squared_norms():
    weights = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]], dtype=F64)
    problem = _hand_problem(weights=weights)
    # w · |r|² = 0.25, 0, 0.03, 5.0, 0, 0.24 → Σ = 5.52.
    torch.testing.assert_close(problem.cost(), torch.tensor([0.5 * 5.52], dtype=F64))
    # residuals() is the whitened residual √w r, raw_residuals() is unchanged.
    expected = weights.sqrt()[..., None] * _hand_residuals()
    torch.testing.assert_close(problem.residuals(), expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(problem.raw_residuals(), _hand_residuals(), atol=1e-12, rtol=0)


def test_information_matrices_give_r_omega_r_and_whitening_by_l_transpose():
    # Ω = L Lᵀ with a hand-chosen Cholesky factor (unique for SPD Ω with a positive diagonal).
    L = torch.tensor([[1.0, 0.0, 0.0], [0.5, 2.0, 0.0], [0.0, 0.3, 1.5]], dtype=F64)
    omega = L @ L.T  # [[1, .5, 0], [.5, 4.25, .6], [0, .6, 2.34]]
    information = omega.expand(1, 6, 3, 3).clone()
    problem = _hand_problem(weights=information)
    # rᵀΩr by hand: (0,0,.5) → 2.34·.25 = 0.585; (.1,0,0) → 0.01; (.5,0,−1) → .25 + 2.34 =
    # 2.59; (0,.2,0) → 4.25·.04 = 0.17; Σ = 3.355.
    torch.testing.assert_close(problem.cost(), torch.tensor([0.5 * 3.355], dtype=F64))
    whitened = problem.residuals()
    expected = (L.T @ _hand_residuals()[..., None])[..., 0]
    torch.testing.assert_close(whitened, expected, atol=1e-12, rtol=0)
    # ‖Lᵀ r‖² = rᵀΩr per observation.
    torch.testing.assert_close(
        0.5 * (whitened**2).sum((-1, -2)), problem.cost(), atol=1e-12, rtol=0
    )


def test_huber_loss_gives_half_sum_of_rho():
    a = 0.4  # knee at s = a² = 0.16: s = 0.25 and 1.25 are linear, 0, 0.01, 0.04 quadratic
    problem = _hand_problem(loss=HuberLoss(a))

    def huber(s: float) -> float:
        return s if s <= a * a else 2 * a * math.sqrt(s) - a * a

    expected = 0.5 * sum(huber(s) for s in (0.25, 0.0, 0.01, 1.25, 0.0, 0.04))
    torch.testing.assert_close(problem.cost(), torch.tensor([expected], dtype=F64))
    assert float(problem.cost().detach()) < _HAND_COST  # the kernel down-weights the two large ones
    # The kernel does not change the residuals themselves.
    torch.testing.assert_close(problem.residuals(), _hand_residuals(), atol=1e-12, rtol=0)


def test_huber_loss_with_information_acts_on_r_omega_r():
    generator = torch.Generator().manual_seed(3)
    information = _random_information((2, 36), generator)
    plain = _scene_problem(seed=4, weights=information)
    robust = _scene_problem(seed=4, weights=information, loss=HuberLoss(0.05))
    s = plain.data.squared_norms(plain.raw_residuals())
    assert bool((s > 0.05**2).any()) and bool((s < 0.05**2).any())  # both branches used
    rho = torch.where(s <= 0.05**2, s, 2 * 0.05 * s.sqrt() - 0.05**2)
    torch.testing.assert_close(robust.cost(), 0.5 * rho.sum(-1), atol=1e-13, rtol=1e-13)
    torch.testing.assert_close(plain.cost(), 0.5 * s.sum(-1), atol=1e-13, rtol=1e-13)


# --------------------------------------------------------------------------- padding


def _padded_hand_inputs(pad_pose: int, pad_point: int, pad_value: float) -> dict[str, Tensor]:
    """The hand problem twice (B = 2), padded to E = 9 with the given garbage in the padding."""
    base = _hand_inputs()
    E = 9
    poses = base["poses"].expand(2, 2, 4, 4).clone()
    points = base["points"].expand(2, 3, 3).clone()
    pose_index = torch.full((2, E), pad_pose)
    point_index = torch.full((2, E), pad_point)
    observations = torch.full((2, E, 3), pad_value, dtype=F64)
    valid = torch.zeros(2, E, dtype=torch.bool)
    # Problem 0: the 6 hand observations in slots 0..5, padding in 6..8.
    pose_index[0, :6] = base["pose_index"][0]
    point_index[0, :6] = base["point_index"][0]
    observations[0, :6] = base["observations"][0]
    valid[0, :6] = True
    # Problem 1: the same 6 observations spread over slots 0, 2, 3, 5, 6, 8 (padding between).
    slots = torch.tensor([0, 2, 3, 5, 6, 8])
    pose_index[1, slots] = base["pose_index"][0]
    point_index[1, slots] = base["point_index"][0]
    observations[1, slots] = base["observations"][0]
    valid[1, slots] = True
    return {
        "poses": poses,
        "points": points,
        "pose_index": pose_index,
        "point_index": point_index,
        "observations": observations,
        "valid": valid,
    }


@pytest.mark.parametrize(
    ("pad_pose", "pad_point", "pad_value"),
    [(0, 0, 0.0), (1, 2, 1e6), (-1, -1, float("nan")), (7, 100, float("inf"))],
    ids=["zeros", "in-range-garbage", "minus-one-nan", "out-of-range-inf"],
)
def test_padding_slots_contribute_exactly_zero(pad_pose, pad_point, pad_value):
    """Padding may hold any index and any value: residuals, cost terms, whitened rows,
    gradients and dense-Jacobian rows of padding are exactly 0 (the constructor checks
    indices and finiteness of valid slots only)."""
    inputs = _padded_hand_inputs(pad_pose, pad_point, pad_value)
    inputs["observations"].requires_grad_(True)
    information = torch.eye(3, dtype=F64).expand(2, 9, 3, 3).clone()
    information[..., 0, 0] = 2.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        problem = PointMapProblem(**inputs, weights=information)
    valid = inputs["valid"]
    r = problem.raw_residuals()
    assert torch.equal(r[~valid], torch.zeros_like(r[~valid]))
    w = problem.residuals()
    assert torch.equal(w[~valid], torch.zeros_like(w[~valid]))
    torch.testing.assert_close(r[valid].reshape(2, 6, 3), _hand_residuals().expand(2, 6, 3))
    # Both problems hold the same 6 observations, so the same cost as the unpadded problem.
    unpadded = _hand_problem(weights=information[:1, :6])
    torch.testing.assert_close(problem.cost(), unpadded.cost().expand(2), atol=1e-15, rtol=0)
    problem.cost().sum().backward()
    grad = inputs["observations"].grad
    assert torch.equal(grad[~valid], torch.zeros_like(grad[~valid]))
    assert bool((grad[valid] != 0).any())
    J = problem.dense_jacobian().reshape(2, 9, 3, -1)
    assert torch.equal(J[~valid], torch.zeros_like(J[~valid]))
    assert torch.isfinite(J).all()


# --------------------------------------------------------------------------- gradients


def test_cost_is_differentiable_wrt_everything_gradcheck():
    problem = _scene_problem(seed=5, batch_size=2, num_poses=3, num_points=6, perturb=0.2)
    data = problem.data
    g = torch.Generator().manual_seed(6)
    weights = torch.rand(data.valid.shape, generator=g, dtype=F64) + 0.5
    weights[0, 0] = 0.0  # the gradient w.r.t. a weight is exact at w = 0 (no square root)

    def cost(pose_tangent, points, observations, weights):
        replaced = dataclasses.replace(data, observations=observations, weights=weights)
        return data_module.cost(pose_tangent, points, replaced)

    inputs = (
        problem.pose_tangent.detach().clone().requires_grad_(True),
        problem.points.detach().clone().requires_grad_(True),
        data.observations.detach().clone().requires_grad_(True),
        weights.requires_grad_(True),
    )
    assert torch.autograd.gradcheck(cost, inputs)


def test_cost_and_whitened_residuals_gradcheck_wrt_information():
    problem = _scene_problem(seed=7, batch_size=1, num_poses=3, num_points=4, perturb=0.2)
    data = problem.data
    g = torch.Generator().manual_seed(8)
    A = 0.3 * torch.randn(*data.valid.shape, 3, 3, generator=g, dtype=F64)
    A = (A + torch.eye(3, dtype=F64)).requires_grad_(True)

    def information(A):
        return A @ A.transpose(-1, -2)  # symmetric positive definite for A near I

    def cost(A):
        replaced = dataclasses.replace(data, information=information(A))
        return data_module.cost(problem.pose_tangent.detach(), problem.points.detach(), replaced)

    def whitened(A):
        replaced = dataclasses.replace(data, information=information(A))
        raw = data_module.raw_residuals(
            problem.pose_tangent.detach(), problem.points.detach(), replaced
        )
        return replaced.whiten(raw)

    assert torch.autograd.gradcheck(cost, (A,))
    assert torch.autograd.gradcheck(whitened, (A,))


def test_robust_cost_gradcheck():
    problem = _scene_problem(seed=9, batch_size=1, num_poses=3, num_points=5, perturb=0.2)
    data = dataclasses.replace(problem.data, loss=HuberLoss(1.0))
    s = data.squared_norms(problem.raw_residuals().detach())
    assert bool((s > 1.0).any()) and bool((s < 1.0).any())  # both sides of the knee

    def cost(pose_tangent, points, observations):
        replaced = dataclasses.replace(data, observations=observations)
        return data_module.cost(pose_tangent, points, replaced)

    inputs = (
        problem.pose_tangent.detach().clone().requires_grad_(True),
        problem.points.detach().clone().requires_grad_(True),
        data.observations.detach().clone().requires_grad_(True),
    )
    assert torch.autograd.gradcheck(cost, inputs)


def test_module_cost_backward_reaches_parameters_observations_and_weights():
    inputs = _hand_inputs()
    inputs["observations"].requires_grad_(True)
    weights = torch.full((1, 6), 2.0, dtype=F64, requires_grad=True)
    problem = PointMapProblem(**inputs, weights=weights)
    problem.cost().sum().backward()
    # ∂/∂X_ij of ½ w |r|² is w r; ∂/∂w_e is ½ |r_e|².
    expected_obs = 2.0 * _hand_residuals()
    torch.testing.assert_close(inputs["observations"].grad, expected_obs, atol=1e-12, rtol=0)
    expected_w = 0.5 * (_hand_residuals() ** 2).sum(-1)
    torch.testing.assert_close(weights.grad, expected_w, atol=1e-12, rtol=0)
    # Point gradient: Σ_e ∂r_e/∂X_jᵀ (w r_e) with ∂r/∂X = −R_i.
    R = inputs["poses"][0, :, :3, :3]
    expected_points = torch.zeros(3, 3, dtype=F64)
    for e, (i, j) in enumerate(zip(_HAND_POSE_INDEX, _HAND_POINT_INDEX, strict=True)):
        expected_points[j] -= R[i].T @ (2.0 * _hand_residuals()[0, e])
    torch.testing.assert_close(problem.points.grad[0], expected_points, atol=1e-12, rtol=0)
    assert problem.pose_tangent.grad is not None
    assert torch.isfinite(problem.pose_tangent.grad).all()


# --------------------------------------------------------------------------- constructors


def _scene_with_uneven_batch():
    """B = 3 scene whose problems have different numbers of observations (E_b = 36, 33, 30)."""
    scene = make_scene(4, 12, batch_size=3, visible_fraction=0.75, seed=11)
    obs, vis = scene.to_dense()
    # Problem b loses the first 3·b of its visible entries of frames 1..3 (each point is seen
    # by 3 of the 4 frames, so every point keeps a view; the tests check no warning is raised).
    for b in (1, 2):
        i, j = vis[b, 1:].nonzero(as_tuple=True)
        i, j = i[: 3 * b] + 1, j[: 3 * b]
        vis[b, i, j] = False
        obs[b, i, j] = 0.0
    return scene, obs, vis


def test_from_dense_equals_edge_lists_with_uneven_batch():
    scene, obs, vis = _scene_with_uneven_batch()
    B, m, n = 3, scene.num_poses, scene.num_points
    g = torch.Generator().manual_seed(12)
    dense_w = torch.rand(B, m, n, generator=g, dtype=F64) + 0.5
    dense_info = _random_information((B, m, n), g)
    for weights_kind in ("none", "scalar", "information"):
        dense_weights = {"none": None, "scalar": dense_w, "information": dense_info}[weights_kind]
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            from_dense = PointMapProblem.from_dense(
                scene.poses_gt, scene.points_gt, obs, vis, weights=dense_weights
            )
        data = from_dense.data
        counts = vis.reshape(B, -1).sum(-1)
        assert counts.tolist() == [36, 33, 30]
        assert data.pose_index.shape == (B, 36)
        assert torch.equal(data.valid.sum(-1), counts)
        # Valid slots come first, then padding, and are sorted by (pose, point).
        assert torch.equal(data.valid, torch.arange(36) < counts[:, None])
        key = data.pose_index * n + data.point_index
        for b in range(B):
            k = key[b, : counts[b]]
            assert bool((k[1:] > k[:-1]).all())
        # The same problem as the edge list built by hand from the dense arrays.
        b_idx, i_idx, j_idx = vis.nonzero(as_tuple=True)  # row-major: sorted (b, i, j)
        slot = torch.cat([torch.arange(int(c)) for c in counts])
        pose_index = torch.zeros(B, 36, dtype=torch.long)
        point_index = torch.zeros(B, 36, dtype=torch.long)
        observations = torch.zeros(B, 36, 3, dtype=F64)
        pose_index[b_idx, slot] = i_idx
        point_index[b_idx, slot] = j_idx
        observations[b_idx, slot] = obs[b_idx, i_idx, j_idx]
        valid = torch.arange(36) < counts[:, None]
        edge_weights = None
        if weights_kind == "scalar":
            edge_weights = torch.ones(B, 36, dtype=F64)
            edge_weights[b_idx, slot] = dense_w[b_idx, i_idx, j_idx]
        elif weights_kind == "information":
            edge_weights = torch.eye(3, dtype=F64).expand(B, 36, 3, 3).clone()
            edge_weights[b_idx, slot] = dense_info[b_idx, i_idx, j_idx]
        edges = PointMapProblem(
            scene.poses_gt,
            scene.points_gt,
            pose_index,
            point_index,
            observations,
            valid=valid,
            weights=edge_weights,
        )
        assert torch.equal(data.pose_index[valid], pose_index[valid])
        assert torch.equal(data.point_index[valid], point_index[valid])
        assert torch.equal(data.observations[valid], observations[valid])
        assert torch.equal(from_dense.residuals(), edges.residuals())
        assert torch.equal(from_dense.cost(), edges.cost())


def test_edge_list_order_does_not_change_the_cost():
    scene, obs, vis = _scene_with_uneven_batch()
    from_dense = PointMapProblem.from_dense(scene.poses_gt, scene.points_gt, obs, vis)
    data = from_dense.data
    g = torch.Generator().manual_seed(13)
    perm = torch.stack([torch.randperm(36, generator=g) for _ in range(3)])
    shuffled = PointMapProblem(
        scene.poses_gt,
        scene.points_gt,
        data.pose_index.gather(1, perm),
        data.point_index.gather(1, perm),
        data.observations.gather(1, perm[..., None].expand(3, 36, 3)),
        valid=data.valid.gather(1, perm),
    )
    # The edge list keeps the user's order (no silent re-sorting), so residuals permute along.
    torch.testing.assert_close(
        shuffled.residuals(), from_dense.residuals().gather(1, perm[..., None].expand(3, 36, 3))
    )
    torch.testing.assert_close(shuffled.cost(), from_dense.cost(), atol=1e-14, rtol=1e-14)


def test_from_scene_at_ground_truth_has_the_scene_noise_as_residuals():
    kwargs = {"batch_size": 2, "visible_fraction": 0.5, "seed": 21}
    noisy = make_scene(6, 40, noise_std=0.01, **kwargs)
    clean = make_scene(6, 40, noise_std=0.0, **kwargs)
    # Same seed, same draws: the two scenes differ only by the noise on the observations.
    assert torch.equal(noisy.poses_gt, clean.poses_gt)
    assert torch.equal(noisy.pose_index, clean.pose_index)
    noise = noisy.observations - clean.observations
    problem = PointMapProblem.from_scene(noisy)
    torch.testing.assert_close(problem.raw_residuals(), noise, atol=1e-13, rtol=0)
    r = problem.raw_residuals().detach()[noisy.valid]
    assert 0.008 < float(r.std()) < 0.012  # sanity: it is the 1 cm noise, not zero
    zero = PointMapProblem.from_scene(clean)
    assert float(zero.raw_residuals().detach().abs().max()) < 1e-13
    assert float(zero.cost().detach().max()) < 1e-24
    torch.testing.assert_close(
        problem.cost(), 0.5 * (noise**2).sum((-1, -2)), atol=1e-13, rtol=1e-10
    )


def test_from_scene_with_given_initialization_and_loss():
    scene = make_scene(5, 30, batch_size=1, seed=22)
    poses = scene.poses_gt @ se3.exp(torch.full((1, 5, 6), 0.01, dtype=F64))
    points = scene.points_gt + 0.1
    problem = PointMapProblem.from_scene(scene, poses, points, loss=HuberLoss(0.02))
    torch.testing.assert_close(problem.poses, poses, atol=1e-13, rtol=0)
    torch.testing.assert_close(problem.points.detach(), points)
    assert isinstance(problem.data.loss, HuberLoss)
    assert float(problem.cost().detach()) > float(PointMapProblem.from_scene(scene).cost().detach())


# --------------------------------------------------------------------------- bad input


def _bad(**changes) -> dict[str, Tensor]:
    """Valid inputs of a B = 2, m = 3, n = 4, E = 12 problem, with ``changes`` applied."""
    base = _hand_inputs()
    poses = torch.cat((base["poses"], base["poses"][:, 1:]), dim=1).expand(2, 3, 4, 4).clone()
    points = torch.cat((base["points"], torch.ones(1, 1, 3, dtype=F64)), 1).expand(2, 4, 3)
    pose_index = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]).expand(2, 12).clone()
    point_index = torch.tensor([0, 1, 2, 3] * 3).expand(2, 12).clone()
    observations = torch.rand(2, 12, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    inputs = {
        "poses": poses,
        "points": points.clone(),
        "pose_index": pose_index,
        "point_index": point_index,
        "observations": observations,
    }
    inputs.update(changes)
    return inputs


def test_the_bad_input_base_case_is_valid():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        problem = PointMapProblem(**_bad())
    assert problem.diagnostics == []
    assert torch.isfinite(problem.cost()).all()


@pytest.mark.parametrize("name", ["pose_index", "point_index"])
@pytest.mark.parametrize("value", [-1, 3, 4, 100])
def test_index_out_of_range_names_problem_and_observation(name, value):
    inputs = _bad()
    size = 3 if name == "pose_index" else 4
    if value == 3 and name == "point_index":
        value = 5  # 3 is in range for points
    inputs[name][1, 7] = value
    with pytest.raises(ValueError, match=rf"'{name}' out of range \[0, {size}\)") as info:
        PointMapProblem(**inputs)
    assert f"problem 1, observation 7 has index {value}" in str(info.value)


@pytest.mark.parametrize("bad_value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_observation_names_problem_observation_pose_and_point(bad_value):
    inputs = _bad()
    inputs["observations"][1, 6, 2] = bad_value
    with pytest.raises(ValueError, match="'observations' has a non-finite value") as info:
        PointMapProblem(**inputs)
    assert "problem 1, observation 6 (pose 1, point 2)" in str(info.value)


def test_non_finite_points_and_poses_are_rejected():
    inputs = _bad()
    inputs["points"][0, 2, 1] = float("nan")
    with pytest.raises(ValueError, match=r"'points'.*non-finite.*\(0, 2, 1\)"):
        PointMapProblem(**inputs)
    inputs = _bad()
    inputs["poses"][1, 2, 0, 3] = float("inf")
    with pytest.raises(ValueError, match=r"'poses'.*non-finite"):
        PointMapProblem(**inputs)


def test_non_rigid_pose_is_rejected():
    inputs = _bad()
    inputs["poses"][1, 2, :3, :3] *= 1.1
    with pytest.raises(ValueError, match=r"'poses' must hold rotation matrices.*\(1, 2\)"):
        PointMapProblem(**inputs)


@pytest.mark.parametrize(
    ("name", "shape"),
    [("points", (3, 4, 3)), ("observations", (1, 12, 3)), ("poses", (3, 3, 4, 4))],
)
def test_mismatched_batch_sizes(name, shape):
    inputs = _bad()
    inputs[name] = torch.zeros(shape, dtype=F64)
    if name == "poses":
        inputs[name][..., :, :] = torch.eye(4, dtype=F64)
    with pytest.raises(ValueError, match="batch sizes differ") as info:
        PointMapProblem(**inputs)
    assert f"'{name}' has B = {shape[0]}" in str(info.value)


@pytest.mark.parametrize("name", ["pose_index", "point_index"])
def test_index_batch_or_length_mismatch(name):
    inputs = _bad()
    inputs[name] = inputs[name][:1]
    with pytest.raises(ValueError, match=rf"'{name}' must have shape \(2, 12\), got \(1, 12\)"):
        PointMapProblem(**inputs)
    inputs = _bad()
    inputs[name] = inputs[name][:, :11]
    with pytest.raises(ValueError, match=rf"'{name}' must have shape \(2, 12\), got \(2, 11\)"):
        PointMapProblem(**inputs)


@pytest.mark.parametrize("name", ["points", "observations"])
def test_mixed_float_dtypes_are_rejected(name):
    inputs = _bad()
    inputs[name] = inputs[name].float()
    with pytest.raises(TypeError, match=rf"'{name}' is torch\.float32"):
        PointMapProblem(**inputs)


def test_mixed_dtype_weights_and_wrong_dtypes_are_rejected():
    with pytest.raises(TypeError, match=r"'weights' is torch\.float32"):
        PointMapProblem(**_bad(), weights=torch.ones(2, 12, dtype=torch.float32))
    with pytest.raises(TypeError, match=r"'pose_index' must be an integer tensor"):
        PointMapProblem(**_bad(pose_index=torch.zeros(2, 12)))
    with pytest.raises(TypeError, match=r"'point_index' must be a torch\.Tensor"):
        PointMapProblem(**_bad(point_index=[[0] * 12] * 2))
    with pytest.raises(TypeError, match="'valid' must be a bool tensor"):
        PointMapProblem(**_bad(), valid=torch.ones(2, 12))
    with pytest.raises(TypeError, match="'fixed_poses' must be a bool tensor"):
        PointMapProblem(**_bad(), fixed_poses=torch.zeros(2, 3, dtype=torch.long))
    with pytest.raises(TypeError, match="'observations' must be float32 or float64"):
        PointMapProblem(**_bad(observations=torch.zeros(2, 12, 3, dtype=torch.int64)))


@pytest.mark.parametrize(
    ("name", "value", "pattern"),
    [
        ("observations", torch.zeros(2, 12, 2, dtype=F64), "'observations' must have shape"),
        ("points", torch.zeros(2, 4, 4, dtype=F64), "'points' must have shape"),
        ("poses", torch.zeros(2, 3, 3, 4, dtype=F64), "'poses' must have shape"),
        (
            "poses",
            torch.eye(4, dtype=F64).expand(3, 4, 4),
            r"'poses' must have shape \(B, m, 4, 4\), got \(3, 4, 4\); add a leading batch dim "
            r"with poses\[None\]",
        ),
        (
            "poses",
            torch.eye(4, dtype=F64).expand(1, 2, 3, 4, 4),
            r"poses' must have shape \(B, m, 4, 4\)",
        ),
        (
            "observations",
            torch.zeros(2, 2, 12, 3, dtype=F64),
            r"observations' must have shape \(B, E, 3\)",
        ),
        ("points", torch.zeros(4, 3, dtype=F64), r"\(B, n, 3\), got \(4, 3\); add a leading batch"),
    ],
)
def test_wrong_shapes_name_the_argument(name, value, pattern):
    with pytest.raises(ValueError, match=pattern):
        PointMapProblem(**_bad(**{name: value}))


def test_wrong_mask_and_weight_shapes_name_the_argument():
    with pytest.raises(ValueError, match=r"'valid' must have shape \(2, 12\)"):
        PointMapProblem(**_bad(), valid=torch.ones(2, 11, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"'fixed_poses' must have shape \(2, 3\)"):
        PointMapProblem(**_bad(), fixed_poses=torch.ones(2, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"'fixed_points' must have shape \(2, 4\)"):
        PointMapProblem(**_bad(), fixed_points=torch.ones(2, 3, dtype=torch.bool))
    for shape in ((2, 12, 3), (2, 12, 1), (12,), (2, 12, 3, 2)):
        with pytest.raises(ValueError, match=r"'weights' must have shape \(B, E\) = \(2, 12\)"):
            PointMapProblem(**_bad(), weights=torch.ones(shape, dtype=F64))


def test_negative_weight_names_problem_and_observation():
    weights = torch.ones(2, 12, dtype=F64)
    weights[1, 4] = -0.5
    with pytest.raises(ValueError, match="'weights' must be finite and ≥ 0") as info:
        PointMapProblem(**_bad(), weights=weights)
    assert "problem 1, observation 4 has -0.5" in str(info.value)
    weights[1, 4] = float("nan")
    with pytest.raises(ValueError, match=r"'weights' must be finite and ≥ 0.*has nan"):
        PointMapProblem(**_bad(), weights=weights)


@pytest.mark.parametrize("kind", ["indefinite", "singular", "asymmetric"])
def test_non_spd_information_names_problem_and_observation(kind):
    information = torch.eye(3, dtype=F64).expand(2, 12, 3, 3).clone()
    if kind == "indefinite":
        information[0, 9, 2, 2] = -1.0
    elif kind == "singular":
        information[0, 9, 2, 2] = 0.0
    else:
        information[0, 9, 0, 1] = 0.5
    with pytest.raises(ValueError, match="symmetric positive definite") as info:
        PointMapProblem(**_bad(), weights=information)
    assert "problem 0, observation 9" in str(info.value)


def test_point_observed_by_no_frame_warns_is_fixed_and_listed():
    inputs = _bad()
    valid = torch.ones(2, 12, dtype=torch.bool)
    valid[1, inputs["point_index"][1] == 3] = False  # nobody sees point 3 of problem 1
    with pytest.warns(UserWarning, match="problem 1: point 3 has no observation; held fixed"):
        problem = PointMapProblem(**inputs, valid=valid)
    assert problem.diagnostics == ["problem 1: point 3 has no observation; held fixed"]
    expected = torch.zeros(2, 4, dtype=torch.bool)
    expected[1, 3] = True
    assert torch.equal(problem.data.fixed_points, expected)
    # Still a variable of the module (not dropped), just held fixed by the solver.
    assert problem.points.shape == (2, 4, 3)


def test_frame_with_fewer_than_three_observations_warns_and_is_fixed():
    inputs = _bad()
    valid = torch.ones(2, 12, dtype=torch.bool)
    valid[0, [9, 10]] = False  # pose 2 of problem 0 keeps 2 observations (slots 8 and 11)
    with pytest.warns(UserWarning, match=r"problem 0: pose 2 has 2 observation\(s\) \(< 3\)"):
        problem = PointMapProblem(**inputs, valid=valid)
    assert len(problem.diagnostics) == 1
    assert "held fixed at its initial value" in problem.diagnostics[0]
    expected = torch.zeros(2, 3, dtype=torch.bool)
    expected[:, 0] = True  # the gauge
    expected[0, 2] = True
    assert torch.equal(problem.data.fixed_poses, expected)
    # Nothing silently dropped: its 2 observations still count and still enter the cost.
    assert problem.num_observations.tolist() == [10, 12]
    s = problem.data.squared_norms(problem.raw_residuals())
    assert bool((s[0, [8, 11]] > 0).all())


def test_pose_with_no_observation_and_several_problems_all_listed():
    inputs = _bad()
    valid = torch.ones(2, 12, dtype=torch.bool)
    valid[:, 8:] = False  # pose 2 unobserved in both problems
    with pytest.warns(UserWarning, match="See problem.diagnostics") as record:
        problem = PointMapProblem(**inputs, valid=valid)
    assert len(record) == 1  # one warning, listing everything
    assert problem.diagnostics == [
        "problem 0: pose 2 has 0 observation(s) (< 3); held fixed at its initial value",
        "problem 1: pose 2 has 0 observation(s) (< 3); held fixed at its initial value",
    ]
    assert problem.data.fixed_poses[:, 2].all()


def test_explicitly_fixed_weak_pose_and_unseen_point_do_not_warn():
    inputs = _bad()
    valid = torch.ones(2, 12, dtype=torch.bool)
    valid[:, 8:] = False
    valid[:, inputs["point_index"][0] == 3] = False
    fixed_poses = torch.tensor([[True, False, True]] * 2)
    fixed_points = torch.tensor([[False, False, False, True]] * 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        problem = PointMapProblem(
            **inputs, valid=valid, fixed_poses=fixed_poses, fixed_points=fixed_points
        )
    assert problem.diagnostics == []
    assert torch.equal(problem.data.fixed_poses, fixed_poses)
    assert torch.equal(problem.data.fixed_points, fixed_points)


def test_from_dense_bad_input():
    scene, obs, vis = _scene_with_uneven_batch()
    poses, points = scene.poses_gt, scene.points_gt
    with pytest.raises(ValueError, match=r"'visibility' must have shape \(3, 4, 12\)"):
        PointMapProblem.from_dense(poses, points, obs, vis[:, :, :5])
    with pytest.raises(TypeError, match="'visibility' must be a bool tensor"):
        PointMapProblem.from_dense(poses, points, obs, vis.double())
    with pytest.raises(ValueError, match=r"'observations' must have shape.*got \(4, 12, 3\)"):
        PointMapProblem.from_dense(poses, points, obs[0], vis[0])
    with pytest.raises(ValueError, match=r"'observations' must have shape \(B, m, n, 3\)"):
        PointMapProblem.from_dense(poses, points, obs[None], vis[None])
    with pytest.raises(ValueError, match="'weights'"):
        PointMapProblem.from_dense(poses, points, obs, vis, weights=torch.ones(3, 4, 12, 3))
    with pytest.raises(ValueError, match="'weights'"):
        PointMapProblem.from_dense(poses, points, obs, vis, weights=torch.ones(3, 4, 3))
    with pytest.raises(TypeError, match=r"'weights' is torch\.float32"):
        weights = torch.ones(3, 4, 12, dtype=torch.float32)
        PointMapProblem.from_dense(poses, points, obs, vis, weights=weights)
    with pytest.raises(ValueError, match="'points'"):
        PointMapProblem.from_dense(poses, points[:, :5], obs, vis)
    with pytest.raises(ValueError, match="'poses'"):
        PointMapProblem.from_dense(poses[:, :3], points, obs, vis)
    bad = obs.clone()
    bad[2, 1, 4] = float("nan")
    visible = vis.clone()
    visible[2, 1, 4] = True
    with pytest.raises(ValueError, match=r"non-finite.*problem 2.*\(pose 1, point 4\)"):
        PointMapProblem.from_dense(poses, points, bad, visible)
    # NaN where nothing is visible is ignored (it is not an observation).
    hidden = obs.clone()
    hidden[~vis] = float("nan")
    problem = PointMapProblem.from_dense(poses, points, hidden, vis)
    assert torch.isfinite(problem.cost()).all()


def test_unknown_jacobian_mode_is_rejected():
    with pytest.raises(ValueError, match="'mode' must be 'analytic' or 'jacrev', got 'fd'"):
        _hand_problem().jacobian_blocks("fd")


# --------------------------------------------------------------------------- nn.Module


def test_module_parameters_shapes_and_default_gauge():
    problem = _scene_problem(seed=31, batch_size=2, num_poses=4, num_points=12)
    assert isinstance(problem, nn.Module)
    assert isinstance(problem.pose_tangent, nn.Parameter)
    assert isinstance(problem.points, nn.Parameter)
    assert problem.pose_tangent.shape == (2, 4, 6)
    assert problem.points.shape == (2, 12, 3)
    assert problem.pose_tangent.dtype == F64 and problem.points.dtype == F64
    params = list(problem.parameters())
    assert len(params) == 2
    assert params[0] is problem.pose_tangent and params[1] is problem.points
    assert dict(problem.named_parameters()).keys() == {"pose_tangent", "points"}
    assert set(problem.state_dict()) == {"pose_tangent", "points"}
    expected = torch.zeros(2, 4, dtype=torch.bool)
    expected[:, 0] = True
    assert torch.equal(problem.data.fixed_poses, expected)
    assert not problem.data.fixed_points.any()
    assert (problem.batch_size, problem.num_poses, problem.num_points) == (2, 4, 12)
    assert "num_poses=4" in repr(problem)


def test_module_stores_log_of_the_poses_and_copies_its_inputs():
    inputs = _hand_inputs()
    problem = PointMapProblem(**inputs)
    xi = problem.pose_tangent.detach()
    torch.testing.assert_close(xi[0, 0], torch.zeros(6, dtype=F64), atol=0, rtol=0)
    # Rz(90°): ω = (0, 0, π/2) (rotation first), v = J_l(ω)⁻¹ t.
    torch.testing.assert_close(
        xi[0, 1, :3], torch.tensor([0, 0, math.pi / 2], dtype=F64), atol=1e-15, rtol=0
    )
    torch.testing.assert_close(problem.poses, inputs["poses"], atol=1e-15, rtol=0)
    # The parameters are copies: changing them leaves the caller's tensors alone.
    with torch.no_grad():
        problem.points.add_(1.0)
    assert torch.equal(inputs["points"], torch.tensor([_HAND_POINTS], dtype=F64))


def test_fixed_poses_given_replace_the_default_gauge():
    problem = _hand_problem(fixed_poses=torch.tensor([[False, True]]))
    assert problem.data.fixed_poses.tolist() == [[False, True]]


def test_module_parameters_drive_the_residuals():
    problem = _hand_problem()
    with torch.no_grad():
        problem.points[0, 2] += torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    # Moving X_2 by +e_z moves T_i0 X_2 by R_i e_z = e_z for both poses (Rz keeps e_z).
    expected = _hand_residuals().clone()
    expected[0, [2, 5], 2] -= 1.0
    torch.testing.assert_close(problem.raw_residuals(), expected, atol=1e-12, rtol=0)


def test_gradient_descent_on_the_module_lowers_the_cost():
    problem = _scene_problem(seed=32, perturb=0.02)
    optimizer = torch.optim.SGD(problem.parameters(), lr=1e-3)
    before = problem.cost().detach()
    for _ in range(5):
        optimizer.zero_grad()
        problem.cost().sum().backward()
        optimizer.step()
    assert bool((problem.cost().detach() < before).all())


# --------------------------------------------------------------------------- float32


def test_float32_residuals_and_cost_match_float64():
    """float32 works; tolerance TOL[float32] relative to the problem's coordinate scale."""
    p64 = _scene_problem(seed=41, perturb=0.1)
    p32 = _scene_problem(seed=41, perturb=0.1, dtype=torch.float32)
    assert p32.pose_tangent.dtype == torch.float32
    assert p32.residuals().dtype == torch.float32 and p32.cost().dtype == torch.float32
    scale = float(p64.data.observations.abs().max())
    atol = TOL[torch.float32] * scale
    torch.testing.assert_close(p32.residuals().double(), p64.residuals(), atol=atol, rtol=0)
    torch.testing.assert_close(
        p32.cost().double(), p64.cost(), atol=0, rtol=TOL[torch.float32] * scale
    )


def test_to_casts_the_data_terms_and_losses_with_the_parameters():
    import torchslam as ts

    scene = ts.data.make_scene(5, 30, seed=0)
    T = scene.poses_gt
    term = ts.RelativePoseTerm(
        torch.tensor([[0, 1]]),
        T[0, :1] @ ts.se3.inverse(T[0, 1:2]),
        loss=ts.HuberLoss(torch.tensor(0.1, dtype=torch.float64)),
    )
    problem = ts.PointMapProblem(
        T,
        scene.points_gt,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        valid=scene.valid,
        terms=[term],
        loss=ts.HuberLoss(torch.tensor(0.05, dtype=torch.float64)),
    )
    cost64 = problem.cost().detach()
    assert problem.float() is problem
    data = problem.data
    assert problem.pose_tangent.dtype == torch.float32
    assert data.observations.dtype == torch.float32
    assert data.loss.scale.dtype == torch.float32
    assert data.terms[0].constants["measurements"].dtype == torch.float32
    assert data.terms[0].loss.scale.dtype == torch.float32
    assert data.pose_index.dtype == torch.int64 and data.valid.dtype == torch.bool
    # The user's loss objects are not modified (copies are cast).
    assert term.loss.scale.dtype == torch.float64
    torch.testing.assert_close(problem.cost().detach(), cost64.float(), rtol=1e-5, atol=1e-6)
    problem.double().to("cpu")
    assert problem.data.observations.dtype == torch.float64
    # Back in float64 with the float32-rounded values: equal to float32 precision.
    torch.testing.assert_close(problem.cost().detach(), cost64, rtol=1e-5, atol=1e-6)


def test_numpy_arrays_are_accepted_as_tensors():
    # as register and the readers accept them (issue 28 §4): the same problem, bit for bit
    scene, obs, vis = _scene_with_uneven_batch()
    tensors = PointMapProblem.from_dense(scene.poses_gt, scene.points_gt, obs, vis)
    arrays = PointMapProblem.from_dense(
        scene.poses_gt.numpy(), scene.points_gt.numpy(), obs.numpy(), vis.numpy()
    )
    assert torch.equal(arrays.cost(), tensors.cost())
    data = tensors.data
    edges = PointMapProblem(
        scene.poses_gt.numpy(), scene.points_gt.numpy(), data.pose_index.numpy(),
        data.point_index.numpy(), data.observations.numpy(), valid=data.valid.numpy(),
    )  # fmt: skip
    assert torch.equal(edges.cost(), tensors.cost())


def test_poses_is_a_property_and_the_old_call_warns():
    # problem.poses is a tensor, as SolveResult.poses is (issue 28 §4); the former method call
    # keeps working for one release with a DeprecationWarning.
    poses = se3.exp(
        torch.randn(1, 3, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    )
    poses[:, 0] = torch.eye(4, dtype=torch.float64)
    with pytest.warns(UserWarning, match="held fixed"):  # 1 observation per pose: fine here
        problem = PointMapProblem(
            poses, torch.zeros(1, 2, 3, dtype=torch.float64), torch.tensor([[1, 2]]),
            torch.tensor([[0, 1]]), torch.zeros(1, 2, 3, dtype=torch.float64),
        )  # fmt: skip
    value = problem.poses
    assert isinstance(value, torch.Tensor) and value.shape == (1, 3, 4, 4)
    # Exp(Log(T)) of a random rigid T: round-off of a few ulp
    torch.testing.assert_close(value, poses, rtol=0, atol=1e-13)
    assert type(value[0] @ value[0]) is torch.Tensor  # the shim does not spread
    value.sum().backward()  # differentiable w.r.t. the tangent parameters
    assert problem.pose_tangent.grad is not None
    with pytest.warns(DeprecationWarning, match=r"PointMapProblem\.poses\(\) is deprecated"):
        called = problem.poses()
    assert type(called) is torch.Tensor and torch.equal(called, value)
