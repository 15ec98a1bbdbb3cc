"""``python -m export --model M --out DIR [--opset N] [--split] [--fp16] [--quantize int8] [--parity P]``

M: a shipped model name (e.g. ``small``), a checkpoint path (official .pth or our .safetensors), or
``preset:NAME`` for an architecture with random weights (e.g. ``preset:mast3r_512``).
Exit code 2 with a one-line message for bad input or a failed parity check.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    from export.exporter import DEFAULT_OPSET
    from export.parity import PARITY_CASES

    ap = argparse.ArgumentParser(prog="python -m export", description="Export a pointmap model to ONNX.")
    ap.add_argument("--model", required=True, help="shipped model name, checkpoint path, or preset:NAME (random weights)")
    ap.add_argument("--out", required=True, type=Path, help="output directory (written atomically)")
    ap.add_argument("--opset", type=int, default=DEFAULT_OPSET, help=f"ONNX opset (default {DEFAULT_OPSET}, min 18)")
    ap.add_argument("--split", action="store_true", help="encoder graph (per image) + decoder/heads graph (per pair)")
    prec = ap.add_mutually_exclusive_group()
    prec.add_argument("--fp16", action="store_true", help="float16 weights/activations, float32 inputs/outputs")
    prec.add_argument("--quantize", choices=["int8"], help="onnxruntime dynamic int8 quantisation of MatMul weights")
    ap.add_argument("--parity", choices=sorted(PARITY_CASES) + ["none"], default="standard",
                    help="parity check against PyTorch eager before writing (default: standard)")
    ap.add_argument("--external-data", action="store_true", help="weights in .onnx.data files even under 2 GB")
    ap.add_argument("--seed", type=int, default=None, help="seed for preset:NAME random weights (default 0)")
    ap.add_argument("--quiet", action="store_true")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if not args.quiet:  # our progress lines only (the ONNX optimiser logs every folded constant at INFO)
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        logging.getLogger("export").addHandler(handler)
        logging.getLogger("export").setLevel(logging.INFO)
    from export import export_model, resolve_model
    from export.exporter import check_target
    from pointmap.errors import PointmapError

    t0 = time.perf_counter()
    if args.seed is not None and not str(args.model).startswith("preset:"):
        print(f"error: --seed seeds the random weights of a preset:NAME model; {args.model} has its own weights",
              file=sys.stderr)
        return 2
    try:
        check_target(args.out, args.opset)  # before the model loads (a ViT-L checkpoint takes a while)
        model = resolve_model(args.model, seed=args.seed or 0)
        meta = export_model(model, args.out, split=args.split, opset=args.opset, fp16=args.fp16,
                            quantize=args.quantize, parity=args.parity,
                            external_data=True if args.external_data else None)
    except (PointmapError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except (FileExistsError, NotADirectoryError, PermissionError) as e:  # --out cannot be a folder here
        print(f"error: --out expected a folder to write the export into, got {str(args.out)!r}: {e.strerror}",
              file=sys.stderr)
        return 2
    if not args.quiet:
        print(f"wrote {args.out} ({meta['precision']}, {'split' if meta['split'] else 'single graph'}, "
              f"opset {meta['opset']}) in {time.perf_counter() - t0:.0f} s")
        for f in sorted(args.out.iterdir()):
            print(f"  {f.name:28s} {f.stat().st_size / 1e6:10.1f} MB")
        for c in meta.get("parity", {}).get("cases", []):
            print(f"  parity {c['case']:28s} worst {c['worst_output']:10s} diff/tol {c['worst_ratio']:.4f}  "
                  f"torch {c['seconds']['torch']:.2f} s  onnxruntime {c['seconds']['onnxruntime']:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
