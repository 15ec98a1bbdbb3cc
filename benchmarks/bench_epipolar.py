"""Time of the epipolar pose refinement (``pointmap.align.epipolar.solve_poses``) against the number of images, with
the analytic Jacobian and with scipy's finite differences (the reference) on the same inputs in the same run.

Inputs: the analytic test scene (tests/align/align_scene.py), a cyclic sliding-window pair graph (every image with
its next ``--window`` images), true matches on a pixel grid of each pair with ``--outliers`` of them moved to random
pixels, and a start ``--rot-deg`` degrees and ``--centre`` (in units of the scene's ~1-unit camera spacing) off the
true poses, camera 0 held and the scale kept, as ``reconstruct`` runs it. Prints a markdown table: per image count
the time, evaluations, the worst relative-pose errors (rotation, direction, degrees) of both Jacobians and the camera
pairs whose direction the fit reversed (``mirrored_pairs``: ``refine_epipolar`` would keep the aligned poses).

    nice .venv/bin/python benchmarks/bench_epipolar.py --sizes 10 40 100 --threads 1

``--stage``: instead, the whole stage as ``reconstruct`` runs it (``refine_epipolar``: coarse matches, the fit with
the analytic Jacobian, the depths re-fitted) next to the dense alignment before it, on predictions of the same scene
with 8-degree pose noise per pass, 2% depth noise and descriptors of the world points (tests/align/align_scene.py);
``--seeds`` gives more scenes, ``--cheirality off one on`` runs the stage without its cheirality residuals, with them
in one descent (session 33's stage) and with them in two descents (the default) on the same alignment. Outside
``--stage``, each ``--cheirality`` mode runs with each ``--jacobians`` on the same inputs, and several ``--seeds``
give several rings and starts, with a summary of the failed starts (the worst rotation above ``--fail-deg``):

    nice .venv/bin/python benchmarks/bench_epipolar.py --sizes 8 --window 2 --hw 48 64 --outliers 0.1 \\
        --rot-deg 15 --centre 0.3 --seeds $(seq 0 15) --jacobians analytic --cheirality off one on
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pointmap.align.optimize import INITS  # noqa: E402


def worst_errors(R, C, gt) -> tuple[float, float, float]:
    """Largest rotation error, median and largest direction errors (degrees) over the relative poses of the
    consecutive images (the ring's random spacing makes some of their baselines short: their directions are the
    ill-conditioned ones)."""
    rot, dirs = [], []
    n = len(gt)
    for i in range(n):
        j = (i + 1) % n
        Ri, Rj = R[i], R[j]
        e_R, g_R = Ri.T @ Rj, gt[i, :3, :3].T @ gt[j, :3, :3]
        e_t, g_t = Ri.T @ (C[j] - C[i]), gt[i, :3, :3].T @ (gt[j, :3, 3] - gt[i, :3, 3])
        rot.append(np.degrees(np.arccos(np.clip((np.trace(e_R.T @ g_R) - 1) / 2, -1, 1))))
        dirs.append(np.degrees(np.arccos(np.clip(e_t @ g_t / np.linalg.norm(e_t) / np.linalg.norm(g_t), -1, 1))))
    return max(rot), float(np.median(dirs)), max(dirs)


def run_stage(sizes, h: int, w: int, window: int, init: str = "averaging", seeds=(0,), cheirality=("on",)) -> None:
    """Seconds of ``global_align`` and of ``refine_epipolar`` after it (with and without its cheirality residuals, on
    the same alignment), and the camera errors of both, per image count and scene seed."""
    sys.path.insert(0, str(ROOT / "tests" / "align"))
    from align_scene import gt_preds, make_scene, pose_errors, views_of, with_descriptors

    from pointmap.align import AlignConfig, EpipolarConfig, global_align, refine_epipolar
    from pointmap.pairs import make_pairs

    rows = []
    for n in sizes:
        for seed in seeds:
            f = 0.85 * w
            sc = make_scene(n, h, w, seed=seed, focal_range=(f * 0.9, f * 1.1))
            pairs = sorted(make_pairs(n, f"swin-{window}"))
            views = views_of(sc)
            preds = with_descriptors(gt_preds(sc, pairs, seed=seed + 2, pair_rot_deg=8.0, noise=0.02), sc)
            t = time.perf_counter()
            recon = global_align(views, preds, config=AlignConfig(quiet=True, init=init))
            t_ga = time.perf_counter() - t
            err_ga = pose_errors(recon.cam2world.double().numpy(), sc["cam2world"])[0]
            for ch in cheirality:
                t = time.perf_counter()
                out = refine_epipolar(views, preds, recon, config=EpipolarConfig(
                    patch=8, cheirality=ch != "off", second_descent=ch == "on"))
                t_e = time.perf_counter() - t
                rep = out.info["epipolar"]
                row = (n, seed, len(pairs), rep.get("matches", 0), t_ga, ch, t_e, rep.get("evaluations", 0),
                       "yes" if rep["applied"] else "kept", err_ga,
                       pose_errors(out.cam2world.double().numpy(), sc["cam2world"])[0])
                rows.append(row)
                print(row, file=sys.stderr, flush=True)
    print(f"\nmaps {h}x{w}, cyclic window {window}, 8-px cells, the alignment's {init} start; rotation error: the worst "
          "camera after a similarity fit; cheirality: the stage's residuals for matched points behind a camera; "
          "applied: 'kept' when the mirror check kept the aligned poses\n")
    print("| images | seed | pairs | matches | alignment (s) | cheirality | epipolar stage (s) | evaluations | applied "
          "| rot err GA / GA+E (deg) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for n, seed, np_, m, t_ga, ch, t_e, ev, applied, r0, r1 in rows:
        print(f"| {n} | {seed} | {np_} | {m} | {t_ga:.1f} | {ch} | {t_e:.1f} | {ev} | {applied} | {r0:.2f} / {r1:.2f} |")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 40, 100])
    ap.add_argument("--hw", type=int, nargs=2, default=[96, 128], metavar=("H", "W"))
    ap.add_argument("--window", type=int, default=3)
    ap.add_argument("--outliers", type=float, default=0.2)
    ap.add_argument("--rot-deg", type=float, default=3.0)
    ap.add_argument("--centre", type=float, default=0.05)
    ap.add_argument("--jacobians", nargs="+", default=["2-point", "analytic"], choices=["2-point", "analytic"])
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the alignment in --stage); the fit itself "
                    "always runs with one BLAS thread")
    ap.add_argument("--stage", action="store_true", help="time the whole stage (refine_epipolar) after global_align")
    ap.add_argument("--init", default="averaging", choices=INITS, help="--stage: the alignment's start")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0],
                    help="scene seeds: one scene (--stage) or one ring and start (the fit alone) per seed")
    ap.add_argument("--fail-deg", type=float, default=5.0,
                    help="the fit alone over several --seeds: a start counts as failed when its worst rotation after "
                    "the fit exceeds this (degrees)")
    ap.add_argument("--cheirality", nargs="+", default=["on"], choices=["on", "one", "off"],
                    help="the fit's cheirality residuals: on (the default: two descents), one (one descent, session "
                    "33), off (before session 33), or several")
    args = ap.parse_args(argv)
    if min(args.sizes) < 3 or args.window < 1:
        ap.error(f"--sizes expected image counts >= 3 and --window >= 1, got {args.sizes} and {args.window}")
    import torch

    sys.path.insert(0, str(ROOT / "tests" / "align"))
    from align_scene import ring_matches

    from pointmap.align.epipolar import solve_poses

    torch.set_num_threads(args.threads)
    h, w = args.hw
    if args.stage:
        run_stage(args.sizes, h, w, args.window, args.init, args.seeds, args.cheirality)
        return
    methods = [(mode, jac) for mode in args.cheirality for jac in args.jacobians]
    rows = []
    for n in args.sizes:
        for seed in args.seeds:
            gt, start, (I, J, r1, r2, scale), n_pairs = ring_matches(n, h, w, args.window, args.outliers,
                                                                     args.rot_deg, args.centre, seed=seed)
            row = {"n": n, "seed": seed, "pairs": n_pairs, "matches": len(I),
                   "start": worst_errors(start[:, :3, :3], start[:, :3, 3], gt)}
            for mode, jac in methods:
                t = time.perf_counter()
                R, C, rep = solve_poses(start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, scale, held=[0],
                                        keep_scale=True, jac=jac, cheirality=mode != "off", second_descent=mode == "on")
                row[mode, jac] = (time.perf_counter() - t, rep["evaluations"], *worst_errors(R, C, gt),
                                  len(rep["mirrored_pairs"]))
            rows.append(row)
            print(row, file=sys.stderr, flush=True)
    print(f"\nmaps {h}x{w}, cyclic window {args.window}, {args.outliers:.0%} outliers, start {args.rot_deg} deg / "
          f"{args.centre} off, one BLAS thread; errors: worst over consecutive images' relative poses\n")
    name = (lambda mode, jac: jac) if len(args.cheirality) == 1 else (lambda mode, jac: f"{mode}, {jac}")
    head = "| images | seed | pairs | matches | start: worst rot / median dir / worst dir (deg) |"
    rule = "|---|---|---|---|---|"
    for m in methods:
        head += f" {name(*m)}: time (s) | evaluations | worst rot / median dir / worst dir | pairs reversed |"
        rule += "---|---|---|---|"
    speedup = len(methods) == 2 and len(args.cheirality) == 1
    if speedup:
        head += f" speed-up ({args.jacobians[0]} / {args.jacobians[1]}) |"
        rule += "---|"
    print(head)
    print(rule)
    for r in rows:
        line = f"| {r['n']} | {r['seed']} | {r['pairs']} | {r['matches']} | {' / '.join(f'{e:.2f}' for e in r['start'])} |"
        for m in methods:
            secs, evals, rot, dir_med, dir_max, mirrored = r[m]
            line += f" {secs:.2f} | {evals} | {rot:.3f} / {dir_med:.3f} / {dir_max:.3f} | {mirrored} |"
        if speedup:
            line += f" {r[methods[0]][0] / max(r[methods[1]][0], 1e-9):.1f}x |"
        print(line)
    if len(args.seeds) > 1:  # several starts: how often each method fails, per image count
        print(f"\nstarts whose worst rotation after the fit exceeds {args.fail_deg:g} degrees (failed), the worst "
              f"rotation of the others, and the median time\n")
        print("| images | method | starts | failed (their worst rotations) | worst rotation of the others | median time (s) |")
        print("|---|---|---|---|---|---|")
        for n in args.sizes:
            mine = [r for r in rows if r["n"] == n]
            for m in methods:
                rots = [r[m][2] for r in mine]
                bad = sorted((x for x in rots if not x <= args.fail_deg), key=lambda x: (x == x, x))  # NaN: failed
                good = [x for x in rots if x <= args.fail_deg]
                worst_good = f"{max(good):.2f}" if good else "-"
                print(f"| {n} | {name(*m)} | {len(rots)} | {len(bad)} ({', '.join(f'{x:.1f}' for x in bad) or '-'}) | "
                      f"{worst_good} | {np.median([r[m][0] for r in mine]):.2f} |")


if __name__ == "__main__":
    main()
