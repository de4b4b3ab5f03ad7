"""FFCx's JIT cache after a process died compiling a form (:mod:`mvfem.jitcache`).

A compile ended by a signal leaves its module's ``.c`` claim without the ready mark, and FFCx
makes every later compile of that form wait 10 s and raise ``TimeoutError`` (session 59: 28
tests of a fresh-cache suite failed so after one test killed a run inside such a compile).
The tests claim a form's module as a dead process leaves it (an empty ``.c``, nothing else),
old and young, in a cache of their own with FFCx's wait cut to 1 s.
"""

from __future__ import annotations

import os
import re
import time

import pytest
import ufl
from dolfinx import fem, mesh as dmesh
from mpi4py import MPI

from mvfem import jitcache


def _claimed(tmp_path, age: float):
    """A form compiled into ``tmp_path``, then its module's files replaced by a bare claim
    ``age`` seconds old. Returns (the form, the jit parameters, the claim)."""
    jitcache.install()
    msh = dmesh.create_unit_square(MPI.COMM_SELF, 1, 1)
    a = 2.5 * ufl.dx(domain=msh)
    params = {"cache_dir": str(tmp_path), "timeout": 1}
    fem.form(a, jit_params=params)
    (c,) = tmp_path.glob("libffcx_forms_*.c")
    for p in tmp_path.glob(f"{c.stem}.*"):
        p.unlink()
    c.touch()
    t = time.time() - age
    os.utime(c, (t, t))
    return a, params, c


def test_a_claim_left_by_a_dead_process_is_compiled_again(tmp_path):
    """A claim older than STALE_S is set aside at the first 1 s wait and the form compiled:
    it assembles to the unit square's area x 2.5 (FFCx alone: TimeoutError)."""
    a, params, c = _claimed(tmp_path, 2 * jitcache.STALE_S)
    t = time.perf_counter()
    form = fem.form(a, jit_params=params)
    assert fem.assemble_scalar(form) == pytest.approx(2.5, rel=1e-12)
    assert time.perf_counter() - t < 0.5 * jitcache.STALE_S
    assert (tmp_path / f"{c.name}.cached").exists()
    assert list(tmp_path.glob(f"{c.stem}.c.stale*"))


def test_a_young_claim_is_waited_for(tmp_path, monkeypatch):
    """A claim younger than STALE_S may be a live compile: it is waited for (here until it is
    3 s old, then set aside), not taken at FFCx's first 1 s timeout."""
    monkeypatch.setattr(jitcache, "STALE_S", 3.0)
    a, params, c = _claimed(tmp_path, 0.0)
    t = time.perf_counter()
    assert fem.assemble_scalar(fem.form(a, jit_params=params)) == pytest.approx(2.5, rel=1e-12)
    assert time.perf_counter() - t > 2.5


def test_a_compile_interrupted_in_this_process_gives_its_claim_up(tmp_path, monkeypatch):
    """A second Ctrl-C inside a compile (a ``KeyboardInterrupt`` out of FFCx's code
    generation, which FFCx does not clean up after): the claim becomes ``.c.failed``, its
    owner file is removed, and the next compile of the form goes ahead at once (FFCx alone:
    TimeoutError after 1 s)."""
    import ffcx.codegeneration.jit as jit

    jitcache.install()
    msh = dmesh.create_unit_square(MPI.COMM_SELF, 1, 1)
    a = 3.5 * ufl.dx(domain=msh)
    params = {"cache_dir": str(tmp_path), "timeout": 1}

    def ctrl_c(*args, **kw):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(jit, "_compile_objects", ctrl_c)
        with pytest.raises(KeyboardInterrupt):
            fem.form(a, jit_params=params)
    assert not list(tmp_path.glob("libffcx_forms_*.c"))
    assert len(list(tmp_path.glob("libffcx_forms_*.c.failed"))) == 1
    assert not list(tmp_path.glob("libffcx_forms_*.c.owner"))   # (its owner file gone too)
    assert fem.assemble_scalar(fem.form(a, jit_params=params)) == pytest.approx(3.5, rel=1e-12)


@pytest.mark.parametrize("owner", ["gone", "running", "another host", "none"])
def test_a_claim_whose_process_is_gone_is_compiled_again_at_once(tmp_path, monkeypatch,
                                                                  caplog, owner):
    """A claim just made (age 0) whose owner file names a process of this host that has
    exited is set aside at FFCx's first 1 s wait, its process gone; one whose owner still
    runs (this test's parent), another host's, or a claim without an owner file waits for
    the age rule (STALE_S, 3 s here). Each ends with the form compiled (2.5 x the unit
    square's area), its own claim's owner file naming this process while it compiles and
    removed after. Until session 60 every claim waited STALE_S (60 s: once in every
    fresh-cache suite)."""
    import logging
    import socket
    import subprocess

    monkeypatch.setattr(jitcache, "STALE_S", 3.0)
    a, params, c = _claimed(tmp_path, 0.0)
    done = subprocess.Popen(["true"])        # a pid of this host that has exited (reaped)
    done.wait()
    pid = os.getppid() if owner == "running" else done.pid
    host = "elsewhere.invalid" if owner == "another host" else socket.gethostname()
    if owner != "none":
        (tmp_path / f"{c.name}.owner").write_text(f"{host} {pid}\n")
    import ffcx.codegeneration.jit as jit

    owners = []

    def compiling(*args, **kw):   # (who the claim says it is, while it compiles)
        owners.append((tmp_path / f"{c.name}.owner").read_text().split())
        return compile_objects(*args, **kw)

    compile_objects = jit._compile_objects
    monkeypatch.setattr(jit, "_compile_objects", compiling)
    with caplog.at_level(logging.WARNING, logger="mvfem.jitcache"):
        form = fem.form(a, jit_params=params)
    assert fem.assemble_scalar(form) == pytest.approx(2.5, rel=1e-12)
    (said,) = [r.getMessage() for r in caplog.records if r.name == "mvfem.jitcache"]
    assert ("its process is gone" in said) is (owner == "gone"), said
    assert (re.search(r"unchanged for \d+ s", said) is not None) is (owner != "gone"), said
    # the compile's own claim said whose it was, and the owner file went with the compile
    assert owners == [[socket.gethostname(), str(os.getpid())]]
    assert not (tmp_path / f"{c.name}.owner").exists()
