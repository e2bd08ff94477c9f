"""The house's floors (perception <- tactile <- fusion) on the walk of one object through ``visuotactile
recognize``: every module entered from one floor besides its own, no call or import upward
(``benchmarks/walk.py``)."""

from __future__ import annotations

import json

import pytest

from benchmarks import walk as walk_module
from benchmarks.walk import FLOORS, SHARED, Walk, floor_of, main, upward_imports


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

    def test_an_upward_import_in_a_lower_floors_source_is_found(self, tmp_path):
        """Imports of a higher floor in perception or tactile source are listed (file, line, name), at any depth;
        imports of the same or a lower floor, and fusion's own imports, are not."""
        for floor, text in {"perception": "import numpy\nfrom perception import errors\n\n\ndef f():\n"
                                          "    import tactile.sampling\n",
                            "tactile": "from perception.geometry import ObjectModel\nfrom fusion.cli import main\n",
                            "fusion": "import tactile\nfrom perception import loading\n"}.items():
            (tmp_path / floor / "sub").mkdir(parents=True)
            (tmp_path / floor / "sub" / "m.py").write_text(text)
        assert upward_imports(tmp_path) == [
            {"file": "perception/sub/m.py", "line": 6, "imports": "tactile.sampling"},
            {"file": "tactile/sub/m.py", "line": 2, "imports": "fusion.cli"}]

    def test_the_command_exits_1_and_prints_each_flag(self, monkeypatch, capsys, tmp_path):
        """Any flag (two floors, an upward call or import) makes the exit code 1 and is printed as FLAG."""
        clean = {"argv": ["visuotactile", "recognize"], "label": "mug", "modules": [], "cast_rays_after": None,
                 "doors": {}, "two_floors": [], "shared": [], "upward": [], "upward_imports": []}
        flags = {"two_floors": [{"module": "perception.geometry", "floors": ["tactile", "fusion"],
                                 "callers": ["tactile.touching", "fusion.cli"]}],
                 "upward": [{"caller": "perception.render", "callee": "tactile.contours"}],
                 "upward_imports": [{"file": "tactile/x.py", "line": 3, "imports": "fusion.cli"}]}
        monkeypatch.setattr(walk_module, "build_case", lambda folder: (tmp_path / "mug.ply", tmp_path / "m.vtm"))
        for name, flagged in [(None, None), *flags.items()]:
            result = clean if name is None else {**clean, name: flagged}
            monkeypatch.setattr(walk_module, "walk", lambda mesh, model, result=result, **kw: result)
            assert main([]) == (0 if name is None else 1)
            out = capsys.readouterr().out
            assert ("FLAG" in out) == (name is not None)

    @pytest.mark.parametrize("argv", [["--touches", "0"], ["--touches", "-3"], ["--strategy", "psychic"]])
    def test_a_bad_touches_or_strategy_is_a_usage_error_before_anything_is_built(self, argv, monkeypatch):
        """A value recognize would refuse is exit 2 with one line, before the case is built (not exit 1, which
        means a flag)."""
        def build_case(folder):
            raise AssertionError("the case was built for arguments that cannot run")

        monkeypatch.setattr(walk_module, "build_case", build_case)
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        assert exit_.value.code == 2
