"""The variables of dense alignment, as increments on a fixed base (the initialisation).

cam2world_n = base_n @ se3_exp(xi_n)          (xi frozen at 0 for known poses)
f_n         = exp(log_f_c(n))                 (fx = fy; known intrinsics are constants; one log_f per
                                              camera c: per image, or shared as AlignConfig.shared_focal says)
depth_n     = exp(log_depth_n)                [N, P] at the stack's pixels
S_e         = s_e [R0_e exp(phi_e) | t0_e + dt_e],  log s_e = log s0_e + dls_e
              (mean of log s held at its initial value when the scale is free: fixes the gauge)
Everything is in a normalised world (scene scale ~1); see optimize.py for the scaling.
"""

from __future__ import annotations

import torch

from pointmap.align.objective import rays, world_points
from pointmap.geometry.rotations import axis_angle_to_matrix, se3_exp


class AlignParams(torch.nn.Module):
    def __init__(self, base_cam2world, pose_free, depth, fx, fy, cx, cy, focal_free, pw_s, pw_R, pw_t,
                 scale_free: bool, dtype=torch.float32, camera: torch.Tensor | None = None):
        super().__init__()
        n, E = base_cam2world.shape[0], pw_s.shape[0]
        self.register_buffer("base_cam2world", base_cam2world.to(dtype))
        self.register_buffer("pose_free", pose_free.to(dtype)[:, None])
        self.register_buffer("focal_free", focal_free.to(torch.bool))
        self.register_buffer("f_fixed_x", fx.to(dtype))
        self.register_buffer("f_fixed_y", fy.to(dtype))
        self.register_buffer("cx", cx.to(dtype))
        self.register_buffer("cy", cy.to(dtype))
        self.register_buffer("pw_R0", pw_R.to(dtype))
        self.register_buffer("pw_t0", pw_t.to(dtype))
        self.register_buffer("pw_ls0", pw_s.log().to(dtype))
        self.register_buffer("pw_ls_mean", pw_s.log().mean().to(dtype))
        self.scale_free = scale_free
        self.xi = torch.nn.Parameter(torch.zeros(n, 6, dtype=dtype))
        # camera: [n] index of each image's camera (default: one per image); one log-focal per camera, started at
        # the mean of its images' starting focals (global_align gives them one value: the median of their estimates)
        camera = torch.arange(n) if camera is None else torch.as_tensor(camera, dtype=torch.long)
        self.register_buffer("camera", camera)
        n_cams = int(camera.max()) + 1
        log_f = torch.zeros(n_cams, dtype=fx.dtype).index_add_(0, camera, fx.log())
        log_f = log_f / torch.bincount(camera, minlength=n_cams)
        self.log_f = torch.nn.Parameter(log_f.to(dtype))
        self.log_depth = torch.nn.Parameter(depth.clamp_min(1e-8).log().to(dtype))
        self.pw_phi = torch.nn.Parameter(torch.zeros(E, 3, dtype=dtype))
        self.pw_dt = torch.nn.Parameter(torch.zeros(E, 3, dtype=dtype))
        self.pw_dls = torch.nn.Parameter(torch.zeros(E, dtype=dtype))

    def param_groups(self, lr: float, lr_focal: float | None = None):
        groups = [{"params": [self.log_depth, self.pw_phi, self.pw_dt, self.pw_dls], "lr": lr}]
        if bool(self.pose_free.any()):
            groups.append({"params": [self.xi], "lr": lr})
        if bool(self.focal_free.any()):
            groups.append({"params": [self.log_f], "lr": lr if lr_focal is None else lr_focal})
        return groups

    def cam2world(self) -> torch.Tensor:
        return self.base_cam2world @ se3_exp(self.xi * self.pose_free)

    def intrinsics(self):
        f = torch.exp(self.log_f)[self.camera]
        fx = torch.where(self.focal_free, f, self.f_fixed_x)
        fy = torch.where(self.focal_free, f, self.f_fixed_y)
        return fx, fy, self.cx, self.cy

    def pw(self):
        ls = self.pw_ls0 + self.pw_dls
        if self.scale_free:
            ls = ls - ls.mean() + self.pw_ls_mean
        R = self.pw_R0 @ axis_angle_to_matrix(self.pw_phi)
        return torch.exp(ls), R, self.pw_t0 + self.pw_dt

    def world_points(self, uv: torch.Tensor) -> torch.Tensor:
        fx, fy, cx, cy = self.intrinsics()
        return world_points(torch.exp(self.log_depth), rays(uv, fx, fy, cx, cy), self.cam2world())
