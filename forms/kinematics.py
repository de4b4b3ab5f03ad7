"""Kinematics of a thin membrane on a 2-manifold embedded in 3-D.

Everything is expressed in the convected (curvilinear) basis of the reference surface, so the
same code serves a flat patch, a sphere and a valve leaflet:

.. math::
    J_0 = \\partial X / \\partial \\xi \\ (3\\times 2), \\quad G = J_0^T J_0, \\quad
    J = (I + \\nabla u) J_0, \\quad g = J^T J.

``G^{-1} g`` is the in-plane right Cauchy-Green tensor (mixed components). For an incompressible
membrane in plane stress the through-thickness stretch follows from volume conservation,
:math:`C_{33} = \\det G / \\det g`, and :math:`I_1 = \\operatorname{tr}(G^{-1} g) + C_{33}`.
A unit tangent reference fibre :math:`a_0` has contravariant components
:math:`A = G^{-1} J_0^T a_0` and stretch :math:`\\lambda^2 = A\\cdot g A / A \\cdot G A`.

``g`` is a ``ufl.variable`` so that laws can be differentiated with respect to it:
the contravariant second Piola-Kirchhoff stress is :math:`S = 2\\,\\partial W/\\partial g` and the
Cauchy stress of the incompressible membrane is :math:`\\sigma = J S J^T` (3x3, tangent to the
deformed surface, :math:`\\sigma_{33} = 0`).

This module imports ufl only.
"""

from __future__ import annotations

from dataclasses import dataclass

import ufl

__all__ = [
    "Membrane",
    "membrane",
    "surface_metric",
    "deformed_tangents",
    "membrane_c33",
    "first_invariant",
    "fibre_components",
    "fibre_stretch_squared",
    "green_strain",
    "second_piola",
    "cauchy_stress",
    "unit_normal",
]


def surface_metric(J0: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """Covariant metric of a surface with tangent basis ``J0`` (3x2): ``J0^T J0``."""
    return J0.T * J0


def deformed_tangents(J0: ufl.core.expr.Expr, u: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """Deformed tangent basis ``(I + grad u) J0`` (3x2) for a displacement ``u`` on the surface."""
    return J0 + ufl.grad(u) * J0


def membrane_c33(G: ufl.core.expr.Expr, g: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """Through-thickness C33 of an incompressible membrane, ``det G / det g``."""
    return ufl.det(G) / ufl.det(g)


def first_invariant(G: ufl.core.expr.Expr, g: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """I1 of the 3-D right Cauchy-Green tensor of an incompressible membrane."""
    return ufl.tr(ufl.inv(G) * g) + membrane_c33(G, g)


def fibre_components(G: ufl.core.expr.Expr, J0: ufl.core.expr.Expr,
                     a0: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """Contravariant components ``A = G^-1 J0^T a0`` of a tangent reference direction ``a0``.

    A vector ``a0`` that is not exactly tangent is replaced by its tangential projection.
    """
    return ufl.inv(G) * J0.T * a0


def fibre_stretch_squared(A: ufl.core.expr.Expr, G: ufl.core.expr.Expr,
                          g: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """Squared stretch ``I4 = A.gA / A.GA`` of the direction with contravariant components A."""
    return ufl.dot(A, g * A) / ufl.dot(A, G * A)


def green_strain(G: ufl.core.expr.Expr, g: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """Green-Lagrange membrane strain in mixed components, ``G^-1 (g - G) / 2``."""
    return ufl.inv(G) * (g - G) / 2


def unit_normal(J: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """Unit normal ``j1 x j2 / |j1 x j2|`` of a surface with tangent basis ``J`` (3x2)."""
    n = ufl.cross(J[:, 0], J[:, 1])
    return n / ufl.sqrt(ufl.dot(n, n))


@dataclass(frozen=True)
class Membrane:
    """Kinematic quantities of one membrane state (all UFL expressions).

    Attributes:
        J0: reference tangent basis (3x2).
        J: deformed tangent basis (3x2).
        G: reference metric (2x2).
        g: deformed metric (2x2), a ``ufl.variable`` for differentiation.
        C33: through-thickness right Cauchy-Green component (incompressible).
        I1: first invariant of the 3-D right Cauchy-Green tensor.
        A: contravariant components of the reference fibre, or None.
        I4: squared fibre stretch, or None.
    """

    J0: ufl.core.expr.Expr
    J: ufl.core.expr.Expr
    G: ufl.core.expr.Expr
    g: ufl.core.expr.Expr
    C33: ufl.core.expr.Expr
    I1: ufl.core.expr.Expr
    A: ufl.core.expr.Expr | None = None
    I4: ufl.core.expr.Expr | None = None

    @property
    def fibre_stretch(self) -> ufl.core.expr.Expr:
        """Stretch of the reference fibre, sqrt(I4)."""
        if self.I4 is None:
            raise ValueError("this membrane has no fibre direction")
        return ufl.sqrt(self.I4)

    @property
    def green_strain(self) -> ufl.core.expr.Expr:
        """Green-Lagrange strain, mixed components (2x2)."""
        return green_strain(self.G, self.g)


def membrane(u: ufl.core.expr.Expr, a0: ufl.core.expr.Expr | None = None,
             domain: ufl.AbstractDomain | None = None) -> Membrane:
    """Membrane kinematics of the displacement ``u`` on its (surface) mesh.

    Args:
        u: displacement, a vector field with 3 components on a surface mesh (tdim 2, gdim 3).
        a0: reference fibre direction (unit, tangent), a vector expression; optional.
        domain: the mesh; taken from ``u`` when omitted.

    Returns:
        The :class:`Membrane` with ``g`` wrapped as a ``ufl.variable``.
    """
    if domain is None:
        domain = ufl.domain.extract_unique_domain(u)
    J0 = ufl.Jacobian(domain)
    G = surface_metric(J0)
    J = deformed_tangents(J0, u)
    g = ufl.variable(J.T * J)
    A = I4 = None
    if a0 is not None:
        A = fibre_components(G, J0, a0)
        I4 = fibre_stretch_squared(A, G, g)
    return Membrane(J0=J0, J=J, G=G, g=g, C33=membrane_c33(G, g), I1=first_invariant(G, g),
                    A=A, I4=I4)


def second_piola(W: ufl.core.expr.Expr, m: Membrane) -> ufl.core.expr.Expr:
    """Contravariant second Piola-Kirchhoff stress ``S = 2 dW/dg`` (2x2)."""
    return 2 * ufl.diff(W, m.g)


def cauchy_stress(W: ufl.core.expr.Expr, m: Membrane) -> ufl.core.expr.Expr:
    """Cauchy stress of the incompressible membrane, ``J S J^T`` (3x3, sigma33 = 0)."""
    return m.J * second_piola(W, m) * m.J.T
