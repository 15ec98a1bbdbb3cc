"""A small textured synthetic scene rendered with pyrender (EGL), for splatting tests and the benchmark.

A room corner (floor, back wall, two side walls) with procedural textures and a few textured boxes,
rendered unlit (flat shading, so colours are view-independent) from cameras on an arc. Everything is
in OpenCV conventions; pyrender's camera is ``cam2world_cv @ diag(1, -1, -1, 1)`` and OpenCV principal
points are passed as ``cx + 0.5``, ``cy + 0.5`` (see /work/shared/research/pyrender-notes.md).
"""

from __future__ import annotations

import math
import os

import numpy as np
import torch

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
if not hasattr(np, "infty"):
    np.infty = np.inf  # pyrender 0.1.45 still uses the alias numpy 2 removed


def _texture(seed: int, size: int = 256, kind: str = "checker") -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    base = rng.uniform(0.0, 1.0, 3)
    alt = 1.0 - base * rng.uniform(0.6, 1.0, 3)
    if kind == "checker":
        n = rng.integers(10, 20)
        m = ((np.floor(xx * n) + np.floor(yy * n)) % 2)[..., None]
        img = m * base + (1 - m) * alt
    elif kind == "stripes":
        f = rng.uniform(8, 16)
        m = (0.5 + 0.5 * np.sin(2 * math.pi * f * (xx + 0.3 * yy)))[..., None]
        img = m * base + (1 - m) * alt
    else:  # blobs
        img = np.zeros((size, size, 3)) + base
        for _ in range(60):
            c = rng.uniform(0, 1, 2)
            r = rng.uniform(0.02, 0.08)
            col = rng.uniform(0, 1, 3)
            mask = (((xx - c[0]) ** 2 + (yy - c[1]) ** 2) < r * r)[..., None]
            img = np.where(mask, col, img)
    # low-amplitude smooth shading so flat regions are not constant
    img = img * (0.85 + 0.15 * np.sin(3 * xx + 2 * yy)[..., None])
    # fine detail: value noise at 1/16 of the texture, bilinearly upsampled
    coarse = rng.uniform(-1, 1, (size // 16 + 1, size // 16 + 1))
    gy, gx = np.mgrid[0:size, 0:size] / 16.0
    i0, j0 = gy.astype(int), gx.astype(int)
    fy, fx = gy - i0, gx - j0
    i1, j1 = np.minimum(i0 + 1, coarse.shape[0] - 1), np.minimum(j0 + 1, coarse.shape[1] - 1)
    noise = ((1 - fy) * ((1 - fx) * coarse[i0, j0] + fx * coarse[i0, j1])
             + fy * ((1 - fx) * coarse[i1, j0] + fx * coarse[i1, j1]))
    img = img + 0.12 * noise[..., None]
    # pyrender decodes textures as sRGB and writes linear values: pre-encode so renders keep this palette
    return (np.clip(img, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)


def _quad(corner, e1, e2, tex):
    import trimesh
    from PIL import Image

    corner, e1, e2 = (np.asarray(v, dtype=np.float64) for v in (corner, e1, e2))
    v = np.stack([corner, corner + e1, corner + e1 + e2, corner + e2])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
    vis = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(tex))
    return trimesh.Trimesh(vertices=v, faces=f, visual=vis, process=False)


def _box(center, size, seed):
    c = np.asarray(center, float)
    sx, sy, sz = size
    h = np.array([sx, sy, sz]) / 2
    kinds = ["checker", "stripes", "blobs"]
    quads = []
    faces = [  # corner, e1, e2 (outward normal = e1 x e2)
        (c + [-h[0], -h[1], -h[2]], [sx, 0, 0], [0, sy, 0]),   # z- face (towards the cameras)
        (c + [h[0], -h[1], h[2]], [-sx, 0, 0], [0, sy, 0]),    # z+
        (c + [-h[0], -h[1], h[2]], [0, 0, -sz], [0, sy, 0]),   # x-
        (c + [h[0], -h[1], -h[2]], [0, 0, sz], [0, sy, 0]),    # x+
        (c + [-h[0], -h[1], h[2]], [sx, 0, 0], [0, 0, -sz]),   # y- (top, y is down)
    ]
    for k, (corner, e1, e2) in enumerate(faces):
        quads.append(_quad(corner, e1, e2, _texture(seed * 10 + k, 128, kinds[(seed + k) % 3])))
    return quads


def build_meshes(seed: int = 0):
    """World frame: y down (OpenCV-like), cameras look along +z; the room spans z in [1.5, 5]."""
    floor_y, back_z = 1.0, 5.0
    meshes = [
        _quad([-3, floor_y, 0.5], [6, 0, 0], [0, 0, back_z - 0.5], _texture(seed + 1, 512, "checker")),   # floor
        _quad([-3, floor_y, back_z], [6, 0, 0], [0, -3.5, 0], _texture(seed + 2, 512, "blobs")),          # back
        _quad([-3, floor_y, 0.5], [0, 0, back_z - 0.5], [0, -3.5, 0], _texture(seed + 3, 256, "stripes")),  # left
        _quad([3, floor_y, back_z], [0, 0, 0.5 - back_z], [0, -3.5, 0], _texture(seed + 4, 256, "blobs")),  # right
    ]
    meshes += _box([-0.7, floor_y - 0.35, 3.4], (0.7, 0.7, 0.7), seed + 5)
    meshes += _box([0.8, floor_y - 0.5, 3.9], (0.6, 1.0, 0.6), seed + 6)
    meshes += _box([0.1, floor_y - 0.2, 2.8], (0.4, 0.4, 0.4), seed + 7)
    return meshes


def look_at(eye, target, down=(0.0, 1.0, 0.0)) -> np.ndarray:
    """OpenCV cam2world looking from ``eye`` at ``target``, image y along world ``down``."""
    eye, target, down = (np.asarray(v, dtype=np.float64) for v in (eye, target, down))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(down, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def arc_cameras(n: int, *, radius: float = 0.8, span_deg: float = 30.0, target=(0.0, 0.3, 3.6)):
    """``n`` cam2world on a horizontal arc in front of the scene, all looking at ``target``."""
    out = []
    for k in range(n):
        t = 0.0 if n == 1 else k / (n - 1) - 0.5
        ang = math.radians(span_deg) * t
        eye = np.array([radius * math.sin(ang) * 2.0, -0.1 + 0.15 * math.cos(3 * ang), 0.0 + 0.3 * abs(t)])
        out.append(look_at(eye, target))
    return np.stack(out)


class SceneRenderer:
    """Renders the scene at a fixed size with OpenCV cameras; returns (rgb [H, W, 3] in [0, 1], depth_z)."""

    def __init__(self, width: int, height: int, seed: int = 0):
        import pyrender

        self.width, self.height = width, height
        self.scene = pyrender.Scene(bg_color=[0, 0, 0, 0], ambient_light=[1.0, 1.0, 1.0])
        for m in build_meshes(seed):
            self.scene.add(pyrender.Mesh.from_trimesh(m, smooth=False))
        self.renderer = pyrender.OffscreenRenderer(width, height)
        self._cam_node = None

    def K(self, fov_x_deg: float = 60.0) -> np.ndarray:
        f = 0.5 * self.width / math.tan(math.radians(fov_x_deg) / 2)
        return np.array([[f, 0, (self.width - 1) / 2], [0, f, (self.height - 1) / 2], [0, 0, 1.0]])

    def render(self, cam2world: np.ndarray, K: np.ndarray):
        import pyrender

        cam = pyrender.IntrinsicsCamera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2] + 0.5, cy=K[1, 2] + 0.5,
                                        znear=0.05, zfar=50.0)
        if self._cam_node is not None:
            self.scene.remove_node(self._cam_node)
        self._cam_node = self.scene.add(cam, pose=cam2world @ np.diag([1.0, -1.0, -1.0, 1.0]))
        flags = pyrender.RenderFlags.FLAT | pyrender.RenderFlags.SKIP_CULL_FACES
        rgb, depth = self.renderer.render(self.scene, flags=flags)
        return rgb.astype(np.float32) / 255.0, depth.astype(np.float32)


def perturb_pose(cam2world: np.ndarray, rot_deg: float, trans: float, rng) -> np.ndarray:
    """Rotate by exactly ``rot_deg`` about a random axis and move the centre by exactly ``trans``."""
    from pointmap.geometry import axis_angle_to_matrix

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R = axis_angle_to_matrix(torch.tensor(axis * math.radians(rot_deg))).numpy()
    d = rng.normal(size=3)
    d *= trans / np.linalg.norm(d)
    out = cam2world.copy()
    out[:3, :3] = R @ cam2world[:3, :3]
    out[:3, 3] = cam2world[:3, 3] + d
    return out


def make_benchmark_scene(width=256, height=192, n_train=4, n_test=3, depth_noise=0.01, rot_deg=1.0,
                         trans=0.02, seed=0):
    """Training views with noisy depth and perturbed poses (view 0 exact: it anchors the gauge), and
    held-out views between them. Returns a dict with a pointmap Reconstruction ``recon``, GT training
    poses ``train_c2w_gt``, held-out ``test_images`` [M, H, W, 3], ``test_c2w_gt`` and perturbed
    ``test_c2w_init`` (the start of test-time alignment), and ``K``."""
    from pointmap.reconstruction import Reconstruction

    rng = np.random.default_rng(seed)
    r = SceneRenderer(width, height, seed)
    K = r.K()
    cams = arc_cameras(n_train + n_test)
    # interleave: training views at the ends and spread, held-out views in between
    order = np.linspace(0, n_train + n_test - 1, n_train).round().astype(int)
    test_idx = [i for i in range(n_train + n_test) if i not in set(order)]
    train_c2w = cams[order]
    test_c2w = cams[test_idx]
    imgs, depths = zip(*(r.render(c, K) for c in train_c2w))
    test_imgs = [r.render(c, K)[0] for c in test_c2w]
    # r's context is left to the process's end: pyrender's teardown terminates the process's shared EGL display,
    # which would end data.render's renderer too (data/render.py)
    depth = np.stack(depths)
    noisy = depth * (1.0 + depth_noise * rng.normal(size=depth.shape)).astype(np.float32)
    noisy[depth <= 0] = 0
    c2w_init = np.stack([train_c2w[0]] + [perturb_pose(c, rot_deg, trans, rng) for c in train_c2w[1:]])
    test_init = np.stack([perturb_pose(c, rot_deg, trans, rng) for c in test_c2w])
    n = len(train_c2w)
    recon = Reconstruction(
        images=torch.tensor(np.stack(imgs)), cam2world=torch.tensor(c2w_init, dtype=torch.float32),
        K=torch.tensor(K, dtype=torch.float32).expand(n, 3, 3).clone(), depth_z=torch.tensor(noisy),
        conf=torch.ones(n, height, width) * 2.0)
    return {"recon": recon, "train_c2w_gt": torch.tensor(train_c2w, dtype=torch.float32),
            "test_images": torch.tensor(np.stack(test_imgs)),
            "test_c2w_gt": torch.tensor(test_c2w, dtype=torch.float32),
            "test_c2w_init": torch.tensor(test_init, dtype=torch.float32),
            "K": torch.tensor(K, dtype=torch.float32)}
