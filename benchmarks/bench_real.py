"""Real photographs with ground truth: the model on camera images it was never trained on, against OpenCV.

The photographs are OpenCV's sample data, shipped by Debian's ``opencv-doc`` package (no other download):

    apt-get download opencv-doc && dpkg-deb -x opencv-doc_*.deb /tmp/opencv-doc
    python benchmarks/bench_real.py --data /tmp/opencv-doc/usr/share/doc/opencv-doc/examples/data --model small

Two sets:
- **stereo rig** (``left01..14.jpg`` / ``right01..14.jpg``, 640x480 grey, 13 pairs): a two-camera rig photographing
  a chessboard in an office. Ground truth comes from OpenCV's own calibration of these images
  (``findChessboardCorners`` -> ``calibrateCamera`` per camera -> ``stereoCalibrate``); the images are undistorted
  with it, so a pinhole K holds. Every pair has the same relative pose (small rotation, sideways baseline).
- **aloe** (``aloeL.jpg`` / ``aloeR.jpg`` / ``aloeGT.png``, Middlebury 2006, 1282x1110): a rectified pair (rotation
  = identity, view 2 displaced along +x) with a ground-truth disparity map. Its focal length and the disparity
  offset of the crop are not shipped, so depth is scored in disparity space: the prediction's inverse depth is
  fitted to the true disparity by least squares (scale and shift: what Z = f B / (d + d_offset) leaves unknown),
  and the residual is reported against a constant (the trivial prior) and OpenCV's semi-global block matching
  (StereoSGBM) on the same network-size images.

- **motorcycle** (Middlebury 2014 ``Motorcycle``, the quarter-size colour pair with its ground-truth disparity that
  scikit-image ships in ``skimage/data``: ``pip install scikit-image``, or ``--middlebury DIR``): a rectified pair
  with its calibration (focal 994.978 px, principal points 311.193 / 342.279 x 254.877, baseline 193.001 mm), so
  the pose rows with the true K run, the focal is scored, and depth is scored in metric depth
  (Z = f B / (d + 31.086)): AbsRel after the median scale (the held-out sets' ``abs_rel``), next to StereoSGBM's
  depth on the same images through the true calibration. Skipped with a note when the files are not found.

Pose rows as in ``bench_pose.py``: the model from its own pointmaps (no intrinsics), the same refined on its own
matches with its own focals (``pm.pair_pose``, what the pipeline reports), the same with the true K (what
``pointmap pair --focal`` reports), the model's coarse matches +
PnP with the true K, the model's pose refined on those matches with the
true K (``pm.refine_pose_with_matches``), SIFT + essential matrix with the true K, and "no rotation". On the rig, the model's focal
(``pointmap.pose.focal_from_prediction``, no intrinsics given) is compared with the calibrated one.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pointmap as pm  # noqa: E402
from benchmarks.bench_pose import errors, model_at_size, print_pose_table, sift_pose  # noqa: E402
from pointmap.pose import focal_from_prediction  # noqa: E402
from pointmap.reconstruction import K_to_map  # noqa: E402
from training.evaluate import PairResult, abs_rel, check_per_pair, write_per_pair  # noqa: E402

BOARD = (9, 6)  # inner corners of the chessboard in OpenCV's stereo sample
RIG_IDS = [1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14]
# Middlebury 2014 Motorcycle at a quarter of its size, as scikit-image ships it (skimage.data.stereo_motorcycle's
# documentation): focal, left principal point, the right one's x offset (doffs), baseline in metres
MOTO_F, MOTO_C, MOTO_DOFFS, MOTO_B = 994.978, (311.193, 254.877), 31.086, 0.193001
MOTO_FILES = ("motorcycle_left.png", "motorcycle_right.png", "motorcycle_disp.npz")


def _read(path: Path, flags=cv2.IMREAD_COLOR) -> np.ndarray:
    im = cv2.imread(str(path), flags)
    if im is None:
        raise SystemExit(f"bench_real: cannot read {path} (expected OpenCV's sample data: see this script's header)")
    return im


def calibrate_rig(data: Path):
    """Calibrate the two cameras and the rig from the chessboard pairs.

    Returns (pairs of grey images, K1, D1, K2, D2, cam2world of the right camera in the left frame, rms)."""
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-6)
    board = np.zeros((BOARD[0] * BOARD[1], 3), np.float32)
    board[:, :2] = np.mgrid[0:BOARD[0], 0:BOARD[1]].T.reshape(-1, 2)
    pairs, obj, c1, c2 = [], [], [], []
    for i in RIG_IDS:
        ims = [_read(data / f"{side}{i:02d}.jpg", cv2.IMREAD_GRAYSCALE) for side in ("left", "right")]
        found = [cv2.findChessboardCorners(im, BOARD) for im in ims]
        pairs.append(ims)
        if not all(ok for ok, _ in found):
            continue
        corners = [cv2.cornerSubPix(im, c, (11, 11), (-1, -1), crit) for im, (_, c) in zip(ims, found)]
        obj.append(board)
        c1.append(corners[0])
        c2.append(corners[1])
    if len(obj) < 5:
        raise SystemExit(f"bench_real: the chessboard was found in only {len(obj)} rig pairs (expected >= 5)")
    size = pairs[0][0].shape[::-1]
    _, K1, D1, _, _ = cv2.calibrateCamera(obj, c1, size, None, None)
    _, K2, D2, _, _ = cv2.calibrateCamera(obj, c2, size, None, None)
    rms, K1, D1, K2, D2, R, T, _, _ = cv2.stereoCalibrate(obj, c1, c2, K1, D1, K2, D2, size,
                                                          flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    world2right = np.eye(4)
    world2right[:3, :3], world2right[:3, 3] = R, T[:, 0]
    return pairs, K1, D1, K2, D2, np.linalg.inv(world2right), float(rms), len(obj)


def _k_on_map(K: np.ndarray, view) -> np.ndarray:
    """Intrinsics in the network input's pixels."""
    return K_to_map(torch.from_numpy(K), torch.tensor(view.map_from_original, dtype=torch.float64)).numpy()


def _resample(full: np.ndarray, view, shape) -> np.ndarray:
    """Nearest sample of a full-resolution map at the network input's pixel centres."""
    sx, sy, left, top = view.map_from_original
    h, w = shape
    u = ((np.arange(w) + 0.5 + left) / sx - 0.5).astype(np.float32)
    v = ((np.arange(h) + 0.5 + top) / sy - 0.5).astype(np.float32)
    mu, mv = np.meshgrid(u, v)
    return cv2.remap(full, mu, mv, cv2.INTER_NEAREST)


def pose_rows(model, im1: np.ndarray, im2: np.ndarray, gt: np.ndarray, size: int, K1=None, K2=None):
    """[(method, (rot err, dir err))] for one pair of RGB uint8 images; the methods that need intrinsics run
    only when the true (original-pixel) K1, K2 are given. Also returns the model's relative focal error (or
    NaN) and (view 1, view 2, prediction)."""
    v1, v2 = pm.load_images([im1, im2], size=size)
    with torch.inference_mode():
        pred = model(v1.img[None], v2.img[None])
        rev = model(v2.img[None], v1.img[None])
    ours = pm.relative_pose(pred, pred_reverse=rev)[0]
    rows = [("model (own pointmaps, no K)", errors(ours.numpy(), gt))]
    m = pm.match_coarse(pred, model.cfg.patch_size) if pred.has_desc else None
    if m is not None:  # what the pipeline reports: refined on its own matches with its own focals (pm.pair_pose)
        own = pm.pair_pose(pred, rev, patch=model.cfg.patch_size, pose=ours[None], matches=[m])[0]
        rows.append(("model + own matches (no K)", errors(own.numpy(), gt)))
    focal_err = float("nan")
    if K1 is not None:
        k1, k2 = _k_on_map(K1, v1), _k_on_map(K2, v2)
        if m is not None:  # what `pointmap pair --focal` reports: pm.pair_pose with both K
            own_k = pm.pair_pose(pred, rev, k1, k2, patch=model.cfg.patch_size, pose=ours[None], matches=[m])[0]
            rows.append(("model + own matches (known K)", errors(own_k.numpy(), gt)))
            rows.append(("model matches+PnP (known K)",
                         errors(pm.relative_pose(pred, K2=torch.from_numpy(k2), matches=[m])[0].numpy(), gt)))
            rows.append(("model refined on matches (known K)",
                         errors(pm.refine_pose_with_matches(ours, m, k1, k2).numpy(), gt)))
        to_u8 = lambda v: (v.img.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)  # noqa: E731
        rows.append(("SIFT+E (known K)", errors(sift_pose(to_u8(v1), to_u8(v2), k1, k2), gt)))
        focal_err = abs(float(focal_from_prediction(pred)[0].nan_to_num(0.0)) - k1[0, 0]) / k1[0, 0]  # none: 100%
    rows.append(("no rotation", (errors(np.eye(4), gt)[0], float("nan"))))
    return rows, focal_err, (v1, v2, pred)


def _pair_result(k: int, rows, true_rot: float) -> PairResult:
    """Pair ``k``'s per-pair row from ``pose_rows``'s rows: the pose from the model's own pointmaps (rows[0]) and,
    when the model has descriptors, the pipeline's (NaN otherwise)."""
    pipeline = dict(rows).get("model + own matches (no K)", (float("nan"),) * 2)
    return PairResult(k, *rows[0][1], true_rot, *pipeline)


def skimage_data_dir() -> Path | None:
    """scikit-image's bundled data folder (holding the Middlebury motorcycle pair), or None when it is not installed.
    Found without importing scikit-image."""
    import importlib.util

    spec = importlib.util.find_spec("skimage")
    if spec is None or not spec.origin:
        return None
    return Path(spec.origin).parent / "data"


def motorcycle(folder: Path):
    """The Middlebury motorcycle pair: (left RGB, right RGB, true depth in metres (NaN where unknown), K1, K2,
    cam2world of the right camera in the left frame); SystemExit with what is missing otherwise."""
    missing = [n for n in MOTO_FILES if not (folder / n).is_file()]
    if missing:
        raise SystemExit(f"bench_real: {folder} lacks {', '.join(missing)} (expected scikit-image's data folder: "
                         f"pip install scikit-image, or --middlebury DIR)")
    left, right = (cv2.cvtColor(_read(folder / n), cv2.COLOR_BGR2RGB) for n in MOTO_FILES[:2])
    with np.load(folder / MOTO_FILES[2]) as z:
        disp = np.asarray(z[z.files[0]], dtype=np.float64)
    if disp.shape != left.shape[:2] or left.shape != right.shape:
        raise SystemExit(f"bench_real: motorcycle images {left.shape}, {right.shape} and disparity {disp.shape} "
                         f"do not agree (expected scikit-image's quarter-size Middlebury pair)")
    ok = np.isfinite(disp) & (disp > 0)
    depth = np.full(disp.shape, np.nan)
    depth[ok] = MOTO_F * MOTO_B / (disp[ok] + MOTO_DOFFS)
    K1 = np.array([[MOTO_F, 0, MOTO_C[0]], [0, MOTO_F, MOTO_C[1]], [0, 0, 1]])
    K2 = K1.copy()
    K2[0, 2] += MOTO_DOFFS
    gt = np.eye(4)
    gt[0, 3] = MOTO_B  # rectified: the right camera is the left one moved along +x
    return left, right, depth, K1, K2, gt


def median_abs_rel(pred_z: np.ndarray, true_z: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    """(AbsRel after the median scale alignment over ``valid``, the held-out sets' measure for a scale-free
    prediction: ``training.evaluate.abs_rel`` itself; Pearson r of the two depths, 0 for a constant prediction)."""
    p, t = pred_z[valid].astype(np.float64), true_z[valid].astype(np.float64)
    r = float(np.corrcoef(p, t)[0, 1]) if p.std() > 0 else 0.0
    return abs_rel(torch.from_numpy(pred_z), torch.from_numpy(true_z), torch.from_numpy(valid)), r


def sgbm_disparity(grey1: np.ndarray, grey2: np.ndarray, max_disp: float) -> np.ndarray:
    """OpenCV's semi-global block matching on a rectified grey pair: disparity in pixels (<= 0 where none), searched
    up to ``max_disp`` rounded up to a multiple of 16."""
    n_disp = 16 * max(1, int(np.ceil(max_disp / 16)))
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=n_disp, blockSize=5, P1=8 * 25, P2=32 * 25,
                                 uniquenessRatio=5, mode=cv2.STEREO_SGBM_MODE_HH)
    return sgbm.compute(grey1, grey2).astype(np.float32) / 16.0


def disparity_fit(pred_inv_depth: np.ndarray, gt: np.ndarray, valid: np.ndarray):
    """Least-squares scale + shift of a prediction (any map affine in disparity) to the true disparity on
    ``valid``: (mean abs residual in GT pixels, Pearson r). A constant prediction gives the prior's error."""
    x, y = pred_inv_depth[valid].astype(np.float64), gt[valid].astype(np.float64)
    A = np.stack([x, np.ones_like(x)], 1)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = float(np.corrcoef(x, y)[0, 1]) if x.std() > 0 else 0.0
    return float(np.abs(A @ coef - y).mean()), r


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, type=Path, help="OpenCV's samples/data (opencv-doc: examples/data)")
    p.add_argument("--model", default="small")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--size", type=int, default=None, help="input size (default: the model's training size)")
    p.add_argument("--middlebury", type=Path, default=None, metavar="DIR",
                   help="folder with motorcycle_left.png, motorcycle_right.png, motorcycle_disp.npz (default: "
                        "scikit-image's data folder when scikit-image is installed; else the set is skipped)")
    p.add_argument("--per-pair", type=Path, default=None, metavar="CSV",
                   help="also save the model's per-pair errors on the rig (set real_rig) and on the rectified pairs "
                        "(set real_rectified: 0 aloe, 1 motorcycle) for benchmarks/paired.py")
    a = p.parse_args(argv)
    if a.per_pair is not None:
        try:  # before the long run, not after it
            check_per_pair(a.per_pair, "real_rig")
        except (OSError, ValueError) as e:
            p.error(str(e))
    moto_dir = a.middlebury or skimage_data_dir()
    moto = None
    if moto_dir is not None and (a.middlebury is not None or (moto_dir / MOTO_FILES[0]).is_file()):
        moto = motorcycle(moto_dir)  # read (and checked) before the long run
    torch.set_num_threads(a.threads)
    model, size = model_at_size(a.model, a.size)

    pairs, K1, D1, K2, D2, gt, rms, n_cal = calibrate_rig(a.data)
    res, focal_err, per_pair = {}, [], []
    true_rot = errors(np.eye(4), gt)[0]
    for k, (left, right) in enumerate(pairs):
        im1 = cv2.cvtColor(cv2.undistort(left, K1, D1), cv2.COLOR_GRAY2RGB)
        im2 = cv2.cvtColor(cv2.undistort(right, K2, D2), cv2.COLOR_GRAY2RGB)
        rows, ferr, _ = pose_rows(model, im1, im2, gt, size, K1, K2)
        focal_err.append(ferr)
        per_pair.append(_pair_result(k, rows, true_rot))
        for name, e in rows:
            res.setdefault(("stereo rig", name), []).append(e)

    rgb = [cv2.cvtColor(_read(a.data / f"aloe{s}.jpg"), cv2.COLOR_BGR2RGB) for s in ("L", "R")]
    disp = _read(a.data / "aloeGT.png", cv2.IMREAD_GRAYSCALE).astype(np.float32)
    gt_rect = np.eye(4)
    gt_rect[0, 3] = 1.0  # rectified: same orientation, view 2 along +x (its focal is not shipped: no K rows)
    rows, _, (v1, v2, pred) = pose_rows(model, rgb[0], rgb[1], gt_rect, size)
    for name, e in rows:
        res.setdefault(("aloe (rectified)", name), []).append(e)
    rectified = [_pair_result(0, rows, 0.0)]

    shape = tuple(pred.pts1_cam1.shape[1:3])
    gt_disp = _resample(disp, v1, shape)
    z = pred.pts1_cam1[0, ..., 2].float().numpy()
    valid = (gt_disp > 0) & (z > 0)
    to_grey = lambda v: cv2.cvtColor((v.img.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8),  # noqa: E731
                                     cv2.COLOR_RGB2GRAY)
    # disparity search range: the true disparities at this size (Aloe's reach ~85 px at 512)
    d_sgbm = sgbm_disparity(to_grey(v1), to_grey(v2), float(gt_disp.max()) * v1.map_from_original[0])
    ok_sgbm = valid & (d_sgbm > 0)
    depth_rows = [("model (1 / depth of view 1)", *disparity_fit(1.0 / np.where(z > 0, z, 1.0), gt_disp, valid),
                   valid.mean()),
                  ("constant (prior)", *disparity_fit(np.zeros_like(z), gt_disp, valid), valid.mean()),
                  ("StereoSGBM (rectified pair, same size)", *disparity_fit(d_sgbm, gt_disp, ok_sgbm), ok_sgbm.mean())]

    moto_rows = moto_focal = None
    if moto is not None:
        left, right, depth, mK1, mK2, mgt = moto
        rows, moto_focal, (m1, m2, mpred) = pose_rows(model, left, right, mgt, size, mK1, mK2)
        for name, e in rows:
            res.setdefault(("motorcycle (rectified)", name), []).append(e)
        rectified.append(_pair_result(1, rows, 0.0))
        mshape = tuple(mpred.pts1_cam1.shape[1:3])
        true_z = _resample(depth.astype(np.float32), m1, mshape)
        mz = mpred.pts1_cam1[0, ..., 2].float().numpy()
        mvalid = np.isfinite(true_z) & (mz > 0)
        sx = m1.map_from_original[0]  # network pixels per original pixel: focal and disparities scale with it
        # d of Z = f B / (d + doffs), in network pixels, searched up to the nearest point's
        d_m = sgbm_disparity(to_grey(m1), to_grey(m2), (MOTO_F * MOTO_B / np.nanmin(depth) - MOTO_DOFFS) * sx)
        z_sgbm = np.where(d_m > 0, MOTO_F * sx * MOTO_B / (np.maximum(d_m, 1e-6) + MOTO_DOFFS * sx), np.nan)
        ok_m = mvalid & np.isfinite(z_sgbm)
        moto_rows = [("model (depth of view 1)", *median_abs_rel(mz, true_z, mvalid), mvalid.mean()),
                     ("constant (prior)", *median_abs_rel(np.ones_like(mz), true_z, mvalid), mvalid.mean()),
                     ("StereoSGBM (true calibration)", *median_abs_rel(z_sgbm, true_z, ok_m), ok_m.mean()),
                     ("model on StereoSGBM's pixels", *median_abs_rel(mz, true_z, ok_m), ok_m.mean())]

    if a.per_pair is not None:
        write_per_pair(a.per_pair, "real_rig", per_pair)
        write_per_pair(a.per_pair, "real_rectified", rectified)
    print(f"model {a.model!r} at {size} px; rig calibrated on {n_cal} of {len(pairs)} pairs, stereo RMS {rms:.3f} px; "
          f"true rig rotation {true_rot:.1f} deg\n")
    print_pose_table(res, "set")
    print(f"\nstereo rig, model focal (no K given) vs calibrated: median relative error {np.median(focal_err):.1%}")
    print("\naloe depth, in disparity space after a least-squares scale + shift (GT disparity in full-size pixels):\n")
    print("| method | mean abs residual (px) | Pearson r | pixels scored |")
    print("|---|---|---|---|")
    for name, err, r, cover in depth_rows:
        print(f"| {name} | {err:.1f} | {r:.2f} | {cover:.0%} |")
    if moto_rows is None:
        print("\nmotorcycle (Middlebury 2014): skipped, its files were not found (pip install scikit-image, or "
              "--middlebury DIR)")
        return 0
    print(f"\nmotorcycle, model focal (no K given) vs calibrated: relative error {moto_focal:.1%}")
    print("\nmotorcycle depth, metric (Z = f B / (d + doffs)), AbsRel after the median scale:\n")
    print("| method | AbsRel | Pearson r | pixels scored |")
    print("|---|---|---|---|")
    for name, err, r, cover in moto_rows:
        print(f"| {name} | {err:.3f} | {r:.2f} | {cover:.0%} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
