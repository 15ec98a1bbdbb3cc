"""RoPE2D and the output transforms, checked against slow formula-by-formula references."""

import math

import pytest
import torch

from pointmap.model.blocks import apply_rope, patch_positions, rope_tables
from pointmap.model.config import PRESETS
from pointmap.model.heads import regress_conf, regress_points


def rope_reference(x, pos, base):
    """x [N, D] one head; rotate channel i with i + D/4 inside each half, angle = pos * base^(-2k/(D/2))."""
    N, D = x.shape
    half, q = D // 2, D // 4
    out = x.clone().double()
    for n in range(N):
        for h, p in enumerate((pos[n, 0], pos[n, 1])):  # first half: row, second half: column
            for k in range(q):
                theta = float(p) * base ** (-2 * k / half)
                i, j = h * half + k, h * half + k + q
                a, b = float(x[n, i]), float(x[n, j])
                out[n, i] = a * math.cos(theta) - b * math.sin(theta)
                out[n, j] = b * math.cos(theta) + a * math.sin(theta)
    return out


def test_rope_rotates_row_then_column_halves_with_rotate_half_pairing():
    torch.manual_seed(0)
    pos = patch_positions(3, 5)
    x = torch.randn(pos.shape[0], 16)
    cos, sin = rope_tables(pos, 16, 100.0, torch.float64)
    fast = apply_rope(x.double()[None, None], cos, sin)[0, 0]
    assert torch.allclose(fast, rope_reference(x, pos, 100.0), atol=1e-10)


def test_rope_attention_scores_depend_only_on_relative_position():
    torch.manual_seed(1)
    q, k = torch.randn(1, 1, 1, 32).double(), torch.randn(1, 1, 1, 32).double()

    def score(pq, pk):
        cq, sq = rope_tables(torch.tensor([pq]), 32, 100.0, torch.float64)
        ck, sk = rope_tables(torch.tensor([pk]), 32, 100.0, torch.float64)
        return float((apply_rope(q, cq, sq) * apply_rope(k, ck, sk)).sum())

    assert abs(score((2, 3), (5, 1)) - score((7, 10), (10, 8))) < 1e-5  # tables are float32 angles
    assert abs(score((2, 3), (5, 1)) - score((2, 3), (5, 2))) > 1e-2


def test_patch_positions_are_row_major_row_col_pairs():
    pos = patch_positions(2, 3)
    assert pos.tolist() == [[0, 0], [0, 1], [0, 2], [1, 0], [1, 1], [1, 2]]


def test_points_keep_direction_and_their_norm_becomes_expm1_of_the_raw_norm():
    raw = torch.tensor([[0.3, -0.4, 1.2], [0.0, 0.0, 0.0], [-2.0, 1.0, 0.5]])
    pts = regress_points(raw, ("exp", -math.inf, math.inf))
    d = raw.norm(dim=-1)
    assert torch.allclose(pts.norm(dim=-1), torch.expm1(d), atol=1e-6)
    nz = d > 0
    assert torch.allclose(pts[nz] / pts[nz].norm(dim=-1, keepdim=True), raw[nz] / d[nz, None], atol=1e-6)
    assert torch.equal(pts[1], torch.zeros(3))


def test_confidence_is_one_plus_exp_and_descriptor_confidence_is_exp():
    x = torch.tensor([-3.0, 0.0, 2.5])
    assert torch.allclose(regress_conf(x, ("exp", 1.0, math.inf)), 1 + x.exp())
    assert torch.allclose(regress_conf(x, ("exp", 0.0, math.inf)), x.exp())
    assert torch.allclose(regress_conf(x, ("sigmoid", 0.0, 2.0)), 2 * torch.sigmoid(x))


def test_dpt_hooks_are_encoder_output_and_decoder_layers_at_half_three_quarters_and_end():
    assert PRESETS["dust3r_512_dpt"].dpt_hooks == (0, 6, 9, 12)
    assert PRESETS["mast3r_512"].dpt_hooks == (0, 6, 9, 12)


def test_cross_attention_scores_are_the_logits_forward_softmaxes():
    from pointmap.model.blocks import CrossAttention, RopeCache

    torch.manual_seed(0)
    att = CrossAttention(32, 4)
    x, y = torch.randn(2, 6, 32), torch.randn(2, 12, 32)
    rope = RopeCache(100.0)
    rx, ry = rope(2, 3, 8, "cpu", torch.float32), rope(3, 4, 8, "cpu", torch.float32)
    s = att.scores(x, y, rx, ry)  # [2, 4, 6, 12]
    v = att.projv(y).reshape(2, 12, 4, 8).transpose(1, 2)
    by_hand = att.proj((s.softmax(-1) @ v).transpose(1, 2).reshape(2, 6, 32))
    assert s.shape == (2, 4, 6, 12)
    assert torch.allclose(att(x, y, rx, ry), by_hand, atol=1e-5)
    assert torch.equal(att.scores(x, y, rx, ry, heads=2), s[:, :2])


def postprocess_reference(raw, cfg):
    """The head's channels read one slice at a time: points 0-2, confidence 3, descriptors, their confidence."""
    from torch.nn.functional import normalize

    f = raw.permute(0, 2, 3, 1)
    out = {"pts": regress_points(f[..., 0:3], cfg.depth_mode), "conf": regress_conf(f[..., 3], cfg.conf_mode)}
    if cfg.has_desc:
        out["desc"] = normalize(f[..., 4:4 + cfg.desc_dim], dim=-1, eps=0.0)
        out["desc_conf"] = (regress_conf(f[..., 4 + cfg.desc_dim], cfg.desc_conf_mode) if cfg.two_confs
                            else out["conf"])
    return out


@pytest.mark.parametrize("name, extra", [("test", 0), ("test", 2), ("test_one_conf", 0), ("dust3r_224_linear", 0),
                                         ("dust3r_224_linear", 1)])
def test_the_head_channels_split_gives_the_slice_by_slice_outputs_and_gradients(name, extra):
    from pointmap.model.heads import postprocess

    cfg = PRESETS["test"].replace(two_confs=False) if name == "test_one_conf" else PRESETS[name]
    known = 4 + (cfg.desc_dim + int(cfg.two_confs) if cfg.has_desc else 0)
    torch.manual_seed(0)
    raw = torch.randn(2, known + extra, 5, 6, dtype=torch.float64, requires_grad=True)  # extra: ignored channels
    weights = {k: torch.randn_like(v) for k, v in postprocess_reference(raw, cfg).items()}
    grads = []
    for fn in (postprocess, postprocess_reference):
        out = fn(raw, cfg)
        assert set(out) == set(weights)
        sum((out[k] * w).sum() for k, w in weights.items()).backward()
        grads.append((raw.grad.clone(), {k: v.detach() for k, v in out.items()}))
        raw.grad = None
    assert torch.allclose(grads[0][0], grads[1][0], atol=1e-12)
    for k in weights:
        assert torch.allclose(grads[0][1][k], grads[1][1][k], atol=1e-12), k
