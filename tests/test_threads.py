"""The thread policy of a solve (torchslam._threads): small problems on one intra-op thread,
larger ones on torch's setting, the caller's count restored in every case."""

from __future__ import annotations

import pytest
import torch

import torchslam as ts
from torchslam import _threads
from torchslam.data import benchmark_case
from torchslam.initialization import initialize_scene


def _problem(case: str) -> ts.PointMapProblem:
    scene = benchmark_case(case, seed=0)
    init = initialize_scene(scene, method="odometry", rotation_noise_deg=1.0, seed=1)
    return ts.PointMapProblem.from_scene(scene, init.poses, init.points)


@pytest.fixture
def two_threads(monkeypatch):
    # a quiet 2-core machine, whatever this one is doing (the load is tested on its own below)
    monkeypatch.setattr(_threads, "usable_cores", lambda: 2)
    monkeypatch.setattr(_threads, "busy_cores", lambda: 0)
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(previous)


def test_a_large_solve_leaves_the_busy_cores_alone(two_threads, monkeypatch):
    data = _problem("M").data
    monkeypatch.setattr(_threads, "busy_cores", lambda: 1)  # another process keeps one busy
    with _threads.threads_for(data):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    monkeypatch.setattr(_threads, "usable_cores", lambda: 8)  # a larger machine has room
    with _threads.threads_for(data):
        assert torch.get_num_threads() == 2
    assert _threads.available_threads(1) == 1


def test_busy_cores_reads_a_count():
    assert _threads.busy_cores() >= 0 and _threads.usable_cores() >= 1


def test_small_problem_runs_on_one_thread_and_restores(two_threads):
    data = _problem("S").data  # 11 frames, 1,400 observations: 9·E below the grain size
    assert _threads.solve_entries(data) < _threads.GRAIN_SIZE
    with _threads.threads_for(data):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2


def test_large_problem_keeps_the_callers_threads(two_threads):
    data = _problem("BATCH").data  # 64 problems: 9·B·E far above the grain size
    assert _threads.solve_entries(data) >= _threads.GRAIN_SIZE
    with _threads.threads_for(data):
        assert torch.get_num_threads() == 2


def test_solve_and_implicit_backward_restore_the_thread_count(two_threads):
    problem = _problem("S")
    seen = []
    ts.solve(problem, callback=lambda info: seen.append(torch.get_num_threads()))
    assert seen and set(seen) == {1}
    assert torch.get_num_threads() == 2
    scene = benchmark_case("S", seed=0)
    init = initialize_scene(scene, method="odometry", rotation_noise_deg=1.0, seed=1)
    result, _ = ts.benchmark.training_step(scene, init)  # forward + implicit backward
    assert result.status[0].converged

    assert torch.get_num_threads() == 2


def test_an_exception_inside_restores_the_thread_count(two_threads):
    data = _problem("S").data
    with pytest.raises(KeyError), _threads.threads_for(data):
        raise KeyError("inside")
    assert torch.get_num_threads() == 2


def test_problem_construction_follows_the_policy_and_restores(two_threads, monkeypatch):
    """A small problem's construction (its checks and gauge) runs on one thread too."""
    seen = []
    original = ts.problem._gauge.hold_ill_posed_fixed

    def spy(*args, **kwargs):
        seen.append(torch.get_num_threads())
        return original(*args, **kwargs)

    monkeypatch.setattr(ts.problem._gauge, "hold_ill_posed_fixed", spy)
    _problem("S")
    assert seen == [1]
    assert torch.get_num_threads() == 2
    seen.clear()
    _problem("BATCH")
    assert seen == [2]
    assert torch.get_num_threads() == 2
