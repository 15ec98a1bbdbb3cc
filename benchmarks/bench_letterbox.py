"""Centre crop against letterbox (padding) for photographs that are not square, on held-out rendered pairs.

Each square render's central 4:3 band (landscape: the middle rows; portrait: the middle columns) stands in for a
photograph. "crop" is what ``load_images`` does at the square sizes: the band's centre square, resized to the
network's size (a landscape + portrait pair: both cut to their common square). "pad" letterboxes the band at the
network's size, the pad filled with one grey value and its confidence zeroed before the pose is taken, as VGGT
pads. "whole" gives the network the band itself at its own shape (its short side cut to whole patches: 224 x 160
at 224), as ``load_images`` prepares photographs at the non-square sizes and as ``reconstruct`` runs a landscape +
portrait pair (each view at its own shape). The pose is the pointmaps' (``pm.relative_pose`` both ways); the truth
is the render's. A row for the whole square render gives the ceiling every approach loses from.

    python benchmarks/bench_letterbox.py --data HELDOUT_SHARDS --model small [--pairs 100] [--pad-values 0,0.5]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pointmap as pm  # noqa: E402
from pointmap.geometry.cameras import invert_rigid  # noqa: E402
from pointmap.geometry.rotations import relative_rotation_error_deg, translation_angle_deg  # noqa: E402

COMBOS = ("landscape + landscape", "portrait + portrait", "landscape + portrait")


def band(img: torch.Tensor, orientation: str) -> torch.Tensor:
    """The central 4:3 band of a square [3, S, S] image: S x 3S/4 (landscape) or 3S/4 x S (portrait)."""
    S = img.shape[-1]
    b = 3 * S // 4
    o = (S - b) // 2
    return img[:, o:o + b, :] if orientation == "landscape" else img[:, :, o:o + b]


def centre_square(img: torch.Tensor, side: int | None = None) -> torch.Tensor:
    """The centre ``side`` x ``side`` square (default: the short side's) of [3, h, w]."""
    h, w = img.shape[-2:]
    s = side or min(h, w)
    return img[:, (h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]


def crop_to(img: torch.Tensor, S: int, side: int | None = None) -> torch.Tensor:
    """``centre_square`` resized to S x S (bicubic, antialiased, clamped to [0, 1])."""
    c = centre_square(img, side)
    return F.interpolate(c[None], size=(S, S), mode="bicubic", align_corners=False, antialias=True)[0].clamp(0, 1)


def whole(img: torch.Tensor, patch: int = 16) -> torch.Tensor:
    """[3, h, w] centre-cropped to whole patches on both sides (no resize)."""
    h, w = img.shape[-2:]
    hh, ww = h // patch * patch, w // patch * patch
    return img[:, (h - hh) // 2:(h - hh) // 2 + hh, (w - ww) // 2:(w - ww) // 2 + ww]


def pad_to(img: torch.Tensor, S: int, value: float) -> tuple[torch.Tensor, torch.Tensor]:
    """[3, h, w] centred on an S x S canvas of ``value``; returns (image, [S, S] float mask, 1 on the image)."""
    h, w = img.shape[-2:]
    out, mask = torch.full((3, S, S), float(value)), torch.zeros(S, S)
    t, left = (S - h) // 2, (S - w) // 2
    out[:, t:t + h, left:left + w] = img
    mask[t:t + h, left:left + w] = 1
    return out, mask


def pair_errors(model, a, b, ma, mb, gt) -> tuple[float, float]:
    """(rotation, direction) errors in degrees of the pointmaps' pose of (a, b), pixels where a mask is 0 left out;
    180 when no pose is found."""
    with torch.inference_mode():
        fwd, rev = model(a[None], b[None]), model(b[None], a[None])
    if ma is not None:
        fwd, rev = replace(fwd, conf1=fwd.conf1 * ma, conf2=fwd.conf2 * mb), \
            replace(rev, conf1=rev.conf1 * mb, conf2=rev.conf2 * ma)
    T = pm.relative_pose(fwd, pred_reverse=rev)[0].double()
    if not bool(torch.isfinite(T).all()):
        return 180.0, 180.0
    rot = float(relative_rotation_error_deg(T[None, :3, :3], gt[None, :3, :3])[0])
    direction = float(translation_angle_deg(T[None, :3, 3], gt[None, :3, 3])[0])
    return rot, direction


def run(model, dataset, n_pairs: int, pad_values: list[float]) -> dict:
    """{(pair kind, method): [(rotation error, direction error), ...]} over the first ``n_pairs`` pairs."""
    out: dict = {}
    for k in range(min(n_pairs, len(dataset))):
        v1, v2 = dataset[k]
        S = v1["img"].shape[-1]
        if tuple(v1["img"].shape[-2:]) != (S, S) or tuple(v2["img"].shape[-2:]) != (S, S):
            raise ValueError(f"pair {k}: expected square renders, got {tuple(v1['img'].shape[-2:])} and "
                             f"{tuple(v2['img'].shape[-2:])}")
        gt = invert_rigid(v1["cam2world"].double()) @ v2["cam2world"].double()
        out.setdefault(("whole square render", "-"), []).append(
            pair_errors(model, v1["img"], v2["img"], None, None, gt))
        for combo in COMBOS:
            o1, o2 = (("landscape", "landscape"), ("portrait", "portrait"), ("landscape", "portrait"))[
                COMBOS.index(combo)]
            b1, b2 = band(v1["img"], o1), band(v2["img"], o2)
            side = min(*b1.shape[-2:], *b2.shape[-2:])  # the square both contain
            out.setdefault((combo, "crop"), []).append(
                pair_errors(model, crop_to(b1, S, side), crop_to(b2, S, side), None, None, gt))
            out.setdefault((combo, "whole"), []).append(pair_errors(model, whole(b1), whole(b2), None, None, gt))
            for value in pad_values:
                (a, ma), (b, mb) = pad_to(b1, S, value), pad_to(b2, S, value)
                out.setdefault((combo, f"pad {value:g}"), []).append(pair_errors(model, a, b, ma, mb, gt))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="held-out pair shards rendered square (e.g. eval_s424242)")
    p.add_argument("--model", default="small")
    p.add_argument("--pairs", type=int, default=100)
    p.add_argument("--size", type=int, default=None, help="render size read (default: the model's training size)")
    p.add_argument("--pad-values", default="0,0.5", help="grey levels in [0, 1] to pad with, comma-separated ('' for "
                   "no padded rows)")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    try:
        pads = [float(v) for v in a.pad_values.split(",") if v.strip()]
    except ValueError:
        p.error(f"--pad-values expected numbers in [0, 1] joined by commas, got {a.pad_values!r}")
    if not all(0 <= v <= 1 for v in pads):
        p.error(f"--pad-values expected numbers in [0, 1], got {a.pad_values!r}")
    if a.pairs < 1:
        p.error(f"--pairs expected >= 1, got {a.pairs}")
    torch.set_num_threads(max(1, a.threads))
    from pointmap.checkpoint import model_input_size
    from training.mix import open_pairs

    try:
        model = pm.load_model(a.model)
        size = a.size or model_input_size(model)
        ds = open_pairs(a.data, size=size, augment=False, split="all")
        res = run(model, ds, a.pairs, pads)
    except (pm.PointmapError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print("| pair | method | pairs | RRA@15 | RTA@15 | median rot err | median dir err |")
    print("|---|---|---|---|---|---|---|")
    for (combo, method), errs in res.items():
        e = torch.tensor(errs)
        print(f"| {combo} | {method} | {len(errs)} | {100 * (e[:, 0] < 15).float().mean():.1f}% | "
              f"{100 * (e[:, 1] < 15).float().mean():.1f}% | {e[:, 0].median():.1f} | {e[:, 1].median():.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
