"""Studies (mvfem/study.py, mvfem/figures.py, mvfem/report.py): cases x parameter sets.

Small clamped disks (136 triangles, about 3 s a run with start-up) stand in for valves. What
the checks compare against: the per-facet values in each run's fields.h5 (percentiles by numpy
here), summary.json of each run, the parameter table read with the csv module, the clock
(runs overlapping in time), file modification times (finished runs not repeated), and a
browser's rendering of the report.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import run_child

from mvfem.cli import main
from mvfem.errors import InputError
from mvfem.study import RESULT_COLUMNS, default_sets, load_study, run_study

ROOT = Path(__file__).resolve().parents[1]

DISK = """title = "clamped disk"
[mesh]
generator = "disk"
radius = 10.0
size = 2.5
[[region]]
law = "mny"
params = "MNY-mean"
[load]
pressure = "16 kPa"
"""

STUDY = """title = "three disks x two sets"
sets = ["CP01", "SVK"]
processes = 2
biaxial = false
map_case = "flat-ref"
[[case]]
name = "r10"
scene = "disk.toml"
[[case]]
name = "r8"
scene = "disk.toml"
set = { mesh.radius = 8.0 }
[[case]]
name = "flat-ref"
scene = "disk.toml"
set = { "load.pressure" = "12 kPa" }
reference = "flat.vtu"
"""


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _write(d: Path, study: str = STUDY, name: str = "study.toml") -> Path:
    d.mkdir(parents=True, exist_ok=True)
    (d / "disk.toml").write_text(DISK)
    (d / name).write_text(study)
    return d / name


def _flat(d: Path) -> None:
    if not (d / "flat.vtu").exists():
        assert main(["mesh", "disk", "--radius", "10", "--size", "2.5",
                     "--out", str(d / "flat.vtu")]) == 0


@pytest.fixture(scope="module")
def disk_study(tmp_path_factory):
    """The 3 x 2 disk study, run once through the CLI (in process) for several tests."""
    d = tmp_path_factory.mktemp("study")
    path = _write(d)
    _flat(d)
    out = d / "out"
    t0 = time.perf_counter()
    code = main(["study", str(path), "--out", str(out)])
    return {"dir": d, "out": out, "code": code, "seconds": time.perf_counter() - t0,
            "study": load_study(path)}


def test_study_runs_every_case_and_set(disk_study):
    out = disk_study["out"]
    assert disk_study["code"] == 0
    rows = _rows(out / "results.csv")
    assert list(rows[0]) == RESULT_COLUMNS
    assert sorted((r["case"], r["set"]) for r in rows) == sorted(
        (c, s) for c in ("r10", "r8", "flat-ref") for s in ("CP01", "SVK"))
    assert all(r["status"] == "converged" and r["converged"] == "true" for r in rows)
    for r in rows:
        d = out / r["run_dir"]
        s = json.loads((d / "summary.json").read_text())
        assert s["converged"] and s["regions"]["membrane"]["set"] == r["set"]
        assert r["anterior_set"] == r["set"] and r["posterior_set"] == ""
        assert float(r["wall_time_s"]) == pytest.approx(s["wall_time_s"], rel=1e-5)
        assert float(r["pressure_Pa"]) == (12e3 if r["case"] == "flat-ref" else 16e3)
        # percentiles: numpy on the per-facet values of fields.h5, and summary.json's
        import h5py

        with h5py.File(d / "fields.h5") as f:
            strain = f["Function/radial_almansi_strain/0"][:].ravel()
            stress = f["Function/radial_cauchy_stress_Pa/0"][:].ravel()
        assert int(r["anterior_cells"]) == len(strain) == s["cells"]
        for name, p in zip(("p5", "p25", "median", "p75", "p95"), (5, 25, 50, 75, 95)):
            assert float(r[f"anterior_radial_strain_{name}"]) == pytest.approx(
                np.percentile(strain, p), rel=1e-5)
            assert float(r[f"anterior_radial_stress_Pa_{name}"]) == pytest.approx(
                np.percentile(stress, p), rel=1e-5)
            assert float(r[f"anterior_radial_stress_Pa_{name}"]) == pytest.approx(
                s["regions"]["membrane"]["radial_cauchy_stress_Pa"][name], rel=1e-5)
        if r["case"] == "flat-ref":
            assert float(r["reference_hausdorff_mm"]) == pytest.approx(
                s["reference"]["hausdorff_mm"], rel=1e-5)
            # against the flat open disk, the Hausdorff distance is the dome's height
            assert float(r["reference_hausdorff_mm"]) == pytest.approx(
                s["max_displacement_mm"], rel=0.02)
        else:
            assert r["reference_mean_abs_error_mm"] == ""
    # the thinner and stiffer sets give what the table says: CP01 (h 0.68 mm) bulges more
    # than SVK (E 400 kPa, h 1 mm)
    disp = {(r["case"], r["set"]): float(r["max_displacement_mm"]) for r in rows}
    assert disp[("r10", "CP01")] > disp[("r10", "SVK")]


def test_runs_ran_in_parallel(disk_study):
    """processes = 2: some two runs overlapped in time (status.json start/finish times)."""
    spans = []
    for st in disk_study["out"].glob("runs/*/*/status.json"):
        s = json.loads(st.read_text())
        spans.append((s["started"], s["finished"]))
    assert len(spans) == 6
    spans.sort()
    assert any(b[0] < a[1] for a, b in zip(spans, spans[1:]))


def test_figures_and_report_exist(disk_study):
    out = disk_study["out"]
    for name in ("box_stress.png", "box_strain.png", "maps_strain.png", "maps_stress.png",
                 "maps_distance.png"):
        assert (out / name).stat().st_size > 20_000, name
    html = (out / "report.html").read_text()
    assert html.count("<table") >= 4 and "flat-ref" in html and "data:image/png;base64," in html
    assert "Closed-state error" in html
    for run_dir in (out / "runs").glob("*/*"):
        assert f'href="runs/{run_dir.parent.name}/{run_dir.name}/"' in html


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        exe = shutil.which(name)
        if exe:
            return exe
    if os.environ.get("CI"):
        pytest.fail("chromium is not installed (make setup installs it)")
    pytest.skip("chromium is not installed (apt-get install chromium; make setup does); "
                "required when CI is set")


def test_report_renders_in_headless_chromium(disk_study, tmp_path):
    exe = _chromium()
    report = (disk_study["out"] / "report.html").resolve()
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--disable-dev-shm-usage", f"--user-data-dir={tmp_path / 'profile'}"]
    shot = tmp_path / "shot.png"
    r = subprocess.run([exe, *flags, f"--screenshot={shot}", "--window-size=1200,2000",
                        report.as_uri()], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and shot.is_file(), r.stderr[-2000:]
    import matplotlib.image as mpimg

    img = mpimg.imread(shot)[..., :3]
    assert img.shape[:2] == (2000, 1200)
    assert img.std() > 0.05  # not a blank page: text, tables and the figures
    # the embedded figures were decoded: many distinct colours (text alone is greyscale)
    sat = img.max(axis=2) - img.min(axis=2)
    assert (sat > 0.2).mean() > 0.01
    dom = subprocess.run([exe, *flags, "--dump-dom", report.as_uri()], capture_output=True,
                         text=True, timeout=120)
    assert dom.returncode == 0
    assert "<table" in dom.stdout and "flat-ref" in dom.stdout and "converged" in dom.stdout


def test_killed_study_resumes_without_repeating(tmp_path):
    """Kill -9 the study after its first finished run: its runs die with it (no orphan goes on
    writing); the same command again makes only the runs that had not finished, and
    results.csv has every run exactly once."""
    study = STUDY.replace("processes = 2", "processes = 1").replace('map_case = "flat-ref"',
                                                                    'map_case = "r10"')
    study = study[:study.index('[[case]]\nname = "flat-ref"')]
    path = _write(tmp_path, study)
    out = tmp_path / "out"
    from test_scripts import _env

    env = _env()
    p = subprocess.Popen([sys.executable, "-m", "mvfem.cli", "study", str(path), "--out",
                          str(out)], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                         text=True, env=env)
    lines = []
    t0 = time.time()
    while time.time() - t0 < 120:
        line = p.stderr.readline()
        lines.append(line)
        if line.startswith("[1/4]"):
            break
    else:
        p.kill()
        pytest.fail("no run finished: " + "".join(lines))
    p.send_signal(signal.SIGKILL)
    p.wait()
    p.stderr.close()
    # no run of the study survives its death (they get SIGTERM from the kernel)
    deadline = time.time() + 15
    while time.time() < deadline:
        alive = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout
        if not alive.strip():
            break
        time.sleep(0.2)
    assert not alive.strip(), alive
    # (a run that SIGTERM caught in its solve wrote the state it reached: still to do)
    done = {s.parent: s.stat().st_mtime_ns for s in out.glob("runs/*/*/summary.json")
            if not json.loads(s.read_text()).get("interrupted")}
    assert 1 <= len(done) < 4
    rows = _rows(out / "results.csv")
    assert len(rows) == 4 and sum(r["status"] == "converged" for r in rows) >= 1
    study_def = load_study(path)
    res = run_study(study_def, out, progress=False, report=False)
    assert res["ran"] == 4 - len(done) and res["skipped"] == len(done)
    assert res["converged"] == 4
    for d, mtime in done.items():
        assert (d / "summary.json").stat().st_mtime_ns == mtime  # not run again
    rows = _rows(out / "results.csv")
    assert sorted((r["case"], r["set"]) for r in rows) == sorted(
        (c, s) for c in ("r10", "r8") for s in ("CP01", "SVK"))
    assert all(r["status"] == "converged" for r in rows)
    # a third time: nothing to do
    assert run_study(study_def, out, progress=False, report=False)["ran"] == 0
    # a changed case is a different run: only its runs are made again
    path.write_text(study.replace("mesh.radius = 8.0", "mesh.radius = 7.0"))
    res = run_study(path, out, progress=False, report=False)
    assert res["ran"] == 2 and res["converged"] == 4
    assert all((d / "summary.json").stat().st_mtime_ns == m for d, m in done.items()
               if d.parent.name == "r10")
    # an edited scene file too: every run of it again
    (tmp_path / "disk.toml").write_text(DISK.replace("16 kPa", "15 kPa"))
    res = run_study(path, out, progress=False, report=False)
    assert res["ran"] == 4 and res["converged"] == 4
    assert {r["pressure_Pa"] for r in _rows(out / "results.csv")} == {"15000"}


FAILING = """sets = ["CP01"]
processes = 2
biaxial = false
[[case]]
name = "good"
scene = "disk.toml"
[[case]]
name = "bad-label"
scene = "two_regions.toml"
"""


def test_failed_run_is_recorded_not_fatal(tmp_path):
    """A run that fails (here: region labels the disk mesh does not have, found when the mesh
    is built, exit code 2 in the run) is a row with its reason; the study goes on, and the
    failure is not repeated unless asked."""
    path = _write(tmp_path, FAILING)
    (tmp_path / "two_regions.toml").write_text(
        DISK.replace('[[region]]\nlaw = "mny"\nparams = "MNY-mean"\n',
                     '[[region]]\nlabel = "anterior"\nlaw = "mny"\nparams = "MNY-mean"\n'
                     '[[region]]\nlabel = "posterior"\nleaflet = "posterior"\nlaw = "mny"\n'
                     'params = "MNY-mean"\n'))
    out = tmp_path / "out"
    res = run_study(path, out, progress=False, report=False)
    assert (res["converged"], res["failed"]) == (1, 1)
    rows = {r["case"]: r for r in _rows(out / "results.csv")}
    bad = rows["bad-label"]
    assert (bad["status"], bad["converged"], bad["exit_code"]) == ("failed", "false", "2"), \
        (bad["reason"], (out / "runs" / "bad-label" / "CP01" / "run.log").read_text())
    assert "is not a label of the mesh" in bad["reason"]
    assert (bad["anterior_set"], bad["posterior_set"]) == ("CP01", "MNY-mean")
    assert rows["good"]["status"] == "converged"
    status = out / "runs" / "bad-label" / "CP01" / "status.json"
    mtime = status.stat().st_mtime_ns
    assert run_study(path, out, progress=False, report=False)["ran"] == 0
    assert status.stat().st_mtime_ns == mtime
    res = run_study(path, out, progress=False, retry_failed=True, report=False)
    assert res["ran"] == 1 and status.stat().st_mtime_ns != mtime


@pytest.mark.parametrize("text, read", [('[1, 2]', None), ('"str"', None), ('{"a": 1', None),
                                        ('{"a": 1}', {"a": 1})])
def test_a_runs_json_that_is_not_an_object_counts_as_none(tmp_path, text, read):
    """A run's summary.json, run.json or status.json is read as a JSON object or not at all:
    a summary.json edited to ``[1, 2]`` made the study's next start an AttributeError
    traceback (session 62); now that run is to do again."""
    from mvfem.study import _read_json

    path = tmp_path / "summary.json"
    path.write_text(text)
    assert _read_json(path) == read


def test_timeout_is_a_failure(tmp_path):
    path = _write(tmp_path, 'sets = ["SVK"]\ntimeout = 0.3\nbiaxial = false\n'
                  '[[case]]\nscene = "disk.toml"\n')
    out = tmp_path / "out"
    res = run_study(path, out, progress=False, report=False)
    assert res["failed"] == 1
    (row,) = _rows(out / "results.csv")
    assert row["case"] == "disk" and "timed out after 0.3 s" in row["reason"]


def test_sets_per_leaflet_on_the_demo_valve():
    """A study set is a name: the anterior region gets the anterior set, the posterior region
    the posterior set of that name, or the posterior MNY-mean where there is none; law,
    parameters and thickness as in materials.csv (read here with the csv module)."""
    with open(ROOT / "mvfem" / "data" / "materials.csv", newline="") as f:
        table = {(r["leaflet"], r["set"]): r for r in csv.DictReader(f)}
    assert default_sets() == [s for (leaf, s) in table if leaf == "anterior"]
    assert len(default_sets()) == 11
    study = load_study({"case": [{"scene": "demo", "set": {"mesh.size": 3.0}}]})
    assert [r.set for r in study.runs] == default_sets()
    from mvfem.scene import load_scene

    for run in study.runs:
        post = run.set if ("posterior", run.set) in table else "MNY-mean"
        assert (run.anterior_set, run.posterior_set) == (run.set, post)
        assert [r["leaflet"] for r in run.regions] == ["anterior", "posterior"]
        scene = load_scene(run.scene).with_changes(run.changes)
        for region, leaflet, name in zip(scene["region"], ("anterior", "posterior"),
                                         (run.set, post)):
            row = table[(leaflet, name)]
            assert region["law"] == row["law"] and region["set"] == name
            assert region["thickness"] == pytest.approx(float(row["thickness_mm"]))
            key = {"mny": "c0", "holzapfel": "c0", "svk": "E"}[row["law"]]
            assert region["params"][key] == pytest.approx(float(row[f"{key}_Pa"]))
        assert scene["mesh"]["size"] == 3.0


@pytest.mark.parametrize("text,words", [
    ('color = 1\n[[case]]\nscene = "disk.toml"\n', ["color", "unknown key"]),
    ('sets = ["CP09"]\n[[case]]\nscene = "disk.toml"\n', ["sets[0]", "CP09", "unknown"]),
    ('sets = ["CP01", "cp01"]\n[[case]]\nscene = "disk.toml"\n', ["sets", "twice"]),
    ('sets = []\n[[case]]\nscene = "disk.toml"\n', ["sets", "expected a list"]),
    ('processes = 0\n[[case]]\nscene = "disk.toml"\n', ["processes", "positive integer"]),
    ('timeout = -1\n[[case]]\nscene = "disk.toml"\n', ["timeout", "positive number"]),
    (f'timeout = 1{"0" * 400}\n[[case]]\nscene = "disk.toml"\n', ["timeout", "positive number"]),
    ('biaxial = "yes"\n[[case]]\nscene = "disk.toml"\n', ["biaxial", "true or false"]),
    ('sets = ["SVK"]\n', ["case", "at least one"]),
    ('[[case]]\nscene = "nowhere.toml"\n', ["case[0].scene", "no such scene file"]),
    ('[[case]]\nname = "a b"\nscene = "disk.toml"\n', ["case[0].name", "directory"]),
    ('[[case]]\nscene = "disk.toml"\n[[case]]\nscene = "disk.toml"\n', ["case[1].name", "twice"]),
    ('[[case]]\nscene = "disk.toml"\nsize = 2\n', ["case[0].size", "unknown key"]),
    ('[[case]]\nscene = "disk.toml"\nset = { mesh.radius = -1.0 }\n',
     ["case[0]", "set CP01", "mesh.radius", "positive"]),
    ('[[case]]\nscene = "disk.toml"\nset = { mesh.colour = 1 }\n', ["case[0]", "mesh.colour"]),
    ('[[case]]\nscene = "disk.toml"\nreference = "none.vtu"\n',
     ["case[0].reference", "no such file"]),
    ('map_case = "x"\n[[case]]\nscene = "disk.toml"\n', ["map_case", "not a case"]),
    ('[[case]\nscene = "disk.toml"\n', ["not valid TOML"]),
])
def test_bad_study_is_one_line_exit_2(tmp_path, capsys, text, words):
    path = _write(tmp_path, text)
    out = tmp_path / "never"
    assert main(["study", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert str(path) in err
    for w in words:
        assert w in err, err
    assert not out.exists()


def test_study_refuses_a_users_directory_and_a_second_study(tmp_path, capsys):
    path = _write(tmp_path, 'sets = ["SVK"]\n[[case]]\nscene = "disk.toml"\n')
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    assert main(["study", str(path), "--out", str(mine)]) == 2
    assert "not written by mvfem" in capsys.readouterr().err
    assert os.listdir(mine) == ["notes.txt"] and (mine / "notes.txt").read_text() == "keep me"
    from mvfem.outputs import prepare_out
    from mvfem.study import _Lock

    out = prepare_out(tmp_path / "busy")
    lock = _Lock(out / ".study.lock")
    try:
        with pytest.raises(InputError, match="another mvfem study is running"):
            run_study(path, out, progress=False)
    finally:
        lock.release()


@pytest.mark.slow
def test_paper_figures_script_quick(tmp_path):
    """scripts/paper_figures.py --quick under mpirun -n 2: two generated valves (the default
    annulus and the kaiser_normal1 patient annulus) x two sets at mesh size 5 mm, all figures.
    40-65 s on two shared cores (so under -m slow)."""
    from test_scripts import _env, _mpirun

    out = tmp_path / "paper"
    r = run_child([*_mpirun(2), sys.executable, str(ROOT / "scripts" / "paper_figures.py"),
                   "--out", str(out), "--quick"], capture_output=True, text=True,
                  env=_env(), timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = _rows(out / "results.csv")
    assert sorted((r["case"], r["set"]) for r in rows) == sorted(
        (c, s) for c in ("default", "patient") for s in ("MNY-mean", "SVK"))
    assert all(r["status"] in ("converged", "stopped") for r in rows), rows
    for row in rows:  # valves: both leaflets, with their own sets
        assert int(row["anterior_cells"]) > 0 and int(row["posterior_cells"]) > 0
        assert row["posterior_set"] == row["set"]
        assert row["coaptation_length_mm"] != ""
    for name in ("box_stress.png", "box_strain.png", "maps_strain.png", "maps_stress.png",
                 "biaxial/biaxial_anterior.png", "biaxial/biaxial_posterior.png", "report.html"):
        assert (out / name).stat().st_size > 20_000, name
    # the runs went two at a time although mpirun bound each rank to one core
    assert "2 at a time" in r.stderr


FLAKY = """sets = ["CP01"]
processes = 1
biaxial = false
[[case]]
name = "good"
scene = "disk.toml"
"""


def _flaky_command(tmp_path, monkeypatch, silent_exits: int):
    """Runs start through a wrapper that exits 1 without a word the first ``silent_exits``
    times (what an MPI singleton's start-up does about once in 150 runs), then runs the real
    command."""
    import mvfem.study as study_mod

    counter = tmp_path / "starts"
    counter.write_text("0")
    wrapper = tmp_path / "flaky.py"
    wrapper.write_text(
        "import os, sys\n"
        f"p = {str(counter)!r}\n"
        "n = int(open(p).read()) + 1\n"
        "open(p, 'w').write(str(n))\n"
        f"if n <= {silent_exits}:\n"
        "    os._exit(1)\n"
        "os.execv(sys.executable, [sys.executable] + sys.argv[1:])\n")
    real = study_mod.RunSpec.command
    monkeypatch.setattr(study_mod.RunSpec, "command",
                        lambda self, out: [sys.executable, str(wrapper)] + real(self, out)[1:])
    return counter


def test_silent_start_exit_is_started_again(tmp_path, monkeypatch):
    """Two silent exits at start-up: the run is started again each time and converges. One
    retry more than the wrapper's exits: the real start that follows them can itself exit
    silently (it did in a CI run of session 32, "exit code 1 with no output" after 0.8 s), and
    is then started once more."""
    import mvfem.study as study_mod

    (tmp_path / "w").mkdir()
    counter = _flaky_command(tmp_path / "w", monkeypatch, silent_exits=2)
    monkeypatch.setattr(study_mod, "_RETRIES", 3)
    path = _write(tmp_path, FLAKY)
    res = run_study(path, tmp_path / "out", progress=False, report=False)
    assert (res["converged"], res["failed"]) == (1, 0)
    assert counter.read_text() in ("3", "4")


def test_silent_exits_beyond_the_retries_are_a_failure(tmp_path, monkeypatch):
    """A run that keeps exiting 1 without a word is recorded as failed after the retries, with
    a reason that says so; it is not started forever."""
    (tmp_path / "w").mkdir()
    counter = _flaky_command(tmp_path / "w", monkeypatch, silent_exits=99)
    path = _write(tmp_path, FLAKY)
    res = run_study(path, tmp_path / "out", progress=False, report=False)
    assert (res["converged"], res["failed"]) == (0, 1)
    assert counter.read_text() == "3"
    row = _rows(tmp_path / "out" / "results.csv")[0]
    assert (row["status"], row["exit_code"]) == ("failed", "1")
    assert "exit code 1 with no output" in row["reason"]


def test_results_carry_a_refined_runs_mesh_move(tmp_path):
    """results.csv's ``mesh_move_mean_mm`` and ``mesh_move_p95_mm`` are the run's last
    refinement's move (summary.json ``coarse_start.distance_to_finer_mm``), empty for a run on
    one mesh (run files written here)."""
    from mvfem.outputs import write_json
    from mvfem.study import Case, RunSpec, Study, _spec_record, collect_results

    runs = [RunSpec(case=c, set="MNY-mean", anterior_set="MNY-mean", posterior_set="",
                    scene="x", changes={}, regions=[]) for c in ("fine", "plain")]
    for r in runs:
        d = r.dir(tmp_path)
        d.mkdir(parents=True)
        write_json(_spec_record(r), d / "run.json")
        summary = {"converged": True, "valve": {"coaptation_length_mm": 7.0}}
        if r.case == "fine":
            summary["coarse_start"] = {"cells": 4, "distance_to_finer_mm": {
                "mean_mm": 0.03, "p95_mm": 0.07, "hausdorff_mm": 0.3}}
        write_json(summary, d / "summary.json")
    study = Study(title="", cases=[Case("fine", "x"), Case("plain", "x")], sets=[],
                  processes=1, timeout_s=None, map_case="fine", include_stopped=True,
                  biaxial=False, runs=runs)
    fine, plain = collect_results(study, tmp_path)
    assert (fine["mesh_move_mean_mm"], fine["mesh_move_p95_mm"]) == (0.03, 0.07)
    assert plain["mesh_move_mean_mm"] is None and plain["mesh_move_p95_mm"] is None
    assert fine["coaptation_length_mm"] == 7.0 and fine["status"] == "converged"


def test_study_under_accuracy_runs_each_cases_sets_on_one_mesh(tmp_path, monkeypatch):
    """A study whose cases ask for ``mesh.accuracy``: each case's sets first run to the
    accuracy; the most refinements any set of a case needed is that case's mesh, on which the
    sets that stopped coarser run again without a target; a case without a target runs as
    it is. Run again (resumed), nothing runs. The runs themselves are a stand-in (the files a
    run writes: set CP01 needs one refinement, MNY-mean two on case "a", one on case "b")."""
    from conftest import write_run_files

    import mvfem.study
    from mvfem.study import mesh_line, run_state

    needs = {("a", "CP01"): 1, ("a", "MNY-mean"): 2, ("b", "CP01"): 1, ("b", "MNY-mean"): 1}
    missed = {("a", "MNY-mean")}  # (its run to the accuracy ends at the cap, not met)
    ran = []

    def schedule(study, out, todo, processes, prog, skipped, total, cpus):
        for r in todo:
            assert run_state(r, out) != "done"
            acc = r.changes.get("mesh.accuracy")
            refine = needs.get((r.case, r.set), 0) if acc else r.changes.get("mesh.refine", 0)
            ran.append((r.key, acc, refine))
            write_run_files(r, out, refine, acc, met=(r.case, r.set) not in missed)
        return len(todo)

    monkeypatch.setattr(mvfem.study, "_schedule", schedule)
    acc = {"mesh.size": 7.0, "mesh.refine": 2, "mesh.accuracy": 0.05}
    spec = {"sets": ["CP01", "MNY-mean"], "biaxial": False,
            "case": [{"name": "a", "scene": "demo", "set": acc},
                     {"name": "b", "scene": "demo", "set": acc},
                     {"name": "c", "scene": "demo", "set": {"mesh.size": 7.0}}]}
    res = run_study(spec, tmp_path / "st", progress=False, report=False)
    first = [k for k, a, _ in ran if a]
    assert sorted(first) == ["a/CP01", "a/MNY-mean", "b/CP01", "b/MNY-mean"]
    assert sorted(k for k, a, _ in ran if not a) == ["a/CP01", "c/CP01", "c/MNY-mean"]
    assert ("a/CP01", False, 2) in ran  # (again, on case a's mesh)
    assert res["meshes"] == {
        "a": {"target_mm": 0.05, "refine": 2, "most_refine": 2,
              "needed": {"CP01": 1, "MNY-mean": 2}, "not_met": ["MNY-mean"]},
        "b": {"target_mm": 0.05, "refine": 1, "most_refine": 2,
              "needed": {"CP01": 1, "MNY-mean": 1}, "not_met": []}}
    assert mesh_line(res["meshes"]["a"], " (a)").endswith("; NOT met by MNY-mean")
    assert "NOT met" not in mesh_line(res["meshes"]["b"])
    rows = {(r["case"], r["set"]): r for r in
            csv.DictReader((tmp_path / "st" / "results.csv").open())}
    assert [rows[("a", s)]["cells"] for s in ("CP01", "MNY-mean")] == ["1600", "1600"]
    assert [rows[("b", s)]["cells"] for s in ("CP01", "MNY-mean")] == ["400", "400"]
    ran.clear()
    again = run_study(spec, tmp_path / "st", progress=False, report=False)
    assert ran == [] and again["meshes"]["a"]["refine"] == 2
    # resumed with a looser target, by which case a's sets need 0 and 1 refinements: the set
    # made again for the first target (CP01 at 2) is not taken for a run at the new one
    needs.update({("a", "CP01"): 0, ("a", "MNY-mean"): 1})
    missed.clear()
    ran.clear()
    acc["mesh.accuracy"] = 0.2
    loose = run_study(spec, tmp_path / "st", progress=False, report=False)
    assert loose["meshes"]["a"] == {"target_mm": 0.2, "refine": 1, "most_refine": 2,
                                    "needed": {"CP01": 0, "MNY-mean": 1}, "not_met": []}
    assert ("a/CP01", False, 1) in ran and ("a/CP01", 0.2, 0) in ran
    assert ("a/MNY-mean", 0.2, 1) in ran
    rows = {(r["case"], r["set"]): r for r in _rows(tmp_path / "st" / "results.csv")}
    assert [rows[("a", s)]["cells"] for s in ("CP01", "MNY-mean")] == ["400", "400"]
