"""Strain-energy laws of leaflet tissue, per unit reference volume (Pa).

Each law is a plain function of a :class:`~mvfem.forms.kinematics.Membrane` and its parameters
(numbers, ``fem.Constant`` or any UFL expression) and returns the energy density ``W``.
Stresses follow by differentiation (:func:`~mvfem.forms.kinematics.cauchy_stress`), never by
hand; the energy per reference area of a membrane of thickness ``h0`` is ``h0 * W``.

This module imports ufl only.
"""

from __future__ import annotations

from typing import Callable

import ufl

from .kinematics import Membrane

__all__ = ["svk", "may_newman_yin", "holzapfel", "neo_hookean", "LAWS", "law_parameters", "uses_fibre"]


def svk(m: Membrane, E, nu) -> ufl.core.expr.Expr:
    """St Venant-Kirchhoff in plane-stress form.

    .. math::
        W = \\frac{E}{2(1-\\nu^2)} \\left[(1-\\nu)\\operatorname{tr}(\\mathbf E^2)
            + \\nu (\\operatorname{tr}\\mathbf E)^2\\right],
        \\quad S = \\frac{E}{1-\\nu^2}\\left[(1-\\nu)\\mathbf E + \\nu\\operatorname{tr}(\\mathbf E) I\\right]

    with the in-plane Green strain ``E`` (mixed components). Unlike the 3-D form this stays
    regular at nu = 1/2.
    """
    Em = m.green_strain
    return E / (2 * (1 - nu**2)) * ((1 - nu) * ufl.tr(Em * Em) + nu * ufl.tr(Em) ** 2)


def may_newman_yin(m: Membrane, c0, c1, c2) -> ufl.core.expr.Expr:
    """May-Newman-Yin transversely isotropic exponential law.

    .. math::
        W = c_0\\left[\\exp\\left(c_1 (I_1 - 3)^2 + c_2 (\\lambda - 1)^4\\right) - 1\\right]

    with ``lambda`` the fibre stretch (``c0`` in Pa).
    """
    return c0 * (ufl.exp(c1 * (m.I1 - 3) ** 2 + c2 * (m.fibre_stretch - 1) ** 4) - 1)


def holzapfel(m: Membrane, c0, c1, c2) -> ufl.core.expr.Expr:
    """Holzapfel-type exponential law (as used for mitral leaflets by Prot et al.).

    .. math::
        W = c_0\\left[\\exp\\left(c_1 (I_1 - 3)^2 + c_2 (\\lambda^2 - 1)^2\\right) - 1\\right]
    """
    return c0 * (ufl.exp(c1 * (m.I1 - 3) ** 2 + c2 * (m.I4 - 1) ** 2) - 1)


def neo_hookean(m: Membrane, mu) -> ufl.core.expr.Expr:
    """Incompressible neo-Hookean law, for verification.

    .. math::
        W = \\frac{\\mu}{2}(I_1 - 3)
    """
    return mu / 2 * (m.I1 - 3)


#: law name (as in scene files) -> energy function
LAWS: dict[str, Callable[..., ufl.core.expr.Expr]] = {
    "svk": svk,
    "mny": may_newman_yin,
    "holzapfel": holzapfel,
    "neo-hookean": neo_hookean,
}

_PARAMETERS = {
    "svk": ("E", "nu"),
    "mny": ("c0", "c1", "c2"),
    "holzapfel": ("c0", "c1", "c2"),
    "neo-hookean": ("mu",),
}


def law_parameters(law: str) -> tuple[str, ...]:
    """Names of the parameters of ``law``, in the order the energy function takes them."""
    return _PARAMETERS[law]


def uses_fibre(law: str) -> bool:
    """Whether ``law`` needs a fibre direction."""
    return law in ("mny", "holzapfel")
