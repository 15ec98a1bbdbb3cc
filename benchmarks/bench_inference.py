"""Inference speed: per-pair latency, FLOPs and achieved GFLOP/s next to the float32 matmul ceiling, and
encoder-cached N-image inference against naive per-pair encoding (as the official inference does).

    python benchmarks/bench_inference.py --presets small dust3r_224_linear --sizes 224 512 --runs 5
    python benchmarks/bench_inference.py --official /path/to/dust3r   # adds the official model, same run
    python benchmarks/bench_inference.py --presets small --sizes 160 512 --desc-stem 24   # + a stem row per preset
    python benchmarks/bench_inference.py --presets --models small --sizes 224   # the shipped file's own architecture

Prints markdown tables; results are recorded in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils.flop_counter import FlopCounterMode

import pointmap as pm

SHAPES = {160: (160, 160), 224: (224, 224), 512: (384, 512)}


def median_time(fn, runs: int, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def matmul_ceiling(n: int = 2048, runs: int = 5) -> float:
    """Achieved GFLOP/s of a float32 n x n matmul (the practical ceiling of this CPU)."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    t = median_time(lambda: a @ b, runs)
    return 2 * n**3 / t / 1e9


def flops_of(fn) -> int:
    """FLOPs of ``fn()`` as torch counts them, attention included: counted with attention in plain matmuls (the
    CPU's fused attention kernel is invisible to FlopCounterMode), which compute the same products."""
    with sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as fc:
        fn()
    return fc.get_total_flops()


def variants(presets, desc_stem: int = 0):
    """(label, ModelConfig) per preset, plus the same preset with a descriptor stem (compared in the same run)."""
    for name in presets:
        cfg = pm.PRESETS[name]
        yield name, cfg
        if desc_stem and cfg.has_desc:
            yield f"{name} + desc_stem {desc_stem}", cfg.replace(desc_stem=desc_stem)


def load_models(names) -> dict:
    """Each name or path of --models loaded once (``pm.load_model``), its parameters frozen; CheckpointError for one
    that is not a PointmapNet file (an ONNX export is timed by benchmarks/bench_onnx.py)."""
    models = {}
    for name in names:
        model = pm.load_model(name)
        if not isinstance(model, pm.PointmapNet):
            raise pm.CheckpointError(f"--models expected a PointmapNet checkpoint or shipped name, got {name!r} "
                                     f"({type(model).__name__}; time ONNX exports with benchmarks/bench_onnx.py)")
        models[name] = model.requires_grad_(False)  # FLOP counting hooks trip on parameters that need grad
    return models


def candidates(presets, models: dict, desc_stem: int = 0):
    """(label, a model factory, is a preset) for every row: the presets with random weights, then the loaded files."""
    for name, cfg in variants(presets, desc_stem):
        yield name, lambda c=cfg: pm.PointmapNet(c).eval().requires_grad_(False), True
    for name, model in models.items():
        cfg = model.cfg
        yield f"{Path(name).name} (file: {cfg.enc_depth} / {cfg.dec_depth} blocks)", lambda m=model: m, False


def bench_pairs(presets, sizes, runs, ceiling, official=None, desc_stem: int = 0, models=None):
    rows = []
    for name, make, is_preset in candidates(presets, models or {}, desc_stem):
        model = make()
        for size in sizes:
            H, W = SHAPES[size]
            a, b = torch.rand(1, 3, H, W), torch.rand(1, 3, H, W)
            with torch.inference_mode():
                fn = functools.partial(model, a, b)
                flops = flops_of(fn)
                t = median_time(fn, runs)
            rows.append((name, f"{H}x{W}", t, flops / 1e9, flops / t / 1e9, 100 * flops / t / 1e9 / ceiling))
            print(f"  {name} {H}x{W}: {t:.3f} s", file=sys.stderr, flush=True)
            if official and is_preset and name.startswith(("dust3r", "mast3r")):
                t_off = official_time(official, name, H, W, runs)
                rows.append((f"official {name}", f"{H}x{W}", t_off, flops / 1e9, flops / t_off / 1e9,
                             100 * flops / t_off / 1e9 / ceiling))
        del model
    print("\n| model | input | median s/pair | GFLOP/pair | GFLOP/s | % of matmul ceiling |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.3f} | {r[3]:.1f} | {r[4]:.1f} | {r[5]:.0f}% |")


def official_time(path, name, H, W, runs):
    """Time the official model of the same architecture (random weights) on the same input."""
    sys.path[:0] = [path, f"{path}/dust3r", f"{path}/croco", f"{path}/dust3r/croco"]
    from dust3r.model import AsymmetricCroCo3DStereo  # (official code, never committed)

    head = {"dust3r_224_linear": "linear", "dust3r_512_linear": "linear", "dust3r_512_dpt": "dpt"}.get(name)
    inf = float("inf")
    kw = dict(pos_embed="RoPE100", img_size=(512, 512), depth_mode=("exp", -inf, inf), conf_mode=("exp", 1, inf),
              enc_embed_dim=1024, enc_depth=24, enc_num_heads=16, dec_embed_dim=768, dec_depth=12, dec_num_heads=12,
              landscape_only=False)
    if head:
        net = AsymmetricCroCo3DStereo(head_type=head, output_mode="pts3d", **kw)
    else:
        from mast3r.model import AsymmetricMASt3R  # needs an official mast3r checkout as the path

        net = AsymmetricMASt3R(head_type="catmlp+dpt", output_mode="pts3d+desc24", two_confs=True,
                               desc_conf_mode=("exp", 0, inf), **kw)
    net.eval()
    v = lambda i: dict(img=torch.rand(1, 3, H, W) * 2 - 1, true_shape=torch.tensor([[H, W]]), instance=[str(i)])  # noqa: E731
    v1, v2 = v(0), v(1)
    with torch.inference_mode():
        return median_time(lambda: net(v1, v2), runs)


def bench_cache(preset, size, counts, runs, models=None):
    """Complete graph over N images: our path (encoder once per image, batched decoders) vs naive
    per-pair forward of both orders (every image re-encoded in every pair, as the official inference).
    ``preset``: one of ``models`` (loaded files, taken first) or a preset name (random weights)."""
    models = models or {}
    model = models[preset] if preset in models else pm.PointmapNet(pm.PRESETS[preset]).eval()
    H, W = SHAPES[size]
    print(f"\n| N images ({preset}, {H}x{W}, complete graph) | directed pairs | cached s | naive per-pair s | speed-up |")
    print("|---|---|---|---|---|")
    for n in counts:
        views = [torch.rand(3, H, W) for _ in range(n)]
        pairs = pm.make_pairs(n)

        def cached():
            pm.predict_pairs(model, views, pairs, batch_size=8, quiet=True)

        def naive():
            with torch.inference_mode():
                for i, j in pairs:
                    model(views[i][None], views[j][None])
                    model(views[j][None], views[i][None])

        tc, tn = median_time(cached, runs, 0), median_time(naive, runs, 0)
        print(f"| {n} | {2 * len(pairs)} | {tc:.2f} | {tn:.2f} | {tn / tc:.2f}x |", flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--presets", nargs="*", default=["small", "dust3r_224_linear"],
                   help="presets timed with random weights (none: --presets with no name)")
    p.add_argument("--models", nargs="+", default=[],
                   help="model files or shipped names (e.g. small) timed with their own architecture")
    p.add_argument("--sizes", nargs="+", type=int, default=[224, 512])
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--cache-preset", default="small",
                   help="the model of the N-image table: a preset, or one of --models (which it means when both)")
    p.add_argument("--cache-counts", nargs="*", type=int, default=[2, 4, 8, 16],
                   help="image counts of the N-image table (none: no table)")
    p.add_argument("--official", default=None, help="path to an official dust3r checkout (with croco) to compare")
    p.add_argument("--quick", action="store_true", help="small preset only, 3 runs, N up to 8")
    p.add_argument("--desc-stem", type=int, default=0,
                   help="also time each descriptor preset with a descriptor stem of this many channels")
    a = p.parse_args(argv)
    if a.quick:
        a.presets, a.runs, a.cache_counts, a.sizes = ["small"] if a.presets else [], 3, [2, 4, 8], [224]
    if set(a.sizes) - set(SHAPES):
        p.error(f"--sizes expected sizes among {sorted(SHAPES)}, got {sorted(set(a.sizes) - set(SHAPES))}")
    if set(a.presets) - set(pm.PRESETS):
        p.error(f"--presets expected names among {sorted(pm.PRESETS)}, got {sorted(set(a.presets) - set(pm.PRESETS))}")
    if a.cache_preset not in a.models and a.cache_preset not in pm.PRESETS:
        p.error(f"--cache-preset expected a preset among {sorted(pm.PRESETS)} or one of --models, got {a.cache_preset!r}")
    if a.runs < 1 or a.threads < 1 or min(a.cache_counts, default=2) < 2:
        p.error(f"--runs and --threads expected >= 1 and --cache-counts >= 2, got {a.runs}, {a.threads}, "
                f"{a.cache_counts}")
    if not a.presets and not a.models:
        p.error("expected at least one of --presets and --models, got neither")
    try:
        models = load_models(a.models)
    except pm.CheckpointError as e:
        p.error(str(e))
    torch.set_num_threads(a.threads)
    ceiling = matmul_ceiling()
    print(f"threads: {a.threads}; float32 matmul ceiling (2048^3): {ceiling:.1f} GFLOP/s")
    bench_pairs(a.presets, a.sizes, a.runs, ceiling, a.official, a.desc_stem, models)
    if a.cache_counts:
        bench_cache(a.cache_preset, a.sizes[0], a.cache_counts, max(1, a.runs // 2), models)
    return 0


if __name__ == "__main__":
    sys.exit(main())
