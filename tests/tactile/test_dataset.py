"""Tactile dataset stores: frames equal explore_object's, bytes independent of workers, resume after
SIGKILL, failures recorded, settings checked, splits and the PyTorch view."""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import faulthandler
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

import perception.saliency as attention
from perception.errors import DatasetError, InvalidArgumentError
from perception.geometry import CENTERINGS
from perception.shapes import make_object
from tactile.dataset import ObjectSpec, contour_seed, frame_encoding, generate, open_dataset, pair_order_seed
from tactile.dataset.store import decode_frames, encode_frames
from tactile.sampling import explore_object
from tactile.sensor import FSRSensor
from tactile.touching import Toucher

ROOT = Path(__file__).resolve().parents[2]
#: Small and fast: 16 x 16 taxels, 10 probes, blind contours on catalogue objects.
SMALL = FSRSensor(rows=16, cols=16)
#: Two classes of three objects: enough for object splits and k-fold.
BLIND_OBJECTS = [("box", 0), ("box", 1), ("box", 2), ("can", 0), ("can", 1), ("can", 2)]
BLIND = {"strategies": ("blind",), "contours_per_object": 12, "sensor": SMALL, "probes": 10, "seed": 7, "progress": False}


# ------------------------------------------------------------------------------------ helpers
def store_files(path: Path) -> dict[str, object]:
    """Every file of a store: bytes, except what legitimately differs between runs (timings in the
    records, creation time and command in the root metadata)."""
    files = {}
    for file in sorted(p for p in path.rglob("*") if p.is_file()):
        rel = file.relative_to(path).as_posix()
        if rel.startswith("records/"):
            record = json.loads(file.read_text())
            for timing in ("seconds", "write_seconds"):
                record.pop(timing, None)
            files[rel] = record
        elif rel == "zarr.json":
            meta = json.loads(file.read_text())
            for key in ("created", "command", "store_id"):
                meta["attributes"]["visuotactile_dataset"].pop(key)
            files[rel] = meta
        else:
            files[rel] = file.read_bytes()
    return files


def expected_row(model, strategy, seed, k, sensor, probes, sal=None):
    """Row k of ``strategy`` in a store of ``seed``, as the module docstring of tactile.dataset says: explore_object
    with the row's contour seed; a guided strategy along position k of the object's pair order."""
    planes = None
    if strategy != "blind":
        order = Toucher(model, strategy, probes=probes, saliency=sal).pair_order(pair_order_seed(seed, model.name,
                                                                                                 strategy))
        planes = [order[k]]
    return explore_object(model, strategy, 1, sensor, probes, seed=contour_seed(seed, model.name, strategy, k),
                          saliency=sal, planes=planes)[0]


def refuse_saliency(*args, **kwargs):
    raise AssertionError("saliency was computed")


def mug_without_saliency():
    """Loader run in the worker: from here on, computing saliency in this process fails."""
    attention.saliency = refuse_saliency
    return make_object("mug", 0)


def mug_counting_saliency(log_file: str):
    """Loader run in the worker: every saliency computation appends its method to ``log_file``."""
    original = attention.saliency

    def counting(model, method="multiview", **kwargs):
        with open(log_file, "a") as f:
            f.write(method + "\n")
        return original(model, method, **kwargs)

    attention.saliency = counting
    return make_object("mug", 0)


def hanging_loader():
    """Loader run in the worker: never returns in reasonable time, as pymeshlab can on tiny meshes."""
    time.sleep(600)


def aborting_loader():
    """Loader run in the worker: a native abort, as pymeshlab does on some meshes."""
    os.abort()


def slow_box(seed: int):
    """Loader run in the worker: a second's work, then a box."""
    time.sleep(1.0)
    return make_object("box", seed)


def raising_loader():
    """Loader run in the worker: an ordinary failure."""
    raise ValueError("no mesh here")


def loader_closing_its_descriptors():
    """Loader run in the worker: closes every descriptor (its pipe to generate among them), then runs on."""
    for fd in range(3, 256):
        with contextlib.suppress(OSError):
            os.close(fd)
    time.sleep(600)


def box_whose_worker_dies_when_idle():
    """Loader run in the worker: a box, but the worker exits when it next waits for an object."""
    import multiprocessing.connection

    multiprocessing.connection.Connection.recv = lambda self: os._exit(5)
    return make_object("box", 0)


def box_noting_its_process(log_file: str, seed: int):
    """Loader run in the worker: appends the worker's process id to ``log_file``, then gives a box."""
    with open(log_file, "a") as f:
        f.write(f"{seed} {os.getpid()}\n")
    return make_object("box", seed)


# ----------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def real_stderr(request):
    """The terminal's stderr, which pytest's output capture does not swallow."""
    capture = request.config.pluginmanager.getplugin("capturemanager")  # None under -p no:capture
    with capture.global_and_fixture_disabled() if capture else contextlib.nullcontext():
        stream = os.fdopen(os.dup(2), "w")
    yield stream
    stream.close()


@pytest.fixture(autouse=True)
def deadline(request, real_stderr):
    """A test of this file still running after 4 minutes (each takes under one) has hung, e.g. on a worker that never
    reports: print every thread's stack and end the run, rather than let CI wait for its own limit."""
    real_stderr.write("")  # opened before the clock starts
    faulthandler.dump_traceback_later(240, exit=True, file=real_stderr)
    yield
    faulthandler.cancel_dump_traceback_later()


@pytest.fixture(scope="module")
def blind_store(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("blind") / "store"
    report = generate(BLIND_OBJECTS, out, workers=1, **BLIND)
    assert report.completed == len(BLIND_OBJECTS) and not report.failed
    return out


@pytest.fixture(scope="module")
def guided_store(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("guided") / "store"
    generate([("mug", 0), ("box", 1)], out, strategies=("guided", "blind"), contours_per_object=3,
             sensor=FSRSensor(), probes=25, seed=3, workers=2, progress=False)
    return out


# ----------------------------------------------------------------------------- known answers
def test_frames_read_back_equal_explore_object(guided_store):
    ds = open_dataset(guided_store)
    assert ds.object_names == ("mug/0", "box/1") and ds.class_names == ("box", "mug")
    assert ds.strategies == ("guided", "blind") and len(ds) == 2 * 2 * 3
    batch = ds.load()
    for name, obj in (("mug", 0), ("box", 1)):
        model = make_object(name, obj)
        sal = attention.saliency(model, "multiview")
        for strategy in ds.strategies:
            rows = np.flatnonzero((ds.object_ids == ds.object_names.index(f"{name}/{obj}"))
                                  & (ds.sequence_strategies == strategy))
            for k, i in enumerate(rows):
                seed = contour_seed(3, f"{name}/{obj}", strategy, k)
                assert ds.contour_seeds[i] == seed
                expected = expected_row(model, strategy, 3, k, FSRSensor(), 25, sal if strategy == "guided" else None)
                assert ds.noise_seeds[i] == expected.seed
                assert np.abs(batch.frames[i] - expected.frames).max() <= ds.max_frame_error * (1 + 1e-6)
                for attr in ("normals", "positions", "tangents", "pad_sides_mm"):
                    np.testing.assert_array_equal(getattr(batch, attr)[i], getattr(expected, attr).astype(np.float32))
                np.testing.assert_array_equal(batch.plane_normals[i], expected.plane.normal)
                assert batch.labels[i] == ds.class_names.index(name)
    # The guided contours' planes pass through the centre and two of the recorded interest points.
    points = ds.interest_points("mug/0")["guided"]
    assert points.shape == (10, 3) and set(ds.interest_points("mug/0")) == {"guided"}
    i = ds.indices("guided")[0]
    on_plane = np.abs((points - batch.plane_points[i]) @ batch.plane_normals[i]) < 1e-6
    assert on_plane.sum() >= 2


def test_noisy_contact_frames_are_stored_losslessly(tmp_path):
    # Contact mode with noise: each contour is pressed alone with its noise seed; ADC levels are exact codes.
    sensor = FSRSensor(rows=8, cols=8, mode="contact", noise_std=0.05, adc_bits=10)
    generate([("box", 5)], tmp_path / "s", strategies="blind", contours_per_object=4, sensor=sensor, probes=6,
             seed=1, workers=1, progress=False)
    ds = open_dataset(tmp_path / "s")
    assert ds.max_frame_error == 0.0
    model = make_object("box", 5)
    for k in range(4):
        expected = explore_object(model, "blind", 1, sensor, 6, seed=contour_seed(1, "box/5", "blind", k))[0]
        np.testing.assert_array_equal(ds.frames([k])[0], expected.frames)


def test_frame_encoding_error_bound():
    enc = frame_encoding(FSRSensor().spec())
    assert enc["scale"] == 10.0 / 65535 and enc["max_error"] == 5.0 / 65535
    values = np.random.default_rng(0).uniform(0, 10, (1000, 4, 4)).astype(np.float32)
    values[0, 0, :2] = [0.0, 10.0]
    decoded = decode_frames(encode_frames(values, enc, "t"), enc)
    assert decoded.dtype == np.float32 and decoded[0, 0, 1] == 10.0 and decoded[0, 0, 0] == 0.0
    assert np.abs(decoded - values).max() <= enc["max_error"] * (1 + 1e-6)
    with pytest.raises(DatasetError, match="NaN"):
        encode_frames(np.array([np.nan], np.float32), enc, "obj")
    with pytest.raises(DatasetError, match="outside"):
        encode_frames(np.array([-1.0], np.float32), enc, "obj")


# ------------------------------------------------------------------------ determinism, resume
def test_workers_do_not_change_the_bytes(blind_store, tmp_path):
    generate(BLIND_OBJECTS, tmp_path / "w2", workers=2, **BLIND)
    assert store_files(tmp_path / "w2") == store_files(blind_store)


def test_sigkill_part_way_then_resume_equals_an_uninterrupted_run(blind_store, tmp_path, child_tmpdir):
    out = tmp_path / "killed"
    script = (
        "from tactile.dataset import generate; from tactile.sensor import FSRSensor; "
        f"generate({BLIND_OBJECTS!r}, {str(out)!r}, strategies=('blind',), contours_per_object=12, "
        "sensor=FSRSensor(rows=16, cols=16), probes=10, seed=7, workers=1, progress=False)"
    )
    # A script without a main guard: workers must not run it again (forkserver would re-import __main__).
    (tmp_path / "run.py").write_text(script.replace("; ", "\n"))
    # its temporary files in a folder of the test's: a killed process cannot remove them
    proc = subprocess.Popen([sys.executable, str(tmp_path / "run.py")], cwd=ROOT,
                            env={**os.environ, "TMPDIR": child_tmpdir})
    deadline = time.monotonic() + 120
    while not list((out / "records").glob("*.json")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    time.sleep(0.5)  # the in-flight worker dies with its forkserver
    done = len(list((out / "records").glob("*.json")))
    assert 1 <= done < len(BLIND_OBJECTS), "the run finished before it could be killed"
    partial = open_dataset(out)
    assert len(partial.object_names) == done and len(partial) == done * 12
    assert len(partial.incomplete) == len(BLIND_OBJECTS) - done
    report = generate(BLIND_OBJECTS, out, workers=2, **BLIND)
    assert report.skipped == done and report.completed == len(BLIND_OBJECTS) - done
    assert store_files(out) == store_files(blind_store)


def test_rerun_skips_complete_objects(blind_store):
    before = {p: p.stat().st_mtime_ns for p in blind_store.rglob("*") if p.is_file()}
    report = generate(BLIND_OBJECTS, blind_store, workers=1, **BLIND)
    assert (report.skipped, report.completed, report.sequences) == (len(BLIND_OBJECTS), 0, 0)
    assert {p: p.stat().st_mtime_ns for p in blind_store.rglob("*") if p.is_file()} == before


@pytest.mark.parametrize(
    "change, message",
    [
        ({"contours_per_object": 13}, "contours_per_object: 12 in the store, 13 asked"),
        ({"sensor": FSRSensor(rows=16, cols=16, range_mm=8.0)}, "range_mm 10.0 -> 8.0"),
        ({"seed": 8}, "seed: 7 in the store, 8 asked"),
        ({"strategies": ("blind", "guided")}, "strategies"),
    ],
)
def test_other_settings_on_an_existing_store_are_refused(blind_store, change, message):
    with pytest.raises(DatasetError, match="other settings") as info:
        generate(BLIND_OBJECTS, blind_store, workers=1, **{**BLIND, **change})
    assert message in str(info.value) and str(blind_store) in str(info.value)


def test_a_guided_store_drawn_with_repeats_is_not_resumed(tmp_path, blind_store):
    """Stores of guided contours record how their pairs were drawn; one made before pairs were drawn without
    repeats (no such setting) is refused, naming the setting, rather than resumed with rows of another kind."""
    from tactile.dataset.store import ATTRS_KEY

    assert "guided_pairs" not in json.loads((blind_store / "zarr.json").read_text())["attributes"][ATTRS_KEY][
        "settings"]  # blind stores keep their identity
    out = tmp_path / "s"
    args = {"strategies": "guided", "contours_per_object": 2, "sensor": FSRSensor(rows=4, cols=4), "probes": 4,
            "workers": 1, "progress": False}
    generate([("box", 1)], out, **args)
    meta = json.loads((out / "zarr.json").read_text())
    assert meta["attributes"][ATTRS_KEY]["settings"]["guided_pairs"] == "without repeats"
    del meta["attributes"][ATTRS_KEY]["settings"]["guided_pairs"]
    (out / "zarr.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="guided_pairs: None in the store, 'without repeats' asked"):
        generate([("box", 1)], out, **args)


def test_other_objects_on_an_existing_store_are_refused(blind_store):
    with pytest.raises(DatasetError, match=r"objects\[4\]"):
        generate([*BLIND_OBJECTS[:4], ("ring", 5), BLIND_OBJECTS[5]], blind_store, workers=1, **BLIND)


# --------------------------------------------------------------------------------- failures
def test_corrupt_and_aborting_meshes_are_recorded_and_the_rest_complete(tmp_path):
    corrupt = tmp_path / "corrupt.off"
    corrupt.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n")  # promises 3 vertices, has 2
    objects = [("mug", 0), ObjectSpec("bad/corrupt", "bad", path=str(corrupt)),
               ObjectSpec("bad/abort", "bad", loader=aborting_loader), ("box", 1)]
    report = generate(objects, tmp_path / "s", strategies="blind", contours_per_object=2, sensor=SMALL, probes=5,
                      workers=2, progress=False)
    assert report.completed == 2 and dict(report.failed).keys() == {"bad/corrupt", "bad/abort"}
    ds = open_dataset(tmp_path / "s")
    assert ds.object_names == ("mug/0", "box/1") and len(ds) == 4
    assert ds.class_names == ("bad", "box", "mug")  # labels keep their meaning when failed objects are redone
    assert "SIGABRT" in ds.failed["bad/abort"]
    assert "MeshLoadError" in ds.failed["bad/corrupt"] and "corrupt.off" in ds.failed["bad/corrupt"]


def test_a_worker_explores_objects_in_turn_and_a_new_one_follows_a_crash_or_a_hang(tmp_path):
    log_file = str(tmp_path / "pids.txt")

    def box(seed):
        return ObjectSpec(f"box/{seed}", "box", loader=functools.partial(box_noting_its_process, log_file, seed))

    objects = [box(0), box(1), ObjectSpec("bad/abort", "bad", loader=aborting_loader), box(2),
               ObjectSpec("bad/hang", "bad", loader=hanging_loader), box(3), box(4)]
    report = generate(objects, tmp_path / "s", strategies="blind", contours_per_object=2, sensor=SMALL, probes=5,
                      workers=1, object_timeout_s=3, progress=False)
    assert report.completed == 5
    assert dict(report.failed) == {"bad/abort": dict(report.failed)["bad/abort"], "bad/hang": "timed out after 3 s"}
    assert "SIGABRT" in dict(report.failed)["bad/abort"]
    pid = dict(line.split() for line in Path(log_file).read_text().splitlines())
    assert pid["0"] == pid["1"]  # one process, one object after the other
    assert pid["2"] != pid["1"]  # the abort ended the first worker
    assert pid["3"] != pid["2"] and pid["3"] == pid["4"]  # the hung one was stopped; its successor goes on
    assert open_dataset(tmp_path / "s").object_names == ("box/0", "box/1", "box/2", "box/3", "box/4")


def test_a_loader_from_the_main_script_fails_its_object_with_the_remedy(tmp_path):
    """Workers cannot unpickle what the main script defines: that object fails, named, with what to do instead;
    a catalogue object after it still completes."""
    script = tmp_path / "main_loader.py"
    script.write_text(textwrap.dedent(f"""
        from perception.shapes import make_object
        from tactile.dataset import ObjectSpec, generate
        from tactile.sensor import FSRSensor

        def box():
            return make_object("box", 0)

        if __name__ == "__main__":
            report = generate([ObjectSpec("box/main", "box", loader=box), ("can", 1)], {str(tmp_path / "s")!r},
                              strategies=("blind",), contours_per_object=2, sensor=FSRSensor(rows=8, cols=8),
                              probes=5, workers=1, progress=False)
            print(report.completed, report.failed[0][0])
            print(report.failed[0][1])
    """))
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, check=False, timeout=120)
    assert run.returncode == 0, run.stderr
    first, reason = run.stdout.splitlines()
    assert first == "1 box/main"
    assert "exited with code 1" in reason and "define it in an importable module" in reason


def test_the_timeout_counts_from_each_objects_start(tmp_path):
    objects = [ObjectSpec(f"box/{i}", "box", loader=functools.partial(slow_box, i)) for i in range(4)]
    report = generate(objects, tmp_path / "s", strategies="blind", contours_per_object=2, sensor=SMALL, probes=5,
                      workers=1, object_timeout_s=3, progress=False)
    assert report.failed == [] and report.completed == 4  # one worker, 4 s of loading in all, 1 s per object


def test_progress_counts_every_sequence(tmp_path, monkeypatch):
    updates = []

    class Bar:
        def update(self, n):
            updates.append(n)

        def set_postfix_str(self, text):
            pass

        def close(self):
            pass

    monkeypatch.setattr(sys.modules["tactile.dataset.generate"], "progress_bar", lambda **kwargs: Bar())
    generate([("box", 0), ("can", 1), ("box", 2)], tmp_path / "s", strategies="blind", contours_per_object=2,
             sensor=SMALL, probes=5, workers=2, progress=True)
    assert sum(updates) == 3 * 2


def test_a_worker_that_closes_its_pipe_and_runs_on_is_stopped(tmp_path):
    start = time.monotonic()
    objects = [("box", 0), ObjectSpec("bad/closes", "bad", loader=loader_closing_its_descriptors), ("box", 1)]
    report = generate(objects, tmp_path / "s", strategies="blind", contours_per_object=2, sensor=SMALL, probes=5,
                      workers=1, object_timeout_s=30, progress=False)
    assert time.monotonic() - start < 25  # stopped when its pipe closed, not at the timeout
    assert report.completed == 2 and [name for name, _ in report.failed] == ["bad/closes"]


def test_a_worker_dying_while_idle_costs_no_object(tmp_path, monkeypatch):
    """The worker reports its object, then dies while generate is busy (here: finished() slowed down): the next
    object goes to a new worker, not to the dead one's pipe."""
    module = sys.modules["tactile.dataset.generate"]
    run_local = module._run_local

    def slowly(store, specs, settings, sensor, todo, n_workers, finished, *rest):
        def finished_slowly(*args):
            finished(*args)
            time.sleep(0.5)

        return run_local(store, specs, settings, sensor, todo, n_workers, finished_slowly, *rest)

    monkeypatch.setattr(module, "_run_local", slowly)
    objects = [ObjectSpec("box/dies", "box", loader=box_whose_worker_dies_when_idle), ("box", 1), ("can", 2)]
    report = generate(objects, tmp_path / "s", strategies="blind", contours_per_object=2, sensor=SMALL, probes=5,
                      workers=1, object_timeout_s=30, progress=False)
    assert report.completed == 3 and report.failed == []


def test_strict_tells_its_idle_worker_to_exit(tmp_path):
    script = textwrap.dedent(f"""
        from perception.errors import DatasetError
        from tactile.dataset import ObjectSpec, generate
        from tactile.sensor import FSRSensor
        from tests.tactile.test_dataset import raising_loader

        try:
            generate([("box", 0), ObjectSpec("bad/raise", "bad", loader=raising_loader), ("box", 1)],
                     {str(tmp_path / "s")!r}, strategies=("blind",), contours_per_object=2,
                     sensor=FSRSensor(rows=8, cols=8), probes=5, workers=1, strict=True, progress=False)
        except DatasetError:
            print("strict")
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, check=False)
    assert run.stdout.split() == ["strict"], run.stderr
    assert "leaked" not in run.stderr, run.stderr


def test_strict_stops_at_the_first_failure(tmp_path):
    objects = [ObjectSpec("bad/abort", "bad", loader=aborting_loader), ("mug", 0), ("box", 1), ("can", 2)]
    with pytest.raises(DatasetError, match="SIGABRT.*strict"):
        generate(objects, tmp_path / "s", strategies="blind", contours_per_object=2, sensor=SMALL, probes=5,
                 workers=1, strict=True, progress=False)
    ds = open_dataset(tmp_path / "s")
    assert "bad/abort" in ds.failed and len(ds.object_names) < 3


def test_a_hanging_object_times_out_and_is_recorded(tmp_path):
    start = time.monotonic()
    report = generate([ObjectSpec("bad/hang", "bad", loader=hanging_loader)], tmp_path / "s", strategies="blind",
                      contours_per_object=2, sensor=SMALL, probes=5, workers=1, object_timeout_s=2, progress=False)
    assert time.monotonic() - start < 60  # not the loader's 600 s
    assert report.completed == 0 and report.failed == [("bad/hang", "timed out after 2 s")]
    assert open_dataset(tmp_path / "s").failed == {"bad/hang": "timed out after 2 s"}


def test_blind_never_computes_saliency_and_guided_computes_it_once(tmp_path):
    spec = ObjectSpec("mug/0", "mug", loader=mug_without_saliency)
    report = generate([spec], tmp_path / "blind", strategies="blind", contours_per_object=2, sensor=SMALL,
                      probes=5, workers=1, progress=False)
    assert report.completed == 1, report.failed
    calls = tmp_path / "calls.txt"
    spec = ObjectSpec("mug/0", "mug", loader=functools.partial(mug_counting_saliency, str(calls)))
    report = generate([spec], tmp_path / "both", strategies=("guided", "blind"), contours_per_object=2,
                      sensor=SMALL, probes=5, workers=1, progress=False)
    assert report.completed == 1, report.failed
    assert calls.read_text().split() == ["multiview"]


# ------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"strategies": ("blind", "psychic")}, "unknown strategies"),
        ({"strategies": ()}, "non-empty"),
        ({"contours_per_object": 0}, "contours_per_object must be an integer >= 1"),
        ({"probes": 1}, "probes must be"),
        ({"workers": 0}, "workers must be"),
        ({"executor": "dask"}, "executor must be"),
    ],
)
def test_bad_generate_arguments(tmp_path, kwargs, message):
    with pytest.raises(InvalidArgumentError, match=message):
        generate([("mug", 0)], tmp_path / "s", **{**BLIND, **kwargs})
    assert not (tmp_path / "s").exists()


def test_bad_objects_and_outputs(tmp_path):
    with pytest.raises(DatasetError, match="both named 'mug/0'"):
        generate([("mug", 0), ("mug", 0)], tmp_path / "s", **BLIND)
    with pytest.raises(DatasetError, match="unknown class 'teapot'"):
        generate([("teapot", 0)], tmp_path / "s", **BLIND)
    with pytest.raises(DatasetError, match="no objects"):
        generate([], tmp_path / "s", **BLIND)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not a dataset store"):
        generate([("mug", 0)], tmp_path / "other", **BLIND)


def test_open_dataset_refuses_what_is_not_a_store(tmp_path):
    with pytest.raises(DatasetError, match="no such dataset store"):
        open_dataset(tmp_path / "missing")
    with pytest.raises(DatasetError, match="not a dataset store"):
        open_dataset(tmp_path)
    import zarr

    zarr.open_group(tmp_path / "plain", mode="w")
    with pytest.raises(DatasetError, match="not a visuotactile tactile dataset"):
        open_dataset(tmp_path / "plain")


# ---------------------------------------------------------------------------- reading, splits
def test_load_selects_in_the_given_order(blind_store):
    ds = open_dataset(blind_store)
    everything = ds.load()
    assert len(everything) == 72 and everything.frames.shape == (72, 10, 16, 16)
    pick = np.array([59, 3, 30, 4])
    part = ds.load(pick)
    np.testing.assert_array_equal(part.frames, everything.frames[pick])
    np.testing.assert_array_equal(part.object_ids, [4, 0, 2, 0])
    assert part.object_names == ds.object_names and part.sensor_spec == SMALL.spec()
    with pytest.raises(DatasetError, match="out of range"):
        ds.load([72])
    with pytest.raises(DatasetError, match="no strategy 'guided'"):
        ds.indices("guided")


def test_splits_by_sequence_are_stratified_seeded_and_disjoint(guided_store):
    ds = open_dataset(guided_store)
    train, test = ds.split_by_sequence(0.5, seed=1)
    assert len(np.intersect1d(train, test)) == 0 and len(train) + len(test) == len(ds)
    for c in range(len(ds.class_names)):
        assert (ds.labels[test] == c).sum() == 3  # round(0.5 * 6)
    again = ds.split_by_sequence(0.5, seed=1)
    np.testing.assert_array_equal(again[1], test)
    guided = ds.indices("guided")
    train, test = ds.split_by_sequence(0.5, seed=1, index=guided)
    assert set(train) | set(test) == set(guided)
    with pytest.raises(InvalidArgumentError, match=r"test_fraction must be in \(0, 1\)"):
        ds.split_by_sequence(1.0)


def test_splits_by_object_hold_out_whole_objects_per_class(blind_store):
    ds = open_dataset(blind_store)
    train, test = ds.split_by_object(0.2, seed=0)
    test_objects, train_objects = set(ds.object_ids[test]), set(ds.object_ids[train])
    assert not test_objects & train_objects and len(test_objects) == 2  # max(1, round(0.6)) per class
    assert sorted(ds.object_labels[list(test_objects)]) == [0, 1]
    assert len(test) == 2 * 12
    other = [set(ds.object_ids[ds.split_by_object(0.2, seed=s)[1]]) for s in range(6)]
    assert len({frozenset(o) for o in other}) > 1  # the seed chooses the held-out objects
    folds = ds.kfold_by_object(3, seed=2)
    tested = np.concatenate([ds.object_ids[t] for _, t in folds])
    assert sorted(set(tested)) == list(range(6)) and len(tested) == len(ds)  # each object tested once
    for train, test in folds:
        assert not set(ds.object_ids[train]) & set(ds.object_ids[test])
        assert sorted(ds.object_labels[np.unique(ds.object_ids[test])]) == [0, 1]  # both classes per fold
    with pytest.raises(DatasetError, match="cannot fill 7 folds"):
        ds.kfold_by_object(7)


def test_torch_dataset_reads_the_same_sequences(blind_store):
    import torch

    ds = open_dataset(blind_store)
    pick = np.array([5, 41, 17])
    batch = ds.load(pick)
    tds = ds.torch_dataset(pick)
    assert len(tds) == 3
    loader = torch.utils.data.DataLoader(tds, batch_size=2, shuffle=False)
    frames, probe, labels = zip(*loader)
    np.testing.assert_array_equal(torch.cat(frames).numpy(), batch.frames)
    np.testing.assert_array_equal(torch.cat([p["normals"] for p in probe]).numpy(), batch.normals)
    np.testing.assert_array_equal(torch.cat(labels).numpy(), batch.labels)
    # Picklable (DataLoader workers): a copy reads the same item.
    import pickle

    copy = pickle.loads(pickle.dumps(tds))
    np.testing.assert_array_equal(copy[2][0].numpy(), batch.frames[2])


def test_guided_rows_take_every_pair_once_before_any_again(tmp_path):
    # 60 guided rows from 10 interest points (at most 45 planes): the first cycle holds each usable pair once,
    # the rest repeat planes, and a repeat is cut and pressed once in the worker. Every row must still be what
    # the documented call gives for it.
    sensor = FSRSensor(rows=8, cols=8)
    generate([("box", 4)], tmp_path / "s", strategies="guided", contours_per_object=60, sensor=sensor, probes=6,
             seed=2, workers=1, progress=False)
    ds = open_dataset(tmp_path / "s")
    batch = ds.load()
    model = make_object("box", 4)
    sal = attention.saliency(model, "multiview")
    usable = len(Toucher(model, "guided", probes=6, saliency=sal).pair_order(0))
    assert usable < 60  # the case under test (17 here: box corners coplanar with the centre share planes)
    # Planes identified up to sign (a pair gives one plane whatever its order).
    signs = np.sign(batch.plane_normals[np.arange(60), np.abs(batch.plane_normals).argmax(1)])
    planes = np.round(batch.plane_normals * signs[:, None], 9)
    assert len(np.unique(planes[:usable], axis=0)) == usable  # no repeat within the first cycle
    assert len(np.unique(planes, axis=0)) == usable  # and nothing new after it
    for k in range(60):
        expected = expected_row(model, "guided", 2, k, sensor, 6, sal)
        assert np.abs(batch.frames[k] - expected.frames).max() <= ds.max_frame_error * (1 + 1e-6)
        np.testing.assert_array_equal(batch.pad_sides_mm[k], expected.pad_sides_mm.astype(np.float32))


def test_stores_sharing_a_saliency_cache_have_the_same_bytes_and_read_its_points(guided_store, tmp_path):
    """With a cache the store's bytes equal the store made without one (the guided_store fixture); a second
    store of the same objects reads the cache: points planted there are the ones its guided planes pass through."""
    cache = tmp_path / "cache"
    out = tmp_path / "cached"
    generate([("mug", 0), ("box", 1)], out, strategies=("guided", "blind"), contours_per_object=3,
             sensor=FSRSensor(), probes=25, seed=3, workers=2, progress=False, saliency_cache=cache)
    assert store_files(out) == store_files(guided_store)
    entries = sorted(cache.glob("*.npy"))
    assert len(entries) == 2  # one per object (multiview), none for blind
    mug = make_object("mug", 0)
    planted = mug.vertices[np.linspace(0, len(mug.vertices) - 1, 10).astype(int)]
    from perception.interest_cache import InterestPointCache

    InterestPointCache(cache).put(mug, "multiview", 0, planted)
    again = tmp_path / "again"
    generate([("mug", 0)], again, strategies=("guided",), contours_per_object=4, sensor=SMALL, probes=6, seed=1,
             workers=1, progress=False, saliency_cache=cache)
    ds = open_dataset(again)
    np.testing.assert_array_equal(ds.interest_points("mug/0")["guided"], planted)
    batch = ds.load()
    for i in range(len(ds)):
        assert (np.abs((planted - batch.plane_points[i]) @ batch.plane_normals[i]) < 1e-6).sum() >= 2


def test_records_time_the_writes_and_the_benchmark_encodes_every_stored_byte(blind_store, monkeypatch):
    """Each object's record says how long its rows took to write; benchmarks.dataset.writing sets that beside
    Blosc encoding exactly the stored arrays' bytes (counted here from the arrays' shapes and types)."""
    import numcodecs
    import zarr

    from benchmarks.dataset import writing
    from tactile.dataset.store import ARRAYS, read_records

    records = read_records(blind_store, len(BLIND_OBJECTS)).values()
    assert len(records) == len(BLIND_OBJECTS) and all(r["write_seconds"] > 0 for r in records)
    expected = sum(int(np.prod(a.shape)) * a.dtype.itemsize
                   for a in (zarr.open_array(f"{blind_store}/{name}", mode="r") for name in ARRAYS))
    encoded = []
    real_encode = numcodecs.Blosc.encode
    monkeypatch.setattr(numcodecs.Blosc, "encode", lambda self, buf: (encoded.append(np.asarray(buf).nbytes),
                                                                      real_encode(self, buf))[1])
    found = writing(blind_store, workers=2)
    assert found["raw_bytes"] == expected == sum(encoded)  # every stored byte went through Blosc
    assert found["write_seconds"] == pytest.approx(sum(r["write_seconds"] for r in records) / 2)
    assert found["blosc_seconds"] > 0 and found["ratio"] == pytest.approx(2 * found["blosc_seconds"] / sum(r["write_seconds"] for r in records))


def test_reading_benchmark_decodes_every_stored_frame_byte_for_its_limit(blind_store):
    """benchmarks.dataset.reading sets loading the store beside Blosc decoding all of its frames (their raw bytes
    counted here from the array's shape and type) and zarr reading them."""
    import zarr

    from benchmarks.dataset import reading

    frames = zarr.open_array(f"{blind_store}/frames", mode="r")
    found = reading(blind_store, repeats=2)
    assert found["raw_bytes"] == int(np.prod(frames.shape)) * frames.dtype.itemsize
    assert found["sequences"] == frames.shape[0] and len(found["load_seconds_all"]) == 2
    assert found["ratio"] == pytest.approx(found["blosc_seconds"] / found["load_seconds"])
    assert found["zarr_frames_seconds"] > 0


def test_reading_loads_the_store_once_per_repeat(tmp_path, monkeypatch):
    from benchmarks.dataset import reading
    from tactile.dataset.reader import TactileDataset
    from tests._small_store import small_store

    store = small_store(tmp_path / "s.zarr")
    calls = []
    load = TactileDataset.load

    def counted(self, *args, **kwargs):
        calls.append(Path(self.path))
        return load(self, *args, **kwargs)

    monkeypatch.setattr(TactileDataset, "load", counted)
    found = reading(store, repeats=3)
    assert len(calls) == 3 and len(found["load_seconds_all"]) == 3
    assert found["sequences"] == 12 and found["raw_bytes"] == 12 * 6 * 8 * 8 * 2


def test_the_benchmark_times_the_repeats_that_do_not_sample_memory(tmp_path, monkeypatch):
    """With several repeats only the first generation samples memory (sampling slows it); the time is the median
    of the others. The generation and the later stages are stand-ins: only the bookkeeping is under test."""
    import benchmarks.dataset as bench
    import tactile.dataset as dataset_module

    seconds = iter([50.0, 10.0, 30.0, 20.0])
    sampled = []

    class Report:
        failed, sequences = [], 100

        def __init__(self):
            self.seconds = next(seconds)

    class Sampler:
        def __init__(self):
            self.peak = 123

        def __enter__(self):
            sampled.append(True)
            return self

        def __exit__(self, *exc):
            return None

    def fake_generate(objects, store, **kwargs):
        Path(store).mkdir(parents=True)
        return Report()

    monkeypatch.setattr(dataset_module, "generate", fake_generate)
    monkeypatch.setattr(bench, "PeakMemory", Sampler)
    monkeypatch.setattr(bench, "raw_limit", lambda store, workers: {"sequences_per_s": 10.0,
                                                                    "distinct_cast_seconds_sum": 8.0})
    for stage in ("storage", "loader_epoch", "reading"):
        monkeypatch.setattr(bench, stage, lambda store, *a: {})
    monkeypatch.setattr(bench, "writing", lambda store, workers: {})
    monkeypatch.setattr(bench, "rays_cast", lambda store, raw, wall: {})
    result = bench.run("quick", 2, tmp_path / "out", False, 4)
    generation = result["generation"]
    assert sampled == [True] and generation["peak_bytes"] == 123
    assert generation["seconds_all"] == [50.0, 10.0, 30.0, 20.0] and generation["seconds"] == 20.0
    assert generation["sequences_per_s"] == 5.0 and result["ratio_to_raw_distinct"] == 4.0 / 20.0
    seconds = iter([7.0])
    assert bench.run("quick", 2, tmp_path / "one", False, 1)["generation"]["seconds"] == 7.0  # one run: it samples


def test_write_seconds_add_up_every_write(tmp_path, monkeypatch):
    """Each array's rows are timed into the record: slowing every write by 5 ms shows in the total (the worker run
    in this process, rewriting a stored object's rows)."""
    from tactile.dataset import worker
    from tactile.dataset.objects import ObjectSpec
    from tactile.dataset.store import ARRAYS, read_attrs

    out = tmp_path / "store"
    generate([("box", 0)], out, workers=1, **BLIND)
    real_write = worker.write_rows

    def slow_write(*args):
        time.sleep(0.005)
        real_write(*args)

    monkeypatch.setattr(worker, "write_rows", slow_write)
    settings = read_attrs(out)["settings"]
    record = worker.explore_into_store(str(out), 0, ObjectSpec("box/0", "box", catalogue=("box", 0)), settings,
                                       FSRSensor.from_spec(settings["sensor"]))
    assert record["write_seconds"] >= 0.005 * len(ARRAYS)


def _mug_with(offsets):  # a loader whose argument is an array (module level: picklable)
    return make_object("mug", 0)


def test_loader_identity_names_array_arguments_by_content():
    """numpy elides the middle of a large array's repr: two arrays differing there must still give two identities
    (a store made with one is not resumed with the other); plain arguments read as their repr."""
    a = np.zeros(5000)
    b = a.copy()
    b[2500] = 1.0
    assert repr(a) == repr(b)  # the trap
    spec = lambda x: ObjectSpec("mug/0", "mug", loader=functools.partial(_mug_with, x)).to_dict()
    assert spec(a) != spec(b)
    assert spec(a) == spec(a.copy())
    assert spec(a)["loader_args"].startswith("((ndarray(shape=(5000,), dtype=float64, sha256=")
    plain = ObjectSpec("mug/0", "mug", loader=functools.partial(_mug_with, (1, "x", [2.5]), k={"s": 3})).to_dict()
    assert plain["loader_args"] == repr((((1, "x", [2.5]),), {"k": {"s": 3}}))
    # A mesh argument is its content, not its name and counts: vertices, and every other field (the centering moves
    # the centre the contour planes pass through).
    box, moved = make_object("box", 0), make_object("box", 0)
    moved.vertices[0] += 1e-3
    assert spec(box) != spec(moved)
    assert spec(box) == spec(make_object("box", 0))
    other_centre = next(c for c in CENTERINGS if c != box.centering)
    assert spec(box) != spec(dataclasses.replace(box, centering=other_centre))
    # Arrays hidden in other containers, of other shapes, or with a mask are still read by content.
    point = collections.namedtuple("Point", "data")
    assert spec(point(a)) != spec(point(b)) and spec(point(a))["loader_args"].startswith("((Point(ndarray(")
    assert spec(np.array([a, a[:3]], dtype=object)) != spec(np.array([b, a[:3]], dtype=object))
    assert spec(np.array(3.0)) != spec(np.array([3.0]))
    assert spec(np.ma.masked_array(a, mask=a > 0)) != spec(np.ma.masked_array(a, mask=b > 0))
    looped: list = [1]
    looped.append(looped)
    assert spec(looped)["loader_args"] == "(([1, ...],), {})"


class _Elided:  # an argument type whose repr hides its middle, as a large tensor's does
    def __repr__(self) -> str:
        return "tensor([0., 0., ..., 0.])"


def test_loader_argument_read_only_in_part_is_refused():
    spec = ObjectSpec("mug/0", "mug", loader=functools.partial(_mug_with, _Elided()))
    with pytest.raises(DatasetError, match=r"mug/0: the loader argument _Elided reads .*eliding its content"):
        spec.to_dict()
    text = ObjectSpec("mug/0", "mug", loader=functools.partial(_mug_with, "wait...")).to_dict()["loader_args"]
    assert text == repr((("wait...",), {}))  # a plain string may hold dots


def test_pair_order_seed_is_kept_exactly_and_in_range():
    # The rows of a guided store follow it: a resumed store made by another version must take the same order.
    assert pair_order_seed(0, "box/4", "guided") == 8137818715169992083
    assert pair_order_seed(7, "mug/0", "mesh") == 5468676966731091621
    seeds = [pair_order_seed(s, f"obj/{i}", m) for s in (0, 1, 2**40) for i in range(40) for m in ("guided", "mesh")]
    assert all(isinstance(x, int) and 0 <= x < 2**63 for x in seeds) and len(set(seeds)) == len(seeds)


def test_every_guided_strategy_of_a_mixed_store_takes_its_own_pair_order(tmp_path, guided_store):
    """A store of blind and guided strategies records how the guided pairs are drawn, and the rows of every guided
    strategy (not only "guided") take the pair order of (seed, object, that strategy)."""
    from tactile.dataset.store import ATTRS_KEY

    settings = json.loads((guided_store / "zarr.json").read_text())["attributes"][ATTRS_KEY]["settings"]
    assert settings["guided_pairs"] == "without repeats"  # ("guided", "blind")
    sensor = FSRSensor(rows=4, cols=4)
    generate([("box", 4)], tmp_path / "s", strategies=("blind", "mesh"), contours_per_object=4, sensor=sensor,
             probes=4, seed=5, workers=1, progress=False)
    ds = open_dataset(tmp_path / "s")
    settings = json.loads((tmp_path / "s" / "zarr.json").read_text())["attributes"][ATTRS_KEY]["settings"]
    assert settings["guided_pairs"] == "without repeats"
    batch = ds.load()
    model = make_object("box", 4)
    sal = attention.saliency(model, "mesh")
    rows = np.flatnonzero(ds.sequence_strategies == "mesh")
    assert len(rows) == 4
    for k, i in enumerate(rows):
        expected = expected_row(model, "mesh", 5, k, sensor, 4, sal)
        assert abs(abs(batch.plane_normals[i] @ expected.plane.normal) - 1) < 1e-9, k
        assert np.abs(batch.frames[i] - expected.frames).max() <= ds.max_frame_error * (1 + 1e-6)
