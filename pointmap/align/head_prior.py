"""The pose heads' relative poses as a prior on the cameras of dense alignment.

The dense objective fits every pair's two pointmaps, and where two regressions of one view disagree it turns the
cameras to fit them; the pair's pose head says better where camera j sits relative to camera i (session 49). On
the tuning set the start from the heads had more rotations within 15 degrees than the dense optimisation that
follows it (docs/alignment.md). So with a pose head every directed edge e = (i, j) adds to the objective

    weight * sum_e w_e [rho(c(R_e^T R_i^T R_j); s_rot) + rho(c(angle(R_i^T (C_j - C_i), t_e)); s_dir)] / sum_e w_e

with (R_e, t_e) the head's transform (camera j -> camera i), R_n / C_n camera n's rotation / centre in the world,
w_e the edge score, c(theta) = 2 sin(theta / 2) the chord of an angle (smooth at 0: ||R_i R_e - R_j||_F / sqrt 2
for rotations, ||u / |u| - t_e / |t_e| || for directions) and rho(x; s) = s^2 log(1 + x^2 / s^2) (Cauchy: a
head that is wrong by much more than s pulls little). Only the cameras feel it; the scale stays the dense
objective's (the heads' baselines come out short, session 49). The prior holds every edge or none: the stack has
the heads' transforms only when every prediction carries one. Edges between two known cameras are left out (they
cannot move). A baseline much shorter than ``baseline_floor`` has no direction to hold (a pan): u is normalised as
u / sqrt(|u|^2 + floor^2), so the direction term's pull fades instead of growing as 1 / |u|; in global_align's
internal unit (the median depth is 1) the floor is 0.01, the training loss's ``MIN_BASELINE``.
"""

from __future__ import annotations

import math

import torch

from pointmap.errors import ShapeError, is_number

BASELINE_FLOOR = 0.01  # in the alignment's internal unit (median depth 1): shorter baselines have no direction


def chord(deg: float) -> float:
    """2 sin(theta / 2) of an angle in degrees: the residual unit of the prior."""
    return 2.0 * math.sin(math.radians(deg) / 2.0)


class HeadPrior:
    """The prior of one alignment: the edges' head transforms and weights, fixed; ``loss(cam2world)`` is
    differentiable in the cameras."""

    def __init__(self, i: torch.Tensor, j: torch.Tensor, T: torch.Tensor, score: torch.Tensor, weight: float,
                 rot_deg: float, dir_deg: float, dtype=torch.float32, baseline_floor: float = BASELINE_FLOOR,
                 pose_free: torch.Tensor | None = None):
        E = i.shape[0]
        if i.shape != (E,) or j.shape != (E,) or T.shape != (E, 4, 4) or score.shape != (E,):
            raise ShapeError(f"HeadPrior expected i, j, score [E] and T [E, 4, 4], got {tuple(i.shape)}, "
                             f"{tuple(j.shape)}, {tuple(score.shape)}, {tuple(T.shape)}")
        if not (is_number(weight) and 0 <= weight < math.inf and is_number(baseline_floor) and baseline_floor > 0):
            raise ShapeError(f"HeadPrior expected a finite weight >= 0 and a baseline floor > 0, got {weight!r}, "
                             f"{baseline_floor!r}")
        ok = torch.isfinite(T.flatten(1)).all(1) & torch.isfinite(score) & (score > 0)
        t = T[:, :3, 3].double()
        ok &= t.norm(dim=1) > 0
        if pose_free is not None:  # an edge between two known cameras cannot move
            ok &= pose_free.bool()[i] | pose_free.bool()[j]
        self.i, self.j = i[ok], j[ok]
        self.R = T[ok, :3, :3].to(dtype)
        self.t = (t[ok] / t[ok].norm(dim=1, keepdim=True)).to(dtype)
        w = score[ok].double()
        self.w = (w / w.sum()).to(dtype) if len(w) else w.to(dtype)
        self.weight, self.floor = float(weight), float(baseline_floor)
        self.s_rot, self.s_dir = chord(rot_deg), chord(dir_deg)

    @property
    def num_edges(self) -> int:
        return int(self.i.shape[0])

    def residuals(self, cam2world: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Squared chords [E] of the rotation and direction residuals at cameras ``cam2world`` [N, 4, 4]."""
        Ri, Rj = cam2world[self.i, :3, :3], cam2world[self.j, :3, :3]
        rot = (Ri @ self.R - Rj).square().sum((-1, -2)) / 2
        u = (Ri.transpose(-1, -2) @ (cam2world[self.j, :3, 3] - cam2world[self.i, :3, 3])[..., None])[..., 0]
        u = u / (u.square().sum(-1, keepdim=True) + self.floor ** 2).sqrt()
        return rot, (u - self.t).square().sum(-1)

    def loss(self, cam2world: torch.Tensor) -> torch.Tensor:
        if self.num_edges == 0:
            return cam2world.new_zeros(())
        rot, dirs = self.residuals(cam2world)
        rho = lambda x2, s: s * s * torch.log1p(x2 / (s * s))  # noqa: E731
        return self.weight * (self.w * (rho(rot, self.s_rot) + rho(dirs, self.s_dir))).sum()


def head_prior(stack, weight: float, rot_deg: float, dir_deg: float, *, pose_free: torch.Tensor | None = None,
               dtype=torch.float32) -> HeadPrior | None:
    """The prior of an edge stack whose predictions carry the pose head's transforms (``stack.T``), or None (no
    transforms, or weight 0). ``pose_free`` [N] bool: False for known cameras."""
    if stack.T is None or weight <= 0:
        return None
    return HeadPrior(stack.i, stack.j, stack.T, stack.score, weight, rot_deg, dir_deg, dtype=dtype,
                     pose_free=pose_free)
