"""Differentiable Gaussian-splatting rasterizer: a tiled PyTorch backend for CPU (the default and the
reference) and an optional gsplat backend on CUDA.

Conventions (docs/conventions.md): OpenCV camera, ``world2cam`` [4, 4], ``K`` [3, 3] in pixels with
integer pixel coordinates at pixel centres, so pixel (row i, column j) is evaluated at (u, v) = (j, i).

Semantics follow the 3DGS / gsplat kernels:

- projection with the EWA Jacobian, camera-space x/z and y/z clamped to 1.3x the frustum for the
  Jacobian (the frustum through the image's outer pixel edges, -0.5 and W - 0.5: x/z in
  [-1.3 (cx + 0.5) / fx, 1.3 (W - 0.5 - cx) / fx]), plus a 0.3 px^2 low-pass on the 2D covariance (``eps2d``);
- alpha = min(0.999, opacity * exp(-q/2)); alphas below 1/255 are skipped;
- front-to-back compositing in global depth order, a pixel stops at the first Gaussian that would
  bring its transmittance below 1e-4 (that Gaussian is not composited);
- the bounding radius of a Gaussian is sqrt(2 ln(255 opacity) * lambda_max), the distance beyond which
  its alpha is below 1/255, so tile culling changes no pixel.

The torch backend bins Gaussians to square tiles, sorts (tile, depth), splits each tile's list into
fixed-size chunks and evaluates all (chunk x pixel x Gaussian) exponents as one batched matrix product
in tile-local coordinates. Compositing is a custom autograd Function with a hand-written backward
(the 3DGS back-to-front recurrence in vectorised form: suffix sums instead of a loop).
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import torch

from pointmap.errors import ConventionError, ShapeError, is_int, is_number
from pointmap.geometry.cameras import K_LAYOUT, is_pinhole_K

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_MIN = 1e-4


class _RenderTuple(NamedTuple):
    image: torch.Tensor   # [H, W, D]
    alpha: torch.Tensor   # [H, W]
    depth: torch.Tensor   # [H, W] expected z-depth (accumulated depth / alpha; 0 where alpha == 0)
    radii: torch.Tensor   # [N] int, 0 = culled


class RenderOutput(_RenderTuple):
    """``(image, alpha, depth, radii)``; also ``.means2d`` [N, 2] (pixels, differentiable) and
    ``.depth_acc`` [H, W] (sum of weight * z, not normalised)."""


# ----------------------------------------------------------------------------------------------------
# projection


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), any norm -> [N, 3, 3]."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*quats.shape[:-1], 3, 3)


def project_gaussians(means, quats, scales, world2cam, K, width, height, *, near=0.01, eps2d=0.3):
    """EWA projection. Returns (means2d [N, 2], conics [N, 3] = (a, b, c) of the inverse 2D covariance,
    depths [N], in_front [N] bool)."""
    R = world2cam[:3, :3]
    t = world2cam[:3, 3]
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    in_front = z > near
    zs = torch.where(in_front, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = fx * x / zs + cx
    v = fy * y / zs + cy
    # Jacobian with x/z, y/z clamped to 1.3x the frustum (3DGS), computed without in-place ops; the frustum's
    # edges are the image's outer pixel edges, u = -0.5 and u = W - 0.5 (pixel centres at integers)
    lim_xp = 1.3 * (width - 0.5 - cx) / fx
    lim_xn = 1.3 * (cx + 0.5) / fx
    lim_yp = 1.3 * (height - 0.5 - cy) / fy
    lim_yn = 1.3 * (cy + 0.5) / fy
    tx = zs * torch.minimum(torch.maximum(x / zs, -lim_xn), lim_xp)
    ty = zs * torch.minimum(torch.maximum(y / zs, -lim_yn), lim_yp)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / (zs * zs), zero, fy / zs, -fy * ty / (zs * zs)],
                    dim=-1).reshape(-1, 2, 3)
    Rg = quat_to_rotmat(quats)
    M = Rg * scales[:, None, :]                     # R diag(s)
    T = J @ R                                       # [N, 2, 3]
    TM = T @ M                                      # [N, 2, 3]
    cov = TM @ TM.transpose(1, 2)                   # [N, 2, 2]
    a = cov[:, 0, 0] + eps2d
    b = cov[:, 0, 1]
    c = cov[:, 1, 1] + eps2d
    det = a * c - b * b
    ok = in_front & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)
    return torch.stack([u, v], dim=-1), conics, z, ok, (a, b, c, det_s)


def _radii(cov_abc, opacities, ok):
    a, b, c, det = cov_abc
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.1))
    # opacities are in [0, 1] (rasterize refuses others): alpha = o exp(-q/2) falls below 1/255 past q = 2 ln(255 o)
    ext2 = 2.0 * torch.log((255.0 * opacities).clamp_min(1.0))
    r = torch.ceil(torch.sqrt(ext2 * lam))
    r = torch.where(ok & (opacities > ALPHA_MIN), r, torch.zeros_like(r))
    return r


# ----------------------------------------------------------------------------------------------------
# tile binning


def _bin_tiles(means2d, radii, depths, width, height, tile, chunk):
    """Return (gid [nc, C] long, -1 = padding; chunk_tile [nc] long; n_tiles_x, n_tiles_y)."""
    device = means2d.device
    ntx = (width + tile - 1) // tile
    nty = (height + tile - 1) // tile
    u, v = means2d[:, 0], means2d[:, 1]
    r = radii
    live = r > 0
    x0 = torch.floor((u - r) / tile).clamp(0, ntx - 1)
    x1 = torch.floor((u + r) / tile).clamp(-1, ntx - 1)
    y0 = torch.floor((v - r) / tile).clamp(0, nty - 1)
    y1 = torch.floor((v + r) / tile).clamp(-1, nty - 1)
    live = live & (u + r >= 0) & (u - r <= width - 1) & (v + r >= 0) & (v - r <= height - 1)
    x0, x1, y0, y1 = (t.long() for t in (x0, x1, y0, y1))
    nx = (x1 - x0 + 1).clamp_min(0)
    ny = (y1 - y0 + 1).clamp_min(0)
    cnt = torch.where(live, nx * ny, torch.zeros_like(nx))
    # generate (Gaussian, tile) pairs with Gaussians in depth order, then a stable sort by tile id
    # gives (tile, depth) order; a small-integer stable sort is a cheap radix sort
    by_depth = torch.argsort(depths, stable=True)
    cnt_d = cnt.index_select(0, by_depth)
    total = int(cnt_d.sum())
    if total == 0:
        return (torch.full((0, chunk), -1, dtype=torch.long, device=device),
                torch.zeros(0, dtype=torch.long, device=device), ntx, nty)
    g = torch.repeat_interleave(by_depth, cnt_d)
    start = torch.cumsum(cnt_d, 0) - cnt_d
    off = torch.arange(total, device=device) - torch.repeat_interleave(start, cnt_d)
    # (index_select is much faster than advanced indexing on CPU)
    nxg = nx.index_select(0, g)
    ty_off = torch.div(off, nxg, rounding_mode="floor")
    tx = x0.index_select(0, g) + (off - ty_off * nxg)
    ty = y0.index_select(0, g) + ty_off
    # drop tiles whose rectangle does not meet the bounding circle
    ug, vg, rg = u.index_select(0, g), v.index_select(0, g), r.index_select(0, g)
    px = torch.minimum(torch.maximum(ug, (tx * tile).to(u.dtype)), (tx * tile + tile - 1).to(u.dtype))
    py = torch.minimum(torch.maximum(vg, (ty * tile).to(v.dtype)), (ty * tile + tile - 1).to(v.dtype))
    keep = ((px - ug) ** 2 + (py - vg) ** 2 <= rg * rg).nonzero().squeeze(1)
    g = g.index_select(0, keep)
    if g.numel() == 0:
        return (torch.full((0, chunk), -1, dtype=torch.long, device=device),
                torch.zeros(0, dtype=torch.long, device=device), ntx, nty)
    tile_id = (ty * ntx + tx).index_select(0, keep)
    small = torch.int16 if ntx * nty < 2 ** 15 else torch.int32
    tile_id, order = torch.sort(tile_id.to(small), stable=True)
    g = g.index_select(0, order)
    tile_id = tile_id.long()
    n_tiles = ntx * nty
    per_tile = torch.bincount(tile_id, minlength=n_tiles)
    tile_start = torch.cumsum(per_tile, 0) - per_tile
    idx_in_tile = torch.arange(g.numel(), device=device) - tile_start.index_select(0, tile_id)
    chunks_per_tile = (per_tile + chunk - 1) // chunk
    chunk_start = torch.cumsum(chunks_per_tile, 0) - chunks_per_tile
    nc = int(chunks_per_tile.sum())
    slot = chunk_start.index_select(0, tile_id) * chunk + idx_in_tile
    gid = torch.full((nc * chunk,), -1, dtype=torch.long, device=device)
    gid.index_copy_(0, slot, g)
    gid = gid.reshape(nc, chunk)
    chunk_tile = torch.repeat_interleave(torch.arange(n_tiles, device=device), chunks_per_tile)
    return gid, chunk_tile, ntx, nty


# ----------------------------------------------------------------------------------------------------
# compositing


def _segmented_sums(tot, chunk_tile, n_tiles):
    """For per-chunk totals ``tot`` [nc, P] (chunks of a tile contiguous), return (exclusive prefix,
    exclusive suffix) within each tile, computed in float64."""
    t64 = tot.double()
    G = torch.cumsum(t64, 0)
    tile_sum = torch.zeros((n_tiles,) + tot.shape[1:], dtype=torch.float64, device=tot.device)
    tile_sum.index_add_(0, chunk_tile, t64)
    tile_base = torch.cumsum(tile_sum, 0) - tile_sum           # sum of all earlier tiles
    incl = G - tile_base[chunk_tile]
    prefix = incl - t64
    suffix = tile_sum[chunk_tile] - incl
    return prefix.to(tot.dtype), suffix.to(tot.dtype)


class _Composite(torch.autograd.Function):
    """Front-to-back compositing of chunked tile lists.

    Inputs: per-Gaussian ``g6`` [N, 6] = (u, v, conic a, b, c, log opacity) and ``vals`` [N, D+1] (colour
    channels and z-depth); the binning ``gid`` [nc, C] (-1 = padding), ``origin`` [nc, 2] (tile-origin pixel
    of each chunk), ``feat`` [P, 6] (per-pixel monomials of tile-local coordinates), ``chunk_tile`` [nc].
    The log-alpha of every (chunk slot, pixel) is one GEMM of per-slot coefficients with ``feat``.
    Outputs per tile: acc [T, P, D+1] (sum of weight * vals) and logT [T, P] (log final transmittance).
    Entries with alpha < 1/255 are zeroed; entries after a pixel's termination are masked (only when
    any pixel terminates, which is checked with one reduction). Every big temporary is updated in place.
    """

    @staticmethod
    def forward(ctx, g6, vals, gid, origin, feat, chunk_tile, n_tiles):
        pad = gid < 0
        gi = gid.clamp_min(0).reshape(-1)
        sl = g6.index_select(0, gi).reshape(*gid.shape, 6)
        mx = sl[..., 0] - origin[:, 0:1]
        my = sl[..., 1] - origin[:, 1:2]
        ca, cb, cc, logo = sl[..., 2], sl[..., 3], sl[..., 4], sl[..., 5]
        px = ca * mx + cb * my                                          # (conic @ m)_x
        py = cb * mx + cc * my
        const = logo - 0.5 * (px * mx + py * my)
        coef = torch.stack([-0.5 * ca, -cb, -0.5 * cc, px, py, const], dim=-1)
        coef.masked_fill_(pad[..., None], 0.0)[..., 5].masked_fill_(pad, -1e4)  # a padding slot: alpha 0 at every pixel
        # (its quadratic and linear terms are Gaussian 0's, large enough to beat -1e4 when it lies far off-screen)
        vals = vals.index_select(0, gi).reshape(*gid.shape, vals.shape[-1])
        # layout [nc, C, P]: Gaussians of a chunk along dim 1, the tile's pixels contiguous along dim 2
        a = torch.matmul(coef, feat.T)                                  # log alpha (one folded GEMM)
        a.exp_()
        torch.nn.functional.threshold_(a, ALPHA_MIN, 0.0)                # alpha < 1/255 -> 0
        a.clamp_(max=ALPHA_MAX)
        l1m = torch.rsub(a, 1.0).log_()                                 # log(1 - alpha), 0 where skipped
        log_after = l1m.cumsum(1)
        pre, _ = _segmented_sums(log_after[:, -1], chunk_tile, n_tiles)
        log_after.add_(pre[:, None])                                    # log T after each Gaussian
        stop = None
        if log_after.numel() and float(log_after.min()) < math.log(T_MIN):
            stop = log_after < math.log(T_MIN)                           # at or after a pixel's termination
            l1m.masked_fill_(stop, 0.0)
        lt_c = l1m.sum(1)                                               # [nc, P]
        T = log_after.sub_(l1m).exp_()
        if stop is not None:
            T.masked_fill_(stop, 0.0)                                   # T = 0 from termination on
        del l1m
        w = a * T
        acc_c = torch.bmm(w.transpose(1, 2), vals)                      # [nc, P, D+1]
        P = feat.shape[0]
        acc = torch.zeros(n_tiles, P, vals.shape[-1], dtype=vals.dtype, device=vals.device)
        acc.index_add_(0, chunk_tile, acc_c)
        lt = torch.zeros(n_tiles, P, dtype=a.dtype, device=a.device).index_add_(0, chunk_tile, lt_c)
        ctx.save_for_backward(a, T, vals, feat, chunk_tile, stop if stop is not None else torch.empty(0),
                              gi, pad, mx, my, sl)
        ctx.n_tiles = n_tiles
        ctx.n = g6.shape[0]
        return acc, lt

    @staticmethod
    def backward(ctx, g_acc, g_lt):
        a, T, vals, feat, chunk_tile, stop, gi, pad, mx, my, sl = ctx.saved_tensors
        w = a * T
        gv = g_acc.index_select(0, chunk_tile)                          # [nc, P, D+1]
        s = torch.bmm(vals, gv.transpose(1, 2))                         # dL/dw, [nc, C, P]
        g_vals = torch.bmm(w, gv) if ctx.needs_input_grad[1] else None
        ws = w.mul_(s)
        cs = ws.cumsum(1)
        del ws, w
        tot = cs[:, -1].clone()
        _, suf = _segmented_sums(tot, chunk_tile, ctx.n_tiles)
        tot.add_(suf).add_(g_lt.index_select(0, chunk_tile))
        # behind_k = sum_{j > k} w_j s_j + dL/dlogT  (in place in cs)
        behind = cs.neg_().add_(tot[:, None])
        behind.div_(torch.rsub(a, 1.0))
        g_la = s.mul_(T).sub_(behind)                                   # dL/dalpha
        del behind
        g_la.mul_(a)                                                    # dL/dlog(alpha); 0 where skipped
        if stop.numel():
            g_la.masked_fill_(stop, 0.0)
        if a.numel() and float(a.max()) >= ALPHA_MAX:
            g_la.masked_fill_(a >= ALPHA_MAX, 0.0)                      # clamped alphas have no gradient
        g = torch.matmul(g_la, feat).masked_fill_(pad[..., None], 0.0)   # dL/dcoef, [nc, C, 6]
        g0, g1, g2, g3, g4, g5 = g.unbind(-1)
        ca, cb, cc = sl[..., 2], sl[..., 3], sl[..., 4]
        px = ca * mx + cb * my
        py = cb * mx + cc * my
        g_slot = torch.stack([
            g3 * ca + g4 * cb - g5 * px,                                # d/du
            g3 * cb + g4 * cc - g5 * py,                                # d/dv
            -0.5 * (g0 + g5 * mx * mx) + g3 * mx,                        # d/da
            -g1 + g3 * my + g4 * mx - g5 * mx * my,                     # d/db
            -0.5 * (g2 + g5 * my * my) + g4 * my,                        # d/dc
            g5,                                                         # d/dlog(opacity)
        ], dim=-1).reshape(-1, 6)
        g_g6 = torch.zeros(ctx.n, 6, dtype=g.dtype, device=g.device).index_add_(0, gi, g_slot)
        g_v = None
        if g_vals is not None:
            g_vals.masked_fill_(pad[..., None], 0.0)
            g_v = torch.zeros(ctx.n, g_vals.shape[-1], dtype=g_vals.dtype, device=g_vals.device)
            g_v.index_add_(0, gi, g_vals.reshape(-1, g_vals.shape[-1]))
        return g_g6, g_v, None, None, None, None, None


_FEAT_CACHE: dict = {}


def _tile_features(tile, dtype, device):
    key = (tile, dtype, str(device))
    if key not in _FEAT_CACHE:
        ly, lx = torch.meshgrid(torch.arange(tile, dtype=dtype, device=device),
                                torch.arange(tile, dtype=dtype, device=device), indexing="ij")
        lx, ly = lx.reshape(-1), ly.reshape(-1)
        _FEAT_CACHE[key] = torch.stack([lx * lx, lx * ly, ly * ly, lx, ly, torch.ones_like(lx)], dim=-1)
    return _FEAT_CACHE[key]


def _rasterize_torch(means, quats, scales, opacities, colors, world2cam, K, width, height, background,
                     near, eps2d, tile, chunk):
    means2d, conics, depths, ok, cov_abc = project_gaussians(means, quats, scales, world2cam, K, width,
                                                             height, near=near, eps2d=eps2d)
    with torch.no_grad():
        radii = _radii(tuple(t.detach() for t in cov_abc), opacities.detach(), ok)
        gid, chunk_tile, ntx, nty = _bin_tiles(means2d.detach(), radii, depths.detach(), width, height,
                                               tile, chunk)
    D = colors.shape[-1]
    dtype = means2d.dtype
    n_tiles = ntx * nty
    origin = torch.stack([(chunk_tile % ntx) * tile, (chunk_tile // ntx) * tile], dim=-1).to(dtype)
    g6 = torch.cat([means2d, conics, torch.log(opacities.clamp_min(1e-12)).to(dtype)[:, None]], dim=-1)
    vals = torch.cat([colors, depths[:, None].to(colors.dtype)], dim=-1)
    feat = _tile_features(tile, dtype, means.device)
    acc, lt = _Composite.apply(g6, vals, gid, origin, feat, chunk_tile, n_tiles)
    col, dep = acc[..., :D], acc[..., D]

    def untile(x):
        x = x.reshape(nty, ntx, tile, tile, *x.shape[2:]).transpose(1, 2)
        return x.reshape(nty * tile, ntx * tile, *x.shape[4:])[:height, :width]

    img = untile(col)
    dep_acc = untile(dep)
    Tf = untile(lt).exp()
    if background is not None:
        img = img + Tf[..., None] * background
    alpha = 1.0 - Tf
    depth = torch.where(alpha > 1e-6, dep_acc / alpha.clamp_min(1e-6), torch.zeros_like(dep_acc))
    out = RenderOutput(img, alpha, depth, radii.to(torch.int32))
    out.means2d = means2d
    out.depth_acc = dep_acc
    return out


# ----------------------------------------------------------------------------------------------------
# gsplat backend (CUDA only, imported lazily)

_GSPLAT_STATE: dict = {}


def _gsplat_available(device) -> bool:
    if "ok" not in _GSPLAT_STATE:
        ok = False
        if torch.cuda.is_available():
            try:
                import gsplat  # noqa: F401

                ok = True
            except Exception as e:  # ImportError, OSError (JIT toolchain), ...
                _GSPLAT_STATE["err"] = repr(e)
        else:
            _GSPLAT_STATE["err"] = "CUDA is not available"
        _GSPLAT_STATE["ok"] = ok
    return _GSPLAT_STATE["ok"] and torch.device(device).type == "cuda"


def _rasterize_gsplat(means, quats, scales, opacities, colors, world2cam, K, width, height, background,
                      near, eps2d):
    import gsplat

    Kg = K.clone()
    Kg[0, 2] = K[0, 2] + 0.5   # gsplat puts pixel centres at i + 0.5
    Kg[1, 2] = K[1, 2] + 0.5
    bg = None if background is None else background.reshape(1, -1)
    img, alpha, meta = gsplat.rasterization(  # "RGB+ED": gsplat appends the expected depth to the colours itself
        means, quats, scales, opacities, colors, world2cam[None], Kg[None], width, height,
        near_plane=near, eps2d=eps2d, packed=False, render_mode="RGB+ED", backgrounds=None)
    rgb = img[0, ..., :-1]
    depth = img[0, ..., -1]
    a = alpha[0, ..., 0]
    if bg is not None:
        rgb = rgb + (1.0 - a)[..., None] * bg
    radii = meta["radii"][0]
    if radii.ndim == 2:
        radii = radii.max(-1).values
    out = RenderOutput(rgb, a, depth, radii.to(torch.int32))
    out.means2d = meta["means2d"][0]
    out.depth_acc = depth * a
    return out


# ----------------------------------------------------------------------------------------------------
# public entry point


def _as_tensor(name: str, t, like: torch.Tensor | None):
    """An input as a tensor: numpy arrays and lists are taken (on ``like``'s device, in its dtype); a tensor is left
    as given (its gradients kept); None stays None."""
    if t is None or isinstance(t, torch.Tensor):
        return t
    try:  # made in the means' dtype directly: a list's 0.2 through float32 would not be float64's 0.2
        out = torch.as_tensor(t) if like is None else torch.as_tensor(t, dtype=like.dtype, device=like.device)
    except (TypeError, ValueError, RuntimeError) as e:
        raise ShapeError(f"{name} expected a tensor or an array of numbers, got {type(t).__name__} ({e})") from None
    # the means set every input's dtype: integer means from a list become the default float
    return out if like is not None or out.is_floating_point() else out.to(torch.get_default_dtype())


def rasterize(means, quats, scales, opacities, colors, world2cam, K, width, height, background=None, *,
              backend: str = "torch", near: float = 0.01, eps2d: float = 0.3, tile: int = 4,
              chunk: int = 32) -> RenderOutput:
    """Render Gaussians into one pinhole camera.

    means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3] (standard deviations, not log),
    opacities [N] in [0, 1], colors [N, D] (any channels, typically RGB), world2cam [4, 4] (OpenCV),
    K [3, 3] (pixels, zero skew), background [D] or None (black).
    Returns ``RenderOutput(image [H, W, D], alpha [H, W], depth [H, W], radii [N])``; all inputs
    (world2cam included) receive gradients. ``backend``: "torch" (default), "gsplat" (CUDA; falls back
    to torch with a warning when unavailable) or "auto" (gsplat when available).
    """
    if not (is_int(width) and is_int(height) and width > 0 and height > 0):
        raise ShapeError(f"width and height expected positive ints, got {width!r} x {height!r}")
    width, height = int(width), int(height)
    means = _as_tensor("means", means, None)
    quats, scales, opacities, colors, world2cam, K, background = (
        _as_tensor(name, t, means) for name, t in (
            ("quats", quats), ("scales", scales), ("opacities", opacities), ("colors", colors),
            ("world2cam", world2cam), ("K", K), ("background", background)))
    if means.ndim != 2 or means.shape[1] != 3 or not means.is_floating_point():
        raise ShapeError(f"means expected floating-point [N, 3], got {list(means.shape)} {means.dtype}")
    n = means.shape[0]
    for name, t, shape in (("quats", quats, (n, 4)), ("scales", scales, (n, 3)),
                           ("opacities", opacities, (n,)),
                           ("world2cam", world2cam, (4, 4)), ("K", K, (3, 3))):
        if tuple(t.shape) != shape:
            raise ShapeError(f"{name} expected {list(shape)}, got {list(t.shape)}")
    if colors.ndim != 2 or colors.shape[0] != n:
        raise ShapeError(f"colors expected [N, D] with N = {n}, got {list(colors.shape)}")
    if background is not None and tuple(background.shape) != (colors.shape[1],):
        raise ShapeError(f"background expected [{colors.shape[1]}], got {list(background.shape)}")
    for name, t in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities),
                    ("colors", colors), ("background", background), ("world2cam", world2cam), ("K", K)):
        if t is not None and not bool(torch.isfinite(t.detach()).all()):
            raise ShapeError(f"{name} expected finite values, got {int((~torch.isfinite(t.detach())).sum())} NaN or inf")
    if not bool(is_pinhole_K(K.detach())):
        raise ConventionError(f"K expected pinhole intrinsics {K_LAYOUT} with positive focals and zero skew (a "
                              f"transposed K puts cx, cy in the bottom row), got {K.detach().tolist()}")
    if not (is_int(tile) and is_int(chunk) and tile >= 1 and chunk >= 1):
        raise ShapeError(f"tile and chunk expected ints >= 1, got {tile!r}, {chunk!r}")
    if not all(is_number(x) and math.isfinite(x) and x >= 0 for x in (near, eps2d)):
        raise ShapeError(f"near and eps2d expected finite numbers >= 0, got {near!r}, {eps2d!r}")
    o = opacities.detach()
    bad = o[(o < 0) | (o > 1)]
    if bad.numel():  # the radius bound takes opacity <= 1: above it, tile culling would cut into the footprint
        raise ShapeError(f"opacities expected values in [0, 1], got {bad.numel()} outside (first {float(bad[0])!r})")
    if backend not in ("torch", "gsplat", "auto"):
        raise ShapeError(f"backend must be 'torch', 'gsplat' or 'auto', got {backend!r}")
    dtype = means.dtype  # every input computed in the means' dtype (float64 colours with float32 means failed deep inside)
    quats, scales, opacities, colors = (t.to(dtype) for t in (quats, scales, opacities, colors))
    world2cam = world2cam.to(dtype)
    K = K.to(dtype)
    if background is not None:
        background = background.to(dtype)
    if backend in ("gsplat", "auto"):
        if _gsplat_available(means.device):
            return _rasterize_gsplat(means, quats, scales, opacities, colors, world2cam, K, width, height,
                                     background, near, eps2d)
        if backend == "gsplat" and not _GSPLAT_STATE.get("warned"):
            warnings.warn(f"gsplat backend unavailable ({_GSPLAT_STATE.get('err', 'tensors not on CUDA')}); "
                          "using the torch rasterizer", RuntimeWarning, stacklevel=2)
            _GSPLAT_STATE["warned"] = True
    return _rasterize_torch(means, quats, scales, opacities, colors, world2cam, K, width, height, background,
                            near, eps2d, tile, chunk)
