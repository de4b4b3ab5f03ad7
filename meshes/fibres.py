"""Radial and circumferential directions on any leaflet surface, from a Laplace problem.

On a valve the radial direction runs from the annulus to the free edge and the fibres run
circumferentially, parallel to the annulus. Neither needs a parametrisation: with ``phi`` the
solution of the surface Laplace problem

.. math:: \\Delta_\\Gamma \\phi = 0,\\quad \\phi = 0 \\text{ on the annulus},\\quad
          \\phi = 1 \\text{ on the free edge}

the radial direction is ``grad phi / |grad phi|`` (tangent to the surface by construction) and
the circumferential one is ``n x radial``. This works on generated and imported valves alike,
with any number of leaflets.
"""

from __future__ import annotations

import numpy as np

__all__ = ["laplace_coordinate", "boundary_split", "radial_circumferential"]


def boundary_split(msh, annulus_vertices: np.ndarray):
    """(annulus facets, free-edge facets) of a surface: exterior edges with both ends on the
    annulus, and the other exterior edges. ``annulus_vertices``: local vertex indices."""
    from dolfinx import mesh as dmesh

    tdim = msh.topology.dim
    msh.topology.create_connectivity(tdim - 1, tdim)
    msh.topology.create_connectivity(tdim - 1, 0)
    exterior = dmesh.exterior_facet_indices(msh.topology)
    f2v = msh.topology.connectivity(tdim - 1, 0)
    on = np.zeros(msh.topology.index_map(0).size_local + msh.topology.index_map(0).num_ghosts,
                  dtype=bool)
    on[np.asarray(annulus_vertices, dtype=np.int64)] = True
    both = np.array([on[f2v.links(f)].all() for f in exterior], dtype=bool)
    return exterior[both].astype(np.int32), exterior[~both].astype(np.int32)


def laplace_coordinate(msh, annulus_facets: np.ndarray, free_edge_facets: np.ndarray):
    """The P1 function ``phi`` (0 on the annulus, 1 on the free edge, harmonic between).

    Raises:
        ValueError: when the annulus or the free edge is empty (on every rank).
    """
    import ufl
    from dolfinx import fem
    from dolfinx.fem import petsc as fpetsc
    from mpi4py import MPI
    from petsc4py import PETSc

    comm = msh.comm
    counts = [comm.allreduce(len(f), op=MPI.SUM) for f in (annulus_facets, free_edge_facets)]
    if counts[0] == 0:
        raise ValueError("the surface has no annulus edges")
    if counts[1] == 0:
        raise ValueError("the surface has no free edge (every boundary edge is on the annulus)")
    V = fem.FunctionSpace(msh, ("Lagrange", 1))
    phi, psi = ufl.TrialFunction(V), ufl.TestFunction(V)
    tdim = msh.topology.dim
    zero = fem.locate_dofs_topological(V, tdim - 1, annulus_facets)
    one = fem.locate_dofs_topological(V, tdim - 1, free_edge_facets)
    one = np.setdiff1d(one, zero)  # the commissures belong to the annulus
    bcs = [fem.dirichletbc(PETSc.ScalarType(0.0), zero, V),
           fem.dirichletbc(PETSc.ScalarType(1.0), one, V)]
    a = ufl.inner(ufl.grad(phi), ufl.grad(psi)) * ufl.dx
    L = fem.Constant(msh, PETSc.ScalarType(0.0)) * psi * ufl.dx
    problem = fpetsc.LinearProblem(a, L, bcs=bcs, petsc_options={
        "ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"})
    out = problem.solve()
    out.name = "radial_coordinate"
    return out


def radial_circumferential(phi, n0):
    """UFL unit radial (``grad phi`` normalised) and circumferential (``n0 x radial``) fields."""
    import ufl

    g = ufl.grad(phi)
    radial = g / ufl.sqrt(ufl.dot(g, g))
    return radial, ufl.cross(n0, radial)
