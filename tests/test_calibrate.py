"""mvfem calibrate (issue 9, item 2): bad input through the CLI, and the synthetic truth."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import run_child
from mpi4py import MPI

import mvfem

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "mvfem" / "data" / "demo.toml"
serial = pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="spawns its own process per case")


def _env():
    from test_scripts import _env as env

    return env()


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A small closed-looking surface with leaflet labels, near the demo valve (no solve)."""
    from mvfem.meshes import write_surface

    d = tmp_path_factory.mktemp("ref")
    x = np.array([[-10.0, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]])
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    write_surface(d / "near.vtu", x, tri, cell_data={"leaflet": np.array([1, 2])})
    write_surface(d / "far.vtu", x + [80.0, 0, 0], tri, cell_data={"leaflet": np.array([1, 2])})
    write_surface(d / "metres.vtu", 1e-3 * x, tri, cell_data={"leaflet": np.array([1, 2])})
    return d


def _run(*args, cwd):
    return run_child([sys.executable, "-m", "mvfem.cli", "calibrate", str(DEMO), *args],
                     capture_output=True, text=True, env=_env(), cwd=cwd, timeout=120)


FIT = "chordae.marginal.length_factor"


@serial
@pytest.mark.parametrize("case, args, words", [
    ("missing", ["--reference", "nope.vtu", "--fit", FIT], "no such file"),
    ("far", ["--reference", "{far}", "--fit", FIT], "does not overlap"),
    ("unknown key", ["--reference", "{near}", "--fit", "chordae.marginal.lenght_factor"],
     "unknown key"),
    ("not numeric", ["--reference", "{near}", "--fit", "title"], "--fit title"),
    ("empty bounds", ["--reference", "{near}", "--fit", FIT, "--bounds", "1.3:0.9"],
     "no value satisfies it"),
    ("start outside", ["--reference", "{near}", "--fit", FIT, "--bounds", "0.9:1.3",
                       "--start", "1.5"], "outside the bounds"),
    ("bounds count", ["--reference", "{near}", "--fit", f"{FIT},chordae.basal.length_factor",
                      "--bounds", "0.9:1.3,1:1.2,1:2"], "3 ranges for 2"),
    ("grid too big", ["--reference", "{near}", "--fit", f"{FIT},chordae.basal.length_factor",
                      "--grid", "6"], "6^2 + 1 = 37"),
    ("grid of one", ["--reference", "{near}", "--fit", FIT, "--grid", "1"], "2 or more"),
    # (session 62: these two were refused after the first solve, the earlier calibration in
    # --out already removed)
    ("metres", ["--reference", "{metres}", "--fit", FIT], "are its coordinates in mm?"),
    ("bounds the scene refuses", ["--reference", "{near}", "--fit", FIT, "--bounds=-1:1",
                                  "--start", "0.5"],
     f"--bounds -1:1: {FIT} = -1 is not a value the scene takes (must be positive"),
])
def test_bad_input_exits_2_with_one_line(tmp_path, reference, case, args, words):
    """Each bad input: exit code 2, one line on stderr naming what is wrong, nothing written."""
    args = [a.format(far=reference / "far.vtu", near=reference / "near.vtu",
                     metres=reference / "metres.vtu") for a in args]
    r = _run(*args, "--out", str(tmp_path / "out"), cwd=tmp_path)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, r.stderr
    assert len(lines) == 1 and lines[0].startswith("mvfem: error:"), r.stderr
    assert words in lines[0]
    assert not (tmp_path / "out").exists()


@serial
def test_an_input_error_in_an_evaluation_leaves_no_directory(tmp_path, reference):
    """The checks before the output directory pass, then the first evaluation's model is an
    input error (a fibre direction along the disk's normal): exit code 2, one line, and the
    directory with its ``evals/`` made meanwhile removed again (until session 60 left holding
    the markers alone)."""
    (tmp_path / "disk.toml").write_text(
        'title = "disk"\n[mesh]\ngenerator = "disk"\nradius = 10.0\nsize = 2.5\n'
        '[fibres]\ndirection = [0, 0, 1]\n[[region]]\nlaw = "mny"\nparams = "MNY-mean"\n')
    r = run_child([sys.executable, "-m", "mvfem.cli", "calibrate", "disk.toml", "--reference",
                   str(reference / "near.vtu"), "--fit", "load.pressure", "--bounds",
                   "1000:2000", "--out", "out"],
                  capture_output=True, text=True, env=_env(), cwd=tmp_path, timeout=120)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, r.stderr
    assert len(lines) == 1 and "fibres.direction" in lines[0], r.stderr
    assert not (tmp_path / "out").exists()


def test_a_calibration_whose_best_run_stopped_short_says_so(tmp_path, reference):
    """Every evaluation stopped at solver.max_steps = 20 (the demo at 5 mm): the result line
    is followed by one saying that the best evaluation did not converge and how many did (it
    read as a calibration like any other, session 62)."""
    from mvfem.calibrate import calibrate

    base = mvfem.load_scene(DEMO).with_changes({"mesh.size": 5.0, "solver.max_steps": 20})
    said = []
    res = calibrate(base, reference / "near.vtu", [FIT], tmp_path / "out",
                    bounds=[(0.9, 1.2)], max_evals=2, say=said.append)
    assert not res["converged"] and res["evaluations"] == 2
    assert said[-1].startswith(f"  the best evaluation ({res['best_evaluation']}) did NOT "
                               "converge (equilibrium residual "), said
    assert said[-1].endswith("0 of 2 evaluations converged (evaluations.csv)")


@pytest.mark.slow
def test_synthetic_truth(shared_tmp):
    """Close the demo valve at mesh size 4 mm with marginal length factor 1.1; write its closed
    leaflets as the reference; calibrate from 1.0 within 0.9:1.3. The fitted factor is the
    truth within 0.02 and the mean distance drops below 0.3 x the start's. (Not 0.2 x, as
    until session 41: the closure is path-dependent, and the solves at factors within 0.012
    of the truth's land 0.145-0.232 mm from its state (0 at 1.1 itself), against 0.71 mm at
    the start; the best of them, 0.145 mm, missed 0.2 x by 2 %. README, Calibration.)"""
    sys.path.insert(0, str(ROOT / "scripts"))
    from valve_refinement import closed_surface

    from mvfem.calibrate import calibrate

    base = mvfem.load_scene(DEMO).with_changes({"mesh.size": 4.0})
    truth = mvfem.solve(base.with_changes({FIT: 1.1}), out=shared_tmp / "truth", progress=False)
    assert truth.converged
    ref = shared_tmp / "truth" / "closed.vtu"
    closed_surface(truth, ref)
    res = calibrate(base, ref, [FIT], shared_tmp / "cal", bounds=[(0.9, 1.3)], start=[1.0],
                    max_evals=25, say=print)
    fitted = res["fitted"][FIT]
    before, after = res["error_before_mm"]["mean_abs_error_mm"], \
        res["error_after_mm"]["mean_abs_error_mm"]
    print(json.dumps({k: res[k] for k in ("fitted", "error_before_mm", "error_after_mm",
                                          "evaluations", "time_s", "held_apart")}))
    assert abs(fitted - 1.1) < 0.02
    assert after < 0.3 * before
    rows = (shared_tmp / "cal" / "evaluations.csv").read_text().splitlines()
    assert len(rows) == res["evaluations"] + 1
    assert "reference" in res["held_apart"]  # truth/summary.json sits next to the reference


@pytest.mark.slow
def test_synthetic_truth_per_leaflet(shared_tmp):
    """Two factors at once: the marginal chords of each leaflet get their own length factor
    through a ``[[chordae.edit]]`` per leaflet. Truth: anterior 1.12, posterior 1.05 at mesh
    size 4 mm (neither on the grid); calibrated from (1, 1) within 0.9:1.3 with a 7 x 7 grid
    first, then Nelder-Mead from its best point. Each fitted factor is its truth within 0.03
    and the mean distance drops well below the start's. (Nelder-Mead alone from (1, 1) ends
    in a local minimum: README, Calibration.)"""
    sys.path.insert(0, str(ROOT / "scripts"))
    from valve_refinement import closed_surface

    from mvfem.calibrate import calibrate

    keys = ["chordae.edit.0.length_factor", "chordae.edit.1.length_factor"]
    base = mvfem.load_scene(DEMO).with_changes({
        "mesh.size": 4.0,
        "chordae.edit": [{"leaflet": "anterior", "family": "marginal", "length_factor": 1.0},
                         {"leaflet": "posterior", "family": "marginal", "length_factor": 1.0}]})
    truth_factors = (1.12, 1.05)
    truth = mvfem.solve(base.with_changes(dict(zip(keys, truth_factors))),
                        out=shared_tmp / "truth2", progress=False)
    assert truth.converged
    ref = shared_tmp / "truth2" / "closed.vtu"
    closed_surface(truth, ref)
    res = calibrate(base, ref, keys, shared_tmp / "cal2", bounds=[(0.9, 1.3)] * 2,
                    start=[1.0, 1.0], max_evals=80, grid=7, say=print)
    print(json.dumps({k: res[k] for k in ("fitted", "error_before_mm", "error_after_mm",
                                          "evaluations", "time_s", "held_apart")}))
    for key, want in zip(keys, truth_factors):
        assert abs(res["fitted"][key] - want) < 0.03, (key, res["fitted"])
    before, after = res["error_before_mm"]["mean_abs_error_mm"], \
        res["error_after_mm"]["mean_abs_error_mm"]
    assert after < 0.2 * before


def test_a_shorter_calibration_into_the_same_directory_keeps_none_of_the_earlier(tmp_path,
                                                                                reference):
    """Three evaluations, then one into the same directory: only the second calibration's
    evaluation is left in ``evals/`` (until session 55 the first one's ``001`` and ``002``
    stayed beside it), and a file of the user's in an evaluation's directory is kept."""
    from mvfem.calibrate import calibrate

    base = mvfem.load_scene(DEMO).with_changes({"mesh.size": 6.0})
    kw = dict(bounds=[(0.9, 1.3)], start=[1.0])
    out = tmp_path / "cal"
    first = calibrate(base, reference / "near.vtu", [FIT], out, max_evals=3, **kw)
    assert first["evaluations"] == 3
    assert sorted(p.name for p in (out / "evals").iterdir()) == ["000", "001", "002"]
    (out / "evals" / "002" / "notes.txt").write_text("mine\n")
    second = calibrate(base, reference / "near.vtu", [FIT], out, max_evals=1, **kw)
    assert second["evaluations"] == 1
    assert sorted(p.name for p in (out / "evals").iterdir()) == ["000", "002"]
    assert [p.name for p in (out / "evals" / "002").iterdir()] == ["notes.txt"]
    rows = (out / "evaluations.csv").read_text().splitlines()
    assert len(rows) == 2
