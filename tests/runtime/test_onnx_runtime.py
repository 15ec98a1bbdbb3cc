"""The onnxruntime runner: PointmapNet's call contract, identical input checks, predict_pairs, load errors."""

import json
import warnings

import pytest
import torch

import pointmap as pm
from pointmap.errors import CheckpointError, ShapeError
from pointmap.model import PRESETS
from pointmap.model.net import Encoded
from pointmap.runtime.onnx import OnnxPointmapModel, load_onnx, resolve_providers


def _close(a: pm.PairPrediction, b: pm.PairPrediction):
    for name, r in a.as_dict().items():
        o = getattr(b, name)
        assert o is not None and o.shape == r.shape and o.dtype == torch.float32, name
        assert float((o - r).abs().max()) <= 1e-4 * (1 + float(r.abs().max())), name


def test_load_model_dispatches_to_onnx(split_export, full_export):
    for path in (split_export, split_export / "encoder.onnx", full_export, full_export / "model.onnx"):
        runner = pm.load_model(path)
        assert isinstance(runner, OnnxPointmapModel)
        assert runner.cfg == PRESETS["test"]
        assert runner.providers[0] == "CPUExecutionProvider"
    assert pm.load_model(split_export).split and not pm.load_model(full_export).split


@pytest.mark.parametrize("kind", ["full", "split"])
def test_calling_the_runner_gives_the_eager_models_outputs(kind, full_export, split_export, test_model):
    runner = load_onnx(full_export if kind == "full" else split_export, threads=1)
    assert runner.eval() is runner and runner.to("cpu") is runner
    img1, img2 = torch.rand(2, 3, 64, 96), torch.rand(2, 3, 96, 64)
    with torch.inference_mode():
        ref = test_model(img1, img2)
    got = runner(img1, img2)
    assert isinstance(got, pm.PairPrediction) and got.has_desc
    assert got.pts1_cam1.shape == (2, 64, 96, 3) and got.desc2.shape == (2, 96, 64, 8)
    _close(ref, got)
    assert float(got.conf1.min()) >= 1
    # float64 inputs are accepted like float32
    _close(ref, runner(img1.double(), img2.double()))


def test_encode_decode_pair_contract(split_export, test_model):
    runner = pm.load_model(split_export)
    img = torch.rand(3, 3, 48, 80)
    enc = runner.encode(img)
    ref_enc = test_model.encode(img)
    assert isinstance(enc, Encoded) and enc.grid == (3, 5) and enc.tokens.shape == ref_enc.tokens.shape
    assert float((enc.tokens - ref_enc.tokens.detach()).abs().max()) < 1e-4
    pred = runner.decode_pair(enc[0:2], enc[1:3])
    with torch.inference_mode():
        ref = test_model.decode_pair(ref_enc[0:2], ref_enc[1:3])
    _close(ref, pred)
    with pytest.raises(ShapeError, match="batch sizes differ"):
        runner.decode_pair(enc[0:1], enc[0:2])
    with pytest.raises(ShapeError, match="enc1 expected this model's encode\\(\\) output"):
        runner.decode_pair(Encoded(enc.tokens, (5, 3 + 1)), enc)


INVALID = [
    (lambda: torch.rand(3, 64, 64), lambda: torch.rand(1, 3, 64, 64)),           # missing batch dim
    (lambda: torch.rand(1, 3, 60, 64), lambda: torch.rand(1, 3, 64, 64)),        # not a multiple of 16
    (lambda: torch.rand(1, 1, 64, 64), lambda: torch.rand(1, 3, 64, 64)),        # one channel
    (lambda: torch.zeros(1, 3, 64, 64, dtype=torch.uint8), lambda: torch.rand(1, 3, 64, 64)),  # uint8
    (lambda: torch.rand(1, 3, 64, 64) * 255, lambda: torch.rand(1, 3, 64, 64)),  # [0, 255] range
    (lambda: torch.rand(1, 3, 64, 64), lambda: torch.full((1, 3, 64, 64), float("nan"))),  # NaN
    (lambda: torch.rand(2, 3, 64, 64), lambda: torch.rand(1, 3, 64, 64)),        # batch mismatch
    (lambda: torch.rand(1, 3, 0, 64), lambda: torch.rand(1, 3, 64, 64)),         # empty
    (lambda: [[0.5]], lambda: torch.rand(1, 3, 64, 64)),                          # not a tensor
]


def test_decode_pair_refuses_encoder_tokens_on_a_single_graph_export_and_tensors_anywhere(full_export, split_export,
                                                                                          test_model):
    img = torch.rand(1, 3, 32, 32)
    with torch.inference_mode():
        enc = test_model.encode(img)
    with pytest.raises(ShapeError, match="is a single-graph export: it decodes only its own encode\\(\\)'s outputs"):
        pm.load_model(full_export).decode_pair(enc, enc)
    for runner in (pm.load_model(split_export), test_model):  # the same message from both
        with pytest.raises(ShapeError, match="enc1 expected this model's encode\\(\\) output \\(an Encoded\\), got Tensor"):
            runner.decode_pair(img, img)


@pytest.mark.parametrize("make", INVALID)
def test_input_errors_identical_to_pytorch(make, split_export, test_model):
    runner = pm.load_model(split_export)
    a, b = make[0](), make[1]()
    with pytest.raises(ShapeError) as ours:
        runner(a, b)
    with pytest.raises(ShapeError) as theirs:
        test_model(a, b)
    assert str(ours.value) == str(theirs.value)


BAD_IMAGES = [
    lambda: torch.rand(3, 64, 64),                                # missing batch dim
    lambda: torch.rand(1, 3, 60, 64),                             # not a multiple of 16
    lambda: torch.zeros(1, 3, 64, 64, dtype=torch.uint8),         # uint8
    lambda: torch.rand(1, 3, 64, 64) * 255,                       # [0, 255] range
    lambda: torch.full((1, 3, 64, 64), float("nan")),             # NaN
    lambda: [[0.5]],                                              # not a tensor
]


@pytest.mark.parametrize("kind", ["full", "split"])
@pytest.mark.parametrize("make", BAD_IMAGES)
def test_encode_refuses_what_the_pytorch_encoder_refuses_with_the_same_message(kind, make, full_export,
                                                                               split_export, test_model):
    runner = pm.load_model(full_export if kind == "full" else split_export)
    img = make()
    with pytest.raises(ShapeError) as ours:
        runner.encode(img)
    with pytest.raises(ShapeError) as theirs:
        test_model.encode(img)
    assert str(ours.value) == str(theirs.value)


@pytest.mark.parametrize("kind", ["full", "split"])
def test_predict_pairs_runs_unchanged(kind, full_export, split_export, test_model):
    runner = pm.load_model(full_export if kind == "full" else split_export)
    imgs = [torch.rand(3, 64, 96) for _ in range(3)] + [torch.rand(3, 96, 64)]
    pairs = [(0, 1), (1, 2), (2, 3)]
    got = pm.predict_pairs(runner, imgs, pairs, batch_size=2, quiet=True)
    ref = pm.predict_pairs(test_model, imgs, pairs, batch_size=2, quiet=True)
    assert set(got) == set(ref) == {(0, 1), (1, 0), (1, 2), (2, 1), (2, 3), (3, 2)}
    for k in ref:
        assert got[k].batch_size == 1
        _close(ref[k], got[k])


def test_a_missing_empty_corrupt_or_foreign_export_is_refused_with_what_is_wrong(tmp_path, split_export):
    with pytest.raises(CheckpointError, match="not found"):
        load_onnx(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="holds no .onnx graph and no pointmap_export.json"):
        load_onnx(tmp_path / "empty")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x08\x07garbage that is not a protobuf" * 10)
    with pytest.raises(CheckpointError, match="cannot read .*bad.onnx as an ONNX model"):
        load_onnx(bad)
    import onnx

    proto = onnx.load(str(sorted(split_export.glob("*.onnx"))[0]), load_external_data=False)
    meta = json.loads(next(p.value for p in proto.metadata_props if p.key == "pointmap"))
    for value, message in [("{not json", "metadata is not valid JSON"), ("[1, 2]", "expected a JSON object, got list"),
                           (json.dumps({**meta, "provenance": "large"}), "provenance expected a dict"),
                           (json.dumps({**meta, "provenance": {"image_size": "large"}}), "positive int image_size")]:
        for p in proto.metadata_props:
            if p.key == "pointmap":
                p.value = value
        onnx.save(proto, str(tmp_path / "meta.onnx"))
        with pytest.raises(CheckpointError, match=message):
            load_onnx(tmp_path / "meta.onnx")
    with pytest.raises(CheckpointError, match="not available"):
        load_onnx(split_export, providers=["CUDAExecutionProvider"] if "CUDAExecutionProvider" not in
                  __import__("onnxruntime").get_available_providers() else ["NoSuchExecutionProvider"])
    with pytest.raises(ValueError):
        load_onnx(split_export, threads=0)
    with pytest.raises(TypeError):
        load_onnx(split_export, colour="blue")


def test_devices_and_provider_lists_resolve_to_onnxruntime_providers_with_cpu_last():
    assert resolve_providers(None) == ["CPUExecutionProvider"]
    assert resolve_providers("cpu") == ["CPUExecutionProvider"]
    assert resolve_providers("auto")[-1] == "CPUExecutionProvider"
    assert resolve_providers([("CPUExecutionProvider", {"arena_extend_strategy": "kSameAsRequested"})])[0][0] == \
        "CPUExecutionProvider"


def test_image_similarity_and_pooled_tokens_refuse_a_single_graph_export_and_agree_with_eager_on_a_split_one(
        full_export, split_export, test_model):
    from pointmap.inference import image_similarity, pooled_tokens

    imgs = [torch.rand(3, 48, 64, generator=torch.Generator().manual_seed(k)) for k in range(3)]
    full, split = pm.load_model(full_export), pm.load_model(split_export)
    with pytest.raises(CheckpointError, match="image_similarity needs .* single-graph ONNX export .* export with "
                                              "--split"):
        image_similarity(full, imgs)
    # pooled tokens of a single-graph export were a mean over the images' colour channels, ranking by nonsense
    with pytest.raises(CheckpointError, match="pooled_tokens .* single-graph ONNX export .* export with --split, or "
                                              "give localize its refs"):
        pooled_tokens(full, imgs)
    assert torch.allclose(image_similarity(split, imgs), image_similarity(test_model, imgs))
    assert torch.allclose(pooled_tokens(split, imgs), pooled_tokens(test_model, imgs), atol=1e-5)


def test_a_requested_provider_that_onnxruntime_could_not_start_is_reported_not_silently_replaced_by_the_cpu(
        full_export, monkeypatch):
    import onnxruntime as ort

    from pointmap.runtime import onnx as rt

    class CpuOnly(ort.InferenceSession):  # what onnxruntime does when the CUDA libraries are missing
        def __init__(self, path, sess_options=None, providers=None):
            super().__init__(path, sess_options=sess_options, providers=["CPUExecutionProvider"])

    monkeypatch.setattr(rt, "resolve_providers", lambda p: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    monkeypatch.setattr(ort, "InferenceSession", CpuOnly)
    with pytest.warns(RuntimeWarning, match=r"could not start \['CUDAExecutionProvider'\] for model.onnx.*"
                                            r"runs on \['CPUExecutionProvider'\]"):
        runner = load_onnx(full_export, providers="cuda")
    assert runner.providers == ["CPUExecutionProvider"]
    # asked for the CPU, or ended on a GPU provider (TensorRT listed but not installed, CUDA running): no warning
    monkeypatch.setattr(rt, "resolve_providers", lambda p: ["CPUExecutionProvider"])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert load_onnx(full_export).providers == ["CPUExecutionProvider"]


def test_an_onnx_export_asked_for_a_gpu_is_left_to_onnxruntime_even_when_torch_has_none(split_export, monkeypatch):
    import onnxruntime as ort

    import pointmap.runtime.onnx as rt

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # a CPU-only torch beside onnxruntime-gpu
    asked = []
    real = rt.resolve_providers
    monkeypatch.setattr(rt, "resolve_providers", lambda p: asked.append(p) or real(p))
    assert isinstance(pm.load_model(split_export, device="auto"), OnnxPointmapModel)
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        # before, "cuda" became "auto": a CPU-only onnxruntime ran on the CPU without a word, and cuda:3 on GPU 0
        for device in ("cuda", "cuda:3"):
            with pytest.raises(pm.CheckpointError, match="provider 'CUDAExecutionProvider' is not available here"):
                pm.load_model(split_export, device=device)
        assert asked == ["auto", [("CUDAExecutionProvider", {"device_id": 0})],
                         [("CUDAExecutionProvider", {"device_id": 3})]]
    for device in ("mps", "cuda:x"):
        with pytest.raises(pm.PointmapError, match="ONNX export|load_model: device expected"):
            pm.load_model(split_export, device=device)
    with pytest.raises(pm.PointmapError, match="load_model: device expected auto, cpu, cuda, cuda:N or mps"):
        pm.load_model(split_export, device="gpu")


def test_a_lone_onnx_file_runs_its_own_graph_whatever_else_its_folder_holds(tmp_path, full_export, split_export,
                                                                             test_model):
    import shutil

    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy(full_export / "model.onnx", lone / "mine.onnx")
    shutil.copy(split_export / "encoder.onnx", lone / "model.onnx")  # another export's graph under the default name
    img1, img2 = torch.rand(1, 3, 32, 48), torch.rand(1, 3, 32, 48)
    with torch.inference_mode():
        want = test_model(img1, img2)
    got = pm.load_model(lone / "mine.onnx")(img1, img2)
    assert torch.allclose(got.pts1_cam1, want.pts1_cam1, atol=1e-4)


def test_a_folder_holding_graphs_of_two_exports_is_refused(tmp_path, split_export):
    import json
    import shutil

    import onnx

    mixed = tmp_path / "mixed"
    shutil.copytree(split_export, mixed)
    proto = onnx.load(str(mixed / "decoder.onnx"), load_external_data=False)
    for p in proto.metadata_props:  # the decoder of an export made a minute later
        if p.key == "pointmap":
            meta = json.loads(p.value)
            meta["provenance"]["created"] = "2001-01-01T00:00:00+00:00"
            p.value = json.dumps(meta)
    onnx.save(proto, str(mixed / "decoder.onnx"))
    with pytest.raises(CheckpointError, match="belongs to another export"):
        load_onnx(mixed)
    load_onnx(split_export)  # the export as written loads (its sidecar's parity report is not in the graphs)


def test_a_sidecar_that_is_not_utf8_is_a_checkpoint_error(tmp_path, split_export):
    import shutil

    from pointmap.runtime.onnx import SIDECAR

    bad = tmp_path / "bad"
    shutil.copytree(split_export, bad)
    (bad / SIDECAR).write_bytes(b"\xff\xfe{}")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_onnx(bad)


def test_a_graph_without_its_exports_description_that_takes_other_inputs_is_refused_at_load(tmp_path, split_export):
    import shutil

    import onnx

    odd = tmp_path / "odd"
    shutil.copytree(split_export, odd)
    proto = onnx.load(str(odd / "encoder.onnx"))
    del proto.metadata_props[:]  # an old graph carries no description: the description's inputs are the check
    onnx.save(proto, str(odd / "decoder.onnx"))
    with pytest.raises(CheckpointError, match="decoder.onnx takes inputs .* a graph of another export"):
        load_onnx(odd)


def test_a_single_graph_exports_deferred_encoding_indexed_to_one_image_is_refused_as_pytorch_refuses_it(
        full_export, test_model):
    x = torch.rand(2, 3, 32, 32)
    runner = pm.load_model(full_export)
    with pytest.raises(ShapeError, match="enc1 expected"):
        runner.decode_pair(runner.encode(x)[0], runner.encode(x)[0])  # the batch dimension indexed away
    with torch.inference_mode(), pytest.raises(ShapeError, match="enc1 expected"):
        test_model.decode_pair(test_model.encode(x)[0], test_model.encode(x)[0])
