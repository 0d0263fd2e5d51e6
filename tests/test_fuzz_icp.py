"""Seeded boundary fuzz of the ICP front end (icp, alignment, tracks): one test per class of
finding of the adversarial review (clear errors naming function and argument, numpy clouds,
no wrong answers at extreme scales, masked entries inert)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

import torchslam
from torchslam import alignment
from torchslam.lie import se3, so3
from torchslam.registration import icp, tracks
from torchslam.registration.icp import ICPConfig

F64 = torch.float64


def _cloud(n: int = 40, seed: int = 0, dtype: torch.dtype = F64) -> torch.Tensor:
    return torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def _pair(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    source = _cloud(40, seed)
    T = se3.exp(torch.tensor([0.05, -0.02, 0.03, 0.1, 0.0, -0.05], dtype=F64))
    return source, se3.act(T, source), T


def test_voxel_downsample_matches_reference_at_any_pitch() -> None:
    # Reference: group by the exact float cell coordinates floor((p - min) / v) in Python.
    def reference(points: torch.Tensor, voxel: float) -> torch.Tensor:
        cells = torch.floor((points - points.amin(0)) / voxel).tolist()
        groups: dict[tuple[float, ...], list[int]] = {}
        for row, cell in enumerate(cells):
            groups.setdefault(tuple(cell), []).append(row)
        return torch.stack([points[groups[key]].mean(0) for key in sorted(groups)])

    rng = torch.Generator().manual_seed(7)
    for trial in range(20):
        points = torch.rand(30, 3, generator=rng, dtype=F64) * 10.0 ** (trial % 7 - 3)
        points[::5] = points[1::5]  # duplicates: always share a voxel
        for voxel in (1e-300, 1e-12, 1e-3, 0.05, 1.0, 1e6):
            got = icp.voxel_downsample(points, voxel)
            # Same groups, so the same sums in a possibly different order: a few ulps.
            assert torch.allclose(got, reference(points, voxel), rtol=1e-12, atol=0.0)
    tiny = torch.tensor([[0.0, 0, 0], [1.0, 1, 1], [1e-3, 2e-3, 3e-3]], dtype=F64)
    assert icp.voxel_downsample(tiny, 1e-300).shape == (3, 3)
    wide = torch.tensor([[0.0, 0, 0], [1e6, 0, 0], [0, 1e6, 0], [0, 0, 1e6], [1.0, 1, 1]])
    assert icp.voxel_downsample(wide.double(), 1e-4).shape == (5, 3)  # > 2^62 cells
    with pytest.raises(ValueError, match=r"voxel_downsample: argument 'voxel_size' .* too small"):
        icp.voxel_downsample(tiny, 1e-310)  # 1 / 1e-310 overflows float64
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="voxel_downsample: argument 'voxel_size'"):
            icp.voxel_downsample(tiny, bad)
    with pytest.raises(TypeError, match="voxel_downsample: argument 'voxel_size'"):
        icp.voxel_downsample(tiny, "0.1")  # type: ignore[arg-type]


@pytest.mark.parametrize("validate", [True, False])
def test_non_finite_clouds_refused_with_names(validate: bool) -> None:
    source, target, _ = _pair()
    rotations = icp.rotations_about_axis(2)
    for value in (math.nan, math.inf, -math.inf):
        _refuse_non_finite(validate, source, target, rotations, value)


def _refuse_non_finite(
    validate: bool,
    source: torch.Tensor,
    target: torch.Tensor,
    rotations: torch.Tensor,
    value: float,
) -> None:
    bad = source.clone()
    bad[3, 1] = value
    calls = {
        ("icp", "source"): lambda: icp.icp(bad, target),
        ("icp", "target"): lambda: icp.icp(source, bad),
        ("icp_batch", "target"): lambda: icp.icp_batch(source, bad, se3.identity(2)),
        ("icp_multistart", "source"): lambda: icp.icp_multistart(
            bad, target, se3.identity(2), fitness_distance=0.1
        ),
        ("register_coarse_to_fine", "target"): lambda: icp.register_coarse_to_fine(
            source, bad, se3.identity(2), [icp.Stage(0.0, fitness_distance=0.1)]
        ),
        ("nearest_neighbors", "query"): lambda: icp.nearest_neighbors(bad, target),
        ("nearest_neighbors", "reference"): lambda: icp.nearest_neighbors(source, bad),
        ("estimate_normals", "points"): lambda: icp.estimate_normals(bad, 5),
        ("voxel_downsample", "points"): lambda: icp.voxel_downsample(bad, 0.5),
        ("mutual_nearest_neighbors", "first"): lambda: tracks.mutual_nearest_neighbors(
            bad, target, 0.1
        ),
        ("build_tracks", "clouds[1]"): lambda: tracks.build_tracks(
            [source, bad], se3.identity(2), 0.1
        ),
    }
    if validate:  # pure-torch functions check values only when validation is on
        calls[("initial_guesses", "source")] = lambda: icp.initial_guesses(bad, target, rotations)
        calls[("weighted_kabsch", "target")] = lambda: alignment.weighted_kabsch(source, bad)
    with torchslam.validation(validate):
        for (fn, name), call in calls.items():
            pattern = rf"^{fn}: argument '{re.escape(name)}' contains .* non-finite"
            with pytest.raises(ValueError, match=pattern):
                call()


def test_numpy_clouds_accepted_and_dtypes_not_mixed() -> None:
    source, target, T = _pair()
    expected = icp.icp(source, target)
    assert torch.allclose(expected.transform, T, atol=1e-9)  # exact correspondences
    for s, t in (
        (source.numpy(), target),
        (source, target.numpy()),
        (source.numpy(), target.numpy()),
    ):
        got = icp.icp(s, t)
        assert isinstance(got.transform, torch.Tensor)
        assert torch.equal(got.transform, expected.transform)
    # float32 numpy arrays stay float32; mixing float32 and float64 is a TypeError.
    with pytest.raises(TypeError, match=r"icp: 'source' is torch.float32 but 'target'"):
        icp.icp(source.numpy().astype(np.float32), target)
    with pytest.raises(TypeError, match="icp: argument 'source' must be float32 or float64"):
        icp.icp(source.numpy().astype(np.int64), target)
    with pytest.raises(TypeError, match=r"icp: argument 'source' must be a torch.Tensor or"):
        icp.icp(source.tolist(), target)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"nearest_neighbors: 'query' is torch.float32"):
        icp.nearest_neighbors(source.float(), target)
    _, i = icp.nearest_neighbors(source.numpy()[::-1], target)  # negative strides
    assert torch.equal(i, icp.nearest_neighbors(source.flip(0), target)[1])
    assert torch.equal(icp.voxel_downsample(source.numpy(), 0.5), icp.voxel_downsample(source, 0.5))
    assert torch.equal(icp.estimate_normals(source.numpy(), 5), icp.estimate_normals(source, 5))
    assert torch.equal(
        alignment.weighted_kabsch(source.numpy(), target.numpy()),
        alignment.weighted_kabsch(source, target),
    )
    assert torch.equal(
        tracks.mutual_nearest_neighbors(source.numpy(), source + 1e-3, 0.1),
        tracks.mutual_nearest_neighbors(source, source + 1e-3, 0.1),
    )
    built = tracks.build_tracks([source.numpy(), source + 1e-3], se3.identity(2), 0.1)
    assert built.num_points == 40


def test_nearest_neighbors_max_distance_validated() -> None:
    source, target, _ = _pair()
    unbounded = icp.nearest_neighbors(source, target)
    assert all(
        torch.equal(a, b)
        for a, b in zip(unbounded, icp.nearest_neighbors(source, target, math.inf), strict=True)
    )
    for bad in (math.nan, -1.0, 0.0, -math.inf):
        with pytest.raises(ValueError, match="nearest_neighbors: argument 'max_distance'"):
            icp.nearest_neighbors(source, target, bad)
    with pytest.raises(TypeError, match="nearest_neighbors: argument 'max_distance'"):
        icp.nearest_neighbors(source, target, "1")  # type: ignore[arg-type]
    empty = icp.nearest_neighbors(torch.zeros(0, 3, dtype=F64), target)
    assert empty[0].shape == (0,) and empty[1].shape == (0,)


def test_zero_hypotheses_and_config_type() -> None:
    source, target, _ = _pair()
    none = torch.zeros(0, 4, 4, dtype=F64)
    runs = icp.icp_batch(source, target, none)
    assert runs.transform.shape == (0, 4, 4) and runs.status.shape == (0,)
    assert runs.reason == [] and runs.history.shape == (1, 0)
    with pytest.raises(ValueError, match=r"icp_multistart: argument 'initial' .*B ≥ 1"):
        icp.icp_multistart(source, target, none, fitness_distance=0.1)
    with pytest.raises(ValueError, match=r"register_coarse_to_fine: argument 'initial'"):
        icp.register_coarse_to_fine(source, target, none, [icp.Stage(0.0, fitness_distance=1)])
    for fn, call in (
        ("icp", lambda c: icp.icp(source, target, config=c)),
        ("icp_batch", lambda c: icp.icp_batch(source, target, se3.identity(1), c)),
        ("icp_multistart", lambda c: icp.icp_multistart(source, target, se3.identity(1), c)),
    ):
        with pytest.raises(TypeError, match=rf"{fn}: argument 'config' must be an ICPConfig"):
            call({"max_iterations": 3})
    with pytest.raises(ValueError, match="icp_multistart: argument 'fitness_distance'"):
        icp.icp_multistart(source, target, se3.identity(1), fitness_distance=math.nan)
    with pytest.raises(TypeError, match="register_coarse_to_fine: argument 'stages'"):
        icp.register_coarse_to_fine(source, target, se3.identity(1), [ICPConfig()])  # type: ignore[list-item]


@pytest.mark.parametrize(
    ("field", "value", "error"),
    [
        ("method", 3, ValueError),
        ("max_iterations", 2.5, TypeError),
        ("max_iterations", "5", TypeError),
        ("max_iterations", True, TypeError),
        ("max_iterations", -3, ValueError),
        ("relative_tolerance", math.nan, ValueError),
        ("relative_tolerance", -1e-3, ValueError),
        ("max_distance", 0.0, ValueError),
        ("max_distance", math.inf, ValueError),
        ("min_distance", math.nan, ValueError),
        ("min_distance", math.inf, ValueError),
        ("min_distance", -1.0, ValueError),
        ("gate_scale", math.inf, ValueError),
        ("gate_scale", 0.0, ValueError),
        ("trim_fraction", 1.5, ValueError),
        ("trim_fraction", "1", TypeError),
        ("min_correspondences", 3.5, TypeError),
        ("min_correspondences", 2, ValueError),
    ],
)
def test_icp_config_fields_validated(field: str, value: object, error: type) -> None:
    with pytest.raises(error, match=rf"ICPConfig: .*'{field}'") as info:
        ICPConfig(**{field: value})  # type: ignore[arg-type]
    if isinstance(value, (int, float)) and not isinstance(value, bool) and field != "method":
        assert repr(value) in str(info.value) or f"{value:g}" in str(info.value)
    with pytest.raises(
        ValueError, match=r"ICPConfig: argument 'min_distance' .* <= 'max_distance'"
    ):
        ICPConfig(max_distance=0.1, min_distance=1.0)
    ICPConfig(max_distance=1, min_distance=1, gate_scale=None, max_iterations=np.int64(3))


def test_small_helpers_validate_with_their_own_names() -> None:
    source, target, _ = _pair()
    with pytest.raises(TypeError, match="estimate_normals: argument 'neighbors'"):
        icp.estimate_normals(source, 5.5)  # type: ignore[arg-type]
    for k in (2, 41):
        with pytest.raises(ValueError, match="estimate_normals: argument 'neighbors'"):
            icp.estimate_normals(source, k)
    with pytest.raises(ValueError, match="estimate_normals: argument 'viewpoint'"):
        icp.estimate_normals(source, 5, torch.zeros(2, 3, dtype=F64))
    with pytest.raises(
        ValueError, match="rotations_about_axis: argument 'axis' must be a non-zero"
    ):
        icp.rotations_about_axis(4, torch.zeros(3, dtype=F64))
    for count in (2.5, "4", 0, True):
        for fn in (icp.rotations_about_axis, icp.rotations_uniform):
            with pytest.raises((TypeError, ValueError), match=rf"{fn.__name__}: argument 'count'"):
                fn(count)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="rotations_uniform: argument 'dtype'"):
        icp.rotations_uniform(4, dtype=torch.int64)
    with pytest.raises(TypeError, match="rotations_about_axis: argument 'dtype'"):
        icp.rotations_about_axis(4, dtype=torch.int64)
    with pytest.raises(
        ValueError, match="initial_guesses: argument 'rotations' must hold rotation"
    ):
        icp.initial_guesses(source, target, torch.ones(2, 3, 3, dtype=F64))
    with pytest.raises(ValueError, match="chain_poses: argument 'relative' must hold rotation"):
        icp.chain_poses(torch.ones(2, 4, 4, dtype=F64))
    assert icp.chain_poses(torch.zeros(0, 4, 4, dtype=F64)).shape == (1, 4, 4)


def test_weighted_kabsch_scale_free() -> None:
    # Random well-spread problems (singular-value gaps of the cross-covariance O(1)): the
    # rotation is well conditioned, so rounding of the scaled inputs (one ulp each) moves R
    # and t / scale by O(10 eps); 1e-12 leaves a wide margin.
    rng = torch.Generator().manual_seed(3)
    for _ in range(10):
        s = torch.randn(4, 12, 3, generator=rng, dtype=F64)
        R = so3.exp(torch.randn(4, 3, generator=rng, dtype=F64))
        t = s @ R.transpose(-1, -2) + torch.randn(4, 1, 3, generator=rng, dtype=F64)
        w = torch.rand(4, 12, generator=rng, dtype=F64) + 0.1
        T = alignment.weighted_kabsch(s, t, w)
        assert torch.allclose(T[..., :3, :3], R, atol=1e-12)
        for scale in (1e160, 1e300, 1e-160, 1e-300):
            Ts = alignment.weighted_kabsch(s * scale, t * scale, w * 1e300)
            assert torch.allclose(Ts[..., :3, :3], T[..., :3, :3], rtol=0, atol=1e-12)
            assert torch.allclose(Ts[..., :3, 3] / scale, T[..., :3, 3], rtol=0, atol=1e-12)
    # Finite clouds centred at ±1e308: t = μ_t − μ_s = −2e308 is not representable.
    base = torch.randn(5, 3, generator=rng, dtype=F64) * 1e306
    with pytest.raises(ValueError, match=r"weighted_kabsch: the translation .* overflows"):
        alignment.weighted_kabsch(base + 1e308, base - 1e308)


def test_weighted_kabsch_masked_weights_inert() -> None:
    rng = torch.Generator().manual_seed(11)
    s = torch.randn(10, 3, generator=rng, dtype=F64)
    t = s @ so3.exp(torch.randn(3, generator=rng, dtype=F64)).T + 1.0
    mask = torch.ones(10, dtype=torch.bool)
    mask[7:] = False
    expected = alignment.weighted_kabsch(s[:7], t[:7])
    for junk in (math.nan, math.inf, -1.0):
        w = torch.ones(10, dtype=F64)
        w[7:] = junk
        s2, t2 = s.clone(), t.clone()
        s2[7:], t2[7:] = junk, -junk
        a = s2.clone().requires_grad_(True)
        b = w.clone().requires_grad_(True)
        got = alignment.weighted_kabsch(a, t2, b, mask)
        assert torch.allclose(got, expected, atol=1e-12)  # same 7 points: rounding only
        got.sum().backward()
        assert torch.isfinite(a.grad).all() and torch.isfinite(b.grad).all()
        assert (a.grad[7:] == 0).all() and (b.grad[7:] == 0).all()
    w = torch.ones(10, dtype=F64)
    w[2] = -1.0
    with pytest.raises(ValueError, match=r"weighted_kabsch: argument 'weights' must be >= 0"):
        alignment.weighted_kabsch(s, t, w, mask)
    with pytest.raises(
        ValueError, match=r"weighted_kabsch: problem \(\) has 0 .*\(after 'mask' and 'weights'\)"
    ):
        alignment.weighted_kabsch(s, t, torch.zeros(10, dtype=F64))


def test_tracks_arguments_validated() -> None:
    a = _cloud(30, 5)
    clouds = [a, a + 1e-3, a + 2e-3]
    poses = se3.identity(3)
    for pairs in ([(0, 1, 2)], [(0.0, 1.0)], [(-1, 0)], [(0, 5)], [(1, 1)], [3], "01"):
        with pytest.raises((TypeError, ValueError), match="build_tracks: argument 'pairs"):
            tracks.build_tracks(clouds, poses, 0.01, pairs=pairs)  # type: ignore[arg-type]
    assert tracks.build_tracks(clouds, poses, 0.01, pairs=np.array([[0, 1], [1, 2]])).num_points
    for kwargs, error in (
        ({"min_views": 2.5}, TypeError),
        ({"min_views": 1}, ValueError),
        ({"conflicts": "merge"}, ValueError),
        ({"radius": "1"}, TypeError),
        ({"radius": math.nan}, ValueError),
    ):
        arg = next(iter(kwargs))
        call = {"radius": 0.01, **kwargs}
        with pytest.raises(error, match=rf"build_tracks: argument '{arg}'"):
            tracks.build_tracks(clouds, poses, **call)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="build_tracks: argument 'clouds' must be a list"):
        tracks.build_tracks(torch.stack(clouds), poses, 0.01)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="mutual_nearest_neighbors: argument 'radius'"):
        tracks.mutual_nearest_neighbors(a, a, "1")  # type: ignore[arg-type]
    assert tracks.mutual_nearest_neighbors(a, a + 1e-3, math.inf).shape == (30, 2)
