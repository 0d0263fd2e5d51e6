"""Closed-form rigid alignment of corresponding point sets (weighted Kabsch/Umeyama, no scale).

Given correspondences ``source_k ↔ target_k`` with weights ``w_k ≥ 0``, the rigid transform
T = [[R, t], [0, 1]] minimizing

    Σ_k w_k ‖target_k − (R source_k + t)‖²

is, with weighted centroids μ_s, μ_t and the weighted cross-covariance
H = Σ_k w_k (source_k − μ_s)(target_k − μ_t)ᵀ = U S Vᵀ (SVD),

    R = V diag(1, 1, d) Uᵀ,   d = sign det(V Uᵀ),   t = μ_t − R μ_s

(Kabsch 1976; Umeyama 1991 without the scale). The factor d replaces a reflection by the
best proper rotation (det R = +1). This is the pairwise alignment of the seed's section 0: the
relative pose T̂_{i+1,i} of successive frames from their shared observations.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchslam import _checks

__all__ = ["weighted_kabsch"]

# A cross-covariance whose second singular value is below this multiple of machine epsilon
# times the first has rank ≤ 1 (collinear or coincident points): the rotation is not unique.
_RANK_TOLERANCE = 1e3


def _rigid_from_covariance(
    H: Tensor, mu_source: Tensor, mu_target: Tensor
) -> tuple[Tensor, Tensor]:
    """Best rigid transform from a centred cross-covariance (no checks).

    Args:
        H: Σ w (s − μ_s)(t − μ_t)ᵀ, shape (..., 3, 3).
        mu_source: weighted source centroids μ_s, shape (..., 3).
        mu_target: weighted target centroids μ_t, shape (..., 3).

    Returns:
        (T, S): transforms (..., 4, 4) mapping source to target and the singular values of
        ``H`` (..., 3), descending (for degeneracy checks).
    """
    U, S, Vh = torch.linalg.svd(H)
    V = Vh.transpose(-1, -2)
    # d = det(V Uᵀ) = ±1; piecewise constant, so it carries no gradient.
    d = torch.linalg.det(V.detach() @ U.detach().transpose(-1, -2))
    one = torch.ones_like(d)
    D = torch.stack((one, one, torch.where(d < 0, -one, one)), dim=-1)
    R = (V * D[..., None, :]) @ U.transpose(-1, -2)
    t = mu_target - (R @ mu_source[..., None]).squeeze(-1)
    top = torch.cat((R, t[..., None]), dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom = torch.cat((bottom[..., :3], torch.ones_like(bottom[..., 3:])), dim=-1)
    return torch.cat((top, bottom), dim=-2), S


def _degenerate_spectrum(S: Tensor) -> Tensor:
    """True where singular values ``S`` (..., 3) of a cross-covariance leave R undetermined.

    The rotation is unique iff rank H ≥ 2 (three or more non-collinear points); the test is
    S[1] ≤ 1e3 · eps · S[0] (which also catches S = 0).
    """
    tol = _RANK_TOLERANCE * torch.finfo(S.dtype).eps
    return S[..., 1] <= tol * S[..., 0]


def weighted_kabsch(
    source: Tensor,
    target: Tensor,
    weights: Tensor | None = None,
    mask: Tensor | None = None,
) -> Tensor:
    """Rigid transform minimizing Σ_k w_k ‖target_k − (R source_k + t)‖² (weighted Kabsch).

    Closed form via the SVD of the weighted cross-covariance with a reflection fix, so the
    result always has det R = +1 (module docstring). Batched over leading dims;
    differentiable w.r.t. ``source``, ``target`` and ``weights`` wherever the singular values
    of the cross-covariance are distinct (generic, non-degenerate input).

    The arithmetic is scale-free (the rotation does not change when the weights or either
    centred cloud are multiplied by a positive constant), so every problem is normalized by
    its largest weight and coordinate before the cross-covariance is formed: huge (1e300) and
    tiny (1e-300) finite coordinates and weights neither overflow nor underflow.

    Args:
        source: points in the source frame, shape (..., N, 3); a torch tensor or a numpy
            array (float32/float64, converted to a tensor on ``target``'s device).
        target: corresponding points in the target frame, shape (..., N, 3), same dtype.
        weights: non-negative weights w_k, shape broadcastable to (..., N); ``None`` means 1.
        mask: bool, shape broadcastable to (..., N); ``False`` entries (padding) are ignored
            entirely (their coordinates and weights may hold anything, NaN included).
            ``None`` keeps all.

    Returns:
        T = [[R, t], [0, 1]] mapping source coordinates to target coordinates,
        target ≈ R source + t, shape (..., 4, 4), same dtype and device as ``source``.

    Raises:
        ValueError: on shape mismatches; and, when value checks are active (eager mode,
            validation on), if a problem has fewer than 3 points with positive weight, if a
            kept weight is negative or not finite, if a kept coordinate is not finite, or if
            the kept points are degenerate (collinear or coincident: the rotation is not
            unique).
        TypeError: on non-float or mixed dtypes, or a non-bool ``mask``.
    """
    fn = "weighted_kabsch"
    like = _checks.first_tensor(source, target)
    source = _checks.as_points(fn, "source", source, like=like, cloud=False, finite=False)
    target = _checks.as_points(fn, "target", target, like=like, cloud=False, finite=False)
    for name, x in (("source", source), ("target", target)):
        if x.dim() < 2:
            raise ValueError(
                f"{fn}: argument '{name}' must have shape (..., N, 3), got {tuple(x.shape)}"
            )
    _checks.check_same_kind(fn, source=source, target=target)
    if source.shape != target.shape:
        raise ValueError(
            f"{fn}: 'source' and 'target' must have the same shape (..., N, 3), got "
            f"{tuple(source.shape)} and {tuple(target.shape)}"
        )
    weights = _checks.from_numpy(weights, source)  # type: ignore[assignment]
    mask = _checks.from_numpy(mask, source)  # type: ignore[assignment]
    points_shape = source.shape[:-1]
    keep = torch.ones(points_shape, dtype=torch.bool, device=source.device)
    if mask is not None:
        _checks.check_tensor(fn, "mask", mask, (), floating=False)
        if mask.dtype != torch.bool:
            raise TypeError(f"{fn}: argument 'mask' must be a bool tensor, got {mask.dtype}")
        _check_broadcasts_to(fn, "mask", mask, points_shape)
        keep = keep & mask
    if weights is not None:
        _checks.check_tensor(fn, "weights", weights, ())
        _checks.check_same_kind(fn, source=source, weights=weights)
        _check_broadcasts_to(fn, "weights", weights, points_shape)
        w = torch.where(keep, weights, torch.zeros_like(weights))
    else:
        w = keep.to(source.dtype)
    w = w.expand(points_shape)

    if _checks.value_checks_active():
        _check_values(fn, source, target, weights, keep, w)

    T, S = _weighted_kabsch(source, target, w, keep)

    if _checks.value_checks_active():
        bad = _degenerate_spectrum(S.detach())
        if bool(bad.any()):
            idx = tuple(int(i) for i in bad.nonzero()[0].tolist())
            raise ValueError(
                f"{fn}: the weighted points of problem {idx} are degenerate (collinear or "
                f"coincident; singular values of the cross-covariance {S[idx].tolist()}), so "
                "the rotation is not unique"
            )
        if not bool(torch.isfinite(T.detach()).all()):
            raise ValueError(
                f"{fn}: the translation t = μ_target − R μ_source overflows "
                f"{source.dtype}: the kept coordinates of 'source' and 'target' are too large "
                "in magnitude"
            )
    return T


def _check_broadcasts_to(fn: str, name: str, x: Tensor, shape: torch.Size) -> None:
    try:
        ok = _checks.broadcast_shapes(x.shape, shape) == shape
    except RuntimeError:
        ok = False
    if not ok:
        raise ValueError(
            f"{fn}: argument '{name}' must have a shape broadcastable to {tuple(shape)} "
            f"(the leading dims of 'source'), got {tuple(x.shape)}"
        )


def _check_values(
    fn: str, source: Tensor, target: Tensor, weights: Tensor | None, keep: Tensor, w: Tensor
) -> None:
    for name, x in (("source", source), ("target", target)):
        kept = torch.where(keep[..., None], x.detach(), torch.zeros_like(x.detach()))
        _checks.check_finite(fn, name, kept)
    if weights is not None:
        # Only the kept entries count: ``w`` already holds 0 where ``mask`` is False.
        _checks.check_finite(fn, "weights", w)
        negative = w.detach() < 0
        if bool(negative.any()):
            idx = tuple(int(i) for i in negative.nonzero()[0].tolist())
            raise ValueError(
                f"{fn}: argument 'weights' must be >= 0, got {float(w[idx]):g} at {idx}"
            )
    count = (w.detach() > 0).sum(-1)
    few = count < 3
    if bool(few.any()):
        idx = tuple(int(i) for i in few.nonzero()[0].tolist())
        raise ValueError(
            f"{fn}: problem {idx} has {int(count[idx])} point(s) with positive weight "
            "(after 'mask' and 'weights'); a rigid alignment needs at least 3 non-collinear "
            "points"
        )


def _weighted_kabsch(
    source: Tensor, target: Tensor, w: Tensor, keep: Tensor
) -> tuple[Tensor, Tensor]:
    """Unchecked core of :func:`weighted_kabsch`; returns (T, singular values)."""
    zeros = torch.zeros_like(source)
    s = torch.where(keep[..., None], source, zeros)
    t = torch.where(keep[..., None], target, zeros)
    # Scale-free arithmetic: centroids are invariant to a common factor of the weights, and R
    # to positive factors of either centred cloud (H scales, its singular vectors do not). The
    # factors are detached constants, so values and gradients are those of the plain formula.
    w = w / _largest(w, 1)
    scale_s, scale_t = _largest(s, 2), _largest(t, 2)
    s, t = s / scale_s, t / scale_t
    total = w.sum(-1, keepdim=True)
    total = torch.where(total > 0, total, torch.ones_like(total))
    mu_s = (w[..., None] * s).sum(-2) / total
    mu_t = (w[..., None] * t).sum(-2) / total
    s_centred = s - mu_s[..., None, :]
    t_centred = t - mu_t[..., None, :]
    s_centred = s_centred / _largest(s_centred, 2)
    t_centred = t_centred / _largest(t_centred, 2)
    H = (s_centred * w[..., None]).transpose(-1, -2) @ t_centred
    return _rigid_from_covariance(H, mu_s * scale_s[..., 0], mu_t * scale_t[..., 0])


def _largest(x: Tensor, dims: int) -> Tensor:
    """Largest |entry| over the last ``dims`` dims (detached, dims kept), 1 where it is 0."""
    m = x.detach().abs().amax(dim=tuple(range(-dims, 0)), keepdim=True)
    return torch.where(m > 0, m, torch.ones_like(m))
