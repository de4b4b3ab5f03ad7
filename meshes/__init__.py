"""Geometry of mvfem: mesh generators, import/export, labels and surface directions.

Knows geometry only; no physics.
"""

from __future__ import annotations

from .generators import SurfaceMesh, disk, sphere, square, tube
from .io import RawSurface, mesh_from_arrays, read_points, read_surface, to_dolfinx, write_surface
from .octasphere import octasphere
from .patch import square_patch
from .valve import ValveMesh, valve, write_valve

__all__ = ["square_patch", "SurfaceMesh", "disk", "square", "sphere", "tube", "RawSurface",
           "read_surface", "read_points", "write_surface", "to_dolfinx", "mesh_from_arrays",
           "octasphere", "ValveMesh", "valve", "write_valve"]
