from dataclasses import fields

import pytest

from training.config import TrainConfig, field_comments


def test_every_training_flag_is_explained_in_help_by_its_config_comment_and_default(capsys):
    notes = field_comments(TrainConfig)
    assert sorted(notes) == sorted(f.name for f in fields(TrainConfig)), "a TrainConfig field without a comment"
    # a comment continued on the lines under its field is joined; the next field's comment is not taken with it
    assert notes["grown_lr"].startswith("... and the output projections") and \
        notes["grown_lr"].endswith("docs/training.md, Growing a model)")
    assert "confidence" not in notes["metric"]
    with pytest.raises(SystemExit) as stop:
        TrainConfig.from_args(["--help"], prog="python -m training.train")
    assert stop.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    assert out.startswith("usage: python -m training.train")
    assert "--match_weight MATCH_WEIGHT weight of the InfoNCE matching loss (default: 0.075)" in out
    assert "--compile BOOL torch.compile the training forward/backward (1.24x on 2 CPU threads;" in out
    for f in fields(TrainConfig):
        assert f"--{f.name} " in out


def test_a_binary_file_given_as_the_config_file_is_refused_in_one_line(tmp_path, capsys):
    # e.g. a checkpoint passed as --config: its bytes are not UTF-8 (a raw UnicodeDecodeError traceback before)
    (tmp_path / "last.pt").write_bytes(b"PK\x03\x04\xff\xfe\x00\x81binary")
    with pytest.raises(SystemExit) as stop:
        TrainConfig.from_args(["--data", "x", "--config", str(tmp_path / "last.pt")])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "not a readable JSON file" in err and "Traceback" not in err


def test_a_held_out_set_that_is_also_a_training_set_is_refused_in_one_line(tmp_path, capsys):
    # before, --eval_data train_b with --data train_a,train_b reported held-out metrics on pairs the run trained on
    a, b = str(tmp_path / "train_a"), str(tmp_path / "train_b")
    for data, held_out in [(a, a), (f"{a},{b}", str(tmp_path / "x" / ".." / "train_b"))]:
        with pytest.raises(SystemExit) as stop:
            TrainConfig.from_args(["--data", data, "--eval_data", held_out])
        assert stop.value.code == 2
        err = capsys.readouterr().err
        assert "--eval_data expected held-out shards (never trained on)" in err and "Traceback" not in err
    assert TrainConfig.from_args(["--data", a, "--eval_data", str(tmp_path / "eval")]).eval_data == str(tmp_path / "eval")


@pytest.mark.parametrize("flags, message", [
    (["--n_corr", "7"], "--n_corr expected >= 8 (the matching losses leave out a pair with fewer"),
    (["--seed=-1"], "--seed expected an int in [0, 2**31), got -1"),
    (["--seed", str(2 ** 32)], "--seed expected an int in [0, 2**31)"),
    (["--coarse_temperature", "0.2", "--coarse_weight", "0"], "--coarse_temperature 0.2 sets a loss that is off: it "
                                                               "needs --coarse_weight > 0"),
    (["--attn_heads", "2"], "--attn_heads 2 sets a loss that is off: it needs --attn_weight > 0"),
    (["--desc_conf_alpha", "5"], "--desc_conf_alpha 5.0 sets a loss that is off: it needs --desc_conf_weight > 0"),
    (["--temperature", "0.1", "--match_weight", "0"], "--temperature 0.1 sets a loss that is off"),
    (["--n_corr", "64", "--match_weight", "0"], "--n_corr 64 sets the matching losses, which are off"),
    (["--keep_decay", "false"], "--keep_decay false acts on resuming a --decay_by_time run"),
])
def test_flags_out_of_range_or_of_a_loss_that_is_off_are_refused_in_one_line(flags, message, capsys):
    # before: n_corr < 8 trained no matching at all, a seed out of numpy's range crashed after setup, and settings
    # of switched-off losses were silently ignored
    with pytest.raises(SystemExit) as stop:
        TrainConfig.from_args(["--data", "x", *flags])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_settings_of_losses_that_are_on_are_taken():
    cfg = TrainConfig.from_args(["--data", "x", "--n_corr", "8", "--seed", str(2 ** 31 - 1), "--attn_weight", "0.5",
                                 "--attn_heads", "2", "--desc_conf_weight", "0.1", "--desc_conf_alpha", "5",
                                 "--match_weight", "0", "--n_corr", "64", "--schedule", "wsd", "--steps", "100",
                                 "--warmup", "10", "--decay_steps", "20", "--decay_by_time", "true", "--max_minutes", "5",
                                 "--keep_decay", "false"])
    assert (cfg.n_corr, cfg.attn_heads, cfg.desc_conf_alpha, cfg.keep_decay) == (64, 2, 5.0, False)


def test_evaluation_settings_without_a_held_out_set_are_warned_about(tmp_path, capsys):
    # before, --eval_every 500 without --eval_data ran without a single evaluation and said nothing
    cfg = TrainConfig.from_args(["--data", "x", "--eval_every", "500", "--eval_pairs", "32"])
    assert (cfg.eval_every, cfg.eval_pairs) == (500, 32)
    assert "warning: --eval_every 500 and --eval_pairs 32 without --eval_data: the run evaluates nothing" in \
        capsys.readouterr().err
    for flags in (["--eval_every", "500", "--eval_data", str(tmp_path / "eval")], []):
        TrainConfig.from_args(["--data", "x", *flags])
        assert "evaluates nothing" not in capsys.readouterr().err
