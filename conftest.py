"""Doctests write their temporary files into pytest's own folder, which pytest cleans up (the examples call
``tempfile.mkdtemp()`` as a user would, and left a folder in /tmp on every run)."""

import tempfile

import pytest


@pytest.fixture(autouse=True)
def _doctest_tmpdir(request, monkeypatch):
    if isinstance(request.node, pytest.DoctestItem):  # tmp_path only for doctests: not a folder for every test
        monkeypatch.setattr(tempfile, "tempdir", str(request.getfixturevalue("tmp_path")))
