"""The active-touch experiment's scoring: paired differences over objects, accuracy against K, touches to reach
90 % and the stopping rule, on hand-made episodes with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.experiments.active import paired_over_objects, render_markdown, summarize
from perception.errors import InvalidArgumentError


def _policy(decisions, top):
    return {"decisions": decisions, "posteriors": [[p, 1 - p] for p in top], "planning_s": [0.2, 0.01],
            "touching_s": [0.05, 0.05], "classifying_s": [0.01, 0.01], "missed": 0, "classes": ["a", "b"]}


def episodes():
    # 10 objects of class "a": random is right after 2 touches on 5 of them, information on all 10 (9 after 1).
    rows = []
    for i in range(10):
        rows.append({"object": f"o{i}", "label": "a", "fold": 1, "policies": {
            "random": _policy(["b", "a" if i < 5 else "b"], [0.6, 0.8]),
            "information": _policy(["a" if i else "b", "a"], [0.95 if i else 0.6, 0.995])}})
    return {"objects": rows, "classifier": "svm", "noise_mm": 1.0, "candidates": 4, "variants": 1, "max_touches": 2}


def test_paired_over_objects():
    a, b = np.array([1.0, 1.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0, 0.0])
    result = paired_over_objects(a, b)
    assert result["difference"] == pytest.approx(0.5) and result["n_objects"] == 4
    assert 0.0 <= result["low"] <= 0.5 <= result["high"] <= 1.0
    same = paired_over_objects(a, a)
    assert same["low"] == same["high"] == same["difference"] == 0.0
    with pytest.raises(InvalidArgumentError):
        paired_over_objects(a, b[:3])


def test_summary_known_answers():
    summary = summarize(episodes())
    acc = {(r["policy"], r["k"]): r["accuracy"]["value"] for r in summary["curve"]}
    assert acc == {("random", 1): 0.0, ("random", 2): 0.5, ("information", 1): 0.9, ("information", 2): 1.0}
    assert summary["touches_to_90"] == {"random": None, "information": 1}
    diff = {d["k"]: d for d in summary["differences"]}
    assert diff[1]["difference"] == pytest.approx(0.9) and diff[2]["difference"] == pytest.approx(0.5)
    assert diff[2]["low"] > 0
    stop = {(s["policy"], s["threshold"]): s for s in summary["stopping"]}
    # Threshold 0.9: information stops after 1 touch on 9 objects (right), after 2 on one (right).
    assert stop[("information", 0.9)]["mean_touches"] == pytest.approx(1.1)
    assert stop[("information", 0.9)]["accuracy"] == 1.0
    assert stop[("random", 0.9)]["mean_touches"] == 2.0 and stop[("random", 0.9)]["accuracy"] == 0.5
    timing = {t["policy"]: t for t in summary["timing"]}
    assert timing["random"]["planning_first_s"] == pytest.approx(0.2)
    assert timing["random"]["step_mean_s"] == pytest.approx((0.26 + 0.07) / 2)
    assert "| information | 1 | +90.0 |" in render_markdown(summary)


def test_reproduce_part_options():
    """The ``active`` reproduce part: its sizes are active_part's keywords, quick is smaller, the report renders it."""
    import inspect

    from fusion.experiments.active import active_episodes
    from fusion.experiments.config import FULL, QUICK
    from fusion.experiments.reproduce import DEFAULT_PARTS, PARTS

    assert "active" in PARTS and "active" not in DEFAULT_PARTS
    keywords = set(inspect.signature(active_episodes).parameters)
    assert set(FULL.active_options()) <= keywords
    assert QUICK.active_options()["candidates"] < FULL.active_options()["candidates"]
    from fusion.experiments.report import render

    text = render({"command": "c", "data": "d", "date": "t", "machine": "m", "seed": 0, "bootstrap": "b", "sizes": {},
                   "active": summarize(episodes())})
    assert "## Active touch" in text and "| information | 1 | +90.0 |" in text


@pytest.mark.slow
def test_reproduce_runs_the_active_part(tmp_path):
    """End to end through ``reproduce(parts=("active",))`` on tiny sizes with a stand-in classifier."""
    from fusion.experiments.reproduce import reproduce
    from tests.fusion.test_experiments import STANDINS, TINY, mesh_folder

    sizes = TINY.with_(active_policies=("random", "information"), active_touches=2, active_candidates=3,
                       active_variants=1)
    results = reproduce(mesh_folder(tmp_path / "meshes"), tmp_path / "report", sizes=sizes, classifiers=STANDINS,
                        parts=("active",), workers=1, progress=False)
    summary = results["active"]
    assert summary["classifier"] == "nm" and summary["n_objects"] >= 6
    assert {(r["policy"], r["k"]) for r in summary["curve"]} == {(p, k) for p in ("random", "information")
                                                                   for k in (1, 2)}
    assert "## Active touch" in (tmp_path / "report" / "report.md").read_text()


def test_capture_batch_touches_what_the_camera_saw(tmp_path, monkeypatch):
    """Training touches for the camera in the loop lie on each training object's reconstruction (smoothed as the
    planner smooths), not on its mesh; they carry the object's class; an object the camera cannot see is left out."""
    from types import SimpleNamespace

    from fusion.active.policies import smoothed
    from fusion.experiments import active
    from fusion.experiments.config import QUICK
    from fusion.experiments.context import Context
    from perception.errors import InvalidMeshError
    from tactile.dataset import ObjectSpec
    from tactile.sensor import FSRSensor

    ctx = Context(tmp_path, 0, QUICK, {}, progress=False)
    specs = {name: ObjectSpec(name, label, catalogue=(label, 0)) for name, label in
             (("mug/0", "mug"), ("box/0", "box"), ("can/0", "can"))}
    sensor = FSRSensor(rows=8, cols=8)
    store = SimpleNamespace(class_names=("box", "can", "mug"), sensor_spec=sensor.spec())
    real = active.camera_models

    def camera(ctx, spec, true, seed):
        if spec.name == "can/0":
            raise InvalidMeshError("can/0: no object on the table")
        return real(ctx, spec, true, seed)

    monkeypatch.setattr(active, "camera_models", camera)
    batch = active.capture_batch(ctx, ["mug/0", "box/0", "can/0"], specs, store, sensor, 8, 3, 2)
    assert len(batch) == 6 and batch.object_names == ("mug/0@capture", "box/0@capture")
    assert [batch.class_names[k] for k in batch.labels] == ["mug"] * 3 + ["box"] * 3
    for k, name in enumerate(("mug/0", "box/0")):
        seen, true = real(ctx, specs[name], specs[name].load(), 0)  # cached: the same capture
        rows = batch.object_ids == k
        points = batch.positions[rows].reshape(-1, 3).astype(np.float64)  # the table's frame, mm
        surface = smoothed(seen, 2)
        on_seen = surface.scene.compute_distance(surface.to_scene(points).astype(np.float32)).numpy()
        on_true = true.scene.compute_distance(true.to_scene(points).astype(np.float32)).numpy()
        assert on_seen.max() < 1e-3  # probes sit on the surface the camera saw
        assert on_true.max() > 0.1  # ... which is not the object's own surface


def test_summary_averages_the_episodes_of_each_object():
    """With several episodes per object, an object's accuracy is the share of its episodes that are right, the
    paired difference pairs those shares, and the stopping rule counts every episode."""
    result = episodes()
    for i, row in enumerate(result["objects"]):
        # A second random episode per object: right after 2 touches on o5..o9 instead of o0..o4, and after 1 on o0.
        row["policies"]["random"]["more_runs"] = [_policy(["a" if i == 0 else "b", "a" if i >= 5 else "b"],
                                                          [0.95 if i == 0 else 0.6, 0.8])]
    result["episodes"] = 2
    summary = summarize(result)
    acc = {(r["policy"], r["k"]): r["accuracy"] for r in summary["curve"]}
    assert acc[("random", 1)]["value"] == pytest.approx(0.05) and acc[("random", 2)]["value"] == pytest.approx(0.5)
    assert acc[("random", 2)]["n"] == 20  # every episode is one decision ...
    # ... but the interval resamples objects: each object's two episodes give 1/2 at K = 2, so it cannot move.
    assert acc[("random", 2)]["low"] == acc[("random", 2)]["high"] == pytest.approx(0.5)
    diff = {d["k"]: d for d in summary["differences"]}
    assert diff[1]["difference"] == pytest.approx(0.9 - 0.05) and diff[2]["difference"] == pytest.approx(0.5)
    stop = {(s["policy"], s["threshold"]): s for s in summary["stopping"]}
    # Threshold 0.9: o0's second random episode stops after 1 touch (right); the other 19 episodes use both.
    assert stop[("random", 0.9)]["mean_touches"] == pytest.approx(39 / 20)
    assert stop[("random", 0.9)]["accuracy"] == pytest.approx(11 / 20)
    assert summary["episodes_per_object"] == 2 and "2 episodes per object" in render_markdown(summary)
    # active_part adds the path of the episodes file under "episodes": the report still renders.
    assert "2 episodes per object" in render_markdown({**summary, "episodes": "parts/active.json"})


def test_part_names_tell_runs_apart():
    from fusion.experiments.active import part_suffix

    names = {part_suffix(v, c, k) for v in ("noisy", "camera") for c in (False, True) for k in (None, "cnn", "knn")
             if not (c and v == "noisy")}
    assert len(names) == 9  # every run its own files: no run's cached episodes overwrite another's
    assert part_suffix("noisy", False) == "" and part_suffix("camera", True, "cnn") == "_camera_captures_cnn"
