"""The command line: benchmark dispatch and the demo's outputs."""

from __future__ import annotations

import json

import pytest

from fusion.cli import main
from fusion.commands.bench import available_benchmarks


def test_benchmarks_are_listed_and_unknown_ones_refused(capsys):
    assert {"geometry", "tactile", "saliency"} <= set(available_benchmarks())
    assert main(["bench", "no-such-bench"]) == 2
    assert "available: " in capsys.readouterr().err


def test_unknown_arguments_are_refused_outside_bench():
    with pytest.raises(SystemExit):
        main(["demo", "--no-such-flag"])


def test_demo_writes_figures_and_summary(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path)]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["figures"] == ["catalogue.png", "saliency.png", "contour_blind.png", "contour_guided.png"]
    for name in summary["figures"]:
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    rows = summary["catalogue"]
    assert all(row["watertight"] and row["diagonal_mm"] == 150.0 for row in rows)
    assert "mug" in capsys.readouterr().out


@pytest.mark.parametrize("name", available_benchmarks())
def test_every_benchmark_imports_and_has_main(name):
    import importlib

    module = importlib.import_module(f"benchmarks.{name}")
    assert callable(module.main)


def test_bench_help_reaches_the_benchmark(capsys):
    with pytest.raises(SystemExit) as info:
        main(["bench", "geometry", "--help"])
    assert info.value.code == 0
    assert "--quick" in capsys.readouterr().out
    assert main(["bench"]) == 2
