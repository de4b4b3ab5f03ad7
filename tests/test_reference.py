"""Checks of the independent reference solutions in :mod:`mvfem.reference` (numpy/scipy only).

Each test states the property it relies on. Units: mm and Pa.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import simpson
from scipy.optimize import minimize_scalar

from mvfem import reference as ref

MU = 100e3  # Pa
A = 10.0    # mm, disc radius
H0 = 0.5    # mm


# --------------------------------------------------------------------------------------------
# Föppl-Hencky
# --------------------------------------------------------------------------------------------


def test_foppl_hencky_nu_03_coefficients():
    """nu = 0.3: w0/a = 0.653 (pa/Eh)^(1/3), sigma_0 = 0.431 (E p^2 a^2/h^2)^(1/3).

    These are the values of Hencky's series with the arithmetic error of 1915 corrected
    (Chien 1948); sigma_0 coefficient = b0/4 with b0 = 1.724 in Hencky's scaling. (Some texts
    print 0.662 for w0/a; the Föppl equations solved here by two independent routes, and by a
    displacement-form collocation solve during development, give 0.65344.)
    """
    fh = ref.foppl_hencky(0.3)
    assert round(fh.C, 3) == 0.653
    assert round(fh.D, 3) == 0.431
    assert fh.centre_deflection(A, H0, 3 * MU, 1e3) == pytest.approx(
        fh.C * A * (1e3 * A / (3 * MU * H0)) ** (1 / 3), rel=1e-14)


@pytest.mark.parametrize("nu", [0.3, 0.5])
def test_foppl_hencky_clamped_edge(nu):
    """The shooting solution meets the clamp: u(a) = 0 and w(a) = 0, and w(0) = w0.

    ``u(a)`` is compared with the natural displacement scale ``w0^2 / a``.
    """
    fh = ref.foppl_hencky(nu)
    E, p = 3 * MU, 2e3
    w0 = fh.centre_deflection(A, H0, E, p)
    assert abs(fh.radial_displacement(A, A, H0, E, p)[0]) < 1e-10 * w0**2 / A
    assert abs(fh.deflection(A, A, H0, E, p)[0]) < 1e-12 * w0
    assert fh.deflection(0.0, A, H0, E, p)[0] == pytest.approx(w0, rel=1e-12)
    # at the clamp eps_theta = 0 <=> sigma_theta = nu sigma_r
    assert fh.hoop_stress(A, A, H0, E, p)[0] == pytest.approx(
        nu * fh.radial_stress(A, A, H0, E, p)[0], rel=1e-9)


@pytest.mark.parametrize("nu", [0.3, 0.5])
def test_foppl_hencky_shooting_and_series_agree(nu):
    """ODE shooting and Hencky's power series (recursion from the ODE) are independent routes.

    They agree on C, D and the whole profile to far better than 1e-6.
    """
    shoot = ref.foppl_hencky(nu, "shooting")
    series = ref.foppl_hencky(nu, "series")
    assert abs(shoot.C - series.C) < 1e-9
    assert abs(shoot.D - series.D) < 1e-9
    rho = np.linspace(0.0, 1.0, 11)
    for a, b in zip(shoot.profile(rho), series.profile(rho)):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-10)


def test_foppl_hencky_nu_05_values():
    """nu = 1/2 (the small-strain limit of the incompressible laws): C = 0.5949, D = 0.4613."""
    fh = ref.foppl_hencky(0.5)
    assert fh.C == pytest.approx(0.594879, abs=1e-6)
    assert fh.D == pytest.approx(0.461328, abs=1e-6)
    with pytest.raises(ValueError, match="Poisson"):
        ref.foppl_hencky(0.6)


# --------------------------------------------------------------------------------------------
# Laws
# --------------------------------------------------------------------------------------------


def _reduced_energy(law, params):
    def W(l1, l2):
        I1 = l1 * l1 + l2 * l2 + 1.0 / (l1 * l2) ** 2
        if law == "neo-hookean":
            return params[0] / 2 * (I1 - 3)
        c0, c1, c2 = params
        fibre = (l1 - 1) ** 4 if law == "mny" else (l1 * l1 - 1) ** 2
        return c0 * (math.exp(c1 * (I1 - 3) ** 2 + c2 * fibre) - 1)
    return W


@pytest.mark.parametrize("law, params", [
    ("neo-hookean", (MU,)),
    ("mny", (399.0, 4.325, 1446.5)),
    ("holzapfel", (52.0, 4.63, 22.6)),
])
def test_principal_stresses_are_energy_derivatives(law, params):
    """sigma_i = l_i dW/dl_i of the reduced energy W(l1, l2, 1/(l1 l2)), by central differences."""
    sigma = {"neo-hookean": ref.neo_hookean, "mny": ref.may_newman_yin,
             "holzapfel": ref.holzapfel}[law](*params)
    W = _reduced_energy(law, params)
    d = 1e-6
    for l1, l2 in [(1.1, 1.05), (1.25, 0.95), (0.97, 1.2)]:
        s1, s2 = sigma(l1, l2)
        f1 = l1 * (W(l1 + d, l2) - W(l1 - d, l2)) / (2 * d)
        f2 = l2 * (W(l1, l2 + d) - W(l1, l2 - d)) / (2 * d)
        assert s1 == pytest.approx(f1, rel=1e-6)
        assert s2 == pytest.approx(f2, rel=1e-6)
    assert np.allclose(sigma(1.0, 1.0), 0.0)


# --------------------------------------------------------------------------------------------
# Inflation of the clamped disc
# --------------------------------------------------------------------------------------------


def test_inflation_small_pressure_tends_to_foppl_hencky():
    """Small pressures: the neo-Hookean disc (E = 3 mu, nu = 1/2) follows Föppl-Hencky.

    The relative difference of the pole height falls like the strain, ~ (p a/(E h))^(2/3),
    and is below 1 % from p a/(mu h0) = 1e-2 down.
    """
    law = ref.neo_hookean(MU)
    fh = ref.foppl_hencky(0.5)
    loads = np.array([1e-2, 1e-3, 1e-4])  # p a / (mu h0)
    diffs = []
    for q in loads:
        p = q * MU * H0 / A
        inflated = ref.axisymmetric_inflation(law, p, A, H0)
        assert inflated.pressure == pytest.approx(p, rel=1e-10)
        assert inflated.r[-1] == pytest.approx(A, rel=1e-12)
        assert inflated.z[-1] == pytest.approx(0.0, abs=1e-12 * A)
        w0 = fh.centre_deflection(A, H0, 3 * MU, p)
        diffs.append(abs(inflated.centre_deflection / w0 - 1))
    assert diffs[0] < 1e-2
    assert diffs[0] > diffs[1] > diffs[2]
    slope = np.polyfit(np.log(loads), np.log(diffs), 1)[0]
    assert slope == pytest.approx(2 / 3, abs=0.05)


def test_inflation_pole_is_a_spherical_cap():
    """At the pole s1 = s2 = sigma(l0, l0) and Laplace's law holds: p = 2 h s / R_curv.

    R_curv is fitted to the computed profile near the pole, z = z0 - r^2/(2 R_curv) + O(r^4)
    (cubic in r^2),
    and h = h0 / l0^2.
    """
    law = ref.neo_hookean(MU)
    p = 1.0 * MU * H0 / A
    inflated = ref.axisymmetric_inflation(law, p, A, H0, npts=801)
    l0 = inflated.centre_stretch
    near = inflated.r < 0.1 * A
    coef = np.polyfit(inflated.r[near] ** 2, inflated.z[near], 3)
    r_curv = -1.0 / (2 * coef[2])
    assert coef[3] == pytest.approx(inflated.centre_deflection, rel=1e-9)
    s = law(l0, l0)[0]
    assert 2 * (H0 / l0**2) * s / r_curv == pytest.approx(p, rel=1e-6)
    np.testing.assert_allclose(inflated.stretch_meridional[0], inflated.stretch_hoop[0])


@pytest.mark.parametrize("l0", [1.5, 2.5])
def test_inflation_virtual_work(l0):
    """Along the equilibrium path the stored energy changes by p dV: dU/dV = p.

    U = 2 pi h0 int W(l1, l2) R dR over the reference disc, V = int pi r^2 |dz| the volume
    under the bubble; central differences in the pole stretch. This checks the ODEs, the
    clamp condition and the follower load together (including past the limit point).
    """
    mu = MU
    law = ref.neo_hookean(mu)

    def energy_volume(lam):
        s = ref.inflation_at_pole_stretch(law, lam, A, H0, npts=2001)
        W = mu / 2 * (s.stretch_meridional**2 + s.stretch_hoop**2
                      + 1 / (s.stretch_meridional * s.stretch_hoop) ** 2 - 3)
        U = 2 * np.pi * H0 * simpson(W * s.R, x=s.R)
        V = simpson(-np.pi * s.r**2 * np.gradient(s.z, s.R, edge_order=2), x=s.R)
        return U, V, s.pressure

    d = 1e-3
    Up, Vp, _ = energy_volume(l0 + d)
    Um, Vm, _ = energy_volume(l0 - d)
    _, _, p = energy_volume(l0)
    assert (Up - Um) / (Vp - Vm) == pytest.approx(p, rel=1e-5)


def test_inflation_limit_point():
    """Neo-Hookean disc: the pressure has a maximum (limit point), here computed as
    p a/(mu h0) = 1.879 at pole stretch 2.196, pole height 1.17 a (past the hemisphere).

    Beyond it no equilibrium exists on the loading branch and a ValueError says so; just
    below it the solution is on the rising branch.
    """
    law = ref.neo_hookean(MU)
    p_max, l_max = ref.inflation_limit_point(law, A, H0)
    q_max = p_max * A / (MU * H0)
    assert q_max == pytest.approx(1.8792, abs=2e-4)
    assert l_max == pytest.approx(2.196, abs=2e-3)
    for dl in (-0.05, 0.05):
        assert ref.inflation_at_pole_stretch(law, l_max + dl, A, H0).pressure < p_max
    top = ref.inflation_at_pole_stretch(law, l_max, A, H0)
    assert top.centre_deflection / A == pytest.approx(1.174, abs=2e-3)
    below = ref.axisymmetric_inflation(law, 0.99 * p_max, A, H0)
    assert below.centre_stretch < l_max
    with pytest.raises(ValueError, match="limit point"):
        ref.axisymmetric_inflation(law, 1.02 * p_max, A, H0)


def test_inflation_rejects_anisotropic_law():
    """A fibre law is not axisymmetric: refuse rather than return a wrong shape."""
    with pytest.raises(ValueError, match="isotropic"):
        ref.axisymmetric_inflation(ref.may_newman_yin(399.0, 4.325, 1446.5), 100.0, A, H0)


# --------------------------------------------------------------------------------------------
# Sphere and tube
# --------------------------------------------------------------------------------------------


def test_neo_hookean_sphere_pressure_maximum():
    """Neo-Hookean balloon: p R/(mu h0) = 2 (l^-1 - l^-7), maximum at l = 7^(1/6) = 1.383
    where p R/(mu h0) = (12/7) 7^(-1/6) (classical; e.g. Ogden, Non-linear elastic
    deformations, 1984). Above it the inverse raises.
    """
    law = ref.neo_hookean(MU)
    R = 5.0
    res = minimize_scalar(lambda s: -ref.sphere_inflation(law, R, H0, s), bounds=(1.0, 3.0),
                          method="bounded", options={"xatol": 1e-10})
    assert res.x == pytest.approx(7 ** (1 / 6), abs=1e-6)
    assert 7 ** (1 / 6) == pytest.approx(1.383, abs=1e-3)
    p_max = -res.fun
    assert p_max == pytest.approx(12 / 7 * 7 ** (-1 / 6) * MU * H0 / R, rel=1e-12)
    assert ref.sphere_inflation(law, R, H0, 1.2) == pytest.approx(
        2 * MU * H0 / R * (1.2**-1 - 1.2**-7), rel=1e-13)
    with pytest.raises(ValueError, match="not reached"):
        ref.sphere_stretch(law, R, H0, 1.01 * p_max)


@pytest.mark.parametrize("law", [ref.neo_hookean(MU), ref.may_newman_yin(399.0, 4.325, 1446.5)])
def test_sphere_inverse_matches_forward(law):
    """sphere_stretch(sphere_inflation(l)) = l on the rising branch."""
    R = 5.0
    for lam in (1.02, 1.1, 1.3):
        p = ref.sphere_inflation(law, R, H0, lam)
        assert ref.sphere_stretch(law, R, H0, p) == pytest.approx(lam, rel=1e-10)
    assert ref.sphere_stretch(law, R, H0, 0.0) == 1.0


def test_cylinder_closed_form_and_inverse():
    """Neo-Hookean tube, plane strain axially (l_z = 1): p R/(mu h0) = 1 - l^-4, rising to an
    asymptote (no limit point), so pressures at or above mu h0 / R have no equilibrium. The
    axial stress is mu (1 - l^-2); the inverse matches the forward map, also for MNY with the
    fibre in the hoop direction and an axial pre-stretch.
    """
    law = ref.neo_hookean(MU)
    R = 5.0
    tube = ref.cylinder_inflation(law, R, H0, 1.3)
    assert tube.pressure == pytest.approx(MU * H0 / R * (1 - 1.3**-4), rel=1e-13)
    assert tube.axial_stress == pytest.approx(MU * (1 - 1.3**-2), rel=1e-13)
    assert ref.cylinder_stretch(law, R, H0, tube.pressure) == pytest.approx(1.3, rel=1e-10)
    with pytest.raises(ValueError, match="not reached"):
        ref.cylinder_stretch(law, R, H0, MU * H0 / R)
    mny = ref.may_newman_yin(399.0, 4.325, 1446.5)
    for lam in (1.05, 1.2):
        p = ref.cylinder_inflation(mny, R, H0, lam, 1.1).pressure
        assert ref.cylinder_stretch(mny, R, H0, p, l_axial=1.1) == pytest.approx(lam, rel=1e-10)
