"""Issue 17: scans in any order and any unit, arrays in, trajectories out, inverted poses.

The registration tests use three Stanford bunny scans, every 4th point (skipped without the
data); the rest is synthetic.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

import torchslam as ts
from tests.helpers import dataset_folder
from torchslam import registration
from torchslam.io import trajectories
from torchslam.io.stanford import pose_errors, read_conf
from torchslam.lie import se3
from torchslam.registration import icp

BUNNY = dataset_folder("bunny")
NAMES = ["bun000", "bun045", "top3"]
needs_bunny = pytest.mark.skipif(
    not (BUNNY / "bun.conf").is_file(), reason=f"no Stanford bunny data at {BUNNY.resolve()}"
)


def _config() -> registration.RegisterConfig:
    return registration.RegisterConfig(hypotheses=64, rounds=1)  # voxel size: derived


@pytest.fixture(scope="module")
def scans() -> list[torch.Tensor]:
    _, clouds = registration.load_scans([BUNNY / f"{n}.ply" for n in NAMES])
    return [c[::4].contiguous() for c in clouds]  # ~9k points each: a fast test


@pytest.fixture(scope="module")
def metres(scans) -> registration.Registration:
    return registration.register(NAMES, scans, _config(), frame="bun000")


@needs_bunny
def test_unordered_scans_in_metres_match_bun_conf(metres):
    assert metres.ok and metres.config.order == "any"
    assert metres.voxel_size == 0.005  # 4 × the spacing of every 4th point (~0.9 mm), rounded
    reference = torch.stack([read_conf(BUNNY / "bun.conf")[n] for n in NAMES])
    rotation, translation = pose_errors(metres.poses, reference, 0)
    # bun.conf is itself a 1990s registration good to ~0.2°; on a quarter of the points and
    # 5 mm voxels 0.5° and 1 mm still separate success from any wrong pairing (≥ 10°).
    assert float(rotation.max()) < 0.5 and float(translation.max()) < 1e-3


@needs_bunny
def test_millimetres_give_the_same_poses_up_to_scale(scans, metres):
    mm = registration.register(NAMES, [c * 1000 for c in scans], _config(), frame="bun000")
    assert mm.voxel_size == 5.0  # exactly 1000 × (the rounding to 1, 2, 5 × 10^k)
    scaled = mm.poses.clone()
    scaled[:, :3, 3] /= 1000
    # The same arithmetic on numbers 1000× larger: only rounding differs (~1e-16 relative),
    # far below any change of a voxel assignment or of the solver's path.
    assert torch.allclose(scaled, metres.poses, rtol=0, atol=1e-9)


@needs_bunny
def test_any_input_order_and_numpy_arrays_give_the_same_poses(scans, metres):
    order = [2, 0, 1]
    names = [NAMES[k] for k in order]
    arrays = [scans[k].numpy() for k in order]  # numpy float64 in, shuffled
    result = registration.register(names, arrays, _config(), frame="bun000")
    back = [names.index(n) for n in NAMES]
    # Scans are processed in the order of their names: the same computation, bit for bit
    # up to the final change of frame.
    assert torch.allclose(result.poses[back], metres.poses, rtol=0, atol=1e-12)
    assert result.names == names and result.frame == names.index("bun000")


def test_numpy_arrays_float32_and_float64_are_accepted_everywhere():
    rng = np.random.default_rng(0)
    target = rng.normal(size=(300, 3))
    R = so3_exp(np.array([0.05, -0.02, 0.03]))
    source = (target - np.array([0.01, 0.0, 0.02])) @ R
    for dtype in (np.float32, np.float64):
        a, b = target.astype(dtype), source.astype(dtype)
        result = icp.icp(b, a, config=icp.ICPConfig(max_iterations=30))
        assert result.transform.dtype == torch.from_numpy(a).dtype
        assert float(result.rms) < 1e-3
        normals = icp.estimate_normals(a, 8)
        assert normals.shape == (300, 3)
        plane = icp.ICPConfig(method="point_to_plane", kernel="huber", max_iterations=30)
        assert float(icp.icp(b, a, config=plane, target_normals=normals).rms) < 1e-3
        assert icp.voxel_downsample(a, 0.5).shape[1] == 3
        scale = registration.scan_scale([a, b])
        assert len(scale.spacing) == 2 and all(s > 0 for s in scale.spacing)
        chain = registration.register_chain(
            [a, b], registration.RegisterConfig(voxel_size=0.2, hypotheses=4)
        )
        assert torch.isfinite(chain.poses).all()


def test_torchslam_register_is_an_attribute_after_import():
    assert ts.register.__name__ == "torchslam.register"
    assert ts.registration.register_tree is registration.register_tree


def so3_exp(w: np.ndarray) -> np.ndarray:
    return se3.exp(torch.tensor([*w, 0.0, 0.0, 0.0]))[:3, :3].numpy()


# ----------------------------------------------------------------------------- units


def test_implausible_scans_get_clear_messages():
    rng = np.random.default_rng(1)
    scan = rng.normal(size=(200, 3))
    with pytest.raises(ValueError, match=r"register: scan 'b' is 1000× the size .* units"):
        registration.register(["a", "b"], [scan, scan * 1000])
    with pytest.raises(ValueError, match=r"scan 'b': all 200 points coincide"):
        registration.register(["a", "b"], [scan, np.ones((200, 3))])
    far = (scan + 1e6).astype(np.float32)  # spacing ~0.3 at 1e6, where float32 steps by 0.125
    with pytest.raises(ValueError, match=r"too far from the origin for torch\.float32"):
        registration.scan_scale([far, far], fn="register")


def test_auto_voxel_size_rounds_scale_equivariantly():
    scale = registration.ScanScale((0.00053, 0.00055), (0.057, 0.055), (0.1, 0.1))
    assert registration.auto_voxel_size(scale) == 0.002
    big = registration.ScanScale((0.53, 0.55), (57.0, 55.0), (100.0, 100.0))
    assert registration.auto_voxel_size(big) == 2.0


# ----------------------------------------------------------------------------- trajectories


def _poses(m: int = 5, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(m, 6, generator=g, dtype=torch.float64)
    xi[:, :3] *= 2.0  # rotations up to ~π
    return se3.exp(xi)


@pytest.mark.parametrize("format", trajectories.FORMATS)
def test_trajectory_formats_round_trip(tmp_path, format):
    poses = _poses()
    names = [f"scan{k}" for k in range(5)]
    path = tmp_path / f"t_{format}.txt"
    trajectories.write_trajectory(path, poses, format, names=names, frame="scan0")
    text = path.read_text()
    header = [line for line in text.splitlines() if line.startswith("#")]
    assert any("T_0i" in line for line in header)  # the convention is stated
    rows = [line.split() for line in text.splitlines() if not line.startswith("#")]
    assert {len(r) for r in rows} == {dict(torchslam=8, tum=8, kitti=12)[format]}
    back, back_names, times = trajectories.read_trajectory(path, format)
    assert back_names == names
    # repr() writes every float64 exactly; the quaternion ↔ matrix conversions and the
    # KITTI projection onto SO(3) cost a few ulps of numbers ≤ ~5.
    assert torch.allclose(back, poses, rtol=0, atol=1e-12)
    if format == "tum":
        assert times is not None and times.tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]
        # scalar last: the w of the first pose is the 8th number of its line
        w = float(rows[0][7])
        assert math.isclose(abs(w), math.cos(float(se3.log(poses[0])[:3].norm()) / 2), abs_tol=1e-9)


def test_trajectory_writer_refuses_bad_input(tmp_path):
    poses = _poses(3)
    with pytest.raises(ValueError, match="write_trajectory: argument 'format'"):
        trajectories.write_trajectory(tmp_path / "x", poses, "g2o")
    with pytest.raises(ValueError, match="write_trajectory: argument 'timestamps'"):
        trajectories.write_trajectory(tmp_path / "x", poses, "tum", timestamps=[0, 0, 1])
    with pytest.raises(ValueError, match="format 'torchslam' needs 'names'"):
        trajectories.write_trajectory(tmp_path / "x", poses, "torchslam")
    bad = tmp_path / "bad.txt"
    bad.write_text("# header\n0 1 2 3 0 0 0\n")
    with pytest.raises(ValueError, match=r"read_trajectory: .*bad\.txt: line 2: expected 8"):
        trajectories.read_trajectory(bad, "tum")


# ----------------------------------------------------------------------------- inverted poses


def _problem(poses_i0: torch.Tensor) -> ts.PointMapProblem:
    g = torch.Generator().manual_seed(3)
    truth = _poses(4, seed=5)
    truth[0] = torch.eye(4, dtype=torch.float64)
    points = torch.randn(60, 3, generator=g, dtype=torch.float64)
    pose_index = torch.arange(4).repeat_interleave(60)
    point_index = torch.arange(60).repeat(4)
    observed = se3.act(se3.inverse(truth)[pose_index], points[point_index])  # X_ij = T_i0 X_j
    return ts.PointMapProblem(
        poses_i0(truth)[None],
        points[None],
        pose_index[None],
        point_index[None],
        observed[None],
    )


def test_inverted_problem_poses_are_detected_and_warned():
    right = _problem(se3.inverse)  # T_i0, as PointMapProblem expects
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (check,) = registration.check_problem_poses(right)
    assert not check.looks_inverted and check.as_given < 1e-20
    wrong = _problem(lambda T: T)  # T_0i handed in by mistake
    with pytest.warns(registration.InvertedPosesWarning, match="look inverted"):
        (check,) = registration.check_problem_poses(wrong)
    assert check.looks_inverted and check.inverted < 1e-20 < check.as_given


def test_inverted_scan_poses_are_detected():
    g = torch.Generator().manual_seed(0)
    surface = torch.rand(400, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 1.0, 0.05])
    T = _poses(3, seed=2)
    T[:, :3, 3] *= 0.2
    clouds = [se3.act(se3.inverse(T[i]), surface) for i in range(3)]  # scan i's frame
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not registration.check_scan_poses(clouds, T, 0.05).looks_inverted
    with pytest.warns(registration.InvertedPosesWarning):
        assert registration.check_scan_poses(clouds, se3.inverse(T), 0.05).looks_inverted
