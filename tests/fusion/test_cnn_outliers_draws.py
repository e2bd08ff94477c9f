"""Outlier exposure, checked from outside the training loop: the known sequences' batches are those of a fit without
outliers (the outlier draws have their own random stream), the outliers are augmented as the known sequences are, and
an empty outlier store or one touched with a sensor of other settings (same grid and probes) is refused by name."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from fusion import cnn
from fusion.cnn import CNNClassifier
from perception.errors import DatasetError, InvalidArgumentError
from tactile import FSRSensor
from tactile.dataset import generate
from tests.fusion.test_cnn_outliers import PROBES, SENSOR, known, outlier_store  # noqa: F401 -- fixtures

BATCH = 8


def model(**params) -> CNNClassifier:
    return CNNClassifier(**{"epochs": 2, "batch_size": BATCH, "progress": False, "threads": 1, **params})


def training_inputs(monkeypatch, fit) -> dict[str, list[np.ndarray]]:
    """What each net is fed at every training step of ``fit()``, per net."""
    seen: dict[str, list[np.ndarray]] = {"CutaneousNet": [], "KinestheticNet": []}
    for name, inputs in seen.items():
        net = getattr(cnn, name)
        features = net.features  # where a training step enters the net (it keeps the hidden layer)

        def record(self, x, features=features, inputs=inputs):
            if self.training:
                inputs.append(x.detach().numpy().copy())
            return features(self, x)

        monkeypatch.setattr(net, "features", record)
    fit()
    monkeypatch.undo()
    return seen


def test_the_known_batches_are_those_of_a_fit_without_outliers(known, outlier_store, monkeypatch):  # noqa: F811
    plain = training_inputs(monkeypatch, lambda: model().fit(known))
    exposed = training_inputs(monkeypatch, lambda: model(outliers=outlier_store, outlier_weight=1.0).fit(known))
    for net in plain:
        assert len(plain[net]) == len(exposed[net]) > 1
        for a, b in zip(plain[net], exposed[net], strict=True):
            assert len(b) == 2 * len(a)  # as many outliers as known sequences, fed after them
            assert np.array_equal(b[:len(a)], a), net


def test_the_outliers_are_augmented_as_the_known_sequences_are(known, outlier_store, monkeypatch):  # noqa: F811
    """Unaugmented, every outlier fed is one of the store's sequences as it is; augmented (a random start probe and
    direction), most are not."""
    def outliers_fed(augment):
        seen = training_inputs(monkeypatch, lambda: model(outliers=outlier_store, augment=augment).fit(known))
        return {net: np.concatenate([x[len(x) // 2:] for x in steps]) for net, steps in seen.items()}

    raw, augmented = outliers_fed(False), outliers_fed(True)
    for net in raw:
        as_stored = {row.tobytes() for row in raw[net]}
        assert len(as_stored) > 1
        unchanged = np.mean([row.tobytes() in as_stored for row in augmented[net]])
        assert unchanged < 0.5, (net, unchanged)


def test_an_outlier_store_without_a_sequence_is_refused_by_name(known, outlier_store, tmp_path):  # noqa: F811
    """A store whose objects are not recorded yet (an interrupted generate) reads as no sequence at all."""
    path = tmp_path / "unfinished.zarr"
    shutil.copytree(outlier_store, path)
    for record in (path / "records").iterdir():
        record.unlink()
    with pytest.raises(DatasetError, match="unfinished.zarr: the outlier store holds no sequence"):
        model(outliers=str(path)).fit(known)


def test_outliers_of_a_sensor_with_other_settings_but_the_same_grid_are_refused(known, tmp_path):  # noqa: F811
    path = tmp_path / "smaller-pad.zarr"
    other = FSRSensor(rows=SENSOR.rows, cols=SENSOR.cols, side_mm=15.0)
    generate([("bowl", 0)], path, strategies=("blind",), contours_per_object=2, sensor=other, probes=PROBES,
             workers=1, progress=False)
    with pytest.raises(DatasetError, match="smaller-pad.zarr.*another sensor"):
        model(epochs=1, outliers=str(path)).fit(known)


@pytest.mark.parametrize("weight", [10**20, 10**400, -(10**20)])
def test_a_weight_too_large_for_a_float_is_an_argument_error(known, weight):  # noqa: F811
    with pytest.raises(InvalidArgumentError, match="outlier_weight"):
        model(outlier_weight=weight).fit(known)


def test_an_outlier_path_too_long_for_the_system_is_refused_by_name(known):  # noqa: F811
    """The system's ENAMETOOLONG was an OSError out of open_dataset: now the DatasetError of any missing store."""
    with pytest.raises(DatasetError, match=r"^x{200}: no such dataset store \(File name too long\)"):
        model(outliers="x" * 5000).fit(known)
