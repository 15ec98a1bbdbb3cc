"""Run by test_loop under torchrun: a few DDP steps, then each rank saves its weights. With a second argument
``sigterm``, rank 1 alone receives SIGTERM during the second update, and every rank must stop after it."""

import os
import signal
import sys

import torch

from pointmap.model import PRESETS, PointmapNet
from training.config import TrainConfig
from training.loop import fit
from training.train import collate, freeze_idle, make_step

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from synthetic import PlanePairs  # noqa: E402

out = sys.argv[1]
signalled = len(sys.argv) > 2 and sys.argv[2] == "sigterm"
# with a time limit and --decay_by_time every step broadcasts rank 0's end and stop decision
# plain: a linear head with a focal head that no loss reaches (--focal_head_weight 0, the default) stopped DDP at its
# second step; sigterm: the DPT head, whose last fusion block has an unused lateral unit
preset = PRESETS["test"] if signalled else PRESETS["test"].replace(head="catmlp+linear", pose_head=True, focal_head=True)
cfg = TrainConfig(data="synthetic", out=out, preset="test", batch_size=2, steps=40 if signalled else 3, warmup=1,
                  ckpt_every=100, eval_every=100, workers=0, quiet=True, n_corr=64, threads=1, schedule="wsd",
                  decay_steps=1, max_minutes=60.0, decay_by_time=True, pose_weight=0.0 if signalled else 1.0)
torch.manual_seed(0)
model = PointmapNet(preset)
freeze_idle(cfg, model)  # as training.train does: the focal head, which no loss reaches, is frozen
step = make_step(cfg)


def step_fn(m, batch, k):
    if signalled and k == 1 and torch.distributed.get_rank() == 1:
        os.kill(os.getpid(), signal.SIGTERM)
    return step(m, batch, k)


result = fit(cfg, model, PlanePairs(8), collate, step_fn)
rank = torch.distributed.get_rank()
torch.save({**model.state_dict(), "__step": torch.tensor(result["step"])}, f"{out}/rank{rank}.pt")
