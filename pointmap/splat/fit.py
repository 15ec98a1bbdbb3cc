"""Joint optimisation of Gaussians and camera poses against the photos (InstantSplat-style).

- Adam with per-parameter learning rates (InstantSplat's: colour 0.025, opacity 0.05, scale 0.05,
  rotation 0.01, positions 1.6e-4 x scene extent with a per-point multiplier 1 + 99 (1 - sigmoid(conf))
  implemented as a reparametrisation, so less confident points move faster);
- loss 0.8 L1 + 0.2 (1 - SSIM) (kornia, 11x11 window), one view per step, black background;
- per-view pose deltas in se(3), composed inside the graph as world2cam_i = exp(xi_i) world2cam_init_i;
  view 0 is anchored (it fixes the gauge);
- coarse-to-fine: the first part of the run renders at half resolution (cheap, and poses converge
  there), the rest at the working resolution;
- optional densify/prune (clone Gaussians with large screen-space gradients, drop transparent ones).

The budget (working resolution, steps, Gaussians) is chosen by ``auto_budget``: on CPU it is sized so
that a 2-6 view scene fits in about two minutes; with CUDA it uses InstantSplat's settings.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch
import torch.nn.functional as F

from pointmap.errors import ShapeError, check_device, check_seed, is_int, is_number
from pointmap.geometry.cameras import K_LAYOUT, invert_rigid, is_pinhole_K, is_rigid, scale_intrinsics
from pointmap.geometry.rotations import se3_exp
from pointmap.reconstruction import Reconstruction
from pointmap.splat.gaussians import Gaussians
from pointmap.splat.rasterize import quat_to_rotmat, rasterize

# ----------------------------------------------------------------------------------------------------
# budget


def auto_budget(n_views: int, map_size: tuple[int, int], device: str | torch.device = "cpu") -> dict:
    """Working resolution (long side), steps and Gaussian count for a scene of ``n_views`` views whose
    maps are ``map_size`` = (width, height)."""
    long_side = max(map_size)
    if torch.device(check_device(device, "auto_budget: device")).type == "cuda":
        return {"max_side": min(long_side, 512), "steps": 1000, "max_gaussians": None, "coarse_frac": 0.0}
    # CPU: about 0.5 s CPU per step at 256x192 with 10k Gaussians (render + SSIM + backward + Adam),
    # a quarter of that at half resolution; 70 % of the steps run at half resolution.
    return {"max_side": min(long_side, 256), "steps": 160, "max_gaussians": 10_000, "coarse_frac": 0.7}


# ----------------------------------------------------------------------------------------------------
# helpers


def _resize_image(img: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[h, w, C] -> [height, width, C] (area-like antialiased bilinear)."""
    if img.shape[0] == height and img.shape[1] == width:
        return img
    x = img.permute(2, 0, 1)[None]
    x = F.interpolate(x, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return x[0].permute(1, 2, 0).contiguous()


def _level_size(recon: Reconstruction, i: int, level: tuple) -> tuple[int, int]:
    """View ``i``'s (width, height) at a working level (width, height) of the canvas: its share of the level."""
    h, w = recon.depth_z.shape[1:]
    vw, vh = recon.map_sizes[i]
    return max(1, round(vw * level[0] / w)), max(1, round(vh * level[1] / h))


def _level_view(recon: Reconstruction, maps: torch.Tensor, i: int, level: tuple, resize) -> torch.Tensor:
    """View ``i``'s own pixels of ``maps`` ([N, h, w, ...], the canvas) at a working level (width, height) of the
    canvas: resized on their own (``resize``: ``_resize_image`` or ``_resize_mask``) to their share of the level
    (the whole level for a view that fills the canvas). A view smaller than the canvas is rendered and fitted at
    that share only: no filter mixes the canvas padding into its edge and no pixel of it is rendered."""
    return resize(recon.crop(maps, i), *_level_size(recon, i, level))


def _level_K(recon: Reconstruction, K_map: torch.Tensor, level: tuple) -> torch.Tensor:
    """[N, 3, 3] intrinsics at a working level: each view's scaled by the factors its image was resized by (its
    rounded share of the level over its own size, not the canvas's factor, which differs by up to half a pixel
    across the view when that share is not a whole number of pixels)."""
    out = []
    for i, (vw, vh) in enumerate(recon.map_sizes):
        lw, lh = _level_size(recon, i, level)
        out.append(scale_intrinsics(K_map[i], lw / vw, lh / vh))
    return torch.stack(out)


def _size_for(width: int, height: int, max_side: int) -> tuple[int, int]:
    s = min(1.0, max_side / max(width, height))
    return max(1, int(round(width * s))), max(1, int(round(height * s)))


def _ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM of two [H, W, 3] images (kornia, 11x11 Gaussian window); with ``mask`` [H, W] bool, the mean of
    the SSIM map over the kept pixels (their windows may reach into the rest). An image with a side below 6 pixels
    (an align_view level of a strip, a coarse level of a panorama) gets the widest odd window its reflect padding
    allows, 2 side - 1 (kornia's 11 failed there with a padding RuntimeError)."""
    import kornia

    window = min(11, 2 * min(a.shape[0], a.shape[1]) - 1)
    m = kornia.metrics.ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], window)
    return m.mean() if mask is None else m[0][:, mask].mean()


def photometric_loss(render: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2,
                     mask: torch.Tensor | None = None) -> torch.Tensor:
    """0.8 L1 + 0.2 (1 - SSIM) of [H, W, 3] images (``ssim_weight``); with ``mask`` [H, W] bool, over the kept
    pixels only (0, still a function of ``render``, when none is kept). The target's pixels outside the mask are
    replaced by the render's (detached) first, so that no SSIM window near the mask's edge sees what the
    photograph shows there: the loss does not depend on it at all."""
    if mask is not None:
        if not bool(mask.any()):
            return render.sum() * 0.0
        target = torch.where(mask[..., None], target, render.detach())
    diff = (render - target).abs()
    l1 = diff.mean() if mask is None else diff[mask].mean()
    if ssim_weight <= 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - _ssim(render, target, mask))


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR in dB of [H, W, 3] images in [0, 1] (``a`` clamped); with ``mask`` [H, W] bool, over the kept pixels
    (NaN when none is kept)."""
    sq = (a.clamp(0, 1) - b) ** 2
    if mask is not None:
        if not bool(mask.any()):
            return float("nan")
        sq = sq[mask]
    mse = float(sq.mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def _resize_mask(mask: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[h, w] bool -> [height, width] bool: the pixels whose every source pixel, through the filter that resizes
    the image (``_resize_image``), is kept. A level pixel at the mask's edge mixes masked-out colours into the
    resized image, so it is left out: the fit does not depend on what the masked-out pixels show at any level
    (nearest-neighbour resizing kept 34 of 658 such pixels at half size, off by up to 0.1)."""
    if tuple(mask.shape) == (height, width):
        return mask
    return _resize_image(mask.float()[..., None], width, height)[..., 0] >= 1 - 1e-6


def _check_image(image, name="image") -> torch.Tensor:
    img = torch.as_tensor(np.asarray(image) if not isinstance(image, torch.Tensor) else image)
    if img.ndim != 3 or img.shape[-1] != 3 or img.shape[0] == 0 or img.shape[1] == 0:
        raise ShapeError(f"{name} expected [H, W, 3] with H, W >= 1, got {list(img.shape)}")
    if img.dtype == torch.uint8:
        img = img.float() / 255.0
    img = img.float()
    if not bool(torch.isfinite(img).all()):
        raise ShapeError(f"{name} values expected finite, in [0, 1] (or uint8), got "
                         f"{int((~torch.isfinite(img)).any(-1).sum())} pixels with NaN or inf")
    if float(img.min()) < -1e-3 or float(img.max()) > 1 + 1e-3:
        raise ShapeError(f"{name} values expected in [0, 1] (or uint8), got range "
                         f"[{float(img.min()):.3g}, {float(img.max()):.3g}]")
    return img


def _check_pose(T, name) -> torch.Tensor:
    T = torch.as_tensor(T, dtype=torch.float32)
    if tuple(T.shape) != (4, 4) or not bool(is_rigid(T)):  # is_rigid: finite too
        raise ShapeError(f"{name} expected a finite [4, 4] cam2world, rigid [R t; 0 0 0 1] with R a rotation, got "
                         f"{list(T.shape) if tuple(T.shape) != (4, 4) else T.tolist()}")
    return T


def _check_K(K) -> torch.Tensor:
    K = torch.as_tensor(K, dtype=torch.float32)
    if tuple(K.shape) != (3, 3) or not bool(is_pinhole_K(K)):
        raise ShapeError(f"K expected finite [3, 3] intrinsics with positive focals ({K_LAYOUT}), got "
                         f"{list(K.shape) if tuple(K.shape) != (3, 3) else K.tolist()}")
    return K


def _check_background(background, name: str = "background") -> torch.Tensor | None:
    """None (black) or an RGB colour [3] in [0, 1], as a float32 tensor; ShapeError otherwise."""
    if background is None:
        return None
    try:
        bg = torch.as_tensor(background, dtype=torch.float32)
    except (TypeError, ValueError, RuntimeError):
        bg = None
    if bg is None or tuple(bg.shape) != (3,) or not bool(((bg >= 0) & (bg <= 1)).all()):
        raise ShapeError(f"{name} expected an RGB colour [3] in [0, 1] (None: black), got {background!r}")
    return bg


LR_KEYS = ("means", "sh_dc", "opacity", "scales", "quats")


def _check_fit_options(*, steps, max_side, coarse_frac, lr, pose_lr, ssim_weight, densify_every, densify_grad,
                       time_budget, background) -> None:
    """ShapeError (one line) for a ``fit`` option out of its range (None means "the default" where allowed)."""
    def is_num(x):
        return is_number(x) and math.isfinite(x)

    bad = []
    if steps is not None and not (is_int(steps) and steps >= 0):
        bad.append(f"steps expected an int >= 0, got {steps!r}")
    if max_side is not None and not (is_int(max_side) and max_side >= 16):
        bad.append(f"max_side expected an int >= 16 (pixels), got {max_side!r}")
    if coarse_frac is not None and not (is_num(coarse_frac) and 0 <= coarse_frac < 1):
        bad.append(f"coarse_frac expected a fraction in [0, 1), got {coarse_frac!r}")
    if lr is not None:
        if not isinstance(lr, dict):
            bad.append(f"lr expected a dict over {LR_KEYS}, got {type(lr).__name__}")
        else:
            unknown = sorted(set(lr) - set(LR_KEYS))
            if unknown:
                bad.append(f"lr expected keys among {LR_KEYS}, got unknown {unknown}")
            bad += [f"lr[{k!r}] expected a finite rate > 0, got {v!r}" for k, v in lr.items()
                    if k in LR_KEYS and not (is_num(v) and v > 0)]
    if not (isinstance(pose_lr, (tuple, list)) and len(pose_lr) == 2 and all(is_num(v) and v >= 0 for v in pose_lr)):
        bad.append(f"pose_lr expected (rotation, translation) rates >= 0, got {pose_lr!r}")
    if not (is_num(ssim_weight) and 0 <= ssim_weight <= 1):
        bad.append(f"ssim_weight expected a weight in [0, 1], got {ssim_weight!r}")
    if not (is_int(densify_every) and densify_every >= 1):
        bad.append(f"densify_every expected an int >= 1, got {densify_every!r}")
    if not (is_num(densify_grad) and densify_grad > 0):
        bad.append(f"densify_grad expected a finite threshold > 0, got {densify_grad!r}")
    if time_budget is not None and not (is_num(time_budget) and time_budget > 0):
        bad.append(f"time_budget expected seconds > 0 (None: no limit), got {time_budget!r}")
    try:
        _check_background(background)
    except ShapeError as e:
        bad.append(str(e))
    if bad:
        raise ShapeError("fit: " + "; ".join(bad))


def _render_params(g: Gaussians):
    return g.means, g.quats, g.scales, g.opacities, g.colors


def _diverged(it: int, view, what: str, history: list) -> ShapeError:
    """The error that stops a fit whose step ``it`` left ``what`` NaN or inf."""
    last = f"; the last finite loss was {history[-1]['loss']:.4g}" if history else ""
    return ShapeError(f"fit: {what} NaN or inf at step {it} (view {view}{last}): the optimisation diverged; lower "
                      "the learning rates (lr=, pose_lr=)")


# ----------------------------------------------------------------------------------------------------
# result


@dataclass
class SplatFit:
    """Result of ``fit``: fitted Gaussians and refined cameras (DESIGN.md section 4 contract)."""

    gaussians: Gaussians
    cam2world: torch.Tensor          # [N, 4, 4] refined (view 0 unchanged)
    cam2world_init: torch.Tensor     # [N, 4, 4] as given
    K: torch.Tensor                  # [N, 3, 3] at the maps' resolution
    size: tuple                      # (width, height) of the maps
    history: list = field(default_factory=list)
    seconds: float = 0.0
    config: dict = field(default_factory=dict)

    def render(self, cam2world, K, width: int, height: int, background=None, *,
               return_all: bool = False):
        """Render the fitted Gaussians from an OpenCV ``cam2world`` with ``K`` for an image of
        ``width`` x ``height``; returns [H, W, 3] in [0, 1] (or the full RenderOutput)."""
        cam2world = _check_pose(cam2world, "cam2world")
        K = _check_K(K)
        bg = _check_background(background)
        with torch.no_grad():
            out = rasterize(*_render_params(self.gaussians), invert_rigid(cam2world), K, width, height, bg,
                            backend=self.config.get("backend", "torch"))
        return out if return_all else out.image.clamp(0, 1)

    def align_view(self, image, cam2world_init, K, steps: int = 100, *, max_side: int | None = None,
                   lr_rot: float = 2e-3, lr_trans: float | None = None, progress: bool = False):
        """Test-time pose alignment: optimise the pose of ``image`` (Gaussians frozen) starting from
        ``cam2world_init``; ``K`` refers to ``image``'s pixels. Returns the refined cam2world [4, 4]: of the poses
        the optimisation visits, the start and the last among them, the one whose render at full resolution
        matches ``image`` best (``photometric_loss``), so never one worse than the start."""
        img = _check_image(image)
        c2w0 = _check_pose(cam2world_init, "cam2world_init")
        K = _check_K(K)
        bad = []
        if not (is_int(steps) and steps >= 0):
            bad.append(f"steps expected an int >= 0, got {steps!r}")
        if max_side is not None and not (is_int(max_side) and max_side >= 16):
            bad.append(f"max_side expected an int >= 16 (pixels), got {max_side!r}")
        for key, v, default in (("lr_rot", lr_rot, ""), ("lr_trans", lr_trans, " (None: 1e-3 x depth_scale)")):
            if not ((v is None and default) or (is_number(v) and math.isfinite(v) and v >= 0)):
                bad.append(f"{key} expected a finite rate >= 0{default}, got {v!r}")
        if bad:
            raise ShapeError("align_view: " + "; ".join(bad))
        H, W = img.shape[:2]
        max_side = max_side or self.config.get("max_side", max(W, H))
        levels = _levels(W, H, max_side, coarse=0.5)
        g = self.gaussians
        params = [t.detach() for t in _render_params(g)]
        lr_trans = lr_trans if lr_trans is not None else 1e-3 * self.config.get("depth_scale", 1.0)
        rho = torch.zeros(3, requires_grad=True)
        phi = torch.zeros(3, requires_grad=True)
        opt = torch.optim.Adam([{"params": [rho], "lr": lr_trans}, {"params": [phi], "lr": lr_rot}])
        w2c0 = invert_rigid(c2w0)
        targets = {lv: (_resize_image(img, *lv), scale_intrinsics(K, lv[0] / W, lv[1] / H)) for lv in levels}
        fine = levels[-1]

        def fine_loss(w2c) -> float:  # NaN (an empty render) counts as no match at all
            with torch.no_grad():
                loss = float(photometric_loss(rasterize(*params, w2c, targets[fine][1], *fine).image,
                                              targets[fine][0]))
            return loss if math.isfinite(loss) else float("inf")

        best, best_loss = w2c0.clone(), fine_loss(w2c0)
        for it in range(steps):
            frac = it / max(steps, 1)
            lv = levels[0] if (len(levels) > 1 and frac < 0.5) else levels[-1]
            target, Ks = targets[lv]
            for grp, base in zip(opt.param_groups, (lr_trans, lr_rot)):
                grp["lr"] = base * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * frac)))
            w2c = se3_exp(torch.cat([rho, phi])) @ w2c0
            out = rasterize(*params, w2c, Ks, lv[0], lv[1])
            loss = photometric_loss(out.image, target)
            if it > 0 and lv == fine and float(loss.detach()) < best_loss:  # it 0: the start, scored above
                best_loss, best = float(loss.detach()), w2c.detach().clone()
            opt.zero_grad()
            loss.backward()
            opt.step()
        if steps > 0:  # the last update's pose, not yet scored
            last = (se3_exp(torch.cat([rho, phi])) @ w2c0).detach()
            if fine_loss(last) < best_loss:
                best = last
        return invert_rigid(best)

    def to_reconstruction(self, recon: Reconstruction) -> Reconstruction:
        """A new Reconstruction equal to ``recon`` but with the refined cam2world."""
        if len(recon) != self.cam2world.shape[0]:
            raise ShapeError(f"reconstruction has {len(recon)} views, the fit {self.cam2world.shape[0]}")
        info = dict(recon.info)
        info["splat_refined_poses"] = True
        return replace(recon, cam2world=self.cam2world.to(recon.cam2world.dtype).clone(), info=info)


def _levels(width: int, height: int, max_side: int, coarse: float) -> list:
    fine = _size_for(width, height, max_side)
    if coarse <= 0:
        return [fine]
    c = _size_for(width, height, max(16, max(fine) // 2))
    return [c, fine] if c != fine else [fine]


# ----------------------------------------------------------------------------------------------------
# fitting


def fit(recon: Reconstruction, gaussians: Gaussians, steps: int | None = None, optimize_poses: bool = True, *,
        max_side: int | None = None, coarse_frac: float | None = None, lr: dict | None = None,
        pose_lr: tuple = (1e-3, 3e-4), ssim_weight: float = 0.2, densify: bool = False,
        densify_every: int = 100, densify_grad: float = 2e-4, background=None, backend: str = "auto",
        seed: int = 0, progress: bool = True, time_budget: float | None = None, callback=None,
        masked: bool = True) -> SplatFit:
    """Refine ``gaussians`` (and, with ``optimize_poses``, the cameras of views 1..N-1) against the
    reconstruction's images.

    ``masked`` (default): the pixels ``recon.masks`` leaves out (the user's masks, e.g. people or cars that move
    between the photographs, and any confidence filter the reconstruction keeps) are left out of the photometric
    loss, as they are out of the initial points, so the Gaussians are not pulled towards them; False fits every
    pixel. ``history`` then reports each step's PSNR over the kept pixels. The canvas padding of a
    reconstruction from images of several sizes (``recon.map_sizes``) is never fitted, masked or not.

    steps / max_side (working resolution, long side) / coarse_frac (fraction of steps at half
    resolution) default to ``auto_budget``. ``lr`` overrides per-parameter learning rates (keys
    means, sh_dc, opacity, scales, quats); ``pose_lr`` = (rotation rad/step, translation as a fraction
    of ``depth_scale``, the median camera-to-Gaussian distance, per step), both decayed 10x over the run.
    ``time_budget`` (seconds) stops early. ``background``: None (black) or an RGB colour [3] in [0, 1]. A step that
    leaves the loss, the Gaussians or a pose NaN or inf stops the fit with a ShapeError (it diverged).
    """
    if not isinstance(recon, Reconstruction):
        raise ShapeError(f"fit expects a pointmap Reconstruction, got {type(recon).__name__}")
    if not isinstance(gaussians, Gaussians):
        raise ShapeError(f"fit expects Gaussians (from pm.splat.init_from), got {type(gaussians).__name__}")
    if len(gaussians) == 0:
        raise ShapeError("fit needs at least one Gaussian")
    _check_fit_options(steps=steps, max_side=max_side, coarse_frac=coarse_frac, lr=lr, pose_lr=pose_lr,
                       ssim_weight=ssim_weight, densify_every=densify_every, densify_grad=densify_grad,
                       time_budget=time_budget, background=background)
    seed = check_seed(seed)
    if not isinstance(masked, bool):
        raise ShapeError(f"masked expected True or False, got {masked!r}")
    t_start = time.perf_counter()
    device = torch.device("cpu")
    n, h, w = recon.depth_z.shape
    budget = auto_budget(n, (w, h), device)
    steps = budget["steps"] if steps is None else int(steps)
    max_side = budget["max_side"] if max_side is None else int(max_side)
    coarse_frac = budget["coarse_frac"] if coarse_frac is None else float(coarse_frac)
    if backend == "auto":
        backend = "torch"   # parameters live on the CPU here; gsplat is used when they are on CUDA
    rates = {"means": 1.6e-4, "sh_dc": 0.025, "opacity": 0.05, "scales": 0.05, "quats": 0.01}
    rates.update(lr or {})
    gen = torch.Generator().manual_seed(seed)

    # images and intrinsics at each resolution level
    levels = _levels(w, h, max_side, 0.5 if coarse_frac > 0 else 0.0)
    K_map = recon.K_map.float()
    user_masked = masked and recon.masks is not None and not bool(recon.masks.all())
    images = recon.images.float()
    data = {lv: ([_level_view(recon, images, i, lv, _resize_image) for i in range(n)], _level_K(recon, K_map, lv))
            for lv in levels}
    # the pixels fitted at each level: each view's own (images of several sizes: the canvas padding is neither
    # rendered nor fitted), within the user's masks when they are used
    fit_masks = {lv: [_level_view(recon, recon.masks, i, lv, _resize_mask) if user_masked else None
                      for i in range(n)] for lv in levels}
    # a view whose masks keep no pixel has nothing to fit: its steps would be spent on a loss of 0 (a thin mask
    # may keep none at a coarse level, whose filter reaches across it, and some at a finer one: fitted, its coarse
    # steps at a loss of 0)
    fitted = [i for i in range(n) if not user_masked or any(bool(fit_masks[lv][i].any()) for lv in levels)]
    if not fitted:
        raise ShapeError("fit: the reconstruction's masks keep no pixel of any view: nothing to fit")
    if len(fitted) < n:
        import warnings

        left = [recon.names[i] for i in range(n) if i not in fitted]
        warnings.warn(f"fit: the masks keep no pixel of {len(left)} view(s), which are left out of the fit (their "
                      f"poses stay as given): {left[:8]}", stacklevel=2)
    w2c_init = invert_rigid(recon.cam2world.float())
    g0 = gaussians.detach().to(torch.float32)

    # scales: ``extent`` as 3DGS (1.1 x the camera spread, for positions) and ``depth_scale`` (median
    # camera-to-Gaussian distance, for pose translations)
    centres = recon.cam2world[:, :3, 3].float()
    depth_scale = float(torch.cdist(g0.means[:: max(1, len(g0) // 4000)], centres).median())
    spread = float((centres - centres.mean(0)).norm(dim=-1).max()) * 1.1
    extent = max(spread, 0.05 * depth_scale)
    bg = _check_background(background)

    # parameters; positions are base + mult * offset so Adam's step is scaled per point
    conf = g0.conf if g0.conf is not None else torch.full((len(g0),), 10.0)
    params = {
        "offset": torch.zeros_like(g0.means), "sh_dc": g0.sh_dc.clone(), "opacity": g0.opacity_logits.clone(),
        "scales": g0.log_scales.clone(), "quats": g0.quats.clone(),
    }
    base = g0.means.clone()
    mult = 1.0 + 99.0 * (1.0 - torch.sigmoid(conf.float()))
    for t in params.values():
        t.requires_grad_(True)
    anchor = torch.ones(n, 1)
    anchor[0] = 0.0
    rho = torch.zeros(n, 3, requires_grad=True)
    phi = torch.zeros(n, 3, requires_grad=True)

    def make_opt():
        groups = [{"params": [params["offset"]], "lr": rates["means"] * extent, "name": "means"},
                  {"params": [params["sh_dc"]], "lr": rates["sh_dc"], "name": "sh_dc"},
                  {"params": [params["opacity"]], "lr": rates["opacity"], "name": "opacity"},
                  {"params": [params["scales"]], "lr": rates["scales"], "name": "scales"},
                  {"params": [params["quats"]], "lr": rates["quats"], "name": "quats"}]
        return torch.optim.Adam(groups, eps=1e-15)

    opt = make_opt()
    pose_groups = [{"params": [phi], "lr": pose_lr[0]}, {"params": [rho], "lr": pose_lr[1] * depth_scale}]
    pose_opt = torch.optim.Adam(pose_groups,
                                eps=1e-15) if optimize_poses and n > 1 else None

    def current_gaussians():
        return Gaussians(means=base + mult[:, None] * params["offset"], quats=params["quats"],
                         log_scales=params["scales"], opacity_logits=params["opacity"], sh_dc=params["sh_dc"])

    grad_acc = torch.zeros(len(base))
    grad_cnt = torch.zeros(len(base))
    history = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, desc="splat fit", leave=False)
    order: list = []
    n_coarse = int(round(coarse_frac * steps)) if len(levels) > 1 else 0
    for it in range(steps):
        if time_budget is not None and time.perf_counter() - t_start > time_budget:
            break
        frac = it / max(steps, 1)
        if pose_opt is not None:
            decay = 0.1 ** frac
            pose_opt.param_groups[0]["lr"] = pose_lr[0] * decay
            pose_opt.param_groups[1]["lr"] = pose_lr[1] * depth_scale * decay
        if not order:
            order = [fitted[k] for k in torch.randperm(len(fitted), generator=gen).tolist()]
        i = order.pop()
        lv = levels[0] if it < n_coarse else levels[-1]
        imgs, Ks = data[lv]
        g = current_gaussians()
        if pose_opt is not None:
            xi = torch.cat([rho[i], phi[i]]) * anchor[i]
            w2c = se3_exp(xi) @ w2c_init[i]
        else:
            w2c = w2c_init[i]
        vh, vw = imgs[i].shape[:2]  # the view's own share of the level (its top-left: the same intrinsics)
        out = rasterize(*_render_params(g), w2c, Ks[i], vw, vh, bg, backend=backend)
        if densify:
            out.means2d.retain_grad()
        mask = fit_masks[lv][i]
        loss = photometric_loss(out.image, imgs[i], ssim_weight, mask)
        lval = float(loss.detach())
        if not math.isfinite(lval):
            raise _diverged(it, recon.names[i], "the loss is", history)
        opt.zero_grad(set_to_none=True)
        if pose_opt is not None:
            pose_opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if pose_opt is not None:
            pose_opt.step()
        p = psnr(out.image.detach(), imgs[i], mask)
        history.append({"step": it, "view": i, "loss": lval, "psnr": p, "res": lv, "size": (vw, vh)})
        with torch.no_grad():
            if not all(bool(torch.isfinite(t).all()) for t in (*_render_params(current_gaussians()), rho, phi)):
                raise _diverged(it, recon.names[i], "the step left the Gaussians or the poses", history)
        if bar is not None:
            bar.set_postfix(loss=f"{lval:.4f}", psnr=f"{p:.2f}")
            bar.update(1)
        if densify:
            with torch.no_grad():
                vis = out.radii > 0
                if out.means2d.grad is not None:
                    # screen-space gradient in NDC units, as 3DGS thresholds it: pixels times half the rendered
                    # width in x, half its height in y
                    rh, rw = out.image.shape[:2]
                    gnorm = (out.means2d.grad * out.means2d.grad.new_tensor([rw / 2, rh / 2])).norm(dim=-1)
                    grad_acc[vis] += gnorm[vis]
                    grad_cnt[vis] += 1
                if (it + 1) % densify_every == 0 and 0.1 * steps < it < 0.8 * steps:
                    base, mult, params, grad_acc, grad_cnt = _densify_prune(
                        base, mult, params, grad_acc, grad_cnt, densify_grad, extent, gen)
                    opt = make_opt()
        if callback is not None:
            callback(it, history[-1])
    if bar is not None:
        bar.close()

    with torch.no_grad():
        final = current_gaussians().detach()
        final.conf = None
        if pose_opt is not None:
            xi = torch.cat([rho, phi], dim=1) * anchor
            w2c = se3_exp(xi) @ w2c_init
        else:
            w2c = w2c_init
        c2w = invert_rigid(w2c)
        c2w[0] = recon.cam2world[0].float()
    cfg = {"steps": steps, "steps_run": len(history), "max_side": max_side, "levels": levels,
           "coarse_frac": coarse_frac, "extent": extent, "depth_scale": depth_scale, "backend": backend,
           "n_gaussians": len(final),
           "optimize_poses": optimize_poses, "masked": user_masked}
    return SplatFit(gaussians=final, cam2world=c2w, cam2world_init=recon.cam2world.float().clone(),
                    K=K_map, size=(w, h), history=history, seconds=time.perf_counter() - t_start, config=cfg)


def _densify_prune(base, mult, params, grad_acc, grad_cnt, grad_thresh, extent, gen, percent_dense=0.01, split_n=2):
    """3DGS's densification: Gaussians with a large mean screen-space gradient grow, nearly transparent ones
    (opacity < 0.005) go. A small one (largest scale at most ``percent_dense`` x ``extent``) is cloned, a large one
    split into ``split_n`` Gaussians at its scales / (0.8 split_n) that replace it. Every new Gaussian stands at
    a sample of its parent, R diag(s) z with z ~ N(0, I), so that the copies can separate."""
    with torch.no_grad():
        means = base + mult[:, None] * params["offset"]
        avg = grad_acc / grad_cnt.clamp_min(1)
        keep = torch.sigmoid(params["opacity"]) > 0.005
        grow = (avg > grad_thresh) & keep
        split = grow & (params["scales"].exp().amax(dim=1) > percent_dense * extent)
        clone = grow & ~split
        born = torch.cat([torch.nonzero(clone).squeeze(1)] + [torch.nonzero(split).squeeze(1)] * split_n)
        idx = torch.cat([torch.nonzero(keep & ~split).squeeze(1), born])
        n_born = len(born)
        out = {k: v.detach()[idx].clone() for k, v in params.items()}
        new_base = means[idx].clone()
        if n_born:
            sc = params["scales"][born].exp()
            rot = quat_to_rotmat(params["quats"][born])
            local = torch.randn(n_born, 3, generator=gen) * sc
            new_base[-n_born:] += (rot @ local[:, :, None])[:, :, 0]
            out["scales"][len(idx) - n_born:] -= split[born][:, None] * math.log(0.8 * split_n)
        out["offset"] = torch.zeros_like(new_base)
        out = {k: v.requires_grad_(True) for k, v in out.items()}
        return new_base, mult[idx].clone(), out, torch.zeros(len(idx)), torch.zeros(len(idx))
