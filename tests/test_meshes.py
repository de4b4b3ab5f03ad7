"""Mesh generators (gmsh) and surface IO (meshio): geometry, orientation, tags, round trips.

Areas and lengths of P1 meshes are those of inscribed polygons/polyhedra: a circle of radius R
cut into n chords of length ~h has perimeter 2 n R sin(pi/n) = 2 pi R (1 - pi^2/(6 n^2) + ...)
and the disk area (n/2) R^2 sin(2 pi/n) = pi R^2 (1 - 2 pi^2/(3 n^2) + ...), so both errors
fall as h^2 (n ~ 2 pi R / h). Order-2 geometry puts edge midpoints on the circle and is much
closer. Orientation: cross(dX/dxi1, dX/dxi2) from ufl.Jacobian, per cell, as the membrane forms
see it.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from mpi4py import MPI

from mvfem.meshes import (RawSurface, SurfaceMesh, disk, read_surface, sphere, square,
                          to_dolfinx, tube, write_surface)


# --- helpers ---------------------------------------------------------------------------------

def _area(msh) -> float:
    return msh.comm.allreduce(fem.assemble_scalar(fem.form(1.0 * ufl.dx(domain=msh))), op=MPI.SUM)


def _length(sm: SurfaceMesh, name: str) -> float:
    ds = ufl.Measure("ds", domain=sm.mesh, subdomain_data=sm.facet_tags)
    value = fem.assemble_scalar(fem.form(1.0 * ds(sm.names[name])))
    return sm.mesh.comm.allreduce(value, op=MPI.SUM)


def _alignment(msh, direction) -> np.ndarray:
    """cos of the angle between cross(J[:, 0], J[:, 1]) and ``direction`` (a UFL vector) at the
    centroid of each owned cell."""
    J = ufl.Jacobian(msh)
    n = ufl.cross(J[:, 0], J[:, 1])
    cos = ufl.dot(n, direction) / ufl.sqrt(ufl.dot(n, n) * ufl.dot(direction, direction))
    V0 = fem.FunctionSpace(msh, ("DG", 0))
    f = fem.Function(V0)
    f.interpolate(fem.Expression(cos, V0.element.interpolation_points()))
    return f.x.array[: msh.topology.index_map(2).size_local].copy()


def _min_alignment(msh, direction) -> float:
    return msh.comm.allreduce(_alignment(msh, direction).min(initial=np.inf), op=MPI.MIN)


def _count(sm: SurfaceMesh, dim: int, name: str) -> int:
    """Global number of owned entities in a named group."""
    tags = sm.cell_tags if dim == 2 else sm.facet_tags
    owned = sm.mesh.topology.index_map(dim).size_local
    idx = tags.indices[tags.values == sm.names[name]]
    return sm.mesh.comm.allreduce(int(np.sum(idx < owned)), op=MPI.SUM)


def _exterior_count(msh) -> int:
    msh.topology.create_connectivity(1, 2)
    ext = dmesh.exterior_facet_indices(msh.topology)
    return msh.comm.allreduce(int(np.sum(ext < msh.topology.index_map(1).size_local)), op=MPI.SUM)


def _euler_characteristic(msh) -> int:
    """V - E + F: 2 for a sphere, 0 for an open tube (duplicated seam nodes would change it)."""
    msh.topology.create_entities(1)
    V, E, F = (msh.topology.index_map(d).size_global for d in range(3))
    return V - E + F


def _facet_midpoints(sm: SurfaceMesh, name: str) -> np.ndarray:
    facets = sm.facets(name)
    return dmesh.compute_midpoints(sm.mesh, 1, facets).reshape(-1, 3)


# --- generators ------------------------------------------------------------------------------

@pytest.mark.mpi
def test_disk_area_and_perimeter_converge_as_h2(comm):
    R = 10.0
    sizes = np.array([2.0, 1.0, 0.5])
    err_a, err_l = [], []
    for h in sizes:
        sm = disk(comm, radius=R, size=h)
        err_a.append(abs(_area(sm.mesh) - np.pi * R**2) / (np.pi * R**2))
        err_l.append(abs(_length(sm, "boundary") - 2 * np.pi * R) / (2 * np.pi * R))
    rate_a = np.polyfit(np.log(sizes), np.log(err_a), 1)[0]
    rate_l = np.polyfit(np.log(sizes), np.log(err_l), 1)[0]
    assert 1.8 < rate_a < 2.2 and 1.8 < rate_l < 2.2, (err_a, err_l)
    assert err_a[-1] < 1e-3 and err_l[-1] < 3e-4


@pytest.mark.mpi
def test_disk_order2_is_nearly_exact(comm):
    R = 10.0
    sm = disk(comm, radius=R, size=1.0, order=2)
    assert sm.mesh.ufl_domain().ufl_coordinate_element().degree() == 2
    assert _area(sm.mesh) == pytest.approx(np.pi * R**2, rel=1e-6)
    assert _length(sm, "boundary") == pytest.approx(2 * np.pi * R, rel=1e-6)
    assert _min_alignment(sm.mesh, ufl.as_vector([0.0, 0.0, 1.0])) > 0.999


@pytest.mark.mpi
def test_disk_normals_tags_and_placement(comm):
    R, c = 4.0, (1.0, -2.0, 3.0)
    sm = disk(comm, radius=R, size=0.5, centre=c)
    msh = sm.mesh
    assert msh.topology.dim == 2 and msh.geometry.dim == 3
    # every cell counter-clockwise seen from +z
    assert _min_alignment(msh, ufl.as_vector([0.0, 0.0, 1.0])) > 1 - 1e-12
    # the same from the geometry arrays, independently of UFL
    x, dofs = msh.geometry.x, msh.geometry.dofmap.array.reshape(-1, 3)
    dofs = dofs[: msh.topology.index_map(2).size_local]
    nz = np.cross(x[dofs[:, 1]] - x[dofs[:, 0]], x[dofs[:, 2]] - x[dofs[:, 0]])[:, 2]
    assert comm.allreduce(int(np.sum(nz <= 0)), op=MPI.SUM) == 0
    assert np.allclose(x[:, 2], c[2])
    # tags: all cells "membrane", the boundary edges exactly the exterior facets, on the circle
    assert set(sm.names) == {"membrane", "boundary"}
    assert _count(sm, 2, "membrane") == msh.topology.index_map(2).size_global
    nb = _count(sm, 1, "boundary")
    assert nb == _exterior_count(msh) and nb >= 2 * np.pi * R / 0.5
    mid = _facet_midpoints(sm, "boundary")
    r = np.linalg.norm(mid[:, :2] - np.array(c[:2]), axis=1)
    assert np.all((r > R * np.cos(np.pi / nb) - 1e-9) & (r < R + 1e-9))
    assert sm.info == {"generator": "disk", "radius": R, "size": 0.5, "centre": list(c),
                       "order": 1}


@pytest.mark.mpi
def test_square_sides(comm):
    side = 10.0
    sm = square(comm, side=side, size=1.0, sides=True)
    assert set(sm.names) == {"membrane", "left", "right", "bottom", "top"}
    assert _area(sm.mesh) == pytest.approx(side**2, rel=1e-12)
    assert _min_alignment(sm.mesh, ufl.as_vector([0.0, 0.0, 1.0])) > 1 - 1e-12
    counts = {}
    for name, axis, value in [("left", 0, 0.0), ("right", 0, side), ("bottom", 1, 0.0),
                              ("top", 1, side)]:
        assert _length(sm, name) == pytest.approx(side, rel=1e-12)
        assert np.allclose(_facet_midpoints(sm, name)[:, axis], value)
        counts[name] = _count(sm, 1, name)
    assert len(set(counts.values())) == 1 and sum(counts.values()) == _exterior_count(sm.mesh)


@pytest.mark.mpi
def test_square_centred_one_boundary(comm):
    sm = square(comm, side=4.0, size=0.5, centred=True)
    x = sm.mesh.geometry.x
    lo = comm.allreduce(x[:, :2].min(initial=np.inf), op=MPI.MIN)
    hi = comm.allreduce(x[:, :2].max(initial=-np.inf), op=MPI.MAX)
    assert lo == pytest.approx(-2.0) and hi == pytest.approx(2.0)
    assert _length(sm, "boundary") == pytest.approx(16.0)
    assert _count(sm, 1, "boundary") == _exterior_count(sm.mesh)


@pytest.mark.mpi
def test_sphere_area_and_outward_normals(comm):
    R, c = 10.0, np.array([0.5, 0.0, -1.0])
    sm = sphere(comm, radius=R, size=1.0, centre=tuple(c))
    msh = sm.mesh
    x = ufl.SpatialCoordinate(msh)
    assert _min_alignment(msh, x - ufl.as_vector(c)) > 0.99
    # inscribed polyhedron: relative area deficit ~ h^2 / (c R^2), a few 1e-3 at h = R/10
    assert _area(msh) == pytest.approx(4 * np.pi * R**2, rel=5e-3)
    assert _area(msh) < 4 * np.pi * R**2
    assert _exterior_count(msh) == 0 and _count(sm, 2, "membrane") == \
        msh.topology.index_map(2).size_global
    assert set(sm.names) == {"membrane"}
    assert _euler_characteristic(msh) == 2
    assert comm.allreduce(len(sm.facet_tags.indices), op=MPI.SUM) == 0


@pytest.mark.mpi
def test_sphere_order2(comm):
    R = 10.0
    sm = sphere(comm, radius=R, size=2.0, order=2)
    assert _area(sm.mesh) == pytest.approx(4 * np.pi * R**2, rel=1e-4)
    x = ufl.SpatialCoordinate(sm.mesh)
    assert _min_alignment(sm.mesh, x) > 0.9


@pytest.mark.mpi
def test_tube_area_ends_and_outward_normals(comm):
    R, L = 5.0, 20.0
    sm = tube(comm, radius=R, length=L, size=0.5)
    msh = sm.mesh
    assert set(sm.names) == {"membrane", "bottom", "top"}
    assert _area(msh) == pytest.approx(2 * np.pi * R * L, rel=2e-3)
    for name, z in [("bottom", 0.0), ("top", L)]:
        assert _length(sm, name) == pytest.approx(2 * np.pi * R, rel=2e-3)
        assert np.allclose(_facet_midpoints(sm, name)[:, 2], z)
    nb, nt = _count(sm, 1, "bottom"), _count(sm, 1, "top")
    assert nb == nt and nb + nt == _exterior_count(msh)
    assert _euler_characteristic(msh) == 0
    x = ufl.SpatialCoordinate(msh)
    assert _min_alignment(msh, ufl.as_vector([x[0], x[1], 0.0])) > 0.99


@pytest.mark.mpi
def test_tube_order2(comm):
    """gmsh orients the extruded surface inward: every 6-node cell is flipped, midpoints too."""
    R, L = 5.0, 10.0
    sm = tube(comm, radius=R, length=L, size=1.0, order=2)
    assert _area(sm.mesh) == pytest.approx(2 * np.pi * R * L, rel=1e-6)
    assert _length(sm, "top") == pytest.approx(2 * np.pi * R, rel=1e-5)
    x = ufl.SpatialCoordinate(sm.mesh)
    assert _min_alignment(sm.mesh, ufl.as_vector([x[0], x[1], 0.0])) > 0.99


@pytest.mark.mpi
def test_info_is_json_and_written(comm, shared_tmp):
    sm = tube(comm, radius=2.0, length=3.0, size=1.0, base=(0.0, 0.0, 1.0))
    assert json.loads(json.dumps(sm.info))["generator"] == "tube"
    path = shared_tmp / "tube.json"
    sm.write_info(path)
    comm.Barrier()
    data = json.loads(path.read_text())
    assert data["names"] == {"membrane": 1, "bottom": 2, "top": 3}
    assert data["info"]["base"] == [0.0, 0.0, 1.0]
    assert np.allclose(_facet_midpoints(sm, "top")[:, 2], 4.0)


def test_gmsh_session_left_as_found():
    """gmsh is finalised when the generator started it, and left running (same current model and
    options) when the caller had it initialised."""
    import gmsh

    from mvfem.meshes.generators import _gmsh_initialized

    comm = MPI.COMM_SELF  # each rank runs its own gmsh here
    square(comm, side=1.0, size=0.5)
    assert not _gmsh_initialized(gmsh)
    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("mine")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 3.0)
        sm = square(comm, side=1.0, size=0.25)
        assert sm.mesh.topology.index_map(2).size_global >= 16
        assert _gmsh_initialized(gmsh)
        assert gmsh.model.getCurrent() == "mine"
        assert gmsh.option.getNumber("Mesh.MeshSizeMax") == 3.0
    finally:
        gmsh.finalize()


def test_bad_parameters():
    with pytest.raises(ValueError, match="size"):
        disk(MPI.COMM_SELF, size=0.0)
    with pytest.raises(ValueError, match="order"):
        disk(MPI.COMM_SELF, order=3)


# --- io --------------------------------------------------------------------------------------

def _quad_file(path):
    """A 2 x 1 strip: one quad, two triangles, one line, one unused point; data on all."""
    import meshio

    points = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0],
                       [5, 5, 5]], dtype=float)
    cells = [("quad", np.array([[0, 1, 4, 3]])), ("triangle", np.array([[1, 2, 5], [1, 5, 4]])),
             ("line", np.array([[0, 1]]))]
    point_data = {"temperature": points[:, 0] + 10 * points[:, 1]}
    cell_data = {"label": [np.array([7]), np.array([8, 9]), np.array([5])]}
    meshio.write(path, meshio.Mesh(points, cells, point_data=point_data, cell_data=cell_data))


@pytest.mark.mpi
def test_io_round_trip_quads_split_data_carried(comm, shared_tmp):
    src, out = shared_tmp / "strip.vtu", shared_tmp / "strip_tri.vtu"
    if comm.rank == 0:
        _quad_file(src)
        raw = read_surface(src)
        assert raw.triangles.tolist() == [[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]]
        assert raw.cell_data["label"].tolist() == [7, 7, 8, 9]
        assert raw.lines.tolist() == [[0, 1]] and raw.line_data["label"].tolist() == [5]
        assert np.allclose(raw.point_data["temperature"], raw.points[:, 0] + 10 * raw.points[:, 1])
        write_surface(out, raw.points, raw.triangles, point_data=raw.point_data,
                      cell_data={"label": raw.cell_data["label"]})
        back = read_surface(out)
        assert np.array_equal(back.points, raw.points)
        assert np.array_equal(back.triangles, raw.triangles)
        assert np.array_equal(back.cell_data["label"], raw.cell_data["label"])
        assert np.allclose(back.point_data["temperature"], raw.point_data["temperature"])
        assert len(back.lines) == 0
    else:
        back = None
    comm.Barrier()

    # distributed mesh with the cell labels; point data mapped through input_global_indices
    msh, tags = to_dolfinx(comm, back, back.cell_data["label"] if comm.rank == 0 else None)
    assert msh.topology.index_map(2).size_global == 4
    assert _area(msh) == pytest.approx(2.0)
    owned = msh.topology.index_map(2).size_local
    for value, n in [(7, 2), (8, 1), (9, 1)]:
        local = int(np.sum(tags.indices[tags.values == value] < owned))
        assert comm.allreduce(local, op=MPI.SUM) == n
    mid = dmesh.compute_midpoints(msh, 2, tags.indices)
    assert np.all(mid[tags.values == 7][:, 0] < 1) and np.all(mid[tags.values != 7][:, 0] > 1)
    temperature = comm.bcast(back.point_data["temperature"] if comm.rank == 0 else None, root=0)
    x = msh.geometry.x
    assert np.allclose(temperature[msh.geometry.input_global_indices], x[:, 0] + 10 * x[:, 1])
    assert _min_alignment(msh, ufl.as_vector([0.0, 0.0, 1.0])) > 1 - 1e-12

    msh2, none = to_dolfinx(comm, back, None)
    assert none is None and msh2.topology.index_map(2).size_global == 4


def test_read_surface_errors(comm, shared_tmp):
    import meshio

    d = shared_tmp / f"rank{comm.rank}"
    d.mkdir()
    with pytest.raises(ValueError, match="not found.*nothing.vtu"):
        read_surface(d / "nothing.vtu")
    (d / "garbage.vtu").write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match="cannot read.*garbage.vtu"):
        read_surface(d / "garbage.vtu")
    (d / "points.unknownext").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="cannot read.*points.unknownext"):
        read_surface(d / "points.unknownext")
    meshio.write(d / "lines.vtu", meshio.Mesh(np.eye(3), [("line", np.array([[0, 1], [1, 2]]))]))
    with pytest.raises(ValueError, match="lines.vtu.*no triangle or quad cells"):
        read_surface(d / "lines.vtu")


def test_raw_surface_defaults():
    raw = RawSurface(np.zeros((3, 3)), np.array([[0, 1, 2]]))
    assert raw.lines.shape == (0, 2) and raw.point_data == {} and raw.cell_data == {}


@pytest.mark.mpi
def test_rank0_errors_raise_on_every_rank(comm):
    """Bad input seen on rank 0 only raises everywhere instead of leaving other ranks waiting."""
    from mvfem.meshes import mesh_from_arrays

    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=float)
    expected = ValueError if comm.rank == 0 else RuntimeError
    with pytest.raises(expected, match="2 cell values for 1 cells"):
        mesh_from_arrays(comm, points, np.array([[0, 1, 2]]), cell_values=np.array([1, 2]))
    with pytest.raises(expected, match="index the 3 points"):
        mesh_from_arrays(comm, points, np.array([[0, 1, 3]]))
    with pytest.raises(TypeError if comm.rank == 0 else RuntimeError, match="RawSurface"):
        to_dolfinx(comm, None)
