"""The sequence cache: ``cached_sequence`` generates a sequence once per key under
``$ADALIO_CACHE_DIR/sim`` and keeps the folder under ``$ADALIO_SIM_CACHE_GB`` (least recently
used first out)."""

from __future__ import annotations

import hashlib
import os
import shutil
import time
import uuid
from pathlib import Path

from adalio.errors import InputError
from adalio.sim.bagout import bag_path_for
from adalio.sim.generate import SimResult, _check_args, simulate
from adalio.sim.lidar import lidar_model


def cache_root() -> Path:
    """``$ADALIO_CACHE_DIR`` (default ``~/.cache/adalio``) / sim."""
    return Path(os.environ.get("ADALIO_CACHE_DIR", "~/.cache/adalio")).expanduser() / "sim"


CACHE_BUDGET_GB = 20.0
"""Default size cap of the sequence cache (``$ADALIO_SIM_CACHE_GB`` overrides it)."""
STALE_TMP_S = 24 * 3600.0
"""An unfinished generation folder this old belonged to a process that died: removed."""
PROTECT_S = 24 * 3600.0
"""Sequences used within this long are not evicted to meet the cap: a benchmark that needs
more than the cap keeps every sequence it generated while it runs (the folder then exceeds
the cap until they age). The disk's free space overrides it (:func:`evict_cache`'s
``need_bytes``), and so does another simulator version (its sequences can never be reused)."""


def cache_budget_bytes() -> int:
    """``$ADALIO_SIM_CACHE_GB`` (default :data:`CACHE_BUDGET_GB`) in bytes."""
    text = os.environ.get("ADALIO_SIM_CACHE_GB", "")
    try:
        gb = float(text) if text.strip() else CACHE_BUDGET_GB
    except ValueError:
        raise InputError(f"ADALIO_SIM_CACHE_GB={text!r} is not a number: set it to the cache "
                         "size cap in GB (e.g. 20) or unset it") from None
    if not gb >= 0:
        raise InputError(f"ADALIO_SIM_CACHE_GB={text!r} must be >= 0")
    return int(gb * 1e9)


def _folder_bytes(d: Path) -> int:
    return sum(f.stat().st_size for f in d.rglob("*") if f.is_file())


def evict_cache(root: Path, budget_bytes: int, keep: Path | None = None,
                protect_s: float = PROTECT_S, need_bytes: int = 0,
                version: str | None = None) -> list[Path]:
    """Least-recently-used eviction: delete finished sequences, the least recently used first
    (last use = the ``COMPLETE`` marker's mtime, touched on every reuse), until the folder holds
    at most ``budget_bytes``; not a sequence used within ``protect_s``, unless it was made by
    another simulator ``version`` than the given one (its key does not end in ``-v<version>``).
    Then, while the disk has less than ``need_bytes`` free, the least recently used of the
    rest go too, protected or not: a full disk fails every run, an evicted sequence is only
    generated again. Nothing goes for that when even an empty cache would leave too little.
    Sequences of other versions go first in both passes; ``keep`` never goes.
    Unfinished folders older than a day (a generation that died) go too. Returns the folders
    removed."""
    removed: list[Path] = []
    if not root.is_dir():
        return removed
    now = time.time()
    entries: list[tuple[bool, float, int, Path]] = []
    for d in root.iterdir():
        if not d.is_dir():
            continue
        marker = d / "COMPLETE"
        try:
            if marker.is_file():
                current = version is None or d.name.endswith(f"-v{version}")
                entries.append((current, marker.stat().st_mtime, _folder_bytes(d), d))
            elif now - d.stat().st_mtime > STALE_TMP_S:
                shutil.rmtree(d, ignore_errors=True)
                removed.append(d)
        except OSError:  # another process removed it meanwhile
            continue
    if keep is not None:
        entries = [e for e in entries if e[3].resolve() != keep.resolve()]
    entries.sort(key=lambda e: (e[0], e[1]))  # other versions first, then least recently used
    total = sum(size for _, _, size, _ in entries) + (_folder_bytes(keep) if keep else 0)
    left: list[tuple[int, Path]] = []
    for current, last_use, size, d in entries:
        if total > budget_bytes and not (current and now - last_use < protect_s):
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
            total -= size
        else:
            left.append((size, d))
    if need_bytes <= 0:
        return removed
    free = shutil.disk_usage(root).free
    if free + sum(size for size, _ in left) < need_bytes:
        return removed  # even an empty cache would not make the room: keep what is there
    for _, d in left:
        if shutil.disk_usage(root).free >= need_bytes:
            break
        shutil.rmtree(d, ignore_errors=True)
        removed.append(d)
    return removed


def _code_version() -> str:
    """Short hash of the simulator's own source, so a changed simulator never reuses old data.
    This module is left out: it stores and finds sequences but never changes their content,
    so editing the cache's housekeeping does not invalidate every cached sequence."""
    digest = hashlib.sha1()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        if path.name != Path(__file__).name:
            digest.update(path.read_bytes())
    return digest.hexdigest()[:8]


def cached_sequence(scene: str, *, seed: int = 0, duration_s: float | None = None,
                    lidar: str = "xt32", fmt: str = "ros1",
                    columns: int | None = None, imu_noise_scale: float = 1.0,
                    imu_bias_scale: float = 1.0, motion_from: str | Path | None = None) -> SimResult:
    """Generate once (atomically: temp folder + rename + completion marker) and reuse
    (the key includes a hash of ``motion_from``'s content). After generating, the cache is
    trimmed to ``$ADALIO_SIM_CACHE_GB`` (default 20 GB) by :func:`evict_cache`, least recently
    used first; a sequence larger than the cap on its own is still kept while it is the newest.
    Before generating, older sequences are evicted while the disk lacks the room the new one
    needs (``generate.sequence_bytes``), even those the cap would keep; if that is not enough,
    ``simulate`` raises an ``OSError`` (ENOSPC) before writing anything."""
    _check_args(scene, duration_s, lidar, fmt, 1.0)
    cols = lidar_model(lidar, columns).columns
    dur = "full" if duration_s is None else f"{float(duration_s):g}"
    imu = "" if imu_noise_scale == 1.0 else f"-imu{imu_noise_scale:g}"
    if imu_bias_scale != 1.0:
        imu += f"-bias{imu_bias_scale:g}"
    hh = ""
    if motion_from is not None:
        try:
            hh = "-hh" + hashlib.sha1(Path(motion_from).read_bytes()).hexdigest()[:8]
        except OSError as exc:
            raise InputError(f"{motion_from}: cannot read the motion file ({exc})") from None
    key = f"{scene}-s{seed}-d{dur}-{lidar}-{fmt}-c{cols}{imu}{hh}-v{_code_version()}"
    final = cache_root() / key

    def result(d: Path) -> SimResult:
        return SimResult(bag_path=bag_path_for(d, scene, fmt), gt_path=d / "gt.tum",
                         meta_path=d / "meta.json", config_path=d / "config.yaml")

    if (final / "COMPLETE").is_file():
        try:
            os.utime(final / "COMPLETE")  # last use, for the least-recently-used eviction
        except OSError:
            pass
        return result(final)
    budget = cache_budget_bytes()
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.parent / f".{key}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"

    def make_room(need_bytes: int) -> None:
        evict_cache(final.parent, budget, need_bytes=need_bytes, version=_code_version())

    try:
        simulate(scene, tmp, seed=seed, duration_s=duration_s, lidar=lidar, fmt=fmt,
                 columns=columns, imu_noise_scale=imu_noise_scale,
                 imu_bias_scale=imu_bias_scale, motion_from=motion_from, make_room=make_room)
        (tmp / "COMPLETE").write_text("ok\n")
        if final.exists() and not (final / "COMPLETE").is_file():
            shutil.rmtree(final, ignore_errors=True)
        try:
            os.rename(tmp, final)
        except OSError:
            if not (final / "COMPLETE").is_file():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    evict_cache(final.parent, budget, keep=final, version=_code_version())
    return result(final)
