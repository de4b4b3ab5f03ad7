"""A small bending stiffness across the edges of a membrane mesh (discrete thin shell).

A membrane has no bending stiffness, so wherever it is compressed (a funnel-shaped open valve
pushed shut) its tangent is indefinite and Newton chases mesh-scale wrinkles. Leaflets are thin
shells; a hinge energy per interior edge in the manner of discrete shells (Grinspun et al.
2003) restores the bending stiffness ``D = E_b h^3 / 12`` that suppresses those wrinkles:

.. math:: \\Pi_b = \\int_{\\mathcal E} \\frac{D}{\\bar h_e}\\,
          \\bigl(1 - \\cos(\\theta - \\theta_0)\\bigr)\\, ds

with ``theta`` the dihedral angle between the deformed unit normals of the two cells at an
edge (signed about the deformed edge tangent), ``theta_0`` the same in the open reference state
(stress free) and ``h_e`` the mean diameter of the two cells; for small angles this is
``(D/2) kappa^2`` per area with curvature ``kappa = (theta - theta_0)/h_e``. ``cos`` of the
difference is expanded in the sines and cosines of the two angles, which are invariant under
rigid rotations, so no ``atan2`` is needed.

On P1 meshes the model uses the same energy as a compiled point term (:mod:`mvfem.hinges`),
checked against this form in ``tests/test_valve_terms.py``: differentiated twice by UFL over
interior facets it took 14 of the 20-27 ms of one tangent assembly of the demo valve.
"""

from __future__ import annotations

import ufl

__all__ = ["hinge_energy"]


def _unit(v):
    return v / ufl.sqrt(ufl.dot(v, v))


def _normal(J):
    return _unit(ufl.cross(J[:, 0], J[:, 1]))


def _angle_cos_sin(n_p, n_m, t):
    """cos and sin of the angle from unit normal ``n_p`` to ``n_m`` about unit axis ``t``."""
    return ufl.dot(n_p, n_m), ufl.dot(ufl.cross(n_p, n_m), t)


def hinge_energy(u, D) -> ufl.core.expr.Expr:
    """Integrand (over interior facets, ``dS``) of the hinge bending energy of displacement
    ``u``; ``D`` is the bending stiffness (Pa mm^3), a Constant or an expression."""
    msh = u.ufl_domain()
    J0 = ufl.Jacobian(msh)
    F = ufl.Identity(3) + ufl.grad(u)
    N_p, N_m = _normal(J0("+")), _normal(J0("-"))
    # edge tangent: the reference one (normal x outward conormal of the '+' cell), mapped by
    # the deformation, which is continuous across the edge
    t0 = ufl.cross(N_p, ufl.FacetNormal(msh)("+"))
    c0, s0 = _angle_cos_sin(N_p, N_m, t0)
    c, s = _angle_cos_sin(_normal(F("+") * J0("+")), _normal(F("-") * J0("-")),
                          _unit(F("+") * t0))
    h = 0.5 * (ufl.CellDiameter(msh)("+") + ufl.CellDiameter(msh)("-"))
    return D / h * (1 - (c * c0 + s * s0))
