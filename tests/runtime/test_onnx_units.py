"""Unit tests from a mutation review of the onnxruntime runner (session 92), of its smaller contracts: provider
resolution and session options, the checks that refuse foreign, corrupt or mixed exports with what is wrong, the
deferred encodings of a single-graph export, the layout of what goes into the graphs and files_used; last, tests of
the bugs it found. They reuse the session's test-preset exports."""

import json
import logging
import shutil
import types
import warnings

import onnx
import pytest
import torch

import pointmap.runtime.onnx as rt
from pointmap.errors import CheckpointError, ShapeError
from pointmap.model import PRESETS
from pointmap.model.net import Encoded
from pointmap.runtime.onnx import (
    DECODER_GRAPH,
    ENCODER_GRAPH,
    FULL_GRAPH,
    SIDECAR,
    load_onnx,
    output_names,
    resolve_providers,
    session_options,
)

CPU, CUDA, TRT = "CPUExecutionProvider", "CUDAExecutionProvider", "TensorrtExecutionProvider"


# -- helpers ----------------------------------------------------------------------------------------------------
def _graph_meta(graph):
    proto = onnx.load(str(graph), load_external_data=False)
    return json.loads(next(p.value for p in proto.metadata_props if p.key == "pointmap"))


def _set_graph_meta(graph, text, out=None):
    """Rewrite (or with text None, remove) the description a graph carries; save it as ``out`` (default: itself)."""
    proto = onnx.load(str(graph), load_external_data=False)
    del proto.metadata_props[:]
    if text is not None:
        entry = proto.metadata_props.add()
        entry.key, entry.value = "pointmap", text
    onnx.save(proto, str(out or graph))


def _without_digests(folder):
    """Make ``folder``'s sidecar one of an export from before the sidecar listed its files' digests (session 93),
    whose graphs load unchecked: so a test may rewrite a graph's own description and load it from the folder."""
    meta = json.loads((folder / SIDECAR).read_text())
    meta.pop("files", None)
    (folder / SIDECAR).write_text(json.dumps(meta))
    return folder


def _fake_ort(monkeypatch, available):
    monkeypatch.setattr(rt, "_ort", lambda: types.SimpleNamespace(get_available_providers=lambda: list(available)))


# -- output names -----------------------------------------------------------------------------------------------
def test_a_pose_head_without_a_focal_head_outputs_the_transform_and_no_focals():
    cfg = PRESETS["test"].replace(pose_head=True)
    assert output_names(cfg) == ["pts1_cam1", "pts2_cam1", "conf1", "conf2", "desc1", "desc2", "desc_conf1",
                                 "desc_conf2", "cam2_to_cam1"]
    assert output_names(cfg.replace(focal_head=True))[-3:] == ["cam2_to_cam1", "focal1", "focal2"]
    assert output_names(PRESETS["dust3r_512_dpt"]) == ["pts1_cam1", "pts2_cam1", "conf1", "conf2"]


# -- providers and session options ----------------------------------------------------------------------------
def test_provider_aliases_resolve_in_any_case_to_onnxruntimes_names_with_the_cpu_appended_last(monkeypatch):
    _fake_ort(monkeypatch, [TRT, CUDA, CPU])
    assert resolve_providers("cuda") == [CUDA, CPU]
    assert resolve_providers("CUDA") == [CUDA, CPU]
    assert resolve_providers(["trt"]) == [TRT, CPU]
    assert resolve_providers(["TensorRT", "cuda"]) == [TRT, CUDA, CPU]
    assert resolve_providers("Cpu") == [CPU]
    assert resolve_providers(["cpu", "cuda"]) == [CPU, CUDA]  # the CPU given first stays first, and only once
    assert resolve_providers(None) == [CPU]
    with pytest.raises(CheckpointError, match="provider 'DmlExecutionProvider' is not available here"):
        resolve_providers("dml")


def test_auto_takes_tensorrt_then_cuda_then_the_cpu_of_those_installed(monkeypatch):
    _fake_ort(monkeypatch, [CPU, CUDA, TRT])
    assert resolve_providers("auto") == [TRT, CUDA, CPU]
    _fake_ort(monkeypatch, [CPU, CUDA])
    assert resolve_providers("auto") == [CUDA, CPU]


def test_provider_options_are_kept_and_a_cpu_given_with_options_is_not_appended_again(monkeypatch):
    _fake_ort(monkeypatch, [CUDA, CPU])
    opts = {"arena_extend_strategy": "kSameAsRequested"}
    assert resolve_providers([(CPU, opts)]) == [(CPU, opts)]
    assert resolve_providers([("cuda", {"device_id": 1})]) == [(CUDA, {"device_id": 1}), CPU]


def test_session_options_optimise_everything_run_sequentially_and_take_the_threads_asked():
    import onnxruntime as ort

    so = session_options(3)
    assert so.graph_optimization_level == ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    assert so.execution_mode == ort.ExecutionMode.ORT_SEQUENTIAL
    assert (so.intra_op_num_threads, so.inter_op_num_threads) == (3, 1)
    assert session_options().intra_op_num_threads == 0  # onnxruntime's own choice
    with pytest.raises(ValueError, match="threads expected .*>= 1, got 0"):
        session_options(0)


def test_the_threads_and_providers_asked_reach_every_loaded_session(split_export):
    runner = load_onnx(split_export, threads=1)
    for sess in runner._sessions.values():
        assert sess.get_session_options().intra_op_num_threads == 1
        assert sess.get_providers() == [CPU]


def test_the_providers_resolved_are_handed_to_onnxruntime(full_export, monkeypatch):
    import onnxruntime as ort

    handed = []

    class Recording(ort.InferenceSession):  # what onnxruntime is asked for (on a GPU build it must be told)
        def __init__(self, path, sess_options=None, providers=None):
            handed.append(providers)
            super().__init__(path, sess_options=sess_options, providers=providers)

    monkeypatch.setattr(ort, "InferenceSession", Recording)
    opts = {"arena_extend_strategy": "kSameAsRequested"}
    load_onnx(full_export, providers=[(CPU, opts)])
    assert handed == [[(CPU, opts)]]


def test_explicit_providers_win_over_a_device(full_export):
    assert load_onnx(full_export, providers=[CPU], device="cuda").providers == [CPU]


@pytest.mark.parametrize("device", ["cuda:x", "cuda:-1"])
def test_a_cuda_device_that_names_no_gpu_is_refused_as_a_device(full_export, device):
    with pytest.raises(CheckpointError, match=f"device expected 'cpu', 'cuda', 'cuda:N' or 'auto' for an ONNX export, "
                                              f"got '{device}'"):
        load_onnx(full_export, device=device)


def test_no_fallback_warning_when_the_gpu_provider_asked_for_runs(full_export, monkeypatch):
    import onnxruntime as ort

    class OnGpu(ort.InferenceSession):  # CUDA started: the session lists it first and the CPU after it
        def __init__(self, path, sess_options=None, providers=None):
            super().__init__(path, sess_options=sess_options, providers=[CPU])

        def get_providers(self):
            return [CUDA, CPU]

    monkeypatch.setattr(rt, "resolve_providers", lambda p: [CUDA, CPU])
    monkeypatch.setattr(ort, "InferenceSession", OnGpu)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert load_onnx(full_export, providers="cuda").providers == [CUDA, CPU]


# -- foreign, corrupt or partial exports --------------------------------------------------------------------------
def test_a_sidecar_that_is_not_json_or_not_a_file_is_a_checkpoint_error_naming_it(tmp_path, full_export):
    bad = shutil.copytree(full_export, tmp_path / "bad")
    (bad / SIDECAR).write_text("{not json")
    with pytest.raises(CheckpointError, match=f"bad/{SIDECAR} is not valid JSON"):
        load_onnx(bad)
    (bad / SIDECAR).unlink()
    (bad / SIDECAR).mkdir()
    with pytest.raises(CheckpointError, match=f"bad/{SIDECAR} is not valid JSON"):
        load_onnx(bad)


def test_a_graph_without_its_description_is_described_by_the_sidecar_beside_it_and_refused_without_one(
        tmp_path, full_export):
    beside = shutil.copytree(full_export, tmp_path / "beside")
    _set_graph_meta(beside / FULL_GRAPH, None)
    with pytest.raises(CheckpointError, match=r"beside/model.onnx is \d+ bytes where its export lists \d+"):
        load_onnx(beside / FULL_GRAPH)  # the sidecar lists the graph as exported, with its description
    runner = load_onnx(_without_digests(beside) / FULL_GRAPH)
    assert runner.meta == json.loads((beside / SIDECAR).read_text())
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(beside / FULL_GRAPH, alone / "m.onnx")
    with pytest.raises(CheckpointError, match=f"m.onnx is not a pointmap ONNX export \\(no 'pointmap' metadata, no "
                                              f"{SIDECAR} beside it\\)"):
        load_onnx(alone / "m.onnx")


def test_an_export_of_another_format_is_refused_naming_what_it_is_and_what_is_expected(tmp_path, full_export):
    meta = _graph_meta(full_export / FULL_GRAPH)
    for fmt in ("pointmap-onnx/2", None):
        _set_graph_meta(full_export / FULL_GRAPH, json.dumps({**meta, "format": fmt}), tmp_path / "g.onnx")
        with pytest.raises(CheckpointError,
                           match=f"unsupported export format {fmt!r} \\(expected 'pointmap-onnx/1'\\)"):
            load_onnx(tmp_path / "g.onnx")


def test_a_graph_of_another_export_in_the_folder_is_refused_naming_it_and_both_creation_times(tmp_path, split_export):
    mixed = shutil.copytree(split_export, tmp_path / "mixed")
    meta = _graph_meta(mixed / DECODER_GRAPH)
    ours = meta["provenance"]["created"]
    meta["provenance"]["created"] = "2001-01-01T00:00:00+00:00"
    _set_graph_meta(mixed / DECODER_GRAPH, json.dumps(meta))
    with pytest.raises(CheckpointError, match=f"mixed/decoder.onnx belongs to another export than the description it "
                                              f"was loaded with \\(created '2001-01-01T00:00:00\\+00:00', the "
                                              f"description '{ours.replace('+', '[+]')}'\\)"):
        load_onnx(mixed)


@pytest.mark.parametrize("text", ["{not json", "[1, 2]"])
def test_a_graph_whose_own_description_is_unreadable_is_judged_by_its_folders_description(tmp_path, full_export, text):
    odd = _without_digests(shutil.copytree(full_export, tmp_path / "odd"))
    _set_graph_meta(odd / FULL_GRAPH, text)
    img = torch.rand(1, 3, 32, 32)
    assert load_onnx(odd)(img, img).pts1_cam1.shape == (1, 32, 32, 3)


def test_a_graph_with_the_outputs_but_not_the_inputs_its_description_lists_is_refused_at_load(tmp_path, full_export,
                                                                                              split_export):
    odd = shutil.copytree(split_export, tmp_path / "odd")
    _set_graph_meta(full_export / FULL_GRAPH, None, odd / DECODER_GRAPH)  # same outputs, inputs img1 and img2
    with pytest.raises(CheckpointError, match=r"decoder.onnx takes inputs \['img1', 'img2'\] and lacks outputs \[\], "
                                              r"but its export's description lists inputs \{'tokens1': .*'tokens2'"):
        load_onnx(odd)


def test_a_graph_lacking_an_output_its_description_lists_is_refused_naming_it(tmp_path, full_export):
    odd = shutil.copytree(full_export, tmp_path / "odd")
    proto = onnx.load(str(odd / FULL_GRAPH))
    keep = [o for o in proto.graph.output if o.name != "conf2"]
    del proto.graph.output[:]
    proto.graph.output.extend(keep)
    onnx.save(proto, str(odd / FULL_GRAPH))
    with pytest.raises(CheckpointError, match=r"model.onnx takes inputs \['img1', 'img2'\] and lacks outputs "
                                              r"\['conf2'\]"):
        load_onnx(odd)


def test_a_lone_graph_is_checked_against_its_exports_description_whatever_its_file_is_called(tmp_path, full_export,
                                                                                              split_export):
    # an encoder graph carrying a single-graph export's description, loaded by its own name
    full_meta = json.dumps(_graph_meta(full_export / FULL_GRAPH))
    _set_graph_meta(split_export / ENCODER_GRAPH, full_meta, tmp_path / "x.onnx")
    with pytest.raises(CheckpointError, match=r"x.onnx takes inputs \['img'\]"):
        load_onnx(tmp_path / "x.onnx")


def test_a_minimal_description_loads_as_fp32_without_provenance_or_graphs_table(tmp_path, full_export):
    meta = json.loads((full_export / SIDECAR).read_text())
    small = shutil.copytree(full_export, tmp_path / "small")
    _set_graph_meta(small / FULL_GRAPH, None)
    (small / SIDECAR).write_text(json.dumps({k: meta[k] for k in ("format", "architecture", "split")}))
    runner = load_onnx(small)
    assert runner.precision == "fp32" and runner.provenance == {} and not runner.split
    img = torch.rand(1, 3, 32, 32)
    assert runner(img, img).conf2.shape == (1, 32, 32)


def test_a_description_without_an_architecture_is_refused_saying_so(tmp_path, full_export):
    meta = json.loads((full_export / SIDECAR).read_text())
    del meta["architecture"]
    _set_graph_meta(full_export / FULL_GRAPH, json.dumps(meta), tmp_path / "g.onnx")
    with pytest.raises(CheckpointError, match="export metadata has no usable architecture"):
        load_onnx(tmp_path / "g.onnx")


def test_a_split_export_missing_its_decoder_is_refused_naming_the_file_and_the_kind(tmp_path, split_export):
    half = shutil.copytree(split_export, tmp_path / "half")
    (half / DECODER_GRAPH).unlink()
    with pytest.raises(CheckpointError, match=r"half is missing decoder.onnx \(listed as split export\)"):
        load_onnx(half)


def test_a_graph_onnxruntime_cannot_load_beside_a_valid_description_is_a_checkpoint_error(tmp_path, full_export):
    bad = shutil.copytree(full_export, tmp_path / "bad")
    (bad / FULL_GRAPH).write_bytes(b"\x08\x07junk" * 20)
    with pytest.raises(CheckpointError, match="onnxruntime cannot load .*bad/model.onnx"):
        load_onnx(bad)


def test_a_non_commercial_licence_in_the_exports_provenance_is_warned_about(tmp_path, full_export):
    nc = _without_digests(shutil.copytree(full_export, tmp_path / "nc"))
    meta = json.loads((nc / SIDECAR).read_text())
    meta["provenance"]["licence"] = "CC-BY-NC-SA-4.0"
    _set_graph_meta(nc / FULL_GRAPH, None)
    (nc / SIDECAR).write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match="licensed CC-BY-NC-SA-4.0 \\(non-commercial use only\\)"):
        load_onnx(nc)


# -- the files' digests -------------------------------------------------------------------------------------------
def test_the_sidecar_lists_every_graph_of_the_export_with_its_size_and_sha256(split_export):
    import hashlib

    files = json.loads((split_export / SIDECAR).read_text())["files"]
    assert sorted(files) == [DECODER_GRAPH, ENCODER_GRAPH]
    for name, listed in files.items():
        data = (split_export / name).read_bytes()
        assert listed == {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def _change_a_weight(graph):
    """Add 1 to one weight matrix of ``graph`` in place (the file keeps its size); returns that weight's name."""
    from onnx import numpy_helper

    proto = onnx.load(str(graph))
    init = next(t for t in proto.graph.initializer if t.data_type == onnx.TensorProto.FLOAT and len(t.dims) == 2)
    init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init) + 1, init.name))
    onnx.save(proto, str(graph))
    return init.name


def test_a_graph_whose_weights_changed_after_the_export_is_refused_naming_it(tmp_path, full_export):
    odd = shutil.copytree(full_export, tmp_path / "odd")
    _change_a_weight(odd / FULL_GRAPH)
    assert (odd / FULL_GRAPH).stat().st_size == (full_export / FULL_GRAPH).stat().st_size
    with pytest.raises(CheckpointError, match="odd/model.onnx does not match the SHA-256 its export lists "
                                              r"\(corrupted or modified since the export\): export again"):
        load_onnx(odd)
    img = torch.rand(1, 3, 32, 32)  # what the check prevents: without the digests the graph loads, other weights
    assert not torch.equal(load_onnx(_without_digests(odd))(img, img).pts1_cam1, load_onnx(full_export)(img, img).pts1_cam1)


def test_external_weights_are_checked_too_and_a_truncated_weights_file_is_refused_by_its_size(tmp_path, full_export):
    ext = shutil.copytree(full_export, tmp_path / "ext")
    proto = onnx.load(str(ext / FULL_GRAPH))
    onnx.save_model(proto, str(ext / FULL_GRAPH), save_as_external_data=True, all_tensors_to_one_file=True,
                    location="model.onnx.data")
    meta = json.loads((ext / SIDECAR).read_text())
    meta["files"] = {k: v for k, v in rt.file_digests(ext).items() if k != SIDECAR}
    (ext / SIDECAR).write_text(json.dumps(meta))
    assert sorted(meta["files"]) == [FULL_GRAPH, "model.onnx.data"]
    img = torch.rand(1, 3, 32, 32)
    assert torch.equal(load_onnx(ext)(img, img).pts1_cam1, load_onnx(full_export)(img, img).pts1_cam1)
    data = (ext / "model.onnx.data").read_bytes()
    (ext / "model.onnx.data").write_bytes(data[:-64] + bytes(64))  # the last weights zeroed: the same size
    with pytest.raises(CheckpointError, match="model.onnx.data does not match the SHA-256 its export lists"):
        load_onnx(ext)
    (ext / "model.onnx.data").write_bytes(data + bytes(8))  # a longer file onnxruntime still reads
    with pytest.raises(CheckpointError, match=f"model.onnx.data is {len(data) + 8} bytes where its export lists "
                                              f"{len(data)} \\(truncated or replaced since the export\\?\\)"):
        load_onnx(ext)


@pytest.mark.parametrize("files", [[], {FULL_GRAPH: "abc"}, {FULL_GRAPH: {"bytes": "12", "sha256": "ab"}},
                                   {FULL_GRAPH: {"bytes": 12}}])
def test_a_sidecar_whose_files_table_is_malformed_is_a_checkpoint_error_showing_it(tmp_path, full_export, files):
    odd = shutil.copytree(full_export, tmp_path / "odd")
    meta = json.loads((odd / SIDECAR).read_text())
    (odd / SIDECAR).write_text(json.dumps({**meta, "files": files}))
    with pytest.raises(CheckpointError, match="odd: its export metadata's files expected a JSON object of file name "
                                              r"-> \{'bytes': int, 'sha256': str\}, got "):
        load_onnx(odd)


# -- the runner ---------------------------------------------------------------------------------------------------
def test_the_runner_names_its_folder_kind_precision_and_providers_and_lives_on_the_cpu(full_export, split_export):
    full, split = load_onnx(full_export), load_onnx(split_export)
    assert repr(full) == f"OnnxPointmapModel({str(full_export)!r}, single graph, fp32, providers=['{CPU}'])"
    assert repr(split) == f"OnnxPointmapModel({str(split_export)!r}, split, fp32, providers=['{CPU}'])"
    assert full.device == torch.device("cpu")


def test_files_used_are_the_graphs_and_the_sidecar_of_a_folder_export(full_export, split_export):
    assert load_onnx(full_export).files_used() == [full_export / FULL_GRAPH, full_export / SIDECAR]
    assert load_onnx(split_export / DECODER_GRAPH).files_used() == [split_export / ENCODER_GRAPH,
                                                                    split_export / DECODER_GRAPH,
                                                                    split_export / SIDECAR]


@pytest.mark.parametrize("kind", ["full", "split"])
def test_images_that_require_grad_or_are_not_contiguous_run(kind, full_export, split_export, test_model):
    runner = load_onnx(full_export if kind == "full" else split_export)
    img1 = torch.rand(1, 3, 48, 32).transpose(2, 3).requires_grad_()  # [1, 3, 32, 48], neither contiguous nor leaf-free
    img2 = torch.rand(1, 3, 32, 48)
    with torch.inference_mode():
        want = test_model(img1.detach(), img2)
    got = runner(img1, img2)
    assert torch.allclose(got.pts1_cam1, want.pts1_cam1, atol=1e-4)
    assert torch.allclose(got.pts2_cam1, want.pts2_cam1, atol=1e-4)


def test_a_split_export_encodes_a_same_size_pair_in_one_encoder_run(split_export):
    runner = load_onnx(split_export)
    runs = []
    real = runner._run
    runner._run = lambda graph, feeds, names: runs.append((graph, {k: v.shape for k, v in feeds.items()})) or \
        real(graph, feeds, names)
    runner(torch.rand(2, 3, 32, 48), torch.rand(2, 3, 32, 48))
    assert runs[0] == (ENCODER_GRAPH, {"img": (4, 3, 32, 48)})
    assert [g for g, _ in runs] == [ENCODER_GRAPH, DECODER_GRAPH]


def test_a_single_graph_exports_encode_gives_the_token_grid_and_logs_once_that_it_defers(full_export, caplog):
    runner = load_onnx(full_export)
    with caplog.at_level(logging.WARNING, logger="pointmap.runtime.onnx"):
        enc = runner.encode(torch.rand(2, 3, 32, 64))
        runner.encode(torch.rand(1, 3, 32, 32))
    assert enc.grid == (2, 4)
    said = [r for r in caplog.records if "is a single-graph export" in r.getMessage()]
    assert len(said) == 1


def test_deferred_encodings_mixed_with_real_ones_or_of_other_batch_sizes_or_a_bad_second_view_are_refused(
        full_export, split_export):
    runner = load_onnx(full_export)
    deferred = runner.encode(torch.rand(2, 3, 32, 32))
    real = load_onnx(split_export).encode(torch.rand(2, 3, 32, 32))
    for a, b in ((deferred, real), (real, deferred)):
        with pytest.raises(ShapeError, match="decode_pair got one deferred and one real encoding"):
            runner.decode_pair(a, b)
    with pytest.raises(ShapeError, match="batch sizes differ: 2 and 1"):
        runner.decode_pair(deferred, deferred[0:1])
    with pytest.raises(ShapeError, match="enc2 expected"):
        runner.decode_pair(deferred, deferred[0])  # the second view's batch dimension indexed away


def test_the_decoder_gets_each_views_tokens_on_its_own_grid(split_export, test_model):
    runner = load_onnx(split_export)
    img1, img2 = torch.rand(1, 3, 32, 64), torch.rand(1, 3, 64, 32)
    enc1, enc2 = runner.encode(img1), runner.encode(img2)
    assert (enc1.grid, enc2.grid) == ((2, 4), (4, 2))
    got = runner.decode_pair(enc1, enc2)
    with torch.inference_mode():
        want = test_model(img1, img2)
    assert got.pts2_cam1.shape == (1, 64, 32, 3)
    assert torch.allclose(got.pts2_cam1, want.pts2_cam1, atol=1e-4)
    assert isinstance(enc1, Encoded)


# --- inputs and descriptions the runner took wrongly (session 92) ---------------------------------------------------


def test_a_thread_count_that_is_not_a_whole_number_is_refused_with_what_was_given(full_export):
    import numpy as np

    from pointmap.runtime.onnx import session_options

    for threads in (2.5, "2", True, "many"):  # before: 2.5 ran on 2 threads, "many" failed inside int()
        with pytest.raises(ValueError, match=f"threads expected an int >= 1, got {threads!r}"):
            load_onnx(full_export, threads=threads)
    assert session_options(np.int64(2)).intra_op_num_threads == 2  # a NumPy int is a whole number


@pytest.mark.parametrize("providers, given", [(5, "int"), ([CPU, {"device_id": 0}], "{'device_id': 0}"),
                                              ((CPU, {"arena_extend_strategy": "kSameAsRequested"}),
                                               "{'arena_extend_strategy': 'kSameAsRequested'}"),
                                              ([(CPU, {}, 3)], "\\('CPUExecutionProvider', {}, 3\\)")])
def test_providers_that_are_not_names_or_name_and_options_tuples_are_refused_saying_what_is_expected(providers, given):
    with pytest.raises(CheckpointError, match=f"providers expected .*name.*\\(name, options\\) tuples.*got {given}"):
        resolve_providers(providers)


def test_a_description_whose_graphs_table_is_not_an_object_is_a_checkpoint_error(tmp_path, full_export):
    odd = shutil.copytree(full_export, tmp_path / "odd")
    proto = onnx.load(str(odd / FULL_GRAPH), load_external_data=False)
    del proto.metadata_props[:]  # the sidecar alone describes the graph
    onnx.save(proto, str(odd / FULL_GRAPH))
    meta = json.loads((odd / SIDECAR).read_text())
    (odd / SIDECAR).write_text(json.dumps({**meta, "graphs": [meta["graphs"]["full"]]}))
    with pytest.raises(CheckpointError, match="export metadata's graphs expected a JSON object .*got list"):
        load_onnx(odd)
