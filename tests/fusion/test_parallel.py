"""Fits side by side (fusion.experiments.parallel): the same bytes as one process, each model trained once, failures
and dying workers answered per task while the caller lives on, the workers' cores limited."""

from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from fusion.base import TactileClassifier
from fusion.classifiers import make_classifier
from fusion.experiments.parallel import (
    FIT_COST,
    FitTask,
    StoreRows,
    raise_failures,
    run_jobs,
    run_tasks,
    shared_workers,
)
from perception.errors import DatasetError, InvalidArgumentError, WorkerError
from perception.runtime import usable_cores
from tactile.dataset import generate, open_dataset
from tactile.sensor import FSRSensor
from tests._processes import alive

OBJECTS = [("box", 0), ("box", 1), ("ring", 0), ("ring", 1)]
#: The tests that watch two workers need two cores (run_jobs never starts more workers than cores).
two_cores = pytest.mark.skipif(usable_cores() < 2, reason="needs 2 usable cores for 2 workers")


class Unpicklable(DatasetError):
    def __init__(self, message, hook):
        super().__init__(message)
        self.hook = hook  # a lambda: pickling the exception fails


class FitLog(TactileClassifier):
    """Class means of the frames; each fit appends "<pid>" to the file ``log``.start, waits ``sleep`` seconds, then
    appends "<pid> <usable cores>" to ``log`` (and each prediction "<pid>" to ``log``.predict). ``fail``: "raise" (a DatasetError), "unpicklable" (an
    exception that cannot travel between processes), "exit" (sys.exit) or "abort" (the process dies) instead of
    fitting."""

    def __init__(self, log: str = "", fail: str = "", sleep: float = 0.0):
        self.log = log
        self.fail = fail
        self.sleep = sleep

    def _fit(self, batch, y):
        if self.log:
            with open(self.log + ".start", "a") as f:
                f.write(f"{os.getpid()}\n")
        if self.fail == "raise":
            raise DatasetError("planted failure")
        if self.fail == "abort":
            os.abort()
        if self.fail == "exit":
            sys.exit(3)
        if self.fail == "unpicklable":
            raise Unpicklable("planted failure", lambda: None)
        time.sleep(self.sleep)
        with open(self.log, "a") as f:
            f.write(f"{os.getpid()} {usable_cores()}\n")
        x = batch.frames.reshape(len(batch), -1).astype(np.float64)
        self.means_ = np.stack([x[y == c].mean(0) for c in range(len(self.classes_))])

    def _predict_proba(self, batch):
        if self.log:
            with open(self.log + ".predict", "a") as f:
                f.write(f"{os.getpid()}\n")
        x = batch.frames.reshape(len(batch), -1).astype(np.float64)
        d = ((x[:, None, :] - self.means_[None]) ** 2).sum(-1)
        e = np.exp(-(d - d.min(1, keepdims=True)))
        return e / e.sum(1, keepdims=True)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("parallel") / "store.zarr"
    generate(OBJECTS, path, strategies=("blind",), contours_per_object=6, sensor=FSRSensor(rows=8, cols=8), probes=6,
             seed=0, workers=1, progress=False)
    ds = open_dataset(path)
    train = np.flatnonzero(np.isin(ds.object_ids, [0, 2]))  # box/0 and ring/0
    test = np.flatnonzero(np.isin(ds.object_ids, [1, 3]))
    return str(path), train, test


def _tasks(store, root, factories: dict) -> list[FitTask]:
    path, train, test = store
    return [FitTask(name, factory, StoreRows(path, train), StoreRows(path, test), root / name, {"train": name})
            for name, factory in factories.items()]


def _logged(log) -> list[tuple[int, int]]:
    return [tuple(map(int, line.split())) for line in log.read_text().splitlines()] if log.exists() else []


@two_cores
def test_workers_give_the_predictions_one_process_gives(store, tmp_path):
    """Two one-thread CNN pairs and a kNN, trained by two workers (each CNN's nets as two jobs) and in this process:
    the same probabilities to the bit (the CNN's kernels sum in the same order on one thread wherever it runs)."""
    factories = {"cnn": functools.partial(make_classifier, "cnn", epochs=3, threads=1, progress=False),
                 "cnn2": functools.partial(make_classifier, "cnn", epochs=3, threads=1, progress=False,
                                           random_state=7),
                 "knn": functools.partial(make_classifier, "knn")}
    apart = raise_failures(run_tasks(_tasks(store, tmp_path / "two", factories), workers=2, progress=False))
    here = raise_failures(run_tasks(_tasks(store, tmp_path / "one", factories), workers=1, progress=False))
    for a, b in zip(apart, here, strict=True):
        assert a.proba.shape == (12, 2)
        assert np.array_equal(a.proba, b.proba)
        assert set(a.modalities) == set(b.modalities)
        assert all(np.array_equal(a.modalities[k], b.modalities[k]) for k in a.modalities)


@two_cores
def test_a_fusion_cnn_trains_its_two_nets_as_two_jobs_then_its_tasks_predict(store, tmp_path, monkeypatch):
    """With two workers, a fusion CNN not trained yet is two jobs, one per net, sent beside the other fits; the
    joined model is saved once with both nets' training time, then its two test sets are predicted (the bits
    equal one fit's: the test above). Cached, nothing is sent again; one worker trains the pair as one fit."""
    from fusion.base import load_model
    from fusion.experiments import parallel

    sent = []
    real = parallel.run_jobs
    monkeypatch.setattr(parallel, "run_jobs", lambda jobs, *a, **k: sent.append(sorted(map(str, jobs))) or real(
        jobs, *a, **k))
    path, train, test = store
    cnn = functools.partial(make_classifier, "cnn", epochs=2, threads=1, progress=False)
    tasks = [FitTask("cnn", cnn, StoreRows(path, train), StoreRows(path, rows), tmp_path / "cnn", {"train": 1},
                     {"tag": tag}) for tag, rows in (("test", test), ("train", train))]
    tasks += _tasks(store, tmp_path, {"knn": functools.partial(make_classifier, "knn")})
    preds = raise_failures(run_tasks(tasks, workers=2, progress=False))
    where = tmp_path / "cnn"
    nets = [f"training the {net} net of cnn in {where}" for net in ("cutaneous", "kinesthetic")]
    assert sent == [sorted([*nets, f"training or testing knn in {tmp_path / 'knn'}"]),
                    [f"training or testing cnn in {where}; training or testing cnn in {where}"]]
    model = load_model(where / "cnn.vtm")
    assert model.modality == "fusion" and set(model.history_) == {"cutaneous", "kinesthetic"}
    assert [len(p.proba) for p in preds] == [12, 12, 12] and set(preds[0].modalities) == {"cutaneous", "kinesthetic"}
    seconds = json.loads((where / "cnn.json").read_text())["fit_seconds"]
    assert seconds > 0 and preds[0].fit_seconds == preds[1].fit_seconds == seconds
    sent.clear()
    raise_failures(run_tasks(tasks, workers=2, progress=False))
    assert sent == [[], []]  # everything cached
    other = FitTask("cnn", cnn, StoreRows(path, train), StoreRows(path, test[:4]), where, {"train": 1}, {"tag": "few"})
    sent.clear()
    raise_failures(run_tasks([other], workers=2, progress=False))
    assert sent == [[f"training or testing cnn in {where}"], []]  # a trained model only predicts a new test set
    assert json.loads((where / "cnn.json").read_text())["fit_seconds"] == seconds  # not trained again
    sent.clear()
    raise_failures(run_tasks(_tasks(store, tmp_path / "one", {"cnn": cnn}), workers=1, progress=False))
    assert sent == [[f"training or testing cnn in {tmp_path / 'one' / 'cnn'}"], []]


@two_cores
def test_a_net_that_fails_fails_every_task_of_its_model_and_the_others_finish(store, tmp_path, monkeypatch):
    from fusion.experiments import parallel

    sent = []
    real = parallel.run_jobs
    monkeypatch.setattr(parallel, "run_jobs", lambda jobs, *a, **k: sent.append(sorted(map(str, jobs))) or real(
        jobs, *a, **k))
    path, train, test = store
    broken = functools.partial(make_classifier, "cnn", epochs=2, threads=1, progress=False, frame_size=0)
    tasks = [FitTask("cnn", broken, StoreRows(path, train), StoreRows(path, rows), tmp_path / "cnn", {"train": 1},
                     {"tag": tag}) for tag, rows in (("test", test), ("train", train))]
    tasks += _tasks(store, tmp_path, {"knn": functools.partial(make_classifier, "knn")})
    outcomes = run_tasks(tasks, workers=2, progress=False)
    assert all(isinstance(o, InvalidArgumentError) and "frame_size" in str(o) for o in outcomes[:2])
    assert len(outcomes[2].proba) == 12
    assert not (tmp_path / "cnn" / "cnn.vtm").exists()
    assert sent[1] == []  # its tasks are not tried again


def test_the_joined_models_training_time_is_the_sum_of_its_nets(store, tmp_path, monkeypatch):
    from fusion.experiments import parallel

    path, train, test = store
    cnn = functools.partial(make_classifier, "cnn", epochs=1, threads=1, progress=False)
    task = FitTask("cnn", cnn, StoreRows(path, train), StoreRows(path, test), tmp_path, {"train": 1})
    fitted = [(model, {"cutaneous": 5.0, "kinesthetic": 2.0}[net])
              for model, _ in (parallel._NetFit(task, net).run() for net in ("cutaneous", "kinesthetic"))
              for net in [model.modality]]
    assert parallel._join_nets(task, fitted) is None
    assert json.loads((tmp_path / "cnn.json").read_text())["fit_seconds"] == 7.0


@two_cores
def test_nets_that_do_not_join_fail_every_task_of_their_model(store, tmp_path, monkeypatch):
    from fusion.cnn import CNNClassifier

    def refuse(*models):
        raise InvalidArgumentError("planted join failure")

    monkeypatch.setattr(CNNClassifier, "from_nets", refuse)  # joining happens in this process
    path, train, test = store
    cnn = functools.partial(make_classifier, "cnn", epochs=1, threads=1, progress=False)
    tasks = [FitTask("cnn", cnn, StoreRows(path, train), StoreRows(path, rows), tmp_path / "cnn", {"train": 1},
                     {"tag": tag}) for tag, rows in (("test", test), ("train", train))]
    outcomes = run_tasks(tasks, workers=2, progress=False)
    assert all(isinstance(o, InvalidArgumentError) and "planted join failure" in str(o) for o in outcomes)
    assert not (tmp_path / "cnn" / "cnn.vtm").exists()


@two_cores
def test_fits_run_in_workers_on_their_share_of_the_cores_and_the_kept_workers_serve_later_calls(store, tmp_path):
    log = tmp_path / "fits.log"
    factories = {f"m{i}": functools.partial(FitLog, log=str(log)) for i in range(4)}
    with shared_workers():
        first = raise_failures(run_tasks(_tasks(store, tmp_path / "a", factories), workers=2, progress=False))
        pids_first = {pid for pid, _ in _logged(log)}
        run_tasks(_tasks(store, tmp_path / "b", factories), workers=2, progress=False)
    fits = _logged(log)
    assert len(fits) == 8 and len(first) == 4
    assert os.getpid() not in pids_first and len(pids_first) <= 2
    assert {pid for pid, _ in fits} <= pids_first  # the second call ran on the same workers
    assert {cores for _, cores in fits} == {max(1, usable_cores() // 2)}


@two_cores
@pytest.mark.parametrize("heavy", [False, True])
def test_a_cached_task_is_read_not_run_and_a_shared_model_is_trained_once(store, tmp_path, monkeypatch, heavy):
    """Heavy (in FIT_COST) or light, two test sets of one model train it once; run again, nothing is fitted or
    predicted."""
    if heavy:
        monkeypatch.setitem(FIT_COST, "FitLog", 5.0)
    log = tmp_path / "fits.log"
    path, train, test = store
    factory = functools.partial(FitLog, log=str(log), sleep=1.0)  # long enough for two workers to start both
    # two test sets of one model (same file, same training record): one fit, two predictions
    tasks = [FitTask("m", factory, StoreRows(path, train), StoreRows(path, rows), tmp_path, {"train": 1},
                     {"tag": tag}) for tag, rows in (("test", test), ("train", train))]
    preds = raise_failures(run_tasks(tasks, workers=2, progress=False))
    assert len(_logged(log)) == 1
    assert [len(p.proba) for p in preds] == [12, 12]
    predictions = (tmp_path / "fits.log.predict").read_text().splitlines()
    assert len(predictions) == 2
    again = raise_failures(run_tasks(tasks, workers=2, progress=False))
    assert len(_logged(log)) == 1  # nothing fitted again
    assert (tmp_path / "fits.log.predict").read_text().splitlines() == predictions  # nor predicted
    assert all(np.array_equal(a.proba, b.proba) for a, b in zip(preds, again, strict=True))


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_fit_comes_back_as_its_exception_and_the_others_finish(store, tmp_path, workers):
    log = tmp_path / "fits.log"
    factories = {"ok": functools.partial(FitLog, log=str(log)), "bad": functools.partial(FitLog, fail="raise"),
                 "ok2": functools.partial(FitLog, log=str(log)), "odd": functools.partial(FitLog, fail="unpicklable")}
    factories["exits"] = functools.partial(FitLog, fail="exit")
    outcomes = run_tasks(_tasks(store, tmp_path, factories), workers=workers, progress=False)
    assert isinstance(outcomes[1], DatasetError) and "planted failure" in str(outcomes[1])
    assert isinstance(outcomes[4], RuntimeError) and "exits" in str(outcomes[4]) and "sys.exit(3)" in str(outcomes[4])
    # from a worker, an exception that cannot be pickled comes back as its text
    assert isinstance(outcomes[3], Unpicklable if workers == 1 else RuntimeError)
    assert "planted failure" in str(outcomes[3])
    assert [len(outcomes[i].proba) for i in (0, 2)] == [12, 12]
    with pytest.raises(DatasetError, match="planted failure"):
        raise_failures(outcomes)


@two_cores
def test_a_fit_that_kills_its_worker_is_a_worker_error_and_the_caller_lives(store, tmp_path):
    """os.abort() in a fit (as a native crash would): that task answers WorkerError naming it; the tasks the dead
    worker's pool had not finished run again and succeed."""
    log = tmp_path / "fits.log"
    path, train, test = store
    factories = {f"ok{i}": functools.partial(FitLog, log=str(log)) for i in range(3)}
    # a training set of its own: light fits of one training set share a worker, and their fate
    crash = FitTask("crash", functools.partial(FitLog, fail="abort"), StoreRows(path, test), StoreRows(path, train),
                    tmp_path / "crash", {"train": "crash"})
    outcomes = run_tasks([crash, *_tasks(store, tmp_path, factories)], workers=2, progress=False)
    assert isinstance(outcomes[0], WorkerError)
    assert str(tmp_path / "crash") in str(outcomes[0])
    assert all(len(o.proba) == 12 for o in outcomes[1:])
    assert len(_logged(log)) >= 3


@two_cores
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a process asks to die with its parent on Linux")
@pytest.mark.parametrize("how", [signal.SIGTERM, signal.SIGKILL])
def test_the_workers_die_when_their_caller_is_killed(store, tmp_path, how, child_tmpdir):
    """A caller terminated or killed mid-fit (the forkserver exits with it) leaves no worker training on."""
    path, train, test = store
    log = tmp_path / "fits.log"
    script = textwrap.dedent(f"""
        import functools
        from pathlib import Path

        import numpy as np
        from fusion.experiments.parallel import FitTask, StoreRows, run_tasks
        from tests.fusion.test_parallel import FitLog

        train, test = np.array({train.tolist()}), np.array({test.tolist()})
        tasks = [FitTask(f"m{{i}}", functools.partial(FitLog, log={str(log)!r}, sleep=120),
                         StoreRows({path!r}, rows), StoreRows({path!r}, test), Path({str(tmp_path)!r}) / f"m{{i}}",
                         {{"train": i}})
                 for i, rows in enumerate((train, test))]
        run_tasks(tasks, workers=2, progress=False)
    """)
    root = Path(__file__).resolve().parents[2]
    # its temporary files in a folder of the test's: a killed process cannot remove them
    caller = subprocess.Popen([sys.executable, "-c", script], cwd=root,
                              env={**os.environ, "PYTHONPATH": str(root), "TMPDIR": child_tmpdir})
    started = Path(str(log) + ".start")
    deadline = time.monotonic() + 60
    while (not started.exists() or len(started.read_text().split()) < 2) and time.monotonic() < deadline:
        time.sleep(0.1)
    pids = [int(p) for p in started.read_text().split()]
    try:
        assert len(pids) == 2 and caller.pid not in pids
        caller.send_signal(how)
        caller.wait(timeout=30)
        deadline = time.monotonic() + 15
        while any(map(alive, pids)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(map(alive, pids))
    finally:
        for pid in filter(alive, pids):
            os.kill(pid, signal.SIGKILL)
        caller.kill()


@two_cores
def test_a_factory_that_cannot_travel_runs_in_this_process(store, tmp_path):
    log = tmp_path / "fits.log"
    factories = {"a": lambda: FitLog(log=str(log)), "b": lambda: FitLog(log=str(log))}
    raise_failures(run_tasks(_tasks(store, tmp_path, factories), workers=2, progress=False))
    assert [pid for pid, _ in _logged(log)] == [os.getpid()] * 2


@two_cores
def test_light_fits_of_one_training_set_run_together_and_a_heavy_one_alone(store, tmp_path):
    """Two kNN-like fits of one training set go to one worker (one read, one feature pass), one after the other,
    while two idle workers were there to take them apart; classes in FIT_COST (the CNN) never join them."""
    path, train, test = store
    slow = functools.partial(FitLog, log=str(tmp_path / "ab.log"), sleep=1.0)
    tasks = [FitTask(name, slow, StoreRows(path, train), StoreRows(path, test), tmp_path / name, {"train": 1})
             for name in ("a", "b")]
    other = FitTask("c", functools.partial(FitLog, log=str(tmp_path / "c.log")), StoreRows(path, test),
                    StoreRows(path, train), tmp_path / "c", {"train": 2})
    raise_failures(run_tasks([*tasks, other], workers=2, progress=False))
    (pid_a, _), (pid_b, _) = _logged(tmp_path / "ab.log")
    assert pid_a == pid_b != os.getpid()
    assert tasks[0].train_key() == tasks[1].train_key() != other.train_key()
    cnn = FitTask("cnn", functools.partial(make_classifier, "cnn", threads=1), StoreRows(path, train),
                  StoreRows(path, test), tmp_path / "cnn", {"train": 1})
    assert cnn.train_key() is None


@two_cores
def test_a_classifier_of_the_callers_main_module_runs_in_this_process(store, tmp_path, monkeypatch):
    """A class defined in the caller's script or notebook pickles by reference to ``__main__``, which the workers do
    not load: such fits run here (before, every one failed as a dead worker)."""
    cls = type("MainFitLog", (FitLog,), {"__module__": "__main__"})
    monkeypatch.setattr(sys.modules["__main__"], "MainFitLog", cls, raising=False)
    log = tmp_path / "fits.log"
    path, train, test = store
    tasks = [FitTask(f"m{i}", functools.partial(cls, log=str(log)), StoreRows(path, rows), StoreRows(path, test),
                     tmp_path / f"m{i}", {"train": i}) for i, rows in enumerate((train, test))]
    raise_failures(run_tasks(tasks, workers=2, progress=False))
    assert [pid for pid, _ in _logged(log)] == [os.getpid()] * 2


@pytest.mark.parametrize("bad", [0, -3, 2.5, "2", True, float("nan")])
def test_run_tasks_refuses_workers_it_cannot_count(store, tmp_path, bad):
    from perception.errors import InvalidArgumentError

    with pytest.raises(InvalidArgumentError, match="workers must be a positive integer"):
        run_tasks(_tasks(store, tmp_path, {"a": FitLog}), workers=bad, progress=False)


def test_reproduce_refuses_workers_it_cannot_count(tmp_path):
    from fusion.experiments import reproduce
    from perception.errors import InvalidArgumentError

    for bad in (0, -1, 2.5, True, "2"):
        with pytest.raises(InvalidArgumentError, match="workers"):
            reproduce(tmp_path, tmp_path / "out", workers=bad, progress=False)


def test_reproduce_trains_its_cnns_on_one_thread(tmp_path, monkeypatch):
    """The models of a run must not depend on the machine's cores or the worker count: reproduce asks for CNNs on
    one thread (the weights' sums depend on the thread count; tests/fusion/test_cnn.py)."""
    import importlib

    module = importlib.import_module("fusion.experiments.reproduce")  # the package's name is the function
    asked = {}

    class Stop(Exception):
        pass

    def spy(*args, **kwargs):
        asked.update(kwargs)
        raise Stop

    monkeypatch.setattr(module, "default_classifiers", spy)
    with pytest.raises(Stop):
        module.reproduce(tmp_path, tmp_path / "out", progress=False)
    assert asked["threads"] == 1


def test_the_noise_part_predicts_on_every_core():
    from fusion.cnn import CNNClassifier
    from fusion.experiments.robustness import _on_every_core

    assert _on_every_core(CNNClassifier(threads=1)).threads is None
    model = FitLog(log="x")
    assert _on_every_core(model) is model and model.get_params() == {"log": "x", "fail": "", "sleep": 0.0}


class SlowWriter:
    """A job that holds a semaphore and writes a large file slowly through atomic_path, as a worker saves a model
    (marks when it starts)."""

    def __init__(self, folder: str, tag: str):
        self.folder, self.tag = folder, tag

    def cost(self) -> float:
        return 1.0

    def run(self):
        import multiprocessing

        from perception.atomic import atomic_path

        # a semaphore of its own, as a library's queue or lock holds one: released when the worker stops
        self.lock = multiprocessing.get_context("forkserver").Lock()
        with atomic_path(Path(self.folder, "out", f"{self.tag}.bin")) as tmp, open(tmp, "wb") as f:
            Path(self.folder, f"started-{self.tag}").write_text(str(os.getpid()))
            for _ in range(6000):
                f.write(b"x" * 65536)
                time.sleep(0.01)


@two_cores
def test_an_interrupt_stops_the_workers_and_they_remove_what_they_were_writing(tmp_path):
    """Ctrl-C in the caller: its workers were SIGKILLed where they stood (a file half saved left behind, semaphores
    leaked); now they unwind within the grace period, removing their temporary files and releasing their semaphores,
    and start none of the jobs still queued (a worker that caught its SystemExit took the next job and was killed
    writing it)."""
    script = textwrap.dedent(f"""
        import os, signal, threading, time
        from pathlib import Path
        from fusion.experiments.parallel import run_jobs
        from tests.fusion.test_parallel import SlowWriter

        folder = {str(tmp_path)!r}

        def interrupt():
            while len(list(Path(folder).glob("started-*"))) < 2:
                time.sleep(0.02)
            time.sleep(0.3)
            os.kill(os.getpid(), signal.SIGINT)

        threading.Thread(target=interrupt, daemon=True).start()
        start = time.monotonic()
        try:
            run_jobs([SlowWriter(folder, tag) for tag in "abcd"], workers=2, progress=False)
        except KeyboardInterrupt:
            print("interrupted after", time.monotonic() - start)
        print("started", sorted(p.name for p in Path(folder).glob("started-*")))
    """)
    root = Path(__file__).resolve().parents[2]
    run = subprocess.run([sys.executable, "-c", script], cwd=root, env={**os.environ, "PYTHONPATH": str(root)},
                         capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 0 and "interrupted after" in run.stdout, run.stderr
    assert "leaked" not in run.stderr and "Traceback" not in run.stderr, run.stderr
    pids = [int(p.read_text()) for p in tmp_path.glob("started-*")]
    deadline = time.monotonic() + 5
    while any(map(alive, pids)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(map(alive, pids))
    assert list((tmp_path / "out").iterdir()) == []
    assert "started ['started-a', 'started-b']" in run.stdout, run.stdout
    assert float(run.stdout.split("interrupted after")[1].split()[0]) < 30  # not the 60 s the jobs would take


class Square:
    """A job that returns the square of its number."""

    def __init__(self, n: int):
        self.n = n

    def cost(self) -> float:
        return 1.0

    def run(self) -> int:
        return self.n * self.n


@two_cores
def test_the_progress_bar_says_what_the_jobs_are(capsys):
    """The active part's episodes went by under the fit bar's words ("fit ... model"): the caller names them."""
    assert run_jobs([Square(n) for n in range(3)], workers=2, desc="episodes, fold 1", unit="object") == [0, 1, 4]
    err = capsys.readouterr().err
    assert "episodes, fold 1" in err and "3/3" in err and "object" in err and "fit" not in err, err
    assert run_jobs([Square(2)], workers=2) == [4]
    err = capsys.readouterr().err
    assert "fit" in err and "model" in err, err
