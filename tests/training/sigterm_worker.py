"""Run by test_loop in its own process group: trains with a data-loading worker until SIGTERM, printing each step."""

import sys

import torch

from pointmap.model import PRESETS, PointmapNet
from training.config import TrainConfig
from training.loop import fit
from training.train import collate, make_step

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from synthetic import PlanePairs  # noqa: E402

cfg = TrainConfig(data="synthetic", out=sys.argv[1], preset="test", batch_size=2, steps=100_000, warmup=1,
                  ckpt_every=100_000, ckpt_minutes=0.0, eval_every=100_000, workers=1, quiet=True, n_corr=64,
                  threads=1)
torch.manual_seed(0)
model = PointmapNet(PRESETS["test"])
step = make_step(cfg)


def printing_step(m, batch, k):
    print(f"step {k}", flush=True)
    return step(m, batch, k)


result = fit(cfg, model, PlanePairs(64), collate, printing_step)
print(f"fit returned at step {result['step']}", flush=True)
