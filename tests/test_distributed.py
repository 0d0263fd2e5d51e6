"""Training through the solver under torch.distributed: 2 gloo processes on CPU.

Each process solves its half of a batch of 4 scenes through ``solve_differentiable`` (implicit
backward) inside a ``DistributedDataParallel`` module; the gradient DDP all-reduces must equal
the gradient of the whole batch solved in one process. The processes are spawned with a
file-store rendezvous, leave through a barrier and are joined with a deadline, so a broken
rendezvous fails the test instead of hanging it.
"""

from __future__ import annotations

import datetime
import gc
import time
import traceback
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import Tensor, nn

import torchslam as ts
from torchslam.solver.differentiable import ImplicitConfig, solve_differentiable

WORLD = 2
BATCH = 4  # scenes per training step, split 2 + 2 over the processes
DEADLINE_S = 120.0  # bound on the whole distributed run (it takes a few seconds)
pytestmark = pytest.mark.skipif(
    not (dist.is_available() and dist.is_gloo_available()),
    reason="torch.distributed with the gloo backend is not available",
)


def _scenes():
    """The batch, drawn from fixed seeds: the same tensors in every process."""
    scene = ts.data.make_scene(
        5, 40, batch_size=BATCH, outlier_fraction=0.15, noise_std=0.01, seed=11
    )
    init = ts.initialization.initialize_scene(scene, method="odometry", seed=11)
    return scene, init


class _WeightNet(nn.Module):
    """Per-observation weights from (observation, range) and a learnable Cauchy scale."""

    def __init__(self) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(3)
        self.net = nn.Sequential(
            nn.Linear(4, 8, dtype=torch.float64), nn.Tanh(), nn.Linear(8, 1, dtype=torch.float64)
        )
        with torch.no_grad():  # a seeded initialization, independent of the global RNG
            for p in self.net.parameters():
                p.copy_(0.5 * torch.randn(p.shape, generator=g, dtype=torch.float64))
        self.log_scale = nn.Parameter(torch.tensor(-3.0, dtype=torch.float64))

    def forward(self, observations: Tensor) -> Tensor:
        features = torch.cat((observations, observations.norm(dim=-1, keepdim=True)), -1)
        return torch.exp(torch.tanh(self.net(features)[..., 0]))


class _SolveShard(nn.Module):
    """Loss of a shard of the batch: mean squared pose error of the solved trajectories."""

    def __init__(self, implicit: ImplicitConfig | None = None) -> None:
        super().__init__()
        self.weights = _WeightNet()
        self.scene, self.init = _scenes()
        self.implicit = implicit

    def forward(self, index: Tensor) -> Tensor:
        s, init = self.scene, self.init
        problem = ts.PointMapProblem(
            init.poses[index],
            init.points[index],
            s.pose_index[index],
            s.point_index[index],
            s.observations[index],
            valid=s.valid[index],
            weights=self.weights(s.observations[index]),
            loss=ts.CauchyLoss(self.weights.log_scale.exp()),
        )
        result = solve_differentiable(
            problem.pose_tangent.detach(),
            problem.points.detach(),
            problem.data,
            implicit=self.implicit,
        )
        error = (result.poses - s.poses_gt[index]).square().sum((-1, -2, -3))
        return error.mean()


def _gradient(module: nn.Module) -> Tensor:
    return torch.cat([p.grad.flatten() for p in module.parameters()])


def _worker(rank: int, out: str) -> None:
    """One process: join the group, solve its shard through DDP, save the reduced gradient."""
    torch.set_num_threads(1)
    try:
        dist.init_process_group(
            "gloo",
            # A file store in the test's folder: no port to race for, and no store server
            # in rank 0 that the other process would still need while rank 0 exits.
            init_method=(Path(out) / "rendezvous").as_uri(),
            rank=rank,
            world_size=WORLD,
            timeout=datetime.timedelta(seconds=60),
        )
        try:
            model = nn.parallel.DistributedDataParallel(_SolveShard())
            shard = torch.arange(BATCH).tensor_split(WORLD)[rank]
            model(shard).backward()  # DDP averages the gradients over the 2 processes
            torch.save(_gradient(model.module), Path(out) / f"rank{rank}.pt")
            # DDP's reducer holds the process group: released here, not at interpreter exit,
            # where gloo's threads would be torn down by static destructors (an abort).
            del model
            gc.collect()
        finally:
            _shutdown()
    except BaseException:
        (Path(out) / f"rank{rank}.err").write_text(traceback.format_exc())
        raise


def _shutdown() -> None:
    """Leave the group cleanly: a barrier first, so that neither process tears down its gloo
    pairs while the other still has a message in flight (without it rank 1 aborted at exit,
    "terminate called without an active exception", about one run in six), then destroy."""
    try:
        dist.barrier()
    finally:
        dist.destroy_process_group()


def _run_workers(out: Path, monkeypatch) -> None:
    # The children read their environment at start: one thread each.
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(name, "1")
    context = mp.get_context("spawn")
    workers = [
        context.Process(target=_worker, args=(rank, str(out)), daemon=True) for rank in range(WORLD)
    ]
    for w in workers:
        w.start()
    deadline = time.monotonic() + DEADLINE_S
    try:
        for w in workers:
            w.join(max(0.0, deadline - time.monotonic()))
    finally:
        hung = [rank for rank, w in enumerate(workers) if w.is_alive()]
        for w in workers:
            if w.is_alive():
                w.kill()
                w.join(5)
    errors = {
        rank: (out / f"rank{rank}.err").read_text()
        for rank in range(WORLD)
        if (out / f"rank{rank}.err").exists()
    }
    if hung:
        pytest.fail(f"distributed workers {hung} still running after {DEADLINE_S:.0f} s: {errors}")
    codes = [w.exitcode for w in workers]
    if errors or any(code != 0 for code in codes):
        pytest.fail(f"distributed workers failed (exit codes {codes}):\n{errors}")


def test_ddp_gradient_equals_single_process(tmp_path, monkeypatch):
    _run_workers(tmp_path, monkeypatch)
    reduced = [torch.load(tmp_path / f"rank{rank}.pt") for rank in range(WORLD)]

    # The same batch in this process, without torch.distributed.
    model = _SolveShard()
    model(torch.arange(BATCH)).backward()
    full = _gradient(model)
    model.zero_grad()
    model(torch.arange(BATCH).tensor_split(WORLD)[0]).backward()
    first_half = _gradient(model)

    scale = full.abs().max()
    assert scale > 0
    # Each process solves the same problems as this one, with the same per-problem decisions
    # (damping, acceptance, stopping and the implicit backward's conjugate-gradient stopping
    # are taken per problem); the results differ by rounding only (batched kernels of size 2
    # vs 4, 1 thread vs the default), ~1e-16 amplified by the conditioning of the solve and
    # of its implicit backward (≲ 1e3 on these well-posed scenes): far inside 1e-10.
    for rank, g in enumerate(reduced):
        error = float((g - full).abs().max() / scale)
        assert error <= 1e-10, f"rank {rank}: relative gradient error {error:.3g}"
    # The all-reduce did happen: half the batch alone gives a visibly different gradient.
    assert float((first_half - full).abs().max() / scale) > 1e-3


def test_shard_gradients_average_to_the_batch_gradient():
    """In one process: the mean of the two half-batch gradients is the batch gradient (a
    problem's solve and implicit backward do not depend on the other problems it is batched
    with), which DDP's averaging relies on. With a loose conjugate-gradient tolerance, so that
    a stopping test shared by the batch (rather than per problem) would show at ~1e-6."""
    model = _SolveShard(ImplicitConfig(tolerance=1e-6))
    model(torch.arange(BATCH)).backward()
    full = _gradient(model)
    halves = []
    for shard in torch.arange(BATCH).tensor_split(WORLD):
        model.zero_grad()
        model(shard).backward()
        halves.append(_gradient(model))
    mean = torch.stack(halves).mean(0)
    # Same rounding argument as above: the same iterations per problem, rounding apart.
    assert float((mean - full).abs().max() / full.abs().max()) <= 1e-10
