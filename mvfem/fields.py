"""Cell-wise (DG0) values of UFL expressions, for outputs and checks.

Values are the midpoint values of each cell, computed by assembling ``(expr, w)`` against a DG0
test function with one-point (midpoint) quadrature and dividing by the cell area. This is exact
for quantities that are constant on a cell (any function of a P1 membrane's kinematics), and it
goes through form compilation, the same path as the solver's forms: FFCx 0.5 generates code that
does not compile for some ``fem.Expression`` that mix ``ufl.Jacobian`` with ``grad(u)``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["cell_function", "cell_values", "per_cell", "mean_deformed_radius"]


def _space(msh, shape):
    from dolfinx import fem

    if shape == ():
        return fem.FunctionSpace(msh, ("DG", 0))
    if len(shape) == 1:
        return fem.VectorFunctionSpace(msh, ("DG", 0), dim=shape[0])
    return fem.TensorFunctionSpace(msh, ("DG", 0), shape=shape)


def cell_function(expr, msh, shape: tuple[int, ...] = (), name: str | None = None):
    """A DG0 ``fem.Function`` of ``shape`` holding ``expr`` at each cell's midpoint."""
    import ufl
    from dolfinx import fem
    from dolfinx.fem import petsc as fpetsc
    from petsc4py import PETSc

    V = _space(msh, shape)
    w = ufl.TestFunction(V)
    dx = ufl.Measure("dx", domain=msh, metadata={"quadrature_degree": 1})
    value = fpetsc.assemble_vector(fem.form(ufl.inner(expr, w) * dx))
    one = ufl.as_tensor(np.ones(shape)) if shape else 1.0
    area = fpetsc.assemble_vector(fem.form(ufl.inner(one, w) * dx))
    f = fem.Function(V, name=name)
    for vec in (value, area):
        vec.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    # DG0 dofs belong to one cell each: no summation across ranks is needed
    n = value.getLocalSize()
    f.x.array[:n] = value.array_r / area.array_r
    f.x.scatter_forward()
    value.destroy()
    area.destroy()
    return f


def per_cell(f) -> np.ndarray:
    """The values of a DG0 function in local cell order (owned, then ghost cells).

    Returns an array of shape ``(ncells, *value_shape)``; a writable copy.
    """
    shape = f.ufl_shape
    size = int(np.prod(shape)) if shape else 1
    blocks = f.function_space.dofmap.list.array  # one DG0 block per cell, in cell order
    return f.x.array.reshape(-1, size)[blocks].reshape((len(blocks), *shape))


def cell_values(expr, msh, shape: tuple[int, ...] = ()) -> np.ndarray:
    """Values of ``expr`` on this rank's owned cells, array of shape ``(ncells, *shape)``."""
    n = msh.topology.index_map(msh.topology.dim).size_local
    return per_cell(cell_function(expr, msh, shape))[:n]


def mean_deformed_radius(u, centre=(0.0, 0.0, 0.0)) -> float:
    """Mean distance of the deformed nodes of a P1 displacement ``u`` from ``centre`` (collective)."""
    from mpi4py import MPI

    V = u.function_space
    n = V.dofmap.index_map.size_local
    x = V.tabulate_dof_coordinates()[:n] + u.x.array.reshape(-1, 3)[:n] - np.asarray(centre)
    comm = V.mesh.comm
    total = comm.allreduce(float(np.linalg.norm(x, axis=1).sum()), op=MPI.SUM)
    return total / comm.allreduce(n, op=MPI.SUM)
