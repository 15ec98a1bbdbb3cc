"""Unit tests from a mutation review of pointmap/pipeline.py (session 92), of its smaller promises: the graph chosen
by the image count, the cost estimate's formula, masks resampled from the original photographs, and what
``reconstruct`` hands to each stage and records; last, tests of the bugs it found. The network modules (pairs,
inference, matching) and the alignment are replaced by stand-ins: every test here runs in milliseconds."""

import sys
import time
import types

import numpy as np
import pytest
import torch
from align_scene import STAND_IN, StandInNet, make_scene, recon_of, stand_in_modules

import pointmap.pipeline as pipeline
from pointmap.align import AlignConfig, EpipolarConfig, SparseConfig
from pointmap.errors import PointmapError, ShapeError
from pointmap.images import View, load_images
from pointmap.model import PRESETS
from pointmap.pipeline import (
    ALIGN_SECONDS_PER_EDGE_PIXEL_ITER,
    CPU_GFLOPS_AT_256,
    CPU_GFLOPS_WIDTH_EXPONENT,
    EPIPOLAR_SECONDS_PER_PAIR_CELL,
    FUSE_SECONDS_PER_EDGE_PIXEL,
    _fmt_s,
    auto_graph,
    estimate_cost,
    inference_gflop,
    masks_to_maps,
    reconstruct,
)


class Exported:
    """Anything with a ``cfg`` (an ONNX export, say): the estimate reads the architecture from it."""

    def __init__(self, cfg):
        self.cfg = cfg


TEST = Exported(PRESETS["test"])  # the smallest architecture: its FLOPs are counted in milliseconds

# --------------------------------------------------------------------------------------------------
# auto_graph


def test_up_to_12_images_are_paired_completely_then_by_logwin_3_up_to_40_then_logwin_4():
    assert [auto_graph(n) for n in (12, 13, 40, 41)] == ["complete", "logwin-3", "logwin-3", "logwin-4"]


def test_a_videos_frames_drop_only_the_wrap_around_pairs_and_12_frames_are_still_paired_completely():
    assert auto_graph(12, sequential=True) == "complete"
    assert auto_graph(13, sequential=True) == "logwin-3-noncyclic" and auto_graph(41, True) == "logwin-4-noncyclic"


# --------------------------------------------------------------------------------------------------
# estimate_cost: its checks


def test_an_estimate_of_one_image_and_no_pair_is_allowed_and_counts_no_edge():
    est = estimate_cost(1, 0, (32, 48), TEST)
    assert est["pairs"] == 0 and est["directed_edges"] == 0 and est["predictions_gb"] == 0.0


def test_the_refusal_of_a_count_gives_each_count_in_its_own_place():
    with pytest.raises(PointmapError, match=r"got 3 and -1$"):
        estimate_cost(3, -1, (32, 48))
    with pytest.raises(PointmapError, match=r"got 0 and 3$"):
        estimate_cost(0, 3, (32, 48))


def test_a_map_size_of_three_numbers_is_refused():
    with pytest.raises(ShapeError, match=r"map_hw expected \(height, width\).*got \(32, 48, 3\)"):
        estimate_cost(3, 3, (32, 48, 3))


def test_a_model_whose_cfg_is_not_a_model_config_is_estimated_as_the_official_size_model():
    other = Exported(types.SimpleNamespace(patch_size=8, enc_dim=64, desc_dim=0))
    assert estimate_cost(3, 3, (32, 48), other) == estimate_cost(3, 3, (32, 48))


# --------------------------------------------------------------------------------------------------
# estimate_cost: its formula


def test_the_estimate_reports_the_pairs_and_twice_as_many_directed_edges():
    est = estimate_cost(4, 5, (32, 48), TEST)
    assert est["pairs"] == 5 and est["directed_edges"] == 10


def test_the_dense_alignment_time_counts_each_sampled_pixel_per_iteration_and_every_pixel_per_fusion_pass():
    cfg = AlignConfig(stride=2, niter=100, fuse_iters=2)  # stride 2 on 32 x 48: 16 x 24 sampled of 32 x 48
    est = estimate_cost(3, 3, (32, 48), TEST, config=cfg)
    E = 6
    expected = (ALIGN_SECONDS_PER_EDGE_PIXEL_ITER * E * 16 * 24 * 100
                + FUSE_SECONDS_PER_EDGE_PIXEL * E * 32 * 48 * (1 + 2))
    assert est["align_seconds"] == pytest.approx(expected, rel=1e-12)


def test_the_memory_estimate_adds_the_subsampled_stack_the_chunked_work_and_the_images():
    E, P, P_opt = 6, 32 * 48, 16 * 24
    images = 4 * P * 200  # 4 images, 3 pairs: the images counted once each
    for chunk in (100, 10 ** 6):  # the chunk below the edges' sampled pixels, then above
        cfg = AlignConfig(stride=2, max_chunk_pixels=chunk)
        est = estimate_cost(4, 3, (32, 48), TEST, config=cfg)  # no matching stage: no descriptors kept
        preds = E * P * 4 * 8
        assert est["predictions_gb"] == pytest.approx(preds / 1e9, rel=1e-12)
        expected = preds + E * P_opt * 4 * 8 + min(chunk, E * P_opt) * 4 * 40 + images
        assert est["memory_gb"] == pytest.approx(expected / 1e9, rel=1e-12)


def test_the_inference_estimate_counts_whole_patches_of_each_side():
    cfg = PRESETS["test"]  # 16-pixel patches
    model = Exported(cfg)
    per_image, per_pair = inference_gflop(cfg, (32, 64))
    rate = CPU_GFLOPS_AT_256 * (cfg.enc_dim / 256) ** CPU_GFLOPS_WIDTH_EXPONENT
    expected = (3 * per_image + 2 * 2 * per_pair) / rate
    assert inference_gflop(cfg, (32, 32)) != (per_image, per_pair)  # a wider map costs more
    for hw in ((32, 64), (40, 64), (32, 70)):  # 40 and 70 hold 2 and 4 whole patches, as 32 and 64
        assert estimate_cost(3, 2, hw, model)["inference_seconds"] == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("device", ["cuda:1", torch.device("cuda", 0)])
def test_any_cuda_device_is_estimated_at_the_gpu_rate(device):
    model = Exported(PRESETS["test"])
    cpu = estimate_cost(3, 2, (32, 48), model)["inference_seconds"]
    assert estimate_cost(3, 2, (32, 48), model, device=device)["inference_seconds"] == pytest.approx(cpu / 100)


def test_the_retrieval_estimate_compares_rows_times_columns_of_patch_tokens():
    cfg = PRESETS["test"]
    model = Exported(cfg)
    plain = estimate_cost(4, 3, (32, 64), model)["inference_seconds"]
    retr = estimate_cost(4, 3, (32, 64), model, retrieval=True)["inference_seconds"]
    rate = CPU_GFLOPS_AT_256 * (cfg.enc_dim / 256) ** CPU_GFLOPS_WIDTH_EXPONENT
    tokens = 2 * 4  # 32 x 64 at 16-pixel patches
    assert retr - plain == pytest.approx(2 * tokens ** 2 * cfg.enc_dim * 6 / 1e9 / rate, rel=1e-9)


def test_the_pose_refinement_estimate_counts_the_coarse_cells_of_the_models_own_patch():
    cfg = PRESETS["test"].replace(patch_size=8, head="catmlp+linear")  # a DPT head needs 16-pixel patches
    assert cfg.desc_dim > 0
    model = Exported(cfg)
    dense = estimate_cost(3, 2, (32, 64), model)["align_seconds"]
    fit = estimate_cost(3, 2, (32, 64), model, epipolar=EpipolarConfig(patch=8, refit_depth=False))["align_seconds"]
    assert fit - dense == pytest.approx(EPIPOLAR_SECONDS_PER_PAIR_CELL * 2 * (32 // 8) * (64 // 8))
    default = estimate_cost(3, 2, (32, 64), model, epipolar=True)["align_seconds"]  # True: the model's patch
    assert default == pytest.approx(fit + dense)  # and the depths re-fitted: a second dense alignment


# --------------------------------------------------------------------------------------------------
# masks_to_maps


def hand_view(original_wh, map_hw, transform, name="hand.png"):
    """A view prepared by a transform given by hand (u_map = (u_orig + 0.5) sx - 0.5 - left, likewise v)."""
    return View(img=torch.zeros(3, *map_hw), original_size=original_wh, map_from_original=transform, name=name,
                index=0)


def two_views():
    return load_images([np.zeros((32, 48, 3), np.uint8)] * 2, size=48)


def test_masks_given_as_one_string_are_refused_as_not_a_list():
    with pytest.raises(ShapeError, match="masks expected a list of per-image masks, got str"):
        masks_to_maps("ab", two_views())


def test_fewer_masks_than_images_are_refused_with_both_counts():
    with pytest.raises(ShapeError, match=r"masks expected one per image \(2\), got 1"):
        masks_to_maps([np.ones((32, 48), bool)], two_views())


def test_a_mask_at_the_map_size_is_taken_as_it_is_when_the_photograph_was_resized():
    views = load_images([np.zeros((120, 200, 3), np.uint8)], size=64)
    h, w = views[0].shape
    assert (h, w) == (32, 64) and views[0].original_size == (200, 120)
    m = np.zeros((h, w), bool)
    m[::3, ::5] = True  # a pattern resampling would not keep
    assert torch.equal(masks_to_maps([m], views)[0], torch.from_numpy(m))


def test_an_original_size_mask_is_sampled_at_each_map_pixels_centre_along_each_axis_with_its_own_scale():
    # 1/3 across and 1/5 down, the map starting 5 rows down the original (a crop): map pixel (r, c) covers
    # original rows 5 (r + 1) .. 5 (r + 1) + 4 and columns 3 c .. 3 c + 2, its centre at (5 r + 7, 3 c + 1)
    view = hand_view((18, 30), (4, 6), (1 / 3, 1 / 5, 0.0, 1.0))
    y, x = np.mgrid[:30, :18]
    r, c = y // 5 - 1, x // 3
    want = np.add.outer(np.arange(4), np.arange(6)) % 2 == 0  # a checkerboard of map pixels
    m = (x % 3 == 1) & (y % 5 == 2) & ((r + c) % 2 == 0)  # true at the centres of the checkerboard's pixels only
    assert torch.equal(masks_to_maps([m], [view])[0], torch.from_numpy(want))


def test_an_original_size_mask_is_sampled_at_the_original_pixel_nearest_each_map_pixels_centre():
    # scale 0.4: map pixel k's centre at original 2.5 k + 0.75 -> the nearest pixels 1, 3, 6, 8 (not 0, 3, 5, 8)
    view = hand_view((10, 10), (4, 4), (0.4, 0.4, 0.0, 0.0))
    m = np.zeros((10, 10), bool)
    m[np.ix_([1, 6], [1, 3, 6, 8])] = True
    want = torch.zeros(4, 4, dtype=torch.bool)
    want[[0, 2]] = True
    assert torch.equal(masks_to_maps([m], [view])[0], want)


# --------------------------------------------------------------------------------------------------
# reconstruct, its stages replaced by stand-ins


@pytest.fixture
def stand_ins(monkeypatch):
    """Stand-in pair, inference and matching modules and alignment: the alignment returns the scene's true
    reconstruction of the views it is given; ``calls`` records what each one was handed."""
    sc = make_scene(3, 32, 48, seed=3)
    calls = {"stop": False, "matched": []}

    def predict_pairs(model, views, pairs, batch_size=8, **kw):
        calls["batch_size"], calls["kw"] = batch_size, kw
        if calls["stop"]:
            raise StopIteration("the stand-in inference stops after recording its inputs")
        return {(a, b): f"prediction {a}-{b}" for i, j in pairs for a, b in ((i, j), (j, i))}

    def match(pred):
        calls["matched"].append(pred)
        return f"matches of {pred}"

    def global_align(views, preds, **kw):
        calls["align"] = kw
        return recon_of(sc, len(views))

    stand_in_modules(monkeypatch, calls, {"predict_pairs": predict_pairs}, {"match": match})
    monkeypatch.setattr(pipeline, "global_align", global_align)
    # the estimate's FLOPs of the official-size model (STAND_IN has no cfg) cost a second a map size: not tested here
    monkeypatch.setattr(pipeline, "inference_gflop", lambda cfg, hw: (1.0, 1.0))
    images = [(im * 255).astype(np.uint8) for im in sc["images"]]
    return sc, images, calls


def test_thirteen_photographs_are_paired_by_the_photographs_graph_not_a_videos(stand_ins):
    _, images, calls = stand_ins
    calls["stop"] = True
    with pytest.raises(StopIteration):
        reconstruct(STAND_IN, images * 4 + images[:1], size=48, quiet=True)
    assert calls["graph"] == "logwin-3"  # the wrap-around pairs kept: photographs have no time order


def test_a_single_photograph_is_refused_by_reconstruct_itself_before_any_pair_is_made(stand_ins):
    from pointmap.errors import GraphError

    _, images, calls = stand_ins
    with pytest.raises(GraphError, match=r"^reconstruct needs at least 2 images, got 1$"):
        reconstruct(STAND_IN, images[:1], size=48, quiet=True)
    assert "graph" not in calls and "batch_size" not in calls


def test_the_batch_size_reaches_the_inference(stand_ins):
    _, images, calls = stand_ins
    calls["stop"] = True
    with pytest.raises(StopIteration):
        reconstruct(STAND_IN, images, size=48, quiet=True, batch_size=3)
    assert calls["batch_size"] == 3


def test_the_estimate_is_made_for_the_largest_map_the_given_align_config_and_the_retrieval(stand_ins, monkeypatch):
    _, images, calls = stand_ins
    seen = []
    real = pipeline.estimate_cost
    monkeypatch.setattr(pipeline, "estimate_cost", lambda *a, **k: seen.append(a) or real(*a, **k))
    cfg = AlignConfig(niter=7, quiet=True)
    # at size 96: the 48 x 32 photographs resized to 96 x 64, the 96 x 48 one kept at 96 x 48
    calls["stop"] = True
    with pytest.raises(StopIteration):
        reconstruct(STAND_IN, [images[0], np.zeros((48, 96, 3), np.uint8), images[1]], size=96, quiet=True,
                    align=cfg, epipolar=False)
    n, n_pairs, hw, _, config, *_, retrieval = seen[-1]
    assert (n, n_pairs, hw) == (3, 3, (64, 96)) and config.niter == 7 and retrieval is False


def test_a_retrieval_graph_is_estimated_with_its_token_comparisons(stand_ins, monkeypatch):
    _, images, calls = stand_ins
    seen = []
    real = pipeline.estimate_cost
    monkeypatch.setattr(pipeline, "estimate_cost", lambda *a, **k: seen.append(a) or real(*a, **k))
    inference = sys.modules["pointmap.inference"]
    monkeypatch.setattr(inference, "encode_views", lambda model, imgs, *a, **k: [None] * len(imgs), raising=False)
    monkeypatch.setattr(inference, "image_similarity", lambda *a, **k: torch.ones(3, 3), raising=False)
    calls["stop"] = True
    with pytest.raises(StopIteration):
        reconstruct(STAND_IN, images, graph="retrieval-1", size=48, quiet=True)
    assert seen[-1][-1] is True


def test_the_inference_time_starts_after_the_estimate(stand_ins, monkeypatch):
    _, images, _ = stand_ins
    real = pipeline.estimate_cost

    def slow_estimate(*a, **k):  # an estimate that takes 0.3 s: not the inference's time
        time.sleep(0.3)
        return real(*a, **k)

    monkeypatch.setattr(pipeline, "estimate_cost", slow_estimate)
    recon = reconstruct(STAND_IN, images, size=48, quiet=True, epipolar=False)
    assert recon.info["pipeline"]["seconds"]["inference"] < 0.3


def test_each_pairs_confidences_are_masked_by_the_mask_of_their_own_image(stand_ins, monkeypatch):
    from align_scene import gt_preds

    sc, images, calls = stand_ins
    monkeypatch.setattr(sys.modules["pointmap.inference"], "predict_pairs", lambda m, v, pairs, **k: gt_preds(sc, pairs))
    seen = {}
    monkeypatch.setattr(pipeline, "global_align", lambda views, preds, **kw: seen.update(preds) or recon_of(sc, 3))
    masks = [np.ones((32, 48), bool) for _ in range(3)]
    masks[0][:, :10] = False
    masks[1][:5] = False
    reconstruct(STAND_IN, images, size=48, quiet=True, epipolar=False, masks=masks)
    assert sorted(seen) == [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]
    for (i, j), pred in seen.items():
        assert torch.equal(pred.conf1[0] > 0, torch.from_numpy(masks[i]))
        assert torch.equal(pred.conf2[0] > 0, torch.from_numpy(masks[j]))


def test_the_known_cameras_and_the_pose_mask_reach_the_alignment_as_given(stand_ins):
    sc, images, calls = stand_ins
    cam2world = sc["cam2world"][:3].copy()
    pose_mask = np.array([True, False, True])
    reconstruct(STAND_IN, images, size=48, quiet=True, epipolar=False, cam2world=cam2world, pose_mask=pose_mask)
    assert calls["align"]["cam2world"] is cam2world and calls["align"]["pose_mask"] is pose_mask


def test_quiet_silences_the_default_alignment_config(stand_ins):
    _, images, calls = stand_ins
    reconstruct(STAND_IN, images, size=48, quiet=True, epipolar=False)
    assert calls["align"]["config"].quiet is True
    reconstruct(STAND_IN, images, size=48, quiet=False, epipolar=False)
    assert calls["align"]["config"].quiet is False


def epipolar_stand_in(monkeypatch, applied=True, refit=True):
    import pointmap.align.epipolar as epipolar

    seen = {}

    def refine_epipolar(views, preds, recon, config=None, align=None):
        seen.update(config=config, align=align)
        recon.info["epipolar"] = ({"applied": True, "matches": 40, "inliers_before": 10, "inliers_after": 30}
                                  if applied else {"applied": False, "reason": "too few matches"})
        if refit:
            recon.info["align_refit"] = {}
        return recon

    monkeypatch.setattr(epipolar, "refine_epipolar", refine_epipolar)
    return seen


def test_the_pose_refinement_takes_the_models_patch_and_the_runs_align_config(stand_ins, monkeypatch):
    _, images, _ = stand_ins
    seen = epipolar_stand_in(monkeypatch)
    model = StandInNet()
    model.cfg = types.SimpleNamespace(patch_size=8)  # a model of 8-pixel patches
    cfg = AlignConfig(niter=7, quiet=True)
    recon = reconstruct(model, images, size=48, quiet=True, align=cfg)
    assert seen["config"].patch == 8 and seen["align"] is not None and seen["align"].niter == 7
    assert recon.info["pipeline"]["epipolar"] is True


@pytest.mark.parametrize("applied, refit, said", [
    (True, True, "(40 matches, 10 -> 30 within the threshold; depths re-fitted to them)"),
    (True, False, "(40 matches, 10 -> 30 within the threshold; depths as aligned)"),
    (False, False, "(skipped: too few matches)")])
def test_the_report_of_the_pose_refinement_says_whether_the_depths_were_re_fitted(stand_ins, monkeypatch, capsys,
                                                                                     applied, refit, said):
    _, images, _ = stand_ins
    epipolar_stand_in(monkeypatch, applied, refit)
    reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True))
    assert f"pointmap: poses refined on the model's matches {said}" in capsys.readouterr().err


def test_the_sparse_stage_matches_each_pair_in_its_own_order_and_is_recorded(stand_ins, monkeypatch):
    import pointmap.align.sparse as sparse

    _, images, calls = stand_ins
    seen = {}

    def refine_matches(recon, matches, config=None):
        seen.update(matches=matches, config=config)
        return recon

    monkeypatch.setattr(sparse, "refine_matches", refine_matches)
    recon = reconstruct(STAND_IN, images, size=48, quiet=True, epipolar=False, refine=True)
    assert seen["matches"] == {(i, j): f"matches of prediction {i}-{j}" for i, j in [(0, 1), (0, 2), (1, 2)]}
    assert isinstance(seen["config"], SparseConfig) and recon.info["pipeline"]["refined"] is True
    plain = reconstruct(STAND_IN, images, size=48, quiet=True, epipolar=False)
    assert plain.info["pipeline"]["refined"] is False


def test_a_cache_serving_several_runs_records_each_runs_own_hits_and_misses(stand_ins, monkeypatch, tmp_path):
    import contextlib

    from pointmap.cache import PredictionCache

    _, images, calls = stand_ins

    class CountingCache(PredictionCache):  # counts what the stand-in inference says it read and wrote
        def __init__(self):
            self.dir, self.hits, self.misses = tmp_path, 0, 0

        def check(self, model):
            pass

        def present(self, imgs, pairs, desc=False):
            return 0

        def _vouched(self, model):
            return contextlib.nullcontext()

    inference = sys.modules["pointmap.inference"]
    fast = inference.predict_pairs

    def predict_pairs(model, views, pairs, batch_size=8, **kw):
        kw["cache"].hits += 4  # each run: 4 directed pairs read back, 2 run
        kw["cache"].misses += 2
        return fast(model, views, pairs, batch_size, **kw)

    monkeypatch.setattr(inference, "predict_pairs", predict_pairs)
    monkeypatch.setattr(inference, "directed", lambda pairs: pairs, raising=False)
    monkeypatch.setattr(inference, "wants_desc", lambda model, keep: keep, raising=False)
    cache = CountingCache()
    runs = [reconstruct(STAND_IN, images, size=48, quiet=True, epipolar=False, cache=cache) for _ in range(2)]
    for recon in runs:
        assert recon.info["pipeline"]["cache"] == {"dir": str(tmp_path), "hits": 4, "misses": 2}


def test_the_run_records_its_size_whole_and_confidence_filters(stand_ins):
    _, images, _ = stand_ins
    recon = reconstruct(STAND_IN, images, size=48, quiet=True, epipolar=False, whole=True, min_conf=1.5,
                        conf_percentile=10.0)
    info = recon.info["pipeline"]
    assert (info["size"], info["whole"], info["min_conf"], info["conf_percentile"]) == (48, True, 1.5, 10.0)


def test_the_warning_of_a_filter_that_keeps_nothing_gives_the_span_of_the_finite_confidences(stand_ins, monkeypatch):
    sc, images, calls = stand_ins

    def global_align(views, preds, **kw):
        recon = recon_of(sc, len(views))
        recon.conf[0, :4] = float("nan")  # pixels without a confidence
        return recon

    monkeypatch.setattr(pipeline, "global_align", global_align)
    with pytest.warns(UserWarning, match=r"keeps none of the 4608 pixels \(their confidences: 3 to 3\)"):
        reconstruct(STAND_IN, images, size=48, quiet=True, epipolar=False, min_conf=50.0)


# --------------------------------------------------------------------------------------------------
# _fmt_s


def test_times_are_shown_in_tenths_below_10_s_in_seconds_below_2_minutes_then_in_tenths_of_minutes():
    assert [_fmt_s(s) for s in (9.94, 10.0, 60.0, 119.0, 150.0)] == ["9.9 s", "10 s", "60 s", "119 s", "2.5 min"]


# --- inputs that were refused with a raw error or a message naming the wrong argument (session 92) ------------

@pytest.mark.parametrize("config", [{"niter": 3}, 300])
def test_the_estimate_refuses_a_config_that_is_not_an_align_config_by_its_name(config):
    # was: AttributeError: 'dict' object has no attribute 'max_opt_pixels'
    with pytest.raises(PointmapError, match=rf"estimate_cost expected config an AlignConfig \(or None\), got "
                                            rf"{type(config).__name__}"):
        estimate_cost(3, 3, (32, 48), config=config)


@pytest.mark.parametrize("quiet", ["no", None, 1])
def test_reconstruct_refuses_a_quiet_that_is_not_true_or_false_by_its_own_name(quiet, tmp_path):
    # was: "AlignConfig.quiet expected True or False, got 'no'" (an AlignConfig the caller never gave), and with
    # align=AlignConfig(quiet=True) the same value passed unchecked
    missing = [tmp_path / "a.png", tmp_path / "b.png"]  # refused before any image is read
    for align in (None, AlignConfig(quiet=True)):
        with pytest.raises(PointmapError, match=rf"reconstruct expected quiet True or False, got {quiet!r}"):
            reconstruct(STAND_IN, missing, size=48, quiet=quiet, align=align)


def test_masks_keyed_by_image_index_are_refused_as_not_a_list():
    # K and cam2world take {image index: value}; masks given alike were read as their keys: "mask 0 ... expected the
    # image's original size 48x32 ..., got an array of shape []"
    views = load_images([np.zeros((32, 48, 3), np.uint8)] * 2, size=48)
    masks = {0: np.ones((32, 48), bool), 1: np.ones((32, 48), bool)}
    with pytest.raises(PointmapError, match=r"masks expected a list of per-image masks, got dict \(one mask per image, "
                                            r"in the images' order"):
        masks_to_maps(masks, views)
