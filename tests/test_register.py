"""Multiview registration (issue 6): pipeline, joint refinement, pose files, CLI, bunny data.

The synthetic fixture is a "critter" (a union of six ellipsoids: body, head, two ears, tail,
paw; about 3 units across) scanned from six viewpoints 45° apart around the y axis: each scan
keeps the points whose normal is within 80° of the viewing direction, gets its own random
sampling and noise, and is expressed in its own frame (random pose).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.helpers import dataset_folder
from torchslam import registration
from torchslam.cli import register as register_command
from torchslam.io.ply import read_ply, write_ply
from torchslam.io.stanford import pose_errors, read_conf, relative_to_first
from torchslam.io.trajectories import read_poses, write_poses
from torchslam.lie import convert, se3, so3
from torchslam.registration import icp

VOXEL = 0.04
BUNNY = dataset_folder("bunny")

# centre, radii of the critter's ellipsoids
PARTS = (
    ((0.0, 0.0, 0.0), (1.0, 0.8, 0.75)),
    ((0.95, 0.65, 0.05), (0.5, 0.45, 0.45)),
    ((1.05, 1.35, 0.25), (0.14, 0.45, 0.1)),
    ((0.85, 1.3, -0.25), (0.12, 0.4, 0.1)),
    ((-1.0, 0.05, 0.2), (0.25, 0.25, 0.25)),
    ((0.4, -0.65, 0.45), (0.35, 0.2, 0.25)),
)


def critter_scans(
    num_scans: int = 6,
    step_deg: float = 45.0,
    points: int = 4000,
    noise: float = 0.002,
    seed: int = 0,
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """(T_0i scan → world (m, 4, 4), scans in their own frames [(N_i, 3)])."""
    rng = np.random.default_rng(seed)
    centres = np.array([c for c, _ in PARTS])
    radii = np.array([r for _, r in PARTS])
    area = radii.prod(1) ** (2 / 3)

    def sample(n: int) -> tuple[np.ndarray, np.ndarray]:
        part = rng.choice(len(PARTS), size=n, p=area / area.sum())
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        p = centres[part] + u * radii[part]
        normal = u / radii[part]
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        inside = (((p[:, None, :] - centres) / radii) ** 2).sum(-1) < 1 - 1e-9
        inside[np.arange(n), part] = False
        keep = ~inside.any(1)
        return p[keep], normal[keep]

    poses, clouds = [], []
    for i in range(num_scans):
        angle = math.radians(step_deg * i)
        view = np.array([math.sin(angle), 0.0, math.cos(angle)])
        p, normal = sample(points * 6)
        p = p[normal @ view > math.cos(math.radians(80.0))][:points]
        omega = torch.tensor([0.0, angle, 0.0], dtype=torch.float64)
        omega = omega + torch.from_numpy(rng.normal(scale=0.05, size=3))
        T = se3.from_rotation_translation(so3.exp(omega), torch.from_numpy(rng.normal(0, 0.3, 3)))
        local = se3.act(se3.inverse(T), torch.from_numpy(p))
        poses.append(T)
        clouds.append(local + noise * torch.from_numpy(rng.normal(size=tuple(local.shape))))
    return torch.stack(poses), clouds


@pytest.fixture(scope="module")
def critter() -> tuple[torch.Tensor, list[torch.Tensor]]:
    return critter_scans()


def config(**changes) -> registration.RegisterConfig:
    # The critter is nearly mirror-symmetric front to back: its views are given as a chain.
    return registration.RegisterConfig(voxel_size=VOXEL, hypotheses=32, order="chain", **changes)


def errors(estimated: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """Max rotation error (degrees) and max translation error, in the frame of scan 0."""
    rotation, translation = pose_errors(estimated, truth, 0)
    return float(rotation.max()), float(translation.max())


# ----------------------------------------------------------------------------- pipeline


def test_pipeline_recovers_known_poses(critter):
    truth, clouds = critter
    names = [f"s{i}" for i in range(len(clouds))]
    lines: list[str] = []
    result = registration.register(names, clouds, config(), progress=lines.append)
    chain_rotation, _ = errors(result.chained, truth)
    rotation, translation = errors(result.poses, truth)
    # The object is ~3 units across and the voxels 0.04: 0.25° and 0.005 are well below both.
    assert rotation < 0.25 and translation < 0.005
    assert chain_rotation < 1.0  # every pair registered (no flipped solution)
    assert rotation < chain_rotation  # the loop closures remove part of the chained error
    assert result.frame == 0 and torch.allclose(result.poses[0], torch.eye(4, dtype=torch.float64))
    assert len(result.refinement.pairs) > len(clouds) - 1  # pairs besides the chain were matched
    assert result.residual_joint < result.residual_chained
    assert sum(not line.startswith(" ") for line in lines) == 3  # one line per stage
    assert all(r.final_cost <= r.initial_cost for r in result.refinement.rounds)


def test_joint_refinement_removes_injected_drift(critter):
    truth, clouds = critter
    exact = relative_to_first(truth, 0)
    # Chain the true relative poses with an extra error per step: 0.57° and 0.02 of drift.
    step = se3.exp(torch.tensor([0.0, 0.0, 0.01, 0.02, 0.0, 0.0], dtype=torch.float64))
    drifted = [exact[0]]
    for i in range(1, len(clouds)):
        relative = se3.compose(se3.inverse(exact[i - 1]), exact[i])
        drifted.append(se3.compose(se3.compose(drifted[-1], relative), step))
    drifted = torch.stack(drifted)
    small = [icp.voxel_downsample(c, VOXEL) for c in clouds]
    result = registration.refine(small, drifted, config())
    drift_rotation, drift_translation = errors(drifted, truth)
    rotation, translation = errors(result.poses, truth)
    assert drift_rotation > 1.0 and drift_translation > 0.04
    assert rotation < 0.1 * drift_rotation and translation < 0.1 * drift_translation
    assert result.tracks is not None and result.tracks.num_points > 1000
    # Marginal covariances of the last round: (m, 6, 6), symmetric, zero for the gauge scan 0,
    # positive definite for the others (a well-posed joint problem).
    cov = result.pose_covariances
    assert cov is not None and cov.shape == (len(clouds), 6, 6)
    assert bool((cov[0] == 0).all())
    assert torch.allclose(cov, cov.transpose(-1, -2), rtol=1e-9, atol=0)
    assert bool((torch.linalg.eigvalsh(cov[1:]) > 0).all())


def test_refine_keeps_exact_poses_nearly_fixed(critter):
    truth, clouds = critter
    small = [icp.voxel_downsample(c, VOXEL) for c in clouds]
    result = registration.refine(small, truth, config(rounds=2))
    rotation, translation = errors(result.poses, truth)
    assert rotation < 0.2 and translation < 0.003  # noise-level bias only
    # On the same tracks the estimate is at least as consistent as the truth (it minimizes).
    cost_truth = registration.joint_cost(result, truth, config())
    cost_estimate = registration.joint_cost(result, result.poses, config())
    assert cost_estimate <= cost_truth * (1 + 1e-6)


def test_refine_takes_given_normals_and_skips_covariances(critter):
    truth, clouds = critter
    small = [icp.voxel_downsample(c, VOXEL) for c in clouds[:4]]
    cfg = config(rounds=1)
    normals = [icp.estimate_normals(c, min(cfg.normal_neighbors, len(c))) for c in small]
    default = registration.refine(small, truth[:4], cfg)
    # the normals refine would estimate, some flipped (the information n nᵀ ignores the
    # sign): the same solve to round-off
    flipped = [n if k % 2 else -n for k, n in enumerate(normals)]
    given = registration.refine(small, truth[:4], cfg, normals=flipped, covariances=False)
    assert given.pose_covariances is None and default.pose_covariances is not None
    torch.testing.assert_close(given.poses, default.poses, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match=r"refine: argument 'normals' must hold one tensor"):
        registration.refine(small, truth[:4], cfg, normals=normals[:2])
    with pytest.raises(ValueError, match=r"refine: argument 'normals\[1\]' must have the shape"):
        registration.refine(
            small, truth[:4], cfg, normals=[normals[0], normals[1][:5], *normals[2:]]
        )
    with pytest.raises(TypeError, match=r"refine: argument 'covariances' must be a bool"):
        registration.refine(small, truth[:4], cfg, covariances="no")
    with pytest.raises(TypeError, match=r"refine: argument 'normals' must be a sequence"):
        registration.refine(small, truth[:4], cfg, normals=normals[0])


def test_refine_takes_given_interior_masks(critter):
    truth, clouds = critter
    small = [icp.voxel_downsample(c, VOXEL) for c in clouds[:4]]
    cfg = config(rounds=1)
    normals = [icp.estimate_normals(c, min(cfg.normal_neighbors, len(c))) for c in small]
    # the masks refine computes itself, given: the same tracks, so the same solve bit for bit
    interior = [
        ~registration.boundary_mask(c, cfg.normal_neighbors, cfg.boundary_threshold, n)
        for c, n in zip(small, normals, strict=True)
    ]
    default = registration.refine(small, truth[:4], cfg, normals=normals, covariances=False)
    given = registration.refine(
        small, truth[:4], cfg, normals=normals, covariances=False, interior=interior
    )
    assert torch.equal(given.poses, default.poses)
    # every point kept: the solve without the boundary test, whatever config says
    everything = [torch.ones(len(c), dtype=torch.bool) for c in small]
    all_points = registration.refine(
        small, truth[:4], cfg, normals=normals, covariances=False, interior=everything
    )
    unmasked = registration.refine(
        small,
        truth[:4],
        config(rounds=1, boundary_threshold=None),
        normals=normals,
        covariances=False,
    )
    assert torch.equal(all_points.poses, unmasked.poses)
    with pytest.raises(TypeError, match=r"refine: argument 'interior' must be a sequence"):
        registration.refine(small, truth[:4], cfg, interior=interior[0])
    with pytest.raises(ValueError, match=r"refine: argument 'interior' must hold one mask"):
        registration.refine(small, truth[:4], cfg, interior=interior[:3])
    with pytest.raises(TypeError, match=r"refine: argument 'interior\[2\]' must be a bool"):
        registration.refine(
            small, truth[:4], cfg, interior=[*interior[:2], interior[2].double(), interior[3]]
        )
    with pytest.raises(ValueError, match=r"refine: argument 'interior\[1\]' must have shape"):
        registration.refine(small, truth[:4], cfg, interior=[interior[0], interior[1][:5]] * 2)


def test_zero_rounds_returns_chained_poses(critter):
    _, clouds = critter
    names = [f"s{i}" for i in range(3)]
    result = registration.register(names, clouds[:3], config(rounds=0), frame="s1")
    assert result.refinement.rounds == []
    assert torch.allclose(result.poses, result.chained)
    assert result.frame == 1
    assert torch.allclose(result.poses[1], torch.eye(4, dtype=torch.float64))


def test_information_matrices_and_boundary_mask():
    normals = torch.nn.functional.normalize(torch.randn(5, 3, dtype=torch.float64), dim=-1)
    omega = registration.information_matrices(normals, 0.01)
    eigenvalues = torch.linalg.eigvalsh(omega)
    assert torch.allclose(eigenvalues, torch.tensor([0.01, 0.01, 1.0]).expand(5, 3).double())
    assert torch.allclose((omega @ normals[..., None])[..., 0], normals)
    # A square grid: the boundary test flags the rim, not the interior.
    g = torch.arange(20, dtype=torch.float64)
    x, y = torch.meshgrid(g, g, indexing="ij")
    grid = torch.stack((x.reshape(-1), y.reshape(-1), torch.zeros(400, dtype=torch.float64)), -1)
    mask = registration.boundary_mask(grid, 12, 0.3).reshape(20, 20)
    assert mask[0].all() and mask[-1].all() and mask[:, 0].all() and mask[:, -1].all()
    assert not mask[3:-3, 3:-3].any()
    # the grid's normal given (either sign): the same test without the PCA
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(400, 3)
    for normals in (up, -up):
        given = registration.boundary_mask(grid, 12, 0.3, normals=normals).reshape(20, 20)
        assert torch.equal(given, mask)
    with pytest.raises(ValueError, match="boundary_mask: argument 'normals' must have the shape"):
        registration.boundary_mask(grid, 12, 0.3, normals=up[:10])


def test_overlapping_pairs():
    cloud = torch.rand(500, 3, dtype=torch.float64)
    far = cloud + torch.tensor([10.0, 0.0, 0.0], dtype=torch.float64)
    poses = torch.eye(4, dtype=torch.float64).expand(3, 4, 4)
    pairs, overlap = registration.overlapping_pairs([cloud, cloud.clone(), far], poses, 1e-6, 0.5)
    assert pairs == [(0, 1)]
    assert overlap.shape == (3, 3) and float(overlap[0, 1]) == 1.0 and float(overlap[0, 2]) == 0.0


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="voxel_size"):
        registration.RegisterConfig(voxel_size=0.0)
    with pytest.raises(ValueError, match="tangent_weight"):
        registration.RegisterConfig(tangent_weight=0.0)
    with pytest.raises(ValueError, match="loss"):
        registration.RegisterConfig(loss="l1")


# ----------------------------------------------------------------------------- files


def test_pose_file_round_trip(tmp_path):
    xi = torch.randn(4, 6, dtype=torch.float64)
    poses = se3.exp(xi)
    path = tmp_path / "poses.txt"
    write_poses(path, ["a", "b", "c", "d"], poses, frame="a")
    names, back = read_poses(path)
    assert names == ["a", "b", "c", "d"]
    assert torch.allclose(back, poses, atol=1e-12)
    first = path.read_text().splitlines()[2].split()
    assert len(first) == 8 and float(first[4]) >= 0  # name tx ty tz qw qx qy qz, qw ≥ 0


def test_read_poses_rejects_malformed_lines(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("a 0 0 0 1 0 0\n")
    with pytest.raises(ValueError, match="line 1: expected"):
        read_poses(path)
    path.write_text("a 0 0 0 one 0 0 0\n")
    with pytest.raises(ValueError, match="line 1: expected a number, got 'one'"):
        read_poses(path)


def test_load_scans_errors(tmp_path):
    good = tmp_path / "good.ply"
    write_ply(good, torch.rand(50, 3, dtype=torch.float64))
    with pytest.raises(FileNotFoundError, match="no such scan file"):
        registration.load_scans([good, tmp_path / "missing.ply"])
    with pytest.raises(ValueError, match="at least 2"):
        registration.load_scans([good])
    with pytest.raises(ValueError, match="distinct"):
        registration.load_scans([good, good])
    broken = tmp_path / "broken.ply"
    broken.write_text("this is not a ply file\n")
    with pytest.raises(ValueError, match=r"broken\.ply"):
        registration.load_scans([good, broken])


# ----------------------------------------------------------------------------- command line


def write_conf(path: Path, names: list[str], poses: torch.Tensor) -> None:
    """A Stanford .conf: p_common = R(q)ᵀ p + t, so q is the conjugate of T's rotation."""
    lines = ["camera 0 0 1 0 0 0 1"]
    for name, T in zip(names, poses, strict=True):
        q = convert.matrix_to_quaternion(T[:3, :3].T)  # (w, x, y, z) of R(q) = Rᵀ
        t = T[:3, 3]
        values = [*t.tolist(), *q[1:].tolist(), float(q[0])]
        lines.append(f"bmesh {name}.ply " + " ".join(repr(v) for v in values))
    path.write_text("\n".join(lines) + "\n")


def test_cli_writes_outputs_and_error_table(critter, tmp_path, capsys):
    truth, clouds = critter
    names = [f"view{i}" for i in range(4)]
    paths = []
    for name, cloud in zip(names, clouds[:4], strict=True):
        paths.append(tmp_path / f"{name}.ply")
        write_ply(paths[-1], cloud, format="ascii")
    conf = tmp_path / "truth.conf"
    write_conf(conf, names, truth[:4])
    assert torch.allclose(torch.stack(list(read_conf(conf).values())), truth[:4], atol=1e-9)
    out = tmp_path / "out"
    argv = [*map(str, paths), "--out", str(out), "--voxel-size", str(VOXEL)]
    argv += ["--hypotheses", "32", "--rounds", "2", "--reference", str(conf), "--frame", "view1"]
    assert register_command.main(argv) == 0
    stdout = capsys.readouterr().out
    for stage in ("[1/5]", "[2/5]", "[3/5]", "[4/5]", "[5/5]"):
        assert stage in stdout
    assert "pairwise rot°" in stdout and "mean" in stdout and "max" in stdout
    assert "1-σ pose uncertainty" in stdout and "rotation" in stdout

    read_names, poses = read_poses(out / "poses.txt")
    assert read_names == names
    expected = relative_to_first(truth[:4], 1)
    rotation, translation = pose_errors(poses, expected, None)
    assert float(rotation.max()) < 0.5 and float(translation.max()) < 0.01
    merged = read_ply(out / "merged.ply")
    vertex = merged.data["vertex"]
    assert {"x", "y", "z", "red", "green", "blue"} <= set(vertex)
    rgb = np.stack([vertex[c] for c in ("red", "green", "blue")], -1)
    assert len(np.unique(rgb, axis=0)) == 4  # one colour per scan
    assert sum("scan view" in c for c in merged.comments) == 4
    assert (out / "registration.png").stat().st_size > 20_000
    assert (out / "poses_pairwise.txt").is_file()


@pytest.mark.parametrize(
    ("extra", "fragment"),
    [
        (["missing.ply"], "no such scan file"),
        (["broken.ply"], "broken.ply"),
        (["--frame", "nope"], "--frame 'nope'"),
        (["--reference", "missing.conf"], "no such reference file"),
        (["--voxel-size", "-1"], "argument --voxel-size"),
        (["--rounds", "-1"], "argument --rounds"),
    ],
)
def test_cli_bad_input_is_one_line_error(extra, fragment, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    write_ply("a.ply", torch.rand(50, 3, dtype=torch.float64))
    write_ply("b.ply", torch.rand(50, 3, dtype=torch.float64))
    header = "ply\nformat ascii 1.0\nelement vertex 2\n"
    header += "property float x\nproperty float y\nproperty float z\nend_header\n"
    Path("broken.ply").write_text(header + "1 2 3\n4 5\n")  # second vertex truncated
    scans = ["a.ply", "b.ply", *(e for e in extra if e.endswith(".ply"))]
    options = [e for e in extra if not e.endswith(".ply")]
    assert register_command.main([*scans, *options, "--out", "out"]) == 2
    err = capsys.readouterr().err
    assert fragment in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_icp_status_is_shown_by_name(generator):
    cloud = torch.rand(60, 3, generator=generator, dtype=torch.float64)
    single = icp.icp(cloud, cloud)  # an exact fit: converged at once
    assert single.status_name == "CONVERGED"
    text = repr(single)
    assert text.startswith("ICPResult(status=CONVERGED, iterations=0,")
    assert "tensor(" not in text.split("transform=")[0]
    initial = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
    batch = icp.icp_batch(cloud, cloud, initial)
    assert batch.status_name == ["CONVERGED", "CONVERGED"]
    assert "status={'CONVERGED': 2}" in repr(batch) and "tensor(" not in repr(batch)


def test_too_few_points_at_a_voxel_size_is_a_clear_error(generator):
    cloud = torch.rand(40, 3, generator=generator, dtype=torch.float64)
    flat = torch.ones(40, 3, dtype=torch.float64)  # one voxel at any pitch
    with pytest.raises(ValueError, match=r"register: scan 'b': all 40 points coincide"):
        registration.register(["a", "b"], [cloud, flat], config())
    tiny = cloud * 0.01  # 40 points within 0.01: one voxel of 0.04
    with pytest.raises(ValueError, match=r"scan 'a' keeps 1 of 40 points on a 0\.04 voxel"):
        registration.register(["a", "b"], [tiny, tiny.flip(0)], config())
    stage = icp.Stage(voxel_size=10.0)
    initial = torch.eye(4, dtype=torch.float64)[None]
    with pytest.raises(ValueError, match=r"level 0 \(voxel size 10\) leaves 1 source"):
        icp.register_coarse_to_fine(cloud, cloud, initial, [stage])


# ----------------------------------------------------------------------------- real data


@pytest.mark.skipif(
    not (BUNNY / "bun.conf").is_file(),
    reason=f"Stanford bunny data not found at {BUNNY.resolve()} (the shared/data checkout "
    "next to the repository); the synthetic tests above cover the pipeline",
)
def test_bunny_three_scans_against_bun_conf():
    names = ["bun000", "bun045", "top3"]
    scan_names, clouds = registration.load_scans([BUNNY / f"{n}.ply" for n in names])
    cfg = registration.RegisterConfig(hypotheses=64, rounds=2)
    result = registration.register(scan_names, clouds, cfg)
    reference = torch.stack([read_conf(BUNNY / "bun.conf")[n] for n in names])
    rotation, translation = pose_errors(result.poses, reference, 0)
    assert float(rotation.max()) < 0.5  # degrees
    assert float(translation.max()) < 1e-3  # metres


def test_load_scans_reads_the_formats_users_have(tmp_path):
    # the same cloud as PLY, NPY, XYZ text and PCD: the same points (NaN rows dropped from the
    # sensor formats; PLY stays strict)
    from pypcd4 import PointCloud

    g = np.random.default_rng(0)
    cloud = g.normal(size=(40, 3)).astype(np.float32).astype(np.float64)  # exact in float32
    with_nan = cloud.copy()
    with_nan[5] = np.nan
    write_ply(tmp_path / "a.ply", cloud)
    np.save(tmp_path / "b.npy", with_nan)
    np.savetxt(tmp_path / "c.xyz", with_nan, fmt="%.17g")  # exact in float64
    PointCloud.from_xyz_points(with_nan.astype(np.float32)).save(tmp_path / "d.pcd")
    paths = [tmp_path / n for n in ("a.ply", "b.npy", "c.xyz", "d.pcd")]
    names, clouds = registration.load_scans(paths)
    assert names == ["a", "b", "c", "d"]
    assert torch.equal(clouds[0], torch.from_numpy(cloud))
    for other in clouds[1:]:
        assert torch.equal(other, torch.from_numpy(np.delete(cloud, 5, axis=0)))
    (tmp_path / "e.e57").write_bytes(b"ASTM-E57")
    with pytest.raises(ValueError, match=r"\.pcd, \.bin, \.ply"):
        registration.load_scans([paths[0], tmp_path / "e.e57"])


def test_load_scans_drops_nan_points_of_a_ply_or_refuses_them(tmp_path):
    import plyfile

    cloud = np.random.default_rng(1).normal(size=(30, 3))
    cloud[[2, 7]] = np.nan
    vertex = np.array([tuple(p) for p in cloud], dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(tmp_path / "a.ply")
    write_ply(tmp_path / "b.ply", np.nan_to_num(cloud))
    _, clouds, dropped = registration.load_scans(
        [tmp_path / "a.ply", tmp_path / "b.ply"], return_dropped=True
    )
    assert dropped == [2, 0] and clouds[0].shape == (28, 3)
    assert torch.equal(clouds[0], torch.from_numpy(np.delete(cloud, [2, 7], axis=0)))
    with pytest.raises(ValueError, match="finite"):
        registration.load_scans([tmp_path / "a.ply", tmp_path / "b.ply"], nonfinite="raise")
    (tmp_path / "empty.ply").write_bytes(b"")
    with pytest.raises(ValueError, match="empty"):
        registration.load_scans([tmp_path / "b.ply", tmp_path / "empty.ply"])


def test_progress_bar_goes_to_stderr_and_changes_nothing(capsys):
    _, clouds = critter_scans(num_scans=3, points=600)
    config = registration.RegisterConfig(voxel_size=0.08, hypotheses=8, rounds=0)
    quiet = registration.register(["a", "b", "c"], clouds, config)
    capsys.readouterr()
    barred = registration.register(["a", "b", "c"], clouds, config, progress_bar=True)
    out, err = capsys.readouterr()
    # the bar's first draw (0 of 3 pairs) is certain; later ones depend on the time per pair
    assert "coarse alignment of all pairs" in err and "0/3" in err and out == ""
    assert torch.equal(barred.poses, quiet.poses)
