"""Torch datasets over rendered shards (layout and item contract: docs/data.md).

- ``PairDataset(root, size=224, augment=True, split="train")``: items ``(view1, view2)``, dicts with
  ``img [3, H, W]`` float32 in [0, 1], ``K [3, 3]``, ``cam2world [4, 4]``, ``depth_z [H, W]``,
  ``valid [H, W]`` bool, ``pts_world [H, W, 3]``, ``pts_cam1 [H, W, 3]`` (points in view 1's camera
  frame) and, in view 1 only, ``corr [H, W, 2]`` (pixel of each view-1 pixel in view 2, NaN where not
  co-visible). Index with an int (square ``size`` x ``size`` output) or with ``(index, aspect)``
  tuples from ``AspectBatchSampler`` (one aspect ratio per batch).
- ``MultiViewDataset(root, split="all", val_percent=2.0, verify=True)``: one item per scene with all its views
  stacked as rendered (no resizing, no augmentation), for alignment and splatting evaluation.
- ``pair_views(dataset)`` / ``camera_rotations_deg(view_pairs)``: each pair's scene metadata and the angle between
  its two cameras, without decoding an image (``data.stats``, the rotation curriculum).
- ``heldout(root_dir)``: renders (once) and opens the fixed evaluation set from reserved seeds.

Augmentation (``augment=True``): random order swap, random resized crop (K, depth, valid and corr
updated consistently; depth and masks resampled with nearest neighbour; by default both views cropped at the
same scale, ``crop_link``, so a pair keeps its rendered focal ratio), colour jitter (brightness,
contrast, saturation, hue), white balance, exposure/gamma, blur and sensor noise, and with probability
``grey_p`` both views turned to grey (a monochrome camera: luma, repeated in the three channels), and with
probability ``flip_p`` the pair mirrored left-right (a mirrored world seen by mirrored cameras: images, depth and
correspondences flipped, each camera's x axis and the world's x axis reversed, so every pose stays a rotation),
and with probability ``pad_p`` each view letterboxed on its own (a band at two edges flat grey and invalid, as a
4:3, 3:2 or 16:9 photograph padded to the square input).
"""

from __future__ import annotations

import math
import warnings
import zlib
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from data.geom import decode_corr
from data.shards import ShardError, ShardReader, completed_shards, load_json, scene_metas
from pointmap.errors import ShapeError, is_int
from pointmap.geometry.rotations import relative_rotation_error_deg

SPLITS = ("train", "val", "all")


def aspect_sizes(size: int) -> list[tuple[int, int]]:
    """Training resolutions (H, W) for a long side ``size``, all multiples of 16: square, landscape
    and portrait (for 224: 224x224, 160x224, 224x160)."""
    if not isinstance(size, (int, np.integer)) or size < 32 or size % 16:
        raise ShapeError(f"size expected a multiple of 16 >= 32, got {size!r}")
    short = max(16, int(size * 5 / 7 / 16 + 0.5) * 16)
    return [(size, size), (short, size), (size, short)]


def _split_of(scene_index: int, seed: int, val_percent: float) -> str:
    h = zlib.crc32(f"{seed}:{scene_index}".encode()) % 10000
    return "val" if h < val_percent * 100 else "train"


class _ShardStore:
    """Opens shards lazily, per process (each DataLoader worker builds its own tar indexes)."""

    def __init__(self, root: Path, entries: list[dict]):
        self.root = root
        self.names = [e["name"] for e in entries]
        self._readers: dict[int, ShardReader] = {}

    def reader(self, k: int) -> ShardReader:
        r = self._readers.get(k)
        if r is None:
            r = self._readers[k] = ShardReader(self.root / self.names[k])
        return r

    def __getstate__(self):
        return {"root": self.root, "names": self.names, "_readers": {}}


def _open_root(root, verify):
    """(root, config, shard store, scenes): ``scenes`` holds ``(k, scene, meta)`` of every scene of the store's
    shards ``k`` in order. A shard that is not this run's (``completed_shards``' checks, then ``scene_metas``':
    scenes of another seed or outside the sidecar's range) is reported with a warning and left out."""
    root = Path(root)
    if not root.is_dir():
        raise ShardError(f"dataset directory {root} is {'a file' if root.exists() else 'missing'}: expected the "
                         "folder `python -m data.render` wrote")
    cfg_path = root / "config.json"
    if not cfg_path.is_file():
        raise ShardError(f"{root} has no config.json: not a directory written by `python -m data.render`")
    config = load_json(cfg_path)
    seed = config.get("seed")
    entries, _ = completed_shards(root, verify=verify, warn=True, seed=seed)
    store = _ShardStore(root, entries)
    scenes = []
    for k, entry in enumerate(entries):
        metas, problem = scene_metas(store.reader(k), entry, seed)
        if problem is not None:
            warnings.warn(f"{root}: shard skipped: {problem}; not used", stacklevel=3)
            continue
        scenes += [(k, scene, meta) for scene, meta in metas]
    store._readers.clear()
    if not scenes:
        raise ShardError(f"{root} has no complete, valid shard")
    return root, config, store, scenes


def _check_index(index, n: int, what: str, item) -> None:
    """An item's index: an int (not a bool: docs/conventions.md) in [-n, n); TypeError or IndexError naming ``item``
    (the whole item asked for) otherwise."""
    if not is_int(index):
        raise TypeError(f"index expected an int, got {type(index).__name__} {index!r}"
                        + ("" if item is index else f" in item {item!r}"))
    if not -n <= index < n:
        raise IndexError(f"index {index} out of range for {n} {what}" + ("" if item is index else f" in item {item!r}"))


def _load_view(reader: ShardReader, scene: str, meta: dict, k: int):
    rgb = reader.read_png(f"{scene}/view-{k}.png")
    depth = reader.read_npz(f"{scene}/view-{k}.npz")["depth_z"]
    v = meta["views"][k]
    return rgb, depth, np.array(v["K"], np.float64), np.array(v["cam2world"], np.float64)


# ---------------------------------------------------------------------------------------------------
# augmentation helpers (numpy, per view)


def _crop_box(rng, src_w, src_h, out_w, out_h, scale_range, center=False, width=None):
    """A crop (x0, y0, cw, ch) of the source with the output's aspect ratio, ``width`` source pixels wide
    (default: the largest such crop times the square root of a draw from ``scale_range``, an area
    fraction)."""
    ar = out_w / out_h
    max_w = min(src_w, src_h * ar)
    cw = max_w if center else (max_w * math.sqrt(rng.uniform(*scale_range)) if width is None else width)
    ch = cw / ar
    if center:
        return (src_w - cw) / 2, (src_h - ch) / 2, cw, ch
    return rng.uniform(0, src_w - cw), rng.uniform(0, src_h - ch), cw, ch


def _apply_crop(rgb, depth, K, box, out_w, out_h):
    """Crop + resize with the exact K update. The box (x0, y0, cw, ch) is in edge coordinates (pixel
    i spans [i, i + 1]); output pixel centre u' samples source u = (u' + 0.5) * cw / out_w + x0 - 0.5.
    Returns (rgb, depth, K, A) with A [2, 3] mapping source pixel coordinates to output ones."""
    x0, y0, cw, ch = box
    sx, sy = out_w / cw, out_h / ch
    A = np.array([[sx, 0, (0.5 - x0) * sx - 0.5], [0, sy, (0.5 - y0) * sy - 0.5]], np.float64)  # src -> dst
    if abs(sx - 1) < 1e-9 and abs(sy - 1) < 1e-9 and float(x0).is_integer() and float(y0).is_integer():
        x0i, y0i = int(x0), int(y0)
        rgb2 = rgb[y0i:y0i + out_h, x0i:x0i + out_w]
        depth2 = depth[y0i:y0i + out_h, x0i:x0i + out_w]
    else:
        src = rgb
        if min(sx, sy) < 0.8:  # anti-alias before shrinking
            sigma = 0.45 / min(sx, sy)
            src = cv2.GaussianBlur(rgb, (0, 0), sigmaX=sigma)
        rgb2 = cv2.warpAffine(src, A, (out_w, out_h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        depth2 = cv2.warpAffine(depth, A, (out_w, out_h), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                                borderValue=0)
    K2 = K.copy()
    K2[0, 0] *= sx
    K2[1, 1] *= sy
    K2[0, 2] = A[0, 0] * K[0, 2] + A[0, 2]
    K2[1, 2] = A[1, 1] * K[1, 2] + A[1, 2]
    return np.ascontiguousarray(rgb2), np.ascontiguousarray(depth2), K2, A


def _warp_corr(corr, A1, A2, out_w, out_h, src_h, src_w):
    """Resample view 1's corr with view 1's crop (nearest) and map its values through view 2's crop."""
    if np.allclose(A1, [[1, 0, 0], [0, 1, 0]]) and corr.shape[:2] == (out_h, out_w):
        c = corr.copy()
    else:
        c = cv2.warpAffine(corr, A1, (out_w, out_h), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=(np.nan, np.nan))
    out = np.empty_like(c)
    out[..., 0] = A2[0, 0] * c[..., 0] + A2[0, 2]
    out[..., 1] = A2[1, 1] * c[..., 1] + A2[1, 2]
    return out


def _geometric_corr(corr, d1, K1, T1, d2, K2, T2, rel_tol: float = 0.05):
    """View 1's correspondences recomputed from its cropped depth, intrinsics and pose where ``corr`` (resampled
    with the crop) says a pixel is co-visible: the projection into view 2 of the very point view 1's pointmap
    target holds at each pixel. Resampling the stored field itself gave each output pixel the match of the source
    pixel nearest to where it samples, up to half a source pixel (two output pixels after a 2x crop) away
    (median 0.49 px off on ``train_p39``). A pixel whose point lands where view 2's depth disagrees by more than
    ``rel_tol`` (an occlusion edge, where depth and correspondence resampling picked different source pixels) is
    left out, and so is one from a pixel without depth or landing outside view 2 or on a pixel without depth.
    corr [H1, W1, 2] view-2 pixels (u, v; NaN: none) -> the same, float32; d1 [H1, W1], d2 [H2, W2] z-depth (0: none);
    K1, K2 [3, 3] in the cropped images' pixels (centres at integers); T1, T2 [4, 4] OpenCV cam2world."""
    ok = np.isfinite(corr).all(-1) & (d1 > 0)
    T = _inv(T2) @ T1
    P = _unproject(d1, K1) @ T[:3, :3].T + T[:3, 3]
    z = P[..., 2]
    ok &= z > 1e-9
    z = np.where(ok, z, 1.0)
    u = K2[0, 0] * P[..., 0] / z + K2[0, 2]
    v = K2[1, 1] * P[..., 1] / z + K2[1, 2]
    h2, w2 = d2.shape
    with np.errstate(invalid="ignore"):
        ok &= (u > -0.5) & (u < w2 - 0.5) & (v > -0.5) & (v < h2 - 0.5)
    out = np.stack([np.where(ok, u, np.nan), np.where(ok, v, np.nan)], -1).astype(np.float32)
    ui, vi = _landing_pixel(out, w2, h2)
    dz = d2[vi, ui].astype(np.float64)
    out[~(ok & (dz > 0) & (np.abs(dz - z) <= rel_tol * z))] = np.nan
    return out


def _landing_pixel(corr, out_w, out_h):
    """(ui, vi) int64 [H, W]: the view-2 pixel each view-1 correspondence lands on (rounded, clipped into the
    image; NaN read as 0, so mask those out with ``np.isfinite(corr)``)."""
    ui = np.clip(np.rint(np.nan_to_num(corr[..., 0])), 0, out_w - 1).astype(np.int64)
    vi = np.clip(np.rint(np.nan_to_num(corr[..., 1])), 0, out_h - 1).astype(np.int64)
    return ui, vi


def _photometric(rng, rgb):
    x = rgb.astype(np.float32) / 255.0
    if rng.random() < 0.8:  # colour jitter
        x = x * rng.uniform(0.7, 1.3)                                         # brightness
        m = x.mean()
        x = (x - m) * rng.uniform(0.7, 1.3) + m                               # contrast
        g = x.mean(-1, keepdims=True)
        x = g + (x - g) * rng.uniform(0.6, 1.4)                               # saturation
        if rng.random() < 0.3:                                                # hue: rotate about grey axis
            a = rng.uniform(-0.3, 0.3)
            k = np.ones(3, np.float32) / math.sqrt(3)
            c, s = math.cos(a), math.sin(a)
            Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], np.float32)
            R = c * np.eye(3, dtype=np.float32) + s * Kx + (1 - c) * np.outer(k, k)
            x = x @ R.T
    if rng.random() < 0.3:   # white balance
        x = x * rng.uniform(0.85, 1.15, 3).astype(np.float32)
    if rng.random() < 0.3:   # exposure / gamma
        x = np.clip(x, 0, None) ** rng.uniform(0.7, 1.4)
    if rng.random() < 0.15:  # defocus / motion-ish blur
        k = int(rng.choice([3, 5]))
        x = cv2.GaussianBlur(x, (k, k), 0)
    if rng.random() < 0.25:  # sensor noise
        x = x + rng.normal(0, rng.uniform(0.005, 0.03), x.shape).astype(np.float32)
    return np.clip(x, 0, 1).astype(np.float32)


def _grey(x):
    """An RGB float image [H, W, 3] as a monochrome camera sees it: OpenCV's luma (0.299 R + 0.587 G + 0.114 B)
    in all three channels."""
    g = cv2.cvtColor(np.ascontiguousarray(x, np.float32), cv2.COLOR_RGB2GRAY)
    return np.repeat(g[..., None], 3, axis=-1)


_REFLECT_X = np.diag([-1.0, 1.0, 1.0, 1.0])


def _mirror(rgb_f, depth, K, cam2world):
    """One view of the left-right mirrored scene. Pixel u (centres at integers) goes to w - 1 - u, so the
    principal point does too; the camera's x axis is reversed (x -> -x matches the flipped column) and so is the
    world's: cam2world -> F @ cam2world @ F with F = diag(-1, 1, 1, 1), a rotation again (two reflections)."""
    w = depth.shape[1]
    K = K.copy()
    K[0, 2] = (w - 1) - K[0, 2]
    K[0, 1] = -K[0, 1]  # a skew term changes sign with x
    return (np.ascontiguousarray(rgb_f[:, ::-1]), np.ascontiguousarray(depth[:, ::-1]), K,
            _REFLECT_X @ cam2world @ _REFLECT_X)


# the photographs' aspect ratios a letterboxed view stands in for: the share of the square its content keeps
LETTERBOX_KEEP = (3 / 4, 2 / 3, 9 / 16)  # 4:3, 3:2, 16:9


def _letterbox(rng, rgb_f, depth):
    """One view letterboxed as a photograph of another aspect ratio would be on a square input: a band at two
    opposite edges (rows: a landscape photograph; columns: a portrait one; whole pixels, centred as
    ``load_images`` centres) replaced by one grey level, drawn in [0, 1], with no depth there (invalid: no
    pointmap loss, no correspondence). The camera is unchanged: the content is the same pixels, fewer of them.
    Returns (rgb, depth, kept) with ``kept`` [H, W] bool, False on the pad."""
    h, w = depth.shape
    keep = LETTERBOX_KEEP[rng.integers(len(LETTERBOX_KEEP))]
    rows = rng.random() < 0.5  # pad rows (a landscape photograph) or columns (a portrait one)
    side = h if rows else w
    pad = (side - round(side * keep)) // 2
    kept = np.ones((h, w), bool)
    if pad > 0:
        if rows:
            kept[:pad], kept[h - pad:] = False, False
        else:
            kept[:, :pad], kept[:, w - pad:] = False, False
    rgb_f, depth = rgb_f.copy(), depth.copy()
    rgb_f[~kept] = np.float32(rng.random())
    depth[~kept] = 0
    return rgb_f, depth, kept


def _to_view(rgb_f, depth, K, cam2world, world2cam1):
    pts_cam = _unproject(depth, K)
    valid = depth > 0
    pts_world = pts_cam @ cam2world[:3, :3].T + cam2world[:3, 3]
    pts_cam1 = pts_world @ world2cam1[:3, :3].T + world2cam1[:3, 3]
    pts_world[~valid] = 0
    pts_cam1[~valid] = 0
    return {
        "img": torch.from_numpy(np.ascontiguousarray(rgb_f.transpose(2, 0, 1))),
        "K": torch.from_numpy(K.astype(np.float32)),
        "cam2world": torch.from_numpy(cam2world.astype(np.float32)),
        "depth_z": torch.from_numpy(depth.astype(np.float32)),
        "valid": torch.from_numpy(valid),
        "pts_world": torch.from_numpy(pts_world.astype(np.float32)),
        "pts_cam1": torch.from_numpy(pts_cam1.astype(np.float32)),
    }


def _unproject(depth, K):
    h, w = depth.shape
    x = (np.arange(w) - K[0, 2]) / K[0, 0]
    y = (np.arange(h) - K[1, 2]) / K[1, 1]
    d = depth.astype(np.float64)
    return np.stack([x[None, :] * d, y[:, None] * d, d], -1)


def _inv(T):
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def pair_views(dataset):
    """``(scene metadata, i, j)`` of every pair of a PairDataset (or anything with its ``items`` and shard store), in
    item order: the pair is views ``meta["views"][i]`` and ``[j]``. Reads metadata only, no image is decoded."""
    for k, scene, i, j in dataset.items:
        yield dataset._store.reader(k).meta(scene), i, j


def camera_rotations_deg(view_pairs) -> np.ndarray:
    """Angle in degrees of the rotation between the two cameras of each ``(view i, view j)`` metadata pair (the
    angle ``training.evaluate`` bins pairs by); float64 [N]."""
    rot = [(np.asarray(vi["cam2world"], np.float64)[:3, :3], np.asarray(vj["cam2world"], np.float64)[:3, :3])
           for vi, vj in view_pairs]
    if not rot:
        return np.zeros(0)
    R1, R2 = (torch.from_numpy(np.stack(r)) for r in zip(*rot))
    return relative_rotation_error_deg(R1, R2).numpy()


class PairDataset(Dataset):
    """Pairs from shards written with ``--kind pairs`` (see module docstring for the item layout).

    root: dataset directory. size: long side of the output (multiple of 16). augment: random
    augmentation (off: deterministic centre crop + resize only when the rendered size differs).
    split: "train", "val" (a fixed ~``val_percent`` % of scenes, chosen by hashing the scene id) or
    "all". verify: check every shard's sha256 before use (shards that fail are reported and skipped).
    crop_link: probability that view 2's random crop has view 1's scale (its position stays random): a crop
    rescales the focal length, so independent crops of two views make a pair whose focal lengths differ by up
    to 1.4x, and a zoom-in then looks like a step forward. Linked, the pair keeps the focal ratio it was
    rendered with (the data engine's ``--same-camera-share`` decides how often that is 1), and the image
    magnification between the views tells the camera's forward motion (docs/data.md).
    grey_p: probability that an augmented pair is seen by a monochrome camera (both views' luma in all three
    channels, after the colour augmentation; 0 draws nothing, so the other augmentations stay as they were).
    flip_p: probability that an augmented pair is mirrored left-right (``_mirror``; drawn last, 0 draws nothing): the
    mirrored pair is a valid pair of a mirrored scene, with the same pair geometry up to the reflection.
    pad_p: probability that each view of an augmented pair, on its own, is letterboxed (``_letterbox``: a band at
    two edges flat grey and invalid, as a 4:3, 3:2 or 16:9 photograph padded to the square; drawn last, 0 draws
    nothing; square items only: the other aspect ratios' items are photographs' own shapes already): models trained without it lose 12-16 points of RRA@15 on padded input (benchmarks/bench_letterbox.py).
    """

    def __init__(self, root, size: int = 224, augment: bool = True, split: str = "train", *,
                 val_percent: float = 2.0, crop_scale=(0.5, 1.0), swap_p: float = 0.5, crop_link: float = 1.0,
                 grey_p: float = 0.0, flip_p: float = 0.0, pad_p: float = 0.0, verify: bool = True):
        if split not in SPLITS:
            raise ValueError(f"split expected one of {SPLITS}, got {split!r}")
        if not 0 <= val_percent <= 100:
            raise ValueError(f"val_percent expected in [0, 100], got {val_percent}")
        lo, hi = crop_scale
        if not 0 < lo <= hi <= 1:
            raise ValueError(f"crop_scale expected 0 < lo <= hi <= 1, got {crop_scale}")
        self.aspects = aspect_sizes(size)
        self.size = size
        self.augment = bool(augment)
        self.crop_scale = (float(lo), float(hi))
        if not 0 <= swap_p <= 1:  # also NaN
            raise ValueError(f"swap_p expected a probability in [0, 1], got {swap_p}")
        self.swap_p = float(swap_p)
        if not 0 <= crop_link <= 1:
            raise ValueError(f"crop_link expected a probability in [0, 1], got {crop_link}")
        self.crop_link = float(crop_link)
        if not 0 <= grey_p <= 1:
            raise ValueError(f"grey_p expected a probability in [0, 1], got {grey_p}")
        self.grey_p = float(grey_p)
        if not 0 <= flip_p <= 1:
            raise ValueError(f"flip_p expected a probability in [0, 1], got {flip_p}")
        self.flip_p = float(flip_p)
        if not 0 <= pad_p <= 1:
            raise ValueError(f"pad_p expected a probability in [0, 1], got {pad_p}")
        self.pad_p = float(pad_p)
        self.root, self.config, self._store, scenes = _open_root(root, verify)
        if self.config.get("kind") != "pairs":
            raise ShardError(f"{self.root} was rendered with --kind {self.config.get('kind')}; PairDataset needs "
                             "--kind pairs (MultiViewDataset reads view sets)")
        seed = int(self.config.get("seed", 0))
        items = []
        for k, scene, meta in scenes:
            if split != "all" and _split_of(meta["scene"], seed, val_percent) != split:
                continue
            for i, j in meta["pairs"]:
                items.append((k, scene, i, j))
        self.items = items
        if not items:
            raise ShardError(f"{self.root}: no pairs in split {split!r}")
        self._rng = None
        self._rng_seed = None

    def __len__(self):
        return len(self.items)

    def _get_rng(self):
        seed = torch.initial_seed()
        if self._rng is None or self._rng_seed != seed:
            self._rng = np.random.default_rng(seed % (2**63))
            self._rng_seed = seed
        return self._rng

    item_seeds = True  # items may carry their augmentation's seed (training.loop.StepBatches)

    def __getitem__(self, index):
        """``index``, ``(index, aspect)`` or ``(index, aspect, seed)``: with a seed (a tuple of ints >= 0) the
        augmentation is drawn from ``np.random.default_rng(seed)``, a function of it alone; without, from a stream
        seeded by the process's torch seed."""
        seed = None
        item = index
        if isinstance(index, tuple):
            if len(index) not in (2, 3):
                raise IndexError(f"an item expected (index, aspect) or (index, aspect, seed), got {len(index)} "
                                 f"entries: {item!r}")
            index, aspect, *rest = index
            if not is_int(aspect):
                raise TypeError(f"aspect index expected an int, got {aspect!r} in item {item!r}")
            if not 0 <= aspect < len(self.aspects):
                raise IndexError(f"aspect index expected in [0, {len(self.aspects)}), got {aspect} in item {item!r}")
            if rest:
                seed = rest[0]
                if not (isinstance(seed, (tuple, list)) and seed and all(is_int(v) and v >= 0 for v in seed)):
                    raise TypeError(f"an item's seed expected a tuple of ints >= 0, got {seed!r} in item {item!r}")
                seed = tuple(int(v) for v in seed)
        else:
            aspect = 0
        _check_index(index, len(self), "pairs", item)
        out_h, out_w = self.aspects[aspect]
        k, scene, i, j = self.items[index]
        reader = self._store.reader(k)
        meta = reader.meta(scene)
        corr_pack = reader.read_npz(f"{scene}/pair-{i}-{j}.npz")
        corr = decode_corr(corr_pack["corr_12"])
        rng = (np.random.default_rng(seed) if seed is not None else self._get_rng()) if self.augment else None
        if self.augment and rng.random() < self.swap_p:
            i, j = j, i
            corr = decode_corr(corr_pack["corr_21"])
        rgb1, d1, K1, T1 = _load_view(reader, scene, meta, i)
        rgb2, d2, K2, T2 = _load_view(reader, scene, meta, j)
        h, w = d1.shape
        box1 = _crop_box(rng, w, h, out_w, out_h, self.crop_scale, center=not self.augment)
        rgb1, d1, K1, A1 = _apply_crop(rgb1, d1, K1, box1, out_w, out_h)
        link = self.augment and (self.crop_link >= 1
                                 or (self.crop_link > 0 and rng.random() < self.crop_link))
        box2 = _crop_box(rng, w, h, out_w, out_h, self.crop_scale, center=not self.augment,
                         width=box1[2] if link else None)
        if self.augment:  # centre view 2's crop on where view 1's crop content lands, so they overlap
            x0, y0, cw, ch = box2
            seen = _warp_corr(corr, A1, np.array([[1.0, 0, 0], [0, 1.0, 0]]), out_w, out_h, h, w)
            seen = seen[np.isfinite(seen).all(-1)]
            if len(seen):
                cu, cv = np.median(seen, 0) + 0.5 + rng.normal(0, 0.15, 2) * (cw, ch)
                x0 = float(np.clip(cu - cw / 2, 0, w - cw))
                y0 = float(np.clip(cv - ch / 2, 0, h - ch))
                box2 = (x0, y0, cw, ch)
        rgb2, d2, K2, A2 = _apply_crop(rgb2, d2, K2, box2, out_w, out_h)
        # a correspondence survives only if it lands inside view 2's crop on a pixel with depth (checked there)
        corr = _geometric_corr(_warp_corr(corr, A1, A2, out_w, out_h, h, w), d1, K1, T1, d2, K2, T2)
        if self.augment:
            f1, f2 = _photometric(rng, rgb1), _photometric(rng, rgb2)
            if self.grey_p > 0 and rng.random() < self.grey_p:
                f1, f2 = _grey(f1), _grey(f2)
            if self.flip_p > 0 and rng.random() < self.flip_p:
                (f1, d1, K1, T1), (f2, d2, K2, T2) = _mirror(f1, d1, K1, T1), _mirror(f2, d2, K2, T2)
                corr = corr[:, ::-1].copy()
                corr[..., 0] = (out_w - 1) - corr[..., 0]
            if self.pad_p > 0 and out_h == out_w:  # each view letterboxed on its own (drawn last, 0 draws nothing;
                # a square input: what load_images' 224 crop would pad a photograph of another shape to)
                if rng.random() < self.pad_p:
                    f1, d1, kept1 = _letterbox(rng, f1, d1)
                    corr[~kept1] = np.nan
                if rng.random() < self.pad_p:
                    f2, d2, kept2 = _letterbox(rng, f2, d2)
                    ui, vi = _landing_pixel(corr, out_w, out_h)
                    corr[np.isfinite(corr).all(-1) & ~kept2[vi, ui]] = np.nan
        else:
            f1, f2 = rgb1.astype(np.float32) / 255.0, rgb2.astype(np.float32) / 255.0
        w2c1 = _inv(T1)
        view1 = _to_view(f1, d1, K1, T1, w2c1)
        view2 = _to_view(f2, d2, K2, T2, w2c1)
        view1["corr"] = torch.from_numpy(np.ascontiguousarray(corr, np.float32))
        for v_, idx in ((view1, i), (view2, j)):
            v_["scene"] = f"{meta['seed']}:{meta['scene']}"
            v_["view_index"] = idx
        return view1, view2


class AspectBatchSampler(Sampler):
    """Batches of ``(index, aspect)`` tuples with one aspect ratio per batch (shuffled, seeded; call
    ``set_epoch`` for a new order each epoch)."""

    def __init__(self, dataset_len: int, batch_size: int, n_aspects: int = 3, *, shuffle: bool = True,
                 seed: int = 0, drop_last: bool = True, weights=None):
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1
                   for v in (dataset_len, batch_size, n_aspects)):
            raise ValueError(f"AspectBatchSampler expected positive int sizes, got len={dataset_len!r}, "
                             f"batch_size={batch_size!r}, n_aspects={n_aspects!r}")
        self.n, self.bs, self.na = int(dataset_len), int(batch_size), int(n_aspects)
        self.shuffle, self.seed, self.drop_last = shuffle, int(seed), drop_last
        w = np.ones(n_aspects) if weights is None else np.asarray(weights, np.float64)
        if w.shape != (n_aspects,) or not np.isfinite(w).all() or w.min() < 0 or w.sum() <= 0:
            raise ValueError(f"weights expected {n_aspects} non-negative numbers, got {weights!r}")
        self.p = w / w.sum()
        self.epoch = 0

    def set_epoch(self, epoch: int):
        self.epoch = int(epoch)

    def __len__(self):
        return self.n // self.bs if self.drop_last else math.ceil(self.n / self.bs)

    def __iter__(self):
        rng = np.random.default_rng([self.seed, self.epoch])
        order = rng.permutation(self.n) if self.shuffle else np.arange(self.n)
        for b in range(len(self)):
            idx = order[b * self.bs:(b + 1) * self.bs]
            a = int(rng.choice(self.na, p=self.p))
            yield [(int(i), a) for i in idx]


class MultiViewDataset(Dataset):
    """One item per scene: ``img [N, 3, H, W]``, ``K [N, 3, 3]``, ``cam2world [N, 4, 4]``,
    ``depth_z [N, H, W]``, ``valid [N, H, W]``, ``overlap [N, N]`` (fraction of view i's pixels seen by
    view j) and ``scene`` (id string). Images are as rendered (no augmentation); works on shards of
    either kind."""

    def __init__(self, root, *, split: str = "all", val_percent: float = 2.0, verify: bool = True):
        if not 0 <= val_percent <= 100:  # NaN fails too (as PairDataset's)
            raise ValueError(f"val_percent expected in [0, 100], got {val_percent}")
        if split not in SPLITS:
            raise ValueError(f"split expected one of {SPLITS}, got {split!r}")
        self.root, self.config, self._store, scenes = _open_root(root, verify)
        seed = int(self.config.get("seed", 0))
        self.items = []
        for k, scene, _ in scenes:
            idx = int(scene.split("-")[1])
            if split == "all" or _split_of(idx, seed, val_percent) == split:
                self.items.append((k, scene))
        if not self.items:
            raise ShardError(f"{self.root}: no scenes in split {split!r}")

    def __len__(self):
        return len(self.items)

    def __getitem__(self, index):
        _check_index(index, len(self), "scenes", index)
        k, scene = self.items[index]
        reader = self._store.reader(k)
        meta = reader.meta(scene)
        imgs, depths, Ks, Ts = [], [], [], []
        for v in range(len(meta["views"])):
            rgb, d, K, T = _load_view(reader, scene, meta, v)
            imgs.append(rgb.transpose(2, 0, 1).astype(np.float32) / 255.0)
            depths.append(d)
            Ks.append(K)
            Ts.append(T)
        depth = np.stack(depths).astype(np.float32)
        return {
            "img": torch.from_numpy(np.stack(imgs)), "K": torch.from_numpy(np.stack(Ks).astype(np.float32)),
            "cam2world": torch.from_numpy(np.stack(Ts).astype(np.float32)), "depth_z": torch.from_numpy(depth),
            "valid": torch.from_numpy(depth > 0), "overlap": torch.tensor(meta["overlap"], dtype=torch.float32),
            "scene": f"{meta['seed']}:{meta['scene']}", "kind": meta["kind"],
        }


def collate_pairs(batch):
    """Collate ``(view1, view2)`` items into two dicts of batched tensors (strings become lists)."""
    out = []
    for side in range(2):
        views = [b[side] for b in batch]
        d = {}
        for key in views[0]:
            vals = [v[key] for v in views]
            d[key] = torch.stack(vals) if isinstance(vals[0], torch.Tensor) else vals
        out.append(d)
    return tuple(out)
