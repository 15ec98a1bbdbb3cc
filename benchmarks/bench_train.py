"""Training-step speed of a preset: pairs/s and achieved GFLOP/s next to the float32 matmul ceiling, and
(with --data) the data-loading time per batch, which must stay well below the step time.

    python benchmarks/bench_train.py --preset small --size 224 --batch 8 --threads 2 [--data SHARDS]
    python benchmarks/bench_train.py --preset small --size 160 --recipe shipped --amp [--compile]
    python benchmarks/bench_train.py --preset small --size 224 --recipe shipped --depths 6,4 8,8

--amp adds bf16-autocast rows (training --amp bf16) next to the float32 ones, with each mode's first-step loss.
--recipe shipped times the shipped model's step (pose head; attention, coarse and pose losses on).
--baseline-code DIR times the same step with another checkout's code (e.g. `git worktree add /tmp/base HEAD~1`),
in a subprocess of the same run, and prints its rows beside this checkout's with the speed ratio. "cpu s/step" is
the process's CPU time per step (all threads): on a shared machine it moves less than the wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils.flop_counter import FlopCounterMode

# the code under test: this checkout, or (set by --baseline-code for its subprocess) another one
sys.path.insert(0, os.environ.get("POINTMAP_BENCH_CODE") or str(Path(__file__).resolve().parents[1]))

import pointmap as pm  # noqa: E402
from benchmarks.bench_inference import matmul_ceiling  # noqa: E402
from training.config import TrainConfig  # noqa: E402
from training.train import collate, make_step  # noqa: E402


def synthetic_batch(B, H, W):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "training"))
    from synthetic import PlanePairs

    data = PlanePairs(B, H, W)
    return collate([data[i] for i in range(B)])


def time_modes(model, step, batch, a) -> list:
    """(parameters, GFLOP count, mode, median s/step, median CPU s/step, first step s, first loss) per mode
    (eager / compiled, float32 / bf16 autocast) of one model's training step."""
    with sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as fc:  # attention counted as matmuls
        loss, _ = step(model, batch, 0)
        loss.backward()
    flops = fc.get_total_flops()
    n = sum(t.numel() for t in model.state_dict().values())
    initial = {k: v.clone() for k, v in model.state_dict().items()}

    def timed(net, amp: bool):
        model.load_state_dict(initial)  # every mode starts from the same weights: its first loss is comparable
        opt = torch.optim.AdamW(model.parameters(), 1e-4)

        def one():
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
                loss, _ = step(net, batch, 0)
            opt.zero_grad()
            loss.backward()
            opt.step()
            return float(loss.detach())

        t0 = time.perf_counter()
        loss = one()  # warm-up (compilation, for a compiled model)
        first = time.perf_counter() - t0
        times, cpu = [], []
        for _ in range(a.steps):
            t, c = time.perf_counter(), time.process_time()
            one()
            times.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
        return statistics.median(times), statistics.median(cpu), first, loss

    compiled = torch.compile(model) if a.compile else None
    rows = []
    for amp in (False, True) if a.amp else (False,):
        precision = "bf16 autocast" if amp else "float32"
        rows.append((n, flops, f"eager, {precision}", *timed(model, amp)))
        if compiled is not None:
            rows.append((n, flops, f"torch.compile, {precision}", *timed(compiled, amp)))
    return rows


def baseline_rows(a, code: str) -> list:
    """time_modes' rows of the same step with the code of another checkout ``code``: this script run in a
    subprocess with that checkout first on its path (POINTMAP_BENCH_CODE), its rows returned as JSON."""
    args = [sys.executable, str(Path(__file__).resolve()), "--preset", a.preset, "--size", str(a.size), "--batch",
            str(a.batch), "--threads", str(a.threads), "--steps", str(a.steps), "--recipe", a.recipe, "--rows-json"]
    args += (["--compile"] if a.compile else []) + (["--amp"] if a.amp else []) + \
        (["--depths", *a.depths] if a.depths else [])
    env = {**os.environ, "POINTMAP_BENCH_CODE": str(Path(code).resolve())}
    done = subprocess.run(args, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"the baseline checkout {code} failed to time its step:\n{done.stderr[-2000:]}")
    return [tuple(r) for r in json.loads(done.stdout.strip().splitlines()[-1])]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="small", choices=sorted(pm.PRESETS))
    p.add_argument("--size", type=int, default=224)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--data", default=None, help="shard root: also time data loading")
    p.add_argument("--compile", action="store_true",
                   help="also time the step with torch.compile (as training --compile true), in the same run")
    p.add_argument("--amp", action="store_true", help="also time bf16 autocast (training --amp bf16), same run")
    p.add_argument("--recipe", choices=("plain", "shipped"), default="plain",
                   help="plain: regression + matching; shipped: + pose head, attention, coarse and pose losses")
    p.add_argument("--depths", nargs="+", default=None, metavar="ENC,DEC",
                   help="time the preset at these encoder,decoder depths, one set of rows each (e.g. 6,4 8,8: "
                        "a model grown by training.grow against the one it grew from)")
    p.add_argument("--baseline-code", default=None, metavar="DIR",
                   help="another checkout of the project (e.g. a git worktree of an earlier commit): the same "
                        "step timed with its code first, its rows beside this checkout's")
    p.add_argument("--rows-json", action="store_true", help=argparse.SUPPRESS)  # a baseline subprocess's output
    a = p.parse_args(argv)
    if a.steps < 1:
        p.error(f"--steps expected >= 1, got {a.steps}")
    if a.baseline_code and not (Path(a.baseline_code) / "pointmap" / "__init__.py").is_file():
        p.error(f"--baseline-code expected a checkout of this project (a directory with pointmap/__init__.py), "
                f"got {a.baseline_code}")
    torch.set_num_threads(a.threads)
    try:
        depths = [tuple(int(x) for x in d.split(",")) for d in a.depths] if a.depths else [None]
        if any(d is not None and (len(d) != 2 or min(d) < 1) for d in depths):
            raise ValueError
    except ValueError:
        p.error(f"--depths expected ENC,DEC pairs of positive integers, got {a.depths}")
    preset = pm.PRESETS[a.preset]
    if a.recipe == "shipped":
        preset = preset.replace(pose_head=True)
        cfg = TrainConfig(data="x", preset=a.preset, n_corr=1024, match_weight=0.25, temperature=0.1,
                          coarse_weight=1.0, attn_weight=0.5, attn_heads=2, pose_weight=1.0, pose_dir_weight=0.5)
    else:
        cfg = TrainConfig(data="x", preset=a.preset, n_corr=1024)
    archs = []  # every architecture checked before anything is timed (the baseline's subprocess included)
    for d in depths:
        try:
            archs.append((d, preset if d is None else preset.replace(enc_depth=d[0], dec_depth=d[1])))
        except pm.CheckpointError as e:  # e.g. a DPT head below 4 decoder blocks
            p.error(f"--depths {d[0]},{d[1]}: {e}")
    rows = [("baseline", *r) for r in baseline_rows(a, a.baseline_code)] if a.baseline_code else []
    ceiling = None if a.rows_json else matmul_ceiling()  # a baseline's subprocess reports rows only
    batch = synthetic_batch(a.batch, a.size, a.size)
    own = []
    for d, arch in archs:
        torch.manual_seed(0)
        name = a.preset if d is None else f"{a.preset} {d[0]}/{d[1]} blocks"
        model = pm.PointmapNet(arch).train()
        step = make_step(cfg)  # its forward taps bind to the first model they see: one per model
        own += [(name, *r) for r in time_modes(model, step, batch, a)]
    if a.rows_json:
        print(json.dumps(own))
        return 0
    rows += [("this", *r) for r in own]
    print(f"threads {a.threads}, float32 matmul ceiling {ceiling:.1f} GFLOP/s, recipe {a.recipe}"
          + (f", baseline code {a.baseline_code}" if a.baseline_code else "") + "\n")
    print("| code | model | parameters | mode | input | batch | first step s | s/step | cpu s/step | pairs/s "
          "| GFLOP/step | GFLOP/s | % ceiling | first loss |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for code, name, n, flops, mode, t, cpu, first, loss in rows:
        print(f"| {code} | {name} | {n / 1e6:.2f}M | {mode} | {a.size}x{a.size} | {a.batch} | {first:.1f} | {t:.2f} | "
              f"{cpu:.2f} | {a.batch / t:.2f} | {flops / 1e9:.1f} | {flops / t / 1e9:.1f} | "
              f"{100 * flops / t / 1e9 / ceiling:.0f}% | {loss:.4f} |")
    print()
    if a.baseline_code:  # each of this checkout's rows against the baseline's row of the same model and mode
        base = {(r[1], r[4]): r for r in rows if r[0] == "baseline"}
        for _, name, _, _, mode, t, cpu, _, _ in (r for r in rows if r[0] == "this"):
            b = base.get((name, mode))
            if b is not None:
                print(f"{name}, {mode}: this / baseline speed {b[5] / t:.2f}x (wall), {b[6] / cpu:.2f}x (CPU time)")
    else:
        first = rows[0]
        for _, name, _, _, mode, t, cpu, _, _ in rows[1:]:
            print(f"{name}, {mode} / {first[1]}, {first[4]} speed: {first[5] / t:.2f}x (wall), "
                  f"{first[6] / cpu:.2f}x (CPU time)")
    t = own[0][4]  # this checkout's first row's s/step
    if a.data:
        from data.datasets import PairDataset

        ds = PairDataset(a.data, size=a.size, augment=True)
        t0 = time.perf_counter()
        n = a.batch * 3
        items = [ds[i % len(ds)] for i in range(n)]
        per_batch = (time.perf_counter() - t0) / 3
        collate(items[: a.batch])
        print(f"\ndata loading: {per_batch:.3f} s per batch of {a.batch} on one process "
              f"({100 * per_batch / t:.0f}% of a training step)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
