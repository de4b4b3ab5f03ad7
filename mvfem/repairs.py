r"""Repairs as scene edits (issue 8): the geometry of each repair on an open valve.

A scene's ``[repair]`` section asks for any of (CONTRACT.md, README "Repairs"):

- ``[repair.ring]`` ring annuloplasty: the annulus nodes are moved onto a ring (prescribed
  motion, :mod:`mvfem.prescribed`, ramped over the first ``solver.ramp_steps`` steps). The ring
  is sized as surgeons name it, by its intercommissural (transverse) diameter ``size`` in mm,
  with ``ap_ratio`` = anteroposterior / transverse (0.75, the 3:4 of the Carpentier-Edwards
  Physio ring). Shapes, in the valve frame (x anterior, y toward the anterolateral
  commissure), ``b = size / 2``, ``A = ap_ratio size``:

  .. math:: x = a(t) \cos t,\quad y = b \sin t,\quad z = (h_s/2) \cos 2t,\qquad
            a = a_{ant}\ (\cos t \ge 0),\ a_{post}\ (\cos t < 0)

  ``"full"``: a complete symmetric ring, ``a_ant = a_post = A/2``; ``"d-shaped"``: a complete
  ring with the flatter anterior side of the D, ``a_ant = A/3``, ``a_post = 2A/3``; ``"band"``:
  a partial posterior band of the D-shaped ring: the posterior annulus goes onto the band's arc
  and the anterior annulus (not sewn) keeps its shape, moved by the displacements of its two
  ends (the commissures) interpolated along it. The ring's centroid goes to the annulus
  centroid in the valve frame. Each annulus node goes to the point of the ring at the same
  fraction of the arc between landmarks: the anterior and posterior crossings of the
  anteroposterior line and the two commissures (the ring's commissure marks at ``t = pi/2,
  3pi/2``). A ring that would enlarge the annulus (size above its intercommissural width, or
  perimeter above its perimeter) is an input error.
- ``[[repair.neochord]]`` neochordae: new tethers (chordae of family ``"neochord"``) from a
  papillary tip to free-edge nodes chosen by position along the leaflet (``at``, fractions
  0 posteromedial .. 1 anterolateral commissure) or by a point near the free edge, with a
  rest length in mm.
- ``[[repair.clip]]`` edge-to-edge repair (Alfieri stitch, clip): ties (:mod:`mvfem.ties`)
  between the anterior and posterior free-edge nodes within ``width`` mm along the free edges
  of the chosen positions, paired by their offset along the edges; each tie holds its two
  nodes ``gap`` apart (default: the contact thickness).
- ``[repair.resection]`` leaflet resection: the cells of a triangular (apex toward the
  annulus) or quadrangular region of a leaflet are removed from the mesh, given by positions
  along the leaflet (``between`` or a Carpentier ``segment``) and a ``depth`` (fraction of the
  leaflet's height from the free edge), the new free edges re-tagged (the mesh goes through
  the import of :mod:`mvfem.meshes.imported`), chordae inserting in the removed tissue dropped,
  and the two sides of the cut tied together by sutures: nodes at the same arc length from
  each end of the cut are paired (a V closes like a zip; a quadrangle's bottom folds in two).

Every repair's geometry is computed on rank 0 and its errors raised on every rank as one
:class:`~mvfem.errors.InputError` line naming the scene and the key.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile

import numpy as np

from mvfem.errors import InputError

__all__ = [
    "RING_SHAPES",
    "TIE_STIFFNESS",
    "clip_pairs",
    "clip_within_edge",
    "free_edge",
    "neochordae",
    "on_root",
    "resect",
    "ring_axes",
    "ring_perimeter",
    "ring_points",
    "ring_targets",
    "snap_to_free_edge",
]

log = logging.getLogger(__name__)

RING_SHAPES = ("full", "d-shaped", "band")
#: default stiffness of a tie (clip, suture): Pa mm (uN/mm); 5 N/mm
TIE_STIFFNESS = 5e6
_DENSE_RING = 1 << 16  # samples of a ring (a multiple of 4: the landmarks are samples)


def on_root(comm, work, where: str):
    """Run ``work()`` on rank 0; an InputError (or ValueError) there is raised on every rank,
    prefixed with ``where`` for a ValueError. Returns rank 0's result (None elsewhere)."""
    result, error = None, None
    if comm.rank == 0:
        try:
            result = work()
        except InputError as e:
            error = str(e)
        except ValueError as e:
            error = f"{where}: {e}"
    error = comm.bcast(error, root=0)
    if error:
        raise InputError(error)
    return result


# --------------------------------------------------------------------------- rings
def ring_axes(shape: str, size: float, ap_ratio: float) -> tuple[float, float, float]:
    """(a_ant, a_post, b) half-axes of a ring, mm (module docstring)."""
    A = ap_ratio * size
    if shape == "full":
        return A / 2, A / 2, size / 2
    return A / 3, 2 * A / 3, size / 2


def ring_points(t, axes, saddle: float = 0.0) -> np.ndarray:
    """Points of the ring at parameters ``t`` in its own frame (x anterior, y anterolateral,
    z axis), centred on the crossing of its axes."""
    t = np.asarray(t, dtype=float)
    a_ant, a_post, b = axes
    c = np.cos(t)
    a = np.where(c >= 0, a_ant, a_post)
    return np.stack([a * c, b * np.sin(t), 0.5 * saddle * np.cos(2 * t)], axis=-1)


def _ring_table(axes, saddle: float):
    t = np.linspace(0.0, 2 * np.pi, _DENSE_RING, endpoint=False)
    p = ring_points(t, axes, saddle)
    seg = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)
    u = np.concatenate([[0.0], np.cumsum(seg)])
    return t, p, u


def ring_perimeter(axes, saddle: float = 0.0) -> float:
    """Length of the ring (a dense polygon of it: relative error ~1e-9)."""
    return float(_ring_table(axes, saddle)[2][-1])


def ring_targets(loop: np.ndarray, frame: np.ndarray, commissures: np.ndarray, shape: str,
                 size: float, ap_ratio: float = 0.75, saddle: float = 0.0,
                 where: str = "repair.ring") -> tuple[np.ndarray, dict]:
    """Positions on the ring of the annulus nodes ``loop`` (ordered along the annulus).

    Returns:
        (positions (n, 3), info: ring perimeter and axes, annulus perimeter and width,
        largest node displacement).

    Raises:
        InputError: the ring would enlarge the annulus, or cannot be matched to it.
    """
    from mvfem.prescribed import arc_length, ccw, landmark_map, landmarks, loop_centroid

    frame = np.asarray(frame, dtype=float)
    loop = np.asarray(loop, dtype=float)
    oriented = ccw(loop, frame)
    flipped = oriented is not loop
    u, L = arc_length(oriented)
    local = (oriented - loop_centroid(oriented)) @ frame.T
    width = float(np.ptp(local[:, 1]))
    axes = ring_axes(shape, size, ap_ratio)
    t, p, uu = _ring_table(axes, saddle)
    perimeter = float(uu[-1])
    q = _DENSE_RING // 4
    marks_ring = uu[[0, q, 2 * q, 3 * q]]                       # anterior, AL, posterior, PM
    try:
        ap = landmarks(oriented, frame)
    except ValueError as e:
        raise InputError(f"{where}: cannot match a ring to this annulus: {e}") from None
    # arc positions of the commissures: the nearest node of the annulus to each
    cm = [u[int(np.argmin(np.linalg.norm(oriented - c, axis=1)))] for c in commissures]
    marks = np.array([ap[0], cm[0], ap[1], cm[1]])
    rel = (marks - marks[0]) % L
    if not np.all(np.diff(rel) > 0):
        raise InputError(f"{where}: cannot match a ring to this annulus: its commissures are "
                         "not one on each side of the anteroposterior line")
    if shape == "band":
        post_len = (marks[3] - marks[1]) % L
        ring_post = uu[3 * q] - uu[q]
        if size >= width or ring_post >= post_len:
            raise InputError(
                f"{where}.size: a {size:g} mm band (posterior arc {ring_post:.1f} mm) is not "
                f"smaller than this annulus (intercommissural width {width:.1f} mm, posterior "
                f"arc {post_len:.1f} mm): it would enlarge it")
    elif size >= width or perimeter >= L:
        raise InputError(
            f"{where}.size: a {size:g} mm {shape} ring (perimeter {perimeter:.1f} mm) is not "
            f"smaller than this annulus (intercommissural width {width:.1f} mm, perimeter "
            f"{L:.1f} mm): it would enlarge it")
    w = landmark_map(u, L, marks, marks_ring, perimeter)
    tt = np.interp(w, uu, np.append(t, 2 * np.pi))
    # the ring's own centroid onto the annulus centroid (valve frame)
    centre_ring = loop_centroid(p)
    placed = loop_centroid(oriented) + (ring_points(tt, axes, saddle) - centre_ring) @ frame
    if shape == "band":
        # the anterior annulus (from PM through anterior to AL) follows its two ends
        rel_u = (u - marks[3]) % L
        span = (marks[1] - marks[3]) % L
        ant = rel_u < span
        i_al = int(np.argmin(np.abs(((u - marks[1]) + L / 2) % L - L / 2)))
        i_pm = int(np.argmin(np.abs(((u - marks[3]) + L / 2) % L - L / 2)))
        d_al, d_pm = placed[i_al] - oriented[i_al], placed[i_pm] - oriented[i_pm]
        f = (rel_u[ant] / span)[:, None]
        placed[ant] = oriented[ant] + (1 - f) * d_pm + f * d_al
    if flipped:
        placed = placed[::-1]
    info = {"shape": shape, "size_mm": float(size), "ap_ratio": float(ap_ratio),
            "saddle_height_mm": float(saddle), "axes_mm": [float(a) for a in axes],
            "ring_perimeter_mm": perimeter, "annulus_perimeter_mm": float(L),
            "annulus_width_mm": width,
            "max_displacement_mm": float(np.linalg.norm(placed - loop, axis=1).max())}
    return placed, info


# --------------------------------------------------------------------------- free edges
def free_edge(view, surface, leaflet: str, points: np.ndarray) -> dict:
    """Free-edge nodes of a leaflet on rank 0: global node indices, reference positions,
    position along the leaflet, and arc length along the edge, sorted by position.

    ``points``: (k, 3) reference coordinates of the leaflet's free-edge vertices (gathered)."""
    node = np.unique(view.node_of_point(points))
    X = view.X[node]
    pos = surface.along_leaflet(X, leaflet)
    order = np.argsort(pos, kind="stable")
    node, X, pos = node[order], X[order], pos[order]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(X, axis=0), axis=1))])
    return {"node": node, "X": X, "pos": pos, "arc": arc, "leaflet": leaflet}


def snap_to_free_edge(edge: dict, at=None, point=None, tolerance: float = 1.5,
                      where: str = "") -> int:
    """Index (into ``edge``) of the free-edge node at position ``at`` along the leaflet, or
    nearest ``point``.

    Raises:
        InputError: ``at`` outside the free edge's span, or ``point`` farther than
            ``tolerance`` mm from every node of the free edge.
    """
    name = edge["leaflet"]
    if point is not None:
        d = np.linalg.norm(edge["X"] - np.asarray(point, dtype=float), axis=1)
        i = int(np.argmin(d))
        if d[i] > tolerance:
            raise InputError(f"{where}: the point {list(map(float, point))} is not on the "
                             f"{name} free edge (nearest free-edge node {d[i]:.2f} mm away; "
                             f"tolerance {tolerance:g} mm)")
        return i
    pos, arc = edge["pos"], edge["arc"]
    # tolerance in position units: the tolerance as a share of the free edge's length
    slack = tolerance / max(arc[-1], 1e-9) * (pos[-1] - pos[0])
    if not pos[0] - slack <= at <= pos[-1] + slack:
        raise InputError(f"{where}: {at:g} is not on the {name} free edge (it spans "
                         f"{pos[0]:.3f} .. {pos[-1]:.3f} along the leaflet)")
    return int(np.argmin(np.abs(pos - at)))


def clip_within_edge(edge: dict, i: int, width: float, where: str) -> None:
    """Input error when a clip ``width`` mm wide centred on free-edge node ``i`` (of
    :func:`free_edge`) runs past an end of the edge, a commissure, by more than
    the edge's last segment there: its grasp would be cut there without a word (a clip 400 mm
    wide tied the whole free edges)."""
    arc = edge["arc"]
    if len(arc) < 2:
        return
    for end, room, cell in (("posteromedial", arc[i] - arc[0], arc[1] - arc[0]),
                            ("anterolateral", arc[-1] - arc[i], arc[-1] - arc[-2])):
        past = width / 2 - room
        if past > cell:
            raise InputError(f"{where}: a {width:g} mm clip centred {room:.2g} mm from the "
                             f"{edge['leaflet']} free edge's {end} end runs {past:.2g} mm past "
                             f"it (that free edge is {arc[-1]:.1f} mm long): move it inward "
                             "or make it narrower")


def _grasp_zone(edge: dict, i: int, width: float, depth: float, X: np.ndarray,
                own: np.ndarray):
    """Nodes of a leaflet a clip centred on its free-edge node ``i`` holds: the free-edge
    nodes within ``width / 2`` along the edge, and with ``depth > 0`` also the leaflet's nodes
    within ``depth`` of those. Returns (nodes, offset along the edge, distance from it)."""
    from scipy.spatial import cKDTree

    off = edge["arc"] - edge["arc"][i]
    on = np.abs(off) <= width / 2 + 1e-9
    nodes, offs, dist = edge["node"][on], off[on], np.zeros(int(on.sum()))
    if depth > 0:
        d, k = cKDTree(edge["X"][on]).query(X[own])
        inner = (d <= depth + 1e-9) & ~np.isin(own, nodes)
        nodes = np.concatenate([nodes, own[inner]])
        offs = np.concatenate([offs, offs[k[inner]]])
        dist = np.concatenate([dist, d[inner]])
    return nodes, offs, dist


def clip_pairs(ant: dict, post: dict, ia: int, ip: int, width: float, depth: float = 0.0,
               X: np.ndarray | None = None, own: dict | None = None) -> np.ndarray:
    """(m, 2) global node pairs (anterior, posterior) of a clip centred on anterior free-edge
    node ``ia`` and posterior ``ip``: the nodes each side holds (:func:`_grasp_zone`: ``width``
    along the free edges, ``depth`` into the leaflets), each node of the side with fewer paired
    to the node of the other side nearest in (offset along the edge, distance from it)."""
    X = np.zeros((0, 3)) if X is None else X
    own = own or {"anterior": np.zeros(0, dtype=np.int64), "posterior": np.zeros(0, dtype=np.int64)}
    na, oa, da = _grasp_zone(ant, ia, width, depth, X, own["anterior"])
    npo, op, dp = _grasp_zone(post, ip, width, depth, X, own["posterior"])
    A, P = np.column_stack([oa, da]), np.column_stack([op, dp])
    if len(na) <= len(npo):
        other = np.argmin(np.linalg.norm(A[:, None, :] - P[None, :, :], axis=2), axis=1)
        pairs = np.column_stack([na, npo[other]])
    else:
        other = np.argmin(np.linalg.norm(P[:, None, :] - A[None, :, :], axis=2), axis=1)
        pairs = np.column_stack([na[other], npo])
    return np.unique(pairs, axis=0)


def neochordae(edge: dict, spec: dict, tips: np.ndarray, muscle: np.ndarray, frame, centre,
               where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(global nodes, papillary tip index, rest length) of one ``[[repair.neochord]]``."""
    from mvfem.meshes.valve import MUSCLES

    nodes, tip_of = [], []
    if spec["point"] is not None:
        idx = [snap_to_free_edge(edge, point=spec["point"], tolerance=spec["tolerance"],
                                 where=f"{where}.point")]
    else:
        idx = [snap_to_free_edge(edge, at=a, tolerance=spec["tolerance"], where=f"{where}.at")
               for a in spec["at"]]
    for i in idx:
        x = edge["X"][i]
        choice = spec["papillary"]
        if choice == "nearest":  # the muscle on the node's side, as the native chordae
            side = 0 if ((x - centre) @ np.asarray(frame)[1]) >= 0 else 1
            cand = np.flatnonzero(muscle == side)
            if len(cand) == 0:
                cand = np.arange(len(tips))
        else:
            cand = np.flatnonzero(muscle == MUSCLES.index(choice))
            if len(cand) == 0:
                raise InputError(f"{where}.papillary: this valve has no {choice} tip")
        k = cand[np.argmin(np.linalg.norm(tips[cand] - x, axis=1))]
        nodes.append(edge["node"][i])
        tip_of.append(k)
    if len(set(nodes)) != len(nodes):
        raise InputError(f"{where}.at: two neochordae snap to the same free-edge node")
    return np.array(nodes), np.array(tip_of), np.full(len(nodes), float(spec["length"]))


# --------------------------------------------------------------------------- resection
def _height_fraction(X, annulus_nodes, free_nodes):
    """0 on the annulus, 1 on the free edge: d_a / (d_a + d_f) by distances to the nodes."""
    from scipy.spatial import cKDTree

    da = cKDTree(X[annulus_nodes]).query(X)[0]
    df = cKDTree(X[free_nodes]).query(X)[0]
    return da / np.maximum(da + df, 1e-300)


def _edge_counts(tri: np.ndarray):
    """The triangles' unique edges and how many triangles each bounds."""
    from mvfem.meshes.refine import cell_edges

    edges, sides = cell_edges(tri)
    return edges, np.bincount(sides.ravel(), minlength=len(edges))


def _chain(edges: np.ndarray) -> list[np.ndarray]:
    """Open polylines (vertex lists) made of ``edges``."""
    nbr: dict[int, list[int]] = {}
    for a, b in edges:
        nbr.setdefault(int(a), []).append(int(b))
        nbr.setdefault(int(b), []).append(int(a))
    seen, chains = set(), []
    for start in sorted(v for v, nb in nbr.items() if len(nb) == 1):
        if start in seen:
            continue
        path, prev = [start], -1
        seen.add(start)
        while True:
            nxt = [v for v in nbr[path[-1]] if v != prev and v not in seen]
            if not nxt:
                break
            prev = path[-1]
            path.append(nxt[0])
            seen.add(nxt[0])
        chains.append(np.array(path))
    return chains


def _resection_mask(raw, surface, spec: dict, where: str):
    """Cells to remove, and the leaflet's tag value (rank 0)."""
    from mvfem.model import SEGMENTS

    name = spec["leaflet"]
    value = (surface.names or {}).get(name)
    if value is None:
        raise InputError(f"{where}.leaflet: {name!r} is not a leaflet of this valve")
    X, tri = raw.points, raw.triangles
    leaf = raw.cell_data["leaflet"] == value
    on_ann = raw.point_data["annulus"] != 0
    edges, counts = _edge_counts(tri)
    boundary = edges[counts == 1]
    free = np.unique(boundary[~on_ann[boundary].all(axis=1)])
    own = np.unique(tri[leaf])
    free_own = np.intersect1d(free, own)
    r = _height_fraction(X, np.flatnonzero(on_ann), free_own)
    span = spec["between"] or SEGMENTS[spec["segment"][1]]
    a, b = span
    cen = X[tri].mean(axis=1)
    pos = np.full(len(tri), np.nan)
    pos[leaf] = surface.along_leaflet(cen[leaf], name)
    depth = 1.0 - r[tri].mean(axis=1)
    h = spec["depth"]
    if spec["shape"] == "triangular":
        half, mid = (b - a) / 2, (a + b) / 2
        inside = depth <= h * (1 - np.abs(pos - mid) / half)
    else:
        inside = (pos >= a) & (pos <= b) & (depth <= h)
    remove = leaf & inside
    free_pos = surface.along_leaflet(X[free_own], name)
    return remove, leaf, free_pos, on_ann, (a, b)


def resect(surface, spec: dict, comm, source: str, contact_gap: float):
    """The valve with a region of one leaflet removed, and the suture pairs (coordinates).

    Returns:
        (new valve, sutures (m, 2, 3) reference coordinates of the tied node pairs on rank 0
        (empty elsewhere), info dict).
    """
    from mvfem.meshes.imported import valve_from_surface, write_valve_with_chordae
    from mvfem.meshes.io import RawSurface, read_surface

    where = f"{source}: repair.resection"
    if not hasattr(surface, "along_leaflet") or not hasattr(surface, "insertion_points"):
        raise InputError(f"{where}: needs a valve mesh (generator = \"valve\" or a valve file)")
    tmp = tempfile.mkdtemp(prefix="mvfem-resect-") if comm.rank == 0 else None
    try:
        write_valve_with_chordae(os.path.join(tmp, "valve.vtu") if tmp else "unused.vtu",
                                 surface)

        def work():
            raw = read_surface(os.path.join(tmp, "valve.vtu"))
            remove, leaf, free_pos, on_ann, (a, b) = _resection_mask(raw, surface, spec, where)
            tri = raw.triangles
            if not remove.any():
                raise InputError(f"{where}: the region removes no cell of the {spec['leaflet']} "
                                 "leaflet (widen `between` or deepen `depth`)")
            area = 0.5 * np.linalg.norm(np.cross(raw.points[tri[:, 1]] - raw.points[tri[:, 0]],
                                                 raw.points[tri[:, 2]] - raw.points[tri[:, 0]]),
                                        axis=1)
            share = area[remove].sum() / area[leaf].sum()
            if a <= free_pos.min() and b >= free_pos.max():
                raise InputError(f"{where}: the region spans the whole free edge of the "
                                 f"{spec['leaflet']} leaflet: that resects the whole leaflet")
            if share > 0.5:
                raise InputError(f"{where}: the region is {100 * share:.0f} % of the "
                                 f"{spec['leaflet']} leaflet: that resects (nearly) the whole "
                                 "leaflet (at most 50 %)")
            e_rm, _ = _edge_counts(tri[remove])
            if np.any(on_ann[e_rm].all(axis=1)):
                raise InputError(f"{where}.depth: the region reaches the annulus (depth "
                                 f"{spec['depth']:g}); leave tissue there (an annular "
                                 "plication is not modelled)")
            keep = ~remove
            old_edges, old_counts = _edge_counts(tri)
            new_edges, new_counts = _edge_counts(tri[keep])
            interior_before = {tuple(e) for e in old_edges[old_counts == 2]}
            cut = np.array([e for e in new_edges[new_counts == 1] if tuple(e) in interior_before])
            chains = _chain(cut)
            if len(chains) != 1:
                raise InputError(f"{where}: the region's cut is not one line from the free edge "
                                 f"and back ({len(chains)} pieces): choose a simpler region")
            chain = chains[0]
            Xc = raw.points[chain]
            arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(Xc, axis=0),
                                                                   axis=1))])
            total = arc[-1]
            first = np.flatnonzero(arc < total / 2 - 1e-9 * total)
            pairs = []
            for i in first:
                j = int(np.argmin(np.abs(arc - (total - arc[i]))))
                if arc[j] > total / 2 + 1e-9 * total:
                    pairs.append((chain[i], chain[j]))
            pairs = np.unique(np.array(pairs, dtype=np.int64).reshape(-1, 2), axis=0)
            # chordae whose insertion is gone (lines: tip -> insertion)
            used = np.zeros(len(raw.points), dtype=bool)
            used[tri[keep].ravel()] = True
            lines, line_data = raw.lines, dict(raw.line_data)
            keep_line = np.ones(len(lines), dtype=bool)
            for k, (p, q) in enumerate(lines):
                on_leaflet = [n for n in (p, q) if n < len(used) and
                              raw.point_data.get("papillary", np.zeros(len(used)))[n] == 0]
                if any(not used[n] for n in on_leaflet):
                    keep_line[k] = False
            new = RawSurface(points=raw.points, triangles=tri[keep],
                             point_data=raw.point_data,
                             cell_data={k: v[keep] for k, v in raw.cell_data.items()},
                             lines=lines[keep_line],
                             line_data={k: v[keep_line] for k, v in line_data.items()})
            info = {"leaflet": spec["leaflet"], "shape": spec["shape"],
                    "between": [float(a), float(b)], "depth": float(spec["depth"]),
                    "cells_removed": int(remove.sum()), "area_removed_mm2":
                    float(area[remove].sum()), "leaflet_share": float(share),
                    "cut_length_mm": float(total), "sutures": len(pairs),
                    "chordae_dropped": int((~keep_line).sum())}
            return new, raw.points[pairs], info

        built = on_root(comm, work, where)
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    raw, sutures, info = built if comm.rank == 0 else (None, np.zeros((0, 2, 3)), None)
    labels = {int(v): k for k, v in (surface.names or {}).items()
              if k in _leaflet_names(surface)}
    try:
        valve = valve_from_surface(comm, raw, labels, source=f"{source} (resected)")
    except ValueError as e:
        raise InputError(f"{where}: the resected valve is not valid: {e}") from None
    info = comm.bcast(info, root=0)
    valve.info["resection"] = info
    log.info("resection: %d cells (%.1f mm^2, %.0f %% of the %s leaflet) removed, %d sutures",
             info["cells_removed"], info["area_removed_mm2"], 100 * info["leaflet_share"],
             info["leaflet"], info["sutures"])
    return valve, sutures, info


def _leaflet_names(surface) -> list[str]:
    names = surface.names or {}
    return [k for k in names if k != "annulus" and not k.startswith("free_edge_")]


def gap_default(scene) -> float:
    """Tied length of clips and sutures when the scene gives none: the contact thickness
    (mid-surface to mid-surface of two leaflets held together), 0 without contact."""
    return scene["contact"]["thickness"] if scene["contact"]["enabled"] else 0.0

