import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import pointmap as pm
from pointmap.model import PRESETS, PointmapNet
from training.config import TrainConfig
from training.loop import StepBatches, batch_indices, fit, lr_factor
from training.train import check_model_options, collate, make_step

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import PlanePairs  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def config(out, steps):
    """A tiny run's config. The wall-time checkpoint is off (ckpt_minutes=0; its test sets it): a test's checkpoints
    do not depend on how long it ran (a run stopped 45 minutes by kill -STOP wrote an extra one inside its decay)."""
    return TrainConfig(data="synthetic", out=str(out), preset="test", batch_size=2, steps=steps, warmup=2,
                       ckpt_every=1, ckpt_minutes=0.0, eval_every=1000, workers=0, quiet=True, n_corr=64)


def tick_clock(monkeypatch, seconds=0.05):
    """Replace training.loop's clock by one that advances ``seconds`` at every reading: a deterministic pace."""
    import types

    import training.loop as loop

    now = [0.0]

    def fake_time():
        now[0] += seconds
        return now[0]

    monkeypatch.setattr(loop, "time", types.SimpleNamespace(time=fake_time))


def run(out, steps, **overrides):
    torch.manual_seed(0)
    model = PointmapNet(PRESETS["test"])
    cfg = dataclasses.replace(config(out, steps), **overrides)
    fit(cfg, model, PlanePairs(6), collate, make_step(cfg))
    return model


def seeded_model_and_batch(model_cfg=PRESETS["test"]):
    """A seed-0 model of ``model_cfg`` and a batch of the two synthetic plane pairs."""
    torch.manual_seed(0)
    model = PointmapNet(model_cfg)
    data = PlanePairs(2)
    return model, collate([data[0], data[1]])


def test_the_fast_batch_sampler_follows_the_reference_data_order():
    fast = list(StepBatches(n=7, batch=3, steps=6, start_step=2, rank=1, world=2, seed=5))
    ref = [batch_indices(s, 1, 2, 3, 7, 5) for s in range(2, 6)]
    assert fast == ref


def test_every_sample_is_seen_once_per_epoch_across_ranks():
    seen = sorted(i for s in range(2) for r in range(2) for i in batch_indices(s, r, 2, 3, 12, 0))
    assert seen == list(range(12))


def test_learning_rate_warms_up_then_decays_to_the_minimum():
    cfg = TrainConfig(data="x", lr=1e-3, min_lr=1e-5, warmup=10, steps=110)
    assert abs(lr_factor(0, cfg) - 0.1) < 1e-9 and abs(lr_factor(9, cfg) - 1.0) < 1e-9
    assert abs(lr_factor(110, cfg) * cfg.lr - 1e-5) < 1e-12


def test_the_wsd_schedule_holds_the_rate_then_falls_to_the_minimum_as_one_minus_sqrt():
    cfg = TrainConfig(data="x", lr=1e-3, min_lr=1e-5, warmup=10, steps=110, schedule="wsd", decay_steps=40)
    # lr_factor(k) is the rate of update k (0-based): updates 10..69 are stable, 70..109 decay
    assert abs(lr_factor(9, cfg) - 1.0) < 1e-12
    assert all(lr_factor(s, cfg) == 1.0 for s in range(10, 70)) and lr_factor(70, cfg) < 1.0
    floor = cfg.min_lr / cfg.lr
    assert abs(lr_factor(79, cfg) - (floor + (1 - floor) * (1 - 0.5))) < 1e-12  # t = 10/40: 1 - sqrt(t) = 1/2
    assert abs(lr_factor(109, cfg) * cfg.lr - 1e-5) < 1e-12  # the last update runs at min_lr
    assert lr_factor(200, cfg) == lr_factor(109, cfg)
    factors = [lr_factor(s, cfg) for s in range(69, 110)]
    assert all(a > b for a, b in zip(factors, factors[1:]))


def test_schedule_options_are_checked_on_the_command_line(capsys):
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--schedule", "step"])
    assert "--schedule expected 'cosine' or 'wsd'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--schedule", "wsd", "--steps", "100", "--warmup", "10"])
    assert "0 < --decay_steps <= --steps - --warmup (100 - 10), got 0" in capsys.readouterr().err
    cfg = TrainConfig.from_args(["--data", "x", "--schedule", "wsd", "--steps", "100", "--decay_steps", "20",
                                 "--warmup", "10"])
    assert cfg.schedule == "wsd" and cfg.decay_steps == 20
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--decay_steps", "20"])
    assert "--decay_steps 20 is for --schedule wsd" in capsys.readouterr().err


def test_a_config_built_in_code_with_an_impossible_schedule_is_refused_by_fit(tmp_path):
    with pytest.raises(ValueError, match="--schedule wsd needs 0 < --decay_steps"):
        run(tmp_path / "x", 4, schedule="wsd", decay_steps=0)
    assert not (tmp_path / "x" / "last.pt").exists()


def test_a_wsd_run_saves_its_stable_checkpoint_and_a_longer_run_resumes_from_it_at_full_rate(tmp_path):
    import csv

    run(tmp_path / "short", 6, schedule="wsd", decay_steps=2, log_every=1)
    stable = tmp_path / "short" / "stable_4.pt"
    assert sorted(p.name for p in (tmp_path / "short").glob("stable_*.pt")) == ["stable_4.pt"]
    assert torch.load(stable, weights_only=True)["step"] == 4
    (tmp_path / "long").mkdir()
    shutil.copy(stable, tmp_path / "long" / "last.pt")
    run(tmp_path / "long", 10, schedule="wsd", decay_steps=2, log_every=1, lr=2e-4, weight_decay=0.01)  # new lr, wd
    groups = torch.load(tmp_path / "long" / "last.pt", weights_only=True)["optimizer"]["param_groups"]
    assert [g["weight_decay"] for g in groups] == [0.01, 0.0] and all(g["initial_lr"] == 2e-4 for g in groups)
    with open(tmp_path / "long" / "train.csv", newline="") as fh:
        lrs = {int(r["step"]): float(r["lr"]) for r in csv.DictReader(fh)}
    assert min(lrs) == 5 and max(lrs) == 10
    assert all(abs(lrs[s] - 2e-4) < 1e-12 for s in (5, 6, 7))  # lr after step s-1: stable through step 8
    assert lrs[9] < 2e-4 and abs(lrs[10] - TrainConfig.min_lr) < 1e-12


def test_a_wsd_run_with_decay_ckpts_keeps_each_checkpoint_of_its_decay_and_only_those(tmp_path):
    run(tmp_path / "a", 8, schedule="wsd", decay_steps=3, ckpt_every=2, decay_ckpts=True)
    kept = sorted((tmp_path / "a").glob("decay_*.pt"), key=lambda p: int(p.stem.split("_")[1]))
    assert [p.name for p in kept] == ["decay_6.pt", "decay_8.pt"]  # step 4 is stable; 6 and 8 decay (5-8)
    last = torch.load(tmp_path / "a" / "last.pt", weights_only=True)
    eight = torch.load(kept[-1], weights_only=True)
    assert eight["step"] == 8 and all(torch.equal(v, last["model"][k]) for k, v in eight["model"].items())
    run(tmp_path / "b", 8, schedule="wsd", decay_steps=3, ckpt_every=2)  # off by default
    assert not list((tmp_path / "b").glob("decay_*.pt"))
    with pytest.raises(ValueError, match="--decay_ckpts true keeps the checkpoints of a wsd decay"):
        run(tmp_path / "c", 8, decay_ckpts=True)  # a cosine run has no decay phase to keep


def test_a_resumed_run_ends_with_the_same_weights_as_an_uninterrupted_one(tmp_path):
    straight = run(tmp_path / "a", 4)
    run(tmp_path / "b", 2)
    resumed = run(tmp_path / "b", 4)  # picks up out/last.pt at step 2
    for k, v in straight.state_dict().items():
        assert torch.allclose(v, resumed.state_dict()[k], atol=1e-6), k
    ck = torch.load(tmp_path / "b" / "last.pt", weights_only=True)
    assert ck["step"] == 4 and ck["kind"] == "train"


def test_a_resumed_run_on_augmented_rendered_pairs_ends_as_an_uninterrupted_one_with_or_without_workers(
        tmp_path, tiny_pairs):
    from data.datasets import PairDataset

    def augmented_run(out, steps, workers):
        torch.manual_seed(0)
        model = PointmapNet(PRESETS["test"])
        torch.manual_seed(123 + steps)  # the process's seed must not matter: each item carries its own
        cfg = dataclasses.replace(config(out, steps), data=str(tiny_pairs), workers=workers, size=64)
        fit(cfg, model, PairDataset(tiny_pairs, size=64, augment=True, split="all"), collate, make_step(cfg))
        return model

    for workers in (0, 1):
        straight = augmented_run(tmp_path / f"a{workers}", 4, workers)
        augmented_run(tmp_path / f"b{workers}", 2, workers)
        resumed = augmented_run(tmp_path / f"b{workers}", 4, workers)
        for k, v in straight.state_dict().items():
            assert torch.allclose(v, resumed.state_dict()[k], atol=1e-6), (workers, k)


def test_a_resumed_pretraining_run_draws_the_same_masks_and_ends_as_an_uninterrupted_one(tmp_path):
    from pointmap.model.pretrain import CrossViewCompletion
    from training.pretrain import make_step as pretrain_step

    def pretrain(out, steps):
        torch.manual_seed(0)
        model = CrossViewCompletion(PRESETS["test"], mask_ratio=0.5)
        cfg = dataclasses.replace(config(out, steps), task="pretrain")
        fit(cfg, model, PlanePairs(6), collate, pretrain_step(cfg))
        return model

    straight = pretrain(tmp_path / "a", 4)
    pretrain(tmp_path / "b", 2)
    resumed = pretrain(tmp_path / "b", 4)
    for k, v in straight.state_dict().items():
        assert torch.allclose(v, resumed.state_dict()[k], atol=1e-6), k


def test_items_carry_their_augmentations_seed_a_function_of_the_runs_seed_step_and_place():
    items = list(StepBatches(n=7, batch=3, steps=4, start_step=2, rank=1, world=2, seed=5, item_seeds=True))
    assert [[i for i, _, _ in b] for b in items] == [batch_indices(s, 1, 2, 3, 7, 5) for s in range(2, 4)]
    assert [seed for _, _, seed in items[0]] == [(5, 2, 15), (5, 2, 16), (5, 2, 17)]  # step 2: 12 + rank 1 * 3 + b


def test_training_reduces_the_loss_on_a_fixed_batch(tmp_path):
    model, batch = seeded_model_and_batch()
    cfg = config(tmp_path, 1)
    step = make_step(cfg)
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    losses = []
    for _ in range(15):
        loss, _ = step(model, batch, 0)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < losses[0] - 0.1


def test_the_coarse_matching_loss_is_added_with_its_weight_when_switched_on(tmp_path):
    model, batch = seeded_model_and_batch()
    base, d0 = make_step(config(tmp_path, 1))(model, batch, 0)
    cfg = dataclasses.replace(config(tmp_path, 1), coarse_weight=0.5)
    both, d1 = make_step(cfg)(model, batch, 0)
    assert "coarse_loss" not in d0 and d1["coarse_loss"] > 0
    assert abs(float(both.detach()) - float(base.detach()) - 0.5 * d1["coarse_loss"]) < 1e-4


def test_cross_attention_supervision_is_added_with_its_weight_and_reaches_the_query_projections(tmp_path):
    model, batch = seeded_model_and_batch()
    base, _ = make_step(config(tmp_path, 1))(model, batch, 0)
    cfg = dataclasses.replace(config(tmp_path, 1), attn_weight=0.5, attn_heads=1)
    step = make_step(cfg)
    both, d = step(model, batch, 0)
    assert d["attn_loss"] > 0 and abs(float(both.detach()) - float(base.detach()) - 0.5 * d["attn_loss"]) < 1e-4
    both.backward()
    assert model.dec_blocks[0].cross_attn.projq.weight.grad.abs().sum() > 0
    assert model.dec_blocks2[-1].cross_attn.projk.weight.grad.abs().sum() > 0
    assert step.taps.cross == {1: [], 2: []}  # released after the step
    model(batch[0]["img"], batch[1]["img"])  # any forward pass outside a step (evaluation, a notebook) ...
    assert step.taps.cross == {1: [], 2: []}  # ... records nothing
    again, d2 = step(model, batch, 0)
    assert abs(d2["attn_loss"] - d["attn_loss"]) < 1e-5


def test_architecture_dependent_options_are_refused_before_training_starts(tmp_path):
    from training.train import check_model_options

    plain, posed = PointmapNet(PRESETS["test"]), PointmapNet(PRESETS["test"].replace(pose_head=True))
    with pytest.raises(ValueError, match="attn_heads 3 exceeds the decoder's 2 heads"):
        check_model_options(dataclasses.replace(config(tmp_path, 1), attn_weight=1.0, attn_heads=3), plain)
    with pytest.raises(ValueError, match="needs a model with a pose head"):
        check_model_options(dataclasses.replace(config(tmp_path, 1), pose_weight=1.0), plain)
    with pytest.raises(ValueError, match="pose_weight > 0"):  # the frame of view 2's head would be free
        check_model_options(config(tmp_path, 1), posed)
    with pytest.raises(ValueError, match="--pose_dir_weight weighs a term of the pose loss"):
        check_model_options(dataclasses.replace(config(tmp_path, 1), pose_dir_weight=1.0), posed)
    check_model_options(dataclasses.replace(config(tmp_path, 1), pose_weight=1.0), posed)
    check_model_options(dataclasses.replace(config(tmp_path, 1), pose_weight=1.0, pose_dir_weight=0.5), posed)
    no_desc = PointmapNet(PRESETS["test"].replace(head="linear", desc_dim=0, two_confs=False))
    check_model_options(dataclasses.replace(config(tmp_path, 1), match_weight=TrainConfig.match_weight), no_desc)
    for flag in ("match_weight", "coarse_weight", "desc_conf_weight"):  # would be ignored without descriptors
        with pytest.raises(ValueError, match=f"--{flag} 3.0 train descriptors, which this model does not have"):
            check_model_options(dataclasses.replace(config(tmp_path, 1), **{flag: 3.0}), no_desc)


def test_negative_loss_weights_are_refused_on_the_command_line(capsys):
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--pose_weight", "-1"])
    assert "--pose_weight expected >= 0" in capsys.readouterr().err


def test_the_pose_loss_is_added_with_its_weight_and_needs_a_pose_head(tmp_path):
    model, batch = seeded_model_and_batch(PRESETS["test"].replace(pose_head=True))
    base, _ = make_step(config(tmp_path, 1))(model, batch, 0)
    both, d = make_step(dataclasses.replace(config(tmp_path, 1), pose_weight=2.0))(model, batch, 0)
    assert d["pose_loss"] > 0 and abs(float(both.detach()) - float(base.detach()) - 2.0 * d["pose_loss"]) < 1e-4
    both.backward()
    assert model.pose_head.out.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="pose head"):
        make_step(dataclasses.replace(config(tmp_path, 1), pose_weight=1.0))(PointmapNet(PRESETS["test"]), batch, 0)


def test_the_direction_term_reaches_the_loss_through_the_pose_weight(tmp_path):
    model, batch = seeded_model_and_batch(PRESETS["test"].replace(pose_head=True))
    cfg = dataclasses.replace(config(tmp_path, 1), pose_weight=2.0)
    base, d0 = make_step(cfg)(model, batch, 0)
    both, d = make_step(dataclasses.replace(cfg, pose_dir_weight=0.5))(model, batch, 0)
    assert "pose_dir_deg" not in d0 and d["pose_dir_deg"] > 0
    assert abs((float(both.detach()) - float(base.detach())) / 2.0 - (d["pose_loss"] - d0["pose_loss"])) < 1e-5
    assert d["pose_loss"] > d0["pose_loss"]


def test_the_focal_term_is_added_with_its_weight_and_reaches_the_pointmap_head(tmp_path):
    model, batch = seeded_model_and_batch()
    with torch.no_grad():  # a fresh head puts every point behind the camera: no focal to measure; move them in front
        model.downstream_head1.dpt.head[4].bias[2] += 3.0
    base, d0 = make_step(config(tmp_path, 1))(model, batch, 0)
    both, d = make_step(dataclasses.replace(config(tmp_path, 1), focal_weight=0.5))(model, batch, 0)
    assert "focal_loss" not in d0 and d["focal_loss"] > 0 and d["focal_log_err"] > 0
    assert abs(float(both.detach()) - float(base.detach()) - 0.5 * d["focal_loss"]) < 1e-4
    both.backward()
    assert any(float(p.grad.abs().sum()) > 0 for n, p in model.named_parameters() if "head" in n and p.grad is not None)
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--focal_weight", "-1"])


def test_with_attention_supervision_the_pose_heads_correspondence_field_is_supervised_too(tmp_path):
    model, batch = seeded_model_and_batch(PRESETS["test"].replace(pose_head=True))
    loss, d = make_step(dataclasses.replace(config(tmp_path, 1), pose_weight=1.0, attn_weight=0.5))(model, batch, 0)
    assert d["pose_match_loss"] > 0 and 0 <= d["pose_match_acc"] <= 1
    loss.backward()
    assert model.pose_head.match.q.weight.grad.abs().sum() > 0


@pytest.mark.slow  # ~2 min of compilation
def test_a_compiled_training_step_gives_the_eager_loss_with_every_auxiliary_loss_on(tmp_path):
    model, batch = seeded_model_and_batch(PRESETS["test"].replace(pose_head=True))
    cfg = dataclasses.replace(config(tmp_path, 1), attn_weight=0.5, attn_heads=1, pose_weight=1.0, coarse_weight=0.5)
    eager, d0 = make_step(cfg)(model, batch, 0)
    compiled, d1 = make_step(cfg)(torch.compile(model), batch, 0)
    assert abs(eager.item() - compiled.item()) < 1e-4 * max(1.0, abs(eager.item()))
    assert d0.keys() == d1.keys() and d1["attn_loss"] > 0 and d1["pose_loss"] > 0


@pytest.mark.skipif(shutil.which("torchrun") is None and not (Path(sys.executable).parent / "torchrun").exists(),
                    reason="torchrun not installed")
@pytest.mark.parametrize("mode", ["plain", "sigterm"])
def test_two_ddp_processes_on_cpu_end_with_identical_weights_even_with_a_head_no_loss_reaches_and_a_sigterm_stops_both(tmp_path, mode):
    torchrun = str(Path(sys.executable).parent / "torchrun")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([torchrun, "--nproc_per_node=2", f"--master_port={29517 + (mode == 'sigterm')}",
                           str(ROOT / "tests/training/ddp_worker.py"), str(tmp_path), mode],
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    w0 = torch.load(tmp_path / "rank0.pt", weights_only=True)
    w1 = torch.load(tmp_path / "rank1.pt", weights_only=True)
    assert int(w0.pop("__step")) == int(w1.pop("__step")) == (2 if mode == "sigterm" else 3)
    torch.manual_seed(0)
    initial = PointmapNet(PRESETS["test"] if mode == "sigterm" else PRESETS["test"].replace(
        head="catmlp+linear", pose_head=True, focal_head=True)).state_dict()
    assert w0.keys() == initial.keys()
    assert all(torch.equal(w0[k], w1[k]) for k in w0)
    assert any(not torch.equal(w0[k], initial[k]) for k in w0)
    if mode == "sigterm":
        assert torch.load(tmp_path / "last.pt", weights_only=True)["step"] == 2


def test_fresh_heads_init_takes_the_trunk_and_keeps_only_head_tensors_whose_shapes_match(tmp_path, monkeypatch):
    import dataclasses

    import pointmap as pm
    from pointmap.errors import CheckpointError
    from training.train import build_model

    src = PointmapNet(PRESETS["test"])
    pm.save_model(src, tmp_path / "src.safetensors")
    monkeypatch.setitem(PRESETS, "test_desc16", dataclasses.replace(PRESETS["test"], desc_dim=16))
    cfg = TrainConfig(data="x", preset="test_desc16", init=str(tmp_path / "src.safetensors"), init_heads="fresh")
    model = build_model(cfg)
    assert model.cfg.desc_dim == 16
    got, want = model.state_dict(), src.state_dict()
    trunk = [k for k in want if not k.startswith("downstream_head")]
    assert trunk and all(torch.equal(got[k], want[k]) for k in trunk)
    same = [k for k in want if k.startswith("downstream_head") and got[k].shape == want[k].shape]
    assert same and all(torch.equal(got[k], want[k]) for k in same)
    assert any(got[k].shape != want[k].shape for k in want if k.startswith("downstream_head"))
    # strict mode keeps --init's own architecture; a trunk that does not fit is refused with the reason
    assert build_model(dataclasses.replace(cfg, init_heads="strict")).cfg.desc_dim == 8
    monkeypatch.setitem(PRESETS, "test_wide", dataclasses.replace(PRESETS["test"], enc_dim=48))
    with pytest.raises(CheckpointError, match="trunk shape mismatches"):
        build_model(dataclasses.replace(cfg, preset="test_wide"))


def test_a_descriptor_stem_joins_a_checkpoint_only_with_fresh_heads_and_starts_as_its_model(tmp_path):
    import dataclasses

    import pointmap as pm
    from pointmap.errors import CheckpointError
    from training.train import build_model

    src = PointmapNet(PRESETS["test"]).eval()
    pm.save_model(src, tmp_path / "src.safetensors")
    cfg = TrainConfig(data="x", preset="test", init=str(tmp_path / "src.safetensors"), desc_stem=4)
    with pytest.raises(CheckpointError, match="init_heads fresh"):
        build_model(cfg)
    model = build_model(dataclasses.replace(cfg, init_heads="fresh")).eval()
    assert model.cfg.desc_stem == 4 and model.desc_stem is not None
    a, b = torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        assert torch.equal(model(a, b).desc1, src(a, b).desc1)


@pytest.mark.parametrize("head", ["catmlp+dpt", "catmlp+linear"])
def test_conf_reset_revives_a_collapsed_confidence_and_leaves_points_and_descriptors_unchanged(tmp_path, head):
    import dataclasses
    import math

    import pointmap as pm
    from training.losses import regression_loss
    from training.train import build_model, reset_confidence

    src = PointmapNet(dataclasses.replace(PRESETS["test"], head=head)).eval()
    reset_confidence(src, 1 + math.exp(-13.0))  # collapsed, as the shipped v17's confidence (raw -13)
    pm.save_model(src, tmp_path / "src.safetensors")
    cfg = TrainConfig(data="x", preset="test", init=str(tmp_path / "src.safetensors"), conf_reset=1.2)
    model = build_model(cfg).eval()
    v1, v2 = PlanePairs(n=1)[0]
    v1, v2 = ({k: v[None] for k, v in v.items()} for v in (v1, v2))

    def conf_grad(m):
        m.zero_grad()
        regression_loss(m(v1["img"], v2["img"]), v1, v2)[0].backward()
        h = m.downstream_head1
        last = h.proj if hasattr(h, "proj") else h.dpt.head[-1]
        g = last.bias.grad
        return float(g[3 * 256: 4 * 256].abs().sum() if hasattr(h, "proj") else g[3].abs())

    with torch.no_grad():
        a, b = src(v1["img"], v2["img"]), model(v1["img"], v2["img"])
    assert torch.equal(a.pts1_cam1, b.pts1_cam1) and torch.equal(a.pts2_cam1, b.pts2_cam1)
    assert torch.equal(a.desc1, b.desc1)
    assert torch.allclose(b.conf1, torch.full_like(b.conf1, 1.2)) and torch.allclose(b.conf2, torch.full_like(b.conf2, 1.2))
    assert float(a.conf1.max()) < 1.0 + 1e-5
    # the collapsed channel passes gradients scaled by e^-13; the restarted one passes them at full scale
    dead, live = conf_grad(src.train()), conf_grad(model.train())
    assert live > 1e4 * dead and live > 1e-3
    with pytest.raises(ValueError, match="between the model's floor"):
        build_model(dataclasses.replace(cfg, conf_reset=0.5))


def test_the_training_command_reports_a_conf_reset_below_the_floor_in_one_line(tmp_path, capsys):
    import pointmap as pm
    from training.train import main

    pm.save_model(PointmapNet(PRESETS["test"]), tmp_path / "src.safetensors")
    code = main(["--data", "x", "--init", str(tmp_path / "src.safetensors"), "--conf_reset", "0.5"])
    err = capsys.readouterr().err
    assert code == 2 and "error: --conf_reset expected a confidence between the model's floor 1.0" in err
    assert "Traceback" not in err


def test_conf_reset_needs_an_init_model_and_a_positive_value():
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--conf_reset", "1.2"])
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--init", "m.safetensors", "--conf_reset", "-1"])


def test_fresh_heads_init_without_init_is_refused():
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--init_heads", "fresh"])



def test_the_csv_log_keeps_one_header_when_a_resumed_run_adds_columns(tmp_path):
    import csv

    from training.loop import Logger

    log = Logger(tmp_path, True)
    log.log("eval", 500, {"RRA15": 10.0, "pairs": 139.0})
    log.log("eval", 1000, {"RRA15": 12.0, "coarse_acc": 0.1, "pairs": 139.0})
    with open(tmp_path / "eval.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["pairs"] for r in rows] == ["139.0", "139.0"]
    assert [r["coarse_acc"] for r in rows] == ["", "0.1"] and None not in rows[1]


def test_a_bf16_autocast_step_keeps_its_losses_in_float32_and_close_to_the_float32_step(tmp_path, monkeypatch):
    import training.train as train

    seen = {}  # loss name -> dtypes of every floating tensor it was given

    def spy(name, fn):
        def wrapped(*args, **kwargs):
            flat = [*args, *kwargs.values()]
            flat = [y for x in flat for y in (x if isinstance(x, (list, tuple)) else [x])]
            flat = [y for x in flat for y in (x.as_dict().values() if hasattr(x, "as_dict") else [x])]
            seen.setdefault(name, set()).update(t.dtype for t in flat if torch.is_tensor(t) and t.is_floating_point())
            assert not torch.is_autocast_enabled("cpu"), f"{name} ran under autocast"
            return fn(*args, **kwargs)
        return wrapped

    for name in ("regression_loss", "matching_loss", "patch_matching_loss", "pose_loss", "cross_attention_loss"):
        monkeypatch.setattr(train, name, spy(name, getattr(train, name)))
    model, batch = seeded_model_and_batch(PRESETS["test"].replace(pose_head=True))
    cfg = dataclasses.replace(config(tmp_path, 1), attn_weight=0.5, attn_heads=1, pose_weight=1.0, coarse_weight=0.5)
    full, d32 = make_step(cfg)(model, batch, 0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        half, d16 = make_step(cfg)(model, batch, 0)
    assert len(seen) == 5 and all(dtypes == {torch.float32} for dtypes in seen.values()), seen
    assert half.dtype == torch.float32 and d16.keys() == d32.keys()
    assert abs(float(half.detach()) - float(full.detach())) < 0.02 * abs(float(full.detach()))
    half.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(g.dtype == torch.float32 and torch.isfinite(g).all() for g in grads)


def test_amp_bf16_trains_on_cpu_and_auto_leaves_cpu_training_in_float32(tmp_path):
    from training.loop import use_autocast

    assert use_autocast(dataclasses.replace(config(tmp_path, 1), amp="bf16"), torch.device("cpu"))
    assert not use_autocast(config(tmp_path, 1), torch.device("cpu"))
    assert not use_autocast(dataclasses.replace(config(tmp_path, 1), amp="off"), torch.device("cuda"))
    model = run(tmp_path / "bf16", 3, amp="bf16")
    assert all(torch.isfinite(p).all() for p in model.parameters())
    assert (tmp_path / "bf16" / "last.pt").exists()


def test_an_unknown_amp_mode_is_refused_with_the_choices(capsys):
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--amp", "fp8"])
    assert "--amp expected 'auto', 'bf16' or 'off', got 'fp8'" in capsys.readouterr().err


@pytest.mark.parametrize("option", ["crop_link", "grey_p", "flip_p", "pad_p"])
def test_a_probability_option_outside_0_to_1_is_refused_before_any_data_is_opened(capsys, option):
    for bad in ("1.5", "-0.2", "nan"):
        with pytest.raises(SystemExit):
            TrainConfig.from_args(["--data", "x", f"--{option}", bad])
        assert f"--{option} expected a probability" in capsys.readouterr().err
    assert getattr(TrainConfig.from_args(["--data", "x", f"--{option}", "0.5"]), option) == 0.5


def test_decay_by_time_starts_the_decay_when_the_minutes_left_fit_just_the_decay(tmp_path):
    from training.loop import DecayByTime

    cfg = dataclasses.replace(config(tmp_path, 1000), schedule="wsd", decay_steps=10, max_minutes=1.0,
                              decay_by_time=True)
    clock = DecayByTime(cfg, start=0, t0=0.0, warm=5)
    # 1 s per step after a 30 s first step (compilation): the pace is measured from step 5 on
    started = [s for s in range(1, 1000) if clock.update(s, 30.0 + (s - 1) * 1.0)]
    # at step s, 60 - (29 + s) s are left: the decay starts when that is <= 10 * 1.1 + 2 steps of 1 s (the decay's
    # steps counted 10% slower), i.e. at s = 18; with no margin, when it is <= 10 + 2 steps, at s = 19
    assert started == [18] and cfg.steps == 28
    assert not clock.update(22, 51.0) and cfg.steps == 28  # fixed once decaying
    exact = DecayByTime(dataclasses.replace(cfg, steps=1000), start=0, t0=0.0, warm=5, margin=0.0)
    assert [s for s in range(1, 1000) if exact.update(s, 30.0 + (s - 1) * 1.0)] == [19]
    late = dataclasses.replace(cfg, steps=1000, warmup=500)
    assert not any(DecayByTime(late, 0, 0.0, warm=5).update(s, 30.0 + s) for s in range(1, 500))  # not in warmup


def test_a_stall_of_the_process_does_not_start_the_decay_by_time_early(tmp_path):
    from training.loop import DecayByTime

    cfg = dataclasses.replace(config(tmp_path, 100_000), schedule="wsd", decay_steps=10, max_minutes=10.0,
                              decay_by_time=True)
    clock = DecayByTime(cfg, start=0, t0=0.0, warm=5)

    def t(s):  # 30 s of compilation, then 1 s per step, and the process stopped for 120 s after step 5 (kill -STOP)
        return 30.0 + (s - 1) + (120.0 if s > 5 else 0.0)

    started = [s for s in range(1, 1000) if clock.update(s, t(s))]
    # the decay starts when 600 - t(s) s fit 10 * 1.1 + 2 steps of 1 s (the stall, counted as 4 steps while in the
    # window, has left it by then): at s = 438. Read from the stalled step alone, the pace was 121 s and the decay
    # started at step 6
    assert started == [438] and clock.pace() == pytest.approx(1.0)
    early = DecayByTime(dataclasses.replace(cfg, steps=100_000), start=0, t0=0.0, warm=5)
    assert not any(early.update(s, t(s)) for s in range(1, 12))
    assert 1.0 < early.pace() <= 1.6  # the stall counted as 4 steps of the first 6
    # a machine that really slows down moves the pace: 3 s per step for the window's length
    slow = DecayByTime(dataclasses.replace(cfg, steps=100_000), start=0, t0=0.0, warm=5, window=50)
    for s in range(5, 100):
        slow.update(s, 30.0 + s + 2.0 * max(0, s - 40))
    assert slow.pace() == pytest.approx(3.0)


def test_a_decay_by_time_run_ends_decayed_when_its_minutes_run_out_and_a_resume_keeps_that_end(tmp_path, monkeypatch):
    import csv

    import training.loop as loop

    tick_clock(monkeypatch)
    saved = loop.save_checkpoint

    def keep_every_checkpoint(path, model, optimizer, scheduler, step, cfg, extra=None):
        saved(path, model, optimizer, scheduler, step, cfg, extra)
        if path.name == "last.pt":
            shutil.copy(path, tmp_path / f"ckpt_{step}.pt")

    monkeypatch.setattr(loop, "save_checkpoint", keep_every_checkpoint)
    out = tmp_path / "run"
    model = run(out, 400, schedule="wsd", decay_steps=6, max_minutes=0.15, decay_by_time=True, log_every=1,
                decay_ckpts=True)
    rows = list(csv.DictReader((out / "train.csv").read_text().splitlines()))
    end = int(rows[-1]["step"])
    assert 20 < end < 400, end                      # ended by the clock, long before the --steps bound
    kept = sorted(int(p.stem.split("_")[1]) for p in out.glob("decay_*.pt"))
    assert kept == list(range(end - 5, end + 1))    # --decay_ckpts: the decay the clock placed, every checkpoint
    lr = {int(r["step"]): float(r["lr"]) for r in rows}  # the rate of the update after each logged step
    assert lr[end - 7] == pytest.approx(2e-4)       # stable until the decay
    assert 1e-6 < lr[end - 6] < 2e-4                # the decay's first update
    assert lr[end - 2] > 1e-6 and lr[end - 1] == pytest.approx(1e-6)  # the last update ran at min_lr
    assert (out / f"stable_{end - 6}.pt").exists()
    ck = torch.load(out / "last.pt", weights_only=True)
    assert ck["step"] == end and ck["train_config"]["steps"] == end
    # a run resumed from a checkpoint written mid-decay finishes the same decay (no new pace measurement)
    out2 = tmp_path / "resumed"
    out2.mkdir()
    shutil.copy(tmp_path / f"ckpt_{end - 3}.pt", out2 / "last.pt")
    torch.manual_seed(0)
    model2 = PointmapNet(PRESETS["test"])
    cfg = dataclasses.replace(config(out2, 400), schedule="wsd", decay_steps=6, max_minutes=0.15,
                              decay_by_time=True, log_every=1)
    result = fit(cfg, model2, PlanePairs(6), collate, make_step(cfg))
    assert result["step"] == end
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), model2.state_dict().values()))
    # resumed once more, with the decay over: nothing to train, and the warning says how to go on
    import contextlib
    import io as _io

    err = _io.StringIO()
    with contextlib.redirect_stderr(err):
        fit(cfg, model2, PlanePairs(6), collate, make_step(cfg))
    assert f"its decay by time ended at step {end}; to train on, resume stable_{end - 6}.pt" in err.getvalue()
    # --keep_decay false forgets that decay: the resumed leg runs at the stable rate until it places its own
    out3 = tmp_path / "replaced"
    out3.mkdir()
    shutil.copy(tmp_path / f"ckpt_{end - 3}.pt", out3 / "last.pt")
    fit(dataclasses.replace(cfg, out=str(out3), keep_decay=False), PointmapNet(PRESETS["test"]), PlanePairs(6),
        collate, make_step(cfg))
    lr3 = {int(r["step"]): float(r["lr"]) for r in csv.DictReader((out3 / "train.csv").read_text().splitlines())}
    assert lr3[end - 2] == pytest.approx(2e-4) and max(lr3) > end
    # a --steps that ends inside the placed decay is refused (it would start the decay over from --steps)
    from pointmap.errors import CheckpointError

    out4 = tmp_path / "short"
    out4.mkdir()
    shutil.copy(tmp_path / f"ckpt_{end - 3}.pt", out4 / "last.pt")
    with pytest.raises(CheckpointError, match=f"runs from step {end - 6} to {end}, and --steps {end - 1} ends "
                                              f"inside it .*pass --steps {end} or more, or --keep_decay false"):
        fit(dataclasses.replace(cfg, out=str(out4), steps=end - 1), PointmapNet(PRESETS["test"]), PlanePairs(6),
            collate, make_step(cfg))


def test_decay_by_time_is_refused_without_wsd_or_a_time_limit(tmp_path):
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--decay_by_time", "true", "--max_minutes", "10"])
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--decay_by_time", "true", "--schedule", "wsd", "--decay_steps", "5"])
    # fit, called directly, refuses it too
    cfg = dataclasses.replace(config(tmp_path, 10), schedule="wsd", decay_steps=5, decay_by_time=True)
    with pytest.raises(ValueError, match="--max_minutes > 0"):
        fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(2), collate, make_step(cfg))
    with pytest.raises(ValueError, match="--amp expected"):
        fit(dataclasses.replace(config(tmp_path, 10), amp="fp8"), PointmapNet(PRESETS["test"]), PlanePairs(2),
            collate, make_step(cfg))


def test_a_run_stopped_by_the_clock_evaluates_its_last_state(tmp_path, monkeypatch):
    import csv

    tick_clock(monkeypatch)
    out = tmp_path / "run"
    calls = []
    torch.manual_seed(0)
    cfg = dataclasses.replace(config(out, 400), max_minutes=0.05)  # eval_every 1000: only the stop evaluates
    result = fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, make_step(cfg),
                 eval_fn=lambda model: calls.append(1) or {"evaluated": float(len(calls))})
    assert 2 < result["step"] < 400, result["step"]  # stopped by the clock
    rows = list(csv.DictReader((out / "eval.csv").read_text().splitlines()))
    assert len(calls) == 1 and [int(r["step"]) for r in rows] == [result["step"]]
    assert torch.load(out / "last.pt", weights_only=True)["step"] == result["step"]


def test_a_scaled_learning_rate_moves_its_tensors_by_that_multiple_and_keeps_it_through_the_schedule(tmp_path):
    scaled = {"enc_blocks.1.mlp.fc2.weight": 10.0, "enc_blocks.1.mlp.fc2.bias": 10.0}

    def train(out, steps, lr_scale, **overrides):
        torch.manual_seed(0)
        model = PointmapNet(PRESETS["test"])
        cfg = dataclasses.replace(config(out, steps), **overrides)
        fit(cfg, model, PlanePairs(6), collate, make_step(cfg), lr_scale=lr_scale)
        return model

    torch.manual_seed(0)
    start = PointmapNet(PRESETS["test"]).state_dict()
    plain, fast = train(tmp_path / "plain", 1, None).state_dict(), train(tmp_path / "fast", 1, scaled).state_dict()
    for k in start:  # AdamW's first update is linear in the rate: lr * (the sign of the gradient + weight decay)
        want = (plain[k] - start[k]) * scaled.get(k, 1.0)
        assert torch.allclose(fast[k] - start[k], want, rtol=1e-3, atol=5e-7), k  # float32 steps of ~1e-4
    assert (plain["enc_blocks.1.mlp.fc2.weight"] != start["enc_blocks.1.mlp.fc2.weight"]).any()
    train(tmp_path / "fast", 6, scaled, schedule="wsd", decay_steps=2)  # resumed through the stable phase into the decay
    groups = torch.load(tmp_path / "fast" / "last.pt", weights_only=True)["optimizer"]["param_groups"]
    assert [(g["weight_decay"], g["lr_scale"], len(g["params"])) for g in groups][2:] == [(0.05, 10.0, 1),
                                                                                          (0.0, 10.0, 1)]
    assert [(g["weight_decay"], g["lr_scale"]) for g in groups][:2] == [(0.05, 1.0), (0.0, 1.0)]
    for g in groups:
        assert g["lr"] == pytest.approx(10 ** (g["lr_scale"] > 1) * groups[0]["lr"])
        assert g["initial_lr"] == pytest.approx(TrainConfig.lr * g["lr_scale"])


def test_a_run_resumed_with_other_learning_rate_groups_keeps_each_parameters_adam_state(tmp_path):
    from pointmap.errors import CheckpointError

    name = "enc_blocks.1.mlp.fc2.weight"

    def resume(out, steps, lr_scale):
        torch.manual_seed(0)
        model = PointmapNet(PRESETS["test"])
        fit(config(out, steps), model, PlanePairs(6), collate, make_step(config(out, steps)), lr_scale=lr_scale)
        return model.state_dict()

    at2 = run(tmp_path / "plain", 2).state_dict()
    shutil.copytree(tmp_path / "plain", tmp_path / "scaled")
    shutil.copy(tmp_path / "plain" / "last.pt", tmp_path / "step2.pt")
    plain, scaled = resume(tmp_path / "plain", 3, None), resume(tmp_path / "scaled", 3, {name: 10.0})
    # the same gradients and, carried by name, the same Adam moments: step 3 moves every tensor as the plain
    # resume does, the scaled one 10x as far (a fresh Adam state would move it by lr * sign(gradient) instead)
    for k in at2:
        want = (plain[k] - at2[k]) * (10.0 if k == name else 1.0)
        assert torch.allclose(scaled[k] - at2[k], want, rtol=1e-3, atol=5e-7), k
    ck = torch.load(tmp_path / "scaled" / "last.pt", weights_only=True)
    assert [g["lr_scale"] for g in ck["optimizer"]["param_groups"]] == [1.0, 1.0, 10.0]
    assert ck["optimizer_names"][2] == [name]
    resume(tmp_path / "scaled", 4, None)  # and off again
    assert [g["lr_scale"] for g in torch.load(tmp_path / "scaled" / "last.pt", weights_only=True)["optimizer"]
            ["param_groups"]] == [1.0, 1.0]
    old = torch.load(tmp_path / "step2.pt", weights_only=True)  # as written before checkpoints named parameters
    del old["optimizer_names"]
    for g in old["optimizer"]["param_groups"]:
        del g["lr_scale"]
    (tmp_path / "old").mkdir()
    torch.save(old, tmp_path / "old" / "last.pt")
    with pytest.raises(CheckpointError, match=r"2 parameter groups \(learning-rate multipliers \[1.0\]\), this run 3 "
                                              r"parameter groups .* cannot be regrouped: start a new --out with --init"):
        resume(tmp_path / "old", 4, {name: 10.0})
    resume(tmp_path / "old", 3, None)  # the same groups: it resumes, and the groups get their multipliers back
    groups = torch.load(tmp_path / "old" / "last.pt", weights_only=True)["optimizer"]["param_groups"]
    assert [g["lr_scale"] for g in groups] == [1.0, 1.0]
    with pytest.raises(ValueError, match="parameters the model does not have"):
        resume(tmp_path / "c", 2, {"nope": 2.0})


def test_grown_learning_rate_options_are_checked_against_each_other_and_the_model(tmp_path, capsys):
    from training.grow import deepen
    from training.train import grown_lr_scale

    for argv, message in ((["--init", "m", "--grown_lr", "10"], "--grown_lr needs --grown_from ENC,DEC"),
                          (["--grown_from", "6,4"], "--grown_from needs --init"),
                          (["--init", "m", "--grown_from", "6"], "--grown_from expected ENC,DEC"),
                          (["--init", "m", "--grown_from", "0,4"], "block counts >= 1"),
                          (["--init", "m", "--grown_from", "6,4", "--grown_lr", "0"], "multiplier > 0, got 0.0"),
                          (["--task", "pretrain", "--init", "m", "--grown_from", "6,4"], "not pretraining")):
        with pytest.raises(SystemExit):
            TrainConfig.from_args(["--data", "x", *argv])
        assert message in capsys.readouterr().err
    model = PointmapNet(PRESETS["test"].replace(head="catmlp+linear"))  # 2 encoder, 4 decoder blocks
    grown = deepen(model, enc_depth=3, dec_depth=6)
    grown.growth = grown.provenance["grown_from"]  # as training.train's build_model records it from --init
    cfg = dataclasses.replace(config(tmp_path, 1), init="g.safetensors", grown_from="2,4", grown_lr=10.0)
    scale = grown_lr_scale(cfg, grown)
    assert set(scale.values()) == {10.0}
    zeroed = {n for n, p in grown.named_parameters() if p.ndim > 1 and not p.any() and "blocks" in n}  # weights
    assert set(scale) == zeroed | {n[: -len("weight")] + "bias" for n in zeroed}
    assert grown_lr_scale(dataclasses.replace(cfg, grown_lr=1.0), grown) == {}  # checked, then nothing to scale
    assert grown_lr_scale(config(tmp_path, 1), grown) == {}
    for wrong in ("3,6", "4,4", "2,7"):
        with pytest.raises(ValueError, match=f"--grown_from {wrong}: the model has 3 encoder and 6 decoder"):
            grown_lr_scale(dataclasses.replace(cfg, grown_from=wrong), grown)
    with pytest.raises(ValueError, match=r"--grown_from 1,4: the --init model's last growth was from 2,4"):
        grown_lr_scale(dataclasses.replace(cfg, grown_from="1,4"), grown)
    grown.growth = []
    with pytest.raises(ValueError, match="was never grown"):
        grown_lr_scale(cfg, grown)
    grown.growth = None  # a checkpoint from before runs recorded growth: --grown_from is taken, with a warning
    assert set(grown_lr_scale(cfg, grown)) == set(scale)
    assert grown.growth == [{"enc_depth": 2, "dec_depth": 4}] and "records no growth history" in capsys.readouterr().err


def test_a_run_from_a_grown_model_records_its_growth_in_every_checkpoint(tmp_path, capsys):
    from training.grow import deepen
    from training.train import main

    torch.manual_seed(0)
    grown = deepen(PointmapNet(PRESETS["test"].replace(head="catmlp+linear")), enc_depth=3)
    init = pm.save_model(grown, tmp_path / "g.safetensors")
    data = tmp_path / "missing"
    assert main(["--data", str(data), "--init", str(init), "--grown_from", "3,4", "--grown_lr", "5"]) == 2
    assert "--grown_from 3,4: the model has 3 encoder and 4 decoder blocks" in capsys.readouterr().err  # before data
    from training.train import build_model

    cfg = dataclasses.replace(config(tmp_path / "run", 4), init=str(init), preset="test", schedule="wsd",
                              decay_steps=2)
    model = build_model(cfg)
    assert model.growth == [{"enc_depth": 2, "dec_depth": 4}]
    fit(cfg, model, PlanePairs(6), collate, make_step(cfg), extra={"grown_from": model.growth})
    for name in ("last.pt", "stable_2.pt"):
        ck = torch.load(tmp_path / "run" / name, weights_only=True)
        assert ck["extra"] == {"grown_from": [{"enc_depth": 2, "dec_depth": 4}]}, name
    assert build_model(dataclasses.replace(cfg, init=str(tmp_path / "run" / "last.pt"))).growth == model.growth


def test_a_run_from_non_commercial_weights_records_their_licence_in_every_checkpoint_and_passes_it_on(tmp_path):
    from pointmap.checkpoint import OFFICIAL_LICENCE
    from training.train import build_model, lineage_extra

    torch.manual_seed(0)
    nc = PointmapNet(PRESETS["test"].replace(head="catmlp+linear"))
    nc.provenance = {"source": "official", "licence": OFFICIAL_LICENCE}
    init = pm.save_model(nc, tmp_path / "nc.safetensors")
    cfg = dataclasses.replace(config(tmp_path / "run", 2), init=str(init), preset="test")
    with pytest.warns(UserWarning, match=r"licensed CC-BY-NC-SA-4.0 \(non-commercial use only\)"):
        model = build_model(cfg)
    assert model.licence == OFFICIAL_LICENCE and lineage_extra(model) == {"licence": OFFICIAL_LICENCE}
    fit(cfg, model, PlanePairs(4), collate, make_step(cfg), extra=lineage_extra(model))
    ck = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    assert ck["extra"] == {"licence": OFFICIAL_LICENCE}
    assert build_model(dataclasses.replace(cfg, init=str(tmp_path / "run" / "last.pt"))).licence == OFFICIAL_LICENCE
    scratch = build_model(dataclasses.replace(cfg, init=None))
    assert scratch.licence is None and lineage_extra(scratch) == {"grown_from": []}


@pytest.mark.parametrize("flags,message", [
    (["--batch_size", "0"], "--batch_size expected >= 1, got 0"),
    (["--log_every", "0"], "--log_every expected >= 1, got 0"),
    (["--steps", "-5"], "--steps expected >= 1, got -5"),
    (["--temperature", "0"], "--temperature expected a finite value > 0, got 0.0"),
    (["--lr", "-1"], "--lr expected a finite value > 0, got -1.0"),
    (["--preset", "nope"], "--preset expected one of"),
    (["--mask_ratio", "1.5"], "--mask_ratio expected a fraction in (0, 1), got 1.5"),
    (["--size", "100"], "--size expected 224 or a multiple of 16 from 32 to 2048 (e.g. 512), got 100"),
    (["--min_lr", "1"], "--min_lr expected <= --lr"),
    (["--match_weight", "nan"], "--match_weight expected a finite number, got nan"),
    (["--pose_head", "true", "--pose_weight", "nan"], "--pose_weight expected a finite number, got nan"),
    (["--coarse_weight", "inf"], "--coarse_weight expected a finite number, got inf"),
    (["--grown_lr", "nan"], "--grown_lr expected a finite number, got nan"),
])
def test_settings_out_of_their_range_are_refused_on_the_command_line_in_one_line(capsys, flags, message):
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", *flags])
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_a_config_file_gets_the_command_lines_types_and_a_bad_one_is_refused_in_one_line(tmp_path, capsys):
    import json

    (tmp_path / "c.json").write_text(json.dumps({"data": "x", "pose_head": "false", "steps": "100", "lr": 1}))
    cfg = TrainConfig.from_args(["--config", str(tmp_path / "c.json")])
    assert cfg.pose_head is False and cfg.steps == 100 and cfg.lr == 1.0
    for text, message in [("[1, 2]", "expected a JSON object"), ("{not json", "not a readable JSON file"),
                          ('{"steps": "many"}', "steps expected int, got 'many'")]:
        (tmp_path / "bad.json").write_text(text)
        with pytest.raises(SystemExit):
            TrainConfig.from_args(["--data", "x", "--config", str(tmp_path / "bad.json")])
        assert message in capsys.readouterr().err
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--config", str(tmp_path / "missing.json")])
    assert "not a readable JSON file" in capsys.readouterr().err


def test_missing_data_or_init_and_a_pretraining_task_end_the_training_command_in_one_line(tmp_path, capsys):
    from training.train import main

    for flags, message in [(["--data", str(tmp_path / "nowhere")], "error:"),
                           (["--data", "x", "--init", str(tmp_path / "missing.pt")], "error:"),
                           (["--data", "x", "--task", "pretrain"], "is python -m training.pretrain's")]:
        assert main(["--preset", "test", "--out", str(tmp_path / "run"), *flags]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1


def test_pretraining_refuses_the_flags_of_pointmap_training_it_would_ignore(tmp_path, capsys):
    from training.pretrain import main

    assert main(["--data", "x", "--preset", "test", "--init", "x.pt", "--match_weight", "5"]) == 2
    assert "--init, --match_weight set pointmap training" in capsys.readouterr().err
    assert main(["--data", "x", "--preset", "test", "--train_only", "enc", "--focal_head", "true"]) == 2
    assert "--focal_head, --train_only set pointmap training" in capsys.readouterr().err
    assert main(["--data", "x", "--preset", "test", "--task", "train"]) == 2
    assert "--task train is python -m training.train's" in capsys.readouterr().err
    from training.train import main as train_main

    assert train_main(["--data", str(tmp_path / "none"), "--preset", "test", "--mask_ratio", "0.5"]) == 2
    assert "--mask_ratio sets cross-view completion pretraining" in capsys.readouterr().err  # before the data


def test_every_setting_pretraining_does_not_read_is_one_it_refuses():
    """A new TrainConfig field that neither the loop nor pretraining reads would be dropped without a word by
    training.pretrain: it must join TRAIN_ONLY (or be refused for pretraining by the config itself)."""
    import re
    from dataclasses import fields

    from training.pretrain import TRAIN_ONLY

    read = "".join((ROOT / "training" / f).read_text() for f in ("loop.py", "pretrain.py", "mix.py"))
    refused_by_config = {"grown_from", "grown_lr"}  # "are for training a grown model (task train)"
    unread = {f.name for f in fields(TrainConfig) if not re.search(rf"cfg\.{f.name}\b", read)}
    assert unread - set(TRAIN_ONLY) - refused_by_config == set()


def test_resuming_into_another_architecture_or_task_is_refused_in_one_line(tmp_path):
    from pointmap.errors import CheckpointError

    run(tmp_path, 1)
    cfg = config(tmp_path, 2)
    with pytest.raises(CheckpointError, match="holds another architecture than this run's"):
        fit(cfg, PointmapNet(PRESETS["test"].replace(enc_depth=3)), PlanePairs(6), collate, make_step(cfg))
    with pytest.raises(CheckpointError, match="is a 'train' checkpoint and this run is 'pretrain'"):
        fit(dataclasses.replace(cfg, task="pretrain"), PointmapNet(PRESETS["test"]), PlanePairs(6), collate,
            make_step(cfg))


def test_a_checkpoint_with_nan_weights_or_a_bad_step_is_refused_and_one_without_its_optimizer_is_not_resumed(
        tmp_path, capsys):
    from pointmap.errors import CheckpointError
    from training.loop import load_checkpoint

    run(tmp_path, 2)
    ck = torch.load(tmp_path / "last.pt", weights_only=False)
    name = next(k for k, v in ck["model"].items() if v.is_floating_point())
    for change, message in (({"model": {**ck["model"], name: ck["model"][name] * float("nan")}},
                             "holds NaN or inf weights"),
                            ({"step": "abc"}, "its step expected an int >= 0, got 'abc'")):
        torch.save({**ck, **change}, tmp_path / "bad.pt")
        with pytest.raises(CheckpointError, match=message):
            load_checkpoint(tmp_path / "bad.pt")
    torch.save({k: v for k, v in ck.items() if k != "optimizer"}, tmp_path / "last.pt")
    cfg = config(tmp_path, 4)
    with pytest.raises(CheckpointError, match="cannot be resumed: it has no optimizer .*--init"):
        fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, make_step(cfg))
    torch.save(ck, tmp_path / "last.pt")
    fit(config(tmp_path, 2), PointmapNet(PRESETS["test"]), PlanePairs(6), collate, make_step(cfg))
    assert "is at step 2, the run's end is step 2: nothing left to train, only the final evaluation" in capsys.readouterr().err


def test_a_csv_row_torn_by_a_killed_run_is_cut_before_the_next_row_is_appended(tmp_path):
    import csv

    from training.loop import Logger

    log = Logger(tmp_path, True)
    log.log("eval", 500, {"RRA15": 10.0})
    with open(tmp_path / "eval.csv", "a") as fh:
        fh.write("600,17958")  # a row cut mid-write
    Logger(tmp_path, True).log("eval", 700, {"RRA15": 12.0})
    with open(tmp_path / "eval.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["step"] for r in rows] == ["500", "700"] and rows[1]["RRA15"] == "12.0"
    with open(tmp_path / "eval.csv", "a") as fh:
        fh.write("800,3")  # torn again, and the next row adds a column: the header is rewritten without it
    Logger(tmp_path, True).log("eval", 900, {"RRA15": 13.0, "RTA15": 5.0})
    with open(tmp_path / "eval.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["step"] for r in rows] == ["500", "700", "900"] and rows[2]["RTA15"] == "5.0"


def test_sigterm_checkpoints_the_current_step_and_a_resumed_run_ends_as_an_uninterrupted_one(tmp_path):
    import signal

    straight = run(tmp_path / "a", 6, ckpt_every=1000)
    cfg = dataclasses.replace(config(tmp_path / "b", 6), ckpt_every=1000)
    step = make_step(cfg)

    def signalled_step(model, batch, k):
        if k == 2:  # the third update: the signal arrives while it runs
            os.kill(os.getpid(), signal.SIGTERM)
        return step(model, batch, k)

    before = signal.getsignal(signal.SIGTERM)
    torch.manual_seed(0)
    result = fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, signalled_step)
    assert result["step"] == 3 and result["terminated"]
    assert torch.load(tmp_path / "b" / "last.pt", weights_only=True)["step"] == 3
    assert signal.getsignal(signal.SIGTERM) is before  # the handler is the loop's only while it runs
    resumed = run(tmp_path / "b", 6, ckpt_every=1000)
    for k, v in straight.state_dict().items():
        assert torch.allclose(v, resumed.state_dict()[k], atol=1e-6), k


def test_ckpt_minutes_checkpoints_by_wall_time_between_ckpt_every_steps(tmp_path, monkeypatch):
    tick_clock(monkeypatch)  # every clock reading 0.05 s later

    def checkpointed_steps(minutes):
        out = tmp_path / f"m{minutes}"
        cfg = dataclasses.replace(config(out, 5), ckpt_every=1000, ckpt_minutes=minutes)
        step, seen = make_step(cfg), []

        def watching_step(model, batch, k):  # the step last.pt holds when each update starts
            seen.append(torch.load(out / "last.pt", weights_only=True)["step"] if (out / "last.pt").exists() else None)
            return step(model, batch, k)

        torch.manual_seed(0)
        fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, watching_step)
        return seen

    assert checkpointed_steps(0.0) == [None] * 5  # by steps alone: only the last update
    assert checkpointed_steps(0.0005) == [None, 1, 2, 3, 4]  # 0.03 s: due after every update (one tick, 0.05 s)
    assert checkpointed_steps(60.0) == [None] * 5


def test_a_sigterm_to_the_whole_process_group_stops_a_run_with_a_data_worker_after_a_checkpoint(tmp_path):
    import signal

    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, str(ROOT / "tests/training/sigterm_worker.py"), str(tmp_path)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        for line in proc.stdout:
            if line.strip() == "step 3":  # a few updates in, with the data worker running
                break
        os.killpg(proc.pid, signal.SIGTERM)  # the main process and its data worker alike
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, err[-2000:]  # the worker script's own exit (training.train's would be 143)
    saved = torch.load(tmp_path / "last.pt", weights_only=True)["step"]
    assert saved >= 4 and f"fit returned at step {saved}" in out
    assert "SIGTERM: checkpointed" in out + err and "DataLoader worker" not in err


def test_checkpoints_by_the_clock_or_a_signal_add_no_decay_keepsakes(tmp_path, monkeypatch):
    import signal

    tick_clock(monkeypatch)
    cfg = dataclasses.replace(config(tmp_path / "a", 8), schedule="wsd", decay_steps=4, ckpt_every=2, decay_ckpts=True,
                              ckpt_minutes=0.0005)  # the clock checkpoints after every update
    step = make_step(cfg)

    def signalled_step(model, batch, k):
        if k == 6:  # the seventh update, inside the decay (5-8)
            os.kill(os.getpid(), signal.SIGTERM)
        return step(model, batch, k)

    torch.manual_seed(0)
    result = fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, signalled_step)
    assert result["step"] == 7 and result["terminated"]
    kept = sorted(p.name for p in (tmp_path / "a").glob("decay_*.pt"))
    assert kept == ["decay_6.pt"]  # the grid's; not 5 (clock) nor 7 (signal)
    assert torch.load(tmp_path / "a" / "last.pt", weights_only=True)["step"] == 7


def test_a_second_sigterm_kills_the_process_as_the_first_would_have(tmp_path):
    code = (
        "import os, signal, time\n"
        "from training.loop import sigterm_flag\n"
        "with sigterm_flag() as got:\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    time.sleep(0.1)\n"
        "    print('first caught', len(got), flush=True)\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    time.sleep(1)\n"
        "print('survived')\n")
    proc = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, text=True, timeout=60)
    assert "first caught 1" in proc.stdout and "survived" not in proc.stdout and proc.returncode == -15


def test_a_sigterm_during_the_last_update_keeps_its_decay_checkpoint_and_the_resume_evaluates_the_end(tmp_path):
    import signal

    cfg = dataclasses.replace(config(tmp_path / "a", 8), schedule="wsd", decay_steps=4, ckpt_every=2,
                              decay_ckpts=True)
    step, evals = make_step(cfg), []

    def signalled_step(model, batch, k):
        if k == 7:  # the last update
            os.kill(os.getpid(), signal.SIGTERM)
        return step(model, batch, k)

    def eval_fn(model):
        evals.append(1)
        return {"score": 1.0}

    torch.manual_seed(0)
    first = fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, signalled_step, eval_fn)
    assert first["step"] == 8 and first["terminated"] and not evals
    assert sorted(p.name for p in (tmp_path / "a").glob("decay_*.pt")) == ["decay_6.pt", "decay_8.pt"]
    again = fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, step, eval_fn)  # resumed at the end
    assert again["step"] == 8 and not again["terminated"] and evals == [1]
    rows = (tmp_path / "a" / "eval.csv").read_text().splitlines()
    assert rows[-1].startswith("8,")
    fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, step, eval_fn)  # once is enough
    assert evals == [1]


def test_train_only_trains_the_named_parameters_and_leaves_every_other_weight_bit_identical(tmp_path):
    from training.train import freeze_except

    model, _ = seeded_model_and_batch(PRESETS["test"].replace(pose_head=True))
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    kept = freeze_except(model, "pose_head")
    assert kept == sum(1 for n, _ in model.named_parameters() if n.startswith("pose_head")) > 0
    cfg = dataclasses.replace(config(tmp_path, 3), pose_weight=1.0, pose_dir_weight=0.5, attn_weight=0.5,
                              train_only="pose_head")
    fit(cfg, model, PlanePairs(6), collate, make_step(cfg))
    moved = {n for n, p in model.named_parameters() if not torch.equal(p, before[n])}
    assert moved and all(n.startswith("pose_head") for n in moved)
    assert freeze_except(model, "") == len(before)  # "" leaves the flags as they are
    with pytest.raises(ValueError, match="'pose_heads' names no parameter"):
        freeze_except(model, "pose_head,pose_heads")
    with pytest.raises(ValueError, match="'' names no parameter"):
        freeze_except(model, "pose_head,")


def test_heads_no_loss_reaches_are_exactly_the_parameters_without_a_gradient_and_are_frozen(tmp_path):
    from training.train import freeze_except, freeze_idle, idle_parameters

    preset = PRESETS["test"].replace(pose_head=True, focal_head=True)
    for kw in (dict(), dict(match_weight=0.0, coarse_weight=0.0, desc_conf_weight=0.0), dict(focal_head_weight=1.0)):
        model, batch = seeded_model_and_batch(preset)
        cfg = dataclasses.replace(config(tmp_path, 1), pose_weight=1.0, **kw)
        loss, _ = make_step(cfg)(model, batch, 0)
        loss.backward()
        # the slow reference: which parameters one step's backward leaves without a gradient (less the DPT's unused
        # lateral unit, which DDP's own search finds)
        no_grad = {n for n, p in model.named_parameters() if p.grad is None and "refinenet4.resConfUnit1" not in n}
        assert set(idle_parameters(cfg, model)) == no_grad
        assert bool(no_grad) == (cfg.focal_head_weight == 0)
        assert set(freeze_idle(cfg, model)) == no_grad
        assert {n for n, p in model.named_parameters() if not p.requires_grad} == no_grad
    model, _ = seeded_model_and_batch(preset)
    freeze_except(model, "focal_head")
    with pytest.raises(ValueError, match="nothing to train: every parameter --train_only focal_head keeps is one no "
                                         "loss reaches"):
        freeze_idle(dataclasses.replace(config(tmp_path, 1), pose_weight=1.0, train_only="focal_head"), model)


def test_the_focal_head_loss_is_added_with_its_weight_and_trains_the_focal_head_alone(tmp_path, capsys):
    from training.train import check_model_options, freeze_except

    model, batch = seeded_model_and_batch(PRESETS["test"].replace(pose_head=True, focal_head=True))
    cfg = dataclasses.replace(config(tmp_path, 1), pose_weight=1.0)
    base, d0 = make_step(cfg)(model, batch, 0)
    both, d = make_step(dataclasses.replace(cfg, focal_head_weight=0.5))(model, batch, 0)
    assert "focal_head_loss" not in d0 and d["focal_head_loss"] > 0
    assert abs(d["focal_head_loss"] - (d["focal_head_err1"] + d["focal_head_err2"]) / 2) < 1e-5
    assert abs(float(both.detach()) - float(base.detach()) - 0.5 * d["focal_head_loss"]) < 1e-4
    assert freeze_except(model, "focal_head") > 0
    only = dataclasses.replace(cfg, pose_weight=0.0, focal_head_weight=1.0, train_only="focal_head")
    check_model_options(only, model)  # no pose loss needed when nothing but the focal head trains
    loss, _ = make_step(only)(model, batch, 0)
    loss.backward()
    assert float(model.focal_head.out.weight.grad.abs().sum()) > 0
    assert all(p.grad is None for n, p in model.named_parameters() if not n.startswith("focal_head"))
    with pytest.raises(ValueError, match="focal head"):
        check_model_options(dataclasses.replace(cfg, focal_head_weight=1.0),
                            PointmapNet(PRESETS["test"].replace(pose_head=True)))
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--data", "x", "--focal_head_weight", "-1"])
    assert "--focal_head_weight expected >= 0" in capsys.readouterr().err


def test_a_fresh_focal_head_is_added_to_an_init_model_without_one(tmp_path):
    from pointmap.checkpoint import save_model
    from training.train import build_model

    torch.manual_seed(0)
    src = PointmapNet(PRESETS["test"].replace(pose_head=True))
    path = save_model(src, tmp_path / "m.safetensors")
    cfg = dataclasses.replace(config(tmp_path, 1), init=str(path), pose_head=True, focal_head=True)
    model = build_model(cfg)
    assert model.cfg.focal_head and float(model.focal_head.out.weight.detach().abs().sum()) == 0
    own = model.state_dict()
    assert all(torch.equal(v, own[k]) for k, v in src.state_dict().items())


BROKEN_SHARD_RUN = """
import dataclasses, sys
sys.path.insert(0, {here!r})
import torch
from data.shards import ShardError
from pointmap.model import PRESETS, PointmapNet
from synthetic import PlanePairs
from training.config import TrainConfig
from training.loop import error_line, fit
from training.train import collate, make_step

class Broken(PlanePairs):
    def __getitem__(self, i):
        if i == 3:
            raise ShardError("shard data/x/shard-000000.tar: member 'scene-1/view-0.npz' is not a readable .npz")
        return super().__getitem__(i)

cfg = TrainConfig(data="synthetic", out={out!r}, preset="test", batch_size=2, steps=6, warmup=2, ckpt_every=100,
                  eval_every=1000, workers=1, quiet=True, n_corr=64, seed=0)
try:
    fit(cfg, PointmapNet(PRESETS["test"]), Broken(6), collate, make_step(cfg))
except ShardError as e:
    print("LINE", error_line(e))
"""


def test_a_shard_that_fails_in_a_loader_worker_ends_the_run_with_its_one_line_instead_of_hanging_it(tmp_path):
    code = BROKEN_SHARD_RUN.format(here=str(Path(__file__).parent), out=str(tmp_path / "run"))
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    assert ("LINE shard data/x/shard-000000.tar: member 'scene-1/view-0.npz' is not a readable .npz"
            in done.stdout.splitlines())


def test_error_line_keeps_a_plain_message_and_takes_a_workers_error_from_the_end_of_its_traceback():
    from training.loop import error_line

    assert error_line(ValueError("loss is nan at step 1: lower --lr")) == "loss is nan at step 1: lower --lr"
    wrapped = ("Caught ShardError in DataLoader worker process 0.\nOriginal Traceback (most recent call last):\n"
               '  File "x.py", line 3, in f\ndata.shards.ShardError: shard a.tar: member \'b\' is bad: x\n')
    assert error_line(RuntimeError(wrapped)) == "shard a.tar: member 'b' is bad: x"


def test_a_finite_loss_with_a_non_finite_gradient_stops_training_before_the_weights_are_written(tmp_path):
    """Clipping by a NaN norm makes every gradient NaN; the optimizer step then wrote NaN weights, and a checkpoint
    at that step kept them. Only the loss was checked."""
    cfg = config(tmp_path / "run", 3)
    step = make_step(cfg)

    def nan_gradient(model, batch, k):
        loss, metrics = step(model, batch, k)
        if k == 1:  # sqrt at 0: the value 0, the gradient NaN (inf times the zero slope of |x| at 0)
            p = next(model.parameters())
            loss = loss + torch.sqrt((p - p.detach()).abs().sum())
        return loss, metrics

    torch.manual_seed(0)
    model = PointmapNet(PRESETS["test"])
    with pytest.raises(FloatingPointError, match=r"gradient norm is nan at step 1 \(the loss, [0-9.]+, is finite\)"):
        fit(cfg, model, PlanePairs(6), collate, nan_gradient)
    assert all(bool(torch.isfinite(p).all()) for p in model.parameters())
    saved = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    assert saved["step"] == 1 and all(bool(torch.isfinite(t).all()) for t in saved["model"].values())


def test_the_descriptor_confidence_loss_joins_a_step_after_the_matching_loss_without_changing_its_sample(tmp_path):
    cfg = config(tmp_path, 1)
    model, batch = seeded_model_and_batch()
    off, d_off = make_step(cfg)(model, batch, 0)
    on, d_on = make_step(dataclasses.replace(cfg, desc_conf_weight=0.5))(model, batch, 0)
    assert "desc_conf_loss" not in d_off and d_on["desc_conf"] > 0
    assert d_on["match_loss"] == d_off["match_loss"] and d_on["match_acc"] == d_off["match_acc"]
    assert float(on.detach()) == pytest.approx(float(off.detach()) + 0.5 * d_on["desc_conf_loss"], rel=1e-5)
    # a head without its own confidence (two_confs false) reports the pointmap's: training it would train that
    one_conf, _ = seeded_model_and_batch(dataclasses.replace(PRESETS["test"], two_confs=False))
    with pytest.raises(ValueError, match="--desc_conf_weight needs a model whose descriptor head predicts its own"):
        check_model_options(dataclasses.replace(cfg, desc_conf_weight=0.5), one_conf)  # before any data is opened


def test_the_seed_fixes_a_fresh_models_initial_weights():
    from training.train import build_model

    cfg = TrainConfig(data="x", preset="test", seed=3)
    torch.manual_seed(100)
    a = build_model(cfg)
    torch.manual_seed(200)
    b = build_model(cfg)
    c = build_model(dataclasses.replace(cfg, seed=4))
    assert all(torch.equal(v, b.state_dict()[k]) for k, v in a.state_dict().items())
    assert not all(torch.equal(v, c.state_dict()[k]) for k, v in a.state_dict().items())


def test_the_steps_own_draws_repeat_on_resume_and_differ_between_ranks(monkeypatch):
    from training.loop import step_generator

    def draw(seed, step):
        return torch.randperm(1000, generator=step_generator(seed, step))[:8].tolist()

    assert draw(3, 17) == draw(3, 17) and draw(3, 17) != draw(3, 18) and draw(3, 17) != draw(4, 17)
    ranks = []
    for rank in (0, 1):
        monkeypatch.setattr(torch.distributed, "is_initialized", lambda: True)
        monkeypatch.setattr(torch.distributed, "get_rank", lambda rank=rank: rank)
        ranks.append(draw(3, 17))
    assert ranks[0] != ranks[1]
    monkeypatch.undo()
    assert ranks[0] == draw(3, 17)  # rank 0 draws what a single process does
