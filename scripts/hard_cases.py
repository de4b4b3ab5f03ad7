"""The hard-case table of the README (issue 7): every case of :mod:`mvfem.hard` through
`mvfem run` in a subprocess, one at a time, and a markdown table of how each ended.

    python scripts/hard_cases.py --out results/hard [--cases cp08-16kPa,slivers]

Writes DIR/hard_cases.md and DIR/<case>/ (scene, damaged mesh, stdout, stderr, outputs);
exit code 1 if a case did not end cleanly (converged, exit 3 with its message, or a damaged
file refused with one line).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mvfem.hard import CASES, markdown, run_case, verdict


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="results/hard")
    p.add_argument("--cases", help="comma-separated case names (default: all)")
    args = p.parse_args(argv)
    names = [c.strip() for c in args.cases.split(",")] if args.cases else None
    cases = [c for c in CASES if names is None or c.name in names]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    outcomes = []
    for c in cases:
        o = run_case(c, out)
        outcomes.append(o)
        ok, why = verdict(o)
        print(f"{c.name:<22s} exit {o.exit_code}  {o.time_s:6.1f} s  "
              f"{'clean' if ok else 'NOT CLEAN: ' + why}  {o.message}", flush=True)
    table = markdown(outcomes)
    (out / "hard_cases.md").write_text(table + "\n")
    print(f"\n{table}\n\n{len(cases)} cases in {time.perf_counter() - t0:.0f} s")
    return 0 if all(verdict(o)[0] for o in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
