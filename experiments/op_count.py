"""ATen operations of one solve of a benchmark case, per phase (deterministic, unlike wall time).

Small cases (S: 11 frames, 200 points) are bound by the number of tensor operations, each a few
µs of dispatch, not by arithmetic; this counts them. One warm-up solve, then one profiled solve
of ``torchslam.solve(PointMapProblem.from_scene(scene, init.poses, init.points, loss=loss))``
under ``torch.profiler`` (CPU). The solver's phases are wrapped in ``record_function`` labels
(by patching the module attributes the loop calls; nothing in torchslam is changed), and every
``aten::`` event is attributed to its innermost label:

- construction: ``PointMapProblem.from_scene`` (argument checks included);
- setup: the rest of ``solve`` before the loop (checks, whitening factors, the linear plan);
- initial linearize: the linearization at the starting point;
- per iteration: factorize, solve (back-substitution), retract, linearize (at the candidate:
  its cost is the candidate cost), decide (model decrease, gain, λ update, accept/reject),
  status (gradient norm and the stopping rules), bookkeeping (the rest of the loop body);
- result: the :class:`SolveResult` and the copy back into the problem.

Two counts per phase: ``all`` counts every aten event, nested ones included (``aten::linalg_cross``
and the ``aten::empty`` it calls are two); ``top`` counts the aten events whose parent is not an
aten event (one per operation the Python code issued). Per-iteration phases are also divided by
the number of iterations.

Run: PYTHONPATH=$PWD .venv/bin/python experiments/op_count.py [CASE ...]   (default: S BATCH)
Options: --top K lists the K most frequent top-level ops of the solve.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import functools

import torch
from torch.profiler import ProfilerActivity, profile, record_function

import torchslam as ts
from torchslam import benchmark
from torchslam.problem import PointMapProblem
from torchslam.solver import loop, plan

PHASES = (
    "construction",
    "setup",
    "initial linearize",
    "factorize",
    "solve",
    "retract",
    "linearize",
    "decide",
    "status",
    "bookkeeping",
    "result",
)
PER_ITERATION = ("factorize", "solve", "retract", "linearize", "decide", "status", "bookkeeping")
_PREFIX = "phase:"


def _labelled(label, fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with record_function(_PREFIX + label):
            return fn(*args, **kwargs)

    return wrapper


@contextlib.contextmanager
def _instrumented():
    """Patch the loop's callees with record_function labels; restore them on exit."""
    patches = [
        (loop, "retract", "retract"),
        (loop, "model_decrease", "decide"),
        (loop, "update_status", "status"),
        (loop, "gradient_norm", "status"),
        (loop, "iterate", "bookkeeping"),
        (loop, "result", "result"),
        (plan.LinearPlan, "factorize", "factorize"),
        (plan.Factorization, "solve", "solve"),
    ]
    saved = [(owner, name, getattr(owner, name)) for owner, name, _ in patches]
    original_linearize = loop.linearize
    original_initial = loop.initial_state
    state = {"initial": False}

    def linearize(*args, **kwargs):
        label = "initial linearize" if state["initial"] else "linearize"
        with record_function(_PREFIX + label):
            return original_linearize(*args, **kwargs)

    def initial_state(*args, **kwargs):
        state["initial"] = True
        try:
            return original_initial(*args, **kwargs)
        finally:
            state["initial"] = False

    try:
        for owner, name, label in patches:
            setattr(owner, name, _labelled(label, getattr(owner, name)))
        loop.linearize = linearize
        loop.initial_state = initial_state
        yield
    finally:
        for owner, name, fn in saved:
            setattr(owner, name, fn)
        loop.linearize = original_linearize
        loop.initial_state = original_initial


def _phase_of(event) -> str:
    """The innermost phase label above an event; the decision code in ``iterate`` (under
    no_grad, not in a callee) counts as "decide" only via model_decrease, the rest is
    bookkeeping."""
    parent = event.cpu_parent
    while parent is not None:
        if parent.name.startswith(_PREFIX):
            return parent.name[len(_PREFIX) :]
        parent = parent.cpu_parent
    return "setup"


def count(case: str, top: int = 0) -> None:
    torch.set_num_threads(1)
    scene, init, loss = benchmark.build(case)

    def one_solve():
        with record_function(_PREFIX + "construction"):
            problem = PointMapProblem.from_scene(scene, init.poses, init.points, loss=loss)
        return ts.solve(problem)

    with _instrumented():
        one_solve()  # warm-up (caches, lazily built tables)
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            result = one_solve()
    iterations = int(result.iterations.max())
    totals = collections.Counter()
    tops = collections.Counter()
    names = collections.Counter()
    for event in prof.events():
        if not event.name.startswith("aten::"):
            continue
        phase = _phase_of(event)
        totals[phase] += 1
        parent = event.cpu_parent
        if parent is None or not parent.name.startswith("aten::"):
            tops[phase] += 1
            names[event.name] += 1
    B = scene.pose_index.shape[0]
    print(f"case {case}: B = {B}, iterations = {iterations}")
    print(f"{'phase':<20}{'all':>8}{'top':>8}{'all/it':>9}{'top/it':>9}")
    for phase in PHASES:
        line = f"{phase:<20}{totals[phase]:>8}{tops[phase]:>8}"
        if phase in PER_ITERATION:
            line += f"{totals[phase] / iterations:>9.1f}{tops[phase] / iterations:>9.1f}"
        print(line)
    extra = set(totals) - set(PHASES)
    for phase in sorted(extra):
        print(f"{phase:<20}{totals[phase]:>8}{tops[phase]:>8}")
    per_it_all = sum(totals[p] for p in PER_ITERATION)
    per_it_top = sum(tops[p] for p in PER_ITERATION)
    print(
        f"{'iterations':<20}{per_it_all:>8}{per_it_top:>8}"
        f"{per_it_all / iterations:>9.1f}{per_it_top / iterations:>9.1f}"
    )
    print(f"{'total':<20}{sum(totals.values()):>8}{sum(tops.values()):>8}")
    if top:
        print(f"most frequent top-level ops of the {case} solve:")
        for name, k in names.most_common(top):
            print(f"  {k:>6}  {name}")
    print()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="*", default=["S", "BATCH"])
    parser.add_argument("--top", type=int, default=0)
    args = parser.parse_args()
    for case in args.cases:
        count(case, args.top)


if __name__ == "__main__":
    main()
