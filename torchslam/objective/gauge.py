"""Gauge and well-posedness of an objective: what the observations and terms determine.

When a :class:`torchslam.PointMapProblem` is built, ill-posed parts are held fixed, never
dropped silently (:func:`hold_ill_posed_fixed`):

- a point with fewer than 3 residual entries (no point observation, or a single 2-entry
  reprojection) is held fixed;
- a free pose with fewer than 3 observed points or fewer than 6 residual entries on them
  is held fixed, unless full-rank pose terms (≥ 6 residual entries: relative poses, priors)
  tie it to an anchor (a fixed pose, a well-observed pose, a prior); a group of such poses
  tied only to each other has a free gauge, and its first pose is held fixed.

Point observations and the instances of terms that touch points count alike (a term's
instance observes each of its poses and its point). Each held variable gets a
``UserWarning`` naming the problem and the index, also listed in ``diagnostics``.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from torch import Tensor

from torchslam.objective.terms import Term

__all__ = ["hold_ill_posed_fixed", "point_term_counts", "term_links", "unanchored_gauges"]


def term_links(terms: tuple[Term, ...], B: int) -> list[tuple]:
    """The terms' full-rank links per problem: [(edges (L, 2), anchors (A,)) for each b].

    An instance links its poses when its residual has ≥ 6 entries and it is valid with a
    positive weight: a unary one (a prior) anchors its pose, one of arity ≥ 2 joins its poses
    (a relative pose fixes one pose given the other). A term that touches a point links its
    poses only through the point, which is a variable too: it neither anchors nor joins them
    here, it observes them (:func:`point_term_counts`) as a point observation does.
    """
    edges = [[] for _ in range(B)]
    anchors = [[] for _ in range(B)]
    for term in terms:
        if term.num_instances == 0 or term.has_point:
            continue
        if term.residual_dim < 6:  # set by Term.bind
            continue
        active = term.valid
        if term.weight is not None:
            active = active & (term.weight.detach() > 0)
        index = term.pose_index.cpu()
        active = active.cpu()
        for b in range(B):
            rows = index[b][active[b]]
            if term.arity == 1:
                anchors[b].append(rows[:, 0])
            else:
                for a in range(1, term.arity):
                    edges[b].append(rows[:, [0, a]])
    empty = torch.zeros(0, dtype=torch.long)
    return [
        (
            torch.cat(edges[b]) if edges[b] else empty.reshape(0, 2),
            torch.cat(anchors[b]) if anchors[b] else empty,
        )
        for b in range(B)
    ]


def point_term_counts(terms: tuple[Term, ...], B: int, m: int, n: int) -> tuple | None:
    """What the terms that touch points add to the observation counts, or None without such
    terms: (instances per pose (B, m), residual entries per pose (B, m), residual entries per
    point (B, n)), long, over the valid instances. An instance counts for each of its poses,
    as a point observation (3 entries) does for its pose."""
    point_terms = [t for t in terms if t.has_point and t.num_instances > 0]
    if not point_terms:
        return None
    device = point_terms[0].valid.device
    links = torch.zeros(B * m, dtype=torch.long, device=device)
    pose_entries = torch.zeros(B * m, dtype=torch.long, device=device)
    point_entries = torch.zeros(B * n, dtype=torch.long, device=device)
    batch = torch.arange(B, device=device)[:, None]
    for term in point_terms:
        ones = term.valid.long()
        d = term.residual_dim  # set by Term.bind
        for a in range(term.arity):
            slots = (batch * m + term.pose_index[..., a]).reshape(-1)
            links.index_add_(0, slots, ones.reshape(-1))
            pose_entries.index_add_(0, slots, d * ones.reshape(-1))
        point_entries.index_add_(
            0, (batch * n + term.point_index).reshape(-1), d * ones.reshape(-1)
        )
    return links.reshape(B, m), pose_entries.reshape(B, m), point_entries.reshape(B, n)


def unanchored_gauges(
    links: list[tuple], weak: Tensor, fixed: Tensor, m: int
) -> tuple[Tensor, list[tuple[int, int, list[int]]]]:
    """Which weak poses (< 3 observations) the terms make well posed, and which to hold.

    Per problem, the components of the poses joined by full-rank term links: a component
    with an anchor (a fixed pose, a pose with ≥ 3 observations, a prior) determines all its
    poses; a component without one has a free gauge, fixed by holding its first weak pose.

    Returns:
        (still_weak (B, m) bool: weak poses no term constrains, held: [(b, pose, group)] the
        gauges held fixed with their component's weak poses).
    """
    import scipy.sparse.csgraph  # lazily: import torchslam stays cheap

    still_weak = weak.clone()
    held = []
    for b, (edges, anchors) in enumerate(links):
        if edges.numel() == 0 and anchors.numel() == 0:
            continue
        e = edges.numpy()
        graph = scipy.sparse.coo_matrix((np.ones(e.shape[0]), (e[:, 0], e[:, 1])), shape=(m, m))
        _, label = scipy.sparse.csgraph.connected_components(graph, directed=False)
        label = torch.from_numpy(label).to(weak.device)
        is_anchor = (~weak[b]) | fixed[b]
        is_anchor[anchors.to(weak.device)] = True
        anchored = torch.zeros(m, dtype=torch.bool, device=weak.device)
        anchored.index_put_((label,), is_anchor, accumulate=True)
        size = torch.bincount(label, minlength=m)
        linked = (size[label] > 1) | is_anchor
        ok = anchored[label] & linked
        for component in torch.unique(label[weak[b] & linked & ~anchored[label]]).tolist():
            members = ((label == component) & weak[b]).nonzero().squeeze(1).tolist()
            held.append((b, members[0], members))
            ok[label == component] = True
        still_weak[b] = weak[b] & ~ok
    return still_weak, held


def hold_ill_posed_fixed(
    fn: str,
    valid: Tensor,
    pose_index: Tensor,
    point_index: Tensor,
    fixed_poses: Tensor,
    fixed_points: Tensor,
    diagnostics: list[str],
    term_links: list[tuple] | None = None,
    point_terms: tuple[Tensor, Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    """Hold fixed what the observations cannot determine (module doc), with diagnostics.

    A pose needs ≥ 3 observed points and ≥ 6 residual entries on them (3 point observations,
    or 3 reprojections of 2 entries each); a point needs ≥ 3 residual entries (one point
    observation, or two reprojections). ``point_terms`` (:func:`point_term_counts`) adds the
    terms that touch points to the point observations' counts.
    """
    B, m = fixed_poses.shape
    n = fixed_points.shape[1]
    ones = valid.to(torch.long)
    batch_offset = torch.arange(B, device=valid.device)[:, None]
    pose_counts = torch.zeros(B * m, dtype=torch.long, device=valid.device)
    pose_counts.index_add_(
        0, (batch_offset * m + pose_index.clamp(0, m - 1)).reshape(-1), ones.reshape(-1)
    )
    point_counts = torch.zeros(B * n, dtype=torch.long, device=valid.device)
    point_counts.index_add_(
        0, (batch_offset * n + point_index.clamp(0, n - 1)).reshape(-1), ones.reshape(-1)
    )
    pose_counts = pose_counts.reshape(B, m)
    pose_entries, point_entries = 3 * pose_counts, 3 * point_counts.reshape(B, n)
    if point_terms is not None:
        pose_counts = pose_counts + point_terms[0]
        pose_entries = pose_entries + point_terms[1]
        point_entries = point_entries + point_terms[2]
    weak_poses = ((pose_counts < 3) | (pose_entries < 6)) & ~fixed_poses
    gauges = []
    if term_links is not None:
        weak_poses, gauges = unanchored_gauges(term_links, weak_poses, fixed_poses, m)
        for b, i, group in gauges:
            weak_poses[b, i] = True
            diagnostics.append(
                f"problem {b}: poses {group} are tied by relative-pose terms to each other but "
                f"not to a fixed or well-observed pose (a free gauge); pose {i} held fixed at "
                "its initial value"
            )
    unseen_points = (point_entries < 3) & ~fixed_points
    held = {(b, i) for b, i, _ in gauges}
    for b, i in weak_poses.nonzero().tolist():
        if (b, i) in held:
            continue
        count = int(pose_counts[b, i])
        what = f"{count} observation(s) (< 3)"
        if count >= 3:
            what = f"{int(pose_entries[b, i])} residual entries on points (< 6)"
        diagnostics.append(f"problem {b}: pose {i} has {what}; held fixed at its initial value")
    for b, j in unseen_points.nonzero().tolist():
        entries = int(point_entries[b, j])
        what = "no observation" if entries == 0 else f"{entries} residual entries (< 3)"
        diagnostics.append(f"problem {b}: point {j} has {what}; held fixed")
    if diagnostics:
        shown = "; ".join(diagnostics[:5]) + (
            f"; … ({len(diagnostics)} in all)" if len(diagnostics) > 5 else ""
        )
        warnings.warn(f"{fn}: {shown}. See problem.diagnostics.", UserWarning, stacklevel=3)
    return fixed_poses | weak_poses, fixed_points | unseen_points
