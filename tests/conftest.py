import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The project's real data samples: ``../shared/data`` beside the checkout (or $CM3D_SHARED_DATA)."""
    path = Path(os.environ.get("CM3D_SHARED_DATA", ROOT.parent / "shared" / "data"))
    assert path.is_dir(), f"shared test data not found at {path}; set CM3D_SHARED_DATA"
    return path
