"""How well the ``retrieval-K`` graph's similarity follows the cameras: on rendered views of each scene kind, the
rank correlation (Spearman) between the image pairs' similarity and their closeness in viewing direction, and how
often an image's most similar other is among its 3 nearest cameras by that angle. ``image_similarity`` (the share
of mutual-nearest encoder tokens, what ``retrieval-K`` pairs by) is printed beside the cosine of the mean tokens
(``pooled_tokens``, the baseline ``localize`` ranks references by), on the same views in the same run.

    nice .venv/bin/python benchmarks/bench_retrieval.py --model small --views 24 --threads 1
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pointmap as pm  # noqa: E402
from benchmarks.bench_inference import load_models  # noqa: E402
from benchmarks.bench_pipeline import KINDS, render_views  # noqa: E402


def view_angles(cam2world: np.ndarray) -> np.ndarray:
    """[N, N] degrees between the cameras' optical axes."""
    z = cam2world[:, :3, 2]
    return np.degrees(np.arccos(np.clip(z @ z.T, -1.0, 1.0)))


def agreement(sim: np.ndarray, angles: np.ndarray) -> tuple[float, int]:
    """(Spearman correlation of similarity with minus the angle over the pairs i < j, the images whose most similar
    other is among their 3 nearest by angle)."""
    from scipy.stats import spearmanr

    iu = np.triu_indices(len(sim), 1)
    rho = float(spearmanr(sim[iu], -angles[iu]).correlation)
    hits = 0
    for i in range(len(sim)):
        s, a = sim[i].astype(float).copy(), angles[i].astype(float).copy()
        s[i], a[i] = -np.inf, np.inf
        hits += int(np.argmax(s) in np.argsort(a, kind="stable")[:3])
    return rho, hits


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="small", help="a shipped model's name or a model file")
    p.add_argument("--views", type=int, default=24, help="rendered views per scene (>= 4)")
    p.add_argument("--scenes", nargs="+", choices=KINDS, default=list(KINDS))
    p.add_argument("--render-size", type=int, default=320)
    p.add_argument("--size", type=int, default=224, help="network input size")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    if a.views < 4 or a.threads < 1:
        p.error(f"--views expected >= 4 and --threads >= 1, got {a.views} and {a.threads}")
    try:
        model = load_models([a.model])[a.model]
    except pm.CheckpointError as e:
        p.error(str(e))
    torch.set_num_threads(a.threads)
    from pointmap.inference import image_similarity, pooled_tokens

    print(f"model {a.model}; {a.views} views per scene at {a.size} px; truth: the angle between optical axes\n")
    print("| scene | similarity | Spearman with closeness | most similar among the 3 nearest |")
    print("|---|---|---|---|")
    for kind in a.scenes:
        images, gt = render_views(a.views, kind, a.render_size)
        views = pm.load_images(images, size=a.size)
        angles = view_angles(gt)
        pooled = pooled_tokens(model, views)
        for name, sim in (("mutual-nearest tokens (retrieval-K)", image_similarity(model, views).numpy()),
                          ("mean-token cosine", (pooled @ pooled.T).numpy())):
            rho, hits = agreement(sim, angles)
            print(f"| {kind} | {name} | {rho:.2f} | {hits} / {len(views)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
