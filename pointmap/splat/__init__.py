"""Gaussian splatting from a reconstruction (InstantSplat-style): init, rasterizer, fitter, outputs.

See docs/splatting.md. ``init_from`` builds Gaussians from a Reconstruction, ``rasterize`` renders
them (tiled PyTorch on CPU, gsplat on CUDA), ``fit`` refines Gaussians and camera poses, ``run`` does
the whole job and writes the outputs.
"""

from pointmap.splat.fit import SplatFit, auto_budget, fit
from pointmap.splat.gaussians import Gaussians
from pointmap.splat.init import init_from
from pointmap.splat.outputs import evaluate_views, run
from pointmap.splat.rasterize import RenderOutput, rasterize

__all__ = ["Gaussians", "RenderOutput", "SplatFit", "auto_budget", "fit", "init_from", "rasterize", "run", "evaluate_views"]
