import json

import pytest

from benchmarks.compare_cards import CardError, compare, main, parse_card


def _card(rra_s42, rra_p4, rra_all, cam=None, fwd=None, moto=False):
    ev = {"size": 224, "RTA15": 10.0, "rot_err_med": 14.0, "trans_err_med": 50.0, "AbsRel": 0.3,
          "depth_ratio_err": 0.2, "match_prec": 0.12, "RRA15_matches": 44.0, "pairs": 100.0}
    if fwd is not None:
        ev["fwd_corr"] = fwd
    lines = ["== eval_s424242", json.dumps({**ev, "RRA15": rra_s42}),
             "== eval_p4_s434343", json.dumps({**ev, "RRA15": rra_p4})]
    if cam is None:
        lines += ["== eval_cam_s464646: skipped (missing)"]
    else:
        lines += ["== eval_cam_s464646", json.dumps({**ev, "RRA15": cam, "pairs": 50.0})]
    lines += ["== bench_s525252", "200 held-out pairs", "",
              "| category | pairs | method | RRA@15 | RTA@15 | median rot err | median dir err |",
              "|---|---|---|---|---|---|---|",
              f"| all | 200 | model | {rra_all}% | 8% | 14.3 | 54.1 |",
              "| all | 200 | sift+E (known K) | 22% | 9% | 173.1 | 137.9 |",
              "| all | 200 | no rotation | 18% | - | 34.3 | - |",
              "| low-texture | 77 | model | 53% | 9% | 14.2 | 47.9 |",
              "== real",
              "| stereo rig | 13 | model (own pointmaps, no K) | 85% | 0% | 9.3 | 39.4 |",
              "| stereo rig | 13 | SIFT+E (known K) | 100% | 77% | 1.5 | 4.5 |",
              "stereo rig, model focal (no K given) vs calibrated: median relative error 3.8%",
              "| model (1 / depth of view 1) | 22.5 | 0.43 | 96% |"]
    if moto:  # bench_real.py with scikit-image's Middlebury pair
        lines += ["| motorcycle (rectified) | 1 | model (own pointmaps, no K) | 100% | 0% | 1.8 | 36.8 |",
                  "| motorcycle (rectified) | 1 | SIFT+E (known K) | 100% | 100% | 0.5 | 3.2 |",
                  "motorcycle, model focal (no K given) vs calibrated: relative error 50.2%",
                  "| method | AbsRel | Pearson r | pixels scored |",
                  "| model (depth of view 1) | 0.187 | 0.31 | 93% |",
                  "| StereoSGBM (true calibration) | 0.028 | 0.97 | 77% |"]
    return "\n".join(lines)


def test_a_card_is_read_back_into_the_figures_the_card_script_printed():
    c = parse_card(_card(54.0, 73.0, 52, cam=44.0, fwd=0.17))
    assert c["eval"]["eval_s424242"]["RRA15"] == 54.0 and c["eval"]["eval_cam_s464646"]["fwd_corr"] == 0.17
    assert c["bench"]["all"] == (200, 52.0, 8.0, 14.3) and c["bench"]["low-texture"][1] == 53.0
    assert c["sift"] == (22.0, 9.0) and c["rig"] == (9.3, 39.4) and c["focal"] == 3.8 and c["aloe_r"] == 0.43
    assert c["moto"] is None and c["moto_absrel"] is None


def test_the_middlebury_motorcycle_rows_are_read_apart_from_the_rig_and_shown_only_when_a_card_has_them():
    c = parse_card(_card(54.0, 73.0, 52, moto=True))
    assert c["moto"] == (1.8, 36.8) and c["moto_focal"] == 50.2 and c["moto_absrel"] == 0.187 and c["moto_r"] == 0.31
    assert c["rig"] == (9.3, 39.4) and c["focal"] == 3.8 and c["aloe_r"] == 0.43  # the rig's figures untouched
    without = parse_card(_card(54.0, 73.0, 52))
    assert "motorcycle" not in compare([without, without], ["a", "b"])
    table = compare([without, c], ["old", "new"])
    assert "| motorcycle: depth AbsRel | - | 0.187 |" in table and "| motorcycle: focal error % | - | 50.2 |" in table


def test_the_comparison_counts_pairs_within_15_degrees_over_the_card_sets_and_marks_what_a_card_lacks():
    old, new = parse_card(_card(50.0, 70.0, 50)), parse_card(_card(60.0, 70.0, 51, cam=40.0, fwd=0.4))
    table = compare([old, new], ["old", "new"])
    # 50 + 70 + 100 of 400 against 60 + 70 + 102; with eval_cam only where every card has it
    assert "| rotation within 15 deg, pairs over eval_s424242 + eval_p4_s434343 + bench_s525252 | 220 / 400 | " \
           "232 / 400 |" in table
    assert "eval_cam_s464646 + bench_s525252 | - | 252 / 450 |" in table
    assert "| `eval_s424242` fwd_corr | - | 0.40 |" in table


def test_the_comparison_refuses_text_that_is_not_a_card(tmp_path, capsys):
    with pytest.raises(CardError, match="model_card.sh"):
        parse_card("just some log\nwith no sections\n")
    (tmp_path / "junk.txt").write_text("nothing here")
    assert main([str(tmp_path / "junk.txt")]) == 2
    assert capsys.readouterr().err.startswith("error: expected the output of benchmarks/model_card.sh")
    (tmp_path / "bad.txt").write_text(_card(50.0, 70.0, 50).replace("| 14.3 |", "| n/a |"))
    assert main([str(tmp_path / "bad.txt")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and len(err.strip().splitlines()) == 1
    with pytest.raises(SystemExit):
        main([str(tmp_path / "junk.txt"), "--names", "a", "b"])


def test_the_pipelines_pose_rows_are_read_and_totalled_apart_and_missing_on_older_cards():
    older = parse_card(_card(50.0, 70.0, 50))
    text = _card(50.0, 70.0, 50)
    text = text.replace('"pairs": 100.0,', '"pairs": 100.0, "RRA15_pair": 52.0, "RTA15_pair": 20.0,')
    text = text.replace("| all | 200 | sift+E", "| all | 200 | model + own matches (no K) | 51% | 12% | 14.0 | 40.0 |\n"
                                                "| all | 200 | sift+E")
    text = text.replace("| stereo rig | 13 | SIFT+E", "| stereo rig | 13 | model + own matches (no K) | 85% | 0% | 9.4 | 43.4 |"
                                                      "\n| stereo rig | 13 | SIFT+E")
    newer = parse_card(text)
    assert newer["bench"] == older["bench"] and newer["rig"] == older["rig"]  # the pointmap pose's rows untouched
    assert newer["bench_pair"]["all"] == (200, 51.0, 12.0, 14.0) and newer["rig_pair"] == (9.4, 43.4)
    assert older["bench_pair"] == {} and older["rig_pair"] is None
    table = compare([older, newer], ["old", "new"])
    # 52 + 52 + 102 rotations and 20 + 20 + 24 directions of 400; the older card has no such pose
    assert "| rotation within 15 deg, the pipeline's pose, pairs over eval_s424242 + eval_p4_s434343 + " \
           "bench_s525252 | - | 206 / 400 |" in table
    assert "| translation within 15 deg, the pipeline's pose, pairs over eval_s424242 + eval_p4_s434343 + " \
           "bench_s525252 | - | 64 / 400 |" in table
    assert "| real rig, the pipeline's pose: dir err | - | 43.4 |" in table
    assert "| rotation within 15 deg, pairs over eval_s424242 + eval_p4_s434343 + bench_s525252 | 220 / 400 | " \
           "220 / 400 |" in table


def test_the_last_row_sums_rotations_and_directions_of_both_poses_over_all_four_sets():
    def with_pipeline(card):
        card = card.replace('"pairs": 100.0,', '"pairs": 100.0, "RRA15_pair": 52.0, "RTA15_pair": 20.0,')
        card = card.replace('"pairs": 50.0,', '"pairs": 50.0, "RRA15_pair": 40.0, "RTA15_pair": 30.0,')
        return card.replace("| all | 200 | sift+E", "| all | 200 | model + own matches (no K) | 51% | 12% | 14.0 | 40.0 |"
                                                    "\n| all | 200 | sift+E")

    full = parse_card(with_pipeline(_card(50.0, 70.0, 50, cam=60.0)))
    no_cam = parse_card(with_pipeline(_card(50.0, 70.0, 50)))
    table = compare([full, no_cam], ["full", "no_cam"])
    # pointmaps: rotations 50 + 70 + 30 + 100, directions 10 + 10 + 5 + 16; pipeline: rotations 52 + 52 + 20 + 102,
    # directions 20 + 20 + 15 + 24; the card without eval_cam_s464646 has no such count
    assert "| rotations + directions within 15 deg, own pointmaps' pose + the pipeline's, pairs over all four sets " \
           f"| {250 + 41 + 226 + 79} | - |" in table
    assert "all four sets" not in compare([no_cam], ["no_cam"])


def test_the_exact_count_from_per_pair_files_counts_both_poses_over_the_four_sets_only(tmp_path, capsys):
    from benchmarks.compare_cards import exact_count
    from benchmarks.paired import read_per_pair
    from training.evaluate import PairResult, write_per_pair

    f = tmp_path / "pairs.csv"
    sets = ("eval_s424242", "eval_p4_s434343", "eval_cam_s464646", "bench_s525252")
    for s in sets:  # per set: a pair with all four within 15, one with the rotations only, one with none
        write_per_pair(f, s, [PairResult(0, 1.0, 2.0, 5.0, 3.0, 4.0), PairResult(1, 14.9, 40.0, 5.0, 10.0, 15.0),
                              PairResult(2, 80.0, float("nan"), 5.0, 90.0, 100.0)])
    write_per_pair(f, "real_rig", [PairResult(0, 1.0, 1.0, 5.0, 1.0, 1.0)])  # not a card set: not counted
    assert exact_count(read_per_pair(f)) == 4 * (4 + 2)
    old = tmp_path / "old.csv"  # a file without the pipeline's columns, or without a set, has no count
    old.write_text("set,pair,rot_err,dir_err,true_rot\n" + "".join(f"{s},0,1,2,3\n" for s in sets))
    assert exact_count(read_per_pair(old)) is None
    short = tmp_path / "short.csv"
    write_per_pair(short, "eval_s424242", [PairResult(0, 1.0, 2.0, 5.0, 3.0, 4.0)])
    assert exact_count(read_per_pair(short)) is None
    card = tmp_path / "card.txt"
    card.write_text(_card(50.0, 70.0, 50, cam=60.0))
    assert main([str(card), str(card), "--per-pair", str(f), str(old)]) == 0
    assert capsys.readouterr().out.rstrip().endswith(
        "| the same, counted pair by pair from the per-pair files (exact) | 24 | - |")
    with pytest.raises(SystemExit):
        main([str(card), str(card), "--per-pair", str(f)])
    assert "--per-pair expected 2 files" in capsys.readouterr().err
