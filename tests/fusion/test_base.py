"""The classifier base: labels, sensor compatibility, multi-touch, save / load, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.base import TactileClassifier, class_indices, load_model
from perception.errors import DatasetError, ModelFileError, ModelMismatchError
from tactile.sensor import FSRSensor
from tests.fusion._synthetic import circle_batch


class MeanFrame(TactileClassifier):
    """Nearest class mean of the mean frame reading, with softmax probabilities (a stand-in classifier)."""

    def __init__(self, temperature: float = 1.0):
        self.temperature = temperature

    def _fit(self, batch, y):
        means = batch.frames.mean(axis=(1, 2, 3))
        self.centres_ = np.array([means[y == k].mean() for k in range(len(self.classes_))])

    def _predict_proba(self, batch):
        d = -np.abs(batch.frames.mean(axis=(1, 2, 3))[:, None] - self.centres_[None]) / self.temperature
        e = np.exp(d - d.max(axis=1, keepdims=True))
        return e / e.sum(axis=1, keepdims=True)


@pytest.fixture
def batch():
    # Class 0: radii near 20 mm, class 1: near 60 mm.
    return circle_batch([19, 20, 21, 22, 58, 60, 61, 63], labels=[0, 0, 0, 0, 1, 1, 1, 1])


def test_fit_predict_score_with_class_names(batch):
    model = MeanFrame().fit(batch)
    assert list(model.classes_) == ["c0", "c1"]
    assert model.score(batch) == 1.0
    probe = circle_batch([18.0, 70.0])
    np.testing.assert_array_equal(model.predict(probe), ["c0", "c1"])
    proba = model.predict_proba(probe)
    assert proba.shape == (2, 2) and np.allclose(proba.sum(axis=1), 1.0)


def test_score_on_a_class_the_model_never_saw_is_refused(batch):
    # it returned 0.0: an accuracy of nothing the model could have answered, read as a measurement
    model = MeanFrame().fit(batch)
    with pytest.raises(DatasetError, match=r"\['mug'\] are not among the classes \['c0', 'c1'\]"):
        model.score(batch, y=np.array(["c0"] * 4 + ["mug"] * 4))
    assert model.score(batch, y=np.array(["c0"] * 4 + ["c0"] * 4)) == 0.5


@pytest.mark.parametrize("name, field", [("positions", "positions"), ("plane_points", "plane_points"),
                                         ("plane_normals", "plane_normals")])
def test_non_finite_or_far_sequence_arrays_are_refused_naming_the_object(batch, name, field):
    import dataclasses

    values = getattr(batch, name).copy()
    values[3] = np.nan
    bad = dataclasses.replace(batch, **{name: values})
    with pytest.raises(DatasetError, match=f"sequence {field} contain NaN or Inf \\(first in object"):
        MeanFrame().fit(bad)
    if name != "plane_normals":
        values = getattr(batch, name).copy()
        values[5] = 3e38  # finite, but cues made from it overflow float32
        where = "" if name == "pad_sides_mm" else " from the origin \\(float32 positions hold no millimetres"
        with pytest.raises(DatasetError, match=f"sequence {field} exceed 1e\\+06 mm{where}"):
            MeanFrame().fit(dataclasses.replace(batch, **{name: values}))


def test_explicit_labels_by_name(batch):
    model = MeanFrame().fit(batch, y=["small"] * 4 + ["large"] * 4)
    assert list(model.classes_) == ["large", "small"]
    assert list(model.predict(circle_batch([18.0]))) == ["small"]


def test_multi_touch_groups(batch):
    model = MeanFrame(temperature=30.0).fit(batch)
    fused = model.predict_proba_touches(batch, np.array([[0, 1, 2], [4, 5, 6]]))
    assert fused.shape == (2, 2) and fused[0].argmax() == 0 and fused[1].argmax() == 1
    # Three agreeing touches are more confident than one.
    assert fused[0, 0] > model.predict_proba(batch)[0, 0]


def test_one_class_nan_and_wrong_types_are_refused(batch):
    with pytest.raises(DatasetError, match="only one class"):
        MeanFrame().fit(batch.subset(slice(0, 4)))
    broken = batch.subset(slice(None))
    broken.frames[0, 0, 0, 0] = np.nan
    with pytest.raises(DatasetError, match="NaN"):
        MeanFrame().fit(broken)
    with pytest.raises(DatasetError, match="expected a SequenceBatch"):
        MeanFrame().fit(np.zeros((3, 4)))


def test_data_from_another_sensor_is_refused_but_noise_settings_may_differ(batch):
    model = MeanFrame().fit(batch)
    other = circle_batch([20.0])
    other.sensor_spec = FSRSensor(rows=4, cols=4, side_mm=30.0).spec()
    with pytest.raises(ModelMismatchError, match="side_mm 20.0 \\(model\\) vs 30.0 \\(data\\)"):
        model.predict(other)
    noisy = circle_batch([20.0])
    noisy.sensor_spec = FSRSensor(rows=4, cols=4, noise_std=0.1, dead_taxel_rate=0.05).spec()
    assert list(model.predict(noisy)) == ["c0"]
    with pytest.raises(ModelMismatchError, match="12 probes of 4 x 4"):
        model.predict(circle_batch([20.0], probes=10))
    assert model.sensor() == FSRSensor(rows=4, cols=4)


def test_save_load_round_trip(batch, tmp_path):
    model = MeanFrame().fit(batch)
    path = model.save(tmp_path / "m.vtm")
    loaded = load_model(path)
    np.testing.assert_array_equal(loaded.predict_proba(batch), model.predict_proba(batch))
    assert list(loaded.classes_) == list(model.classes_)


def test_loading_garbage_or_missing_files_is_refused(tmp_path):
    with pytest.raises(ModelFileError, match="missing.vtm: no such model file"):
        load_model(tmp_path / "missing.vtm")
    (tmp_path / "junk.vtm").write_bytes(b"not a pickle at all")
    with pytest.raises(ModelFileError, match="junk.vtm: not a readable visuotactile model file"):
        load_model(tmp_path / "junk.vtm")


class TestNotFitted:
    """A classifier used before fit raises the project's NotFittedError (which the CLI turns into exit 2)."""

    def test_predict_and_save_before_fit(self, batch, tmp_path):
        from perception.errors import NotFittedError, VisuotactileError

        model = MeanFrame()
        with pytest.raises(NotFittedError, match="fit"):
            model.predict(batch)
        with pytest.raises(NotFittedError, match="fit"):
            model.save(tmp_path / "m.vtm")
        with pytest.raises(NotFittedError) as info:
            model.predict_proba(batch)
        assert isinstance(info.value, VisuotactileError) and isinstance(info.value, ValueError)


def test_class_indices_finds_each_name_and_refuses_strangers():
    classes = np.array(["bottle", "cup", "mug"], dtype=object)
    assert class_indices(classes, ["mug", "bottle", "mug", "cup"]).tolist() == [2, 0, 2, 1]
    # Names that sort between, before or after the classes are not classes (searchsorted alone would index them).
    for stranger in ("can", "apple", "zebra"):
        with pytest.raises(DatasetError, match=stranger):
            class_indices(classes, ["cup", stranger])
