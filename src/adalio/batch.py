"""``adalio batch``: a fleet of bags as one job, on an embedded or an existing Dask cluster.

Each bag is one Dask task. The task runs :func:`adalio.pipeline.run_bag` in a worker process
with the config ``adalio run`` builds from the same options, so ``OUT/<bag name>/`` holds exactly
what ``adalio run BAG --out OUT/<bag name>`` writes (the same trajectory, bit for bit). By default
the tasks run on an embedded ``distributed.LocalCluster`` of single-threaded worker processes
(one bag per process: the numba kernels are not meant to be entered by two threads at once);
``scheduler="tcp://host:8786"`` sends them to an existing cluster, whose workers must see the
bags, the config and ``OUT`` under the same paths (a shared filesystem).

Outputs besides the bag folders: ``OUT/summary.csv`` and ``OUT/summary.md`` (one row per bag,
:data:`SUMMARY_COLUMNS`), and ``OUT/.adalio-batch/<bag name>.json``, the marker a worker writes
only after a bag's run finished; a rerun skips bags whose marker matches the bag, ground truth
and config, so an interrupted or failed bag is redone.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import json
import math
import os
import time
import urllib.parse
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Annotated, Any

import typer

from adalio.cpus import usable_cpus
from adalio.errors import AdalioError, InputError

SUMMARY_COLUMNS = ("bag", "status", "poses", "scans", "degenerate_pct", "ms_per_scan", "worker",
                   "ate_se3_m", "sensor_checks", "error", "wall_s", "bag_path")
"""Columns of ``summary.csv``; ``bag`` is the output folder name under OUT."""
MARKER_DIR = ".adalio-batch"
CONNECT_TIMEOUT_S = 10.0
"""How long to wait for an existing scheduler to answer, and then for its first worker."""
NO_WORKER_S = 60.0
"""With bags left and no worker at the scheduler for this long (every worker died or was
stopped), the batch stops: the bags left fail, their rows say why (a cluster's nanny restarts
a worker within seconds). Without it the batch waited for ever."""
WATCH_S = 0.5
"""How often the batch looks at the scheduler's workers while no bag finishes."""


# ------------------------------------------------------------------------------ finding bags
def _is_ros2_folder(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def find_bags(inputs: Sequence[str | Path]) -> list[Path]:
    """The bags named by ``inputs``: each a bag (``.bag``, ``.mcap``, ``.db3``, ROS2 folder) or
    a folder searched recursively for ``.bag`` / ``.mcap`` files and ROS2 bag folders.

    In a searched folder every ``.bag`` file is its own bag (split ROS1 bags are not joined).
    Absolute paths, each bag once, in input order (sorted within a folder).
    """
    if isinstance(inputs, str | Path):  # one input, not a sequence of its characters
        inputs = [inputs]
    found: dict[Path, None] = {}
    for item in inputs:
        p = Path(item).expanduser()
        if not p.exists():
            raise InputError(f"input {p} does not exist: give bags or folders holding them")
        p = p.resolve()
        if p.is_file() or _is_ros2_folder(p):
            found[p] = None
            continue
        in_folder: list[Path] = []
        seen_dirs = {os.path.realpath(p)}
        # symbolic links to folders are followed (a data folder linked into a batch), each
        # real folder searched once (a link back up the tree ends there)
        for root, dirs, files in os.walk(p, followlinks=True):
            root_p = Path(root)
            bag_dirs = [d for d in dirs if _is_ros2_folder(root_p / d)]
            in_folder += [root_p / d for d in bag_dirs]
            keep = []
            for d in sorted(dirs):
                real = os.path.realpath(root_p / d)
                if d in bag_dirs or d.startswith(".") or real in seen_dirs:
                    continue
                seen_dirs.add(real)
                keep.append(d)
            dirs[:] = keep
            in_folder += [root_p / f for f in files if f.lower().endswith((".bag", ".mcap"))]
        real_bags = {os.path.realpath(b) for b in found}
        for bag in sorted(in_folder):
            real = os.path.realpath(bag)
            if real not in real_bags:  # one bag reached by two paths runs once
                real_bags.add(real)
                found[bag] = None
        if not in_folder:
            raise InputError(f"no bags in folder {p} (looked for .bag, .mcap and ROS2 bag "
                             "folders with metadata.yaml)")
    if not found:
        raise InputError("no bags given: name bags or folders holding them")
    return list(found)


def bag_stem(bag_path: str | Path) -> str:
    """The bag's file or folder name without its extension (as ``adalio run`` names runs)."""
    stem = Path(str(bag_path).rstrip("/")).name
    for suffix in (".bag", ".mcap", ".db3"):
        stem = stem.removesuffix(suffix)
    return stem or "bag"


def unique_names(bags: Sequence[Path]) -> list[str]:
    """One output folder name per bag: its stem; stems shared by several bags get the parent
    folder's name in front (``day1_run``), and a number after if that is still not unique."""
    stems = [bag_stem(b) for b in bags]
    names = [s if stems.count(s) == 1 else f"{b.parent.name}_{s}" for b, s in
             zip(bags, stems, strict=True)]
    out: list[str] = []
    for n in names:
        name, k = n, 1
        while name in out:
            k += 1
            name = f"{n}_{k}"
        out.append(name)
    return out


def find_gt(bag_path: Path, gt_pattern: str | None = None) -> Path | None:
    """Ground truth for a bag: ``gt_pattern`` formatted with ``{dir}`` (the bag's folder) and
    ``{name}`` (its stem), relative to the bag's folder unless absolute; else a ``gt.tum``
    beside the bag. None when that file does not exist."""
    folder = bag_path.parent
    if gt_pattern:
        try:
            text = gt_pattern.format(dir=str(folder), name=bag_stem(bag_path))
        except (KeyError, IndexError, ValueError):
            raise InputError(f"--gt-pattern {gt_pattern!r} may only use {{dir}} and {{name}}, "
                             "e.g. '{name}_gt.tum'") from None
        path = Path(text).expanduser()
        path = path if path.is_absolute() else folder / path
    else:
        path = folder / "gt.tum"
    return path if path.is_file() else None


# ------------------------------------------------------------------------------ one bag
@dataclass
class BagJob:
    """One task: run ``bag_path`` with ``config`` into ``out_dir / name``."""

    name: str
    bag_path: Path
    config: Any
    """The :class:`adalio.config.Config` the run uses (as ``adalio run`` builds it)."""
    out_dir: Path
    """The batch's output folder; the run writes into ``out_dir / name``."""
    gt_path: Path | None = None

    @property
    def run_dir(self) -> Path:
        return self.out_dir / self.name

    @property
    def marker_path(self) -> Path:
        return self.out_dir / MARKER_DIR / f"{self.name}.json"

    def fingerprint(self) -> dict[str, str]:
        """What a finished run must match to be skipped on a rerun: the paths, the config, and
        the bag's and the ground truth's files as they are (sizes and modification times: a
        bag recorded again at the same path is run again)."""
        return {"bag_path": str(self.bag_path), "gt_path": str(self.gt_path or ""),
                "config_sha1": hashlib.sha1(self.config.to_yaml().encode()).hexdigest(),
                "bag_files": _files_stamp(self.bag_path),
                "gt_file": _files_stamp(self.gt_path) if self.gt_path else ""}


def _files_stamp(path: Path) -> str:
    """Size and modification time (ns) of a file, or of every file in a folder (a ROS2 bag)."""
    p = Path(path)
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    stats = [(f.relative_to(p) if p.is_dir() else f.name, f.stat()) for f in files if f.exists()]
    return ";".join(f"{name}:{st.st_size}:{st.st_mtime_ns}" for name, st in stats)


@dataclass
class BagRow:
    """One row of ``summary.csv``."""

    bag: str
    status: str
    """ok | failed | cancelled (Ctrl-C before the bag finished)"""
    poses: int = 0
    scans: int = 0
    degenerate_pct: float = math.nan
    ms_per_scan: float = math.nan
    worker: str = ""
    ate_se3_m: float = math.nan
    sensor_checks: str = ""
    """What the IMU time offset, LiDAR-IMU rotation and lever arm checks concluded
    (:func:`checks_text`)."""
    error: str = ""
    wall_s: float = math.nan
    bag_path: str = ""
    skipped: bool = field(default=False, compare=False)
    """True when a rerun took the row from the bag's marker instead of running it."""

    def csv_row(self) -> dict[str, str]:
        def fmt(value: Any) -> str:
            if isinstance(value, float):
                return "" if math.isnan(value) else f"{value:.6g}"
            return str(value)

        return {c: fmt(getattr(self, c)) for c in SUMMARY_COLUMNS}


def checks_text(res: Any) -> str:
    """The sensor checks of a run in a few words: 'offset +0.2 ms; rotation 0.05 deg;
    translation (+0.3, -0.2, +0.4) cm', a value found and restarted with ('rotation 0.95 deg
    found'), or 'not settled 0.62+-0.16 deg' / 'not checked' (README, IMU time offset,
    LiDAR-IMU rotation, LiDAR-IMU lever arm); '' with the checks off."""
    parts = []
    for name, found, left, unsettled, show in (
            ("offset", getattr(res, "time_offset_found", None),
             getattr(res, "time_offset", None), getattr(res, "time_offset_unsettled", None),
             lambda e: (f"{e.offset_s * 1e3:+.1f}", f"{e.sigma_s * 1e3:.1f}", "ms")),
            ("rotation", getattr(res, "extrinsic_rotation_found", None),
             getattr(res, "extrinsic_rotation", None),
             getattr(res, "extrinsic_rotation_unsettled", None),
             lambda e: (f"{math.degrees(e.angle_rad):.2f}", f"{math.degrees(e.sigma_rad):.2f}",
                        "deg")),
            ("gyro scale", getattr(res, "gyro_scale_found", None),
             getattr(res, "gyro_scale", None), getattr(res, "gyro_scale_unsettled", None),
             lambda e: (f"{100 * e.largest:.2f}", f"{100 * e.sigma:.2f}", "%")),
            ("translation", None, getattr(res, "extrinsic_translation", None),
             getattr(res, "extrinsic_translation_unsettled", None),
             lambda e: ("(" + ", ".join(f"{100 * v:+.1f}" for v in e.horizontal_m) + ")",
                        f"{100 * e.sigma_m:.1f}", "cm"))):
        text = ""
        if found is not None:
            value = (f"{found.offset_s * 1e3:+.1f} ms" if name == "offset" else
                     f"{found.largest_pct:.2f} %" if name == "gyro scale" else
                     f"{found.angle_deg:.2f} deg")
            text = f"{name} {value} found"
        if unsettled is not None:
            est = unsettled.estimate
            if est is None:
                text += f"{'; ' if text else name + ' '}not checked"
            else:
                v, s, unit = show(est)
                text += f"{', then ' if text else name + ' '}not settled {v}+-{s} {unit}"
        elif left is not None and not text:
            v, _, unit = show(left)
            text = f"{name} {v} {unit}"
        if name == "rotation" and getattr(res, "extrinsic_rotation_gross_found", None) is not None:
            gross = f"{math.degrees(res.extrinsic_rotation_gross_found.angle_rad):.1f} deg gross"
            text = (f"rotation {gross}, then {text.removeprefix('rotation ')}" if text
                    else f"rotation {gross}")
        if text:
            parts.append(text)
    return "; ".join(parts)


def one_line(exc: BaseException) -> str:
    """An error as one line: the AdalioError message, else ``Type: message``."""
    text = str(exc) if isinstance(exc, AdalioError) else \
        f"{type(exc).__name__}: {exc}".rstrip(": ")
    lines = [s.strip() for s in text.splitlines() if s.strip()]
    return (lines[0] if lines else type(exc).__name__)[:300]


def _worker_address() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return ""


def process_bag(job: BagJob) -> BagRow:
    """The task: run one bag and evaluate it; never raises for a bad bag (``failed`` row).

    The marker is removed first and written only after the run finished, so a bag interrupted
    in between is redone by the next batch.
    """
    from adalio.eval.metrics import ate
    from adalio.pipeline import run_bag

    row = BagRow(bag=job.name, status="failed", worker=_worker_address(),
                 bag_path=str(job.bag_path))
    job.marker_path.unlink(missing_ok=True)
    t0 = time.perf_counter()
    try:
        use_bag_threads()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = run_bag(job.bag_path, job.config, job.run_dir, progress=False,
                          parallel_compile=False)
        row.poses, row.scans = res.n_scans, res.n_scans_in
        row.degenerate_pct = 100.0 * res.n_degenerate / res.n_scans if res.n_scans else math.nan
        row.ms_per_scan = res.ms_per_scan_median
        row.sensor_checks = checks_text(res)
        if res.interrupted:
            raise AdalioError("interrupted")
        if job.gt_path is not None:
            row.ate_se3_m = float(ate(res.trajectory_path, job.gt_path, align="se3")["rmse_m"])
        row.status = "ok"
    except Exception as exc:  # noqa: BLE001  (a failed bag becomes a row, never a crash)
        row.error = one_line(exc)
    except KeyboardInterrupt:
        row.error = "interrupted"
    row.wall_s = time.perf_counter() - t0
    if row.status == "ok":
        job.marker_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = job.marker_path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_text(json.dumps({**job.fingerprint(), "row": asdict(row)}, indent=1))
        os.replace(tmp, job.marker_path)
    return row


def finished_row(job: BagJob) -> BagRow | None:
    """The row of a finished earlier run of exactly this job, from its marker, or None."""
    try:
        data = json.loads(job.marker_path.read_text())
    except (OSError, ValueError):
        return None
    if any(data.get(k) != v for k, v in job.fingerprint().items()):
        return None
    if not (job.run_dir / "trajectory.tum").is_file():
        return None
    names = {f.name for f in fields(BagRow)}
    row = BagRow(**{k: v for k, v in data.get("row", {}).items() if k in names})
    row.skipped = True
    return row


# ------------------------------------------------------------------------------ the cluster
def check_scheduler_address(address: str) -> None:
    """InputError unless ``address`` is ``[tcp://|tls://]HOST:PORT``. Checked before a client
    is made: distributed, given a malformed address, raises from a background event loop, and
    after a cluster ran in the same process its client could hang."""
    url = urllib.parse.urlsplit(address if "://" in address else f"tcp://{address}")
    try:
        port = url.port
    except ValueError:
        port = None
    if url.scheme not in ("tcp", "tls") or not url.hostname or port is None:
        raise InputError(f"--scheduler {address} is not a scheduler address: give "
                         "tcp://HOST:PORT (or HOST:PORT)")


@contextlib.contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None) -> Iterator[Any]:
    """A ``distributed.Client``: on an embedded LocalCluster of ``workers`` single-threaded
    processes (default: the number of cores this process may run on, its affinity where the
    platform gives one: a batch job's cpuset, ``taskset``; :func:`adalio.cpus.usable_cpus`),
    or connected to ``scheduler``. Closed on exit."""
    import logging

    from distributed import Client, LocalCluster

    if scheduler:
        check_scheduler_address(scheduler)
        try:
            client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler} "
                             f"({one_line(exc)}): start it with 'dask scheduler' and check "
                             "--scheduler tcp://HOST:PORT") from None
        with client:
            try:
                client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
            except TimeoutError:
                raise InputError(f"the Dask scheduler at {scheduler} has no workers: start "
                                 "some with 'dask worker --nthreads 1 "
                                 f"{scheduler}'") from None
            yield client
        return
    cpus = usable_cpus()  # those this process may run on, as numba counts its threads
    n = workers if workers is not None else cpus
    if n < 1:
        raise InputError(f"--workers must be >= 1 (got {n})")
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                      dashboard_address=None, memory_limit=0, host="127.0.0.1",
                      silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
        client.run(_ignore_sigint)
        client.run(_read_without_thread)
        if not os.environ.get("NUMBA_NUM_THREADS"):
            client.run(_share_cores, max(1, cpus // n))
        yield client


_BAG_NUMBA_THREADS: int | None = None
"""Numba threads for each bag this worker process runs (set by the embedded cluster)."""


def _share_cores(n_threads: int) -> None:
    """In an embedded worker process: run each bag's parallel kernels on ``n_threads`` numba
    threads (cores // workers), since with more threads than cores they wait for each other's
    cores (one search: 8 instead of 3.8 ms measured while OpenMP's threads still spun as they
    waited, before session 88). Applied by :func:`process_bag` in the task's
    own thread (numba's thread count is per calling thread)."""
    global _BAG_NUMBA_THREADS
    _BAG_NUMBA_THREADS = n_threads


def _read_without_thread() -> None:
    """In an embedded worker process: read each bag without a read-ahead thread
    (:attr:`Sequencer.read_ahead`): the bags of the other workers use the other cores, whatever
    ``NUMBA_NUM_THREADS`` says."""
    from adalio.io.sequencer import Sequencer

    Sequencer.read_ahead = False


def use_bag_threads() -> int:
    """Apply this worker's share of the cores to the calling thread; returns numba's thread
    count for it."""
    import numba

    if _BAG_NUMBA_THREADS is not None:
        numba.set_num_threads(max(1, min(_BAG_NUMBA_THREADS, numba.config.NUMBA_NUM_THREADS)))
    return numba.get_num_threads()


def _ignore_sigint() -> None:
    """In an embedded worker process: leave Ctrl-C to the client, which cancels the tasks and
    closes the cluster (the workers share the terminal's process group)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


# ------------------------------------------------------------------------------ the batch
@dataclass
class BatchResult:
    """What :func:`run_jobs` / :func:`run_batch` produced."""

    out_dir: Path
    rows: list[BagRow]
    summary_csv: Path
    summary_md: Path
    wall_s: float
    interrupted: bool = False

    @property
    def n_ok(self) -> int:
        return sum(r.status == "ok" for r in self.rows)

    @property
    def n_failed(self) -> int:
        return sum(r.status != "ok" for r in self.rows)

    @property
    def n_skipped(self) -> int:
        return sum(r.skipped for r in self.rows)


def _check_out_dir(out_dir: Path, jobs: Sequence[BagJob]) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} is a file: give a folder for the batch outputs")
    for job in jobs:
        run_dir = job.run_dir.resolve()
        bag = job.bag_path.resolve()
        if bag == run_dir or run_dir in bag.parents:
            raise InputError(f"--out {out_dir} would write the outputs of {bag} into the bag "
                             "itself: choose another --out folder")


def _progress_bar(enabled: bool) -> Any:
    from rich.console import Console

    from adalio.pipeline import progress_bar

    return progress_bar(enabled, "bags", "note", Console(stderr=True))


def run_jobs(jobs: Sequence[BagJob], out_dir: str | Path, *, client: Any = None,
             workers: int | None = None, scheduler: str | None = None, force: bool = False,
             progress: bool = False,
             on_row: Callable[[BagRow], None] | None = None) -> BatchResult:
    """Run ``jobs`` as Dask tasks (on ``client``, else on :func:`dask_client`) and write the
    summary. Bags with a matching marker are skipped unless ``force``. ``on_row`` is called in
    this process for every row as it arrives (skipped ones first). On Ctrl-C the tasks are
    cancelled, the finished rows kept and the rest marked ``cancelled`` (``interrupted``)."""
    out = Path(out_dir)
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be >= 1 (got {workers})")
    names = [j.name for j in jobs]
    if len(set(names)) != len(names):
        raise InputError("two jobs share an output folder name; give each bag its own name")
    _check_out_dir(out, jobs)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows: dict[str, BagRow] = {}
    for job in jobs:
        row = None if force else finished_row(job)
        if row is not None:
            rows[job.name] = row
            if on_row is not None:
                on_row(row)
    todo = [j for j in jobs if j.name not in rows]

    def summarize() -> tuple[list[BagRow], Path, Path]:
        if interrupted:
            # a bag whose worker wrote its marker before the Ctrl-C reached the client finished
            # in this run (a started task removes its marker first)
            for j in todo:
                row = None if j.name in rows else finished_row(j)
                if row is not None:
                    row.skipped = False
                    rows[j.name] = row
        ordered = [rows.get(j.name) or BagRow(bag=j.name, status="cancelled",
                                              error="cancelled (Ctrl-C) before it finished",
                                              bag_path=str(j.bag_path)) for j in jobs]
        return ordered, *write_summary(ordered, out)

    interrupted = False
    if todo:
        try:
            with contextlib.ExitStack() as stack:
                if client is None:
                    client = stack.enter_context(dask_client(workers, scheduler))
                interrupted = _gather(client, todo, rows, len(jobs), progress, on_row)
                summarize()  # before the cluster closes, which a Ctrl-C may cut short
        except KeyboardInterrupt:
            interrupted = True
    ordered, csv_path, md_path = summarize()
    return BatchResult(out_dir=out, rows=ordered, summary_csv=csv_path, summary_md=md_path,
                       wall_s=time.perf_counter() - t0, interrupted=interrupted)


def _gather(client: Any, todo: Sequence[BagJob], rows: dict[str, BagRow], n_total: int,
            progress: bool, on_row: Callable[[BagRow], None] | None) -> bool:
    """Submit ``todo``, collect rows as they finish; True when stopped by Ctrl-C."""
    import uuid

    from distributed import as_completed

    from adalio.pipeline import GracefulStop

    tag = uuid.uuid4().hex[:8]
    futures = {client.submit(process_bag, job, key=f"adalio-batch-{job.name}-{tag}",
                             pure=False, retries=0): job for job in todo}
    n_failed = 0
    try:
        # a first Ctrl-C is a flag this loop reads: raised wherever it lands, it could land in
        # a Dask future's __del__, where Python drops it, and the batch ran on to exit 1
        with _progress_bar(progress) as bar, GracefulStop() as stop:
            task = bar.add_task("bags", total=n_total, completed=n_total - len(todo), note="")
            ac = as_completed(list(futures))
            left = set(futures)
            no_worker_since = None
            while left and not stop.requested:
                done = ac.next_batch(block=False)
                stranded: list[Any] = []
                if not done:
                    if client.nthreads():
                        no_worker_since = None
                    elif no_worker_since is None:
                        no_worker_since = time.monotonic()
                    elif time.monotonic() - no_worker_since > NO_WORKER_S:
                        stranded = sorted(left, key=lambda f: futures[f].name)
                        client.cancel(stranded, force=True)
                    if not stranded:
                        time.sleep(WATCH_S)
                        continue
                for fut in done + stranded:
                    left.discard(fut)
                    job = futures[fut]
                    if stranded:
                        row = BagRow(bag=job.name, status="failed", error=(
                            f"not run: the Dask scheduler had no worker for {NO_WORKER_S:g} s "
                            "(every worker died or was stopped); start workers and run the "
                            "batch again (finished bags are skipped)"), bag_path=str(job.bag_path))
                    else:
                        try:
                            row = fut.result()
                        except Exception as exc:  # noqa: BLE001  (a lost worker, unpicklable)
                            row = BagRow(bag=job.name, status="failed", error=one_line(exc),
                                         bag_path=str(job.bag_path))
                    rows[job.name] = row
                    n_failed += row.status != "ok"
                    bar.update(task, advance=1,
                               note=f"{job.name} {row.status}" + (f", {n_failed} failed"
                                                                  if n_failed else ""))
                    if on_row is not None:
                        on_row(row)
            if stop.requested:  # also during the last bags: they are in, but it was stopped
                raise KeyboardInterrupt
    except KeyboardInterrupt:
        import sys

        sys.stderr.write("cancelling the unfinished bags and closing the workers "
                         "(Ctrl-C again to stop at once)\n")
        with contextlib.suppress(Exception):
            client.cancel(list(futures), force=True)
        return True
    return False


def write_summary(rows: Sequence[BagRow], out_dir: Path) -> tuple[Path, Path]:
    """``summary.csv`` (:data:`SUMMARY_COLUMNS`) and the same table as ``summary.md``."""
    csv_path, md_path = out_dir / "summary.csv", out_dir / "summary.md"
    with open(csv_path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=SUMMARY_COLUMNS)
        writer.writeheader()
        for r in rows:
            writer.writerow(r.csv_row())
    md_path.write_text(markdown_table(rows) + "\n", encoding="utf-8")
    return csv_path, md_path


def markdown_table(rows: Sequence[BagRow]) -> str:
    """The summary as a markdown table (without the bag path)."""
    cols = [c for c in SUMMARY_COLUMNS if c != "bag_path"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = r.csv_row()
        cells["ate_se3_m"] = "" if math.isnan(r.ate_se3_m) else f"{r.ate_se3_m:.3f}"
        cells["degenerate_pct"] = "" if math.isnan(r.degenerate_pct) else \
            f"{r.degenerate_pct:.0f}"
        cells["ms_per_scan"] = "" if math.isnan(r.ms_per_scan) else f"{r.ms_per_scan:.1f}"
        cells["wall_s"] = "" if math.isnan(r.wall_s) else f"{r.wall_s:.1f}"
        lines.append("| " + " | ".join(cells[c].replace("|", "\\|") for c in cols) + " |")
    return "\n".join(lines)


def run_batch(inputs: Sequence[str | Path], out_dir: str | Path, *, preset: str | None = None,
              config_file: str | Path | None = None, overrides: dict[str, Any] | None = None,
              mode: str | None = None, workers: int | None = None,
              scheduler: str | None = None, force: bool = False, gt_pattern: str | None = None,
              progress: bool = False,
              on_row: Callable[[BagRow], None] | None = None) -> BatchResult:
    """Run every bag found in ``inputs`` with one config, each into ``out_dir/<bag name>``.

    The config is what ``adalio run --preset P --config F --mode M`` builds (``overrides`` are
    dotted keys like ``{"adaptive.tau_n": 1500}``). See the module docstring for the rest.
    """
    from adalio.config import load_config

    cfg = load_config(preset, config_file,
                      {**(overrides or {}), **({} if mode is None else {"adaptive.mode": mode})})
    bags = find_bags(inputs)
    out = Path(out_dir).expanduser().resolve()
    jobs = [BagJob(name=name, bag_path=bag, config=cfg, out_dir=out,
                   gt_path=find_gt(bag, gt_pattern))
            for bag, name in zip(bags, unique_names(bags), strict=True)]
    return run_jobs(jobs, out, workers=workers, scheduler=scheduler, force=force,
                    progress=progress, on_row=on_row)


# ------------------------------------------------------------------------------ CLI
def batch(inputs: Annotated[list[Path], typer.Argument(
              help="Bags (ROS1 .bag, ROS2 folder, .mcap) or folders searched for them.",
              show_default=False)],
          out: Annotated[Path, typer.Option(help="Output folder: OUT/<bag name>/ per bag, "
                                            "OUT/summary.csv and summary.md.")],
          preset: Annotated[str | None, typer.Option(help="Preset name (adalio config show).")]
          = None,
          config: Annotated[Path | None, typer.Option("--config", help="YAML config file.")]
          = None,
          mode: Annotated[str | None, typer.Option(help="adaptive | fixed | adaptive+")] = None,
          set_: Annotated[list[str] | None, typer.Option(
              "--set", help="Config override KEY=VALUE (repeatable).")] = None,
          workers: Annotated[int | None, typer.Option(
              help="Worker processes of the embedded cluster (default: the number of cores).")]
          = None,
          scheduler: Annotated[str | None, typer.Option(
              help="Address of an existing Dask scheduler (tcp://HOST:PORT); its workers must "
                   "see the same paths.")] = None,
          gt_pattern: Annotated[str | None, typer.Option(
              help="Ground truth per bag, with {dir} and {name} (the bag's stem), relative to "
                   "the bag's folder (default: gt.tum beside the bag).")] = None,
          force: Annotated[bool, typer.Option("--force", help="Rerun bags already done.")]
          = False,
          no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")]
          = False,
          ) -> None:
    """Run many bags as one job on a Dask cluster; write OUT/<bag>/ and OUT/summary.csv."""
    from rich.console import Console

    from adalio.config import set_options

    err = Console(stderr=True)
    res = run_batch(inputs, out, preset=preset, config_file=config, overrides=set_options(set_),
                    mode=mode, workers=workers, scheduler=scheduler, force=force,
                    gt_pattern=gt_pattern, progress=not no_progress and err.is_terminal)
    typer.echo(res.summary_md.read_text(encoding="utf-8"), nl=False)
    skipped = f", {res.n_skipped} skipped (done before; --force reruns them)" \
        if res.n_skipped else ""
    err.print(f"{res.n_ok}/{len(res.rows)} bags ok{skipped} in {res.wall_s:.1f} s → "
              f"{res.summary_csv}", highlight=False, soft_wrap=True)
    if res.interrupted:
        err.print("[yellow]interrupted[/]: finished bags are kept; rerun to do the rest")
        raise typer.Exit(130)
    if res.n_failed:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    """Add batch to the main app."""
    app.command("batch")(batch)
