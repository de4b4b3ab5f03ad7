"""Shared fixtures; MPI-safe teardown (dolfinx's own test conftest does the same)."""

from __future__ import annotations

import gc
import subprocess
import time
import warnings

import pytest

from mvfem.cli import quiet_jit_logs  # noqa: E402
from mvfem.relaunch import RETRIES, silent_start_exit, without_mpi_job  # noqa: E402

quiet_jit_logs()


def xdist_controller(config) -> bool:
    """Whether this process is pytest-xdist's controller (``-n N``, N > 0), which runs no
    test and starts the workers. It must not start MPI: importing ``mpi4py`` makes a process
    an Open MPI singleton, which puts its PMIx identity (``PMIX_NAMESPACE``, ``PMIX_RANK``,
    ``PMIX_SERVER_URI*``, ``OMPI_MCA_ess=singleton``, ...) into the environment every process
    it starts inherits, so each worker's own ``MPI_Init`` connected to the controller's PMIx
    server as the controller itself (seen in session 57: 24 such variables in a worker).
    Without MPI in the controller each worker is a singleton of its own."""
    return bool(getattr(config.option, "numprocesses", None)) and \
        not hasattr(config, "workerinput")


def pytest_configure(config):
    """Under mpirun each rank gets its own temporary root, inside one directory made fresh for
    this run: two ranks cleaning pytest's shared numbered directories at once race (seen as a
    failed `make test-mpi`), and a fixed path would be shared by two test runs on one machine.
    (Not in pytest-xdist's controller: :func:`xdist_controller`.)

    gmsh is imported first, before MPI starts, as the CLI does
    (:func:`mvfem.cli._import_gmsh_before_mpi`: its import's ``ldconfig`` child, exiting
    after an Open MPI singleton's ``MPI_Init``, ended the process with code 1 and no word
    about one time in two in the hard cases). Until session 58 each worker started MPI here
    and imported gmsh in its first test that made a mesh: the likely cause of the workers
    that exited 1 without a word in their first test (sessions 56-58; the first
    ``test_distance.py`` test each time, whose fixture meshes a disk)."""
    if xdist_controller(config):
        return
    from mvfem.cli import _import_gmsh_before_mpi

    _import_gmsh_before_mpi()
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    if comm.size > 1 and not config.option.basetemp:
        import os
        import tempfile

        root = tempfile.mkdtemp(prefix="mvfem-pytest-") if comm.rank == 0 else None
        root = comm.bcast(root, root=0)
        config.option.basetemp = os.path.join(root, f"rank{comm.rank}")
        config._mvfem_tmp_root = root


def pytest_unconfigure(config):
    root = getattr(config, "_mvfem_tmp_root", None)
    if root is not None:
        import shutil

        from mpi4py import MPI

        MPI.COMM_WORLD.Barrier()
        if MPI.COMM_WORLD.rank == 0:
            shutil.rmtree(root, ignore_errors=True)


#: how many times a test whose pytest-xdist worker died in it runs again on a new worker, where
#: it was that worker's first test (:func:`pytest_handlecrashitem`)
WORKER_RERUNS = RETRIES

_worker_tests: dict[str, set[str]] = {}  # (the controller's) each worker's reported tests
_worker_reruns: dict[str, list[str]] = {}  # the tests run again: how each worker ended


def _worker_end(worker) -> str:
    """How a dead worker's process ended (``exited 1``, ``killed by SIGKILL``), from its
    ``Popen`` in execnet's gateway (a private attribute: ``unknown`` where it is not there)."""
    import signal

    try:
        rc = worker.gateway._io.popen.wait(timeout=5)
    except Exception:
        return "unknown"
    if rc is None:
        return "unknown"
    if rc < 0:
        try:
            return f"killed by {signal.Signals(-rc).name}"
        except ValueError:
            return f"killed by signal {-rc}"
    return f"exited {rc}"


def pytest_runtest_logreport(report):
    worker = getattr(report, "node", None)  # (a worker's report, in xdist's controller)
    if worker is not None:
        _worker_tests.setdefault(worker.gateway.id, set()).add(report.nodeid)


def pytest_handlecrashitem(crashitem, report, sched):
    """A test whose pytest-xdist worker died in it runs again on the new worker that replaces
    it, at most ``WORKER_RERUNS`` times, where it was that worker's first test: its start-up
    (PETSc's, MPI's, the JIT's first loads), where the silent start-up exits of the suite's
    children happen too (README "Studies"; ``run_child`` starts those children again). Once
    in session 56 a fresh clone's suite failed so: "worker 'gw1' crashed while running
    tests/test_distance.py::test_run_with_reference_reports_the_deflection", its first test,
    which passed in three runs more; session 57's first ``make test`` lost gw1 in the same
    test, again its first, and passed with the rerun. A worker that had run other tests, or a test that kills
    its worker every time, fails as before; each rerun is named in pytest's summary."""
    worker = getattr(report, "node", None)
    if worker is None or not _worker_tests.get(worker.gateway.id, set()) <= {crashitem}:
        return None
    ends = _worker_reruns.get(crashitem, [])
    if len(ends) >= WORKER_RERUNS:
        return None
    try:
        sched.mark_test_pending(crashitem)
    except NotImplementedError:  # (--dist loadscope, loadfile: a scope is not split)
        return None
    _worker_reruns[crashitem] = [*ends, _worker_end(worker)]
    report.outcome = "rerun"
    return None


def pytest_report_teststatus(report):
    if report.outcome == "rerun":
        return "rerun", "R", "RERUN"
    return None


def pytest_terminal_summary(terminalreporter):
    if _worker_reruns:
        terminalreporter.write_sep("=", "run again: their worker died in them, its first test")
        for nodeid, ends in sorted(_worker_reruns.items()):
            terminalreporter.write_line(f"{nodeid}: run again {len(ends)} of at most "
                                        f"{WORKER_RERUNS} times on a new worker (the worker "
                                        f"{', then '.join(ends)})")


@pytest.fixture(autouse=True)
def _no_slow_notice(monkeypatch):
    """In-process runs say nothing of a slow set-up or outputs phase: a test that counts the
    lines on stderr must not depend on the machine's load (the notice came after 1.5 s of a
    valve file's import in a fresh-cache CI run beside another suite, session 62). The tests
    of the notice set ``SLOW_NOTICE_S`` themselves."""
    import mvfem.run as run_mod

    monkeypatch.setattr(run_mod, "SLOW_NOTICE_S", 600.0)


@pytest.fixture(autouse=True)
def _collect_and_sync():
    yield
    from mpi4py import MPI

    gc.collect(0)
    MPI.COMM_WORLD.Barrier()


@pytest.fixture
def comm():
    from mpi4py import MPI

    return MPI.COMM_WORLD


@pytest.fixture
def shared_tmp(tmp_path, comm):
    """A temporary directory that every rank sees (rank 0's)."""
    return comm.bcast(tmp_path, root=0)


def tilted_frame(angle_x: float = 0.4, angle_z: float = 0.9):
    """An orthonormal frame (columns t1, t2, n) rotated away from the coordinate axes."""
    import numpy as np

    cx, sx, cz, sz = np.cos(angle_x), np.sin(angle_x), np.cos(angle_z), np.sin(angle_z)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Rx


def rotation(axis, angle: float):
    """Rotation matrix about ``axis`` by ``angle`` (Rodrigues)."""
    import numpy as np

    k = np.asarray(axis, dtype=float)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


#: how many times the suite starts a child again that exits silently at start-up, and the
#: pause before the n-th new start (n x this): such exits come in bursts (README "Studies"),
#: and in session 52 one child of the suite in two pytest-xdist workers exited so twice in
#: a row, one short of the ``RETRIES`` a study or the Makefile allows
CHILD_RETRIES = 2 * RETRIES
CHILD_PAUSE_S = 1.0


def run_child(cmd, *, retries: int = CHILD_RETRIES, pause_s: float = CHILD_PAUSE_S,
              **kw) -> subprocess.CompletedProcess:
    """``subprocess.run(cmd, capture_output=True, text=True, **kw)``, started again (at most
    ``retries`` times, the n-th after a pause of n x ``pause_s``, each with a warning in
    pytest's summary) where it exits silently at start-up
    (:func:`mvfem.relaunch.silent_start_exit`), as a study starts its runs again
    (``mvfem.study``): in session 32 three fresh-clone suites failed on one such child each.
    A child that says anything, or exits otherwise, is returned as it is. Its environment is
    the suite's without an MPI job's variables (:func:`mvfem.relaunch.without_mpi_job`)
    unless ``env`` is given: a child of this process, an MPI singleton, would otherwise
    inherit the singleton's."""
    kw.setdefault("env", without_mpi_job())
    kw.setdefault("capture_output", True)
    kw.setdefault("text", True)
    check = kw.pop("check", False)
    for attempt in range(retries + 1):
        t0 = time.monotonic()
        r = subprocess.run(cmd, **kw)
        if attempt == retries or not silent_start_exit(r.returncode, time.monotonic() - t0,
                                                        r.stdout, r.stderr):
            break
        warnings.warn(f"{' '.join(map(str, cmd))[:200]}: exited 1 at start-up without a "
                      f"word after {time.monotonic() - t0:.1f} s; started again "
                      f"({attempt + 1} of {retries})")
        time.sleep((attempt + 1) * pause_s)
    if check:
        r.check_returncode()
    return r


def write_run_files(spec, out, refine: int, target=None, met: bool = True, **summary):
    """The files a study's run leaves (a stand-in for the run, for the tests of the study
    runner and of ``repair-compare``): run.json, and summary.json with the cells of the mesh
    refined ``refine`` times (100 x 4^refine), ``summary``'s entries and, where the run
    asked for ``mesh.accuracy`` (``target``), the record of a run that stopped refining
    there (``met``: whether the target was met)."""
    import json

    from mvfem.study import _spec_record

    d = spec.dir(out)
    d.mkdir(parents=True, exist_ok=True)
    rec = {"converged": True, "cells": 100 * 4 ** refine, **summary}
    if target:
        rec["accuracy"] = {"target_mm": target, "refine": refine, "most_refine": 2,
                           "moved_mm": 0.01, "met": met}
    (d / "summary.json").write_text(json.dumps(rec))
    (d / "run.json").write_text(json.dumps(_spec_record(spec)))
