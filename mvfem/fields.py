"""Cell-wise (DG0) values of UFL expressions, for outputs and checks."""

from __future__ import annotations

import numpy as np

__all__ = ["cell_function", "cell_values"]


def cell_function(expr, msh, shape: tuple[int, ...] = (), name: str | None = None):
    """Interpolate ``expr`` at the cell midpoints into a DG0 ``fem.Function`` of ``shape``.

    Exact for quantities that are constant on each cell (any function of a P1 membrane's
    kinematics on flat triangles).
    """
    from dolfinx import fem

    if shape == ():
        V = fem.FunctionSpace(msh, ("DG", 0))
    elif len(shape) == 1:
        V = fem.VectorFunctionSpace(msh, ("DG", 0), dim=shape[0])
    else:
        V = fem.TensorFunctionSpace(msh, ("DG", 0), shape=shape)
    f = fem.Function(V, name=name)
    f.interpolate(fem.Expression(expr, V.element.interpolation_points()))
    f.x.scatter_forward()
    return f


def cell_values(expr, msh, shape: tuple[int, ...] = ()) -> np.ndarray:
    """Values of ``expr`` on this rank's owned cells, array of shape ``(ncells, *shape)``."""
    f = cell_function(expr, msh, shape)
    n = msh.topology.index_map(msh.topology.dim).size_local
    size = int(np.prod(shape)) if shape else 1
    blocks = f.function_space.dofmap.list.array[:n]  # one DG0 block per cell, in cell order
    return f.x.array.reshape(-1, size)[blocks].reshape((n, *shape))
