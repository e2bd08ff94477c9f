"""The demo's recognition part (stand-in classifier, few objects) and, slow, the whole demo."""

from __future__ import annotations

import json

import pytest

from fusion.demo import DEMO_SIZES, check_demo_sizes, run_demo, run_recognition
from fusion.experiments.analysis import TOUCH_REPEATS
from perception.errors import InvalidArgumentError
from tests.fusion.test_experiments import STANDINS

PNG = b"\x89PNG\r\n\x1a\n"


def test_demo_recognition_trains_tests_and_saves_models(tmp_path):
    lines: list[str] = []
    sizes = DEMO_SIZES.with_(objects_per_class=2, unseen_contours=8, touches=(1, 2, 4), unseen_classifiers=("nm",),
                             strategies=("blind",))
    result = run_recognition(tmp_path, 0, sizes, {"nm": STANDINS["nm"]}, classes=["box", "ring"],
                       workers=2, progress=False, echo=lines.append)
    (row,) = result["table"]
    assert set(row) == {"classifier", "sequence blind", "unseen blind", "paper guided / blind"}
    # 2 classes x 2 instances: one per class is unseen; 20 % of the other's 8 contours are the by-sequence test.
    assert result["objects"] == ["box/0", "box/1", "ring/0", "ring/1"]
    ks = {(r["k"], r["rule"]) for r in result["touches"]}
    assert ks == {(k, rule) for k in (1, 2, 4) for rule in ("log", "sum")}
    # K > 1: each of the 10 cuts of an object's 8 sequences gives 8 // K decisions (K = 1: each sequence once)
    assert all(r["accuracy"]["n"] == 2 * 8 // r["k"] * (1 if r["k"] == 1 else TOUCH_REPEATS) for r in result["touches"])
    assert result["models"] == ["models/blind/nm.vtm"]
    for name in result["figures"]:
        assert (tmp_path / name).read_bytes()[:8] == PNG
    assert any("Test accuracy" in line for line in lines)


def test_demo_sizes_refuse_too_few_objects():
    with pytest.raises(InvalidArgumentError, match="at least 2 objects per class"):
        check_demo_sizes(DEMO_SIZES.with_(objects_per_class=1))
    with pytest.raises(InvalidArgumentError, match="largest K"):
        check_demo_sizes(DEMO_SIZES.with_(unseen_contours=4, touches=(1, 8)))


@pytest.mark.slow
def test_whole_demo_with_a_stand_in_classifier(tmp_path):
    sizes = DEMO_SIZES.with_(objects_per_class=2, unseen_contours=8, touches=(1, 2), unseen_classifiers=("nm",))
    summary = run_demo(tmp_path, seed=0, sizes=sizes, classifiers={"nm": STANDINS["nm"]}, workers=2,
                       progress=False, echo=lambda line: None)
    assert summary["figures"][:4] == ["catalogue.png", "saliency.png", "contour_blind.png", "contour_guided.png"]
    assert "accuracy_vs_k.png" in summary["figures"]
    assert {"confusion_unseen_guided_nm.png", "confusion_unseen_blind_nm.png"} <= set(summary["figures"])
    for name in summary["figures"]:
        assert (tmp_path / name).read_bytes()[:8] == PNG
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["recognition"]["models"] == ["models/blind/nm.vtm", "models/nm.vtm"]
    report = (tmp_path / "report.md").read_text()
    assert "## Recognition" in report and "](accuracy_vs_k.png)" in report
