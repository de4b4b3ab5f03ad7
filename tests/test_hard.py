"""Hard cases (issue 7, `pytest -m hard`, about 10-15 min): each ends converged, or with exit
code 3 and its one-line message and a summary saying "converged": false, or (a damaged
imported mesh) refused with one line, exit code 2. Never a hang (every case has a timeout and
is killed with its process group), a traceback, a signal or a NaN in summary.json. The cases
and the verdict are :mod:`mvfem.hard`; ``python scripts/hard_cases.py`` prints the README table.

Besides the clean ending, what each case must show where the physics says so:

- a converged valve has no leaflet through the other (max_penetration_mm 0), except the
  cases in KNOWN_PENETRATION (none now), which xfail with the depth;
- the crossing leaflets are refused, or reported as penetrating;
- the coincident nodes are merged with a warning, or refused;
- the ruptured marginal chordae lose the coaptation of the healthy demo at this size
  (coaptation length below the 4 mm valve's, which is about 8 mm);
- the 1 mm valve started from its 2 mm closure (sequenced or nested) converges within the
  300 steps in which it cannot from the open state: the point of a coarse start.
"""

from __future__ import annotations

import pytest

from mvfem.hard import CASES, run_case, verdict

pytestmark = pytest.mark.hard

#: converged valves whose final state has an edge through the other leaflet, which xfail with
#: their depth. Empty since the step limit checks every pair of edges (until then the imported
#: 4 mm valve with duplicate nodes, 1.21 mm, and the prolapse, 0.36-1.32 mm, depending on
#: roundoff in the path): any penetration of a converged case fails
KNOWN_PENETRATION: dict[str, float] = {}


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("hard")


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_hard_case_ends_cleanly(case, workdir):
    o = run_case(case, workdir)
    print(f"\n{case.name}: exit {o.exit_code}, {o.time_s:.1f} s: {o.message}")
    ok, why = verdict(o)
    assert ok, f"{why}\n--- stderr tail ---\n{o.stderr[-3000:]}"
    s = o.summary or {}
    if case.name == "crossing-leaflets":
        assert o.exit_code == 2 or (s.get("max_penetration_mm") or 0) > 0, \
            "leaflets that start crossed were neither refused nor reported"
    if case.name == "duplicate-nodes" and o.exit_code != 2:
        assert "merged" in o.stderr
    if case.name in ("fine-mesh-sequenced", "fine-mesh-nested"):
        assert o.exit_code == 0 and s.get("coarse_start", {}).get("used"), \
            f"the coarse start did not close the fine mesh: {o.message}"
    if case.name == "prolapse-no-marginal" and o.exit_code == 0:
        assert s["valve"]["coaptation_length_mm"] < 6.0
    if o.exit_code == 0 and (s.get("max_penetration_mm") or 0) > 0:
        if case.name in KNOWN_PENETRATION:
            pytest.xfail(f"converged with {s['max_penetration_mm']:.3g} mm penetration "
                         "(known: KNOWN_PENETRATION)")
        pytest.fail(f"converged with a leaflet through the other: "
                    f"{s['max_penetration_mm']:.3g} mm")
