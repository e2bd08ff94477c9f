"""The generate worker's process set-up: it dies with its parent, and glibc keeps its freed heap (Linux only)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl and mallopt are Linux / glibc")
ROOT = Path(__file__).resolve().parents[2]


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"  # a zombie has died
    except FileNotFoundError:
        return False


@pytest.mark.parametrize("dies", [True, False])
def test_a_worker_dies_with_its_parent(dies):
    # parent -> child; the child calls _die_with_parent (or not) and sleeps; killing the parent must kill it
    # like the real worker, the child ignores SIGINT and SIGTERM: only the SIGKILL it asked for may end it
    child = ("import signal, time; from tactile.dataset.generate import _die_with_parent; "
             "signal.signal(signal.SIGINT, signal.SIG_IGN); signal.signal(signal.SIGTERM, signal.SIG_IGN); "
             + ("_die_with_parent(); " if dies else "") + "print('ready', flush=True); time.sleep(30)")
    parent = textwrap.dedent(f"""
        import subprocess, sys, time
        p = subprocess.Popen([sys.executable, "-c", {child!r}], stdout=subprocess.PIPE, text=True)
        assert p.stdout.readline().strip() == "ready"
        print(p.pid, flush=True)
        time.sleep(30)
    """)
    proc = subprocess.Popen([sys.executable, "-c", parent], stdout=subprocess.PIPE, text=True, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    pid = int(proc.stdout.readline())
    try:
        assert _alive(pid)
        proc.kill()
        proc.wait()
        deadline = time.monotonic() + (10 if dies else 1)
        while _alive(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _alive(pid) is not dies
    finally:
        if _alive(pid):
            os.kill(pid, 9)


def test_freed_heap_memory_is_kept_after_the_call():
    # 16 blocks of 16 MiB: at glibc's initial mmap threshold (128 KiB) each is mapped and unmapped on its own; after
    # the call they come from the heap (threshold 32 MiB) and stay there when freed (trim threshold 1 GiB). The heap's size (mallinfo2's arena, glibc >= 2.33) after the frees, in MiB.
    script = textwrap.dedent("""
        import ctypes
        from tactile.dataset.generate import _keep_freed_memory

        class Info(ctypes.Structure):
            _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                                                       "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

        libc = ctypes.CDLL(None)
        if not hasattr(libc, "mallinfo2"):
            raise SystemExit("no mallinfo2")
        libc.mallinfo2.restype = Info
        libc.malloc.restype = ctypes.c_void_p
        libc.free.argtypes = [ctypes.c_void_p]

        def kept_mib():
            before = libc.mallinfo2().arena
            blocks = [libc.malloc(16 << 20) for _ in range(16)]
            for block in reversed(blocks):
                libc.free(block)
            return (libc.mallinfo2().arena - before) >> 20

        libc.mallopt(-3, 128 << 10)  # glibc's initial mmap threshold again (imports may have raised it)
        print(kept_mib(), end=" ")
        _keep_freed_memory()
        print(kept_mib())
    """)
    run = subprocess.run([sys.executable, "-c", script], check=False, capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    if run.returncode and "no mallinfo2" in run.stderr:
        pytest.skip("this C library has no mallinfo2 (glibc < 2.33 or not glibc)")
    assert run.returncode == 0, run.stderr
    before, after = (int(v) for v in run.stdout.split())
    assert before < 64 and after >= 240  # given back before the call; kept (but for the top's slack) after
