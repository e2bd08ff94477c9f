"""What a model file says is checked when it loads, not when it is first used: class names, the calibration's
temperature and reference features, the training record's values, the header's sizes. Each file below passes every
integrity check (it is resealed with a valid checksum) and is refused by name, as ModelFileError naming the file."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fusion.base import MAX_CLASS_NAME, load_model
from fusion.commands import print_json
from fusion.conventional import ConventionalClassifier
from fusion.openset import calibrate, class_distances, per_touch
from perception.errors import DatasetError, InvalidArgumentError, ModelFileError
from tests._model_files import rewrite
from tests.fusion.test_features import small_batch


@pytest.fixture(scope="module")
def batch():
    return small_batch(8, 8)  # 4 classes x 2 objects x 10 contours


@pytest.fixture(scope="module")
def knn_file(batch, tmp_path_factory):
    path = tmp_path_factory.mktemp("values") / "knn.vtm"
    ConventionalClassifier("knn").fit(batch).save(path)
    return path


@pytest.fixture(scope="module")
def calibrated_file(batch, tmp_path_factory):
    path = tmp_path_factory.mktemp("values-cal") / "knn-open.vtm"
    calibrate(ConventionalClassifier("knn"), batch, cv=2, class_folds=2, holdout=2, max_touches=4).save(path)
    return path


def _set(key, value):
    def edit(description, arrays):
        description[key] = value
    return edit


@pytest.mark.parametrize("classes, problem", [
    (["box\nvisuotactile recognize: error: FAKE", "ring"], "not a printable name"),
    (["\udcff", "ring"], "not a printable name"),
    (["b" * (MAX_CLASS_NAME + 1), "ring"], "not a printable name"),
    (["box", "unknown"], "may not be named 'unknown'"),
    (["UNKNOWN", "box"], "may not be named 'UNKNOWN'"),
    (["ring", "box"], "not in sorted order"),
])
def test_class_names_that_would_forge_output_or_reorder_the_columns_are_refused(knn_file, tmp_path, classes,
                                                                               problem):
    # A reordered pair loaded before and silently swapped every prediction (the columns follow sorted names).
    bad = rewrite(knn_file, tmp_path / "bad.vtm", _set("classes", classes + ["x2", "x3"]))
    with pytest.raises(ModelFileError, match=problem) as info:
        load_model(bad)
    assert str(bad) in str(info.value)


def test_training_data_with_a_class_named_unknown_is_refused_at_fit(batch):
    names = np.array(["cup", "Unknown", "box", "ring"], dtype=object)[batch.labels]
    with pytest.raises(DatasetError, match="may not be named 'Unknown'"):
        ConventionalClassifier("knn").fit(batch, y=names)


def _edit_calibration(edit_state):
    """An edit applying ``edit_state(state, arrays)`` to the file's encoded calibration state."""
    def edit(description, arrays):
        edit_state(description["state"]["fitted"]["dict"]["calibration_"]["dict"], arrays)
    return edit


def _array_of(state, name):
    """The file's tensor key of the encoded array ``state[name]`` (``{"array": {"key", "order"}}``)."""
    return state[name]["array"]["key"]


@pytest.mark.parametrize("temperature", [5e-324, 1e-308, 1e6])
def test_a_temperature_no_fit_can_give_is_refused(calibrated_file, tmp_path, temperature):
    # 5e-324 passed "finite and > 0" and then failed every prediction ("probabilities must be finite")
    bad = rewrite(calibrated_file, tmp_path / "t.vtm",
                  _edit_calibration(lambda s, a: s.__setitem__("temperature", temperature)))
    with pytest.raises(ModelFileError, match="temperature .* outside the fitted range"):
        load_model(bad)


def test_reference_features_of_another_width_are_refused_at_load(calibrated_file, tmp_path):
    def narrower(state, arrays):
        key = _array_of(state, "reference")
        arrays[key] = np.ascontiguousarray(arrays[key][:, :2])

    bad = rewrite(calibrated_file, tmp_path / "w.vtm", _edit_calibration(narrower))
    with pytest.raises(ModelFileError, match="columns: the model's feature space") as info:
        load_model(bad)
    assert str(bad) in str(info.value)


def test_huge_reference_features_are_refused_and_distances_stay_finite(calibrated_file, tmp_path):
    def huge(state, arrays):
        key = _array_of(state, "reference")
        arrays[key] = np.full_like(arrays[key], 1e308)

    with pytest.raises(ModelFileError, match="at most 1e"):
        load_model(rewrite(calibrated_file, tmp_path / "h.vtm", _edit_calibration(huge)))
    # and features near the float range (a hostile test input, say) give the largest float, not inf
    d = class_distances(np.full((2, 3), 1e308), np.array([[-1e308, -1e308, -1e308], [1e308, 1e308, 1e308]]),
                        np.array([0, 1]), 2, neighbors=1)
    assert np.isfinite(d).all() and (d[:, 0] == np.finfo(np.float64).max).all() and (d[:, 1] == 0).all()


def test_a_sound_calibrated_file_still_loads_and_scores(calibrated_file, batch):
    model = load_model(calibrated_file)
    proba, distances, _ = per_touch(model, batch)
    assert np.isfinite(proba).all() and np.isfinite(distances).all()


@pytest.mark.parametrize("key, value", [("split", "bogus"), ("strategy", "nope"), ("test_fraction", 5.0),
                                        ("test_fraction", 0.0), ("seed", -1), ("train_sequences", -3)])
def test_impossible_training_record_values_are_refused_naming_the_file(knn_file, tmp_path, key, value):
    def edit(description, arrays):  # the record `visuotactile train` writes, one value made impossible
        description["training"]["dict"].update({"store": "s.zarr", "store_id": "x", "split": "sequence",
                                                "strategy": None, "test_fraction": 0.2, "seed": 0,
                                                "train_sequences": 10, key: value})

    bad = rewrite(knn_file, tmp_path / "r.vtm", edit)
    with pytest.raises(ModelFileError, match=f"impossible '{key}'") as info:
        load_model(bad)
    assert str(bad) in str(info.value)


def test_header_sizes_follow_the_toolkit_limits(knn_file, tmp_path, monkeypatch):
    probes = rewrite(knn_file, tmp_path / "p.vtm", _set("probes", 20_000))  # above the default 10,000 probes
    with pytest.raises(ModelFileError, match="VISUOTACTILE_MAX_PROBES"):
        load_model(probes)
    monkeypatch.setenv("VISUOTACTILE_MAX_TAXELS", "100")
    grid = rewrite(knn_file, tmp_path / "g.vtm", lambda d, a: (d.__setitem__("grid", [16, 16]),
                                                               d["sensor_spec"]["dict"].update(rows=16, cols=16)))
    with pytest.raises(ModelFileError, match="16 x 16 taxel grid .* VISUOTACTILE_MAX_TAXELS"):
        load_model(grid)


def test_saving_to_a_folder_names_it_and_a_bad_byte_limit_is_an_argument_error(knn_file, tmp_path):
    model = load_model(knn_file)
    with pytest.raises(ModelFileError, match="is a folder"):
        model.save(tmp_path)
    (tmp_path / "a-file").write_text("not a folder")
    with pytest.raises(ModelFileError, match="cannot write the model file"):
        model.save(tmp_path / "a-file" / "m.vtm")
    with pytest.raises(InvalidArgumentError, match="max_bytes"):
        load_model(knn_file, max_bytes=-1)


def test_json_output_refuses_nan_rather_than_print_it(capsys):
    """`--json` output is JSON a strict parser reads: a NaN or inf reaching it is a bug to raise, and nothing of the
    refused document is printed."""
    with pytest.raises(ValueError, match="not JSON compliant"):
        print_json({"label": "box", "known_score": float("-inf")})
    assert capsys.readouterr().out == ""
    print_json({"label": "box", "known_score": -1.5})
    assert json.loads(capsys.readouterr().out) == {"label": "box", "known_score": -1.5}


@pytest.mark.parametrize("call", [lambda: load_model(None), lambda: load_model(b"m.vtm"),
                                  lambda: calibrate(None, None), lambda: calibrate("knn", None)])
def test_a_wrong_kind_of_argument_is_an_argument_error(call):
    with pytest.raises(InvalidArgumentError, match="expected a"):
        call()
