"""Transformer building blocks with 2D rotary position embeddings (RoPE2D, CroCo style).

Parameter names follow the official CroCo/DUSt3R layout (``attn.qkv``, ``cross_attn.projq``, ``norm_y``,
``mlp.fc1`` ...) so official state dicts load without renaming.
"""

from __future__ import annotations

from functools import partial

import torch
import torch.nn as nn
import torch.nn.functional as F

LayerNorm = partial(nn.LayerNorm, eps=1e-6)


def patch_positions(h: int, w: int, device=None) -> torch.Tensor:
    """[h*w, 2] integer (row, col) position of each patch token, row-major."""
    ys, xs = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
    return torch.stack([ys.reshape(-1), xs.reshape(-1)], dim=-1)


def rope_tables(pos: torch.Tensor, head_dim: int, base: float, dtype=torch.float32):
    """cos/sin tables [N, head_dim] for RoPE2D at token positions ``pos`` [N, 2] = (row, col).

    The first half of the channels encodes the row, the second half the column. Inside each half of
    size d, frequency k (k < d/2) is ``base ** (-2k / d)`` and channel i pairs with channel i + d/2
    ("rotate half" pairing), so each half's table is ``cat(freqs, freqs)``.
    """
    d = head_dim // 2
    inv_freq = 1.0 / (base ** (torch.arange(0, d, 2, device=pos.device).float() / d))  # [d/2]
    ang_y = pos[:, 0:1].float() * inv_freq  # [N, d/2]
    ang_x = pos[:, 1:2].float() * inv_freq
    ang = torch.cat([ang_y, ang_y, ang_x, ang_x], dim=-1)  # [N, head_dim]
    return ang.cos().to(dtype), ang.sin().to(dtype)


def rotate_half_2d(x: torch.Tensor) -> torch.Tensor:
    """Within each of the two halves [a | b] of the last dim, return [-b | a]."""
    *lead, D = x.shape
    x = x.reshape(*lead, 2, 2, D // 4)
    a, b = x.unbind(-2)  # unbind, not two selects: its backward is one stack, not a zero-filled copy per half
    return torch.stack([-b, a], dim=-2).reshape(*lead, D)


def apply_rope(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """x [B, heads, N, D] rotated by tables [N, D] (or [B, 1, N, D])."""
    return x * cos + rotate_half_2d(x) * sin


class RopeCache:
    """cos/sin tables per (grid h, w, head_dim, device, dtype), built once (not while tracing/exporting). ``base``
    is read-only: the tables already built hold it, and a model's config (which checkpoints, exports and prediction
    caches record) says it; another base is another model, built from a config that says so."""

    def __init__(self, base: float) -> None:
        self._base = float(base)
        self._cache: dict = {}

    @property
    def base(self) -> float:
        return self._base

    @base.setter
    def base(self, value) -> None:
        raise AttributeError(f"RopeCache.base is read-only (it is {self._base}, asked {value!r}): build the model "
                             "from a config with rope_base set, e.g. dataclasses.replace(model.cfg, rope_base=...)")

    def __call__(self, h: int, w: int, head_dim: int, device, dtype):
        key = (h, w, head_dim, str(device), dtype)
        tracing = torch.jit.is_tracing() or torch.onnx.is_in_onnx_export() or torch.compiler.is_compiling()
        if tracing or key not in self._cache:
            # built outside inference mode: a table first made under torch.inference_mode() must still be
            # usable by a later training step (inference tensors cannot be saved for backward)
            with torch.inference_mode(False), torch.no_grad():
                pos = patch_positions(h, w, device=device)
                tables = rope_tables(pos, head_dim, self.base, dtype)
            if tracing:
                return tables
            self._cache[key] = tables
        return self._cache[key]


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int, out: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, out or dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Attention(nn.Module):
    """Self-attention with RoPE on q and k."""

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, dim * 3)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, rope: tuple) -> torch.Tensor:
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.heads, C // self.heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)
        cos, sin = rope
        q, k = apply_rope(q, cos, sin), apply_rope(k, cos, sin)
        x = F.scaled_dot_product_attention(q, k, v)
        return self.proj(x.transpose(1, 2).reshape(B, N, C))


class CrossAttention(nn.Module):
    """Queries from one view, keys/values from the other; RoPE with each side's own positions."""

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.projq = nn.Linear(dim, dim)
        self.projk = nn.Linear(dim, dim)
        self.projv = nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)

    def _qk(self, x: torch.Tensor, y: torch.Tensor, rope_x: tuple, rope_y: tuple):
        B, Nq, C = x.shape
        h = self.heads
        q = self.projq(x).reshape(B, Nq, h, C // h).transpose(1, 2)
        k = self.projk(y).reshape(B, y.shape[1], h, C // h).transpose(1, 2)
        return apply_rope(q, *rope_x), apply_rope(k, *rope_y)

    def forward(self, x: torch.Tensor, y: torch.Tensor, rope_x: tuple, rope_y: tuple) -> torch.Tensor:
        B, Nq, C = x.shape
        q, k = self._qk(x, y, rope_x, rope_y)
        v = self.projv(y).reshape(B, y.shape[1], self.heads, C // self.heads).transpose(1, 2)
        x = F.scaled_dot_product_attention(q, k, v)
        return self.proj(x.transpose(1, 2).reshape(B, Nq, C))

    def scores(self, x: torch.Tensor, y: torch.Tensor, rope_x: tuple, rope_y: tuple,
               heads: int | None = None) -> torch.Tensor:
        """Pre-softmax attention logits [B, heads, Nq, Nk] of the first ``heads`` heads (all by default), the
        ones ``forward`` softmaxes: where each query token of one view looks in the other view (training
        supervises them with ground-truth correspondences, training.losses.cross_attention_loss)."""
        q, k = self._qk(x, y, rope_x, rope_y)
        if heads is not None:
            q, k = q[:, :heads], k[:, :heads]
        return (q @ k.transpose(-2, -1)) * q.shape[-1] ** -0.5


class Block(nn.Module):
    """Pre-norm ViT block: x + attn(norm1 x), then x + mlp(norm2 x)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float) -> None:
        super().__init__()
        self.norm1 = LayerNorm(dim)
        self.attn = Attention(dim, heads)
        self.norm2 = LayerNorm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor, rope: tuple) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), rope)
        return x + self.mlp(self.norm2(x))


class DecoderBlock(nn.Module):
    """Self-attention, cross-attention to the other view's (normalised) tokens, MLP."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float) -> None:
        super().__init__()
        self.norm1 = LayerNorm(dim)
        self.attn = Attention(dim, heads)
        self.norm2 = LayerNorm(dim)
        self.cross_attn = CrossAttention(dim, heads)
        self.norm_y = LayerNorm(dim)
        self.norm3 = LayerNorm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor, y: torch.Tensor, rope_x: tuple, rope_y: tuple) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), rope_x)
        x = x + self.cross_attn(self.norm2(x), self.norm_y(y), rope_x, rope_y)
        return x + self.mlp(self.norm3(x))


def init_weights(module: nn.Module) -> None:
    """xavier-uniform Linear weights with zero bias, unit LayerNorms (as the ViT/CroCo recipe)."""
    if isinstance(module, nn.Linear):
        nn.init.xavier_uniform_(module.weight)
        if module.bias is not None:
            nn.init.zeros_(module.bias)
    elif isinstance(module, nn.LayerNorm):
        nn.init.ones_(module.weight)
        nn.init.zeros_(module.bias)
