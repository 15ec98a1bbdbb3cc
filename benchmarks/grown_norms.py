"""How far a grown model's new blocks have woken up: their output projections' norms against their originals'.

``training.grow`` zeroes a new block's output projections (self-attention, cross-attention, MLP), so a copy adds
nothing until training moves them. This prints, for each model or training checkpoint given, the Frobenius norm
of every block's output projections (weights), marks the blocks the growth from ``--grown_from ENC,DEC`` added,
and summarises each kind as the new blocks' median norm over the originals' median. Reading the weights only:
no data, a few seconds.

    python benchmarks/grown_norms.py runs/g88/train/last.pt grown.safetensors --grown_from 6,4
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pointmap.checkpoint import load_model  # noqa: E402
from pointmap.errors import CheckpointError  # noqa: E402
from pointmap.model.config import ModelConfig  # noqa: E402
from training.config import grown_depths  # noqa: E402
from training.grow import GROWN, SILENT, is_growth, new_blocks  # noqa: E402
from training.loop import load_checkpoint  # noqa: E402


def weights(path: str):
    """(state dict, model config) of a training checkpoint (.pt) or of anything ``load_model`` reads."""
    if path.endswith(".pt"):
        ck = load_checkpoint(Path(path))
        return ck["model"], ModelConfig.from_dict(ck["model_config"])
    model = load_model(path)
    if not hasattr(model, "cfg"):
        raise CheckpointError(f"{path} is not a PyTorch model")
    return model.state_dict(), model.cfg


def block_norms(state: dict, enc_from: int, dec_from: int, cfg: ModelConfig) -> list[tuple[str, int, bool, dict]]:
    """(block list, index, new?, {projection: weight norm}) for every block of ``GROWN``."""
    new = new_blocks(enc_from, dec_from, cfg.enc_depth, cfg.dec_depth)
    rows: dict[tuple[str, int], dict] = {}
    for name, t in state.items():
        m = re.fullmatch(rf"({'|'.join(GROWN)})\.(\d+)\.({'|'.join(re.escape(s) for s in SILENT)})\.weight", name)
        if m:
            rows.setdefault((m[1], int(m[2])), {})[m[3]] = float(t.float().norm())
    return [(g, i, i in new[g], norms) for (g, i), norms in sorted(rows.items())]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("models", nargs="+", help="training checkpoints (.pt) or models (.safetensors, a shipped name)")
    p.add_argument("--grown_from", required=True, help="ENC,DEC: the depths the model was grown from")
    a = p.parse_args(argv)
    try:
        enc_from, dec_from = grown_depths(a.grown_from)
    except ValueError as e:
        p.error(str(e))
    for path in a.models:
        try:
            state, cfg = weights(path)
        except (CheckpointError, OSError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        if not is_growth((enc_from, dec_from), (cfg.enc_depth, cfg.dec_depth)):
            print(f"error: {path} has {cfg.enc_depth} encoder and {cfg.dec_depth} decoder blocks: it was not grown "
                  f"from {a.grown_from}", file=sys.stderr)
            return 2
        rows = block_norms(state, enc_from, dec_from, cfg)
        print(f"\n{path} ({cfg.enc_depth} encoder / {cfg.dec_depth} decoder blocks, grown from {a.grown_from})")
        print(f"{'block':<16} {'new':<4} " + " ".join(f"{s:>16}" for s in SILENT))
        for g, i, is_new, norms in rows:
            print(f"{g + '.' + str(i):<16} {'yes' if is_new else '':<4} "
                  + " ".join(f"{norms[s]:16.3f}" if s in norms else f"{'':>16}" for s in SILENT))
        for s in SILENT:
            new = [n[s] for _, _, is_new, n in rows if is_new and s in n]
            old = [n[s] for _, _, is_new, n in rows if not is_new and s in n]
            if new and old:
                print(f"{s}: new blocks' median norm / originals' = {statistics.median(new):.3f} / "
                      f"{statistics.median(old):.3f} = {statistics.median(new) / statistics.median(old):.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
