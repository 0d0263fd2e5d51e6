"""Camera models: analytic Jacobians against torch.func.jacrev and central differences, in
float64, at the image centre and the edge, tiny and large depths, angle 0 and ≈ π."""

from __future__ import annotations

import math

import pytest
import torch

from tests.helpers import central_difference
from torchslam import cameras
from torchslam.lie import se3

F64 = torch.float64


def _pose(omega, t) -> torch.Tensor:
    return se3.exp(torch.tensor([*omega, *t], dtype=F64))


# (pose, a point in the camera frame to place): centre (on the axis), edge (far off-axis),
# tiny depth (1 mm) and large depth (1 km), rotations of 0 and ≈ π.
def _cases(model: str):
    sign = -1.0 if model == "snavely" else 1.0  # Snavely looks down −z
    poses = [
        _pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        _pose((0.3, -0.2, 0.1), (0.5, -1.0, 2.0)),
        _pose((math.pi - 1e-6, 0.0, 0.0), (0.1, 0.2, 0.3)),
    ]
    in_camera = [
        (0.0, 0.0, 2.0),  # image centre
        (1.5, -1.2, 2.0),  # near the edge of a wide field of view
        (1e-4, 2e-4, 1e-3),  # tiny depth
        (30.0, -20.0, 1000.0),  # large depth
    ]
    for T in poses:
        for x, y, z in in_camera:
            P = torch.tensor([x, y, sign * z], dtype=F64)
            X = se3.act(se3.inverse(T), P)  # world point that lands at P
            yield T, X


SNAVELY = torch.tensor([500.0, -0.05, 0.01], dtype=F64)
PINHOLE4 = torch.tensor([520.0, 515.0, 319.5, 239.5], dtype=F64)
PINHOLE8 = torch.tensor([520.0, 515.0, 319.5, 239.5, -0.2, 0.05, 1e-3, -2e-3], dtype=F64)
MODELS = {
    "snavely": (cameras.snavely_project, cameras.snavely_jacobians, SNAVELY),
    "pinhole4": (cameras.pinhole_project, cameras.pinhole_jacobians, PINHOLE4),
    "pinhole8": (cameras.pinhole_project, cameras.pinhole_jacobians, PINHOLE8),
}


def _tolerance(reference: torch.Tensor, eps: float) -> float:
    # central differences: truncation O(eps²·f''') and round-off O(ulp·|f|/eps), relative to
    # the size of the Jacobian (tiny depths have derivatives ~1e9)
    return 1e-6 * max(1.0, float(reference.abs().max()))


@pytest.mark.parametrize("model", list(MODELS))
def test_jacobians_match_jacrev_and_central_differences(model):
    project, jacobians, K = MODELS[model]
    sign = "snavely" if model == "snavely" else "pinhole"
    for T, X in _cases(sign):
        u, J_xi, J_X, J_K = jacobians(T, X, K)
        torch.testing.assert_close(u, project(T, X, K), rtol=0, atol=0)

        def of_xi(xi, T=T, X=X):
            return project(se3.compose(T, se3.exp(xi)), X, K)

        zero = torch.zeros(6, dtype=F64)
        rev = (
            torch.func.jacrev(of_xi)(zero),
            torch.func.jacrev(lambda x, T=T: project(T, x, K))(X),
            torch.func.jacrev(lambda k, T=T, X=X: project(T, X, k))(K),
        )
        # jacrev differentiates the same formulas: agreement to round-off
        for analytic, reference in zip((J_xi, J_X, J_K), rev, strict=True):
            scale = max(1.0, float(reference.abs().max()))
            torch.testing.assert_close(analytic, reference, rtol=0, atol=1e-12 * scale)
        # central differences, each step relative to the variable's scale
        depth = float(se3.act(T, X).abs().max())
        steps = (1e-6, 1e-6 * max(depth, 1e-3), 1e-6 * float(K.abs().max()))
        numeric = (
            central_difference(of_xi, zero, eps=1e-7 if depth < 1e-2 else 1e-6),
            central_difference(lambda x, T=T: project(T, x, K), X, eps=steps[1]),
        )
        for analytic, reference in zip((J_xi, J_X), numeric, strict=True):
            torch.testing.assert_close(
                analytic, reference, rtol=1e-5, atol=_tolerance(reference, 1e-6)
            )
        for k in range(K.shape[0]):  # per intrinsic, a step relative to its value
            h = 1e-6 * max(abs(float(K[k])), 1e-3)
            e = torch.zeros_like(K)
            e[k] = h
            column = (project(T, X, K + e) - project(T, X, K - e)) / (2 * h)
            torch.testing.assert_close(J_K[:, k], column, rtol=1e-5, atol=_tolerance(column, h))


def test_batched_equals_one_by_one():
    g = torch.Generator().manual_seed(0)
    T = se3.exp(0.3 * torch.randn(5, 6, generator=g, dtype=F64))
    X = torch.randn(5, 3, generator=g, dtype=F64) + torch.tensor([0.0, 0.0, 6.0], dtype=F64)
    for _, jacobians, K in MODELS.values():
        batched = jacobians(T, X, K.expand(5, -1))
        for i in range(5):
            single = jacobians(T[i], X[i], K)
            for a, b in zip(batched, single, strict=True):
                torch.testing.assert_close(a[i], b, rtol=0, atol=1e-12)


def test_pinhole_convention_by_hand():
    # u = fx·x/z + cx: the point (1, 0.5, 2) in the camera lands at (520·0.5 + 319.5, …)
    u = cameras.pinhole_project(
        torch.eye(4, dtype=F64), torch.tensor([1.0, 0.5, 2.0]).double(), PINHOLE4
    )
    assert u.tolist() == [520.0 * 0.5 + 319.5, 515.0 * 0.25 + 239.5]
    # Snavely: −P_xy/P_z, the camera looks down −z
    s = cameras.snavely_project(
        torch.eye(4, dtype=F64), torch.tensor([1.0, 0.5, -2.0]).double(),
        torch.tensor([100.0, 0.0, 0.0], dtype=F64),
    )  # fmt: skip
    assert s.tolist() == [50.0, 25.0]
    with pytest.raises(ValueError, match="intrinsics"):
        cameras.pinhole_jacobians(torch.eye(4, dtype=F64), torch.ones(3, dtype=F64), PINHOLE4[:3])
