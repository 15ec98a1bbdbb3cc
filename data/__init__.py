"""Synthetic data engine: procedural scenes rendered with pyrender into pairs and view sets with exact
ground truth (docs/data.md). Import submodules directly (``data.scene``, ``data.render``,
``data.datasets`` ...); this package itself imports nothing heavy."""

from __future__ import annotations

from pathlib import Path

HELDOUT_SEED = 2**31 - 1000  # first of data.generate.RESERVED_SEEDS: never usable by training runs


def heldout(root_dir, *, kind: str = "pairs", size: int = 224, scenes: int = 32, views: int = 4,
            workers: int = 1, progress: bool = False):
    """The fixed held-out evaluation set: rendered once into ``root_dir/heldout-{kind}-{size}`` from the
    reserved seed (training runs refuse reserved seeds), then opened without augmentation.

    Returns a ``PairDataset`` (split "all", augment=False) for kind "pairs", a ``MultiViewDataset``
    for kind "views". Rendering again with the same arguments reuses the existing shards, and a set made by an older
    generator version (data.generate.GENERATOR_VERSION) is completed with that version's scenes.
    """
    from data.datasets import MultiViewDataset, PairDataset
    from data.generate import GenConfig, generate

    if kind not in ("pairs", "views"):
        raise ValueError(f"kind expected 'pairs' or 'views', got {kind!r}")
    out = Path(root_dir) / f"heldout-{kind}-{size}"
    cfg = GenConfig(kind=kind, scenes=scenes, views=views, size=size, shard_size=min(16, scenes), seed=HELDOUT_SEED)
    if (out / "config.json").is_file():  # a set rendered before: again with its own generator version
        from dataclasses import replace

        from data.shards import load_json

        cfg = replace(cfg, version=load_json(out / "config.json").get("version"))
    generate(out, cfg, workers=workers, progress=progress, log=None)
    if kind == "pairs":
        return PairDataset(out, size=size, augment=False, split="all")
    return MultiViewDataset(out, split="all")

