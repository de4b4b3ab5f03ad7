"""Output directories and files shared by all commands."""

from __future__ import annotations

import json
import os
from pathlib import Path

from mvfem.errors import InputError

__all__ = ["prepare_out", "write_json", "MARKER"]

#: file that marks a directory as mvfem output, so later runs may write into it again
MARKER = ".mvfem-output"


def prepare_out(out: str | os.PathLike, option: str = "--out") -> Path:
    """Create the output directory, or reuse one that mvfem made before.

    A directory that exists, is not empty and was not made by mvfem is refused, so that nothing
    a user wrote is overwritten.
    """
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise InputError(f"{option} {path}: exists and is not a directory")
    if path.is_dir() and any(path.iterdir()) and not (path / MARKER).exists():
        raise InputError(f"{option} {path}: directory exists, is not empty and was not written "
                         "by mvfem; choose a new directory")
    path.mkdir(parents=True, exist_ok=True)
    (path / MARKER).touch()
    return path


def write_json(data: dict, path: str | os.PathLike) -> None:
    """Write ``data`` as indented JSON atomically (write a temporary file, then rename)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")
    os.replace(tmp, path)
