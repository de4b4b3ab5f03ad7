"""Contact pressure between two parallel flat sheets at a given gap, by mesh size: does the
barrier (mvfem.contact.Contact: node-triangle and edge-edge pairs within the thickness) give
the same pressure on every mesh?

    python scripts/contact_sheets.py [--sizes 1,0.5,0.25,0.125] [--gaps 0.1,0.2,0.3,0.4]

Two 6 mm square sheets on aligned right-triangle grids of spacing h, 3 mm apart in the
reference (beyond the exclusion), the upper one moved to the gap g; the pressure is the
barrier force on the lower sheet's inner nodes (|x|, |y| < 1 mm) over their lumped area, in
Pa, with the default thickness 0.5 mm and the valves' stiffness 32 kPa/mm. Prints a markdown
table (README, "Nested levels").
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from mpi4py import MPI


def sheet(n: int, side: float, z: float) -> tuple[np.ndarray, np.ndarray]:
    """An (n x n)-square grid of right triangles of the given side at height z."""
    t = np.linspace(-side / 2, side / 2, n + 1)
    X, Y = np.meshgrid(t, t, indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z)])
    idx = np.arange(len(P)).reshape(n + 1, n + 1)
    a, b, c, d = (idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(),
                  idx[:-1, 1:].ravel())
    return P, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def sheets_contact(h: float, side: float = 6.0, thickness: float = 0.5,
                   stiffness: float = 32e3):
    """(view, contact term) of two parallel grids of spacing h, at z = 0 and z = 3 (the
    upper one, z > 1.5, to be moved to the gap)."""
    from dolfinx import fem

    from mvfem.contact import Contact
    from mvfem.meshes.io import mesh_from_arrays
    from mvfem.nodal import NodalView

    n = int(round(side / h))
    P1, T1 = sheet(n, side, 0.0)
    P2, T2 = sheet(n, side, 3.0)
    msh, _, _ = mesh_from_arrays(MPI.COMM_SELF, np.vstack([P1, P2]),
                                 np.vstack([T1, T2 + len(P1)]))
    view = NodalView(fem.VectorFunctionSpace(msh, ("Lagrange", 1)))
    return view, Contact(view, thickness, stiffness)


def pressures(h: float, gaps, side: float = 6.0, thickness: float = 0.5,
              stiffness: float = 32e3) -> list[tuple[float, int, int]]:
    """(pressure Pa, node-triangle pairs, edge pairs) at each gap, for grid spacing h."""
    view, contact = sheets_contact(h, side, thickness, stiffness)
    top = view.X[:, 2] > 1.5
    inner = (np.abs(view.X[:, 0]) < 1.0) & (np.abs(view.X[:, 1]) < 1.0) & ~top
    out = []
    for g in gaps:
        x = view.X.copy()
        x[top, 2] = g
        blk = contact(x)
        f = np.zeros_like(x)
        np.add.at(f, blk.nodes.ravel(), blk.force.reshape(-1, 3))
        # the energy's gradient on the lower sheet points up (toward the other): push is -f
        p = float(-f[inner, 2].sum() / view.area[inner].sum())
        out.append((-p, len(contact.active_pairs(x)[0]), len(contact.edge_pairs(x)[0])))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="1,0.5,0.25,0.125")
    p.add_argument("--gaps", default="0.1,0.2,0.3,0.4")
    args = p.parse_args(argv)
    sizes = [float(v) for v in args.sizes.split(",")]
    gaps = [float(v) for v in args.gaps.split(",")]
    print("| h (mm) | " + " | ".join(f"p at g = {g:g} mm (kPa)" for g in gaps)
          + " | pairs at the smallest gap (node-triangle + edge) |")
    print("|---:|" + "---:|" * len(gaps) + "---:|")
    for h in sizes:
        rows = pressures(h, gaps)
        print(f"| {h:g} | " + " | ".join(f"{r[0] / 1e3:.0f}" for r in rows)
              + f" | {rows[0][1]} + {rows[0][2]} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
