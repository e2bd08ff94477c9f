"""How generate stops a busy worker (SIGTERM, then SIGKILL once ``STOP_GRACE_S`` has passed), against hostile loaders:
one that ignores SIGTERM, one that swallows the SystemExit it raises, one stopped while it writes a large file;
stopped by an object timeout or by an interrupt. Each run is a subprocess, so that its stderr (the resource
tracker's warnings) and its processes can be checked. (From a break attempt on the change.)"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from tests._processes import alive, children

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="signals, /proc")
ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------ loaders (module level: workers unpickle them)
def _started(folder: str, tag: str) -> None:
    Path(folder, f"pid-{tag}").write_text(str(os.getpid()))
    Path(folder, f"started-{tag}").touch()


def _box():
    from perception.shapes import make_object

    return make_object("box", 0)


def ignoring_sigterm(folder: str, tag: str):
    """Ignores SIGTERM, then sleeps: only the SIGKILL after the grace period ends it."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _started(folder, tag)
    try:
        time.sleep(600)
    finally:
        Path(folder, f"unwound-{tag}").touch()


def swallowing_exit(folder: str, tag: str):
    """Catches BaseException (the SystemExit of the worker's SIGTERM handler) and sleeps on."""
    _started(folder, tag)
    while True:
        try:
            time.sleep(600)
        except BaseException:  # noqa: BLE001 -- hostile on purpose
            Path(folder, f"swallowed-{tag}").touch()


def swallowing_exit_then_box(folder: str, tag: str):
    """Sleeps; when its SystemExit comes, swallows it and returns a box at once, so that its worker goes on to
    explore and write the object (and its completion record) within the grace period."""
    _started(folder, tag)
    try:
        time.sleep(600)
    except BaseException:  # noqa: BLE001 -- hostile on purpose
        Path(folder, f"swallowed-{tag}").touch()
    return _box()


def writing_a_large_file(folder: str, tag: str):
    """Writes a large file through atomic_path (as write_rows writes chunk files), slowly, when it is stopped."""
    from perception.atomic import atomic_path

    block = os.urandom(1 << 20)
    with atomic_path(Path(folder, "store", "big.bin")) as tmp, open(tmp, "wb") as f:
        _started(folder, tag)
        for _ in range(4000):
            f.write(block)
            time.sleep(0.01)
    return _box()


def spawning_a_child(folder: str, tag: str):
    """Starts a child process (a plain subprocess, nothing ends it), notes its pid, then sleeps."""
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    Path(folder, f"child-{tag}").write_text(str(child.pid))
    _started(folder, tag)
    time.sleep(600)


def finishing_while_its_caller_is_stopped(folder: str, tag: str):
    """Stops generate's process (SIGSTOP) past the object timeout (3 s), and lets its worker explore the box it
    returns meanwhile: when generate goes on, the object's progress and its "done" both wait in the pipe."""
    caller = int(Path(folder, "caller").read_text())
    os.kill(caller, signal.SIGSTOP)
    _started(folder, tag)
    record = Path(folder, "store", "records", f"{int(tag):05d}.json")  # the object's index is its tag here

    def resume():  # once the worker has written the object (and then sent "done"), however slow the machine
        deadline = time.monotonic() + 60
        while not record.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        os.kill(caller, signal.SIGCONT)

    time.sleep(3.5)
    threading.Thread(target=resume, daemon=True).start()
    return _box()


def closing_its_pipe(folder: str, tag: str):
    """Closes its descriptors but the pidfd that exit_with watches (its pipe among them: the parent sees EOF), then
    sleeps on; notes it if the sleep is unwound."""
    _started(folder, tag)
    for fd in map(int, os.listdir("/proc/self/fd")):
        try:
            if fd > 2 and "pidfd" not in os.readlink(f"/proc/self/fd/{fd}"):
                os.close(fd)
        except OSError:
            pass
    try:
        time.sleep(600)
    finally:
        Path(folder, f"unwound-{tag}").touch()


# ------------------------------------------------------------------ the run, in a subprocess
SCRIPT = textwrap.dedent("""
    import functools, json, os, signal, sys, threading, time, traceback
    from pathlib import Path
    from perception.errors import DatasetError
    from tactile.dataset import ObjectSpec, generate
    from tactile.sensor import FSRSensor
    import tests.tactile.test_worker_stopping as hostile

    folder, loaders, mode, workers, timeout, strict, grace, box_first = json.loads(sys.argv[1])
    Path(folder, "caller").write_text(str(os.getpid()))
    sys.modules["tactile.dataset.generate"].STOP_GRACE_S = grace  # the package's "generate" is the function
    out = {"interrupted_at": None}

    def interrupt_once_started():
        while not all(Path(folder, f"started-{i}").exists() for i in range(len(loaders))):
            time.sleep(0.02)
        time.sleep(0.3)
        out["interrupted_at"] = time.monotonic()
        os.kill(os.getpid(), signal.SIGINT)

    if mode == "interrupt":
        threading.Thread(target=interrupt_once_started, daemon=True).start()
    specs = [ObjectSpec(f"bad/{i}", "bad", loader=functools.partial(getattr(hostile, name), folder, str(i)))
             for i, name in enumerate(loaders)]
    objects = [("box", 0), *specs, ("can", 1), ("box", 2)] if box_first else [*specs, ("box", 0), ("can", 1), ("box", 2)]
    start = time.monotonic()
    try:
        report = generate(objects, folder + "/store", strategies=("blind",), contours_per_object=2,
                          sensor=FSRSensor(rows=8, cols=8), probes=5, workers=workers, object_timeout_s=timeout,
                          strict=strict, progress=False)
        out.update(outcome="returned", completed=report.completed, failed=report.failed)
    except KeyboardInterrupt:
        out["outcome"] = "KeyboardInterrupt"
    except DatasetError as exc:
        out["outcome"] = "DatasetError"
    end = time.monotonic()
    out["seconds"] = end - start
    out["after_interrupt"] = None if out["interrupted_at"] is None else end - out["interrupted_at"]
    del out["interrupted_at"]
    print(json.dumps(out))
""")


def run_case(tmp_path, loaders, mode, workers=2, timeout=None, strict=False, grace=2.0, box_first=False, limit=120):
    folder = str(tmp_path)
    # Files, not pipes: a child process a loader started would hold a pipe open if it outlived its worker.
    with open(tmp_path / "stdout", "w") as stdout, open(tmp_path / "stderr", "w") as stderr:
        run = subprocess.run([sys.executable, "-c", SCRIPT, json.dumps([folder, loaders, mode, workers, timeout,
                                                                         strict, grace, box_first])],
                             stdout=stdout, stderr=stderr, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                             timeout=limit, check=False)
    err = (tmp_path / "stderr").read_text()
    assert run.returncode == 0, err
    result = json.loads((tmp_path / "stdout").read_text().strip().splitlines()[-1])
    result["stderr"] = err
    pids = [int(p.read_text()) for p in tmp_path.glob("pid-*")]
    childs = [int(p.read_text()) for p in tmp_path.glob("child-*")]
    deadline = time.monotonic() + 3
    while any(map(alive, pids + childs)) and time.monotonic() < deadline:
        time.sleep(0.05)
    result["workers_alive"] = [p for p in pids if alive(p)]
    result["children_alive"] = [p for p in childs if alive(p)]
    for pid in result["workers_alive"] + result["children_alive"]:
        os.kill(pid, signal.SIGKILL)
    store = tmp_path / "store"
    result["hidden"] = sorted(str(p.relative_to(store)) for p in store.rglob(".*")) if store.exists() else []
    result["marks"] = sorted(p.name for p in tmp_path.iterdir() if p.name.split("-")[0] in ("unwound", "swallowed"))
    return result


def clean(result) -> None:
    assert "resource_tracker" not in result["stderr"] and "leaked" not in result["stderr"], result["stderr"]
    assert result["workers_alive"] == [] and result["children_alive"] == [], result
    assert result["hidden"] == [], result


# ------------------------------------------------------------------ tests
@pytest.mark.parametrize("loader", ["ignoring_sigterm", "swallowing_exit"])
def test_a_hostile_object_times_out_and_the_others_complete(tmp_path, loader):
    result = run_case(tmp_path, [loader], "timeout", timeout=2)
    assert result["outcome"] == "returned" and result["completed"] == 3, result
    assert result["failed"] == [["bad/0", "timed out after 2 s"]], result
    clean(result)


def test_an_interrupt_mid_write_removes_the_temporary_file_at_once(tmp_path):
    result = run_case(tmp_path, ["writing_a_large_file"], "interrupt")
    assert result["outcome"] == "KeyboardInterrupt", result
    assert result["after_interrupt"] < 2.0, result  # it unwound: no wait for the grace period
    clean(result)  # no hidden temporary file in the store


def test_the_grace_period_is_shared_by_the_workers_stopped_together(tmp_path):
    """Two busy workers that ignore SIGTERM, interrupted: both are killed at the one deadline, STOP_GRACE_S after
    the interrupt, not one grace period after the other."""
    result = run_case(tmp_path, ["ignoring_sigterm", "ignoring_sigterm"], "interrupt", grace=3.0)
    assert result["outcome"] == "KeyboardInterrupt", result
    assert 3.0 <= result["after_interrupt"] < 3.0 * 1.6, result
    clean(result)


def test_a_timed_out_object_that_finishes_in_its_grace_period_is_recorded_failed_in_the_store(tmp_path):
    """The parent writes the timed-out object's failed record only once its worker is gone: a worker that finishes
    the object while it is being stopped (here a loader that swallows the SystemExit) must not leave a complete
    record in the store for an object the report calls failed."""
    result = run_case(tmp_path, ["swallowing_exit_then_box"], "timeout", timeout=2, grace=5.0)
    assert result["failed"] == [["bad/0", "timed out after 2 s"]], result
    record = json.loads((tmp_path / "store" / "records" / "00000.json").read_text())
    assert record["status"] == "failed", record


@pytest.mark.parametrize("strict", [False, True])
def test_a_worker_that_closed_its_pipe_is_killed_without_grace(tmp_path, strict):
    """A worker whose pipe is closed (dead, or running on without it) is only reaped: killed after the 1 s join,
    not sent SIGTERM and given STOP_GRACE_S (its loader's ``finally`` does not run)."""
    result = run_case(tmp_path, ["closing_its_pipe"], "timeout", workers=1, timeout=30, strict=strict)
    assert result["outcome"] == ("DatasetError" if strict else "returned"), result
    assert result["marks"] == [], result
    clean(result)


@pytest.mark.parametrize("mode", ["timeout", "interrupt"])
def test_a_process_the_loader_started_ends_with_its_worker(tmp_path, mode):
    """A loader's own child process (say an external converter that hangs) is killed with its stopped worker: it
    would run on for ever, and hold the terminal's stdout (``generate ... | tee`` waited for it)."""
    result = run_case(tmp_path, ["spawning_a_child"], mode, timeout=2 if mode == "timeout" else None)
    assert result["outcome"] == ("returned" if mode == "timeout" else "KeyboardInterrupt"), result
    clean(result)


def test_an_object_done_while_generate_was_held_up_is_kept(tmp_path):
    """An object whose "done" waits in the pipe behind a progress message when generate next looks at the clock
    (here generate was stopped past the timeout while the worker finished) is recorded completed, not timed out:
    before, the object was recorded failed and its work was lost."""
    result = run_case(tmp_path, ["finishing_while_its_caller_is_stopped"], "timeout", workers=1, timeout=3)
    assert result["outcome"] == "returned", result
    assert result["failed"] == [], result
    assert result["completed"] == 4, result  # the bad object and the three good ones
    clean(result)


# ------------------------------------------------------------------ SIGTERM and what a kill leaves
def test_stale_temporaries_are_the_names_atomic_path_gives(tmp_path):
    from perception.atomic import atomic_path, stale_temporaries

    (tmp_path / "c" / "0").mkdir(parents=True)
    for name in (".keep", ".0.notahex", "0.abcd1234", ".3.json.0123abcd.txt", ".backup.1", ".notes.cafebab",
                 ".notes.123456789", ".notes.CAFEBABE"):  # not atomic_path's: it names 8 hex digits and keeps the suffix
        (tmp_path / "c" / name).write_text("x")
    for target in (tmp_path / "c" / "0" / "0", tmp_path / "records" / "3.json", tmp_path / "zarr.json"):
        with atomic_path(target) as tmp:
            assert stale_temporaries(tmp_path) == [tmp]
    assert stale_temporaries(tmp_path) == []


def test_a_resumed_run_removes_what_killed_writers_left(tmp_path):
    """A worker SIGKILLed while it replaced a chunk leaves its temporary file; the next run on the store, holding its
    lock, removes such files (and only those) and the store verifies."""
    from tactile.dataset import generate, verify_store
    from tactile.sensor import FSRSensor

    store = tmp_path / "store"
    kwargs = {"strategies": ("blind",), "contours_per_object": 2, "sensor": FSRSensor(rows=8, cols=8), "probes": 5,
              "workers": 1, "progress": False}
    generate([("box", 0), ("can", 1)], store, **kwargs)
    chunk = next(p for p in (store / "frames" / "c").rglob("*") if p.is_file())
    planted = [chunk.with_name(f".{chunk.name}.0badc0de"), store / "records" / ".1.json.12345678.json"]
    for path in planted:
        path.write_bytes(b"half a chunk")
    (store / ".mine").write_text("a user's file")
    generate([("box", 0), ("can", 1)], store, **kwargs)
    assert not any(p.exists() for p in planted) and (store / ".mine").exists()
    assert verify_store(store).ok


def test_sigterm_stops_generate_as_ctrl_c_does(tmp_path):
    """`kill`, `timeout` and batch schedulers send SIGTERM: the command unwinds (workers stopped, each removing its
    temporary file), says so in one line and exits 143; the run resumes."""
    store = tmp_path / "store"
    argv = [sys.executable, "-m", "fusion.cli", "generate", "--catalogue", "3", "--out", str(store),
            "--strategies", "blind", "--contours", "300", "--probes", "10", "--workers", "2", "--no-progress"]
    with open(tmp_path / "stderr", "w") as stderr:
        proc = subprocess.Popen(argv, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.DEVNULL,
                                stderr=stderr)
        deadline = time.monotonic() + 120
        while not list((store / "records").glob("*.json")) and time.monotonic() < deadline:
            time.sleep(0.05)
        workers = children(proc.pid)
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=60)
    err = (tmp_path / "stderr").read_text()
    assert code == 143, err
    assert err.strip().splitlines()[-1] == ("visuotactile generate: terminated; finished work is kept, re-run to "
                                           "resume"), err
    assert "resource_tracker" not in err and "Traceback" not in err, err
    deadline = time.monotonic() + 5
    while any(map(alive, workers)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(map(alive, workers))
    assert [p for p in store.rglob(".*") if p.is_file()] == []
