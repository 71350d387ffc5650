"""Result writers: TUM trajectories, binary PLY / PCD point maps and the per-scan ``scans.csv``.

TUM rows are ``t_s tx ty tz qx qy qz qw`` (seconds with 9 decimals, metres, unit quaternion
x y z w) of ``T_world_imu``; every row is flushed as written so an interrupted run keeps them.
Maps are float32 x y z in the world frame (metres).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import IO, Self

import numpy as np

from adalio.types import ScanStats

REPORT_FILES = ("report.md", "metrics.json", "trajectory_top.png", "trajectory_side.png",
                "error.png", "error_sigma.png", "degeneracy.png", "map_top.png")
"""What ``adalio report`` (``eval.report.make_report``) writes into a run folder; a run into the
folder removes an earlier run's (``pipeline.remove_stale_outputs``)."""

SIGMA_COLUMNS: tuple[str, ...] = ("sigma_x_m", "sigma_y_m", "sigma_z_m", "sigma_roll_deg",
                                  "sigma_pitch_deg", "sigma_yaw_deg")
"""The sigma columns of ``scans.csv`` (:func:`rewrite_sigmas` rewrites them at a run's end)."""


def scan_sigmas(stats: ScanStats) -> np.ndarray:
    """(6,) the values of :data:`SIGMA_COLUMNS` for a scan: position (m), then rotation (deg)."""
    return np.r_[np.resize(np.asarray(stats.sigma_p_world_m, float), 3),
                 np.resize(np.asarray(stats.sigma_rot_world_deg, float), 3)]


def _sigma_fields(sigmas: np.ndarray) -> list[str]:
    """:data:`SIGMA_COLUMNS` as ``scans.csv`` writes them."""
    return [f"{v:.4g}" for v in sigmas]


SCANS_CSV_COLUMNS: tuple[str, ...] = (
    "t_s", "n_raw", "n_down", "n_down_general", "n_near", "degenerate", "trigger",
    "voxel_size_m", "search_radius_m", "plane_margin_m", "n_matched", "iterations", "wall_ms",
    "eig0", "eig1", "eig2", "eig3", "eig4", "eig5", "weak_rx", "weak_ry", "weak_rz", "weak_tx",
    "weak_ty", "weak_tz", "degeneracy_score", "held_dirs", "restoring_min", "imu_gap",
    *SIGMA_COLUMNS, "backfill", "rest", "height_blind", "lidar_gap", "n_moving", "n_seen_through", "n_stray",
    "n_stray_dropped",
)


def ns_to_s_str(t_ns: int) -> str:
    """Exact decimal seconds with 9 decimals from int64 ns (no float rounding)."""
    t_ns = int(t_ns)
    sign = "-" if t_ns < 0 else ""
    q, r = divmod(abs(t_ns), 1_000_000_000)
    return f"{sign}{q}.{r:09d}"


def s_str_to_ns(field: str) -> int:
    """Exact int64 ns of decimal seconds as ``ns_to_s_str`` writes them (no float rounding)."""
    sec, _, frac = field.strip().partition(".")
    sign = -1 if sec.startswith("-") else 1
    return sign * (abs(int(sec)) * 1_000_000_000 + int((frac + "000000000")[:9]))


def matrix_to_tum_fields(T: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    T = np.asarray(T, dtype=np.float64)
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    return [*T[:3, 3].tolist(), *q.tolist()]


class _RowFile:
    """A text output written row by row and flushed per row; closing is idempotent."""

    def __init__(self, path: str | Path, newline: str | None = None) -> None:
        self.path = Path(path)
        self._fh: IO[str] | None = open(  # noqa: SIM115
            self.path, "w", encoding="utf-8", newline=newline)
        self.rows = 0

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class TumWriter(_RowFile):
    """Append-only TUM trajectory file, flushed per row."""

    def write(self, t_ns: int, T_world_imu: np.ndarray) -> None:
        vals = matrix_to_tum_fields(T_world_imu)
        assert self._fh is not None
        self._fh.write(ns_to_s_str(t_ns) + " " + " ".join(f"{v:.9f}" for v in vals) + "\n")
        self._fh.flush()
        self.rows += 1


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns (N,) int64, poses (N,7) tx ty tz qx qy qz qw) of a TUM file ('#' lines skipped)."""
    t, vals = [], []
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        t.append(s_str_to_ns(parts[0]))
        vals.append([float(v) for v in parts[1:8]])
    return np.array(t, dtype=np.int64), np.array(vals, dtype=np.float64).reshape(-1, 7)


class ScansCsvWriter(_RowFile):
    """``scans.csv`` with :data:`SCANS_CSV_COLUMNS`, flushed per row."""

    def __init__(self, path: str | Path) -> None:
        super().__init__(path, newline="")
        assert self._fh is not None
        self._csv = csv.writer(self._fh)
        self._csv.writerow(SCANS_CSV_COLUMNS)
        self._fh.flush()

    def write(self, stats: ScanStats) -> None:
        eig = np.zeros(6) if stats.eigenvalues is None else np.asarray(stats.eigenvalues)
        weak = np.zeros(6) if stats.weakest_direction is None \
            else np.asarray(stats.weakest_direction)
        eig = np.resize(eig.astype(float), 6)
        weak = np.resize(weak.astype(float), 6)
        row = [ns_to_s_str(stats.t_ns), stats.n_raw, stats.n_down, stats.n_down_general,
               stats.n_near, int(bool(stats.degenerate)), stats.trigger,
               f"{stats.voxel_size_m:.6g}", f"{stats.search_radius_m:.6g}",
               f"{stats.plane_margin_m:.6g}", stats.n_matched, stats.iterations,
               f"{stats.wall_ms:.3f}", *[f"{v:.6g}" for v in eig],
               *[f"{v:.6g}" for v in weak], f"{stats.degeneracy_score:.6g}",
               stats.held_directions, f"{stats.min_restoring:.4g}",
               f"{stats.imu_gap_s:.4g}",
               *_sigma_fields(scan_sigmas(stats)),
               int(bool(stats.backfill)), int(bool(stats.rest_update)),
               int(bool(stats.height_blind)), f"{stats.lidar_gap_s:.4g}", stats.n_moving,
               stats.n_seen_through, stats.n_stray, stats.n_stray_dropped]
        assert self._fh is not None
        self._csv.writerow(row)
        self._fh.flush()
        self.rows += 1


def rewrite_sigmas(path: str | Path, t_ns: np.ndarray, sigmas: np.ndarray,
                   rows: np.ndarray) -> int:
    """Rewrite the :data:`SIGMA_COLUMNS` of the data rows ``rows`` (indices in the file's
    order) of a ``scans.csv`` written by :class:`ScansCsvWriter` with ``sigmas`` (N, 6: m, m,
    m, deg, deg, deg; formatted as written). ``t_ns`` (N,) are the stamps of all its data
    rows in the file's order: a file that does not hold them, row by row, is left as it is
    (0 returned). Returns the rows rewritten."""
    path = Path(path)
    with open(path, newline="") as fh:
        lines = fh.read().splitlines(keepends=True)
    if not lines:
        return 0
    header = next(csv.reader([lines[0]]))
    if not all(c in header for c in SIGMA_COLUMNS) or len(lines) - 1 != len(t_ns):
        return 0
    cols = [header.index(c) for c in SIGMA_COLUMNS]
    out = list(lines)
    for i in np.asarray(rows, dtype=np.int64):
        fields = next(csv.reader([lines[i + 1]]))
        if s_str_to_ns(fields[0]) != int(t_ns[i]):
            return 0
        for c, v in zip(cols, _sigma_fields(sigmas[i]), strict=True):
            fields[c] = v
        buf = io.StringIO()
        csv.writer(buf).writerow(fields)  # as ScansCsvWriter writes it
        out[i + 1] = buf.getvalue()
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as fh:
        fh.write("".join(out))
    tmp.replace(path)
    return len(rows)


def sort_rows_by_time(*paths: str | Path) -> None:
    """Rewrite row files (``trajectory.tum``, ``scans.csv``) with their data rows in time order
    (stable; header and comment lines first): the backfill's rows arrive after later ones.
    Every line keeps its bytes, line ending included (the csv module's ``\r\n`` in
    ``scans.csv``, as :func:`rewrite_sigmas` keeps them)."""
    for path in paths:
        path = Path(path)
        with open(path, newline="") as fh:
            lines = fh.read().splitlines(keepends=True)
        head = [ln for ln in lines if ln.startswith(("#", "t_s"))]
        rows = [ln for ln in lines if ln.strip() and not ln.startswith(("#", "t_s"))]
        rows.sort(key=lambda ln: s_str_to_ns(ln.split(",", 1)[0].split()[0]))  # stable
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "w", newline="") as fh:
            fh.write("".join(head + rows))
        tmp.replace(path)


def _points_f4(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    return np.ascontiguousarray(pts, dtype="<f4")


def write_ply(path: str | Path, points: np.ndarray) -> Path:
    """Binary little-endian PLY with float x y z vertices (Open3D / CloudCompare readable)."""
    pts = _points_f4(points)
    header = ("ply\nformat binary_little_endian 1.0\ncomment adalio map (world frame, metres)\n"
              f"element vertex {pts.shape[0]}\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n")
    path = Path(path)
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(pts.tobytes())
    return path


def write_pcd(path: str | Path, points: np.ndarray) -> Path:
    """Binary PCD v0.7 with float x y z."""
    pts = _points_f4(points)
    n = pts.shape[0]
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
              "SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
              f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")
    path = Path(path)
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(pts.tobytes())
    return path


def read_ply_points(path: str | Path) -> np.ndarray:
    """Points of a PLY written by :func:`write_ply` (binary little-endian float xyz)."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii").splitlines()
    if header[0] != "ply" or "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path} is not a binary little-endian PLY")
    n = next(int(h.split()[2]) for h in header if h.startswith("element vertex"))
    return np.frombuffer(raw[end:end + 12 * n], dtype="<f4").reshape(n, 3).astype(np.float64)


def read_pcd_points(path: str | Path) -> np.ndarray:
    """Points of a PCD written by :func:`write_pcd`."""
    raw = Path(path).read_bytes()
    end = raw.index(b"DATA binary\n") + len(b"DATA binary\n")
    header = raw[:end].decode("ascii").splitlines()
    n = next(int(h.split()[1]) for h in header if h.startswith("POINTS"))
    return np.frombuffer(raw[end:end + 12 * n], dtype="<f4").reshape(n, 3).astype(np.float64)


def write_map(path: str | Path, points: np.ndarray, fmt: str) -> Path:
    return write_pcd(path, points) if fmt == "pcd" else write_ply(path, points)
