"""The source paper's Figs 1-2: canonical biaxial curves of every parameter set.

Run as ``mpirun -n 2 python scripts/biaxial_figures.py [OUT]`` (or plain ``python``); rank 0
evaluates the curves (they are a few thousand point evaluations, no mesh to share) and writes
``OUT/biaxial.csv`` and one figure per leaflet (default OUT: results/paper_figs_1_2).
"""

from __future__ import annotations

import sys

import dolfinx  # noqa: F401  (initialises PETSc, which is collective: every rank imports it)
from mpi4py import MPI

from mvfem.biaxial import run_biaxial
from mvfem.outputs import prepare_out


def main(out: str = "results/paper_figs_1_2") -> None:
    comm = MPI.COMM_WORLD
    if comm.rank == 0:
        res = run_biaxial(prepare_out(out))
        for f in res["files"]:
            print("wrote", f)
    comm.Barrier()


if __name__ == "__main__":
    main(*sys.argv[1:2])
