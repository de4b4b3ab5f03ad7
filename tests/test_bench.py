"""`mvfem bench --quick` as a smoke test of the speed-against-error benchmark (issue 7).

The benchmark is run once through the CLI (in-process, ``main(argv) -> int``) and its files
are checked against things it did not compute itself: the disk references are recomputed here
from :mod:`mvfem.reference` (Hencky's closed form, the axisymmetric shooting solution), the
relative errors recomputed from the CSV's values, and the P1 disk errors must fall under mesh
refinement (O(h^2): at least 2x per halving of the mesh size, for both disks).
"""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from mvfem import reference as ref
from mvfem.bench import COLUMNS, _front, fastest_table, read_csv
from mvfem.cli import main


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    from mvfem.outputs import MARKER

    out = tmp_path_factory.mktemp("bench") / "quick"
    out.mkdir()   # as an earlier full benchmark left it (test_earlier_benchmarks_files_go)
    (out / MARKER).touch()
    for name in ("valve_reference_h2_r2.vtu", "bench.md", "notes.txt"):
        (out / name).write_text("earlier\n")
    code = main(["bench", "--quick", "--out", str(out)])
    assert code == 0
    return out


def test_earlier_benchmarks_files_go(quick):
    """A benchmark into an earlier one's directory leaves none of its files: the full sweep's
    reference (``valve_reference_h2_r2.vtu``), which the quick one does not write, would
    otherwise read as this one's (session 55); a file of the user's stays."""
    names = sorted(p.name for p in quick.iterdir() if not p.name.startswith("."))
    assert "valve_reference_h2_r2.vtu" not in names
    assert (quick / "notes.txt").read_text() == "earlier\n"
    assert (quick / "bench.md").read_text() != "earlier\n"
    refs = [n for n in names if n.startswith("valve_reference_")]
    assert len(refs) == 1, names


def test_quick_bench_writes_its_files(quick):
    """bench.csv has the contract's columns and a row per run and quantity of each problem;
    the plot is a non-blank PNG; bench.md names settings."""
    with open(quick / "bench.csv", newline="") as f:
        header = next(csv.reader(f))
    assert header == COLUMNS
    rows = read_csv(quick / "bench.csv")
    assert {r["problem"] for r in rows} == {"foppl", "neo-hookean", "valve"}
    assert all(r["converged"] for r in rows), [r["setting"] for r in rows if not r["converged"]]
    for r in rows:  # the time split adds up to the wall time (rest >= 0)
        parts = r["assembly_s"] + r["linear_solve_s"] + r["contact_s"]
        assert r["rest_s"] >= -1e-9 and math.isclose(parts + r["rest_s"], r["wall_time_s"],
                                                      rel_tol=1e-6, abs_tol=1e-8)
        assert r["dofs"] > 0 and r["newton_iterations"] > 0
    valve = [r for r in rows if r["problem"] == "valve" and r["quantity"] != "reference run"]
    assert {"closed_shape_mean", "coaptation_length_mm", "coaptation_trace_length_mm",
            "anterior_radial_stress_p95_Pa"} <= {r["quantity"] for r in valve}
    assert all(r["contact_s"] > 0 for r in valve)
    png = (quick / "bench_pareto.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    md = (quick / "bench.md").read_text()
    assert "fastest to 1.0%" in md and "h1 P1" in md


def test_disk_errors_against_independent_references_fall_with_refinement(quick):
    """The CSV's reference values are Hencky's and the shooting solution's, its errors are
    |value - reference| / reference, and the P1 errors fall at least twofold from h 2 to 1 mm
    (and from 1 to 0.7 mm for the neo-Hookean disk, at least 1.4x: h^2 would give 2x)."""
    rows = read_csv(quick / "bench.csv")
    expected = {"foppl": ref.foppl_hencky(0.5).centre_deflection(10.0, 1.0, 4e5, 1.0),
                "neo-hookean": ref.axisymmetric_inflation(ref.neo_hookean(20e3), 3000.0, 10.0,
                                                          1.0).centre_deflection}
    for prob, w in expected.items():
        sel = [r for r in rows if r["problem"] == prob]
        for r in sel:
            assert r["reference"] == pytest.approx(w, rel=1e-5)
            assert r["rel_error"] == pytest.approx(abs(r["value"] - w) / w, rel=1e-4, abs=1e-9)
        p1 = {r["mesh_size_mm"]: r["rel_error"] for r in sel
              if r["degree"] == 1 and r["solver"] == "lu"}
        print(f"\n{prob}: P1 relative error by mesh size {p1}")
        assert p1[1.0] < p1[2.0] / 2
        if 0.7 in p1:
            assert p1[0.7] < p1[1.0] / 1.4
        assert p1[1.0] < 0.01  # what a 10 mm disk at 1 mm gives with O(h^2) (README)


def test_valve_errors_are_against_the_finest_run(quick):
    """The valve's finest run, the 5 mm valve refined once (nested), is the reference: its
    closed shape is 0 from itself, so it has no error rows. It has four times the triangles of
    the 5 mm run (each split in four), a count the bench does not compute. The coarser runs'
    shape errors are distances of a few tenths of a mm (0 < mean <= p95 <= Hausdorff, relative
    to the largest displacement)."""
    rows = read_csv(quick / "bench.csv")
    valve = [r for r in rows if r["problem"] == "valve"]
    ref_rows = [r for r in valve if r["quantity"] == "reference run"]
    assert [(r["setting"], r["mesh_size_mm"], r["refine"]) for r in ref_rows] == \
        [("h5 r1 P1", 5.0, 1)]
    h5 = next(r for r in valve if r["setting"] == "h5 P1")
    assert h5["refine"] == 0 and ref_rows[0]["cells"] == 4 * h5["cells"]
    assert "h5 r1 P1" in (quick / "bench.md").read_text()
    for setting in ("h5 P1", "h6 P1"):
        q = {r["quantity"]: r for r in valve if r["setting"] == setting}
        mean, p95, haus = (q[f"closed_shape_{k}"]["value"] for k in ("mean", "p95", "hausdorff"))
        assert 0 < mean <= p95 <= haus < 10.0
        assert q["closed_shape_mean"]["rel_error"] == pytest.approx(
            mean / q["closed_shape_mean"]["reference"])


def test_fastest_table_and_front_on_made_up_rows():
    """The table picks the fastest run within each threshold, the front the non-dominated
    points."""
    rows = [{"problem": "p", "quantity": "q", "setting": s, "converged": True,
             "rel_error": e, "wall_time_s": t}
            for s, e, t in (("a", 2e-2, 1.0), ("b", 9e-3, 3.0), ("c", 8e-3, 2.0),
                            ("d", 5e-4, 9.0), ("e", 4e-4, 20.0))]
    table = fastest_table(rows)
    line = next(ln for ln in table.splitlines() if ln.startswith("| p |"))
    assert "c: 2.00 s" in line and "d: 9.00 s" in line and "4.00e-04 (e)" in line
    pts = [(r["rel_error"], r["wall_time_s"]) for r in rows]
    assert sorted(_front(pts)) == [0, 2, 3, 4]
    assert np.all(np.diff([pts[i][1] for i in _front(pts)]) < 0)
