"""Data shipped with the package: a small sample scene to try the tool on (see CREDITS.md here)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

SAMPLE_NAME = "plant_crop.ply"


def sample_path() -> Path:
    """Path of the shipped sample: a 20,000-splat crop of the "plant" scene by Marcel Padilla,
    CC-BY-4.0 (a real file, also from an installed wheel)."""
    return Path(str(resources.files(__name__) / SAMPLE_NAME))
