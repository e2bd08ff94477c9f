"""Shared fixtures: the real data folder (skipped, saying why, where absent), a TMPDIR for child processes; Ctrl-C
handled as Python does by default, whatever the shell that started the tests."""

from __future__ import annotations

import shutil
import signal
import tempfile
from pathlib import Path

import pytest

from perception.data import DATA

# A shell starts a background job (``&``, nohup) with SIGINT ignored, and every process inherits that: the child
# processes the interrupt tests send SIGINT to never saw it, and those tests hung until their timeouts (6 of them,
# 120 s each). A handler set here is reset to the default in every program this process starts, so each child's
# Python installs its usual KeyboardInterrupt handler, as it does when the tests run from a terminal.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def data_folder(name: str) -> Path:
    """The shared data subfolder ``name``, or skip the test with the reason."""
    folder = DATA / name
    if not folder.is_dir():
        pytest.skip(f"real data {folder} is absent (set VISUOTACTILE_DATA to the shared data folder)")
    return folder


@pytest.fixture
def shrec07() -> Path:
    return data_folder("shrec07")


@pytest.fixture
def psb_open() -> Path:
    return data_folder("psb_open")


@pytest.fixture
def ycb() -> Path:
    return data_folder("ycb")


@pytest.fixture
def no_oak() -> None:
    """Skip where an OAK camera is attached (the test checks what happens without one)."""
    from perception.camera import find_oak_devices
    from perception.errors import DeviceNotFoundError

    try:
        if find_oak_devices():
            pytest.skip("an OAK is connected")
    except DeviceNotFoundError:
        pass


@pytest.fixture
def child_tmpdir():
    """A short temporary folder to give a child process as its TMPDIR: what it leaves there (its own temporary
    folders; multiprocessing's socket folder, which only a clean exit removes) goes with the test instead of piling
    up in /tmp. Short, because a Unix socket's path is limited to 107 bytes."""
    folder = tempfile.mkdtemp(prefix="vt-child-")
    yield folder
    shutil.rmtree(folder, ignore_errors=True)
