"""mvfem: closure of heart valves with hyperelastic membranes in FEniCSx.

The package composes the physics in :mod:`mvfem.forms` (UFL only) and the geometry in
:mod:`mvfem.meshes` into runs driven by PETSc SNES.
"""

from __future__ import annotations

import os


def _passive_openmp() -> None:
    """Idle OpenMP threads sleep instead of spinning (``OMP_WAIT_POLICY=passive``) unless the
    environment says otherwise (``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` set). The OpenMP
    runtime reads it once, when it loads, which PETSc's import does (its libraries link
    libgomp); hence here, before any of mvfem's modules imports PETSc. On 2 cores a run alone
    is as fast either way (the demo refined twice 36.3-36.9 s against 36.4-37.6 s), but two
    runs side by side, each on two kernel threads, spun against each other: the demo took
    0.066-0.076 s a step against 0.031-0.032 s passive (README "Threads that wait, asleep",
    session 36).
    A script that imports dolfinx or petsc4py before mvfem keeps the runtime's default."""
    if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
        os.environ["OMP_WAIT_POLICY"] = "passive"


_passive_openmp()

from mvfem.errors import InputError, Interrupted, SolverError
from mvfem.materials import ParameterSet, get_set, parameter_sets
from mvfem.scene import Scene, load_scene

__version__ = "0.1.0"

__all__ = ["InputError", "SolverError", "Interrupted", "ParameterSet", "get_set",
           "parameter_sets", "Scene", "load_scene", "solve", "Result", "__version__"]

# solve() needs dolfinx; importing it lazily keeps `import mvfem.forms` free of dolfinx/PETSc
_LAZY = {"solve": "mvfem.run", "Result": "mvfem.run"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'mvfem' has no attribute {name!r}")
