"""Unit tests from a mutation review of export/exporter.py (session 93), of what the slow end-to-end exports do not
pin: what ``export_graphs`` asks torch's exporter for and does to the graph it gets back, the weight-transpose fold,
the metadata stamped into each graph and the sidecar, the external-data and precision choices, the parity gate, and
the staging folder and its atomic publish. ``torch.onnx.export``, the parity run, the runner and int8 quantisation
are replaced by stand-ins that write or check tiny graphs: every test here runs in well under a second. Last, tests
of the bug it found: ``export_model`` took any value for its flags (``split="no"`` wrote a split export whose sidecar
said ``"split": "no"``) and a parity name that is not a string failed with a bare TypeError."""

import datetime
import json
import logging
import os
import types

import numpy as np
import onnx
import onnx_ir as ir
import pytest
import torch
from onnx import TensorProto, helper, numpy_helper

import export.exporter as ex
import export.graphs
import export.parity
import export.precision
import pointmap as pm
import pointmap.runtime.onnx as rt
from export.exporter import (
    DEFAULT_OPSET,
    PROTO_LIMIT,
    _atomic_publish,
    _foreign_files,
    check_target,
    export_graphs,
    export_model,
    fold_weight_transposes,
    param_bytes,
    stamp,
)
from export.parity import PARITY_CASES
from pointmap.errors import CheckpointError
from pointmap.model import PRESETS
from pointmap.runtime.onnx import FORMAT, METADATA_KEY, SIDECAR

TOP = onnx.defs.onnx_opset_version()


# -- helpers ----------------------------------------------------------------------------------------------------
def _tiny_proto(opset=DEFAULT_OPSET, props=None):
    """A valid one-node graph (y = x + b), optionally carrying metadata entries."""
    b = numpy_helper.from_array(np.ones(3, dtype=np.float32), "b")
    g = helper.make_graph([helper.make_node("Add", ["x", "b"], ["y"])], "g",
                          [helper.make_tensor_value_info("x", TensorProto.FLOAT, [3])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, [3])], [b])
    proto = helper.make_model(g, opset_imports=[helper.make_opsetid("", opset)])
    for k, v in (props or {}).items():
        e = proto.metadata_props.add()
        e.key, e.value = k, v
    return proto


def _ir(nodes, inputs, outputs, inits, opset=DEFAULT_OPSET):
    g = helper.make_graph(nodes, "g", inputs, outputs, inits)
    return ir.serde.deserialize_model(helper.make_model(g, opset_imports=[helper.make_opsetid("", opset)]))


def _vi(name, dims):
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, dims)


def _dims(value):
    return [d.value if isinstance(d, ir.SymbolicDim) else d for d in value.shape]


def _hidden(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


@pytest.fixture
def stand_ins(monkeypatch):
    """Replace the export, the runner, the parity run and int8 quantisation: each writes or records, instantly.
    ``seen`` records every call; ``seen.report`` is what the parity run returns."""
    seen = types.SimpleNamespace(export=[], load=[], parity=[], quantize=[], returned=[], report=None)

    def fake_export_graphs(model, tmp, *, split, opset, external, fp16=False, quiet=True):
        seen.export.append(dict(model=model, tmp=tmp, split=split, opset=opset, external=external, fp16=fp16))
        specs = export.graphs.graph_specs(model, split)
        for s in specs:
            onnx.save(_tiny_proto(props={"old": "stale"}), str(tmp / s["file"]))
            s["export_seconds"] = 0.5
        return specs

    def fake_load(path, *a, **k):
        seen.load.append(dict(path=path, files=sorted(p.name for p in path.iterdir())))
        return object()

    def fake_parity(model, runner, cases, *, strict=True, seed=0):
        seen.parity.append(dict(model=model, cases=cases, strict=strict))
        seen.returned.append(seen.report or {"passed": True, "strict": strict,
                                             "cases": [{"case": "c", "worst_ratio": 0.1}]})
        return seen.returned[-1]

    monkeypatch.setattr(ex, "export_graphs", fake_export_graphs)
    monkeypatch.setattr(rt, "load_onnx", fake_load)
    monkeypatch.setattr(export.parity, "check_parity", fake_parity)
    monkeypatch.setattr(export.precision, "quantize_int8",
                        lambda path, *, external=False: seen.quantize.append((path.name, external)))
    return seen


@pytest.fixture
def model():
    torch.manual_seed(0)
    cfg = PRESETS["test"].replace(head="linear", desc_dim=0, patch_size=14, img_mean=(0.1, 0.2, 0.3),
                                  img_std=(0.4, 0.5, 0.6))
    return pm.PointmapNet(cfg)


# -- export_graphs: what torch's exporter is asked for, and what is done to its graph -----------------------------
class _Prog:
    def __init__(self, model, saves):
        self.model, self.saves = model, saves

    def save(self, path, external_data=False):
        self.saves.append((path, external_data))
        onnx.save(ir.serde.serialize_model(self.model), path)


def _spec():
    return dict(file="model.onnx", role="full", wrapper=torch.nn.Identity().train(), args=(torch.zeros(1),),
                dynamic_shapes={"img": {0: "B"}}, inputs={"img": ["batch", 3, "height", "width"]},
                outputs={"out": ["batch", "height", "width", 3], "extra": ["batch"]})


def _exported_ir(opset):
    """What torch.export writes: '16*s1'-style dims, a Transpose on a weight, a rank the spec does not list."""
    W = numpy_helper.from_array(np.arange(6, dtype=np.float32).reshape(3, 2), "W")
    nodes = [helper.make_node("Transpose", ["W"], ["Wt"], perm=[1, 0]),
             helper.make_node("MatMul", ["img", "Wt"], ["out"]), helper.make_node("Identity", ["img"], ["extra"])]
    return _ir(nodes, [_vi("img", ["s0", 3, "16*s1", "16*s2"])],
               [_vi("out", ["s0", "16*s1", "16*s2", 3]), _vi("extra", ["s0", "s9"])], [W], opset)


@pytest.fixture
def fake_torch_export(monkeypatch):
    """torch.onnx.export replaced: records its arguments and the noisy logger's level, prints chatter, returns a
    program holding ``_exported_ir``; ``calls.fail`` makes it raise, ``calls.got_opset`` sets the graph's opset."""
    calls = types.SimpleNamespace(kwargs=[], saves=[], levels=[], fail=None, got_opset=None, specs=[])

    def fake(wrapper, args, **kw):
        calls.kwargs.append(dict(kw, training=wrapper.training, args=args))
        calls.levels.append(logging.getLogger("torch.onnx._internal.exporter._registration").level)
        print("exporter chatter")
        if calls.fail:
            raise calls.fail
        return _Prog(_exported_ir(calls.got_opset or kw["opset_version"]), calls.saves)

    def specs(model, split, dtype=torch.float32):
        calls.specs.append(dtype)
        return [_spec()]

    monkeypatch.setattr(torch.onnx, "export", fake)
    monkeypatch.setattr(ex, "graph_specs", specs)
    return calls


def test_export_graphs_asks_torch_for_a_dynamo_export_with_the_specs_names_shapes_and_opset(tmp_path,
                                                                                             fake_torch_export):
    (spec,) = export_graphs(torch.nn.Linear(1, 1), tmp_path, split=False, opset=19, external=True)
    (kw,) = fake_torch_export.kwargs
    assert kw["dynamo"] is True and kw["opset_version"] == 19 and kw["optimize"] is True
    assert kw["input_names"] == ["img"] and kw["output_names"] == ["out", "extra"]
    assert kw["dynamic_shapes"] == {"img": {0: "B"}} and not kw["training"]
    assert fake_torch_export.saves == [(str(tmp_path / "model.onnx"), True)]  # under its file name, external asked
    assert 0 <= spec["export_seconds"] < 60  # a duration, not the clock
    assert fake_torch_export.specs == [torch.float32]


def test_export_graphs_names_every_dimension_of_the_spec_and_folds_the_weight_transposes(tmp_path,
                                                                                          fake_torch_export):
    export_graphs(torch.nn.Linear(1, 1), tmp_path, split=False, opset=DEFAULT_OPSET, external=False)
    m = ir.serde.deserialize_model(onnx.load(str(tmp_path / "model.onnx")))
    assert _dims(m.graph.inputs[0]) == ["batch", 3, "height", "width"]
    assert isinstance(m.graph.inputs[0].shape[1], int)  # a fixed size stays a number
    assert _dims(m.graph.outputs[0]) == ["batch", "height", "width", 3]
    assert _dims(m.graph.outputs[1]) == ["s0", "s9"]  # the spec lists another rank: the dims are left as they are
    assert [n.op_type for n in m.graph] == ["MatMul", "Identity"] and list(m.graph.initializers) == ["W.T"]


def test_quiet_export_graphs_swallows_the_exporters_chatter_and_silences_its_registration_logger_meanwhile(
        tmp_path, fake_torch_export, capsys):
    noisy = logging.getLogger("torch.onnx._internal.exporter._registration")
    noisy.setLevel(logging.INFO)
    try:
        export_graphs(torch.nn.Linear(1, 1), tmp_path, split=False, opset=DEFAULT_OPSET, external=False, quiet=True)
        assert capsys.readouterr().out == "" and fake_torch_export.levels == [logging.ERROR]
        assert noisy.level == logging.INFO  # put back afterwards
        export_graphs(torch.nn.Linear(1, 1), tmp_path, split=False, opset=DEFAULT_OPSET, external=False, quiet=False)
        assert "exporter chatter" in capsys.readouterr().out and fake_torch_export.levels[-1] == logging.INFO
    finally:
        noisy.setLevel(logging.NOTSET)


def test_a_failing_export_is_a_checkpoint_error_naming_the_graph_and_the_first_line_of_the_cause(tmp_path,
                                                                                                 fake_torch_export):
    fake_torch_export.fail = RuntimeError("unsupported op aten::foo\nfull traceback follows")
    with pytest.raises(CheckpointError, match="ONNX export of the full graph failed: RuntimeError: unsupported op "
                                              "aten::foo$"):
        export_graphs(torch.nn.Linear(1, 1), tmp_path, split=False, opset=DEFAULT_OPSET, external=False)


@pytest.mark.parametrize("asked, got", [(19, 18), (18, 19)])
def test_a_graph_that_does_not_carry_the_opset_asked_for_is_refused_naming_both(tmp_path, fake_torch_export, asked,
                                                                                 got):
    fake_torch_export.got_opset = got
    with pytest.raises(CheckpointError, match=f"asked for opset {asked} and got {got}.*ask for {got}"):
        export_graphs(torch.nn.Linear(1, 1), tmp_path, split=False, opset=asked, external=False)


def test_an_fp16_export_builds_its_specs_in_float16_from_the_half_backbone_and_fp32_leaves_it(tmp_path,
                                                                                              fake_torch_export,
                                                                                              monkeypatch):
    halved = []
    monkeypatch.setattr(export.graphs, "half_backbone", lambda m: halved.append(m) or m)
    export_graphs(torch.nn.Linear(1, 1), tmp_path, split=False, opset=DEFAULT_OPSET, external=False)
    assert halved == [] and fake_torch_export.specs == [torch.float32]
    export_graphs(torch.nn.Linear(1, 1), tmp_path, split=False, opset=DEFAULT_OPSET, external=False, fp16=True)
    assert len(halved) == 1 and fake_torch_export.specs[-1] == torch.float16


# -- fold_weight_transposes -------------------------------------------------------------------------------------
def test_the_fold_applies_the_perm_and_gives_the_folded_weight_its_transposed_shape():
    W = numpy_helper.from_array(np.arange(24, dtype=np.float32).reshape(2, 3, 4), "W")
    nodes = [helper.make_node("Transpose", ["W"], ["Wt"], perm=[1, 0, 2]), helper.make_node("Neg", ["Wt"], ["y"])]
    m = _ir(nodes, [], [_vi("y", [3, 2, 4])], [W])
    assert fold_weight_transposes(m) == 1
    new = m.graph.initializers["W.T"]
    assert tuple(new.shape) == (3, 2, 4)
    assert np.array_equal(new.const_value.numpy(), np.arange(24).reshape(2, 3, 4).transpose(1, 0, 2))


def test_the_fold_takes_the_ai_onnx_domain_spelling_and_leaves_other_domains_and_non_weights_alone():
    W = numpy_helper.from_array(np.ones((2, 3), dtype=np.float32), "W")
    nodes = [helper.make_node("Transpose", ["W"], ["A"], perm=[1, 0], domain="ai.onnx"),
             helper.make_node("Transpose", ["W"], ["B"], perm=[1, 0], domain="com.example"),
             helper.make_node("Transpose", ["x"], ["C"], perm=[1, 0])]
    nodes += [helper.make_node("Neg", [n], [n.lower()]) for n in "ABC"]
    m = _ir(nodes, [_vi("x", [2, 3])], [_vi(n, [3, 2]) for n in "abc"], [W])
    m.opset_imports["com.example"] = 1
    assert fold_weight_transposes(m) == 1
    assert [(n.domain, n.op_type, n.inputs[0].name) for n in m.graph if n.op_type == "Transpose"] == \
        [("com.example", "Transpose", "W"), ("", "Transpose", "x")]
    assert set(m.graph.initializers) == {"W", "W.T"}  # W still read by the custom-domain node


def test_the_folded_weight_gets_a_fresh_name_past_every_taken_one():
    inits = [numpy_helper.from_array(np.full((2, 3), v, dtype=np.float32), n) for n, v in
             (("W", 1), ("W.T", 2), ("W.T_", 3))]
    nodes = [helper.make_node("Transpose", ["W"], ["Wt"], perm=[1, 0]), helper.make_node("Neg", ["Wt"], ["y"]),
             helper.make_node("Add", ["W.T", "W.T_"], ["s"])]
    m = _ir(nodes, [], [_vi("y", [3, 2]), _vi("s", [2, 3])], inits)
    assert fold_weight_transposes(m) == 1
    assert {n: float(v.const_value.numpy().flat[0]) for n, v in m.graph.initializers.items()} == \
        {"W.T": 2, "W.T_": 3, "W.T__": 1}


def test_only_initializers_are_folded_not_a_constant_nodes_output_that_carries_its_value():
    value = numpy_helper.from_array(np.ones((2, 3), dtype=np.float32))
    nodes = [helper.make_node("Constant", [], ["c"], value=value),
             helper.make_node("Transpose", ["c"], ["t"], perm=[1, 0]), helper.make_node("Neg", ["t"], ["y"])]
    m = _ir(nodes, [], [_vi("y", [3, 2])], [])
    next(iter(m.graph)).outputs[0].const_value = ir.tensor(np.ones((2, 3), dtype=np.float32))  # as folding passes do
    assert fold_weight_transposes(m) == 0
    assert [n.op_type for n in m.graph] == ["Constant", "Transpose", "Neg"] and not m.graph.initializers


@pytest.mark.parametrize("also", ["read by another node", "a graph output"])
def test_a_weight_still_needed_elsewhere_is_kept_beside_its_folded_copy(also):
    W = numpy_helper.from_array(np.ones((2, 2), dtype=np.float32), "W")
    nodes = [helper.make_node("Transpose", ["W"], ["Wt"], perm=[1, 0]), helper.make_node("Neg", ["Wt"], ["y"])]
    outs = [_vi("y", [2, 2])]
    if also == "read by another node":
        nodes.append(helper.make_node("Neg", ["W"], ["n"]))
        outs.append(_vi("n", [2, 2]))
    else:
        outs.append(_vi("W", [2, 2]))
    m = _ir(nodes, [], outs, [W])
    assert fold_weight_transposes(m) == 1
    assert set(m.graph.initializers) == {"W", "W.T"}
    onnx.checker.check_model(ir.serde.serialize_model(m))


def test_param_bytes_counts_the_bytes_of_every_tensor_of_the_state_dict_buffers_included():
    bn = torch.nn.BatchNorm1d(4)  # weight, bias, running mean and var: 4 float32 each; num_batches_tracked: 1 int64
    assert param_bytes(bn) == 4 * 4 * 4 + 8


# -- stamp --------------------------------------------------------------------------------------------------------
def test_stamp_replaces_the_graphs_metadata_by_the_description_and_keeps_external_weights_external(tmp_path):
    graph = tmp_path / "g.onnx"
    onnx.save(_tiny_proto(props={"old": "stale", METADATA_KEY: "{}"}), str(graph), save_as_external_data=True,
              all_tensors_to_one_file=True, location="g.onnx.data", size_threshold=0)
    data = (tmp_path / "g.onnx.data").read_bytes()
    stamp(graph, {"format": FORMAT, "n": 1})
    proto = onnx.load(str(graph), load_external_data=False)
    assert [(p.key, json.loads(p.value)) for p in proto.metadata_props] == [(METADATA_KEY, {"format": FORMAT, "n": 1})]
    assert proto.producer_name == "pointmap-export"
    assert proto.graph.initializer[0].data_location == onnx.TensorProto.EXTERNAL
    assert (tmp_path / "g.onnx.data").read_bytes() == data and sorted(os.listdir(tmp_path)) == ["g.onnx", "g.onnx.data"]


# -- export_model: the sidecar and what each graph carries ----------------------------------------------------------
def test_the_sidecar_describes_the_export_asked_for_and_is_what_export_model_returns(tmp_path, stand_ins, model):
    meta = export_model(model, tmp_path / "out", split=True, opset=19, parity="quick")
    text = (tmp_path / "out" / SIDECAR).read_text()
    assert text.endswith("}\n") and json.loads(text) == meta
    assert meta["format"] == FORMAT and meta["split"] is True and meta["opset"] == 19 and meta["precision"] == "fp32"
    assert pm.ModelConfig.from_dict(meta["architecture"]) == model.cfg
    pre = meta["preprocessing"]
    assert pre["patch_size"] == 14 and pre["mean"] == [0.1, 0.2, 0.3] and pre["std"] == [0.4, 0.5, 0.6]
    specs = export.graphs.graph_specs(model, True)
    assert meta["graphs"] == {s["role"]: {"file": s["file"], "inputs": s["inputs"], "outputs": s["outputs"],
                                          "dtype_io": "float32", "external_data": False} for s in specs}
    assert meta["parity"] == stand_ins.returned[0]
    assert sorted(os.listdir(tmp_path / "out")) == sorted([SIDECAR, "encoder.onnx", "decoder.onnx"])


def test_every_graph_carries_the_sidecar_without_the_parity_report_and_digests_as_its_only_metadata(
        tmp_path, stand_ins, model):
    meta = export_model(model, tmp_path / "out", split=True, parity="quick")
    assert "parity" in meta and sorted(meta["files"]) == ["decoder.onnx", "encoder.onnx"]
    assert rt.AFTER_STAMP == ("parity", "files")
    for f in ("encoder.onnx", "decoder.onnx"):
        proto = onnx.load(str(tmp_path / "out" / f), load_external_data=False)
        assert [p.key for p in proto.metadata_props] == [METADATA_KEY]  # the stale entry is gone
        assert json.loads(proto.metadata_props[0].value) == {k: v for k, v in meta.items() if k not in rt.AFTER_STAMP}
        assert meta["files"][f] == rt.file_digests(tmp_path / "out")[f]  # the published file is the one listed
        assert proto.producer_name == "pointmap-export"


def test_the_provenance_is_the_callers_with_the_exporters_own_record_which_the_caller_cannot_overwrite(
        tmp_path, stand_ins, model):
    import onnxruntime

    model.register_buffer("extra", torch.zeros(10, dtype=torch.float64))  # counted as float32: the copy exported
    meta = export_model(model, tmp_path / "out", split=True, parity="none",
                        provenance={"source": "mine", "versions": "old", "created": "then"})
    prov = meta["provenance"]
    assert prov["source"] == "mine" and prov["exporter"] == "torch.onnx.export(dynamo=True)"
    v = prov["versions"]
    assert v["onnxruntime"] == onnxruntime.__version__ and v["onnx"] == onnx.__version__ and v["torch"]
    created = datetime.datetime.fromisoformat(prov["created"])
    assert created.utcoffset() == datetime.timedelta(0) and created.microsecond == 0
    assert abs((datetime.datetime.now(datetime.timezone.utc) - created).total_seconds()) < 600
    assert prov["parameters_bytes_fp32"] == sum(t.numel() * 4 for t in model.state_dict().values())
    assert prov["export_seconds"] == {"encoder": 0.5, "decoder": 0.5}


def test_the_pointmap_version_is_recorded_as_unknown_when_it_is_not_installed(tmp_path, stand_ins, model,
                                                                               monkeypatch):
    import importlib.metadata

    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", missing)
    meta = export_model(model, tmp_path / "out", parity="none")
    assert meta["provenance"]["versions"]["pointmap"] == "unknown"


def test_the_exported_copy_is_float32_in_eval_mode_and_the_parity_check_runs_on_it(tmp_path, stand_ins, model):
    model = model.half().train()
    export_model(model, tmp_path / "out", parity="quick")
    (call,) = stand_ins.export
    assert call["model"] is not model and not call["model"].training
    assert next(call["model"].parameters()).dtype == torch.float32
    assert stand_ins.parity[0]["model"] is call["model"]


@pytest.mark.parametrize("nbytes, asked, external", [
    (PROTO_LIMIT, None, False), (PROTO_LIMIT + 1, None, True),
    (2 * 1024**3 - 32 * 1024**2, None, True),  # under 2 GB, but not with room for the graph itself
    (2 * 1024**3 - 96 * 1024**2, None, False),
    (10**12, False, False), (10, True, True)])
def test_weights_go_to_external_files_only_past_protobufs_limit_with_room_for_the_graph_unless_asked(
        tmp_path, stand_ins, model, monkeypatch, nbytes, asked, external):
    monkeypatch.setattr(ex, "param_bytes", lambda m: nbytes)
    meta = export_model(model, tmp_path / "out", split=True, quantize="int8", parity="none", external_data=asked)
    assert stand_ins.export[0]["external"] is external
    assert {g["external_data"] for g in meta["graphs"].values()} == {external}
    assert stand_ins.quantize == [("encoder.onnx", external), ("decoder.onnx", external)]


@pytest.mark.parametrize("kw, precision, strict", [({}, "fp32", True), ({"fp16": True}, "fp16", False),
                                                    ({"quantize": "int8"}, "int8", False)])
def test_the_precision_is_recorded_and_only_fp32_is_held_to_the_strict_parity_tolerance(tmp_path, stand_ins, model,
                                                                                       kw, precision, strict):
    meta = export_model(model, tmp_path / "out", split=True, parity="quick", **kw)
    assert meta["precision"] == precision and stand_ins.parity[0]["strict"] is strict
    assert stand_ins.export[0]["fp16"] is (precision == "fp16")
    assert {g["dtype_io"] for g in meta["graphs"].values()} == {"float32"}  # inputs and outputs float32 always
    assert stand_ins.quantize == ([("encoder.onnx", False), ("decoder.onnx", False)] if precision == "int8" else [])
    times = meta["provenance"].get("convert_seconds")  # the int8 conversion's time, per graph
    assert (sorted(times) == ["decoder", "encoder"] and all(t >= 0 for t in times.values())) if precision == "int8" \
        else times is None


# -- export_model: the parity gate ----------------------------------------------------------------------------------
@pytest.mark.parametrize("parity", ["quick", "standard", "full"])
def test_the_parity_check_runs_the_cases_asked_on_the_stamped_graphs_before_the_sidecar_is_written(
        tmp_path, stand_ins, model, parity):
    export_model(model, tmp_path / "out", parity=parity)
    (load,) = stand_ins.load
    assert load["files"] == ["model.onnx"] and load["path"].parent == tmp_path  # the staged folder, beside out
    assert stand_ins.parity[0]["cases"] == PARITY_CASES[parity]


def test_parity_none_loads_and_checks_nothing_and_records_no_report(tmp_path, stand_ins, model):
    meta = export_model(model, tmp_path / "out", parity="none")
    assert stand_ins.load == [] and stand_ins.parity == [] and "parity" not in meta


@pytest.mark.parametrize("kw", [{}, {"fp16": True}])
def test_a_failed_parity_check_names_the_worst_case_and_writes_nothing(tmp_path, stand_ins, model, kw):
    stand_ins.report = {"passed": False, "cases": [
        {"case": "224x224 b1", "worst_output": "conf1", "worst_ratio": 0.5},
        {"case": "512x384 b1", "worst_output": "pts2_cam1", "worst_ratio": 3.0},
        {"case": "224x224 b3", "worst_output": "desc1", "worst_ratio": 2.0}]}
    with pytest.raises(CheckpointError, match=r"worst pts2_cam1 at 512x384 b1 differs by 3x the tolerance"):
        export_model(model, tmp_path / "out", parity="standard", **kw)
    assert os.listdir(tmp_path) == []


# -- export_model: staging and publishing ---------------------------------------------------------------------------
def test_the_export_is_staged_in_a_hidden_folder_beside_the_target_named_for_this_process(tmp_path, stand_ins, model,
                                                                                         monkeypatch):
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")  # not where it is staged
    stale = tmp_path / f".out.tmp-{os.getpid()}"  # left by a crashed export of this pid: cleared, not an error
    stale.mkdir()
    (stale / "junk.onnx").write_text("x")
    export_model(model, tmp_path / "out", parity="none")
    assert stand_ins.export[0]["tmp"] == stale
    assert sorted(os.listdir(tmp_path)) == ["cwd", "out"]
    assert sorted(os.listdir(tmp_path / "out")) == sorted([SIDECAR, "model.onnx"])


def test_missing_parent_folders_of_the_target_are_created(tmp_path, stand_ins, model):
    export_model(model, tmp_path / "a" / "b" / "out", parity="none")
    assert (tmp_path / "a" / "b" / "out" / SIDECAR).is_file()


def test_an_unexpected_error_while_exporting_leaves_no_staging_folder(tmp_path, stand_ins, model, monkeypatch):
    def broken(graph, meta):
        raise OSError("disk full")

    monkeypatch.setattr(ex, "stamp", broken)
    with pytest.raises(OSError, match="disk full"):
        export_model(model, tmp_path / "out", parity="none")
    assert os.listdir(tmp_path) == []


def test_a_failed_export_removes_the_parent_folders_it_created_and_keeps_those_that_existed(tmp_path, stand_ins,
                                                                                           model):
    stand_ins.report = {"passed": False, "cases": [{"case": "224x224 b1", "worst_output": "conf1",
                                                    "worst_ratio": 2.0}]}
    (tmp_path / "mine").mkdir()
    with pytest.raises(CheckpointError, match="parity check failed"):
        export_model(model, tmp_path / "mine" / "a" / "b" / "out", parity="standard")
    assert os.listdir(tmp_path) == ["mine"] and os.listdir(tmp_path / "mine") == []


def test_a_failed_export_keeps_a_new_parent_folder_that_something_else_wrote_into_meanwhile(tmp_path, stand_ins,
                                                                                           model, monkeypatch):
    def broken(graph, meta):  # another writer fills the folder the export created, then the export fails
        (tmp_path / "a" / "theirs.txt").write_text("x")
        raise OSError("disk full")

    monkeypatch.setattr(ex, "stamp", broken)
    with pytest.raises(OSError, match="disk full"):
        export_model(model, tmp_path / "a" / "b" / "out", parity="none")
    assert os.listdir(tmp_path / "a") == ["theirs.txt"]


def test_replacing_a_split_export_by_a_single_graph_one_leaves_none_of_the_old_files(tmp_path, stand_ins, model):
    out = tmp_path / "out"
    out.mkdir()
    for f in (SIDECAR, "encoder.onnx", "decoder.onnx", "decoder.onnx.data"):
        (out / f).write_text("old")
    export_model(model, out, parity="none")
    assert sorted(os.listdir(out)) == sorted([SIDECAR, "model.onnx"]) and os.listdir(tmp_path) == ["out"]


def test_an_empty_folder_is_a_valid_target_and_is_filled(tmp_path, stand_ins, model):
    (tmp_path / "out").mkdir()
    assert check_target(tmp_path / "out", DEFAULT_OPSET) == tmp_path / "out"
    export_model(model, tmp_path / "out", parity="none")
    assert sorted(os.listdir(tmp_path / "out")) == sorted([SIDECAR, "model.onnx"])


# -- the target folder and the publish --------------------------------------------------------------------------
def test_an_exports_own_files_are_graphs_their_data_files_and_the_sidecar_and_the_rest_is_listed_sorted(tmp_path):
    for f in (SIDECAR, "model.onnx", "model.onnx.data", "zeta.txt", "alpha.txt"):
        (tmp_path / f).write_text("x")
    (tmp_path / "engine.onnx").mkdir()  # a folder is never an export's file, whatever its name
    assert _foreign_files(tmp_path) == ["alpha.txt", "engine.onnx", "zeta.txt"]


def test_an_export_listing_its_files_owns_those_alone_so_a_users_data_or_onnx_file_beside_them_is_foreign(tmp_path):
    for f in ("model.onnx", "model.onnx.data", "results.data", "mine.onnx"):
        (tmp_path / f).write_text("x")
    listed = {f: {"bytes": 1, "sha256": "0" * 64} for f in ("model.onnx", "model.onnx.data")}
    (tmp_path / SIDECAR).write_text(json.dumps({"format": FORMAT, "files": listed}))
    assert _foreign_files(tmp_path) == ["mine.onnx", "results.data"]
    with pytest.raises(CheckpointError, match=r"also holds \['mine.onnx', 'results.data'\]"):
        check_target(tmp_path, DEFAULT_OPSET)
    for text in ('{"format": "pointmap-onnx/1"}', "[1]", "{not json", '{"files": [1]}'):  # older or unreadable
        (tmp_path / SIDECAR).write_text(text)
        assert _foreign_files(tmp_path) == []


def test_a_folder_of_graphs_without_a_sidecar_is_not_an_export_and_is_refused(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "model.onnx").write_text("someone else's")
    with pytest.raises(CheckpointError, match="exists and is not a pointmap export"):
        check_target(tmp_path / "out", DEFAULT_OPSET)


def test_the_refusal_of_an_export_holding_other_files_names_up_to_five_of_them(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / SIDECAR).write_text("{}")
    for i in range(7):
        (out / f"note{i}.txt").write_text("mine")
    with pytest.raises(CheckpointError, match=r"\['note0.txt', 'note1.txt', 'note2.txt', 'note3.txt', 'note4.txt'\]"):
        check_target(out, DEFAULT_OPSET)


def test_publishing_to_a_new_folder_renames_the_staged_one_into_place(tmp_path):
    tmp, out = tmp_path / ".out.tmp", tmp_path / "out"
    tmp.mkdir()
    (tmp / "model.onnx").write_text("new")
    inode = tmp.stat().st_ino
    _atomic_publish(tmp, out)
    assert out.stat().st_ino == inode and not tmp.exists()  # renamed, not copied


def test_replacing_an_export_leaves_a_users_folder_named_like_a_backup_alone(tmp_path):
    out, tmp, backup = tmp_path / "exp", tmp_path / ".exp.tmp", tmp_path / "exp.old"
    for d in (out, tmp):
        d.mkdir()
        (d / SIDECAR).write_text("{}")
    backup.mkdir()
    (backup / "mine.txt").write_text("keep")
    _atomic_publish(tmp, out)
    assert (backup / "mine.txt").read_text() == "keep" and sorted(os.listdir(tmp_path)) == ["exp", "exp.old"]


def test_a_numpy_opset_reaches_the_exporter_and_the_sidecar_as_a_python_int(tmp_path, stand_ins, model):
    meta = export_model(model, tmp_path / "out", opset=np.int64(DEFAULT_OPSET), parity="none")
    assert type(stand_ins.export[0]["opset"]) is int and type(meta["opset"]) is int
    assert json.loads((tmp_path / "out" / SIDECAR).read_text())["opset"] == DEFAULT_OPSET


def test_the_newest_opset_onnx_knows_is_accepted_and_opsets_that_are_not_ints_are_refused(tmp_path):
    assert check_target(tmp_path / "a", TOP) == tmp_path / "a"
    assert check_target(tmp_path / "a", np.int64(DEFAULT_OPSET)) == tmp_path / "a"  # a NumPy int is an int
    for bad in (18.0, "18", True):
        with pytest.raises(ValueError, match="opset expected an int from 18"):
            check_target(tmp_path / "a", bad)


def test_a_blank_output_path_is_refused_as_empty(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match="out_dir expected a folder to export to, got an empty path"):
        check_target("  ", DEFAULT_OPSET)


# -- the bug the review found ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, value", [("split", "no"), ("split", 1), ("fp16", "false"), ("quiet", None),
                                         ("external_data", "no"), ("external_data", 0)])
def test_export_model_refuses_a_flag_that_is_not_true_or_false_naming_it_before_anything_is_exported(
        tmp_path, stand_ins, model, name, value):
    with pytest.raises(ValueError, match=f"{name} expected True or False.*got {value!r}"):
        export_model(model, tmp_path / "out", parity="none", **{name: value})
    assert stand_ins.export == [] and list(tmp_path.iterdir()) == []


def test_export_model_refuses_a_parity_that_is_not_a_name_with_the_parity_message(tmp_path, stand_ins, model):
    with pytest.raises(ValueError, match=r"parity expected one of \['full', 'quick', 'standard', 'none'\], "
                                         r"got \['quick'\]"):
        export_model(model, tmp_path / "out", parity=["quick"])
    assert stand_ins.export == []
