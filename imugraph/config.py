"""Where the shared real recordings live: $IMUGRAPH_DATA, else ../shared/data beside the repository."""

from __future__ import annotations

import os
from pathlib import Path

_REPO_ROOT = Path(__file__).resolve().parents[1]


def data_dir() -> Path:
    """Return the configured data directory (it may not exist; callers check)."""
    env = os.environ.get("IMUGRAPH_DATA")
    if env:
        return Path(env)
    return (_REPO_ROOT / ".." / "shared" / "data").resolve()


def broad_dir() -> Path:
    return data_dir() / "broad"
