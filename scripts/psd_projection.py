"""Time of the contact blocks' PSD projection (mvfem.contact.project_psd, the convexified
tangent): compiled against numpy's batched ``eigh``, on the same blocks, alternating; and
of the contact evaluation that projecting the computed blocks in place saves.

    python scripts/psd_projection.py [--h 0.25] [--gap 0.15] [--repeats 3]

The blocks are the exact contact Hessians of two parallel sheets (scripts/contact_sheets.py)
on grids of spacing h, the upper one moved to the gap and both perturbed by 0.05 h, so that
pairs meet faces, edges and vertices: at h = 0.25 mm about as many blocks as the demo valve
refined twice closed (165,000). Prints the block count, the median times of each way, their
ratio, the largest difference of the two projections relative to each block's largest
entry, and the most negative eigenvalue left (relative), a markdown row (README, "Nested
levels"). Then the median time of one exact contact evaluation at that state (distances,
barrier, forces, Hessians: what a convexified re-solve evaluated again before
``PointTerms.convexify`` projected the blocks already computed) and of one convex one.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def scene(h: float, gap: float, side: float = 6.0, thickness: float = 0.5,
          stiffness: float = 32e3):
    """The contact term between the two sheets and the perturbed positions."""
    from contact_sheets import sheets_contact

    view, contact = sheets_contact(h, side, thickness, stiffness)
    x = view.X.copy()
    x[view.X[:, 2] > 1.5, 2] = gap
    x += np.random.default_rng(0).uniform(-0.05 * h, 0.05 * h, x.shape)
    return contact, x


def blocks(contact, x) -> np.ndarray:
    """The exact stiffness blocks (m, 12, 12) of the contact at x."""
    contact.convex = False
    return np.ascontiguousarray(contact(x).stiffness)


def main(argv=None) -> int:
    from mvfem import contact, kernels

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--h", type=float, default=0.25)
    p.add_argument("--gap", type=float, default=0.15)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    if kernels.load() is None:
        print("psd_projection: the contact kernels did not compile", file=sys.stderr)
        return 2
    term, x = scene(args.h, args.gap)
    K = blocks(term, x)
    times = {"compiled": [], "numpy": []}
    out = {}
    for _ in range(args.repeats):
        for name, f in (("numpy", contact.project_psd_numpy), ("compiled", contact.project_psd)):
            Kc = K.copy()
            t0 = time.perf_counter()
            out[name] = f(Kc)
            times[name].append(time.perf_counter() - t0)
    scale = np.maximum(np.abs(K).max(axis=(1, 2)), 1e-300)[:, None, None]
    diff = float((np.abs(out["compiled"] - out["numpy"]) / scale).max())
    low = float((np.linalg.eigvalsh(out["compiled"]) / scale[:, :, 0]).min())
    tn, tc = np.median(times["numpy"]), np.median(times["compiled"])
    print("| blocks | numpy eigh (s) | compiled (s) | ratio | max difference "
          "| most negative eigenvalue left |")
    print("|---:|---:|---:|---:|---:|---:|")
    print(f"| {len(K)} | {tn:.3f} | {tc:.3f} | {tn / tc:.1f} | {diff:.1e} | {low:.1e} |")
    print(f"(kernel threads {kernels.threads()}, {args.repeats} repeats, h = {args.h:g} mm, "
          f"gap {args.gap:g} mm)")
    ev = {False: [], True: []}
    for _ in range(args.repeats):
        for convex in (False, True):
            term.convex = convex
            t0 = time.perf_counter()
            term(x).stiffness
            ev[convex].append(time.perf_counter() - t0)
    te, tv = np.median(ev[False]), np.median(ev[True])
    print(f"one contact evaluation: exact {te:.3f} s, convex {tv:.3f} s; projecting the exact "
          f"blocks in place {tc:.3f} s saves {tv - tc:.3f} s per convexified re-solve")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    sys.exit(main())
