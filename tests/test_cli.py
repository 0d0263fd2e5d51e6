"""The ``torchslam`` command keeps its contract (issue 8 and the "trust" issue).

- bad arguments and bad files: one line ``torchslam <command>: error: …`` on stderr, exit 2,
  never a traceback; numeric options are range-checked by argparse;
- a failed solve exits 1, one that stopped without converging warns;
- ``--quiet``, ``--verbose``, ``--version`` on every subcommand and at the top level;
- without matplotlib the default figures are skipped with one line (exit 0), ``--plot`` is an
  error before solving, and no "wrote" line names a file that was not written.

Everything runs in-process through ``cli.main`` (importing torch in a subprocess costs
seconds; tests/posegraph checks ``python -m torchslam`` end to end), on tiny problems.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
from pathlib import Path

import pytest
import torch

from torchslam import cli
from torchslam.cli import demo
from torchslam.cli import posegraph as posegraph_command
from torchslam.io import g2o
from torchslam.io.ply import write_ply
from torchslam.lie import se3, so3
from torchslam.posegraph.graph import PoseGraph
from torchslam.solver import Status

TINY_DEMO = ["demo", "--poses", "5", "--points", "60"]
SUBCOMMANDS = ["demo", "bench", "posegraph", "register", "slam"]


def call(argv: list[str], capsys) -> tuple[int, str, str]:
    """Run ``torchslam *argv`` in-process: (exit status, stdout, stderr)."""
    try:
        code = cli.main(argv)
    except SystemExit as exit_:  # argparse: errors, --help, --version
        code = exit_.code
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, err: str, prog: str, *fragments: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{prog}: error: "), err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, err)


def ring_graph_file(path: Path, n: int = 8, seed: int = 0) -> Path:
    """A small noisy 3D ring (odometry + 2 loop closures), vertices at the odometry chain."""
    generator = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    theta = 2 * math.pi * torch.arange(n, dtype=f64) / n
    zero = torch.zeros(n, dtype=f64)
    R = so3.exp(torch.stack((zero, zero, theta), -1))
    t = torch.stack((3 * torch.cos(theta), 3 * torch.sin(theta), zero), -1)
    truth = se3.from_rotation_translation(R, t)
    pairs = [(k, k + 1) for k in range(n - 1)] + [(n - 1, 0), (0, n // 2)]
    edges = torch.tensor(pairs, dtype=torch.int64)
    noise = se3.exp(0.02 * torch.randn(len(pairs), 6, generator=generator, dtype=f64))
    Z = se3.compose(se3.compose(se3.inverse(truth[edges[:, 0]]), truth[edges[:, 1]]), noise)
    chain = [truth[0]]
    for k in range(n - 1):
        chain.append(se3.compose(chain[-1], Z[k]))
    graph = PoseGraph(
        ids=torch.arange(n, dtype=torch.int64),
        poses=torch.stack(chain),
        edges=edges,
        measurements=Z,
        information=100.0 * torch.eye(6, dtype=f64).expand(len(pairs), 6, 6).clone(),
    )
    g2o.write_g2o(path, graph)
    return path


@pytest.fixture
def ring(tmp_path) -> Path:
    return ring_graph_file(tmp_path / "ring.g2o")


@pytest.fixture
def no_matplotlib(monkeypatch):
    """Simulate an install without matplotlib: importing it raises ModuleNotFoundError."""
    for name in ("matplotlib", "matplotlib.pyplot", "matplotlib.backends.backend_agg"):
        monkeypatch.setitem(sys.modules, name, None)


# ----------------------------------------------------------------------------- demo


def test_demo_small_writes_figure_and_summary(tmp_path, capsys):
    out = tmp_path / "figures"
    code, stdout, err = call(
        ["demo", "--poses", "12", "--points", "300", "--out", str(out)], capsys
    )
    assert code == 0, err
    assert (out / "demo.png").stat().st_size > 10_000
    lines = stdout.splitlines()
    assert any(line.strip().startswith("1 ") for line in lines)  # a progress line per iteration
    summary = next(line for line in lines if line.startswith("rotation error"))
    initial, optimized = (float(part.split("/")[0]) for part in summary.split()[-6::3][:2])
    assert optimized < 0.1 * initial
    assert "CONVERGED" in stdout and f"wrote {out / 'demo.png'}" in stdout


# ----------------------------------------------------------------------------- bad arguments


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["demo", "--points", "100000000000"], "argument --points: expected an integer in"),
        (["demo", "--points", "abc"], "argument --points"),
        (["demo", "--poses", "-3"], "argument --poses"),
        (["demo", "--poses", "2"], "argument --poses: expected an integer in [3, "),
        (["demo", "--noise", "1e300"], "argument --noise: expected a number in [0, 1]"),
        (["demo", "--noise", "nan"], "argument --noise"),
        (["demo", "--noise", "-0.1"], "argument --noise"),
        (["demo", "--drift-deg", "inf"], "argument --drift-deg"),
        (["demo", "--drift-translation", "1e9"], "argument --drift-translation"),
        (["demo", "--visible-fraction", "0"], "argument --visible-fraction"),
        (["demo", "--visible-fraction", "1.5"], "argument --visible-fraction"),
        (["demo", "--batch-size", "0"], "argument --batch-size"),
        (["demo", "--seed", "-1"], "argument --seed"),
        (["demo", "--seed", "99999999999999999999999"], "argument --seed"),
        (["demo", "--jacobian", "numeric"], "invalid choice"),
        (["demo", "--batch-size", "256", "--poses", "1000", "--points", "1000"], "≤ 1e+08"),
        (["bench", "--cases", "XL"], "invalid choice"),
        (["bench", "--repeats", "0"], "argument --repeats"),
        (["bench", "--threads", "0"], "argument --threads"),
        (["posegraph", "x.g2o", "--max-iterations", "0"], "argument --max-iterations"),
        (["posegraph", "x.g2o", "--threads", "1e3"], "argument --threads"),
        (["register", "a.ply", "b.ply", "--voxel-size", "-1"], "argument --voxel-size"),
        (["register", "a.ply", "b.ply", "--voxel-size", "inf"], "argument --voxel-size"),
        (["register", "a.ply", "b.ply", "--hypotheses", "0"], "argument --hypotheses"),
        (["register", "a.ply", "b.ply", "--rounds", "-1"], "argument --rounds"),
        (["frobnicate"], "invalid choice"),
        ([], "required: COMMAND"),
        (["--quiet", "demo", "--verbose"], "exclude each other"),
        (["demo", "--quiet", "--verbose"], "not allowed with argument"),
    ],
)
def test_bad_arguments_are_one_line_errors(argv, fragment, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = call(argv, capsys)
    prog = f"torchslam {argv[0]}" if argv and argv[0] in SUBCOMMANDS else "torchslam"
    if "exclude each other" in fragment:
        prog = "torchslam"
    assert_one_line_error(code, err, prog, fragment)
    assert out == ""
    assert not (tmp_path / "out").exists()  # nothing ran


# ----------------------------------------------------------------------------- bad files

PLY_HEADER = (
    "ply\nformat ascii 1.0\nelement vertex 12\nproperty float x\nproperty float y\n"
    "property float z\nproperty uchar red\nend_header\n"
)
GOOD_ROWS = [f"{0.1 * k} {0.2 * k % 1} {0.3 * k % 1} 7" for k in range(12)]


def _ply(rows: list[str]) -> str:
    return PLY_HEADER + "\n".join(rows) + "\n"


@pytest.mark.parametrize(
    ("name", "content", "fragments"),
    [
        ("binary.g2o", bytes(range(256)), ["binary.g2o", "line", "not a text g2o file"]),
        ("latin1.g2o", "# caf\xe9\n".encode("latin-1"), ["latin1.g2o", "line 1", "not a text"]),
        ("nan.g2o", "VERTEX_SE3:QUAT 0 nan 0 0 0 0 0 1\n", ["nan.g2o", "line 1", "finite"]),
        ("id.g2o", "VERTEX_SE3:QUAT 1" + "0" * 30 + " 0 0 0 0 0 0 1\n", ["id.g2o", "line 1"]),
        ("empty.g2o", "", ["empty.g2o", "no vertices"]),
    ],
)
def test_posegraph_bad_file_is_one_line_error(name, content, fragments, tmp_path, capsys):
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    code, _, err = call(["posegraph", str(path), "--out", str(tmp_path / "o.g2o")], capsys)
    assert_one_line_error(code, err, "torchslam posegraph", *fragments)
    assert not (tmp_path / "o.g2o").exists()


@pytest.mark.parametrize(
    ("content", "fragments"),
    [
        (_ply(["0 0 0 300", *GOOD_ROWS[1:]]), ["bad.ply", "line 9", "uchar", "300"]),
        (_ply(["0 0 0 2.7", *GOOD_ROWS[1:]]), ["bad.ply", "line 9", "'2.7'"]),
        # (a NaN coordinate is a missed return: dropped with a count, test_register.py)
        (_ply(GOOD_ROWS[:5]), ["bad.ply", "truncated"]),
        (_ply([*GOOD_ROWS, "1 2 3 4"]), ["bad.ply", "line 21", "beyond"]),
        ((PLY_HEADER + "\n".join(GOOD_ROWS)).replace("7", "\xe9", 1), ["bad.ply", "line 9"]),
        (b"\x00\xff" * 50, ["bad.ply", "not a PLY file"]),
    ],
)
def test_register_bad_scan_is_one_line_error(content, fragments, tmp_path, capsys):
    write_ply(tmp_path / "good.ply", torch.rand(20, 3, dtype=torch.float64))
    bad = tmp_path / "bad.ply"
    bad.write_bytes(content if isinstance(content, bytes) else content.encode("latin-1"))
    argv = ["register", str(tmp_path / "good.ply"), str(bad), "--out", str(tmp_path / "out")]
    code, _, err = call(argv, capsys)
    assert_one_line_error(code, err, "torchslam register", *fragments)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("line", "fragment"),
    [
        ("bmesh good.ply 0 0 nan 0 0 0 1", "finite"),
        ("bmesh good.ply 0 0 0 0 0 0 0", "zero quaternion"),
        ("bmesh good.ply 0 0 0 0 0 0 1 \xe9", "not a text .conf file"),
    ],
)
def test_register_bad_reference_is_one_line_error(line, fragment, tmp_path, capsys):
    for name in ("good", "other"):
        write_ply(tmp_path / f"{name}.ply", torch.rand(20, 3, dtype=torch.float64))
    conf = tmp_path / "ref.conf"
    conf.write_bytes(f"camera 0 0 0 0 0 0 1\n{line}\n".encode("latin-1"))
    argv = ["register", *(str(tmp_path / f"{n}.ply") for n in ("good", "other"))]
    code, _, err = call([*argv, "--reference", str(conf), "--out", str(tmp_path / "o")], capsys)
    assert_one_line_error(code, err, "torchslam register", "ref.conf", "line 2", fragment)


# ----------------------------------------------------------------------------- solve status


def _force_status(monkeypatch, status: Status) -> None:
    real = demo.solve

    def solve(*args, **kwargs):
        result = real(*args, **kwargs)
        result.status = [status] * len(result.status)
        return result

    monkeypatch.setattr(demo, "solve", solve)


def test_failed_solve_exits_1_and_says_so(tmp_path, capsys, monkeypatch):
    _force_status(monkeypatch, Status.NON_FINITE)
    code, out, err = call([*TINY_DEMO, "--out", str(tmp_path)], capsys)
    assert code == cli.EXIT_FAILED
    assert "status NON_FINITE" in out
    assert err.strip() == "torchslam demo: error: the solve failed: status NON_FINITE"


def test_unconverged_solve_warns_and_exits_0(tmp_path, capsys, monkeypatch):
    _force_status(monkeypatch, Status.MAX_ITERATIONS)
    code, out, err = call([*TINY_DEMO, "--out", str(tmp_path), "--quiet"], capsys)
    assert code == 0 and out == ""
    assert err.strip() == (
        "torchslam demo: warning: the solve stopped without converging: status MAX_ITERATIONS"
    )


def test_posegraph_status_decides_the_exit_status(ring, capsys, monkeypatch):
    code, out, err = call(["posegraph", str(ring), "--max-iterations", "1"], capsys)
    assert code == 0 and "status MAX_ITERATIONS" in out
    assert "warning: the solve stopped without converging: status MAX_ITERATIONS" in err
    real = posegraph_command.solve_pose_graph
    monkeypatch.setattr(
        posegraph_command,
        "solve_pose_graph",
        lambda *a, **k: dataclasses.replace(real(*a, **k), status=Status.NON_FINITE),
    )
    code, out, err = call(["posegraph", str(ring)], capsys)
    assert code == 1 and "status NON_FINITE" in out
    assert err.strip() == "torchslam posegraph: error: the solve failed: status NON_FINITE"


# ----------------------------------------------------------------------------- common options


@pytest.mark.parametrize("argv", [[], *([sub] for sub in SUBCOMMANDS)])
def test_version_everywhere(argv, capsys):
    from torchslam import __version__

    code, out, err = call([*argv, "--version"], capsys)
    assert code == 0 and out.strip() == f"torchslam {__version__}" and err == ""


@pytest.mark.parametrize("sub", SUBCOMMANDS)
def test_help_lists_common_options(sub, capsys):
    code, out, _ = call([sub, "--help"], capsys)
    assert code == 0 and out.startswith(f"usage: torchslam {sub}")
    for option in ("--quiet", "--verbose", "--version"):
        assert option in out


@pytest.mark.parametrize("where", ["top", "sub"])
def test_quiet_prints_nothing(where, ring, tmp_path, capsys):
    for argv in ([*TINY_DEMO, "--out", str(tmp_path)], ["posegraph", str(ring)]):
        argv = ["--quiet", *argv] if where == "top" else [*argv, "-q"]
        code, out, err = call(argv, capsys)
        assert (code, out, err) == (0, "", "")
    assert (tmp_path / "demo.png").is_file()  # outputs are still written


def test_verbose_prints_the_library_log_records(ring, capsys):
    logger = logging.getLogger("torchslam")
    level, handlers = logger.level, list(logger.handlers)
    code, out, err = call(["posegraph", str(ring), "--verbose"], capsys)
    assert code == 0
    assert "torchslam.posegraph: iter   1" in err
    assert "accepted" not in out  # each iteration once: the log record, not the table line too
    code, _, err = call(["--verbose", *TINY_DEMO, "--out", str(ring.parent)], capsys)
    assert code == 0 and "torchslam.solver: iter   1" in err
    assert logger.level == level and logger.handlers == handlers  # restored after the run
    code, _, err = call(["posegraph", str(ring)], capsys)
    assert "torchslam.posegraph" not in err


# ----------------------------------------------------------------------------- no matplotlib

SKIPPED = "figure skipped: matplotlib is not installed; pip install 'torchslam[plot]'"


def test_demo_without_matplotlib_skips_the_figure(no_matplotlib, tmp_path, capsys):
    code, out, err = call([*TINY_DEMO, "--out", str(tmp_path / "o")], capsys)
    assert code == 0
    assert err.strip() == f"torchslam demo: {SKIPPED}"
    assert "wrote" not in out and not (tmp_path / "o" / "demo.png").exists()


def test_posegraph_plot_without_matplotlib_fails_before_solving(no_matplotlib, ring, capsys):
    out_file, plot = ring.parent / "opt.g2o", ring.parent / "fig.png"
    argv = ["posegraph", str(ring), "--out", str(out_file), "--plot", str(plot)]
    code, out, err = call(argv, capsys)
    assert_one_line_error(code, err, "torchslam posegraph", "--plot needs matplotlib", "[plot]")
    assert out == "" and not out_file.exists() and not plot.exists()
    code, out, err = call(["posegraph", str(ring), "--out", str(out_file)], capsys)
    assert code == 0 and err == "" and out_file.is_file()  # no figure asked for: no message


def test_bench_without_matplotlib_writes_only_the_json(no_matplotlib, tmp_path, capsys):
    argv = ["bench", "--cases", "S", "--quick", "--threads", "1", "--out", str(tmp_path)]
    code, out, err = call(argv, capsys)
    assert code == 0, err
    assert err.strip() == f"torchslam bench: {SKIPPED}"
    assert f"wrote {tmp_path / 'bench_solver.json'}\n" in out and ".png" not in out
    assert (tmp_path / "bench_solver.json").is_file()
    assert not (tmp_path / "bench_solver.png").exists()


def test_register_without_matplotlib_writes_the_rest(no_matplotlib, tmp_path, capsys):
    from tests.test_register import critter_scans

    _, clouds = critter_scans(num_scans=2, points=600)
    paths = [tmp_path / f"s{i}.ply" for i in range(2)]
    for path, cloud in zip(paths, clouds, strict=True):
        write_ply(path, cloud)
    out = tmp_path / "out"
    argv = ["register", *map(str, paths), "--voxel-size", "0.08", "--hypotheses", "8", "--chain"]
    code, stdout, err = call([*argv, "--rounds", "1", "--out", str(out)], capsys)
    assert code == 0, err
    assert err.strip() == f"torchslam register: {SKIPPED}"
    assert "registration.png" not in stdout
    assert "s0 ← s1 (1/1): converged" in stdout  # the ICP status by name
    assert {p.name for p in out.iterdir()} == {"poses.txt", "poses_pairwise.txt", "merged.ply"}


# ----------------------------------------------------------------------------- entry points


@pytest.mark.parametrize("sub", ["register", "bench"])
def test_module_mains_share_the_contract(sub, capsys):
    from torchslam.cli import bench, register

    main = register.main if sub == "register" else bench.main
    argv = ["a.ply", "b.ply", "--rounds", "-2"] if sub == "register" else ["--repeats", "-2"]
    code, _, err = call_main(main, argv, capsys)
    assert_one_line_error(code, err, f"torchslam {sub}", "argument")


def call_main(main, argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code
    out, err = capsys.readouterr()
    return code, out, err


# ----------------------------------------------------------------------------- posegraph --certify


def test_certify_writes_what_it_certified_and_says_so_under_quiet(ring, tmp_path, capsys):
    from torchslam.io import g2o
    from torchslam.posegraph import objectives

    out = tmp_path / "opt.g2o"
    code, stdout, err = call(["posegraph", str(ring), "--certify", "--out", str(out), "-q"], capsys)
    assert code == 0, err
    # -q: the verdict line only
    assert stdout.startswith("certified global optimum: yes") and stdout.count("\n") == 1
    objective = float(stdout.split("SE-Sync objective ")[1].split(" ")[0])
    written = g2o.read_g2o(out)
    # the file holds the certified (SE-Sync-refined) poses: its objective is the certified one
    # to the 8 digits printed
    value = float(objectives.sesync_objective(written, written.poses))
    assert value == pytest.approx(objective, rel=1e-7)
    code, stdout, _ = call(["posegraph", str(ring), "--certify", "--out", str(out)], capsys)
    assert "(the SE-Sync-refined poses that were certified)" in stdout


def test_not_certified_exits_3(ring, capsys, monkeypatch):
    import dataclasses

    from torchslam.posegraph import certification

    real = certification.certify

    def uncertain(*args, **kwargs):
        return dataclasses.replace(real(*args, **kwargs), certified=False)

    monkeypatch.setattr(certification, "certify", uncertain)
    code, stdout, _ = call(["posegraph", str(ring), "--certify", "-q"], capsys)
    assert code == 3 and stdout.startswith("certified global optimum: no")
