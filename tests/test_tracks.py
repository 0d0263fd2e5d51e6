"""Point tracks from mutual nearest neighbours across scans."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchslam.lie import se3
from torchslam.registration import tracks

F64 = torch.float64


def scene(generator, m=4, n=400, noise=1e-4, seen=0.6):
    """World points on a jittered grid (spacing 0.1) seen by m scans with random poses.

    Returns clouds (scan frames, shuffled), poses T_0i, and per scan the world id of each
    cloud point.
    """
    grid = torch.stack(
        torch.meshgrid(*(torch.arange(8, dtype=F64),) * 3, indexing="ij"), dim=-1
    ).reshape(-1, 3)
    world = grid[torch.randperm(len(grid), generator=generator)[:n]] * 0.1
    world = world + 0.01 * torch.rand(world.shape, generator=generator, dtype=F64)
    poses = se3.exp(torch.randn(m, 6, generator=generator, dtype=F64))
    clouds, ids = [], []
    for i in range(m):
        visible = torch.nonzero(torch.rand(n, generator=generator) < seen).squeeze(-1)
        visible = visible[torch.randperm(len(visible), generator=generator)]
        local = se3.act(se3.inverse(poses[i]), world[visible])
        clouds.append(local + noise * torch.randn(local.shape, generator=generator, dtype=F64))
        ids.append(visible)
    return clouds, poses, ids, world


def test_tracks_recover_the_true_association(generator):
    clouds, poses, ids, world = scene(generator)
    result = tracks.build_tracks(clouds, poses, radius=0.03)
    assert result.num_conflicts == 0 and result.num_poses == 4
    edges = zip(result.pose_index.tolist(), result.source_index.tolist(), strict=True)
    true_id = torch.stack([ids[i][a] for i, a in edges])
    # Every track is one world point, and every world point seen twice or more is one track.
    for j in range(result.num_points):
        assert len(set(true_id[result.point_index == j].tolist())) == 1
    seen_in = torch.zeros(len(world), dtype=torch.int64)
    for visible in ids:
        seen_in[visible] += 1
    expected = set(torch.nonzero(seen_in >= 2).squeeze(-1).tolist())
    got = set(true_id.tolist())
    assert got == expected
    assert result.num_points == len(expected)
    first_edge = torch.searchsorted(result.point_index, torch.arange(result.num_points))
    track_id = true_id[first_edge]
    assert torch.equal(result.views_per_point(), seen_in[track_id])
    # Observations are the cloud points themselves; the initial points average them (0.2).
    for e in range(0, result.num_edges, 37):
        i, a = int(result.pose_index[e]), int(result.source_index[e])
        assert torch.equal(result.observations[e], clouds[i][a])
    assert torch.allclose(result.points, world[track_id], atol=1e-3)


def test_edges_are_sorted_and_padded_form_matches(generator):
    clouds, poses, _, _ = scene(generator, m=3, n=200)
    result = tracks.build_tracks(clouds, poses, radius=0.03)
    key = result.point_index * result.num_poses + result.pose_index
    assert torch.all(key[1:] > key[:-1])  # sorted by point, then pose; one edge per (j, i)
    assert result.point_index.dtype == result.pose_index.dtype == torch.int64
    assert int(result.point_index.max()) == result.num_points - 1
    pose, source, observations, mask = result.padded()
    assert pose.shape == (result.num_points, int(result.views_per_point().max()))
    assert torch.equal(mask.sum(-1), result.views_per_point())
    assert torch.equal(pose[mask], result.pose_index)
    assert torch.equal(source[mask], result.source_index)
    assert torch.equal(observations[mask], result.observations)
    assert (pose[~mask] == -1).all() and (observations[~mask] == 0).all()
    # The residual of the joint problem vanishes up to noise at the true poses.
    residual = result.observations - se3.act(
        se3.inverse(poses[result.pose_index]), result.points[result.point_index]
    )
    assert float(residual.norm(dim=-1).max()) < 1e-3


def test_min_views_and_pairs(generator):
    clouds, poses, _, _ = scene(generator, m=4, n=300, seen=0.8)
    every = tracks.build_tracks(clouds, poses, radius=0.03)
    three = tracks.build_tracks(clouds, poses, radius=0.03, min_views=3)
    assert int(three.views_per_point().min()) >= 3
    assert three.num_points < every.num_points
    chain = tracks.build_tracks(clouds, poses, radius=0.03, pairs=[(0, 1), (1, 2), (2, 3)])
    # Points seen only in scans 0 and 2 are not linked when (0, 2) is not matched.
    assert chain.num_points <= every.num_points
    assert chain.num_edges < every.num_edges


def test_conflicts_are_refused_greedily_or_dropped():
    # Scan 0 has two points (a, a') 0.8 apart; scan 1 matches a, scan 2 matches a', and
    # scans 1 and 2 match each other: {a, b, c, a'} would hold scan 0 twice.
    eye = torch.eye(4, dtype=F64).expand(3, 4, 4)
    a, a2 = [0.0, 0.0, 0.0], [0.8, 0.0, 0.0]
    clouds = [
        torch.tensor([a, a2, [5.0, 5.0, 5.0]], dtype=F64),
        torch.tensor([[0.1, 0.0, 0.0], [5.0, 5.0, 5.1]], dtype=F64),
        torch.tensor([[0.65, 0.0, 0.0], [5.0, 5.1, 5.0]], dtype=F64),
    ]
    pairs = [(0, 1), (1, 2), (0, 2)]
    dropped = tracks.build_tracks(clouds, eye, radius=0.6, pairs=pairs, conflicts="drop")
    assert dropped.num_conflicts == 1
    assert dropped.num_points == 1  # only the far-away, consistent point remains
    assert dropped.source_index.tolist() == [2, 1, 1]
    # Greedy: a–b (0.1) and a'–c (0.15) merge first; b–c (0.55) would repeat scan 0.
    greedy = tracks.build_tracks(clouds, eye, radius=0.6, pairs=pairs)
    assert greedy.num_conflicts == 1 and greedy.num_points == 3
    views = []
    for j in range(3):
        on_track = greedy.point_index == j
        pose, source = greedy.pose_index[on_track], greedy.source_index[on_track]
        views.append(sorted(zip(pose.tolist(), source.tolist(), strict=True)))
    assert sorted(views) == [[(0, 0), (1, 0)], [(0, 1), (2, 0)], [(0, 2), (1, 1), (2, 1)]]


def test_mutual_nearest_neighbors():
    first = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]], dtype=F64)
    second = torch.tensor([[0.1, 0, 0], [0.2, 0, 0], [2.05, 0, 0], [9.0, 0, 0]], dtype=F64)
    pairs = tracks.mutual_nearest_neighbors(first, second, radius=0.5)
    # 0 ↔ 0 (0.1 closer than 0.2), 1 has no partner within 0.5, 2 ↔ 2; second[1] is left.
    assert pairs.tolist() == [[0, 0], [2, 2]]
    assert tracks.mutual_nearest_neighbors(first, second, radius=0.07).tolist() == [[2, 2]]


def test_input_validation(generator):
    clouds, poses, _, _ = scene(generator, m=2, n=50)
    with pytest.raises(
        ValueError, match=r"build_tracks: argument 'poses' must have shape \(2, 4, 4\)"
    ):
        tracks.build_tracks(clouds, poses[:1], 0.1)
    with pytest.raises(ValueError, match="at least 2 clouds"):
        tracks.build_tracks(clouds[:1], poses[:1], 0.1)
    with pytest.raises(ValueError, match=r"'radius' must be .*> 0"):
        tracks.build_tracks(clouds, poses, 0.0)
    with pytest.raises(ValueError, match="invalid scan pair"):
        tracks.build_tracks(clouds, poses, 0.1, pairs=[(0, 0)])
    with pytest.raises(TypeError, match="float32"):
        tracks.build_tracks([clouds[0], clouds[1].float()], poses, 0.1)


def test_greedy_components_label_every_point_by_its_root():
    """The labels are the union-find roots: a chain merged against its order (deep trees
    before path compression) ends in one component labelled by one of its points, a
    refused merge (two points of one scan) keeps two components apart."""
    from torchslam.registration.tracks import _greedy_components

    total = 64
    scan = np.arange(total)  # every point its own scan: no merge is refused
    row, col = np.arange(total - 1, 0, -1), np.arange(total - 2, -1, -1)
    label, refused = _greedy_components(row, col, scan, total)
    assert refused == 0 and len(set(label.tolist())) == 1 and 0 <= label[0] < total
    # points 0, 1 in scan 0 and 2, 3 in scan 1: 0–2 and 1–3 merge, 0–1 would repeat a scan
    label, refused = _greedy_components(
        np.array([0, 1, 0]), np.array([2, 3, 1]), np.array([0, 0, 1, 1]), 4
    )
    assert refused == 1
    assert label[0] == label[2] and label[1] == label[3] and label[0] != label[1]
    assert label[0] in (0, 2) and label[1] in (1, 3)
