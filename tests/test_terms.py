"""Terms (torchslam.objective.terms): Jacobian blocks, costs, problems with terms, errors, solves.

Conventions: ξ = (ω, v) rotation first; right perturbation T ← T·Exp(δ); poses T_i0 map world
→ frame i. RelativePoseTerm r = Log(Z⁻¹ T_i T_j⁻¹) with Z ≈ T_i T_j⁻¹; PosePriorTerm
r = Log(Z⁻¹ T). Jacobian blocks are ∂r/∂δ_a (d × 6 per pose) at δ = 0.
"""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from torch import Tensor

import torchslam
from torchslam import HuberLoss, PointMapProblem, SolverConfig, solve, validation
from torchslam.data.synthetic import make_scene
from torchslam.lie import se3
from torchslam.objective import data as data_module
from torchslam.objective.terms import (
    PosePriorTerm,
    RelativePoseTerm,
    Term,
    term_cost,
    term_jacobians,
    term_poses,
)

F64 = torch.float64
# Angles of the residual rotation: ≈ 0 and ≈ π (Log is defined for |ω| < π only).
HARD_ANGLES = (0.0, 1e-9, 1e-5, 0.5, 2.0, math.pi - 1e-3, math.pi - 1e-6)
# Magnitudes of the translations of the poses, the measurements and the residual.
HARD_TRANSLATIONS = (0.0, 1e-9, 1.0, 1e4)
# Central-difference step: keeps π − 1e-6 below π under the perturbation.
FD_STEP = 1e-7
# Tight tolerances: the solves below run to round-off.
TIGHT = dict(function_tolerance=1e-15, gradient_tolerance=1e-12, parameter_tolerance=1e-15)


# --------------------------------------------------------------------------- inputs


def _random_poses(count: int, g: torch.Generator, scale: float = 1.0) -> Tensor:
    xi = torch.randn(count, 6, generator=g, dtype=F64)
    xi[:, 3:] *= scale
    return se3.exp(xi)


def _hard_twists(g: torch.Generator) -> Tensor:
    """Twists over every hard angle × every hard translation magnitude (two each), (K, 6)."""
    rows = []
    for angle in HARD_ANGLES:
        for scale in HARD_TRANSLATIONS:
            for _ in range(2):
                axis = torch.randn(3, generator=g, dtype=F64)
                v = torch.randn(3, generator=g, dtype=F64) * scale
                rows.append(torch.cat((angle * axis / axis.norm(), v)))
    return torch.stack(rows)


def _with_translation_scales(T: Tensor, g: torch.Generator) -> Tensor:
    """Rescale the translations of poses (K, 4, 4) cyclically through HARD_TRANSLATIONS
    (in a random order), so tiny and huge world translations meet every residual angle."""
    T = T.clone()
    scales = torch.tensor(HARD_TRANSLATIONS, dtype=F64)
    order = torch.randperm(T.shape[0], generator=g)
    T[:, :3, 3] *= scales.repeat(T.shape[0] // len(scales) + 1)[: T.shape[0]][order, None]
    return T


def _bound(term: Term, poses: Tensor) -> tuple[Term, Tensor]:
    """Bind a term to one problem with poses (m, 4, 4); return it and its (1, K, a, 4, 4)."""
    term = term.bind(1, poses.shape[0], poses)
    return term, term_poses(term, poses[None])


def _relative_case(kind: str, g: torch.Generator) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(T_i, T_j, Z, ξ) with K instances each.

    - "hard": E = Z⁻¹ T_i T_j⁻¹ = Exp(ξ) with every hard angle and translation, T_i and T_j
      with tiny to huge translations; so r = ξ. The last two instances have T_i = T_j pure
      translations (one huge) and Z = I, so E = I exactly (r = 0 bit for bit).
    - "random": everything random, world translations up to 1e4; ξ = Log(E).
    """
    if kind == "hard":
        xi = _hard_twists(g)
        K = xi.shape[0]
        T_i = _with_translation_scales(_random_poses(K, g), g)
        T_j = _with_translation_scales(_random_poses(K, g), g)
        Z = T_i @ se3.inverse(T_j) @ se3.exp(-xi)
        shift = se3.exp(torch.tensor([[0, 0, 0, 0.3, -2, 1], [0, 0, 0, 1e4, 3e3, -2e3]], dtype=F64))
        eye = torch.eye(4, dtype=F64).expand(2, 4, 4)
        xi = torch.cat((xi, xi.new_zeros(2, 6)))
        return torch.cat((T_i, shift)), torch.cat((T_j, shift)), torch.cat((Z, eye)), xi
    T_i = _random_poses(24, g, scale=1e4)
    T_j = _random_poses(24, g, scale=1e3)
    Z = _random_poses(24, g, scale=10.0)
    return T_i, T_j, Z, se3.log(se3.inverse(Z) @ T_i @ se3.inverse(T_j))


def _relative_term(T_i: Tensor, T_j: Tensor, Z: Tensor) -> tuple[Term, Tensor]:
    K = T_i.shape[0]
    poses = torch.cat((T_i, T_j))
    index = torch.stack((torch.arange(K), torch.arange(K, 2 * K)), dim=-1)
    return _bound(RelativePoseTerm(index, Z), poses)


def _prior_case(kind: str, g: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """(T, Z, ξ): "hard" has Z⁻¹T = Exp(ξ) over the hard twists, plus T = Z (r = 0 to
    round-off); "random" is random with ξ = Log(Z⁻¹T)."""
    if kind == "hard":
        xi = _hard_twists(g)
        Z = _with_translation_scales(_random_poses(xi.shape[0] + 1, g), g)
        T = torch.cat((Z[:-1] @ se3.exp(xi), Z[-1:]))
        return T, Z, torch.cat((xi, xi.new_zeros(1, 6)))
    T, Z = _random_poses(24, g, scale=1e4), _random_poses(24, g, scale=1e4)
    return T, Z, se3.log(se3.inverse(Z) @ T)


def _prior_term(T: Tensor, Z: Tensor) -> tuple[Term, Tensor]:
    return _bound(PosePriorTerm(torch.arange(T.shape[0]), Z), T)


# --------------------------------------------------------------------------- comparisons


def _central_blocks(term: Term, P: Tensor, h: float = FD_STEP) -> Tensor:
    """∂r/∂δ_a by central differences on the manifold, T_a ← T_a·Exp(±h e_q): (B, K, d, a, 6)."""
    columns = []
    with validation(False):
        for a in range(P.shape[2]):
            for q in range(6):
                step = torch.zeros(6, dtype=P.dtype)
                step[q] = h
                plus, minus = P.clone(), P.clone()
                plus[:, :, a] = P[:, :, a] @ se3.exp(step)
                minus[:, :, a] = P[:, :, a] @ se3.exp(-step)
                r_plus = term.residual(plus, **term.constants)
                r_minus = term.residual(minus, **term.constants)
                columns.append((r_plus - r_minus) / (2 * h))
    B, K, a = P.shape[:3]
    return torch.stack(columns, dim=-1).reshape(B, K, -1, a, 6)


def _scale(term: Term, P: Tensor) -> Tensor:
    """1 + Σ |translations| of an instance's poses and measurements, (B, K): the size of what
    the residual adds up, which sets the round-off of a central difference."""
    scale = 1 + P[..., :3, 3].norm(dim=-1).sum(-1)
    if "measurements" in term.constants:
        scale = scale + term.constants["measurements"][..., :3, 3].norm(dim=-1)
    return scale


def _assert_matches_central_differences(term: Term, P: Tensor, J: Tensor) -> None:
    fd = _central_blocks(term, P)
    err = (J - fd).flatten(-3).norm(dim=-1)
    round_off = 1e-15 * _scale(term, P) / FD_STEP
    bound = 1e-6 * fd.flatten(-3).norm(dim=-1) + round_off
    worst = int((err - bound).argmax())
    assert bool((err <= bound).all()), (
        f"instance {worst}: |J − fd| = {float(err.flatten()[worst]):.3g} > "
        f"{float(bound.flatten()[worst]):.3g}"
    )


def _relative_error(A: Tensor, B: Tensor) -> Tensor:
    """Per-instance relative Frobenius error over the last three dims (d, a, 6)."""
    return (A - B).flatten(-3).norm(dim=-1) / B.flatten(-3).norm(dim=-1)


# --------------------------------------------------------------------------- Jacobian blocks


@pytest.mark.parametrize("kind", ["hard", "random"])
def test_relative_pose_analytic_equals_jacrev(kind, generator):
    term, P = _relative_term(*_relative_case(kind, generator)[:3])
    r, J = term_jacobians(term, P, "analytic")
    r_ref, J_ref = term_jacobians(term, P, "jacrev")
    assert J.shape == (1, term.num_instances, 6, 2, 6)
    torch.testing.assert_close(r, r_ref, rtol=0, atol=0)
    # Both differentiate through sums of the instance's translations (up to 1e4 here): their
    # round-off, ε·_scale relative to blocks of size ~1, bounds the disagreement.
    eps = torch.finfo(J.dtype).eps
    assert bool((_relative_error(J, J_ref) <= 16 * eps * _scale(term, P)).all())


@pytest.mark.parametrize("kind", ["hard", "random"])
def test_relative_pose_analytic_equals_central_differences(kind, generator):
    term, P = _relative_term(*_relative_case(kind, generator)[:3])
    _, J = term_jacobians(term, P, "analytic")
    _assert_matches_central_differences(term, P, J)


@pytest.mark.parametrize("case", ["relative", "prior"])
def test_hard_residuals_have_the_hard_angles(case, generator):
    """The hard inputs really reach r = 0 exactly, angles of 1e-9 and of π − 1e-6, and the
    residual is the twist they were built from (r = ξ)."""
    if case == "relative":
        *inputs, xi = _relative_case("hard", generator)
        term, P = _relative_term(*inputs)
    else:
        *inputs, xi = _prior_case("hard", generator)
        term, P = _prior_term(*inputs)
    r, _ = term_jacobians(term, P, "analytic")
    angles = r[0, :, :3].norm(dim=-1)
    scale = 1 + _scale(term, P)[0]
    # The last instance has T = Z: its residual is zero to round-off, not bit for bit. The
    # product Z⁻¹T is the identity only up to the rounding of a matmul, which depends on the
    # machine's kernels (FMA or not): 5e-26 on a translation of this size on one AMD machine,
    # exactly 0 on others. Round-off of that product is below ε times the translations.
    assert float(r[0, -1].abs().max()) <= 1e-15 * float(scale[-1])
    assert bool(((angles > 5e-10) & (angles < 2e-9)).any())
    assert angles.max() > math.pi - 2e-6 and angles.max() < math.pi
    assert bool(((r[0] - xi).abs().amax(-1) <= 1e-15 * scale).all())


def test_relative_pose_blocks_at_the_measurement(generator):
    """At r = 0: ∂r/∂δ_i = Ad(T_j) = −∂r/∂δ_j."""
    T_i = _random_poses(6, generator, scale=5.0)
    T_j = _random_poses(6, generator, scale=5.0)
    term, P = _relative_term(T_i, T_j, T_i @ se3.inverse(T_j))
    r, J = term_jacobians(term, P, "analytic")
    assert r.abs().max() <= 1e-12
    torch.testing.assert_close(J[0, :, :, 0], se3.adjoint(T_j), rtol=0, atol=1e-10)
    torch.testing.assert_close(J[0, :, :, 1], -se3.adjoint(T_j), rtol=0, atol=1e-10)


@pytest.mark.parametrize("kind", ["hard", "random"])
def test_pose_prior_analytic_equals_jacrev_and_central_differences(kind, generator):
    term, P = _prior_term(*_prior_case(kind, generator)[:2])
    r, J = term_jacobians(term, P, "analytic")
    r_ref, J_ref = term_jacobians(term, P, "jacrev")
    assert J.shape == (1, term.num_instances, 6, 1, 6)
    torch.testing.assert_close(r, r_ref, rtol=0, atol=0)
    # Both differentiate through sums of the instance's translations (up to 1e4 here): their
    # round-off, ε·_scale relative to blocks of size ~1, bounds the disagreement.
    eps = torch.finfo(J.dtype).eps
    assert bool((_relative_error(J, J_ref) <= 16 * eps * _scale(term, P)).all())
    _assert_matches_central_differences(term, P, J)


class RangeTerm(Term):
    """A user term without analytic blocks: r = |c_i − c_j| − d, c = −Rᵀt the sensor
    position of a frame in the world (arity 2, d = 1)."""

    def __init__(self, pose_index: Tensor, distance: Tensor, **kwargs) -> None:
        super().__init__(pose_index, {"distance": distance}, **kwargs)

    def residual(self, poses: Tensor, distance: Tensor) -> Tensor:
        R, t = poses[..., :3, :3], poses[..., :3, 3:]
        c = -(R.transpose(-1, -2) @ t)[..., 0]
        return (c[..., 0, :] - c[..., 1, :]).norm(dim=-1, keepdim=True) - distance[..., None]


class PositionTerm(Term):
    """A user term without analytic blocks: r = c_i − c (arity 1, d = 3)."""

    def __init__(self, pose_index: Tensor, position: Tensor, **kwargs) -> None:
        super().__init__(pose_index[:, None], {"position": position}, **kwargs)

    def residual(self, poses: Tensor, position: Tensor) -> Tensor:
        R, t = poses[..., 0, :3, :3], poses[..., 0, :3, 3:]
        return -(R.transpose(-1, -2) @ t)[..., 0] - position


def test_user_term_without_analytic_blocks_uses_jacrev(generator):
    # Sensors metres to kilometres apart (|c_i − c_j| > 0: the norm is smooth there).
    T = _random_poses(16, generator, scale=3.0)
    T[:4, :3, 3] *= 1e3
    index = torch.stack((torch.arange(8), torch.arange(8, 16)), dim=-1)
    distance = torch.rand(8, generator=generator, dtype=F64)
    for term in (
        RangeTerm(index, distance),
        PositionTerm(torch.arange(16), torch.randn(16, 3, generator=generator, dtype=F64)),
    ):
        bound, P = _bound(term, T)
        assert bound.jacobians(P, **bound.constants) is None
        r, J = term_jacobians(bound, P, "analytic")
        r_ref, J_ref = term_jacobians(bound, P, "jacrev")
        assert J.shape == (1, term.num_instances, r.shape[-1], term.arity, 6)
        torch.testing.assert_close(J, J_ref, rtol=0, atol=0)
        torch.testing.assert_close(r, r_ref, rtol=0, atol=0)
        _assert_matches_central_differences(bound, P, J)


# --------------------------------------------------------------------------- costs


def _hand_relative_residuals(poses: Tensor, index: Tensor, Z: Tensor) -> Tensor:
    return se3.log(se3.inverse(Z) @ poses[index[:, 0]] @ se3.inverse(poses[index[:, 1]]))


def _huber(s: Tensor, a: float) -> Tensor:
    return torch.where(s <= a * a, s, 2 * a * s.sqrt() - a * a)


def test_term_cost_by_hand(generator):
    m, K = 5, 6
    poses = _random_poses(m, generator, scale=2.0)
    index = torch.randint(0, m, (K, 2), generator=generator)
    Z = _random_poses(K, generator)
    r = _hand_relative_residuals(poses, index, Z)
    s_unit = (r * r).sum(-1)
    A = torch.randn(K, 6, 6, generator=generator, dtype=F64)
    information = A @ A.mT + 0.1 * torch.eye(6, dtype=F64)
    s_info = (r[:, None, :] @ information @ r[:, :, None])[:, 0, 0]
    weight = torch.rand(K, generator=generator, dtype=F64)
    # Huber's knee in the middle of the squared norms: some inside, some outside.
    a = float(s_unit.median().sqrt())
    valid = torch.tensor([True, False, True, True, False, True])
    padded_index = torch.where(valid[:, None], index, 99)  # padding may hold any index
    cases = [
        (RelativePoseTerm(index, Z), 0.5 * s_unit.sum()),
        (RelativePoseTerm(index, Z, information=information), 0.5 * s_info.sum()),
        (RelativePoseTerm(index, Z, weight=weight), 0.5 * (weight * s_unit).sum()),
        (RelativePoseTerm(index, Z, loss=HuberLoss(a)), 0.5 * _huber(s_unit, a).sum()),
        (
            RelativePoseTerm(index, Z, weight=weight, loss=HuberLoss(a)),
            0.5 * _huber(weight * s_unit, a).sum(),
        ),
        (RelativePoseTerm(padded_index, Z, valid=valid), 0.5 * s_unit[valid].sum()),
        (
            RelativePoseTerm(
                padded_index, Z, information=information, loss=HuberLoss(a), valid=valid
            ),
            0.5 * _huber(s_info, a)[valid].sum(),
        ),
    ]
    assert bool((s_unit > a * a).any()) and bool((s_unit < a * a).any())
    for term, expected in cases:
        bound = term.bind(1, m, poses)
        torch.testing.assert_close(
            term_cost(bound, poses[None]), expected[None], rtol=1e-13, atol=0
        )

    prior_r = se3.log(se3.inverse(Z[:2]) @ poses[[3, 1]])
    prior = PosePriorTerm(torch.tensor([3, 1]), Z[:2], weight=torch.tensor([2.0, 0.5], dtype=F64))
    expected = 0.5 * (2.0 * prior_r[0].square().sum() + 0.5 * prior_r[1].square().sum())
    got = term_cost(prior.bind(1, m, poses), poses[None])
    torch.testing.assert_close(got, expected[None], rtol=1e-13, atol=0)


# --------------------------------------------------------------------------- problems with terms


def _scene_problem_inputs(seed: int, B: int = 1, m: int = 5, n: int = 24, noise: float = 0.01):
    scene = make_scene(m, n, batch_size=B, visible_fraction=0.6, noise_std=noise, seed=seed)
    g = torch.Generator().manual_seed(seed + 100)
    poses = scene.poses_gt @ se3.exp(0.1 * torch.randn(B, m, 6, generator=g, dtype=F64))
    poses[:, 0] = scene.poses_gt[:, 0]  # the gauge
    points = scene.points_gt + 0.1 * torch.randn(B, n, 3, generator=g, dtype=F64)
    return scene, poses, points, g


def _problem(scene, poses, points, terms=(), **kwargs) -> PointMapProblem:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return PointMapProblem(
            poses,
            points,
            scene.pose_index,
            scene.point_index,
            scene.observations,
            valid=scene.valid,
            terms=list(terms),
            **kwargs,
        )


def _odometry(scene, g: torch.Generator, sigma: float = 0.01) -> tuple[Tensor, Tensor]:
    """Chain measurements Z_(i,i+1) = T_i T_(i+1)⁻¹ Exp(noise): index (m−1, 2), Z (B, m−1, 4, 4)."""
    T = scene.poses_gt
    B, m = T.shape[:2]
    noise = sigma * torch.randn(B, m - 1, 6, generator=g, dtype=F64)
    Z = T[:, :-1] @ se3.inverse(T[:, 1:]) @ se3.exp(noise)
    index = torch.stack((torch.arange(m - 1), torch.arange(1, m)), dim=-1)
    return index, Z


def test_problem_cost_is_point_cost_plus_term_costs_and_broadcasts():
    scene, poses, points, g = _scene_problem_inputs(3, B=2)
    index, Z = _odometry(scene, g)
    # A term shared by the batch (no batch dim) and a batched one.
    shared = RelativePoseTerm(index, Z[0], weight=torch.full((4,), 3.0, dtype=F64))
    prior_Z = scene.poses_gt[:, 2:4] @ se3.exp(0.05 * torch.randn(2, 2, 6, generator=g, dtype=F64))
    batched = PosePriorTerm(torch.tensor([[2, 3], [3, 2]]), prior_Z)
    plain = _problem(scene, poses, points)
    with_terms = _problem(scene, poses, points, [shared, batched])
    T = plain.poses.detach()
    expected = plain.cost().detach().clone()
    for b in range(2):
        r = _hand_relative_residuals(T[b], index, Z[0])
        expected[b] += 0.5 * 3.0 * r.square().sum()
        order = [2, 3] if b == 0 else [3, 2]
        r = se3.log(se3.inverse(prior_Z[b]) @ T[b, order])
        expected[b] += 0.5 * r.square().sum()
    torch.testing.assert_close(with_terms.cost().detach(), expected, rtol=1e-13, atol=0)
    assert with_terms.data.terms[0].pose_index.shape == (2, 4, 2)
    # A batch of size 1 broadcasts too.
    one = RelativePoseTerm(index[None], Z[:1])
    problem = _problem(scene, poses, points, [one])
    r = _hand_relative_residuals(T[1], index, Z[0])
    torch.testing.assert_close(
        problem.cost()[1].detach(), plain.cost()[1].detach() + 0.5 * r.square().sum()
    )


def _weak_last_pose_inputs():
    """A scene whose last pose keeps < 3 valid observations (each of a point seen elsewhere)."""
    scene = make_scene(4, 12, visible_fraction=0.75, seed=5)
    valid = scene.valid.clone()
    views = torch.bincount(scene.point_index[0][valid[0]], minlength=12)
    kept = 0
    for e in (scene.pose_index[0] == 3).nonzero()[:, 0].tolist():
        j = int(scene.point_index[0, e])
        if kept < 2 or views[j] < 2:
            kept += 1
        else:
            valid[0, e] = False
            views[j] -= 1
    assert int((valid[0] & (scene.pose_index[0] == 3)).sum()) < 3
    return scene, valid


def _weak_problem(scene, valid, terms):
    return PointMapProblem(
        scene.poses_gt,
        scene.points_gt,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        valid=valid,
        terms=terms,
    )


def test_relative_term_keeps_a_weakly_observed_pose_free():
    scene, valid = _weak_last_pose_inputs()
    with pytest.warns(UserWarning, match="pose 3 has 2 observation"):
        problem = _weak_problem(scene, valid, [])
    assert bool(problem.data.fixed_poses[0, 3])
    # A relative pose to the (fixed) pose 0 gives it 6 rows: free, and no warning.
    Z = scene.poses_gt[:, 0] @ se3.inverse(scene.poses_gt[:, 3])
    for term in (
        RelativePoseTerm(torch.tensor([[0, 3]]), Z),
        PosePriorTerm(torch.tensor([3]), scene.poses_gt[:, 3]),
    ):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            problem = _weak_problem(scene, valid, [term])
        assert not bool(problem.data.fixed_poses[0, 3])
        assert problem.diagnostics == []
    # One 1-dim residual is not enough: still held fixed, with the warning.
    one_row = RangeTerm(torch.tensor([[0, 3]]), torch.ones(1, dtype=F64))
    with pytest.warns(UserWarning, match="pose 3"):
        problem = _weak_problem(scene, valid, [one_row])
    assert bool(problem.data.fixed_poses[0, 3])


# --------------------------------------------------------------------------- errors


def test_term_argument_errors(generator):
    Z = _random_poses(3, generator)
    index = torch.tensor([[0, 1], [1, 2], [2, 3]])
    with pytest.raises(TypeError, match="'pose_index' must be an integer tensor"):
        RelativePoseTerm(index.double(), Z)
    with pytest.raises(TypeError, match="'pose_index' must be an integer tensor"):
        PosePriorTerm(torch.tensor([True, False, True]), Z)
    for dtype in (torch.complex64, torch.complex128):
        with pytest.raises(TypeError, match="'pose_index' must be an integer tensor"):
            Term(torch.zeros(1, 1, dtype=dtype))
    with pytest.raises(TypeError, match=r"'pose_index' must be a torch\.Tensor"):
        Term([[0, 1]])
    with pytest.raises(ValueError, match="'pose_index' must have shape"):
        RelativePoseTerm(torch.zeros(3, 3, dtype=torch.long), Z)
    with pytest.raises(ValueError, match="'pose_index' must have shape"):
        PosePriorTerm(torch.zeros(1, 1, 3, dtype=torch.long), Z)
    with pytest.raises(ValueError, match="'pose_index' must have shape"):
        Term(torch.zeros(3, dtype=torch.long))
    with pytest.raises(ValueError, match="'weight' or 'information', not both"):
        RelativePoseTerm(
            index,
            Z,
            weight=torch.ones(3, dtype=F64),
            information=torch.eye(6, dtype=F64).expand(3, 6, 6),
        )
    with pytest.raises(ValueError, match="'information' must have shape"):
        RelativePoseTerm(index, Z, information=torch.ones(3, 6, dtype=F64))
    with pytest.raises(ValueError, match="'weight' must have shape"):
        RelativePoseTerm(index, Z, weight=torch.ones(4, dtype=F64))
    with pytest.raises(ValueError, match="'weight' must be finite and ≥ 0"):
        RelativePoseTerm(index, Z, weight=-torch.ones(3, dtype=F64))
    with pytest.raises(TypeError, match="'valid' must be a bool tensor"):
        RelativePoseTerm(index, Z, valid=torch.ones(3))
    with pytest.raises(ValueError, match=r"'valid' must be a bool tensor of shape \(3,\)"):
        RelativePoseTerm(index, Z, valid=torch.ones(2, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"'measurements' must have shape \(3,\) \+ \(4, 4\)"):
        RelativePoseTerm(index, Z[:2])
    with pytest.raises(TypeError, match="'measurements'"):
        RelativePoseTerm(index, Z.to(torch.int64))
    with pytest.raises(TypeError, match=r"'pose_index' must be a torch\.Tensor"):
        PosePriorTerm([0], Z[:1])
    with pytest.raises(ValueError, match="'measurements' must have shape"):
        RelativePoseTerm(index, Z[:, None].expand(3, 2, 4, 4))
    with pytest.raises(ValueError, match="'measurements' must have shape"):
        PosePriorTerm(torch.tensor([0, 1]), Z)
    with pytest.raises(ValueError, match="constant 'X' must have leading shape"):
        Term(index, {"X": torch.zeros(2, 3, dtype=F64)})
    # Integer constants (e.g. labels) are allowed.
    assert Term(index, {"label": torch.arange(3)}).constants["label"].dtype == torch.int64
    eye = torch.eye(6, dtype=F64).expand(3, 6, 6)
    with pytest.raises(ValueError, match="'information' must be finite, symmetric positive"):
        RelativePoseTerm(index, Z, information=-eye)
    asymmetric = eye.clone()
    asymmetric[1, 0, 5] = 0.5
    with pytest.raises(ValueError, match=r"instance \(1,\) is not"):
        RelativePoseTerm(index, Z, information=asymmetric)
    with pytest.raises(ValueError, match=r"'information' must be finite.*instance \(0,\)"):
        RelativePoseTerm(index, Z, information=eye * float("nan"))


def test_problem_term_errors():
    scene, poses, points, g = _scene_problem_inputs(1, m=4, n=16)
    _, Z = _odometry(scene, g)
    Z = Z[0]

    def build(terms):
        return _problem(scene, poses, points, terms)

    with pytest.raises(
        ValueError, match=r"RelativePoseTerm: 'pose_index' out of range.*instance 1"
    ):
        build([RelativePoseTerm(torch.tensor([[0, 1], [1, 4], [2, 3]]), Z)])
    with pytest.raises(ValueError, match=r"PosePriorTerm: 'pose_index' out of range.*instance 2"):
        build([PosePriorTerm(torch.tensor([0, 1, -1]), Z)])
    with pytest.raises(ValueError, match="'pose_index' has batch size 3"):
        build([RelativePoseTerm(torch.zeros(3, 3, 2, dtype=torch.long), Z.expand(3, 3, 4, 4))])
    with pytest.raises(TypeError, match=r"'constants\.measurements' must have the problem's dtype"):
        build([RelativePoseTerm(torch.tensor([[0, 1], [1, 2], [2, 3]]), Z.float())])
    with pytest.raises(TypeError, match="'weight' must have the problem's dtype"):
        build([PosePriorTerm(torch.tensor([1, 2, 3]), Z, weight=torch.ones(3))])
    with pytest.raises(ValueError, match=r"'information' must be \(6, 6\)"):
        build(
            [
                PosePriorTerm(
                    torch.tensor([1, 2, 3]), Z, information=torch.eye(3, dtype=F64).expand(3, 3, 3)
                )
            ]
        )
    with pytest.raises(ValueError, match=r"residual must return shape \(\.\.\., d\)"):
        bad = RangeTerm(torch.tensor([[0, 1]]), torch.ones(1, dtype=F64))
        bad.residual = lambda poses, distance: distance  # (…,) instead of (…, d)
        build([bad])
    prior = PosePriorTerm(torch.tensor([1]), Z[:1])
    for not_a_list in (prior, {prior}, iter([prior])):
        with pytest.raises(TypeError, match="argument 'terms' must be a list or tuple"):
            PointMapProblem(
                poses,
                points,
                scene.pose_index,
                scene.point_index,
                scene.observations,
                valid=scene.valid,
                terms=not_a_list,
            )
    with pytest.raises(TypeError, match=r"terms\[1\] must be a torchslam.Term"):
        build([prior, "prior"])
    with pytest.raises(NotImplementedError, match="must implement residual"):
        build([Term(torch.zeros(1, 1, dtype=torch.long))])


# --------------------------------------------------------------------------- solves


def _mixed_problem(
    seed: int, B: int = 1, loss=None, outlier: bool = False, keep: slice | None = None
) -> PointMapProblem:
    """Points (weights) + an odometry chain (6×6 information) + a prior on the last pose;
    ``keep`` selects some problems of the batch (to solve them on their own)."""
    scene, poses, points, g = _scene_problem_inputs(seed, B=B)
    index, Z = _odometry(scene, g)
    if outlier:
        Z = Z.clone()
        Z[:, 1] = Z[:, 1] @ se3.exp(torch.tensor([0.3, 0, 0, 0.5, 0, 0], dtype=F64))
    m = scene.poses_gt.shape[1]
    prior_Z = scene.poses_gt[:, -1:] @ se3.exp(0.02 * torch.randn(B, 1, 6, generator=g, dtype=F64))
    # Weights 1/σ²: points σ = 0.01 (the scene's noise), odometry 0.01, prior 0.02.
    information = torch.diag(torch.tensor([1e4] * 6, dtype=F64))
    keep = keep or slice(None)
    k = len(range(B)[keep])
    odometry = RelativePoseTerm(
        index.expand(k, -1, -1), Z[keep], information=information.expand(k, m - 1, 6, 6), loss=loss
    )
    prior = PosePriorTerm(
        torch.full((k, 1), m - 1), prior_Z[keep], weight=torch.full((k, 1), 10.0, dtype=F64)
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return PointMapProblem(
            poses[keep],
            points[keep],
            scene.pose_index[keep],
            scene.point_index[keep],
            scene.observations[keep],
            valid=scene.valid[keep],
            weights=torch.full(scene.valid[keep].shape, 1e4, dtype=F64),
            terms=[odometry, prior],
        )


def _gradients(problem: PointMapProblem) -> tuple[Tensor, Tensor]:
    """Autograd ∂F/∂ξ of the free poses and ∂F/∂X of problem.cost()."""
    problem.zero_grad()
    problem.cost().sum().backward()
    return problem.pose_tangent.grad[~problem.data.fixed_poses], problem.points.grad


def _assert_stationary(problem: PointMapProblem, initial: PointMapProblem, rtol: float) -> None:
    """At the solution of a B = 1 problem whose only fixed pose is pose 0 (the gauge):
    max |∂F/∂(free ξ, points)| ≤ rtol · its value at the initial guess, and the Newton
    decrement ½ gᵀ∇²F⁻¹g (the decrease still to be had) is below the round-off of the cost,
    1e-16 F (exact gradient and Hessian of the cost by autograd, in the ξ chart)."""
    scale = max(float(g.abs().max()) for g in _gradients(initial))
    for name, g in zip(("pose", "point"), _gradients(problem), strict=True):
        assert float(g.abs().max()) <= rtol * scale, (name, float(g.abs().max()), scale)
    m = problem.num_poses
    assert problem.data.fixed_poses.tolist() == [[True] + [False] * (m - 1)]
    xi0, X0 = problem.pose_tangent.detach()[0], problem.points.detach()[0]

    def cost(x: Tensor) -> Tensor:
        xi = torch.cat((xi0[:1], x[: 6 * (m - 1)].reshape(m - 1, 6)))
        return data_module.cost(xi[None], x[6 * (m - 1) :].reshape(1, -1, 3), problem.data)[0]

    x = torch.cat((xi0[1:].reshape(-1), X0.reshape(-1)))
    with validation(False):
        g = torch.func.grad(cost)(x)
        H = torch.func.jacrev(torch.func.grad(cost))(x)
    decrement = 0.5 * float(g @ torch.linalg.solve(H, g))
    F = float(cost(x))
    assert 0 <= decrement <= 1e-16 * F, (decrement, F)


# Linear solvers: the full system ("dense"), or the Schur complement with its reduced pose
# system factored densely or sparsely (SuperLU).
LINEAR_SOLVERS = {
    "dense": dict(linear_solver="dense"),
    "schur-dense": dict(linear_solver="schur", reduced_solver="dense"),
    "schur-sparse": dict(linear_solver="schur", reduced_solver="sparse"),
}
_SOLVES: dict = {}


def _solved(linear_solver: str, jacobian: str):
    key = (linear_solver, jacobian)
    if key not in _SOLVES:
        problem = _mixed_problem(11)
        config = SolverConfig(jacobian=jacobian, **LINEAR_SOLVERS[linear_solver], **TIGHT)
        _SOLVES[key] = (problem, solve(problem, config))
    return _SOLVES[key]


@pytest.mark.parametrize("linear_solver", list(LINEAR_SOLVERS))
@pytest.mark.parametrize("jacobian", ["analytic", "jacrev"])
def test_mixed_solve_agrees_across_solvers_and_is_stationary(linear_solver, jacobian):
    problem, result = _solved(linear_solver, jacobian)
    _, reference_result = _solved("schur-dense", "analytic")
    assert result.converged == [True], result.summary()
    assert float(result.final_cost[0]) < 0.1 * float(result.initial_cost[0])
    torch.testing.assert_close(result.poses, reference_result.poses, rtol=0, atol=1e-9)
    torch.testing.assert_close(result.points, reference_result.points, rtol=0, atol=1e-9)
    torch.testing.assert_close(result.final_cost, reference_result.final_cost, rtol=1e-12, atol=0)
    torch.testing.assert_close(result.final_cost, problem.cost().detach(), rtol=1e-13, atol=0)
    # LM never accepts a step that increases the cost.
    assert bool((result.cost_history.diff(dim=1) <= 0).all())
    _assert_stationary(problem, _mixed_problem(11), 1e-10)


def test_batched_solve_equals_separate_solves():
    config = SolverConfig(**TIGHT)
    result = solve(_mixed_problem(21, B=2), config)
    assert result.converged == [True, True], result.summary()
    for b in range(2):
        one = solve(_mixed_problem(21, B=2, keep=slice(b, b + 1)), config)
        torch.testing.assert_close(one.poses[0], result.poses[b], rtol=0, atol=1e-9)
        torch.testing.assert_close(one.points[0], result.points[b], rtol=0, atol=1e-9)
        torch.testing.assert_close(one.final_cost[0], result.final_cost[b], rtol=1e-12, atol=0)


def _pose_error(poses: Tensor, seed: int) -> float:
    scene = _scene_problem_inputs(seed)[0]
    return float(se3.log(poses @ se3.inverse(scene.poses_gt)).norm(dim=-1).max())


def test_robust_term_converges():
    """A Huber odometry term with one wrong measurement converges (monotone LM cost history,
    gradient down to the resolution of the cost), down-weights the outlier, and recovers the
    poses better than least squares."""
    problem = _mixed_problem(31, loss=HuberLoss(3.0), outlier=True)
    result = solve(problem, SolverConfig(**TIGHT))
    assert result.converged == [True], result.summary()
    assert bool((result.cost_history.diff(dim=1) <= 0).all())
    # Huber's IRLS model converges linearly: LM stops where the cost decrease it could still
    # make is below the round-off of the cost (~1e-15 F), at gradients ~1e-7 (not 1e-12).
    assert float(result.gradient_norm[0]) <= 1e-5
    _assert_stationary(problem, _mixed_problem(31, loss=HuberLoss(3.0), outlier=True), 1e-9)
    # The outlier is in Huber's linear regime at the solution, the others are not.
    odometry = problem.data.terms[0]
    r = term_jacobians(odometry, term_poses(odometry, problem.poses.detach()))[0]
    s = (r[..., None, :] @ odometry.information @ r[..., None])[..., 0, 0]
    assert float(s[0, 1]) > 9.0 and float(s[0, [0, 2, 3]].max()) < 9.0
    # Least squares with the same outlier is pulled further from the ground truth.
    least_squares = _mixed_problem(31, outlier=True)
    solve(least_squares, SolverConfig(**TIGHT))
    assert _pose_error(problem.poses.detach(), 31) < 0.7 * _pose_error(
        least_squares.poses.detach(), 31
    )


def test_solve_agrees_with_scipy_least_squares():
    """The same objective (whitened point + term residuals) as a function of the se(3)
    coordinates ξ of the free poses (T = Exp(ξ)) and the points, minimized by scipy's
    trust-region least squares: the same minimum."""
    scipy_optimize = pytest.importorskip("scipy.optimize")
    problem = _mixed_problem(41)
    data = problem.data
    odometry, prior = data.terms
    xi0 = problem.pose_tangent.detach()[0]
    X0 = problem.points.detach()[0]
    m, n = xi0.shape[0], X0.shape[0]
    assert data.fixed_poses[0].tolist() == [True] + [False] * (m - 1)  # the gauge only
    valid = data.valid[0]
    i_e, j_e = data.pose_index[0][valid], data.point_index[0][valid]
    obs, sqrt_w = data.observations[0][valid], data.weights[0][valid].sqrt()
    i_odo, j_odo = odometry.pose_index[0].unbind(-1)
    Z_odo_inv = se3.inverse(odometry.constants["measurements"][0])
    U_odo = torch.linalg.cholesky(odometry.information[0]).mT  # UᵀU = Ω
    i_prior = prior.pose_index[0, :, 0]
    Z_prior_inv = se3.inverse(prior.constants["measurements"][0])
    sqrt_prior = prior.weight[0].sqrt()

    def residuals(x: Tensor) -> Tensor:
        """Whitened residual vector of points + terms; x = (ξ of poses 1 … m−1, points)."""
        T = se3.exp(torch.cat((xi0[:1], x[: 6 * (m - 1)].reshape(m - 1, 6))))
        X = x[6 * (m - 1) :].reshape(n, 3)
        r_points = obs - (T[i_e, :3, :3] @ X[j_e][..., None])[..., 0] - T[i_e, :3, 3]
        r_odo = se3.log(Z_odo_inv @ T[i_odo] @ se3.inverse(T[j_odo]))
        r_prior = se3.log(Z_prior_inv @ T[i_prior])
        return torch.cat(
            (
                (sqrt_w[:, None] * r_points).reshape(-1),
                (U_odo @ r_odo[..., None]).reshape(-1),
                (sqrt_prior[:, None] * r_prior).reshape(-1),
            )
        )

    jacobian = torch.func.jacrev(residuals)

    def fun(x):
        with validation(False):
            return residuals(torch.from_numpy(x)).numpy()

    def jac(x):
        with validation(False):
            return jacobian(torch.from_numpy(x)).numpy()

    x0 = torch.cat((xi0[1:].reshape(-1), X0.reshape(-1)))
    fit = scipy_optimize.least_squares(
        fun, x0.numpy(), jac=jac, method="trf", ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=100
    )
    ours = solve(problem, SolverConfig(**TIGHT))
    assert ours.converged == [True], ours.summary()
    assert 0.5 * float(residuals(x0).square().sum()) == pytest.approx(
        float(ours.initial_cost[0]), rel=1e-12
    )
    assert float(ours.final_cost[0]) == pytest.approx(fit.cost, rel=1e-10)
    # The same minimizer (the ξ chart and the right perturbations meet at the same poses).
    x = torch.from_numpy(fit.x)
    torch.testing.assert_close(ours.points[0], x[6 * (m - 1) :].reshape(n, 3), rtol=0, atol=1e-7)
    torch.testing.assert_close(
        ours.poses[0, 1:], se3.exp(x[: 6 * (m - 1)].reshape(-1, 6)), rtol=0, atol=1e-7
    )


# ------------------------------------------------------------------------------------------
# Edge cases found in review


def _loop_inputs(m: int = 10):
    from torchslam.data.loop import make_loop_scene

    loop = make_loop_scene(num_poses=m, points_per_frame=6, window=3, noise_std=0.01, seed=0)
    chain = [torch.eye(4, dtype=F64)]
    for Z in loop.odometry:
        chain.append(se3.inverse(Z) @ chain[-1])
    return loop, torch.stack(chain)[None]


def _loop_problem(loop, poses, terms):
    s = loop.scene
    return PointMapProblem(
        poses, s.points_gt, s.pose_index, s.point_index, s.observations, valid=s.valid, terms=terms
    )


@pytest.mark.parametrize("reduced_solver", ["dense", "sparse"])
def test_a_term_without_instances_changes_nothing(reduced_solver):
    loop, poses = _loop_inputs()
    empty = RelativePoseTerm(torch.zeros(0, 2, dtype=torch.long), torch.zeros(0, 4, 4, dtype=F64))
    odometry = RelativePoseTerm(loop.odometry_pairs, loop.odometry)
    config = SolverConfig(reduced_solver=reduced_solver)
    with_empty = _loop_problem(loop, poses, [empty, odometry])
    without = _loop_problem(loop, poses, [odometry])
    a, b = solve(with_empty, config), solve(without, config)
    assert a.converged and b.converged
    assert torch.equal(a.final_cost, b.final_cost)
    assert torch.equal(with_empty.pose_tangent, without.pose_tangent)


def test_term_weight_and_loss_gradients_implicit_equal_unrolled_and_finite_at_zero_weight():
    loop, poses = _loop_inputs()
    m = poses.shape[1]
    weight = torch.tensor([100.0] * (m - 2) + [0.0], dtype=F64, requires_grad=True)
    scale = torch.tensor(0.05, dtype=F64, requires_grad=True)
    config = SolverConfig(
        function_tolerance=1e-15, gradient_tolerance=1e-12, parameter_tolerance=1e-15
    )

    def loss_of(w, c, backward):
        term = RelativePoseTerm(loop.odometry_pairs, loop.odometry, weight=w, loss=HuberLoss(c))
        problem = _loop_problem(loop, poses, [term])
        result = torchslam.solve_differentiable(
            problem.pose_tangent.detach(),
            problem.points.detach(),
            problem.data,
            config,
            backward=backward,
        )
        return (result.pose_tangent[..., 3:] ** 2).sum()

    grads = {
        mode: torch.autograd.grad(loss_of(weight, scale, mode), (weight, scale))
        for mode in ("implicit", "unrolled")
    }
    for g in grads["implicit"] + grads["unrolled"]:
        assert torch.isfinite(g).all()
    torch.testing.assert_close(grads["implicit"][0], grads["unrolled"][0], rtol=1e-5, atol=1e-9)
    torch.testing.assert_close(grads["implicit"][1], grads["unrolled"][1], rtol=1e-5, atol=1e-9)
    # The loss scale's gradient is real (a wrong odometry step sits in Huber's linear range)
    # and matches finite differences. Each solve stops where LM's accept test stops seeing
    # decreases, so the loss carries a stopping noise of ~1e-9 that the machine's rounding
    # decides: a difference quotient has noise ~1e-9/h. The scale: central, h = 1e-5 (noise
    # ~2e-5 relative; a larger h reaches Huber's kink). The zero weight (one-sided, since w ≥ 0):
    # the second-order stencil (−3f(0) + 4f(h) − f(2h))/2h, truncation O(h²) ≈ 5e-5 relative
    # at h = 1e-2, noise ~1e-7: both far inside the 1e-3 asserted.
    h = 1e-5
    with torch.no_grad():
        fd_scale = (loss_of(weight, scale + h, "none") - loss_of(weight, scale - h, "none")) / (
            2 * h
        )
        h = 1e-2
        step = torch.zeros_like(weight)
        step[-1] = h
        f0, f1, f2 = (loss_of(weight + k * step, scale, "none") for k in (0, 1, 2))
        fd_weight = (-3 * f0 + 4 * f1 - f2) / (2 * h)
    assert float(grads["implicit"][1]) == pytest.approx(float(fd_scale), rel=1e-3)
    assert float(grads["implicit"][0][-1]) == pytest.approx(float(fd_weight), rel=1e-3)


def test_poses_tied_only_to_each_other_get_one_gauge_held():
    scene = make_scene(6, 30, seed=0)
    keep = scene.valid & (scene.pose_index < 4)  # poses 4 and 5 observe nothing
    T = scene.poses_gt

    def build(terms):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            problem = PointMapProblem(
                T,
                scene.points_gt,
                scene.pose_index,
                scene.point_index,
                scene.observations,
                valid=keep,
                terms=terms,
            )
        return problem, [str(w.message) for w in caught]

    def relative(pairs):
        pairs = torch.tensor(pairs)
        return RelativePoseTerm(pairs, T[0, pairs[:, 0]] @ se3.inverse(T[0, pairs[:, 1]]))

    problem, _ = build([])
    assert problem.data.fixed_poses[0].tolist() == [True, False, False, False, True, True]
    # 4 — 5 only: a free gauge; pose 4 is held, 5 follows through the term.
    problem, messages = build([relative([[4, 5]])])
    assert problem.data.fixed_poses[0].tolist() == [True, False, False, False, True, False]
    assert any("free gauge" in m and "pose 4 held fixed" in m for m in messages)
    # 3 — 4 — 5: tied to a well-observed pose, nothing held.
    problem, messages = build([relative([[3, 4], [4, 5]])])
    assert problem.data.fixed_poses[0].tolist() == [True] + [False] * 5
    assert not any("pose" in m and "held fixed" in m for m in messages)
    # A zero-weight link does not count.
    zero = RelativePoseTerm(
        torch.tensor([[3, 4], [4, 5]]),
        torch.stack((T[0, 3] @ se3.inverse(T[0, 4]), T[0, 4] @ se3.inverse(T[0, 5]))),
        weight=torch.tensor([0.0, 1.0], dtype=F64),
    )
    problem, _ = build([zero])
    assert problem.data.fixed_poses[0].tolist() == [True, False, False, False, True, False]
    # A prior anchors its pose.
    prior = PosePriorTerm(torch.tensor([5]), T[0, 5:6])
    problem, _ = build([relative([[4, 5]]), prior])
    assert problem.data.fixed_poses[0].tolist() == [True] + [False] * 5
