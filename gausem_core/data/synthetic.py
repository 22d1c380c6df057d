"""A deterministic procedural indoor scene with semantic labels, rendered by exact ray casting (the embedded dataset).

A 7 x 6 x 2.5 m room (world z up, floor at z = 0) furnished with analytic primitives: oriented boxes, spheres and
vertical cylinders, in 12 classes (``SYNTHETIC_CLASSES``). Surfaces carry solid procedural textures (checker,
stripes, value noise) under view-independent Lambertian shading, so colour is consistent across views and has
gradients for photometric tracking. The camera walks a closed, hand-held-like loop around the room looking outward,
so the visible classes change along the way and the last frames revisit the first. Everything (textures, jitter)
derives from ``seed``; frames are rendered on demand. The ``_noisy`` variants pass each render through a
Kinect-v1-like sensor model (:mod:`gausem_core.data.sensor`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gausem_core.config import SensorConfig
from gausem_core.data.classes import SYNTHETIC_CLASSES
from gausem_core.data.frame import Dataset, Frame
from gausem_core.data.sensor import AutoExposure, SensorModel
from gausem_core.geometry import PinholeCamera

ROOM_HALF = np.array([3.5, 3.0, 1.25])  # the room spans [-3.5, 3.5] x [-3, 3] x [0, 2.5]
ROOM_CENTRE = np.array([0.0, 0.0, 1.25])
LIGHT = np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82])
# Optical camera axes (x right, y down, z forward) in world coordinates when looking along +x with z up.
OPTICAL_TO_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
NOISE_PERIOD = 32  # value-noise lattice cells per period along each axis (a power of 2)
NOISY_SUFFIX = "_noisy"  # a sequence name with this suffix is seen through the default sensor model


@dataclass(frozen=True)
class Material:
    """Class, base colour (RGB in [0, 1]) and solid texture: 'checker', 'stripes' or 'noise' with a period in metres."""

    class_name: str
    color: tuple[float, float, float]
    texture: str
    period: float


TEXTURES = ("checker", "stripes", "noise")
# Room faces first, in the order :func:`_room_material` indexes them.
MATERIALS = [
    Material("floor", (0.62, 0.45, 0.30), "checker", 0.5),
    Material("ceiling", (0.88, 0.88, 0.85), "noise", 0.4),
    Material("wall", (0.80, 0.74, 0.62), "stripes", 0.25),  # east (+x)
    Material("wall", (0.60, 0.72, 0.80), "stripes", 0.35),  # west (-x)
    Material("wall", (0.78, 0.78, 0.70), "noise", 0.3),  # north (+y)
    Material("wall", (0.70, 0.80, 0.66), "stripes", 0.2),  # south (-y)
    Material("sofa", (0.55, 0.20, 0.18), "noise", 0.15),
    Material("picture", (0.25, 0.35, 0.70), "checker", 0.12),
    Material("picture", (0.85, 0.60, 0.20), "stripes", 0.08),
    Material("lamp", (0.95, 0.90, 0.60), "noise", 0.1),
    Material("plant", (0.20, 0.55, 0.22), "noise", 0.08),
    Material("table", (0.50, 0.32, 0.18), "stripes", 0.06),
    Material("chair", (0.30, 0.30, 0.35), "checker", 0.1),
    Material("cabinet", (0.85, 0.85, 0.88), "stripes", 0.3),
    Material("door", (0.45, 0.28, 0.15), "noise", 0.2),
    Material("box", (0.75, 0.60, 0.40), "checker", 0.15),
]
_M = {name: i for i, name in reversed(list(enumerate(m.class_name for m in MATERIALS)))}  # first material of a class
PICTURE_2 = _M["picture"] + 1


@dataclass
class _Primitives:
    """Boxes: centre, half extents, yaw (rad); spheres: centre, radius; vertical cylinders: base centre, radius,
    height. Each with a material index."""

    boxes: list
    spheres: list
    cylinders: list


def _layout() -> _Primitives:
    hx, hy = ROOM_HALF[:2]
    boxes, spheres, cylinders = [], [], []

    def box(material, centre, half, yaw_deg=0.0):
        boxes.append((material, centre, half, math.radians(yaw_deg)))

    # East: sofa with arms, a picture above it, a floor lamp and a plant.
    box(_M["sofa"], (hx - 0.45, 0.0, 0.22), (0.45, 1.0, 0.22))
    box(_M["sofa"], (hx - 0.12, 0.0, 0.5), (0.12, 1.0, 0.5))
    for y in (-1.0, 1.0):
        box(_M["sofa"], (hx - 0.45, y, 0.34), (0.45, 0.1, 0.34))
    box(_M["picture"], (hx - 0.02, 0.0, 1.55), (0.02, 0.6, 0.35))
    cylinders += [(_M["lamp"], (hx - 0.4, 1.6, 0.0), 0.15, 0.04), (_M["lamp"], (hx - 0.4, 1.6, 0.0), 0.03, 1.4)]
    spheres.append((_M["lamp"], (hx - 0.4, 1.6, 1.55), 0.2))
    cylinders.append((_M["plant"], (hx - 0.45, -1.8, 0.0), 0.22, 0.45))
    spheres.append((_M["plant"], (hx - 0.45, -1.8, 0.85), 0.38))
    # North: a table with four legs between two chairs, a picture.
    box(_M["table"], (0.0, hy - 0.65, 0.74), (0.8, 0.45, 0.03))
    for sx in (-0.72, 0.72):
        for sy in (-0.38, 0.38):
            cylinders.append((_M["table"], (sx, hy - 0.65 + sy, 0.0), 0.035, 0.71))
    for side in (-1.0, 1.0):
        cx = side * 1.2
        box(_M["chair"], (cx, hy - 0.65, 0.45), (0.22, 0.22, 0.03))
        box(_M["chair"], (cx + side * 0.2, hy - 0.65, 0.78), (0.03, 0.22, 0.3))
        for dx in (-0.19, 0.19):
            for dy in (-0.19, 0.19):
                box(_M["chair"], (cx + dx, hy - 0.65 + dy, 0.21), (0.025, 0.025, 0.21))
    box(PICTURE_2, (-1.9, hy - 0.02, 1.5), (0.45, 0.02, 0.3))
    # West: a tall cabinet, a door, a stack of boxes.
    box(_M["cabinet"], (-hx + 0.28, -0.8, 0.95), (0.28, 0.6, 0.95))
    box(_M["door"], (-hx + 0.03, 1.2, 1.0), (0.03, 0.5, 1.0))
    box(_M["box"], (-hx + 0.7, -2.2, 0.25), (0.25, 0.25, 0.25), 20.0)
    box(_M["box"], (-hx + 0.7, -2.2, 0.65), (0.15, 0.15, 0.15), 55.0)
    # South: a low cabinet with a picture above, a box, a plant.
    box(_M["cabinet"], (0.5, -hy + 0.22, 0.4), (0.9, 0.22, 0.4))
    box(_M["picture"], (0.5, -hy + 0.02, 1.45), (0.5, 0.02, 0.3))
    box(_M["box"], (2.0, -hy + 0.6, 0.2), (0.2, 0.3, 0.2), 30.0)
    cylinders.append((_M["plant"], (-1.5, -hy + 0.4, 0.0), 0.2, 0.4))
    spheres.append((_M["plant"], (-1.5, -hy + 0.4, 0.75), 0.33))
    return _Primitives(boxes, spheres, cylinders)


class Scene:
    """The primitives as arrays, the materials' textures, and exact ray casting."""

    def __init__(self, seed: int = 0):
        rng = np.random.default_rng(seed)
        p = _layout()
        self.box_material = np.array([b[0] for b in p.boxes])
        self.box_centre = np.array([b[1] for b in p.boxes], np.float32)
        self.box_half = np.array([b[2] for b in p.boxes], np.float32)
        yaw = np.array([b[3] for b in p.boxes], np.float32)
        self.box_cos, self.box_sin = np.cos(yaw), np.sin(yaw)
        self.sphere_material = np.array([s[0] for s in p.spheres])
        self.sphere_centre = np.array([s[1] for s in p.spheres], np.float32)
        self.sphere_radius = np.array([s[2] for s in p.spheres], np.float32)
        self.cylinder_material = np.array([c[0] for c in p.cylinders])
        self.cylinder_base = np.array([c[1] for c in p.cylinders], np.float32)
        self.cylinder_radius = np.array([c[2] for c in p.cylinders], np.float32)
        self.cylinder_height = np.array([c[3] for c in p.cylinders], np.float32)
        self.material_class = np.array([SYNTHETIC_CLASSES.id_of(m.class_name) for m in MATERIALS])
        self.material_color = np.array([m.color for m in MATERIALS], np.float32)
        self.material_texture = np.array([TEXTURES.index(m.texture) for m in MATERIALS])
        self.material_period = np.array([m.period for m in MATERIALS], np.float32)
        self.texture_offset = rng.uniform(0, 1, (len(MATERIALS), 3)).astype(np.float32)
        self.noise_lattice = rng.uniform(0, 1, NOISE_PERIOD**3).astype(np.float32)
        # bounding spheres (centres (P, 3), radii (P,)) of boxes, spheres and cylinders, for view culling
        self.bounds = [(self.box_centre, np.linalg.norm(self.box_half, axis=-1)),
                       (self.sphere_centre, self.sphere_radius),
                       (self.cylinder_base + np.stack([0 * self.cylinder_height, 0 * self.cylinder_height,
                                                       self.cylinder_height / 2], -1),
                        np.hypot(self.cylinder_radius, self.cylinder_height / 2))]

    # --- intersections: (R,) or (R, P) ray parameters t (inf where missed); rays are o + t d ------------------------
    def _room_t(self, o, d):
        with np.errstate(divide="ignore"):
            inv = 1.0 / d
        exits = np.maximum((ROOM_CENTRE - ROOM_HALF - o) * inv, (ROOM_CENTRE + ROOM_HALF - o) * inv)
        return np.minimum(np.minimum(exits[:, 0], exits[:, 1]), exits[:, 2])[:, None].astype(np.float32)

    def _box_t(self, o, d, k):
        cos, sin, half = self.box_cos[k], self.box_sin[k], self.box_half[k]
        rel = o - self.box_centre[k]
        origin = [cos * rel[:, 0] + sin * rel[:, 1], -sin * rel[:, 0] + cos * rel[:, 1], rel[:, 2]]  # box frames
        x, y = d[:, 0:1], d[:, 1:2]
        direction = [cos * x + sin * y, -sin * x + cos * y, d[:, 2:3]]
        near = np.full((len(d), len(k)), -np.inf, np.float32)
        far = np.full((len(d), len(k)), np.inf, np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            for axis in range(3):  # slabs; fmin/fmax skip the NaN of rays parallel to a slab face
                inv = 1.0 / direction[axis]
                t1, t2 = (-half[:, axis] - origin[axis]) * inv, (half[:, axis] - origin[axis]) * inv
                near, far = np.fmax(near, np.fmin(t1, t2)), np.fmin(far, np.fmax(t1, t2))
        return np.where((near <= far) & (near > 1e-4), near, np.inf)

    def _sphere_t(self, o, d, k):
        oc = o - self.sphere_centre[k]  # (S, 3)
        a = (d * d).sum(-1, keepdims=True)
        b = d @ oc.T
        c = (oc * oc).sum(-1) - self.sphere_radius[k] ** 2
        disc = b * b - a * c
        t = (-b - np.sqrt(np.maximum(disc, 0))) / a
        return np.where((disc >= 0) & (t > 1e-4), t, np.inf)

    def _cylinder_t(self, o, d, k):
        base, radius, height = self.cylinder_base[k], self.cylinder_radius[k], self.cylinder_height[k]
        oc = o[:2] - base[:, :2]  # (C, 2)
        a = (d[:, :2] ** 2).sum(-1, keepdims=True)
        b = d[:, :2] @ oc.T
        c = (oc * oc).sum(-1) - radius**2
        disc = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            side = (-b - np.sqrt(np.maximum(disc, 0))) / a
            z = o[2] + side * d[:, 2:3] - base[:, 2]
            side = np.where((disc >= 0) & (side > 1e-4) & (z >= 0) & (z <= height), side, np.inf)
            top = base[:, 2] + height
            cap = (top - o[2]) / d[:, 2:3]  # only the top cap is visible from outside, and only from above
        radial = ((oc[None] + cap[..., None] * d[:, None, :2]) ** 2).sum(-1)
        cap = np.where((o[2] > top) & (cap > 1e-4) & (radial <= radius**2), cap, np.inf)
        return np.minimum(side, cap)

    # --- normals and materials of the hit surfaces ------------------------------------------------------------------
    def _room_surface(self, p):
        q = (p - ROOM_CENTRE) / ROOM_HALF
        axis = np.abs(q).argmax(-1)
        positive = np.take_along_axis(q, axis[:, None], -1)[:, 0] > 0
        normal = np.zeros_like(p)
        normal[np.arange(len(p)), axis] = np.where(positive, -1.0, 1.0)
        # floor 0, ceiling 1, east 2, west 3, north 4, south 5
        material = np.choose(axis, [np.where(positive, 2, 3), np.where(positive, 4, 5), np.where(positive, 1, 0)])
        return normal, material

    def _box_surface(self, p, k):
        cos, sin = self.box_cos[k], self.box_sin[k]
        rel = p - self.box_centre[k]
        local = np.stack([cos * rel[:, 0] + sin * rel[:, 1], -sin * rel[:, 0] + cos * rel[:, 1], rel[:, 2]], -1)
        q = local / self.box_half[k]
        axis = np.abs(q).argmax(-1)
        n_local = np.zeros_like(p)
        n_local[np.arange(len(p)), axis] = np.sign(np.take_along_axis(q, axis[:, None], -1)[:, 0])
        normal = np.stack([cos * n_local[:, 0] - sin * n_local[:, 1], sin * n_local[:, 0] + cos * n_local[:, 1],
                           n_local[:, 2]], -1)
        return normal, self.box_material[k]

    def _sphere_surface(self, p, k):
        return (p - self.sphere_centre[k]) / self.sphere_radius[k][:, None], self.sphere_material[k]

    def _cylinder_surface(self, p, k):
        rel = p - self.cylinder_base[k]
        half_h = self.cylinder_height[k] / 2
        radial = np.linalg.norm(rel[:, :2], axis=-1)
        on_cap = np.abs(rel[:, 2] - half_h) / half_h > radial / self.cylinder_radius[k]
        normal = np.concatenate([rel[:, :2] / np.maximum(radial, 1e-9)[:, None], np.zeros_like(radial)[:, None]], -1)
        normal[on_cap] = [0.0, 0.0, 0.0]
        normal[on_cap, 2] = np.sign(rel[on_cap, 2] - half_h[on_cap])
        return normal, self.cylinder_material[k]

    @staticmethod
    def _ray_cone(d):
        """Axis (3,) and half angle of a cone holding every ray direction (R, 3)."""
        unit = d / np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2)[:, None]
        axis = unit.mean(0)
        axis /= np.linalg.norm(axis)
        return axis, np.arccos(np.clip((unit @ axis).min(), -1, 1))

    @staticmethod
    def _in_cone(o, axis, half_angle, centres, radii):
        """Indices of bounding spheres that meet the cone from ``o`` (a conservative view cull)."""
        v = centres - o
        dist = np.linalg.norm(v, axis=-1)
        angle = np.arccos(np.clip(v @ axis / np.maximum(dist, 1e-9), -1, 1))
        margin = np.arcsin(np.clip(radii / np.maximum(dist, 1e-9), 0, 1))
        return np.flatnonzero((dist <= radii) | (angle - margin <= half_angle))

    def cast(self, origin: np.ndarray, dirs: np.ndarray):
        """Nearest hits of rays ``origin + t * dirs`` (dirs (R, 3)) -> t (R,), normals, points (R, 3), material (R,)."""
        o, d = origin.astype(np.float32), dirs.astype(np.float32)
        axis, half_angle = self._ray_cone(d)
        visible = [np.zeros(1, np.int64)] + [self._in_cone(o, axis, half_angle, c, r) for c, r in self.bounds]
        parts = [self._room_t(o, d), self._box_t(o, d, visible[1]), self._sphere_t(o, d, visible[2]),
                 self._cylinder_t(o, d, visible[3])]
        bounds = np.cumsum([0] + [t.shape[1] for t in parts])
        all_t = np.concatenate(parts, -1)
        winner = all_t.argmin(-1)
        t = np.take_along_axis(all_t, winner[:, None], -1)[:, 0]
        points = o + t[:, None] * d
        normals, material = np.zeros_like(points), np.zeros(len(t), np.int64)
        surfaces = [self._room_surface, self._box_surface, self._sphere_surface, self._cylinder_surface]
        for kind, surface in enumerate(surfaces):
            rays = np.flatnonzero((winner >= bounds[kind]) & (winner < bounds[kind + 1]))
            if rays.size:
                args = (points[rays],) if kind == 0 else (points[rays], visible[kind][winner[rays] - bounds[kind]])
                normals[rays], material[rays] = surface(*args)
        return t, normals, points, material

    # --- appearance -------------------------------------------------------------------------------------------------
    def _value_noise(self, p):
        """Smooth lattice value noise in [0, 1] at points (N, 3) given in lattice units."""
        cell = np.floor(p).astype(np.int32)
        f = p - cell
        u = f * f * (3 - 2 * f)
        n, mask = NOISE_PERIOD, NOISE_PERIOD - 1
        index = [[((cell[:, i] + o) & mask) * n ** (2 - i) for o in (0, 1)] for i in range(3)]
        weight = [[1 - u[:, i], u[:, i]] for i in range(3)]
        return sum(weight[0][a] * weight[1][b] * weight[2][c]
                   * self.noise_lattice[index[0][a] + index[1][b] + index[2][c]] for a, b, c in np.ndindex(2, 2, 2))

    def shade(self, points, normals, material):
        """RGB in [0, 1] (N, 3) of surface points: textured base colour under ambient + Lambertian light."""
        period = self.material_period[material][:, None]
        p = points / period + self.texture_offset[material]
        fine = self._value_noise(p * 2.0)
        checker = (np.floor(p).astype(np.int64).sum(-1) & 1).astype(np.float32)
        stripes = 0.5 + 0.5 * np.sin(2 * np.pi * (p[:, 0] + p[:, 1]))
        noise = self._value_noise(p)
        pattern = np.choose(self.material_texture[material], [0.7 * checker + 0.3 * fine,
                                                             0.6 * stripes + 0.4 * fine, 0.6 * noise + 0.4 * fine])
        light = 0.6 + 0.4 * np.clip(normals @ LIGHT, 0, None)
        return self.material_color[material] * ((0.6 + 0.4 * pattern) * light)[:, None]

    def render_linear(self, cam_to_world: np.ndarray, camera: PinholeCamera):
        """Exact ray casting through pixel centres -> rgb (H, W, 3) float in [0, 1], depth (H, W) metres, labels."""
        rays = camera.pixel_rays().numpy().reshape(-1, 3)
        t, normals, points, material = self.cast(cam_to_world[:3, 3], rays @ cam_to_world[:3, :3].T.astype(np.float32))
        shape = (camera.height, camera.width)
        return (self.shade(points, normals, material).reshape(shape + (3,)), t.reshape(shape),
                self.material_class[material].reshape(shape))

    def render(self, cam_to_world: np.ndarray, camera: PinholeCamera):
        """:meth:`render_linear` with rgb as (H, W, 3) uint8 (the clean, noise-free camera)."""
        rgb, depth, labels = self.render_linear(cam_to_world, camera)
        return np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8), depth, labels


@dataclass(frozen=True)
class Sequence:
    """A closed walk: an ellipse (semi-axes ``radii``) around the room centre, looking outward with swings."""

    frames: int
    radii: tuple[float, float]
    height: float
    yaw_swing_deg: float
    pitch_deg: float
    pitch_swing_deg: float


SEQUENCES = {
    "default": Sequence(frames=180, radii=(1.3, 0.9), height=1.4, yaw_swing_deg=10.0, pitch_deg=8.0,
                        pitch_swing_deg=14.0),
    "loop": Sequence(frames=360, radii=(1.7, 1.2), height=1.45, yaw_swing_deg=20.0, pitch_deg=6.0,
                     pitch_swing_deg=15.0),
}


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


class Trajectory:
    """Hand-held-like smooth poses along a :class:`Sequence`: periodic in the frame index, so the walk closes."""

    def __init__(self, sequence: Sequence, seed: int = 0):
        self.sequence = sequence
        rng = np.random.default_rng(seed + 1)
        self.harmonics = np.array([4, 7, 11, 17])
        # jitter amplitudes: 6 mm and 0.4 deg shared over the harmonics; 6 dof x harmonics phases
        self.amplitude = np.concatenate([np.full(3, 0.006), np.full(3, math.radians(0.4))])[:, None] * rng.uniform(
            0.5, 1.0, (6, len(self.harmonics))) / len(self.harmonics) ** 0.5
        self.phase = rng.uniform(0, 2 * np.pi, (6, len(self.harmonics)))

    def pose(self, index: int) -> np.ndarray:
        """cam_to_world (4, 4) float64 of frame ``index``."""
        seq = self.sequence
        s = index / seq.frames
        angle = 2 * np.pi * s
        jitter = (self.amplitude * np.sin(2 * np.pi * self.harmonics * s + self.phase)).sum(-1)
        position = np.array([seq.radii[0] * math.cos(angle), seq.radii[1] * math.sin(angle),
                             seq.height + 0.05 * math.sin(3 * angle)]) + jitter[:3]
        yaw = angle + math.radians(seq.yaw_swing_deg) * math.sin(2 * angle) + jitter[3]
        pitch = math.radians(seq.pitch_deg + seq.pitch_swing_deg * math.sin(2 * angle + 0.5)) + jitter[4]
        roll = math.radians(3.0) * math.sin(3 * angle) + jitter[5]
        pose = np.eye(4)
        pose[:3, :3] = _rot_z(yaw) @ OPTICAL_TO_LEVEL @ _rot_x(-pitch) @ _rot_z(roll)
        pose[:3, 3] = position
        return pose


def default_camera(width: int = 160, height: int = 120, hfov_deg: float = 60.0) -> PinholeCamera:
    """Square pixels, principal point at the image centre, ``hfov_deg`` horizontal field of view."""
    f = width / 2 / math.tan(math.radians(hfov_deg) / 2)
    return PinholeCamera(f, f, width / 2, height / 2, width, height)


class SyntheticDataset(Dataset):
    """The procedural room along a named sequence ("default" 180 frames, "loop" 360 frames), with labels and GT.

    A name ending in ``_noisy`` ("default_noisy", "loop_noisy") sees the room through a Kinect-v1-like sensor
    (:class:`~gausem_core.config.SensorConfig` defaults); ``sensor`` sets one explicitly (labels and ground-truth
    poses stay exact). resolution: (width, height) rendered natively (default 160x120, 60 deg horizontal field of
    view); fps: frame rate for the timestamps and the motion over an exposure. ``size``/``stride``/``max_frames`` as
    for every dataset.
    """

    class_table = SYNTHETIC_CLASSES

    def __init__(self, sequence: str = "default", *, seed: int = 0, resolution: tuple[int, int] = (160, 120),
                 fps: float = 30.0, sensor: SensorConfig | None = None, **options):
        super().__init__(**options)
        base = sequence.removesuffix(NOISY_SUFFIX)
        if base not in SEQUENCES:
            raise ValueError(f"unknown synthetic sequence {sequence!r}; known: {', '.join(sequence_names())}")
        if sequence.endswith(NOISY_SUFFIX):
            if sensor is not None:
                raise ValueError(f"sequence {sequence!r} already names the default sensor; pass {base!r} with sensor")
            sensor = SensorConfig()
        self.name = f"synthetic_{base}" + (NOISY_SUFFIX if sensor is not None else "")
        self.sequence, self.seed, self.fps = base, seed, float(fps)
        self.camera = default_camera(*resolution)
        self.scene = Scene(seed)
        self.trajectory = Trajectory(SEQUENCES[base], seed)
        self.sensor = None if sensor is None else SensorModel(sensor, seed)
        self.exposure = None if sensor is None else AutoExposure(sensor, self._meter)

    def _source_length(self) -> int:
        return SEQUENCES[self.sequence].frames

    def _meter(self, index: int) -> np.ndarray:
        """Mean clean RGB of frame ``index`` rendered at a quarter of the resolution (the exposure's metering)."""
        camera = self.camera.scaled(max(8, self.camera.width // 4), max(6, self.camera.height // 4))
        return self.sensor.meter(self.scene.render_linear(self.trajectory.pose(index), camera)[0], camera)

    def _load(self, index: int) -> Frame:
        pose = self.trajectory.pose(index)
        if self.sensor is None:
            rgb, depth, labels = self.scene.render(pose, self.camera)
            return Frame(index, index / self.fps, rgb, depth, labels, self.camera, pose)
        linear, depth, labels = self.scene.render_linear(pose, self.camera)  # the frame's time is mid-exposure
        offsets = self.sensor.exposure_offsets()
        if len(offsets) > 1:  # motion blur: the mean of renders along the camera's motion over the exposure
            linear = np.mean([self.scene.render_linear(self.trajectory.pose(index + dt * self.fps), self.camera)[0]
                              for dt in offsets], axis=0)
        rgb = self.sensor.color(linear, self.camera, index, *self.exposure.gains(index))
        return Frame(index, index / self.fps, rgb, self.sensor.depth(depth, self.camera, index), labels, self.camera,
                     pose)


def sequence_names() -> list[str]:
    """Every sequence name :class:`SyntheticDataset` takes: the clean walks, then their noisy variants."""
    return list(SEQUENCES) + [name + NOISY_SUFFIX for name in SEQUENCES]
