r"""Prescribed motion of the clamped loop (a valve's annulus, a disk's rim) and of the papillary
tips: from the open (stress-free) positions to given ones, ramped while solving.

The open mesh stays the reference. The clamped nodes get a Dirichlet value ``f g`` with ``g``
the displacement to their target and ``f`` the ramp fraction (:class:`Prescribed`); the
chordae anchors move by ``f`` times their tip's displacement.

Matching a target loop to the nodes (:func:`match_loop`). Both loops (the nodes of the open
annulus in their order along it, and the target) are parametrised by arc length, piecewise
between *landmarks*: the points where the loop crosses the anteroposterior line (the line
through the loop's own centroid along the valve frame's anterior direction), anterior first,
both loops running counter-clockwise about the valve axis seen from the atrium. A node at a
fraction ``s`` of the arc between two landmarks goes to the same fraction between the
target's landmarks. With ``match = "points"`` the target has one point per node and each node
takes the point nearest its position (one to one, else an error); with ``"curve"`` the
target is a closed polyline and each node goes to the point at its position on it (linear
interpolation). A rigid motion that keeps the anteroposterior line's crossings where they were
(a translation, a tilt about the commissural direction) is reproduced exactly by either.

Lengths in mm. numpy only; the caller gathers the nodes (rank 0) and shares the result.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "arc_length",
    "ccw",
    "landmark_map",
    "landmarks",
    "loop_centroid",
    "match_loop",
    "order_loop",
]


def loop_centroid(loop: np.ndarray) -> np.ndarray:
    """Arc-length weighted centroid of a closed polyline (k, 3)."""
    nxt = np.roll(loop, -1, axis=0)
    seg = np.linalg.norm(nxt - loop, axis=1)
    return ((loop + nxt) / 2 * seg[:, None]).sum(axis=0) / seg.sum()


def ccw(loop: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """The loop (k, 3) in counter-clockwise order about ``frame[2]`` (reversed if need be)."""
    local = (loop - loop_centroid(loop)) @ np.asarray(frame).T
    area = 0.5 * np.sum(local[:, 0] * np.roll(local[:, 1], -1)
                        - np.roll(local[:, 0], -1) * local[:, 1])
    return loop if area >= 0 else loop[::-1].copy()


def order_loop(points: np.ndarray, frame: np.ndarray, curve: np.ndarray | None = None
               ) -> np.ndarray:
    """Indices that put unordered loop nodes in order along the loop (counter-clockwise about
    ``frame[2]``): along ``curve`` (an ordered dense loop they lie near, e.g. a valve's
    ``annulus_curve``) when given, else by polar angle about their centroid."""
    pts = np.asarray(points, dtype=float)
    if curve is not None and len(curve) >= 3:
        from scipy.spatial import cKDTree

        curve = ccw(np.asarray(curve, dtype=float), frame)
        seg = np.linalg.norm(np.roll(curve, -1, axis=0) - curve, axis=1)
        u = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
        _, idx = cKDTree(curve).query(pts)
        key = u[idx]
    else:
        local = (pts - pts.mean(axis=0)) @ np.asarray(frame).T
        key = np.arctan2(local[:, 1], local[:, 0])
    return np.argsort(key, kind="stable")


def arc_length(loop: np.ndarray) -> tuple[np.ndarray, float]:
    """Arc length at each vertex of a closed polyline (from vertex 0) and the perimeter."""
    seg = np.linalg.norm(np.roll(loop, -1, axis=0) - loop, axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)[:-1]]), float(seg.sum())


def landmarks(loop: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Arc length (from vertex 0) of the anterior and posterior crossings of the
    anteroposterior line through the loop's centroid. ``loop`` must run counter-clockwise
    about ``frame[2]``.

    Raises:
        ValueError: the line does not cross the loop once on each side.
    """
    frame = np.asarray(frame, dtype=float)
    local = (loop - loop_centroid(loop)) @ frame.T
    y, x = local[:, 1], local[:, 0]
    y1, x1 = np.roll(y, -1), np.roll(x, -1)
    u, L = arc_length(loop)
    seg = np.linalg.norm(np.roll(loop, -1, axis=0) - loop, axis=1)
    out = []
    for up, side in ((True, 1.0), (False, -1.0)):
        cross = ((y <= 0) & (y1 > 0)) if up else ((y > 0) & (y1 <= 0))
        t = np.where(cross, -y / np.where(cross, y1 - y, 1.0), 0.0)
        xc = x + t * (x1 - x)
        hits = np.flatnonzero(cross & (side * xc > 0))
        if len(hits) != 1:
            raise ValueError(f"the anteroposterior line crosses the loop {len(hits)} times on "
                             f"its {'anterior' if up else 'posterior'} side (expected once)")
        i = hits[0]
        out.append(u[i] + t[i] * seg[i])
    return np.array(out)


def landmark_map(u: np.ndarray, L: float, marks: np.ndarray, marks_t: np.ndarray,
                 L_t: float) -> np.ndarray:
    """Arc positions ``u`` on a loop of length ``L`` with landmarks ``marks`` (increasing
    cyclically) -> positions on a target loop of length ``L_t`` with landmarks ``marks_t``:
    piecewise proportional between consecutive landmarks."""
    u = np.asarray(u, dtype=float)
    m = len(marks)
    out = np.empty_like(u)
    rel = (u - marks[0]) % L                       # from the first landmark
    rel_marks = (np.asarray(marks) - marks[0]) % L
    rel_marks_t = (np.asarray(marks_t) - marks_t[0]) % L_t
    edges = np.append(rel_marks, L)
    edges_t = np.append(rel_marks_t, L_t)
    for k in range(m):
        sel = (rel >= edges[k]) & (rel < edges[k + 1]) if k < m - 1 else rel >= edges[k]
        frac = (rel[sel] - edges[k]) / (edges[k + 1] - edges[k])
        out[sel] = edges_t[k] + frac * (edges_t[k + 1] - edges_t[k])
    return (out + marks_t[0]) % L_t


def match_loop(nodes: np.ndarray, target: np.ndarray, frame: np.ndarray,
               mode: str = "auto") -> np.ndarray:
    """Target position of each loop node (``nodes`` ordered along the loop).

    Args:
        nodes: (n, 3) the open loop's nodes in order (either way round).
        target: (k, 3) the target loop, ordered (either way round, any start; a repeated
            first point at the end is dropped).
        frame: rows = anterior, commissural and axis directions of the valve.
        mode: "points" (k == n, one point per node), "curve" (polyline resampled at the
            nodes' positions) or "auto" (points when k == n, else curve).

    Returns:
        (n, 3) positions, in the order of ``nodes``.

    Raises:
        ValueError: too few target points, landmarks not found, or (points) no one-to-one
            match.
    """
    nodes = np.asarray(nodes, dtype=float)
    target = np.asarray(target, dtype=float)
    if len(target) > 3 and np.linalg.norm(target[0] - target[-1]) <= 1e-12 * np.ptp(target):
        target = target[:-1]
    if len(target) < 3:
        raise ValueError(f"a target loop needs at least 3 points, got {len(target)}")
    if mode == "auto":
        mode = "points" if len(target) == len(nodes) else "curve"
    if mode == "points" and len(target) != len(nodes):
        raise ValueError(f"match = \"points\" needs one point per clamped node: {len(nodes)} "
                         f"nodes, {len(target)} points (or use match = \"curve\")")
    order = np.arange(len(nodes))
    loop = ccw(nodes, frame)
    if loop is not nodes:
        order = order[::-1]
    tgt = ccw(target, frame)
    u, L = arc_length(loop)
    v, Lt = arc_length(tgt)
    pos = landmark_map(u, L, landmarks(loop, frame), landmarks(tgt, frame), Lt)
    if mode == "points":
        d = np.abs(pos[:, None] - v[None, :])
        d = np.minimum(d, Lt - d)
        pick = np.argmin(d, axis=1)
        if len(np.unique(pick)) != len(pick):
            raise ValueError("the target points do not match the clamped nodes one to one (two "
                             "nodes nearest the same point); use match = \"curve\"")
        placed = tgt[pick]
    else:
        closed = np.vstack([tgt, tgt[:1]])
        vv = np.append(v, Lt)
        placed = np.column_stack([np.interp(pos, vv, closed[:, j]) for j in range(3)])
    out = np.empty_like(placed)
    out[order] = placed
    return out
