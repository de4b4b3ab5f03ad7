"""Closed-state error (mvfem/distance.py) against closed forms, and the [reference] scene key.

Every expected number is derived here from geometry, not from the module: a patch against a
copy shifted along its normal (every distance is the shift), a copy also slid in its plane
(the Hausdorff distance is the hypotenuse), a sphere against a concentric sphere (bounds from
the facet planes of the two polyhedra), brute force over all triangles, and the deflection of
a solved disk against its flat reference.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import rotation, tilted_frame

from mvfem.distance import (
    point_triangle_distance,
    points_within,
    read_reference,
    surface_distance,
    surface_samples,
    weighted_percentile,
)


def grid(nx: int, ny: int, lx: float = 10.0, ly: float = 6.0):
    """A flat rectangle [0, lx] x [0, ly] in z = 0, triangulated with alternating diagonals."""
    xs, ys = np.linspace(0, lx, nx + 1), np.linspace(0, ly, ny + 1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    idx = np.arange(pts.shape[0]).reshape(nx + 1, ny + 1)
    tri = []
    for i in range(nx):
        for j in range(ny):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            tri += [[a, b, c], [a, c, d]] if (i + j) % 2 else [[a, b, d], [b, c, d]]
    return pts, np.array(tri)


def icosphere(radius: float, subdivisions: int):
    """Icosahedron subdivided ``subdivisions`` times, nodes pushed onto the sphere."""
    t = (1 + 5 ** 0.5) / 2
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
         [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    v = [np.array(p, float) / np.linalg.norm(p) for p in v]
    for _ in range(subdivisions):
        mid, nf = {}, []

        def m(a, b, mid=mid):
            key = (min(a, b), max(a, b))
            if key not in mid:
                p = v[a] + v[b]
                v.append(p / np.linalg.norm(p))
                mid[key] = len(v) - 1
            return mid[key]

        for a, b, c in f:
            ab, bc, ca = m(a, b), m(b, c), m(c, a)
            nf += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        f = nf
    return radius * np.array(v), np.array(f)


def inradius(x, tri):
    """Smallest distance from the origin to the plane of a facet (a convex polyhedron about
    the origin contains the ball of this radius)."""
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1)[:, None]
    return float(np.abs(np.einsum("ij,ij->i", n, a)).min())


def test_patch_against_copy_shifted_along_its_normal():
    """Every point of a flat patch is 0.7 mm from its copy moved 0.7 mm along the normal (the
    projection of every point falls inside the copy): all three numbers are 0.7, both ways,
    whatever the orientation of the patch."""
    x, tri = grid(12, 7)
    R = tilted_frame()
    n = R[:, 2]
    xp = x @ R.T + np.array([3.0, -2.0, 5.0])
    xr = xp + 0.7 * n
    res = surface_distance(xp, tri, xr, tri)
    for v in (res.mean_abs_error_mm, res.p95_error_mm, res.hausdorff_mm,
              res.max_to_prediction_mm, res.mean_to_prediction_mm):
        assert v == pytest.approx(0.7, abs=1e-12)
    assert np.allclose(res.facet_mm, 0.7, atol=1e-12)
    # a different triangulation of the reference changes nothing
    x2, tri2 = grid(5, 9)
    res2 = surface_distance(xp, tri, x2 @ R.T + np.array([3.0, -2.0, 5.0]) + 0.7 * n, tri2)
    assert res2.hausdorff_mm == pytest.approx(0.7, abs=1e-12)
    assert res2.mean_abs_error_mm == pytest.approx(0.7, abs=1e-12)


def test_patch_slid_in_its_plane_too():
    """The copy moved 0.7 along the normal and 0.3 along x: points of either patch beyond the
    other's edge by s <= 0.3 are sqrt(0.7^2 + s^2) away, so the Hausdorff distance is
    sqrt(0.58) both ways; the area-weighted mean over the prediction is exactly
    (0.7 (L - 0.3) + int_0^0.3 sqrt(0.49 + s^2) ds) / L with the strip's nodes and centroids
    sampled, so it lies between 0.7 and the Hausdorff value."""
    L = 10.0
    x, tri = grid(100, 6, lx=L)   # node spacing 0.1: the strip holds nodes at s = 0.1, 0.2, 0.3
    xr = x + np.array([0.3, 0.0, 0.7])
    res = surface_distance(x + 0.0, tri, xr, tri)
    h = np.hypot(0.7, 0.3)
    assert res.hausdorff_mm == pytest.approx(h, abs=1e-12)
    assert res.max_to_reference_mm == pytest.approx(h, abs=1e-12)
    assert res.max_to_prediction_mm == pytest.approx(h, abs=1e-12)
    exact = (0.7 * (L - 0.3) + 0.5 * (0.3 * h + 0.49 * np.arcsinh(0.3 / 0.7))) / L
    assert 0.7 < res.mean_abs_error_mm < h
    assert res.mean_abs_error_mm == pytest.approx(exact, abs=2e-4)


def test_sphere_against_concentric_sphere():
    """Predicted: a polyhedron inscribed in the sphere of radius 10; reference: a finer one in
    radius 11. Both are convex about the centre, so a point p of the prediction (inside the
    reference) is between rho_ref - |p| and 11 - |p| from the reference, with rho_ref the
    smallest distance from the centre to a reference facet plane; a reference node (|q| = 11,
    outside the prediction) is between 1 and 11 - rho_pred from the prediction. The error
    against the exact 1 mm is the facets' sagitta: second order in the edge length, which
    halves with each subdivision."""
    errors = []
    for subdivisions in (1, 2, 3):
        xp, tp = icosphere(10.0, subdivisions)
        xr, tr = icosphere(11.0, subdivisions + 2)
        rho_r, rho_p = inradius(xr, tr), inradius(xp, tp)
        pts, w, _ = surface_samples(xp, tp)
        d = point_triangle_distance(pts, xr, tr)
        r = np.linalg.norm(pts, axis=1)
        assert np.all(d >= rho_r - r - 1e-9) and np.all(d <= 11.0 - r + 1e-9)
        res = surface_distance(xp, tp, xr, tr)
        assert rho_r - 10.0 - 1e-9 <= res.max_to_reference_mm <= 11.0 - r.min() + 1e-9
        assert 1.0 - 1e-9 <= res.max_to_prediction_mm <= 11.0 - rho_p + 1e-9
        lo = float((w * (rho_r - r)).sum() / w.sum())
        hi = float((w * (11.0 - r)).sum() / w.sum())
        assert lo - 1e-9 <= res.mean_abs_error_mm <= hi + 1e-9
        errors.append([res.mean_abs_error_mm - 1.0, res.hausdorff_mm - 1.0])
    errors = np.array(errors)
    assert np.all(errors > 0)
    for j in range(2):
        rate = np.polyfit(np.log(0.5 ** np.arange(3)), np.log(errors[:, j]), 1)[0]
        assert 1.8 < rate < 2.2
    assert errors[-1, 0] < 0.02  # 1280 facets: mean error 1.02 mm for the exact 1


def test_candidates_match_brute_force():
    """The KD-tree with its radius bound finds the closest triangle: distances of scattered
    points (near and far) to a wavy sheet equal the minimum over all triangles."""
    rng = np.random.default_rng(3)
    x, tri = grid(20, 12)
    x[:, 2] = np.sin(x[:, 0]) * np.cos(0.7 * x[:, 1])
    p = np.column_stack([rng.uniform(-5, 15, 300), rng.uniform(-5, 11, 300),
                         rng.uniform(-6, 6, 300)])
    from mvfem.contact import closest_point_on_triangles

    brute = np.array([closest_point_on_triangles(np.repeat(q[None], len(tri), 0), x[tri[:, 0]],
                                                 x[tri[:, 1]], x[tri[:, 2]])[0].min() for q in p])
    for k in (1, 4, 8):
        assert np.allclose(point_triangle_distance(p, x, tri, k=k), brute, rtol=0, atol=1e-12)


def test_compiled_closest_points_match_numpy(monkeypatch):
    """The distance's pairs go through the compiled kernel where it loads (session 50): the
    same distances as numpy's closest points, row by row, for points whose closest point is a
    vertex, an edge or the face (and for slivers), and the numpy path where no kernel loads
    (``MVFEM_NO_KERNELS``)."""
    from mvfem import distance, kernels
    from mvfem.contact import closest_point_on_triangles

    assert kernels.load() is not None, "the kernels do not compile here"
    rng = np.random.default_rng(7)
    m = 3000
    a, b, c = (rng.normal(size=(m, 3)) for _ in range(3))
    c[:200] = a[:200] + 1e-7 * rng.normal(size=(200, 3))   # slivers
    p = rng.normal(scale=2.0, size=(m, 3))
    p[300:600] = (a + b + c)[300:600] / 3 + 0.1 * np.cross(b - a, c - a)[300:600]  # above faces
    expected = closest_point_on_triangles(p, a, b, c)[0]
    got = distance._closest(p, a, b, c)
    assert np.allclose(got, expected, rtol=1e-12, atol=1e-12)
    # rows, not a minimum over them: each point against its own triangle
    assert not np.allclose(got[1:], expected[:-1])
    monkeypatch.setattr(kernels, "load", lambda: None)
    assert np.array_equal(distance._closest(p, a, b, c), expected)


def test_points_within_match_brute_force():
    """Whether a point is within a distance of a wavy sheet, as the minimum over all triangles
    says: points scattered near and far, and points just above the nodes (far from every
    centroid: a reach without the triangles' radius misses them), at reaches from below the
    cells' size to above it."""
    rng = np.random.default_rng(5)
    x, tri = grid(20, 12)
    x[:, 2] = np.sin(x[:, 0]) * np.cos(0.7 * x[:, 1])
    p = np.vstack([np.column_stack([rng.uniform(-2, 12, 400), rng.uniform(-2, 8, 400),
                                    rng.uniform(-2, 2, 400)]),
                   x + [0.0, 0.0, 0.04]])
    from mvfem.contact import closest_point_on_triangles

    brute = np.array([closest_point_on_triangles(np.repeat(q[None], len(tri), 0), x[tri[:, 0]],
                                                 x[tri[:, 1]], x[tri[:, 2]])[0].min() for q in p])
    for within in (0.05, 0.3, 1.0, 3.0):
        got = points_within(p, x, tri, within)
        assert np.array_equal(got, brute <= within), within
        assert 0 < got.sum() < len(p)
    # small chunks give the same answer (the budget splits the points)
    assert np.array_equal(points_within(p, x, tri, 0.3, budget=100), brute <= 0.3)
    assert not points_within(np.zeros((0, 3)), x, tri, 1.0).size


def test_rotation_and_scale():
    """A rigid motion of both surfaces changes nothing; scaling both by s scales every number
    by s."""
    x, tri = grid(10, 8)
    x[:, 2] = 0.3 * np.sin(x[:, 0])
    y = x + np.array([0.2, -0.1, 0.5]) + 0.2 * np.cos(x[:, [1, 0, 2]])
    base = surface_distance(x, tri, y, tri)
    Q = rotation([1.0, 2.0, -0.5], 0.8)
    s = 2.5
    moved = surface_distance(s * x @ Q.T + 4.0, tri, s * y @ Q.T + 4.0, tri)
    for k in ("mean_abs_error_mm", "p95_error_mm", "hausdorff_mm", "mean_to_prediction_mm"):
        assert getattr(moved, k) == pytest.approx(s * getattr(base, k), rel=1e-10)


def test_leaflets_compared_with_their_namesakes():
    """Reference: leaflet 'anterior' in z = 0 and 'posterior' in z = 3 over the same square;
    prediction: an 'anterior' sheet at z = 2. Leaflet with leaflet it is 2 mm off; against
    the whole reference (no names) 1 mm (the posterior sheet is nearer)."""
    x, tri = grid(6, 6)
    xr = np.vstack([x, x + [0, 0, 3.0]])
    tr = np.vstack([tri, tri + len(x)])
    names = np.array(["anterior"] * len(tri) + ["posterior"] * len(tri), dtype=object)
    xp = x + [0, 0, 2.0]
    by = surface_distance(xp, tri, xr, tr, np.array(["anterior"] * len(tri), dtype=object), names)
    assert by.compared == "by leaflet"
    assert by.mean_abs_error_mm == pytest.approx(2.0, abs=1e-12)
    assert by.hausdorff_mm == pytest.approx(2.0, abs=1e-12)
    whole = surface_distance(xp, tri, xr, tr)
    assert whole.mean_abs_error_mm == pytest.approx(1.0, abs=1e-12)
    # the reference's posterior sheet has no namesake: it is measured to the whole prediction
    assert whole.max_to_prediction_mm == pytest.approx(2.0, abs=1e-12)


def test_weighted_percentile():
    v = np.arange(1, 101, dtype=float)
    assert weighted_percentile(v, np.ones(100), 95) == 95.0
    assert weighted_percentile(v, np.ones(100), 50) == 50.0
    w = np.ones(100)
    w[-1] = 1000.0  # the largest value carries most of the weight
    assert weighted_percentile(v, w, 50) == 100.0


def test_read_reference_quads_labels_and_errors(tmp_path):
    import meshio

    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
    quads = np.array([[0, 1, 2, 3], [1, 4, 5, 2]])
    path = tmp_path / "ref.vtu"
    meshio.write(path, meshio.Mesh(pts, [("quad", quads)],
                                   cell_data={"leaflet": [np.array([1, 2])]}))
    ref = read_reference(path)
    assert ref.tri.shape == (4, 3)
    assert list(ref.leaflet) == ["anterior", "anterior", "posterior", "posterior"]
    assert list(read_reference(path, {1: "a", 2: "p"}).leaflet) == ["a", "a", "p", "p"]
    with pytest.raises(ValueError, match="value 2"):
        read_reference(path, {1: "anterior"})
    (tmp_path / "junk.vtu").write_text("not a mesh")
    with pytest.raises(ValueError, match="cannot read"):
        read_reference(tmp_path / "junk.vtu")


# --------------------------------------------------------------------------- through a run
DISK = """title = "disk"
[mesh]
generator = "disk"
radius = 10.0
size = 2.5
[[region]]
law = "mny"
params = "MNY-mean"
[load]
pressure = "16 kPa"
"""


@pytest.fixture
def flat_disk(tmp_path):
    """The disk scene's own open (flat) mesh as a reference surface."""
    from mvfem.cli import main

    assert main(["mesh", "disk", "--radius", "10", "--size", "2.5",
                 "--out", str(tmp_path / "flat.vtu")]) == 0
    return tmp_path / "flat.vtu"


def test_run_with_reference_reports_the_deflection(tmp_path, flat_disk):
    """A clamped disk inflated by 16 kPa against its flat open mesh: every point of the dome is
    |z| from the plane (its projection falls on the flat disk except within a rounding of the
    rim), and every point of the plane is no further from the dome than the dome point above
    it. So the Hausdorff distance is the largest |z| over the nodes and centroids of the
    deformed mesh (read from fields.h5) and the mean absolute error is the quadrature of |z|
    (a sixth of each triangle's area at its nodes, half at its centroid)."""
    import h5py

    from mvfem.cli import main

    scene = tmp_path / "disk.toml"
    scene.write_text(DISK + '[reference]\nfile = "flat.vtu"\n')
    out = tmp_path / "run"
    assert main(["run", str(scene), "--out", str(out)]) == 0
    ref = json.loads((out / "summary.json").read_text())["reference"]
    with h5py.File(out / "fields.h5") as f:
        x = f["Mesh/mesh/geometry"][:] + f["Function/displacement/0"][:]
        tri = f["Mesh/mesh/topology"][:]
    z = np.abs(x[:, 2])
    zc = np.abs(x[tri].mean(axis=1)[:, 2])
    area = 0.5 * np.linalg.norm(np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]]),
                                axis=1)
    mae = float((area * (z[tri].sum(axis=1) / 6 + zc / 2)).sum() / area.sum())
    assert max(z.max(), zc.max()) > 8.0  # the dome is high: the check is not trivial
    assert ref["hausdorff_mm"] == pytest.approx(max(z.max(), zc.max()), rel=1e-9)
    assert ref["mean_abs_error_mm"] == pytest.approx(mae, rel=1e-3)
    assert ref["compared"] == "whole surface"
    assert 0 < ref["mean_abs_error_mm"] < ref["p95_error_mm"] <= ref["hausdorff_mm"]
    assert (out / "distance.vtu").is_file() and (out / "map_distance.png").stat().st_size > 20_000
    d = read_reference(out / "distance.vtu")
    assert len(d.tri) == len(tri)


@pytest.mark.parametrize("table,words", [
    ('[reference]\nfile = "missing.vtu"\n', ["reference.file", "no such file"]),
    ('[reference]\nfile = "junk.vtu"\n', ["reference.file", "cannot read"]),
    ('[reference]\nfile = "flat.vtu"\nlabels = { a = "x" }\n', ["reference.labels.a", "integers"]),
    ('[reference]\nlabels = { 1 = "anterior" }\n', ["reference.labels", "without reference.file"]),
    ('[reference]\nfile = "flat.vtu"\ncolour = 1\n', ["reference.colour", "unknown key"]),
])
def test_bad_reference_is_one_line_exit_2(tmp_path, flat_disk, capsys, table, words):
    from mvfem.cli import main

    (tmp_path / "junk.vtu").write_text("no mesh here")
    scene = tmp_path / "disk.toml"
    scene.write_text(DISK + table)
    out = tmp_path / "never"
    assert main(["run", str(scene), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    for w in words:
        assert w in err
    assert str(scene) in err
    assert not out.exists()


def test_nodal_average_of_facet_values():
    """``nodal_average`` (the level map's node colours): on a fan of four triangles around
    node 0 and a lone node, each node gets the mean of its facets' values, written out by
    hand; the lone node 0. A linear field's facet means averaged back to an interior node of
    a symmetric fan give the node's own value."""
    from mvfem.distance import nodal_average

    tri = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])
    facet = np.array([1.0, 2.0, 3.0, 6.0])
    got = nodal_average(tri, facet, 6)
    want = [3.0, (1 + 6) / 2, (1 + 2) / 2, (2 + 3) / 2, (3 + 6) / 2, 0.0]
    assert got == pytest.approx(want, abs=1e-15)
    x = np.array([[0, 0], [1, 0], [0, 1], [-1, 0], [0, -1]], dtype=float)
    f = 2.0 + 3.0 * x[:, 0] - 5.0 * x[:, 1]
    assert nodal_average(tri, f[tri].mean(axis=1), 5)[0] == pytest.approx(f[0], abs=1e-14)
