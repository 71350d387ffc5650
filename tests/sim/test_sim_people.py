"""People walking through a simulated scene (``simulate(people=N)``), against independent
truth: Embree ray casting on a cylinder mesh, finite differences of the walk, and the same
sweep without them."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from adalio.errors import InputError
from adalio.sim import simulate
from adalio.sim.generate import START_NS, T_IMU_LIDAR_HILTI, build_trajectory
from adalio.sim.lidar import (
    PERSON_FACE,
    Occluder,
    RayCaster,
    SweepSimulator,
    lidar_model,
)
from adalio.sim.people import MAX_OFFSET_M, People, check_people
from adalio.sim.scenes import RIG_HEIGHT_M, build_scene


def _one_person(foot: np.ndarray) -> People:
    route = np.array([foot - [5.0, 0.0, 0.0], foot + [5.0, 0.0, 0.0]])
    return People(route, np.array([5.0]), np.array([0.0]), np.array([0.0]))


def test_a_person_is_where_embree_finds_the_same_cylinder():
    """Rays from around and above a standing person hit it where Embree hits a
    256-sided capped cylinder mesh of the same size (to its facets' 0.03 mm), miss it where
    Embree misses, and a ray from inside the person sees through."""
    foot = np.array([1.0, -2.0, 0.3])
    person = _one_person(foot)
    mesh = trimesh.creation.cylinder(radius=person.radius_m, height=person.height_m,
                                     sections=256)
    mesh.apply_translation(foot + [0.0, 0.0, person.height_m / 2])
    rng = np.random.default_rng(0)
    n = 4000
    origins = foot + rng.uniform([-3.0, -3.0, 0.05], [3.0, 3.0, 3.5], (n, 3))  # above its feet
    keep = np.hypot(*(origins - foot)[:, :2].T) > person.radius_m + 0.01
    origins = origins[keep]
    target = foot + rng.uniform([-0.4, -0.4, -0.2], [0.4, 0.4, 2.0], (len(origins), 3))
    dirs = target - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    feet = np.repeat(person.positions(np.zeros(1)), len(origins), axis=0)
    np.testing.assert_allclose(feet[0, 0], foot, atol=1e-12)
    d_person, cos_inc = person.cast(origins, dirs, feet)
    d_mesh, face = RayCaster(mesh).cast(origins, dirs)
    hit = np.isfinite(d_mesh)
    assert 0.3 < hit.mean() < 0.9  # both kinds of ray are tested
    assert np.array_equal(np.isfinite(d_person), hit)
    np.testing.assert_allclose(d_person[hit], d_mesh[hit], atol=1e-3)
    normals = np.asarray(mesh.face_normals)[face[hit]]
    np.testing.assert_allclose(cos_inc[hit], np.abs((normals * dirs[hit]).sum(-1)), atol=0.03)
    from_above = hit & (origins[:, 2] > foot[2] + person.height_m) & (np.abs(dirs[:, 2]) > 0.9)
    assert from_above.any()  # the head is hit from above
    inside = np.array([foot + [0.05, 0.0, 1.0]])
    d_in, _ = person.cast(inside, np.array([[1.0, 0.0, 0.0]]), feet[:1])
    assert np.isinf(d_in[0])


def test_people_walk_the_route_at_their_speed_and_turn_at_its_ends():
    """Each person keeps to the floor of the route (within ``MAX_OFFSET_M`` sideways), walks at
    the speed drawn for them (finite differences), turns back at the route's ends, and the draw
    is the seed's."""
    scn = build_scene("corridor", 1)
    people = People.along_route(scn.waypoints_m, 5, 1)
    assert people.count == 5
    again = People.along_route(scn.waypoints_m, 5, 1)
    assert np.array_equal(people.start_m, again.start_m)
    assert not np.array_equal(people.start_m, People.along_route(scn.waypoints_m, 5, 2).start_m)
    t = np.arange(0.0, 120.0, 0.05)
    p = people.positions(t)
    floor = scn.waypoints_m[0, 2] - RIG_HEIGHT_M
    np.testing.assert_allclose(p[..., 2], floor, atol=1e-12)
    route = scn.waypoints_m[:, :2]
    seg_a, seg_b = route[:-1], route[1:]
    q = p[..., :2].reshape(-1, 2)[:, None]
    ab = seg_b - seg_a
    u = np.clip(((q - seg_a) * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    dist = np.linalg.norm(q - (seg_a + u[..., None] * ab), axis=-1).min(axis=1)
    assert dist.max() <= MAX_OFFSET_M + 1e-9
    speed = np.linalg.norm(np.diff(p, axis=0), axis=-1) / 0.05
    for j in range(people.count):
        straight = np.median(speed[:, j])
        assert abs(straight - abs(people.velocity_m_s[j])) < 0.01
    length = np.linalg.norm(np.diff(scn.waypoints_m, axis=0), axis=1).sum()
    assert 120.0 * np.abs(people.velocity_m_s).min() > length  # each reaches an end ...
    ends = np.array([scn.waypoints_m[0, :2], scn.waypoints_m[-1, :2]])
    to_end = np.linalg.norm(p[:, :, None, :2] - ends, axis=-1).min(axis=-1)  # (T, N)
    assert np.all(to_end.min(axis=0) < MAX_OFFSET_M + 0.1)
    turned = np.argmin(to_end, axis=0)
    for j, k in enumerate(turned):  # ... and walks back from it
        assert to_end[min(k + 40, len(t) - 1), j] > 1.0


def test_a_sweep_with_people_differs_only_where_a_person_is_nearer():
    """The same sweep with and without people: bit for bit the same returns except those on a
    person, which lie on that person's cylinder where they stood at the column's firing time
    (within the range noise)."""
    scn = build_scene("corridor", 0)
    T = np.asarray(T_IMU_LIDAR_HILTI)
    traj = build_trajectory(scn, T, 0)
    caster = RayCaster(scn.mesh, 0)
    model = lidar_model("xt32", 512)
    people = People.along_route(scn.waypoints_m, 8, 0)
    with_p = SweepSimulator(caster, traj, model, T, START_NS, Occluder(), people)
    without = SweepSimulator(caster, traj, model, T, START_NS, Occluder())
    on_people = 0
    for t_s in np.arange(2.0, 60.0, 4.0):
        t_ns = START_NS + round(t_s * 1e9)
        a = with_p.sweep(t_ns, np.random.default_rng(1))
        b = without.sweep(t_ns, np.random.default_rng(1))
        person = a.valid & (a.face == PERSON_FACE)
        same = ~person & (a.face == b.face)
        assert np.array_equal(a.xyz_lidar_m[same], b.xyz_lidar_m[same])
        behind = person & b.valid  # a person only ever shortens a ray (same noise draws)
        assert np.all(a.range_m[behind] < b.range_m[behind])
        if not person.any():
            continue
        on_people += int(person.sum())
        col_t = (a.t_ns[person] - START_NS) * 1e-9
        s = traj.sample(col_t)
        R_wl = s.R_world_imu @ T[:3, :3]
        p_wl = s.p_world_imu_m + s.R_world_imu @ T[:3, 3]
        xyz_w = np.einsum("nij,nj->ni", R_wl, a.xyz_lidar_m[person].astype(np.float64)) + p_wl
        feet = people.positions(col_t)
        radial = np.abs(np.hypot(*(xyz_w[:, None, :2] - feet[..., :2]).transpose(2, 0, 1))
                        - people.radius_m)
        j = radial.argmin(axis=1)
        height = xyz_w[:, 2] - feet[np.arange(len(j)), j, 2]
        near = radial.min(axis=1) < 4 * model.range_noise_m
        top = np.abs(height - people.height_m) < 4 * model.range_noise_m
        assert np.mean(near | top) > 0.99
        assert np.all((height > -0.1) & (height < people.height_m + 0.1))
    assert on_people > 500


def test_simulate_records_the_people_and_refuses_too_many(tmp_path):
    res = simulate("corridor", tmp_path / "a", duration_s=1.0, columns=64, seed=2, people=3)
    meta = json.loads(res.meta_path.read_text())
    assert meta["people"]["count"] == 3
    assert len(meta["people"]["velocity_along_route_m_s"]) == 3
    none = json.loads(simulate("corridor", tmp_path / "b", duration_s=1.0, columns=64,
                               seed=2).meta_path.read_text())
    assert none["people"]["count"] == 0
    with pytest.raises(InputError, match="--people must be"):
        check_people(21)
    with pytest.raises(InputError, match="--people must be"):
        check_people(-1)
