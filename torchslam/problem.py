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

Ill-posed parts are never dropped silently: when the problem is built, what the observations
and terms cannot determine (a point with < 3 residual entries, a pose with < 3 observed points
or < 6 entries on them and no full-rank pose term to an anchor, a free gauge of poses tied
only to each other) is held fixed, with a ``UserWarning`` naming the problem and the index,
also listed in ``diagnostics`` (:mod:`torchslam.objective.gauge`).

The data (:class:`torchslam.objective.data.PointMapData`), the terms
(:mod:`torchslam.objective.terms`) and the gauge analysis live in :mod:`torchslam.objective`;
this module holds the ``nn.Module`` only.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor, nn

from torchslam import _checks, jacobians, losses
from torchslam._deprecated import callable_tensor
from torchslam._threads import threads_for_entries
from torchslam.lie import se3
from torchslam.objective import data as _data
from torchslam.objective import gauge as _gauge
from torchslam.objective import parameters as _parameters
from torchslam.objective import terms as _terms

__all__ = ["PointMapProblem"]


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
        parameters: parameter blocks, variables beyond poses and points (camera intrinsics,
            calibrations): a mapping group name → initial values (q, d) (shared by the batch)
            or (B, q, d); terms touch them with ``parameters={name: index}``
            (:mod:`torchslam.objective.parameters`). Held as ``parameter_blocks``.
        fixed_parameters: blocks held fixed, group name → bool (q,) or (B, q); default none.

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
        terms: Sequence[_terms.Term] = (),
        parameters: Mapping[str, Tensor] | None = None,
        fixed_parameters: Mapping[str, Tensor] | None = None,
    ) -> None:
        super().__init__()
        fn = "PointMapProblem"
        # numpy arrays are accepted (as by register and the readers): copied to tensors
        like = _checks.first_tensor(poses, points, observations)
        poses, points, pose_index, point_index, observations, valid, weights = (
            _checks.from_numpy(x, like)
            for x in (poses, points, pose_index, point_index, observations, valid, weights)
        )
        fixed_poses, fixed_points = (
            _checks.from_numpy(x, like) for x in (fixed_poses, fixed_points)
        )
        _checks.check_batched(fn, "poses", poses, ("B", "m"), (4, 4))
        _checks.check_batched(fn, "points", points, ("B", "n"), (3,))
        _checks.check_batched(fn, "observations", observations, ("B", "E"), (3,))
        _checks.check_same_kind(fn, poses=poses, points=points, observations=observations)
        B, m = poses.shape[:2]
        n = points.shape[1]
        E = observations.shape[1]
        _data.check_batch(fn, B, points=points, observations=observations)
        if m == 0:
            raise ValueError(
                f"{fn}: a problem needs at least one pose (m ≥ 1); 'poses' has shape "
                f"{tuple(poses.shape)}"
            )
        edges = f" ((B, E) of 'observations' {tuple(observations.shape)})"
        device = observations.device
        pose_index = _data.index_tensor(fn, "pose_index", pose_index, (B, E), device, edges)
        point_index = _data.index_tensor(fn, "point_index", point_index, (B, E), device, edges)
        valid = _data.bool_mask(fn, "valid", valid, (B, E), device, True, edges)
        fixed_poses_given = fixed_poses is not None
        source = f" ((B, m) of 'poses' {tuple(poses.shape)})"
        fixed_poses = _data.bool_mask(
            fn, "fixed_poses", fixed_poses, (B, m), poses.device, False, source
        )
        if not fixed_poses_given:
            fixed_poses = fixed_poses.clone()
            fixed_poses[:, 0] = True
        source = f" ((B, n) of 'points' {tuple(points.shape)})"
        fixed_points = _data.bool_mask(
            fn, "fixed_points", fixed_points, (B, n), points.device, False, source
        )
        losses.check_loss(fn, loss)
        scalar_weights, information = _data.split_weights(fn, weights, B, E, observations)
        values, fixed_blocks = _parameters.check_parameters(
            fn, parameters, B, observations, fixed_parameters
        )
        layout = _parameters.parameter_layout(values, fixed_blocks, m)
        terms = _terms.bind_terms(fn, terms, B, m, observations, n, layout)

        # Small problems' checks on one thread (torchslam._threads).
        with threads_for_entries(max(9 * B * E, 16 * B * m, 3 * B * n)):
            _checks.check_pose_matrix(fn, "poses", poses)
            _checks.check_finite(fn, "points", points)
            self.diagnostics: list[str] = []
            checked = _checks.value_checks_active()
            if checked:
                _data.check_observations(fn, observations, valid, pose_index, point_index, m, n)
                _data.check_weight_values(fn, valid, scalar_weights, information)
                fixed_poses, fixed_points = _gauge.hold_ill_posed_fixed(
                    fn,
                    valid,
                    pose_index,
                    point_index,
                    fixed_poses,
                    fixed_points,
                    self.diagnostics,
                    _gauge.term_links(terms, B) if terms else None,
                    _gauge.point_term_counts(terms, B, m, n),
                )

            # The poses were checked above: the private log (a new tensor) skips checking again.
            self.pose_tangent = nn.Parameter(se3._log(poses.detach()))
            self.points = nn.Parameter(points.detach().clone())
            self.parameter_blocks = nn.ParameterDict(
                {k: nn.Parameter(v) for k, v in values.items()}
            )
            # PointMapData makes the padding inert (index 0, observation 0, weight 1, information
            # I), whatever it holds: NaN, Inf, out-of-range indices.
            self.data = _data.PointMapData(
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
                parameters=layout,
            )
            # Checked above, or deliberately not (built inside validation(False)): a solve does not
            # check these values again (a non-finite observation then shows in the status).
            _data.mark_checked(self.data)

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
        like = _checks.first_tensor(poses, points, observations)
        poses, points, observations, visibility, weights = (
            _checks.from_numpy(x, like) for x in (poses, points, observations, visibility, weights)
        )
        fixed_poses, fixed_points = (
            _checks.from_numpy(x, like) for x in (fixed_poses, fixed_points)
        )
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
        visibility = _data.bool_mask(
            fn, "visibility", visibility, (B, m, n), observations.device, False
        )
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

    @property
    def poses(self) -> Tensor:
        """Current poses T_i0 = Exp(ξ_i), shape (B, m, 4, 4) (differentiable w.r.t. ξ).

        A property, as :attr:`SolveResult.poses` is; the former call ``problem.poses``
        still works for one release, with a ``DeprecationWarning``."""
        return callable_tensor(se3.exp(self.pose_tangent, form="fast"), "PointMapProblem", "poses")

    def raw_residuals(self) -> Tensor:
        """r_e = X_ij − T_i0 X_j, (B, E, 3), zero on padding (differentiable w.r.t. all)."""
        return _data.raw_residuals(self.pose_tangent, self.points, self.data)

    def residuals(self) -> Tensor:
        """Weighted (whitened) residuals Lᵀ r_e with Ω_e = L Lᵀ, (B, E, 3), zero on padding.

        The point observations only: the pose terms' residuals are their own
        (:func:`torchslam.terms.term_jacobians`); :meth:`cost` sums both.
        """
        return self.data.whiten(self.raw_residuals())

    def cost(self) -> Tensor:
        """Per-problem cost ½ Σ_e ρ(r_eᵀ Ω_e r_e) (+ the terms' costs), shape (B,);
        differentiable w.r.t. the poses, points and parameter blocks."""
        slots = None
        if self.data.parameters is not None:
            slots = self.data.parameters.pack(dict(self.parameter_blocks.items()))
        return _data.cost(self.pose_tangent, self.points, self.data, slots)

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
        return _data.jacobian_blocks(self.pose_tangent, self.points, self.data, mode)

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
# Deprecated names: they moved to torchslam.objective (kept for one release, see docs/reference.md).

# Each name of torchslam.objective.data was importable from here.
_MOVED = {name: (_data, name) for name in _data.__all__}


def __getattr__(name: str) -> object:
    if name in _MOVED:
        module, new = _MOVED[name]
        warnings.warn(
            f"torchslam.problem.{name} is deprecated and will be removed: use "
            f"{module.__name__}.{new}",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(module, new)
    raise AttributeError(f"module 'torchslam.problem' has no attribute {name!r}")
