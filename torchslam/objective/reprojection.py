"""Reprojection terms: a camera pose, a world point and the camera's intrinsics → pixels.

Instance k observes world point X_j in camera i at pixel u_k; its residual (2 entries, pixels)
is the camera model's prediction minus the observation,

    r_k = π(T_i X_j; c) − u_k,

with T_i the camera pose **world → camera** (the problem's T_i0) and c the intrinsics; the
camera models and their conventions are those of :mod:`torchslam.cameras` (``"snavely"``:
BAL/Bundler, c = (f, k1, k2), looking down −z, pixels from the image centre; ``"pinhole"``:
OpenCV, c = (fx, fy, cx, cy[, k1, k2, p1, p2]), looking down +z, pixels from the top-left
pixel's centre). The cost is ½ Σ ρ(w‖r‖²) as for every term (Ceres' and BAL's ½Σr²).

The intrinsics are either **variables** — a parameter group of the problem
(:mod:`torchslam.objective.parameters`), one block per camera or one shared by all, with
``intrinsics_index`` saying which block each observation uses — or **constants** (known
calibration; a tensor that may require grad, so that :func:`torchslam.solve_differentiable`
gives gradients with respect to it). The analytic Jacobians (:func:`torchslam.cameras.
snavely_jacobians`, :func:`~torchslam.cameras.pinhole_jacobians`) are checked against
``jacrev`` and central differences in the tests.
"""

from __future__ import annotations

from torch import Tensor

from torchslam import _checks
from torchslam.cameras import pinhole_jacobians, snavely_jacobians, snavely_project
from torchslam.objective.terms import Term

__all__ = ["ReprojectionTerm"]

_MODELS = {"snavely": (3,), "pinhole": (4, 8)}


class ReprojectionTerm(Term):
    """Reprojection residuals r = π(T_i X_j; c) − u of K observations (module doc).

    Args:
        camera_index: observing camera (a pose of the problem) of each observation, integer
            (K,) or (B, K).
        point_index: observed world point, integer (K,) or (B, K).
        pixels: observed pixels u, (K, 2) or (B, K, 2), in the model's pixel convention.
        model: ``"snavely"`` (default; BAL) or ``"pinhole"``.
        intrinsics_index: the block of parameter group ``group`` each observation uses,
            integer (K,) or (B, K): the intrinsics are variables of the problem (give the
            group to the problem as ``parameters={group: (q, d)}``).
        intrinsics: known intrinsics instead, (d,) shared or (K, d) / (B, K, d) per
            observation: constants (may require grad).
        group: the parameter group's name (default ``"intrinsics"``).
        weight: as :class:`torchslam.Term` (per observation).
        information: as :class:`torchslam.Term` (per observation).
        loss: as :class:`torchslam.Term` (per observation).
        valid: as :class:`torchslam.Term` (per observation).

    Exactly one of ``intrinsics_index`` and ``intrinsics``.
    """

    def __init__(
        self,
        camera_index: Tensor,
        point_index: Tensor,
        pixels: Tensor,
        *,
        model: str = "snavely",
        intrinsics_index: Tensor | None = None,
        intrinsics: Tensor | None = None,
        group: str = "intrinsics",
        weight: Tensor | None = None,
        information: Tensor | None = None,
        loss: object | None = None,
        valid: Tensor | None = None,
    ) -> None:
        fn = "ReprojectionTerm"
        if model not in _MODELS:
            raise ValueError(
                f"{fn}: argument 'model' must be one of {sorted(_MODELS)}, got {model!r}"
            )
        if (intrinsics_index is None) == (intrinsics is None):
            raise ValueError(
                f"{fn}: give exactly one of 'intrinsics_index' (the intrinsics are variables: "
                "a parameter group of the problem) and 'intrinsics' (known constants)"
            )
        if not isinstance(camera_index, Tensor):
            raise TypeError(
                f"{fn}: argument 'camera_index' must be an integer torch.Tensor (K,) or (B, K), "
                f"got {_checks.describe(camera_index)}"
            )
        if camera_index.dim() not in (1, 2):
            raise ValueError(
                f"{fn}: argument 'camera_index' must have shape (K,) or (B, K), got "
                f"{tuple(camera_index.shape)}"
            )
        lead = tuple(camera_index.shape)
        _checks.check_tensor(fn, "pixels", pixels, (2,), min_batch_dims=1, dims="K")
        if tuple(pixels.shape[:-1]) != lead:
            raise ValueError(
                f"{fn}: argument 'pixels' must have shape {lead} + (2,) to match "
                f"'camera_index', got {tuple(pixels.shape)}"
            )
        self.model = model
        self.group = group
        constants = {"pixels": pixels}
        parameters = None
        if intrinsics is not None:
            _checks.check_tensor(fn, "intrinsics", intrinsics)
            d = intrinsics.shape[-1] if intrinsics.dim() else 0
            if intrinsics.dim() == 1:
                intrinsics = intrinsics.expand(*lead, d)
            if tuple(intrinsics.shape[:-1]) != lead:
                raise ValueError(
                    f"{fn}: argument 'intrinsics' must have shape (d,) or {lead} + (d,), got "
                    f"{tuple(intrinsics.shape)}"
                )
            _check_size(fn, model, d)
            constants["known_intrinsics"] = intrinsics
        else:
            parameters = {group: intrinsics_index}
        super().__init__(
            camera_index[..., None],
            constants,
            point_index=point_index,
            weight=weight,
            information=information,
            loss=loss,
            valid=valid,
            parameters=parameters,
        )

    def padding_constant(self, name: str, like: Tensor):
        if name == "known_intrinsics":  # a camera that projects: focal length 1
            out = like.new_zeros(like.shape)
            out[..., :1] = 1.0
            if self.model == "pinhole":
                out[..., 1:2] = 1.0
            return out
        return super().padding_constant(name, like)

    def bind(self, batch_size, num_poses, like, num_points=None, parameters=None):
        if parameters is not None and self.group in self.parameter_index:
            if self.group in parameters.names:
                d = parameters.dims[parameters.group(self.group)]
                _check_size("ReprojectionTerm", self.model, d, f"parameter group {self.group!r}")
        return super().bind(batch_size, num_poses, like, num_points, parameters)

    def _intrinsics(self, values: dict) -> Tensor:
        if "known_intrinsics" in values:
            return values.pop("known_intrinsics")
        return values.pop(self.group)

    def residual(self, poses: Tensor, points: Tensor, pixels: Tensor, **values: Tensor) -> Tensor:
        c = self._intrinsics(values)
        T = poses[..., 0, :, :]
        if self.model == "snavely":
            return snavely_project(T, points, c) - pixels
        return pinhole_jacobians(T, points, c)[0] - pixels

    def jacobians(self, poses: Tensor, points: Tensor, pixels: Tensor, **values: Tensor):
        variable = self.group in values and "known_intrinsics" not in values
        c = self._intrinsics(values)
        T = poses[..., 0, :, :]
        model = snavely_jacobians if self.model == "snavely" else pinhole_jacobians
        predicted, J_pose, J_point, J_c = model(T, points, c)
        r = predicted - pixels
        if variable:
            return r, J_pose[..., None, :], J_point, {self.group: J_c}
        return r, J_pose[..., None, :], J_point


def _check_size(fn: str, model: str, d: int, what: str = "'intrinsics'") -> None:
    if d not in _MODELS[model]:
        sizes = " or ".join(str(s) for s in _MODELS[model])
        raise ValueError(
            f"{fn}: the {model!r} model takes {sizes} intrinsics values; {what} has {d}"
        )
