"""The ``mocap`` command line.

Each subcommand lives in ``mocap.cli.commands.<name>`` and exposes ``DESCRIPTION`` (with an
example), ``add_arguments(parser)`` and ``run(args) -> int``. Modules are imported only when
their command runs, so ``mocap --help`` stays fast (rerun and matplotlib are slow to import).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# name -> one-line help; the module mocap.cli.commands.<name> holds the rest.
COMMANDS: dict[str, str] = {
    "validate": "check a session directory against the input contract and summarise it",
    "simulate": "make a virtual capture session with known truth (and optional hidden effects)",
    "calibrate": "calibrate the camera rig from the wand and ground takes",
    "run": "process a session: calibration, reconstruction, analyses, figures, audit",
    "import": "vendors' exports (C3D, Motive CSV, QTM TSV, Vicon CSV) to a labeled session",
    "export": "labeled trajectories to C3D (markers, rate, mm, commands as analog channels)",
    "replay": "open a run's Rerun recording (session.rrd) in the viewer",
    "batch": "run many sessions in parallel on Dask (a local cluster or a scheduler)",
    "audit": "capture-quality audit: calibration, cameras, markers, rejections",
    "schedule": "identification battery of command files (rates, minor loops, DU pairs)",
    "design": "command files that realise a motion plan (A-E) from identified responses",
    "discrepancy": "where the face model and the measurement disagree: name the missing effect",
}


def _module(name: str):
    # "import" is a Python keyword: its module is mocap.cli.commands.import_
    return importlib.import_module(f"mocap.cli.commands.{name}_" if name == "import" else f"mocap.cli.commands.{name}")


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The top-level parser; only ``selected``'s module is imported (all when None)."""
    parser = argparse.ArgumentParser(
        prog="mocap",
        description="facemocap: facial motion capture, raw camera exports to a face model.",
        epilog="Run 'mocap COMMAND --help' for a command's options and an example.",
    )
    from mocap import __version__

    parser.add_argument("--version", action="version", version=f"facemocap {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_text in COMMANDS.items():
        if selected is not None and name != selected:
            sub.add_parser(name, help=help_text)
            continue
        module = _module(name)
        p = sub.add_parser(
            name,
            help=help_text,
            description=module.DESCRIPTION,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(p)
    return parser


def single_threaded_blas() -> None:
    """One BLAS thread per process unless the user set one (before numpy is imported).

    The heavy arithmetic is compiled (numba) or spread over processes (``--jobs``); the BLAS
    calls left are products of small matrices (the bundle adjustment's 78 x 78 Schur
    complement over thousands of frames), where OpenBLAS's threads gain nothing and, on a
    machine whose cores are busy (other jobs, our own worker processes), spin-wait: the
    bundle adjustment of a wand take with ghosts ran 47 s with the default threads and 25 s
    with one on a loaded 2-core machine. Dask's workers make the same choice
    (``distributed.nanny.pre-spawn-environ``). Spawned worker processes inherit it.
    """
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")


def main(argv: list[str] | None = None) -> int:
    # the command line draws figures into files: a non-interactive matplotlib backend, chosen
    # here (the library never picks one) and without importing matplotlib
    os.environ.setdefault("MPLBACKEND", "Agg")
    single_threaded_blas()
    argv = list(sys.argv[1:] if argv is None else argv)
    selected = next((a for a in argv if a in COMMANDS), None)
    parser = build_parser(selected)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    return int(_module(args.command).run(args) or 0)
