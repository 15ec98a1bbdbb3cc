"""Render the demo scenes that ship with the package (``pointmap/demo_scenes``), from seeds never used
for training: ``python -m data.demo_scenes --out pointmap/demo_scenes``.

Each scene directory holds ``view-K.png`` (the photos, 320x240) and ``gt.npz`` (K [V, 3, 3] in those
pixels, cam2world [V, 4, 4] OpenCV, depth_z [V, H, W] float16 metres, 0 = background).
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path

import numpy as np

from data.cameras import CameraConfig, DegenerateScene, sample_views
from data.scene import make_scene
from data.shards import png_bytes, write_atomic

DEMO_SEED = 31_337_000  # a seed range never used for training sets
DEMO_VERSION = 1  # the generator version the shipped scenes were drawn with: this renders them again byte for byte
DEMO = (("room", "room", 0.0), ("objects", "cluster", 0.0), ("courtyard", "courtyard", 0.0))


DEMO_CAMERA = CameraConfig(orientation_weights=(0.0, 1.0, 0.0), short_side_ratios=(0.75,), overlap=(0.35, 0.9),
                           move_weights=(0.3, 0.4, 0.3, 0.0, 0.0, 0.0), fov_deg=(50.0, 70.0))


def render_demo(out: Path, views: int = 3, size: int = 320, version: int = DEMO_VERSION) -> list[Path]:
    from data.render import get_renderer

    renderer = get_renderer()
    cam = DEMO_CAMERA
    written = []
    for k, (name, kind, low) in enumerate(DEMO):
        rng = np.random.default_rng([DEMO_SEED, k])
        for _ in range(20):
            scene = make_scene(rng, kind, low_texture_share=low, version=version)
            try:
                vs = sample_views(rng, scene, renderer, views, size, cam)
            except DegenerateScene:
                continue
            if len(vs.pairs(0.3, 0.95)) >= views - 1:
                break
        else:
            raise RuntimeError(f"demo scene {name}: no acceptable views")
        d = out / name
        d.mkdir(parents=True, exist_ok=True)
        for i, v in enumerate(vs.views):
            write_atomic(d / f"view-{i}.png", png_bytes(v.rgb))
        buf = io.BytesIO()
        np.savez_compressed(buf, K=np.stack([v.K for v in vs.views]).astype(np.float64),
                            cam2world=np.stack([v.cam2world for v in vs.views]).astype(np.float64),
                            depth_z=np.stack([v.depth for v in vs.views]).astype(np.float16))
        write_atomic(d / "gt.npz", buf.getvalue())
        write_atomic(d / "scene.json", json.dumps({"kind": kind, "seed": [DEMO_SEED, k], "views": views,
                                                   "overlap": np.round(vs.overlap, 3).tolist()}, indent=1).encode())
        written.append(d)
    return written


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m data.demo_scenes", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="pointmap/demo_scenes")
    p.add_argument("--views", type=int, default=3)
    a = p.parse_args(argv)
    for d in render_demo(Path(a.out), a.views):
        print(d)
    return 0


if __name__ == "__main__":
    sys.exit(main())
