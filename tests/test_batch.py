"""``adalio batch`` on real Dask clusters: an embedded LocalCluster with 2 workers, and a
``dask scheduler`` with two ``dask worker`` processes started here on 127.0.0.1.

Truths the batch is checked against: a direct :func:`adalio.pipeline.run_bag` of the same bag
(trajectory bytes), :func:`adalio.eval.metrics.ate` on the written trajectory (summary ATE),
the scheduler's own list of workers (summary ``worker`` column).
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

import adalio
from adalio.batch import find_bags, find_gt, process_bag, run_batch, unique_names
from adalio.config import load_config
from adalio.errors import ConfigError, InputError
from adalio.eval.metrics import ate
from adalio.pipeline import run_bag

SCENES = ("hall", "corridor")
TIMEOUT_S = 60.0


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """FLEET/<scene>/<scene>.bag + gt.tum + config.yaml (4 s, 512 columns) and a garbage
    FLEET/broken.bag."""
    root = tmp_path_factory.mktemp("fleet")
    for k, scene in enumerate(SCENES):
        adalio.simulate(scene, root / scene, seed=k + 1, duration_s=4, columns=512)
    (root / "broken.bag").write_bytes(os.urandom(4096))
    return root


@pytest.fixture(scope="module")
def config_file(fleet: Path) -> Path:
    return fleet / "hall" / "config.yaml"


@pytest.fixture(scope="module")
def direct(fleet: Path, config_file: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The hall bag run in this process, as ``adalio run`` does (also warms the numba cache
    the worker processes then load)."""
    out = tmp_path_factory.mktemp("direct") / "hall"
    run_bag(fleet / "hall" / "hall.bag", load_config(None, config_file), out, progress=False)
    return out


@pytest.fixture(scope="module")
def local_batch(fleet: Path, config_file: Path, direct: Path,
                tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("batch") / "out"
    return run_batch([fleet], out, config_file=config_file, workers=2)


def read_summary(out: Path) -> dict[str, dict[str, str]]:
    with open(out / "summary.csv", newline="", encoding="utf-8") as fh:
        return {r["bag"]: r for r in csv.DictReader(fh)}


def test_local_cluster_runs_every_bag_and_a_garbage_bag_fails_alone(local_batch) -> None:
    rows = read_summary(local_batch.out_dir)
    assert set(rows) == {"hall", "corridor", "broken"}
    assert rows["broken"]["status"] == "failed"
    assert "not a ROS1 bag" in rows["broken"]["error"]
    assert "\n" not in rows["broken"]["error"]
    for scene in SCENES:
        row = rows[scene]
        assert row["status"] == "ok" and row["error"] == ""
        assert row["worker"].startswith("tcp://127.0.0.1:")
        traj = (local_batch.out_dir / scene / "trajectory.tum").read_text().splitlines()
        assert int(row["poses"]) == len(traj) > 20
        assert int(row["scans"]) >= int(row["poses"])
        assert {p.name for p in (local_batch.out_dir / scene).iterdir()} == \
            {"trajectory.tum", "scans.csv", "map.ply", "map_dense.ply", "config.yaml"}
    assert (local_batch.n_ok, local_batch.n_failed, local_batch.n_skipped) == (2, 1, 0)
    md = (local_batch.out_dir / "summary.md").read_text()
    assert md.startswith("| bag | status |") and md.count("\n") == 5


def test_summary_says_what_the_sensor_checks_concluded(local_batch) -> None:
    """4 s bags: 3.5 s of updates, under the 5 s the checks need at the end of the data; the
    column says so, as each bag's config.yaml records it."""
    import yaml

    rows = read_summary(local_batch.out_dir)
    assert rows["broken"]["sensor_checks"] == ""
    for scene in SCENES:
        measured = yaml.safe_load((local_batch.out_dir / scene / "config.yaml").read_text())[
            "measured"]
        assert measured["imu_time_offset_unsettled_after_s"] < 5.0
        assert measured["extrinsic_rotation_unsettled_after_s"] < 5.0
        assert measured["extrinsic_translation_unsettled_after_s"] < 5.0
        assert measured["gyro_scale_unsettled_after_s"] < 5.0
        assert rows[scene]["sensor_checks"] == ("offset not checked; rotation not checked; "
                                                "gyro scale not checked; "
                                                "translation not checked")


def test_trajectory_is_bit_identical_to_a_direct_run(local_batch, direct: Path) -> None:
    for name in ("trajectory.tum", "config.yaml", "map.ply"):
        assert (local_batch.out_dir / "hall" / name).read_bytes() == (direct / name).read_bytes()


def test_summary_ate_is_the_ate_of_the_written_trajectory(local_batch, fleet: Path) -> None:
    rows = read_summary(local_batch.out_dir)
    for scene in SCENES:
        truth = ate(local_batch.out_dir / scene / "trajectory.tum", fleet / scene / "gt.tum",
                    align="se3")["rmse_m"]
        assert float(rows[scene]["ate_se3_m"]) == pytest.approx(truth, rel=1e-5)
        assert truth < 0.2
    assert rows["broken"]["ate_se3_m"] == ""


def test_rerun_skips_finished_bags_and_retries_failed_ones(local_batch, fleet: Path,
                                                           config_file: Path) -> None:
    out = local_batch.out_dir
    before = {s: (out / s / "trajectory.tum").stat().st_mtime_ns for s in SCENES}
    old = read_summary(out)
    proc = subprocess.run(
        [sys.executable, "-m", "adalio.cli", "batch", str(fleet), "--out", str(out),
         "--config", str(config_file), "--workers", "1"],
        check=False, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, proc.stderr
    assert "2 skipped" in proc.stderr and "Traceback" not in proc.stderr
    assert "| broken | failed |" in proc.stdout
    rows = read_summary(out)
    for scene in SCENES:
        assert (out / scene / "trajectory.tum").stat().st_mtime_ns == before[scene]
        assert rows[scene] == old[scene]
    assert rows["broken"]["worker"].startswith("tcp://127.0.0.1:")


def test_force_reruns_a_finished_bag(local_batch, fleet: Path, config_file: Path) -> None:
    out = local_batch.out_dir
    marker = out / ".adalio-batch" / "hall.json"
    first = json.loads(marker.read_text())["row"]["wall_s"]
    res = run_batch([fleet / "hall" / "hall.bag"], out, config_file=config_file, workers=1,
                    force=True)
    assert [(r.bag, r.status, r.skipped) for r in res.rows] == [("hall", "ok", False)]
    assert json.loads(marker.read_text())["row"]["wall_s"] != first
    # a changed setting is not "done" either
    res = run_batch([fleet / "hall" / "hall.bag"], out, config_file=config_file, workers=1,
                    mode="fixed")
    assert not res.rows[0].skipped and res.rows[0].status == "ok"
    # nor is a bag recorded again at the same path (its file changed: here its time stamp)
    bag = fleet / "hall" / "hall.bag"
    res = run_batch([bag], out, config_file=config_file, workers=1, mode="fixed")
    assert res.rows[0].skipped
    st = bag.stat()
    os.utime(bag, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    res = run_batch([bag], out, config_file=config_file, workers=1, mode="fixed")
    assert not res.rows[0].skipped and res.rows[0].status == "ok"


def test_a_set_mode_is_the_mode_the_bags_run(fleet: Path, config_file: Path,
                                             tmp_path: Path) -> None:
    """``--set adaptive.mode=...`` without ``--mode`` is the mode each bag's written
    config.yaml says it ran (it was replaced by ``adaptive`` before), and a mode that does not
    exist is refused like any other bad setting."""
    res = run_batch([fleet / "hall" / "hall.bag"], tmp_path / "o", config_file=config_file,
                    workers=1, overrides={"adaptive.mode": "fixed"})
    assert res.rows[0].status == "ok"
    written = load_config(None, tmp_path / "o" / "hall" / "config.yaml")
    assert written.adaptive.mode == "fixed"
    with pytest.raises(ConfigError, match="adaptive.mode"):
        run_batch([fleet / "hall" / "hall.bag"], tmp_path / "o2", config_file=config_file,
                  workers=1, overrides={"adaptive.mode": "turbo"})


def _wait_for(predicate, what: str, procs: list[subprocess.Popen]) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not predicate():
        for p in procs:
            if p.poll() is not None:
                raise AssertionError(f"{what}: {p.args[:2]} exited with {p.returncode}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


@contextlib.contextmanager
def dask_processes(tmp_path: Path, n_workers: int, *, nanny: bool = True
                   ) -> Iterator[tuple[str, list[subprocess.Popen]]]:
    """A ``dask scheduler`` and ``n_workers`` ``dask worker`` processes on 127.0.0.1: the
    scheduler's address and the processes (the scheduler first), stopped on exit."""
    dask_bin = str(Path(sys.executable).parent / "dask")
    sched_file = tmp_path / "scheduler.json"
    common = ["--scheduler-file", str(sched_file), "--no-dashboard"]
    procs: list[subprocess.Popen] = []
    try:
        procs.append(subprocess.Popen([dask_bin, "scheduler", "--host", "127.0.0.1",
                                       "--port", "0", *common],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        _wait_for(sched_file.is_file, "the scheduler file", procs)
        for _ in range(n_workers):
            procs.append(subprocess.Popen(
                [dask_bin, "worker", "--nthreads", "1", "--host", "127.0.0.1",
                 "--memory-limit", "0", *([] if nanny else ["--no-nanny"]), *common],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        yield json.loads(sched_file.read_text())["address"], procs
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=10)


def test_external_cluster_runs_the_bags_on_its_workers(fleet: Path, config_file: Path,
                                                       direct: Path, tmp_path: Path) -> None:
    from distributed import Client

    with dask_processes(tmp_path, 2) as (address, _):
        assert address.startswith("tcp://127.0.0.1:")
        with Client(address, timeout="20s") as client:
            client.wait_for_workers(2, timeout=TIMEOUT_S)
            workers = set(client.scheduler_info()["workers"])
        assert len(workers) == 2
        out = tmp_path / "out"
        res = run_batch([fleet / s / f"{s}.bag" for s in SCENES], out,
                        config_file=config_file, scheduler=address)
        rows = read_summary(out)
        assert [r.status for r in res.rows] == ["ok", "ok"]
        assert {r["worker"] for r in rows.values()} <= workers
        assert (out / "hall" / "trajectory.tum").read_bytes() == \
            (direct / "trajectory.tum").read_bytes()


def test_a_cluster_that_loses_every_worker_fails_the_bags_left(fleet: Path, config_file: Path,
                                                              tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch
                                                              ) -> None:
    """A ``dask scheduler`` whose one worker (no nanny to restart it) is killed while it runs a
    bag: the bags left fail once the scheduler has had no worker for ``NO_WORKER_S``, their rows
    say so, and the summary is written. Before session 77 the batch waited for ever."""
    import signal
    import threading

    from distributed import Client

    import adalio.batch

    monkeypatch.setattr(adalio.batch, "NO_WORKER_S", 2.0)
    killed: list[str] = []
    with dask_processes(tmp_path, 1, nanny=False) as (address, procs), \
            Client(address, timeout="20s") as client:
        client.wait_for_workers(1, timeout=TIMEOUT_S)

        def kill_when_busy() -> None:
            deadline = time.monotonic() + TIMEOUT_S
            while time.monotonic() < deadline:
                busy = [k for keys in client.processing().values() for k in keys]
                if busy:
                    procs[1].send_signal(signal.SIGKILL)
                    killed.extend(busy)
                    return
                time.sleep(0.05)

        watcher = threading.Thread(target=kill_when_busy, daemon=True)
        watcher.start()
        t0 = time.monotonic()
        res = run_batch([fleet / s / f"{s}.bag" for s in SCENES], tmp_path / "out",
                        config_file=config_file, scheduler=address)
        took = time.monotonic() - t0
        watcher.join(timeout=10)
    assert killed, "the worker was never seen running a bag"
    assert [r.status for r in res.rows] == ["failed", "failed"], res.rows
    for row in read_summary(tmp_path / "out").values():
        assert row["error"].startswith("not run: the Dask scheduler had no worker for 2 s")
    assert took < TIMEOUT_S


def test_bad_command_line_input_is_one_error_line(fleet: Path, tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    cases = [([str(empty), "--out", str(tmp_path / "o")], "no bags in folder"),
             ([str(tmp_path / "missing"), "--out", str(tmp_path / "o")], "does not exist"),
             ([str(fleet / "hall"), "--out", str(a_file)], "is a file")]
    for args, message in cases:
        proc = subprocess.run([sys.executable, "-m", "adalio.cli", "batch", *args],
                              check=False, capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2
        assert proc.stderr.strip().startswith("error:") and message in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1


def test_ctrl_c_cancels_and_keeps_finished_bags(fleet: Path, config_file: Path, direct: Path,
                                                tmp_path: Path) -> None:
    import signal

    out = tmp_path / "out"
    marker = out / ".adalio-batch" / "corridor.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "adalio.cli", "batch", str(fleet), "--out", str(out),
         "--config", str(config_file), "--workers", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _wait_for(marker.is_file, "the first finished bag", [proc])
        os.killpg(proc.pid, signal.SIGINT)
        _, stderr = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "interrupted" in stderr
    rows = read_summary(out)
    assert rows["corridor"]["status"] == "ok"
    assert rows["hall"]["status"] in ("ok", "cancelled")
    assert (out / "corridor" / "trajectory.tum").is_file()


def test_a_ctrl_c_that_lands_in_a_del_still_stops_the_batch(monkeypatch: pytest.MonkeyPatch,
                                                           tmp_path: Path) -> None:
    """A Ctrl-C raised where Python cannot raise (a Dask future's ``__del__``, as in a CI run
    of the test above: 'Exception ignored in: <function Future.__del__ ...>
    KeyboardInterrupt', and the batch ran on to exit 1) is dropped. The batch's loop takes the
    first Ctrl-C as a flag it reads instead (``pipeline.GracefulStop``), so it stops all the
    same: ``_gather`` reports the interrupt and cancels the bags. Reproduced without a cluster:
    the SIGINT is sent from inside a ``__del__`` while no bag has finished; on the code before,
    the interrupt is lost and the loop runs until the (fake) bags are done."""
    import signal

    import distributed

    import adalio.batch
    from adalio.batch import BagJob

    class Dying:
        def __del__(self) -> None:
            os.kill(os.getpid(), signal.SIGINT)

    class Batches:
        def __init__(self, futures: list) -> None:
            self.futures, self.calls = futures, 0

        def next_batch(self, block: bool = False) -> list:
            self.calls += 1
            if self.calls == 2:
                Dying()  # collected at once: its __del__ sends the Ctrl-C
            return list(self.futures) if self.calls > 20 else []  # then every bag is done

    class Future:
        def result(self) -> adalio.batch.BagRow:
            return adalio.batch.BagRow(bag="x", status="ok")

    class Client:
        def __init__(self) -> None:
            self.cancelled: list = []

        def submit(self, *args: object, **kwargs: object) -> Future:
            return Future()

        def nthreads(self) -> dict:
            return {"worker": 1}

        def cancel(self, futures: list, force: bool = False) -> None:
            self.cancelled.extend(futures)

    monkeypatch.setattr(distributed, "as_completed", Batches)
    monkeypatch.setattr(adalio.batch, "WATCH_S", 0.01)
    jobs = [BagJob(name=n, bag_path=tmp_path / f"{n}.bag", config=None, out_dir=tmp_path)
            for n in ("a", "b")]
    client = Client()
    rows: dict = {}
    before = signal.getsignal(signal.SIGINT)
    assert adalio.batch._gather(client, jobs, rows, len(jobs), False, None) is True
    assert len(client.cancelled) == 2 and rows == {}
    assert signal.getsignal(signal.SIGINT) is before  # restored


def test_unreachable_scheduler_is_an_input_error(fleet: Path, tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    import socket

    import adalio.batch

    monkeypatch.setattr(adalio.batch, "CONNECT_TIMEOUT_S", 2.0)

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(InputError, match="cannot reach the Dask scheduler"):
        run_batch([fleet / "hall" / "hall.bag"], tmp_path / "o",
                  scheduler=f"tcp://127.0.0.1:{port}")
    for address in ("foo", "tcp://127.0.0.1", "http://127.0.0.1:8786"):
        with pytest.raises(InputError, match="is not a scheduler address"):
            run_batch([fleet / "hall" / "hall.bag"], tmp_path / "o", scheduler=address)


def test_linked_folders_are_searched_once(tmp_path: Path) -> None:
    """A data folder linked into a batch folder is searched (os.walk did not follow links: its
    bags were skipped without a word); linked twice, its bags run once; a link back up the tree
    ends there."""
    data = tmp_path / "data" / "site"
    data.mkdir(parents=True)
    (data / "a.bag").write_bytes(b"")
    batch = tmp_path / "batch"
    batch.mkdir()
    (batch / "b.bag").write_bytes(b"")
    (batch / "site").symlink_to(data)
    (batch / "again").symlink_to(data)
    (batch / "up").symlink_to(batch)
    assert find_bags([batch]) == [batch / "again" / "a.bag", batch / "b.bag"]


def test_finding_bags_names_and_ground_truth(tmp_path: Path) -> None:
    for day in ("day1", "day2"):
        (tmp_path / day).mkdir()
        (tmp_path / day / "run.bag").write_bytes(b"")
    ros2 = tmp_path / "day2" / "walk_ros2"
    ros2.mkdir()
    (ros2 / "metadata.yaml").write_text("x")
    (ros2 / "walk_ros2_0.mcap").write_bytes(b"")
    (tmp_path / "day2" / "loop.mcap").write_bytes(b"")
    (tmp_path / "day1" / "gt.tum").write_text("")
    (tmp_path / "day2" / "run_gt.tum").write_text("")
    bags = find_bags([tmp_path])
    assert bags == [tmp_path / "day1" / "run.bag", tmp_path / "day2" / "loop.mcap",
                    tmp_path / "day2" / "run.bag", ros2]
    # one folder given as a str or a Path, not a list: the same (a str was read as its
    # characters, and '/' walked the whole file system)
    assert find_bags(str(tmp_path)) == bags and find_bags(tmp_path) == bags
    assert unique_names(bags) == ["day1_run", "loop", "day2_run", "walk_ros2"]
    assert find_gt(bags[0]) == tmp_path / "day1" / "gt.tum"
    assert find_gt(bags[2]) is None
    assert find_gt(bags[2], "{name}_gt.tum") == tmp_path / "day2" / "run_gt.tum"
    assert find_gt(bags[0], "{dir}/../day2/{name}_gt.tum") is not None


def test_a_task_outside_a_cluster_reports_errors_as_rows(tmp_path: Path) -> None:
    from adalio.batch import BagJob

    bad = tmp_path / "x.bag"
    bad.write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    row = process_bag(BagJob("x", bad, load_config(), tmp_path / "out"))
    assert row.status == "failed" and row.error and "\n" not in row.error
    assert not (tmp_path / "out" / ".adalio-batch" / "x.json").exists()


@pytest.mark.parametrize("numba_threads", [None, "1"])
def test_embedded_workers_read_their_bags_without_a_read_ahead_thread(monkeypatch,
                                                                      numba_threads) -> None:
    """The embedded workers share the cores one bag each, so their Sequencers do not read ahead
    (adalio run's thread would only compete there), whether or not NUMBA_NUM_THREADS is set."""
    from adalio.batch import dask_client

    if numba_threads is None:
        monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("NUMBA_NUM_THREADS", numba_threads)
    with dask_client(workers=2) as client:
        got = client.run(lambda: __import__("adalio.io.sequencer",
                                            fromlist=["Sequencer"]).Sequencer.read_ahead)
    assert list(got.values()) == [False, False]


def test_embedded_workers_share_the_cores_between_their_numba_threads(monkeypatch) -> None:
    """Two workers on this machine: a bag's task thread gets cores // 2 numba threads (at least
    1), so the parallel kernels of two bags never spin-wait for each other's cores; the workers'
    own numba pools stay as numba made them (changing NUMBA_NUM_THREADS after numba launched its
    threads is an error)."""
    from adalio.batch import dask_client, use_bag_threads
    from adalio.cpus import usable_cpus

    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    with dask_client(workers=2) as client:
        got = [client.submit(use_bag_threads, pure=False, workers=[w]).result()
               for w in client.scheduler_info()["workers"]]
    assert len(got) == 2
    assert got == [max(1, usable_cpus() // 2)] * 2
