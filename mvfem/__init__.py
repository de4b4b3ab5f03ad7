"""mvfem: closure of heart valves with hyperelastic membranes in FEniCSx.

The package composes the physics in :mod:`mvfem.forms` (UFL only) and the geometry in
:mod:`mvfem.meshes` into runs driven by PETSc SNES.
"""

from __future__ import annotations

from mvfem.errors import InputError, SolverError
from mvfem.materials import ParameterSet, get_set, parameter_sets

__version__ = "0.1.0"

__all__ = ["InputError", "SolverError", "ParameterSet", "get_set", "parameter_sets", "__version__"]
