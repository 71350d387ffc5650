"""The live view: ``adalio run --rrd`` on a short simulated run, read back with rerun's dataframe
API; ``--view`` on a virtual X display, checked by the viewer's own screenshot; missing rerun
and a headless ``--view`` end with one error line."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from adalio.cli import app
from adalio.io.writers import read_tum

ENTITIES = ("/world/scan", "/world/trajectory", "/world/imu", "/world/weakest_direction",
            "/world/map/0000", "/plots/degeneracy/score", "/plots/degeneracy/degenerate",
            "/plots/points/n_raw", "/plots/points/n_down", "/plots/points/n_matched",
            "/plots/sigma/position_z_cm", "/plots/sigma/yaw_deg")


@pytest.fixture(scope="module")
def corridor():
    from adalio.sim import cached_sequence

    return cached_sequence("corridor", seed=0, duration_s=4.0, columns=512)


def test_rrd_recording_has_every_scan(corridor, tmp_path):
    from rerun.chunk import RrdReader

    rrd = tmp_path / "live.rrd"
    out = tmp_path / "run"
    res = CliRunner().invoke(app, ["run", str(corridor.bag_path), "--config",
                                   str(corridor.config_path), "--out", str(out), "--rrd",
                                   str(rrd), "--no-progress"])
    assert res.exit_code == 0, res.output + repr(res.exception)
    assert f"live view recorded to {rrd}" in res.output
    t_ns, _ = read_tum(out / "trajectory.tum")
    assert len(t_ns) > 20

    store = RrdReader(rrd).store().stream().collect()
    table = store.reader(index="scan_time").to_arrow_table()
    columns = table.column_names
    for entity in ENTITIES:
        assert any(c.startswith(entity + ":") for c in columns), (entity, columns)
    scan_col = next(c for c in columns if c.startswith("/world/scan:") and "positions" in c)
    times = table.column("scan_time").to_numpy()
    has_scan = table.column(scan_col).is_valid().to_numpy(zero_copy_only=False)
    scan_times = np.unique(times[has_scan].astype("datetime64[ns]").astype(np.int64))
    assert len(scan_times) == len(t_ns)
    np.testing.assert_array_equal(scan_times, t_ns)

    degenerate = table.column(next(c for c in columns
                                   if c.startswith("/plots/degeneracy/degenerate:")))
    flags = [v[0] for v in degenerate.to_pylist() if v is not None]
    assert len(flags) == len(t_ns) and set(flags) <= {0.0, 1.0}
    map_cols = [c for c in columns if c.startswith("/world/map/") and "positions" in c]
    n_map = sum(len(v) for c in map_cols for v in table.column(c).to_pylist() if v is not None)
    assert n_map > 1000, n_map


def test_view_without_rerun_says_how_to_install(monkeypatch, tmp_path):
    from adalio.errors import AdalioError
    from adalio.view import RerunView

    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(AdalioError, match=r"pip install 'adalio\[view\]'"):
        RerunView(rrd_path=tmp_path / "x.rrd")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="display check is Linux-only")
def test_view_without_display_is_one_error_line(tmp_path):
    env = {k: v for k, v in os.environ.items()
           if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-c", "from adalio.cli import main; main()", "run",
                           str(tmp_path / "missing.bag"), "--view"], capture_output=True,
                          text=True, env=env, timeout=60, check=False)
    # the bag is checked after the viewer, so the headless error comes first
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --view needs a display"), lines


def _display_without_server() -> str:
    """A display number no X server listens on here."""
    return next(f":{n}" for n in range(99, 40, -1) if not os.path.exists(f"/tmp/.X11-unix/X{n}"))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="X displays are Linux-only")
def test_view_on_a_display_that_does_not_answer_is_one_error_line(tmp_path):
    """DISPLAY set, but no X server behind it (a lost ssh -X session): the viewer exits as it
    starts. One error line with its reason, before the bag is read; with --rrd, a warning and the
    recording alone. (Before session 77 the run went on for its whole length, the viewer's log
    on the screen, its messages lost, exit 0.)"""
    pytest.importorskip("rerun")
    sys.path.insert(0, str(Path(__file__).resolve().parent / "io"))
    import bagfactory as bf

    env = {k: v for k, v in os.environ.items() if k != "WAYLAND_DISPLAY"}
    env["DISPLAY"] = _display_without_server()
    port = str(_free_port())
    code = ("import sys, adalio.view; adalio.view.VIEWER_PORT = int(sys.argv.pop(1)); "
            "from adalio.cli import main; main()")
    proc = subprocess.run([sys.executable, "-c", code, port, "run", str(tmp_path / "missing.bag"),
                           "--view"], capture_output=True, text=True, env=env, timeout=120,
                          check=False)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("error: --view: the rerun viewer exited as it started on "
                               f"display {env['DISPLAY']} (")
    assert lines[0].endswith("record with --rrd FILE and open it elsewhere with `rerun FILE`")
    rig = bf.write_static_rig(tmp_path / "rig.bag", duration_s=1.5, columns=60)
    rrd = tmp_path / "rec" / "run.rrd"
    proc = subprocess.run([sys.executable, "-c", code, port, "run", str(rig), "--view", "--rrd",
                           str(rrd), "--out", str(tmp_path / "out"), "--no-progress"],
                          capture_output=True, text=True, env=env, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    warned = [ln for ln in proc.stderr.splitlines() if "rerun viewer" in ln]
    assert len(warned) == 1 and warned[0].startswith("warning: --view: the rerun viewer exited")
    assert warned[0].endswith("writing only the .rrd"), warned
    assert rrd.stat().st_size > 0 and (tmp_path / "out" / "trajectory.tum").stat().st_size > 0
    assert "WARN" not in proc.stderr and "ERROR" not in proc.stderr, proc.stderr


FAKE_VIEWER = """
import socket, sys, time
port = int(next(a for a in sys.argv if a.startswith("--port=")).split("=")[1])
mode = sys.argv[1]
if mode == "fails":
    print("Error: no window for you"); sys.exit(1)
s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(("127.0.0.1", port)); s.listen()
if mode == "listens_then_panics":
    time.sleep(0.3); print("thread 'main' panicked at 'no render context'"); sys.exit(101)
time.sleep(60)
"""


@pytest.mark.parametrize("mode", ["stays", "fails", "listens_then_panics"])
def test_start_viewer_waits_until_the_viewer_is_up_or_says_why_it_is_not(tmp_path, mode):
    """The viewer's start, against processes that behave as the rerun viewer was seen to: up
    and listening; exiting with an ``Error:`` line (no X server); listening, then panicking
    (no render context, 0.6 s after the port here)."""
    from adalio.errors import AdalioError
    from adalio.view import _listening, start_viewer

    exe = tmp_path / "viewer"
    exe.write_text(f"#!{sys.executable}\nimport sys; sys.argv.insert(1, {mode!r})\n"
                   + FAKE_VIEWER)
    exe.chmod(0o755)
    port = _free_port()
    if mode == "stays":
        proc = start_viewer(str(exe), port)
        try:
            assert proc is not None and proc.poll() is None and _listening(port)
            assert start_viewer(str(exe), port) is None  # one listens there already: reused
        finally:
            proc.kill()
            proc.wait()
        return
    why = "(Error: no window for you)" if mode == "fails" else \
        "(thread 'main' panicked at 'no render context')"
    with pytest.raises(AdalioError) as info:
        start_viewer(str(exe), port)
    assert str(info.value).startswith("--view: the rerun viewer exited as it started")
    assert str(info.value).endswith(why), str(info.value)


def test_rrd_where_it_cannot_be_written_is_one_error_line(tmp_path):
    """A recording path rerun cannot open is one `error:` line naming it (was rerun's
    RuntimeError as a traceback)."""
    pytest.importorskip("rerun")
    bad = "/proc/adalio-test/run.rrd"  # /proc takes no new folder, also for root
    proc = subprocess.run([sys.executable, "-c", "from adalio.cli import main; main()", "run",
                           str(tmp_path / "any.bag"), "--rrd", bad], capture_output=True,
                          text=True, timeout=60, check=False)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if "WARN" not in ln]
    assert len(lines) == 1 and lines[0].startswith(f"error: --rrd {bad}: cannot write the "
                                                   "recording there"), proc.stderr


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _x_server_answers(display: str, timeout_s: float = 10.0) -> bool:
    """Whether the X server on ``:display`` completes a connection handshake (protocol 11.0, no
    auth) within the timeout. Xvfb reports its display number before it accepts clients."""
    setup = b"l\x00\x0b\x00\x00\x00\x00\x00\x00\x00\x00\x00"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(2.0)
                s.connect(f"/tmp/.X11-unix/X{display}")
                s.sendall(setup)
                if s.recv(1) == b"\x01":
                    return True
        except OSError:
            pass
        time.sleep(0.1)
    return False


def _pixels_near(rgb_image: np.ndarray, rgb: tuple[int, int, int], tol: int = 30) -> int:
    return int((np.abs(rgb_image - np.asarray(rgb)).max(axis=-1) < tol).sum())


@pytest.mark.skipif(shutil.which("Xvfb") is None, reason="needs Xvfb for a virtual display")
def test_live_view_on_a_virtual_display(corridor, tmp_path, monkeypatch):
    """``adalio run --view`` on an X display: the spawned viewer window receives the whole run
    and paints it. Its own screenshot of the 3D view (rerun's ViewerClient) must show the scan
    in the general/degenerate colours and the grey map, which neither the background nor the
    grid (at most ~60 grey) has."""
    import matplotlib.image as mpimg
    from rerun.experimental import ViewerClient

    import adalio.view

    read_fd, write_fd = os.pipe()
    with open(tmp_path / "xvfb.log", "w") as xlog:
        # Xvfb may write its display number again (after a reset, when its last client leaves,
        # e.g. the handshake probe): the read end stays open until it exits, and -noreset
        # keeps the probe from resetting it
        xvfb = subprocess.Popen(["Xvfb", "-displayfd", str(write_fd), "-noreset", "-screen", "0",
                                 "1280x800x24"], pass_fds=(write_fd,), stderr=xlog)
    os.close(write_fd)
    port = _free_port()
    try:
        display = os.read(read_fd, 32).decode().strip()
        assert display and _x_server_answers(display), (tmp_path / "xvfb.log").read_text()
        monkeypatch.setenv("DISPLAY", f":{display}")
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        monkeypatch.setattr(adalio.view, "VIEWER_PORT", port)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = CliRunner().invoke(app, ["run", str(corridor.bag_path), "--config",
                                           str(corridor.config_path), "--out",
                                           str(tmp_path / "run"), "--view", "--no-progress"])
        if res.exit_code and "graphics driver is lacking" in str(res.exception):
            pytest.skip(f"the viewer cannot draw on this machine's display: {res.exception}")
        assert res.exit_code == 0, res.output + repr(res.exception)
        assert not [w for w in caught if "viewer" in str(w.message)], [str(w.message)
                                                                          for w in caught]
        views = adalio.view.blueprint()[1]
        client = ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
        whole, world = tmp_path / "viewer.png", tmp_path / "world.png"
        client.save_screenshot(str(whole))
        client.save_screenshot(str(world), view_id=views["world"].id)
    finally:
        # the viewer first (it panics when its display goes away), then the display
        subprocess.run(["pkill", "-f", f"rerun.*port={port}"], check=False)
        time.sleep(0.5)
        xvfb.terminate()
        xvfb.wait(timeout=10)
        os.close(read_fd)
    image = (mpimg.imread(world)[..., :3] * 255).round().astype(int)
    assert image.shape[0] > 300 and image.shape[1] > 300, image.shape
    scan = (_pixels_near(image, adalio.view.DEGENERATE_RGB)
            + _pixels_near(image, adalio.view.GENERAL_RGB))
    assert scan > 200, scan
    assert _pixels_near(image, adalio.view.MAP_RGB) > 200
    window = mpimg.imread(whole)
    assert window.shape[0] > image.shape[0] and window.shape[1] > image.shape[1]
