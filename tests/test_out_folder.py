"""A run into a folder that holds an earlier run: nothing of the earlier run is left to be
read as this one's."""

from pathlib import Path

from adalio.config import load_config
from adalio.eval.report import REPORT_FILES, make_report
from adalio.pipeline import run_bag
from adalio.sim import cached_sequence


def test_a_run_into_an_earlier_runs_folder_leaves_none_of_its_outputs(tmp_path: Path) -> None:
    """The first run writes a PLY map and a report (with ground truth); the second, into the
    same folder, writes a PCD map and no report. Afterwards the folder holds the second run's
    files only, and a file of the user's is untouched."""
    sim = cached_sequence("hall", seed=1, duration_s=6.0, columns=500)
    cfg = load_config(config_file=sim.config_path)
    out = tmp_path / "run"
    run_bag(sim.bag_path, cfg, out, progress=False)
    make_report(out, gt=sim.gt_path)
    first = {p.name for p in out.iterdir()}
    assert set(REPORT_FILES) <= first and {"map.ply", "map_dense.ply"} <= first
    (out / "notes.txt").write_text("mine")

    res = run_bag(sim.bag_path, cfg, out, progress=False, max_scans=30, map_format="pcd")
    second = {p.name for p in out.iterdir()}
    assert not set(REPORT_FILES) & second and not {"map.ply", "map_dense.ply"} & second
    # exactly what a run writes, whatever a report's file list says
    assert second == {"map.pcd", "map_dense.pcd", "trajectory.tum", "scans.csv", "config.yaml",
                      "notes.txt"}
    assert (out / "notes.txt").read_text() == "mine"
    assert res.map_path == out / "map.pcd"
    assert 0 < len((out / "trajectory.tum").read_text().splitlines()) <= 30
