"""Ctrl-C (or SIGTERM) during a solve: the first stops the run at its next step and writes the
last accepted state (summary.json ``"interrupted": true``, exit code 130, 143 for SIGTERM); a
second stops at once; a study makes an interrupted run again (README, "Running a scene":
"Ctrl-C and SIGTERM")."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_scripts import _env

from mvfem.solver import stop_asked, stop_on_interrupt

ROOT = Path(__file__).resolve().parents[1]


class _Comm:
    """A serial communicator's stand-in (one rank: no collective call is made)."""

    def __init__(self, size: int = 1, rank: int = 0):
        self.size, self.rank = size, rank


def _deliver(signum: int = signal.SIGINT) -> None:
    """Send ``signum`` to this process and let Python run its handler (at the next bytecode
    of the main thread)."""
    os.kill(os.getpid(), signum)
    for _ in range(100):
        time.sleep(0.001)


@pytest.fixture
def default_sigint():
    """Python's own SIGINT and SIGTERM dispositions for the test (whatever the test runner
    set), then back."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    old_term = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    yield
    signal.signal(signal.SIGINT, old)
    signal.signal(signal.SIGTERM, old_term)


def test_the_first_ctrl_c_asks_the_second_raises_and_the_handler_goes_back(default_sigint):
    with stop_on_interrupt(_Comm(1)) as stop:
        assert not stop_asked()
        _deliver()                       # no exception: a request
        assert stop_asked() and stop.asked
        with stop_on_interrupt(_Comm(1)):  # a coarser level's solve inside: the same request
            assert stop_asked()
        with pytest.raises(KeyboardInterrupt):
            _deliver()                   # the second: at once
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert stop.asked and not stop_asked()  # readable afterwards; no solve under way
    with stop_on_interrupt(_Comm(1)) as again:  # the next solve starts unasked
        assert not again.asked
    with pytest.raises(KeyboardInterrupt):  # outside any solve: Python's default
        _deliver()
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


class _SecondCtrlCInAFinaliser:
    """An object whose finaliser receives a Ctrl-C: Python swallows the KeyboardInterrupt
    raised there ("Exception ignored in ..."), as it did in an import's lock callback."""

    def __del__(self):
        _deliver()


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_second_ctrl_c_that_python_swallowed_is_raised_at_the_next_check(default_sigint):
    """A second Ctrl-C whose KeyboardInterrupt came inside a finaliser (swallowed there, as a
    fresh-cache suite met it in session 60: the run went on to write its outputs as after
    one Ctrl-C) raises KeyboardInterrupt at the steppers' next check (``stop_asked``) and
    at the run's check after its steps (``agree_on_stop``); the next solve starts afresh."""
    from mvfem.solver import agree_on_stop

    with stop_on_interrupt(_Comm(1)) as stop:
        _deliver()                          # the first: a request
        _SecondCtrlCInAFinaliser()          # (collected at once: its __del__ swallows it)
        assert stop.again
        with pytest.raises(KeyboardInterrupt):
            stop_asked()
    with pytest.raises(KeyboardInterrupt):
        agree_on_stop(_Comm(1))
    with stop_on_interrupt(_Comm(1)):
        assert not stop_asked()
    assert not agree_on_stop(_Comm(1))


def test_a_sigterm_asks_too(default_sigint):
    """SIGTERM (a batch system's time limit, ``timeout``) asks as Ctrl-C does, and says so
    (a second one ends the process: in ``test_a_second_ctrl_c_stops_at_once_writing_nothing``)."""
    with stop_on_interrupt(_Comm(1)) as stop:
        assert signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL  # (else it would kill)
        _deliver(signal.SIGTERM)
        assert stop_asked() and stop.cause == "SIGTERM" and stop.exit_code == 143
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    with stop_on_interrupt(_Comm(1)) as stop:
        _deliver()
        assert stop.cause == "the user (Ctrl-C)" and stop.exit_code == 130


def test_ctrl_c_is_said_by_rank_0_and_left_to_a_program_that_handles_it(default_sigint,
                                                                         capfd):
    for rank in (1, 0):
        with stop_on_interrupt(_Comm(1, rank)):
            _deliver()
            assert stop_asked()
        said = capfd.readouterr().err
        assert said.count("mvfem: Ctrl-C: stopping after this step") == (rank == 0), said
    seen = []
    old = signal.signal(signal.SIGINT, lambda s, f: seen.append(s))
    try:
        with stop_on_interrupt(_Comm(1)):  # a program's own handler stays
            _deliver()
            assert seen == [signal.SIGINT] and not stop_asked()
    finally:
        signal.signal(signal.SIGINT, old)


def test_a_mesh_made_with_gmsh_leaves_the_programs_ctrl_c_handler():
    """gmsh 4.8's ``finalize()`` sets SIGINT to the handler there was when gmsh was imported,
    whatever the program installed since: a test suite's worker that had imported gmsh under
    one test's handler put it back with every mesh made later, where a later test's Ctrl-C
    could find it (session 58: the likely cause of three fresh-cache suites in a row failing
    ``test_a_run_killed_while_its_outputs_are_made_leaves_a_state_to_resume``). Here gmsh is
    imported under one handler, the program installs Python's, and a disk is meshed (gmsh
    initialised and finalised): Python's handler is still there (in a fresh interpreter)."""
    code = ("import signal\nfrom mpi4py import MPI\nfrom mvfem import meshes\n"
            "signal.signal(signal.SIGINT, lambda s, f: None)\nimport gmsh\n"
            "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
            "m = meshes.disk(MPI.COMM_SELF, radius=1.0, size=0.5)\n"
            "assert m.mesh.topology.index_map(2).size_global > 4\n"
            "print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=_env(), preexec_fn=_sigdfl, timeout=120)
    assert r.stdout.strip() == "True", r.stdout[-500:] + r.stderr[-2000:]


def test_importing_gmsh_leaves_ctrl_c_to_python():
    """gmsh 4.8's module sets SIGINT to its system default when imported (until
    ``gmsh.finalize()``): in the CLI, which imports it first of all, Ctrl-C killed a study
    outright and a run with no gmsh session could not stop at its next step. The handler is
    Python's again after the CLI's import (in a fresh interpreter: this one may have gmsh)."""
    code = ("import signal\nfrom mvfem.cli import _import_gmsh_before_mpi\n"
            "_import_gmsh_before_mpi()\nimport sys\nassert 'gmsh' in sys.modules\n"
            "print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=_env(), preexec_fn=_sigdfl, timeout=60)
    assert r.stdout.strip() == "True", r.stderr[-2000:]


@pytest.mark.mpi
def test_a_stop_asked_of_one_rank_is_every_ranks(default_sigint):
    """SIGTERM to the last rank alone: at the next step boundary every rank is asked, with
    the same cause (a collective check), so they stop at the same step."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    with stop_on_interrupt(comm) as stop:
        assert not stop_asked(comm)
        if comm.rank == comm.size - 1:
            _deliver(signal.SIGTERM)
        assert stop_asked(comm)
        assert stop.cause == "SIGTERM" and stop.exit_code == 143


def test_sigterm_to_the_ranks_of_an_mpirun_job_writes_the_last_accepted_state(tmp_path):
    """``mpirun -n 2 mvfem -v run`` of the 4 mm demo, SIGTERM to each rank at the 40th
    pseudo-time step (as Slurm signals its tasks at a time limit; mpirun does so itself
    ``odls_base_sigkill_timeout`` seconds after a Ctrl-C): the ranks stop together and write
    the last accepted state, said once; each exits 143. Until session 56 they died with
    nothing written."""
    from test_scripts import _mpirun

    out = tmp_path / "out"
    p = subprocess.Popen([*_mpirun(2), sys.executable, "-m", "mvfem.cli", "-v", "run",
                          str(ROOT / "mvfem" / "data" / "demo.toml"), "--set", "mesh.size=4",
                          "--out", str(out)], cwd=tmp_path, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True, env=_env(), preexec_fn=_sigdfl)
    lines, ranks = [], []
    try:
        for line in p.stdout:
            lines.append(line.rstrip("\n"))
            if not ranks and (m := _PT.match(line)) is not None and int(m.group(1)) >= 40:
                ranks = subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True,
                                       text=True).stdout.split()
                for pid in ranks:
                    os.kill(int(pid), signal.SIGTERM)
        p.wait(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    text = "\n".join(lines[-30:])
    assert len(ranks) == 2, (ranks, text)
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"] is True and s["converged"] is False, s["stop_reason"]
    assert re.fullmatch(r"stopped by SIGTERM after \d+ pseudo-time steps", s["stop_reason"])
    # (anywhere in a line: mpirun forwards a rank's stdout and stderr apart, and a fresh
    # clone's suite got "... max displacement 6.654 mmmvfem: stopped by SIGTERM ...", the
    # stdout line's newline after the stderr line, session 58)
    said = [ln[ln.index("mvfem: stopped by SIGTERM"):] for ln in lines
            if "mvfem: stopped by SIGTERM" in ln]
    assert len(said) == 1 and f"is written in {out}" in said[0], text
    assert sum("stopping after this step" in ln for ln in lines) == 1, text
    assert s["newton_iterations"] < 184 and p.returncode != 0


def _sigdfl() -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_DFL)


def _run_and_interrupt(args: list[str], ready, tmp_path: Path, signals=(signal.SIGINT,),
                       timeout: float = 120):
    """``mvfem -v ARGS`` as a child; once a line it prints satisfies ``ready``, ``signals``
    sent to it, 0.1 s apart (two at once are one: the kernel does not queue them); (exit
    code, its lines, stdout's and stderr's as they came). The child gets the default
    dispositions of SIGINT and SIGTERM whatever this process's."""
    p = subprocess.Popen([sys.executable, "-m", "mvfem.cli", "-v", *args], cwd=tmp_path,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         env=_env(), preexec_fn=_sigdfl)
    lines, sent, t0 = [], False, time.monotonic()
    try:
        for line in p.stdout:
            lines.append(line.rstrip("\n"))
            if not sent and ready(line):
                for k, sig in enumerate(signals):
                    if k:
                        time.sleep(0.1)
                    p.send_signal(sig)
                sent = True
            if time.monotonic() - t0 > timeout:
                break
        rc = p.wait(timeout=max(timeout - (time.monotonic() - t0), 1))
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert sent, "\n".join(lines[-20:])
    return rc, lines


_PT = re.compile(r"^\s+pseudo-time step\s+(\d+)\s+residual\s+(\S+) of the load.*\b(ok|refused)\b")


@pytest.mark.parametrize("sig, code, cause", [(signal.SIGINT, 130, "the user (Ctrl-C)"),
                                               (signal.SIGTERM, 143, "SIGTERM")])
def test_ctrl_c_on_a_valve_writes_its_last_accepted_state(tmp_path, sig, code, cause):
    """The 4 mm demo (184 pseudo-time steps) stopped by Ctrl-C at its 40th step: exit code
    130, one closing line, and the outputs of the last accepted step: the steps its progress
    lines counted, and the very state that the same run stopped there by ``solver.max_steps``
    writes (the same path, step for step). The code before wrote nothing (exit 130, "mvfem:
    interrupted"). SIGTERM (a batch system's time limit, ``timeout``) likewise, exit code 143
    (the code before: killed by it)."""
    out = tmp_path / "out"
    demo = ["run", str(ROOT / "mvfem" / "data" / "demo.toml"), "--set", "mesh.size=4"]
    rc, lines = _run_and_interrupt(
        [*demo, "--out", str(out)],
        lambda ln: (m := _PT.match(ln)) is not None and int(m.group(1)) >= 40, tmp_path,
        signals=(sig,))
    text = "\n".join(lines[-30:])
    assert rc == code, text
    assert lines[-1].startswith(f"mvfem: stopped by {cause} after "), text
    assert lines[-1].endswith(f"is written in {out} (--resume {out} goes on from it)"), text
    assert not any("Traceback" in ln for ln in lines), text
    steps = [_PT.match(ln) for ln in lines if _PT.match(ln)]
    accepted = [m for m in steps if m.group(3) == "ok"]
    s = json.loads((out / "summary.json").read_text())
    assert s["converged"] is False and s["interrupted"] is True, s["stop_reason"]
    assert s["stop_reason"] == f"stopped by {cause} after {steps[-1].group(1)} " \
                               "pseudo-time steps"
    assert s["newton_iterations"] == int(steps[-1].group(1)) < 184
    assert s["load_steps"] == len(accepted)
    for name in ("fields.xdmf", "fields.h5", "chordae.csv"):
        assert (out / name).is_file(), name
    assert any(ln.startswith("NOT converged: 16 kPa") for ln in lines), text

    capped = tmp_path / "capped"
    r = subprocess.run([sys.executable, "-m", "mvfem.cli", *demo, "--set",
                        f"solver.max_steps={s['newton_iterations']}", "--out", str(capped)],
                       cwd=tmp_path, capture_output=True, text=True, env=_env(), timeout=120)
    assert r.returncode == 3, r.stderr[-2000:]
    c = json.loads((capped / "summary.json").read_text())
    assert (c["newton_iterations"], c["load_steps"]) == (s["newton_iterations"], s["load_steps"])
    for key in ("equilibrium_residual", "max_displacement_mm"):
        assert s[key] == pytest.approx(c[key], rel=1e-9), key
    assert s["valve"].keys() == c["valve"].keys()
    for key, value in s["valve"].items():  # (those of an open valve: null, or numbers)
        if isinstance(value, float):
            assert value == pytest.approx(c["valve"][key], rel=1e-9, abs=1e-12), key
        elif not isinstance(value, dict):
            assert value == c["valve"][key], key


@pytest.mark.parametrize("sig, code, last", [(signal.SIGINT, 130, "mvfem: interrupted"),
                                              (signal.SIGTERM, -signal.SIGTERM, None)])
def test_a_second_ctrl_c_stops_at_once_writing_nothing(tmp_path, sig, code, last):
    """Two Ctrl-C 0.1 s apart: the second ends the run where it is (within the step or while
    the outputs are written: they take about a second), as Ctrl-C did before, exit code 130;
    no complete summary.json (at most the partial one written with the state, first: since
    session 57). Two SIGTERM: killed by the second, as by one before."""
    out = tmp_path / "out"
    rc, lines = _run_and_interrupt(
        ["run", str(ROOT / "mvfem" / "data" / "demo.toml"), "--set", "mesh.size=4", "--out",
         str(out)], lambda ln: (m := _PT.match(ln)) is not None and int(m.group(1)) >= 40,
        tmp_path, signals=(sig, sig))
    assert rc == code, "\n".join(lines[-20:])
    if last is not None:
        assert lines[-1] == last, "\n".join(lines[-20:])
    summary = out / "summary.json"
    assert not summary.exists() or "partial" in json.loads(summary.read_text())


def test_ctrl_c_on_a_coarser_level_ends_the_run_writing_nothing(tmp_path):
    """The 4 mm demo refined once closes the unrefined valve first (a nested start): Ctrl-C
    there ends the whole run with a line that says so; the finer level does not start from
    the open state, as it would after a coarser level that stopped short."""
    out = tmp_path / "out"
    rc, lines = _run_and_interrupt(
        ["run", str(ROOT / "mvfem" / "data" / "demo.toml"), "--set", "mesh.size=4", "--set",
         "mesh.refine=1", "--out", str(out)],
        lambda ln: (m := _PT.match(ln)) is not None and int(m.group(1)) >= 40, tmp_path)
    text = "\n".join(lines[-30:])
    assert rc == 130, text
    assert lines[-1] == ("mvfem: stopped by the user (Ctrl-C) while closing the unrefined "
                         "valve (322 cells) for a coarse start, before the scene's own mesh; "
                         "nothing written"), text
    assert not any("continuing on" in ln for ln in lines), text
    assert not (out / "summary.json").exists()


class _Killed(BaseException):
    """SIGKILL's stand-in: nothing after it runs (no handler, no ``finally`` that writes)."""


def test_a_run_killed_while_its_outputs_are_made_leaves_a_state_to_resume(tmp_path, monkeypatch,
                                                                         default_sigint):
    """Ctrl-C under ``mpirun``: the ranks stop after their step, and mpirun's SIGTERM a second
    later kills them while the outputs are made (the refined demo's take 1.9 s). Here the 4 mm
    demo gets SIGINT at its 40th step, in this process, and its maps raise (the kill's
    stand-in): its state and a partial summary.json are there already, and ``--resume`` goes
    on from them to the closure of a run without a stop. The code before wrote summary.json
    last: nothing to resume ("no run's summary.json there")."""
    import h5py

    import mvfem.outputs
    import mvfem.run
    from mvfem.cli import main

    progress = mvfem.run._PseudoTimeProgress.__call__

    def ctrl_c_at_40(self, rec, ptc):
        progress(self, rec, ptc)
        if rec.step == 40:
            os.kill(os.getpid(), signal.SIGINT)

    def killed(*args, **kw):
        raise _Killed

    monkeypatch.setattr(mvfem.run._PseudoTimeProgress, "__call__", ctrl_c_at_40)
    monkeypatch.setattr(mvfem.outputs, "_write_maps", killed)
    out = tmp_path / "out"
    demo = ["run", str(ROOT / "mvfem" / "data" / "demo.toml"), "--set", "mesh.size=4"]
    with pytest.raises(_Killed):
        main([*demo, "--out", str(out)])
    monkeypatch.undo()
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"] is True and s["converged"] is False
    assert s["partial"] == mvfem.outputs.PARTIAL and "valve" not in s
    assert s["stop_reason"] == "stopped by the user (Ctrl-C) after 40 pseudo-time steps"
    assert main([*demo, "--resume", str(out), "--out", str(out)]) == 0
    resumed = json.loads((out / "summary.json").read_text())
    assert resumed["converged"] and "partial" not in resumed
    assert resumed["resumed_from"]["newton_iterations"] == 40
    whole = tmp_path / "whole"
    assert main([*demo, "--out", str(whole)]) == 0

    def u(d):
        with h5py.File(d / "fields.h5", "r") as f:
            return f["Function/displacement/0"][:]

    assert abs(u(out) - u(whole)).max() < 1e-5


_LS = re.compile(r"^\s+step\s+(\d+)\s+p =\s+(\S+) kPa\s+(ok|FAIL)")


def test_ctrl_c_on_a_load_stepped_disk_keeps_its_last_converged_load(tmp_path):
    """A flat CP08 disk ramped in 11 load steps (``first_step = 0.02``), stopped by Ctrl-C
    after its 7th: the state written is the last accepted step's, at the pressure its
    progress line gave, not converged."""
    scene = tmp_path / "disk.toml"
    scene.write_text('title = "disk"\n[mesh]\ngenerator = "disk"\nradius = 10.0\nsize = 1.25\n'
                     '[[region]]\nlaw = "mny"\nparams = "CP08"\n[solver]\nfirst_step = 0.02\n')
    out = tmp_path / "out"
    rc, lines = _run_and_interrupt(
        ["run", str(scene), "--out", str(out)],
        lambda ln: (m := _LS.match(ln)) is not None and int(m.group(1)) >= 7, tmp_path)
    text = "\n".join(lines[-30:])
    assert rc == 130, text
    assert lines[-1].startswith("mvfem: stopped by the user (Ctrl-C) after "), text
    steps = [_LS.match(ln) for ln in lines if _LS.match(ln)]
    ok = [m for m in steps if m.group(3) == "ok"]
    s = json.loads((out / "summary.json").read_text())
    assert s["converged"] is False and s["interrupted"] is True
    assert s["stop_reason"] == f"stopped by the user (Ctrl-C) after {len(steps)} load steps"
    assert s["pressure_Pa"] / 1e3 == pytest.approx(float(ok[-1].group(2)), abs=5e-4)
    assert 0 < s["pressure_Pa"] < 16000.0 and len(steps) < 11
    assert (out / "fields.xdmf").is_file()


def test_a_study_makes_a_run_that_ctrl_c_stopped_again(tmp_path):
    """A run whose summary.json says ``interrupted`` (Ctrl-C wrote the state it had reached)
    is still to make: not done when the study resumes, pending in results.csv, and not
    recorded as finished when it exits 130 (the code before counted it done, "stopped")."""
    from mvfem.outputs import write_json
    from mvfem.study import (Case, RunSpec, Study, _finish, _Lock, _Running, _spec_record,
                             collect_results, run_state)

    spec = RunSpec(case="a", set="MNY-mean", anterior_set="MNY-mean", posterior_set="",
                   scene="x", changes={}, regions=[])
    d = spec.dir(tmp_path)
    d.mkdir(parents=True)
    write_json(_spec_record(spec), d / "run.json")
    write_json({"converged": False, "interrupted": True, "pressure_Pa": 16000.0,
                "stop_reason": "stopped by the user (Ctrl-C) after 40 pseudo-time steps"},
               d / "summary.json")
    study = Study(title="", cases=[Case("a", "x")], sets=[], processes=1, timeout_s=None,
                  map_case="a", include_stopped=True, biaxial=False, runs=[spec])
    assert run_state(spec, tmp_path) == "todo"
    assert collect_results(study, tmp_path)[0]["status"] == "pending"

    proc = subprocess.Popen([sys.executable, "-c", "raise SystemExit(130)"])
    proc.wait()
    running = _Running(spec, proc, time.perf_counter(), time.time(), open(d / "run.log", "w"),
                       _Lock(d / ".lock"))
    assert _finish(running, tmp_path, proc.returncode) is None
    assert not (d / "status.json").exists() and run_state(spec, tmp_path) == "todo"
    # the same summary without the mark: a run that stopped short, done
    write_json({"converged": False, "pressure_Pa": 8000.0, "stop_reason": "x"},
               d / "summary.json")
    assert run_state(spec, tmp_path) == "done"
    assert collect_results(study, tmp_path)[0]["status"] == "stopped"


@pytest.mark.slow
def test_a_study_stopped_by_ctrl_c_keeps_its_runs_state_and_makes_it_again(tmp_path):
    """Ctrl-C to a study whose one run (the 2 mm demo, about 8 s of solve) is in its solve:
    the study stops its run with SIGTERM, which writes the state it reached (summary.json
    ``interrupted``) within the study's grace of 5 s; results.csv says pending; the same
    command again makes the run and it converges. Until session 56 the run died with
    nothing written (the same outcome for the study, nothing to look at)."""
    import csv

    from mvfem.study import load_study, run_study

    study = tmp_path / "study.toml"
    study.write_text(f'sets = ["MNY-mean"]\nprocesses = 1\nbiaxial = false\n[[case]]\n'
                     f'name = "demo"\nscene = "{ROOT / "mvfem" / "data" / "demo.toml"}"\n')
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "mvfem.cli", "study", str(study), "--out",
                          str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         text=True, env=_env(), preexec_fn=_sigdfl)
    log = None
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120:   # the run's first progress line: 2 s into its solve
            logs = list(out.glob("runs/*/*/run.log"))
            if logs and "pseudo-time step" in logs[0].read_text(errors="replace"):
                log = logs[0]
                break
            time.sleep(0.1)
        assert log is not None, "the run never reached its solve"
        p.send_signal(signal.SIGINT)
        err = p.communicate(timeout=60)[1]
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130, err[-2000:]
    s = json.loads((log.parent / "summary.json").read_text())
    assert s["interrupted"] is True and s["converged"] is False, s["stop_reason"]
    assert s["stop_reason"].startswith("stopped by SIGTERM after ")
    assert (log.parent / "fields.xdmf").is_file()
    with open(out / "results.csv", newline="") as f:
        assert [r["status"] for r in csv.DictReader(f)] == ["pending"]
    res = run_study(load_study(study), out, progress=False, report=False)
    assert res["ran"] == 1 and res["converged"] == 1
    assert json.loads((log.parent / "summary.json").read_text())["converged"] is True
