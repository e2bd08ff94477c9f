"""Outlier exposure (``CNNClassifier(outliers=STORE)``): the nets learn the uniform distribution on touches of objects
of no known class, and a bad outlier store or weight is refused by name."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.base import load_model
from fusion.cnn import MAX_OUTLIER_WEIGHT, CNNClassifier
from fusion.experiments.touch import touch_objects
from perception.errors import DatasetError, InvalidArgumentError
from perception.shapes import make_object
from tactile import FSRSensor
from tactile.dataset import generate, open_dataset

SENSOR = FSRSensor(rows=8, cols=8)
PROBES = 10


@pytest.fixture(scope="module")
def known():
    """Touches of two classes (box, can), two objects each."""
    objects = [make_object("box", s) for s in range(2)] + [make_object("can", s) for s in range(2)]
    return touch_objects(objects, ["box"] * 2 + ["can"] * 2, "blind", 12, sensor=SENSOR, probes=PROBES)


@pytest.fixture(scope="module")
def outlier_store(tmp_path_factory):
    """A store of touches of three objects that are neither a box nor a can."""
    path = tmp_path_factory.mktemp("outliers") / "outliers.zarr"
    generate([("bowl", 0), ("ring", 0), ("spoon", 0)], path, strategies=("blind",), contours_per_object=12,
             sensor=SENSOR, probes=PROBES, workers=1, progress=False)
    return str(path)


def model(**params) -> CNNClassifier:
    return CNNClassifier(**{"epochs": 60, "progress": False, "threads": 1, **params})


def test_exposed_outliers_read_near_uniform_and_the_known_classes_are_still_told_apart(known, outlier_store):
    """The term asks for the uniform distribution (1/2 each for two classes) on the outlier touches: with it, their
    mean largest probability falls near 1/2; without it, the nets call them a box or a can with confidence."""
    outliers = open_dataset(outlier_store).load()
    truth = np.asarray(known.class_names, dtype=object)[known.labels]
    plain = model().fit(known)
    exposed = model(outliers=outlier_store, outlier_weight=2.0).fit(known)
    plain_top = plain.predict_proba(outliers).max(axis=1).mean()
    exposed_top = exposed.predict_proba(outliers).max(axis=1).mean()
    assert exposed_top < 0.6 < plain_top, (exposed_top, plain_top)
    assert np.mean(exposed.predict(known) == truth) >= 0.95


def test_no_outliers_or_a_zero_weight_trains_the_plain_model(known, outlier_store):
    """A weight of 0 turns the term off (the store is not read): the weights are those of a fit without outliers,
    bit for bit."""
    plain = model(epochs=3).fit(known)
    off = model(epochs=3, outliers=outlier_store, outlier_weight=0.0).fit(known)
    for net in ("cutaneous_net_", "kinesthetic_net_"):
        a, b = getattr(plain, net).state_dict(), getattr(off, net).state_dict()
        assert all(np.array_equal(a[k].numpy(), b[k].numpy()) for k in a)


def test_the_outlier_setting_survives_a_model_file(known, outlier_store, tmp_path):
    exposed = model(epochs=3, outliers=outlier_store, outlier_weight=1.5).fit(known)
    exposed.save(tmp_path / "m.vtm")
    loaded = load_model(tmp_path / "m.vtm")
    assert loaded.outliers == outlier_store and loaded.outlier_weight == 1.5
    assert np.array_equal(loaded.predict_proba(known), exposed.predict_proba(known))


@pytest.mark.parametrize("weight", [-0.1, float("nan"), float("inf"), MAX_OUTLIER_WEIGHT * 2, True, "1",
                                    pytest.param(10**5000, id="10**5000")])
def test_a_bad_weight_is_refused(known, weight):
    with pytest.raises(InvalidArgumentError, match="outlier_weight"):
        model(outlier_weight=weight).fit(known)


def test_outliers_must_be_a_store_path(known, tmp_path):
    with pytest.raises(InvalidArgumentError, match="outliers must be"):
        model(outliers=tmp_path).fit(known)  # a Path, not the str a model file can keep
    missing = str(tmp_path / "nowhere.zarr")
    with pytest.raises(DatasetError, match="nowhere.zarr"):
        model(outliers=missing).fit(known)


def test_outliers_touched_with_another_sensor_are_refused(known, tmp_path):
    path = tmp_path / "coarse.zarr"
    generate([("bowl", 0)], path, strategies=("blind",), contours_per_object=2, sensor=FSRSensor(rows=4, cols=4),
             probes=PROBES, workers=1, progress=False)
    with pytest.raises(DatasetError, match="coarse.zarr.*another sensor"):
        model(epochs=1, outliers=str(path)).fit(known)
