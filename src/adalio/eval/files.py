"""Readers for the files a run leaves behind: TUM trajectories, ``scans.csv`` and the map.

Trajectories are TUM text files ``t x y z qx qy qz qw`` (seconds, metres, Hamilton quaternion in
x y z w order), read with evo's ``file_interface.read_tum_trajectory_file`` into an evo
``PoseTrajectory3D``; a whitespace-tolerant numpy fallback accepts tab / multi-space separated
files that evo's strict single-space reader refuses. Maps are binary little-endian PLY or binary
PCD point clouds (world frame, metres); only x, y, z are returned. Every problem with a file
becomes an :class:`~adalio.errors.InputError` with a one-line message.
"""

from __future__ import annotations

import csv
import warnings
from pathlib import Path

import numpy as np
from evo.core.trajectory import PoseTrajectory3D
from evo.tools import file_interface

from adalio.errors import InputError

TrajectoryLike = str | Path | PoseTrajectory3D
MAX_COORDINATE_M = 1e9
"""A position coordinate beyond this (metres; 150 times the Earth's radius) is refused: the
statistics of such numbers overflow (an ATE of inf, numpy warnings)."""


def read_trajectory(path: TrajectoryLike, what: str = "trajectory") -> PoseTrajectory3D:
    """Load a TUM file (or pass an evo trajectory through, copied) and validate it.

    Raises InputError if the file is missing, is not TUM, is empty, has non-finite values,
    zero quaternions, time stamps that go backwards or two different poses at one time stamp
    (a line repeated as it is is read once).
    """
    if isinstance(path, PoseTrajectory3D):
        import copy

        return copy.deepcopy(path)
    path = Path(path)
    if path.is_dir():
        inside = path / "trajectory.tum"
        hint = (f"the trajectory file in it ({inside}?)" if inside.is_file() else
                "a TUM file ('t x y z qx qy qz qw' per line)")
        raise InputError(f"{what} file {path} is a folder, not a TUM trajectory: give {hint}")
    if not path.is_file():
        raise InputError(f"{what} file {path} does not exist: check the path")
    try:
        traj = file_interface.read_tum_trajectory_file(str(path))
        stamps = np.asarray(traj.timestamps, dtype=np.float64)
        mat = np.column_stack([stamps, traj.positions_xyz,
                               np.roll(traj.orientations_quat_wxyz, -1, axis=1)])
    except Exception:  # noqa: BLE001 - evo raises several types for malformed text
        mat = _loadtxt_tum(path, what)
    return _trajectory_from_matrix(mat, path, what)


def _loadtxt_tum(path: Path, what: str) -> np.ndarray:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an empty file is reported below, once
            mat = np.loadtxt(path, comments="#", dtype=np.float64, ndmin=2)
    except (ValueError, UnicodeDecodeError):
        mat = None
    if mat is not None and mat.size == 0:
        raise InputError(f"{what} file {path} has no poses (it is empty or only comments); "
                         "give a trajectory with at least one 't x y z qx qy qz qw' line")
    if mat is None or mat.ndim != 2 or mat.shape[1] != 8:
        raise InputError(f"{what} file {path} is not a TUM trajectory: {_first_bad_line(path)}"
                         "expected 8 numbers 't x y z qx qy qz qw' per line")
    return mat


def _first_bad_line(path: Path) -> str:
    """``"line N (...) has ...; "`` for the first line of ``path`` that is not 8 numbers (after
    removing a ``#`` comment), or ``""`` when the file is not text."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError):
        return "it is not text; "
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        try:
            [float(f) for f in fields]
        except ValueError:
            numeric = False
        else:
            numeric = True
        if not numeric or len(fields) != 8:
            shown = line.strip() if len(line.strip()) <= 60 else line.strip()[:57] + "..."
            what = f"{len(fields)} numbers" if numeric else "text that is not a number"
            return f"line {number} ({shown!r}) has {what}; "
    return ""


def _trajectory_from_matrix(mat: np.ndarray, path: Path, what: str) -> PoseTrajectory3D:
    if mat.shape[0] == 0:
        raise InputError(f"{what} file {path} has no poses")
    if not np.all(np.isfinite(mat)):
        row = int(np.nonzero(~np.all(np.isfinite(mat), axis=1))[0][0])
        raise InputError(f"{what} file {path}: pose {row + 1} has a NaN/inf value")
    far = np.nonzero(np.any(np.abs(mat[:, 1:4]) > MAX_COORDINATE_M, axis=1))[0]
    if far.size:
        k = int(far[0])
        value = float(mat[k, 1 + int(np.argmax(np.abs(mat[k, 1:4])))])
        raise InputError(f"{what} file {path}: pose {k + 1} has a coordinate of {value:g} m, "
                         f"beyond ±{MAX_COORDINATE_M:g} m: are its x y z in metres?")
    stamps = mat[:, 0]
    back = np.nonzero(np.diff(stamps) < 0)[0]
    if back.size:
        raise InputError(f"{what} file {path}: time goes backwards at pose {back[0] + 2} "
                         f"({stamps[back[0]]:.6f} -> {stamps[back[0] + 1]:.6f} s); sort it by time")
    same = np.nonzero(np.diff(stamps) == 0)[0]
    if same.size:
        differ = same[np.any(mat[same] != mat[same + 1], axis=1)]
        if differ.size:
            k = int(differ[0])
            raise InputError(f"{what} file {path}: poses {k + 1} and {k + 2} have the same time "
                             f"stamp ({stamps[k]:.6f} s) but different poses; keep one pose per "
                             "time stamp")
        mat = np.delete(mat, same + 1, axis=0)  # lines repeated as they are: read once
        stamps = mat[:, 0]
    quat_xyzw = mat[:, 4:8]
    norms = np.linalg.norm(quat_xyzw, axis=1)
    if np.any(norms < 1e-9):
        row = int(np.argmin(norms))
        raise InputError(f"{what} file {path}: pose {row + 1} has a zero quaternion")
    quat_wxyz = np.roll(quat_xyzw / norms[:, None], 1, axis=1)
    return PoseTrajectory3D(positions_xyz=mat[:, 1:4].copy(), orientations_quat_wxyz=quat_wxyz,
                            timestamps=stamps.copy())


def read_scans_csv(path: str | Path) -> dict[str, np.ndarray]:
    """``scans.csv`` as one array per column (numbers as float64, ``trigger`` as str).

    ``degenerate`` is converted to bool whether written as 0/1 or true/false.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"scans file {path} does not exist: check the run directory")
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames is None:
            raise InputError(f"scans file {path} is empty")
        rows = list(reader)
        names = list(reader.fieldnames)
    out: dict[str, np.ndarray] = {}
    for name in names:
        values = [r.get(name) or "" for r in rows]
        if name == "trigger":
            out[name] = np.array(values, dtype=object)
            continue
        if name == "degenerate":
            out[name] = np.array([v.strip().lower() in ("1", "true", "yes", "1.0")
                                  for v in values], dtype=bool)
            continue
        try:
            out[name] = np.array([float(v) if v.strip() else np.nan for v in values])
        except ValueError:
            out[name] = np.array(values, dtype=object)
    if "t_s" not in out:
        raise InputError(f"scans file {path} has no 't_s' column: is it an adalio scans.csv?")
    return out


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}


def read_map_points(path: str | Path) -> np.ndarray:
    """x, y, z of a binary / ascii PLY or PCD point cloud as (N, 3) float64 (world frame, m)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"map file {path} does not exist")
    data = path.read_bytes()
    if path.suffix.lower() == ".ply" or data.startswith(b"ply"):
        return _read_ply(data, path)
    return _read_pcd(data, path)


def _split_header(data: bytes, end_token: bytes, path: Path) -> tuple[list[str], int]:
    pos = 0
    lines: list[str] = []
    while True:
        nl = data.find(b"\n", pos)
        if nl < 0:
            raise InputError(f"map file {path} has a truncated header")
        line = data[pos:nl].decode("ascii", errors="replace").strip()
        lines.append(line)
        pos = nl + 1
        if line.split(" ")[0].encode() == end_token:
            return lines, pos


def _read_ply(data: bytes, path: Path) -> np.ndarray:
    lines, body = _split_header(data, b"end_header", path)
    fmt = ""
    n_vertex = -1
    props: list[tuple[str, str]] = []
    in_vertex = False
    for line in lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                n_vertex = int(parts[2])
        elif parts[0] == "property" and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise InputError(f"map file {path}: unsupported vertex property {line!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    names = [p[0] for p in props]
    if n_vertex < 0 or not {"x", "y", "z"} <= set(names):
        raise InputError(f"map file {path}: no vertex element with x, y, z")
    if fmt == "ascii":
        arr = np.loadtxt(data[body:].decode().splitlines()[:n_vertex], ndmin=2)
        return arr[:, [names.index(c) for c in "xyz"]].astype(np.float64)
    endian = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    if endian is None:
        raise InputError(f"map file {path}: unknown PLY format {fmt!r}")
    dtype = np.dtype([(n, endian + t) for n, t in props])
    if len(data) - body < dtype.itemsize * n_vertex:
        raise InputError(f"map file {path} is truncated ({n_vertex} vertices announced)")
    rec = np.frombuffer(data, dtype=dtype, count=n_vertex, offset=body)
    return np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)


def _read_pcd(data: bytes, path: Path) -> np.ndarray:
    lines, body = _split_header(data, b"DATA", path)
    head: dict[str, list[str]] = {}
    for line in lines:
        parts = line.split()
        if parts and not parts[0].startswith("#"):
            head[parts[0].upper()] = parts[1:]
    try:
        fields = head["FIELDS"]
        sizes = [int(s) for s in head["SIZE"]]
        types = head["TYPE"]
        counts = [int(c) for c in head.get("COUNT", ["1"] * len(fields))]
        n_points = int(head["POINTS"][0])
        mode = head["DATA"][0]
    except (KeyError, IndexError, ValueError):
        raise InputError(f"map file {path} is neither a PLY nor a valid PCD file") from None
    if not {"x", "y", "z"} <= set(fields):
        raise InputError(f"map file {path}: PCD has no x, y, z fields")
    if mode == "ascii":
        arr = np.loadtxt(data[body:].decode().splitlines()[:n_points], ndmin=2)
        cols = np.cumsum([0] + counts)
        return arr[:, [cols[fields.index(c)] for c in "xyz"]].astype(np.float64)
    if mode != "binary":
        raise InputError(f"map file {path}: PCD DATA {mode!r} not supported (ascii or binary)")
    kinds = {"F": "f", "I": "i", "U": "u"}
    dtype = np.dtype([(f, f"<{kinds[t]}{s}", (c,)) if c > 1 else (f, f"<{kinds[t]}{s}")
                      for f, s, t, c in zip(fields, sizes, types, counts, strict=True)])
    if len(data) - body < dtype.itemsize * n_points:
        raise InputError(f"map file {path} is truncated ({n_points} points announced)")
    rec = np.frombuffer(data, dtype=dtype, count=n_points, offset=body)
    return np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
