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


class TestBenchmarksPackaging:
    """The benchmarks run from a checkout and are not installed as a top-level package."""

    def test_the_package_list_leaves_benchmarks_out(self):
        import configparser
        from pathlib import Path

        from setuptools import find_packages

        root = Path(__file__).resolve().parents[2]
        cfg = configparser.ConfigParser()
        cfg.read(root / "setup.cfg")
        include = cfg.get("options.packages.find", "include").split()
        packages = find_packages(where=str(root), include=include)
        assert {"perception", "tactile", "fusion", "fusion.commands"} <= set(packages)
        assert not any(p.split(".")[0] in ("benchmarks", "tests", "examples") for p in packages)

    def test_bench_without_a_checkout_says_where_they_are(self, monkeypatch, capsys):
        monkeypatch.setattr("perception.runtime.checkout_root", lambda: None)
        assert available_benchmarks() == []
        assert main(["bench", "geometry"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "checkout" in err[0] and "python -m benchmarks.NAME" in err[0]
