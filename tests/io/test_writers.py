"""Writers: exact TUM stamps, PLY read back by trimesh (independent reader), PCD, scans.csv."""

from __future__ import annotations

import csv
import io

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from adalio.io.writers import (
    SCANS_CSV_COLUMNS,
    ScansCsvWriter,
    TumWriter,
    ns_to_s_str,
    read_pcd_points,
    read_tum,
    rewrite_sigmas,
    sort_rows_by_time,
    write_pcd,
    write_ply,
)
from adalio.pipeline import _flag_ranges, default_out_dir
from adalio.types import ScanStats


def test_tum_rows_exact_stamps_and_poses(tmp_path):
    rng = np.random.default_rng(0)
    stamps = [1_646_304_541_527_137_041, 5, 1_700_000_000_999_999_999]
    poses = []
    with TumWriter(tmp_path / "t.tum") as w:
        for k, t in enumerate(stamps):
            T = np.eye(4)
            T[:3, :3] = Rotation.random(random_state=k).as_matrix()
            T[:3, 3] = rng.normal(size=3) * 100
            poses.append(T)
            w.write(t, T)
            assert len((tmp_path / "t.tum").read_text().splitlines()) == k + 1  # flushed
    t_ns, vals = read_tum(tmp_path / "t.tum")
    assert t_ns.tolist() == stamps
    assert (tmp_path / "t.tum").read_text().split()[0] == "1646304541.527137041"
    for T, v in zip(poses, vals, strict=True):
        np.testing.assert_allclose(v[:3], T[:3, 3], atol=1e-8)
        R = Rotation.from_quat(v[3:]).as_matrix()
        np.testing.assert_allclose(R, T[:3, :3], atol=1e-8)
    assert ns_to_s_str(-1_500_000_000) == "-1.500000000"


def test_ply_and_pcd_read_back(tmp_path):
    pts = np.random.default_rng(1).normal(size=(1000, 3)) * 10
    pts[5] = np.nan
    write_ply(tmp_path / "m.ply", pts)
    mesh = trimesh.load(tmp_path / "m.ply")
    finite = pts[np.isfinite(pts).all(axis=1)]
    np.testing.assert_array_equal(np.asarray(mesh.vertices), finite.astype(np.float32))
    write_pcd(tmp_path / "m.pcd", pts)
    np.testing.assert_array_equal(read_pcd_points(tmp_path / "m.pcd"), finite.astype(np.float32))
    write_ply(tmp_path / "empty.ply", np.zeros((0, 3)))
    assert "element vertex 0" in (tmp_path / "empty.ply").read_text()


def test_scans_csv_columns_and_values(tmp_path):
    w = ScansCsvWriter(tmp_path / "s.csv")
    st = ScanStats(t_ns=1_000_000_001, n_raw=10, n_down=5, degenerate=True, trigger="count",
                   voxel_size_m=0.1, eigenvalues=np.arange(6.0),
                   weakest_direction=np.eye(6)[3], degeneracy_score=0.25, held_directions=2,
                   min_restoring=0.125)
    w.write(st)
    w.write(ScanStats(t_ns=2_000_000_000))
    w.close()
    with open(tmp_path / "s.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(SCANS_CSV_COLUMNS)
    r = rows[0]
    assert (r["t_s"], r["n_raw"], r["degenerate"], r["trigger"]) == ("1.000000001", "10", "1",
                                                                     "count")
    assert [float(r[f"eig{i}"]) for i in range(6)] == list(range(6))
    assert float(r["weak_tx"]) == 1.0 and float(r["degeneracy_score"]) == 0.25
    assert (int(r["held_dirs"]), float(r["restoring_min"])) == (2, 0.125)
    assert int(rows[1]["held_dirs"]) == 0 and np.isnan(float(rows[1]["restoring_min"]))


def test_default_out_dir_is_auto_indexed(tmp_path):
    assert default_out_dir("/data/exp04.bag", tmp_path) == tmp_path / "exp04"
    (tmp_path / "exp04").mkdir()
    (tmp_path / "exp04_1").mkdir()
    assert default_out_dir("/data/exp04.bag", tmp_path) == tmp_path / "exp04_2"
    assert default_out_dir("/data/ros2_bag/", tmp_path) == tmp_path / "ros2_bag"


def test_flag_ranges():
    t = [0, 10**8, 2 * 10**8, 3 * 10**8, 4 * 10**8, 5 * 10**8]
    f = [False, True, True, False, True, True]
    assert _flag_ranges(t, f) == [(0.1, 0.2), (0.4, 0.5)]


def test_rows_written_late_are_sorted_into_time_order(tmp_path):
    """The backfill's rows arrive after later ones: sort_rows_by_time puts both files in time
    order (by the exact stamps, also across a change in the number of integer digits), header
    first, every row kept as written."""
    rng = np.random.default_rng(1)
    stamps = [9_000_000_000, 10_000_000_001, 10_000_000_002, 3, 999_999_999, 9_500_000_000]
    poses = {}
    with TumWriter(tmp_path / "t.tum") as w, ScansCsvWriter(tmp_path / "s.csv") as c:
        for t in stamps:
            T = np.eye(4)
            T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
            T[:3, 3] = rng.normal(size=3)
            poses[t] = T
            w.write(t, T)
            c.write(ScanStats(t_ns=t, n_raw=t % 1000, backfill=t < 9_000_000_000))
    before = {name: sorted((tmp_path / name).read_bytes().splitlines(keepends=True))
              for name in ("t.tum", "s.csv")}
    sort_rows_by_time(tmp_path / "t.tum", tmp_path / "s.csv")
    for name, lines in before.items():  # every line's bytes kept, its ending too (csv: \r\n)
        assert sorted((tmp_path / name).read_bytes().splitlines(keepends=True)) == lines
    assert (tmp_path / "s.csv").read_bytes().count(b"\r\n") == len(stamps) + 1
    t_ns, pose = read_tum(tmp_path / "t.tum")
    assert list(t_ns) == sorted(stamps)
    for t, row in zip(t_ns, pose, strict=True):
        assert np.allclose(row[:3], poses[int(t)][:3, 3], atol=1e-9)
    rows = list(csv.DictReader((tmp_path / "s.csv").open()))
    assert [r["t_s"] for r in rows] == [ns_to_s_str(t) for t in sorted(stamps)]
    assert [int(r["n_raw"]) for r in rows] == [t % 1000 for t in sorted(stamps)]
    assert [int(r["backfill"]) for r in rows] == [int(t < 9_000_000_000) for t in sorted(stamps)]


def test_sigmas_rewritten_in_the_rows_named_and_nowhere_else(tmp_path):
    """rewrite_sigmas (the sigmas widened at a run's end) changes the six sigma columns of the
    rows it is given, formatted as written, and no other byte; a file whose stamps are not the
    ones given is left as it is."""
    stamps = [5_000_000_000, 5_100_000_000, 5_200_000_000, 4_900_000_000]
    with ScansCsvWriter(tmp_path / "s.csv") as c:
        for k, t in enumerate(stamps):
            c.write(ScanStats(t_ns=t, n_raw=100 + k, trigger="eigen,ratio" if k else "",
                              sigma_p_world_m=np.full(3, 0.01 * (k + 1)),
                              sigma_rot_world_deg=np.full(3, 0.1 * (k + 1))))
    before = (tmp_path / "s.csv").read_bytes()
    wide = np.array([[0.01, 0.01, 0.01, 0.1, 0.1, 0.1], [0.5, 0.25, 0.125, 3.0, 2.0, 1.0],
                     [0.03, 0.03, 0.03, 0.3, 0.3, 0.3], [0.123456, 0.04, 0.04, 0.4, 0.4, 0.4]])
    assert rewrite_sigmas(tmp_path / "s.csv", np.array(stamps), wide, np.array([1, 3])) == 2
    rows = list(csv.DictReader((tmp_path / "s.csv").open(newline="")))
    cols = ["sigma_x_m", "sigma_y_m", "sigma_z_m", "sigma_roll_deg", "sigma_pitch_deg",
            "sigma_yaw_deg"]
    assert [r["sigma_x_m"] for r in rows] == ["0.01", "0.5", "0.03", "0.1235"]
    assert [float(rows[1][c]) for c in cols] == [0.5, 0.25, 0.125, 3.0, 2.0, 1.0]
    old = list(csv.DictReader(io.StringIO(before.decode())))
    for r, o in zip(rows, old, strict=True):  # every other field as written
        assert {k: v for k, v in r.items() if k not in cols} == \
            {k: v for k, v in o.items() if k not in cols}
    assert rows[1]["trigger"] == "eigen,ratio"
    lines, old_lines = (tmp_path / "s.csv").read_bytes().split(b"\r\n"), before.split(b"\r\n")
    assert [i for i, (a, b) in enumerate(zip(lines, old_lines, strict=True)) if a != b] == [2, 4]
    after = (tmp_path / "s.csv").read_bytes()
    wrong = np.array(stamps) + np.array([0, 0, 0, 1])
    assert rewrite_sigmas(tmp_path / "s.csv", wrong, wide * 2, np.array([0, 3])) == 0
    assert rewrite_sigmas(tmp_path / "s.csv", np.array(stamps[:3]), wide * 2,
                          np.array([0])) == 0
    assert (tmp_path / "s.csv").read_bytes() == after

