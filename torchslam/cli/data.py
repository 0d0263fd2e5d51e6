"""``torchslam data``: the named data sets (:mod:`torchslam.data.files`).

``torchslam data list`` prints each data set with its size, where it is (mirror, cached or
missing) and its licence note; ``torchslam data fetch NAME [NAME …]`` (or ``--all``) fetches
and checks them; ``torchslam data path NAME`` prints the folder (fetching it first), for
shell use: ``data=$(torchslam data path bunny)``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from torchslam.cli import EXIT_OK, _stderr

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``torchslam data``."""
    from torchslam.data.files import DATASETS

    sub = parser.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    sub.add_parser("list", help="the data sets, their size, where they are and their licence")
    fetch = sub.add_parser("fetch", help="download (or find) and check data sets")
    fetch.add_argument("names", nargs="*", choices=[*DATASETS, []], metavar="NAME")
    fetch.add_argument("--all", action="store_true", help="every data set")
    path = sub.add_parser("path", help="print a data set's folder (fetched first)")
    path.add_argument("name", choices=list(DATASETS), metavar="NAME")


def run(
    args: argparse.Namespace,
    echo: Callable[[str], None] = print,
    warn: Callable[[str], None] = _stderr,
) -> int:
    """Run ``torchslam data`` (module docstring); returns the exit status."""
    from torchslam.data import files

    if args.action == "list":
        echo(f"cache: {files.cache_folder()}  (TORCHSLAM_DATA; mirror: TORCHSLAM_DATA_MIRROR)")
        for name, dataset in files.DATASETS.items():
            echo(
                f"{name:18} {dataset.size / 1e6:7.1f} MB  {files.status(name):8} "
                f"{dataset.description}"
            )
            echo(f"{'':18} licence: {dataset.licence}")
        return EXIT_OK
    if args.action == "path":
        print(files.fetch(args.name, progress=sys.stderr.isatty()))
        return EXIT_OK
    names = list(files.DATASETS) if args.all else list(args.names)
    if not names:
        raise ValueError("name one or more data sets, or --all (see 'torchslam data list')")
    for name in names:
        folder = files.fetch(name, progress=sys.stderr.isatty() and echo is print)
        echo(f"{name}: {folder} ({len(files.DATASETS[name].files)} files checked)")
    return EXIT_OK
