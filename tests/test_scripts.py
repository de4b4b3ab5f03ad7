"""Scripts under scripts/ run as users run them: under mpirun, as a subprocess (smoke tests)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _mpirun(n: int) -> list[str]:
    exe = shutil.which("mpirun")
    if exe is None:
        pytest.fail("mpirun is not installed (make setup installs openmpi-bin)")
    return [exe, "--oversubscribe", "-n", str(n)]


def _env():
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OPENBLAS_NUM_THREADS="1")
    # a pytest already inside mpirun must not hand its MPI environment to the child
    for k in [k for k in env if k.startswith(("OMPI_COMM", "PMIX", "OMPI_MCA_orte"))]:
        env.pop(k)
    return env


def test_biaxial_figures(tmp_path):
    out = tmp_path / "figs"
    r = subprocess.run([*_mpirun(2), sys.executable, str(ROOT / "scripts" / "biaxial_figures.py"),
                        str(out)], capture_output=True, text=True, env=_env(), timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (out / "biaxial.csv").stat().st_size > 100_000
    assert (out / "biaxial_anterior.png").exists() and (out / "biaxial_posterior.png").exists()


def test_solver_options_coarse(tmp_path):
    r = subprocess.run([*_mpirun(2), sys.executable, str(ROOT / "scripts" / "solver_options.py"),
                        "2.5"], capture_output=True, text=True, env=_env(), timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "lu: 11 converged" in r.stdout and "iterative: 11 converged" in r.stdout
