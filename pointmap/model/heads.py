"""Prediction heads: linear (pixel shuffle), DPT, and the MASt3R descriptor MLP; output transforms.

Every head maps the decoder's token list ``[enc_out, dec_1, ..., dec_L]`` (dec_L normalised) of one view
to a raw channel map [B, C, H, W]; ``postprocess`` turns it into points / confidences / descriptors
exactly as the official ``reg_dense_depth`` / ``reg_dense_conf`` / ``reg_desc`` do.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from pointmap.errors import ShapeError
from pointmap.model.blocks import LayerNorm, Mlp
from pointmap.model.config import ModelConfig


def tokens_to_map(tokens: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """[B, h*w, C] -> [B, C, h, w]."""
    return tokens.transpose(1, 2).reshape(tokens.shape[0], tokens.shape[2], h, w)


class ResidualConvUnit(nn.Module):
    def __init__(self, ch: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(ch, ch, 3, padding=1)
        self.conv2 = nn.Conv2d(ch, ch, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """DPT feature fusion: (skip + rcu1(lateral)) -> rcu2 -> bilinear x2 (align_corners) -> 1x1 conv."""

    def __init__(self, ch: int) -> None:
        super().__init__()
        self.resConfUnit1 = ResidualConvUnit(ch)
        self.resConfUnit2 = ResidualConvUnit(ch)
        self.out_conv = nn.Conv2d(ch, ch, 1)

    def forward(self, x: torch.Tensor, lateral: torch.Tensor | None = None) -> torch.Tensor:
        if lateral is not None:
            x = x + self.resConfUnit1(lateral)
        x = self.resConfUnit2(x)
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class Upsample2x(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)


class DPT(nn.Module):
    """Dense prediction transformer head on 4 hooked token maps (official ``DPTOutputAdapter_fix``)."""

    def __init__(self, cfg: ModelConfig, out_channels: int) -> None:
        super().__init__()
        self.hooks = cfg.dpt_hooks
        dims_in = (cfg.enc_dim, cfg.dec_dim, cfg.dec_dim, cfg.dec_dim)
        ld, fd = cfg.dpt_layer_dims, cfg.dpt_feature_dim
        self.act_postprocess = nn.ModuleList([
            nn.Sequential(nn.Conv2d(dims_in[0], ld[0], 1), nn.ConvTranspose2d(ld[0], ld[0], 4, stride=4)),
            nn.Sequential(nn.Conv2d(dims_in[1], ld[1], 1), nn.ConvTranspose2d(ld[1], ld[1], 2, stride=2)),
            nn.Sequential(nn.Conv2d(dims_in[2], ld[2], 1)),
            nn.Sequential(nn.Conv2d(dims_in[3], ld[3], 1), nn.Conv2d(ld[3], ld[3], 3, stride=2, padding=1)),
        ])
        self.scratch = nn.Module()
        for i in range(4):
            setattr(self.scratch, f"layer{i + 1}_rn", nn.Conv2d(ld[i], fd, 3, padding=1, bias=False))
            setattr(self.scratch, f"refinenet{i + 1}", FusionBlock(fd))
        self.head = nn.Sequential(
            nn.Conv2d(fd, fd // 2, 3, padding=1), Upsample2x(),
            nn.Conv2d(fd // 2, cfg.dpt_last_dim, 3, padding=1), nn.ReLU(),
            nn.Conv2d(cfg.dpt_last_dim, out_channels, 1),
        )
        self.patch = cfg.patch_size

    def forward(self, tokens: list, H: int, W: int) -> torch.Tensor:
        h, w = H // self.patch, W // self.patch
        s = self.scratch
        maps = [self.act_postprocess[i](tokens_to_map(tokens[k], h, w)) for i, k in enumerate(self.hooks)]
        l1, l2, l3, l4 = (getattr(s, f"layer{i + 1}_rn")(m) for i, m in enumerate(maps))
        p4 = s.refinenet4(l4)[:, :, : l3.shape[2], : l3.shape[3]]
        p3 = s.refinenet3(p4, l3)
        p2 = s.refinenet2(p3, l2)
        p1 = s.refinenet1(p2, l1)
        return self.head(p1)


class DescStem(nn.Module):
    """Full-resolution local features for the descriptor heads: three 3 x 3 convolutions (dilation 1, 2, 4:
    a 15-pixel receptive field) on the normalised image, run once per image like the encoder.

    The ViT sees 16 x 16 patches through one linear map; a descriptor decoded from a patch token cannot
    tell pixels inside the patch apart well, which is what 3-pixel matching needs. Output in token layout
    ``[B, h*w, C*p*p]`` (pixel-unshuffled) so it travels with the tokens (``Encoded.local``, the ONNX
    encoder/decoder interface)."""

    def __init__(self, channels: int, patch: int) -> None:
        super().__init__()
        self.patch = patch
        self.convs = nn.ModuleList([nn.Conv2d(3, channels, 3, padding=1),
                                    nn.Conv2d(channels, channels, 3, padding=2, dilation=2),
                                    nn.Conv2d(channels, channels, 3, padding=4, dilation=4)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for conv in self.convs:
            x = F.gelu(conv(x))
        return F.pixel_unshuffle(x, self.patch).flatten(2).transpose(1, 2)


class DownstreamHead(nn.Module):
    """One view's head: points + confidence (linear or DPT), plus optional MASt3R descriptors (with
    ``desc_stem``, refined by a 1 x 1 convolution over [stem features, descriptor channels], added as a
    residual and zero-initialised so that a model gaining a stem starts as the model it was)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        kind = cfg.head.split("+")[-1]
        if kind == "linear":
            self.proj = nn.Linear(cfg.dec_dim, 4 * cfg.patch_size**2)
        else:
            self.dpt = DPT(cfg, 4)
        if cfg.has_desc:
            cat_dim = cfg.enc_dim + cfg.dec_dim
            out = (cfg.desc_dim + int(cfg.two_confs)) * cfg.patch_size**2
            self.head_local_features = Mlp(cat_dim, int(cfg.desc_hidden_factor * cat_dim), out)
            if cfg.desc_stem:
                n = cfg.desc_dim + int(cfg.two_confs)
                self.desc_fuse = nn.Conv2d(cfg.desc_stem + n, n, 1)
                self.reset_fuse()

    def fuse_local(self, desc: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
        """desc [B, n, H, W] + desc_fuse([stem features, desc]); local in token layout [B, h*w, C*p*p]."""
        p = self.cfg.patch_size
        stem = F.pixel_shuffle(tokens_to_map(local, desc.shape[-2] // p, desc.shape[-1] // p), p)
        return desc + self.desc_fuse(torch.cat([stem, desc], dim=1))

    def reset_fuse(self) -> None:
        nn.init.zeros_(self.desc_fuse.weight)
        nn.init.zeros_(self.desc_fuse.bias)

    @torch.no_grad()
    def reset_conf(self, raw: float) -> None:
        """Make the confidence channel (channel 3) output ``raw`` at every pixel: its weights zeroed, its bias
        set. With the official ``vmin + exp(x)`` confidence, a channel driven to x = -13 passes gradients
        scaled by e^-13 and can never rise again (training/train.py, ``--conf_reset``); restarting it from a
        constant gives it back its gradient while leaving points and descriptors untouched."""
        if hasattr(self, "proj"):
            n = self.cfg.patch_size ** 2  # pixel_shuffle: channel c is rows c*p*p .. (c+1)*p*p - 1
            self.proj.weight[3 * n: 4 * n].zero_()
            self.proj.bias[3 * n: 4 * n].fill_(raw)
        else:
            last = self.dpt.head[-1]
            last.weight[3].zero_()
            last.bias[3].fill_(raw)

    def forward(self, tokens: list, H: int, W: int, local: torch.Tensor | None = None) -> torch.Tensor:
        """Raw channels [B, 4 (+ desc_dim + two_confs), H, W]: x, y, z, conf, desc..., desc_conf.
        ``local``: the DescStem's features in token layout, required when the config has ``desc_stem``."""
        p = self.cfg.patch_size
        if hasattr(self, "proj"):
            raw = F.pixel_shuffle(tokens_to_map(self.proj(tokens[-1]), H // p, W // p), p)
        else:
            raw = self.dpt(tokens, H, W)
        if self.cfg.has_desc:
            feats = self.head_local_features(torch.cat([tokens[0], tokens[-1]], dim=-1))
            desc = F.pixel_shuffle(tokens_to_map(feats, H // p, W // p), p)
            if self.cfg.desc_stem:
                if local is None:
                    raise ShapeError("this model has a descriptor stem (desc_stem): its heads need the encoder's "
                                     "local features (Encoded.local); got none")
                desc = self.fuse_local(desc, local)
            raw = torch.cat([raw, desc], dim=1)
        return raw


def regress_points(xyz: torch.Tensor, mode: tuple) -> torch.Tensor:
    """Official ``reg_dense_depth`` (no bounds): direction times f(norm); xyz channels-last."""
    kind = mode[0]
    if kind == "linear":
        return xyz
    d = xyz.norm(dim=-1, keepdim=True)
    direction = xyz / d.clamp_min(1e-8)
    if kind == "square":
        return direction * d.square()
    return direction * torch.expm1(d)


def regress_conf(x: torch.Tensor, mode: tuple) -> torch.Tensor:
    """Official ``reg_dense_conf``: vmin + exp(x) clipped, or a scaled sigmoid."""
    kind, vmin, vmax = mode
    if kind == "sigmoid":
        return (vmax - vmin) * torch.sigmoid(x) + vmin
    return vmin + x.exp().clamp(max=vmax - vmin)


def postprocess(raw: torch.Tensor, cfg: ModelConfig) -> dict:
    """Raw head channels [B, C, H, W] -> dict of channels-last outputs (see PairPrediction)."""
    fmap = raw.permute(0, 2, 3, 1)
    # channels: points (3), confidence (1), then descriptors (desc_dim) and their confidence (1); split, not
    # sliced: a slice's backward zero-fills and copies the whole map, once per slice
    sizes = [3, 1] + ([cfg.desc_dim] + [1] * int(cfg.two_confs) if cfg.has_desc else [])
    rest = fmap.shape[-1] - sum(sizes)
    parts = fmap.split(sizes + [rest] if rest > 0 else sizes, dim=-1)
    out = {"pts": regress_points(parts[0], cfg.depth_mode), "conf": regress_conf(parts[1].squeeze(-1), cfg.conf_mode)}
    if cfg.has_desc:
        desc = parts[2]
        out["desc"] = desc / desc.norm(dim=-1, keepdim=True)
        if cfg.two_confs:
            out["desc_conf"] = regress_conf(parts[3].squeeze(-1), cfg.desc_conf_mode)
        else:
            out["desc_conf"] = out["conf"].clone()
    return out


def rotation_from_6d(x: torch.Tensor) -> torch.Tensor:
    """[..., 6] -> [..., 3, 3] rotation: Gram-Schmidt on the two 3-vectors (Zhou et al. 2019); its columns are
    the orthonormalised first vector, the orthonormalised second, and their cross product."""
    a = F.normalize(x[..., 0:3], dim=-1)
    b = F.normalize(x[..., 3:6] - (a * x[..., 3:6]).sum(-1, keepdim=True) * a, dim=-1)
    return torch.stack([a, b, torch.cross(a, b, dim=-1)], dim=-1)


def patch_centres(h: int, w: int, device=None, dtype=None) -> torch.Tensor:
    """[h*w, 2] (x, y) of each patch centre, row-major, divided by half the long side: the long side spans
    [-1, 1] and the short side the same scale (so the aspect ratio shows)."""
    s = max(h, w)
    ys = (torch.arange(h, device=device, dtype=dtype) + 0.5 - h / 2) / (s / 2)
    xs = (torch.arange(w, device=device, dtype=dtype) + 0.5 - w / 2) / (s / 2)
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


def fourier(xy: torch.Tensor, n_freq: int) -> torch.Tensor:
    """[..., 2] coordinates -> [..., 4 * n_freq] sin/cos features at frequencies pi * 2^k / 2, k < n_freq."""
    freqs = torch.pi * 2.0 ** torch.arange(n_freq, device=xy.device, dtype=xy.dtype) / 2
    ang = torch.cat([xy[..., 0:1] * freqs, xy[..., 1:2] * freqs], dim=-1)
    return torch.cat([ang.sin(), ang.cos()], dim=-1)


class PoolBlock(nn.Module):
    """A query token attends to a set of tokens (pre-norm), then an MLP."""

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.norm_q, self.norm_kv, self.norm2 = LayerNorm(dim), LayerNorm(dim), LayerNorm(dim)
        self.q, self.kv, self.proj = nn.Linear(dim, dim), nn.Linear(dim, 2 * dim), nn.Linear(dim, dim)
        self.mlp = Mlp(dim, 2 * dim)

    def forward(self, q: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        B, N, C = x.shape
        h = self.heads
        qh = self.q(self.norm_q(q)).reshape(B, -1, h, C // h).transpose(1, 2)
        k, v = self.kv(self.norm_kv(x)).reshape(B, N, 2, h, C // h).permute(2, 0, 3, 1, 4)
        a = F.scaled_dot_product_attention(qh, k, v).transpose(1, 2).reshape(B, -1, C)
        q = q + self.proj(a)
        return q + self.mlp(self.norm2(q))


class MatchScores(nn.Module):
    """Logits [B, N1, N2] of where each view-1 token's content lies among view 2's tokens (training supervises
    them with the ground-truth correspondences, ``training.losses.cross_attention_loss``)."""

    def __init__(self, dim: int, inner: int = 64) -> None:
        super().__init__()
        self.inner = inner
        self.q, self.k = nn.Linear(dim, inner), nn.Linear(dim, inner)

    def forward(self, tok1: torch.Tensor, tok2: torch.Tensor) -> torch.Tensor:
        return self.q(tok1) @ self.k(tok2).transpose(1, 2) * self.inner ** -0.5


class PoseHead(nn.Module):
    """cam2 -> cam1 rigid transform [B, 4, 4] from a correspondence field and view 1's geometry.

    For every view-1 token: where its content lies in view 2 (the expectation of patch centres under a softmax
    over ``MatchScores``, with the spread and the peak of that softmax as its certainty), its own patch centre,
    and its 3D point (view 1's predicted points averaged over the patch, divided by their mean distance) -- the
    inputs of a PnP, as features -- plus its token. A learned query attends to these twice and a linear
    read-out gives a 6-D rotation and a translation in units of that mean distance (so the transform follows
    the scale of the predicted points). Pooling tokens alone did not learn: the tokens say what a patch
    matched, not where (cross-attention values carry no position), so the head is given the where.
    The read-out starts at zero weights and the identity bias: a fresh head predicts the identity pose, so a
    trunk whose view-2 head was trained to give cam1 points starts where it was.
    """

    n_freq = 6

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        d = cfg.dec_dim
        self.patch = cfg.patch_size
        self.match = MatchScores(d)
        self.embed = Mlp(8 * self.n_freq + 5, d, d)
        self.tok_proj = nn.Linear(d, d)
        self.query = nn.Parameter(torch.zeros(1, 1, d))
        self.blocks = nn.ModuleList([PoolBlock(d, cfg.dec_heads) for _ in range(2)])
        self.norm = LayerNorm(d)
        self.out = nn.Linear(d, 9)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        nn.init.normal_(self.query, std=0.02)
        nn.init.zeros_(self.out.weight)
        with torch.no_grad():
            self.out.bias.copy_(torch.tensor([1.0, 0, 0, 0, 1, 0, 0, 0, 0]))

    def forward(self, tok1: torch.Tensor, tok2: torch.Tensor, grid1: tuple, grid2: tuple,
                pts1: torch.Tensor) -> torch.Tensor:
        """tok1 [B, N1, C], tok2 [B, N2, C] last decoder tokens; pts1 [B, H1, W1, 3] view 1's points."""
        B = tok1.shape[0]
        c1 = patch_centres(*grid1, device=tok1.device, dtype=tok1.dtype)
        c2 = patch_centres(*grid2, device=tok1.device, dtype=tok1.dtype)
        P = self.match(tok1, tok2).softmax(-1)  # [B, N1, N2]
        E = P @ c2  # expected position of each view-1 token's content in view 2
        spread = ((P @ (c2 * c2).sum(-1, keepdim=True)) - (E * E).sum(-1, keepdim=True)).clamp_min(0).add(1e-6).sqrt()
        peak = P.amax(-1, keepdim=True)
        X1 = F.avg_pool2d(pts1.permute(0, 3, 1, 2), self.patch).flatten(2).transpose(1, 2)  # [B, N1, 3]
        scale = X1.norm(dim=-1).mean(1).clamp_min(1e-6)  # [B]
        feat = torch.cat([fourier(c1, self.n_freq).expand(B, -1, -1), fourier(E, self.n_freq),
                          X1 / scale[:, None, None], spread, peak], dim=-1)
        x = self.embed(feat) + self.tok_proj(tok1)
        q = self.query.expand(B, -1, -1)
        for blk in self.blocks:
            q = blk(q, x)
        o = self.out(self.norm(q[:, 0]))
        T = torch.zeros(B, 4, 4, dtype=o.dtype, device=o.device)
        T[:, :3, :3] = rotation_from_6d(o[:, :6])
        T[:, :3, 3] = o[:, 6:9] * scale[:, None]
        T[:, 3, 3] = 1
        return T


class FocalHead(nn.Module):
    """One view's focal [B] (pixels of its pointmap's grid) from its last decoder tokens and own-frame pointmap.

    The pointmap's own focal (``focal_from_pointmap``: principal point at the centre, the L1 fit of pixel offsets
    to the points' x / z, y / z; no gradient) is the starting estimate; the head reads, for every token, its patch
    centre, the mean ray of its points and that ray's offset from the pinhole fit (where the pointmap bends away
    from one focal), and the token itself, pools them with a learned query and multiplies the estimate by the
    exponential of a correction in [-3, 3]. The read-out starts at zero: a fresh head returns the pointmap's
    focal, so adding it to a trained model changes nothing until it is trained (``--focal_head_weight``). Why a
    head: the regression loss measures the pointmap's shape after normalising its scale, where one focal for
    every image costs little, and the model learned nearly that (session 55: slope 0.14 of log predicted on log
    true focal), while the pipeline's translation needs the focal (RTA@15 doubles with the true one).
    """

    n_freq = 6

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        d = cfg.dec_dim
        self.patch = cfg.patch_size
        self.embed = Mlp(4 * self.n_freq + 5, d, d)
        self.tok_proj = nn.Linear(d, d)
        self.query = nn.Parameter(torch.zeros(1, 1, d))
        self.blocks = nn.ModuleList([PoolBlock(d, cfg.dec_heads) for _ in range(2)])
        self.norm = LayerNorm(d)
        self.out = nn.Linear(d, 1)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        nn.init.normal_(self.query, std=0.02)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    @staticmethod
    def base_focal(pts: torch.Tensor) -> torch.Tensor:
        """[B] the pointmap's own focal (no gradient); max(H, W) (a 53-degree view) where it has none."""
        from pointmap.geometry.focal import focal_from_pointmap

        with torch.no_grad():
            f = focal_from_pointmap(pts.detach().float())
        # max(H, W) as a tensor op (a Python number would be fixed at the example size in an exported graph)
        side = torch.maximum(f.new_ones(pts.shape[1]).sum(), f.new_ones(pts.shape[2]).sum())
        return torch.where(torch.isfinite(f) & (f > 0), f, side.expand_as(f)).to(pts.dtype)

    def forward(self, tok: torch.Tensor, grid: tuple, pts: torch.Tensor) -> torch.Tensor:
        """tok [B, N, C] last decoder tokens; pts [B, H, W, 3] the view's points in its own frame."""
        B = tok.shape[0]
        h, w = grid
        half = torch.maximum(tok.new_ones(h).sum(), tok.new_ones(w).sum()) * (self.patch / 2)  # (see base_focal)
        f0 = self.base_focal(pts)
        c = patch_centres(h, w, device=tok.device, dtype=tok.dtype)  # [N, 2], the long side spans [-1, 1]
        X = F.avg_pool2d(pts.detach().permute(0, 3, 1, 2), self.patch).flatten(2).transpose(1, 2)  # [B, N, 3]
        z = X[..., 2:3]
        ok = torch.isfinite(X).all(-1, keepdim=True) & (z > 1e-6)
        ray = torch.where(ok, X[..., :2] / torch.where(ok, z, torch.ones_like(z)), torch.zeros_like(z))
        resid = (ray * (f0 / half)[:, None, None] - c).clamp(-4, 4)  # the pinhole fit's miss, in centre units
        zmean = torch.where(ok, z, torch.zeros_like(z)).sum(1, keepdim=True) / ok.sum(1, keepdim=True).clamp_min(1)
        logz = torch.where(ok, (z / zmean.clamp_min(1e-6)).clamp_min(1e-6).log(), torch.zeros_like(z)).clamp(-4, 4)
        feat = torch.cat([fourier(c, self.n_freq).expand(B, -1, -1), ray.clamp(-4, 4), resid, logz], dim=-1)
        x = self.embed(feat) + self.tok_proj(tok)
        q = self.query.expand(B, -1, -1)
        for blk in self.blocks:
            q = blk(q, x)
        return f0 * self.out(self.norm(q[:, 0]))[:, 0].clamp(-3, 3).exp()
