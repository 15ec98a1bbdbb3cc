"""Camera sampling: pairs and N-view sets with controlled overlap, baselines and fields of view.

A view set is grown one view at a time: the first view looks at a point of interest of the scene; each
further view is derived from a random earlier one ("reference") by one of six moves:

- ``small``:  translation of 2-25 % of the viewing distance, look-at jitter;
- ``medium``: orbit of 8-30 degrees about a surface point seen by the reference;
- ``wide``:   orbit of 30-90 degrees about that point (wide baselines around objects);
- ``zoom``:   move 25-60 % of the way to the point, or back 15-36 % of that distance, small rotation;
- ``slide``:  the reference's orientation turned by at most 3 degrees, the camera moved 5-40 % of the viewing
  distance sideways (plus a little up/down and forward/back): a stereo rig, a dolly, a walking camera;
- ``pan``:    the camera turned in place by 8-35 degrees (yaw about the vertical, a little pitch), moved by at
  most 4 % of the viewing distance: a handheld panorama.

The first four aim every new view at a point the reference sees, which ties the translation to the rotation;
``slide`` and ``pan`` break that tie (real photographs often have one without the other). Their default weight is
0, so a run without ``--moves`` draws the same views as before they existed.

Every view draws its own field of view (``fov_deg``) unless the set is taken with one camera (a share
``same_camera`` of the sets: all views keep view 0's intrinsics). With independent fields of view a zoom-in
looks like a step forward, so a pair's forward motion can only be read from perspective cues; one camera,
the common case of a phone, a video or a stereo rig, lets the image magnification tell it (docs/data.md).

Every candidate is rendered depth-only first and rejected when degenerate: camera inside an
obstacle box or outside the scene's camera region, geometry closer than ``min_depth`` on more than 1 %
of pixels (inside/touching geometry), fewer than ``min_valid`` pixels with depth, or overlap with its
reference outside ``overlap`` (overlap = fraction of view-1 pixels with depth co-visible in view 2, by
depth test; required in both directions, and the smaller of the two must not exceed the maximum).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from data.geom import axis_angle, correspondences, intrinsics_from_fov, look_at, overlap
from pointmap.errors import ShapeError

MOVES = ("small", "medium", "wide", "zoom", "slide", "pan")
OVERLAP_STRIDE = 2   # overlaps are estimated on every 2nd row and column (4x faster, ~1% accurate)


class DegenerateScene(RuntimeError):
    """No acceptable view could be found in the allotted tries (the caller draws another scene)."""


@dataclass(frozen=True)
class CameraConfig:
    fov_deg: tuple = (40.0, 90.0)
    orientation_weights: tuple = (0.4, 0.35, 0.25)   # square, landscape, portrait
    short_side_ratios: tuple = (0.75, 5 / 7)          # short/long for non-square images
    overlap: tuple = (0.15, 0.95)
    move_weights: tuple = (0.3, 0.25, 0.3, 0.15, 0.0, 0.0)  # small, medium, wide, zoom, slide, pan
    wide_deg: tuple = (30.0, 90.0)
    min_valid: float = 0.4
    min_depth: float = 0.08
    max_roll_deg: float = 8.0
    big_roll_share: float = 0.1                         # share of views with roll up to 30 deg
    principal_jitter: float = 0.03                      # fraction of the image size
    max_tries: int = 25
    same_camera: float = 0.0                            # share of view sets taken with one camera: every view
                                                        # has view 0's intrinsics (0 draws nothing: older runs
                                                        # render as before)

    def __post_init__(self):
        lo, hi = self.fov_deg
        if not (10 <= lo <= hi <= 150):
            raise ValueError(f"fov_deg expected 10 <= lo <= hi <= 150, got {self.fov_deg}")
        olo, ohi = self.overlap
        if not (0 <= olo <= ohi <= 1):
            raise ValueError(f"overlap expected 0 <= lo <= hi <= 1, got {self.overlap}")
        if (len(self.move_weights) != len(MOVES) or not all(np.isfinite(self.move_weights))
                or min(self.move_weights) < 0 or sum(self.move_weights) <= 0):
            raise ValueError(f"move_weights expected {len(MOVES)} finite non-negative weights for {MOVES}, "
                             f"got {self.move_weights}")
        if not (0 <= self.min_valid <= 1):
            raise ValueError(f"min_valid expected in [0, 1], got {self.min_valid}")
        if not (0 <= self.same_camera <= 1):
            raise ValueError(f"same_camera expected a share in [0, 1], got {self.same_camera}")


@dataclass
class View:
    K: np.ndarray               # [3, 3] float64, pixels
    cam2world: np.ndarray       # [4, 4] float64, OpenCV
    width: int
    height: int
    depth: np.ndarray           # [H, W] float32, 0 = background
    rgb: np.ndarray | None = None
    move: str = "first"
    ref: int = -1


@dataclass
class ViewSet:
    views: list
    overlap: np.ndarray          # [V, V]: overlap[i, j] = fraction of view i's pixels co-visible in view j

    def corr(self, i: int, j: int) -> np.ndarray:
        """Full-resolution correspondences [H, W, 2] of view i's pixels in view j (NaN = none)."""
        a, b = self.views[i], self.views[j]
        return correspondences(a.depth, a.K, a.cam2world, b.depth, b.K, b.cam2world)[0]

    def pairs(self, lo: float, hi: float):
        """Index pairs (i < j) whose overlap is >= lo in both directions and whose smaller overlap <= hi."""
        out = []
        n = len(self.views)
        for i in range(n):
            for j in range(i + 1, n):
                a, b = self.overlap[i, j], self.overlap[j, i]
                if min(a, b) >= lo and min(a, b) <= hi:
                    out.append((i, j))
        return out


def image_size(rng: np.random.Generator, size: int, cfg: CameraConfig) -> tuple[int, int]:
    """(width, height): the long side is ``size``; the short side a multiple of 16 (landscape/portrait)."""
    if not isinstance(size, (int, np.integer)) or size < 16:
        raise ShapeError(f"size expected an int >= 16, got {size!r}")
    w = np.asarray(cfg.orientation_weights, np.float64)
    o = int(rng.choice(3, p=w / w.sum()))
    if o == 0:
        return size, size
    ratio = float(cfg.short_side_ratios[int(rng.integers(len(cfg.short_side_ratios)))])
    short = max(16, int(size * ratio / 16 + 0.5) * 16)
    return (size, short) if o == 1 else (short, size)


def sample_K(rng, width, height, cfg: CameraConfig) -> np.ndarray:
    fov = rng.uniform(*cfg.fov_deg)
    j = cfg.principal_jitter
    return intrinsics_from_fov(width, height, fov, cx_offset=rng.uniform(-j, j) * width,
                               cy_offset=rng.uniform(-j, j) * height)


def _roll(rng, cfg):
    m = 30.0 if rng.random() < cfg.big_roll_share else cfg.max_roll_deg
    return np.radians(rng.uniform(-m, m))


def _unit(v):
    return v / np.linalg.norm(v)


def _first_pose(rng, scene, K, width, cfg):
    """Eye near a point of interest, at a distance where it fills a good part of the view."""
    n = len(scene.targets)
    for _ in range(40):
        t = int(rng.integers(n))
        target = scene.targets[t] + rng.normal(0, 0.05, 3) * scene.target_radius[t]
        half_fov = np.arctan(0.5 * width / K[0, 0])
        d = scene.target_radius[t] / np.tan(half_fov) * rng.uniform(0.7, 2.5)
        d = float(np.clip(d, 0.4, scene.extent * 0.4))
        az = rng.uniform(0, 2 * np.pi)
        el = np.radians(rng.uniform(-5, 40) if rng.random() < 0.8 else rng.uniform(40, 70))
        eye = target + d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        if not scene.inside_obstacle(eye, margin=0.12):
            return look_at(eye, target, roll=_roll(rng, cfg))
    for _ in range(40):  # fallback: anywhere in the camera region, looking at a target
        eye = rng.uniform(scene.camera_lo, scene.camera_hi)
        target = scene.targets[int(rng.integers(n))]
        if not scene.inside_obstacle(eye, margin=0.12) and np.linalg.norm(target - eye) > 0.3:
            return look_at(eye, target, roll=_roll(rng, cfg))
    return None


def _focus_point(rng, ref: View):
    """A 3D surface point seen near the centre of the reference view (what a person would orbit)."""
    h, w = ref.depth.shape
    ys, xs = np.nonzero(ref.depth[h // 4: 3 * h // 4, w // 4: 3 * w // 4] > 0)
    if len(xs) == 0:
        ys, xs = np.nonzero(ref.depth > 0)
    else:
        ys, xs = ys + h // 4, xs + w // 4
    k = int(rng.integers(len(xs)))
    d = float(ref.depth[ys[k], xs[k]])
    p_cam = np.array([(xs[k] - ref.K[0, 2]) / ref.K[0, 0] * d, (ys[k] - ref.K[1, 2]) / ref.K[1, 1] * d, d])
    return ref.cam2world[:3, :3] @ p_cam + ref.cam2world[:3, 3], d


def _posed(R: np.ndarray, eye: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, eye
    return T


def _related_pose(rng, scene, ref: View, move: str, cfg):
    eye0 = ref.cam2world[:3, 3]
    R0 = ref.cam2world[:3, :3]
    if move in ("slide", "pan"):  # moves that keep no look-at point: scaled by the reference's median depth
        d = float(np.median(ref.depth[ref.depth > 0]))
    if move == "slide":
        side = rng.uniform(0.05, 0.4) * rng.choice([-1, 1])
        offset = np.array([side, rng.normal(0, 0.05), rng.uniform(-0.15, 0.15)]) * d  # camera axes
        R = R0 @ axis_angle(rng.normal(size=3), np.radians(rng.uniform(0, 3)))
        eye = eye0 + R0 @ offset
        return eye, _posed(R, eye)
    if move == "pan":
        yaw = np.radians(rng.uniform(8, 35)) * rng.choice([-1, 1])
        pitch = np.radians(rng.uniform(-8, 8))
        R = axis_angle([0, 0, 1], yaw) @ R0 @ axis_angle([1, 0, 0], pitch)  # world vertical, then camera x
        eye = eye0 + _unit(rng.normal(size=3)) * d * rng.uniform(0, 0.04)
        return eye, _posed(R, eye)
    P, d = _focus_point(rng, ref)
    jitter = rng.normal(0, 0.04, 3) * d
    if move == "small":
        eye = eye0 + _unit(rng.normal(size=3)) * d * rng.uniform(0.02, 0.25)
        return eye, look_at(eye, P + jitter, roll=_roll(rng, cfg))
    if move in ("medium", "wide"):
        lo, hi = (8.0, 30.0) if move == "medium" else cfg.wide_deg
        ang = np.radians(rng.uniform(lo, hi)) * rng.choice([-1, 1])
        off = eye0 - P
        c, s = np.cos(ang), np.sin(ang)
        off = np.array([c * off[0] - s * off[1], s * off[0] + c * off[1], off[2]])  # about the vertical
        el = np.radians(rng.uniform(-12, 12))                                    # and a little up/down
        horiz = np.linalg.norm(off[:2])
        r = np.linalg.norm(off)
        cur = np.arctan2(off[2], max(horiz, 1e-9))
        new = np.clip(cur + el, np.radians(-20), np.radians(75))
        scale = rng.uniform(0.75, 1.3)
        if horiz > 1e-9:
            off = np.r_[off[:2] / horiz * r * np.cos(new), r * np.sin(new)]
        eye = P + off * scale
        return eye, look_at(eye, P + jitter, roll=_roll(rng, cfg))
    # zoom
    f = rng.uniform(0.25, 0.6) * rng.choice([1, -0.6])
    eye = eye0 + (P - eye0) * f + rng.normal(0, 0.03, 3) * d
    return eye, look_at(eye, P + jitter, roll=_roll(rng, cfg))


def _acceptable(depth, cfg):
    if (depth > 0).mean() < cfg.min_valid:
        return False
    near = (depth > 0) & (depth < cfg.min_depth)
    return near.mean() <= 0.01


def sample_views(rng: np.random.Generator, scene, renderer, n_views: int, size: int,
                 cfg: CameraConfig = CameraConfig(), *, color: bool = True) -> ViewSet:
    """Grow a set of ``n_views`` views of ``scene`` (each overlapping an earlier one within
    ``cfg.overlap``) and render them; raises ``DegenerateScene`` when the scene offers no valid view."""
    if not isinstance(n_views, (int, np.integer)) or n_views < 1:
        raise ValueError(f"n_views expected an int >= 1, got {n_views!r}")
    width, height = image_size(rng, size, cfg)
    one_camera = cfg.same_camera > 0 and rng.random() < cfg.same_camera
    views: list[View] = []
    ov = np.eye(n_views)
    done = np.eye(n_views, dtype=bool)
    mw = np.asarray(cfg.move_weights, np.float64)
    st = OVERLAP_STRIDE
    for k in range(n_views):
        accepted = False
        for _ in range(cfg.max_tries):
            K = views[0].K if one_camera and views else sample_K(rng, width, height, cfg)
            if k == 0:
                T = _first_pose(rng, scene, K, width, cfg)
                if T is None:
                    break
                move, ref = "first", -1
            else:
                ref = int(rng.integers(k))
                move = MOVES[int(rng.choice(len(MOVES), p=mw / mw.sum()))]
                eye, T = _related_pose(rng, scene, views[ref], move, cfg)
                if scene.inside_obstacle(eye, margin=0.12):
                    continue
            _, depth = renderer.render(scene, K, T, width, height, color=False)
            if not _acceptable(depth, cfg):
                continue
            view = View(K=K, cam2world=T, width=width, height=height, depth=depth, move=move, ref=ref)
            if k > 0:
                r = views[ref]
                a = overlap(r.depth, r.K, r.cam2world, depth, K, T, stride=st)
                b = overlap(depth, K, T, r.depth, r.K, r.cam2world, stride=st)
                if min(a, b) < cfg.overlap[0] or min(a, b) > cfg.overlap[1]:
                    continue
                ov[ref, k], ov[k, ref] = a, b
                done[ref, k] = done[k, ref] = True
            views.append(view)
            accepted = True
            break
        if not accepted:
            raise DegenerateScene(f"no acceptable view {k} in {cfg.max_tries} tries")
    for i in range(n_views):  # overlaps of all remaining ordered pairs
        for j in range(n_views):
            if not done[i, j]:
                a, b = views[i], views[j]
                ov[i, j] = overlap(a.depth, a.K, a.cam2world, b.depth, b.K, b.cam2world, stride=st)
    if color:
        for v in views:
            v.rgb, _ = renderer.render(scene, v.K, v.cam2world, width, height, color=True, depth=False)
    return ViewSet(views=views, overlap=ov)
