"""From a scene to the discrete problem: mesh, unknown, and the terms the scene asks for.

Only what a scene needs is built: a region energy per ``[[region]]``, a follower (or dead)
pressure, and a clamp on the boundary when there is one. The start-up stabiliser is not a form:
the solver adds it as a lumped diagonal (see :func:`lumped_mass`).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field

import numpy as np
import ufl
from dolfinx import fem, mesh as dmesh
from mpi4py import MPI
from petsc4py import PETSc

from mvfem import jitcache
from mvfem.errors import InputError
from mvfem.forms import (LAWS, Membrane, cauchy_stress, is_exponential, membrane, unit_normal,
                         uses_fibre)
from mvfem.forms.pressure import dead_potential, dead_pressure, follower_potential, follower_pressure
from mvfem.scene import Scene

jitcache.install()  # a form's compile left by a dead process is done again, not waited for

__all__ = ["Model", "Region", "build_model", "build_mesh", "default_size", "lumped_mass"]

log = logging.getLogger(__name__)

#: cap on the exponent of the Fung laws in simulations: e^200 c0 is ~1e89 Pa, far beyond any
#: tissue state, so only wild Newton iterates meet it (and a final state that does is rejected)
MAX_EXPONENT = 200.0
#: default bending modulus of valve leaflets (Pa): a thin-shell stiffness that suppresses
#: mesh-scale wrinkles where the membrane is compressed (forms/bending.py)
VALVE_BENDING_MODULUS = 100e3


@dataclass
class Region:
    """One material region: its cells, law, parameters (Constants) and energy density."""

    label: str
    tag: int | None
    law: str
    set: str
    constants: dict
    thickness: fem.Constant
    W: ufl.core.expr.Expr
    dx: ufl.Measure
    #: the fibre term bears tension only (scene ``region.fibre_compression = false``)
    tension_only: bool = False


@dataclass
class Model:
    """The discrete membrane problem of a scene.

    Attributes:
        pressure: the applied pressure (Pa), a Constant the load stepper scales.
        stabiliser_scale: weight (Pa/mm) of the start-up proximal term ``k M (u - u_prev)``.
        residual: the residual form of the problem as posed (internal - pressure).
        load_form: the pressure term alone at the current pressure (its norm scales tolerances).
    """

    scene: Scene
    surface: object
    mesh: dmesh.Mesh
    V: fem.FunctionSpace
    u: fem.Function
    kin: Membrane
    regions: list[Region]
    fibre: ufl.core.expr.Expr
    radial: ufl.core.expr.Expr
    circumferential: ufl.core.expr.Expr
    pressure: fem.Constant
    p_target: float
    stabiliser_scale: float
    energy: ufl.core.expr.Expr
    residual: ufl.core.expr.Expr
    load_form: ufl.core.expr.Expr
    bcs: list
    quadrature_degree: int
    length_scale: float
    info: dict = field(default_factory=dict)
    view: object = None          # mvfem.nodal.NodalView when there are point terms
    chordae: object = None       # mvfem.chordae.Chordae
    contact: object = None       # mvfem.contact.Contact
    point_terms: object = None   # mvfem.nodal.PointTerms
    phi: object = None           # Laplace coordinate of a valve (0 annulus, 1 free edge)
    #: total potential of the forms (strain and bending energy minus the pressure's
    #: potential; point terms add theirs), whose derivative is ``residual`` only where the
    #: whole boundary is held (a clamped disk): on leaflets with free edges the pressure has
    #: no potential, and the solver's merit is ``energy`` with the pressure's work
    #: integrated along each update (mvfem.solver.SNESProblem.load_work)
    potential: ufl.core.expr.Expr | None = None
    ties: object = None          # mvfem.ties.Ties (clips, sutures)
    #: bending stiffness D of the hinges when they are a point term (mvfem.hinges; 0 when the
    #: bending is in ``energy`` as a form, or absent)
    hinge_stiffness: float = 0.0
    hinges: object = None        # mvfem.hinges.Hinges
    #: the Fung laws' exponent cap (a Constant, MAX_EXPONENT but while a sequenced start
    #: relaxes, mvfem/sequence.py)
    exponent_cap: object = None
    #: a zero bilinear form over the interior facets: room in the matrix for the hinges'
    #: couplings (SNESProblem's ``sparsity``); None without hinges
    sparsity: object = None
    #: prescribed motion (annulus target, ring, papillary target, ties drawn tight):
    #: ``ramp(f)`` sets it to the fraction f in [0, 1]; None when the scene has none
    ramp: object = None
    ramp_steps: int = 0
    #: ``lift(squeeze=None)``: move ``u`` onto the current Dirichlet values of the prescribed
    #: loop, the interior by the harmonic extension of the change (a start for the next
    #: solve), as far as the contact allows; returns the fraction taken
    lift: object = None
    #: rank 0: global node indices of a prescribed (moving) annulus, in order along it
    annulus_nodes: object = None
    motion: dict = field(default_factory=dict)  # what is prescribed (summary.json "motion")

    @property
    def comm(self):
        return self.mesh.comm

    def cauchy(self, region: Region) -> ufl.core.expr.Expr:
        """Cauchy stress (3x3) of a region's law."""
        return cauchy_stress(region.W, self.kin)


def default_size(m: dict) -> float:
    """A target edge length giving a few thousand triangles for the generated shapes."""
    gen = m["generator"]
    if gen == "disk":
        return m["radius"] / 20
    if gen == "square":
        return m["side"] / 30
    if gen in ("sphere", "octasphere"):
        return m["radius"] / 8
    if gen == "tube":
        return m["radius"] / 8
    if gen == "valve":
        return 1.0
    return 0.0


#: memory a valve closure takes per cell (bytes): the demo at 1 and 0.5 mm (4385 and 16,957
#: cells) peaked at 311 and 810 MB in three steps (`/usr/bin/time`, session 59), 40 kB a cell
#: more; disks take less (no contact, chordae or hinges), so for them this is an upper bound
BYTES_PER_CELL = 40e3
#: memory making a mesh alone takes per cell (bytes; ``mvfem mesh``): a disk of radius 10 mm
#: at 0.5 and 0.1 mm (2944 and 72,835 cells) peaked at 151 and 216 MB, a valve at 1 and 0.25
#: mm (4461 and 68,559 cells) at 211 and 241 MB (session 59)
MESH_BYTES_PER_CELL = 1e3
#: cells the demo's valve has at mesh.size = 1 mm (free edge at half the size): 4385; at 2
#: and 0.5 mm it has 1144 and 16,957. Its dimensions are the generator's defaults but for
#: :data:`VALVE_CELLS_DIMENSIONS`; other valves scale from it (:func:`_valve_scale`)
VALVE_CELLS_AT_1MM = 4385.0
VALVE_CELLS_DIMENSIONS = {"anterior_height": 23.0}
#: cells per (area / size^2) of gmsh's unstructured triangles (a disk of radius 10 mm at
#: size 2 mm: 206 cells, 2.62 x pi 100 / 4)
CELLS_PER_AREA = 2.6


def expected_cells(m: dict, size: float) -> float | None:
    """About how many cells a generated mesh of the scene's ``[mesh]`` will have, before it
    is made (None for a file: its count is read)."""
    gen = m["generator"]
    if gen == "octasphere":
        return 8.0 * 4.0 ** m["refinements"]
    area = {"disk": lambda: np.pi * m["radius"] ** 2, "square": lambda: m["side"] ** 2,
            "sphere": lambda: 4 * np.pi * m["radius"] ** 2,
            "tube": lambda: 2 * np.pi * m["radius"] * m["length"]}
    if gen in area:
        return CELLS_PER_AREA * area[gen]() / size**2
    if gen == "valve":
        return VALVE_CELLS_AT_1MM * _valve_scale(m) / size**2 * 4.0 ** m["refine"]
    return None


def _loop_length(loop: np.ndarray) -> float:
    """The length of the closed polyline ``loop`` (k, 3)."""
    return float(np.linalg.norm(loop - np.roll(loop, 1, axis=0), axis=1).sum())


def _valve_scale(m: dict) -> float:
    """A generated valve's cells over the built-in valve's at one size, about: its annulus
    perimeter times its leaflets' heights (each leaflet's by its share of the annulus), each
    height with the band along the free edge where the size grows from half (twice the
    cells an area there) added. A patient annulus in micrometres, not millimetres, was
    meshed for minutes before the memory ran out; its estimate now refuses it."""
    import inspect

    from mvfem.meshes.io import read_points
    from mvfem.meshes.valve import valve

    d = {k: p.default for k, p in inspect.signature(valve).parameters.items()}
    demo = {**d, **VALVE_CELLS_DIMENSIONS}

    def perimeter(ap, cc, saddle, loop=None):
        if loop is None:
            t = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
            loop = np.column_stack([ap / 2 * np.cos(t), cc / 2 * np.sin(t),
                                    saddle / 2 * np.cos(2 * t)])
        return _loop_length(loop)

    def height(ant, post):
        share, band = d["anterior_share"], d["refine_distance"]
        return share * (ant + min(ant, band)) + (1 - share) * (post + min(post, band))

    def given(key):
        return d[key] if m.get(key) is None else m[key]

    base = (perimeter(demo["ap_diameter"], demo["commissural_diameter"], demo["saddle_height"])
            * height(demo["anterior_height"], demo["posterior_height"]))
    loop = read_points(m["annulus"]) if m.get("annulus") is not None else None
    this = (perimeter(given("ap_diameter"), given("commissural_diameter"),
                      given("saddle_height"), loop)
            * height(given("anterior_height"), given("posterior_height")))
    return this / base


def _host_memory(comm) -> float:
    """Physical memory of the hosts the ranks of ``comm`` run on (bytes; each host once)."""
    import os

    try:
        mine = float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        mine = float("inf")
    hosts = dict(comm.allgather((MPI.Get_processor_name(), mine)))
    return float(sum(hosts.values()))


def check_cells(cells: float, what: str, source: str, comm, meshing: bool = False) -> None:
    """Input error when a mesh of about ``cells`` cells would need more memory than the hosts
    have (at :data:`BYTES_PER_CELL`, or :data:`MESH_BYTES_PER_CELL` when the mesh is only
    made): such a run would only end when the memory ran out, after minutes or hours of
    meshing. ``what`` names the key and value that make the mesh."""
    per_cell, use = ((MESH_BYTES_PER_CELL, "making a mesh") if meshing else
                     (BYTES_PER_CELL, "a valve closure"))
    need = cells * per_cell
    have = _host_memory(comm)
    if need <= have:
        return
    raise InputError(f"{source}: {what} would make about {_about(cells)} cells, which at the "
                     f"{per_cell / 1e3:.0f} kB a cell of {use} need about "
                     f"{_about(need / 2**30)} GiB, more than the {_about(have / 2**30)} GiB of "
                     f"memory here (about {_about(have / per_cell)} cells fit)")


def _about(n: float) -> str:
    """``n`` to two significant digits, in words from a million up."""
    if n >= 1e6:
        return f"{float(f'{n / 1e6:.2g}'):g} million"
    if n >= 100:
        return f"{float(f'{n:.2g}'):,.0f}"
    return f"{n:.2g}"


def build_mesh(scene: Scene, comm=MPI.COMM_WORLD, meshing: bool = False):
    """The scene's surface mesh (a :class:`mvfem.meshes.SurfaceMesh`); one the memory here
    would not hold (:func:`check_cells`; ``meshing``: the mesh alone is made) is an input
    error before it is made."""
    from mvfem import meshes

    m = scene["mesh"]
    gen = m["generator"]
    size = m["size"] or default_size(m)
    cells = expected_cells(m, size)
    if cells is not None:
        what = (f"mesh.refinements = {m['refinements']}" if gen == "octasphere" else
                f"mesh.size = {size:g} mm" + (f" with mesh.refine = {m['refine']}"
                                              if gen == "valve" and m["refine"] else ""))
        if gen == "valve" and m["annulus"] is not None:  # (a loop in other units shows here)
            from mvfem.meshes.io import read_points

            what += (f" on the annulus of {m['annulus']}, "
                     f"{_loop_length(read_points(m['annulus'])):.3g} mm around,")
        check_cells(cells, what, scene.source, comm, meshing)
    if gen == "disk":
        return meshes.disk(comm, radius=m["radius"], size=size)
    if gen == "square":
        return meshes.square(comm, side=m["side"], size=size, centred=True)
    if gen == "sphere":
        return meshes.sphere(comm, radius=m["radius"], size=size)
    if gen == "tube":
        return meshes.tube(comm, radius=m["radius"], length=m["length"], size=size)
    if gen == "octasphere":
        return meshes.octasphere(comm, radius=m["radius"], refinements=m["refinements"])
    if gen == "valve":
        return _resected(scene, _valve(scene, comm, size), comm)
    if gen == "file":
        try:
            raw = meshes.read_surface(m["file"])
        except ValueError as e:
            raise InputError(f"{scene.source}: mesh.file: {e}") from None
        if "annulus" in raw.point_data:  # a valve: annulus, free edges, chordae, as generated
            from mvfem.meshes.imported import (check_surface, refine_surface,
                                               valve_from_surface)

            smooth = bool(m["refine"]) and m["refine_surface"] == "smooth"
            if m["refine"]:
                check_cells(len(raw.triangles) * 4.0 ** m["refine"],
                            f"mesh.refine = {m['refine']} of {m['file']}", scene.source, comm,
                            meshing)
                try:  # the file's own problems in its own nodes first
                    check_surface(comm, raw, m["labels"], source=m["file"])
                except ValueError as e:
                    raise InputError(f"{scene.source}: mesh.file: {e}") from None
                raw = refine_surface(raw, m["refine"], smooth=smooth)
            try:
                surface = valve_from_surface(comm, raw, m["labels"], source=m["file"])
            except ValueError as e:
                hint = (" (split with mesh.refine_surface = \"smooth\"; \"facets\" keeps the "
                        "file's surface)") if smooth else ""
                raise InputError(f"{scene.source}: mesh.file: {e}{hint}") from None
            return _resected(scene, surface, comm)
        if m["refine"]:
            raise InputError(f"{scene.source}: mesh.refine: refines valves only ({m['file']} has "
                             "no 'annulus' point data)")
        from mvfem.meshes.imported import check_plain_surface

        values = raw.cell_data.get("leaflet")
        if m["labels"] and values is None:
            raise InputError(f"{scene.source}: mesh.labels: {m['file']} has no 'leaflet' cell "
                             "data for them to name")
        try:  # (given labels must name every value the file has, as a valve file's must)
            check_plain_surface(raw, m["file"], m["labels"])
        except ValueError as e:
            raise InputError(f"{scene.source}: mesh.file: {e}") from None
        msh, tags = meshes.to_dolfinx(comm, raw, values)
        # a label names cells only where the file has them ('leaflet' cell data)
        present = set() if values is None else {int(v) for v in np.unique(values)}
        names = {v: int(k) for k, v in (m["labels"] or {}).items() if int(k) in present}
        return meshes.SurfaceMesh(mesh=msh, cell_tags=tags, facet_tags=None, names=names,
                                  info={"generator": "file", "file": m["file"]})
    raise InputError(f"{scene.source}: mesh.generator: {gen!r} is not available")


def _resected(scene: Scene, surface, comm):
    """The valve with the scene's ``[repair.resection]`` applied (its suture pairs, reference
    coordinates on rank 0, in ``surface.sutures``)."""
    spec = scene["repair"]["resection"]
    if spec is None:
        return surface
    from mvfem.repairs import resect

    # the radial direction of the tissue left is the one it had before the cut: the Laplace
    # coordinate of the whole valve, not one re-solved with the cut made a free edge (phi = 1
    # along the cut: cells with three nodes on it have no gradient, and 0/0 = NaN radial
    # directions; the bottom of a quadrangular cut would also turn radial into circumferential)
    phi = _laplace_phi(surface, scene.source)
    valve, sutures, _ = resect(surface, spec, comm, scene.source, 0.0)
    valve.sutures = sutures if spec["sutures"] else np.zeros((0, 2, 3))
    if phi is not None:
        valve.radial_coordinate = _gather_nodal(phi)
    return valve


def _laplace_phi(surface, source: str):
    """The Laplace coordinate of a valve surface (0 annulus, 1 free edge), or None."""
    annulus = _annulus_facets(surface)
    if annulus is None:
        return None
    from mvfem.meshes.fibres import boundary_split, laplace_coordinate

    msh = surface.mesh
    vertices = dmesh.compute_incident_entities(msh, annulus, msh.topology.dim - 1, 0)
    ann, free_edge = boundary_split(msh, vertices)
    try:
        return laplace_coordinate(msh, ann, free_edge)
    except ValueError as e:
        raise InputError(f"{source}: mesh: {e}") from None


def _gather_nodal(f) -> tuple[np.ndarray, np.ndarray]:
    """(coordinates, values) of a scalar P1 function's owned dofs, gathered on every rank."""
    V = f.function_space
    n = V.dofmap.index_map.size_local
    comm = V.mesh.comm
    x = np.concatenate(comm.allgather(V.tabulate_dof_coordinates()[:n]))
    v = np.concatenate(comm.allgather(f.x.array[:n].copy()))
    return x, v


def _nodal_function(msh, points: np.ndarray, values: np.ndarray, name: str):
    """The P1 function on ``msh`` taking ``values`` at ``points`` (every node of ``msh`` is
    one of ``points``: a resected valve keeps the coordinates of its nodes)."""
    from scipy.spatial import cKDTree

    V = fem.FunctionSpace(msh, ("Lagrange", 1))
    x = V.tabulate_dof_coordinates()
    dist, idx = cKDTree(points).query(x)
    if len(dist) and dist.max() > 1e-9 * (1.0 + np.abs(points).max()):
        raise RuntimeError(f"{name}: a node of the mesh is not one of the given points")
    f = fem.Function(V, name=name)
    f.x.array[:] = values[idx]
    return f


def _valve(scene: Scene, comm, size: float):
    from mvfem.meshes.io import read_points
    from mvfem.meshes.valve import valve

    m = scene["mesh"]
    kw = {k: m[k] for k in ("ap_diameter", "commissural_diameter", "saddle_height",
                            "anterior_height", "posterior_height", "papillary_depth",
                            "free_edge_size", "chordae_spacing", "anterior_direction")
          if m[k] is not None}
    for key in ("annulus", "papillary"):
        if m[key] is not None:
            kw[key] = read_points(m[key])
    if "free_edge_size" not in kw:
        kw["free_edge_size"] = size / 2
    try:
        return valve(comm, size=size, refine=m["refine"], **kw)
    except ValueError as e:
        # the generator's advice in the scene's keys (its tilt and smoothing are not scene keys)
        said = re.sub(r"the (\w+) leaflet folds (.*): lower its height or tilt, or raise "
                      r"ruling_smoothing",
                      r"the \1 leaflet folds \2: lower mesh.\1_height", str(e))
        raise InputError(f"{scene.source}: mesh: {said}") from None


def _centre(msh, given) -> np.ndarray:
    if given is not None:
        return np.asarray(given, dtype=float)
    n = msh.geometry.index_map().size_local
    x = msh.geometry.x[:n]
    s = msh.comm.allreduce(x.sum(axis=0), op=MPI.SUM)
    c = msh.comm.allreduce(len(x), op=MPI.SUM)
    return s / max(c, 1)


#: a direction projected on the surface is undefined where its tangential part is shorter
#: than this fraction of the vector it is projected from (the vector within this angle of the
#: surface's normal) or of the roundoff scale of that vector (a difference of positions: the
#: vector itself roundoff), at a cell's midpoint. The tangential part carries a roundoff of a
#: few 1e-16 of those lengths, so below 1e-9 the direction would be off by more than 1e-7
#: rad, and at 0 it is NaN.
NORMAL_ANGLE = 1e-9


class _Projected:
    """The tangential part of a vector field on a surface of unit normal ``n0`` (UFL), and
    its direction; ``scale``: the length the vector's roundoff is relative to (0 for a given
    nonzero vector)."""

    def __init__(self, vec, n0, scale=0.0):
        self.vec = vec
        self.scale = scale
        self.tangent = vec - ufl.dot(vec, n0) * n0
        self.unit = self.tangent / ufl.sqrt(ufl.dot(self.tangent, self.tangent))

    def share(self):
        """The tangential part's length over the vector's and its scale's: the sine of the
        vector's angle to the normal where the vector is long, 0 where it is zero."""
        return ufl.sqrt(ufl.dot(self.tangent, self.tangent)) / (
            ufl.sqrt(ufl.dot(self.vec, self.vec)) + self.scale)


def _directions(msh, fibres: dict, phi=None, uses_fibre: bool = True, source: str = "scene"):
    """(fibre, radial, circumferential) unit tangent fields of the reference surface (UFL).

    With ``phi`` (a valve's Laplace coordinate, :mod:`mvfem.meshes.fibres`) radial is its
    gradient direction; otherwise radial and circumferential are taken about ``fibres.axis``
    through ``fibres.centre``. A direction projected on the surface that is undefined at a
    cell (its vector along the normal there, or zero) is an input error
    (:func:`_check_directions`); the fibre is checked where a law uses it (``uses_fibre``),
    radial and circumferential always (the reports' strains and stresses are along them).
    """
    x = ufl.SpatialCoordinate(msh)
    n0 = unit_normal(ufl.Jacobian(msh))
    direction = fibres["direction"]
    given = None
    if not isinstance(direction, str):
        given = _Projected(fem.Constant(msh, np.asarray(direction, dtype=float)), n0)
    checks = {"fibre": given} if given is not None and uses_fibre else {}
    if phi is not None:
        from mvfem.meshes.fibres import radial_circumferential

        radial, circ = radial_circumferential(phi, n0)
    else:
        axis = np.asarray(fibres["axis"], dtype=float)
        # Constants, not literals: the generated code is then the same for every mesh (JIT
        # cache)
        axis = fem.Constant(msh, axis / np.linalg.norm(axis))
        centre = _centre(msh, fibres["centre"])
        c = fem.Constant(msh, centre)
        d = x - c
        # the roundoff of x - centre is relative to |x| + |centre|
        scale = ufl.sqrt(ufl.dot(x, x)) + ufl.sqrt(ufl.dot(c, c))
        about = {"radial": _Projected(d - ufl.dot(d, axis) * axis, n0, scale),
                 "circumferential": _Projected(ufl.cross(axis, d), n0, scale)}
        checks.update(about)
        radial, circ = about["radial"].unit, about["circumferential"].unit
    _check_directions(msh, checks, fibres, source, None if phi is not None else centre)
    if direction == "circumferential":
        return circ, radial, circ
    if direction == "radial":
        return radial, radial, circ
    return given.unit, radial, circ


def _check_directions(msh, checks: dict, fibres: dict, source: str, centre) -> None:
    """Input error naming the first direction of ``checks`` ({name: :class:`_Projected`})
    undefined at some cell: the vector it is projected from zero or within
    :data:`NORMAL_ANGLE` of the normal at the cell's midpoint (there its unit field is 0/0 or
    roundoff, and a solve or a report would meet NaN). Collective."""
    if not checks:
        return
    from mvfem.fields import cell_values

    names = list(checks)
    shares = [checks[k].share() for k in names]
    expr = shares[0] if len(shares) == 1 else ufl.as_vector(shares)
    values = cell_values(expr, msh, () if len(shares) == 1 else (len(shares),))
    values = values.reshape(len(values), len(names))
    comm = msh.comm
    n_cells = comm.allreduce(len(values), op=MPI.SUM)
    bad = values < NORMAL_ANGLE
    counts = comm.allreduce(bad.sum(axis=0), op=MPI.SUM)
    for j, name in enumerate(names):
        if counts[j] == 0:
            continue
        mine = np.flatnonzero(bad[:, j])
        point = None
        if len(mine):
            point = dmesh.compute_midpoints(msh, msh.topology.dim, mine[:1].astype(np.int32))[0]
        point = next(p for p in comm.allgather(point) if p is not None)
        where = f"at {counts[j]} of {n_cells} cells (the first near {_point(point)})"
        axis = _numbers(fibres["axis"])
        if name == "fibre":
            raise InputError(f"{source}: fibres.direction: {_numbers(fibres['direction'])} lies "
                             f"along the surface's normal {where}: the fibre, its projection "
                             "on the surface, is undefined there")
        if name == "circumferential":
            raise InputError(f"{source}: fibres.axis: the circumferential direction about "
                             f"{axis} lies along the surface's normal {where}, so it is "
                             "undefined there (an axis that lies in the surface: choose one "
                             "across it)")
        raise InputError(f"{source}: fibres.centre: the radial direction from the axis "
                         f"{axis} through {_point(centre)} is "
                         f"undefined {where}: the cell lies on the axis, or the direction "
                         "along the surface's normal (move fibres.centre or fibres.axis)")


def _numbers(v) -> str:
    return "[" + ", ".join(f"{float(c):g}" for c in v) + "]"


def _point(x) -> str:
    return "(" + ", ".join(f"{float(c):.4g}" for c in x) + ")"


def _cell_labels(surface, comm) -> dict[str, int]:
    """The labels of the surface's cells that some cell has (name -> tag value; its edge
    tags, e.g. a valve's annulus, and labels of no cell left out)."""
    names = getattr(surface, "names", {}) or {}
    tags = surface.cell_tags
    mine = set() if tags is None else {int(v) for v in np.unique(tags.values)}
    present = set().union(*comm.allgather(mine))
    return {k: int(v) for k, v in names.items() if int(v) in present}


def _region_cells(labels: dict[str, int], label: str | None, n_regions: int, where: str,
                  source: str):
    """The tag value of a region's cells (None: every cell), ``labels`` those of
    :func:`_cell_labels`. A label the cells do not have is refused where the mesh has
    labels; on an unlabelled mesh a single region's label only names it."""
    if label is None:
        return None
    if label in labels:
        return labels[label]
    if n_regions == 1 and not labels:
        return None
    raise InputError(f"{source}: {where}.label: {label!r} is not a label of the mesh's cells "
                     f"(labels: {', '.join(map(str, labels)) or 'none'})")


def _check_covered(labels: dict[str, int], tags, regions, comm, source: str) -> None:
    """Every labelled cell is in a region: cells of no region had no material (a valve file
    with one region for its anterior leaflet closed with a posterior leaflet of nothing)."""
    covered = {r.tag for r in regions}
    if None in covered or tags is None:
        return
    for name, value in labels.items():
        if value not in covered:
            n = comm.allreduce(int(np.sum(tags.values == value)), op=MPI.SUM)
            raise InputError(f"{source}: region: the mesh's {n} cells labelled {name!r} are in "
                             f"no [[region]]; add one with label = \"{name}\" (or give a "
                             "single region no label: it covers every cell)")


def build_model(scene: Scene, comm=MPI.COMM_WORLD) -> Model:
    """Compose the terms of ``scene`` on its mesh."""
    surface = build_mesh(scene, comm)
    msh = surface.mesh
    s = scene["solver"]
    degree = s["degree"]
    q = s["quadrature_degree"] or (1 if degree == 1 else 2 * degree)
    V = fem.VectorFunctionSpace(msh, ("Lagrange", degree))
    u = fem.Function(V, name="displacement")
    v = ufl.TestFunction(V)

    annulus = _annulus_facets(surface)
    given = getattr(surface, "radial_coordinate", None)  # a resected valve's, from before
    if given is not None and annulus is not None:
        phi = _nodal_function(msh, *given, name="radial_coordinate")
    else:
        phi = _laplace_phi(surface, scene.source)
    fibre, radial, circ = _directions(msh, scene["fibres"], phi,
                                      any(uses_fibre(r["law"]) for r in scene["region"]),
                                      scene.source)
    kin = membrane(u, fibre)
    meta = {"quadrature_degree": q}
    tags = surface.cell_tags
    regions = []
    energy = 0
    # the Fung laws' exponent beyond which they continue linearly (C1): MAX_EXPONENT, lowered
    # at the start of a grid-sequenced solve (mvfem/sequence.py)
    cap = fem.Constant(msh, MAX_EXPONENT)
    labels = _cell_labels(surface, comm)
    for i, r in enumerate(scene["region"]):
        tag = _region_cells(labels, r["label"], len(scene["region"]), f"region[{i}]",
                            scene.source)
        dx = (ufl.Measure("dx", domain=msh, subdomain_data=tags, subdomain_id=tag, metadata=meta)
              if tag is not None else ufl.Measure("dx", domain=msh, metadata=meta))
        consts = {k: fem.Constant(msh, float(val)) for k, val in r["params"].items()}
        h0 = fem.Constant(msh, float(r["thickness"]))
        tension_only = not r.get("fibre_compression", True)
        extra = {"max_exponent": cap, "tension_only": tension_only} \
            if is_exponential(r["law"]) else {}
        W = LAWS[r["law"]](kin, *consts.values(), **extra)
        regions.append(Region(r["label"] or "membrane", tag, r["law"], r.get("set", "custom"),
                              consts, h0, W, dx, tension_only))
        energy = energy + h0 * W * dx
    _check_covered(labels, tags, regions, comm, scene.source)

    E_b = scene["bending"]["modulus"]
    if E_b is None:
        E_b = VALVE_BENDING_MODULUS if annulus is not None else 0.0
    hinge_D = 0.0
    if E_b > 0:
        h_mean = float(np.mean([float(r.thickness.value) for r in regions]))
        hinge_D = E_b * h_mean**3 / 12.0
        if not (degree == 1 and _compiled_hinges(comm)):
            from mvfem.forms.bending import hinge_energy

            D = fem.Constant(msh, hinge_D)
            energy = energy + hinge_energy(u, D) * ufl.dS(domain=msh,
                                                          metadata={"quadrature_degree": 1})
            hinge_D = 0.0  # in the form, not a point term

    load = scene["load"]
    pressure = fem.Constant(msh, 0.0)
    dxp = ufl.Measure("dx", domain=msh, metadata=meta)
    if load["follower"]:
        p_term = follower_pressure(pressure, kin, v) * dxp
        p_pot = follower_potential(pressure, kin, ufl.SpatialCoordinate(msh) + u) * dxp
    else:
        p_term = dead_pressure(pressure, kin, v) * dxp
        p_pot = dead_potential(pressure, kin, u) * dxp

    area = comm.allreduce(fem.assemble_scalar(fem.form(1.0 * dxp)), op=MPI.SUM)
    L = float(np.sqrt(area))
    internal = ufl.derivative(energy, u, v)
    residual = internal - p_term

    bcs = []
    loop_motion = None  # (Function g, its full values, info) of a prescribed clamped loop
    if scene["boundary"]["clamp"] == "boundary":
        msh.topology.create_connectivity(1, 2)
        facets = dmesh.exterior_facet_indices(msh.topology)
        n_facets = comm.allreduce(len(facets), op=MPI.SUM)
        if n_facets == 0:
            raise InputError(f"{scene.source}: boundary.clamp: the mesh has no boundary to clamp "
                             "(use clamp = \"none\")")
        dofs = fem.locate_dofs_topological(V, 1, facets)
        loop_motion = _loop_motion(scene, surface, V, dofs)
        bcs.append(_clamp(V, dofs, loop_motion))
    elif scene["boundary"]["clamp"] == "rigid":
        bcs += _rigid_pins(V, scene)
    elif scene["boundary"]["clamp"] == "annulus":
        if annulus is None or comm.allreduce(len(annulus), op=MPI.SUM) == 0:
            raise InputError(f"{scene.source}: boundary.clamp: \"annulus\" needs a valve mesh "
                             "(generator = \"valve\", or a file with point data 'annulus')")
        dofs = fem.locate_dofs_topological(V, 1, annulus)
        loop_motion = _loop_motion(scene, surface, V, dofs)
        bcs.append(_clamp(V, dofs, loop_motion))
    if scene["repair"]["ring"] is not None and scene["boundary"]["clamp"] != "annulus":
        raise InputError(f"{scene.source}: repair.ring: needs the annulus clamped "
                         "(boundary.clamp = \"annulus\", the default of valves)")

    p_target = float(load["pressure"])
    stab_scale = s["stabilisation"] * max(abs(p_target), 1.0) / L
    model = Model(scene=scene, surface=surface, mesh=msh, V=V, u=u, kin=kin,
                  regions=regions, fibre=fibre, radial=radial, circumferential=circ,
                  pressure=pressure, p_target=p_target, stabiliser_scale=stab_scale,
                  energy=energy, residual=residual, load_form=p_term, bcs=bcs,
                  quadrature_degree=q, length_scale=L, info={"area_mm2": area}, phi=phi,
                  potential=energy + p_pot, hinge_stiffness=hinge_D, exponent_cap=cap)
    _point_terms(model)
    _compose_ramp(model, loop_motion)
    return model


def _loop_frame(surface, scene: Scene) -> np.ndarray:
    """Rows: anterior, commissural, axis directions (a valve's frame; else x, y about the
    scene's fibres.axis)."""
    frame = getattr(surface, "frame", None)
    if frame is not None:
        return np.asarray(frame, dtype=float)
    z = np.asarray(scene["fibres"]["axis"], dtype=float)
    z = z / np.linalg.norm(z)
    x = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    return np.array([x, np.cross(z, x), z])


#: an annulus target this many times longer or shorter than the valve's annulus is not that
#: annulus moved (a loop in metres stopped at 63 % of its motion with advice on the mesh; 10
#: x larger, with "a ring too small for this annulus?", session 62)
TARGET_RATIO = 3.0


def _loop_motion(scene: Scene, surface, V, dofs):
    """The clamped loop's prescribed displacement (``[annulus] target`` or ``[repair.ring]``):
    (Function holding it at the clamped dofs, those full values, info), or None."""
    from scipy.spatial import cKDTree

    from mvfem.prescribed import match_loop, order_loop
    from mvfem.repairs import on_root, ring_targets

    ring, target = scene["repair"]["ring"], scene["annulus"]["target"]
    if ring is None and target is None:
        return None
    comm = V.mesh.comm
    coords = V.tabulate_dof_coordinates()
    n_owned = V.dofmap.index_map.size_local
    parts = comm.gather(coords[dofs[dofs < n_owned]], root=0)
    frame = _loop_frame(surface, scene)
    key = "repair.ring" if ring is not None else "annulus.target"

    def work():
        from mvfem.meshes.io import read_points

        pts = np.concatenate(parts)
        loop = pts[order_loop(pts, frame, getattr(surface, "annulus_curve", None))]
        if ring is not None:
            if getattr(surface, "commissures", None) is None or \
                    not hasattr(surface, "along_leaflet"):
                raise InputError(f"{scene.source}: repair.ring: needs a valve mesh")
            placed, info = ring_targets(loop, frame, surface.commissures, ring["shape"],
                                        ring["size"], ring["ap_ratio"], ring["saddle_height"],
                                        where=f"{scene.source}: repair.ring")
            info = {"kind": "ring", **info}
        else:
            aim = read_points(target)
            here, there = _loop_length(loop), _loop_length(aim)
            if not here / TARGET_RATIO <= there <= here * TARGET_RATIO:
                raise InputError(f"{scene.source}: annulus.target: {target} is {there:.3g} mm "
                                 f"around, the valve's annulus {here:.3g} mm: not the same "
                                 f"annulus moved (within a factor of {TARGET_RATIO:g}; are "
                                 "its coordinates in mm?)")
            placed = match_loop(loop, aim, frame, scene["annulus"]["match"])
            info = {"kind": "annulus target", "file": target, "nodes": int(len(loop)),
                    "max_displacement_mm":
                        float(np.linalg.norm(placed - loop, axis=1).max())}
        return loop, placed - loop, info

    loop, disp, info = comm.bcast(on_root(comm, work, f"{scene.source}: {key}"), root=0)
    g = fem.Function(V, name="prescribed")
    dist, idx = cKDTree(loop).query(coords[dofs])
    if len(dist) and dist.max() > 1e-9 * (1.0 + np.abs(loop).max()):
        raise RuntimeError("a clamped dof is not on the gathered loop")
    values = g.x.array.reshape(-1, 3)
    values[dofs] = disp[idx]
    full = g.x.array.copy()
    g.x.array[:] = 0.0
    return g, full, info, dofs, loop


class _Lifting:
    r"""Harmonic extension of a change of the clamped values into the interior.

    ``lift()`` sets ``u += w`` with ``w`` the P1 solution of the surface Laplace problem
    :math:`\int \nabla w : \nabla v = 0`, ``w = g - u`` on the clamped dofs. On a flat
    surface an affine motion of the rim (a translation, rotation, uniform stretch) extends to
    the affine field itself, the exact homogeneous state; on a curved valve it is a smooth
    start. It keeps the first Newton step from meeting a membrane whose rim alone has moved
    (the Fung laws have no stiffness at the stress-free state: the load steps stalled)."""

    def __init__(self, V, dofs, g, u):
        from dolfinx.fem import petsc as fpetsc

        w, v = ufl.TrialFunction(V), ufl.TestFunction(V)
        self.a = fem.form(ufl.inner(ufl.grad(w), ufl.grad(v)) * ufl.dx)
        zero = ufl.inner(fem.Constant(V.mesh, np.zeros(3, dtype=PETSc.ScalarType)), v) * ufl.dx
        self.L = fem.form(zero)
        self.m = fem.Function(V)
        self.bc = fem.dirichletbc(self.m, dofs)
        self.A = fpetsc.assemble_matrix(self.a, bcs=[self.bc])
        self.A.assemble()
        self.ksp = PETSc.KSP().create(V.mesh.comm)
        self.ksp.setOperators(self.A)
        self.ksp.setType("preonly")
        self.ksp.getPC().setType("lu")
        self.ksp.getPC().setFactorSolverType("mumps")
        self.g, self.u, self.w = g, u, fem.Function(V)
        self.b = fpetsc.create_vector(self.L)
        #: ``limit(u_owned, w_owned, squeeze=None)`` -> the fraction of ``w`` allowed (contact:
        #: the collision check, and with ``squeeze`` the closest pairs kept that share apart)
        self.limit = None

    def __call__(self, squeeze: float | None = None) -> float:
        """Lift ``u`` towards the current Dirichlet values; the fraction of the lifting taken
        (the clamped dofs too: they end at ``u + alpha (g - u)``), bounded by the collision
        check and, with ``squeeze``, by :meth:`mvfem.contact.Contact.squeeze_limit`."""
        from dolfinx.fem import petsc as fpetsc

        self.m.x.array[:] = self.g.x.array - self.u.x.array
        with self.b.localForm() as bl:
            bl.set(0.0)
        fpetsc.assemble_vector(self.b, self.L)
        fpetsc.apply_lifting(self.b, [self.a], bcs=[[self.bc]])
        self.b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fpetsc.set_bc(self.b, [self.bc])
        self.ksp.solve(self.b, self.w.vector)
        self.w.x.scatter_forward()
        alpha = 1.0
        if self.limit is not None:  # no leaflet moved through another by the lifting
            n = self.u.function_space.dofmap.index_map.size_local * 3
            alpha = self.limit(self.u.x.array[:n], self.w.x.array[:n], squeeze=squeeze)
        self.u.x.array[:] += alpha * self.w.x.array
        self.u.x.scatter_forward()
        return alpha


def _clamp(V, dofs, loop_motion):
    if loop_motion is None:
        return fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType), dofs, V)
    return fem.dirichletbc(loop_motion[0], dofs)


def _compose_ramp(model: Model, loop_motion) -> None:
    """``model.ramp(f)``: the prescribed motion at fraction f (clamped loop, papillary tips,
    ties drawn tight), when the scene prescribes any."""
    parts = []
    if loop_motion is not None:
        g, full, info, dofs, loop = loop_motion
        model.motion["annulus"] = info
        model.lift = _Lifting(model.V, dofs, g, model.u)
        if model.point_terms is not None:
            model.lift.limit = model.point_terms.step_limit
        if model.view is not None and model.comm.rank == 0:  # the moved annulus, for metrics
            model.annulus_nodes = model.view.node_of_point(loop)

        def move_loop(f, g=g, full=full):
            g.x.array[:] = f * full
        parts.append(move_loop)
    ch = model.chordae
    shift = getattr(ch, "anchor_shift", None) if ch is not None else None
    if shift is not None:
        start = ch.anchor.copy()
        model.motion["papillary"] = getattr(ch, "motion_info", {})

        def move_tips(f, ch=ch, start=start, shift=shift):
            ch.anchor[:] = start + f * shift
        parts.append(move_tips)
    if model.ties is not None:
        model.motion["ties"] = {"count": model.comm.allreduce(len(model.ties), op=MPI.SUM)}
        parts.append(model.ties.set_fraction)
    if not parts:
        return
    pt = model.point_terms

    def ramp(f: float) -> None:
        for p in parts:
            p(f)
        if pt is not None:  # the point terms' cache is keyed on positions only
            pt._last_x = None
    model.ramp = ramp
    model.ramp_steps = int(model.scene["solver"]["ramp_steps"])
    if model.ties is not None:
        model.ties.set_fraction(0.0)


def _annulus_facets(surface):
    """Local annulus edges of a valve surface, or None for a surface without an annulus."""
    names = getattr(surface, "names", {}) or {}
    if "annulus" not in names or surface.facet_tags is None:
        return None
    return surface.facets("annulus")


def _has_chordae(surface) -> bool:
    return len(getattr(surface, "insertion_points", ())) > 0


#: the hinge bending as a compiled point term (mvfem.hinges) where the kernels compile and the
#: space is P1; False: always the UFL form over interior facets (the reference of the tests)
COMPILED_HINGES = True


def _compiled_hinges(comm) -> bool:
    """Whether the hinges are a point term (collective: rank 0, which evaluates them, decides)."""
    from mvfem import kernels

    ok = COMPILED_HINGES and (comm.rank != 0 or kernels.load() is not None)
    return bool(comm.bcast(ok if comm.rank == 0 else None, root=0))


def _point_terms(model: Model) -> None:
    """Chordae, contact, ties and hinges, when the scene asks for them (chordae, contact and
    ties on a valve)."""
    from mvfem.contact import Contact
    from mvfem.nodal import NodalView, PointTerms

    scene, surface = model.scene, model.surface
    valve = _annulus_facets(surface) is not None
    rep = scene["repair"]
    want_chordae = (scene["chordae"]["enabled"] and _has_chordae(surface)) or bool(rep["neochord"])
    want_contact = scene["contact"]["enabled"] and valve
    want_ties = surface_has_sutures(surface, model.comm) or bool(rep["clip"])  # collective
    if (rep["neochord"] or rep["clip"]) and not valve:
        raise InputError(f"{scene.source}: repair: neochordae and clips need a valve mesh")
    if scene["papillary"]["target"] is not None and not want_chordae:
        raise InputError(f"{scene.source}: papillary.target: the scene has no chordae to move")
    want_hinges = model.hinge_stiffness > 0
    if not (want_chordae or want_contact or want_ties or want_hinges):
        return
    try:
        view = NodalView(model.V, model.bcs, surface.cell_tags)
    except ValueError as e:
        raise InputError(f"{scene.source}: solver.degree: {e}") from None
    terms = []
    if want_chordae:
        model.chordae = _chordae(scene, surface, view)
        terms.append(model.chordae)
    if want_contact:
        c = scene["contact"]
        delta = c["thickness"]
        # barrier pressure kappa delta = the load at about half the thickness
        k = c["stiffness"] or max(abs(model.p_target), 1e3) / delta
        model.contact = Contact(view, delta, k, exclusion=c["exclusion"])
        terms.append(model.contact)
    if want_ties:
        model.ties = _ties(scene, surface, view, model.V)
        terms.append(model.ties)
    if want_hinges:
        from mvfem.hinges import Hinges

        model.hinges = Hinges(view, model.hinge_stiffness)
        terms.append(model.hinges)
        v, du = ufl.TestFunction(model.V), ufl.TrialFunction(model.V)
        zero = fem.Constant(model.mesh, 0.0)
        model.sparsity = zero * ufl.inner(ufl.jump(du), ufl.jump(v)) * ufl.dS(domain=model.mesh)
    model.view = view
    model.point_terms = PointTerms(view, terms)


#: Carpentier's segments as fractions along a leaflet from the posteromedial commissure
SEGMENTS = {"3": (0.0, 1 / 3), "2": (1 / 3, 2 / 3), "1": (2 / 3, 1.0)}


def _chordae(scene: Scene, surface, view):
    """Tethers of the valve's chordae insertions, with the scene's family parameters and
    edits (``[[chordae.edit]]``: lengthened, shortened or ruptured chords)."""
    from mvfem.chordae import Chordae

    edges = {n["leaflet"]: _free_edge_points(surface, n["leaflet"], view.comm)
             for n in scene["repair"]["neochord"]}
    chords, error = None, None
    if view.comm.rank == 0:
        try:
            chords = _chordae_on_root(scene, surface, view, edges)
        except InputError as e:
            error = str(e)
        except ValueError as e:
            error = f"{scene.source}: {e}"
    error = view.comm.bcast(error, root=0)
    if error:
        raise InputError(error)
    if view.comm.rank != 0:
        chords = Chordae(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(0),
                         np.zeros(0, dtype="<U8"))
        if scene["papillary"]["target"] is not None:
            chords.anchor_shift = np.zeros((0, 3))
    return chords


def _chordae_on_root(scene: Scene, surface, view, edges=None):
    from mvfem.chordae import Chordae

    fams = scene["chordae"]
    names = {v: k for k, v in (surface.names or {}).items()}
    if not scene["chordae"]["enabled"] or not _has_chordae(surface):  # neochordae only
        surface_tip = np.zeros(0, dtype=np.int64)
        node, anchor = np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        chords = Chordae(node, anchor, np.zeros(0), np.zeros(0), np.zeros(0, dtype="<U8"),
                         np.zeros(0, dtype="<U16"))
        return _with_repairs(scene, surface, view, chords, surface_tip, edges or {})
    node = view.node_of_point(surface.insertion_points)
    anchor = surface.papillary_tips[surface.insertion_tip]
    # imported trees: path length along the tree; generated valves: the length that makes the
    # chord just taut with its insertion where the designed closed valve puts it. Chordae are
    # designed for the closed valve: in the open (stress-free) valve some are slack and some
    # already pull (the posterior ones; README, "Chordae")
    length = getattr(surface, "insertion_path_length", None)
    if length is None or len(length) != len(node):
        target = getattr(surface, "insertion_closed", None)
        if target is None or len(target) != len(node):
            target = surface.insertion_points
        length = np.linalg.norm(target - anchor, axis=1)
    family = np.asarray(surface.insertion_family)
    factor = np.array([fams[f]["length_factor"] for f in family])
    rest = factor * length
    EA = np.array([fams[f]["modulus"] * fams[f]["area"] for f in family])  # Pa mm^2
    leaflet = np.array([names.get(int(t), str(t)) for t in surface.insertion_leaflet])
    keep = np.ones(len(node), dtype=bool)
    for i, e in enumerate(fams["edit"]):
        sel = np.ones(len(node), dtype=bool)
        if e["leaflet"] is not None:
            sel &= leaflet == e["leaflet"]
        if e["family"] is not None:
            sel &= family == e["family"]
        span = e["between"] or (SEGMENTS[e["segment"][1]] if e["segment"] else None)
        if span is not None:
            pos = np.full(len(node), np.nan)
            for name in np.unique(leaflet[sel]):
                on = sel & (leaflet == name)
                pos[on] = surface.along_leaflet(surface.insertion_points[on], str(name))
            sel &= (pos >= span[0]) & (pos <= span[1])
        if not sel.any() and scene["repair"]["resection"] is not None:
            # the resection took out the tissue (and the chords) the edit was about: a
            # ruptured segment resected is the usual repair
            log.info(f"chordae.edit[{i}]: selects no chord left after the resection")
            continue
        if not sel.any():
            raise InputError(f"{scene.source}: chordae.edit[{i}]: selects no chord of this valve "
                             f"(leaflets: {', '.join(sorted(set(leaflet)))}; families: "
                             f"{', '.join(sorted(set(family)))})")
        if e["rupture"]:
            keep &= ~sel
        else:
            rest[sel] *= e["length_factor"]
    chords = Chordae(node[keep], anchor[keep], rest[keep], EA[keep] / rest[keep], family[keep],
                     leaflet[keep])
    return _with_repairs(scene, surface, view, chords,
                         np.asarray(surface.insertion_tip)[keep], edges or {})


def _free_edge_points(surface, leaflet: str, comm) -> np.ndarray | None:
    """Reference coordinates of the vertices of a leaflet's free edge, gathered on rank 0
    (collective; None elsewhere)."""
    from dolfinx import cpp

    from mvfem.meshes.io import _cpp_mesh

    msh = surface.mesh
    name = f"free_edge_{leaflet}"
    if name not in (surface.names or {}):
        pts = np.zeros((0, 3))
    else:
        facets = surface.facets(name)
        geo = cpp.mesh.entities_to_geometry(_cpp_mesh(msh), 1, facets, False).ravel()
        pts = msh.geometry.x[geo]
    parts = comm.gather(pts, root=0)
    return np.concatenate(parts) if comm.rank == 0 else None


def surface_has_sutures(surface, comm) -> bool:
    """Whether a resected valve carries sutures (rank 0 holds them; collective)."""
    return comm.allreduce(len(getattr(surface, "sutures", ())), op=MPI.SUM) > 0


def _with_repairs(scene: Scene, surface, view, chords, tip, edges: dict):
    """The chordae with the scene's neochordae appended, and the anchors' shift to the
    papillary target (``chords.anchor_shift``, ``chords.tip``) when the scene has one
    (rank 0)."""
    from mvfem.chordae import Chordae
    from mvfem.repairs import free_edge, neochordae

    nodes, tips, rest, EA, leaf = [chords.node], [np.asarray(tip, dtype=np.int64)], \
        [chords.rest_length], [chords.stiffness * chords.rest_length], [chords.leaflet]
    fam = [chords.family.astype("<U8")]
    tip_xyz = np.asarray(getattr(surface, "papillary_tips", np.zeros((0, 3))), dtype=float)
    muscle = np.asarray(getattr(surface, "papillary_muscle", np.zeros(0, dtype=np.int32)))
    for i, n in enumerate(scene["repair"]["neochord"]):
        where = f"{scene.source}: repair.neochord[{i}]"
        if len(tip_xyz) == 0:
            raise InputError(f"{where}: this valve has no papillary tips to anchor it")
        edge = free_edge(view, surface, n["leaflet"], edges[n["leaflet"]])
        if len(edge["node"]) == 0:
            raise InputError(f"{where}.leaflet: the {n['leaflet']} leaflet has no free edge")
        nd, tp, L = neochordae(edge, n, tip_xyz, muscle, surface.frame, surface.centre, where)
        E = n["modulus"] or scene["chordae"]["marginal"]["modulus"]
        A = n["area"] or scene["chordae"]["marginal"]["area"]
        nodes.append(nd)
        tips.append(tp)
        rest.append(L)
        EA.append(np.full(len(nd), E * A))
        fam.append(np.full(len(nd), "neochord", dtype="<U8"))
        leaf.append(np.full(len(nd), n["leaflet"], dtype="<U16"))
    tip_all = np.concatenate(tips).astype(np.int64)
    rest_all = np.concatenate(rest)
    out = Chordae(np.concatenate(nodes).astype(np.int64),
                  tip_xyz[tip_all].reshape(-1, 3) if len(tip_all) else np.zeros((0, 3)),
                  rest_all, np.concatenate(EA) / rest_all, np.concatenate(fam),
                  np.concatenate(leaf).astype("<U16"))
    out.tip = tip_all
    target = scene["papillary"]["target"]
    if target is not None:
        from mvfem.meshes.io import read_points

        to = read_points(target)
        if to.shape != tip_xyz.shape:
            raise InputError(f"{scene.source}: papillary.target: {target}: {len(to)} point(s) "
                             f"for the valve's {len(tip_xyz)} papillary tip(s) (one row per "
                             "tip, in the valve's order: anterolateral first)")
        shift = to - tip_xyz
        out.anchor_shift = shift[tip_all].reshape(-1, 3)
        out.motion_info = {"file": target, "tips": int(len(tip_xyz)),
                           "max_displacement_mm": float(np.linalg.norm(shift, axis=1).max())}
    return out


def _ties(scene: Scene, surface, view, V):
    """Clips and sutures as :class:`mvfem.ties.Ties` (rank 0; empty elsewhere)."""
    from mvfem.repairs import (clip_pairs, clip_within_edge, free_edge, gap_default,
                               snap_to_free_edge)
    from mvfem.ties import Ties

    comm = view.comm
    clips = scene["repair"]["clip"]
    edges = {}
    if clips:
        edges = {leaf: _free_edge_points(surface, leaf, comm) for leaf in ("anterior",
                                                                            "posterior")}
    sutures = getattr(surface, "sutures", np.zeros((0, 2, 3)))
    res = scene["repair"]["resection"]

    def work():
        pairs, rest, k, kind, group = [], [], [], [], []
        gap0 = gap_default(scene)
        names = surface.names or {}
        own = {leaf: np.unique(view.cells[view.cell_tag == names.get(leaf, -1)])
               for leaf in ("anterior", "posterior")}
        for i, c in enumerate(clips):
            where = f"{scene.source}: repair.clip[{i}]"
            ant = free_edge(view, surface, "anterior", edges["anterior"])
            post = free_edge(view, surface, "posterior", edges["posterior"])
            pts = c["points"] or (None, None)
            ia = snap_to_free_edge(ant, at=c["anterior"], point=pts[0], tolerance=c["tolerance"],
                                   where=f"{where}.{'points' if pts[0] else 'anterior'}")
            ip = snap_to_free_edge(post, at=c["posterior"], point=pts[1],
                                   tolerance=c["tolerance"],
                                   where=f"{where}.{'points' if pts[1] else 'posterior'}")
            for edge, i_mid in ((ant, ia), (post, ip)):
                clip_within_edge(edge, i_mid, c["width"], f"{where}.width")
            p = clip_pairs(ant, post, ia, ip, c["width"], c["depth"], view.X, own)
            pairs.append(p)
            rest.append(np.full(len(p), gap0 if c["gap"] is None else c["gap"]))
            k.append(np.full(len(p), c["stiffness"]))
            kind.append(np.full(len(p), "clip", dtype="<U8"))
            group.append(np.full(len(p), i))
        if len(sutures):
            p = view.node_of_point(np.asarray(sutures).reshape(-1, 3)).reshape(-1, 2)
            pairs.append(p)
            gap = gap0 if res is None or res["gap"] is None else res["gap"]
            rest.append(np.full(len(p), gap))
            k.append(np.full(len(p), res["stiffness"] if res else 5e6))
            kind.append(np.full(len(p), "suture", dtype="<U8"))
            group.append(np.full(len(p), len(clips)))
        pairs = np.concatenate(pairs) if pairs else np.zeros((0, 2), dtype=np.int64)
        start = np.linalg.norm(view.X[pairs[:, 0]] - view.X[pairs[:, 1]], axis=1)
        return Ties(pairs, np.concatenate(rest), np.concatenate(k), np.concatenate(kind),
                    np.concatenate(group), start_length=start)

    from mvfem.repairs import on_root

    ties = on_root(comm, work, f"{scene.source}: repair")
    if comm.rank != 0:
        ties = Ties(np.zeros((0, 2), dtype=np.int64), np.zeros(0), np.zeros(0),
                    np.zeros(0, dtype="<U8"), np.zeros(0, dtype=np.int64))
    return ties


def _rigid_pins(V, scene: Scene) -> list:
    """Six constraints that remove the rigid-body motion of a closed surface about its centre c.

    With R the largest distance of a node from c along each axis, the nodes at c +- R e_z keep
    ux = uy = 0 and the node at c + R e_x keeps uy = uz = 0: translations (x, y by the poles,
    z by the x-node), rotations about x and y (the poles) and about z (the x-node). A uniform
    inflation about c satisfies all six, so they do not change its answer. The nodes must exist
    (an octasphere has them); otherwise the scene is refused.
    """
    msh = V.mesh
    comm = msh.comm
    x = msh.geometry.x
    c = _centre(msh, scene["fibres"]["centre"])
    d = x - c
    R = comm.allreduce(float(np.abs(d).max(initial=0.0)), op=MPI.MAX)
    bcs = []
    for point, comps in (((0, 0, R), (0, 1)), ((0, 0, -R), (0, 1)), ((R, 0, 0), (1, 2))):
        near = np.flatnonzero(np.linalg.norm(d - np.array(point), axis=1) < 1e-8 * R)
        if comm.allreduce(len(near), op=MPI.SUM) == 0:
            raise InputError(f"{scene.source}: boundary.clamp: \"rigid\" needs mesh nodes at the "
                             f"centre +- R e_z and + R e_x (R = {R:.4g} mm), as an octasphere has")
        for comp in comps:
            Vc = V.sub(comp)
            dofs = fem.locate_dofs_geometrical(
                (Vc, Vc.collapse()[0]),
                lambda y, p=np.array(point) + c: np.linalg.norm(y.T - p, axis=1) < 1e-8 * R)
            zero = fem.Function(Vc.collapse()[0])
            bcs.append(fem.dirichletbc(zero, dofs, Vc))
    return bcs


def lumped_mass(model: Model):
    """Nodal area per displacement dof (PETSc Vec), zero on Dirichlet dofs.

    P1: the row sums of the mass matrix (a third of each adjacent triangle's area). Higher
    degrees: the row sums of P2 vanish at the vertices (the integral of a vertex function is
    0), so the pseudo-time shift ``k M`` left the flat start singular there and MUMPS reported
    a zero pivot or not by roundoff (the P2 Foppl disk of ``mvfem bench --quick`` failed on one
    machine and passed on another); they take the diagonal of the mass matrix scaled to the
    same total area instead (HRZ lumping: positive everywhere)."""
    from dolfinx.fem import petsc as fpetsc

    v = ufl.TestFunction(model.V)
    dx = ufl.dx(domain=model.mesh)
    row_sums = fem.form(ufl.dot(ufl.as_vector((1.0, 1.0, 1.0)), v) * dx)
    if model.V.ufl_element().degree() == 1:
        m = fpetsc.assemble_vector(row_sums)
        m.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    else:
        M = fpetsc.assemble_matrix(fem.form(ufl.inner(ufl.TrialFunction(model.V), v) * dx))
        M.assemble()
        m = fpetsc.create_vector(row_sums)  # the same ghosted layout
        M.getDiagonal(m)
        M.destroy()
        m.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        area = model.comm.allreduce(fem.assemble_scalar(fem.form(1.0 * dx)), op=MPI.SUM)
        m.scale(3 * area / m.sum())
    fpetsc.set_bc(m, model.bcs, scale=0.0)
    return m
