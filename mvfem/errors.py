"""Exceptions that the CLI turns into exit codes (see CONTRACT.md)."""

from __future__ import annotations

__all__ = ["InputError", "SolverError"]


class InputError(ValueError):
    """Bad input: the CLI prints the message as one line and exits with code 2.

    The message names the file (or option), the key and what is wrong.
    """


class SolverError(RuntimeError):
    """The solver stopped short of the requested load: exit code 3."""
