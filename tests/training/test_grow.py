"""training.grow: a deepened model computes what the original did, and its new blocks can learn."""

import numpy as np
import pytest
import torch

import pointmap as pm
from pointmap.model import PRESETS, PointmapNet
from training.grow import deepen, main, silent_parameters

CFG = PRESETS["test"].replace(head="catmlp+linear", pose_head=True, desc_stem=4)


def _model(seed=0, cfg=CFG):
    torch.manual_seed(seed)
    model = PointmapNet(cfg).eval()
    with torch.no_grad():  # non-trivial norms and biases, so a copy that is not silent would show
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model


@pytest.mark.parametrize("head, depths", [("catmlp+linear", dict(enc_depth=5, dec_depth=7)),
                                          ("linear", dict(enc_depth=3, dec_depth=5)),
                                          ("catmlp+dpt", dict(enc_depth=4))])
def test_a_deepened_model_computes_exactly_what_the_original_computes(head, depths):
    cfg = CFG.replace(head=head, desc_dim=CFG.desc_dim if head.startswith("catmlp") else 0,
                      desc_stem=CFG.desc_stem if head.startswith("catmlp") else 0)
    model = _model(cfg=cfg)
    grown = deepen(model, **depths).eval()
    assert grown.cfg == cfg.replace(**depths) and model.cfg == cfg
    torch.manual_seed(1)
    a, b = torch.rand(2, 3, 32, 48), torch.rand(2, 3, 32, 48)
    with torch.no_grad():
        want, got = model(a, b), grown(a, b)
    for k in ("pts1_cam1", "pts2_cam1", "conf1", "conf2", "desc1", "desc2"):
        if getattr(want, k) is not None:
            assert torch.equal(getattr(got, k), getattr(want, k)), k


def test_new_blocks_precede_the_block_they_copy_spread_evenly_with_silent_outputs():
    model = _model()
    grown = deepen(model, enc_depth=5, dec_depth=6)  # encoder 2 -> 5: block 0 gets 1 copy, block 1 gets 2
    for blocks, old_blocks, src, originals in ((grown.enc_blocks, model.enc_blocks, [0, 0, 1, 1, 1], (1, 4)),
                                               (grown.dec_blocks2, model.dec_blocks2, [0, 1, 1, 2, 3, 3], (0, 2, 3, 5))):
        for i, blk in enumerate(blocks):
            old = old_blocks[src[i]]
            if i in originals:
                assert blk is not old and all(torch.equal(x, y) for x, y in
                                              zip(blk.state_dict().values(), old.state_dict().values())), i
                continue
            torch.testing.assert_close(blk.attn.qkv.weight, old.attn.qkv.weight, rtol=0, atol=0)
            torch.testing.assert_close(blk.mlp.fc1.weight, old.mlp.fc1.weight, rtol=0, atol=0)
            outs = [blk.attn.proj, blk.mlp.fc2] + ([blk.cross_attn.proj] if hasattr(blk, "cross_attn") else [])
            assert all(bool((lin.weight == 0).all() and (lin.bias == 0).all()) for lin in outs), i


def test_the_silent_blocks_get_gradients_and_learn():
    grown = deepen(_model(), dec_depth=5).train()
    out = grown(torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32))
    (out.pts1_cam1.square().mean() + out.pts2_cam1.square().mean()).backward()
    new = grown.dec_blocks[3]  # 4 -> 5: the one copy precedes the last block
    assert float(new.mlp.fc2.weight.detach().abs().sum()) == 0
    assert float(new.mlp.fc2.weight.grad.abs().sum()) > 0
    assert float(new.cross_attn.proj.weight.grad.abs().sum()) > 0


def test_growth_refuses_shrinking_no_change_and_a_dpt_decoder_with_the_reason():
    with pytest.raises(ValueError, match="growth only"):
        deepen(_model(), enc_depth=1)
    with pytest.raises(ValueError, match="nothing to grow"):
        deepen(_model(), enc_depth=2)
    with pytest.raises(ValueError, match="expected an int"):
        deepen(_model(), enc_depth=2.7)
    assert deepen(_model(), enc_depth=np.int64(3)).cfg.enc_depth == 3  # a NumPy int is an int
    with pytest.raises(ValueError, match="intermediate decoder layers"):
        deepen(PointmapNet(PRESETS["test"]), dec_depth=6)


def test_the_command_writes_a_grown_model_file_and_fails_in_one_line(tmp_path, capsys):
    model = _model()
    pm.save_model(model, tmp_path / "m.safetensors", provenance={"steps": 9})
    assert main(["--init", str(tmp_path / "m.safetensors"), "--dec_depth", "6", "--out", str(tmp_path / "g.safetensors")]) == 0
    grown = pm.load_model(tmp_path / "g.safetensors")
    assert grown.cfg.dec_depth == 6 and grown.provenance["grown_from"] == [{"enc_depth": 2, "dec_depth": 4}]
    assert grown.provenance["steps"] == 9
    assert main(["--init", str(tmp_path / "g.safetensors"), "--enc_depth", "3", "--out", str(tmp_path / "g2.safetensors")]) == 0
    assert pm.load_model(tmp_path / "g2.safetensors").provenance["grown_from"] == [
        {"enc_depth": 2, "dec_depth": 4}, {"enc_depth": 2, "dec_depth": 6}]
    (tmp_path / "junk.safetensors").write_bytes(b"junk")
    for args in (["--init", str(tmp_path / "junk.safetensors")], ["--init", str(tmp_path / "m.safetensors"), "--enc_depth", "1"],
                 ["--init", str(tmp_path / "m.safetensors")]):
        assert main([*args, "--out", str(tmp_path / "x.safetensors")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error:") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.safetensors").exists()


@pytest.mark.parametrize("new", [(3, 7), (2, 5), (7, 4)])
def test_silent_parameters_name_exactly_the_tensors_growth_zeroed(new):
    model = _model()  # every tensor non-zero, so the grown model's zeros are growth's
    old = (model.cfg.enc_depth, model.cfg.dec_depth)
    grown = deepen(model, enc_depth=new[0], dec_depth=new[1])
    zero = {n for n, p in grown.named_parameters() if not p.any()}
    silent = silent_parameters([n for n, _ in grown.named_parameters()], *old, *new)
    assert zero and set(silent) == zero and len(silent) == len(zero)
    assert not silent_parameters([n for n, _ in model.named_parameters()], *old, *old)  # no growth, none


def test_after_two_growths_silent_parameters_of_the_last_one_name_its_zeroed_tensors():
    first = deepen(_model(), enc_depth=3, dec_depth=6)
    with torch.no_grad():  # trained since: the first growth's copies are no longer zero
        for p in first.parameters():
            p.add_(0.05 * torch.randn_like(p))
    grown = deepen(first, enc_depth=4, dec_depth=8)
    assert grown.provenance["grown_from"][-2:] == [{"enc_depth": 2, "dec_depth": 4}, {"enc_depth": 3, "dec_depth": 6}]
    zero = {n for n, p in grown.named_parameters() if not p.any()}
    assert zero and set(silent_parameters([n for n, _ in grown.named_parameters()], 3, 6, 4, 8)) == zero


def test_a_grown_model_cannot_be_cut_down_to_a_shallower_one_by_loading_its_trunk():
    from pointmap.checkpoint import load_trunk
    from pointmap.errors import CheckpointError

    grown = deepen(_model(), enc_depth=3, dec_depth=6)
    with pytest.raises(CheckpointError, match=r"blocks the model does not have \(e.g. \['dec_blocks.4'"):
        load_trunk(PointmapNet(CFG), grown.state_dict(), source="grown")
