"""Command-line pieces that the study scripts in ``scripts/`` share (``level_costs.py``,
``level_variants.py``, ``tolerance_error.py``, ``coaptation_trace.py``). Each may run under
``mpirun``: rank 0 speaks and writes, every rank returns the same exit code."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mpi4py import MPI


def add_demo_levels(parser: argparse.ArgumentParser) -> None:
    """``--refine``, ``--size`` and ``--pressures``: the demo's mesh refined into nested
    levels, closed at each pressure."""
    parser.add_argument("--refine", type=int, default=2, help="times the demo's mesh is refined")
    parser.add_argument("--size", type=float, default=2.0, help="the demo's mesh size, mm")
    parser.add_argument("--pressures", default="16", help="kPa, comma-separated")


def errors(prog: str):
    """``(root, error)``: whether this is rank 0, and ``error(msg)``, which prints ``prog:
    msg`` on stderr there and returns the exit code 2 (bad input) on every rank."""
    root = MPI.COMM_WORLD.rank == 0

    def error(msg: str) -> int:
        if root:
            print(f"{prog}: {msg}", file=sys.stderr)
        return 2
    return root, error


def existing_out(out: str | None) -> str | None:
    """The error of an ``--out`` that names an existing file (nothing a user wrote is
    overwritten), None otherwise; collective: rank 0 looks, every rank gets its answer."""
    root = MPI.COMM_WORLD.rank == 0
    if out is not None and MPI.COMM_WORLD.bcast(Path(out).exists() if root else None):
        return f"--out {out}: exists; choose another name"
    return None
