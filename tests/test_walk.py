"""The house's floors (perception <- tactile <- fusion) on the walk of one object through ``visuotactile
recognize``: every module entered from one floor besides its own, no call or import upward
(``benchmarks/walk.py``)."""

from __future__ import annotations

import json

from benchmarks.walk import FLOORS, SHARED, Walk, floor_of, main


class TestTheWalkOfOneObject:
    """``visuotactile recognize`` (guided) on a catalogue mug with a tiny in-process model, traced."""

    def test_each_module_is_entered_from_one_floor_and_nothing_calls_upward(self, capsys):
        assert main(["--json"]) == 0
        result = json.loads(capsys.readouterr().out)
        modules = {m["module"]: m for m in result["modules"]}
        order = [m["module"] for m in result["modules"]]
        assert result["two_floors"] == [] and result["upward"] == [] and result["upward_imports"] == []
        assert {m["module"] for m in result["shared"]} <= set(SHARED)
        # From the command down to the ray caster and back up to the decision.
        assert order[0] == "fusion.cli" and {floor_of(m) for m in order} == set(FLOORS)
        # Rays are cast by the multiview saliency (guided touching) and by the pressed pad.
        assert {m for m in order if modules[m]["cast_rays"]} == {"perception.render", "tactile.sensor"}
        assert order.index("tactile.touching") < result["cast_rays_after"] <= order.index("fusion.decide")
        # fusion touches through tactile.touching; tactile reaches perception's geometry; the file comes in
        # through perception.loading.
        assert {floor_of(c) for c in modules["tactile.touching"]["callers"]} == {"fusion"}
        assert {floor_of(c) for c in modules["perception.geometry"]["callers"]} <= {"perception", "tactile"}
        assert {floor_of(c) for c in modules["perception.loading"]["callers"]} <= {"perception", "fusion"}
        assert "perception.geometry" not in result["doors"]["fusion -> perception"]
        assert result["label"] in ("mug", "box")

    def test_a_module_entered_from_two_other_floors_and_an_upward_call_are_flagged(self):
        walk = Walk()
        walk.order = ["fusion.cli", "tactile.contours", "perception.geometry", "perception.runtime"]
        walk.callers = {"fusion.cli": {}, "tactile.contours": dict.fromkeys(["tactile.touching", "perception.render"]),
                        "perception.geometry": dict.fromkeys(["perception.loading", "tactile.touching", "fusion.cli"]),
                        "perception.runtime": dict.fromkeys(["tactile.touching", "fusion.cli"])}
        report = walk.report()
        assert [m["module"] for m in report["two_floors"]] == ["perception.geometry"]
        assert report["two_floors"][0]["floors"] == ["tactile", "fusion"]
        assert [m["module"] for m in report["shared"]] == ["perception.runtime"]
        assert report["upward"] == [{"caller": "perception.render", "callee": "tactile.contours"}]
