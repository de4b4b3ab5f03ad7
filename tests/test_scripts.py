"""Scripts under scripts/ run as users run them: under mpirun, as a subprocess (smoke tests)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import run_child

from mvfem.relaunch import without_mpi_job

ROOT = Path(__file__).resolve().parents[1]


def _mpirun(n: int) -> list[str]:
    exe = shutil.which("mpirun")
    if exe is None:
        pytest.fail("mpirun is not installed (make setup installs openmpi-bin)")
    return [exe, "--oversubscribe", "-n", str(n)]


def _env():
    # a pytest inside mpirun, or an MPI singleton's child (pytest-xdist's workers), must not
    # hand its MPI environment to the child
    return without_mpi_job(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                           OPENBLAS_NUM_THREADS="1")


def test_biaxial_figures(tmp_path):
    out = tmp_path / "figs"
    r = run_child([*_mpirun(2), sys.executable, str(ROOT / "scripts" / "biaxial_figures.py"),
                   str(out)], capture_output=True, text=True, env=_env(), timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (out / "biaxial.csv").stat().st_size > 100_000
    assert (out / "biaxial_anterior.png").exists() and (out / "biaxial_posterior.png").exists()


def test_solver_options_coarse(tmp_path):
    r = run_child([*_mpirun(2), sys.executable, str(ROOT / "scripts" / "solver_options.py"),
                   "2.5"], capture_output=True, text=True, env=_env(), timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "lu: 11 converged" in r.stdout and "iterative: 11 converged" in r.stdout


def test_scaling_script_on_two_ranks(tmp_path):
    """scripts/scaling.py (issue 7) under mpirun -n 2 on a coarse disk: one JSON record with the
    process count and a converged run whose centre deflection is the axisymmetric solution's
    to the coarse mesh's error (2 % at 2 mm, README Speed against error)."""
    import json

    from mvfem import reference as ref

    rec = tmp_path / "scaling.jsonl"
    r = run_child([*_mpirun(2), sys.executable, str(ROOT / "scripts" / "scaling.py"),
                   "--case", "disk", "--size", "2", "--record", str(rec)],
                  capture_output=True, text=True, env=_env(), timeout=300,
                  stdin=subprocess.DEVNULL, check=False)
    assert r.returncode == 0, r.stderr[-2000:]
    row = json.loads(rec.read_text())
    assert row["processes"] == 2 and row["converged"] and row["cells"] > 100
    w = ref.axisymmetric_inflation(ref.neo_hookean(20e3), 3000.0, 10.0, 1.0).centre_deflection
    assert abs(row["centre_mm"][2] - w) / w < 0.03


def test_scaling_script_refuses_bad_input(tmp_path):
    """scripts/scaling.py: ``--all`` does not append to (and table) a record that exists, and a
    case it cannot run (an unknown one, a refined disk) is refused; each with one line and exit
    code 2, before any run starts."""
    old = tmp_path / "old.jsonl"
    old.write_text('{"case": "disk"}\n')
    script = str(ROOT / "scripts" / "scaling.py")
    for args in (["--all", "--record", str(old)],
                 ["--all", "--cases", "cube:1", "--record", str(tmp_path / "a.jsonl")],
                 ["--all", "--cases", "disk:1:1", "--record", str(tmp_path / "b.jsonl")],
                 ["--case", "disk", "--refine", "1"]):
        r = run_child([sys.executable, script, *args], capture_output=True, text=True,
                      env=_env(), timeout=120, check=False)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, (args, r.stderr)
        assert r.stdout == ""
    assert old.read_text() == '{"case": "disk"}\n'
    assert not (tmp_path / "a.jsonl").exists() and not (tmp_path / "b.jsonl").exists()


def test_coaptation_trace_script_serial_and_on_two_ranks(tmp_path):
    """scripts/coaptation_trace.py on the 5 mm demo, alone and under mpirun -n 2: one
    converged row each, both leaflets' continuous lengths in (0, 20) mm, the stepped mean the
    mean of its leaflets, and the continuous lengths of the two runs within 0.05 mm of each
    other (their paths differ by roundoff; the measure is continuous). Bad ``--meshes`` and an
    existing ``--out`` are refused with one line and exit code 2."""
    script = str(ROOT / "scripts" / "coaptation_trace.py")
    rows = []
    for prefix, name in (([], "one.json"), (_mpirun(2), "two.json")):
        out = tmp_path / name
        r = run_child([*prefix, sys.executable, script, "--meshes", "5", "--out", str(out)],
                      capture_output=True, text=True, env=_env(), timeout=300,
                      stdin=subprocess.DEVNULL, check=False)
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
        (row,) = json.loads(out.read_text())
        assert row["converged"] and row["cells"] > 100
        assert all(0.0 < v < 20.0 for v in row["trace_per_leaflet_mm"].values())
        assert row["coaptation_length_mm"] == pytest.approx(
            np.mean(list(row["stepped_per_leaflet_mm"].values())))
        assert "| 5 mm |" in r.stdout
        rows.append(row)
    for leaflet, v in rows[0]["trace_per_leaflet_mm"].items():
        assert abs(rows[1]["trace_per_leaflet_mm"][leaflet] - v) < 0.05
    for args in (["--meshes", "5x"], ["--meshes", "5", "--out", str(tmp_path / "one.json")]):
        r = run_child([sys.executable, script, *args], capture_output=True, text=True,
                      env=_env(), timeout=120, check=False)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, (args, r.stderr)


def test_hard_cases_script_two_cases(tmp_path):
    """scripts/hard_cases.py (issue 7) on two quick cases: the flat disk converges, the folded
    imported valve is refused with one line; the table says so."""
    r = run_child([sys.executable, str(ROOT / "scripts" / "hard_cases.py"), "--out",
                   str(tmp_path / "hard"), "--cases", "flat-disk-cp08,inverted"],
                  capture_output=True, text=True, env=_env(), timeout=300, check=False)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    table = (tmp_path / "hard" / "hard_cases.md").read_text()
    assert "| flat-disk-cp08 |" in table and "| converged | 0 |" in table
    assert "| rejected | 2 |" in table and "passes through itself" in table


def test_valve_refinement_nested_levels(tmp_path):
    """scripts/valve_refinement.py --refine 1 on the 5 mm demo valve: the refined level (the
    reference) is closed from the unrefined closure (nested, its coarser steps recorded), the
    unrefined closure is measured against it (a positive distance, below the 5 mm mesh's
    sagitta-scale error of a few tenths of a mm: measured 0.30 mm), and refinement.csv has
    both rows, the refined one with the move the run reports of itself."""
    import csv

    r = run_child([sys.executable, str(ROOT / "scripts" / "valve_refinement.py"), "--out",
                   str(tmp_path / "nested"), "--sizes", "5", "--refine", "1"],
                  capture_output=True, text=True, env=_env(), timeout=600, check=False)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    rows = list(csv.DictReader(open(tmp_path / "nested" / "refinement.csv")))
    assert [(row["refine"], row["start"]) for row in rows] == [("1", "nested"), ("0", "open")]
    fine, coarse = rows
    assert fine["converged"] == coarse["converged"] == "True"
    assert int(fine["coarser_steps"]) > 0 and int(fine["cells"]) == 4 * int(coarse["cells"])
    assert 0.0 < float(coarse["mean_abs_error_mm"]) < 1.0
    assert float(fine["ratio"]) > 1
    # what the refined run reports of itself: the same two closures measured the other way
    # (the refined surface to the unrefined one; at 4 mm 0.252 against 0.206 mm), and nothing
    # for the unrefined run
    moved = float(fine["moved_mean_mm"])
    assert 0.5 < moved / float(coarse["mean_abs_error_mm"]) < 2.0
    assert moved < float(fine["moved_p95_mm"]) and coarse["moved_mean_mm"] == ""


def test_contact_sheets_pressure_on_coarse_grids(tmp_path):
    """scripts/contact_sheets.py at spacings 1 and 0.5 mm (no finer than the contact thickness,
    0.5 mm): the barrier's pressure between two parallel sheets 0.2 mm apart is the same on
    both grids (within 5 %, measured 629 and 635 kPa) and pushes them apart. (Finer grids give
    more: README, "Nested levels".)"""
    r = run_child([sys.executable, str(ROOT / "scripts" / "contact_sheets.py"), "--sizes",
                   "1,0.5", "--gaps", "0.2"],
                  capture_output=True, text=True, env=_env(), timeout=300, check=False)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    rows = [line.split("|") for line in r.stdout.splitlines() if line.startswith("| 1 |")
            or line.startswith("| 0.5 |")]
    p1, p05 = (float(row[2]) for row in rows)
    assert p1 > 0 and abs(p05 - p1) < 0.05 * p1


def test_psd_projection_script_agrees_with_eigh(tmp_path):
    """scripts/psd_projection.py on 0.5 mm grids (a few thousand blocks): the compiled
    projection equals numpy's ``eigh`` one to 1e-12 of each block's largest entry and leaves
    no eigenvalue below -1e-12 of it; the in-place line is printed."""
    r = run_child([sys.executable, str(ROOT / "scripts" / "psd_projection.py"), "--h", "0.5",
                   "--repeats", "1"],
                  capture_output=True, text=True, env=_env(), timeout=300, check=False)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    row = next(line.split("|") for line in r.stdout.splitlines()
               if line.startswith("| ") and line[2].isdigit())
    blocks, diff, low = int(row[1]), float(row[5]), float(row[6])
    assert blocks > 1000 and diff < 1e-12 and low > -1e-12
    assert "saves" in r.stdout


def test_level_costs_script(tmp_path):
    """scripts/level_costs.py on the 5 mm demo refined once: a row per level whose counts agree
    with the run's own records (the coarse level's steps in summary ``coarse_start``, the fine
    level's steps and accepted steps in ``newton_iterations`` and ``load_steps``), times that
    add up (linear solves and assembly within the level's wall time), the finest level's
    history with a row per step; an existing ``--out`` is refused (exit 2). With ``--hot``,
    every accepted step's record: a share of ``|F|^2`` in (0, 1], moves whose sum bounds the
    level's start-to-end distance (the triangle inequality), and at the last step a median
    nodal force below the residual's norm (so the forces are the residual's)."""
    out = tmp_path / "costs.json"
    cmd = [sys.executable, str(ROOT / "scripts" / "level_costs.py"), "--size", "5", "--refine",
           "1", "--pressures", "16", "--history", "--hot", "--out", str(out)]
    r = run_child(cmd, capture_output=True, text=True, env=_env(), timeout=600,
                  check=False)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    (rec,) = json.loads(out.read_text())
    assert rec["converged"] and len(rec["levels"]) == 2
    coarse, fine = rec["levels"]
    assert coarse["steps"] == rec["coarse_start"]["steps"]
    assert fine["steps"] == rec["newton_iterations"]
    assert fine["steps"] - fine["refused"] == rec["load_steps"]
    assert fine["dofs"] > 3 * coarse["dofs"]
    for lv in rec["levels"]:
        assert 0 < lv["linear_s"] + lv["assembly_s"] <= lv["wall_s"]
        assert len(lv["history"]) == lv["steps"]
        assert sum(not h["accepted"] for h in lv["history"]) == lv["refused"]
        hot = lv["hot"]
        accepted = [i for i, h in enumerate(lv["history"], 1) if h["accepted"]]
        assert [d["step"] for d in hot] == accepted
        assert all(0 < d["top_share"] <= 1 for d in hot)
        assert 0 < lv["start_to_end_mm"] <= sum(d["largest_move_mm"] for d in hot) + 1e-9
        assert hot[-1]["median_force"] <= lv["history"][accepted[-1] - 1]["residual"]
    assert f"| {fine['steps']} | " in r.stdout and "start to end at most" in r.stdout
    cs = rec["coarse_start"]
    assert cs["used"] and cs["scale"] == 1.0 and "unfolded" not in cs
    assert f"| open | {coarse['dofs']} | " in r.stdout
    assert f"| moved | {fine['dofs']} | " in r.stdout
    again = run_child(cmd, capture_output=True, text=True, env=_env(), timeout=600,
                      check=False)
    assert again.returncode == 2 and "exists" in again.stderr


def test_tolerance_error_script(tmp_path):
    """scripts/tolerance_error.py on the 5 mm demo refined once at 16 kPa: the run at the
    looser tolerance takes the default run's path through the coarser level to the step (the
    coarser levels keep the default tolerance) and no more finest steps; both end within 10 x
    their tolerance of the load (the run's own convergence rule); the looser closure is within
    0.02 mm of the default one (the 5 mm mesh's own error against its refinement is 0.3 mm)
    and its reported distances are the nodes' (rms at most the largest). An existing
    ``--out`` is refused (exit 2)."""
    out = tmp_path / "tol.json"
    cmd = [sys.executable, str(ROOT / "scripts" / "tolerance_error.py"), "--size", "5",
           "--refine", "1", "--pressures", "16", "--tolerances", "1e-4", "--out", str(out)]
    r = run_child(cmd, capture_output=True, text=True, env=_env(), timeout=600, check=False)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    ref, loose = json.loads(out.read_text())
    assert ref["tolerance"] == 1e-8 and loose["tolerance"] == 1e-4
    assert ref["converged"] and loose["converged"]
    assert ref["equilibrium_residual"] <= 10 * 1e-8
    assert loose["equilibrium_residual"] <= 10 * 1e-4
    assert len(ref["steps"]) == len(loose["steps"]) == 2
    assert loose["steps"][0] == ref["steps"][0] and loose["steps"][1] <= ref["steps"][1]
    assert 0 <= loose["rms_mm"] <= loose["max_mm"] < 0.02
    assert "max_mm" not in ref
    assert f"| 16 | 0.0001 | {loose['steps'][0]} + {loose['steps'][1]} |" in r.stdout
    again = run_child(cmd, capture_output=True, text=True, env=_env(), timeout=600,
                      check=False)
    assert again.returncode == 2 and "exists" in again.stderr and "Traceback" not in again.stderr


def test_level_variants_script(tmp_path):
    """scripts/level_variants.py on the 5 mm demo refined once at 16 kPa: the first variant,
    the control as it is, takes the finest steps of the plain run of that scene (its own
    ``newton_iterations``: the same start and path); a variant capped at 5 steps stops there,
    not converged (the fields reach the variant); after it, the first variant repeated takes
    its steps again to its closure, node for node (the state and the matrix made anew: on the
    room the first run grew, the repeat took 75 steps against 72; without the state set back
    the capped variant started at the first one's closure and took none). A field
    PseudoTransient lacks, and an existing ``--out``, exit 2 with one line."""
    import mvfem
    from mvfem.run import solve

    scene = mvfem.load_scene(ROOT / "mvfem" / "data" / "demo.toml").with_changes(
        {"mesh.size": 5, "mesh.refine": 1})
    plain = solve(scene, progress=False, write=False)
    out = tmp_path / "variants.json"
    cmd = [sys.executable, str(ROOT / "scripts" / "level_variants.py"), "--size", "5",
           "--refine", "1", "--pressures", "16", "--out", str(out),
           "base:", "short:max_steps=5", "again:"]
    r = run_child(cmd, capture_output=True, text=True, env=_env(), timeout=600, check=False)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    base, short, again = json.loads(out.read_text())
    assert base["converged"] and base["steps"] == plain.summary["newton_iterations"]
    assert short["steps"] == 5 and not short["converged"] and short["options"] == \
        {"max_steps": 5}
    assert again["converged"] and again["steps"] == base["steps"]
    assert again["refused"] == base["refused"]
    assert again["distance_mm"] == again["rms_mm"] == 0.0
    assert 0.0 < short["rms_mm"] <= short["distance_mm"]
    assert f"| 16 | again | {base['steps']} | " in r.stdout
    for bad, what in ((cmd, "exists"), (cmd[:2] + ["x:foo=1"], "no field 'foo'")):
        e = run_child(bad, capture_output=True, text=True, env=_env(), timeout=600,
                      check=False)
        assert e.returncode == 2 and what in e.stderr and "Traceback" not in e.stderr


def test_level_costs_names_how_each_level_started():
    """level_costs.starts reads summary ``coarse_start`` (the finest level's start, its
    ``coarser`` the next level's) into one label per level, coarsest first, and leaves the
    column blank where the solves are not one a level."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("level_costs",
                                                  ROOT / "scripts" / "level_costs.py")
    lc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(lc)
    rec = {"levels": [{}] * 4, "coarse_start": {
        "used": True, "scale": 0.8, "coarser": {
            "used": True, "scale": 1.0, "unfolded": 1, "coarser": {"used": False}}}}
    assert lc.starts(rec) == ["open", "open (refused)", "smoothed (1)", "x 0.8"]
    assert lc.starts({"levels": [{}]}) == ["open"]
    assert lc.starts({**rec, "levels": [{}] * 5}) == [""] * 5


def test_symmetric_tangent_script(tmp_path):
    """scripts/symmetric_tangent.py on the 5 mm demo refined once: a row per weight, where the
    LU and LDL^T updates differ by less than 5 % at the sequenced start's weight (1e4: there
    ``k M`` dominates the tangent's skew part) and both descend (positive cosines with -F)."""
    r = run_child([sys.executable, str(ROOT / "scripts" / "symmetric_tangent.py"),
                   "--size", "5", "--refine", "1", "--repeats", "1", "--weights", "1e4,1"],
                  capture_output=True, text=True, env=_env(), timeout=600, check=False)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    rows = [line.split("|") for line in r.stdout.splitlines()
            if line.startswith("| ") and line[2].isdigit()]
    assert [float(row[1]) for row in rows] == [1e4, 1.0]
    assert float(rows[0][5]) < 5e-2
    for row in rows:
        assert all(float(c) > 0 for c in row[6].split("/"))


def test_contact_corrugation_script():
    """scripts/contact_corrugation.py: on a sheet of 2 mm triangles, 0.42 mm below the node
    (contact thickness 0.5 mm), the sampled positions include a vertex, where the six
    triangles around it are each at 0.42 mm and no other is within 0.5 mm (six barriers), and
    a triangle's centroid, 0.577 mm from the other triangles' edges sideways (one barrier):
    the least and greatest sums are b(h) and 6 b(h) of IPC's barrier, written out here.
    Bad numbers are refused with one line and exit code 2."""
    import math

    r = run_child([sys.executable, str(ROOT / "scripts" / "contact_corrugation.py"), "--sizes",
                   "2", "--heights", "0.42", "--samples", "4"],
                  capture_output=True, text=True, env=_env(), timeout=120, check=False)
    assert r.returncode == 0, r.stderr[-2000:]
    row = next(ln for ln in r.stdout.splitlines() if ln.startswith("| 2 | 0.42 |"))
    least, most, _ = (float(v) for v in row.split("|")[4].split("/"))
    h, delta = 0.42, 0.5
    b = -(16e3 / delta) * (h - delta) ** 2 * math.log(h / delta)
    assert least == pytest.approx(b, rel=1e-3) and most == pytest.approx(6 * b, rel=1e-3)
    bad = run_child([sys.executable, str(ROOT / "scripts" / "contact_corrugation.py"),
                     "--heights", "0.6"], capture_output=True, text=True, env=_env(),
                    timeout=120, check=False)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1


def test_path_spread_script(tmp_path):
    """scripts/path_spread.py closes one repaired scene along two paths (ramp_steps 10 and
    20, the 5 mm pathological valve with the 36 mm ring, about 9 s) and prints a row a run and
    their spread, which is the largest minus the smallest of the runs it wrote; bad input is
    one line and exit code 2, an existing ``--out`` among it (left as it was)."""
    out = tmp_path / "spread.json"
    scene = ROOT / "scripts" / "scenes" / "valve_pathological.toml"
    cmd = [sys.executable, str(ROOT / "scripts" / "path_spread.py"), str(scene), "--repair",
           str(ROOT / "scripts" / "scenes" / "repairs" / "ring_d36.toml"), "--set",
           "mesh.size=5", "--ramp-steps", "10,20", "--out", str(out)]
    r = run_child(cmd, capture_output=True, text=True, env=_env(), timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = [line for line in r.stdout.splitlines() if line.startswith("| with-pressure")]
    assert len(rows) == 2
    d = json.loads(out.read_text())
    assert [x["ramp_steps"] for x in d["runs"]] == [10, 20]
    assert all(x["converged"] for x in d["runs"])
    for k in ("coaptation_length_mm", "coaptation_trace_length_mm", "tenting_height_mm"):
        vals = [x[k] for x in d["runs"]]
        assert d["spread"][k] == pytest.approx(max(vals) - min(vals))
    bad = run_child([sys.executable, str(ROOT / "scripts" / "path_spread.py"), str(scene),
                     "--motion", "sideways"], capture_output=True, text=True, env=_env(),
                    timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == [
        "path_spread: --motion: 'sideways': each must be with-pressure or before-pressure"]
    written = out.read_text()
    again = run_child(cmd, capture_output=True, text=True, env=_env(), timeout=120)
    assert again.returncode == 2 and out.read_text() == written
    assert again.stderr.strip().splitlines() == [f"path_spread: --out {out}: exists; choose "
                                                 "another name"]


def test_path_spread_stopped_by_a_signal_keeps_the_runs_done(tmp_path, monkeypatch, capsys):
    """A Ctrl-C or SIGTERM that stops path_spread.py's second run (``mvfem.solve`` raises
    ``mvfem.Interrupted``, as a signal makes it: tests/test_interrupt.py) prints one line
    and the first run's row, writes the done run to ``--out`` marked interrupted, and exits
    with the signal's code, no traceback."""
    import importlib.util
    from types import SimpleNamespace

    import mvfem

    spec = importlib.util.spec_from_file_location("path_spread",
                                                  ROOT / "scripts" / "path_spread.py")
    ps = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ps)
    calls = []

    def fake_solve(scene, progress=True, write=True):
        calls.append(scene.data["solver"]["ramp_steps"])
        if len(calls) == 2:
            raise mvfem.Interrupted("stopped by SIGTERM after 12 pseudo-time steps",
                                    exit_code=143)
        return SimpleNamespace(summary={"converged": True, "newton_iterations": 40,
                                        "max_penetration_mm": 0.0,
                                        "valve": {"coaptation_length_mm": 7.5}})

    monkeypatch.setattr(mvfem, "solve", fake_solve)
    out = tmp_path / "spread.json"
    code = ps.main([str(ROOT / "scripts" / "scenes" / "valve_pathological.toml"),
                    "--ramp-steps", "10,20,30", "--out", str(out)])
    err = capsys.readouterr()
    assert code == 143 and calls == [10, 20]
    assert err.err.strip().splitlines()[-1] == (
        "path_spread: stopped by SIGTERM after 12 pseudo-time steps; 1 of 3 runs done")
    rows = [line for line in err.out.splitlines() if line.startswith("| with-pressure")]
    assert len(rows) == 1 and "| 40 |" in rows[0]
    d = json.loads(out.read_text())
    assert d["interrupted"] is True and [r["ramp_steps"] for r in d["runs"]] == [10]


def test_refine_surface_script(tmp_path):
    """scripts/refine_surface.py on the demo's valve at 5 mm split once (three closures, about
    12 s): the smooth split's new nodes lie closer to the generator's own surface than the
    midpoints, and its closed leaflets closer to the generated valve's closure than those of
    the split on the facets (0.024 against 0.040 mm on average when written); every closure
    converged on the same cells; an existing ``--out`` is one line and exit code 2,
    the file left as it was."""
    out = tmp_path / "split.json"
    cmd = [sys.executable, str(ROOT / "scripts" / "refine_surface.py"), "--size", "5",
           "--refine", "1", "--out", str(out)]
    r = run_child(cmd, capture_output=True, text=True, env=_env(), timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = {w["run"]: w for w in json.loads(out.read_text())}
    assert set(rows) == {"generated", "facets", "smooth"}
    assert all(w["converged"] for w in rows.values())
    assert len({w["cells"] for w in rows.values()}) == 1
    f, s = rows["facets"], rows["smooth"]
    assert s["new_nodes_off_surface_mean_mm"] < f["new_nodes_off_surface_mean_mm"] / 4
    assert s["mean_abs_error_mm"] < 0.8 * f["mean_abs_error_mm"]
    assert s["p95_error_mm"] < f["p95_error_mm"]
    written = out.read_text()
    again = run_child(cmd, capture_output=True, text=True, env=_env(), timeout=120)
    assert again.returncode == 2 and out.read_text() == written
    assert again.stderr.strip().splitlines() == [f"refine_surface.py: --out {out}: exists; "
                                                 "choose another name"]
