"""Shared helpers of the command-line tests: a small simulated rig on virtual time."""

from __future__ import annotations

import uuid
from pathlib import Path

import pytest

from rigd.app.config import default_sim_rig


@pytest.fixture
def small_rig(tmp_path: Path) -> Path:
    """A config file of the sim rig at 320x180 mono, on virtual time (fast and repeatable)."""
    cfg = default_sim_rig(
        world=f"cli-{uuid.uuid4().hex[:8]}", resolution=(320, 180), pixel_format="mono8", clock="virtual"
    )
    path = tmp_path / "rig.json"
    path.write_text(cfg.model_dump_json())
    return path
