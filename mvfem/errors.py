"""Exceptions that the CLI turns into exit codes (see CONTRACT.md)."""

from __future__ import annotations

__all__ = ["InputError", "SolverError", "Interrupted"]


class InputError(ValueError):
    """Bad input: the CLI prints the message as one line and exits with code 2.

    The message names the file (or option), the key and what is wrong.
    """


class SolverError(RuntimeError):
    """The solver stopped short of the requested load: exit code 3."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM stopped a solve at a step boundary
    (:func:`mvfem.solver.stop_on_interrupt`): raised by :func:`mvfem.solve` after its
    outputs, where it writes any, are written; the CLI prints the message as one line and
    exits with ``exit_code`` (130 for Ctrl-C, 143 for SIGTERM, as the shell reports them).

    Attributes:
        result: the :class:`mvfem.run.Result` of the state reached (the last accepted one),
            or None where the stop came before the scene's own level (a coarser level of a
            nested start; nothing written).
        written: whether that state's outputs were written.
        exit_code: 128 + the signal's number.
    """

    def __init__(self, message: str, result=None, written: bool = False,
                 exit_code: int = 130):
        super().__init__(message)
        self.result, self.written, self.exit_code = result, written, exit_code
