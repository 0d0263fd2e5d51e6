"""Bad input and padding across problem, terms, losses, config and the solve entry points.

Targeted tests per reported failure (NaN padding, pose-graph-only jacrev, poses-only user
terms, unchecked solve arguments, loss/config validation, empty sizes, extreme kernel
scales, shape messages), then a seeded fuzz over the public surface: every call either
raises a ValueError/TypeError naming the function or class and the argument, or returns a
result whose status is honest (finite poses from finite input).

All problems are tiny (m = 3 poses, n = 8 points, a few iterations) so the file runs in a
few seconds.
"""

from __future__ import annotations

import dataclasses
import math
import random
import warnings

import pytest
import torch
from torch import Tensor

import torchslam as ts
from torchslam import jacobians
from torchslam.lie import se3
from torchslam.problem import PointMapProblem
from torchslam.solver import Status
from torchslam.solver.differentiable import ImplicitConfig, solve_differentiable

F64 = torch.float64
FEW = ts.SolverConfig(max_iterations=30)


def _tiny(B: int = 1, m: int = 3, n: int = 8, seed: int = 0, noise: float = 0.01):
    """Every pose sees every point; poses near the identity, points in front of them."""
    g = torch.Generator().manual_seed(seed)
    xi = 0.1 * torch.randn(B, m, 6, generator=g, dtype=F64)
    poses = se3.exp(xi)
    points = torch.randn(B, n, 3, generator=g, dtype=F64) + torch.tensor([0.0, 0.0, 4.0], dtype=F64)
    pose_index = torch.arange(m).repeat_interleave(n)[None].expand(B, -1).clone()
    point_index = torch.arange(n).repeat(m)[None].expand(B, -1).clone()
    T = poses[torch.arange(B)[:, None], pose_index]
    X = points[torch.arange(B)[:, None], point_index]
    obs = se3.act(T, X) + noise * torch.randn(B, m * n, 3, generator=g, dtype=F64)
    # Start from perturbed poses (pose 0, the gauge, at its true value).
    start = se3.exp(
        xi
        + 0.05
        * torch.randn(B, m, 6, generator=g, dtype=F64)
        * (torch.arange(m) > 0).to(F64)[None, :, None]
    )
    return {
        "poses": start,
        "points": points + 0.05 * torch.randn(B, n, 3, generator=g, dtype=F64),
        "pose_index": pose_index,
        "point_index": point_index,
        "observations": obs,
    }


def _pad(inputs: dict, extra: int, g: torch.Generator) -> tuple[dict, Tensor]:
    """The same problem with ``extra`` padding slots appended, holding NaN, Inf and
    out-of-range indices; returns (inputs, valid)."""
    B, E = inputs["pose_index"].shape
    out = dict(inputs)
    junk_obs = torch.full((B, extra, 3), math.nan, dtype=F64)
    junk_obs[:, ::2] = math.inf
    out["observations"] = torch.cat((inputs["observations"], junk_obs), 1)
    out["pose_index"] = torch.cat(
        (inputs["pose_index"], torch.randint(-5, 50, (B, extra), generator=g)), 1
    )
    out["point_index"] = torch.cat(
        (inputs["point_index"], torch.randint(-5, 50, (B, extra), generator=g)), 1
    )
    valid = torch.cat(
        (torch.ones(B, E, dtype=torch.bool), torch.zeros(B, extra, dtype=torch.bool)), 1
    )
    return out, valid


def _build(**kwargs) -> PointMapProblem:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return PointMapProblem(**kwargs)


# --------------------------------------------------------------------------- padding is inert


@pytest.mark.parametrize("weighting", ["none", "scalar", "information"])
@pytest.mark.parametrize("loss", [None, ts.HuberLoss(0.1)], ids=["ls", "huber"])
def test_nan_padding_gives_the_result_without_it(weighting, loss):
    g = torch.Generator().manual_seed(3)
    inputs = _tiny(B=2)
    B, E = inputs["pose_index"].shape
    padded, valid = _pad(inputs, 7, g)
    weights = padded_weights = None
    if weighting == "scalar":
        weights = torch.rand(B, E, generator=g, dtype=F64) + 0.5
        junk = torch.full((B, 7), math.nan, dtype=F64)
        junk[:, 1] = -3.0
        padded_weights = torch.cat((weights, junk), 1)
    elif weighting == "information":
        A = 0.2 * torch.randn(B, E, 3, 3, generator=g, dtype=F64) + torch.eye(3, dtype=F64)
        weights = A @ A.mT
        junk = torch.full((B, 7, 3, 3), math.nan, dtype=F64)
        junk[:, 1] = -torch.eye(3, dtype=F64)  # not positive definite: padding, so fine
        padded_weights = torch.cat((weights, junk), 1)
    plain = _build(**inputs, weights=weights, loss=loss)
    noisy = _build(**padded, valid=valid, weights=padded_weights, loss=loss)
    a = ts.solve(plain, FEW)
    b = ts.solve(noisy, FEW)
    assert a.status == b.status and all(s.converged for s in b.status)
    # The valid slots come first and in the same order; the padding adds exact zeros to the
    # index_add sums, so the iterates agree to round-off of this well-conditioned problem.
    torch.testing.assert_close(b.pose_tangent, a.pose_tangent, rtol=0, atol=1e-12)
    torch.testing.assert_close(b.points, a.points, rtol=0, atol=1e-12)
    torch.testing.assert_close(b.final_cost, a.final_cost, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(noisy.cost(), plain.cost(), rtol=1e-12, atol=0)
    assert bool(torch.isfinite(noisy.residuals()).all())
    assert bool(torch.isfinite(noisy.dense_jacobian()).all())
    if weighting == "none" and loss is None:
        assert bool(torch.isfinite(noisy.dense_jacobian("jacrev")).all())


@pytest.mark.parametrize("backward", ["implicit", "unrolled", "truncated"])
def test_nan_padding_gives_finite_gradients(backward):
    g = torch.Generator().manual_seed(4)
    inputs = _tiny(B=1)
    B, E = inputs["pose_index"].shape
    padded, valid = _pad(inputs, 5, g)
    w = torch.rand(B, E, generator=g, dtype=F64) + 0.5
    w_padded = torch.cat((w, torch.full((B, 5), math.nan, dtype=F64)), 1)
    config = ts.SolverConfig(max_iterations=10)

    def grads(obs, weights, **kw):
        obs = obs.clone().requires_grad_(True)
        weights = weights.clone().requires_grad_(True)
        p = _build(**{**kw, "observations": obs}, weights=weights, loss=ts.HuberLoss(0.02))
        r = solve_differentiable(p.pose_tangent, p.points, p.data, config, backward=backward)
        (r.pose_tangent.sum() + r.points.sum()).backward()
        return obs.grad, weights.grad

    g_obs, g_w = grads(
        inputs["observations"], w, **{k: v for k, v in inputs.items() if k != "observations"}
    )
    h_obs, h_w = grads(
        padded["observations"],
        w_padded,
        **{k: v for k, v in padded.items() if k != "observations"},
        valid=valid,
    )
    for h in (h_obs, h_w):
        assert bool(torch.isfinite(h).all())
    assert bool((h_obs[:, E:] == 0).all()) and bool((h_w[:, E:] == 0).all())
    # Same solve on the valid slots: the gradients agree to round-off amplified by the
    # (well-conditioned, m = 3) solve.
    torch.testing.assert_close(h_obs[:, :E], g_obs, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(h_w[:, :E], g_w, rtol=1e-8, atol=1e-10)


def test_padding_term_instances_are_inert():
    inputs = _tiny(B=1)
    poses = inputs["poses"][0]
    Z = poses[:2] @ se3.inverse(poses[1:3])
    info = torch.eye(6, dtype=F64).expand(2, 6, 6)
    nan_pose = torch.full((4, 4), math.nan, dtype=F64)
    term = ts.RelativePoseTerm(torch.tensor([[0, 1], [1, 2]]), Z, information=info)
    padded = ts.RelativePoseTerm(
        torch.tensor([[0, 1], [7, -4], [1, 2]]),
        torch.stack((Z[0], nan_pose, Z[1])),
        information=torch.stack((info[0], torch.full((6, 6), math.nan, dtype=F64), info[1])),
        valid=torch.tensor([True, False, True]),
    )
    a = ts.solve(_build(**inputs, terms=[term]), FEW)
    measurements = padded.constants["measurements"].clone().requires_grad_(True)
    padded.constants["measurements"] = measurements
    p = _build(**inputs, terms=[padded])
    b = solve_differentiable(p.pose_tangent, p.points, p.data, FEW)
    torch.testing.assert_close(b.pose_tangent, a.pose_tangent, rtol=0, atol=1e-12)
    b.pose_tangent.sum().backward()
    assert bool(torch.isfinite(measurements.grad).all())
    assert bool((measurements.grad[1] == 0).all())


@pytest.mark.parametrize("kind", ["relative", "prior"])
def test_all_padding_term_is_inert(kind):
    # Every instance padding, holding a non-rigid (and NaN) measurement: accepted, and the
    # solve is the one without the term (issue 28 §7).
    inputs = _tiny(B=1)
    junk = torch.full((2, 4, 4), 2.0, dtype=F64)
    junk[0, 0, 0] = math.nan
    valid = torch.tensor([False, False])
    if kind == "relative":
        term = ts.RelativePoseTerm(torch.tensor([[0, 1], [1, 2]]), junk, valid=valid)
    else:
        term = ts.PosePriorTerm(torch.tensor([1, 2]), junk, valid=valid)
    a = ts.solve(_build(**inputs), FEW)
    b = ts.solve(_build(**inputs, terms=[term]), FEW)
    torch.testing.assert_close(b.pose_tangent, a.pose_tangent, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- reported failures


def test_jacrev_on_a_pose_graph_without_observations():
    inputs = _tiny(B=1)
    poses = inputs["poses"]
    Z = se3.exp(0.05 * torch.ones(2, 6, dtype=F64)) @ poses[0, :2] @ se3.inverse(poses[0, 1:3])
    empty = torch.zeros(1, 0, dtype=torch.long)
    results = []
    for mode in ("analytic", "jacrev"):
        p = _build(
            poses=poses,
            points=inputs["points"][:, :0],
            pose_index=empty,
            point_index=empty,
            observations=torch.zeros(1, 0, 3, dtype=F64),
            terms=[ts.RelativePoseTerm(torch.tensor([[0, 1], [1, 2]]), Z)],
        )
        results.append(ts.solve(p, ts.SolverConfig(jacobian=mode)))
        assert p.jacobian_blocks("jacrev")[0].shape == (1, 0, 3, 6)
    assert all(r.converged[0] for r in results)
    torch.testing.assert_close(results[1].pose_tangent, results[0].pose_tangent, atol=1e-10, rtol=0)


def test_user_term_with_poses_only():
    class Height(ts.Term):
        """z of the sensor position pulled to 0 (no constants)."""

        def residual(self, poses):
            T = se3.inverse(poses[..., 0, :, :])
            return T[..., 2:3, 3]

    inputs = _tiny(B=2)
    p = _build(**inputs, terms=[Height(torch.tensor([[1], [2]]))])
    assert p.data.terms[0].residual_dim == 1
    result = ts.solve(p, FEW)
    assert all(s.converged for s in result.status)


def test_solve_entry_points_check_their_arguments():
    p = _build(**_tiny(B=2))
    xi, X, data = p.pose_tangent, p.points, p.data
    cases = [
        (lambda: ts.solve(p, "lm"), TypeError, r"solve: argument 'config' must be .*got str 'lm'"),
        (lambda: ts.solve(None), TypeError, r"solve: argument 'problem' must be"),
        (lambda: ts.solve(data), TypeError, r"solve: argument 'problem'.*solve_tensors"),
        (lambda: ts.solve(p, callback=3), TypeError, r"solve: argument 'callback'"),
        (lambda: ts.solve_tensors(xi, X, p), TypeError, r"solve_tensors: got a PointMapProblem"),
        (lambda: ts.solve_tensors(p, X, data), TypeError, r"solve_tensors: got a PointMapProblem"),
        (lambda: ts.solve_tensors(xi, X, None), TypeError, r"solve_tensors: argument 'data'"),
        (
            lambda: ts.solve_tensors(xi[:, :2], X, data),
            ValueError,
            r"'pose_tangent' must have shape \(B, m, 6\) = \(2, 3, 6\) to match 'data', "
            r"got \(2, 2, 6\)",
        ),
        (
            lambda: ts.solve_tensors(xi[0], X, data),
            ValueError,
            r"'pose_tangent' must have shape \(B, m, 6\), got \(3, 6\); add a leading batch dim",
        ),
        (lambda: ts.solve_tensors(xi, X[:1], data), ValueError, r"'points' must have shape"),
        (
            lambda: ts.solve_tensors(xi.float(), X, data),
            TypeError,
            r"'pose_tangent' is torch.float32",
        ),
        (
            lambda: ts.solve_tensors(xi.long(), X, data),
            TypeError,
            r"'pose_tangent' must be float32",
        ),
        (
            lambda: ts.solve_tensors(xi.detach() * math.nan, X, data),
            ValueError,
            r"solve_tensors: argument 'pose_tangent' contains",
        ),
        (
            lambda: solve_differentiable(xi, X, data, ts.SolverConfig, backward="none"),
            TypeError,
            r"solve_differentiable: argument 'config' must be .*the class SolverConfig",
        ),
        (
            lambda: solve_differentiable(xi, X.detach() + math.inf, data),
            ValueError,
            r"solve_differentiable: argument 'points' contains",
        ),
        (lambda: solve_differentiable(xi, X, p), TypeError, r"solve_differentiable: got a Point"),
    ]
    for call, error, pattern in cases:
        with pytest.raises(error, match=pattern):
            call()


@pytest.mark.parametrize(
    ("loss", "pattern"),
    [
        ("huber", r"must be a RobustLoss instance such as ts.HuberLoss\(0.05\).*got str 'huber'"),
        (ts.HuberLoss, r"got the class HuberLoss itself; create one, e.g. ts.HuberLoss\(0.05\)"),
        (ts.TrivialLoss, r"e.g. ts.TrivialLoss\(\)"),
        (0.5, r"got float 0.5"),
        (lambda s: (s, s, s), r"got function"),
    ],
)
def test_losses_are_checked_where_they_are_given(loss, pattern):
    inputs = _tiny()
    with pytest.raises(TypeError, match=r"PointMapProblem: argument 'loss' .*" + pattern):
        _build(**inputs, loss=loss)
    Z = torch.eye(4, dtype=F64)[None]
    with pytest.raises(TypeError, match=r"PosePriorTerm: argument 'loss' .*" + pattern):
        ts.PosePriorTerm(torch.tensor([1]), Z, loss=loss)
    p = _build(**inputs)
    with pytest.raises(TypeError, match=r"PointMapData: argument 'loss' .*" + pattern):
        dataclasses.replace(p.data, loss=loss)


def test_config_rejects_a_contradictory_combination():
    with pytest.raises(ValueError, match=r"SolverConfig: 'reduced_solver' = 'sparse'"):
        ts.SolverConfig(linear_solver="dense", reduced_solver="sparse")


def test_point_map_data_checks_its_fields():
    data = _build(**_tiny(B=2)).data
    cases = [
        ({"valid": data.valid.long()}, TypeError, r"PointMapData: field 'valid' must be a bool"),
        ({"pose_index": data.pose_index[:, :-1]}, ValueError, r"'pose_index' must have shape"),
        ({"pose_index": data.pose_index.double()}, TypeError, r"'pose_index' must be an integer"),
        ({"observations": data.observations[0]}, ValueError, r"'observations' must have shape"),
        ({"weights": torch.ones(2, 5, dtype=F64)}, ValueError, r"'weights' must have shape"),
        (
            {
                "weights": torch.ones(2, 24, dtype=F64),
                "information": torch.eye(3).expand(2, 24, 3, 3),
            },
            ValueError,
            r"give 'weights' or 'information', not both",
        ),
        ({"fixed_poses": data.fixed_poses[:1]}, ValueError, r"field 'fixed_poses' has shape"),
        ({"fixed_points": None}, TypeError, r"field 'fixed_points' must be a bool"),
        ({"terms": [object()]}, TypeError, r"field 'terms' must be a tuple"),
    ]
    for changes, error, pattern in cases:
        with pytest.raises(error, match=pattern):
            dataclasses.replace(data, **changes)
    # Values are checked once, by the first solve of a directly built PointMapData.
    bad = data.pose_index.clone()
    bad[1, 3] = 7
    wrong = dataclasses.replace(data, pose_index=bad)
    with pytest.raises(ValueError, match=r"solve_tensors: 'pose_index' out of range \[0, 3\)"):
        ts.solve_tensors(torch.zeros(2, 3, 6, dtype=F64), torch.zeros(2, 8, 3, dtype=F64), wrong)


def test_implicit_config_checks_every_field():
    for kwargs in (
        {"hessian": "bfgs"},
        {"hessian": None},
        {"tolerance": math.nan},
        {"tolerance": -1.0},
        {"tolerance": math.inf},
        {"tolerance": "1e-8"},
        {"max_iterations": 0},
        {"max_iterations": True},
        {"max_iterations": 2.0},
    ):
        with pytest.raises(ValueError, match=f"ImplicitConfig: '{next(iter(kwargs))}'"):
            ImplicitConfig(**kwargs)


def test_empty_sizes():
    inputs = _tiny(B=2)
    # m = 0: nothing to solve.
    with pytest.raises(ValueError, match=r"PointMapProblem: a problem needs at least one pose"):
        _build(**{**inputs, "poses": inputs["poses"][:, :0]})
    # n = 0 with valid observations.
    with pytest.raises(ValueError, match=r"there are no points \(n = 0\)"):
        _build(**{**inputs, "points": inputs["points"][:, :0]})
    # B = 0: an empty result.
    empty = {k: v[:0] for k, v in inputs.items()}
    result = ts.solve(_build(**empty), FEW)
    assert result.status == [] and result.pose_tangent.shape == (0, 3, 6)
    # E = 0 and n = 0: a problem of fixed poses, nothing moves.
    none = torch.zeros(2, 0, dtype=torch.long)
    p = _build(
        poses=inputs["poses"],
        points=inputs["points"][:, :0],
        pose_index=none,
        point_index=none,
        observations=torch.zeros(2, 0, 3, dtype=F64),
    )
    result = ts.solve(p, FEW)
    assert all(s.converged for s in result.status)
    assert torch.equal(result.pose_tangent, se3.log(inputs["poses"]))


SCALES = (1e-300, 1e-200, 1e-155, 1e-20, 1.0, 1e20, 1e155, 1e200, 1e300)
SQUARED = (0.0, 5e-324, 1e-300, 1e-200, 1e-40, 1e-10, 1.0, 1e10, 1e40, 1e200, 1e300)


@pytest.mark.parametrize(
    "kind", [ts.HuberLoss, ts.CauchyLoss, ts.TukeyLoss], ids=lambda k: k.__name__
)
def test_kernels_are_finite_for_every_scale(kind):
    s = torch.tensor(SQUARED, dtype=F64)
    for a in SCALES:
        for scale in (a, torch.tensor(a, dtype=F64, requires_grad=True)):
            x = s.clone().requires_grad_(True)
            rho, rho1, rho2 = kind(scale)(x)
            for name, value in (("rho", rho), ("rho1", rho1), ("rho2", rho2)):
                assert bool(torch.isfinite(value).all()), (kind, a, name, value)
            # ρ ≤ s (every kernel lies below the quadratic), 0 ≤ ρ' ≤ 1, ρ'' ≤ 0.
            assert bool((rho <= s * (1 + 1e-12)).all()) and bool((rho >= 0).all())
            assert bool(((rho1 >= 0) & (rho1 <= 1)).all()) and bool((rho2 <= 0).all())
            grads = torch.autograd.grad(
                rho.sum(), [x] + ([scale] if isinstance(scale, Tensor) else [])
            )
            assert all(bool(torch.isfinite(d).all()) for d in grads), (kind, a)
            if 1e-150 < a < 1e150:
                # ∂ρ/∂s by autograd is ρ' (in [0, 1]) to a few ulps of 1. (Beyond, a² is
                # subnormal in the chain rule and only finiteness is asked.)
                torch.testing.assert_close(grads[0], rho1, rtol=1e-9, atol=1e-15)
            residual_scale, alpha_over_s = ts.losses.triggs_correction(
                s, rho1.detach(), rho2.detach()
            )
            assert bool(torch.isfinite(residual_scale).all() & torch.isfinite(alpha_over_s).all())


def test_extreme_scales_in_a_solve():
    inputs = _tiny(B=1)
    plain = ts.solve(_build(**inputs), FEW)
    # CauchyLoss(1e200) is least squares to round-off (ρ = s (1 − s/(2a²) + …)).
    wide = ts.solve(_build(**inputs, loss=ts.CauchyLoss(1e200)), FEW)
    assert wide.converged[0]
    torch.testing.assert_close(wide.pose_tangent, plain.pose_tangent, rtol=0, atol=1e-10)
    # TukeyLoss(1e-200): every observation is an outlier, ρ' = 0: nothing moves, and the
    # status says so without NaN.
    flat = ts.solve(_build(**inputs, loss=ts.TukeyLoss(1e-200)), FEW)
    assert flat.status[0] != Status.NON_FINITE
    assert bool(torch.isfinite(flat.pose_tangent).all())
    for bad in (0.0, -1.0, math.nan, math.inf, 10**400):
        with pytest.raises(ValueError, match=r"CauchyLoss: argument 'scale' must be positive"):
            ts.CauchyLoss(bad)


# --------------------------------------------------------------------------- the fuzz


def _random_value(rng: random.Random, good):
    """A random mutation of a good argument value."""
    choice = rng.randrange(12)
    if choice == 0:
        return None
    if choice == 1:
        return "x"
    if choice == 2:
        return rng.choice([0, -1, 1.5, math.nan, math.inf, True])
    if not isinstance(good, Tensor):
        return rng.choice([[1, 2], {"a": 1}, ts.HuberLoss, object()])
    if choice == 3:
        return good[0] if good.dim() > 0 else good[None]
    if choice == 4:
        return good[None]
    if choice == 5:
        return good.float() if good.dtype == F64 else good.double()
    if choice == 6:
        return good.long() if good.is_floating_point() else good.to(F64)
    if choice == 7 and good.dim() > 1:
        return good[:, :-1] if good.shape[1] > 0 else good
    if choice == 8 and good.is_floating_point() and good.numel() > 0:
        bad = good.detach().clone()
        bad.view(-1)[rng.randrange(bad.numel())] = rng.choice([math.nan, math.inf, -math.inf])
        return bad
    if choice == 9 and not good.is_floating_point() and good.dtype != torch.bool and good.numel():
        bad = good.clone()
        bad.view(-1)[rng.randrange(bad.numel())] = rng.choice([-1, 99])
        return bad
    if choice == 10 and good.dtype == torch.bool:
        return good.to(torch.uint8)
    return good.transpose(0, -1) if good.dim() > 1 else good[:0]


_NAMES = {
    "PointMapProblem",
    "PointMapData",
    "RelativePoseTerm",
    "PosePriorTerm",
    "SolverConfig",
    "HuberLoss",
    "CauchyLoss",
    "TukeyLoss",
    "solve",
    "solve_tensors",
    "solve_differentiable",
    "from_dense",
}


def _assert_clean_error(error: Exception, argument: str) -> None:
    message = str(error)
    assert any(name in message for name in _NAMES), message
    assert argument in message or argument == "*", (argument, message)


def _check_result(result, batch_size: int) -> None:
    assert len(result.status) == batch_size
    for b, status in enumerate(result.status):
        finite = bool(torch.isfinite(result.pose_tangent[b]).all()) and bool(
            torch.isfinite(result.points[b]).all()
        )
        assert finite, (status, result.pose_tangent[b])
        if status != Status.NON_FINITE:
            assert math.isfinite(float(result.final_cost[b]))


PROBLEM_ARGS = (
    "poses",
    "points",
    "pose_index",
    "point_index",
    "observations",
    "valid",
    "weights",
    "fixed_poses",
    "fixed_points",
    "loss",
)


def _benign(rng: random.Random, good: dict, g: torch.Generator) -> dict:
    """A random well-formed variation: padding (holding NaN/Inf and wild indices), zero and
    random weights, fixed masks, another kernel (extreme scales included)."""
    kwargs = dict(good)
    B, E = good["pose_index"].shape
    if rng.random() < 0.5:
        valid = torch.rand(B, E, generator=g) < 0.8
        kwargs["valid"] = valid
        obs = good["observations"].clone()
        obs[~valid] = rng.choice([math.nan, math.inf, 1e300])
        kwargs["observations"] = obs
        index = good["pose_index"].clone()
        index[~valid] = rng.choice([-1, 99])
        kwargs["pose_index"] = index
    if rng.random() < 0.5:
        w = torch.rand(B, E, generator=g, dtype=F64) * rng.choice([1.0, 1e-8, 1e8])
        w[torch.rand(B, E, generator=g) < 0.2] = 0.0
        kwargs["weights"] = w
    if rng.random() < 0.3:
        kwargs["fixed_poses"] = torch.rand(B, 3, generator=g) < 0.4
        kwargs["fixed_points"] = torch.rand(B, 8, generator=g) < 0.2
    if rng.random() < 0.5:
        kind = rng.choice([ts.HuberLoss, ts.CauchyLoss, ts.TukeyLoss])
        kwargs["loss"] = kind(rng.choice([1e-200, 1e-3, 0.05, 1.0, 1e200]))
    return kwargs


def test_fuzz_problem_construction_and_solve():
    rng = random.Random(20261122)
    g = torch.Generator().manual_seed(1)
    base = _tiny(B=2)
    B, E = base["pose_index"].shape
    good = dict(
        base,
        valid=torch.ones(B, E, dtype=torch.bool),
        weights=torch.ones(B, E, dtype=F64),
        fixed_poses=torch.tensor([[True, False, False]] * B),
        fixed_points=torch.zeros(B, 8, dtype=torch.bool),
        loss=ts.HuberLoss(0.1),
    )
    outcomes = {"error": 0, "solved": 0}
    for _case in range(200):
        kwargs = _benign(rng, good, g)
        names = rng.sample(PROBLEM_ARGS, rng.choice([0, 0, 1, 1, 2]))
        for name in names:
            kwargs[name] = _random_value(rng, good[name])
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                problem = PointMapProblem(**kwargs)
        except (ValueError, TypeError) as error:
            assert names, error  # a benign variation must be accepted
            _assert_clean_error(error, names[0] if len(names) == 1 else "*")
            outcomes["error"] += 1
            continue
        config = ts.SolverConfig(
            max_iterations=rng.choice([0, 1, 2]),
            algorithm=rng.choice(["levenberg_marquardt", "gauss_newton", "gradient_descent"]),
            jacobian="jacrev" if rng.random() < 0.1 else "analytic",
            linear_solver=rng.choice(["schur", "dense"]),
        )
        _check_result(ts.solve(problem, config), problem.batch_size)
        outcomes["solved"] += 1
    # Both outcomes occur: the fuzz is not only hitting one branch.
    assert outcomes["error"] > 40 and outcomes["solved"] > 40, outcomes


def test_fuzz_solve_arguments():
    rng = random.Random(7)
    problem = _build(**_tiny(B=2), loss=ts.CauchyLoss(0.1))
    good = {"pose_tangent": problem.pose_tangent.detach(), "points": problem.points.detach()}
    entry_points = {
        "solve_tensors": lambda xi, X, data, cfg: ts.solve_tensors(xi, X, data, cfg),
        "solve_differentiable": lambda xi, X, data, cfg: solve_differentiable(
            xi, X, data, cfg, backward=rng.choice(["implicit", "none", "unrolled"])
        ),
    }
    errors = 0
    for _case in range(150):
        name = rng.choice(["pose_tangent", "points", "data", "config"])
        fn = rng.choice(list(entry_points))
        args = dict(good, data=problem.data, config=ts.SolverConfig(max_iterations=2))
        if name == "data":
            args["data"] = rng.choice([problem, None, "data", problem.data.observations])
        elif name == "config":
            args["config"] = rng.choice(["lm", ts.SolverConfig, {"max_iterations": 3}, 3])
        else:
            args[name] = _random_value(rng, good[name])
        try:
            result = entry_points[fn](
                args["pose_tangent"], args["points"], args["data"], args["config"]
            )
        except (ValueError, TypeError) as error:
            assert fn in str(error), str(error)
            errors += 1
            continue
        _check_result(result, 2)
    assert errors > 100


def test_fuzz_terms():
    rng = random.Random(11)
    inputs = _tiny(B=2)
    poses = inputs["poses"][0]
    good = {
        "pose_index": torch.tensor([[0, 1], [1, 2]]),
        "measurements": poses[:2] @ se3.inverse(poses[1:3]),
        "weight": torch.ones(2, dtype=F64),
        "valid": torch.tensor([True, True]),
    }
    outcomes = {"error": 0, "solved": 0}
    for _case in range(80):
        kwargs = dict(good)
        if rng.random() < 0.4:  # benign: a padding instance holding NaN and a wild index
            kwargs["valid"] = torch.tensor([rng.random() < 0.5, True])
            kwargs["measurements"] = good["measurements"].clone()
            kwargs["measurements"][~kwargs["valid"]] = math.nan
            kwargs["pose_index"] = torch.where(kwargs["valid"][:, None], good["pose_index"], -7)
            kwargs["weight"] = torch.rand(2, dtype=F64)
            name = None
        else:
            name = rng.choice(list(good))
            kwargs[name] = _random_value(rng, good[name])
        try:
            term = ts.RelativePoseTerm(
                kwargs.pop("pose_index"), kwargs.pop("measurements"), **kwargs
            )
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                problem = PointMapProblem(**inputs, terms=[term])
        except (ValueError, TypeError) as error:
            assert name is not None, error  # a benign variation must be accepted
            _assert_clean_error(error, name)
            outcomes["error"] += 1
            continue
        _check_result(ts.solve(problem, ts.SolverConfig(max_iterations=2)), 2)
        outcomes["solved"] += 1
    assert outcomes["error"] > 20 and outcomes["solved"] > 10, outcomes


def test_fuzz_config_and_losses():
    rng = random.Random(5)
    fields = {f.name: f.default for f in dataclasses.fields(ts.SolverConfig)}
    for _case in range(200):
        name = rng.choice(list(fields))
        value = rng.choice(
            [None, "x", -1, 0, 1, 2.5, -0.5, math.nan, math.inf, True, [1], 10**400, 1e-300]
        )
        try:
            config = ts.SolverConfig(**{name: value})
        except ValueError as error:
            assert f"SolverConfig: '{name}'" in str(error)
            continue
        big = value == 10**400 and isinstance(fields[name], float)
        assert getattr(config, name) == (math.inf if big else value)
    for _case in range(100):
        kind = rng.choice([ts.HuberLoss, ts.CauchyLoss, ts.TukeyLoss])
        value = rng.choice([None, "1", -1, 0, 1e-300, 1e300, math.nan, -math.inf, True, 10**400])
        try:
            loss = kind(value)
        except (ValueError, TypeError) as error:
            assert f"{kind.__name__}: argument 'scale'" in str(error)
            continue
        out = loss(torch.tensor(SQUARED, dtype=F64))
        assert all(bool(torch.isfinite(o).all()) for o in out)


def test_jacobians_module_functions_check_arguments():
    R = torch.eye(3, dtype=F64).expand(4, 3, 3)
    X = torch.zeros(4, 3, dtype=F64)
    with pytest.raises(ValueError, match=r"jacobians.analytic_blocks: 'R' and 'points'"):
        jacobians.analytic_blocks(R, X[:3])
    with pytest.raises(TypeError, match=r"jacobians.analytic_blocks: 'R' is torch.float64"):
        jacobians.analytic_blocks(R, X.float())
    xi = torch.zeros(4, 6, dtype=F64)
    with pytest.raises(ValueError, match=r"jacobians.jacrev_blocks: argument 'points'"):
        jacobians.jacrev_blocks(xi, X[:, :2], X)
    assert jacobians.jacrev_blocks(xi[:0], X[:0], X[:0])[0].shape == (0, 3, 6)
    with pytest.raises(ValueError, match=r"central_difference_blocks: 'eps'"):
        jacobians.central_difference_blocks(xi, X, X, eps=0.0)
    J_xi, J_X = torch.zeros(1, 4, 3, 6, dtype=F64), torch.zeros(1, 4, 3, 3, dtype=F64)
    index = torch.zeros(1, 4, dtype=torch.long)
    with pytest.raises(ValueError, match=r"dense_jacobian: 'pose_index' out of range \[0, 2\)"):
        jacobians.dense_jacobian(J_xi, J_X, index + 2, index, 2, 1)
    with pytest.raises(TypeError, match=r"dense_jacobian: 'point_index' must be an integer"):
        jacobians.dense_jacobian(J_xi, J_X, index, index.double(), 2, 1)
    with pytest.raises(ValueError, match=r"dense_jacobian: argument 'J_r_xi' must have shape"):
        jacobians.dense_jacobian(J_xi[:, :3], J_X, index, index, 2, 1)
    with pytest.raises(ValueError, match=r"dense_jacobian: 'num_points' must be an int"):
        jacobians.dense_jacobian(J_xi, J_X, index, index, 2, -1)


def test_zero_weight_gradients_are_finite_or_refused_never_nan():
    # A valid observation with weight exactly 0: its weight's gradient is finite (structured
    # path, implicit backward) or refused with a clear error (unrolling the √w block path),
    # never NaN.
    from torchslam.data import make_scene
    from torchslam.initialization import initialize_scene

    scene = make_scene(4, 12, batch_size=1, noise_std=0.01, seed=3)
    init = initialize_scene(scene, method="odometry")
    w = torch.ones(scene.valid.shape, dtype=torch.float64)
    w[0, scene.valid[0].nonzero()[0, 0]] = 0.0
    w.requires_grad_(True)
    cases = [
        ("jacrev", "schur", "unrolled", False),
        ("analytic", "dense", "unrolled", False),
        ("analytic", "schur", "unrolled", True),
        ("jacrev", "schur", "implicit", True),
        ("analytic", "dense", "implicit", True),
    ]
    for jacobian, linear_solver, backward, allowed in cases:
        problem = ts.PointMapProblem(
            init.poses,
            init.points,
            scene.pose_index,
            scene.point_index,
            scene.observations,
            valid=scene.valid,
            weights=w,
        )
        config = ts.SolverConfig(jacobian=jacobian, linear_solver=linear_solver)

        def run(problem=problem, config=config, backward=backward):
            return solve_differentiable(
                problem.pose_tangent.detach(),
                problem.points.detach(),
                problem.data,
                config,
                backward=backward,
            )

        if not allowed:
            with pytest.raises(ValueError, match=r"solve_differentiable.*weight of exactly 0"):
                run()
            continue
        (grad,) = torch.autograd.grad(run().poses.sum(), w)
        assert torch.isfinite(grad).all()


def test_solve_differentiable_rejects_a_non_config_implicit():
    problem = _build(**_tiny())
    with pytest.raises(TypeError, match=r"solve_differentiable.*'implicit'"):
        solve_differentiable(
            problem.pose_tangent, problem.points, problem.data, implicit={"hessian": "exact"}
        )


def test_shape_messages_name_the_dims_and_suggest_the_batch_dim():
    problem = _build(**_tiny())
    with pytest.raises(ValueError) as caught:
        solve_differentiable(problem.pose_tangent[0], problem.points, problem.data)
    message = str(caught.value)
    assert "(B, m, 6)" in message and "pose_tangent[None]" in message
    assert "(B, B" not in message


def test_a_learnable_loss_scale_moved_below_zero_is_refused_at_solve_time():
    scale = torch.tensor(0.1, dtype=F64, requires_grad=True)
    problem = _build(**_tiny(), loss=ts.HuberLoss(scale))
    with torch.no_grad():
        scale.sub_(0.5)  # an optimizer step pushed it negative
    with pytest.raises(ValueError, match=r"solve_differentiable: data\.loss HuberLoss.*scale"):
        solve_differentiable(problem.pose_tangent, problem.points, problem.data)
    with pytest.raises(ValueError, match=r"solve: data\.loss HuberLoss.*scale"):
        ts.solve(problem)


def test_losses_take_zero_dim_scales_and_inputs():
    for kind in (ts.HuberLoss, ts.CauchyLoss, ts.TukeyLoss):
        rho = kind(torch.tensor(0.3, dtype=F64))(torch.tensor(1.0, dtype=F64))
        assert all(r.shape == () and torch.isfinite(r) for r in rho)


@pytest.mark.parametrize("backward", ["unrolled", "truncated"])
def test_unmoved_outputs_of_an_unrolled_solve_carry_zero_gradients(backward):
    # No iteration runs: the outputs are constants of the data, d/d(observations) = 0, as the
    # implicit mode returns; backward() must work (not torch's "does not require grad").
    inputs = _tiny()
    observations = inputs["observations"].clone().requires_grad_(True)
    problem = _build(**{**inputs, "observations": observations})
    result = solve_differentiable(
        problem.pose_tangent.detach(),
        problem.points.detach(),
        problem.data,
        ts.SolverConfig(max_iterations=0),
        backward=backward,
        on_unconverged="unroll",
    )
    (grad,) = torch.autograd.grad(result.pose_tangent.sum() + result.points.sum(), observations)
    assert torch.equal(grad, torch.zeros_like(grad))


class _PositionTerm(ts.Term):
    def residual(self, poses):
        return poses[..., 0, :3, 3]


class _WrongBlocks(_PositionTerm):
    def jacobians(self, poses):
        r = self.residual(poses)
        return r, r.new_zeros(*r.shape[:-1], 3, 6)  # the arity dim is missing


class _NoneBlocks(_PositionTerm):
    def jacobians(self, poses):
        return None, None


class _Unbatched(ts.Term):
    def residual(self, poses):
        return poses.new_zeros(1, 1, 3)  # ignores the leading dims


@pytest.mark.parametrize(
    ("kind", "error", "pattern"),
    [
        (_WrongBlocks, ValueError, r"_WrongBlocks\.jacobians: blocks must have shape"),
        (_NoneBlocks, TypeError, r"_NoneBlocks\.jacobians: residuals must be a torch\.Tensor"),
        (_Unbatched, ValueError, r"_Unbatched\.residual: .* must return shape \(d,\)"),
    ],
)
def test_user_terms_with_wrong_output_shapes_get_named_errors(kind, error, pattern):
    problem = _build(**_tiny(), terms=[kind(torch.tensor([[1]]))])
    with pytest.raises(error, match=pattern):
        ts.solve(problem)


def test_terms_none_means_no_terms():
    assert _build(**_tiny(), terms=None).data.terms == ()
