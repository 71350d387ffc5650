"""Stray returns in a simulated sweep (``simulate(ghosts=..., dust=...)``): ghosts behind their
surface, dust in front of it. The independent truth is the same walk with neither (the same
seed: the same scene, motion, noise and dropouts), read back from both bags point by point
(the Ouster layout: organized, a point's place in the cloud is its beam and column)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from scipy import stats

from adalio.errors import InputError
from adalio.io.pointcloud2 import CloudLayout, decode_fields
from adalio.sim import cached_sequence, simulate
from adalio.sim.lidar import lidar_model

ADALIO = str(Path(sys.executable).with_name("adalio"))
WALK = {"seed": 3, "duration_s": 1.5, "columns": 256, "lidar": "ouster64"}
GHOSTS, DUST = 0.1, 0.2
LO, HI = 0.3, 2.0
"""The stray returns' distance from their surface along their ray (uniform, metres)."""
SLACK_M = 1e-4
"""What float32 coordinates of ranges up to ~30 m leave of a range difference."""


def _clouds(bag: Path) -> dict[str, np.ndarray]:
    """Every sweep's points (organized, zero where no return) stacked: xyz, intensity, t, ring."""
    out: dict[str, list] = {"xyz": [], "intensity": [], "t": [], "ring": []}
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.msgtype.endswith("PointCloud2")]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            f = decode_fields(msg.data, CloudLayout.from_msg(msg),
                              ["x", "y", "z", "intensity", "t", "ring"])
            out["xyz"].append(np.column_stack([f["x"], f["y"], f["z"]]))
            for k in ("intensity", "t", "ring"):
                out[k].append(np.asarray(f[k]))
    return {k: np.concatenate(v) for k, v in out.items()}


@pytest.fixture(scope="module")
def walks(tmp_path_factory):
    """The clean walk and the same walk with ghosts, with dust, and with both."""
    root = tmp_path_factory.mktemp("stray")
    runs = {"clean": {}, "ghosts": {"ghosts": GHOSTS}, "dust": {"dust": DUST},
            "both": {"ghosts": GHOSTS, "dust": DUST}}
    out = {}
    for name, kw in runs.items():
        res = simulate("hall", root / name, **WALK, **kw)
        out[name] = (_clouds(res.bag_path), json.loads(res.meta_path.read_text()))
    return out


def _compare(clean: dict, dirty: dict) -> dict[str, np.ndarray]:
    """Per point of the clean walk: valid in each, range change, and whether the ray is the
    same (the dirty point on the clean one's ray, pointing the same way)."""
    assert len(clean["xyz"]) == len(dirty["xyz"])
    # the layout is the same: the point times and rings are the beams', return or not
    assert np.array_equal(clean["t"], dirty["t"])
    assert np.array_equal(clean["ring"], dirty["ring"])
    a = clean["xyz"].astype(np.float64)
    b = dirty["xyz"].astype(np.float64)
    ra, rb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    va, vb = ra > 0, rb > 0
    both = va & vb
    cos = np.ones(len(a))
    cos[both] = (a[both] * b[both]).sum(1) / (ra[both] * rb[both])
    return {"va": va, "vb": vb, "both": both, "dr": rb - ra, "ra": ra, "cos": cos}


def _share_ok(count: int, n: int, p: float) -> bool:
    """``count`` of ``n`` is a Binomial(n, p) draw within 4 sigma."""
    return abs(count - n * p) <= 4.0 * math.sqrt(n * p * (1.0 - p))


def test_ghosts_push_a_tenth_of_the_returns_0_3_to_2_m_further_along_their_ray(walks):
    clean, meta_clean = walks["clean"]
    dirty, meta = walks["ghosts"]
    assert (meta["ghosts"], meta["dust"]) == (GHOSTS, 0.0)
    assert (meta_clean["ghosts"], meta_clean["dust"]) == (0.0, 0.0)
    c = _compare(clean, dirty)
    n = int(c["va"].sum())
    assert n > 100_000
    # no return appears, and in a 30 m hall none is pushed beyond the 100 m range
    assert np.array_equal(c["va"], c["vb"])
    assert lidar_model("ouster64").max_range_m - c["ra"].max() > HI
    moved = c["both"] & (c["dr"] != 0)
    # every other point is the clean one, bit for bit, intensity included
    same = c["both"] & ~moved
    assert np.array_equal(clean["xyz"][same], dirty["xyz"][same])
    assert np.array_equal(clean["intensity"][c["va"]], dirty["intensity"][c["va"]])
    dr = c["dr"][moved]
    assert dr.min() > LO - SLACK_M and dr.max() < HI + SLACK_M  # further, 0.3-2.0 m
    assert np.all(c["cos"][moved] > 1.0 - 1e-9)  # along the same ray, outwards
    assert _share_ok(int(moved.sum()), n, GHOSTS), moved.mean()
    assert stats.kstest(dr, stats.uniform(LO, HI - LO).cdf).pvalue > 1e-4


def test_dust_pulls_a_fifth_of_the_returns_0_3_to_2_m_nearer_or_below_the_minimum_range(walks):
    clean, _ = walks["clean"]
    dirty, meta = walks["dust"]
    assert (meta["ghosts"], meta["dust"]) == (0.0, DUST)
    c = _compare(clean, dirty)
    n = int(c["va"].sum())
    assert not np.any(c["vb"] & ~c["va"])  # no return appears
    lost = c["va"] & ~c["vb"]
    moved = c["both"] & (c["dr"] != 0)
    same = c["both"] & ~moved
    assert np.array_equal(clean["xyz"][same], dirty["xyz"][same])
    assert np.array_equal(clean["intensity"][c["both"]], dirty["intensity"][c["both"]])
    dr = c["dr"][moved]
    assert -dr.max() > LO - SLACK_M and -dr.min() < HI + SLACK_M  # nearer, 0.3-2.0 m
    assert np.all(c["cos"][moved] > 1.0 - 1e-9)  # along the same ray, still in front
    # a lost return was near enough for dust up to 2 m in front to fall below 0.05 m: the
    # operator's body behind the LiDAR; and a near return that stayed was pulled in by less
    min_range = lidar_model("ouster64").min_range_m
    assert lost.sum() > 100 and c["ra"][lost].max() < HI + min_range + SLACK_M
    assert np.all(c["ra"][moved] + c["dr"][moved] >= min_range - SLACK_M)
    assert _share_ok(int(moved.sum() + lost.sum()), n, DUST), (moved.sum() + lost.sum()) / n
    far = moved & (c["ra"] > HI + min_range)  # no offset was cut off by the minimum range
    assert stats.kstest(-c["dr"][far], stats.uniform(LO, HI - LO).cdf).pvalue > 1e-4


def test_ghosts_and_dust_together_each_keep_their_share_and_no_return_is_both(walks):
    clean, _ = walks["clean"]
    dirty, meta = walks["both"]
    assert (meta["ghosts"], meta["dust"]) == (GHOSTS, DUST)
    c = _compare(clean, dirty)
    n = int(c["va"].sum())
    lost = c["va"] & ~c["vb"]
    grown = c["both"] & (c["dr"] > 0)
    shrunk = c["both"] & (c["dr"] < 0)
    # a return both pushed and pulled would have moved by less than 0.3 m, or not at all
    assert np.all(np.abs(c["dr"][grown | shrunk]) > LO - SLACK_M)
    assert _share_ok(int(grown.sum()), n, GHOSTS), grown.mean()
    assert _share_ok(int(shrunk.sum() + lost.sum()), n, DUST), (shrunk.sum() + lost.sum()) / n


def test_shares_outside_0_to_0_5_are_refused(tmp_path):
    for kw, flag in (({"ghosts": 0.6}, "--ghosts"), ({"dust": -0.1}, "--dust"),
                     ({"ghosts": float("nan")}, "--ghosts"), ({"dust": float("nan")}, "--dust")):
        with pytest.raises(InputError, match=f"^{flag} must be a fraction 0-0.5 "):
            simulate("hall", tmp_path / "s", duration_s=1.0, columns=64, **kw)
        with pytest.raises(InputError, match=f"^{flag} must be a fraction 0-0.5 "):
            cached_sequence("hall", duration_s=1.0, columns=64, **kw)
    assert not (tmp_path / "s").exists()
    simulate("hall", tmp_path / "edge", duration_s=0.6, columns=64, ghosts=0.5, dust=0.5)


def test_the_command_line_refuses_a_share_in_one_error_line(tmp_path):
    for args, says in ((["--ghosts", "0.7"], "--ghosts must be a fraction 0-0.5 (got 0.7)"),
                       (["--dust", "nan"], "--dust must be a fraction 0-0.5 (got nan)")):
        proc = subprocess.run([ADALIO, "simulate", "--scene", "hall", "--out",
                               str(tmp_path / "s"), *args], capture_output=True, text=True,
                              timeout=120, check=False)
        both = proc.stdout + proc.stderr
        assert proc.returncode == 2, both
        assert "Traceback" not in both, both
        lines = [ln for ln in both.splitlines() if ln.strip()]
        assert lines == [f"error: {says}"], both
        assert not (tmp_path / "s").exists()
