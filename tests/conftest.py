"""Shared pytest set-up: generated sequences go under pytest's temporary folder.

``adalio.sim.cached_sequence`` writes into ``$ADALIO_CACHE_DIR``; unless that is set already
(to reuse sequences between sessions on purpose), it points at a folder of this session's
``tmp_path_factory`` base (``/tmp/pytest-of-$USER/pytest-N``, of which pytest keeps the last
three), so a test run leaves nothing in the repository.
"""

import os
from pathlib import Path

import matplotlib
import pytest

matplotlib.use("Agg")

REPO = Path(__file__).resolve().parents[1]


@pytest.hookimpl(trylast=True)
def pytest_configure(config: pytest.Config) -> None:
    if os.environ.get("ADALIO_CACHE_DIR"):
        return
    factory = getattr(config, "_tmp_path_factory", None)
    if factory is not None:
        cache = factory.getbasetemp() / "adalio-cache"
    else:  # the tmpdir plugin is disabled: still stay out of the repository
        import tempfile

        cache = Path(tempfile.mkdtemp(prefix="adalio-cache-"))
    cache.mkdir(parents=True, exist_ok=True)
    os.environ["ADALIO_CACHE_DIR"] = str(cache)
