"""The open (diastolic) mitral valve as a triangle surface mesh: the stress-free reference shape
of a closure simulation. Lengths in millimetres.

Geometry (all in a local frame: ``x`` anterior, ``y`` commissural with the anterolateral
commissure at ``+y``, ``z`` = the annulus-plane normal from ventricle to atrium; the frame is
right-handed, so looking from the atrium with anterior up, ``+y`` is on the left as in the
surgeon's view):

- the annulus is a closed curve ``A(s)``, ``s`` the normalised arc length, running
  counter-clockwise about ``z`` from the anterior midpoint (``s = 0``). Parametric default: the
  ellipse ``x = (D_ap/2) cos t, y = (D_c/2) sin t`` with the saddle
  ``z = (h_s/2) cos 2t`` (high points anterior and posterior, low points at the commissures).
  Patient: the given loop, its plane, centre and axes by PCA, smoothed by a truncated Fourier
  series in arc length.
- the commissures split it by arc length: the anterior leaflet hangs from
  ``|s| <= share/2``, the posterior from the rest.
- each leaflet is the ruled surface ``X(s, r) = A(s) + r H(s) d(s)``, ``0 <= r <= 1``, with
  ``d = -cos(alpha) z + sin(alpha) n_in`` (down toward the ventricle, tilted inward by
  ``alpha`` along the in-plane inward normal ``n_in = z x T`` of the annulus, Gaussian-smoothed
  along the annulus so that rulings do not cross at sharp turns: a funnel) and the height
  profile

  .. math:: H = h_c + (H_{max} - h_c)\\, g(\\tau),\\quad g = 1 - (1 - \\sin \\pi\\tau)^q,

  ``tau`` in [0, 1] across the leaflet, ``q = 1`` anterior (rounded), ``q = 2`` posterior
  (flatter, wide), ``h_c`` the commissural height; the tilt ``alpha`` blends the same way from
  the mean of the two leaflets' tilts at the commissures to the leaflet's own.
- commissures: the leaflets are one continuous curtain, as in the heart. At each commissure
  both leaflets end on the same ruling, of height ``h_c`` (``commissure_height``), which is
  an interior line of the mesh shared by the two leaflets; the free edge is one closed loop,
  with a notch where the two leaflets' free edges meet below each commissure. (An earlier
  design let each free edge run up to the annulus at the commissure, leaving a V-shaped slit
  there; under pressure the slit's edges bulged past the annulus and the closure did not
  converge, README.)

Meshing: the ruled surfaces are sampled finely (a discrete gmsh model), reparametrised by gmsh
(``createGeometry``) and remeshed with the target ``size``, graded to ``free_edge_size`` near
the free edges; gmsh runs on rank 0 only, the mesh is distributed as in
:mod:`mvfem.meshes.generators`.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .generators import SurfaceMesh, _gmsh_model, _orient
from .io import _cpp_mesh, _root_or_error, mesh_from_arrays, write_surface

__all__ = ["ValveMesh", "valve", "write_valve", "surface_distance", "LEAFLETS", "MUSCLES"]

logger = logging.getLogger(__name__)

#: cell tag values of the leaflets (also the ``leaflet`` cell data written by :func:`write_valve`)
LEAFLETS = {"anterior": 1, "posterior": 2}
#: papillary muscle names, by index: 0 on the +y (anterolateral) side, 1 on the -y side
MUSCLES = ("anterolateral", "posteromedial")
_GROUPS = {"anterior": 1, "posterior": 2, "annulus": 3, "free_edge_anterior": 4,
           "free_edge_posterior": 5}
# exponent q of the height profile g = 1 - (1 - sin(pi tau))^q
_PROFILE = {"anterior": 1.0, "posterior": 2.0}
_DENSE = 4096  # samples of the annulus curve
#: grid (mm) the fine sample of each leaflet is rounded to before its Delaunay triangulation
#: and gmsh: 2^-20 mm, about 1 nm. The sample is a staggered grid full of co-circular
#: quadruples, whose Delaunay diagonals (and then gmsh's mesh of the surface) flipped with the
#: last bit of the sines, norms and sums behind them: the demo's annulus curve perturbed by
#: one unit in the last place gave another mesh, and numpy's AVX-512 kernels gave 648 nodes
#: where its AVX2 ones gave 643, the closed coaptation length 7.73 against 7.84 mm (README,
#: "The open valve"). Rounded, the inputs are the same bits on every machine unless one
#: lies within roundoff of a grid line (about 1e-13 / 1e-6 per coordinate)
SNAP = 2.0**-20


@dataclass
class ValveMesh(SurfaceMesh):
    """An open mitral valve: a :class:`SurfaceMesh` with the subvalvular landmarks.

    Every array below is the same on all ranks (global, not distributed).

    Attributes:
        papillary_tips: (P, 3) chordae origins on the papillary muscles, mm.
        papillary_muscle: (P,) index into :data:`MUSCLES` of each tip's muscle.
        insertion_points: (K, 3) chordae insertion points; each is a mesh vertex.
        insertion_leaflet: (K,) tag value (:data:`LEAFLETS`) of the leaflet it is on.
        insertion_family: (K,) ``"marginal"`` (a free-edge vertex), ``"strut"`` (anterior belly)
            or ``"basal"`` (posterior belly, near the annulus).
        insertion_muscle: (K,) muscle index (the muscle on the insertion's side of the
            anteroposterior midline).
        insertion_tip: (K,) index into ``papillary_tips``: the nearest tip of that muscle.
        insertion_closed: (K, 3) where each insertion sits in the designed closed valve (see
            ``closed_depth``); chordae rest lengths are measured to it.
        axis: unit annulus-plane normal, from ventricle to atrium (the cell normals' side).
        centre: annulus centroid (arc-length weighted), mm.
        frame: rows = unit anterior, commissural (toward the anterolateral commissure) and
            ``axis`` directions: the local frame of the module docstring.
        commissures: (2, 3) the anterolateral and posteromedial commissure points.
        annulus_curve: (M, 3) the (smoothed) annulus curve the mesh is built on, closed, in
            order of increasing ``s`` from the anterior midpoint.

    Tags (``names``): cells ``"anterior"`` (1) and ``"posterior"`` (2); edges ``"annulus"``,
    ``"free_edge_anterior"``, ``"free_edge_posterior"``. The cross product of the cell
    tangents, cross(dX/dxi1, dX/dxi2), points from the ventricle to the atrium in every cell.
    """

    papillary_tips: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    papillary_muscle: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    insertion_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    insertion_leaflet: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    insertion_family: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype="<U8"))
    insertion_muscle: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    insertion_tip: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    insertion_closed: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    frame: np.ndarray = field(default_factory=lambda: np.eye(3))
    commissures: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    annulus_curve: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def along_leaflet(self, points: np.ndarray, leaflet: str) -> np.ndarray:
        """Position of points of a leaflet along it: the arc length of the annulus, from the
        posteromedial (0) to the anterolateral (1) commissure through the leaflet's middle, of
        the annulus point in the same direction from the axis (seen from the atrium).
        Carpentier's segments A1/P1, A2/P2, A3/P3 are its anterolateral, middle and
        posteromedial thirds."""
        loop = np.asarray(self.annulus_curve, dtype=float)
        ring = (loop - self.centre) @ self.frame.T
        seg = np.linalg.norm(np.roll(ring, -1, axis=0) - ring, axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)[:-1]])           # arc length of each vertex
        ang_ring = np.arctan2(ring[:, 1], ring[:, 0])

        def arc(p):
            local = (np.asarray(p, dtype=float).reshape(-1, 3) - self.centre) @ self.frame.T
            a = np.arctan2(local[:, 1], local[:, 0])
            d = np.abs(np.angle(np.exp(1j * (a[:, None] - ang_ring[None, :]))))
            return s[np.argmin(d, axis=1)]

        total = float(seg.sum())
        s_al, s_pm = arc(self.commissures)
        x = arc(points)
        mid = arc(self.centre + (1.0 if leaflet == "anterior" else -1.0) * self.frame[0])[0]
        # the way from the posteromedial commissure through the middle (the loop runs
        # counter-clockwise about the axis, from the anterior midpoint)
        fwd = (mid - s_pm) % total <= (s_al - s_pm) % total
        span = (s_al - s_pm) % total if fwd else (s_pm - s_al) % total
        start = s_pm if fwd else s_al
        # signed arc length from the leaflet's middle (never half the loop away), so that
        # points just beyond a commissure come out just outside [0, 1]
        centre = (start + 0.5 * span) % total
        off = (x - centre + 0.5 * total) % total - 0.5 * total
        return 0.5 + (off if fwd else -off) / span

    def annulus_nodes(self) -> np.ndarray:
        """(n, 3) reference coordinates of the annulus nodes, every rank's, in order along
        ``annulus_curve`` (from the anterior midpoint, counter-clockwise about the axis seen
        from the atrium): e.g. to write a target loop for ``[annulus] target``. Collective."""
        from scipy.spatial import cKDTree

        from dolfinx import cpp

        msh = self.mesh
        geo = cpp.mesh.entities_to_geometry(_cpp_mesh(msh), 1, self.facets("annulus"), False)
        parts = msh.comm.allgather(msh.geometry.x[np.unique(geo.ravel())])
        pts = np.concatenate(parts)
        scale = 1e-9 * (1.0 + float(np.abs(pts).max(initial=0.0)))
        _, first = np.unique(np.round(pts / scale).astype(np.int64), axis=0, return_index=True)
        pts = pts[np.sort(first)]
        curve = np.asarray(self.annulus_curve, dtype=float)
        idx = cKDTree(curve).query(pts)[1]
        return pts[np.argsort(idx, kind="stable")]

    def free_edge_nodes(self, leaflet: str) -> np.ndarray:
        """(n, 3) reference coordinates of a leaflet's free-edge nodes, every rank's, in order
        of their position along the leaflet (:meth:`along_leaflet`). Collective."""
        from dolfinx import cpp

        msh = self.mesh
        geo = cpp.mesh.entities_to_geometry(_cpp_mesh(msh), 1,
                                            self.facets(f"free_edge_{leaflet}"), False)
        pts = np.concatenate(msh.comm.allgather(msh.geometry.x[np.unique(geo.ravel())]))
        scale = 1e-9 * (1.0 + float(np.abs(pts).max(initial=0.0)))
        _, first = np.unique(np.round(pts / scale).astype(np.int64), axis=0, return_index=True)
        pts = pts[np.sort(first)]
        return pts[np.argsort(self.along_leaflet(pts, leaflet), kind="stable")]

    def insertions(self, family: str | None = None, leaflet: str | None = None) -> np.ndarray:
        """Indices (into ``insertion_points``) of one family and/or one leaflet."""
        keep = np.ones(len(self.insertion_points), dtype=bool)
        if family is not None:
            keep &= self.insertion_family == family
        if leaflet is not None:
            keep &= self.insertion_leaflet == LEAFLETS[leaflet]
        return np.flatnonzero(keep)


def valve(comm, *, ap_diameter: float = 28.0, commissural_diameter: float = 37.0,
          saddle_height: float = 6.0, anterior_height: float = 24.0,
          posterior_height: float = 13.0, anterior_share: float = 150.0 / 360.0,
          commissure_height: float = 6.0,
          anterior_angle: float = 20.0, posterior_angle: float = 25.0,
          papillary_depth: float = 23.5,
          papillary_position: Sequence[float] = (0.25, 0.75),
          size: float = 1.0, free_edge_size: float = 0.5, refine_distance: float = 5.0,
          chordae_spacing: float = 2.5, coaptation_offset: float = 0.3,
          closed_depth: float = 13.0,
          strut_points: Sequence[Sequence[float]] = ((0.3, 0.6), (0.7, 0.6)),
          basal_points: Sequence[Sequence[float]] = ((0.25, 0.3), (0.5, 0.3), (0.75, 0.3)),
          annulus: np.ndarray | None = None, papillary: np.ndarray | None = None,
          anterior_direction: Sequence[float] | None = None,
          annulus_modes: int = 16, ruling_smoothing: float = 4.0, refine: int = 0) -> ValveMesh:
    """The open mitral valve: two leaflets hanging from the annulus toward the papillary
    muscles (see the module docstring for the construction).

    Defaults are the healthy adult numbers of ``/work/shared/data/README.md``.

    Args:
        comm: MPI communicator (gmsh runs on its rank 0).
        ap_diameter: anteroposterior annulus diameter, mm (parametric annulus only).
        commissural_diameter: commissural annulus diameter, mm (parametric annulus only).
        saddle_height: annulus height, highest minus lowest point, mm (parametric only).
        anterior_height: anterior leaflet height at its middle, annulus to free edge, mm.
        posterior_height: posterior leaflet height at its middle, mm.
        anterior_share: fraction of the annulus length taken by the anterior leaflet.
        commissure_height: height of the leaflet curtain at the commissures (the ruling the
            two leaflets share), mm (at most 3/4 of the shorter leaflet's height).
        anterior_angle: inward tilt of the anterior leaflet from the axis, degrees (0: hangs
            straight down; larger closes the funnel).
        posterior_angle: inward tilt of the posterior leaflet, degrees.
        papillary_depth: default tips: depth below the annulus plane, mm.
        papillary_position: default tips: their position in the annulus plane as fractions
            of the anterior (positive) or posterior (negative) half of the anteroposterior
            extent and of the half commissural extent, one tip on each side: by default about
            4 mm inside the commissures, a little anterior of the centre. (The patient tips of
            ``data/kaiser_normal1`` sit further out and posterior, at about (-0.8, 0.9); with
            the chordae designed as here the anterior leaflet then billows 8 mm into the
            atrium and covers 80 % of the orifice, README.)
        size: target edge length, mm.
        free_edge_size: edge length at the free edges, mm (graded to ``size`` over
            ``refine_distance``).
        refine_distance: distance from the free edge over which the size grows, mm.
        chordae_spacing: marginal insertions: about one free-edge vertex per this arc length,
            mm, and one at each commissural notch.
        coaptation_offset: designed closed valve: how far the coaptation line lies toward
            the posterior annulus at the middle, as a fraction of the distance from the
            commissures' chord to the posterior annulus.
        closed_depth: designed closed valve: depth of the free edges at the middle below the
            commissures' chord, mm. The chordae are just taut when their insertions sit
            there (rest length = distance from the tip). With 13 mm the built-in valve
            (``mvfem demo``: these defaults with a 23 mm anterior leaflet) closes with a
            tenting height of 5.2 mm and a coaptation length of 7.8 mm (healthy: 5 +- 0.7
            and 3-8 mm, data README); measured at 12, 13.5 and 15 mm on the 24 mm leaflet:
            tenting 3.9, 5.8, 6.4 mm, coaptation 8.4, 8.0, 7.6 mm (README).
        strut_points: anterior strut insertions as ``(tau, r)``: fraction across the leaflet
            (from the posteromedial commissure) and fraction of the local height from the
            annulus.
        basal_points: posterior basal insertions as ``(tau, r)``.
        annulus: optional patient annulus, (N, 3) ordered closed loop, any frame (e.g. image
            coordinates), mm; overrides the three annulus dimensions.
        papillary: optional papillary tips, (P, 3), same frame as ``annulus``; their side of
            the annulus plane is the ventricle. Without it the tips are placed as by default
            (and, for a patient annulus, the ventricle is taken on the side about which the
            loop turns clockwise).
        anterior_direction: optional vector (in the frame of ``annulus``) from the annulus
            centre toward the anterior annulus. Without it the anterior side is the flatter
            side of the loop (the straight border of the D-shaped annulus), i.e. the one
            nearer the commissural axis.
        annulus_modes: Fourier modes kept when smoothing a patient annulus.
        ruling_smoothing: the in-plane direction of the rulings is the annulus's inward normal
            smoothed by a Gaussian of this standard deviation along the annulus, mm; it keeps
            the rulings from crossing where the annulus turns sharply (a D-shaped patient
            annulus's corners).
        refine: uniform refinements of the mesh after the chordae insertions are placed: each
            splits every triangle into four at its edges' midpoints, placed on the leaflets'
            ruled surfaces (so ``size`` 2 refined twice has the edge lengths of ``size`` 0.5,
            16x the cells). The insertions and the tagged curves are the unrefined mesh's, so
            the levels are nested meshes of one valve (``mesh.refine``, README "Nested
            levels").

    Returns:
        A :class:`ValveMesh`.

    Raises:
        ValueError: on invalid arguments (on every rank).
    """
    params = dict(ap_diameter=ap_diameter, commissural_diameter=commissural_diameter,
                  saddle_height=saddle_height, anterior_height=anterior_height,
                  posterior_height=posterior_height, anterior_share=anterior_share,
                  commissure_height=commissure_height,
                  anterior_angle=anterior_angle, posterior_angle=posterior_angle,
                  papillary_depth=papillary_depth,
                  size=size, free_edge_size=free_edge_size, refine_distance=refine_distance,
                  chordae_spacing=chordae_spacing, annulus_modes=annulus_modes,
                  coaptation_offset=coaptation_offset, closed_depth=closed_depth,
                  ruling_smoothing=ruling_smoothing, refine=refine)
    params = {k: (int(v) if k in ("annulus_modes", "refine") else float(v))
              for k, v in params.items()}
    params["papillary_position"] = [float(a) for a in papillary_position]
    params["strut_points"] = [[float(a) for a in p] for p in strut_points]
    params["basal_points"] = [[float(a) for a in p] for p in basal_points]

    _check(params)  # on every rank: the same ValueError everywhere
    # bad input data (a ValueError on rank 0) is a ValueError on every rank
    result = _root_or_error(comm, lambda: _build_on_root(params, annulus, papillary,
                                                         anterior_direction))
    if comm.rank == 0:
        arrays, extras = result
    else:
        arrays, extras = (None,) * 5, None
    extras = comm.bcast(extras, root=0)
    msh, cell_tags, facet_tags = mesh_from_arrays(comm, *arrays)
    return ValveMesh(msh, cell_tags, facet_tags, dict(_GROUPS), extras.pop("info"), **extras)


def write_valve(path: str | os.PathLike, valve: ValveMesh) -> None:
    """Write the valve (its current geometry) as an imported-valve file (CONTRACT.md): cell data
    ``leaflet`` (1 anterior, 2 posterior) and point data ``annulus`` (1 on annulus nodes).

    Collective over the mesh's communicator; rank 0 writes. Any meshio format (.vtu, .xdmf, ...).
    """
    from dolfinx import cpp

    msh = valve.mesh
    comm = msh.comm
    tdim = msh.topology.dim
    nloc = msh.topology.index_map(tdim).size_local
    dofs = msh.geometry.dofmap.array.reshape(-1, 3)[:nloc]
    gid = np.asarray(msh.geometry.input_global_indices, dtype=np.int64)
    leaflet = np.zeros(nloc, dtype=np.int32)
    owned = valve.cell_tags.indices < nloc
    leaflet[valve.cell_tags.indices[owned]] = valve.cell_tags.values[owned]
    facets = valve.facets("annulus")
    ann = cpp.mesh.entities_to_geometry(_cpp_mesh(msh), tdim - 1, facets, False).ravel()

    parts = comm.gather((gid[dofs], msh.geometry.x[dofs], leaflet, gid[ann]), root=0)
    if comm.rank != 0:
        return
    ids = np.concatenate([p[0] for p in parts])
    xyz = np.concatenate([p[1] for p in parts]).reshape(-1, 3)
    used, first, tri = np.unique(ids.ravel(), return_index=True, return_inverse=True)
    points = xyz[first]
    on_annulus = np.isin(used, np.concatenate([p[3] for p in parts])).astype(np.int32)
    write_surface(path, points, tri.reshape(-1, 3),
                  point_data={"annulus": on_annulus},
                  cell_data={"leaflet": np.concatenate([p[2] for p in parts])})


# --- construction on rank 0 ------------------------------------------------------------------

#: the last gmsh mesh made in this process and its inputs: the nested levels of a refined
#: valve split the same gmsh mesh (0.45 s of gmsh a level on the demo, run once instead of
#: once a level); ``time_s.gmsh`` is 0 and ``gmsh_reused`` true where it was reused
_LAST_MESH: dict = {}


def _mesh_key(p: dict, annulus, papillary, anterior_direction) -> tuple:
    """What the gmsh mesh depends on: every parameter but ``refine`` and the given points."""
    import json

    def arr(a):
        return None if a is None else np.asarray(a, dtype=float).tobytes()

    params = json.dumps({k: v for k, v in p.items() if k != "refine"}, sort_keys=True,
                        default=lambda v: np.asarray(v).tolist())
    return params, arr(annulus), arr(papillary), arr(anterior_direction)


def _build_on_root(p: dict, annulus, papillary, anterior_direction):
    t_start = time.perf_counter()
    if annulus is None:
        loop, origin, frame, source = _ellipse(p), np.zeros(3), np.eye(3), "parametric"
        if papillary is not None:
            papillary = _points(papillary, "papillary")
    else:
        annulus = _points(annulus, "annulus")
        papillary = None if papillary is None else _points(papillary, "papillary")
        loop, origin, frame = _patient_frame(annulus, papillary, anterior_direction,
                                             p["annulus_modes"])
        source = "patient"
    curve = _Curve(loop, p["ruling_smoothing"])
    perimeter = curve.length
    fit = 0.0
    if annulus is not None:  # how far the given points are from the smoothed curve
        from scipy.spatial import cKDTree

        fit = float(cKDTree(curve.x).query((annulus - origin) @ frame.T)[0].max())
    s_c = 0.5 * p["anterior_share"]
    leaflets = _leaflets(curve, p)

    # papillary tips in the local frame, their muscles
    if papillary is None:
        fx, fy = p["papillary_position"]
        x_half = -curve.x[:, 0].min() if fx < 0 else curve.x[:, 0].max()
        tips = np.array([[fx * x_half, fy * curve.x[:, 1].max(), -p["papillary_depth"]],
                         [fx * x_half, fy * curve.x[:, 1].min(), -p["papillary_depth"]]])
        muscle = np.array([0, 1], dtype=np.int32)
    else:
        tips = (papillary - origin) @ frame.T
        mid = 0.5 * (tips[:, 1].min() + tips[:, 1].max())
        muscle = np.where(tips[:, 1] >= mid, 0, 1).astype(np.int32)
        if len(tips) == 1:
            muscle = np.array([0 if tips[0, 1] >= 0 else 1], dtype=np.int32)

    t_geom = time.perf_counter()
    key = _mesh_key(p, annulus, papillary, anterior_direction)
    if _LAST_MESH.get("key") == key:
        arrays = tuple(a.copy() for a in _LAST_MESH["arrays"])
        stats = {**_LAST_MESH["stats"], "gmsh_s": 0.0, "reused": True}
    else:
        arrays, stats = _mesh(leaflets, p)
        _LAST_MESH.update(key=key, arrays=tuple(a.copy() for a in arrays), stats=stats)
    points, cells, cell_values, edges, edge_values = arrays
    t_mesh = time.perf_counter()

    ins = _insertions(points, cells, cell_values, edges, edge_values, leaflets, tips, muscle, p)
    base = {"cells": int(len(cells)), "vertices": int(len(points))}
    if p["refine"]:
        points, cells, cell_values, edges, edge_values, off = _refine(
            points, cells, cell_values, edges, edge_values, leaflets, p["refine"])
        base["surface_distance_mm"] = off
    t_refine = time.perf_counter()

    # local frame -> given frame
    to_global = lambda x: origin + np.asarray(x) @ frame  # noqa: E731
    points = to_global(points)
    centre = to_global(curve.centroid)
    axis = frame[2].copy()
    # (rounded as the mesh's nodes are: the commissures are two of them)
    comm_pts = to_global(_snap(np.array([curve.point(s_c), curve.point(-s_c)])))
    q = _quality(points, cells)
    areas = {name: float(q["areas"][cell_values == v].sum()) for name, v in LEAFLETS.items()}

    info = {"generator": "valve", "annulus_source": source, **p,
            "anterior_direction": None if anterior_direction is None
            else [float(v) for v in anterior_direction],
            "annulus_points_given": 0 if annulus is None else int(len(annulus)),
            "papillary_given": 0 if papillary is None else int(len(papillary)),
            "frame_origin": origin.tolist(), "frame": frame.tolist(),
            "annulus_perimeter_mm": float(perimeter), "annulus_fit_max_mm": fit,
            "annulus_saddle_height_mm": float(np.ptp(curve.x[:, 2])),
            "commissure_s": [float(s_c), float(-s_c)],
            "leaflets": {name: lf.describe() for name, lf in leaflets.items()},
            "leaflet_area_mm2": areas,
            "cells": int(len(cells)), "vertices": int(len(points)),
            "min_angle_deg": q["min_angle"], "max_angle_deg": q["max_angle"],
            "min_quality": q["min_quality"], "mean_quality": q["mean_quality"],
            "cells_min_angle_below_30deg": q["below30"],
            "edge_length_mm": q["edges"],
            "cells_flipped": stats["flipped"], "unrefined": base,
            "gmsh_reused": bool(stats.get("reused", False)),
            "time_s": {"geometry": t_geom - t_start, "gmsh": stats["gmsh_s"],
                       "refine": t_refine - t_mesh, "total_root": time.perf_counter() - t_start}}
    extras = {"info": info,
              "papillary_tips": to_global(tips), "papillary_muscle": muscle,
              "insertion_points": to_global(ins["points"]),
              "insertion_leaflet": ins["leaflet"], "insertion_family": ins["family"],
              "insertion_muscle": ins["muscle"], "insertion_tip": ins["tip"],
              "insertion_closed": to_global(ins["closed"]),
              "axis": axis, "centre": centre, "frame": frame.copy(), "commissures": comm_pts,
              "annulus_curve": to_global(curve.x)}
    logger.info("valve: %d cells, %d vertices, min angle %.1f deg, %.2f s", len(cells),
                len(points), q["min_angle"], time.perf_counter() - t_start)
    return (points, cells, cell_values, edges, edge_values), extras


def _check(p: dict) -> None:
    for k in ("ap_diameter", "commissural_diameter", "anterior_height", "posterior_height",
              "commissure_height", "size", "free_edge_size", "refine_distance",
              "chordae_spacing", "papillary_depth"):
        if not p[k] > 0:
            raise ValueError(f"valve: {k} must be positive, got {p[k]}")
    for k in ("saddle_height", "ruling_smoothing"):
        if not p[k] >= 0:
            raise ValueError(f"valve: {k} must be >= 0, got {p[k]}")
    if not 0.1 <= p["anterior_share"] <= 0.9:
        raise ValueError(f"valve: anterior_share must be in [0.1, 0.9], got {p['anterior_share']}")
    if p["commissure_height"] > 0.75 * min(p["anterior_height"], p["posterior_height"]):
        raise ValueError("valve: commissure_height must not exceed 3/4 of the shorter leaflet's "
                         f"height, got {p['commissure_height']}")
    for k in ("anterior_angle", "posterior_angle"):
        if not 0.0 <= p[k] < 80.0:
            raise ValueError(f"valve: {k} must be in [0, 80) degrees, got {p[k]}")
    if p["free_edge_size"] > p["size"]:
        raise ValueError("valve: free_edge_size must not exceed size")
    if not 0 <= p["refine"] <= 4:
        raise ValueError(f"valve: refine must be 0 to 4 (each refinement is 4x the cells), "
                         f"got {p['refine']}")
    if p["annulus_modes"] < 2:
        raise ValueError("valve: annulus_modes must be >= 2")
    pp = p["papillary_position"]
    if len(pp) != 2 or not all(-1.5 <= a <= 1.5 for a in pp):
        raise ValueError(f"valve: papillary_position must be two fractions in [-1.5, 1.5], "
                         f"got {pp}")
    for k in ("strut_points", "basal_points"):
        for tr in p[k]:
            if len(tr) != 2 or not (0 < tr[0] < 1 and 0 < tr[1] <= 1):
                raise ValueError(f"valve: {k} entries must be (tau, r) with 0 < tau < 1, "
                                 f"0 < r <= 1, got {tr}")


def _points(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or len(a) < 1 or not np.all(np.isfinite(a)):
        raise ValueError(f"valve: {name} must be a finite (N, 3) array, got shape {a.shape}")
    return a


def _ellipse(p: dict) -> np.ndarray:
    t = np.linspace(0.0, 2 * np.pi, 8 * _DENSE, endpoint=False)
    return np.column_stack([0.5 * p["ap_diameter"] * np.cos(t),
                            0.5 * p["commissural_diameter"] * np.sin(t),
                            0.5 * p["saddle_height"] * np.cos(2 * t)])


def _patient_frame(loop: np.ndarray, papillary, anterior_direction, modes: int):
    """Plane, centre and axes of a patient annulus; its smoothed loop in the local frame."""
    if len(loop) < 8:
        raise ValueError(f"valve: annulus needs at least 8 points, got {len(loop)}")
    if np.linalg.norm(loop[0] - loop[-1]) < 1e-9 * np.ptp(loop):
        loop = loop[:-1]
    seg = np.linalg.norm(np.roll(loop, -1, axis=0) - loop, axis=1)
    mids = 0.5 * (loop + np.roll(loop, -1, axis=0))
    c = (mids * seg[:, None]).sum(0) / seg.sum()
    _, sv, vt = np.linalg.svd(loop - c, full_matrices=False)
    if sv[1] < 1e-6 * sv[0]:
        raise ValueError("valve: annulus points are collinear")
    e2, n = vt[0], vt[2]  # major axis: commissural; least: plane normal
    if papillary is not None:
        if (papillary.mean(0) - c) @ n > 0:
            n = -n
    else:
        # no papillary tips: the loop turns counter-clockwise about the atrial normal
        xy = (loop - c) @ np.array([vt[0], vt[1]]).T
        area = 0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])
        if area * (np.cross(vt[0], vt[1]) @ n) < 0:
            n = -n
        logger.warning("valve: patient annulus without papillary tips; ventricle side taken "
                       "from the loop's orientation")
    e1 = np.cross(e2, n)
    if anterior_direction is not None:
        a = np.asarray(anterior_direction, dtype=float)
        if a.shape != (3,) or abs(a @ e1) < 1e-12:
            raise ValueError("valve: anterior_direction must be a 3-vector not along the "
                             "commissural axis")
        sign = np.sign(a @ e1)
    else:
        x = (loop - c) @ e1
        sign = 1.0 if x.max() < -x.min() else -1.0  # the flatter (nearer) side is anterior
        if papillary is not None and ((papillary.mean(0) - c) @ e1) * sign > 0:
            logger.warning("valve: the papillary tips lie on the side taken as anterior")
    e1, e2 = sign * e1, sign * e2
    frame = np.array([e1, e2, n])
    local = (loop - c) @ frame.T
    # counter-clockwise about +z
    area = 0.5 * np.sum(local[:, 0] * np.roll(local[:, 1], -1)
                        - np.roll(local[:, 0], -1) * local[:, 1])
    if area < 0:
        local = local[::-1]
    return _fourier(local, modes), c, frame


def _fourier(loop: np.ndarray, modes: int) -> np.ndarray:
    """Least-squares truncated Fourier series of a closed loop in its arc length; resampled."""
    seg = np.linalg.norm(np.roll(loop, -1, axis=0) - loop, axis=1)
    u = np.concatenate([[0.0], np.cumsum(seg)[:-1]]) / seg.sum()
    modes = min(modes, (len(loop) - 1) // 2)
    k = np.arange(1, modes + 1)

    def basis(v):
        return np.column_stack([np.ones_like(v), np.cos(2 * np.pi * np.outer(v, k)),
                                np.sin(2 * np.pi * np.outer(v, k))])

    coef, *_ = np.linalg.lstsq(basis(u), loop, rcond=None)
    return basis(np.linspace(0.0, 1.0, 8 * _DENSE, endpoint=False)) @ coef


def _snap(a: np.ndarray) -> np.ndarray:
    """``a`` rounded to the :data:`SNAP` grid (a power of two: the scaling is exact)."""
    return np.round(np.asarray(a, dtype=float) / SNAP) * SNAP


class _Curve:
    """A closed curve in the local frame, by normalised arc length ``s`` (period 1), ``s = 0``
    where it crosses the +x half-axis, running counter-clockwise about +z."""

    def __init__(self, loop: np.ndarray, smoothing: float = 0.0):
        closed = np.vstack([loop, loop[:1]])
        seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
        u = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(u[-1])
        # start where the polar angle changes sign at x > 0
        ang = np.arctan2(loop[:, 1], loop[:, 0])
        cross = np.flatnonzero((ang <= 0) & (np.roll(ang, -1) > 0) & (loop[:, 0] > 0))
        if len(cross) != 1:
            raise ValueError("valve: the annulus must wind once around its centre "
                             "(it crosses the anterior half-axis "
                             f"{len(cross)} times)")
        i = cross[0]
        frac = -ang[i] / (ang[(i + 1) % len(ang)] - ang[i])
        u0 = u[i] + frac * seg[i]
        s = np.linspace(0.0, 1.0, _DENSE, endpoint=False)
        target = (u0 + s * self.length) % self.length
        self.x = np.column_stack([np.interp(target, u, closed[:, j]) for j in range(3)])
        self.s = s
        h = 1.0 / _DENSE
        t = (np.roll(self.x, -1, axis=0) - np.roll(self.x, 1, axis=0)) / (2 * h * self.length)
        self.t = t / np.linalg.norm(t, axis=1)[:, None]
        tp = self.t * np.array([1.0, 1.0, 0.0])
        tp /= np.linalg.norm(tp, axis=1)[:, None]
        self.n_in = np.cross(np.array([0.0, 0.0, 1.0]), tp)
        if smoothing > 0:  # periodic Gaussian filter, standard deviation `smoothing` mm
            k = np.fft.rfftfreq(_DENSE, d=self.length / _DENSE)
            gain = np.exp(-2.0 * (np.pi * smoothing * k) ** 2)
            self.n_in = np.fft.irfft(np.fft.rfft(self.n_in, axis=0) * gain[:, None], n=_DENSE,
                                     axis=0)
            self.n_in /= np.linalg.norm(self.n_in, axis=1)[:, None]
        mids = 0.5 * (self.x + np.roll(self.x, -1, axis=0))
        self.centroid = mids.mean(0)

    def _interp(self, data, s):
        s = np.asarray(s, dtype=float) % 1.0
        ss = np.concatenate([self.s, [1.0]])
        dd = np.vstack([data, data[:1]])
        return np.stack([np.interp(s, ss, dd[:, j]) for j in range(3)], axis=-1)

    def point(self, s):
        return self._interp(self.x, s)

    def tangent(self, s):
        t = self._interp(self.t, s)
        return t / np.linalg.norm(t, axis=-1, keepdims=True)

    def inward(self, s):
        n = self._interp(self.n_in, s)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)


class _Leaflet:
    """The ruled surface of one leaflet over the annulus arc ``s0 <= s <= s1``."""

    def __init__(self, name: str, curve: _Curve, s0: float, s1: float, p: dict):
        self.name, self.curve, self.s0, self.s1 = name, curve, s0, s1
        self.arc = (s1 - s0) * curve.length
        self.height = p[f"{name}_height"]
        self.alpha = math.radians(p[f"{name}_angle"])
        # both leaflets meet the commissural ruling with the same tilt
        self.alpha_c = math.radians(0.5 * (p["anterior_angle"] + p["posterior_angle"]))
        self.q = _PROFILE[name]
        self.hc = p["commissure_height"]

    def describe(self) -> dict:
        return {"arc_length_mm": float(self.arc), "height_mm": float(self.height),
                "commissure_height_mm": float(self.hc),
                "tilt_deg": math.degrees(self.alpha), "profile_q": self.q,
                "mean_height_mm": float(self.heights(np.linspace(0, 1, 2001)).mean())}

    def s(self, tau):
        return self.s0 + np.asarray(tau) * (self.s1 - self.s0)

    def _g(self, tau):
        tau = np.clip(np.asarray(tau, dtype=float), 0.0, 1.0)
        # sin(pi min(tau, 1 - tau)): exactly 0 at both ends, so neighbouring leaflets' end
        # rulings are sampled alike
        return 1.0 - (1.0 - np.sin(np.pi * np.minimum(tau, 1.0 - tau))) ** self.q

    def heights(self, tau):
        return self.hc + (self.height - self.hc) * self._g(tau)

    def direction(self, tau):
        n_in = self.curve.inward(self.s(tau))
        alpha = (self.alpha_c + (self.alpha - self.alpha_c) * self._g(tau))[..., None]
        return -np.cos(alpha) * np.array([0.0, 0.0, 1.0]) + np.sin(alpha) * n_in

    def point(self, tau, r):
        """X(tau, r) = A + r H d."""
        tau, r = np.broadcast_arrays(np.asarray(tau, float), np.asarray(r, float))
        return (self.curve.point(self.s(tau)) + (r * self.heights(tau))[..., None]
                * self.direction(tau))

    def sample(self, h: float):
        """A fine triangulation of the leaflet, edge length about ``h``: Delaunay in the
        developed coordinates (arc length along the annulus, distance along the ruling),
        mapped onto the ruled surface.

        Returns:
            ``(X, tri, annulus, free, ends)``: points (n, 3); triangles (m, 3) oriented along
            cross(dX/dtau, dX/dr) (the atrial side); the annulus and free-edge vertices in order
            of increasing tau; the two commissural rulings (at tau = 0 and tau = 1), each from
            the annulus to the free edge. The curves share their end vertices (``annulus[0] ==
            ends[0][0]``, ``free[0] == ends[0][-1]``, ...). The rulings are sampled the same
            way for every leaflet, so that neighbouring leaflets' rulings coincide.
        """
        from scipy.spatial import Delaunay

        nt = max(int(math.ceil(self.arc / h)), 16)
        tau = np.linspace(0.0, 1.0, nt + 1)
        H = self.heights(tau)
        xi, eta, kind, col = [], [], [], []  # kind: 0 interior, 1 annulus, 2 free edge
        for i, (t, hh) in enumerate(zip(tau, H)):
            m = max(int(math.ceil(hh / h)), 1)
            if i % 2 and i != nt:  # stagger alternate columns: near-equilateral triangles
                rr = np.concatenate([[0.0], (np.arange(m) + 0.5) / m, [1.0]])
            else:
                rr = np.linspace(0.0, 1.0, m + 1)
            xi += [t] * len(rr)
            eta += list(rr * hh)
            kind += [1] + [0] * (len(rr) - 2) + [2]
            col += [i] * len(rr)
        xi, eta, kind, col = np.array(xi), np.array(eta), np.array(kind), np.array(col)
        plane = _snap(np.column_stack([xi * self.arc, eta]))
        tri = Delaunay(plane).simplices
        # keep triangles inside the domain eta <= H(xi) (drop hull triangles above the edge)
        cen = plane[tri].mean(axis=1)
        inside = cen[:, 1] <= np.interp(cen[:, 0], tau * self.arc, H) + 1e-9 * self.height
        tri = tri[inside]
        v = plane[tri]
        det = ((v[:, 1, 0] - v[:, 0, 0]) * (v[:, 2, 1] - v[:, 0, 1])
               - (v[:, 1, 1] - v[:, 0, 1]) * (v[:, 2, 0] - v[:, 0, 0]))
        tri[det < 0] = tri[det < 0][:, [0, 2, 1]]  # counter-clockwise in the plane: dtau x dr
        tri = tri[np.abs(det) > 1e-9 * h * h]  # no slivers of collinear edge points
        hh = np.interp(xi, tau, H)
        r = np.divide(eta, hh, out=np.zeros_like(eta), where=hh > 0)
        X = _snap(self.point(xi, r))
        # the map (tau, r) -> X must not fold: rulings that cross flip the 3-D normal
        tc = xi[tri].mean(axis=1)
        n3 = np.cross(X[tri[:, 1]] - X[tri[:, 0]], X[tri[:, 2]] - X[tri[:, 0]])
        ref = np.cross(self.curve.tangent(self.s(tc)), self.direction(tc))
        if np.any(np.einsum("ij,ij->i", n3, ref) <= 0):
            raise ValueError(f"valve: the {self.name} leaflet folds (its rulings cross where "
                             "the annulus turns sharply): lower its height or tilt, or raise "
                             "ruling_smoothing")
        order = np.argsort(xi, kind="stable")
        annulus = order[kind[order] == 1]
        free = order[kind[order] == 2]
        ends = tuple(np.flatnonzero(col == c)[np.argsort(eta[col == c])] for c in (0, nt))
        return X, tri, annulus, free, ends


# --- meshing ---------------------------------------------------------------------------------

def _mesh(leaflets: dict, p: dict):
    """Discrete gmsh model of the fine ruled surfaces -> reparametrise -> remesh."""
    t0 = time.perf_counter()
    with _gmsh_model("valve") as gmsh:
        factor = gmsh.option.getNumber("Mesh.MeshSizeFactor")
        try:
            arrays, ref_centroids, ref_normals = _remesh(gmsh, leaflets, p)
        finally:
            gmsh.option.setNumber("Mesh.MeshSizeFactor", factor)
    gmsh_s = time.perf_counter() - t0

    from scipy.spatial import cKDTree

    tree = cKDTree(np.concatenate(ref_centroids))
    normals = np.concatenate(ref_normals)
    normals /= np.linalg.norm(normals, axis=1)[:, None]

    def atrial(xc):
        return normals[tree.query(xc)[1]]

    flipped = _orient(arrays[0], arrays[1], atrial, 1)
    return arrays, {"flipped": flipped, "gmsh_s": gmsh_s}


def _remesh(gmsh, leaflets: dict, p: dict):
    """Build and mesh the model in the current gmsh session; return the arrays of
    :func:`generators._extract` and the fine triangles' centroids and atrial normals."""
    from .generators import _extract, _set_options

    h_fine = max(0.5 * min(p["free_edge_size"], p["size"]), 0.25)
    ref_centroids, ref_normals = [], []
    model = gmsh.model
    # points: 1, 2 the anterolateral (s = +share/2) and posteromedial (s = -share/2)
    # commissures on the annulus, 3, 4 the feet of their rulings on the free edge
    fine = {name: lf.sample(h_fine) for name, lf in leaflets.items()}
    next_tag = [1]

    def new_nodes(n):
        tags = np.arange(next_tag[0], next_tag[0] + n)
        next_tag[0] += n
        return tags

    # curves: annulus and free edge of each leaflet from its tau = 0 end to its tau = 1 end,
    # and the two commissural rulings (annulus -> free edge), shared by both leaflets
    curve_tag = {"anterior": (1, 2), "posterior": (3, 4)}
    ruling_tag = {"al": 5, "pm": 6}
    corner = {"al": (1, 3), "pm": (2, 4)}       # (annulus point, free-edge point)
    surf_tag = {"anterior": 1, "posterior": 2}
    sides = {"anterior": ("pm", "al"), "posterior": ("al", "pm")}  # commissure at tau = 0, 1
    point_node: dict[int, int] = {}
    ruling_nodes: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # tags, coordinates
    for name in ("anterior", "posterior"):
        X, tri, ann, free, ends = fine[name]
        tag_of = np.zeros(len(X), dtype=np.int64)
        for side, line in zip(sides[name], ends):
            for ptag, v in zip(corner[side], (line[0], line[-1])):
                if ptag not in point_node:
                    model.addDiscreteEntity(0, ptag)
                    point_node[ptag] = int(new_nodes(1)[0])
                    model.mesh.addNodes(0, ptag, [point_node[ptag]], X[v])
                tag_of[v] = point_node[ptag]
            inner = line[1:-1]
            if side not in ruling_nodes:
                a, b = corner[side]
                model.addDiscreteEntity(1, ruling_tag[side], [a, b])
                tags = new_nodes(len(inner))
                model.mesh.addNodes(1, ruling_tag[side], tags, X[inner].ravel())
                ruling_nodes[side] = (tags, X[inner])
                lt = np.concatenate([[point_node[a]], tags, [point_node[b]]])
                model.mesh.addElementsByType(ruling_tag[side], 1, [],
                                             np.column_stack([lt[:-1], lt[1:]]).ravel())
            tags, xs = ruling_nodes[side]
            if len(xs) != len(inner) or (len(xs) and np.abs(xs - X[inner]).max() > 1e-9):
                raise RuntimeError("valve: the leaflets' commissural rulings do not coincide")
            tag_of[inner] = tags
        p0 = (corner[sides[name][0]], corner[sides[name][1]])
        ca, cf = curve_tag[name]
        for ctag, line, (a, b) in ((ca, ann, (p0[0][0], p0[1][0])),
                                   (cf, free, (p0[0][1], p0[1][1]))):
            model.addDiscreteEntity(1, ctag, [a, b])
            tags = new_nodes(len(line) - 2)
            model.mesh.addNodes(1, ctag, tags, X[line[1:-1]].ravel())
            tag_of[line[1:-1]] = tags
            lt = tag_of[line]
            model.mesh.addElementsByType(ctag, 1, [], np.column_stack([lt[:-1],
                                                                       lt[1:]]).ravel())
        model.addDiscreteEntity(2, surf_tag[name], [ca, ruling_tag[sides[name][1]], cf,
                                                    ruling_tag[sides[name][0]]])
        inner = np.flatnonzero(tag_of == 0)
        tag_of[inner] = new_nodes(len(inner))
        model.mesh.addNodes(2, surf_tag[name], tag_of[inner], X[inner].ravel())
        model.mesh.addElementsByType(surf_tag[name], 2, [], tag_of[tri].ravel())
        v0, v1, v2 = (X[tri[:, k]] for k in range(3))
        ref_centroids.append((v0 + v1 + v2) / 3.0)
        ref_normals.append(np.cross(v1 - v0, v2 - v0))

    model.mesh.createGeometry()
    field_ = model.mesh.field
    field_.add("Distance", 1)
    field_.setNumbers(1, "CurvesList", [curve_tag["anterior"][1], curve_tag["posterior"][1]])
    field_.setNumber(1, "NumPointsPerCurve", 2000)
    # gmsh 4.8 caps the size on these reparametrised discrete entities at 1 (whatever the
    # field or Mesh.MeshSizeMax say), but honours Mesh.MeshSizeFactor: sizes in units of
    # `size`, times the factor
    field_.add("Threshold", 2)
    field_.setNumber(2, "InField", 1)
    field_.setNumber(2, "SizeMin", p["free_edge_size"] / p["size"])
    field_.setNumber(2, "SizeMax", 1.0)
    field_.setNumber(2, "DistMin", 0.5 * p["free_edge_size"])
    field_.setNumber(2, "DistMax", p["refine_distance"])
    field_.setAsBackgroundMesh(2)
    _set_options(gmsh, {"Mesh.MeshSizeMin": p["free_edge_size"] / p["size"],
                        "Mesh.MeshSizeMax": 1.0, "Mesh.MeshSizeFromPoints": 0,
                        "Mesh.MeshSizeExtendFromBoundary": 0, "Mesh.Algorithm": 1,
                        "Mesh.MeshSizeFactor": p["size"]})
    for name, value in _GROUPS.items():
        dim, tags = {"anterior": (2, [1]), "posterior": (2, [2]),
                     "annulus": (1, [curve_tag["anterior"][0], curve_tag["posterior"][0]]),
                     "free_edge_anterior": (1, [curve_tag["anterior"][1]]),
                     "free_edge_posterior": (1, [curve_tag["posterior"][1]])}[name]
        model.addPhysicalGroup(dim, tags, value)
        model.setPhysicalName(dim, value, name)
    model.mesh.generate(2)
    return _extract(gmsh, 1), ref_centroids, ref_normals


# --- nested refinement -----------------------------------------------------------------------

def _refine(points, cells, cell_values, edges, edge_values, leaflets: dict, times: int):
    """``times`` 1-to-4 splits of the mesh (local frame), each new node on its leaflet's ruled
    surface at the mean of its edge's end nodes' surface coordinates ``(tau, r)`` (the free edge
    stays at ``r = 1``, the annulus at ``r = 0``). Returns the refined ``(points, cells,
    cell_values, edges, edge_values)`` and the largest distance of an unrefined node from its
    surface (the gmsh nodes lie on a finely sampled copy of it), mm."""
    from .refine import split, split_edges

    ann = np.unique(edges[edge_values == _GROUPS["annulus"]])
    free = np.unique(edges[np.isin(edge_values, [_GROUPS["free_edge_anterior"],
                                                 _GROUPS["free_edge_posterior"]])])
    coords, off = {}, 0.0  # tag value -> (n, 2) (tau, r) of the leaflet's nodes, else nan
    for name, lf in leaflets.items():
        v = LEAFLETS[name]
        nodes = np.unique(cells[cell_values == v])
        tr = np.full((len(points), 2), np.nan)
        tr[nodes], dist = _surface_coordinates(lf, points[nodes])
        off = max(off, float(dist.max(initial=0.0)))
        on = ~np.isnan(tr[:, 0])
        tr[np.intersect1d(ann, np.flatnonzero(on)), 1] = 0.0
        tr[np.intersect1d(free, np.flatnonzero(on)), 1] = 1.0
        coords[v] = tr
    e = np.concatenate([cells[:, [0, 1]], cells[:, [1, 2]], cells[:, [2, 0]]])
    shortest = float(np.linalg.norm(points[e[:, 0]] - points[e[:, 1]], axis=1).min())
    if not off < 0.25 * shortest:  # the inversion failed: new nodes would be misplaced
        raise RuntimeError(f"valve: refine: a mesh node lies {off:.3g} mm off its leaflet's "
                           f"surface (shortest edge {shortest:.3g} mm)")
    for _ in range(times):
        n, m = len(points), len(cells)
        pairs, children = split(cells, n)
        mids = children[3 * m:] - n  # each parent cell's three edges (the middle child)
        new = np.full((len(pairs), 3), np.nan)
        for name, lf in leaflets.items():
            v = LEAFLETS[name]
            mine = np.unique(mids[cell_values == v])  # this leaflet's edges
            tr = np.vstack([coords[v], np.full((len(pairs), 2), np.nan)])
            tr[n + mine] = 0.5 * (coords[v][pairs[mine, 0]] + coords[v][pairs[mine, 1]])
            coords[v] = tr
            todo = mine[np.isnan(new[mine, 0])]  # an edge of both (a commissural ruling): once
            new[todo] = lf.point(tr[n + todo, 0], tr[n + todo, 1])
        points = np.vstack([points, new])
        cells, cell_values = children, np.tile(cell_values, 4)
        edges, edge_values = split_edges(edges, pairs, n), np.tile(edge_values, 2)
    return points, cells, cell_values, edges, edge_values, off


def _leaflets(curve: "_Curve", p: dict) -> dict:
    """The two leaflets' ruled surfaces over the annulus ``curve`` (name -> :class:`_Leaflet`),
    the commissures at ``+-anterior_share / 2`` of its length."""
    s_c = 0.5 * p["anterior_share"]
    return {"anterior": _Leaflet("anterior", curve, -s_c, s_c, p),
            "posterior": _Leaflet("posterior", curve, s_c, 1.0 - s_c, p)}


def surface_distance(x: np.ndarray, **params) -> np.ndarray:
    """Distances (mm) of the points ``x`` (n, 3; the parametric valve's own frame) from the
    leaflets' ruled surfaces of the valve :func:`valve` makes with ``params`` (its defaults
    for the rest), by the inversion its refinement uses (:func:`_surface_coordinates`): how
    far a point is off the surface that the valve's meshes sample. A patient annulus has no
    such surface here: ``annulus`` or ``papillary`` is a ValueError."""
    import inspect

    p = {k: v.default for k, v in inspect.signature(valve).parameters.items()
         if v.default is not inspect.Parameter.empty}
    p.update(params)
    if p.get("annulus") is not None or p.get("papillary") is not None:
        raise ValueError("surface_distance: a patient annulus has no parametric surface")
    curve = _Curve(_ellipse(p), p["ruling_smoothing"])
    return np.min([_surface_coordinates(lf, x)[1] for lf in _leaflets(curve, p).values()],
                  axis=0)


def _surface_coordinates(lf: "_Leaflet", x: np.ndarray, iterations: int = 12):
    """``(tau, r)`` (n, 2) of the points ``x`` on the ruled surface of ``lf`` (the nearest point
    of a 401 x 101 grid over [0, 1]^2, then Gauss-Newton on the distance, kept in [0, 1]^2),
    and the points' distances to it."""
    from scipy.spatial import cKDTree

    tg, rg = (a.ravel() for a in np.meshgrid(np.linspace(0.0, 1.0, 401),
                                             np.linspace(0.0, 1.0, 101), indexing="ij"))
    i = cKDTree(lf.point(tg, rg)).query(x)[1]
    t, r = tg[i].copy(), rg[i].copy()
    eps = 1e-7
    for _ in range(iterations):
        res = x - lf.point(t, r)
        jt = (lf.point(t + eps, r) - lf.point(t - eps, r)) / (2 * eps)
        jr = (lf.point(t, r + eps) - lf.point(t, r - eps)) / (2 * eps)
        a, b, c = (np.einsum("ij,ij->i", p, q) for p, q in ((jt, jt), (jt, jr), (jr, jr)))
        f, g = np.einsum("ij,ij->i", jt, res), np.einsum("ij,ij->i", jr, res)
        det = a * c - b * b
        t = np.clip(t + (c * f - b * g) / det, 0.0, 1.0)
        r = np.clip(r + (a * g - b * f) / det, 0.0, 1.0)
    return np.column_stack([t, r]), np.linalg.norm(x - lf.point(t, r), axis=1)


# --- chordae insertions ----------------------------------------------------------------------

def _insertions(points, cells, cell_values, edges, edge_values, leaflets, tips, muscle, p):
    """Marginal (free-edge vertices, every ~chordae_spacing) and strut/basal (belly vertices)
    insertion points, in the local frame; each with its muscle (by side) and nearest tip."""
    out_pts, out_leaf, out_fam, out_closed = [], [], [], []
    boundary = np.unique(edges)
    closed = _closure_design(leaflets, p)
    for name, lf in leaflets.items():
        value = LEAFLETS[name]
        fe = edges[edge_values == _GROUPS[f"free_edge_{name}"]]
        path = _chain(fe)
        xs = points[path]
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xs, axis=0), axis=1))])
        n = max(int(round(arc[-1] / p["chordae_spacing"])) - 1, 1)
        targets = arc[-1] * np.arange(1, n + 1) / (n + 1)
        pick = np.unique([int(np.argmin(np.abs(arc - t))) for t in targets])
        pick = pick[(pick > 0) & (pick < len(path) - 1)]
        if name == "anterior":  # the commissural notches, shared by both free edges: once
            pick = np.concatenate([[0], pick, [len(path) - 1]])
        for i in pick:
            out_pts.append(xs[i])
            out_leaf.append(value)
            out_fam.append("marginal")
            out_closed.append(closed(xs[i]))
        # belly points: nearest interior vertex of this leaflet
        family, where = ("strut", p["strut_points"]) if name == "anterior" else \
            ("basal", p["basal_points"])
        verts = np.setdiff1d(np.unique(cells[cell_values == value]), boundary)
        for tau, r in where:
            target = lf.point(tau, r)
            k = verts[np.argmin(np.linalg.norm(points[verts] - target, axis=1))]
            out_pts.append(points[k])
            out_leaf.append(value)
            out_fam.append(family)
            foot = lf.point(tau, 0.0)
            out_closed.append(foot + r * (closed(lf.point(tau, 1.0)) - foot))
    pts = np.array(out_pts)
    # muscle by side of the anteroposterior midline (y = 0); nearest tip of that muscle
    present = np.unique(muscle)
    side = np.where(pts[:, 1] >= 0, 0, 1)
    m = np.where(np.isin(side, present), side, present[0]).astype(np.int32)
    tip = np.empty(len(pts), dtype=np.int32)
    for i, (x, mi) in enumerate(zip(pts, m)):
        cand = np.flatnonzero(muscle == mi)
        tip[i] = cand[np.argmin(np.linalg.norm(tips[cand] - x, axis=1))]
    return {"points": pts, "leaflet": np.array(out_leaf, dtype=np.int32),
            "family": np.array(out_fam), "muscle": m, "tip": tip,
            "closed": np.array(out_closed)}


def _closure_design(leaflets: dict, p: dict):
    """Where a free-edge point sits in the designed closed valve (local frame): below the
    coaptation curve, which runs from commissure to commissure, bowed toward the posterior
    annulus by ``coaptation_offset`` x the posterior half-diameter at the middle and sunk by
    ``closed_depth`` (tenting height + coaptation length) below the commissures' chord there,
    both tapering as ``4u(1 - u)`` to the commissures. Returns a function of a local point."""
    lf = leaflets["anterior"]
    c0, c1 = lf.curve.point(lf.s0), lf.curve.point(lf.s1)
    post_mid = leaflets["posterior"].point(0.5, 0.0)
    axis_xy = (c1 - c0)[:2]
    length2 = float(axis_xy @ axis_xy)
    mid = 0.5 * (c0 + c1)
    toward_post = post_mid[:2] - mid[:2]
    toward_post -= (toward_post @ axis_xy) / length2 * axis_xy

    def closed(x):
        u = float(np.clip((np.asarray(x)[:2] - c0[:2]) @ axis_xy / length2, 0.0, 1.0))
        bump = 4.0 * u * (1.0 - u)
        xy = c0[:2] + u * axis_xy + p["coaptation_offset"] * bump * toward_post
        z = c0[2] + u * (c1[2] - c0[2]) - p["closed_depth"] * bump
        return np.array([xy[0], xy[1], z])

    return closed


def _chain(edges: np.ndarray) -> np.ndarray:
    """Vertices of an open polyline given by its edges, in order from one end."""
    nbr: dict[int, list[int]] = {}
    for a, b in edges:
        nbr.setdefault(int(a), []).append(int(b))
        nbr.setdefault(int(b), []).append(int(a))
    ends = [v for v, nb in nbr.items() if len(nb) == 1]
    if len(ends) != 2 or any(len(nb) > 2 for nb in nbr.values()):
        raise RuntimeError("valve: a free edge is not a single open curve")
    path, prev = [min(ends)], -1
    while len(path) < len(nbr):
        nxt = [v for v in nbr[path[-1]] if v != prev]
        prev = path[-1]
        path.append(nxt[0])
    return np.array(path)


# --- quality ---------------------------------------------------------------------------------

def _quality(points: np.ndarray, cells: np.ndarray) -> dict:
    """Angles, edge lengths, areas; quality = 4 sqrt(3) area / sum of squared edge lengths
    (1 for an equilateral triangle)."""
    x = points[cells]
    e = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 1], x[:, 0] - x[:, 2]], axis=1)
    L = np.linalg.norm(e, axis=2)
    area = 0.5 * np.linalg.norm(np.cross(e[:, 0], -e[:, 2]), axis=1)
    ang = []
    for i in range(3):
        u, v = e[:, i], -e[:, i - 1]
        ang.append(np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", u, v)
                                                / (L[:, i] * L[:, i - 1]), -1, 1))))
    ang = np.stack(ang, axis=1)
    qual = 4 * np.sqrt(3) * area / (L**2).sum(1)
    return {"min_angle": float(ang.min()), "max_angle": float(ang.max()),
            "min_quality": float(qual.min()), "mean_quality": float(qual.mean()),
            "below30": int(np.sum(ang.min(1) < 30)),
            "edges": {"min": float(L.min()), "median": float(np.median(L)),
                      "max": float(L.max())},
            "areas": area}
