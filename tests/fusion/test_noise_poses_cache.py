"""The noise part's cache record names the poses it tested in (``NOISE_POSES``): a noise part cached by the code
that tested upright and in any pose (its record had no ``poses`` entry) is computed again, not reported."""

from __future__ import annotations

import json

from fusion.experiments import reproduce
from fusion.experiments.context import _part_key
from tests.fusion.test_experiments import STANDINS, TINY, mesh_folder


def test_an_old_noise_part_with_upright_rows_is_computed_again_in_any_pose_only(tmp_path, monkeypatch):
    """First run as the old code ran: the noise part in both poses (``NOISE_POSES`` patched to them), its part file
    then rewritten as the old code wrote it (the same record without ``poses``, keyed on that). The second run, with
    the real ``NOISE_POSES``, must not take that file: its rows are in any pose only, and the part file is rewritten
    with a record that names the pose."""
    from fusion.experiments import robustness

    data = mesh_folder(tmp_path / "meshes", per_class=2)
    sizes = TINY.with_(unseen_contours=4, unseen_folds=2, unseen_per_class=2, objects_per_class=2,
                       noise_levels={"taxel_noise": (0.5,)})
    kwargs = {"sizes": sizes, "classifiers": STANDINS, "parts": ("unseen", "noise"), "workers": 1, "progress": False}
    out = tmp_path / "report"

    with monkeypatch.context() as patch:
        patch.setattr(robustness, "NOISE_POSES", ("upright", "any pose"))
        old = reproduce(data, out, **kwargs)
    assert {r["pose"] for r in old["noise"]["rows"]} == {"upright", "any pose"}  # the old part, both poses

    part = out / "parts" / "noise.json"
    saved = json.loads(part.read_text())
    record = {k: v for k, v in saved["record"].items() if k != "poses"}  # the old code's record
    part.write_text(json.dumps({"key": _part_key(record), "record": record, "result": saved["result"]}, indent=2))

    new = reproduce(data, out, **kwargs)
    assert {r["pose"] for r in new["noise"]["rows"]} == {"any pose"}
    assert json.loads((out / "results.json").read_text())["noise"]["rows"] == new["noise"]["rows"]
    assert json.loads(part.read_text())["record"]["poses"] == ["any pose"]
    # the any-pose rows are those the old part computed (the same models, contours and seeds): only the upright
    # half went
    assert new["noise"]["rows"] == [r for r in old["noise"]["rows"] if r["pose"] == "any pose"]
