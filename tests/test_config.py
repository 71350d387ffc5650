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
    with pytest.raises(ConfigError, match=r"did you mean 'adaptive\.general\.voxel_size_m'\?$"):
        load_config(overrides={"adaptive.general.voxel_sze_m": 0.3})
    with pytest.raises(ConfigError, match=r"'adaptive\.mdoe'; did you mean 'adaptive\.mode'\?$"):
        load_config(overrides={"adaptive.mdoe": "fixed"})


def test_unknown_key_at_the_wrong_level_names_the_dotted_key():
    """A setting written without its section (or in another one) is suggested with its whole
    dotted key, every section that has it named; a close misspelling too."""
    with pytest.raises(ConfigError, match=r"unknown config key 'voxel_size_m'; did you mean "
                                          r"'adaptive\.general\.voxel_size_m'\? \(or "
                                          r"adaptive\.degenerate\.voxel_size_m\)$"):
        load_config(overrides={"voxel_size_m": 0.3})
    with pytest.raises(ConfigError, match=r"'map\.gate_sigma'; did you mean 'filter\.gate_sigmas'"):
        load_config(overrides={"map.gate_sigma": 3.0})
    with pytest.raises(ConfigError, match=r"'filter\.map_voxel_m'; did you mean "
                                          r"'output\.map_voxel_m'\?$"):  # not filter.map_...
        load_config(overrides={"filter.map_voxel_m": 0.1})
    with pytest.raises(ConfigError, match=r"'imu\.zzzq'; valid keys: imu\.gyro_cov, "):
        load_config(overrides={"imu.zzzq": 1})


def test_a_config_file_given_as_the_preset_names_config_file(tmp_path):
    """``load_config(path)`` (the file in the preset's place) and ``--preset file.yaml``: a
    ConfigError that says where the file goes, never a TypeError from the name matching."""
    f = tmp_path / "c.yaml"
    f.write_text("preset: hilti2022\n")
    for given in (f, str(f), "mine.yml"):
        with pytest.raises(ConfigError, match=r"is a file, not a preset name: pass it with "
                                              r"--config \(Python: load_config\(config_file="):
            load_config(given)
    with pytest.raises(ConfigError, match="a preset is named by a string, got int"):
        load_config(3)
    assert load_config(config_file=f).sensor.lidar_topic == "/hesai/pandar"


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


def test_a_lever_arm_in_millimetres_is_refused_with_its_metres():
    """Every preset's lever arm and a vehicle's (2 m) load; the HILTI rig's typed in millimetres
    (55 mm as 55) is refused, naming the key and the value in metres."""
    for name in available_presets():
        T = load_config(preset=name).T_imu_lidar()
        assert np.linalg.norm(T[:3, 3]) < 1.0
    T = load_config(preset="hilti2022").T_imu_lidar()
    vehicle = T.copy()
    vehicle[:3, 3] = [1.2, -0.8, 1.4]
    load_config(overrides={"sensor.T_imu_lidar": vehicle.tolist()})
    in_mm = T.copy()
    in_mm[:3, 3] *= 1000.0
    with pytest.raises(ConfigError, match=r"sensor\.T_imu_lidar's translation .* is 55\.7 m long"
                       r".* millimetres.* it is \[-0\.001, -0\.00855, 0\.055\] m"):
        load_config(overrides={"sensor.T_imu_lidar": in_mm.tolist()})


def test_wrong_type_names_key():
    with pytest.raises(ConfigError, match="filter.max_iterations"):
        load_config(overrides={"filter.max_iterations": "many"})


def test_generic_imu_noise_is_named_in_the_init_line(tmp_path):
    """The generic presets keep Faster-LIO's IMU densities, which cost the shafts their track
    (README, Presets): a run on them says so in its initialization line; a config with an IMU's
    own densities (hilti2022, the Livox presets' built-in IMUs since session 83 and the Ouster's
    since session 84, or a simulated sequence's) or measured white noise does not."""
    from dataclasses import replace

    from adalio.config import GENERIC_IMU_FIELDS, imu_noise_is_generic
    from adalio.pipeline import run_bag
    from adalio.sim import simulate

    for name in ("velodyne", "hesai_xt32"):
        assert imu_noise_is_generic(load_config(name).imu), name
    assert not imu_noise_is_generic(load_config("hilti2022").imu)
    for name in ("livox_mid360", "livox_avia", "ouster"):  # a built-in MEMS IMU of its class
        builtin = load_config(name).imu
        assert not imu_noise_is_generic(builtin), name
        for k in GENERIC_IMU_FIELDS:
            assert getattr(builtin, k) == getattr(load_config("hilti2022").imu, k), (name, k)
        assert builtin.noise_source == "at_least_config"  # a noisier one's white noise measured
    generic = load_config("velodyne").imu
    assert not imu_noise_is_generic(replace(generic, noise_source="measured"))
    assert imu_noise_is_generic(replace(generic, noise_source="config"))
    assert not imu_noise_is_generic(replace(generic, accel_bias_cov=1.85e-5))

    seq = simulate("hall", tmp_path / "seq", duration_s=3.0, columns=180, lidar="vlp16")
    own = load_config(config_file=seq.config_path)
    assert not imu_noise_is_generic(own.imu)  # the sequence describes its IMU
    lines = {}
    for label, cfg in (("own", own), ("generic", replace(own, imu=generic))):
        res = run_bag(seq.bag_path, cfg, tmp_path / label, progress=False)
        assert res.n_scans > 0
        lines[label] = res.init_report.describe()
    assert "generic values" in lines["generic"] and "generic values" not in lines["own"]


@pytest.mark.parametrize("start", ["still", "moving"])
def test_a_simulated_imu_10x_noisier_than_its_config_gets_its_gyro_raised(tmp_path, start):
    """End to end on simulated bags whose config.yaml describes the HILTI BMI085: with the
    simulator's IMU at its own noise the filter keeps the configured densities; with its white
    noise 10x, the default (at_least_config) raises the gyro's about 10x and keeps the
    accelerometer's, whose configured value (12x the BMI085's) the x10 noise does not exceed.
    From a still start (the still window) and from a moving start (3 s cut from a walk: the
    moving start's IMU samples, median of second differences)."""
    import re

    from adalio.pipeline import run_bag
    from adalio.sim import simulate

    moving = start == "moving"
    used = {}
    for scale in (1.0, 10.0):
        if moving:
            seq = simulate("hall", tmp_path / f"seq{scale:g}", seed=3, duration_s=6.0,
                           columns=512, imu_noise_scale=scale)
        else:
            seq = simulate("hall", tmp_path / f"seq{scale:g}", duration_s=1.5, columns=180,
                           lidar="vlp16", imu_noise_scale=scale)
        cfg = load_config(config_file=seq.config_path, overrides={"imu.backfill_s": "0"})
        assert cfg.imu.noise_source == "at_least_config"
        res = run_bag(seq.bag_path, cfg, tmp_path / f"run{scale:g}", progress=False,
                      start_s=3.0 if moving else 0.0)
        assert res.init_report.method == ("moving" if moving else "static") and res.n_scans > 0
        used[scale] = res.init_report.noise_used
    assert used[1.0] == "config"
    m = re.fullmatch(r"measured gyro \(([0-9.]+)x the configured density\) and config "
                     r"accelerometer", used[10.0])
    assert m is not None, used[10.0]
    assert 8.5 <= float(m.group(1)) <= 11.5


def test_a_key_given_twice_in_a_config_file_is_an_error(tmp_path):
    """YAML keeps the last of two equal keys: a second `preprocess:` section silently dropped
    the first one's settings. Now an error naming the key and its line; anchors and merges
    (`<<`) still read."""
    f = tmp_path / "twice.yaml"
    f.write_text("preprocess:\n  blind_m: 1.5\nmap:\n  map_voxel_m: 0.1\npreprocess:\n"
                 "  point_filter: 2\n")
    with pytest.raises(ConfigError, match=r"'preprocess' is given twice in one mapping \(line "
                                          r"5\); YAML keeps only the last"):
        load_config(config_file=f)
    f.write_text("preprocess:\n  blind_m: 1.5\n  blind_m: 0.7\n")
    with pytest.raises(ConfigError, match=r"'blind_m' is given twice .* \(line 3\)"):
        load_config(config_file=f)
    f.write_text("filter: &f\n  gate_sigmas: 4.0\nadaptive:\n  general: &g\n    voxel_size_m: 0.3\n"
                 "  degenerate:\n    <<: *g\n    search_radius_m: 1.5\n")
    cfg = load_config(config_file=f)
    assert cfg.adaptive.degenerate.voxel_size_m == 0.3 and cfg.filter.gate_sigmas == 4.0


def test_overrides_in_both_styles_and_matrices_as_text():
    """Dotted and nested overrides apply in order, none dropping another (a nested section
    after a dotted key of it replaced that key's value); a matrix may come as text, as
    `--set sensor.T_imu_lidar=[[...]]` gives it."""
    cfg = load_config(overrides={"adaptive.general.voxel_size_m": 0.3,
                                 "adaptive": {"mode": "fixed"}})
    assert cfg.adaptive.general.voxel_size_m == 0.3 and cfg.adaptive.mode == "fixed"
    cfg = load_config(overrides={"sensor.T_imu_lidar":
                                 "[[1,0,0,0.1],[0,1,0,0],[0,0,1,0],[0,0,0,1]]"})
    assert cfg.T_imu_lidar()[0, 3] == 0.1
    with pytest.raises(ConfigError, match="sensor.T_imu_lidar' expects a list"):
        load_config(overrides={"sensor.T_imu_lidar": "[[1,0"})
    with pytest.raises(ConfigError, match="overrides must be a mapping"):
        load_config(overrides=[("adaptive.mode", "fixed")])
