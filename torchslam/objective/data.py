"""The data of an objective: the ICP-SLAM point observations, their whitening, their checks.

B independent problems, each with m poses T_i0 (world → frame i) and n world points X_j,
observed as X_ij in frame i. Residual r_ij = X_ij − T_i0 X_j (seed eq. 1.1), cost

    F = ½ Σ_e ρ(r_eᵀ Ω_e r_e) + Σ_terms ½ Σ_k ρ_t(s_k)

with per-observation information Ω_e (scalar weight w_e → Ω_e = w_e I; default I), a robust
kernel ρ (default ρ(s) = s) and the terms of :mod:`torchslam.objective.terms`. The ½ follows
Ceres, scipy and GTSAM; the seed's Σ‖r‖² has the same minimizer.

Observations are stored once, as padded edge lists of length E (memory O(E), not O(m·n)):
``pose_index`` (B, E), ``point_index`` (B, E), ``observations`` (B, E, 3) and ``valid``
(B, E) (False for padding), in :class:`PointMapData`, with the functional residuals and
costs the solver evaluates on plain tensors.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchslam import _checks, _inference, jacobians, losses
from torchslam.lie import se3
from torchslam.objective.parameters import ParameterLayout
from torchslam.objective.terms import Term, terms_cost
from torchslam.objective.whitening import whiten, whitening

__all__ = [
    "PointMapData",
    "check_data_values",
    "cost",
    "cost_from_poses",
    "gather_points",
    "gather_poses",
    "jacobian_blocks",
    "mark_checked",
    "per_observation",
    "raw_residuals",
    "raw_residuals_from_poses",
]


@dataclass(frozen=True)
class PointMapData:
    """Everything of a problem that is not a variable: observations, weights, structure.

    Shapes: B problems, E observation slots (padded), m poses, n points.
    """

    # Index of the observing pose of each observation, long (B, E).
    pose_index: Tensor
    # Index of the observed world point of each observation, long (B, E).
    point_index: Tensor
    # Observed points X_ij in their frame, (B, E, 3).
    observations: Tensor
    # False for padding slots, bool (B, E).
    valid: Tensor
    # Scalar weights w_e (B, E), or None when ``information`` is given or weights are 1.
    weights: Tensor | None
    # Information matrices Ω_e (B, E, 3, 3), or None.
    information: Tensor | None
    # Poses held fixed, bool (B, m).
    fixed_poses: Tensor
    # Points held fixed, bool (B, n).
    fixed_points: Tensor
    # Robust kernel ρ applied to s_e = r_eᵀ Ω_e r_e, or None for ρ(s) = s.
    loss: object | None
    # Extra pose terms of the objective (:mod:`torchslam.terms`), bound to batch B.
    terms: tuple[Term, ...] = ()
    # Where the parameter blocks sit in the reduced system (:mod:`.parameters`), or None.
    parameters: ParameterLayout | None = None

    def __post_init__(self) -> None:
        """Check types and shapes (free: no host sync); point padding indices at row 0.

        Padding slots (``valid`` False) may hold anything (NaN, Inf, out-of-range indices).
        Their indices are replaced by 0 here; their observations, weights and information are
        kept as given and replaced on every use (:meth:`masked_observations`, …, by
        ``torch.where``, so no NaN reaches a value or a gradient, and a graph built from
        the given tensors can be differentiated more than once).
        """
        fn = "PointMapData"
        set_ = functools.partial(object.__setattr__, self)
        valid = self.valid
        if not isinstance(valid, Tensor) or valid.dtype != torch.bool or valid.dim() != 2:
            raise TypeError(
                f"{fn}: field 'valid' must be a bool tensor of shape (B, E), got "
                f"{_checks.describe(valid)}"
            )
        B, E = valid.shape
        for name in ("pose_index", "point_index"):
            index = index_tensor(fn, name, getattr(self, name), (B, E), valid.device)
            set_(name, torch.where(valid, index, 0))
        obs = _checks.check_batched(fn, "observations", self.observations, ("B", "E"), (3,), (B, E))
        if obs.device != valid.device:
            raise ValueError(
                f"{fn}: 'observations' is on {obs.device} but 'valid' is on {valid.device}"
            )
        if self.weights is not None and self.information is not None:
            raise ValueError(f"{fn}: give 'weights' or 'information', not both")
        if self.weights is not None:
            w = _checks.check_batched(fn, "weights", self.weights, ("B", "E"), (), (B, E))
            _checks.check_same_kind(fn, observations=obs, weights=w)
        if self.information is not None:
            info = _checks.check_batched(
                fn, "information", self.information, ("B", "E"), (3, 3), (B, E)
            )
            _checks.check_same_kind(fn, observations=obs, information=info)
        for name in ("fixed_poses", "fixed_points"):
            mask = getattr(self, name)
            if not isinstance(mask, Tensor) or mask.dtype != torch.bool or mask.dim() != 2:
                raise TypeError(
                    f"{fn}: field '{name}' must be a bool tensor of shape "
                    f"(B, {'m' if name == 'fixed_poses' else 'n'}), got {_checks.describe(mask)}"
                )
            if mask.shape[0] != B or mask.device != valid.device:
                raise ValueError(
                    f"{fn}: field '{name}' has shape {tuple(mask.shape)} on {mask.device}; "
                    f"expected batch size B = {B} on {valid.device}"
                )
        losses.check_loss(fn, self.loss)
        if not isinstance(self.terms, tuple) or not all(isinstance(t, Term) for t in self.terms):
            raise TypeError(
                f"{fn}: field 'terms' must be a tuple of bound torchslam.Term objects, got "
                f"{_checks.describe(self.terms)}"
            )
        with_points = self.pose_index.shape[-1] > 0 or any(t.has_point for t in self.terms)
        inverted = [t for t in self.terms if t.convention == "frame_to_world"]
        if with_points and inverted:
            raise ValueError(
                f"{fn}: {type(inverted[0]).__name__} reads frame → world poses "
                "(convention='frame_to_world') but the point observations need world → frame "
                "poses T_i0; use the term with convention='world_to_frame' (e.g. "
                "PoseGraph.relative_pose_term() on graph.frame_poses())"
            )

    @property
    def num_poses(self) -> int:
        return self.fixed_poses.shape[-1]

    @property
    def num_slots(self) -> int:
        """Slots of the reduced system: the m poses, then the parameter blocks' slots
        (:mod:`.parameters`); m without parameter blocks."""
        return self.num_poses + (0 if self.parameters is None else self.parameters.num_slots)

    @functools.cached_property
    def fixed_slots(self) -> Tensor:
        """Slots held fixed, bool (B, num_slots): ``fixed_poses``, then the fixed parameter
        blocks' slots (the same tensor as ``fixed_poses`` without parameter blocks)."""
        if self.parameters is None:
            return self.fixed_poses
        with _inference.outside():
            return torch.cat((self.fixed_poses, self.parameters.fixed_slots()), dim=-1)

    @functools.cached_property
    def flat_pose_index(self) -> Tensor:
        """b·m + pose_index, long (B, E): rows of (B·m, …) tensors, for ``index_select``."""
        B = self.pose_index.shape[0]
        with _inference.outside():  # cached: a normal tensor even when made in a solve
            batch = torch.arange(B, device=self.pose_index.device)[:, None]
            return batch * self.num_poses + self.pose_index

    @functools.cached_property
    def flat_point_index(self) -> Tensor:
        """b·n + point_index, long (B, E): rows of (B·n, …) tensors, for ``index_select``."""
        B = self.point_index.shape[0]
        with _inference.outside():  # cached: a normal tensor even when made in a solve
            batch = torch.arange(B, device=self.point_index.device)[:, None]
            return batch * self.num_points + self.point_index

    @property
    def num_points(self) -> int:
        return self.fixed_points.shape[-1]

    def _derived(self, name: str, sources: tuple[Tensor, ...], compute):
        """``compute()``, kept on the data while ``sources`` are unedited (their versions: the
        fields cannot be reassigned, but a tensor can be edited in place); not kept for
        inference or ``torch.func`` tensors, nor for anything that needs a gradient. An edit
        that bypasses the version counter (through ``.data``, a NumPy view or DLPack) is not
        seen, as autograd does not see it: edit the tensor itself, or build a new data."""
        if not all(
            _inference.cacheable(t) and not torch._C._functorch.is_functorch_wrapped_tensor(t)
            for t in sources
        ):
            return compute()
        versions = tuple(t._version for t in sources)
        cached = self.__dict__.get(name)
        if cached is not None and cached[0] == versions:
            return cached[1]
        with _inference.outside(), torch.no_grad():
            value = compute()
        self.__dict__[name] = (versions, value)
        return value

    def all_valid(self) -> bool:
        """Whether no observation slot is padding (the solver then skips its masking): one
        host read, kept; False under ``torch.func`` transforms (no read possible)."""
        if torch._C._functorch.is_functorch_wrapped_tensor(self.valid):
            return False
        return self._derived("_all_valid", (self.valid,), lambda: bool(self.valid.all()))

    def observation_masks(self) -> tuple[Tensor, Tensor]:
        """(free pose, free point) of each observation, bool (B, E): its pose, its point is
        not held fixed. Kept."""

        def compute() -> tuple[Tensor, Tensor]:
            free_pose = ~torch.gather(self.fixed_poses, 1, self.pose_index)
            return free_pose, ~torch.gather(self.fixed_points, 1, self.point_index)

        sources = (self.fixed_poses, self.pose_index, self.fixed_points, self.point_index)
        return self._derived("_observation_masks", sources, compute)

    def unit_weights(self, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Without ``weights`` and ``information``: w (1 on valid slots, 0 on padding) and its
        products with the free masks (:meth:`observation_masks`), w·free pose, w·free point
        and w·both, each (B, E) of ``dtype``. Kept per dtype."""

        def compute() -> tuple[Tensor, Tensor, Tensor, Tensor]:
            return weight_products(self.valid.to(dtype), *self.observation_masks())

        sources = (
            self.valid,
            self.fixed_poses,
            self.pose_index,
            self.fixed_points,
            self.point_index,
        )
        return self._derived(f"_unit_weights_{dtype}", sources, compute)

    def masked_observations(self) -> Tensor:
        """Observations (B, E, 3) with 0 on the padding (whatever it holds)."""
        if self.all_valid():
            return self.observations
        return torch.where(self.valid[..., None], self.observations, 0.0)

    def masked_weights(self) -> Tensor | None:
        """Scalar weights (B, E) with 1 on the padding, or None."""
        if self.weights is None:
            return None
        return torch.where(self.valid, self.weights, 1.0)

    def masked_information(self) -> Tensor | None:
        """Information matrices (B, E, 3, 3) with I on the padding, or None."""
        if self.information is None:
            return None
        eye = torch.eye(3, dtype=self.information.dtype, device=self.information.device)
        return torch.where(self.valid[..., None, None], self.information, eye)

    def whiten(self, vectors: Tensor) -> Tensor:
        """Apply the square root of the information, Lᵀ v with Ω = L Lᵀ; (B, E, 3, ...) → same.

        Accepts residuals (B, E, 3) or Jacobian blocks (B, E, 3, k).
        """
        column = vectors.dim() == 3
        v = vectors[..., None] if column else vectors
        v = whiten(whitening(self.masked_weights(), self.masked_information()), v)
        v = torch.where(self.valid[..., None, None], v, 0.0)
        return v[..., 0] if column else v

    def apply(self, fn) -> PointMapData:
        """A copy with ``fn`` applied to every tensor (observations, indices, masks, weights,
        the loss's and the terms' tensors): what ``problem.to(...)``/``.double()`` use."""
        changes = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, Tensor):
                changes[field.name] = fn(value)
        moved = {k: fn(v) for k, v in losses.tensor_attributes(self.loss, False).items()}
        changes["loss"] = losses.with_tensor_attributes(self.loss, moved)
        changes["terms"] = tuple(term.apply(fn) for term in self.terms)
        if self.parameters is not None:
            changes["parameters"] = self.parameters.apply(fn)
        return dataclasses.replace(self, **changes)

    def squared_norms(self, raw_residuals: Tensor) -> Tensor:
        """s_e = r_eᵀ Ω_e r_e, (B, E); exactly 0 on padding. No square root, so gradients
        w.r.t. the weights are exact even at w = 0."""
        if self.information is not None:
            info = self.masked_information()
            s = (raw_residuals[..., None, :] @ info @ raw_residuals[..., None])[..., 0, 0]
        else:
            s = (raw_residuals * raw_residuals).sum(-1)
            if self.weights is not None:
                s = self.masked_weights() * s
        return torch.where(self.valid, s, torch.zeros_like(s))


# ------------------------------------------------------------------------------------------
# Functional forms (used by the solver, which works on plain tensors)


def weight_products(
    w: Tensor, free_pose: Tensor, free_point: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(w, w·free pose, w·free point, w·both) of per-observation weights and the free masks
    of :meth:`PointMapData.observation_masks`, each (B, E)."""
    w_pose = w * free_pose
    return w, w_pose, w * free_point, w_pose * free_point


def per_observation(values: Tensor, flat_index: Tensor) -> Tensor:
    """Rows of ``values`` (B, k, *tail) picked by a flat index (B, E) → (B, E, *tail).

    ``flat_index`` is ``data.flat_pose_index`` or ``data.flat_point_index``; an
    ``index_select`` on the flattened rows is much cheaper than ``gather`` with an index
    expanded over the tail.
    """
    B, E = flat_index.shape
    tail = values.shape[2:]
    flat = values.reshape(-1, *tail)
    return torch.index_select(flat, 0, flat_index.reshape(-1)).reshape(B, E, *tail)


def gather_poses(pose_tangent: Tensor, data: PointMapData) -> Tensor:
    """ξ of the observing pose of each observation: (B, m, 6) → (B, E, 6)."""
    return per_observation(pose_tangent, data.flat_pose_index)


def gather_points(points: Tensor, data: PointMapData) -> Tensor:
    """Point of each observation: (B, n, 3) → (B, E, 3)."""
    return per_observation(points, data.flat_point_index)


def raw_residuals_from_poses(T: Tensor, points: Tensor, data: PointMapData) -> Tensor:
    """r_e = X_ij − T_i X_j from pose matrices T (B, m, 4, 4); (B, E, 3), zero on padding."""
    T_e = per_observation(T, data.flat_pose_index)
    X_e = gather_points(points, data)
    r = data.masked_observations() - se3.act(T_e, X_e)
    return torch.where(data.valid[..., None], r, torch.zeros_like(r))


def raw_residuals(pose_tangent: Tensor, points: Tensor, data: PointMapData) -> Tensor:
    """r_e = X_ij − Exp(ξ_i) X_j, (B, E, 3), zero on padding."""
    return raw_residuals_from_poses(se3.exp(pose_tangent, form="fast"), points, data)


def cost_from_poses(
    T: Tensor, points: Tensor, data: PointMapData, parameters: Tensor | None = None
) -> Tensor:
    """½ Σ_e ρ(r_eᵀ Ω_e r_e) + the terms' costs per problem, (B,), from pose matrices
    T (B, m, 4, 4) (and the parameter blocks' slot values (B, S, 6), if any)."""
    s = data.squared_norms(raw_residuals_from_poses(T, points, data))
    if data.loss is not None:
        s = torch.where(data.valid, data.loss(s)[0], torch.zeros_like(s))
    return 0.5 * s.sum(-1) + terms_cost(data.terms, T, points, data.parameters, parameters)


def cost(
    pose_tangent: Tensor, points: Tensor, data: PointMapData, parameters: Tensor | None = None
) -> Tensor:
    """½ Σ_e ρ(r_eᵀ Ω_e r_e) + the terms' costs per problem, (B,) (``parameters``: the
    parameter blocks' slot values (B, S, 6), if any)."""
    return cost_from_poses(se3.exp(pose_tangent, form="fast"), points, data, parameters)


def jacobian_blocks(
    pose_tangent: Tensor, points: Tensor, data: PointMapData, mode: str = "analytic"
) -> tuple[Tensor, Tensor]:
    """Raw-residual Jacobian blocks (B, E, 3, 6) and (B, E, 3, 3); see :mod:`jacobians`."""
    X_e = gather_points(points, data)
    if mode == "analytic":
        R_e = per_observation(se3.exp(pose_tangent, form="fast")[..., :3, :3], data.flat_pose_index)
        return jacobians.analytic_blocks(R_e, X_e)
    if mode == "jacrev":
        xi_e = gather_poses(pose_tangent, data)
        return jacobians.jacrev_blocks(xi_e, X_e, data.masked_observations())
    raise ValueError(f"jacobian_blocks: 'mode' must be 'analytic' or 'jacrev', got {mode!r}")


# ------------------------------------------------------------------------------------------
# Input checks


def check_batch(fn: str, B: int, **tensors: Tensor) -> None:
    for name, t in tensors.items():
        if t.shape[0] != B:
            raise ValueError(
                f"{fn}: batch sizes differ: 'poses' has B = {B} but '{name}' has "
                f"B = {t.shape[0]} (shape {tuple(t.shape)})"
            )


def index_tensor(fn: str, name: str, x: object, shape: tuple, device, source: str = "") -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"{fn}: argument '{name}' must be a torch.Tensor, got {type(x).__name__}")
    _checks.check_integer_tensor(fn, name, x)
    if tuple(x.shape) != tuple(shape):
        raise ValueError(
            f"{fn}: argument '{name}' must have shape {shape}, got {tuple(x.shape)}{source}"
        )
    return x.to(device=device, dtype=torch.long)


def bool_mask(
    fn: str, name: str, x: object, shape: tuple, device, default: bool, source: str = ""
) -> Tensor:
    if x is None:
        return torch.full(shape, default, dtype=torch.bool, device=device)
    if not isinstance(x, Tensor) or x.dtype != torch.bool:
        got = x.dtype if isinstance(x, Tensor) else type(x).__name__
        raise TypeError(f"{fn}: argument '{name}' must be a bool tensor, got {got}")
    if tuple(x.shape) != tuple(shape):
        raise ValueError(
            f"{fn}: argument '{name}' must have shape {shape}, got {tuple(x.shape)}{source}"
        )
    return x.to(device)


def split_weights(
    fn: str, weights: Tensor | None, B: int, E: int, observations: Tensor
) -> tuple[Tensor | None, Tensor | None]:
    if weights is None:
        return None, None
    _checks.check_tensor(fn, "weights", weights)
    _checks.check_same_kind(fn, observations=observations, weights=weights)
    if tuple(weights.shape) == (B, E):
        return weights, None
    if tuple(weights.shape) == (B, E, 3, 3):
        return None, weights
    raise ValueError(
        f"{fn}: argument 'weights' must have shape (B, E) = ({B}, {E}) for scalar weights or "
        f"(B, E, 3, 3) = ({B}, {E}, 3, 3) for information matrices, got {tuple(weights.shape)}"
    )


def check_weight_values(
    fn: str, valid: Tensor, weights: Tensor | None, information: Tensor | None
) -> None:
    """Scalar weights finite and ≥ 0, information matrices symmetric positive definite, at
    the valid observations (padding may hold anything)."""
    if weights is not None:
        w = weights.detach()
        bad = valid & ~(torch.isfinite(w) & (w >= 0))
        if bool(bad.any()):
            b, e = (int(i) for i in bad.nonzero()[0])
            raise ValueError(
                f"{fn}: argument 'weights' must be finite and ≥ 0 at valid observations; "
                f"problem {b}, observation {e} has {float(w[b, e]):.6g}"
            )
    if information is not None:
        eye = torch.eye(3, dtype=information.dtype, device=information.device)
        info = torch.where(valid[..., None, None], information.detach(), eye)
        finite = torch.isfinite(info).all(dim=(-1, -2))
        info = torch.where(finite[..., None, None], info, eye)
        asym = (info - info.transpose(-1, -2)).abs().amax(dim=(-1, -2))
        _, not_pd = torch.linalg.cholesky_ex(info)
        bad = ~finite | (not_pd > 0) | (asym > 1e-9 * info.abs().amax(dim=(-1, -2)).clamp_min(1))
        if bool(bad.any()):
            b, e = (int(i) for i in bad.nonzero()[0])
            what = "finite, symmetric positive definite"
            raise ValueError(
                f"{fn}: information matrices in 'weights' must be {what}; problem {b}, "
                f"observation {e} is not"
            )


def mark_checked(data: PointMapData) -> None:
    """Record that the values of ``data`` (index ranges, finite observations, weights) were
    checked (or deliberately not, inside ``validation(False)``), so that a solve does not
    check them again (a new PointMapData, e.g. from ``dataclasses.replace``, is checked
    anew)."""
    object.__setattr__(data, "_values_checked", True)


def check_data_values(fn: str, data: PointMapData) -> None:
    """Value checks of a :class:`PointMapData` (once; only when value checks are active):
    indices in range, observations finite and weights valid at the valid slots."""
    if getattr(data, "_values_checked", False) or not _checks.value_checks_active():
        return
    check_observations(
        fn,
        data.observations,
        data.valid,
        data.pose_index,
        data.point_index,
        data.num_poses,
        data.num_points,
    )
    check_weight_values(fn, data.valid, data.weights, data.information)
    for k, term in enumerate(data.terms):
        if term.pose_index.dim() != 3 or term.pose_index.shape[0] != data.valid.shape[0]:
            raise ValueError(
                f"{fn}: data.terms[{k}] ({type(term).__name__}) is not bound to the batch of "
                f"B = {data.valid.shape[0]} problems; build the problem with terms=[...] (or "
                "call term.bind(B, m, observations))"
            )
        bad = term.valid & ((term.pose_index < 0) | (term.pose_index >= data.num_poses)).any(-1)
        if bool(bad.any()):
            raise ValueError(
                f"{fn}: data.terms[{k}] ({type(term).__name__}) has a pose index outside "
                f"[0, {data.num_poses})"
            )
        if term.has_point:
            point_index = term.point_index
            bad = term.valid & ((point_index < 0) | (point_index >= data.num_points))
            if point_index.shape != term.valid.shape or bool(bad.any()):
                raise ValueError(
                    f"{fn}: data.terms[{k}] ({type(term).__name__}) has a point index outside "
                    f"[0, {data.num_points})"
                )
    mark_checked(data)


def check_observations(
    fn: str,
    observations: Tensor,
    valid: Tensor,
    pose_index: Tensor,
    point_index: Tensor,
    m: int,
    n: int,
) -> None:
    for name, index, size in (("pose_index", pose_index, m), ("point_index", point_index, n)):
        bad = valid & ((index < 0) | (index >= size))
        if bool(bad.any()):
            b, e = (int(i) for i in bad.nonzero()[0])
            none = ""
            if size == 0:
                what = "points (n = 0)" if name == "point_index" else "poses (m = 0)"
                none = f"; there are no {what}, so no observation may be valid"
            raise ValueError(
                f"{fn}: '{name}' out of range [0, {size}): problem {b}, observation {e} has "
                f"index {int(index[b, e])}{none}"
            )
    bad = valid[..., None] & ~(observations.detach().abs() < math.inf)  # not finite (or NaN)
    if bool(bad.any()):
        b, e, _ = (int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"{fn}: argument 'observations' has a non-finite value (NaN or Inf) in problem {b}, "
            f"observation {e} (pose {int(pose_index[b, e])}, point {int(point_index[b, e])}); "
            "remove it or mark it invalid with 'valid'"
        )
