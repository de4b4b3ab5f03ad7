r"""Ties: sutures and clips that pull two leaflet nodes together (repairs, mvfem/repairs.py).

A tie between nodes ``a`` and ``b`` is a tension-only spring of rest length ``L`` and stiffness
``k`` on their distance,

.. math:: \Pi_t = \phi(|x_a - x_b| - L)

with :func:`mvfem.nodal.smooth_penalty` (``phi' = k (d - L - eps/2)`` once taut, 0 when slack,
rounded over ``eps``): a suture pulls, it cannot push. The rest length is ramped from the
distance of the two nodes in the open valve down to the tie's own length (the contact
thickness by default: two leaflets held against each other, mid-surface to mid-surface, which
is where the contact barrier lets go), so that a stitch is drawn tight over the first
pseudo-time steps rather than yanked shut at once (:meth:`Ties.set_fraction`).

Ties are point terms like the chordae (:class:`mvfem.nodal.PointTerms`) and do not touch the
contact: the two tied nodes and everything around them stay subject to the barrier, so a tie
can never pull one leaflet through the other.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mvfem.nodal import Blocks, smooth_penalty

__all__ = ["TIE_ONSET", "Ties"]

#: rounding of the slack-to-taut transition of a tie, mm (a tie at its rest length must not
#: switch its full stiffness on and off between Newton iterates; cf. mvfem.chordae.ONSET)
TIE_ONSET = 0.02


@dataclass
class Ties:
    """Two-node tension-only springs (rank 0 holds them; empty arrays elsewhere).

    Attributes:
        nodes: (m, 2) global node indices.
        rest_length: (m,) the tied length, mm.
        stiffness: (m,) Pa mm (uN/mm; 1 N/mm = 1e6 Pa mm).
        kind: (m,) what each tie is ("clip", "suture", ...).
        group: (m,) index of the repair item each tie belongs to (clip 0, clip 1, ...).
        start_length: (m,) rest length at the start of the ramp (the open distance), mm.
    """

    nodes: np.ndarray
    rest_length: np.ndarray
    stiffness: np.ndarray
    kind: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype="<U8"))
    group: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    start_length: np.ndarray | None = None

    def __post_init__(self):
        self.nodes = np.asarray(self.nodes, dtype=np.int64).reshape(-1, 2)
        self.target_length = np.asarray(self.rest_length, dtype=float).copy()
        self.rest_length = self.target_length.copy()
        self.stiffness = np.asarray(self.stiffness, dtype=float)
        if self.start_length is None:
            self.start_length = self.target_length.copy()
        self.start_length = np.maximum(np.asarray(self.start_length, dtype=float),
                                       self.target_length)

    def __len__(self) -> int:
        return len(self.nodes)

    def set_fraction(self, f: float) -> None:
        """Rest length at ramp fraction ``f``: the start length at 0, the tie's own at 1."""
        f = min(max(float(f), 0.0), 1.0)
        self.rest_length = (1.0 - f) * self.start_length + f * self.target_length

    def length(self, x: np.ndarray) -> np.ndarray:
        """Distance between the two nodes of each tie at positions ``x`` (N, 3)."""
        return np.linalg.norm(x[self.nodes[:, 0]] - x[self.nodes[:, 1]], axis=1)

    def tension(self, x: np.ndarray) -> np.ndarray:
        """Tension of each tie (Pa mm^2 = uN)."""
        return smooth_penalty(self.length(x) - self.rest_length, self.stiffness, TIE_ONSET)[1]

    def force_N(self, x: np.ndarray) -> np.ndarray:
        return self.tension(x) * 1e-6

    def __call__(self, x: np.ndarray) -> Blocks:
        d = x[self.nodes[:, 0]] - x[self.nodes[:, 1]]
        length = np.linalg.norm(d, axis=1)
        e = d / np.maximum(length, 1e-300)[:, None]
        phi, t, kt = smooth_penalty(length - self.rest_length, self.stiffness, TIE_ONSET)
        f = t[:, None] * e
        force = np.stack([f, -f], axis=1)                       # (m, 2, 3)
        eye = np.eye(3)
        outer = e[:, :, None] * e[:, None, :]
        # d2 phi(|d|)/dd2 = phi'' e e^T + phi'/|d| (I - e e^T); d = x_a - x_b
        k3 = kt[:, None, None] * outer + (t / np.maximum(length, 1e-300))[:, None, None] \
            * (eye - outer)
        K = np.zeros((len(self), 6, 6))
        K[:, :3, :3] = k3
        K[:, 3:, 3:] = k3
        K[:, :3, 3:] = -k3
        K[:, 3:, :3] = -k3
        return Blocks(self.nodes, force, K, float(phi.sum()))

    def summary(self, x: np.ndarray) -> dict:
        """Per kind: count, largest distance of the tied nodes, largest and total tension (N)."""
        out = {}
        length, force = self.length(x), self.force_N(x)
        for kind in np.unique(self.kind):
            sel = self.kind == kind
            out[str(kind)] = {"count": int(sel.sum()),
                              "max_distance_mm": float(length[sel].max()),
                              "rest_length_mm": float(self.target_length[sel].max()),
                              "max_force_N": float(force[sel].max()),
                              "total_force_N": float(force[sel].sum()),
                              "groups": len(np.unique(self.group[sel]))}
        return out
