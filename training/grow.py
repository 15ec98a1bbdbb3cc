"""Deepen a trained model without changing what it computes (net2net-style growth):

    python -m training.grow --init pointmap/weights/small.safetensors --enc_depth 8 --dec_depth 8 --out grown.safetensors

Every new block is a copy of the block it precedes with its output projections (self-attention ``proj``,
cross-attention ``proj``, MLP ``fc2``) zeroed: each residual branch then adds exactly zero, so the grown
model's outputs equal the original's, and training starts from the trained model's level instead of from
scratch. The copied inner weights (queries, keys, values, ``fc1``) give the new block meaningful features
the moment its output projections move off zero. Each copy is placed before its original: every original
block then sees what it saw before, and the last block is still an original (the layer whose attention
accuracy training logs). The outputs are preserved; the cross-attention loss, taken at every decoder
layer, is not exactly (a copy's queries lack the self-attention update its original adds before them).

New blocks are spread evenly: with L old blocks and L' >= L new ones, old block i is preceded by
``(i + 1) * (L' - L) // L - i * (L' - L) // L`` copies of itself. Both decoders grow alike (they share
a depth). The result is written as our fp32 .safetensors, which ``training.train --init`` fine-tunes;
its provenance lists every growth in ``grown_from``.
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import torch
from torch import nn

from pointmap.checkpoint import CheckpointError, load_model, save_model
from pointmap.errors import is_int
from pointmap.model import PointmapNet

SILENT = ("attn.proj", "cross_attn.proj", "mlp.fc2")  # a new block's output projections, zeroed at growth
GROWN = ("enc_blocks", "dec_blocks", "dec_blocks2")    # the block lists growth deepens


def _silent_copy(block: nn.Module) -> nn.Module:
    """A copy of ``block`` whose residual branches add exactly zero (its output projections zeroed)."""
    new = copy.deepcopy(block)
    with torch.no_grad():
        for name in SILENT:
            if not hasattr(new, name.split(".")[0]):  # an encoder block has no cross-attention
                continue
            lin = new.get_submodule(name)
            lin.weight.zero_()
            if lin.bias is not None:
                lin.bias.zero_()
    return new


def _copies_before(i: int, old: int, new: int) -> int:
    """How many silent copies of old block ``i`` precede it when ``old`` blocks grow to ``new`` (module doc)."""
    return (i + 1) * (new - old) // old - i * (new - old) // old


def new_block_indices(old: int, new: int) -> list[int]:
    """Positions of the silent copies in a block list grown from ``old`` to ``new`` blocks."""
    out, pos = [], 0
    for i in range(old):
        k = _copies_before(i, old, new)
        out.extend(range(pos, pos + k))
        pos += k + 1
    return out


def is_growth(old: tuple[int, int], new: tuple[int, int]) -> bool:
    """Whether (encoder, decoder) depths ``new`` can have grown from ``old``: none fewer, and not the same."""
    return old != new and all(o <= n for o, n in zip(old, new))


def new_blocks(enc_from: int, dec_from: int, enc_depth: int, dec_depth: int) -> dict[str, list[int]]:
    """The silent copies' positions in each block list of ``GROWN`` after growth from ``enc_from`` / ``dec_from``
    blocks to ``enc_depth`` / ``dec_depth`` (both decoders grow alike)."""
    dec = new_block_indices(dec_from, dec_depth)
    return {"enc_blocks": new_block_indices(enc_from, enc_depth), "dec_blocks": dec, "dec_blocks2": dec}


def silent_parameters(names, enc_from: int, dec_from: int, enc_depth: int, dec_depth: int) -> list[str]:
    """The parameters (of ``names``) that growth from ``enc_from`` / ``dec_from`` blocks to ``enc_depth`` /
    ``dec_depth`` zeroed: the new blocks' output projections (``SILENT``), weights and biases. They start at
    zero while every other weight starts trained, and AdamW moves every weight by about the same amount per
    step, so they stay small for long (``training.train --grown_lr`` scales their learning rate)."""
    new = new_blocks(enc_from, dec_from, enc_depth, dec_depth)
    prefixes = tuple(f"{g}.{i}.{m}." for g in GROWN for i in new[g] for m in SILENT)
    return [n for n in names if n.startswith(prefixes)]


def _deepen(blocks: nn.ModuleList, depth: int) -> nn.ModuleList:
    out = []
    for i, blk in enumerate(blocks):
        out.extend(_silent_copy(blk) for _ in range(_copies_before(i, len(blocks), depth)))
        out.append(blk)
    return nn.ModuleList(out)


def deepen(model: PointmapNet, *, enc_depth: int | None = None, dec_depth: int | None = None) -> PointmapNet:
    """A new model with ``enc_depth`` encoder and ``dec_depth`` decoder blocks (None: unchanged) computing the
    same function as ``model`` (see the module doc). ``model`` itself is left as it was. ValueError for a
    depth that is not an int above the current one (growth only; at least one more block), a model without
    blocks to copy, or a DPT head's decoder (its hooks index decoder layers)."""
    cfg = model.cfg
    enc_depth = cfg.enc_depth if enc_depth is None else enc_depth
    dec_depth = cfg.dec_depth if dec_depth is None else dec_depth
    for name, d in (("enc_depth", enc_depth), ("dec_depth", dec_depth)):
        if not is_int(d):
            raise ValueError(f"{name} expected an int, got {d!r}")
    if enc_depth < cfg.enc_depth or dec_depth < cfg.dec_depth:
        raise ValueError(f"growth only: expected enc_depth >= {cfg.enc_depth} and dec_depth >= {cfg.dec_depth}, "
                         f"got {enc_depth} and {dec_depth}")
    if (enc_depth, dec_depth) == (cfg.enc_depth, cfg.dec_depth):
        raise ValueError(f"nothing to grow: the model already has {cfg.enc_depth} encoder and {cfg.dec_depth} "
                         "decoder blocks")
    if (enc_depth > cfg.enc_depth and cfg.enc_depth == 0) or (dec_depth > cfg.dec_depth and cfg.dec_depth == 0):
        raise ValueError(f"growth copies existing blocks; the model has {cfg.enc_depth} encoder and "
                         f"{cfg.dec_depth} decoder blocks")
    if "dpt" in cfg.head and dec_depth != cfg.dec_depth:
        raise ValueError(f"a {cfg.head!r} head reads intermediate decoder layers; deepening its decoder would "
                         "change what they hold (only the encoder can grow)")
    grown = PointmapNet(cfg.replace(enc_depth=int(enc_depth), dec_depth=int(dec_depth)))
    src = copy.deepcopy(model).float()
    src.enc_blocks = _deepen(src.enc_blocks, enc_depth)
    src.dec_blocks = _deepen(src.dec_blocks, dec_depth)
    src.dec_blocks2 = _deepen(src.dec_blocks2, dec_depth)
    grown.load_state_dict(src.state_dict(), strict=True)
    prov = dict(getattr(model, "provenance", {}) or {})
    prov["grown_from"] = [*prov.get("grown_from", []), {"enc_depth": cfg.enc_depth, "dec_depth": cfg.dec_depth}]
    grown.provenance = prov
    return grown


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.grow", description=__doc__.split("\n\n")[0])
    p.add_argument("--init", required=True, help="a model load_model reads (shipped name or .safetensors)")
    p.add_argument("--enc_depth", type=int, default=None)
    p.add_argument("--dec_depth", type=int, default=None)
    p.add_argument("--out", required=True, help="the grown model (.safetensors, fp32)")
    a = p.parse_args(argv)
    try:
        model = load_model(a.init)
        if not isinstance(model, PointmapNet):
            raise CheckpointError(f"--init {a.init} is not a PyTorch model")
        grown = deepen(model, enc_depth=a.enc_depth, dec_depth=a.dec_depth)
        path = save_model(grown, Path(a.out))
    except (CheckpointError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    n0 = sum(t.numel() for t in model.state_dict().values())
    n1 = sum(t.numel() for t in grown.state_dict().values())
    print(f"{path}: encoder {model.cfg.enc_depth} -> {grown.cfg.enc_depth} blocks, decoders {model.cfg.dec_depth} -> "
          f"{grown.cfg.dec_depth}; {n0 / 1e6:.2f}M -> {n1 / 1e6:.2f}M parameters")
    return 0


if __name__ == "__main__":
    sys.exit(main())
