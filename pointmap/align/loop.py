"""The optimisation loop of dense alignment: Adam (cosine/linear schedule) or LBFGS, early stopping,
progress bar, keeping the best iterate, and the convergence report."""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

import torch

from pointmap.align.objective import loss_and_grad
from pointmap.align.params import AlignParams

if TYPE_CHECKING:
    from pointmap.align.head_prior import HeadPrior
    from pointmap.align.optimize import AlignConfig


def _lr_at(cfg: AlignConfig, it: int) -> float:
    t = it / max(1, cfg.niter)
    if cfg.schedule == "cosine":
        return cfg.lr_min + (cfg.lr - cfg.lr_min) * (1 + math.cos(math.pi * t)) / 2
    if cfg.schedule == "linear":
        return cfg.lr + (cfg.lr_min - cfg.lr) * t
    if cfg.schedule == "constant":
        return cfg.lr
    raise ValueError(f"schedule expected 'cosine', 'linear' or 'constant', got {cfg.schedule!r}")


def run(params: AlignParams, stack, cfg: AlignConfig, chunk: int, prior: HeadPrior | None = None) -> dict:
    """Optimise in place; returns the convergence report (the best iterate is restored). ``prior``: the pose
    heads' prior on the cameras (pointmap.align.head_prior), added to the dense objective."""
    def closure_value() -> float:
        s, R, t = params.pw()
        value = loss_and_grad(params.world_points(stack.uv), s, R, t, stack, chunk)
        if prior is not None:  # a prior without edges adds a constant 0
            p = prior.loss(params.cam2world())
            if p.requires_grad:
                p.backward()
            value += float(p.detach())
        return value

    t0 = time.perf_counter()
    history: list[float] = []
    best = (float("inf"), None)
    reason = "max iterations"
    if cfg.optimizer == "none" or cfg.niter <= 0:
        with torch.no_grad():
            v = closure_value()
        return {"iterations": 0, "init_loss": v, "final_loss": v, "converged": False,
                "stop_reason": "optimizer='none'", "history": [v], "seconds": 0.0}
    from tqdm.auto import tqdm

    bar = tqdm(total=cfg.niter, desc="global alignment", disable=cfg.quiet, leave=False)
    if cfg.optimizer == "adam":
        opt = torch.optim.Adam(params.param_groups(cfg.lr, cfg.lr_focal), lr=cfg.lr, betas=(0.9, 0.9))
        base_lrs = [g["lr"] for g in opt.param_groups]
    elif cfg.optimizer == "lbfgs":
        opt = torch.optim.LBFGS([p for g in params.param_groups(1.0) for p in g["params"]], lr=1.0,
                                max_iter=1, max_eval=25, history_size=20, line_search_fn="strong_wolfe",
                                tolerance_grad=0.0, tolerance_change=0.0)
    else:
        raise ValueError(f"optimizer expected 'adam', 'lbfgs' or 'none', got {cfg.optimizer!r}")
    for it in range(cfg.niter):
        if cfg.optimizer == "adam":
            scale = _lr_at(cfg, it) / cfg.lr
            for g, b in zip(opt.param_groups, base_lrs):
                g["lr"] = b * scale
            opt.zero_grad(set_to_none=True)
            value = closure_value()
        else:
            def closure():
                opt.zero_grad(set_to_none=True)
                return torch.tensor(closure_value())
            value = None
        if value is not None and not math.isfinite(value):
            reason = "non-finite loss"
            break
        if value is not None and value < best[0]:
            best = (value, {k: v.detach().clone() for k, v in params.state_dict().items()})
        if cfg.optimizer == "adam":
            opt.step()
        else:
            before = {k: v.detach().clone() for k, v in params.state_dict().items()}
            value = float(opt.step(closure))
            if not math.isfinite(value):
                reason = "non-finite loss"
                break
            if value < best[0]:
                best = (value, before)
        history.append(value)
        bar.update(1)
        bar.set_postfix(loss=f"{value:.3e}")
        if value < 1e-12:
            reason = "converged (loss ~ 0)"
            break
        W = cfg.early_stop_window
        if len(history) > W and history[-W - 1] - min(history[-W:]) < cfg.early_stop_tol * abs(history[-1]):
            reason = "converged (relative improvement below tolerance)"
            break
    bar.close()
    # evaluate the last iterate too (Adam's step after the last recorded loss)
    with torch.no_grad():
        last = closure_value()
    if math.isfinite(last) and last < best[0]:
        best = (last, None)
    if best[1] is not None:
        params.load_state_dict(best[1])
    return {"iterations": len(history), "init_loss": history[0] if history else last, "final_loss": best[0],
            "converged": reason.startswith("converged"), "stop_reason": reason,
            "history": history[:: max(1, len(history) // 100)], "seconds": time.perf_counter() - t0}
