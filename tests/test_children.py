"""The guards against commands that exit at start-up without a word: the suite's children
(``run_child`` in conftest.py) and the Makefile's top commands (``python -m mvfem.relaunch``).
Such a command is started again; any other outcome is returned as it is."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from conftest import run_child

# exits 1 without a word the first ``fails`` times it is started (a count in a file), then
# prints "ran" and exits with ``rc``
CHILD = """
import subprocess
import sys
from pathlib import Path
count, fails, rc, say = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
n = int(count.read_text()) if count.exists() else 0
count.write_text(str(n + 1))
if n < fails:
    if say == "mpirun":  # the report mpirun writes when a rank exits so
        sys.stderr.write("-" * 55 + "\\nPrimary job  terminated normally, but 1 process returned\\n"
                         "a non-zero exit code. Per user-direction, the job has been aborted.\\n"
                         + "-" * 55 + "\\n" + "-" * 74 + "\\nmpirun detected that one or more "
                         "processes exited with non-zero status, thus causing\\nthe job to be "
                         "terminated. The first process to do so was:\\n\\n  Process name: "
                         "[[1234,1],1]\\n  Exit code:    1\\n" + "-" * 74 + "\\n")
    elif say:
        print(say)
    sys.exit(1)
print("ran")
sys.exit(rc)
"""


def _child(tmp_path, fails: int, rc: int = 0, say: str = ""):
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    return [sys.executable, str(script), str(tmp_path / "count"), str(fails), str(rc), say]


def _starts(tmp_path) -> int:
    return int((tmp_path / "count").read_text())


@pytest.mark.parametrize("say", ["", "mpirun"])
def test_silent_start_exits_are_started_again(tmp_path, say):
    """Each new start after a pause that grows (n x ``pause_s`` before the n-th)."""
    t0 = time.monotonic()
    with pytest.warns(UserWarning, match="without a word") as seen:
        r = run_child(_child(tmp_path, fails=2, say=say), pause_s=0.3)
    assert r.returncode == 0 and r.stdout == "ran\n"
    assert _starts(tmp_path) == 3 and len(seen) == 2
    assert time.monotonic() - t0 >= 0.9


def test_the_suites_children_get_more_starts_than_a_study(tmp_path):
    """The suite's default: a child that exits silently four times in a row still runs."""
    from conftest import CHILD_RETRIES

    from mvfem.relaunch import RETRIES

    assert CHILD_RETRIES == 4 > RETRIES
    with pytest.warns(UserWarning):
        r = run_child(_child(tmp_path, fails=4), pause_s=0.0)
    assert r.returncode == 0 and _starts(tmp_path) == 5


def test_a_child_that_keeps_exiting_silently_fails(tmp_path):
    with pytest.warns(UserWarning):
        r = run_child(_child(tmp_path, fails=5), retries=2, pause_s=0.0)
    assert r.returncode == 1 and _starts(tmp_path) == 3


@pytest.mark.parametrize("fails,rc,say", [(1, 0, "an error of ours"), (0, 1, ""), (0, 2, "")])
def test_other_exits_are_returned_as_they_are(tmp_path, recwarn, fails, rc, say):
    """A child that says a word, or exits 1 after its work, or with another code, is not
    started again."""
    r = run_child(_child(tmp_path, fails=fails, rc=rc, say=say))
    assert r.returncode == (1 if fails else rc) and _starts(tmp_path) == 1
    assert not [w for w in recwarn if "without a word" in str(w.message)]


def test_check_raises_after_the_retries(tmp_path):
    with pytest.warns(UserWarning), pytest.raises(Exception) as err:
        run_child(_child(tmp_path, fails=5), retries=1, pause_s=0.0, check=True)
    assert "returned non-zero exit status 1" in str(err.value) and _starts(tmp_path) == 2


# `make demo` and `make test` run their top commands through `python -m mvfem.relaunch`, the
# same rule outside pytest: the command's output passes through as it comes


def _relaunch(tmp_path, fails: int, rc: int = 0, say: str = "", *args):
    cmd = [sys.executable, "-m", "mvfem.relaunch", *args, "--", *_child(tmp_path, fails, rc, say)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("say", ["", "mpirun"])
def test_relaunch_starts_a_silent_start_exit_again(tmp_path, say):
    r = _relaunch(tmp_path, 2, 0, say)
    assert r.returncode == 0 and r.stdout == "ran\n" and _starts(tmp_path) == 3
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("mvfem.relaunch:")]
    assert len(lines) == 2 and "(1 of 2)" in lines[0] and "(2 of 2)" in lines[1]
    assert all("exited 1 at start-up without a word" in ln for ln in lines)
    if say == "mpirun":  # mpirun's report of each exit is passed through, not swallowed
        assert r.stderr.count("mpirun detected") == 2


def test_relaunch_gives_up_after_its_retries(tmp_path):
    r = _relaunch(tmp_path, 5, 0, "", "--retries", "1")
    assert r.returncode == 1 and _starts(tmp_path) == 2 and r.stdout == ""
    assert r.stderr.count("starting it again") == 1


@pytest.mark.parametrize("fails,rc,say", [(1, 0, "an error of ours"), (0, 1, ""), (0, 2, ""),
                                          (0, 3, "")])
def test_relaunch_passes_other_exits_through(tmp_path, fails, rc, say):
    """A command that says a word, exits 1 after its work, or with another code, runs once,
    and its code and output are the wrapper's."""
    r = _relaunch(tmp_path, fails, rc, say)
    assert r.returncode == (1 if fails else rc) and _starts(tmp_path) == 1
    assert r.stdout == (say + "\n" if fails else "ran\n") and "relaunch" not in r.stderr


def test_relaunch_counts_only_exits_within_its_window(tmp_path):
    """A silent exit 1 after the window (here 0.001 s) is the command's failure, not a
    start-up exit."""
    r = _relaunch(tmp_path, 5, 0, "", "--within", "0.001")
    assert r.returncode == 1 and _starts(tmp_path) == 1


def test_relaunch_refuses_a_missing_command(tmp_path):
    r = subprocess.run([sys.executable, "-m", "mvfem.relaunch", "--", str(tmp_path / "none")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "cannot start" in r.stderr
    r = subprocess.run([sys.executable, "-m", "mvfem.relaunch"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "no command given" in r.stderr


def test_relaunch_imports_no_petsc():
    """The wrapper must not itself be a process that can exit so: the exits follow PETSc's
    start (README, Studies)."""
    code = ("import sys, runpy; sys.argv = ['x', '--', 'true']\n"
            "try:\n    runpy.run_module('mvfem.relaunch', run_name='__main__')\n"
            "except SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('petsc4py', 'mpi4py', 'dolfinx', 'gmsh')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


def test_relaunch_passes_output_through_as_it_comes(tmp_path):
    """A line the command prints reaches the wrapper's stdout while the command still runs
    (here: the command waits for a file that the test writes once it has read the line),
    also where the caller's environment leaves Python's output buffered."""
    flag = tmp_path / "go"
    script = tmp_path / "talk.py"
    script.write_text("import sys, time\nfrom pathlib import Path\nprint('first')\n"
                      "t = time.monotonic()\n"
                      f"while not Path({str(flag)!r}).exists() and time.monotonic() - t < 10:\n"
                      "    time.sleep(0.02)\n"
                      f"print('second' if Path({str(flag)!r}).exists() else 'waited in vain')\n")
    p = subprocess.Popen([sys.executable, "-m", "mvfem.relaunch", "--", sys.executable,
                          str(script)], stdout=subprocess.PIPE, text=True,
                         env={k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"})
    assert p.stdout.readline() == "first\n"
    flag.write_text("")
    rest, _ = p.communicate(timeout=60)
    assert rest == "second\n" and p.returncode == 0


def test_relaunch_drains_a_command_whose_reader_stopped(tmp_path):
    """A reader that stops early (``| head``) must not leave the command blocked on a full
    pipe: the wrapper keeps draining it and returns its exit code."""
    script = tmp_path / "loud.py"
    script.write_text("for i in range(50000):\n    print('line', i)\n")
    p = subprocess.Popen([sys.executable, "-m", "mvfem.relaunch", "--", sys.executable,
                          str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert p.stdout.readline() == b"line 0\n"
        p.stdout.close()
        assert p.wait(timeout=30) == 0
    finally:
        p.kill()  # (a hung wrapper; its command ends on its own pipe)
    assert b"Traceback" not in p.stderr.read()


# a process that became an MPI singleton (mpi4py imported) starts a child with its own
# environment, as pytest starts pytest-xdist's workers: the child's environment, as JSON
_SINGLETONS_CHILD = """
import json, subprocess, sys
from mpi4py import MPI
assert MPI.COMM_WORLD.size == 1
print(subprocess.run([sys.executable, "-c", "import json, os; print(json.dumps(dict(os.environ)))"],
                     capture_output=True, text=True, check=True).stdout)
"""


def test_an_mpirun_started_from_a_singletons_child_runs_without_its_mpi_job():
    """``without_mpi_job``: a child of an MPI singleton inherits the singleton's variables
    (``OMPI_MCA_ess=singleton``...), with which an ``mpirun`` it starts exits 1 without a word
    (session 52: every mpirun of the suite under pytest-xdist); without them, that mpirun
    runs its two ranks. The variables of ``mpirun``'s own permission are kept."""
    import json
    import shutil

    from mvfem.relaunch import without_mpi_job

    base = without_mpi_job()  # (this process may be a singleton's child itself)
    inherited = json.loads(run_child([sys.executable, "-c", _SINGLETONS_CHILD], env=base,
                                     timeout=120, check=True).stdout)
    added = {k for k in inherited if k not in base}
    assert any(k.startswith("OMPI_MCA") for k in added), added  # (what this test is about)
    inherited.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
    env = without_mpi_job(inherited, OPENBLAS_NUM_THREADS="1")
    assert not any(k.startswith(("OMPI_MCA", "PMIX_")) or k == "OMPI_APP_CTX_NUM_PROCS"
                   for k in env)
    assert env["OMPI_ALLOW_RUN_AS_ROOT"] == "1" and env["OPENBLAS_NUM_THREADS"] == "1"
    assert env["PATH"] == inherited["PATH"]
    r = run_child([shutil.which("mpirun"), "--oversubscribe", "-n", "2", sys.executable, "-c",
                   "from mpi4py import MPI; c = MPI.COMM_WORLD; s = c.gather(c.size); "
                   "c.rank == 0 and print(*s)"],
                  env=env, stdin=subprocess.DEVNULL, timeout=120)
    assert r.returncode == 0 and r.stdout.split() == ["2", "2"], r.stderr[-2000:]
