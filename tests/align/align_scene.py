"""An analytic test scene: cameras inside a box room with two spheres, depth by exact ray casting.

``make_scene`` gives ground-truth cameras and depth; ``gt_preds`` turns them into PairPredictions as a
perfect network would (both maps in view 1's frame, each pair at its own random scale), optionally with
noise and outliers.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import types

import numpy as np
import torch

from pointmap.images import View
from pointmap.prediction import PairPrediction

ROOM = 4.0
SPHERES = [((0.0, 0.0, 0.0), 1.0), ((1.6, 0.6, -0.4), 0.6), ((-1.2, -0.8, 1.0), 0.5)]
SCENE_SIZE = 2 * ROOM


def look_at(centre, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """OpenCV cam2world looking from ``centre`` at ``target`` (y down)."""
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, centre
    return T


def ray_cast(cam2world: np.ndarray, K: np.ndarray, h: int, w: int) -> np.ndarray:
    """z-depth [h, w] of the room + spheres."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d = d_cam @ cam2world[:3, :3].T  # world direction, scaled so that t = z-depth
    o = cam2world[:3, 3]
    t_best = np.full((h, w), np.inf)
    for axis in range(3):
        for wall in (-ROOM, ROOM):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (wall - o[axis]) / d[..., axis]
            t_best = np.where((t > 1e-6) & (t < t_best), t, t_best)
    for c, r in SPHERES:
        oc = o - np.asarray(c)
        a = (d * d).sum(-1)
        b = 2 * (d * oc).sum(-1)
        cc = oc @ oc - r * r
        disc = b * b - 4 * a * cc
        sq = np.sqrt(np.clip(disc, 0, None))
        t = (-b - sq) / (2 * a)
        t_best = np.where((disc > 0) & (t > 1e-6) & (t < t_best), t, t_best)
    return t_best


def texture(pts_world: np.ndarray) -> np.ndarray:
    """A smooth colourful texture [.., 3] in [0, 1] from world positions."""
    return 0.5 + 0.5 * np.stack([np.sin(3 * pts_world[..., 0] + 1), np.sin(2.3 * pts_world[..., 1] + 2),
                                 np.sin(2.7 * pts_world[..., 2] + 0.5 * pts_world[..., 0])], -1)


def make_scene(n: int = 5, h: int = 32, w: int = 48, seed: int = 0, focal_range=(38.0, 52.0), shapes=None,
               focals=None, aspect: float = 1.0):
    """Cameras on a ring (radius ~3) looking at the middle sphere, each with its own focal (drawn from
    ``focal_range``, or ``focals``: one per view; fy = aspect * fx, non-square pixels when aspect != 1). ``shapes``:
    one (h, w) per view (portrait among landscape); the per-view maps are then lists, not stacked arrays."""
    rng = np.random.default_rng(seed)
    shapes = shapes or [(h, w)] * n
    cams, Ks, depths = [], [], []
    for k, (h, w) in enumerate(shapes):
        ang = 2 * math.pi * k / n * 0.6 + rng.uniform(-0.1, 0.1)
        centre = np.array([3.0 * math.cos(ang), rng.uniform(-0.8, 0.8), 3.0 * math.sin(ang)])
        target = rng.uniform(-0.5, 0.5, 3)
        T = look_at(centre, target)
        f = rng.uniform(*focal_range) if focals is None else focals[k]
        K = np.array([[f, 0, (w - 1) / 2], [0, f * aspect, (h - 1) / 2], [0, 0, 1.0]])
        cams.append(T)
        Ks.append(K)
        depths.append(ray_cast(T, K, h, w))
    cam2world = np.stack(cams)
    K = np.stack(Ks)
    pts_world = [depth_to_cam(d[None], k[None])[0] @ T[:3, :3].T + T[:3, 3] for d, k, T in zip(depths, Ks, cams)]
    images = [texture(p) for p in pts_world]
    if len(set(shapes)) == 1:
        depths, pts_world, images = np.stack(depths), np.stack(pts_world), np.stack(images)
    return {"cam2world": cam2world, "K": K, "depth": depths, "pts_world": pts_world, "images": images}


def depth_to_cam(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    n, h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x = (u[None] - K[:, 0, 2, None, None]) / K[:, 0, 0, None, None] * depth
    y = (v[None] - K[:, 1, 2, None, None]) / K[:, 1, 1, None, None] * depth
    return np.stack([x, y, depth], -1)


def views_of(scene) -> list[View]:
    out = []
    for k, im in enumerate(scene["images"]):
        h, w = im.shape[:2]
        out.append(View(img=torch.from_numpy(im).permute(2, 0, 1).float(), original_size=(w, h),
                        map_from_original=(1.0, 1.0, 0.0, 0.0), name=f"img_{k:02d}.jpg", index=k))
    return out


def gt_preds(scene, pairs, *, seed: int = 0, noise: float = 0.0, outliers: float = 0.0,
             pair_rot_deg: float = 0.0, conf: float = 3.0, dtype=torch.float32) -> dict:
    """PairPredictions for (i, j) and (j, i) of every pair: exact (noise=0) or perturbed.

    noise: relative per-pixel depth-direction noise (std); outliers: fraction of pixels moved randomly by
    up to 30% of their depth (with low confidence); pair_rot_deg: per-prediction random rotation of view
    2's map about view 1 (a pose error of the 'network').
    """
    rng = np.random.default_rng(seed)
    c2w, pw = scene["cam2world"], scene["pts_world"]
    out = {}
    for a, b in pairs:
        for i, j in ((a, b), (b, a)):
            w2c = np.linalg.inv(c2w[i])
            p1 = pw[i] @ w2c[:3, :3].T + w2c[:3, 3]
            p2 = pw[j] @ w2c[:3, :3].T + w2c[:3, 3]
            c1 = np.full(p1.shape[:2], conf)
            c2 = np.full(p2.shape[:2], conf)
            if pair_rot_deg:
                axis = rng.normal(size=3)
                axis *= math.radians(pair_rot_deg) / np.linalg.norm(axis)
                Rp = torch.from_numpy(axis).double()
                from pointmap.geometry.rotations import axis_angle_to_matrix
                Rm = axis_angle_to_matrix(Rp).numpy()
                p2 = p2 @ Rm.T
            for p, c in ((p1, c1), (p2, c2)):
                if noise:
                    p *= 1 + noise * rng.standard_normal(p.shape[:2])[..., None]
                if outliers:
                    m = rng.random(p.shape[:2]) < outliers
                    p[m] *= 1 + rng.uniform(-0.3, 0.3, (int(m.sum()), 3))
                    c[m] = 1.2
                if noise or outliers:
                    c += rng.uniform(0, 1, c.shape)
            s = rng.uniform(0.3, 3.0)  # the network's unknown per-pair scale
            out[(i, j)] = PairPrediction(
                pts1_cam1=torch.from_numpy(p1 * s)[None].to(dtype), pts2_cam1=torch.from_numpy(p2 * s)[None].to(dtype),
                conf1=torch.from_numpy(c1)[None].to(dtype), conf2=torch.from_numpy(c2)[None].to(dtype))
    return out


def recon_of(scene, n: int, world_scale: float = 1.0, conf: float = 3.0):
    """A Reconstruction of the scene's first ``n`` views at their true cameras and depths, in units ``world_scale``
    times the scene's (what localisation must land its queries in)."""
    from pointmap.reconstruction import Reconstruction

    h, w = scene["depth"].shape[1:]
    recon = Reconstruction(
        images=torch.from_numpy(scene["images"][:n]).float(),
        cam2world=torch.from_numpy(scene["cam2world"][:n]).clone(), K=torch.from_numpy(scene["K"][:n]),
        depth_z=torch.from_numpy(scene["depth"][:n]).float() * world_scale, conf=torch.full((n, h, w), conf))
    recon.cam2world[:, :3, 3] *= world_scale
    return recon


def stand_in_modules(monkeypatch, calls: dict, inference: dict, matching: dict) -> None:
    """Replace the network modules ``reconstruct`` imports when it runs with stand-ins: ``pointmap.pairs`` whose
    ``make_pairs`` records the graph asked for in ``calls["graph"]`` and pairs every image with every other (the
    graph parsers are the real ones), and ``pointmap.inference`` / ``pointmap.matching`` holding the functions
    ``inference`` / ``matching`` name."""
    from pointmap.pairs import pairs_from_list, pairs_from_similarity, parse_graph

    def make_pairs(n, graph):
        calls["graph"] = graph
        return complete_pairs(n)

    pairs = {"make_pairs": make_pairs, "pairs_from_list": pairs_from_list,
             "pairs_from_similarity": pairs_from_similarity, "parse_graph": parse_graph}
    for name, fns in (("pointmap.pairs", pairs), ("pointmap.inference", inference), ("pointmap.matching", matching)):
        mod = types.ModuleType(name)
        mod.__dict__.update(fns)
        monkeypatch.setitem(sys.modules, name, mod)


def complete_pairs(n: int) -> list:
    return [(i, j) for i in range(n) for j in range(i + 1, n)]


def chain_pairs(n: int, window: int = 2) -> list:
    return [(i, j) for i in range(n) for j in range(i + 1, min(n, i + window + 1))]


def pose_errors(cam2world_est: np.ndarray, cam2world_gt: np.ndarray):
    """(max rotation error deg, max centre error / scene size, similarity) after Sim(3) on centres+rotations."""
    from pointmap.geometry.rotations import project_to_rotation

    est = torch.as_tensor(cam2world_est, dtype=torch.float64)
    gt = torch.as_tensor(cam2world_gt, dtype=torch.float64)
    Ra = project_to_rotation((gt[:, :3, :3] @ est[:, :3, :3].transpose(-1, -2)).sum(0))
    ce, cg = est[:, :3, 3], gt[:, :3, 3]
    me, mg = ce.mean(0), cg.mean(0)
    x = (ce - me) @ Ra.T
    a = float(((cg - mg) * x).sum() / (x * x).sum())
    c_al = a * x + mg
    R_al = Ra @ est[:, :3, :3]
    cos = ((R_al.transpose(-1, -2) @ gt[:, :3, :3]).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    rot = torch.rad2deg(torch.acos(cos.clamp(-1, 1)))
    centre = (c_al - cg).norm(dim=-1) / SCENE_SIZE
    return float(rot.max()), float(centre.max()), a


def with_descriptors(preds, sc, dim=24, seed=0):
    """Each pixel's descriptor: random Fourier features of its world point (what a perfect matcher would learn),
    so that coarse matches land on true correspondences where the views overlap."""
    rng = np.random.default_rng(seed)
    B = rng.normal(scale=1.5, size=(3, dim // 2))
    desc = []
    for pw in sc["pts_world"]:
        z = pw @ B
        f = np.concatenate([np.sin(z), np.cos(z)], -1)
        desc.append(torch.from_numpy(f / np.linalg.norm(f, axis=-1, keepdims=True)).float())
    out = {}
    for (i, j), p in preds.items():
        out[(i, j)] = dataclasses.replace(p, desc1=desc[i][None], desc2=desc[j][None], desc_conf1=torch.ones_like(p.conf1),
                                          desc_conf2=torch.ones_like(p.conf2))
    return out


def gt_matches(sc, i, j, step=3, outliers=0.0, seed=0, occluded: bool = False):
    """Pixels of image i on a grid and where their true 3D points land in image j: the visible ones, or with
    ``occluded`` every point in front of camera j inside its image (hidden points still obey the epipolar
    constraint); ``outliers``: that share of xy2 moved to random pixels."""
    rng = np.random.default_rng(seed)
    h, w = sc["depth"][i].shape  # image i's grid; matches land inside image j's own size
    v, u = np.mgrid[1:h:step, 1:w:step]
    h, w = sc["depth"][j].shape
    pw = sc["pts_world"][i][v, u].reshape(-1, 3)
    w2c = np.linalg.inv(sc["cam2world"][j])
    pc = pw @ w2c[:3, :3].T + w2c[:3, 3]
    K = sc["K"][j]
    uv = pc[:, :2] / pc[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
    inside = (pc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    visible = inside
    if not occluded:
        d_j = ray_cast(sc["cam2world"][j], K, h, w)
        ui, vi = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1), np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
        visible = inside & (np.abs(d_j[vi, ui] - pc[:, 2]) < 0.05 * pc[:, 2])
    xy1 = np.stack([u.reshape(-1), v.reshape(-1)], -1)[visible].astype(float)
    xy2 = uv[visible]
    if outliers:
        m = rng.random(len(xy2)) < outliers
        xy2[m] = rng.uniform([0, 0], [w - 1, h - 1], (int(m.sum()), 2))
    return xy1, xy2, np.ones(len(xy1))


def ring_matches(n: int, h: int, w: int, window: int, outliers: float, rot_deg: float, centre: float, seed: int = 0):
    """Inputs of the epipolar fit on a ring of ``n`` views (``make_scene``, focals within 10% of 0.85 w): a cyclic
    sliding-window pair graph (every image with its next ``window``), true matches on a pixel grid of each pair
    (hidden points included) with ``outliers`` of them moved to random pixels, and a start ``rot_deg`` degrees
    (a random axis per camera) and ``centre`` (normal, per coordinate) off the true poses, camera 0 exact.
    Returns (true cam2world [n, 4, 4], start [n, 4, 4], (I, J, r1, r2, scale), number of pairs); each match's scale
    is 2 px over its first camera's focal."""
    from pointmap.geometry.rotations import axis_angle_to_matrix
    from pointmap.pairs import make_pairs
    from pointmap.pose import _bearings

    f = 0.85 * w
    sc = make_scene(n, h, w, seed=seed, focal_range=(f * 0.9, f * 1.1))
    pairs = sorted(make_pairs(n, f"swin-{window}"))
    I, J, r1, r2 = [], [], [], []
    for p, (i, j) in enumerate(pairs):
        xy1, xy2, _ = gt_matches(sc, i, j, step=max(2, h // 24), outliers=outliers, seed=seed + p, occluded=True)
        I.append(np.full(len(xy1), i))
        J.append(np.full(len(xy1), j))
        r1.append(_bearings(xy1, sc["K"][i]))
        r2.append(_bearings(xy2, sc["K"][j]))
    I, J, r1, r2 = (np.concatenate(x) for x in (I, J, r1, r2))
    scale = 2.0 / sc["K"][I, 0, 0]
    rng = np.random.default_rng(seed + 1)
    start = sc["cam2world"].copy()
    for k in range(1, n):
        axis = rng.normal(size=3)
        axis *= np.radians(rot_deg) / np.linalg.norm(axis)
        start[k, :3, :3] = axis_angle_to_matrix(torch.from_numpy(axis)).numpy() @ start[k, :3, :3]
        start[k, :3, 3] += rng.normal(scale=centre, size=3)
    return sc["cam2world"], start, (I, J, r1, r2, scale), len(pairs)


class StandInNet:
    """What the pipeline and localize take for a model where a test replaces ``pointmap.inference`` with ground
    truth: it passes their model check (``decode_pair``, callable) and fails loudly if anything runs it."""

    def decode_pair(self, *args, **kwargs):
        raise AssertionError("the stand-in network was run")

    def __call__(self, *args, **kwargs):
        raise AssertionError("the stand-in network was run")


STAND_IN = StandInNet()
