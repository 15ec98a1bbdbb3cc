"""Unit checks of pointmap.model.heads, each against a small by-hand reference: the token-to-map layout, the
linear, DPT and descriptor heads, the descriptor stem and its fuse, the output transforms, the 6-D rotation, the
patch centres and Fourier features, and the features the pose and focal heads pool."""

import math

import pytest
import torch
import torch.nn.functional as F

import pointmap as pm
from pointmap.model.heads import (
    DPT,
    DescStem,
    DownstreamHead,
    FocalHead,
    FusionBlock,
    MatchScores,
    PoolBlock,
    PoseHead,
    ResidualConvUnit,
    Upsample2x,
    fourier,
    patch_centres,
    postprocess,
    regress_conf,
    regress_points,
    tokens_to_map,
)

P = 16  # the patch size of every preset


def _tokens(cfg, B, h, w, seed=0):
    """The decoder's token list [enc_out, dec_1, ..., dec_L] of one view, random."""
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(B, h * w, cfg.enc_dim, generator=g)] + \
        [torch.randn(B, h * w, cfg.dec_dim, generator=g) for _ in range(cfg.dec_depth)]


def _shuffle_reference(t, h, w, c):
    """[B, h*w, c*P*P] token features -> [B, c, h*P, w*P], pixel by pixel: channel k of pixel (y, x) is feature
    k*P*P + (y % P)*P + x % P of token (y // P)*w + x // P."""
    B = t.shape[0]
    out = torch.empty(B, c, h * P, w * P, dtype=t.dtype)
    for y in range(h * P):
        for x in range(w * P):
            n = (y // P) * w + x // P
            for k in range(c):
                out[:, k, y, x] = t[:, n, k * P * P + (y % P) * P + x % P]
    return out


def _all_parameters_get_a_gradient(module, loss):
    loss.backward()
    return [name for name, p in module.named_parameters() if p.grad is None or not bool(p.grad.abs().sum() > 0)]


def test_tokens_become_a_channel_map_in_row_major_patch_order():
    tokens = torch.arange(2 * 6 * 3, dtype=torch.float32).reshape(2, 6, 3)  # B=2, h*w=2*3 tokens, 3 channels
    m = tokens_to_map(tokens, 2, 3)
    assert m.shape == (2, 3, 2, 3)
    for n in range(6):
        assert torch.equal(m[:, :, n // 3, n % 3], tokens[:, n])


@pytest.mark.parametrize("two_confs", [True, False])
def test_a_linear_downstream_head_reads_the_last_decoder_tokens_and_its_descriptors_read_encoder_then_decoder(
        two_confs):
    cfg = pm.PRESETS["test"].replace(head="catmlp+linear", enc_dim=48, enc_heads=2, two_confs=two_confs)
    torch.manual_seed(0)
    head = DownstreamHead(cfg).eval()
    tokens = _tokens(cfg, 2, 2, 3)
    with torch.no_grad():
        raw = head(tokens, 2 * P, 3 * P)
        pts = _shuffle_reference(head.proj(tokens[-1]), 2, 3, 4)
        feats = head.head_local_features(torch.cat([tokens[0], tokens[-1]], dim=-1))
        desc = _shuffle_reference(feats, 2, 3, cfg.desc_dim + int(cfg.two_confs))
    assert raw.shape == (2, 4 + cfg.desc_dim + int(cfg.two_confs), 32, 48)
    assert torch.allclose(raw, torch.cat([pts, desc], dim=1), atol=1e-6)


def test_a_dpt_downstream_head_puts_its_four_channels_before_the_descriptors():
    cfg = pm.PRESETS["test"]
    torch.manual_seed(0)
    head = DownstreamHead(cfg).eval()
    tokens = _tokens(cfg, 1, 2, 3)
    with torch.no_grad():
        raw = head(tokens, 2 * P, 3 * P)
        dpt = head.dpt(tokens, 2 * P, 3 * P)
    assert dpt.shape == (1, 4, 32, 48) and torch.equal(raw[:, :4], dpt)


def test_the_dpt_takes_the_encoder_output_at_its_first_hook_when_encoder_and_decoder_widths_differ():
    cfg = pm.PRESETS["test"].replace(enc_dim=48, enc_heads=2)
    torch.manual_seed(0)
    dpt = DPT(cfg, 4).eval()
    tokens = _tokens(cfg, 1, 3, 2)
    with torch.no_grad():
        out = dpt(tokens, 3 * P, 2 * P)
        unhooked = [k for k in range(len(tokens)) if k not in cfg.dpt_hooks]
        for k in unhooked:
            tokens[k] += 1.0
        same = dpt(tokens, 3 * P, 2 * P)
    assert out.shape == (1, 4, 48, 32) and torch.equal(out, same)


def test_every_dpt_parameter_shapes_its_output():
    cfg = pm.PRESETS["test"]
    torch.manual_seed(0)
    dpt = DPT(cfg, 4)
    out = dpt(_tokens(cfg, 1, 3, 2), 3 * P, 2 * P)
    unused = _all_parameters_get_a_gradient(dpt, (out * torch.randn_like(out)).sum())
    # the deepest fusion block has no lateral input: its first unit is unused, as in the official head
    assert unused and all(name.startswith("scratch.refinenet4.resConfUnit1.") for name in unused)


def test_the_dpt_output_layer_reads_rectified_features():
    cfg = pm.PRESETS["test"]
    torch.manual_seed(0)
    dpt = DPT(cfg, 4).eval()
    seen = []
    dpt.head[-1].register_forward_pre_hook(lambda mod, args: seen.append(args[0]))
    with torch.no_grad():
        dpt(_tokens(cfg, 1, 2, 2), 2 * P, 2 * P)
    assert float(seen[0].min()) >= 0 and float(seen[0].max()) > 0


def test_residual_conv_units_and_fusion_blocks_follow_the_dpt_formulas():
    torch.manual_seed(0)
    rcu, fuse = ResidualConvUnit(4), FusionBlock(4)
    x, lat = torch.randn(1, 4, 3, 5), torch.randn(1, 4, 3, 5)

    def rcu_ref(m, t):
        return t + m.conv2(F.relu(m.conv1(F.relu(t))))

    with torch.no_grad():
        assert torch.allclose(rcu(x), rcu_ref(rcu, x), atol=1e-6)
        up = F.interpolate(rcu_ref(fuse.resConfUnit2, x + rcu_ref(fuse.resConfUnit1, lat)), size=(6, 10),
                           mode="bilinear", align_corners=True)
        assert torch.allclose(fuse(x, lat), fuse.out_conv(up), atol=1e-6)
        alone = F.interpolate(rcu_ref(fuse.resConfUnit2, x), size=(6, 10), mode="bilinear", align_corners=True)
        assert torch.allclose(fuse(x), fuse.out_conv(alone), atol=1e-6)


def test_the_dpt_upsampling_is_bilinear_with_the_corners_aligned():
    x = torch.tensor([[[[0.0, 3.0], [6.0, 9.0]]]])
    up = Upsample2x()(x)
    # align_corners: the corners stay, the 4 samples spread the range evenly (0, 1, 2, 3 along a row)
    assert torch.allclose(up[0, 0, 0], torch.tensor([0.0, 1.0, 2.0, 3.0]))
    assert torch.allclose(up[0, 0, :, 0], torch.tensor([0.0, 2.0, 4.0, 6.0]))


def test_the_descriptor_stem_is_three_gelu_convolutions_unshuffled_into_token_layout():
    torch.manual_seed(0)
    stem = DescStem(2, P).eval()
    x = torch.rand(1, 3, 2 * P, 3 * P)
    with torch.no_grad():
        y = x
        for conv, dil in zip(stem.convs, (1, 2, 4)):
            y = F.gelu(F.conv2d(y, conv.weight, conv.bias, padding=dil, dilation=dil))
        got = stem(x)
    assert got.shape == (1, 6, 2 * P * P)
    for n in range(6):  # token n holds patch n's pixels, channel-major
        r, c = divmod(n, 3)
        want = y[0, :, r * P:(r + 1) * P, c * P:(c + 1) * P].reshape(-1)
        assert torch.allclose(got[0, n], want, atol=1e-6)


def test_a_downstream_head_built_with_a_stem_starts_with_a_fuse_that_changes_nothing():
    cfg = pm.PRESETS["test"].replace(desc_stem=3)
    torch.manual_seed(0)
    head = DownstreamHead(cfg)
    n = cfg.desc_dim + int(cfg.two_confs)
    desc, local = torch.randn(1, n, 2 * P, 3 * P), torch.randn(1, 6, 3 * P * P)
    assert torch.equal(head.fuse_local(desc, local), desc)


def test_the_fuse_adds_a_1x1_convolution_of_stem_features_then_descriptors():
    cfg = pm.PRESETS["test"].replace(desc_stem=3)
    torch.manual_seed(0)
    head = DownstreamHead(cfg)
    n = cfg.desc_dim + int(cfg.two_confs)
    with torch.no_grad():
        head.desc_fuse.weight.normal_()
        head.desc_fuse.bias.normal_()
        desc, local = torch.randn(1, n, 2 * P, 3 * P), torch.randn(1, 6, 3 * P * P)
        stem = _shuffle_reference(local, 2, 3, 3)
        w = head.desc_fuse.weight[:, :, 0, 0]
        want = desc + torch.einsum("oc,bchw->bohw", w, torch.cat([stem, desc], 1)) + head.desc_fuse.bias[:, None, None]
        assert torch.allclose(head.fuse_local(desc, local), want, atol=1e-4)


def test_a_stem_head_called_without_local_features_refuses_in_one_line():
    cfg = pm.PRESETS["test"].replace(desc_stem=3)
    head = DownstreamHead(cfg)
    with pytest.raises(pm.ShapeError, match="need the encoder's local features"):
        head(_tokens(cfg, 1, 2, 2), 2 * P, 2 * P)


@pytest.mark.parametrize("head_kind", ["catmlp+dpt", "catmlp+linear"])
def test_reset_conf_sets_the_confidence_channel_everywhere_and_leaves_the_others(head_kind):
    cfg = pm.PRESETS["test"].replace(head=head_kind)
    torch.manual_seed(0)
    head = DownstreamHead(cfg)
    tokens = _tokens(cfg, 1, 2, 3)
    with torch.no_grad():
        before = head(tokens, 2 * P, 3 * P)
    head.reset_conf(-0.75)  # outside no_grad: the parameters require grad
    assert all(p.requires_grad for p in head.parameters())
    with torch.no_grad():
        after = head(tokens, 2 * P, 3 * P)
    assert torch.equal(after[:, :3], before[:, :3]) and torch.equal(after[:, 4:], before[:, 4:])
    assert torch.equal(after[:, 3], torch.full_like(after[:, 3], -0.75))


def test_points_with_a_tiny_raw_norm_keep_that_norm():
    raw = torch.tensor([[1e-5, -2e-5, 2e-5], [3e-4, 0.0, -4e-4]], dtype=torch.float64)
    pts = regress_points(raw, ("exp", -math.inf, math.inf))
    assert torch.allclose(pts, raw, rtol=1e-3)  # expm1(d) ~ d for small d: direction times d is the raw vector


def test_the_square_depth_mode_squares_the_norm_and_linear_returns_the_raw_points():
    raw = torch.tensor([[0.3, -0.4, 1.2], [-2.0, 1.0, 0.5]])
    d = raw.norm(dim=-1, keepdim=True)
    assert torch.allclose(regress_points(raw, ("square", -math.inf, math.inf)), raw / d * d.square(), atol=1e-6)
    assert torch.equal(regress_points(raw, ("linear", -math.inf, math.inf)), raw)


@pytest.mark.parametrize("mode", [("exp", -math.inf, math.inf), ("square", -math.inf, math.inf)])
def test_the_point_transforms_have_the_analytic_gradient(mode):
    raw = torch.tensor([[0.3, -0.4, 1.2], [-2.0, 1.0, 0.5]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: regress_points(x, mode), (raw,))


def test_confidences_respect_a_finite_ceiling_and_a_nonzero_floor():
    x = torch.tensor([-20.0, 0.0, 1.0, 20.0])
    assert torch.allclose(regress_conf(x, ("sigmoid", 1.0, 3.0)), 1 + 2 * torch.sigmoid(x))
    got = regress_conf(x, ("exp", 1.0, 5.0))
    assert torch.allclose(got, torch.tensor([1.0 + math.exp(-20.0), 2.0, 1 + math.e, 5.0]))


def test_a_one_confidence_model_gets_its_descriptor_confidence_as_a_copy_of_the_confidence():
    cfg = pm.PRESETS["test"].replace(two_confs=False)
    raw = torch.randn(1, 4 + cfg.desc_dim, 3, 4)
    out = postprocess(raw, cfg)
    assert torch.equal(out["desc_conf"], out["conf"])
    out["desc_conf"].zero_()  # a caller masking one leaves the other
    assert bool((out["conf"] >= 1).all())


def test_descriptors_have_the_analytic_gradient_of_a_normalisation():
    cfg = pm.PRESETS["test"]
    raw = torch.randn(1, 4 + cfg.desc_dim + 1, 2, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda r: postprocess(r, cfg)["desc"], (raw,))


def test_patch_centres_are_row_major_x_y_in_units_of_half_the_long_side():
    c = patch_centres(2, 4)
    xs, ys = [-0.75, -0.25, 0.25, 0.75], [-0.25, 0.25]
    assert torch.allclose(c, torch.tensor([[x, y] for y in ys for x in xs]))
    assert torch.allclose(patch_centres(3, 1), torch.tensor([[0.0, -2 / 3], [0.0, 0.0], [0.0, 2 / 3]]))


def test_fourier_features_are_the_sines_then_the_cosines_of_x_then_y_at_halved_octaves():
    xy = torch.tensor([[0.5, -0.25]], dtype=torch.float64)
    ang = torch.tensor([0.5 * math.pi / 2, 0.5 * math.pi, -0.25 * math.pi / 2, -0.25 * math.pi], dtype=torch.float64)
    assert torch.allclose(fourier(xy, 2), torch.cat([ang.sin(), ang.cos()])[None])


def _pool_reference(blk, q, x):
    B, N, C = x.shape
    h = blk.heads
    qn = blk.q(blk.norm_q(q))
    k, v = blk.kv(blk.norm_kv(x)).split(C, dim=-1)
    outs = []
    for i in range(h):
        s = slice(i * C // h, (i + 1) * C // h)
        a = (qn[..., s] @ k[..., s].transpose(1, 2) / math.sqrt(C // h)).softmax(-1)
        outs.append(a @ v[..., s])
    q = q + blk.proj(torch.cat(outs, -1))
    return q + blk.mlp(blk.norm2(q))


def test_a_pool_block_is_pre_norm_multi_head_attention_then_an_mlp_and_each_query_attends_alone():
    torch.manual_seed(0)
    blk = PoolBlock(8, 2).eval()
    with torch.no_grad():  # non-trivial norms, so that each is seen
        for norm in (blk.norm_q, blk.norm_kv, blk.norm2):
            norm.weight.normal_()
            norm.bias.normal_()
        q, x = torch.randn(2, 2, 8), torch.randn(2, 5, 8)
        got = blk(q, x)
        assert torch.allclose(got, _pool_reference(blk, q, x), atol=1e-5)
        assert torch.allclose(got[:, 1:], blk(q[:, 1:], x), atol=1e-5)


def test_match_scores_are_scaled_dot_products_of_the_query_and_key_projections():
    torch.manual_seed(0)
    m = MatchScores(8, inner=16)
    a, b = torch.randn(1, 3, 8), torch.randn(1, 5, 8)
    with torch.no_grad():
        want = torch.einsum("bic,bjc->bij", m.q(a), m.k(b)) / 4.0
        assert torch.allclose(m(a, b), want, atol=1e-5)


class _FixedScores(torch.nn.Module):
    def __init__(self, logits):
        super().__init__()
        self.logits = logits

    def forward(self, tok1, tok2):
        return self.logits


def _embedded_features(head, *args):
    seen = []
    handle = head.embed.register_forward_pre_hook(lambda mod, a: seen.append(a[0]))
    with torch.no_grad():
        out = head(*args)
    handle.remove()
    return seen[0], out


def test_the_pose_head_reads_where_each_token_matched_how_sharply_and_its_scaled_patch_point():
    torch.manual_seed(0)
    head = PoseHead(pm.PRESETS["test"]).eval()
    grid1, grid2 = (2, 2), (2, 3)
    target = torch.tensor([4, 0, 5, 2])  # view-1 token i matched view-2 token target[i]
    head.match = _FixedScores(60.0 * F.one_hot(target, 6).float()[None])
    patch_pts = torch.tensor([[1.0, 0.0, 2.0], [0.0, 1.0, 3.0], [-1.0, 0.5, 4.0], [0.5, -2.0, 1.0]])
    pts1 = patch_pts.reshape(2, 2, 1, 1, 3).expand(2, 2, P, P, 3).permute(0, 2, 1, 3, 4).reshape(1, 2 * P, 2 * P, 3)
    tok1, tok2 = torch.randn(1, 4, 32), torch.randn(1, 6, 32)
    feat, T = _embedded_features(head, tok1, tok2, grid1, grid2, pts1)
    n = 4 * head.n_freq
    c1, c2 = patch_centres(*grid1), patch_centres(*grid2)
    assert torch.allclose(feat[0, :, :n], fourier(c1, head.n_freq), atol=1e-6)
    assert torch.allclose(feat[0, :, n:2 * n], fourier(c2[target], head.n_freq), atol=1e-5)
    scale = patch_pts.norm(dim=-1).mean()
    assert torch.allclose(feat[0, :, 2 * n:2 * n + 3], patch_pts / scale, atol=1e-6)
    assert torch.allclose(feat[0, :, -2], torch.full((4,), 1e-3), atol=2e-4)  # a sharp match: no spread
    assert torch.allclose(feat[0, :, -1], torch.ones(4), atol=1e-5)  # and a peak of 1
    assert torch.equal(T[0, 3], torch.tensor([0.0, 0.0, 0.0, 1.0]))


def test_a_pose_head_undecided_between_all_patches_reads_their_centroid_and_their_spread():
    torch.manual_seed(0)
    head = PoseHead(pm.PRESETS["test"]).eval()
    head.match = _FixedScores(torch.zeros(1, 4, 6))
    pts1 = torch.rand(1, 2 * P, 2 * P, 3) + 1
    feat, _ = _embedded_features(head, torch.randn(1, 4, 32), torch.randn(1, 6, 32), (2, 2), (2, 3), pts1)
    n = 4 * head.n_freq
    c2 = patch_centres(2, 3)
    assert torch.allclose(feat[0, :, n:2 * n], fourier(c2.mean(0), head.n_freq).expand(4, -1), atol=1e-6)
    spread = ((c2 * c2).sum(-1).mean() - c2.mean(0).square().sum() + 1e-6).sqrt()
    assert torch.allclose(feat[0, :, -2], spread.expand(4), atol=1e-6)
    assert torch.allclose(feat[0, :, -1], torch.full((4,), 1 / 6), atol=1e-6)


def test_every_pose_head_parameter_shapes_a_trained_heads_transform():
    torch.manual_seed(0)
    head = PoseHead(pm.PRESETS["test"])
    with torch.no_grad():
        head.out.weight.normal_(0, 0.5)
    T = head(torch.randn(1, 4, 32), torch.randn(1, 6, 32), (2, 2), (2, 3), torch.rand(1, 2 * P, 2 * P, 3) + 1)
    assert _all_parameters_get_a_gradient(head, (T * torch.randn_like(T)).sum()) == []


def _pinhole_pointmap(h, w, f, z_patch):
    """[1, h*P, w*P, 3] points of a pinhole camera of focal f (centred principal point), depth constant per patch."""
    H, W = h * P, w * P
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    z = z_patch.double().repeat_interleave(P, 0).repeat_interleave(P, 1)
    return torch.stack([(u - (W - 1) / 2) / f * z, (v - (H - 1) / 2) / f * z, z], dim=-1)[None].float()


def test_the_focal_head_reads_rays_a_zero_pinhole_miss_and_log_depths_of_a_pinhole_pointmap():
    torch.manual_seed(0)
    head = FocalHead(pm.PRESETS["test"]).eval()
    h, w, f = 2, 3, 10.0  # a wide view: rays beyond 1 at the corners
    z = torch.tensor([[1.0, 2.0, 30.0], [4.0, 5.0, 6.0]])
    pts = _pinhole_pointmap(h, w, f, z)
    feat, focal = _embedded_features(head, torch.randn(1, h * w, 32), (h, w), pts)
    n = 4 * head.n_freq
    c = patch_centres(h, w)
    half = max(h, w) * P / 2
    assert torch.allclose(focal, torch.tensor([f]), rtol=1e-4)  # a fresh head: the pointmap's own focal
    assert torch.allclose(feat[0, :, :n], fourier(c, head.n_freq), atol=1e-6)
    assert torch.allclose(feat[0, :, n:n + 2], c * half / f, atol=1e-4) and float(feat[0, :, n:n + 2].abs().max()) > 1
    assert torch.allclose(feat[0, :, n + 2:n + 4], torch.zeros(6, 2), atol=1e-4)
    logz = (z.reshape(-1) / z.mean()).log()
    assert torch.allclose(feat[0, :, -1], logz, atol=1e-5) and float(logz.abs().max()) > 1


def test_the_focal_head_leaves_patches_behind_the_camera_out_of_its_rays_and_mean_depth():
    torch.manual_seed(0)
    head = FocalHead(pm.PRESETS["test"]).eval()
    z = torch.tensor([[1.0, 2.0], [-3.0, 4.0]])  # patch 2 is behind the camera
    pts = _pinhole_pointmap(2, 2, 30.0, z)
    feat, _ = _embedded_features(head, torch.randn(1, 4, 32), (2, 2), pts)
    n = 4 * head.n_freq
    assert torch.equal(feat[0, 2, n:n + 2], torch.zeros(2)) and torch.equal(feat[0, 2, -1], torch.tensor(0.0))
    front = torch.tensor([1.0, 2.0, 4.0])
    assert torch.allclose(feat[0, [0, 1, 3], -1], (front / front.mean()).log(), atol=1e-5)


def test_the_focal_head_falls_back_to_the_long_side_for_a_mirrored_or_empty_pointmap_of_any_shape():
    torch.manual_seed(0)
    head = FocalHead(pm.PRESETS["test"]).eval()
    pts = _pinhole_pointmap(2, 3, 30.0, torch.full((2, 3), 2.0))
    mirrored = pts * torch.tensor([-1.0, -1.0, 1.0])  # the L1 fit gives a negative focal
    behind = pts * torch.tensor([1.0, 1.0, -1.0])
    with torch.no_grad():
        for bad in (mirrored, behind):
            assert torch.equal(head(torch.randn(1, 6, 32), (2, 3), bad), torch.tensor([48.0]))


def test_the_focal_head_correction_is_bounded_both_ways_and_follows_the_points_dtype():
    torch.manual_seed(0)
    head = FocalHead(pm.PRESETS["test"]).eval()
    pts = _pinhole_pointmap(2, 2, 30.0, torch.full((2, 2), 2.0))
    tok = torch.randn(1, 4, 32)
    with torch.no_grad():
        head.out.bias.fill_(-10.0)
        assert torch.allclose(head(tok, (2, 2), pts), torch.tensor([30.0 * math.exp(-3)]), rtol=1e-4)
        assert head.base_focal(pts.double()).dtype == torch.float64


def test_the_focal_head_passes_no_gradient_to_the_pointmap_and_trains_all_its_parameters():
    torch.manual_seed(0)
    head = FocalHead(pm.PRESETS["test"])
    with torch.no_grad():
        head.out.weight.normal_(0, 0.5)
    pts = _pinhole_pointmap(2, 3, 30.0, torch.rand(2, 3) + 1).requires_grad_()
    focal = head(torch.randn(1, 6, 32), (2, 3), pts)
    assert _all_parameters_get_a_gradient(head, focal.sum()) == []
    assert pts.grad is None
