"""Pairwise ICP chaining on the 10 Stanford bunny range scans, evaluated against bun.conf.

The seed's section 0 baseline: register successive scans with ICP, chain the relative poses
T̂_0i = T̂_01 T̂_12 ⋯ T̂_(i−1,i) (eq. (0.1)), and compare with the reference alignment. Errors
accumulate along the chain; the joint multiview least-squares solve is meant to remove them.

Chain order. The six turntable views (bun000 … bun315) form a ring, but bun090↔bun180 and
bun180↔bun270 share little surface (about 0.2–0.35 of their points lie within 1 mm of the other
scan at the reference alignment) and are 90° apart; plain ICP gets them wrong. The extra views
bridge those gaps, so the default order is one path through all 10 scans in which every
successive pair shares 0.4–0.8 of its points:

    bun270 → bun315 → chin → bun000 → bun045 → top3 → bun090 → ear_back → bun180 → top2

(overlaps measured once with bun.conf, see the module's ``OVERLAP_NOTE``). Poses are reported
in the frame of bun000, which sits in the middle of the path, so drift grows towards both ends.

Initial guesses. Successive views differ by 34°–170° about arbitrary axes (the top/chin/ear
views are not turntable rotations), so every pair starts from 128 rotations spread uniformly
over SO(3) (centroids aligned), refined coarse to fine: 10 mm voxels (8 ICP iterations, all
hypotheses) → 5 mm (best 8) → 2 mm (best 1), point-to-plane ICP throughout. No knowledge of
bun.conf is used by the registration.

Usage: python experiments/bunny_pairwise.py [--data DIR] [--order a,b,c,...]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from torchslam import registration
from torchslam.data import fetch
from torchslam.io.ply import read_ply_points
from torchslam.io.stanford import pose_errors, read_conf, relative_to_first, stack
from torchslam.registration import icp

DEFAULT_ORDER = (
    "bun270",
    "bun315",
    "chin",
    "bun000",
    "bun045",
    "top3",
    "bun090",
    "ear_back",
    "bun180",
    "top2",
)
OVERLAP_NOTE = (
    "fraction of a scan's points within 1 mm of the other scan at the bun.conf alignment: "
    "bun270-bun315 0.59/0.51, bun315-chin 0.46/0.51, chin-bun000 0.42/0.41, "
    "bun000-bun045 0.79/0.83, bun045-top3 0.55/0.58, top3-bun090 0.45/0.53, "
    "bun090-ear_back 0.42/0.42, ear_back-bun180 0.79/0.65, bun180-top2 0.70/0.72; "
    "for comparison bun090-bun180 0.26/0.21, bun180-bun270 0.26/0.34"
)
REFERENCE_SCAN = "bun000"


def default_stages() -> tuple[icp.Stage, ...]:
    """Coarse-to-fine schedule in metres: 10, 5, 2 mm (``registration.default_stages``)."""
    return registration.default_stages(0.002)


@dataclass
class PairwiseResult:
    """Chained pairwise ICP over ``names`` (in chain order)."""

    # scan names in chain order
    names: list[str]
    # T̂ mapping scan k+1 into scan k, shape (M − 1, 4, 4)
    relative: torch.Tensor
    # chained poses mapping each scan into the frame of REFERENCE_SCAN, shape (M, 4, 4)
    poses: torch.Tensor
    # per pair: ICP result of the last stage (fitness/rms at its yardstick)
    pair_results: list[icp.ICPResult]
    # per pair: wall time in seconds
    pair_seconds: list[float]
    # the scans after the finest downsampling, in scan coordinates, name → (N_i, 3)
    clouds: dict[str, torch.Tensor]
    # seconds spent reading the PLY files
    load_seconds: float


def run(
    data: Path,
    names: tuple[str, ...] | list[str] = DEFAULT_ORDER,
    hypotheses: int = 128,
    stages: tuple[icp.Stage, ...] | None = None,
) -> PairwiseResult:
    """Load the scans, register successive pairs, chain. See the module docstring."""
    stages = default_stages() if stages is None else stages
    start = time.perf_counter()
    raw = {n: read_ply_points(data / f"{n}.ply") for n in names}
    load_seconds = time.perf_counter() - start
    config = registration.RegisterConfig(hypotheses=hypotheses, stages=stages)
    chain = registration.register_chain([raw[n] for n in names], config)
    relative_t, chained = chain.relative, chain.poses  # chained: into the frame of names[0]
    pair_results, pair_seconds = chain.pair_results, chain.pair_seconds
    reference_index = list(names).index(REFERENCE_SCAN) if REFERENCE_SCAN in names else 0
    poses = relative_to_first(chained, reference_index)
    finest = stages[-1].voxel_size
    clouds = {n: icp.voxel_downsample(p, finest) if finest > 0 else p for n, p in raw.items()}
    return PairwiseResult(
        list(names), relative_t, poses, pair_results, pair_seconds, clouds, load_seconds
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--data", type=Path, default=None, help="bunny data folder (default: the data set 'bunny')"
    )
    parser.add_argument(
        "--order", default=",".join(DEFAULT_ORDER), help="comma-separated chain order"
    )
    parser.add_argument("--hypotheses", type=int, default=128, help="initial rotations per pair")
    args = parser.parse_args(argv)
    data: Path = args.data or fetch("bunny")
    if not (data / "bun.conf").is_file():
        print(f"no bun.conf in {os.path.normpath(data)}; pass --data", file=sys.stderr)
        return 2
    names = [n.strip() for n in args.order.split(",") if n.strip()]
    torch.set_num_threads(min(2, torch.get_num_threads()))

    wall = time.perf_counter()
    result = run(data, names, args.hypotheses)
    elapsed = time.perf_counter() - wall

    reference = read_conf(data / "bun.conf")
    reference_poses = stack(reference, names)
    first = names.index(REFERENCE_SCAN) if REFERENCE_SCAN in names else 0
    rotation_deg, translation = pose_errors(result.poses, reference_poses, first)
    translation_mm = translation * 1000

    print(f"data: {os.path.normpath(data)}")
    print(f"chain: {' -> '.join(names)}  (poses in the frame of {names[first]})")
    print()
    print(f"{'pair (target <- source)':<26} {'fitness':>7} {'rms mm':>7} {'iters':>5} {'s':>5}")
    for k, (res, sec) in enumerate(zip(result.pair_results, result.pair_seconds, strict=True)):
        pair = f"{names[k]} <- {names[k + 1]}"
        print(
            f"{pair:<26} {float(res.fitness):7.3f} {float(res.rms) * 1000:7.3f} "
            f"{int(res.iterations):5d} {sec:5.2f}"
        )
    yardstick = result.pair_results[0].gate * 1000
    print(
        f"(fitness: fraction of source points within {float(yardstick):.0f} mm of the target at "
        "the final pose; rms over those points; iters: last stage)"
    )
    print()
    print(f"{'scan':<10} {'rot err deg':>11} {'trans err mm':>12}")
    for i, name in enumerate(names):
        print(f"{name:<10} {float(rotation_deg[i]):11.3f} {float(translation_mm[i]):12.3f}")
    others = [i for i in range(len(names)) if i != first]
    rot, trans = rotation_deg[others], translation_mm[others]
    print(f"{'mean':<10} {float(rot.mean()):11.3f} {float(trans.mean()):12.3f}")
    print(f"{'max':<10} {float(rot.max()):11.3f} {float(trans.max()):12.3f}")
    print(f"(mean and max over the {len(others)} scans other than {names[first]})")
    print()
    print(
        f"wall time {elapsed:.2f} s (reading PLY {result.load_seconds:.2f} s, "
        f"ICP {sum(result.pair_seconds):.2f} s), torch threads {torch.get_num_threads()}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
