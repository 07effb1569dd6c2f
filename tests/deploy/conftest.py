"""Fixtures shared by the deploy tests: the bundled sample's CAD library, built once."""

from __future__ import annotations

import pytest

from deploy.commands.demo import bundled_sample_dir


@pytest.fixture(scope="session")
def library(tmp_path_factory):
    """The library built from the bundled sample's meshes (the sample ships with the repository)."""
    sample = bundled_sample_dir()
    from reconstruction.library import build_library

    out = tmp_path_factory.mktemp("lib") / "library"
    build_library(sample / "library_meshes", out, progress=False, log=lambda _m: None)
    return out
