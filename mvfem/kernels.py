"""Compiled kernels of the contact terms: distances, their gradients and curvatures per pair.

The contact energy needs, for thousands of node-triangle and edge-edge pairs and at every
Newton step, the distance, its gradient and its curvature. In numpy these small fixed-size
computations cost most of a valve closure (46 of 97 s of the demo); here they are
plain C loops, compiled once with the system's C compiler into ``~/.cache/mvfem`` (or
``$MVFEM_CACHE``) and loaded with cffi, as FFCx does for the forms. The pair search's narrow
phase is here too: distances over candidate pairs given by node indices
(:func:`point_triangle_distance`, :func:`segment_distance`), and the rows of the point terms'
tangent (:func:`elements_csr`). The curvatures are exact (``dist_curv``: the Hessian of a
minimum over closest-point parameters), 2.4-3.4x faster than the central differences of the
gradient (24 gradients a pair) they replaced, and right where those stepped across the edge
mollifier's switch. Where no compiler is available the numpy versions in
:mod:`mvfem.contact` are used (the same formulas, the curvatures by central differences;
checked against each other in ``tests/test_valve_terms.py``). The loops over pairs run on OpenMP
threads (:func:`threads`; the library is built with ``-fopenmp`` where the compiler has it),
with the results of one thread, bit for bit.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

__all__ = ["load", "point_triangle_gradient", "point_triangle_hessian",
           "point_triangle_stiffness", "edge_edge_energy",
           "edge_edge_hessian", "point_triangle_distance", "segment_distance", "elements_csr",
           "csr_missing", "csr_union", "csr_drop_zero_blocks", "threads", "one_blas_thread",
           "hinge_cos_sin", "hinge_energy", "hinge_hessian", "hinge_hessian_add", "psd_project"]

log = logging.getLogger(__name__)

_CDEF = """
void pt_grad(long m, const double *y, double *d, double *g);
void pt_hess(long m, const double *y, double *H);
void pt_stiff(long m, const double *y, const double *dphi, const double *ddphi,
              const double *dd, double *H);
void ee_energy(long m, const double *y, const double *w, const double *eps, double delta,
               double *E, double *g, double *d);
void ee_hess(long m, const double *y, const double *w, const double *eps, double delta,
             double *H);
void pt_dist(long m, const double *x, const int64_t *cells, const int64_t *s, const int64_t *t,
             double *d, double *bary);
void ee_dist(long m, const double *x, const int64_t *edges, const int64_t *i, const int64_t *j,
             double *d);
void pt_dist_cut(long m, const double *x, const int64_t *cells, const int64_t *s,
                 const int64_t *t, const double *lb, const double *D, double cut, double *d);
void ee_dist_cut(long m, const double *x, const int64_t *edges, const int64_t *i,
                 const int64_t *j, const double *lb, const double *D, double cut, double *d);
void hinge_cos_sin(long m, const double *y, double *c, double *s);
void hinge_energy(long m, const double *y, const double *c0, const double *s0,
                  const double *k, double *E, double *g);
void hinge_hess(long m, const double *y, const double *c0, const double *s0, const double *k,
                double rel, double *H);
void hinge_hess_add(long m, const double *y, const double *c0, const double *s0,
                    const double *k, double rel, const int64_t *place, double *vals);
long elements_csr(long G, const int64_t *m, const int64_t *k, int64_t **nodes, double **K,
                  long N, const uint8_t *fr, int64_t *indptr, int64_t *cols, double *vals,
                  int64_t *work);
long csr_missing(long n, const int64_t *ia, const int64_t *ja, const int64_t *ib,
                 const int64_t *jb);
long csr_union(long n, const int64_t *ia, const int64_t *ja, const int64_t *ib,
               const int64_t *jb, int64_t *ic, int64_t *jc);
long csr_drop_zero_blocks(long N, int64_t *indptr, int64_t *cols, double *vals, int64_t *mark);
void psd_proj(long m, int p, double *K, int *fail);
int set_threads(int n);
int team_size(void);
"""

_SOURCE = r"""
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

/* loops over pairs (hinges, rows) run on OpenMP threads where the library was built with
   OpenMP and they are long enough to pay for the fork; each iteration writes its own
   outputs, so the results do not depend on the number of threads. The count is this
   library's own, not OpenMP's global setting: a valve solve leaves that at 1 (set inside
   the solver libraries; measured) */
static int n_threads = 1;
#define PAR _Pragma("omp parallel for schedule(static) num_threads(n_threads) if (m > 512)")

/* the number of threads of the parallel loops (n > 0 sets it); 1 without OpenMP */
int set_threads(int n) {
#ifdef _OPENMP
  if (n > 0) n_threads = n;
  return n_threads;
#else
  (void)n;
  return 1;
#endif
}

/* the threads a parallel loop gets (a check that nothing else capped them) */
int team_size(void) {
  int size = 1;
#ifdef _OPENMP
  #pragma omp parallel num_threads(n_threads)
  {
    #pragma omp single
    size = omp_get_num_threads();
  }
#endif
  return size;
}

static double dot3(const double *a, const double *b) { return a[0]*b[0] + a[1]*b[1] + a[2]*b[2]; }
static void sub3(const double *a, const double *b, double *c) {
  c[0] = a[0] - b[0]; c[1] = a[1] - b[1]; c[2] = a[2] - b[2]; }
static void cross3(const double *a, const double *b, double *c) {
  c[0] = a[1]*b[2] - a[2]*b[1]; c[1] = a[2]*b[0] - a[0]*b[2]; c[2] = a[0]*b[1] - a[1]*b[0]; }
static double clamp01(double t) { return t < 0 ? 0 : (t > 1 ? 1 : t); }

/* closest point of p on triangle (a, b, c): the orthogonal projection where it falls inside,
   else the nearest of the three edges' clamped closest points (as contact.py does). */
static double closest_tri(const double *p, const double *a, const double *b, const double *c,
                          double *bary) {
  double ab[3], ac[3], ap[3];
  sub3(b, a, ab); sub3(c, a, ac); sub3(p, a, ap);
  double d00 = dot3(ab, ab), d01 = dot3(ab, ac), d11 = dot3(ac, ac);
  double d20 = dot3(ap, ab), d21 = dot3(ap, ac), den = d00 * d11 - d01 * d01;
  double v = (d11 * d20 - d01 * d21) / den, w = (d00 * d21 - d01 * d20) / den, u = 1 - v - w;
  if (u >= 0 && v >= 0 && w >= 0) {
    double q[3];
    for (int k = 0; k < 3; k++) q[k] = a[k] + v * ab[k] + w * ac[k] - p[k];
    bary[0] = u; bary[1] = v; bary[2] = w;
    return sqrt(dot3(q, q));
  }
  const double *V[3] = {a, b, c};
  double best = INFINITY;
  for (int i = 0; i < 3; i++) {
    int j = (i + 1) % 3;
    double e[3], pv[3];
    sub3(V[j], V[i], e); sub3(p, V[i], pv);
    double t = clamp01(dot3(pv, e) / dot3(e, e)), r[3];
    for (int k = 0; k < 3; k++) r[k] = pv[k] - t * e[k];
    double dist = sqrt(dot3(r, r));
    if (dist < best) {
      best = dist;
      bary[0] = bary[1] = bary[2] = 0; bary[i] = 1 - t; bary[j] = t;
    }
  }
  return best;
}

/* distance of node p = y[0:3] to triangle y[3:12] and its gradient (envelope theorem) */
static double pt_one(const double *y, double *g) {
  double xi[3];
  double d = closest_tri(y, y + 3, y + 6, y + 9, xi);
  double nu[3], dd = d > 1e-300 ? d : 1e-300;
  for (int k = 0; k < 3; k++) {
    double q = xi[0] * y[3 + k] + xi[1] * y[6 + k] + xi[2] * y[9 + k];
    nu[k] = (y[k] - q) / dd;
  }
  for (int k = 0; k < 3; k++) {
    g[k] = nu[k]; g[3 + k] = -xi[0] * nu[k]; g[6 + k] = -xi[1] * nu[k];
    g[9 + k] = -xi[2] * nu[k];
  }
  return d;
}

void pt_grad(long m, const double *y, double *d, double *g) {
  PAR
  for (long i = 0; i < m; i++) d[i] = pt_one(y + 12 * i, g + 12 * i);
}

/* Which feature of the triangle is closest to the node: 0 the face, 1 + i the edge from
   vertex i to i + 1, 4 + i vertex i (the same choice as closest_tri). */
static int pt_type(const double *y) {
  const double *p = y, *a = y + 3, *b = y + 6, *c = y + 9;
  double xi[3];
  closest_tri(p, a, b, c, xi);
  int nz = (xi[0] > 0) + (xi[1] > 0) + (xi[2] > 0);
  if (nz == 3) return 0;
  if (nz == 1) return 4 + (xi[0] > 0 ? 0 : (xi[1] > 0 ? 1 : 2));
  if (xi[2] == 0) return 1;          /* edge 0-1 */
  if (xi[0] == 0) return 2;          /* edge 1-2 */
  return 3;                          /* edge 2-0 */
}

/* the closest point's weights xi on the feature `type` extended smoothly (plane, line, point):
   the distance's curvature is that of the feature the node is closest to, with no kink where
   the closest feature changes */
static void pt_params(const double *y, int type, double *xi) {
  const double *p = y, *V[3] = {y + 3, y + 6, y + 9};
  xi[0] = xi[1] = xi[2] = 0;
  if (type == 0) {
    double ab[3], ac[3], ap[3];
    sub3(V[1], V[0], ab); sub3(V[2], V[0], ac); sub3(p, V[0], ap);
    double d00 = dot3(ab, ab), d01 = dot3(ab, ac), d11 = dot3(ac, ac);
    double d20 = dot3(ap, ab), d21 = dot3(ap, ac), den = d00 * d11 - d01 * d01;
    xi[1] = (d11 * d20 - d01 * d21) / den; xi[2] = (d00 * d21 - d01 * d20) / den;
    xi[0] = 1 - xi[1] - xi[2];
  } else if (type <= 3) {
    int i = type - 1, j = (i + 1) % 3;
    double e[3], pv[3];
    sub3(V[j], V[i], e); sub3(p, V[i], pv);
    double t = dot3(pv, e) / dot3(e, e);
    xi[i] = 1 - t; xi[j] = t;
  } else {
    xi[type - 4] = 1;
  }
}

/* h = (h + h^T) / 2 for a 12 x 12 row-major block */
static void symmetrise12(double *h) {
  for (int r = 0; r < 12; r++)
    for (int c = r + 1; c < 12; c++) {
      double s = 0.5 * (h[12 * r + c] + h[12 * c + r]);
      h[12 * r + c] = h[12 * c + r] = s;
    }
}

/* The curvature of a distance that is the minimum over closest-point parameters, into h
   (12 x 12, row-major). The closest points' difference is r = sum_n c_n y_n over the four
   points y_n = y[3n..3n+2], with weights c_n affine in the nz free parameters z
   (dc_n/dz_q = beta[2n + q]), given at the minimiser. For f(y, z) = |r|^2 the minimum's
   value g(y) = f(y, z*(y)) has the Hessian f_yy - f_yz f_zz^-1 f_zy (f_z = 0 there), and
   d = sqrt(g):
       d2d = [c c^T (x) (I - nu nu^T) - B A^-1 B^T] / d,
   A_qk = e_q . e_k, B_(n,i),q = c_n e_q,i + beta_nq r_i, e_q = dr/dz_q = sum_n beta_nq y_n,
   nu = r / d. Fixed parameters (an end of a segment, a vertex) are no z: nz = 0 gives the
   curvature of a point-point distance. Returns d and nu. */
static double dist_curv(const double *y, const double *c, const double *beta, int nz,
                        double *nu, double *h) {
  double r[3] = {0, 0, 0}, e[2][3] = {{0, 0, 0}, {0, 0, 0}};
  for (int n = 0; n < 4; n++)
    for (int k = 0; k < 3; k++) {
      r[k] += c[n] * y[3 * n + k];
      for (int q = 0; q < nz; q++) e[q][k] += beta[2 * n + q] * y[3 * n + k];
    }
  double d = sqrt(dot3(r, r)), dd = d > 1e-300 ? d : 1e-300, P[9];
  for (int k = 0; k < 3; k++) nu[k] = r[k] / dd;
  for (int i = 0; i < 3; i++)
    for (int j = 0; j < 3; j++) P[3 * i + j] = ((i == j) - nu[i] * nu[j]) / dd;
  for (int n = 0; n < 4; n++)
    for (int m = 0; m < 4; m++) {
      double cc = c[n] * c[m];
      for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) h[12 * (3 * n + i) + 3 * m + j] = cc * P[3 * i + j];
    }
  if (nz == 0) return d;
  double Ai[4];          /* A^-1 / d */
  if (nz == 1) {
    double a = dot3(e[0], e[0]);
    if (!(a > 0)) return d;
    Ai[0] = 1 / (a * dd);
  } else {
    double a00 = dot3(e[0], e[0]), a01 = dot3(e[0], e[1]), a11 = dot3(e[1], e[1]);
    double det = a00 * a11 - a01 * a01;
    if (!(det > 0)) return d;
    Ai[0] = a11 / (det * dd); Ai[1] = Ai[2] = -a01 / (det * dd); Ai[3] = a00 / (det * dd);
  }
  double B[12][2], BA[12][2];
  for (int n = 0; n < 4; n++)
    for (int i = 0; i < 3; i++)
      for (int q = 0; q < nz; q++) B[3 * n + i][q] = c[n] * e[q][i] + beta[2 * n + q] * r[i];
  for (int p = 0; p < 12; p++)
    for (int q = 0; q < nz; q++) {
      double v = 0;
      for (int k = 0; k < nz; k++) v += B[p][k] * Ai[nz * k + q];
      BA[p][q] = v;
    }
  for (int p = 0; p < 12; p++)
    for (int q = p; q < 12; q++) {
      double v = 0;
      for (int k = 0; k < nz; k++) v += BA[p][k] * B[q][k];
      h[12 * p + q] -= v;
      if (q != p) h[12 * q + p] -= v;
    }
  return d;
}

/* the curvature of one node-triangle distance into h (12 x 12): that of the closest feature
   (face: the two barycentric weights free; edge: its parameter; vertex: none) */
static void pt_hess_one(const double *y, double *h) {
  int type = pt_type(y);
  double xi[3], nu[3], beta[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  pt_params(y, type, xi);
  double c[4] = {1, -xi[0], -xi[1], -xi[2]};
  int nz = 0;
  if (type == 0) {   /* z = (xi_1, xi_2), xi_0 = 1 - z_0 - z_1 */
    beta[2] = beta[3] = 1; beta[4] = -1; beta[7] = -1; nz = 2;
  } else if (type <= 3) {   /* z = t, xi_i = 1 - t, xi_j = t */
    int i = type - 1, j = (i + 1) % 3;
    beta[2 * (1 + i)] = 1; beta[2 * (1 + j)] = -1; nz = 1;
  }
  dist_curv(y, c, beta, nz, nu, h);
}

void pt_hess(long m, const double *y, double *H) {
  PAR
  for (long i = 0; i < m; i++) pt_hess_one(y + 12 * i, H + 144 * i);
}

/* the barrier's blocks dphi d2d + ddphi dd dd^T of node-triangle pairs (dd (m, 12) the
   distances' gradients), as contact.Contact builds them in numpy: the same operations in
   the same order, in one pass instead of three over 144 m doubles */
void pt_stiff(long m, const double *y, const double *dphi, const double *ddphi,
              const double *dd, double *H) {
  PAR
  for (long i = 0; i < m; i++) {
    double *h = H + 144 * i;
    const double *g = dd + 12 * i;
    pt_hess_one(y + 12 * i, h);
    for (int r = 0; r < 12; r++) {
      double a = ddphi[i] * g[r];
      for (int c = 0; c < 12; c++) h[12 * r + c] = h[12 * r + c] * dphi[i] + a * g[c];
    }
  }
}

/* segment distance with the clamped closest-point parameters (Ericson 5.1.9) */
static double seg_closest(const double *p0, const double *p1, const double *q0,
                          const double *q1, double *sp, double *tp) {
  double d1[3], d2[3], r[3];
  sub3(p1, p0, d1); sub3(q1, q0, d2); sub3(p0, q0, r);
  double a = dot3(d1, d1), e = dot3(d2, d2), b = dot3(d1, d2), c = dot3(d1, r);
  double f = dot3(d2, r), eps = 1e-24, s = 0, t = 0;
  int pa = a > eps, pe = e > eps;
  double den = a * e - b * b;
  if (pa && pe && den > 1e-12 * a * e) s = (b * f - c * e) / den;
  if (pa && !pe) s = -c / a;
  s = clamp01(s);
  t = pe ? (b * s + f) / e : 0.0;
  double tc = clamp01(t);
  if (pa && tc != t) s = clamp01((tc * b - c) / a);
  double w[3];
  for (int k = 0; k < 3; k++) w[k] = p0[k] + s * d1[k] - (q0[k] + tc * d2[k]);
  *sp = s; *tp = tc;
  return sqrt(dot3(w, w));
}

/* IPC's log barrier with unit stiffness and its first two derivatives in d: infinite (no
   slope) at d <= 0, 0 from d = delta */
static void barrier1(double d, double delta, double *b, double *db, double *ddb) {
  if (d <= 0) { *b = INFINITY; *db = *ddb = 0; return; }
  if (d >= delta) { *b = *db = *ddb = 0; return; }
  double g = d - delta, l = log(d / delta);
  *b = -g * g * l;
  *db = -(2 * g * l + g * g / d);
  *ddb = -(2 * l + 4 * g / d - g * g / (d * d));
}

/* IPC's edge-edge mollifier m(c) of c = |ea x eb|^2, ea = a1 - a0, eb = b1 - b0 (y the
   pair's 12 coordinates), and its first two derivatives in c; gc the gradient of c in y */
static void ee_mollifier(const double *y, double eps, double *m, double *dm, double *ddm,
                         double *gc) {
  double ea[3], eb[3], n[3], dca[3], dcb[3];
  sub3(y + 3, y, ea); sub3(y + 9, y + 6, eb); cross3(ea, eb, n);
  double r = dot3(n, n) / eps;
  cross3(eb, n, dca); cross3(n, ea, dcb);
  for (int k = 0; k < 3; k++) {
    gc[k] = -2 * dca[k]; gc[3 + k] = 2 * dca[k]; gc[6 + k] = -2 * dcb[k]; gc[9 + k] = 2 * dcb[k];
  }
  *m = 1; *dm = *ddm = 0;
  if (r < 1) { *m = (2 - r) * r; *dm = 2 * (1 - r) / eps; *ddm = -2 / (eps * eps); }
}

/* closest-point parameters of a case: fs/ft < 0 free (the lines' own minimiser, given the
   other), else fixed at that value (an end of the segment) */
static void ee_params(const double *y, double fs, double ft, double *sp, double *tp) {
  const double *a0 = y, *a1 = y + 3, *b0 = y + 6, *b1 = y + 9;
  double d1[3], d2[3], r[3];
  sub3(a1, a0, d1); sub3(b1, b0, d2); sub3(a0, b0, r);
  double a = dot3(d1, d1), e = dot3(d2, d2), b = dot3(d1, d2), c = dot3(d1, r);
  double f = dot3(d2, r), den = a * e - b * b, s = fs, t = ft;
  if (fs < 0 && ft < 0) { s = (b * f - c * e) / den; t = (a * f - b * c) / den; }
  else if (fs < 0) s = (t * b - c) / a;
  else if (ft < 0) t = (b * s + f) / e;
  *sp = s; *tp = t;
}

/* the mollified edge-edge barrier of one pair, its gradient (g) and the distance (dist) */
static double ee_one(const double *y, double w, double eps, double delta, double *g,
                     double *dist) {
  const double *a0 = y, *a1 = y + 3, *b0 = y + 6, *b1 = y + 9;
  double s, t, d = seg_closest(a0, a1, b0, b1, &s, &t);
  *dist = d;
  double nu[3], dd = d > 1e-300 ? d : 1e-300;
  for (int k = 0; k < 3; k++)
    nu[k] = (a0[k] + s * (a1[k] - a0[k]) - b0[k] - t * (b1[k] - b0[k])) / dd;
  double moll, dmoll, ddmoll, gc[12], b, db, ddb;
  ee_mollifier(y, eps, &moll, &dmoll, &ddmoll, gc);
  barrier1(d, delta, &b, &db, &ddb);
  double kc = w * dmoll * b, kd = w * moll * db;
  for (int k = 0; k < 3; k++) {
    g[k] = kc * gc[k] + kd * (1 - s) * nu[k];
    g[3 + k] = kc * gc[3 + k] + kd * s * nu[k];
    g[6 + k] = kc * gc[6 + k] - kd * (1 - t) * nu[k];
    g[9 + k] = kc * gc[9 + k] - kd * t * nu[k];
  }
  return w * moll * b;
}

void ee_energy(long m, const double *y, const double *w, const double *eps, double delta,
               double *E, double *g, double *d) {
  PAR
  for (long i = 0; i < m; i++)
    E[i] = ee_one(y + 12 * i, w[i], eps[i], delta, g + 12 * i, d + i);
}

/* The Hessian of one mollified edge-edge barrier w m(c) b(d), exact, into h (12 x 12):
       w [m'' b gc gc^T + m' b Hc + m' b' (gc gd^T + gd gc^T) + m b'' gd gd^T + m b' Hd]
   with gc, Hc the derivatives of c = |ea x eb|^2 = |ea|^2 |eb|^2 - (ea . eb)^2 and gd, Hd
   those of the segment distance (dist_curv) in the case found at y: an end parameter (0 or 1)
   stays fixed, an interior one follows the lines (the gradient, ee_one, is that case's) */
static void ee_hess_one(const double *y, double w, double eps, double delta, double *h) {
  double s0, t0;
  seg_closest(y, y + 3, y + 6, y + 9, &s0, &t0);
  double fs = (s0 <= 0 || s0 >= 1) ? s0 : -1, ft = (t0 <= 0 || t0 >= 1) ? t0 : -1, s, t;
  ee_params(y, fs, ft, &s, &t);
  double c[4] = {1 - s, s, -(1 - t), -t}, beta[8] = {0, 0, 0, 0, 0, 0, 0, 0}, nu[3];
  int nz = 0;
  if (fs < 0) { beta[nz] = -1; beta[2 + nz] = 1; nz++; }
  if (ft < 0) { beta[4 + nz] = 1; beta[6 + nz] = -1; nz++; }
  double d = dist_curv(y, c, beta, nz, nu, h), b, db, ddb;
  if (!(d > 0 && d < delta)) { memset(h, 0, 144 * sizeof(double)); return; }
  barrier1(d, delta, &b, &db, &ddb);
  double m, dm, ddm, gc[12], gd[12];
  ee_mollifier(y, eps, &m, &dm, &ddm, gc);
  for (int q = 0; q < 4; q++)
    for (int k = 0; k < 3; k++) gd[3 * q + k] = c[q] * nu[k];
  double kd = w * m * db, kdd = w * m * ddb, kcc = w * ddm * b, kcd = w * dm * db;
  for (int p = 0; p < 12; p++)
    for (int q = 0; q < 12; q++)
      h[12 * p + q] = kd * h[12 * p + q] + kdd * gd[p] * gd[q] + kcc * gc[p] * gc[q]
                      + kcd * (gc[p] * gd[q] + gd[p] * gc[q]);
  if (dm != 0) {   /* w m' b Hc, Hc over (ea, eb) mapped by ea = a1 - a0, eb = b1 - b0 */
    double ea[3], eb[3];
    sub3(y + 3, y, ea); sub3(y + 9, y + 6, eb);
    double kc = w * dm * b, A2 = dot3(ea, ea), B2 = dot3(eb, eb), AB = dot3(ea, eb);
    double Caa[9], Cbb[9], Cab[9];
    for (int i = 0; i < 3; i++)
      for (int j = 0; j < 3; j++) {
        double I = i == j;
        Caa[3 * i + j] = 2 * (B2 * I - eb[i] * eb[j]);
        Cbb[3 * i + j] = 2 * (A2 * I - ea[i] * ea[j]);
        Cab[3 * i + j] = 2 * (2 * ea[i] * eb[j] - eb[i] * ea[j] - AB * I);
      }
    const double pa[4] = {-1, 1, 0, 0}, pb[4] = {0, 0, -1, 1};
    for (int u = 0; u < 4; u++)
      for (int v = 0; v < 4; v++)
        for (int i = 0; i < 3; i++)
          for (int j = 0; j < 3; j++)
            h[12 * (3 * u + i) + 3 * v + j] += kc * (pa[u] * pa[v] * Caa[3 * i + j]
                + pa[u] * pb[v] * Cab[3 * i + j] + pb[u] * pa[v] * Cab[3 * j + i]
                + pb[u] * pb[v] * Cbb[3 * i + j]);
  }
}

void ee_hess(long m, const double *y, const double *w, const double *eps, double delta,
             double *H) {
  PAR
  for (long i = 0; i < m; i++) ee_hess_one(y + 12 * i, w[i], eps[i], delta, H + 144 * i);
}

/* distances of nodes x[s[k]] to triangles cells[t[k]] (positions x (n, 3), cells (c, 3)):
   the narrow phase of the candidate lists, reading the positions through the indices (a numpy
   gather of the pairs' coordinates cost as much as the distances); the closest points'
   barycentric coordinates into bary (m, 3) unless it is NULL */
void pt_dist(long m, const double *x, const int64_t *cells, const int64_t *s, const int64_t *t,
             double *d, double *bary) {
  PAR
  for (long k = 0; k < m; k++) {
    double b[3];
    const int64_t *c = cells + 3 * t[k];
    d[k] = closest_tri(x + 3 * s[k], x + 3 * c[0], x + 3 * c[1], x + 3 * c[2], b);
    if (bary) for (int i = 0; i < 3; i++) bary[3 * k + i] = b[i];
  }
}

/* distances of the segments edges[i[k]] and edges[j[k]] (edges (e, 2) node indices) */
void ee_dist(long m, const double *x, const int64_t *edges, const int64_t *i, const int64_t *j,
             double *d) {
  PAR
  for (long k = 0; k < m; k++) {
    double s, t;
    const int64_t *a = edges + 2 * i[k], *b = edges + 2 * j[k];
    d[k] = seg_closest(x + 3 * a[0], x + 3 * a[1], x + 3 * b[0], x + 3 * b[1], &s, &t);
  }
}

/* pt_dist where a pair may be closer than cut: the pair k is at least lb[k] - D[node] -
   max D[vertex] apart (lb its distance, or a lower bound of it, at positions from which
   each node n has since moved by D[n]); where that is cut or more, d[k] stays as it was
   (INFINITY: not computed). Entries of d already finite are kept (a call with a larger cut
   completes an earlier one). */
void pt_dist_cut(long m, const double *x, const int64_t *cells, const int64_t *s,
                 const int64_t *t, const double *lb, const double *D, double cut, double *d) {
  PAR
  for (long k = 0; k < m; k++) {
    if (isfinite(d[k])) continue;
    const int64_t *c = cells + 3 * t[k];
    double Dt = D[c[0]] > D[c[1]] ? D[c[0]] : D[c[1]];
    Dt = Dt > D[c[2]] ? Dt : D[c[2]];
    if (lb[k] - D[s[k]] - Dt >= cut) continue;
    double bary[3];
    d[k] = closest_tri(x + 3 * s[k], x + 3 * c[0], x + 3 * c[1], x + 3 * c[2], bary);
  }
}

/* ee_dist where a pair may be closer than cut (as pt_dist_cut) */
void ee_dist_cut(long m, const double *x, const int64_t *edges, const int64_t *i,
                 const int64_t *j, const double *lb, const double *D, double cut, double *d) {
  PAR
  for (long k = 0; k < m; k++) {
    if (isfinite(d[k])) continue;
    const int64_t *a = edges + 2 * i[k], *b = edges + 2 * j[k];
    double Da = D[a[0]] > D[a[1]] ? D[a[0]] : D[a[1]];
    double Db = D[b[0]] > D[b[1]] ? D[b[0]] : D[b[1]];
    if (lb[k] - Da - Db >= cut) continue;
    double s, t;
    d[k] = seg_closest(x + 3 * a[0], x + 3 * a[1], x + 3 * b[0], x + 3 * b[1], &s, &t);
  }
}

/* The dihedral angle of a hinge y = (c, d, a, b) (12 doubles): the edge from a to b, c the
   third node of one triangle and d of the other. With the normals N1 = (c - a) x (c - b),
   N2 = (d - b) x (d - a) (parallel in a flat hinge, whatever the cells' orientation), the angle
   is atan2((n1 x n2) . e, n1 . n2), e the unit edge; its cosine and sine, and (g not NULL) its
   gradient: -|E| Ni / |Ni|^2 at the opposite nodes, and at the edge nodes the combinations of
   Bridson et al. (2003), whose sign convention is the opposite of this angle's. */
static void hinge_angle(const double *y, double *cs, double *sn, double *g) {
  const double *c = y, *d = y + 3, *a = y + 6, *b = y + 9;
  double E[3], ca[3], cb[3], db[3], da[3], N1[3], N2[3], n12[3];
  sub3(b, a, E); sub3(c, a, ca); sub3(c, b, cb); sub3(d, b, db); sub3(d, a, da);
  cross3(ca, cb, N1); cross3(db, da, N2);
  double L2 = dot3(E, E), L = sqrt(L2), A1 = dot3(N1, N1), A2 = dot3(N2, N2);
  A1 = A1 > 1e-300 ? A1 : 1e-300; A2 = A2 > 1e-300 ? A2 : 1e-300;
  double r12 = 1.0 / sqrt(A1 * A2);
  cross3(N1, N2, n12);
  *cs = dot3(N1, N2) * r12;
  *sn = dot3(n12, E) * r12 / (L > 1e-300 ? L : 1e-300);
  if (g == NULL) return;
  double w1 = dot3(cb, E) / L, w2 = dot3(db, E) / L;     /* (x1 - x4) . E / |E| etc. */
  double v1 = dot3(ca, E) / L, v2 = dot3(da, E) / L;
  for (int k = 0; k < 3; k++) {
    double q1 = N1[k] / A1, q2 = N2[k] / A2;
    g[k] = -L * q1;
    g[3 + k] = -L * q2;
    g[6 + k] = -(w1 * q1 + w2 * q2);
    g[9 + k] = v1 * q1 + v2 * q2;
  }
}

void hinge_cos_sin(long m, const double *y, double *c, double *s) {
  PAR
  for (long i = 0; i < m; i++) hinge_angle(y + 12 * i, c + i, s + i, NULL);
}

/* hinge energies k (1 - cos(theta - theta0)) and their gradients, theta0 given by its cosine
   c0 and sine s0 */
void hinge_energy(long m, const double *y, const double *c0, const double *s0,
                  const double *k, double *E, double *g) {
  PAR
  for (long i = 0; i < m; i++) {
    double cs, sn, *gi = g + 12 * i;
    hinge_angle(y + 12 * i, &cs, &sn, gi);
    E[i] = k[i] * (1.0 - (cs * c0[i] + sn * s0[i]));
    double f = k[i] * (sn * c0[i] - cs * s0[i]);          /* k sin(theta - theta0) */
    for (int j = 0; j < 12; j++) gi[j] *= f;
  }
}

/* Hessians k cos(theta - theta0) g g^T + k sin(theta - theta0) H_theta, the curvature of the
   angle by central differences of its exact gradient (step rel x the edge length) */
/* the Hessian of one hinge into h (12 x 12, row-major, symmetric) */
static void hinge_hess_one(const double *y, double c0, double s0, double k, double rel,
                           double *h) {
  double yy[12], g0[12], gp[12], gm[12], cs, sn;
  memcpy(yy, y, sizeof yy);
  hinge_angle(yy, &cs, &sn, g0);
  double e[3];
  sub3(yy + 9, yy + 6, e);
  double step = rel * sqrt(dot3(e, e));
  step = step > 1e-12 ? step : 1e-12;
  double fc = k * (cs * c0 + sn * s0), fs = k * (sn * c0 - cs * s0);
  for (int j = 0; j < 12; j++) {
    double keep = yy[j], dc, ds;
    yy[j] = keep + step; hinge_angle(yy, &dc, &ds, gp);
    yy[j] = keep - step; hinge_angle(yy, &dc, &ds, gm);
    yy[j] = keep;
    for (int r = 0; r < 12; r++)
      h[12 * r + j] = fc * g0[r] * g0[j] + fs * (gp[r] - gm[r]) / (2 * step);
  }
  symmetrise12(h);
}

void hinge_hess(long m, const double *y, const double *c0, const double *s0, const double *k,
                double rel, double *H) {
  PAR
  for (long i = 0; i < m; i++) hinge_hess_one(y + 12 * i, c0[i], s0[i], k[i], rel, H + 144 * i);
}

/* the Hessians summed into a fixed sparse pattern: entry q of hinge i is added to
   vals[place[144 i + q]] (skipped where place is negative: a fixed dof). The Hessians of a
   chunk of hinges are computed in parallel, then added in the hinges' order, so the sums do
   not depend on the number of threads. */
void hinge_hess_add(long m, const double *y, const double *c0, const double *s0,
                    const double *k, double rel, const int64_t *place, double *vals) {
  const long chunk = 4096;
  double *h = malloc(sizeof(double) * 144 * (m < chunk ? (m > 0 ? m : 1) : chunk));
  if (h == NULL) {                     /* no room for a chunk: one hinge at a time */
    double one[144];
    for (long i = 0; i < m; i++) {
      hinge_hess_one(y + 12 * i, c0[i], s0[i], k[i], rel, one);
      const int64_t *p = place + 144 * i;
      for (int q = 0; q < 144; q++)
        if (p[q] >= 0) vals[p[q]] += one[q];
    }
    return;
  }
  for (long i0 = 0; i0 < m; i0 += chunk) {
    long n = m - i0 < chunk ? m - i0 : chunk;
    #pragma omp parallel for schedule(static) num_threads(n_threads) if (n > 512)
    for (long i = 0; i < n; i++)
      hinge_hess_one(y + 12 * (i0 + i), c0[i0 + i], s0[i0 + i], k[i0 + i], rel, h + 144 * i);
    for (long i = 0; i < n; i++) {
      const int64_t *p = place + 144 * (i0 + i);
      for (int q = 0; q < 144; q++)
        if (p[q] >= 0) vals[p[q]] += h[144 * i + q];
    }
  }
  free(h);
}

/* The point terms' tangent as CSR rows (3 N of them, the free dofs' entries only, columns
   sorted): the sum of G groups of element blocks, group g of m[g] elements of k[g] nodes
   nodes[g] (m, k) with stiffness K[g] (m, 3k, 3k), rows node-major. Each entry sums its
   blocks in the order (group, element, row node, column node), as the numpy version in
   mvfem.nodal does. Rows are bucketed by element row (a node of an element), not by 3 x 3
   block: k times fewer bucket entries, and no index arrays built outside. The node rows are
   then built in parallel: a first pass counts each one's entries (its column nodes), a
   second fills them at their offsets, each row's sums in the same order whatever the
   number of threads.
   work: 3 N + 1 + sum(m k) integers (the bucketing; every thread has its own marks, column
   list and accumulator). Returns the entries; -1 where memory ran out. */
#define SOME(v) (fr[3 * (v)] | fr[3 * (v) + 1] | fr[3 * (v) + 2])
#define NFREE(v) (fr[3 * (v)] + fr[3 * (v) + 1] + fr[3 * (v) + 2])
/* A row's element rows lie anywhere in K (their stiffness rows, 3 of 3 k doubles each, are
   read in bucket order): fetched AHEAD entries early, the rows of the 165,579 blocks of a
   twice-refined demo's fine tangent took 30 ms instead of 55-60 on two threads, 55 instead
   of 110 on one (4-32 ahead alike) */
#define AHEAD 8
#if defined(__GNUC__) || defined(__clang__)
#define PREFETCH(a) __builtin_prefetch(a)
#else
#define PREFETCH(a) ((void)0)
#endif
/* row node v's column nodes (free somewhere), sorted, into list; their count */
static long row_nodes(long v, const int64_t *start, const int64_t *bucket, const int64_t *k,
                      int64_t **nodes, const uint8_t *fr, int64_t *mark, int64_t *list) {
  long nc = 0;
  for (int64_t p = start[v]; p < start[v + 1]; p++) {
    int64_t g = bucket[p] >> 40, q = bucket[p] & (((int64_t)1 << 40) - 1);
    const int64_t *el = nodes[g] + (q / k[g]) * k[g];
    for (long b = 0; b < k[g]; b++) {
      int64_t w = el[b];
      if (SOME(w) && mark[w] != v) { mark[w] = v; list[nc++] = w; }
    }
  }
  for (long a = 1; a < nc; a++) {   /* the row's column nodes, sorted (tens of them) */
    int64_t w = list[a];
    long b = a - 1;
    while (b >= 0 && list[b] > w) { list[b + 1] = list[b]; b--; }
    list[b + 1] = w;
  }
  return nc;
}

long elements_csr(long G, const int64_t *m, const int64_t *k, int64_t **nodes, double **K,
                  long N, const uint8_t *fr, int64_t *indptr, int64_t *cols, double *vals,
                  int64_t *work) {
  long n = 0;
  for (long g = 0; g < G; g++) n += m[g] * k[g];
  int64_t *start = work, *mark = work + N + 1, *count = mark + N;
  int64_t *bucket = count + N;                 /* (group, element row) as g 2^40 + e k + a */
  for (long v = 0; v <= N; v++) start[v] = 0;
  for (long g = 0; g < G; g++)
    for (long q = 0; q < m[g] * k[g]; q++)
      if (SOME(nodes[g][q])) start[nodes[g][q] + 1]++;
  for (long v = 0; v < N; v++) { start[v + 1] += start[v]; mark[v] = start[v]; }
  for (long g = 0; g < G; g++)            /* each row's element rows, in order */
    for (long q = 0; q < m[g] * k[g]; q++) {
      int64_t v = nodes[g][q];
      if (SOME(v)) bucket[mark[v]++] = ((int64_t)g << 40) + q;
    }
  int nt = 1;
#ifdef _OPENMP
  if (n > 4096) nt = n_threads;
#endif
  long NN = N > 0 ? N : 1;
  int64_t *scratch = malloc(sizeof(int64_t) * 3 * NN * nt);   /* marks, list, slots */
  double *accs = malloc(sizeof(double) * 9 * NN * nt);
  if (scratch == NULL || accs == NULL) { free(scratch); free(accs); return -1; }
  #pragma omp parallel num_threads(nt)
  {
    int id = 0;
#ifdef _OPENMP
    id = omp_get_thread_num();
#endif
    int64_t *tm = scratch + 3 * NN * id, *tl = tm + NN, *ts = tl + NN;
    double *ta = accs + 9 * NN * id;
    for (long v = 0; v < N; v++) tm[v] = -1;
    #pragma omp for schedule(static)
    for (long v = 0; v < N; v++) {      /* entries per row of node v: its free column dofs */
      long nc = row_nodes(v, start, bucket, k, nodes, fr, tm, tl), c = 0;
      for (long a = 0; a < nc; a++) c += NFREE(tl[a]);
      count[v] = c;
    }
    #pragma omp single
    {
      indptr[0] = 0;
      for (long v = 0; v < N; v++)
        for (int i = 0; i < 3; i++)
          indptr[3 * v + i + 1] = indptr[3 * v + i] + (fr[3 * v + i] ? count[v] : 0);
    }
    for (long v = 0; v < N; v++) tm[v] = -1;
    #pragma omp for schedule(static)
    for (long v = 0; v < N; v++) {
      long nc = row_nodes(v, start, bucket, k, nodes, fr, tm, tl);
      for (long a = 0; a < nc; a++) ts[tl[a]] = a;
      for (long a = 0; a < 9 * nc; a++) ta[a] = 0.0;
      for (int64_t p = start[v]; p < start[v + 1]; p++) {
        if (p + AHEAD < start[N]) {   /* the stiffness rows of the element row AHEAD on */
          int64_t g2 = bucket[p + AHEAD] >> 40;
          int64_t q2 = bucket[p + AHEAD] & (((int64_t)1 << 40) - 1);
          long k2 = k[g2];
          const char *f = (const char *)(K[g2] + 9 * k2 * q2);   /* 9 k^2 e + 3 a (3 k) */
          for (long c = 0; c < (long)(9 * k2 * sizeof(double)); c += 64) PREFETCH(f + c);
          PREFETCH(nodes[g2] + q2 - q2 % k2);
        }
        int64_t g = bucket[p] >> 40, q = bucket[p] & (((int64_t)1 << 40) - 1);
        long kk = k[g], e = q / kk, a = q % kk, st = 3 * kk;
        const int64_t *el = nodes[g] + e * kk;
        const double *Ke = K[g] + 9 * kk * kk * e + 3 * a * st;
        for (long b = 0; b < kk; b++) {
          if (!SOME(el[b])) continue;
          double *to = ta + 9 * ts[el[b]];
          const double *from = Ke + 3 * b;
          for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) to[3 * i + j] += from[i * st + j];
        }
      }
      for (int i = 0; i < 3; i++) {
        if (!fr[3 * v + i]) continue;
        int64_t at = indptr[3 * v + i];
        for (long a = 0; a < nc; a++)
          for (int j = 0; j < 3; j++)
            if (fr[3 * tl[a] + j]) {
              cols[at] = 3 * tl[a] + j;
              vals[at++] = ta[9 * a + 3 * i + j];
            }
      }
    }
  }
  free(scratch); free(accs);
  return indptr[3 * N];
}
#undef NFREE
#undef AHEAD
#undef SOME

/* The CSR rows of elements_csr (3 N rows, node-major, columns sorted) without the 3 x 3
   node blocks all of whose entries are zero, in place: the new number of entries. A contact
   pair's 12 x 12 block is zero wherever its closest points leave a node out (a node beyond
   the edge or vertex of the triangle that is closest, an edge's end beyond the other
   edge's closest point); kept, those zeros were a third of the twice-refined demo's matrix
   and half of MUMPS's factorisation. mark: N integers (scratch). */
long csr_drop_zero_blocks(long N, int64_t *indptr, int64_t *cols, double *vals,
                          int64_t *mark) {
  for (long w = 0; w < N; w++) mark[w] = -1;
  int64_t at = 0, next = indptr[0];
  for (long v = 0; v < N; v++) {
    int64_t lo = next, hi = indptr[3 * v + 3];
    for (int64_t p = lo; p < hi; p++)
      if (vals[p] != 0.0) mark[cols[p] / 3] = v;
    for (int i = 0; i < 3; i++) {
      int64_t r = 3 * v + i, end = indptr[r + 1];
      for (int64_t p = next; p < end; p++)
        if (mark[cols[p] / 3] == v) { cols[at] = cols[p]; vals[at++] = vals[p]; }
      next = end;
      indptr[r + 1] = at;
    }
  }
  return at;
}

/* How many entries of the CSR pattern b (n rows, columns sorted in each row) are not in the
   pattern a (same rows, columns sorted): a merge of each row pair. */
long csr_missing(long n, const int64_t *ia, const int64_t *ja, const int64_t *ib,
                 const int64_t *jb) {
  long missing = 0;
  for (long r = 0; r < n; r++) {
    int64_t p = ia[r], pe = ia[r + 1];
    for (int64_t q = ib[r]; q < ib[r + 1]; q++) {
      while (p < pe && ja[p] < jb[q]) p++;
      if (p == pe || ja[p] != jb[q]) missing++;
    }
  }
  return missing;
}

/* The union of the CSR patterns a and b (n rows, columns sorted and distinct in each row)
   into ic (n + 1 entries) and jc (room for both): a merge of each row pair, its columns
   sorted and distinct; returns its entry count. */
long csr_union(long n, const int64_t *ia, const int64_t *ja, const int64_t *ib,
               const int64_t *jb, int64_t *ic, int64_t *jc) {
  long at = 0;
  ic[0] = 0;
  for (long r = 0; r < n; r++) {
    int64_t p = ia[r], pe = ia[r + 1], q = ib[r], qe = ib[r + 1];
    while (p < pe || q < qe) {
      if (q == qe || (p < pe && ja[p] < jb[q])) {
        jc[at++] = ja[p++];
      } else if (p == pe || jb[q] < ja[p]) {
        jc[at++] = jb[q++];
      } else {            /* in both */
        jc[at++] = ja[p++];
        q++;
      }
    }
    ic[r + 1] = at;
  }
  return at;
}

/* sqrt(a^2 + b^2): libm's hypot, careful about overflow, took a third of a projection's
   time; the plain formula where the squares cannot overflow */
static inline double pyth(double a, double b) {
  double fa = fabs(a), fb = fabs(b);
  return (fa < 1e150 && fb < 1e150) ? sqrt(a * a + b * b) : hypot(a, b);
}

/* Symmetric eigenproblems of small blocks (the PSD projection below), after EISPACK's tred2
   and tql2. Householder reduction of the symmetric a (n x n, row-major) to tridiagonal form:
   diagonal d, subdiagonal e (e[0] = 0); a is replaced by the orthogonal transformation */
static void tridiagonal(int n, double *a, double *d, double *e) {
  for (int i = n - 1; i > 0; i--) {
    int l = i - 1;
    double h = 0.0, scale = 0.0;
    if (l > 0) {
      for (int k = 0; k <= l; k++) scale += fabs(a[i * n + k]);
      if (scale == 0.0) {
        e[i] = a[i * n + l];
      } else {
        for (int k = 0; k <= l; k++) {
          a[i * n + k] /= scale;
          h += a[i * n + k] * a[i * n + k];
        }
        double f = a[i * n + l];
        double g = f >= 0.0 ? -sqrt(h) : sqrt(h);
        e[i] = scale * g;
        h -= f * g;
        a[i * n + l] = f - g;
        f = 0.0;
        for (int j = 0; j <= l; j++) {
          a[j * n + i] = a[i * n + j] / h;
          g = 0.0;
          for (int k = 0; k <= j; k++) g += a[j * n + k] * a[i * n + k];
          for (int k = j + 1; k <= l; k++) g += a[k * n + j] * a[i * n + k];
          e[j] = g / h;
          f += e[j] * a[i * n + j];
        }
        double hh = f / (h + h);
        for (int j = 0; j <= l; j++) {
          f = a[i * n + j];
          e[j] = g = e[j] - hh * f;
          for (int k = 0; k <= j; k++) a[j * n + k] -= f * e[k] + g * a[i * n + k];
        }
      }
    } else {
      e[i] = a[i * n + l];
    }
    d[i] = h;
  }
  d[0] = 0.0;
  e[0] = 0.0;
  for (int i = 0; i < n; i++) {
    int l = i - 1;
    if (d[i] != 0.0) {
      for (int j = 0; j <= l; j++) {
        double g = 0.0;
        for (int k = 0; k <= l; k++) g += a[i * n + k] * a[k * n + j];
        for (int k = 0; k <= l; k++) a[k * n + j] -= g * a[k * n + i];
      }
    }
    d[i] = a[i * n + i];
    a[i * n + i] = 1.0;
    for (int j = 0; j <= l; j++) a[j * n + i] = a[i * n + j] = 0.0;
  }
}

/* eigenvalues d and eigenvectors (the columns of z, on entry the transformation of
   tridiagonal()) of the tridiagonal matrix (d, e) by QL with implicit shifts; 0, or -1
   where 60 iterations did not split off an eigenvalue */
static int tridiagonal_ql(int n, double *d, double *e, double *z) {
  for (int i = 1; i < n; i++) e[i - 1] = e[i];
  e[n - 1] = 0.0;
  for (int l = 0; l < n; l++) {
    int iter = 0, m;
    do {
      for (m = l; m < n - 1; m++) {
        double dd = fabs(d[m]) + fabs(d[m + 1]);
        if (fabs(e[m]) <= DBL_EPSILON * dd) break;
      }
      if (m != l) {
        if (iter++ == 60) return -1;
        double g = (d[l + 1] - d[l]) / (2.0 * e[l]);
        double r = pyth(g, 1.0);
        g = d[m] - d[l] + e[l] / (g + (g >= 0.0 ? fabs(r) : -fabs(r)));
        double s = 1.0, c = 1.0, p = 0.0;
        int i;
        for (i = m - 1; i >= l; i--) {
          double f = s * e[i], b = c * e[i];
          e[i + 1] = r = pyth(f, g);
          if (r == 0.0) {
            d[i + 1] -= p;
            e[m] = 0.0;
            break;
          }
          s = f / r;
          c = g / r;
          g = d[i + 1] - p;
          r = (d[i] - g) * s + 2.0 * c * b;
          d[i + 1] = g + (p = s * r);
          g = c * r - b;
          for (int k = 0; k < n; k++) {
            f = z[k * n + i + 1];
            z[k * n + i + 1] = s * z[k * n + i] + c * f;
            z[k * n + i] = c * z[k * n + i] - s * f;
          }
        }
        if (r == 0.0 && i >= l) continue;
        d[l] -= p;
        e[l] = g;
        e[m] = 0.0;
      }
    } while (m != l);
  }
  return 0;
}

/* the positive semidefinite part of each symmetric block of K (m blocks of p points, n = 3p
   <= 12 rows), in place: K - sum over its negative eigenpairs of w v v^T. Blocks of an
   energy that a translation of all p points leaves unchanged (their 3 x 3 block rows sum to
   zero, to 1e-12 of the largest entry) are projected through the 3(p - 1) relative
   coordinates x_a - x_0: with T the map to those, K = T^T K_r T, K_r the trailing block of
   K. T T^T = C (x) I_3, C = I + 1 1^T = L L^T (Cholesky), so Q = T^T L^-T is an orthonormal
   basis of the non-translations, K = Q (L^T K_r L) Q^T, and the projection of K is that of
   the smaller L^T K_r L carried back by Q: 2.5 instead of 12 us a 12 x 12 contact block on
   one thread (LAPACK through numpy's eigh; scripts/psd_projection.py). Others are projected
   whole. fail[b] = 1 where QL did not converge (the block left unchanged) */
void psd_proj(long m, int p, double *K, int *fail) {
  int n = 3 * p, q = p - 1, r = 3 * q;
  double Lc[16];  /* Cholesky factor of I + 1 1^T ((p - 1) x (p - 1)) */
  for (int i = 0; i < q; i++)
    for (int j = 0; j <= i; j++) {
      double s = (i == j ? 2.0 : 1.0);
      for (int k = 0; k < j; k++) s -= Lc[i * 4 + k] * Lc[j * 4 + k];
      Lc[i * 4 + j] = i == j ? sqrt(s) : s / Lc[j * 4 + j];
    }
  PAR
  for (long b = 0; b < m; b++) {
    double *Kb = K + b * n * n;
    double z[144], d[12], e[12], U[144];
    double top = 0.0, sum = 0.0;
    for (int i = 0; i < n * n; i++) top = fmax(top, fabs(Kb[i]));
    for (int i = 0; i < 3 && q > 0; i++)
      for (int c = 0; c < n; c++) {
        double s = 0.0;
        for (int a = 0; a < p; a++) s += Kb[(3 * a + i) * n + c];
        sum = fmax(sum, fabs(s));
      }
    int reduced = q > 0 && sum <= 1e-12 * top, k_n = reduced ? r : n;
    if (reduced) {
      /* z = L^T K_r L, L = Lc (x) I_3: (L^T K_r L)[(a,i),(c,j)] = sum_{a'>=a, c'>=c}
         Lc[a'][a] K_r[(a',i),(c',j)] Lc[c'][c] */
      double t[144];
      for (int a = 0; a < q; a++) for (int i = 0; i < 3; i++)
        for (int cc = 0; cc < r; cc++) {
          double s = 0.0;
          for (int a2 = a; a2 < q; a2++) s += Lc[a2 * 4 + a] * Kb[(3 + 3 * a2 + i) * n + 3 + cc];
          t[(3 * a + i) * r + cc] = s;
        }
      for (int row = 0; row < r; row++)
        for (int c = 0; c < q; c++) for (int j = 0; j < 3; j++) {
          double s = 0.0;
          for (int c2 = c; c2 < q; c2++) s += t[row * r + 3 * c2 + j] * Lc[c2 * 4 + c];
          z[row * r + 3 * c + j] = s;
        }
    } else {
      memcpy(z, Kb, sizeof(double) * n * n);
    }
    tridiagonal(k_n, z, d, e);
    fail[b] = tridiagonal_ql(k_n, d, e, z) != 0;
    if (fail[b]) continue;
    int neg = 0;
    for (int k = 0; k < k_n; k++) neg += d[k] < 0.0;
    if (!neg) continue;
    int zero[4] = {1, 1, 1, 1};   /* points whose rows (and columns) are all zero */
    for (int a = 0; a < p; a++)
      for (int i = 3 * a * n; i < 3 * (a + 1) * n && zero[a]; i++) zero[a] = Kb[i] == 0.0;
    if (reduced) {
      /* U = T^T L^-T V, column k the eigenvector k in the n coordinates: W = L^-T V by back
         substitution (L^T upper triangular), then U rows of point 0 = -(sum of W's points) */
      for (int k = 0; k < r; k++) {
        if (d[k] >= 0.0) continue;
        for (int j = 0; j < 3; j++) {
          double s0 = 0.0;
          for (int a = q - 1; a >= 0; a--) {
            double s = z[(3 * a + j) * r + k];
            for (int a2 = a + 1; a2 < q; a2++) s -= Lc[a2 * 4 + a] * U[(3 + 3 * a2 + j) * 12 + k];
            U[(3 + 3 * a + j) * 12 + k] = s / Lc[a * 4 + a];
            s0 += U[(3 + 3 * a + j) * 12 + k];
          }
          U[j * 12 + k] = -s0;
        }
      }
    } else {
      for (int i = 0; i < n; i++) for (int k = 0; k < n; k++) U[i * 12 + k] = z[i * n + k];
    }
    for (int k = 0; k < k_n; k++) {
      if (d[k] >= 0.0) continue;
      for (int row = 0; row < n; row++) {
        double f = d[k] * U[row * 12 + k];
        for (int c = 0; c < n; c++) Kb[row * n + c] -= f * U[c * 12 + k];
      }
    }
    /* a point the block leaves out stays out: its rows and columns are zero in the exact
       projection (K e = 0 there), not the roundoff of the eigenvectors, which would couple
       it in the matrix's pattern */
    for (int a = 0; a < p; a++)
      if (zero[a])
        for (int i = 3 * a; i < 3 * a + 3; i++)
          for (int c = 0; c < n; c++) Kb[i * n + c] = Kb[c * n + i] = 0.0;
  }
}
"""

_lib = None
_tried = False


def _cache_dir() -> Path:
    return Path(os.environ.get("MVFEM_CACHE", Path.home() / ".cache" / "mvfem"))


def _threads() -> int:
    """Threads for the kernels' loops: ``MVFEM_THREADS`` where set, else ``OMP_NUM_THREADS``,
    else this process's share of the cores it may run on (all of them in a serial run; one
    each under ``mpirun -n 2`` on two cores, until :func:`mvfem.nodal.lend_cores` gives rank
    0, which alone runs the kernels, the cores of the ranks that sleep meanwhile)."""
    for var in ("MVFEM_THREADS", "OMP_NUM_THREADS"):
        try:
            n = int(os.environ.get(var, ""))
        except ValueError:
            continue
        if n > 0:
            return n
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 1
    mpi = sys.modules.get("mpi4py.MPI")
    size = mpi.COMM_WORLD.size if mpi is not None else 1
    return max(1, cores // size)


def _compile(src: Path, out: Path) -> None:
    """Build the library, with OpenMP where the compiler has it, else without."""
    cc = os.environ.get("CC", "cc")
    base = [cc, "-O2", "-shared", "-fPIC", str(src), "-o", str(out), "-lm"]
    try:
        subprocess.run(base[:1] + ["-fopenmp"] + base[1:], check=True, capture_output=True,
                       timeout=120)
    except subprocess.CalledProcessError:
        subprocess.run(base, check=True, capture_output=True, timeout=120)


def load():
    """The compiled library (cffi), building it on first use; None where that fails (then
    the numpy versions are used, with one warning). Its loops run on :func:`_threads`
    threads where the compiler has OpenMP (:func:`threads`)."""
    global _lib, _tried
    if _tried:
        return _lib
    _tried = True
    if os.environ.get("MVFEM_NO_KERNELS"):
        return None
    try:
        import cffi

        ffi = cffi.FFI()
        ffi.cdef(_CDEF)
        key = hashlib.sha256((_SOURCE + _CDEF + sys.platform).encode()).hexdigest()[:16]
        path = _cache_dir() / f"contact_{key}.so"
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
                src = Path(tmp) / "contact.c"
                src.write_text(_SOURCE)
                out = Path(tmp) / path.name
                _compile(src, out)
                os.replace(out, path)  # atomic: concurrent runs may build it too
        _lib = (ffi, ffi.dlopen(str(path)))
        _lib[1].set_threads(_threads())
    except Exception as e:  # no compiler, no cffi, read-only cache: numpy instead
        log.warning(f"contact kernels not compiled ({type(e).__name__}: {e}); using numpy")
        _lib = None
    return _lib


_blas = []


def _openblas():
    """This process's OpenBLAS (ctypes), None where the BLAS loaded is another."""
    if not _blas:
        lib = None
        try:
            with open("/proc/self/maps") as f:
                paths = {ln.split()[-1] for ln in f if "openblas" in ln and ".so" in ln}
            for path in sorted(paths):
                cand = ctypes.CDLL(path)
                if hasattr(cand, "openblas_set_num_threads"):
                    lib = cand
                    break
        except OSError:
            lib = None
        _blas.append(lib)
    return _blas[0]


@contextmanager
def one_blas_thread():
    """OpenBLAS on one thread inside (restored on exit). Its threads spin-wait between
    calls: numpy's batched ``eigh`` of 60,000 12 x 12 blocks took 1.9 s with OpenBLAS's
    default two threads and 1.2 s with one, and split over two Python threads 6.7 s against
    0.6 s (measured here)."""
    lib = _openblas()
    n = lib.openblas_get_num_threads() if lib is not None else 1
    if n > 1:
        lib.openblas_set_num_threads(1)
    try:
        yield
    finally:
        if n > 1:
            lib.openblas_set_num_threads(n)


def threads(n: int | None = None) -> int:
    """The number of threads of the kernels' loops (1 without OpenMP or kernels); ``n`` sets
    it first. The results do not depend on it (every loop writes its own outputs, and sums
    run in a fixed order)."""
    lib = load()
    if lib is None:
        return 1
    return int(lib[1].set_threads(int(n) if n else 0))


def _ptr(ffi, a: np.ndarray):
    return ffi.cast("double *", ffi.from_buffer(a))


def point_triangle_gradient(y: np.ndarray):
    """(d (m,), gradient (m, 12)) of node-triangle distances for stacked ``y`` (m, 12)."""
    ffi, lib = load()
    y = np.ascontiguousarray(y, dtype=np.float64)
    m = len(y)
    d, g = np.empty(m), np.empty((m, 12))
    lib.pt_grad(m, _ptr(ffi, y), _ptr(ffi, d), _ptr(ffi, g))
    return d, g


def _out(out, shape) -> np.ndarray:
    """``out`` (a C-contiguous float64 array of ``shape``, written in place) or a new one."""
    if out is None:
        return np.empty(shape)
    if out.shape != shape or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float64 array of shape {shape}")
    return out


def point_triangle_hessian(y: np.ndarray, out=None) -> np.ndarray:
    """(m, 12, 12) curvature of node-triangle distances (see contact.distance_hessian), into
    ``out`` when given."""
    ffi, lib = load()
    y = np.ascontiguousarray(y, dtype=np.float64)
    H = _out(out, (len(y), 12, 12))
    lib.pt_hess(len(y), _ptr(ffi, y), _ptr(ffi, H))
    return H


def point_triangle_stiffness(y: np.ndarray, dphi: np.ndarray, ddphi: np.ndarray,
                             dd: np.ndarray, out=None) -> np.ndarray:
    """(m, 12, 12) barrier blocks ``dphi d2d + ddphi dd dd^T`` of node-triangle pairs ``y``
    (m, 12), ``dd`` (m, 12) the distances' gradients, into ``out`` when given."""
    ffi, lib = load()
    y, dphi, ddphi, dd = _f64(y), _f64(dphi), _f64(ddphi), _f64(dd)
    H = _out(out, (len(y), 12, 12))
    lib.pt_stiff(len(y), _ptr(ffi, y), _ptr(ffi, dphi), _ptr(ffi, ddphi), _ptr(ffi, dd),
                 _ptr(ffi, H))
    return H


def edge_edge_energy(y, weight, eps_x, delta: float):
    """(E, gradient, d) of the mollified edge-edge barrier (see contact.edge_edge_energy)."""
    ffi, lib = load()
    y = np.ascontiguousarray(y, dtype=np.float64)
    m = len(y)
    w = np.ascontiguousarray(np.broadcast_to(weight, (m,)), dtype=np.float64)
    e = np.ascontiguousarray(np.broadcast_to(eps_x, (m,)), dtype=np.float64)
    E, g, d = np.empty(m), np.empty((m, 12)), np.empty(m)
    lib.ee_energy(m, _ptr(ffi, y), _ptr(ffi, w), _ptr(ffi, e), float(delta), _ptr(ffi, E),
                  _ptr(ffi, g), _ptr(ffi, d))
    return E, g, d


def edge_edge_hessian(y, weight, eps_x, delta: float, out=None) -> np.ndarray:
    """(m, 12, 12) Hessian of the edge-edge barrier (see contact.edge_edge_hessian), into
    ``out`` when given."""
    ffi, lib = load()
    y = np.ascontiguousarray(y, dtype=np.float64)
    m = len(y)
    w = np.ascontiguousarray(np.broadcast_to(weight, (m,)), dtype=np.float64)
    e = np.ascontiguousarray(np.broadcast_to(eps_x, (m,)), dtype=np.float64)
    H = _out(out, (m, 12, 12))
    lib.ee_hess(m, _ptr(ffi, y), _ptr(ffi, w), _ptr(ffi, e), float(delta), _ptr(ffi, H))
    return H


def _index(ffi, a: np.ndarray):
    return ffi.cast("int64_t *", ffi.from_buffer(a))


def point_triangle_distance(x: np.ndarray, cells: np.ndarray, s: np.ndarray,
                            t: np.ndarray, bary: bool = False):
    """(m,) distances of the nodes ``x[s]`` to the triangles ``cells[t]`` ((c, 3) node
    indices) at positions ``x`` (n, 3); with ``bary`` also the closest points' barycentric
    coordinates (m, 3), as :func:`mvfem.contact.closest_point_on_triangles` gives them."""
    ffi, lib = load()
    x, cells, s, t = _f64(x), _i64(cells), _i64(s), _i64(t)
    d = np.empty(len(s))
    b = np.empty((len(s), 3)) if bary else None
    lib.pt_dist(len(s), _ptr(ffi, x), _index(ffi, cells), _index(ffi, s), _index(ffi, t),
                _ptr(ffi, d), _ptr(ffi, b) if bary else ffi.NULL)
    return (d, b) if bary else d


def segment_distance(x: np.ndarray, edges: np.ndarray, i: np.ndarray,
                     j: np.ndarray) -> np.ndarray:
    """(m,) distances of the segments ``edges[i]`` and ``edges[j]`` ((e, 2) node indices) at
    positions ``x`` (n, 3)."""
    ffi, lib = load()
    x, edges, i, j = _f64(x), _i64(edges), _i64(i), _i64(j)
    d = np.empty(len(i))
    lib.ee_dist(len(i), _ptr(ffi, x), _index(ffi, edges), _index(ffi, i), _index(ffi, j),
                _ptr(ffi, d))
    return d


def point_triangle_distance_cut(x: np.ndarray, cells: np.ndarray, s: np.ndarray,
                                t: np.ndarray, lb: np.ndarray, D: np.ndarray, cut: float,
                                out: np.ndarray) -> np.ndarray:
    """:func:`point_triangle_distance` into ``out`` (float64, contiguous) of the pairs that
    may be closer than ``cut`` and whose entry there is inf; the others are left as they
    are. Pair ``k`` is at least ``lb[k] - D[s] - max D[vertices]`` apart, with ``lb`` its
    distance (or a lower bound of it) at positions from which node ``n`` has since moved by
    ``D[n]``."""
    return _distance_cut("pt_dist_cut", x, cells, s, t, lb, D, cut, out)


def segment_distance_cut(x: np.ndarray, edges: np.ndarray, i: np.ndarray, j: np.ndarray,
                         lb: np.ndarray, D: np.ndarray, cut: float,
                         out: np.ndarray) -> np.ndarray:
    """:func:`segment_distance` into ``out`` as :func:`point_triangle_distance_cut` (an edge
    moves by its nodes' larger ``D``)."""
    return _distance_cut("ee_dist_cut", x, edges, i, j, lb, D, cut, out)


def _distance_cut(kernel: str, x, shapes, i, j, lb, D, cut: float, out) -> np.ndarray:
    """Call the cut distance ``kernel`` on the pairs ``(i[k], j[k])`` of nodes and triangles
    or of edges (``shapes``, their node indices)."""
    ffi, lib = load()
    x, shapes, i, j, lb, D = _f64(x), _i64(shapes), _i64(i), _i64(j), _f64(lb), _f64(D)
    d = _out(out, (len(i),))
    getattr(lib, kernel)(len(i), _ptr(ffi, x), _index(ffi, shapes), _index(ffi, i),
                         _index(ffi, j), _ptr(ffi, lb), _ptr(ffi, D), float(cut), _ptr(ffi, d))
    return d


def _f64(a):
    return np.ascontiguousarray(a, dtype=np.float64)


def _i64(a):
    return np.ascontiguousarray(a, dtype=np.int64)


def hinge_cos_sin(y: np.ndarray):
    """(cos, sin) of the dihedral angles of stacked hinges ``y`` (m, 12), see
    :func:`hinge_energy`."""
    ffi, lib = load()
    y = _f64(y)
    c, s = np.empty(len(y)), np.empty(len(y))
    lib.hinge_cos_sin(len(y), _ptr(ffi, y), _ptr(ffi, c), _ptr(ffi, s))
    return c, s


def hinge_energy(y: np.ndarray, c0: np.ndarray, s0: np.ndarray, k: np.ndarray):
    """(E (m,), gradient (m, 12)) of the hinge energies ``k (1 - cos(theta - theta0))`` of
    stacked hinges ``y`` (m, 12): nodes (c, d, a, b), the edge a-b between the triangles
    (a, b, c) and (a, b, d); ``theta0`` by its cosine ``c0`` and sine ``s0`` (:mod:`mvfem.hinges`)."""
    ffi, lib = load()
    y, c0, s0, k = _f64(y), _f64(c0), _f64(s0), _f64(k)
    m = len(y)
    E, g = np.empty(m), np.empty((m, 12))
    lib.hinge_energy(m, _ptr(ffi, y), _ptr(ffi, c0), _ptr(ffi, s0), _ptr(ffi, k), _ptr(ffi, E),
                     _ptr(ffi, g))
    return E, g


def hinge_hessian(y: np.ndarray, c0: np.ndarray, s0: np.ndarray, k: np.ndarray,
                  rel: float = 1e-4) -> np.ndarray:
    """(m, 12, 12) Hessians of :func:`hinge_energy`."""
    ffi, lib = load()
    y, c0, s0, k = _f64(y), _f64(c0), _f64(s0), _f64(k)
    H = np.empty((len(y), 12, 12))
    lib.hinge_hess(len(y), _ptr(ffi, y), _ptr(ffi, c0), _ptr(ffi, s0), _ptr(ffi, k), rel,
                   _ptr(ffi, H))
    return H


def hinge_hessian_add(y: np.ndarray, c0: np.ndarray, s0: np.ndarray, k: np.ndarray,
                      place: np.ndarray, nnz: int, rel: float = 1e-4) -> np.ndarray:
    """(nnz,) the Hessians of :func:`hinge_energy` summed into a fixed pattern: entry ``q`` of
    hinge ``i`` into ``place[i, q]`` ((m, 144), negative: left out)."""
    ffi, lib = load()
    y, c0, s0, k, place = _f64(y), _f64(c0), _f64(s0), _f64(k), _i64(place)
    vals = np.zeros(int(nnz))
    lib.hinge_hess_add(len(y), _ptr(ffi, y), _ptr(ffi, c0), _ptr(ffi, s0), _ptr(ffi, k), rel,
                       _index(ffi, place), _ptr(ffi, vals))
    return vals


def psd_project(K: np.ndarray) -> np.ndarray:
    """Each symmetric block of ``K`` ((m, n, n), n = 3, 6, 9 or 12: the blocks of 1-4 points,
    C-contiguous float64) replaced in place by its positive semidefinite part (the negative
    eigenvalues set to zero). Returns the (m,) mask of blocks whose eigenvalues did not
    converge, left unchanged (the caller projects those otherwise)."""
    ffi, lib = load()
    if K.ndim != 3 or K.shape[1] != K.shape[2] or K.shape[1] % 3 or not 3 <= K.shape[1] <= 12:
        raise ValueError(f"blocks of 3 to 12 rows, a multiple of 3, not {K.shape[1:]}")
    m, n = K.shape[0], K.shape[1]
    if K.dtype != np.float64 or not K.flags.c_contiguous:
        raise ValueError("K must be a C-contiguous float64 array")
    fail = np.zeros(m, dtype=np.intc)
    lib.psd_proj(m, n // 3, _ptr(ffi, K), ffi.cast("int *", ffi.from_buffer(fail)))
    return fail.astype(bool)


def elements_csr(N: int, free: np.ndarray, groups) -> tuple[np.ndarray, ...]:
    """(indptr, cols, vals) over 3 ``N`` rows of the sum of element blocks: ``groups`` a list
    of (nodes (m, k), stiffness (m, 3k, 3k)); the entries of dofs not ``free`` ((N, 3)) left
    out, each entry summed in the order (group, element, row node, column node)."""
    ffi, lib = load()
    groups = [(_i64(nd), _f64(K)) for nd, K in groups if len(nd)]
    m = np.array([len(nd) for nd, _ in groups], dtype=np.int64)
    k = np.array([nd.shape[1] for nd, _ in groups], dtype=np.int64)
    fr = np.ascontiguousarray(free, dtype=np.uint8)
    n_rows = int((m * k).sum())
    n_blocks = int((m * k * k).sum())
    indptr = np.empty(3 * N + 1, dtype=np.int64)
    cols = np.empty(9 * n_blocks, dtype=np.int64)
    vals = np.empty(9 * n_blocks)
    work = np.empty(3 * N + 1 + n_rows, dtype=np.int64)
    nodes_p = ffi.new("int64_t *[]", [_index(ffi, nd) for nd, _ in groups] or [ffi.NULL])
    K_p = ffi.new("double *[]", [_ptr(ffi, K) for _, K in groups] or [ffi.NULL])
    nnz = lib.elements_csr(len(groups), _index(ffi, m), _index(ffi, k), nodes_p, K_p, N,
                           ffi.cast("uint8_t *", ffi.from_buffer(fr)), _index(ffi, indptr),
                           _index(ffi, cols), _ptr(ffi, vals), _index(ffi, work))
    if nnz < 0:
        raise MemoryError("elements_csr: no memory for the threads' scratch")
    return indptr, cols[:nnz], vals[:nnz]


def csr_drop_zero_blocks(csr) -> tuple[np.ndarray, ...]:
    """``csr`` = (indptr, cols, vals) of :func:`elements_csr` without its 3 x 3 node blocks of
    zeros (changed in place; the kept entries in their order)."""
    ffi, lib = load()
    indptr, cols, vals = _i64(csr[0]), _i64(csr[1]), _f64(csr[2])
    N = (len(indptr) - 1) // 3
    mark = np.empty(max(N, 1), dtype=np.int64)
    nnz = lib.csr_drop_zero_blocks(N, _index(ffi, indptr), _index(ffi, cols), _ptr(ffi, vals),
                                   _index(ffi, mark))
    return indptr, cols[:nnz], vals[:nnz]


def csr_union(a, b) -> tuple[np.ndarray, np.ndarray]:
    """The union of the CSR patterns ``a`` and ``b`` ((indptr, cols, ...) over the same rows,
    columns sorted and distinct in each row): (indptr, cols), the same way sorted."""
    ffi, lib = load()
    ia, ja, ib, jb = _i64(a[0]), _i64(a[1]), _i64(b[0]), _i64(b[1])
    if len(ia) != len(ib):
        raise ValueError(f"patterns of {len(ia) - 1} and {len(ib) - 1} rows")
    ic = np.empty(len(ia), dtype=np.int64)
    jc = np.empty(len(ja) + len(jb), dtype=np.int64)
    nnz = lib.csr_union(len(ia) - 1, _index(ffi, ia), _index(ffi, ja), _index(ffi, ib),
                        _index(ffi, jb), _index(ffi, ic), _index(ffi, jc))
    return ic, jc[:nnz]    # (a view: its buffer has room for both, not copied again)


def csr_missing(a, b) -> int:
    """Entries of the CSR pattern ``b`` ((indptr, cols, ...), columns sorted in each row) that
    the pattern ``a`` (the same rows) lacks."""
    ffi, lib = load()
    ia, ja, ib, jb = _i64(a[0]), _i64(a[1]), _i64(b[0]), _i64(b[1])
    if len(ia) != len(ib):
        raise ValueError(f"patterns of {len(ia) - 1} and {len(ib) - 1} rows")
    return int(lib.csr_missing(len(ia) - 1, _index(ffi, ia), _index(ffi, ja), _index(ffi, ib),
                               _index(ffi, jb)))
