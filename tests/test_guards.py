"""Guards added after review: modes that must not poison caches, convention mixes that must be
refused, shapes that must match."""

import math

import pytest
import torch

import torchslam as ts
from torchslam.io import trajectories
from torchslam.lie import se3

F64 = torch.float64


def test_exp_under_inference_mode_then_with_gradients():
    # The series tables are cached: one built under inference_mode must not be reused by a
    # later differentiable call (inference tensors cannot be saved for backward).
    with torch.inference_mode():
        se3.exp(torch.zeros(3, 6, dtype=F64), form="fast")
    xi = torch.full((3, 6), 1e-3, dtype=F64, requires_grad=True)
    se3.exp(xi, form="fast").sum().backward()
    assert xi.grad is not None and torch.isfinite(xi.grad).all()


def test_frame_to_world_terms_are_refused_next_to_point_observations():
    scene = ts.data.make_scene(4, 30, seed=0)
    edges = torch.tensor([[0, 1], [1, 2]])
    term = ts.RelativePoseTerm(
        edges, torch.eye(4, dtype=F64).expand(2, 4, 4), convention="frame_to_world"
    )
    with pytest.raises(ValueError, match="frame_to_world"):
        ts.PointMapProblem(
            scene.poses_gt,
            scene.points_gt,
            scene.pose_index,
            scene.point_index,
            scene.observations,
            valid=scene.valid,
            terms=[term],
        )


def test_relative_pose_term_rejects_an_unknown_convention():
    with pytest.raises(ValueError, match="convention"):
        ts.RelativePoseTerm(
            torch.tensor([[0, 1]]), torch.eye(4, dtype=F64)[None], convention="body"
        )


def test_retract_exp_x_must_match_x():
    x = torch.zeros(5, 6, dtype=F64)
    with pytest.raises(ValueError, match="exp_x"):
        ts.manifold.SE3Tangent().retract(x, x, exp_x=torch.eye(4, dtype=F64)[None])


def test_tum_timestamps_stay_float64(tmp_path):
    poses = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    path = tmp_path / "t.txt"
    times = [1.7e9 + 0.25, 1.7e9 + 0.5]
    trajectories.write_trajectory(path, poses, "tum", timestamps=times)
    _, _, read = trajectories.read_trajectory(path, dtype=torch.float32)
    assert read.dtype == F64 and read.tolist() == times


def test_small_block_products_propagate_nan_and_inf_without_warnings():
    """The NumPy path of the small-block products behaves as torch's @ on non-finite input:
    NaN and Inf propagate, and no floating-point warning escapes (users run with -W error)."""
    import warnings

    from torchslam._batched import matmul

    a = torch.tensor([[[math.nan, 1.0], [1e308, 1e308]]], dtype=F64)
    b = torch.tensor([[[1.0, 0.0], [1e308, 1.0]]], dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        product = matmul(a, b)
    expected = a @ b
    assert torch.equal(product.isnan(), expected.isnan())
    assert torch.equal(product.isinf(), expected.isinf())
