"""Finite-element patch test: a square membrane stretched through its boundary.

The boundary nodes of a tilted square follow the homogeneous biaxial deformation
``u = (F - I) X``; the interior nodes start perturbed in and out of the plane. The exact solution
of the discrete problem is the homogeneous state, whatever the triangulation, so after the PETSc
SNES solve every cell must carry the same stress, equal to the closed form of test_materials.py
(derived there by hand from W), and the interior must be flat again.
The boundary stretch is reached by load stepping from a small pre-stretch (LoadStepper).
"""

from __future__ import annotations

import numpy as np
import pytest
import ufl
from conftest import tilted_frame
from dolfinx import fem, mesh
from dolfinx.fem import petsc as _  # noqa: F401  (fem.petsc)
from test_materials import closed_form

from mvfem.fields import cell_values
from mvfem.forms import LAWS, cauchy_stress, membrane
from mvfem.meshes import square_patch
from mvfem.solver import LoadStepper, SNESProblem

CASES = [
    ("mny", {"c0": 399.0, "c1": 4.325, "c2": 1446.5}, (0.18, 0.12)),
    ("mny", {"c0": 2171.0, "c1": 2.19, "c2": 1408.8}, (0.15, 0.225)),  # CP08, off-biaxial
    ("holzapfel", {"c0": 52.0, "c1": 4.63, "c2": 22.6}, (0.2, 0.15)),
    ("svk", {"E": 4.0e5, "nu": 0.5}, (0.1, 0.15)),
    ("neo-hookean", {"mu": 5.0e3}, (0.4, 0.2)),
]


def _patch_solve(comm, law, params, strains, n=6, fibre_angle=0.6, seed=1):
    frame = tilted_frame()
    msh = square_patch(comm, n=n, size=10.0, frame=frame)
    V = fem.VectorFunctionSpace(msh, ("Lagrange", 1))
    u, v = fem.Function(V), ufl.TestFunction(V)
    a0v = np.cos(fibre_angle) * frame[:, 0] + np.sin(fibre_angle) * frame[:, 1]
    b0v = np.cross(frame[:, 2], a0v)
    consts = [fem.Constant(msh, float(params[k])) for k in params]
    m = membrane(u, fem.Constant(msh, a0v))
    W = LAWS[law](m, *consts)
    h0 = 0.85
    dx = ufl.dx(metadata={"quadrature_degree": 2})
    F = ufl.derivative(h0 * W * dx, u, v)

    def deformation(t):
        ep, eq = t * strains[0], t * strains[1]
        return np.eye(3) + ep * np.outer(a0v, a0v) + eq * np.outer(b0v, b0v)

    msh.topology.create_connectivity(1, 2)
    bfacets = mesh.exterior_facet_indices(msh.topology)
    bdofs = fem.locate_dofs_topological(V, 1, bfacets)
    u_bc = fem.Function(V)
    bc = fem.dirichletbc(u_bc, bdofs)

    def set_load(t):
        D = deformation(t) - np.eye(3)
        u_bc.interpolate(lambda x: D @ x)

    # absolute tolerance on the force scale stress x thickness x side (round-off ~1e-16 of it)
    stress = max(np.abs(closed_form(law, params, np.array(1 + strains[0]),
                                    np.array(1 + strains[1]))))
    problem = SNESProblem(F, u, [bc], prefix=f"patch_{law}_",
                          options={"snes_atol": 1e-11 * stress * h0 * 10.0, "snes_rtol": 1e-12})
    t0 = 0.25
    set_load(t0)
    D0 = deformation(t0) - np.eye(3)
    rng = np.random.default_rng(seed)
    u.interpolate(lambda x: D0 @ x + 0.1 * rng.uniform(-1, 1, size=x.shape))
    fem.petsc.set_bc(u.vector, [bc])  # boundary nodes exactly on the imposed stretch
    u.x.scatter_forward()

    def get_state():
        return u.x.array.copy()

    def set_state(a):
        u.x.array[:] = a
        u.x.scatter_forward()

    stepper = LoadStepper(set_load, problem.solve, get_state, set_state, first_step=0.25)
    reached, t = stepper.run(target=1.0, start=t0)
    sigma = cell_values(cauchy_stress(W, m), msh, (3, 3))
    F_exact = deformation(1.0)
    u_exact = fem.Function(V)
    u_exact.interpolate(lambda x: (F_exact - np.eye(3)) @ x)
    err = np.abs(u.x.array - u_exact.x.array).max()
    a = F_exact @ a0v
    b = F_exact @ b0v
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    problem.destroy()
    return reached, stepper, sigma, err, a, b


@pytest.mark.mpi
@pytest.mark.parametrize("law,params,strains", CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(CASES)])
def test_patch_uniform_stress(comm, law, params, strains):
    reached, stepper, sigma, err, a, b = _patch_solve(comm, law, params, strains)
    assert reached, stepper.history
    assert stepper.newton_iterations > 0  # a real solve, not the initial guess
    assert comm.allreduce(err, op=max) < 1e-8  # homogeneous: the interior is back in place
    cp, cq = closed_form(law, params, np.array(1 + strains[0]), np.array(1 + strains[1]))
    sp = np.einsum("i,cij,j->c", a, sigma, a)
    sq = np.einsum("i,cij,j->c", b, sigma, b)
    scale = max(abs(cp), abs(cq))
    for s, c in ((sp, cp), (sq, cq)):
        worst = comm.allreduce(np.abs(s - c).max() if len(s) else 0.0, op=max)
        assert worst < 1e-7 * scale, (s, c)
