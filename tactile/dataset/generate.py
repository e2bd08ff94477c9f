"""Generating a tactile dataset store: deterministic, resumable, on local worker processes or Ray.

Each object is explored by a worker (a process forked from a forkserver that explores one object after
another, or a Ray task) that loads it, computes its saliency at most once per method, explores every strategy,
writes its rows and then its completion record. An object whose worker raises, hangs past ``object_timeout_s``
or dies (e.g. a native abort in a mesh library) is recorded as failed with the reason; a new worker takes the
next object, and the others go on. Resuming
first checks every complete object against its checksums and digests (:mod:`tactile.dataset.integrity`):
a damaged object loses its record and is explored again, so the store ends as an undamaged run would.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shlex
import signal
import sys
import time
import uuid
from collections import deque
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from perception.errors import DatasetError, InvalidArgumentError, shown
from perception.runtime import (
    STOP_GRACE_S,
    cores_limited,
    descendant_handles,
    exit_with,
    kill_handles,
    libc,
    limit_cores,
    package_version,
    progress_bar,
    stop_as_told,
    usable_cores,
    without_main_module,
    worker_cores,
)
from tactile import sampling
from tactile.dataset.objects import ObjectSpec, object_specs
from tactile.dataset.store import (
    create_store,
    frame_encoding,
    layout_of,
    read_attrs,
    read_records,
    record_path,
    settings_difference,
    store_lock,
    write_record,
)
from tactile.dataset.version import generation_code_version
from tactile.sensor import FSRSensor

log = logging.getLogger(__name__)

EXECUTORS = ("local", "ray")
#: Messages of an overdue worker read before its timeout is enforced (its object may have finished meanwhile).
MAX_WAITING_MESSAGES = 1000
#: What the workers' forkserver imports before it forks them, with Ctrl-C held off meanwhile (the guards).
WORKER_PRELOAD = ["perception.preload_guard", "tactile.dataset.worker", "zarr", "numcodecs.blosc", "google_crc32c",
                  "perception.preload_guard_end"]


@dataclass
class GenerationReport:
    """What a :func:`generate` call did.

    Attributes:
        path: the store.
        objects: objects in the store.
        skipped: objects already complete (and intact) before this call (resumed).
        completed: objects completed by this call.
        repaired: (object name, what was wrong) of complete objects found damaged and explored again.
        failed: (object name, reason) of the objects that failed in this call.
        sequences: sequences written by this call.
        seconds: wall time of this call, s.
    """

    path: Path
    objects: int
    skipped: int = 0
    completed: int = 0
    repaired: list[tuple[str, str]] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)
    sequences: int = 0
    seconds: float = 0.0

    @property
    def sequences_per_s(self) -> float:
        return self.sequences / self.seconds if self.seconds > 0 else 0.0

    def to_dict(self) -> dict:
        return {
            "path": str(self.path), "objects": self.objects, "skipped": self.skipped,
            "completed": self.completed, "repaired": [list(r) for r in self.repaired],
            "failed": [list(f) for f in self.failed], "sequences": self.sequences,
            "seconds": round(self.seconds, 3), "sequences_per_s": round(self.sequences_per_s, 2),
        }


def _check_sizes(n_objects: int, strategies: tuple[str, ...], contours: int, probes: int, sensor: FSRSensor,
                 object_timeout_s) -> None:
    """Every count within its limit (:mod:`perception.limits`) and a usable timeout, before the store is made."""
    import math

    from perception.limits import check_bytes, check_count

    check_count("objects", n_objects, "objects")
    check_count("contours", contours, "contours per object and strategy")
    check_count("probes", probes, "probes per contour")
    taxels = check_count("taxels", sensor.rows * sensor.cols, "sensor rows x cols")
    block = len(strategies) * contours
    check_count("sequences", n_objects * block, f"{n_objects} objects x {len(strategies)} strategies x {contours} "
                                                "contours")
    check_bytes(block * probes * (taxels * 6 + 64), f"one object's {block} sequences (what a worker holds)")
    if object_timeout_s is not None and (isinstance(object_timeout_s, bool) or not isinstance(
            object_timeout_s, (int, float)) or not math.isfinite(object_timeout_s) or object_timeout_s <= 0):
        raise InvalidArgumentError(f"object_timeout_s (--timeout) must be a finite number of seconds > 0 (or None), got "
                                   f"{object_timeout_s!r}")


def _check(strategies, contours_per_object, sensor, probes, seed, workers, executor) -> tuple[str, ...]:
    strategies = (strategies,) if isinstance(strategies, str) else tuple(strategies)
    if not strategies or len(set(strategies)) != len(strategies):
        raise InvalidArgumentError(f"strategies must be a non-empty list without repeats, got {list(strategies)}")
    unknown = [s for s in strategies if s not in sampling.STRATEGIES]
    if unknown:
        raise InvalidArgumentError(f"unknown strategies {unknown}; choose from {', '.join(sampling.STRATEGIES)}")
    for name, value, low in (("contours_per_object", contours_per_object, 1), ("probes", probes, 2), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise InvalidArgumentError(f"{name} must be an integer >= {low}, got {value!r}")
    if not isinstance(sensor, FSRSensor):
        raise InvalidArgumentError(f"sensor must be an FSRSensor, got {type(sensor).__name__}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise InvalidArgumentError(f"workers must be a positive integer or None, got {workers!r}")
    if executor not in EXECUTORS:
        raise InvalidArgumentError(f"executor must be one of {EXECUTORS}, got {executor!r}")
    return strategies


def _open_or_create(out: Path, settings: dict, command: str | None) -> None:
    """Create the store, or check that the existing one was made with the same settings."""
    if out.exists() and not (out.is_dir() and not any(out.iterdir())):
        if not out.is_dir():
            raise DatasetError(f"{out}: exists and is not a folder; choose another output path")
        attrs = read_attrs(out)
        diffs = settings_difference(attrs["settings"], settings)
        if diffs:
            raise DatasetError(
                f"{out}: the store was generated with other settings ({'; '.join(diffs)}); "
                "re-run with the same settings to resume, or choose another output path"
            )
        if attrs.get("package_version") != package_version():
            log.warning("%s: made by visuotactile %s, resuming with %s", out, _inert(attrs.get("package_version")),
                        package_version())
        elif attrs.get("generation_code", generation_code_version()) != generation_code_version():
            log.warning("%s: begun by other generation code (%s, now %s): the objects generated now may read "
                        "otherwise than those before; generate into a new path for one code's rows", out,
                        _inert(attrs["generation_code"]), generation_code_version())
        return
    meta = {
        "package_version": package_version(),
        "generation_code": generation_code_version(),
        "command": command if command is not None else shlex.join(sys.argv),
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "store_id": uuid.uuid4().hex,  # tells two stores of the same settings apart (models record it)
    }
    create_store(out, settings, meta)


def _inert(value) -> str:
    """A value read from a store's attributes (untrusted) as a log line may show it: a short printable string as it
    is, anything else abbreviated and escaped (no megabytes, no terminal escapes)."""
    if isinstance(value, str) and len(value) <= 64 and value.isprintable():
        return value
    return shown(value)


def _remove_stale_temporaries(out: Path) -> None:
    """Remove the temporary files of writers killed mid-write (a chunk being replaced when SIGKILL came) from the
    store ``out``: called under its lock, where no writer of it can be alive."""
    from perception.atomic import stale_temporaries

    stale = stale_temporaries(out)
    for path in stale:
        path.unlink(missing_ok=True)
    if stale:
        log.info("%s: removed %d temporary files of an interrupted run", out, len(stale))


def generate(
    objects,
    out: str | Path,
    *,
    strategies=("guided", "blind"),
    contours_per_object: int,
    sensor: FSRSensor | None = None,
    probes: int = 25,
    seed: int = 0,
    workers: int | None = None,
    executor: str = "local",
    strict: bool = False,
    progress: bool = True,
    object_timeout_s: float | None = None,
    ray_address: str | None = None,
    command: str | None = None,
    saliency_cache: str | Path | None = None,
) -> GenerationReport:
    """Explore every object along ``contours_per_object`` contours per strategy into the zarr store ``out``.

    Args:
        objects: a class-per-folder mesh collection, (path, label) pairs, catalogue (class, seed) pairs
            or :class:`ObjectSpec` (see :func:`object_specs`).
        out: the store folder. If it exists with the same settings, complete objects are skipped
            (resume); failed, unfinished and damaged ones (a missing or altered chunk, rows that differ from
            their record's digest) are explored again.
        strategies: sampling strategies (:data:`tactile.sampling.STRATEGIES`); saliency is computed once
            per object and method, never for blind-only runs.
        sensor: the FSR sensor (default ``FSRSensor()``); probes: probes per contour.
        seed: contour k of strategy s of object o uses seeds from (seed, o's name, s, k) only, so the
            store's bytes do not depend on ``workers``, the executor or the order objects finish in.
        workers: parallel workers (default: the usable cores; Ray: CPUs of a local instance it starts).
        executor: "local" (``workers`` processes, each exploring one object after another: a loader must leave no
            global state behind, such as a patched function, which would reach the next object; the processes it
            starts end with its worker, at the end of the run or when the worker is stopped) or "ray" (one
            task per object; an existing ``ray.init`` is used, else ``ray_address`` / ``RAY_ADDRESS``, else a local
            instance).
            Ray workers write to ``out`` themselves: on a cluster it must be on a shared file system.
        strict: stop at the first failed object (finished objects are kept) and raise.
        progress: show a tqdm bar (sequences, objects, rate, ETA).
        object_timeout_s: a worker still running after this long is stopped and its object recorded as
            failed (local executor); None waits.
        command: the creation command to record (default: this process's command line).
        saliency_cache: a folder of interest points by mesh content
            (:class:`~perception.interest_cache.InterestPointCache`): objects found there skip their saliency,
            the others add theirs. Stores of the same objects with other sizes or sensors then compute each
            object's saliency once. The store's bytes are the same with or without it.

    Returns:
        a :class:`GenerationReport`.

    Raises:
        DatasetError: bad arguments, ``out`` holds something else or a store with other settings, or
            (strict) an object failed.

    Examples:
        >>> import tempfile
        >>> from tactile.dataset import generate, open_dataset
        >>> from tactile.sensor import FSRSensor
        >>> out = tempfile.mkdtemp() + "/small.zarr"
        >>> report = generate([("box", 0), ("can", 0)], out, strategies="blind", contours_per_object=2, probes=5,
        ...                   sensor=FSRSensor(rows=8, cols=8), workers=1, progress=False)
        >>> report.completed, report.failed
        (2, [])
        >>> len(open_dataset(out))  # 2 objects x 2 contours
        4
    """
    start = time.perf_counter()
    sensor = FSRSensor() if sensor is None else sensor
    strategies = _check(strategies, contours_per_object, sensor, probes, seed, workers, executor)
    specs = object_specs(objects)
    _check_sizes(len(specs), strategies, contours_per_object, probes, sensor, object_timeout_s)
    sensor_spec = sensor.spec()
    settings = {
        "objects": [s.to_dict() for s in specs],
        "class_names": sorted({s.label for s in specs}),
        "strategies": list(strategies),
        "contours_per_object": contours_per_object,
        "probes": probes,
        "sensor": sensor_spec,
        "seed": seed,
        "encoding": frame_encoding(sensor_spec),
        **sampling.pair_setting(strategies),
    }
    out = Path(out).resolve()
    with store_lock(out):  # one writer at a time: a second run on this store is refused
        _open_or_create(out, settings, command)
        _remove_stale_temporaries(out)
        layout = layout_of(settings)
        repaired = _forget_damaged(out, specs, progress)
        records = read_records(out, len(specs))
        todo = [i for i in range(len(specs)) if records.get(i, {}).get("status") != "complete"]
        report = GenerationReport(out, len(specs), skipped=len(specs) - len(todo), repaired=repaired)
        if not todo:
            log.info("%s: all %d objects are complete", out, len(specs))
            report.seconds = time.perf_counter() - start
            return report
        n_workers = min(workers or usable_cores(), len(todo))
        bar = progress_bar(total=len(todo) * layout.block, enabled=progress, desc="generate", unit="seq", smoothing=0.1)
        bar.set_postfix_str(f"objects {report.skipped}/{len(specs)}")

        def finished(index: int, ok: bool, detail) -> None:
            if ok:
                report.completed += 1
                report.sequences += layout.block
            else:
                reason = str(detail)
                write_record(out, index, {"index": index, "name": specs[index].name, "label": specs[index].label,
                                          "status": "failed", "reason": reason})
                report.failed.append((specs[index].name, reason))
                log.warning("%s: failed: %s", specs[index].name, reason)
            bar.set_postfix_str(
                f"objects {report.skipped + report.completed}/{len(specs)}"
                + (f", failed {len(report.failed)}" if report.failed else "")
            )
            if not ok and strict:
                raise DatasetError(
                    f"{specs[index].name}: {detail} (strict: stopped at the first failure; finished objects are "
                    f"kept in {out}, re-run to resume)"
                )

        cache = None if saliency_cache is None else str(Path(saliency_cache).resolve())
        args = (str(out), specs, settings, sensor, todo, n_workers, finished, bar, cache)
        try:
            if executor == "local":
                _run_local(*args, object_timeout_s)
            else:
                _run_ray(*args, ray_address)
        finally:
            bar.close()
        report.seconds = time.perf_counter() - start
        return report


def _forget_damaged(out: Path, specs: list[ObjectSpec], progress: bool) -> list[tuple[str, str]]:
    """Check the store's complete objects; remove the record of each damaged one (so that it is explored again,
    even if this run is interrupted) and return (name, what was wrong)."""
    from tactile.dataset.integrity import damaged_objects

    damaged = damaged_objects(out, progress=progress)
    for index, problem in damaged.items():
        log.warning("%s: %s is damaged (%s); exploring it again", out, specs[index].name, problem)
        with contextlib.suppress(FileNotFoundError):
            os.remove(record_path(out, index))
    return [(specs[index].name, problem) for index, problem in damaged.items()]


# ------------------------------------------------------------------------------------ local executor
def _reason_for_exit(code: int | None) -> str:
    if code is not None and code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"worker process died with {name} (a native crash, e.g. in a mesh library, or killed)"
    if code == 1:  # what an unpicklable object spec gives
        return (f"worker process exited with code {code} before reporting (an ObjectSpec loader defined in the main "
                "script cannot be loaded by workers: define it in an importable module)")
    return f"worker process exited with code {code} before reporting (the object's loader, or a library, ended it)"


def _worker(conn, store: str, settings: dict, sensor: FSRSensor, saliency_cache: str | None, caller: int,
            cores: int) -> None:
    """Worker process body: explore the objects the parent sends, one at a time, until it sends None, on at most
    ``cores`` cores (:func:`~perception.runtime.worker_cores`); report each one's progress and outcome through
    ``conn``. One process explores many objects, so only the first pays for a fresh process's memory (page faults,
    first calls: 0.55 of the 5.3 s of a SHREC object explored alone); an object that kills its worker (a native
    abort) or hangs is recorded as failed and the parent starts a new worker."""
    stop_as_told()  # asked to stop mid-object (an interrupt, a timeout): unwind, removing a chunk file half written
    exit_with(caller)  # generate's process killed: no orphan writes on into the store
    _keep_freed_memory()
    limit_cores(cores)
    from tactile.dataset.worker import explore_into_store

    while (task := _next_task(conn)) is not None:
        index, spec = task
        try:
            explore_into_store(store, index, spec, settings, sensor, progress=lambda n: conn.send(("progress", n)),
                               saliency_cache=saliency_cache)
            conn.send(("done", None))
        except Exception as exc:  # noqa: BLE001 -- any failure of one object is recorded, never raised
            conn.send(("failed", f"{type(exc).__name__}: {exc}"))
    conn.close()


def _next_task(conn):
    """The next (index, spec) from the parent; None when it says so, or when its end of the pipe is closed (a parent
    interrupted while it started this worker exits without knowing of it: no traceback for that)."""
    try:
        return conn.recv()
    except (EOFError, OSError):
        return None


def _keep_freed_memory() -> None:
    """glibc: serve allocations up to 32 MiB from the heap and keep up to 1 GiB of freed heap, so the worker's
    per-cast buffers (rays, Open3D's hit arrays: tens of MB each, a few thousand per object) reuse memory instead
    of mapping fresh zeroed pages each time. Measured on 3 SHREC objects explored in one process: 6 % less CPU, 8 %
    less wall time, the same bytes. Elsewhere (no glibc ``mallopt``) nothing changes."""
    mallopt = getattr(libc(), "mallopt", None)
    if mallopt is None:
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's malloc.h
    mallopt(m_mmap_threshold, 32 << 20)  # glibc's largest allowed value
    mallopt(m_trim_threshold, 1 << 30)


def _context():
    import multiprocessing as mp

    # forkserver: children fork from a clean server with the libraries imported once (fast start, and no
    # fork of a parent whose Open3D/BLAS thread pools are running). The worker imports zarr and its codecs
    # lazily: preloaded, each child saves their import (0.17 s per object; nothing of theirs runs at import).
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(WORKER_PRELOAD)
    return ctx


@dataclass
class _Running:
    """A worker process, its end of the pipe, and the object it explores (None: idle) since when."""

    process: object
    conn: object
    index: int | None = None
    started: float = 0.0


def _run_local(store, specs, settings, sensor, todo, n_workers, finished, bar, saliency_cache, timeout_s) -> None:
    from multiprocessing.connection import wait

    ctx = _context()
    pending = deque(todo)
    workers: list[_Running] = []

    def start_worker() -> _Running:
        parent, child = ctx.Pipe(duplex=True)
        proc = ctx.Process(target=_worker, args=(child, store, settings, sensor, saliency_cache, os.getpid(),
                                                   worker_cores(n_workers)),
                           name="generate-worker", daemon=True)
        with without_main_module():
            proc.start()
        child.close()  # the worker holds the other end: EOF here means it has exited (or closed it)
        worker = _Running(proc, parent)
        workers.append(worker)
        return worker

    def stop(*ending: _Running, dead: bool = False) -> None:
        """End the ``ending`` workers together, each so that its clean-up runs (a SIGKILL leaves half-written temporary
        chunk files, and the semaphores a library made for the resource tracker to warn about): an idle one is told to
        exit, a busy one is sent SIGTERM (see :func:`perception.runtime.stop_as_told`); any not gone within
        ``STOP_GRACE_S`` is killed.
        ``dead``: workers whose pipe is closed, only reaped. The processes a worker's loader started go with it: listed
        before it is signalled (an orphan can no longer be traced to it), killed once it is gone."""
        started = [descendant_handles(worker.process.pid) for worker in ending]
        for worker in () if dead else ending:
            if worker.index is None:
                with contextlib.suppress(OSError):
                    worker.conn.send(None)
            else:
                worker.process.terminate()
        deadline = time.monotonic() + (0.0 if dead else STOP_GRACE_S)
        for worker, handles in zip(ending, started):
            worker.process.join(timeout=max(deadline - time.monotonic(), 0.0))
            worker.process.kill()
            worker.process.join()
            kill_handles(handles)
            worker.conn.close()
            workers.remove(worker)

    def assign(worker: _Running, fresh: bool) -> None:
        """Send ``worker`` the next object. A closed pipe means the worker has died: a new worker's death fails the
        object (as a worker dying with it would); a reused one may have died idle, so its object waits for another."""
        index = pending.popleft()
        try:
            worker.conn.send((index, specs[index]))
        except OSError:
            stop(worker, dead=True)
            if fresh:
                finished(index, False, _reason_for_exit(worker.process.exitcode))
            else:
                pending.appendleft(index)
            return
        worker.index, worker.started = index, time.monotonic()

    def receive(worker: _Running) -> None:
        """Take one message of ``worker`` (its pipe is readable): progress, or its object's outcome."""
        try:
            kind, value = worker.conn.recv()
        except (EOFError, OSError):  # the worker died (a native abort, killed) or closed its pipe
            worker.process.join(timeout=1)  # one that closed its pipe and runs on is killed by stop
            index = worker.index
            stop(worker, dead=True)
            if index is not None:
                finished(index, False, _reason_for_exit(worker.process.exitcode))
            return
        if kind == "progress":
            bar.update(value)
            return
        index, worker.index = worker.index, None  # idle before finished(), which raises when strict
        finished(index, kind == "done", value)

    try:
        while pending or any(w.index is not None for w in workers):
            for worker in [w for w in workers if w.index is None]:
                if pending:
                    assign(worker, fresh=False)
            while pending and len(workers) < n_workers:
                assign(start_worker(), fresh=True)
            for conn in wait([w.conn for w in workers], timeout=1.0):
                receive(next(w for w in workers if w.conn is conn))
            if timeout_s is not None:
                now = time.monotonic()
                for worker in [w for w in workers if w.index is not None and now - w.started > timeout_s]:
                    # an object finished while this loop was elsewhere is done, not timed out (the messages
                    # waiting now; a bound, so that a stream of progress cannot put the timeout off for ever)
                    for _ in range(MAX_WAITING_MESSAGES):
                        if worker not in workers or worker.index is None or not worker.conn.poll():
                            break
                        receive(worker)
                    if worker in workers and worker.index is not None:
                        index = worker.index
                        stop(worker)
                        finished(index, False, f"timed out after {timeout_s:g} s")
    finally:
        stop(*workers)  # done, interrupted or strict


# -------------------------------------------------------------------------------------- Ray executor
def _ray_task(store: str, index: int, spec: ObjectSpec, settings: dict, sensor: FSRSensor,
              saliency_cache: str | None = None) -> tuple:
    from tactile.dataset.worker import explore_into_store

    try:
        # The task holds one of Ray's CPUs; the worker process is Ray's, so its limits are given back after.
        with cores_limited(1):
            explore_into_store(store, index, spec, settings, sensor, saliency_cache=saliency_cache)
        return True, None
    except Exception as exc:  # noqa: BLE001 -- any failure of one object is recorded, never raised
        return False, f"{type(exc).__name__}: {exc}"


def _run_ray(store, specs, settings, sensor, todo, n_workers, finished, bar, saliency_cache, address) -> None:
    try:
        import ray
    except ImportError as exc:
        raise DatasetError(
            "executor='ray' needs Ray: pip install 'visuotactile[dist]' (or pip install 'ray>=2.40')"
        ) from exc
    started_here = not ray.is_initialized()
    if started_here:
        address = address or os.environ.get("RAY_ADDRESS")
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=n_workers, include_dashboard=False, log_to_driver=False)
    task = ray.remote(num_cpus=1, max_retries=0)(_ray_task)
    layout = layout_of(settings)
    refs = {task.remote(store, i, specs[i], settings, sensor, saliency_cache): i for i in todo}
    try:
        while refs:
            ready, _ = ray.wait(list(refs), num_returns=1)
            index = refs.pop(ready[0])
            try:
                ok, reason = ray.get(ready[0])
            except ray.exceptions.RayError as exc:  # the worker died (abort, OOM kill, node lost)
                ok, reason = False, f"Ray worker failed: {type(exc).__name__}: {str(exc).splitlines()[0]}"
            if ok:
                bar.update(layout.block)
            finished(index, ok, reason)
    finally:
        for ref in refs:
            ray.cancel(ref, force=True)
        if started_here:
            ray.shutdown()


__all__ = ["EXECUTORS", "GenerationReport", "generate"]
