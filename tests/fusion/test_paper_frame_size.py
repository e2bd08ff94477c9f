"""``benchmarks.classifiers --frame-size N`` reaches the CNNs it fits, and the paper's frame size keys the model cache."""

from __future__ import annotations

import pytest

import fusion.cnn as cnn_module
from tests.fusion.test_cnn import make_batch


@pytest.mark.parametrize("argv,frame_size,features", [
    ([], 16, 1280),  # no option: CNNClassifier's own 16 (16 channels x 5 probes x 4 x 4)
    (["--frame-size", "8"], 8, 320),  # 16 x 5 x 2 x 2
])
def test_benchmark_frame_size_option_reaches_the_fitted_cnn(monkeypatch, capsys, argv, frame_size, features):
    """The benchmark's CNN is built with the frame size asked for (or the classifier's default without the option)
    and its cutaneous net reads frames pooled to that size: 32 x 32 frames, 5 probes, two stride-2 convolutions."""
    import benchmarks.classifiers as bench

    fitted = []

    class Recording(cnn_module.CNNClassifier):
        def fit(self, batch, *args, **kwargs):
            fitted.append(self)
            return super().fit(batch, *args, **kwargs)

    monkeypatch.setattr(cnn_module, "CNNClassifier", Recording)
    monkeypatch.setattr(bench, "catalogue_batch", lambda objects, contours, strategy, seed: make_batch(
        n_per_class=5, grid=(32, 32)))
    assert bench.main(["--quick", "--cues", "normals", "--no-conventional", "--epochs", "1", "--threads", "1",
                       "--repeats", "1", *argv]) == 0
    assert "32 x 32 taxels" in capsys.readouterr().out
    (model,) = fitted
    assert model.frame_size == frame_size
    assert model.cutaneous_net_.fc1.in_features == features


def test_paper_models_cache_record_names_their_frame_size():
    """A paper model cached before PAPER_FRAME_SIZE (pooled to 16) is trained again: the frame size is one of the
    estimator parameters its cache record holds, and 8 and 16 give different records."""
    import functools

    from fusion.experiments.models import PAPER_FRAME_SIZE, default_classifiers, model_record

    paper = default_classifiers(seed=0, epochs=1)["cnn-normals"]
    assert paper().frame_size == PAPER_FRAME_SIZE == 8
    old = functools.partial(paper, frame_size=16)
    assert model_record(paper, {"data": 1}) != model_record(old, {"data": 1})
    assert '"frame_size": 8' in model_record(paper, {"data": 1})["estimator"]


@pytest.mark.parametrize("bad", ["0", "-3", "abc"])
def test_benchmark_refuses_a_frame_size_below_one_before_any_work(capsys, bad):
    """argparse's one-line error (exit 2) naming the option, before any data is built."""
    import benchmarks.classifiers as bench

    with pytest.raises(SystemExit) as stop:
        bench.main(["--quick", "--frame-size", bad])
    assert stop.value.code == 2
    assert "--frame-size" in capsys.readouterr().err
