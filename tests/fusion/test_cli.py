"""The command line: benchmark dispatch and the demo's outputs."""

from __future__ import annotations

import pytest

from fusion.cli import main
from fusion.commands.bench import available_benchmarks


def test_benchmarks_are_listed_and_unknown_ones_refused(capsys):
    assert {"geometry", "tactile", "saliency"} <= set(available_benchmarks())
    assert main(["bench", "no-such-bench"]) == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.startswith("visuotactile bench: error: unknown benchmark 'no-such-bench'")
    assert "available: " in out.err and len(out.err.strip().splitlines()) == 1


def test_bench_without_a_name_is_an_error_line_and_its_help_the_list(capsys):
    assert main(["bench"]) == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.startswith("visuotactile bench: error: name a benchmark: one of ")
    assert main(["bench", "--help"]) == 0
    assert "geometry" in capsys.readouterr().out


def test_unknown_arguments_are_refused_outside_bench(capsys):
    assert main(["demo", "--no-such-flag"]) == 2
    assert "unrecognized arguments: --no-such-flag" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["demo", "--contours", "0"], ["demo", "--objects-per-class", "-1"],
                                  ["generate", "--catalogue", "1", "--contours", "0", "--out", "x.zarr"],
                                  ["generate", "--catalogue", "0", "--out", "x.zarr"],
                                  ["reproduce", "--data", "d", "--workers", "0"], ["recognize", "m.off", "--touches", "-3"],
                                  ["evaluate", "--model", "m", "--store", "s", "--touches", "0"],
                                  ["camera", "--views", "two"]])
def test_counts_are_refused_naming_the_option_before_any_work(argv, capsys, tmp_path, monkeypatch):
    # they named Python internals ("Sizes.unseen_contours", "contours_per_object") or disagreed (-3 vs 0)
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    option = next(a for a in argv if a.startswith("--") and a not in ("--data", "--out", "--model", "--store")
                  and argv[argv.index(a) + 1] in ("0", "-1", "-3", "two"))
    assert len(err) == 1 and f"argument {option}" in err[0] and "must be a positive integer" in err[0], err
    assert list(tmp_path.iterdir()) == []  # nothing written


@pytest.mark.parametrize("argv, names", [(["train", "--seed", "abc"], "--seed"),
                                         (["reproduce", "--parts", "bogus"], "--parts"),
                                         (["demo", "--no-such-flag"], "--no-such-flag"),
                                         ([], "command")])
def test_a_bad_option_is_one_line_naming_it(argv, names, capsys):
    # argparse prints the whole usage (6-9 lines for some subcommands) before its error line by default
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and names in err[0] and "error:" in err[0] and err[0].endswith("--help)"), err


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


def test_the_callers_sigterm_handler_is_set_back():
    """main() turns SIGTERM into an unwinding exception while a command runs; a program calling it gets its own
    handler back whatever the outcome."""
    import signal

    def mine(signum, frame):
        pass

    previous = signal.signal(signal.SIGTERM, mine)
    try:
        assert main(["generate", "--catalogue", "1", "--classes", "teapot", "--out", "x"]) == 2
        assert signal.getsignal(signal.SIGTERM) is mine
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        assert main(["generate", "--catalogue", "1", "--classes", "teapot", "--out", "x"]) == 2
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    finally:
        signal.signal(signal.SIGTERM, previous)
