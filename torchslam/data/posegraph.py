"""Seeded synthetic 3D pose graphs: a grid ("cube") or a torus, with loop closures, Gaussian
measurement noise and optionally planted wrong loop closures.

Like SE-Sync's synthetic benchmarks (cube, torus): a trajectory through the scene, odometry
edges between consecutive poses, loop closures between poses that revisit a place, each
measurement Z_ij = (T_i⁻¹ T_j)·Exp(ξ), ξ ~ N(0, diag(σ_R² I, σ_t² I)) in (ω, v) order, with the
matching information diag(σ_R⁻² I, σ_t⁻² I). The graph's vertex values are the odometry chain
composed from the noisy odometry (what a file would hold), so a solve from them starts from
the dead-reckoning drift.

- ``"grid"``: the s × s × s grid points (spacing 1) visited by a serpentine (boustrophedon)
  path, random orientations; loop closures join a pose to each earlier pose at a neighbouring
  grid point (6-neighbourhood, not its predecessor) with probability ``loop_probability``.
- ``"torus"``: a helix wound on a torus (major radius R, minor radius r): pose k at minor
  angle 2πk/w and major angle 2πk/N (w poses per winding), the body x axis along the helix;
  loop closures join k and k + w (the next winding, side by side) with probability
  ``loop_probability``.

Wrong loop closures (``wrong_loop_closures`` > 0) join random pairs of poses at least N/4
apart along the trajectory with a measurement drawn at random (rotation angle uniform in
[π/2, π], translation of norm 5 in a random direction) and the loop closures' information;
their edge indices are returned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from torchslam.lie import se3
from torchslam.posegraph.graph import PoseGraph

__all__ = ["SyntheticPoseGraph", "make_pose_graph"]


@dataclass(frozen=True)
class SyntheticPoseGraph:
    """A synthetic pose graph and its ground truth."""

    # The graph: vertex values = the noisy odometry chain, vertex 0 = the true pose 0.
    graph: PoseGraph
    # True poses T_i (body → world), (N, 4, 4).
    truth: Tensor
    # Indices (W,) of the planted wrong loop-closure edges in graph.edges (empty if none).
    wrong_edges: Tensor


def _check(fn: str, name: str, value: object, low: float, integer: bool = False) -> None:
    kind = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind):
        raise TypeError(
            f"{fn}: argument '{name}' must be {'an int' if integer else 'a number'}, "
            f"got {type(value).__name__}"
        )
    if not (math.isfinite(value) and value >= low):
        raise ValueError(f"{fn}: argument '{name}' must be finite and ≥ {low}, got {value!r}")


def _grid(num_poses: int, rng: np.random.Generator, p: float):
    side = max(2, math.ceil(num_poses ** (1 / 3)))
    points = []
    for z in range(side):
        ys = range(side) if z % 2 == 0 else range(side - 1, -1, -1)
        for row, y in enumerate(ys):
            xs = range(side) if (row + z * side) % 2 == 0 else range(side - 1, -1, -1)
            points.extend((x, y, z) for x in xs)
    points = np.array(points[:num_poses], dtype=float)
    index = {tuple(q): k for k, q in enumerate(points.astype(int).tolist())}
    loops = []
    for k, q in enumerate(points.astype(int).tolist()):
        for axis in range(3):
            for step in (-1, 1):
                other = list(q)
                other[axis] += step
                m = index.get(tuple(other))
                if m is not None and m < k - 1 and rng.random() < p:
                    loops.append((m, k))
    q = rng.standard_normal((len(points), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.stack(
        (
            np.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)), -1),
            np.stack((2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)), -1),
            np.stack((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), -1),
        ),
        axis=1,
    )
    return points, R, loops


def _torus(num_poses: int, rng: np.random.Generator, p: float, per_winding: int = 25):
    k = np.arange(num_poses)
    major, minor = 20.0, 5.0
    theta = 2 * np.pi * k / per_winding
    phi = 2 * np.pi * k / num_poses

    def position(theta, phi):
        return np.stack(
            (
                (major + minor * np.cos(theta)) * np.cos(phi),
                (major + minor * np.cos(theta)) * np.sin(phi),
                minor * np.sin(theta),
            ),
            axis=-1,
        )

    points = position(theta, phi)
    # Body x axis along the helix, z axis towards the torus' core circle's outward normal.
    h = 1e-3
    tangent = position(theta + 2 * np.pi * h / per_winding, phi + 2 * np.pi * h / num_poses)
    tangent = tangent - points
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    core = np.stack((major * np.cos(phi), major * np.sin(phi), 0 * phi), axis=-1)
    normal = points - core
    normal -= (normal * tangent).sum(1, keepdims=True) * tangent
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    R = np.stack((tangent, np.cross(normal, tangent), normal), axis=-1)
    loops = [(m, m + per_winding) for m in range(num_poses - per_winding) if rng.random() < p]
    return points, R, loops


def make_pose_graph(
    kind: Literal["grid", "torus"] = "torus",
    num_poses: int = 2000,
    *,
    rotation_noise: float = 0.05,
    translation_noise: float = 0.1,
    loop_probability: float = 0.5,
    wrong_loop_closures: int = 0,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
) -> SyntheticPoseGraph:
    """A seeded synthetic 3D pose graph (module docstring).

    Args:
        kind: ``"grid"`` or ``"torus"``.
        num_poses: N ≥ 2 (``"torus"``: N > 25, one winding is 25 poses).
        rotation_noise: σ_R of the measurements' rotation noise (radians), > 0.
        translation_noise: σ_t of their translation noise (scene units), > 0.
        loop_probability: probability of each candidate loop closure, in [0, 1].
        wrong_loop_closures: number W ≥ 0 of planted wrong loop closures.
        seed: seed of the NumPy generator (the same seed gives the same graph).
        dtype: floating dtype of the graph.

    Returns:
        A :class:`SyntheticPoseGraph` (graph, truth, wrong_edges).
    """
    fn = "make_pose_graph"
    if kind not in ("grid", "torus"):
        raise ValueError(f"{fn}: argument 'kind' must be 'grid' or 'torus', got {kind!r}")
    _check(fn, "num_poses", num_poses, 26 if kind == "torus" else 2, integer=True)
    _check(fn, "rotation_noise", rotation_noise, 0.0)
    _check(fn, "translation_noise", translation_noise, 0.0)
    if rotation_noise <= 0 or translation_noise <= 0:
        raise ValueError(f"{fn}: the noise levels must be > 0 (they set the information)")
    _check(fn, "loop_probability", loop_probability, 0.0)
    if loop_probability > 1:
        raise ValueError(f"{fn}: argument 'loop_probability' must be ≤ 1, got {loop_probability}")
    _check(fn, "wrong_loop_closures", wrong_loop_closures, 0, integer=True)
    _check(fn, "seed", seed, 0, integer=True)
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"{fn}: argument 'dtype' must be a floating torch.dtype, got {dtype!r}")
    rng = np.random.default_rng(seed)
    build = _grid if kind == "grid" else _torus
    points, R, loops = build(num_poses, rng, loop_probability)
    n = points.shape[0]
    truth = np.zeros((n, 4, 4))
    truth[:, :3, :3], truth[:, :3, 3], truth[:, 3, 3] = R, points, 1.0
    pairs = [(k, k + 1) for k in range(n - 1)] + loops
    wrong = []
    far = max(1, n // 4)
    while len(wrong) < wrong_loop_closures:
        a, b = sorted(rng.integers(0, n, 2).tolist())
        if b - a >= far:
            wrong.append((a, b))
    edges = np.array(pairs + wrong, dtype=np.int64)
    T = torch.from_numpy(truth)
    Z = se3.inverse(T[edges[:, 0]]) @ T[edges[:, 1]]
    E = edges.shape[0]
    sigma = torch.tensor([rotation_noise] * 3 + [translation_noise] * 3, dtype=torch.float64)
    Z = Z @ se3.exp(torch.from_numpy(rng.standard_normal((E, 6))) * sigma)
    W = len(wrong)
    if W:
        axis = rng.standard_normal((W, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        angle = rng.uniform(np.pi / 2, np.pi, W)[:, None]
        direction = rng.standard_normal((W, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        xi = torch.from_numpy(np.concatenate((axis * angle, 5.0 * direction), axis=1))
        Z[E - W :] = se3.exp(xi)
    information = torch.diag(sigma**-2).expand(E, 6, 6).clone()
    # Vertex values: the noisy odometry chain from the true pose 0.
    chain = [T[0]]
    for k in range(n - 1):
        chain.append(chain[-1] @ Z[k])
    graph = PoseGraph(
        ids=torch.arange(n),
        poses=torch.stack(chain).to(dtype),
        edges=torch.from_numpy(edges),
        measurements=Z.to(dtype),
        information=information.to(dtype),
    )
    wrong_edges = torch.arange(E - W, E, dtype=torch.int64)
    return SyntheticPoseGraph(graph=graph, truth=T.to(dtype), wrong_edges=wrong_edges)
