"""What a nested or sequenced run reports of its coarser levels (session 50): each level's valve
metrics and how far its closure lies from the next finer level's (summary.json
``coarse_start``: ``valve``, ``distance_to_finer_mm``; ``map_level_change.png``; the
terminal's level lines).

The expected numbers come from elsewhere: the coarser level closed on its own in a run of its
own (the same scene, so the same path on the same ranks), and the distances between the two
closed surfaces by brute force over every triangle with numpy's closest points, not the
module's candidate search and compiled kernel.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

import mvfem.run as run_mod
from mvfem.cli import accuracy_line, level_lines
from mvfem.contact import closest_point_on_triangles
from mvfem.distance import surface_samples
from mvfem.run import LEVEL_METRICS, solve
from mvfem.scene import load_scene

DEMO = Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml"


def _brute(points: np.ndarray, x: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest of all triangles ``tri`` (numpy, every pair)."""
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    return np.array([closest_point_on_triangles(np.repeat(p[None], len(tri), 0), a, b, c)[0]
                     .min() for p in points])


def _directed(src, dst):
    """Brute-force distances of ``src``'s nodes and centroids to ``dst``, leaflet against
    leaflet (a node on two leaflets keeps the nearer namesake's)."""
    (xs, ts, gs), (xd, td, gd) = src, dst
    node = np.full(len(xs), np.inf)
    cen = np.full(len(ts), np.inf)
    for g in set(gs.tolist()):
        mine, theirs = ts[gs == g], td[gd == g]
        nodes = np.unique(mine)
        node[nodes] = np.minimum(node[nodes], _brute(xs[nodes], xd, theirs))
        cen[gs == g] = _brute(xs[mine].mean(axis=1), xd, theirs)
    return node, cen


@pytest.mark.mpi
def test_each_level_reports_itself_against_the_next(tmp_path, monkeypatch):
    """The 7 mm demo refined twice (nested levels, 112 / 448 / 1792 cells):

    - the middle level's ``distance_to_finer_mm`` is its closed surface's distance from the
      finest closure, as brute force gives it on the two closed surfaces the run made: the
      area-weighted mean of the finest facets' values (nodes a sixth, centroid a half) and
      the Hausdorff distance both ways, leaflet with leaflet; the p95 between the two;
    - on one process, against the same valve refined once, a run of its own on the same
      path: the middle level's record (``coarse_start``) has that run's valve metrics, and
      the coarsest level's record is that run's own (metrics and distance). (Under mpirun
      the two runs' coarsest closures differ by roundoff, 1e-15, and the middle level of
      this coarse valve can then settle in another fold: coaptation 6.94 against 6.86 mm.);
    - each closed surface is made once (three for three levels: the middle level's, made for
      its own comparison, serves the finest's), so no rank makes one alone (a rank that
      did hung the run under mpirun);
    - the run writes map_level_change.png and the terminal gets the levels' lines; the shape
      converges (the second refinement moves the closure less than the first); an unrefined
      run has none of it."""
    import mvfem.distance as distance

    comm = MPI.COMM_WORLD
    out = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0))
    made = {}
    real = distance._deformed_surface

    def counted(model):
        surface = real(model)
        made.setdefault(model.mesh.topology.index_map(2).size_global, []).append(surface)
        return surface

    monkeypatch.setattr(distance, "_deformed_surface", counted)
    demo = load_scene(DEMO).with_changes({"mesh.size": 7.0})
    fine = solve(demo.with_changes({"mesh.refine": 2}), out=out / "fine", progress=False)
    monkeypatch.setattr(distance, "_deformed_surface", real)
    plain = solve(demo, out=out / "plain", progress=False)
    s = fine.summary
    levels = run_mod.coarse_levels(s)
    assert fine.converged and plain.converged
    assert [lv["refine"] for lv in levels] == [1, 0] and all(lv["used"] for lv in levels)
    assert sorted(made) == [levels[1]["cells"], levels[0]["cells"], s["cells"]]
    assert all(len(v) == 1 for v in made.values())
    if comm.size == 1:
        middle = solve(demo.with_changes({"mesh.refine": 1}), progress=False, write=False)
        m = middle.summary
        assert middle.converged
        assert {k: levels[0]["valve"][k] for k in LEVEL_METRICS} == {
            k: pytest.approx(m["valve"][k], rel=1e-12, abs=1e-12) for k in LEVEL_METRICS}
        assert levels[1]["valve"] == m["coarse_start"]["valve"]
        assert levels[1]["distance_to_finer_mm"] == m["coarse_start"]["distance_to_finer_mm"]
    assert all(np.isfinite(lv["valve"][k]) for lv in levels for k in LEVEL_METRICS)
    d = levels[0]["distance_to_finer_mm"]
    assert d["compared"] == "by leaflet" and s["timing"]["level_change_s"] > 0
    assert d["mean_mm"] < levels[1]["distance_to_finer_mm"]["mean_mm"]
    written = json.loads((out / "fine" / "summary.json").read_text())
    assert written["coarse_start"]["distance_to_finer_mm"] == d
    assert all("_closed" not in lv for lv in levels)
    lines = level_lines(s)
    cells = [lv["cells"] for lv in levels[::-1]] + [s["cells"]]
    lengths = [lv["valve"]["coaptation_length_mm"] for lv in levels[::-1]] + [
        s["valve"]["coaptation_length_mm"]]
    moved = levels[1]["distance_to_finer_mm"]
    assert lines[0] == (f"mesh levels {cells[0]} / {cells[1]} / {cells[2]} cells: each "
                        f"refinement moved the closure by {moved['mean_mm']:.3g} / "
                        f"{d['mean_mm']:.3g} mm on average (p95 {moved['p95_mm']:.3g} / "
                        f"{d['p95_mm']:.3g} mm)")
    assert lines[1].startswith(f"  by level: coaptation length {lengths[0]:.3g} / "
                               f"{lengths[1]:.3g} / {lengths[2]:.3g} mm")
    assert level_lines(plain.summary) == [] and "coarse_start" not in plain.summary
    assert "level_change_s" not in plain.summary["timing"]
    if comm.rank != 0:
        return
    surfaces = [made[s["cells"]][0], made[levels[0]["cells"]][0]]
    (xf, tf, gf), _ = surfaces
    node, cen = _directed(surfaces[0], surfaces[1])
    back_node, back_cen = _directed(surfaces[1], surfaces[0])
    _, _, area = surface_samples(xf, tf)
    facet = node[tf].sum(axis=1) / 6 + cen / 2
    assert d["mean_mm"] == pytest.approx((area * facet).sum() / area.sum(), rel=1e-9)
    haus = max(node[np.unique(tf)].max(), cen.max(), back_node[np.unique(surfaces[1][1])].max(),
               back_cen.max())
    assert d["hausdorff_mm"] == pytest.approx(haus, rel=1e-9)
    assert d["mean_mm"] < d["p95_mm"] < d["hausdorff_mm"]
    assert (out / "fine" / "map_level_change.png").stat().st_size > 10_000
    assert not (out / "plain" / "map_level_change.png").exists()


@pytest.mark.parametrize("how", ["compare", "scene"])
def test_compare_off_measures_no_level(tmp_path, monkeypatch, how):
    """``solve(..., compare=False)`` (and ``outputs=False``, the coarser levels' own solves
    when their finer level does not compare), or the scene's ``output.levels = false``, keeps
    the coarser levels unmeasured: no metrics, no distance, no map, no closed surface made."""
    import mvfem.distance as distance

    made = []
    real = distance._deformed_surface

    def counted(model):
        made.append(model)
        return real(model)

    monkeypatch.setattr(distance, "_deformed_surface", counted)
    demo = load_scene(DEMO).with_changes({"mesh.size": 5.0, "mesh.refine": 1})
    if how == "compare":
        r = solve(demo, out=tmp_path / "off", progress=False, compare=False)
    else:
        r = solve(demo.with_changes({"output.levels": False}), out=tmp_path / "off",
                  progress=False)
    seq = r.summary["coarse_start"]
    assert r.converged and seq["used"]
    assert "valve" not in seq and "distance_to_finer_mm" not in seq and "_closed" not in seq
    assert "level_change_s" not in r.summary["timing"] and made == []
    assert not (tmp_path / "off" / "map_level_change.png").exists()


@pytest.mark.mpi
def test_accuracy_refines_until_the_move_is_small_enough(tmp_path, monkeypatch):
    """``mesh.accuracy`` on the 7 mm demo with ``mesh.refine = 2``, levels built bottom up:

    - at 1e-6 mm it refines to the cap and says the target is not met (exit 0, the closure
      converged); on one process its closure is the plain ``mesh.refine = 2`` run's;
    - at exactly the first refinement's move, read from that run, it stops refined once,
      met, and never builds the twice-refined mesh; its closure is the first run's middle
      level (the same levels in the same order: the same path), and summary.json says so;
    - just below that move it goes on to the cap.

    Under mpirun two runs of the same levels differ by roundoff (and this coarse valve's
    middle level can then settle in another fold), so there the target that stops refined
    once is 1 m, and the closures are not compared."""
    from mvfem.errors import InputError

    comm = MPI.COMM_WORLD
    out = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0))
    built, real = [], run_mod.build_model

    def counted(scene, *a, **kw):
        built.append(scene["mesh"]["refine"])
        return real(scene, *a, **kw)

    monkeypatch.setattr(run_mod, "build_model", counted)
    demo = load_scene(DEMO).with_changes({"mesh.size": 7.0, "mesh.refine": 2})
    tight = solve(demo.with_changes({"mesh.accuracy": 1e-6}), progress=False, write=False)
    s = tight.summary
    moves = [lv["distance_to_finer_mm"]["mean_mm"] for lv in run_mod.coarse_levels(s)[::-1]]
    assert tight.converged and built == [0, 1, 2] and len(moves) == 2
    assert s["accuracy"] == {"target_mm": 1e-6, "refine": 2, "most_refine": 2,
                             "moved_mm": moves[1], "met": False}
    assert accuracy_line(s["accuracy"]) == (
        f"mesh.accuracy 1e-06 mm: NOT met; stopped refined 2 time(s) (the last refinement "
        f"moved the closure by {moves[1]:.3g} mm), the most mesh.refine allows")
    built.clear()
    serial = comm.size == 1
    target = moves[0] if serial else 1000.0
    t0 = time.perf_counter()
    stop = solve(demo.with_changes({"mesh.accuracy": target}), out=out / "stop",
                 progress=False)
    elapsed = time.perf_counter() - t0
    t = stop.summary
    assert built == [0, 1] and t["cells"] == run_mod.coarse_levels(s)[0]["cells"]
    moved = t["coarse_start"]["distance_to_finer_mm"]["mean_mm"]
    assert t["accuracy"] == {"target_mm": target, "refine": 1, "most_refine": 2,
                             "moved_mm": moved, "met": True}
    written = json.loads((out / "stop" / "summary.json").read_text())
    assert written["accuracy"] == t["accuracy"] and written["cells"] == t["cells"]
    assert accuracy_line(t["accuracy"]).startswith(
        f"mesh.accuracy {target:g} mm: met refined 1 time(s)")
    # the level solved before counts in the wall time, as one solved within the run does
    # (the unrefined level is a quarter of the call here)
    # (rank 0's: another rank's wall time ends with its share of the outputs, before rank 0
    # draws the maps, which its call then waits for: 85 % of its call on a 2-core Zen 2)
    tt = t["timing"]
    wall, took = comm.bcast((t["wall_time_s"], elapsed), root=0)
    assert 0.9 * took < wall <= took
    assert tt["coarse_start_s"] > 0 and tt["other_s"] > 0
    assert tt["assembly_s"] + tt["linear_solve_s"] + tt["contact_s"] + tt["coarse_start_s"] + \
        tt["other_s"] == pytest.approx(t["wall_time_s"], rel=1e-12)
    if serial:
        assert moved == moves[0]
        assert {k: t["valve"][k] for k in LEVEL_METRICS} == \
            run_mod.coarse_levels(s)[0]["valve"]
        built.clear()
        below = solve(demo.with_changes({"mesh.accuracy": moves[0] * (1 - 1e-9)}),
                      progress=False, write=False)
        assert built == [0, 1, 2] and below.summary["accuracy"]["refine"] == 2
        plain = solve(demo, progress=False, write=False)
        assert {k: s["valve"][k] for k in LEVEL_METRICS} == {
            k: plain.summary["valve"][k] for k in LEVEL_METRICS}
    for changes, what in (({"mesh.accuracy": 0.1, "mesh.refine": 0}, "needs mesh.refine"),
                          ({"mesh.accuracy": 0.1, "solver.nested": False}, "needs nested levels"),
                          ({"mesh.accuracy": 0.1, "output.levels": False}, "needs the levels")):
        with pytest.raises(InputError, match=f"mesh.accuracy: {what}"):
            solve(demo.with_changes(changes), progress=False, write=False)


def test_accuracy_stops_where_a_level_stops_short(monkeypatch):
    """``mesh.accuracy``: a finer level that stops short (no distance to its coarser level,
    which is measured on converged closures only) ends the run there, with its outputs, the
    target not met and no move, so that the run reports the stop (exit code 3), not an input
    error; a level that converged without a measured move is one. Each level's solve is
    stubbed: only the decision between levels is looked at."""
    from mvfem.errors import InputError

    calls = []

    def stub(sc, out, comm, progress, write, initial, outputs, compare, coarse=None,
             more=None, converged=(True, False)):
        level = sc["mesh"]["refine"]
        calls.append((level, coarse is not None))
        summary = {"converged": converged[level], "coarse_start": {} if level else None}
        r = run_mod.Result(summary=summary, u=None, model=None, out=None)
        r.outputs_written = not more(r)
        return r

    monkeypatch.setattr(run_mod, "_solve", stub)
    demo = load_scene(DEMO).with_changes({"mesh.refine": 2, "mesh.accuracy": 0.05})
    r = run_mod.solve(demo, progress=False, write=False)
    assert calls == [(0, False), (1, True)] and r.outputs_written
    assert r.summary["accuracy"] == {"target_mm": 0.05, "refine": 1, "most_refine": 2,
                                     "moved_mm": None, "met": False}
    assert accuracy_line(r.summary["accuracy"]).endswith("time(s), a level stopped short")
    calls.clear()
    monkeypatch.setattr(run_mod, "_solve", lambda *a, **kw: stub(*a, **kw,
                                                                 converged=(True, True)))
    with pytest.raises(InputError, match="mesh.accuracy: needs nested levels"):
        run_mod.solve(demo, progress=False, write=False)
