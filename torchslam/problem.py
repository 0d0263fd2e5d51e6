"""The ICP-SLAM problem (seed section 1) as a batched ``nn.Module``.

B independent problems, each with m poses T_i0 (world → frame i) and n world points X_j,
observed as X_ij in frame i. Residual r_ij = X_ij − T_i0 X_j (seed eq. 1.1), cost

    F = ½ Σ_e ρ(r_eᵀ Ω_e r_e)

with per-observation information Ω_e (scalar weight w_e → Ω_e = w_e I; default I) and a robust
kernel ρ (default ρ(s) = s). The ½ follows Ceres, scipy and GTSAM; the seed's Σ‖r‖² has the
same minimizer.

Poses are kept as se(3) tangent parameters ξ_i = (ω, v) (``pose_tangent``, an
``nn.Parameter`` of shape (B, m, 6)); T_i0 = Exp(ξ_i). The solver updates them on the
manifold, T ← T·Exp(δ) (seed eq. L1), never T − δT. Points are an ``nn.Parameter`` (B, n, 3)
updated in Euclidean space.

Observations are stored once, as padded edge lists of length E (memory O(E), not O(m·n)):
``pose_index`` (B, E), ``point_index`` (B, E), ``observations`` (B, E, 3) and ``valid``
(B, E) (False for padding). :meth:`PointMapProblem.from_dense` converts the dense
(B, m, n, 3) + visibility (B, m, n) form.

Gauge: pose 0 is held fixed at its given value by default (the seed's T_0 = [I | 0] when it
is initialized at the identity). Any poses or points can be held fixed.

Ill-posed parts are never dropped silently. When the problem is built:
- a point with no valid observation is held fixed (it does not enter the cost);
- a free pose with fewer than 3 valid observations is held fixed (6 unknowns need ≥ 3 points),
  unless full-rank pose terms (≥ 6 residual entries: relative poses, priors) tie it to an
  anchor (a fixed pose, a pose with ≥ 3 observations, a prior); a group of such poses tied
  only to each other has a free gauge, and its first pose is held fixed;
each with a ``UserWarning`` naming the problem and the index, also listed in ``diagnostics``.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import torch
from torch import Tensor, nn

from torchslam import _checks, jacobians, losses
from torchslam.lie import se3
from torchslam.terms import Term, terms_cost

__all__ = ["PointMapData", "PointMapProblem"]


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
            index = _index_tensor(fn, name, getattr(self, name), (B, E), valid.device)
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

    @property
    def num_poses(self) -> int:
        return self.fixed_poses.shape[-1]

    @functools.cached_property
    def flat_pose_index(self) -> Tensor:
        """b·m + pose_index, long (B, E): rows of (B·m, …) tensors, for ``index_select``."""
        B = self.pose_index.shape[0]
        batch = torch.arange(B, device=self.pose_index.device)[:, None]
        return batch * self.num_poses + self.pose_index

    @functools.cached_property
    def flat_point_index(self) -> Tensor:
        """b·n + point_index, long (B, E): rows of (B·n, …) tensors, for ``index_select``."""
        B = self.point_index.shape[0]
        batch = torch.arange(B, device=self.point_index.device)[:, None]
        return batch * self.num_points + self.point_index

    @property
    def num_points(self) -> int:
        return self.fixed_points.shape[-1]

    def masked_observations(self) -> Tensor:
        """Observations (B, E, 3) with 0 on the padding (whatever it holds)."""
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
        if self.information is not None:
            L = torch.linalg.cholesky(self.masked_information())
            v = L.transpose(-1, -2) @ v
        elif self.weights is not None:
            v = torch.sqrt(self.masked_weights())[..., None, None] * v
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


class PointMapProblem(nn.Module):
    """B independent ICP-SLAM problems: poses ξ (B, m, 6) and points (B, n, 3) as parameters.

    Args:
        poses: initial poses T_i0 (world → frame i), shape (B, m, 4, 4); stored as
            ``pose_tangent`` = Log(T) (B, m, 6), ξ = (ω, v) rotation first.
        points: initial world points X_j, shape (B, n, 3).
        pose_index: observing pose of each observation, integer (B, E), in [0, m).
        point_index: observed point of each observation, integer (B, E), in [0, n).
        observations: observed points X_ij in frame i, shape (B, E, 3).
        valid: False for padding slots, bool (B, E); default all True.
        weights: per-observation scalar weights (B, E) ≥ 0, or information matrices
            (B, E, 3, 3) (symmetric positive definite); default 1.
        fixed_poses: poses held fixed, bool (B, m); default: pose 0 only (the gauge).
        fixed_points: points held fixed, bool (B, n); default none.
        loss: robust kernel from :mod:`torchslam.losses` (e.g. ``HuberLoss(0.05)``), applied
            per observation to s = rᵀΩr; default none (least squares).
        terms: extra terms of the objective on the poses (:mod:`torchslam.terms`: relative-pose
            constraints, pose priors, user terms), each shared by the batch or batched (B, …).

    The objective is ½ Σ_e ρ(r_eᵀ Ω_e r_e) + Σ_terms ½ Σ_k ρ_t(s_k).

    All float tensors must share one dtype (float64 recommended) and device.
    """

    def __init__(
        self,
        poses: Tensor,
        points: Tensor,
        pose_index: Tensor,
        point_index: Tensor,
        observations: Tensor,
        *,
        valid: Tensor | None = None,
        weights: Tensor | None = None,
        fixed_poses: Tensor | None = None,
        fixed_points: Tensor | None = None,
        loss: object | None = None,
        terms: Sequence[Term] = (),
    ) -> None:
        super().__init__()
        fn = "PointMapProblem"
        _checks.check_batched(fn, "poses", poses, ("B", "m"), (4, 4))
        _checks.check_batched(fn, "points", points, ("B", "n"), (3,))
        _checks.check_batched(fn, "observations", observations, ("B", "E"), (3,))
        _checks.check_same_kind(fn, poses=poses, points=points, observations=observations)
        B, m = poses.shape[:2]
        n = points.shape[1]
        E = observations.shape[1]
        _check_batch(fn, B, points=points, observations=observations)
        if m == 0:
            raise ValueError(
                f"{fn}: a problem needs at least one pose (m ≥ 1); 'poses' has shape "
                f"{tuple(poses.shape)}"
            )
        edges = f" ((B, E) of 'observations' {tuple(observations.shape)})"
        device = observations.device
        pose_index = _index_tensor(fn, "pose_index", pose_index, (B, E), device, edges)
        point_index = _index_tensor(fn, "point_index", point_index, (B, E), device, edges)
        valid = _mask(fn, "valid", valid, (B, E), device, True, edges)
        fixed_poses_given = fixed_poses is not None
        source = f" ((B, m) of 'poses' {tuple(poses.shape)})"
        fixed_poses = _mask(fn, "fixed_poses", fixed_poses, (B, m), poses.device, False, source)
        if not fixed_poses_given:
            fixed_poses = fixed_poses.clone()
            fixed_poses[:, 0] = True
        source = f" ((B, n) of 'points' {tuple(points.shape)})"
        fixed_points = _mask(fn, "fixed_points", fixed_points, (B, n), points.device, False, source)
        losses.check_loss(fn, loss)
        scalar_weights, information = _split_weights(fn, weights, B, E, observations)
        terms = _bind_terms(fn, terms, B, m, observations, n)

        _checks.check_pose_matrix(fn, "poses", poses)
        _checks.check_finite(fn, "points", points)
        self.diagnostics: list[str] = []
        checked = _checks.value_checks_active()
        if checked:
            _check_observations(fn, observations, valid, pose_index, point_index, m, n)
            _check_weight_values(fn, valid, scalar_weights, information)
            fixed_poses, fixed_points = _hold_ill_posed_fixed(
                fn,
                valid,
                pose_index,
                point_index,
                fixed_poses,
                fixed_points,
                self.diagnostics,
                _term_links(terms, B) if terms else None,
                _point_term_counts(terms, B, m, n),
            )

        self.pose_tangent = nn.Parameter(se3.log(poses.detach()).clone())
        self.points = nn.Parameter(points.detach().clone())
        # PointMapData makes the padding inert (index 0, observation 0, weight 1, information
        # I), whatever it holds: NaN, Inf, out-of-range indices.
        self.data = PointMapData(
            pose_index=pose_index,
            point_index=point_index,
            observations=observations,
            valid=valid,
            weights=scalar_weights,
            information=information,
            fixed_poses=fixed_poses,
            fixed_points=fixed_points,
            loss=loss,
            terms=terms,
        )
        # Checked above, or deliberately not (built inside validation(False)): a solve does not
        # check these values again (a non-finite observation then shows in the status).
        mark_checked(self.data)

    def _apply(self, fn, recurse: bool = True):
        # nn.Module.to / .double() / .cuda() reach the parameters through _apply; the data is
        # not a buffer (a dataclass), so move it here too.
        super()._apply(fn, recurse)
        self.data = self.data.apply(fn)
        return self

    # ----------------------------------------------------------------------------------------
    # Constructors

    @classmethod
    def from_dense(
        cls,
        poses: Tensor,
        points: Tensor,
        observations: Tensor,
        visibility: Tensor,
        *,
        weights: Tensor | None = None,
        fixed_poses: Tensor | None = None,
        fixed_points: Tensor | None = None,
        loss: object | None = None,
    ) -> PointMapProblem:
        """Build from dense observations (B, m, n, 3) and a visibility mask (B, m, n).

        ``weights`` may be dense too: (B, m, n) scalars or (B, m, n, 3, 3) information.
        Internally the visible entries become padded edge lists, sorted by (pose, point).
        """
        fn = "PointMapProblem.from_dense"
        _checks.check_tensor(fn, "observations", observations, (3,), min_batch_dims=3, dims="Bmn")
        if observations.dim() != 4:
            raise ValueError(
                f"{fn}: argument 'observations' must have shape (B, m, n, 3), "
                f"got {tuple(observations.shape)}"
            )
        B, m, n, _ = observations.shape
        for name, t, size in (("poses", poses, m), ("points", points, n)):
            if not isinstance(t, Tensor):
                raise TypeError(
                    f"{fn}: argument '{name}' must be a torch.Tensor, got {_checks.describe(t)}"
                )
            if t.dim() < 2 or t.shape[1] != size:
                raise ValueError(
                    f"{fn}: argument '{name}' must have {size} rows to match 'observations' "
                    f"(B, m, n, 3) = {tuple(observations.shape)}, got {tuple(t.shape)}"
                )
        if weights is not None:
            _checks.check_tensor(fn, "weights", weights)
        if weights is not None and tuple(weights.shape) not in ((B, m, n), (B, m, n, 3, 3)):
            got = tuple(weights.shape)
            raise ValueError(
                f"{fn}: argument 'weights' must have shape (B, m, n) = ({B}, {m}, {n}) for scalar "
                f"weights or (B, m, n, 3, 3) for information matrices, got {got}"
            )
        visibility = _mask(fn, "visibility", visibility, (B, m, n), observations.device, False)
        flat = visibility.reshape(B, m * n)
        counts = flat.sum(-1)
        E = int(counts.max()) if B > 0 else 0
        # Stable sort puts each problem's visible entries first, in (pose, point) order.
        order = torch.sort((~flat).to(torch.uint8), dim=-1, stable=True).indices[:, :E]
        valid = torch.arange(E, device=flat.device) < counts[:, None]
        obs = torch.gather(observations.reshape(B, m * n, 3), 1, order[..., None].expand(B, E, 3))
        edge_weights = None
        if weights is not None:
            tail = weights.shape[3:]
            w = weights.reshape(B, m * n, *tail)
            idx = order.reshape(B, E, *([1] * len(tail))).expand(B, E, *tail)
            edge_weights = torch.gather(w, 1, idx)
            if tail:
                eye = torch.eye(3, dtype=w.dtype, device=w.device)
                edge_weights = torch.where(valid[..., None, None], edge_weights, eye)
            else:
                edge_weights = torch.where(valid, edge_weights, torch.ones_like(edge_weights))
        return cls(
            poses,
            points,
            order // n,
            order % n,
            obs,
            valid=valid,
            weights=edge_weights,
            fixed_poses=fixed_poses,
            fixed_points=fixed_points,
            loss=loss,
        )

    @classmethod
    def from_scene(
        cls,
        scene: object,
        poses: Tensor | None = None,
        points: Tensor | None = None,
        *,
        loss: object | None = None,
    ) -> PointMapProblem:
        """Build from a :class:`torchslam.data.synthetic.SyntheticScene`.

        ``poses``/``points`` default to the scene's ground truth (useful for tests); pass an
        initialization (e.g. from :mod:`torchslam.initialization`) to solve.
        """
        fields = ("poses_gt", "points_gt", "pose_index", "point_index", "observations", "valid")
        missing = [f for f in fields if not hasattr(scene, f)]
        if missing:
            raise TypeError(
                "PointMapProblem.from_scene: argument 'scene' must be a SyntheticScene "
                f"(torchslam.data.synthetic.make_scene), got {_checks.describe(scene)} without "
                f"{', '.join(missing)}"
            )
        return cls(
            scene.poses_gt if poses is None else poses,
            scene.points_gt if points is None else points,
            scene.pose_index,
            scene.point_index,
            scene.observations,
            valid=scene.valid,
            loss=loss,
        )

    # ----------------------------------------------------------------------------------------
    # Sizes

    @property
    def batch_size(self) -> int:
        return self.pose_tangent.shape[0]

    @property
    def num_poses(self) -> int:
        return self.pose_tangent.shape[1]

    @property
    def num_points(self) -> int:
        return self.points.shape[1]

    @property
    def num_observations(self) -> Tensor:
        """Valid observations per problem, long (B,)."""
        return self.data.valid.sum(-1)

    # ----------------------------------------------------------------------------------------
    # Residuals and cost

    def poses(self) -> Tensor:
        """Current poses T_i0 = Exp(ξ_i), shape (B, m, 4, 4)."""
        return se3._exp(self.pose_tangent)

    def raw_residuals(self) -> Tensor:
        """r_e = X_ij − T_i0 X_j, (B, E, 3), zero on padding (differentiable w.r.t. all)."""
        return raw_residuals(self.pose_tangent, self.points, self.data)

    def residuals(self) -> Tensor:
        """Weighted (whitened) residuals Lᵀ r_e with Ω_e = L Lᵀ, (B, E, 3), zero on padding.

        The point observations only: the pose terms' residuals are their own
        (:func:`torchslam.terms.term_jacobians`); :meth:`cost` sums both.
        """
        return self.data.whiten(self.raw_residuals())

    def cost(self) -> Tensor:
        """Per-problem cost ½ Σ_e ρ(r_eᵀ Ω_e r_e) (+ the terms' costs), shape (B,)."""
        return cost(self.pose_tangent, self.points, self.data)

    def forward(self) -> Tensor:
        """The per-problem cost, shape (B,) (so the module can be called like a loss)."""
        return self.cost()

    # ----------------------------------------------------------------------------------------
    # Jacobians

    def jacobian_blocks(self, mode: str = "analytic") -> tuple[Tensor, Tensor]:
        """Per-observation blocks of the raw residual, right perturbation, (ω, v) order.

        Args:
            mode: ``"analytic"`` (default) or ``"jacrev"`` (``torch.func.jacrev`` + vmap).

        Returns:
            (J_r_xi (B, E, 3, 6), J_r_point (B, E, 3, 3)); padding rows are not zeroed.
        """
        return jacobian_blocks(self.pose_tangent, self.points, self.data, mode)

    def dense_jacobian(self, mode: str = "analytic") -> Tensor:
        """The seed's overall Jacobian of the whitened residuals, (B, 3E, 6m + 3n).

        Rows of the point observations only (the pose terms are not included). For small
        problems and debugging only: refuses (ValueError) above
        ``torchslam.jacobians.DENSE_JACOBIAN_MAX_ENTRIES`` entries. Padding rows are zero.
        """
        B, E = self.data.pose_index.shape
        cols = 6 * self.num_poses + 3 * self.num_points
        if B * 3 * E * cols > jacobians.DENSE_JACOBIAN_MAX_ENTRIES:
            # Check before computing anything.
            jacobians.dense_jacobian(
                self.points.new_zeros(B, E, 3, 6),
                self.points.new_zeros(B, E, 3, 3),
                self.data.pose_index,
                self.data.point_index,
                self.num_poses,
                self.num_points,
            )
        J_xi, J_point = self.jacobian_blocks(mode)
        return jacobians.dense_jacobian(
            self.data.whiten(J_xi),
            self.data.whiten(J_point),
            self.data.pose_index,
            self.data.point_index,
            self.num_poses,
            self.num_points,
        )

    def extra_repr(self) -> str:
        return (
            f"batch_size={self.batch_size}, num_poses={self.num_poses}, "
            f"num_points={self.num_points}, max_observations={self.data.pose_index.shape[1]}"
        )


# ------------------------------------------------------------------------------------------
# Functional forms (used by the solver, which works on plain tensors)


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
    r = data.masked_observations() - se3._act(T_e, X_e)
    return torch.where(data.valid[..., None], r, torch.zeros_like(r))


def raw_residuals(pose_tangent: Tensor, points: Tensor, data: PointMapData) -> Tensor:
    """r_e = X_ij − Exp(ξ_i) X_j, (B, E, 3), zero on padding."""
    return raw_residuals_from_poses(se3._exp(pose_tangent), points, data)


def cost_from_poses(T: Tensor, points: Tensor, data: PointMapData) -> Tensor:
    """½ Σ_e ρ(r_eᵀ Ω_e r_e) + the terms' costs per problem, (B,), from pose matrices
    T (B, m, 4, 4)."""
    s = data.squared_norms(raw_residuals_from_poses(T, points, data))
    if data.loss is not None:
        s = torch.where(data.valid, data.loss(s)[0], torch.zeros_like(s))
    return 0.5 * s.sum(-1) + terms_cost(data.terms, T, points)


def cost(pose_tangent: Tensor, points: Tensor, data: PointMapData) -> Tensor:
    """½ Σ_e ρ(r_eᵀ Ω_e r_e) + the terms' costs per problem, (B,)."""
    return cost_from_poses(se3._exp(pose_tangent), points, data)


def jacobian_blocks(
    pose_tangent: Tensor, points: Tensor, data: PointMapData, mode: str = "analytic"
) -> tuple[Tensor, Tensor]:
    """Raw-residual Jacobian blocks (B, E, 3, 6) and (B, E, 3, 3); see :mod:`jacobians`."""
    X_e = gather_points(points, data)
    if mode == "analytic":
        R_e = per_observation(se3._exp(pose_tangent)[..., :3, :3], data.flat_pose_index)
        return jacobians.analytic_blocks(R_e, X_e)
    if mode == "jacrev":
        xi_e = gather_poses(pose_tangent, data)
        return jacobians.jacrev_blocks(xi_e, X_e, data.masked_observations())
    raise ValueError(f"jacobian_blocks: 'mode' must be 'analytic' or 'jacrev', got {mode!r}")


# ------------------------------------------------------------------------------------------
# Input checks


def _check_batch(fn: str, B: int, **tensors: Tensor) -> None:
    for name, t in tensors.items():
        if t.shape[0] != B:
            raise ValueError(
                f"{fn}: batch sizes differ: 'poses' has B = {B} but '{name}' has "
                f"B = {t.shape[0]} (shape {tuple(t.shape)})"
            )


def _index_tensor(fn: str, name: str, x: object, shape: tuple, device, source: str = "") -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"{fn}: argument '{name}' must be a torch.Tensor, got {type(x).__name__}")
    if x.dtype.is_floating_point or x.dtype.is_complex or x.dtype == torch.bool:
        raise TypeError(f"{fn}: argument '{name}' must be an integer tensor, got {x.dtype}")
    if tuple(x.shape) != tuple(shape):
        raise ValueError(
            f"{fn}: argument '{name}' must have shape {shape}, got {tuple(x.shape)}{source}"
        )
    return x.to(device=device, dtype=torch.long)


def _mask(
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


def _split_weights(
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


def _check_weight_values(
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
    _check_observations(
        fn,
        data.observations,
        data.valid,
        data.pose_index,
        data.point_index,
        data.num_poses,
        data.num_points,
    )
    _check_weight_values(fn, data.valid, data.weights, data.information)
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


def _check_observations(
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
    bad = valid[..., None] & ~torch.isfinite(observations.detach())
    if bool(bad.any()):
        b, e, _ = (int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"{fn}: argument 'observations' has a non-finite value (NaN or Inf) in problem {b}, "
            f"observation {e} (pose {int(pose_index[b, e])}, point {int(point_index[b, e])}); "
            "remove it or mark it invalid with 'valid'"
        )


def _bind_terms(
    fn: str, terms: object, B: int, m: int, observations: Tensor, n: int = 0
) -> tuple[Term, ...]:
    if terms is None:
        return ()
    if isinstance(terms, Term) or not isinstance(terms, (list, tuple)):
        raise TypeError(
            f"{fn}: argument 'terms' must be a list or tuple of torchslam.Term objects, "
            f"got {type(terms).__name__}"
        )
    for k, term in enumerate(terms):
        if not isinstance(term, Term):
            raise TypeError(
                f"{fn}: terms[{k}] must be a torchslam.Term (e.g. RelativePoseTerm), "
                f"got {type(term).__name__}"
            )
    return tuple(term.bind(B, m, observations, n) for term in terms)


def _term_links(terms: tuple[Term, ...], B: int) -> list[tuple]:
    """The terms' full-rank links per problem: [(edges (L, 2), anchors (A,)) for each b].

    An instance links its poses when its residual has ≥ 6 entries and it is valid with a
    positive weight: a unary one (a prior) anchors its pose, one of arity ≥ 2 joins its poses
    (a relative pose fixes one pose given the other). A term that touches a point links its
    poses only through the point, which is a variable too: it neither anchors nor joins them
    here, it observes them (:func:`_point_term_counts`) as a point observation does.
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


def _point_term_counts(terms: tuple[Term, ...], B: int, m: int, n: int) -> tuple | None:
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


def _unanchored_gauges(
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


def _hold_ill_posed_fixed(
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
    observation, or two reprojections). ``point_terms`` (:func:`_point_term_counts`) adds the
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
        weak_poses, gauges = _unanchored_gauges(term_links, weak_poses, fixed_poses, m)
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
