"""Checkpoints: official .pth files (safely), our safetensors format, shipped names, clear failures."""

import argparse
import json
import math
import os
import re

import numpy as np
import pytest
import torch

import pointmap as pm
from pointmap.checkpoint import config_from_ctor, parse_ctor

TINY_CTOR = ("AsymmetricMASt3R(pos_embed='RoPE100', patch_embed_cls='ManyAR_PatchEmbed', img_size=(512, 512), "
             "head_type='catmlp+dpt', output_mode='pts3d+desc8', depth_mode=('exp', -inf, inf), "
             "conf_mode=('exp', 1, inf), enc_embed_dim=32, enc_depth=2, enc_num_heads=2, dec_embed_dim=32, "
             "dec_depth=4, dec_num_heads=2, two_confs=True, desc_conf_mode=('exp', 0, inf))")


def official_style_state(model):
    """Our state dict written the way the official code saves it: DPT alias keys and a mask token."""
    sd = dict(model.state_dict())
    for k in list(sd):
        if ".scratch.layer" in k and "_rn." in k:
            i = int(k.split(".scratch.layer")[1][0])
            sd[k.replace(f".scratch.layer{i}_rn.", f".scratch.layer_rn.{i - 1}.")] = sd[k]
    sd["mask_token"] = torch.zeros(1, 1, 32)
    return sd


def tiny_official(tmp_path, ctor=TINY_CTOR):
    cfg = config_from_ctor(ctor)
    cfg = cfg.replace(dpt_layer_dims=(96, 192, 384, 768))
    torch.manual_seed(0)
    model = pm.PointmapNet(cfg).eval()
    path = tmp_path / "official.pth"
    torch.save({"model": official_style_state(model), "args": argparse.Namespace(model=ctor, lr=1e-4), "epoch": 3},
               path)
    return model, path


def test_the_constructor_grammar_reads_keywords_numbers_strings_tuples_and_inf():
    name, kw = parse_ctor("Net(a=1, b=-2.5, c='x', d=(1, 'y', -inf), e=True, f=None, g=[inf])")
    assert name == "Net"
    assert kw == {"a": 1, "b": -2.5, "c": "x", "d": (1, "y", -math.inf), "e": True, "f": None, "g": (math.inf,)}


@pytest.mark.parametrize("text,message", [("__import__('os').system('ls')", "must be Name\\(key=value, ...\\)"),
                                          ("Net(a=os.system('x'))", "unsupported value Call"),
                                          ("Net(a=1+2)", "unsupported value BinOp"),
                                          ("Net(**kw)", "'\\*\\*' is not allowed"),
                                          ("Net(a=f(1))", "unsupported value Call"),
                                          ("Net(1)", "must be Name\\(key=value, ...\\)")])
def test_the_constructor_grammar_refuses_anything_but_literals(text, message):
    with pytest.raises(pm.CheckpointError, match=message):
        parse_ctor(text)


@pytest.mark.filterwarnings("ignore:.*non-commercial use only:UserWarning")  # the licence warning has its own test
def test_an_official_checkpoint_with_alias_keys_and_a_namespace_loads_into_identical_outputs(tmp_path):
    model, path = tiny_official(tmp_path)
    loaded = pm.load_model(path)
    a, b = torch.rand(1, 3, 32, 48), torch.rand(1, 3, 32, 48)
    with torch.no_grad():
        ref, got = model(a, b), loaded(a, b)
    for name, t in ref.as_dict().items():
        assert torch.equal(t, getattr(got, name)), name
    assert loaded.cfg.desc_dim == 8 and loaded.cfg.two_confs


def test_an_official_checkpoint_says_it_is_non_commercial_and_a_saved_copy_keeps_its_licence(tmp_path):
    from pointmap.checkpoint import OFFICIAL_LICENCE, model_licence

    _, path = tiny_official(tmp_path)
    with pytest.warns(UserWarning, match=r"official NAVER weights are licensed CC-BY-NC-SA-4.0 \(non-commercial"):
        loaded = pm.load_model(path)
    assert model_licence(loaded) == OFFICIAL_LICENCE
    copy = pm.save_model(loaded, tmp_path / "copy.safetensors")
    with pytest.warns(UserWarning, match=r"derived from official ones\) are licensed CC-BY-NC-SA-4.0"):
        assert model_licence(pm.load_model(copy)) == OFFICIAL_LICENCE
    assert model_licence(pm.PointmapNet(pm.PRESETS["test"])) is None


@pytest.mark.filterwarnings("ignore:.*non-commercial use only:UserWarning")  # the licence warning has its own test
def test_an_official_checkpoint_runs_at_the_size_its_constructor_names(tmp_path):
    from pointmap.checkpoint import model_input_size

    _, path = tiny_official(tmp_path)
    assert model_input_size(pm.load_model(path)) == 512  # img_size=(512, 512)
    (tmp_path / "224").mkdir()
    ctor = TINY_CTOR.replace("img_size=(512, 512)", "img_size=(224, 224)")
    assert model_input_size(pm.load_model(tiny_official(tmp_path / "224", ctor)[1])) == 224
    (tmp_path / "none").mkdir()  # no img_size: the caller's default
    ctor = TINY_CTOR.replace("img_size=(512, 512), ", "")
    assert model_input_size(pm.load_model(tiny_official(tmp_path / "none", ctor)[1]), default=7) == 7


def test_a_croco_checkpoint_without_second_decoder_gets_a_copy_of_the_first(tmp_path):
    from pointmap.checkpoint import official_to_ours

    model = pm.PointmapNet(pm.PRESETS["test"])
    sd = {k: v for k, v in model.state_dict().items() if not k.startswith("dec_blocks2.")}
    out = official_to_ours(sd)
    assert torch.equal(out["dec_blocks2.0.attn.qkv.weight"], sd["dec_blocks.0.attn.qkv.weight"])


def test_mismatched_keys_and_shapes_are_all_listed(tmp_path):
    model, path = tiny_official(tmp_path)
    with torch.serialization.safe_globals([argparse.Namespace]):
        ck = torch.load(path, weights_only=True)
    del ck["model"]["enc_norm.weight"]
    ck["model"]["extra.weight"] = torch.zeros(1)
    ck["model"]["decoder_embed.bias"] = torch.zeros(5)
    torch.save(ck, tmp_path / "broken.pth")
    with pytest.raises(pm.CheckpointError) as e:
        pm.load_model(tmp_path / "broken.pth")
    msg = str(e.value)
    assert "missing" in msg and "enc_norm.weight" in msg and "extra.weight" in msg and "decoder_embed.bias" in msg


def test_a_checkpoint_that_needs_pickled_code_is_refused_without_running_it(tmp_path):
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    torch.save({"model": {}, "args": Evil()}, tmp_path / "evil.pth")
    with pytest.raises(pm.CheckpointError, match="arbitrary pickled code"):
        pm.load_model(tmp_path / "evil.pth")
    assert not marker.exists()


def test_truncated_corrupt_and_foreign_files_give_one_line_errors(tmp_path):
    model, path = tiny_official(tmp_path)
    data = path.read_bytes()
    (tmp_path / "trunc.pth").write_bytes(data[: len(data) // 2])
    (tmp_path / "text.pth").write_text("not a checkpoint")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pth")
    for name, pattern in [("trunc.pth", "cannot read"), ("text.pth", "cannot read"), ("foreign.pth", "not a DUSt3R")]:
        with pytest.raises(pm.CheckpointError, match=pattern):
            pm.load_model(tmp_path / name)
    with pytest.raises(pm.CheckpointError, match="not found"):
        pm.load_model(tmp_path / "missing.pth")


def test_unknown_architectures_are_named_in_the_error(tmp_path):
    torch.save({"model": {}, "args": argparse.Namespace(model="ResNet50(depth=50)")}, tmp_path / "r.pth")
    with pytest.raises(pm.CheckpointError, match="unknown architecture 'ResNet50'"):
        pm.load_model(tmp_path / "r.pth")
    with pytest.raises(pm.CheckpointError, match="pos_embed='cosine'"):
        config_from_ctor("AsymmetricCroCo3DStereo(pos_embed='cosine')")


def test_our_format_round_trips_exactly_and_keeps_provenance(tmp_path, tiny_model):
    path = pm.save_model(tiny_model, tmp_path / "m", provenance={"image_size": 224, "steps": 5})
    assert path.suffix == ".safetensors" and not list(tmp_path.glob("*.tmp"))
    loaded = pm.load_model(path)
    assert loaded.cfg == tiny_model.cfg and loaded.provenance["image_size"] == 224
    for k, v in tiny_model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k


def test_a_name_with_a_dot_gets_the_suffix_appended_so_two_steps_stay_two_files(tmp_path, tiny_model):
    a = pm.save_model(tiny_model, tmp_path / "run.step1000")
    b = pm.save_model(tiny_model, tmp_path / "run.step2000", provenance={"lr": np.float32(1e-4), "data": tmp_path})
    assert (a.name, b.name) == ("run.step1000.safetensors", "run.step2000.safetensors") and a.exists()
    assert pm.load_model(b).provenance == {"lr": pytest.approx(1e-4), "data": str(tmp_path)}


def test_half_precision_files_load_back_as_float32_within_half_precision_error(tmp_path, tiny_model):
    path = pm.save_model(tiny_model, tmp_path / "m16.safetensors", dtype=torch.float16)
    loaded = pm.load_model(path)
    w = loaded.state_dict()["enc_norm.weight"]
    assert w.dtype == torch.float32
    assert torch.allclose(w, tiny_model.state_dict()["enc_norm.weight"], atol=1e-2)


def test_int8_quantization_agrees_with_a_channel_by_channel_reference():
    from pointmap.checkpoint import dequantize_int8, quantize_int8

    w = torch.randn(6, 5, 3) * torch.tensor([1e-3, 0.1, 1.0, 10.0, 0.0, 2.0])[:, None, None]
    q, scale = quantize_int8(w)
    for c in range(6):  # the reference: one channel at a time, in Python numbers
        m = max(abs(float(x)) for x in w[c].flatten())
        s = max(m, 1e-12) / 127.0
        assert math.isclose(float(scale[c]), s, rel_tol=1e-6)
        for x, qx in zip(w[c].flatten().tolist(), q[c].flatten().tolist()):
            assert qx == max(-127, min(127, round(x / s)))
    back = dequantize_int8(q, scale)
    assert q.dtype == torch.int8 and back.shape == w.shape
    assert ((back - w).abs() <= scale[:, None, None] / 2 + 1e-9).all()


def test_int8_files_hold_weight_matrices_in_int8_and_load_back_within_half_a_step(tmp_path, tiny_model):
    from safetensors import safe_open

    from pointmap.checkpoint import SCALE_SUFFIX, quantize_int8

    path = pm.save_model(tiny_model, tmp_path / "m8.safetensors", dtype="int8")
    with safe_open(str(path), framework="pt") as f:
        quantized = json.loads(f.metadata()["int8"])
        stored = {k: f.get_tensor(k) for k in f.keys()}
    assert "enc_blocks.0.mlp.fc1.weight" in quantized
    assert all(stored[k].dtype == torch.int8 for k in quantized)
    assert stored["enc_norm.weight"].dtype == torch.float16  # small tensors stay fp16
    loaded = pm.load_model(path)
    for k, v in tiny_model.state_dict().items():
        got = loaded.state_dict()[k]
        assert got.dtype == v.dtype, k
        if k in quantized:
            step = quantize_int8(v)[1].reshape(-1, *[1] * (v.ndim - 1))
            assert ((got - v).abs() <= step / 2 + 1e-7).all(), k
            assert torch.equal(stored[k + SCALE_SUFFIX], quantize_int8(v)[1]), k
        elif v.is_floating_point():
            torch.testing.assert_close(got, v.half().float(), rtol=0, atol=0)
    x = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        a, b = tiny_model.eval()(x, x), loaded(x, x)
    assert torch.allclose(a.pts1_cam1, b.pts1_cam1, rtol=0.05, atol=0.05)


def test_int8_files_whose_tensors_or_list_do_not_match_are_refused_in_one_line(tmp_path, tiny_model):
    from safetensors import safe_open
    from safetensors.torch import save_file

    path = pm.save_model(tiny_model, tmp_path / "m8.safetensors", dtype="int8")
    with safe_open(str(path), framework="pt") as f:
        meta, state = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    listed = json.loads(meta["int8"])
    k, sk = listed[0], listed[0] + ":int8_scale"

    def changed(**tensors):
        return {**state, **tensors}

    # without the checksum, so that each int8 check itself answers (the checksum refuses every changed tensor first;
    # and this test's folder name holds "int8", so each message is matched after the file name)
    summed, meta = meta, {a: b for a, b in meta.items() if a != "sha256"}
    q, listed_k, bad_k = f"'{k}'", re.escape(str([k])), re.escape(str([k, sk]))
    cases = {"missing scale": ({n: v for n, v in state.items() if n != sk}, meta,
                               f"int8 tensor {q} expected in the file with its scale .*missing: the scale"),
             "unlisted int8": (state, {**meta, "int8": json.dumps(listed[1:])},
                               f"int8 tensors or scales not listed in its metadata: {bad_k}"),
             "unlisted int8 without its scale": ({n: v for n, v in state.items() if n != sk},
                                                 {**meta, "int8": json.dumps(listed[1:])},
                                                 f"int8 tensors or scales not listed in its metadata: {listed_k}"),
             "broken list": (state, {**meta, "int8": "[not json"}, "has a broken int8 tensor list"),
             "not a list": (state, {**meta, "int8": json.dumps({"a": 1})},
                            "int8 metadata expected a list of tensor names, got dict"),
             "repeated name": (state, {**meta, "int8": json.dumps(listed + [k])},
                               f"int8 metadata expected distinct weight names, got repeated or scale names {listed_k}"),
             "scale listed": (state, {**meta, "int8": json.dumps(listed + [sk])},
                              "int8 metadata expected distinct weight names, got repeated or scale names"),
             "float tensor listed": (changed(**{k: state[k].float()}), meta,
                                     "expected a non-empty int8 tensor, got torch.float32"),
             "int8 scale": (changed(**{sk: state[sk].to(torch.int8)}), meta,
                            r"expected a float32 scale of shape \[\d+\], got torch.int8"),
             "short scale": (changed(**{sk: state[sk][:-1]}), meta,
                             r"expected a float32 scale of shape \[\d+\], got torch.float32"),
             "NaN scale": (changed(**{sk: torch.full_like(state[sk], float("nan"))}), meta,
                           "expected finite positive scales"),
             "negative scale": (changed(**{sk: -state[sk]}), meta, "expected finite positive scales"),
             "0-dim tensor": (changed(**{k: torch.tensor(3, dtype=torch.int8)}), meta,
                              r"expected a non-empty int8 tensor, got torch.int8 \(\)"),
             "checksum": (changed(**{sk: -state[sk]}), summed, "do not match the checksum in its header")}
    for name, (tensors, md, message) in cases.items():
        save_file(tensors, str(tmp_path / "bad.safetensors"), metadata=md)
        with pytest.raises(pm.CheckpointError, match="bad.safetensors.*" + message) as e:
            pm.load_model(tmp_path / "bad.safetensors")
        assert "\n" not in str(e.value), name
    save_file(state, str(tmp_path / "bad.safetensors"), metadata={**meta, "provenance": "{broken"})
    with pytest.raises(pm.CheckpointError, match="provenance"):
        pm.load_model(tmp_path / "bad.safetensors")


def test_saving_refuses_an_unknown_dtype_and_weights_int8_cannot_hold(tmp_path, tiny_model):
    from pointmap.checkpoint import quantize_int8

    with pytest.raises(ValueError, match="dtype expected"):
        pm.save_model(tiny_model, tmp_path / "x.safetensors", dtype=torch.int8)
    with torch.no_grad():
        tiny_model.enc_blocks[0].mlp.fc1.weight[3, 5] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        pm.save_model(tiny_model, tmp_path / "x.safetensors", dtype="int8")
    assert not (tmp_path / "x.safetensors").exists()
    for bad in (torch.tensor(1.0), torch.zeros(0, 3), torch.ones(3, 3, dtype=torch.int64)):
        with pytest.raises(ValueError, match="expected a non-empty floating tensor"):
            quantize_int8(bad)


def test_a_safetensors_file_from_another_project_is_refused(tmp_path):
    from safetensors.torch import save_file

    save_file({"w": torch.zeros(2)}, str(tmp_path / "other.safetensors"))
    with pytest.raises(pm.CheckpointError, match="not a pointmap checkpoint"):
        pm.load_model(tmp_path / "other.safetensors")


def test_unknown_names_list_what_is_shipped_and_an_empty_name_is_no_working_directory():
    with pytest.raises(pm.CheckpointError, match="no such file or shipped model"):
        pm.load_model("nonexistent_model_name")
    for empty in ("", "  "):  # not the working directory, which Path("") would be
        with pytest.raises(pm.CheckpointError, match=f"a checkpoint path or a PointmapNet, got {empty!r}"):
            pm.load_model(empty)


def test_a_folder_named_like_a_shipped_model_does_not_hide_it_and_a_model_on_disk_so_named_is_read_with_a_warning(
        tmp_path, monkeypatch):
    import warnings

    from pointmap.checkpoint import WEIGHTS_DIR

    name = pm.checkpoint.shipped_models()[0]
    monkeypatch.chdir(tmp_path)
    (tmp_path / name).mkdir()  # a folder of photographs, say: the shipped model, without a word
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert isinstance(pm.load_model(name), pm.PointmapNet)
    (tmp_path / name / "model.onnx").write_bytes(b"not really")  # now an export of that name: read, and said
    with pytest.warns(UserWarning, match=f"'{name}' is a shipped model's name and a model folder in the working "
                                         f"directory: loading the one on disk; the shipped one is "
                                         f"{re.escape(str(WEIGHTS_DIR))}"):
        with pytest.raises(pm.CheckpointError, match="cannot read"):
            pm.load_model(name)
    with pytest.raises(pm.CheckpointError, match="cannot read"), warnings.catch_warnings():
        warnings.simplefilter("error")  # written as a path: no warning
        pm.load_model(f".{os.sep}{name}")


def test_every_shipped_model_fits_the_package_budget_of_25_mb_and_records_its_steps_data_and_licence():
    from pointmap.checkpoint import WEIGHTS_DIR

    assert pm.checkpoint.shipped_models()
    for name in pm.checkpoint.shipped_models():
        assert (WEIGHTS_DIR / f"{name}.safetensors").stat().st_size <= 25_000_000, name
        prov = pm.load_model(name).provenance
        assert prov.get("steps", 0) > 0 and prov.get("data"), (name, sorted(prov))
        assert prov.get("licence") == "Apache-2.0", name  # trained here from scratch: the project's licence


@pytest.mark.parametrize("change,named", [({"enc_heads": 0}, "enc_heads=0"), ({"enc_dim": "abc"}, "enc_dim='abc'"),
                                          ({"dec_depth": -1}, "dec_depth=-1"),
                                          ({"mlp_ratio": float("inf")}, "mlp_ratio=inf"),
                                          ({"conf_mode": ["exp", "abc", "inf"]}, "conf_mode expected"),
                                          ({"conf_mode": ["exp", 3, 1]}, "conf_mode expected"),
                                          ({"conf_mode": ["linear", 1, "inf"]}, "conf_mode expected"),
                                          ({"depth_mode": ["exp", 0, 1]}, "no bounds"),
                                          ({"depth_mode": ["sigmoid", "-inf", "inf"]}, "depth_mode expected"),
                                          ({"head": ["dpt"]}, "head expected one of .*got \\('dpt',\\)")])
def test_a_safetensors_file_whose_config_has_impossible_sizes_is_refused_naming_them(tmp_path, tiny_model, change,
                                                                                      named):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    from pointmap.checkpoint import save_model

    good = save_model(tiny_model, tmp_path / "good.safetensors")
    with safe_open(str(good), "pt") as f:
        meta = f.metadata()
    meta["config"] = json.dumps({**json.loads(meta["config"]), **change})
    save_file(load_file(str(good)), str(tmp_path / "bad.safetensors"), metadata=meta)
    with pytest.raises(pm.CheckpointError, match=f"invalid model config: .*{named}"):
        pm.load_model(tmp_path / "bad.safetensors")


def test_an_official_constructor_with_a_malformed_number_is_refused_as_a_checkpoint_error():
    with pytest.raises(pm.CheckpointError, match="malformed .*could not convert string to float: 'a'"):
        config_from_ctor(TINY_CTOR.replace("dec_num_heads=2", "dec_num_heads=2, mlp_ratio='a'"))
    with pytest.raises(pm.CheckpointError, match="pts3d\\+descN with N a number"):
        config_from_ctor(TINY_CTOR.replace("pts3d+desc8", "pts3d+descX"))
    for bad in ("enc_depth=2.7", "enc_depth=True", "two_confs='no'"):  # truncated or read as truthy before
        key = bad.split("=")[0]
        ctor = re.sub(rf"{key}=[^,)]+", bad, TINY_CTOR) if f"{key}=" in TINY_CTOR else TINY_CTOR.replace(
            "dec_num_heads=2", f"dec_num_heads=2, {bad}")
        with pytest.raises(pm.CheckpointError, match=f"{key} expected"):
            config_from_ctor(ctor)


@pytest.mark.parametrize("src", [None, 123, 1.5])
def test_load_model_refuses_what_is_neither_a_name_nor_a_path_nor_a_model(src):
    with pytest.raises(pm.CheckpointError, match="expected a shipped model's name .*got "):
        pm.load_model(src)


def test_load_model_refuses_onnx_only_options_for_a_pytorch_model_instead_of_dropping_them(tmp_path):
    model = pm.PointmapNet(pm.PRESETS["test"])
    pm.save_model(model, tmp_path / "m.safetensors")
    for src in (model, tmp_path / "m.safetensors"):
        with pytest.raises(TypeError, match=r"load_model got \['providers', 'threads'\], which only an ONNX export"):
            pm.load_model(src, providers=["cuda"], threads=4)
    assert isinstance(pm.load_model(tmp_path / "m.safetensors"), pm.PointmapNet)


def test_save_model_refuses_what_is_not_a_model_a_path_or_a_provenance_and_weights_that_diverged(tmp_path):
    model = pm.PointmapNet(pm.PRESETS["test"])
    for args, kw, named in (((None, tmp_path / "m"), {}, "expected a PointmapNet, got NoneType"),
                            ((model, tmp_path), {}, "expected a file path, got the folder"),
                            ((model, tmp_path / "m"), {"provenance": "abc"}, "provenance expected a dict, got str"),
                            ((model, tmp_path / "m"), {"dtype": "fp16"}, "dtype expected None, torch.float16"),
                            ((model, tmp_path / "m"), {"provenance": {"when": object()}},
                             "provenance expected JSON values .*got object"),
                            ((model, tmp_path / "m"), {"provenance": {"image_size": 224.0}},
                             "provenance's image_size expected a positive int .*got 224.0")):
        with pytest.raises(ValueError, match=named):
            pm.save_model(*args, **kw)
    assert not list(tmp_path.iterdir())  # nothing written
    with torch.no_grad():
        next(model.parameters()).fill_(float("nan"))
    with pytest.raises(ValueError, match=r"is not finite \(NaN or inf values\): a model that diverged is not saved"):
        pm.save_model(model, tmp_path / "nan")
    model = pm.PointmapNet(pm.PRESETS["test"])
    with torch.no_grad():
        model.downstream_head1.dpt.head[-1].bias[0] = 7e4  # finite in float32, inf in float16
    for dtype in (torch.float16, "int8"):
        with pytest.raises(ValueError, match="downstream_head1.dpt.head.4.bias holds values beyond float16's range"):
            pm.save_model(model, tmp_path / "big", dtype=dtype)
    assert not (tmp_path / "big.safetensors").exists()
    pm.load_model(pm.save_model(model, tmp_path / "big"))  # float32 keeps it


def test_a_file_whose_weights_are_nan_is_refused_on_loading(tmp_path):
    from safetensors.torch import load_file, save_file

    from pointmap.errors import CheckpointError

    path = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "m.safetensors")
    from safetensors import safe_open

    with safe_open(str(path), "pt") as f:
        meta = f.metadata()
    tensors = load_file(str(path))
    name = next(k for k, v in tensors.items() if v.is_floating_point())
    tensors[name] = torch.full_like(tensors[name], float("nan"))
    meta.pop("sha256")  # a file written before files carried a checksum: the finiteness check is its guard
    save_file(tensors, str(path), metadata=meta)
    with pytest.raises(CheckpointError, match=rf"holds NaN or inf weights \(e.g. \['{name}'\]\)"):
        pm.load_model(path)


def test_official_weights_that_are_nan_or_not_named_tensors_and_our_training_checkpoints_are_refused_by_name(tmp_path):
    model, path = tiny_official(tmp_path)
    ckpt = torch.load(path, weights_only=False)
    name = next(k for k, v in ckpt["model"].items() if v.is_floating_point() and k != "mask_token")
    for bad, message in ((dict(ckpt["model"], **{name: torch.full_like(ckpt["model"][name], float("inf"))}),
                          rf"holds NaN or inf weights \(e.g. \['{name}'\]\)"),
                         ([1, 2], "expected a dict of named tensors, got list"),
                         (torch.zeros(3), "expected a dict of named tensors, got Tensor"),
                         ({"enc_norm.weight": 3}, "expected a dict of named tensors, got 'enc_norm.weight': int")):
        torch.save(dict(ckpt, model=bad), tmp_path / "bad.pth")
        with pytest.raises(pm.CheckpointError, match=message):
            pm.load_model(tmp_path / "bad.pth")
    torch.save({"model": model.state_dict(), "model_config": model.cfg.to_dict(), "step": 100}, tmp_path / "last.pt")
    with pytest.raises(pm.CheckpointError, match="is a pointmap training checkpoint .*python -m training.ship --ckpt"):
        pm.load_model(tmp_path / "last.pt")
    with pytest.raises(pm.CheckpointError, match="constructor arguments are missing or malformed"):
        config_from_ctor(TINY_CTOR.replace("conf_mode=('exp', 1, inf)", "conf_mode=5"))


@pytest.mark.parametrize("provenance", ['"hello"', "[1]", '{"image_size": "512x384"}', '{"image_size": -3}'])
def test_a_safetensors_file_whose_provenance_is_not_an_object_with_a_positive_image_size_is_refused(
        tmp_path, tiny_model, provenance):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    path = pm.save_model(tiny_model, tmp_path / "m.safetensors")
    with safe_open(str(path), "pt") as f:
        meta = f.metadata()
    save_file(load_file(str(path)), str(path), metadata=dict(meta, provenance=provenance))
    with pytest.raises(pm.CheckpointError, match="broken provenance metadata: expected a JSON object"):
        pm.load_model(path)


def test_an_official_state_dict_with_a_malformed_layer_rn_alias_is_a_checkpoint_error():
    from pointmap.checkpoint import official_to_ours

    w = torch.zeros(2)
    for key in ("downstream_head1.dpt.scratch.layer_rn.weight", "downstream_head1.dpt.scratch.layer_rn.x.weight"):
        with pytest.raises(pm.CheckpointError, match="layer_rn alias expected"):
            official_to_ours({key: w})
    ok = official_to_ours({"downstream_head1.dpt.scratch.layer_rn.0.weight": w})
    assert list(ok) == ["downstream_head1.dpt.scratch.layer1_rn.weight"]


def test_a_croco_pretraining_checkpoint_is_refused_as_a_model_and_starts_training_with_its_trunk(tmp_path):
    from pointmap.model.pretrain import CrossViewCompletion
    from training.config import TrainConfig
    from training.train import build_model

    cfg = pm.PRESETS["test"].replace(head="linear", desc_dim=0)
    croco = CrossViewCompletion(cfg)
    kw = dict(enc_embed_dim=cfg.enc_dim, enc_depth=cfg.enc_depth, enc_num_heads=cfg.enc_heads,
              dec_embed_dim=cfg.dec_dim, dec_depth=cfg.dec_depth, dec_num_heads=cfg.dec_heads, pos_embed="RoPE100",
              img_size=224)
    torch.save({"model": croco.state_dict(), "croco_kwargs": kw}, tmp_path / "croco.pth")
    with pytest.raises(pm.CheckpointError, match="CroCo pretraining checkpoint .* its heads would be random"):
        pm.load_model(tmp_path / "croco.pth")
    with pytest.warns(UserWarning, match="CC-BY-NC-SA"):
        model = build_model(TrainConfig(data="x", preset="test", init=str(tmp_path / "croco.pth")))
    own = croco.state_dict()
    assert torch.equal(model.state_dict()["enc_blocks.0.attn.qkv.weight"], own["enc_blocks.0.attn.qkv.weight"])


def test_a_model_file_whose_tensors_changed_after_saving_is_refused_and_one_without_a_checksum_loads(tmp_path):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    path = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "m.safetensors", dtype="int8")
    with safe_open(str(path), "pt") as f:
        meta = f.metadata()
    tensors = load_file(str(path))
    name = next(k for k, v in tensors.items() if k.endswith("norm1.weight"))  # fp16 ones
    tensors[name] = tensors[name].clone()
    tensors[name].view(-1)[: tensors[name].numel() // 2] = 0  # half of one tensor lost, every value finite
    save_file(tensors, str(tmp_path / "bad.safetensors"), metadata=meta)
    with pytest.raises(pm.CheckpointError, match="do not match the checksum in its header \\(corrupted\\)"):
        pm.load_model(tmp_path / "bad.safetensors")
    save_file(tensors, str(tmp_path / "old.safetensors"), metadata={k: v for k, v in meta.items() if k != "sha256"})
    pm.load_model(tmp_path / "old.safetensors")  # written before files carried a checksum: loads as before


def test_a_config_of_impossible_size_is_refused_before_the_network_is_allocated(tmp_path):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    good = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "m.safetensors")
    with safe_open(str(good), "pt") as f:
        meta = f.metadata()
    cfg = json.loads(meta["config"])
    meta = {**meta, "config": json.dumps({**cfg, "enc_dim": 2**24, "enc_heads": 2**20})}
    meta.pop("sha256")
    save_file(load_file(str(good)), str(tmp_path / "huge.safetensors"), metadata=meta)
    with pytest.raises(pm.CheckpointError, match="does not match the architecture: .*shape mismatches"):
        pm.load_model(tmp_path / "huge.safetensors")  # 50 GB asked of the allocator before


@pytest.mark.parametrize("change,named", [
    ({"enc_dim": 2**40}, "its config builds no model \\(RuntimeError"),  # too large to index, even on meta
    ({"enc_dim": 10**30}, "its config builds no model \\((TypeError|OverflowError|RuntimeError)"),
    ({"enc_depth": 10**6}, "its config says 1000000 enc_blocks, its weights hold"),  # not built block by block
    ({"dec_depth": 20}, "its config says 20 dec_blocks, its weights hold"),
])
def test_a_config_too_large_to_build_or_with_other_block_counts_is_a_checkpoint_error(tmp_path, change, named):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    good = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "m.safetensors")
    with safe_open(str(good), "pt") as f:
        meta = f.metadata()
    meta = {**meta, "config": json.dumps({**json.loads(meta["config"]), **change})}
    meta.pop("sha256")
    save_file(load_file(str(good)), str(tmp_path / "bad.safetensors"), metadata=meta)
    with pytest.raises(pm.CheckpointError, match=named):
        pm.load_model(tmp_path / "bad.safetensors")


def test_disagreeing_layer_rn_aliases_are_refused_also_in_a_state_dict_saved_with_a_module_prefix():
    from pointmap.checkpoint import official_to_ours

    w = torch.zeros(2)
    state = {"module.downstream_head1.dpt.scratch.layer1_rn.weight": w,
             "module.downstream_head1.dpt.scratch.layer_rn.0.weight": w + 1}
    with pytest.raises(pm.CheckpointError, match="hold different values"):
        official_to_ours(state)
    same = official_to_ours({k: w for k in state})
    assert list(same) == ["downstream_head1.dpt.scratch.layer1_rn.weight"]


def test_an_official_checkpoint_without_its_second_decoder_is_refused_not_given_a_copy_of_the_first(tmp_path):
    _, path = tiny_official(tmp_path)
    with torch.serialization.safe_globals([argparse.Namespace]):
        ck = torch.load(path, weights_only=True)
    ck["model"] = {k: v for k, v in ck["model"].items() if not k.startswith("dec_blocks2.")}
    torch.save(ck, tmp_path / "no_dec2.pth")
    with pytest.raises(pm.CheckpointError, match=r"no second decoder \(dec_blocks2"):
        pm.load_model(tmp_path / "no_dec2.pth")
