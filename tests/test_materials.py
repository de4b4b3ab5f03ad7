"""The UFL membrane laws against closed-form plane-stress biaxial stresses derived by hand.

Derivation (incompressible membrane, principal stretches l1 along the fibre, l2 across it,
l3 = 1/(l1 l2), sigma33 = 0). With the reduced energy w(l1, l2) = W(l1, l2, 1/(l1 l2)) the
principal Cauchy stresses are sigma_i = l_i dw/dl_i. Since dl3/dl1 = -l3/l1,

    l1 dI1/dl1 = 2 (l1^2 - l3^2),     l2 dI1/dl2 = 2 (l2^2 - l3^2),

so for W = f(I1) + g(l1):  sigma_1 = f'(I1) 2(l1^2 - l3^2) + l1 g'(l1),
                           sigma_2 = f'(I1) 2(l2^2 - l3^2).

- neo-Hookean W = mu/2 (I1 - 3):   sigma_i = mu (l_i^2 - l3^2).
- May-Newman-Yin W = c0 [exp(Q) - 1], Q = c1 (I1-3)^2 + c2 (l1-1)^4:
      sigma_1 = c0 e^Q [4 c1 (I1-3)(l1^2 - l3^2) + 4 c2 (l1-1)^3 l1],
      sigma_2 = c0 e^Q [4 c1 (I1-3)(l2^2 - l3^2)].
- Holzapfel-type, Q = c1 (I1-3)^2 + c2 (l1^2-1)^2:
      sigma_1 = c0 e^Q [4 c1 (I1-3)(l1^2 - l3^2) + 4 c2 (l1^2-1) l1^2].
- SVK in plane stress, W = E/(2(1-nu^2)) [(1-nu)(E1^2+E2^2) + nu (E1+E2)^2], E_i = (l_i^2-1)/2:
      S_1 = dW/dE1 = E/(1-nu^2) (E1 + nu E2),  sigma_1 = l1^2 S_1 (F S F^T, incompressible).

The UFL side: a triangle in a tilted plane, the fibre at an angle in that plane, stretched along
and across the fibre and then rigidly rotated; the Cauchy stress from ``ufl.diff`` of the energy
is projected on the deformed fibre and cross-fibre directions.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import rotation, tilted_frame

from mvfem.biaxial import MODES, PatchStress, mode_strains
from mvfem.materials import parameter_sets


def closed_form(law: str, p: dict, l1: np.ndarray, l2: np.ndarray):
    """Principal Cauchy stresses (along, across the fibre) from the formulas in the docstring."""
    l3 = 1.0 / (l1 * l2)
    I1 = l1**2 + l2**2 + l3**2
    d1, d2 = 2 * (l1**2 - l3**2), 2 * (l2**2 - l3**2)
    with np.errstate(over="ignore", invalid="ignore"):
        if law == "neo-hookean":
            return p["mu"] / 2 * d1, p["mu"] / 2 * d2
        if law == "svk":
            E1, E2 = (l1**2 - 1) / 2, (l2**2 - 1) / 2
            k = p["E"] / (1 - p["nu"] ** 2)
            return l1**2 * k * (E1 + p["nu"] * E2), l2**2 * k * (E2 + p["nu"] * E1)
        c0, c1, c2 = p["c0"], p["c1"], p["c2"]
        if law == "mny":
            Q = c1 * (I1 - 3) ** 2 + c2 * (l1 - 1) ** 4
            fib = 4 * c2 * (l1 - 1) ** 3 * l1
        elif law == "holzapfel":
            Q = c1 * (I1 - 3) ** 2 + c2 * (l1**2 - 1) ** 2
            fib = 4 * c2 * (l1**2 - 1) * l1**2
        else:
            raise ValueError(law)
        e = c0 * np.exp(Q)
        return e * (2 * c1 * (I1 - 3) * d1 + fib), e * (2 * c1 * (I1 - 3) * d2)


def _cases():
    sets = [(s.law, s.leaflet + "/" + s.name, s.params) for s in parameter_sets()]
    sets.append(("neo-hookean", "mu=5kPa", {"mu": 5000.0}))
    return sets


LAWS = ("svk", "mny", "holzapfel", "neo-hookean")


@pytest.fixture(scope="module")
def evaluators():
    frame = tilted_frame()
    return {law: PatchStress(law, frame=frame, fibre_angle=0.7) for law in LAWS}


@pytest.mark.parametrize("law,name,params", _cases(), ids=[c[1] for c in _cases()])
def test_biaxial_stress_matches_closed_form(evaluators, law, name, params):
    ev = evaluators[law]
    ev.set_parameters(params)
    R = rotation([0.3, -1.0, 0.5], 1.1)  # a rigid rotation must not change the stresses
    e = np.linspace(-0.5, 0.5, 41)
    compared = 0
    for mode in MODES:
        ep, eq = mode_strains(mode, e)
        with np.errstate(all="ignore"):
            sp, sq = ev.biaxial(ep, eq, rotation=R)
        cp, cq = closed_form(law, params, 1 + ep, 1 + eq)
        finite = np.isfinite(cp) & np.isfinite(cq)
        # where the closed form overflows float64 the evaluated stress cannot be finite either
        assert not np.any(np.isfinite(sp[~finite]) & np.isfinite(sq[~finite]))
        # relative to the stress, or to the law's modulus where the stress passes through zero
        modulus = params.get("E", params.get("mu", params.get("c0")))
        scale = np.maximum(np.maximum(np.abs(cp), np.abs(cq)), modulus)[finite]
        np.testing.assert_array_less(np.abs(sp[finite] - cp[finite]) / scale, 1e-11)
        np.testing.assert_array_less(np.abs(sq[finite] - cq[finite]) / scale, 1e-11)
        compared += finite.sum()
    assert compared >= 0.9 * 4 * len(e)  # overflow is confined to strong compression


@pytest.mark.parametrize("law", LAWS)
def test_stress_is_tangent_and_principal(evaluators, law):
    """sigma33 = 0 and no shear between fibre and cross-fibre directions, after rotation."""
    ev = evaluators[law]
    ev.set_parameters({"svk": {"E": 4e5, "nu": 0.5}, "neo-hookean": {"mu": 5e3}}.get(
        law, {"c0": 399.0, "c1": 4.325, "c2": 1446.5}))
    R = rotation([1.0, 2.0, -0.5], 0.8)
    F = ev.deformation(0.2, 0.1, rotation=R)
    s = ev.cauchy(F)
    n = R @ ev.n0
    a, b = F @ ev.a0, F @ ev.b0
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    scale = np.abs(s).max()
    assert scale > 0
    assert np.allclose(s, s.T, atol=1e-12 * scale)
    assert abs(a @ s @ b) < 1e-12 * scale
    assert np.linalg.norm(s @ n) < 1e-12 * scale


def test_stress_free_reference(evaluators):
    """Every law and set is stress free at the identity."""
    for law, _, params in _cases():
        ev = evaluators[law]
        ev.set_parameters(params)
        assert np.abs(ev.cauchy(np.eye(3))).max() < 1e-9


@pytest.mark.parametrize("law", ["mny", "holzapfel"])
def test_fibres_that_bear_tension_only(law):
    """``region.fibre_compression = false``: where the fibre is stretched the stress is the
    paper's law (the closed form above); where it is compressed, the closed form with c2 = 0
    (no fibre term), while the paper's law there carries the fibre's compression."""
    from mvfem.materials import get_set

    p = dict(get_set("MNY-mean" if law == "mny" else "Holzapfel", "anterior").params)
    patch = PatchStress(law, tension_only=True)
    paper = PatchStress(law)
    for q in (patch, paper):
        q.set_parameters(p)
    for e_par, e_perp in ((0.15, 0.05), (0.1, 0.2), (-0.2, 0.1), (-0.3, 0.3)):
        l1, l2 = np.array([1 + e_par]), np.array([1 + e_perp])
        want = closed_form(law, p if e_par >= 0 else {**p, "c2": 0.0}, l1, l2)
        s = patch.cauchy(patch.deformation(e_par, e_perp))
        assert s[0, 0] == pytest.approx(want[0][0], rel=1e-9)
        assert s[1, 1] == pytest.approx(want[1][0], rel=1e-9)
        full = paper.cauchy(paper.deformation(e_par, e_perp))[0, 0]
        if e_par < 0:  # the paper's law: the compressed fibre adds (a negative) stress
            assert full < s[0, 0] - 1e-6 * abs(s[0, 0])
        else:
            assert full == pytest.approx(s[0, 0], rel=1e-12)
