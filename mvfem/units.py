"""Quantities with units in scene files: "16 kPa", "120 mmHg", "0.85 mm".

Inside mvfem lengths are millimetres and pressures/moduli pascals.
"""

from __future__ import annotations

import math
import re
import sys

__all__ = ["PRESSURE", "LENGTH", "AREA", "STIFFNESS", "parse_quantity"]

MMHG_PA = 101325.0 / 760.0

PRESSURE = {"pa": 1.0, "kpa": 1e3, "mpa": 1e6, "gpa": 1e9, "mmhg": MMHG_PA, "bar": 1e5,
            "n/mm2": 1e6, "n/mm^2": 1e6, "n/m2": 1.0, "n/m^2": 1.0}
LENGTH = {"mm": 1.0, "cm": 10.0, "m": 1e3, "um": 1e-3, "\u00b5m": 1e-3}
AREA = {"mm2": 1.0, "mm^2": 1.0, "cm2": 100.0, "cm^2": 100.0}
#: contact penalty: pressure per length of intrusion
STIFFNESS = {"pa/mm": 1.0, "kpa/mm": 1e3, "mpa/mm": 1e6}

_NUMBER = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([^\s\d].*)?$")


def parse_quantity(value, units: dict[str, float], default_unit: str) -> float:
    """A number (already in the default unit) or a string "<number> <unit>" -> float.

    Raises:
        ValueError: with a message that names the accepted units.
    """
    if isinstance(value, bool):
        raise ValueError(f"expected a number or a string with a unit, got {value!r}")
    if isinstance(value, (int, float)):
        big = beyond_float(value)
        if big:
            raise ValueError(big)
        x = float(value)
    elif isinstance(value, str):
        m = _NUMBER.match(value)
        if not m:
            raise ValueError(f"cannot read {value!r} as a quantity "
                             f"(e.g. '1.5 {default_unit}'; units: {', '.join(_names(units))})")
        unit = (m.group(2) or default_unit).strip()
        factor = units.get(unit.lower())
        if factor is None:
            raise ValueError(f"unknown unit {unit!r} in {value!r} (units: {', '.join(_names(units))})")
        x = float(m.group(1)) * factor
    else:
        raise ValueError(f"expected a number or a string with a unit, got {value!r}")
    if not math.isfinite(x):
        raise ValueError(f"{value!r} is not finite")
    return x


def beyond_float(value) -> str:
    """What is wrong with an integer too large for a float (TOML and Python integers have
    any number of digits; ``float()`` of one raises OverflowError), or ''."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > sys.float_info.max:
        return f"an integer of {len(str(abs(value)))} digits is beyond the range of a float"
    return ""


def _names(units: dict[str, float]) -> list[str]:
    """The units to name in a message: a pressure's without its N/mm2 spellings; a
    stiffness's (every one a ratio) all, as Pa/mm, kPa/mm and MPa/mm."""
    pretty = {"pa": "Pa", "kpa": "kPa", "mpa": "MPa", "gpa": "GPa", "mmhg": "mmHg", "bar": "bar"}
    plain = [k for k in units if "/" not in k] or list(units)
    return ["/".join(pretty.get(p, p) for p in k.split("/")) for k in plain]
