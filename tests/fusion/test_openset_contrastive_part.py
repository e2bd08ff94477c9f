"""Only the open-set part's CNNs train with the supervised contrastive term, and its cached result names the weight
(the calibration part's does not: changing the weight leaves it cached)."""

from __future__ import annotations

from fusion.experiments import openset
from fusion.experiments.context import Context
from fusion.experiments.data import folder_objects
from fusion.experiments.reproduce import reproduce
from tests.fusion.test_experiments import OPEN_SET_SIZES, EmbeddingMean, open_set_data, with_stores  # noqa: F401


def test_only_the_openset_part_trains_with_the_contrastive_term(tmp_path, open_set_data, monkeypatch):  # noqa: F811
    data, stores = open_set_data
    weights, real = [], openset.contrastive
    monkeypatch.setattr(openset, "contrastive", lambda f, w: weights.append(w) or real(f, w))
    ctx = Context(with_stores(tmp_path / "r", stores), 0, OPEN_SET_SIZES, {"em": EmbeddingMean}, progress=False,
                  workers=1)
    objects = folder_objects(data, None, OPEN_SET_SIZES.unseen_per_class)
    openset._openset_plan(ctx, objects)
    openset._calibration_plan(ctx, objects)
    assert weights == [openset.OPENSET_CONTRASTIVE, 0] and openset.OPENSET_CONTRASTIVE > 0


def test_the_weight_keys_the_open_set_part_only(tmp_path, open_set_data, monkeypatch):  # noqa: F811
    data, stores = open_set_data
    out = with_stores(tmp_path / "report", stores)
    calls = []
    for part in ("calibration_part", "openset_part"):
        real = getattr(openset, part)
        monkeypatch.setattr(openset, part, lambda ctx, objects, real=real, part=part: calls.append(part)
                            or real(ctx, objects))
    run = {"sizes": OPEN_SET_SIZES, "classifiers": {"em": EmbeddingMean}, "parts": ("calibration", "openset"),
           "workers": 1, "progress": False}
    first = reproduce(data, out, **run)
    assert first["openset"]["contrastive"] == openset.OPENSET_CONTRASTIVE
    monkeypatch.setattr(openset, "OPENSET_CONTRASTIVE", 0.25)
    assert reproduce(data, out, **run)["openset"]["contrastive"] == 0.25
    assert calls == ["calibration_part", "openset_part", "openset_part"]  # the calibration part came from its cache
