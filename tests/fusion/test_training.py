"""Training on a store and evaluating there: the record a model keeps, and the held-out part evaluation uses."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.base import load_model
from fusion.training import SPLITS, evaluate_on_store, evaluation_indices, split_indices, train_on_store
from perception.errors import DatasetError, InvalidArgumentError
from tactile.dataset import generate, open_dataset
from tactile.sensor import FSRSensor


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    out = tmp_path_factory.mktemp("training") / "s.zarr"
    objects = [(name, seed) for name in ("box", "ring") for seed in (0, 1)]
    generate(objects, out, strategies=("blind",), contours_per_object=10, sensor=FSRSensor(rows=8, cols=8),
             probes=10, seed=0, workers=1, progress=False)
    return out


class TestSplits:
    def test_each_split_partitions_the_strategys_sequences(self, store):
        ds = open_dataset(store)
        for split in SPLITS:
            train, test = split_indices(ds, split, "blind", 0.25, 3)
            assert sorted(np.concatenate([train, test]).tolist()) == ds.indices("blind").tolist()
            again = split_indices(ds, split, "blind", 0.25, 3)
            assert np.array_equal(train, again[0]) and np.array_equal(test, again[1])
        _, test = split_indices(ds, "object", None, 0.5, 0)
        assert len(set(ds.object_ids[test].tolist())) == 2  # whole objects, one per class

    def test_an_unknown_split_is_refused(self, store):
        with pytest.raises(InvalidArgumentError, match="split"):
            split_indices(open_dataset(store), "by-colour", None, 0.2, 0)


@pytest.fixture(scope="module")
def guided(tmp_path_factory):
    """Guided contours, 60 per object: more than the 45 planes ten interest points make, so some repeat."""
    out = tmp_path_factory.mktemp("guided") / "g.zarr"
    generate([("box", 0), ("mug", 0)], out, strategies=("guided",), contours_per_object=60,
             sensor=FSRSensor(rows=8, cols=8), probes=6, seed=0, workers=1, progress=False)
    return out


class TestSequenceSplitKeepsContoursTogether:
    """Ten interest points make at most 45 guided planes: a store with more guided contours repeats them, and the
    default `train --split sequence` failed its own held-out check on every such store (copies on both sides)."""

    def test_no_contour_is_on_both_sides_and_the_model_passes_its_held_out_check(self, guided, tmp_path):
        ds = open_dataset(guided)
        train, test = split_indices(ds, "sequence", None, 0.2, 0)
        ids = ds.contour_ids()
        assert len(np.unique(ids)) < len(ids)  # the store does repeat contours
        assert not set(ids[train].tolist()) & set(ids[test].tolist())
        assert sorted(np.concatenate([train, test]).tolist()) == list(range(len(ds)))
        assert 0.1 <= len(test) / len(ds) <= 0.3
        result = train_on_store(guided, "knn", tmp_path / "m.vtm")  # the default split: it raised DataLeakError
        assert result["test_sequences"] == len(test) and (tmp_path / "m.vtm").is_file()

    def test_a_store_without_repeats_splits_as_before(self, store):
        ds = open_dataset(store)
        assert len(np.unique(ds.contour_ids())) == len(ds)  # blind planes never repeat
        for seed in (0, 1):
            expected = ds.split_by_sequence(0.25, seed=seed)
            found = split_indices(ds, "sequence", None, 0.25, seed)
            assert all(np.array_equal(a, b) for a, b in zip(expected, found, strict=True))

    def test_a_plane_stored_with_its_normal_flipped_is_the_same_contour(self, guided, monkeypatch):
        # the generator writes repeats with one sign; a pair touched the other way round would flip it
        ds = open_dataset(guided)
        expected = ds.contour_ids()
        read = ds._read

        def flipped(name, rows):
            values = read(name, rows)
            if name == "plane_normals":
                values = values.copy()
                values[::2] *= -1
            return values

        monkeypatch.setattr(ds, "_read", flipped)
        np.testing.assert_array_equal(ds.contour_ids(), expected)

    def test_a_model_that_fails_its_held_out_check_is_not_written(self, store, tmp_path, monkeypatch):
        from fusion import training
        from perception.errors import DataLeakError

        honest = training.split_indices

        def leaky(*args):
            train, test = honest(*args)
            return train, np.concatenate([test, train[:3]])

        monkeypatch.setattr(training, "split_indices", leaky)
        with pytest.raises(DataLeakError, match="not held out"):
            train_on_store(store, "knn", tmp_path / "m.vtm")
        assert not (tmp_path / "m.vtm").exists()

    def test_copies_are_found_whichever_way_a_plane_normal_points(self, guided):
        ds = open_dataset(guided)
        batch = ds.load()
        ids = ds.contour_ids()
        # sequences with one id share their object and plane (up to the normal's sign), those with two ids do not
        def key(i):  # the normal turned to face a generic direction: n and -n are one plane
            n = batch.plane_normals[i].astype(np.float64)
            return int(batch.object_ids[i]), tuple(np.round(n if n @ [1.0, 1e-3, 1e-6] > 0 else -n, 4))

        for a in range(0, len(ds), 7):
            for b in range(a + 1, len(ds), 11):
                assert (ids[a] == ids[b]) == (key(a) == key(b) and np.allclose(batch.plane_points[a],
                                                                                  batch.plane_points[b]))


class TestTrainAndEvaluate:
    def test_the_model_remembers_its_store_and_evaluation_uses_the_held_out_part(self, store, tmp_path):
        result = train_on_store(store, "knn", tmp_path / "m.vtm", split="object", test_fraction=0.5, random_state=1)
        model = load_model(tmp_path / "m.vtm")
        assert model.training_["split"] == "object" and model.training_["seed"] == 1
        assert model.training_["train_sequences"] == result["train_sequences"] == 20
        ds = open_dataset(store)
        index, subset = evaluation_indices(model, ds, store)
        assert subset == "held-out object split of training"
        np.testing.assert_array_equal(index, split_indices(ds, "object", None, 0.5, 1)[1])
        found = evaluate_on_store(model, store, seed=1)
        assert found["decisions"] == result["test_sequences"] == 20
        assert found["accuracy"] == result["test_accuracy"]  # same sequences, same predictions

    def test_a_model_from_elsewhere_is_tested_on_everything(self, store, tmp_path):
        train_on_store(store, "knn", tmp_path / "m.vtm", split="none")
        model = load_model(tmp_path / "m.vtm")
        model.training_ = {**model.training_, "store_id": "another"}
        index, subset = evaluation_indices(model, open_dataset(store), store)
        assert subset == "all sequences" and len(index) == 40

    def test_an_evaluation_on_what_the_model_was_fitted_on_says_so(self, store, tmp_path):
        # trained on every sequence and evaluated on the same store: 100 % that must not read as a held-out score
        train_on_store(store, "knn", tmp_path / "m.vtm", split="none")
        found = evaluate_on_store(load_model(tmp_path / "m.vtm"), store)
        assert found["subset"].endswith("fitted on 40 of these 40 sequences: not a held-out score")
        half = open_dataset(store).indices()[::2]  # trained on half: 20 of the 40 evaluated were seen
        from fusion.conventional import ConventionalClassifier

        model = ConventionalClassifier("knn").fit(open_dataset(store).load(half))
        assert "fitted on 20 of these 40 sequences" in evaluate_on_store(model, store)["subset"]

    def test_a_store_of_classes_the_model_never_saw_is_refused_naming_them(self, store, tmp_path):
        other = tmp_path / "other.zarr"
        generate([("mug", 0), ("box", 5)], other, strategies=("blind",), contours_per_object=2,
                 sensor=FSRSensor(rows=8, cols=8), probes=10, seed=0, workers=1, progress=False)
        train_on_store(store, "knn", tmp_path / "m.vtm", split="none")
        with pytest.raises(DatasetError, match=r"other.zarr: classes \['mug'\] are not among the model's classes"):
            evaluate_on_store(load_model(tmp_path / "m.vtm"), other)
