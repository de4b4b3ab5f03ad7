"""Scene files (TOML): what to simulate, validated up front.

A scene names the mesh, the regions with their laws, the fibres, the boundary, the load, the
solver settings and the outputs (see CONTRACT.md). :func:`load_scene` reads a file or a dict,
fills defaults, converts units (lengths to mm, pressures and moduli to Pa) and raises
:class:`~mvfem.errors.InputError` with one line naming the file, the key and the problem.
"""

from __future__ import annotations

import copy
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from mvfem.errors import InputError
from mvfem.units import AREA, LENGTH, PRESSURE, STIFFNESS, beyond_float, parse_quantity

__all__ = ["Scene", "load_scene", "parse_set_option", "read_toml", "GENERATORS", "LAW_NAMES"]

GENERATORS = ("disk", "square", "sphere", "octasphere", "tube", "valve", "file")
LAW_NAMES = ("svk", "mny", "holzapfel", "neo-hookean")
_MISSING = object()


class _Bad(Exception):
    """A validation failure at a key path; turned into an InputError with the file name."""

    def __init__(self, path: str, message: str):
        super().__init__(message)
        self.path, self.message = path, message


# --------------------------------------------------------------------------- value checkers
def _number(path, v, minimum=None, positive=False, integer=False):
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _Bad(path, f"expected a number, got {v!r}")
    big = beyond_float(v)
    if big:
        raise _Bad(path, big)
    if integer and (not float(v).is_integer()):
        raise _Bad(path, f"expected an integer, got {v!r}")
    if not math.isfinite(v):
        raise _Bad(path, f"must be finite, got {v!r}")
    if positive and v <= 0:
        raise _Bad(path, f"must be positive, got {v!r}")
    if minimum is not None and v < minimum:
        raise _Bad(path, f"must be at least {minimum}, got {v!r}")
    return int(v) if integer else float(v)


def _quantity(units, unit, positive=True, allow_zero=False):
    def check(path, v):
        try:
            x = parse_quantity(v, units, unit)
        except ValueError as e:
            raise _Bad(path, str(e)) from None
        if positive and (x < 0 or (x == 0 and not allow_zero)):
            raise _Bad(path, f"must be {'non-negative' if allow_zero else 'positive'}, got {v!r}")
        return x
    return check


def _choice(*options):
    def check(path, v):
        if not isinstance(v, str) or v.lower() not in options:
            raise _Bad(path, f"expected one of {', '.join(options)}, got {v!r}")
        return v.lower()
    return check


def _bool(path, v):
    if not isinstance(v, bool):
        raise _Bad(path, f"expected true or false, got {v!r}")
    return v


def _str(path, v):
    if not isinstance(v, str) or not v.strip():
        raise _Bad(path, f"expected a non-empty string, got {v!r}")
    return v


def _vector3(path, v):
    if (not isinstance(v, (list, tuple)) or len(v) != 3
            or any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in v)):
        raise _Bad(path, f"expected a vector of three numbers [x, y, z], got {v!r}")
    big = next(filter(None, map(beyond_float, v)), "")
    if big:
        raise _Bad(path, f"a component is {big}")
    if not all(math.isfinite(c) for c in v):
        raise _Bad(path, f"must be finite, got {v!r}")
    return [float(c) for c in v]


def _pos(path, v):
    return _number(path, v, positive=True)


def _coarse_sizes(path, v):
    """A mesh size (mm) or a list of them: the levels of a grid sequence."""
    if isinstance(v, list):
        if not v:
            raise _Bad(path, "expected a mesh size (mm) or a non-empty list of them")
        sizes = [_pos(f"{path}[{i}]", x) for i, x in enumerate(v)]
        if len(set(sizes)) != len(sizes):
            raise _Bad(path, f"a size is given twice: {v!r}")
        return sorted(sizes, reverse=True)
    return _pos(path, v)


def _int(minimum, maximum=None, why=""):
    def check(path, v):
        n = _number(path, v, minimum=minimum, integer=True)
        if maximum is not None and n > maximum:
            raise _Bad(path, f"must be at most {maximum}{why}, got {v!r}")
        return n
    return check


#: the element degrees and quadrature degrees a scene may ask for: the membrane is verified
#: at P1 and P2 (README "Speed against error"); P3 and P4 compile in seconds, but degree 50
#: compiled for minutes and quadrature degree 200 took a minute for a 1 mm disk (session 62)
MAX_DEGREE, MAX_QUADRATURE_DEGREE = 4, 20


_length = _quantity(LENGTH, "mm")


def _accuracy(path, v):
    """``mesh.accuracy``: a length (mm), or false for none (the default; a ``--set`` that
    switches off a file's target, as repair-compare does where one mesh serves every case)."""
    if v is False:
        return None
    if v is True:
        raise _Bad(path, "expected a length (mm) or false, got True")
    return _length(path, v)


_pressure_any = _quantity(PRESSURE, "Pa", positive=False)


# --------------------------------------------------------------------------- schema
# section -> key -> (checker, default); _MISSING = required
_SCHEMA: dict[str, dict[str, tuple[Callable, Any]]] = {
    "mesh": {
        "generator": (_choice(*GENERATORS), _MISSING),
        "radius": (_length, 10.0),
        "side": (_length, 10.0),
        "length": (_length, 20.0),
        "size": (_length, None),
        "refinements": (_int(0), 3),  # octasphere
        # valve: uniform 1-to-4 splits of the generated mesh, new nodes on the leaflets'
        # surfaces (meshes.valve refine); the coarser levels are nested meshes of one valve
        "refine": (_int(0), 0),
        # a valve file's new nodes: on its facets (the file's surface) or on a smooth surface
        # through its nodes (meshes.refine.smooth_midpoints)
        "refine_surface": (_choice("facets", "smooth"), "facets"),
        # a valve refined level by level until the last refinement moves the closure by at
        # most this on average (mm; mesh.refine the most refinements tried; mvfem.run
        # _solve_to_accuracy, README "A mesh chosen by accuracy")
        "accuracy": (_accuracy, None),
        "file": (_str, None),
        "labels": (None, None),  # checked in _check_mesh
        # generator = "valve" (meshes.valve); geometry defaults there, healthy adult numbers
        "ap_diameter": (_length, None),
        "commissural_diameter": (_length, None),
        "saddle_height": (_quantity(LENGTH, "mm", positive=False), None),
        "anterior_height": (_length, None),
        "posterior_height": (_length, None),
        "papillary_depth": (_length, None),
        "free_edge_size": (_length, None),
        "chordae_spacing": (_length, None),
        "annulus": (_str, None),      # CSV of an ordered closed annulus loop (x, y, z), mm
        "papillary": (_str, None),    # CSV of papillary tips (x, y, z), same frame
        "anterior_direction": (_vector3, None),
    },
    "fibres": {
        "direction": (None, "circumferential"),  # checked in _check_fibres
        "axis": (_vector3, [0.0, 0.0, 1.0]),
        "centre": (_vector3, None),
    },
    "boundary": {
        # rigid: pin the six rigid-body modes of a closed surface (see model._rigid_pins)
        "clamp": (_choice("boundary", "annulus", "rigid", "none"), "boundary"),
    },
    "chordae": {
        "enabled": (_bool, True),  # valve scenes with chordae only
        "marginal": (None, {}),    # family tables: checked in _check_chordae
        "strut": (None, {}),
        "basal": (None, {}),
        "edit": (None, []),        # list of tables: checked in _check_chordae
    },
    "bending": {
        # hinge bending stiffness D = modulus x h^3 / 12 (forms/bending.py); None: 100 kPa for
        # valves (suppresses wrinkling of the compressed leaflets), 0 for other scenes
        "modulus": (_quantity(PRESSURE, "Pa", allow_zero=True), None),
    },
    "contact": {
        "enabled": (_bool, True),  # valve scenes only
        "thickness": (_length, 0.5),     # surfaces are kept this far apart
        "stiffness": (_quantity(STIFFNESS, "Pa/mm"), None),
        "exclusion": (_length, None),
    },
    "load": {
        "pressure": (_pressure_any, 16e3),
        "follower": (_bool, True),
    },
    "solver": {
        "degree": (_int(1, MAX_DEGREE, " (higher orders compile for minutes)"), 1),
        "quadrature_degree": (_int(1, MAX_QUADRATURE_DEGREE,
                                   " (exact for polynomials of that degree; more compiles for "
                                   "minutes)"), None),
        "tolerance": (_pos, 1e-8),  # equilibrium: ||R|| <= tolerance x ||pressure load||
        "step_tolerance": (_pos, 1e-6),  # intermediate load steps, same measure
        "max_it": (_int(1), 25),
        "linear_solver": (_choice("lu", "iterative"), "lu"),
        "ramp": (_choice("cubic", "linear"), "cubic"),
        "first_step": (_pos, 0.1),
        "min_step": (_pos, 1e-5),
        "max_steps": (_int(1), None),  # None: 400 load steps, 1500 pseudo-time steps
        # pseudo-time: pseudo-transient continuation at the full load (one Newton step per
        # pseudo-time step); load-steps: pressure ramp with inner proximal solves; auto:
        # pseudo-time for scenes with chordae or contact, load steps otherwise
        "method": (_choice("auto", "pseudo-time", "load-steps"), "auto"),
        "stabilisation": (_pos, 0.1),
        "petsc_options": (None, None),  # a table of PETSc options under the problem's prefix
        # prescribed motion (annulus target, ring, papillary target, ties): spread over the
        # first ramp_steps pseudo-time steps, or over the load steps' load parameter
        "ramp_steps": (_int(1), 20),
        # with-pressure: the motion and the pressure together; before-pressure: the motion
        # over the first half of the ramp at zero pressure, then the pressure (as a ring is
        # sewn in on the arrested heart)
        "motion": (_choice("with-pressure", "before-pressure"), "with-pressure"),
        # grid sequencing (mvfem/sequence.py): close the same generated scene on a coarser
        # mesh of this size (mm) first and start from its closed state moved onto this mesh;
        # a list of sizes chains the levels, coarsest first
        "coarse_start": (_coarse_sizes, None),
        # a refined valve (mesh.refine = n): close the unrefined mesh first and each finer
        # level from the one below (nested meshes; mvfem/sequence.py); false: from the open
        # state on the finest mesh alone
        "nested": (_bool, True),
    },
    "output": {
        "probes": (None, []),  # checked in _check_probes
        "xdmf": (_bool, True),
        # a nested or sequenced run measures each coarser level's closure against the next
        # finer one's (summary.json coarse_start: valve, distance_to_finer_mm;
        # map_level_change.png; mvfem.run._compare_levels): about 0.9 s of the demo refined
        # twice
        "levels": (_bool, True),
    },
    # prescribed motion of the clamped loop (a valve's annulus, a disk's rim) to a target
    # loop in the mesh's frame, from its open (stress-free) position (mvfem/prescribed.py)
    "annulus": {
        "target": (_str, None),   # CSV of an ordered closed loop (x, y, z), mm
        "match": (_choice("auto", "points", "curve"), "auto"),
    },
    # prescribed motion of the papillary tips (the chordae anchors)
    "papillary": {
        "target": (_str, None),   # CSV, one row per papillary tip in the valve's order
    },
    # repairs as scene edits (mvfem/repairs.py): checked in _check_repair
    "repair": {
        "ring": (None, None),
        "neochord": (None, []),
        "clip": (None, []),
        "resection": (None, None),
    },
    # a reference closed surface (any meshio format) to measure the predicted closed state
    # against (mvfem/distance.py); labels name its cell data 'leaflet' (default: mesh.labels,
    # else 1 anterior, 2 posterior)
    "reference": {
        "file": (_str, None),
        "labels": (None, None),  # checked in _check_reference
    },
}
_REGION = {
    "label": (_str, None),
    "law": (_choice(*LAW_NAMES), _MISSING),
    "params": (None, _MISSING),  # a set name or a table of law parameters
    "thickness": (_length, None),
    "leaflet": (_choice("anterior", "posterior"), None),
    # false: the fibre term bears tension only (mny, holzapfel; forms.materials._fibre)
    "fibre_compression": (_bool, True),
}
_VALVE_KEYS = ("ap_diameter", "commissural_diameter", "saddle_height", "anterior_height",
               "posterior_height", "papillary_depth", "free_edge_size", "chordae_spacing",
               "annulus", "papillary", "anterior_direction")
_TOP = ("title", "mesh", "region", "fibres", "boundary", "load", "bending", "chordae", "contact",
        "solver", "output", "reference", "annulus", "papillary", "repair")
#: chordae families and their defaults: rest length = length_factor x open length (or tree
#: path length); axial stiffness = modulus x area / rest length. The modulus is a modelling
#: choice of the order reported for human chordae (README); the area is the data README's.
CHORD_FAMILIES = ("marginal", "strut", "basal")
_FAMILY = {
    "length_factor": (_pos, 1.0),
    "modulus": (_quantity(PRESSURE, "Pa"), 40e6),
    "area": (_quantity(AREA, "mm2"), 0.35),
}


def _check_table(path: str, table: Any, spec: dict) -> dict:
    if not isinstance(table, dict):
        raise _Bad(path, f"expected a table, got {table!r}")
    unknown = sorted(set(table) - set(spec))
    if unknown:
        raise _Bad(f"{path}.{unknown[0]}" if path else unknown[0],
                   f"unknown key (known: {', '.join(spec)})")
    out = {}
    for key, (check, default) in spec.items():
        where = f"{path}.{key}" if path else key
        if key in table:
            out[key] = check(where, table[key]) if check else table[key]
        elif default is _MISSING:
            raise _Bad(where, "required key is missing")
        else:
            out[key] = copy.deepcopy(default)
    return out


def _check_region(path: str, region: dict) -> dict:
    from mvfem.forms.materials import law_parameters
    from mvfem.materials import get_set

    r = _check_table(path, region, _REGION)
    if not r["fibre_compression"] and r["law"] not in ("mny", "holzapfel"):
        raise _Bad(f"{path}.fibre_compression", f"law {r['law']!r} has no fibre term (only "
                   "mny and holzapfel do)")
    params = r["params"]
    if isinstance(params, str):
        leaflet = r["leaflet"] or (r["label"] if r["label"] in ("anterior", "posterior")
                                   else "anterior")
        try:
            ps = get_set(params, leaflet)
        except InputError as e:
            raise _Bad(f"{path}.params", str(e)) from None
        if ps.law != r["law"]:
            raise _Bad(f"{path}.params", f"set {params!r} is for law {ps.law!r}, not {r['law']!r}")
        r["params"] = dict(ps.params)
        r["set"] = ps.name
        if r["thickness"] is None:
            r["thickness"] = ps.thickness_mm
    elif isinstance(params, dict):
        names = law_parameters(r["law"])
        known = {k.lower(): v for k, v in params.items()}
        extra = sorted(set(known) - {n.lower() for n in names})
        if extra:
            raise _Bad(f"{path}.params.{extra[0]}",
                       f"not a parameter of law {r['law']!r} (expected {', '.join(names)})")
        values = {}
        for n in names:
            if n.lower() not in known:
                raise _Bad(f"{path}.params.{n}", f"required by law {r['law']!r}")
            v = known[n.lower()]
            if n in ("E", "mu", "c0"):
                values[n] = _quantity(PRESSURE, "Pa")(f"{path}.params.{n}", v)
            elif n == "nu":
                values[n] = _number(f"{path}.params.{n}", v)
                if not -1 < values[n] <= 0.5:
                    raise _Bad(f"{path}.params.nu", f"must be in (-1, 0.5], got {v!r}")
            else:
                values[n] = _number(f"{path}.params.{n}", v, minimum=0.0)
        r["params"] = values
        r["set"] = "custom"
    else:
        raise _Bad(f"{path}.params", f"expected a set name or a table of parameters, got {params!r}")
    if r["thickness"] is None:
        raise _Bad(f"{path}.thickness", "required when params is a table")
    return r


#: the longest length a generated mesh may have (mm: a kilometre). gmsh aborts the process
#: on a disk of radius 1e9 mm (exit code 134, a C++ backtrace) and meshes a tube of 1e10
#: mm without end (session 62); a length this long is a unit mistaken. (A mesh file's nodes
#: have the same bound, ``mvfem.meshes.imported.MAX_COORDINATE_MM``.)
MAX_LENGTH_MM = 1e6


def _check_mesh(mesh: dict, base_dir: Path) -> None:
    for key in ("radius", "side", "length", "size", *_VALVE_KEYS):
        v = mesh.get(key)
        if isinstance(v, float) and abs(v) > MAX_LENGTH_MM:
            raise _Bad(f"mesh.{key}", f"{v:g} mm is longer than {MAX_LENGTH_MM:g} mm (a "
                       "kilometre; lengths are in mm unless a unit is given)")
    if mesh["refine"] and mesh["generator"] not in ("valve", "file"):
        raise _Bad("mesh.refine", "refines valves only (generator = \"valve\", or a valve file)")
    if mesh["refine"] > 4:
        raise _Bad("mesh.refine", f"at most 4 (each refinement is 4x the cells), "
                   f"got {mesh['refine']}")
    if mesh["accuracy"] is not None and not mesh["refine"]:
        raise _Bad("mesh.accuracy", "needs mesh.refine >= 1, the most refinements to try")
    if mesh["refine_surface"] == "smooth" and mesh["generator"] != "file":
        raise _Bad("mesh.refine_surface", "places a valve file's new nodes (generator = "
                   "\"file\"); a generated valve's are on its own surface")
    if mesh["generator"] == "file":
        if not mesh["file"]:
            raise _Bad("mesh.file", "required when generator = \"file\"")
        p = _existing_file("mesh.file", mesh["file"], base_dir)
        mesh["file"] = str(p)
    labels = mesh["labels"]
    if labels is not None:
        if not isinstance(labels, dict) or not labels:
            raise _Bad("mesh.labels", "expected a table such as { 1 = \"anterior\" }")
        out = {}
        for k, v in labels.items():
            try:
                key = int(k)
            except (TypeError, ValueError):
                raise _Bad(f"mesh.labels.{k}", "label keys must be integers") from None
            out[key] = _str(f"mesh.labels.{k}", v)
        mesh["labels"] = out


def _fraction_pair(path, v):
    if (not isinstance(v, (list, tuple)) or len(v) != 2
            or any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in v)
            or not 0.0 <= v[0] < v[1] <= 1.0):
        raise _Bad(path, f"expected [from, to] with 0 <= from < to <= 1, got {v!r}")
    return [float(v[0]), float(v[1])]


#: one edit of the chordae a scene's valve has: which chords (all criteria given must hold)
#: and what happens to them
_EDIT = {
    "leaflet": (_str, None),
    "family": (_choice(*CHORD_FAMILIES), None),
    # Carpentier segments: 1 anterolateral, 2 middle, 3 posteromedial thirds of a leaflet
    "segment": (_choice("a1", "a2", "a3", "p1", "p2", "p3"), None),
    # fraction along the leaflet's free edge from the posteromedial (0) to the
    # anterolateral (1) commissure
    "between": (_fraction_pair, None),
    "length_factor": (_pos, None),   # multiplies the rest length
    "rupture": (_bool, False),       # removes the chords
}


def _check_chordae(ch: dict) -> None:
    for fam in CHORD_FAMILIES:
        ch[fam] = _check_table(f"chordae.{fam}", ch[fam], _FAMILY)
    edits = ch["edit"]
    if isinstance(edits, dict):
        edits = [edits]
    if not isinstance(edits, list):
        raise _Bad("chordae.edit", f"expected a list of tables [[chordae.edit]], got {edits!r}")
    out = []
    for i, e in enumerate(edits):
        path = f"chordae.edit[{i}]"
        e = _check_table(path, e, _EDIT)
        if e["segment"] is not None and e["between"] is not None:
            raise _Bad(f"{path}.between", "give either segment or between, not both")
        if e["length_factor"] is None and not e["rupture"]:
            raise _Bad(path, "says neither length_factor nor rupture = true")
        if e["length_factor"] is not None and e["rupture"]:
            raise _Bad(f"{path}.rupture", "a ruptured chord has no length_factor")
        if e["segment"] is not None:
            named = {"a": "anterior", "p": "posterior"}[e["segment"][0]]
            if e["leaflet"] not in (None, named):
                raise _Bad(f"{path}.segment", f"{e['segment'].upper()} is on the {named} leaflet, "
                           f"not the {e['leaflet']} one")
            e["leaflet"] = named
        out.append(e)
    ch["edit"] = out


def _tie_stiffness(path, v):
    """A stiffness in N/mm (a number) or a string with N/mm, Pa mm -> Pa mm (uN/mm)."""
    try:
        x = parse_quantity(v, {"n/mm": 1e6, "pa mm": 1.0, "un/mm": 1.0}, "N/mm")
    except ValueError as e:
        raise _Bad(path, str(e)) from None
    if not isinstance(v, str):  # a plain number is in N/mm
        x *= 1e6
    if x <= 0:
        raise _Bad(path, f"must be positive, got {v!r}")
    return x


def _fraction(path, v):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= 1.0:
        raise _Bad(path, f"expected a fraction along the leaflet in [0, 1] (0 posteromedial, "
                   f"1 anterolateral commissure), got {v!r}")
    return float(v)


def _fractions(path, v):
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return [_fraction(path, v)]
    if not isinstance(v, list) or not v:
        raise _Bad(path, f"expected a fraction or a list of fractions, got {v!r}")
    return [_fraction(f"{path}[{i}]", x) for i, x in enumerate(v)]


_LEAFLET = _choice("anterior", "posterior")
_RING = {
    "shape": (_choice("full", "d-shaped", "band"), _MISSING),
    # the ring's intercommissural (transverse) diameter, as the sizers name it (26-40 mm)
    "size": (_length, _MISSING),
    "ap_ratio": (_pos, 0.75),          # anteroposterior / transverse
    "saddle_height": (_quantity(LENGTH, "mm", allow_zero=True), 0.0),
}
_NEOCHORD = {
    "leaflet": (_LEAFLET, _MISSING),
    "at": (_fractions, None),          # positions along the leaflet of the free-edge nodes
    "point": (_vector3, None),         # or a point near the free edge (mm)
    "length": (_length, _MISSING),     # rest length, mm
    "papillary": (_choice("nearest", "anterolateral", "posteromedial"), "nearest"),
    "modulus": (_quantity(PRESSURE, "Pa"), None),   # default: the marginal chordae's
    "area": (_quantity(AREA, "mm2"), None),
    "tolerance": (_length, 1.5),       # mm from the free edge a point may be
}
_CLIP = {
    "at": (_fraction, None),           # the same position on both free edges
    "anterior": (_fraction, None),     # or one per leaflet
    "posterior": (_fraction, None),
    "points": (None, None),            # or [[anterior x, y, z], [posterior x, y, z]]
    "width": (_length, 4.0),           # mm along the free edges the clip grasps
    # mm of each leaflet from its free edge the clip holds (0: the free-edge nodes alone, an
    # Alfieri stitch); a clip's arms grasp several mm
    "depth": (_quantity(LENGTH, "mm", allow_zero=True), 0.0),
    "gap": (_quantity(LENGTH, "mm", allow_zero=True), None),  # default: contact thickness
    "stiffness": (_tie_stiffness, 5e6),
    "tolerance": (_length, 1.5),
}
_RESECTION = {
    "leaflet": (_LEAFLET, _MISSING),
    "shape": (_choice("triangular", "quadrangular"), _MISSING),
    "between": (_fraction_pair, None),
    "segment": (_choice("a1", "a2", "a3", "p1", "p2", "p3"), None),
    # fraction of the leaflet height from the free edge (the apex of a triangle)
    "depth": (_pos, _MISSING),
    "sutures": (_bool, True),
    "gap": (_quantity(LENGTH, "mm", allow_zero=True), None),
    "stiffness": (_tie_stiffness, 5e6),
}


def _items(path: str, v) -> list:
    if isinstance(v, dict):
        v = [v]
    if not isinstance(v, list):
        raise _Bad(path, f"expected a list of tables [[{path}]], got {v!r}")
    return v


def _check_repair(rep: dict, data: dict) -> None:
    gen = data["mesh"]["generator"]
    if gen not in ("valve", "file") and any(rep[k] for k in rep):
        raise _Bad("repair", "repairs need a valve (generator = \"valve\" or a valve file)")
    if rep["ring"] is not None:
        r = rep["ring"] = _check_table("repair.ring", rep["ring"], _RING)
        if not 16.0 <= r["size"] <= 50.0:
            raise _Bad("repair.ring.size", f"expected a ring size in mm as surgeons name them "
                       f"(16-50 mm; usual 26-40), got {r['size']:g}")
        if data["annulus"]["target"] is not None:
            raise _Bad("repair.ring", "give either annulus.target or repair.ring, not both")
    out = []
    for i, n in enumerate(_items("repair.neochord", rep["neochord"])):
        path = f"repair.neochord[{i}]"
        n = _check_table(path, n, _NEOCHORD)
        if (n["at"] is None) == (n["point"] is None):
            raise _Bad(path, "give either at (positions along the leaflet) or point")
        out.append(n)
    rep["neochord"] = out
    out = []
    for i, c in enumerate(_items("repair.clip", rep["clip"])):
        path = f"repair.clip[{i}]"
        c = _check_table(path, c, _CLIP)
        given = [k for k in ("at", "points") if c[k] is not None]
        if c["anterior"] is not None or c["posterior"] is not None:
            if c["anterior"] is None or c["posterior"] is None:
                raise _Bad(path, "give both anterior and posterior positions")
            given.append("anterior/posterior")
        if len(given) != 1:
            raise _Bad(path, "give the clip's position once: at, anterior and posterior, or "
                       "points")
        if c["at"] is not None:
            c["anterior"] = c["posterior"] = c["at"]
        if c["points"] is not None:
            pts = c["points"]
            if not isinstance(pts, list) or len(pts) != 2:
                raise _Bad(f"{path}.points", "expected [[anterior x, y, z], [posterior x, y, "
                           f"z]], got {pts!r}")
            c["points"] = [_vector3(f"{path}.points[{j}]", p) for j, p in enumerate(pts)]
        out.append(c)
    rep["clip"] = out
    if rep["resection"] is not None:
        r = rep["resection"] = _check_table("repair.resection", rep["resection"], _RESECTION)
        if (r["between"] is None) == (r["segment"] is None):
            raise _Bad("repair.resection", "give either between or segment")
        if r["segment"] is not None:
            named = {"a": "anterior", "p": "posterior"}[r["segment"][0]]
            if r["leaflet"] != named:
                raise _Bad("repair.resection.segment", f"{r['segment'].upper()} is on the "
                           f"{named} leaflet, not the {r['leaflet']} one")
        if r["depth"] > 1.0:
            raise _Bad("repair.resection.depth", f"a fraction of the leaflet height (at most "
                       f"1), got {r['depth']:g}")


def _points_file(key: str, value, base_dir: Path):
    """(path, (N, 3) points) of the CSV of points a scene key names; points beyond a
    kilometre are refused (an annulus target of radius 1e6 mm asked for 1.4 PiB)."""
    import numpy as np

    from mvfem.meshes.io import read_points

    p = _existing_file(key, value, base_dir)
    try:
        pts = read_points(p)
    except ValueError as e:
        raise _Bad(key, str(e)) from None
    far = np.flatnonzero(np.abs(pts).max(axis=1) > MAX_LENGTH_MM) if len(pts) else []
    if len(far):
        raise _Bad(key, f"{p}: point {far[0]} {pts[far[0]].tolist()} is farther than "
                   f"{MAX_LENGTH_MM:g} mm from the origin (coordinates are in mm)")
    return p, pts


def _check_targets(data: dict, base_dir: Path) -> None:
    for section in ("annulus", "papillary"):
        t = data[section]["target"]
        if t is None:
            continue
        p, pts = _points_file(f"{section}.target", t, base_dir)
        if section == "annulus" and len(pts) < 3:
            raise _Bad("annulus.target", f"{p}: a loop needs at least 3 points, got {len(pts)}")
        data[section]["target"] = str(p)
    if data["annulus"]["target"] is not None and data["boundary"]["clamp"] not in (
            "annulus", "boundary"):
        raise _Bad("annulus.target", "moves the clamped loop: needs boundary.clamp = "
                   "\"annulus\" (valves) or \"boundary\"")
    if data["papillary"]["target"] is not None and data["mesh"]["generator"] not in (
            "valve", "file"):
        raise _Bad("papillary.target", "only for valves with chordae")


def _check_valve_files(mesh: dict, base_dir: Path) -> None:
    for key in ("annulus", "papillary"):
        if mesh[key] is None:
            continue
        if mesh["generator"] != "valve":
            raise _Bad(f"mesh.{key}", "only for generator = \"valve\"")
        p, _ = _points_file(f"mesh.{key}", mesh[key], base_dir)
        mesh[key] = str(p)


def _has_annulus(path: str) -> bool:
    """Whether a mesh file has point data 'annulus' (an imported valve); a file that cannot
    be read is reported when the mesh is built."""
    from mvfem.meshes.io import read_surface

    try:
        return "annulus" in read_surface(path).point_data
    except ValueError:
        return False


def _check_reference(ref: dict, base_dir: Path, mesh_labels: dict | None) -> None:
    """The reference closed surface: the file exists and reads as a surface whose 'leaflet'
    values (if any) the labels name (``reference.labels``, else ``mesh.labels``)."""
    labels = ref["labels"]
    if labels is not None:
        if not isinstance(labels, dict) or not labels:
            raise _Bad("reference.labels", "expected a table such as { 1 = \"anterior\" }")
        out = {}
        for k, v in labels.items():
            try:
                key = int(k)
            except (TypeError, ValueError):
                raise _Bad(f"reference.labels.{k}", "label keys must be integers") from None
            out[key] = _str(f"reference.labels.{k}", v)
        ref["labels"] = labels = out
    if ref["file"] is None:
        if labels is not None:
            raise _Bad("reference.labels", "given without reference.file")
        return
    from mvfem.distance import read_reference

    p = _existing_file("reference.file", ref["file"], base_dir)
    try:
        read_reference(p, labels or mesh_labels)
    except ValueError as e:
        raise _Bad("reference.file", str(e)) from None
    ref["file"] = str(p)


def _unit(path: str, v: list[float]) -> list[float]:
    """``v`` made a unit vector (scaled by its largest component first, so that neither
    [1e200, 1e200, 0] overflows nor [1e-200, 0, 0] underflows, which gave NaN directions)."""
    big = max(abs(c) for c in v)
    if big == 0:
        raise _Bad(path, "must not be the zero vector")
    w = [c / big for c in v]
    n = math.sqrt(sum(c * c for c in w))
    return [c / n for c in w]


def _check_fibres(fib: dict) -> None:
    d = fib["direction"]
    if isinstance(d, str):
        fib["direction"] = _choice("circumferential", "radial")("fibres.direction", d)
    else:
        fib["direction"] = _unit("fibres.direction", _vector3("fibres.direction", d))
    fib["axis"] = _unit("fibres.axis", fib["axis"])
    if fib["centre"] is not None and max(abs(c) for c in fib["centre"]) > MAX_LENGTH_MM:
        raise _Bad("fibres.centre", f"{fib['centre']} is farther than {MAX_LENGTH_MM:g} mm from "
                   "the origin (lengths are in mm)")


def _check_probes(probes) -> list:
    if not isinstance(probes, list):
        raise _Bad("output.probes", "expected a list of { name = ..., point = [x, y, z] }")
    out, seen = [], set()
    for i, p in enumerate(probes):
        q = _check_table(f"output.probes[{i}]", p, {"name": (_str, _MISSING),
                                                      "point": (_vector3, _MISSING)})
        if q["name"] in seen:
            raise _Bad(f"output.probes[{i}].name", f"duplicate probe name {q['name']!r}")
        seen.add(q["name"])
        out.append(q)
    return out


def _validate(raw: dict, base_dir: Path) -> dict:
    unknown = sorted(set(raw) - set(_TOP))
    if unknown:
        raise _Bad(unknown[0], f"unknown key (known: {', '.join(_TOP)})")
    data: dict[str, Any] = {"title": raw.get("title", "")}
    if not isinstance(data["title"], str):
        raise _Bad("title", f"expected a string, got {data['title']!r}")
    if "mesh" not in raw:
        raise _Bad("mesh", "required section is missing")
    for section, spec in _SCHEMA.items():
        data[section] = _check_table(section, raw.get(section, {}), spec)
    _check_mesh(data["mesh"], base_dir)
    _check_valve_files(data["mesh"], base_dir)
    _check_chordae(data["chordae"])
    _check_fibres(data["fibres"])
    _check_reference(data["reference"], base_dir, data["mesh"]["labels"])
    data["output"]["probes"] = _check_probes(data["output"]["probes"])
    opts = data["solver"]["petsc_options"]
    if opts is not None and not isinstance(opts, dict):
        raise _Bad("solver.petsc_options", "expected a table of PETSc options")
    regions = raw.get("region")
    if regions is None:
        raise _Bad("region", "at least one [[region]] is required")
    if isinstance(regions, dict):
        regions = [regions]
    if not isinstance(regions, list) or not regions:
        raise _Bad("region", "expected [[region]] tables")
    data["region"] = [_check_region(f"region[{i}]", r) for i, r in enumerate(regions)]
    labels = [r["label"] for r in data["region"]]
    if len(labels) > 1 and (None in labels or len(set(labels)) != len(labels)):
        raise _Bad("region", "with several regions each needs its own distinct label")
    gen = data["mesh"]["generator"]
    if gen in ("sphere", "octasphere") and "clamp" not in raw.get("boundary", {}):
        data["boundary"]["clamp"] = "rigid"  # a closed surface has no boundary to clamp
    if gen == "valve" and "clamp" not in raw.get("boundary", {}):
        data["boundary"]["clamp"] = "annulus"
    if (gen == "file" and "clamp" not in raw.get("boundary", {})
            and _has_annulus(data["mesh"]["file"])):
        data["boundary"]["clamp"] = "annulus"  # an imported valve, clamped like a generated one
    _check_targets(data, base_dir)
    _check_repair(data["repair"], data)
    valve_keys = [k for k in _VALVE_KEYS if data["mesh"][k] is not None]
    if valve_keys and gen != "valve":
        raise _Bad(f"mesh.{valve_keys[0]}", "only for generator = \"valve\"")
    return data


# --------------------------------------------------------------------------- Scene
@dataclass(frozen=True)
class Scene:
    """A validated scene.

    Attributes:
        data: the normalised scene (defaults filled, lengths in mm, pressures in Pa).
        raw: the scene as written (used to apply changes and validate again).
        source: the file it came from, or "<dict>".
    """

    data: dict
    raw: dict = field(repr=False)
    source: str = "<dict>"
    base_dir: Path = field(default=Path("."), repr=False)

    def __getitem__(self, key: str):
        return self.data[key]

    def with_changes(self, changes: dict[str, Any]) -> "Scene":
        """A new scene with dotted keys replaced, e.g. ``{"load.pressure": "120 mmHg"}``.

        ``region.0.thickness`` addresses the first region. Validated like a file.
        """
        raw = copy.deepcopy(self.raw)
        for dotted, value in changes.items():
            _assign(raw, dotted, value, self.source)
        return _make(raw, self.source, self.base_dir)


def _assign(raw: dict, dotted: str, value, source: str) -> None:
    parts = dotted.split(".")
    node = raw
    for i, part in enumerate(parts[:-1]):
        nxt = parts[i + 1]
        if isinstance(node, list):
            try:
                node = node[int(part)]
            except (ValueError, IndexError):
                raise InputError(f"{source}: --set {dotted}: no item {part!r}") from None
            continue
        if not isinstance(node, dict):  # (a path through a value: a string, a number)
            raise InputError(f"{source}: --set {dotted}: {'.'.join(parts[:i])} is not a table")
        if part == "region" and isinstance(node.get(part), dict):
            node[part] = [node[part]]
        if part not in node:
            node[part] = [] if nxt.isdigit() else {}
        node = node[part]
    last = parts[-1]
    if isinstance(node, list):
        try:
            node[int(last)] = value
        except (ValueError, IndexError):
            raise InputError(f"{source}: --set {dotted}: no item {last!r}") from None
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise InputError(f"{source}: --set {dotted}: {'.'.join(parts[:-1])} is not a table")


def _make(raw: dict, source: str, base_dir: Path) -> Scene:
    try:
        data = _validate(raw, base_dir)
    except _Bad as e:
        raise InputError(f"{source}: {e.path}: {e.message}") from None
    return Scene(data=data, raw=raw, source=source, base_dir=base_dir)


def _file_problem(p: Path) -> str:
    """'' for a regular file, else what it is instead (a directory, a device or a FIFO, no
    such file, a name too long to look up)."""
    try:
        if p.is_file():
            return ""
        if p.is_dir():
            return "a directory, not a file"
        return "not a regular file" if p.exists() else "no such file"
    except OSError as e:   # (a name too long; exists() raises that one)
        return f"cannot be looked up ({e.strerror or e})"


def _existing_file(key: str, value, base_dir: Path) -> Path:
    """The file a scene key names (relative to the scene's directory), a regular file."""
    p = Path(value)
    p = p if p.is_absolute() else base_dir / p
    problem = _file_problem(p)
    if problem:
        raise _Bad(key, f"{problem}: {p}")
    return p


def load_scene(scene: str | Path | dict | Scene) -> Scene:
    """Read and validate a scene from a TOML file, a dict, or return a Scene as it is."""
    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, dict):
        return _make(copy.deepcopy(scene), "<dict>", Path("."))
    path = Path(scene)
    return _make(read_toml(path, "scene"), str(path), path.resolve().parent)


def read_toml(path: Path, what: str, missing: str | None = None) -> dict:
    """The table of a TOML file; one-line InputError when it is missing (``missing``, else
    "PATH: no such WHAT file"), not TOML or not text (scenes, studies, repair files)."""
    problem = _file_problem(path)
    if problem == "no such file":
        raise InputError(missing or f"{path}: no such {what} file")
    if problem:
        raise InputError(f"{path}: {problem.replace('a file', f'a {what} file')}")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: not valid TOML: {e}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file") from None
    except OSError as e:   # (no permission to read it)
        raise InputError(f"{path}: cannot be read ({e.strerror or e})") from None


def parse_set_option(text: str) -> tuple[str, Any]:
    """``key.path=value`` from the command line; the value is read as TOML when it parses."""
    if "=" not in text:
        raise InputError(f"--set {text}: expected key.path=value")
    key, value = text.split("=", 1)
    key = key.strip()
    if not key:
        raise InputError(f"--set {text}: empty key")
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value.strip()
    return key, parsed
