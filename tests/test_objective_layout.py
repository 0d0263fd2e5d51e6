"""The objective's rooms (torchslam.objective: data, terms, gauge) and the deprecated paths.

Names that moved out of ``torchslam.problem`` and ``torchslam.terms`` stay reachable there
for one release, as the same objects, with a DeprecationWarning naming the new place.
"""

from __future__ import annotations

import importlib
import warnings

import pytest

import torchslam
from torchslam.objective import data, terms

MOVED_FROM_PROBLEM = {
    "PointMapData": data.PointMapData,
    "cost": data.cost,
    "cost_from_poses": data.cost_from_poses,
    "gather_points": data.gather_points,
    "gather_poses": data.gather_poses,
    "jacobian_blocks": data.jacobian_blocks,
    "per_observation": data.per_observation,
    "raw_residuals": data.raw_residuals,
    "raw_residuals_from_poses": data.raw_residuals_from_poses,
    "check_data_values": data.check_data_values,
    "mark_checked": data.mark_checked,
}


@pytest.mark.parametrize("name", sorted(MOVED_FROM_PROBLEM))
def test_old_problem_names_warn_and_are_the_moved_objects(name):
    problem = importlib.import_module("torchslam.problem")
    with pytest.warns(DeprecationWarning, match=rf"torchslam\.problem\.{name} is deprecated"):
        value = getattr(problem, name)
    assert value is MOVED_FROM_PROBLEM[name]


@pytest.mark.parametrize("name", ["Term", "RelativePoseTerm", "term_jacobians", "term_poses"])
def test_old_terms_module_warns_and_gives_the_moved_objects(name):
    old = importlib.import_module("torchslam.terms")
    with pytest.warns(DeprecationWarning, match=rf"torchslam\.objective\.terms\.{name}"):
        value = getattr(old, name)
    assert value is getattr(terms, name)


def test_unknown_names_raise_attribute_error_without_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for module in ("torchslam.problem", "torchslam.terms"):
            with pytest.raises(AttributeError, match="has no attribute 'nonexistent'"):
                _ = importlib.import_module(module).nonexistent


def test_public_names_need_no_deprecated_path():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from torchslam.problem import PointMapProblem

    assert PointMapProblem is torchslam.PointMapProblem
    assert torchslam.PointMapData is data.PointMapData
    for name in ("Term", "RelativePoseTerm", "PosePriorTerm", "PointObservationTerm"):
        assert getattr(torchslam, name) is getattr(terms, name)
