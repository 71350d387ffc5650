"""Operating-system errors (a full disk, no permission) are one ``error:`` line naming the file
or the output folder, exit 2, never a traceback. A full disk is produced for real with a file
size limit (``RLIMIT_FSIZE``): the write fails with EFBIG exactly as it would with ENOSPC."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest

from adalio.cli import os_error_line
from adalio.errors import writing_to

resource = pytest.importorskip("resource")
ADALIO = str(Path(sys.executable).with_name("adalio"))  # the installed console script


def _adalio(args: list[str], limit_bytes: int | None = None) -> subprocess.CompletedProcess:
    def limit() -> None:
        if limit_bytes is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return subprocess.run([ADALIO, *args], check=False,
                          capture_output=True, text=True, timeout=600, preexec_fn=limit)


def _one_error_line(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1, proc.stderr
    for needle in needles:
        assert needle in errors[0], errors[0]


def test_os_error_line_names_the_file_and_what_to_do(tmp_path: Path) -> None:
    full = os_error_line(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / "o")))
    assert full.startswith(f"{tmp_path / 'o'}: {os.strerror(errno.ENOSPC)}")
    assert "free space or write elsewhere (--out)" in full
    assert "cached" not in full  # the output is not in the sequence cache
    anonymous = os_error_line(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
    assert anonymous.startswith(os.strerror(errno.ENOSPC)) and "cached in" in anonymous
    denied = os_error_line(PermissionError(errno.EACCES, os.strerror(errno.EACCES), "/x/y"))
    assert denied == f"/x/y: {os.strerror(errno.EACCES)} (no permission: choose another folder)"


def test_writing_to_names_the_output_only_for_an_anonymous_full_disk(tmp_path: Path) -> None:
    with pytest.raises(OSError) as info, writing_to(tmp_path):
        raise OSError(errno.EFBIG, os.strerror(errno.EFBIG))
    assert info.value.filename == str(tmp_path)
    with pytest.raises(OSError) as info, writing_to(tmp_path):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/elsewhere/file")
    assert info.value.filename == "/elsewhere/file"  # its own file name is kept
    with pytest.raises(OSError) as info, writing_to(tmp_path):
        raise OSError(errno.EIO, os.strerror(errno.EIO))
    assert info.value.filename is None  # not a full disk: nothing is guessed


def test_simulate_on_a_full_disk_is_one_error_line(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    proc = _adalio(["simulate", "--scene", "hall", "--duration", "2", "--columns", "256",
                    "--out", str(out)], limit_bytes=200_000)
    _one_error_line(proc, str(out), os.strerror(errno.EFBIG), "--out")


def test_run_on_a_full_disk_is_one_error_line(tmp_path: Path) -> None:
    seq = tmp_path / "seq"
    made = _adalio(["simulate", "--scene", "hall", "--duration", "3", "--columns", "256",
                    "--out", str(seq)])
    assert made.returncode == 0, made.stderr
    args = ["run", str(seq / "hall.bag"), "--config", str(seq / "config.yaml"), "--no-progress"]
    clean = _adalio([*args, "--out", str(tmp_path / "clean")])  # also fills numba's cache
    assert clean.returncode == 0, clean.stderr
    out = tmp_path / "run"
    proc = _adalio([*args, "--out", str(out)], limit_bytes=20_000)
    _one_error_line(proc, str(out), os.strerror(errno.EFBIG), "--out")
