"""Shared pytest set-up: generated data goes to the repo's git-ignored .cache folder."""

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("ADALIO_CACHE_DIR", str(REPO / ".cache"))
