"""``reproduce --outliers``: the calibration and open-set parts' CNNs train with outlier exposure on a store of the
given objects' touches; the other classifiers and a run without outliers are as before."""

from __future__ import annotations

from pathlib import Path

import pytest

from fusion.commands.reproduce import outlier_objects
from fusion.experiments.context import Context
from fusion.experiments.models import default_classifiers
from fusion.experiments.openset import exposed
from perception.errors import DatasetError
from tactile.dataset import open_dataset
from tests.fusion.test_experiments import OPEN_SET_SIZES, open_set_data  # noqa: F401 -- a fixture


def test_the_cnn_factories_get_a_store_of_the_outliers_touches_and_the_others_stay(tmp_path):
    factories = {name: f for name, f in default_classifiers(0, 1, threads=1).items() if name in ("cnn", "knn")}
    ctx = Context(tmp_path, 0, OPEN_SET_SIZES, factories, progress=False, workers=1)
    assert exposed(ctx, factories) == factories  # no outliers: the factories as they are
    ctx.outliers = [("spoon", 0), ("hammer", 1)]
    made = exposed(ctx, factories)
    assert made["knn"] is factories["knn"]
    cnn, plain = made["cnn"](), factories["cnn"]()
    assert plain.outliers is None and Path(cnn.outliers).parent == tmp_path / "stores"
    assert {k: v for k, v in cnn.get_params().items() if k != "outliers"} == {
        k: v for k, v in plain.get_params().items() if k != "outliers"}
    store = open_dataset(cnn.outliers)
    assert len(store.object_names) == 2 and len(store) == 2 * OPEN_SET_SIZES.unseen_contours
    assert list(store.sequence_strategies) == [OPEN_SET_SIZES.calibration_strategy] * len(store)


def test_outlier_paths_are_mesh_files_or_folders_of_them(tmp_path):
    """Listed by name (each is read when its store is made): a folder's mesh files in sorted order, then a file."""
    folder = tmp_path / "things"
    folder.mkdir()
    for name in ("b.off", "a.obj", "notes.txt"):
        (folder / name).write_text("x")
    single = tmp_path / "c.ply"
    single.write_text("x")
    assert outlier_objects([str(folder), str(single)]) == [
        (str(folder / "a.obj"), "outlier"), (str(folder / "b.off"), "outlier"), (str(single), "outlier")]
    empty = tmp_path / "empty"
    empty.mkdir()
    for bad, words in ((empty, "holds no mesh"), (folder / "notes.txt", "not a mesh file"),
                       (tmp_path / "missing.obj", "not a mesh file")):
        with pytest.raises(DatasetError, match=words):
            outlier_objects([str(bad)])


def test_no_outlier_store_is_made_that_no_model_reads(tmp_path):
    """With only classifiers that are not CNNs nothing reads an outlier store, so none is made."""
    from tests.fusion.test_experiments import EmbeddingMean

    factories = {"em": EmbeddingMean}
    ctx = Context(tmp_path, 0, OPEN_SET_SIZES, factories, progress=False, workers=1, outliers=[("spoon", 0)])
    assert exposed(ctx, factories) == factories and not (tmp_path / "stores").exists()


def test_the_report_names_the_outliers_and_a_bad_path_is_refused_in_one_line(tmp_path, open_set_data, capsys):  # noqa: F811
    from fusion.cli import main
    from fusion.experiments import reproduce
    from tests.fusion.test_experiments import EmbeddingMean, with_stores

    data, stores = open_set_data
    out = with_stores(tmp_path / "report", stores)
    results = reproduce(data, out, sizes=OPEN_SET_SIZES, classifiers={"em": EmbeddingMean}, parts=("openset",),
                        workers=2, progress=False, outliers=[("spoon", 0), ("hammer", 0)])
    assert results["openset"]["outliers"] == 2
    assert "outlier exposure on the touches of 2 objects" in (out / "report.md").read_text()
    assert main(["reproduce", "--data", str(data), "--out", str(tmp_path / "r2"), "--parts", "openset",
                 "--outliers", str(tmp_path / "nothing.obj")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing.obj" in err[0] and "not a mesh file" in err[0], err


def test_a_run_with_outliers_does_not_reuse_the_parts_of_a_run_without(tmp_path, open_set_data, monkeypatch):  # noqa: F811
    """The parts' record names the outliers: parts cached without them are computed again with them."""
    from fusion.experiments import openset, reproduce
    from tests.fusion.test_experiments import EmbeddingMean, with_stores

    data, stores = open_set_data
    out = with_stores(tmp_path / "report", stores)
    calls = []
    real = openset.openset_part
    monkeypatch.setattr(openset, "openset_part", lambda ctx, objects: calls.append(ctx.outliers) or real(ctx, objects))
    run = {"sizes": OPEN_SET_SIZES, "classifiers": {"em": EmbeddingMean}, "parts": ("openset",), "workers": 2,
           "progress": False}
    reproduce(data, out, **run)
    reproduce(data, out, **run)  # cached
    reproduce(data, out, **run, outliers=[("spoon", 0)])
    assert calls == [None, [("spoon", 0)]]
