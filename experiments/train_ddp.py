"""Training through the solver under torch.distributed (DistributedDataParallel).

The learning experiment of ``experiments/learn_weights.py`` (a small MLP predicts per-
observation weights; the robust weighted problem is solved by ``solve_differentiable`` with
the implicit backward; the loss is the pose error of the solved trajectories), in a smaller
configuration, run data-parallel: every global batch of scenes is split into equal shards,
each process solves its shard through the solver, and DDP averages the gradients, so each
step equals the single-process step on the whole batch (up to rounding).

Start it with torchrun (one process per GPU, or per group of CPU cores)::

    torchrun --nproc-per-node 2 experiments/train_ddp.py --steps 40
    python experiments/train_ddp.py --steps 40        # the same, one process, no group

Backend and device follow the hardware with no code change: CUDA when available (process k
on ``cuda:LOCAL_RANK``, backend NCCL), else CPU with gloo; ``--device`` and ``--backend``
override. Every process builds the same scenes from fixed seeds and draws the same batch
order from a seeded generator; the pre-solve that computes the model's features is sharded
too (each process pre-solves a slice of the scenes, on the CPU, then all gather). Held-out
evaluation is sharded and all-reduced. CPU threads per process default to the machine's
cores divided by the processes on it (``--threads``).

Rank 0 prints the per-step times and the held-out accuracy before and after training and
writes ``out/train_ddp_<N>proc.json`` (``--out`` to change).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import gc
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch import Tensor, nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
import learn_weights as lw  # the experiment: scenes, features, model, loss

from torchslam.lie import se3
from torchslam.metrics import evaluate

OUT = Path("out")  # under the working directory
# The Cauchy scale learn_weights.py selects on its training scenes (its scale sweep).
CAUCHY_SCALE = 0.01


@dataclasses.dataclass(frozen=True)
class Setup:
    rank: int
    world: int
    local_rank: int
    device: torch.device
    backend: str | None  # None: a single process without a process group
    threads: int

    @property
    def distributed(self) -> bool:
        return self.backend is not None


def setup(args: argparse.Namespace) -> Setup:
    """Rank, device and backend from torchrun's environment and the hardware (or flags)."""
    launched = "RANK" in os.environ and "WORLD_SIZE" in os.environ
    rank = int(os.environ.get("RANK", 0))
    world = int(os.environ.get("WORLD_SIZE", 1))
    local_rank = int(os.environ.get("LOCAL_RANK", 0))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", 1))
    device_type = args.device
    if device_type == "auto":
        device_type = "cuda" if torch.cuda.is_available() else "cpu"
    if device_type == "cuda":
        if not torch.cuda.is_available():
            sys.exit("train_ddp: --device cuda, but torch.cuda.is_available() is False")
        device = torch.device("cuda", local_rank % torch.cuda.device_count())
        torch.cuda.set_device(device)
    else:
        device = torch.device("cpu")
    threads = args.threads or max(1, (os.cpu_count() or 1) // local_world)
    torch.set_num_threads(threads)
    backend = None
    if launched:
        backend = args.backend
        if backend == "auto":
            backend = "nccl" if device.type == "cuda" else "gloo"
        # torchrun's env:// rendezvous (MASTER_ADDR, MASTER_PORT, RANK, WORLD_SIZE).
        dist.init_process_group(backend, timeout=datetime.timedelta(seconds=args.timeout))
    return Setup(rank, world, local_rank, device, backend, threads)


def _map_tensors(obj, fn):
    """A copy of a (nested) dataclass with ``fn`` applied to its tensor fields."""
    if isinstance(obj, Tensor):
        return fn(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        changes = {f.name: _map_tensors(getattr(obj, f.name), fn) for f in dataclasses.fields(obj)}
        return dataclasses.replace(obj, **changes)
    return obj


def gather_features(scenes: lw.Scenes, env: Setup, cauchy_scale: float) -> lw.Scenes:
    """The fixed-Cauchy pre-solve and the model's features (``learn_weights.add_features``),
    sharded: each process pre-solves a contiguous slice of the scenes (on the CPU, where
    ``add_features`` runs), then every process receives all of them."""
    count = scenes.observations.shape[0]
    index = torch.arange(count).tensor_split(env.world)[env.rank]
    part = _map_tensors(scenes, lambda t: t[index])
    lw.add_features(part, cauchy_scale)
    mine = (part.features, part.presolve_poses, part.presolve_points)
    if env.distributed:
        parts: list = [None] * env.world
        dist.all_gather_object(parts, mine)
    else:
        parts = [mine]
    features, poses, points = (torch.cat(x) for x in zip(*parts, strict=True))
    return dataclasses.replace(
        scenes, features=features, presolve_poses=poses, presolve_points=points
    )


class ShardSolve(nn.Module):
    """The trained module: weights from the MLP, then the solve of a shard of the scenes."""

    def __init__(self, model: lw.WeightModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, scenes: lw.Scenes, index: Tensor) -> Tensor:
        """Solved ξ* (len(index), m, 6) of the indexed scenes, differentiable (implicit)."""
        result, _ = lw.learned_solve(self.model, scenes, sl=index)
        return result.pose_tangent


def held_out(module: ShardSolve, scenes: lw.Scenes, env: Setup) -> tuple[float, float]:
    """Mean ATE (mm) and mean rotation error (°) over the scenes, solved in shards."""
    count = scenes.observations.shape[0]
    index = torch.arange(count, device=env.device).tensor_split(env.world)[env.rank]
    with torch.no_grad():
        xi = module(scenes, index)
        e = evaluate(se3.exp(xi), scenes.scene.poses_gt[index])
        sums = torch.stack((e.ate.sum(), e.rotation_error_deg.mean(-1).sum()))
    if env.distributed:
        dist.all_reduce(sums)
    return 1000 * float(sums[0]) / count, float(sums[1]) / count


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=40, help="Adam steps (default 40)")
    parser.add_argument("--lr", type=float, default=0.1, help="initial Adam learning rate")
    parser.add_argument("--batch", type=int, default=8, help="scenes per step, all processes")
    parser.add_argument("--train-scenes", type=int, default=32)
    parser.add_argument("--test-scenes", type=int, default=16)
    parser.add_argument("--cauchy-scale", type=float, default=CAUCHY_SCALE)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    parser.add_argument("--backend", choices=("auto", "gloo", "nccl"), default="auto")
    parser.add_argument("--threads", type=int, default=0, help="CPU threads per process")
    parser.add_argument("--timeout", type=float, default=600, help="collective timeout (s)")
    parser.add_argument("--out", type=Path, help="JSON summary (default out/train_ddp_<N>proc)")
    args = parser.parse_args()

    t_start = time.perf_counter()
    env = setup(args)
    if args.batch % env.world:
        sys.exit(f"train_ddp: --batch {args.batch} must be a multiple of the {env.world} processes")
    log = print if env.rank == 0 else (lambda *a, **k: None)
    log(
        f"{env.world} process(es), backend {env.backend or 'none'}, device {env.device.type}, "
        f"{env.threads} thread(s) each; batch {args.batch} = {env.world} × "
        f"{args.batch // env.world} scenes, {args.steps} steps"
    )

    train = lw.make_scenes(args.train_scenes, seed=1000 + args.seed)
    test = lw.make_scenes(args.test_scenes, seed=2000 + args.seed)
    train = gather_features(train, env, args.cauchy_scale)
    test = gather_features(test, env, args.cauchy_scale)
    train, test = (_map_tensors(s, lambda t: t.to(env.device)) for s in (train, test))
    flat = train.features[train.scene.valid]
    torch.manual_seed(args.seed)  # the same initial model everywhere (DDP broadcasts rank 0's)
    model = lw.WeightModel(flat.mean(0), flat.std(0), args.cauchy_scale).to(env.device)
    module = ShardSolve(model)
    ddp = module
    if env.distributed:
        device_ids = [env.device.index] if env.device.type == "cuda" else None
        ddp = nn.parallel.DistributedDataParallel(module, device_ids=device_ids)
    optimizer = torch.optim.Adam(ddp.parameters(), lr=args.lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, args.steps, args.lr / 30)
    setup_seconds = time.perf_counter() - t_start
    before = held_out(module, test, env)
    log(f"setup {setup_seconds:.1f} s; held-out before training: ATE {before[0]:.3f} mm")

    order_generator = torch.Generator().manual_seed(args.seed)  # the same order everywhere
    order = torch.randperm(args.train_scenes, generator=order_generator)
    times: dict[str, list[float]] = {"forward": [], "backward": [], "step": [], "cpu": []}
    losses = []
    for step in range(args.steps):
        first = (step * args.batch) % args.train_scenes
        if first == 0 and step > 0:
            order = torch.randperm(args.train_scenes, generator=order_generator)
        batch = order[first : first + args.batch]
        shard = batch.tensor_split(env.world)[env.rank].to(env.device)
        synchronize(env.device)
        t0, c0 = time.perf_counter(), time.process_time()
        xi = ddp(train, shard)
        loss = lw.pose_loss(xi, train.scene.poses_gt[shard])  # mean over the shard
        synchronize(env.device)
        t1 = time.perf_counter()
        optimizer.zero_grad()
        loss.backward()  # DDP all-reduces (averages) the gradients here
        synchronize(env.device)
        t2 = time.perf_counter()
        optimizer.step()
        schedule.step()
        synchronize(env.device)
        t3 = time.perf_counter()
        times["forward"].append(t1 - t0)
        times["backward"].append(t2 - t1)
        times["step"].append(t3 - t0)
        times["cpu"].append(time.process_time() - c0)  # this process's CPU time, all threads
        batch_loss = loss.detach().clone()
        if env.distributed:
            dist.all_reduce(batch_loss)
            batch_loss /= env.world
        losses.append(float(batch_loss))
        if (step + 1) % 10 == 0 or step == args.steps - 1:
            log(
                f"  step {step + 1:4d}  batch RMS pose error {math.sqrt(losses[-1]) * 1e3:7.3f}"
                f" mm  {times['step'][-1]:.2f} s/step"
            )
    after = held_out(module, test, env)

    # Per-rank timings (forward = the shard's solve; a rank waits for the slowest in backward).
    per_rank = [times]
    if env.distributed:
        per_rank = [None] * env.world
        dist.all_gather_object(per_rank, times)
    steady = times["step"][1:] or times["step"]  # the first step pays one-time costs
    parameters = torch.cat([p.detach().flatten().cpu() for p in module.parameters()])
    summary = {
        "processes": env.world,
        "backend": env.backend,
        "device": env.device.type,
        "threads_per_process": env.threads,
        "steps": args.steps,
        "batch": args.batch,
        "train_scenes": args.train_scenes,
        "test_scenes": args.test_scenes,
        "cauchy_scale": args.cauchy_scale,
        "seed": args.seed,
        "setup_seconds": setup_seconds,
        "step_seconds_median": statistics.median(steady),
        "step_seconds_mean": statistics.fmean(steady),
        "forward_seconds_median_per_rank": [statistics.median(t["forward"]) for t in per_rank],
        "cpu_seconds_per_step_per_rank": [
            statistics.median(t["cpu"][1:] or t["cpu"]) for t in per_rank
        ],
        "train_seconds": sum(times["step"]),
        "held_out_before": {"ate_mm": before[0], "rotation_deg": before[1]},
        "held_out_after": {"ate_mm": after[0], "rotation_deg": after[1]},
        "final_batch_loss": losses[-1],
        "parameter_sum": float(parameters.sum()),
        "parameter_norm": float(parameters.norm()),
        "losses": losses,
        "step_seconds": times["step"],
    }
    log(
        f"time per step: median {summary['step_seconds_median']:.3f} s, mean "
        f"{summary['step_seconds_mean']:.3f} s (steps 2-{args.steps}); forward (solve) median "
        "per rank "
        + ", ".join(f"{t:.3f}" for t in summary["forward_seconds_median_per_rank"])
        + "; CPU time per step per rank "
        + ", ".join(f"{t:.3f}" for t in summary["cpu_seconds_per_step_per_rank"])
    )
    log(
        f"held-out ({args.test_scenes} scenes): ATE {before[0]:.4f} → {after[0]:.6f} mm, "
        f"rotation {before[1]:.5f} → {after[1]:.7f}°; final batch loss {losses[-1]:.10e}; "
        f"parameter norm {summary['parameter_norm']:.12f}"
    )
    if env.rank == 0:
        path = args.out or OUT / f"train_ddp_{env.world}proc.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(summary, indent=2))
        log(f"wrote {path} ({time.perf_counter() - t_start:.0f} s in all)")
    if env.distributed:
        # Leave cleanly: DDP's reducer (which holds the group) released first, then a barrier
        # so that no process tears down its gloo pairs while another still has a message in
        # flight (without it a rank could abort at exit), then destroy.
        del ddp
        gc.collect()
        dist.barrier()
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
