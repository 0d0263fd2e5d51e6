"""The ``torchslam`` command: a thin argparse front end over the library.

Subcommands: ``demo`` (synthetic ICP-SLAM solve with live progress and a figure),
``bench`` (the solver benchmark), ``posegraph`` (optimize a g2o pose graph), ``register``
(multiview registration of range scans), ``slam`` (ICP-SLAM on a sequence of depth images or
LiDAR scans), ``ba`` (bundle adjustment of a BAL file) and ``data`` (the named real data
sets).

Options of every subcommand (and of ``torchslam`` itself): ``--quiet`` (only warnings and
errors, on stderr), ``--verbose`` (also the library's log records: loggers
``torchslam.solver`` and ``torchslam.posegraph``, on stderr) and ``--version``.

Exit status:

- 0: success. A solve that stopped without converging (iteration limit, damping limit) still
  exits 0, but its status is printed and a ``warning:`` line goes to stderr.
- 1: the run failed: a solve ended ``NON_FINITE`` or ``LINEAR_SOLVE_FAILED`` (status printed,
  outputs still written), or the machine ran out of memory.
- 2: bad input: an impossible option value, a missing or malformed file, a figure asked for
  with ``--plot`` while matplotlib is missing. One line on stderr,
  ``torchslam <command>: error: …``, and never a traceback.
- 3: ``posegraph --certify`` solved, but SE-Sync's certificate does not prove the optimum
  global (the verdict line is printed even under ``--quiet``).
- 130: interrupted (Ctrl-C).

Threads (one policy for every subcommand): ``--threads N`` sets torch's intra-op threads for
the run (and the worker threads of SciPy's KD-tree queries in ``register``), default
:data:`DEFAULT_THREADS` = 1. The per-observation and per-edge tensors of these solves are small,
and on a CPU shared with other work a second OpenMP thread waits for a busy core (measured 5–7×
slower); only large dense systems (the L case of ``bench``) gain from more. Inside the library a
solve whose tensors all stay below torch's parallel grain size runs on one thread whatever the
setting (:mod:`torchslam._threads`), so more threads never slow a small solve down. The
previous thread count is restored when the command returns.

Figures need matplotlib (``pip install 'torchslam[plot]'``). Without it, the figures that a
command writes by default (``demo``, ``bench``, ``register``) are skipped with one
``figure skipped: …`` line on stderr and exit status 0; ``posegraph --plot`` asks for one
explicitly and stops with status 2 before solving.

Layout: this module holds the parser, the shared option types and the exit-status rules; each
subcommand has its module (:mod:`~torchslam.cli.demo`, :mod:`~torchslam.cli.bench`,
:mod:`~torchslam.cli.posegraph`, :mod:`~torchslam.cli.register`, :mod:`~torchslam.cli.slam`:
options, ``run``), and
:mod:`~torchslam.cli.plots` draws every figure (matplotlib, imported lazily).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import re
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import NoReturn

__all__ = [
    "DEFAULT_THREADS",
    "EXIT_FAILED",
    "EXIT_INTERRUPTED",
    "EXIT_NOT_CERTIFIED",
    "EXIT_OK",
    "EXIT_USAGE",
    "Parser",
    "add_common_options",
    "add_threads_argument",
    "float_range",
    "int_range",
    "main",
    "solve_exit_status",
    "using_threads",
]

EXIT_OK = 0
# torch threads of every subcommand unless --threads says otherwise (module docstring).
DEFAULT_THREADS = 1
EXIT_FAILED = 1
EXIT_USAGE = 2
# posegraph --certify: the solve succeeded but its optimum is not certified global
EXIT_NOT_CERTIFIED = 3
EXIT_INTERRUPTED = 130

# Loggers of the library (documented in docs/index.md, "Logging").
LOGGERS = ("torchslam.solver", "torchslam.posegraph")


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line on stderr (no usage block), exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def int_range(low: int, high: int) -> Callable[[str], int]:
    """argparse ``type``: a decimal integer in [low, high]."""

    def parse(text: str) -> int:
        try:
            value = int(text, 10)
        except ValueError:
            value = None
        if value is None or not low <= value <= high:
            raise argparse.ArgumentTypeError(
                f"expected an integer in [{low}, {high}], got {text!r}"
            )
        return value

    parse.__name__ = "integer"  # argparse names the type in some messages
    return parse


def float_range(low: float, high: float, *, low_open: bool = False) -> Callable[[str], float]:
    """argparse ``type``: a finite number in [low, high] (or (low, high] with ``low_open``)."""
    interval = f"{'(' if low_open else '['}{low:g}, {high:g}]"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        above = value > low if low_open else value >= low
        if not (math.isfinite(value) and above and value <= high):  # also rejects NaN
            raise argparse.ArgumentTypeError(f"expected a number in {interval}, got {text!r}")
        return value

    parse.__name__ = "number"
    return parse


def add_common_options(parser: argparse.ArgumentParser, *, top_level: bool = False) -> None:
    """``--quiet``, ``--verbose`` and ``--version``.

    On a subcommand the defaults are suppressed, so that ``torchslam --quiet demo`` and
    ``torchslam demo --quiet`` both work (a subparser's default would overwrite the value the
    top-level parser set).
    """
    from torchslam import __version__

    default = False if top_level else argparse.SUPPRESS
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=default,
        help="print nothing but warnings and errors (on stderr)",
    )
    group.add_argument(
        "-v",
        "--verbose",
        action="store_true",
        default=default,
        help=f"also print the library's log records ({', '.join(LOGGERS)}) on stderr",
    )
    parser.add_argument("--version", action="version", version=f"torchslam {__version__}")


def add_threads_argument(parser: argparse.ArgumentParser) -> None:
    """``--threads N`` (the module docstring's policy), the same on every subcommand."""
    parser.add_argument(
        "--threads",
        type=int_range(1, 1024),
        default=DEFAULT_THREADS,
        help=f"torch CPU threads [1, 1024] (default {DEFAULT_THREADS}: on a CPU shared with "
        "other work a second thread waits for a busy core; more pay only for large dense "
        "systems)",
    )


@contextlib.contextmanager
def using_threads(threads: int) -> Iterator[None]:
    """``with using_threads(n):`` torch runs on n intra-op threads inside, restored after."""
    import torch

    if not isinstance(threads, int) or isinstance(threads, bool) or threads < 1:
        raise ValueError(f"--threads must be an integer ≥ 1, got {threads!r}")
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _stderr(line: str) -> None:
    """The default ``warn`` of the subcommands' ``run`` functions: one line on stderr."""
    print(line, file=sys.stderr)


def solve_exit_status(
    statuses: Iterable, warn: Callable[[str], None], what: str = "the solve"
) -> int:
    """Exit status of solves (module docstring): 1 if any failed, else 0 (with a warning for
    any that stopped without converging). ``statuses``: ``torchslam.solver.Status`` values or
    their names."""
    from torchslam.solver import Status

    statuses = [Status[s] if isinstance(s, str) else Status(int(s)) for s in statuses]
    failed = sorted(
        {s.name for s in statuses if s in (Status.NON_FINITE, Status.LINEAR_SOLVE_FAILED)}
    )
    stopped = sorted({s.name for s in statuses if not s.converged} - set(failed))
    if failed:
        warn(f"error: {what} failed: status {', '.join(failed)}")
        return EXIT_FAILED
    if stopped:
        warn(f"warning: {what} stopped without converging: status {', '.join(stopped)}")
    return EXIT_OK


def _parser() -> Parser:
    parser = Parser(
        prog="torchslam",
        description="ICP-SLAM as batched, differentiable least squares on SE(3).",
        epilog="Exit status: 0 success, 1 a solve failed (NON_FINITE, LINEAR_SOLVE_FAILED), "
        "2 bad arguments or input files, 3 posegraph --certify: not certified, 130 interrupted. "
        "Threads: every command runs torch on --threads N CPU threads, 1 by default (on a CPU "
        "shared with other work a second thread waits for a busy core).",
    )
    add_common_options(parser, top_level=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    demo = sub.add_parser(
        "demo",
        help="solve a synthetic looping ICP-SLAM scene with LM and plot it",
        description="Generate a looping synthetic scene with noise and drifted odometry, solve "
        "it with Levenberg-Marquardt (one progress line per iteration), print a summary table "
        "and write demo.png (needs matplotlib; skipped with a message without it).",
    )
    from torchslam.cli import bench as bench_command
    from torchslam.cli import data as data_command
    from torchslam.cli import demo as demo_command
    from torchslam.cli import posegraph as posegraph_command
    from torchslam.cli import register as register_command
    from torchslam.cli import slam as slam_command

    demo_command.add_arguments(demo)
    add_common_options(demo)

    bench = sub.add_parser(
        "bench",
        help="run the solver benchmark (cases S, M, L, O, BATCH, TRAIN)",
        description="Time the solver on the synthetic cases S, M, L, O, BATCH and TRAIN "
        "(float64), compare with scipy.optimize.least_squares, write bench_solver.json and "
        "bench_solver.png.",
    )
    bench_command.add_arguments(bench)
    add_common_options(bench)

    posegraph = sub.add_parser(
        "posegraph",
        help="optimize a g2o pose graph with Levenberg-Marquardt",
        description="Read a 3D (VERTEX_SE3:QUAT/EDGE_SE3:QUAT) or 2D (VERTEX_SE2/EDGE_SE2) g2o "
        "pose graph, minimize ½ Σ rᵀΩr with Levenberg-Marquardt and a sparse linear solver "
        "(one progress line per iteration), print the costs before and after, optionally "
        "write the optimized graph and a figure of the trajectory before and after.",
    )
    posegraph_command.add_arguments(posegraph)
    add_common_options(posegraph)

    register = sub.add_parser(
        "register",
        help="register range scans (PLY, PCD, XYZ, NPY, BIN, LAS) by pairwise ICP + joint ICP-SLAM",
        description="Multiview registration: pairwise ICP over all pairs of scans in any order "
        "(their spanning tree; --chain: along the given order) for the initial poses, point "
        "tracks, then the joint ICP-SLAM least-squares solve (robust), re-associated a few "
        "rounds. Writes poses.txt (joint), poses_pairwise.txt (initial), merged.ply and "
        "registration.png.",
    )
    register_command.add_arguments(register)
    add_common_options(register)

    slam = sub.add_parser(
        "slam",
        help="ICP-SLAM on a folder of depth images or LiDAR scans",
        description="Frame-to-model point-to-plane odometry, keyframes, ICP-verified loop "
        "closures and a pose graph over the keyframes, on a folder of frames (depth .png, or "
        ".pcd/.bin/.ply/.npy LiDAR scans, sorted by name). Writes trajectory_tum.txt, "
        "trajectory_kitti.txt (frame → world), map.ply and slam.png; with --reference, "
        "prints ATE and RPE.",
    )
    slam_command.add_arguments(slam)
    add_common_options(slam)

    from torchslam.cli import ba as ba_command

    ba = sub.add_parser(
        "ba",
        help="bundle adjustment of a BAL file (cameras with intrinsics, points)",
        description="Solve a Bundle Adjustment in the Large problem (each camera a pose plus "
        "an intrinsics block (f, k1, k2), Snavely's projection) with Levenberg-Marquardt and "
        "the Schur complement on the points; prints Ceres-like iteration lines and a summary; "
        "--out writes the optimized problem in BAL format.",
    )
    ba_command.add_arguments(ba)
    add_common_options(ba)

    data = sub.add_parser(
        "data",
        help="list, fetch or locate the named real data sets",
        description="The real data sets of the examples and tests (torchslam.data.files): "
        "list them, fetch them (checked by sha256; TORCHSLAM_DATA sets the cache folder, "
        "TORCHSLAM_DATA_MIRROR an offline mirror), or print a data set's folder.",
    )
    data_command.add_arguments(data)
    add_common_options(data)
    return parser


class _Logging:
    """``--verbose``: the library's log records (DEBUG and up) on stderr, for one run."""

    def __init__(self, verbose: bool) -> None:
        self.verbose = verbose
        self.logger = logging.getLogger("torchslam")
        self.handler = logging.StreamHandler(sys.stderr)
        self.handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
        self.level = self.logger.level

    def __enter__(self) -> _Logging:
        if self.verbose:
            self.logger.addHandler(self.handler)
            self.logger.setLevel(logging.DEBUG)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.verbose:
            self.logger.removeHandler(self.handler)
            self.logger.setLevel(self.level)


def run_guarded(prog: str, body: Callable[[], int]) -> int:
    """Run a command body; turn bad input into one line on stderr and an exit status."""
    try:
        return body()
    except (ValueError, TypeError, OSError) as error:
        _stderr(f"{prog}: error: {_one_line(error)}")
        return EXIT_USAGE
    except MemoryError:
        _stderr(f"{prog}: error: out of memory (try smaller sizes)")
        return EXIT_FAILED
    except KeyboardInterrupt:
        _stderr(f"{prog}: interrupted")
        return EXIT_INTERRUPTED


def _one_line(error: BaseException) -> str:
    """The error as one line for a command-line user: an OSError without its ``[Errno N]``,
    and without the library function the message starts with (``read_g2o: …``), which names
    the code rather than what went wrong."""
    text = str(error)
    if isinstance(error, OSError) and error.strerror:
        text = error.strerror
        if error.filename is not None and str(error.filename) not in text:
            text = f"{text}: {error.filename}"
    text = " ".join(text.split())
    match = _FUNCTION_PREFIX.match(text)
    if match and not Path(match.group(1)).exists():
        text = text[match.end() :]
    return text or type(error).__name__


# "name: " at the start of a message, name a Python identifier (a library function's name).
_FUNCTION_PREFIX = re.compile(r"([A-Za-z_][A-Za-z0-9_]*): ")


def _check_version_last(parser: Parser, argv: list[str]) -> None:
    """argparse prints the version and exits at ``--version``, ignoring what follows it:
    refuse arguments after it instead (exit status 2), so ``--version extra`` is an error."""
    for k, token in enumerate(argv):
        if token == "--":
            return
        # argparse also accepts unambiguous abbreviations (--versi, --versio).
        if len(token) >= len("--versi") and "--version".startswith(token):
            if argv[k + 1 :]:
                parser.error(
                    f"{token} takes no other arguments after it, got {' '.join(argv[k + 1 :])}"
                )
            return


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``torchslam`` console script; returns the exit status (argparse's
    exits for errors, ``--help`` and ``--version`` included: nothing raises SystemExit)."""
    parser = _parser()
    try:
        _check_version_last(parser, sys.argv[1:] if argv is None else list(argv))
        args = parser.parse_args(argv)
        quiet, verbose = getattr(args, "quiet", False), getattr(args, "verbose", False)
        if quiet and verbose:
            parser.error("--quiet and --verbose exclude each other")
    except SystemExit as exit_:
        code = exit_.code
        return EXIT_OK if code is None else code if isinstance(code, int) else EXIT_USAGE
    prog = f"torchslam {args.command}"
    echo: Callable[[str], None] = (lambda _line: None) if quiet else print

    def warn(line: str) -> None:
        _stderr(f"{prog}: {line}")

    def body() -> int:
        if args.command == "demo":
            from torchslam.cli import demo

            result = demo.run_demo(demo.options_from_args(args), echo=echo, warn=warn)
            return solve_exit_status(result.status, warn)
        if args.command == "bench":
            from torchslam.cli import bench

            rows = bench.run(args, echo=echo, warn=warn)
            statuses = [s for row in rows for s in row["status"]]
            return solve_exit_status(statuses, warn, "a benchmark solve")
        if args.command == "posegraph":
            from torchslam.cli import posegraph

            certificates: list = []
            result = posegraph.run_posegraph(
                posegraph.options_from_args(args), echo=echo, verdict=print,
                on_certificate=certificates.append,
            )  # fmt: skip
            code = solve_exit_status([result.status], warn)
            if code == EXIT_OK and certificates and not certificates[0].certified:
                return EXIT_NOT_CERTIFIED
            return code
        if args.command == "data":
            from torchslam.cli import data

            return data.run(args, echo=echo, warn=warn)
        if args.command == "slam":
            from torchslam.cli import slam

            return slam.run(args, echo=echo, warn=warn)
        if args.command == "ba":
            from torchslam.cli import ba

            result = ba.run(args, echo=echo, warn=warn)
            return solve_exit_status(result.status, warn)
        from torchslam.cli import register

        return register.run(args, echo=echo, warn=warn)

    with _Logging(verbose):
        return run_guarded(prog, body)
