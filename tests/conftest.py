"""Shared pytest set-up: generated sequences go under pytest's temporary folder.

``adalio.sim.cached_sequence`` writes into ``$ADALIO_CACHE_DIR``. Unless that is set already (to
reuse sequences between sessions on purpose), it points at ``adalio-cache`` in this session's
``tmp_path_factory`` base (``/tmp/pytest-of-$USER/pytest-N``), which is deleted at the end of
the session; the terminal summary says how much it held. A test run leaves nothing in the
repository. The suite's pytest-xdist workers start after the controller's ``pytest_configure``
and inherit its ``ADALIO_CACHE_DIR``, so they share one folder (and its lock files: a sequence
two workers need is generated once); only the controller removes it.

A suite started with Ctrl-C ignored (a background job of a shell without job control, as some
CI scripts start it) would pass that on to every command the tests start, and the Ctrl-C tests
would see their interrupt ignored: the session gives SIGINT back its default, so the commands
start as they do from a terminal.
"""

import os
import shutil
import signal
from pathlib import Path

import matplotlib
import pytest

matplotlib.use("Agg")

REPO = Path(__file__).resolve().parents[1]
_SESSION_CACHE: list[Path] = []

if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


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
    _SESSION_CACHE.append(cache)


HALL_WALK = {"seed": 0, "duration_s": 14.0, "columns": 512}
"""The 14 s hall walk (XT-32 at 512 columns) the sensor checks' run tests share."""


@pytest.fixture(scope="module")
def hall_walk_of():
    """``hall_walk_of(**settings)``: the shared hall walk simulated with other settings (an IMU
    running late, ...)."""
    from adalio.sim import cached_sequence

    return lambda **settings: cached_sequence("hall", **HALL_WALK, **settings)


@pytest.fixture(scope="session")
def turned():
    """``turned(cfg, deg)``: a copy of ``cfg`` whose extrinsic's rotation is turned by ``deg``
    about the fixed unit axis ``turned.axis`` (IMU frame: ``R <- Exp(deg * axis) R``), the
    rotation error the extrinsic checks' run tests give the shared walk."""
    import copy

    import numpy as np
    from scipy.spatial.transform import Rotation

    axis = np.array([0.6, -0.3, 0.74]) / np.linalg.norm([0.6, -0.3, 0.74])

    def turn(cfg, deg: float):
        out = copy.deepcopy(cfg)
        T = cfg.T_imu_lidar()
        T[:3, :3] = Rotation.from_rotvec(np.deg2rad(deg) * axis).as_matrix() @ T[:3, :3]
        out.sensor.T_imu_lidar = T.tolist()
        return out

    turn.axis = axis
    return turn


@pytest.fixture(scope="session")
def summary_text():
    """``summary_text(res)``: what the run summary prints for a ``RunResult`` (a wide console,
    no colour)."""
    import io

    from rich.console import Console

    from adalio.io.cli import _summary

    def text(res) -> str:
        buf = io.StringIO()
        _summary(Console(file=buf, width=400), res, profile=False)
        return buf.getvalue()

    return text


@pytest.fixture
def hall_walk(hall_walk_of):
    """The shared 14 s hall walk as simulated. Looked up for each test: the sequence cache keeps
    only the sequence a process was handed last from eviction, and ``cached_sequence``
    simulates an evicted one again (a longer-lived fixture went stale in CI)."""
    return hall_walk_of()


def pytest_terminal_summary(terminalreporter) -> None:
    for cache in _SESSION_CACHE:
        size = sum(f.stat().st_size for f in cache.rglob("*") if f.is_file())
        terminalreporter.write_line(f"adalio: {size / 1e6:.0f} MB of generated sequences in "
                                    f"{cache} (removed at exit)")


def pytest_unconfigure(config: pytest.Config) -> None:
    while _SESSION_CACHE:
        shutil.rmtree(_SESSION_CACHE.pop(), ignore_errors=True)
