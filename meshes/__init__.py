"""Geometry of mvfem: mesh generators, import/export, labels and surface directions.

Knows geometry only; no physics.
"""

from __future__ import annotations

from .patch import square_patch

__all__ = ["square_patch"]
