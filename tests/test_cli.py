"""The CLI, in process: biaxial and materials; bad input exits 2 with one line, no traceback."""

from __future__ import annotations

import csv
from pathlib import Path

import meshio
import numpy as np
import pytest
from test_materials import closed_form

from mvfem.cli import main
from mvfem.materials import get_set


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_biaxial_writes_csv_and_figures(tmp_path, capsys):
    out = tmp_path / "bx"
    assert main(["biaxial", "--out", str(out), "--points", "11"]) == 0
    rows = _rows(out / "biaxial.csv")
    assert list(rows[0]) == ["leaflet", "set", "mode", "strain_parallel", "strain_perpendicular",
                             "sigma_parallel_Pa", "sigma_perpendicular_Pa"]
    # both leaflets: 11 anterior + 3 posterior sets, four modes, 11 strains
    assert len(rows) == (11 + 3) * 4 * 11
    assert {r["mode"] for r in rows} == {"equibiaxial", "off-biaxial", "strip-parallel",
                                        "strip-perpendicular"}
    sets = {(r["leaflet"], r["set"]) for r in rows}
    assert ("anterior", "CP08") in sets and ("posterior", "MNY-mean") in sets
    assert ("posterior", "CP01") not in sets
    for leaflet in ("anterior", "posterior"):
        assert (out / f"biaxial_{leaflet}.png").stat().st_size > 20_000
    # the CSV carries the closed-form stress (an independent check of what is written)
    for r in rows:
        if r["sigma_parallel_Pa"] == "":
            continue
        s = get_set(r["set"], r["leaflet"])
        l1, l2 = 1 + float(r["strain_parallel"]), 1 + float(r["strain_perpendicular"])
        cp, cq = closed_form(s.law, s.params, np.array(l1), np.array(l2))
        scale = max(abs(cp), abs(cq), s.params.get("c0", s.params.get("E", 1.0)))
        assert abs(float(r["sigma_parallel_Pa"]) - cp) < 1e-8 * scale
        assert abs(float(r["sigma_perpendicular_Pa"]) - cq) < 1e-8 * scale
    # strip-perpendicular holds the parallel strain at +15 %, off-biaxial is 1.5 x
    assert all(float(r["strain_parallel"]) == pytest.approx(0.15) for r in rows
               if r["mode"] == "strip-perpendicular")
    assert all(float(r["strain_perpendicular"]) == pytest.approx(1.5 * float(r["strain_parallel"]))
               for r in rows if r["mode"] == "off-biaxial")
    assert "wrote" in capsys.readouterr().out


def test_biaxial_one_leaflet_and_rerun_same_dir(tmp_path):
    out = tmp_path / "post"
    args = ["biaxial", "--leaflet", "posterior", "--points", "5", "--strain=0:0.3", "--out", str(out)]
    assert main(args) == 0
    assert main(args) == 0  # mvfem may write again where it wrote before
    rows = _rows(out / "biaxial.csv")
    assert {r["leaflet"] for r in rows} == {"posterior"}
    assert len(rows) == 3 * 4 * 5
    assert not (out / "biaxial_anterior.png").exists()
    # both leaflets, then one: the other's figure does not stay behind (until session 55 it did)
    assert main(["biaxial", "--points", "5", "--strain=0:0.3", "--out", str(out)]) == 0
    assert (out / "biaxial_anterior.png").exists()
    assert main(args) == 0
    assert not (out / "biaxial_anterior.png").exists()
    assert {r["leaflet"] for r in _rows(out / "biaxial.csv")} == {"posterior"}


def test_materials_lists_sets_and_missing(capsys):
    assert main(["materials"]) == 0
    text = capsys.readouterr().out
    for name in ("CP01", "CP08", "MNY-mean", "Holzapfel", "SVK", "1446.5", "305.4", "4.15"):
        assert name in text
    assert "not available" in text and "Table II" in text


def test_valve_line_puts_the_trace_length_beside_the_stepped_one():
    """The line a valve's run prints: both coaptation lengths (the trace beside the stepped
    one), and n/a for a metric the summary lacks (a valve that did not coapt has no trace)."""
    from mvfem.cli import valve_line

    s = {"valve": {"coaptation_length_mm": 7.8431, "coaptation_trace_length_mm": 7.1549,
                   "coaptation_area_mm2": 262.2, "regurgitant_orifice_area_mm2": 0.0,
                   "tenting_height_mm": 5.1497},
         "max_penetration_mm": 0.0, "contact": {"min_distance_mm": 0.1562}}
    assert valve_line(s) == ("coaptation length 7.84 mm (trace 7.15 mm), area 262 mm2; "
                             "regurgitant orifice 0 mm2; tenting 5.15 mm; max penetration 0 mm "
                             "(closest approach 0.156 mm)")
    s["valve"]["coaptation_trace_length_mm"] = None
    assert valve_line(s).startswith("coaptation length 7.84 mm (trace n/a), area")


@pytest.mark.parametrize("args,words", [
    (["biaxial", "--sets", "CP09"], ["CP09", "unknown"]),
    (["biaxial", "--leaflet", "posterior", "--sets", "CP03"], ["CP03", "not available"]),
    (["biaxial", "--strain", "abc"], ["--strain", "MIN:MAX"]),
    (["biaxial", "--strain=0.5:-0.5"], ["--strain", "not below"]),
    (["biaxial", "--strain=-1.2:0.5"], ["--strain", "stretch"]),
    (["biaxial", "--points", "1"], ["--points"]),
    (["biaxial", "--points", "many"], ["--points", "invalid int"]),
    (["biaxial", "--points", "100000000000"], ["--points", "at most 100,000"]),  # (745 GiB)
    (["biaxial", "--leaflet", "middle"], ["--leaflet", "middle"]),
    (["nonsense"], ["nonsense"]),
    # (session 62: an empty value meant the default: results/NAME, every set, every problem)
    (["biaxial", "--sets", ""], ["--sets: empty"]),
    (["bench", "--problems", ",", "--out", "never"], ["--problems: empty"]),
    (["run", "scripts/scenes/disk_mny.toml", "--out", ""], ["--out: empty"]),
])
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, args, words, monkeypatch):
    monkeypatch.chdir(tmp_path)   # (nothing of a refused run may appear here)
    args = [str(Path(__file__).parents[1] / a) if a.endswith(".toml") else a for a in args]
    out = tmp_path / "never"
    assert main(args + ["--out", str(out)] if args[0] == "biaxial" else args) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0]
    assert not any(tmp_path.iterdir())
    assert not out.exists()  # nothing written on bad input


def test_refuses_user_directory(tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "biaxial.csv").write_text("my own data\n")
    assert main(["biaxial", "--points", "3", "--out", str(mine)]) == 2
    assert "not written by mvfem" in capsys.readouterr().err
    assert (mine / "biaxial.csv").read_text() == "my own data\n"


def test_mesh_command_writes_readable_file(tmp_path, capsys):
    from mvfem.meshes import read_surface

    out = tmp_path / "disk.vtu"
    assert main(["mesh", "disk", "--radius", "5", "--size", "0.5", "--out", str(out)]) == 0
    raw = read_surface(out)
    a, b, c = (raw.points[raw.triangles[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    # a polygon inscribed in the circle with edges of 0.5 mm misses well under 1 % of the area
    assert area == pytest.approx(np.pi * 25, rel=1e-2)
    assert (tmp_path / "disk.vtu.json").exists()
    assert main(["mesh", "disk", "--out", str(out)]) == 2  # never overwrites
    assert main(["mesh", "disk", "--size", "-1", "--out", str(tmp_path / "x.vtu")]) == 2
    assert "--size" in capsys.readouterr().err


def test_mesh_command_never_replaces_a_file_it_would_write_beside_the_mesh(tmp_path, capsys):
    """The info file ``OUT.json`` and an .xdmf's ``.h5`` are the command's output too: a user's
    file of that name is refused like the mesh itself, and a write that fails part way (the
    info path a directory) leaves no mesh behind."""
    mine = tmp_path / "m.vtu.json"
    mine.write_text('{"mine": 1}')
    assert main(["mesh", "disk", "--size", "4", "--out", str(tmp_path / "m.vtu")]) == 2
    assert "m.vtu.json" in capsys.readouterr().err
    assert mine.read_text() == '{"mine": 1}' and not (tmp_path / "m.vtu").exists()
    heavy = tmp_path / "x.h5"
    heavy.write_text("mine")
    assert main(["mesh", "disk", "--size", "4", "--out", str(tmp_path / "x.xdmf")]) == 2
    assert "x.h5" in capsys.readouterr().err and heavy.read_text() == "mine"
    (tmp_path / "d.vtu.json").mkdir()
    assert main(["mesh", "disk", "--size", "4", "--out", str(tmp_path / "d.vtu"),
                 "--force"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "d.vtu.json" in err[0], err
    assert not (tmp_path / "d.vtu").exists()


def test_an_output_name_too_long_is_one_line(tmp_path, capsys):
    """A file name longer than the file system takes (255 bytes) after --out is an input
    error of ``mvfem run`` and ``mvfem mesh`` (it was an OSError traceback)."""
    disk = Path(__file__).parents[1] / "scripts" / "scenes" / "disk_mny.toml"
    long = tmp_path / ("a" * 300)
    for args in (["run", str(disk)], ["mesh", "disk"]):
        out = str(long) + (".vtu" if args[0] == "mesh" else "")
        assert main(args + ["--out", out]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "File name too long" in err[0] and "--out" in err[0], err


@pytest.mark.mpi
def test_bad_input_is_one_line_and_a_mesh_one_file_under_mpirun(shared_tmp, capsys,
                                                              monkeypatch):
    """Under ``mpirun -n 2`` (and serially) a bad input is one line on stderr in all, rank 0's,
    with exit code 2 on every rank; ``mvfem mesh`` writes its file once (one call of the
    writer in all; no rank finds the file another has just written: exit code 0 on every
    rank) and, asked again, every rank refuses to overwrite it."""
    from mpi4py import MPI

    import mvfem.meshes

    comm = MPI.COMM_WORLD
    writes = []
    real = mvfem.meshes.write_surface
    monkeypatch.setattr(mvfem.meshes, "write_surface",
                        lambda *a, **k: (writes.append(1), real(*a, **k))[1])
    capsys.readouterr()
    missing = main(["run", str(shared_tmp / "nothere.toml")])
    lines = comm.allgather(capsys.readouterr().err.strip().splitlines())
    out = shared_tmp / "disk.vtu"
    first = main(["mesh", "disk", "--radius", "5", "--size", "2", "--out", str(out)])
    capsys.readouterr()
    again = main(["mesh", "disk", "--radius", "5", "--size", "2", "--out", str(out)])
    again_lines = comm.allgather(capsys.readouterr().err.strip().splitlines())
    codes = comm.allgather((missing, first, again))
    written = comm.allreduce(len(writes))
    assert sum(len(x) for x in lines) == 1 and "nothere.toml" in lines[0][0], lines
    assert all(c == (2, 0, 2) for c in codes), codes
    assert sum(len(x) for x in again_lines) == 1 and "exists" in again_lines[0][0]
    assert written == 1
    assert out.is_file() and len(meshio.read(out).cells_dict["triangle"]) > 10


def _unusable_out(tmp_path):
    """An output path no one can make: its parent is a regular file (as root too)."""
    blocker = tmp_path / "a_file"
    blocker.write_text("mine\n")
    return blocker / "out"


@pytest.mark.parametrize("command", ["biaxial", "run", "bench", "mesh"])
def test_an_output_path_that_cannot_be_made_is_one_line(tmp_path, capsys, command):
    """``--out`` under a regular file (or on a read-only disk, or without permission) is an
    input error naming the option and the path, exit code 2, before anything is computed;
    until session 55 it was a ``NotADirectoryError`` traceback (exit code 1) and, under
    mpirun, a job whose other ranks waited for rank 0 forever
    (``test_an_output_path_that_cannot_be_made_ends_an_mpirun_job``)."""
    from pathlib import Path

    out = _unusable_out(tmp_path)
    scene = Path(__file__).resolve().parents[1] / "scripts" / "scenes" / "disk_mny.toml"
    args = {"biaxial": ["biaxial", "--points", "3", "--out", str(out)],
            "run": ["run", str(scene), "--out", str(out)],
            "bench": ["bench", "--quick", "--out", str(out)],
            "mesh": ["mesh", "disk", "--radius", "5", "--size", "2", "--out",
                     str(out / "disk.vtu")]}[command]
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("mvfem: error: --out ") and str(out) in lines[0]
    assert "cannot be" in lines[0] and "Not a directory" in lines[0]
    assert (tmp_path / "a_file").read_text() == "mine\n"


def _mpirun_child(args, timeout=180):
    import subprocess
    import sys

    from conftest import run_child
    from test_scripts import _env, _mpirun

    try:
        return run_child([*_mpirun(2), sys.executable, *args], env=_env(), timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"mpirun -n 2 {' '.join(args)}: still running after {timeout} s (a hang)")


def test_an_output_path_that_cannot_be_made_ends_an_mpirun_job(tmp_path):
    """Under ``mpirun -n 2`` the same bad ``--out`` is one line and exit code 2 within
    seconds (it hung until session 55: rank 0 raised, rank 1 waited in the broadcast of the
    verdict)."""
    from pathlib import Path

    out = _unusable_out(tmp_path)
    scene = Path(__file__).resolve().parents[1] / "scripts" / "scenes" / "disk_mny.toml"
    r = _mpirun_child(["-m", "mvfem.cli", "run", str(scene), "--out", str(out)])
    assert r.returncode == 2, r.stderr[-2000:]
    said = [ln for ln in r.stderr.splitlines() if ln.startswith("mvfem: ")]
    assert len(said) == 1 and str(out) in said[0] and "Traceback" not in r.stderr


# a command that fails unexpectedly on rank 0 only, while rank 1 waits for it in a collective
ONE_RANK_FAILS = """
import mvfem.cli as cli
from mpi4py import MPI

def broken(args):
    if MPI.COMM_WORLD.rank == 0:
        raise RuntimeError("a bug on rank 0 alone")
    MPI.COMM_WORLD.barrier()
    return 0

cli._cmd_materials = broken
raise SystemExit(cli.main(["materials"]))
"""


def test_an_unexpected_error_on_one_rank_ends_the_mpirun_job(tmp_path):
    """An exception that only one rank meets (a bug, not bad input) ends the whole job with
    its traceback (``MPI_Abort``, exit code 1) instead of leaving the other rank waiting."""
    script = tmp_path / "one_rank_fails.py"
    script.write_text(ONE_RANK_FAILS)
    r = _mpirun_child([str(script)], timeout=120)
    assert r.returncode != 0
    assert "RuntimeError: a bug on rank 0 alone" in r.stderr
    assert "Traceback" in r.stderr


@pytest.mark.parametrize("command", ["study", "repair-compare"])
def test_a_study_under_mpirun_is_refused_in_one_line(tmp_path, command):
    """``mpirun -n 2 mvfem study`` (or ``repair-compare``, a study of repairs) is refused on
    every rank before anything is written: each case is a process of its own. Until session
    55 both ranks ran the study into one directory; one met the other's lock, exited 2
    without a word (rank 0 speaks for all) and mpirun aborted the job around the other."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    study = tmp_path / "tiny.toml"
    study.write_text('title = "tiny"\nsets = ["MNY-mean"]\nprocesses = 1\nbiaxial = false\n'
                     '[[case]]\nname = "small"\nscene = "demo"\nset = { "mesh.size" = 6.0 }\n')
    out = tmp_path / "out"
    args = {"study": ["study", str(study)],
            "repair-compare": ["repair-compare", str(root / "scripts" / "scenes"
                                                     / "valve_pathological.toml"),
                               "--repairs", str(root / "scripts" / "scenes" / "repairs"
                                                / "ring_d36.toml")]}[command]
    r = _mpirun_child(["-m", "mvfem.cli", *args, "--out", str(out)])
    said = [ln for ln in r.stderr.splitlines() if ln.startswith("mvfem: ")]
    assert r.returncode == 2, r.stderr[-2000:]
    assert len(said) == 1 and "without mpirun" in said[0] and command in said[0], r.stderr
    assert not out.exists()


def test_the_command_lines_own_output_is_said_once_under_mpirun():
    """``--help`` and a command line argparse refuses come before MPI is started, so rank 0
    could not speak for the others: under ``mpirun -n 2`` each was printed twice (the two
    errors on one line). mpirun's environment names the rank there (session 55)."""
    helped = _mpirun_child(["-m", "mvfem.cli", "--help"])
    refused = _mpirun_child(["-m", "mvfem.cli", "run"])
    assert helped.returncode == 0 and helped.stdout.count("usage: ") == 1, helped.stdout
    assert refused.returncode == 2
    assert refused.stderr.count("mvfem: error: mvfem run: the following arguments are "
                                "required: scene") == 1, refused.stderr
