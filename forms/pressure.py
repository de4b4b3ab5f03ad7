"""Pressure loads on a membrane, as virtual work per unit reference area (UFL only)."""

from __future__ import annotations

import ufl

from .kinematics import Membrane, unit_normal

__all__ = ["follower_pressure", "dead_pressure"]


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
