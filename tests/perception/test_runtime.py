"""Runtime information and the progress switch: one version, one machine description, one place that decides
whether a progress bar shows."""

from __future__ import annotations

import configparser
from pathlib import Path

import pytest

import perception
from perception import runtime

ROOT = Path(__file__).resolve().parents[2]


class TestVersion:
    def test_version_is_the_packages_or_the_checkouts(self):
        """``__version__`` is the installed metadata's version, which is setup.cfg's in a checkout."""
        cfg = configparser.ConfigParser()
        cfg.read(ROOT / "setup.cfg")
        assert perception.__version__ == runtime.package_version() == cfg.get("metadata", "version")

    def test_versions_name_python_numpy_the_toolkit_and_what_is_asked(self):
        found = runtime.versions("scikit-learn", "no-such-distribution-xyz")
        assert found["visuotactile"] == perception.__version__
        assert found["no-such-distribution-xyz"] == "not installed"
        assert {"python", "numpy", "scikit-learn"} <= set(found)

    def test_a_saved_model_records_the_version(self, tmp_path):
        from fusion.modelfile import read_model_file
        from tests.fusion._synthetic import circle_batch
        from tests.fusion.test_base import MeanFrame

        path = MeanFrame().fit(circle_batch([19, 20, 58, 60], labels=[0, 0, 1, 1])).save(tmp_path / "m.vtm")
        description, _ = read_model_file(path)
        assert description["versions"]["visuotactile"] == perception.__version__

    def test_a_store_records_the_version(self, tmp_path):
        from tactile.dataset import generate, open_dataset
        from tactile.sensor import FSRSensor

        generate([("box", 0)], tmp_path / "s", strategies="blind", contours_per_object=1, probes=3,
                 sensor=FSRSensor(rows=4, cols=4), workers=1, progress=False)
        assert open_dataset(tmp_path / "s").attrs["package_version"] == perception.__version__


class TestMachine:
    def test_machine_counts_cores(self):
        info = runtime.machine()
        assert 1 <= info["cores_available"] <= info["cpu_count"]
        assert f"{info['cores_available']} usable" in runtime.machine_line()

    INTEL = ("processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: Intel(R) Xeon(R) Platinum 8488C\n"
             "flags\t\t: fpu sse2 avx avx2 fma avx512f avx512bw avx512_bf16 amx_bf16 amx_tile\n\n"
             "processor\t: 1\nmodel name\t: Intel(R) Xeon(R) Platinum 8488C\nflags\t\t: fpu avx2\n")
    AMD = "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse2 avx fma avx2 sha_ni\n"
    ARM = "processor\t: 0\nBogoMIPS\t: 50.00\nFeatures\t: fp asimd evtstrm aes crc32\nCPU part\t: 0xd0c\n"

    @pytest.mark.parametrize("text, expected", [
        (INTEL, ("Intel(R) Xeon(R) Platinum 8488C", "amx_tile+avx512_bf16+avx512f+avx2")),
        (AMD, ("AMD EPYC", "avx2")),
        (ARM, ("", "asimd")),
        ("", ("", "")),
        ("model name : \x00 odd\tspacing  here\nflags:\n", ("\x00 odd spacing here", "")),
    ])
    def test_cpu_description_reads_the_model_and_the_widest_vector_extensions(self, text, expected):
        """The first CPU's entries: a later CPU listing fewer flags does not count (hand-made /proc/cpuinfo texts)."""
        assert runtime.cpu_description(text) == expected

    def test_machine_line_names_the_cpu(self, monkeypatch):
        monkeypatch.setattr(runtime, "_cpu", lambda: ("AMD EPYC", "avx2"))
        assert "AMD EPYC (avx2) " in runtime.machine_line()
        assert runtime.machine()["cpu_vector"] == "avx2"
        monkeypatch.setattr(runtime, "_cpu", lambda: ("", ""))
        assert "()" not in runtime.machine_line() and "  " not in runtime.machine_line()


class TestProgressSwitch:
    @pytest.fixture(autouse=True)
    def _reset(self, monkeypatch):
        monkeypatch.delenv(runtime.PROGRESS_ENV, raising=False)
        yield
        runtime.set_progress(None)

    def test_a_bar_shows_only_when_asked_and_switched_on(self, monkeypatch):
        assert runtime.progress_enabled(True) and not runtime.progress_enabled(False)
        runtime.set_progress(False)
        assert not runtime.progress_enabled(True)
        assert runtime.progress_bar(range(3), enabled=True).disable
        runtime.set_progress(None)
        monkeypatch.setenv(runtime.PROGRESS_ENV, "0")
        assert not runtime.progress_enabled(True)
        runtime.set_progress(True)  # an explicit switch wins over the environment
        assert runtime.progress_enabled(True) and not runtime.progress_enabled(False)

    def test_a_bar_in_a_log_writes_a_line_per_half_minute_not_per_postfix(self):
        """Not a terminal: a training run's per-epoch postfix waits for the next scheduled line (tqdm writes one
        at once otherwise: 50 lines here); the start and the end are written."""
        import io

        log = io.StringIO()
        bar = runtime.progress_bar(range(50), enabled=True, desc="train", file=log)
        for i in bar:
            bar.set_postfix(loss=f"{i}")
            bar.set_postfix_str(f"objects {i}")
        bar.close()
        lines = [line for line in log.getvalue().split("\r") if line.strip()]
        assert len(lines) == 2
        assert lines[0].startswith("train:   0%") and "50/50" in lines[1] and "objects 49" in lines[1]
        assert bar.mininterval == 30.0

    def test_a_bar_on_a_closed_stream_or_switched_off_by_its_caller_does_not_raise(self):
        import io

        closed = io.StringIO()
        closed.close()
        assert runtime.progress_bar(range(3), enabled=False, file=closed).disable
        assert runtime.progress_bar(range(3), enabled=True, disable=True).disable
        assert list(runtime.progress_bar(range(3), enabled=True, disable=True)) == [0, 1, 2]

    def test_the_command_line_switch_holds_for_one_command(self, monkeypatch, capsys):
        """``--no-progress`` turns the switch off while the command runs and restores it after."""
        from fusion import cli

        seen = []
        monkeypatch.setattr("fusion.commands.verify.run", lambda args, rest: seen.append(
            runtime.progress_enabled(True)) or 0)
        assert cli.main(["verify", "x.zarr", "--no-progress"]) == 0
        assert seen == [False] and runtime.progress_enabled(True)


def test_limit_cores_bounds_open3d_and_lifting_it_restores_open3d_default():
    """Open3D's ray casting spreads over every core unless told: ``limit_cores`` tells it, and None lifts the limit."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        import open3d as o3d
        from perception import runtime
        default = o3d.utility.get_max_threads()
        runtime.limit_cores(1)
        print(o3d.utility.get_max_threads(), runtime.usable_cores())
        runtime.limit_cores(None)
        print(o3d.utility.get_max_threads() == default)
        for n in (0, -1):  # one core: never Open3D's "no limit" 0, nor its error for a negative count
            runtime.limit_cores(n)
            print(o3d.utility.get_max_threads(), runtime.usable_cores())
    """)
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True, text=True, timeout=120,
                         env={**__import__("os").environ, "PYTHONPATH": str(root)}, check=True).stdout.split()
    assert out == ["1", "1", "True", "1", "1", "1", "1"]
