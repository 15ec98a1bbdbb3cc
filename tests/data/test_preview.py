import pytest

from data.preview import contact_sheet, main


def test_a_contact_sheet_has_a_row_per_scene_up_to_the_row_limit(tiny_pairs):
    shard = str(sorted(tiny_pairs.glob("shard-*.tar"))[0])
    assert contact_sheet(shard, max_rows=1, seed=3).shape[0] < contact_sheet(shard, max_rows=2, seed=3).shape[0]


def test_a_negative_seed_is_refused_in_one_line_like_a_bad_row_count(tiny_pairs, tmp_path, capsys):
    shard = str(sorted(tiny_pairs.glob("shard-*.tar"))[0])
    out = tmp_path / "p.png"
    for flag, value, text in (("--seed", "-1", "--seed expected an int >= 0, got -1"),
                              ("--rows", "0", "--rows expected >= 1, got 0")):
        with pytest.raises(SystemExit) as e:
            main([shard, "-o", str(out), flag, value])
        assert e.value.code == 2 and text in capsys.readouterr().err and not out.exists()
    for kw, text in (({"seed": -1}, "seed expected an int >= 0, got -1"), ({"seed": 1.5}, "seed expected an int"),
                     ({"max_rows": 0}, "max_rows expected an int >= 1, got 0"),
                     ({"max_rows": True}, "max_rows expected an int >= 1, got True")):
        with pytest.raises(ValueError, match=text):
            contact_sheet(shard, **kw)
    assert main([shard, "-o", str(out), "--seed", "0"]) == 0 and out.is_file()


def test_a_dataset_folder_given_for_a_shard_is_named_as_a_folder(tiny_pairs, tmp_path, capsys):
    # before: "error: DIR does not exist", for a folder that exists
    assert main([str(tiny_pairs), "-o", str(tmp_path / "p.png")]) == 2
    assert f"{tiny_pairs} is a folder: expected one shard-NNNNNN.tar of a dataset" in capsys.readouterr().err
