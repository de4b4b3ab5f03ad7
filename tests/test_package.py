"""The package imports as one tree (mvfem, mvfem.forms, mvfem.meshes) from anywhere."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from conftest import run_child

ROOT = Path(__file__).resolve().parents[1]
CODE = ("import mvfem, mvfem.forms, mvfem.meshes, mvfem.forms.kinematics as k; "
        "print(mvfem.forms.__file__); print(mvfem.meshes.__file__)")


@pytest.mark.parametrize("where", ["root", "elsewhere"])
def test_import(where, tmp_path):
    cwd = ROOT if where == "root" else tmp_path
    out = run_child([sys.executable, "-c", CODE], cwd=cwd, capture_output=True, text=True,
                    check=True).stdout.split()
    assert Path(out[0]) == ROOT / "forms" / "__init__.py"
    assert Path(out[1]) == ROOT / "meshes" / "__init__.py"


def test_forms_import_ufl_only():
    """forms/ knows UFL only: importing it must not pull in dolfinx, PETSc or MPI."""
    code = ("import sys; import mvfem.forms; "
            "bad = [m for m in ('dolfinx', 'petsc4py', 'mpi4py', 'gmsh', 'meshio') if m in sys.modules]; "
            "print(','.join(bad))")
    r = run_child([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                  check=True)
    assert r.stdout.strip() == ""


def test_console_script(tmp_path):
    exe = Path(sys.executable).parent / "mvfem"
    r = run_child([str(exe), "materials", "--leaflet", "anterior"], capture_output=True,
                  text=True, cwd=tmp_path)
    assert r.returncode == 0 and "CP05" in r.stdout
