"""Unit tests of pointmap.matching on small hand-built descriptors, against slow loop references."""

import math

import pytest
import torch

import pointmap as pm
from pointmap.matching import match_coarse, reciprocal_nn_bruteforce, reciprocal_nn_fast


def unit(*shape, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(*shape, generator=g), dim=-1)


def pair(d1, d2, dc1=None, dc2=None, p1=None, p2=None):
    """A batch-1 prediction with descriptors d1 [H1, W1, D], d2 [H2, W2, D] and the given confidences."""
    (H1, W1), (H2, W2) = d1.shape[:2], d2.shape[:2]
    dc1 = torch.ones(H1, W1) if dc1 is None else dc1
    dc2 = torch.ones(H2, W2) if dc2 is None else dc2
    p1 = torch.zeros(H1, W1, 3) if p1 is None else p1
    p2 = torch.zeros(H2, W2, 3) if p2 is None else p2
    return pm.PairPrediction(p1[None], p2[None], torch.ones(1, H1, W1), torch.ones(1, H2, W2), desc1=d1[None],
                             desc2=d2[None], desc_conf1=dc1[None], desc_conf2=dc2[None])


def loop_matches(d1, d2, c1, c2, min_conf=None):
    """Mutual nearest neighbours by dot product over all finite (and confident enough) pixels, one pixel pair at a
    time in float64: {(u1, v1, u2, v2): sqrt(c1 * c2)}."""
    def pixels(d, c):
        H, W = d.shape[:2]
        return [(u, v) for v in range(H) for u in range(W) if all(math.isfinite(x) for x in d[v, u].tolist())
                and (min_conf is None or c[v, u] >= min_conf)]

    P1, P2 = pixels(d1, c1), pixels(d2, c2)
    a, b = d1.double(), d2.double()

    def best(p, view, others, other_view):
        return max(others, key=lambda o: float(view[p[1], p[0]] @ other_view[o[1], o[0]]))

    out = {}
    for p in P1:
        q = best(p, a, P2, b)
        if best(q, b, P1, a) == p:
            out[p + q] = math.sqrt(float(c1[p[1], p[0]]) * float(c2[q[1], q[0]]))
    return out


def as_dict(m):
    return {tuple(int(t) for t in x1 + x2): float(s) for x1, x2, s in zip(m.xy1.tolist(), m.xy2.tolist(), m.score)}


def test_dense_matches_on_views_of_different_sizes_are_the_mutual_neighbours_a_pixel_loop_finds():
    d1, d2 = unit(5, 7, 6, seed=1), unit(6, 4, 6, seed=2)
    d2[:3, :3] = d1[1:4, 2:5]  # a shared patch, so that there are matches whatever the noise
    d1[0, 0, 2] = d1[2, 3, 0] = float("nan")  # one non-finite component drops the pixel
    d2[0, 1, 5] = d2[1, 0, 1] = float("inf")
    d1[1, 2] = d2[0, 0] * 0.9 + 0.1 * d2[2, 3]
    g = torch.Generator().manual_seed(3)
    c1 = torch.randint(1, 4, (5, 7), generator=g).float()  # confidences 1, 2, 3: some exactly at min_conf=2
    c2 = torch.randint(1, 4, (6, 4), generator=g).float()
    pred = pair(d1, d2, c1, c2)
    for min_conf in (None, 2.0):
        want = loop_matches(d1, d2, c1, c2, min_conf)
        assert len(want) >= 4
        for kw in ({"subsample": 1}, {"bruteforce": True}):
            got = as_dict(pm.match(pred, use="desc", min_conf=min_conf, **kw))
            assert got.keys() == want.keys(), kw
            assert all(abs(got[k] - want[k]) < 1e-5 for k in want)


def test_the_fast_path_seeds_exactly_the_grid_half_a_step_in_from_the_corner_every_subsample_pixels():
    H, W = 7, 10
    d = unit(H, W, 32, seed=4)  # view 2 is view 1: every pixel is its own mutual neighbour, found from its own seed
    d[0, 0] = float("nan")  # pixel 0 not valid: compact indices and pixel indices differ by one
    pred = pair(d, d.clone())
    for s in (1, 2, 3, 4):
        m = pm.match(pred, use="desc", subsample=s, max_iter=1)
        want = {(u, v) for v in range(s // 2, H, s) for u in range(s // 2, W, s)} - {(0, 0)}
        assert {tuple(int(t) for t in xy) for xy in m.xy1.tolist()} == want, s
        assert torch.equal(m.xy1, m.xy2)


def chain():
    """1-D points (L2): seed 0 of view 1 -> view-2 point 0 -> view-1 point 1 <-> view-2 point 1 (mutual), two
    round trips from seed 0 and one from seed 1."""
    return torch.tensor([[0.0], [2.0]]), torch.tensor([[1.2], [2.1]])


def test_a_seed_reaches_a_mutual_pair_two_round_trips_away_only_with_max_iter_of_at_least_two():
    f1, f2 = chain()
    seed0 = torch.tensor([0])
    assert [t.tolist() for t in reciprocal_nn_fast(f1, f2, seed0, "l2", max_iter=1)] == [[], []]
    for n in (2, 3):
        assert [t.tolist() for t in reciprocal_nn_fast(f1, f2, seed0, "l2", max_iter=n)] == [[1], [1]]
    assert [t.tolist() for t in reciprocal_nn_bruteforce(f1, f2, "l2")] == [[1], [1]]


def test_a_mutual_pair_reached_from_two_seeds_is_returned_once():
    f1, f2 = chain()
    i1, i2 = reciprocal_nn_fast(f1, f2, torch.tensor([0, 1]), "l2")
    assert i1.tolist() == [1] and i2.tolist() == [1]
    f1, f2 = torch.cat([f1, f1 + 10]), torch.cat([f2, f2 + 10])  # two chains: sorted by view-1 index
    i1, i2 = reciprocal_nn_fast(f1, f2, torch.tensor([3, 2, 1, 0]), "l2")
    assert i1.tolist() == [1, 3] and i2.tolist() == [1, 3]


def test_without_a_valid_seed_or_a_valid_pixel_in_either_view_matching_returns_no_matches():
    f1, f2 = chain()
    i1, i2 = reciprocal_nn_fast(f1, f2, torch.zeros(0, dtype=torch.long))
    assert i1.numel() == 0 and i2.numel() == 0
    d = unit(4, 4, 8, seed=5)
    holes = d.clone()
    holes[1::2, 1::2] = float("nan")  # every seed of subsample=2 is not finite; the other pixels are
    assert len(pm.match(pair(holes, d), use="desc", subsample=2)) == 0
    low = torch.ones(4, 4)
    for c1, c2 in ((low, low * 5), (low * 5, low)):  # min_conf keeps view 1 but none of view 2, or the reverse
        m = pm.match(pair(d, d, c1, c2), use="desc", min_conf=3.0, subsample=1)
        assert len(m) == 0 and m.xy1.shape == m.xy2.shape == (0, 2) and m.score.shape == (0,)


def test_auto_matches_on_descriptors_when_there_are_some_and_an_unknown_use_is_refused():
    d1, d2 = unit(4, 5, 8, seed=6), unit(4, 5, 8, seed=7)
    d2[:, 1:] = d1[:, :-1]  # by descriptors, pixel (u, v) of view 1 is pixel (u + 1, v) of view 2
    pts = unit(4, 5, 3, seed=8)  # by points, pixel (u, v) is pixel (u, v)
    pred = pair(d1, d2, p1=pts, p2=pts.clone())
    auto, desc = pm.match(pred, subsample=1), pm.match(pred, subsample=1, use="desc")
    assert torch.equal(auto.xy1, desc.xy1) and torch.equal(auto.xy2, desc.xy2)
    assert ((desc.xy2 - desc.xy1) == torch.tensor([1.0, 0.0])).all(-1).sum() >= 12
    with pytest.raises(pm.ShapeError, match="use expected 'auto', 'desc' or 'pts', got 'points'"):
        pm.match(pred, use="points")


def test_the_border_is_measured_against_each_views_own_width_and_height():
    d1, d2 = unit(12, 8, 8, seed=9), unit(8, 12, 8, seed=10)
    d2[:8, :8] = d1[:8]  # view-1 pixel (u, v) is view-2 pixel (u, v) for v < 8
    pred = pair(d1, d2)
    every = pm.match(pred, use="desc", subsample=1)
    for b in (1, 2):
        keep = [k for k, (x1, x2) in enumerate(zip(every.xy1.tolist(), every.xy2.tolist()))
                if b <= x1[0] < 8 - b and b <= x1[1] < 12 - b and b <= x2[0] < 12 - b and b <= x2[1] < 8 - b]
        got = pm.match(pred, use="desc", subsample=1, border=b)
        assert torch.equal(got.xy1, every.xy1[keep]) and torch.equal(got.xy2, every.xy2[keep])


def test_reciprocal_neighbours_tell_apart_dot_products_closer_than_float32_resolution():
    f1 = torch.tensor([[1.0, 1e-8]])  # 1 and 1 + 1e-8 are one float32 number, two float64 ones
    f2 = torch.tensor([[1.0, 0.0], [1.0, 1.0]])
    assert [t.tolist() for t in reciprocal_nn_bruteforce(f1, f2)] == [[0], [1]]


def loop_cells(d, c, p):
    """{(u, v) cell centre: (unit mean descriptor, mean confidence)} over the finite cells, one cell at a time."""
    H, W = d.shape[:2]
    out = {}
    for v in range(0, H, p):
        for u in range(0, W, p):
            mean = d[v: v + p, u: u + p].double().reshape(-1, d.shape[-1]).mean(0)
            if bool(torch.isfinite(mean).all()):
                out[(u + p // 2, v + p // 2)] = (mean / mean.norm(), float(c[v: v + p, u: u + p].double().mean()))
    return out


def loop_coarse(d1, d2, c1, c2, p):
    """Mutual nearest cells by dot product, with their centres and score sqrt(mean conf1 * mean conf2), and the
    refined view-2 pixel: the best by dot product with view 1's centre pixel among the finite pixels of the matched
    cell grown by p // 2."""
    k1, k2 = loop_cells(d1, c1, p), loop_cells(d2, c2, p)
    H2, W2 = d2.shape[:2]
    out = {}
    for x1, (f1, s1) in k1.items():
        x2 = max(k2, key=lambda x: float(f1 @ k2[x][0]))
        if max(k1, key=lambda x: float(k1[x][0] @ k2[x2][0])) != x1:
            continue
        u0, v0 = x2[0] - p // 2, x2[1] - p // 2
        window = [(u, v) for v in range(max(0, v0 - p // 2), min(H2, v0 + p + p // 2))
                  for u in range(max(0, u0 - p // 2), min(W2, u0 + p + p // 2))
                  if bool(torch.isfinite(d2[v, u]).all())]
        q = d1[x1[1], x1[0]].double()
        fine = max(window, key=lambda x: float(q @ d2[x[1], x[0]].double()))
        out[x1] = (x2, fine, math.sqrt(max(0.0, s1 * k2[x2][1])))
    return out


def coarse_scene(p=4):
    """View 1 of 3 x 4 cells, view 2 of 4 x 3 cells sharing most of their cell codes (plus pixel noise), a non-finite
    pixel in one cell of each, and confidences that differ from pixel to pixel (one cell's mean negative)."""
    g = torch.Generator().manual_seed(11)
    codes1 = torch.nn.functional.normalize(torch.randn(3, 4, 16, generator=g), dim=-1)
    codes2 = torch.nn.functional.normalize(torch.randn(4, 3, 16, generator=g), dim=-1)
    codes2[1:4, 0:3] = codes1[0:3, 1:4]

    def pix(codes):
        x = codes.repeat_interleave(p, 0).repeat_interleave(p, 1)
        return torch.nn.functional.normalize(x + 0.6 * torch.randn(x.shape, generator=g), dim=-1)

    d1, d2 = pix(codes1), pix(codes2)
    d1[p + 1, 2 * p + 2, 3] = float("nan")
    d2[2 * p + 3, 1, 0] = float("inf")
    c1 = torch.rand(3 * p, 4 * p, generator=g) * 3 - 0.5
    c2 = torch.rand(4 * p, 3 * p, generator=g) * 3 - 0.5
    c1[:p, p: 2 * p] = -1.0  # view-1 cell (0, 1), view-2 cell (1, 0): a negative mean, score 0
    return d1, d2, c1, c2


def test_coarse_matches_on_views_of_different_sizes_are_the_mutual_cells_a_loop_finds_and_refine_as_it_does():
    p = 4
    d1, d2, c1, c2 = coarse_scene(p)
    want = loop_coarse(d1, d2, c1, c2, p)
    assert len(want) >= 6
    pred = pair(d1, d2, c1, c2)
    for refine in (False, True):
        m = match_coarse(pred, patch=p, refine=refine)
        got = {tuple(int(t) for t in x1): (tuple(int(t) for t in x2), float(s))
               for x1, x2, s in zip(m.xy1.tolist(), m.xy2.tolist(), m.score)}
        assert got.keys() == want.keys(), refine
        for x1, (x2, fine, score) in want.items():
            assert got[x1][0] == (fine if refine else x2) and abs(got[x1][1] - score) < 1e-5


def test_coarse_matching_refuses_a_patch_that_is_not_a_positive_int_dividing_both_views():
    d1, d2, c1, c2 = coarse_scene(4)
    pred = pair(d1, d2, c1, c2)
    for patch in (0, -4, 4.0, True):
        with pytest.raises(pm.ShapeError, match="patch"):
            match_coarse(pred, patch=patch)
    with pytest.raises(pm.ShapeError, match=r"descriptor maps 12x16 and 10x12 must be multiples of patch=4"):
        match_coarse(pair(d1, d2[:10].contiguous()), patch=4)


def test_a_map_narrower_than_half_the_seed_step_is_still_seeded_inside_it():
    torch.manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(1, 4, 30, 8), dim=-1)
    ones = torch.ones(1, 4, 30)
    pred = pm.PairPrediction(torch.zeros(1, 4, 30, 3), torch.zeros(1, 4, 30, 3), ones, ones, desc1=d,
                             desc2=d.clone(), desc_conf1=ones, desc_conf2=ones)
    m = pm.match(pred)  # subsample 8: rows from min(4, 3) = 3, columns 4, 12, 20, 28; identical views match in place
    assert sorted(m.xy1.tolist()) == [[4.0, 3.0], [12.0, 3.0], [20.0, 3.0], [28.0, 3.0]]
    assert torch.equal(m.xy1, m.xy2)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_coarse_refinement_never_lands_on_a_non_finite_pixel_of_a_neighbouring_cell(bad):
    torch.manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(1, 8, 8, 4), dim=-1)
    d2 = d.clone()
    d2[0, 4, 4] = bad  # in the right-hand cell, inside the window grown around the left-hand cell (columns 0-5)
    d2[0, 4, 4, 0] = 1.0  # a NaN or inf vector with one finite entry: not finite either way
    ones = torch.ones(1, 8, 8)
    pred = pm.PairPrediction(torch.zeros(1, 8, 8, 3), torch.zeros(1, 8, 8, 3), ones, ones, desc1=d, desc2=d2,
                             desc_conf1=ones, desc_conf2=ones)
    m = match_coarse(pred, patch=4, refine=True)
    assert len(m) > 0 and torch.isfinite(d2[0, m.xy2[:, 1].long(), m.xy2[:, 0].long()]).all()
