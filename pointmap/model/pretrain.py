"""Cross-view completion (CroCo) pretraining network: reconstruct masked patches of view 1 from its
visible patches and view 2. Its encoder/decoder keys equal PointmapNet's, so a pretrained state dict
initialises a PointmapNet (heads start fresh, ``dec_blocks2`` is copied from ``dec_blocks``)."""

from __future__ import annotations

import torch
import torch.nn as nn

from pointmap.errors import ShapeError
from pointmap.model.blocks import (
    Block,
    DecoderBlock,
    LayerNorm,
    RopeCache,
    init_weights,
    patch_positions,
    rope_tables,
)
from pointmap.model.config import ModelConfig
from pointmap.model.net import PatchEmbed


def check_mask(mask, B: int, N: int) -> None:
    """ShapeError unless ``mask`` is a bool [B, N] (True = masked) hiding as many tokens in every row (the visible
    tokens of the batch are gathered into one [B, Nv] tensor)."""
    if not (isinstance(mask, torch.Tensor) and mask.dtype == torch.bool and tuple(mask.shape) == (B, N)):
        got = f"{mask.dtype} {list(mask.shape)}" if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ShapeError(f"mask expected a bool tensor [{B}, {N}] (batch, patches of img1; True = masked), got {got}")
    if mask.is_meta or torch.compiler.is_compiling():  # no values to count
        return
    counts = mask.sum(1)
    if B and bool((counts != counts[0]).any()):
        raise ShapeError(f"mask expected the same number of masked patches in every row, got {counts.tolist()}")


class CrossViewCompletion(nn.Module):
    def __init__(self, cfg: ModelConfig, mask_ratio: float = 0.9) -> None:
        super().__init__()
        self.cfg, self.mask_ratio = cfg, mask_ratio
        self.patch_embed = PatchEmbed(cfg.patch_size, cfg.enc_dim)
        self.enc_blocks = nn.ModuleList([Block(cfg.enc_dim, cfg.enc_heads, cfg.mlp_ratio) for _ in range(cfg.enc_depth)])
        self.enc_norm = LayerNorm(cfg.enc_dim)
        self.decoder_embed = nn.Linear(cfg.enc_dim, cfg.dec_dim)
        self.mask_token = nn.Parameter(torch.zeros(1, 1, cfg.dec_dim))
        self.dec_blocks = nn.ModuleList([DecoderBlock(cfg.dec_dim, cfg.dec_heads, cfg.mlp_ratio)
                                         for _ in range(cfg.dec_depth)])
        self.dec_norm = LayerNorm(cfg.dec_dim)
        self.prediction_head = nn.Linear(cfg.dec_dim, cfg.patch_size**2 * 3)
        self.register_buffer("img_mean", torch.tensor(cfg.img_mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("img_std", torch.tensor(cfg.img_std).view(1, 3, 1, 1), persistent=False)
        self.rope = RopeCache(cfg.rope_base)
        self.apply(init_weights)
        nn.init.normal_(self.mask_token, std=0.02)
        w = self.patch_embed.proj.weight.data
        nn.init.xavier_uniform_(w.view(w.shape[0], -1))

    def random_mask(self, B: int, N: int, generator=None, device=None) -> torch.Tensor:
        """[B, N] bool, exactly round(mask_ratio * N) True (masked) per row."""
        n_mask = int(round(self.mask_ratio * N))
        order = torch.rand(B, N, generator=generator).argsort(1)
        mask = torch.zeros(B, N, dtype=torch.bool)
        mask.scatter_(1, order[:, :n_mask], True)
        return mask.to(device)

    def _encode(self, img, keep_idx=None):
        p = self.cfg.patch_size
        h, w = img.shape[-2] // p, img.shape[-1] // p
        x = self.patch_embed((img - self.img_mean) / self.img_std)
        hd = self.cfg.enc_dim // self.cfg.enc_heads
        if keep_idx is None:
            rope = self.rope(h, w, hd, x.device, x.dtype)
        else:
            x = torch.gather(x, 1, keep_idx[..., None].expand(-1, -1, x.shape[-1]))
            pos = patch_positions(h, w, x.device)[keep_idx]  # [B, Nv, 2]
            cos, sin = rope_tables(pos.reshape(-1, 2), hd, self.cfg.rope_base, x.dtype)
            rope = (cos.reshape(*pos.shape[:2], hd)[:, None], sin.reshape(*pos.shape[:2], hd)[:, None])
        for blk in self.enc_blocks:
            x = blk(x, rope)
        return self.enc_norm(x), (h, w)

    def forward(self, img1: torch.Tensor, img2: torch.Tensor, mask: torch.Tensor | None = None):
        """Returns (pred_patches [B, N, p*p*3], mask [B, N] True = masked)."""
        B = img1.shape[0]
        p = self.cfg.patch_size
        N = (img1.shape[-2] // p) * (img1.shape[-1] // p)
        if mask is None:
            mask = self.random_mask(B, N, device=img1.device)
        check_mask(mask, B, N)
        keep_idx = (~mask).nonzero()[:, 1].reshape(B, -1)
        vis, grid1 = self._encode(img1, keep_idx)
        f2, grid2 = self._encode(img2)
        full = self.mask_token.expand(B, N, -1).clone()
        full = full.scatter(1, keep_idx[..., None].expand(-1, -1, full.shape[-1]), self.decoder_embed(vis))
        y = self.decoder_embed(f2)
        hd = self.cfg.dec_dim // self.cfg.dec_heads
        r1 = self.rope(*grid1, hd, img1.device, full.dtype)
        r2 = self.rope(*grid2, hd, img1.device, full.dtype)
        x = full
        for blk in self.dec_blocks:
            x = blk(x, y, r1, r2)
        return self.prediction_head(self.dec_norm(x)), mask
