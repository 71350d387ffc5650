"""LiDAR models, spinning multi-beam and non-repetitive (Livox), ray-cast through Embree with
per-firing motion.

Frames: ``lidar`` = sensor frame (x forward at azimuth 0, z up along the spin axis; a
forward-looking model's view centred on x); rays start at the LiDAR origin. The simulator's rigs
hold the LiDAR level on the handle (:mod:`adalio.sim.trajectory`: ``R_rig_lidar = I`` whatever
``T_imu_lidar`` does to the IMU, unless pitched by ``lidar_tilt_deg``), so x points along the walk
and z up. Every column of a spinning head's sweep is fired at its own time ``t_start + c * T / C``
from the sensor pose at that time (real motion distortion); every point of a non-repetitive frame
(:func:`non_repetitive_directions`, :func:`rosette_directions`) at its own time
``t_start + i * T / N``. The returned points are expressed in the LiDAR frame at their firing
time, exactly like a driver without deskewing. Ranges in metres, times in int64 ns. Ring 0 is the
top beam (a non-repetitive model's ring: the laser). Ray casting: Embree via
``trimesh.ray.ray_pyembree.RayMeshIntersector`` (embreex), one call per sweep.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from adalio.errors import InputError
from adalio.sim.people import People
from adalio.sim.trajectory import Trajectory

PERSON_FACE = -2
"""``SweepPoints.face`` of a return from a walking person (no face of the scene's mesh)."""
PERSON_ALBEDO = 0.35
STRAY_OFFSET_M = (0.3, 2.0)
"""How far along its ray a stray return lies from its surface (metres, drawn uniformly): a
ghost behind it (multipath off glass or metal, cross-talk), dust in front of it."""


@dataclass(frozen=True)
class LidarModel:
    """Geometry and noise of a spinning or a non-repetitive (``lasers`` set) LiDAR."""

    name: str
    elevations_deg: tuple[float, ...]
    """Beam elevations, ring 0 first (top); a non-repetitive model: the band its lasers sweep,
    (top, bottom) (a rosette: its vertical field of view)."""
    columns: int
    """Columns a sweep (each fires every beam at once); a non-repetitive model: firing cycles a
    frame (each fires its ``lasers`` one after another)."""
    rate_hz: float = 10.0
    azimuth0_deg: float = 90.0
    """Azimuth of column 0 (of the sequence's first firing); the head turns clockwise seen from
    above (azimuth decreasing). A forward-looking (rosette) model: the centre of its view."""
    min_range_m: float = 0.05
    max_range_m: float = 120.0
    range_noise_m: float = 0.015
    dropout_prob: float = 0.01
    lidar_topic: str = "/hesai/pandar"
    imu_topic: str = "/alphasense/imu"
    lidar_frame: str = "pandar"
    imu_frame: str = "imu"
    driver: str = "hesai"
    """Whose driver's cloud layout and config the sequence gets: ``hesai`` (unorganized, absolute
    ``timestamp`` in s), ``ouster`` (organized rings x columns, relative ``t`` in ns),
    ``velodyne`` (unorganized, relative ``time`` in s) or ``livox`` (Livox ``CustomMsg``: points
    in firing order, ``offset_time`` in ns after the frame's ``timebase``)."""
    lasers: int | None = None
    """A non-repetitive scanner (:func:`non_repetitive_directions`) with that many lasers; None:
    a spinning head with one beam per entry of ``elevations_deg``."""
    imu_accel_unit: str = "m_s2"
    """The unit of the accelerometer its IMU topic carries: ``m_s2``, or ``g`` (Livox's drivers;
    written as m/s^2 divided by the standard gravity 9.80665)."""
    pattern: str = "zigzag"
    """A non-repetitive model's scan pattern: ``zigzag`` (all around, the Mid-360's:
    :func:`non_repetitive_directions`) or ``rosette`` (forward-looking, the Avia's:
    :func:`rosette_directions`); a spinning head has none."""
    azimuth_fov_deg: float = 360.0
    """Horizontal field of view (degrees), centred on ``azimuth0_deg``: a rosette's; 360 for
    the others, which see all around."""
    preset: str = "hilti2022"
    """The adalio preset its sequences' ``config.yaml`` names (``adalio/presets/<preset>.yaml``)."""
    builtin_imu: bool = False
    """The IMU is the LiDAR's own (a Livox's): ``simulate`` mounts it where the preset's
    ``T_imu_lidar`` says unless told another mounting; False: the HILTI rig's separate IMU
    (:func:`adalio.sim.generate.default_mounting`)."""

    @property
    def channels(self) -> int:
        """Beams (rings) of a spinning head; lasers of a non-repetitive one."""
        return len(self.elevations_deg) if self.lasers is None else self.lasers

    @property
    def non_repetitive(self) -> bool:
        return self.lasers is not None

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.rate_hz)


XT32 = LidarModel(name="xt32", elevations_deg=tuple(15.0 - np.arange(32.0)), columns=2000)
"""Hesai PandarXT-32 as in HILTI 2022: 32 beams +15..-16 deg, 10 Hz, 2000 columns."""

OUSTER64 = LidarModel(name="ouster64", elevations_deg=tuple(np.linspace(22.5, -22.5, 64)),
                      columns=1024, azimuth0_deg=180.0, max_range_m=100.0,
                      range_noise_m=0.012, lidar_topic="/ouster/points", imu_topic="/ouster/imu",
                      lidar_frame="os_lidar", imu_frame="os_imu", driver="ouster",
                      preset="ouster")
"""Ouster OS0/OS1-64-like: 64 beams +-22.5 deg, 1024 columns, 10 Hz."""

OUSTER128 = replace(OUSTER64, name="ouster128", elevations_deg=tuple(np.linspace(45.0, -45.0, 128)),
                    max_range_m=50.0, range_noise_m=0.015)
"""Ouster OS0-128-like: the wide field of view, 128 beams +-45 deg (0.7 deg apart), 1024
columns, 10 Hz, 50 m range, 1.5 cm range noise; the OS1-64's driver layout and topics."""

VLP16 = LidarModel(name="vlp16", elevations_deg=tuple(np.linspace(15.0, -15.0, 16)),
                   columns=1800, azimuth0_deg=0.0, max_range_m=100.0, range_noise_m=0.02,
                   lidar_topic="/velodyne_points", imu_topic="/imu/data",
                   lidar_frame="velodyne", imu_frame="imu_link", driver="velodyne",
                   preset="velodyne")
"""Velodyne VLP-16 (Puck): 16 beams +-15 deg every 2 deg, 1800 columns (0.2 deg) at 10 Hz, range
accuracy +-3 cm (2σ). A handheld rig adds its own IMU (here the same BMI085 model)."""

MID360 = LidarModel(name="mid360", elevations_deg=(52.0, -7.0), columns=5000, lasers=4,
                    azimuth0_deg=0.0, min_range_m=0.1, max_range_m=40.0, range_noise_m=0.02,
                    lidar_topic="/livox/lidar", imu_topic="/livox/imu", lidar_frame="livox_frame",
                    imu_frame="livox_frame", driver="livox", imu_accel_unit="g",
                    preset="livox_mid360", builtin_imu=True)
"""Livox Mid-360-like: 360 deg x -7..+52 deg, 4 lasers, 200 000 points/s in 10 Hz frames of
20 000 (5000 firing cycles of the 4 lasers), non-repetitive (:func:`non_repetitive_directions`),
0.1-40 m, 2 cm range noise; ``CustomMsg`` on ``/livox/lidar`` and its built-in IMU's topic
``/livox/imu`` (accelerometer in g), both in ``livox_frame``. The IMU samples as the simulator's
other rigs' (``simulate``'s rate and noise, the BMI085's by default)."""

AVIA = replace(MID360, name="avia", elevations_deg=(38.6, -38.6), columns=4000, lasers=6,
               pattern="rosette", azimuth_fov_deg=70.4, min_range_m=1.0, max_range_m=100.0,
               preset="livox_avia")
"""Livox Avia-like: forward-looking, 70.4 deg (horizontal) x 77.2 deg (vertical) centred on the
LiDAR's x axis, which the simulator's rigs hold level along the walk (so no azimuth or elevation
offset is needed); 6 lasers, 240 000 points/s in 10 Hz frames of 24 000 (4000 firing cycles of
the 6 lasers), a non-repetitive rosette (:func:`rosette_directions`), 1-100 m (its 1 m blind
zone), 2 cm range noise; ``CustomMsg`` on ``/livox/lidar`` and its built-in IMU on
``/livox/imu`` (accelerometer in g, as livox_ros_driver publishes it), both in ``livox_frame``;
``config.yaml`` takes the ``livox_avia`` preset."""

LIDAR_MODELS = {"xt32": XT32, "ouster64": OUSTER64, "ouster128": OUSTER128, "vlp16": VLP16,
                "mid360": MID360, "avia": AVIA}


MIN_LIDAR_RATE_HZ = 2.0
MAX_LIDAR_RATE_HZ = 50.0
"""The sweep rates ``lidar_model`` accepts (spinning LiDARs turn at 5-20 Hz)."""


def lidar_model(name: str, columns: int | None = None,
                rate_hz: float | None = None) -> LidarModel:
    """The named model, optionally with another number of columns per sweep or another sweep
    rate (Hz; the columns per sweep stay as given: a real head that turns twice as fast at the
    same firing rate has half the columns, ``columns`` says which)."""
    if name not in LIDAR_MODELS:
        raise InputError(f"unknown lidar model '{name}': choose one of {', '.join(LIDAR_MODELS)}")
    model = LIDAR_MODELS[name]
    if columns is not None:
        if int(columns) < 8:
            raise InputError(f"--columns must be >= 8 (got {columns})")
        model = replace(model, columns=int(columns))
    if rate_hz is not None:
        if not MIN_LIDAR_RATE_HZ <= float(rate_hz) <= MAX_LIDAR_RATE_HZ:
            raise InputError(f"--lidar-rate must be {MIN_LIDAR_RATE_HZ:g}-{MAX_LIDAR_RATE_HZ:g} "
                             f"Hz (got {rate_hz})")
        model = replace(model, rate_hz=float(rate_hz))
    return model


@dataclass
class Occluder:
    """Operator body as an axis-aligned box in the rig (handle) frame, around the LiDAR's origin
    (metres): in the LiDAR frame when the LiDAR sits level on the handle."""

    lo: tuple[float, float, float] = (-0.42, -0.25, -0.9)
    hi: tuple[float, float, float] = (-0.22, 0.25, 0.25)


@dataclass
class SweepPoints:
    """One simulated sweep, column-major (C, K) arrays flattened; ``valid`` marks returns."""

    xyz_lidar_m: np.ndarray
    """(C*K, 3) float32, zero where invalid."""
    range_m: np.ndarray
    t_ns: np.ndarray
    """(C*K,) int64 absolute firing time."""
    ring: np.ndarray
    column: np.ndarray
    intensity: np.ndarray
    valid: np.ndarray
    face: np.ndarray
    """Mesh face hit (-1 for misses and occluder returns, ``PERSON_FACE`` for a person)."""


class RayCaster:
    """Embree ray caster over a scene mesh (first hit)."""

    def __init__(self, mesh: trimesh.Trimesh, seed: int = 0) -> None:
        self.mesh = mesh
        self._intersector = RayMeshIntersector(mesh, scale_to_box=False)
        self._embree = self._intersector._scene
        self.face_normals = np.asarray(mesh.face_normals, dtype=np.float64)
        self.albedo = np.random.default_rng([seed, 11]).uniform(0.15, 0.9, len(mesh.faces))

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance along unit ``directions`` to the first hit (inf if none) and the face."""
        out = self._embree.run(np.ascontiguousarray(origins, dtype=np.float32),
                               np.ascontiguousarray(directions, dtype=np.float32), output=1)
        face = np.asarray(out["primID"], dtype=np.int64)
        dist = np.where(face >= 0, np.asarray(out["tfar"], dtype=np.float64), np.inf)
        return dist, face


GOLDEN_FRACTION = (np.sqrt(5.0) - 1.0) / 2.0
"""1/φ = 0.618...: the most irrational step, by which a non-repetitive pattern moves on each frame."""


def zigzag_cycles_per_frame(model: LidarModel) -> float:
    """Up-and-down cycles each laser of a non-repetitive model sweeps its band in a frame: the
    whole number ``n`` (at least 1) that puts the points along a laser's trace about as far
    apart in elevation as the traces lie apart in azimuth (``2 B n / C = 180 / (n K)`` degrees,
    ``B`` the band, ``C`` the firing cycles a frame, ``K`` the lasers: 43 and about 1 deg for the
    Mid-360), plus :data:`GOLDEN_FRACTION`, so that each frame's zigzag starts 0.618 of a cycle
    further on than the last's."""
    band_deg = abs(model.elevations_deg[0] - model.elevations_deg[-1])
    n = math.floor(math.sqrt(90.0 * model.columns / (band_deg * model.channels)))
    return max(n, 1) + GOLDEN_FRACTION


def non_repetitive_directions(model: LidarModel, first_index: int) -> np.ndarray:
    """(N, 3) unit ray directions in the LiDAR frame of one frame's ``N = columns * lasers``
    firings, the first being the sequence's ``first_index``-th (0 at the sequence's start).

    A deterministic low-discrepancy pattern (not Livox's own): the lasers fire one after another
    (laser ``l = n mod K`` of firing ``n``) while the azimuth turns clockwise at a constant rate,
    ``az(n) = az0 - 2π (n / N) (1 + 0.618 / N)``: one revolution a frame plus 0.618 of a firing
    step, so that no azimuth recurs. Each laser zigzags over the elevation band at a constant
    rate (a triangle wave, uniform in elevation), ``el(n) = bottom + B tri(frac(f n / N + l /
    K))``, ``tri(p) = 1 - |2p - 1|``, ``f`` = :func:`zigzag_cycles_per_frame` (whole cycles plus
    0.618), the lasers a quarter cycle (``1 / K``) apart. A frame thus draws ``2 f K`` steep
    traces around the horizon, about evenly spaced; the next frame's traces lie 0.618 of a trace
    spacing on from this frame's (the golden-ratio rotation, Weyl's equidistribution): frames
    never repeat and their union fills the field of view in ever finer, even steps, as a Livox
    scanner's does."""
    N = model.columns * model.channels
    K = model.channels
    n = int(first_index) + np.arange(N, dtype=np.int64)
    frames = n / N
    az = np.radians(model.azimuth0_deg) - 2.0 * np.pi * frames * (1.0 + GOLDEN_FRACTION / N)
    phase = np.mod(frames * zigzag_cycles_per_frame(model) + (n % K) / K, 1.0)
    top, bottom = np.radians(model.elevations_deg[0]), np.radians(model.elevations_deg[-1])
    el = bottom + (top - bottom) * (1.0 - np.abs(2.0 * phase - 1.0))
    ce = np.cos(el)
    return np.column_stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)])


ROSETTE_HZ = (10.0 * (7.0 + GOLDEN_FRACTION), 10.0 * (3.0 + math.sqrt(2.0)))
"""Turns a second of a rosette's two counter-rotating deflections (Hz): 76.18 and 44.14, 7.618
and 4.414 a 10 Hz frame, whose fractions 0.618 and 0.414 (1/φ, √2 - 1) are a Kronecker step."""
ROSETTE_LASER_SPACING_DEG = 0.15
"""Elevation between neighbouring lasers of a rosette model (degrees), the lasers in a vertical
row."""


def rosette_directions(model: LidarModel, first_index: int) -> np.ndarray:
    """(N, 3) unit ray directions in the LiDAR frame of a forward-looking rosette's frame of
    ``N = columns * lasers`` firings, the first being the sequence's ``first_index``-th (0 at
    the sequence's start); firing ``n`` at ``t = n / (N rate)`` seconds, by laser ``n mod K``.

    A deterministic pattern like a Risley-prism scanner's (not Livox's own): two deflections
    turning opposite ways, ``z(t) = (exp(i 2π f1 t) + exp(-i 2π f2 t)) / 2`` (:data:`ROSETTE_HZ`),
    trace a rose inside the unit disc: a petal from the centre out to the rim and back each time
    ``f1 t + f2 t`` grows by one (12 petals a 10 Hz frame, ~48 deg apart), turning ``(f1 - f2)
    / 2`` times a second. ``f1 / f2`` is irrational, so the trace never closes; ``f1 T``, ``f2
    T`` and 1 are rationally independent (``T`` = 0.1 s), so each frame starts at a new point of
    the torus of the two deflections' phases (Weyl): frames never repeat and their union keeps
    filling the view (at 0.5 deg: about 20 % in one frame, 94 % in ten, nearly all in twenty). The
    radius ``|cos(π (f1 + f2) t)|`` is uniform in phase, so the returns are densest at the
    centre (and thicken again at the rim, where the trace turns). Laser ``l`` sits
    ``(l - (K - 1) / 2)`` :data:`ROSETTE_LASER_SPACING_DEG` above the disc's centre (6 parallel
    traces); azimuth ``az = az0 + (H / 2) Re z`` and elevation ``el = el_l + (V / 2 - |el_l|max)
    Im z`` (``H`` = ``azimuth_fov_deg``, ``V`` the band of ``elevations_deg``, ``az0`` =
    ``azimuth0_deg``, the band's middle the disc's centre), so every ray lies inside the H x V
    box and the rim reaches its four edges. Direction ``(cos el cos az, cos el sin az, sin
    el)``."""
    K = model.channels
    N = model.columns * K
    n = int(first_index) + np.arange(N, dtype=np.int64)
    firings_hz = N * model.rate_hz
    th1 = 2.0 * np.pi * np.mod(n * (ROSETTE_HZ[0] / firings_hz), 1.0)
    th2 = 2.0 * np.pi * np.mod(n * (ROSETTE_HZ[1] / firings_hz), 1.0)
    top, bottom = model.elevations_deg[0], model.elevations_deg[-1]
    laser_el = (np.arange(K) - (K - 1) / 2.0) * ROSETTE_LASER_SPACING_DEG
    half_v = abs(top - bottom) / 2.0 - np.abs(laser_el).max()
    az = np.radians(model.azimuth0_deg + 0.5 * model.azimuth_fov_deg
                    * 0.5 * (np.cos(th1) + np.cos(th2)))
    el = np.radians(0.5 * (top + bottom) + laser_el[n % K] + half_v
                    * 0.5 * (np.sin(th1) - np.sin(th2)))
    ce = np.cos(el)
    return np.column_stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)])


def beam_directions(model: LidarModel) -> np.ndarray:
    """(C, K, 3) unit ray directions in the LiDAR frame, column-major."""
    el = np.radians(np.asarray(model.elevations_deg))
    az = np.radians(model.azimuth0_deg) - 2 * np.pi * np.arange(model.columns) / model.columns
    ce, se = np.cos(el), np.sin(el)
    return np.stack([np.cos(az)[:, None] * ce[None], np.sin(az)[:, None] * ce[None],
                     np.broadcast_to(se[None], (model.columns, len(el)))], axis=-1)


def _occluder_distance(dirs: np.ndarray, occ: Occluder) -> np.ndarray:
    """Ray-box (slab) distance from the LiDAR origin, ``dirs`` and the box in one frame; inf if
    missed."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        t0 = np.asarray(occ.lo) * inv
        t1 = np.asarray(occ.hi) * inv
    tn = np.nanmax(np.minimum(t0, t1), axis=-1)
    tf = np.nanmin(np.maximum(t0, t1), axis=-1)
    hit = (tf >= np.maximum(tn, 0.0)) & (tn > 0)
    return np.where(hit, tn, np.inf)


def dirty_ranges(r: np.ndarray, valid: np.ndarray, ghosts: float, dust: float,
                  rng: np.random.Generator) -> np.ndarray:
    """The ranges ``r`` with stray returns among the ``valid`` ones, each return on its own:
    with probability ``dust`` it comes from dust in front of its surface (the range shortened),
    with probability ``ghosts`` it is a ghost behind it (lengthened), by a distance drawn
    uniformly from :data:`STRAY_OFFSET_M` along its own ray; never both (one uniform draw ``u``
    per beam: ``u < dust`` dust, ``dust <= u < dust + ghosts`` a ghost; ``ghosts + dust <= 1``).
    Two draws for every beam of the sweep, valid or not, so a beam's fate depends on its index
    only. The caller drops the ranges now outside the model's."""
    n = len(r)
    u = rng.random(n)
    offset = rng.uniform(STRAY_OFFSET_M[0], STRAY_OFFSET_M[1], n)
    in_dust = valid & (u < dust)
    ghost = valid & (u >= dust) & (u < dust + ghosts)
    return r + np.where(ghost, offset, 0.0) - np.where(in_dust, offset, 0.0)


class SweepSimulator:
    """Simulates sweeps of one LiDAR model on one scene (directions and occluder precomputed)."""

    def __init__(self, caster: RayCaster, traj: Trajectory, model: LidarModel,
                 T_imu_lidar: np.ndarray, t0_ns: int, occluder: Occluder | None = None,
                 people: People | None = None) -> None:
        """The LiDAR's poses come from ``traj``'s IMU through ``T_imu_lidar``; the operator's
        body (``occluder``, a box in the rig frame) is seen through the LiDAR's attitude on the
        handle, ``traj.R_rig_imu`` ``R_imu_lidar`` (level, or tilted:
        :func:`adalio.sim.trajectory.tilt_rig_lidar`)."""
        self.caster, self.traj, self.model, self.t0_ns = caster, traj, model, int(t0_ns)
        self.people = people if people is not None and people.count else None
        self.R_il = np.asarray(T_imu_lidar, dtype=np.float64)[:3, :3]
        self.t_il = np.asarray(T_imu_lidar, dtype=np.float64)[:3, 3]
        self.R_rig_lidar = traj.R_rig_imu @ self.R_il
        self.occluder = occluder
        if not model.non_repetitive:  # the same directions every sweep
            self.dirs_lidar = beam_directions(model)
            self.dirs_flat = self.dirs_lidar.reshape(-1, 3)
            self.occ_dist = self._occluder_distance(self.dirs_flat)
        K, C = model.channels, model.columns
        self.ring = np.tile(np.arange(K, dtype=np.uint16), C)
        self.column = np.repeat(np.arange(C, dtype=np.uint16), K)

    def _occluder_distance(self, dirs_lidar: np.ndarray) -> np.ndarray:
        """Distance from the LiDAR's origin to the operator's body along unit ``dirs_lidar``
        (LiDAR frame); inf where missed or without a body."""
        if self.occluder is None:
            return np.full(len(dirs_lidar), np.inf)
        return _occluder_distance(dirs_lidar @ self.R_rig_lidar.T, self.occluder)

    def sweep(self, t_start_ns: int, rng: np.random.Generator,
              noise_scale: float = 1.0, ghosts: float = 0.0, dust: float = 0.0,
              stray_rng: np.random.Generator | None = None) -> SweepPoints:
        """Ray-cast the sweep (a non-repetitive model: the frame) starting at ``t_start_ns``
        (absolute; a non-repetitive pattern counts its firings from the simulator's ``t0_ns``).
        ``ghosts`` and ``dust``: the shares of the valid returns made stray
        (:func:`dirty_ranges`, drawn from ``stray_rng``, which only they use)."""
        model = self.model
        C, K = model.columns, model.channels
        n = C * K
        if model.non_repetitive:  # every firing its own time and direction
            fire_t_ns = t_start_ns + (np.arange(n, dtype=np.int64) * model.period_ns) // n
            first = ((int(t_start_ns) - self.t0_ns) * n) // model.period_ns
            dirs_flat = (rosette_directions(model, first) if model.pattern == "rosette"
                         else non_repetitive_directions(model, first))
            dirs_lidar = dirs_flat[:, None]
            occ_dist = self._occluder_distance(dirs_flat)
            per_firing = 1
        else:  # a column's K beams at once
            fire_t_ns = t_start_ns + (np.arange(C, dtype=np.int64) * model.period_ns) // C
            dirs_flat, dirs_lidar, occ_dist = self.dirs_flat, self.dirs_lidar, self.occ_dist
            per_firing = K
        s = self.traj.sample((fire_t_ns - self.t0_ns) * 1e-9)
        R_wl = s.R_world_imu @ self.R_il
        p_wl = s.p_world_imu_m + s.R_world_imu @ self.t_il
        dirs_w = np.matmul(dirs_lidar, R_wl.transpose(0, 2, 1)).reshape(-1, 3)
        origins = np.repeat(p_wl, per_firing, axis=0)
        dist, face = self.caster.cast(origins, dirs_w)
        use_occ = occ_dist < dist
        dist = np.where(use_occ, occ_dist, dist)
        face = np.where(use_occ, -1, face)
        fidx = np.maximum(face, 0)
        cos_inc = np.abs((self.caster.face_normals[fidx] * dirs_w).sum(-1))
        cos_inc = np.where(use_occ, 0.8, cos_inc)
        albedo = np.where(use_occ, 0.3, self.caster.albedo[fidx])
        if self.people is not None:
            feet = np.repeat(self.people.positions((fire_t_ns - self.t0_ns) * 1e-9), per_firing,
                             axis=0)
            d_person, cos_person = self.people.cast(origins, dirs_w, feet)
            on_person = d_person < dist
            dist = np.where(on_person, d_person, dist)
            face = np.where(on_person, PERSON_FACE, face)
            cos_inc = np.where(on_person, cos_person, cos_inc)
            albedo = np.where(on_person, PERSON_ALBEDO, albedo)
        finite = np.isfinite(dist)
        r_true = np.where(finite, dist, 0.0)
        valid = finite & (cos_inc > 0.02)
        if noise_scale > 0:
            p_drop = model.dropout_prob + 0.5 * np.clip(1.0 - cos_inc / 0.1, 0.0, 1.0)
            valid &= rng.random(n) >= noise_scale * p_drop
            r = r_true + (noise_scale * model.range_noise_m) * rng.standard_normal(n)
        else:
            r = r_true
        valid &= (r >= model.min_range_m) & (r <= model.max_range_m)
        if ghosts > 0 or dust > 0:
            if stray_rng is None:
                raise ValueError("ghosts or dust need a stray_rng")
            r = dirty_ranges(r, valid, ghosts, dust, stray_rng)
            valid &= (r >= model.min_range_m) & (r <= model.max_range_m)
        r = np.where(valid, r, 0.0)
        xyz = (dirs_flat * r[:, None]).astype(np.float32)
        inten = albedo * (0.3 + 0.7 * cos_inc) * 255.0 / (1.0 + (r_true / 15.0) ** 2)
        inten = np.where(valid, np.round(np.clip(inten, 0.0, 255.0)), 0.0).astype(np.float32)
        return SweepPoints(xyz_lidar_m=xyz, range_m=r.astype(np.float32),
                           t_ns=np.repeat(fire_t_ns, per_firing), ring=self.ring,
                           column=self.column,
                           intensity=inten, valid=valid, face=np.where(valid, face, -1))
