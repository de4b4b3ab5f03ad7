"""Import of damaged valve meshes (issue 7, "poor triangles"): what `meshes/imported.py`
refuses or warns about, on the generated 4 mm valve written in the import format and then
damaged by :func:`mvfem.hard.damage_file` (the same files as the hard cases).

- A node pushed across the edge opposite it folds its triangle over the neighbours: the
  surface passes through itself (edges cross triangles they share no node with): refused,
  naming the file and where.
- A posterior leaflet shifted through the anterior one: refused the same way; shifted until
  0.3 mm from it (nothing crossed, checked here by brute force over every edge and triangle):
  accepted.
- Nodes moved to 1 % of the opposite edge make slivers: kept, with a warning that names the
  smallest angle; the smallest angle computed here by hand.
- Coincident copies of nodes: merged, with a warning.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from mpi4py import MPI
from mvfem.meshes.imported import valve_from_file
from mvfem.meshes.io import read_surface

from mvfem.hard import base_valve_file, damage_file


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return base_valve_file(tmp_path_factory.mktemp("quality") / "base.vtu")


def _crossings(path) -> int:
    """Edges through triangles they share no node with, by brute force (every pair)."""
    r = read_surface(path)
    X, T = r.points, r.triangles
    E = np.unique(np.sort(np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1),
                  axis=0)
    a, b, c = X[T[:, 0]], X[T[:, 1]], X[T[:, 2]]
    n = np.cross(b - a, c - a)
    count = 0
    for e in E:
        p, q = X[e[0]], X[e[1]]
        dp, dq = np.einsum("ij,ij->i", p - a, n), np.einsum("ij,ij->i", q - a, n)
        ok = (dp * dq < 0) & ~np.isin(T, e).any(axis=1)
        t = np.where(ok, dp / np.where(ok, dp - dq, 1.0), 0.0)
        y = p + t[:, None] * (q - p)
        for u, v in ((a, b), (b, c), (c, a)):
            ok &= np.einsum("ij,ij->i", np.cross(v - u, y - u), n) > 0
        count += int(ok.sum())
    return count


def test_generated_valve_is_accepted_without_warnings(base, caplog):
    with caplog.at_level(logging.WARNING):
        v = valve_from_file(MPI.COMM_SELF, base)
    assert v.info["cells"] > 200 and not caplog.records
    assert _crossings(base) == 0


@pytest.mark.parametrize("kind", ["inverted", "crossing"])
def test_self_intersecting_surfaces_are_refused(base, tmp_path, kind):
    """Refused, with as many crossing edges as the brute-force count finds."""
    f = damage_file(kind, base, tmp_path / f"{kind}.vtu")
    expected = _crossings(f)
    assert expected > 0
    with pytest.raises(ValueError, match=rf"{f}: the leaflet surface passes through itself: "
                       rf"{expected} edge\(s\)"):
        valve_from_file(MPI.COMM_SELF, f)


def test_nearly_touching_leaflets_are_accepted(base, tmp_path):
    f = damage_file("nearly-touching", base, tmp_path / "near.vtu")
    assert _crossings(f) == 0
    r = read_surface(f)
    post = np.unique(r.triangles[r.cell_data["leaflet"] == 2])
    # the middle of the posterior leaflet (the commissures lie along y), off the annulus
    y = np.abs(r.points[post, 1])
    mid = post[(y < 0.7 * y.max()) & (r.point_data["annulus"][post] == 0)]
    ant_tri = r.triangles[(r.cell_data["leaflet"] == 1)
                          & ~np.isin(r.triangles, post).any(axis=1)]
    # distance to the anterior triangles sampled on a barycentric grid (brute force; it can
    # only overestimate the exact 0.3 mm, by at most about the grid spacing)
    g = np.linspace(0.0, 1.0, 61)
    uu, vv = np.meshgrid(g, g)
    u, v = uu[uu + vv <= 1], vv[uu + vv <= 1]
    X = r.points
    a, b, c = (X[ant_tri[:, k]] for k in range(3))
    pts = (a[:, None] + u[None, :, None] * (b - a)[:, None]
           + v[None, :, None] * (c - a)[:, None]).reshape(-1, 3)
    d = min(float(np.linalg.norm(pts - X[i], axis=1).min()) for i in mid)
    assert 0.29 < d < 0.4
    valve_from_file(MPI.COMM_SELF, f)


def test_slivers_are_kept_with_a_warning(base, tmp_path, caplog):
    f = damage_file("slivers", base, tmp_path / "slivers.vtu")
    r = read_surface(f)
    x = r.points[r.triangles]
    smallest = 180.0
    for k in range(3):
        a, b = x[:, (k + 1) % 3] - x[:, k], x[:, (k + 2) % 3] - x[:, k]
        cos = np.einsum("ij,ij->i", a, b) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
        smallest = min(smallest, np.degrees(np.arccos(cos)).min())
    with caplog.at_level(logging.WARNING):
        valve_from_file(MPI.COMM_SELF, f)
    text = " ".join(r.getMessage() for r in caplog.records)
    assert "sliver triangle(s)" in text and f"smallest {smallest:.2g} deg" in text


def test_duplicate_nodes_are_merged_with_a_warning(base, tmp_path, caplog):
    f = damage_file("duplicates", base, tmp_path / "dup.vtu")
    with caplog.at_level(logging.WARNING):
        v = valve_from_file(MPI.COMM_SELF, f)
    assert v.info["nodes_merged"] == 10
    assert "merged 10 coincident node(s)" in " ".join(r.getMessage() for r in caplog.records)
