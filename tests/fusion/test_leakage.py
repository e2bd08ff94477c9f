"""Tests that catch train/test leaks: what a model was fitted on (its sequence fingerprints) against what it is
scored on, multi-touch groups of one object each, unseen-object splits disjoint by object and by mesh, and the noise
experiment's noisy and repaired frames differing from the clean ones."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

import fusion.leakage as leakage_module
from fusion.base import load_model
from fusion.cli import main
from fusion.decide import touch_groups
from fusion.leakage import KEY, check_held_out, fingerprints_of, sequence_fingerprints
from fusion.training import evaluate_on_store, train_on_store
from perception.errors import DataLeakError
from tactile.dataset import generate, open_dataset
from tactile.dataset.reader import check_disjoint_splits
from tactile.sensor import FSRSensor


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Two objects per class (box, ring), 6 contours each."""
    out = tmp_path_factory.mktemp("leakage") / "s.zarr"
    objects = [(name, seed) for name in ("box", "ring") for seed in (0, 1)]
    generate(objects, out, strategies="blind", contours_per_object=6, sensor=FSRSensor(rows=8, cols=8), probes=6,
             seed=0, workers=1, progress=False)
    return out


@pytest.fixture(scope="module")
def trained(store, tmp_path_factory):
    """{split: (model file, train_on_store's result)} of kNN models held out by sequence (25 %) and by object."""
    folder = tmp_path_factory.mktemp("leakage-models")
    return {split: (folder / f"{split}.vtm", train_on_store(store, "knn", folder / f"{split}.vtm", split=split,
                                                            test_fraction=0.25 if split == "sequence" else 0.5))
            for split in ("sequence", "object")}


class TestWhatTheModelWasFittedOn:
    def test_the_model_file_keeps_a_fingerprint_of_every_training_sequence(self, store, trained):
        path, result = trained["sequence"]
        model = load_model(path)
        ds = open_dataset(store)
        train, test = ds.split_by_sequence(0.25, seed=0)
        trained = fingerprints_of(model)
        assert trained is not None and len(trained) == result["train_sequences"] == len(train)
        assert set(trained.tolist()) == set(sequence_fingerprints(ds.load(train)).tolist())
        assert not np.isin(sequence_fingerprints(ds.load(test)), trained).any()

    def test_a_model_fitted_on_its_test_sequences_is_refused_at_evaluation(self, store, trained):
        # What `train` would do if it fitted on train + test: the record says 25 % held out, the fingerprints say
        # all. Evaluation trusts the fingerprints.
        model = load_model(trained["sequence"][0])
        ds = open_dataset(store)
        model.training_[KEY] = sequence_fingerprints(ds.load())
        with pytest.raises(DataLeakError, match="fitted on 6 of the 6 test sequences"):
            evaluate_on_store(model, store)

    def test_an_unseen_object_claim_is_refused_when_one_sequence_of_a_test_object_was_seen(self, store, trained):
        model = load_model(trained["object"][0])
        ds = open_dataset(store)
        _, test = ds.split_by_object(0.5, seed=0)
        batch = ds.load(test)
        check_held_out(model, batch, "clean", by_object=True)  # nothing seen
        model.training_[KEY] = np.concatenate([fingerprints_of(model), sequence_fingerprints(batch)[:1]])
        with pytest.raises(DataLeakError, match="sequences of 1 test object"):
            evaluate_on_store(model, store)

    def test_fingerprints_tell_sequences_apart_and_survive_a_store_round_trip(self, store):
        ds = open_dataset(store)
        a, b = sequence_fingerprints(ds.load()), sequence_fingerprints(ds.load())
        assert np.array_equal(a, b) and len(np.unique(a)) == len(a) == 24


def test_touches_are_grouped_by_object_never_by_class(store, trained, tmp_path, capsys):
    # 2 objects x 6 sequences per class: groups of 4 sequences of one object give one decision per object (4);
    # grouping by class would give 3 per class (6). The model counts as one from elsewhere: all sequences.
    model = load_model(trained["sequence"][0])
    model.training_ = {"store_id": "another"}
    model = model.save(tmp_path / "elsewhere.vtm")
    assert main(["evaluate", "--model", str(model), "--store", str(store), "--touches", "4", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["decisions"] == 4
    ds = open_dataset(store)
    for seed in range(3):
        groups = touch_groups(ds.object_ids, 4, seed=seed, repeats=2)
        assert all(len(set(ds.object_ids[g].tolist())) == 1 for g in groups)
        assert all(len(set(g.tolist())) == 4 for g in groups)


class TestUnseenObjectSplits:
    def test_every_split_and_fold_is_disjoint_by_object_and_mesh(self, store):
        ds = open_dataset(store)
        meshes = ds.mesh_ids()
        assert sorted(meshes) == ["catalogue:box/0", "catalogue:box/1", "catalogue:ring/0", "catalogue:ring/1"]
        for seed in range(4):
            train, test = ds.split_by_object(0.5, seed=seed)
            folds = ds.kfold_by_object(2, seed=seed)
            for tr, te in [(train, test), *folds]:
                assert len(tr) and len(te) and not set(tr) & set(te)
                assert not set(ds.object_ids[tr]) & set(ds.object_ids[te])
                assert not set(meshes[ds.object_ids[tr]]) & set(meshes[ds.object_ids[te]])
                assert sorted(np.concatenate([tr, te]).tolist()) == list(range(len(ds)))
            tested = np.concatenate([te for _, te in folds])
            assert sorted(tested.tolist()) == list(range(len(ds)))  # every object tested exactly once

    def test_split_checks_refuse_shared_sequences_objects_and_meshes(self):
        ids = np.array([0, 0, 1, 1, 2, 2])
        check_disjoint_splits(ids, [0, 1, 2, 3], [4, 5], "fine", mesh_ids=["a", "b", "c"])
        with pytest.raises(DataLeakError, match="2 sequences are in both"):
            check_disjoint_splits(ids, [0, 1, 2, 3, 4, 5], [4, 5], "train + test")
        with pytest.raises(DataLeakError, match=r"objects \[1\]"):
            check_disjoint_splits(ids, [0, 1, 2], [3, 4, 5], "half an object")
        with pytest.raises(DataLeakError, match="mesh"):
            check_disjoint_splits(ids, [0, 1, 2, 3], [4, 5], "a copy", mesh_ids=["a", "b", "a"])

    def test_a_split_that_leaks_is_refused_before_it_is_used(self, store, monkeypatch):
        ds = open_dataset(store)
        real = type(ds)._split_by_object

        def train_plus_test(self, *args, **kwargs):  # the leak the issue planted: train = train + test
            train, test = real(self, *args, **kwargs)
            return np.union1d(train, test), test

        monkeypatch.setattr(type(ds), "_split_by_object", train_plus_test)
        with pytest.raises(DataLeakError, match="split by object"):
            ds.split_by_object(0.5)


class TestNoiseExperimentFrames:
    @pytest.fixture(scope="class")
    @classmethod
    def touched(cls):
        from fusion.experiments.robustness import _sensor_and_jitter
        from fusion.experiments.touch import touch_objects
        from perception.shapes import make_object

        models = [make_object("box", 0), make_object("ring", 0)]

        def read(kind, level):
            sensor, jitter = _sensor_and_jitter(kind, level)
            batch = touch_objects(models, ["box", "ring"], "blind", 3, sensor=sensor, probes=6, seed=5,
                                  jitter_mm=jitter)
            return batch, sensor

        return read

    @pytest.mark.parametrize("kind,level", [("taxel_noise", 0.2), ("dead_taxels", 0.05), ("pose_jitter", 2.0)])
    def test_every_noise_kind_changes_the_frames(self, touched, kind, level):
        clean, _ = touched("clean", 0.0)
        noisy, _ = touched(kind, level)
        assert noisy.frames.shape == clean.frames.shape
        changed = np.abs(noisy.frames - clean.frames).max(axis=(1, 2, 3)) > 1e-3
        assert changed.all(), f"{kind} {level}: {int((~changed).sum())} sequences read as clean"

    def test_repaired_frames_differ_from_the_raw_ones_and_are_closer_to_clean(self, touched):
        from fusion.experiments.robustness import _inputs

        clean, _ = touched("clean", 0.0)
        broken, sensor = touched("dead_taxels", 0.05)
        inputs = _inputs(broken, sensor, ["dead_taxels", "dead_taxels_repaired"])
        raw, repaired = inputs["raw"].frames, inputs["repaired"].frames
        assert np.array_equal(raw, broken.frames)
        assert (np.abs(repaired - raw).max(axis=(1, 2, 3)) > 1e-3).all()  # every sequence had a dead taxel fixed
        assert np.abs(repaired - clean.frames).mean() < 0.5 * np.abs(raw - clean.frames).mean()


def test_noise_part_rereads_read_out_noise_bit_for_bit_and_touches_jitter(tmp_path):
    """The noise part derives taxel-noise and dead-taxel batches from its cached clean batch (no rays): they equal
    touching with the noisy sensor, bit for bit; jittered batches are touched (and cached)."""
    from fusion.experiments.config import QUICK
    from fusion.experiments.context import Context
    from fusion.experiments.robustness import TEST_SEED_OFFSET, _noisy_batch, _sensor_and_jitter
    from fusion.experiments.touch import touch_objects
    from perception.shapes import make_object

    ctx = Context(out=tmp_path, seed=2, sizes=QUICK, classifiers={}, progress=False)
    models = [make_object("box", 0), make_object("ring", 0)]
    for kind, level in [("taxel_noise", 0.3), ("dead_taxels", 0.2), ("dead_taxels_repaired", 0.2), ("pose_jitter", 1.0)]:
        sensor, jitter = _sensor_and_jitter(kind, level)
        got = _noisy_batch(ctx, models, ["box", "ring"], "upright", "blind", kind, level, sensor, jitter, None)
        expected = touch_objects(models, ["box", "ring"], "blind", QUICK.noise_contours, sensor=sensor,
                                 seed=2 + TEST_SEED_OFFSET, jitter_mm=jitter)
        assert got.frames.tobytes() == expected.frames.tobytes(), kind
        assert got.sensor_spec == expected.sensor_spec
        np.testing.assert_array_equal(got.positions, expected.positions)
    cached = sorted(p.name.split("-")[2] for p in (tmp_path / "noise").iterdir())  # pose-strategy-kind-...
    assert cached == ["clean", "pose_jitter"]  # read-out noise needed no touch of its own


def test_noise_levels_reuse_the_cached_clean_batch_and_its_seeds(tmp_path, monkeypatch):
    """After the clean batch is touched once, read-out noise levels never touch: touching is made to fail and
    the dead-taxel level still comes back; the cache holds each sequence's own read-out seed."""
    from fusion.experiments import robustness
    from fusion.experiments.config import QUICK
    from fusion.experiments.context import Context
    from fusion.experiments.touch import load_batch_with_seeds, touch_object
    from perception.shapes import make_object

    ctx = Context(out=tmp_path, seed=4, sizes=QUICK, classifiers={}, progress=False)
    models = [make_object("box", 0), make_object("ring", 0)]
    args = (ctx, models, ["box", "ring"], "upright", "blind")
    sensor, _ = robustness._sensor_and_jitter("taxel_noise", 0.3)
    robustness._noisy_batch(*args, "taxel_noise", 0.3, sensor, 0.0, None)
    (clean_file,) = (tmp_path / "noise").iterdir()
    _, seeds = load_batch_with_seeds(clean_file, None)
    expected = [s.seed for m in models
                for s in touch_object(m, "blind", QUICK.noise_contours, seed=4 + robustness.TEST_SEED_OFFSET)[0]]
    assert seeds.dtype == np.int64 and seeds.tolist() == expected

    def no_touching(*a, **k):
        raise AssertionError("touched again")

    monkeypatch.setattr(robustness, "touch_objects", no_touching)
    sensor, _ = robustness._sensor_and_jitter("dead_taxels", 0.2)
    assert len(robustness._noisy_batch(*args, "dead_taxels", 0.2, sensor, 0.0, None)) == len(seeds)


def test_batch_cache_returns_seeds_only_when_they_are_usable(tmp_path):
    from fusion.experiments.models import write_cache
    from fusion.experiments.touch import _ARRAYS, load_batch, load_batch_with_seeds, save_batch, touch_objects
    from perception.errors import InvalidArgumentError
    from perception.shapes import make_object

    batch = touch_objects([make_object("box", 0)], ["box"], "blind", 3, probes=6, seed=1)
    plain = save_batch(batch, tmp_path / "plain.npz", {"k": 1})
    assert load_batch_with_seeds(plain, {"k": 1}) is None  # no seeds in the file: touch again
    assert load_batch(plain, {"k": 1}).frames.tobytes() == batch.frames.tobytes()
    with pytest.raises(InvalidArgumentError, match="per sequence"):
        save_batch(batch, tmp_path / "short.npz", {"k": 1}, noise_seeds=np.asarray([5, 6]))
    meta = {"class_names": list(batch.class_names), "object_names": list(batch.object_names),
            "sensor_spec": batch.sensor_spec, "key": {"k": 1}}
    for name, seeds in (("short", [5, 6]), ("negative", [5, -6, 7])):  # written by hand: unusable on loading
        path = write_cache(tmp_path / f"{name}-hand.npz", meta, {**{a: getattr(batch, a) for a in _ARRAYS},
                                                                 "noise_seeds": np.asarray(seeds)})
        assert load_batch_with_seeds(path, {"k": 1}) is None, name
    good = save_batch(batch, tmp_path / "good.npz", {"k": 1}, noise_seeds=[7, 8, 9])
    found, seeds = load_batch_with_seeds(good, {"k": 1})
    assert seeds.dtype == np.int64 and seeds.tolist() == [7, 8, 9]
    assert found.frames.tobytes() == batch.frames.tobytes()


def test_a_noisy_sensor_of_another_geometry_touches_again(tmp_path):
    """Re-reading the clean frames is exact only for the default pad; a noisy pad of another size (no jitter) is
    pressed for real: its frames have its own grid, and a noise kind with it is cached as a touched batch."""
    from fusion.experiments import robustness
    from fusion.experiments.config import QUICK
    from fusion.experiments.context import Context
    from perception.shapes import make_object
    from tactile import FSRSensor

    ctx = Context(out=tmp_path, seed=4, sizes=QUICK, classifiers={}, progress=False)
    args = (ctx, [make_object("box", 0)], ["box"], "upright", "blind")
    small = FSRSensor(rows=8, cols=8, noise_std=0.3)
    batch = robustness._noisy_batch(*args, "taxel_noise", 0.3, small, 0.0, None)
    assert batch.frames.shape[2:] == (8, 8)
    assert sorted(p.name.split("-")[2] for p in (tmp_path / "noise").iterdir()) == ["taxel_noise"]


def test_batch_cache_seeds_zero_is_usable_floats_and_huge_are_not(tmp_path):
    from fusion.experiments.models import write_cache
    from fusion.experiments.touch import _ARRAYS, load_batch, load_batch_with_seeds, save_batch, touch_objects
    from perception.errors import InvalidArgumentError
    from perception.shapes import make_object

    batch = touch_objects([make_object("box", 0)], ["box"], "blind", 3, probes=6, seed=1)
    path = save_batch(batch, tmp_path / "zero.npz", {"k": 1}, noise_seeds=[0, 1, 2])
    assert load_batch_with_seeds(path, {"k": 1})[1].tolist() == [0, 1, 2]
    for bad in ([7.9, 8.1, 9.5], [True, False, True], [-1, 1, 2], np.array([2**63 + 1, 1, 2], np.uint64)):
        with pytest.raises(InvalidArgumentError, match="noise_seeds"):
            save_batch(batch, tmp_path / "bad.npz", {"k": 1}, noise_seeds=bad)
    assert not (tmp_path / "bad.npz").exists()
    meta = {"class_names": list(batch.class_names), "object_names": list(batch.object_names),
            "sensor_spec": batch.sensor_spec, "key": {"k": 1}}
    arrays = {a: getattr(batch, a) for a in _ARRAYS}
    for name, seeds in (("float", np.array([7.0, 8.5, 9.0])), ("huge", np.array([2**63 + 1, 1, 2], np.uint64))):
        written = write_cache(tmp_path / f"{name}-hand.npz", meta, {**arrays, "noise_seeds": seeds})
        assert load_batch_with_seeds(written, {"k": 1}) is None, name
    # A file whose meta lacks a field, or whose arrays do not fit together, is unreadable: made again, no crash.
    no_names = write_cache(tmp_path / "no-names.npz", {"key": {"k": 1}}, arrays)
    assert load_batch(no_names, {"k": 1}) is None
    not_a_list = write_cache(tmp_path / "none-names.npz", {**meta, "class_names": None}, arrays)
    assert load_batch(not_a_list, {"k": 1}) is None
    not_an_object = write_cache(tmp_path / "list-meta.npz", [1, 2], arrays)
    assert load_batch(not_an_object, {"k": 1}) is None
    short = write_cache(tmp_path / "short.npz", meta, {**arrays, "labels": arrays["labels"][:1]})
    assert load_batch(short, {"k": 1}) is None


def test_a_clean_cache_without_seeds_is_touched_again(tmp_path):
    """A clean batch cached without seeds (older code) cannot be re-read: it is touched again (the noisy frames
    then equal pressing with the noisy sensor, byte for byte) and saved with its seeds."""
    import json

    from fusion.experiments import robustness
    from fusion.experiments.config import QUICK
    from fusion.experiments.context import Context
    from fusion.experiments.touch import load_batch_with_seeds, save_batch, touch_objects
    from perception.shapes import make_object

    ctx = Context(out=tmp_path, seed=4, sizes=QUICK, classifiers={}, progress=False)
    models = [make_object("box", 0)]
    args = (ctx, models, ["box"], "upright", "blind")
    robustness._touched(*args, "clean", 0.0, robustness.FSRSensor(), 0.0, None)
    (clean_file,) = (tmp_path / "noise").iterdir()
    batch, _ = load_batch_with_seeds(clean_file)
    key = json.loads(str(np.load(clean_file)["meta"]))["key"]
    save_batch(batch, clean_file, key)  # the same batch and key, no seeds
    sensor, _ = robustness._sensor_and_jitter("taxel_noise", 0.3)
    got = robustness._noisy_batch(*args, "taxel_noise", 0.3, sensor, 0.0, None)
    expected = touch_objects(models, ["box"], "blind", QUICK.noise_contours, sensor=sensor,
                             seed=4 + robustness.TEST_SEED_OFFSET)
    assert got.frames.tobytes() == expected.frames.tobytes()
    assert load_batch_with_seeds(clean_file, key) is not None


# ------------------------------------------------------------------ fingerprints on threads (from a break attempt)
#: What a fingerprint hashes, in order: each sequence's arrays as float32 bytes.
NAMES = ("frames", "normals", "positions", "pad_sides_mm")


def _batch(arrays: dict, n: int):
    return type("Batch", (), {**arrays, "__len__": lambda self: n})()


def _expected(arrays: dict, i: int) -> int:
    """The 64-bit BLAKE2b of sequence ``i``'s float32 bytes, computed with hashlib alone."""
    data = b"".join(np.ascontiguousarray(np.asarray(arrays[k][i], dtype=np.float32)).tobytes() for k in NAMES)
    return int.from_bytes(hashlib.blake2b(data, digest_size=8).digest(), "little", signed=True)


def _arrays(rng, n: int) -> dict:
    return {"frames": rng.random((n, 2, 3, 3)), "normals": rng.random((n, 2, 3)).astype(np.float32),
            "positions": rng.random((n, 2, 3)), "pad_sides_mm": rng.random((n, 2)).astype(np.float32)}


@pytest.mark.parametrize("cores", [1, 2, 3, 5])
def test_every_row_is_hashed_whatever_the_threads(monkeypatch, cores):
    monkeypatch.setattr(leakage_module, "usable_cores", lambda: cores)
    rng = np.random.default_rng(11)
    n = 1300  # 5 threads' worth of rows
    sequence_fingerprints(_batch(_arrays(rng, n), n))  # leaves its fingerprints in memory numpy may hand out again
    arrays = _arrays(rng, n)
    found = sequence_fingerprints(_batch(arrays, n))
    assert found.tolist() == [_expected(arrays, i) for i in range(n)]


def test_rows_not_contiguous_in_memory_are_hashed_as_their_float32_bytes(monkeypatch):
    monkeypatch.setattr(leakage_module, "usable_cores", lambda: 2)
    rng = np.random.default_rng(12)
    n = 600
    arrays = _arrays(rng, n)
    arrays["pad_sides_mm"] = rng.random((n, 4)).astype(np.float32)[:, ::2]  # strided rows, float32 already
    arrays["normals"] = np.asfortranarray(arrays["normals"])
    found = sequence_fingerprints(_batch(arrays, n))
    assert found.tolist() == [_expected(arrays, i) for i in range(n)]
