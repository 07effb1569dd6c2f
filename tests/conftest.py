"""Shared test fixtures: where the shared real-data folder lives, and a skip when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

from reconstruction.parallel import configure_openmp

# As the CLI does (deploy/cli.py): OpenMP threads that spin only briefly, set before torch is imported.
configure_openmp()
# MuJoCo picks its GL backend when first imported, and collection may import it through any module:
# headless EGL, as rig/render_mujoco.py asks for, on machines with no display.
os.environ.setdefault("MUJOCO_GL", "egl")

import pytest  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def shared_data() -> Path:
    """`../shared/data` beside the checkout (CI has it; a user's fresh clone does not)."""
    return Path(os.environ.get("CADSPLAT_SHARED_DATA", REPO.parent / "shared" / "data"))


def require_shared(*parts: str) -> Path:
    """Path under the shared data folder, or skip the test with the reason a user would accept."""
    path = shared_data().joinpath(*parts)
    if not path.exists():
        pytest.skip(f"needs the shared real-data folder ({path} is absent in a fresh clone)")
    return path
