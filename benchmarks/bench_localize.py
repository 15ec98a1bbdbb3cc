"""Localization on held-out multi-view scenes: what the query's intrinsics are worth to ``pm.localize``.

For each scene of the given held-out sets (the card's have 4 views each) and each of its views in turn as the query,
the other views are reconstructed as ``pointmap reconstruct`` does (``pm.reconstruct``: the complete graph, the
global alignment with ``--shared-focal`` when asked, or with the views' true K given with ``--recon-K``, and the
epipolar stage), and the query is posed in that reconstruction by ``pm.localize`` three ways:

- "estimated": its focal from its own pointmap (``pointmap localize`` without ``--focal``);
- "recon focal": the K of the reconstruction's first view (right when one camera took the reconstruction's views and
  the query, as on one-camera sets like eval_cam_s464646, with ``--shared-focal``);
- "true K": the scene's true intrinsics (``--focal F`` with the right F).

Each posed query is scored against every reconstruction view i: the relative pose inv(c2w_i) @ c2w_query against
the true one (rotation error and translation direction error; scale-free), so the reconstruction's own errors
weigh the same on every method. The table gives RRA@15 / RTA@15 and median errors per set and overall; a query no
method can pose counts 180 degrees. ``--per-pair PREFIX`` writes one CSV per method for benchmarks/paired.py.

    python benchmarks/bench_localize.py --model small --data DIR [DIR ...] [--scenes 24] [--shared-focal | --recon-K]
"""

from __future__ import annotations

import sys
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pointmap as pm  # noqa: E402
from pointmap.align import AlignConfig  # noqa: E402
from pointmap.errors import PointmapError  # noqa: E402
from pointmap.geometry.rotations import rotation_angle  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_ga import open_sets, per_pair_path, print_sets_table, sets_parser  # noqa: E402
from bench_pose import errors  # noqa: E402

from training.evaluate import PairResult, write_per_pair  # noqa: E402

METHODS = ("estimated", "recon focal", "true K")


def scene_errors(model, size: int, scene: dict, shared_focal: bool, recon_K: bool = False) -> tuple[dict, list]:
    """{method: [(rot err, dir err, true rotation), ...]} over (query, reconstruction view) for every view of the
    scene as the query, and the failures (query, method, message)."""
    imgs = [(x.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for x in scene["img"]]
    gt = scene["cam2world"].double()
    K_true = scene["K"].double()
    out, failed = defaultdict(list), []
    for q in range(len(imgs)):
        others = [k for k in range(len(imgs)) if k != q]
        rel_gt = [(torch.linalg.inv(gt[i]) @ gt[q]).numpy() for i in others]
        true_rot = [float(torch.rad2deg(rotation_angle(torch.from_numpy(T[:3, :3])))) for T in rel_gt]
        recon = pm.reconstruct(model, [imgs[k] for k in others], graph="complete", size=size, quiet=True,
                               align=AlignConfig(shared_focal=shared_focal, quiet=True),
                               K=K_true[others] if recon_K else None)
        for method, K in zip(METHODS, (None, recon.K[0].double(), K_true[q])):
            try:
                with warnings.catch_warnings():  # intrinsics of another kind than the reconstruction's: on purpose
                    warnings.filterwarnings("ignore", message="localize: ")
                    loc = pm.localize(model, recon, [imgs[q]], K=K, quiet=True)
            except PointmapError as e:  # not posed: its pairs count 180 degrees
                failed.append((q, method, str(e)))
                out[method] += [(180.0, 180.0, r) for r in true_rot]
                continue
            c2w = recon.cam2world.double()
            for k, (T, r) in enumerate(zip(rel_gt, true_rot)):
                est = (torch.linalg.inv(c2w[k]) @ loc.cam2world[0].double()).numpy()
                out[method].append((*errors(est, T), r))
    return out, failed


def main(argv=None) -> int:
    ap = sets_parser(__doc__)
    ap.add_argument("--shared-focal", dest="shared_focal", action="store_true",
                    help="reconstruct with one focal for all views (one-camera sets)")
    ap.add_argument("--recon-K", dest="recon_K", action="store_true",
                    help="reconstruct with the views' true intrinsics given (pointmap reconstruct --focal F)")
    args = ap.parse_args(argv)
    if args.shared_focal and args.recon_K:
        ap.error("--shared-focal and --recon-K: a known K is not estimated, shared or not; give one")
    model, size, datasets, set_names = open_sets(ap, args, list(METHODS))
    res, failures = defaultdict(list), []
    for ds, set_name in zip(datasets, set_names):
        count = len(ds) if args.scenes is None else min(len(ds), args.scenes)
        for k in tqdm(range(count), desc=set_name, leave=False):
            out, failed = scene_errors(model, size, ds[k], args.shared_focal, args.recon_K)
            failures += [f"{set_name} scene {k} query {q} ({m}): {e}" for q, m, e in failed]
            for m, v in out.items():
                res[(set_name, m)] += v
                res[("overall", m)] += v
        if args.per_pair:
            for m in METHODS:
                write_per_pair(per_pair_path(args.per_pair, m), set_name,
                               [PairResult(k, r, t, a) for k, (r, t, a) in enumerate(res[(set_name, m)])])
    print(f"model {args.model} at {size}px; each view localized in the reconstruction of its scene's others "
          f"({'true K' if args.recon_K else 'one shared focal' if args.shared_focal else 'a focal per view'}); rows: "
          "(query, reconstruction view)")
    for f in failures:
        print(f"not posed (its rows count 180 degrees): {f}")
    print_sets_table(res, "rows")
    return 0


if __name__ == "__main__":
    sys.exit(main())
