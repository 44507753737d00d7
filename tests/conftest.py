"""Shared test fixtures and helpers."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parent.parent
CONF_DIR = REPO / "conf"
SHARED_VDB = REPO.parent / "shared" / "data" / "wdas_cloud_sixteenth.vdb"

torch.set_num_threads(2)


def compose(overrides: list[str] | None = None):
    """The resolved app config for ``overrides`` (as ``python -m nrc`` would see it)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose(config_name="config", overrides=overrides or [])


@pytest.fixture
def shared_vdb() -> Path:
    if not SHARED_VDB.is_file():
        pytest.skip(f"shared Disney cloud not found at {SHARED_VDB}")
    return SHARED_VDB
