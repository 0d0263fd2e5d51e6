"""The sequence pipeline (torchslam.slam) on a synthetic room scanned along a loop.

The scene (torchslam.data.make_sequence) is a 16 m room with pillars; the sensor circles it
(radius 4 m, 1.15 turns, 0.7 m and ~10° between frames), each frame a fresh sample of ~3400
points with 1 cm Gaussian noise, so no two frames share a point. Tolerances below follow from
that noise and the 0.25 m voxel, not from this machine's figures.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest
import torch

from tests.test_cli import assert_one_line_error, call
from torchslam import metrics, registration
from torchslam.data import make_sequence
from torchslam.lie import se3
from torchslam.slam import SLAM, FrameStatus, Odometry, SLAMConfig, run_sequence


@pytest.fixture(scope="module")
def sequence():
    return make_sequence(40, seed=0)


@pytest.fixture(scope="module")
def result(sequence):
    return run_sequence(sequence.clouds, SLAMConfig.for_sensor("lidar"))


def _ate(poses, reference) -> float:
    errors = metrics.evaluate(se3.inverse(poses), se3.inverse(reference), align="se3")
    return float(errors.ate)


def test_odometry_follows_the_known_motion(sequence, result):
    # Each step's registration averages ~3400 points of σ = 1 cm noise over well-spread planes:
    # its error is millimetres, and 40 of them random-walk to well under 5 cm (0.2 voxel).
    # Anything that breaks the alignment (a wrong convention, a lost frame) is metres off.
    assert _ate(result.odometry_poses, sequence.poses) < 0.05
    assert all(f.trusted for f in result.frames)
    assert result.frames[0].status == FrameStatus.FIRST
    assert {f.status for f in result.frames[1:]} <= {FrameStatus.TRACKED, FrameStatus.RETRIED}
    # frame → world, the first frame is the world
    assert torch.equal(result.poses[0], torch.eye(4, dtype=torch.float64))
    relative = se3.compose(se3.inverse(sequence.poses[0]), sequence.poses)
    step_error = (result.odometry_poses[1:, :3, 3] - relative[1:, :3, 3]).norm(dim=-1)
    assert float(step_error.max()) < 0.1


def test_dense_frames_are_registered_on_a_fixed_subset(sequence):
    # Frames with more points than max_source_points are registered on that many (the map
    # keeps all). 1000 of the ~3400 points, σ = 1 cm, still average each step to millimetres:
    # the bounds of the test above hold, and the subset is the same on every run.
    config = SLAMConfig.for_sensor("lidar", max_source_points=1000, loops=False)
    first = run_sequence(sequence.clouds[:12], config)
    assert {f.points for f in first.frames} == {1000}
    odometry = Odometry(config)
    for cloud in sequence.clouds[:3]:
        odometry.add(cloud)
    assert odometry.keyframes[1].points.shape[0] > 1000  # the map keeps every point
    assert _ate(first.odometry_poses, sequence.poses[:12]) < 0.05
    again = run_sequence(sequence.clouds[:12], config)
    assert torch.equal(again.odometry_poses, first.odometry_poses)
    assert SLAMConfig.for_sensor("lidar").max_source_points == 4000
    assert SLAMConfig.for_sensor("depth").max_source_points == 8000


def test_joint_refinement_of_the_keyframes(sequence, result):
    # The same frames with one round of the seed's joint refinement after the pose graph: it
    # runs on the keyframes with their own normals and keeps the trajectory within the same
    # noise bound (its points are the tracks of 1 cm noise samples; the pose graph's ATE here
    # is millimetres, see above). Whatever the round does, the poses stay finite and rigid.
    config = SLAMConfig.for_sensor("lidar", refine_rounds=1, refine_iterations=3)
    refined = run_sequence(sequence.clouds, config)
    assert refined.backend is not None and refined.backend.refine_rounds == 1
    assert refined.seconds["refine"] > 0
    assert _ate(refined.poses, sequence.poses) < 0.05
    assert torch.isfinite(refined.poses).all()
    R = refined.keyframe_poses[:, :3, :3]
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, rtol=0, atol=1e-12)


def test_keyframes_carry_the_refinements_boundary_test(sequence):
    # With the refinement on, each keyframe keeps the boundary test of refine's tracks, made
    # from its normals' neighbourhoods: the same mask as boundary_mask on its points with its
    # normals (the same k nearest, whose distances are distinct in noisy samples, so the same
    # neighbourhoods in the same order); off, none is computed.
    config = SLAMConfig.for_sensor("lidar", refine_rounds=1, loops=False)
    odometry = Odometry(config)
    for cloud in sequence.clouds[:6]:
        odometry.add(cloud)
    threshold = registration.RegisterConfig.boundary_threshold
    for keyframe in odometry.keyframes:
        k = min(config.normal_neighbors, keyframe.points.shape[0])
        expected = ~registration.boundary_mask(keyframe.points, k, threshold, keyframe.normals)
        assert keyframe.interior is not None and torch.equal(keyframe.interior, expected)
    plain = Odometry(SLAMConfig.for_sensor("lidar", refine_rounds=0, loops=False))
    plain.add(sequence.clouds[0])
    assert plain.keyframes[0].interior is None


def test_loop_closures_found_and_correct(sequence, result):
    # 1.15 turns: the last ~6 frames revisit the first ones.
    accepted = result.accepted_loops
    assert accepted, [c.reason for c in result.loops]
    truth = sequence.poses[result.keyframe_frames]
    for c in accepted:
        assert c.second - c.first >= result.config.loop_min_gap
        true_z = se3.compose(se3.inverse(truth[c.first]), truth[c.second])
        error = se3.compose(se3.inverse(true_z), c.measurement)
        # a verified closure is as good as an odometry step: centimetres (noise / √points)
        assert float(error[:3, 3].norm()) < 0.05
    # with the loops the trajectory is no worse than odometry (no drift to remove here; the
    # real sequences of experiments/slam_sequences.py show the gain), within noise
    assert _ate(result.poses, sequence.poses) < 0.05
    assert result.keyframe_covariances is not None
    assert result.keyframe_covariances.shape == (len(result.keyframe_frames), 6, 6)
    assert bool((torch.linalg.eigvalsh(result.keyframe_covariances[1:]) > 0).all())


def test_streaming_equals_one_call(sequence, result):
    slam = SLAM(SLAMConfig.for_sensor("lidar"))
    for k, cloud in enumerate(sequence.clouds):
        pose = slam.add(cloud.numpy(), timestamp=0.1 * k)  # numpy arrays too
        assert pose.shape == (4, 4)
    streamed = slam.finish()
    # the same code path on the same numbers: bit-identical
    assert torch.equal(streamed.poses, result.poses)
    assert torch.equal(streamed.odometry_poses, result.odometry_poses)
    assert streamed.keyframe_frames == result.keyframe_frames
    assert torch.allclose(streamed.timestamps, 0.1 * torch.arange(40, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="finish"):
        slam.add(sequence.clouds[0])


def test_planted_wrong_candidate_is_rejected(sequence, result):
    from torchslam.slam.loops import verify_loop

    slam = SLAM(SLAMConfig.for_sensor("lidar", loops=False))
    for cloud in sequence.clouds[:22]:
        slam.add(cloud)
    keyframes = list(slam.keyframes)
    # Drifted odometry that puts keyframe 15 (6.7 m away along the circle, turned 114°) 0.3 m
    # from keyframe 4: a candidate from distant places. Its verification must fail, whatever
    # ICP does from that guess. (A place the room's half-turn symmetry maps onto another,
    # keyframes 2 and 19, passes any geometric test, as it would in a real symmetric room:
    # the back end's χ² test is what catches such a closure, test_forced_wrong_closure_...)
    guess = keyframes[4].pose.clone()
    guess[:3, 3] += torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64)
    keyframes[15] = dataclasses.replace(keyframes[15], pose=guess)
    closure = verify_loop(keyframes, 4, 15, slam.config)
    assert not closure.accepted and closure.quality.problem is not None
    # the same pair from the true odometry (the room is seen from both places) is accepted
    assert slam.add_loop(4, 15).accepted


def test_forced_wrong_closure_does_not_bend_the_map(sequence, result):
    slam = SLAM(SLAMConfig.for_sensor("lidar"))
    for cloud in sequence.clouds:
        slam.add(cloud)
    # "keyframe 19 is where keyframe 2 is", as confident as an odometry step
    forced = slam.add_loop(2, 19, measurement=torch.eye(4, dtype=torch.float64))
    assert forced.forced and forced.accepted
    bent = slam.finish()
    assert not forced.kept and forced.reason == "forced, dropped by χ² against the odometry"
    # the χ² test drops it: the trajectory is the one without it, to the solver's tolerance
    reference = _ate(result.poses, sequence.poses)
    assert abs(_ate(bent.poses, sequence.poses) - reference) <= 0.03 * reference + 1e-4


def test_lone_wrong_closure_is_dropped_against_the_odometry(sequence):
    # No detected loop to contradict it (loops off): only the test against the odometry chain
    # can catch a lone wrong closure; the graph alone would bend the chain to fit it, leaving
    # the loop edge's own χ² small.
    config = SLAMConfig.for_sensor("lidar", loops=False)
    plain = run_sequence(sequence.clouds, config)
    slam = SLAM(config)
    for cloud in sequence.clouds:
        slam.add(cloud)
    forced = slam.add_loop(2, 19, measurement=torch.eye(4, dtype=torch.float64))
    bent = slam.finish()
    assert forced.contradicts_odometry and not forced.kept
    assert forced.reason == "forced, dropped by χ² against the odometry"
    assert forced.odometry_chi2 > config.loop_max_chi2 and forced.chi2 == forced.odometry_chi2
    assert bent.accepted_loops == [] and bent.backend.graph_status is None
    # dropped before the graph: the back end is the one without it, bit for bit
    assert torch.equal(bent.poses, plain.poses)


def test_true_closure_passes_the_odometry_test(sequence):
    # The same pair with its true relative pose: its innovation is the odometry's own drift
    # over 17 keyframes (millimetres, see test_odometry_follows_the_known_motion), whose χ²
    # under the scaled information is a few units at most, far below the bound.
    config = SLAMConfig.for_sensor("lidar", loops=False)
    slam = SLAM(config)
    for cloud in sequence.clouds:
        slam.add(cloud)
    truth = sequence.poses[[kf.frame for kf in slam.keyframes]]
    closure = slam.add_loop(2, 19, measurement=se3.compose(se3.inverse(truth[2]), truth[19]))
    result = slam.finish()
    assert closure.kept and not closure.contradicts_odometry and closure.reason == "forced"
    assert closure.odometry_chi2 < 0.1 * config.loop_max_chi2
    assert result.accepted_loops == [closure]


def test_odometry_chi2_is_the_cost_of_the_chain_and_the_loop():
    # The closed form νᵀ(Σ_chain + Σ_loop)⁻¹ν against the graph of the chain and that loop
    # solved by the library's solver (2× its least-squares cost): equal to first order in the
    # innovation ν, so their gap shrinks with |ν|. A chain of 8 random steps of ~17° and ~20 m
    # (the adjoints' lever arms), random SPD information.
    from torchslam import _checks
    from torchslam.registration.quality import AlignmentQuality
    from torchslam.slam import backend
    from torchslam.slam.loops import LoopClosure
    from torchslam.slam.odometry import Keyframe

    g = torch.Generator().manual_seed(3)
    f64 = torch.float64

    def spd():
        A = torch.randn(6, 6, generator=g, dtype=f64)
        return 1e3 * (A @ A.T + 0.5 * torch.eye(6, dtype=f64))

    K = 9
    xi = torch.cat([0.3 * torch.randn(K - 1, 3, generator=g, dtype=f64),
                    20 * torch.randn(K - 1, 3, generator=g, dtype=f64)], -1)  # fmt: skip
    poses = [torch.eye(4, dtype=f64)]
    for step in se3.exp(xi):
        poses.append(poses[-1] @ step)
    poses = torch.stack(poses)
    empty = torch.zeros(0, 3, dtype=f64)
    keyframes = [Keyframe(k, poses[k], empty, empty, spd()) for k in range(K)]
    config = SLAMConfig.for_sensor("lidar")
    direction = torch.randn(6, generator=g, dtype=f64)
    direction /= direction.norm()
    information = spd()
    gaps = []
    for size in (1e-2, 1e-3):
        Z = se3.compose(se3.compose(se3.inverse(poses[1]), poses[7]), se3.exp(size * direction))
        quality = AlignmentQuality(math.nan, math.nan, math.nan, 0, information, None)
        closure = LoopClosure(1, 7, Z, information, quality, True)
        with _checks.validation(False):
            closed = float(backend._odometry_chi2(poses, keyframes, [closure])[0])
            graph = backend._solve_graph(poses, keyframes, [closure], config, robust=False)[1]
        exact = 2 * float(graph.final_cost[0])
        gaps.append(abs(closed - exact) / exact)
    assert gaps[1] < 1e-4 and gaps[1] < 0.2 * gaps[0]


def test_untrusted_frame_is_marked_and_not_a_keyframe(sequence):
    odometry = Odometry(SLAMConfig.for_sensor("lidar"))
    for cloud in sequence.clouds[:5]:
        odometry.add(cloud)
    keyframes = len(odometry.keyframes)
    g = torch.Generator().manual_seed(0)
    clutter = torch.rand(3000, 3, generator=g, dtype=torch.float64) * 40 - 20  # no structure
    odometry.add(clutter)
    info = odometry.frames[-1]
    assert info.status == FrameStatus.UNRELIABLE and not info.trusted
    assert not info.is_keyframe and len(odometry.keyframes) == keyframes
    odometry.add(sequence.clouds[5])  # and tracking goes on from the prediction
    assert odometry.frames[-1].trusted


@pytest.mark.parametrize(
    ("points", "error", "fragment"),
    [
        (torch.zeros(0, 3), ValueError, "empty frame"),
        (torch.zeros(10, 2), ValueError, "shape (N, 3)"),
        (torch.full((5, 3), float("nan")), ValueError, "no finite point"),
        ([[0.0, 0.0, 1.0]], TypeError, "tensor or numpy array"),
        (torch.zeros(10, 3, dtype=torch.int64), TypeError, "floating point"),
    ],
)
def test_bad_frames_are_refused(points, error, fragment):
    with pytest.raises(error, match=r"Odometry\.add") as raised:
        Odometry(SLAMConfig.for_sensor("lidar")).add(points)
    assert fragment in str(raised.value)


def test_bad_config_and_arguments():
    with pytest.raises(ValueError, match="SLAMConfig: argument 'voxel'"):
        SLAMConfig(voxel=-1.0)
    with pytest.raises(ValueError, match="'sensor' must be 'depth' or 'lidar'"):
        SLAMConfig.for_sensor("radar")
    with pytest.raises(TypeError, match="unknown option"):
        SLAMConfig.for_sensor("lidar", vox=0.1)
    with pytest.raises(ValueError, match="run_sequence: argument 'frames' is empty"):
        run_sequence([])
    with pytest.raises(ValueError, match=r"SLAM\.finish: no frame"):
        SLAM().finish()
    with pytest.raises(ValueError, match="every"):
        run_sequence([torch.zeros(5, 3)], every=0)
    for name in ("icp_step_voxels", "icp_step_deg"):
        for value in (0.0, -0.01, math.inf):
            with pytest.raises(ValueError, match=f"SLAMConfig: argument '{name}'"):
                SLAMConfig(**{name: value})
    with pytest.raises(ValueError, match="SLAMConfig: argument 'refine_iterations'"):
        SLAMConfig(refine_iterations=0)
    # depth: a map on half the frame's voxel, LiDAR keyframes on the frame's voxel
    assert SLAMConfig.for_sensor("depth").map_voxel_fraction == 0.5
    assert SLAMConfig.for_sensor("lidar").map_voxel_fraction == 1.0


def _depth_folder(tmp_path, K_text: str | None = "585 0 320\n0 585 240\n0 0 1\n"):
    import imageio.v3 as iio

    folder = tmp_path / "depth"
    folder.mkdir()
    for k in range(2):
        iio.imwrite(folder / f"frame-{k:06d}.depth.png", np.full((96, 128), 1500, np.uint16))
    if K_text is not None:
        (folder / "camera-intrinsics.txt").write_text(K_text)
    return folder


def test_bad_sequence_inputs(tmp_path):
    folder = _depth_folder(tmp_path, K_text=None)
    with pytest.raises(ValueError, match="intrinsics"):
        run_sequence(folder)
    with pytest.raises(ValueError, match=r"'intrinsics' must be a 3×3 K .* got shape \(2, 2\)"):
        run_sequence(folder, intrinsics=np.eye(2))
    broken = tmp_path / "lidar"
    broken.mkdir()
    (broken / "000000.pcd").write_bytes(b"not a pcd file\n")
    with pytest.raises(ValueError, match=r"000000\.pcd"):
        run_sequence(broken)
    with pytest.raises(FileNotFoundError):
        run_sequence(tmp_path / "missing")


def test_cli_writes_trajectories_and_evaluates(sequence, tmp_path, capsys):
    from torchslam.io.trajectories import read_trajectory, write_trajectory

    frames = tmp_path / "scans"
    frames.mkdir()
    for k, cloud in enumerate(sequence.clouds[:12]):
        np.save(frames / f"{k}.npy", cloud.numpy())
    (frames / "notes.txt").write_text("ignored\n")
    write_trajectory(tmp_path / "ref_kitti.txt", sequence.poses[:12], "kitti")
    out = tmp_path / "out"
    argv = ["slam", str(frames), "--reference", str(tmp_path / "ref_kitti.txt")]
    code, stdout, err = call([*argv, "--out", str(out), "--every", "2"], capsys)
    assert code == 0, err
    assert "6 lidar frames" not in stdout and "12 lidar frames, using 6" in stdout
    assert "after back end: ATE" in stdout
    poses, _, times = read_trajectory(out / "trajectory_tum.txt", "tum")
    assert poses.shape == (6, 4, 4) and times.tolist() == [0.0, 2.0, 4.0, 6.0, 8.0, 10.0]
    kitti, _, _ = read_trajectory(out / "trajectory_kitti.txt", "kitti")
    assert torch.allclose(kitti, poses, atol=1e-6)  # the same poses in both files
    assert (out / "map.ply").is_file()
    code, _, err = call(["slam", str(tmp_path / "nowhere")], capsys)
    assert_one_line_error(code, err, "torchslam slam", "no such folder")


def test_cli_matches_a_reference_at_another_rate_by_timestamp(sequence, tmp_path, capsys):
    # As TUM RGB-D: the frames' times in the folder, a reference at 3× the frame rate in a
    # TUM file, every frame's pose 2 ms from its own time and two wrong poses (1 m off)
    # between frames; frames 0–1 precede the reference. The errors must be those against
    # the per-frame reference of the matched frames: a wrong match would add ~1 m.
    from torchslam.io.trajectories import write_trajectory

    frames = tmp_path / "scans"
    frames.mkdir()
    for k, cloud in enumerate(sequence.clouds[:12]):
        np.save(frames / f"{k}.npy", cloud.numpy())
    times = 1000.0 + 0.1 * np.arange(12)
    (frames / "times.txt").write_text("".join(f"{t:.6f}\n" for t in times))
    wrong = se3.compose(
        sequence.poses[:12], se3.exp(torch.tensor([0, 0, 0, 1.0, 0, 0], dtype=torch.float64))
    )
    poses = torch.cat([sequence.poses[2:12], wrong[2:12], wrong[2:12]])
    stamps = np.concatenate([times[2:] + 0.002, times[2:] + 0.033, times[2:] + 0.066])
    order = np.argsort(stamps)
    write_trajectory(tmp_path / "ref_tum.txt", poses[order], "tum", timestamps=stamps[order])
    code, stdout, err = call(
        ["slam", str(frames), "--reference", str(tmp_path / "ref_tum.txt"), "--no-loops",
         "--out", str(tmp_path / "out")], capsys,
    )  # fmt: skip
    assert code == 0, err
    assert "10 of 12 frames matched" in stdout
    result = run_sequence(frames, SLAMConfig.for_sensor("lidar", loops=False))
    ate = _ate(result.poses[2:], sequence.poses[2:12])
    reported = float(re.search(r"after back end: ATE ([0-9.]+) m", stdout).group(1))
    assert abs(reported - ate) <= 1e-4  # printed to 4 decimals
    # no timestamps on one side, or none near the frames: a one-line error
    write_trajectory(tmp_path / "ref_kitti.txt", poses, "kitti")
    code, _, err = call(
        ["slam", str(frames), "--reference", str(tmp_path / "ref_kitti.txt")], capsys
    )
    assert_one_line_error(code, err, "torchslam slam", "match them by time")
    write_trajectory(tmp_path / "late.txt", poses[order], "tum", timestamps=stamps[order] + 50.0)
    argv = ["slam", str(frames), "--reference", str(tmp_path / "late.txt"), "--no-loops"]
    code, _, err = call([*argv, "--out", str(tmp_path / "out2")], capsys)
    assert_one_line_error(code, err, "torchslam slam", "0 of 12 frames have a reference pose")


def test_depth_sequence_runs_from_a_folder(tmp_path):
    # two identical views of a flat wall 1.5 m away: the second frame stays at the first
    folder = _depth_folder(tmp_path)
    config = dataclasses.replace(SLAMConfig.for_sensor("depth"), pixel_stride=1)
    result = run_sequence(folder, config)
    assert result.num_frames == 2
    assert float(result.poses[1, :3, 3].norm()) < 1e-6


def test_turned_starts_are_right_perturbations():
    from torchslam.lie import so3
    from torchslam.slam.odometry import turned_starts

    T = se3.exp(torch.tensor([0.3, -0.2, 0.9, 1.0, 2.0, -3.0], dtype=torch.float64))
    assert turned_starts(T, 5.0, "z").shape == (2, 4, 4)
    torch.testing.assert_close(turned_starts(T, 5.0, "z"), turned_starts(T, 5.0)[4:])
    starts = turned_starts(T, 5.0)
    assert starts.shape == (6, 4, 4)
    angle = np.radians(5.0)
    for k in range(6):
        omega = torch.zeros(3, dtype=torch.float64)
        omega[k // 2] = angle if k % 2 else -angle
        expected = se3.compose(T, se3.from_rotation_translation(so3.exp(omega), omega.new_zeros(3)))
        # products of a few unit-norm 4×4 matrices: round-off of a few ulp
        torch.testing.assert_close(starts[k], expected, rtol=0, atol=1e-14)


def test_screening_recovers_an_alignment_in_a_wrong_basin(sequence):
    # The mechanism of odometry step 4 on its own: a main alignment slid 0.6 m (2.4 voxels)
    # along the trajectory, as the wide gate does on hand-held keyframes, must be replaced by
    # a start that converges to the right pose; a right main alignment must be kept.
    odometry = Odometry(SLAMConfig.for_sensor("lidar"))
    for cloud in sequence.clouds[:6]:
        odometry.add(cloud)
    truth = se3.compose(se3.inverse(sequence.poses[0]), sequence.poses[6])
    _, source = odometry._preprocess(sequence.clouds[6].to(torch.float64))
    slid = truth.clone()
    slid[:3, 3] += 0.6 * torch.nn.functional.normalize(truth[:3, 3] - odometry._last[:3, 3], dim=0)
    prediction = se3.compose(
        truth, se3.exp(torch.tensor([0.0, 0.0, 0.05, 0.1, 0.0, 0.0], dtype=torch.float64))
    )
    pose, start, passes = odometry._screen(source, prediction, slid)
    assert start >= 1 and passes > 0
    # the refined start is as good as a normal odometry step (test above: < 0.1 m)
    assert float((pose[:3, 3] - truth[:3, 3]).norm()) < 0.1
    kept, start, _ = odometry._screen(source, prediction, pose)
    assert start == 0 and torch.equal(kept, pose)


def test_screening_options_are_checked():
    assert SLAMConfig.for_sensor("depth").start_rotation_deg == 0.0  # off for 30 Hz depth
    assert SLAMConfig.for_sensor("lidar").start_rotation_deg > 0
    for name, value in (
        ("start_rotation_deg", -1.0),
        ("start_rotation_deg", 120.0),
        ("screen_points", 10),
        ("screen_iterations", 0),
        ("screen_voxels", 0.0),
        ("screen_margin", 1.5),
        ("start_axes", ""),
        ("start_axes", "zz"),
        ("start_axes", "w"),
    ):
        with pytest.raises(ValueError, match=f"SLAMConfig: argument '{name}'"):
            SLAMConfig(**{name: value})
    # with the screening off every pose comes from the main alignment
    result = run_sequence(make_sequence(8, seed=1).clouds, SLAMConfig(start_rotation_deg=0.0))
    assert all(f.start == 0 for f in result.frames)


def test_six_dof_wide_stage_tracks_the_known_motion(sequence):
    # The default wide stage keeps the predicted translation (coarse_rotation_only); with it
    # off that stage solves all six, and the odometry meets the same bound as the default
    # one (first test).
    assert SLAMConfig().coarse_rotation_only and SLAMConfig.for_sensor("depth").coarse_rotation_only
    config = SLAMConfig.for_sensor("lidar", coarse_rotation_only=False, refine_rounds=0)
    odometry = Odometry(config)
    for cloud in sequence.clouds[:20]:
        odometry.add(cloud)
    assert all(f.trusted for f in odometry.frames)
    assert _ate(odometry.poses, sequence.poses[:20]) < 0.05
    with pytest.raises(TypeError, match="SLAMConfig: argument 'coarse_rotation_only' must be"):
        SLAMConfig(coarse_rotation_only="yes")


def test_retries_run_the_two_stage_registration(sequence, monkeypatch):
    # An untrusted main alignment (forced here: the first judgement of frame 6 fails) is
    # retried from the prediction with a 3x wider gate, as the main registration runs: the
    # wide stage turning only, then all six at the judging gate. The retry is the same
    # alignment of the same frame, so it meets the odometry bound of the first test.
    from torchslam.slam import odometry as _odometry

    odometry = Odometry(SLAMConfig.for_sensor("lidar", refine_rounds=0, loops=False))
    for cloud in sequence.clouds[:6]:
        odometry.add(cloud)
    calls, judged = [], []
    icp, judge = _odometry.Odometry._icp, _odometry.Odometry._judge

    def recording_icp(self, source, initial, gate, iterations=None, matcher=None, **kw):
        calls.append((gate, kw.get("rotation_only", False), initial.dim()))
        return icp(self, source, initial, gate, iterations, matcher, **kw)

    def failing_once(self, source, T):
        quality = judge(self, source, T)
        judged.append(quality)
        return dataclasses.replace(quality, problem="forced") if len(judged) == 1 else quality

    monkeypatch.setattr(_odometry.Odometry, "_icp", recording_icp)
    monkeypatch.setattr(_odometry.Odometry, "_judge", failing_once)
    odometry.add(sequence.clouds[6])
    info = odometry.frames[-1]
    assert info.status == FrameStatus.RETRIED and info.trusted
    fine = _odometry.JUDGE_VOXELS * odometry.config.voxel
    single = [c for c in calls if c[2] == 2]  # the screening's batched run aside
    retry = single[-2:]
    assert retry[0][0] > 1.5 * fine and retry[0][1]  # the 3x gate, turning only
    assert retry[1] == (fine, False, 2)  # then all six at the judging gate
    assert _ate(odometry.poses, sequence.poses[:7]) < 0.05


def test_judging_from_the_icp_lookups_equals_a_fresh_query():
    """Odometry judges an alignment from the last ICP run's lookups (neighbors._Matcher):
    its certified answers are those of a fresh KD-tree query, so every measure equals
    alignment_quality's bit for bit, at the pose ICP left and at poses away from it (where
    the certificates fail and the points are looked up again)."""
    from torchslam.registration import alignment_quality
    from torchslam.registration import quality as _quality

    clouds = make_sequence(6, seed=2).clouds
    odometry = Odometry(SLAMConfig.for_sensor("lidar"))
    for cloud in clouds[:-1]:
        odometry.add(cloud)
    _, source = odometry._preprocess(odometry._check_points("test", clouds[-1])[0])
    prediction = odometry._predict()
    result = odometry._icp(source, prediction, 0.75)
    target, normals = odometry.map.state()
    gate = 0.75
    turn = se3.exp(torch.tensor([0.0, 0.0, 0.05, 0.3, -0.2, 0.1], dtype=torch.float64))
    for T in (result.transform, result.transform @ turn, prediction):
        lookups = odometry._lookups
        assert lookups is not None and lookups[0] is source
        got = _quality._measure(
            "test", source, target, normals, T, gate, odometry._thresholds, 0.025,
            odometry.map.tree, lookups[1],
        )  # fmt: skip
        want = alignment_quality(
            source, target, normals, T, gate, odometry._thresholds, noise_floor=0.025
        )
        assert (got.fitness, got.rms, got.condition, got.inliers, got.problem) == (
            want.fitness, want.rms, want.condition, want.inliers, want.problem,
        )  # fmt: skip
        assert torch.equal(got.information, want.information)


def test_make_depth_sequence_renders_the_surfaces_it_states():
    # Frames are ray-cast depth images: back-projected and mapped by their pose (camera →
    # world), every point lies on one of the scene's rectangles' planes to within the depth
    # noise (σ = noise·z² ≤ 0.0015 · 4² = 2.4 cm at the 4 m range cap; 5σ bound) plus the
    # millimetre quantization; the same frame renders the same bits twice.
    from torchslam.data import make_depth_sequence

    seq = make_depth_sequence(20, seed=3)
    assert len(seq) == 20 and seq.poses.shape == (20, 4, 4)
    image = seq.depth(5, stride=8)
    assert image.dtype == np.uint16 and image.shape == (60, 80)
    assert np.array_equal(image, seq.depth(5, stride=8))
    cloud = seq.cloud(5, stride=8)
    T = seq.poses[5]
    world = cloud @ T[:3, :3].T + T[:3, 3]
    table = seq.surfaces
    normal = torch.nn.functional.normalize(torch.linalg.cross(table[:, 1], table[:, 2]), dim=-1)
    plane = ((world[:, None, :] - table[None, :, 0]) * normal[None]).sum(-1).abs().min(1).values
    z = cloud[:, 2]
    assert bool((plane <= 5 * 0.0015 * z**2 + 0.001).all())
    with pytest.raises(ValueError, match="make_depth_sequence: the path"):
        make_depth_sequence(10, radius=3.0)
    with pytest.raises(ValueError, match=r"SyntheticDepthSequence\.depth: argument 'index'"):
        seq.depth(20)
