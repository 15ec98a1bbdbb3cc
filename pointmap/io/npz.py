"""Everything in one .npz: maps, cameras, names, masks and the alignment report (JSON)."""

from __future__ import annotations

import json

import numpy as np
import torch

from pointmap.io.atomic import atomic_open


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.generic,)):
        return x.item()
    if torch.is_tensor(x):
        return x.tolist()
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return repr(x)


def write_npz(path, recon) -> None:
    arrays = {
        "images": recon.images.float().numpy(), "cam2world": recon.cam2world.float().numpy(),
        "K": recon.K.float().numpy(), "K_map": recon.K_map.float().numpy(),
        "depth_z": recon.depth_z.float().numpy(), "conf": recon.conf.float().numpy(),
        "pts_world": recon.pts_world.float().numpy(),
        "map_from_original": recon.map_from_original.float().numpy(),
        "original_sizes": np.asarray(recon.original_sizes, dtype=np.int64),
        "names": np.asarray(recon.names), "info_json": np.asarray(json.dumps(_jsonable(recon.info))),
    }
    if recon.masks is not None:
        arrays["masks"] = recon.masks.numpy()
    with atomic_open(path) as f:
        np.savez_compressed(f, **arrays)


def load_npz(path):
    """Read a ``write_npz`` file back into a Reconstruction."""
    from pointmap.reconstruction import Reconstruction

    with np.load(path, allow_pickle=False) as z:
        t = {k: torch.from_numpy(z[k]) for k in ("images", "cam2world", "K", "depth_z", "conf", "map_from_original")}
        return Reconstruction(**t, original_sizes=[tuple(int(v) for v in s) for s in z["original_sizes"]],
                              names=[str(s) for s in z["names"]],
                              masks=torch.from_numpy(z["masks"]) if "masks" in z.files else None,
                              info=json.loads(str(z["info_json"])))
