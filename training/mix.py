"""Several shard roots as one training set: ``--data A,B`` (e.g. the procedural set plus a photo-textured one)."""

from __future__ import annotations

import bisect
import os

import numpy as np
from torch.utils.data import Dataset

from data.datasets import PairDataset, camera_rotations_deg, pair_views


def _split_index(index, n: int):
    """``index`` or ``(index, aspect, ...)`` -> (index in [0, n), a function giving the same form for another
    index); IndexError when index is outside [-n, n)."""
    idx, rest = (index[0], index[1:]) if isinstance(index, tuple) else (index, ())
    if not -n <= idx < n:
        raise IndexError(f"index {idx} out of range for {n} pairs")
    idx = idx % n  # a negative index counts from the end, as PairDataset's and a list's do
    return idx, (lambda i: (i, *rest)) if rest else (lambda i: i)


class PairMix(Dataset):
    """Concatenation of pair datasets that share one aspect-ratio list; items accept ``index`` or
    ``(index, aspect)`` like ``data.datasets.PairDataset``."""

    def __init__(self, parts: list) -> None:
        if not parts:
            raise ValueError("PairMix expected at least one dataset, got none")
        aspects = [list(getattr(p, "aspects", [None])) for p in parts]
        if any(a != aspects[0] for a in aspects):
            raise ValueError(f"PairMix parts must share their aspect ratios, got {aspects}")
        self.parts = parts
        self.aspects = aspects[0]
        self.item_seeds = all(getattr(p, "item_seeds", False) for p in parts)
        self.ends = []
        n = 0
        for p in parts:
            n += len(p)
            self.ends.append(n)

    def __len__(self) -> int:
        return self.ends[-1]

    def __getitem__(self, index):
        idx, readdress = _split_index(index, len(self))
        k = bisect.bisect_right(self.ends, idx)
        return self.parts[k][readdress(idx - (self.ends[k - 1] if k else 0))]


def open_pairs(spec: str, **kwargs):
    """``PairDataset`` of one root, or a ``PairMix`` of a comma-separated list of roots."""
    if isinstance(spec, os.PathLike):
        spec = os.fspath(spec)
    if not isinstance(spec, str):
        raise ValueError(f"--data expected shard directories (a path, or paths joined by commas), got "
                         f"{type(spec).__name__}")
    roots = [r for r in spec.split(",") if r]
    if not roots:
        raise ValueError(f"--data expected one or more shard directories, got {spec!r}")
    resolved = [os.path.realpath(r) for r in roots]
    twice = sorted({r for r, p in zip(roots, resolved) if resolved.count(p) > 1})
    if twice:
        raise ValueError(f"--data names the same directory more than once ({', '.join(twice)}): its pairs would "
                         "count twice")
    sets = [PairDataset(r, **kwargs) for r in roots]
    return sets[0] if len(sets) == 1 else PairMix(sets)


class PairSubset(Dataset):
    """The pairs ``indices`` of a pair dataset (keeps its aspect ratios and (index, aspect) items)."""

    def __init__(self, dataset, indices) -> None:
        self.dataset, self.indices = dataset, list(indices)
        self.aspects = list(getattr(dataset, "aspects", [None]))
        self.item_seeds = bool(getattr(dataset, "item_seeds", False))
        if not self.indices:
            raise ValueError("PairSubset expected at least one pair, got none (is the filter too strict?)")

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index):
        idx, readdress = _split_index(index, len(self))
        return self.dataset[readdress(self.indices[idx])]


def relative_rotations_deg(dataset) -> np.ndarray:
    """Ground-truth rotation angle between the two cameras of every pair (from the shard metadata)."""
    if isinstance(dataset, PairMix):
        return np.concatenate([relative_rotations_deg(p) for p in dataset.parts])
    return camera_rotations_deg((m["views"][i], m["views"][j]) for m, i, j in pair_views(dataset))


def limit_rotation(dataset, max_deg: float):
    """Only the pairs whose cameras differ by at most ``max_deg`` degrees (a curriculum: small baselines
    first, where cross-view correspondence is easiest to discover)."""
    if max_deg <= 0:
        return dataset
    return PairSubset(dataset, np.flatnonzero(relative_rotations_deg(dataset) <= max_deg).tolist())
