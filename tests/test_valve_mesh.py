"""The open mitral valve mesh (meshes/valve.py): annulus, leaflets, orientation, tags, chordae
insertion points, a patient annulus, and the imported-valve file.

Independent references:
- annulus: the ellipse x = a cos t, y = b sin t (a, b the half diameters) has the perimeter
  (Ramanujan) P ~ pi [3 (a + b) - sqrt((3a + b)(a + 3b))]; the saddle z = (h/2) cos 2t adds
  length out of the plane, so the projected length is compared with Ramanujan and the 3-D length
  with the quadrature of |dX/dt| over t;
- leaflet area ~ (annulus arc length) x (mean leaflet height over the arc): a rectangle unrolled
  from the annulus. The mesh is smaller because the leaflets converge toward the orifice (a
  funnel: the free edge is shorter than the annulus arc), by about 20 %; within 30 %;
- orientation: the membrane forms see the normal cross(dX/dxi1, dX/dxi2) (ufl.Jacobian); it
  must point to the atrium (+axis) in every cell (the leaflets hang tilted inward, so the
  smooth surface normal has axis component sin(tilt) ~ 0.34 everywhere), and no cell may be
  folded back: across every interior edge the two cells traverse the edge in opposite
  directions (consistent orientation) and their unit normals differ by less than 60 degrees.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import ufl
from dolfinx import cpp, fem
from dolfinx import mesh as dmesh
from mpi4py import MPI

from mvfem.meshes import ValveMesh, read_surface, valve, write_valve
from mvfem.meshes.io import _cpp_mesh

DATA = Path("/work/shared/data/kaiser_normal1")
ANNULUS_CSV = DATA / "normal1_annulus_loop_mm.csv"
PAPILLARY_CSV = DATA / "normal1_papillary_tips_mm.csv"


# --- fixtures and helpers --------------------------------------------------------------------

@pytest.fixture(scope="module")
def default_valve():
    t0 = time.perf_counter()
    v = valve(MPI.COMM_WORLD)
    v.info["test_build_s"] = time.perf_counter() - t0
    return v


@pytest.fixture(scope="module")
def patient():
    if not ANNULUS_CSV.is_file():
        pytest.skip(f"patient data not found: {DATA}")
    loop = np.loadtxt(ANNULUS_CSV, delimiter=",", skiprows=1)
    tips = np.loadtxt(PAPILLARY_CSV, delimiter=",", skiprows=1)
    return loop, tips, valve(MPI.COMM_WORLD, annulus=loop, papillary=tips)


def _sum(comm, value):
    return comm.allreduce(value, op=MPI.SUM)


def _area(v: ValveMesh, name: str | None = None) -> float:
    dx = ufl.Measure("dx", domain=v.mesh, subdomain_data=v.cell_tags)
    form = 1.0 * (dx if name is None else dx(v.names[name]))
    return _sum(v.mesh.comm, fem.assemble_scalar(fem.form(form)))


def _length(v: ValveMesh, name: str) -> float:
    ds = ufl.Measure("ds", domain=v.mesh, subdomain_data=v.facet_tags)
    return _sum(v.mesh.comm, fem.assemble_scalar(fem.form(1.0 * ds(v.names[name]))))


def _normal_dot_axis(v: ValveMesh) -> np.ndarray:
    """Per owned cell: cross(J[:, 0], J[:, 1]) / |.| . axis."""
    msh = v.mesh
    J = ufl.Jacobian(msh)
    n = ufl.cross(J[:, 0], J[:, 1])
    cos = ufl.dot(n, ufl.as_vector(v.axis)) / ufl.sqrt(ufl.dot(n, n))
    V0 = fem.FunctionSpace(msh, ("DG", 0))
    f = fem.Function(V0)
    f.interpolate(fem.Expression(cos, V0.element.interpolation_points()))
    return f.x.array[: msh.topology.index_map(2).size_local].copy()


def _owned(v: ValveMesh, dim: int, name: str) -> np.ndarray:
    idx = v.facets(name) if dim == 1 else v.cells(name)
    return idx[idx < v.mesh.topology.index_map(dim).size_local]


def _facet_points(v: ValveMesh, facets: np.ndarray) -> np.ndarray:
    """(F, 2, 3) end points of the given local facets."""
    g = cpp.mesh.entities_to_geometry(_cpp_mesh(v.mesh), 1, facets, False)
    return v.mesh.geometry.x[g.reshape(-1, 2)]


def _gathered(comm, a: np.ndarray) -> np.ndarray:
    parts = comm.allgather(np.asarray(a))
    return np.concatenate(parts) if parts else a


def _min_angles(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    x = points[tri]
    out = []
    for i in range(3):
        u, w = x[:, (i + 1) % 3] - x[:, i], x[:, (i + 2) % 3] - x[:, i]
        c = np.einsum("ij,ij->i", u, w) / np.linalg.norm(u, axis=1) / np.linalg.norm(w, axis=1)
        out.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    return np.min(out, axis=0)


def _segment_distance(p: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Distance of each point to the closed polyline ``loop``."""
    a, b = loop, np.roll(loop, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("pkj,kj->pk", p[:, None] - a[None], ab) / np.sum(ab * ab, axis=1),
                0, 1)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(p[:, None] - closest, axis=2).min(axis=1)


# --- the parametric default ------------------------------------------------------------------

def test_default_annulus_perimeter_and_saddle(default_valve):
    v = default_valve
    comm = v.mesh.comm
    a, b, h = 14.0, 18.5, 6.0
    ramanujan = np.pi * (3 * (a + b) - np.sqrt((3 * a + b) * (a + 3 * b)))  # 102.6 mm
    t = np.linspace(0, 2 * np.pi, 200001)
    speed = np.sqrt((a * np.sin(t)) ** 2 + (b * np.cos(t)) ** 2 + (h * np.sin(2 * t)) ** 2)
    length_3d = np.trapz(speed, t)  # 106.0 mm

    seg = _facet_points(v, _owned(v, 1, "annulus"))
    projected = _sum(comm, float(np.linalg.norm(seg[:, 1, :2] - seg[:, 0, :2], axis=1).sum()))
    assert projected == pytest.approx(ramanujan, rel=0.02)
    assert projected == pytest.approx(ramanujan, rel=2e-3)  # measured: -0.02 %
    assert _length(v, "annulus") == pytest.approx(length_3d, rel=0.01)

    # annulus nodes on the saddle ellipse; its height as requested
    x = _gathered(comm, seg.reshape(-1, 3))
    assert np.allclose((x[:, 0] / a) ** 2 + (x[:, 1] / b) ** 2, 1.0, atol=2e-3)
    theta = np.arctan2(x[:, 1] / b, x[:, 0] / a)
    assert np.allclose(x[:, 2], 0.5 * h * np.cos(2 * theta), atol=0.01)
    assert np.ptp(x[:, 2]) == pytest.approx(h, rel=0.01)
    assert v.info["annulus_perimeter_mm"] == pytest.approx(length_3d, rel=1e-3)
    # saddle high points anterior (x > 0) and posterior, low points at the commissures
    assert x[np.argmax(x[:, 2]), 1] == pytest.approx(0.0, abs=1.0)
    assert abs(x[np.argmin(x[:, 2]), 1]) == pytest.approx(b, abs=0.1)


def test_default_leaflet_areas_plausible(default_valve):
    v = default_valve
    total = _area(v)
    areas = {name: _area(v, name) for name in ("anterior", "posterior")}
    assert sum(areas.values()) == pytest.approx(total, rel=1e-12)
    for name, area in areas.items():
        lf = v.info["leaflets"][name]
        rectangle = lf["arc_length_mm"] * lf["mean_height_mm"]  # unrolled, no convergence
        assert 0.7 * rectangle < area < rectangle, (name, area, rectangle)  # measured 0.82, 0.83
        assert area == pytest.approx(v.info["leaflet_area_mm2"][name], rel=1e-9)
    # arc lengths: anterior_share of the annulus (150 of 360 degrees by length)
    ant, post = (v.info["leaflets"][k]["arc_length_mm"] for k in ("anterior", "posterior"))
    assert ant / (ant + post) == pytest.approx(150 / 360, rel=1e-3)
    # enough tissue to close: leaflet area well above the orifice (annulus) area
    assert 1.3 < total / (np.pi * 14.0 * 18.5) < 2.0  # measured 1.46


def test_default_normals_point_to_atrium(default_valve):
    v = default_valve
    comm = v.mesh.comm
    assert np.allclose(v.axis, [0, 0, 1]) and np.allclose(v.frame, np.eye(3))
    cos = _normal_dot_axis(v)
    n = _sum(comm, len(cos))
    assert comm.allreduce(cos.min(initial=1.0), op=MPI.MIN) > 0.15  # measured 0.32
    assert _sum(comm, float(cos.sum())) / n > 0.3  # measured 0.38
    assert v.info["cells_flipped"] == 0  # gmsh already gave the atrial orientation


def test_default_tags_partition_and_boundary(default_valve):
    v = default_valve
    msh, comm = v.mesh, v.mesh.comm
    assert v.names == {"anterior": 1, "posterior": 2, "annulus": 3, "free_edge_anterior": 4,
                       "free_edge_posterior": 5}
    nloc = msh.topology.index_map(2).size_local
    ids = v.cell_tags.indices[v.cell_tags.indices < nloc]
    assert len(np.unique(ids)) == len(ids) == nloc  # every owned cell exactly once
    assert set(v.cell_tags.values) <= {1, 2}
    n_ant, n_post = (_sum(comm, len(_owned(v, 2, k))) for k in ("anterior", "posterior"))
    assert n_ant + n_post == msh.topology.index_map(2).size_global == v.info["cells"]
    assert n_ant > 0 and n_post > 0

    # the three edge groups are disjoint and together exactly the boundary
    msh.topology.create_connectivity(1, 2)
    exterior = dmesh.exterior_facet_indices(msh.topology)
    groups = {k: v.facets(k) for k in ("annulus", "free_edge_anterior", "free_edge_posterior")}
    tagged = np.concatenate(list(groups.values()))
    assert len(np.unique(tagged)) == len(tagged)
    assert np.array_equal(np.sort(tagged), np.sort(exterior))
    for k, f in groups.items():
        assert _sum(comm, len(_owned(v, 1, k))) > 20, k
    # a free edge borders only cells of its own leaflet
    f2c = msh.topology.connectivity(1, 2)
    cell_value = np.zeros(msh.topology.index_map(2).size_local
                          + msh.topology.index_map(2).num_ghosts, dtype=np.int32)
    cell_value[v.cell_tags.indices] = v.cell_tags.values
    for name in ("anterior", "posterior"):
        cells = np.concatenate([f2c.links(f) for f in groups[f"free_edge_{name}"]] or [[]])
        assert np.all(cell_value[cells.astype(np.int32)] == v.names[name])
    # the leaflets are one curtain: they share the two commissural rulings, lines of about
    # commissure_height (6 mm) from each commissure down to the free edge, and nothing else
    owned_cells = [msh.geometry.dofmap.array.reshape(-1, 3)[v.cells(k)] for k in
                   ("anterior", "posterior")]
    gid = np.asarray(msh.geometry.input_global_indices)
    ant, post = (set(_gathered(comm, gid[c].ravel()).tolist()) for c in owned_cells)
    shared = np.array(sorted(ant & post))
    ids = _gathered(comm, gid)
    xyz = _gathered(comm, msh.geometry.x)
    x_of = dict(zip(ids.tolist(), xyz))
    xs = np.array([x_of[i] for i in shared])
    d = np.linalg.norm(xs[:, None] - v.commissures[None], axis=2).min(axis=1)
    h = v.info["commissure_height"]
    assert d.min() < 1e-9 and d.max() == pytest.approx(h, rel=0.05)
    assert 2 * (h / v.info["size"]) <= len(shared) <= 2 * (h / v.info["free_edge_size"] + 2)
    # the free edge is one closed loop through both notches
    fe = np.concatenate([_owned(v, 1, f"free_edge_{k}") for k in ("anterior", "posterior")])
    g = cpp.mesh.entities_to_geometry(_cpp_mesh(msh), 1, fe, False).reshape(-1, 2)
    _, degree = np.unique(_gathered(comm, gid[g].ravel()), return_counts=True)
    assert np.all(degree == 2)


def test_default_quality_and_info(default_valve):
    v = default_valve
    assert v.info["min_angle_deg"] > 25.0  # measured 32.1
    assert v.info["mean_quality"] > 0.95
    assert v.info["edge_length_mm"]["max"] < 1.6 * v.info["size"]
    json.dumps(v.info)  # JSON-serialisable
    print(f"\ndefault valve: {v.info['cells']} cells, {v.info['vertices']} vertices, min angle "
          f"{v.info['min_angle_deg']:.1f} deg, build {v.info['test_build_s']:.1f} s")


def test_default_insertion_points(default_valve):
    v = default_valve
    msh, comm = v.mesh, v.mesh.comm
    P = v.insertion_points
    assert P.shape == (len(v.insertion_leaflet), 3) and len(P) > 30

    def nearest(points, candidates):
        d = np.full(len(points), np.inf)
        if len(candidates):
            d = np.min(np.linalg.norm(points[:, None] - candidates[None], axis=2), axis=1)
        out = np.empty_like(d)
        comm.Allreduce(d, out, op=MPI.MIN)
        return out

    # every insertion point is a mesh vertex
    assert np.all(nearest(P, msh.geometry.x) < 1e-10)
    for name in ("anterior", "posterior"):
        marginal = v.insertions("marginal", name)
        assert 10 < len(marginal) < 40, (name, len(marginal))
        edge = _facet_points(v, v.facets(f"free_edge_{name}")).reshape(-1, 3)
        assert np.all(nearest(P[marginal], edge) < 1e-10)  # on the free edge
        # not at the commissures; ~2.5 mm apart along the edge
        assert np.all(np.linalg.norm(P[marginal][:, None] - v.commissures[None], axis=2)
                      > 1.5)
        gaps = np.linalg.norm(np.diff(P[marginal], axis=0), axis=1)
        assert 1.0 < gaps.min() and gaps.max() < 4.0 and 2.0 < np.median(gaps) < 3.0
        belly = v.insertions("strut" if name == "anterior" else "basal", name)
        assert len(belly) == (2 if name == "anterior" else 3)
        leaflet_x = msh.geometry.x[msh.geometry.dofmap.array.reshape(-1, 3)[v.cells(name)]]
        assert np.all(nearest(P[belly], leaflet_x.reshape(-1, 3)) < 1e-10)
        msh.topology.create_connectivity(1, 2)
        boundary = _facet_points(v, dmesh.exterior_facet_indices(msh.topology)).reshape(-1, 3)
        assert np.all(nearest(P[belly], boundary) > 0.5 * v.info["free_edge_size"])
    # papillary muscles: tips below the annulus, one muscle per side; insertions by side
    assert v.papillary_tips.shape == (2, 3)
    assert np.allclose(v.papillary_tips[:, 2], -23.5)
    assert list(v.papillary_muscle) == [0, 1] and v.papillary_tips[0, 1] > 0
    assert np.array_equal(v.papillary_muscle[v.insertion_tip], v.insertion_muscle)
    side = np.where(P[:, 1] >= 0, 0, 1)
    assert np.array_equal(side, v.insertion_muscle)
    # papillary_position (0.25, 0.75): a quarter of the way toward the anterior annulus (AP
    # 28 mm) and three quarters of the way toward each commissure (37 mm)
    assert np.allclose(v.papillary_tips[:, :2], [[0.25 * 14, 0.75 * 18.5],
                                                 [0.25 * 14, -0.75 * 18.5]], atol=0.01)


def test_orifice_is_open(default_valve):
    """The free edges are well apart: the anteroposterior gap between them at the middle."""
    v = default_valve
    xa = v.insertion_points[v.insertions("marginal", "anterior")]
    xp = v.insertion_points[v.insertions("marginal", "posterior")]
    gap = (xa[np.argmin(np.abs(xa[:, 1])), 0] - xp[np.argmin(np.abs(xp[:, 1])), 0])
    assert gap > 10.0  # measured 14.2 mm of the 28 mm annulus


# --- the imported-valve file and MPI ---------------------------------------------------------

@pytest.mark.mpi
def test_valve_distributed_and_written(default_valve, shared_tmp):
    """Same mesh on any number of ranks; the written file has the leaflet and annulus data,
    and no cell is folded back (edge-neighbour criterion of the module docstring)."""
    v = default_valve
    comm = v.mesh.comm
    assert v.mesh.topology.index_map(2).size_global == v.info["cells"]
    assert _area(v, "anterior") == pytest.approx(v.info["leaflet_area_mm2"]["anterior"],
                                                 rel=1e-9)
    assert comm.allreduce(_normal_dot_axis(v).min(initial=1.0), op=MPI.MIN) > 0.15
    path = shared_tmp / "valve.vtu"
    write_valve(path, v)
    comm.Barrier()
    raw = read_surface(path)
    assert len(raw.triangles) == v.info["cells"] and len(raw.points) == v.info["vertices"]
    leaflet = raw.cell_data["leaflet"]
    assert set(np.unique(leaflet)) == {1, 2}
    assert np.sum(leaflet == 1) == _sum(comm, len(_owned(v, 2, "anterior")))
    n_annulus_edges = _sum(comm, len(_owned(v, 1, "annulus")))
    assert int(raw.point_data["annulus"].sum()) == n_annulus_edges  # a closed loop
    assert np.all(raw.points[raw.point_data["annulus"] == 1, 2] > -3.0 - 1e-9)
    assert _min_angles(raw.points, raw.triangles).min() > 25.0

    # consistent orientation, no folds: each interior edge is used once in each direction,
    # and the unit normals of its two cells are within 60 degrees
    tri = raw.triangles
    x = raw.points[tri]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    n /= np.linalg.norm(n, axis=1)[:, None]
    half = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    owner = np.tile(np.arange(len(tri)), 3)
    key = {tuple(e): c for e, c in zip(half.tolist(), owner)}
    assert len(key) == len(half)  # no directed edge twice: consistent orientation
    pairs = np.array([(c, key[(b, a)]) for (a, b), c in key.items() if (b, a) in key])
    assert len(pairs) > 0
    assert np.einsum("ij,ij->i", n[pairs[:, 0]], n[pairs[:, 1]]).min() > 0.5
    assert np.all(n @ v.axis > 0)


# --- patient annulus -------------------------------------------------------------------------

def test_patient_annulus_valve(patient):
    loop, tips, v = patient
    comm = v.mesh.comm
    size = v.info["size"]
    # frame: axis away from the papillary tips, centre on the loop's plane and centroid
    assert np.all((tips - v.centre) @ v.axis < -20.0)
    assert np.linalg.norm(v.centre - loop.mean(axis=0)) < 1.0
    assert np.abs((loop - v.centre) @ v.axis).max() < 0.5  # this loop is planar
    assert np.allclose(v.frame @ v.frame.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(v.frame) == pytest.approx(1.0)
    # annulus nodes on the given loop; length as the loop's
    seg = _facet_points(v, _owned(v, 1, "annulus"))
    d = _segment_distance(seg.reshape(-1, 3), loop)
    dmax = comm.allreduce(d.max(initial=0.0), op=MPI.MAX)
    assert dmax < size and dmax < 0.3  # measured 0.043 mm
    perimeter = np.linalg.norm(np.roll(loop, -1, axis=0) - loop, axis=1).sum()
    assert _length(v, "annulus") == pytest.approx(perimeter, rel=0.02)
    # commissures: commissural extent of the loop (+-21.8 mm) along the frame's second axis
    c_local = (v.commissures - v.centre) @ v.frame.T
    assert c_local[0, 1] > 15 and c_local[1, 1] < -15
    # papillary tips: two muscles of four, one on each side
    assert np.bincount(v.papillary_muscle).tolist() == [4, 4]
    tl = (v.papillary_tips - v.centre) @ v.frame.T
    assert np.all(tl[v.papillary_muscle == 0, 1] > 0) and np.all(tl[v.papillary_muscle == 1, 1] < 0)
    # orientation, quality, tags, insertion points as for the default
    cos = _normal_dot_axis(v)
    assert comm.allreduce(cos.min(initial=1.0), op=MPI.MIN) > 0.1  # measured 0.27
    assert v.info["min_angle_deg"] > 20.0  # measured 28.2
    assert 1.2 < _area(v) / _projected_loop_area(loop, v) < 2.0  # measured 1.48
    assert np.all(np.min(np.linalg.norm(v.insertion_points[:, None]
                                        - _gathered(comm, v.mesh.geometry.x)[None], axis=2),
                         axis=1) < 1e-10)
    assert np.array_equal(v.papillary_muscle[v.insertion_tip], v.insertion_muscle)
    json.dumps(v.info)


def _projected_loop_area(loop: np.ndarray, v: ValveMesh) -> float:
    xy = (loop - v.centre) @ v.frame[:2].T
    return 0.5 * abs(np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1]))


def test_patient_anterior_hint(patient):
    """By default the flatter side of the D is anterior; a hint can turn the valve round."""
    loop, tips, v = patient
    hint = -v.frame[0]
    w = valve(MPI.COMM_WORLD, annulus=loop, papillary=tips, anterior_direction=hint, size=2.0,
              free_edge_size=2.0, refine_distance=2.0)
    assert np.allclose(w.frame[0], hint) and np.allclose(w.frame[2], v.frame[2])
    assert np.allclose(w.frame[1], -v.frame[1])
    # the default choice: the anterior side is nearer the commissural axis (flatter)
    x = (loop - v.centre) @ v.frame[0]
    assert x.max() < -x.min()


def test_invalid_arguments():
    comm = MPI.COMM_WORLD
    with pytest.raises(ValueError, match="anterior_angle"):
        valve(comm, anterior_angle=-5.0)
    with pytest.raises(ValueError, match="free_edge_size"):
        valve(comm, size=0.5, free_edge_size=1.0)
    with pytest.raises(ValueError, match="annulus"):
        valve(comm, annulus=np.zeros((4, 3)))


# --- nested refinement (valve(refine=n), mesh.refine) ----------------------------------------

@pytest.fixture(scope="module")
def refined():
    """The 4 mm valve unrefined, refined once and twice."""
    return [valve(MPI.COMM_WORLD, size=4.0, free_edge_size=2.0, refine=n) for n in (0, 1, 2)]


@pytest.mark.mpi
def test_refined_valve_is_nested(refined):
    """Each 1-to-4 split keeps every node and insertion of the level below, has 4x its cells
    and V + E vertices (one new node per edge; E = 3 F / 2 + boundary edges / 2 on a surface
    with F triangles), 2x its annulus and free-edge facets, and every cell still points to the
    atrium."""
    comm = MPI.COMM_WORLD
    for coarse, fine in zip(refined, refined[1:]):
        F, V = coarse.info["cells"], coarse.info["vertices"]
        n_boundary = sum(_sum(comm, len(_owned(coarse, 1, name))) for name in
                         ("annulus", "free_edge_anterior", "free_edge_posterior"))
        assert fine.info["cells"] == 4 * F
        assert fine.info["vertices"] == V + (3 * F + n_boundary) // 2
        for name in ("annulus", "free_edge_anterior", "free_edge_posterior"):
            assert _sum(comm, len(_owned(fine, 1, name))) == 2 * _sum(comm,
                                                                      len(_owned(coarse, 1, name)))
        for name in ("anterior", "posterior"):
            assert _sum(comm, len(_owned(fine, 2, name))) == 4 * _sum(comm,
                                                                      len(_owned(coarse, 2, name)))
        xf = _gathered(comm, fine.mesh.geometry.x)
        xc = _gathered(comm, coarse.mesh.geometry.x)
        d = np.min(np.linalg.norm(xc[:, None] - xf[None], axis=2), axis=1)
        assert d.max() < 1e-12  # the coarse nodes are fine nodes
        assert np.array_equal(fine.insertion_points, coarse.insertion_points)
        assert np.array_equal(fine.insertion_family, coarse.insertion_family)
        assert _sum(comm, int(np.sum(_normal_dot_axis(fine) <= 0.0))) == 0
        # a 1-to-4 split of flat triangles keeps their angles; the new nodes' placement on the
        # curved surface moves them a little
        assert fine.info["min_angle_deg"] > 0.8 * coarse.info["min_angle_deg"]
    assert refined[2].info["unrefined"]["cells"] == refined[0].info["cells"]


@pytest.mark.mpi
def test_refined_nodes_lie_on_the_curved_surface(refined):
    """The new nodes are placed on the leaflets' surfaces, not on the coarse flat triangles:
    (a) the annulus nodes of the twice-refined valve are no further from the annulus curve
    (its 4096-point polyline, whose own chord error is ~1e-5 mm) than the unrefined mesh's
    nodes are from the leaflet surfaces (gmsh's nodes lie on a sampled copy: ~0.01 mm), where
    the chords' midpoints of the 4 mm mesh miss it by up to h^2 / (8 R) ~ 0.1 mm; (b) areas and lengths converge as h^2: the
    differences between successive levels shrink about fourfold (Richardson), and each level
    adds area (a convex ruled surface's inscribed facets have less area than it)."""
    comm = MPI.COMM_WORLD
    fine = refined[2]
    ann = _facet_points(fine, _owned(fine, 1, "annulus")).reshape(-1, 3)
    d = _segment_distance(ann, np.asarray(fine.annulus_curve)) if len(ann) else np.zeros(1)
    off = fine.info["unrefined"]["surface_distance_mm"]
    assert comm.allreduce(float(d.max()), op=MPI.MAX) < off + 1e-6 and off < 0.02
    coarse = refined[0]
    ann0 = _facet_points(coarse, _owned(coarse, 1, "annulus"))
    mid = ann0.mean(axis=1)
    d0 = _segment_distance(mid, np.asarray(coarse.annulus_curve)) if len(mid) else np.zeros(1)
    assert comm.allreduce(float(d0.max()), op=MPI.MAX) > 3 * off  # the chords' midpoints
    for measure in ([lambda v, n=n: _area(v, n) for n in ("anterior", "posterior")]
                    + [lambda v: _length(v, "annulus"),
                       lambda v: _length(v, "free_edge_anterior")]):
        a0, a1, a2 = (measure(v) for v in refined)
        assert a0 < a1 < a2
        assert 3.0 < (a1 - a0) / (a2 - a1) < 5.0, (a0, a1, a2)


def test_levels_reuse_the_gmsh_mesh_of_the_same_valve():
    """A refined valve made right after another level of the same valve splits that gmsh
    mesh instead of meshing again (nested levels), to the same mesh as a fresh one; any other
    parameter meshes again."""
    import importlib

    valve_module = importlib.import_module("mvfem.meshes.valve")  # (the package: the function)

    def arrays(v):
        return v.mesh.geometry.x.copy(), v.mesh.geometry.dofmap.array.copy()

    kw = dict(size=4.0, free_edge_size=2.0)
    valve_module._LAST_MESH.clear()
    fresh = valve(MPI.COMM_SELF, refine=1, **kw)
    assert not fresh.info["gmsh_reused"] and fresh.info["time_s"]["gmsh"] > 0
    valve(MPI.COMM_SELF, refine=0, **kw)
    again = valve(MPI.COMM_SELF, refine=1, **kw)
    assert again.info["gmsh_reused"] and again.info["time_s"]["gmsh"] == 0.0
    for a, b in zip(arrays(fresh), arrays(again)):
        assert np.array_equal(a, b)
    assert np.array_equal(fresh.insertion_points, again.insertion_points)
    other = valve(MPI.COMM_SELF, refine=1, anterior_height=20.0, **kw)
    assert not other.info["gmsh_reused"] and other.info["cells"] != fresh.info["cells"]


def test_mesh_is_deaf_to_the_last_bit_of_its_geometry(monkeypatch):
    """The leaflets' fine sample (a staggered grid, full of co-circular quadruples) is rounded
    to ``SNAP`` before its Delaunay triangulation and gmsh: the annulus curve perturbed by one
    unit in the last place either way, or by 1e-14, gives the same mesh, bit for bit. The
    control: without the rounding, these perturbations give other meshes (another node count,
    or nodes mm apart), as numpy's AVX-512 and AVX2 kernels did (648 against 643 nodes on
    the demo)."""
    import importlib

    vm = importlib.import_module("mvfem.meshes.valve")  # (the package: the function)
    curve_init = vm._Curve.__init__

    def mesh(eps: float):
        def perturbed(self, loop, smoothing=0.0):
            curve_init(self, loop, smoothing)
            self.length *= 1.0 + eps
            self.x = self.x * (1.0 + eps)
        vm._LAST_MESH.clear()
        with monkeypatch.context() as m:
            m.setattr(vm._Curve, "__init__", perturbed)
            v = valve(MPI.COMM_SELF, size=2.0, anterior_height=23.0)
        return v.mesh.geometry.x.copy(), v.mesh.geometry.dofmap.array.copy()

    def same(a, b):
        return all(p.shape == q.shape and np.array_equal(p, q) for p, q in zip(a, b))

    epsilons = (2.0**-52, -(2.0**-52), 1e-14)
    base = mesh(0.0)
    for eps in epsilons:
        assert same(mesh(eps), base), eps
    monkeypatch.setattr(vm, "_snap", lambda a: a)
    raw = mesh(0.0)
    assert not all(same(mesh(eps), raw) for eps in epsilons)
    vm._LAST_MESH.clear()


def test_refine_out_of_range():
    with pytest.raises(ValueError, match="refine"):
        valve(MPI.COMM_WORLD, size=4.0, free_edge_size=2.0, refine=5)
