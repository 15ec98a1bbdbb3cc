"""PointmapNet: siamese ViT encoder -> two cross-attending decoders -> per-view heads.

Wiring only; the blocks live in blocks.py and heads.py. State-dict keys follow the official
DUSt3R/MASt3R layout, so official checkpoints load through checkpoint.py with alias handling only.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from pointmap.errors import ShapeError, is_int
from pointmap.geometry.cameras import transform_points
from pointmap.model.blocks import Block, DecoderBlock, LayerNorm, RopeCache, init_weights
from pointmap.model.config import ModelConfig
from pointmap.model.heads import DescStem, DownstreamHead, FocalHead, PoseHead, postprocess
from pointmap.prediction import PairPrediction


class PatchEmbed(nn.Module):
    def __init__(self, patch: int, dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, dim, kernel_size=patch, stride=patch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


def autocast_on(device_type: str) -> bool:
    """Whether autocast is on for ``device_type`` (its tokens may then be bf16): torch >= 2.4 takes the device type,
    older versions answer for CUDA only and have ``is_autocast_cpu_enabled``."""
    try:
        return torch.is_autocast_enabled(device_type)
    except TypeError:
        return torch.is_autocast_cpu_enabled() if device_type == "cpu" else torch.is_autocast_enabled()


class Encoded:
    """Encoder output of a batch of images: tokens [B, N, enc_dim], the patch grid (h, w), and for a model
    with a descriptor stem its local features ``local`` [B, N, desc_stem * patch**2] (else None)."""

    __slots__ = ("tokens", "grid", "local")

    def __init__(self, tokens: torch.Tensor, grid: tuple, local: torch.Tensor | None = None) -> None:
        self.tokens, self.grid, self.local = tokens, grid, local

    def __getitem__(self, idx) -> Encoded:
        return Encoded(self.tokens[idx], self.grid, None if self.local is None else self.local[idx])

    def split(self, sizes: list) -> list:
        """Consecutive batch slices of these sizes (``Tensor.split``: in training, one backward that concatenates,
        where indexing would zero-fill and copy the whole batch once per slice)."""
        local = [None] * len(sizes) if self.local is None else self.local.split(sizes)
        return [Encoded(t, self.grid, loc) for t, loc in zip(self.tokens.split(sizes), local)]

    @staticmethod
    def cat(encs: list) -> Encoded:
        """Concatenate along the batch (all on the same grid)."""
        first = encs[0]
        if any(e.grid != first.grid for e in encs):
            raise ShapeError(f"cannot batch encodings on different grids: {sorted({e.grid for e in encs})}")
        local = None if first.local is None else torch.cat([e.local for e in encs], dim=0)
        return Encoded(torch.cat([e.tokens for e in encs], dim=0), first.grid, local)


class PointmapNet(nn.Module):
    """``model(img1, img2) -> PairPrediction``.

    img1: [B, 3, H1, W1], img2: [B, 3, H2, W2], float in [0, 1], H and W multiples of 16 (the two views
    may differ in size). Returns (docs/conventions.md):
      pts1_cam1 [B, H1, W1, 3], pts2_cam1 [B, H2, W2, 3] (both in view 1's camera frame),
      conf1 [B, H1, W1], conf2 [B, H2, W2] (>= 1),
      desc1/desc2 [B, H, W, desc_dim] unit vectors and desc_conf1/2 [B, H, W] for descriptor heads, else None.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        if not isinstance(cfg, ModelConfig):
            hint = f" (PRESETS[{cfg!r}] is the config; pm.load_model({cfg!r}) the trained model)" \
                if isinstance(cfg, str) else ""
            raise ShapeError(f"PointmapNet expected a ModelConfig, got {type(cfg).__name__}{hint}")
        self.cfg = cfg
        self.patch_embed = PatchEmbed(cfg.patch_size, cfg.enc_dim)
        self.enc_blocks = nn.ModuleList([Block(cfg.enc_dim, cfg.enc_heads, cfg.mlp_ratio) for _ in range(cfg.enc_depth)])
        self.enc_norm = LayerNorm(cfg.enc_dim)
        self.decoder_embed = nn.Linear(cfg.enc_dim, cfg.dec_dim)
        self.dec_blocks = nn.ModuleList([DecoderBlock(cfg.dec_dim, cfg.dec_heads, cfg.mlp_ratio)
                                         for _ in range(cfg.dec_depth)])
        self.dec_blocks2 = nn.ModuleList([DecoderBlock(cfg.dec_dim, cfg.dec_heads, cfg.mlp_ratio)
                                          for _ in range(cfg.dec_depth)])
        self.dec_norm = LayerNorm(cfg.dec_dim)
        self.downstream_head1 = DownstreamHead(cfg)
        self.downstream_head2 = DownstreamHead(cfg)
        self.pose_head = PoseHead(cfg) if cfg.pose_head else None
        self.focal_head = FocalHead(cfg) if cfg.focal_head else None
        self.desc_stem = DescStem(cfg.desc_stem, cfg.patch_size) if cfg.desc_stem else None
        self.register_buffer("img_mean", torch.tensor(cfg.img_mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("img_std", torch.tensor(cfg.img_std).view(1, 3, 1, 1), persistent=False)
        self.rope = RopeCache(cfg.rope_base)
        self.apply(init_weights)
        w = self.patch_embed.proj.weight.data
        nn.init.xavier_uniform_(w.view(w.shape[0], -1))
        if self.pose_head is not None:
            self.pose_head.reset_parameters()
        if self.focal_head is not None:
            self.focal_head.reset_parameters()
        if self.desc_stem is not None:
            self.downstream_head1.reset_fuse()
            self.downstream_head2.reset_fuse()

    # -- checks ------------------------------------------------------------------------------------
    def check_images(self, name: str, img: torch.Tensor) -> None:
        p = self.cfg.patch_size
        if not isinstance(img, torch.Tensor) or img.ndim != 4 or img.shape[1] != 3 or img.shape[2] % p or \
                img.shape[3] % p or img.shape[2] == 0 or img.shape[3] == 0:
            shape = list(img.shape) if isinstance(img, torch.Tensor) else type(img).__name__
            raise ShapeError(f"{name} expected [B, 3, H, W] with H, W positive multiples of {p}, got {shape}")
        if not img.is_floating_point():
            raise ShapeError(f"{name} expected a float tensor in [0, 1], got dtype {img.dtype}")
        if torch.jit.is_tracing() or torch.compiler.is_compiling():
            return
        ref = next(iter(self.parameters()), None) if isinstance(self, nn.Module) else None  # (ONNX runs borrow this)
        if ref is not None and (torch.promote_types(img.dtype, ref.dtype) != ref.dtype or img.device != ref.device):
            raise ShapeError(f"{name} expected the model's {ref.dtype} on {ref.device}, got {img.dtype} on "
                             f"{img.device} (img.to(model's dtype and device))")
        head = next(iter(self.downstream_head1.parameters()), None) if isinstance(self, nn.Module) else None
        if head is not None and head.dtype != torch.float32:  # heads() hands them float32 tokens
            raise ShapeError(f"the prediction heads expected float32 weights, got {head.dtype}: convert the backbone "
                             "alone (export.graphs.half_backbone) or run under torch.autocast, not model.half() / "
                             ".to(torch.bfloat16)")
        if img.numel():
            lo, hi = float(img.detach().min()), float(img.detach().max())  # no autograd warning for a leaf
            if not (lo >= -1e-3 and hi <= 1 + 1e-3):  # also catches NaN
                raise ShapeError(f"{name} expected values in [0, 1], got range [{lo:.3g}, {hi:.3g}]")

    # -- stages ------------------------------------------------------------------------------------
    def encode(self, img: torch.Tensor) -> Encoded:
        """[B, 3, H, W] in [0, 1] -> Encoded (tokens after enc_norm; the descriptor stem's features)."""
        self.check_images("img", img)
        return self._encode(img)

    def _encode(self, img: torch.Tensor) -> Encoded:
        p = self.cfg.patch_size
        h, w = img.shape[-2] // p, img.shape[-1] // p
        img = (img - self.img_mean) / self.img_std
        x = self.patch_embed(img)
        rope = self.rope(h, w, self.cfg.enc_dim // self.cfg.enc_heads, x.device, x.dtype)
        for blk in self.enc_blocks:
            x = blk(x, rope)
        local = self.desc_stem(img) if self.desc_stem is not None else None
        return Encoded(self.enc_norm(x), (h, w), local)

    def decode(self, enc1: Encoded, enc2: Encoded) -> tuple[list, list]:
        """Both decoder branches, simultaneous exchange. Returns per view [enc, dec_1, ..., dec_L (normed)]."""
        hd = self.cfg.dec_dim // self.cfg.dec_heads
        r1 = self.rope(*enc1.grid, hd, enc1.tokens.device, enc1.tokens.dtype)
        r2 = self.rope(*enc2.grid, hd, enc2.tokens.device, enc2.tokens.dtype)
        f1, f2 = self.decoder_embed(enc1.tokens), self.decoder_embed(enc2.tokens)
        out1, out2 = [enc1.tokens], [enc2.tokens]
        for blk1, blk2 in zip(self.dec_blocks, self.dec_blocks2):
            f1, f2 = blk1(f1, f2, r1, r2), blk2(f2, f1, r2, r1)
            out1.append(f1)
            out2.append(f2)
        out1[-1], out2[-1] = self.dec_norm(out1[-1]), self.dec_norm(out2[-1])
        return out1, out2

    def heads(self, tok1: list, tok2: list, grid1: tuple, grid2: tuple,
              local1: torch.Tensor | None = None, local2: torch.Tensor | None = None) -> PairPrediction:
        """The prediction heads in float32, autocast off (as the official code runs them): under bf16 autocast the
        points drifted twice as far from float32's and the pose head's rotation from orthonormal by 8e-3."""
        device = tok1[-1].device.type
        if device == "meta":  # a shape-only copy (the pipeline's cost estimate): no autocast there, none to turn off
            return self._heads(tok1, tok2, grid1, grid2, local1, local2)
        with torch.autocast(device, enabled=False):
            return self._heads(tok1, tok2, grid1, grid2, local1, local2)

    def _heads(self, tok1, tok2, grid1, grid2, local1, local2) -> PairPrediction:
        p = self.cfg.patch_size
        tok1 = [t.float() for t in tok1]
        tok2 = [t.float() for t in tok2]
        local1 = None if local1 is None else local1.float()
        local2 = None if local2 is None else local2.float()
        o1 = postprocess(self.downstream_head1(tok1, grid1[0] * p, grid1[1] * p, local1), self.cfg)
        o2 = postprocess(self.downstream_head2(tok2, grid2[0] * p, grid2[1] * p, local2), self.cfg)
        T = f1 = f2 = None
        if self.focal_head is not None:  # (needs the pose head: o2["pts"] is still in view 2's own frame here)
            f1 = self.focal_head(tok1[-1], grid1, o1["pts"])
            f2 = self.focal_head(tok2[-1], grid2, o2["pts"])
        if self.pose_head is not None:  # o2["pts"] is in view 2's own frame: move it into view 1's
            T = self.pose_head(tok1[-1], tok2[-1], grid1, grid2, o1["pts"])
            o2["pts"] = transform_points(T, o2["pts"])
        return PairPrediction(pts1_cam1=o1["pts"], pts2_cam1=o2["pts"], conf1=o1["conf"], conf2=o2["conf"],
                              desc1=o1.get("desc"), desc2=o2.get("desc"),
                              desc_conf1=o1.get("desc_conf"), desc_conf2=o2.get("desc_conf"), cam2_to_cam1=T,
                              focal1=f1, focal2=f2)

    def check_encodings(self, enc1: Encoded, enc2: Encoded) -> None:
        """ShapeError unless both are this model's ``encode()`` outputs of one batch size: tokens [B, h*w, enc_dim]
        of floats on the grid (h, w) they carry, the descriptor stem's features [B, h*w, desc_stem * patch**2] for a
        model with one, finite values of the model's dtype and device. Checked when run eagerly (under tracing or
        compilation the shapes are symbolic: nothing is checked)."""
        if torch.jit.is_tracing() or torch.compiler.is_compiling():  # symbolic shapes: checked when run eagerly
            return
        L = self.cfg.desc_stem * self.cfg.patch_size ** 2
        for name, enc in (("enc1", enc1), ("enc2", enc2)):
            if not isinstance(enc, Encoded):
                raise ShapeError(f"{name} expected this model's encode() output (an Encoded), got {type(enc).__name__}")
            grid, t = enc.grid, enc.tokens
            if not (isinstance(grid, tuple) and len(grid) == 2 and all(is_int(g) and g > 0 for g in grid)):
                raise ShapeError(f"{name}.grid expected (h, w), two positive ints, got {grid!r}")
            h, w = grid
            if not isinstance(t, torch.Tensor) or t.ndim != 3 or t.shape[1] != h * w or t.shape[2] != self.cfg.enc_dim \
                    or not t.is_floating_point():
                got = f"{list(t.shape)} {t.dtype}" if isinstance(t, torch.Tensor) else type(t).__name__
                raise ShapeError(f"{name} expected this model's encode() output (float tokens [B, {h}*{w}, "
                                 f"{self.cfg.enc_dim}] for its grid {grid}), got tokens {got}")
            loc = enc.local
            if L and (not isinstance(loc, torch.Tensor) or tuple(loc.shape) != (t.shape[0], h * w, L)):
                got = list(loc.shape) if isinstance(loc, torch.Tensor) else type(loc).__name__
                raise ShapeError(f"{name}.local expected the descriptor stem's local features [B, {h}*{w}, {L}], got {got}")
        if enc1.tokens.shape[0] != enc2.tokens.shape[0]:
            raise ShapeError(f"batch sizes differ: {enc1.tokens.shape[0]} and {enc2.tokens.shape[0]}")
        ref = next(iter(self.parameters()), None) if isinstance(self, nn.Module) else None  # (ONNX runs borrow this)
        for name, enc in (("enc1", enc1), ("enc2", enc2)):
            t = enc.tokens
            if t.is_meta:  # shapes only (the pipeline counts FLOPs on the meta device): no values to check
                continue
            if ref is not None and (t.device != ref.device or (t.dtype != ref.dtype and not autocast_on(t.device.type))):
                raise ShapeError(f"{name} expected tokens of the model's {ref.dtype} on {ref.device}, got {t.dtype} "
                                 f"on {t.device}")
            if not bool(torch.isfinite(t).all()):
                raise ShapeError(f"{name} tokens hold NaN or inf values")

    def decode_pair(self, enc1: Encoded, enc2: Encoded) -> PairPrediction:
        """Decoders and heads on cached encoder outputs (used by inference to encode each image once)."""
        self.check_encodings(enc1, enc2)
        return self._decode_pair(enc1, enc2)

    def _decode_pair(self, enc1: Encoded, enc2: Encoded) -> PairPrediction:
        """``decode_pair`` unchecked: for encodings this model has just made (``forward``, each training step)."""
        tok1, tok2 = self.decode(enc1, enc2)
        return self.heads(tok1, tok2, enc1.grid, enc2.grid, enc1.local, enc2.local)

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> PairPrediction:
        self.check_images("img1", img1)
        self.check_images("img2", img2)
        if img1.shape[0] != img2.shape[0]:
            raise ShapeError(f"img1 and img2 need the same batch size, got {img1.shape[0]} and {img2.shape[0]}")
        if img1.shape[-2:] == img2.shape[-2:]:
            both = self._encode(torch.cat([img1, img2], dim=0))  # checked above
            B = img1.shape[0]
            enc1, enc2 = both.split([B, B])
        else:
            enc1, enc2 = self._encode(img1), self._encode(img2)
        return self._decode_pair(enc1, enc2)
