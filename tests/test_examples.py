"""The example scripts a new user copies from still run and print what they promise."""

from __future__ import annotations

import runpy
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_quickstart_prints_frame_and_normal_shapes(capsys):
    runpy.run_path(str(EXAMPLES / "quickstart.py"), run_name="__main__")
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "(25, 32, 32)" and lines[1] == "(25, 3)"
    sides = [float(s) for s in lines[2].strip("[]").split(",")]
    assert len(sides) == 25 and all(5.0 <= s <= 20.0 for s in sides)
