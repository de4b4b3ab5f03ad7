"""``mvfem run --resume DIR``: a run starts from the state an earlier run of the same mesh wrote
(README, "Running a scene": "Resuming a run")."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from mvfem.cli import main

ROOT = Path(__file__).resolve().parents[1]
DEMO = str(ROOT / "mvfem" / "data" / "demo.toml")


def _u(d: Path) -> np.ndarray:
    """The displacement written in ``d/fields.h5``, its nodes in the order of their reference
    coordinates: under mpirun the order written is the partition's, and PT-Scotch's partition of
    the same mesh differs now and then between runs (a CI run's three runs of one process did)."""
    with h5py.File(d / "fields.h5", "r") as f:
        x = np.asarray(f["Mesh/mesh/geometry"])
        u = np.asarray(f["Function/displacement/0"])
    return u[np.lexsort(x.T[::-1])]


def _summary(d: Path) -> dict:
    return json.loads((d / "summary.json").read_text())


@pytest.mark.mpi
def test_a_valve_stopped_short_resumes_to_the_closure_of_an_uninterrupted_run(shared_tmp, comm,
                                                                              capsys):
    """The 4 mm demo stopped after 60 pseudo-time steps (``solver.max_steps``, exit code 3),
    then resumed from the state it wrote, into the same directory: it converges to the
    closure of the demo run without a stop (every node to 1e-5 mm; both are converged to
    1e-8 of the load), in fewer steps than that run took from the open state, so it did start
    from the written state. Also under ``mpirun -n 2`` (each rank matches its own nodes)."""
    tmp_path = shared_tmp
    part = tmp_path / "part"
    small = ["--set", "mesh.size=4"]
    assert main(["run", DEMO, *small, "--set", "solver.max_steps=60", "--out", str(part)]) == 3
    if comm.rank == 0:  # (the line is rank 0's)
        assert capsys.readouterr().err.strip().endswith(
            f"last converged state written in {part} (--resume {part} goes on from it)")
    assert main(["run", DEMO, *small, "--resume", str(part), "--out", str(part)]) == 0
    whole = tmp_path / "whole"
    assert main(["run", DEMO, *small, "--out", str(whole)]) == 0
    r, w = _summary(part), _summary(whole)
    went_on = r["resumed_from"]
    assert r["converged"] and {k: went_on[k] for k in (
        "directory", "pressure_Pa", "converged", "newton_iterations")} == {
        "directory": str(part), "pressure_Pa": 16000.0, "converged": False,
        "newton_iterations": 60}
    assert went_on["pseudo_time"]["threshold"] == 1.0  # (the open state's start)
    assert "coarse_start" not in r
    np.testing.assert_allclose(_u(part), _u(whole), rtol=0, atol=1e-5)
    assert r["newton_iterations"] < w["newton_iterations"] - 20, \
        (r["newton_iterations"], w["newton_iterations"])


def test_load_steps_resume_from_the_pressure_reached(tmp_path):
    """A flat CP08 disk stopped after 4 load steps resumes from the pressure it reached, and
    one converged at 16 kPa goes on to 20 kPa from there: each reaches the centre deflection
    of a run from the flat state (1e-6 relative), in fewer load steps."""
    scene = tmp_path / "disk.toml"
    scene.write_text('title = "disk"\n[mesh]\ngenerator = "disk"\nradius = 10.0\nsize = 1.25\n'
                     '[[region]]\nlaw = "mny"\nparams = "CP08"\n[output]\nprobes = '
                     '[{ name = "c", point = [0.0, 0.0, 0.0] }]\n')

    def run(name: str, *args: str) -> dict:
        main(["run", str(scene), "--out", str(tmp_path / name), *args])
        return _summary(tmp_path / name)

    short = run("short", "--set", "solver.max_steps=4")
    assert not short["converged"] and 0 < short["pressure_Pa"] < 16000.0
    resumed = run("resumed", "--resume", str(tmp_path / "short"))
    whole = run("whole")
    assert resumed["converged"] and whole["converged"]
    assert resumed["resumed_from"]["pressure_Pa"] == short["pressure_Pa"]
    assert resumed["probes"]["c"]["displacement_mm"][2] == pytest.approx(
        whole["probes"]["c"]["displacement_mm"][2], rel=1e-6)
    assert resumed["load_steps"] < whole["load_steps"]

    higher = ["--set", "load.pressure=20000.0"]
    on = run("on", *higher, "--resume", str(tmp_path / "whole"))
    direct = run("direct", *higher)
    assert on["converged"] and direct["converged"]
    assert on["probes"]["c"]["displacement_mm"][2] == pytest.approx(
        direct["probes"]["c"]["displacement_mm"][2], rel=1e-6)
    assert on["load_steps"] < direct["load_steps"]


@pytest.mark.parametrize("case, words", [
    ("nothing", "no run's summary.json there"),
    ("other mesh", "a run of 491 cells, this scene has"),
    ("no fields", "no fields.h5 there"),
    ("accuracy", "asks for mesh.accuracy"),
    ("broken fields", "its fields.h5 cannot be read as a run's state"),
    # (session 62: a summary.json edited by hand was a ValueError, TypeError or
    # ZeroDivisionError traceback; a NaN in the state was blamed on solver.petsc_options)
    ("pressure edited", "its summary.json has pressure_Pa 'x', not a finite number"),
    ("pseudo_time edited", "its summary.json has pseudo_time 'x', not a table"),
    ("weight edited", "its summary.json has pseudo_time.weight 0, not a positive number"),
    ("NaN state", "non-finite coordinates or displacements"),
])
def test_a_resume_from_what_cannot_be_resumed_is_one_line(tmp_path, capsys, case, words):
    scene = tmp_path / "disk.toml"
    scene.write_text('title = "disk"\n[mesh]\ngenerator = "disk"\nradius = 10.0\nsize = 1.25\n'
                     '[[region]]\nlaw = "svk"\nparams = "SVK"\n')
    earlier = tmp_path / "earlier"
    args = []
    if case in ("other mesh", "no fields", "broken fields", "pressure edited",
                "pseudo_time edited", "weight edited", "NaN state"):
        assert main(["run", str(scene), "--out", str(earlier)]) == 0
    edits = {"pressure edited": {"pressure_Pa": "x"}, "pseudo_time edited": {"pseudo_time": "x"},
             "weight edited": {"pseudo_time": {"weight": 0, "threshold": 1.0,
                                               "symmetric": False, "convex_window": 0}}}
    if case in edits:
        summary = json.loads((earlier / "summary.json").read_text())
        (earlier / "summary.json").write_text(json.dumps({**summary, **edits[case]}))
    elif case == "NaN state":
        import h5py

        with h5py.File(earlier / "fields.h5", "r+") as f:
            u = f["Function/displacement/0"]
            u[3, 0] = float("nan")
    if case == "other mesh":
        args = ["--set", "mesh.size=2.5"]
    elif case == "no fields":
        (earlier / "fields.h5").unlink()
    elif case == "broken fields":  # (as a write cut short leaves it)
        data = (earlier / "fields.h5").read_bytes()
        (earlier / "fields.h5").write_bytes(data[: len(data) // 3])
    elif case == "accuracy":  # (refused before anything is built)
        scene, args = DEMO, ["--set", "mesh.accuracy=0.1", "--set", "mesh.refine=1"]
    capsys.readouterr()
    assert main(["run", str(scene), *args, "--resume", str(earlier), "--out",
                 str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"mvfem: error: ") and words in err[0], err
    assert "Traceback" not in "".join(err)


@pytest.mark.slow
def test_a_nested_level_stopped_short_goes_on_along_its_own_path(tmp_path):
    """The demo refined twice, its finest level stopped after 10 pseudo-time steps, resumed:
    the finest level goes on with the weight, Newton's threshold and tangents it had
    (summary.json ``pseudo_time``), so the two parts take about the steps of the run without
    a stop (session 56: 10 + 34 against 44) and reach its closure (1e-6 mm). Resumed from
    the open state's weight instead, it took 147 more steps."""
    part, whole = tmp_path / "part", tmp_path / "whole"
    refined = ["--set", "mesh.refine=2"]
    assert main(["run", DEMO, *refined, "--set", "solver.max_steps=10", "--out",
                 str(part)]) == 3
    assert _summary(part)["pseudo_time"]["threshold"] > 1.0  # (a nested level's start)
    assert main(["run", DEMO, *refined, "--resume", str(part), "--out", str(part)]) == 0
    assert main(["run", DEMO, *refined, "--out", str(whole)]) == 0
    r, w = _summary(part), _summary(whole)
    np.testing.assert_allclose(_u(part), _u(whole), rtol=0, atol=1e-6)
    assert 10 + r["newton_iterations"] <= w["newton_iterations"] + 5, \
        (r["newton_iterations"], w["newton_iterations"])


def test_a_ring_repair_resumes_once_its_motion_is_complete(tmp_path, capsys):
    """The pathological valve (4 mm) with a 36 mm D-shaped ring, a prescribed motion: the ring
    motion completes at some step, the laws' exponent stays capped until the capped problem
    converges, then the true law goes on (``motion.completed_at_step``,
    ``cap_raised_at_step``). Stopped before the motion completes: no ``--resume`` hint, and a
    resume is refused in one line (its ramp's state is not written). Stopped with the
    exponent capped, and stopped under the true law: each resumed run converges to the
    closure of the run without a stop (every node within 1e-6 mm), the first raising the
    cap in its own steps, the second with the true law from its start. Another ring, or the
    valve without the ring: refused (the state's annulus is not where the scene holds it;
    the latter ran 30 refusals to "no admissible step" before). Until session 57 every
    motion was refused, and the stop's line offered ``--resume`` all the same."""
    scene = tmp_path / "ring.toml"
    text = (ROOT / "scripts" / "scenes" / "valve_pathological.toml").read_text()
    scene.write_text(text.replace("size = 2.0", "size = 4.0")
                     + '\n[repair.ring]\nshape = "d-shaped"\nsize = 36.0\n')
    whole = tmp_path / "whole"
    assert main(["run", str(scene), "--out", str(whole)]) == 0
    w = _summary(whole)
    done, raised, total = (w["motion"]["completed_at_step"], w["motion"]["cap_raised_at_step"],
                           w["newton_iterations"])
    assert 10 < done < raised < total - 5 and w["motion"]["exponent_capped"] is False

    def stop_at(n: int) -> Path:
        out = tmp_path / f"at{n}"
        capsys.readouterr()
        assert main(["run", str(scene), "--set", f"solver.max_steps={n}", "--out",
                     str(out)]) == 3
        return out

    hint = "try mesh.size=8 with mesh.refine=1 (about as many cells"
    early = stop_at(done - 5)
    err = capsys.readouterr().err
    assert "--resume" not in err and hint in err  # (a motion that stopped on its own mesh)
    assert main(["run", str(scene), "--resume", str(early), "--out", str(tmp_path / "x")]) == 2
    assert "had not completed" in capsys.readouterr().err
    for n, capped in ((raised - 5, True), (raised + 2, False)):
        part = stop_at(n)
        err = capsys.readouterr().err
        assert f"(--resume {part} goes on from it)" in err
        assert (hint in err) is capped  # (the capped problem had converged: not the crawl)
        assert _summary(part)["motion"]["exponent_capped"] is capped
        # (stopped capped: the cap never raised; until session 60 the stop's last step)
        assert _summary(part)["motion"]["cap_raised_at_step"] == (None if capped else raised)
        assert main(["run", str(scene), "--resume", str(part), "--out", str(part)]) == 0
        r = _summary(part)
        assert r["converged"] and r["motion"]["completed_at_step"] == 0
        assert ((r["motion"]["cap_raised_at_step"] or 0) > 0) is capped, r["motion"]
        np.testing.assert_allclose(_u(part), _u(whole), rtol=0, atol=1e-6)
    assert main(["run", str(scene), "--set", "repair.ring.size=34", "--resume", str(part),
                 "--out", str(tmp_path / "y")]) == 2
    assert "the state there has nodes up to 1 mm from where" in capsys.readouterr().err
    unrepaired = tmp_path / "unrepaired.toml"  # (its annulus clamped where it was: 10.4 mm)
    unrepaired.write_text(text.replace("size = 2.0", "size = 4.0"))
    assert main(["run", str(unrepaired), "--resume", str(part), "--out",
                 str(tmp_path / "z")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("mvfem: error: --resume ") and "has nodes up to" in err[-1], err
    assert not any("Traceback" in line for line in err)
