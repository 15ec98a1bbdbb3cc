"""Procedural scenes: indoor rooms, object clusters on a ground plane, open courtyards.

Everything is drawn from one ``np.random.Generator`` (no global RNG), so a scene is a pure function of
its generator state. World frame: metres, z up, ground at z = 0. A ``Scene`` is plain data (trimesh
meshes in world coordinates, material descriptions, lights, where cameras may go); ``data.render``
turns it into a pyrender scene. Objects are placed without interpenetration by bounding-circle tests
on the ground (vertical cylinders around each object) and by stacking only on flat tops.
"""

from __future__ import annotations

import contextvars
import functools
import math
import numbers
from dataclasses import dataclass, field

import numpy as np
import trimesh

from data.textures import photo_texture, random_color, random_texture

KINDS = ("room", "cluster", "courtyard")
SCENE_VERSIONS = (1, 2, 3)  # the scene versions make_scene draws (data.generate.GENERATOR_VERSION is the last)
# the version make_scene is drawing, for the builders whose geometry changed between versions (their own calls,
# outside make_scene, draw the latest): one seed, one scene, in every version
_DRAWING = contextvars.ContextVar("scene_version", default=SCENE_VERSIONS[-1])
DEFAULT_KIND_WEIGHTS = {"room": 0.4, "cluster": 0.35, "courtyard": 0.25}


@dataclass
class Material:
    """A surface look: base colour (RGBA in [0, 1]) times an optional texture (uint8 [S, S, 3]) that
    repeats every ``uv_scale`` metres; metallic/roughness as in glTF."""
    base_color: np.ndarray
    texture: np.ndarray | None = None
    uv_scale: float = 1.0
    uv_rotation: float = 0.0
    metallic: float = 0.0
    roughness: float = 0.8


@dataclass
class Surface:
    mesh: trimesh.Trimesh          # world coordinates
    material: Material
    smooth: bool = False           # smooth (vertex) normals for curved primitives

    def geometry(self):
        """Per-corner arrays for rendering: positions [3F, 3], normals [3F, 3], uv [3F, 2] float32.

        UVs come from a triplanar-style box projection per face (the face's dominant normal axis
        picks the plane), in metres divided by the material's ``uv_scale``, so textures keep a
        consistent physical size on every primitive.
        """
        m = self.mesh
        faces = np.asarray(m.faces)
        pos = np.asarray(m.vertices, np.float64)[faces]              # [F, 3, 3]
        fn = np.asarray(m.face_normals, np.float64)                  # [F, 3]
        if self.smooth:
            nrm = np.asarray(m.vertex_normals, np.float64)[faces]
        else:
            nrm = np.repeat(fn[:, None, :], 3, axis=1)
        axis = np.abs(fn).argmax(1)
        sign = np.sign(fn[np.arange(len(fn)), axis])
        sign[sign == 0] = 1
        # (u, v) axes per dominant axis: x -> (y, z), y -> (x, z), z -> (x, y); mirrored faces flip u
        ua = np.array([1, 0, 0])[axis]
        va = np.array([2, 2, 1])[axis]
        u = pos[np.arange(len(fn))[:, None], np.arange(3)[None, :], ua[:, None]]
        v = pos[np.arange(len(fn))[:, None], np.arange(3)[None, :], va[:, None]]
        u = u * np.where(axis == 1, -sign, sign)[:, None]
        uv = np.stack([u, v], -1) / self.material.uv_scale
        c, s = np.cos(self.material.uv_rotation), np.sin(self.material.uv_rotation)
        uv = uv @ np.array([[c, -s], [s, c]])
        return (pos.reshape(-1, 3).astype(np.float32), nrm.reshape(-1, 3).astype(np.float32),
                uv.reshape(-1, 2).astype(np.float32))


@dataclass
class Light:
    kind: str                      # "directional" | "point" | "spot"
    color: np.ndarray              # RGB in [0, 1]
    intensity: float               # W/m^2 for directional, candela-ish for point/spot (pyrender units)
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))  # travel direction
    inner_cone: float = 0.0
    outer_cone: float = np.pi / 4


@dataclass
class Scene:
    kind: str
    surfaces: list
    lights: list
    ambient: np.ndarray            # RGB ambient light
    bg_color: np.ndarray           # RGB shown where nothing is hit (depth 0)
    camera_lo: np.ndarray          # cameras must lie inside this axis-aligned box...
    camera_hi: np.ndarray
    obstacles: np.ndarray          # [N, 2, 3] ...and outside these boxes (furniture, objects, buildings)
    targets: np.ndarray            # [M, 3] points worth looking at
    target_radius: np.ndarray      # [M] rough size of what is at each target (m)
    low_texture: bool = False
    extent: float = 10.0           # rough scene diameter (m), used for near/far planes
    version: int = SCENE_VERSIONS[-1]  # the generator version that drew it (data.render renders each version's way)

    def inside_obstacle(self, p: np.ndarray, margin: float = 0.0) -> bool:
        p = np.asarray(p, np.float64)
        if np.any(p < self.camera_lo) or np.any(p > self.camera_hi):
            return True
        if len(self.obstacles) == 0:
            return False
        lo = self.obstacles[:, 0] - margin
        hi = self.obstacles[:, 1] + margin
        return bool(np.any(np.all((p >= lo) & (p <= hi), axis=1)))

    @property
    def n_triangles(self) -> int:
        return int(sum(len(s.mesh.faces) for s in self.surfaces))


# ----------------------------------------------------------------------------------------------------
# materials


def random_material(rng: np.random.Generator, *, low_texture: bool = False, texture_size: int = 256,
                    photos=None, photo_share: float = 0.0) -> Material:
    """One material: textured (most), plain colour (low-texture), glossy or metallic. With ``photos`` (a
    data.textures.PhotoCollection) a share ``photo_share`` of the textures are crops of photographs."""
    plain_p = 0.85 if low_texture else 0.15
    tex = None
    if rng.random() >= plain_p:
        kind = "gradient" if (low_texture and rng.random() < 0.5) else None
        # no random draw when photos are off: scenes without photos stay byte-identical
        if photos is not None and photo_share > 0 and kind is None and rng.random() < photo_share:
            tex = photo_texture(rng, photos, texture_size)
        else:
            tex = random_texture(rng, texture_size, kind=kind)
    color = np.ones(4)
    if tex is None:
        color[:3] = random_color(rng, saturation=(0.0, 0.8), value=(0.25, 0.95))
    elif rng.random() < 0.3:
        color[:3] = np.clip(random_color(rng, saturation=(0.0, 0.3), value=(0.7, 1.0)), 0, 1)
    r = rng.random()
    if r < 0.12:           # metal
        metallic, roughness = rng.uniform(0.6, 1.0), rng.uniform(0.15, 0.5)
    elif r < 0.3:          # glossy dielectric
        metallic, roughness = rng.uniform(0.0, 0.2), rng.uniform(0.1, 0.35)
    else:                  # matte
        metallic, roughness = 0.0, rng.uniform(0.55, 1.0)
    return Material(base_color=color, texture=tex, uv_scale=float(np.exp(rng.uniform(np.log(0.25), np.log(3.0)))),
                    uv_rotation=float(rng.choice([0.0, np.pi / 2]) if rng.random() < 0.8 else rng.uniform(0, np.pi)),
                    metallic=float(metallic), roughness=float(roughness))


# ----------------------------------------------------------------------------------------------------
# object builders: local frame, centred in x/y, resting on z = 0. Each returns (parts, flat_top) where
# parts is a list of (mesh, slot, smooth): slot indexes the object's own small material palette.


_BOX_F = np.asarray(trimesh.creation.box(bounds=[[-0.5, -0.5, 0.0], [0.5, 0.5, 1.0]]).faces)
_BOX_V0 = np.asarray(trimesh.creation.box(bounds=[[-0.5, -0.5, 0.0], [0.5, 0.5, 1.0]]).vertices)


def _box(ex, ey, ez, at=(0, 0, 0)):
    """Axis-aligned box of extents (ex, ey, ez), centred at ``at`` in x/y, bottom at ``at``'s z."""
    return trimesh.Trimesh(_BOX_V0 * [ex, ey, ez] + np.asarray(at, np.float64), _BOX_F.copy(), process=False)


@functools.lru_cache(maxsize=None)
def _unit_mesh(kind: str, sections: int):
    """Vertices/faces of unit primitives, built once and scaled per use (trimesh creation is slow)."""
    if kind == "cylinder":   # radius 1, z in [0, 1]
        m = trimesh.creation.cylinder(radius=1.0, height=1.0, sections=sections)
        m.apply_translation([0, 0, 0.5])
    elif kind == "cone":     # radius 1, base z = 0, apex z = 1
        m = trimesh.creation.cone(radius=1.0, height=1.0, sections=sections)
    elif kind == "sphere":   # radius 1, centred
        m = trimesh.creation.icosphere(subdivisions=sections, radius=1.0)
    else:  # pragma: no cover
        raise ValueError(kind)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    v.flags.writeable = False
    f.flags.writeable = False
    return v, f


def _scaled(kind, sections, sx, sy, sz, at=(0, 0, 0)):
    v, f = _unit_mesh(kind, sections)
    return trimesh.Trimesh(v * [sx, sy, sz] + np.asarray(at, np.float64), f.copy(), process=False)


def _cyl(r, h, at=(0, 0, 0), sections=20):
    return _scaled("cylinder", sections, r, r, h, at)


def _cone(r, h, sections=24):
    return _scaled("cone", sections, r, r, h)


def _sphere(r, subdivisions=2):
    return _scaled("sphere", subdivisions, r, r, r)


def _rest(m):
    """Move a mesh so it is centred in x/y and rests on z = 0."""
    lo, hi = m.bounds
    m.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return m


def _star_prism(rng, radius, height, n=None):
    """Extrusion of a random polygon, star-shaped about its centre (fan-triangulated caps, quad sides), centred in
    x/y and resting on z = 0. Versions 1-2 (``_DRAWING``): random angles that leave a gap of half a turn or more
    put the centre outside the polygon (caps with inverted flaps, the whole prism inside-out when all angles fall
    in one half-turn), and the prism was not centred (a group's parts overlapped); version 3 spaces such angles
    evenly instead, from the same draws, and centres the prism."""
    n = int(rng.integers(3, 11)) if n is None else n
    ang = np.sort(rng.uniform(0, 2 * np.pi, n)) if rng.random() < 0.5 else np.linspace(0, 2 * np.pi, n, endpoint=False)
    rad = radius * (rng.uniform(0.45, 1.0, n) if rng.random() < 0.6 else np.ones(n))
    v3 = _DRAWING.get() >= 3
    if v3 and np.diff(np.r_[ang, ang[0] + 2 * np.pi]).max() >= np.pi * (1 - 1e-9):
        ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1)
    verts = np.concatenate([np.c_[ring, np.zeros(n)], np.c_[ring, np.full(n, height)],
                            [[0, 0, 0], [0, 0, height]]])
    faces = []
    b, t = 2 * n, 2 * n + 1
    for i in range(n):
        j = (i + 1) % n
        faces += [[b, j, i], [t, n + i, n + j], [i, j, n + j], [i, n + j, n + i]]
    m = trimesh.Trimesh(verts, np.array(faces), process=False)
    return _rest(m) if v3 else m


def _primitive(rng, s):
    """One random primitive of size ~s; returns (mesh, smooth, flat_top)."""
    k = rng.choice(["box", "sphere", "cylinder", "cone", "capsule", "torus", "hull", "prism"],
                   p=[0.24, 0.12, 0.14, 0.08, 0.07, 0.07, 0.14, 0.14])
    if k == "box":
        e = s * rng.uniform(0.3, 1.0, 3)
        return _box(*e), False, True
    if k == "sphere":
        m = _sphere(s * rng.uniform(0.25, 0.5))
        return _rest(m), True, False
    if k == "cylinder":
        return _cyl(s * rng.uniform(0.12, 0.45), s * rng.uniform(0.3, 1.2), sections=24), False, True
    if k == "cone":
        m = _cone(s * rng.uniform(0.15, 0.45), s * rng.uniform(0.3, 1.0))
        return _rest(m), False, False
    if k == "capsule":
        r = s * rng.uniform(0.1, 0.25)
        m = trimesh.creation.capsule(height=s * rng.uniform(0.2, 0.7), radius=r, count=[12, 12])
        if rng.random() < 0.5:
            m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        return _rest(m), True, False
    if k == "torus":
        R = s * rng.uniform(0.2, 0.4)
        m = trimesh.creation.torus(major_radius=R, minor_radius=R * rng.uniform(0.15, 0.45),
                                   major_sections=24, minor_sections=12)
        if rng.random() < 0.5:
            m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        return _rest(m), True, False
    if k == "hull":
        pts = rng.normal(0, 1, (int(rng.integers(8, 30)), 3)) * s * rng.uniform(0.15, 0.4, 3)
        return _rest(trimesh.convex.convex_hull(pts)), False, False
    m = _star_prism(rng, s * rng.uniform(0.2, 0.5), s * rng.uniform(0.15, 1.0))
    return m, False, True


def _random_rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return trimesh.transformations.quaternion_matrix(q)


def obj_primitive(rng, s):
    m, smooth, flat = _primitive(rng, s)
    if rng.random() < 0.25:  # tumbled
        m.apply_transform(_random_rotation(rng))
        _rest(m)
        flat = False
    return [(m, 0, smooth)], flat


def obj_stack(rng, s=0.6):
    """2-4 primitives stacked on each other's tops, each turned about z."""
    parts, z = [], 0.0
    width = s
    for i in range(int(rng.integers(2, 5))):
        m, smooth, flat = _primitive(rng, width)
        m.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), [0, 0, 1]))
        _rest(m)
        m.apply_translation([0, 0, z])
        parts.append((m, i % 2, smooth))
        z = m.bounds[1, 2]
        ext = m.extents[:2].min()
        if not flat:
            break
        width = min(width * 0.8, ext * 1.2)
    return parts, False


def obj_group(rng, s):
    """A small group of primitives rotated together as one rigid body (e.g. a tipped-over assembly)."""
    a, sa, _ = _primitive(rng, s * 0.7)
    b, sb, _ = _primitive(rng, s * 0.6)
    b.apply_translation([a.extents[0] / 2 + b.extents[0] / 2 + 0.01 * s, 0, 0])
    R = _random_rotation(rng) if rng.random() < 0.5 else trimesh.transformations.rotation_matrix(
        rng.uniform(0, 2 * np.pi), [0, 0, 1])
    for m in (a, b):
        m.apply_transform(R)
    both = trimesh.util.concatenate([a, b])
    lo, hi = both.bounds
    off = [-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]]
    a.apply_translation(off)
    b.apply_translation(off)
    return [(a, 0, sa), (b, 1, sb)], False


def obj_table(rng, s=1.0):
    w, d, h = rng.uniform(0.6, 1.8), rng.uniform(0.5, 1.0), rng.uniform(0.45, 0.8)
    top = rng.uniform(0.025, 0.06)
    parts = [(_box(w, d, top, at=(0, 0, h - top)), 0, False)]
    leg = rng.uniform(0.03, 0.06)
    round_legs = rng.random() < 0.5
    for sx in (-1, 1):
        for sy in (-1, 1):
            at = (sx * (w / 2 - leg * 1.5), sy * (d / 2 - leg * 1.5), 0)
            parts.append((_cyl(leg, h - top, at=at) if round_legs else _box(2 * leg, 2 * leg, h - top, at=at), 1, False))
    return parts, True


def obj_chair(rng, s=1.0):
    w, h = rng.uniform(0.4, 0.55), rng.uniform(0.4, 0.5)
    parts = [(_box(w, w, 0.04, at=(0, 0, h - 0.04)), 0, False),
             (_box(w, 0.04, rng.uniform(0.35, 0.6), at=(0, w / 2 - 0.02, h)), 0, False)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append((_box(0.04, 0.04, h - 0.04, at=(sx * (w / 2 - 0.03), sy * (w / 2 - 0.03), 0)), 1, False))
    return parts, False


def obj_shelf(rng, s=1.0):
    w, d, h = rng.uniform(0.6, 1.6), rng.uniform(0.25, 0.45), rng.uniform(0.8, 2.2)
    t = 0.025
    parts = [(_box(t, d, h, at=(-w / 2 + t / 2, 0, 0)), 0, False), (_box(t, d, h, at=(w / 2 - t / 2, 0, 0)), 0, False),
             (_box(w, t, h, at=(0, d / 2 - t / 2, 0)), 1, False)]
    n = int(rng.integers(2, 6))
    for i in range(n + 1):
        z = i * (h - t) / n
        parts.append((_box(w - 2 * t, d - t, t, at=(0, -t / 2, z)), 0, False))
        if i < n and rng.random() < 0.7:  # books: a row of thin boxes
            x = -w / 2 + 2 * t
            while x < w / 2 - 3 * t:
                bw = rng.uniform(0.02, 0.07)
                bh = min(rng.uniform(0.15, 0.3), (h - t) / n - 2 * t)
                if x + bw > w / 2 - 2 * t or bh <= 0.02:
                    break
                parts.append((_box(bw, d * rng.uniform(0.5, 0.85), bh, at=(x + bw / 2, -t, z + t)), 2, False))
                x += bw + rng.uniform(0.0, 0.03)
    return parts, False


def obj_sofa(rng, s=1.0):
    w, d = rng.uniform(1.2, 2.2), rng.uniform(0.7, 1.0)
    seat = rng.uniform(0.35, 0.5)
    parts = [(_box(w, d, seat), 0, False), (_box(w, 0.2, rng.uniform(0.35, 0.5), at=(0, d / 2 - 0.1, seat)), 0, False)]
    arm = rng.uniform(0.15, 0.3)
    for sx in (-1, 1):
        parts.append((_box(0.18, d, arm, at=(sx * (w / 2 - 0.09), 0, seat)), 1, False))
    return parts, False


def obj_cabinet(rng, s=1.0):
    w, d, h = rng.uniform(0.4, 1.4), rng.uniform(0.35, 0.6), rng.uniform(0.5, 1.2)
    parts = [(_box(w, d, h), 0, False)]
    n = int(rng.integers(1, 4))
    for i in range(n):  # drawer fronts / handles
        z = (i + 0.5) * h / n
        parts.append((_box(w * 0.9, 0.02, h / n * 0.8, at=(0, -d / 2 - 0.01, z - h / n * 0.4)), 1, False))
        parts.append((_cyl(0.012, 0.03, at=(0, -d / 2 - 0.03, z), sections=8), 2, False))
    return parts, True


def obj_lamp(rng, s=1.0):
    h = rng.uniform(0.4, 1.7)
    parts = [(_cyl(rng.uniform(0.1, 0.18), 0.03), 1, False), (_cyl(0.015, h, at=(0, 0, 0.03), sections=8), 1, False)]
    shade = _cone(rng.uniform(0.12, 0.25), rng.uniform(0.15, 0.3), sections=20)
    shade.apply_translation([0, 0, h - 0.05])
    parts.append((shade, 0, False))
    return parts, False


def obj_tree(rng, s=1.0):
    h = rng.uniform(1.5, 5.0)
    parts = [(_cyl(rng.uniform(0.06, 0.2), h * 0.5, sections=12), 0, False)]
    if rng.random() < 0.5:
        crown = _sphere(h * rng.uniform(0.25, 0.4))
        crown.apply_translation([0, 0, h * 0.5 + crown.extents[2] * 0.35])
        parts.append((crown, 1, True))
    else:
        crown = _cone(h * rng.uniform(0.2, 0.3), h * 0.7, sections=16)
        crown.apply_translation([0, 0, h * 0.35])
        parts.append((crown, 1, False))
    return parts, False


def obj_arch(rng, s=1.0):
    w, h, t = rng.uniform(1.5, 3.5), rng.uniform(2.2, 4.0), rng.uniform(0.25, 0.5)
    parts = [(_box(t, t, h, at=(-w / 2, 0, 0)), 0, False), (_box(t, t, h, at=(w / 2, 0, 0)), 0, False),
             (_box(w + t, t * 1.2, t * 0.8, at=(0, 0, h)), 1, False)]
    return parts, False


def obj_bench(rng, s=1.0):
    w = rng.uniform(1.0, 2.0)
    parts = [(_box(w, 0.4, 0.06, at=(0, 0, 0.42)), 0, False)]
    for sx in (-1, 1):
        parts.append((_box(0.06, 0.4, 0.42, at=(sx * (w / 2 - 0.1), 0, 0)), 1, False))
    return parts, True


def obj_fountain(rng, s=1.0):
    r = rng.uniform(0.8, 2.0)
    parts = [(_cyl(r, 0.45, sections=32), 0, False)]
    ring = trimesh.creation.torus(major_radius=r, minor_radius=0.08, major_sections=32, minor_sections=8)
    ring.apply_translation([0, 0, 0.45])
    parts.append((ring, 1, True))
    parts.append((_cyl(0.12, rng.uniform(0.8, 1.6), at=(0, 0, 0.45), sections=12), 1, False))
    return parts, False


SMALL_OBJECTS = [(obj_primitive, 0.5), (obj_stack, 0.2), (obj_group, 0.15)]
FURNITURE = [(obj_table, 0.22), (obj_chair, 0.18), (obj_shelf, 0.15), (obj_sofa, 0.12), (obj_cabinet, 0.18),
             (obj_lamp, 0.1), (obj_stack, 0.05)]
OUTDOOR = [(obj_tree, 0.25), (obj_arch, 0.12), (obj_bench, 0.15), (obj_fountain, 0.06), (obj_primitive, 0.22),
           (obj_stack, 0.12), (obj_group, 0.08)]


def _pick(rng, table):
    w = np.array([p for _, p in table])
    return table[int(rng.choice(len(table), p=w / w.sum()))][0]


# ----------------------------------------------------------------------------------------------------
# placement


class _Builder:
    def __init__(self, rng, low_texture, texture_size, photos=None, photo_share=0.0):
        self.rng = rng
        self.low_texture = low_texture
        self.texture_size = texture_size
        self.photo_kw = {"photos": photos, "photo_share": photo_share}
        self.surfaces: list[Surface] = []
        self.obstacles: list[np.ndarray] = []
        self.targets: list[np.ndarray] = []
        self.radii: list[float] = []
        self.pool = [random_material(rng, low_texture=low_texture, texture_size=texture_size, **self.photo_kw)
                     for _ in range(int(rng.integers(4, 9)))]

    def material(self):
        if self.rng.random() < 0.15:  # a fresh material now and then keeps scenes from looking uniform
            return random_material(self.rng, low_texture=self.low_texture, texture_size=self.texture_size,
                                   **self.photo_kw)
        return self.pool[int(self.rng.integers(len(self.pool)))]

    def add(self, mesh, material, smooth=False, obstacle=True, target=False):
        self.surfaces.append(Surface(mesh, material, smooth))
        if obstacle:
            self.obstacles.append(np.asarray(mesh.bounds, np.float64).copy())
        if target:
            lo, hi = mesh.bounds
            self.targets.append((lo + hi) / 2)
            self.radii.append(float(np.linalg.norm(hi - lo) / 2))

    def add_object(self, parts, pose, target=True):
        """Add an object's parts with a 4x4 pose; one obstacle box and one target for the whole object."""
        mats = [self.material() for _ in range(3)]
        if self.rng.random() < 0.4:
            mats = [mats[0]] * 3
        meshes = []
        for m, slot, smooth in parts:
            m = m.copy()
            m.apply_transform(pose)
            self.surfaces.append(Surface(m, mats[slot % 3], smooth))
            meshes.append(m)
        lo = np.min([m.bounds[0] for m in meshes], 0)
        hi = np.max([m.bounds[1] for m in meshes], 0)
        self.obstacles.append(np.stack([lo, hi]))
        if target:
            self.targets.append((lo + hi) / 2)
            self.radii.append(float(np.linalg.norm(hi - lo) / 2))
        return lo, hi


def _footprint_radius(parts):
    lo = np.min([m.bounds[0] for m, _, _ in parts], 0)
    hi = np.max([m.bounds[1] for m, _, _ in parts], 0)
    return float(np.hypot(max(abs(lo[0]), abs(hi[0])), max(abs(lo[1]), abs(hi[1])))), float(hi[2])


def _place_discs(rng, parts_list, lo, hi, placed, margin=0.05, tries=60, against=None):
    """Place objects (given as part lists) at random x/y in [lo, hi] without overlapping bounding circles.

    ``placed`` holds (x, y, r) of circles already on the ground; returns [(k, parts, pose, (x, y, r))] for the
    objects placed, ``k`` the object's index in ``parts_list``: an object that finds no room is left out, so the
    output is not parallel to ``parts_list`` (zipping the two gave an object another one's flags).
    """
    out = []
    for k, parts in enumerate(parts_list):
        r, _ = _footprint_radius(parts)
        for _ in range(tries):
            x, y = rng.uniform(lo[0] + r, hi[0] - r) if hi[0] - lo[0] > 2 * r else None, \
                rng.uniform(lo[1] + r, hi[1] - r) if hi[1] - lo[1] > 2 * r else None
            if x is None or y is None:
                break
            if all((x - px) ** 2 + (y - py) ** 2 > (r + pr + margin) ** 2 for px, py, pr in placed):
                yaw = rng.uniform(0, 2 * np.pi) if against is None else against(x, y)
                pose = trimesh.transformations.rotation_matrix(yaw, [0, 0, 1])
                pose[:3, 3] = [x, y, 0]
                placed.append((x, y, r))
                out.append((k, parts, pose, (x, y, r)))
                break
    return out


def _stack_small_on(rng, b: _Builder, support, pose, bounds, shrink, n):
    """Put up to n small objects, without overlap, on the flat top of ``support`` (an object's parts, placed by the
    4x4 ``pose``; ``bounds`` its world box, as ``add_object`` gave it), inside the box shrunk by ``shrink`` of its
    size on each side.

    Version 3 (``_DRAWING``) places them in the support's own frame, on its own box, and keeps those whose centre
    stands on one of its top faces; versions 1-2 used the world box, whose corners lie off a turned table's top (4
    of 142 stacked objects stood beside it, in the air) or off a cylinder's or prism's."""
    v3 = _DRAWING.get() >= 3
    if v3:
        lo = np.min([m.bounds[0] for m, _, _ in support], 0)
        hi = np.max([m.bounds[1] for m, _, _ in support], 0)
    else:
        lo, hi = bounds
    top_lo, top_hi = lo + shrink * (hi - lo), hi - shrink * (hi - lo)
    placed = []
    size = float(min(top_hi[0] - top_lo[0], top_hi[1] - top_lo[1]))
    if size < 0.15:
        return
    objs = []
    for _ in range(n):
        parts, _ = _pick(rng, SMALL_OBJECTS)(rng, size * rng.uniform(0.25, 0.5))
        objs.append(parts)
    for _, parts, on, (x, y, _) in _place_discs(rng, objs, top_lo[:2], top_hi[:2], placed, margin=0.01, tries=20):
        on[2, 3] = hi[2]
        if v3:
            if not _stands_on(support, x, y, hi[2]):
                continue
            on = pose @ on
        b.add_object(parts, on)


def _stands_on(parts, x, y, z) -> bool:
    """Whether the point (x, y) lies on an upward face of ``parts`` (an object's meshes in its own frame) at
    height z."""
    p = np.array([x, y], np.float64)
    for m, _, _ in parts:
        up = (np.asarray(m.face_normals)[:, 2] > 1 - 1e-6) & (np.abs(m.triangles[:, :, 2] - z) < 1e-6).all(1)
        tri = m.triangles[up][:, :, :2]                                    # [T, 3, 2], counter-clockwise from above
        edge, to_p = np.roll(tri, -1, axis=1) - tri, p - tri               # [T, 3, 2] each
        side = edge[..., 0] * to_p[..., 1] - edge[..., 1] * to_p[..., 0]  # >= 0: p left of (or on) the edge
        if (side >= -1e-12).all(1).any():
            return True
    return False


def _ground(b: _Builder, half: float, material=None, z=0.0):
    g = _box(2 * half, 2 * half, 0.1, at=(0, 0, z - 0.1))
    b.add(g, material or b.material(), obstacle=False)


def _wall_with_openings(length, height, thick, openings):
    """Boxes of a wall along +x from 0 to ``length`` (interior face at y = 0, wall at y in [-thick, 0]),
    with rectangular openings (x_center, width, bottom, top) cut out."""
    boxes = []
    openings = sorted(openings)
    x = 0.0
    for cx, w, bot, top in openings:
        x0, x1 = cx - w / 2, cx + w / 2
        if x0 > x:
            boxes.append((x, x0, 0.0, height))
        if bot > 0:
            boxes.append((x0, x1, 0.0, bot))
        if top < height:
            boxes.append((x0, x1, top, height))
        x = x1
    if x < length:
        boxes.append((x, length, 0.0, height))
    meshes = []
    for x0, x1, z0, z1 in boxes:
        if x1 - x0 > 1e-3 and z1 - z0 > 1e-3:
            meshes.append(_box(x1 - x0, thick, z1 - z0, at=((x0 + x1) / 2, -thick / 2, z0)))
    return meshes


def _flag_source(k: int, n_placed: int) -> int:
    """Whose flat-top flag the ``n_placed``-th placed object (object ``k`` of the list) takes: its own (version 2 on),
    or version 1's, the ``n_placed``-th object's (once an object found no room, the next inherited another's)."""
    return k if _DRAWING.get() >= 2 else n_placed


def _room(rng, b: _Builder):
    W, D, H = rng.uniform(3.0, 8.0), rng.uniform(3.0, 7.0), rng.uniform(2.4, 3.4)
    t = 0.12
    floor_mat, wall_mat, ceil_mat = b.material(), b.material(), b.material()
    any_window = False
    # walls: (length, transform taking the wall's local frame to the room)
    corners = [(0, 0), (W, 0), (W, D), (0, D)]
    for side, length in enumerate((W, D, W, D)):
        openings = []
        if rng.random() < 0.45 and length > 2.0:  # door
            w = rng.uniform(0.8, 1.2)
            openings.append((rng.uniform(w / 2 + 0.2, length - w / 2 - 0.2), w, 0.0, min(2.1, H - 0.2)))
        if rng.random() < 0.5 and length > 2.5:   # window
            w = rng.uniform(0.6, 1.8)
            cx = rng.uniform(w / 2 + 0.2, length - w / 2 - 0.2)
            if all(abs(cx - o[0]) > (w + o[1]) / 2 + 0.15 for o in openings):
                openings.append((cx, w, rng.uniform(0.7, 1.1), min(H - 0.3, rng.uniform(1.9, 2.4))))
        any_window |= bool(openings)
        # local wall frame: along +x, outward -y; turning by side * 90 deg about z walks round the room
        pose = trimesh.transformations.rotation_matrix(side * np.pi / 2, [0, 0, 1])
        pose[:3, 3] = [corners[side][0], corners[side][1], 0]
        mat = wall_mat if rng.random() < 0.8 else b.material()
        for m in _wall_with_openings(length, H, t, openings):
            m.apply_transform(pose)
            b.add(m, mat, obstacle=False)
    if any_window or rng.random() < 0.3:
        _ground(b, max(W, D) + 20, material=b.material(), z=-0.005)  # outdoor ground seen through openings
        # a few blocks outside so openings do not only show sky
        for _ in range(int(rng.integers(0, 5))):
            ang = rng.uniform(0, 2 * np.pi)
            dist = rng.uniform(max(W, D) * 0.8 + 3, max(W, D) + 12)
            c = np.array([W / 2 + dist * np.cos(ang), D / 2 + dist * np.sin(ang)])
            m = _box(rng.uniform(2, 8), rng.uniform(2, 8), rng.uniform(2, 10), at=(c[0], c[1], 0))
            b.add(m, b.material(), obstacle=False)
    b.add(_box(W + 2 * t, D + 2 * t, t, at=(W / 2, D / 2, -t)), floor_mat, obstacle=False)
    b.add(_box(W + 2 * t, D + 2 * t, t, at=(W / 2, D / 2, H)), ceil_mat, obstacle=False)
    # rugs / wall panels: thin textured slabs adding texture variety
    for _ in range(int(rng.integers(0, 3))):
        rw, rd = rng.uniform(0.8, W * 0.6), rng.uniform(0.8, D * 0.6)
        b.add(_box(rw, rd, 0.01, at=(rng.uniform(rw / 2, W - rw / 2), rng.uniform(rd / 2, D - rd / 2), 0)),
              b.material(), obstacle=False)
    # furniture: along walls (facing the room) or free-standing
    placed = []
    n = int(rng.integers(3, 10))
    center = np.array([W / 2, D / 2])

    def face_center(x, y):
        return float(np.arctan2(center[1] - y, center[0] - x) + np.pi / 2)

    objs = [(_pick(rng, FURNITURE), ) for _ in range(n)]
    built = [f[0](rng) for f in objs]
    against = face_center if rng.random() < 0.6 else None
    for n_placed, (k, parts, pose, _) in enumerate(_place_discs(rng, [p for p, _ in built], (0.05, 0.05),
                                                                (W - 0.05, D - 0.05), placed, against=against)):
        flat = built[_flag_source(k, n_placed)][1]  # only a flat top takes small objects
        lo, hi = b.add_object(parts, pose)
        if flat and rng.random() < 0.7:
            _stack_small_on(rng, b, parts, pose, (lo, hi), 0.15, int(rng.integers(1, 4)))
    # wall targets so cameras also look at walls/doors
    for _ in range(3):
        p = np.array([rng.uniform(0.3, W - 0.3), rng.uniform(0.3, D - 0.3), rng.uniform(0.5, H - 0.5)])
        side = int(rng.integers(4))
        if side % 2 == 0:
            p[1] = 0.0 if side == 0 else D
        else:
            p[0] = W if side == 1 else 0.0
        b.targets.append(p)
        b.radii.append(1.0)
    # lights: ceiling points/spots, sometimes sunlight through the windows
    lights = []
    for _ in range(int(rng.integers(1, 4))):
        pos = np.array([rng.uniform(0.5, W - 0.5), rng.uniform(0.5, D - 0.5), H - 0.25])
        col = _light_color(rng)
        if rng.random() < 0.7:
            lights.append(Light("point", col, float(rng.uniform(3, 12) * W * D / 10), position=pos))
        else:
            lights.append(Light("spot", col, float(rng.uniform(8, 30) * W * D / 10), position=pos,
                                direction=_unit(np.array([rng.normal(0, 0.4), rng.normal(0, 0.4), -1.0])),
                                inner_cone=float(rng.uniform(0.1, 0.4)), outer_cone=float(rng.uniform(0.5, 1.1))))
    if any_window and rng.random() < 0.6:
        lights.append(Light("directional", _light_color(rng), float(rng.uniform(1, 4)),
                            direction=_unit(rng.normal(0, 1, 3) * [1, 1, 0.3] - [0, 0, 1])))
    lo = np.array([0.3, 0.3, 0.4])
    hi = np.array([W - 0.3, D - 0.3, min(H - 0.3, 2.2)])
    return lights, lo, hi, float(np.hypot(W, D) + 25 * any_window)


def _cluster(rng, b: _Builder):
    R = rng.uniform(1.0, 4.0)
    _ground(b, 40.0)
    placed = []
    n = int(rng.integers(4, 16))
    objs = []
    for _ in range(n):
        s = rng.uniform(0.25, 1.4) * R / 2.5
        parts, flat = _pick(rng, SMALL_OBJECTS + [(obj_table, 0.05), (obj_cabinet, 0.05), (obj_chair, 0.03)])(rng, s)
        objs.append((parts, flat))
    for n_placed, (k, parts, pose, _) in enumerate(_place_discs(rng, [p for p, _ in objs], (-R, -R), (R, R), placed,
                                                                margin=rng.uniform(0.02, 0.3))):
        flat = objs[_flag_source(k, n_placed)][1]
        lo, hi = b.add_object(parts, pose)
        if flat and rng.random() < 0.5:
            _stack_small_on(rng, b, parts, pose, (lo, hi), 0.1, int(rng.integers(1, 3)))
    if rng.random() < 0.4:  # backdrop walls far away
        for k in range(int(rng.integers(1, 4))):
            ang = rng.uniform(0, 2 * np.pi)
            dist = R + rng.uniform(4, 12)
            wall = _box(rng.uniform(6, 20), 0.3, rng.uniform(2, 6))
            pose = trimesh.transformations.rotation_matrix(ang + np.pi / 2, [0, 0, 1])
            pose[:3, 3] = [dist * np.cos(ang), dist * np.sin(ang), 0]
            wall.apply_transform(pose)
            b.add(wall, b.material(), obstacle=True)
    lights = _outdoor_lights(rng)
    lo = np.array([-R - 8, -R - 8, 0.25])
    hi = np.array([R + 8, R + 8, R + 5])
    return lights, lo, hi, 2 * R + 40


def _courtyard(rng, b: _Builder):
    Lx, Ly = rng.uniform(8, 22), rng.uniform(8, 22)
    _ground(b, max(Lx, Ly) + 30)
    facade = [b.material() for _ in range(3)]
    # buildings along the sides (some sides open), as boxes or extruded footprints
    for side in range(4):
        if rng.random() < 0.2:
            continue
        length = Lx if side % 2 == 0 else Ly
        x = -length / 2
        while x < length / 2 - 1:
            w = min(rng.uniform(3, 10), length / 2 - x)
            h = rng.uniform(3, 15)
            d = rng.uniform(3, 8)
            if rng.random() < 0.25:
                m = _star_prism(rng, min(w, d) / 2, h, n=int(rng.integers(4, 8)))
                m.apply_translation([x + w / 2, (Ly if side % 2 == 0 else Lx) / 2 + d / 2, 0])
            else:
                m = _box(w, d, h, at=(x + w / 2, (Ly if side % 2 == 0 else Lx) / 2 + d / 2, 0))
            pose = trimesh.transformations.rotation_matrix(side * np.pi / 2, [0, 0, 1])
            m.apply_transform(pose)
            b.add(m, facade[int(rng.integers(3))], obstacle=True, target=rng.random() < 0.3)
            x += w + (rng.uniform(0.5, 3) if rng.random() < 0.3 else 0.0)
    placed = []
    objs = [_pick(rng, OUTDOOR)(rng, rng.uniform(0.4, 1.5)) for _ in range(int(rng.integers(5, 16)))]
    for _, parts, pose, _ in _place_discs(rng, [p for p, _ in objs], (-Lx / 2 + 0.5, -Ly / 2 + 0.5),
                                          (Lx / 2 - 0.5, Ly / 2 - 0.5), placed, margin=0.3):
        b.add_object(parts, pose)
    lights = _outdoor_lights(rng)
    lo = np.array([-Lx / 2 + 0.3, -Ly / 2 + 0.3, 1.0])
    hi = np.array([Lx / 2 - 0.3, Ly / 2 - 0.3, rng.uniform(2.0, 6.0)])
    return lights, lo, hi, float(np.hypot(Lx, Ly) + 60)


def _unit(v):
    return v / np.linalg.norm(v)


def _light_color(rng):
    temp = rng.uniform(0, 1)  # warm .. cool
    warm, cool = np.array([1.0, 0.8, 0.6]), np.array([0.8, 0.9, 1.0])
    c = warm * (1 - temp) + cool * temp
    if rng.random() < 0.1:
        c = random_color(rng, saturation=(0.3, 0.8), value=(0.9, 1.0))
    return np.clip(c, 0, 1)


def _outdoor_lights(rng):
    lights = [Light("directional", _light_color(rng), float(rng.uniform(2, 6)),
                    direction=_unit(np.array([rng.normal(), rng.normal(), -rng.uniform(0.3, 2.0)])))]
    if rng.random() < 0.5:
        lights.append(Light("directional", _light_color(rng), float(rng.uniform(0.5, 2)),
                            direction=_unit(np.array([rng.normal(), rng.normal(), -rng.uniform(0.2, 1.0)]))))
    if rng.random() < 0.3:
        lights.append(Light("point", _light_color(rng), float(rng.uniform(20, 80)),
                            position=np.array([rng.normal(0, 3), rng.normal(0, 3), rng.uniform(2, 5)])))
    return lights


def make_scene(rng: np.random.Generator, kind: str | None = None, *, low_texture_share: float = 0.15,
               kind_weights: dict | None = None, texture_size: int = 256, photos=None,
               photo_share: float = 0.0, version: int = SCENE_VERSIONS[-1]) -> Scene:
    """Draw one procedural scene.

    kind: "room", "cluster", "courtyard" or None (drawn with ``kind_weights``).
    low_texture_share: probability in [0, 1] that the scene is low-texture (mostly plain colours).
    photos, photo_share: a data.textures.PhotoCollection and the share of textures cut from its photographs.
    version: the generator version whose scenes to draw (``SCENE_VERSIONS``; data.generate.GENERATOR_VERSION):
    3 builds every prism star-shaped about its centre and centred, and stands stacked objects on their support's
    own top (a spot whose centre misses the top is left empty, not drawn again); 2 stacks small objects only on
    the flat tops they were drawn for; 1 draws the scenes earlier datasets hold (held-out sets rendered with it
    render again identically).
    """
    if not 0.0 <= float(photo_share) <= 1.0:
        raise ValueError(f"photo_share expected a probability in [0, 1], got {photo_share!r}")
    if photo_share > 0 and photos is None:
        raise ValueError("photo_share > 0 needs photos (a data.textures.PhotoCollection)")
    if not isinstance(version, int) or isinstance(version, bool) or version not in SCENE_VERSIONS:
        raise ValueError(f"version expected one of {SCENE_VERSIONS}, got {version!r}")
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng expected a numpy.random.Generator, got {type(rng).__name__}")
    if not 0.0 <= float(low_texture_share) <= 1.0:
        raise ValueError(f"low_texture_share expected a probability in [0, 1], got {low_texture_share!r}")
    weights = dict(DEFAULT_KIND_WEIGHTS if kind_weights is None else kind_weights)
    usable = all(isinstance(w, numbers.Real) and not isinstance(w, bool) and math.isfinite(w) and w >= 0
                 for w in weights.values())
    if set(weights) - set(KINDS) or not usable or sum(weights.values()) <= 0:
        raise ValueError(f"kind_weights expected finite non-negative weights over {KINDS} with a positive sum, "
                         f"got {kind_weights!r}")
    if kind is None:  # in KINDS' order, whatever the dict's: one seed, one scene
        names = [k for k in KINDS if k in weights]
        p = np.array([weights[k] for k in names], np.float64)
        kind = names[int(rng.choice(len(names), p=p / p.sum()))]
    if kind not in KINDS:
        raise ValueError(f"scene kind expected one of {KINDS}, got {kind!r}")
    drawing = _DRAWING.set(version)
    try:
        low = bool(rng.random() < low_texture_share)
        b = _Builder(rng, low, texture_size, photos, photo_share)
        lights, lo, hi, extent = {"room": _room, "cluster": _cluster, "courtyard": _courtyard}[kind](rng, b)
    finally:
        _DRAWING.reset(drawing)
    if not b.targets:
        b.targets.append((lo + hi) / 2)
        b.radii.append(1.0)
    ambient = np.full(3, rng.uniform(0.05, 0.35)) * _light_color(rng)
    sky = random_color(rng, saturation=(0.0, 0.6), value=(0.3, 1.0))
    return Scene(kind=kind, surfaces=b.surfaces, lights=lights, ambient=ambient, bg_color=sky,
                 camera_lo=lo, camera_hi=hi,
                 obstacles=np.array(b.obstacles, np.float64).reshape(-1, 2, 3),
                 targets=np.array(b.targets, np.float64), target_radius=np.array(b.radii, np.float64),
                 low_texture=low, extent=float(extent), version=version)


def plane_scene(distance: float, size: float = 50.0, texture: np.ndarray | None = None) -> Scene:
    """A single square plane facing -z... placed at z = ``distance`` in front of a camera at the
    origin looking along +z (OpenCV identity pose). Used to check analytic depth."""
    m = trimesh.Trimesh(vertices=[[-size, -size, distance], [size, -size, distance], [size, size, distance],
                                  [-size, size, distance]], faces=[[0, 2, 1], [0, 3, 2]], process=False)
    mat = Material(base_color=np.array([0.8, 0.8, 0.8, 1.0]), texture=texture, uv_scale=0.5)
    return Scene(kind="plane", surfaces=[Surface(m, mat)],
                 lights=[Light("directional", np.ones(3), 3.0, direction=np.array([0.0, 0.0, 1.0]))],
                 ambient=np.full(3, 0.3), bg_color=np.zeros(3), camera_lo=np.full(3, -1e3),
                 camera_hi=np.full(3, 1e3), obstacles=np.zeros((0, 2, 3)), targets=np.array([[0, 0, distance]]),
                 target_radius=np.array([1.0]), extent=float(distance * 2 + size))
