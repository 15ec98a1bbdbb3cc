"""What gets exported: thin nn.Module wrappers around PointmapNet with plain-tensor inputs and outputs.

* ``FullGraph``:    img1 [B, 3, H1, W1], img2 [B, 3, H2, W2] -> pts1_cam1, pts2_cam1, conf1, conf2 (+ desc...)
* ``EncoderGraph``: img [B, 3, H, W] -> tokens [B, H/16, W/16, enc_dim]   (run once per image)
* ``DecoderGraph``: tokens1 [B, h1, w1, enc_dim], tokens2 [B, h2, w2, enc_dim] -> the same outputs as FullGraph

The token grid travels as the shape of the token tensor, so the decoder graph needs no extra inputs and
every size stays symbolic (dynamic batch, H, W; the two views may differ in size). RoPE tables are built
inside the graph from the grid shape (Range, Cos, Sin), there are no complex numbers and no custom ops.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from pointmap.model.net import Encoded, PointmapNet
from pointmap.runtime.onnx import DECODER_GRAPH, ENCODER_GRAPH, FULL_GRAPH, output_names

MAX_GRID = 512  # largest token grid side the dynamic shapes allow (8192 pixels)


def _outputs(model: PointmapNet, pred) -> tuple:
    return tuple(getattr(pred, n) for n in output_names(model.cfg))


class _Graph(nn.Module):
    """Inputs and outputs float32; the encoder and decoders compute in ``compute_dtype`` (float16 for
    ``--fp16``: then the model's backbone is half and its heads float, see ``half_backbone``)."""

    def __init__(self, model: PointmapNet, compute_dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        self.model = model
        self.compute_dtype = compute_dtype


class FullGraph(_Graph):
    """Both views encoded separately (so they may differ in size), then decoders + heads."""

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> tuple:
        m, dt = self.model, self.compute_dtype
        return _outputs(m, m.decode_pair(m.encode(img1.to(dt)), m.encode(img2.to(dt))))


class EncoderGraph(_Graph):
    """img -> tokens [B, h, w, enc_dim] (and, with a descriptor stem, local [B, h, w, desc_stem * p * p])."""

    def forward(self, img: torch.Tensor):
        enc = self.model.encode(img.to(self.compute_dtype))
        h, w = enc.grid
        tokens = enc.tokens.reshape(img.shape[0], h, w, enc.tokens.shape[-1]).float()
        if enc.local is None:
            return tokens
        return tokens, enc.local.reshape(img.shape[0], h, w, enc.local.shape[-1]).float()


class DecoderGraph(_Graph):
    def forward(self, tokens1: torch.Tensor, tokens2: torch.Tensor, local1: torch.Tensor | None = None,
                local2: torch.Tensor | None = None) -> tuple:
        encs = []
        for t, loc in ((tokens1, local1), (tokens2, local2)):
            B, h, w, C = t.shape
            if loc is not None:
                loc = loc.reshape(B, h * w, loc.shape[-1])
            encs.append(Encoded(t.to(self.compute_dtype).reshape(B, h * w, C), (h, w), loc))
        return _outputs(self.model, self.model.decode_pair(*encs))


def half_backbone(model: PointmapNet) -> PointmapNet:
    """A copy of ``model`` with the patch embedding, encoder and decoders (and the normalisation
    buffers) in float16 and the heads (and the pose and focal heads) in float32. PointmapNet.heads casts the tokens
    to float32, so the output transforms (exp of depth and confidence, norms) stay float32."""
    import copy

    half = copy.deepcopy(model).half()
    half.downstream_head1.float()
    half.downstream_head2.float()
    if half.pose_head is not None:  # it reads the float32 tokens PointmapNet.heads hands the heads
        half.pose_head.float()
    if half.focal_head is not None:  # so does the focal head
        half.focal_head.float()
    return half.eval()


def graph_specs(model: PointmapNet, split: bool, compute_dtype: torch.dtype = torch.float32) -> list[dict]:
    """For each graph to export: file name, wrapper, example inputs, dynamic shapes, and the names of
    every input/output dimension (written into the graph and the sidecar)."""
    cfg = model.cfg
    p, C = cfg.patch_size, cfg.enc_dim
    B = torch.export.Dim("batch", min=1, max=1024)
    dims = {k: torch.export.Dim(k, min=1, max=MAX_GRID) for k in ("gh1", "gw1", "gh2", "gw2", "gh", "gw")}
    # example sizes: batch 2, odd and unequal grids, so nothing specialises to 1 or to a square
    ex1, ex2 = torch.rand(2, 3, 5 * p, 7 * p), torch.rand(2, 3, 6 * p, 4 * p)
    outs = output_names(cfg)

    view = {"pts1_cam1": 1, "pts2_cam1": 2, "conf1": 1, "conf2": 2, "desc1": 1, "desc2": 2,
            "desc_conf1": 1, "desc_conf2": 2}
    pix = {}
    for n in outs:
        if n == "cam2_to_cam1":  # the pose head's transform: one per pair
            pix[n] = ["batch", 4, 4]
            continue
        if n in ("focal1", "focal2"):  # the focal head's: one per view
            pix[n] = ["batch"]
            continue
        v = view[n]
        tail = [3] if n.startswith("pts") else [cfg.desc_dim] if n in ("desc1", "desc2") else []
        pix[n] = ["batch", f"height{v}", f"width{v}", *tail]
    if not split:
        return [dict(
            file=FULL_GRAPH, role="full", wrapper=FullGraph(model, compute_dtype), args=(ex1, ex2),
            dynamic_shapes={"img1": {0: B, 2: p * dims["gh1"], 3: p * dims["gw1"]},
                            "img2": {0: B, 2: p * dims["gh2"], 3: p * dims["gw2"]}},
            inputs={"img1": ["batch", 3, "height1", "width1"], "img2": ["batch", 3, "height2", "width2"]},
            outputs=pix,
        )]
    args = (torch.rand(2, 5, 7, C), torch.rand(2, 6, 4, C))
    enc_out = {"tokens": ["batch", "grid_h", "grid_w", C]}
    dec_in = {"tokens1": ["batch", "grid_h1", "grid_w1", C], "tokens2": ["batch", "grid_h2", "grid_w2", C]}
    dec_dyn = {"tokens1": {0: B, 1: dims["gh1"], 2: dims["gw1"]}, "tokens2": {0: B, 1: dims["gh2"], 2: dims["gw2"]}}
    if cfg.desc_stem:  # the stem's local features travel beside the tokens, in the same [B, h, w, .] layout
        L = cfg.desc_stem * p * p
        args += (torch.rand(2, 5, 7, L), torch.rand(2, 6, 4, L))
        enc_out["local"] = ["batch", "grid_h", "grid_w", L]
        dec_in.update(local1=["batch", "grid_h1", "grid_w1", L], local2=["batch", "grid_h2", "grid_w2", L])
        dec_dyn.update(local1=dec_dyn["tokens1"], local2=dec_dyn["tokens2"])
    return [
        dict(file=ENCODER_GRAPH, role="encoder", wrapper=EncoderGraph(model, compute_dtype), args=(ex1,),
             dynamic_shapes={"img": {0: B, 2: p * dims["gh"], 3: p * dims["gw"]}},
             inputs={"img": ["batch", 3, "height", "width"]}, outputs=enc_out),
        dict(file=DECODER_GRAPH, role="decoder", wrapper=DecoderGraph(model, compute_dtype), args=args,
             dynamic_shapes=dec_dyn, inputs=dec_in, outputs=pix),
    ]
