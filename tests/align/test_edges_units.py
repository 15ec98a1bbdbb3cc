"""Unit tests of pointmap/align/edges.py on tiny hand-made predictions (no scene, no optimisation): the
weights, sampling grid, validation, 'auto' weighting, stacking, pair scores, dropping and connectivity that the
alignment builds on. Written from a mutation review; each test names the behaviour it pins down."""

import math
import re
import warnings

import numpy as np
import pytest
import torch
from align_scene import complete_pairs, gt_preds, make_scene, views_of

from pointmap.align import AlignConfig, global_align
from pointmap.align.edges import (
    build_stack,
    check_connected,
    check_preds,
    choose_stride,
    conf_to_weight,
    drop_empty_edges,
    resolve_conf_transform,
    sample_index,
)
from pointmap.errors import GraphError, ShapeError
from pointmap.prediction import PairPrediction


def pair(h=4, w=6, h2=None, w2=None, conf1=2.0, conf2=2.0, T=None, offset=0.0):
    """A prediction whose points encode their pixel: x = column, y = row, z = 10 + view (+ offset)."""
    h2, w2 = h2 or h, w2 or w

    def pts(hh, ww, z):
        v, u = torch.meshgrid(torch.arange(hh, dtype=torch.float32), torch.arange(ww, dtype=torch.float32),
                              indexing="ij")
        return torch.stack([u, v, torch.full_like(u, z + offset)], -1)[None]

    def conf(c, hh, ww):
        return c.reshape(1, hh, ww).float() if isinstance(c, torch.Tensor) else torch.full((1, hh, ww), float(c))

    return PairPrediction(pts(h, w, 10.0), pts(h2, w2, 11.0), conf(conf1, h, w), conf(conf2, h2, w2),
                          cam2_to_cam1=T)


def stack_of(preds, shapes, stride=1, transform="log"):
    keys = check_preds(preds, len(shapes), shapes)
    return build_stack(preds, keys, shapes, stride, transform)


# ---------------------------------------------------------------- conf_to_weight

def test_each_confidence_transform_gives_the_documented_weight_and_never_a_negative_or_infinite_one():
    c = torch.tensor([-1.0, 0.0, 0.25, 1.0, 4.0, math.inf, math.nan])
    expect = {"log": [0, 0, 0, 0, math.log(4.0), 0, 0],
              "m1": [0, 0, 0, 0, 3.0, 0, 0],
              "sqrt": [0, 0, 0.5, 1.0, 2.0, 0, 0],
              "id": [0, 0, 0.25, 1.0, 4.0, 0, 0]}
    for name, want in expect.items():
        got = conf_to_weight(c, name)
        assert torch.allclose(got, torch.tensor(want, dtype=torch.float32)), (name, got)


# ---------------------------------------------------------------- sample_index

def test_sampling_keeps_the_centre_of_every_stride_cell_up_to_the_last_row_and_column():
    rows, cols = sample_index(4, 6, 2)
    assert rows.tolist() == [1, 3] and cols.tolist() == [1, 3, 5]
    assert [x.tolist() for x in sample_index(3, 2, 1)] == [[0, 1, 2], [0, 1]]


# ---------------------------------------------------------------- check_preds

def test_prediction_keys_that_are_not_pairs_of_integer_indices_are_refused_naming_the_key():
    p = pair()
    for bad in [(0, 1, 2), (0.0, 1), (0, 1.0), (True, 1), "01"]:
        with pytest.raises(GraphError, match=r"\(i, j\) tuples.*got " + re.escape(repr(bad))):
            check_preds({bad: p, (0, 1): p}, 2, [(4, 6)] * 2)


def test_pairs_naming_an_image_outside_the_range_are_refused_with_the_valid_range():
    p = pair()
    for bad in [(2, 0), (0, 2), (-1, 1), (1, -1)]:
        with pytest.raises(GraphError, match=rf"pair \({bad[0]}, {bad[1]}\) refers to an image outside 0\.\.1$"):
            check_preds({(0, 1): p, bad: p}, 2, [(4, 6)] * 2)


def test_a_self_pair_is_dropped_with_a_warning_and_the_other_keys_come_back_sorted_and_directed():
    p = pair()
    preds = {(2, 1): p, (1, 1): p, (0, 2): p, (1, 0): p}
    with pytest.warns(UserWarning, match=r"pair \(1, 1\) pairs an image with itself"):
        keys = check_preds(preds, 3, [(4, 6)] * 3)
    assert keys == [(0, 2), (1, 0), (2, 1)]


def test_a_prediction_holding_two_pairs_is_refused():
    two = PairPrediction.cat([pair(), pair()])
    with pytest.raises(ShapeError, match="batch size 1 per pair, got 2"):
        check_preds({(0, 1): two}, 2, [(4, 6)] * 2)


def test_each_view_map_is_checked_against_its_own_images_height_and_width_naming_both():
    shapes = [(4, 6), (5, 3)]
    good = pair(4, 6, 5, 3)
    assert check_preds({(0, 1): good, (1, 0): pair(5, 3, 4, 6)}, 2, shapes) == [(0, 1), (1, 0)]
    with pytest.raises(ShapeError, match=r"pair \(0, 1\): pts2_cam1 is \[4, 6\] but image 1 is \[5, 3\] \(h, w\)"):
        check_preds({(0, 1): pair(4, 6, 4, 6)}, 2, shapes)
    with pytest.raises(ShapeError, match=r"pair \(0, 1\): pts1_cam1 is \[5, 3\] but image 0 is \[4, 6\]"):
        check_preds({(0, 1): pair(5, 3, 5, 3)}, 2, shapes)
    with pytest.raises(ShapeError, match=r"pts1_cam1 is \[4, 5\] but image 0 is \[4, 6\]"):  # width alone
        check_preds({(0, 1): pair(4, 5, 5, 3)}, 2, shapes)


# ---------------------------------------------------------------- resolve_conf_transform

def _conf(n, **share):
    """n confidences: share[value] = count, the rest at the floor 1.0."""
    c = torch.ones(n)
    at = 0
    for v, k in share.items():
        c[at:at + k] = {"spread": 1.1, "zero": 0.0, "inf": math.inf}[v]
        at += k
    return c


def test_auto_weighting_picks_log_from_a_tenth_of_confidences_at_1_1_counted_over_both_views_and_all_pairs():
    n = 24  # 4 x 6 pixels a view
    spread_view2 = pair(conf1=1.0, conf2=_conf(n, spread=5))  # 5 of 48 usable >= 1.1: log
    assert resolve_conf_transform("auto", {(0, 1): spread_view2}, [(0, 1)]) == "log"
    thin = pair(conf1=1.0, conf2=_conf(n, spread=4))  # 4 of 48 (1.1 itself counts): below a tenth
    assert resolve_conf_transform("auto", {(0, 1): thin}, [(0, 1)]) == "id"
    just_below = pair(conf1=1.0, conf2=torch.full((n,), 1.09))
    assert resolve_conf_transform("auto", {(0, 1): just_below}, [(0, 1)]) == "id"
    preds = {(0, 1): pair(conf1=1.0, conf2=1.0), (1, 0): pair(conf1=2.0, conf2=2.0)}  # the second pair spreads
    assert resolve_conf_transform("auto", preds, [(0, 1), (1, 0)]) == "log"


def test_auto_weighting_picks_log_when_exactly_a_tenth_of_the_confidences_leave_the_floor():
    exactly = pair(4, 5, conf1=1.0, conf2=_conf(20, spread=4))  # 4 of 40
    assert resolve_conf_transform("auto", {(0, 1): exactly}, [(0, 1)]) == "log"
    one_less = pair(4, 5, conf1=1.0, conf2=_conf(20, spread=3))
    assert resolve_conf_transform("auto", {(0, 1): one_less}, [(0, 1)]) == "id"


def test_auto_weighting_leaves_out_masked_infinite_and_pointless_pixels_and_falls_back_to_conf_itself():
    n = 24
    # 24 of view 2 masked (0): 2 + 1 of the 24 usable of view 1 above the floor reach a tenth only without them
    p = pair(conf1=_conf(n, spread=3), conf2=torch.zeros(n))
    assert resolve_conf_transform("auto", {(0, 1): p}, [(0, 1)]) == "log"
    # 12 infinite confidences are not usable either: 2 of 36 is below a tenth (counted usable: 14 of 48, log)
    p = pair(conf1=_conf(n, inf=12), conf2=_conf(n, spread=2))
    assert resolve_conf_transform("auto", {(0, 1): p}, [(0, 1)]) == "id"
    # view 2's spread confidences sit on non-finite points of view 2 (view 1's points are finite): not usable
    p = pair(conf1=1.0, conf2=_conf(n, spread=6))
    p.pts2_cam1[0].view(-1, 3)[:6, 2] = math.nan
    assert resolve_conf_transform("auto", {(0, 1): p}, [(0, 1)]) == "id"
    # nothing usable at all: conf itself, not log
    assert resolve_conf_transform("auto", {(0, 1): pair(conf1=0.0, conf2=0.0)}, [(0, 1)]) == "id"
    with pytest.raises(ValueError, match=r"conf_transform expected one of .*got 'rank'"):
        resolve_conf_transform("rank", {(0, 1): pair()}, [(0, 1)])


# ---------------------------------------------------------------- build_stack

def test_the_stack_pads_images_of_different_sizes_to_the_largest_and_samples_each_views_own_grid():
    shapes = [(2, 3), (3, 4)]
    st = stack_of({(0, 1): pair(2, 3, 3, 4), (1, 0): pair(3, 4, 2, 3)}, shapes)
    assert st.num_pixels == 12 and st.num_edges == 2
    assert st.i.tolist() == [0, 1] and st.j.tolist() == [1, 0] and st.keys == [(0, 1), (1, 0)]
    # uv: (column, row) of each kept pixel, row-major; padding is (0, 0) and not valid
    assert st.uv[0, :6].tolist() == [[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1]]
    assert st.uv[1, 4].tolist() == [0, 1] and st.uv[1, 11].tolist() == [3, 2]
    assert st.pix_valid[0].tolist() == [True] * 6 + [False] * 6 and bool(st.pix_valid[1].all())
    # edge (0, 1): view 1 on image 0's 6 pixels, view 2 on image 1's 12; the points encode (u, v)
    assert torch.equal(st.pred_i[0, :6, :2], st.uv[0, :6]) and torch.equal(st.pred_j[0, :, :2], st.uv[1])
    assert bool((st.pred_i[0, 6:] == 0).all()) and bool((st.w_i[0, 6:] == 0).all())
    assert torch.equal(st.pred_i[1, :, :2], st.uv[1]) and torch.equal(st.pred_j[1, :6, :2], st.uv[0, :6])
    assert bool((st.pred_j[:, :, 2][st.w_j > 0] == 11).all())


def test_the_stack_records_its_stride_and_samples_cell_centres():
    st = stack_of({(0, 1): pair(4, 6)}, [(4, 6)] * 2, stride=2)
    assert st.stride == 2 and st.num_pixels == 6
    assert st.uv[0].tolist() == [[1, 1], [3, 1], [5, 1], [1, 3], [3, 3], [5, 3]]


def test_each_views_weights_come_from_its_own_confidences_with_the_chosen_transform():
    c1 = torch.linspace(1.0, 3.0, 24)
    c2 = torch.linspace(5.0, 2.0, 24)
    for transform in ("log", "m1", "sqrt", "id"):
        st = stack_of({(0, 1): pair(conf1=c1, conf2=c2)}, [(4, 6)] * 2, transform=transform)
        assert torch.allclose(st.w_i[0], conf_to_weight(c1, transform)), transform
        assert torch.allclose(st.w_j[0], conf_to_weight(c2, transform)), transform


def test_a_pixel_with_a_non_finite_point_coordinate_or_confidence_weighs_nothing_and_stacks_as_zero():
    c1 = torch.full((24,), 3.0)
    c1[5], c1[6] = math.nan, math.inf
    p = pair(conf1=c1)
    p.pts1_cam1[0].view(-1, 3)[2, 1] = math.nan   # one coordinate only
    p.pts1_cam1[0].view(-1, 3)[3, 0] = -math.inf
    st = stack_of({(0, 1): p}, [(4, 6)] * 2)
    for k in (2, 3, 5, 6):
        assert float(st.w_i[0, k]) == 0.0 and st.pred_i[0, k].tolist() == [0.0, 0.0, 0.0], k
    assert bool(torch.isfinite(st.pred_i).all()) and int((st.w_i[0] > 0).sum()) == 20


def test_a_pairs_score_is_the_product_of_its_views_mean_usable_confidences():
    c1 = torch.full((24,), 2.0)
    c1[:6] = -4.0          # negative: counts 0
    c1[6] = math.nan       # not finite: counts 0
    c2 = torch.full((24,), 3.0)
    p = pair(conf1=c1, conf2=c2)
    p.pts2_cam1[0].view(-1, 3)[:12, 0] = math.nan  # half of view 2 has no point: its confidences count 0
    q = pair(conf1=c2, conf2=c1)
    st = stack_of({(0, 1): p, (1, 0): q}, [(4, 6)] * 2, stride=2)
    mean1 = 2.0 * 17 / 24  # full resolution, whatever the stride
    assert st.score.dtype == torch.float64
    assert math.isclose(float(st.score[0]), mean1 * 3.0 * 12 / 24, rel_tol=1e-9)
    assert math.isclose(float(st.score[1]), 3.0 * mean1, rel_tol=1e-9)


def test_the_pose_heads_transforms_are_stacked_detached_in_float64_only_when_every_pair_has_one():
    T = torch.eye(4)[None].clone()
    T[0, 0, 3] = 0.5
    T.requires_grad_(True)
    both = {(0, 1): pair(T=T), (1, 0): pair(T=T * 2)}
    st = stack_of(both, [(4, 6)] * 2)
    assert st.T.dtype == torch.float64 and not st.T.requires_grad and st.T.shape == (2, 4, 4)
    assert float(st.T[0, 0, 3]) == 0.5 and float(st.T[1, 0, 3]) == 1.0
    one = {(0, 1): pair(T=T.detach()), (1, 0): pair()}
    assert stack_of(one, [(4, 6)] * 2).T is None


# ---------------------------------------------------------------- drop_empty_edges

def test_a_pair_with_no_weight_in_one_view_is_dropped_from_every_field_with_a_warning_naming_it():
    T = torch.eye(4)[None]
    preds = {(0, 1): pair(conf2=3.0, T=T, offset=1.0), (0, 2): pair(conf2=0.5, T=T),
             (1, 2): pair(conf1=0.5, T=T), (2, 0): pair(conf1=4.0, T=T * 3, offset=2.0)}
    st = stack_of(preds, [(4, 6)] * 3)
    with pytest.warns(UserWarning, match=r"2 pair\(s\) have zero weight in a view .* ignored: "
                                         r"\[\(0, 2\), \(1, 2\)\]$"):
        out = drop_empty_edges(st, "log")
    assert out.keys == [(0, 1), (2, 0)] and out.i.tolist() == [0, 2] and out.j.tolist() == [1, 0]
    assert out.num_edges == 2 and out.score.shape == (2,) and out.T.shape == (2, 4, 4)
    assert float(out.T[1, 0, 0]) == 3.0
    for name in ("pred_i", "pred_j", "w_i", "w_j"):
        assert torch.equal(getattr(out, name), getattr(st, name)[[0, 3]]), name
    assert not torch.equal(out.w_i, out.w_j)  # each view keeps its own weights
    assert bool((out.pred_j[:, :, 2] > out.pred_i[:, :, 2]).all())  # view 2 stays view 2
    assert torch.equal(out.uv, st.uv) and out.stride == st.stride


def test_the_dropped_pairs_list_is_cut_after_eight_with_an_ellipsis():
    preds = {(0, j): pair(conf2=0.5) for j in range(1, 9)} | {(1, 0): pair()}
    st = stack_of(preds, [(4, 6)] * 9)
    with pytest.warns(UserWarning, match=r"8 pair\(s\).*\(0, 8\)\]$"):
        drop_empty_edges(st, "log")
    preds[(0, 9)] = pair(conf2=0.5)
    st = stack_of(preds, [(4, 6)] * 10)
    with pytest.warns(UserWarning, match=r"9 pair\(s\).*\(0, 8\)\] \.\.\.$"):
        drop_empty_edges(st, "log")


def test_when_every_pair_has_zero_weight_nothing_is_aligned_and_the_error_says_why():
    st = stack_of({(0, 1): pair(conf1=1.0, conf2=1.0)}, [(4, 6)] * 2)
    with pytest.raises(GraphError, match=r"every pair has zero weight.*conf_transform='id' weighs"):
        drop_empty_edges(st, "log")
    # 'm1' weighs conf - 1: confidences at the floor are the likely reason there too
    st = stack_of({(0, 1): pair(conf1=1.0, conf2=1.0)}, [(4, 6)] * 2, transform="m1")
    with pytest.raises(GraphError, match=r"every confidence <= 1 under .*conf_transform='id' weighs"):
        drop_empty_edges(st, "m1")
    st = stack_of({(0, 1): pair(conf1=0.0, conf2=0.0)}, [(4, 6)] * 2, transform="id")
    with pytest.raises(GraphError, match=r"every pair has zero weight.*masked out\) or not finite"):
        drop_empty_edges(st, "id")


# ---------------------------------------------------------------- check_connected

def test_connectivity_joins_every_pair_in_either_direction_and_checks_the_last_image():
    check_connected(4, [(0, 1), (0, 2), (0, 3)])           # a star: 0 joined several times
    check_connected(4, [(1, 0), (2, 1), (3, 2)])
    check_connected(5, [(0, 1), (2, 3), (3, 4), (1, 4)])
    with pytest.raises(GraphError, match=r"2 groups .*\(\[0, 1, 2\]; \[3\]\)"):
        check_connected(4, [(0, 1), (1, 2)])


def test_a_disconnected_graph_lists_its_groups_in_order_of_their_first_image_up_to_five():
    with pytest.raises(GraphError, match=r"disconnected: 3 groups of images share no pair "
                                         r"\(\[0, 2\]; \[1, 4\]; \[3\]\)"):
        check_connected(5, [(4, 1), (2, 0)])
    with pytest.raises(GraphError, match=r"7 groups .*\(\[0\]; \[1\]; \[2\]; \[3\]; \[4\]; and 2 more\)"):
        check_connected(7, [])  # says how many it left out
    with pytest.raises(GraphError, match=r"\[4\]\)"):
        check_connected(5, [])


# ---------------------------------------------------------------- choose_stride

def test_an_explicit_stride_is_returned_as_a_python_int_and_one_below_one_is_refused():
    assert choose_stride([(10, 10)], 4, 3) == 3
    s = choose_stride([(10, 10)], None, np.int64(2))  # AlignConfig accepts NumPy ints; the report is JSON
    assert s == 2 and type(s) is int
    assert choose_stride([(10, 10)], None, 1) == 1
    for bad in (0, -2):
        with pytest.raises(ValueError, match=f"stride expected >= 1, got {bad}"):
            choose_stride([(10, 10)], None, bad)


def test_without_a_pixel_cap_the_stride_is_one():
    assert choose_stride([(40, 60)], None, None) == 1
    assert choose_stride([(40, 60)], 0, None) == 1


def test_the_automatic_stride_keeps_every_image_under_the_cap_and_no_smaller_stride_keeps_more():
    shapes = [(4, 6), (30, 40)]
    for cap in (1, 2, 12, 20, 100, 300, 1199, 1200, 5000):
        s = choose_stride(shapes, cap, None)
        kept = max(len(r) * len(c) for r, c in (sample_index(h, w, s) for h, w in shapes))
        assert kept <= cap or s >= 40, (cap, s)
        if s > 1:
            smaller = max(len(r) * len(c) for r, c in (sample_index(h, w, s - 1) for h, w in shapes))
            assert smaller > cap or smaller == kept, (cap, s)  # no smaller stride keeps more pixels under the cap
    assert choose_stride(shapes, 1200, None) == 1  # exactly at the cap: full resolution


def test_the_automatic_stride_is_the_smallest_that_fits_even_below_the_square_root_of_the_area_ratio():
    # cell centres keep fewer rows and columns than h / s rounded up: an 8 x 78 map at 17 pixels fits at stride 6
    # (1 x 13 kept), though sqrt(624 / 17) rounds up to 7 (1 x 11)
    for h, w, cap in [(8, 78, 17), (904, 1600, 10000), (30, 40, 100), (224, 224, 96 * 64)]:
        s = choose_stride([(h, w)], cap, None)
        kept = [len(r) * len(c) for r, c in (sample_index(h, w, t) for t in range(1, s + 1))]
        assert kept[-1] <= cap and all(k > cap for k in kept[:-1]), (h, w, cap, s, kept)
    assert choose_stride([(8, 78)], 17, None) == 6
    assert choose_stride([(224, 224)], 96 * 64, None) == 3  # the default cap at the shipped size: as before


# ---------------------------------------------------------------- warnings through global_align

def test_the_self_pair_and_dropped_pair_warnings_point_at_the_line_that_called_global_align():
    sc = make_scene(3, 16, 24, seed=3)
    preds = gt_preds(sc, complete_pairs(3), seed=3)
    preds[(1, 1)] = preds[(0, 1)]
    p = preds[(0, 2)]
    preds[(0, 2)] = PairPrediction(p.pts1_cam1, p.pts2_cam1, p.conf1, torch.ones_like(p.conf2))  # log weighs 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        global_align(views_of(sc), preds, config=AlignConfig(quiet=True, niter=0, conf_transform="log"))
    mine = [w for w in caught if "itself" in str(w.message) or "zero weight" in str(w.message)]
    assert len(mine) == 2, [str(w.message) for w in caught]
    assert all(w.filename == __file__ for w in mine), [(w.filename, str(w.message)[:40]) for w in mine]


# ---------------------------------------------------------------- the dropped-pair warning's reason

def _stack(conf2, transform):
    def p(c2):
        pts = torch.randn(1, 4, 6, 3)
        return PairPrediction(pts, pts + 1, torch.full((1, 4, 6), 3.0), torch.full((1, 4, 6), c2))
    preds = {(0, 1): p(3.0), (1, 2): p(conf2), (0, 2): p(3.0)}
    shapes = [(4, 6)] * 3
    return build_stack(preds, check_preds(preds, 3, shapes), shapes, 1, transform)


def test_the_dropped_pair_warning_names_the_transform_the_weights_were_made_with():
    with pytest.warns(UserWarning) as rec:
        drop_empty_edges(_stack(1.0, "m1"), "m1")  # m1: conf - 1 = 0 everywhere in view 2
    msg = str(rec[0].message)
    assert "conf_transform='m1'" in msg and "conf_transform='log'" not in msg, msg


@pytest.mark.parametrize("transform", ["sqrt", "id"])
def test_the_dropped_pair_warning_counts_negative_confidences_among_those_that_weigh_nothing(transform):
    with pytest.warns(UserWarning) as rec:
        drop_empty_edges(_stack(-2.0, transform), transform)
    msg = str(rec[0].message)
    assert "confidence <= 0" in msg, msg
