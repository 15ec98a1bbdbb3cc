"""Two-view relative pose on held-out rendered pairs: the model (from its own pointmaps) against an
OpenCV SIFT + essential-matrix baseline that is GIVEN the true intrinsics. Reported overall and by
category (scene kind, low texture, wide baseline = true rotation > 30 degrees, translation only = true rotation
< 5 degrees, as in a stereo rig, short baseline = camera centres less than 0.1 x view 1's median depth apart,
where the translation direction rests on little parallax). For models with descriptors,
"model matches+PnP (known K)" is MASt3R-style: the model's patch-level matches (pm.match_coarse) lifted by
view 1's own pointmap, PnP-RANSAC with view 2's true K (as the SIFT baseline gets); "model refined on
matches (known K)" takes the model's pose as a prior and refines its rotation and translation direction on the same
matches (pm.refine_pose_with_matches: robust least squares on the epipolar constraint). "model + own matches (no K)"
is what the pipeline reports (pm.pair_pose): the same refinement with each view's focal from its own pointmap, the
rotation held within a few degrees of the pointmaps'; "model + own matches (known K)" is pm.pair_pose given both true
K (what `pointmap pair --focal` and `pointmap localize --focal / --cameras` report: a 1-degree rotation prior, where
the refinement row above has refine_pose_with_matches' 10); "model + own matches (one focal)" gives both views one
focal, the geometric mean of their own estimates (right for two photographs of one camera, as in one-camera sets like
eval_cam_s464646), with the estimated focal's 3-degree prior. A last row, "no rotation",
is the trivial prior (identity rotation; no translation estimate): a model must beat it to have learnt
anything about rotation.

    python benchmarks/bench_pose.py --data HELDOUT_SHARDS --model small [--pairs 200] [--per-pair CSV]
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pointmap as pm  # noqa: E402
from pointmap.geometry.rotations import relative_rotation_error_deg, translation_angle_deg  # noqa: E402
from pointmap.images import INPUT_SIZE_RULE, is_input_size  # noqa: E402
from pointmap.pose import focal_from_prediction, pose_from_essential  # noqa: E402
from training.evaluate import PairResult, check_per_pair, write_per_pair  # noqa: E402


def sift_pose(img1: np.ndarray, img2: np.ndarray, K1: np.ndarray, K2: np.ndarray):
    """cam2world of view 2 in view 1's frame (unit translation) from SIFT + 5-point RANSAC, or None."""
    sift = cv2.SIFT_create(4000)
    g1, g2 = (cv2.cvtColor(i, cv2.COLOR_RGB2GRAY) for i in (img1, img2))
    k1, d1 = sift.detectAndCompute(g1, None)
    k2, d2 = sift.detectAndCompute(g2, None)
    if d1 is None or d2 is None or len(k1) < 8 or len(k2) < 8:
        return None
    matches = cv2.BFMatcher().knnMatch(d1, d2, k=2)
    good = [m[0] for m in matches if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    if len(good) < 8:
        return None
    p1 = np.float64([k1[m.queryIdx].pt for m in good])
    p2 = np.float64([k2[m.trainIdx].pt for m in good])
    return pose_from_essential(p1, p2, K1, K2, threshold_px=1.0)


def errors(est, gt):
    if est is None or not np.isfinite(est).all():
        return 180.0, 180.0
    e, g = torch.as_tensor(est, dtype=torch.float64), torch.as_tensor(gt, dtype=torch.float64)
    return float(relative_rotation_error_deg(e[:3, :3], g[:3, :3])), float(translation_angle_deg(e[:3, 3], g[:3, 3]))


def model_at_size(name: str, size: int | None):
    """(model, input size): ``size`` or the size the model was trained at (its provenance; 224 if unknown)."""
    model = pm.load_model(name)
    return model, size or int((getattr(model, "provenance", None) or {}).get("image_size", 224))


def print_pose_table(res: dict, first: str) -> None:
    """Markdown rows of RRA@15 / RTA@15 / median errors from {(group, method): [(rot err, dir err), ...]};
    a method without translation (all dir errors NaN) prints '-'. The shares have one decimal, so that a count
    read back from them is exact on up to 200 pairs (whole percents had put ``compare_cards``' counts a pair off)."""
    print(f"| {first} | pairs | method | RRA@15 | RTA@15 | median rot err | median dir err |")
    print("|---|---|---|---|---|---|---|")
    for (group, name), vals in res.items():
        v = np.array(vals)
        rta, dir_med = (("-", "-") if np.isnan(v[:, 1]).all()
                        else (f"{100 * np.mean(v[:, 1] < 15):.1f}%", f"{np.median(v[:, 1]):.1f}"))
        print(f"| {group} | {len(v)} | {name} | {100 * np.mean(v[:, 0] < 15):.1f}% | {rta} | "
              f"{np.median(v[:, 0]):.1f} | {dir_med} |")


def one_focal_K(pred, rev) -> torch.Tensor | None:
    """[3, 3] K of both views of a pair as one camera's: the geometric mean of the two views' focals from their own
    pointmaps (``focal_from_prediction`` of each pass), the principal point at the centre (one size); None when a
    view has no focal (a degenerate pointmap), as ``write_pair_outputs(shared_focal=True)`` then keeps each view's."""
    from pointmap.geometry.cameras import intrinsics

    f = float(focal_from_prediction(pred)[0]) * float(focal_from_prediction(rev)[0])
    if not (math.isfinite(f) and f > 0):
        return None
    f = math.sqrt(f)
    H, W = pred.pts1_cam1.shape[1:3]
    return intrinsics(f, (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)


def main(argv=None) -> int:
    from data.datasets import PairDataset

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="held-out shards (never trained on)")
    p.add_argument("--model", default="small")
    p.add_argument("--pairs", type=int, default=200)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--size", type=int, default=None, help="input size (default: the model's training size)")
    p.add_argument("--known-k-priors", default="", metavar="DEG[,DEG...]",
                   help="also rows of pm.pair_pose given both true K at these rotation priors (degrees >= 0), e.g. "
                        "0,1,3,10: the sweep that chose its default (docs/models.md)")
    p.add_argument("--per-pair", type=Path, default=None, metavar="CSV",
                   help="also save the model's per-pair errors (set: the --data folder's name) for benchmarks/paired.py")
    a = p.parse_args(argv)
    if a.pairs < 1:
        p.error(f"--pairs expected >= 1, got {a.pairs}")
    if a.size is not None and not is_input_size(a.size):
        p.error(f"--size expected {INPUT_SIZE_RULE}, got {a.size}")
    if a.per_pair is not None:
        try:  # before the long run, not after it
            check_per_pair(a.per_pair, Path(a.data).resolve().name)
        except (OSError, ValueError) as e:
            p.error(str(e))
    try:
        priors = [float(x) for x in a.known_k_priors.split(",") if x.strip()]
    except ValueError:
        priors = [-1.0]
    if not all(math.isfinite(x) and x >= 0 for x in priors):
        p.error(f"--known-k-priors expected degrees >= 0 separated by commas, got {a.known_k_priors!r}")
    torch.set_num_threads(a.threads)
    try:  # the model and the data, checked before the long run
        model, size = model_at_size(a.model, a.size)
        ds = PairDataset(a.data, size=size, augment=False, split="all")
    except (pm.PointmapError, OSError, ValueError) as e:
        p.error(str(e))
    per_pair = []
    res = defaultdict(lambda: defaultdict(list))
    n = min(a.pairs, len(ds))
    for idx in range(n):
        v1, v2 = ds[idx]
        k, scene, i, j = ds.items[idx]
        meta = ds._store.reader(k).meta(scene)
        gt = (torch.linalg.inv(v1["cam2world"].double()) @ v2["cam2world"].double()).numpy()
        cats = ["all", meta["kind"], "low-texture" if meta["low_texture"] else "textured"]
        true_rot = errors(np.eye(4), gt)[0]
        if true_rot > 30:
            cats.append("wide (>30 deg)")
        if true_rot < 5:
            cats.append("translation only (<5 deg)")
        if np.linalg.norm(gt[:3, 3]) < 0.1 * float(v1["depth_z"][v1["valid"]].median()):
            cats.append("short baseline (<0.1 depth)")
        with torch.inference_mode():
            pred = model(v1["img"][None], v2["img"][None])
            rev = model(v2["img"][None], v1["img"][None])
        ours = pm.relative_pose(pred, pred_reverse=rev)[0].numpy()
        cm = hybrid = own = own_k = own_one = None
        if pred.has_desc:  # MASt3R-style: the model's own (patch-level) matches + view 1's pointmap, PnP with K
            m = pm.match_coarse(pred, model.cfg.patch_size)
            cm = pm.relative_pose(pred, K2=v2["K"].double(), matches=[m])[0].numpy()
            hybrid = pm.refine_pose_with_matches(torch.from_numpy(ours), m, v1["K"].double(), v2["K"].double()).numpy()
            own = pm.pair_pose(pred, rev, patch=model.cfg.patch_size, pose=torch.from_numpy(ours)[None], matches=[m])[0].numpy()
            own_k = pm.pair_pose(pred, rev, v1["K"].double(), v2["K"].double(), patch=model.cfg.patch_size,
                                 pose=torch.from_numpy(ours)[None], matches=[m])[0].numpy()
            K_one = one_focal_K(pred, rev)  # one camera: one focal for both views, still estimated (prior 3)
            own_one = own if K_one is None else pm.pair_pose(  # no focal to share: each view's, as `pointmap pair`
                pred, rev, K_one, K_one, patch=model.cfg.patch_size, rotation_prior_deg=3.0,
                pose=torch.from_numpy(ours)[None], matches=[m])[0].numpy()
        per_pair.append(PairResult(idx, *errors(ours, gt), true_rot,
                                   *(errors(own, gt) if own is not None else (float("nan"),) * 2)))
        to_u8 = lambda v: (v["img"].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)  # noqa: E731
        base = sift_pose(to_u8(v1), to_u8(v2), v1["K"].double().numpy(), v2["K"].double().numpy())
        swept = [(f"model + own matches (known K, prior {x:g})",
                  pm.pair_pose(pred, rev, v1["K"].double(), v2["K"].double(), patch=model.cfg.patch_size,
                               pose=torch.from_numpy(ours)[None], matches=[m], rotation_prior_deg=x)[0].numpy())
                 for x in priors] if pred.has_desc else []
        rows = [("model", ours), ("model + own matches (no K)", own), ("model + own matches (one focal)", own_one),
                ("model + own matches (known K)", own_k), *swept,
                ("model matches+PnP (known K)", cm), ("model refined on matches (known K)", hybrid),
                ("sift+E (known K)", base), ("no rotation", None)]
        for name, est in rows:
            if name.startswith("model ") and est is None:  # a model without descriptors has no matches
                continue
            r, t = errors(est, gt) if name != "no rotation" else (errors(np.eye(4), gt)[0], float("nan"))
            for c in cats:
                res[c][name].append((r, t))
    if a.per_pair is not None:
        write_per_pair(a.per_pair, Path(a.data).resolve().name, per_pair)
    print(f"{n} held-out pairs from {a.data}; model {a.model!r}\n")
    print_pose_table({(c, name): vals for c in sorted(res, key=lambda c: (c != "all", c))
                      for name, vals in res[c].items()}, "category")
    return 0


if __name__ == "__main__":
    sys.exit(main())
