"""The README's Python API example, run as written on a short simulated hall walk."""

from pathlib import Path

import numpy as np

from adalio import Bag, ImuBatch, Sequencer, load_config
from adalio.io.writers import read_tum
from adalio.sim import cached_sequence

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_api_code() -> str:
    """The first ```python block of the README's *Python API* section."""
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Python API"):]
    start = section.index("```python\n") + len("```python\n")
    return section[start:section.index("```", start)]


def test_readme_python_api_example_tracks_ground_truth():
    """Every scan the sequencer hands out gets a pose from the example's prints, the backfill's
    included (a 6 s walk is shorter than ``imu.backfill_after_s``: ``finish()`` runs it), and
    the poses lie on the ground truth."""
    sim = cached_sequence("hall", seed=1, duration_s=6.0, columns=500)
    code = readme_api_code()
    assert '"exp11.bag"' in code and 'load_config("hilti2022", ' in code
    code = code.replace('"exp11.bag"', repr(str(sim.bag_path)))
    code = code.replace('load_config("hilti2022", ',
                        f"load_config(config_file={str(sim.config_path)!r}, ")
    printed: list[tuple] = []
    namespace = {"print": lambda *args: printed.append(args)}
    exec(compile(code, str(README), "exec"), namespace)  # noqa: S102 - the README's own code
    assert namespace["map_world"].shape[1] == 3 and len(namespace["map_world"]) > 1000

    cfg = load_config(config_file=sim.config_path)
    with Bag(sim.bag_path) as bag:
        scan_ends = sorted(int(item.t_ns.max()) for item in
                           Sequencer(bag, cfg.sensor.lidar_topic, cfg.sensor.imu_topic,
                                     cfg.sensor) if not isinstance(item, ImuBatch))
    t_ns = np.array([int(a[0]) for a in printed])
    assert len(set(t_ns.tolist())) == len(t_ns), "a scan's pose printed twice"
    n_backfill = sum(1 for a in printed if a[-1] == "backfill")
    assert n_backfill > 0
    assert len(t_ns) == len(scan_ends), (len(t_ns), len(scan_ends), n_backfill)

    order = np.argsort(t_ns)
    p_est = np.array([np.asarray(printed[i][1]) for i in order])
    t_gt_ns, poses_gt = read_tum(sim.gt_path)
    t_gt_s = (t_gt_ns - t_gt_ns[0]) * 1e-9
    t_est_s = (t_ns[order] - t_gt_ns[0]) * 1e-9
    # gt.tum and the estimate share the world frame (IMU at t0): compare without alignment
    p_gt = np.stack([np.interp(t_est_s, t_gt_s, poses_gt[:, k]) for k in range(3)], axis=1)
    travelled = np.linalg.norm(np.diff(p_gt, axis=0), axis=1).sum()
    assert travelled > 1.0
    assert np.abs(p_est - p_gt).max() < 0.05


def test_run_bag_names_what_it_takes_in_the_configs_place(tmp_path):
    """`run_bag(bag, "hilti2022", out)` (a preset's name where the Config goes) is a ConfigError
    that says what to give (it was an AttributeError from inside), before anything is read."""
    import pytest

    from adalio.errors import ConfigError
    from adalio.pipeline import run_bag

    for wrong in ("hilti2022", {"preset": "hilti2022"}):
        with pytest.raises(ConfigError, match=r"run_bag takes a Config \(adalio\.load_config"):
            run_bag(tmp_path / "none.bag", wrong, tmp_path / "out")
    assert not (tmp_path / "out").exists()
