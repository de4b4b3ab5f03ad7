"""Imported valves (meshes/imported.py): a valve file becomes a full valve (tags, frame,
orientation, chordae) like a generated one; bad files are one-line input errors.

Independent references:
- round trip: the generated valve (``meshes.valve``) written with its chordae and read back
  must have the generator's own numbers: leaflet areas (its info), annulus vertices and tag
  counts (its facet tags), insertion points, families and tips, and the chord lengths of its
  design (tip to the insertion in the designed closed valve); and a scene on the written file
  must give the model a scene ``generator = "valve"`` gives (dofs, clamp, fibres, chordae);
- a funnel made of rings of nodes, ``r`` from 6 to 12 mm, ``z = -(12 - r)/2``, 24 sectors of
  planar isosceles trapezoids: each has the area ``(a + b)/2 h`` with the chords
  ``a, b = 2 r sin(pi/24)`` and the slant height ``h = sqrt((dr cos(pi/24))^2 + dz^2)``;
- a chordal tree with hand-placed nodes: root P = (0, 0, -20), branch B1 = (0, 0, -8)
  (|P B1| = 12), B2 = B1 + (-3, 4, 0) (|B1 B2| = 5); insertions at funnel nodes
  I1 = (6, 0, -3) (|B1 I1| = sqrt 61), I2 = (9, 0, -1.5) (|B1 I2| = sqrt 123.25) and
  I3 = (-6, 0, -3) (|B2 I3| = sqrt 50); a second tip Q straight below the funnel node I4 at
  r = 9, 255 degrees, z = -1.5, with Q at z = -20 (|Q I4| = 18.5).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import meshio
import numpy as np
import pytest
import ufl
from dolfinx import cpp, fem
from mpi4py import MPI

from mvfem.cli import main
from mvfem.meshes import read_surface, valve
from mvfem.meshes.imported import (ImportedValve, chord_lengths, valve_from_file,
                                   write_valve_with_chordae)
from mvfem.meshes.io import _cpp_mesh

SECTORS = 24
RADII = np.array([6.0, 7.5, 9.0, 10.5, 12.0])


# --- a funnel valve with a hand-made chordal tree --------------------------------------------

def _z(r):
    return -0.5 * (12.0 - r)


def _funnel(quads: bool = True) -> dict:
    """Arrays of the funnel: points (ring-major), quads or triangles, leaflet 1 where the
    sector's middle has x > 0 (anterior), 2 elsewhere, annulus on the outer ring."""
    th = 2 * np.pi * np.arange(SECTORS) / SECTORS
    pts = np.array([[r * np.cos(t), r * np.sin(t), _z(r)] for r in RADII for t in th])
    idx = lambda i, j: i * SECTORS + j % SECTORS  # noqa: E731
    q = np.array([[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)]
                  for i in range(len(RADII) - 1) for j in range(SECTORS)])
    mid = np.cos(2 * np.pi * (np.arange(SECTORS) + 0.5) / SECTORS)
    leaflet = np.tile(np.where(mid > 0, 1, 2), len(RADII) - 1).astype(np.int32)
    if not quads:
        q = np.stack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]], axis=1).reshape(-1, 3)
        leaflet = np.repeat(leaflet, 2)
    annulus = np.zeros(len(pts), dtype=np.int32)
    annulus[idx(len(RADII) - 1, 0):] = 1
    return {"points": pts, "cells": q, "leaflet": leaflet, "annulus": annulus}


def _node(r, deg):
    i = int(np.flatnonzero(RADII == r)[0])
    return i * SECTORS + int(round(deg / 360 * SECTORS)) % SECTORS


I1, I2, I3, I4 = _node(6.0, 0), _node(9.0, 0), _node(6.0, 180), _node(9.0, 255)
_I4 = np.array([9 * np.cos(np.radians(255)), 9 * np.sin(np.radians(255)), -1.5])
P, B1, B2, Q = (0.0, 0.0, -20.0), (0.0, 0.0, -8.0), (-3.0, 4.0, -8.0), tuple(_I4 - [0, 0, 18.5])


def _with_tree(f: dict) -> dict:
    """Add the tree P -> B1 -> {I1, I2, B2 -> I3} and the chord Q -> I4 (module docstring);
    the segment B2 -> I3 says family 1 (strut), the others nothing (-1)."""
    n = len(f["points"])
    f = dict(f)
    f["points"] = np.vstack([f["points"], [P, B1, B2, Q]])
    p, b1, b2, q = n, n + 1, n + 2, n + 3
    f["lines"] = np.array([[p, b1], [b1, I1], [b1, I2], [b1, b2], [b2, I3], [q, I4]])
    f["family"] = np.array([-1, -1, -1, -1, 1, -1], dtype=np.int32)
    f["papillary"] = np.zeros(n + 4, dtype=np.int32)
    f["papillary"][[p, q]] = 1
    f["annulus"] = np.concatenate([f["annulus"], np.zeros(4, dtype=np.int32)])
    return f


def _write(path, f: dict) -> Path:
    """Write the arrays of :func:`_funnel` / :func:`_with_tree` with meshio (keys left out
    are not written)."""
    kind = "quad" if f["cells"].shape[1] == 4 else "triangle"
    cells = [(kind, f["cells"])]
    lines = f.get("lines")
    has_lines = lines is not None and len(lines)
    if has_lines:
        cells.append(("line", lines))
    cell_data = {}
    if "leaflet" in f:
        cell_data["leaflet"] = [f["leaflet"]] + ([np.zeros(len(lines), np.int32)]
                                                 if has_lines else [])
    for key in ("family", "rest_length"):
        if key in f and has_lines:
            given = f[key] if len(f[key]) == len(lines) else np.full(len(lines), -1)  # lines
            cell_data[key] = [np.full(len(f["cells"]), -1, dtype=given.dtype), given]  # changed
    point_data = {k: f[k] for k in ("annulus", "papillary") if k in f}
    meshio.write(str(path), meshio.Mesh(f["points"], cells, point_data=point_data,
                                        cell_data=cell_data))
    return Path(path)


def _trapezoid_areas() -> np.ndarray:
    """Area of one sector's trapezoid in each of the four rows (module docstring)."""
    s, c = np.sin(np.pi / SECTORS), np.cos(np.pi / SECTORS)
    r0, r1 = RADII[:-1], RADII[1:]
    h = np.sqrt(((r1 - r0) * c) ** 2 + (_z(r1) - _z(r0)) ** 2)
    return (r0 + r1) * s * h


def _sum(comm, x):
    return comm.allreduce(x, op=MPI.SUM)


def _area(v, name=None) -> float:
    dx = ufl.Measure("dx", domain=v.mesh, subdomain_data=v.cell_tags)
    return _sum(v.mesh.comm, fem.assemble_scalar(fem.form(1.0 * (dx if name is None
                                                                 else dx(v.names[name])))))


def _owned_count(v, dim: int, name: str) -> int:
    idx = v.facets(name) if dim == 1 else v.cells(name)
    return _sum(v.mesh.comm, int(np.sum(idx < v.mesh.topology.index_map(dim).size_local)))


def _annulus_vertices(v) -> np.ndarray:
    """Coordinates of the vertices of the annulus edges (all ranks), sorted, unique."""
    msh = v.mesh
    f = v.facets("annulus")
    g = cpp.mesh.entities_to_geometry(_cpp_mesh(msh), 1, f, False).ravel()
    x = np.concatenate(msh.comm.allgather(msh.geometry.x[g]))
    return np.unique(np.round(x, 9), axis=0)


def _cell_normals(v) -> tuple[np.ndarray, np.ndarray]:
    """(unit normal cross(dX/dxi1, dX/dxi2) of each owned cell, its vertex coordinates)."""
    msh = v.mesh
    n = msh.topology.index_map(2).size_local
    x = msh.geometry.x[msh.geometry.dofmap.array.reshape(-1, 3)[:n]]
    nrm = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    return nrm / np.linalg.norm(nrm, axis=1)[:, None], x


# --- the generated valve through a file ------------------------------------------------------

@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    comm = MPI.COMM_WORLD
    v = valve(comm, size=2.0)
    path = comm.bcast(str(tmp_path_factory.mktemp("import") / "valve.vtu"), root=0)
    write_valve_with_chordae(path, v)
    comm.Barrier()
    return v, path


@pytest.mark.mpi
def test_generated_valve_round_trip(generated):
    """Areas, annulus, tags, frame and chordae of the generated valve survive the file."""
    v, path = generated
    w = valve_from_file(MPI.COMM_WORLD, path)
    assert isinstance(w, ImportedValve)
    assert w.names == v.names
    for name in ("anterior", "posterior"):
        assert _area(w, name) == pytest.approx(v.info["leaflet_area_mm2"][name], rel=1e-9)
        assert _owned_count(w, 2, name) == _owned_count(v, 2, name)
    for name in ("annulus", "free_edge_anterior", "free_edge_posterior"):
        assert _owned_count(w, 1, name) == _owned_count(v, 1, name) > 10
    # the annulus loop: the same vertices, in one loop, counter-clockwise about the axis
    ring = _annulus_vertices(v)
    assert np.array_equal(np.unique(np.round(w.annulus_curve, 9), axis=0), ring)
    assert len(w.annulus_curve) == len(ring) == _owned_count(v, 1, "annulus")
    ang = np.unwrap(np.arctan2(w.annulus_curve[:, 1], w.annulus_curve[:, 0]))
    assert np.all(np.diff(ang) > 0) and ang[-1] - ang[0] == pytest.approx(2 * np.pi, abs=0.3)
    assert abs(ang[0]) < np.pi / 8  # starts at the anterior midpoint, like the generator's
    # frame and landmarks: the generator's (its annulus plane is z, anterior +x)
    assert w.axis @ v.axis > 1 - 1e-8
    assert w.frame[0] @ v.frame[0] > 1 - 1e-8
    assert np.allclose(w.commissures, v.commissures, atol=1e-9)
    assert np.linalg.norm(w.centre - v.centre) < 0.05
    assert np.allclose(w.papillary_tips, v.papillary_tips, atol=1e-12)
    assert np.array_equal(w.papillary_muscle, v.papillary_muscle)
    # chordae: the same chords, lengths the model gives the generated valve
    assert len(w.insertion_points) == len(v.insertion_points) > 20
    assert np.allclose(w.insertion_points, v.insertion_points, atol=1e-12)
    for key in ("insertion_family", "insertion_leaflet", "insertion_tip", "insertion_muscle"):
        assert np.array_equal(getattr(w, key), getattr(v, key)), key
    anchor = v.papillary_tips[v.insertion_tip]
    open_ = np.linalg.norm(v.insertion_points - anchor, axis=1)
    designed = np.linalg.norm(v.insertion_closed - anchor, axis=1)
    assert np.allclose(w.insertion_path_length, designed, rtol=1e-12)
    assert np.allclose(w.insertion_tree_length, open_, rtol=1e-12)  # straight: distance
    assert np.abs(designed - open_).max() > 0.05 * open_.max()  # the test tells them apart
    # the imported valve written again and read back: the same chords
    assert np.allclose(chord_lengths(w), designed, rtol=1e-12)


@pytest.fixture(scope="module")
def cli_file(tmp_path_factory):
    """The demo's valve (size 2) written by `mvfem mesh valve` (serial)."""
    out = tmp_path_factory.mktemp("cli") / "valve.vtu"
    assert main(["mesh", "valve", "--size", "2", "--out", str(out)]) == 0
    return out


_REGIONS = [{"label": "anterior", "law": "mny", "params": "MNY-mean"},
            {"label": "posterior", "law": "mny", "params": "MNY-mean", "leaflet": "posterior"}]


def test_model_of_the_imported_valve_is_the_generated_one(cli_file):
    """The scene `generator = "file"` on the written valve and the scene `generator = "valve"`
    give the same problem: annulus clamp by default, the same dofs, clamped dofs, Laplace
    coordinate (fibres), chordae (nodes, anchors, rest lengths, stiffness) and contact."""
    from mvfem.model import build_model
    from mvfem.scene import load_scene

    gen = build_model(load_scene({"mesh": {"generator": "valve", "size": 2.0},
                                  "region": _REGIONS}), MPI.COMM_SELF)
    scene = load_scene({"mesh": {"generator": "file", "file": str(cli_file),
                                 "labels": {"1": "anterior", "2": "posterior"}},
                        "region": _REGIONS})
    assert scene["boundary"]["clamp"] == "annulus"
    imp = build_model(scene, MPI.COMM_SELF)
    assert isinstance(imp.surface, ImportedValve)
    assert imp.V.dofmap.index_map.size_global == gen.V.dofmap.index_map.size_global
    assert imp.info["area_mm2"] == pytest.approx(gen.info["area_mm2"], rel=1e-12)
    assert [len(b.dof_indices()[0]) for b in imp.bcs] == [len(b.dof_indices()[0])
                                                          for b in gen.bcs]
    assert np.allclose(np.sort(imp.phi.x.array), np.sort(gen.phi.x.array), atol=1e-9)
    a, b = imp.chordae, gen.chordae
    assert len(a) == len(b) > 20
    assert np.allclose(imp.view.X[a.node], gen.view.X[b.node], atol=1e-12)
    for key in ("anchor", "rest_length", "stiffness"):
        assert np.allclose(getattr(a, key), getattr(b, key), rtol=1e-12), key
    assert np.array_equal(a.family, b.family) and np.array_equal(a.leaflet, b.leaflet)
    assert imp.contact is not None and gen.contact is not None
    assert imp.contact.thickness == gen.contact.thickness


# --- the funnel: trees, quads, orientation, duplicates ---------------------------------------

def test_chordal_tree_reduced_to_tethers_with_path_lengths(tmp_path):
    f = _with_tree(_funnel())
    f["rest_length"] = np.array([-1, -1, -1, 7.0, -1, -1])  # B1 -> B2 unstretched 7, not 5
    w = valve_from_file(MPI.COMM_SELF, _write(tmp_path / "tree.vtu", f),
                        {1: "anterior", 2: "posterior"})
    x = f["points"]
    assert np.allclose(w.insertion_points, x[[I1, I2, I3, I4]], atol=1e-12)  # segment order
    s61, s12325, s50 = np.sqrt([61.0, 123.25, 50.0])
    assert np.allclose(w.insertion_tree_length, [12 + s61, 12 + s12325, 12 + 5 + s50, 18.5],
                       rtol=1e-12)
    assert np.allclose(w.insertion_path_length, [12 + s61, 12 + s12325, 12 + 7 + s50, 18.5],
                       rtol=1e-12)
    assert list(w.insertion_family) == ["marginal", "basal", "strut", "basal"]
    assert list(w.insertion_leaflet) == [1, 1, 2, 2]
    assert np.allclose(w.papillary_tips, [P, Q])
    assert list(w.insertion_tip) == [0, 0, 0, 1]
    assert list(w.papillary_muscle) == [0, 1]  # P on the +y (commissural) side of Q
    assert list(w.insertion_muscle) == [0, 0, 0, 1]
    assert w.info["chordae_trees"] == 2 and w.info["chordae_branch_points"] == 2
    # frame of the funnel: axis +z (tips below), anterior +x, commissures at +-y on the annulus
    assert np.allclose(w.axis, [0, 0, 1], atol=1e-12)
    assert np.allclose(w.frame, np.eye(3), atol=1e-12)
    assert np.allclose(w.commissures, [[0, 12, 0], [0, -12, 0]], atol=1e-12)
    assert np.allclose(w.centre, [0, 0, 0], atol=1e-12)
    assert len(w.annulus_curve) == SECTORS and np.allclose(w.annulus_curve[0], [12, 0, 0])
    assert list(w.insertions(leaflet="posterior")) == [2, 3]


def test_quads_split_and_areas(tmp_path):
    """24 x 4 planar trapezoids, each split in two: the trapezoids' closed-form area."""
    w = valve_from_file(MPI.COMM_SELF, _write(tmp_path / "quads.vtu", _funnel(quads=True)))
    assert w.mesh.topology.index_map(2).size_global == 2 * SECTORS * (len(RADII) - 1)
    ring = _trapezoid_areas()
    assert _area(w) == pytest.approx(SECTORS * ring.sum(), rel=1e-12)
    assert _area(w, "anterior") == pytest.approx(SECTORS / 2 * ring.sum(), rel=1e-12)
    assert _owned_count(w, 1, "annulus") == SECTORS
    assert _owned_count(w, 1, "free_edge_anterior") == _owned_count(w, 1, "free_edge_posterior") \
        == SECTORS // 2
    assert w.info["leaflet_area_mm2"]["posterior"] == pytest.approx(SECTORS / 2 * ring.sum(),
                                                                    rel=1e-12)


def test_flipped_triangles_are_oriented_atrially(generated, tmp_path):
    """The generated valve with a third of its triangles and then all of them flipped: read
    back, every normal faces the atrium again (the generator's own criterion: n . axis > 0.15
    in every cell) and exactly the flipped ones were turned."""
    v, path = generated
    raw = read_surface(path)
    tri = raw.triangles.copy()
    rng = np.random.default_rng(5)
    flip = rng.random(len(tri)) < 1 / 3
    tri[flip] = tri[flip][:, [0, 2, 1]]
    m = meshio.read(path)
    for name, some in (("some", tri), ("all", tri[:, [0, 2, 1]])):
        cells = [("triangle", some), ("line", m.cells_dict["line"])]
        out = tmp_path / f"{name}.vtu"
        meshio.write(out, meshio.Mesh(m.points, cells, point_data=m.point_data,
                                      cell_data=m.cell_data))
        w = valve_from_file(MPI.COMM_SELF, out)
        n, _ = _cell_normals(w)
        assert (n @ w.axis).min() > 0.15
        assert w.info["cells_flipped"] == (flip.sum() if name == "some" else (~flip).sum())


def test_orientation_without_papillary_tips(tmp_path, caplog):
    """No tips: the ventricle is where the funnel hangs (z < 0), with a warning; triangles
    given clockwise from +z are turned."""
    f = _funnel(quads=False)
    f["cells"] = f["cells"][:, [0, 2, 1]]
    with caplog.at_level(logging.WARNING, logger="mvfem.meshes.imported"):
        w = valve_from_file(MPI.COMM_SELF, _write(tmp_path / "down.vtu", f))
    assert "no 'papillary' tips" in caplog.text
    assert np.allclose(w.axis, [0, 0, 1], atol=1e-12)
    n, _ = _cell_normals(w)
    assert n[:, 2].min() > 0.8 and w.info["cells_flipped"] == len(f["cells"])


def test_coincident_nodes_are_merged(tmp_path, caplog):
    """The posterior leaflet saved with its own copy of the nodes it shares with the anterior:
    read back, the same nodes and edges as the shared mesh."""
    f = _funnel(quads=False)
    post = f["cells"][f["leaflet"] == 2]
    shared = np.intersect1d(post, f["cells"][f["leaflet"] == 1])
    n = len(f["points"])
    copy_of = {int(k): n + i for i, k in enumerate(shared)}
    f["cells"][f["leaflet"] == 2] = np.vectorize(lambda k: copy_of.get(int(k), k))(post)
    f["points"] = np.vstack([f["points"], f["points"][shared] * (1 + 1e-13)])
    f["annulus"] = np.concatenate([f["annulus"], f["annulus"][shared]])
    with caplog.at_level(logging.WARNING, logger="mvfem.meshes.imported"):
        w = valve_from_file(MPI.COMM_SELF, _write(tmp_path / "dup.vtu", f))
    assert f"merged {len(shared)} coincident" in caplog.text
    assert w.info["nodes_merged"] == len(shared) == 2 * len(RADII)  # the two seams
    assert w.info["vertices"] == n
    assert _owned_count(w, 1, "annulus") == SECTORS  # the seams are interior again


# --- bad input -------------------------------------------------------------------------------

def _bad_nonmanifold(f):
    f = _tri(f)
    n = len(f["points"])
    f["points"] = np.vstack([f["points"], [[9.0, 0.0, 5.0]]])
    e = f["cells"][0]  # a third triangle on the interior radial edge of its first two nodes
    f["cells"] = np.vstack([f["cells"], [[e[0], e[1], n]]])
    f["leaflet"] = np.append(f["leaflet"], 1).astype(np.int32)
    for key in ("annulus", "papillary"):
        if key in f:
            f[key] = np.append(f[key], 0).astype(np.int32)
    return f


def _tri(f):
    g = _funnel(quads=False)
    g.update({k: v for k, v in f.items() if k not in ("cells", "leaflet")})
    return g


def _bad_degenerate(f):
    f = _tri(f)
    n = len(f["points"])
    f["points"] = np.vstack([f["points"], [[20.0, 0, 0], [21.0, 0, 0], [22.0, 0, 0]]])
    f["cells"] = np.vstack([f["cells"], [[n, n + 1, n + 2]]])
    f["leaflet"] = np.append(f["leaflet"], 1).astype(np.int32)
    for key in ("annulus", "papillary"):
        if key in f:
            f[key] = np.append(f[key], [0, 0, 0]).astype(np.int32)
    return f


def _set(key, fn):
    def change(f):
        f[key] = fn(f)
        return f
    return change


def _drop(key):
    def change(f):
        f.pop(key)
        return f
    return change


def _flag_nodes(nodes):
    def change(f):
        f["annulus"] = np.zeros_like(f["annulus"])
        f["annulus"][nodes(f)] = 1
        return f
    return change


_OUTER = (len(RADII) - 1) * SECTORS
BAD = {
    "no leaflet data": (_drop("leaflet"), ["no 'leaflet' cell data"]),
    "leaflet not in labels": (_set("leaflet", lambda f: np.where(
        np.arange(len(f["leaflet"])) == 3, 3, f["leaflet"]).astype(np.int32)),
        ["'leaflet' value 3", "mesh.labels"]),
    "no annulus data": (_drop("annulus"), ["no 'annulus' point data"]),
    "non-manifold edge": (_bad_nonmanifold, ["non-manifold edge", "more than two"]),
    "degenerate triangle": (_bad_degenerate, ["degenerate (zero-area)", "(21, 0, 0)"]),
    "duplicate triangle": (lambda f: {**f, "cells": np.vstack([f["cells"], f["cells"][5:6]]),
                                      "leaflet": np.append(f["leaflet"], f["leaflet"][5])},
                           ["duplicate triangle", "same three nodes"]),
    "non-finite": (_set("points", lambda f: np.where(np.arange(len(f["points"]))[:, None] == 7,
                                                     np.nan, f["points"])),
                   ["non-finite coordinates", "node 7"]),
    "two annulus nodes": (_flag_nodes(lambda f: [_OUTER, _OUTER + 1]), ["only 2", "at least 3"]),
    "open annulus": (_flag_nodes(lambda f: np.arange(_OUTER, _OUTER + SECTORS // 2)),
                     ["not form one closed loop", "ends at"]),
    "two annulus loops": (_flag_nodes(lambda f: np.r_[np.arange(SECTORS),
                                                      np.arange(_OUTER, _OUTER + SECTORS)]),
                          ["several separate loops"]),
    "annulus node inside": (_flag_nodes(lambda f: np.r_[np.arange(_OUTER, _OUTER + SECTORS),
                                                        [2 * SECTORS]]),
                            ["not on an annulus edge"]),
    "tree without root": (_set("papillary", lambda f: np.zeros_like(f["papillary"])),
                          ["no root", "'papillary'"]),
    "lines without papillary data": (_drop("papillary"), ["no 'papillary' point data"]),
    "two roots": (_set("lines", lambda f: np.vstack([f["lines"], [[I1, len(f["points"]) - 1]]])),
                  ["connect 2 papillary roots"]),
    "cycle": (_set("lines", lambda f: np.vstack([f["lines"], [[I3, len(f["points"]) - 3]]])),
              ["cycle"]),
    "chord ends in space": (_set("lines", lambda f: f["lines"][[0, 1, 2, 3, 5]]),
                            ["ends in space", "(-3, 4, -8)"]),
    "bad family": (_set("family", lambda f: np.array([-1, -1, 5, -1, 1, -1], dtype=np.int32)),
                   ["'family'", "got 5"]),
    "tip on a leaflet": (_set("papillary", lambda f: np.where(np.arange(len(f["papillary"])) == I2,
                                                              1, f["papillary"])),
                         ["is a leaflet node"]),
}
def _bad_file(tmp_path, case) -> Path:
    change, _ = BAD[case]
    return _write(tmp_path / "bad.vtu", change(_with_tree(_funnel())))


@pytest.mark.parametrize("case", list(BAD))
def test_bad_valve_files_are_value_errors(tmp_path, case):
    path = _bad_file(tmp_path, case)
    with pytest.raises(ValueError) as err:
        valve_from_file(MPI.COMM_SELF, path, {1: "anterior", 2: "posterior"})
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(path)), msg
    for word in BAD[case][1]:
        assert word in msg, msg


def test_non_orientable_surface_is_refused(tmp_path):
    """A Moebius strip (its one boundary loop flagged as the annulus) has no consistent
    orientation: refused with where it twists."""
    n, R = 24, 10.0
    pts = []
    for k in range(n):
        t = 2 * np.pi * k / n
        radial = np.array([np.cos(t), np.sin(t), 0.0])
        across = np.cos(t / 2) * radial + np.sin(t / 2) * np.array([0.0, 0.0, 1.0])
        pts += [R * radial + w * across for w in (-1.0, 0.0, 1.0)]
    node = lambda k, w: 3 * (k % n) + (w if k < n else 2 - w)  # noqa: E731 - half twist
    quads = np.array([[node(k, w), node(k + 1, w), node(k + 1, w + 1), node(k, w + 1)]
                      for k in range(n) for w in (0, 1)])
    annulus = np.array([w != 1 for _ in range(n) for w in range(3)], dtype=np.int32)
    path = _write(tmp_path / "moebius.vtu", {"points": np.array(pts), "cells": quads,
                                             "leaflet": np.ones(len(quads), dtype=np.int32),
                                             "annulus": annulus})
    with pytest.raises(ValueError, match="moebius.vtu: the leaflet surface is not orientable"):
        valve_from_file(MPI.COMM_SELF, path)


@pytest.mark.parametrize("split", ["", "smooth"])
@pytest.mark.parametrize("case", [c for c in BAD if c != "no annulus data"])
def test_bad_valve_files_through_mvfem_run(tmp_path, capsys, case, split):
    """One line on stderr naming the scene, the key and the file; exit code 2; no results.
    (A file without 'annulus' is a plain membrane, not an error.) The same line where the
    scene splits the file smoothly (``mesh.refine = 1``, ``refine_surface = "smooth"``): the
    file is checked before it is split, so its problems are named in its own nodes and
    places."""
    path = _bad_file(tmp_path, case)
    scene = tmp_path / "imported.toml"
    refine = 'refine = 1\nrefine_surface = "smooth"\n' if split else ""
    scene.write_text(f'[mesh]\ngenerator = "file"\nfile = "{path.name}"\n{refine}'
                     'labels = {1 = "anterior", 2 = "posterior"}\n'
                     '[[region]]\nlabel = "anterior"\nlaw = "mny"\nparams = "MNY-mean"\n'
                     '[[region]]\nlabel = "posterior"\nlaw = "mny"\nparams = "MNY-mean"\n')
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "imported.toml: mesh.file: " in lines[0] and "bad.vtu" in lines[0]
    for word in BAD[case][1]:
        assert word in lines[0]
    assert "refine_surface" not in lines[0]
    assert not (out / "summary.json").exists()


def _plain_square(tmp_path, case: str):
    """A 4 x 4 grid of 8 mm squares split in two (a membrane file without an annulus), the
    left half 'leaflet' 1, the right half 2, with one ``case`` of damage."""
    n = 5
    xs = np.linspace(-16.0, 16.0, n)
    X, Y = np.meshgrid(xs, xs)
    pts = np.c_[X.ravel(), Y.ravel(), np.zeros(n * n)]
    tri = np.array([t for i in range(n - 1) for j in range(n - 1)
                    for t in ([i * n + j, i * n + j + 1, i * n + j + n + 1],
                              [i * n + j, i * n + j + n + 1, i * n + j + n])])
    leaflet = np.where(pts[tri].mean(axis=1)[:, 0] < 0, 1, 2)
    data = {"leaflet": [leaflet]}
    if case == "nan node":
        pts[7, 2] = np.nan
    elif case == "scaled by 1e200":
        pts *= 1e200
    elif case == "zero-area triangle":
        pts = np.vstack([pts, [[40.0, 0, 0], [41.0, 0, 0], [42.0, 0, 0]]])
        tri = np.vstack([tri, [[n * n, n * n + 1, n * n + 2]]])
        data = {"leaflet": [np.r_[leaflet, 1]]}
    elif case == "duplicate triangle":
        tri = np.vstack([tri, tri[:1]])
        data = {"leaflet": [np.r_[leaflet, 1]]}
    elif case == "fractional leaflet":
        data = {"leaflet": [leaflet + 0.5]}
    elif case in ("no leaflet data", "a label without cells"):
        data = {} if case == "no leaflet data" else {"leaflet": [np.ones_like(leaflet)]}
    elif case == "a value without a label":
        data = {"leaflet": [np.where(leaflet == 2, 3, 1)]}
    path = tmp_path / "plain.vtu"
    meshio.write(path, meshio.Mesh(pts, [("triangle", tri)], cell_data=data))
    return path


PLAIN_BAD = {
    "nan node": ["mesh.file", "plain.vtu", "non-finite coordinates"],
    "scaled by 1e200": ["mesh.file", "plain.vtu", "farther than 1e+06 mm", "in mm"],
    "zero-area triangle": ["mesh.file", "plain.vtu", "degenerate (zero-area)"],
    "duplicate triangle": ["mesh.file", "plain.vtu", "duplicate triangle"],
    "fractional leaflet": ["mesh.file", "plain.vtu", "must be integers"],
    "no leaflet data": ["mesh.labels", "plain.vtu", "no 'leaflet' cell data"],
    "a label without cells": ["region[1].label", "'right'", "not a label"],
    "a value without a label": ["mesh.file", "plain.vtu", "'leaflet' value 3 (16 cells) is "
                                "not in mesh.labels"],
}


@pytest.mark.parametrize("case", ["none", *PLAIN_BAD])
def test_bad_membrane_files_through_mvfem_run(tmp_path, capsys, case):
    """A membrane file without an annulus gets the valve files' checks that need no annulus:
    non-finite nodes, zero-area and duplicate triangles, 'leaflet' data that are not
    integers, and labels that name no cells are one line naming the scene, the key and the
    file, exit code 2, no results. Until session 62 a zero-area triangle ran to exit code 0
    with NaN areas and percentiles, a NaN node ended in a PETSc traceback, and a region whose
    label named no cells in an AttributeError (or exit code 3). The undamaged file closes."""
    path = _plain_square(tmp_path, case)
    scene = tmp_path / "plain.toml"
    scene.write_text(f'[mesh]\ngenerator = "file"\nfile = "{path.name}"\n'
                     'labels = {1 = "left", 2 = "right"}\n'
                     '[[region]]\nlabel = "left"\nlaw = "mny"\nparams = "MNY-mean"\n'
                     '[[region]]\nlabel = "right"\nlaw = "mny"\nparams = "MNY-mean"\n'
                     '[load]\npressure = "1 kPa"\n')
    out = tmp_path / "out"
    code = main(["run", str(scene), "--out", str(out)])
    err = capsys.readouterr().err
    if case == "none":
        assert code == 0, err
        summary = json.loads((out / "summary.json").read_text())
        assert summary["regions"]["left"]["area_mm2"] == pytest.approx(512.0)
        return
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert "plain.toml: " in lines[0]
    for word in PLAIN_BAD[case]:
        assert word in lines[0], lines[0]
    assert not (out / "summary.json").exists()


@pytest.mark.parametrize("regions, words", [
    ('[[region]]\nlabel = "anterior"\nlaw = "mny"\nparams = "MNY-mean"\n',
     ["region: the mesh's 581 cells labelled 'posterior' are in no [[region]]"]),
    ('[[region]]\nlabel = "annulus"\nlaw = "mny"\nparams = "MNY-mean"\n',
     ["region[0].label: 'annulus' is not a label of the mesh's cells",
      "labels: anterior, posterior"]),
])
def test_every_labelled_cell_is_in_a_region(tmp_path, capsys, regions, words):
    """The example valve file (576 anterior and 581 posterior cells) with one region for its
    anterior leaflet: the posterior cells would have no material, which is an input error
    naming them (until session 62 it ran, reporting the whole valve's area as 'anterior');
    a region may not take an edge tag's name (the annulus) either."""
    example = Path(__file__).parents[1] / "scripts" / "scenes" / "valve_imported.vtu"
    scene = tmp_path / "one.toml"
    scene.write_text(f'[mesh]\ngenerator = "file"\nfile = "{example}"\n'
                     'labels = {1 = "anterior", 2 = "posterior"}\n' + regions)
    assert main(["run", str(scene), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err) and err[-1].startswith("mvfem: error: ")
    for w in words:
        assert w in err[-1], err[-1]
    assert not (tmp_path / "out" / "summary.json").exists()


# --- writing, MPI, the example scene ---------------------------------------------------------

@pytest.mark.mpi
def test_import_on_all_ranks(shared_tmp):
    """The funnel with its tree on every rank: global counts and areas as in one process;
    the chordae arrays the same on every rank."""
    comm = MPI.COMM_WORLD
    path = shared_tmp / "tree.vtu"
    if comm.rank == 0:
        _write(path, _with_tree(_funnel(quads=False)))
    comm.Barrier()
    w = valve_from_file(comm, path)
    assert w.mesh.topology.index_map(2).size_global == 2 * SECTORS * (len(RADII) - 1)
    assert _area(w) == pytest.approx(SECTORS * _trapezoid_areas().sum(), rel=1e-12)
    assert _owned_count(w, 1, "annulus") == SECTORS
    lengths = comm.allgather(w.insertion_path_length)
    assert all(np.array_equal(lengths[0], x) for x in lengths)
    assert np.allclose(w.insertion_path_length[0], 12 + np.sqrt(61.0), rtol=1e-12)
    with pytest.raises(ValueError, match="no root"):  # the same error on every rank
        bad = shared_tmp / "bad.vtu"
        if comm.rank == 0:
            _bad_file(shared_tmp, "tree without root")
        comm.Barrier()
        valve_from_file(comm, bad)


@pytest.mark.mpi
def test_smooth_split_of_a_file_on_all_ranks(shared_tmp):
    """A scene that splits a valve file smoothly builds its mesh on every rank (the file's
    check before the split is collective): 4x the file's cells in all, and every rank's nodes
    are nodes of the split made in one process (1e-12); a bad file is the same error on
    every rank."""
    from scipy.spatial import cKDTree

    import mvfem
    from mvfem.errors import InputError
    from mvfem.meshes.imported import refine_surface
    from mvfem.model import build_mesh

    comm = MPI.COMM_WORLD
    path = shared_tmp / "valve5.vtu"
    if comm.rank == 0:
        write_valve_with_chordae(str(path), valve(MPI.COMM_SELF, size=5.0, free_edge_size=2.5))
    comm.Barrier()
    scene = {"mesh": {"generator": "file", "file": str(path), "refine": 1,
                      "refine_surface": "smooth"},
             "region": [{"label": "anterior", "law": "mny", "params": "MNY-mean"},
                        {"label": "posterior", "law": "mny", "params": "MNY-mean",
                         "leaflet": "posterior"}]}
    msh = build_mesh(mvfem.load_scene(scene), comm).mesh
    cells = msh.topology.index_map(2).size_global
    raw = read_surface(path)
    serial = refine_surface(raw, 1, smooth=True).points
    far = cKDTree(serial).query(msh.geometry.x)[0].max()
    bad = shared_tmp / "bad.vtu"
    if comm.rank == 0:
        _bad_file(shared_tmp, "tree without root")
    comm.Barrier()
    with pytest.raises(InputError, match="no root"):
        build_mesh(mvfem.load_scene({**scene, "mesh": {**scene["mesh"], "file": str(bad)}}),
                   comm)
    assert cells == 4 * len(raw.triangles)
    assert far < 1e-12


def test_mesh_command_writes_the_chordae(cli_file, tmp_path, capsys):
    """`mvfem mesh valve` writes the chordae (one line from a tip per chord, the three
    families, rest lengths) and reads back with them; a format that cannot keep line cells is
    refused."""
    raw = read_surface(cli_file)
    tips = np.flatnonzero(raw.point_data["papillary"])
    assert len(tips) == 2 and len(raw.lines) > 20
    assert np.all(np.isin(raw.lines[:, 0], tips)) and not np.any(np.isin(raw.lines[:, 1], tips))
    seg = np.linalg.norm(raw.points[raw.lines[:, 1]] - raw.points[raw.lines[:, 0]], axis=1)
    assert np.all(raw.line_data["rest_length"] > 0.5 * seg) and np.all(seg > 1.0)
    assert set(raw.line_data["family"]) == {0, 1, 2}
    w = valve_from_file(MPI.COMM_SELF, cli_file)
    assert len(w.insertion_points) == len(raw.lines)
    assert np.allclose(w.insertion_path_length, raw.line_data["rest_length"], rtol=1e-12)
    capsys.readouterr()
    assert main(["mesh", "valve", "--out", str(tmp_path / "valve.stl")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "valve.stl" in err[0] and ".vtu" in err[0]
    assert not (tmp_path / "valve.stl").exists()


def test_mesh_command_writes_a_scenes_mesh(tmp_path, capsys):
    """``mvfem mesh SCENE.toml [--set ...]`` writes the mesh the scene runs on: the demo's
    valve at 5 mm refined once is the generator's own valve with the demo's geometry
    (``anterior_height`` 23 mm; a scene's free edge is meshed at half its size) refined
    once, node for node, and reads back with every
    chord; a plain membrane scene writes its surface in any format. Options of a generated
    kind with a scene, ``--set`` without one and a kind that is neither are one line and
    exit code 2, nothing written."""
    from scipy.spatial import cKDTree

    import mvfem

    demo = Path(mvfem.__file__).parent / "data" / "demo.toml"
    out = tmp_path / "demo5r1.vtu"
    assert main(["mesh", str(demo), "--set", "mesh.size=5", "--set", "mesh.refine=1",
                 "--out", str(out)]) == 0
    raw = read_surface(out)
    own = valve(MPI.COMM_SELF, size=5.0, free_edge_size=2.5, refine=1, anterior_height=23.0)
    x = own.mesh.geometry.x
    assert len(raw.triangles) == own.info["cells"] == 4 * own.info["unrefined"]["cells"]
    assert cKDTree(raw.points[np.unique(raw.triangles)]).query(x)[0].max() < 1e-9
    back = valve_from_file(MPI.COMM_SELF, out)
    assert len(back.insertion_points) == len(own.insertion_points) > 10
    disk = tmp_path / "disk.toml"
    disk.write_text('[mesh]\ngenerator = "disk"\nradius = 5.0\nsize = 2.0\n'
                    '[[region]]\nlaw = "svk"\nparams = "SVK"\n')
    assert main(["mesh", str(disk), "--out", str(tmp_path / "disk.stl")]) == 0
    assert len(read_surface(tmp_path / "disk.stl").triangles) > 20
    capsys.readouterr()
    for argv, words in ((["mesh", str(demo), "--size", "3"], ["--size applies", "--set mesh."]),
                        (["mesh", "disk", "--set", "mesh.size=1"], ["--set applies"]),
                        (["mesh", "blob"], ["'blob'", "scene file"])):
        bad = tmp_path / "bad.vtu"
        assert main(argv + ["--out", str(bad)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and all(w in err[0] for w in words), err
        assert not bad.exists()


def test_example_scene_is_an_imported_valve():
    from mvfem.model import build_mesh
    from mvfem.scene import load_scene

    path = Path(__file__).resolve().parents[1] / "scripts" / "scenes" / "valve_imported.toml"
    scene = load_scene(path)
    assert scene["mesh"]["generator"] == "file" and scene["boundary"]["clamp"] == "annulus"
    v = build_mesh(scene, MPI.COMM_SELF)
    assert isinstance(v, ImportedValve) and len(v.insertion_points) > 20
    assert set(v.insertion_family) == {"marginal", "strut", "basal"}


@pytest.mark.slow
def test_example_imported_valve_closes(tmp_path):
    """scripts/scenes/valve_imported.toml (the demo valve, size 2, through its file) closes
    to equilibrium, as the demo does (about 40 s)."""
    import mvfem

    path = Path(__file__).resolve().parents[1] / "scripts" / "scenes" / "valve_imported.toml"
    result = mvfem.solve(path, out=tmp_path / "out", progress=False)
    assert result.converged
    v = result.summary["valve"]
    assert v["chordae_force_N"]["count"] > 20 and v["chordae_force_N"]["taut"] > 0


# --- mesh.refine of a valve file (session 47) -------------------------------------------------

def _angle_range(raw) -> tuple[float, float]:
    """Smallest and largest corner angle (rad) of the triangles of a raw surface."""
    x = raw.points[raw.triangles]
    out = []
    for i in range(3):
        u, w = x[:, (i + 1) % 3] - x[:, i], x[:, (i + 2) % 3] - x[:, i]
        c = np.einsum("ij,ij->i", u, w) / np.linalg.norm(u, axis=1) / np.linalg.norm(w, axis=1)
        out.append(np.arccos(np.clip(c, -1.0, 1.0)))
    ang = np.concatenate(out)
    return float(ang.min()), float(ang.max())


def test_refined_import_splits_the_files_facets(tmp_path):
    """``refine_surface``: each triangle of the file split 1-to-4 at its edges' midpoints, so
    each child is similar to its parent (the same smallest and largest angle). A flat split
    keeps each leaflet's area (the four children tile their parent, so to
    roundoff) and the annulus's perimeter (the new annulus nodes are its chords' midpoints),
    with 4x the triangles and 2x the annulus nodes (every annulus edge halves; an interior
    edge between two annulus nodes would not be one); the file's nodes keep their indices
    and places, so the chordae, their insertions and the tips are the file's."""
    from mvfem.meshes.imported import refine_surface, valve_from_surface

    comm = MPI.COMM_SELF
    path = str(tmp_path / "valve4.vtu")
    write_valve_with_chordae(path, valve(comm, size=4.0, free_edge_size=2.0))
    raw = read_surface(path)
    fine_raw = refine_surface(raw, 2)
    assert np.array_equal(fine_raw.points[:len(raw.points)], raw.points)
    assert np.array_equal(fine_raw.lines, raw.lines)
    # split at the midpoints, every child is similar to its parent: the same angles
    for a, b in zip(_angle_range(raw), _angle_range(fine_raw)):
        assert b == pytest.approx(a, abs=1e-9)
    coarse, fine = valve_from_surface(comm, raw), valve_from_surface(comm, fine_raw)
    c, f = coarse.info, fine.info
    assert f["cells"] == 16 * c["cells"]
    assert f["annulus_nodes"] == 4 * c["annulus_nodes"]
    assert f["annulus_perimeter_mm"] == pytest.approx(c["annulus_perimeter_mm"], rel=1e-12)
    for name in ("anterior", "posterior"):
        assert f["leaflet_area_mm2"][name] == pytest.approx(c["leaflet_area_mm2"][name],
                                                            rel=1e-12)
        assert _area(fine, name) == pytest.approx(_area(coarse, name), rel=1e-12)
    assert f["chordae"] == c["chordae"] > 10
    assert np.array_equal(fine.insertion_points, coarse.insertion_points)
    assert np.array_equal(fine.papillary_tips, coarse.papillary_tips)
    assert np.allclose(fine.commissures, coarse.commissures, atol=1e-9)


def test_refined_import_closes_level_by_level(tmp_path):
    """A valve file with ``mesh.refine = 1`` closes as nested levels: the file first, then its
    split from that closure (the coarse nodes are the fine mesh's first nodes: nothing to
    interpolate across cells). ``mesh.refine`` of a file that is not a valve (no 'annulus'
    point data) is an input error naming the key."""
    import mvfem
    from mvfem.errors import InputError

    path = str(tmp_path / "valve5.vtu")
    write_valve_with_chordae(path, valve(MPI.COMM_SELF, size=5.0, free_edge_size=2.5))
    scene = {"mesh": {"generator": "file", "file": path, "refine": 1},
             "region": [{"label": "anterior", "law": "mny", "params": "MNY-mean"},
                        {"label": "posterior", "law": "mny", "params": "MNY-mean",
                         "leaflet": "posterior"}],
             "load": {"pressure": "16 kPa"}}
    r = mvfem.solve(scene, progress=False)
    s = r.summary
    assert s["converged"], s["stop_reason"]
    cs = s["coarse_start"]
    assert cs["nested"] and cs["used"] and cs["refine"] == 0
    assert s["cells"] == 4 * cs["cells"]
    disk = str(tmp_path / "disk.vtu")
    assert main(["mesh", "disk", "--radius", "5", "--size", "2", "--out", disk]) == 0
    with pytest.raises(InputError, match="mesh.refine: refines valves only"):
        mvfem.solve({"mesh": {"generator": "file", "file": disk, "refine": 1},
                     "region": [{"law": "svk", "params": "SVK"}]}, progress=False)


def test_smooth_split_of_a_valve_file_lies_on_the_valves_surface(tmp_path):
    """``mesh.refine_surface = "smooth"``: a generated valve's file (4 mm) split once puts its
    new nodes within 0.033 mm of the generator's own ruled surface, which the file samples
    (``meshes.valve.surface_distance``, the generator's inversion; the file's own nodes
    are up to 0.012 mm off it), 0.005 mm on average, where the midpoints of the flat split
    are 0.039 mm off on average and up to 0.24 mm. The file's nodes and the annulus's new
    nodes are the flat split's. The scene key reaches the model's mesh, and asked of a
    generated valve it is an input error naming the key."""
    from scipy.spatial import cKDTree

    import mvfem
    from mvfem.errors import InputError
    from mvfem.meshes.imported import refine_surface
    from mvfem.meshes.valve import surface_distance
    from mvfem.model import build_mesh

    path = str(tmp_path / "valve4.vtu")
    write_valve_with_chordae(path, valve(MPI.COMM_SELF, size=4.0, free_edge_size=2.0))
    raw = read_surface(path)

    def off_surface(x):
        return surface_distance(x, size=4.0, free_edge_size=2.0)

    assert off_surface(raw.points[np.unique(raw.triangles)]).max() < 0.015
    flat, smooth = refine_surface(raw, 1), refine_surface(raw, 1, smooth=True)
    n = len(raw.points)
    assert np.array_equal(smooth.points[:n], raw.points)
    assert np.array_equal(smooth.triangles, flat.triangles)
    assert np.array_equal(smooth.point_data["annulus"], flat.point_data["annulus"])
    d_flat, d_smooth = off_surface(flat.points[n:]), off_surface(smooth.points[n:])
    assert d_flat.mean() > 0.03 and d_flat.max() > 0.2
    assert d_smooth.max() < 0.04 and d_smooth.mean() < d_flat.mean() / 5.0

    scene = {"mesh": {"generator": "file", "file": path, "refine": 1,
                      "refine_surface": "smooth"},
             "region": [{"label": "anterior", "law": "mny", "params": "MNY-mean"},
                        {"label": "posterior", "law": "mny", "params": "MNY-mean",
                         "leaflet": "posterior"}],
             "load": {"pressure": "16 kPa"}}
    x = build_mesh(mvfem.load_scene(scene), MPI.COMM_SELF).mesh.geometry.x
    assert cKDTree(smooth.points).query(x)[0].max() < 1e-9
    assert cKDTree(flat.points).query(x)[0].max() > 0.1
    with pytest.raises(InputError, match="mesh.refine_surface: places a valve file"):
        mvfem.load_scene({"mesh": {"generator": "valve", "size": 4.0, "refine": 1,
                                   "refine_surface": "smooth"},
                          "region": [{"law": "svk", "params": "SVK"}]})


def test_a_smooth_split_that_crosses_is_refused_naming_the_split(tmp_path, monkeypatch, capsys):
    """A file that is valid as given but whose smooth split passes through itself (here the
    new nodes turned half round the valve's axis) is one line naming the problem and the
    split, exit code 2; the same scene split on its facets builds its mesh."""
    import mvfem.meshes.refine as refine_mod
    from mvfem.model import build_mesh

    import mvfem

    real = refine_mod.smooth_midpoints

    def folded(points, cells, edges, sides, kind=None):
        new = real(points, cells, edges, sides, kind)
        new[:, :2] *= -1.0  # turned half round the axis: the children span the valve
        return new

    path = tmp_path / "valve5.vtu"
    write_valve_with_chordae(str(path), valve(MPI.COMM_SELF, size=5.0, free_edge_size=2.5))
    scene = tmp_path / "split.toml"
    scene.write_text(f'[mesh]\ngenerator = "file"\nfile = "{path.name}"\nrefine = 1\n'
                     'refine_surface = "smooth"\n'
                     '[[region]]\nlabel = "anterior"\nlaw = "mny"\nparams = "MNY-mean"\n'
                     '[[region]]\nlabel = "posterior"\nlaw = "mny"\nparams = "MNY-mean"\n')
    monkeypatch.setattr(refine_mod, "smooth_midpoints", folded)
    capsys.readouterr()  # (the generator's log of the file's valve)
    assert main(["run", str(scene), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "passes through itself" in err[0], err
    assert 'mesh.refine_surface = "smooth"' in err[0]
    facets = mvfem.load_scene(scene).with_changes({"mesh.refine_surface": "facets"})
    assert build_mesh(facets, MPI.COMM_SELF).mesh.topology.index_map(2).size_local > 0
