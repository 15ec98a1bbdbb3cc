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
