"""Disk space: ``simulate`` checks for the whole sequence's room before writing, against an
upper bound that the written bags stay under, and the sequence cache evicts to make that room
(even sequences its cap would keep) before giving up with one ``error:`` line."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
import time
from collections import namedtuple
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

import adalio.sim.cache as cache_mod
from adalio import cli
from adalio.sim import generate
from adalio.sim.cache import LOCKS, cached_sequence, evict_cache, reserved_bytes
from adalio.sim.generate import SPARE_BYTES, sequence_bytes, simulate

Usage = namedtuple("Usage", "total used free")


def _bytes(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


@pytest.mark.parametrize("fmt", ["ros1", "ros2", "mcap"])
def test_written_bags_stay_within_the_estimated_size(tmp_path: Path, fmt: str) -> None:
    """The estimate is an upper bound of what is written, in every format, without its spare
    room: the free-space check never lets a generation run out of disk on the bag alone."""
    res = simulate("corridor", tmp_path / fmt, duration_s=1.5, columns=64, fmt=fmt)
    meta = json.loads(res.meta_path.read_text())
    bound = sequence_bytes(meta["n_scans"], meta["columns"], meta["channels"], meta["n_imu"])
    written = _bytes(res.bag_path)
    assert written <= bound - SPARE_BYTES, (written, bound - SPARE_BYTES)
    if fmt != "mcap":  # and a close one where nothing is compressed: indoors most beams return
        assert written >= 0.8 * (bound - SPARE_BYTES)


def test_simulate_refuses_before_writing_when_the_disk_lacks_room(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setattr(generate.shutil, "disk_usage", lambda p: Usage(10**12, 0, 10**6))
    out = tmp_path / "seq"
    with pytest.raises(OSError) as info:
        simulate("hall", out, duration_s=2.0, columns=128, make_room=seen.append)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(out)
    assert "not enough free space" in info.value.strerror
    assert len(seen) == 1 and seen[0] > SPARE_BYTES  # make_room was asked for the same size
    assert not any(out.iterdir())  # nothing written, no partial bag


def test_cli_simulate_without_room_is_one_error_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(generate.shutil, "disk_usage", lambda p: Usage(10**12, 0, 10**6))
    out = tmp_path / "seq"
    monkeypatch.setattr(sys, "argv", ["adalio", "simulate", "--scene", "hall", "--duration",
                                      "2", "--columns", "128", "--out", str(out)])
    with pytest.raises(SystemExit) as info:
        cli.main()
    err = capsys.readouterr().err
    assert info.value.code == 2 and "Traceback" not in err
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1, err
    assert str(out) in errors[0] and "not enough free space" in errors[0]
    assert "free space or write elsewhere (--out)" in errors[0]


def _entry(root: Path, name: str, n_bytes: int, last_use_s: float) -> Path:
    d = root / name
    d.mkdir(parents=True)
    (d / "data.bin").write_bytes(b"x" * n_bytes)
    (d / "COMPLETE").write_text("ok\n")
    os.utime(d / "COMPLETE", (last_use_s, last_use_s))
    return d


def _small_disk(monkeypatch, root: Path, capacity: int) -> None:
    """The cache's disk as a disk of ``capacity`` bytes holding only the cache folder."""
    def usage(path):
        used = _bytes(root)
        return Usage(capacity, used, capacity - used)

    monkeypatch.setattr(cache_mod.shutil, "disk_usage", usage)


def test_eviction_makes_room_on_the_disk_before_the_cap(tmp_path, monkeypatch):
    now = time.time()
    root = tmp_path / "sim"
    a = _entry(root, "a-v1", 40_000, now - 30)
    b = _entry(root, "b-v1", 40_000, now - 20)
    c = _entry(root, "c-v1", 40_000, now - 10)
    _small_disk(monkeypatch, root, 150_000)  # about 30 kB free
    # every entry is within the cap and used within the protection window: the cap keeps all
    assert evict_cache(root, 10**9, need_bytes=0, version="1") == []
    # room for 60 kB: the least recently used go until it is there, protected or not
    removed = evict_cache(root, 10**9, need_bytes=60_000, version="1")
    assert removed == [a] and not a.exists() and b.exists() and c.exists()
    assert shutil.disk_usage(root).free >= 60_000
    # more than an empty cache would give: nothing goes for it (the caller's check reports)
    assert evict_cache(root, 10**9, need_bytes=10**9, version="1") == []
    assert b.exists() and c.exists()
    # room for 60 kB and 20 kB to spare: the next least recently used goes too
    assert evict_cache(root, 10**9, need_bytes=60_000, version="1", headroom_bytes=20_000) == [b]
    assert c.exists() and shutil.disk_usage(root).free >= 80_000


def test_a_generation_leaves_the_headroom_free(tmp_path, monkeypatch):
    """Sequences used minutes ago are protected from the cap, not from the disk: the cache
    frees the new sequence's room plus a share of the disk (5 %, at most 10 GB), so the
    generation does not leave the disk full for the runs that follow."""
    monkeypatch.setenv("ADALIO_CACHE_DIR", str(tmp_path))
    # the first two without a headroom: on a real disk with less free than that, the second
    # would already evict the first
    headroom_max = cache_mod.HEADROOM_MAX_BYTES
    monkeypatch.setattr(cache_mod, "HEADROOM_MAX_BYTES", 0)
    old = cached_sequence("corridor", duration_s=1.0, columns=36)
    new = cached_sequence("corridor", seed=1, duration_s=1.0, columns=36)
    assert old.bag_path.is_file()
    monkeypatch.setattr(cache_mod, "HEADROOM_MAX_BYTES", headroom_max)
    os.utime(old.bag_path.parent / "COMPLETE", (time.time() - 60, time.time() - 60))
    root = old.bag_path.parent.parent
    need = sequence_bytes(10, 36, 32, 401)  # its bound (0.2 GB of it spare) dwarfs the bags
    capacity = _bytes(root) + need + 1000  # room for the third, not for the headroom
    _small_disk(monkeypatch, root, capacity)
    assert cache_mod.headroom_bytes(root) == int(0.05 * capacity)
    monkeypatch.setattr(cache_mod, "HEADROOM_MAX_BYTES", 1000 + _bytes(old.bag_path.parent) // 2)
    third = cached_sequence("corridor", seed=2, duration_s=1.0, columns=36)
    assert third.bag_path.is_file() and new.bag_path.is_file()
    assert not old.bag_path.exists()  # the least recently used went for the headroom


def test_another_simulator_version_goes_first_and_unprotected(tmp_path):
    now = time.time()
    root = tmp_path / "sim"
    old = _entry(root, "hall-s0-vdeadbeef", 30_000, now - 5)  # used seconds ago
    cur_a = _entry(root, "hall-s0-v12345678", 30_000, now - 50)
    cur_b = _entry(root, "hall-s1-v12345678", 30_000, now - 40)
    sizes = _bytes(cur_a) + _bytes(cur_b)
    removed = evict_cache(root, sizes + 100, version="12345678")
    assert removed == [old] and cur_a.exists() and cur_b.exists()
    # without a version every folder counts as current: a recent one is protected
    again = _entry(root, "hall-s0-vdeadbeef", 30_000, now - 5)
    assert evict_cache(root, sizes + 100) == [] and again.exists()


def test_cached_sequence_evicts_for_room_then_reports_what_is_missing(tmp_path, monkeypatch):
    monkeypatch.setenv("ADALIO_CACHE_DIR", str(tmp_path))
    first = cached_sequence("corridor", duration_s=1.0, columns=36)
    root = first.bag_path.parent.parent
    need = sequence_bytes(10, 36, 32, 401)  # 1 s: 10 sweeps, 401 IMU samples
    # a disk with room for the new sequence only once the first one is gone
    _small_disk(monkeypatch, root, _bytes(root) + need - 1)  # shutil: generate's too
    second = cached_sequence("corridor", seed=1, duration_s=1.0, columns=36)
    assert second.bag_path.is_file() and not first.bag_path.exists()
    # a disk that cannot hold it even empty: an ENOSPC in the cache, nothing evicted for it
    _small_disk(monkeypatch, root, need // 2)
    with pytest.raises(OSError) as info:
        cached_sequence("corridor", seed=2, duration_s=1.0, columns=36)
    assert info.value.errno == errno.ENOSPC and str(root) in info.value.filename
    assert "not enough free space" in info.value.strerror
    assert "reserved" not in info.value.strerror  # no other generation holds any
    # no temp folder, and no reservation left
    assert [p.name for p in root.iterdir() if p.name != LOCKS] == [second.bag_path.parent.name]
    assert not list((root / LOCKS).glob("*.reserve"))


def _reserve(root: Path, pid: int, need: int, folder: Path) -> Path:
    f = root / LOCKS / f"{pid}-test.reserve"
    f.parent.mkdir(parents=True, exist_ok=True)
    f.write_text(f"{need}\n{folder}\n")
    return f


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_reserved_bytes_count_what_live_generations_still_need(tmp_path):
    root = tmp_path / "sim"
    folder = root / ".x.tmp-1"
    folder.mkdir(parents=True)
    (folder / "part.bin").write_bytes(b"x" * 30_000)
    live = _reserve(root, os.getpid(), 100_000, folder)
    assert reserved_bytes(root) == 70_000  # asked for 100 kB, 30 kB of it written
    (folder / "more.bin").write_bytes(b"x" * 90_000)
    assert reserved_bytes(root) == 0  # never negative
    live.unlink()
    dead = _reserve(root, _dead_pid(), 100_000, folder)
    assert reserved_bytes(root) == 0 and not dead.exists()  # a dead process's goes


def test_cached_sequence_counts_the_room_other_generations_reserved(tmp_path, monkeypatch):
    """Two benchmarks generating at once: each checks the disk for itself, so without
    reservations both see room for their own sequence and together fill it."""
    monkeypatch.setenv("ADALIO_CACHE_DIR", str(tmp_path))
    first = cached_sequence("corridor", duration_s=1.0, columns=36)
    root = first.bag_path.parent.parent
    need = sequence_bytes(10, 36, 32, 401)
    _small_disk(monkeypatch, root, _bytes(root) + 2 * need)  # room for two more sequences
    other = root / ".other.tmp-1"
    other.mkdir()
    reservation = _reserve(root, os.getpid(), 2 * need, other)  # another one needs both
    with pytest.raises(OSError) as info:
        cached_sequence("corridor", seed=1, duration_s=1.0, columns=36)
    assert info.value.errno == errno.ENOSPC and str(root) in info.value.filename
    assert "reserved by other generations in progress" in info.value.strerror
    assert first.bag_path.is_file()  # nothing evicted for a room it could not make
    # the other generation took a quarter of what it asked for and finished: room for one more,
    # and for the headroom (5 % of this disk)
    (other / "part.bin").write_bytes(b"x" * (need // 2))
    reservation.unlink()
    second = cached_sequence("corridor", seed=1, duration_s=1.0, columns=36)
    assert second.bag_path.is_file() and first.bag_path.is_file()


def test_one_process_generates_a_key_the_others_wait_and_reuse(tmp_path, monkeypatch):
    monkeypatch.setenv("ADALIO_CACHE_DIR", str(tmp_path))
    calls = []
    real = cache_mod.simulate

    def slow_simulate(*args, **kwargs):
        calls.append(args[1])
        time.sleep(0.5)  # the others arrive while it generates
        return real(*args, **kwargs)

    monkeypatch.setattr(cache_mod, "simulate", slow_simulate)
    with ThreadPoolExecutor(3) as pool:
        results = list(pool.map(
            lambda _: cached_sequence("hall", duration_s=1.0, columns=36), range(3)))
    assert len(calls) == 1
    assert {r.bag_path for r in results} == {results[0].bag_path}
    assert results[0].bag_path.is_file()


_TRY_EXCLUSIVE = """import fcntl, sys
fh = open(sys.argv[1], "a")
try:
    fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
except OSError:
    sys.exit(1)
"""


def _free_in_another_process(path: Path) -> bool:
    """Could another process lock ``path`` exclusively right now (no one holds it)?"""
    return subprocess.run([sys.executable, "-c", _TRY_EXCLUSIVE, str(path)],
                          check=False).returncode == 0


@pytest.mark.skipif(cache_mod.fcntl is None, reason="needs fcntl (POSIX)")
def test_eviction_skips_a_sequence_another_process_holds(tmp_path):
    """A sequence a process is using (its ``.use`` lock held shared) is not evicted, by the cap
    or for the disk, even when it is the least recently used; once let go, it is."""
    now = time.time()
    root = tmp_path / "sim"
    a = _entry(root, "a-v1", 40_000, now - 300)
    b = _entry(root, "b-v1", 40_000, now - 200)
    (root / LOCKS).mkdir()
    hold = ("import fcntl, sys\nfh = open(sys.argv[1], 'a')\nfcntl.flock(fh, fcntl.LOCK_SH)\n"
            "print('held', flush=True)\nsys.stdin.read()\n")
    holder = subprocess.Popen([sys.executable, "-c", hold, str(root / LOCKS / "a-v1.use")],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert evict_cache(root, 0, protect_s=0) == [b]
        assert a.exists()
        c = _entry(root, "c-v1", 40_000, now - 100)
        assert evict_cache(root, 10**9, protect_s=0, need_bytes=shutil.disk_usage(root).free
                           + 10**6) == []  # not even for the disk
        assert a.exists() and c.exists()
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)
    assert evict_cache(root, 0, protect_s=0) == [a, c]


@pytest.mark.skipif(cache_mod.fcntl is None, reason="needs fcntl (POSIX)")
def test_the_sequence_handed_out_last_stays_held(tmp_path, monkeypatch):
    """``cached_sequence`` holds the sequence it returns until it returns another: another
    process's eviction then keeps the one in use and removes the one let go."""
    monkeypatch.setenv("ADALIO_CACHE_DIR", str(tmp_path))
    first = cached_sequence("corridor", duration_s=1.0, columns=36)
    root = first.bag_path.parent.parent

    def use_lock(res):
        return root / LOCKS / f"{res.bag_path.parent.name}.use"

    assert not _free_in_another_process(use_lock(first))
    second = cached_sequence("corridor", seed=1, duration_s=1.0, columns=36)
    assert _free_in_another_process(use_lock(first))
    assert not _free_in_another_process(use_lock(second))
    evict = ("import sys\nfrom pathlib import Path\nfrom adalio.sim.cache import evict_cache\n"
             "evict_cache(Path(sys.argv[1]), 0, protect_s=0)\n")
    subprocess.run([sys.executable, "-c", evict, str(root)], check=True)
    assert not first.bag_path.exists() and second.bag_path.is_file()
