"""mvfem: closure of heart valves with hyperelastic membranes in FEniCSx.

The package composes the physics in :mod:`mvfem.forms` (UFL only) and the geometry in
:mod:`mvfem.meshes` into runs driven by PETSc SNES.
"""

from __future__ import annotations

from mvfem.errors import InputError, SolverError
from mvfem.materials import ParameterSet, get_set, parameter_sets
from mvfem.scene import Scene, load_scene

__version__ = "0.1.0"

__all__ = ["InputError", "SolverError", "ParameterSet", "get_set", "parameter_sets", "Scene",
           "load_scene", "solve", "Result", "__version__"]

# solve() needs dolfinx; importing it lazily keeps `import mvfem.forms` free of dolfinx/PETSc
_LAZY = {"solve": "mvfem.run", "Result": "mvfem.run"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'mvfem' has no attribute {name!r}")
