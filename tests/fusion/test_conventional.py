"""ConventionalClassifier: learns, probabilities, determinism, persistence, sensor checks, numerics, CV."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.model_selection import StratifiedGroupKFold, StratifiedKFold, cross_val_score

from fusion.base import load_model
from fusion.conventional import SEARCH_GRID, ConventionalClassifier, conventional_pipeline, cross_validate
from fusion.features import sequence_features
from perception.errors import DatasetError, InvalidArgumentError, ModelMismatchError
from tests.fusion.test_features import small_batch

FAST = {"som_iterations": 300, "n_select": 30, "search": None}  # the configured (paper) pipeline


def _split(batch, seed=0):
    """Every 4th contour of each object for testing (by sequence, as in the paper)."""
    test = np.zeros(len(batch), dtype=bool)
    test[np.arange(len(batch)) % 5 == seed % 5] = True
    return batch.subset(~test), batch.subset(test)


@pytest.fixture(scope="module")
def fitted():
    """An SVM and a kNN trained once on 4/5 of the small batch (fitting costs seconds: share them)."""
    train, test = _split(small_batch())
    models = {kind: ConventionalClassifier(kind=kind, **FAST).fit(train) for kind in ("svm", "knn")}
    return models, train, test


@pytest.mark.parametrize("kind", ["svm", "knn"])
def test_learns_and_gives_probabilities(fitted, kind):
    models, train, test = fitted
    clf = models[kind]
    assert list(clf.classes_) == sorted(train.class_names)
    proba = clf.predict_proba(test)
    assert proba.shape == (len(test), 4) and np.isfinite(proba).all()
    np.testing.assert_allclose(proba.sum(axis=1), 1.0)
    # Four classes, 16 test sequences: chance is 25 % (P(>= 7 right by chance) < 0.1). This tiny set (64
    # training sequences) is far from the paper's scale; accuracy is measured on larger batches (report).
    assert clf.score(test) >= 7 / 16
    assert clf.score(train) >= 0.6
    assert len(clf.pipeline_.named_steps["reduce"].representatives_) == 5  # "SOM to 5"


def test_same_seed_same_bytes_and_save_load(fitted, tmp_path):
    models, train, test = fitted
    a = models["svm"]
    b = ConventionalClassifier(kind="svm", **FAST).fit(train.subset(np.arange(len(train))))  # no shared cache
    assert a.predict_proba(test).tobytes() == b.predict_proba(test).tobytes()
    path = a.save(tmp_path / "svm.vtm")
    loaded = load_model(path)
    assert isinstance(loaded, ConventionalClassifier) and loaded.cue == a.cue == "invariant"
    assert loaded.predict_proba(test).tobytes() == a.predict_proba(test).tobytes()


def test_other_sensor_is_refused(fitted):
    models, _, test = fitted
    other = test.subset(np.arange(len(test)))
    other.sensor_spec = dict(other.sensor_spec, side_mm=15.0)
    with pytest.raises(ModelMismatchError, match="side_mm"):
        models["knn"].predict(other)


def test_invariant_cue_and_small_training_sets():
    batch = small_batch()
    clf = ConventionalClassifier(kind="knn", cue="invariant", **FAST).fit(batch.subset(np.arange(0, 80, 10)))
    # 8 sequences: k is capped at 8, the selector keeps what there is; still a valid distribution.
    assert clf.pipeline_[-1].n_neighbors == 8
    proba = clf.predict_proba(batch)
    assert np.isfinite(proba).all() and np.allclose(proba.sum(axis=1), 1.0)
    # One sequence per class: no information gain is measurable (all 0), PCA gets at most 4 components.
    one_each = ConventionalClassifier(kind="knn", reduce="pca", **FAST).fit(batch.subset(np.arange(0, 80, 20)))
    assert one_each.pipeline_.named_steps["reduce"].n_components == 4
    assert np.isfinite(one_each.predict_proba(batch)).all()
    with pytest.raises(DatasetError, match="at least 2 sequences per class"):
        ConventionalClassifier(kind="svm", **FAST).fit(batch.subset(np.arange(0, 80, 20)))


def test_constant_video_and_bad_input(fitted):
    batch = small_batch()
    models, train, _ = fitted
    clf = models["svm"]
    flat = batch.subset(np.arange(3))
    flat.frames = np.zeros_like(flat.frames)  # a constant tactile video: all subband stds are 0
    assert np.all(sequence_features(flat)[:, : 16 * flat.n_probes] == 0.0)
    assert np.isfinite(clf.predict_proba(flat)).all()
    # Constant training features (every frame flat, every normal equal) still train and predict finitely.
    dull = train.subset(np.arange(len(train)))
    dull.frames = np.zeros_like(dull.frames)
    dull.normals = np.broadcast_to(np.float32([0, 0, 1]), dull.normals.shape).copy()
    proba = ConventionalClassifier(kind="knn", **FAST).fit(dull).predict_proba(dull)
    assert np.isfinite(proba).all()
    nan = batch.subset(np.arange(3))
    nan.frames = nan.frames.copy()
    nan.frames[0, 0, 0, 0] = np.nan
    with pytest.raises(DatasetError, match="NaN"):
        clf.predict(nan)
    single = batch.subset(batch.labels == 0)
    with pytest.raises(DatasetError, match="only one class"):
        ConventionalClassifier(**FAST).fit(single)
    with pytest.raises(InvalidArgumentError, match="unknown classifier kind"):
        ConventionalClassifier(kind="forest").fit(train)
    with pytest.raises(InvalidArgumentError, match="unknown kinesthetic cue"):
        conventional_pipeline(cue="colour")


def test_cross_validate_matches_sklearn():
    batch = small_batch().subset(np.arange(0, 80, 2))  # 40 sequences, 10 per class: two folds of 20
    clf = ConventionalClassifier(kind="knn", **FAST)
    scores = cross_validate(clf, batch, folds=2, seed=3)
    assert scores.shape == (2,) and ((0 <= scores) & (scores <= 1)).all()
    # Peer: scikit-learn's own cross_val_score of the array half of the pipeline, same folds.
    features = sequence_features(batch, clf.cue)
    cv = StratifiedKFold(2, shuffle=True, random_state=3)
    ref = cross_val_score(clf.make_pipeline(batch.labels[:20])[1:], features, batch.labels, cv=cv)
    np.testing.assert_allclose(scores, ref)
    with pytest.raises(DatasetError, match="sequences per class"):
        cross_validate(clf, batch.subset(np.arange(0, 40, 4)), folds=5)


@pytest.mark.slow
def test_som_to_5_against_pca_to_5():
    """Our reading of "SOM to 5" against PCA to 5 on the same splits (10 classes x 3 objects x 20 blind contours,
    the paper's normals cue, 3 splits 80/20). Both must recognise far above chance (10 %). SOM is *not* at least as
    accurate as PCA here (measured 2026-11-25: SVM 74.4 % vs 78.6 %, kNN 69.7 % vs 71.1 %), so that claim is not
    asserted: it was an ``xfail(strict=False)`` that could not fail (and had stopped running at all: its features
    did not match the classifier's default cue)."""
    from perception.shapes import CLASSES, make_object
    from tactile.explore import SequenceBatch
    from tactile.sampling import explore_object
    from tactile.sensor import FSRSensor

    sensor = FSRSensor()
    sequences = []
    for c, name in enumerate(CLASSES):
        for o in range(3):
            sequences += explore_object(make_object(name, 1000 * c + o), "blind", 20, sensor=sensor, seed=7 * o + c)
    batch = SequenceBatch.from_sequences(sequences, CLASSES, sensor_spec=sensor.spec())
    features, y = sequence_features(batch, "normals"), batch.labels
    accuracy = {}
    for seed in range(3):  # 80/20 by sequence, stratified
        test = np.zeros(len(y), dtype=bool)
        for label in np.unique(y):
            members = np.random.default_rng(seed).permutation(np.flatnonzero(y == label))
            test[members[: len(members) // 5]] = True
        for reduce in ("som", "pca"):
            for kind in ("svm", "knn"):
                tail = ConventionalClassifier(kind=kind, reduce=reduce, cue="normals").make_pipeline(y[~test])[1:]
                tail.fit(features[~test], y[~test])
                accuracy.setdefault((reduce, kind), []).append(np.mean(tail.predict(features[test]) == y[test]))
    for kind in ("svm", "knn"):
        som, pca = np.mean(accuracy[("som", kind)]), np.mean(accuracy[("pca", kind)])
        print(f"{kind}: SOM {som:.3f}, PCA {pca:.3f}")
        assert som > 0.5 and pca > 0.5, f"{kind}: SOM {som:.3f}, PCA {pca:.3f}"  # 10 classes: chance is 10 %


# ------------------------------------------------------------------------------ pipeline search
@pytest.fixture(scope="module")
def searched():
    """kNN with the grouped search, trained on 4/5 of the small batch (2 objects per class)."""
    train, test = _split(small_batch())
    return ConventionalClassifier(kind="knn", som_iterations=300, search="objects").fit(train), train, test


def test_search_scores_are_grouped_cross_validation_over_training_objects(searched):
    clf, train, _ = searched
    search = clf.search_
    assert len(search["scores"]) == len(SEARCH_GRID["knn"]) and search["chosen"] == int(np.argmax(search["scores"]))
    # scikit-learn's own cross-validation of each candidate, folds of whole objects, gives the same scores
    features = sequence_features(train, "invariant")
    # two objects per class: two grouped folds (the most that leave every class on both sides)
    folds = StratifiedGroupKFold(2, shuffle=True, random_state=0).split(features, train.labels, train.object_ids)
    folds = list(folds)
    for candidate, score in enumerate(search["scores"]):
        tail = clf.make_pipeline(train.labels, candidate)[1:]
        expected = cross_val_score(tail, features, train.labels, cv=folds).mean()
        assert score == pytest.approx(expected, abs=1e-6)
    for train_idx, test_idx in folds:  # no object on both sides of an inner fold
        assert not set(train.object_ids[train_idx]) & set(train.object_ids[test_idx])
    chosen = SEARCH_GRID["knn"][search["chosen"]]
    assert ("reduce" in clf.pipeline_.named_steps) == (chosen.get("reduce", "som") != "none")


def test_search_survives_save_and_load_and_refuses_a_foreign_choice(searched, tmp_path):
    from fusion.modelfile import read_model_file, write_model_file
    from perception.errors import ModelFileError

    clf, _, test = searched
    path = clf.save(tmp_path / "knn.vtm")
    assert load_model(path).predict_proba(test).tobytes() == clf.predict_proba(test).tobytes()
    description, arrays = read_model_file(path)

    def plant(node):  # the stored choice -> a candidate that does not exist
        if isinstance(node, dict):
            if "chosen" in node:
                node["chosen"] = len(SEARCH_GRID["knn"]) + 3
                return True
            return any(plant(v) for v in node.values())
        return isinstance(node, list) and any(plant(v) for v in node)

    assert plant(description)
    write_model_file(tmp_path / "bad.vtm", description, arrays)
    with pytest.raises(ModelFileError, match="search"):
        load_model(tmp_path / "bad.vtm")


def test_search_falls_back_to_the_configured_pipeline_with_one_object_per_class():
    batch = small_batch()
    one = batch.subset(np.isin(batch.object_ids, [i for i in np.unique(batch.object_ids) if i % 2 == 0]))
    clf = ConventionalClassifier(kind="knn", som_iterations=300, n_select=30).fit(one)
    assert clf.search_ is None and "reduce" in clf.pipeline_.named_steps


@pytest.mark.parametrize("search", [None, "objects"])
def test_a_refit_learns_the_new_batch_only(search):
    """Fitting a fitted classifier again on another batch gives the model a fresh classifier fits on that batch
    (nothing of the first batch, e.g. its wavelet statistics, is reused)."""
    from tests.fusion._synthetic import circle_batch

    first = circle_batch([10, 11, 12, 20, 21, 22], labels=[0, 0, 0, 1, 1, 1], seed=1)
    second = circle_batch([10, 11, 20, 21, 30, 31, 40, 41], labels=[0, 0, 1, 1, 0, 0, 1, 1], seed=2)
    params = {"kind": "knn", "som_iterations": 100, "n_select": 10, "search": search}
    again = ConventionalClassifier(**params).fit(first).fit(second)
    fresh = ConventionalClassifier(**params).fit(second)
    assert again.predict_proba(second).tobytes() == fresh.predict_proba(second).tobytes()
    assert again.predict_proba(first).tobytes() == fresh.predict_proba(first).tobytes()


def test_search_with_one_sequence_per_object_uses_folds_it_can_fill():
    from tests.fusion._synthetic import circle_batch

    batch = circle_batch([10, 11, 20, 21, 30, 31], labels=[0, 0, 1, 1, 2, 2], seed=0)  # 2 objects per class
    knn = ConventionalClassifier(kind="knn", som_iterations=100, n_select=10).fit(batch)
    assert len(knn.search_["scores"]) == len(SEARCH_GRID["knn"])  # two grouped folds, each class on both sides
    # the SVM's Platt folds need two sequences of each class in every inner training fold: no search
    svm = ConventionalClassifier(kind="svm", som_iterations=100, n_select=10).fit(batch)
    assert svm.search_ is None and "reduce" in svm.pipeline_.named_steps
