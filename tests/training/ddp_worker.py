"""Run by test_loop under torchrun: a few DDP steps, then each rank saves its weights."""

import sys

import torch

from pointmap.model import PRESETS, PointmapNet
from training.config import TrainConfig
from training.loop import fit
from training.train import collate, make_step

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from synthetic import PlanePairs  # noqa: E402

out = sys.argv[1]
# with a time limit and --decay_by_time every step broadcasts rank 0's end and stop decision
cfg = TrainConfig(data="synthetic", out=out, preset="test", batch_size=2, steps=3, warmup=1, ckpt_every=100,
                  eval_every=100, workers=0, quiet=True, n_corr=64, threads=1, schedule="wsd", decay_steps=1,
                  max_minutes=60.0, decay_by_time=True)
torch.manual_seed(0)
model = PointmapNet(PRESETS["test"])
fit(cfg, model, PlanePairs(8), collate, make_step(cfg))
rank = torch.distributed.get_rank()
torch.save(model.state_dict(), f"{out}/rank{rank}.pt")
