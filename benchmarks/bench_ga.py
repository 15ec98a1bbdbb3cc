"""Global alignment on held-out multi-view scenes: the model's pairwise poses against the poses global
alignment makes of all of a scene's views at once, for several alignment settings on the SAME predictions.

Each scene of the given held-out sets (the card's have 4 views each) is predicted once on its complete pair graph (both
orders); then for every camera pair (i < j):

- "pairwise": ``pm.relative_pose(pred, pred_reverse)`` of that pair alone (the pointmaps' pose the model card measures);
- "pairwise + matches": ``pm.pair_pose(pred, pred_reverse)``, that pose refined on the pair's own matches (what
  ``pointmap pair`` reports);
- "GA <setting>": the relative pose of cameras i and j after ``global_align`` of all the scene's views.

A setting is a conf_transform name ('auto' = the default, 'log' = DUSt3R's, 'm1', 'sqrt', 'id'), optionally with
':lbfgs' (optimizer) or ':none' (the start only, no optimisation), then '+K' to give the alignment the scenes'
true intrinsics (the rendered sets' K is in the images' own pixels, which the 224 px maps keep) and/or '+F' for
one focal shared by a scene's views (``AlignConfig.shared_focal``: right for one-camera sets like eval_cam_s464646),
'+S' for the sparse refinement on matches (``refine_matches``), '+E' for the epipolar pose refinement on the
model's coarse matches (``refine_epipolar``, what ``reconstruct`` runs by default; '+E-' for that stage without its
cheirality residuals, as before session 33; '+E@<deg>' with that width of its rotation prior,
``EpipolarConfig.rotation_prior_deg``), '+T' for DUSt3R's
spanning-tree start (``AlignConfig(init='mst')``, the default before session 32) instead of the motion-averaging one
and '+C' with an epipolar stage for its focals self-calibrated on the matches (``EpipolarConfig.self_calibrate``),
'+P' for the averaging start from the Procrustes of the pointmaps even when the model has a pose head
(``AlignConfig(pose_head=False)``, as before session 49), '+H<weight>' or '+H<weight>@<rot>,<dir>' for the pose
heads' prior on the cameras at that weight and those Cauchy widths in degrees (``AlignConfig.head_prior``,
``head_prior_deg``; '+H0' turns it off). The table gives RRA@15 / RTA@15 / median
errors per set and overall, and the median focal error of each view (GA only; 0 when the intrinsics are given).
``--per-pair PREFIX`` also writes every camera pair's errors, one CSV per method (PREFIX-pairwise.csv,
PREFIX-GA_log.csv, ...), so that two methods can be compared pair by pair with benchmarks/paired.py.

    python benchmarks/bench_ga.py --model small --data DIR [DIR ...] [--scenes 24] [--settings auto log id]
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pointmap as pm  # noqa: E402
from pointmap.align import AlignConfig, global_align  # noqa: E402
from pointmap.align.edges import CONF_TRANSFORMS  # noqa: E402
from pointmap.align.epipolar import EpipolarConfig, refine_epipolar  # noqa: E402
from pointmap.align.sparse import SparseConfig, refine_matches  # noqa: E402
from pointmap.errors import PointmapError  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pose import errors, model_at_size  # noqa: E402

from pointmap.geometry.rotations import rotation_angle  # noqa: E402
from pointmap.images import INPUT_SIZE_RULE, is_input_size  # noqa: E402
from training.evaluate import PairResult, check_per_pair, write_per_pair  # noqa: E402


def per_pair_path(prefix: str, method: str) -> Path:
    return Path(f"{prefix}-{method.replace(' ', '_').replace(':', '_')}.csv")


def parse_setting(s: str) -> tuple[AlignConfig, bool, bool, EpipolarConfig | None]:
    """'log', 'id:lbfgs', 'auto:none', 'auto+K', 'auto+F', 'auto+S', 'auto+E', 'auto+E@1', 'auto+E-', 'auto+E1', 'auto+T', 'auto+P' ... -> (AlignConfig
    (quiet), whether the true intrinsics are given, whether the sparse refinement on matches follows, the epipolar
    pose refinement's config or None)."""
    body, *flags = s.split("+")
    stages = {"E", "E-", "E1"}
    prior = [f for f in flags if f.startswith("H")]
    flags = [f for f in flags if not f.startswith("H")]
    stage_prior = {}  # 'E@<deg>', 'E-@<deg>', 'E1@<deg>': the stage's rotation prior width in degrees
    for k, f in enumerate(flags):
        stage, at, deg = f.partition("@")
        if at and stage in stages:
            try:
                stage_prior = {"rotation_prior_deg": float(deg)}
                EpipolarConfig(**stage_prior)  # the width checked by EpipolarConfig itself
            except (ValueError, PointmapError):
                stage = f  # refused below, with the other unknown flags
            flags[k] = stage
    prior_cfg = {}
    try:  # 'H<weight>' or 'H<weight>@<rotation deg>,<direction deg>'
        if prior:
            w, _, widths = prior[0][1:].partition("@")
            prior_cfg["head_prior"] = float(w)
            if widths:
                prior_cfg["head_prior_deg"] = tuple(float(x) for x in widths.split(","))
        AlignConfig(**prior_cfg)  # the weight and widths checked by AlignConfig itself
        prior_ok = True
    except (ValueError, PointmapError):
        prior_ok = False
    if any(f not in ("K", "F", "S", "T", "P", "C", *stages) for f in flags) or len(set(flags)) < len(flags) \
            or len(stages & set(flags)) > 1 or len(prior) > 1 or not prior_ok or (prior and "P" in flags) \
            or ("C" in flags and not stages & set(flags)):
        raise argparse.ArgumentTypeError(f"setting {s!r}: expected '+K' (true intrinsics), '+F' (shared focal), "
                                         "'+S' (sparse refinement on matches), '+E' (epipolar pose refinement "
                                         "on matches, as reconstruct), '+E-' (the same without its cheirality "
                                         "residuals) or '+E1' (with them, one descent: session 33's stage), each "
                                         "with an optional '@<deg>' (its rotation prior's width, e.g. +E@1), '+T' "
                                         "(spanning-tree start), '+P' (the averaging start from the "
                                         "pointmaps' Procrustes, not the pose head) and/or '+H<weight>[@<rot>,<dir>]' (the "
                                         "pose heads' prior at that weight and widths in degrees, e.g. +H0.1, "
                                         "+H0.1@10,20; +H0: off; not with +P, which has no head), '+C' (with an "
                                         "epipolar stage: its focals self-calibrated on the matches)")
    transform, _, opt = body.partition(":")
    if transform not in CONF_TRANSFORMS + ("auto",):
        raise argparse.ArgumentTypeError(f"setting {s!r}: conf_transform expected 'auto' or one of {CONF_TRANSFORMS}")
    if opt not in ("", "adam", "lbfgs", "none"):
        raise argparse.ArgumentTypeError(f"setting {s!r}: optimizer expected adam, lbfgs or none after ':'")
    cfg = AlignConfig(conf_transform=transform, optimizer=opt or "adam", shared_focal="F" in flags,
                      init="mst" if "T" in flags else "averaging", pose_head="P" not in flags, quiet=True,
                      **prior_cfg)
    epipolar = EpipolarConfig(cheirality="E-" not in flags, second_descent="E" in flags, self_calibrate="C" in flags,
                              **stage_prior) \
        if stages & set(flags) else None
    return cfg, "K" in flags, "S" in flags, epipolar


def setting_name(s: str) -> str:
    """argparse type: a setting string, checked (parse_setting's errors)."""
    parse_setting(s)
    return s


def scene_errors(model, size: int, scene: dict, settings: dict) -> tuple:
    """{method: [(rot err, dir err, true rotation), ...] over camera pairs i < j}, {method: [focal err %, ...]},
    the alignments that failed (their pairs count 180 degrees, their focals 100%) and the '+E' stages that kept the
    aligned poses (with the stage's reason)."""
    imgs = [(x.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for x in scene["img"]]
    views = pm.load_images(imgs, size=size)
    n = len(views)
    pairs = pm.make_pairs(n)
    preds = pm.predict_pairs(model, views, pairs, quiet=True)
    gt = scene["cam2world"].double()
    rel_gt = {(i, j): (torch.linalg.inv(gt[i]) @ gt[j]).numpy() for i, j in pairs}
    true_rot = {k: float(torch.rad2deg(rotation_angle(torch.from_numpy(T[:3, :3])))) for k, T in rel_gt.items()}
    out = defaultdict(list)
    focal = defaultdict(list)
    for i, j in pairs:
        est = pm.relative_pose(preds[(i, j)], pred_reverse=preds[(j, i)])
        out["pairwise"].append((*errors(est[0].double().numpy(), rel_gt[(i, j)]), true_rot[(i, j)]))
        est = pm.pair_pose(preds[(i, j)], preds[(j, i)], patch=model.cfg.patch_size, pose=est)[0].double().numpy()
        out["pairwise + matches"].append((*errors(est, rel_gt[(i, j)]), true_rot[(i, j)]))
    f_gt = scene["K"][:, 0, 0].double()
    failed, kept = [], []  # kept: '+E' settings whose stage left the aligned poses (its reason)
    matches = None
    for name, (cfg, known_K, sparse, epipolar) in settings.items():
        try:
            recon = global_align(views, preds, config=cfg, K=scene["K"].double() if known_K else None)
            if epipolar is not None:
                recon = refine_epipolar(views, preds, recon, config=replace(epipolar, patch=model.cfg.patch_size))
                if not recon.info["epipolar"]["applied"]:
                    kept.append(f"GA {name}: {recon.info['epipolar']['reason']}")
            if sparse:  # as reconstruct(refine=True): the focals stay as aligned when known or shared
                matches = matches or {k: pm.match(p) for k, p in preds.items()}
                recon = refine_matches(recon, matches, config=SparseConfig(quiet=True),
                                       fixed_intrinsics=True if known_K or cfg.shared_focal else ())
        except PointmapError as e:  # e.g. every weight zero under 'log': the scene counts as failed (180 deg)
            failed.append(f"GA {name}: {e}")
            out[f"GA {name}"] += [(180.0, 180.0, true_rot[k]) for k in pairs]
            focal[f"GA {name}"] += [100.0] * n
            continue
        c2w = recon.cam2world.double()
        for i, j in pairs:
            est = (torch.linalg.inv(c2w[i]) @ c2w[j]).numpy()
            out[f"GA {name}"].append((*errors(est, rel_gt[(i, j)]), true_rot[(i, j)]))
        focal[f"GA {name}"] += (100 * (recon.K[:, 0, 0].double() - f_gt).abs() / f_gt).tolist()
    return out, focal, failed, kept


def open_sets(ap, args, methods: list) -> tuple:
    """(model, size, datasets, set names) of ``--model``, ``--size`` and the multi-view sets ``--data``, checked
    before the long run (``ap.error`` otherwise): ``--scenes`` positive, ``--size`` an input size, each set named
    once (by its folder), ``--per-pair``'s files PREFIX-<method>.csv writable for every method and set, the model
    and the sets opened; ``--threads`` set."""
    from data.datasets import MultiViewDataset

    if args.scenes is not None and args.scenes < 1:
        ap.error(f"--scenes expected a positive count, got {args.scenes}")
    if args.size is not None and not is_input_size(args.size):
        ap.error(f"--size expected {INPUT_SIZE_RULE}, got {args.size}")
    set_names = [Path(d).resolve().name for d in args.data]
    twice = sorted({nm for nm in set_names if set_names.count(nm) > 1})
    if twice:
        ap.error(f"--data: set name(s) {twice} given twice (a set is named by its folder)")
    if args.per_pair:
        for m in methods:
            for nm in set_names:
                try:
                    check_per_pair(per_pair_path(args.per_pair, m), nm)
                except (ValueError, OSError) as e:
                    ap.error(f"--per-pair: {e}")
    torch.set_num_threads(args.threads)
    try:  # the model and every set, opened before the long run
        model, size = model_at_size(args.model, args.size)
        datasets = [MultiViewDataset(d) for d in args.data]
    except (PointmapError, OSError, ValueError) as e:
        ap.error(str(e))
    return model, size, datasets, set_names


def sets_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments of a benchmark over multi-view held-out sets (``open_sets`` checks them): --model, --data,
    --scenes, --size, --threads, --per-pair."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="small", help="a shipped name or a .safetensors file")
    ap.add_argument("--data", nargs="+", required=True, help="held-out shard folders (multi-view scenes)")
    ap.add_argument("--scenes", type=int, default=None, help="at most this many scenes per set (default all)")
    ap.add_argument("--size", type=int, default=None, help="network input size (default: the model's)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--per-pair", dest="per_pair", default=None, metavar="PREFIX",
                    help="write PREFIX-<method>.csv per method (benchmarks/paired.py reads them)")
    return ap


def print_sets_table(res: dict, unit: str) -> None:
    """The markdown table of {(set or "overall", method): [(rot err, dir err, true rotation), ...]}: RRA@15,
    RTA@15 and the median errors, the sets first, "overall" last."""
    print(f"| set | {unit} | method | RRA@15 | RTA@15 | median rot err | median dir err |")
    print("|---|---|---|---|---|---|---|")
    for (group, m), vals in sorted(res.items(), key=lambda kv: (kv[0][0] == "overall", kv[0][0])):
        v = np.array(vals)
        d = v[:, 1][~np.isnan(v[:, 1])]  # NaN only from files of other tools (a zero baseline scores 90 here)
        rta, dir_med = (f"{100 * np.mean(d < 15):.1f}%", f"{np.median(d):.1f}") if len(d) else ("-", "-")
        print(f"| {group} | {len(v)} | {m} | {100 * np.mean(v[:, 0] < 15):.1f}% | {rta} | "
              f"{np.median(v[:, 0]):.1f} | {dir_med} |")


def main(argv=None) -> int:
    ap = sets_parser(__doc__)
    ap.add_argument("--settings", nargs="+", type=setting_name, default=None,
                    help="alignment settings to compare (default: auto log id)")
    args = ap.parse_args(argv)
    names = list(dict.fromkeys(args.settings or ["auto", "log", "id"]))
    settings = {nm: parse_setting(nm) for nm in names}
    model, size, datasets, set_names = open_sets(ap, args, ["pairwise", "pairwise + matches"] +
                                                 [f"GA {nm}" for nm in names])
    res = defaultdict(list)
    foc = defaultdict(list)
    failures, kept_all, view_counts = [], [], set()
    for ds, set_name in zip(datasets, set_names):
        count = len(ds) if args.scenes is None else min(len(ds), args.scenes)
        for k in tqdm(range(count), desc=set_name, leave=False):
            scene = ds[k]
            view_counts.add(len(scene["img"]))
            out, focal, failed, kept = scene_errors(model, size, scene, settings)
            failures += [f"{set_name} scene {k}: {f}" for f in failed]
            kept_all += [f"{set_name} scene {k}: {f}" for f in kept]
            for m, v in out.items():
                res[(set_name, m)] += v
                res[("overall", m)] += v
            for m, v in focal.items():
                foc[("overall", m)] += v
        if args.per_pair:
            for (group, m), v in res.items():
                if group == set_name:
                    write_per_pair(per_pair_path(args.per_pair, m), group,
                                   [PairResult(k, r, t, a) for k, (r, t, a) in enumerate(v)])
    print(f"model {args.model} at {size}px; every camera pair of scenes of {sorted(view_counts)} views; "
          "GA = global_align of each scene's views")
    for f in failures:
        print(f"alignment failed (its pairs count 180 degrees): {f}")
    for f in kept_all:
        print(f"epipolar stage not applied (the aligned poses kept): {f}")
    print_sets_table(res, "camera pairs")
    print()
    print("| method | views | median focal err | focal err < 10% |")
    print("|---|---|---|---|")
    for (_, m), vals in foc.items():
        v = np.array(vals)
        print(f"| {m} | {len(v)} | {np.median(v):.1f}% | {100 * np.mean(v < 10):.0f}% |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
