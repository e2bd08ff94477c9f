"""``visuotactile train`` and ``evaluate`` on a small store: held-out split remembered, K touches, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fusion.base import load_model
from fusion.cli import main
from tactile.dataset import generate, open_dataset
from tactile.sensor import FSRSensor


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    out = tmp_path_factory.mktemp("train") / "small.zarr"
    objects = [(name, seed) for name in ("box", "ring", "spoon") for seed in (0, 1)]
    generate(objects, out, strategies=("blind",), contours_per_object=12, sensor=FSRSensor(rows=8, cols=8),
             probes=10, seed=0, workers=1, progress=False)
    return out


def test_train_then_evaluate_on_the_held_out_sequences(store, tmp_path, capsys):
    model_path = tmp_path / "knn.vtm"
    assert main(["train", "--store", str(store), "--model", "knn", "--out", str(model_path), "--json"]) == 0
    trained = json.loads(capsys.readouterr().out)
    # 6 objects x 12 contours, 20 % held out by sequence.
    assert trained["train_sequences"] + trained["test_sequences"] == 72
    assert 0.15 * 72 <= trained["test_sequences"] <= 0.25 * 72
    model = load_model(model_path)
    assert list(model.classes_) == ["box", "ring", "spoon"]

    assert main(["evaluate", "--model", str(model_path), "--store", str(store), "--json",
                 "--figure", str(tmp_path / "c.png")]) == 0
    evaluated = json.loads(capsys.readouterr().out)
    assert evaluated["subset"].startswith("held-out sequence split")
    assert evaluated["decisions"] == trained["test_sequences"]
    # The same held-out sequences, the same predictions: the same accuracy as train reported.
    assert evaluated["accuracy"]["value"] == pytest.approx(trained["test_accuracy"]["value"])
    assert (tmp_path / "c.png").stat().st_size > 1000

    # Independent check of that accuracy with the library.
    data = open_dataset(store)
    _, test = data.split_by_sequence(test_fraction=0.2, seed=0, index=data.indices(None))
    batch = data.load(test)
    truth = np.asarray(batch.class_names)[batch.labels]
    assert evaluated["accuracy"]["value"] == pytest.approx(np.mean(model.predict(batch) == truth))


def test_evaluate_with_touches_groups_sequences_of_one_object(store, tmp_path, capsys):
    model_path = tmp_path / "knn.vtm"
    main(["train", "--store", str(store), "--model", "knn", "--out", str(model_path), "--split", "none"])
    capsys.readouterr()
    assert main(["evaluate", "--model", str(model_path), "--store", str(store), "--touches", "3", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    # trained on all of it (--split none): the subset says the score is not a held-out one
    assert result["subset"].startswith("all sequences; the model was fitted on 72 of these 72")
    assert result["decisions"] == 6 * 12 // 3


def test_bad_inputs_end_with_one_line_and_exit_2(store, tmp_path, capsys):
    assert main(["evaluate", "--model", str(tmp_path / "missing.vtm"), "--store", str(store)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such model file" in err[0]
    assert main(["train", "--store", str(tmp_path / "nothing.zarr"), "--model", "svm", "--out", str(tmp_path / "m")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


@pytest.fixture(scope="module")
def four_class_store(tmp_path_factory):
    out = tmp_path_factory.mktemp("train4") / "four.zarr"
    objects = [(name, seed) for name in ("box", "can", "ring", "spoon") for seed in (0, 1, 2)]
    generate(objects, out, strategies=("blind",), contours_per_object=8, sensor=FSRSensor(rows=8, cols=8),
             probes=10, seed=0, workers=1, progress=False)
    return out


def test_train_calibrate_writes_a_model_that_can_answer_unknown(four_class_store, tmp_path, capsys):
    """``--calibrate`` fits calibration and the reject option on the training objects: the saved model carries them
    (the same state the library's calibrate fits on the same data) and predicts "unknown" below its threshold."""
    from fusion.classifiers import make_classifier
    from fusion.openset import SCORES, UNKNOWN, calibrate

    model_path = tmp_path / "knn.vtm"
    assert main(["train", "--store", str(four_class_store), "--model", "knn", "--split", "none", "--calibrate",
                 "--out", str(model_path), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["calibration"]["score"] in SCORES
    model = load_model(model_path)
    data = open_dataset(four_class_store)
    batch = data.load(data.indices(None))
    expected = calibrate(make_classifier("knn", cue="invariant", random_state=0), batch, class_folds=4,
                         random_state=0).calibration_
    assert model.calibration_["score"] == expected["score"]
    assert model.calibration_["temperature"] == pytest.approx(expected["temperature"])
    np.testing.assert_allclose(model.calibration_["thresholds"], expected["thresholds"])
    # Each sequence alone: "unknown" exactly where its known score is under the K = 1 threshold, else the class.
    scores, threshold = model.known_score(batch), model.calibration_["thresholds"][0]
    expected_answers = np.where(scores < threshold, UNKNOWN, model.predict(batch)).astype(str)
    np.testing.assert_array_equal(model.predict(batch, reject=True).astype(str), expected_answers)
    assert result["calibration"]["temperature"] == pytest.approx(model.calibration_["temperature"], abs=1e-4)
    assert result["calibration"]["dependence"] == pytest.approx(model.calibration_["dependence"], abs=1e-4)
    assert main(["train", "--store", str(four_class_store), "--model", "knn", "--split", "none", "--calibrate",
                 "--out", str(tmp_path / "k2.vtm")]) == 0
    assert f"answers 'unknown' by {result['calibration']['score'].replace('_', ' ')}" in capsys.readouterr().out


def test_train_calibrate_fits_on_the_training_part_with_its_seed(four_class_store, tmp_path, capsys):
    """With a held-out split and another seed, the calibration is the library's on exactly the training part."""
    from fusion.classifiers import make_classifier
    from fusion.openset import calibrate
    from fusion.training import split_indices

    model_path = tmp_path / "knn.vtm"
    assert main(["train", "--store", str(four_class_store), "--model", "knn", "--calibrate", "--seed", "1",
                 "--out", str(model_path), "--json"]) == 0
    capsys.readouterr()
    data = open_dataset(four_class_store)
    train, _ = split_indices(data, "sequence", None, 0.2, 1)
    expected = calibrate(make_classifier("knn", cue="invariant", random_state=1), data.load(train), class_folds=4,
                         random_state=1).calibration_
    got = load_model(model_path).calibration_
    assert got["temperature"] == pytest.approx(expected["temperature"])
    np.testing.assert_allclose(got["thresholds"], expected["thresholds"])


@pytest.mark.parametrize("names,open_set", [(("box", "ring"), False), (("box", "can", "ring"), True)])
def test_train_calibrate_with_two_or_three_classes(names, open_set, tmp_path, capsys):
    """Two classes: calibrated, no 'unknown' answer (said so); three: leave-classes-out folds of one class each."""
    store = tmp_path / "s.zarr"
    generate([(n, seed) for n in names for seed in (0, 1, 2)], store, strategies=("blind",), contours_per_object=6,
             sensor=FSRSensor(rows=8, cols=8), probes=10, seed=0, workers=1, progress=False)
    assert main(["train", "--store", str(store), "--model", "knn", "--split", "none", "--calibrate",
                 "--out", str(tmp_path / "m.vtm")]) == 0
    out = capsys.readouterr().out
    state = load_model(tmp_path / "m.vtm").calibration_
    assert ("thresholds" in state) is open_set
    assert ("no 'unknown' answer: fewer than three classes" in out) is not open_set


def test_train_calibrate_needs_three_objects_per_class(store, tmp_path, capsys):
    assert main(["train", "--store", str(store), "--model", "knn", "--split", "none", "--calibrate",
                 "--out", str(tmp_path / "m.vtm")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--calibrate needs at least 3 training objects per class" in err[0]
    assert "{'box': 2, 'ring': 2, 'spoon': 2}" in err[0]
    assert not (tmp_path / "m.vtm").exists()


def test_train_with_outliers_keeps_the_store_in_the_model(store, tmp_path, capsys):
    """``--outliers``: the CNN trains with outlier exposure on a store of objects of no class of ``--store``; the SVM
    and kNN have no such training, and the training store itself is no outlier store."""
    outliers = tmp_path / "outliers.zarr"
    generate([("bowl", 0), ("can", 0)], outliers, strategies=("blind",), contours_per_object=6,
             sensor=FSRSensor(rows=8, cols=8), probes=10, seed=0, workers=1, progress=False)
    model_path = tmp_path / "cnn.vtm"
    assert main(["train", "--store", str(store), "--model", "cnn", "--outliers", str(outliers), "--out",
                 str(model_path)]) == 0
    capsys.readouterr()
    model = load_model(model_path)
    assert model.outliers == str(outliers) and list(model.classes_) == ["box", "ring", "spoon"]
    for argv, words in ((["--model", "svm", "--outliers", str(outliers)], ("only the cnn", "svm")),
                        (["--model", "cnn", "--outliers", str(store)], ("training store itself",))):
        assert main(["train", "--store", str(store), "--out", str(tmp_path / "m.vtm"), *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and all(w in err[0] for w in words), err


def test_train_with_contrastive_keeps_the_weight_in_the_model(store, tmp_path, capsys):
    """``--contrastive``: the CNN trains with the supervised contrastive term of that weight, which the model file
    keeps; the SVM has no such term, and a weight the CNN refuses writes no model."""
    model_path = tmp_path / "cnn.vtm"
    assert main(["train", "--store", str(store), "--model", "cnn", "--contrastive", "0.5", "--split", "none",
                 "--out", str(model_path)]) == 0
    capsys.readouterr()
    assert load_model(model_path).contrastive_weight == 0.5
    plain = tmp_path / "plain.vtm"
    assert main(["train", "--store", str(store), "--model", "cnn", "--split", "none", "--out", str(plain)]) == 0
    capsys.readouterr()
    assert load_model(plain).contrastive_weight == 0.0
    for argv, words in ((["--model", "svm", "--contrastive", "0.5"], ("only the cnn", "svm", "contrastive")),
                        (["--model", "cnn", "--contrastive", "-1"], ("contrastive_weight", "-1")),
                        (["--model", "cnn", "--contrastive", "nan"], ("contrastive_weight", "nan"))):
        bad = tmp_path / "bad.vtm"
        assert main(["train", "--store", str(store), "--out", str(bad), *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and all(w in err[0] for w in words), err
        assert not bad.exists()


@pytest.mark.parametrize("weight", [None, "0.5", np.array([1.0, 0.0]), True])
@pytest.mark.parametrize("kind", ["cnn", "knn"])
def test_train_on_store_refuses_a_contrastive_weight_that_is_no_number(store, tmp_path, weight, kind):
    from fusion.training import train_on_store
    from perception.errors import InvalidArgumentError

    with pytest.raises(InvalidArgumentError, match="contrastive: expected a number"):
        train_on_store(store, kind, tmp_path / "m.vtm", contrastive=weight)
    assert not (tmp_path / "m.vtm").exists()
