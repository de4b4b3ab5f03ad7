"""The smooth split of a triangle mesh (``meshes.refine.smooth_midpoints``, ``mesh.refine_surface
= "smooth"``): new nodes on a smooth surface through the nodes, checked against surfaces whose
points are known in closed form (a circle, a sphere, a plane) and against the ruled surface
that a generated valve file samples."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from mvfem.meshes.refine import cell_edges, smooth_midpoints, vertex_normals


def _fan(n: int, flip_every: int = 0):
    """A disk cut in ``n`` triangles around its centre (the last node), on the unit circle;
    every ``flip_every``-th triangle oriented the other way (a file need not orient them)."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    points = np.vstack([np.column_stack([np.cos(t), np.sin(t), np.zeros(n)]), [0.0, 0.0, 0.0]])
    cells = np.array([[i, (i + 1) % n, n] for i in range(n)])
    if flip_every:
        cells[::flip_every] = cells[::flip_every, ::-1]
    return points, cells


def _sphere(n: int):
    """``n`` nodes spread over the unit sphere (a Fibonacci lattice: no two triangles alike),
    their convex hull's triangles, half of them turned over."""
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1.0 - 2.0 * i / n), np.pi * (1.0 + 5.0 ** 0.5) * i
    points = np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi),
                              np.cos(phi)])
    cells = ConvexHull(points).simplices.copy()
    cells[::2] = cells[::2, ::-1]
    return points, cells


def _new_nodes(points, cells, kind=None):
    edges, sides = cell_edges(cells)
    return edges, sides, smooth_midpoints(points, cells, edges, sides, kind)


@pytest.mark.parametrize("n", [12, 16, 32])
def test_a_boundary_circle_keeps_its_curvature(n):
    """The new node of a boundary chord of angle ``2 theta`` on the unit circle is the middle
    of the cubic Hermite curve with the circle's tangents at its ends: ``3 theta^4 / 8`` inside
    the circle (its Taylor series), where the midpoint is ``1 - cos(theta)`` inside; however
    the triangles are oriented (at 8 chords the turn, 45 deg, makes every node a corner).
    The interior edges (radii) stay straight: their nodes' normals are the plane's."""
    theta = np.pi / n
    for flip in (0, 3):
        points, cells = _fan(n, flip)
        edges, sides, new = _new_nodes(points, cells)
        boundary = np.bincount(sides.ravel(), minlength=len(edges)) == 1
        r = np.linalg.norm(new[boundary], axis=1)
        assert 1.0 - r == pytest.approx(np.full(n, 3.0 * theta ** 4 / 8.0), rel=0.08)
        assert np.all(1.0 - r < 0.12 * (1.0 - np.cos(theta)))
        mid = 0.5 * (points[edges[~boundary, 0]] + points[edges[~boundary, 1]])
        assert np.abs(new[~boundary] - mid).max() < 1e-12


def test_a_sphere_is_approached_at_the_fourth_power():
    """On an irregular triangulation of the unit sphere (inconsistently oriented), the new
    nodes lie within ``c h^4`` of the sphere: halving the spacing (4x the nodes) divides
    their largest distance by more than 10 (16 for ``h^4``), where the midpoints' falls 4x
    (``h^2``) and is 100x larger at 800 nodes. The node normals are the sphere's to 0.01 deg
    (Max's weights are exact on a sphere's own points; the lattice's triangles are not)."""
    err, mid_err = [], []
    for n in (200, 800):
        points, cells = _sphere(n)
        normals = vertex_normals(points, cells)
        cos = np.abs(np.einsum("ij,ij->i", normals, points))
        assert np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max() < 0.02
        edges, _, new = _new_nodes(points, cells)
        err.append(np.abs(np.linalg.norm(new, axis=1) - 1.0).max())
        mid = 0.5 * (points[edges[:, 0]] + points[edges[:, 1]])
        mid_err.append(np.abs(np.linalg.norm(mid, axis=1) - 1.0).max())
    assert err[0] / err[1] > 10.0
    assert 3.0 < mid_err[0] / mid_err[1] < 5.0
    assert err[1] < mid_err[1] / 100.0


def test_a_plane_with_corners_is_split_at_its_midpoints():
    """A flat square (its boundary straight, its corners turning 90 deg: corners, not a curve
    to round) is split at its edges' midpoints exactly, as the flat split does; so is a
    boundary where the edge ``kind`` changes (an annulus meeting a free edge)."""
    n = 6
    xs = np.linspace(0.0, 2.0, n)
    x, y = np.meshgrid(xs, xs)
    points = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)])
    cells = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            cells += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    cells = np.array(cells)
    edges, sides, new = _new_nodes(points, cells)
    assert np.abs(new - 0.5 * (points[edges[:, 0]] + points[edges[:, 1]])).max() < 1e-14
    # a circle's boundary cut in two kinds: the two nodes where they meet are corners, so the
    # chords that end there get only the other end's tangent
    points, cells = _fan(16)
    edges, sides = cell_edges(cells)
    boundary = np.bincount(sides.ravel(), minlength=len(edges)) == 1
    kind = (boundary & (edges.max(axis=1) <= 8) & (edges.max(axis=1) > 0)).astype(int)
    new = smooth_midpoints(points, cells, edges, sides, kind)
    plain = smooth_midpoints(points, cells, edges, sides)
    corner_chords = boundary & (np.isin(edges, [0, 8]).any(axis=1))
    assert corner_chords.sum() == 4
    assert np.abs(new[boundary & ~corner_chords] - plain[boundary & ~corner_chords]).max() \
        < 1e-14
    assert np.all(np.linalg.norm(new[corner_chords] - plain[corner_chords], axis=1) > 1e-4)
