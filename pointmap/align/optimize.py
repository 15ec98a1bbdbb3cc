"""``global_align``: pair predictions -> Reconstruction (poses, intrinsics in original pixels, depth).

Steps: validate the graph; stack the edges at the optimisation resolution (stride-subsampled); intrinsics
(known, or Weiszfeld); a start by motion averaging over every edge (or DUSt3R's maximum spanning tree); gauge (known poses, or unit mean edge scale);
Adam or LBFGS on the chunked DUSt3R objective with early stopping (the best iterate is kept); full-
resolution depth by fusing every edge with the final poses; without known poses, the world moved to image 0's
camera frame; a Reconstruction with a convergence report
in ``recon.info["align"]``.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import asdict, dataclass

import torch

from pointmap.align.averaging import init_averaging
from pointmap.align.edges import (
    CONF_TRANSFORMS,
    build_stack,
    check_connected,
    check_preds,
    choose_stride,
    drop_empty_edges,
    resolve_conf_transform,
)
from pointmap.align.fuse import fuse_depth
from pointmap.align.gauge import anchor_to_first, apply_similarity, similarity_to_known
from pointmap.align.head_prior import head_prior
from pointmap.align.init import init_mst, own_maps
from pointmap.align.inputs import camera_index, parse_known_K, parse_known_poses, parse_views
from pointmap.align.loop import run
from pointmap.align.objective import chunk_size_for
from pointmap.align.params import AlignParams
from pointmap.errors import GraphError, PointmapError, ShapeError, is_int, is_number
from pointmap.geometry.focal import focal_from_pointmap
from pointmap.reconstruction import K_to_original, Reconstruction, to_canvas

INITS = ("averaging", "mst")


@dataclass(frozen=True)
class AlignConfig:
    """Settings of dense global alignment (defaults follow DUSt3R where it has one).

    optimizer: 'adam' (default), 'lbfgs', or 'none' (initialisation only)
    niter: maximum iterations; lr / lr_min with schedule 'cosine' | 'linear' | 'constant' (Adam)
    lr_focal: learning rate of log-focal (None = lr)
    conf_transform: residual weight from confidence: 'auto' (default: 'log' when the confidences spread
        above 1, as the official models' do, else 'id'; see edges.resolve_conf_transform), 'log' (DUSt3R),
        'm1', 'sqrt', 'id'
    max_opt_pixels: pixels per image used while optimising (maps are stride-subsampled to fit);
        None = full resolution. ``stride`` overrides it.
    max_chunk_pixels: edge-pixels evaluated at once; caps the peak memory of one iteration
    early_stop_tol / early_stop_window: stop when the loss improved by less than tol (relative)
        over the last ``window`` iterations
    fuse_iters: reweighting passes of the full-resolution depth fusion (0 = weighted least squares)
    shared_focal: all images come from one camera: one focal for all of them (started at the median of the
        per-image estimates), as MASt3R's ``shared_intrinsics``; or a camera label per image (e.g. [0, 0, 1, 1, 1]):
        the images of one label share one focal (photographs from two phones). The images of one camera need one
        original size, resized and cropped alike, and K given for all of them (one focal) or none
        (``check_one_camera``)
    init: the start of the optimisation: 'averaging' (default: every edge at once, rotation, scale and centre
        averaging; pointmap.align.averaging) or 'mst' (DUSt3R's maximum spanning tree: one edge per image, chained)
    pose_head: the averaging start takes each edge's rotation and the direction of its centre from the pose head's
        transform when every prediction carries one (``PairPrediction.cam2_to_cam1``; the length stays the
        Procrustes'); False: the Procrustes of the pointmaps, as before session 49 (models without a pose head
        always use it)
    head_prior: weight of the pose heads' prior on the cameras during the dense optimisation (with ``pose_head``
        and predictions that all carry the heads' transforms; 0: off; pointmap.align.head_prior). The default, 0.1
        since session 51, was chosen on a tuning set and checked on the held-out sets (docs/alignment.md). The
        report's losses include it; ``head_prior_loss`` is its share at the end
    head_prior_deg: its Cauchy widths (rotation, translation direction), in degrees
    quiet: no progress bar
    """

    optimizer: str = "adam"
    niter: int = 100
    lr: float = 0.01
    lr_min: float = 1e-6
    lr_focal: float | None = None
    schedule: str = "cosine"
    conf_transform: str = "auto"
    max_opt_pixels: int | None = 96 * 64
    stride: int | None = None
    max_chunk_pixels: int = 2_000_000
    early_stop_tol: float = 1e-4
    early_stop_window: int = 20
    fuse_iters: int = 1
    shared_focal: bool | tuple = False
    init: str = "averaging"
    pose_head: bool = True
    head_prior: float = 0.1
    head_prior_deg: tuple[float, float] = (10.0, 20.0)
    quiet: bool = False

    def __post_init__(self):
        """Names are checked here, before any inference or initialisation runs on a bad config."""
        for field, value, allowed in (("optimizer", self.optimizer, ("adam", "lbfgs", "none")),
                                      ("schedule", self.schedule, ("cosine", "linear", "constant")),
                                      ("conf_transform", self.conf_transform, ("auto",) + CONF_TRANSFORMS),
                                      ("init", self.init, INITS)):
            if value not in allowed:
                raise ShapeError(f"AlignConfig.{field} expected one of {allowed}, got {value!r}")

        def number(name, positive, allow_none=False, integer=False):
            v = getattr(self, name)
            if v is None and allow_none:
                return
            ok = (is_int(v) if integer else is_number(v)) and math.isfinite(v) and (v > 0 if positive else v >= 0)
            if not ok:
                kind = "an int" if integer else "a finite number"
                raise ShapeError(f"AlignConfig.{name} expected {kind} {'> 0' if positive else '>= 0'}"
                                 f"{' or None' if allow_none else ''}, got {v!r}")

        number("niter", positive=False, integer=True)  # 0: no optimisation, the start is returned
        number("lr", positive=True)
        number("lr_min", positive=False)
        if self.lr_min > self.lr:  # the cosine schedule would raise the rate, and the report still say converged
            raise ShapeError(f"AlignConfig.lr_min expected <= lr ({self.lr}), got {self.lr_min}")
        number("lr_focal", positive=True, allow_none=True)
        number("max_opt_pixels", positive=True, allow_none=True, integer=True)
        number("stride", positive=True, allow_none=True, integer=True)
        number("max_chunk_pixels", positive=True, integer=True)
        number("early_stop_tol", positive=False)
        number("early_stop_window", positive=True, integer=True)
        number("fuse_iters", positive=False, integer=True)
        number("head_prior", positive=False)
        d = self.head_prior_deg
        if not (isinstance(d, (tuple, list)) and len(d) == 2 and all(is_number(x) and 0.01 <= x < 180 for x in d)):
            raise ShapeError(f"AlignConfig.head_prior_deg expected two angles in [0.01, 180) degrees (rotation, "
                             f"direction), got {d!r}")
        object.__setattr__(self, "head_prior_deg", tuple(float(x) for x in d))  # hashable, as the rest
        for name in ("pose_head", "quiet"):
            if not isinstance(getattr(self, name), bool):
                raise ShapeError(f"AlignConfig.{name} expected True or False, got {getattr(self, name)!r}")
        cams = self.shared_focal
        if not isinstance(cams, (bool, str, bytes)) and hasattr(cams, "__iter__"):  # read once (a generator)
            cams = tuple(cams)
        if not isinstance(cams, bool):  # a camera label per image: hashable, as the rest
            if isinstance(cams, (str, bytes)) or not hasattr(cams, "__iter__") or not all(is_int(c) for c in cams):
                raise ShapeError(f"AlignConfig.shared_focal expected True, False or a camera label (an int) per "
                                 f"image, got {cams!r}")
            object.__setattr__(self, "shared_focal", tuple(int(c) for c in cams))


def _initial_focals(preds, stack, shapes, fx, fy, cx, cy, known):
    """Fill unknown focals (fx = fy): a focal head's, else Weiszfeld on each image's own full-resolution map."""
    own = own_maps(len(shapes), stack)
    for n in range(len(shapes)):
        h, w = shapes[n]
        if not known[n]:
            cx[n], cy[n] = (w - 1) / 2, (h - 1) / 2
            p = preds[stack.keys[own[n]]]
            f = float(p.focal1.detach()[0]) if p.focal1 is not None else math.nan
            if not (math.isfinite(f) and f > 0):  # no focal head, or one that gave none: the pointmap's
                # a NaN / inf confidence pixel weighs nothing
                f = float(focal_from_pointmap(p.pts1_cam1.detach().double(), weights=torch.nan_to_num(
                    p.conf1.detach().double(), nan=0.0, posinf=0.0).clamp_min(0))[0])
            fx[n] = fy[n] = f if math.isfinite(f) and f > 0 else max(h, w)
    return fx, fy, cx, cy



def global_align(views, preds: dict, K=None, cam2world=None, *, config: AlignConfig | None = None,
                 pose_mask=None, quiet: bool | None = None) -> Reconstruction:
    """Align pairwise pointmaps into one scene.

    views: list of ``pm.View`` (or [3, h, w] images at the maps' resolution), of one size or several (portrait
        among landscape: each view is aligned at its own size, and the Reconstruction holds them on one canvas,
        ``recon.map_sizes``)
    preds: {(i, j): PairPrediction} with batch size 1, ideally both orders (as ``predict_pairs`` gives)
    K: known intrinsics in ORIGINAL image pixels: [3, 3] shared, [N, 3, 3], or {index: [3, 3]}
    cam2world: known OpenCV camera-to-world poses: [N, 4, 4] (all, or those where ``pose_mask``),
        or {index: [4, 4]}. Known poses come back bit-identical (as float32); with two or more known
        camera centres the output scale is theirs.
    Returns a Reconstruction (K in original pixels); ``recon.info["align"]`` holds the report.
    """
    cfg = config or AlignConfig()
    if not isinstance(cfg, AlignConfig):
        raise ShapeError(f"global_align: config expected an AlignConfig, got {type(cfg).__name__} (AlignConfig(**d) "
                         "for a dict)")
    if quiet is not None:
        cfg = AlignConfig(**{**asdict(cfg), "quiet": quiet})
    t_start = time.perf_counter()
    info = parse_views(views)
    n = len(info.shapes)
    if n < 2:
        raise GraphError(f"global alignment needs at least 2 images, got {n}; for a single image run the "
                         "model on (img, img) and use pred.pts1_cam1 (its own camera frame) directly")
    keys = check_preds(preds, n, info.shapes)
    check_connected(n, keys)
    K_given, K_known, fx, fy, cx, cy = parse_known_K(K, n, info)
    camera = camera_index(cfg.shared_focal, n)
    check_cameras(camera, info.original_sizes, info.map_from_original, K_known, fx)
    known_poses = parse_known_poses(cam2world, n, pose_mask)
    stride = choose_stride(info.shapes, cfg.max_opt_pixels, cfg.stride)
    conf_transform = resolve_conf_transform(cfg.conf_transform, preds, keys)
    stack = drop_empty_edges(build_stack(preds, keys, info.shapes, stride, conf_transform), conf_transform)
    if len(stack.keys) < len(keys):
        try:
            check_connected(n, stack.keys)
        except GraphError as err:
            raise GraphError(f"after dropping zero-confidence pairs: {err}") from None
    fx, fy, cx, cy = _initial_focals(preds, stack, info.shapes, fx, fy, cx, cy, K_known)
    fx, fy = fx.clone(), fy.clone()
    for c in range(int(camera.max()) + 1):  # a camera's focal: the median of its images' estimates (unless known)
        one = camera == c
        if int(one.sum()) > 1 and not bool(K_known[one].any()):
            fx[one] = fy[one] = fx[one].quantile(0.5)
    t_init = time.perf_counter()
    init, init_used = None, cfg.init
    if cfg.init == "averaging":
        try:
            init = init_averaging(stack, fx, fy, cx, cy, pose_head=cfg.pose_head)
        except GraphError as err:  # the graph is connected (checked above): the averaging itself failed
            warnings.warn(f"global_align: the motion-averaging start failed ({err}); starting from the spanning "
                          "tree instead", stacklevel=2)
            init_used = f"mst (averaging failed: {err})"
    if init is None:
        init = init_mst(stack, fx, fy, cx, cy)
    c2w, depth, pw_s, pw_R, pw_t = init.cam2world, init.depth, init.pw_s, init.pw_R, init.pw_t
    scale_fixed = False
    if known_poses:
        a, Ra, ta, scale_fixed = similarity_to_known(c2w, known_poses)
        c2w, depth, pw_s, pw_R, pw_t = apply_similarity(a, Ra, ta, c2w, depth, pw_s, pw_R, pw_t)
    if not scale_fixed:  # free scale: make the geometric mean of edge scales 1 (about the origin)
        a = float(torch.exp(-pw_s.log().mean()))
        if known_poses:  # scale about a known camera's centre so that camera stays where it was given
            anchor = c2w[min(known_poses), :3, 3].clone()
            ta = anchor * (1 - a)
        else:
            ta = torch.zeros(3, dtype=torch.float64)
        c2w, depth, pw_s, pw_R, pw_t = apply_similarity(a, torch.eye(3, dtype=torch.float64), ta,
                                                        c2w, depth, pw_s, pw_R, pw_t)
    # internal unit: typical depth ~ 1
    valid_depth = depth[stack.pix_valid]
    unit = float(valid_depth.median()) if valid_depth.numel() else 1.0
    unit = unit if math.isfinite(unit) and unit > 0 else 1.0
    c2w = c2w.clone()
    c2w[:, :3, 3] /= unit
    for i, T in known_poses.items():
        c2w[i] = T.double()
        c2w[i, :3, 3] /= unit
    pose_free = torch.tensor([i not in known_poses for i in range(n)])
    params = AlignParams(c2w, pose_free, depth / unit, fx, fy, cx, cy, ~K_known, pw_s / unit, pw_R,
                         pw_t / unit, scale_free=not scale_fixed, camera=camera)
    seconds_init = time.perf_counter() - t_init
    chunk = chunk_size_for(stack, cfg.max_chunk_pixels)
    prior = head_prior(stack, cfg.head_prior, *cfg.head_prior_deg, pose_free=pose_free,
                       dtype=params.base_cam2world.dtype) if cfg.pose_head else None
    report = run(params, stack, cfg, chunk, prior)
    with torch.no_grad():  # the losses above include the prior; its own share at the kept iterate
        report["head_prior_loss"] = float(prior.loss(params.cam2world())) if prior is not None else 0.0
    if report["stop_reason"] == "non-finite loss":  # stopped early: the poses are the best iterate's, not converged
        cause = "NaN or inf in the predictions" + (f", or too high a learning rate (lr={cfg.lr})"
                                                   if cfg.optimizer == "adam" else "")
        kept = (f"the best iterate so far is kept (loss {report['final_loss']:.4g}, from {report['init_loss']:.4g})"
                if report["iterations"] else "the initial state is returned, unoptimised")
        warnings.warn(f"global_align: the loss became non-finite after {report['iterations']} of {cfg.niter} "
                      f"iterations ({cause}); {kept}", RuntimeWarning, stacklevel=2)
    with torch.no_grad():
        c2w_out = params.cam2world().double()
        fxo, fyo, cxo, cyo = (x.double() for x in params.intrinsics())
        s_o, R_o, t_o = (x.double() for x in params.pw())
    depths, confs = fuse_depth(preds, stack.keys, info.shapes, c2w_out, fxo, fyo, cxo, cyo, s_o, R_o, t_o,
                               conf_transform, cfg.fuse_iters)
    if not known_poses:  # the world is image 0's camera frame (fused depths are per camera: unaffected)
        c2w_out = anchor_to_first(c2w_out)
    return _build(info, c2w_out, (fxo, fyo, cxo, cyo), depths, confs, unit, known_poses, K_given, K_known,
                  report={**report, "init_seconds": seconds_init, "total_seconds": time.perf_counter() - t_start,
                          "num_images": n, "num_edges": stack.num_edges, "stride": stride,
                          "opt_pixels_per_image": stack.num_pixels, "chunk_edges": chunk,
                          "scale_fixed_by_known_poses": scale_fixed, "init": init_used, "root": init.root,
                          "tree": init.tree,
                          "conf_transform": conf_transform,
                          "head_prior_edges": 0 if prior is None else prior.num_edges,
                          "known_pose_indices": sorted(known_poses),
                          "known_K_indices": [k for k in range(n) if K_known[k]],
                          "config": asdict(cfg)})


def check_cameras(camera: torch.Tensor, original_sizes, map_from_original, K_known=None, fx=None) -> None:
    """``check_one_camera`` for the images of each camera of ``camera`` (``camera_index``) that has several, the
    camera named in the message when there are several."""
    several = int(camera.max()) + 1 > 1
    for c in range(int(camera.max()) + 1):
        idx = torch.nonzero(camera == c).flatten().tolist()
        if len(idx) < 2:
            continue
        try:
            check_one_camera([original_sizes[k] for k in idx], torch.as_tensor(map_from_original)[idx],
                             None if K_known is None else K_known[idx], None if fx is None else fx[idx])
        except PointmapError as e:  # ShapeError is one
            if not several:
                raise
            raise type(e)(f"camera {c} (images {idx[:8]}{' ...' if len(idx) > 8 else ''}): {e}") from None


def check_one_camera(original_sizes, map_from_original, K_known=None, fx=None) -> None:
    """``shared_focal``'s preconditions: every image of one original size, resized and cropped alike (one focal
    in map pixels is then one camera); K known for all images or none, and if for all, one focal."""
    sizes = sorted(set(tuple(s) for s in original_sizes))
    if len(sizes) > 1:
        raise ShapeError(f"shared_focal expects images of one camera, all of one size; got sizes (w, h) {sizes[:5]}")
    mfo = torch.as_tensor(map_from_original, dtype=torch.float64)
    if not bool((mfo == mfo[0]).all()):
        raise ShapeError("shared_focal expects images resized and cropped alike (one map_from_original); got "
                         f"{sorted(set(tuple(float(x) for x in r) for r in mfo))[:3]}")
    if K_known is not None and bool(K_known.any()):
        if not bool(K_known.all()):
            raise PointmapError("shared_focal with K known for some images only: give K for all images (then the "
                                "focal is fixed) or for none")
        if fx is not None and float(fx.max() - fx.min()) > 1e-6 * float(fx.max()):
            raise PointmapError(f"shared_focal with known focals that differ ({sorted(set(round(float(f), 3) for f in fx))[:5]} "
                                "map px): one camera has one focal; drop shared_focal or give one K")


def _build(info, c2w, intr, depths, confs, unit, known_poses, K_given, K_known, report) -> Reconstruction:
    n = len(info.shapes)
    fx, fy, cx, cy = intr
    cam2world = c2w.clone()
    cam2world[:, :3, 3] *= unit
    cam2world = cam2world.float()
    for i, T in known_poses.items():
        cam2world[i] = T.to(torch.float32)
    K_map = torch.zeros(n, 3, 3, dtype=torch.float64)
    K_map[:, 0, 0], K_map[:, 1, 1], K_map[:, 0, 2], K_map[:, 1, 2], K_map[:, 2, 2] = fx, fy, cx, cy, 1.0
    K_orig = K_to_original(K_map, info.map_from_original).float()
    for i in range(n):
        if K_known[i]:
            K_orig[i] = K_given[i].to(torch.float32)
    # images of different sizes share one canvas, each at its top-left (Reconstruction.map_sizes); padding has
    # no depth and no confidence
    depth_z, map_sizes = to_canvas([(d * unit).float() for d in depths])
    conf = to_canvas([c.float() for c in confs])[0]
    for name, t in (("cam2world", cam2world), ("K", K_orig), ("depth_z", depth_z)):
        if not torch.isfinite(t).all():
            raise PointmapError(f"alignment produced non-finite {name}; the predictions are degenerate "
                                "(check confidences and that pairs overlap)")
    return Reconstruction(images=to_canvas(info.images)[0], map_sizes=map_sizes, cam2world=cam2world, K=K_orig, depth_z=depth_z,
                          conf=conf, map_from_original=info.map_from_original.float(),
                          original_sizes=list(info.original_sizes), names=list(info.names),
                          info={"align": report})
