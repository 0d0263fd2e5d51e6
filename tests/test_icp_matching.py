"""The fast paths of the ICP front end give the answers of the plain computations.

- ICP's correspondences (:class:`torchslam.registration.neighbors._Matcher`), which skip the
  KD-tree for points whose previous nearest neighbour is certain to still be the nearest,
  equal a fresh brute-force nearest-neighbour search at every pass.
- The closed-form normals equal the eigenvectors of a LAPACK eigendecomposition.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from torchslam.lie import se3
from torchslam.registration import icp, neighbors
from torchslam.registration.kdtree import KDTree

F64 = torch.float64


def _wavy(count: int, generator: torch.Generator) -> torch.Tensor:
    """Points near a bumpy sheet about 2 units across (spacing about 0.1)."""
    uv = 2 * torch.rand(count, 2, generator=generator, dtype=F64) - 1
    height = 0.2 * torch.sin(3 * uv[:, :1]) * torch.cos(2 * uv[:, 1:])
    noise = 0.01 * torch.randn(count, 1, generator=generator, dtype=F64)
    return torch.cat((uv, height + noise), -1)


class _CountingTree:
    """The library's KDTree, counting the points it is asked about."""

    def __init__(self, points: np.ndarray) -> None:
        self.tree = KDTree(points)
        self.asked = 0

    def query(self, x, **kwargs):
        self.asked += len(x)
        return self.tree.query(x, **kwargs)


def test_matcher_equals_a_fresh_search_at_every_pass(generator) -> None:
    target = _wavy(500, generator)
    # Exact duplicates: ties between two nearest points must still give a nearest point.
    target = torch.cat((target, target[:25]))
    source = _wavy(400, generator) + torch.tensor([0.0, 0.0, 0.03], dtype=F64)
    batch = 3
    tree = _CountingTree(target.numpy())
    matcher = neighbors._Matcher(tree, target.numpy(), batch, len(source))  # type: ignore[arg-type]
    goal = se3.exp(0.05 * torch.randn(batch, 6, generator=generator, dtype=F64))
    T = goal @ se3.exp(0.3 * torch.randn(batch, 6, generator=generator, dtype=F64))
    gate = np.array([0.4, 0.25, 0.15])
    rows = np.arange(batch)
    asked = []
    for step in range(12):
        if step == 6:
            rows = np.array([0, 2])  # run 1 stopped
        if step == 8:
            # A jump far larger than the point spacing: every answer must be looked up again.
            T[2] = se3.exp(torch.tensor([0.0, 0.0, 0.3, 0.2, 0.0, 0.0], dtype=F64)) @ T[2]
        moved = icp._move(T[torch.from_numpy(rows)], source)
        before = tree.asked
        distance, index = matcher(rows, moved, gate[rows], "test", "source")
        asked.append(tree.asked - before)
        # (R, n, M) from squared differences (not the less accurate Gram-matrix form)
        true = torch.cdist(moved, target[None], compute_mode="donot_use_mm_for_euclid_dist")
        nearest, _ = true.min(-1)
        for r in range(len(rows)):
            inside = nearest[r] <= gate[rows[r]]
            found = index[r] >= 0
            # Every point with a target point within the gate gets its nearest one...
            assert found[inside].all()
            assert torch.allclose(distance[r][inside], nearest[r][inside], rtol=1e-13, atol=0)
            # ... and any other answer is a true nearest point (beyond the gate) or none.
            assert torch.isinf(distance[r][~found]).all()
            where = found.nonzero().squeeze(-1)
            assert torch.allclose(distance[r][where], nearest[r][where], rtol=1e-13, atol=0)
            # The index names a point at that distance (duplicates: either copy).
            at = true[r, where, index[r][where]]
            assert torch.allclose(at, nearest[r][where], rtol=1e-13, atol=0)
        # Converge towards the goal (shrinking steps), gates shrinking as ICP's do.
        T = se3.exp(0.75 * se3.log(goal @ se3.inverse(T))) @ T
        gate = np.maximum(0.8 * gate, 0.1)
    # Near convergence most points keep their answer without a lookup.
    assert asked[0] == batch * len(source)
    assert min(asked[4:8]) < 0.2 * 2 * len(source)
    assert asked[8] >= len(source)  # the jumped run looked all its points up again


def test_icp_results_do_not_depend_on_skipped_lookups(generator) -> None:
    """icp with the matcher equals ICP whose every pass queries the tree (same iterations,
    transforms to round-off: the correspondences are the same)."""
    from tests.test_icp import views

    true_transform = se3.exp(torch.tensor([0.25, -0.15, 0.2, 0.3, -0.2, 0.1], dtype=F64))
    source, target = views(generator, true_transform, noise=0.002, count=2000)
    normals = icp.estimate_normals(target, 10)
    config = icp.ICPConfig(
        method="point_to_plane", max_distance=0.3, min_distance=0.02, max_iterations=40
    )
    initial = se3.exp(torch.tensor([0.02, -0.01, 0.01, 0.01, 0.0, -0.01], dtype=F64))
    initial = initial @ true_transform
    fast = icp.icp(source, target, initial, config, normals)

    class _Fresh(neighbors._Matcher):
        def __call__(self, rows, moved, gate, fn, name):  # forget every certificate
            self.margin[...] = -np.inf
            self.index[...] = -1
            return super().__call__(rows, moved, gate, fn, name)

    original = icp._Matcher
    icp._Matcher = _Fresh  # type: ignore[misc]
    try:
        plain = icp.icp(source, target, initial, config, normals)
    finally:
        icp._Matcher = original  # type: ignore[misc]
    assert int(fast.iterations) == int(plain.iterations) and int(fast.iterations) > 3
    # Same correspondences and normal equations; the distances differ at most in the last
    # bit (recomputed instead of taken from the tree), so the transforms agree to round-off.
    assert torch.allclose(fast.transform, plain.transform, atol=1e-12)
    assert torch.equal(fast.fitness, plain.fitness)


def test_closed_form_normals_equal_eigh(generator) -> None:
    points = _wavy(3000, generator).numpy()
    _, index = cKDTree(points).query(points, k=9)
    normals = neighbors._smallest_eigenvectors(points, index)
    local = points[index] - points[index].mean(1, keepdims=True)
    _, vectors = np.linalg.eigh(local.transpose(0, 2, 1) @ local)
    reference = vectors[..., 0]
    assert np.allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-14)
    # The gap between the two smallest eigenvalues is far from zero on this sheet, so the
    # eigenvector is determined to ~1e-15 (up to its sign) by either method.
    assert np.allclose(np.abs((normals * reference).sum(-1)), 1.0, atol=1e-12)


@pytest.mark.parametrize("shape", ["line", "point", "isotropic"])
def test_closed_form_normals_of_degenerate_neighbourhoods(shape) -> None:
    """Neighbourhoods whose normal is ill-defined still give a unit vector orthogonal to the
    directions they span (the eigh fallback)."""
    if shape == "line":
        points = np.zeros((8, 3))
        points[:, 0] = np.linspace(0.0, 1.0, 8)  # along x: any normal ⊥ x
    elif shape == "point":
        points = np.full((8, 3), 0.5)
    else:
        points = np.concatenate((np.eye(3), -np.eye(3)))  # scatter matrix 2 I
    index = np.tile(np.arange(len(points)), (len(points), 1))
    normals = neighbors._smallest_eigenvectors(points, index)
    assert np.isfinite(normals).all()
    assert np.allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-14)
    if shape == "line":
        assert np.allclose(normals[:, 0], 0.0, atol=1e-14)


def test_normals_keep_float32(generator) -> None:
    points = _wavy(400, generator)
    single = icp.estimate_normals(points.float(), 8)
    double = icp.estimate_normals(points, 8)
    assert single.dtype == torch.float32
    # float32 coordinates (rounded by 6e-8 relative) move a normal of this sheet by ~1e-6.
    assert torch.allclose(
        (single.double() * double).sum(-1).abs(), torch.ones(400, dtype=F64), atol=1e-5
    )
