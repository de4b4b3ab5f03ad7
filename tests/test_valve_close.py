"""Closure of the parametric valve (slow: one to four minutes per run; pytest -m slow)."""

from __future__ import annotations

import pytest


@pytest.mark.slow
def test_valve_without_contact_closes_to_16_kpa(tmp_path):
    """The coarse built-in valve (size 2 mm), chordae on, contact off, reaches 16 kPa with an
    equilibrium residual below 10 x the tolerance; the closed leaflets then cover the annulus
    seen along the axis to within 1 % (they may overlap: no contact), the chordae carry load
    and the outputs (maps, chordae.csv) are written."""
    import mvfem

    scene = mvfem.load_scene(
        __import__("pathlib").Path(mvfem.__file__).parent / "data" / "demo.toml"
    ).with_changes({"contact.enabled": False})
    r = mvfem.solve(scene, out=tmp_path / "out", progress=False)
    s = r.summary
    assert s["converged"] and s["equilibrium_residual"] < 1e-7
    v = s["valve"]
    assert v["regurgitant_orifice_area_mm2"] < 0.01 * v["annulus_area_mm2"]
    assert v["chordae_force_N"]["taut"] > 0 and v["chordae_force_N"]["total"] > 0
    for name in ("map_radial_strain.png", "map_radial_stress.png", "chordae.csv"):
        assert (tmp_path / "out" / name).stat().st_size > 0


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 5 open: the demo reaches 16 kPa closed and "
                   "coapting, but removing the pseudo-time stabiliser stalls (residual ~1e-2 "
                   "of the load, a patch next to each commissure still drifting; README "
                   "'Closing the valve')")
def test_demo_valve_closes_competently_with_contact(tmp_path):
    """`mvfem demo`'s scene (chordae and contact on) reaches 16 kPa as an equilibrium; the
    closed leaflets cover the annulus opening (orifice below 1 % of the annulus area), coapt
    over a length within the healthy 3-8 mm of shared/data/README.md (3D TEE, A2-P2), no node
    has reached the other leaflet (smallest distance positive) and contact carries load."""
    import mvfem

    scene = mvfem.load_scene(
        __import__("pathlib").Path(mvfem.__file__).parent / "data" / "demo.toml")
    r = mvfem.solve(scene, out=tmp_path / "out", progress=False)
    s = r.summary
    assert s["converged"], s["stop_reason"]
    v = s["valve"]
    assert v["regurgitant_orifice_area_mm2"] < 0.01 * v["annulus_area_mm2"]
    assert 3.0 <= v["coaptation_length_mm"] <= 8.0
    assert s["contact"]["active_pairs"] > 0 and s["contact"]["min_distance_mm"] > 0
