"""Pressure loads on a membrane, as virtual work per unit reference area (UFL only)."""

from __future__ import annotations

import ufl

from .kinematics import Membrane, unit_normal

__all__ = ["follower_pressure", "dead_pressure", "follower_potential", "dead_potential"]


def follower_pressure(p, m: Membrane, v) -> ufl.core.expr.Expr:
    """Virtual work of a pressure ``p`` along the deformed normal, per reference area.

    .. math::
        \\delta W = p\\, \\mathbf n \\cdot \\delta\\mathbf u \\, da
                  = p\\, (\\mathbf j_1 \\times \\mathbf j_2) \\cdot \\delta\\mathbf u
                    \\, d\\xi = p\\, \\frac{(\\mathbf j_1 \\times \\mathbf j_2)
                    \\cdot \\delta\\mathbf u}{\\sqrt{\\det G}} \\, dA

    Positive ``p`` pushes along ``j1 x j2``, the normal given by the cell orientation.
    """
    return p * ufl.dot(ufl.cross(m.J[:, 0], m.J[:, 1]), v) / ufl.sqrt(ufl.det(m.G))


def dead_pressure(p, m: Membrane, v) -> ufl.core.expr.Expr:
    """Virtual work of a pressure ``p`` along the fixed reference normal, per reference area."""
    return p * ufl.dot(unit_normal(m.J0), v)


def follower_potential(p, m: Membrane, x) -> ufl.core.expr.Expr:
    """Potential of :func:`follower_pressure` per reference area, ``-p`` x the volume swept
    toward the atrium, with ``x`` the deformed position:

    .. math:: \\Pi_p = -\\frac{p}{3}\\, \\mathbf x \\cdot (\\mathbf j_1 \\times \\mathbf j_2)
              \\, d\\xi

    Its variation is ``-p n . du da`` wherever the boundary is held (a clamped annulus): the
    boundary term of an open surface vanishes with ``du`` there. A merit function for the
    solver, not part of the residual.
    """
    return -p / 3 * ufl.dot(x, ufl.cross(m.J[:, 0], m.J[:, 1])) / ufl.sqrt(ufl.det(m.G))


def dead_potential(p, m: Membrane, u) -> ufl.core.expr.Expr:
    """Potential of :func:`dead_pressure` per reference area, ``-p N . u``."""
    return -p * ufl.dot(unit_normal(m.J0), u)
