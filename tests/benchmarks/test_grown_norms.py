import re

import pytest
import torch

import pointmap as pm
from benchmarks.grown_norms import block_norms, main
from training.grow import deepen


def _grown(tmp_path):
    torch.manual_seed(0)
    model = pm.PointmapNet(pm.PRESETS["test"].replace(head="catmlp+linear"))  # 2 encoder, 4 decoder blocks
    grown = deepen(model, enc_depth=3, dec_depth=6)
    with torch.no_grad():  # "training" woke one new block up: its MLP projection now has a known norm
        grown.enc_blocks[1].mlp.fc2.weight.fill_(0.5)
    return grown, pm.save_model(grown, tmp_path / "grown.safetensors")


def test_the_new_blocks_are_marked_and_their_norms_read_against_the_originals(tmp_path, capsys):
    grown, path = _grown(tmp_path)
    rows = block_norms(grown.state_dict(), 2, 4, grown.cfg)
    new = {(g, i) for g, i, is_new, _ in rows if is_new}
    assert new == {("enc_blocks", 1), *((d, i) for d in ("dec_blocks", "dec_blocks2") for i in (1, 4))}  # copies precede their originals
    norms = {(g, i): n for g, i, _, n in rows}
    w = grown.enc_blocks[1].mlp.fc2.weight
    assert norms[("enc_blocks", 1)]["mlp.fc2"] == pytest.approx(0.5 * w.numel() ** 0.5)
    assert norms[("enc_blocks", 1)]["attn.proj"] == 0 and "cross_attn.proj" not in norms[("enc_blocks", 1)]
    assert norms[("dec_blocks", 1)]["cross_attn.proj"] == pytest.approx(float(grown.dec_blocks[1].cross_attn.proj.weight.detach().norm()))
    assert main([str(path), "--grown_from", "2,4"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^attn\.proj: new blocks' median norm / originals' = 0\.000 / ", out, re.M)
    assert re.search(r"^mlp\.fc2: new blocks' median norm / originals' = 0\.000 / ", out, re.M)  # 1 of 5 woke up
    assert re.search(r"^enc_blocks\.1 +yes +0\.000 +\d+\.\d{3}$", out, re.M)  # no cross-attention in the encoder


def test_a_model_that_cannot_have_grown_from_the_given_depths_is_refused(tmp_path, capsys):
    _, path = _grown(tmp_path)
    for depths in ("4,4", "3,6"):  # more blocks than it has; no fewer than it has
        assert main([str(path), "--grown_from", depths]) == 2
        assert f"was not grown from {depths}" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(path), "--grown_from", "x"])
    assert "--grown_from expected ENC,DEC (two block counts, e.g. 6,4), got 'x'" in capsys.readouterr().err
