"""Boundary checks of register, io readers, data generators, initialization and the CLI.

Every bad argument gets a ValueError/TypeError that names the public function and the argument
(or, for readers, the file and line); none leaks a stray IndexError/AttributeError/RuntimeError,
is silently accepted or gives a wrong answer. Seeded and fast (no registration is run).
"""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
import torch

from torchslam import cli, initialization
from torchslam import registration as reg
from torchslam.data import make_loop_scene, make_scene
from torchslam.io import g2o, ply, stanford, trajectories
from torchslam.lie import se3

D = torch.float64


def _poses(m: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return se3.exp(torch.randn(m, 6, generator=g, dtype=D))


def _cloud(n: int = 30, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 3, generator=g, dtype=D)


def test_write_poses_refuses_names_read_poses_would_lose(tmp_path):
    path = tmp_path / "poses.txt"
    P = _poses(2)
    for names in (["#a", "b"], ["a b", "c"], ["", "c"], ["a\t", "c"], ["a", "a"]):
        with pytest.raises(ValueError, match="write_poses: argument 'names'"):
            trajectories.write_poses(path, names, P)
        assert not path.exists()  # nothing written before the check
    with pytest.raises(TypeError, match="write_poses: argument 'names'"):
        trajectories.write_poses(path, [1, 2], P)
    with pytest.raises(TypeError, match="write_poses: argument 'names'"):
        trajectories.write_poses(path, "ab", P)
    with pytest.raises(ValueError, match="write_poses: argument 'poses' must have shape"):
        trajectories.write_poses(path, ["a", "b", "c"], P)
    with pytest.raises(ValueError, match="write_poses: argument 'poses'"):
        trajectories.write_poses(path, ["a", "b"], torch.ones(2, 4, 4, dtype=D))
    # numpy poses are accepted; the file reads back exactly the names and (to round-off) poses
    names = ["a#", "b-1", "c.2"]
    P3 = _poses(3, seed=1)
    trajectories.write_poses(path, names, P3.numpy())
    back_names, back = trajectories.read_poses(path)
    assert back_names == names
    # repr() writes shortest round-trip decimals; the quaternion → matrix conversion adds a
    # few ulps of the unit-norm entries.
    torch.testing.assert_close(back, P3, atol=1e-12, rtol=0)


def test_read_poses_path_dtype_and_range(tmp_path):
    with pytest.raises(ValueError, match="read_poses: argument 'path' must be a file"):
        trajectories.read_poses(tmp_path)
    with pytest.raises(TypeError, match="read_poses: argument 'path'"):
        trajectories.read_poses(3)
    path = tmp_path / "p.txt"
    path.write_text("a 0 0 0 1 0 0 0\nb 1e300 0 0 1 0 0 0\n")
    with pytest.raises(TypeError, match="read_poses: argument 'dtype'"):
        trajectories.read_poses(path, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"read_poses: .*p\.txt: line 2: .*overflows"):
        trajectories.read_poses(path, dtype=torch.float32)
    names, P = trajectories.read_poses(path)  # float64 holds 1e300
    assert names == ["a", "b"] and float(P[1, 0, 3]) == 1e300


def test_register_config_fields_fuzzed():
    rng = random.Random(7)
    bad_values = {
        "voxel_size": [0.0, -1.0, math.nan, math.inf, True, "0.1"],  # None: derived
        "order": ["auto", None, 1],
        "candidates": [0, 1.5, "3"],
        "hypotheses": [0, 2.5, "8", True, math.nan],
        "stages": [[1, 2], (), "abc", 5],
        "min_overlap": [-0.1, 1.5, math.nan, "x"],
        "track_radius": [0, -2.0, math.inf],
        "normal_neighbors": [2, 3.0, "12"],
        "boundary_threshold": [0.0, -1.0, math.nan, "0.3"],
        "tangent_weight": [0.0, 1.5, math.nan, "0.1"],
        "loss": ["l2", 3, None],
        "loss_scale": [0.0, math.nan],
        "rounds": [-1, 1.5, math.nan, True],
        "rotation_tolerance_deg": [-1.0, math.nan, "1"],
        "translation_tolerance": [-1.0, math.inf],
        "max_iterations": [-1, 2.5, "30"],
    }
    cases = [(field, value) for field, values in bad_values.items() for value in values]
    rng.shuffle(cases)
    for field, value in cases:
        with pytest.raises((ValueError, TypeError)) as info:
            reg.RegisterConfig(**{field: value})
        message = str(info.value)
        assert message.startswith("RegisterConfig:") and f"'{field}'" in message, message
    # valid values pass, and a list of stages is stored as a tuple
    config = reg.RegisterConfig(stages=list(reg.default_stages(0.01)), boundary_threshold=None)
    assert isinstance(config.stages, tuple)
    for bad in (-1.0, math.nan, "0.1"):
        with pytest.raises((ValueError, TypeError), match="default_stages: argument 'voxel_size'"):
            reg.default_stages(bad)


def test_register_arguments_refused_before_any_work():
    a = _cloud()
    cfg = reg.RegisterConfig(hypotheses=2, rounds=0, voxel_size=0.05)
    calls = [
        (TypeError, "'config'", lambda: reg.register(["a", "b"], [a, a], {"voxel_size": 0.1})),
        (TypeError, "'frame'", lambda: reg.register(["a", "b"], [a, a], cfg, frame=True)),
        (TypeError, "'frame'", lambda: reg.register(["a", "b"], [a, a], cfg, frame=1.0)),
        (ValueError, "'frame'", lambda: reg.register(["a", "b"], [a, a], cfg, frame=-1)),
        (ValueError, "'frame'", lambda: reg.register(["a", "b"], [a, a], cfg, frame="c")),
        (ValueError, "'names'", lambda: reg.register(["a", "a"], [a, a], cfg)),
        (ValueError, "'names'", lambda: reg.register(["#a", "b"], [a, a], cfg)),
        (TypeError, "'names'", lambda: reg.register([1, 2], [a, a], cfg)),
        (ValueError, "'names'", lambda: reg.register(["a"], [a, a], cfg)),
        (TypeError, "'clouds", lambda: reg.register(["a", "b"], [a.numpy(), a.numpy() > 0], cfg)),
        (TypeError, "'clouds", lambda: reg.register(["a", "b"], [a, a.float()], cfg)),
        (ValueError, "'clouds[1]'", lambda: reg.register(["a", "b"], [a, a[:, :2]], cfg)),
        (TypeError, "'clouds'", lambda: reg.register_chain(a, cfg)),
    ]
    an = a.clone()
    an[3, 1] = math.nan
    calls.append((ValueError, "'clouds[0]'", lambda: reg.register(["a", "b"], [an, a], cfg)))
    for error, argument, call in calls:
        with pytest.raises(error, match=argument.replace("[", r"\[").replace("]", r"\]")) as info:
            call()
        assert str(info.value).startswith(("register:", "register_chain:")), str(info.value)


def test_helpers_validate_and_accept_numpy():
    a = _cloud(40)
    eye = torch.eye(4, dtype=D).expand(2, 4, 4)
    with pytest.raises(ValueError, match="overlapping_pairs: argument 'poses'"):
        reg.overlapping_pairs([a, a, a], eye, 0.1, 0.5)
    with pytest.raises(ValueError, match="overlapping_pairs: argument 'distance'"):
        reg.overlapping_pairs([a, a], eye, math.nan, 0.5)
    with pytest.raises(TypeError, match="overlapping_pairs: argument 'poses'"):
        reg.overlapping_pairs([a, a], eye.numpy(), 0.1, 0.5)
    # boundary_mask: a numpy cloud gives the tensor's answer; bad clouds are refused
    assert torch.equal(reg.boundary_mask(a.numpy()), reg.boundary_mask(a))
    with pytest.raises(ValueError, match="boundary_mask: argument 'points'"):
        reg.boundary_mask(a[:1])
    an = a.clone()
    an[5, 2] = math.inf
    with pytest.raises(ValueError, match=r"boundary_mask: argument 'points'.*point 5"):
        reg.boundary_mask(an)
    normals = torch.tensor([[0.0, 0.0, 1.0]], dtype=D)
    for bad in (0.0, 1.5, math.nan, "0.1"):
        with pytest.raises((ValueError, TypeError), match=r"information_matrices: .*tangent_w"):
            reg.information_matrices(normals, bad)
    with pytest.raises(TypeError, match=r"load_scans: argument 'paths'.*wrap it in a list"):
        reg.load_scans("scan.ply")
    with pytest.raises(ValueError, match=r"load_scans: argument 'paths'.*at least 2"):
        reg.load_scans(["scan.ply"])
    with pytest.raises(ValueError, match="refine: argument 'pairs'"):
        reg.refine([a, a], eye, pairs=[(0, 1, 2)])
    with pytest.raises(ValueError, match=r"error_table: argument 'frame'"):
        reg.error_table(["a", "b"], 2, eye, {"x": eye})


def test_io_readers_check_path_elements_and_dtype(tmp_path):
    good = tmp_path / "good.ply"
    header = "ply\nformat ascii 1.0\nelement vertex 2\n"
    props = "property float x\nproperty float y\nproperty float z\nend_header\n"
    good.write_text(header + props + "0 0 0\n1.7 -2.5 3.9\n")
    for dtype in (torch.int64, torch.int32, torch.bool, "float64", np.float64):
        with pytest.raises(TypeError, match="read_ply_points: argument 'dtype'"):
            ply.read_ply_points(good, dtype=dtype)
    with pytest.raises(TypeError, match="read_ply: argument 'path'"):
        ply.read_ply(5)
    with pytest.raises(ValueError, match="read_ply: argument 'path' must be a file"):
        ply.read_ply(tmp_path)
    with pytest.raises(FileNotFoundError, match="read_ply"):
        ply.read_ply(tmp_path / "missing.ply")
    assert list(ply.read_ply(good, elements="vertex").data) == ["vertex"]
    with pytest.raises(TypeError, match="read_ply: argument 'elements'"):
        ply.read_ply(good, elements=[1])
    gp = tmp_path / "g.g2o"
    gp.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1e300 0 0 0 0 0 1\n")
    with pytest.raises(TypeError, match="read_g2o: argument 'dtype'"):
        g2o.read_g2o(gp, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"g\.g2o, line 2: value 1e\+300 overflows"):
        g2o.read_g2o(gp, dtype=torch.float32)
    cp = tmp_path / "s.conf"
    cp.write_text("bmesh a.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(TypeError, match="read_conf: argument 'dtype'"):
        stanford.read_conf(cp, dtype=torch.int32)
    with pytest.raises(ValueError, match="stack: argument 'names'"):
        stanford.stack({}, [])
    with pytest.raises(TypeError, match="stack: argument 'names'"):
        stanford.stack({"a": torch.eye(4, dtype=D)}, "a")
    with pytest.raises(ValueError, match="relative_to_first: argument 'first'"):
        stanford.relative_to_first(_poses(2), 5)


def test_data_generators_seed_device_and_size():
    ok = {"num_poses": 4, "num_points": 20}
    calls = [
        (TypeError, "seed", lambda: make_scene(**ok, seed=1.5)),
        (ValueError, "seed", lambda: make_scene(**ok, seed=2**70)),
        (ValueError, "device", lambda: make_scene(**ok, device="gpu0")),
        (TypeError, "device", lambda: make_scene(**ok, device=3.0)),
        (ValueError, "num_points", lambda: make_scene(3, 10**12)),
        (ValueError, "num_poses", lambda: make_scene(-1, 20)),
        (ValueError, "visible_fraction", lambda: make_scene(**ok, visible_fraction=math.nan)),
        (ValueError, "outlier_fraction", lambda: make_scene(**ok, outlier_fraction=1.5)),
        (ValueError, "noise_std", lambda: make_scene(**ok, noise_std=math.nan)),
        (TypeError, "noise_std", lambda: make_scene(**ok, noise_std="0.1")),
        (TypeError, "seed", lambda: make_loop_scene(num_poses=5, seed=0.5)),
        (ValueError, "device", lambda: make_loop_scene(num_poses=5, device="gpu0")),
        (ValueError, "points_per_frame", lambda: make_loop_scene(10**5, 10**4)),
    ]
    for error, argument, call in calls:
        with pytest.raises(error, match=rf"make_(loop_)?scene: .*{argument}"):
            call()
    # the full seed range of torch.Generator is accepted and deterministic
    a = make_scene(**ok, seed=2**64 - 1)
    b = make_scene(**ok, seed=2**64 - 1)
    assert torch.equal(a.observations, b.observations)


def test_initialization_refuses_nonrigid_and_mismatched_poses():
    scene = make_scene(4, 20, seed=3)
    args = (scene.pose_index, scene.point_index, scene.observations, scene.num_points)
    with pytest.raises(ValueError, match="chain_relative_poses: argument 'relative_poses'"):
        initialization.chain_relative_poses(torch.ones(1, 3, 4, 4, dtype=D))
    with pytest.raises(ValueError, match="average_points: argument 'poses'"):
        initialization.average_points(torch.ones(1, 4, 4, 4, dtype=D), *args)
    with pytest.raises(ValueError, match=r"average_points: argument 'poses' has m = 5.*\[4\]"):
        initialization.average_points(_poses(5)[None], *args)
    with pytest.raises(TypeError, match="initialize_scene: argument 'scene'"):
        initialization.initialize_scene("scene")
    with pytest.raises(ValueError, match="initialize_scene: argument 'rotation_noise_deg'"):
        initialization.initialize_scene(scene, method="odometry", rotation_noise_deg=math.nan)
    with pytest.raises(TypeError, match="initialize: argument 'num_points'"):
        initialization.initialize(*args[:3], 4, 20.0)


def test_cli_version_refuses_extra_arguments(capsys):
    assert cli.main(["--version", "extra"]) == cli.EXIT_USAGE
    assert "--version takes no other arguments" in capsys.readouterr().err
    assert cli.main(["--version"]) == cli.EXIT_OK
    assert capsys.readouterr().out.startswith("torchslam ")
