"""Stanford .conf alignments: the p_common = R(q)ᵀ p_scan + t convention, relative poses, errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.helpers import dataset_folder
from torchslam.io.ply import read_ply_points
from torchslam.io.stanford import pose_errors, read_conf, relative_to_first, scan_name, stack
from torchslam.lie import se3

BUNNY = dataset_folder("bunny")

CONF = """camera -0.0172 -0.0936 -0.734  -0.0461723 0.970603 -0.235889 0.0124573
bmesh bun000.ply 0 0 0 0 0 0 1
bmesh bun045.ply -0.0520211 -0.000383981 -0.0109223 0.00548449 -0.294635 -0.0038555 0.955586
bmesh sub/top2.ply 0.1 0.2 0.3 0.908911 -0.0569874 0.154429 0.383126
"""


def _hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (w, x, y, z) quaternions, written out independently of torchslam."""
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def test_read_conf_follows_the_conjugate_rotation_convention(tmp_path):
    path = tmp_path / "bun.conf"
    path.write_text(CONF)
    poses = read_conf(path)
    assert list(poses) == ["bun000", "bun045", "top2"]
    assert torch.equal(poses["bun000"], torch.eye(4, dtype=torch.float64))
    p = np.array([0.03, -0.02, 0.11])
    for name, line in zip(["bun045", "top2"], CONF.splitlines()[2:], strict=True):
        values = [float(v) for v in line.split()[2:]]
        t = np.array(values[:3])
        qx, qy, qz, qw = values[3:]
        q = np.array([qw, qx, qy, qz]) / np.linalg.norm([qw, qx, qy, qz])
        q_conj = q * np.array([1, -1, -1, -1])
        # p_common = R(q)ᵀ p + t = q* ⊗ (0, p) ⊗ q + t.
        expected = _hamilton(_hamilton(q_conj, np.concatenate(([0.0], p))), q)[1:] + t
        got = se3.act(poses[name], torch.from_numpy(p)).numpy()
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
        assert poses[name].dtype == torch.float64


def test_read_conf_rejects_malformed_lines(tmp_path):
    path = tmp_path / "bad.conf"
    path.write_text("bmesh a.ply 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"bad\.conf: line 1: expected 'bmesh <file>"):
        read_conf(path)
    path.write_text("camera 1 2 3 0 0 0 1\nmesh a.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="line 2: expected 'camera' or 'bmesh'"):
        read_conf(path)
    path.write_text("bmesh a.ply 0 0 x 0 0 0 1\n")
    with pytest.raises(ValueError, match="line 1: not a number"):
        read_conf(path)
    path.write_text("bmesh a.ply 0 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match="line 1: zero quaternion"):
        read_conf(path)
    path.write_text("bmesh a.ply 0 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="line 2: scan 'a' listed twice"):
        read_conf(path)


def test_scan_name():
    assert scan_name("data/bunny/bun045.ply") == "bun045"
    assert scan_name(Path("ear_back.ply")) == "ear_back"


def test_relative_to_first_and_stack(generator):
    xi = torch.randn(4, 6, generator=generator, dtype=torch.float64)
    poses = se3.exp(xi)
    relative = relative_to_first(poses, 2)
    assert torch.allclose(relative[2], torch.eye(4, dtype=torch.float64), atol=1e-12)
    # T_2⁻¹ T_i: the pose of scan i seen from scan 2, for every common frame.
    offset = se3.exp(torch.randn(6, generator=generator, dtype=torch.float64))
    again = relative_to_first(se3.compose(offset, poses), 2)
    assert torch.allclose(again, relative, atol=1e-12)
    mapping = dict(zip("abcd", poses, strict=True))
    by_name = relative_to_first(mapping, "c")
    assert list(by_name) == list("abcd")
    assert torch.allclose(stack(by_name, list("abcd")), relative, atol=1e-12)
    with pytest.raises(ValueError, match="no pose for scan"):
        stack(mapping, ["a", "z"])


def test_pose_errors_measure_a_known_perturbation(generator):
    reference = se3.exp(torch.randn(5, 6, generator=generator, dtype=torch.float64))
    angle = torch.tensor([0.0, 0.01, 0.2, 1.0, 3.0], dtype=torch.float64)
    axis = torch.nn.functional.normalize(torch.randn(5, 3, generator=generator), dim=-1).double()
    shift = torch.tensor([0.0, 1e-3, 0.0, 0.5, 2.0], dtype=torch.float64)
    direction = torch.nn.functional.normalize(torch.randn(5, 3, generator=generator), dim=-1)
    perturbation = se3.from_rotation_translation(
        se3.exp(torch.cat((angle[:, None] * axis, torch.zeros(5, 3).double()), -1))[..., :3, :3],
        shift[:, None] * direction.double(),
    )
    # Perturb in the frame of scan 0 (the frame the errors are measured in).
    first = reference[0]
    estimated = se3.compose(
        first, se3.compose(perturbation, se3.compose(se3.inverse(first), reference))
    )
    estimated[0] = reference[0]
    rotation_deg, translation = pose_errors(estimated, reference, first=0)
    expected_deg = torch.rad2deg(angle)
    expected_deg[0] = 0.0
    assert torch.allclose(rotation_deg, expected_deg, atol=1e-9)
    rel_ref = relative_to_first(reference, 0)
    moved = se3.compose(perturbation, rel_ref)[:, :3, 3] - rel_ref[:, :3, 3]
    expected_t = moved.norm(dim=-1)
    expected_t[0] = 0.0
    assert torch.allclose(translation, expected_t, atol=1e-12)
    assert math.isclose(float(pose_errors(reference, reference)[0].abs().max()), 0.0, abs_tol=1e-9)


@pytest.mark.skipif(
    not (BUNNY / "bun.conf").is_file(),
    reason=f"Stanford bunny data not found ({BUNNY})",
)
def test_bunny_conf_overlap_of_bun000_and_bun045():
    """shared/data/README.md: at bun.conf, bun045 covers about half of bun000 within 1 mm."""
    from scipy.spatial import cKDTree

    poses = read_conf(BUNNY / "bun.conf")
    assert len(poses) == 10 and torch.equal(poses["bun000"], torch.eye(4, dtype=torch.float64))
    a = se3.act(poses["bun000"], read_ply_points(BUNNY / "bun000.ply")[::8])
    b = se3.act(poses["bun045"], read_ply_points(BUNNY / "bun045.ply")[::8])
    d, _ = cKDTree(b.numpy()).query(a.numpy(), distance_upper_bound=0.001)
    assert np.isfinite(d).mean() > 0.3
    # The plain R(q) reading (no conjugate) leaves the scans apart.
    R = poses["bun045"][:3, :3].T
    wrong = read_ply_points(BUNNY / "bun045.ply")[::8] @ R.T + poses["bun045"][:3, 3]
    d, _ = cKDTree(wrong.numpy()).query(a.numpy(), distance_upper_bound=0.001)
    assert np.isfinite(d).mean() < 0.05
