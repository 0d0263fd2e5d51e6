"""The CUDA path checked against the CPU: Lie functions, batched solves, implicit backward.

    python experiments/cuda_check.py                 # CUDA vs CPU (exits cleanly without CUDA)
    python experiments/cuda_check.py --device cpu    # dry run on a machine without a GPU

Every check runs the same float64 inputs on the CPU and on the device and compares:

1. every public function of ``torchslam.lie`` (so3, se3, convert) and its vector-Jacobian
   product, on rotation angles from 0 through the series branch to 3 rad: max |Δ| ≤ 1e-10
   (relative to the largest reference entry when that exceeds 1);
2. batched solves (``solve_tensors``): benchmark case BATCH (64 × S, the dense batched
   Cholesky), case S with ``linear_solver="dense"`` and case S with ``reduced_solver="sparse"``
   (SciPy's SuperLU on the host: a device → host → device round trip per iteration): the same
   iterations, statuses and accept/reject decisions per problem, cost histories to 1e-10
   relative and the final iterates to 1e-10;
3. ``solve_differentiable`` with the implicit backward (exact Hessian and Gauss-Newton) on 4
   scenes with outliers, learned weights and a learnable Huber scale: the gradients w.r.t.
   the weight logits, the scale, the observations and the initial guess, to 1e-8 relative
   (conjugate gradients stop at a 1e-10 relative residual, which the Hessian's conditioning
   amplifies);
4. ``pytest tests/lie`` (the suite's ``device`` fixture adds CUDA where available);

then times the BATCH solve on the device and on the CPU (median of ``--repeats``).

``--device cpu`` runs the same code with the CPU as the "device", and there the device side
runs inside ``with torch.device("meta")``: any tensor the library creates without an explicit
``device=`` lands on the meta device and fails loudly when combined with the CPU inputs,
exactly where a CPU tensor would meet CUDA inputs (``--no-meta-audit`` to switch off).

Exit status 0 when every check passes (or when there is no CUDA device), 1 otherwise.
``--out FILE`` writes the numbers as JSON.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

import torchslam as ts
from torchslam.lie import convert, se3, so3
from torchslam.solver.differentiable import ImplicitConfig, solve_differentiable

ROOT = Path(__file__).resolve().parents[1]
F64 = torch.float64
ITERATE_TOL = 1e-10
GRADIENT_TOL = 1e-8


class Report:
    """Collects named checks: the measured error, the tolerance, pass or fail."""

    def __init__(self) -> None:
        self.rows: list[dict] = []

    def check(self, name: str, error: float, tol: float, note: str = "") -> bool:
        ok = bool(error <= tol)  # NaN fails
        self.rows.append({"check": name, "error": error, "tol": tol, "ok": ok, "note": note})
        flag = "ok  " if ok else "FAIL"
        print(f"  [{flag}] {name:<58} {error:9.2e} (tol {tol:.0e}) {note}", flush=True)
        return ok

    @property
    def failed(self) -> list[str]:
        return [r["check"] for r in self.rows if not r["ok"]]


def max_error(a: Tensor, b: Tensor, relative: bool = True) -> float:
    """max |a − b| over entries (a on any device, b the CPU reference), relative to
    max(1, max |b|) when ``relative``; NaN in the same places counts as equal."""
    a = a.detach().cpu()
    b = b.detach().cpu()
    if a.shape != b.shape:
        return math.inf
    nan_a, nan_b = torch.isnan(a), torch.isnan(b)
    if not torch.equal(nan_a, nan_b):
        return math.inf
    a, b = a[~nan_a], b[~nan_b]
    if a.numel() == 0:
        return 0.0
    scale = max(1.0, float(b.abs().max())) if relative else 1.0
    return float((a - b).abs().max()) / scale


# ------------------------------------------------------------------------------------------
# 1. Lie functions


def lie_inputs(count: int = 64) -> dict[str, Tensor]:
    """Seeded float64 CPU inputs: angles 0, 1e-12, …, up to 3 rad (not at π, where log is
    ill-conditioned), translations from 0 to 10."""
    g = torch.Generator().manual_seed(7)
    axis = torch.randn(count, 3, generator=g, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    special = torch.tensor([0.0, 1e-12, 1e-8, 1e-4, 1e-2, 0.5, 1.5, 3.0], dtype=F64)
    angle = torch.cat((special, 3.0 * torch.rand(count - len(special), generator=g, dtype=F64)))
    omega = axis * angle[:, None]
    v = (
        torch.randn(count, 3, generator=g, dtype=F64)
        * torch.logspace(-9, 1, count, dtype=F64)[:, None]
    )
    xi = torch.cat((omega, v), -1)
    R = so3.exp(omega)
    T = se3.exp(xi)
    T2 = se3.exp(torch.randn(count, 6, generator=g, dtype=F64))
    return {
        "omega": omega,
        "xi": xi,
        "R": R,
        "T": T,
        "T2": T2,
        "t": v,
        "q": convert.axis_angle_to_quaternion(omega),
        "points": 3 * torch.randn(count, 3, generator=g, dtype=F64),
        "M": R + 1e-3 * torch.randn(count, 3, 3, generator=g, dtype=F64),
        "Omega": so3.hat(omega),
        "Xi": se3.hat(xi),
    }


LIE_FUNCTIONS: list[tuple[str, Callable, tuple[str, ...]]] = [
    ("so3.hat", so3.hat, ("omega",)),
    ("so3.vee", so3.vee, ("Omega",)),
    ("so3.exp", so3.exp, ("omega",)),
    ("so3.log", so3.log, ("R",)),
    ("so3.jl", so3.jl, ("omega",)),
    ("so3.jr", so3.jr, ("omega",)),
    ("so3.jl_inv", so3.jl_inv, ("omega",)),
    ("so3.jr_inv", so3.jr_inv, ("omega",)),
    ("so3.inverse", so3.inverse, ("R",)),
    ("so3.act", so3.act, ("R", "points")),
    ("so3.adjoint", so3.adjoint, ("R",)),
    ("so3.project", so3.project, ("M",)),
    ("se3.from_rotation_translation", se3.from_rotation_translation, ("R", "t")),
    ("se3.hat", se3.hat, ("xi",)),
    ("se3.vee", se3.vee, ("Xi",)),
    ("se3.exp", se3.exp, ("xi",)),
    ("se3.log", se3.log, ("T",)),
    ("se3.inverse", se3.inverse, ("T",)),
    ("se3.compose", se3.compose, ("T", "T2")),
    ("se3.act", se3.act, ("T", "points")),
    ("se3.adjoint", se3.adjoint, ("T",)),
    ("se3.jl", se3.jl, ("xi",)),
    ("se3.jr", se3.jr, ("xi",)),
    ("se3.jl_inv", se3.jl_inv, ("xi",)),
    ("se3.jr_inv", se3.jr_inv, ("xi",)),
    ("convert.quaternion_to_matrix", convert.quaternion_to_matrix, ("q",)),
    ("convert.matrix_to_quaternion", convert.matrix_to_quaternion, ("R",)),
    ("convert.axis_angle_to_quaternion", convert.axis_angle_to_quaternion, ("omega",)),
    ("convert.quaternion_to_axis_angle", convert.quaternion_to_axis_angle, ("q",)),
    ("convert.axis_angle_to_matrix", convert.axis_angle_to_matrix, ("omega",)),
    ("convert.matrix_to_axis_angle", convert.matrix_to_axis_angle, ("R",)),
    (
        "convert.pose_from_translation_quaternion",
        convert.pose_from_translation_quaternion,
        ("t", "q"),
    ),
    ("convert.pose_to_translation_quaternion", convert.pose_to_translation_quaternion, ("T",)),
]


def _value_and_vjp(fn: Callable, args: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
    """Outputs of fn(*args) and the gradient of Σ out·c (c a fixed pattern) w.r.t. args."""
    leaves = [a.detach().clone().requires_grad_(True) for a in args]
    out = fn(*leaves)
    outs = list(out) if isinstance(out, tuple) else [out]
    total = sum(
        (o * torch.linspace(-1, 1, o.numel(), dtype=o.dtype, device=o.device).view_as(o)).sum()
        for o in outs
    )
    grads = torch.autograd.grad(total, leaves, allow_unused=True)
    grads = [torch.zeros_like(a) if g is None else g for a, g in zip(leaves, grads, strict=True)]
    return [o.detach() for o in outs], [g.detach() for g in grads]


def check_lie(report: Report, device: torch.device, on_device: Callable) -> None:
    print("1. Lie functions (values and vector-Jacobian products), device vs CPU")
    inputs = lie_inputs()
    moved = {k: v.to(device) for k, v in inputs.items()}
    for name, fn, keys in LIE_FUNCTIONS:
        ref_out, ref_grad = _value_and_vjp(fn, [inputs[k] for k in keys])
        try:
            with on_device():
                out, grad = _value_and_vjp(fn, [moved[k] for k in keys])
        except Exception as exc:  # a device error is a finding, not a crash of the script
            report.check(name, math.inf, ITERATE_TOL, f"raised {type(exc).__name__}: {exc}")
            continue
        value_error = max(max_error(a, b) for a, b in zip(out, ref_out, strict=True))
        grad_error = max(max_error(a, b) for a, b in zip(grad, ref_grad, strict=True))
        devices = {t.device.type for t in out + grad}
        note = "" if devices == {device.type} else f"outputs on {sorted(devices)}"
        report.check(f"{name} value / VJP", max(value_error, grad_error), ITERATE_TOL, note)


# ------------------------------------------------------------------------------------------
# 2. Batched solves


def _case(name: str):
    scene = ts.data.benchmark_case(name, seed=0)
    init = ts.initialization.initialize_scene(
        scene, method="odometry", rotation_noise_deg=1.0, translation_noise=0.02, seed=1
    )
    return scene, init


def _solve(tensors: dict[str, Tensor], config: ts.SolverConfig):
    """Build the problem from raw tensors and solve it, recording every iteration."""
    history: list[dict] = []
    problem = ts.PointMapProblem(
        tensors["poses"],
        tensors["points"],
        tensors["pose_index"],
        tensors["point_index"],
        tensors["observations"],
        valid=tensors["valid"],
    )
    result = ts.solve_tensors(
        problem.pose_tangent,
        problem.points,
        problem.data,
        config,
        callback=lambda info: history.append(
            {k: v.detach().cpu() if isinstance(v, Tensor) else v for k, v in info.items()}
        ),
    )
    return result, history


def _tensors(scene, init, device: torch.device) -> dict[str, Tensor]:
    raw = {
        "poses": init.poses,
        "points": init.points,
        "pose_index": scene.pose_index,
        "point_index": scene.point_index,
        "observations": scene.observations,
        "valid": scene.valid,
    }
    return {k: v.to(device) for k, v in raw.items()}


def check_solves(report: Report, device: torch.device, on_device: Callable) -> None:
    print("2. Batched solves (solve_tensors), device vs CPU")
    cases = [
        ("BATCH (64 × S), dense batched Cholesky", "BATCH", ts.SolverConfig()),
        ("S, linear_solver='dense'", "S", ts.SolverConfig(linear_solver="dense")),
        (
            "S, reduced_solver='sparse' (host round trip)",
            "S",
            ts.SolverConfig(reduced_solver="sparse"),
        ),
    ]
    for label, case, config in cases:
        scene, init = _case(case)
        ref, ref_history = _solve(_tensors(scene, init, torch.device("cpu")), config)
        try:
            with on_device():
                out, history = _solve(_tensors(scene, init, device), config)
        except Exception as exc:
            report.check(label, math.inf, ITERATE_TOL, f"raised {type(exc).__name__}: {exc}")
            continue
        same_path = (
            len(history) == len(ref_history)
            and torch.equal(out.iterations.cpu(), ref.iterations)
            and out.status == ref.status
            and all(
                torch.equal(a["accepted"], b["accepted"])
                for a, b in zip(history, ref_history, strict=True)
            )
        )
        report.check(
            f"{label}: iterations, statuses, accept/reject",
            0.0 if same_path else math.inf,
            0.0,
            f"iterations {int(ref.iterations.min())}-{int(ref.iterations.max())}",
        )
        cost_error = max_error(
            out.cost_history / ref.cost_history.clamp_min(1e-300),
            torch.ones_like(ref.cost_history),
            relative=False,
        )
        report.check(f"{label}: cost history (relative)", cost_error, ITERATE_TOL)
        iterate_error = max(
            max_error(out.pose_tangent, ref.pose_tangent), max_error(out.points, ref.points)
        )
        report.check(f"{label}: final iterate", iterate_error, ITERATE_TOL)
        if out.pose_tangent.device.type != device.type:
            report.check(f"{label}: result device", math.inf, 0.0, str(out.pose_tangent.device))


# ------------------------------------------------------------------------------------------
# 3. Implicit backward


def _differentiable_inputs() -> dict[str, Tensor]:
    scene = ts.data.make_scene(8, 100, batch_size=4, outlier_fraction=0.1, seed=0)
    init = ts.initialization.initialize_scene(scene, method="odometry", seed=0)
    g = torch.Generator().manual_seed(5)
    return {
        "poses": init.poses,
        "points": init.points,
        "pose_index": scene.pose_index,
        "point_index": scene.point_index,
        "observations": scene.observations,
        "valid": scene.valid,
        "logits": 2 + 0.5 * torch.randn(scene.valid.shape, generator=g, dtype=F64),
        "log_scale": torch.tensor(math.log(0.03), dtype=F64),
        "poses_gt": scene.poses_gt,
    }


def _implicit_gradients(tensors: dict[str, Tensor], implicit: ImplicitConfig) -> dict:
    leaves = {
        k: tensors[k].detach().clone().requires_grad_(True)
        for k in ("logits", "log_scale", "observations")
    }
    problem = ts.PointMapProblem(
        tensors["poses"],
        tensors["points"],
        tensors["pose_index"],
        tensors["point_index"],
        leaves["observations"],
        valid=tensors["valid"],
        weights=torch.sigmoid(leaves["logits"]),
        loss=ts.HuberLoss(leaves["log_scale"].exp()),
    )
    xi0 = problem.pose_tangent.detach().clone().requires_grad_(True)
    X0 = problem.points.detach().clone().requires_grad_(True)
    result = solve_differentiable(xi0, X0, problem.data, implicit=implicit)
    loss = (result.poses - tensors["poses_gt"]).square().sum() + result.points.square().mean()
    names = [*leaves, "initial poses", "initial points"]
    grads = torch.autograd.grad(loss, [*leaves.values(), xi0, X0])
    return {"loss": loss.detach(), **dict(zip(names, grads, strict=True))}


def check_implicit(report: Report, device: torch.device, on_device: Callable) -> None:
    print("3. Implicit backward (solve_differentiable), device vs CPU")
    inputs = _differentiable_inputs()
    moved = {k: v.to(device) for k, v in inputs.items()}
    for label, implicit in (
        ("exact Hessian", ImplicitConfig()),
        ("Gauss-Newton", ImplicitConfig(hessian="gauss_newton")),
    ):
        ref = _implicit_gradients(inputs, implicit)
        try:
            with on_device():
                out = _implicit_gradients(moved, implicit)
        except Exception as exc:
            report.check(label, math.inf, GRADIENT_TOL, f"raised {type(exc).__name__}: {exc}")
            continue
        report.check(f"implicit ({label}): loss", max_error(out["loss"], ref["loss"]), ITERATE_TOL)
        for name in ref:
            if name == "loss":
                continue
            scale = float(ref[name].abs().max())
            error = float((out[name].cpu() - ref[name]).abs().max()) / max(scale, 1e-300)
            report.check(f"implicit ({label}): d loss / d {name}", error, GRADIENT_TOL)


# ------------------------------------------------------------------------------------------
# 4. pytest tests/lie, timing


def run_lie_tests(report: Report) -> None:
    print("4. pytest tests/lie (the device fixture includes CUDA when available)")
    command = [sys.executable, "-m", "pytest", "tests/lie", "-q", "-p", "no:cacheprovider"]
    t = time.perf_counter()
    run = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    tail = (run.stdout.strip().splitlines() or [""])[-1]
    report.check(
        "pytest tests/lie",
        0.0 if run.returncode == 0 else math.inf,
        0.0,
        f"{tail} ({time.perf_counter() - t:.0f} s)",
    )
    if run.returncode != 0:
        print(run.stdout[-4000:], run.stderr[-2000:])


def time_batch(device: torch.device, repeats: int, on_device: Callable) -> dict[str, float]:
    """Median wall time of the BATCH solve (problem construction excluded)."""
    scene, init = _case("BATCH")
    out = {}
    for where, dev, context in (
        ("device", device, on_device),
        ("cpu", torch.device("cpu"), contextlib.nullcontext),
    ):
        t = _tensors(scene, init, dev)
        with context():
            problem = ts.PointMapProblem(
                t["poses"],
                t["points"],
                t["pose_index"],
                t["point_index"],
                t["observations"],
                valid=t["valid"],
            )
            times = []
            for _ in range(repeats + 1):  # the first run warms up
                _synchronize(dev)
                start = time.perf_counter()
                result = ts.solve_tensors(problem.pose_tangent, problem.points, problem.data)
                _synchronize(dev)
                times.append(time.perf_counter() - start)
        out[f"{where}_median_s"] = statistics.median(times[1:])
        out[f"{where}_iterations"] = int(result.iterations.max())
    if device.type == "cuda":
        out["device_peak_memory_mib"] = torch.cuda.max_memory_allocated(device) / 2**20
    return out


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", choices=("cuda", "cpu"), default="cuda")
    parser.add_argument("--repeats", type=int, default=5, help="timed BATCH solves per side")
    parser.add_argument("--no-pytest", action="store_true", help="skip pytest tests/lie")
    parser.add_argument("--no-meta-audit", action="store_true", help="dry run without meta")
    parser.add_argument("--out", type=Path, help="write the results as JSON")
    args = parser.parse_args()

    if args.device == "cuda" and not torch.cuda.is_available():
        print(
            "cuda_check: no CUDA device (torch.cuda.is_available() is False, torch "
            f"{torch.__version__}); nothing checked. Run with --device cpu for a dry run."
        )
        return 0
    device = torch.device(args.device)
    meta_audit = device.type == "cpu" and not args.no_meta_audit
    on_device = (lambda: torch.device("meta")) if meta_audit else contextlib.nullcontext
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor()
    print(
        f"torch {torch.__version__}, device {device} ({name or 'cpu'})"
        + (", CUDA " + str(torch.version.cuda) if device.type == "cuda" else "")
        + (", dry run: device side under torch.device('meta')" if meta_audit else "")
    )
    report = Report()
    t0 = time.perf_counter()
    check_lie(report, device, on_device)
    check_solves(report, device, on_device)
    check_implicit(report, device, on_device)
    if not args.no_pytest:
        run_lie_tests(report)
    timing = time_batch(device, args.repeats, on_device)
    print(
        f"BATCH (64 × S) solve: {device.type} {timing['device_median_s']:.3f} s, cpu "
        f"{timing['cpu_median_s']:.3f} s (median of {args.repeats}, "
        f"{timing['device_iterations']} iterations, torch threads {torch.get_num_threads()})"
        + (
            f"; peak device memory {timing['device_peak_memory_mib']:.0f} MiB"
            if "device_peak_memory_mib" in timing
            else ""
        )
    )
    failed = report.failed
    print(
        f"{len(report.rows) - len(failed)}/{len(report.rows)} checks passed "
        f"({time.perf_counter() - t0:.0f} s)" + (": FAILED " + ", ".join(failed) if failed else "")
    )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(
            json.dumps(
                {
                    "torch": torch.__version__,
                    "device": str(device),
                    "device_name": name,
                    "meta_audit": meta_audit,
                    "checks": report.rows,
                    "timing": timing,
                },
                indent=2,
            )
        )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
