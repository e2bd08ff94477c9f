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


def test_demo_calibrates_on_seen_instances_and_scores_the_unseen_ones(tmp_path):
    """Three instances per class: the two seen ones calibrate the classifier (two folds by object), the unseen one
    is scored before and after at K = 1 and the largest K; ECE intervals around their values, a reliability
    figure and its section in the report. With two instances per class the step is skipped, saying so."""
    lines: list[str] = []
    sizes = DEMO_SIZES.with_(objects_per_class=3, unseen_contours=8, touches=(1, 4), unseen_classifiers=("nm",),
                             strategies=("blind",))
    result = run_recognition(tmp_path, 0, sizes, {"nm": STANDINS["nm"]}, classes=["box", "ring", "can"], workers=2,
                             progress=False, echo=lines.append)
    cal = result["calibration"]
    assert [(r["k"], r["variant"]) for r in cal["rows"]] == [(1, "before"), (1, "after"), (4, "before"),
                                                              (4, "after")]
    # the unseen instances: 3 objects x 8 sequences at K = 1, one cut of 8 // 4 groups each at K = 4
    assert [r["n"] for r in cal["rows"]] == [24, 24, 6, 6]
    assert all(0 <= r["low"] <= r["ece"] <= r["high"] <= 1 for r in cal["rows"])
    assert "reliability.png" in result["figures"]
    assert (tmp_path / "reliability.png").read_bytes()[:8] == PNG
    assert any(line.startswith("Calibration of nm") for line in (x.strip() for x in lines))
    skipped: list[str] = []
    result = run_recognition(tmp_path / "two", 0, sizes.with_(objects_per_class=2), {"nm": STANDINS["nm"]},
                             classes=["box", "ring"], workers=2, progress=False, echo=skipped.append)
    assert result["calibration"] is None and any("Calibration skipped" in line for line in skipped)
