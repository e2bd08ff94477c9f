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


def test_catalogue_items_name_built_in_shapes_by_class_and_count(tmp_path):
    """``catalogue:CLASS[,CLASS...][:N]``: N seeds 0..N-1 of each class (3 without N), in the order given, beside
    mesh paths."""
    from fusion.commands.reproduce import CATALOGUE_OUTLIERS

    mesh = tmp_path / "a.obj"
    mesh.write_text("x")
    assert outlier_objects(["catalogue:spoon,box:2", str(mesh), "catalogue:ring"]) == [
        ("spoon", 0), ("spoon", 1), ("box", 0), ("box", 1), (str(mesh), "outlier"),
        *[("ring", i) for i in range(CATALOGUE_OUTLIERS)]]
    assert CATALOGUE_OUTLIERS == 3


@pytest.mark.parametrize("item, words", [
    ("catalogue:", "expected catalogue:CLASS"), ("catalogue:spoon:2:3", "expected catalogue:CLASS"),
    ("catalogue:teapot", "teapot"), ("catalogue:spoon,spoon", "named twice"), ("catalogue:spoon:0", "positive"),
    ("catalogue:spoon:-1", "positive"), ("catalogue:spoon:x", "positive"), ("catalogue:spoon:²", "positive"),
    ("catalogue:spoon:" + "9" * 5000, "too large"), ("catalogue:spoon:99999999", "objects"),
    ("x" * 5000, "not a mesh file"),
])
def test_a_bad_catalogue_item_is_refused_naming_it(item, words):
    from perception.errors import VisuotactileError

    with pytest.raises(VisuotactileError, match=words) as caught:  # a path's error is a DatasetError
        outlier_objects([item])
    assert item[:40] in str(caught.value) and len(str(caught.value)) < 500


def test_the_command_line_refuses_a_bad_catalogue_item_in_one_line(tmp_path, capsys):
    from fusion.cli import main

    assert main(["reproduce", "--data", str(tmp_path), "--out", str(tmp_path / "r"), "--parts", "openset",
                 "--outliers", "catalogue:spoon,teapot:2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "catalogue:spoon,teapot:2" in err[0] and "teapot" in err[0], err
    assert not (tmp_path / "r" / "stores").exists()


def test_a_catalogue_count_of_one_is_seed_zero_alone():
    assert outlier_objects(["catalogue:box:1"]) == [("box", 0)]
    assert outlier_objects(["catalogue:box:002"]) == [("box", 0), ("box", 1)]


@pytest.mark.parametrize("item, words", [
    ("catalogue:box,", "unknown catalogue classes"), ("catalogue:,box", "unknown catalogue classes"),
    ("catalogue:BOX", "BOX"), ("catalogue:box, spoon", "' spoon'"),
    ("catalogue:spoon,box,spoon", "named twice"),  # not side by side
    ("catalogue:box:\u0663", "positive"),  # Arabic-Indic 3: a decimal digit to \d and to int()
    ("catalogue:box:\uff13", "positive"),  # full-width 3
    ("catalogue:box:", "positive"), ("catalogue:box:000", "positive"),
    ("catalogue:box:9999999999", "too large"), ("catalogue:box:" + "9" * 5000, "too large"),
])
def test_more_bad_catalogue_items_are_refused_naming_them(item, words):
    from perception.errors import InvalidArgumentError

    with pytest.raises(InvalidArgumentError, match=words) as caught:
        outlier_objects([item])
    assert f"--outliers {item[:40]}" in str(caught.value) and len(str(caught.value)) < 500


def test_a_malformed_catalogue_item_lists_the_classes():
    from perception.errors import InvalidArgumentError

    with pytest.raises(InvalidArgumentError, match="classes: bottle, bowl, box"):
        outlier_objects(["catalogue::3"])


@pytest.mark.parametrize("item", ["catalogue", "Catalogue:box", "catalogues:box"])
def test_only_the_exact_prefix_is_a_catalogue_item(tmp_path, monkeypatch, item):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(DatasetError, match=r"not a mesh file .*catalogue:CLASS\[,CLASS\.\.\.\]\[:N\]"):
        outlier_objects([item])


def test_a_file_named_like_a_catalogue_item_is_refused_unless_written_as_a_path(tmp_path, monkeypatch):
    from perception.errors import InvalidArgumentError

    monkeypatch.chdir(tmp_path)
    (tmp_path / "catalogue:box.obj").write_text("x")
    (tmp_path / "catalogue:spoon").mkdir()
    (tmp_path / "catalogue:spoon" / "a.obj").write_text("x")
    assert outlier_objects(["./catalogue:box.obj"]) == [("catalogue:box.obj", "outlier")]
    for item in ("catalogue:box.obj", "catalogue:spoon"):
        with pytest.raises(InvalidArgumentError, match=f"write ./{item}"):
            outlier_objects([item])


def test_items_may_be_paths_and_an_empty_item_is_refused(tmp_path):
    mesh = tmp_path / "a.obj"
    mesh.write_text("x")
    assert outlier_objects([Path(mesh)]) == [(str(mesh), "outlier")]
    with pytest.raises(DatasetError, match="empty item"):
        outlier_objects([""])


@pytest.mark.parametrize("items", [["catalogue:box", "catalogue:box:5"], ["catalogue:box", "catalogue:spoon,box:1"]])
def test_an_object_named_by_two_items_is_refused_before_any_work(items):
    with pytest.raises(DatasetError, match="--outliers.*box/0"):
        outlier_objects(items)


def test_the_same_mesh_name_from_two_folders_is_refused(tmp_path):
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "x.obj").write_text("x")
    with pytest.raises(DatasetError, match="--outliers.*x"):
        outlier_objects([str(tmp_path / "a"), str(tmp_path / "b" / "x.obj")])


def test_the_object_limit_counts_every_item_together(monkeypatch):
    from perception.errors import InvalidArgumentError

    monkeypatch.setenv("VISUOTACTILE_MAX_OBJECTS", "5")
    assert len(outlier_objects(["catalogue:box:2", "catalogue:spoon:3"])) == 5
    with pytest.raises(InvalidArgumentError, match="--outliers: 6 objects"):
        outlier_objects(["catalogue:box:3", "catalogue:spoon:3"])


def test_a_long_missing_path_is_cut_in_the_middle_keeping_its_file_name(tmp_path):
    long = str(tmp_path / ("d" * 200) / ("e" * 200) / "nothing.obj")
    with pytest.raises(DatasetError, match="not a mesh file") as caught:
        outlier_objects([long])
    message = str(caught.value)
    assert long[:60] in message and message.split(":")[0].endswith("nothing.obj") and "..." in message
    assert len(message) < 300
