"""The saliency policy looks once per object (2026-12-07): the summary's and report's saliency seconds, the active
part's cache record, and SaliencyPolicy given a saliency of another method or object, or no saliency at all."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.active import make_policy, noisy_copy
from fusion.experiments.active import render_markdown, summarize
from perception.errors import SaliencyError
from perception.shapes import make_object
from tests.fusion.test_active import _proposals


def _policy(decisions, top):
    return {"decisions": decisions, "posteriors": [[p, 1 - p] for p in top], "planning_s": [0.2, 0.01],
            "touching_s": [0.05, 0.05], "classifying_s": [0.01, 0.01], "missed": 0, "classes": ["a", "b"]}


def _episodes(saliency_s):
    rows = []
    for i, seconds in enumerate(saliency_s):
        row = {"object": f"o{i}", "label": "a", "fold": 1, "policies": {
            "random": _policy(["b", "a" if i < 2 else "b"], [0.6, 0.8]),
            "saliency": _policy(["a", "a"], [0.9, 0.95])}}
        if seconds is not None:
            row["saliency_s"] = seconds
        rows.append(row)
    return {"objects": rows, "classifier": "svm", "noise_mm": 1.0, "candidates": 4, "variants": 1, "max_touches": 2}


def test_the_saliency_seconds_per_object_are_the_median_on_the_saliency_row_and_in_the_report():
    summary = summarize(_episodes([0.1, 0.7, 0.3, 0.2, 0.9]))
    timing = {t["policy"]: t for t in summary["timing"]}
    assert timing["saliency"]["saliency_per_object_s"] == pytest.approx(0.3)
    assert "saliency_per_object_s" not in timing["random"]
    text = render_markdown(summary)
    assert "once per object before its episodes" in text and "0.300 s (median)" in text


def test_records_without_saliency_seconds_add_no_saliency_line():
    summary = summarize(_episodes([None] * 4))
    assert all("saliency_per_object_s" not in t for t in summary["timing"])
    assert "once per object" not in render_markdown(summary)


def test_the_active_parts_record_names_the_once_per_object_saliency():
    """A part cached before 2026-12-07 (a saliency per episode) has another record, so it is computed again."""
    from types import SimpleNamespace

    from fusion.experiments import active
    from fusion.experiments.config import QUICK

    records = []
    ctx = SimpleNamespace(sizes=QUICK, seed=0,
                          cached_part=lambda name, record, compute: records.append(record) or _episodes([0.1, 0.2]))
    active.active_part(ctx, [])
    assert records[0]["saliency"] == "once per object"
    # parts without the saliency policy did not change: their cached records stay valid
    active.active_part(ctx, [], policies=("random", "information"))
    assert "saliency" not in records[1]


@pytest.fixture(scope="module")
def visual():
    return noisy_copy(make_object("mug", 0), 0.5, seed=1)


def test_a_saliency_of_another_method_or_of_a_copy_of_the_visual_model_is_refused(visual):
    from perception import saliency as attention

    mesh = attention.saliency(visual, "mesh")
    with pytest.raises(SaliencyError, match="needs 'multiview' saliency"):
        _proposals(make_policy("saliency", 0, saliency=mesh), visual, 1)
    twin = noisy_copy(make_object("mug", 0), 0.5, seed=1)  # the same geometry, another object
    with pytest.raises(SaliencyError, match="saliency of"):
        _proposals(make_policy("saliency", 0, saliency=attention.saliency(twin, "multiview")), visual, 1)


@pytest.mark.parametrize("bad", ["abc", 123, np.zeros(3)])
def test_a_saliency_that_is_no_saliency_is_refused_when_the_policy_is_made(bad):
    from perception.errors import InvalidArgumentError

    with pytest.raises(InvalidArgumentError, match="must be a perception.saliency.Saliency"):
        make_policy("saliency", 0, saliency=bad)


@pytest.mark.parametrize("name", ["random", "saliency", "information"])
@pytest.mark.parametrize("bad", [0, -1, 1.7, True, "abc", float("nan")])
def test_a_cache_size_below_one_or_not_an_integer_is_refused(name, bad):
    from fusion.active.policies import InformationPolicy, RandomPolicy, SaliencyPolicy
    from perception.errors import InvalidArgumentError

    policy = {"random": RandomPolicy, "saliency": SaliencyPolicy, "information": InformationPolicy}[name]
    with pytest.raises(InvalidArgumentError, match="cache_size must be an integer >= 1"):
        policy(0, cache_size=bad)
