"""training.loop's parts one at a time (sampler, optimizer groups, schedules, DecayByTime, RNG state, checkpoints,
the logger, append_line, SIGTERM) and fit's resume paths: each test pins a behaviour that no test of test_loop.py
held, found by a mutation review (session 88: 68 mutants, 31 missed before, 2 of them equivalent)."""

import csv
import dataclasses
import random
import signal
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pointmap.errors import CheckpointError
from pointmap.model import PRESETS, PointmapNet
from training.config import TrainConfig
from training.loop import (
    DecayByTime,
    Logger,
    StepBatches,
    append_line,
    check_loop_options,
    fit,
    load_checkpoint,
    lr_factor,
    make_optimizer,
    save_checkpoint,
    sigterm_flag,
)
from training.train import collate, make_step

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import PlanePairs  # noqa: E402
from test_loop import config, run, tick_clock  # noqa: E402


def recording_fit(cfg, record, **kwargs):
    """``fit`` of a seed-0 test model on six plane pairs, whose step appends ``(step, draws)`` to ``record``: one
    draw from each global generator (torch, numpy, random and random's Gaussian) the step could use."""
    step = make_step(cfg)

    def recording_step(model, batch, k):
        record.append((k, (float(torch.rand(())), float(np.random.rand()), random.random(), random.gauss(0, 1))))
        return step(model, batch, k)

    torch.manual_seed(0)
    model = PointmapNet(PRESETS["test"])
    return model, fit(cfg, model, PlanePairs(6), collate, recording_step, **kwargs)


def checkpoint_with(path, **train_config):
    """Rewrite the train_config of the checkpoint at ``path`` (as an earlier leg with those settings wrote it)."""
    ck = torch.load(path, weights_only=True)
    ck["train_config"].update(train_config)
    torch.save(ck, path)


# -- data order -----------------------------------------------------------------------------------
def test_each_steps_aspect_ratio_is_a_function_of_the_step_alone_so_a_resumed_sampler_repeats_it():
    args = dict(n=7, batch=2, steps=12, rank=0, world=1, seed=5, n_aspects=3)
    whole = list(StepBatches(start_step=0, **args))
    resumed = StepBatches(start_step=5, **args)
    assert list(resumed) == whole[5:] and len(resumed) == 7
    assert all(len(item) == 2 and item[1] == b[0][1] for b in whole for item in b)  # (index, aspect), one per step
    assert len({b[0][1] for b in whole}) > 1  # the aspect does change between steps


def test_a_sampler_resumed_past_its_end_has_no_batches_and_length_zero():
    done = StepBatches(n=7, batch=2, steps=4, start_step=6, rank=0, world=1, seed=0)
    assert len(done) == 0 and list(done) == []


# -- optimisation ---------------------------------------------------------------------------------
def test_tokens_get_no_weight_decay_and_the_optimizer_is_adamw_with_betas_0_9_and_0_95():
    from pointmap.model.pretrain import CrossViewCompletion

    model = CrossViewCompletion(PRESETS["test"], mask_ratio=0.5)
    cfg = TrainConfig(data="x", weight_decay=0.05)
    opt = make_optimizer(model, cfg)
    decay_of = {id(p): g["weight_decay"] for g in opt.param_groups for p in g["params"]}
    named = dict(model.named_parameters())
    assert named["mask_token"].ndim == 3 and decay_of[id(named["mask_token"])] == 0.0
    assert {decay_of[id(p)] for n, p in named.items() if p.ndim >= 2 and "token" not in n} == {0.05}
    assert isinstance(opt, torch.optim.AdamW) and opt.defaults["betas"] == (0.9, 0.95)


def test_a_wsd_decay_may_start_right_after_the_warmup():
    check_loop_options(TrainConfig(data="x", steps=100, warmup=10, schedule="wsd", decay_steps=90))
    with pytest.raises(ValueError, match="0 < --decay_steps <= --steps - --warmup"):
        check_loop_options(TrainConfig(data="x", steps=100, warmup=10, schedule="wsd", decay_steps=91))


def test_the_cosine_schedule_runs_the_first_update_after_warmup_at_full_rate_and_is_halfway_at_mid_decay():
    cfg = TrainConfig(data="x", lr=1e-3, min_lr=1e-5, warmup=10, steps=110)
    floor = cfg.min_lr / cfg.lr
    assert lr_factor(10, cfg) == pytest.approx(1.0, abs=1e-12)
    assert lr_factor(60, cfg) == pytest.approx(floor + (1 - floor) * 0.5, abs=1e-12)  # t = 50/100
    assert lr_factor(35, cfg) == pytest.approx(floor + (1 - floor) * 0.5 * (1 + 2 ** -0.5), abs=1e-12)  # t = 1/4


# -- decay by time --------------------------------------------------------------------------------
def test_decay_by_time_reads_the_pace_only_after_min_steps_durations_of_this_legs_warm_steps(tmp_path):
    # no time left at all: the decay starts at the first step the pace may be read, min_steps durations after the
    # leg's warm-th step (counted from where the leg started, so a resumed leg excludes its own compilation)
    for start in (0, 100):
        cfg = dataclasses.replace(config(tmp_path, 1000), schedule="wsd", decay_steps=10, max_minutes=0.01,
                                  decay_by_time=True)
        clock = DecayByTime(cfg, start=start, t0=0.0, warm=5, min_steps=5)
        started = [s for s in range(start + 1, start + 30) if clock.update(s, 60.0 + s)]
        assert started == [start + 10] and cfg.steps == start + 20, start


def test_decay_by_time_keeps_the_reserve_for_the_last_evaluation_and_checkpoint(tmp_path):
    cfg = dataclasses.replace(config(tmp_path, 1000), schedule="wsd", decay_steps=10, max_minutes=1.0,
                              decay_by_time=True)
    clock = DecayByTime(cfg, start=0, t0=0.0, warm=5)
    # as test_loop's 1 s steps after a 30 s first one (the decay started at step 18), with 3 s kept back: 3 steps earlier
    assert [s for s in range(1, 100) if clock.update(s, 30.0 + (s - 1), reserve=3.0)] == [15]


def test_the_pace_is_the_mean_of_the_last_window_durations(tmp_path):
    cfg = dataclasses.replace(config(tmp_path, 1000), warmup=0, schedule="wsd", decay_steps=10, max_minutes=60.0,
                              decay_by_time=True)
    clock = DecayByTime(cfg, start=0, t0=0.0, warm=0, window=3)
    now = 0.0
    for s, seconds in enumerate([1, 1, 1, 1, 3, 3], start=1):
        now += seconds
        clock.update(s, now)
    assert clock.pace() == pytest.approx(7 / 3)  # 1, 3, 3 (the median 3 clips nothing)


def test_fit_passes_the_last_evaluations_and_checkpoints_durations_to_decay_by_time(tmp_path, monkeypatch):
    import training.loop as loop

    tick_clock(monkeypatch)  # each evaluation and checkpoint takes one tick: 0.05 s
    reserves = []

    class Recording(loop.DecayByTime):
        def update(self, step, now, reserve=0.0):
            reserves.append(reserve)
            return super().update(step, now, reserve)

    monkeypatch.setattr(loop, "DecayByTime", Recording)
    cfg = dataclasses.replace(config(tmp_path, 3), eval_every=1, schedule="wsd", decay_steps=1, max_minutes=60.0,
                              decay_by_time=True)
    torch.manual_seed(0)
    fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, make_step(cfg), eval_fn=lambda m: {"x": 1.0})
    assert reserves[0] == 0.0 and reserves[1:] == pytest.approx([0.1, 0.1])


# -- checkpoints and resuming ---------------------------------------------------------------------
def test_a_checkpoint_restores_every_global_random_generator_including_randoms_cached_gaussian(tmp_path):
    from training.loop import _set_rng_state

    torch.manual_seed(0)
    model = PointmapNet(PRESETS["test"])
    cfg = config(tmp_path, 1)
    opt = make_optimizer(model, cfg)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    torch.manual_seed(11), np.random.seed(12), random.seed(13)
    np.random.rand(5)  # a position inside numpy's key
    random.gauss(0, 1)  # random keeps the second Gaussian of the pair it draws
    save_checkpoint(tmp_path / "c.pt", model, opt, sched, 1, cfg)

    def draws():
        return (torch.rand(3).tolist(), np.random.rand(3).tolist(), random.gauss(0, 1), random.random())

    want = draws()
    draws()
    _set_rng_state(load_checkpoint(tmp_path / "c.pt")["rng"])
    assert draws() == want


def test_a_resumed_run_draws_what_the_uninterrupted_one_did_from_every_global_generator(tmp_path):
    """torch's too: until session 88 iter(loader) drew the workers' base seed from it after the checkpoint's RNG
    state was restored, so a resumed run's torch draws were one draw off."""
    straight, resumed = [], []
    recording_fit(config(tmp_path / "a", 4), straight)
    recording_fit(config(tmp_path / "b", 2), resumed)
    recording_fit(config(tmp_path / "b", 4), resumed)
    assert [k for k, _ in resumed] == [0, 1, 2, 3]
    for (k, want), (_, got) in zip(straight, resumed):
        assert got == want, k


def test_a_run_resumed_inside_its_warmup_ends_with_the_same_weights_as_an_uninterrupted_one(tmp_path):
    straight = run(tmp_path / "a", 5, warmup=4)
    run(tmp_path / "b", 2, warmup=4)
    resumed = run(tmp_path / "b", 5, warmup=4)
    for k, v in straight.state_dict().items():
        assert torch.allclose(v, resumed.state_dict()[k], atol=1e-6), k


def test_resume_false_starts_over_in_an_out_that_holds_a_checkpoint(tmp_path):
    run(tmp_path, 2)
    seen = []
    _, result = recording_fit(dataclasses.replace(config(tmp_path, 3), resume=False), seen)
    assert [k for k, _ in seen] == [0, 1, 2] and result["step"] == 3


def test_ranks_draw_from_differently_seeded_global_generators(tmp_path, monkeypatch):
    import training.loop as loop

    draws = {}
    for rank in (0, 1):
        monkeypatch.setattr(loop, "setup_distributed", lambda rank=rank: (rank, 1, torch.device("cpu")))
        record = []
        recording_fit(config(tmp_path / f"r{rank}", 1), record)
        draws[rank] = record[0][1]
    assert all(a != b for a, b in zip(draws[0], draws[1]))


def test_a_resumed_optimizer_whose_names_do_not_match_the_model_is_refused_in_one_line(tmp_path):
    run(tmp_path, 1)
    good = torch.load(tmp_path / "last.pt", weights_only=True)
    cfg = config(tmp_path, 2)
    renamed = [list(g) for g in good["optimizer_names"]]
    renamed[0][0] = "no.such.parameter"
    short = [list(g) for g in good["optimizer_names"]]
    short[1] = short[1][:-1]
    short[0] = short[0] + [good["optimizer_names"][1][-1]]  # the same names, one of them filed in the wrong group
    for names, message in ((renamed, "holds other parameters than this model's"),
                           (short, r"names \d+ parameters for a group of \d+")):
        torch.save({**good, "optimizer_names": names}, tmp_path / "last.pt")
        with pytest.raises(CheckpointError, match=message):
            fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, make_step(cfg))


def test_a_failed_checkpoint_write_leaves_the_previous_checkpoint_whole(tmp_path, monkeypatch):
    torch.manual_seed(0)
    model = PointmapNet(PRESETS["test"])
    cfg = config(tmp_path, 1)
    opt = make_optimizer(model, cfg)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    save_checkpoint(tmp_path / "last.pt", model, opt, sched, 1, cfg)
    before = (tmp_path / "last.pt").read_bytes()

    def torn_save(obj, f, *args, **kwargs):  # the process dies half way through the write
        Path(f).write_bytes(b"PK\x03\x04 half a checkpoint")
        raise OSError("No space left on device")

    monkeypatch.setattr(torch, "save", torn_save)
    with pytest.raises(OSError, match="No space left"):
        save_checkpoint(tmp_path / "last.pt", model, opt, sched, 2, cfg)
    monkeypatch.undo()
    assert (tmp_path / "last.pt").read_bytes() == before and load_checkpoint(tmp_path / "last.pt")["step"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]  # no temporary file left


def test_a_checkpoint_at_step_zero_loads_and_a_boolean_step_is_refused(tmp_path):
    run(tmp_path, 1)
    ck = torch.load(tmp_path / "last.pt", weights_only=True)
    torch.save({**ck, "step": 0}, tmp_path / "zero.pt")
    assert load_checkpoint(tmp_path / "zero.pt")["step"] == 0
    torch.save({**ck, "step": True}, tmp_path / "bool.pt")
    with pytest.raises(CheckpointError, match="its step expected an int >= 0, got True"):
        load_checkpoint(tmp_path / "bool.pt")


def decay_by_time(out, steps, decay_steps):
    return dataclasses.replace(config(out, steps), schedule="wsd", decay_steps=decay_steps, max_minutes=60.0,
                               decay_by_time=True)


def test_a_decay_by_time_run_resumed_from_its_stable_checkpoint_trains_on_to_the_new_steps(tmp_path):
    run(tmp_path, 2)  # as stable_2.pt of a leg whose clock placed its end at step 4
    checkpoint_with(tmp_path / "last.pt", schedule="wsd", steps=4, decay_steps=2, decay_by_time=True, max_minutes=60.0)
    cfg = decay_by_time(tmp_path, 6, 2)
    result = fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, make_step(cfg))
    assert result["step"] == 6


def test_a_decay_by_time_run_resumed_mid_decay_keeps_where_the_decay_started_and_the_callers_config(tmp_path):
    # a leg whose decay (2 steps) was placed from step 2 to 4 is resumed at step 3 with --decay_steps 3: the decay
    # keeps its start, step 2, and now ends at 5; --steps 5 (the placed end) is enough
    for steps in (100, 5):
        out = tmp_path / str(steps)
        run(out, 3)
        checkpoint_with(out / "last.pt", schedule="wsd", steps=4, decay_steps=2, decay_by_time=True, max_minutes=60.0)
        cfg = decay_by_time(out, steps, 3)
        result = fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, make_step(cfg))
        assert result["step"] == 5 and cfg.steps == steps, steps


def test_evaluation_runs_every_eval_every_steps_and_at_the_end_and_train_csv_every_log_every_steps(tmp_path):
    cfg = dataclasses.replace(config(tmp_path, 5), eval_every=2, log_every=2)
    torch.manual_seed(0)
    fit(cfg, PointmapNet(PRESETS["test"]), PlanePairs(6), collate, make_step(cfg), eval_fn=lambda m: {"x": 1.0})
    with open(tmp_path / "eval.csv", newline="") as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == [2, 4, 5]
    with open(tmp_path / "train.csv", newline="") as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == [2, 4]


# -- logging and signals --------------------------------------------------------------------------
def test_has_eval_is_true_only_for_a_step_eval_csv_holds(tmp_path):
    log = Logger(tmp_path, True)
    assert not log.has_eval(4)
    log.log("eval", 4, {"x": 1.0})
    assert log.has_eval(4) and not log.has_eval(8) and not log.has_eval(40)


def test_a_torn_eval_row_does_not_count_as_the_steps_evaluation(tmp_path):
    Logger(tmp_path, True).log("eval", 4, {"x": 1.0})
    with open(tmp_path / "eval.csv", "a") as fh:
        fh.write("8,17958")  # the final evaluation's row, cut mid-write
    assert not Logger(tmp_path, True).has_eval(8)


def test_append_line_cuts_a_torn_last_line_and_keeps_the_newline_before_it(tmp_path):
    path = tmp_path / "log.txt"
    append_line(path, b"a\n")
    with open(path, "ab") as fh:
        fh.write(b"b")  # torn
    append_line(path, b"c\n")
    assert path.read_bytes() == b"a\nc\n"


def test_append_line_keeps_a_long_file_whose_last_64_kib_hold_no_newline(tmp_path):
    path = tmp_path / "log.csv"
    long_line = b"a,b\n" + b"x" * 70_000  # no newline in the last 64 KiB: where the torn row starts is unknown
    path.write_bytes(long_line)
    append_line(path, b"1,2\n")
    assert path.read_bytes() == long_line + b"1,2\n"


def test_sigterm_flag_gives_back_a_python_handler_installed_before_it(tmp_path):
    def mine(signum, frame):
        pass

    before = signal.signal(signal.SIGTERM, mine)
    try:
        with sigterm_flag():
            assert signal.getsignal(signal.SIGTERM) is not mine
        assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, before)
