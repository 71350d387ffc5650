"""The sequence cache: ``cached_sequence`` generates a sequence once per key under
``$ADALIO_CACHE_DIR/sim`` and keeps the folder under ``$ADALIO_SIM_CACHE_GB`` (least recently
used first out)."""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import os
import shutil
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np

try:
    import fcntl
except ImportError:  # not POSIX: no cross-process coordination
    fcntl = None

from adalio.config import validate_transform
from adalio.errors import InputError
from adalio.sim.bagout import bag_path_for
from adalio.sim.generate import (
    IMU_RATE_HZ,
    SimResult,
    _check_args,
    check_free_space,
    check_imu_scale_error,
    check_imu_vibration,
    check_lidar_tilt,
    check_stray,
    simulate,
)
from adalio.sim.lidar import lidar_model
from adalio.sim.people import check_people
from adalio.sim.trajectory import NO_HAND, check_pace, is_no_hand


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


HEADROOM_FRACTION = 0.05
"""Before generating, the cache frees room for the new sequence plus this share of the disk
(at most :data:`HEADROOM_MAX_BYTES`), protected sequences included, so a generation does not
leave the disk full for the runs' outputs and whatever else shares it."""
HEADROOM_MAX_BYTES = 10_000_000_000


def headroom_bytes(root: Path) -> int:
    """The free space the cache leaves on ``root``'s disk after a generation, where it can."""
    return int(min(HEADROOM_FRACTION * shutil.disk_usage(root).total, HEADROOM_MAX_BYTES))


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
    total = 0
    for f in d.rglob("*"):
        try:
            if f.is_file():
                total += f.stat().st_size
        except OSError:  # removed meanwhile (another process's generation or eviction)
            continue
    return total


LOCKS = ".locks"
"""Folder of the cache's lock files and space reservations (never evicted)."""


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """An exclusive cross-process lock (``flock``) on ``path`` while the block runs. The lock
    file stays: unlinking a lock file lets a later process lock a new file while an earlier
    one still holds the old."""
    if fcntl is None:
        yield
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


_HELD: list = []
"""The open ``.use`` lock file of the sequence this process was handed last (:func:`_hold`)."""
_HELD_LOCK = threading.Lock()


@atexit.register
def _release_held() -> None:
    """Close the held ``.use`` file at exit (the lock goes with the process anyway; closing it
    keeps the interpreter from warning about an unclosed file)."""
    with _HELD_LOCK:
        while _HELD:
            _HELD.pop().close()


def _hold(root: Path, key: str) -> None:
    """Hold a shared ``flock`` on ``.locks/<key>.use`` until this process is handed another
    sequence or exits: evictions skip a sequence so held (:func:`_remove_unless_in_use`), so a
    run does not lose its bag to another process making room. Blocks while an eviction of that
    key is under way, so the reuse check that follows sees whether it is gone."""
    if fcntl is None:
        return
    path = root / LOCKS / f"{key}.use"
    path.parent.mkdir(parents=True, exist_ok=True)
    fh = open(path, "a")  # noqa: SIM115 - held beyond this function on purpose
    fcntl.flock(fh, fcntl.LOCK_SH)
    with _HELD_LOCK:
        if _HELD:
            _HELD.pop().close()
        _HELD.append(fh)


def _remove_unless_in_use(root: Path, d: Path) -> bool:
    """Delete the sequence folder ``d`` unless a process holds it (:func:`_hold`; this process's
    own last sequence counts as held). The exclusive lock is kept while deleting, so no process
    starts using ``d`` meanwhile (the lock file is created if missing: a process that creates
    it just after a check for it would otherwise hold it while ``d`` goes). Returns whether it
    was deleted."""
    if fcntl is None:
        shutil.rmtree(d, ignore_errors=True)
        return True
    path = root / LOCKS / f"{d.name}.use"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return False
        try:
            shutil.rmtree(d, ignore_errors=True)
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
    return True


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def reserved_bytes(root: Path) -> int:
    """Disk space other generations in progress still need: for each live reservation in
    ``root/.locks`` (``<pid>-<id>.reserve``: the bytes it asked for and its folder), what it asked
    for less what its folder already holds. A dead process's reservation is removed."""
    total = 0
    for f in (root / LOCKS).glob("*.reserve"):
        try:
            pid = int(f.name.split("-", 1)[0])
            need_text, folder = f.read_text().split("\n", 1)
            need = int(need_text)
        except (OSError, ValueError):
            continue
        if not _pid_alive(pid):
            f.unlink(missing_ok=True)
            continue
        held = Path(folder.strip())
        total += max(0, need - (_folder_bytes(held) if held.is_dir() else 0))
    return total


def evict_cache(root: Path, budget_bytes: int, keep: Path | None = None,
                protect_s: float = PROTECT_S, need_bytes: int = 0,
                version: str | None = None, headroom_bytes: int = 0) -> list[Path]:
    """Least-recently-used eviction: delete finished sequences, the least recently used first
    (last use = the ``COMPLETE`` marker's mtime, touched on every reuse), until the folder holds
    at most ``budget_bytes``; not a sequence used within ``protect_s``, unless it was made by
    another simulator ``version`` than the given one (its key does not end in ``-v<version>``).
    Then, while the disk has less than ``need_bytes`` + ``headroom_bytes`` free, the least
    recently used of the rest go too, protected or not: a full disk fails every run, an evicted
    sequence is only generated again. Nothing goes for that when even an empty cache would leave
    less than ``need_bytes``.
    Sequences of other versions go first in both passes; ``keep`` never goes, nor does a
    sequence a process holds (the last one :func:`cached_sequence` handed it).
    Unfinished folders older than a day (a generation that died) go too. Returns the folders
    removed."""
    removed: list[Path] = []
    if not root.is_dir():
        return removed
    now = time.time()
    entries: list[tuple[bool, float, int, Path]] = []
    for d in root.iterdir():
        if not d.is_dir() or d.name == LOCKS:
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
        if (total > budget_bytes and not (current and now - last_use < protect_s)
                and _remove_unless_in_use(root, d)):
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
        if shutil.disk_usage(root).free >= need_bytes + headroom_bytes:
            break
        if _remove_unless_in_use(root, d):
            removed.append(d)
    return removed


def _code_version() -> str:
    """Short hash of the simulator's own source, so a changed simulator never reuses old data.
    This module and the command line (``cli.py``) are left out: one stores and finds
    sequences, the other hands its options to ``simulate``; neither changes a sequence's
    content for given arguments, so editing them does not invalidate every cached sequence."""
    digest = hashlib.sha1()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        if path.name not in (Path(__file__).name, "cli.py"):
            digest.update(path.read_bytes())
    return digest.hexdigest()[:8]


def cached_sequence(scene: str, *, seed: int = 0, duration_s: float | None = None,
                    lidar: str = "xt32", fmt: str = "ros1",
                    columns: int | None = None, imu_noise_scale: float = 1.0,
                    imu_bias_scale: float = 1.0, motion_from: str | Path | None = None,
                    T_imu_lidar: list[list[float]] | np.ndarray | None = None,
                    imu_rate_hz: float = IMU_RATE_HZ,
                    lidar_rate_hz: float | None = None,
                    imu_time_offset_s: float = 0.0,
                    imu_scale_error_pct: float = 0.0, people: int = 0,
                    lidar_tilt_deg: float = 0.0, ghosts: float = 0.0,
                    dust: float = 0.0, pace: float = 1.0,
                    imu_vibration: float = 0.0) -> SimResult:
    """Generate once (atomically: temp folder + rename + completion marker) and reuse
    (the key includes the IMU rate when it is not the default 400 Hz, the LiDAR's sweep rate
    when it is not the model's, the IMU's stamp offset and sensitivity errors, the number of
    people walking, the LiDAR's tilt and the shares of ghost and dust returns when they are
    not 0, the walking pace when it is not 1, the IMU's vibration when it is not 0, a hash of
    ``motion_from``'s content (``-hhnone`` for ``"none"``, no hand motion), and of
    ``T_imu_lidar``, the mounting
    ``simulate`` takes instead of the HILTI one, when given). After generating, the cache is
    trimmed to ``$ADALIO_SIM_CACHE_GB`` (default 20 GB) by :func:`evict_cache`, least recently
    used first; a sequence larger than the cap on its own is still kept while it is the newest.
    Before generating, older sequences are evicted while the disk lacks the room the new one
    needs (``generate.sequence_bytes``) on top of what other generations in progress still need
    (:func:`reserved_bytes`) and :func:`headroom_bytes`, even those the cap would keep; if even
    the room for the sequence itself cannot be made, an
    ``OSError`` (ENOSPC) is raised before writing anything. Processes sharing the cache
    coordinate through lock files in ``.locks``: one generates a key while the others wait for it
    and reuse it, and the check and reservation of room happen one process at a time. The
    sequence returned stays held (no process evicts it) until this process asks for another."""
    _check_args(scene, duration_s, lidar, fmt, 1.0, imu_rate_hz)
    check_imu_scale_error(imu_scale_error_pct)
    check_people(people)
    check_lidar_tilt(lidar_tilt_deg)
    check_stray("--ghosts", ghosts)
    check_stray("--dust", dust)
    check_pace(pace)
    check_imu_vibration(imu_vibration)
    model = lidar_model(lidar, columns, lidar_rate_hz)
    cols = model.columns
    dur = "full" if duration_s is None else f"{float(duration_s):g}"
    imu = "" if imu_noise_scale == 1.0 else f"-imu{imu_noise_scale:g}"
    if imu_bias_scale != 1.0:
        imu += f"-bias{imu_bias_scale:g}"
    if imu_rate_hz != IMU_RATE_HZ:
        imu += f"-{imu_rate_hz:g}hz"
    if model.rate_hz != lidar_model(lidar).rate_hz:
        imu += f"-l{model.rate_hz:g}hz"
    if imu_time_offset_s:
        imu += f"-toff{imu_time_offset_s * 1e3:g}ms"
    if imu_scale_error_pct:
        imu += f"-scl{imu_scale_error_pct:g}pct"
    if people:
        imu += f"-ppl{int(people)}"
    if lidar_tilt_deg:
        imu += f"-tilt{float(lidar_tilt_deg):g}"
    if ghosts:
        imu += f"-gh{float(ghosts):g}"
    if dust:
        imu += f"-dust{float(dust):g}"
    if pace != 1.0:
        imu += f"-pace{float(pace):g}"
    if imu_vibration:
        imu += f"-vib{float(imu_vibration):g}"
    hh = ""
    if is_no_hand(motion_from):
        hh = "-hh" + NO_HAND
    elif motion_from is not None:
        try:
            hh = "-hh" + hashlib.sha1(Path(motion_from).read_bytes()).hexdigest()[:8]
        except OSError as exc:
            raise InputError(f"{motion_from}: cannot read the motion file ({exc})") from None
    mount = ""
    if T_imu_lidar is not None:
        T = validate_transform(T_imu_lidar, "T_imu_lidar")
        mount = "-m" + hashlib.sha1(np.round(T, 9).tobytes()).hexdigest()[:8]
    key = f"{scene}-s{seed}-d{dur}-{lidar}-{fmt}-c{cols}{imu}{hh}{mount}-v{_code_version()}"
    final = cache_root() / key

    def result(d: Path) -> SimResult:
        return SimResult(bag_path=bag_path_for(d, scene, fmt), gt_path=d / "gt.tum",
                         meta_path=d / "meta.json", config_path=d / "config.yaml")

    def reuse() -> bool:
        if not (final / "COMPLETE").is_file():
            return False
        try:
            os.utime(final / "COMPLETE")  # last use, for the least-recently-used eviction
        except OSError:
            pass
        return True

    root = final.parent
    root.mkdir(parents=True, exist_ok=True)
    _hold(root, key)  # before the reuse check: an eviction under way finishes first
    if reuse():
        return result(final)
    budget = cache_budget_bytes()
    with _locked(root / LOCKS / f"{key}.lock"):  # another process generating it: wait, reuse
        if reuse():
            return result(final)
        token = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
        tmp = root / f".{key}.tmp-{token}"
        reservation = root / LOCKS / f"{token}.reserve"

        def make_room(need_bytes: int) -> None:
            with _locked(root / LOCKS / "space.lock"):
                others = reserved_bytes(root)
                evict_cache(root, budget, need_bytes=need_bytes + others,
                            version=_code_version(), headroom_bytes=headroom_bytes(root))
                check_free_space(root, need_bytes, others)
                reservation.write_text(f"{need_bytes}\n{tmp}\n")

        try:
            simulate(scene, tmp, seed=seed, duration_s=duration_s, lidar=lidar, fmt=fmt,
                     columns=columns, imu_noise_scale=imu_noise_scale,
                     imu_bias_scale=imu_bias_scale, motion_from=motion_from,
                     T_imu_lidar=T_imu_lidar, make_room=make_room, imu_rate_hz=imu_rate_hz,
                     lidar_rate_hz=lidar_rate_hz, imu_time_offset_s=imu_time_offset_s,
                     imu_scale_error_pct=imu_scale_error_pct, people=people,
                     lidar_tilt_deg=lidar_tilt_deg, ghosts=ghosts, dust=dust, pace=pace,
                     imu_vibration=imu_vibration)
            (tmp / "COMPLETE").write_text("ok\n")
            if final.exists() and not (final / "COMPLETE").is_file():
                shutil.rmtree(final, ignore_errors=True)
            try:
                os.rename(tmp, final)
            except OSError:
                if not (final / "COMPLETE").is_file():
                    raise
        finally:
            reservation.unlink(missing_ok=True)
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
    evict_cache(root, budget, keep=final, version=_code_version())
    return result(final)
