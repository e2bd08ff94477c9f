"""Many models trained and tested side by side: one worker process per core, each on one core.

A part of an experiment lists its fits as :class:`FitTask` objects (what :func:`train_and_predict` takes, with the
data named by store and rows so that a worker can read it itself), and :func:`run_tasks` runs those whose model or
predictions are not cached yet in worker processes, the most expensive first.

Why processes and one core each: on two cores a CNN step is only 1.4-1.6 times faster on two threads than on one,
so two fits on one thread each finish about a fifth sooner than the same fits one after the other on two threads;
libsvm trains on one thread whatever it is given. The experiments' CNNs train on one thread wherever they run
(:func:`fusion.experiments.models.default_classifiers`), so their weights are the same bytes with any number of
workers or cores (a CNN's sums depend on its thread count); the paper's SVM pipeline moved in the ninth decimal
(2e-9) between one worker of two cores and two of one, its decisions unchanged. A fusion CNN's two nets train as
two jobs (:meth:`fusion.cnn.CNNClassifier.from_nets` joins them into the weights one fit gives), so three equal
folds spread over two workers without one waiting for the last.

A worker that dies (a native crash, the kernel's out-of-memory killer) takes no one with it: its unfinished tasks
are run again one at a time, each in a fresh worker, and the one that kills its worker again is answered with
:class:`perception.errors.WorkerError`.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import pickle
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.experiments.models import Factory, Predictions, cached_predictions, train_and_predict
from fusion.modelfile import SUFFIX
from perception.errors import InvalidArgumentError, WorkerError
from perception.runtime import (
    STOP_GRACE_S,
    Stopped,
    exit_with,
    limit_cores,
    progress_bar,
    set_progress,
    stop_as_told,
    usable_cores,
    without_main_module,
    worker_cores,
)

log = logging.getLogger(__name__)

#: Relative training cost per sequence of a classifier class (others: 1): the expensive fits start first.
FIT_COST = {"CNNClassifier": 20.0}


@dataclass(frozen=True, eq=False)
class StoreRows:
    """The rows ``index`` of the store at ``path``, read when called (a loader a worker process can take)."""

    path: str
    index: np.ndarray

    def key(self) -> tuple[str, str]:
        return self.path, hashlib.sha256(np.ascontiguousarray(self.index, dtype=np.int64)).hexdigest()

    def __call__(self):
        key = self.key()
        if key not in _last_read:
            from tactile.dataset import open_dataset

            while len(_last_read) >= READS_KEPT:
                _last_read.pop(next(iter(_last_read)))
            _last_read[key] = open_dataset(self.path).load(self.index)
        _last_read[key] = _last_read.pop(key)  # the most recent last
        return _last_read[key]


#: Batches a process keeps from its last reads (a training and a test set): the light fits of one training set
#: read it once, and compute their features once (they are cached per batch object, ``fusion.features``).
READS_KEPT = 2
_last_read: dict = {}


@dataclass(frozen=True)
class FitTask:
    """One :func:`fusion.experiments.models.train_and_predict` call: train classifier ``name`` (or load it from
    ``folder``) on ``train`` and predict ``test``."""

    name: str
    factory: Factory
    train: Callable
    test: Callable
    folder: Path
    record: dict
    test_record: dict | None = None

    def run(self) -> Predictions:
        return train_and_predict(self.name, self.factory, self.train, self.test, self.folder, self.record,
                                 self.test_record)

    def model_path(self) -> Path:
        return self.folder / f"{self.name}{SUFFIX}"

    def cached(self) -> Predictions | None:
        """Its cached predictions (then :meth:`run` would only read them), or None."""
        return cached_predictions(self.name, self.factory, self.folder, self.record, self.test_record)

    def cost(self) -> float:
        """A rough relative cost of running it, to start the expensive tasks first."""
        return fit_cost(self.factory, self.train)

    def train_key(self) -> tuple | None:
        """What identifies its training set when it may share it with other light tasks (None: it runs alone)."""
        if not isinstance(self.train, StoreRows) or type(self.factory()).__name__ in FIT_COST:
            return None
        return self.train.key()

    def __str__(self) -> str:
        return f"training or testing {self.name} in {self.folder}"


def run_tasks(tasks: list[FitTask], workers: int | None = None, progress: bool = True) -> list:
    """Run ``tasks`` and return, in their order, each one's :class:`Predictions` or the exception it raised.

    Tasks not cached yet run by :func:`run_jobs`, in groups that run one after the other in one worker: the tasks
    of one model (the same file: the first trains it, the others read it and predict), and the light tasks
    (classifiers not in :data:`FIT_COST`) of one training set (one read, one feature pass). With two workers or
    more, a fusion CNN not trained yet trains its two nets as two jobs first, beside the other groups
    (:class:`_NetFit`; the same weights as one fit), so one model's nets spread over the workers; its group then
    reads it and predicts.
    Nothing is raised for a failed task: callers decide what a failure means.
    """
    outcomes: dict[int, object] = {}
    groups: dict[tuple, list[int]] = {}
    for i, task in enumerate(tasks):
        cached = task.cached()
        if cached is not None:
            outcomes[i] = cached
            continue
        train = task.train_key()
        groups.setdefault(("model", task.model_path()) if train is None else ("train", *train), []).append(i)
    members = list(groups.values())
    side_by_side = _worker_count(workers) > 1
    split = [g for g in members if side_by_side and _nets_to_train(tasks[g[0]])]
    first = [g for g in members if g not in split]
    net_jobs = [_NetFit(tasks[g[0]], net) for g in split for net in NET_SHARE]
    with shared_workers():  # one pool for both rounds
        done = run_jobs(net_jobs + [_group_job(tasks, g) for g in first], workers, progress)
        _collect(outcomes, first, done[len(net_jobs):])
        joined = []
        for n, group in enumerate(split):
            error = _join_nets(tasks[group[0]], done[n * len(NET_SHARE):(n + 1) * len(NET_SHARE)])
            if error is None:
                joined.append(group)
            else:
                outcomes.update(dict.fromkeys(group, error))
        _collect(outcomes, joined, run_jobs([_group_job(tasks, g) for g in joined], workers, progress))
    return [outcomes[i] for i in range(len(tasks))]


#: The nets of a fusion CNN trained as separate jobs, with their rough share of its training cost (measured at
#: the paper's and the unseen part's sizes: the cutaneous net takes 2 to 3 times the kinesthetic one).
NET_SHARE = {"cutaneous": 0.7, "kinesthetic": 0.3}


def _nets_to_train(task: FitTask) -> bool:
    """Whether ``task``'s model is a fusion CNN that is not trained yet (then its nets train as two jobs)."""
    from fusion.cnn import CNNClassifier
    from fusion.experiments.models import cached_fit_seconds, model_record

    estimator = task.factory()
    return (type(estimator) is CNNClassifier and estimator.modality == "fusion"
            and cached_fit_seconds(task.model_path(), model_record(task.factory, task.record)) is None)


@dataclass(frozen=True)
class _NetFit:
    """Train one net of ``task``'s fusion CNN: the model with ``modality=net``; returns (model, seconds)."""

    task: FitTask
    net: str

    def run(self) -> tuple:
        estimator = self.task.factory().set_params(modality=self.net)
        batch = self.task.train()
        start = time.perf_counter()
        estimator.fit(batch)
        return estimator, time.perf_counter() - start

    def cost(self) -> float:
        return self.task.cost() * NET_SHARE[self.net]

    def __str__(self) -> str:
        return f"training the {self.net} net of {self.task.name} in {self.task.folder}"


def _join_nets(task: FitTask, fitted: list) -> BaseException | None:
    """Save ``task``'s fusion model joined from its nets' :class:`_NetFit` outcomes (its training time: the sum of
    theirs); the failure, if a net or the saving failed."""
    from fusion.cnn import CNNClassifier
    from fusion.experiments.models import model_record, save_fitted

    failed = next((outcome for outcome in fitted if isinstance(outcome, BaseException)), None)
    if failed is not None:
        return failed
    try:
        model = CNNClassifier.from_nets(*(estimator for estimator, _ in fitted))
        save_fitted(model, sum(seconds for _, seconds in fitted), task.model_path(),
                    model_record(task.factory, task.record))
    except Exception as exc:  # noqa: BLE001 -- the tasks of this model fail with it, the others go on
        return exc
    return None


def _worker_count(workers: int | None) -> int:
    """The worker processes :func:`run_jobs` starts when asked for ``workers`` (None: the usable cores; never more).

    Raises:
        InvalidArgumentError: ``workers`` is not None or a positive integer.
    """
    if workers is None:
        return usable_cores()
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise InvalidArgumentError(f"workers must be a positive integer or None (the usable cores), got {workers!r}")
    return min(int(workers), usable_cores())


def _group_job(tasks: list[FitTask], group: list[int]):
    return tasks[group[0]] if len(group) == 1 else _Together([tasks[i] for i in group])


def _collect(outcomes: dict[int, object], groups: list[list[int]], results: list) -> None:
    """Each task's outcome from its group's (a list for a group of several, one outcome for a dead worker's)."""
    for group, result in zip(groups, results, strict=True):
        together = len(group) > 1 and not isinstance(result, BaseException)
        outcomes.update({i: result[n] if together else result for n, i in enumerate(group)})


def run_jobs(jobs: list, workers: int | None = None, progress: bool = True, *, desc: str = "fit",
             unit: str = "model") -> list:
    """Run ``jobs`` (objects with ``run()`` and ``cost()``; e.g. :class:`FitTask`) and return, in their order, what
    each ``run()`` returned or the exception it raised. ``desc`` and ``unit`` label the progress bar (one step per
    job).

    They run in ``workers`` processes (None, or more than the usable cores: the usable cores), the most expensive
    first, each worker on ``usable cores / workers`` cores (a lone job too: a crash there leaves this process
    alive); in this process when one worker is asked for, or when a job cannot be sent to another process (e.g. a
    classifier factory that is a lambda).

    Raises:
        InvalidArgumentError: ``workers`` is not None or a positive integer (so does :func:`run_tasks`).
    """
    workers = _worker_count(workers)
    try:
        if jobs and workers > 1 and _picklable(jobs):
            order = sorted(range(len(jobs)), key=lambda i: -jobs[i].cost())
            with progress_bar(total=len(jobs), enabled=progress, desc=desc, unit=unit) as bar:
                done = _in_workers(jobs, order, workers, bar)
            return [done[i] for i in range(len(jobs))]
        return [_outcome(job) for job in jobs]
    finally:
        _last_read.clear()


@dataclass(frozen=True)
class _Together:
    """Tasks run one after the other in one worker (they share a model or a training set); their outcomes, in
    order."""

    tasks: list[FitTask]

    def run(self) -> list:
        failed: dict[Path, BaseException] = {}  # a model that failed to train fails its other tasks, not twice
        out = []
        for task in self.tasks:
            outcome = failed.get(task.model_path()) or _outcome(task)
            if isinstance(outcome, BaseException):
                failed[task.model_path()] = outcome
            out.append(outcome)
        return out

    def cost(self) -> float:
        return sum(task.cost() for task in self.tasks)

    def __str__(self) -> str:
        return "; ".join(str(task) for task in self.tasks)


def raise_failures(outcomes: list) -> list[Predictions]:
    """The outcomes of :func:`run_tasks`, raising the first failure."""
    for outcome in outcomes:
        if isinstance(outcome, BaseException):
            raise outcome
    return outcomes


def fit_cost(factory: Factory, train) -> float:
    """A rough relative cost of training ``factory()`` on ``train`` (a :class:`StoreRows`: its rows count)."""
    rows = len(train.index) if isinstance(train, StoreRows) else 1
    return rows * FIT_COST.get(type(factory()).__name__, 1.0)


def _outcome(job):
    try:
        return job.run()
    except Exception as exc:  # noqa: BLE001 -- handed to the caller, which decides
        return exc
    except Stopped:  # the worker was told to stop: not the job's outcome
        raise
    except SystemExit as exc:  # a job that exits must not end the caller's process (nor, from a worker, its run)
        return RuntimeError(f"{job}: it called sys.exit({exc.code!r})")


def _picklable(jobs: list) -> bool:
    """Whether ``jobs`` can go to a worker: they pickle, and name nothing of ``__main__`` (a class defined in the
    caller's script or notebook), which the workers do not load."""
    try:
        sent = pickle.dumps(jobs)
    except (pickle.PicklingError, TypeError, AttributeError) as exc:
        log.info("running in this process: a job cannot go to a worker (%s)", exc)
        return False
    if b"__main__" in sent:
        log.info("running in this process: a job refers to the caller's __main__ module")
        return False
    return True


def _start_worker(cores: int, caller: int) -> None:
    stop_as_told()  # stopped (an interrupt in the caller): unwind, so that a model file half saved is removed
    exit_with(caller)  # the caller terminated or killed: no worker trains on for nobody
    set_progress(False)  # one bar, the caller's, counts the models
    limit_cores(cores)


def _run_in_worker(job):
    import joblib

    try:
        # threads, not loky's processes, for scikit-learn's inner jobs: a worker waits for its own children's
        # idle timeout (300 s) when it stops
        with joblib.parallel_config(backend="threading"):
            return _travelling(_outcome(job))
    except Stopped as exc:
        # The job has unwound (a file it was saving removed). Leave now: the pool's loop would catch the SystemExit,
        # report it and hand this worker the next queued job. multiprocessing's exit finalizers first (what a normal
        # exit of the process runs; private, hence guarded): semaphores a job made are released, not reported leaked.
        from multiprocessing import util

        with contextlib.suppress(Exception):
            util._run_finalizers(0)
            util._run_finalizers()
        os._exit(exc.code)
    finally:
        _last_read.clear()  # an idle worker holds no data


def _travelling(outcome):
    """``outcome`` as it can go back to the caller: a list element by element; what does not survive pickling and
    unpickling becomes a RuntimeError with its text (never a worker that seems to have died)."""
    if isinstance(outcome, list):
        return [_travelling(item) for item in outcome]
    try:
        pickle.loads(pickle.dumps(outcome))
    except Exception as exc:  # noqa: BLE001 -- whatever fails, the caller gets its text
        if isinstance(outcome, BaseException):
            return RuntimeError(f"{type(outcome).__name__}: {outcome}")
        return RuntimeError(f"the result of the job cannot be sent back ({type(exc).__name__}: {exc})")
    return outcome


def _in_workers(jobs: list, order: list[int], workers: int, bar) -> dict[int, object]:
    """Outcomes of ``jobs[i]`` for ``i`` in ``order``; a job whose worker died runs again alone, once."""
    done: dict[int, object] = {}
    cores = worker_cores(workers)
    left = _run_pool(jobs, order, workers, cores, done, bar)
    if left:  # every unfinished job again, each in a fresh worker of its own: only the one that kills dies
        log.warning("a worker process died; running its %d unfinished jobs again one by one", len(left))
        for i in list(left):
            if not _run_pool(jobs, [i], 1, cores, done, bar, keep=False):
                left.remove(i)
    for i in left:
        done[i] = WorkerError(f"the worker process died while {jobs[i]} (a crash in a native library, or out of "
                              f"memory)")
        bar.update()
    return done


#: Pools kept by :func:`shared_workers` ((workers, cores) -> pool); None outside such a block.
_kept: dict | None = None


@contextlib.contextmanager
def shared_workers() -> Iterator[None]:
    """Keep the worker processes of every :func:`run_tasks` call in the block: they start, and import PyTorch and
    scikit-learn, once (a few seconds each), however many parts and folds run; they stop when the block ends."""
    global _kept
    if _kept is not None:  # nested: the outer block keeps them
        yield
        return
    _kept = {}
    try:
        yield
    finally:
        pools, _kept = _kept, None
        for pool in pools.values():
            pool.shutdown(cancel_futures=True)


def _run_pool(jobs: list, order: list[int], workers: int, cores: int, done: dict, bar,
              keep: bool = True) -> list[int]:
    """Run ``jobs[i]`` for ``i`` in ``order`` on a pool of ``workers`` (kept by :func:`shared_workers` when
    ``keep``), their outcomes into ``done``; returns the indices left unfinished because a worker died."""
    import multiprocessing as mp

    key = (workers, cores)
    pool = _kept.pop(key, None) if keep and _kept is not None else None
    if pool is not None and getattr(pool, "_broken", False):  # a kept worker died while idle: start afresh
        pool.shutdown(wait=False, cancel_futures=True)
        pool = None
    if pool is None:
        pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("forkserver"), initializer=_start_worker,
                                   initargs=(cores, os.getpid()))
    broken = False
    try:
        futures = {}
        with without_main_module():  # the workers start as tasks are submitted
            for i in order:
                try:
                    futures[pool.submit(_run_in_worker, jobs[i])] = i
                except BrokenProcessPool:  # a worker died under an earlier job: the rest run again below
                    broken = True
                    break
        for future in as_completed(futures):
            try:
                done[futures[future]] = future.result()
            except BrokenProcessPool:
                broken = True
                continue
            except Exception as exc:  # noqa: BLE001 -- the job's outcome could not come back: its failure
                done[futures[future]] = exc
            bar.update()
    except BaseException:
        _kill(pool)  # an interrupt must not wait for fits of minutes
        raise
    if keep and _kept is not None and not broken:
        _kept[key] = pool
    else:
        pool.shutdown()
    return [i for i in order if i not in done]


def _kill(pool: ProcessPoolExecutor) -> None:
    """Stop ``pool``'s workers now: SIGTERM (each unwinds), SIGKILL for those not gone within :data:`STOP_GRACE_S`."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)  # no queued job starts while they stop
    for process in processes:
        process.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for process in processes:
        process.join(timeout=max(deadline - time.monotonic(), 0.0))
        if process.is_alive():
            process.kill()


__all__ = ["FIT_COST", "FitTask", "StoreRows", "fit_cost", "raise_failures", "run_jobs", "run_tasks", "shared_workers"]
