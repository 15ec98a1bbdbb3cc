"""Outputs of ``pointmap pair``: npz with everything, a coloured PLY, PNG previews."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pointmap.atomic import atomic_path
from pointmap.errors import ShapeError


def color_range(*maps_and_masks) -> tuple[float, float]:
    """One robust (2-98 %) value range over several (map, valid-mask-or-None) pairs, so that maps drawn
    with it share their colours. Masked-out and non-finite values do not count; (0, 1) if none is left."""
    vals = [x[np.isfinite(x) if m is None else m & np.isfinite(x)] for x, m in maps_and_masks]
    v = np.concatenate([a.ravel() for a in vals]) if vals else np.zeros(0)
    return (float(np.percentile(v, 2)), float(np.percentile(v, 98))) if v.size else (0.0, 1.0)


def colorize(x: np.ndarray, valid: np.ndarray | None = None, value_range: tuple | None = None) -> np.ndarray:
    """Float map -> uint8 RGB with a perceptual colour map over ``value_range`` (default: the map's own robust
    2-98 % range; pass one ``color_range`` to several maps to make their colours comparable)."""
    import cv2

    lo, hi = value_range if value_range is not None else color_range((x, valid))
    norm = np.clip((x - lo) / max(hi - lo, 1e-12), 0, 1)
    img = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    if valid is not None:
        img = img * valid[..., None]
    return np.ascontiguousarray(img)


def draw_matches(img1: np.ndarray, img2: np.ndarray, xy1: np.ndarray, xy2: np.ndarray, n: int = 80) -> np.ndarray:
    import cv2

    h = max(img1.shape[0], img2.shape[0])
    canvas = np.zeros((h, img1.shape[1] + img2.shape[1], 3), np.uint8)
    canvas[: img1.shape[0], : img1.shape[1]] = img1
    canvas[: img2.shape[0], img1.shape[1]:] = img2
    if len(xy1):
        sel = np.linspace(0, len(xy1) - 1, min(n, len(xy1))).astype(int)
        rng = np.random.default_rng(0)
        for k in sel:
            c = tuple(int(x) for x in rng.integers(64, 255, 3))
            p1 = (int(xy1[k, 0]), int(xy1[k, 1]))
            p2 = (int(xy2[k, 0]) + img1.shape[1], int(xy2[k, 1]))
            cv2.line(canvas, p1, p2, c, 1, cv2.LINE_AA)
            cv2.circle(canvas, p1, 2, c, -1)
            cv2.circle(canvas, p2, 2, c, -1)
    return canvas


def write_png(path: Path, rgb: np.ndarray) -> Path:
    import cv2

    path = Path(path).with_suffix(".png")
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
            raise OSError(f"cannot write {path}")
    return path


PAIR_OUTPUTS = ("pair.npz", "pair.ply", "depth1.png", "depth2.png", "conf1.png", "conf2.png", "matches.png")


def write_pair_outputs(model, path1, path2, out: str | Path, *, size: int = 512, quiet: bool = False,
                       focal: tuple | None = None, shared_focal: bool = False, device="cpu") -> list[Path]:
    """Pointmaps, matches, relative pose and focals of two images into ``out`` (pair.npz, pair.ply, PNG previews:
    depth1.png and depth2.png are the z of each view's points in camera 1's frame, on one colour scale, so
    depth2.png is view 2's depth only where the cameras look alike; conf1/conf2.png the log confidences;
    matches.png the matches).

    The pose is ``pointmap.pose.pair_pose``: the pointmaps' pose refined on the model's own matches (rotation and
    translation direction; models with descriptors) with each view's focal from its own pointmap, or with
    ``focal``: the known focal lengths (f1, f2) in ORIGINAL pixels (principal points at the image centres), which
    are then stored instead of the estimated ones; or with ``shared_focal`` (two photographs of one camera, of one
    size): one estimated focal for both, the geometric mean of the two (on one-camera held-out pairs, 56 -> 63
    translation directions within 15 degrees of 140, docs/models.md; each view's own when one has none).
    ``device``: where the model runs (it must already be there, ``pm.load_model(..., device=)``); the outputs come
    back to the CPU."""
    import trimesh

    from pointmap.errors import check_model_device
    from pointmap.images import load_images
    from pointmap.matching import match
    from pointmap.pose import focal_from_prediction, pair_pose, relative_pose
    from pointmap.reconstruction import K_to_map

    if focal is not None:
        given = focal
        try:
            focal = tuple(float(f) for f in focal)
        except (TypeError, ValueError):  # one number, a string: said with what was given
            raise ShapeError(f"focal expected two positive focal lengths in pixels (f1, f2), got {given!r}") from None
        if len(focal) != 2 or not all(np.isfinite(f) and f > 0 for f in focal):
            raise ShapeError(f"focal expected two positive focal lengths in pixels (f1, f2), got {focal}")
    if not isinstance(shared_focal, bool) or (shared_focal and focal is not None):
        raise ShapeError(f"shared_focal expected True or False, and False with a focal given, got {shared_focal!r} "
                         f"with focal {focal!r}")
    if not isinstance(out, (str, Path)):
        raise ShapeError(f"out expected a folder path, got {type(out).__name__}")
    out = Path(out)
    device = check_model_device(model, device, "write_pair_outputs")
    views = load_images([path1, path2], size=size)
    if shared_focal and (views[0].original_size, views[0].map_from_original) != (views[1].original_size,
                                                                                   views[1].map_from_original):
        raise ShapeError(f"shared_focal expected two photographs of one camera, of one size; got "
                         f"{views[0].original_size} and {views[1].original_size} (w, h)")
    if views[0].img.shape == views[1].img.shape and torch.equal(views[0].img, views[1].img):
        import warnings

        warnings.warn(f"write_pair_outputs: {views[0].name} and {views[1].name} are the same image: no baseline, so "
                      "the relative pose's translation direction is meaningless (the pointmaps still are a depth "
                      "estimate)", stacklevel=2)
    img1, img2 = views[0].img[None].to(device), views[1].img[None].to(device)
    with torch.inference_mode():
        pred = model(img1, img2)
        pred_rev = model(img2, img1)
    pred, pred_rev = pred.map(lambda t: t.float().cpu()), pred_rev.map(lambda t: t.float().cpu())
    m = match(pred)
    patch = getattr(getattr(model, "cfg", None), "patch_size", 16)
    if focal is None:
        focal1 = focal_from_prediction(pred)[0]
        focal2 = focal_from_prediction(pred_rev)[0]
        K = None
        if shared_focal and bool(torch.isfinite(focal1 * focal2)) and float(focal1 * focal2) > 0:
            from pointmap.geometry.cameras import intrinsics

            focal1 = focal2 = (focal1 * focal2).sqrt()
            H, W = pred.pts1_cam1.shape[1:3]
            K = [intrinsics(float(focal1), (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)] * 2
    else:
        K = []
        for f, v in zip(focal, views):
            W, H = v.original_size
            K_orig = torch.tensor([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], dtype=torch.float64)
            K.append(K_to_map(K_orig, torch.tensor(v.map_from_original, dtype=torch.float64)))
        focal1, focal2 = K[0][0, 0].float(), K[1][0, 0].float()
    pointmap_pose = relative_pose(pred, pred_reverse=pred_rev)[0]
    cam2world_2 = pair_pose(pred, pred_rev, *(K or (None, None)), patch=patch, pose=pointmap_pose[None],
                            rotation_prior_deg=None if focal is not None else 3.0)[0]  # 3: an estimated focal's
    refined_on_matches = bool(torch.isfinite(pointmap_pose).all()) and not torch.equal(cam2world_2, pointmap_pose)
    out.mkdir(parents=True, exist_ok=True)
    rgb1 = (views[0].img.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    rgb2 = (views[1].img.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    arrays = dict(pts1_cam1=pred.pts1_cam1[0].numpy(), pts2_cam1=pred.pts2_cam1[0].numpy(),
                  conf1=pred.conf1[0].numpy(), conf2=pred.conf2[0].numpy(), img1=rgb1, img2=rgb2,
                  matches_xy1=m.xy1.numpy(), matches_xy2=m.xy2.numpy(), matches_score=m.score.numpy(),
                  cam2world_2_in_1=cam2world_2.numpy(),
                  # the focals in each ORIGINAL image's pixels (DESIGN: reported intrinsics are the user's images');
                  # times map_from_original[0] they are the maps' (the pointmaps' pixel grid)
                  focal1=(focal1 / views[0].map_from_original[0]).numpy(),
                  focal2=(focal2 / views[1].map_from_original[0]).numpy(), focal_units=np.array("original"),
                  focal_given=np.array(focal is not None), focal_shared=np.array(K is not None and focal is None),
                  refined_on_matches=np.array(refined_on_matches),
                  map_from_original1=np.array(views[0].map_from_original),
                  map_from_original2=np.array(views[1].map_from_original))
    with atomic_path(out / "pair.npz") as tmp:
        np.savez_compressed(tmp, **arrays)
    written = [out / "pair.npz"]
    conf_all = np.concatenate([arrays["conf1"].ravel(), arrays["conf2"].ravel()])
    thr = np.percentile(conf_all, 30)
    keep1, keep2 = arrays["conf1"] >= thr, arrays["conf2"] >= thr
    pts = np.concatenate([arrays["pts1_cam1"][keep1], arrays["pts2_cam1"][keep2]])
    cols = np.concatenate([rgb1[keep1], rgb2[keep2]])
    cloud = trimesh.PointCloud(pts, colors=np.concatenate([cols, np.full((len(cols), 1), 255, np.uint8)], 1))
    with atomic_path(out / "pair.ply") as tmp:
        cloud.export(str(tmp), file_type="ply")
    written.append(out / "pair.ply")
    depth1, depth2 = arrays["pts1_cam1"][..., 2], arrays["pts2_cam1"][..., 2]
    depth_range = color_range((depth1, None), (depth2, None))  # both in view 1's frame: one scale
    written.append(write_png(out / "depth1", colorize(depth1, value_range=depth_range)))
    written.append(write_png(out / "depth2", colorize(depth2, value_range=depth_range)))
    log_conf1, log_conf2 = np.log(arrays["conf1"]), np.log(arrays["conf2"])
    conf_range = color_range((log_conf1, None), (log_conf2, None))
    written.append(write_png(out / "conf1", colorize(log_conf1, value_range=conf_range)))
    written.append(write_png(out / "conf2", colorize(log_conf2, value_range=conf_range)))
    written.append(write_png(out / "matches", draw_matches(rgb1, rgb2, arrays["matches_xy1"], arrays["matches_xy2"])))
    return written
