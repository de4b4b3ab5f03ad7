"""FFCx's JIT cache, made to survive a process that died while it compiled a form.

FFCx (0.5, Debian's) claims a form's module by creating its ``.c`` file exclusively, writes
and compiles it, then marks it ready (``.c.cached``); a process that finds the ``.c`` waits
for the mark, ``timeout`` seconds (10), and then raises ``TimeoutError("JIT compilation timed
out, probably due to a failed previous compile")``. It cleans up after a compile that raises
an ``Exception``, but not after one ended by a signal (SIGKILL, a second Ctrl-C's
``KeyboardInterrupt``, the kernel's out-of-memory killer): the empty ``.c`` stays, and every
later run that needs the form fails after 10 s until the cache is cleared by hand. Session
59 met it: a fresh-cache test suite in which the test that kills a run while its outputs are
made killed it inside the compile of the outputs' forms, and 28 later tests failed so.

:func:`install` wraps FFCx's ``get_cached_module``: where the wait ends without the mark and
none of the module's files has changed for :data:`STALE_S` seconds (a compile of mvfem's
largest form writes its files within 3 s here), the claim is a dead process's; it is moved
aside (``.c.stale``) and the form compiled afresh. A claim younger than that is waited for.
It also wraps ``compile_forms``, ``compile_expressions`` and ``compile_elements``: a compile
this process claimed and a ``KeyboardInterrupt`` or ``SystemExit`` ended (a second Ctrl-C)
gives its claim up (``.c.failed``, as FFCx does after an ``Exception``), so that nobody
waits for it.

A process that claims a module writes who it is beside the claim (``.c.owner``: host and
pid); a claim whose owner on this host is no longer running is set aside at once, without
the :data:`STALE_S` wait (session 60: every fresh-cache test suite met one such claim, left
by a test's run killed inside a compile, and waited its 60 s). The owner file goes
before a claim is set aside or given up, and when its compile ends (compiled, or after
FFCx's own clean-up after an ``Exception``), so that none speaks for the next claim; a claim
without one (its owner not yet written, or its file removed by the last claim's clean-up a
moment late), another host's, or one whose owner runs is left to the age rule.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from pathlib import Path

__all__ = ["install", "STALE_S"]

log = logging.getLogger(__name__)

#: seconds without a change to a module's files after which a claim without its ready mark
#: is a dead process's
STALE_S = 60.0

_installed = False
#: (cache_dir, module_name) of the compiles this process has claimed and not finished
_claims: list[tuple[Path, str]] = []


def _last_change(cache_dir: Path, module_name: str) -> float | None:
    """The newest modification time of the module's files in ``cache_dir`` (the ``.c`` and
    what its compile writes), or None when its ``.c`` is gone."""
    c = cache_dir / f"{module_name}.c"
    try:
        newest = c.stat().st_mtime
    except FileNotFoundError:
        return None
    for p in cache_dir.glob(f"{module_name}.*"):
        try:
            newest = max(newest, p.stat().st_mtime)
        except FileNotFoundError:
            pass
    return newest


def _owner(cache_dir: Path, module_name: str) -> Path:
    return cache_dir / f"{module_name}.c.owner"


def _write_owner(cache_dir: Path, module_name: str) -> None:
    """Say beside a claim just made which process on which host made it."""
    try:
        _owner(cache_dir, module_name).write_text(f"{socket.gethostname()} {os.getpid()}\n")
    except OSError:   # (the age rule alone then)
        pass


def _drop_owner(cache_dir: Path, module_name: str) -> None:
    """Remove a claim's owner file before the claim ends without its ready mark, so that no
    owner file outlives its claim and speaks for the next one."""
    try:
        _owner(cache_dir, module_name).unlink()
    except OSError:
        pass


def _owner_gone(cache_dir: Path, module_name: str) -> bool:
    """Whether the claim's owner file names a process of this host that no longer runs."""
    try:
        host, pid = _owner(cache_dir, module_name).read_text().split()
        pid = int(pid)
    except (OSError, ValueError):
        return False
    if host != socket.gethostname() or pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:   # (running, another user's)
        return False
    return False


def _set_aside(cache_dir: Path, module_name: str) -> bool:
    """Move a dead process's claim aside (True), unless it changed since it was judged."""
    c = cache_dir / f"{module_name}.c"
    last = _last_change(cache_dir, module_name)
    if last is None:
        return False
    gone = _owner_gone(cache_dir, module_name)
    if not gone and time.time() - last < STALE_S:
        return False
    if (cache_dir / f"{module_name}.c.cached").exists():
        return False
    _drop_owner(cache_dir, module_name)
    try:
        os.replace(c, c.with_suffix(f".c.stale{os.getpid()}"))
    except FileNotFoundError:
        return False
    why = "its process is gone" if gone else f"unchanged for {time.time() - last:.0f} s"
    log.warning(f"JIT cache: {c.name} was left by a process that died compiling it "
                f"({why}); compiling it again")
    return True


def _patient(original):
    def get_cached_module(module_name, object_names, cache_dir, timeout):
        cache_dir = Path(cache_dir)
        while True:
            try:
                obj, mod = original(module_name, object_names, cache_dir, timeout)
                if obj is None:  # claimed: this process compiles it
                    _write_owner(cache_dir, module_name)
                    _claims.append((cache_dir, module_name))
                return obj, mod
            except TimeoutError:
                # a dead process's claim is set aside; then, as after a claim given up or
                # made ready meanwhile, the look-up again claims or loads it; a live
                # compile's (or a dead one's not yet stale) is waited on
                _set_aside(cache_dir, module_name)
    get_cached_module.__wrapped__ = original
    return get_cached_module


def _giving_up(original):
    def compile_(*args, **kw):
        depth = len(_claims)
        try:
            return original(*args, **kw)
        except (KeyboardInterrupt, SystemExit):
            for cache_dir, module_name in _claims[depth:]:
                c = cache_dir / f"{module_name}.c"
                if not (cache_dir / f"{module_name}.c.cached").exists():
                    _drop_owner(cache_dir, module_name)
                    try:
                        os.replace(c, c.with_suffix(".c.failed"))
                    except FileNotFoundError:
                        pass
            raise
        finally:   # (compiled, or given up by FFCx after an Exception: its owner file goes)
            for cache_dir, module_name in _claims[depth:]:
                _drop_owner(cache_dir, module_name)
            del _claims[depth:]
    compile_.__wrapped__ = original
    return compile_


def install() -> None:
    """Wrap FFCx's JIT cache look-up and compiles (once per process)."""
    global _installed
    if _installed:
        return
    import ffcx.codegeneration.jit as jit

    jit.get_cached_module = _patient(jit.get_cached_module)
    jit.compile_forms = _giving_up(jit.compile_forms)
    jit.compile_expressions = _giving_up(jit.compile_expressions)
    jit.compile_elements = _giving_up(jit.compile_elements)
    _installed = True
