"""ONNX export: graph structure, sidecar, parity against PyTorch eager, CLI and atomic writing."""

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

import pointmap as pm
from export import PARITY_CASES, check_parity, export_model, resolve_model
from export.__main__ import main
from export.exporter import DEFAULT_OPSET, _atomic_publish, check_target
from export.parity import RTOL, compare, random_pair
from pointmap.errors import CheckpointError
from pointmap.model import PRESETS
from pointmap.runtime.onnx import FORMAT, METADATA_KEY, SIDECAR, OnnxPointmapModel

STD_OPS = {"", "ai.onnx"}


def _dims(value_info):
    return [d.dim_param or d.dim_value for d in value_info.type.tensor_type.shape.dim]


def test_full_export_graph_is_plain_onnx_with_dynamic_shapes(full_export):
    proto = onnx.load(str(full_export / "model.onnx"))
    onnx.checker.check_model(proto)
    ops = {(n.domain, n.op_type) for n in proto.graph.node}
    assert all(domain in STD_OPS for domain, _ in ops), f"custom-domain ops: {ops}"
    types = {op for _, op in ops}
    assert {"Cos", "Sin", "Range"} <= types  # RoPE tables built in the graph from the grid size
    assert not types & {"DFT", "STFT"}  # no complex arithmetic
    inputs = {i.name: _dims(i) for i in proto.graph.input}
    outputs = {o.name: _dims(o) for o in proto.graph.output}
    assert inputs == {"img1": ["batch", 3, "height1", "width1"], "img2": ["batch", 3, "height2", "width2"]}
    assert list(outputs) == ["pts1_cam1", "pts2_cam1", "conf1", "conf2", "desc1", "desc2", "desc_conf1", "desc_conf2"]
    assert outputs["pts2_cam1"] == ["batch", "height2", "width2", 3]
    assert outputs["desc1"] == ["batch", "height1", "width1", PRESETS["test"].desc_dim]
    # int8 quantisation needs the weights of every MatMul as initializers (no Transpose left on them)
    inits = {i.name for i in proto.graph.initializer}
    producers = {o: n for n in proto.graph.node for o in n.output}
    for n in proto.graph.node:
        if n.op_type == "Transpose":
            assert n.input[0] not in inits, f"unfolded weight transpose {n.input[0]}"
    assert sum(n.op_type == "MatMul" and n.input[1] in inits for n in proto.graph.node) > 0
    assert producers  # sanity


def test_sidecar_describes_the_export(full_export):
    meta = json.loads((full_export / SIDECAR).read_text())
    assert meta["format"] == FORMAT and meta["split"] is False and meta["precision"] == "fp32"
    assert pm.ModelConfig.from_dict(meta["architecture"]) == PRESETS["test"]
    assert meta["preprocessing"]["mean"] == [0.5, 0.5, 0.5] and meta["preprocessing"]["patch_size"] == 16
    assert meta["graphs"]["full"]["inputs"]["img1"] == ["batch", 3, "height1", "width1"]
    assert meta["provenance"]["source"] == "preset:test" and "torch" in meta["provenance"]["versions"]
    assert meta["parity"]["passed"] and meta["parity"]["cases"][0]["worst_ratio"] <= 1
    # the same description travels inside the graph
    proto = onnx.load(str(full_export / "model.onnx"), load_external_data=False)
    embedded = json.loads({p.key: p.value for p in proto.metadata_props}[METADATA_KEY])
    assert embedded["architecture"] == meta["architecture"]


def test_a_split_export_is_an_encoder_graph_and_a_decoder_graph_with_dynamic_sizes(split_export):
    enc = onnx.load(str(split_export / "encoder.onnx"), load_external_data=False)
    dec = onnx.load(str(split_export / "decoder.onnx"), load_external_data=False)
    C = PRESETS["test"].enc_dim
    assert {i.name: _dims(i) for i in enc.graph.input} == {"img": ["batch", 3, "height", "width"]}
    assert {o.name: _dims(o) for o in enc.graph.output} == {"tokens": ["batch", "grid_h", "grid_w", C]}
    assert [i.name for i in dec.graph.input] == ["tokens1", "tokens2"]
    assert _dims(dec.graph.input[1]) == ["batch", "grid_h2", "grid_w2", C]
    assert not (split_export / "model.onnx").exists()


@pytest.mark.parametrize("kind", ["full", "split"])
def test_parity_with_eager_on_all_resolutions_and_batches(kind, full_export, split_export, test_model):
    """224x224, 512x384, 384x512 at batch 1 and 3, plus a portrait/landscape pair: fp32 tolerance."""
    runner = pm.load_model(full_export if kind == "full" else split_export)
    assert isinstance(runner, OnnxPointmapModel) and runner.split == (kind == "split")
    report = check_parity(test_model, runner, PARITY_CASES["full"])
    assert len(report["cases"]) == 7
    for case in report["cases"]:
        assert case["finite"], case["case"]
        assert case["worst_ratio"] <= 1, f"{case['case']}: {case['worst_output']} ratio {case['worst_ratio']}"
        for name, o in case["outputs"].items():
            assert o["max_abs_diff"] <= o["tol"], (case["case"], name)
    assert report["passed"]


def test_parity_compare_catches_a_difference(test_model):
    img1, img2 = random_pair(64, 96, 64, 96, 1)
    with torch.inference_mode():
        ref = test_model(img1, img2)
    bad = ref.map(lambda t: t.clone())
    bad.conf2[0, 3, 4] += 1.0
    res = compare(ref, bad)
    assert res["worst_output"] == "conf2" and res["worst_ratio"] > 1
    assert res["outputs"]["conf2"]["tol"] == pytest.approx(RTOL * (1 + float(ref.conf2.abs().max())))
    bad.pts1_cam1[0, 0, 0, 0] = float("nan")
    assert not compare(ref, bad)["finite"]
    nan_ref = ref.map(lambda t: t.clone())  # a NaN in the PyTorch output is no pass either
    nan_ref.conf2[0, 0, 0] = float("nan")
    res = compare(nan_ref, ref)
    assert not res["finite"] and res["worst_output"] == "conf2" and res["worst_ratio"] == float("inf")
    assert res["outputs"]["pts1_cam1"]["ratio"] == 0.0  # outputs other than the bad one keep their own figures


def test_export_leaves_the_callers_model_as_it_was_and_keeps_its_licence(tmp_path, monkeypatch):
    import export.exporter as ex

    model = pm.PointmapNet(PRESETS["test"]).half().train()
    model.provenance = {"source": "official", "licence": "CC-BY-NC-SA-4.0"}
    seen = {}

    def no_graphs(m, tmp, **kw):
        seen["model"] = m
        raise CheckpointError("stop here")

    monkeypatch.setattr(ex, "export_graphs", no_graphs)
    with pytest.raises(CheckpointError, match="stop here"):
        export_model(model, tmp_path / "a", parity="none")
    assert model.training and next(model.parameters()).dtype == torch.float16  # not turned to eval / float32
    assert seen["model"] is not model and not seen["model"].training
    from pointmap.checkpoint import provenance_keeping_licence

    assert provenance_keeping_licence(model, {"note": "mine"}) == {"note": "mine", "licence": "CC-BY-NC-SA-4.0"}
    assert provenance_keeping_licence(model)["source"] == "official"


def test_a_weight_read_by_two_transposes_is_folded_once():
    import onnx_ir as ir
    from onnx import TensorProto, helper, numpy_helper

    from export.exporter import fold_weight_transposes

    W = numpy_helper.from_array(np.arange(12, dtype=np.float32).reshape(4, 3), "W")
    nodes = [helper.make_node("Transpose", ["W"], ["Wt1"], perm=[1, 0]),
             helper.make_node("Transpose", ["W"], ["Wt2"], perm=[1, 0]),
             helper.make_node("MatMul", ["x", "Wt1"], ["y1"]), helper.make_node("MatMul", ["x", "Wt2"], ["y2"])]
    out = [helper.make_tensor_value_info(n, TensorProto.FLOAT, [2, 4]) for n in ("y1", "y2")]
    g = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 3])], out, [W])
    m = ir.serde.deserialize_model(helper.make_model(g, opset_imports=[helper.make_opsetid("", 18)]))
    assert fold_weight_transposes(m) == 2
    proto = ir.serde.serialize_model(m)
    onnx.checker.check_model(proto)
    inits = {i.name: numpy_helper.to_array(i) for i in proto.graph.initializer}
    assert list(inits) == ["W.T"] and np.array_equal(inits["W.T"], np.arange(12).reshape(4, 3).T)
    assert [n.op_type for n in proto.graph.node] == ["MatMul", "MatMul"]


def test_export_rejects_bad_arguments(tmp_path, test_model):
    with pytest.raises(ValueError, match="fp16 and quantize"):
        export_model(test_model, tmp_path / "a", fp16=True, quantize="int8")
    with pytest.raises(ValueError, match="quantize"):
        export_model(test_model, tmp_path / "a", quantize="int4")
    with pytest.raises(ValueError, match="opset"):
        export_model(test_model, tmp_path / "a", opset=13)
    with pytest.raises(ValueError, match="opset expected an int from 18"):  # the exporter cannot convert down to 17
        export_model(test_model, tmp_path / "a", opset=17)
    with pytest.raises(ValueError, match="parity"):
        export_model(test_model, tmp_path / "a", parity="sometimes")
    with pytest.raises(CheckpointError, match="PointmapNet"):
        export_model(torch.nn.Linear(2, 2), tmp_path / "a")
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    with pytest.raises(CheckpointError, match="not a pointmap export"):
        export_model(test_model, foreign)
    assert (foreign / "notes.txt").read_text() == "keep me"
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no temp dir left behind


def test_a_preset_resolves_to_seeded_random_weights_and_unknown_or_missing_models_are_refused(tmp_path):
    m = resolve_model("preset:test", seed=3)
    assert m.cfg == PRESETS["test"] and "random" in m.provenance["weights"]
    m2 = resolve_model("preset:test", seed=3)
    assert torch.equal(m.patch_embed.proj.weight, m2.patch_embed.proj.weight)
    with pytest.raises(CheckpointError, match="unknown preset"):
        resolve_model("preset:nope")
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        resolve_model(str(tmp_path / "missing.pth"))


def test_cli_exit_code_2_on_bad_input(tmp_path, capsys):
    assert main(["--model", "preset:nope", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: unknown preset")


def test_cli_checks_the_output_folder_and_opset_before_it_loads_the_model(tmp_path, capsys, monkeypatch):
    import export

    assert main(["--model", "preset:test", "--out", str(tmp_path / "new"), "--seed", "99999999999999999999"]) == 2
    assert "seed expected an int in [0, 2**64), got 99999999999999999999" in capsys.readouterr().err
    monkeypatch.setattr(export, "resolve_model", lambda *a, **k: pytest.fail("the model loaded first"))
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    for extra, message in ((["--out", str(tmp_path / "full")], "exists and is not a pointmap export"),
                           (["--out", str(tmp_path / "new"), "--opset", "16"], "opset expected an int from 18"),
                           (["--out", str(tmp_path / "new"), "--seed", "3"],  # ignored before, without a word
                            "--seed seeds the random weights of a preset:NAME model; some/huge.pth has its own")):
        assert main(["--model", "some/huge.pth", *extra]) == 2
        assert message in capsys.readouterr().err


def test_atomic_publish_replaces_only_exports(tmp_path):
    out = tmp_path / "exp"
    out.mkdir()
    (out / SIDECAR).write_text("{}")
    (out / "old.onnx").write_text("old")
    tmp = tmp_path / ".exp.tmp"
    tmp.mkdir()
    (tmp / SIDECAR).write_text("{}")
    (tmp / "model.onnx").write_text("new")
    _atomic_publish(tmp, out)
    assert sorted(p.name for p in out.iterdir()) == sorted([SIDECAR, "model.onnx"])
    assert not tmp.exists() and [p.name for p in tmp_path.iterdir()] == ["exp"]
    other = tmp_path / "other"
    other.mkdir()
    (other / "x").write_text("x")
    tmp.mkdir()
    with pytest.raises(CheckpointError):
        _atomic_publish(tmp, other)
    assert (other / "x").exists()
    # an export that also holds a user's files: they were deleted with it
    (out / "NOTES.md").write_text("mine")
    (tmp / "model.onnx").write_text("newer")
    with pytest.raises(CheckpointError, match=r"also holds \['NOTES.md'\], which replacing it would delete"):
        _atomic_publish(tmp, out)
    assert (out / "NOTES.md").read_text() == "mine" and (out / "model.onnx").read_text() == "new"
    with pytest.raises(CheckpointError, match="also holds"):
        check_target(out, DEFAULT_OPSET)  # said before minutes of export
    (out / "NOTES.md").unlink()


@pytest.mark.parametrize("error", [OSError("disk gone"), KeyboardInterrupt("disk gone")])
def test_an_export_that_cannot_be_moved_in_or_is_interrupted_moving_in_puts_the_old_one_back(tmp_path, monkeypatch,
                                                                                            error):
    import os

    out, tmp = tmp_path / "exp", tmp_path / ".exp.tmp"
    for d, text in ((out, "old"), (tmp, "new")):
        d.mkdir()
        (d / SIDECAR).write_text("{}")
        (d / "model.onnx").write_text(text)
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: (_ for _ in ()).throw(error) if Path(a) == tmp else real(a, b))
    with pytest.raises(type(error), match="disk gone"):
        _atomic_publish(tmp, out)
    assert (out / "model.onnx").read_text() == "old"  # before, --out was gone and the old export hidden


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["int8", "fp16"])
def test_reduced_precision_exports_run_and_stay_close(kind, tmp_path, test_model):
    extra = ["--quantize", "int8"] if kind == "int8" else ["--fp16"]
    out = tmp_path / kind
    assert main(["--model", "preset:test", "--out", str(out), "--split", "--parity", "quick", "--quiet", *extra]) == 0
    meta = json.loads((out / SIDECAR).read_text())
    assert meta["precision"] == kind and meta["parity"]["passed"] and not meta["parity"]["strict"]
    ops = {n.op_type for f in ("encoder.onnx", "decoder.onnx") for n in onnx.load(str(out / f)).graph.node}
    if kind == "int8":
        assert "MatMulInteger" in ops or "DynamicQuantizeMatMul" in ops
    else:
        types = {i.data_type for f in ("encoder.onnx",) for i in onnx.load(str(out / f)).graph.initializer}
        assert onnx.TensorProto.FLOAT16 in types
    runner = pm.load_model(out)
    img1, img2 = random_pair(224, 224, 224, 224, 2)
    with torch.inference_mode():
        ref, got = test_model(img1, img2), runner(img1, img2)
    assert got.pts1_cam1.dtype == torch.float32
    rel = ((got.pts1_cam1 - ref.pts1_cam1).norm(dim=-1) / ref.pts1_cam1.norm(dim=-1)).median()
    assert float(rel) < (0.05 if kind == "int8" else 0.01)
    assert np.isfinite(got.conf2.numpy()).all()


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["dust3r_512_dpt", "mast3r_512"])
def test_official_size_exports_pass_parity(preset, tmp_path):
    """Official DPT and MASt3R architectures (random weights), split graphs, standard parity set."""
    model = resolve_model(f"preset:{preset}")
    meta = export_model(model, tmp_path / preset, split=True, parity="standard")
    assert meta["parity"]["passed"], meta["parity"]
    assert all(c["worst_ratio"] <= 1 for c in meta["parity"]["cases"])
    runner = pm.load_model(tmp_path / preset)
    assert runner.cfg == PRESETS[preset]


@pytest.fixture(scope="module")
def heads_export(tmp_path_factory):
    """(model, folder): one test-preset model with every optional head (pose, focal, descriptor stem), each moved off
    the neutral start it is initialised at so its path shows in the outputs, exported once as split graphs (the
    stem's local features must cross from the encoder graph to the decoder graph). One export instead of one per
    head: each takes 1-3 minutes on 2 cores."""
    torch.manual_seed(0)
    model = pm.PointmapNet(PRESETS["test"].replace(pose_head=True, focal_head=True, desc_stem=4)).eval()
    with torch.no_grad():
        model.pose_head.out.weight.normal_(0, 0.3)  # far from the identity it starts at
        model.focal_head.out.weight.normal_(0, 0.3)  # a correction that depends on the image
        for h in (model.downstream_head1, model.downstream_head2):
            h.dpt.head[4].bias[2] += 6.0  # points in front: a focal to start from
            h.desc_fuse.weight.normal_(0, 0.5)  # away from the zero-initialised fuse: the stem's path is exercised
    out = tmp_path_factory.mktemp("heads") / "export"
    export_model(model, out, split=True, parity="quick", quiet=True)
    return model, out


def test_a_model_with_pose_focal_and_stem_heads_exports_every_output_with_parity(heads_export):
    model, folder = heads_export
    runner = pm.load_model(folder)
    assert runner.split and runner.cfg == model.cfg
    report = check_parity(model, runner, [(64, 96, 96, 64, 2)])
    assert report["passed"], report["cases"]
    assert {"cam2_to_cam1", "focal1", "focal2", "desc1", "desc2"} <= set(report["cases"][0]["outputs"])
    img1, img2 = torch.rand(2, 3, 64, 96), torch.rand(2, 3, 96, 64)
    with torch.no_grad():
        want = model(img1, img2)
    got = runner(img1, img2)
    assert got.focal1.shape == (2,) and torch.allclose(got.focal1, want.focal1, rtol=1e-3)
    assert torch.allclose(got.focal2, want.focal2, rtol=1e-3)
    assert torch.allclose(got.cam2_to_cam1, want.cam2_to_cam1, atol=1e-4)


def test_an_export_from_before_the_pose_output_existed_predicts_without_it(heads_export, tmp_path):
    """Exports written before the pose head's transform was a graph output: their predictions come without it
    (relative_pose then uses the Procrustes of the pointmaps) instead of failing."""
    import shutil

    model, folder = heads_export
    old = shutil.copytree(folder, tmp_path / "old")
    meta = json.loads((old / "pointmap_export.json").read_text())
    del meta["files"]  # nor did their sidecars list the files' digests (session 93)
    (old / "pointmap_export.json").write_text(json.dumps(meta))
    graph = onnx.load(str(old / "decoder.onnx"))
    keep = [o for o in graph.graph.output if o.name != "cam2_to_cam1"]
    assert len(keep) == len(graph.graph.output) - 1
    del graph.graph.output[:]
    graph.graph.output.extend(keep)
    onnx.save(graph, str(old / "decoder.onnx"))
    img1, img2 = torch.rand(1, 3, 64, 96), torch.rand(1, 3, 96, 64)
    pred = pm.load_model(old)(img1, img2)
    with torch.no_grad():
        want = model(img1, img2)
    assert pred.cam2_to_cam1 is None and torch.allclose(pred.pts1_cam1, want.pts1_cam1, atol=1e-4)
    assert pred.focal1 is not None  # only the missing output is dropped


@pytest.mark.parametrize("extra, module", [(dict(pose_head=True), "pose_head.out"),
                                           (dict(pose_head=True, focal_head=True), "focal_head.out"),
                                           (dict(desc_stem=4), "downstream_head1.desc_fuse")])
def test_the_half_precision_graph_keeps_the_pose_and_focal_heads_and_the_descriptor_fuse_in_float32(extra, module):
    from export.graphs import FullGraph, half_backbone

    model = pm.PointmapNet(PRESETS["test"].replace(**extra)).eval()
    half = half_backbone(model)
    assert half.get_submodule(module).weight.dtype == torch.float32
    img = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        out = FullGraph(half, torch.float16)(img, img)
    assert all(torch.isfinite(o).all() for o in out)


def test_a_descriptor_stem_export_carries_its_local_features_between_the_graphs(heads_export):
    from pointmap.model.net import Encoded

    runner = pm.load_model(heads_export[1])
    assert runner.cfg.desc_stem == 4
    enc = runner.encode(torch.rand(1, 3, 32, 48))
    assert enc.local.shape == (1, 6, 4 * 16 * 16)
    with pytest.raises(pm.ShapeError, match="enc1.local expected the descriptor stem's local features"):
        runner.decode_pair(Encoded(enc.tokens, enc.grid), enc)


def test_cli_refuses_an_output_path_under_a_file_in_one_line(tmp_path, capsys):
    (tmp_path / "taken").write_text("x")
    assert main(["--model", "preset:test", "--out", str(tmp_path / "taken" / "sub"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --out expected a folder to write the export into")


def test_an_opset_beyond_onnx_an_unnamed_folder_and_a_symlinked_one_are_handled_before_the_export(tmp_path,
                                                                                                   monkeypatch):
    import onnx

    from export.exporter import check_target

    top = onnx.defs.onnx_opset_version()
    with pytest.raises(ValueError, match=f"opset expected an int from 18 .* to {top}"):
        check_target(tmp_path / "a", top + 1)
    monkeypatch.chdir(tmp_path)
    assert check_target(".", 18) == tmp_path.resolve()  # '.' has a name once resolved
    with pytest.raises(ValueError, match="empty path"):
        check_target("", 18)
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "link").symlink_to(real)
    assert check_target(tmp_path / "link", 18) == real.resolve()  # the target folder is what gets replaced


def test_a_provenance_with_paths_and_numpy_values_is_recorded_as_json_and_an_odd_patch_size_passes_parity(tmp_path):
    from pathlib import Path

    torch.manual_seed(0)
    model = pm.PointmapNet(PRESETS["test"].replace(head="linear", desc_dim=0, patch_size=14))
    model.provenance = {"source": Path("/data/ckpt.pth"), "image_size": np.int64(224)}
    meta = export_model(model, tmp_path / "odd")  # standard parity: 512 x 384 is no whole number of 14 px patches
    assert meta["parity"]["passed"]
    side = json.loads((tmp_path / "odd" / SIDECAR).read_text())
    assert side["provenance"]["source"] == "/data/ckpt.pth" and side["provenance"]["image_size"] == 224


def test_a_provenance_the_loader_would_refuse_is_refused_before_anything_is_exported(tmp_path):
    # before, image_size [384, 512] was exported (with parity "none", a folder that can never be loaded)
    model = pm.PointmapNet(PRESETS["test"])
    for parity in ("none", "quick"):
        with pytest.raises(pm.ShapeError, match=r"image_size expected a positive int .*got \[384, 512\]"):
            export_model(model, tmp_path / parity, provenance={"image_size": [384, 512]}, parity=parity)
        assert not (tmp_path / parity).exists() and not list(tmp_path.glob(".*"))
