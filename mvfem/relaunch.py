"""Start a command again where it exits 1 at start-up without a word.

    python -m mvfem.relaunch [--retries N] [--within S] -- COMMAND [ARGS...]

Runs ``COMMAND``, passing its output through as it comes, and exits with its exit code. Where
it exits with code 1 within ``S`` seconds (60) of its start having written nothing (on stderr
at most mpirun's own report of a rank that exited so), it is started again, at most ``N``
times (2), each with a line on stderr saying so. Any other outcome is final: a command that
says anything, fails later or with another code is never run twice.

Such exits come in bursts on the shared machines: a Python process exits 1 about 60 ms after
PETSc installs its signal handlers, before its first gmsh call, with no signal and nothing
written (strace); their cause is not established (README, Studies). The test suite's children
(``tests/conftest.py`` ``run_child``) and a study's runs (:mod:`mvfem.study`) are started
again so already; the Makefile runs its top commands (``make demo``, the serial suite, the
``mpirun`` of the MPI suite, ``make bench``, ``make test-hard``) through this module, which
imports nothing of PETSc's, MPI's or gmsh's.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import threading
import time

__all__ = ["RETRIES", "WITHIN_S", "silent_start_exit", "without_mpi_job", "run", "main"]

#: how many times a command that exits silently at start-up is started again (also the suite's
#: ``run_child`` and a study's runs)
RETRIES = 2
#: seconds after its start within which such an exit counts as one
WITHIN_S = 60.0

#: mpirun's own report of a rank that exited with a non-zero code (no word of the rank's)
_MPIRUN_REPORT = re.compile(r"^(-+|Primary job +terminated normally.*|a non-zero exit code\..*|"
                            r"mpirun detected that one or more processes exited.*|"
                            r"the job to be terminated\..*|\s*Process name:.*|"
                            r"\s*Exit code:.*|)$")


def silent_start_exit(returncode: int, seconds: float, stdout: str | None, stderr: str | None,
                      within_s: float = WITHIN_S) -> bool:
    """Whether a command exited 1 at start-up without a word: within ``within_s`` and with
    nothing on stdout or stderr but mpirun's report of it. Every error of ours says one line,
    and Python's own a traceback."""
    return (returncode == 1 and seconds < within_s and not (stdout or "").strip()
            and all(_MPIRUN_REPORT.match(line) for line in (stderr or "").splitlines()))


#: the variables of an MPI job (Open MPI's, its runtime's, PMIx's, PMI's, MPICH's Hydra's)
_MPI_JOB = ("OMPI_", "PMIX_", "PMI_", "ORTE_", "OPAL_", "PRTE_", "HYDRA_", "HYDI_",
            "MPI_LOCALRANKID")


def without_mpi_job(env: dict | None = None, **extra: str) -> dict:
    """A copy of ``env`` (default ``os.environ``) without the variables of an MPI job, but
    ``OMPI_ALLOW_RUN_AS_ROOT*``, with ``extra`` set: the environment of a child that runs as
    a program of its own, serially or under an ``mpirun`` of its own.

    A rank of an ``mpirun`` has them, and so does a process that became an MPI singleton
    (importing ``mpi4py``: Open MPI sets ``OMPI_MCA_ess=singleton``, ``OMPI_MCA_pmix`` and
    ``OMPI_APP_CTX_NUM_PROCS=1`` in its environment), and every process it starts inherits
    them: an ``mpirun`` started with a singleton's variables exits 1 without a word (seen in
    session 52 from pytest-xdist's workers, which pytest starts after its conftest made it a
    singleton)."""
    env = dict(os.environ if env is None else env)
    for k in [k for k in env if k.startswith(_MPI_JOB)
              and not k.startswith("OMPI_ALLOW_RUN_AS_ROOT")]:
        del env[k]
    env.update(extra)
    return env


def _pump(src, dst, kept: list[bytes], limit: int = 1 << 16) -> None:
    """Copy ``src`` to ``dst`` as it comes (flushed), keeping its first ``limit`` bytes. Where
    ``dst`` is closed (a reader that stopped early), ``src`` is still drained: the command
    must not block on a full pipe."""
    size = 0
    for chunk in iter(lambda: src.read1(1 << 14), b""):
        if dst is not None:
            try:
                dst.write(chunk)
                dst.flush()
            except (OSError, ValueError):
                dst = None
        if size < limit:
            kept.append(chunk[: limit - size])
            size += len(kept[-1])
    src.close()


def _once(cmd: list[str], env: dict) -> tuple[int, float, str, str]:
    """Run ``cmd`` once, its output passed through; its code, seconds and (the start of) its
    stdout and stderr."""
    t0 = time.monotonic()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    out: list[bytes] = []
    err: list[bytes] = []
    pumps = [threading.Thread(target=_pump, args=(p.stdout, sys.stdout.buffer, out)),
             threading.Thread(target=_pump, args=(p.stderr, sys.stderr.buffer, err))]
    for t in pumps:
        t.start()
    while True:
        try:
            rc = p.wait()
            break
        except KeyboardInterrupt:  # Ctrl-C reaches the child too (its process group): its end
            continue
    for t in pumps:
        t.join()
    text = [b"".join(part).decode(errors="replace") for part in (out, err)]
    return rc, time.monotonic() - t0, text[0], text[1]


def run(cmd: list[str], retries: int = RETRIES, within_s: float = WITHIN_S) -> int:
    """Run ``cmd`` (started again after a silent start-up exit, at most ``retries`` times);
    its last exit code."""
    # through a pipe Python buffers stdout in blocks: the suite's dots would come minutes late
    env = {**os.environ, "PYTHONUNBUFFERED": os.environ.get("PYTHONUNBUFFERED", "1")}
    if sys.stdout.isatty():
        env.setdefault("PY_COLORS", "1")  # pytest colours its report for the terminal behind
    attempt = 0
    while True:
        try:
            rc, seconds, out, err = _once(cmd, env)
        except OSError as e:
            print(f"mvfem.relaunch: cannot start {cmd[0]}: {e.strerror}", file=sys.stderr)
            return 2
        if attempt == retries or not silent_start_exit(rc, seconds, out, err, within_s):
            return rc
        attempt += 1
        print(f"mvfem.relaunch: {' '.join(cmd)[:200]} exited 1 at start-up without a word "
              f"after {seconds:.1f} s; starting it again ({attempt} of {retries})",
              file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mvfem.relaunch",
                                description="Run a command; start it again where it exits 1 "
                                            "at start-up without a word.")
    p.add_argument("--retries", type=int, default=RETRIES,
                   help=f"starts after the first ({RETRIES})")
    p.add_argument("--within", type=float, default=WITHIN_S,
                   help=f"seconds after its start within which such an exit counts "
                        f"({WITHIN_S:g})")
    p.add_argument("command", nargs=argparse.REMAINDER, help="-- COMMAND [ARGS...]")
    a = p.parse_args(argv)
    cmd = a.command[1:] if a.command[:1] == ["--"] else a.command
    if not cmd:
        p.error("no command given (python -m mvfem.relaunch -- COMMAND [ARGS...])")
    if a.retries < 0 or a.within <= 0:
        p.error("--retries must be at least 0 and --within positive")
    rc = run(cmd, a.retries, a.within)
    return 128 - rc if rc < 0 else rc  # killed by a signal: the shell's code for it


if __name__ == "__main__":
    sys.exit(main())
