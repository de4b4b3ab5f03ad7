"""Canonical biaxial tests of the membrane laws, evaluated through the UFL membrane.

A homogeneous in-plane stretch ``F = lambda_par a0 (x) a0 + lambda_perp b0 (x) b0 + n (x) n``
(optionally followed by a rigid rotation) is applied to a flat triangle in 3-D, and the Cauchy
stress of the law is evaluated with the same forms every simulation uses
(:mod:`mvfem.forms`). Four modes, with ``e`` the imposed strain (stretch - 1):

==================== ================= =====================
mode                 strain parallel   strain perpendicular
==================== ================= =====================
equibiaxial          e                 e
off-biaxial          e                 1.5 e
strip-parallel       e                 +0.15 (fixed)
strip-perpendicular  +0.15 (fixed)     e
==================== ================= =====================

"parallel" is along the fibre. Stresses are Cauchy stresses in Pa (sigma33 = 0).
"""

from __future__ import annotations

import csv
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mvfem.errors import InputError
from mvfem.materials import LEAFLETS, ParameterSet, parameter_sets

__all__ = ["MODES", "FIXED_STRAIN", "mode_strains", "PatchStress", "biaxial_curves",
           "write_csv", "plot_curves", "COLUMNS", "run_biaxial"]

log = logging.getLogger(__name__)

MODES = ("equibiaxial", "off-biaxial", "strip-parallel", "strip-perpendicular")
FIXED_STRAIN = 0.15
OFF_BIAXIAL_RATIO = 1.5
STRESS_LIMIT = 1e7  # Pa, the plotted range
COLUMNS = ("leaflet", "set", "mode", "strain_parallel", "strain_perpendicular",
           "sigma_parallel_Pa", "sigma_perpendicular_Pa")


def mode_strains(mode: str, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(strain parallel, strain perpendicular) of ``mode`` at the imposed strains ``e``."""
    e = np.asarray(e, dtype=float)
    fixed = np.full_like(e, FIXED_STRAIN)
    if mode == "equibiaxial":
        return e, e.copy()
    if mode == "off-biaxial":
        return e, OFF_BIAXIAL_RATIO * e
    if mode == "strip-parallel":
        return e, fixed
    if mode == "strip-perpendicular":
        return fixed, e
    raise InputError(f"mode: unknown biaxial mode {mode!r} (expected one of {', '.join(MODES)})")


def varied_direction(mode: str) -> str:
    """Which strain a mode varies: "perpendicular" for strip-perpendicular, else "parallel"."""
    return "perpendicular" if mode == "strip-perpendicular" else "parallel"


class PatchStress:
    """Cauchy stress of one law on a flat triangle under homogeneous deformations.

    The triangle lies in the plane spanned by the first two columns of ``frame`` (an orthonormal
    3x3 matrix), with the fibre ``a0`` in that plane. The law's parameters are ``fem.Constant``,
    so one compiled expression serves every parameter set of the law.

    Args:
        law: a key of :data:`mvfem.forms.LAWS`.
        frame: orthonormal 3x3 matrix (columns t1, t2, n); identity by default (xy-plane).
        fibre_angle: angle of the fibre from t1 towards t2, radians.
        tension_only: the fibre term bears tension only (``region.fibre_compression = false``).
    """

    def __init__(self, law: str, frame: np.ndarray | None = None, fibre_angle: float = 0.0,
                 tension_only: bool = False):
        import ufl
        from dolfinx import fem, mesh
        from mpi4py import MPI

        from mvfem.forms import LAWS, cauchy_stress, law_parameters, membrane

        Q = np.eye(3) if frame is None else np.asarray(frame, dtype=float)
        if not np.allclose(Q.T @ Q, np.eye(3), atol=1e-12):
            raise ValueError("frame must be orthonormal")
        self.frame = Q
        ca, sa = np.cos(fibre_angle), np.sin(fibre_angle)
        self.a0 = ca * Q[:, 0] + sa * Q[:, 1]
        self.b0 = -sa * Q[:, 0] + ca * Q[:, 1]
        self.n0 = Q[:, 2]
        points = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]) @ Q[:, :2].T
        cell = ufl.Cell("triangle", geometric_dimension=3)
        domain = ufl.Mesh(ufl.VectorElement("Lagrange", cell, 1))
        self.mesh = mesh.create_mesh(MPI.COMM_SELF, np.array([[0, 1, 2]], dtype=np.int64),
                                     points, domain)
        V = fem.VectorFunctionSpace(self.mesh, ("Lagrange", 1))
        self.u = fem.Function(V)
        self.law = law
        self.constants = {k: fem.Constant(self.mesh, 0.0) for k in law_parameters(law)}
        a0 = fem.Constant(self.mesh, self.a0)
        m = membrane(self.u, a0)
        extra = {"tension_only": True} if tension_only else {}
        W = LAWS[law](m, *self.constants.values(), **extra)
        sigma = cauchy_stress(W, m)
        # one point per cell: the stress is homogeneous on a P1 triangle
        from mvfem import jitcache

        jitcache.install()
        self._expr = fem.Expression(sigma, np.array([[1 / 3, 1 / 3]]))
        self._cells = np.array([0], dtype=np.int32)

    def set_parameters(self, params: dict) -> None:
        """Set the law parameters (names of :func:`mvfem.forms.law_parameters`)."""
        for k, c in self.constants.items():
            c.value = float(params[k])

    def deformation(self, strain_par: float, strain_perp: float,
                    rotation: np.ndarray | None = None) -> np.ndarray:
        """The deformation gradient of a biaxial stretch along (a0, b0), then ``rotation``."""
        F = ((1 + strain_par) * np.outer(self.a0, self.a0)
             + (1 + strain_perp) * np.outer(self.b0, self.b0) + np.outer(self.n0, self.n0))
        return F if rotation is None else rotation @ F

    def cauchy(self, F: np.ndarray) -> np.ndarray:
        """Cauchy stress (3x3, Pa) at the homogeneous deformation gradient ``F``."""
        D = np.asarray(F, dtype=float) - np.eye(3)
        self.u.interpolate(lambda x: D @ x)
        return self._expr.eval(self._cells).reshape(3, 3)

    def biaxial(self, strain_par: np.ndarray, strain_perp: np.ndarray,
                rotation: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Cauchy stress along the deformed fibre and across it, for each strain pair."""
        sp, sq = [], []
        for ep, eq in zip(np.atleast_1d(strain_par), np.atleast_1d(strain_perp)):
            F = self.deformation(ep, eq, rotation)
            s = self.cauchy(F)
            a = F @ self.a0
            b = F @ self.b0
            a /= np.linalg.norm(a)
            b /= np.linalg.norm(b)
            sp.append(a @ s @ a)
            sq.append(b @ s @ b)
        return np.array(sp), np.array(sq)


@dataclass
class Curve:
    """One biaxial curve: a set, a mode, strains and stresses (Pa)."""

    leaflet: str
    set: str
    mode: str
    strain_parallel: np.ndarray
    strain_perpendicular: np.ndarray
    sigma_parallel: np.ndarray
    sigma_perpendicular: np.ndarray

    @property
    def finite(self) -> np.ndarray:
        """Mask of states whose stresses are representable in float64."""
        return np.isfinite(self.sigma_parallel) & np.isfinite(self.sigma_perpendicular)


#: strain values a biaxial curve may have (the CSV holds one row per value, set and mode)
MAX_POINTS = 100_000


def strain_grid(strain_min: float, strain_max: float, points: int) -> np.ndarray:
    """Imposed strains; an :class:`InputError` for a range that is not one."""
    if not (np.isfinite(strain_min) and np.isfinite(strain_max)):
        raise InputError("--strain: the range must be two finite numbers")
    if strain_min >= strain_max:
        raise InputError(f"--strain: minimum {strain_min} is not below maximum {strain_max}")
    if strain_min <= -1 or strain_min * OFF_BIAXIAL_RATIO <= -1:
        raise InputError(f"--strain: minimum {strain_min} gives a zero or negative stretch "
                         f"(off-biaxial imposes {OFF_BIAXIAL_RATIO} x the strain); use > "
                         f"{-1 / OFF_BIAXIAL_RATIO:.4f}")
    if points < 2:
        raise InputError(f"--points: need at least 2 points, got {points}")
    if points > MAX_POINTS:   # (1e11 asked for 745 GiB)
        raise InputError(f"--points: at most {MAX_POINTS:,} points a curve, got {points:,}")
    return np.linspace(strain_min, strain_max, points)


def biaxial_curves(sets: list[ParameterSet], strains: np.ndarray,
                   modes: tuple[str, ...] = MODES) -> list[Curve]:
    """Evaluate every set in every mode at the imposed ``strains``.

    States whose stress overflows float64 (the exponential laws in strong compression, where
    ``I1`` grows without bound) are not finite; :attr:`Curve.finite` marks them.
    """
    evaluators: dict[str, PatchStress] = {}
    curves = []
    for s in sets:
        ev = evaluators.get(s.law)
        if ev is None:
            ev = evaluators[s.law] = PatchStress(s.law)
        ev.set_parameters(s.params)
        for mode in modes:
            ep, eq = mode_strains(mode, strains)
            with np.errstate(all="ignore"):
                sp, sq = ev.biaxial(ep, eq)
            curves.append(Curve(s.leaflet, s.name, mode, ep, eq, sp, sq))
    return curves


def write_csv(curves: list[Curve], path: Path) -> None:
    """Write ``biaxial.csv`` (columns of CONTRACT.md).

    A stress beyond float64 (above 1.8e308 Pa) is left empty: its value is not representable,
    and its sign is not known once the exponential has overflowed.
    """
    tmp = Path(str(path) + ".part")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for c in curves:
            for row in zip(c.strain_parallel, c.strain_perpendicular, c.sigma_parallel,
                           c.sigma_perpendicular):
                strains = [f"{v:.6g}" for v in row[:2]]
                stresses = [f"{v:.10g}" if np.isfinite(v) else "" for v in row[2:]]
                w.writerow([c.leaflet, c.set, c.mode, *strains, *stresses])
    os.replace(tmp, path)


def plot_curves(curves: list[Curve], leaflet: str, path: Path) -> None:
    """Four panels (one per mode): stress in the varied direction against its strain.

    The stress axis is symmetric-logarithmic (linear within +-100 Pa) so that curves spanning many
    decades, tensile and compressive, stay readable; it is cut at +-10 MPa, far above the
    strength of leaflet tissue, beyond which the exponential laws run off to 1e300 Pa.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mine = [c for c in curves if c.leaflet == leaflet]
    names = list(dict.fromkeys(c.set for c in mine))
    special = {"MNY-mean": dict(color="k", lw=2.4, ls="-"),
               "Holzapfel": dict(color="tab:purple", lw=2.2, ls="--"),
               "SVK": dict(color="0.45", lw=2.0, ls="-.")}
    palette = iter(plt.get_cmap("tab10").colors)
    styles = {n: special.get(n) or dict(color=next(palette), lw=1.2, ls="-") for n in names}
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.5), sharey=True)
    for ax, mode in zip(axes.flat, MODES):
        d = varied_direction(mode)
        for c in (c for c in mine if c.mode == mode):
            x = c.strain_parallel if d == "parallel" else c.strain_perpendicular
            y = c.sigma_parallel if d == "parallel" else c.sigma_perpendicular
            ok = np.isfinite(y) & (np.abs(y) < 10 * STRESS_LIMIT)
            ax.plot(100 * x[ok], y[ok], label=c.set, **styles[c.set])
        ax.set_yscale("symlog", linthresh=100.0)
        ax.set_ylim(-STRESS_LIMIT, STRESS_LIMIT)
        ax.set_title({"equibiaxial": "equibiaxial",
                      "off-biaxial": f"off-biaxial (perpendicular = {OFF_BIAXIAL_RATIO} x parallel)",
                      "strip-parallel": f"strip, perpendicular fixed at +{FIXED_STRAIN:.0%}",
                      "strip-perpendicular": f"strip, parallel fixed at +{FIXED_STRAIN:.0%}"}[mode],
                     fontsize=10)
        sym = "\u2225" if d == "parallel" else "\u22a5"
        ax.set_xlabel(f"strain {d} to fibre, {sym} (%)")
        ax.set_ylabel(f"Cauchy stress {sym} (Pa)")
        ax.grid(True, which="major", alpha=0.4)
        ax.axhline(0, color="k", lw=0.6)
        ax.axvline(0, color="k", lw=0.6)
    axes.flat[0].legend(fontsize=8, ncol=2, loc="upper left")
    fig.suptitle(f"Canonical biaxial tests, {leaflet} leaflet parameter sets "
                 "(symlog stress axis, linear within \u00b1100 Pa, cut at \u00b110 MPa)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_biaxial(out: Path, leaflets: tuple[str, ...] = LEAFLETS,
                strain_min: float = -0.5, strain_max: float = 0.5, points: int = 101,
                sets: tuple[str, ...] | None = None) -> dict:
    """The `mvfem biaxial` job: CSV and one figure per leaflet in ``out``.

    Returns:
        A dict with the number of rows, of overflowed states, and the files written.
    """
    from mvfem.materials import get_set
    from mvfem.outputs import remove_earlier_files

    strains = strain_grid(strain_min, strain_max, points)
    chosen = []
    for leaflet in leaflets:
        if sets:
            chosen += [get_set(n, leaflet) for n in sets]
        else:
            chosen += parameter_sets(leaflet)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # an earlier job's figure of a leaflet this one leaves out would read as this one's
    remove_earlier_files(out, ["biaxial.csv"] + [f"biaxial_{lf}.png" for lf in LEAFLETS])
    curves = biaxial_curves(chosen, strains)
    csv_path = out / "biaxial.csv"
    write_csv(curves, csv_path)
    files = [csv_path]
    for leaflet in leaflets:
        png = out / f"biaxial_{leaflet}.png"
        plot_curves(curves, leaflet, png)
        files.append(png)
    rows = sum(len(c.strain_parallel) for c in curves)
    overflow = sum(int((~c.finite).sum()) for c in curves)
    return {"rows": rows, "overflow": overflow, "files": files, "curves": curves}
