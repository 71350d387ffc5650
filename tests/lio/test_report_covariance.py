"""The reported sigmas discount what the normals' noise fakes (filter.sigmas_discount_normal_noise)."""

from __future__ import annotations

import numpy as np

from adalio.config import load_config
from adalio.eval.files import read_scans_csv
from adalio.eval.metrics import sigma_consistency
from adalio.io.writers import read_tum
from adalio.lio.odometry import real_information
from adalio.pipeline import run_bag
from adalio.sim import cached_sequence

SIGMAS = ("sigma_x_m", "sigma_y_m", "sigma_z_m", "sigma_roll_deg", "sigma_pitch_deg",
          "sigma_yaw_deg")


def test_real_information_stays_between_nothing_and_the_claim():
    """Random claims and fakes: the result is PSD, never above the claim (no direction gains
    information), equals the claim without a fake, and is zero where the fake covers it."""
    rng = np.random.default_rng(5)
    for _ in range(300):
        X = rng.normal(size=(6, 4))
        A = X @ X.T  # rank 4: two directions hold nothing
        Y = rng.normal(size=(6, 3))
        B = Y @ Y.T * rng.uniform(0.0, 3.0)
        J = real_information(A, B)
        assert np.linalg.eigvalsh(J).min() > -1e-9
        assert np.linalg.eigvalsh(A - J).min() > -1e-9
        null = np.linalg.svd(X.T)[2][4:]  # directions A holds nothing along
        np.testing.assert_allclose(null @ J @ null.T, 0.0, atol=1e-9)
        np.testing.assert_allclose(real_information(A, np.zeros((6, 6))), A, atol=1e-9)
        np.testing.assert_allclose(real_information(A, 2.0 * A), 0.0, atol=1e-9)


def test_spiral_sigmas_grow_where_the_walls_fake_height_and_the_trajectory_stays(tmp_path):
    """25 s of the simulated spiral (the shaft from 13 s): with and without the discount the
    trajectory is bit-identical, every reported sigma is at least the filter's own, and the
    errors against ground truth fall within 3σ in height more often and the mean NEES is lower,
    both for the filter's covariance alone (where it comes closer to 3) and with the map's
    added. The filter runs without its own errors in variables (on by default), which takes
    the same discount into the update: the report's discount is for a filter that follows
    those rows (``filter.errors_in_variables: false``)."""
    sim = cached_sequence("spiral", seed=0, duration_s=25.0, columns=512)
    for with_map in (False, True):
        runs = {}
        for on in (False, True):
            cfg = load_config(None, sim.config_path)
            cfg.filter.sigmas_discount_normal_noise = on
            cfg.filter.errors_in_variables = False
            cfg.filter.map_uncertainty = with_map
            out = tmp_path / f"map_{with_map}_discount_{on}"
            run_bag(sim.bag_path, cfg, out, progress=False)
            scans = read_scans_csv(out / "scans.csv")
            runs[on] = (read_tum(out / "trajectory.tum"), scans,
                        sigma_consistency(out / "trajectory.tum", sim.gt_path, scans))
        (t_off, T_off), scans_off, cons_off = runs[False]
        (t_on, T_on), scans_on, cons_on = runs[True]
        np.testing.assert_array_equal(t_on, t_off)
        np.testing.assert_array_equal(T_on, T_off)
        s_off = np.column_stack([scans_off[c] for c in SIGMAS])
        s_on = np.column_stack([scans_on[c] for c in SIGMAS])
        assert np.all(s_on >= s_off * (1 - 1e-3) - 1e-9)
        assert cons_on.within_3sigma[2] > cons_off.within_3sigma[2], (cons_on, cons_off)
        assert cons_on.mean_nees < cons_off.mean_nees
        if not with_map:  # 29 -> 8.7 (3 is honest); with the map's added 2.9 -> 1.1
            assert abs(np.log(cons_on.mean_nees / 3)) < abs(np.log(cons_off.mean_nees / 3))
        assert s_on[-1, 2] > 2.0 * s_off[-1, 2]  # height, at the end, in the shaft
