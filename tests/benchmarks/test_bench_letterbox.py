import pytest
import torch

from benchmarks.bench_letterbox import band, crop_to, main, pad_to, whole


def test_the_band_is_the_central_four_by_three_strip_and_padding_puts_it_back_with_a_mask_of_exactly_it():
    img = torch.rand(3, 64, 64)
    land, port = band(img, "landscape"), band(img, "portrait")
    assert land.shape == (3, 48, 64) and port.shape == (3, 64, 48)
    assert torch.equal(land, img[:, 8:56]) and torch.equal(port, img[:, :, 8:56])
    padded, mask = pad_to(land, 64, 0.25)
    assert torch.equal(padded[:, 8:56], img[:, 8:56]) and bool((padded[:, :8] == 0.25).all())
    assert mask.sum() == 48 * 64 and bool((mask[8:56] == 1).all()) and bool((mask[:8] == 0).all())
    # the crop of a band is the render's own centre square, resized: of an already square band, the image itself
    assert torch.allclose(crop_to(img, 64), img.clamp(0, 1), atol=1e-5)
    assert crop_to(land, 64).shape == (3, 64, 64)
    # whole: the band as it is, its sides cut to whole patches about the centre (56 -> 48 rows)
    assert torch.equal(whole(land), land) and torch.equal(whole(img[:, 4:60]), img[:, 8:56])


def test_the_letterbox_benchmark_scores_every_pair_kind_both_ways_and_refuses_bad_pad_values(scenes_and_model,
                                                                                             capsys):
    data, model_path = scenes_and_model
    assert main(["--data", str(data), "--model", str(model_path), "--pairs", "2", "--size", "64",
                 "--pad-values", "0,0.5"]) == 0
    rows = {}
    for line in capsys.readouterr().out.splitlines()[2:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        rows[(cells[0], cells[1])] = cells
    kinds = ("landscape + landscape", "portrait + portrait", "landscape + portrait")
    assert set(rows) == {("whole square render", "-")} | {(k, m) for k in kinds for m in ("crop", "whole", "pad 0", "pad 0.5")}
    assert all(r[2] == "2" and 0 <= float(r[3].rstrip("%")) <= 100 for r in rows.values())
    # both same-orientation crops are the render's centre square: the same input, the same errors
    assert rows[(kinds[0], "crop")][3:] == rows[(kinds[1], "crop")][3:]
    for bad in ("2", "x"):
        with pytest.raises(SystemExit):
            main(["--data", str(data), "--model", str(model_path), "--pad-values", bad])
    assert main(["--data", str(data / "missing"), "--model", str(model_path)]) == 2
    assert "error:" in capsys.readouterr().err
