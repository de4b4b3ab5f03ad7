"""The suite's pytest-xdist workers (``make test`` runs the serial suite in two): they start
without the controller's MPI job, and a test whose worker died in it, its first test, runs
again on a new worker (conftest.py: ``xdist_controller``, ``pytest_handlecrashitem``). Each
test runs pytest on a small test file of its own, with this suite's conftest as a plugin."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from conftest import WORKER_RERUNS, run_child

from mvfem.relaunch import without_mpi_job

TESTS = Path(__file__).resolve().parent

# the MPI job's variables a worker started with (its environment as it was at its start;
# Open MPI's permission to run as root is the suite's own, not a job's)
PROBE = """
import json, os
from pathlib import Path

def test_probe():
    start = Path(f"/proc/{os.getpid()}/environ").read_bytes().split(b"\\0")
    names = sorted(v.split(b"=")[0].decode() for v in start
                   if v.startswith((b"OMPI_", b"PMIX_"))
                   and not v.startswith(b"OMPI_ALLOW_RUN_AS_ROOT"))
    Path(os.environ["PROBE_OUT"]).write_text(json.dumps(names))
"""

# kills its worker (an exit without a word, as the silent start-up exits) the first FAILS
# times it runs (a count in the file COUNT)
CRASH = """
import os
from pathlib import Path

def test_crashes():
    count = Path(os.environ["COUNT"])
    n = int(count.read_text()) if count.exists() else 0
    count.write_text(str(n + 1))
    if n < int(os.environ["FAILS"]):
        os._exit(1)
"""


def _pytest(tmp_path: Path, files: dict[str, str], **env: str):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    cmd = [sys.executable, "-m", "pytest", "-q", "-n", "1", "-p", "conftest",
           "-p", "no:cacheprovider", *files]
    return run_child(cmd, cwd=tmp_path, timeout=300,
                     env=without_mpi_job(PYTHONPATH=str(TESTS), **env))


def _outcomes(stdout: str) -> dict[str, int]:
    """pytest's last line as counts (``1 passed, 1 rerun in 1.3s`` -> passed 1, rerun 1),
    without its warnings, which are not what these tests are about: a fresh-cache suite's
    inner pytest said ``1 passed, 1 warning, 1 rerun`` once (session 58; what warned was not
    in the part of its output the failure showed, which is now all of it)."""
    last = stdout.strip().splitlines()[-1] if stdout.strip() else ""
    counts = {word: int(n) for n, word in re.findall(r"(\d+) (\w+)", last.split(" in ")[0])}
    return {k: v for k, v in counts.items() if not k.startswith("warning")}


def test_the_workers_start_without_the_controllers_mpi_job(tmp_path):
    """The worker's environment at its start has no Open MPI or PMIx variables: the
    controller did not become an MPI singleton (with ``mpi4py`` imported there, as the
    conftest did before session 57, a worker started with 24 of them: the controller's PMIx
    namespace, rank and server)."""
    out = tmp_path / "probe.json"
    r = _pytest(tmp_path, {"test_probe.py": PROBE}, PROBE_OUT=str(out))
    assert r.returncode == 0, r.stdout + r.stderr
    assert json.loads(out.read_text()) == []


def test_a_test_whose_worker_died_in_its_first_test_runs_again(tmp_path):
    count = tmp_path / "count"
    r = _pytest(tmp_path, {"test_crash.py": CRASH}, COUNT=str(count), FAILS="1")
    assert r.returncode == 0, r.stdout + r.stderr
    assert count.read_text() == "2"
    assert _outcomes(r.stdout) == {"passed": 1, "rerun": 1}, r.stdout
    assert (f"test_crash.py::test_crashes: run again 1 of at most {WORKER_RERUNS} times on a "
            "new worker (the worker exited 1)") in r.stdout


def test_a_test_that_kills_every_worker_fails_after_its_reruns(tmp_path):
    count = tmp_path / "count"
    r = _pytest(tmp_path, {"test_crash.py": CRASH}, COUNT=str(count), FAILS="99")
    assert r.returncode == 1, r.stdout + r.stderr
    assert count.read_text() == str(WORKER_RERUNS + 1)
    assert _outcomes(r.stdout) == {"failed": 1, "rerun": WORKER_RERUNS}, r.stdout
    assert f"(the worker {', then '.join(['exited 1'] * WORKER_RERUNS)})" in r.stdout


def test_a_worker_that_had_run_another_test_is_not_replaced_for_a_rerun(tmp_path):
    """The worker ran a test before the one it died in (one worker, the files in order): not
    a start-up exit, so the test fails at once."""
    count = tmp_path / "count"
    r = _pytest(tmp_path, {"test_a.py": "def test_passes():\n    pass\n",
                           "test_crash.py": CRASH}, COUNT=str(count), FAILS="1")
    assert r.returncode == 1, r.stdout + r.stderr
    assert count.read_text() == "1"
    assert _outcomes(r.stdout) == {"failed": 1, "passed": 1}, r.stdout
    assert "rerun" not in r.stdout
