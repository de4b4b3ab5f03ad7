"""How much the contact energy of one node varies as it slides over a flat triangulated sheet.

    python scripts/contact_corrugation.py [--sizes 2,1,0.5] [--heights 0.25,0.35,0.42]
                                          [--thickness 0.5] [--samples 21]

The contact energy (``mvfem.contact``) sums IPC's barrier over every triangle of the other
surface within the thickness ``delta`` of a node. Over a flat sheet of equilateral triangles
(edge ``a``) at height ``h`` the distance to the surface is ``h`` wherever the node is, but the
sum is not: above a vertex all six triangles around it are at ``h`` (six barriers), above a
triangle's centre on a coarse sheet only that triangle is. So the energy is corrugated at the
mesh's scale: it pushes nodes toward the other surface's triangle centres, like a friction
(whether it slows the solver is weighed in README, "Where the finest level's steps go": at the
closed valve its sideways curvature is far below the membrane's). For each edge ``a`` and
height ``h`` the script samples the node's lateral position over one cell of the sheet
(``samples`` x ``samples`` points) and prints the sum's least, greatest and mean value, its
spread ``(max - min) / mean``, and the same with the pairs merged by closest feature (IPC's
point-triangle, point-edge and point-point pairs: each face, edge or vertex counted once),
which does not remove it. The barrier's stiffness is the demo's (16 kPa / delta); the spread
does not depend on it.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from mvfem.contact import barrier, closest_point_on_triangles


def sheet(a: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Equilateral triangles of edge ``a`` in the plane z = 0, (2n+1)^2 nodes around 0."""
    ij = [(i, j) for j in range(-n, n + 1) for i in range(-n, n + 1)]
    index = {p: k for k, p in enumerate(ij)}
    pts = np.array([[a * (i + 0.5 * j), a * j * np.sqrt(3) / 2, 0.0] for i, j in ij])
    tris = []
    for j in range(-n, n):
        for i in range(-n, n):
            tris.append([index[i, j], index[i + 1, j], index[i, j + 1]])
            tris.append([index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]])
    return pts, np.array(tris)


def energies(a: float, h: float, delta: float, kappa: float, samples: int):
    """The node's barrier sum at each sampled lateral position over one cell, per triangle
    (as mvfem.contact) and merged by closest feature; arrays of samples**2."""
    n = int(np.ceil(delta / a)) + 2
    pts, tris = sheet(a, n)
    A, B, C = (pts[tris[:, k]] for k in range(3))
    per_triangle, merged = [], []
    for u in np.linspace(0.0, 1.0, samples):
        for v in np.linspace(0.0, 1.0, samples):
            p = np.array([a * (u + 0.5 * v), a * v * np.sqrt(3) / 2, h])
            d, xi, _ = closest_point_on_triangles(np.repeat(p[None], len(tris), 0), A, B, C)
            near = d < delta
            per_triangle.append(barrier(d[near], delta, kappa)[0].sum())
            features = {}
            for t in np.flatnonzero(near):
                on = tuple(sorted(tris[t][xi[t] > 1e-9]))  # the vertices spanning the feature
                features[("face", t) if len(on) == 3 else on] = d[t]
            merged.append(barrier(np.array(list(features.values())), delta, kappa)[0].sum())
    return np.array(per_triangle), np.array(merged)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="2,1,0.5", help="triangle edges a, mm")
    p.add_argument("--heights", default="0.25,0.35,0.42", help="heights h above the sheet, mm")
    p.add_argument("--thickness", type=float, default=0.5, help="contact thickness delta, mm")
    p.add_argument("--samples", type=int, default=21, help="positions along each cell side")
    args = p.parse_args(argv)
    try:
        sizes = [float(s) for s in args.sizes.split(",")]
        heights = [float(s) for s in args.heights.split(",")]
    except ValueError:
        print("contact_corrugation: --sizes and --heights take comma-separated numbers",
              file=sys.stderr)
        return 2
    delta = args.thickness
    if not (delta > 0 and all(s > 0 for s in sizes) and all(0 < h < delta for h in heights)
            and args.samples >= 2):
        print("contact_corrugation: need thickness > 0, sizes > 0, 0 < heights < thickness and "
              "samples >= 2", file=sys.stderr)
        return 2
    kappa = 16e3 / delta
    print(f"contact thickness {delta:g} mm; one barrier b(h) per row; the node's energy over "
          f"one cell of the sheet, {args.samples}^2 positions")
    print("| edge a (mm) | height h (mm) | b(h) | per triangle: min / max / mean | spread "
          "| merged by feature: min / max / mean | spread |")
    print("|---:|---:|---:|---|---:|---|---:|")
    for a in sizes:
        for h in heights:
            e, m = energies(a, h, delta, kappa, args.samples)
            b = barrier(np.array([h]), delta, kappa)[0][0]
            print(f"| {a:g} | {h:g} | {b:.4g} | {e.min():.4g} / {e.max():.4g} / {e.mean():.4g} "
                  f"| {(e.max() - e.min()) / e.mean():.2f} | {m.min():.4g} / {m.max():.4g} / "
                  f"{m.mean():.4g} | {(m.max() - m.min()) / m.mean():.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
