"""Old module paths keep working for one release: the same objects, with a DeprecationWarning.

Issue 13 ("Rooms that say what they hold") moved the registration and command-line code; the
old paths are shims that forward every moved name to its new home (README: "Deprecated names").
"""

from __future__ import annotations

import importlib
import warnings

import pytest

import torchslam

# old module → {name: new module}
MOVED = {
    "torchslam.icp": {
        name: "torchslam.registration.icp"
        for name in (
            "ICPConfig",
            "ICPResult",
            "ICPStatus",
            "Stage",
            "icp",
            "icp_batch",
            "icp_multistart",
            "initial_guesses",
            "register_coarse_to_fine",
            "rotations_about_axis",
            "rotations_uniform",
            "chain_poses",
            "voxel_downsample",
            "nearest_neighbors",
            "estimate_normals",
        )
    },
    "torchslam.tracks": {
        name: "torchslam.registration.tracks"
        for name in ("Tracks", "build_tracks", "mutual_nearest_neighbors")
    },
    "torchslam.register": {
        **dict.fromkeys(("RegisterConfig", "default_stages"), "torchslam.registration.config"),
        **dict.fromkeys(
            (
                "ChainResult",
                "RefineResult",
                "Registration",
                "RoundInfo",
                "boundary_mask",
                "information_matrices",
                "joint_cost",
                "load_scans",
                "overlapping_pairs",
                "refine",
                "register",
                "register_chain",
            ),
            "torchslam.registration.pipeline",
        ),
        **dict.fromkeys(
            ("alignment_residual", "error_table", "plane_distances"),
            "torchslam.registration.report",
        ),
        **dict.fromkeys(("read_poses", "write_poses"), "torchslam.io.trajectories"),
        **dict.fromkeys(("add_arguments", "main", "run"), "torchslam.cli.register"),
        **dict.fromkeys(
            ("merged_cloud", "plot_registration", "scan_colors"), "torchslam.cli.plots"
        ),
    },
    "torchslam.posegraph.command": {
        **dict.fromkeys(
            (
                "INITIALIZATIONS",
                "PoseGraphOptions",
                "add_arguments",
                "initial_poses",
                "options_from_args",
                "run_posegraph",
            ),
            "torchslam.cli.posegraph",
        ),
        "plot_trajectories": "torchslam.cli.plots",
    },
    "torchslam.demo": dict.fromkeys(
        ("DemoOptions", "LIMITS", "add_arguments", "options_from_args", "run_demo", "validate"),
        "torchslam.cli.demo",
    ),
    "torchslam.benchmark": dict.fromkeys(("add_arguments", "main", "run"), "torchslam.cli.bench"),
}
CASES = [(old, name, new) for old, names in MOVED.items() for name, new in names.items()]


@pytest.mark.parametrize(("old", "name", "new"), CASES)
def test_old_path_gives_the_same_object_and_warns(old, name, new):
    module = importlib.import_module(old)
    with pytest.warns(DeprecationWarning, match=rf"{old}\.{name} is deprecated: use {new}\.{name}"):
        value = getattr(module, name)
    assert value is getattr(importlib.import_module(new), name)


@pytest.mark.parametrize("old", sorted(MOVED))
def test_importing_an_old_path_does_not_warn_and_from_import_does(old):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        module = importlib.import_module(old)
    name = next(iter(MOVED[old]))
    with pytest.warns(DeprecationWarning, match=f"{old}.{name}"):
        exec(f"from {old} import {name}", {})
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        module.not_a_name  # noqa: B018


def test_top_level_aliases_are_the_shims():
    assert torchslam.icp is importlib.import_module("torchslam.icp")
    assert torchslam.tracks is importlib.import_module("torchslam.tracks")
    with pytest.warns(DeprecationWarning, match="use torchslam.registration.icp.icp"):
        assert torchslam.icp.icp is torchslam.registration.icp.icp


def test_benchmark_keeps_its_measurements_without_warning():
    from torchslam import benchmark

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert callable(benchmark.run_case) and callable(benchmark.build)
