"""The command line: benchmark dispatch and the demo's outputs."""

from __future__ import annotations

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
