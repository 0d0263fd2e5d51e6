"""Old module paths keep working for one release: the same objects, with a DeprecationWarning.

Issue 13 ("Rooms that say what they hold") moved the registration and command-line code; the
old paths are shims that forward every moved name to its new home (docs/reference.md:
"Deprecated names").
"""

from __future__ import annotations

import importlib
import warnings

import pytest

import torchslam

# old module → {new module: the names that moved there} (the old modules' public names)
MOVED = {
    "torchslam.icp": {
        "torchslam.registration.icp": "ICPConfig ICPResult ICPStatus Stage chain_poses icp "
        "icp_batch icp_multistart initial_guesses register_coarse_to_fine rotations_about_axis "
        "rotations_uniform voxel_downsample nearest_neighbors estimate_normals"
    },
    "torchslam.tracks": {
        "torchslam.registration.tracks": "Tracks build_tracks mutual_nearest_neighbors"
    },
    "torchslam.register": {
        "torchslam.registration.config": "RegisterConfig default_stages",
        "torchslam.registration.pipeline": "ChainResult RefineResult Registration RoundInfo "
        "boundary_mask information_matrices joint_cost load_scans overlapping_pairs refine "
        "register register_chain",
        "torchslam.registration.report": "alignment_residual error_table plane_distances",
        "torchslam.io.trajectories": "read_poses write_poses",
        "torchslam.cli.register": "add_arguments main run",
        "torchslam.cli.plots": "merged_cloud plot_registration scan_colors",
    },
    "torchslam.posegraph.command": {
        "torchslam.cli.posegraph": "INITIALIZATIONS PoseGraphOptions add_arguments initial_poses "
        "options_from_args run_posegraph",
        "torchslam.cli.plots": "plot_trajectories",
    },
    "torchslam.demo": {
        "torchslam.cli.demo": "DemoOptions LIMITS MAX_SCENE_SIZE add_arguments options_from_args "
        "run_demo validate"
    },
    "torchslam.benchmark": {"torchslam.cli.bench": "add_arguments main run"},
}
CASES = [
    (old, name, new)
    for old, homes in MOVED.items()
    for new, names in homes.items()
    for name in names.split()
]


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
    name = next(name for case_old, name, _ in CASES if case_old == old)
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


def test_iteration_info_item_access_warns_and_maps_lambda_to_damping():
    import torch

    import torchslam

    seen = []
    scene = torchslam.data.make_scene(4, 30, seed=0)
    problem = torchslam.PointMapProblem.from_scene(scene, scene.poses_gt, scene.points_gt + 0.01)
    torchslam.solve(problem, callback=seen.append)
    info = seen[0]
    assert isinstance(info, torchslam.IterationInfo)
    with pytest.warns(DeprecationWarning, match="info.damping"):
        assert torch.equal(info["lambda"], info.damping)
    with pytest.warns(DeprecationWarning, match="info.cost"):
        assert torch.equal(info["cost"], info.cost)
    with pytest.warns(DeprecationWarning), pytest.raises(KeyError):
        info["no such key"]
