"""From a scene to the discrete problem: mesh, unknown, and the terms the scene asks for.

Only what a scene needs is built: a region energy per ``[[region]]``, a follower (or dead)
pressure, and a clamp on the boundary when there is one. The start-up stabiliser is not a form:
the solver adds it as a lumped diagonal (see :func:`lumped_mass`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import ufl
from dolfinx import fem, mesh as dmesh
from mpi4py import MPI
from petsc4py import PETSc

from mvfem.errors import InputError
from mvfem.forms import LAWS, Membrane, cauchy_stress, is_exponential, membrane, unit_normal
from mvfem.forms.pressure import dead_potential, dead_pressure, follower_potential, follower_pressure
from mvfem.scene import Scene

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
    #: potential; point terms add theirs), whose derivative is ``residual`` where the
    #: boundary is held: the solver's merit function (mvfem.solver.PseudoTransient)
    potential: ufl.core.expr.Expr | None = None

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


def build_mesh(scene: Scene, comm=MPI.COMM_WORLD):
    """The scene's surface mesh (a :class:`mvfem.meshes.SurfaceMesh`)."""
    from mvfem import meshes

    m = scene["mesh"]
    gen = m["generator"]
    size = m["size"] or default_size(m)
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
        return _valve(scene, comm, size)
    if gen == "file":
        try:
            raw = meshes.read_surface(m["file"])
        except ValueError as e:
            raise InputError(f"{scene.source}: mesh.file: {e}") from None
        if "annulus" in raw.point_data:  # a valve: annulus, free edges, chordae, as generated
            from mvfem.meshes.imported import valve_from_surface

            try:
                return valve_from_surface(comm, raw, m["labels"], source=m["file"])
            except ValueError as e:
                raise InputError(f"{scene.source}: mesh.file: {e}") from None
        values = raw.cell_data.get("leaflet")
        msh, tags = meshes.to_dolfinx(comm, raw, values)
        names = {v: int(k) for k, v in (m["labels"] or {}).items()}
        return meshes.SurfaceMesh(mesh=msh, cell_tags=tags, facet_tags=None, names=names,
                                  info={"generator": "file", "file": m["file"]})
    raise InputError(f"{scene.source}: mesh.generator: {gen!r} is not available")


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
        return valve(comm, size=size, **kw)
    except ValueError as e:
        raise InputError(f"{scene.source}: mesh: {e}") from None


def _centre(msh, given) -> np.ndarray:
    if given is not None:
        return np.asarray(given, dtype=float)
    n = msh.geometry.index_map().size_local
    x = msh.geometry.x[:n]
    s = msh.comm.allreduce(x.sum(axis=0), op=MPI.SUM)
    c = msh.comm.allreduce(len(x), op=MPI.SUM)
    return s / max(c, 1)


def _tangent_unit(vec, n0):
    t = vec - ufl.dot(vec, n0) * n0
    return t / ufl.sqrt(ufl.dot(t, t))


def _directions(msh, fibres: dict, phi=None):
    """(fibre, radial, circumferential) unit tangent fields of the reference surface (UFL).

    With ``phi`` (a valve's Laplace coordinate, :mod:`mvfem.meshes.fibres`) radial is its
    gradient direction; otherwise radial and circumferential are taken about ``fibres.axis``
    through ``fibres.centre``.
    """
    x = ufl.SpatialCoordinate(msh)
    n0 = unit_normal(ufl.Jacobian(msh))
    if phi is not None:
        from mvfem.meshes.fibres import radial_circumferential

        radial, circ = radial_circumferential(phi, n0)
        direction = fibres["direction"]
        if direction == "circumferential":
            return circ, radial, circ
        if direction == "radial":
            return radial, radial, circ
        return _tangent_unit(fem.Constant(msh, np.asarray(direction, dtype=float)), n0), \
            radial, circ
    axis = np.asarray(fibres["axis"], dtype=float)
    # Constants, not literals: the generated code is then the same for every mesh (JIT cache)
    axis = fem.Constant(msh, axis / np.linalg.norm(axis))
    c = fem.Constant(msh, _centre(msh, fibres["centre"]))
    d = x - c
    circ = _tangent_unit(ufl.cross(axis, d), n0)
    radial = _tangent_unit(d - ufl.dot(d, axis) * axis, n0)
    direction = fibres["direction"]
    if direction == "circumferential":
        fibre = circ
    elif direction == "radial":
        fibre = radial
    else:
        fibre = _tangent_unit(fem.Constant(msh, np.asarray(direction, dtype=float)), n0)
    return fibre, radial, circ


def _region_cells(surface, label: str | None, n_regions: int, source: str):
    """(tag value, measure subdomain) for a region label."""
    if n_regions == 1 and label is None:
        return None
    names = getattr(surface, "names", {}) or {}
    if label in names:
        return int(names[label])
    if n_regions == 1:
        return None
    raise InputError(f"{source}: region.label: {label!r} is not a label of the mesh "
                     f"(labels: {', '.join(map(str, names)) or 'none'})")


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
    phi = None
    if annulus is not None:
        from mvfem.meshes.fibres import boundary_split, laplace_coordinate

        vertices = dmesh.compute_incident_entities(msh, annulus, msh.topology.dim - 1, 0)
        ann, free_edge = boundary_split(msh, vertices)
        try:
            phi = laplace_coordinate(msh, ann, free_edge)
        except ValueError as e:
            raise InputError(f"{scene.source}: mesh: {e}") from None
    fibre, radial, circ = _directions(msh, scene["fibres"], phi)
    kin = membrane(u, fibre)
    meta = {"quadrature_degree": q}
    tags = surface.cell_tags
    regions = []
    energy = 0
    for r in scene["region"]:
        tag = _region_cells(surface, r["label"], len(scene["region"]), scene.source)
        dx = (ufl.Measure("dx", domain=msh, subdomain_data=tags, subdomain_id=tag, metadata=meta)
              if tag is not None else ufl.Measure("dx", domain=msh, metadata=meta))
        consts = {k: fem.Constant(msh, float(val)) for k, val in r["params"].items()}
        h0 = fem.Constant(msh, float(r["thickness"]))
        extra = {"max_exponent": MAX_EXPONENT} if is_exponential(r["law"]) else {}
        W = LAWS[r["law"]](kin, *consts.values(), **extra)
        regions.append(Region(r["label"] or "membrane", tag, r["law"], r.get("set", "custom"),
                              consts, h0, W, dx))
        energy = energy + h0 * W * dx

    E_b = scene["bending"]["modulus"]
    if E_b is None:
        E_b = VALVE_BENDING_MODULUS if annulus is not None else 0.0
    if E_b > 0:
        from mvfem.forms.bending import hinge_energy

        h_mean = float(np.mean([float(r.thickness.value) for r in regions]))
        D = fem.Constant(msh, E_b * h_mean**3 / 12.0)
        energy = energy + hinge_energy(u, D) * ufl.dS(domain=msh, metadata={"quadrature_degree": 1})

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
    if scene["boundary"]["clamp"] == "boundary":
        msh.topology.create_connectivity(1, 2)
        facets = dmesh.exterior_facet_indices(msh.topology)
        n_facets = comm.allreduce(len(facets), op=MPI.SUM)
        if n_facets == 0:
            raise InputError(f"{scene.source}: boundary.clamp: the mesh has no boundary to clamp "
                             "(use clamp = \"none\")")
        dofs = fem.locate_dofs_topological(V, 1, facets)
        bcs.append(fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType), dofs, V))
    elif scene["boundary"]["clamp"] == "rigid":
        bcs += _rigid_pins(V, scene)
    elif scene["boundary"]["clamp"] == "annulus":
        if annulus is None or comm.allreduce(len(annulus), op=MPI.SUM) == 0:
            raise InputError(f"{scene.source}: boundary.clamp: \"annulus\" needs a valve mesh "
                             "(generator = \"valve\", or a file with point data 'annulus')")
        dofs = fem.locate_dofs_topological(V, 1, annulus)
        bcs.append(fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType), dofs, V))

    p_target = float(load["pressure"])
    stab_scale = s["stabilisation"] * max(abs(p_target), 1.0) / L
    model = Model(scene=scene, surface=surface, mesh=msh, V=V, u=u, kin=kin,
                  regions=regions, fibre=fibre, radial=radial, circumferential=circ,
                  pressure=pressure, p_target=p_target, stabiliser_scale=stab_scale,
                  energy=energy, residual=residual, load_form=p_term, bcs=bcs,
                  quadrature_degree=q, length_scale=L, info={"area_mm2": area}, phi=phi,
                  potential=energy + p_pot)
    _point_terms(model)
    return model


def _annulus_facets(surface):
    """Local annulus edges of a valve surface, or None for a surface without an annulus."""
    names = getattr(surface, "names", {}) or {}
    if "annulus" not in names or surface.facet_tags is None:
        return None
    return surface.facets("annulus")


def _has_chordae(surface) -> bool:
    return len(getattr(surface, "insertion_points", ())) > 0


def _point_terms(model: Model) -> None:
    """Chordae and contact, when the scene asks for them and the mesh is a valve."""
    from mvfem.contact import Contact
    from mvfem.nodal import NodalView, PointTerms

    scene, surface = model.scene, model.surface
    valve = _annulus_facets(surface) is not None
    want_chordae = scene["chordae"]["enabled"] and _has_chordae(surface)
    want_contact = scene["contact"]["enabled"] and valve
    if not (want_chordae or want_contact):
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
    model.view = view
    model.point_terms = PointTerms(view, terms)


#: Carpentier's segments as fractions along a leaflet from the posteromedial commissure
SEGMENTS = {"3": (0.0, 1 / 3), "2": (1 / 3, 2 / 3), "1": (2 / 3, 1.0)}


def _chordae(scene: Scene, surface, view):
    """Tethers of the valve's chordae insertions, with the scene's family parameters and
    edits (``[[chordae.edit]]``: lengthened, shortened or ruptured chords)."""
    from mvfem.chordae import Chordae

    chords, error = None, None
    if view.comm.rank == 0:
        try:
            chords = _chordae_on_root(scene, surface, view)
        except InputError as e:
            error = str(e)
    error = view.comm.bcast(error, root=0)
    if error:
        raise InputError(error)
    if view.comm.rank != 0:
        return Chordae(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(0),
                       np.zeros(0, dtype="<U8"))
    return chords


def _chordae_on_root(scene: Scene, surface, view):
    from mvfem.chordae import Chordae

    fams = scene["chordae"]
    names = {v: k for k, v in (surface.names or {}).items()}
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
        if not sel.any():
            raise InputError(f"{scene.source}: chordae.edit[{i}]: selects no chord of this valve "
                             f"(leaflets: {', '.join(sorted(set(leaflet)))}; families: "
                             f"{', '.join(sorted(set(family)))})")
        if e["rupture"]:
            keep &= ~sel
        else:
            rest[sel] *= e["length_factor"]
    return Chordae(node[keep], anchor[keep], rest[keep], EA[keep] / rest[keep], family[keep],
                   leaflet[keep])


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
    """Nodal area per displacement dof (PETSc Vec), zero on Dirichlet dofs."""
    from dolfinx.fem import petsc as fpetsc

    v = ufl.TestFunction(model.V)
    one = ufl.as_vector((1.0, 1.0, 1.0))
    m = fpetsc.assemble_vector(fem.form(ufl.dot(one, v) * ufl.dx(domain=model.mesh)))
    m.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    fpetsc.set_bc(m, model.bcs, scale=0.0)
    return m
