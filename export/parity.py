"""Parity of an exported model (onnxruntime) against PyTorch eager, on random images.

Criterion (fp32): for every output, max|onnx - torch| <= 1e-4 * (1 + max|torch|). Reduced-precision
exports (fp16, int8) are measured with the same numbers plus the relative error of the points, and
only fail on non-finite outputs.
"""

from __future__ import annotations

import time

import torch

from pointmap.prediction import PairPrediction

RTOL = 1e-4

# (H1, W1, H2, W2, batch)
_RES = [(224, 224), (512, 384), (384, 512)]
PARITY_CASES = {
    "quick": [(224, 224, 224, 224, 1)],
    "standard": [(h, w, h, w, 1) for h, w in _RES] + [(224, 224, 224, 224, 3)],
    "full": [(h, w, h, w, b) for b in (1, 3) for h, w in _RES] + [(512, 384, 384, 512, 1)],
}


def random_pair(H1: int, W1: int, H2: int, W2: int, B: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed + 7919 * H1 + W1 + 31 * B)
    return torch.rand(B, 3, H1, W1, generator=g), torch.rand(B, 3, H2, W2, generator=g)


def compare(ref: PairPrediction, got: PairPrediction) -> dict:
    """Per-output max abs diff, tolerance and their ratio; points' median/max relative error."""
    outs = {}
    worst_name, worst = None, 0.0
    finite = True  # every output of both runs finite
    for name, r in ref.as_dict().items():
        o = getattr(got, name)
        if o is None or tuple(o.shape) != tuple(r.shape):
            raise AssertionError(f"{name}: onnx shape {None if o is None else list(o.shape)} vs torch {list(r.shape)}")
        o, r = o.double(), r.double()
        both = bool(torch.isfinite(o).all()) and bool(torch.isfinite(r).all())  # a NaN in torch's is no pass
        finite &= both
        diff = float((o - r).abs().max())
        tol = RTOL * (1 + float(r.abs().max()))
        ratio = diff / tol if both and tol > 0 else float("inf")
        outs[name] = {"max_abs_diff": diff, "tol": tol, "ratio": ratio}
        if name.startswith("pts"):
            rel = (o - r).norm(dim=-1) / r.norm(dim=-1).clamp_min(1e-12)
            outs[name]["rel_err_median"] = float(rel.median())
            outs[name]["rel_err_p99"] = float(torch.quantile(rel.flatten()[:1_000_000].float(), 0.99))
        if ratio > worst or worst_name is None:
            worst_name, worst = name, ratio
    return {"outputs": outs, "worst_output": worst_name, "worst_ratio": worst, "finite": finite}


@torch.inference_mode()
def check_parity(model, runner, cases, *, strict: bool = True, seed: int = 0) -> dict:
    """Run ``model`` (PyTorch eager) and ``runner`` (onnxruntime) on random pairs for each case.

    Returns {"passed", "criterion", "cases": [{case, worst_output, worst_ratio, outputs, seconds}]}.
    strict: pass needs every ratio <= 1 (fp32); otherwise only finite outputs are required.
    """
    model = model.eval()
    p = model.cfg.patch_size  # the cases' sizes rounded to whole patches (224, 512 and 384 are for patch 16)
    report = []
    for case in cases:
        case = tuple(max(p, round(x / p) * p) for x in case[:4]) + tuple(case[4:])
        img1, img2 = random_pair(*case, seed=seed)
        t0 = time.perf_counter()
        ref = model(img1, img2)
        t1 = time.perf_counter()
        got = runner(img1, img2)
        t2 = time.perf_counter()
        res = compare(ref, got)
        H1, W1, H2, W2, B = case
        res["case"] = f"{H1}x{W1}+{H2}x{W2} batch {B}"
        res["seconds"] = {"torch": round(t1 - t0, 3), "onnxruntime": round(t2 - t1, 3)}
        report.append(res)
    ok = all(c["finite"] and (not strict or c["worst_ratio"] <= 1) for c in report)
    return {"passed": ok, "strict": strict, "criterion": "max|onnx - torch| <= 1e-4 (1 + max|torch|)",
            "cases": report}
