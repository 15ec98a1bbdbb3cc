import math

import pytest
import torch

import pointmap as pm
from pointmap.geometry import depth_to_points_cam
from training.losses import (
    DIR_EPS,
    _scales,
    cell_correspondence_counts,
    completion_loss,
    cross_attention_loss,
    focal_loss,
    gt_cam2_to_cam1,
    gt_points_cam1,
    matching_loss,
    patch_matching_loss,
    patchify,
    pose_loss,
    regression_loss,
)


def test_patchify_follows_the_row_major_token_order():
    img = torch.arange(2 * 3 * 32 * 48, dtype=torch.float32).reshape(2, 3, 32, 48)
    p = patchify(img, 16)
    assert p.shape == (2, 6, 768)
    assert p[1, 4, 0] == img[1, 0, 16, 16] and p[1, 4, 2] == img[1, 2, 16, 16] and p[0, 2, 3] == img[0, 0, 0, 33]


def test_completion_loss_is_zero_for_the_normalised_target_and_ignores_visible_patches():
    img = torch.rand(2, 3, 32, 32)
    t = patchify(img, 16)
    target = (t - t.mean(-1, keepdim=True)) / (t.var(-1, keepdim=True) + 1e-6).sqrt()
    mask = torch.tensor([[True, False, True, False], [False, False, True, True]])
    assert completion_loss(target, img, mask, 16) < 1e-8
    noisy = target.clone()
    noisy[~mask] += 5.0  # visible patches do not count
    assert completion_loss(noisy, img, mask, 16) < 1e-8
    noisy[mask] += 1.0
    assert abs(float(completion_loss(noisy, img, mask, 16)) - 1.0) < 1e-5


def make_views(B=2, H=16, W=24):
    K = torch.tensor([[20.0, 0, 11.5], [0, 20.0, 7.5], [0, 0, 1]]).expand(B, 3, 3)
    c2w1 = torch.eye(4).expand(B, 4, 4).clone()
    c2w2 = c2w1.clone()
    c2w2[:, 0, 3] = 0.5
    c2w1[:, 2, 3] = -1.0  # a world frame different from camera 1
    c2w2[:, 2, 3] = -1.0
    v1 = dict(K=K, cam2world=c2w1, depth_z=2 + torch.rand(B, H, W), valid=torch.ones(B, H, W, dtype=torch.bool))
    v2 = dict(K=K, cam2world=c2w2, depth_z=2 + torch.rand(B, H, W), valid=torch.ones(B, H, W, dtype=torch.bool))
    return v1, v2


def test_ground_truth_of_view_two_is_expressed_in_camera_one():
    v1, v2 = make_views()
    _, p2 = gt_points_cam1(v1, v2)
    own = depth_to_points_cam(v2["depth_z"], v2["K"])
    assert torch.allclose(p2 - own, torch.tensor([0.5, 0, 0]).expand_as(p2), atol=1e-5)


def pred_from(p1, p2, conf=1.0):
    B, H, W, _ = p1.shape
    return pm.PairPrediction(p1, p2, torch.full((B, H, W), conf), torch.full((B, H, W), conf))


def test_regression_loss_is_zero_for_ground_truth_at_any_scale_unless_metric():
    v1, v2 = make_views()
    g1, g2 = gt_points_cam1(v1, v2)
    loss, _ = regression_loss(pred_from(3 * g1, 3 * g2), v1, v2)
    assert float(loss) < 1e-5
    metric, _ = regression_loss(pred_from(3 * g1, 3 * g2), v1, v2, metric=True)
    assert float(metric) > 1.0


def test_regression_loss_weighs_errors_by_confidence_and_rewards_confidence_by_its_log():
    v1, v2 = make_views()
    g1, g2 = gt_points_cam1(v1, v2)
    off = pred_from(g1 + 0.3, g2 + 0.3, conf=1.0)
    l1, d = regression_loss(off, v1, v2, alpha=0.2)
    l2, _ = regression_loss(pred_from(g1 + 0.3, g2 + 0.3, conf=2.0), v1, v2, alpha=0.2)
    err = d["regr1"] + d["regr2"]
    assert abs(float(l1) - err) < 1e-4
    assert abs(float(l2) - (2 * err - 2 * 0.2 * torch.log(torch.tensor(2.0)))) < 1e-4


@pytest.mark.parametrize("metric", [False, True])
def test_regression_loss_equals_a_per_pixel_python_sum_with_offsets_confidences_and_invalid_pixels(metric):
    g = torch.Generator().manual_seed(3)
    B, H, W, alpha = 2, 5, 6, 0.3
    v1, v2 = make_views(B, H, W)
    v1["valid"] = torch.rand(B, H, W, generator=g) > 0.3
    v2["valid"] = torch.rand(B, H, W, generator=g) > 0.5
    g1, g2 = gt_points_cam1(v1, v2)
    p1, p2 = 1.7 * g1 + torch.randn(g1.shape, generator=g), 1.7 * g2 + torch.randn(g2.shape, generator=g)
    c1, c2 = 1 + 3 * torch.rand(B, H, W, generator=g), 1 + 3 * torch.rand(B, H, W, generator=g)
    loss, d = regression_loss(pm.PairPrediction(p1, p2, c1, c2), v1, v2, alpha=alpha, metric=metric)

    def mean_dist(a, b, b_idx):  # over both views' valid pixels of pair b_idx
        pts = [a[b_idx, y, x] for y in range(H) for x in range(W) if v1["valid"][b_idx, y, x]]
        pts += [b[b_idx, y, x] for y in range(H) for x in range(W) if v2["valid"][b_idx, y, x]]
        return sum(math.dist(q.tolist(), (0, 0, 0)) for q in pts) / len(pts)

    want, regr = 0.0, {}
    for name, pr, gt, v, c in (("1", p1, g1, v1["valid"], c1), ("2", p2, g2, v2["valid"], c2)):
        terms, errs = [], []
        for b in range(B):
            s_gt = mean_dist(g1, g2, b)
            s_pr = s_gt if metric else mean_dist(p1, p2, b)
            for y in range(H):
                for x in range(W):
                    if v[b, y, x]:
                        e = math.dist((pr[b, y, x] / s_pr).tolist(), (gt[b, y, x] / s_gt).tolist())
                        terms.append(float(c[b, y, x]) * e - alpha * math.log(float(c[b, y, x])))
                        errs.append(e)
        want += sum(terms) / len(terms)
        regr[f"regr{name}"] = sum(errs) / len(errs)
    assert float(loss) == pytest.approx(want, rel=1e-5)
    assert d == pytest.approx(regr, rel=1e-5)


def test_invalid_pixels_do_not_contribute_even_far_from_the_truth():
    v1, v2 = make_views()
    g1, g2 = gt_points_cam1(v1, v2)
    bad1 = g1.clone()
    bad1[:, :4] = 100.0
    v1["valid"][:, :4] = False
    loss, _ = regression_loss(pred_from(bad1, g2), v1, v2)
    assert float(loss) < 1e-5


def test_matching_loss_is_low_for_matching_descriptors_and_high_for_shuffled_ones():
    torch.manual_seed(0)
    B, H, W, D = 1, 12, 16, 32
    desc1 = torch.nn.functional.normalize(torch.randn(B, H, W, D), dim=-1)
    corr = torch.full((B, H, W, 2), float("nan"))
    corr[0, 2:10, 3:13, 0] = torch.arange(3, 13).float() + 1  # shift by one column
    corr[0, 2:10, 3:13, 1] = torch.arange(2, 10).float()[:, None]
    desc2 = torch.nn.functional.normalize(torch.randn(B, H, W, D), dim=-1)
    desc2[0, 2:10, 4:14] = desc1[0, 2:10, 3:13]
    good, acc = matching_loss(desc1, desc2, corr, n_corr=64, temperature=0.05)
    shuffled, acc_bad = matching_loss(desc1, torch.roll(desc2, 3, dims=2), corr, n_corr=64, temperature=0.05)
    assert acc == 1.0 and float(good) < 0.05
    assert float(shuffled) > 2.0 and acc_bad < 0.2


def test_matching_loss_without_correspondences_is_a_differentiable_zero_with_no_accuracy():
    desc = torch.nn.functional.normalize(torch.randn(1, 4, 4, 8), dim=-1).requires_grad_()
    loss, acc = matching_loss(desc, desc, torch.full((1, 4, 4, 2), float("nan")))
    loss.backward()
    # the accuracy is NaN, as the coarse matching's: a 0.0 entered the training log as an all-wrong batch
    assert float(loss.detach()) == 0 and math.isnan(acc) and desc.grad is not None


def test_matching_loss_of_a_batch_is_the_mean_of_its_pairs_losses_with_the_same_gradients():
    torch.manual_seed(1)
    B, H1, W1, H2, W2, D = 3, 6, 8, 5, 7, 16  # views of different sizes: each has its own row offsets
    desc1 = torch.nn.functional.normalize(torch.randn(B, H1, W1, D, dtype=torch.float64), dim=-1).requires_grad_()
    desc2 = torch.nn.functional.normalize(torch.randn(B, H2, W2, D, dtype=torch.float64), dim=-1).requires_grad_()
    corr = torch.stack([torch.rand(B, H1, W1) * (W2 - 1), torch.rand(B, H1, W1) * (H2 - 1)], dim=-1).double()
    corr[1] = float("nan")  # pair 1 has no correspondence: left out of the mean
    corr[2, :2] = float("nan")
    # n_corr 12 of ~30-48 co-visible pixels: each pair draws a subset from the generator, in pair order
    loss, acc = matching_loss(desc1, desc2, corr, n_corr=12, temperature=0.1,
                              generator=torch.Generator().manual_seed(5))
    grads = torch.autograd.grad(loss, (desc1, desc2))
    g = torch.Generator().manual_seed(5)  # one pair at a time, the same draws: the obviously-correct reference
    per_pair = [matching_loss(desc1[b:b + 1], desc2[b:b + 1], corr[b:b + 1], n_corr=12, temperature=0.1,
                              generator=g)[0] for b in (0, 2)]
    reference = torch.stack(per_pair).mean()
    assert torch.allclose(loss, reference, atol=1e-12)
    for got, want in zip(grads, torch.autograd.grad(reference, (desc1, desc2))):
        assert torch.allclose(got, want, atol=1e-12)
    assert grads[0][1].abs().max() == 0 and grads[0][0].abs().max() > 0 and grads[1][2].abs().max() > 0
    assert 0 < (grads[0][0].abs().sum(-1) > 0).sum() <= 12  # a subset of view 1's pixels, at most n_corr


def _cells(codes: torch.Tensor, p: int) -> torch.Tensor:
    """[B, h, w, D] cell codes -> [B, h*p, w*p, D] pixel descriptors: unit noise around each cell's code."""
    pix = codes.repeat_interleave(p, 1).repeat_interleave(p, 2)
    return torch.nn.functional.normalize(pix + 0.3 * torch.randn_like(pix), dim=-1)


def test_patch_matching_loss_finds_the_cell_holding_each_centres_correspondence_among_all_cells():
    torch.manual_seed(0)
    p, h, w, D = 4, 5, 6, 32
    codes1 = torch.nn.functional.normalize(torch.randn(1, h, w, D), dim=-1)
    codes2 = torch.nn.functional.normalize(torch.randn(1, h, w, D), dim=-1)
    codes2[0, 1:5, 0:5] = codes1[0, 0:4, 1:6]  # view-1 cell (r, c) is view-2 cell (r + 1, c - 1)
    corr = torch.full((1, h * p, w * p, 2), float("nan"))
    ys, xs = torch.meshgrid(torch.arange(h * p).float(), torch.arange(w * p).float(), indexing="ij")
    corr[0, ..., 0], corr[0, ..., 1] = xs - p + 0.5, ys + p + 0.5
    corr[0, 4 * p:] = float("nan")  # the last view-1 row has no partner
    corr[0, :, :p] = float("nan")   # nor the first column
    good, acc = patch_matching_loss(_cells(codes1, p), _cells(codes2, p), corr, p, temperature=0.05)
    bad, acc_bad = patch_matching_loss(_cells(codes1, p), _cells(torch.roll(codes2, 2, dims=2), p), corr, p, 0.05)
    assert acc == 1.0 and float(good) < 0.1
    assert float(bad) > 3.0 and acc_bad < 0.2


def test_patch_matching_loss_pools_pixels_so_a_cell_matches_whatever_its_sub_pixel_descriptors_differ():
    torch.manual_seed(1)
    p, h, w, D = 4, 3, 3, 16
    codes = torch.nn.functional.normalize(torch.randn(1, h, w, D), dim=-1)
    d1 = _cells(codes, p)
    d2 = _cells(codes, p)  # same cells, independent per-pixel noise: pixel descriptors differ, cell means agree
    ys, xs = torch.meshgrid(torch.arange(h * p).float(), torch.arange(w * p).float(), indexing="ij")
    corr = torch.stack([xs, ys], -1)[None]
    _, acc = patch_matching_loss(d1, d2, corr, p, temperature=0.05)
    assert acc == 1.0


def test_patch_matching_loss_without_correspondences_is_a_differentiable_zero_and_checks_the_grid():
    desc = torch.nn.functional.normalize(torch.randn(1, 8, 8, 8), dim=-1).requires_grad_()
    loss, acc = patch_matching_loss(desc, desc, torch.full((1, 8, 8, 2), float("nan")), 4)
    loss.backward()
    assert float(loss.detach()) == 0 and math.isnan(acc) and desc.grad is not None
    import pytest

    with pytest.raises(ValueError, match="multiples of the patch size 16"):
        patch_matching_loss(desc, desc, torch.zeros(1, 8, 8, 2), 16)


def test_patch_matching_loss_has_no_floor_when_several_view_one_cells_fall_in_one_view_two_cell():
    torch.manual_seed(2)
    p, D = 4, 32
    codes2 = torch.nn.functional.normalize(torch.randn(1, 2, 2, D), dim=-1)
    codes1 = codes2.repeat_interleave(2, 1).repeat_interleave(2, 2)  # view 2 zoomed out 2x: 4 cells -> 1
    ys, xs = torch.meshgrid(torch.arange(4 * p).float(), torch.arange(4 * p).float(), indexing="ij")
    corr = torch.stack([xs / 2, ys / 2], -1)[None]
    d1 = torch.nn.functional.normalize(codes1.repeat_interleave(p, 1).repeat_interleave(p, 2), dim=-1)
    d2 = torch.nn.functional.normalize(codes2.repeat_interleave(p, 1).repeat_interleave(p, 2), dim=-1)
    loss, acc = patch_matching_loss(d1, d2, corr, p, temperature=0.05)
    assert acc == 1.0 and float(loss) < 0.05  # one-positive backwards would stay at ln 4 / 2 = 0.69


def test_patch_matching_loss_assigns_a_correspondence_to_the_cell_of_its_nearest_pixel():
    p, D = 4, 8
    codes = torch.nn.functional.normalize(torch.eye(D)[:4].reshape(1, 2, 2, D), dim=-1)
    d = codes.repeat_interleave(p, 1).repeat_interleave(p, 2)
    corr = torch.full((1, 2 * p, 2 * p, 2), float("nan"))
    centres = [(r * p + p // 2, c * p + p // 2) for r in range(2) for c in range(2)]
    for r, c in centres:  # every centre maps to itself, except that u = 3.7 lies in pixel 4, the second cell
        corr[0, r, c] = torch.tensor([float(c), float(r)])
    corr[0, p // 2, p // 2] = torch.tensor([p - 0.3, p // 2])
    _, acc = patch_matching_loss(d, d, corr, p, temperature=0.05)
    assert acc == 0.75  # the moved centre now targets cell 1 while its descriptor is cell 0's


def _shift_corr(h, w, p, dr, dc):
    """corr of an h*p x w*p view 1 whose content sits dr cell rows lower, dc cell columns right in view 2."""
    ys, xs = torch.meshgrid(torch.arange(h * p).float(), torch.arange(w * p).float(), indexing="ij")
    return torch.stack([xs + dc * p, ys + dr * p], -1)[None]


def test_cell_correspondence_counts_say_which_view_two_cell_each_view_one_cells_pixels_land_in():
    p, h, w = 4, 3, 4
    corr = _shift_corr(h, w, p, 1, -1)  # cell (r, c) -> (r + 1, c - 1); falls out of view 2 at the edges
    counts = cell_correspondence_counts(corr, p, (h * p, w * p))
    assert counts.shape == (1, h * w, h * w)
    for r in range(h):
        for c in range(w):
            row = counts[0, r * w + c]
            if r + 1 < h and c - 1 >= 0:
                assert row[(r + 1) * w + c - 1] == p * p and row.sum() == p * p
            else:
                assert row.sum() == 0
    half = cell_correspondence_counts(corr + torch.tensor([p / 2, 0.0]), p, (h * p, w * p))  # straddles two cells
    assert half[0, 1 * w + 1, 2 * w + 0] == p * p / 2 and half[0, 1 * w + 1, 2 * w + 1] == p * p / 2


def test_cross_attention_loss_vanishes_when_attention_follows_correspondences_and_not_otherwise():
    p, h, w = 4, 3, 4
    n = h * w
    counts = cell_correspondence_counts(_shift_corr(h, w, p, 1, -1), p, (h * p, w * p))
    sharp = torch.where(counts > 0, 30.0, -30.0)[:, None]  # [1, 1, n, n] logits peaked on the true cell
    loss, acc = cross_attention_loss([sharp], [sharp.transpose(-1, -2)], counts, min_pixels=8)
    assert float(loss) < 1e-6 and acc == 1.0
    wrong = torch.roll(sharp, 1, dims=-1)
    bad, acc_bad = cross_attention_loss([wrong], [wrong.transpose(-1, -2)], counts, min_pixels=8)
    assert float(bad) > 10 and acc_bad == 0.0
    flat = torch.zeros(1, 2, n, n, requires_grad=True)  # uniform attention: KL = log n for every supervised token
    uni, _ = cross_attention_loss([flat], [flat.transpose(-1, -2)], counts, min_pixels=8)
    assert abs(float(uni.detach()) - math.log(n)) < 1e-5
    uni.backward()
    assert flat.grad.abs().sum() > 0


def test_cross_attention_loss_ignores_tokens_without_enough_covisible_pixels():
    p, h, w = 4, 2, 2
    corr = _shift_corr(h, w, p, 0, 0)
    corr[0, :p, :p] = float("nan")       # cell 0: no partner
    corr[0, :p, p:p + 2] = float("nan")  # cell 1: only half of its pixels are co-visible
    counts = cell_correspondence_counts(corr, p, (h * p, w * p))
    logits = torch.where(torch.eye(4, dtype=torch.bool), 30.0, -30.0)[None, None]
    logits[0, 0, 1] = torch.tensor([30.0, -30.0, -30.0, -30.0])  # cell 1 looks at the wrong cell
    strict, _ = cross_attention_loss([logits], [], counts, min_pixels=12)
    loose, _ = cross_attention_loss([logits], [], counts, min_pixels=8)
    assert float(strict) < 1e-6 and float(loose) > 10


def test_pose_loss_is_zero_for_the_true_transform_at_the_predictions_scale_and_measures_rotation_errors():
    v1, v2 = make_views()
    g1, g2 = gt_points_cam1(v1, v2)
    pred = pred_from(3 * g1, 3 * g2)  # the prediction's units are 3x the ground truth's
    T = torch.eye(4).expand(2, 4, 4).clone()
    T[:, 0, 3] = 0.5 * 3  # camera 2 sits 0.5 (GT units) to the right of camera 1
    loss, d = pose_loss(T, pred, v1, v2)
    assert float(loss) < 1e-5 and d["pose_rot_deg"] < 0.1
    a = math.radians(20)
    Rz = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])
    T_bad = T.clone()
    T_bad[:, :3, :3] = Rz
    bad, d_bad = pose_loss(T_bad, pred, v1, v2)
    assert abs(d_bad["pose_rot_deg"] - 20) < 0.05 and float(bad) > 0.3
    unscaled, _ = pose_loss(T, pred, v1, v2, metric=True)  # metric: the prediction's 3x is an error
    assert float(unscaled) > 0.1


def test_the_direction_term_of_the_pose_loss_measures_the_translation_angle_and_skips_tiny_baselines():
    v1, v2 = make_views()
    g1, g2 = gt_points_cam1(v1, v2)
    pred = pred_from(3 * g1, 3 * g2)
    T = torch.eye(4).expand(2, 4, 4).clone()
    T[:, 0, 3] = 0.5 * 3  # the true transform
    base, _ = pose_loss(T, pred, v1, v2)
    same, d = pose_loss(T, pred, v1, v2, dir_weight=2.0)
    assert abs(float(same) - float(base)) < 1e-6 and d["pose_dir_deg"] < 0.1
    turned = T.clone()
    turned[:, :3, 3] = torch.tensor([0.0, 0.0, 1.5])  # same length, 90 degrees off
    plain, _ = pose_loss(turned, pred, v1, v2)
    with_dir, d = pose_loss(turned, pred, v1, v2, dir_weight=2.0)
    assert abs(d["pose_dir_deg"] - 90) < 0.05
    # chord of 90 degrees between unit vectors is sqrt(2); the predicted norm is smoothed by DIR_EPS
    n = 1.5 / _scales(pred, v1, v2, False)[3]  # |t| in mean point distances, per pair (same for the truth)
    u = n / (n ** 2 + DIR_EPS ** 2) ** 0.5     # the smoothed unit length; the chord of 90 degrees is u sqrt(2)
    assert abs(float(with_dir) - float(plain) - 2.0 * float((u * 2 ** 0.5).mean())) < 1e-4
    assert float(u.min()) > 0.95  # a long baseline: nearly the plain chord
    # a fresh pose head predicts t = 0: the term's gradient stays bounded (no 1 / |t| blow-up)
    zero = T.clone()
    zero[:, :3, 3] = 0.0
    zero.requires_grad_(True)
    loss0, _ = pose_loss(zero, pred, v1, v2, dir_weight=2.0)
    loss0.backward()
    assert torch.isfinite(zero.grad).all() and float(zero.grad.norm()) < 2.0 / DIR_EPS
    # a camera that did not move has no direction: the term is left out
    still = {k: (v.clone() if torch.is_tensor(v) else v) for k, v in v2.items()}
    still["cam2world"] = v1["cam2world"].clone()
    T0 = torch.eye(4).expand(2, 4, 4).clone()
    T0[:, 0, 3] = 0.7
    a, _ = pose_loss(T0, pred, v1, still)
    b, d = pose_loss(T0, pred, v1, still, dir_weight=2.0)
    assert float(a) == float(b) and "pose_dir_deg" not in d


def test_the_losses_refuse_inputs_that_would_give_a_wrong_value_or_a_deep_error():
    from pointmap.errors import ShapeError
    from training.losses import completion_loss, matching_loss, patch_matching_loss

    d = torch.nn.functional.normalize(torch.randn(1, 16, 16, 8), dim=-1)
    corr = torch.rand(1, 16, 16, 2) * 15
    for kw, message in [({"n_corr": 0}, "n_corr >= 1"), ({"temperature": 0.0}, "temperature > 0"),
                        ({"temperature": -0.1}, "temperature > 0")]:
        with pytest.raises(ShapeError, match=message):
            matching_loss(d, d, corr, **kw)
    with pytest.raises(ShapeError, match="corr \\[1, 16, 16, 2\\] \\(view 1's grid\\), got \\[1, 8, 8, 2\\]"):
        matching_loss(d, d, corr[:, :8, :8])
    with pytest.raises(ShapeError, match="desc1 \\[B, H1, W1, D\\]"):
        matching_loss(d[0], d[0], corr[0])
    with pytest.raises(ShapeError, match="temperature > 0"):
        patch_matching_loss(d, d, corr, patch=8, temperature=0.0)
    with pytest.raises(ShapeError, match="H and W multiples of 16"):
        completion_loss(torch.zeros(1, 4, 768), torch.zeros(1, 3, 40, 40), torch.ones(1, 4, dtype=torch.bool), 16)


def _scene_points(B=2, H=12, W=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    depth = 2 + torch.rand(B, H, W, generator=g)
    K = torch.tensor([[[20.0, 0, 7.0], [0, 20.0, 5.5], [0, 0, 1]], [[31.0, 0, 8.0], [0, 31.0, 5.0], [0, 0, 1]]])[:B]
    return depth_to_points_cam(depth, K), K, torch.ones(B, H, W, dtype=torch.bool)


def test_the_focal_loss_is_zero_for_true_points_and_the_log_of_the_factor_a_field_of_view_is_off_by():
    pts, K, valid = _scene_points()
    loss, d = focal_loss(pts, K, valid)
    assert float(loss) < 1e-5 and d["focal_log_err"] < 1e-5
    wide = pts.clone()
    wide[..., :2] *= 1.25  # x / z 1.25x too large: a focal 1.25x too short, whatever the depth scale
    loss, d = focal_loss(3 * wide.requires_grad_(), K, valid)
    assert float(loss.detach()) == pytest.approx(math.log(1.25), abs=1e-4)
    loss.backward()
    assert wide.grad is not None and float(wide.grad.abs().sum()) > 0
    # only the valid pixels count: corrupt the invalid ones
    bad = pts.clone()
    valid = valid.clone()
    valid[:, :, :4] = False
    bad[:, :, :4, :2] *= 5
    assert float(focal_loss(bad, K, valid)[0]) < 1e-5


def test_the_focal_loss_measures_the_l1_focal_a_brute_force_search_finds():
    pts, K, valid = _scene_points(B=1, seed=1)
    g = torch.Generator().manual_seed(2)
    noisy = pts * (1 + 0.05 * torch.randn(pts.shape, generator=g))
    noisy[0, :3, :5, :2] *= 4  # outlier pixels the L1 estimate resists
    loss, _ = focal_loss(noisy, K, valid, iters=30)
    H, W = valid.shape[1:]
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    p = torch.stack([u - K[0, 0, 2], v - K[0, 1, 2]], -1)
    r = (noisy[0, ..., :2] / noisy[0, ..., 2:]).double()
    grid = torch.linspace(10, 40, 30001, dtype=torch.float64)
    cost = torch.stack([(p - f * r).norm(dim=-1).sum() for f in grid])
    best = float(grid[cost.argmin()])
    assert math.exp(float(loss)) * 20.0 == pytest.approx(best, rel=2e-3) or \
        math.exp(-float(loss)) * 20.0 == pytest.approx(best, rel=2e-3)


def test_the_focal_loss_without_a_usable_pixel_is_a_differentiable_zero():
    pts, K, valid = _scene_points()
    pts = pts.clone().requires_grad_()
    loss, d = focal_loss(pts, K, torch.zeros_like(valid))
    assert float(loss.detach()) == 0 and math.isnan(d["focal_log_err"])
    loss.backward()
    assert pts.grad is not None and float(pts.grad.abs().sum()) == 0
    behind = pts.detach().clone()
    behind[..., 2] *= -1  # every point behind the camera
    assert float(focal_loss(behind, K, valid)[0]) == 0


def test_a_pair_without_a_valid_pixel_adds_its_rotation_but_not_its_unscalable_translation_to_the_pose_loss():
    """Its scale clamps to 1e-8: a true baseline of 5e7 and a gradient of 5e8 that clipping let drive the whole
    update. With it, the loss is the other pair's translation and both pairs' rotations."""
    v1, v2 = make_views()
    g1, g2 = gt_points_cam1(v1, v2)
    T = torch.eye(4).expand(2, 4, 4).clone()
    T[:, 0, 3] = 0.2  # the truth is 0.5: both translations are off
    ref, _ = pose_loss(T[:1], pred_from(g1[:1], g2[:1]), {k: t[:1] for k, t in v1.items()},
                       {k: t[:1] for k, t in v2.items()})
    for v in (v1, v2):
        v["valid"] = v["valid"].clone()
        v["valid"][1] = False
    assert float(pose_loss(T, pred_from(g1, g2), v1, v2)[0]) == pytest.approx(float(ref), rel=1e-6)  # pair 0's
    T = T.clone().requires_grad_()
    loss, _ = pose_loss(T, pred_from(g1, g2), v1, v2, dir_weight=0.5)
    loss.backward()
    assert math.isfinite(loss.item()) and loss.item() < 2
    assert float(T.grad[1, :3, 3].abs().max()) == 0.0 and float(T.grad.abs().max()) < 10


def test_a_pair_whose_correspondences_all_land_on_fewer_than_eight_pixels_is_left_out_of_the_matching_loss():
    torch.manual_seed(0)
    desc1 = torch.nn.functional.normalize(torch.randn(2, 8, 8, 16), dim=-1)
    desc2 = torch.nn.functional.normalize(torch.randn(2, 8, 8, 16), dim=-1)
    corr = torch.full((2, 8, 8, 2), float("nan"))
    corr[0, :4, :4] = torch.tensor([3.0, 3.0])  # sixteen pixels, one target: a "pair" with loss 0 and accuracy 1
    corr[1, :4, :4, 0] = torch.arange(4).float()
    corr[1, :4, :4, 1] = torch.arange(4).float()[:, None]
    both, acc = matching_loss(desc1, desc2, corr, n_corr=64)
    alone, acc_alone = matching_loss(desc1[1:], desc2[1:], corr[1:], n_corr=64)
    assert float(both) == pytest.approx(float(alone)) and acc == acc_alone


def test_the_descriptor_confidence_loss_is_masts_conf_matching_loss_with_the_infonce_held_fixed():
    """A slow reference, correspondence by correspondence: l_i c_i - alpha log c_i, c_i the mean of the two pixels'
    confidences, l_i the mean of the row and column cross-entropies. The gradient reaches the confidences only
    (the descriptors' objective stays matching_loss's); until session 72 no loss reached them at all."""
    from pointmap.errors import ShapeError
    from training.losses import descriptor_confidence_loss

    torch.manual_seed(0)
    B, H, W, D = 2, 6, 8, 16
    desc1 = torch.nn.functional.normalize(torch.randn(B, H, W, D), dim=-1).requires_grad_()
    desc2 = torch.nn.functional.normalize(torch.randn(B, H, W, D), dim=-1).requires_grad_()
    conf1 = (torch.rand(B, H, W) * 3 + 0.2).requires_grad_()
    conf2 = (torch.rand(B, H, W) * 3 + 0.2).requires_grad_()
    corr = torch.full((B, H, W, 2), float("nan"))
    corr[:, 1:5, 1:6, 0] = torch.arange(1, 6).float() + 1
    corr[:, 1:5, 1:6, 1] = torch.arange(1, 5).float()[:, None]
    loss, mean_c = descriptor_confidence_loss(desc1, desc2, conf1, conf2, corr, n_corr=64, temperature=0.1,
                                              alpha=2.0)
    with torch.no_grad():  # the reference takes floats from tensors that need no gradient
        ref, cs = 0.0, []
        for b in range(B):
            p1 = [(v, u) for v in range(H) for u in range(W) if bool(torch.isfinite(corr[b, v, u]).all())]
            p2 = [(int(corr[b, v, u, 1]), int(corr[b, v, u, 0])) for v, u in p1]
            S = torch.stack([torch.stack([desc1[b, v, u] @ desc2[b, y, x] for y, x in p2]) for v, u in p1]) / 0.1
            terms = []
            for i, ((v, u), (y, x)) in enumerate(zip(p1, p2)):
                li = 0.5 * (-torch.log_softmax(S[i], 0)[i] - torch.log_softmax(S[:, i], 0)[i])
                c = 0.5 * (conf1[b, v, u] + conf2[b, y, x])
                cs.append(float(c))
                terms.append(float(li) * c - 2.0 * torch.log(c))
            ref = ref + torch.stack(terms).mean() / B
    assert loss.item() == pytest.approx(float(ref), rel=1e-5) and mean_c == pytest.approx(sum(cs) / len(cs), rel=1e-5)
    loss.backward()
    assert desc1.grad is None and desc2.grad is None
    assert float(conf1.grad.abs().sum()) > 0 and float(conf2.grad.abs().sum()) > 0
    # no correspondence: a differentiable zero
    none, c_none = descriptor_confidence_loss(desc1, desc2, conf1, conf2, torch.full_like(corr, float("nan")))
    assert none.item() == 0 and math.isnan(c_none)
    with pytest.raises(ShapeError, match=r"expected conf2 \[2, 6, 8\], got \[2, 6\]"):
        descriptor_confidence_loss(desc1, desc2, conf1, conf2[..., 0], corr)


def test_the_direction_term_averages_over_the_pairs_it_covers_and_the_log_over_the_pairs_with_a_scale():
    v1, v2 = make_views()
    still = {k: (v.clone() if torch.is_tensor(v) else v) for k, v in v2.items()}
    still["cam2world"][1] = v1["cam2world"][1]  # pair 1: no baseline, no direction
    g1, g2 = gt_points_cam1(v1, still)
    pred = pred_from(g1, g2)
    T = gt_cam2_to_cam1(v1, still).float().clone()
    T[0, :3, 3] = torch.tensor([0.0, 0.0, float(T[0, :3, 3].norm())])  # pair 0: 90 degrees off, same length
    plain, _ = pose_loss(T, pred, v1, still)
    with_dir, d = pose_loss(T, pred, v1, still, dir_weight=1.0)
    n = float(T[0, :3, 3].norm()) / float(_scales(pred, v1, still, False)[3][0])
    u = n / (n ** 2 + DIR_EPS ** 2) ** 0.5
    assert abs(float(with_dir - plain) - u * 2 ** 0.5) < 1e-4  # pair 0's chord alone: it was halved by B = 2
    blank = {k: (v.clone() if torch.is_tensor(v) else v) for k, v in v1.items()}
    blank["valid"][1] = False
    blank2 = {k: (v.clone() if torch.is_tensor(v) else v) for k, v in v2.items()}
    blank2["valid"][1] = False
    _, d = pose_loss(gt_cam2_to_cam1(v1, v2).float(), pred_from(*gt_points_cam1(v1, v2)), blank, blank2)
    assert d["pose_trans"] < 1e-4  # pair 1 has no scale: its translation left out of the log as of the loss
