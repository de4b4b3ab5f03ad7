"""Independent reference solutions for verifying the membrane solver (numpy and scipy only).

Nothing here imports dolfinx or UFL: each result comes from a classical membrane theory solved
by ODE shooting, power series or closed form, so that finite element runs can be checked
against it. Units: mm and Pa (any consistent set works; lengths and stresses scale out).

Three families:

- :func:`foppl_hencky`: clamped flat circular linear-elastic membrane under small uniform
  pressure (Föppl membrane equations, Hencky's problem), by shooting and, independently, by
  power series.
- :func:`axisymmetric_inflation`: large inflation of a clamped flat circular incompressible
  hyperelastic membrane under follower pressure, by shooting on the pole stretch.
- :func:`sphere_inflation`, :func:`cylinder_inflation` and their inverses: closed membranes
  under uniform stretch (Laplace's law).

A membrane law is given to the last two families as a callable ``sigma(l1, l2) -> (s1, s2)``
returning the principal Cauchy stresses (Pa) of an incompressible membrane in plane stress
(``sigma33 = 0``) at principal stretches ``l1, l2`` (thickness stretch ``1/(l1 l2)``);
:func:`neo_hookean`, :func:`may_newman_yin` and :func:`holzapfel` build them.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq, minimize_scalar

__all__ = [
    "StressLaw",
    "FopplHencky",
    "foppl_hencky",
    "neo_hookean",
    "may_newman_yin",
    "holzapfel",
    "Inflation",
    "axisymmetric_inflation",
    "inflation_at_pole_stretch",
    "inflation_limit_point",
    "sphere_inflation",
    "sphere_stretch",
    "TubeInflation",
    "cylinder_inflation",
    "cylinder_stretch",
]

#: principal Cauchy stresses (s1, s2) of an incompressible membrane at stretches (l1, l2), Pa
StressLaw = Callable[[float, float], "tuple[float, float]"]


# --------------------------------------------------------------------------------------------
# Föppl-Hencky: clamped circular linear-elastic membrane, small uniform pressure
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FopplHencky:
    """Hencky's solution of the Föppl membrane equations for one Poisson ratio.

    With ``K = (E h p^2 a^2)^(1/3)`` the radial stress resultant is ``N_r = K S(rho)``,
    ``rho = r/a``, where ``S`` solves the dimensionless problem of :func:`foppl_hencky`.

    Attributes:
        nu: Poisson ratio.
        C: centre deflection coefficient, ``w0 = C a (p a / (E h))^(1/3)``.
        D: centre stress coefficient, ``sigma_0 = D (E p^2 a^2 / h^2)^(1/3)`` (equibiaxial).
        edge_stress: radial stress coefficient at the clamp, same scaling as ``D``.
        method: "shooting" or "series", the route the numbers came from.
    """

    nu: float
    C: float
    D: float
    edge_stress: float
    method: str
    #: rho -> (S, dS/drho, I) with I(rho) = int_0^rho t/S(t) dt; rho in [0, 1]
    profile: Callable[[np.ndarray], "tuple[np.ndarray, np.ndarray, np.ndarray]"] = field(
        repr=False, compare=False)

    @staticmethod
    def _scale(a: float, h: float, E: float, p: float) -> float:
        return (E * h * p * p * a * a) ** (1.0 / 3.0)

    def centre_deflection(self, a: float, h: float, E: float, p: float) -> float:
        """Deflection at the centre, ``C a (p a / (E h))^(1/3)`` (units of ``a``).

        Args:
            a: membrane radius (mm).
            h: thickness (mm).
            E: Young's modulus (Pa).
            p: pressure (Pa).

        The other methods take the same arguments after ``r`` (radii, array-like) and return
        arrays.
        """
        return self.C * a * (p * a / (E * h)) ** (1.0 / 3.0)

    def centre_stress(self, a: float, h: float, E: float, p: float) -> float:
        """Equibiaxial stress at the centre, ``D (E p^2 a^2 / h^2)^(1/3)``."""
        return self.D * (E * p * p * a * a / (h * h)) ** (1.0 / 3.0)

    def deflection(self, r, a: float, h: float, E: float, p: float) -> np.ndarray:
        """Deflection ``w(r)``: ``w' = -p r / (2 N_r)`` integrated from the clamp ``w(a) = 0``."""
        rho = np.asarray(r, dtype=float) / a
        _, _, I_rho = self.profile(rho)
        _, _, I_one = self.profile(np.array([1.0]))
        return p * a * a / (2.0 * self._scale(a, h, E, p)) * (I_one[0] - I_rho)

    def radial_stress(self, r, a: float, h: float, E: float, p: float) -> np.ndarray:
        """Radial Cauchy stress ``N_r / h`` at radius ``r``."""
        S, _, _ = self.profile(np.asarray(r, dtype=float) / a)
        return self._scale(a, h, E, p) * S / h

    def hoop_stress(self, r, a: float, h: float, E: float, p: float) -> np.ndarray:
        """Hoop stress ``N_theta / h`` with ``N_theta = d(r N_r)/dr``."""
        rho = np.asarray(r, dtype=float) / a
        S, dS, _ = self.profile(rho)
        return self._scale(a, h, E, p) * (S + rho * dS) / h

    def radial_displacement(self, r, a: float, h: float, E: float, p: float) -> np.ndarray:
        """In-plane displacement ``u = r eps_theta = r (N_theta - nu N_r) / (E h)``."""
        rho = np.asarray(r, dtype=float) / a
        S, dS, _ = self.profile(rho)
        return rho * a * self._scale(a, h, E, p) * ((1.0 - self.nu) * S + rho * dS) / (E * h)


def _foppl_rhs(rho: float, y: np.ndarray) -> list[float]:
    S, dS, _ = y
    if rho == 0.0:  # regular centre: S'(0) = 0, S''(0) (1 + 3) = -1/(8 S^2)
        return [dS, -1.0 / (32.0 * S * S), 0.0]
    return [dS, -1.0 / (8.0 * S * S) - 3.0 * dS / rho, rho / S]


def _foppl_collapse(rho: float, y: np.ndarray) -> float:
    return y[0] - 1e-3


_foppl_collapse.terminal = True


def _foppl_integrate(s0: float):
    return solve_ivp(_foppl_rhs, (0.0, 1.0), [s0, 0.0, 0.0], method="DOP853", rtol=1e-12,
                     atol=1e-14, dense_output=True, events=_foppl_collapse)


def _foppl_edge_residual(s0: float, nu: float) -> float:
    sol = _foppl_integrate(s0)
    if sol.status != 0:  # S fell to ~0 before the edge: far too little centre stress
        return -1.0
    S, dS, _ = sol.y[:, -1]
    return (1.0 - nu) * S + dS


def _foppl_by_shooting(nu: float) -> FopplHencky:
    s0 = brentq(_foppl_edge_residual, 0.05, 5.0, args=(nu,), xtol=1e-15, rtol=1e-14)
    sol = _foppl_integrate(s0)

    def profile(rho):
        rho = np.clip(np.atleast_1d(np.asarray(rho, dtype=float)), 0.0, 1.0)
        S, dS, I = sol.sol(rho)
        return S, dS, I

    S1 = sol.y[0, -1]
    return FopplHencky(nu=nu, C=0.5 * sol.y[2, -1], D=s0, edge_stress=S1, method="shooting",
                       profile=profile)


def _foppl_series_coefficients(b0: float, nterms: int) -> np.ndarray:
    """Coefficients ``b_n`` of ``S = sum b_n x^n``, ``x = rho^2``, with ``S(0) = b0``.

    ``S'' + 3 S'/rho = sum 4 n (n+1) b_n x^(n-1) =: sum L_m x^m`` and ``S^2 (S'' + 3 S'/rho)
    = -1/8``; with ``c = b * b`` (Cauchy product) this gives, order by order in ``x``,
    ``c_0 L_m = -delta_m0 / 8 - sum_{k=1..m} c_k L_(m-k)``, ``b_(m+1) = L_m / (4 (m+1)(m+2))``.
    """
    b = np.zeros(nterms)
    c = np.zeros(nterms)
    L = np.zeros(nterms)
    b[0] = b0
    c[0] = b0 * b0
    for m in range(nterms - 1):
        s = (-0.125 if m == 0 else 0.0) - float(np.dot(c[1:m + 1], L[m - 1::-1][:m]))
        L[m] = s / c[0]
        b[m + 1] = L[m] / (4.0 * (m + 1) * (m + 2))
        c[m + 1] = float(np.dot(b[:m + 2], b[m + 1::-1]))
    return b


def _reciprocal_series(b: np.ndarray) -> np.ndarray:
    q = np.zeros_like(b)
    q[0] = 1.0 / b[0]
    for n in range(1, b.size):
        q[n] = -float(np.dot(b[1:n + 1], q[n - 1::-1][:n])) / b[0]
    return q


def _foppl_by_series(nu: float, nterms: int = 80) -> FopplHencky:
    n = np.arange(nterms)

    def edge(b0):  # (1 - nu) S(1) + S'(1) with S'(1) = sum 2 n b_n
        b = _foppl_series_coefficients(b0, nterms)
        return float(np.sum(b * ((1.0 - nu) + 2.0 * n)))

    b0 = brentq(edge, 0.1, 5.0, xtol=1e-15, rtol=1e-14)
    b = _foppl_series_coefficients(b0, nterms)
    q = _reciprocal_series(b)  # 1/S = sum q_n x^n
    iq = 0.5 * q / (n + 1.0)   # int_0^rho t/S dt = (1/2) int_0^x dx/S = sum iq_n x^(n+1)

    def profile(rho):
        rho = np.clip(np.atleast_1d(np.asarray(rho, dtype=float)), 0.0, 1.0)
        x = rho * rho
        S = np.polynomial.polynomial.polyval(x, b)
        dS = 2.0 * rho * np.polynomial.polynomial.polyval(x, n[1:] * b[1:])
        I = x * np.polynomial.polynomial.polyval(x, iq)
        return S, dS, I

    S1, _, I1 = profile(np.array([1.0]))
    return FopplHencky(nu=nu, C=0.5 * float(I1[0]), D=b0, edge_stress=float(S1[0]),
                       method="series", profile=profile)


@functools.lru_cache(maxsize=32)
def foppl_hencky(nu: float, method: str = "shooting") -> FopplHencky:
    """Hencky's problem: clamped flat circular membrane under small uniform pressure.

    Föppl membrane (no bending stiffness, moderate rotations), radius ``a``, thickness ``h``,
    plane-stress linear elasticity ``E, nu``. Equilibrium of the stress resultants:
    ``d(r N_r)/dr = N_theta`` (in plane) and ``N_r w' = -p r / 2`` (vertical force on the disc
    of radius ``r``). Strains ``eps_r = u' + w'^2/2``, ``eps_theta = u/r``; eliminating ``u``
    (``u' = eps_theta + r eps_theta'``) with ``N_theta = N_r + r N_r'`` leaves the
    compatibility equation, independent of ``nu``::

        r^2 N_r'' + 3 r N_r' + E h w'^2 / 2 = 0,   w' = -p r / (2 N_r).

    With ``N_r = K S(rho)``, ``rho = r/a``, ``K = (E h p^2 a^2)^(1/3)``::

        S'' + 3 S'/rho + 1/(8 S^2) = 0,   S'(0) = 0,
        u(a) = 0  <=>  N_theta - nu N_r = 0  <=>  (1 - nu) S(1) + S'(1) = 0.

    Then ``sigma_0 = N_r(0)/h = S(0) (E p^2 a^2/h^2)^(1/3)``, so ``D = S(0)``, and
    ``w0 = int_0^a p r/(2 N_r) dr = a (p a/(E h))^(1/3) * (1/2) int_0^1 rho/S drho``, so
    ``C = (1/2) int_0^1 rho/S drho``. Only ``nu`` enters, through the edge condition.

    Args:
        nu: Poisson ratio (-1 < nu <= 1/2).
        method: "shooting" (default): integrate from the centre with ``S(0)`` unknown and
            root-find ``S(0)`` on the edge condition (DOP853, rtol 1e-12). "series": the
            power series ``S = sum b_n rho^(2n)`` of Hencky (1915) with its recursion
            computed here from the ODE (so free of the arithmetic error in Hencky's printed
            coefficients, corrected by Chien 1948), ``1/S`` as the reciprocal series
            integrated term by term; an independent route for cross-checks.

    Returns:
        The coefficients and the dimensionless profile (cached per ``nu`` and ``method``).

    Raises:
        ValueError: ``nu`` outside (-1, 1/2] or unknown ``method``.
    """
    if not -1.0 < nu <= 0.5:
        raise ValueError(f"nu: Poisson ratio {nu} outside (-1, 1/2]")
    if method == "shooting":
        return _foppl_by_shooting(float(nu))
    if method == "series":
        return _foppl_by_series(float(nu))
    raise ValueError(f"method: {method!r} is not 'shooting' or 'series'")


# --------------------------------------------------------------------------------------------
# Principal-stress laws of incompressible membranes
# --------------------------------------------------------------------------------------------


def neo_hookean(mu: float) -> StressLaw:
    """Incompressible neo-Hookean membrane, ``W = mu/2 (I1 - 3)``.

    With ``lambda_3 = 1/(l1 l2)`` and the reduced energy ``W(l1, l2, 1/(l1 l2))``,
    ``sigma_i = l_i dW/dl_i = mu (l_i^2 - lambda_3^2)`` (the pressure that keeps
    ``sigma_33 = 0`` is already eliminated by the reduction). Small strains: ``E = 3 mu``,
    ``nu = 1/2``.

    Args:
        mu: shear modulus, Pa.
    """

    def sigma(l1, l2):
        l3sq = 1.0 / (l1 * l2) ** 2
        return mu * (l1 * l1 - l3sq), mu * (l2 * l2 - l3sq)

    return sigma


def may_newman_yin(c0: float, c1: float, c2: float) -> StressLaw:
    """May-Newman-Yin law with the fibre along direction 1.

    .. math::
        W = c_0\\left[\\exp Q - 1\\right],\\quad Q = c_1 (I_1 - 3)^2 + c_2 (\\lambda_1 - 1)^4,
        \\quad I_1 = \\lambda_1^2 + \\lambda_2^2 + \\lambda_1^{-2}\\lambda_2^{-2}

    By hand: ``l1 dI1/dl1 = 2 (l1^2 - lambda_3^2)`` with ``lambda_3 = 1/(l1 l2)``, so::

        sigma_1 = l1 dW/dl1 = 4 c0 e^Q [c1 (I1 - 3)(l1^2 - lambda_3^2) + c2 l1 (l1 - 1)^3]
        sigma_2 = l2 dW/dl2 = 4 c0 e^Q  c1 (I1 - 3)(l2^2 - lambda_3^2)

    Args:
        c0: Pa. c1, c2: dimensionless.
    """

    def sigma(l1, l2):
        l3sq = 1.0 / (l1 * l2) ** 2
        I1m3 = l1 * l1 + l2 * l2 + l3sq - 3.0
        with np.errstate(over="ignore"):
            e = 4.0 * c0 * np.exp(c1 * I1m3**2 + c2 * (l1 - 1.0) ** 4)
        return (e * (c1 * I1m3 * (l1 * l1 - l3sq) + c2 * l1 * (l1 - 1.0) ** 3),
                e * c1 * I1m3 * (l2 * l2 - l3sq))

    return sigma


def holzapfel(c0: float, c1: float, c2: float) -> StressLaw:
    """Holzapfel-type law ``W = c0 [exp(c1 (I1-3)^2 + c2 (l1^2-1)^2) - 1]``, fibre along 1.

    As for :func:`may_newman_yin`, with ``l1 d(l1^2 - 1)^2/dl1 = 4 l1^2 (l1^2 - 1)``::

        sigma_1 = 4 c0 e^Q [c1 (I1 - 3)(l1^2 - lambda_3^2) + c2 l1^2 (l1^2 - 1)]
        sigma_2 = 4 c0 e^Q  c1 (I1 - 3)(l2^2 - lambda_3^2)
    """

    def sigma(l1, l2):
        l3sq = 1.0 / (l1 * l2) ** 2
        I1m3 = l1 * l1 + l2 * l2 + l3sq - 3.0
        with np.errstate(over="ignore"):
            e = 4.0 * c0 * np.exp(c1 * I1m3**2 + c2 * (l1 * l1 - 1.0) ** 2)
        return (e * (c1 * I1m3 * (l1 * l1 - l3sq) + c2 * l1 * l1 * (l1 * l1 - 1.0)),
                e * c1 * I1m3 * (l2 * l2 - l3sq))

    return sigma


# --------------------------------------------------------------------------------------------
# Inflation of a clamped flat circular incompressible membrane (follower pressure)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Inflation:
    """An axisymmetric equilibrium of the inflated disc.

    Attributes:
        pressure: follower pressure, Pa.
        centre_deflection: height of the pole above the clamping plane (units of the radius).
        centre_stretch: equibiaxial stretch at the pole, ``lambda_0``.
        R: reference radii of the profile points, ``0 .. a``.
        r, z: deformed radius and height above the clamping plane at those points.
        stretch_meridional, stretch_hoop: principal stretches ``lambda_1, lambda_2 = r/R``.
        edge_angle: angle of the meridian below the horizontal at the clamp, radians
            (above pi/2 once the bubble overhangs its base).
    """

    pressure: float
    centre_deflection: float
    centre_stretch: float
    R: np.ndarray = field(repr=False)
    r: np.ndarray = field(repr=False)
    z: np.ndarray = field(repr=False)
    stretch_meridional: np.ndarray = field(repr=False)
    stretch_hoop: np.ndarray = field(repr=False)
    edge_angle: float = 0.0


_FD_STEP = 1e-6
_INFLATION_RTOL = 1e-10


def _nominal(law: StressLaw, l1: float, l2: float):
    """``t_i = sigma_i / l_i = dW/dl_i`` and the derivatives ``dt1/dl1, dt1/dl2`` (central FD)."""
    s1, s2 = law(l1, l2)
    d1 = _FD_STEP * l1
    d2 = _FD_STEP * l2
    t11 = (law(l1 + d1, l2)[0] / (l1 + d1) - law(l1 - d1, l2)[0] / (l1 - d1)) / (2.0 * d1)
    t12 = (law(l1, l2 + d2)[0] - law(l1, l2 - d2)[0]) / (2.0 * d2 * l1)
    return float(s1) / l1, float(s2) / l2, float(t11), float(t12)


def _inflation_rhs(law: StressLaw):
    def rhs(xi, y):
        l1, l2, th, _ = y
        t1, t2, t11, t12 = _nominal(law, l1, l2)
        c, s = math.cos(th), math.sin(th)
        return [(t2 * c - t1 - t12 * (l1 * c - l2)) / (xi * t11),
                (l1 * c - l2) / xi,
                (l1 * l2 - t2 * s / xi) / t1,
                l1 * s]
    return rhs


def _edge_event(xi, y):
    return y[1] - 1.0


_edge_event.terminal = True
_edge_event.direction = -1


def _folded_event(xi, y):  # meridian turned back past the vertical downwards: give up
    return y[2] - 0.95 * math.pi


_folded_event.terminal = True


def _shoot_inflation(law: StressLaw, lam0: float):
    """Integrate the scaled disc equations from the pole at pole stretch ``lam0``.

    Returns ``(xi_edge, sol)`` with ``xi_edge = p a / h0`` of the disc whose clamp is where
    the hoop stretch returns to 1, or ``(None, sol)`` if it never does.
    """
    t0, t0b, t11, t12 = _nominal(law, lam0, lam0)
    if not abs(t0 - t0b) <= 1e-8 * abs(t0) or t0 <= 0.0:
        raise ValueError("law: axisymmetric inflation needs an isotropic law with tension at "
                         f"equibiaxial stretch (got s1/l = {t0}, s2/l = {t0b} at {lam0})")
    # series at the pole: l1 = l0 + A xi^2, l2 = l0 + B xi^2, theta = c xi
    c = lam0 * lam0 / (2.0 * t0)
    A, B = np.linalg.solve([[1.0, -3.0], [3.0 * t11 - t12, 3.0 * t12 - t11]],
                           [lam0 * c * c / 2.0, -t0 * c * c / 2.0])
    xi0 = 1e-4 * t0 * min(1.0, math.sqrt(lam0 - 1.0))
    y0 = [lam0 + A * xi0**2, lam0 + B * xi0**2, c * xi0, lam0 * c * xi0**2 / 2.0]
    sol = solve_ivp(_inflation_rhs(law), (xi0, 1e6 * t0), y0, method="DOP853",
                    rtol=_INFLATION_RTOL, atol=1e-14, dense_output=True,
                    events=(_edge_event, _folded_event))
    if sol.t_events[0].size == 0:
        return None, sol
    return float(sol.t_events[0][0]), sol


def _pressure_parameter(law: StressLaw, lam0: float) -> float:
    """``p a / h0`` as a function of the pole stretch; -inf where there is no equilibrium."""
    xi, _ = _shoot_inflation(law, lam0)
    return -math.inf if xi is None else xi


def inflation_at_pole_stretch(law: StressLaw, pole_stretch: float, radius: float,
                              thickness: float, npts: int = 101) -> Inflation:
    """The inflated disc whose pole stretch is ``pole_stretch`` (pressure follows).

    Formulation (Adkins & Rivlin 1952; Yang & Feng 1970): reference radius ``R``, deformed
    meridian ``(r(R), z(R))`` at angle ``theta`` below the horizontal; stretches
    ``l1 = |d(r, z)/dR|`` (meridional), ``l2 = r/R`` (hoop), thickness ``h = h0/(l1 l2)``;
    tensions per deformed length ``T_i = h sigma_i = h0 t_i / l_j`` with ``t_i = sigma_i/l_i
    = dW/dl_i``. Meridional and normal equilibrium of the surface of revolution::

        d(r T1)/ds = T2 cos(theta),   T1 dtheta/ds + T2 sin(theta)/r = p,   ds = l1 dR,

    become, in ``xi = p R / h0`` (which removes ``p``, ``h0`` and ``a``)::

        d(xi t1)/dxi = t2 cos(theta)        -> dl1/dxi via dt1/dl1, dt1/dl2
        dl2/dxi = (l1 cos(theta) - l2)/xi     (from r' = l1 cos(theta))
        dtheta/dxi = (l1 l2 - t2 sin(theta)/xi) / t1
        dzeta/dxi = l1 sin(theta)             (zeta = p (z_pole - z) / h0)

    Symmetry at the pole gives ``l1 = l2 = lambda_0`` and ``theta = c xi`` with
    ``c = lambda_0^2 / (2 t(lambda_0))``; the ``xi^2`` terms of the stretches come from a
    2x2 linear system and start the integration just off the pole. The clamp is where the
    hoop stretch returns to 1: ``xi_edge = p a / h0``. The first integral
    ``t1 sin(theta) = xi l2^2 / 2`` (vertical force on a cap) is not imposed and can serve
    as an accuracy check. The law must be isotropic; its derivatives are central
    differences.

    Args:
        law: principal Cauchy stresses of the incompressible membrane, ``sigma(l1, l2)``.
        pole_stretch: ``lambda_0 > 1``.
        radius: clamp radius ``a`` (mm).
        thickness: reference thickness ``h0`` (mm).
        npts: number of profile points, uniform in ``R``.

    Raises:
        ValueError: no disc equilibrium reaches the clamp from this pole stretch, or the
            law is anisotropic.
    """
    if not pole_stretch > 1.0:
        raise ValueError(f"pole_stretch: {pole_stretch} must exceed 1")
    xi_e, sol = _shoot_inflation(law, float(pole_stretch))
    if xi_e is None:
        raise ValueError(f"pole_stretch: no axisymmetric equilibrium reaches the clamp from "
                         f"pole stretch {pole_stretch}")
    k = xi_e / radius  # p / h0
    R = np.linspace(0.0, radius, npts)
    xi = k * R
    xi0 = sol.t[0]
    y = np.empty((4, npts))
    inside = xi >= xi0
    y[:, inside] = sol.sol(np.minimum(xi[inside], xi_e))
    near = ~inside  # the series at the pole
    y0 = sol.y[:, 0]
    cc = y0[2] / xi0
    y[0, near] = pole_stretch + (y0[0] - pole_stretch) * (xi[near] / xi0) ** 2
    y[1, near] = pole_stretch + (y0[1] - pole_stretch) * (xi[near] / xi0) ** 2
    y[2, near] = cc * xi[near]
    y[3, near] = pole_stretch * cc * xi[near] ** 2 / 2.0
    y[1, -1] = 1.0
    zeta_e = float(sol.y_events[0][0][3])
    return Inflation(pressure=k * thickness, centre_deflection=zeta_e / k,
                     centre_stretch=float(pole_stretch), R=R, r=R * y[1],
                     z=(zeta_e - y[3]) / k, stretch_meridional=y[0], stretch_hoop=y[1],
                     edge_angle=float(sol.y_events[0][0][2]))


def _march_pole_stretch(law: StressLaw, target: float, start: float, max_pole_stretch: float):
    """March ``lambda_0 - 1`` upwards from ``start`` until ``p a/h0 >= target``.

    Returns ``(lo, hi)`` bracketing the first crossing, or ``("max", lo, hi)`` when the
    pressure parameter fell (a limit point lies in ``[lo, hi]``) before reaching the target,
    or ``None`` when ``max_pole_stretch`` was reached.
    """
    e_prev2, e_prev, f_prev = None, None, -math.inf
    e = start
    while 1.0 + e <= max_pole_stretch:
        f = _pressure_parameter(law, 1.0 + e)
        if f >= target:
            return e_prev, e
        if f < f_prev:
            return "max", (e_prev2 if e_prev2 is not None else e_prev / 1.5), e
        e_prev2, e_prev, f_prev = e_prev, e, f
        e *= 1.5
    return None


def _limit_in(law: StressLaw, lo: float, hi: float) -> tuple[float, float]:
    res = minimize_scalar(lambda e: -_pressure_parameter(law, 1.0 + e), bounds=(lo, hi),
                          method="bounded", options={"xatol": 1e-9 * max(1.0, hi)})
    return 1.0 + float(res.x), -float(res.fun)


def _start_strain(law: StressLaw, target: float) -> float:
    """A first pole strain from the small-strain (Föppl) estimate for ``nu = 1/2``.

    Equibiaxial modulus ``M = sigma/e`` at e = 1e-3; ``E ~ M/2``; Hencky:
    ``e0 ~ (1 - nu) D (p a/(E h))^(2/3)`` with ``D ~ 0.46``.
    """
    M = float(law(1.001, 1.001)[0]) / 1e-3
    if not M > 0.0 or not math.isfinite(M):
        return 1e-3
    return min(max(0.23 * (2.0 * target / M) ** (2.0 / 3.0), 1e-7), 0.5)


def axisymmetric_inflation(law: StressLaw, pressure: float, radius: float, thickness: float,
                           npts: int = 101, max_pole_stretch: float = 10.0) -> Inflation:
    """Inflate a clamped flat circular incompressible membrane by a follower pressure.

    Shoots on the pole stretch ``lambda_0`` (see :func:`inflation_at_pole_stretch` for the
    equations): the scaled equations give ``p a / h0`` as a function of ``lambda_0`` alone,
    and the root of ``p(lambda_0) = pressure`` on the rising branch (the stable one, from the
    flat state up to the limit point) is found by marching and Brent's method (relative
    tolerance 1e-12 on ``lambda_0``).

    Args:
        law: principal Cauchy stresses ``sigma(l1, l2)`` of an isotropic incompressible
            membrane (Pa), e.g. :func:`neo_hookean`.
        pressure: Pa, > 0.
        radius: clamp radius ``a`` (mm).
        thickness: reference thickness ``h0`` (mm).
        npts: number of profile points.
        max_pole_stretch: give up beyond this pole stretch.

    Returns:
        The equilibrium (pressure, pole height and stretch, profile).

    Raises:
        ValueError: the pressure is above the limit point (no equilibrium on the loading
            branch; the message gives the limit pressure), or no equilibrium was found up to
            ``max_pole_stretch``, or a non-positive pressure.
    """
    if not pressure > 0.0:
        raise ValueError(f"pressure: {pressure} Pa; the inflation needs a positive pressure")
    target = pressure * radius / thickness
    e = _start_strain(law, target)
    while e > 1e-9 and _pressure_parameter(law, 1.0 + e) >= target:
        e /= 4.0
    found = _march_pole_stretch(law, target, e, max_pole_stretch)
    if found is None:
        raise ValueError(f"pressure: {pressure} Pa not reached with pole stretch up to "
                         f"{max_pole_stretch}")
    if found[0] == "max":
        lam_max, xi_max = _limit_in(law, found[1], found[2])
        if xi_max < target:
            raise ValueError(
                f"pressure: {pressure} Pa is beyond the limit point of the inflated disc "
                f"(maximum {xi_max * thickness / radius:.6g} Pa at pole stretch "
                f"{lam_max:.4f}): no equilibrium")
        lo, hi = found[1], lam_max - 1.0
    else:
        lo, hi = found
        if lo is None:
            lo = 0.0
    lam0 = 1.0 + brentq(lambda s: _pressure_parameter(law, 1.0 + s) - target,
                        max(lo, 1e-12), hi, xtol=1e-14, rtol=1e-12)
    return inflation_at_pole_stretch(law, lam0, radius, thickness, npts)


def inflation_limit_point(law: StressLaw, radius: float, thickness: float,
                          max_pole_stretch: float = 10.0) -> tuple[float, float]:
    """The limit point (pressure maximum) of the inflated disc on its loading branch.

    Args:
        law: isotropic membrane law, as for :func:`axisymmetric_inflation`.
        radius: clamp radius ``a``. thickness: ``h0``.
        max_pole_stretch: search bound.

    Returns:
        ``(pressure_max, pole_stretch)``; use :func:`inflation_at_pole_stretch` for the shape.

    Raises:
        ValueError: the pressure keeps rising up to ``max_pole_stretch``.
    """
    found = _march_pole_stretch(law, math.inf, 1e-3, max_pole_stretch)
    if found is None or found[0] != "max":
        raise ValueError(f"law: no limit point up to pole stretch {max_pole_stretch}")
    lam, xi = _limit_in(law, found[1], found[2])
    return xi * thickness / radius, lam


# --------------------------------------------------------------------------------------------
# Closed membranes: sphere and tube (Laplace's law)
# --------------------------------------------------------------------------------------------


def sphere_inflation(law_sigma: StressLaw, R: float, h0: float, stretch: float) -> float:
    """Pressure in a closed spherical incompressible membrane at equibiaxial stretch.

    Laplace: ``p = (T1 + T2) / r`` with ``r = R lambda``, ``T_i = h sigma_i`` and
    ``h = h0 / lambda^2``; for an isotropic law ``p = 2 h0 sigma(lambda, lambda) /
    (lambda^2 R lambda)``. For an anisotropic law this is the normal balance with the mean
    tension (a uniformly stretched sphere is then not in tangential equilibrium everywhere).

    Args:
        law_sigma: principal Cauchy stresses ``sigma(l1, l2)``, Pa.
        R: reference radius (mm). h0: reference thickness (mm). stretch: ``lambda``.
    """
    s1, s2 = law_sigma(stretch, stretch)
    return float(h0 / stretch**2 * (s1 + s2) / (R * stretch))


class TubeInflation(NamedTuple):
    """Pressure and axial Cauchy stress of an inflated tube (Pa)."""

    pressure: float
    axial_stress: float


def cylinder_inflation(law_sigma: StressLaw, R: float, h0: float, l_hoop: float,
                       l_axial: float = 1.0) -> TubeInflation:
    """Open or closed tube of an incompressible membrane at uniform stretches.

    Direction 1 of ``law_sigma`` is the hoop, direction 2 the axis (swap the arguments in a
    wrapper to put a fibre axially). Hoop equilibrium: ``p = h sigma_theta / r`` with
    ``h = h0 / (l_hoop l_axial)``, ``r = R l_hoop``. The axial stress is whatever the ends
    must carry: axial force ``2 pi r h sigma_z``; a closed-end tube needs
    ``2 pi r h sigma_z = p pi r^2``.

    Args:
        law_sigma: principal Cauchy stresses ``sigma(l_hoop, l_axial)``, Pa.
        R: reference radius (mm). h0: reference thickness (mm).
        l_hoop, l_axial: principal stretches.
    """
    s_theta, s_z = law_sigma(l_hoop, l_axial)
    h = h0 / (l_hoop * l_axial)
    return TubeInflation(float(h * s_theta / (R * l_hoop)), float(s_z))


def _first_crossing(f: Callable[[float], float], target: float, max_stretch: float,
                    what: str) -> float:
    """Smallest stretch in ``[1, max_stretch]`` with ``f(stretch) = target`` (bracketed)."""
    if not target > 0.0:
        if target == 0.0:
            return 1.0
        raise ValueError(f"pressure: {target} Pa; a membrane under suction has no inflated "
                         "equilibrium")
    grid = 1.0 + (max_stretch - 1.0) * np.linspace(0.0, 1.0, 401) ** 2
    lo, f_max, lam_max = 1.0, 0.0, 1.0
    for lam in grid[1:]:
        val = f(lam)
        if not math.isfinite(val):  # overflow of an exponential law: bisect to a finite value
            hi = lam
            for _ in range(200):
                mid = 0.5 * (lo + hi)
                v = f(mid)
                if math.isfinite(v) and v >= target:
                    hi = mid
                    break
                if math.isfinite(v):
                    lo = mid
                else:
                    hi = mid
            return brentq(lambda s: f(s) - target, lo, hi, xtol=1e-14, rtol=1e-13)
        if val >= target:
            return brentq(lambda s: f(s) - target, lo, lam, xtol=1e-14, rtol=1e-13)
        if val > f_max:
            f_max, lam_max = val, lam
        lo = lam
    raise ValueError(f"pressure: {target} Pa is not reached by the {what} for stretches up to "
                     f"{max_stretch} (largest {f_max:.6g} Pa near stretch {lam_max:.4f}; "
                     "beyond a limit point there is no equilibrium)")


def sphere_stretch(law_sigma: StressLaw, R: float, h0: float, pressure: float,
                   max_stretch: float = 5.0) -> float:
    """Inverse of :func:`sphere_inflation`: the smallest stretch carrying ``pressure``.

    Raises:
        ValueError: the pressure exceeds every pressure on ``[1, max_stretch]`` (e.g. above
            the neo-Hookean maximum at ``lambda = 7^(1/6)``), or is negative.
    """
    return _first_crossing(lambda s: sphere_inflation(law_sigma, R, h0, s), pressure,
                           max_stretch, "sphere")


def cylinder_stretch(law_sigma: StressLaw, R: float, h0: float, pressure: float,
                     l_axial: float = 1.0, max_stretch: float = 5.0) -> float:
    """Inverse of :func:`cylinder_inflation`: the smallest hoop stretch carrying ``pressure``
    at the given axial stretch.

    Raises:
        ValueError: the pressure is not reached for hoop stretches up to ``max_stretch``.
    """
    return _first_crossing(lambda s: cylinder_inflation(law_sigma, R, h0, s, l_axial).pressure,
                           pressure, max_stretch, "tube")
