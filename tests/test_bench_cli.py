"""The benchmarks' command lines reject a bad ``--set`` before any run: one ``error:`` line
naming the key and what is wrong, exit 1, no traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _refused(script: str, args: list[str], names: str, tmp_path: Path) -> None:
    """``script args`` (with ``--out`` under ``tmp_path`` where the script writes one) exits 1
    with one ``error:`` line naming ``names``, no traceback, and nothing written."""
    cmd = [sys.executable, str(BENCHMARKS / script), *args]
    if script not in ("bench_setting.py", "bench_rows.py"):  # these write only their table
        cmd += ["--out", str(tmp_path / "out")]
    proc = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=120,
                          cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and names in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert not any(tmp_path.iterdir())  # no run started


@pytest.mark.parametrize("script", ["bench_modes.py", "bench_sensors.py", "bench_setting.py",
                                    "bench_rows.py"])
@pytest.mark.parametrize(("item", "names"), [
    ("filter.no_such_key=1", "filter.no_such_key"),
    ("filter.robust_scale=-1", "filter.robust_scale"),
    ("filter.robust_kernel", "KEY=VALUE"),
])
def test_bad_set_is_one_error_line(script: str, item: str, names: str, tmp_path: Path) -> None:
    _refused(script, ["--set", item], names, tmp_path)


@pytest.mark.parametrize("args", [["--future-s", "-1"], ["--future-s", "nan"],
                                  ["--warmup-s", "-1"]])
def test_bench_rows_bad_window_is_one_error_line(args: list[str], tmp_path: Path) -> None:
    _refused("bench_rows.py", args, args[0], tmp_path)


@pytest.mark.parametrize(("script", "args", "names"), [
    ("bench_sensors.py", ["--lidar-rates", "100"], "--lidar-rate"),
    ("bench_sensors.py", ["--imu-rates", "5"], "--imu-rate"),
    ("bench_rows.py", ["--lidar-rate", "1"], "--lidar-rate"),
    ("bench_sensors.py", ["--imu-time-offsets-ms", "20", "5000"], "--imu-time-offsets-ms"),
    ("bench_sensors.py", ["--extrinsic-errors-deg", "1", "200"], "--extrinsic-errors-deg"),
    ("bench_sensors.py", ["--imu-bias-scales", "3", "-1"], "--imu-bias-scales"),
])
def test_a_rate_the_simulator_refuses_is_one_error_line(script: str, args: list[str],
                                                        names: str, tmp_path: Path) -> None:
    _refused(script, args, names, tmp_path)
