"""ICP front end on synthetic surface-like clouds with known rigid transforms."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest
import torch

from tests.helpers import dataset_folder
from torchslam.io.stanford import pose_errors, read_conf, stack
from torchslam.lie import se3, so3
from torchslam.registration import icp
from torchslam.registration.icp import ICPConfig, ICPStatus

F64 = torch.float64


def surface(
    count: int, generator: torch.Generator, scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
) -> tuple[torch.Tensor, torch.Tensor]:
    """Points on a bumpy closed surface without symmetries (about 2 units across).

    ``scale`` stretches it along x, y, z. Returns the points (count, 3) and their unit
    directions from the centre (for cropping "views").
    """
    u = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator, dtype=F64), dim=-1)
    x, y, z = u.unbind(-1)
    radius = 1 + 0.25 * torch.sin(3 * x + 1) * torch.cos(2 * y) + 0.15 * z**2 + 0.1 * x * y
    return radius[:, None] * u * torch.tensor(scale, dtype=F64), u


def rotation_error_deg(T: torch.Tensor, T_true: torch.Tensor) -> float:
    E = T_true[:3, :3].T @ T[:3, :3]
    return math.degrees(float(so3.log(so3.project(E)).norm()))


def translation_error(T: torch.Tensor, T_true: torch.Tensor) -> float:
    return float((T[:3, 3] - T_true[:3, 3]).norm())


@pytest.fixture
def true_transform() -> torch.Tensor:
    xi = torch.tensor([0.25, -0.15, 0.2, 0.3, -0.2, 0.1], dtype=F64)  # ≈ 20°
    return se3.exp(xi)


def views(generator, true_transform, noise=0.0, count=3000):
    """Two partially overlapping noisy views of one sampled surface.

    source: the points with direction x > −0.4 in the source frame; target: those with
    x < 0.5, moved by ``true_transform`` (target ≈ T source). Both get independent noise, so
    the overlap −0.4 < x < 0.5 (about 64% of the source) has noisy true correspondences.
    """
    points, direction = surface(count, generator)
    source = points[direction[:, 0] > -0.4]
    target = se3.act(true_transform, points[direction[:, 0] < 0.5])
    if noise > 0:
        source = source + noise * torch.randn(source.shape, generator=generator, dtype=F64)
        target = target + noise * torch.randn(target.shape, generator=generator, dtype=F64)
    return source, target


# ----------------------------------------------------------------------------- preprocessing


def test_voxel_downsample_matches_a_loop(generator):
    points = torch.rand(2000, 3, generator=generator, dtype=F64) * torch.tensor([1.0, 2.0, 0.5])
    voxel = 0.13
    got = icp.voxel_downsample(points, voxel)
    cells = torch.floor((points - points.amin(0)) / voxel).to(torch.int64)
    groups: dict[tuple[int, ...], list[int]] = {}
    for i, cell in enumerate(cells.tolist()):
        groups.setdefault(tuple(cell), []).append(i)
    expected = torch.stack([points[idx].mean(0) for _, idx in sorted(groups.items())])
    assert got.shape == expected.shape
    assert torch.allclose(got, expected, atol=1e-14)
    assert got.dtype == F64


def test_voxel_downsample_small_cases():
    points = torch.tensor([[0.0, 0, 0], [0.05, 0, 0], [1.0, 1.0, 1.0]], dtype=F64)
    got = icp.voxel_downsample(points, 0.1)
    assert torch.allclose(got, torch.tensor([[0.025, 0, 0], [1.0, 1.0, 1.0]], dtype=F64))
    assert icp.voxel_downsample(points[:0], 0.1).shape == (0, 3)
    with pytest.raises(ValueError, match=r"voxel_downsample: argument 'voxel_size' must be .*> 0"):
        icp.voxel_downsample(points, 0.0)
    with pytest.raises(ValueError, match="voxel_downsample: argument 'points'"):
        icp.voxel_downsample(points[None], 0.1)


def test_nearest_neighbors_match_brute_force(generator):
    reference = torch.randn(300, 3, generator=generator, dtype=F64)
    query = torch.randn(2, 40, 3, generator=generator, dtype=F64)
    distance, index = icp.nearest_neighbors(query, reference)
    brute = torch.cdist(query.reshape(-1, 3), reference)  # small: fine in a test
    assert torch.equal(index.reshape(-1), brute.argmin(-1))
    assert torch.allclose(distance.reshape(-1), brute.min(-1).values, atol=1e-14)
    assert distance.shape == index.shape == (2, 40)
    gated_d, gated_i = icp.nearest_neighbors(query, reference, max_distance=0.2)
    far = distance > 0.2
    assert torch.isinf(gated_d[far]).all() and (gated_i[far] == -1).all()
    assert torch.equal(gated_i[~far], index[~far])


def test_estimate_normals_on_a_tilted_plane(generator):
    uv = torch.rand(500, 2, generator=generator, dtype=F64)
    normal = torch.nn.functional.normalize(torch.tensor([0.2, -0.3, 1.0], dtype=F64), dim=0)
    e1 = torch.nn.functional.normalize(
        torch.linalg.cross(normal, torch.tensor([1.0, 0, 0]).double()), dim=0
    )
    e2 = torch.linalg.cross(normal, e1)
    points = uv[:, :1] * e1 + uv[:, 1:] * e2 + 0.5 * normal
    normals = icp.estimate_normals(points, neighbors=10)
    assert torch.allclose((normals @ normal).abs(), torch.ones(500, dtype=F64), atol=1e-10)
    oriented = icp.estimate_normals(points, 10, viewpoint=torch.zeros(3, dtype=F64))
    # The origin lies on the −normal side of the plane (offset +0.5 along the normal).
    assert torch.allclose(oriented @ normal, -torch.ones(500, dtype=F64), atol=1e-10)


# ----------------------------------------------------------------------------- ICP


def test_exact_copy_is_recovered_to_round_off(generator, true_transform):
    points, _ = surface(1500, generator)
    result = icp.icp(points, se3.act(true_transform, points), config=ICPConfig(max_iterations=100))
    assert result.converged and result.reason.startswith("relative decrease")
    assert rotation_error_deg(result.transform, true_transform) < 1e-8
    assert translation_error(result.transform, true_transform) < 1e-10
    assert float(result.rms) < 1e-10
    assert float(result.fitness) == 1.0
    assert result.history.shape == (int(result.iterations) + 1,)


def test_partial_overlap_with_noise_recovers_transform(generator, true_transform):
    source, target = views(generator, true_transform, noise=0.002)
    config = ICPConfig(max_distance=0.5, min_distance=0.02, trim_fraction=0.9, max_iterations=80)
    result = icp.icp(source, target, config=config)
    assert bool(result.converged)
    assert rotation_error_deg(result.transform, true_transform) < 0.1
    assert translation_error(result.transform, true_transform) < 2e-3
    # Overlap −0.4 < x < 0.5 is roughly 45% of the source's area; trimming keeps 90% of that.
    assert 0.3 < float(result.fitness) < 0.7
    assert float(result.rms) < 0.02


def test_ungated_icp_is_biased_by_partial_overlap(generator, true_transform):
    source, target = views(generator, true_transform, noise=0.002)
    plain = icp.icp(source, target, config=ICPConfig(gate_scale=None, max_iterations=80))
    gated = icp.icp(
        source, target, config=ICPConfig(max_distance=0.5, min_distance=0.02, max_iterations=80)
    )
    assert rotation_error_deg(plain.transform, true_transform) > 1.0
    assert rotation_error_deg(gated.transform, true_transform) < 0.1


def test_trimming_and_gating_reject_outliers(generator, true_transform):
    source, target = views(generator, true_transform, noise=0.001)
    # 30% gross outliers in both clouds, spread over a box around the object.
    box = lambda n: (torch.rand(n, 3, generator=generator, dtype=F64) - 0.5) * 4  # noqa: E731
    source = torch.cat((source, box(int(0.3 * len(source)))))
    target = torch.cat((target, se3.act(true_transform, box(int(0.3 * len(target))))))
    perm = torch.randperm(len(source), generator=generator)
    source = source[perm]
    config = ICPConfig(max_distance=0.5, min_distance=0.02, trim_fraction=0.7, max_iterations=80)
    result = icp.icp(source, target, config=config)
    assert rotation_error_deg(result.transform, true_transform) < 0.15
    assert translation_error(result.transform, true_transform) < 3e-3


def test_point_to_plane_converges_fast(generator, true_transform):
    source, target = views(generator, true_transform, noise=0.001)
    normals = icp.estimate_normals(target, neighbors=12)
    config = ICPConfig(
        method="point_to_plane", max_distance=0.5, min_distance=0.02, trim_fraction=0.9
    )
    result = icp.icp(source, target, config=config, target_normals=normals)
    assert bool(result.converged) and int(result.iterations) < 30
    assert rotation_error_deg(result.transform, true_transform) < 0.1
    assert translation_error(result.transform, true_transform) < 2e-3
    with pytest.raises(ValueError, match="needs 'target_normals'"):
        icp.icp(source, target, config=config)


def test_point_to_plane_far_from_origin_and_on_a_plane(generator, true_transform):
    source, target = views(generator, true_transform, noise=0.0, count=2000)
    offset = torch.tensor([1000.0, -500.0, 200.0], dtype=F64)
    far_source = source + offset
    far_target = target + offset
    # target + o = T (source + o − o) + o  ⇒  T' = Trans(o) T Trans(−o).
    shift = se3.from_rotation_translation(torch.eye(3, dtype=F64), offset)
    T_far = shift @ true_transform @ se3.inverse(shift)
    config = ICPConfig(method="point_to_plane", max_distance=0.5, min_distance=0.02)
    initial = shift @ se3.inverse(shift)  # identity, built in the far frame
    normals = icp.estimate_normals(far_target, neighbors=12)
    result = icp.icp(far_source, far_target, initial, config, normals)
    # Compare where the points land: the translation of T_far amplifies rotation errors by
    # the offset (|o| ≈ 1100), the cloud itself is about 2 units across.
    moved = se3.act(result.transform, far_source) - se3.act(T_far, far_source)
    assert float(moved.norm(dim=-1).max()) < 1e-4  # as accurate as at the origin
    assert rotation_error_deg(result.transform, T_far) < 0.01
    # A plane constrains only 3 of 6 directions; the others must stay put (no blow-up).
    plane = torch.cat((torch.rand(400, 2, generator=generator, dtype=F64), torch.zeros(400, 1)), -1)
    lifted = plane + torch.tensor([0.0, 0.0, 0.05], dtype=F64)
    flat = icp.icp(plane, lifted, None, config, icp.estimate_normals(lifted, 8))
    assert torch.allclose(
        flat.transform[:3, 3], torch.tensor([0.0, 0.0, 0.05], dtype=F64), atol=1e-9
    )
    assert torch.allclose(flat.transform[:3, :3], torch.eye(3, dtype=F64), atol=1e-9)


def test_batch_equals_single_runs(generator, true_transform):
    source, target = views(generator, true_transform, noise=0.001, count=1200)
    initial = se3.exp(0.1 * torch.randn(3, 6, generator=generator, dtype=F64))
    config = ICPConfig(max_distance=0.5, min_distance=0.03, trim_fraction=0.9, max_iterations=15)
    batch = icp.icp_batch(source, target, initial, config)
    assert batch.transform.shape == (3, 4, 4) and batch.rms.shape == (3,)
    assert isinstance(batch.reason, list) and len(batch.reason) == 3
    for b in range(3):
        single = icp.icp(source, target, initial[b], config)
        assert torch.allclose(single.transform, batch.transform[b], atol=1e-12)
        assert int(single.iterations) == int(batch.iterations[b])
        assert int(single.status) == int(batch.status[b])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_point_to_plane_batch_equals_single_runs(generator, true_transform, dtype):
    # The odometry's configuration: a Cauchy kernel and step tolerances, so that runs stop
    # after different numbers of passes (some on the step test, some on the RMS test) and the
    # loop continues on the remaining rows; each row must still be its own run.
    source, target = views(generator, true_transform, noise=0.001, count=1200)
    source, target = source.to(dtype), target.to(dtype)
    normals = icp.estimate_normals(target, 10)
    initial = se3.exp(0.05 * torch.randn(5, 6, generator=generator, dtype=F64)).to(dtype)
    initial[0] = true_transform.to(dtype)  # starts at the answer: stops at once
    config = ICPConfig(
        method="point_to_plane", max_distance=0.5, gate_scale=None, kernel="cauchy",
        kernel_scale=0.1, max_iterations=25, rotation_tolerance_deg=0.01,
        translation_tolerance=1e-4,
    )  # fmt: skip
    batch = icp.icp_batch(source, target, initial, config, normals)
    assert len(set(batch.iterations.tolist())) > 1  # the rows stopped at different passes
    for b in range(5):
        single = icp.icp(source, target, initial[b], config, normals)
        # the same operations on the same numbers: equal to round-off of the batched products
        tol = 50 * torch.finfo(dtype).eps
        assert torch.allclose(single.transform, batch.transform[b], atol=tol, rtol=0)
        assert int(single.iterations) == int(batch.iterations[b])
        assert int(single.status) == int(batch.status[b])
        assert float(single.fitness) == float(batch.fitness[b])


def test_results_are_normal_tensors_and_keep_the_autograd_graph(generator, true_transform):
    # Without a gradient to track the loop runs in inference mode; its result must still be
    # ordinary tensors (editable in place, usable under autograd), equal to the tracked run's.
    source, target = views(generator, true_transform, noise=0.001, count=600)
    config = ICPConfig(max_distance=0.5, max_iterations=10)
    plain = icp.icp(source, target, true_transform, config)
    for name in ("transform", "rms", "fitness", "gate", "iterations", "status", "history"):
        assert not getattr(plain, name).is_inference(), name
    plain.transform.add_(0.0)  # an inference tensor would refuse this outside inference mode
    assert (plain.transform.clone().requires_grad_() * 2).sum().requires_grad
    leaf = source.clone().requires_grad_(True)
    tracked = icp.icp(leaf, target, true_transform, config)
    assert tracked.transform.grad_fn is not None  # as before: the unrolled passes' graph
    assert torch.equal(tracked.transform.detach(), plain.transform)
    assert int(tracked.iterations) == int(plain.iterations)
    with torch.inference_mode():  # a caller's inference mode: the result is its own
        inside = icp.icp(source, target, true_transform, config)
    assert torch.equal(inside.transform, plain.transform)


def test_rotation_only_turns_about_the_source_origin(generator, true_transform):
    # A stage that may only turn the source about its own origin (the sensor): from the true
    # translation and a rotation 3° off it recovers the rotation, and from a wrong translation
    # it keeps that translation (to round-off of the composed increments: ~1e-15 · |t|).
    # The whole surface both ways (exact correspondences, no partial overlap to bias it).
    source, _ = surface(1500, generator)
    target = se3.act(true_transform, source)
    normals = icp.estimate_normals(target, 10)
    config = ICPConfig(
        method="point_to_plane", max_distance=0.5, gate_scale=None, max_iterations=30,
        rotation_only=True,
    )  # fmt: skip
    turned = true_transform.clone()
    turned[:3, :3] = true_transform[:3, :3] @ so3.exp(torch.tensor([0.0, 0.03, 0.04], dtype=F64))
    result = icp.icp(source, target, turned, config, normals)
    assert bool(result.converged)
    # exact copies: the rotation is found to round-off (Gauss-Newton converges quadratically;
    # 1e-9° leaves orders of magnitude for other machines' kernels)
    assert rotation_error_deg(result.transform, true_transform) < 1e-9
    shifted = turned.clone()
    shifted[:3, 3] += torch.tensor([0.05, -0.02, 0.03], dtype=F64)
    moved = icp.icp(source, target, shifted, config, normals).transform
    scale = float(shifted[:3, 3].abs().max())
    assert torch.allclose(moved[:3, 3], shifted[:3, 3], atol=1e-13 * scale, rtol=0)
    assert rotation_error_deg(moved, shifted) > 0.1  # it did turn
    # batched rows are their own runs here too
    batch = icp.icp_batch(source, target, torch.stack((turned, shifted)), config, normals)
    assert torch.allclose(batch.transform[0], result.transform, atol=1e-12, rtol=0)
    assert torch.allclose(batch.transform[1], moved, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="ICPConfig: argument 'rotation_only' needs method"):
        ICPConfig(rotation_only=True)
    with pytest.raises(TypeError, match="ICPConfig: argument 'rotation_only' must be a bool"):
        ICPConfig(method="point_to_plane", rotation_only=1)


def test_large_rotation_needs_multistart(generator):
    points, _ = surface(2500, generator, scale=(1.0, 0.7, 0.5))
    T_true = se3.exp(torch.tensor([2.2, -1.0, 1.3, 0.5, 0.3, -0.4], dtype=F64))  # ≈ 154°
    source = icp.voxel_downsample(points, 0.12)
    target = icp.voxel_downsample(se3.act(T_true, points), 0.12)
    normals = icp.estimate_normals(target, 10)
    config = ICPConfig(
        method="point_to_plane", max_distance=1.0, min_distance=0.12, max_iterations=30
    )
    start = icp.initial_guesses(source, target, se3.identity(1, dtype=F64)[:, :3, :3])
    single = icp.icp(source, target, start[0], config, normals)
    assert rotation_error_deg(single.transform, T_true) > 20
    guesses = icp.initial_guesses(source, target, icp.rotations_uniform(64))
    best, runs = icp.icp_multistart(source, target, guesses, config, 0.06, normals)
    assert runs.transform.shape == (64, 4, 4)
    # The voxel grids of source and target differ, which limits the accuracy.
    assert rotation_error_deg(best.transform, T_true) < 0.5
    assert float(best.fitness) > 0.7


def test_coarse_to_fine_recovers_large_rotation_precisely(generator):
    points, _ = surface(6000, generator, scale=(1.0, 0.7, 0.5))
    T_true = se3.exp(torch.tensor([-0.9, 2.0, 0.7, -0.2, 0.6, 0.3], dtype=F64))
    target = se3.act(T_true, surface(6000, generator, scale=(1.0, 0.7, 0.5))[0])
    stages = (
        icp.Stage(0.15, ICPConfig(max_iterations=8, max_distance=1.0, min_distance=0.15), keep=4),
        icp.Stage(0.05, ICPConfig(max_iterations=20, max_distance=0.3, min_distance=0.05)),
        icp.Stage(
            0.0,
            ICPConfig(method="point_to_plane", max_distance=0.1, min_distance=0.02),
            fitness_distance=0.03,
        ),
    )
    guesses = icp.initial_guesses(points, target, icp.rotations_uniform(64))
    best, per_stage = icp.register_coarse_to_fine(points, target, guesses, stages)
    assert [r.transform.shape[0] for r in per_stage] == [64, 4, 1]
    assert rotation_error_deg(best.transform, T_true) < 0.3
    assert translation_error(best.transform, T_true) < 5e-3


def test_status_and_reasons(generator, true_transform):
    source, target = views(generator, true_transform, count=600)
    capped = icp.icp(source, target, config=ICPConfig(max_iterations=0))
    assert int(capped.status) == ICPStatus.MAX_ITERATIONS and not bool(capped.converged)
    assert capped.reason == "maximum number of iterations reached"
    assert torch.equal(capped.transform, torch.eye(4, dtype=F64))
    far = se3.from_rotation_translation(
        torch.eye(3, dtype=F64), torch.tensor([50.0, 0, 0]).double()
    )
    lost = icp.icp(source, target, far, ICPConfig(max_distance=0.1))
    assert int(lost.status) == ICPStatus.TOO_FEW_CORRESPONDENCES
    assert lost.reason == "too few correspondences within the gate"
    assert int(lost.iterations) == 0 and float(lost.fitness) == 0.0


def test_input_validation():
    cloud = torch.zeros(10, 3, dtype=F64)
    with pytest.raises(ValueError, match="icp: argument 'source' must have shape"):
        icp.icp(torch.zeros(10, 2, dtype=F64), cloud)
    with pytest.raises(TypeError, match=r"icp: 'source' is torch.float64 but 'target'"):
        icp.icp(cloud, cloud.float())
    with pytest.raises(ValueError, match="icp: argument 'initial' must have shape \\(4, 4\\)"):
        icp.icp(cloud, cloud, torch.eye(4, dtype=F64)[None])
    with pytest.raises(ValueError, match="must hold rotation matrices"):
        icp.icp(cloud, cloud, 2 * torch.eye(4, dtype=F64))
    with pytest.raises(ValueError, match="trim_fraction"):
        ICPConfig(trim_fraction=0.0)
    with pytest.raises(ValueError, match="unknown method"):
        ICPConfig(method="point_to_line")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"'keep' must be .*>= 1"):
        icp.Stage(0.1, keep=0)


# ----------------------------------------------------------------------------- rotations, chains


def test_rotations_uniform_cover_so3(generator):
    R = icp.rotations_uniform(128)
    assert R.shape == (128, 3, 3) and R.dtype == F64
    assert torch.allclose(
        R.transpose(-1, -2) @ R, torch.eye(3, dtype=F64).expand(128, 3, 3), atol=1e-12
    )
    assert torch.allclose(torch.linalg.det(R), torch.ones(128, dtype=F64), atol=1e-12)
    probes = so3.exp(torch.randn(500, 3, generator=generator, dtype=F64) * 2)
    angles = so3.log(so3.project(probes[:, None].transpose(-1, -2) @ R[None])).norm(dim=-1)
    nearest = torch.rad2deg(angles.min(-1).values)
    assert float(nearest.max()) < 45  # covering radius of 128 samples (≈ 30° mean spacing)


def test_rotations_about_axis():
    R = icp.rotations_about_axis(8)
    assert torch.allclose(R[0], torch.eye(3, dtype=F64))
    y = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    assert torch.allclose(R @ y, y.expand(8, 3), atol=1e-15)
    assert torch.allclose(so3.log(R[2]), torch.tensor([0.0, math.pi / 2, 0.0], dtype=F64))


def test_chain_poses_compose_successive_steps(generator):
    relative = se3.exp(0.3 * torch.randn(4, 6, generator=generator, dtype=F64))
    poses = icp.chain_poses(relative)
    assert poses.shape == (5, 4, 4)
    assert torch.equal(poses[0], torch.eye(4, dtype=F64))
    expected = relative[0] @ relative[1] @ relative[2] @ relative[3]
    assert torch.allclose(poses[4], expected, atol=1e-12)
    # T̂_0(k+1) = T̂_0k T̂_(k,k+1): scan k+1 → scan k → scan 0.
    for k in range(4):
        assert torch.allclose(poses[k + 1], poses[k] @ relative[k], atol=1e-12)


# ----------------------------------------------------------------------------- real data

_REPO = Path(__file__).resolve().parents[1]
_BUNNY = dataset_folder("bunny")


@pytest.mark.skipif(
    not (_BUNNY / "bun.conf").is_file(),
    reason=f"Stanford bunny data not found ({_BUNNY}); the synthetic tests above cover ICP itself",
)
def test_bunny_pairwise_chain_small(monkeypatch):
    """Three real scans through experiments/bunny_pairwise.py, checked against bun.conf."""
    spec = importlib.util.spec_from_file_location(
        "bunny_pairwise", _REPO / "experiments" / "bunny_pairwise.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # dataclasses look the module up
    spec.loader.exec_module(module)
    names = ["bun000", "bun045", "top3"]
    result = module.run(_BUNNY, names)
    reference = stack(read_conf(_BUNNY / "bun.conf"), names)
    rotation_deg, translation = pose_errors(result.poses, reference, first=0)
    assert torch.equal(result.poses[0], torch.eye(4, dtype=F64))
    assert float(rotation_deg.max()) < 0.5
    assert float(translation.max()) < 1e-3  # metres
    assert all(float(r.fitness) > 0.5 for r in result.pair_results)


@pytest.mark.parametrize("kernel", ["huber", "cauchy", "tukey"])
def test_kernel_weights_equal_the_losses_weight(generator, kernel):
    # ICP's IRLS weights skip the loss's argument checks only: the same ρ' on the same clamped
    # scale, so the values must be equal bit for bit (no tolerance), across both branches of
    # each kernel (residuals far inside and beyond the scale) and scales at the clamp bounds.
    from torchslam.losses import CauchyLoss, HuberLoss, TukeyLoss

    kind = {"huber": HuberLoss, "cauchy": CauchyLoss, "tukey": TukeyLoss}[kernel]
    residual = torch.randn(4, 500, generator=generator, dtype=torch.float64)
    residual = residual * torch.tensor([1e-3, 1.0, 1e3, 1e-150], dtype=torch.float64)[:, None]
    scale = torch.tensor([0.3, 1.0, 1e-320, 1e308], dtype=torch.float64)
    got = icp._kernel_weights(kernel, residual, scale)
    expected = kind(scale).weight(residual * residual)
    assert torch.equal(got, expected)


def _wall_and_floor(generator: torch.Generator, noise: float) -> torch.Tensor:
    """A wall (x = 1) over a floor (z = 0), 1.5 × 1 each, with a 1 mm ripple along y on the
    wall: the translation along y (the line where they meet) is constrained ~10⁴× more weakly
    than the others (a camera facing a bare wall), plus Gaussian noise of ``noise``."""
    u = torch.rand(2, 1500, generator=generator, dtype=F64)
    wall = torch.stack((1 + 0.001 * torch.sin(8 * u[0]), 1.5 * u[0] - 0.75, u[1]), -1)
    v = torch.rand(2, 1500, generator=generator, dtype=F64)
    floor = torch.stack((v[0], 1.5 * v[1] - 0.75, torch.zeros_like(v[0])), -1)
    points = torch.cat((wall, floor))
    return points + noise * torch.randn(points.shape, generator=generator, dtype=F64)


def test_degenerate_condition_keeps_weak_directions_where_they_started(generator):
    # Source and target are two noisy samplings of a wall over a floor; the true transform is
    # the identity and the start is 2 cm off in x, y and z. The wall's normal (x) and the floor's
    # (z) pin x and z, and the rotations, to the noise level; y only by a 1 mm ripple, so that a
    # plain point-to-plane ICP moves y by whatever the noise pushes it to. With
    # degenerate_condition the y translation stays where it started.
    source = _wall_and_floor(generator, 0.002)
    target = _wall_and_floor(generator, 0.002)
    normals = icp.estimate_normals(target, 10)
    start = torch.eye(4, dtype=F64)
    start[:3, 3] = torch.tensor([0.02, 0.02, 0.02], dtype=F64)
    base = dict(method="point_to_plane", max_distance=0.1, gate_scale=None, max_iterations=30)
    kept = icp.icp(source, target, start, ICPConfig(**base, degenerate_condition=0.01), normals)
    # x and z: 3000 pairs at 2 mm noise fix them to ~0.1 mm; 1 mm leaves 10× that
    assert abs(float(kept.transform[0, 3])) < 1e-3 and abs(float(kept.transform[2, 3])) < 1e-3
    # y: no step along the weak direction; y still moves a little with the constrained
    # rotations (steps about the centroid; the weak eigenvector mixes in rotation), by at
    # most ~0.3 mm over seeds here; a plain ICP moves it by up to the full 2 cm
    assert abs(float(kept.transform[1, 3]) - 0.02) < 1e-3
    plain = icp.icp(source, target, start, ICPConfig(**base), normals)
    assert abs(float(plain.transform[0, 3])) < 1e-3 and abs(float(plain.transform[2, 3])) < 1e-3
    # a well-conditioned alignment (a closed bumpy surface: λ_min/λ_max ≫ 0.01) is the same
    # bit for bit with the option: no direction is weak, the plain solve is used as it is
    points, _ = surface(1500, generator)
    T = se3.exp(torch.tensor([0.02, -0.01, 0.03, 0.02, 0.01, -0.02], dtype=F64))
    target = se3.act(T, points)
    normals = icp.estimate_normals(target, 10)
    eye = torch.eye(4, dtype=F64)
    on = icp.icp(points, target, eye, ICPConfig(**base, degenerate_condition=0.01), normals)
    off = icp.icp(points, target, eye, ICPConfig(**base), normals)
    assert torch.equal(on.transform, off.transform)
    with pytest.raises(ValueError, match="ICPConfig: argument 'degenerate_condition' needs method"):
        ICPConfig(degenerate_condition=0.01)
    with pytest.raises(ValueError, match="degenerate_condition"):
        ICPConfig(method="point_to_plane", degenerate_condition=1.5)


def test_weak_directions_kept_zeroes_only_the_weak_eigen_directions():
    # H = S⁻¹ Q diag(λ) Qᵀ S⁻¹ with a known orthonormal Q in the lever-scaled units: the
    # remapped step has no component along the columns of Q with λ < 0.01 λ_max and the
    # Gauss-Newton one along the others (float64 on a 6 × 6 system: 1e-12 relative).
    g = torch.Generator().manual_seed(3)
    Q, _ = torch.linalg.qr(torch.randn(6, 6, generator=g, dtype=F64))
    values = torch.tensor([1e-5, 1e-3, 0.5, 1.0, 2.0, 3.0], dtype=F64)
    arm = torch.randn(1, 50, 3, generator=g, dtype=F64)
    w = torch.ones(1, 50, dtype=F64)
    lever = float(arm.square().sum(-1).mean().sqrt())
    S = torch.diag(torch.tensor([1 / lever] * 3 + [1.0] * 3, dtype=F64))
    Hs = Q @ torch.diag(values) @ Q.T
    H = torch.linalg.inv(S) @ Hs @ torch.linalg.inv(S)
    grad = torch.randn(6, 1, generator=g, dtype=F64)
    delta = -torch.linalg.solve(H, grad).squeeze(-1)
    out = icp._weak_directions_kept(delta[None], H[None], grad[None], arm, w, 0.01)[0]
    scaled = torch.linalg.solve(S, out)  # δ̃ = S⁻¹ δ
    components = Q.T @ scaled
    expected = -(Q.T @ (S @ grad)).squeeze(-1) / values
    zero = torch.zeros(2, dtype=F64)
    assert torch.allclose(components[:2], zero, atol=1e-12 * float(expected.abs().max()))
    assert torch.allclose(components[2:], expected[2:], rtol=1e-10, atol=0)
    # no weak direction: the input step comes back unchanged
    same = icp._weak_directions_kept(delta[None], H[None], grad[None], arm, w, 1e-7)[0]
    assert torch.equal(same, delta)
