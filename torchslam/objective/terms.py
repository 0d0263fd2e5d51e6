"""Pluggable residual terms on poses and points: relative poses, priors, point observations,
user terms.

The objective of a :class:`torchslam.PointMapProblem` is a sum of terms: the ICP-SLAM point
observations (built in; the Schur complement eliminates their points) plus any number of
:class:`Term` objects passed as ``terms=[...]``. A term is a small object holding K instances
of one residual r_k (d entries) over a poses each (its *arity*), with

    cost_k = ½ ρ(|U_k r_k|²),    U_kᵀU_k = Ω_k (information) or w_k I (scalar weight),

ρ an optional robust kernel of :mod:`torchslam.losses` (identity by default). Its poses are
the problem's variables T_i0 (world → frame i, :class:`torchslam.PointMapProblem`) in the same
convention everywhere: ξ = (ω, v) rotation first, right perturbation T ← T·Exp(δ).

Writing a term. Subclass :class:`Term` and implement :meth:`Term.residual`, batched over any
leading dims::

    class PointToPlane(Term):        # r = nᵀ(T X − p): world point X, plane (p, n) in frame i
        def __init__(self, pose_index, X, p, n, weight=None):
            super().__init__(pose_index[:, None], dict(X=X, p=p, n=n), weight=weight)

        def residual(self, poses, X, p, n):
            T = poses[..., 0, :, :]
            TX = (T[..., :3, :3] @ X[..., None])[..., 0] + T[..., :3, 3]
            return ((TX - p) * n).sum(-1, keepdim=True)

Its Jacobian blocks ∂r/∂δ_a (d × 6 per pose) then come from ``torch.func.jacrev`` of
r(T_a·Exp(δ_a)) at δ = 0, vmapped over the instances; a term may also override
:meth:`Term.jacobians` with analytic blocks (the built-in terms do, and the tests check them
against ``jacrev`` and central differences).

Terms that touch points. Given ``point_index`` (K,) or (B, K), each instance also touches one
world point X_j (a variable of the problem, like the points of the point observations) and
is called as ``residual(poses, points, **constants)`` with points (..., 3); ``jacrev`` then
also differentiates r(…, X_j + δX) at δX = 0, and analytic :meth:`Term.jacobians` return
(r, J_poses, J_point (..., d, 3)). The solver eliminates these points by the same Schur
complement as the point observations (each (pose, point) pair of an instance is a coupling
edge, :func:`torchslam.solver.linearize.coupling_edges`). Such a term may touch no pose at
all (``pose_index=None``: arity 0, e.g. a prior on a point). A pinhole reprojection term is in
``examples/bundle_adjustment.py``.

Terms that touch parameter blocks. Given ``parameters={group: index}`` (index (K,) or (B, K),
one block per instance, or (K, c) for c blocks), each instance also touches blocks of the
problem's parameter group (camera intrinsics, calibrations: :mod:`torchslam.objective.
parameters`), passed to :meth:`Term.residual` by the group's name, (..., d) or (..., c, d);
``jacrev`` differentiates them as Euclidean increments, analytic :meth:`Term.jacobians` append
a dict {group: ∂r/∂x}. :class:`torchslam.ReprojectionTerm` is the built-in one.

Built-in terms (derivations in their docstrings):

- :class:`RelativePoseTerm`: r_ij = Log(Z_ij⁻¹ · T_i · T_j⁻¹) with Z_ij ≈ T_i0 T_j0⁻¹, the
  pose of frame j in frame i (it maps frame-j coordinates to frame i: what ICP of scan j onto
  scan i returns, and the odometry T_(i,i+1) of the chain T_0i = T_01 T_12 …).
- :class:`PosePriorTerm`: r = Log(Z⁻¹ · T) with Z ≈ T.
- :class:`PointObservationTerm`: r = X_ij − T_i0 X_j, the ICP-SLAM point observation (seed
  eq. 1.1) that :class:`torchslam.PointMapProblem` keeps in its data for its structured fast
  path.

Pose graphs of :mod:`torchslam.posegraph` use g2o's body → world vertices T_i^g = T_i0⁻¹ and
measurements Z_ij^g ≈ (T_i^g)⁻¹ T_j^g = T_i0 T_j0⁻¹: the same Z_ij, so a g2o edge (i, j) is a
:class:`RelativePoseTerm` on the inverted vertices with the same measurement and information.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping

import torch
from torch import Tensor

from torchslam import _checks, _inference, losses
from torchslam._batched import matmul
from torchslam.lie import se3, so3
from torchslam.manifold import right_jacobian_jacrev
from torchslam.objective.parameters import SLOT, ParameterLayout
from torchslam.objective.whitening import whitening

__all__ = [
    "PointObservationTerm",
    "PosePriorTerm",
    "RelativePoseTerm",
    "Term",
    "bind_terms",
    "point_observation_jacobians",
    "pose_prior_residual",
    "relative_pose_jacobians",
    "relative_pose_residual",
    "term_blocks",
    "term_cost",
    "term_jacobians",
    "term_parameters",
    "term_points",
    "term_poses",
    "term_rows",
    "term_squared_norms",
    "term_whitening",
    "terms_cost",
]


class Term:
    """K instances of a residual over ``arity`` poses each, optionally weighted and robust.

    Args:
        pose_index: poses each instance touches, integer (K, a) or (B, K, a): a = arity.
        constants: the instances' data, a mapping name → tensor (K, …) or (B, K, …) with the
            same leading dims as ``pose_index`` (floating ones in the problem's dtype; integer
            ones allowed); passed to :meth:`residual` by name. Floating ones may require grad
            (the differentiable solve carries gradients to them).
        weight: scalar weights w_k ≥ 0, (K,) or (B, K); or
        information: information matrices Ω_k, symmetric positive definite, (K, d, d) or
            (B, K, d, d). Default: unit weights. Not both.
        loss: robust kernel of :mod:`torchslam.losses` applied to s_k = r_kᵀ Ω_k r_k.
        valid: False for padding instances, bool (K,) or (B, K); default all True.

    Without a batch dim the term is shared by every problem of the batch. All floating
    tensors must share the problem's dtype and device.

    ``convention`` names the poses the residual reads: ``"world_to_frame"`` (T_i0, those of
    :class:`torchslam.PointMapProblem`; the default) or ``"frame_to_world"`` (body → world
    vertices, as the pose-graph adapter holds them); point observations need the former, so a
    problem refuses to mix them with a frame_to_world term.
    """

    convention: str = "world_to_frame"

    def __init__(
        self,
        pose_index: Tensor,
        constants: Mapping[str, Tensor] | None = None,
        *,
        point_index: Tensor | None = None,
        weight: Tensor | None = None,
        information: Tensor | None = None,
        loss: object | None = None,
        valid: Tensor | None = None,
        parameters: Mapping[str, Tensor] | None = None,
    ) -> None:
        fn = type(self).__name__
        if pose_index is None and isinstance(point_index, Tensor):
            # A term on points only (e.g. a point prior): arity 0.
            pose_index = point_index.new_zeros(*point_index.shape, 0)
        if not isinstance(pose_index, Tensor):
            raise TypeError(
                f"{fn}: argument 'pose_index' must be a torch.Tensor, "
                f"got {type(pose_index).__name__}"
            )
        _checks.check_integer_tensor(fn, "pose_index", pose_index)
        least = 0 if point_index is not None else 1
        if pose_index.dim() not in (2, 3) or pose_index.shape[-1] < least:
            raise ValueError(
                f"{fn}: argument 'pose_index' must have shape (K, a) or (B, K, a) with a ≥ 1 "
                f"poses per instance (a ≥ 0 with 'point_index'), got {tuple(pose_index.shape)}"
            )
        if weight is not None and information is not None:
            raise ValueError(f"{fn}: give 'weight' or 'information', not both")
        self.pose_index = pose_index.long()
        lead = tuple(pose_index.shape[:-1])
        # The point each instance touches, long (K,) or (B, K), or None for a pose term.
        self.point_index = None
        if point_index is not None:
            if not isinstance(point_index, Tensor):
                raise TypeError(
                    f"{fn}: argument 'point_index' must be a torch.Tensor or None, "
                    f"got {_checks.describe(point_index)}"
                )
            _checks.check_integer_tensor(fn, "point_index", point_index)
            if tuple(point_index.shape) != lead:
                raise ValueError(
                    f"{fn}: argument 'point_index' must have shape {lead} (those of "
                    f"'pose_index' without the arity), got {tuple(point_index.shape)}"
                )
            self.point_index = point_index.to(pose_index.device, torch.long)
        if valid is None:
            valid = torch.ones(lead, dtype=torch.bool, device=pose_index.device)
        if not isinstance(valid, Tensor) or valid.dtype != torch.bool:
            raise TypeError(
                f"{fn}: argument 'valid' must be a bool tensor of shape {lead}, got "
                f"{_checks.describe(valid)}"
            )
        if tuple(valid.shape) != lead:
            raise ValueError(
                f"{fn}: argument 'valid' must be a bool tensor of shape {lead}, got "
                f"{tuple(valid.shape)}"
            )
        valid = valid.to(pose_index.device)
        if constants is not None and not isinstance(constants, Mapping):
            raise TypeError(
                f"{fn}: argument 'constants' must be a mapping name → tensor, got "
                f"{_checks.describe(constants)}"
            )
        self.constants = dict(constants or {})
        self.parameter_index = _parameter_indices(fn, parameters, lead, pose_index.device)
        check_values = _checks.value_checks_active()
        reserved = ("poses", "points") if self.point_index is not None else ("poses",)
        reserved = reserved + tuple(self.parameter_index)
        for name, value in self.constants.items():
            if not isinstance(name, str) or not name.isidentifier():
                raise TypeError(
                    f"{fn}: constant names must be identifiers (they are passed to residual() "
                    f"by name), got {name!r}"
                )
            if name in reserved:
                raise ValueError(
                    f"{fn}: constant name {name!r} is taken by the argument of residual() "
                    f"of that name (a variable: poses, points or a parameter group); rename "
                    f"the constant"
                )
            _checks.check_tensor(fn, name, value, floating=False)
            if tuple(value.shape[: len(lead)]) != lead:
                raise ValueError(
                    f"{fn}: constant '{name}' must have leading shape {lead} (those of "
                    f"'pose_index' without the arity), got {tuple(value.shape)}"
                )
            if check_values and (value.is_floating_point() or value.is_complex()):
                _check_finite_where_valid(fn, f"constant '{name}'", value, valid)
        if weight is not None:
            _checks.check_tensor(fn, "weight", weight)
            if tuple(weight.shape) != lead:
                raise ValueError(
                    f"{fn}: argument 'weight' must have shape {lead}, got {tuple(weight.shape)}"
                )
            if check_values:
                w = weight.detach()
                bad = valid.to(w.device) & ~(torch.isfinite(w) & (w >= 0))
                if bool(bad.any()):
                    where = tuple(int(i) for i in bad.nonzero()[0])
                    raise ValueError(
                        f"{fn}: argument 'weight' must be finite and ≥ 0 at valid instances; "
                        f"instance {where} has {float(w[where]):.6g}"
                    )
        if information is not None:
            _checks.check_tensor(fn, "information", information)
            if (
                information.dim() != len(lead) + 2
                or tuple(information.shape[: len(lead)]) != lead
                or information.shape[-1] != information.shape[-2]
            ):
                raise ValueError(
                    f"{fn}: argument 'information' must have shape {lead} + (d, d), "
                    f"got {tuple(information.shape)}"
                )
            if check_values and information.numel() > 0:
                mask = valid.to(information.device)[..., None, None]
                eye = torch.eye(
                    information.shape[-1], dtype=information.dtype, device=information.device
                )
                info = torch.where(mask, information.detach(), eye)
                finite = torch.isfinite(info).all(dim=(-1, -2))
                info = torch.where(finite[..., None, None], info, eye)
                asym = (info - info.transpose(-1, -2)).abs().amax(dim=(-1, -2))
                scale = info.abs().amax(dim=(-1, -2)).clamp_min(1)
                bad = ~finite | (torch.linalg.cholesky_ex(info)[1] > 0) | (asym > 1e-9 * scale)
                if bool(bad.any()):
                    where = tuple(int(i) for i in bad.nonzero()[0])
                    raise ValueError(
                        f"{fn}: argument 'information' must be finite, symmetric positive "
                        f"definite at valid instances; instance {where} is not"
                    )
        losses.check_loss(fn, loss)
        self.weight = weight
        self.information = information
        self.loss = loss
        self.valid = valid
        # Entries d of one residual; set by bind() (None before, or without instances).
        self.residual_dim: int | None = None

    # ----------------------------------------------------------------------------------------
    # What a subclass writes

    def padding_constant(self, name: str, like: Tensor) -> Tensor:
        """The value of constant ``name`` at padding instances when no instance is valid (one
        instance's value, shaped and typed like ``like``): zeros. A term whose residual
        refuses zeros overrides it (the pose terms give the identity), so that padding stays
        inert whatever it holds."""
        return torch.zeros_like(like)

    def residual(self, poses: Tensor, *args: Tensor, **constants: Tensor) -> Tensor:
        """Residuals of the instances: poses (..., a, 4, 4) and constants (..., …) → (..., d).

        ``poses[..., a, :, :]`` is the a-th pose the instance touches (T_i0, world → frame i).
        A term with ``point_index`` is called as ``residual(poses, points, **constants)`` with
        its world points X_j (..., 3) as the second argument. A term with ``parameters`` also
        gets each group's blocks by the group's name: (..., d) for an index (K,), (..., c, d)
        for an index (K, c). Must be written batched over the leading dims (it is also called
        under ``vmap``).
        """
        raise NotImplementedError(f"{type(self).__name__} must implement residual()")

    def jacobians(self, poses: Tensor, *args: Tensor, **constants: Tensor) -> tuple | None:
        """Optional analytic blocks at the arguments of :meth:`residual`.

        A pose term returns (r (..., d), J (..., d, a, 6)), J[..., :, a, :] = ∂r/∂δ_a for
        T_a ← T_a·Exp(δ_a), columns (ω, v); a term with ``point_index`` returns
        (r, J_poses (..., d, a, 6), J_point (..., d, 3)), J_point = ∂r/∂X for X ← X + δX.
        A term with ``parameters`` appends a dict {group: ∂r/∂x (..., d, d_g) or
        (..., d, c, d_g)} for x ← x + δx. The default (None) means ``jacrev``."""
        return None

    # ----------------------------------------------------------------------------------------
    # Sizes and plumbing

    @property
    def arity(self) -> int:
        """Poses per instance a."""
        return self.pose_index.shape[-1]

    @property
    def slot_index(self) -> Tensor:
        """The reduced-system slots each instance touches, long (…, K, a'): its poses, then
        the slots of its parameter blocks group by group (:mod:`.parameters`); the same tensor
        as ``pose_index`` for a term without parameter blocks, or before :meth:`bind`."""
        slots = getattr(self, "_slot_index", None)
        return self.pose_index if slots is None else slots

    @property
    def slot_arity(self) -> int:
        """Slots per instance a' (the arity without parameter blocks)."""
        return self.slot_index.shape[-1]

    @property
    def has_parameters(self) -> bool:
        """Each instance also touches parameter blocks (``parameters`` was given)."""
        return bool(self.parameter_index)

    @property
    def has_point(self) -> bool:
        """Each instance also touches one world point (``point_index`` was given)."""
        return self.point_index is not None

    @property
    def num_instances(self) -> int:
        """Instances K."""
        return self.pose_index.shape[-2]

    def tensors(self) -> dict[str, Tensor]:
        """The floating tensors the cost depends on, by name: ``constants.<name>``, ``weight``,
        ``information`` and ``loss.<attribute>`` (e.g. a tensor scale of the robust kernel).

        The implicit backward of :func:`torchslam.solve_differentiable` differentiates with
        respect to exactly these; a tensor a subclass keeps elsewhere is a constant there.
        """
        out = {f"constants.{k}": v for k, v in self.constants.items() if v.is_floating_point()}
        for name in ("weight", "information"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        for name, value in losses.tensor_attributes(self.loss).items():
            out[f"loss.{name}"] = value
        return out

    def replace_tensors(self, tensors: Mapping[str, Tensor]) -> Term:
        """A shallow copy with some of :meth:`tensors` replaced (same names)."""
        new = copy.copy(self)
        new.constants = dict(self.constants)
        loss_values = {}
        for name, value in tensors.items():
            if name.startswith("constants."):
                new.constants[name[len("constants.") :]] = value
            elif name.startswith("loss."):
                loss_values[name[len("loss.") :]] = value
            else:
                setattr(new, name, value)
        new.loss = losses.with_tensor_attributes(self.loss, loss_values)
        return new

    def apply(self, fn) -> Term:
        """A shallow copy with ``fn`` applied to every tensor (indices, mask, constants,
        weight, information, the loss's tensor attributes): moves or casts the term."""
        new = copy.copy(self)
        new.pose_index = fn(self.pose_index)
        new.point_index = None if self.point_index is None else fn(self.point_index)
        new.parameter_index = {k: fn(v) for k, v in self.parameter_index.items()}
        if getattr(self, "_slot_index", None) is not None:
            new._slot_index = fn(self._slot_index)
        new.valid = fn(self.valid)
        new.constants = {k: fn(v) for k, v in self.constants.items()}
        new.weight = None if self.weight is None else fn(self.weight)
        new.information = None if self.information is None else fn(self.information)
        moved = {k: fn(v) for k, v in losses.tensor_attributes(self.loss, False).items()}
        new.loss = losses.with_tensor_attributes(self.loss, moved)
        return new

    def bind(
        self,
        batch_size: int,
        num_poses: int,
        like: Tensor,
        num_points: int | None = None,
        parameters: ParameterLayout | None = None,
    ) -> Term:
        """A copy with every tensor expanded to batch ``batch_size``, checked against a problem
        of ``num_poses`` poses (and ``num_points`` points, needed by a term with
        ``point_index``; and the parameter groups of ``parameters``, needed by a term with
        ``parameters``) whose floating tensors are like ``like`` (dtype, device)."""
        fn = type(self).__name__
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 0:
            raise ValueError(f"{fn}.bind: 'batch_size' must be an int ≥ 0, got {batch_size!r}")
        if isinstance(num_poses, bool) or not isinstance(num_poses, int) or num_poses < 1:
            raise ValueError(f"{fn}.bind: 'num_poses' must be an int ≥ 1, got {num_poses!r}")
        if self.has_point and (
            isinstance(num_points, bool) or not isinstance(num_points, int) or num_points < 0
        ):
            raise ValueError(
                f"{fn}.bind: a term with 'point_index' needs 'num_points', an int ≥ 0, "
                f"got {num_points!r}"
            )
        _checks.check_tensor(f"{fn}.bind", "like", like)
        B = batch_size
        batched = self.pose_index.dim() == 3
        if batched and self.pose_index.shape[0] not in (1, B):
            raise ValueError(
                f"{fn}: 'pose_index' has batch size {self.pose_index.shape[0]}, the problem has "
                f"B = {B} (give (K, a), (1, K, a) or (B, K, a))"
            )
        for name, value in self.tensors().items():
            if value.dtype != like.dtype or value.device != like.device:
                raise TypeError(
                    f"{fn}: '{name}' must have the problem's dtype and device ({like.dtype}, "
                    f"{like.device}), got ({value.dtype}, {value.device})"
                )

        def expand(x: Tensor) -> Tensor:
            x = x if batched else x[None]
            return x.expand(B, *x.shape[1:])

        new = copy.copy(self)
        new.pose_index = expand(self.pose_index.to(like.device))
        new.valid = expand(self.valid.to(like.device))
        bad = new.valid & ((new.pose_index < 0) | (new.pose_index >= num_poses)).any(-1)
        if bool(bad.any()):
            b, k = (int(i) for i in bad.nonzero()[0])
            raise ValueError(
                f"{fn}: 'pose_index' out of range [0, {num_poses}): problem {b}, instance {k} "
                f"has {new.pose_index[b, k].tolist()}"
            )
        # Padding instances are inert, whatever they hold (NaN, Inf, any index): their poses
        # are pose 0 here; on every use (masked_constants, masked_weighting) their constants
        # are those of a valid instance (values residual() handles), weight 1, information I,
        # by torch.where, so no NaN reaches a value or a gradient.
        flat_valid = new.valid.reshape(-1)
        first = int(flat_valid.to(torch.uint8).argmax()) if flat_valid.numel() > 0 else 0
        new._fill_instance = first if flat_valid.numel() > 0 and bool(flat_valid[first]) else -1
        new.pose_index = torch.where(new.valid[..., None], new.pose_index, 0)
        if self.has_point:
            new.point_index = expand(self.point_index.to(like.device))
            bad = new.valid & ((new.point_index < 0) | (new.point_index >= num_points))
            if bool(bad.any()):
                b, k = (int(i) for i in bad.nonzero()[0])
                raise ValueError(
                    f"{fn}: 'point_index' out of range [0, {num_points}): problem {b}, "
                    f"instance {k} has {int(new.point_index[b, k])}"
                )
            new.point_index = torch.where(new.valid, new.point_index, 0)
        new.parameter_index = {}
        slots = [new.pose_index]
        for name, index in self.parameter_index.items():
            if parameters is None or name not in parameters.names:
                known = [] if parameters is None else list(parameters.names)
                raise ValueError(
                    f"{fn}: the term touches parameter group {name!r}, which the problem does not "
                    f"have (its groups: {known}); give it as parameters={{{name!r}: …}}"
                )
            index = expand(index.to(like.device))
            q = parameters.counts[parameters.group(name)]
            outside = (index < 0) | (index >= q)
            bad = new.valid & (outside.any(-1) if outside.dim() == 3 else outside)
            if bool(bad.any()):
                b, k = (int(i) for i in bad.nonzero()[0])
                raise ValueError(
                    f"{fn}: 'parameters[{name!r}]' index out of range [0, {q}): problem {b}, "
                    f"instance {k} has {index[b, k].tolist()}"
                )
            keep = new.valid if index.dim() == 2 else new.valid[..., None]
            index = torch.where(keep, index, 0)
            new.parameter_index[name] = index
            block = index if index.dim() == 3 else index[..., None]
            slots.append(parameters.slot_index(name, block).flatten(2))
        new._slot_index = torch.cat(slots, dim=-1) if len(slots) > 1 else None
        new.constants = {k: expand(v) for k, v in self.constants.items()}
        new.weight = None if self.weight is None else expand(self.weight)
        new.information = None if self.information is None else expand(self.information)
        if new.num_instances > 0 and B > 0:
            # One instance, batch dims (1, 1): poses (1, 1, a, 4, 4), points (1, 1, 3),
            # constants (1, 1, …); only the shape and dtype of the value are used.
            one = {
                name: like.new_zeros(
                    1, 1, *index.shape[2:], parameters.dims[parameters.group(name)]
                )
                for name, index in new.parameter_index.items()
            }
            r = _call_residual(
                new,
                se3.identity(1, 1, new.arity, dtype=like.dtype, device=like.device),
                like.new_zeros(1, 1, 3),
                {k: v[:1, :1] for k, v in masked_constants(new).items()},
                one,
            )
            if not isinstance(r, Tensor) or r.dim() != 3 or tuple(r.shape[:2]) != (1, 1):
                got = tuple(r.shape) if isinstance(r, Tensor) else _checks.describe(r)
                points = ", points (1, 1, 3)" if new.has_point else ""
                raise ValueError(
                    f"{fn}.residual must return shape (..., d) for poses (..., a, 4, 4); for "
                    f"one instance (1, 1, a, 4, 4){points} it returned {got}"
                )
            if r.dtype != like.dtype:
                raise TypeError(
                    f"{fn}.residual must return the problem's dtype {like.dtype}, got {r.dtype}"
                )
            d = new.residual_dim = r.shape[-1]
            if new.information is not None:
                if tuple(new.information.shape[-2:]) != (d, d):
                    raise ValueError(
                        f"{fn}: argument 'information' must be ({d}, {d}) per instance for its "
                        f"{d}-dim residual, got {tuple(new.information.shape[-2:])}"
                    )
        return new

    def __repr__(self) -> str:
        weighting = "information" if self.information is not None else "weight"
        if self.information is None and self.weight is None:
            weighting = "unit"
        point = ", point" if self.has_point else ""
        return (
            f"{type(self).__name__}(instances={self.num_instances}, arity={self.arity}{point}, "
            f"weighting={weighting}, loss={self.loss!r})"
        )


def bind_terms(
    fn: str,
    terms: object,
    B: int,
    m: int,
    like: Tensor,
    n: int = 0,
    parameters: ParameterLayout | None = None,
) -> tuple[Term, ...]:
    """The terms of a problem bound to its batch B, m poses and n points (:meth:`Term.bind`),
    after checking that ``terms`` is a list or tuple of :class:`Term` (errors name ``fn``)."""
    if terms is None:
        return ()
    terms = _checks.check_sequence(
        fn,
        "terms",
        terms,
        Term,
        "torchslam.Term objects",
        "a torchslam.Term (e.g. RelativePoseTerm)",
    )
    return tuple(term.bind(B, m, like, n, parameters) for term in terms)


def _check_finite_where_valid(fn: str, what: str, value: Tensor, valid: Tensor) -> None:
    """ValueError if ``value`` (lead + tail) has a NaN or Inf at a valid instance."""
    lead = valid.dim()
    finite = torch.isfinite(value.detach()).flatten(lead) if value.dim() > lead else None
    finite = torch.isfinite(value.detach()) if finite is None else finite.all(-1)
    bad = valid.to(value.device) & ~finite
    if bool(bad.any()):
        where = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"{fn}: {what} has a non-finite value (NaN or Inf) at valid instance {where}; "
            "remove the instance or mark it invalid with 'valid'"
        )


def masked_constants(term: Term) -> dict[str, Tensor]:
    """The constants of a bound term with those of a valid instance on its padding instances
    (zeros when no instance is valid), by ``torch.where``: what residual() is called with."""
    fill = getattr(term, "_fill_instance", None)
    if fill is None or term_all_valid(term):  # not bound, or no padding: as given
        return dict(term.constants)
    B, K = term.valid.shape
    out = {}
    for name, v in term.constants.items():
        tail = v.shape[2:]
        one = v.reshape(B * K, *tail)
        value = (
            one[fill]
            if fill >= 0
            else term.padding_constant(name, one[0] if len(one) else v.new_zeros(tail))
        )
        out[name] = torch.where(term.valid.reshape(B, K, *([1] * len(tail))), v, value)
    return out


def masked_weighting(term: Term) -> tuple[Tensor | None, Tensor | None]:
    """(weight (B, K) with 1, information (B, K, d, d) with I, on the padding instances) of
    a bound term; None where the term has none."""
    weight, information = term.weight, term.information
    if weight is not None:
        weight = torch.where(term.valid, weight, 1.0)
    if information is not None:
        eye = torch.eye(information.shape[-1], dtype=information.dtype, device=information.device)
        information = torch.where(term.valid[..., None, None], information, eye)
    return weight, information


def term_poses(term: Term, poses: Tensor) -> Tensor:
    """The poses each instance touches: poses (B, m, 4, 4) → (B, K, a, 4, 4) (bound term)."""
    B, m = poses.shape[:2]
    flat = torch.arange(B, device=poses.device)[:, None, None] * m + term.pose_index
    rows = poses.reshape(B * m, 16).index_select(0, flat.reshape(-1))  # 2-D: a faster gather
    return rows.reshape(*flat.shape, 4, 4)


def term_points(term: Term, points: Tensor) -> Tensor:
    """The point each instance touches: points (B, n, 3) → (B, K, 3) (bound point term)."""
    B, n = points.shape[:2]
    flat = torch.arange(B, device=points.device)[:, None] * n + term.point_index
    return points.reshape(B * n, 3).index_select(0, flat.reshape(-1)).reshape(*flat.shape, 3)


def _call_residual(
    term: Term,
    poses: Tensor,
    points: Tensor | None,
    constants: Mapping[str, Tensor],
    parameters: Mapping[str, Tensor] | None = None,
) -> Tensor:
    """``term.residual`` with the points as second argument for a point term and the
    parameter blocks by name."""
    extra = dict(parameters or {})
    if term.has_point:
        return term.residual(poses, points, **extra, **constants)
    return term.residual(poses, **extra, **constants)


def _parameter_indices(
    fn: str, parameters: object, lead: tuple[int, ...], device: torch.device
) -> dict[str, Tensor]:
    """The checked ``parameters`` argument of a term: {group: long index lead or lead + (c,)}."""
    if parameters is None:
        return {}
    if not isinstance(parameters, Mapping):
        raise TypeError(
            f"{fn}: argument 'parameters' must be a mapping group name → block index of shape "
            f"{lead} (or {lead} + (c,)), got {_checks.describe(parameters)}"
        )
    out = {}
    for name, index in parameters.items():
        if not isinstance(name, str) or not name.isidentifier():
            raise TypeError(f"{fn}: parameter group names must be identifiers, got {name!r}")
        if not isinstance(index, Tensor):
            raise TypeError(
                f"{fn}: 'parameters[{name!r}]' must be an integer torch.Tensor of shape {lead}, "
                f"got {_checks.describe(index)}"
            )
        _checks.check_integer_tensor(fn, f"parameters[{name!r}]", index)
        if tuple(index.shape[: len(lead)]) != lead or index.dim() not in (len(lead), len(lead) + 1):
            raise ValueError(
                f"{fn}: 'parameters[{name!r}]' must have shape {lead} (one block per instance) "
                f"or {lead} + (c,), got {tuple(index.shape)}"
            )
        out[name] = index.to(device, torch.long)
    return out


def term_parameters(term: Term, layout: ParameterLayout, slots: Tensor) -> dict[str, Tensor]:
    """The parameter blocks each instance touches, {group: (B, K, d) or (B, K, c, d)}, from
    the slot values (B, S, 6) of the problem's blocks (bound term)."""
    if not term.parameter_index:
        return {}
    if layout is None or slots is None:
        raise ValueError(
            f"{type(term).__name__} touches parameter blocks {sorted(term.parameter_index)}; "
            "give their values (the problem's parameter_blocks)"
        )
    values = layout.unpack(slots)
    out = {}
    for name, index in term.parameter_index.items():
        v = values[name]
        B, q, d = v.shape
        batch = torch.arange(B, device=index.device).reshape(B, *[1] * (index.dim() - 1))
        flat = (batch * q + index).reshape(-1)
        out[name] = v.reshape(B * q, d).index_select(0, flat).reshape(*index.shape, d)
    return out


def term_blocks(
    term: Term,
    poses: Tensor,
    points: Tensor | None = None,
    mode: str = "analytic",
    parameters: Mapping[str, Tensor] | None = None,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Residuals and Jacobian blocks of a bound term at its poses and points.

    Args:
        term: a bound term (:meth:`Term.bind`).
        poses: the poses each instance touches, (B, K, a, 4, 4) (:func:`term_poses`).
        points: the point each instance touches, (B, K, 3) (:func:`term_points`); only for a
            term with ``point_index``.
        mode: ``"analytic"`` uses :meth:`Term.jacobians` when the term has them, else
            ``jacrev``; ``"jacrev"`` always differentiates :meth:`Term.residual` with
            ``torch.func.jacrev`` w.r.t. the right perturbations δ_a of the poses
            (T_a ← T_a·Exp(δ_a)) and the Euclidean increments of the point and of the
            parameter blocks, at zero.
        parameters: the parameter blocks each instance touches (:func:`term_parameters`),
            for a term with ``parameters``.

    Returns:
        (r (B, K, d), J (B, K, d, a', 6), J_point (B, K, d, 3) or None for a pose term): J
        over the instance's slots (:attr:`Term.slot_index`): the a pose blocks, then each
        parameter block's ∂r/∂x in its ⌈d_g/6⌉ slots (zero columns past d_g).
    """
    if not term.has_parameters:
        return _pose_point_blocks(term, poses, points, mode, {})
    parameters = dict(parameters or {})
    missing = [k for k in term.parameter_index if k not in parameters]
    if missing:
        raise TypeError(
            f"term_blocks: {type(term).__name__} touches parameter group {missing[0]!r}; give "
            "its blocks (term_parameters)"
        )
    r, J, J_point, J_params = _pose_point_blocks(term, poses, points, mode, parameters)
    B, K, d = r.shape
    parts = [J]
    for name in term.parameter_index:
        Jg = J_params[name]
        single = Jg.dim() == 4
        if single:
            Jg = Jg[..., None, :]
        width = -(-Jg.shape[-1] // SLOT) * SLOT
        if width != Jg.shape[-1]:
            Jg = torch.nn.functional.pad(Jg, (0, width - Jg.shape[-1]))
        parts.append(Jg.reshape(B, K, d, -1, SLOT))
    return r, torch.cat(parts, dim=3), J_point


def term_rows(
    term: Term,
    poses: Tensor,
    points: Tensor,
    mode: str,
    parameters: Mapping[str, Tensor] | None,
    free_point: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """(r (B, K, d), J (B, K, d, 6a' + 3)) of a point term: :func:`term_blocks`' slot blocks
    flattened, then the point's 3 columns (times ``free_point`` (B, K) when given), written
    into one tensor (no concatenations). Outside autograd and ``torch.func`` transforms
    (in-place writes into a new tensor); elsewhere :func:`term_blocks` and a concatenation."""
    plain = not torch.is_grad_enabled() and not any(
        torch._C._functorch.is_functorch_wrapped_tensor(x) for x in (poses, points)
    )
    if not plain:
        r, J, J_point = term_blocks(term, poses, points, mode, parameters)
        if free_point is not None:
            J_point = J_point * free_point[..., None, None]
        return r, torch.cat((J.flatten(-2), J_point), -1)
    parameters = dict(parameters or {})
    out = _pose_point_blocks(term, poses, points, mode, parameters)
    r, J, J_point = out[:3]
    B, K, d = r.shape
    a = J.shape[3]
    blocks = []
    width = 6 * a
    for name in term.parameter_index if term.has_parameters else ():
        Jg = out[3][name]
        if Jg.dim() == 4:
            Jg = Jg[..., None, :]
        slots = -(-Jg.shape[-1] // SLOT)
        blocks.append((width, Jg, slots))
        width += Jg.shape[-2] * slots * SLOT
    rows = r.new_empty(B, K, d, width + 3)
    rows[..., : 6 * a].view(B, K, d, a, 6).copy_(J)
    for start, Jg, slots in blocks:
        q, size = Jg.shape[-2:]
        part = rows[..., start : start + q * slots * SLOT].view(B, K, d, q, slots * SLOT)
        part[..., :size].copy_(Jg)
        part[..., size:].zero_()
    if free_point is None:
        rows[..., width:].copy_(J_point)
    else:
        torch.mul(J_point, free_point[..., None, None], out=rows[..., width:])
    return r, rows


def _pose_point_blocks(term, poses, points, mode, parameters):
    """:func:`term_blocks` before the parameter blocks' slots: (r, J_poses, J_point) without
    parameters, (r, J_poses, J_point, {group: ∂r/∂x}) with."""
    with_parameters = term.has_parameters
    name = type(term).__name__
    if term.has_point and not isinstance(points, Tensor):
        raise TypeError(f"term_blocks: {name} touches points; give its points (B, K, 3)")
    if not term.has_point:
        points = None
    constants = masked_constants(term)
    B, K, a = poses.shape[:3]
    d = getattr(term, "residual_dim", None)
    if mode == "analytic":
        if term.has_point:
            out = term.jacobians(poses, points, **parameters, **constants)
        else:
            out = term.jacobians(poses, **parameters, **constants)
        if out is not None:
            fn = f"{name}.jacobians"
            size = (3 if term.has_point else 2) + with_parameters
            if not (isinstance(out, tuple) and len(out) == size):
                what = (
                    "(residuals, pose blocks, point blocks"
                    if term.has_point
                    else ("(residuals, blocks")
                )
                what += ", {group: parameter blocks})" if with_parameters else ")"
                raise TypeError(
                    f"{fn} must return None or a tuple {what}, got {_checks.describe(out)}"
                )
            r = out[0]
            _check_term_output(fn, "residuals", r, (B, K, d), poses)
            _check_term_output(fn, "blocks", out[1], (B, K, r.shape[-1], a, 6), poses)
            J_point = None
            if term.has_point:
                J_point = out[2]
                _check_term_output(fn, "point blocks", J_point, (B, K, r.shape[-1], 3), poses)
            if not with_parameters:
                return r, out[1], J_point
            J_params = out[-1]
            if not isinstance(J_params, Mapping) or set(J_params) != set(parameters):
                raise TypeError(
                    f"{fn}: its last value must be a dict with the blocks of the parameter "
                    f"groups {sorted(parameters)}, got {_checks.describe(J_params)}"
                )
            for group, value in parameters.items():
                shape = (B, K, r.shape[-1], *value.shape[2:])
                _check_term_output(fn, f"parameter blocks {group!r}", J_params[group], shape, poses)
            return r, out[1], J_point, dict(J_params)
    if with_parameters:
        return _jacrev_with_parameters(term, poses, points, constants, parameters)
    r = _call_residual(term, poses, points, constants)
    _check_term_output(f"{name}.residual", "its return value", r, (B, K, d), poses)
    d = r.shape[-1]
    if B * K == 0:
        J_point = r.new_zeros(B, K, d, 3) if term.has_point else None
        return r, r.new_zeros(B, K, d, a, 6), J_point

    if a == 0:  # a term on a point only (e.g. a point prior)
        no_poses = poses.new_zeros(0, 4, 4)
        (J_point,) = right_jacobian_jacrev(
            lambda X, **c: term.residual(no_poses, X, **c),
            (),
            (points,),
            constants=constants,
            batch_dims=2,
        )
        J = J_point.new_zeros(B, K, d, 0, 6)
    elif term.has_point:
        J, J_point = right_jacobian_jacrev(
            lambda T, X, **c: term.residual(T, X, **c),
            (poses,),
            (points,),
            constants=constants,
            batch_dims=2,
        )
    else:
        (J,) = right_jacobian_jacrev(
            lambda T, **c: term.residual(T, **c), (poses,), constants=constants, batch_dims=2
        )
    if tuple(J.shape) != (B, K, d, a, 6):
        raise ValueError(
            f"{name}.residual: for one instance (poses (a, 4, 4) = {(a, 4, 4)}, no batch dims) "
            f"it must return shape (d,) = ({d},), got {tuple(J.shape[2:-2])}; compute it "
            "batched over all leading dims (use '...')"
        )
    return r, J, (J_point if term.has_point else None)


def _jacrev_with_parameters(term, poses, points, constants, parameters):
    """(r, J_poses, J_point, {group: ∂r/∂x}) of a term with parameter blocks by ``jacrev``
    (the parameter blocks are Euclidean arguments of :func:`right_jacobian_jacrev`)."""
    names = tuple(parameters)
    r = _call_residual(term, poses, points, constants, parameters)
    B, K, a = poses.shape[:3]
    d = r.shape[-1]
    _check_term_output(f"{type(term).__name__}.residual", "its return value", r, (B, K, d), poses)
    if B * K == 0:
        J_point = r.new_zeros(B, K, d, 3) if term.has_point else None
        zeros = {k: r.new_zeros(B, K, d, *v.shape[2:]) for k, v in parameters.items()}
        return r, r.new_zeros(B, K, d, a, 6), J_point, zeros
    euclidean = ((points,) if term.has_point else ()) + tuple(parameters[k] for k in names)
    skip = 1 if term.has_point else 0

    def fn(*args, **c):
        T = args[0] if a > 0 else poses.new_zeros(0, 4, 4)
        rest = args[1:] if a > 0 else args
        X = rest[0] if term.has_point else None
        values = dict(zip(names, rest[skip:], strict=True))
        return _call_residual(term, T, X, c, values)

    out = right_jacobian_jacrev(
        fn, (poses,) if a > 0 else (), euclidean, constants=constants, batch_dims=2
    )
    J = out[0] if a > 0 else r.new_zeros(B, K, d, 0, 6)
    rest = out[1:] if a > 0 else out
    J_point = rest[0] if term.has_point else None
    return r, J, J_point, dict(zip(names, rest[skip:], strict=True))


def term_jacobians(term: Term, poses: Tensor, mode: str = "analytic") -> tuple[Tensor, Tensor]:
    """Residuals (B, K, d) and blocks (B, K, d, a, 6) of a bound pose term at its poses
    (B, K, a, 4, 4): :func:`term_blocks` without a point."""
    if term.has_point:
        raise ValueError(
            f"term_jacobians: {type(term).__name__} touches points; use term_blocks(term, "
            "poses, points, mode)"
        )
    r, J, _ = term_blocks(term, poses, None, mode)
    return r, J


def _check_term_output(
    fn: str, what: str, value: object, expected: tuple[int | None, ...], poses: Tensor
) -> None:
    """A user term's residuals (B, K, d) or blocks (B, K, d, a, 6) at the solver's call: a
    tensor of the poses' dtype and device and exactly that shape (``None``: any size)."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{fn}: {what} must be a torch.Tensor, got {_checks.describe(value)}")
    shape = tuple(value.shape)
    if len(shape) != len(expected) or any(
        e is not None and e != g for e, g in zip(expected, shape, strict=True)
    ):
        want = "(" + ", ".join("d" if e is None else str(e) for e in expected) + ")"
        raise ValueError(
            f"{fn}: {what} must have shape {want} for poses {tuple(poses.shape)} "
            f"(B, K, a, 4, 4), got {shape}; compute it batched over all leading dims"
        )
    if value.dtype != poses.dtype or value.device != poses.device:
        raise TypeError(
            f"{fn}: {what} must be {poses.dtype} on {poses.device} like the poses, got "
            f"{value.dtype} on {value.device}"
        )


def _check_measurements(
    fn: str, measurements: object, lead: tuple[int, ...], valid: object = None
) -> None:
    """Measurements of a built-in term: poses of shape lead + (4, 4), rigid transforms at
    the valid instances (padding instances may hold anything)."""
    _checks.check_tensor(fn, "measurements", measurements, (4, 4), min_batch_dims=1, dims="K")
    if tuple(measurements.shape[:-2]) != lead:
        raise ValueError(
            f"{fn}: argument 'measurements' must have shape {lead} + (4, 4) to match "
            f"'pose_index', got {tuple(measurements.shape)}"
        )
    if not _checks.value_checks_active():
        return
    if isinstance(valid, Tensor) and valid.dtype == torch.bool and tuple(valid.shape) == lead:
        measurements = measurements[valid.to(measurements.device)]
    _checks.check_pose_matrix(fn, "measurements", measurements)


def _check_one_pose_index(fn: str, pose_index: object) -> None:
    """The pose index of a term with one pose per instance: an integer tensor (K,) or (B, K)
    (the integer dtype is checked by :class:`Term`)."""
    if not isinstance(pose_index, Tensor):
        raise TypeError(
            f"{fn}: argument 'pose_index' must be a torch.Tensor, got {type(pose_index).__name__}"
        )
    if pose_index.dim() not in (1, 2):
        raise ValueError(
            f"{fn}: argument 'pose_index' must have shape (K,) or (B, K), "
            f"got {tuple(pose_index.shape)}"
        )


def relative_pose_residual(
    T_i: Tensor, T_j: Tensor, Z_ij: Tensor, convention: str = "world_to_frame"
) -> Tensor:
    """The one relative-pose residual, ξ = (ω, v), poses (…, 4, 4) → (…, 6):

    - ``convention="world_to_frame"`` (T_i = T_i0, the solver's poses): r = Log(Z_ij⁻¹ T_i T_j⁻¹),
      Z_ij ≈ T_i T_j⁻¹ (the pose of frame j in frame i);
    - ``"frame_to_world"`` (g2o's body → world vertices): r = Log(Z_ij⁻¹ T_i⁻¹ T_j),
      Z_ij ≈ T_i⁻¹ T_j. With T = T0⁻¹ both are the same number.
    """
    if convention == "frame_to_world":
        return se3.log(matmul(se3.inverse(Z_ij), matmul(se3.inverse(T_i), T_j)))
    return se3.log(matmul(matmul(se3.inverse(Z_ij), T_i), se3.inverse(T_j)))


def relative_pose_jacobians(
    T_i: Tensor, T_j: Tensor, Z_ij: Tensor, convention: str = "world_to_frame"
) -> tuple[Tensor, Tensor, Tensor]:
    """(r, ∂r/∂δ_i, ∂r/∂δ_j) of :func:`relative_pose_residual` for right perturbations
    T ← T·Exp(δ), shapes (…, 6), (…, 6, 6), (…, 6, 6); the derivation is in
    :class:`RelativePoseTerm`."""
    r = relative_pose_residual(T_i, T_j, Z_ij, convention)
    Jr_inv = se3.jr_inv(r, form="fast")
    if convention == "frame_to_world":
        # E = Z⁻¹ T_i⁻¹ T_j: ∂r/∂δ_j = Jr⁻¹(r), ∂r/∂δ_i = −Jr⁻¹(r)·Ad(T_j⁻¹ T_i).
        J_i = matmul(-Jr_inv, se3.adjoint(matmul(se3.inverse(T_j), T_i)))
        return r, J_i, Jr_inv
    J_i = matmul(Jr_inv, se3.adjoint(T_j))
    return r, J_i, -J_i


def pose_prior_residual(T: Tensor, Z: Tensor) -> Tensor:
    """r = Log(Z⁻¹ · T), ξ = (ω, v), zero when T = Z; poses (…, 4, 4) in either convention
    (as long as Z is in the same one) → (…, 6)."""
    return se3.log(matmul(se3.inverse(Z), T))


class RelativePoseTerm(Term):
    """Relative-pose (between) terms r_ij = Log(Z_ij⁻¹ · T_i · T_j⁻¹), ξ = (ω, v).

    T_i = T_i0 maps world to frame i, so T_i T_j⁻¹ is the pose of frame j in frame i and the
    residual is zero when it equals the measurement Z_ij (ICP of scan j onto scan i, odometry,
    a loop closure). Equivalently, with g2o's body → world vertices T^g = T⁻¹,
    r = Log(Z_ij⁻¹ (T_i^g)⁻¹ T_j^g), the residual of :mod:`torchslam.posegraph.between`.

    Jacobians (right perturbations; Jr the right Jacobian of SE(3), Exp(r + d) ≈
    Exp(r) Exp(Jr(r) d), hence Log(Exp(r) Exp(u)) = r + Jr⁻¹(r) u + O(|u|²)). With
    E = Z⁻¹ T_i T_j⁻¹ and T Exp(δ) T⁻¹ = Exp(Ad(T) δ):

    - T_i ← T_i Exp(δ_i): E ← Z⁻¹ T_i Exp(δ_i) T_j⁻¹ = E · Exp(Ad(T_j) δ_i), so
      ∂r/∂δ_i = Jr⁻¹(r) · Ad(T_j);
    - T_j ← T_j Exp(δ_j): T_j⁻¹ ← Exp(−δ_j) T_j⁻¹, E ← E · Exp(−Ad(T_j) δ_j), so
      ∂r/∂δ_j = −Jr⁻¹(r) · Ad(T_j).

    With ``convention="frame_to_world"`` the poses the solver holds are the body → world
    vertices themselves (as g2o, GTSAM and :func:`torchslam.posegraph.solve_pose_graph`
    keep them, so the right perturbation moves the vertex): r = Log(Z_ij⁻¹ T_i⁻¹ T_j) with
    Z_ij ≈ T_i⁻¹ T_j, ∂r/∂δ_j = Jr⁻¹(r) and, through T_i⁻¹ ← Exp(−δ_i) T_i⁻¹ and
    A = T_j⁻¹ T_i, ∂r/∂δ_i = −Jr⁻¹(r) · Ad(T_j⁻¹ T_i). A
    :class:`torchslam.PointMapProblem`'s point observations need T_i0, the default.

    Args:
        pose_index: (i, j) of each term, integer (K, 2) or (B, K, 2).
        measurements: Z_ij ≈ T_i0 T_j0⁻¹ (or T_i⁻¹ T_j, frame_to_world), (K, 4, 4) or
            (B, K, 4, 4).
        information: Ω_ij in (ω, v) order, (…, K, 6, 6); or ``weight`` (…, K); default 1.
        loss: as :class:`Term`.
        valid: as :class:`Term`.
        convention: which pose the solver's poses are: ``"world_to_frame"`` (T_i0, default)
            or ``"frame_to_world"``.
    """

    def __init__(
        self,
        pose_index: Tensor,
        measurements: Tensor,
        *,
        information: Tensor | None = None,
        weight: Tensor | None = None,
        loss: object | None = None,
        valid: Tensor | None = None,
        convention: str = "world_to_frame",
    ) -> None:
        fn = "RelativePoseTerm"
        if convention not in ("world_to_frame", "frame_to_world"):
            raise ValueError(
                f"{fn}: argument 'convention' must be 'world_to_frame' or 'frame_to_world', "
                f"got {convention!r}"
            )
        self.convention = convention
        if isinstance(pose_index, Tensor) and pose_index.shape[-1:] != (2,):
            raise ValueError(
                f"{fn}: argument 'pose_index' must have shape (K, 2) or (B, K, 2), "
                f"got {tuple(pose_index.shape)}"
            )
        if isinstance(pose_index, Tensor):
            _check_measurements(fn, measurements, tuple(pose_index.shape[:-1]), valid)
        super().__init__(
            pose_index,
            {"measurements": measurements},
            weight=weight,
            information=information,
            loss=loss,
            valid=valid,
        )

    def padding_constant(self, name: str, like: Tensor) -> Tensor:
        if name == "measurements":  # a rigid transform: the identity
            return torch.eye(4, dtype=like.dtype, device=like.device).expand_as(like).clone()
        return super().padding_constant(name, like)

    def residual(self, poses: Tensor, measurements: Tensor) -> Tensor:
        return relative_pose_residual(
            poses[..., 0, :, :], poses[..., 1, :, :], measurements, self.convention
        )

    def jacobians(self, poses: Tensor, measurements: Tensor) -> tuple[Tensor, Tensor]:
        r, J_i, J_j = relative_pose_jacobians(
            poses[..., 0, :, :], poses[..., 1, :, :], measurements, self.convention
        )
        return r, torch.stack((J_i, J_j), dim=-2)


class PosePriorTerm(Term):
    """Pose priors r = Log(Z⁻¹ · T_i), zero when T_i0 = Z; ∂r/∂δ = Jr⁻¹(r) (T ← T·Exp(δ)).

    Args:
        pose_index: the pose of each prior, integer (K,) or (B, K).
        measurements: prior poses Z ≈ T_i0, (K, 4, 4) or (B, K, 4, 4).
        information: Ω in (ω, v) order, (…, K, 6, 6); or ``weight`` (…, K); default 1.
        loss: as :class:`Term`.
        valid: as :class:`Term`.
    """

    def __init__(
        self,
        pose_index: Tensor,
        measurements: Tensor,
        *,
        information: Tensor | None = None,
        weight: Tensor | None = None,
        loss: object | None = None,
        valid: Tensor | None = None,
    ) -> None:
        fn = "PosePriorTerm"
        _check_one_pose_index(fn, pose_index)
        _check_measurements(fn, measurements, tuple(pose_index.shape), valid)
        super().__init__(
            pose_index[..., None],
            {"measurements": measurements},
            weight=weight,
            information=information,
            loss=loss,
            valid=valid,
        )

    def padding_constant(self, name: str, like: Tensor) -> Tensor:
        if name == "measurements":  # a rigid transform: the identity
            return torch.eye(4, dtype=like.dtype, device=like.device).expand_as(like).clone()
        return super().padding_constant(name, like)

    def residual(self, poses: Tensor, measurements: Tensor) -> Tensor:
        return pose_prior_residual(poses[..., 0, :, :], measurements)

    def jacobians(self, poses: Tensor, measurements: Tensor) -> tuple[Tensor, Tensor]:
        r = self.residual(poses, measurements)
        return r, se3.jr_inv(r, form="fast")[..., None, :]


def point_observation_jacobians(T: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
    """Blocks of the ICP-SLAM point observation r = X_ij − T_i0 X_j (seed eq. 1.1).

    With T ← T·Exp(δ), T Exp(δ) X ≈ T (X + ω × X + v), so ∂r/∂δ = [R [X]× | −R] and
    ∂r/∂X = −R.

    Args:
        T: observing poses T_i0, (..., 4, 4); points: world points X_j, (..., 3).

    Returns:
        (J_r_xi (..., 3, 6), J_r_point (..., 3, 3)).
    """
    R = T[..., :3, :3]
    return torch.cat((R @ so3.hat(points), -R), dim=-1), -R


class PointObservationTerm(Term):
    """Point observations r_k = X_k − T_i X_j (seed eq. 1.1) as a term: the residual of the
    problem's own observations (:class:`torchslam.PointMapProblem`, which keeps them in its
    data for the structured fast path), here for one more set of observations with their own
    weights or robust kernel. Blocks: :func:`point_observation_jacobians`.

    Args:
        pose_index: observing pose i of each observation, integer (K,) or (B, K).
        point_index: observed world point j, integer (K,) or (B, K).
        observations: X_k, the point in frame i, (K, 3) or (B, K, 3).
        information: Ω (…, K, 3, 3); or ``weight`` (…, K); default 1.
        loss: as :class:`Term`.
        valid: as :class:`Term`.
    """

    def __init__(
        self,
        pose_index: Tensor,
        point_index: Tensor,
        observations: Tensor,
        *,
        information: Tensor | None = None,
        weight: Tensor | None = None,
        loss: object | None = None,
        valid: Tensor | None = None,
    ) -> None:
        fn = "PointObservationTerm"
        _check_one_pose_index(fn, pose_index)
        lead = tuple(pose_index.shape)
        _checks.check_tensor(fn, "observations", observations, (3,))
        if tuple(observations.shape[:-1]) != lead:
            raise ValueError(
                f"{fn}: argument 'observations' must have shape {lead} + (3,) to match "
                f"'pose_index', got {tuple(observations.shape)}"
            )
        super().__init__(
            pose_index[..., None],
            {"observations": observations},
            point_index=point_index,
            weight=weight,
            information=information,
            loss=loss,
            valid=valid,
        )

    def residual(self, poses: Tensor, points: Tensor, observations: Tensor) -> Tensor:
        return observations - se3.act(poses[..., 0, :, :], points)

    def jacobians(
        self, poses: Tensor, points: Tensor, observations: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        J_xi, J_point = point_observation_jacobians(poses[..., 0, :, :], points)
        return self.residual(poses, points, observations), J_xi[..., None, :], J_point


def _cached(term: Term, name: str, tensors: tuple[Tensor, ...], compute):
    """``compute()`` once per term while ``tensors`` are the same objects, unedited in place
    (their versions), kept in the term's ``__dict__`` under ``name``; not under torch.func."""
    if not all(_inference.cacheable(t) for t in tensors):  # no version counter to check
        return compute()
    versions = tuple(t._version for t in tensors)
    cached = term.__dict__.get(name)
    if (
        cached is not None
        and all(a is b for a, b in zip(cached[0], tensors, strict=True))
        and cached[1] == versions
    ):
        return cached[2]
    with _inference.outside():  # kept on the term: normal tensors, even made in a solve
        value = compute()
    if not any(torch._C._functorch.is_functorch_wrapped_tensor(t) for t in tensors):
        term.__dict__[name] = (tensors, versions, value)
    return value


def term_all_valid(term: Term) -> bool:
    """Whether no instance of the term is padding (then masking can be skipped); one host
    read per term and mask, cached."""
    return _cached(term, "_all_valid_cache", (term.valid,), lambda: bool(term.valid.all()))


def term_free_poses(term: Term, fixed_poses: Tensor) -> Tensor | None:
    """Which slots of each instance are free, bool (B, K, a'), for a problem's
    ``fixed_slots`` (B, m + S) (its ``fixed_poses`` (B, m) without parameter blocks); None
    when all are (the common case: no masking needed). Cached per term."""

    def compute() -> Tensor | None:
        B, m = fixed_poses.shape
        batch = torch.arange(B, device=fixed_poses.device)[:, None, None]
        free = ~fixed_poses.reshape(-1)[batch * m + term.slot_index]
        return None if bool(free.all()) else free

    return _cached(term, "_free_poses_cache", (term.slot_index, fixed_poses), compute)


def term_fixed_rows(term: Term, fixed_poses: Tensor) -> tuple[Tensor, Tensor] | None:
    """The instances of a term that touch a fixed pose, as (rows, free): rows (R,) long, their
    flat index b·K + k, and free (R, a) bool, which of their poses are free; None when no
    instance touches a fixed pose. Usually a handful (the gauge's edges): masking those rows
    is cheaper than a pass over every instance. Cached per term."""

    def compute() -> tuple[Tensor, Tensor] | None:
        free = term_free_poses(term, fixed_poses)
        if free is None:
            return None
        free = free.reshape(-1, free.shape[-1])
        rows = torch.nonzero(~free.all(-1))[:, 0]
        return rows, free[rows]

    return _cached(term, "_fixed_rows_cache", (term.slot_index, fixed_poses), compute)


def term_whitening(term: Term) -> Tensor | None:
    """U with UᵀU = Ω per instance (B, K, d, d), √w (B, K), or None for unit weights.

    The factor of a term's information matrices is computed once and reused while the
    tensors are unchanged (same objects, no in-place edit) and need no gradient: a solve
    linearizes the same term every iteration."""
    tensors = (term.weight, term.information, term.valid)
    differentiable = _inference.tracked(*tensors)
    if not all(t is None or _inference.cacheable(t) for t in tensors):
        return whitening(*masked_weighting(term))
    versions = tuple(t._version if t is not None else None for t in tensors)
    cached = getattr(term, "_whitening_cache", None)
    if (
        not differentiable
        and cached is not None
        and all(a is b for a, b in zip(cached[0], tensors, strict=True))
        and cached[1] == versions
    ):
        return cached[2]
    with _inference.outside():  # kept on the term: a normal tensor, even made in a solve
        factor = whitening(*masked_weighting(term))
    if not differentiable and not torch._C._functorch.is_functorch_wrapped_tensor(term.valid):
        # The cache holds the tensors themselves: an identity test cannot match a new one.
        term._whitening_cache = (tensors, versions, factor)
    return factor


def term_squared_norms(term: Term, r: Tensor) -> Tensor:
    """s_k = r_kᵀ Ω_k r_k (B, K), 0 on padding; no square root (exact gradients at w = 0)."""
    weight, information = masked_weighting(term)
    r = torch.where(term.valid[..., None], r, 0.0)
    if information is not None:
        s = (r[..., None, :] @ information @ r[..., None])[..., 0, 0]
    else:
        s = (r * r).sum(-1)
        if weight is not None:
            s = weight * s
    return torch.where(term.valid, s, torch.zeros_like(s))


def term_cost(
    term: Term,
    poses: Tensor,
    points: Tensor | None = None,
    parameters: Mapping[str, Tensor] | None = None,
) -> Tensor:
    """½ Σ_k ρ(s_k) of a bound term at all poses (B, m, 4, 4) and points (B, n, 3, needed by
    a term with ``point_index``), with ``parameters`` its instances' parameter blocks
    (:func:`term_parameters`, for a term with ``parameters``) → (B,). Differentiable."""
    if term.has_point and not isinstance(points, Tensor):
        raise TypeError(
            f"term_cost: {type(term).__name__} touches points; give the points (B, n, 3)"
        )
    X = term_points(term, points) if term.has_point else None
    r = _call_residual(term, term_poses(term, poses), X, masked_constants(term), parameters)
    s = term_squared_norms(term, r)
    if term.loss is not None:
        s = torch.where(term.valid, term.loss(s)[0], torch.zeros_like(s))
    return 0.5 * s.sum(-1)


def terms_cost(
    terms: tuple[Term, ...],
    poses: Tensor,
    points: Tensor | None = None,
    layout: ParameterLayout | None = None,
    slots: Tensor | None = None,
) -> Tensor:
    """Σ over bound terms of :func:`term_cost`, (B,) (zeros without terms); ``layout`` and
    the slot values ``slots`` (B, S, 6) give the parameter blocks of terms that touch them."""
    total = poses.new_zeros(poses.shape[0])
    for term in terms:
        params = term_parameters(term, layout, slots) if term.has_parameters else None
        total = total + term_cost(term, poses, points, params)
    return total
