"""Range-sensor frames (torchslam.io.frames) on small files written here by the reference
writers (pypcd4, plyfile, imageio, numpy), plus one real file of each kind when the data sets
are available (torchslam.data: mirrored or cached)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import plyfile
import pypcd4
import pytest
import torch

from tests.helpers import dataset_folder
from torchslam.io.frames import (
    POINT_SUFFIXES,
    associate_timestamps,
    check_intrinsics,
    depth_to_points,
    find_intrinsics,
    find_timestamps,
    list_frames,
    read_depth,
    read_intrinsics,
    read_points,
    read_reference_poses,
    read_timestamps,
)

# Dyadic values (exact in float32 and printed exactly by pypcd4's ascii "%.10f").
XYZI = np.array(
    [
        [0.5, -1.25, 3.0, 7.0],
        [100.125, -0.375, 2.5, 1.0],
        [-8.0, 0.0, 0.0625, 255.0],
        [1.75, 2.25, -4.5, 0.5],
    ],
    dtype=np.float32,
)

# fx ≠ fy; all the back-projections below are exact in binary (dyadic numbers, few bits).
FX, FY, CX, CY = 2.0, 4.0, 2.5, 1.5
K = [[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]]
# A 4 × 5 (H × W) depth image in millimetres; every z = d / 1000 is a dyadic number.
DEPTH = np.array(
    [
        [1000, 2000, 500, 250, 1500],
        [4000, 3000, 1250, 750, 2500],
        [125, 1000, 2000, 3500, 6000],
        [8000, 500, 1000, 1750, 2000],
    ],
    dtype=np.uint16,
)


def _pixel(u: int, v: int, d: float, fx=FX, fy=FY, cx=CX, cy=CY, scale=1000.0) -> list[float]:
    """The docstring's back-projection of pixel (u column, v row) with depth d, by hand."""
    z = d / scale
    return [(u - cx) * z / fx, (v - cy) * z / fy, z]


def _all_pixels(depth: np.ndarray, stride: int = 1) -> list[list[float]]:
    """Every valid pixel, row-major (v outer, u inner), by hand."""
    rows = []
    for v in range(0, depth.shape[0], stride):
        for u in range(0, depth.shape[1], stride):
            d = float(depth[v, u])
            if d > 0 and d != 65535:
                rows.append(_pixel(u, v, d))
    return rows


def _names(paths) -> list[str]:
    return [p.name for p in paths]


def _touch(folder: Path, *names: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_bytes(b"x")


# ----------------------------------------------------------------------------------- PCD

ENCODINGS = [pypcd4.Encoding.ASCII, pypcd4.Encoding.BINARY, pypcd4.Encoding.BINARY_COMPRESSED]


@pytest.mark.parametrize("encoding", ENCODINGS, ids=lambda e: e.value)
def test_read_pcd_written_by_pypcd4_with_intensity(tmp_path, encoding):
    path = tmp_path / "cloud.pcd"
    pypcd4.PointCloud.from_xyzi_points(XYZI).save(path, encoding=encoding)
    assert f"DATA {encoding.value}".encode() in path.read_bytes()
    points = read_points(path)
    assert points.dtype == torch.float64 and points.shape == (4, 3)
    assert torch.equal(points, torch.from_numpy(XYZI[:, :3].astype(np.float64)))


@pytest.mark.parametrize("encoding", ENCODINGS, ids=lambda e: e.value)
def test_read_pcd_picks_xyz_by_name_whatever_the_field_order(tmp_path, encoding):
    columns = [XYZI[:, 3], XYZI[:, 2], XYZI[:, 0], XYZI[:, 1]]
    fields = ("intensity", "z", "x", "y")
    cloud = pypcd4.PointCloud.from_points(columns, fields, [np.float32] * 4)
    path = tmp_path / "cloud.pcd"
    cloud.save(path, encoding=encoding)
    assert torch.equal(read_points(path), torch.from_numpy(XYZI[:, :3].astype(np.float64)))


@pytest.mark.parametrize(
    "encoding", [pypcd4.Encoding.BINARY, pypcd4.Encoding.BINARY_COMPRESSED], ids=lambda e: e.value
)
def test_read_binary_pcd_keeps_every_float32_bit(tmp_path, encoding):
    rng = np.random.default_rng(7)
    xyzi = (rng.standard_normal((200, 4)) * 30).astype(np.float32)
    path = tmp_path / "cloud.pcd"
    pypcd4.PointCloud.from_xyzi_points(xyzi).save(path, encoding=encoding)
    points = read_points(path)
    assert torch.equal(points, torch.from_numpy(xyzi[:, :3].astype(np.float64)))
    assert torch.equal(read_points(path, dtype=torch.float32), torch.from_numpy(xyzi[:, :3]))


def test_read_pcd_without_z_names_the_missing_field(tmp_path):
    path = tmp_path / "flat.pcd"
    cloud = pypcd4.PointCloud.from_points(
        XYZI[:, [0, 1, 3]], ("x", "y", "intensity"), [np.float32] * 3
    )
    cloud.save(path, encoding=pypcd4.Encoding.BINARY)
    with pytest.raises(ValueError, match=r"flat\.pcd.*no field z"):
        read_points(path)


# --------------------------------------------------------------------------------- depth


def test_depth_to_points_hand_computed_pixels():
    points = depth_to_points(DEPTH, K)
    assert points.dtype == torch.float64 and points.shape == (20, 3)
    # Row-major: pixel (u, v) is row v * W + u (all 20 pixels are valid).
    for u, v in [(0, 0), (4, 0), (1, 2), (3, 1), (4, 3), (0, 3)]:
        assert points[v * 5 + u].tolist() == _pixel(u, v, float(DEPTH[v, u]))
    assert points[0].tolist() == [-1.25, -0.375, 1.0]  # (0 − 2.5)·1/2, (0 − 1.5)·1/4, 1
    assert points[19].tolist() == [1.5, 0.75, 2.0]  # u=4, v=3: (1.5·2/2, 1.5·2/4, 2)
    assert points.tolist() == _all_pixels(DEPTH)


def test_depth_to_points_accepts_tensors_and_float_images():
    expected = depth_to_points(DEPTH, K)
    assert torch.equal(depth_to_points(torch.from_numpy(DEPTH.astype(np.int32)), K), expected)
    metres = DEPTH.astype(np.float32) / 1000  # dyadic values: exact in float32
    assert torch.equal(depth_to_points(metres, K, depth_scale=1.0), expected)
    tum = depth_to_points(DEPTH.astype(np.float64) * 5, K, depth_scale=5000.0)
    assert torch.equal(tum, expected)


def test_depth_to_points_stride_keeps_the_image_pixel_coordinates():
    points = depth_to_points(DEPTH, K, stride=2)
    # Rows 0, 2 and columns 0, 2, 4, still at their own (u, v).
    assert points.tolist() == [_pixel(u, v, float(DEPTH[v, u])) for v in (0, 2) for u in (0, 2, 4)]
    assert points.tolist() == _all_pixels(DEPTH, stride=2)
    assert depth_to_points(DEPTH, K, stride=3).tolist() == _all_pixels(DEPTH, stride=3)
    assert depth_to_points(DEPTH, K, stride=10).tolist() == [_pixel(0, 0, 1000.0)]


def test_intrinsics_four_values_equal_the_matrix():
    expected = depth_to_points(DEPTH, K)
    for intrinsics in ((FX, FY, CX, CY), [FX, FY, CX, CY], np.array([FX, FY, CX, CY])):
        assert torch.equal(depth_to_points(DEPTH, intrinsics), expected)
    assert torch.equal(depth_to_points(DEPTH, torch.tensor(K)), expected)
    assert torch.equal(
        check_intrinsics("f", (FX, FY, CX, CY)), torch.tensor(K, dtype=torch.float64)
    )


def test_depth_to_points_with_skew_reprojects_onto_its_pixels():
    K_skew = torch.tensor([[500.0, 3.0, 319.5], [0.0, 480.0, 239.5], [0.0, 0.0, 1.0]])
    depth = np.full((3, 4), 1234, dtype=np.uint16)
    points = depth_to_points(depth, K_skew)
    pixels = (K_skew.double() @ points.T).T
    pixels = pixels[:, :2] / pixels[:, 2:]
    v, u = np.mgrid[0:3, 0:4]
    expected = torch.from_numpy(np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64))
    # K·p / z undoes the back-projection up to a few roundings of numbers ~ 500.
    assert torch.allclose(pixels, expected, rtol=0, atol=1e-9)
    assert torch.equal(points[:, 2], torch.full((12,), 1.234, dtype=torch.float64))


def test_uint16_zero_and_no_return_code_are_dropped():
    depth = DEPTH.copy()
    depth[0, 1] = 0
    depth[2, 3] = 65535
    depth[3, 0] = 0
    points = depth_to_points(depth, K)
    assert points.shape == (17, 3)
    assert points.tolist() == _all_pixels(depth)
    assert depth_to_points(np.zeros((2, 3), np.uint16), K).shape == (0, 3)
    assert depth_to_points(np.full((2, 3), 65535, np.uint16), K).shape == (0, 3)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_nonfinite_and_nonpositive_float_depths_are_dropped(dtype):
    depth = np.array([[1.0, np.nan, 2.0], [np.inf, -1.0, 0.5], [-np.inf, 0.0, 4.0]], dtype=dtype)
    points = depth_to_points(depth, (1.0, 2.0, 1.0, 1.0), depth_scale=1.0)
    expected = [[-1.0, -0.5, 1.0], [2.0, -1.0, 2.0], [0.5, 0.0, 0.5], [4.0, 2.0, 4.0]]
    assert points.tolist() == expected
    assert bool(torch.isfinite(points).all())


def test_min_and_max_range_are_inclusive_bounds_in_metres():
    z = sorted({float(d) / 1000 for d in DEPTH.ravel()})
    for low, high in [(0.5, 2.0), (1.0, 1.0 + 1e-9), (0.0, 0.125), (3.5, math.inf)]:
        points = depth_to_points(DEPTH, K, min_range=low, max_range=high)
        kept = [t for t in DEPTH.ravel().astype(np.float64) / 1000 if low <= t <= high]
        assert points[:, 2].tolist() == kept
        assert all(low <= t <= high for t in points[:, 2].tolist())
    assert z[0] == 0.125 and z[-1] == 8.0
    assert depth_to_points(DEPTH, K, min_range=9.0).shape == (0, 3)
    with pytest.raises(ValueError, match="max_range"):
        depth_to_points(DEPTH, K, min_range=2.0, max_range=1.0)


def test_read_depth_16bit_png_round_trip(tmp_path):
    depth = DEPTH.copy()
    depth[1, 1] = 0
    depth[3, 4] = 65535
    path = tmp_path / "frame-000000.depth.png"
    iio.imwrite(path, depth)
    assert iio.imread(path).dtype == np.uint16
    points = read_depth(path, K)
    assert torch.equal(points, depth_to_points(depth, K))
    assert points.shape == (18, 3)
    assert torch.equal(
        read_depth(path, (FX, FY, CX, CY), stride=2, max_range=3.0),
        depth_to_points(depth, K, stride=2, max_range=3.0),
    )


def test_read_depth_refuses_a_colour_image_naming_the_file(tmp_path):
    path = tmp_path / "frame-000000.color.png"
    iio.imwrite(path, np.zeros((4, 5, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match=r"frame-000000\.color\.png.*single-channel"):
        read_depth(path, K)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # imageio tries its legacy plugins
def test_read_depth_refuses_a_file_that_is_not_an_image(tmp_path):
    path = tmp_path / "broken.png"
    path.write_bytes(b"not a png at all")
    with pytest.raises(ValueError, match=r"broken\.png"):
        read_depth(path, K)


def test_read_depth_16bit_pgm_drops_the_no_return_code(tmp_path):
    depth = np.array([[1000, 0, 65535], [2000, 65535, 500]], dtype=np.uint16)
    path = tmp_path / "frame-0.pgm"
    path.write_bytes(b"P5\n3 2\n65535\n" + depth.astype(">u2").tobytes())  # 16-bit: big-endian
    assert torch.equal(read_depth(path, K), depth_to_points(depth, K))


# --------------------------------------------------------------------------- NaN points

NAN_XYZ = np.array(
    [[1.0, 2.0, 3.0], [np.nan, 0.0, 1.0], [0.5, -0.25, 8.0], [0.0, np.inf, 0.0], [4, 5, -np.inf]]
)
FINITE_XYZ = NAN_XYZ[[0, 2]]


def _write_npy(path):
    np.save(path, np.concatenate([NAN_XYZ, np.ones((5, 1))], axis=1))


def _write_text(path):
    path.write_text(
        "# x y z intensity\n1 2 3 10\nnan 0 1 11\n0.5,-0.25,8,12\n0 Inf 0 13\n4 5 -inf 14\n"
    )


def _write_ply(path):
    vertex = np.zeros(5, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4")])
    for i, k in enumerate("xyz"):
        vertex[k] = NAN_XYZ[:, i]
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(path))


def _write_pcd(path, encoding=pypcd4.Encoding.BINARY):
    xyzi = np.concatenate([NAN_XYZ, np.arange(5.0)[:, None]], axis=1).astype(np.float32)
    pypcd4.PointCloud.from_xyzi_points(xyzi).save(path, encoding=encoding)


def _write_bin(path):
    np.concatenate([NAN_XYZ, np.ones((5, 1))], axis=1).astype("<f4").tofile(path)


NAN_WRITERS = {
    "cloud.npy": _write_npy,
    "cloud.xyz": _write_text,
    "cloud.txt": _write_text,
    "cloud.pts": _write_text,
    "cloud.ply": _write_ply,
    "cloud.pcd": _write_pcd,
    "ascii.pcd": lambda p: _write_pcd(p, pypcd4.Encoding.ASCII),
    "cloud.bin": _write_bin,
}


@pytest.mark.parametrize("name", list(NAN_WRITERS))
def test_nonfinite_points_are_dropped_and_counted(tmp_path, name):
    path = tmp_path / name
    NAN_WRITERS[name](path)
    points, dropped = read_points(path, return_dropped=True)
    assert dropped == 3
    assert points.dtype == torch.float64 and points.shape == (2, 3)
    assert torch.equal(points, torch.from_numpy(FINITE_XYZ))
    assert torch.equal(read_points(path), points)
    assert torch.equal(read_points(path, nonfinite="drop"), points)


@pytest.mark.parametrize("name", list(NAN_WRITERS))
def test_nonfinite_raise_refuses_the_file(tmp_path, name):
    path = tmp_path / name
    NAN_WRITERS[name](path)
    with pytest.raises(ValueError, match=re.escape(str(path)) + r".*point 1 .*3 non-finite"):
        read_points(path, nonfinite="raise")


def test_finite_file_reports_zero_dropped(tmp_path):
    path = tmp_path / "cloud.npy"
    np.save(path, FINITE_XYZ)
    points, dropped = read_points(path, return_dropped=True, nonfinite="raise")
    assert dropped == 0 and torch.equal(points, torch.from_numpy(FINITE_XYZ))


def test_nonfinite_argument_is_checked(tmp_path):
    path = tmp_path / "cloud.npy"
    np.save(path, FINITE_XYZ)
    with pytest.raises(ValueError, match="nonfinite"):
        read_points(path, nonfinite="keep")


# ------------------------------------------------------------------------------ KITTI bin


def test_read_kitti_bin_records(tmp_path):
    records = np.array(
        [[1.5, -2.25, 0.125, 0.75], [10.0, 20.5, -3.0, 0.0], [-0.5, 0.0, 1.0, 1.0]],
        dtype="<f4",
    )
    path = tmp_path / "000000.bin"
    records.tofile(path)
    assert path.stat().st_size == 48
    points = read_points(path)
    assert points.dtype == torch.float64
    assert torch.equal(points, torch.from_numpy(records[:, :3].astype(np.float64)))


def test_kitti_bin_of_a_wrong_size_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "000001.bin"
    np.arange(7, dtype="<f4").tofile(path)  # 28 bytes
    with pytest.raises(ValueError, match=r"000001\.bin.*16 bytes.*28 bytes"):
        read_points(path)


# ------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize("suffix", POINT_SUFFIXES)
def test_empty_file_is_refused(tmp_path, suffix):
    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*empty"):
        read_points(path)


def test_unknown_suffix_lists_the_accepted_ones(tmp_path):
    path = tmp_path / "cloud.e57"
    path.write_bytes(b"1 2 3\n")
    with pytest.raises(ValueError, match=r"cloud\.e57.*'\.e57'") as info:
        read_points(path)
    for suffix in POINT_SUFFIXES:
        assert suffix in str(info.value)


def test_missing_files_raise_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_points(tmp_path / "missing.pcd")
    with pytest.raises(FileNotFoundError):
        read_depth(tmp_path / "missing.png", K)
    with pytest.raises(FileNotFoundError):
        read_intrinsics(tmp_path / "missing.txt")
    with pytest.raises(FileNotFoundError):
        read_timestamps(tmp_path / "times.txt")
    with pytest.raises(FileNotFoundError):
        read_reference_poses(tmp_path / "poses.txt")


@pytest.mark.parametrize(
    "content",
    [
        b"this is not a pcd\n\x00\x01garbage",
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 5\nHEIGHT 1\n"
        b"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 5\nDATA binary\n\x00\x00",  # truncated data
    ],
    ids=["garbage", "truncated"],
)
def test_garbage_pcd_is_refused_naming_the_file(tmp_path, content):
    path = tmp_path / "garbage.pcd"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=r"garbage\.pcd.*PCD"):
        read_points(path)


def test_garbage_ply_and_npy_are_refused_naming_the_file(tmp_path):
    for name in ("garbage.ply", "garbage.npy"):
        path = tmp_path / name
        path.write_bytes(b"definitely not the format\n")
        with pytest.raises(ValueError, match=re.escape(name)):
            read_points(path)
    path = tmp_path / "flat.npy"
    np.save(path, np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"flat\.npy.*\(N, ≥3\)"):
        read_points(path)


def test_text_cloud_with_a_bad_token_names_file_and_line(tmp_path):
    path = tmp_path / "cloud.xyz"
    path.write_text("# header\n1 2 3\n4 5 6\n7 oops 9\n")
    with pytest.raises(ValueError, match=r"cloud\.xyz: line 4: .*'oops'"):
        read_points(path)
    path.write_text("1 2 3\n\n4 5\n")
    with pytest.raises(ValueError, match=r"cloud\.xyz: line 3: expected x y z"):
        read_points(path)


def test_text_cloud_formats(tmp_path):
    path = tmp_path / "cloud.pts"
    path.write_text("2\n1 2 3 99 7\n// comment\n-0.5, 0.25, 1e2\n")
    assert read_points(path).tolist() == [[1.0, 2.0, 3.0], [-0.5, 0.25, 100.0]]


@pytest.mark.parametrize(
    "intrinsics",
    [[[1.0, 0.0], [0.0, 1.0]], [1.0, 1.0, 0.0, 0.0, 1.0], [1.0, 2.0, 3.0], np.eye(4)],
    ids=["2x2", "5-values", "3-values", "4x4"],
)
def test_wrong_intrinsics_shape_is_refused(intrinsics):
    with pytest.raises(ValueError, match="intrinsics"):
        depth_to_points(DEPTH, intrinsics)
    with pytest.raises(ValueError, match="intrinsics"):
        check_intrinsics("f", intrinsics)


@pytest.mark.parametrize(
    "intrinsics",
    [(0.0, 1.0, 2.0, 2.0), (-1.0, 1.0, 2.0, 2.0), (1.0, 0.0, 2.0, 2.0), (1.0, -5.0, 2.0, 2.0)],
)
def test_nonpositive_focal_length_is_refused(intrinsics):
    with pytest.raises(ValueError, match="fx, fy > 0"):
        depth_to_points(DEPTH, intrinsics)


def test_nonfinite_or_non_pinhole_intrinsics_are_refused():
    with pytest.raises(ValueError, match="finite"):
        check_intrinsics("f", (np.nan, 1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="pinhole"):
        check_intrinsics("f", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0]])


def test_read_intrinsics_seven_scenes_text(tmp_path):
    path = tmp_path / "camera-intrinsics.txt"
    path.write_bytes(
        b" 5.85000000e+02\t 0.00000000e+00\t 3.20000000e+02\t\n"
        b" 0.00000000e+00\t 5.85000000e+02\t 2.40000000e+02\t\n"
        b" 0.00000000e+00\t 0.00000000e+00\t 1.00000000e+00\t\n"
    )
    K_read = read_intrinsics(path)
    assert K_read.dtype == torch.float64
    assert torch.equal(K_read, torch.tensor([[585.0, 0, 320], [0, 585, 240], [0, 0, 1]]).double())


def test_read_intrinsics_four_numbers(tmp_path):
    path = tmp_path / "intrinsics.txt"
    path.write_text("# fx fy cx cy\n525.0 520.5 319.5 239.5\n")
    expected = torch.tensor([[525.0, 0, 319.5], [0, 520.5, 239.5], [0, 0, 1]]).double()
    assert torch.equal(read_intrinsics(path), expected)
    path.write_text("525.0, 520.5, 319.5, 239.5  # comma separated\n")
    assert torch.equal(read_intrinsics(path), expected)


def test_read_intrinsics_bad_files_name_the_file(tmp_path):
    path = tmp_path / "K.txt"
    path.write_text("1 2 3\n4 5 6\n7\n")
    with pytest.raises(ValueError, match=r"K\.txt.*got 7"):
        read_intrinsics(path)
    path.write_text("500 500 320\nabc\n")
    with pytest.raises(ValueError, match=r"K\.txt: line 2"):
        read_intrinsics(path)
    path.write_text("-500 500 320 240\n")
    with pytest.raises(ValueError, match=r"K\.txt.*fx, fy > 0"):
        read_intrinsics(path)


# ---------------------------------------------------------------------------- list_frames


def test_list_frames_sorts_numbers_as_numbers(tmp_path):
    _touch(tmp_path, "frame-10.pcd", "frame-2.pcd", "frame-1.pcd", "frame-100.pcd", "frame-9.pcd")
    paths, sensor = list_frames(tmp_path)
    assert sensor == "lidar"
    assert _names(paths) == [f"frame-{i}.pcd" for i in (1, 2, 9, 10, 100)]
    assert all(p.parent == tmp_path for p in paths)


def test_list_frames_prefers_depth_pngs_beside_colour_pngs(tmp_path):
    for i in (10, 2, 1):
        _touch(tmp_path, f"frame-{i:06d}.color.png", f"frame-{i}.depth.png", f"frame-{i}.pose.txt")
    _touch(tmp_path, "camera-intrinsics.txt", "README.txt")
    paths, sensor = list_frames(tmp_path)
    assert sensor == "depth"
    assert _names(paths) == ["frame-1.depth.png", "frame-2.depth.png", "frame-10.depth.png"]
    assert list_frames(tmp_path, sensor="depth") == (paths, "depth")


def test_list_frames_takes_every_png_when_none_is_named_depth(tmp_path):
    _touch(tmp_path, "b.png", "a.tif", "c.PGM", "notes.txt", "times.txt")
    paths, sensor = list_frames(tmp_path)
    assert sensor == "depth" and _names(paths) == ["a.tif", "b.png", "c.PGM"]


@pytest.mark.parametrize("suffix", [".pcd", ".bin", ".ply", ".npy"])
def test_list_frames_infers_lidar_and_ignores_text_files(tmp_path, suffix):
    _touch(tmp_path, f"000001{suffix}", f"000000{suffix}", "times.txt", "poses.txt", "a.xyz")
    assert list_frames(tmp_path) == (
        [tmp_path / f"000000{suffix}", tmp_path / f"000001{suffix}"],
        "lidar",
    )


def test_list_frames_with_depth_and_lidar_needs_a_sensor(tmp_path):
    _touch(tmp_path, "0.png", "1.png", "0.pcd")
    with pytest.raises(ValueError, match="sensor"):
        list_frames(tmp_path)
    pngs = [tmp_path / "0.png", tmp_path / "1.png"]
    assert list_frames(tmp_path, sensor="depth") == (pngs, "depth")
    assert list_frames(tmp_path, sensor="lidar") == ([tmp_path / "0.pcd"], "lidar")
    with pytest.raises(ValueError, match="sensor"):
        list_frames(tmp_path, sensor="camera")


def test_list_frames_refuses_several_point_formats(tmp_path):
    _touch(tmp_path, "0.pcd", "1.bin")
    with pytest.raises(ValueError, match="several formats"):
        list_frames(tmp_path)


def test_list_frames_looks_into_a_single_scans_subfolder(tmp_path):
    _touch(tmp_path / "Scans", "000010.pcd", "000002.pcd")
    _touch(tmp_path, "times.txt", "odom_poses.txt")
    paths, sensor = list_frames(tmp_path)
    assert sensor == "lidar"
    assert paths == [tmp_path / "Scans" / "000002.pcd", tmp_path / "Scans" / "000010.pcd"]


def test_list_frames_looks_into_a_preferred_subfolder_among_several(tmp_path):
    _touch(tmp_path / "rgb", "1.png")
    _touch(tmp_path / "depth", "2.png", "1.png")
    expected = [tmp_path / "depth" / "1.png", tmp_path / "depth" / "2.png"]
    assert list_frames(tmp_path) == (expected, "depth")


def test_list_frames_empty_and_missing_folders(tmp_path):
    with pytest.raises(ValueError, match="no frames"):
        list_frames(tmp_path)
    _touch(tmp_path, "times.txt")
    with pytest.raises(ValueError, match="no frames"):
        list_frames(tmp_path)
    with pytest.raises(FileNotFoundError):
        list_frames(tmp_path / "missing")
    with pytest.raises(ValueError, match="not a folder"):
        list_frames(tmp_path / "times.txt")


# ----------------------------------------------------------------------------- timestamps


def test_read_timestamps_one_per_line(tmp_path):
    path = tmp_path / "times.txt"
    path.write_text("0.000000e+00\n1.036400e-01\n2.073000e-01\n")
    times = read_timestamps(path, count=3)
    assert times.dtype == np.float64
    assert times.tolist() == [0.0, 0.10364, 0.2073]
    assert read_timestamps(path, names=["a.bin", "b.bin", "c.bin"]).tolist() == times.tolist()


def test_read_timestamps_tum_lines_matched_by_name(tmp_path):
    path = tmp_path / "depth.txt"
    path.write_text(
        "# depth maps\n# file: 'rgbd_dataset_freiburg1_xyz.bag'\n# timestamp filename\n"
        "1305031102.160407 depth/1305031102.160407.png\n"
        "1305031102.194330 depth/1305031102.194330.png\n"
        "1305031102.226738 depth/1305031102.226738.png\n"
    )
    in_order = [1305031102.160407, 1305031102.194330, 1305031102.226738]
    assert read_timestamps(path).tolist() == in_order
    names = ["1305031102.226738.png", "/data/depth/1305031102.160407.png"]
    assert read_timestamps(path, names=names, count=2).tolist() == [in_order[2], in_order[0]]
    with pytest.raises(ValueError, match=r"depth\.txt.*no timestamp for frame 'x\.png'"):
        read_timestamps(path, names=["x.png"])


def test_read_timestamps_association_lines(tmp_path):
    path = tmp_path / "associations.txt"
    path.write_text("1.5 rgb/a.png 1.25 depth/a.png\n2.5 rgb/b.png 2.75 depth/b.png\n")
    assert read_timestamps(path, names=["a.png", "b.png"]).tolist() == [1.25, 2.75]
    assert read_timestamps(path).tolist() == [1.5, 2.5]


def test_read_timestamps_count_mismatch_and_bad_token(tmp_path):
    path = tmp_path / "times.txt"
    path.write_text("0.0\n0.1\n")
    with pytest.raises(ValueError, match=r"times\.txt.*2 timestamps for 3 frames"):
        read_timestamps(path, count=3)
    path.write_text("0.0\nnope\n")
    with pytest.raises(ValueError, match=r"times\.txt: line 2"):
        read_timestamps(path)


def test_find_timestamps_and_intrinsics_in_the_folder_or_its_parent(tmp_path):
    frames = tmp_path / "seq" / "Scans"
    _touch(frames, "0.pcd")
    assert find_timestamps(frames) is None and find_intrinsics(frames) is None
    _touch(tmp_path / "seq", "times.txt", "K.txt")
    assert find_timestamps(frames) == tmp_path / "seq" / "times.txt"
    assert find_intrinsics(frames) == tmp_path / "seq" / "K.txt"
    _touch(frames, "timestamps.txt", "camera-intrinsics.txt")
    assert find_timestamps(frames) == frames / "timestamps.txt"  # the folder before its parent
    assert find_intrinsics(frames) == frames / "camera-intrinsics.txt"
    assert find_timestamps(tmp_path / "seq") == tmp_path / "seq" / "times.txt"


# -------------------------------------------------------------------------- reference poses

# Exact rotations: identity and 90° about z.
RZ90 = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
EXPECTED_POSES = torch.tensor(
    [
        [[1.0, 0, 0, 0.5], [0, 1, 0, -1.25], [0, 0, 1, 2.0], [0, 0, 0, 1]],
        [[0.0, -1, 0, 3.0], [1, 0, 0, 0.0], [0, 0, 1, -0.75], [0, 0, 0, 1]],
    ],
    dtype=torch.float64,
)


def test_read_reference_poses_kitti(tmp_path):
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0.5 0 1 0 -1.25 0 0 1 2.0\n0 -1 0 3.0 1 0 0 0.0 0 0 1 -0.75\n")
    poses, times = read_reference_poses(path, count=2)
    assert times is None
    assert poses.dtype == torch.float64 and poses.shape == (2, 4, 4)
    # The reader projects rotations onto SO(3) by an SVD: exact rotations come back to ~1 ulp.
    assert torch.allclose(poses, EXPECTED_POSES, rtol=0, atol=1e-12)
    assert torch.equal(poses[:, :3, 3], EXPECTED_POSES[:, :3, 3])
    with pytest.raises(ValueError, match="2 poses for 3 frames"):
        read_reference_poses(path, count=3)


def test_read_reference_poses_tum_returns_timestamps(tmp_path):
    path = tmp_path / "groundtruth.txt"
    path.write_text(
        "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n"
        "1305031098.6659 0.5 -1.25 2.0 0 0 0 1\n"
        "1305031098.6758 3.0 0.0 -0.75 0 0 1 1\n"  # qz = qw: 90° about z once normalized
    )
    poses, times = read_reference_poses(path)
    assert times.dtype == np.float64
    assert times.tolist() == [1305031098.6659, 1305031098.6758]
    # The quaternion is normalized by 1/√2, so its matrix is exact only to rounding.
    assert torch.allclose(poses, EXPECTED_POSES, rtol=0, atol=1e-12)
    assert torch.equal(poses[:, :3, 3], EXPECTED_POSES[:, :3, 3])


def test_read_reference_poses_folder_of_pose_files(tmp_path):
    _touch(tmp_path, "frame-000000.depth.png", "frame-000001.depth.png")
    for i, T in [(10, EXPECTED_POSES[1]), (2, EXPECTED_POSES[0])]:
        text = "\r\n".join("\t ".join(f"{x:.7e}" for x in row) for row in T.tolist())
        (tmp_path / f"frame-{i}.pose.txt").write_text(text + "\r\n")
    poses, times = read_reference_poses(tmp_path, count=2)
    assert times is None
    # Sorted frame-2 before frame-10; the SVD re-orthonormalization keeps exact rotations to ~ulp.
    assert torch.allclose(poses, EXPECTED_POSES, rtol=0, atol=1e-12)
    assert torch.equal(poses[:, :3, 3], EXPECTED_POSES[:, :3, 3])


def test_read_reference_poses_bad_inputs(tmp_path):
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0.5 0 1 0 -1.25 0 0 1 2.0\n0.0 1 2 3 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"poses\.txt.*\[8, 12\]"):
        read_reference_poses(path)
    folder = tmp_path / "empty"
    folder.mkdir()
    with pytest.raises(ValueError, match=r"no \*\.pose\.txt"):
        read_reference_poses(folder)
    (folder / "frame-0.pose.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(ValueError, match=r"frame-0\.pose\.txt.*got 6 numbers"):
        read_reference_poses(folder)


# ---------------------------------------------------------------------------- real data

_HKU = dataset_folder("lidar-hku2-loop")
_SEVEN_SCENES = dataset_folder("rgbd-7scenes")


@pytest.mark.skipif(not _HKU.is_dir(), reason=f"data set not found ({_HKU})")
def test_real_hku_lidar_scan():
    path = _HKU / "Scans" / "000000.pcd"
    if not path.is_file():
        pytest.skip(f"{path} missing")
    points, dropped = read_points(path, return_dropped=True)
    assert points.dtype == torch.float64 and points.ndim == 2 and points.shape[1] == 3
    assert points.shape[0] > 1000 and dropped >= 0
    assert bool(torch.isfinite(points).all())


@pytest.mark.skipif(not _SEVEN_SCENES.is_dir(), reason=f"data set not found ({_SEVEN_SCENES})")
def test_real_seven_scenes_depth_frame():
    folder = _SEVEN_SCENES
    path = folder / "frame-000150.depth.png"
    if not path.is_file():
        pytest.skip(f"{path} missing")
    intrinsics = find_intrinsics(folder)
    assert intrinsics == folder / "camera-intrinsics.txt"
    K_read = read_intrinsics(intrinsics)
    assert K_read.tolist() == [[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]]
    points = read_depth(path, K_read)
    assert points.shape[0] > 1000
    z = points[:, 2]
    assert bool((z > 0).all()) and bool((z <= 10.0).all())
    paths, sensor = list_frames(folder)
    assert sensor == "depth" and paths[0] == path


def test_las_points_are_read_scaled(tmp_path):
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([100.0, 200.0, 0.0])
    data = laspy.LasData(header)
    xyz = np.array([[100.5, 200.25, 1.0], [101.0, 199.0, -2.5]])
    data.x, data.y, data.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    data.write(tmp_path / "scan.las")
    points = read_points(tmp_path / "scan.las")
    # the file stores integers of 1 mm: the coordinates come back to that resolution
    np.testing.assert_allclose(points.numpy(), xyz, rtol=0, atol=1e-9)
    (tmp_path / "bad.las").write_bytes(b"LASF" + b"\x00" * 20)
    with pytest.raises(ValueError, match=r"bad\.las"):
        read_points(tmp_path / "bad.las")


def test_las_without_laspy_says_how_to_install(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "laspy", None)  # import laspy raises ImportError
    (tmp_path / "scan.las").write_bytes(b"LASF" + b"\x00" * 20)
    with pytest.raises(ImportError, match=r"torchslam\[las\]"):
        read_points(tmp_path / "scan.las")


def test_associate_timestamps_takes_the_nearest_sample_within_the_bound():
    # 30 Hz frames against a 100 Hz reference, given out of order; the last frame is 2 s
    # past the reference's end. The times are multiples of 1/2⁷ s plus a third of that, so
    # every difference compared is far from the 0.01 s bound and from a tie.
    step = 1 / 128
    reference = np.arange(0.0, 1.0, step)[::-1]
    frames = np.array([0.0, 4, 8, 12]) * step + step / 3
    frames = np.append(frames, 3.0)
    matched_frames, matched = associate_timestamps(frames, reference, max_difference=0.01)
    assert matched_frames.tolist() == [0, 1, 2, 3]
    np.testing.assert_array_equal(reference[matched], [0.0, 4 * step, 8 * step, 12 * step])
    # a bound below the offset leaves every frame unmatched; 0 matches equal times only
    assert associate_timestamps(frames, reference, max_difference=step / 4)[0].size == 0
    assert associate_timestamps([0.5], [0.5, 0.25], max_difference=0.0)[1].tolist() == [0]
    assert associate_timestamps(torch.tensor([2.0]), [2.004])[0].tolist() == [0]  # one sample
    # a tie takes the earlier sample
    assert associate_timestamps([1.5], [1.0, 2.0], max_difference=1.0)[1].tolist() == [0]


@pytest.mark.parametrize(
    ("times", "reference", "message"),
    [
        ([], [1.0], "'times' must be a non-empty 1-D"),
        ([[1.0]], [1.0], "'times' must be a non-empty 1-D"),
        ([1.0], [np.nan], "'reference_times' holds non-finite"),
        (["a"], [1.0], "'times' must be a 1-D sequence of numbers"),
    ],
)
def test_associate_timestamps_refuses_bad_times(times, reference, message):
    error = TypeError if message.endswith("numbers") else ValueError
    with pytest.raises(error, match=re.escape(message)):
        associate_timestamps(times, reference)
    with pytest.raises(ValueError, match="max_difference"):
        associate_timestamps([1.0], [1.0], max_difference=-1.0)


@pytest.mark.parametrize(
    ("name", "dtype"),
    [("d.png", np.uint16), ("d8.png", np.uint8), ("d.tif", np.float32), ("d16.tif", np.uint16),
     ("d.pgm", np.uint16)],
)  # fmt: skip
def test_depth_images_read_directly_equal_imageio(tmp_path, name, dtype):
    # read_depth reads one-frame single-channel images through Pillow directly: the pixels
    # (and so the points) must be imageio's, bit for bit
    from torchslam.io.frames import _single_channel_image

    rng = np.random.default_rng(0)
    high = 1.0 if dtype == np.float32 else np.iinfo(dtype).max
    image = (rng.random((12, 16)) * high).astype(dtype)
    iio.imwrite(tmp_path / name, image)
    direct = _single_channel_image(str(tmp_path / name))
    expected = iio.imread(tmp_path / name)
    assert direct is not None and direct.dtype == expected.dtype
    np.testing.assert_array_equal(direct, expected)
    K = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    points = read_depth(tmp_path / name, K, depth_scale=1.0)
    expected_points = depth_to_points(
        expected.astype(np.uint16) if expected.dtype == np.int32 else expected, K, depth_scale=1.0
    )
    assert torch.equal(points, expected_points)
    # colour and palette images go through imageio (and are refused or converted as before)
    Image = pytest.importorskip("PIL.Image")
    Image.fromarray(np.zeros((4, 4), np.uint8)).convert("P").save(tmp_path / "p.png")
    assert _single_channel_image(str(tmp_path / "p.png")) is None
