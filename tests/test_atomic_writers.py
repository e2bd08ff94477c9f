"""Nothing lost: every writer, interrupted part-way, leaves the old file intact (byte for
byte) or the new one complete, and no temporary file behind after an exception.

Two ways of interrupting:

- in this process: ``open``/``io.open`` patched so that files opened for writing fail once a given number of
  bytes is written (at the first byte, half-way, one byte short of the end), with ``KeyboardInterrupt`` (Ctrl-C)
  or ``OSError(ENOSPC)`` (a full disk);
- SIGKILL of a forked child (no exception handler or ``finally`` runs): stopped by the same patch at chosen
  byte counts and killed there (the old file must be intact), or writing in a loop and killed at random
  moments, which also covers writes made in C++ (Open3D's PLY / PCD writer) that no Python patch sees (the
  file must be the old or the new one, whole). A killed process cannot clean up: its hidden temporary
  (``.<name>.<random><suffix>``) stays.

Controls: the same interruptions applied to a plain ``open(path, "w")`` writer do tear its file.
"""

from __future__ import annotations

import builtins
import contextlib
import errno
import io
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from perception.atomic import atomic_path, save_figure, write_text

ERRORS = {"ctrl-c": KeyboardInterrupt, "disk-full": lambda: OSError(errno.ENOSPC, "No space left on device")}


# ------------------------------------------------------------------------------------ the interrupter
class Budget:
    """Bytes (text: characters) that writes may make before ``error()`` is raised (or called: it may stop the
    process instead)."""

    def __init__(self, limit: float, error) -> None:
        self.limit, self.error, self.written, self.fired = limit, error, 0, False


class CutFile:
    """A file opened for writing, whose writes stop with the budget's error once the budget is spent."""

    def __init__(self, file, budget: Budget) -> None:
        self._file, self._budget = file, budget

    def write(self, data):
        b = self._budget
        if b.fired and b.error is KeyboardInterrupt:  # Ctrl-C is one event; clean-up code may write again
            return self._file.write(data)
        view = data if isinstance(data, str) else memoryview(data).cast("B")
        if b.written + len(view) > b.limit:
            keep = max(int(b.limit - b.written), 0)
            self._file.write(view[:keep])
            self._file.flush()
            b.written, b.fired = b.written + keep, True
            raise b.error()
        b.written += len(view)
        return self._file.write(data)

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def fileno(self):  # writers that would write to the descriptor (Pillow) must use write() instead
        raise io.UnsupportedOperation("fileno")

    def __getattr__(self, name):
        return getattr(self._file, name)

    def __iter__(self):
        return iter(self._file)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> bool:
        self._file.close()
        return False


@contextlib.contextmanager
def cut_writes(limit: float, error=KeyboardInterrupt):
    """Files opened for writing (any mode with w, a, x or +) fail after ``limit`` bytes in all."""
    budget = Budget(limit, error)
    real_open = builtins.open

    def cut_open(file, mode="r", *args, **kwargs):
        f = real_open(file, mode, *args, **kwargs)
        return CutFile(f, budget) if set(mode) & set("wax+") else f

    from numpy.lib import _datasource  # np.savetxt opens through a reference to io.open taken at import

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(builtins, "open", cut_open)
        mp.setattr(io, "open", cut_open)
        mp.setitem(_datasource._file_openers._file_openers, None, cut_open)
        yield budget


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden ones included), by relative path, with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------------------ writers
def _frames(version: int):
    from perception.camera.frame import Intrinsics, RGBDFrame

    k = Intrinsics(5.0, 5.0, 1.5, 1.5, 4, 4)
    rng = np.random.default_rng(version)
    return [RGBDFrame(rng.integers(0, 255, (4, 4, 3), dtype=np.uint8), np.full((4, 4), 500.0 + 10 * version + i), k)
            for i in range(2 + version)]


@pytest.fixture(scope="module")
def models():
    """Two fitted kNN models (different training data), as ``save_model`` writes them."""
    from fusion.classifiers import make_classifier
    from tests.fusion._synthetic import circle_batch

    out = []
    for version in (0, 1):
        model = make_classifier("knn", random_state=0)
        model.fit(circle_batch([10, 11, 20, 21, 30 + version, 31], labels=[0, 0, 1, 1, 2, 2], seed=version))
        out.append(model)
    return out


class FakeDataset:
    """What ``visuotactile train`` reads from a store, from a synthetic batch (no store generation)."""

    def __init__(self, version: int) -> None:
        from tests.fusion._synthetic import circle_batch

        self.batch = circle_batch([10, 11, 20, 21, 30 + version, 31], labels=[0, 0, 1, 1, 2, 2], seed=version)
        self.attrs = {"store_id": f"fake-{version}"}

    def indices(self, strategy):
        return np.arange(len(self.batch))

    def load(self, index):
        return self.batch


def _cli_train(path: Path, version: int, set_inputs) -> None:
    from fusion.cli import main

    set_inputs(version)
    with contextlib.redirect_stdout(io.StringIO()):
        code = main(["train", "--store", "fake", "--model", "knn", "--split", "none", "--out", str(path), "--json"])
    if code == 130:  # the command line's answer to Ctrl-C: "interrupted; finished work is kept"
        raise KeyboardInterrupt
    assert code == 0


def _store_settings() -> dict:
    """A store's settings as generate writes them (read_attrs checks every field)."""
    return {"objects": [{"name": "box/0", "label": "box", "catalogue": ["box", 0]}], "class_names": ["box"],
            "strategies": ["blind"], "contours_per_object": 2, "probes": 3, "sensor": {"rows": 4, "cols": 4},
            "seed": 0, "encoding": {"dtype": "uint16", "scale": 1e-4, "max_error": 5e-5}}


def writers(models, set_inputs) -> dict:
    """name -> (target relative to the output folder, write(path, version))."""
    from fusion.evaluate import plot_confusion
    from fusion.experiments.models import Predictions
    from fusion.experiments.touch import save_batch
    from perception.camera.recording import write_recording
    from perception.reconstruct.pointfiles import write_points
    from tactile.dataset.store import write_record
    from tests.fusion._synthetic import circle_batch

    def figure(path, v):
        from matplotlib.figure import Figure

        fig = Figure(figsize=(2, 2))
        fig.add_subplot().plot([0, 1, 2], [v, 1 - v, v])
        save_figure(fig, path, dpi=50)

    def cloud(path, v):
        rng = np.random.default_rng(v)
        write_points(path, rng.normal(size=(40, 3)), rng.normal(size=(40, 3)))

    def predictions(path, v):
        proba = np.full((3, 2), 0.5) + [[0.1 * v, -0.1 * v]]
        Predictions(proba, np.array(["a", "b", "a"]), np.arange(3), ["a", "b"], ["o0", "o1", "o2"]).save(path, {"v": v})

    return {
        "report (write_text)": ("report.md", lambda p, v: write_text(p, f"# report {v}\n" + "row | value\n" * 500 * (v + 1))),
        "figure (save_figure)": ("figure.png", figure),
        "confusion figure (plot_confusion)": ("confusion.png",
                                              lambda p, v: plot_confusion(np.array([[3, v], [1, 4]]), ["a", "b"], p)),
        "points .xyz (write_points)": ("cloud.xyz", cloud),
        "points .npy (write_points)": ("cloud.npy", cloud),
        "points .npz (write_points)": ("cloud.npz", cloud),
        "model (save_model)": ("model.vtm", lambda p, v: models[v].save(p)),
        "CLI train --out": ("cli.vtm", lambda p, v: _cli_train(p, v, set_inputs)),
        "dataset record (write_record)": ("store/records/00000.json",
                                          lambda p, v: write_record(p.parents[1], 0, {"index": 0, "version": v})),
        "predictions cache (Predictions.save)": ("pred.npz", predictions),
        "batch cache (save_batch)": ("batch.npz", lambda p, v: save_batch(circle_batch([10, 20 + v]), p, {"v": v})),
        "camera recording (write_recording)": ("rec/index.json", lambda p, v: write_recording(p.parent, _frames(v))),
    }


@pytest.fixture
def set_inputs(monkeypatch, models):
    """Make ``visuotactile train`` read a synthetic batch and fit (instantly) to ``models[version]``: what
    is tested is how it writes ``--out``."""
    import copy

    import fusion.classifiers
    import tactile.dataset

    def set_version(version: int) -> None:
        monkeypatch.setattr(tactile.dataset, "open_dataset", lambda path: FakeDataset(version))
        monkeypatch.setattr(fusion.classifiers, "make_classifier", lambda name, **kw: copy.deepcopy(models[version]))
        monkeypatch.setattr(type(models[version]), "fit", lambda self, batch: self)

    return set_version


@pytest.fixture
def all_writers(models, set_inputs):
    return writers(models, set_inputs)


NAMES = [
    "report (write_text)", "figure (save_figure)", "confusion figure (plot_confusion)", "points .xyz (write_points)",
    "points .npy (write_points)", "points .npz (write_points)", "model (save_model)", "CLI train --out",
    "dataset record (write_record)", "predictions cache (Predictions.save)", "batch cache (save_batch)",
    "camera recording (write_recording)",
]


# ------------------------------------------------------------------------------------ in-process cuts
_SIZES: dict[str, int] = {}


@pytest.mark.parametrize(("where", "error"), [("first byte", "ctrl-c"), ("half-way", "disk-full"),
                                              ("last byte", "ctrl-c")])
@pytest.mark.parametrize("name", NAMES)
def test_interrupted_write_keeps_the_old_file_and_leaves_nothing(tmp_path, all_writers, name, where, error):
    target_name, write = all_writers[name]
    if name not in _SIZES:  # how many bytes a complete write makes (measured once, on a scratch copy)
        scratch = tmp_path / "scratch"
        write(scratch / target_name, 0)
        with cut_writes(float("inf")) as total:
            write(scratch / target_name, 1)
        _SIZES[name] = total.written
    n = _SIZES[name]
    assert n > 2
    folder = tmp_path / "out"
    target = folder / target_name
    write(target, 0)
    before = snapshot(folder)
    cut = {"first byte": 1, "half-way": n // 2, "last byte": n - 1}[where]
    with pytest.raises((KeyboardInterrupt, OSError)), cut_writes(cut, ERRORS[error]) as budget:
        write(target, 1)
    assert budget.fired and 0 < budget.written < n  # it stopped part-way through the new content
    assert snapshot(folder) == before  # the old file(s) byte for byte, and no temporary left


def test_interrupted_store_creation_leaves_nothing(tmp_path):
    from tactile.dataset.store import create_store

    with pytest.raises(OSError), cut_writes(200, ERRORS["disk-full"]) as budget:
        create_store(tmp_path / "small.zarr", _store_settings(), {"command": "test"})
    assert budget.fired
    assert list(tmp_path.iterdir()) == []


def test_store_creation_is_complete_or_absent(tmp_path):
    from tactile.dataset.store import create_store, read_attrs

    create_store(tmp_path / "small.zarr", _store_settings(), {"command": "test"})
    assert read_attrs(tmp_path / "small.zarr")["settings"] == _store_settings()
    with pytest.raises(OSError), cut_writes(200, ERRORS["disk-full"]):
        create_store(tmp_path / "other.zarr", _store_settings(), {"command": "test"})
    assert not (tmp_path / "other.zarr").exists()  # no half-made store under the real name


# -------------------------------------------------------------------------------------- SIGKILL
def _fork(body) -> tuple[int, int]:
    """Run ``body(write_fd)`` in a forked child (it never returns into pytest); returns (pid, read_fd)."""
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            os.close(read_fd)
            body(write_fd)
        finally:
            os._exit(1)
    os.close(write_fd)
    return pid, read_fd


def _kill(pid: int) -> None:
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)


def _temporaries(target: Path) -> list[Path]:
    """What a killed atomic writer leaves: hidden files named after the target (removed here)."""
    found = [p for p in target.parent.iterdir() if p.name.startswith(f".{target.name}.")]
    for p in found:
        p.unlink()
    return found


def _kill_at_bytes(target: Path, write, cuts) -> list[bytes | None]:
    """For each byte count in ``cuts``: a child writes version 1 to ``target`` and stops once that many bytes
    are written; it is SIGKILLed there (no exception handler, no ``finally`` runs). Returns the target's bytes
    after each kill."""

    def pause(fd):
        def stop():
            os.write(fd, b"p")
            time.sleep(600)  # the parent kills us here

        return stop

    seen = []
    for cut in cuts:
        def body(fd, cut=cut):
            with cut_writes(int(cut), pause(fd)):
                write(target, 1)

        pid, read_fd = _fork(body)
        paused = os.read(read_fd, 1)
        os.close(read_fd)
        _kill(pid)
        assert paused == b"p", f"the writer finished before byte {cut}"
        _temporaries(target)
        seen.append(target.read_bytes() if target.exists() else None)
    return seen


def _kill_at_random(target: Path, write, kills: int, seed: int = 0, max_kills: int = 60) -> tuple[list[bytes | None], int]:
    """A child writes version 1, 0, 1, ... to ``target`` in a loop; SIGKILL it at random moments (writes made
    in C++ included), ``kills`` times and then on until one kill has landed while a write was under way (at
    most ``max_kills``). Returns the target's bytes after each kill and how many kills left a temporary."""
    rng = np.random.default_rng(seed)
    start = time.perf_counter()
    write(target, 1)  # the kill moments span a few writes, however fast this machine writes
    one_write_s = time.perf_counter() - start
    seen, mid_write = [], 0
    while len(seen) < kills or (mid_write == 0 and len(seen) < max_kills):
        def body(fd):
            os.write(fd, b"x")
            for i in range(1 << 30):
                write(target, i % 2)

        pid, read_fd = _fork(body)
        os.read(read_fd, 1)
        os.close(read_fd)
        time.sleep(float(rng.uniform(0.0, 3 * one_write_s)))
        _kill(pid)
        mid_write += bool(_temporaries(target))
        seen.append(target.read_bytes() if target.exists() else None)
    return seen, mid_write


def _cuts(write, target_name: str, tmp_path: Path, k: int = 4) -> list[int]:
    """``k`` byte counts spread through a complete write of version 1 (first byte to last)."""
    with cut_writes(float("inf")) as total:
        write(tmp_path / "measure" / target_name, 1)
    return sorted({1, total.written - 1, *np.random.default_rng(0).integers(1, total.written, k - 2).tolist()})


@pytest.mark.parametrize("name", ["report (write_text)", "model (save_model)", "dataset record (write_record)",
                                  "points .npz (write_points)", "CLI train --out", "figure (save_figure)"])
def test_sigkill_mid_write_leaves_the_old_file(tmp_path, all_writers, name):
    target_name, write = all_writers[name]
    target = tmp_path / "out" / target_name
    write(target, 0)
    old = target.read_bytes()
    cuts = _cuts(write, target_name, tmp_path)
    assert _kill_at_bytes(target, write, cuts) == [old] * len(cuts)


def test_sigkill_mid_recording_overwrite_leaves_the_old_recording(tmp_path, all_writers):
    from perception.camera.recording import read_recording

    def content(frames):
        return [(f.color.tobytes(), np.asarray(f.depth_mm, np.float64).tobytes()) for f in frames]

    target_name, write = all_writers["camera recording (write_recording)"]
    target = tmp_path / "out" / target_name
    write(target, 0)
    cuts = _cuts(write, target_name, tmp_path)
    for cut in cuts:
        _kill_at_bytes(target, write, [cut])
        assert content(read_recording(target.parent)) == content(_frames(0))


def _big_report(path: Path, v: int) -> None:
    write_text(path, f"version {v}\n" * (200000 + 50000 * v))


def _big_cloud(path: Path, v: int) -> None:
    from perception.reconstruct.pointfiles import write_points

    write_points(path, np.random.default_rng(v).normal(size=(20000 + 5000 * v, 3)))


@pytest.mark.parametrize(("target_name", "write"), [("report.md", _big_report), ("cloud.ply", _big_cloud),
                                                    ("cloud.pcd", _big_cloud)], ids=["text", "ply-open3d", "pcd-open3d"])
def test_sigkill_at_random_moments_leaves_the_old_or_the_new_file(tmp_path, target_name, write):
    # Open3D writes PLY and PCD in C++, where no Python patch can stop it part-way: random kills instead.
    complete = []
    for v in (0, 1):
        write(tmp_path / f"v{v}" / target_name, v)
        complete.append((tmp_path / f"v{v}" / target_name).read_bytes())
    assert complete[0] != complete[1]
    target = tmp_path / "out" / target_name
    write(target, 0)
    seen, mid_write = _kill_at_random(target, write, kills=6)
    assert all(s in complete for s in seen), [None if s is None else len(s) for s in seen]
    assert mid_write >= 1  # some kills did land while a write was under way


# ------------------------------------------------------------------------------------------ controls
def _plain_write(path: Path, v: int) -> None:
    with open(path, "w") as f:
        f.writelines(f"version {v}\n" * 2000 for _ in range(64))


def test_control_a_plain_writer_is_torn_by_the_same_interruptions(tmp_path):
    path = tmp_path / "plain.txt"
    _plain_write(path, 0)
    old = path.read_bytes()
    with pytest.raises(KeyboardInterrupt), cut_writes(1000):
        _plain_write(path, 1)
    assert len(path.read_bytes()) == 1000  # torn: neither the old file nor the new one
    _plain_write(path, 0)
    assert _kill_at_bytes(path, _plain_write, [5000]) != [old]


def test_control_a_plain_writer_is_torn_by_random_kills(tmp_path):
    complete = []
    for v in (0, 1):
        _plain_write(tmp_path / f"v{v}.txt", v)
        complete.append((tmp_path / f"v{v}.txt").read_bytes())
    path = tmp_path / "plain.txt"
    _plain_write(path, 0)
    seen, _ = _kill_at_random(path, _plain_write, kills=6, max_kills=6)  # leaves no temporaries to wait for
    assert any(s not in complete for s in seen)


# ------------------------------------------------------------------------------------------ details
def test_written_files_get_the_usual_permissions(tmp_path):
    # mkstemp made every atomically written file 0600 (reports and figures unreadable to others).
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    write_text(tmp_path / "report.md", "x")
    assert (tmp_path / "report.md").stat().st_mode == plain.stat().st_mode
    os.chmod(tmp_path / "report.md", 0o640)
    write_text(tmp_path / "report.md", "y")  # a replaced file keeps its mode, as open(..., "w") keeps it
    assert (tmp_path / "report.md").stat().st_mode & 0o777 == 0o640


def test_temporary_names_keep_the_suffix_and_are_hidden(tmp_path):
    # Writers infer the format from the suffix (matplotlib, Open3D); hidden: ls and shell globs skip them.
    with atomic_path(tmp_path / "cloud.ply") as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".ply" and tmp.name.startswith(".cloud.ply.")
        tmp.write_bytes(b"new")
    assert [p.name for p in tmp_path.iterdir()] == ["cloud.ply"]
    assert (tmp_path / "cloud.ply").read_bytes() == b"new"
