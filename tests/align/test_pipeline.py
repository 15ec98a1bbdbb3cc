"""reconstruct() glue, with stand-ins for the network modules (pairs, inference, matching) that return
ground truth of the analytic scene."""

import sys
import time

import numpy as np
import pytest
import torch
from align_scene import (
    STAND_IN,
    StandInNet,
    gt_preds,
    make_scene,
    pose_errors,
    stand_in_modules,
    with_descriptors,
)

from pointmap.align import AlignConfig, EpipolarConfig
from pointmap.errors import PointmapError, ShapeError
from pointmap.matching import match_coarse
from pointmap.pipeline import auto_graph, estimate_cost, masks_to_maps, reconstruct


@pytest.fixture
def fake_stack(monkeypatch, request):
    portrait = "portrait" in request.node.name  # views 1 and 3 portrait (48 high, 32 wide) among landscape
    sc = make_scene(5, 32, 48, seed=51, shapes=[(48, 32) if k % 2 else (32, 48) for k in range(5)] if portrait else None)
    calls = {"descriptors": "descriptors" in request.node.name,
             "varied": "varied_confidences" in request.node.name}  # a little noise: confidences 3 + U(0, 1)

    def predict_pairs(model, views, pairs, batch_size=8, **kw):
        calls["pairs"], calls["kw"], calls["shapes"] = list(pairs), kw, [v.shape for v in views]
        if calls.get("stop"):
            raise StopIteration("stand-in stops after recording its inputs")
        return gt_preds(sc, pairs, seed=1, noise=1e-4 if calls["varied"] else 0.0)

    def predict_pairs_with_descriptors(model, views, pairs, batch_size=8, **kw):
        return with_descriptors(predict_pairs(model, views, pairs, batch_size, **kw), sc)

    def match(pred):
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)

    def encode_views(model, imgs, batch_size=8, device="cpu", progress=None):
        calls["encoded"] = calls.get("encoded", 0) + len(imgs)
        return [f"encoding of image {k}" for k in range(len(imgs))]

    inference = {"predict_pairs": predict_pairs_with_descriptors if calls.get("descriptors") else predict_pairs,
                 "encode_views": encode_views}
    stand_in_modules(monkeypatch, calls, inference, {"match": match, "match_coarse": match_coarse})
    images = [(im * 255).astype(np.uint8) for im in sc["images"]]
    return sc, images, calls


def test_reconstruct_end_to_end(fake_stack, capsys, tmp_path):
    sc, images, calls = fake_stack
    # 48x32 arrays at size=48: no resize, no crop (48 and 32 are multiples of 16)
    recon = reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True), min_conf=2.0)
    assert recon.info["pipeline"]["size"] == 48  # recorded: pointmap.localization prepares new photographs alike
    err = capsys.readouterr().err
    assert "5 images, graph complete: 10 pairs" in err and "peak memory" in err
    assert calls["graph"] == "complete" and len(calls["pairs"]) == 10
    rot, centre, _ = pose_errors(recon.cam2world.numpy(), sc["cam2world"])
    assert rot < 0.1 and centre < 0.005
    assert recon.masks.all()  # conf 3 > 2 everywhere
    assert recon.info["pipeline"]["pairs"] == 10
    # the stand-in predictions have no descriptors: the pose refinement on matches says it was skipped, and why
    assert not recon.info["pipeline"]["epipolar"] and "descriptor" in recon.info["epipolar"]["reason"]
    written = recon.save(tmp_path, formats=("colmap", "ply"))
    assert (tmp_path / "sparse/0/images.bin").exists() and written["ply"].stat().st_size > 0


def test_a_confidence_filter_that_keeps_no_pixel_warns_with_the_confidences_and_keeps_the_poses(fake_stack):
    sc, images, _ = fake_stack
    with pytest.warns(UserWarning, match=r"min_conf=50.*keeps none of the 7680 pixels \(their confidences: 3 to 3\)"):
        recon = reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True), min_conf=50.0, quiet=True)
    assert not recon.masks.any()
    rot, centre, _ = pose_errors(recon.cam2world.numpy(), sc["cam2world"])
    assert rot < 0.1 and centre < 0.005


def test_with_descriptors_the_poses_are_refined_on_matches_unless_turned_off(fake_stack):
    sc, images, _ = fake_stack
    recon = reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True), epipolar=EpipolarConfig(patch=4))
    rep = recon.info["epipolar"]
    assert recon.info["pipeline"]["epipolar"] and rep["applied"] and rep["matches"] > 0
    assert "align_refit" in recon.info  # the depths were re-fitted to the refined poses
    plain = reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True), epipolar=False)
    assert not plain.info["pipeline"]["epipolar"] and "epipolar" not in plain.info
    assert not torch.equal(plain.cam2world, recon.cam2world)
    with pytest.raises(PointmapError, match="epipolar expected True, False or an EpipolarConfig, got str"):
        reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True), epipolar="yes")


def test_with_descriptors_reconstruct_records_and_reports_each_stages_wall_time(fake_stack, capsys, monkeypatch):
    sc, images, _ = fake_stack
    inference = sys.modules["pointmap.inference"]
    fast = inference.predict_pairs

    def slow(*args, **kw):  # inference that takes a known 0.3 s at least
        time.sleep(0.3)
        return fast(*args, **kw)

    monkeypatch.setattr(inference, "predict_pairs", slow)
    recon = reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True), epipolar=EpipolarConfig(patch=4))
    seconds = recon.info["pipeline"]["seconds"]
    assert list(seconds) == ["inference", "alignment", "epipolar"]  # the stages that ran, in their order
    assert 0.3 <= seconds["inference"] < 30 and all(v > 0 for v in seconds.values())
    err = capsys.readouterr().err
    assert f"took inference {seconds['inference']:.1f} s, alignment {seconds['alignment']:.1f} s, pose refinement " \
           f"on matches {seconds['epipolar']:.1f} s" in err
    quiet = reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True), epipolar=False, quiet=True)
    assert list(quiet.info["pipeline"]["seconds"]) == ["inference", "alignment"] and "took" not in capsys.readouterr().err


def test_reconstruct_masks_and_percentile(fake_stack):
    sc, images, _ = fake_stack
    masks = [np.ones((32, 48), bool) for _ in images]
    masks[2][:, :10] = False
    recon = reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True), masks=masks, conf_percentile=0.0,
                        quiet=True)
    assert not recon.masks[2, :, :10].any() and recon.masks[2, :, 10:].all()


def test_a_confidence_percentile_keeps_that_share_of_the_pixels_the_masks_keep_with_varied_confidences(fake_stack):
    sc, images, _ = fake_stack
    masks = [np.ones((32, 48), bool) for _ in images]
    for m in masks:
        m[:, :24] = False  # half of every image masked: its pixels must not count towards the percentile
    recon = reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True), masks=masks, conf_percentile=50.0,
                        quiet=True)
    kept = recon.masks
    assert not kept[:, :, :24].any()
    share = float(kept[:, :, 24:].float().mean())
    assert abs(share - 0.5) < 0.02, share  # with the masked pixels counted it kept all of them (share 1.0)


def test_masks_to_maps_from_original_size():
    from pointmap.images import load_images

    views = load_images([np.zeros((120, 200, 3), np.uint8)], size=64)  # -> 64 x ~38 resize, crop to 64x32
    h, w = views[0].shape
    m = np.zeros((120, 200), bool)
    m[:, 100:] = True  # right half of the original
    mm = masks_to_maps([m], views)[0]
    assert mm.shape == (h, w) and mm[:, : w // 2 - 1].sum() == 0 and mm[:, w // 2 + 1:].all()
    with pytest.raises(Exception, match=r"mask 0 \(of image image_000.png\) expected the image's original size "
                                        r"200x120 or the network's map size 64x32 \(width x height\), got 5x3"):
        masks_to_maps([np.zeros((3, 5), bool)], views)
    with pytest.raises(Exception, match=r"got an array of shape \[120, 200, 3\] \(one channel \[H, W\] expected\)"):
        masks_to_maps([np.zeros((120, 200, 3), np.uint8)], views)  # a colour mask image as cv2.imread reads it
    for bad, named in ((5, "masks expected a list of per-image masks, got int"), ([None], "mask 0 expected bools"),
                       ([np.full((h, w), 0.5)], "mask 0 expected bools")):  # 0.5 was quietly True
        with pytest.raises(ValueError, match=named):
            masks_to_maps(bad, views)
    assert masks_to_maps([(mm.numpy() * 255).astype(np.uint8)], views)[0].equal(mm)  # a 0 / 255 mask image
    off_crop = np.zeros((120, 200), bool)
    off_crop[:5] = True  # keeps only rows the crop leaves out (the top ~9 of the original's 120)
    with pytest.raises(ValueError, match="image_000.png keep no pixel of the network's view"):
        masks_to_maps([off_crop], views)


def test_auto_graph_and_estimates():
    assert auto_graph(5) == "complete" and auto_graph(30) == "logwin-3" and auto_graph(200) == "logwin-4"
    small = estimate_cost(10, 30, (384, 512))
    big = estimate_cost(100, 400, (384, 512))
    assert big["align_seconds"] > small["align_seconds"] > 0 and big["memory_gb"] > small["memory_gb"] > 0


def test_the_estimate_counts_the_pixels_the_alignment_samples_at_the_stride_it_chooses():
    from pointmap.align.edges import choose_stride

    assert choose_stride([(8, 78)], 17, None) == 6  # the alignment's own choice (sqrt(624 / 17) would say 7)
    capped = estimate_cost(3, 3, (8, 78), config=AlignConfig(max_opt_pixels=17))
    assert capped == estimate_cost(3, 3, (8, 78), config=AlignConfig(stride=6, max_opt_pixels=None))
    assert capped["align_seconds"] > estimate_cost(3, 3, (8, 78), config=AlignConfig(stride=7))["align_seconds"]
    full = estimate_cost(3, 3, (8, 78), config=AlignConfig(max_opt_pixels=None))
    assert full["memory_gb"] > capped["memory_gb"]


@pytest.mark.parametrize("hw", [(-5, 10), (0, 10), (10.5, 10), (224,), "224x224", None])
def test_the_estimate_refuses_a_map_size_that_is_not_two_positive_integers(hw):
    with pytest.raises(ShapeError, match=r"map_hw expected \(height, width\) in pixels, two integers >= 1, got"):
        estimate_cost(3, 3, hw)


@pytest.mark.parametrize("n_images, n_pairs", [(0, 3), (3, -1), (3.0, 3), (True, 3), (3, None)])
def test_the_estimate_refuses_counts_that_are_not_whole_numbers(n_images, n_pairs):
    with pytest.raises(PointmapError, match="estimate_cost expected n_images >= 1 and n_pairs >= 0"):
        estimate_cost(n_images, n_pairs, (32, 48))


def test_the_alignment_estimate_adds_the_pose_refinement_on_matches_for_a_model_with_descriptors():
    from pointmap.align.epipolar import EpipolarConfig
    from pointmap.errors import PointmapError
    from pointmap.model import PRESETS
    from pointmap.pipeline import EPIPOLAR_SECONDS_PER_PAIR_CELL

    class Exported:  # anything with a ``cfg``
        def __init__(self, cfg):
            self.cfg = cfg

    with_desc = Exported(PRESETS["small"])
    assert with_desc.cfg.desc_dim > 0
    for pairs in (6, 48):
        dense = estimate_cost(8, pairs, (224, 224), with_desc)["align_seconds"]
        fit = EPIPOLAR_SECONDS_PER_PAIR_CELL * pairs * 14 * 14  # 196 coarse cells of 16 px at 224 px
        assert estimate_cost(8, pairs, (224, 224), with_desc, epipolar=True)["align_seconds"] == pytest.approx(
            2 * dense + fit)  # the fit, then the depths re-fitted: a second dense alignment
        no_refit = estimate_cost(8, pairs, (224, 224), with_desc, epipolar=EpipolarConfig(refit_depth=False))
        assert no_refit["align_seconds"] == pytest.approx(dense + fit)
    # refine_epipolar skips a model without descriptors (the default official-size dust3r_512_dpt has none)
    assert PRESETS["dust3r_512_dpt"].desc_dim == 0
    assert estimate_cost(4, 6, (384, 512), epipolar=True) == estimate_cost(4, 6, (384, 512))
    with pytest.raises(PointmapError, match="epipolar expected True, False or an EpipolarConfig, got str"):
        estimate_cost(4, 6, (224, 224), with_desc, epipolar="yes")


@pytest.mark.parametrize("stages", [{}, {"epipolar": True}, {"refine": True}])
def test_the_memory_estimate_counts_the_bytes_of_the_predictions_the_inference_keeps(stages):
    from pointmap.inference import predict_pairs
    from pointmap.model import PRESETS, PointmapNet

    torch.manual_seed(0)
    model = PointmapNet(PRESETS["test"]).eval()
    assert model.cfg.desc_dim > 0
    images = [torch.rand(3, 32, 48) for _ in range(3)]
    pairs = [(0, 1), (1, 2)]
    keep_desc = bool(stages)  # as reconstruct keeps them: only for a stage that matches on descriptors
    preds = predict_pairs(model, images, pairs, keep_desc=keep_desc, quiet=True)
    kept = sum(t.nbytes for p in preds.values() for t in vars(p).values() if isinstance(t, torch.Tensor))
    est = estimate_cost(3, len(pairs), (32, 48), model, **stages)
    assert est["predictions_gb"] * 1e9 == pytest.approx(kept, rel=1e-9)
    assert est["memory_gb"] > est["predictions_gb"]
    # a MASt3R-size model with its descriptors kept: 8 + 2 x 25 floats per pixel against 8 without
    mast3r = type("Exported", (), {"cfg": PRESETS["mast3r_512"]})()
    with_desc = estimate_cost(100, 400, (384, 512), mast3r, epipolar=True)["predictions_gb"]
    assert with_desc == pytest.approx(58 / 8 * estimate_cost(100, 400, (384, 512), mast3r)["predictions_gb"])


@pytest.mark.parametrize("stages,keep", [({"epipolar": False}, False), ({}, True),
                                         ({"epipolar": False, "refine": True}, True)])
def test_reconstruct_keeps_descriptors_only_for_a_stage_that_matches_on_them(fake_stack, stages, keep):
    _, images, calls = fake_stack
    calls["stop"] = True
    with pytest.raises(StopIteration):
        reconstruct(STAND_IN, images, size=48, quiet=True, **stages)
    assert calls["kw"]["keep_desc"] is keep


def test_the_flops_counted_on_the_meta_device_equal_those_of_a_real_forward():
    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.utils.flop_counter import FlopCounterMode

    from pointmap.model import PRESETS, PointmapNet
    from pointmap.pipeline import inference_gflop

    cfg = PRESETS["test"]
    torch.manual_seed(0)
    net = PointmapNet(cfg).eval().requires_grad_(False)
    img = torch.rand(1, 3, 32, 48)
    # the reference: a real encode and decode on real weights, attention in plain matmuls (the CPU's fused
    # attention kernel is not counted by FlopCounterMode; on the meta device attention decomposes into them)
    with sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as fc:
        enc = net.encode(img)
    per_image = fc.get_total_flops()
    with sdpa_kernel(SDPBackend.MATH), FlopCounterMode(display=False) as fc:
        net.decode_pair(enc, enc)
    assert inference_gflop(cfg, (32, 48)) == pytest.approx((per_image / 1e9, fc.get_total_flops() / 1e9), rel=1e-9)
    assert per_image > 0 and fc.get_total_flops() > 0


def test_the_inference_estimate_counts_each_image_encoded_once_and_each_pair_decoded_both_ways():
    from pointmap.model import PRESETS
    from pointmap.pipeline import CPU_GFLOPS_AT_256, inference_gflop

    cfg = PRESETS["small"]

    class Exported:  # an ONNX export carries its architecture as ``cfg`` and has no parameters
        pass

    exported = Exported()
    exported.cfg = cfg
    per_image, per_pair = inference_gflop(cfg, (224, 224))
    for n, pairs in [(4, 6), (16, 48)]:
        got = estimate_cost(n, pairs, (224, 224), exported)["inference_seconds"]
        assert got == pytest.approx((n * per_image + 2 * pairs * per_pair) / CPU_GFLOPS_AT_256)
    listed = Exported()  # a config built by hand with lists where from_dict makes tuples
    listed.cfg = cfg.replace(img_mean=list(cfg.img_mean))
    assert listed.cfg == cfg and hash(listed.cfg) == hash(cfg)  # ModelConfig keeps its tuple fields as tuples
    assert estimate_cost(4, 6, (224, 224), listed)["inference_seconds"] == pytest.approx(
        estimate_cost(4, 6, (224, 224), exported)["inference_seconds"])
    large = estimate_cost(4, 6, (384, 512))["inference_seconds"]  # no model: the official-size one
    assert large > 100 * estimate_cost(4, 6, (224, 224), exported)["inference_seconds"]
    assert estimate_cost(4, 6, (224, 224), exported, device="cuda")["inference_seconds"] == pytest.approx(
        estimate_cost(4, 6, (224, 224), exported)["inference_seconds"] / 100)


def test_single_image_is_a_clear_error(fake_stack):
    from pointmap.errors import GraphError

    _, images, _ = fake_stack
    with pytest.raises(GraphError, match="at least 2 images"):
        reconstruct(STAND_IN, images[:1], size=48, quiet=True)


def test_reconstruct_passes_its_device_and_quiet_to_the_inference(fake_stack, monkeypatch):
    _, images, calls = fake_stack
    calls["stop"] = True
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # a machine with two GPUs
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    with pytest.raises(StopIteration):
        reconstruct(STAND_IN, images, size=48, quiet=True, device=torch.device("cuda", 1))
    assert calls["kw"]["device"] == "cuda:1" and calls["kw"]["quiet"] is True


def test_quiet_silences_the_progress_of_a_given_align_config_too(fake_stack, capsys):
    # cfg = align or AlignConfig(quiet=quiet): a caller's AlignConfig printed its progress under quiet=True
    _, images, _ = fake_stack
    reconstruct(STAND_IN, images, size=48, quiet=True, epipolar=False, align=AlignConfig(niter=5))
    assert capsys.readouterr().err == ""


def test_reconstruct_defaults_to_the_size_the_model_was_trained_at(fake_stack):
    _, images, calls = fake_stack
    calls["stop"] = True
    model = StandInNet()
    model.provenance, model.cfg = {"image_size": 32}, None
    with pytest.raises(StopIteration):
        reconstruct(model, images, quiet=True)
    assert calls["shapes"][0] == (16, 32)  # 48x32 by the long side to 32 -> 32x21, cropped to whole patches


def test_whole_photographs_reach_the_inference_at_their_own_shape_and_the_default_crops_them_square(fake_stack):
    _, _, calls = fake_stack
    calls["stop"] = True
    wide = [np.zeros((48, 96, 3), np.uint8)] * 3  # 2:1 photographs
    for whole, shape in ((True, (112, 224)), (False, (224, 224))):
        with pytest.raises(StopIteration):
            reconstruct(STAND_IN, wide, size=224, quiet=True, whole=whole)
        assert calls["shapes"] == [shape] * 3


def test_portrait_and_landscape_images_with_varied_confidences_are_inferred_and_aligned_whole(fake_stack, tmp_path):
    sc, images, calls = fake_stack
    recon = reconstruct(STAND_IN, images, size=48, align=AlignConfig(quiet=True), conf_percentile=50, quiet=True)
    assert calls["shapes"] == [im.shape[:2] for im in images]  # no crop: each image at its own shape
    assert recon.map_sizes == [(im.shape[1], im.shape[0]) for im in images] and recon.depth_z.shape[1:] == (48, 48)
    rot, centre, _ = pose_errors(recon.cam2world.numpy(), sc["cam2world"])
    assert rot < 0.1 and centre < 0.005
    # the percentile is over the views' own pixels (the padding's confidence 0 would halve what it keeps)
    own = int(recon.regions.sum())
    assert not (recon.masks & ~recon.regions).any() and abs(int(recon.masks.sum()) - own / 2) <= 0.01 * own
    recon.save(tmp_path, formats=("ply",))
    from pointmap.io import read_ply

    assert len(read_ply(tmp_path / "points.ply")["x"]) == int(recon.valid().sum())

def test_masks_reach_the_descriptor_confidence_that_matching_weighs():
    import torch

    from pointmap.pipeline import _mask_pred
    from pointmap.prediction import PairPrediction

    ones = torch.ones(1, 4, 6)
    pred = PairPrediction(torch.zeros(1, 4, 6, 3), torch.zeros(1, 4, 6, 3), ones, ones,
                          desc1=torch.zeros(1, 4, 6, 8), desc2=torch.zeros(1, 4, 6, 8), desc_conf1=ones,
                          desc_conf2=ones)
    m1, m2 = torch.ones(4, 6, dtype=torch.bool), torch.ones(4, 6, dtype=torch.bool)
    m1[:, :2] = False
    m2[0] = False
    out = _mask_pred(pred, m1, m2)
    for conf, m in ((out.conf1, m1), (out.desc_conf1, m1), (out.conf2, m2), (out.desc_conf2, m2)):
        assert torch.equal(conf[0] > 0, m)


@pytest.mark.parametrize("kwargs,message", [
    ({"K": {5: np.eye(3)}}, "image index 5 outside"),
    ({"cam2world": {0: 2 * np.eye(4)}}, "cam2world"),
    ({"K": {0: np.diag([50.0, 50.0, 1.0])}, "align": AlignConfig(quiet=True, shared_focal=True)},
     "K known for some images only"),
])
def test_known_cameras_that_alignment_would_refuse_are_refused_before_the_inference(fake_stack, kwargs, message):
    from pointmap.errors import PointmapError

    _, images, calls = fake_stack
    calls["stop"] = True  # the stand-in inference would raise StopIteration: it must not be reached
    with pytest.raises(PointmapError, match=message):
        reconstruct(STAND_IN, images, size=48, quiet=True, **kwargs)
    assert "shapes" not in calls


@pytest.mark.parametrize("kw,message", [
    ({"conf_percentile": 150}, "conf_percentile expected a percentile in \\[0, 100\\)"),
    ({"min_conf": float("nan")}, "min_conf expected a finite confidence"),
    ({"min_conf": "3"}, "min_conf expected a finite confidence"),
    ({"align": {"niter": 3}}, "align expected an AlignConfig"),
    ({"refine": "no"}, "refine expected True, False or a SparseConfig"),
])
def test_reconstruct_refuses_its_options_before_the_inference(fake_stack, kw, message):
    _, images, calls = fake_stack
    calls["stop"] = True  # the stand-in inference would stop the run: the refusal must come first
    with pytest.raises(PointmapError, match=message):
        reconstruct(STAND_IN, images, size=48, quiet=True, **kw)
    assert "pairs" not in calls


def test_photographs_given_as_an_iterator_keep_their_files_for_the_exports(fake_stack, tmp_path):
    import cv2

    _, images, _ = fake_stack
    paths = []
    for k, im in enumerate(images):
        paths.append(tmp_path / f"p{k}.png")
        cv2.imwrite(str(paths[-1]), im[..., ::-1])
    recon = reconstruct(STAND_IN, iter(paths), size=48, align=AlignConfig(quiet=True), quiet=True)
    assert recon.info["sources"] == [str(p.resolve()) for p in paths]


def test_a_given_list_of_pairs_is_run_as_given_and_a_disconnected_one_is_refused_before_the_inference(fake_stack):
    from pointmap.errors import GraphError

    sc, images, calls = fake_stack
    recon = reconstruct(STAND_IN, images, graph=[(1, 0), (1, 2), (2, 3), (4, 3), (0, 1)], size=48, quiet=True,
                        epipolar=False)
    assert calls["pairs"] == [(0, 1), (1, 2), (2, 3), (3, 4)]  # unordered, deduplicated, sorted
    assert recon.info["pipeline"]["graph"] == "given" and recon.info["pipeline"]["pairs"] == 4
    calls.pop("pairs")
    for bad, message in [([(0, 1), (2, 3), (3, 4)], "disconnected: 2 components"), ([(0, 5)], "invalid pair"),
                         ([], "at least one"), ([(0, 1, 2)], "expected")]:
        with pytest.raises(GraphError, match=message):
            reconstruct(STAND_IN, images, graph=bad, size=48, quiet=True)
    assert "pairs" not in calls  # refused before any inference


def test_the_retrieval_estimate_adds_the_token_comparisons_and_no_second_encoding():
    from pointmap.model import PRESETS
    from pointmap.pipeline import CPU_GFLOPS_AT_256, CPU_GFLOPS_WIDTH_EXPONENT

    model = type("Exported", (), {"cfg": PRESETS["small"]})()
    plain = estimate_cost(10, 20, (224, 224), model)["inference_seconds"]
    retr = estimate_cost(10, 20, (224, 224), model, retrieval=True)["inference_seconds"]
    tokens, dim = 14 * 14, PRESETS["small"].enc_dim
    rate = CPU_GFLOPS_AT_256 * (dim / 256) ** CPU_GFLOPS_WIDTH_EXPONENT
    assert retr - plain == pytest.approx(2 * tokens ** 2 * dim * 45 / 1e9 / rate)


@pytest.mark.parametrize("bad", [0, 2.5, "8"])
def test_reconstruct_refuses_a_batch_size_before_anything_runs(fake_stack, bad):
    _, images, calls = fake_stack
    with pytest.raises(ShapeError, match="batch_size expected an int >= 1"):
        reconstruct(STAND_IN, images, graph="retrieval-2", size=48, quiet=True, batch_size=bad)
    assert "pairs" not in calls


def test_an_unknown_graph_name_is_refused_before_any_image_is_read_and_auto_is_among_the_names_offered(tmp_path):
    with pytest.raises(PointmapError, match="unknown graph 'bogus'; expected one of: auto, complete"):
        reconstruct(STAND_IN, [tmp_path / "missing_a.png", tmp_path / "missing_b.png"], graph="bogus", quiet=True)


def test_stage_arguments_and_masks_are_refused_before_the_retrieval_runs_the_encoder(fake_stack, monkeypatch):
    _, images, calls = fake_stack
    for name in ("encode_views", "image_similarity"):  # the stand-in module's
        monkeypatch.setattr(sys.modules["pointmap.inference"], name, lambda *a, **k: pytest.fail("the encoder ran"),
                            raising=False)
    with pytest.raises(PointmapError, match="epipolar expected True, False or an EpipolarConfig, got str"):
        reconstruct(STAND_IN, images, graph="retrieval-2", size=48, quiet=True, epipolar="yes")
    with pytest.raises(PointmapError, match="refine expected True, False or a SparseConfig, got str"):
        reconstruct(STAND_IN, images, graph="retrieval-2", size=48, quiet=True, refine="no")
    with pytest.raises(Exception, match=r"mask 0 \(of image image_000.png\) expected"):
        reconstruct(STAND_IN, images, graph="retrieval-2", size=48, quiet=True, masks=[np.zeros((5, 5), bool)] * 5)


def test_a_retrieval_run_encodes_each_image_once_records_its_stage_time_and_every_run_its_pairs(fake_stack,
                                                                                                 monkeypatch):
    sc, images, calls = fake_stack
    sim = np.eye(5) + 0.5 * (np.abs(np.subtract.outer(np.arange(5), np.arange(5))) == 1)  # a chain 0-1-2-3-4

    def image_similarity(model, views, *a, encodings=None, **k):
        calls["similarity_encodings"] = encodings
        return torch.from_numpy(sim)

    monkeypatch.setattr(sys.modules["pointmap.inference"], "image_similarity", image_similarity, raising=False)
    recon = reconstruct(STAND_IN, images, graph="retrieval-1", size=48, quiet=True, epipolar=False)
    assert calls["encoded"] == 5 and calls["similarity_encodings"] == [f"encoding of image {k}" for k in range(5)]
    assert calls["kw"]["encodings"] is calls["similarity_encodings"]  # the pairs decode the retrieval's encodings
    info = recon.info["pipeline"]
    assert calls["pairs"] == [(0, 1), (1, 2), (2, 3), (3, 4)] and info["pair_list"] == [[0, 1], [1, 2], [2, 3], [3, 4]]
    assert list(info["seconds"])[:2] == ["retrieval", "inference"] and info["seconds"]["retrieval"] >= 0
