"""CNN model files that pass every integrity check (valid checksum, right tensor shapes, finite values) but carry a
hostile constructor parameter or numbers that make prediction non-finite: refused, in one line naming the file."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from fusion.base import load_model
from fusion.cli import main
from fusion.cnn import MAX_THREADS, CNNClassifier
from perception.errors import InvalidArgumentError, ModelFileError
from tactile.dataset import open_dataset
from tests._model_files import rewrite
from tests._small_store import small_store

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return small_store(tmp_path_factory.mktemp("cnn-params") / "small.zarr")


@pytest.fixture(scope="module")
def cnn_file(store, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cnn-params-model") / "cnn.vtm"
    CNNClassifier(epochs=2, batch_size=8, progress=False, threads=1).fit(open_dataset(store).load()).save(path)
    return path




def _param(name, value):
    return lambda d, a: d["params"]["dict"].__setitem__(name, value)


@pytest.mark.parametrize("threads", [10**6, -3, 0.5, "x", [1]])
def test_a_hostile_thread_count_in_a_model_file_is_refused_on_loading(cnn_file, tmp_path, threads):
    """`threads` is not checked by CNNClassifier._check_params. From a model file: 10**6 makes libgomp print
    'Out of memory allocating ...' and exit(1) the whole process at the first predict (a native kill of the
    caller: `visuotactile evaluate` exits 1 with no Python error); -3 gives RuntimeError and 'x' ValueError
    tracebacks. Loading must refuse it (ModelFileError naming the file)."""
    path = rewrite(cnn_file, tmp_path / "m.vtm", _param("threads", threads))
    with pytest.raises(ModelFileError, match="threads") as info:
        load_model(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("threads", [-1, "x"])
def test_a_bad_thread_count_is_an_argument_error(store, threads):
    with pytest.raises(InvalidArgumentError, match="threads"):
        CNNClassifier(epochs=1, batch_size=8, progress=False, threads=threads).fit(open_dataset(store).load())


def test_a_huge_thread_count_in_a_model_file_does_not_kill_evaluate(cnn_file, store, tmp_path):
    """The native kill, end to end (in a child process: it would take pytest down with it)."""
    path = rewrite(cnn_file, tmp_path / "m.vtm", _param("threads", 10**6))
    script = textwrap.dedent(f"""
        import sys
        from fusion.cli import main
        sys.exit(main(["evaluate", "--model", {str(path)!r}, "--store", {str(store)!r}, "--no-progress"]))
    """)
    proc = subprocess.run([sys.executable, "-c", script], check=False, cwd=ROOT, capture_output=True, text=True,
                          timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-1000:])
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0], err


def _array(name, fill):
    return lambda d, a: a.__setitem__(name, np.full_like(a[name], fill))


HOSTILE_NUMBERS = {
    "negative batch-norm variance": _array("cutaneous.bn1.running_var", -1.0),
    "weights near float32 max": _array("kinesthetic.fc1.weight", 3e38),
    "zero cue scale": _array("fitted.cue_std_", 0.0),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_NUMBERS))
def test_finite_but_hostile_numbers_are_one_line_not_a_floating_point_traceback(cnn_file, store, tmp_path, capsys,
                                                                                case):
    """Finite values pass the NaN/Inf check on loading, but a negative running variance (sqrt of < 0) or weights
    near the float32 maximum make every probability NaN: predict_proba raises FloatingPointError, which the CLI
    prints as a traceback (exit 1). A zero cue scale is refused for frame_std_ but not cue_std_ (division by zero,
    RuntimeWarning on stderr). Expected: refused on loading, or one line and exit 2 naming the model file."""
    path = rewrite(cnn_file, tmp_path / "m.vtm", HOSTILE_NUMBERS[case])
    capsys.readouterr()
    assert main(["evaluate", "--model", str(path), "--store", str(store), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0], err


@pytest.mark.parametrize("threads", [1, MAX_THREADS])
def test_thread_counts_at_the_bounds_load(cnn_file, tmp_path, threads):
    assert load_model(rewrite(cnn_file, tmp_path / "m.vtm", _param("threads", threads))).threads == threads


def test_a_boolean_thread_count_is_refused_on_loading(cnn_file, tmp_path):
    path = rewrite(cnn_file, tmp_path / "m.vtm", _param("threads", True))
    with pytest.raises(ModelFileError, match="threads"):
        load_model(path)


def test_a_negative_batch_norm_variance_is_refused_on_loading(cnn_file, tmp_path):
    def edit(description, arrays):
        arrays["cutaneous.bn1.running_var"] = np.full_like(arrays["cutaneous.bn1.running_var"], -1.0)

    path = rewrite(cnn_file, tmp_path / "m.vtm", edit)
    with pytest.raises(ModelFileError, match=r"cutaneous\.bn1\.running_var holds negative variances") as info:
        load_model(path)
    assert str(path) in str(info.value)
