"""Named material parameter sets, read from ``data/materials.csv``.

The table carries, per leaflet and set: the law, its parameters (Pa or dimensionless), the
thickness in mm, the source, and whether the values were checked against that source.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from importlib import resources

from mvfem.errors import InputError
from mvfem.forms.materials import LAWS, law_parameters

__all__ = ["ParameterSet", "parameter_sets", "get_set", "LEAFLETS", "MISSING", "TABLE"]

LEAFLETS = ("anterior", "posterior")
TABLE = "data/materials.csv"

#: sets the source paper has but our sources do not: leaflet -> (names, reason)
MISSING = {
    "posterior": (
        tuple(f"CP{i:02d}" for i in range(1, 9)),
        "the per-specimen posterior sets (the source paper's Table II) are not in our sources;"
        " they are not invented here",
    ),
}

_COLUMNS = {"E": "E_Pa", "nu": "nu", "c0": "c0_Pa", "c1": "c1", "c2": "c2", "mu": "mu_Pa"}


@dataclass(frozen=True)
class ParameterSet:
    """One row of the parameter table.

    Attributes:
        leaflet: "anterior" or "posterior".
        name: set name, e.g. "CP01", "MNY-mean", "Holzapfel", "SVK".
        law: law key of :data:`mvfem.forms.LAWS`.
        params: parameter name -> value (Pa for moduli and c0).
        thickness_mm: leaflet thickness.
        verified: whether the values were checked against ``source``.
        source: where the values come from.
    """

    leaflet: str
    name: str
    law: str
    params: dict = field(hash=False)
    thickness_mm: float
    verified: bool
    source: str

    def values(self) -> tuple[float, ...]:
        """Parameter values in the order the law function takes them."""
        return tuple(self.params[k] for k in law_parameters(self.law))


def _read_table() -> list[ParameterSet]:
    text = resources.files("mvfem").joinpath(TABLE).read_text()
    sets = []
    for row in csv.DictReader(text.splitlines()):
        law = row["law"]
        if law not in LAWS:
            raise InputError(f"{TABLE}: set {row['set']}: unknown law {law!r}")
        params = {k: float(row[_COLUMNS[k]]) for k in law_parameters(law)}
        sets.append(ParameterSet(leaflet=row["leaflet"], name=row["set"], law=law, params=params,
                                 thickness_mm=float(row["thickness_mm"]),
                                 verified=row["verified"].strip().lower() == "true",
                                 source=row["source"]))
    return sets


_SETS: list[ParameterSet] | None = None


def parameter_sets(leaflet: str | None = None) -> list[ParameterSet]:
    """All parameter sets in table order, optionally of one leaflet."""
    global _SETS
    if _SETS is None:
        _SETS = _read_table()
    if leaflet is not None and leaflet not in LEAFLETS:
        raise InputError(f"leaflet: unknown leaflet {leaflet!r} (expected one of {', '.join(LEAFLETS)})")
    return [s for s in _SETS if leaflet is None or s.leaflet == leaflet]


def get_set(name: str, leaflet: str = "anterior") -> ParameterSet:
    """The parameter set ``name`` of ``leaflet``; an :class:`InputError` names what exists."""
    sets = parameter_sets(leaflet)
    for s in sets:
        if s.name.lower() == name.lower():
            return s
    missing = MISSING.get(leaflet)
    if missing and name.upper() in missing[0]:
        raise InputError(f"parameter set {name!r} ({leaflet}): not available: {missing[1]}")
    raise InputError(f"parameter set {name!r} ({leaflet}): unknown; known sets: "
                     + ", ".join(s.name for s in sets))
