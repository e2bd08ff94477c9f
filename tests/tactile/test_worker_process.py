"""The workers' process set-up: each dies with the process that started it, and glibc keeps its freed heap (Linux
only)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from tests._processes import alive, children

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pidfds and mallopt are Linux / glibc")
ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("watch", ["pidfd", "poll", "none"])
def test_a_worker_dies_when_the_process_it_watches_exits(watch):
    """exit_with(pid): the worker is killed when ``pid`` exits, though its own parent (here this test; in a run the
    forkserver, which outlives its caller) lives on; by a pidfd, or by polling where there is none. It ignores SIGINT
    and SIGTERM (a real worker ignores SIGINT and unwinds on SIGTERM): only the SIGKILL it asked for may end it."""
    caller = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    worker_code = ("import os, signal, time; from perception.runtime import exit_with; "
                   "signal.signal(signal.SIGINT, signal.SIG_IGN); signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                   + ("del os.pidfd_open; " if watch == "poll" else "")
                   + (f"exit_with({caller.pid}); " if watch != "none" else "")
                   + "print('ready', flush=True); time.sleep(30)")
    worker = subprocess.Popen([sys.executable, "-c", worker_code], stdout=subprocess.PIPE, text=True, cwd=ROOT,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert worker.stdout.readline().strip() == "ready"
        time.sleep(0.3)
        assert worker.poll() is None  # alive while the caller is
        caller.kill()
        caller.wait()
        try:
            worker.wait(timeout=10 if watch != "none" else 1.5)
        except subprocess.TimeoutExpired:
            pass
        assert worker.returncode == (None if watch == "none" else -signal.SIGKILL)
    finally:
        caller.kill()
        worker.kill()
        worker.wait()


def test_a_worker_takes_the_processes_it_started_with_it():
    """exit_with: a process the worker started (a loader's converter) and that process's own child end with the
    worker when the watched process exits; before, the worker's SIGKILL left them running as orphans."""
    caller = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    worker_code = ("import subprocess, sys, time; from perception.runtime import exit_with; "
                   f"exit_with({caller.pid}); "
                   "kid = subprocess.Popen([sys.executable, '-c', "
                   "'import subprocess, sys, time; g = subprocess.Popen([\"sleep\", \"60\"]); "
                   "print(g.pid, flush=True); time.sleep(60)'], stdout=subprocess.PIPE, text=True); "
                   "print(kid.pid, kid.stdout.readline().strip(), flush=True); time.sleep(30)")
    worker = subprocess.Popen([sys.executable, "-c", worker_code], stdout=subprocess.PIPE, text=True, cwd=ROOT,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
    started: list[int] = []
    try:
        started = [int(p) for p in worker.stdout.readline().split()]
        assert len(started) == 2 and all(map(alive, started))
        caller.kill()
        caller.wait()
        worker.wait(timeout=10)
        deadline = time.monotonic() + 5
        while any(map(alive, started)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert worker.returncode == -signal.SIGKILL
        assert not any(map(alive, started))
    finally:
        caller.kill()
        worker.kill()
        worker.wait()
        for pid in filter(alive, started):
            os.kill(pid, signal.SIGKILL)


def test_generation_workers_die_when_generate_is_killed(tmp_path, child_tmpdir):
    """Killing ``generate``'s process ends its object workers at once, though their parent (the forkserver) waits
    for them: no orphan explores on and writes into the store."""
    script = textwrap.dedent(f"""
        from tactile.dataset import generate
        from tactile.sensor import FSRSensor

        generate([("box", i) for i in range(4)], {str(tmp_path / "store.zarr")!r}, strategies=("blind",),
                 contours_per_object=20000, sensor=FSRSensor(rows=8, cols=8), probes=10, seed=0, workers=2,
                 progress=False)
    """)
    # its temporary files in a folder of the test's: a killed process cannot remove them
    caller = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT,
                              env={**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": child_tmpdir})
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while not workers and time.monotonic() < deadline:  # the forkserver's children: the object workers
            workers = [w for child in children(caller.pid) for w in children(child)]
            time.sleep(0.1)
        assert workers, "no worker started"
        time.sleep(1.0)
        assert all(map(alive, workers))  # exploring (one object takes minutes at this size)
        caller.kill()
        caller.wait()
        deadline = time.monotonic() + 10
        while any(map(alive, workers)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(map(alive, workers))
    finally:
        caller.kill()
        for pid in filter(alive, workers):
            os.kill(pid, signal.SIGKILL)


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


@pytest.mark.parametrize("bad", [0, -1, True, 2.5, "1", 2**31, 10**30])
def test_exit_with_refuses_what_is_not_a_process_id(bad):
    from perception.errors import InvalidArgumentError
    from perception.runtime import exit_with

    with pytest.raises(InvalidArgumentError, match="pid must be a positive integer"):
        exit_with(bad)


def test_the_generation_workers_preload_leaves_out_scipy_stats():
    """The forkserver imports the workers' modules before the first object starts, on one core while the other
    waits: scipy.stats (0.6 s of it, for a helper no worker calls) stays out."""
    script = ("import sys; from tactile.dataset.generate import WORKER_PRELOAD; [__import__(m) for m in WORKER_PRELOAD]; "
              "print('scipy.stats' in sys.modules, 'open3d' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", script], check=True, capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert run.stdout.split() == ["False", "True"]


def test_generation_ends_its_workers_cleanly(child_tmpdir):
    """Idle workers are asked to exit, not killed: a killed worker's clean-up does not run, and the resource tracker
    then warns the user of the semaphores it left behind."""
    script = textwrap.dedent("""
        import tempfile
        from tactile.dataset import generate
        from tactile.sensor import FSRSensor

        report = generate([("box", i) for i in range(4)], tempfile.mkdtemp() + "/s", strategies=("blind",),
                          contours_per_object=3, sensor=FSRSensor(rows=8, cols=8), probes=5, workers=2, progress=False)
        print(report.completed)
    """)
    run = subprocess.run([sys.executable, "-c", script], check=True, capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": child_tmpdir})
    assert run.stdout.split() == ["4"]
    assert "leaked" not in run.stderr and "resource_tracker" not in run.stderr, run.stderr


def box_then_wait_for_ever(folder: str):
    """Loader run in the worker: notes that it started, then sleeps; notes it if the sleep is unwound."""
    Path(folder, "started").touch()
    try:
        time.sleep(600)
    finally:
        Path(folder, "unwound").touch()


def test_an_interrupt_unwinds_the_busy_workers(child_tmpdir):
    """Ctrl-C during generation: a worker busy with an object is sent SIGTERM and unwinds (its ``finally`` blocks run:
    a chunk file half written is removed), and its exit handlers release what it made for the resource tracker. A
    SIGKILL left both, and the tracker warned the user of leaked semaphores."""
    script = textwrap.dedent("""
        import functools, os, signal, tempfile, threading, time
        from pathlib import Path
        from tactile.dataset import ObjectSpec, generate
        from tactile.sensor import FSRSensor
        from tests.tactile.test_worker_process import box_then_wait_for_ever

        folder = tempfile.mkdtemp()

        def interrupt_once_waiting():
            while not Path(folder, "started").exists():
                time.sleep(0.05)
            os.kill(os.getpid(), signal.SIGINT)

        threading.Thread(target=interrupt_once_waiting, daemon=True).start()
        slow = ObjectSpec("slow/0", "slow", loader=functools.partial(box_then_wait_for_ever, folder))
        start = time.monotonic()
        try:  # the first object is written (Blosc made its lock) before the worker starts the slow one
            generate([("box", 0), slow], folder + "/s", strategies=("blind",), contours_per_object=3,
                     sensor=FSRSensor(rows=8, cols=8), probes=5, workers=1, progress=False)
        except KeyboardInterrupt:
            print("interrupted", Path(folder, "unwound").exists(), time.monotonic() - start < 60)
    """)
    run = subprocess.run([sys.executable, "-c", script], check=True, capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": child_tmpdir}, timeout=120)
    assert run.stdout.split() == ["interrupted", "True", "True"], run.stderr
    assert "leaked" not in run.stderr and "resource_tracker" not in run.stderr, run.stderr


def test_ctrl_c_while_the_forkserver_preloads_is_held_off():
    """Python's forkserver ignores SIGINT only after its preload: an interrupt in that second or so killed it with a
    KeyboardInterrupt traceback on the user's terminal. A fresh interpreter imports the workers' preload as the
    forkserver does (in order, on its main thread) while SIGINT is sent: it is held off, and the handler in force
    before is back afterwards."""
    from tactile.dataset.generate import WORKER_PRELOAD

    script = textwrap.dedent(f"""
        import os, signal, sys, threading, time

        preload, sent = {WORKER_PRELOAD!r}, []

        def interrupt_while_loading():
            while preload[1].split(".")[0] not in sys.modules:  # the guard has run, the next module loads
                time.sleep(0.001)
            sent.append(preload[-1] not in sys.modules)  # sent before the guard's end ran
            os.kill(os.getpid(), signal.SIGINT)

        threading.Thread(target=interrupt_while_loading, daemon=True).start()
        for name in preload:
            __import__(name)
        time.sleep(0.2)
        print(sent, signal.getsignal(signal.SIGINT) is signal.default_int_handler)
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120, check=False)
    assert run.returncode == 0 and run.stdout.split() == ["[True]", "True"], run.stderr


def test_a_worker_whose_parent_closed_its_end_takes_no_task_and_raises_nothing():
    """A parent interrupted while it starts a worker exits without knowing of it; the worker, waiting for its first
    object, then reads end-of-file and exits quietly (it printed an EOFError traceback on the user's terminal)."""
    import multiprocessing

    from tactile.dataset.generate import _next_task

    parent, child = multiprocessing.Pipe(duplex=True)
    parent.send((3, "spec"))
    assert _next_task(child) == (3, "spec")
    parent.send(None)
    assert _next_task(child) is None
    parent.close()
    assert _next_task(child) is None


def test_descendants_are_listed_and_killed_even_once_orphaned():
    """descendant_handles(pid): pidfds of pid's children and theirs; kill_handles ends them, the grandchild here after
    its parent is gone (orphaned: no longer traceable through /proc from pid)."""
    from perception.runtime import descendant_handles, kill_handles

    code = ("import subprocess, sys, time; "
            "g = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)']); "
            "print(g.pid, flush=True); time.sleep(120)")
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        grandchild = int(child.stdout.readline())
        theirs = descendant_handles(child.pid)
        assert len(theirs) == 1
        child.kill()
        child.wait()  # the grandchild is an orphan now
        time.sleep(0.3)
        assert alive(grandchild)
        kill_handles(theirs)
        deadline = time.monotonic() + 10
        while alive(grandchild) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not alive(grandchild)
        assert descendant_handles(child.pid) == []  # gone: nothing listed
    finally:
        child.kill()
        child.wait()



two_cores = pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 usable cores to tell a limit of 1 "
                               "from none")


@two_cores
def test_each_generation_worker_casts_on_its_share_of_the_cores(monkeypatch):
    """A worker limits Open3D's threads (its ray casting) and its own pools to the cores it is given, so that two
    workers on two cores do not each spread over both."""
    import importlib
    import multiprocessing as mp

    import open3d as o3d

    from perception import runtime
    from tactile.dataset import worker

    gen = importlib.import_module("tactile.dataset.generate")  # the module: the package exports its function

    def report_limits(store, index, spec, settings, sensor, progress, saliency_cache):
        progress((o3d.utility.get_max_threads(), runtime.usable_cores()))

    monkeypatch.setattr(worker, "explore_into_store", report_limits)  # the forked worker imports it from here
    parent, child = mp.get_context("fork").Pipe(duplex=True)
    proc = mp.get_context("fork").Process(target=gen._worker, args=(child, "unused", {}, None, None, os.getpid(), 1))
    proc.start()
    try:
        child.close()
        parent.send((0, None))
        assert parent.poll(30) and parent.recv() == ("progress", (1, 1))
        assert parent.poll(30) and parent.recv() == ("done", None)
        parent.send(None)
        proc.join(30)
        assert proc.exitcode == 0
    finally:
        proc.kill()


def test_generation_starts_each_worker_on_its_share_of_the_cores(monkeypatch):
    """The usable cores split among the workers, at least 1 each (workers forked here so that the stand-in explorer
    reaches them; it reports the limit it runs under as its failure)."""
    import importlib
    import multiprocessing as mp

    from perception import runtime
    from tactile.dataset import worker

    gen = importlib.import_module("tactile.dataset.generate")

    def report_limit(*args, **kwargs):
        raise RuntimeError(f"limit {runtime._core_limit}")

    monkeypatch.setattr(worker, "explore_into_store", report_limit)
    monkeypatch.setattr(gen, "_context", lambda: mp.get_context("fork"))
    monkeypatch.setattr(runtime, "usable_cores", lambda: 8)
    for n_workers, share in ((3, 2), (8, 1), (9, 1)):
        seen = []
        gen._run_local("unused", [None] * n_workers, {}, None, list(range(n_workers)), n_workers,
                       lambda i, ok, detail, seen=seen: seen.append((ok, detail)), None, None, 60)
        assert seen == [(False, f"RuntimeError: limit {share}")] * n_workers
    assert runtime.worker_cores(1) == 8 and runtime._core_limit is None  # this process keeps its own


@two_cores
def test_a_ray_task_limits_its_process_to_one_core_and_gives_the_limits_back(monkeypatch):
    """A Ray task holds one CPU, so it casts on one core; the process is Ray's worker (or the caller's own, in local
    mode), which runs other tasks after it, so its limits are as before once the task ends."""
    import importlib

    import open3d as o3d

    from perception import runtime
    from tactile.dataset import worker

    gen = importlib.import_module("tactile.dataset.generate")
    seen = []
    monkeypatch.setattr(worker, "explore_into_store",
                        lambda *a, **k: seen.append((o3d.utility.get_max_threads(), runtime.usable_cores())))
    monkeypatch.setattr(runtime, "_core_limit", None)
    o3d.utility.set_max_threads(2)
    try:
        assert gen._ray_task("unused", 0, None, {}, None, None) == (True, None)
        assert seen == [(1, 1)]
        assert o3d.utility.get_max_threads() == 2 and runtime._core_limit is None
    finally:
        o3d.utility.set_max_threads(0)
