"""Runs of scenes: outputs, exit codes, and the same answer on 1 and 2 processes."""

from __future__ import annotations

import functools
import json
import re
import time
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

import mvfem.run as run_mod
from mvfem.cli import main
from mvfem.errors import InputError
from mvfem.run import solve

#: a patient's annulus and papillary tips (../shared beside the repository)
PATIENT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kaiser_normal1"
DISK = {"title": "coarse disk", "mesh": {"generator": "disk", "radius": 10.0, "size": 1.25},
        "region": [{"law": "mny", "params": "MNY-mean"}],
        "output": {"probes": [{"name": "centre", "point": [0.0, 0.0, 0.0]},
                              {"name": "off", "point": [3.0, 2.0, 0.0]}]}}


@pytest.mark.mpi
def test_same_answer_on_one_and_all_processes(comm):
    """Every rank solves the whole disk alone (COMM_SELF) and together (COMM_WORLD)."""
    together = solve(DISK, comm=comm, progress=False)
    alone = solve(DISK, comm=MPI.COMM_SELF, progress=False)
    assert together.converged and alone.converged
    for name in ("centre", "off"):
        a = np.array(together.summary["probes"][name]["displacement_mm"])
        b = np.array(alone.summary["probes"][name]["displacement_mm"])
        assert np.abs(a - b).max() < 1e-8 * np.abs(b).max()
    for key in ("p5", "median", "p95"):
        a = together.summary["regions"]["membrane"]["radial_cauchy_stress_Pa"][key]
        b = alone.summary["regions"]["membrane"]["radial_cauchy_stress_Pa"][key]
        assert a == pytest.approx(b, rel=1e-8)
    assert together.summary["cells"] == alone.summary["cells"]


def _disk_scene(**fibres):
    from mvfem.scene import load_scene

    scene = dict(DISK, fibres=fibres) if fibres else DISK
    return load_scene(scene)


@pytest.mark.mpi
@pytest.mark.parametrize("fibres,law,key,words", [
    # the disk lies in z = 0: z is its normal at every cell
    ({"direction": [0.0, 0.0, 1.0]}, "mny", "fibres.direction",
     ["[0, 0, 1] lies along the surface's normal", "the fibre"]),
    # axis x (x - c) is along z for every x in the plane of an axis in it
    ({"direction": "circumferential", "axis": [1.0, 0.0, 0.0]}, "svk", "fibres.axis",
     ["circumferential direction about [1, 0, 0]"]),
    # the same with radial fibres: the reports' circumferential direction is still undefined
    ({"direction": "radial", "axis": [1.0, 0.0, 0.0]}, "mny", "fibres.axis",
     ["circumferential direction"]),
])
def test_a_direction_along_the_surfaces_normal_is_an_input_error(comm, fibres, law, key, words):
    """A vector projected on the surface that is the surface's normal has no projection: the
    fibre (or a report's direction) would be 0/0 at every cell and the solve or the report NaN
    (before: the solver stopped at 0 kPa, DIVERGED_FNORM_NAN, exit 3; or the circumferential
    fields all NaN). The error names the key and counts every cell, on any number of ranks."""
    from mvfem.model import build_mesh, build_model

    scene = _disk_scene(**fibres)
    scene = scene.with_changes({"region": [{"law": law, "params": {"mny": "MNY-mean",
                                                                    "svk": "SVK"}[law]}]})
    n_cells = comm.allreduce(build_mesh(scene, comm).mesh.topology.index_map(2).size_local,
                             op=MPI.SUM)
    with pytest.raises(InputError) as e:
        build_model(scene, comm)
    text = str(e.value)
    assert text.startswith(f"{scene.source}: {key}: "), text
    assert f"at {n_cells} of {n_cells} cells (the first near (" in text
    for w in words:
        assert w in text


@pytest.mark.mpi
def test_a_radial_direction_undefined_at_one_cell_is_an_input_error(comm):
    """The radial direction about the axis through a cell's midpoint is zero there (0/0): an
    input error that counts that one cell and names ``fibres.centre``; a centre off it by a
    tenth of a millimetre is accepted (a tangential part of 0.1 mm against NORMAL_ANGLE)."""
    from dolfinx import mesh as dmesh

    from mvfem.model import build_mesh, build_model

    scene = _disk_scene()
    msh = build_mesh(scene, comm).mesh
    n_cells = comm.allreduce(msh.topology.index_map(2).size_local, op=MPI.SUM)
    mid = dmesh.compute_midpoints(msh, 2, np.array([0], dtype=np.int32))[0]
    mid = comm.bcast(mid, root=0)
    with pytest.raises(InputError) as e:
        build_model(scene.with_changes({"fibres.centre": list(mid)}), comm)
    text = str(e.value)
    assert text.startswith(f"{scene.source}: fibres.centre: the radial direction"), text
    assert f"at 1 of {n_cells} cells" in text
    build_model(scene.with_changes({"fibres.centre": list(mid + [0.1, 0.0, 0.0])}), comm)


def test_a_direction_near_the_normal_is_its_projection(comm):
    """A vector 1e-3 rad off the disk's normal, toward x, projects on x at every cell (the
    closed form of the projection on the plane z = 0); an SVK membrane, which has no fibre,
    accepts the normal itself."""
    from mvfem.fields import cell_values
    from mvfem.model import build_model

    m = build_model(_disk_scene(direction=[1e-3, 0.0, 1.0]), comm)
    fibre = cell_values(m.fibre, m.mesh, (3,))
    assert np.abs(fibre - [1.0, 0.0, 0.0]).max() < 1e-12
    scene = _disk_scene(direction=[0.0, 0.0, 1.0]).with_changes(
        {"region": [{"law": "svk", "params": "SVK"}]})
    assert build_model(scene, comm).regions[0].law == "svk"


def test_outputs_and_equilibrium(tmp_path):
    r = solve(DISK, out=tmp_path / "run", progress=False)
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    for key in ("converged", "wall_time_s", "dofs", "cells", "load_steps", "newton_iterations",
                "pressure_Pa", "max_displacement_mm", "max_penetration_mm", "timing", "probes",
                "regions"):
        assert key in s
    t = s["timing"]
    for key in ("assembly_s", "linear_solve_s", "contact_s", "other_s", "reference_step_s"):
        assert t[key] >= 0
    assert t["coarse_start_s"] == 0.0 and t["reference_steps"] == pytest.approx(
        s["wall_time_s"] / t["reference_step_s"], rel=1e-12)
    assert t["assembly_s"] + t["linear_solve_s"] + t["contact_s"] + t["other_s"] == \
        pytest.approx(s["wall_time_s"], rel=1e-12)
    assert s["converged"] and s["equilibrium_residual"] < 1e-7
    assert s["pressure_Pa"] == 16e3
    # the centre of an axisymmetric inflation moves (almost) straight up
    u = s["probes"]["centre"]["displacement_mm"]
    assert u[2] > 5 and abs(u[0]) < 0.02 * u[2] and abs(u[1]) < 0.02 * u[2]
    assert s["max_displacement_mm"] == pytest.approx(np.linalg.norm(u), rel=0.02)
    reg = s["regions"]["membrane"]
    assert reg["area_mm2"] == pytest.approx(np.pi * 100, rel=0.02)
    q = reg["radial_cauchy_stress_Pa"]
    assert 0 < q["p5"] <= q["p25"] <= q["median"] <= q["p75"] <= q["p95"]
    xdmf = (tmp_path / "run" / "fields.xdmf").read_text()
    for name in ("displacement", "radial_almansi_strain", "radial_cauchy_stress_Pa",
                 "circumferential_cauchy_stress_Pa", "region"):
        assert f'Name="{name}"' in xdmf
    assert r.fields["radial_cauchy_stress_Pa"].x.array.min() > 0  # inflated: all in tension


def test_cli_run_and_solver_stopped_short(tmp_path, capsys):
    scene = tmp_path / "disk.toml"
    scene.write_text('title = "disk"\n[mesh]\ngenerator = "disk"\nradius = 10.0\nsize = 1.25\n'
                     '[[region]]\nlaw = "mny"\nparams = "CP08"\n')
    assert main(["run", str(scene), "--out", str(tmp_path / "ok")]) == 0
    assert json.loads((tmp_path / "ok" / "summary.json").read_text())["converged"]
    # a step budget too small to arrive: exit 3, a summary with converged false, a state kept
    code = main(["run", str(scene), "--out", str(tmp_path / "short"), "--set", "solver.max_steps=2",
                 "--set", "solver.first_step=0.05"])
    assert code == 3
    err = capsys.readouterr().err
    assert "solver stopped" in err and "kPa" in err and "Traceback" not in err
    s = json.loads((tmp_path / "short" / "summary.json").read_text())
    assert s["converged"] is False and 0 < s["pressure_Pa"] < 16e3
    assert "max_steps" in s["stop_reason"]
    assert (tmp_path / "short" / "fields.xdmf").exists()


def test_quiet_phases_say_what_is_going_on(tmp_path, capsys, monkeypatch):
    """A set-up or outputs phase still running SLOW_NOTICE_S on says so, once (a first run
    compiles its forms there, seconds with nothing printed); a quicker one says nothing."""
    scene = tmp_path / "disk.toml"
    scene.write_text('title = "disk"\n[mesh]\ngenerator = "disk"\nradius = 10.0\nsize = 2.5\n'
                     '[[region]]\nlaw = "svk"\nparams = "SVK"\n')
    monkeypatch.setattr(run_mod, "SLOW_NOTICE_S", 0.0)
    assert main(["run", str(scene), "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err  # (the log; the results' lines are on stdout)
    assert err.count("setting up the model") == 1
    assert err.count("converged; computing stresses, strains and metrics") == 1
    # each before the line it waits for: the run's first line, the last step's
    assert err.index("setting up the model") < err.index("disk: ") \
        < err.index("converged; computing")
    monkeypatch.setattr(run_mod, "SLOW_NOTICE_S", 1e3)
    assert main(["run", str(scene), "--out", str(tmp_path / "b")]) == 0
    out, err = capsys.readouterr()
    assert "setting up" not in err and "computing stresses" not in err and "disk: " in err
    assert "converged: 16 kPa" in out


def test_an_input_error_after_the_claim_leaves_no_directory(tmp_path, capsys):
    """A run claims its ``--out`` (made, marked) before it builds the model; an input error
    found there (a fibre direction along the disk's normal) is exit code 2 with nothing
    written: the directories it made, parents too, are removed again, and so is the marker it
    put into a user's empty directory (the directory stays); an earlier run's directory keeps
    its files. ``mvfem.solve(out=...)`` the same. Until session 60 the directory was left
    holding only the marker."""
    from mvfem.outputs import MARKER

    scene = tmp_path / "disk.toml"
    scene.write_text('title = "disk"\n[mesh]\ngenerator = "disk"\nradius = 10.0\nsize = 2.5\n'
                     '[fibres]\ndirection = [0, 0, 1]\n'
                     '[[region]]\nlaw = "mny"\nparams = "MNY-mean"\n')
    users = tmp_path / "mine"
    users.mkdir()
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / MARKER).touch()
    (earlier / "summary.json").write_text("{}\n")
    for out in (tmp_path / "new" / "deeper", users, earlier):
        capsys.readouterr()
        assert main(["run", str(scene), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "fibres.direction" in err[0], err
    assert not (tmp_path / "new").exists()
    assert list(users.iterdir()) == []
    assert sorted(p.name for p in earlier.iterdir()) == [MARKER, "summary.json"]
    with pytest.raises(InputError, match="fibres.direction"):
        solve(str(scene), out=tmp_path / "api", progress=False)
    assert not (tmp_path / "api").exists()


def test_output_directories_are_recorded_only_where_they_may_be_given_back(tmp_path):
    """``prepare_out`` records what it made only inside a ``given_back_if_unused`` block,
    which forgets it as the block ends; outside one (bench, calibrate and compare through the
    Python API) the record stayed for the process's life. Inside, an exception gives the new
    directory back; outside, the directory stays."""
    from mvfem import outputs

    before = list(outputs._made)
    outputs.prepare_out(tmp_path / "outside" / "a")
    assert outputs._made == before and (tmp_path / "outside" / "a").is_dir()
    with pytest.raises(RuntimeError):
        with outputs.given_back_if_unused():
            outputs.prepare_out(tmp_path / "inside" / "b")
            assert outputs._made[len(before):] == [tmp_path / "inside", tmp_path / "inside" / "b",
                                                   tmp_path / "inside" / "b" / outputs.MARKER]
            raise RuntimeError("an input error, say")
    assert outputs._made == before and not (tmp_path / "inside").exists()


def test_a_run_into_an_earlier_runs_directory_leaves_none_of_its_files(tmp_path, capsys):
    """A run writing into a directory an earlier run wrote (mvfem's marker in it) removes the
    earlier run's files that it does not write itself: a disk has no chordae, no valve or
    level maps and no reference surface, so a valve's ``chordae.csv`` and maps, left there,
    would read as this run's (until session 55 they were, and the run's "wrote" line listed
    them). Files that are not a run's (a user's notes) stay as they are."""
    from mvfem.outputs import MARKER

    out = tmp_path / "out"
    out.mkdir()
    (out / MARKER).touch()
    stale = ["chordae.csv", "map_level_change.png", "map_radial_strain.png", "distance.vtu",
             "map_distance.png", "summary.json"]
    for name in stale:
        (out / name).write_text("an earlier run's\n")
    (out / "notes.txt").write_text("mine\n")
    scene = tmp_path / "disk.toml"
    scene.write_text('title = "disk"\n[mesh]\ngenerator = "disk"\nradius = 10.0\nsize = 2.5\n'
                     '[[region]]\nlaw = "svk"\nparams = "SVK"\n[output]\nxdmf = false\n')
    capsys.readouterr()
    assert main(["run", str(scene), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    left = sorted(p.name for p in out.iterdir())
    assert left == [MARKER, "notes.txt", "summary.json"], left
    assert (out / "notes.txt").read_text() == "mine\n"
    assert json.loads((out / "summary.json").read_text())["converged"] is True
    assert f"wrote {out}: summary.json\n" in said   # (the run's files, not the notes)


def test_notice_is_said_once_and_never_after_its_phase(caplog, monkeypatch):
    import time

    comm = MPI.COMM_SELF
    n = run_mod._Notice(comm, True, "slow phase")
    with caplog.at_level("INFO", logger="mvfem"):
        monkeypatch.setattr(run_mod, "SLOW_NOTICE_S", 0.05)  # (read as a watch starts)
        with n.watch():  # a phase that lasts until it is said (at most 10 s: a busy machine)
            end = time.monotonic() + 10.0
            while not n.said and time.monotonic() < end:
                time.sleep(0.01)
        with n.watch():  # a second slow phase of the same notice: not said again
            time.sleep(0.3)
        monkeypatch.setattr(run_mod, "SLOW_NOTICE_S", 0.2)
        quick = run_mod._Notice(comm, True, "quick phase")
        with quick.watch():
            pass
        monkeypatch.setattr(run_mod, "SLOW_NOTICE_S", 0.0)
        silent = run_mod._Notice(comm, False, "no progress")
        with silent.watch():
            time.sleep(0.1)
        time.sleep(0.4)  # past the quick phase's threshold: it was cancelled
    said = [r.getMessage() for r in caplog.records]
    assert said == ["slow phase"] and n.said and not quick.said


def test_cli_run_bad_input(tmp_path, capsys):
    scene = tmp_path / "disk.toml"
    scene.write_text('[mesh]\ngenerator = "disk"\n[[region]]\nlaw = "mny"\nparams = "MNY-mean"\n'
                     'thickness = -1\n')
    out = tmp_path / "never"
    assert main(["run", str(scene), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "disk.toml" in err[0] and "region[0].thickness" in err[0]
    assert not out.exists()
    assert main(["run", str(scene), "--set", "nokey"]) == 2


def test_contract_python_api(tmp_path):
    """The API of CONTRACT.md: mvfem.load_scene, with_changes, mvfem.solve, summary, u."""
    import mvfem

    scene = mvfem.load_scene(DISK).with_changes({"load.pressure": "60 mmHg"})
    result = mvfem.solve(scene, out=tmp_path / "x", progress=False)
    assert isinstance(result, mvfem.Result) and result.converged
    assert result.summary["pressure_Pa"] == pytest.approx(60 * 133.322368, rel=1e-8)
    assert result.u.function_space.mesh is result.model.mesh


@pytest.mark.parametrize("follower", [True, False])
def test_potential_is_the_residuals_primitive(follower):
    """The solver's merit, ``Model.potential`` (strain and bending energy minus the pressure's
    potential, -p x swept volume for a follower load), has the residual as its derivative on
    the free dofs: at a random clamped-boundary displacement of a pressurised disk, the
    assembled derivative matches the residual to roundoff, and a central difference of the
    assembled potential along a random direction matches F . v."""
    import ufl
    from dolfinx import fem
    from dolfinx.fem import petsc as fpetsc
    from petsc4py import PETSc

    from mvfem.model import build_model
    from mvfem.scene import load_scene

    scene = load_scene(Path(__file__).parents[1] / "scripts" / "scenes" / "disk_mny.toml")
    scene = scene.with_changes({"mesh.size": 2.0, "load.follower": follower})
    m = build_model(scene, MPI.COMM_WORLD)
    m.pressure.value = m.p_target
    rng = np.random.default_rng(3)
    x = m.V.tabulate_dof_coordinates()
    r = np.linalg.norm(x[:, :2], axis=1)
    n = len(x)
    bump = (1 - (r / r.max()) ** 2)[:, None] * np.array([0.3, -0.2, 1.5])
    m.u.x.array[:] = (bump + 0.05 * rng.standard_normal((n, 3)) * (r < 0.9 * r.max())[:, None]
                      ).ravel()[: m.u.x.array.size]
    fpetsc.set_bc(m.u.vector, m.bcs, scale=0.0)
    m.u.x.scatter_forward()
    v = ufl.TestFunction(m.V)
    dPi = fpetsc.assemble_vector(fem.form(ufl.derivative(m.potential, m.u, v)))
    F = fpetsc.assemble_vector(fem.form(m.residual))
    for b in (dPi, F):
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fpetsc.set_bc(b, m.bcs, scale=0.0)
    assert (dPi - F).norm() < 1e-9 * F.norm()
    # the assembled scalar itself: central difference along a random free direction
    w = fem.Function(m.V)
    w.x.array[:] = rng.standard_normal(w.x.array.size)
    fpetsc.set_bc(w.vector, m.bcs, scale=0.0)
    w.x.scatter_forward()
    Pi = fem.form(m.potential)
    u0 = m.u.x.array.copy()
    h = 1e-5
    vals = []
    for s in (h, -h):
        m.u.x.array[:] = u0 + s * w.x.array
        vals.append(MPI.COMM_WORLD.allreduce(fem.assemble_scalar(Pi), op=MPI.SUM))
    fd = (vals[0] - vals[1]) / (2 * h)
    assert abs(fd - F.dot(w.vector)) < 1e-6 * abs(F.dot(w.vector))


class _DoubleWell:
    """A point term on node 0's z displacement, ``E = (z^2 - 1)^2 / 4``: its Hessian
    ``3 z^2 - 1`` is negative for ``|z| < 1/sqrt(3)``, as the contact barrier's is in some
    directions; ``convex`` clamps it at zero, as contact's blocks are projected."""

    def __init__(self, X, lazy=False):
        self.X, self.convex, self.lazy = X, False, lazy
        self.events = []   # ("call", z) of every evaluation, ("K", z, convex) of every tangent

    def __call__(self, x):
        from mvfem.nodal import Blocks

        z = x[0, 2] - self.X[0, 2]
        self.events.append(("call", z))
        f = np.zeros((1, 1, 3))
        f[0, 0, 2] = z ** 3 - z

        def stiffness():  # (lazy: when first asked for, as contact's are)
            self.events.append(("K", z, self.convex))
            K = np.zeros((1, 3, 3))
            K[0, 2, 2] = max(3 * z ** 2 - 1, 0.0) if self.convex else 3 * z ** 2 - 1
            return K
        return Blocks(np.zeros((1, 1), dtype=np.int64), f,
                      stiffness if self.lazy else stiffness(), (z ** 2 - 1) ** 2 / 4)


def _one_node(term, prefix: str, z0: float = 0.0, c: float = 0.01, potential: bool = True,
              **options):
    """Pseudo-time on one triangle held by a weak spring (``c u . v`` over it, potential
    ``c u . u / 2`` unless not ``potential``), node 0 also under the point term ``term(X)``
    and started at z = ``z0``; ``options`` go to :class:`PseudoTransient`. Returns (info,
    solver, z of node 0, the term). Once the other nodes' z are condensed out of the P1 mass
    matrix, the spring on node 0 is ``c (1/12 - 1/36) = c / 18``."""
    import ufl
    from dolfinx import fem, mesh

    from mvfem.nodal import NodalView, PointTerms
    from mvfem.solver import PseudoTransient, SNESProblem

    domain = ufl.Mesh(ufl.VectorElement("Lagrange", ufl.Cell("triangle", geometric_dimension=3),
                                        1))
    msh = mesh.create_mesh(MPI.COMM_SELF, np.array([[0, 1, 2]], dtype=np.int64),
                           np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), domain)
    V = fem.VectorFunctionSpace(msh, ("Lagrange", 1))
    u, v = fem.Function(V), ufl.TestFunction(V)
    cc = fem.Constant(msh, c)
    view = NodalView(V)
    assert np.allclose(view.X[0], 0.0)
    point = term(view.X)
    pb = SNESProblem(cc * ufl.inner(u, v) * ufl.dx, u, [], prefix=prefix,
                     point_terms=PointTerms(view, [point]),
                     potential=0.5 * cc * ufl.inner(u, u) * ufl.dx if potential else None)
    try:
        w = u.vector.copy()
        w.set(1.0)
        pb.set_proximal(1.0, weights=w, centre=u.vector.copy())
        u.x.array[2] = z0
        ptc = PseudoTransient(pb, **{"atol": 1e-10, **options})
        info = ptc.run()
        return info, ptc, float(u.x.array[2]), point
    finally:
        pb.destroy()


def _double_well(convexify: bool, early: bool = False, lazy: bool = False):
    """Node 0 in the double well, started beside the hump's top (z = 0.05); ``early``:
    projected blocks before Newton's regime too. Returns (info, solver, z, the well)."""
    return _one_node(lambda X: _DoubleWell(X, lazy), f"well{int(convexify)}_", z0=0.05,
                     k0=0.5, max_steps=100, convexify=convexify, convexify_early=early)


def test_pseudo_time_convexifies_where_newton_climbs():
    """In Newton's regime (k below its start) with ``k`` smaller than the well's negative
    curvature, the exact tangent's update points up the hump (``F . du > 0``): it is refused
    however far it is shortened. Solved again with the convexified term it descends: no
    refusal, and the bottom of the well, where z^3 - z + c z / 18 = 0 (the spring on node 0
    once the other nodes' z are condensed out of the P1 mass matrix: c (1/12 - 1/36))."""
    info, ptc, z, _ = _double_well(True)
    assert info.converged
    assert ptc.convexified >= 1
    assert all(r.accepted for r in ptc.history)
    assert abs(z + np.sqrt(1 - 0.01 / 18)) < 1e-9
    info, ptc, z, _ = _double_well(False)  # the same start without: a refusal, every halving up
    assert info.converged and ptc.convexified == 0
    assert not all(r.accepted for r in ptc.history)


class _StiffCubic:
    """A point term on node 0's z displacement, force ``K (z^3 + z - g)``: so stiff (``K`` =
    1e14) that roundoff of the position alone leaves a residual of order ``eps K`` (its root
    is not a double)."""

    def __init__(self, X, K=1e14, g=0.7):
        self.X, self.K, self.g = X, K, g

    def __call__(self, x):
        from mvfem.nodal import Blocks

        z = x[0, 2] - self.X[0, 2]
        f = np.zeros((1, 1, 3))
        f[0, 0, 2] = self.K * (z ** 3 + z - self.g)
        K = np.zeros((1, 3, 3))
        K[0, 2, 2] = self.K * (3 * z ** 2 + 1)
        return Blocks(np.zeros((1, 1), dtype=np.int64), f, K,
                      self.K * (z ** 4 / 4 + z ** 2 / 2 - self.g * z))


def test_pseudo_time_converges_at_its_roundoff_floor():
    """A residual tolerance below what roundoff of the positions allows is never met: node 0
    under a spring of stiffness 1e14 whose force ``K (z^3 + z - g)`` has no double root (the
    residual stays near 0.01). With ``roundoff_floor`` and ``atol`` 1e-3 the run converges
    once the residual is at most eps ||K||_inf (|X|_inf + |u|_inf) (about 0.06 here, within
    ``floor_factor`` = 100 x ``atol``), at the root of z^3 + z (1 + c / 18 K) - g (numpy's
    roots of the cubic) to 1e-12; without the floor, or with ``atol`` 1e-5 (the floor capped
    at 1e-3, below the residual), the same run stops short."""
    from mvfem.solver import EPS

    c, K, g = 0.01, 1e14, 0.7
    roots = np.roots([1.0, 0.0, 1.0 + c / (18 * K), -g])
    root = float(roots[np.argmin(np.abs(roots.imag))].real)
    runs = {}
    for name, options in (("floor", {}), ("off", {"roundoff_floor": False}),
                          ("capped", {"atol": 1e-5})):
        options = {"atol": 1e-3, **options}
        runs[name] = _one_node(lambda X: _StiffCubic(X, K, g), f"floor{name}_", z0=0.0, c=c,
                               k0=1e3, max_steps=60, **options)
    info, ptc, z, _ = runs["floor"]
    assert info.converged and ptc.at_floor
    assert 1e-3 < info.residual_norm <= ptc.floor <= 10 * EPS * K * (3 * root ** 2 + 1) * 2
    assert abs(z - root) < 1e-12
    for name in ("off", "capped"):
        info, ptc, z, _ = runs[name]
        assert not info.converged and not ptc.at_floor, name
        assert abs(z - root) < 1e-12   # (as close: only the test differs)


class _NoRoot:
    """A point term on node 0's z displacement with force ``z^2 + 1``: no equilibrium (with
    the harness's spring ``c z / 18``, c = 0.01, ``z^2 + c z / 18 + 1`` keeps above 0.99), so
    Newton's regime stalls, the residual near 1, however often it restarts."""

    def __init__(self, X):
        self.X = X

    def __call__(self, x):
        from mvfem.nodal import Blocks

        z = x[0, 2] - self.X[0, 2]
        f = np.zeros((1, 1, 3))
        f[0, 0, 2] = z ** 2 + 1
        K = np.zeros((1, 3, 3))
        K[0, 2, 2] = 2 * z
        return Blocks(np.zeros((1, 1), dtype=np.int64), f, K, 0.0)


def test_a_restart_that_did_not_halve_the_residual_is_followed_by_a_slower_one():
    """``PseudoTransient.restart_weight_after``: after ``restart_after`` refusals in a row in
    Newton's regime pseudo-time restarts at ``restart_weight`` x ``k0``; where the last
    restart did not halve the residual, the next one starts ``restart_growth`` x slower than
    it (from nearly the same state the same weight would repeat its path: the ringed patient
    valve on 1.5 mm did, four times). A problem without an equilibrium (residual >= 0.99
    throughout) restarts at 1e3, 1e4, 1e5, 1e6 and 1e7 x ``k0``; a restart that halved the
    residual is followed by one at ``restart_weight`` again."""
    info, ptc, z, _ = _one_node(_NoRoot, "noroot_", z0=1.0, potential=False, k0=2.0,
                                max_steps=2000, convexify=False)
    h = ptc.history
    assert not info.converged and min(r.residual for r in h) > 0.99
    # a restart: after a refusal a weight other than shrink x the refused one's
    starts = [h[i].weight for i in range(1, len(h)) if not h[i - 1].accepted
              and not np.isclose(h[i].weight, ptc.shrink * h[i - 1].weight, rtol=1e-12)]
    assert starts == [2.0 * 10.0 ** e for e in (3, 4, 5, 6, 7)], starts
    assert ptc.restart_weight_after(1e4, 1.0, 0.5) == 1e3     # halved: back to the first
    assert ptc.restart_weight_after(1e4, 1.0, 0.51) == 1e5
    assert ptc.restart_weight_after(1e4, None, 0.51) == 1e3   # (the first restart)


def test_a_stop_at_the_step_budget_gives_the_residual_as_a_fraction_of_the_load():
    """``PseudoTransient.load``: a run that used its steps says its residual and tolerance as
    fractions of the load, the progress lines' unit; without a load, in uN as before. The
    no-root problem's residual, 0.99 or more, is a quarter of a load of 4."""
    pattern = (r"residual (\S+) of the load, above the tolerance 2\.5e-11 of it after 30 "
               r"pseudo-time steps \(solver\.max_steps\)")
    info, ptc, _, _ = _one_node(_NoRoot, "budget_", z0=1.0, potential=False, k0=2.0,
                                max_steps=30, convexify=False, load=4.0)
    m = re.fullmatch(pattern, ptc.stop_reason)
    assert not info.converged and m, ptc.stop_reason
    last = [h.residual for h in ptc.history if h.accepted][-1]
    assert float(m.group(1)) == pytest.approx(last / 4.0, rel=1e-2) and last >= 0.99
    _, plain, _, _ = _one_node(_NoRoot, "budget_plain_", z0=1.0, potential=False, k0=2.0,
                               max_steps=30, convexify=False)
    assert re.fullmatch(r"residual \S+ above the tolerance 1e-10 after 30 pseudo-time steps "
                        r"\(solver\.max_steps\)", plain.stop_reason), plain.stop_reason


def test_pseudo_time_starts_at_its_first_weight():
    """``PseudoTransient.k_first``: the first step is taken at that weight, the weight then
    evolving as from any start. The double well from z = 0.05 with ``k0`` = 0.5: from ``k0``
    the first update goes over the hump to the bottom at z < 0; from a first weight 8 x
    ``k0`` (4), damped, it slides back to the bottom at z > 0; both bottoms are the closed
    form's, z^3 - z + c z / 18 = 0."""
    root = np.sqrt(1 - 0.01 / 18)
    for first, bottom in ((None, -root), (4.0, root)):
        info, ptc, z, _ = _one_node(lambda X: _DoubleWell(X, False), f"wellfirst{first}_",
                                    z0=0.05, k0=0.5, k_first=first, max_steps=100,
                                    convexify=True)
        assert info.converged
        assert ptc.history[0].weight == (0.5 if first is None else first)
        assert abs(z - bottom) < 1e-9


def test_pseudo_time_keeps_projecting_for_a_window_after_a_climb():
    """``PseudoTransient.convex_window``: after an accepted update that had to be solved
    again with the projected blocks, the next ``convex_window`` accepted updates are solved
    with them at once (one tangent each instead of two where the exact one still climbs),
    then the exact tangent is tried first again. In the well: without the window, the exact
    tangent at z = -0.0514 and at -0.174 (both on the hump, 3 z^2 - 1 < 0) climbs and is
    solved again; with a window of 2, the re-solve at -0.0514 is followed by two projected
    tangents at once and then exact ones. Same path and equilibrium (z^3 - z + c z / 18 = 0)."""
    root = np.sqrt(1 - 0.01 / 18)
    runs = {}
    for window in (0, 2):
        info, ptc, z, well = _one_node(lambda X: _DoubleWell(X, lazy=True), f"window{window}_",
                                       z0=0.05, k0=0.5, max_steps=100, convex_window=window)
        assert info.converged and abs(z + root) < 1e-9
        tangents = [e[1:] for e in well.events if e[0] == "K"]
        runs[window] = (ptc, tangents)
    (plain, exact), (kept, ahead) = runs[0], runs[2]
    hump = [i for i, (z, convex) in enumerate(exact) if convex]    # the re-solves
    assert len(hump) == 2 and plain.convexified == 2 and plain.convexified_ahead == 0
    assert all(3 * exact[i][0] ** 2 < 1 and not exact[i - 1][1] for i in hump)
    i = hump[0]
    assert ahead[:i + 1] == exact[:i + 1]      # the same start, the first re-solve included
    assert [convex for _, convex in ahead[i + 1:i + 4]] == [True, True, False]
    assert kept.convexified == 1 and kept.convexified_ahead == 2
    assert len(ahead) == len(exact) - 1        # the second climb's exact tangent saved
    assert [h.weight for h in kept.history] == [h.weight for h in plain.history]


def test_pseudo_time_projects_before_newtons_regime():
    """``PseudoTransient.convexify_early``: before Newton's regime every update is solved with
    the projected blocks, the first one at the start (z = 0.05, where the exact curvature is
    -0.99); a term whose stiffness is computed when asked for (contact's) is evaluated once
    there, the projection applied to the blocks at hand, while an eager one is evaluated
    again; without it the first tangent is the exact one. All reach an equilibrium of the
    well (z^3 - z + c z / 18 = 0)."""
    root = np.sqrt(1 - 0.01 / 18)
    for lazy in (True, False):
        info, ptc, z, well = _double_well(True, early=True, lazy=lazy)
        assert info.converged and abs(abs(z) - root) < 1e-9
        assert ptc.history[0].weight == 0.5        # the first update is before Newton's regime
        first = [("call", 0.05), ("K", 0.05, True)] if lazy else \
            [("call", 0.05), ("K", 0.05, False), ("call", 0.05), ("K", 0.05, True)]
        assert well.events[:len(first)] == first
    info, ptc, z, well = _double_well(True, early=False, lazy=True)
    assert info.converged and abs(abs(z) - root) < 1e-9
    assert well.events[:2] == [("call", 0.05), ("K", 0.05, False)]


class _Wall:
    """A point term on node 0's z displacement: a constant force ``f`` towards a wall ``g``
    below, and the contact barrier ``kappa b(d)``, ``b = -(d - delta)^2 log(d / delta)`` for
    ``d = z + g < delta`` (IPC's, :func:`mvfem.contact.barrier` itself): its force grows fast
    as ``d`` falls, so an update can descend the potential and grow the residual tenfold."""

    def __init__(self, X, f=1.0, kappa=1000.0, g=1.5, delta=1.0):
        self.X, self.f, self.kappa, self.g, self.delta = X, f, kappa, g, delta

    def __call__(self, x):
        from mvfem.contact import barrier
        from mvfem.nodal import Blocks

        z = x[0, 2] - self.X[0, 2]
        d = z + self.g
        if d <= 0:  # through the wall: nothing finite (the barrier gives no force there)
            E = dE = ddE = np.inf
        else:
            b, db, ddb = (float(v) for v in barrier(d, self.delta, self.kappa))
            E, dE, ddE = self.f * z + b, self.f + db, ddb
        f, K = np.zeros((1, 1, 3)), np.zeros((1, 3, 3))
        f[0, 0, 2], K[0, 2, 2] = dE, ddE
        return Blocks(np.zeros((1, 1), dtype=np.int64), f, K, E)

    def equilibrium(self, spring):
        """z where ``f + kappa b'(z + g) + spring z = 0`` (bisection in the barrier's reach;
        ``b'`` written out here, not :func:`mvfem.contact.barrier`'s)."""
        from scipy.optimize import brentq

        def force(z):
            d, dl = z + self.g, self.delta
            return self.f + self.kappa * (-2 * (d - dl) * np.log(d / dl) - (d - dl) ** 2 / d) \
                + spring * z
        return brentq(force, 1e-9 - self.g, self.delta - self.g, xtol=1e-14)


def test_newtons_regime_judges_by_the_potential_alone():
    """In Newton's regime (``k`` below ``k0 = 20``) the update towards the wall grows the
    residual 70-fold. By default the potential judges it: halved until it descends, taken,
    no refusal. With ``reject_descending`` (the rule before session 25) it is refused for the
    residual's growth and ``k`` grows fourfold, as it is by default where the problem has no
    potential (the residual is the merit there) and before Newton's regime. All reach the
    equilibrium of the wall and the spring (``c / 18`` on node 0, as in the double well).
    Checked to fail with the potential judging always, or also before Newton's regime, or
    also without a potential."""
    runs = {old: _one_node(_Wall, f"wall{int(old)}_", k0=20.0, max_steps=200,
                           reject_descending=old) for old in (False, True)}
    runs["no potential"] = _one_node(_Wall, "wall_np_", k0=20.0, max_steps=200,
                                     potential=False)
    for old, (info, _, z, wall) in runs.items():
        z_eq = wall.equilibrium(0.01 / 18)
        assert info.converged and abs(z - z_eq) < 1e-9, (old, z, z_eq)
    new = runs[False][1].history
    assert all(rec.accepted for rec in new)
    assert any(rec.weight < 20.0 and rec.alpha < 1.0 for rec in new)   # halved, taken
    for key in (True, "no potential"):
        grown = [rec for rec in _grown_fivefold(runs[key][1].history) if rec.weight < 20.0]
        assert grown and not any(rec.accepted for rec in grown), key
    # before Newton's regime (k >= k0 = 0.5) the fivefold rule stays: from 2 mm off the wall
    # an update grows the residual 5.4-fold, and is refused
    info, ptc, z, wall = _one_node(lambda X: _Wall(X, g=2.0), "wall_pre_", k0=0.5,
                                   max_steps=200)
    assert info.converged and abs(z - wall.equilibrium(0.01 / 18)) < 1e-9
    grown = [rec for rec in _grown_fivefold(ptc.history) if rec.weight >= 0.5]
    assert grown and not any(rec.accepted for rec in grown)


def _grown_fivefold(history):
    """The records whose residual is more than 5x that of the state they started from."""
    out, r = [], None
    for rec in history:
        if r is not None and rec.residual > 5 * r:
            out.append(rec)
        if rec.accepted:
            r = rec.residual
    return out


def _small_valve(prefix: str, comm=None, **kw):
    """The demo valve at 5 mm under its pressure, and its problem (point terms, potential and
    load as a run has them), on ``comm`` (every process by default)."""
    from mvfem.model import build_model
    from mvfem.scene import load_scene
    from mvfem.solver import SNESProblem

    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    m = build_model(scene.with_changes({"mesh.size": 5.0}), comm or MPI.COMM_WORLD)
    m.pressure.value = m.p_target
    pb = SNESProblem(m.residual, m.u, m.bcs, prefix=prefix, point_terms=m.point_terms,
                     potential=m.energy, load=m.load_form, **kw)
    return m, pb


def _smooth(m, a: float, b: float, c: float) -> np.ndarray:
    """A displacement field (mm) smooth over the valve ``m``, on this rank's owned dofs (a
    PETSc vector's local array)."""
    X = m.V.tabulate_dof_coordinates()[:, :3]
    field = np.stack([a * np.sin(0.2 * X[:, 1]), b * np.cos(0.15 * X[:, 0]),
                      c * np.sin(0.1 * (X[:, 0] + X[:, 1]))], axis=1).ravel()
    return field[: m.u.vector.getLocalSize()]


def _displaced(m, pb, a: float, b: float, c: float, start=None):
    """A new PETSc vector: ``start`` (the problem's ``u``, the open state, by default) plus
    :func:`_smooth` ``(a, b, c)``, zero on the clamped dofs."""
    from dolfinx.fem import petsc as fpetsc

    x = (pb.u.vector if start is None else start).copy()
    x.array[:] += _smooth(m, a, b, c)
    fpetsc.set_bc(x, m.bcs, scale=0.0)
    return x


def test_merit_change_is_the_work_of_the_residual_on_a_valve():
    """The pseudo-time end game judges an update by the change of its merit: the change of the
    strain, bending, chordae and contact energies minus the pressure's work along the update
    (``SNESProblem.load_work``, Simpson's rule). On the valve, whose leaflets have free edges,
    that must be the work of the residual along the update, integrated here by 48-point
    Gauss-Legendre on four sub-intervals; ``-p`` x the swept volume (``Model.potential``) is
    not: its derivative misses a free-edge term as large as the load (checked on the state
    the change starts from)."""
    import ufl
    from dolfinx import fem
    from dolfinx.fem import petsc as fpetsc
    from petsc4py import PETSc

    m, pb = _small_valve("merit_test_")
    try:
        x, y = pb.u.vector.copy(), pb.u.vector.copy()
        x.array[:] = _smooth(m, 0.2, -0.1, 0.5)
        y.array[:] = x.array + _smooth(m, -0.15, 0.2, 0.3)
        for v in (x, y):
            fpetsc.set_bc(v, m.bcs, scale=0.0)
        d = y.copy()
        d.axpy(-1.0, x)
        change = pb.evaluate_energy(y) - pb.evaluate_energy(x) - pb.load_work(x, y)
        g, w = np.polynomial.legendre.leggauss(48)
        work, z = 0.0, x.copy()
        for part in range(4):
            for gi, wi in zip(g, w):
                s = (part + 0.5 * (gi + 1)) / 4
                x.copy(z)
                z.axpy(s, d)
                pb.evaluate_residual(z)
                work += wi / 8 * pb.b.dot(d)
        assert abs(change - work) < 1e-8 * abs(work)
        # the swept-volume potential's derivative against the residual, on the free dofs
        pb._update_u(x)
        free = fem.Function(m.V)
        free.x.array[:] = 1.0
        fpetsc.set_bc(free.vector, m.bcs, scale=0.0)
        dPi = fpetsc.assemble_vector(fem.form(ufl.derivative(m.potential, m.u,
                                                             ufl.TestFunction(m.V))))
        F = fpetsc.assemble_vector(fem.form(m.residual))
        for b in (dPi, F):
            b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            b.pointwiseMult(b, free.vector)
        assert (dPi - F).norm() > 0.1 * F.norm()
    finally:
        pb.destroy()


@pytest.mark.mpi
def test_symmetric_tangent_is_the_tangents_symmetric_part(comm):
    """``SNESProblem.evaluate_tangent(symmetric=True)`` on the valve, displaced smoothly: the
    exact tangent is not symmetric (the follower pressure on leaflets with free edges), the
    symmetric one is its symmetric part ``(A + A^T) / 2``, computed here by PETSc's transpose
    of the exact one, to roundoff; ``symmetric_solver`` (MUMPS's LDL^T of its upper triangle)
    solves it. A problem without a load form, or with an iterative linear solver, has none."""
    from petsc4py import PETSc

    m, pb = _small_valve("sym_tangent_")
    try:
        x = _displaced(m, pb, 0.2, -0.1, 0.5)
        pb.evaluate_tangent(x, 0.0)
        A = pb.A.copy()
        pb.evaluate_tangent(x, 0.0, symmetric=True)
        S = pb.A.copy()
        At = A.transpose(PETSc.Mat())
        skew = A.copy()
        skew.axpy(-1.0, At)
        half = A.copy()
        half.axpy(1.0, At)
        half.scale(0.5)
        half.axpy(-1.0, S)
        norm = A.norm(PETSc.NormType.FROBENIUS)
        assert skew.norm(PETSc.NormType.FROBENIUS) > 1e-3 * norm
        assert half.norm(PETSc.NormType.FROBENIUS) < 1e-12 * norm
        ksp = pb.symmetric_solver()
        assert ksp is not None and ksp.getPC().getType() == "cholesky"
        b, y = x.duplicate(), x.duplicate()
        b.setRandom()
        ksp.setOperators(pb.A)
        ksp.solve(b, y)
        r = b.duplicate()
        S.mult(y, r)
        r.axpy(-1.0, b)
        assert r.norm() < 1e-9 * b.norm()
        for M in (A, S, At, skew, half):
            M.destroy()
    finally:
        pb.destroy()
    _, pb = _small_valve("sym_iterative_", options={"ksp_type": "gmres", "pc_type": "bjacobi"})
    try:
        assert pb.symmetric_solver() is None
    finally:
        pb.destroy()


@pytest.mark.mpi
def test_tangent_is_assembled_at_its_state(comm):
    """``SNESProblem.evaluate_tangent(x)`` is the tangent at ``x`` whatever state the last
    evaluation left in ``u``: after ``load_work(x, y)`` (which ends at ``x + (y - x)``; a
    pseudo-time step's trial ``y`` accepted, the next tangent is at ``y``) it equals, entry
    for entry, the tangent assembled right after the residual at ``x`` (SNES's order). Until
    session 33 its forms were assembled where ``u`` was left."""
    from petsc4py import PETSc

    m, pb = _small_valve("tangent_at_x_")
    try:
        x = _displaced(m, pb, 0.2, -0.1, 0.5)
        y = _displaced(m, pb, -0.3, 0.2, 0.1, start=x)
        pb.evaluate_residual(x)
        pb.evaluate_tangent(x, 0.0)
        at_x = pb.A.copy()
        pb.load_work(x, y)
        pb.evaluate_tangent(x, 0.0)
        diff = at_x.copy()
        diff.axpy(-1.0, pb.A)
        assert diff.norm(PETSc.NormType.INFINITY) == 0.0
        pb.evaluate_tangent(y, 0.0)   # (the tangent at y differs: the check can fail)
        diff = at_x.copy()
        diff.axpy(-1.0, pb.A)
        assert diff.norm(PETSc.NormType.INFINITY) > 1e-3 * at_x.norm(PETSc.NormType.INFINITY)
    finally:
        pb.destroy()


@pytest.mark.mpi
def test_point_terms_reach_the_same_dofs_on_any_number_of_processes(comm):
    """Under mpirun rank 0, which computes the point terms, sends each rank its slice of
    their forces and its rows of their tangent (``PointTerms.add_residual``, ``insert``),
    where it used to set them through PETSc's stash. At a smoothly displaced state of the 5
    mm demo (chordae, hinges, contact), the point terms' forces alone and the whole tangent
    give the same numbering-free numbers on all processes as the same valve built by each
    rank on its own (``COMM_SELF``): the forces' norm, their product with a smooth field
    ``w``, and ``w^T K w`` with and without the point terms, to 1e-10 of each."""
    from dolfinx.fem import petsc as fpetsc

    def numbers(c):
        m, pb = _small_valve(f"same_dofs_{c.size}_", comm=c)
        try:
            x = _displaced(m, pb, 0.2, -0.1, 0.5)
            w = pb.u.vector.copy()
            w.array[:] = _smooth(m, 0.3, 0.7, -0.2)
            fpetsc.set_bc(w, m.bcs, scale=0.0)
            f = pb.b.duplicate()
            f.set(0.0)
            m.point_terms.add_residual(x, f)
            Kw = w.duplicate()
            quad = []
            for terms in (m.point_terms, None):
                pb.point_terms = terms
                pb.evaluate_tangent(x, 0.0)
                pb.A.mult(w, Kw)
                quad.append(w.dot(Kw))
            pb.point_terms = m.point_terms
            return np.array([f.norm(), f.dot(w), quad[0], quad[0] - quad[1]])
        finally:
            pb.destroy()

    alone = numbers(MPI.COMM_SELF)
    every = numbers(comm)
    assert np.all(np.abs(alone) > 0)
    assert np.allclose(every, alone, rtol=1e-10, atol=0), (every, alone)


@pytest.mark.mpi
def test_other_ranks_wait_for_rank_0_asleep_and_lend_it_their_cores(comm, monkeypatch):
    """While rank 0 computes the point terms the others wait in ``nodal.idle_wait``, asleep:
    in 0.4 s of rank 0's work they spend less than 0.1 s of processor time (in a
    ``Barrier`` Open MPI polls: the whole 0.4 s). ``nodal.lend_cores`` gives rank 0's kernels
    as many threads as the ranks on its host have cores (each rank given one core of the
    host's here, so that an earlier lending does not hide a missing one), and leaves rank
    0's own thread on its core. The checks come after the last collective call, so that a
    failure on one rank cannot leave the others waiting."""
    import os
    import socket
    import threading
    import time

    from mvfem import kernels
    from mvfem.nodal import idle_wait, lend_cores

    if comm.rank == 0:
        time.sleep(0.4)
    cpu = time.process_time()
    idle_wait(comm)
    spent = time.process_time() - cpu
    waited = comm.allreduce(spent if comm.rank > 0 else 0.0, op=MPI.MAX)

    for var in ("MVFEM_THREADS", "OMP_NUM_THREADS"):
        monkeypatch.delenv(var, raising=False)
    before = os.sched_getaffinity(0)
    host = socket.gethostname()
    every = comm.allgather((host, sorted(before)))
    cores = sorted(set().union(*[set(cs) for h, cs in every if h == host]))
    narrow = {cores[comm.rank % len(cores)]}
    given = comm.allgather((host, narrow))
    expected = len(set().union(*[cs for h, cs in given if h == given[0][0]]))
    # (the kernels loaded first: OpenMP, started within the narrowed affinity, would take its
    # one core as its default team, and a serial run expects the team it had; the test failed
    # where it ran before any other had loaded them, e.g. alone)
    kernels.threads()
    os.sched_setaffinity(0, narrow)
    try:
        n = lend_cores(comm)
        kept = os.sched_getaffinity(0) == narrow
        team = kernels.load()[1].team_size() if comm.rank == 0 else n
        # the kernels' threads (the main one's siblings) were made with every core allowed
        spread = comm.rank > 0 or comm.size == 1 or any(
            len(os.sched_getaffinity(int(t.name))) == expected
            for t in Path("/proc/self/task").iterdir() if int(t.name) != threading.get_native_id())
    finally:
        os.sched_setaffinity(0, before)
        kernels.threads(kernels._threads())
    team = comm.bcast(team, root=0)
    assert waited < 0.1, waited
    assert kept and comm.allreduce(spread, op=MPI.LAND)
    assert n == team == (expected if comm.size > 1 else kernels.threads())


def test_point_terms_time_includes_their_energy():
    """summary.json ``timing.contact_s`` is the point terms' time (``PointTerms.time_s``),
    taken out of the assembly's: a potential evaluated at a new state (in Newton's regime
    before the residual, since session 33) counts there, inside the assembly's time."""
    m, pb = _small_valve("energy_time_")
    try:
        pt = m.point_terms
        x = _displaced(m, pb, 0.2, -0.1, 0.5)
        t_pt, t_asm = pt.time_s, pb.assembly_s
        pb.evaluate_energy(x)
        spent_pt, spent_asm = pt.time_s - t_pt, pb.assembly_s - t_asm
        assert 0.0 < spent_pt <= spent_asm
    finally:
        pb.destroy()


@pytest.mark.mpi
def test_shifted_tangent_is_the_tangent_at_another_weight(comm):
    """``SNESProblem.shift_tangent(k2)`` after ``evaluate_tangent(x, k1)`` is, entry for entry,
    the matrix of SNES's Jacobian with the proximal weight ``k2`` (``_jacobian``, which adds
    ``k2 W`` to the assembled tangent's diagonal itself; exact and symmetric tangents of the
    valve, displaced smoothly), and it differs from the first by ``(k2 - k1) W`` on the
    diagonal alone, ``W`` the lumped mass (to roundoff)."""
    from petsc4py import PETSc

    from mvfem.model import lumped_mass

    m, pb = _small_valve("shift_tangent_")
    try:
        W = lumped_mass(m)
        pb.set_proximal(0.0, weights=W, centre=pb.u.vector.copy())
        x = _displaced(m, pb, 0.2, -0.1, 0.5)
        k1, k2 = 3.0 * m.stabiliser_scale, 50.0 * m.stabiliser_scale
        for symmetric in (False, True):
            pb.evaluate_tangent(x, k1, symmetric=symmetric)
            first = pb.A.copy()
            pb.shift_tangent(k2)
            shifted = pb.A.copy()
            pb.set_proximal(k2)
            pb._jacobian(pb.snes, x, pb.A, pb.A,
                         form=pb._symmetric_form() if symmetric else None)
            pb.set_proximal(0.0)
            fresh = pb.A.copy()
            fresh.axpy(-1.0, shifted)
            assert fresh.norm(PETSc.NormType.INFINITY) == 0.0
            diff = shifted.copy()
            diff.axpy(-1.0, first)
            expected = W.copy()
            expected.scale(k2 - k1)
            d = diff.getDiagonal()
            d.axpy(-1.0, expected)
            scale = first.norm(PETSc.NormType.INFINITY)
            assert d.norm(PETSc.NormType.INFINITY) < 1e-12 * scale
            zero = W.duplicate()
            zero.set(0.0)
            diff.setDiagonal(zero, addv=PETSc.InsertMode.INSERT_VALUES)
            diff.assemble()
            assert diff.norm(PETSc.NormType.INFINITY) == 0.0
            for M in (first, shifted, fresh, diff):
                M.destroy()
    finally:
        pb.destroy()


def test_refused_update_shifts_the_tangent_it_had():
    """After a refused update (the valve's open state refuses its first ones, ``k`` growing
    fourfold at each) the state is the same, so the next update's tangent is the held one with
    its diagonal shifted to the new ``k`` (:meth:`SNESProblem.shift_tangent`), not evaluated
    again; after an accepted one it is evaluated at the new state. The path is, bit for bit,
    the one where each of those shifts is a fresh evaluation at the held state."""
    from mvfem.model import lumped_mass
    from mvfem.solver import PseudoTransient

    paths = {}
    for mode in ("shift", "fresh"):
        m, pb = _small_valve(f"shift_ptc_{mode}_")
        try:
            calls, held = [], {"inside": False}
            evaluate, shift = pb.evaluate_tangent, pb.shift_tangent

            def record_evaluate(x, k, symmetric=False):
                calls.append(("evaluate", k))
                held.update(x=x.copy(), symmetric=symmetric, inside=True)
                try:
                    evaluate(x, k, symmetric=symmetric)
                finally:
                    held["inside"] = False

            def record_shift(k):
                if held["inside"]:  # evaluate_tangent's own shift
                    return shift(k)
                calls.append(("shift", k))
                if mode == "shift":
                    return shift(k)
                held["inside"] = True
                try:
                    evaluate(held["x"], k, symmetric=held["symmetric"])
                finally:
                    held["inside"] = False
            pb.evaluate_tangent, pb.shift_tangent = record_evaluate, record_shift
            k0 = m.stabiliser_scale
            pb.set_proximal(k0, weights=lumped_mass(m), centre=pb.u.vector.copy())
            ptc = PseudoTransient(pb, k0=k0, atol=1e-30, max_steps=30)
            ptc.run()
            h = ptc.history
            assert len(h) == 30 and len(calls) == 30 and ptc.convexified == 0
            refused = [i for i, r in enumerate(h) if not r.accepted]
            assert len(refused) >= 3 and refused[0] == 0
            for i, r in enumerate(h[1:], 1):
                kind = "shift" if not h[i - 1].accepted else "evaluate"
                assert calls[i] == (kind, r.weight)
                if kind == "shift":
                    assert r.weight == 4 * h[i - 1].weight
            paths[mode] = [(r.weight, r.alpha, r.residual, r.accepted) for r in h]
        finally:
            pb.destroy()
    assert paths["shift"] == paths["fresh"]


def test_newton_regime_skips_the_residual_where_the_potential_rose(monkeypatch):
    """In Newton's regime the potential alone judges an update: a trial whose potential rose
    is halved or the step refused whatever its residual, so that residual is not evaluated
    (nan in the history where a refused step's last trial rose). The 5 mm valve refined once
    (nested) backtracks there on its fine level (47 of 67 steps halved). Its path is, bit for
    bit, the one where every trial's residual is evaluated before its potential (the order
    before session 33), and the states whose residual is skipped are trials only: every
    state whose residual the old order evaluates and the new one does not had its potential
    evaluated."""
    import mvfem.run as run_mod
    from mvfem.scene import load_scene

    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    scene = scene.with_changes({"mesh.size": 5.0, "mesh.refine": 1})
    runs, base = {}, run_mod.PseudoTransient
    for mode in ("skip", "every"):
        levels = []

        class Recorded(base):
            def run(self):
                pb = self.problem
                seen = {"energy": set(), "residual": []}
                evaluate_energy, evaluate_residual = pb.evaluate_energy, pb.evaluate_residual

                def energy(x):
                    if mode == "every":  # the residual first, as at every trial before
                        residual(x)
                    seen["energy"].add(x.array_r.tobytes())
                    return evaluate_energy(x)

                def residual(x):
                    seen["residual"].append(x.array_r.tobytes())
                    return evaluate_residual(x)
                pb.evaluate_energy, pb.evaluate_residual = energy, residual
                try:
                    return super().run()
                finally:
                    pb.evaluate_energy, pb.evaluate_residual = evaluate_energy, evaluate_residual
                    levels.append((self.k0, list(self.history), seen))
        monkeypatch.setattr(run_mod, "PseudoTransient", Recorded)
        res = run_mod.solve(scene, progress=False, write=False)
        assert res.converged and len(levels) >= 2  # the coarse level, the fine one (in parts)
        runs[mode] = levels
    assert len(runs["skip"]) == len(runs["every"])
    for (k0, h, skip), (_, h_every, every) in zip(runs["skip"], runs["every"]):
        path = [(r.weight, r.alpha, r.accepted) + ((r.residual,) if r.accepted else ())
                for r in h]
        assert path == [(r.weight, r.alpha, r.accepted) + ((r.residual,) if r.accepted else ())
                        for r in h_every]
        assert all(np.isfinite(r.residual) for r in h if r.accepted)
        assert all(r.weight < k0 for r in h if np.isnan(r.residual))
        skipped = set(every["residual"]) - set(skip["residual"])
        assert skipped <= skip["energy"]
    halved = [r for k0, h, _ in runs["skip"] for r in h if r.weight < k0 and r.alpha < 1]
    assert len(halved) >= 10 and any(np.isnan(r.residual) for _, h, _ in runs["skip"] for r in h)
    skipped = sum(len(set(every["residual"]) - set(skip["residual"]))
                  for (_, _, skip), (_, _, every) in zip(runs["skip"], runs["every"]))
    assert skipped >= len(halved)


def test_pseudo_time_solves_with_the_symmetric_tangent_above_its_weight():
    """``PseudoTransient.symmetric_above``: from the valve's open state, every update whose
    weight ``k`` is at least that is solved with the symmetric tangent (LDL^T), every other one
    with the exact tangent (LU); ``symmetric=False`` never uses it. The open state's first
    updates are refused (``k`` grows fourfold from ``k0`` at each), so with the threshold at
    ``16 k0`` the first eight steps see both."""
    from mvfem.model import lumped_mass
    from mvfem.solver import PseudoTransient

    for symmetric in (True, False):
        m, pb = _small_valve(f"sym_ptc_{int(symmetric)}_")
        try:
            calls, held = [], {"inside": False}
            exact, shift_tangent = pb.evaluate_tangent, pb.shift_tangent

            def record(x, shift, symmetric=False):
                calls.append((shift, symmetric))
                held.update(symmetric=symmetric, inside=True)
                try:
                    exact(x, shift, symmetric=symmetric)
                finally:
                    held["inside"] = False

            def record_shift(shift):  # a refused update's successor: the held tangent
                if not held["inside"]:
                    calls.append((shift, held["symmetric"]))
                shift_tangent(shift)
            pb.evaluate_tangent, pb.shift_tangent = record, record_shift
            k0 = m.stabiliser_scale
            pb.set_proximal(k0, weights=lumped_mass(m), centre=pb.u.vector.copy())
            ptc = PseudoTransient(pb, k0=k0, atol=1e-30, max_steps=8, symmetric=symmetric,
                                  symmetric_above=16 * k0)
            ptc.run()
            assert len(calls) >= 8
            if symmetric:
                assert all(sym == (k >= 16 * k0) for k, sym in calls)
                assert {sym for _, sym in calls} == {True, False}
            else:
                assert not any(sym for _, sym in calls)
        finally:
            pb.destroy()


@pytest.mark.parametrize("method", ["load-steps", "pseudo-time"])
def test_zero_pressure_without_motion_stays_at_rest(tmp_path, capsys, method):
    """No pressure and no prescribed motion: the reference state is the equilibrium (u = 0,
    zero stress). Before, the force scale of the tolerances was the pressure load, 0: the
    pseudo-time progress line divided by it (ZeroDivisionError) and load stepping could never
    meet a zero tolerance (stopped short, exit 3)."""
    scene = tmp_path / "rest.toml"
    scene.write_text('title = "disk at rest"\n[mesh]\ngenerator = "disk"\nradius = 10.0\n'
                     'size = 2.0\n[[region]]\nlaw = "mny"\nparams = "MNY-mean"\n'
                     '[load]\npressure = 0.0\n')
    # -v: every progress line is formatted and logged
    rc = main(["-v", "run", str(scene), "--out", str(tmp_path / "run"),
               "--set", f"solver.method={method}"])
    assert rc == 0, capsys.readouterr().err[-2000:]
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["converged"] and s["pressure_Pa"] == 0.0
    assert s["max_displacement_mm"] == 0.0
    q = s["regions"]["membrane"]["radial_cauchy_stress_Pa"]
    assert q["p5"] == 0.0 and q["p95"] == 0.0


def test_max_exponent_reads_each_law_on_its_own_region():
    """The exponent cap's check (run._max_exponent) evaluates a region's Fung law on that
    region's cells only: with the anterior leaflet MNY and the posterior SVK, and only nodes of
    posterior cells alone moved (stretched 30 % about the centre), every anterior cell is
    unstrained, so the largest exponent is exactly 0 (each law over every cell read the
    posterior stretch through the MNY law)."""
    from mvfem.model import build_model
    from mvfem.run import _max_exponent
    from mvfem.scene import load_scene

    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    scene = scene.with_changes({"mesh.size": 4.0, "region.1.law": "svk",
                                "region.1.params": {"E": 4e5, "nu": 0.5},
                                "region.1.thickness": 0.5})
    m = build_model(scene, MPI.COMM_SELF)
    tags = m.surface.cell_tags
    ant = tags.find(m.regions[0].tag)
    cells = m.V.dofmap.list.array.reshape(-1, 3)
    n_cells = len(cells)
    post_only = np.setdiff1d(np.arange(len(m.V.tabulate_dof_coordinates())),
                             cells[ant[ant < n_cells]].ravel())
    X = m.V.tabulate_dof_coordinates()
    u = np.zeros_like(X)
    u[post_only] = 0.3 * (X[post_only] - X.mean(axis=0))
    m.u.x.array[:] = u.ravel()
    assert len(post_only) > 20
    assert _max_exponent(m) < 1e-20
    m.regions[1].law = "mny"             # the posterior's stretch, read by an MNY law: > 0
    m.regions[1].constants = m.regions[0].constants
    assert _max_exponent(m) > 1.0


@pytest.mark.parametrize("changes, what", [
    ({"mesh.size": 4.0, "solver.coarse_start": 3.0}, "not coarser than the mesh"),
    ({"mesh.size": 4.0, "solver.coarse_start": [6.0, 3.0]}, "3 mm is not coarser than the mesh"),
    ({"mesh.size": 4.0, "solver.coarse_start": 6.0, "solver.method": "load-steps"},
     "needs the pseudo-time method"),
])
def test_coarse_start_refuses_what_it_cannot_start(changes, what):
    """solver.coarse_start (grid sequencing) refuses, with one line naming the key and before
    any solve: a size not coarser than the mesh, and load steps (they start from zero
    pressure). (A prescribed motion, refused until session 48, ramps on the coarser mesh:
    tests/test_repairs.py.)"""
    from mvfem.errors import InputError
    from mvfem.scene import load_scene

    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    with pytest.raises(InputError, match=r"solver\.coarse_start: .*" + what):
        solve(scene.with_changes(changes), progress=False, write=False)


def test_transfer_scales_a_crossing_state_back():
    """The 6.5 mm demo's closure moved onto the 4 mm mesh crosses (edges through triangles,
    with the offsets and without; measured: 26 and 36 crossings, still some at 0.9-0.7 x the
    state without offsets, none at 0.6 x, by the model's own crossing count; the 6 mm closure
    no longer crossed with the offsets once the generator rounded its sample, session 39).
    ``sequence.transfer`` with no scales refuses it and leaves the open state; with scales
    0.9, 0.8, ..., 0.1 it takes the first of them whose state does not cross, exactly that
    multiple of the state moved without offsets (``transfer_nodes``, the clamp at zero); with
    the default scales it does so, or refuses when that multiple is below them."""
    from mvfem.model import build_model
    from mvfem.scene import load_scene
    from mvfem.sequence import SCALES, transfer, transfer_nodes

    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    coarse = solve(scene.with_changes({"mesh.size": 6.5}), progress=False, write=False)
    assert coarse.converged
    fine = build_model(scene.with_changes({"mesh.size": 4.0}), MPI.COMM_WORLD)
    cv, fv = coarse.model.view, fine.view
    Uc = cv.gather(coarse.model.u.x.array[:coarse.model.V.dofmap.index_map.size_local * 3])
    moved = {}
    for offsets in (True, False):
        moved[offsets], _ = transfer_nodes(cv.X, cv.cells, Uc, fv.X, offsets=offsets)
        moved[offsets][~fv.free] = 0.0
    assert all(fine.contact.penetration(fv.X + U)["intersections"] > 0 for U in moved.values())
    scales = tuple(round(0.1 * i, 1) for i in range(9, 0, -1))
    first = next(s for s in scales
                 if fine.contact.penetration(fv.X + s * moved[False])["intersections"] == 0)
    assert first < 1.0

    out = transfer(coarse.model, fine, scales=())
    assert not out["used"] and out["crossings"] > 0
    assert np.abs(fine.u.x.array).max() == 0.0
    out = transfer(coarse.model, fine)
    assert out["used"] == (first >= min(SCALES))
    assert np.abs(fine.u.x.array).max() == (0.0 if first < min(SCALES) else
                                            np.abs(first * moved[False]).max())
    out = transfer(coarse.model, fine, scales=scales)
    assert out["used"] and out["scale"] == first and not out["offsets"]
    u = fine.u.x.array.reshape(-1, 3)[:len(fv.X)]
    assert np.array_equal(u, first * moved[False])


def test_unfold_smooths_the_nodes_near_a_crossing_and_no_others():
    """``sequence.unfold`` on a flat grid with one node lifted 1 mm (the "crossing": that
    node above 0.2 mm): one sweep puts the node at its neighbours' mean (0: w = 1 there),
    each node within the radius at ``w(d) / deg`` (its neighbours' mean, the lifted node one
    of them; ``w`` the smoothstep of ``1 - d / r``, ``deg`` its neighbour count), and leaves
    every node beyond the radius and every fixed node exactly where it was; a crossing that
    no sweep removes gives None."""
    from mvfem.sequence import unfold

    n = 9
    xs = np.arange(n + 1, dtype=float)
    X = np.column_stack([np.repeat(xs, n + 1), np.tile(xs, n + 1), np.zeros((n + 1) ** 2)])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    cells = np.vstack([np.column_stack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(),
                                        idx[1:, 1:].ravel()]),
                       np.column_stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel(),
                                        idx[:-1, 1:].ravel()])])
    free = np.ones((len(X), 3), dtype=bool)
    i, fixed = idx[4, 4], idx[5, 4]
    free[fixed] = False
    U = np.zeros_like(X)
    U[i, 2] = 1.0
    U[fixed, 2] = 0.3            # a fixed dof keeps whatever it has
    r = 1.6
    out, k = unfold(X, cells, free, U, np.array([i]), r, lambda V: int(V[i, 2] > 0.2))
    assert k == 1 and out[i, 2] == pytest.approx(0.3 / 6)   # its 6 neighbours, one fixed
    d = np.linalg.norm(X - X[i], axis=1)
    t = np.clip(1 - d / r, 0, 1)
    w = t * t * (3 - 2 * t)
    edges = {tuple(sorted(e)) for c in cells for e in ((c[0], c[1]), (c[1], c[2]), (c[2], c[0]))}
    deg = np.bincount(np.array(list(edges)).ravel(), minlength=len(X))
    ring = [j for j in range(len(X)) if 0 < d[j] < r and free[j].all()]
    assert len(ring) == 7
    for j in ring:
        nbrs = [a + b - j for a, b in edges if j in (a, b)]
        assert out[j, 2] == pytest.approx(w[j] * U[nbrs, 2].sum() / deg[j], abs=1e-15)
    beyond = (d >= r) | ~free.all(axis=1)
    assert np.array_equal(out[beyond], U[beyond])
    assert unfold(X, cells, free, U, np.array([i]), r, lambda V: 1, sweeps=3) == (None, 3)
    assert unfold(X, cells, free, U, np.zeros(0, dtype=int), r, lambda V: 1) == (None, 0)


def test_nested_transfer_unfolds_a_crossing_in_place():
    """At 16.5 kPa the demo's closure passes through itself in the posterior leaflet, unseen
    on its own mesh (within the contact's 1 mm exclusion); moved onto the mesh refined once,
    two edges cross a triangle with the offsets and without (README, "Nested levels").
    Which pressures do is the roundoff's path: on a machine with AVX-512 (session 54) 16.5
    kPa does not, 16.25 and 16.75 kPa do; the first of those three that does is used.
    ``transfer`` with sweeps smooths the state without offsets near the crossing until it no
    longer crosses: the nodes farther than the exclusion from the crossing's nodes keep
    exactly the moved state, the crossing's own nodes move; without sweeps the whole state
    is scaled back (0.8). Under 1 mm of the state changes, against the 20 % of every
    displacement that the scaling takes back."""
    from scipy.spatial import cKDTree

    from mvfem.model import build_model
    from mvfem.scene import load_scene
    from mvfem.sequence import UNFOLD_SWEEPS, transfer, transfer_nodes

    demo = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    for pressure in ("16.5 kPa", "16.25 kPa", "16.75 kPa"):
        scene = demo.with_changes({"load.pressure": pressure})
        coarse = solve(scene, progress=False, write=False)
        assert coarse.converged
        fine = build_model(scene.with_changes({"mesh.refine": 1}), MPI.COMM_WORLD)
        cv, fv = coarse.model.view, fine.view
        Uc = cv.gather(coarse.model.u.x.array[:coarse.model.V.dofmap.index_map.size_local * 3])
        moved, _ = transfer_nodes(cv.X, cv.cells, Uc, fv.X, offsets=False)
        moved[~fv.free] = 0.0
        near = fine.contact.crossing_nodes(fv.X + moved)
        if len(near) > 0:
            break
    assert len(near) > 0, "no crossing at any of the three pressures"

    out = transfer(coarse.model, fine, sweeps=0)
    assert out["used"] and out["scale"] < 1.0 and "unfolded" not in out
    out = transfer(coarse.model, fine, sweeps=UNFOLD_SWEEPS)
    assert out["used"] and out["scale"] == 1.0 and not out["offsets"]
    assert 1 <= out["unfolded"] <= UNFOLD_SWEEPS and out["crossings"] > 0
    u = fine.u.x.array.reshape(-1, 3)[:len(fv.X)]
    assert fine.contact.intersections(fv.X + u)[1] == 0
    d, _ = cKDTree(fv.X[near]).query(fv.X)
    far = d >= fine.contact.exclusion
    assert np.array_equal(u[far], moved[far])
    change = np.linalg.norm(u - moved, axis=1)
    assert change[near].max() > 0 and 0 < change.max() < 1.0


def test_crushed_cells_counts_slivers():
    """``sequence.crushed_cells``: two unit right triangles; the second squeezed by moving a
    corner onto the line of the other two (area 0), then to 0.5 % and 2 % of its area: one,
    one and no cell below 1 %; a flipped triangle of full area is not crushed."""
    from mvfem.sequence import CRUSHED_AREA, crushed_cells

    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    cells = np.array([[0, 1, 2], [1, 3, 2]])
    U = np.zeros_like(X)
    assert crushed_cells(X, cells, U) == 0
    for frac, count in ((0.0, 1), (0.005, 1), (0.02, 0)):
        U[3] = (1 - frac) * ((X[1] + X[2]) / 2 - X[3])
        assert crushed_cells(X, cells, U) == count, frac
    U[3] = 2 * ((X[1] + X[2]) / 2 - X[3])  # (through the diagonal: flipped, the same area)
    assert crushed_cells(X, cells, U) == 0 and CRUSHED_AREA == 0.01


def test_transfer_passes_over_a_state_with_crushed_cells(monkeypatch):
    """``transfer`` uses no moved state with a sliver in it (session 51: the resected valve
    with a ring, refined twice, started its finest level from such a state and sat at 1e26
    x the load for 1500 steps). On the open 7 mm demo moved onto itself, the two states are
    stood in: with the offsets one node lifted 1 mm (counted as a crossing while it stands
    0.2 mm above its neighbours' mean), without them a node moved onto its neighbour (two
    slivers, no crossing). The state without the offsets, which the transfer took before, is
    passed over; the one with them is smoothed where it "crosses" and taken (one sweep: the
    lifted node at its neighbours' mean). Without slivers the state without the offsets is
    taken, as before; with no way out (no sweeps, no scales) the transfer refuses, saying
    why."""
    import mvfem.sequence as seq
    from mvfem.model import build_model
    from mvfem.scene import load_scene

    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    scene = scene.with_changes({"mesh.size": 7.0})
    coarse = build_model(scene, MPI.COMM_WORLD)
    fine = build_model(scene, MPI.COMM_WORLD)
    fv = fine.view
    inner = np.flatnonzero(fv.free.all(axis=1))
    k, j = inner[len(inner) // 2], inner[len(inner) // 3]
    nbr = fv.cells[(fv.cells == j).any(axis=1)]
    other = int(next(n for n in nbr.ravel() if n != j and fv.free[n].all()))
    lifted = np.zeros_like(fv.X)
    lifted[k, 2] = 1.0
    squeezed = np.zeros_like(fv.X)
    squeezed[j] = fv.X[other] - fv.X[j]
    assert seq.crushed_cells(fv.X, fv.cells, squeezed) >= 2

    def lift(x):  # node k's height above its neighbours' mean
        ring = np.unique(fv.cells[(fv.cells == k).any(axis=1)])
        ring = ring[ring != k]
        return x[k, 2] - x[ring, 2].mean()

    monkeypatch.setattr(fine.contact, "intersections",
                        lambda x: (0.0, int(lift(x) > 0.2)))
    monkeypatch.setattr(fine.contact, "crossing_nodes", lambda x: np.array([k]))
    states = {True: lifted, False: squeezed}
    monkeypatch.setattr(seq, "transfer_nodes", lambda Xc, cc, Uc, Xf, offsets=True: (
        states[offsets].copy(), np.zeros(len(Xf))))

    def u():
        return fine.u.x.array.reshape(-1, 3)[:len(fv.X)]

    out = seq.transfer(coarse, fine, sweeps=seq.UNFOLD_SWEEPS)
    assert out["used"] and out["offsets"] and out["unfolded"] == 1 and out["crushed"] >= 2
    assert abs(lift(fv.X + u())) < 1e-12 and np.abs(u()[j]).max() == 0.0
    states[False] = np.zeros_like(fv.X)  # (no sliver: taken, as before)
    fine.u.x.array[:] = 0.0
    out = seq.transfer(coarse, fine, sweeps=seq.UNFOLD_SWEEPS)
    assert out["used"] and not out["offsets"] and "crushed" not in out
    states[False] = squeezed
    fine.u.x.array[:] = 0.0
    out = seq.transfer(coarse, fine, sweeps=0, scales=())
    assert not out["used"] and "squeezed below 0.01 of their area" in out["reason"]
    assert np.abs(fine.u.x.array).max() == 0.0


def _spy_transfer(monkeypatch) -> list:
    """The ``sweeps`` each call of ``sequence.transfer`` gets (nested levels smooth a crossing
    away, ``solver.coarse_start`` does not: README, "A crossing smoothed in place")."""
    import mvfem.sequence as sequence

    seen, real = [], sequence.transfer

    def spy(coarse, fine, **kw):
        seen.append(kw.get("sweeps", 0))
        return real(coarse, fine, **kw)
    monkeypatch.setattr(sequence, "transfer", spy)
    return seen


def test_nested_levels_close_a_refined_valve(tmp_path, monkeypatch):
    """``mesh.refine = 1`` (``solver.nested`` by default) on the 5 mm demo valve: the unrefined
    valve is closed first, its closed state carried onto the refined mesh (whose nodes include
    the coarse ones: the transfer moves them exactly, max_distance_mm is the new nodes' offset
    from the coarse triangles, below the sagitta h^2 / (8 R) ~ 0.3 mm of 5 mm edges on the
    ~10 mm radius annulus), and the refined valve converges from it without penetration;
    summary.json says so, one level."""
    from mvfem.scene import load_scene

    from mvfem.sequence import UNFOLD_SWEEPS

    seen = _spy_transfer(monkeypatch)
    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    r = solve(scene.with_changes({"mesh.size": 5.0, "mesh.refine": 1}), out=tmp_path / "out",
              progress=False)
    assert seen == [UNFOLD_SWEEPS]
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    seq = s["coarse_start"]
    assert r.converged and s["max_penetration_mm"] == 0.0
    assert seq["nested"] and seq["refine"] == 0 and seq["used"] and seq["converged"]
    assert 4 * seq["cells"] == s["cells"] and "coarser" not in seq
    assert 0.0 < seq["max_distance_mm"] < 0.5
    assert s["valve"]["regurgitant_orifice_area_mm2"] == 0.0
    # the wall time splits into this level's parts, the coarse start's and the rest
    t = s["timing"]
    assert t["coarse_start_s"] == seq["wall_time_s"] > 0 and t["other_s"] > 0
    assert t["assembly_s"] + t["linear_solve_s"] + t["contact_s"] + t["coarse_start_s"] + \
        t["other_s"] == pytest.approx(s["wall_time_s"], rel=1e-12)


def test_solve_runs_openblas_on_one_thread(monkeypatch):
    """A run's solves, its coarser levels' included, see OpenBLAS on one thread (whose idle
    threads would spin on the kernels' second core: mvfem.run.solve), and the caller's
    thread count is back afterwards."""
    import numpy.linalg  # noqa: F401  (loads the BLAS)

    from mvfem import kernels
    from mvfem.scene import load_scene
    from mvfem.solver import PseudoTransient

    lib = kernels._openblas()
    assert lib is not None, "no OpenBLAS in this process"
    before = lib.openblas_get_num_threads()
    lib.openblas_set_num_threads(2)
    n = lib.openblas_get_num_threads()   # (2, or 1 on one core)
    seen, run = [], PseudoTransient.run

    def counted(self):
        seen.append(lib.openblas_get_num_threads())
        return run(self)

    monkeypatch.setattr(PseudoTransient, "run", counted)
    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    try:
        r = solve(scene.with_changes({"mesh.size": 5.0, "mesh.refine": 1}), progress=False,
                  write=False)
        assert r.converged and seen == [1, 1]     # the coarse level, then the scene's
        assert lib.openblas_get_num_threads() == n
    finally:
        lib.openblas_set_num_threads(before)


@pytest.mark.parametrize("changes, windows, firsts", [
    ({"mesh.size": 5.0, "mesh.refine": 1}, [0, run_mod.NESTED_CONVEX_WINDOW],
     [None, run_mod.NESTED_FIRST_WEIGHT]),
    ({"mesh.size": 4.0, "solver.coarse_start": 5.0}, [0, 0], [None, None]),
])
def test_only_nested_levels_keep_projecting_after_a_climb(monkeypatch, changes, windows,
                                                          firsts):
    """The window of projected blocks after a convexified re-solve
    (``PseudoTransient.convex_window``) is opened on nested levels only: the refined level of
    ``mesh.refine`` gets ``NESTED_CONVEX_WINDOW`` (2), while the open-state start below it and
    a level started from a coarser mesh's closure (``solver.coarse_start``, where it cost 10 %
    more steps; README, "Solving") keep none. Likewise the first weight above the start
    weight (``PseudoTransient.k_first``, ``NESTED_FIRST_WEIGHT`` x ``k0``): nested levels
    only, as measured. Each level's solve is recorded as it starts."""
    from mvfem.scene import load_scene
    from mvfem.solver import PseudoTransient

    assert run_mod.NESTED_CONVEX_WINDOW == 2 and PseudoTransient.convex_window == 0
    assert PseudoTransient.k_first is None
    seen, first, run = [], [], PseudoTransient.run

    def recorded(self):
        seen.append(self.convex_window)
        first.append(None if self.k_first is None else self.k_first / self.k0)
        if self.k_first is not None:  # the solve starts there
            out = run(self)
            assert self.history[0].weight == self.k_first
            return out
        return run(self)

    monkeypatch.setattr(PseudoTransient, "run", recorded)
    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    r = solve(scene.with_changes(changes), progress=False, write=False)
    assert r.converged and r.summary["coarse_start"]["used"]
    assert seen == windows
    assert first == [None if f is None else pytest.approx(f) for f in firsts]


@pytest.mark.parametrize("changes", [{"mesh.refine": 1}, {"solver.coarse_start": 8.0}])
def test_coarser_levels_get_their_own_step_budget_and_tolerance(monkeypatch, changes):
    """``solver.max_steps`` and ``solver.tolerance`` are the scene's own (finest) level's: a
    coarser level of a nested or sequenced start gets its method's default budget and the
    default tolerance. (With the scene's 300 the 2 mm demo level, 304 steps on one path,
    stopped short, and the 1 mm hard cases restarted from the open state; a coarser level
    stopped at a looser tolerance hands the next one a start that costs it what was saved.)
    The coarse solve is stubbed: only the scene it is given is looked at."""
    from types import SimpleNamespace

    import mvfem.run as run
    from mvfem.model import build_model
    from mvfem.scene import load_scene

    demo = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    default_tolerance = demo["solver"]["tolerance"]
    scene = demo.with_changes({"mesh.size": 5.0, "solver.max_steps": 300,
                               "solver.tolerance": 1e-4, **changes})
    seen = []

    def coarse_solve(sc, **kw):
        seen.append(sc)
        return SimpleNamespace(converged=False, summary={"newton_iterations": 0, "cells": 1})

    monkeypatch.setattr(run, "solve", coarse_solve)
    info = run._coarse_start(scene, build_model(scene), MPI.COMM_WORLD, progress=False)
    assert len(seen) == 1 and not info["used"]
    assert scene["solver"]["max_steps"] == 300 and seen[0]["solver"]["max_steps"] is None
    assert scene["solver"]["tolerance"] == 1e-4 != default_tolerance
    assert seen[0]["solver"]["tolerance"] == default_tolerance
    assert seen[0]["solver"]["nested"] == scene["solver"]["nested"]


@pytest.mark.parametrize("changes, what", [
    ({"mesh.generator": "disk", "mesh.refine": 1}, "refines valves only"),
    ({"mesh.refine": 5}, "at most 4"),
    ({"mesh.refine": -1}, ""),
])
def test_refine_refused(changes, what):
    from mvfem.errors import InputError
    from mvfem.scene import load_scene

    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    with pytest.raises(InputError, match=r"mesh\.refine: .*" + what):
        scene.with_changes(changes)


@pytest.mark.parametrize("mesh, slack", [
    ({"generator": "disk", "radius": 10.0, "size": 2.0}, 0.25),
    ({"generator": "disk", "radius": 10.0, "size": 0.7}, 0.25),
    ({"generator": "square", "side": 10.0, "size": 0.8}, 0.25),
    ({"generator": "tube", "radius": 5.0, "length": 10.0, "size": 1.0}, 0.25),
    ({"generator": "octasphere", "radius": 10.0, "refinements": 3}, 0.0),
    ({"generator": "valve", "size": 3.0}, 0.25),
    ({"generator": "valve", "size": 2.0, "refine": 1}, 0.25),
    ({"generator": "valve", "size": 3.0, "ap_diameter": 42.0, "commissural_diameter": 55.5},
     0.25),
    ({"generator": "valve", "size": 2.0, "anterior_height": 12.0, "posterior_height": 8.0},
     0.25),
    ({"generator": "valve", "size": 3.0, "annulus": str(PATIENT / "normal1_annulus_loop_mm.csv"),
      "papillary": str(PATIENT / "normal1_papillary_tips_mm.csv")}, 0.25),
])
def test_expected_cells_are_the_meshes_cells(mesh, slack):
    """The count a mesh is refused by (``model.expected_cells``, before it is made) against
    the cells of the mesh made: gmsh's shapes within a quarter, the octasphere's exact. A
    valve's count scales with its annulus's perimeter and its leaflets' heights (a dilated
    annulus, short leaflets, a patient's annulus; until session 62 every valve was counted as
    the built-in one, and a patient annulus in micrometres was meshed for minutes)."""
    from mvfem.model import build_mesh, expected_cells
    from mvfem.scene import load_scene

    scene = load_scene({"mesh": mesh, "region": [{"law": "svk", "params": "SVK"}]})
    made = build_mesh(scene, MPI.COMM_SELF).mesh.topology.index_map(2).size_local
    assert expected_cells(scene["mesh"], mesh.get("size")) == pytest.approx(made, rel=slack)


def _refusing(monkeypatch, memory: float):
    """Hosts of ``memory`` bytes; returns what makes the valve generator one that must not be
    reached."""
    import sys

    import mvfem.meshes.valve  # noqa: F401 (the package's name `valve` is the function)
    import mvfem.model as model_mod

    valve_mod = sys.modules["mvfem.meshes.valve"]

    monkeypatch.setattr(model_mod, "_host_memory", lambda comm: memory)

    @functools.wraps(valve_mod.valve)   # (its defaults are the estimate's built-in valve)
    def never(*a, **kw):
        raise AssertionError("meshed a mesh the memory would not hold")
    return lambda: monkeypatch.setattr(valve_mod, "valve", never)


def test_a_mesh_the_memory_would_not_hold_is_refused_before_it_is_made(tmp_path, monkeypatch,
                                                                       capsys):
    """With hosts of 100 MB, the demo at 2 mm (about 1100 cells, 44 MB at 40 kB a cell) is
    made and at 1 mm (about 4400 cells, 175 MB) refused before gmsh runs; ``mvfem mesh``
    (1 kB a cell) makes it. With this machine's memory a valve at 1 micrometre (4.4e9 cells)
    is one line and exit code 2 from ``mvfem run`` and ``mvfem mesh``, nothing written."""
    from mvfem.errors import InputError
    from mvfem.model import build_mesh
    from mvfem.scene import load_scene

    demo = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    stop_meshing = _refusing(monkeypatch, 100e6)
    assert build_mesh(demo, MPI.COMM_SELF).mesh.topology.index_map(2).size_local == 1144
    stop_meshing()
    with pytest.raises(InputError) as e:
        build_mesh(demo.with_changes({"mesh.size": 1.0}), MPI.COMM_SELF)
    assert str(e.value).startswith(f"{demo.source}: mesh.size = 1 mm would make about 4,400 "
                                   "cells"), str(e.value)
    assert "more than the 0.093 GiB of memory here (about 2,500 cells fit)" in str(e.value)
    with pytest.raises(AssertionError, match="meshed a mesh"):
        build_mesh(demo.with_changes({"mesh.size": 1.0}), MPI.COMM_SELF, meshing=True)
    monkeypatch.undo()
    capsys.readouterr()  # (the 2 mm valve's line)
    # (the generator's own valve has a 24 mm anterior leaflet, the demo's 23 mm)
    for args, key, out, cells in (
            (["run", str(demo.source), "--set", "mesh.size=0.001"], "mesh.size", tmp_path / "r",
             4400),
            (["mesh", "valve", "--size", "0.001"], "--size", tmp_path / "m.vtu", 4500)):
        assert main(args + ["--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{key} = 0.001 mm would make about {cells} million" in err[0]
        assert not out.exists()


def test_a_patient_annulus_in_micrometres_is_refused_naming_its_length(tmp_path, monkeypatch,
                                                                       capsys):
    """The patient's annulus and tips written in micrometres (1000 x their millimetres): its
    valve at 2 mm would have about 1000 x the cells the millimetre one has (the annulus 1000
    x as long, the leaflets' heights as given), which is refused before gmsh runs, naming the
    file and its length (120 mm x 1000); until session 62 it was counted as the built-in
    valve's 1100 cells and meshed for minutes."""
    from mvfem.model import expected_cells
    from mvfem.scene import load_scene

    paths = {}
    for key, name in (("annulus", "normal1_annulus_loop_mm.csv"),
                      ("papillary", "normal1_papillary_tips_mm.csv")):
        pts = np.loadtxt(PATIENT / name, delimiter=",", skiprows=1)
        paths[key] = tmp_path / f"{key}_um.csv"
        np.savetxt(paths[key], 1000 * pts, delimiter=",")
    scene = tmp_path / "patient_um.toml"
    scene.write_text(f'[mesh]\ngenerator = "valve"\nsize = 2.0\nannulus = "{paths["annulus"]}"\n'
                     f'papillary = "{paths["papillary"]}"\n'
                     '[[region]]\nlabel = "anterior"\nlaw = "mny"\nparams = "MNY-mean"\n'
                     '[[region]]\nlabel = "posterior"\nlaw = "mny"\nparams = "MNY-mean"\n'
                     'leaflet = "posterior"\n')
    mm = load_scene({"mesh": {"generator": "valve", "size": 2.0,
                              "annulus": str(PATIENT / "normal1_annulus_loop_mm.csv")},
                     "region": [{"law": "svk", "params": "SVK"}]})
    um = load_scene(scene)
    assert expected_cells(um["mesh"], 2.0) > 500 * expected_cells(mm["mesh"], 2.0)
    _refusing(monkeypatch, 24 * 2**30)()
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "annulus_um.csv, 1.2e+05 mm around, would make about" in err[0]
    assert not out.exists()


def test_a_valve_file_refined_beyond_the_memory_is_refused(tmp_path, monkeypatch):
    """A valve file's refinements are counted from its triangles (each 4 a refinement)."""
    from mvfem.errors import InputError
    from mvfem.meshes import read_surface
    from mvfem.model import build_mesh
    from mvfem.scene import load_scene

    scene = load_scene(Path(__file__).parents[1] / "scripts" / "scenes" / "valve_imported.toml")
    n = len(read_surface(scene["mesh"]["file"]).triangles)
    _refusing(monkeypatch, 40e3 * n * 16 * 0.99)  # two refinements just do not fit
    with pytest.raises(InputError) as e:
        build_mesh(scene.with_changes({"mesh.refine": 2}), MPI.COMM_SELF)
    counted = re.search(r": mesh\.refine = 2 of \S+ would make about ([0-9,]+) cells",
                        str(e.value))
    assert counted and float(counted[1].replace(",", "")) == pytest.approx(16 * n, rel=0.05)


@pytest.mark.mpi
def test_the_memory_of_one_host_is_counted_once(comm):
    """Ranks on one host share its memory: ``_host_memory`` is this host's physical memory on
    any number of ranks (here all on one machine)."""
    import os

    from mvfem.model import _host_memory

    assert _host_memory(comm) == os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def test_coarse_start_levels_chain(tmp_path, monkeypatch):
    """``solver.coarse_start = [5, 4]`` on the 3 mm demo: the 4 mm closure starts from the 5 mm
    one and the 3 mm from the 4 mm; summary.json nests the levels, each with its own mesh, and
    the 3 mm closure converges without penetration. (Coarser pairs, 8 -> 6 -> 4 mm, refuse
    the transfer: edges of the moved state cross triangles.)"""
    import json

    from mvfem.scene import load_scene

    seen = _spy_transfer(monkeypatch)
    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    r = solve(scene.with_changes({"mesh.size": 3.0, "solver.coarse_start": [4.0, 5.0]}),
              out=tmp_path / "out", progress=False)
    assert seen == [0, 0]
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    seq = s["coarse_start"]
    assert r.converged and s["max_penetration_mm"] == 0.0
    assert (seq["size_mm"], seq["coarser"]["size_mm"]) == (4.0, 5.0)
    assert seq["used"] and seq["coarser"]["used"] and "coarser" not in seq["coarser"]
    assert seq["coarser"]["cells"] < seq["cells"] < s["cells"]
    assert seq["wall_time_s"] > seq["coarser"]["wall_time_s"]


@pytest.mark.mpi
@pytest.mark.parametrize("degree", [1, 2])
def test_lumped_mass_is_positive_and_holds_the_area(degree):
    """The pseudo-time weights (model.lumped_mass) are positive on every free dof and add up to
    3 x the disk's area (one per displacement component): pi R^2 up to the inscribed
    polygon's defect (< 1 %). P2's row sums vanish at the vertices (the integral of a P2
    vertex function is 0), which left the flat disk's first pseudo-time tangent singular there
    (a MUMPS zero pivot, by roundoff, on some machines); P1's are the row sums."""
    from mvfem.model import build_model, lumped_mass
    from mvfem.scene import load_scene

    area = np.pi * 10.0**2
    for clamp in ("boundary", "none"):
        m = build_model(load_scene({**DISK, "solver": {"degree": degree},
                                    "boundary": {"clamp": clamp}}))
        w = lumped_mass(m)
        n = m.V.dofmap.index_map.size_local * 3
        free = np.ones(n, dtype=bool)
        for bc in m.bcs:
            dofs = bc.dof_indices()[0]
            free[dofs[dofs < n]] = False
        assert MPI.COMM_WORLD.allreduce(float(w.array_r[free].min(initial=1.0)), op=MPI.MIN) > 0
        assert float(np.abs(w.array_r[~free]).max(initial=0.0)) == 0.0
    assert 3 * 0.99 * area < w.sum() < 3 * area  # unclamped: every dof counts


def test_prescribed_motion_steps_back_on_a_refusal_and_stops_where_the_lifting_did():
    """``_AdaptiveRamp`` on a stand-in model (a 4-dof rim moving to ``full``, ramp_steps 4: a
    share of 0.25 a call): a lifting cut to half of its way leaves the motion at 0.125, with
    the Dirichlet values there too (the rim where the lifting took it); an accepted step
    lets it on by 0.25; a refused one puts the state and the share back where they were
    before that call, and halves the increment; the call that reaches 1 says so and names
    the step."""
    from types import SimpleNamespace

    from mvfem.run import _AdaptiveRamp

    full = np.array([1.0, -2.0, 0.5, 3.0])
    u = SimpleNamespace(x=SimpleNamespace(array=np.zeros(4), scatter_forward=lambda: None))
    g = np.zeros(4)
    cuts = iter([0.5, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])

    def lift(squeeze=None):
        assert squeeze == run_mod.LIFT_SQUEEZE
        alpha = next(cuts)
        u.x.array += alpha * (g - u.x.array)
        return alpha

    def motion(share):
        g[:] = share * full
        return share, share

    model = SimpleNamespace(ramp_steps=4, u=u, lift=lift, pressure=SimpleNamespace(value=0.0),
                            p_target=16e3, scene={"solver": {"motion": "with-pressure"}})
    history = []
    ramp = _AdaptiveRamp(model, motion, lambda: history)

    def step(accepted):
        history.append(SimpleNamespace(accepted=accepted))

    assert ramp(0.0) is False
    assert ramp.share == pytest.approx(0.125)
    assert np.allclose(u.x.array, 0.125 * full) and np.allclose(g, u.x.array)
    assert model.pressure.value == 16e3
    step(True)
    ramp(0.0)
    assert ramp.share == pytest.approx(0.375) and np.allclose(u.x.array, 0.375 * full)
    step(False)
    ramp(0.0)   # back to 0.125, then half the increment
    assert ramp.share == pytest.approx(0.25) and np.allclose(u.x.array, 0.25 * full)
    shares = []
    while True:
        step(True)
        done = ramp(0.0)
        shares.append(ramp.share)
        if done:
            break
    # increments 0.1875, 0.25, 0.25, then the rest
    assert shares == pytest.approx([0.4375, 0.6875, 0.9375, 1.0])
    assert ramp.completed_at == len(history) + 1 == 7
    assert np.allclose(u.x.array, full)
    # without a lifting (papillary tips, ties: point terms' parameters, the state unmoved) a
    # refused step takes its share back too: 0.25, 0.5 accepted, refused, then 0.25 + 0.125
    set_to = []
    model.lift = None
    history.clear()
    ramp = _AdaptiveRamp(model, lambda share: (set_to.append(share), (share, share))[1],
                         lambda: history)
    ramp(0.0)
    step(True)
    ramp(0.0)
    step(False)
    ramp(0.0)
    assert set_to == pytest.approx([0.25, 0.5, 0.375]) and ramp.share == pytest.approx(0.375)


def test_a_stop_far_below_the_target_reports_no_step_it_did_not_solve():
    """An SVK disk asked for 1e9 kPa stops short (exit code 3 in the CLI). Whatever state it
    reports must be an equilibrium of the pressure it reports, to an intermediate step's
    tolerance at most: until session 55 a step carrying under a millionth of the full load
    passed with no iteration (its tolerance was measured against the full load alone), and
    the run reported the undeformed disk as converged at 996.9 kPa, its residual the whole
    load there (``equilibrium_residual`` 1.0)."""
    from mvfem.scene import load_scene

    scene = load_scene({"mesh": {"generator": "disk", "radius": 10.0, "size": 2.5},
                        "region": [{"law": "svk", "params": "SVK"}],
                        "load": {"pressure": "1e9 kPa"}})
    s = solve(scene, progress=False).summary
    assert not s["converged"]
    assert s["pressure_Pa"] == 0.0 or s["equilibrium_residual"] <= run_mod.STEP_OWN_LOAD, \
        (s["pressure_Pa"], s["equilibrium_residual"], s["max_displacement_mm"])


@pytest.mark.parametrize("first_step", [0.002, 0.01])
def test_a_small_first_step_on_a_flat_fung_disk_still_closes(first_step):
    """A smaller ``solver.first_step`` (what a user tries when a ramp fails) reaches the same
    equilibrium as the default one. Session 55 solved every step to 1e-3 of its own load as
    well: the flat MNY disk's first steps, under 1e-5 of the load, then never settled, and
    the run stopped at 0 kPa (exit code 3)."""
    from mvfem.scene import load_scene

    def centre(fs: float) -> float:
        scene = load_scene({"mesh": {"generator": "disk", "radius": 10.0, "size": 1.25},
                            "region": [{"law": "mny", "params": "CP08"}],
                            "solver": {"first_step": fs},
                            "output": {"probes": [{"name": "c", "point": [0.0, 0.0, 0.0]}]}})
        s = solve(scene, progress=False).summary
        assert s["converged"], (fs, s["pressure_Pa"], s["stop_reason"])
        return s["probes"]["c"]["displacement_mm"][2]

    assert centre(first_step) == pytest.approx(centre(0.1), rel=1e-6)


@pytest.mark.mpi
def test_a_probe_off_the_surface_reads_the_closest_surface_point():
    """A probe off the surface (a curved leaflet's point between its flat facets, a
    sphere's) reads the displacement at the surface's closest point when that lies within its
    cell's diameter, and says how far it was; farther, the run refuses it as bad input
    before it solves (session 56; session 55 solved and then read nothing there, with a
    warning). On a flat disk the closest point of (x, y, h) is (x, y, 0): the probe 0.4 mm
    above a point must read that point's displacement (evaluated on its cell) and a distance
    of 0.4 mm; 40 mm beyond the rim (the disk's cells are at most 2.5 mm x 1.3 across), a
    line that says how far. Until session 55 every point off the cells read nothing. Also
    under ``mpirun -n 2``, where the closest cell may be another rank's."""
    from mvfem.scene import load_scene

    on, above = [1.3, 0.7, 0.0], [1.3, 0.7, 0.4]
    probes = [{"name": "on", "point": on}, {"name": "above", "point": above},
              {"name": "centre", "point": [0.0, 0.0, 0.0]},
              {"name": "over_centre", "point": [0.0, 0.0, -0.4]}]
    disk = {"mesh": {"generator": "disk", "radius": 10.0, "size": 2.5},
            "region": [{"law": "svk", "params": "SVK"}]}
    far = load_scene({**disk, "output": {"probes": [*probes, {"name": "far",
                                                              "point": [50.0, 0.0, 0.0]}]}})
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=r"output\.probes\[4\] \('far'\): point \[50\.0, 0\.0, "
                       r"0\.0\] is 40 mm from the surface, farther than its closest cell's "
                       r"diameter"):
        solve(far, progress=False)
    assert time.perf_counter() - t0 < 5.0   # (refused before the solve)
    scene = load_scene({**disk, "output": {"probes": probes}})
    p = solve(scene, progress=False).summary["probes"]
    assert p["on"]["distance_mm"] == 0.0 and p["centre"]["distance_mm"] == 0.0
    for name, at in (("above", "on"), ("over_centre", "centre")):
        assert p[name]["distance_mm"] == pytest.approx(0.4, rel=1e-12)
        np.testing.assert_allclose(p[name]["displacement_mm"], p[at]["displacement_mm"],
                                   rtol=1e-9, atol=1e-12)
    assert abs(p["on"]["displacement_mm"][2]) > 1.0   # (a deflected disk, not a zero)


def test_the_level_by_level_hint_names_twice_the_size_refined_once():
    """The hint a stopped motion's reason gets (:func:`mvfem.run._level_by_level_hint`):
    twice the generated valve's size refined once, which has about as many cells (each
    refinement splits a triangle in four); nothing for a refined valve, which is already
    closed level by level, nor for a file's mesh, which has no coarser size."""
    from mvfem.run import _level_by_level_hint
    from mvfem.scene import load_scene

    root = Path(__file__).parents[1]
    demo = load_scene(root / "mvfem" / "data" / "demo.toml")
    assert "try mesh.size=3 with mesh.refine=1" in _level_by_level_hint(
        demo.with_changes({"mesh.size": 1.5}))
    assert _level_by_level_hint(demo.with_changes({"mesh.size": 1.5, "mesh.refine": 1})) == ""
    imported = load_scene(root / "scripts" / "scenes" / "valve_imported.toml")
    assert _level_by_level_hint(imported) == ""


def test_the_maps_name_the_leaflets_where_they_lie():
    """The strain and stress maps write each leaflet's name at its facets' area-weighted
    centroid in the view (session 62; the maps named neither): a unit square of 'anterior'
    cells above a 2 x 2 square of 'posterior' ones, each split in two triangles."""
    from types import SimpleNamespace

    from mvfem.maps import _leaflet_places

    p2 = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0, -2], [2, -2], [2, 0]], dtype=float)
    cells = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 0]])
    surface = SimpleNamespace(names={"anterior": 1, "posterior": 2, "annulus": 3})
    places = dict(_leaflet_places(p2, cells, np.array([1, 1, 2, 2]), surface))
    assert set(places) == {"anterior", "posterior"}
    assert places["anterior"] == pytest.approx([0.5, 0.5])
    assert places["posterior"] == pytest.approx([1.0, -1.0])
    assert _leaflet_places(p2, cells, np.zeros(4, dtype=int), surface) == []
