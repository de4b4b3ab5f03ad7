"""Chordae tendineae: tension-only tethers from fixed papillary points to leaflet nodes.

A chord of rest length ``L`` and axial stiffness ``k = E A / L`` (modulus times cross-section
over length) stores

.. math:: \\Pi_c = \\phi(\\ell - L),\\qquad \\ell = |x_i - P|

with :func:`mvfem.nodal.smooth_penalty` (``phi' = k (l - L - eps/2)`` when taut, 0 when slack,
rounded over ``eps``): it pulls only. Chordae of a family share a length factor (rest length =
factor x the length in the open valve, or x the path length along an imported chordal tree),
a modulus and a cross-section.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mvfem.nodal import Blocks, smooth_penalty

__all__ = ["Chordae"]

#: rounding of the slack-to-taut transition, as a fraction of the rest length: of the order of
#: the toe region of chordae (collagen uncrimping, a few % strain). With 1e-3 a chord that
#: hovered at its rest length switched its full stiffness on and off between Newton iterates,
#: and the prolapsing valve's end game cycled (README, "Solving")
ONSET = 2e-2


@dataclass
class Chordae:
    """The tethers of a scene (rank 0 holds them; empty arrays elsewhere).

    Attributes:
        node: (m,) global node index of each insertion.
        anchor: (m, 3) papillary point of each chord, mm.
        rest_length: (m,) mm.
        stiffness: (m,) axial stiffness E A / L, Pa mm (1 Pa mm = 1e-3 N/mm).
        family: (m,) family name of each chord ("marginal", "strut", "basal", ...).
        leaflet: (m,) leaflet name of each insertion.
    """

    node: np.ndarray
    anchor: np.ndarray
    rest_length: np.ndarray
    stiffness: np.ndarray
    family: np.ndarray
    leaflet: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype="<U16"))

    def __len__(self) -> int:
        return len(self.node)

    def tension(self, x: np.ndarray) -> np.ndarray:
        """Tension of each chord (Pa mm^2, i.e. uN) at nodal positions ``x``."""
        d = x[self.node] - self.anchor
        length = np.linalg.norm(d, axis=1)
        return smooth_penalty(length - self.rest_length, self.stiffness,
                              ONSET * self.rest_length)[1]

    def force_N(self, x: np.ndarray) -> np.ndarray:
        """Tension of each chord in newtons (1 Pa mm^2 = 1e-6 N)."""
        return self.tension(x) * 1e-6

    def __call__(self, x: np.ndarray) -> Blocks:
        d = x[self.node] - self.anchor
        length = np.linalg.norm(d, axis=1)
        e = d / length[:, None]
        stretch = length - self.rest_length
        phi, t, kt = smooth_penalty(stretch, self.stiffness, ONSET * self.rest_length)
        force = (t[:, None] * e)[:, None, :]
        eye = np.eye(3)
        outer = e[:, :, None] * e[:, None, :]
        # d2(phi(l))/dx2 = phi'' e e^T + phi'/l (I - e e^T)
        K = kt[:, None, None] * outer + (t / length)[:, None, None] * (eye - outer)
        return Blocks(self.node[:, None], force, K, float(phi.sum()))
