"""Hostile options refused as one stderr line and exit 2, before any work: seeds beyond 32 bits (31 for camera),
output places nothing can be written in, a figure of an unknown format, a file where the demo's folder goes,
demo epochs below one."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from fusion.cli import SEED_MAX, main
from perception.errors import InvalidArgumentError
from tests._small_store import small_knn_model, small_store

MESH = ("OFF\n8 6 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n1 0 1\n1 1 1\n0 1 1\n"
        "4 0 3 2 1\n4 4 5 6 7\n4 0 1 5 4\n4 1 2 6 5\n4 2 3 7 6\n4 3 0 4 7\n")
#: A place nothing can be created in, even by root (Linux procfs; a read-only folder does not stop root).
UNWRITABLE = Path("/proc/visuotactile-hostile-test")
needs_proc = pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return small_store(tmp_path_factory.mktemp("cli-args") / "small.zarr")


@pytest.fixture(scope="module")
def model(store, tmp_path_factory) -> Path:
    return small_knn_model(store, tmp_path_factory.mktemp("cli-args-model") / "knn.vtm")


@pytest.fixture
def cube(tmp_path) -> Path:
    path = tmp_path / "cube.off"
    path.write_text(MESH)
    return path


def refused(capsys, argv, *expect) -> str:
    """Run the CLI: exit 2 with exactly one stderr line holding every ``expect``; returns the line."""
    capsys.readouterr()
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, (code, err)
    for text in expect:
        assert text in err[0], err[0]
    return err[0]


# ------------------------------------------------------------------------------------------- seeds
@pytest.mark.parametrize("kind", ["knn", "svm"])
@pytest.mark.parametrize("seed", [2**32, 10**23])
def test_train_seed_beyond_32_bits_is_refused(store, tmp_path, capsys, kind, seed):
    # scikit-learn's seeding raised ValueError ('Seed must be between 0 and 2**32 - 1') as a traceback.
    refused(capsys, ["train", "--store", str(store), "--model", kind, "--out", str(tmp_path / "m.vtm"),
                     "--split", "none", "--seed", str(seed), "--no-progress"], "--seed", str(seed), str(SEED_MAX))
    assert not (tmp_path / "m.vtm").exists()


@pytest.mark.parametrize("kind", ["knn", "svm"])
def test_train_takes_the_largest_seed(store, tmp_path, kind):
    assert main(["train", "--store", str(store), "--model", kind, "--out", str(tmp_path / "m.vtm"), "--split",
                 "none", "--seed", str(SEED_MAX), "--no-progress"]) == 0


@pytest.mark.parametrize("argv", [
    ["generate", "--catalogue", "1", "--classes", "box", "ring", "--out", "{tmp}/s", "--contours", "2"],
    ["evaluate", "--model", "{model}", "--store", "{store}"],
    ["recognize", "{cube}", "--model", "{model}", "--touches", "1", "--strategy", "blind"],
    ["train", "--store", "{store}", "--model", "cnn", "--out", "{tmp}/c.vtm"],
    ["demo", "--out", "{tmp}/demo", "--objects-per-class", "2", "--contours", "8", "--no-recognition"],
    ["reproduce", "--data", "{tmp}", "--out", "{tmp}/r"],
], ids=lambda argv: argv[0])
def test_every_subcommand_refuses_a_seed_beyond_32_bits_first(argv, store, model, cube, tmp_path, capsys):
    values = {"tmp": str(tmp_path), "model": str(model), "store": str(store), "cube": str(cube)}
    argv = [a.format(**values) for a in argv]
    refused(capsys, [*argv, "--seed", str(2**32), "--no-progress"], "--seed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.off"]  # nothing was written


@pytest.mark.parametrize("seed", [2**31, 2**64])
def test_camera_seed_beyond_31_bits_is_refused(tmp_path, capsys, seed):
    # Open3D's o3d.utility.random.seed takes a C int: 2**31 was a TypeError traceback after the capture.
    refused(capsys, ["camera", "--source", "virtual:box", "--views", "1", "--contours", "1", "--out",
                     str(tmp_path / "cam"), "--seed", str(seed), "--no-progress"], "--seed", str(2**31 - 1))
    assert not (tmp_path / "cam").exists()


# ------------------------------------------------------------------------------------------- output places
@needs_proc
def test_train_to_an_unwritable_place_is_refused_before_training(store, capsys):
    refused(capsys, ["train", "--store", str(store), "--model", "knn", "--out", str(UNWRITABLE / "m.vtm"),
                     "--split", "none", "--no-progress"], "--out", str(UNWRITABLE), "cannot write in '/proc'")


@needs_proc
def test_evaluate_figure_in_an_unwritable_place(store, model, capsys):
    refused(capsys, ["evaluate", "--model", str(model), "--store", str(store), "--figure",
                     str(UNWRITABLE / "c.png")], "--figure", str(UNWRITABLE))


@needs_proc
def test_recognize_figure_in_an_unwritable_place(model, cube, capsys):
    refused(capsys, ["recognize", str(cube), "--model", str(model), "--touches", "1", "--strategy", "blind",
                     "--figure", str(UNWRITABLE / "r.png")], "--figure", str(UNWRITABLE))


@needs_proc
@pytest.mark.parametrize("place", [UNWRITABLE / "cam", Path("/sys/visuotactile-hostile-test")])
def test_camera_out_in_an_unwritable_place(capsys, place):
    refused(capsys, ["camera", "--source", "virtual:box", "--views", "1", "--contours", "1", "--out", str(place),
                     "--no-progress"], "--out", str(place))


@needs_proc
@pytest.mark.parametrize("command", [["demo", "--no-recognition"], ["generate", "--catalogue", "1"],
                                     ["reproduce", "--data", "."]], ids=lambda c: c[0])
def test_output_folders_in_an_unwritable_place(capsys, command):
    refused(capsys, [*command, "--out", str(UNWRITABLE / "o"), "--no-progress"], "--out", str(UNWRITABLE))


def test_a_writable_place_is_left_as_it_was(tmp_path, capsys):
    from perception.atomic import check_output_file, check_output_folder

    check_output_file(tmp_path / "a" / "b" / "m.vtm", "--out")
    check_output_folder(tmp_path / "c" / "d", "--out")
    assert list(tmp_path.iterdir()) == []  # the write test leaves nothing behind, creates no folder


# ------------------------------------------------------------------------------------------- names and sizes
def test_recognize_figure_of_an_unknown_format_is_refused_before_touching(model, cube, tmp_path, capsys):
    # matplotlib's ValueError ('Format 'txt' is not supported') came out as a traceback after the touching.
    refused(capsys, ["recognize", str(cube), "--model", str(model), "--touches", "1", "--strategy", "blind",
                     "--figure", str(tmp_path / "r.txt")], "--figure", ".png, .pdf, .svg")


def test_demo_out_is_a_file(tmp_path, capsys):
    target = tmp_path / "a-file"
    target.write_text("x")
    refused(capsys, ["demo", "--out", str(target), "--objects-per-class", "2", "--contours", "8",
                     "--no-recognition", "--no-progress"], "--out", "is a file")
    assert target.read_text() == "x"


@pytest.mark.parametrize("epochs", [0, -1])
def test_demo_epochs_below_one_are_refused_before_any_work(epochs, tmp_path, capsys):
    # --epochs 0 trained the default (an `if epochs` test); -1 was refused by the CNN after the stores were made.
    from fusion.demo import DEMO_SIZES

    with pytest.raises(InvalidArgumentError, match="epochs"):
        replace(DEMO_SIZES, epochs=epochs)
    refused(capsys, ["demo", "--out", str(tmp_path / "demo"), "--epochs", str(epochs), "--no-progress"],
            "--epochs", str(epochs))
    assert not (tmp_path / "demo").exists()


def test_generate_to_an_empty_out_is_refused_as_empty(tmp_path, capsys, monkeypatch):
    """``--out ""`` is an empty path, not the current folder (it was read as ".", and refused as "not a store")."""
    monkeypatch.chdir(tmp_path)
    assert main(["generate", "--catalogue", "2", "--contours", "2", "--out", ""]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out: an empty path" in err[0], err
    assert list(tmp_path.iterdir()) == []
