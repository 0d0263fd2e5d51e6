"""The figures of the command line, and matplotlib, imported lazily.

matplotlib is an optional dependency: ``pip install 'torchslam[plot]'`` (the ``dev`` extra
includes it). The library never needs it; only the figures of ``torchslam demo``, ``bench``,
``posegraph --plot`` and ``register`` do. Every figure function imports it through
:func:`require_pyplot` when called and raises :class:`MatplotlibMissingError` without it, so
importing this module never needs matplotlib.

Figures: :func:`plot_demo` (``demo``), :func:`plot_bench` (``bench``),
:func:`plot_trajectories` (``posegraph --plot``), :func:`plot_registration` (``register``),
:func:`plot_slam` (``slam``).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3

if TYPE_CHECKING:
    from torchslam.data import SyntheticScene
    from torchslam.posegraph.graph import PoseGraph
    from torchslam.posegraph.solve import PoseGraphSolveResult
    from torchslam.registration.pipeline import Registration
    from torchslam.slam.pipeline import SLAMResult
    from torchslam.solver import SolveResult

__all__ = [
    "INSTALL_HINT",
    "MatplotlibMissingError",
    "check_figure_format",
    "merged_cloud",
    "plot_bench",
    "plot_demo",
    "plot_registration",
    "plot_slam",
    "plot_trajectories",
    "require_matplotlib",
    "require_pyplot",
    "scan_colors",
]

INSTALL_HINT = "pip install 'torchslam[plot]'"


class MatplotlibMissingError(ImportError):
    """matplotlib is not installed (or cannot be imported); the message says how to fix it."""


def require_matplotlib() -> ModuleType:
    """The ``matplotlib`` module with the non-interactive Agg backend selected.

    Raises:
        MatplotlibMissingError: matplotlib is not installed or cannot be imported.
    """
    try:
        import matplotlib
    except ImportError as error:
        missing = isinstance(error, ModuleNotFoundError) and error.name == "matplotlib"
        problem = "is not installed" if missing else f"cannot be imported ({error})"
        raise MatplotlibMissingError(f"matplotlib {problem}; {INSTALL_HINT}") from None
    matplotlib.use("Agg")  # figures are written to files; no display needed
    return matplotlib


def require_pyplot() -> ModuleType:
    """``matplotlib.pyplot`` with the Agg backend (:func:`require_matplotlib`).

    Raises:
        MatplotlibMissingError: matplotlib is not installed or cannot be imported.
    """
    require_matplotlib()
    try:
        import matplotlib.pyplot as plt
    except ImportError as error:
        raise MatplotlibMissingError(
            f"matplotlib.pyplot cannot be imported ({error}); {INSTALL_HINT}"
        ) from None
    return plt


def check_figure_format(path: Path) -> None:
    """matplotlib is there and can write ``path``'s format; ValueError otherwise."""
    try:
        require_matplotlib()
    except MatplotlibMissingError as error:
        raise ValueError(f"--plot needs matplotlib: {error}") from None
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    formats = FigureCanvasAgg.get_supported_filetypes()
    suffix = path.suffix.lstrip(".").lower()
    if suffix and suffix not in formats:
        raise ValueError(
            f"--plot: unknown figure format {path.suffix!r} (use one of {', '.join(formats)})"
        )


def plot_demo(
    scene: SyntheticScene,
    initial_poses: torch.Tensor,
    result: SolveResult,
    out: Path,
    position_covariances: torch.Tensor | None = None,
) -> Path:
    """``demo.png`` in ``out``: top view of the true, initial and optimized trajectories of
    problem 0 (with 3σ ellipses of the optimized positions when ``position_covariances`` is
    given), and the cost per iteration. Returns the file written.

    Args:
        scene: the synthetic scene (``poses_gt`` T_i0, shape (B, m, 4, 4); ``points_gt``).
        initial_poses: the initial T_i0, shape (B, m, 4, 4).
        result: the solve result.
        out: the output folder (created if missing).
        position_covariances: covariances of the optimized frame positions in the world
            (frame 0) coordinates, (B, m, 3, 3)
            (:func:`torchslam.covariance.position_covariance`), or None.

    Raises:
        MatplotlibMissingError: matplotlib is not installed.
    """
    plt = require_pyplot()
    out.mkdir(parents=True, exist_ok=True)

    def positions(T: torch.Tensor) -> torch.Tensor:  # sensor positions: translation of T_0i
        R, t = T[0, :, :3, :3], T[0, :, :3, 3]
        return -(R.transpose(-1, -2) @ t[..., None])[..., 0]

    fig, (ax, ax_cost) = plt.subplots(1, 2, figsize=(11, 4.8))
    # "Top view": the two world axes along which the true trajectory spreads most (frame 0
    # is a sensor frame, so the ground plane need not be x-y).
    gt = positions(scene.poses_gt)
    a, b = sorted(torch.argsort(gt.std(dim=0), descending=True)[:2].tolist())
    for T, label, style, width in (
        (scene.poses_gt, "ground truth", "k-", 4.0),
        (initial_poses, "initial (drifted odometry)", "r--", 1.5),
        (result.poses, "optimized (LM)", "c-", 1.5),
    ):
        p = positions(T.detach()).numpy()
        ax.plot(p[:, a], p[:, b], style, label=label, lw=width, alpha=0.9)
    pts = scene.points_gt[0].numpy()
    ax.scatter(pts[:, a], pts[:, b], s=1, c="0.8", zorder=0, label="points")
    if position_covariances is not None:
        _draw_ellipses(ax, positions(result.poses.detach()), position_covariances[0], (a, b))
    ax.set_aspect("equal")
    ax.set_xlabel(f"{'xyz'[a]} (m)")
    ax.set_ylabel(f"{'xyz'[b]} (m)")
    ax.set_title("trajectory, top view")
    ax.legend(loc="upper right", fontsize=8)
    history = result.cost_history[0].numpy()
    ax_cost.semilogy(range(len(history)), history, "o-")
    ax_cost.set_xlabel("iteration")
    ax_cost.set_ylabel("cost ½Σ‖r‖²")
    ax_cost.set_title("Levenberg-Marquardt cost")
    ax_cost.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    path = out / "demo.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _draw_ellipses(ax, centres: Tensor, covariances: Tensor, axes: tuple[int, int]) -> None:
    """3σ ellipses of the positions ``centres`` (m, 3) with covariances (m, 3, 3), projected
    on the world axes ``axes``; magnified by a power of ten (stated in the legend) when the
    largest would be under 1% of the trajectory's extent."""
    from matplotlib.patches import Ellipse

    a, b = axes
    index = torch.tensor([a, b])
    C = covariances.detach().cpu().double()[:, index][:, :, index]
    if not bool(torch.isfinite(C).all()):
        return
    values, vectors = torch.linalg.eigh(0.5 * (C + C.transpose(-1, -2)))
    semi = 3.0 * values.clamp_min(0).sqrt()  # (m, 2): 3σ semi-axes
    p = centres.detach().cpu().double().numpy()
    extent = float(np.ptp(p[:, [a, b]], axis=0).max()) or 1.0
    largest = float(semi.max())
    scale = 1.0
    if 0 < largest < 0.01 * extent:
        scale = 10.0 ** np.ceil(np.log10(0.01 * extent / largest))
    label = "3σ position ellipses, world axes" + (f" (×{scale:g})" if scale != 1 else "")
    major = vectors[:, :, 1].numpy()  # eigenvector of the larger eigenvalue, (m, 2)
    for i in range(p.shape[0]):
        angle = float(np.degrees(np.arctan2(major[i, 1], major[i, 0])))
        ax.add_patch(
            Ellipse(
                (p[i, a], p[i, b]),
                2 * scale * float(semi[i, 1]),
                2 * scale * float(semi[i, 0]),
                angle=angle,
                fill=False,
                color="tab:blue",
                lw=0.8,
                label=label if i == 0 else None,
            )
        )


def plot_bench(rows: list[dict], path: Path) -> None:
    """Bar chart of the benchmark timings, torchslam vs scipy per case (rows of
    :func:`torchslam.benchmark.run_case`); raises MatplotlibMissingError without matplotlib."""
    plt = require_pyplot()
    cases = [r["case"] for r in rows]
    fig, ax = plt.subplots(figsize=(7, 4))
    x = range(len(cases))
    ax.bar([i - 0.2 for i in x], [r["median_s"] for r in rows], 0.4, label="torchslam (LM)")
    if any("scipy_s" in r for r in rows):
        ax.bar(
            [i + 0.2 for i in x],
            [r.get("scipy_s", 0) for r in rows],
            0.4,
            label="scipy least_squares (trf)",
        )
    ax.set_yscale("log")
    ax.set_xticks(list(x), cases)
    ax.set_ylabel("wall time (s), log scale")
    counts = sorted({int(r["threads"]) for r in rows if "threads" in r})
    threads = ", ".join(map(str, counts)) if counts else "?"
    ax.set_title(f"ICP-SLAM solve time, float64, {threads} thread{'s' if counts != [1] else ''}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_trajectories(
    path: Path,
    initial: torch.Tensor,
    result: PoseGraphSolveResult,
    title: str = "",
    graph: PoseGraph | None = None,
) -> None:
    """Figure: vertex positions t_i before and after, and the cost per iteration.

    3D graphs get an x-y and an x-z projection, 2D graphs (``graph.dimension == 2``) the x-y
    plane only. With ``graph``, its loop closures (the edges that are not odometry, see
    :meth:`PoseGraph.odometry_mask`) are drawn as thin lines between the optimized positions.

    Args:
        path: the figure file (format from its suffix).
        initial: initial poses, shape (N, 4, 4) (body → world; positions are the translations).
        result: the solve result.
        title: a title for the figure (e.g. the file name).
        graph: the pose graph (its dimension and edges), or None (3D, no loop closures drawn).

    Raises:
        MatplotlibMissingError: matplotlib is not installed.
    """
    plt = require_pyplot()
    from matplotlib.collections import LineCollection

    before = initial[:, :3, 3].detach().cpu().double().numpy()
    after = result.poses[:, :3, 3].detach().cpu().double().numpy()
    planes = ((0, 1),) if graph is not None and graph.dimension == 2 else ((0, 1), (0, 2))
    closures = np.zeros((0, 2), dtype=np.int64)
    if graph is not None:
        closures = graph.edges[~graph.odometry_mask()].cpu().numpy()
    fig, axes = plt.subplots(1, len(planes) + 1, figsize=(5 * (len(planes) + 1), 4.8))
    for ax, (a, b) in zip(axes[:-1], planes, strict=True):
        if len(closures):
            segments = np.stack(
                (after[closures[:, 0]][:, [a, b]], after[closures[:, 1]][:, [a, b]]), 1
            )
            ax.add_collection(
                LineCollection(
                    segments,
                    colors="tab:green",
                    linewidths=0.4,
                    alpha=0.7,
                    label=f"loop closures ({len(closures)})",
                )
            )
        ax.plot(before[:, a], before[:, b], "r-", lw=0.6, alpha=0.6, label="initial")
        ax.plot(after[:, a], after[:, b], "b-", lw=0.8, label="optimized (LM)")
        ax.set_xlabel(f"{'xyz'[a]} (m)")
        ax.set_ylabel(f"{'xyz'[b]} (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"{'xyz'[a]}-{'xyz'[b]} {'plane' if len(planes) == 1 else 'projection'}")
        ax.legend(loc="best", fontsize=8)
    history = result.cost_history.numpy()
    ax_cost = axes[-1]
    if (history > 0).all():
        ax_cost.semilogy(range(len(history)), history, "o-")
    else:  # an exact graph reaches cost 0, which a log axis cannot show
        ax_cost.plot(range(len(history)), history, "o-")
    ax_cost.set_xlabel("iteration")
    ax_cost.set_ylabel("cost ½Σ rᵀΩr")
    ax_cost.set_title(f"Levenberg-Marquardt: {result.status.name}")
    ax_cost.grid(True, which="both", alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


_PALETTE = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
    ],
    dtype=np.uint8,
)


def scan_colors(count: int) -> np.ndarray:
    """One RGB colour (uint8) per scan, shape (count, 3) (matplotlib's tab10, repeating)."""
    count = _checks.check_int("scan_colors", "count", count, minimum=0)
    return _PALETTE[np.arange(count) % len(_PALETTE)]


def merged_cloud(clouds: Sequence[Tensor], poses: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """All clouds moved into the common frame, with one colour per scan: (N, 3), (N, 3) uint8."""
    from torchslam.registration.config import check_clouds, check_poses  # lazily (SciPy)

    clouds = check_clouds("merged_cloud", clouds)
    poses = check_poses("merged_cloud", poses, len(clouds)).to(clouds[0].dtype)
    colors = scan_colors(len(clouds))
    points = [se3.act(poses[i], c).detach().cpu().numpy() for i, c in enumerate(clouds)]
    rgb = [np.repeat(colors[i][None], len(p), axis=0) for i, p in enumerate(points)]
    return np.concatenate(points), np.concatenate(rgb)


def _order(registration: Registration) -> str:
    """How the pairwise stage picked its pairs: "chain" or "spanning tree"."""
    return "chain" if registration.config.order == "chain" else "spanning tree"


def plot_registration(registration: Registration, path: str | os.PathLike) -> None:
    """Figure of a registration: pairwise ICP (row 1) vs joint ICP-SLAM (row 2).

    Columns: top view (x, z) and side view (x, y) of the merged downsampled cloud, coloured by
    scan, in the axes of the reference scan (mm for scans in metres, judged by a voxel size
    under 5 cm; otherwise the scans' units); a section, the slab
    |z − z_mid| < one voxel through the middle of the cloud, where misregistration shows as
    doubled contours; and two diagnostics: the histogram of point-to-plane distances between
    overlapping scans (pairwise and joint, row 1) and the change of every pose from pairwise to
    joint (row 2: rotation in degrees, translation in mm).

    Raises:
        MatplotlibMissingError: matplotlib is not installed.
    """
    plt = require_pyplot()

    reg = registration
    colors = scan_colors(len(reg.names)) / 255.0
    # Scans in metres (voxels under 5 cm) are drawn in mm; others in their own units.
    scale, mm = (1000.0, "mm") if reg.voxel_size < 0.05 else (1.0, "units")
    voxel = reg.voxel_size * scale
    rows = (
        (f"pairwise ICP ({_order(reg)})", reg.chained, reg.residual_chained),
        ("joint ICP-SLAM", reg.poses, reg.residual_joint),
    )
    worlds = [
        [se3.act(poses[i], c).detach().cpu().numpy() * scale for i, c in enumerate(reg.clouds)]
        for _, poses, _ in rows
    ]
    z_mid = float(np.median(np.concatenate(worlds[1])[:, 2]))
    fig, axes = plt.subplots(2, 4, figsize=(20, 9.5), gridspec_kw={"width_ratios": [1, 1, 1, 0.9]})
    for row, ((title, _, residual), world) in enumerate(zip(rows, worlds, strict=True)):
        inside = [np.abs(p[:, 2] - z_mid) < voxel for p in world]
        panels = (
            ("top view", [(p[:, 0], p[:, 2]) for p in world], ("x", "z"), 0.25),
            ("side view", [(p[:, 0], p[:, 1]) for p in world], ("x", "y"), 0.25),
            (
                f"section |z − {z_mid:.0f}| < {voxel:g} {mm}",
                [(p[k, 0], p[k, 1]) for p, k in zip(world, inside, strict=True)],
                ("x", "y"),
                2.5,
            ),
        )
        for col, (name, series, (u, v), size) in enumerate(panels):
            ax = axes[row, col]
            for i, (x, y) in enumerate(series):
                ax.scatter(x, y, s=size, color=colors[i], linewidths=0, alpha=0.8)
            ax.set_aspect("equal")
            ax.set_xlabel(f"{u} ({mm})")
            ax.set_ylabel(f"{v} ({mm})")
            ax.set_title(f"{title}: {name}", fontsize=11)
        axes[row, 0].annotate(
            f"point-to-plane RMS between overlapping scans {residual * scale:.3f} {mm}",
            xy=(0.02, 0.02),
            xycoords="axes fraction",
            fontsize=9,
        )

    from torchslam.registration.report import plane_distances  # lazily (SciPy)

    ax = axes[0, 3]
    pairs = reg.refinement.pairs
    bins = np.linspace(-3 * voxel / 4, 3 * voxel / 4, 61)
    for (title, poses, residual), color in zip(rows, ("tab:gray", "tab:blue"), strict=True):
        d = plane_distances(reg.refinement.track_clouds, poses, pairs, reg.voxel_size) * scale
        ax.hist(
            d,
            bins=bins,
            histtype="step",
            linewidth=1.5,
            color=color,
            label=f"{title} (RMS {residual * scale:.3f} {mm})",
        )
    ax.set_xlabel(f"point-to-plane distance ({mm})")
    ax.set_ylabel("points")
    ax.set_title("consistency of the overlaps", fontsize=11)
    ax.legend(fontsize=8, loc="upper left")

    ax = axes[1, 3]
    change = se3.compose(se3.inverse(reg.chained), reg.poses)
    rotation = torch.rad2deg(torch.linalg.vector_norm(se3.log(change)[:, :3], dim=-1))
    translation = torch.linalg.vector_norm(reg.poses[:, :3, 3] - reg.chained[:, :3, 3], dim=-1)
    x = np.arange(len(reg.names))
    ax.bar(x - 0.2, rotation.numpy(), 0.4, color="tab:blue", label="rotation (°)")
    ax.bar(
        x + 0.2, translation.numpy() * scale, 0.4, color="tab:orange", label=f"translation ({mm})"
    )
    ax.set_xticks(x, reg.names, rotation=60, fontsize=8)
    ax.set_title(f"pose change pairwise → joint (frame {reg.names[reg.frame]})", fontsize=11)
    ax.legend(fontsize=8)

    handles = [
        plt.Line2D([], [], marker="o", linestyle="", color=colors[i], label=n)
        for i, n in enumerate(reg.names)
    ]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 10), frameon=False)
    fig.suptitle(
        f"{len(reg.names)} scans ({voxel:g} {mm} voxels) in the frame of "
        f"{reg.names[reg.frame]}: pairwise ICP, {_order(reg)} (top) vs joint ICP-SLAM (bottom)"
    )
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_slam(result: SLAMResult, path: str | os.PathLike, max_points: int = 200_000) -> None:
    """Top view of a SLAM run: the map (grey), the trajectory of every frame, the keyframes and
    the accepted loop closures (red segments between their keyframes).

    "Top" drops the world axis along which the trajectory varies least (z for a walking or
    driving LiDAR, y for a depth camera held upright, whose y points down).
    """
    plt = require_pyplot()
    positions = result.poses[:, :3, 3].detach().cpu().numpy()
    keyframes = result.keyframe_poses[:, :3, 3].detach().cpu().numpy()
    up = int(np.argmin(np.ptp(positions, axis=0))) if len(positions) > 1 else 2
    a, b = [axis for axis in range(3) if axis != up]
    figure, ax = plt.subplots(figsize=(8, 8))
    cloud = result.map_points().detach().cpu().numpy()
    if len(cloud) > max_points:
        cloud = cloud[np.random.default_rng(0).choice(len(cloud), max_points, replace=False)]
    ax.scatter(cloud[:, a], cloud[:, b], s=0.2, c="0.6", linewidths=0, label="map")
    if result.odometry_poses is not None and result.loops:
        odometry = result.odometry_poses[:, :3, 3].detach().cpu().numpy()
        ax.plot(odometry[:, a], odometry[:, b], color="tab:orange", lw=1, label="odometry")
    ax.plot(positions[:, a], positions[:, b], color="tab:blue", lw=1.5, label="trajectory")
    ax.scatter(keyframes[:, a], keyframes[:, b], s=6, color="tab:blue", zorder=3)
    for k, closure in enumerate(result.accepted_loops):
        p, q = keyframes[closure.first], keyframes[closure.second]
        ax.plot(
            [p[a], q[a]], [p[b], q[b]], color="tab:red", lw=1.2,
            label="loop closure" if k == 0 else None, zorder=4,
        )  # fmt: skip
    # frame the trajectory with a margin (a LiDAR map reaches far beyond it)
    low, high = positions.min(0), positions.max(0)
    margin = max(0.3 * float(np.max(high - low)), 1.0)
    ax.set_xlim(low[a] - margin, high[a] + margin)
    ax.set_ylim(low[b] - margin, high[b] + margin)
    names = "xyz"
    ax.set_xlabel(f"{names[a]} (m)")
    ax.set_ylabel(f"{names[b]} (m)")
    ax.set_aspect("equal")
    ax.set_title(
        f"{result.num_frames} frames, {len(result.keyframe_frames)} keyframes, "
        f"{len(result.accepted_loops)} loop closures"
    )
    ax.legend(loc="best", markerscale=10)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
