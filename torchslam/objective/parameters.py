"""Parameter blocks: variables beyond poses and points (camera intrinsics, calibrations, …).

A problem's variables are of three types, each with its tangent size and its retraction:

=================  ===============  ===========================  ============================
variable           value            tangent                      retraction x ⊞ δ
=================  ===============  ===========================  ============================
pose T_i0          (4, 4) in SE(3)  6, ξ = (ω, v)                T ← T·Exp(δ) (right)
point X_j          (3,)             3                            X ← X + δ
parameter block    (d,)             d                            x ← x + δ (Euclidean)
=================  ===============  ===========================  ============================

Parameter blocks come in named groups: a group holds q blocks of one size d (e.g.
``"intrinsics"``: one (f, k1, k2) per camera, q = C, d = 3; or one block shared by every
camera, q = 1), and a :class:`torchslam.Term` says which block of each group its instances
touch (``parameters={"intrinsics": index}``). As in Ceres' elimination groups, the points are
eliminated first (Schur complement) and the parameter blocks stay in the reduced system with
the poses.

In the reduced system every variable is a *slot* of 6 tangent entries: a pose is one slot, a
parameter block of size d takes ⌈d/6⌉ slots, placed after the m poses (group by group, block
by block); the entries past d of its last slot are inert (zero Jacobian columns, an identity
diagonal and a zero gradient: their step is exactly zero). :class:`ParameterLayout` holds
that map, fixed once per problem: the solver's blocks, pairs, sparsity patterns, damping,
covariances and the implicit backward then treat poses and parameter blocks alike.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from torchslam import _checks

__all__ = ["SLOT", "ParameterLayout", "check_parameters", "parameter_layout"]

# Tangent entries of one slot of the reduced system (a pose's).
SLOT = 6


@dataclass(frozen=True)
class ParameterLayout:
    """Where the parameter blocks of a problem sit in its reduced system (module doc).

    ``names``, ``counts`` q_g and ``dims`` d_g per group (in the order given); ``num_poses``
    m (the slots of group g's block k start at m + offset_g + k·⌈d_g/6⌉); ``fixed`` the
    blocks held fixed, one bool (B, q_g) per group.
    """

    names: tuple[str, ...]
    counts: tuple[int, ...]
    dims: tuple[int, ...]
    num_poses: int
    fixed: tuple[Tensor, ...]

    def slots_per_block(self, g: int) -> int:
        """⌈d_g / 6⌉."""
        return -(-self.dims[g] // SLOT)

    @functools.cached_property
    def offsets(self) -> tuple[int, ...]:
        """First slot of each group, counted from the first slot after the poses."""
        out, total = [], 0
        for g in range(len(self.names)):
            out.append(total)
            total += self.counts[g] * self.slots_per_block(g)
        return tuple(out)

    @property
    def num_slots(self) -> int:
        """S: slots of all parameter blocks."""
        if not self.names:
            return 0
        g = len(self.names) - 1
        return self.offsets[g] + self.counts[g] * self.slots_per_block(g)

    def group(self, name: str) -> int:
        return self.names.index(name)

    def slot_index(self, name: str, block: Tensor) -> Tensor:
        """Reduced-system slots of blocks ``block`` (any shape, long) of group ``name``:
        (*block.shape, ⌈d/6⌉), counted from 0 over poses and parameters (m + …)."""
        g = self.group(name)
        per = self.slots_per_block(g)
        first = self.num_poses + self.offsets[g] + block * per
        return first[..., None] + torch.arange(per, device=block.device)

    @functools.cached_property
    def active(self) -> Tensor:
        """Which tangent entries of the S slots belong to a block, bool (S, 6) (CPU)."""
        rows = []
        for g in range(len(self.names)):
            per = self.slots_per_block(g)
            one = torch.arange(per * SLOT) < self.dims[g]
            rows.append(one.reshape(per, SLOT).repeat(self.counts[g], 1))
        if not rows:
            return torch.zeros(0, SLOT, dtype=torch.bool)
        return torch.cat(rows)

    def fixed_slots(self) -> Tensor:
        """Slots of fixed blocks, bool (B, S)."""
        parts = [
            f.repeat_interleave(self.slots_per_block(g), dim=-1) for g, f in enumerate(self.fixed)
        ]
        return torch.cat(parts, dim=-1)

    def pack(self, values: Mapping[str, Tensor]) -> Tensor:
        """Slot values (B, S, 6) of the groups' values, each (B, q_g, d_g) (zeros past d)."""
        parts = []
        for g, name in enumerate(self.names):
            v = values[name]
            per = self.slots_per_block(g)
            pad = per * SLOT - self.dims[g]
            if pad:
                v = torch.nn.functional.pad(v, (0, pad))
            parts.append(v.reshape(v.shape[0], self.counts[g] * per, SLOT))
        return torch.cat(parts, dim=1)

    def unpack(self, slots: Tensor) -> dict[str, Tensor]:
        """The groups' values {name: (B, q_g, d_g)} of slot values (B, S, 6)."""
        out = {}
        B = slots.shape[0]
        for g, name in enumerate(self.names):
            per = self.slots_per_block(g)
            start = self.offsets[g]
            part = slots[:, start : start + self.counts[g] * per]
            out[name] = part.reshape(B, self.counts[g], per * SLOT)[..., : self.dims[g]]
        return out

    def apply(self, fn) -> ParameterLayout:
        """The layout with ``fn`` applied to its masks (moves them with the problem)."""
        return ParameterLayout(
            self.names, self.counts, self.dims, self.num_poses, tuple(fn(f) for f in self.fixed)
        )


def check_parameters(
    fn: str,
    parameters: object,
    B: int,
    like: Tensor,
    fixed: object = None,
) -> tuple[dict[str, Tensor], tuple[Tensor, ...]]:
    """Checked parameter groups {name: (B, q, d)} (a group given as (q, d) is shared by the
    batch: expanded) and their fixed masks (B, q) per group (default: none fixed), from the
    user's ``parameters`` (a mapping name → tensor) and ``fixed`` (mapping name → bool (q,) or
    (B, q), or None). Errors name ``fn`` and the argument."""
    if parameters is None:
        return {}, ()
    if not isinstance(parameters, Mapping):
        raise TypeError(
            f"{fn}: argument 'parameters' must be a mapping name → tensor (q, d) or (B, q, d), "
            f"e.g. {{'intrinsics': torch.zeros(C, 3)}}, got {_checks.describe(parameters)}"
        )
    if fixed is not None and not isinstance(fixed, Mapping):
        raise TypeError(
            f"{fn}: argument 'fixed_parameters' must be a mapping name → bool tensor (q,) or "
            f"(B, q), got {_checks.describe(fixed)}"
        )
    fixed = dict(fixed or {})
    unknown = sorted(set(fixed) - set(parameters))
    if unknown:
        raise ValueError(
            f"{fn}: 'fixed_parameters' names {unknown[0]!r}, which is not a parameter group "
            f"(groups: {sorted(parameters)})"
        )
    values, masks = {}, []
    for name, value in parameters.items():
        if not isinstance(name, str) or not name.isidentifier():
            raise TypeError(
                f"{fn}: parameter group names must be identifiers (they are passed to a term's "
                f"residual() by name), got {name!r}"
            )
        if name in ("poses", "points"):
            raise ValueError(f"{fn}: parameter group name {name!r} is taken; rename the group")
        what = f"parameters['{name}']"
        value = _checks.from_numpy(value, like)
        if not isinstance(value, Tensor):
            raise TypeError(
                f"{fn}: {what} must be a torch.Tensor (q, d) or (B, q, d), got "
                f"{_checks.describe(value)}"
            )
        if value.dim() == 2:
            value = value[None].expand(B, *value.shape)
        if value.dim() != 3 or value.shape[0] != B or value.shape[2] == 0:
            raise ValueError(
                f"{fn}: {what} must have shape (q, d) or (B, q, d) with B = {B} and d ≥ 1, "
                f"got {tuple(value.shape)}"
            )
        _checks.check_same_kind(fn, observations=like, **{what: value})
        _checks.check_finite(fn, what, value)
        q = value.shape[1]
        mask = _checks.from_numpy(fixed.get(name), like)
        if mask is None:
            mask = torch.zeros(B, q, dtype=torch.bool, device=value.device)
        else:
            if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
                raise TypeError(
                    f"{fn}: fixed_parameters['{name}'] must be a bool tensor (q,) or (B, q) "
                    f"with q = {q}, got {_checks.describe(mask)}"
                )
            if mask.dim() == 1:
                mask = mask[None].expand(B, -1)
            if tuple(mask.shape) != (B, q):
                raise ValueError(
                    f"{fn}: fixed_parameters['{name}'] must have shape ({q},) or ({B}, {q}), "
                    f"got {tuple(mask.shape)}"
                )
            mask = mask.to(value.device)
        values[name] = value.detach().clone()
        masks.append(mask)
    return values, tuple(masks)


def parameter_layout(
    values: Mapping[str, Tensor], fixed: tuple[Tensor, ...], num_poses: int
) -> ParameterLayout | None:
    """The :class:`ParameterLayout` of checked groups (None without any)."""
    if not values:
        return None
    names = tuple(values)
    return ParameterLayout(
        names,
        tuple(int(values[k].shape[1]) for k in names),
        tuple(int(values[k].shape[2]) for k in names),
        num_poses,
        fixed,
    )


def pack_values(
    fn: str, layout: ParameterLayout | None, values: object, like: Tensor, detach: bool = True
) -> Tensor | None:
    """The slot values (B, S, 6) of a solve's starting parameter blocks ``values`` ({name:
    (B, q, d)}, every group of ``layout``), checked (errors name ``fn``), detached unless
    ``detach`` is False (the differentiable solve); None without a layout."""
    if layout is None:
        if values:
            raise ValueError(
                f"{fn}: argument 'parameters' gives blocks {sorted(values)}, but 'data' has no "
                "parameter groups (build the problem with parameters={...})"
            )
        return None
    if not isinstance(values, Mapping):
        raise TypeError(
            f"{fn}: the problem has parameter groups {list(layout.names)}; argument "
            f"'parameters' must be a mapping name → tensor (B, q, d), got "
            f"{_checks.describe(values)}"
        )
    if set(values) != set(layout.names):
        raise ValueError(
            f"{fn}: argument 'parameters' must give every parameter group of 'data' "
            f"{sorted(layout.names)}, got {sorted(values)}"
        )
    B = like.shape[0]
    for g, name in enumerate(layout.names):
        v = values[name]
        expected = (B, layout.counts[g], layout.dims[g])
        if not isinstance(v, Tensor) or tuple(v.shape) != expected:
            got = tuple(v.shape) if isinstance(v, Tensor) else _checks.describe(v)
            raise ValueError(
                f"{fn}: parameters['{name}'] must have shape {expected} (B, q, d), got {got}"
            )
        _checks.check_same_kind(fn, pose_tangent=like, **{f"parameters['{name}']": v})
        if _checks.value_checks_active():
            _checks.check_finite(fn, f"parameters['{name}']", v)
    return layout.pack({k: v.detach() if detach else v for k, v in values.items()})
