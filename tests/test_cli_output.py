"""What a new user sees: piped output keeps paths and commands whole, help shows flags without
types, ``info`` says where the extrinsic comes from, ``run --gt`` prints the ATE and the report,
the demo writes under ``runs/``, generated data stays out of the repository, and the pipeline
does not import the evaluation."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parent / "io"))
import bagfactory as bf

from adalio.cli import app

REPO = Path(__file__).resolve().parents[1]


def adalio_piped(*args: str, columns: str | None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    if columns is not None:
        env["COLUMNS"] = columns
    return subprocess.run([sys.executable, "-c", "from adalio.cli import main; main()",
                           *map(str, args)], capture_output=True, text=True, env=env,
                          timeout=300, check=False)


@pytest.fixture(scope="module")
def corridor():
    from adalio.sim import cached_sequence

    return cached_sequence("corridor", seed=0, duration_s=4.0, columns=512)


@pytest.mark.parametrize("columns", [None, "80"])
def test_piped_run_keeps_long_paths_on_one_line(tmp_path, corridor, columns):
    out = tmp_path / ("a_folder_name_long_enough_to_wrap_" * 3) / "run_with_ground_truth"
    proc = adalio_piped("run", corridor.bag_path, "--config", corridor.config_path, "--gt",
                        corridor.gt_path, "--out", out, columns=columns)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.splitlines()
    assert any(ln.startswith("done: ") and ln.endswith(f"→ {out}") for ln in lines), lines
    assert f"report: {out / 'report.md'}" in lines, lines
    ate = [ln for ln in lines if ln.startswith("ATE (SE(3)-aligned")]
    assert len(ate) == 1 and " m, max " in ate[0], lines
    assert (out / "report.md").is_file()


def test_piped_tables_are_not_wrapped(tmp_path, corridor):
    proc = adalio_piped("eval", corridor.gt_path, corridor.gt_path, columns="60")
    assert proc.returncode == 0, proc.stderr
    header = [ln for ln in proc.stdout.splitlines() if "RMSE (m)" in ln]
    assert len(header) == 2 and "max (m)" in header[0] and "drift (%)" in header[1], proc.stdout
    assert "[m]" not in proc.stdout


@pytest.mark.parametrize("command", ["run", "info", "eval", "report", "compare", "demo",
                                     "simulate"])
def test_help_has_no_bool_type(command):
    res = CliRunner().invoke(app, [command, "--help"])
    assert res.exit_code == 0, res.output
    assert "<bool>" not in res.output
    if command == "run":
        assert "--view" in res.output and "adalio[view]" in res.output and "--rrd" in res.output
        assert "--profile / --no-profile" in res.output
    if command == "demo":
        assert "runs/demo" in res.output


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    T[:3, 3] = [0.1, 0.0, 0.05]
    d = tmp_path_factory.mktemp("rigs")
    plain = bf.write_static_rig(d / "plain.bag", duration_s=1.0, columns=90)
    tf = bf.write_static_rig(d / "tf.bag", duration_s=1.0, columns=90,
                             tf_static=[("imu", "lidar", T)])
    return plain, tf


def test_info_says_where_the_extrinsic_comes_from(rigs, corridor, tmp_path):
    plain, tf = rigs
    runner = CliRunner()

    res = runner.invoke(app, ["info", str(plain)])
    assert res.exit_code == 0, res.output
    assert "extrinsic a run would use: T_imu_lidar from identity (fallback)" in res.output
    assert "warning: no extrinsic in the preset, the config or /tf_static" in res.output

    res = runner.invoke(app, ["info", str(corridor.bag_path), "--preset", "hilti2022"])
    assert res.exit_code == 0, res.output
    assert "T_imu_lidar from preset hilti2022: t = [-0.001, -0.00855, 0.055] m" in res.output
    assert "warning" not in res.output

    cfg = tmp_path / "c.yaml"
    cfg.write_text("sensor:\n  T_imu_lidar: [[1,0,0,0.2],[0,1,0,0],[0,0,1,0],[0,0,0,1]]\n")
    res = runner.invoke(app, ["info", str(plain), "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    assert f"T_imu_lidar from config file {cfg}: t = [0.2, 0.0, 0.0] m" in res.output

    res = runner.invoke(app, ["info", str(tf)])
    assert res.exit_code == 0, res.output
    assert "T_imu_lidar from tf_static (imu <- lidar): t = [0.1, 0.0, 0.05] m" in res.output
    assert "warning" not in res.output


def test_demo_writes_under_runs_by_default(monkeypatch):
    from adalio.errors import InputError
    from adalio.eval import demo

    seen = []

    def fake_run_demo(out_dir, **_):
        seen.append(Path(out_dir))
        raise InputError("stop here")

    monkeypatch.setattr(demo, "run_demo", fake_run_demo)
    res = CliRunner().invoke(app, ["demo", "--short"])
    assert isinstance(res.exception, InputError)
    assert seen == [Path("runs") / "demo"]
    assert "/runs/" in (REPO / ".gitignore").read_text().split()


def test_generated_sequences_stay_out_of_the_repository():
    from adalio.sim.cache import cache_root

    assert not cache_root().resolve().is_relative_to(REPO), cache_root()


def test_pipeline_does_not_import_eval():
    tree = ast.parse((REPO / "src" / "adalio" / "pipeline.py").read_text())
    names = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    names += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    assert not [m for m in names if m and m.startswith("adalio.eval")], names


@pytest.mark.parametrize("cold", [True, False])
def test_a_run_on_a_cold_kernel_cache_says_it_compiles(tmp_path, corridor, monkeypatch, cold):
    """A first run after an install sits at its first scan while the kernels compile: it says
    so before, and its summary says the timings include the compilation; a warm run says
    neither."""
    from adalio.lio import warmup

    monkeypatch.setattr(warmup, "cache_is_cold", lambda: cold)
    monkeypatch.setattr(warmup, "start", lambda: warmup.Warmup(None))
    res = CliRunner().invoke(app, ["run", str(corridor.bag_path), "--config",
                                   str(corridor.config_path), "--out", str(tmp_path / "o"),
                                   "--max-scans", "12", "--no-progress"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    before = [i for i, ln in enumerate(lines) if ln.startswith("note: first run after an install")]
    after = [i for i, ln in enumerate(lines) if ln.startswith("note: this run compiled")]
    done = [i for i, ln in enumerate(lines) if ln.startswith("done: ")]
    assert len(done) == 1, lines
    if cold:
        assert len(before) == 1 and len(after) == 1 and before[0] < done[0] < after[0], lines
    else:
        assert before == [] and after == [], lines


@pytest.mark.parametrize("fault", ["not_a_bag", "cloud_time_field_absent"])
def test_a_bad_input_on_a_cold_kernel_cache_is_still_one_error_line(tmp_path, monkeypatch,
                                                                    capsys, corridor, fault):
    """The compile notice comes once the first cloud is decoded, never before an input error:
    neither a file that is no bag nor a config naming a time field the clouds lack."""
    from adalio.cli import main
    from adalio.lio import warmup

    monkeypatch.setattr(warmup, "cache_is_cold", lambda: True)
    monkeypatch.setattr(warmup, "start", lambda: warmup.Warmup(None))
    if fault == "not_a_bag":
        bag = tmp_path / "not_a_bag.bag"
        bag.write_bytes(b"no bag here")
        extra: list[str] = []
    else:
        bag = corridor.bag_path
        from adalio.config import load_config

        config = load_config(config_file=corridor.config_path)
        config.sensor.point_time_field = "t"
        cfg = tmp_path / "t.yaml"
        cfg.write_text(config.to_yaml())
        extra = ["--config", str(cfg)]
    monkeypatch.setattr(sys, "argv", ["adalio", "run", str(bag), "--out", str(tmp_path / "o"),
                                      *extra])
    with pytest.raises(SystemExit) as stop:
        main()
    assert stop.value.code == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), lines
