"""Config loading: presets, strict keys, overrides, extrinsic validation."""

import numpy as np
import pytest

from adalio.config import available_presets, load_config, transform_from_xyz_quat
from adalio.errors import ConfigError


def test_presets_load_and_validate():
    names = available_presets()
    assert {"hilti2022", "hesai_xt32", "ouster", "velodyne"} <= set(names)
    for name in names:
        load_config(name)


def test_hilti_extrinsic_matches_calibration_quaternion():
    # Hilti calibration: quaternion xyzw (0.7071068, -0.7071068, 0, 0), t = (-0.001, -0.00855, 0.055)
    T_cli = np.array(transform_from_xyz_quat("-0.001 -0.00855 0.055 0.7071068 -0.7071068 0 0"))
    T_preset = load_config("hilti2022").T_imu_lidar()
    assert np.allclose(T_cli, T_preset, atol=1e-6)


def test_unknown_key_suggests_nearest():
    with pytest.raises(ConfigError, match="did you mean 'voxel_size_m'"):
        load_config(overrides={"adaptive.general.voxel_sze_m": 0.3})


def test_overrides_win_over_preset(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("preset: hilti2022\nadaptive: {mode: fixed}\n")
    cfg = load_config(config_file=f, overrides={"preprocess.blind_m": 1.5})
    assert cfg.adaptive.mode == "fixed"
    assert cfg.preprocess.blind_m == 1.5
    assert cfg.sensor.lidar_topic == "/hesai/pandar"


def test_non_rotation_extrinsic_rejected():
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(ConfigError, match="not a rigid transform"):
        load_config(overrides={"sensor.T_imu_lidar": T.tolist()})
    with pytest.raises(ConfigError, match="not 1"):
        transform_from_xyz_quat("0 0 0 1 1 0 0")


def test_wrong_type_names_key():
    with pytest.raises(ConfigError, match="filter.max_iterations"):
        load_config(overrides={"filter.max_iterations": "many"})
