"""Everything in one .npz: maps, cameras, names, masks and the alignment report (JSON)."""

from __future__ import annotations

import json
from pathlib import Path

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
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
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
        "map_sizes": np.asarray(recon.map_sizes, dtype=np.int64),
        "names": np.asarray(recon.names), "info_json": np.asarray(json.dumps(_jsonable(recon.info))),
    }
    if recon.masks is not None:
        arrays["masks"] = recon.masks.numpy()
    with atomic_open(path) as f:
        np.savez_compressed(f, **arrays)


_KEYS = ("images", "cam2world", "K", "depth_z", "conf", "map_from_original", "original_sizes", "names", "info_json")


def load_npz(path):
    """Read a ``write_npz`` file back into a Reconstruction. PointmapError (one line, naming the file) for a file
    that is missing, not an npz archive, truncated, or another program's archive."""
    from pointmap.errors import PointmapError, ShapeError
    from pointmap.reconstruction import Reconstruction

    path = Path(path)
    if not path.is_file():
        raise PointmapError(f"expected a reconstruction.npz file, got {str(path)!r}, which is not a file")
    with open(path, "rb") as f:
        head = f.read(6)
    if not head.startswith(b"PK"):  # an .npz is a zip archive
        raise PointmapError(f"{path} is not a readable reconstruction.npz (not a zip archive; it starts with {head!r})")
    try:
        with np.load(path, allow_pickle=False) as z:
            if not hasattr(z, "files"):
                raise PointmapError(f"{path} is not a pointmap reconstruction.npz (a single .npy array)")
            missing = [k for k in _KEYS if k not in z.files]
            if missing:
                raise PointmapError(f"{path} is not a pointmap reconstruction.npz (missing {', '.join(missing)}; "
                                    f"it holds {', '.join(z.files[:8]) or 'nothing'})")
            t = {k: torch.from_numpy(z[k]) for k in _KEYS[:6]}
            return Reconstruction(**t, original_sizes=[tuple(int(v) for v in s) for s in z["original_sizes"]],
                                  names=[str(s) for s in z["names"]],
                                  masks=torch.from_numpy(z["masks"]) if "masks" in z.files else None,
                                  # files from before mixed sizes: every view fills the canvas
                                  map_sizes=z["map_sizes"].tolist() if "map_sizes" in z.files else None,
                                  info=json.loads(str(z["info_json"])))
    except ShapeError as e:  # arrays that do not make a reconstruction
        raise PointmapError(f"{path}: not a valid reconstruction: {e}") from None
    except PointmapError:
        raise
    except Exception as e:  # noqa: BLE001 - a damaged archive fails in zipfile, zlib, numpy's header parser (a
        # SyntaxError, tokenize.TokenError), its array reader or json, each with its own type: one message
        raise PointmapError(f"{path} is not a readable reconstruction.npz ({e.__class__.__name__}: {e})") from None
