"""`adalio demo --short` end to end (simulation, two modes, table, reports)."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner


@pytest.mark.slow
def test_demo_short(tmp_path):
    from adalio.cli import app

    out = tmp_path / "demo"
    res = CliRunner().invoke(app, ["demo", "--short", "--out", str(out)])
    assert res.exit_code == 0, res.output + repr(res.exception)
    data = json.loads((out / "compare.json").read_text())
    assert [r["mode"] for r in data["rows"]] == ["fixed", "adaptive"]
    for row in data["rows"]:
        assert row["n_scans"] > 10
        assert row["ate_rmse_m"] is not None and row["ate_rmse_m"] >= 0
        assert (out / row["out_dir"].split("/")[-1] / "report.md").is_file()
    assert "ATE rmse" in res.output and "compare.md" in res.output
