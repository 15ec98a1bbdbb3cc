"""``pointmap demo``: reconstruct the demo scenes shipped with the package, report errors against their
ground truth, write outputs and PNG previews.

The scenes (``pointmap/demo_scenes/<name>``: photos ``view-K.png`` and ``gt.npz``) were rendered by the data
engine from seeds never used in training (``python -m data.demo_scenes``).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
import torch

from pointmap.errors import PointmapError

SCENES_DIR = Path(__file__).parent / "demo_scenes"
log = logging.getLogger(__name__)


def demo_scenes() -> list[Path]:
    return sorted(p for p in SCENES_DIR.iterdir() if (p / "gt.npz").exists()) if SCENES_DIR.exists() else []


def gt_depth_on_map(depth_orig: np.ndarray, transform, shape) -> np.ndarray:
    """Sample an original-resolution depth map at the network-resolution pixels (nearest)."""
    sx, sy, left, top = transform
    h, w = shape
    u = np.clip(np.rint((np.arange(w) + 0.5 + left) / sx - 0.5), 0, depth_orig.shape[1] - 1).astype(int)
    v = np.clip(np.rint((np.arange(h) + 0.5 + top) / sy - 0.5), 0, depth_orig.shape[0] - 1).astype(int)
    return depth_orig[v[:, None], u[None, :]]


def evaluate_scene(model, scene: Path, out: Path, size: int, quiet: bool = False, device="cpu") -> dict:
    """Pairwise predictions on one scene: relative pose, focal and depth errors against the ground truth."""
    from pointmap.geometry.rotations import relative_rotation_error_deg, translation_angle_deg
    from pointmap.images import load_images
    from pointmap.inference import predict_pairs
    from pointmap.io_pair import color_range, colorize, draw_matches, write_png
    from pointmap.matching import match
    from pointmap.pairs import make_pairs
    from pointmap.pose import focal_from_prediction, pair_pose

    gt = np.load(scene / "gt.npz")
    paths = sorted(scene.glob("view-*.png"))
    views = load_images(paths, size=size)
    pairs = make_pairs(len(views))
    preds = predict_pairs(model, views, pairs, quiet=quiet, device=device)
    rows = []
    out.mkdir(parents=True, exist_ok=True)
    d_gts = [gt_depth_on_map(gt["depth_z"][k].astype(np.float32), v.map_from_original, v.shape)
             for k, v in enumerate(views)]
    depth_range = color_range(*[(d, d > 0) for d in d_gts])  # one colour range for every preview of the scene
    for i, j in pairs:
        pred, rev = preds[(i, j)], preds[(j, i)]
        est = pair_pose(pred, rev, patch=model.cfg.patch_size)[0].double()
        c2w = torch.from_numpy(gt["cam2world"])
        gt_rel = torch.linalg.inv(c2w[i]) @ c2w[j]
        rot = float(relative_rotation_error_deg(est[:3, :3], gt_rel[:3, :3]))
        trans = float(translation_angle_deg(est[:3, 3], gt_rel[:3, 3]))
        d_gt = d_gts[i]
        z = pred.pts1_cam1[0, ..., 2].float().numpy()
        valid = (d_gt > 0) & (z > 0)
        scale = np.median(d_gt[valid] / z[valid]) if valid.any() else np.nan
        absrel = float(np.mean(np.abs(z[d_gt > 0].clip(0) * scale - d_gt[d_gt > 0]) / d_gt[d_gt > 0]))
        f_map = float(focal_from_prediction(pred)[0].nan_to_num(0.0))  # none: a 100% error
        f_orig = f_map / views[i].map_from_original[0]
        f_err = abs(f_orig - gt["K"][i][0, 0]) / gt["K"][i][0, 0] * 100
        m = match(pred)
        rows.append(dict(scene=scene.name, pair=f"{i}-{j}", rot_deg=rot, trans_deg=trans, focal_err_pct=f_err,
                         abs_rel=absrel, matches=len(m)))
        rgb_i = (views[i].img.permute(1, 2, 0).numpy() * 255).astype(np.uint8)
        rgb_j = (views[j].img.permute(1, 2, 0).numpy() * 255).astype(np.uint8)
        write_png(out / f"pair{i}{j}_matches", draw_matches(rgb_i, rgb_j, m.xy1.numpy(), m.xy2.numpy()))
        # prediction scaled to the ground truth by the median ratio, both drawn over the scene's range
        z_aligned = z * scale if np.isfinite(scale) else z
        write_png(out / f"pair{i}{j}_depth", np.concatenate(
            [rgb_i, colorize(z_aligned, z > 0, depth_range), colorize(d_gt, d_gt > 0, depth_range)], axis=1))
    return {"rows": rows, "views": views, "preds": preds, "gt": gt, "depth_range": depth_range,
            "patch": model.cfg.patch_size}


def run_demo(out: Path, model_name: str = "small", quiet: bool = False, device="cpu") -> int:
    from pointmap.checkpoint import load_model, model_input_size

    scenes = demo_scenes()
    if not scenes:
        raise PointmapError(f"no demo scenes found in {SCENES_DIR} (render them: python -m data.demo_scenes)")
    model = load_model(model_name, device=device)
    size = model_input_size(model, default=224)
    all_rows, aligned, depth_ranges = [], {}, {}
    for scene in scenes:
        res = evaluate_scene(model, scene, out / scene.name, size, quiet, device)
        all_rows += res["rows"]
        depth_ranges[scene.name] = res["depth_range"]
        aligned[scene.name] = align_scene(res, out / scene.name, quiet)
    print(f"\npointmap demo: model {model_name!r} at {size}px on {len(scenes)} scenes never seen in training\n")
    print(f"{'scene':<10} {'pair':>4} {'rot err':>8} {'dir err':>8} {'focal err':>9} {'AbsRel':>7} {'matches':>7}")
    for r in all_rows:
        print(f"{r['scene']:<10} {r['pair']:>4} {r['rot_deg']:7.1f}° {r['trans_deg']:7.1f}° "
              f"{r['focal_err_pct']:8.1f}% {r['abs_rel']:7.3f} {r['matches']:7d}")
    rot = np.array([r["rot_deg"] for r in all_rows])
    tr = np.array([r["trans_deg"] for r in all_rows])
    print(f"\nRRA@15 {100 * np.mean(rot < 15):.0f}%  RTA@15 {100 * np.mean(tr < 15):.0f}%  "
          f"median AbsRel {np.median([r['abs_rel'] for r in all_rows]):.3f}")
    print("\nglobal alignment of all views, poses refined on the matches (mean over view pairs):")
    for name, a in aligned.items():
        print(f"  {name:<10} rot err {a['rot_deg']:5.1f}°  dir err {a['trans_deg']:5.1f}°  focal err {a['focal_err_pct']:5.1f}%")
    print(f"outputs and previews: {out}/  (SCENE/recon/points.ply and SCENE/recon/scene.glb open in any 3D viewer)")
    print("  SCENE/pairIJ_depth.png: image | predicted depth (scaled to the ground truth by the median ratio) | "
          "ground-truth depth; one colour range (turbo, blue near, red far: 2-98 % of the scene's ground-truth "
          "depths) for all previews of a scene:")
    for name, (lo, hi) in depth_ranges.items():
        print(f"  {name:<10} depth colours {lo:.2f} m (blue) to {hi:.2f} m (red)")
    return 0


def align_scene(res: dict, out: Path, quiet: bool) -> dict:
    """Global alignment of the scene, its exports, and its errors against the ground truth: pairwise
    relative rotation / direction errors of the aligned cameras, focal error in original pixels."""
    from pointmap.align import EpipolarConfig, global_align, refine_epipolar
    from pointmap.geometry.rotations import relative_rotation_error_deg, translation_angle_deg

    recon = global_align(res["views"], res["preds"], quiet=quiet)  # then the poses on the matches, as reconstruct
    recon = refine_epipolar(res["views"], res["preds"], recon, config=EpipolarConfig(patch=res["patch"]))
    recon.save(out / "recon", formats=("ply", "glb", "npz"))
    gt_c2w = torch.from_numpy(res["gt"]["cam2world"])
    est = recon.cam2world.double()
    n = len(est)
    rot, tr = [], []
    for i in range(n):
        for j in range(i + 1, n):
            e = torch.linalg.inv(est[i]) @ est[j]
            g = torch.linalg.inv(gt_c2w[i]) @ gt_c2w[j]
            rot.append(float(relative_rotation_error_deg(e[:3, :3], g[:3, :3])))
            tr.append(float(translation_angle_deg(e[:3, 3], g[:3, 3])))
    f_err = (recon.K[:, 0, 0].double() - torch.from_numpy(res["gt"]["K"][:, 0, 0])).abs() / \
        torch.from_numpy(res["gt"]["K"][:, 0, 0])
    return {"rot_deg": float(np.mean(rot)), "trans_deg": float(np.mean(tr)), "focal_err_pct": float(f_err.mean() * 100)}


if __name__ == "__main__":
    sys.exit(run_demo(Path("demo_out")))
