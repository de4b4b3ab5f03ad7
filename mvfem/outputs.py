"""Output directories and files shared by all commands."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

from mvfem.errors import InputError

__all__ = ["prepare_out", "prepare_out_on_root", "given_back_if_unused", "write_json",
           "remove_earlier_files", "MARKER", "RUN_FILES"]

#: file that marks a directory as mvfem output, so later runs may write into it again
MARKER = ".mvfem-output"

#: every file a run may write into its output directory (which of them depends on the scene:
#: chordae, a valve's maps, a refined run's level map, a reference surface's distances);
#: a run into a directory an earlier run wrote removes them before writing its own, so that
#: none is left from the earlier run beside this one's (:func:`write_outputs`)
RUN_FILES = ("summary.json", "fields.xdmf", "fields.h5", "chordae.csv",
             "map_radial_strain.png", "map_radial_stress.png", "map_level_change.png",
             "distance.vtu", "map_distance.png")


def check_out(out: str | os.PathLike, option: str = "--out") -> None:
    """Raise the :class:`InputError` :func:`prepare_out` would for what is at ``out`` (a file,
    a user's directory that is not empty), without making anything: a command that builds
    meshes before it claims its directory says so first."""
    path = Path(out)
    try:
        if path.exists() and not path.is_dir():
            raise InputError(f"{option} {path}: exists and is not a directory")
        if path.is_dir() and any(path.iterdir()) and not (path / MARKER).exists():
            raise InputError(f"{option} {path}: directory exists, is not empty and was not "
                             "written by mvfem; choose a new directory")
    except OSError as e:   # (a name too long, no permission to list it)
        raise InputError(f"{option} {path}: cannot be used as the output directory "
                         f"({e.strerror or e})") from None


def prepare_out(out: str | os.PathLike, option: str = "--out") -> Path:
    """Create the output directory, or reuse one that mvfem made before.

    A directory that exists, is not empty and was not made by mvfem is refused, so that nothing
    a user wrote is overwritten; so is one that cannot be made or marked (a parent that is a
    file, no permission, a read-only disk): :class:`InputError` either way.
    """
    path = Path(out)
    try:
        check_out(path, option)
        new = [p for p in (path, *path.parents) if not p.exists()][::-1]  # (outermost first)
        marked = (path / MARKER).exists()
        path.mkdir(parents=True, exist_ok=True)
        (path / MARKER).touch()
        if _blocks:   # (outside any given_back_if_unused block nothing is given back)
            _made.extend(new)
            if not marked:
                _made.append(path / MARKER)
    except OSError as e:   # (a parent that is a file, no permission, a read-only disk)
        raise InputError(f"{option} {path}: cannot be used as the output directory "
                         f"({e.strerror or e})") from None
    return path


#: what :func:`prepare_out` made within :func:`given_back_if_unused` blocks, in order: the
#: directories (with the parents it made) and the markers it put into directories that had
#: none; and how many such blocks are open (outside them nothing is recorded: bench,
#: calibrate and compare called through the Python API would add a few paths a call)
_made: list[Path] = []
_blocks = 0


@contextlib.contextmanager
def given_back_if_unused():
    """What :func:`prepare_out` makes within the block is removed again if the block ends by
    an exception and the directory holds nothing but mvfem's marker: a command claims its
    output directory before it reads the mesh or builds the model, and an input error found
    there (exit code 2, "nothing is written") or a Ctrl-C during the set-up would otherwise
    leave an empty directory behind (or a marker in a user's empty one). A directory this
    command wrote into, or that held anything before, is kept as it is."""
    global _blocks
    since = len(_made)
    _blocks += 1
    try:
        yield
    except BaseException:
        for p in reversed(_made[since:]):   # (innermost first: a marker before its directory)
            try:
                if p.name == MARKER:
                    if {q.name for q in p.parent.iterdir()} == {MARKER}:
                        p.unlink()
                elif not any(p.iterdir()):
                    p.rmdir()
            except OSError:   # (gone already, or written into meanwhile by another process)
                pass
        raise
    finally:
        _blocks -= 1
        del _made[since:]


def write_json(data: dict, path: str | os.PathLike) -> None:
    """Write ``data`` as indented JSON atomically (write a temporary file, then rename)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")
    os.replace(tmp, path)


# --------------------------------------------------------------------------- run outputs
PERCENTILES = (5, 25, 50, 75, 95)
_PNAMES = ("p5", "p25", "median", "p75", "p95")


def _percentiles(values, areas=None) -> dict:
    """The percentiles of the facets' ``values``: each facet counted once (numpy's linear
    interpolation; the paper's per-facet box plots), or, with ``areas``, by the share of the
    leaflet's reference area it covers (:func:`mvfem.distance.weighted_percentile`), which
    does not depend on how the mesh is graded."""
    import numpy as np

    if len(values) == 0:
        return {k: None for k in _PNAMES}
    if areas is None:
        return {k: float(v) for k, v in zip(_PNAMES, np.percentile(values, PERCENTILES))}
    from mvfem.distance import weighted_percentile

    return {k: weighted_percentile(values, areas, q) for k, q in zip(_PNAMES, PERCENTILES)}


def direction_fields(model) -> dict:
    """UFL expressions of the per-facet output quantities (conventions of DESIGN.md).

    Radial Almansi strain ``(1 - 1/lambda_r^2)/2`` with ``lambda_r`` the stretch of the
    reference radial direction; radial Cauchy stress ``r.sigma.r`` with ``r`` the deformed radial
    direction; the same for the circumferential direction.
    """
    import ufl

    from mvfem.forms import fibre_components, fibre_stretch_squared

    k = model.kin
    out = {}
    for name, d0 in (("radial", model.radial), ("circumferential", model.circumferential)):
        A = fibre_components(k.G, k.J0, d0)
        lam2 = fibre_stretch_squared(A, k.G, k.g)
        out[f"{name}_almansi_strain"] = (1 - 1 / lam2) / 2
        d = k.J * A
        out[f"{name}_direction"] = d / ufl.sqrt(ufl.dot(d, d))
    return out


def cell_fields(model) -> dict:
    """DG0 functions of strains and stresses per cell, and the region label of each cell.

    The directions are evaluated once and each region's stress tensor once; the projections
    ``d.sigma.d`` are formed here in numpy.
    """
    import numpy as np
    from dolfinx import fem

    from mvfem.fields import cell_function, per_cell

    msh = model.mesh
    exprs = direction_fields(model)
    V0 = fem.FunctionSpace(msh, ("DG", 0))
    blocks = V0.dofmap.list.array  # DG0 dof of each local cell (owned and ghost)
    fields = {}
    dirs = {}
    for name in ("radial", "circumferential"):
        fields[f"{name}_almansi_strain"] = cell_function(exprs[f"{name}_almansi_strain"], msh,
                                                         name=f"{name}_almansi_strain")
        fields[f"{name}_cauchy_stress_Pa"] = fem.Function(V0, name=f"{name}_cauchy_stress_Pa")
        dirs[name] = per_cell(cell_function(exprs[f"{name}_direction"], msh, (3,)))
    label = fem.Function(V0, name="region")
    n_cells = len(blocks)
    for i, region in enumerate(model.regions):
        if region.tag is None:
            cells = np.arange(n_cells, dtype=np.int32)
        else:
            cells = model.surface.cell_tags.find(region.tag)
        sigma = per_cell(cell_function(model.cauchy(region), msh, (3, 3)))
        for name in ("radial", "circumferential"):
            d = dirs[name][cells]
            values = np.einsum("ci,cij,cj->c", d, sigma[cells], d)
            fields[f"{name}_cauchy_stress_Pa"].x.array[blocks[cells]] = values
        label.x.array[blocks[cells]] = i
    fields["region"] = label
    return fields


def _gather_region_values(model, fields) -> dict:
    """Per-region arrays (on rank 0) of owned-cell values: strain, stress, area."""
    import numpy as np
    import ufl

    from mvfem.fields import cell_values, per_cell

    msh = model.mesh
    n = msh.topology.index_map(2).size_local
    area = cell_values(ufl.sqrt(ufl.det(model.kin.G)) / 2, msh)  # reference area, P1 triangles
    label = per_cell(fields["region"])[:n]
    strain = per_cell(fields["radial_almansi_strain"])[:n]
    stress = per_cell(fields["radial_cauchy_stress_Pa"])[:n]
    out = {}
    for i, region in enumerate(model.regions):
        sel = label == i
        parts = msh.comm.gather((strain[sel], stress[sel], area[sel]), root=0)
        if msh.comm.rank == 0:
            out[region.label] = tuple(np.concatenate([p[j] for p in parts]) for j in range(3))
    return out


def check_probes_reach(model, probes: list, source) -> None:
    """Bad input (:class:`InputError`, exit code 2), said before anything is solved: a probe
    farther from the surface than its closest cell's diameter, which would read nothing
    (:func:`probe_displacements`). Collective."""
    found = probe_displacements(model, probes, warn=False)
    for i, p in enumerate(probes):
        r = found[p["name"]]
        if r["displacement_mm"] is None:
            raise InputError(
                f"{source}: output.probes[{i}] ({p['name']!r}): point {p['point']} is "
                f"{r['distance_mm']:.4g} mm from the surface, farther than its closest cell's "
                "diameter (a probe reads the displacement of a surface point, in reference "
                "coordinates)")


def probe_displacements(model, probes: list, warn: bool = True) -> dict:
    """Displacement at each probe point (reference coordinates, on or near the surface).

    A point on a cell is evaluated there; a point off the surface (a curved leaflet's point
    between its flat facets, a sphere's) at the surface's closest point, where that lies
    within the diameter of its cell (``distance_mm`` says how far it was; 0 on the surface),
    else not at all (``displacement_mm`` null, and a warning with ``warn``; a run refuses
    such a probe before it solves: :func:`check_probes_reach`)."""
    import numpy as np
    from dolfinx import geometry

    msh = model.mesh
    if not probes:
        return {}
    pts = np.array([p["point"] for p in probes], dtype=float)
    tree = geometry.BoundingBoxTree(msh, msh.topology.dim)
    cand = geometry.compute_collisions(tree, pts)
    hits = geometry.compute_colliding_cells(msh, cand, pts)
    local = np.full((len(pts), 3), np.nan)
    n_owned = msh.topology.index_map(2).size_local
    for i in range(len(pts)):
        cells = hits.links(i)
        cells = cells[cells < n_owned]
        if len(cells):
            local[i] = model.u.eval(pts[i], cells[:1])
    everything = msh.comm.allgather(local)
    found = [[a[i] for a in everything if np.all(np.isfinite(a[i]))] for i in range(len(pts))]
    off = [i for i in range(len(pts)) if not found[i]]
    near = _nearest_on_surface(model, pts[off]) if off else []
    result = {}
    for i, p in enumerate(probes):
        if found[i]:
            result[p["name"]] = {"displacement_mm": [float(c) for c in found[i][0]],
                                 "distance_mm": 0.0}
            continue
        d, value = near[off.index(i)]
        result[p["name"]] = {"displacement_mm": None if value is None
                             else [float(c) for c in value], "distance_mm": d}
        if value is None and warn and msh.comm.rank == 0:
            import logging

            logging.getLogger(__name__).warning(
                f"probe {p['name']!r}: point {p['point']} is not on the surface (the closest "
                f"surface point is {d:.3g} mm away, more than its cell's diameter)")
    return result


def _nearest_on_surface(model, pts) -> list:
    """For each point of ``pts`` (m, 3): (distance to the surface, displacement at the
    surface's closest point), the displacement None where that distance exceeds the
    diameter of the closest point's cell. Collective; the same list on every rank."""
    import numpy as np

    from mvfem.contact import closest_point_on_triangles

    msh = model.mesh
    n_owned = msh.topology.index_map(2).size_local
    x = msh.geometry.x
    dofmap = msh.geometry.dofmap
    tri = dofmap.array.reshape(dofmap.num_nodes, -1)[:n_owned, :3]   # (the vertices first)
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    diam = np.max(np.linalg.norm(np.stack([b - a, c - b, a - c]), axis=2), axis=0)
    mine = []
    for p in pts:
        if not len(tri):
            mine.append((np.inf, 0.0, None))
            continue
        d, bary, _ = closest_point_on_triangles(np.broadcast_to(p, a.shape), a, b, c)
        k = int(np.argmin(d))
        q = bary[k, 0] * a[k] + bary[k, 1] * b[k] + bary[k, 2] * c[k]
        mine.append((float(d[k]), float(diam[k]), model.u.eval(q, np.array([k], dtype=np.int32))))
    everyone = msh.comm.allgather(mine)
    out = []
    for j in range(len(pts)):
        d, size, value = min((r[j] for r in everyone), key=lambda r: r[0])
        out.append((d, None if d > size else value))
    return out


def reference_step_time(model, problem) -> float:
    """Seconds for one assembly and one LU factorisation of the tangent at the current state:
    the forms' and the hinge bending's (a point term where it is compiled, mvfem.hinges; the
    chordae and contact are left out), in a matrix of their own pattern. (Until session 17 the
    solver's matrix was copied, which by then had room for every contact coupling of the run,
    and MUMPS factorises those explicit zeros too: the 28,548-dof valve reported 1.72 s that
    way and 0.50 s this way, README "Nested levels".)"""
    import time

    from dolfinx.fem import petsc as fpetsc
    from mpi4py import MPI
    from petsc4py import PETSc

    comm = model.comm
    A = problem.forms_matrix()  # with room for the hinges, not for the contact's couplings
    comm.Barrier()
    t0 = time.perf_counter()
    fpetsc.assemble_matrix(A, problem.a, bcs=problem.bcs)
    A.assemble()
    if model.hinges is not None:
        n_owned = model.V.dofmap.index_map.size_local * 3
        x = model.point_terms.positions(model.u.x.array[:n_owned])
        blk = model.hinges(x) if x is not None else None
        # as the run inserts them: on more than one process each rank gets its own rows
        model.point_terms.insert(A, [blk.csr()] if blk is not None and blk.csr is not None
                                 else [])
    ksp = PETSc.KSP().create(comm)
    ksp.setOperators(A)
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("lu")
    pc.setFactorSolverType("mumps")
    ksp.setUp()
    comm.Barrier()
    dt = time.perf_counter() - t0
    ksp.destroy()
    A.destroy()
    return comm.allreduce(dt, op=MPI.MAX)


def write_xdmf(model, fields: dict, path) -> None:
    """Mesh, displacement (P1) and the per-cell fields in one XDMF file ParaView opens."""
    from dolfinx import fem
    from dolfinx.io import XDMFFile

    u = model.u
    if model.V.ufl_element().degree() != 1:
        V1 = fem.VectorFunctionSpace(model.mesh, ("Lagrange", 1))
        u1 = fem.Function(V1, name="displacement")
        u1.interpolate(u)
        u = u1
    with XDMFFile(model.comm, str(path), "w") as f:
        f.write_mesh(model.mesh)
        f.write_function(u)
        for fn in fields.values():
            f.write_function(fn)


def _summary_problem(written: dict) -> str:
    """What in a run's summary.json a resume cannot start from ('' for nothing): the values
    it reads (the load reached, the pseudo-time weights) of the wrong type or not finite, as
    a hand-edited file may hold (they were tracebacks, or a ZeroDivisionError mid-run)."""
    import math

    def number(v, positive=False):
        return (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                and (v > 0 or not positive))

    p = written.get("pressure_Pa")
    if p is not None and not number(p):
        return f"has pressure_Pa {p!r}, not a finite number"
    pt = written.get("pseudo_time")
    if pt is None:
        return ""
    if not isinstance(pt, dict):
        return f"has pseudo_time {pt!r}, not a table"
    for key in ("weight", "threshold"):
        if not number(pt.get(key), positive=True):
            return f"has pseudo_time.{key} {pt.get(key)!r}, not a positive number"
    if not isinstance(pt.get("symmetric"), bool):
        return f"has pseudo_time.symmetric {pt.get('symmetric')!r}, not true or false"
    w = pt.get("convex_window")
    if isinstance(w, bool) or not isinstance(w, int) or w < 0:
        return f"has pseudo_time.convex_window {w!r}, not a whole number"
    return ""


def read_state(model, directory, option: str = "--resume") -> dict:
    """Set ``model.u`` to the displacement an earlier run of the same mesh wrote in
    ``directory`` (its ``fields.h5``: the P1 displacement at the mesh's nodes, matched to this
    mesh's nodes by their reference coordinates; interpolated into a P2 space); that run's
    summary. Collective.

    Raises:
        InputError: no such run, no displacement written (``output.xdmf = false``), or another
            mesh (its cell count or a node that is not this mesh's).
    """
    import numpy as np
    from dolfinx import fem
    from mpi4py import MPI
    from scipy.spatial import cKDTree

    d = Path(directory)
    comm = model.comm
    where = f"{option} {d}"
    error = written = None
    if comm.rank == 0:
        summary, h5 = d / "summary.json", d / "fields.h5"
        try:
            written = json.loads(summary.read_text())
        except (OSError, ValueError):
            written = None
        problem = _summary_problem(written) if isinstance(written, dict) else ""
        if not isinstance(written, dict):
            error = f"{where}: no run's summary.json there"
        elif problem:
            error = f"{where}: its summary.json {problem}"
        elif not h5.is_file():
            error = (f"{where}: no fields.h5 there (the state is written with output.xdmf = "
                     "true, the default)")
        else:
            cells = model.mesh.topology.index_map(2).size_global
            if written.get("cells") != cells:
                error = (f"{where}: a run of {written.get('cells')} cells, this scene has "
                         f"{cells} (the same mesh is needed: the same mesh keys and refine)")
    error, written = comm.bcast((error, written if error is None else None), root=0)
    if error:
        raise InputError(error)
    import h5py

    try:  # (every rank reads it: a few MB at most)
        with h5py.File(d / "fields.h5", "r") as f:
            xw = np.asarray(f["Mesh/mesh/geometry"], dtype=float)
            uw = np.asarray(f["Function/displacement/0"], dtype=float)
        if xw.ndim != 2 or xw.shape[1] != 3 or uw.shape != xw.shape:
            raise ValueError(f"geometry {xw.shape}, displacement {uw.shape}")
        if not (np.isfinite(uw).all() and np.isfinite(xw).all()):
            raise ValueError("non-finite coordinates or displacements")
    except (OSError, KeyError, ValueError) as e:
        raise InputError(f"{where}: its fields.h5 cannot be read as a run's state "
                         f"({str(e) or type(e).__name__})") from None
    x = model.mesh.geometry.x
    extent = float(np.abs(xw).max(initial=1.0))
    dist, row = cKDTree(xw).query(x)
    far = comm.allreduce(float(dist.max(initial=0.0)), op=MPI.MAX)
    if far > 1e-9 * extent:
        raise InputError(f"{where}: another mesh (a node of this one is {far:.3g} mm from "
                         "every node written there)")
    # P1: a cell's dofs and its vertices (its first three geometry nodes) in the same order
    V1 = fem.VectorFunctionSpace(model.mesh, ("Lagrange", 1))
    u1 = fem.Function(V1)
    geo = model.mesh.geometry.dofmap
    nodes = geo.array.reshape(geo.num_nodes, -1)[:, :3].ravel()
    dofs = V1.dofmap.list.array
    u1.x.array.reshape(-1, V1.dofmap.index_map_bs)[dofs] = uw[row[nodes]]
    model.u.interpolate(u1)
    model.u.x.scatter_forward()
    return written


def _point_outputs(model, contact: bool = True) -> dict:
    """Contact penetration (``contact``) and valve metrics (collective; the same dict on every
    rank)."""
    from mvfem.metrics import valve_metrics

    if model.view is None:
        return {}
    comm = model.comm
    n_owned = model.V.dofmap.index_map.size_local * 3
    x = model.point_terms.positions(model.u.x.array[:n_owned])
    out = None
    if comm.rank == 0:
        out = {}
        if model.contact is not None and contact:
            pen = model.contact.penetration(x)
            out["max_penetration_mm"] = pen["max_penetration_mm"]
            out["contact"] = {"thickness_mm": model.contact.thickness,
                              "stiffness_Pa_per_mm": model.contact.stiffness,
                              "active_pairs": pen["active_pairs"],
                              "min_distance_mm": pen["min_distance_mm"],
                              "max_intrusion_mm": pen["max_intrusion_mm"],
                              "intersections": pen["intersections"],
                              # full searches for the Verlet candidate lists in the run
                              "list_builds": model.contact.list_builds,
                              # lists patched where a few nodes had moved beyond them
                              "list_patches": model.contact.list_patches}
        if getattr(model.surface, "annulus_curve", None) is not None:
            v = valve_metrics(model, x)
            v.pop("_coapting")
            out["valve"] = v
    out = comm.bcast(out, root=0)
    out["_x"] = x
    return out


def write_chordae_csv(model, x, path) -> None:
    """One row per chord: family, leaflet, insertion node, papillary point, lengths, force."""
    import csv

    import numpy as np

    ch = model.chordae
    length = np.linalg.norm(x[ch.node] - ch.anchor, axis=1)
    force = ch.force_N(x)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["chord", "family", "leaflet", "node", "papillary_x_mm", "papillary_y_mm",
                    "papillary_z_mm", "rest_length_mm", "length_mm", "force_N"])
        for i in range(len(ch)):
            w.writerow([i, ch.family[i], ch.leaflet[i] if len(ch.leaflet) else "",
                        int(ch.node[i]), *(f"{a:.6g}" for a in ch.anchor[i]),
                        f"{ch.rest_length[i]:.6g}", f"{length[i]:.6g}", f"{force[i]:.6g}"])


def _write_maps(model, fields, x, out) -> None:
    """PNG maps of radial strain and stress (log10 Pa) on the closed valve (rank 0)."""
    import numpy as np

    from mvfem.fields import per_cell

    if model.view is None or getattr(model.surface, "annulus_curve", None) is None:
        return
    msh = model.mesh
    n = msh.topology.index_map(2).size_local
    parts = msh.comm.gather({k: per_cell(fields[k])[:n] for k in
                             ("radial_almansi_strain", "radial_cauchy_stress_Pa")}, root=0)
    if msh.comm.rank != 0:
        return
    from mvfem.maps import valve_maps

    values = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    valve_maps(x, model.view.cells, model.view.cell_tag, values, model.surface, out)


def remove_earlier_files(out, names=RUN_FILES) -> None:
    """The files ``names`` in ``out`` (an earlier job's, in a directory mvfem made:
    :func:`prepare_out`), removed where present; nothing else in it is touched."""
    for name in names:
        (Path(out) / name).unlink(missing_ok=True)


#: summary.json ``partial`` of a run that Ctrl-C or SIGTERM stopped, until its complete
#: summary.json replaces it (:func:`_write_state_first`)
PARTIAL = ("the state alone: written first after the stop, the metrics, maps and the rest "
           "were not completed")


def _write_state_first(model, fields, s: dict, out) -> None:
    """A stopped run's state (fields.xdmf / .h5) and summary.json so far (``partial``), written
    before the metrics, the maps and the reference step are computed (1.8 s of the 1.9 s of
    the twice-refined demo's outputs; its fields 0.08 s): a Ctrl-C under ``mpirun`` is
    followed by mpirun's SIGTERM ``odls_base_sigkill_timeout`` (1 s) later, which kills a
    run already stopping, and until session 57 such a run left no summary.json, so nothing
    ``--resume`` could go on from. Collective."""
    if model.scene["output"]["xdmf"]:
        write_xdmf(model, fields, out / "fields.xdmf")
    if model.comm.rank == 0:
        write_json({**s, "partial": PARTIAL}, out / "summary.json")
    model.comm.Barrier()


def write_outputs(result, problem, write: bool = True) -> None:
    """Complete ``result.summary`` (displacement, regions, probes, timing) and write files."""
    import time

    import numpy as np
    from mpi4py import MPI

    model = result.model
    comm = model.comm
    s = result.summary
    t0 = time.perf_counter()
    if write:
        if comm.rank == 0:
            remove_earlier_files(result.out)
        comm.Barrier()   # (before any rank writes: the fields are written by every rank)
    nloc = model.V.dofmap.index_map.size_local * 3
    umax = np.linalg.norm(model.u.x.array[:nloc].reshape(-1, 3), axis=1).max(initial=0.0)
    s["max_displacement_mm"] = comm.allreduce(float(umax), op=MPI.MAX)
    s["max_penetration_mm"] = None  # no contact in this scene
    s["probes"] = probe_displacements(model, model.scene["output"]["probes"])
    fields = cell_fields(model)
    early = bool(write and s.get("interrupted"))
    if early:
        _write_state_first(model, fields, s, result.out)
    point = _point_outputs(model)
    s.update({k: v for k, v in point.items() if not k.startswith("_")})
    per_region = _gather_region_values(model, fields)
    regions = {}
    if comm.rank == 0:
        for region in model.regions:
            strain, stress, area = per_region[region.label]
            regions[region.label] = {
                "law": region.law, "set": region.set,
                **({"fibre_compression": False} if region.tension_only else {}),
                "area_mm2": float(area.sum()),
                "radial_almansi_strain": _percentiles(strain),
                "radial_cauchy_stress_Pa": _percentiles(stress),
                # (the same by area: the facets' count weighs the finer parts of a graded mesh)
                "radial_almansi_strain_area_weighted": _percentiles(strain, area),
                "radial_cauchy_stress_Pa_area_weighted": _percentiles(stress, area),
            }
    s["regions"] = comm.bcast(regions, root=0)
    if model.scene["reference"]["file"]:  # closed-state error against a reference surface
        from mvfem.distance import reference_outputs

        s["reference"] = reference_outputs(model, result.out if write else None)
    timing = s["timing"]
    timing["reference_step_s"] = reference_step_time(model, problem)
    if write:
        if model.scene["output"]["xdmf"] and not early:
            write_xdmf(model, fields, result.out / "fields.xdmf")
        if comm.rank == 0 and model.chordae is not None and len(model.chordae):
            write_chordae_csv(model, point["_x"], result.out / "chordae.csv")
        _write_maps(model, fields, point.get("_x"), result.out)
        if comm.rank == 0 and result.level_facets is not None:
            from mvfem.distance import level_change_map

            seq = s["coarse_start"]
            level_change_map(model.surface, result.closed, result.level_facets,
                             seq["distance_to_finer_mm"], (seq["cells"], s["cells"]),
                             result.out / "map_level_change.png")
    timing["output_s"] = time.perf_counter() - t0
    s["wall_time_s"] += timing["output_s"]
    # the coarser levels of a nested or sequenced start, whole (their assembly, solves and
    # contact are not in this level's: README "Speed against error")
    timing["coarse_start_s"] = float((s.get("coarse_start") or {}).get("wall_time_s", 0.0))
    timing["other_s"] = max(s["wall_time_s"] - timing["assembly_s"] - timing["linear_solve_s"]
                            - timing["contact_s"] - timing["coarse_start_s"], 0.0)
    # issue 7's measure: the run's wall time in reference steps
    ref = timing["reference_step_s"]
    timing["reference_steps"] = s["wall_time_s"] / ref if ref > 0 else None
    result.fields = fields
    if write and comm.rank == 0:
        write_json(s, result.out / "summary.json")
    comm.Barrier()


def prepare_out_on_root(out, comm) -> None:
    """:func:`prepare_out` on rank 0, its verdict shared (collective): a refused directory
    is the same InputError on every rank, so no rank runs on alone."""
    from mvfem.errors import InputError

    refused = None
    if comm.rank == 0:
        try:
            prepare_out(out)
        except InputError as e:
            refused = str(e)
    refused = comm.bcast(refused, root=0)
    if refused:
        raise InputError(refused)
