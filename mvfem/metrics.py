"""Valve metrics of a closed state: coaptation, regurgitant orifice, tenting, chordae forces.

All are computed on rank 0 from the nodal positions (:class:`mvfem.nodal.NodalView`) and the
contact pairs of the final state:

- a node *coapts* when it is paired with a triangle of another leaflet at a gap below
  ``COAPT_SLACK`` x the contact thickness; the coaptation area is the deformed (lumped) area of
  the coapting nodes, averaged over the two sides of the contact (sum over leaflets / 2);
- the coaptation length and the tenting height are read in the A2-P2 section: the plane
  through the annulus centre spanned by the valve axis and the anteroposterior direction. The
  coaptation length is the length of the coapting part of each leaflet's trace in that plane
  (mean of the two leaflets); the tenting height is the depth, below the annulus plane (least
  squares through the annulus nodes), of the atrial-most coapting point of the section;
- the coaptation trace length reads the same trace continuously: the length of each leaflet's
  trace within ``COAPT_SLACK`` x the contact thickness of the other leaflet, sampled every
  ``TRACE_STEP`` mm (:func:`coapting_trace_length`), where the coaptation length counts a cut
  triangle's segment whole or not at all;
- the regurgitant orifice area is the part of the annulus opening, seen along the axis, that no
  closed leaflet covers: the projected leaflets are rasterised (``PIXEL``), grown by half the
  contact thickness (the leaflets' own thickness closes a gap of one contact thickness), and
  subtracted from the projected annulus polygon;
- the leak gap area sees what the projection cannot: leaflets that overlap seen from the atrium
  without touching (a prolapsing segment rising past the other leaflet) leave a channel between
  them. In sections across the coaptation line (planes spanned by the axis and the
  anteroposterior direction, every ``SECTION_STEP`` mm from commissure to commissure) it takes
  the smallest distance between the traces of the two leaflets, less the contact thickness
  (touching leaflets seal), and integrates it along the line: a channel of width ``w`` over a
  length ``L`` gives ``(w - delta) L``, like the projected hole of a slot of that width;
- the regurgitant orifice area reported is the larger of the two (each is a lower bound of the
  narrowest cross-section the jet passes).
"""

from __future__ import annotations

import numpy as np

from mvfem.contact import segment_distance
from mvfem.nodal import lumped_area

__all__ = ["valve_metrics", "coapting_nodes", "orifice_area", "leak_gap_area",
           "coapting_trace_length", "segment_distance", "COAPT_SLACK",
           "PIXEL", "SECTION_STEP", "ORIFICE_MIN_AREA", "TRACE_STEP"]

#: a pair coapts when its gap is below this multiple of the contact thickness
COAPT_SLACK = 1.5
#: raster size of the orifice area (mm)
PIXEL = 0.05
#: pixels of the triangles' boxes tested at once by orifice_area
CHUNK = 1 << 20
#: largest spacing of the samples of a trace (coapting_trace_length, mm)
TRACE_STEP = 0.02
#: spacing of the sections of the leak gap area (mm)
SECTION_STEP = 0.25
#: an open piece of the projected annulus smaller than this (mm^2) is not counted as an
#: orifice of its own (orifice_count); its area still counts in the totals
ORIFICE_MIN_AREA = 0.5


def _frame(annulus: np.ndarray, axis_hint: np.ndarray):
    """Centre, unit normal (oriented like ``axis_hint``) of the least-squares annulus plane."""
    c = annulus.mean(axis=0)
    # only V: the full U of the demo's 4000-point annulus curve cost 0.85 s of its 58 s
    _, _, vt = np.linalg.svd(annulus - c, full_matrices=False)
    n = vt[2]
    if n @ axis_hint < 0:
        n = -n
    return c, n


def coapting_nodes(contact, x: np.ndarray, cell_tag: np.ndarray) -> np.ndarray:
    """Boolean (N,) mask: nodes closer than ``COAPT_SLACK`` x the contact thickness to a
    triangle of another leaflet."""
    view = contact.view
    mask = np.zeros(len(view.X), dtype=bool)
    s, t, _, _ = contact.active_pairs(x, within=COAPT_SLACK * contact.thickness)
    if len(s) == 0:
        return mask
    node_tag = _node_tags(view.cells, cell_tag, len(view.X))
    mask[s[node_tag[s] != cell_tag[t]]] = True
    return mask


def _node_tags(cells, cell_tag, n) -> np.ndarray:
    tag = np.zeros(n, dtype=cell_tag.dtype)
    tag[cells.ravel()] = np.repeat(cell_tag, 3)
    return tag


def _section(x, cells, flags, origin, normal):
    """Segments of the surface's trace in a plane: (k, 2, 3) end points and (k,) flags (True
    when both crossed edges have a flagged end), one per triangle the plane cuts, in the
    triangles' order, each from its first crossed edge (of 01, 12, 20) to its second."""
    d = (x - origin) @ normal
    neg = d[cells] < 0
    cut = neg.any(axis=1) & ~neg.all(axis=1)  # only the triangles the plane cuts
    if not cut.any():
        return np.zeros((0, 2, 3)), np.zeros(0, dtype=bool)
    cells, neg = cells[cut], neg[cut]
    nxt = [1, 2, 0]
    # a cut triangle has one vertex on one side and two on the other: two edges cross
    row, k = np.nonzero(neg != neg[:, nxt])  # row-major: each triangle's two edges in order
    a, b = cells[row, k], cells[row, np.asarray(nxt)[k]]
    t = d[a] / (d[a] - d[b])
    pts = x[a] + t[:, None] * (x[b] - x[a])
    f = (flags[a] | flags[b]).reshape(-1, 2)
    return pts.reshape(-1, 2, 3), f[:, 0] & f[:, 1]


def coapting_trace_length(x, cells_a, cells_b, origin, normal, within: float,
                          step: float = TRACE_STEP) -> float:
    """Length (mm) of the trace of the surface ``cells_a`` (triangles into the positions ``x``)
    in the plane through ``origin`` with unit ``normal`` that lies within ``within`` of the
    surface ``cells_b``: each segment of the trace (:func:`_section`) cut into equal parts no
    longer than ``step``, a part counted where its midpoint is that close to a triangle of
    ``cells_b``.

    Continuous in the positions, unlike the ``coaptation_length_mm`` of :func:`valve_metrics`,
    which counts a segment (about a cell long) whole or not at all by its nodes' flags: on the
    demo's meshes of 5, 4, 3, 2.5 and 2 mm that one read 7.36, 7.95, 5.41, 7.61, 7.84 mm and
    this one 6.56, 6.33, 6.43, 7.11, 7.16 mm; on the 2 mm mesh refined twice 7.88 and 7.72 mm
    (README, "Valve outputs and metrics"; ``scripts/coaptation_trace.py``).
    """
    segs, _ = _section(x, cells_a, np.zeros(len(x), dtype=bool), origin, normal)
    return _length_within(segs, x, cells_b, within, step)


def _length_within(segs, x, cells_b, within: float, step: float) -> float:
    """:func:`coapting_trace_length` of the trace's segments ``segs`` ((k, 2, 3))."""
    from mvfem.distance import points_within

    if len(segs) == 0 or len(cells_b) == 0:
        return 0.0
    length = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1)
    parts = np.maximum(np.ceil(length / step).astype(np.int64), 1)
    seg = np.repeat(np.arange(len(segs)), parts)
    first = np.repeat(np.cumsum(parts) - parts, parts)
    u = (np.arange(len(seg)) - first + 0.5) / parts[seg]
    p = segs[seg, 0] + u[:, None] * (segs[seg, 1] - segs[seg, 0])
    near = points_within(p, x, cells_b, within)
    return float(np.sum((length / parts)[seg][near]))


def _inside_polygon(ring: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """(len(gx), len(gy)) mask of the grid points inside the closed polygon ``ring`` (k, 2),
    by the even-odd rule, one scanline per ``gy`` (a point-in-polygon test of every grid point
    took 5 s for the demo's 4096-vertex annulus)."""
    a, b = ring, np.roll(ring, -1, axis=0)
    out = np.zeros((len(gx), len(gy)), dtype=bool)
    for j, y in enumerate(gy):
        cross = (a[:, 1] <= y) != (b[:, 1] <= y)
        if not cross.any():
            continue
        a_, b_ = a[cross], b[cross]
        xs = np.sort(a_[:, 0] + (y - a_[:, 1]) * (b_[:, 0] - a_[:, 0]) / (b_[:, 1] - a_[:, 1]))
        out[:, j] = np.searchsorted(xs, gx) % 2 == 1
    return out


def orifice_area(x, cells, annulus_loop, centre, axis, grow: float, components: bool = False):
    """Area (mm^2) of the projected annulus polygon not covered by the projected triangles
    grown by ``grow`` mm; with ``components`` also the areas of its connected pieces (the
    separate orifices, largest first; 8-connected pixels)."""
    from scipy import ndimage

    e1 = np.cross(axis, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.1:
        e1 = np.cross(axis, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    P = lambda y: np.stack([(y - centre) @ e1, (y - centre) @ e2], axis=-1)  # noqa: E731
    ring = P(annulus_loop)
    lo, hi = ring.min(axis=0) - 1.0, ring.max(axis=0) + 1.0
    nx, ny = (np.ceil((hi - lo) / PIXEL)).astype(int)
    gx = lo[0] + (np.arange(nx) + 0.5) * PIXEL
    gy = lo[1] + (np.arange(ny) + 0.5) * PIXEL
    inside = _inside_polygon(ring, gx, gy)
    covered = np.zeros((nx, ny), dtype=bool)
    q = P(x)[cells]  # (C, 3, 2)
    # each triangle's box of pixels, clipped to the grid
    ia, ja = np.maximum(np.floor((q.min(axis=1) - lo) / PIXEL).astype(int), 0).T
    ib, jb = np.ceil((q.max(axis=1) - lo) / PIXEL).astype(int).T
    ib, jb = np.minimum(ib, nx), np.minimum(jb, ny)
    a, v0, v1 = q[:, 0], q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]
    den = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    keep = np.flatnonzero((ib > ia) & (jb > ja) & (np.abs(den) >= 1e-14))
    w, h = ib[keep] - ia[keep], jb[keep] - ja[keep]
    # every (triangle, pixel of its box) at once, in chunks of about CHUNK pixels (or one
    # triangle's box, where larger)
    ends = np.cumsum(w * h)
    first = 0
    while first < len(keep):
        last = int(np.searchsorted(ends, (ends[first - 1] if first else 0) + CHUNK,
                                   side="right"))
        last = max(last, first + 1)
        sel = keep[first:last]
        n = w[first:last] * h[first:last]
        c = np.repeat(np.arange(len(sel)), n)
        k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        hc = h[first:last][c]
        i, j = ia[sel][c] + k // hc, ja[sel][c] + k % hc
        t_ = sel[c]
        wx, wy = gx[i] - a[t_, 0], gy[j] - a[t_, 1]
        s = (wx * v1[t_, 1] - wy * v1[t_, 0]) / den[t_]
        t = (v0[t_, 0] * wy - v0[t_, 1] * wx) / den[t_]
        hit = (s >= 0) & (t >= 0) & (s + t <= 1)
        covered[i[hit], j[hit]] = True
        first = last
    r = int(np.ceil(grow / PIXEL))
    if r > 0:
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        covered = ndimage.binary_dilation(covered, structure=(xx**2 + yy**2) <= r * r)
    open_ = inside & ~covered
    area = float(np.sum(open_) * PIXEL**2)
    if not components:
        return area
    labels, n = ndimage.label(open_, structure=np.ones((3, 3), dtype=bool))
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:] * PIXEL**2
    return area, sorted((float(a) for a in sizes), reverse=True)


def leak_gap_area(x, cells_a, cells_b, origin, axis, along, span, thickness) -> tuple:
    """Leak gap area (mm^2) between two leaflets (triangles ``cells_a``, ``cells_b`` into the
    positions ``x``), and the gap per section: sections are the planes through ``origin + y
    along`` with normal ``along`` (a unit vector across the coaptation line, perpendicular to
    ``axis``) for ``y`` in ``span`` (from, to) every :data:`SECTION_STEP` mm. Sections where
    one leaflet has no trace do not count.

    Returns:
        (area, y, gap) with ``gap = max(0, smallest distance - thickness)`` per section.
    """
    y0, y1 = span
    n = max(int(np.ceil((y1 - y0) / SECTION_STEP)), 1)
    ys = y0 + (np.arange(n) + 0.5) * (y1 - y0) / n
    gaps = np.full(n, np.nan)
    flags = np.zeros(len(x), dtype=bool)
    for i, y in enumerate(ys):
        o = origin + y * along
        sa, _ = _section(x, cells_a, flags, o, along)
        sb, _ = _section(x, cells_b, flags, o, along)
        if len(sa) == 0 or len(sb) == 0:
            continue
        ia, ib = np.meshgrid(np.arange(len(sa)), np.arange(len(sb)), indexing="ij")
        ia, ib = ia.ravel(), ib.ravel()
        d = segment_distance(sa[ia, 0], sa[ia, 1], sb[ib, 0], sb[ib, 1]).min()
        gaps[i] = max(d - thickness, 0.0)
    ok = np.isfinite(gaps)
    area = float(np.sum(gaps[ok]) * (y1 - y0) / n)
    return area, ys, gaps


def valve_metrics(model, x: np.ndarray) -> dict:
    """The ``valve`` block of summary.json (rank 0), with the coapting-node mask under
    ``"_coapting"`` (removed before writing)."""
    view, surface, contact = model.view, model.surface, model.contact
    names = {v: k for k, v in (surface.names or {}).items()}
    ann_loop = np.asarray(getattr(surface, "annulus_curve", np.zeros((0, 3))))
    moved = getattr(model, "annulus_nodes", None)
    if moved is not None and len(moved) >= 3:  # a prescribed annulus (ring): where it is now
        ann_loop = x[moved]
    axis = np.asarray(getattr(surface, "axis", [0.0, 0.0, 1.0]), dtype=float)
    out: dict = {}
    if contact is not None:
        flags = coapting_nodes(contact, x, view.cell_tag)
        area = lumped_area(x, view.cells)
        node_tag = _node_tags(view.cells, view.cell_tag, len(view.X))
        per_leaflet = {names.get(int(t), str(t)): float(area[flags & (node_tag == t)].sum())
                       for t in np.unique(view.cell_tag)}
        out["coaptation_area_mm2"] = 0.5 * sum(per_leaflet.values())
        out["coaptation_area_per_leaflet_mm2"] = per_leaflet
    else:
        flags = np.zeros(len(view.X), dtype=bool)
        out["coaptation_area_mm2"] = None
    if len(ann_loop) >= 3:
        centre, n = _frame(ann_loop, axis)
        ap = np.asarray(getattr(surface, "frame", np.eye(3)))[0]
        ap = ap - (ap @ n) * n
        ap /= np.linalg.norm(ap)
        section_normal = np.cross(n, ap)
        lengths, depths, trace = {}, [], {}
        for t in np.unique(view.cell_tag):
            segs, fl = _section(x, view.cells[view.cell_tag == t], flags, centre, section_normal)
            name = names.get(int(t), str(t))
            lengths[name] = float(np.linalg.norm(segs[fl, 1] - segs[fl, 0], axis=1).sum())
            if contact is not None:  # the same trace measured continuously
                trace[name] = _length_within(segs, x, view.cells[view.cell_tag != t],
                                             COAPT_SLACK * contact.thickness, TRACE_STEP)
            if fl.any():
                depths.append(float(((segs[fl].reshape(-1, 3) - centre) @ n).max()))
        out["coaptation_length_mm"] = float(np.mean(list(lengths.values()))) if lengths else None
        out["coaptation_length_per_leaflet_mm"] = lengths
        # (README, "Valve outputs and metrics": the stepped and the continuous lengths)
        out["coaptation_trace_length_mm"] = (float(np.mean(list(trace.values())))
                                             if trace else None)
        out["coaptation_trace_length_per_leaflet_mm"] = trace or None
        out["tenting_height_mm"] = (-max(depths)) if depths else None
        grow = 0.5 * contact.thickness if contact is not None else 0.0
        projected, pieces = orifice_area(x, view.cells, ann_loop, centre, n, grow,
                                         components=True)
        leak = _leak_between_leaflets(surface, view, x, centre, n, ap, section_normal,
                                      2 * grow, names)
        out["projected_orifice_area_mm2"] = projected
        out["leak_gap_area_mm2"] = leak
        out["regurgitant_orifice_area_mm2"] = max(projected, leak if leak is not None else 0.0)
        out["annulus_area_mm2"] = orifice_area(x, view.cells[:0], ann_loop, centre, n, 0.0)
        # the separate openings seen along the axis (a clipped valve opens on both sides of
        # the clip: two orifices); under an atrial-side (diastolic) pressure their total is
        # the diastolic orifice area
        out["orifice_count"] = int(sum(a >= ORIFICE_MIN_AREA for a in pieces))
        out["orifice_areas_mm2"] = [a for a in pieces if a >= ORIFICE_MIN_AREA]
        out["diastolic_orifice_area_mm2"] = projected if model.p_target < 0 else None
    if model.chordae is not None and len(model.chordae):
        ch = model.chordae
        f = ch.force_N(x)
        block = {"total": float(f.sum()), "max": float(f.max(initial=0.0)),
                 "taut": int(np.sum(f > 0)), "count": int(len(f))}
        for fam in np.unique(ch.family):
            sel = ch.family == fam
            block[str(fam)] = {"total": float(f[sel].sum()), "max": float(f[sel].max()),
                               "taut": int(np.sum(f[sel] > 0)), "count": int(sel.sum())}
        out["chordae_force_N"] = block
    else:
        out["chordae_force_N"] = None
    ties = getattr(model, "ties", None)
    out["ties"] = ties.summary(x) if ties is not None and len(ties) else None
    out["_coapting"] = flags
    return out


def _leak_between_leaflets(surface, view, x, centre, axis, ap, across, thickness, names):
    """:func:`leak_gap_area` between the anterior leaflet and the rest (or the two largest
    labels), from commissure to commissure; None without two leaflets or commissures."""
    tags = np.unique(view.cell_tag)
    comm_pts = np.asarray(getattr(surface, "commissures", np.zeros((0, 3))))
    if len(tags) < 2 or len(comm_pts) != 2:
        return None
    by_name = {names.get(int(t), str(t)): t for t in tags}
    if "anterior" in by_name:
        first = view.cell_tag == by_name["anterior"]
    else:
        counts = [(np.sum(view.cell_tag == t), t) for t in tags]
        first = view.cell_tag == max(counts)[1]
    ys = sorted(float((c - centre) @ across) for c in comm_pts)
    area, _, _ = leak_gap_area(x, view.cells[first], view.cells[~first], centre, axis,
                               across, ys, thickness)
    return area
