"""``visuotactile recognize``: a mesh file -> class, probabilities, touched contours (with a stand-in model)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fusion.cli import main
from fusion.experiments.recognize import recognize
from fusion.experiments.touch import touch_objects
from perception.geometry import load_object
from perception.shapes import make_object
from tests.fusion.test_experiments import NearestMean, write_off


@pytest.fixture(scope="module")
def model_and_meshes(tmp_path_factory):
    root = tmp_path_factory.mktemp("recognize")
    objects = [make_object(c, s) for c in ("box", "can") for s in range(3)]
    batch = touch_objects(objects, ["box", "can"], "blind", 6, probes=10, seed=0)
    model = NearestMean().fit(batch)
    path = model.save(root / "model.vtm")
    # Instances never seen in training.
    meshes = {c: write_off(make_object(c, 11), root / f"{c}.off") for c in ("box", "can")}
    return path, meshes, root


@pytest.mark.parametrize("cls", ["box", "can"])
def test_recognize_json_is_the_librarys_decision_fused_by_the_log_rule(model_and_meshes, cls, capsys):
    """The command passes mesh, model, touches, strategy and seed through: its JSON is what the library gives
    on the same file, and its label is the argmax of the summed log-probabilities of its own touches (the
    stand-in classifier is too weak for the class itself to be a stable check; real classifiers' accuracy on
    unseen instances is measured by ``benchmarks.camera_recognition`` and ``reproduce``)."""
    from fusion.base import load_model

    path, meshes, root = model_and_meshes
    figure = root / f"{cls}.png"
    rc = main(["recognize", str(meshes[cls]), "--model", str(path), "--touches", "4", "--strategy", "blind",
               "--seed", "3", "--json", "--figure", str(figure)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    out = json.loads(captured.out)
    expected = recognize(load_model(path), load_object(meshes[cls]), touches=4, strategy="blind", seed=3)
    assert len(out["per_touch"]) == 4 and out["rule"] == "log"
    # Two classes: each touch's (label, top probability) gives its whole probability vector back.
    per_touch = np.array([[t["probability"], 1 - t["probability"]][:: 1 if t["label"] == "box" else -1]
                          for t in out["per_touch"]])
    assert np.allclose(per_touch, expected.per_touch, atol=2e-6)
    assert out["label"] == expected.label == ["box", "can"][int(np.argmax(np.log(per_touch).sum(axis=0)))]
    assert set(out["probabilities"]) == {"box", "can"}
    assert sum(out["probabilities"].values()) == pytest.approx(1.0, abs=1e-5)
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_recognize_is_seeded_and_uses_the_models_sensor(model_and_meshes):
    path, meshes, _ = model_and_meshes
    from fusion.base import load_model

    model = load_model(path)
    obj = load_object(meshes["can"])
    a = recognize(model, obj, touches=3, strategy="blind", seed=1)
    b = recognize(model, obj, touches=3, strategy="blind", seed=1)
    c = recognize(model, obj, touches=3, strategy="blind", seed=2)
    assert np.array_equal(a.per_touch, b.per_touch)
    assert not np.array_equal(a.per_touch, c.per_touch)
    assert all(contour.n_probes == model.probes == 10 for contour in a.contours)
    assert a.seconds["saliency"] == 0.0  # blind touching never computes saliency


def test_recognize_errors_are_one_line_and_exit_2(model_and_meshes, tmp_path, capsys):
    path, meshes, _ = model_and_meshes
    assert main(["recognize", str(meshes["box"]), "--model", str(tmp_path / "none.vtm")]) == 2
    assert "no model there" in capsys.readouterr().err
    assert main(["recognize", str(tmp_path / "missing.off"), "--model", str(path)]) == 2
    assert "missing.off" in capsys.readouterr().err
    assert main(["recognize", str(meshes["box"]), "--model", str(path), "--touches", "0"]) == 2
    assert "argument --touches/-k: must be a positive integer" in capsys.readouterr().err


def test_recognize_refuses_an_unknown_strategy_before_loading_anything(tmp_path, capsys):
    """An unknown strategy is one line on stderr and exit 2, even when the model does not exist."""
    assert main(["recognize", str(tmp_path / "absent.off"), "--model", str(tmp_path / "absent.vtm"),
                 "--strategy", "psychic"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown sampling strategy 'psychic'" in err[0]
