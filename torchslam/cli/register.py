"""``torchslam register``: multiview registration of PLY range scans, with outputs and a figure.

Reads the scans (any order and any unit; ``--chain`` when successive scans overlap), runs
:func:`torchslam.registration.register` with one progress line per stage, pair and round, and
writes to ``--out``: the poses and the initial (pairwise) poses in the ``--format`` of
:mod:`torchslam.io.trajectories` (``poses.txt``/``poses_pairwise.txt`` for torchslam,
``poses_tum.txt``/``poses_pairwise_tum.txt`` for tum, ``poses_kitti.txt``/… for kitti: the joint
poses and the initial ones of pairwise ICP, over a spanning tree or, with ``--chain``, a chain),
``merged.ply`` (all scans in the reference frame, one colour per scan) and
``registration.png`` (needs matplotlib; skipped with a message without it). With
``--reference`` (a Stanford ``.conf``) it also prints the per-scan error table of
:func:`torchslam.registration.error_table`. It exits 1, after writing, when a pose is not
finite or a joint solve failed.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from torchslam.cli import (
    EXIT_FAILED,
    _stderr,
    add_threads_argument,
    float_range,
    int_range,
    plots,
    solve_exit_status,
    using_threads,
)
from torchslam.io.ply import write_ply
from torchslam.io.stanford import read_conf, scan_name, stack
from torchslam.io.trajectories import FORMATS, write_trajectory

if TYPE_CHECKING:
    from torchslam.registration.config import RegisterConfig

__all__ = ["add_arguments", "main", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``torchslam register``."""
    parser.add_argument(
        "scans",
        nargs="+",
        type=Path,
        help="scans, any order (≥ 2): PLY, PCD, XYZ/TXT/PTS, NPY or KITTI .bin",
    )
    parser.add_argument(
        "--chain",
        action="store_true",
        help="the scans are in chain order (successive ones overlap): register along it",
    )
    parser.add_argument(
        "--format",
        choices=FORMATS,
        default="torchslam",
        help="pose file format: torchslam (name tx ty tz qw qx qy qz), tum, kitti (torchslam)",
    )
    parser.add_argument(
        "--reference", type=Path, default=None, help="Stanford .conf alignment to compare with"
    )
    parser.add_argument("--out", type=Path, default=Path("out"), help="output folder (out)")
    parser.add_argument(
        "--frame", default=None, help="scan whose frame the poses are in (default: the first)"
    )
    parser.add_argument(
        "--voxel-size",
        type=float_range(0.0, 1e6, low_open=True),
        default=None,
        help="finest voxel pitch, scan units (0, 1e6] (default: from the scans' spacing/size)",
    )
    parser.add_argument(
        "--hypotheses", type=int_range(1, 10_000), default=128, help="starts per pair (128)"
    )
    parser.add_argument(
        "--rounds", type=int_range(0, 100), default=4, help="joint rounds at most [0, 100] (4)"
    )
    add_threads_argument(parser)


def run(
    args: argparse.Namespace,
    echo: Callable[[str], None] = print,
    warn: Callable[[str], None] = _stderr,
) -> int:
    """Run ``torchslam register``: progress lines, poses, merged PLY, PNG, optional table.

    Returns the exit status: 0, or 1 when a joint solve ended ``NON_FINITE`` or
    ``LINEAR_SOLVE_FAILED`` (outputs are still written; :mod:`torchslam.cli`). Without
    matplotlib the figure is skipped with one ``figure skipped: …`` line through ``warn``.

    Raises:
        ValueError: bad option values or input files. OSError: unreadable or unwritable files.
    """
    if args.threads < 1:
        raise ValueError(f"--threads must be ≥ 1, got {args.threads}")
    if args.voxel_size is not None and not (args.voxel_size > 0 and math.isfinite(args.voxel_size)):
        raise ValueError(f"--voxel-size must be > 0, got {args.voxel_size}")
    if args.hypotheses < 1:
        raise ValueError(f"--hypotheses must be ≥ 1, got {args.hypotheses}")
    if args.rounds < 0:
        raise ValueError(f"--rounds must be ≥ 0, got {args.rounds}")
    if len(args.scans) < 2:
        raise ValueError(f"need at least 2 scans, got {len(args.scans)}")
    expected = [scan_name(p) for p in args.scans]
    frame = expected[0] if args.frame is None else args.frame
    if frame not in expected:
        raise ValueError(f"--frame {frame!r} is not among the scans ({', '.join(expected)})")
    if args.out.exists() and not args.out.is_dir():
        raise ValueError(f"--out {args.out} exists and is not a directory")
    from torchslam.registration.config import RegisterConfig  # SciPy: loaded when used

    config = RegisterConfig(
        voxel_size=args.voxel_size,
        hypotheses=args.hypotheses,
        rounds=args.rounds,
        order="chain" if getattr(args, "chain", False) else "any",
    )
    with using_threads(args.threads):
        return _run(args, config, expected, frame, echo, warn)


def _run(
    args: argparse.Namespace,
    config: RegisterConfig,
    expected: list[str],
    frame: str,
    echo: Callable[[str], None],
    warn: Callable[[str], None],
) -> int:
    from torchslam.registration import icp
    from torchslam.registration.pipeline import load_scans, register
    from torchslam.registration.report import error_table

    start = time.perf_counter()
    reference = None
    if args.reference is not None:
        if not args.reference.is_file():
            raise FileNotFoundError(f"no such reference file: {args.reference}")
        reference = read_conf(args.reference)
        missing = [n for n in expected if n not in reference]
        if missing:
            raise ValueError(f"{args.reference}: no pose for scan(s) {', '.join(missing)}")
    echo(f"[1/5] reading {len(args.scans)} scans …")
    names, clouds, dropped = load_scans(args.scans, return_dropped=True)
    echo(f"      {', '.join(f'{n} ({len(c)})' for n, c in zip(names, clouds, strict=True))}")
    for name, count in zip(names, dropped, strict=True):
        if count:
            echo(f"      {name}: dropped {count} non-finite point(s)")
    stage = iter(("[2/5]", "[3/5]", "[4/5]"))

    def progress(line: str) -> None:
        prefix = "     " if line.startswith(" ") else next(stage, "     ")
        echo(f"{prefix} {line}")

    bar = echo is print and sys.stderr.isatty()  # not under --quiet, not into a file
    registration = register(names, clouds, config, frame=frame, progress=progress, progress_bar=bar)
    bad = [
        n
        for n, T, T0 in zip(names, registration.poses, registration.chained, strict=True)
        if not (torch.isfinite(T).all() and torch.isfinite(T0).all())
    ]
    if bad:
        warn(f"error: non-finite pose for scan(s) {', '.join(bad)}; nothing written")
        return EXIT_FAILED
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    echo(f"[5/5] writing {out} …")
    format = getattr(args, "format", "torchslam")
    suffix = "" if format == "torchslam" else f"_{format}"
    written = [f"poses{suffix}.txt", f"poses_pairwise{suffix}.txt"]
    for file, poses in zip(written, (registration.poses, registration.chained), strict=True):
        write_trajectory(out / file, poses, format, names=names, frame=frame)
    points, colors = plots.merged_cloud(registration.clouds, registration.poses)
    legend = [
        f"scan {n} rgb {' '.join(map(str, c))}"
        for n, c in zip(names, plots.scan_colors(len(names)), strict=True)
    ]
    write_ply(out / "merged.ply", points, colors, coordinate_type="float", comments=legend)
    written.append(f"merged.ply ({len(points)} points)")
    try:
        plots.plot_registration(registration, out / "registration.png")
    except plots.MatplotlibMissingError as error:
        warn(f"figure skipped: {error}")
    else:
        written.append("registration.png")
    echo(f"      {', '.join(written)}")
    echo(
        f"point-to-plane RMS between overlapping scans: pairwise "
        f"{registration.residual_chained:.4g} → joint {registration.residual_joint:.4g}"
    )
    if reference is not None:
        reference_poses = stack(reference, names)
        text, _ = error_table(
            names,
            registration.frame,
            reference_poses,
            {"pairwise": registration.chained, "joint": registration.poses},
        )
        echo(
            f"errors vs {args.reference} in the frame of {frame} (translation × 1000: mm for "
            "scans in metres):"
        )
        echo(text)
    _echo_uncertainty(names, registration, echo)
    echo(f"total {time.perf_counter() - start:.1f} s")
    for (a, b), result in zip(
        registration.chain.tree_edges, registration.chain.pair_results, strict=True
    ):
        if int(result.status) == icp.ICPStatus.TOO_FEW_CORRESPONDENCES:
            warn(f"warning: pairwise ICP {names[a]} ← {names[b]}: {result.reason}")
    statuses = [info.status for info in registration.refinement.rounds]
    return solve_exit_status(statuses, warn, "a joint solve")


def main(argv: list[str] | None = None) -> int:
    """``python -m torchslam.cli.register``: the same as ``torchslam register``."""
    from torchslam import cli

    return cli.main(["register", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())


def _echo_uncertainty(names: list[str], registration, echo: Callable[[str], None]) -> None:
    """Each scan's 1-σ rotation (°) and position uncertainty (the scans' unit), from the joint
    solve's marginal covariances (:attr:`RefineResult.pose_covariances`), relative to the
    scan that fixed the gauge."""
    from torchslam.covariance import pose_uncertainty
    from torchslam.lie import se3

    refinement = registration.refinement
    covariances = refinement.pose_covariances
    if covariances is None:
        echo("pose uncertainty: not available (no joint round, or its Hessian is singular)")
        return
    gauge = [n for n, c in zip(names, covariances, strict=True) if not bool(c.any())]
    rotation, position = pose_uncertainty(covariances, se3.inverse(refinement.poses))
    echo(
        "1-σ pose uncertainty from the joint solve (largest axis; relative to scan "
        f"{gauge[0] if gauge else '?'}, a-posteriori variance factor):"
    )
    for name, r, p in zip(names, rotation.tolist(), position.tolist(), strict=True):
        echo(f"      {name:>12}  rotation {r:.4f}°  position {p:.4g}")
