"""Experiments machinery: Pareto front, K-touch scoring, jitter, caches, and a tiny end-to-end reproduce.

The classifiers here are a small stand-in (:class:`NearestMean`), so the machinery is tested without the
CNN / contourlet pipelines; the real ones are exercised by the lead's full runs.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from fusion.base import TactileClassifier
from fusion.cues import kinesthetic_cues
from fusion.experiments import Sizes, reproduce
from fusion.experiments.analysis import (
    TOUCH_REPEATS,
    name_operating_points,
    object_accuracy,
    paired_difference,
    pareto_front,
    score,
    touches_score,
)
from fusion.experiments.data import any_pose, folder_objects
from fusion.experiments.models import Predictions
from fusion.experiments.report import pct, pivot, table1
from fusion.experiments.touch import load_batch, save_batch, touch_object, touch_objects
from perception.errors import DatasetError, InvalidArgumentError
from perception.shapes import make_object
from tactile.contours import Contour, Plane
from tactile.touching import TILT_DEG_PER_MM, TouchTiming, jitter_contour


# ------------------------------------------------------------------------------------------ stand-in
def _features(batch) -> np.ndarray:
    cues = kinesthetic_cues(batch, "invariant").mean(axis=1)
    frames = batch.frames.reshape(len(batch), -1)
    return np.column_stack([cues, frames.mean(axis=1), frames.std(axis=1)]).astype(np.float64)


class NearestMean(TactileClassifier):
    """Nearest class mean of a few z-scored sequence statistics; softmax of minus the squared distance."""

    def __init__(self, scale: float = 1.0):
        self.scale = scale

    def _fit(self, batch, y):
        x = _features(batch)
        self.mu_, self.sd_ = x.mean(0), x.std(0) + 1e-9
        z = (x - self.mu_) / self.sd_
        self.means_ = np.stack([z[y == c].mean(0) for c in range(len(self.classes_))])

    def _predict_proba(self, batch):
        z = (_features(batch) - self.mu_) / self.sd_
        d = ((z[:, None, :] - self.means_[None]) ** 2).sum(-1) * self.scale
        e = np.exp(-(d - d.min(1, keepdims=True)))
        return e / e.sum(1, keepdims=True)


STANDINS = {"nm": lambda: NearestMean(), "nm-soft": lambda: NearestMean(scale=0.3)}


def recorder(fits: list) -> type:
    """A :class:`NearestMean` that appends (sequences, names of the objects) of every fit to ``fits``."""

    class Recorder(NearestMean):
        def _fit(self, batch, y):
            fits.append((len(batch), {batch.object_names[o] for o in batch.object_ids}))
            super()._fit(batch, y)

    return Recorder


def write_off(model, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["OFF", f"{len(model.vertices)} {len(model.triangles)} 0"]
    lines += [" ".join(f"{x:.6f}" for x in v) for v in model.vertices]
    lines += ["3 " + " ".join(map(str, t)) for t in model.triangles]
    path.write_text("\n".join(lines) + "\n")
    return path


def mesh_folder(root: Path, classes=("box", "can"), per_class: int = 3) -> Path:
    for c in classes:
        for s in range(per_class):
            write_off(make_object(c, s), root / c / f"{c}{s}.off")
    return root


# ----------------------------------------------------------------------------------- pure functions
def test_pareto_front_by_hand():
    times = [1.0, 2.0, 3.0, 4.0, 5.0, 2.0]
    errors = [0.5, 0.4, 0.45, 0.1, 0.1, 0.3]
    # (2, 0.3) beats (2, 0.4); (3, 0.45) is beaten; (5, 0.1) ties (4, 0.1) in error but is slower.
    assert pareto_front(times, errors).tolist() == [0, 5, 3]
    with pytest.raises(InvalidArgumentError):
        pareto_front([1.0], [0.1, 0.2])


def test_operating_points_name_the_knee():
    # Normalised log-time 0, 0.151, 1; normalised error drop 0, 0.889, 1: the middle point is the knee.
    times, errors = [1.0, 2.0, 100.0], [0.5, 0.1, 0.05]
    named = name_operating_points(times, errors, pareto_front(times, errors))
    assert named == {"fastest": 0, "most accurate": 2, "knee": 1}


def _predictions() -> Predictions:
    # Object 0 (class a): two confident right, two mild wrong. Object 1 (class b): one confident right,
    # three mild wrong: log rule -> b (log .99 + 3 log .3 > log .01 + 3 log .7), sum rule -> a (2.11 > 1.89).
    proba = np.array([[0.9, 0.1], [0.9, 0.1], [0.4, 0.6], [0.4, 0.6],
                      [0.01, 0.99], [0.7, 0.3], [0.7, 0.3], [0.7, 0.3]])
    labels = np.array(["a"] * 4 + ["b"] * 4, dtype=object)
    return Predictions(proba, labels, np.repeat([0, 1], 4), ["a", "b"], ["a/0", "b/0"])


def test_touch_scores_by_hand():
    pred = _predictions()
    assert score(pred).value == pytest.approx(3 / 8)
    assert touches_score(pred, 4, "log").value == 1.0
    assert touches_score(pred, 4, "sum").value == 0.5
    acc = touches_score(pred, 1, "log")
    assert acc.value == pytest.approx(3 / 8) and acc.n == 8 and 0 <= acc.low <= acc.value <= acc.high <= 1
    with pytest.raises(DatasetError):
        touches_score(pred, 5)


def test_touch_scores_average_over_cuts():
    """One object, three sequences, one of them wrong enough to veto under the log rule: a K = 2 decision is
    right only when the cut leaves the bad one out (the remainder is dropped), i.e. with probability 1/3. One cut
    scores 0 or 1; many cuts average towards 1/3."""
    proba = np.array([[0.9, 0.1], [0.9, 0.1], [1e-6, 1 - 1e-6]])
    pred = Predictions(proba, np.array(["a"] * 3, dtype=object), np.zeros(3, dtype=np.int64), ["a", "b"], ["a/0"])
    assert touches_score(pred, 2, repeats=1).value in (0.0, 1.0)
    many = touches_score(pred, 2, repeats=600)
    assert many.n == 600 and abs(many.value - 1 / 3) < 0.06
    assert touches_score(pred, 1).n == 3  # K = 1: each sequence once, whatever the repeats


def test_touch_scores_default_to_several_cuts_and_object_accuracy_takes_repeats():
    """The 3-sequence object above (a K = 2 decision is right with probability 1/3): by default every score
    averages TOUCH_REPEATS > 1 cuts (one group each), so an object's share is a multiple of 1 / TOUCH_REPEATS,
    not the 0 or 1 of a single cut; object_accuracy honours ``repeats``."""
    proba = np.array([[0.9, 0.1], [0.9, 0.1], [1e-6, 1 - 1e-6]])
    pred = Predictions(proba, np.array(["a"] * 3, dtype=object), np.zeros(3, dtype=np.int64), ["a", "b"], ["a/0"])
    assert TOUCH_REPEATS > 1
    assert touches_score(pred, 2).n == TOUCH_REPEATS  # one group of 2 per cut, the third sequence left over
    share = object_accuracy(pred, 2, seed=1)["a/0"]  # (seed 0 happens to leave the bad one in all 10 cuts)
    assert 0 < share < 1 and share * TOUCH_REPEATS == pytest.approx(round(share * TOUCH_REPEATS))
    assert object_accuracy(pred, 2, repeats=1)["a/0"] in (0.0, 1.0)
    assert abs(object_accuracy(pred, 2, repeats=600)["a/0"] - 1 / 3) < 0.06
    assert object_accuracy(pred, 1, repeats=600)["a/0"] == pytest.approx(2 / 3)  # K = 1: each sequence once


def test_table1_puts_paper_numbers_only_next_to_the_papers_classifiers():
    """The paper's numbers sit beside the classifiers with the paper's (normals) cue, not the pose-free ones."""
    acc = {"value": 0.9, "low": 0.8, "high": 0.95, "n": 10}
    rows = [{"classifier": c, "strategy": s, "accuracy": acc}
            for c in ("CNN fusion (normals cue)", "CNN cutaneous", "SVM (normals cue)", "SVM")
            for s in ("guided", "blind")]
    out = {r["classifier"]: r for r in table1(rows)}
    assert out["CNN fusion (normals cue)"]["paper guided"] == "98.97 %"
    assert out["SVM (normals cue)"]["paper blind"] == "77.21 %"
    assert out["CNN cutaneous"]["paper guided"] == "-" and out["SVM"]["paper guided"] == "-"
    assert out["SVM"]["guided"] == "90.0 % [80.0, 95.0]"


def test_pivot_gives_a_row_per_key_in_first_seen_order_and_a_dash_where_a_cell_is_missing():
    """Keys keep the order they first appear in; columns are the sorted values; a missing (key, K) is '-'."""
    rows = [{"c": "b", "k": 2, "v": 1}, {"c": "a", "k": 1, "v": 2}, {"c": "b", "k": 1, "v": 3},
            {"c": "b", "k": 1, "v": 9}]
    assert pivot(rows, ("c",), lambda r: str(r["v"])) == [{"c": "b", "K=1": "3", "K=2": "1"},
                                                           {"c": "a", "K=1": "2", "K=2": "-"}]
    assert pivot(rows, ("c",), lambda r: r["v"], column="v", head=str)[1] == {"c": "a", "1": "-", "2": 2, "3": "-",
                                                                               "9": "-"}


def test_touches_and_noise_tables_name_the_rule_and_keep_each_rows_pose():
    """The K-touch table spells the fusion rule out ('log' -> 'sum of log', else 'sum') and keeps one setting;
    the noise table gives a row without a pose the pose 'upright' but keeps a row's own pose, one column per
    level ('{level:g}')."""
    from fusion.experiments.report import noise_table, touches_table

    acc = {"value": 0.5, "low": 0.4, "high": 0.6, "n": 10}
    rows = [{"setting": "s", "classifier": "SVM", "strategy": "guided", "rule": r, "k": 1, "accuracy": acc}
            for r in ("log", "sum")] + [{"setting": "t", "classifier": "kNN", "strategy": "blind", "rule": "log",
                                         "k": 2, "accuracy": acc}]
    table = touches_table(rows, "s")
    assert [(r["classifier"], r["rule"]) for r in table] == [("SVM", "sum of log"), ("SVM", "sum")]
    assert all(set(r) == {"classifier", "strategy", "rule", "K=1"} for r in table)
    noise = [{"kind": "n", "classifier": "SVM", "strategy": "blind", "level": 0.5, "accuracy": acc},
             {"kind": "n", "pose": "tilted", "classifier": "SVM", "strategy": "blind", "level": 2.0, "accuracy": acc},
             {"kind": "other", "classifier": "SVM", "strategy": "blind", "level": 9.0, "accuracy": acc}]
    assert noise_table(noise, "n") == [
        {"pose": "upright", "classifier": "SVM", "strategy": "blind", "0.5": pct(acc), "2": "-"},
        {"pose": "tilted", "classifier": "SVM", "strategy": "blind", "0.5": "-", "2": pct(acc)}]


def test_paired_difference_by_hand():
    """Object a/0: A right 4 of 4, B right 2 of 4; object b/0: A 1 of 4, B 1 of 4 -> differences 0.5 and 0:
    mean 0.25, bootstrap interval within [0, 0.5], detectable = 2.8 x std(ddof 1) / sqrt(2) = 0.7."""
    ids = np.repeat([0, 1], 4)
    right, wrong = [0.9, 0.1], [0.1, 0.9]
    labels = np.array(["a"] * 4 + ["b"] * 4, dtype=object)
    a = Predictions(np.array([right] * 4 + [right, right, right, wrong]), labels, ids, ["a", "b"], ["a/0", "b/0"])
    b = Predictions(np.array([right, right, wrong, wrong] + [right, right, right, wrong]), labels, ids, ["a", "b"],
                    ["a/0", "b/0"])
    out = paired_difference(a, b, 1)
    assert out["difference"] == pytest.approx(0.25) and out["n_objects"] == 2
    assert 0 <= out["low"] <= 0.25 <= out["high"] <= 0.5
    assert out["detectable"] == pytest.approx(2.8 * np.std([0.5, 0.0], ddof=1) / np.sqrt(2))


def test_any_pose_gives_each_object_its_own_seeded_rotation():
    objects = [("mug", 0), ("box", 1)]
    a, b, other = any_pose(objects, 3), any_pose(objects, 3), any_pose(objects, 4)
    assert [s.name for s in a] == ["mug/0", "box/1"] and [s.label for s in a] == ["mug", "box"]
    assert [s.rotation_seed for s in a] == [s.rotation_seed for s in b]  # same seed, same poses
    assert len({s.rotation_seed for s in a}) == 2  # each object its own
    assert all(x.rotation_seed != y.rotation_seed for x, y in zip(a, other, strict=True))


def _loaded_mug(seed: int):  # a loader for the store-record test (never called there)
    raise AssertionError("not loaded")


def test_objects_made_by_one_loader_get_stores_of_their_own():
    """Two sets of loaded objects with the same function and labels but other arguments (other captures of the
    same classes, say) are other data: their stores must not share a name; the same set gives the same record."""
    import functools

    from fusion.experiments.data import store_record
    from tactile.dataset.objects import ObjectSpec

    def objects(seeds, names=("mug/a", "mug/b")):
        return [ObjectSpec(name=n, label="mug", loader=functools.partial(_loaded_mug, s)) for n, s in zip(names, seeds)]

    first = store_record(objects((0, 1)), 10, 0)
    assert store_record(objects((0, 1)), 10, 0) == first
    assert store_record(objects((2, 3)), 10, 0) != first  # other arguments
    assert store_record(objects((0, 1), ("mug/c", "mug/d")), 10, 0) != first  # other names
    # Files and catalogue items keep the record they always had (cached stores keep their names).
    assert store_record([("mug", 4)], 10, 0)["objects"] == [["('mug', 4)", "mug"]]


def test_store_records_of_guided_contours_say_how_their_pairs_are_drawn():
    """Models cached from stores whose guided pairs were drawn with repeats must not be reused: the record of any
    store with a guided strategy (mixed with blind or not) names how pairs are drawn; blind-only records keep theirs."""
    from fusion.experiments.data import store_record

    assert "guided_pairs" not in store_record([("mug", 4)], 10, 0, strategies=("blind",))
    for strategies in (("guided",), ("guided", "blind"), ("blind", "mesh")):
        assert store_record([("mug", 4)], 10, 0, strategies=strategies)["guided_pairs"] == "without repeats"
    # One strategy named as a string is that strategy (as generate reads it), not its letters.
    assert store_record([("mug", 4)], 10, 0, strategies="guided") == store_record([("mug", 4)], 10, 0,
                                                                                   strategies=("guided",))


def test_byte_identical_meshes_count_as_one_object(tmp_path):
    """Two files with the same bytes (SHREC's Fish/226 and 227) are one object: the later one is left out."""
    for name, text in (("226.off", "OFF\n# fish\n"), ("227.off", "OFF\n# fish\n"), ("228.off", "OFF\n# other\n")):
        (tmp_path / "Fish").mkdir(exist_ok=True)
        (tmp_path / "Fish" / name).write_text(text)
    assert [p.name for p, _ in folder_objects(tmp_path)] == ["226.off", "228.off"]
    # Files equal in their first kilobyte and length but not after it are two objects.
    head = "OFF\n#" + "x" * 1024
    (tmp_path / "Fish" / "229.off").write_text(head + "a\n")
    (tmp_path / "Fish" / "230.off").write_text(head + "b\n")
    assert [p.name for p, _ in folder_objects(tmp_path)] == ["226.off", "228.off", "229.off", "230.off"]


def test_store_identity_is_the_whole_path_and_any_pose_draws_from_seed_and_name(tmp_path):
    """Same-named files of two folders are other objects (other stores); the any-pose rotation of an object is the
    one :func:`tactile.dataset.store.contour_seed` gives for (seed, name, "pose", 0), so the poses of one seed are
    fixed and another seed turns the objects otherwise."""
    from fusion.experiments.data import store_record
    from tactile.dataset.store import contour_seed

    a, b = mesh_folder(tmp_path / "a", per_class=1), mesh_folder(tmp_path / "b", per_class=1)
    record = functools.partial(store_record, strategies=("blind",), contours=2, seed=0)
    assert record(folder_objects(a)) != record(folder_objects(b))
    posed = any_pose(folder_objects(a), 5)
    assert [o.rotation_seed for o in posed] == [contour_seed(5, o.name, "pose", 0) for o in posed]
    assert all(x.rotation_seed != y.rotation_seed for x, y in zip(posed, any_pose(folder_objects(a), 6)))


def test_sizes_refuse_bad_values():
    with pytest.raises(InvalidArgumentError, match="paper_contours"):
        Sizes(paper_contours=0)
    with pytest.raises(InvalidArgumentError, match="unseen_folds"):
        Sizes(unseen_folds=1)
    with pytest.raises(InvalidArgumentError, match="openset_rotations"):  # one rotation would test no known object
        Sizes(openset_rotations=1)
    for bad in ("2", 2.5, True):  # a folder count from a config file: a project error, not a TypeError or 2.5 folds
        for name in ("unseen_folds", "attention_folds", "openset_rotations"):
            with pytest.raises(InvalidArgumentError, match=name):
                Sizes(**{name: bad})
    with pytest.raises(InvalidArgumentError, match="unknown kinds"):
        Sizes(noise_levels={"cosmic_rays": (1.0,)})


# ------------------------------------------------------------------------------------------ jitter
def _flat_contour(n: int = 4000) -> Contour:
    positions = np.zeros((n, 3))
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    tangents = np.tile([1.0, 0.0, 0.0], (n, 1))
    plane = Plane(np.zeros(3), np.array([0.0, 1.0, 0.0]))
    return Contour(plane, positions[:3] + np.eye(3), True, positions, normals, tangents, np.zeros(n, dtype=np.int64))


def test_jitter_moves_probes_in_the_pad_plane_with_the_stated_spread():
    contour = _flat_contour()
    assert jitter_contour(contour, 0.0, np.random.default_rng(0)) is contour
    moved = jitter_contour(contour, 2.0, np.random.default_rng(0))
    shift = moved.positions - contour.positions
    assert np.abs(shift[:, 2]).max() == 0  # in the pad plane (z = 0 here)
    assert np.std(shift[:, :2], axis=0) == pytest.approx([2.0, 2.0], rel=0.06)
    tilt = np.degrees(np.arccos(np.clip(moved.normals[:, 2], -1, 1)))
    # |N(0, s)| has RMS s: the tilt's RMS is the stated std.
    assert math.sqrt(np.mean(tilt**2)) == pytest.approx(TILT_DEG_PER_MM * 2.0, rel=0.06)
    assert np.allclose(np.linalg.norm(moved.normals, axis=1), 1)
    assert np.abs(np.sum(moved.normals * moved.tangents, axis=1)).max() < 1e-12
    with pytest.raises(InvalidArgumentError):
        jitter_contour(contour, -1.0, np.random.default_rng(0))


def test_touching_is_seeded_and_jitter_keeps_the_planned_contours():
    box = make_object("box", 0)
    timing = TouchTiming()
    clean, contours = touch_object(box, "blind", 3, probes=10, seed=5, timing=timing)
    again, _ = touch_object(box, "blind", 3, probes=10, seed=5)
    jittered, _ = touch_object(box, "blind", 3, probes=10, seed=5, jitter_mm=2.0)
    assert timing.saliency_seconds == [] and len(timing.contour_seconds) == 3  # blind: no saliency
    for a, b, c, contour in zip(clean, again, jittered, contours):
        assert np.array_equal(a.frames, b.frames)
        assert np.array_equal(a.plane.normal, c.plane.normal)
        assert np.array_equal(c.normals, contour.normals) and np.array_equal(c.positions, contour.positions)
        assert not np.array_equal(a.frames, c.frames)


def test_batch_cache_round_trip_and_key(tmp_path):
    batch = touch_objects([make_object("can", 1)], ["box", "can"], "blind", 2, probes=6, seed=1)
    path = save_batch(batch, tmp_path / "b.npz", {"level": 1})
    back = load_batch(path, {"level": 1})
    assert np.array_equal(back.frames, batch.frames) and back.class_names == ("box", "can")
    assert back.labels.tolist() == [1, 1] and back.sensor_spec == batch.sensor_spec
    assert load_batch(path, {"level": 2}) is None and load_batch(tmp_path / "none.npz") is None


def test_an_unreadable_or_incomplete_cache_is_made_again_not_raised(tmp_path):
    """A cache file that is not an .npz, or whose meta matches but an array is missing, reads back as None
    (made again) instead of raising."""
    from fusion.experiments.models import write_cache

    (tmp_path / "garbage.npz").write_bytes(b"not a cache at all")
    assert load_batch(tmp_path / "garbage.npz", {"level": 1}) is None
    assert Predictions.load(tmp_path / "garbage.npz", {"level": 1}) is None
    write_cache(tmp_path / "partial.npz", {"key": {"level": 1}, "class_names": ["a"], "object_names": ["a/0"],
                                           "sensor_spec": {}}, {"frames": np.zeros((1, 2, 4, 4))})
    assert load_batch(tmp_path / "partial.npz", {"level": 1}) is None


def test_a_cache_cut_short_is_made_again_not_raised(tmp_path):
    """A cache file cut short (a copy interrupted, a full disk) reads back as None, like any unreadable one."""
    batch = touch_objects([make_object("can", 1)], ["box", "can"], "blind", 2, probes=6, seed=1)
    whole = save_batch(batch, tmp_path / "b.npz", {"level": 1}).read_bytes()
    (tmp_path / "short.npz").write_bytes(whole[: len(whole) // 2])
    assert load_batch(tmp_path / "short.npz", {"level": 1}) is None


def test_folder_objects_choose_and_refuse(tmp_path):
    for c in ("b", "a", "c"):
        for i in range(2):
            (tmp_path / c).mkdir(exist_ok=True)
            (tmp_path / c / f"{i}.off").write_text(f"OFF\n# {c}{i}\n")
    assert [label for _, label in folder_objects(tmp_path, max_classes=2)] == ["a", "a", "b", "b"]
    assert [p.name for p, _ in folder_objects(tmp_path, ["c"], per_class=1)] == ["0.off"]
    with pytest.raises(DatasetError, match="'zebra'"):
        folder_objects(tmp_path, ["zebra"])
    with pytest.raises(DatasetError, match="fewer than the 3"):
        folder_objects(tmp_path, per_class=3)


def test_folder_objects_leave_out_a_copy_and_warn_once(tmp_path, caplog):
    """A byte-identical copy counts once; every part of a run lists the objects again, but the warning is said once."""
    (tmp_path / "a").mkdir()
    for name, text in (("0.off", "OFF\n# one\n"), ("1.off", "OFF\n# one\n"), ("2.off", "OFF\n# two\n")):
        (tmp_path / "a" / name).write_text(text)
    with caplog.at_level("WARNING", logger="fusion.experiments.data"):
        for _ in range(3):
            assert [p.name for p, _ in folder_objects(tmp_path)] == ["0.off", "2.off"]
    warnings = [r.getMessage() for r in caplog.records if "byte-identical" in r.getMessage()]
    assert len(warnings) == 1 and "1.off is byte-identical to" in warnings[0] and warnings[0].count("0.off") == 1


def test_a_copy_in_a_class_not_asked_for_is_left_out_without_a_warning(tmp_path, caplog):
    # SHREC's Fish/227 = Fish/226 was announced even when only Cup was asked for; a copy across classes still counts
    for c, files in (("cup", {"0.off": "OFF\n# cup\n"}), ("fish", {"0.off": "OFF\n# f\n", "1.off": "OFF\n# f\n"}),
                     ("mug", {"0.off": "OFF\n# cup\n", "1.off": "OFF\n# mug\n"})):
        (tmp_path / c).mkdir()
        for name, text in files.items():
            (tmp_path / c / name).write_text(text)
    with caplog.at_level("WARNING", logger="fusion.experiments.data"):
        assert [p.name for p, _ in folder_objects(tmp_path, ["cup"])] == ["0.off"]
        assert not [r for r in caplog.records if "byte-identical" in r.getMessage()]
        assert [str(p.relative_to(tmp_path)) for p, _ in folder_objects(tmp_path, ["mug"])] == ["mug/1.off"]
    warnings = [r.getMessage() for r in caplog.records if "byte-identical" in r.getMessage()]
    assert len(warnings) == 1 and "mug/0.off is byte-identical to" in warnings[0] and "cup/0.off" in warnings[0]


def test_reproduce_refuses_bad_parts(tmp_path):
    with pytest.raises(InvalidArgumentError, match="unknown parts"):
        reproduce(tmp_path, tmp_path / "r", parts=("paper", "tea"), classifiers=STANDINS)
    with pytest.raises(InvalidArgumentError, match="add 'paper' or 'unseen'"):
        reproduce(tmp_path, tmp_path / "r", parts=("touches",), classifiers=STANDINS)


# ------------------------------------------------------------------------------------ end to end
# Blind only: no saliency, so the fast tests stay fast (the slow test runs both strategies and every part).
TINY = Sizes(strategies=("blind",), paper_contours=10, unseen_contours=10, unseen_folds=3, touches=(1, 2), noise_contours=2,
             noise_levels={"taxel_noise": (0.5,), "dead_taxels": (0.5,), "dead_taxels_repaired": (0.5,),
                           "pose_jitter": (2.0,)},
             paper_classifiers=("nm", "nm-soft"), unseen_classifiers=("nm",))
FAST_PARTS = ("paper", "unseen", "touches", "noise")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("reproduce")
    data = mesh_folder(root / "meshes")
    out = root / "report"
    results = reproduce(data, out, sizes=TINY, classifiers=STANDINS, parts=FAST_PARTS, workers=2, progress=False)
    return data, out, results


def _accuracies(obj):
    if isinstance(obj, dict):
        if set(obj) == {"value", "low", "high", "n"}:
            yield obj
        for v in obj.values():
            yield from _accuracies(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _accuracies(v)


def test_reproduce_writes_a_complete_report(tiny_run):
    _, out, _results = tiny_run
    saved = json.loads((out / "results.json").read_text())
    assert set(FAST_PARTS) <= set(saved)
    rows = saved["paper"]["rows"]
    assert {(r["classifier"], r["strategy"]) for r in rows} == {("nm", "blind"), ("nm-soft", "blind")}
    # 2 classes x 3 objects x 10 contours, 20 % held out per strategy.
    assert all(r["accuracy"]["n"] == 12 for r in rows)
    assert sum(r["accuracy"]["n"] for r in saved["unseen"]["rows"]) == 2 * 3 * 10
    # The same test objects in a random pose each: every sequence predicted once more, paired with upright.
    assert sum(r["accuracy"]["n"] for r in saved["unseen"]["any_pose_rows"]) == 2 * 3 * 10
    assert {r["k"] for r in saved["unseen"]["pose_differences"]} >= {1}
    assert all(r["n_objects"] == 6 for r in saved["unseen"]["pose_differences"])
    # The paper protocol and the unseen part share one upright store; the any-pose store is the second.
    assert len(list((out / "stores").glob("*.zarr"))) == 2
    accs = list(_accuracies(saved))
    assert accs and all(0 <= a["low"] <= a["value"] <= a["high"] <= 1 for a in accs)
    assert {r["kind"] for r in saved["noise"]["rows"]} == {"taxel_noise", "dead_taxels", "dead_taxels_repaired",
                                                          "pose_jitter"}
    assert {r["pose"] for r in saved["noise"]["rows"]} == {"any pose"}  # the robot's world only (NOISE_POSES)
    # Batches touched per fold, in any pose: clean and pose jitter only (read-out noise re-reads the clean frames), and
    # each fold's batch holds that fold's test objects only, so the objects split into the 3 folds exactly once.
    batches = sorted((out / "noise").glob("*.npz"))
    reads = {p.name.rsplit("-", 2)[0] for p in batches}  # "<pose>-<strategy>-<read>-<level>-<objects>.npz"
    assert reads == {f"anypose-blind-{read}" for read in ("clean", "pose_jitter")}
    clean = [load_batch(p) for p in batches if p.name.startswith("anypose-blind-clean-")]
    names = [set(b.object_names) for b in clean]
    assert len(clean) == 3 and sum(len(n) for n in names) == 6 and len(set.union(*names)) == 6
    report = (out / "report.md").read_text()
    for name in ["accuracy_vs_k.png", "accuracy_vs_noise.png", *saved["paper"]["figures"]]:
        assert f"]({name})" in report
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "## Paper protocol (Table 1)" in report and "## Unseen objects" in report


def test_reproduce_resumes_from_its_cache_with_the_same_numbers(tiny_run):
    data, out, results = tiny_run
    models = sorted((out / "models").rglob("*.vtm"))
    predictions = sorted((out / "models").rglob("*.npz"))  # each pose's of a fold model in a file of its own
    assert {p.stem.rsplit("-", 1)[-1] for p in predictions} == {"test", "anypose"}
    stamps = [p.stat().st_mtime_ns for p in models + predictions]
    again = reproduce(data, out, sizes=TINY, classifiers=STANDINS, parts=FAST_PARTS, workers=2, progress=False)
    assert [p.stat().st_mtime_ns for p in models + predictions] == stamps  # nothing retrained nor predicted again
    for part in ("paper", "unseen", "touches", "noise"):
        assert list(_accuracies(again[part])) == list(_accuracies(results[part]))


def test_unseen_folds_train_one_model_on_every_strategys_contours(tmp_path):
    """Per fold one model, fitted on the guided and the blind contours of the fold's training objects (4 of the
    6), never on a test object; it predicts each strategy's contours of the 2 test objects, upright and turned."""
    fits = []
    Recorder = recorder(fits)

    data = mesh_folder(tmp_path / "meshes")
    sizes = TINY.with_(strategies=("guided", "blind"), unseen_classifiers=("rec",))
    results = reproduce(data, tmp_path / "report", sizes=sizes, classifiers={"rec": Recorder},
                        parts=("unseen", "touches"), workers=2, progress=False)
    assert [n for n, _ in fits] == [2 * 10 * 4] * 3  # 3 folds, both strategies' 10 contours of 4 objects each
    trained = [names for _, names in fits]
    assert set.union(*trained) == {f"{c}/{c}{i}" for c in ("box", "can") for i in range(3)}
    assert all(len(names) == 4 for names in trained)  # each object held out by exactly one fold
    assert sorted(len(set.intersection(*trained[:i], *trained[i + 1:])) for i in range(3)) == [2, 2, 2]
    for rows in (results["unseen"]["rows"], results["unseen"]["any_pose_rows"]):
        assert {r["strategy"]: r["accuracy"]["n"] for r in rows} == {"guided": 6 * 10, "blind": 6 * 10}
    assert sorted(p.name for p in (tmp_path / "report" / "models" / "unseen" / "guided+blind").iterdir()) == [
        "fold1", "fold2", "fold3"]
    # K touches without the paper part: the unseen objects' curves only
    assert {r["setting"] for r in results["touches"]["rows"]} == {"unseen_objects", "unseen_objects_any_pose"}


@pytest.mark.slow
def test_reproduce_every_part_both_strategies(tmp_path):
    data = mesh_folder(tmp_path / "meshes", classes=("box", "can", "mug"))
    sizes = TINY.with_(strategies=("guided", "blind"), attention_contours=6, attention_folds=3, runtime_contours=6,
                       runtime_probes=(5, 10), runtime_grids=(8, 16), touches=(1, 2, 4))
    results = reproduce(data, tmp_path / "report", sizes=sizes, classifiers=STANDINS, workers=2, progress=False)
    assert {r["strategy"] for r in results["paper"]["rows"]} == {"guided", "blind"}
    attention = {r["strategy"]: r for r in results["attention"]["rows"]}
    assert set(attention) == {"blind", "guided", "mesh", "iss", "pcl_harris", "pcl_iss"}
    assert attention["blind"]["saliency_seconds_per_object"] == 0.0
    assert attention["guided"]["saliency_seconds_per_object"] > 0
    runtime = results["runtime"]
    assert {(p["probes"], p["grid"]) for p in runtime["points"]} == {(5, 8), (5, 16), (10, 8), (10, 16)}
    front = [runtime["points"][i] for i in runtime["front"]]
    # Along the front time grows and error falls, and no point beats a front point in both.
    assert all(a["seconds"] <= b["seconds"] and a["error"] > b["error"] for a, b in itertools.pairwise(front))
    for f in front:
        assert not any(p["seconds"] < f["seconds"] and p["error"] < f["error"] for p in runtime["points"])
    assert set(runtime["named"]) >= {"fastest", "most accurate"}
    # the same held-out objects in their random poses beside each point: a pose-free stand-in errs alike (within
    # one of the three test objects, where saliency on a turned, near-symmetric object picks other contours)
    assert all(abs(p["error_any_pose"] - p["error"]) < 0.34 for p in runtime["points"])
    for name in ("pareto.png", "accuracy_vs_k.png", "accuracy_vs_noise.png"):
        assert (tmp_path / "report" / name).stat().st_size > 10_000


def test_reproduce_command_help_and_errors(tmp_path, capsys):
    from fusion.cli import main

    assert main(["reproduce", "--help"]) == 0 and "--objects-per-class" in capsys.readouterr().out
    assert main(["reproduce", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "r")]) == 2
    assert "nowhere: not a folder" in capsys.readouterr().err
    (tmp_path / "meshes" / "a").mkdir(parents=True)
    (tmp_path / "meshes" / "a" / "x.off").write_text("OFF\n")
    assert main(["reproduce", "--data", str(tmp_path / "meshes"), "--classes", "b", "--out", str(tmp_path / "r")]) == 2
    assert "no class folders ['b']" in capsys.readouterr().err


def test_guided_noise_contours_reuse_the_stores_interest_points():
    from fusion.experiments.robustness import _attention
    from perception.interest_cache import KnownInterestPoints

    mug = make_object("mug", 0)
    points = mug.vertices[::max(1, len(mug.vertices) // 10)][:10]

    class FakeStore:
        def interest_points(self, name):
            return {"guided": points} if name == mug.name else {}

    attention = _attention(FakeStore(), [mug], "guided", seed=0)
    assert isinstance(attention[mug.name], KnownInterestPoints)
    assert _attention(FakeStore(), [mug], "blind", seed=0) is None
    sequences, _ = touch_object(mug, "guided", 4, probes=8, seed=0, attention=attention[mug.name])
    for seq in sequences:
        # Every plane holds the centre and two of the stored points (distance to the plane ~ 0).
        distance = np.abs((points - mug.center) @ seq.plane.normal)
        assert np.sum(distance < 1e-6) >= 2


def test_model_cache_reloads_only_the_same_estimator_on_the_same_data(tmp_path):
    from fusion.experiments.models import fit_cached

    batch = touch_objects([make_object("box", 0), make_object("can", 0)], ["box", "can"], "blind", 3, probes=6)
    path = tmp_path / "m.vtm"
    calls = []

    def train():
        calls.append(1)
        return batch

    first, _ = fit_cached(lambda: NearestMean(), train, path, {"data": "a"})
    again, _ = fit_cached(lambda: NearestMean(), train, path, {"data": "a"})
    assert len(calls) == 1 and np.array_equal(again.means_, first.means_)  # loaded, not trained
    fit_cached(lambda: NearestMean(scale=2.0), train, path, {"data": "a"})  # other parameters
    fit_cached(lambda: NearestMean(scale=2.0), train, path, {"data": "b"})  # other data
    assert len(calls) == 3


def test_a_model_saved_over_an_old_one_never_pairs_with_the_old_record(tmp_path):
    """save_fitted removes the old record before it writes the model: a save interrupted in between leaves no record
    (the model is trained again), never the old record beside a model it does not describe."""
    from fusion.experiments.models import cached_fit_seconds, model_record, save_fitted

    batch = touch_objects([make_object("box", 0), make_object("can", 0)], ["box", "can"], "blind", 3, probes=6)
    path = tmp_path / "m.vtm"
    old = NearestMean().fit(batch)
    save_fitted(old, 1.0, path, model_record(NearestMean, {"data": "a"}))
    assert cached_fit_seconds(path, model_record(NearestMean, {"data": "a"})) == 1.0

    class Interrupted(NearestMean):
        def save(self, where):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        save_fitted(Interrupted().fit(batch), 2.0, path, model_record(NearestMean, {"data": "b"}))
    assert cached_fit_seconds(path, model_record(NearestMean, {"data": "a"})) is None


def test_a_saved_part_without_its_result_is_computed_again(tmp_path, caplog):
    from fusion.experiments.context import Context, _part_key

    ctx = Context(tmp_path, 0, TINY, {})
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "x.json").write_text(json.dumps({"key": _part_key({"a": 1})}))  # no "result"
    with caplog.at_level("WARNING"):
        assert not ctx.has_part("x", {"a": 1})
        assert ctx.cached_part("x", {"a": 1}, lambda: {"made": True}) == {"made": True}
    assert "x.json unreadable" in caplog.text
    assert ctx.has_part("x", {"a": 1}) and not ctx.has_part("x", {"a": 2})


class TestModelCodeVersion:
    """A cached model's code key covers the modules its classifier's code lives in, and only those."""

    @staticmethod
    def _key_after_edit(monkeypatch, cls, edited: str, addition: str = "\n# an edit\n") -> str:
        """The key of ``cls`` as it would be with ``addition`` appended to the file ``edited`` (fusion/...);
        the real files are read, never written."""
        from fusion.experiments import models

        real = models._source_text
        monkeypatch.setattr(models, "_source_text",
                            lambda path: real(path) + (addition if path.as_posix().endswith(edited) else ""))
        return models.model_code_version.__wrapped__(cls)

    def test_files_of_each_classifier(self):
        from fusion.cnn import CNNClassifier
        from fusion.conventional import ConventionalClassifier
        from fusion.experiments.models import model_code_files

        cnn = {p.name for p in model_code_files(CNNClassifier)}
        conventional = {p.name for p in model_code_files(ConventionalClassifier)}
        assert {"cnn.py", "base.py", "cues.py", "modelfile.py", "leakage.py"} <= cnn
        assert {"conventional.py", "features.py", "contourlet.py", "base.py", "cues.py"} <= conventional
        assert not {"demo.py", "cli.py", "decide.py", "evaluate.py", "models.py"} & (cnn | conventional)
        assert "conventional.py" not in cnn and "cnn.py" not in conventional

    def test_an_edit_to_an_unrelated_module_keeps_the_key(self, monkeypatch):
        from fusion.cnn import CNNClassifier
        from fusion.experiments.models import model_code_version

        assert self._key_after_edit(monkeypatch, CNNClassifier, "fusion/demo.py") == model_code_version(CNNClassifier)

    def test_an_edit_to_the_classifiers_module_changes_the_key(self, monkeypatch):
        from fusion.cnn import CNNClassifier
        from fusion.experiments.models import model_code_version

        assert self._key_after_edit(monkeypatch, CNNClassifier, "fusion/cnn.py") != model_code_version(CNNClassifier)

    @pytest.mark.parametrize("library", ["numpy", "scipy", "scikit-learn", "torch", "PyWavelets"])
    def test_another_library_version_changes_the_key(self, monkeypatch, library):
        from fusion.cnn import CNNClassifier
        from fusion.experiments import models
        from perception import runtime

        now = models.model_code_version.__wrapped__(CNNClassifier)
        real = runtime.version
        monkeypatch.setattr(runtime, "version", lambda name: "0.0.1" if name == library else real(name))
        assert models.model_code_version.__wrapped__(CNNClassifier) != now

    def test_every_keyed_library_is_installed(self):
        """A misspelt distribution name would read "not installed" forever and key nothing."""
        from fusion.experiments.models import MODEL_LIBRARIES
        from perception.runtime import versions

        assert "not installed" not in versions(*MODEL_LIBRARIES).values()

    def test_an_edit_to_another_classifier_keeps_the_key(self, monkeypatch):
        from fusion.conventional import ConventionalClassifier
        from fusion.experiments.models import model_code_version

        unchanged = model_code_version(ConventionalClassifier)
        assert self._key_after_edit(monkeypatch, ConventionalClassifier, "fusion/cnn.py") == unchanged
        assert self._key_after_edit(monkeypatch, ConventionalClassifier, "fusion/contourlet.py") != unchanged

    def test_a_new_import_brings_its_module_in(self, monkeypatch):
        """An edit that makes a classifier's module import another puts that module's code in the key."""
        from fusion.cnn import CNNClassifier
        from fusion.experiments import models

        real = models._source_text
        monkeypatch.setattr(models, "_source_text", lambda path: real(path) + (
            "\n\ndef later():\n    from fusion.demo import run_demo\n" if path.name == "cues.py" else ""))
        assert "demo.py" in {p.name for p in models.model_code_files(CNNClassifier)}

    def test_a_relative_import_is_followed_from_a_module_and_from_a_package(self, monkeypatch):
        """``from .x import y`` in fusion/cues.py names fusion.x; in a package's __init__.py (reached through
        ``from fusion.commands import ...``), ``from .x import y`` names fusion.commands.x."""
        from fusion.cnn import CNNClassifier
        from fusion.experiments import models

        real = models._source_text
        extra = {"fusion/cues.py": "\n\ndef later():\n    from .demo import run_demo\n"
                                   "    from fusion.commands import main\n",
                 "fusion/commands/__init__.py": "\n\ndef later():\n    from .verify import x\n"}
        monkeypatch.setattr(models, "_source_text", lambda path: real(path) + next(
            (text for end, text in extra.items() if path.as_posix().endswith(end)), ""))
        files = {p.relative_to(Path(models.__file__).resolve().parents[2]).as_posix()
                 for p in models.model_code_files(CNNClassifier)}
        assert {"fusion/demo.py", "fusion/commands/__init__.py", "fusion/commands/verify.py"} <= files


def test_reproduce_command_offers_exactly_the_parts_and_defaults():
    from fusion.commands.reproduce import DEFAULT_PARTS as COMMAND_DEFAULTS
    from fusion.commands.reproduce import PARTS as COMMAND_PARTS
    from fusion.experiments import PARTS
    from fusion.experiments.reproduce import DEFAULT_PARTS

    assert COMMAND_PARTS == PARTS
    assert COMMAND_DEFAULTS == DEFAULT_PARTS == ("paper", "unseen", "touches", "noise", "attention", "runtime")


CALLS = {"fit": 0, "predict": 0}


class CountingMean(NearestMean):
    """NearestMean that counts its fits and predictions (module level: model files name the class)."""

    def _fit(self, batch, y):
        CALLS["fit"] += 1
        super()._fit(batch, y)

    def _predict_proba(self, batch):
        CALLS["predict"] += 1
        return super()._predict_proba(batch)


def test_noise_reads_the_pooled_fold_models_and_a_rerun_reuses_every_prediction(tmp_path):
    """Both strategies: the noise part loads the 2 pooled fold models the unseen part trained (no fit of its
    own, rows for both strategies, in any pose only); run again, nothing is fitted or predicted (each strategy's
    test predictions are cached in a file of their own beside the shared fold model)."""
    CALLS.update(fit=0, predict=0)
    data = mesh_folder(tmp_path / "meshes", per_class=2)
    sizes = TINY.with_(strategies=("guided", "blind"), unseen_classifiers=("count",), unseen_contours=4, unseen_folds=2,
                       unseen_per_class=2, objects_per_class=2, noise_levels={"taxel_noise": (0.5,)})
    # one worker: the fits run in this process, where CALLS counts them
    kwargs = {"sizes": sizes, "classifiers": {"count": CountingMean}, "parts": ("unseen", "noise"), "workers": 1,
              "progress": False}
    results = reproduce(data, tmp_path / "report", **kwargs)
    assert CALLS["fit"] == 2
    assert {(r["pose"], r["strategy"]) for r in results["noise"]["rows"]} == {
        ("any pose", s) for s in ("guided", "blind")}
    # every sequence of the 4 objects x 2 noise contours, per (pose, strategy, kind, level)
    assert {r["accuracy"]["n"] for r in results["noise"]["rows"]} == {4 * 2}
    CALLS.update(fit=0, predict=0)
    again = reproduce(data, tmp_path / "report", **kwargs)
    assert CALLS == {"fit": 0, "predict": 0}
    assert list(_accuracies(again["unseen"])) == list(_accuracies(results["unseen"]))


def test_noise_settings_run_side_by_side_and_give_the_rows_of_one_process(tmp_path):
    """Each (pose, strategy) of the noise part is a job on the run's workers: two workers give the rows one process
    gives, field for field, in strategy order (any pose only)."""
    data = mesh_folder(tmp_path / "meshes", per_class=2)
    sizes = TINY.with_(strategies=("guided", "blind"), unseen_contours=4, unseen_folds=2, unseen_per_class=2,
                       objects_per_class=2, noise_levels={"taxel_noise": (0.5,), "pose_jitter": (2.0,)})
    rows = {}
    for workers in (1, 2):
        results = reproduce(data, tmp_path / f"report{workers}", sizes=sizes, classifiers=STANDINS,
                            parts=("unseen", "noise"), workers=workers, progress=False)
        rows[workers] = results["noise"]["rows"]
    assert rows[1] == rows[2]
    settings = list(dict.fromkeys((r["pose"], r["strategy"]) for r in rows[1]))
    assert settings == [("any pose", s) for s in ("guided", "blind")]


def test_noise_jobs_touch_each_pose_s_objects_with_that_pose_s_interest_points(tmp_path, monkeypatch):
    """The noise part runs in any pose only: its jobs get the objects turned by their poses (the meshes as stored,
    each turned about its own rotation) and read the guided interest points the any-pose store recorded for them
    (found in that pose), never the upright store's."""
    from fusion.experiments import robustness
    from fusion.experiments.context import Context
    from fusion.experiments.data import folder_objects, load_models
    from fusion.experiments.protocol import pose_stores, unseen_objects

    objects = folder_objects(mesh_folder(tmp_path / "meshes", per_class=2), None, None)
    sizes = TINY.with_(strategies=("guided", "blind"), unseen_contours=4, unseen_folds=2,
                       noise_levels={"taxel_noise": (0.5,)})
    ctx = Context(tmp_path / "out", 5, sizes, STANDINS, progress=False)
    ctx.workers = 1
    unseen_objects(ctx, objects)
    read = []
    real = robustness._attention
    monkeypatch.setattr(robustness, "_attention", lambda ds, models, strategy, seed: read.append(
        (str(ds.path), strategy, sorted(m.name for m in models), [m.vertices.copy() for m in models]))
        or real(ds, models, strategy, seed))
    robustness.noise_rows(ctx, objects)
    stores = {pose: str(pose_stores(ctx, objects, pose, sizes.strategies, sizes.unseen_contours)[2].path)
              for pose in ("upright", "any pose")}
    assert stores["upright"] != stores["any pose"]
    assert [(path, strategy) for path, strategy, _, _ in read] == [
        (stores["any pose"], strategy) for strategy in ("guided", "blind")]
    upright = [m.vertices for m in load_models(objects)]
    turned = read[0][3]
    assert read[0][2] == sorted(m.name for m in load_models(objects)) and len(turned) == len(objects)
    for a, b in zip(upright, turned, strict=True):  # the same meshes, each turned about its own rotation
        assert a.shape == b.shape and not np.allclose(a, b)
        assert np.allclose(np.sort(np.linalg.norm(a - a.mean(0), axis=1)), np.sort(np.linalg.norm(b - b.mean(0), axis=1)),
                           atol=1e-6)


def test_unseen_folds_can_train_on_more_contours_than_they_test(tmp_path):
    """``unseen_train_contours``: each fold's model learns from 15 contours per training object, while every test
    object is scored on its 10 contours (upright from a store of their own, any pose as before), in the same folds."""
    fits = []
    Recorder = recorder(fits)

    data = mesh_folder(tmp_path / "meshes")
    sizes = TINY.with_(unseen_train_contours=15, unseen_classifiers=("rec",))
    results = reproduce(data, tmp_path / "report", sizes=sizes, classifiers={"rec": Recorder},
                        parts=("unseen",), workers=2, progress=False)
    assert [n for n, _ in fits] == [15 * 4] * 3
    assert all(len(names) == 4 for _, names in fits)
    for rows in (results["unseen"]["rows"], results["unseen"]["any_pose_rows"]):
        assert [r["accuracy"]["n"] for r in rows] == [6 * 10]
    assert results["unseen"]["train_contours"] == 15 and results["unseen"]["contours"] == 10
    stores = sorted(p.name.split("-")[1] for p in (tmp_path / "report" / "stores").glob("*.zarr"))
    assert stores == ["10c", "10c", "15c"]  # upright test, any-pose test, training
    # The folds are those of the 10-contour store: each object tested once, by the fold that left it out.
    trained = [names for _, names in fits]
    assert sorted(len(set.intersection(*trained[:i], *trained[i + 1:])) for i in range(3)) == [2, 2, 2]


def test_sizes_refuse_bad_training_contours():
    for bad in (0, -3, 2.5, True, "72"):
        with pytest.raises(InvalidArgumentError, match="unseen_train_contours"):
            Sizes(unseen_train_contours=bad)
    assert Sizes(unseen_train_contours=None).unseen_train_contours is None


def test_more_training_contours_feed_the_noise_part_and_a_rerun_reuses_everything(tmp_path):
    """With ``unseen_train_contours``, upright and any-pose predictions are cached under their own names beside
    each fold's model, the noise part reads those models (no fit of its own), and a second run fits and predicts
    nothing; the report names both contour counts."""
    CALLS.update(fit=0, predict=0)
    data = mesh_folder(tmp_path / "meshes")
    sizes = TINY.with_(unseen_train_contours=15, unseen_classifiers=("count",), noise_levels={"taxel_noise": (0.5,)})
    # one worker: the fits run in this process, where CALLS counts them
    kwargs = {"sizes": sizes, "classifiers": {"count": CountingMean}, "parts": ("unseen", "noise"), "workers": 1,
              "progress": False}
    results = reproduce(data, tmp_path / "report", **kwargs)
    assert CALLS["fit"] == 3
    fold = tmp_path / "report" / "models" / "unseen" / "blind" / "fold1"
    assert sorted(p.name for p in fold.iterdir()) == ["count-anypose.npz", "count-test.npz", "count.json",
                                                      "count.vtm"]
    assert {r["accuracy"]["n"] for r in results["noise"]["rows"]} == {6 * TINY.noise_contours}
    assert "10 contours per test object and strategy (15 per training object)" in (
        tmp_path / "report" / "report.md").read_text()
    CALLS.update(fit=0, predict=0)
    reproduce(data, tmp_path / "report", **kwargs)
    assert CALLS == {"fit": 0, "predict": 0}


def test_by_default_the_unseen_part_trains_on_the_contours_it_tests(tiny_run):
    _, out, results = tiny_run
    assert results["unseen"]["train_contours"] == results["unseen"]["contours"] == 10
    assert "(10 per training object)" in (out / "report.md").read_text()


class EmbeddingMean(NearestMean):
    """NearestMean with a feature space (its z-scored statistics), so the open-set distance scores run too."""

    def embed(self, batch):
        return (_features(batch) - self.mu_) / self.sd_


OPEN_SET_CLASSES = ("bottle", "bowl", "box", "can", "funnel", "mug", "ring", "wineglass")
OPEN_SET_SIZES = TINY.with_(unseen_contours=6, touches=(1, 2), openset_rotations=2, calibration_classifiers=("em",))


@pytest.fixture(scope="module")
def open_set_data(tmp_path_factory):
    """``(meshes, stores)``: the 8 catalogue classes x 6 objects of the open-set tests, and the stores their parts
    read, made once for the module (a store is named after its objects' paths, so every test reads these meshes).
    Each test copies the stores into its report folder with :func:`with_stores`: what it checks is made anew."""
    root = tmp_path_factory.mktemp("open_set")
    meshes = mesh_folder(root / "meshes", classes=OPEN_SET_CLASSES, per_class=6)
    reproduce(meshes, root / "made", sizes=OPEN_SET_SIZES, classifiers={"em": EmbeddingMean},
              parts=("openset",), workers=2, progress=False)
    return meshes, root / "made" / "stores"


def with_stores(report: Path, stores: Path) -> Path:
    """``report``, a new report folder holding a copy of ``stores`` (the tests then generate nothing)."""
    shutil.copytree(stores, report / "stores")
    return report


def test_calibration_and_open_set_parts_report_every_k_and_score(tmp_path, open_set_data):
    """The two parts end to end on 8 catalogue classes x 6 objects (blind, 6 contours, any pose): ECE rows before and
    after calibration for every K with intervals around them and one reliability figure; open-set rows for every
    score and K, AUROCs in [0, 1] over exactly the left-out objects, and shares at the training-chosen threshold."""
    classes = OPEN_SET_CLASSES
    data, stores = open_set_data
    with_stores(tmp_path / "report", stores)
    fits = []

    class Recording(EmbeddingMean):
        def _fit(self, batch, y):
            names = np.asarray(batch.object_names, dtype=object)[batch.object_ids]
            labels = np.asarray(batch.class_names, dtype=object)[batch.labels]
            fits.append({c: len(set(names[labels == c])) for c in set(labels)})
            super()._fit(batch, y)

    results = reproduce(data, tmp_path / "report", sizes=OPEN_SET_SIZES, classifiers={"em": Recording},
                        parts=("openset",), workers=2, progress=False)
    # Open set: every fit sees the known classes of one rotation only, and at most the 3 objects per class that its
    # rotation did not hold out for testing (the other 3 of 6 are the known test objects).
    left_out = results["openset"]["left_out"]
    for fit in fits:
        assert any(not set(fit) & set(group) for group in left_out), fit
        assert max(fit.values()) <= 3, fit
    results |= reproduce(data, tmp_path / "report", sizes=OPEN_SET_SIZES, classifiers={"em": EmbeddingMean},
                         parts=("calibration",), workers=2, progress=False)
    ece = results["calibration"]["rows"]
    assert {(r["k"], r["variant"].split(" ")[0]) for r in ece} >= {(k, v) for k in (1, 2) for v in ("before", "after")}
    assert all(0 <= r["low"] <= r["ece"] <= r["high"] <= 1 for r in ece)
    assert results["calibration"]["figures"] == ["reliability_em.png"]
    saved = sorted(p.name for p in (tmp_path / "report" / "calibration").glob("*.vtm"))  # kept for a re-run
    assert saved == [f"fold{i + 1}-em.vtm" for i in range(OPEN_SET_SIZES.unseen_folds)]
    assert (tmp_path / "report" / "reliability_em.png").read_bytes()[:4] == b"\x89PNG"
    rows = results["openset"]["rows"]
    assert {(r["k"], r["score"]) for r in rows} == {(k, s) for k in (1, 2)
                                                   for s in ("probability", "distance", "class_distance",
                                                             "set_distance", "chosen")}
    left_out = results["openset"]["left_out"]
    assert sorted(c for group in left_out for c in group) == sorted(classes)  # each class left out by exactly one rotation
    for r in rows:
        assert 0 <= r["auroc_low"] <= r["auroc"] <= r["auroc_high"] <= 1
    # K = 1: every contour of every object once as unknown (8 x 6 x 6); as known, each rotation's held-out half of
    # the other 4 classes' objects (2 rotations x 4 classes x 3 objects x 6 contours).
    assert {(r["n_unknown"], r["n_known"]) for r in rows if r["k"] == 1} == {(288, 144)}
    chosen = [r for r in rows if r["score"] == "chosen"]
    assert all(0 <= r["known_kept"] <= 1 and 0 <= r["unknown_rejected"] <= 1 for r in chosen)
    for r in chosen:  # every class is left out once, with as many decisions as any other: the shares average out
        assert sorted(r["rejected_by_class"]) == sorted(classes)
        assert np.mean(list(r["rejected_by_class"].values())) == pytest.approx(r["unknown_rejected"])
    picked = {r["score"] for r in results["openset"]["rotations"]}
    if len(picked) == 1:  # every rotation chose one score: the "chosen" rows are that score's
        (name,) = picked
        by = {(r["k"], r["score"]): r["auroc"] for r in rows}
        assert all(by[(k, "chosen")] == by[(k, name)] for k in (1, 2))


def test_open_set_part_resumes_from_the_calibrations_it_saved(tmp_path, caplog, open_set_data):
    """Each rotation's calibrated model is saved as it is made: a re-run of the part (its result file gone, as after an
    interrupt) loads them, fits nothing and reports the same rows; a damaged model file is calibrated again, alone."""
    data, stores = open_set_data
    with_stores(tmp_path / "report", stores)
    fits = []

    class Recording(EmbeddingMean):
        def _fit(self, batch, y):
            fits.append(len(batch))
            super()._fit(batch, y)

    def run():
        (tmp_path / "report" / "parts" / "openset.json").unlink(missing_ok=True)
        fits.clear()
        return reproduce(data, tmp_path / "report", sizes=OPEN_SET_SIZES, classifiers={"em": Recording},
                         parts=("openset",), workers=2, progress=False)["openset"]

    first = run()
    first_fits = len(fits)
    saved = sorted(p.name for p in (tmp_path / "report" / "openset").glob("*.vtm"))
    assert saved == ["rotation1-em.vtm", "rotation2-em.vtm"]
    assert first_fits >= 2 * 3  # per rotation: the model and its inner folds
    again = run()
    assert fits == []
    assert again["rows"] == first["rows"] and again["rotations"] == first["rotations"]
    damaged = tmp_path / "report" / "openset" / "rotation2-em.vtm"
    damaged.write_bytes(damaged.read_bytes()[:100])
    with caplog.at_level("WARNING", logger="fusion.experiments.openset"):
        third = run()
    assert "rotation2-em.vtm unusable" in caplog.text
    assert 0 < len(fits) < first_fits  # the damaged rotation only
    assert third["rows"] == first["rows"]
    record = tmp_path / "report" / "openset" / "rotation1-em.json"  # made with other settings: calibrated again
    meta = json.loads(record.read_text())
    meta["record"]["options"]["max_touches"] = 7
    record.write_text(json.dumps(meta))
    run()
    assert 0 < len(fits) < first_fits
    (tmp_path / "report").rename(tmp_path / "moved")  # a report folder moved elsewhere still resumes
    fits.clear()
    (tmp_path / "moved" / "parts" / "openset.json").unlink()
    moved = reproduce(data, tmp_path / "moved", sizes=OPEN_SET_SIZES, classifiers={"em": Recording},
                      parts=("openset",), workers=2, progress=False)["openset"]
    assert fits == [] and moved["rows"] == first["rows"]
    # three rotations train each on other rows of the same store: no saved rotation fits them, all are made again
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "moved" / "openset").glob("*.vtm")}
    reproduce(data, tmp_path / "moved", sizes=OPEN_SET_SIZES.with_(openset_rotations=3), classifiers={"em": Recording},
              parts=("openset",), workers=2, progress=False)
    after = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "moved" / "openset").glob("*.vtm")}
    assert all(after[name] != stamp for name, stamp in before.items())


def test_open_set_shares_follow_the_threshold_of_each_k(tmp_path, monkeypatch, open_set_data):
    """The shares kept and rejected use each K's own threshold: below every score at K = 1 (all kept, none
    rejected), above every score at K = 2 (none kept, all rejected)."""
    from fusion.experiments import openset as experiment

    asked = []

    def threshold(model, k):
        asked.append(k)
        return 0.0 if k == 1 else np.inf

    real = experiment.group_scores

    def tied(*args, **kwargs):  # every score exactly 0: at K = 1 each decision sits on its threshold, and is kept
        s = real(*args, **kwargs)
        return {n: np.zeros(len(v)) if n in experiment.SCORES else v for n, v in s.items()}

    monkeypatch.setattr(experiment, "threshold_for", threshold)
    monkeypatch.setattr(experiment, "group_scores", tied)
    data, stores = open_set_data
    results = reproduce(data, with_stores(tmp_path / "report", stores), sizes=OPEN_SET_SIZES,
                        classifiers={"em": EmbeddingMean},
                        parts=("openset",), workers=2, progress=False)
    assert sorted(set(asked)) == [1, 2]
    shares = {r["k"]: (r["known_kept"], r["unknown_rejected"]) for r in results["openset"]["rows"]
              if r["score"] == "chosen"}
    assert shares == {1: (1.0, 0.0), 2: (0.0, 1.0)}
    by_class = {r["k"]: r["rejected_by_class"] for r in results["openset"]["rows"] if r["score"] == "chosen"}
    assert by_class == {1: dict.fromkeys(sorted(OPEN_SET_CLASSES), 0.0), 2: dict.fromkeys(sorted(OPEN_SET_CLASSES), 1.0)}
    report = (tmp_path / "report" / "report.md").read_text()
    assert "em, K = 2, unknown answered 'unknown' by left-out class: bottle 100 %, bowl 100 %" in report


def test_attention_part_names_each_pose_to_the_folds(tmp_path, monkeypatch):
    """The attention part asks the folds for every pose by name, in one call (the pose names the cached
    predictions: upright and any-pose predictions of one fold model must not share a file)."""
    from fusion.experiments import attention
    from fusion.experiments.context import Context

    asked = []

    def folds(ctx, part, stores, strategies, classifiers, n_folds, **kwargs):
        asked.extend((part, pose_stores, pose) for pose, pose_stores in stores.items())
        return {pose: {} for pose in stores}

    monkeypatch.setattr(attention, "grouped_kfold", folds)
    monkeypatch.setattr(attention, "pose_stores", lambda ctx, objects, pose, strategies, contours: pose)
    monkeypatch.setattr(attention, "saliency_seconds", lambda *a, **k: {})
    data = mesh_folder(tmp_path / "meshes", per_class=1)
    objects = [(p, p.parent.name) for p in sorted(data.glob("*/*.off"))]
    ctx = Context(out=tmp_path / "report", seed=0, sizes=TINY, classifiers=STANDINS, progress=False)
    attention.attention_rows(ctx, objects)
    assert asked and all(part == "attention" and stores == pose for part, stores, pose in asked)
    assert [pose for *_, pose in asked][:2] == ["upright", "any pose"]


# ---------------------------------------------------------------------------- benchmarks.new_instances
def test_new_instances_refuses_a_training_mesh_and_an_unknown_class(tmp_path, capsys):
    from benchmarks import new_instances

    train = mesh_folder(tmp_path / "train", per_class=2)
    copy = tmp_path / "copy" / "box" / "again.off"
    copy.parent.mkdir(parents=True)
    copy.write_bytes((train / "box" / "box1.off").read_bytes())
    assert new_instances.main(["--instances", str(copy.parents[1]), "--train", str(train), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "again.off" in err and "box1.off" in err and "byte for byte" in err
    other = mesh_folder(tmp_path / "other", classes=("box", "mug"), per_class=1)
    assert new_instances.main(["--instances", str(other), "--train", str(train), "--out", str(tmp_path / "o")]) == 2
    assert "['mug'] are not in the training set" in capsys.readouterr().err
    assert new_instances.main(["--instances", str(other), "--train", str(train), "--seed", "-1"]) == 2
    assert "seed must be an integer in [0, 2**32 - 1], got -1" in capsys.readouterr().err
    assert new_instances.main(["--instances", str(other), "--train", str(train), "--seed", str(2**32)]) == 2
    assert f"got {2**32}" in capsys.readouterr().err  # scikit-learn would fail on it after the stores were made
    assert new_instances.main(["--instances", str(other), "--train", str(train), "--touches", "1"]) == 2
    assert "need 2 <= touches <= contours, got 1 touches" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # refused before anything was generated


def test_new_instances_trains_once_and_tests_every_pose_and_strategy(tmp_path, monkeypatch):
    """Every test object scored once per pose and strategy by a model that saw only the training meshes; the paired
    differences agree with the accuracies (equal decisions per object, so a mean over objects is a mean over
    decisions)."""
    from benchmarks import new_instances
    from fusion.experiments import models

    fits: list = []
    monkeypatch.setattr(models, "default_classifiers", lambda seed=0, **_: {"nm": recorder(fits)})
    train = mesh_folder(tmp_path / "train", per_class=2)
    test = tmp_path / "test"
    for c in ("box", "can"):
        for s in (7, 8):
            write_off(make_object(c, s), test / c / f"{c}{s}.off")
    result = new_instances.run(test, train, tmp_path / "o", contours=4, touches=2, classifiers=("nm",))
    assert len(fits) == 1 and fits[0] == (2 * 4 * 4, {"box/box0", "box/box1", "can/can0", "can/can1"})
    assert {(r["pose"], r["strategy"]) for r in result["rows"]} == {(p, s) for p in ("upright", "any") for s in
                                                                    ("guided", "blind")}
    assert all(r["objects"] == 4 and r["k1"]["n"] == 16 and r["k2"]["n"] == 4 * 2 * 10 for r in result["rows"])
    by = {(r["pose"], r["strategy"], k): r[k]["value"] for r in result["rows"] for k in ("k1", "k2")}
    for d in result["differences"]:
        a, b = d["compare"].split(" (")[0].split(" - "), d["compare"].split("(")[1][:-1]
        k = f"k{d['k']}"
        if a == ["guided", "blind"]:
            expected = by[(b, "guided", k)] - by[(b, "blind", k)]
        else:
            expected = by[("any", b, k)] - by[("upright", b, k)]
        assert d["difference"] == pytest.approx(100 * expected) and d["n_objects"] == 4
    assert result["tested_objects"] == result["test_objects"] == 4
    # The any-pose store holds the test meshes each in the pose any_pose draws from the seed; the upright one none.
    from fusion.experiments.data import any_pose, folder_objects
    from tactile.dataset import open_dataset

    stored = []
    for store in (tmp_path / "o" / "stores").glob("*.zarr"):
        objects = open_dataset(store).attrs["settings"]["objects"]
        stored.append(sorted(o.get("rotation_seed", -1) for o in objects))
    drawn = sorted(spec.rotation_seed for spec in any_pose(folder_objects(test), 0))
    assert sorted(stored) == sorted([[-1] * 4, [-1] * 4, drawn])  # training, upright test, any-pose test
    # A second run scores from the cache: no model is fitted again.
    predicted: list = []
    real_predict = models.predict
    monkeypatch.setattr(models, "predict", lambda model, batch, *a: predicted.append(set(batch.object_names)) or
                        real_predict(model, batch, *a))
    again = new_instances.run(test, train, tmp_path / "o", contours=4, touches=2, classifiers=("nm",),
                              poses=("upright", "any", "upright"))  # a pose named twice is tested once
    assert len(fits) == 1 and again["rows"] == result["rows"] and not predicted
    assert again["differences"] == result["differences"]
    assert "| nm | any | guided |" in new_instances.report(result)
    # Other instances into the same folder: the model is reused, the predictions are made anew on them.
    other = tmp_path / "other"
    for c in ("box", "can"):
        write_off(make_object(c, 9), other / c / f"{c}9.off")
    new_instances.run(other, train, tmp_path / "o", contours=4, touches=2, classifiers=("nm",))
    assert len(fits) == 1 and len(predicted) == 4 and all(names == {"box/box9", "can/can9"} for names in predicted)


def test_the_poses_of_grouped_kfold_must_share_their_training_store():
    """Each pose's models are the fold models trained once: poses that name other training stores are refused
    before anything runs."""
    from types import SimpleNamespace

    from fusion.experiments.protocol import grouped_kfold
    from perception.errors import InvalidArgumentError

    stores = {pose: (SimpleNamespace(path=f"/stores/{pose}.zarr"), {}, None, {}) for pose in ("upright", "any pose")}
    with pytest.raises(InvalidArgumentError, match="must share one training store"):
        grouped_kfold(None, "unseen", stores, ("blind",), {}, 3)


def test_calibration_folds_follow_the_fewest_training_objects_of_a_class():
    """Three calibration folds where every class has three training objects or more; fewer where a fold's training
    rows hold fewer (a quick run: 2); a class with a single training object is refused, naming the part."""
    from types import SimpleNamespace

    from fusion.experiments.openset import calibration_folds

    # rows: (object, class); objects 0-4 of class 0, 5-6 of class 1, 7 of class 2
    objects = np.array([0, 0, 1, 2, 3, 4, 5, 5, 6, 7])
    labels = np.array([0, 0, 0, 0, 0, 0, 1, 1, 1, 2])
    ds = SimpleNamespace(object_ids=objects, labels=labels, path="store.zarr")
    assert calibration_folds(ds, [np.arange(6)], "calibration") == 3  # class 0 alone: 5 objects
    assert calibration_folds(ds, [np.arange(6), np.arange(9)], "calibration") == 2  # class 1 has 2
    assert calibration_folds(ds, [np.array([0, 2, 6, 8])], "calibration") == 2
    with pytest.raises(DatasetError, match="store.zarr: the openset part needs at least 2 training objects"):
        calibration_folds(ds, [np.arange(10)], "openset")  # class 2: one object
    with pytest.raises(DatasetError, match="store.zarr: the calibration part has no training rows"):
        calibration_folds(ds, [np.array([], dtype=np.int64)], "calibration")


def test_a_part_that_cannot_calibrate_does_not_stop_the_other(tmp_path):
    """Both parts asked for, the open-set part's rotations leaving a single training object of a class: the
    calibration part is still made and written, then the open-set part stops with its own message."""
    data = mesh_folder(tmp_path / "meshes", classes=OPEN_SET_CLASSES[:4], per_class=3)
    with pytest.raises(DatasetError, match="the openset part needs at least 2 training objects"):
        reproduce(data, tmp_path / "report", sizes=OPEN_SET_SIZES, classifiers={"em": EmbeddingMean},
                  parts=("calibration", "openset"), workers=1, progress=False)
    saved = json.loads((tmp_path / "report" / "parts" / "calibration.json").read_text())
    assert {r["k"] for r in saved["result"]["rows"]} == {1, 2}


def test_calibration_part_runs_on_two_training_objects_per_class(tmp_path):
    """Three objects per class in three folds leave two training objects of a class: the part calibrates on two
    folds (as ``--quick`` does; it stopped with "fewer objects than the 3 calibration folds" before)."""
    data = mesh_folder(tmp_path / "meshes", classes=OPEN_SET_CLASSES[:4], per_class=3)
    results = reproduce(data, tmp_path / "report", sizes=OPEN_SET_SIZES, classifiers={"em": EmbeddingMean},
                        parts=("calibration",), workers=1, progress=False)
    assert {(r["k"], r["variant"].split(" ")[0]) for r in results["calibration"]["rows"]} >= {
        (k, v) for k in (1, 2) for v in ("before", "after")}


def test_calibration_and_open_set_calibrate_in_one_pool(tmp_path, monkeypatch, open_set_data):
    """Both parts asked for: every calibration of both is made in one pool before either part runs (the parts then
    load them), and the rows are those of the two parts run one at a time."""
    from fusion.experiments.context import Context

    data, stores = open_set_data
    pools = []
    real = Context.run_jobs

    def recording(self, jobs):
        pools.append(sorted({Path(job.path).parent.name for job in jobs}))
        out = real(self, jobs)
        if len(pools) == 1:  # the models the pool saved, to check that the parts only load them
            saved.update({p: p.stat().st_mtime_ns for p in (tmp_path / "both").rglob("*.vtm")})
            assert out == [None] * len(jobs)  # saved, not sent back to this process
        return out

    saved = {}

    monkeypatch.setattr(Context, "run_jobs", recording)
    both = reproduce(data, with_stores(tmp_path / "both", stores), sizes=OPEN_SET_SIZES,
                     classifiers={"em": EmbeddingMean},
                     parts=("calibration", "openset"), workers=2, progress=False)
    assert pools[0] == ["calibration", "openset"] and len(pools) == 3
    assert "calibrations" in both["seconds"]
    assert len(saved) == OPEN_SET_SIZES.unseen_folds + OPEN_SET_SIZES.openset_rotations  # one classifier
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "both").rglob("*.vtm")} == saved  # none made again
    alone = {part: reproduce(data, with_stores(tmp_path / part, stores), sizes=OPEN_SET_SIZES,
                             classifiers={"em": EmbeddingMean},
                             parts=(part,), workers=2, progress=False)[part] for part in ("calibration", "openset")}
    assert both["openset"]["rows"] == alone["openset"]["rows"]
    assert both["calibration"]["rows"] == alone["calibration"]["rows"]


def test_noise_rows_read_each_fold_with_its_own_model(tmp_path, monkeypatch):
    """Each noise job predicts a fold's test objects with that fold's unseen-part model (one that never trained on
    them), whatever pose or strategy."""
    from fusion.base import load_model
    from fusion.experiments import robustness
    from fusion.experiments.context import Context
    from fusion.experiments.data import folder_objects
    from fusion.experiments.protocol import fold_folder, pooled_folds, unseen_objects

    objects = folder_objects(mesh_folder(tmp_path / "meshes"), None, None)
    sizes = TINY.with_(noise_levels={"taxel_noise": (0.5,)})
    ctx = Context(tmp_path / "out", 5, sizes, STANDINS, progress=False)
    ctx.workers = 1  # the jobs in this process, where the spy is
    unseen_objects(ctx, objects)
    seen = []
    real = robustness.predict
    monkeypatch.setattr(robustness, "predict", lambda estimator, data, *a: seen.append(
        (estimator.mu_, {data.object_names[o] for o in data.object_ids})) or real(estimator, data, *a))
    rows = robustness.noise_rows(ctx, objects)
    assert rows and seen
    ds, _ = ctx.store(objects, strategies=sizes.strategies, contours=sizes.unseen_contours)
    folds = pooled_folds(ctx, ds, sizes.strategies, sizes.unseen_folds)
    tested = [{ds.object_names[o] for o in ds.object_ids[test]} for _, test in folds]
    saved = [load_model(fold_folder(ctx, "unseen", sizes.strategies, i) / "nm.vtm").mu_ for i in range(len(folds))]
    for mu, names in seen:
        fold = next(i for i, t in enumerate(tested) if names <= t)  # one fold's objects at a time
        assert np.array_equal(mu, saved[fold])
