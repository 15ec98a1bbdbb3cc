"""Checkpoints, unit by unit: refusals, conversions and guarantees that test_checkpoint.py leaves untested."""

import argparse
import json
import math
import os
import warnings

import pytest
import torch

import pointmap as pm
from pointmap import checkpoint
from pointmap.checkpoint import config_from_ctor, dequantize_int8, load_trunk, parse_ctor

# a small DUSt3R-linear constructor: its network builds in a fraction of a second (no DPT head)
LINEAR_CTOR = ("AsymmetricCroCo3DStereo(pos_embed='RoPE100', img_size=(512, 384), head_type='linear', "
               "output_mode='pts3d', depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), "
               "enc_embed_dim=32, enc_depth=2, enc_num_heads=2, "
               "dec_embed_dim=32, dec_depth=2, dec_num_heads=2)")


def small_official(path, ctor=LINEAR_CTOR, **save_kw):
    torch.manual_seed(0)
    model = pm.PointmapNet(config_from_ctor(ctor))
    torch.save({"model": model.state_dict(), "args": argparse.Namespace(model=ctor)}, path, **save_kw)
    return model


def rewritten(path, dest, *, drop=(), drop_meta=()):
    """A copy of the safetensors file ``path`` at ``dest`` without the tensors ``drop`` and the metadata
    entries ``drop_meta`` (and its checksum, so that the check under test answers rather than the checksum)."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(path), "pt") as f:
        md, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys() if k not in drop}
    md = {k: v for k, v in md.items() if k not in ("sha256", *drop_meta)}
    save_file(tensors, str(dest), metadata=md)
    return dest


def test_a_constructor_may_name_nan_but_a_sign_on_a_boolean_is_refused():
    assert math.isnan(parse_ctor("Net(a=nan)")[1]["a"])
    with pytest.raises(pm.CheckpointError, match="unary sign on a non-number"):
        parse_ctor("Net(a=-True)")


@pytest.mark.parametrize("old,new,message", [
    ("dec_num_heads=2)", "dec_num_heads=2, norm_im2_in_dec=False)", "norm_im2_in_dec=False is not supported"),
    ("output_mode='pts3d'", "output_mode='conf'", "output_mode='conf' is not supported"),
    ("head_type='linear'", "head_type='catmlp+dpt'", "'catmlp\\+dpt' needs output_mode 'pts3d\\+descN'"),
    ("dec_num_heads=2)", "dec_num_heads=2, desc_mode='raw')", "desc_mode='raw' is not supported"),
    ("dec_num_heads=2)", "dec_num_heads=2, dropout=0.1)",
     "unsupported constructor arguments .*\\['dropout'\\]"),
    ("depth_mode=('exp', -inf, inf)", "depth_mode=('exp', 0, inf)",
     "depth_mode with bounds is not supported"),
    ("dec_num_heads=2)", "dec_num_heads=2, patch_size=8)", "patch_size=8 is not supported"),
])
def test_an_official_constructor_the_network_cannot_reproduce_is_refused_by_name(old, new, message):
    assert old in LINEAR_CTOR
    with pytest.raises(pm.CheckpointError, match=message):
        config_from_ctor(LINEAR_CTOR.replace(old, new))


def test_an_official_constructor_carries_its_rope_base_metric_flag_and_descriptor_confidence():
    linear = config_from_ctor(LINEAR_CTOR.replace("RoPE100", "RoPE10"))
    assert linear.rope_base == 10.0 and linear.metric is False
    mast3r = config_from_ctor(
        LINEAR_CTOR.replace("AsymmetricCroCo3DStereo", "AsymmetricMASt3R").replace("'linear'", "'catmlp+dpt'")
        .replace("'pts3d'", "'pts3d+desc8'").replace("dec_depth=2", "dec_depth=4")  # (a DPT head needs 4)
        .replace("dec_num_heads=2)", "dec_num_heads=2, desc_conf_mode=('exp', 0, inf))"))
    assert mast3r.metric is True and mast3r.desc_dim == 8
    assert tuple(mast3r.desc_conf_mode) == ("exp", 0, math.inf)
    assert tuple(mast3r.conf_mode) == ("exp", 1, math.inf)


def test_load_trunk_refuses_a_pose_head_a_deeper_checkpoint_and_missing_or_resized_trunk_tensors():
    model = pm.PointmapNet(pm.PRESETS["test"])
    state = dict(model.state_dict())
    cases = [({**state, "pose_head.fc.weight": torch.zeros(2, 2)}, "has a pose head"),
             (pm.PointmapNet(pm.PRESETS["test"].replace(enc_depth=3)).state_dict(),
              r"1 blocks the model does not have \(e.g. \['enc_blocks.2'\]: a deeper checkpoint\)"),
             ({k: v for k, v in state.items() if k != "enc_norm.weight"},
              r"1 missing trunk keys \(e.g. \['enc_norm.weight'\]\)"),
             ({**state, "enc_norm.weight": torch.ones(7)},
              r"1 trunk shape mismatches \(e.g. \['enc_norm.weight: checkpoint \(7,\) vs model \(32,\)'\]\)")]
    for bad, message in cases:
        with pytest.raises(pm.CheckpointError, match=message):
            load_trunk(model, bad, source="ck.pth")


def test_load_trunk_takes_the_trunk_and_matching_head_tensors_and_names_the_resized_ones_it_left_fresh():
    torch.manual_seed(0)
    source = pm.PointmapNet(pm.PRESETS["test"])
    torch.manual_seed(1)
    target = pm.PointmapNet(pm.PRESETS["test"].replace(desc_dim=16))
    fresh_before = {k: v.clone() for k, v in target.state_dict().items()}
    left = load_trunk(target, source.state_dict())
    own, src = target.state_dict(), source.state_dict()
    resized = sorted(k for k in own if src[k].shape != own[k].shape)
    assert resized and left == resized
    for k, v in own.items():
        assert torch.equal(v, fresh_before[k] if k in resized else src[k]), k


def test_a_file_that_is_no_pytorch_file_is_refused_naming_its_first_bytes_and_a_legacy_pickle_loads(tmp_path):
    (tmp_path / "photo.pth").write_bytes(b"GIF89a" + bytes(100))
    with pytest.raises(pm.CheckpointError, match=r"not a PyTorch file .*starts with b'GIF89a"):
        pm.load_model(tmp_path / "photo.pth")
    # torch < 1.6's format: a plain pickle
    model = small_official(tmp_path / "legacy.pth", _use_new_zipfile_serialization=False)
    assert (tmp_path / "legacy.pth").read_bytes()[:1] == b"\x80"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the non-commercial licence
        loaded = pm.load_model(tmp_path / "legacy.pth")
    assert torch.equal(loaded.state_dict()["enc_norm.weight"], model.state_dict()["enc_norm.weight"])


@pytest.mark.filterwarnings("ignore:.*non-commercial use only:UserWarning")
def test_an_official_checkpoint_records_its_longest_input_side_or_its_single_size(tmp_path):
    small_official(tmp_path / "wide.pth")  # img_size=(512, 384)
    assert pm.load_model(tmp_path / "wide.pth").provenance["image_size"] == 512
    small_official(tmp_path / "square.pth", LINEAR_CTOR.replace("img_size=(512, 384)", "img_size=224"))
    assert pm.load_model(tmp_path / "square.pth").provenance["image_size"] == 224


def test_a_training_checkpoint_is_sent_to_ship_and_one_of_another_kind_to_train_init(tmp_path):
    for kind, hint in ((None, "python -m training.ship --ckpt"), ("train", "python -m training.ship --ckpt"),
                       ("grow", "a 'grow' run's: start pointmap training from it with "
                                "`python -m training.train --init")):
        ck = {"model": {}, "model_config": {}, "step": 3, **({"kind": kind} if kind else {})}
        torch.save(ck, tmp_path / "last.pt")
        with pytest.raises(pm.CheckpointError, match=f"is a pointmap training checkpoint .*{hint}"):
            pm.load_model(tmp_path / "last.pt")


def test_a_provenance_given_on_saving_even_an_empty_one_keeps_the_licence_the_weights_carry(tmp_path, tiny_model):
    from safetensors import safe_open

    tiny_model.provenance = {"licence": "CC-BY-NC-SA-4.0", "steps": 9}
    for given, licence in (({"steps": 3}, "CC-BY-NC-SA-4.0"),
                           ({"steps": 3, "licence": "Other-1.0"}, "Other-1.0"),
                           ({}, "CC-BY-NC-SA-4.0")):  # an empty one is given too: not the model's "steps"
        path = pm.save_model(tiny_model, tmp_path / "m.safetensors", provenance=given)
        with safe_open(str(path), "pt") as f:
            assert json.loads(f.metadata()["provenance"]) == {**given, "licence": licence}


def test_a_non_commercial_licence_written_in_lower_case_still_warns_on_loading(tmp_path, tiny_model):
    path = pm.save_model(tiny_model, tmp_path / "m.safetensors", provenance={"licence": "cc-by-nc-4.0"})
    with pytest.warns(UserWarning, match="licensed cc-by-nc-4.0 \\(non-commercial use only\\)"):
        pm.load_model(path)


def test_int8_dequantization_refuses_a_zero_scale():
    q = torch.ones(2, 3, dtype=torch.int8)
    with pytest.raises(ValueError, match="expected finite positive scales"):
        dequantize_int8(q, torch.tensor([0.5, 0.0]))


def test_int8_files_quantize_only_matrices_however_large_a_vector_is(tmp_path, tiny_model, monkeypatch):
    from safetensors import safe_open

    monkeypatch.setattr(checkpoint, "INT8_MIN_NUMEL", 100)  # fc1.bias (128 entries) is then large enough
    path = pm.save_model(tiny_model, tmp_path / "m8.safetensors", dtype="int8")
    with safe_open(str(path), "pt") as f:
        quantized = json.loads(f.metadata()["int8"])
        assert f.get_tensor("enc_blocks.0.mlp.fc1.bias").dtype == torch.float16
    assert "enc_blocks.0.mlp.fc1.weight" in quantized and "enc_blocks.0.mlp.fc1.bias" not in quantized


def test_a_save_that_fails_midway_leaves_the_previous_file_whole_and_no_temporary_file(tmp_path, tiny_model,
                                                                                         monkeypatch):
    import safetensors.torch

    path = pm.save_model(tiny_model, tmp_path / "m.safetensors")
    before = path.read_bytes()

    def dies_midway(tensors, filename, metadata=None):
        with open(filename, "wb") as f:
            f.write(b"half a file")
        raise OSError("No space left on device")

    monkeypatch.setattr(safetensors.torch, "save_file", dies_midway)
    with pytest.raises(OSError, match="No space left"):
        pm.save_model(tiny_model, path)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["m.safetensors"]


def test_a_safetensors_file_missing_a_head_tensor_is_refused_naming_it(tmp_path, tiny_model):
    good = pm.save_model(tiny_model, tmp_path / "m.safetensors")
    name = "downstream_head1.dpt.head.4.bias"
    bad = rewritten(good, tmp_path / "bad.safetensors", drop=[name])
    message = rf"bad.safetensors does not match the architecture: 1 missing keys \(e.g. \['{name}'\]\)"
    with pytest.raises(pm.CheckpointError, match=message):
        pm.load_model(bad)


def test_a_safetensors_file_without_a_config_is_refused_and_one_without_provenance_loads(tmp_path,
                                                                                          tiny_model):
    good = pm.save_model(tiny_model, tmp_path / "m.safetensors")
    with pytest.raises(pm.CheckpointError, match="has a broken config: 'config'"):
        pm.load_model(rewritten(good, tmp_path / "noconfig.safetensors", drop_meta=["config"]))
    noprov = rewritten(good, tmp_path / "noprov.safetensors", drop_meta=["provenance"])
    assert pm.load_model(noprov).provenance == {}


def test_a_truncated_safetensors_file_is_refused_as_corrupt_or_truncated(tmp_path, tiny_model):
    good = pm.save_model(tiny_model, tmp_path / "m.safetensors")
    data = good.read_bytes()
    for n in (4, 100, len(data) // 2):
        (tmp_path / "cut.safetensors").write_bytes(data[:n])
        with pytest.raises(pm.CheckpointError, match=r"cut.safetensors as safetensors \(corrupt or truncated"):
            pm.load_model(tmp_path / "cut.safetensors")


@pytest.mark.parametrize("name", [".", "..", " small", "small ", "", f"a{os.sep}b"])
def test_a_shipped_models_name_must_be_bare(name):
    with pytest.raises(pm.CheckpointError, match="a shipped model's name expected a bare name"):
        checkpoint.shipped_file(name)


def test_a_preset_without_shipped_weights_says_so_and_how_to_get_random_weights(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    name = next(p for p in pm.PRESETS if p not in checkpoint.shipped_models())
    with pytest.raises(pm.CheckpointError, match=rf"preset '{name}' has no shipped weights; .*PointmapNet"):
        pm.load_model(name)


def test_int8_quantization_refuses_nan_or_inf_weights_itself():
    from pointmap.checkpoint import quantize_int8

    for bad in (float("nan"), float("inf")):
        w = torch.ones(3, 4)
        w[1, 2] = bad
        with pytest.raises(ValueError, match="quantize_int8 expected finite weights, got 1 NaN/inf"):
            quantize_int8(w)


def test_a_folder_without_an_onnx_export_is_refused_as_no_model(tmp_path):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.jpg").write_bytes(b"\xff\xd8")
    with pytest.raises(pm.CheckpointError, match="photos is a directory without an .onnx export"):
        pm.load_model(tmp_path / "photos")


def test_load_trunk_leaves_a_new_descriptor_stem_fresh_as_a_head():
    source = pm.PointmapNet(pm.PRESETS["test"])
    target = pm.PointmapNet(pm.PRESETS["test"].replace(desc_stem=4))
    left = load_trunk(target, source.state_dict())
    stem = [k for k in target.state_dict() if k.startswith("desc_stem.")]
    assert stem and set(stem) <= set(left)
    assert all(k.startswith(("desc_stem.", "downstream_head")) for k in left)  # (a head fed by the stem resized)


def test_disagreeing_layer_rn_aliases_are_refused_whichever_comes_first():
    from pointmap.checkpoint import official_to_ours

    w = torch.zeros(2)
    state = {"downstream_head1.dpt.scratch.layer_rn.0.weight": w + 1,
             "downstream_head1.dpt.scratch.layer1_rn.weight": w}  # the alias before its plain name
    with pytest.raises(pm.CheckpointError, match="hold different values"):
        official_to_ours(state)


def test_an_official_checkpoint_without_an_architecture_string_or_with_unnamed_weights_is_refused(tmp_path):
    torch.save({"model": {}, "args": argparse.Namespace(lr=1e-4)}, tmp_path / "noargs.pth")
    with pytest.raises(pm.CheckpointError, match=r"noargs.pth has no architecture string \(args.model\)"):
        pm.load_model(tmp_path / "noargs.pth")
    unnamed = {"model": {3: torch.zeros(2)}, "args": argparse.Namespace(model=LINEAR_CTOR)}
    torch.save(unnamed, tmp_path / "int.pth")
    with pytest.raises(pm.CheckpointError, match="weights expected a dict of named tensors, got 3: Tensor"):
        pm.load_model(tmp_path / "int.pth")


def test_an_architecture_string_naming_a_keyword_twice_is_refused_not_read_as_its_last_value():
    with pytest.raises(pm.CheckpointError, match="names 'enc_depth' twice"):
        parse_ctor("AsymmetricCroCo3DStereo(enc_depth=2, dec_depth=2, enc_depth=24)")


def test_saving_onto_a_folder_that_has_the_files_name_is_refused_before_anything_is_written(tmp_path, tiny_model):
    (tmp_path / "m.safetensors").mkdir()
    with pytest.raises(pm.ShapeError, match="expected a file path, got the folder .*m.safetensors"):
        pm.save_model(tiny_model, tmp_path / "m")  # the suffix is appended first, then the folder is found
    assert [p.name for p in tmp_path.iterdir()] == ["m.safetensors"] and not any((tmp_path / "m.safetensors").iterdir())
