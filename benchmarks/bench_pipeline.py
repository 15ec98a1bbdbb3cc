"""Photos to a reconstruction, end to end: each stage's measured wall time against ``estimate_cost``'s estimate.

Renders one scene (the data engine, the demo scenes' camera; a seed range never trained on) with as many views as
the largest ``--counts``, then runs ``pm.reconstruct`` on its first N views for each N (the default graph: complete
up to 12 images) and prints one markdown row per N: pairs, inference and alignment time (estimated and measured;
alignment includes the pose refinement on matches, which the estimate counts per pair and coarse cell plus its
depth re-fit as a second dense run, with the refinement's own share in parentheses), the total, and
the aligned cameras' accuracy against the truth (RRA@15 over every camera pair), so a time is that of a working
reconstruction. The estimate is the baseline the measurement is compared with in the same run.

    nice .venv/bin/python benchmarks/bench_pipeline.py --model small --counts 4 8 16 --threads 2
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pointmap as pm  # noqa: E402
from benchmarks.bench_inference import load_models  # noqa: E402
from benchmarks.bench_pose import errors  # noqa: E402

SCENE_SEED = 31_337_500  # beside the demo scenes' range (data.demo_scenes.DEMO_SEED), never used for training
KINDS = ("room", "cluster", "courtyard")


def render_views(n: int, kind: str, size: int, seed: int = SCENE_SEED):
    """``n`` overlapping views of one procedural scene: (uint8 images [n] of [H, W, 3], cam2world [n, 4, 4])."""
    from data.cameras import DegenerateScene, sample_views
    from data.demo_scenes import DEMO_CAMERA
    from data.render import get_renderer
    from data.scene import make_scene

    rng = np.random.default_rng([seed, KINDS.index(kind)])
    for _ in range(20):
        scene = make_scene(rng, kind, low_texture_share=0.0)
        try:
            vs = sample_views(rng, scene, get_renderer(), n, size, DEMO_CAMERA)
        except DegenerateScene:
            continue
        return [v.rgb for v in vs.views], np.stack([v.cam2world for v in vs.views])
    raise RuntimeError(f"bench_pipeline: no acceptable {n}-view {kind} scene in 20 tries (seed {seed})")


def rra15(cam2world_pred: torch.Tensor, cam2world_gt: np.ndarray) -> float:
    """Share (%) of camera pairs i < j whose relative rotation is within 15 degrees of the truth (``bench_pose.errors``
    on the pair's relative pose, as ``bench_ga`` scores aligned cameras)."""
    gt = torch.as_tensor(cam2world_gt, dtype=torch.float64)
    pred = cam2world_pred.to(torch.float64)
    errs = [errors((torch.linalg.inv(pred[i]) @ pred[j]).numpy(), (torch.linalg.inv(gt[i]) @ gt[j]).numpy())[0]
            for i, j in itertools.combinations(range(len(gt)), 2)]
    return 100.0 * float(np.mean(np.asarray(errs) < 15.0))


def run(model, images, gt, counts, size, epipolar: bool, graphs=("auto",)) -> list[dict]:
    rows = []
    for n, graph in itertools.product(counts, graphs):
        t = time.perf_counter()
        recon = pm.reconstruct(model, images[:n], graph=graph, size=size, epipolar=epipolar, quiet=True,
                               align=pm.AlignConfig(quiet=True))
        total = time.perf_counter() - t
        info = recon.info["pipeline"]
        sec, est = info["seconds"], info["estimate"]
        rows.append({"n": n, "graph": info["graph"], "pairs": info["pairs"],
                     "inference_est": est["inference_seconds"],
                     "inference": sec["inference"] + sec.get("retrieval", 0.0),  # the estimate counts both
                     "align_est": est["align_seconds"], "align": sec["alignment"] + sec.get("epipolar", 0.0),
                     "epipolar": sec.get("epipolar", 0.0),
                     "total": total, "rra15": rra15(recon.cam2world, gt[:n])})
        print(f"  {n} images, {info['graph']}: {total:.1f} s", file=sys.stderr, flush=True)
    return rows


def table(rows) -> str:
    lines = ["| images | graph | pairs | inference s, estimated / measured | alignment s (+ refinement on matches), "
             "estimated / measured (of which the refinement) | total s | RRA@15 of camera pairs |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['n']} | {r['graph']} | {r['pairs']} | {r['inference_est']:.2f} / {r['inference']:.2f} | "
                     f"{r['align_est']:.2f} / {r['align']:.2f} ({r['epipolar']:.2f}) | {r['total']:.1f} | "
                     f"{r['rra15']:.0f}% |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="small", help="a shipped model's name or a model file")
    p.add_argument("--counts", nargs="+", type=int, default=[4, 8, 16], help="image counts, each >= 2")
    p.add_argument("--scene", choices=KINDS, default="room")
    p.add_argument("--render-size", type=int, default=320, help="the rendered photographs' long side")
    p.add_argument("--size", type=int, default=None, help="network input size (default: the model's own)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--epipolar", choices=("on", "off"), default="on", help="the pose refinement on matches")
    p.add_argument("--graphs", nargs="+", default=["auto"],
                   help="pair graphs, each run on every count (auto, complete, logwin-3, retrieval-3, ...)")
    p.add_argument("--shuffle", type=int, default=None, metavar="SEED",
                   help="put the rendered views in a random order first (photos in no particular order: the file "
                   "order no longer follows the camera path)")
    a = p.parse_args(argv)
    if not a.counts or min(a.counts) < 2:
        p.error(f"--counts expected image counts >= 2, got {a.counts}")
    for flag, v, low in (("--render-size", a.render_size, 32), ("--threads", a.threads, 1)):
        if v < low:  # argparse has made them ints
            p.error(f"{flag} expected an int >= {low}, got {v}")
    if a.size is not None and (a.size < 16 or a.size % 16):
        p.error(f"--size expected a multiple of 16 (>= 16), got {a.size}")
    from pointmap.pairs import parse_graph

    for g in a.graphs:
        try:
            parse_graph(g, auto=True)
        except pm.GraphError as e:
            p.error(f"--graphs: {e}")
    try:
        model = load_models([a.model])[a.model]  # a PointmapNet, or the one-line reason it is not
    except pm.CheckpointError as e:
        p.error(str(e))
    torch.set_num_threads(a.threads)
    counts = sorted(set(a.counts))
    images, gt = render_views(max(counts), a.scene, a.render_size)
    if a.shuffle is not None:
        order = np.random.default_rng(a.shuffle).permutation(len(images))
        images, gt = [images[k] for k in order], gt[order]
    print(f"model {a.model} ({model.cfg.enc_depth} / {model.cfg.dec_depth} blocks); {a.scene} scene, "
          f"{images[0].shape[1]}x{images[0].shape[0]} photographs; {a.threads} threads; pose refinement on matches "
          f"{a.epipolar}" + ("" if a.shuffle is None else f"; views shuffled (seed {a.shuffle})"))
    print(table(run(model, images, gt, counts, a.size, a.epipolar == "on", a.graphs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
