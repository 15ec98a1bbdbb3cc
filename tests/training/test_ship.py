"""training.ship: a training checkpoint (or the average of several) becomes a model file load_model reads."""

import warnings
from dataclasses import replace

import pytest
import torch

import pointmap as pm
from pointmap.model import PRESETS, PointmapNet
from training.config import TrainConfig
from training.ship import average_checkpoints, main


def _checkpoint(path, seed, step, cfg=PRESETS["test"], kind="train", extra=None, run_seed=0):
    torch.manual_seed(seed)
    model = PointmapNet(cfg)
    torch.save({"model": model.state_dict(), "model_config": model.cfg.to_dict(), "step": step, "kind": kind,
                "train_config": TrainConfig(seed=run_seed).to_dict(), **({"extra": extra} if extra is not None else {})},
               path)
    return model


def test_a_shipped_checkpoint_loads_back_as_the_same_model_in_fp16(tmp_path):
    model = _checkpoint(tmp_path / "a.pt", seed=0, step=7)
    assert main(["--ckpt", str(tmp_path / "a.pt"), "--out", str(tmp_path / "m.safetensors"), "--note", "n"]) == 0
    back = pm.load_model(tmp_path / "m.safetensors")
    assert back.provenance["steps"] == 7 and "averaged_steps" not in back.provenance
    for k, v in model.state_dict().items():
        if v.is_floating_point():
            torch.testing.assert_close(back.state_dict()[k].float(), v.half().float())


def test_several_checkpoints_ship_their_weight_average_as_averaging_by_hand_gives(tmp_path):
    models = [_checkpoint(tmp_path / f"{i}.pt", seed=i, step=100 * (i + 1)) for i in range(3)]
    paths = [str(tmp_path / f"{i}.pt") for i in range(3)]
    ck = average_checkpoints(paths)
    assert ck["step"] == 300 and ck["averaged_steps"] == [100, 200, 300]
    for k, v in models[0].state_dict().items():  # the reference: each tensor summed by hand
        if v.is_floating_point():
            by_hand = (models[0].state_dict()[k].double() + models[1].state_dict()[k].double()
                       + models[2].state_dict()[k].double()) / 3
            torch.testing.assert_close(ck["model"][k].double(), by_hand, rtol=1e-6, atol=1e-7)
    assert main(["--ckpt", *paths, "--out", str(tmp_path / "avg.safetensors")]) == 0
    assert pm.load_model(tmp_path / "avg.safetensors").provenance["averaged_steps"] == [100, 200, 300]


def test_averaging_refuses_checkpoints_of_other_architectures_or_kinds_in_one_line(tmp_path, capsys):
    _checkpoint(tmp_path / "a.pt", seed=0, step=1)
    _checkpoint(tmp_path / "b.pt", seed=1, step=2, cfg=replace(PRESETS["test"], enc_depth=3))
    _checkpoint(tmp_path / "c.pt", seed=1, step=2, kind="pretrain")
    with pytest.raises(pm.CheckpointError, match="another architecture"):
        average_checkpoints([tmp_path / "a.pt", tmp_path / "b.pt"])
    with pytest.raises(pm.CheckpointError, match="'pretrain' checkpoint"):
        average_checkpoints([tmp_path / "a.pt", tmp_path / "c.pt"])
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    for bad in ("b.pt", "junk.pt"):
        assert main(["--ckpt", str(tmp_path / "a.pt"), str(tmp_path / bad), "--out", str(tmp_path / "x.safetensors")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error:") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.safetensors").exists()


def test_a_checkpoint_ships_in_int8_at_about_half_the_fp16_size_and_loads_as_float(tmp_path):
    cfg = replace(PRESETS["test"], enc_dim=64, dec_dim=64, enc_heads=4, dec_heads=4)  # matrices worth quantizing
    model = _checkpoint(tmp_path / "a.pt", seed=0, step=7, cfg=cfg)
    assert main(["--ckpt", str(tmp_path / "a.pt"), "--out", str(tmp_path / "m16.safetensors")]) == 0
    assert main(["--ckpt", str(tmp_path / "a.pt"), "--out", str(tmp_path / "m8.safetensors"), "--dtype", "int8"]) == 0
    size16, size8 = (tmp_path / "m16.safetensors").stat().st_size, (tmp_path / "m8.safetensors").stat().st_size
    assert size8 < 0.65 * size16
    back = pm.load_model(tmp_path / "m8.safetensors")
    w = model.state_dict()["enc_blocks.0.mlp.fc1.weight"]
    got = back.state_dict()["enc_blocks.0.mlp.fc1.weight"]
    assert got.dtype == torch.float32 and not torch.equal(got, w)
    assert ((got - w).abs() <= w.abs().amax(dim=1, keepdim=True) / 254 + 1e-7).all()  # half a step per channel


def test_the_growth_history_a_run_records_ships_in_the_provenance(tmp_path):
    _checkpoint(tmp_path / "g.pt", seed=0, step=5, extra={"grown_from": [{"enc_depth": 1, "dec_depth": 2}]})
    _checkpoint(tmp_path / "p.pt", seed=0, step=5, extra={"grown_from": []})
    for name in ("g", "p"):
        assert main(["--ckpt", str(tmp_path / f"{name}.pt"), "--out", str(tmp_path / f"{name}.safetensors")]) == 0
    assert pm.load_model(tmp_path / "g.safetensors").provenance["grown_from"] == [{"enc_depth": 1, "dec_depth": 2}]
    assert pm.load_model(tmp_path / "p.safetensors").provenance["grown_from"] == []  # never grown, and it says so


def test_the_shipped_licence_is_the_projects_unless_an_input_records_another_which_it_keeps(tmp_path, capsys):
    from pointmap.checkpoint import OFFICIAL_LICENCE

    _checkpoint(tmp_path / "own.pt", seed=0, step=5)
    _checkpoint(tmp_path / "nc.pt", seed=1, step=6, extra={"licence": OFFICIAL_LICENCE})
    nc_file = PointmapNet(PRESETS["test"])
    nc_file.provenance = {"steps": 3, "licence": OFFICIAL_LICENCE}
    pm.save_model(nc_file, tmp_path / "nc.safetensors")

    def shipped(*args):
        assert main([*args, "--out", str(tmp_path / "m.safetensors")]) == 0
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            licence = pm.load_model(tmp_path / "m.safetensors").provenance["licence"]
        # the loader warns exactly when the shipped file carries the non-commercial licence
        assert any("non-commercial use only" in str(w.message) for w in seen) == (OFFICIAL_LICENCE in licence)
        return licence

    assert shipped("--ckpt", str(tmp_path / "own.pt")) == "Apache-2.0"
    assert shipped("--ckpt", str(tmp_path / "nc.pt")) == OFFICIAL_LICENCE
    assert shipped("--ckpt", str(tmp_path / "nc.safetensors"), str(tmp_path / "own.pt")) == OFFICIAL_LICENCE
    # an input with no share adds nothing, its licence neither
    assert shipped("--ckpt", str(tmp_path / "nc.safetensors"), str(tmp_path / "own.pt"), "--weights", "0", "1") \
        == "Apache-2.0"
    _checkpoint(tmp_path / "mixed.pt", seed=2, step=7, extra={"licence": f"Apache-2.0 AND {OFFICIAL_LICENCE}"})
    assert shipped("--ckpt", str(tmp_path / "mixed.pt"), str(tmp_path / "nc.pt")) == f"Apache-2.0 AND {OFFICIAL_LICENCE}"
    assert main(["--ckpt", str(tmp_path / "nc.pt"), "--licence", "MIT", "--out", str(tmp_path / "x.safetensors")]) == 2
    assert "--licence MIT: the weights derive from ones licensed CC-BY-NC-SA-4.0" in capsys.readouterr().err
    assert not (tmp_path / "x.safetensors").exists()


def test_shipping_refuses_a_metrics_file_that_is_missing_or_not_an_eval_csv_in_one_line(tmp_path, capsys):
    ck = tmp_path / "a.pt"
    _checkpoint(ck, 0, 100)
    (tmp_path / "bad.csv").write_text("step,RRA15\n100,lots\n")
    (tmp_path / "train.csv").write_text("step,time,loss,grad_norm,lr\n100,5.0,1.2,0.3,0.0001\n")
    for metrics, message in [(tmp_path / "nope.csv", "which is not a file"),
                             (tmp_path / "bad.csv", "its row of step 100 is not all numbers"),
                             (tmp_path / "train.csv", "this is a run's train.csv (training losses); expected its")]:
        assert main(["--ckpt", str(ck), "--name", "x", "--metrics", str(metrics), "--out",
                     str(tmp_path / "x.safetensors")]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.safetensors").exists()



def test_shipping_refuses_a_name_that_is_a_path_whatever_out_is_in_one_line(tmp_path, capsys):
    ck = tmp_path / "a.pt"
    _checkpoint(ck, 0, 100)
    for name in ("../small", "a/b", "..", "", " ", " small"):
        for out in ([], ["--out", str(tmp_path / "x.safetensors")]):
            assert main(["--ckpt", str(ck), "--name", name, *out]) == 2
            err = capsys.readouterr().err
            assert f"expected a bare name (no path separator, not '.', '..' or blank, no surrounding spaces), got " \
                   f"{name!r}" in err
            assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.safetensors").exists()
    assert main(["--ckpt", str(ck), "--name", "tiny_v2", "--out", str(tmp_path / "x.safetensors")]) == 0
    assert pm.load_model(tmp_path / "x.safetensors").provenance["name"] == "tiny_v2"

def test_a_model_file_averages_with_checkpoints_at_the_shares_weights_give_as_by_hand(tmp_path):
    start = _checkpoint(tmp_path / "s.pt", seed=0, step=50)
    assert main(["--ckpt", str(tmp_path / "s.pt"), "--out", str(tmp_path / "start.safetensors")]) == 0  # fp16
    tuned = [_checkpoint(tmp_path / f"{i}.pt", seed=i + 1, step=100 * (i + 1)) for i in range(2)]
    inputs = [str(tmp_path / "start.safetensors"), str(tmp_path / "0.pt"), str(tmp_path / "1.pt")]
    ck = average_checkpoints(inputs, weights=[2, 1, 1])
    assert ck["step"] == 200 and ck["averaged_steps"] == [100, 200]
    assert [(d["kind"], d["share"]) for d in ck["averaged"]] == [("model", 0.5), ("train", 0.25), ("train", 0.25)]
    for k, v in start.state_dict().items():  # the reference: the model file read back as float, then by hand
        if v.is_floating_point():
            by_hand = (2 * v.half().double() + tuned[0].state_dict()[k].double()
                       + tuned[1].state_dict()[k].double()) / 4
            torch.testing.assert_close(ck["model"][k].double(), by_hand, rtol=1e-6, atol=1e-7)
    assert main(["--ckpt", *inputs, "--weights", "2", "1", "1", "--out", str(tmp_path / "w.safetensors")]) == 0
    back = pm.load_model(tmp_path / "w.safetensors").provenance
    assert back["steps"] == 200 and [d["source"].split("/")[-1] for d in back["averaged"]] == [
        "start.safetensors", "0.pt", "1.pt"]


def test_averaging_refuses_bad_weights_and_model_files_alone_in_one_line(tmp_path, capsys):
    _checkpoint(tmp_path / "a.pt", seed=0, step=1)
    _checkpoint(tmp_path / "b.pt", seed=1, step=2)
    assert main(["--ckpt", str(tmp_path / "a.pt"), "--out", str(tmp_path / "m.safetensors")]) == 0
    two = [str(tmp_path / "a.pt"), str(tmp_path / "b.pt")]
    for weights, message in [(["1"], "one weight per checkpoint"), (["1", "-1"], "non-negative"),
                             (["0", "0"], "positive sum"), (["1", "nan"], "non-negative finite")]:
        assert main(["--ckpt", *two, "--weights", *weights, "--out", str(tmp_path / "x.safetensors")]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1
    with pytest.raises(pm.CheckpointError, match="at least one training checkpoint"):
        average_checkpoints([tmp_path / "m.safetensors"])
    with pytest.raises(pm.CheckpointError, match="model file not found"):
        average_checkpoints([tmp_path / "a.pt", tmp_path / "gone.safetensors"])
    with pytest.raises(pm.CheckpointError, match="one number per checkpoint"):
        average_checkpoints(two, weights=["x", 1])


def test_the_shipped_file_records_the_latest_step_whatever_order_the_shell_gives_the_checkpoints(tmp_path):
    for step in (9000, 9500, 10000):
        _checkpoint(tmp_path / f"decay_{step}.pt", seed=step, step=step)
    in_text_order = sorted(str(p) for p in tmp_path.glob("decay_*.pt"))  # decay_10000.pt comes first
    ck = average_checkpoints(in_text_order)
    assert ck["step"] == 10000 and sorted(ck["averaged_steps"]) == [9000, 9500, 10000]
    assert average_checkpoints(in_text_order, weights=[0, 1, 1])["step"] == 9500  # a state with no share is not it


def test_the_provenance_tells_apart_inputs_of_the_same_name_from_two_runs(tmp_path):
    for run, seed in (("run_a", 0), ("run_b", 1)):
        (tmp_path / run / "train").mkdir(parents=True)
        _checkpoint(tmp_path / run / "train" / "decay_100.pt", seed=seed, step=100, run_seed=seed)
    paths = [tmp_path / run / "train" / "decay_100.pt" for run in ("run_a", "run_b")]
    with pytest.warns(UserWarning, match="the checkpoints come from different runs: their seed differ"):
        ck = average_checkpoints(paths)
    assert [d["seed"] for d in ck["averaged"]] == [0, 1]  # each input's run recorded
    assert [d["source"] for d in ck["averaged"]] == ["run_a/train/decay_100.pt", "run_b/train/decay_100.pt"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one run: nothing to warn about
        _checkpoint(tmp_path / "run_a" / "train" / "decay_200.pt", seed=2, step=200, run_seed=0)
        one = average_checkpoints([paths[0], tmp_path / "run_a" / "train" / "decay_200.pt"])  # one run: short names
    assert [d["source"] for d in one["averaged"]] == ["train/decay_100.pt", "train/decay_200.pt"]


def test_an_older_checkpoint_without_the_newer_config_fields_averages_with_a_model_file(tmp_path):
    _checkpoint(tmp_path / "a.pt", seed=0, step=1)
    assert main(["--ckpt", str(tmp_path / "a.pt"), "--out", str(tmp_path / "m.safetensors")]) == 0
    old = torch.load(tmp_path / "a.pt", weights_only=True)
    for k in ("pose_head", "desc_stem"):  # fields added to ModelConfig later, at their defaults
        old["model_config"].pop(k)
    torch.save(old, tmp_path / "old.pt")
    ck = average_checkpoints([tmp_path / "m.safetensors", tmp_path / "old.pt"])
    assert ck["step"] == 1 and [d["source"] for d in ck["averaged"]] == [f"{tmp_path.name}/m.safetensors",
                                                                          f"{tmp_path.name}/old.pt"]
    assert not (tmp_path / "x.safetensors").exists()


def test_shipping_records_the_metrics_row_of_the_shipped_step_and_warns_when_there_is_none(tmp_path, capsys):
    ck = tmp_path / "a.pt"
    _checkpoint(ck, 0, 120)  # e.g. a run stopped by SIGTERM at step 120 after its last evaluation at 100
    (tmp_path / "eval.csv").write_text("step,RRA15\n100,50.0\n")
    assert main(["--ckpt", str(ck), "--metrics", str(tmp_path / "eval.csv"), "--out",
                 str(tmp_path / "x.safetensors")]) == 0
    assert ("it has no row of the shipped weights' step 120; its last row is step 100: the recorded held-out metrics "
            "are an earlier state's") in capsys.readouterr().err
    # the row of the shipped step is recorded, not the last one (a stable checkpoint shipped from a run evaluated on)
    (tmp_path / "eval.csv").write_text("step,RRA15\n100,50.0\n120,51.0\n120,51.5\n140,60.0\n")
    assert main(["--ckpt", str(ck), "--metrics", str(tmp_path / "eval.csv"), "--out",
                 str(tmp_path / "y.safetensors")]) == 0
    assert "warning" not in capsys.readouterr().err
    assert pm.load_model(tmp_path / "y.safetensors").provenance["heldout_metrics"] == {"step": 120.0, "RRA15": 51.5}
    (tmp_path / "eval.csv").write_text("step,RRA15\n140,60.0\n")
    assert main(["--ckpt", str(ck), "--metrics", str(tmp_path / "eval.csv"), "--out",
                 str(tmp_path / "z.safetensors")]) == 0
    assert "its last row is step 140: the recorded held-out metrics are a later state's" in capsys.readouterr().err


def test_an_eval_csv_whose_last_row_has_no_step_is_refused_in_one_line(tmp_path, capsys):
    ck = tmp_path / "a.pt"
    _checkpoint(ck, 0, 100)
    (tmp_path / "eval.csv").write_text("step,RRA15\n100,50.0\n,51.0\n")
    assert main(["--ckpt", str(ck), "--metrics", str(tmp_path / "eval.csv"), "--out", str(tmp_path / "x.safetensors")]) == 2
    err = capsys.readouterr().err
    assert "at least one row with its step" in err and len(err.strip().splitlines()) == 1


def test_shipping_names_the_input_with_nan_weights_and_refuses_what_it_cannot_record_in_one_line(
        tmp_path, capsys):
    good = _checkpoint(tmp_path / "good.pt", 0, 100)
    ck = torch.load(tmp_path / "good.pt", weights_only=False)
    name = next(k for k, v in ck["model"].items() if v.is_floating_point())
    ck["model"][name] = torch.full_like(ck["model"][name], float("nan"))
    torch.save(ck, tmp_path / "nan.pt")
    for weights in (["1", "1"], ["1", "0"]):  # a corrupt input is refused, even one given no share
        assert main(["--ckpt", str(tmp_path / "good.pt"), str(tmp_path / "nan.pt"), "--weights", *weights, "--out",
                     str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err
        assert "nan.pt holds NaN or inf weights" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.safetensors").exists()
    ck["model"][name] = good.state_dict()[name]
    del ck["train_config"]
    torch.save(ck, tmp_path / "bare.pt")
    (tmp_path / "folder").mkdir()
    for args, message in (([str(tmp_path / "bare.pt"), "--weights", "1"], "the run's train_config"),
                          ([str(tmp_path / "good.pt"), "--out", str(tmp_path / "folder")],
                           "--out expected a file to write the weights to, got the folder")):
        if "--out" not in args:
            args += ["--out", str(tmp_path / "y")]
        assert main(["--ckpt", *args]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1


def test_an_averages_metrics_are_recorded_as_one_inputs_and_zero_share_inputs_are_not_averaged_steps(tmp_path, capsys):
    for i, step in enumerate((100, 200)):
        _checkpoint(tmp_path / f"{i}.pt", seed=i, step=step)
    (tmp_path / "eval.csv").write_text("step,RRA15\n200,50.0\n")
    paths = [str(tmp_path / "0.pt"), str(tmp_path / "1.pt")]
    assert main(["--ckpt", *paths, "--weights", "1", "3", "--metrics", str(tmp_path / "eval.csv"), "--out",
                 str(tmp_path / "avg.safetensors")]) == 0
    assert "its row is step 200's" in capsys.readouterr().err
    prov = pm.load_model(tmp_path / "avg.safetensors").provenance
    assert "heldout_metrics" not in prov and prov["heldout_metrics_of_input"]["RRA15"] == 50.0
    assert prov["heldout_metrics_of_input"]["source"].endswith("1.pt")  # the input of step 200, in any order
    assert main(["--ckpt", paths[1], paths[0], "--metrics", str(tmp_path / "eval.csv"), "--out",
                 str(tmp_path / "rev.safetensors")]) == 0
    rev = pm.load_model(tmp_path / "rev.safetensors").provenance["heldout_metrics_of_input"]
    assert rev["source"].endswith("1.pt")
    assert main(["--ckpt", *paths, "--out", str(tmp_path / "none.safetensors")]) == 0  # no --metrics: no entry
    none = pm.load_model(tmp_path / "none.safetensors").provenance
    assert not none.get("heldout_metrics") and "heldout_metrics_of_input" not in none
    assert average_checkpoints(paths, [1, 0])["averaged_steps"] == [100]


def test_a_model_file_shipped_with_every_training_checkpoint_at_share_zero_is_refused_in_one_line(tmp_path, capsys):
    # before: the weights were the model file's alone and the file recorded b.pt's run (step 500, its config)
    _checkpoint(tmp_path / "a.pt", seed=0, step=1)
    assert main(["--ckpt", str(tmp_path / "a.pt"), "--out", str(tmp_path / "m.safetensors")]) == 0
    _checkpoint(tmp_path / "b.pt", seed=1, step=500)
    assert main(["--ckpt", str(tmp_path / "m.safetensors"), str(tmp_path / "b.pt"), "--weights", "1", "0",
                 "--out", str(tmp_path / "x.safetensors")]) == 2
    err = capsys.readouterr().err
    assert "expected a training checkpoint (.pt) with a share > 0" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.safetensors").exists()


def test_two_inputs_holding_the_same_weights_are_refused_naming_both(tmp_path, capsys):
    # a run's last.pt is its last decay_<step>.pt: `--ckpt run/*.pt` gave that state twice the share, silently
    _checkpoint(tmp_path / "decay_4.pt", seed=0, step=4)
    _checkpoint(tmp_path / "decay_3.pt", seed=1, step=3)
    _checkpoint(tmp_path / "last.pt", seed=0, step=4)
    paths = [str(tmp_path / n) for n in ("decay_3.pt", "decay_4.pt", "last.pt")]
    assert main(["--ckpt", *paths, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert f"{paths[1]} and {paths[2]} hold the same weights" in err and len(err.strip().splitlines()) == 1
    assert main(["--ckpt", *paths[:2], "--weights", "1", "2", "--out", str(tmp_path / "y")]) == 0
