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

__all__ = ["svk", "may_newman_yin", "holzapfel", "neo_hookean", "LAWS", "law_parameters", "uses_fibre",
           "is_exponential", "exponent"]


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


def _exp(Q, max_exponent):
    """``exp(Q)``, or with ``max_exponent`` its C1 continuation beyond that exponent.

    Beyond ``Qc`` the exponential is continued by its tangent line ``e^Qc (1 + Q - Qc)``: the
    energy keeps growing (an over-stretched element still resists; a flat cap would let Newton
    park elements on a plateau), yet stays finite.
    """
    if max_exponent is None:
        return ufl.exp(Q)
    Qc = max_exponent
    inside = ufl.exp(ufl.min_value(Q, Qc))  # never overflows, even where not selected
    return ufl.conditional(ufl.lt(Q, Qc), inside, ufl.exp(Qc) * (1 + Q - Qc))


def _fibre(x, tension_only: bool):
    """The fibre strain ``x`` (``lambda - 1`` or ``I4 - 1``), or with ``tension_only`` its
    positive part: fibres that buckle instead of bearing compression."""
    return ufl.max_value(x, 0.0) if tension_only else x


def may_newman_yin(m: Membrane, c0, c1, c2, max_exponent=None,
                   tension_only: bool = False) -> ufl.core.expr.Expr:
    """May-Newman-Yin transversely isotropic exponential law.

    .. math::
        W = c_0\\left[\\exp\\left(c_1 (I_1 - 3)^2 + c_2 (\\lambda - 1)^4\\right) - 1\\right]

    with ``lambda`` the fibre stretch (``c0`` in Pa). With ``max_exponent`` the exponent is
    continued linearly beyond that value (see :func:`_exp`), so that a wild Newton iterate gives
    a huge but finite residual instead of an overflow; states that pass it are far outside the
    law's range and are flagged by the solver. With ``tension_only`` the fibre term is
    ``c2 max(lambda - 1, 0)^4`` (three times differentiable at ``lambda = 1``): the paper's law
    resists compression along the fibres as steeply as stretch, which a ring that shrinks the
    annulus turns into exponents of 40-150 (README, "Repairs").
    """
    Q = c1 * (m.I1 - 3) ** 2 + c2 * _fibre(m.fibre_stretch - 1, tension_only) ** 4
    return c0 * (_exp(Q, max_exponent) - 1)


def holzapfel(m: Membrane, c0, c1, c2, max_exponent=None,
              tension_only: bool = False) -> ufl.core.expr.Expr:
    """Holzapfel-type exponential law (as used for mitral leaflets by Prot et al.).

    .. math::
        W = c_0\\left[\\exp\\left(c_1 (I_1 - 3)^2 + c_2 (\\lambda^2 - 1)^2\\right) - 1\\right]

    ``max_exponent`` as for :func:`may_newman_yin`; ``tension_only``: ``c2 max(I4 - 1, 0)^2``
    (once differentiable at ``I4 = 1``), the usual switch of fibre-reinforced laws.
    """
    Q = c1 * (m.I1 - 3) ** 2 + c2 * _fibre(m.I4 - 1, tension_only) ** 2
    return c0 * (_exp(Q, max_exponent) - 1)


def exponent(law: str, m: Membrane, c0, c1, c2,
             tension_only: bool = False) -> ufl.core.expr.Expr:
    """The exponent Q of an exponential law (to check a state against the cap)."""
    if law == "mny":
        return c1 * (m.I1 - 3) ** 2 + c2 * _fibre(m.fibre_stretch - 1, tension_only) ** 4
    if law == "holzapfel":
        return c1 * (m.I1 - 3) ** 2 + c2 * _fibre(m.I4 - 1, tension_only) ** 2
    raise ValueError(f"{law!r} has no exponent")


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


def is_exponential(law: str) -> bool:
    """Whether ``law`` is a Fung-type exponential law (takes ``max_exponent``)."""
    return law in ("mny", "holzapfel")


def uses_fibre(law: str) -> bool:
    """Whether ``law`` needs a fibre direction."""
    return law in ("mny", "holzapfel")
