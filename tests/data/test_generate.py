import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from data.generate import GenConfig, generate, main, parse_shards
from data.shards import ShardError, completed_shards
from pointmap.errors import ShapeError

ROOT = Path(__file__).resolve().parents[2]
ARGS = ["--scenes", "5", "--shard-size", "1", "--size", "64", "--views", "2", "--seed", "5", "--quiet"]


def _run(out, extra=()):
    env = dict(os.environ, PYOPENGL_PLATFORM="egl", PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "data.render", "--out", str(out), *ARGS, *extra], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _files(d):
    return {p.name: p.read_bytes() for p in sorted(Path(d).iterdir()) if p.is_file()}


def test_a_run_killed_mid_way_and_restarted_gives_byte_identical_shards(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    p = _run(a)
    assert p.wait(timeout=300) == 0, p.stderr.read().decode()
    killed = _run(b)
    deadline = time.time() + 300
    while not (b / "shard-000001.json").exists():  # wait until some, but not all, shards are done
        assert killed.poll() is None, "run finished before it could be killed"
        assert time.time() < deadline
        time.sleep(0.05)
    killed.send_signal(signal.SIGKILL)
    killed.wait()
    assert not (b / "shard-000004.json").exists()
    p = _run(b)
    assert p.wait(timeout=300) == 0, p.stderr.read().decode()
    fa, fb = _files(a), _files(b)
    assert fa.keys() == fb.keys()  # no temporary files left behind either
    for name in fa:
        assert fa[name] == fb[name], name
    manifest = json.loads(fa["manifest.json"])
    assert manifest["complete"] and len(manifest["shards"]) == 5


def test_a_shard_with_a_wrong_checksum_is_reported_not_used_and_re_rendered(tmp_path):
    cfg = GenConfig(kind="pairs", scenes=2, views=2, size=64, shard_size=1, seed=11)
    generate(tmp_path, cfg, progress=False, log=None)
    good = (tmp_path / "shard-000001.tar").read_bytes()
    bad = bytearray(good)
    bad[700] ^= 0xFF
    (tmp_path / "shard-000001.tar").write_bytes(bytes(bad))
    with pytest.warns(UserWarning, match="sha256 mismatch"):
        entries, problems = completed_shards(tmp_path)
    assert [e["index"] for e in entries] == [0] and len(problems) == 1
    from data.datasets import PairDataset
    with pytest.warns(UserWarning, match="shard-000001.tar"):
        ds = PairDataset(tmp_path, size=64, split="all")
    assert {k for k, *_ in ds.items} == {0}
    generate(tmp_path, cfg, progress=False, log=None)  # resume notices and re-renders it
    assert (tmp_path / "shard-000001.tar").read_bytes() == good


def test_shard_ranges_render_only_their_shards_and_merge_into_one_manifest(tmp_path):
    cfg = GenConfig(kind="views", scenes=3, views=2, size=64, shard_size=1, seed=3)
    generate(tmp_path, cfg, shards=range(1, 2), progress=False, log=None)
    assert [p.name for p in sorted(tmp_path.glob("shard-*.tar"))] == ["shard-000001.tar"]
    generate(tmp_path, cfg, shards=range(0, 1), progress=False, log=None)
    generate(tmp_path, cfg, shards=range(2, 3), progress=False, log=None)
    m = json.loads((tmp_path / "manifest.json").read_text())
    assert m["complete"] and [s["index"] for s in m["shards"]] == [0, 1, 2]


def test_two_workers_write_the_same_bytes_as_one(tmp_path):
    cfg = GenConfig(kind="pairs", scenes=2, views=2, size=64, shard_size=1, seed=21)
    generate(tmp_path / "one", cfg, workers=1, progress=False, log=None)
    generate(tmp_path / "two", cfg, workers=2, progress=False, log=None)
    assert _files(tmp_path / "one") == _files(tmp_path / "two")


def test_workers_forked_by_a_process_without_gl_write_the_same_bytes_as_one_worker(tmp_path):
    generate(tmp_path / "one", GenConfig(kind="pairs", scenes=5, views=2, size=64, shard_size=1, seed=5),
             workers=1, progress=False, log=None)
    p = _run(tmp_path / "two", ["--workers", "2"])  # the CLI's process never touches GL: its workers are forked
    assert p.wait(timeout=300) == 0, p.stderr.read().decode()
    assert _files(tmp_path / "one") == _files(tmp_path / "two")


def test_a_render_worker_that_dies_stops_the_run_with_a_message_instead_of_a_hang(tmp_path):
    # a multiprocessing.Pool replaced the killed worker and waited forever for the shard it held
    p = _run(tmp_path / "d", ["--workers", "2", "--scenes", "40"])
    t0, workers = time.time(), []
    while len(workers) < 2 and time.time() - t0 < 120 and p.poll() is None:
        time.sleep(0.2)
        found = subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True, text=True).stdout.split()
        workers = [int(w) for w in found]
    assert workers, "no render worker started"
    time.sleep(1.0)
    os.kill(max(workers), signal.SIGKILL)  # as the OOM killer would
    assert p.wait(timeout=180) == 2
    err = p.stderr.read().decode()
    assert "a render worker died (killed, or out of memory?)" in err and "Traceback" not in err


def test_workers_are_forked_only_while_this_process_has_not_touched_gl(monkeypatch):
    from data.generate import _pool_context

    for name in ("pyrender", "OpenGL"):
        monkeypatch.setitem(sys.modules, name, sys.modules.get(name, object()))
    assert _pool_context().get_start_method() == "spawn"
    for name in ("pyrender", "OpenGL"):
        monkeypatch.delitem(sys.modules, name)
    assert _pool_context().get_start_method() == "fork"


def test_cli_rejects_bad_arguments_with_exit_code_2(tmp_path, capsys):
    assert main(["--out", str(tmp_path / "x"), "--scenes", "0"]) == 2
    assert "scenes expected" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "x"), "--scenes", "2", "--size", "100"]) == 2
    assert "multiple of 16" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "x"), "--scenes", "2", "--seed", str(2**31 - 5)]) == 2
    assert "reserved" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "x"), "--scenes", "2", "--shards", "1:9"]) == 2
    assert "outside" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "x"), "--scenes", "2", "--views", "100000"]) == 2
    assert "views expected at most 64 per scene, got 100000" in capsys.readouterr().err


def test_an_overlap_no_scene_can_meet_is_one_line_naming_the_flag(tmp_path, capsys):
    assert main(["--out", str(tmp_path / "x"), "--scenes", "1", "--size", "64", "--views", "2", "--overlap", "0.999",
                 "1.0", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no view set overlapped within --overlap 0.999 1.0; widen it" in err[0]
    # the widened command runs: the failed run left only its config.json (refused as "holds shards" before)
    assert main(["--out", str(tmp_path / "x"), "--scenes", "1", "--size", "64", "--views", "2", "--quiet"]) == 0
    assert json.loads((tmp_path / "x" / "config.json").read_text())["overlap_lo"] != 0.999


def test_a_folder_whose_config_json_is_not_a_datasets_is_refused_and_left_as_it_was(tmp_path, capsys):
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "config.json").write_text('{"architectures": ["Dust3r"]}')
    assert main(["--out", str(tmp_path / "model"), "--scenes", "1", "--size", "64", "--views", "2", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "config.json is not a data.render dataset's (its format is None" in err
    assert "generator-version" not in err  # before: "resume it with --generator-version None"
    assert (tmp_path / "model" / "config.json").read_text() == '{"architectures": ["Dust3r"]}'


def test_resuming_with_another_configuration_is_refused(tmp_path):
    generate(tmp_path, GenConfig(kind="views", scenes=1, views=1, size=64, seed=1), progress=False, log=None)
    with pytest.raises(ShardError, match="another configuration"):
        generate(tmp_path, GenConfig(kind="views", scenes=1, views=1, size=64, seed=2), progress=False, log=None)


def test_shard_ranges_parse_as_python_slices_and_a_bare_number_is_refused():
    assert parse_shards("2:5", 10) == range(2, 5)
    assert parse_shards(":3", 10) == range(0, 3) and parse_shards("7:", 10) == range(7, 10)
    with pytest.raises(ValueError, match="A:B"):
        parse_shards("3", 10)


def test_cli_refuses_an_output_path_that_is_a_file_in_one_line(tmp_path, capsys):
    (tmp_path / "taken").write_text("x")
    assert main(["--out", str(tmp_path / "taken"), "--scenes", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out expected a folder for the dataset" in err[0]


def test_stale_temp_removal_leaves_the_temps_of_a_host_whose_name_starts_with_this_ones(tmp_path, monkeypatch):
    import socket

    from data.generate import _remove_stale_temps

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # a pid no process has any more (here)
    monkeypatch.setattr(socket, "gethostname", lambda: "vm")
    ours = tmp_path / f".shard-000001.tar.tmp-vm-{dead.pid}"           # this host's, its writer gone: removed
    other = tmp_path / f".shard-000003.tar.tmp-vm-2-{dead.pid}"        # host "vm-2"'s, in flight there: kept
    dotted = tmp_path / f".shard-000004.tar.tmp-vm.lan-{dead.pid}"     # host "vm.lan"'s: kept
    for p in (ours, other, dotted):
        p.write_bytes(b"in flight")
    _remove_stale_temps(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([other.name, dotted.name])
    monkeypatch.setattr(socket, "gethostname", lambda: "vm-2")  # on its own host, vm-2 removes its dead writer's
    _remove_stale_temps(tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == [dotted.name]


def test_a_pair_size_the_correspondence_format_cannot_hold_is_refused_before_anything_is_written(tmp_path, capsys):
    from data.geom import CORR_MAX

    with pytest.raises(ValueError, match=r"size expected at most 1008 with kind 'pairs' .*, got 1024"):
        GenConfig(kind="pairs", scenes=1, size=1024)
    from data.geom import decode_corr, encode_corr

    edge = GenConfig(kind="pairs", scenes=1, size=1008).size - 0.5 - 1e-6  # the far edge of the largest size
    assert edge + 0.5 <= CORR_MAX and abs(float(decode_corr(encode_corr(np.full((1, 1, 2), edge)))[0, 0, 0]) - edge) < 0.01
    with pytest.raises(ShapeError, match="corr values expected in"):  # 1024's last half pixel: stored as 'none'
        encode_corr(np.full((1, 1, 2), 1023.48))
    assert GenConfig(kind="views", scenes=1, size=1040).size == 1040  # view sets store no correspondences
    out = tmp_path / "big"
    assert main(["--out", str(out), "--scenes", "1", "--size", "1040", "--quiet"]) == 2
    assert "size expected at most 1008" in capsys.readouterr().err and not out.exists()


def test_a_run_of_an_older_generator_version_resumes_only_with_that_version_and_a_heldout_set_keeps_its_own(
        tmp_path, capsys):
    import data
    from data.generate import GENERATOR_VERSION

    old = GENERATOR_VERSION - 1
    cfg = GenConfig(kind="views", scenes=2, views=1, size=64, seed=1, shard_size=1, version=old)
    generate(tmp_path / "run", cfg, shards=range(1), progress=False, log=None)  # one of its two shards, then stopped
    before = _files(tmp_path / "run")
    with pytest.raises(ShardError, match=f"rendered by generator version {old}, this run asks for version "
                                         f"{GENERATOR_VERSION}.*resume it with --generator-version {old}"):
        generate(tmp_path / "run", replace(cfg, version=GENERATOR_VERSION), progress=False, log=None)
    assert _files(tmp_path / "run") == before
    assert main(["--out", str(tmp_path / "run"), "--kind", "views", "--scenes", "2", "--views", "1", "--size", "64",
                 "--seed", "1", "--shard-size", "1", "--generator-version", str(old), "--quiet"]) == 0
    assert json.loads((tmp_path / "run" / "manifest.json").read_text())["complete"]
    with pytest.raises(ValueError, match="version expected a generator version of"):
        GenConfig(kind="views", scenes=1, version=GENERATOR_VERSION + 1)
    held = tmp_path / "older" / "heldout-views-64"  # a held-out set the older code rendered: read with its version
    generate(held, GenConfig(kind="views", scenes=1, views=2, size=64, shard_size=1, seed=data.HELDOUT_SEED,
                             version=old), progress=False, log=None)
    before = _files(held)
    assert data.heldout(tmp_path / "older", kind="views", size=64, scenes=1, views=2).config["version"] == old
    assert _files(held) == before
    assert data.heldout(tmp_path, kind="views", size=64, scenes=1, views=2).config["version"] == GENERATOR_VERSION

def test_counts_may_be_numpy_integers_but_not_bools_and_the_size_stays_within_the_renderer():
    # before: np.int64 scenes were refused ("expected an int, got np.int64(2)") and True was taken as 1
    cfg = GenConfig(kind="pairs", scenes=np.int64(2), views=np.int32(2), size=64, seed=np.int64(3))
    assert (cfg.scenes, cfg.seed) == (2, 3) and type(cfg.scenes) is int and type(cfg.seed) is int
    assert json.loads(json.dumps(cfg.to_dict()))["scenes"] == 2
    for kw, message in ((dict(scenes=True), "scenes expected an int >= 1, got True"),
                        (dict(seed=True), "seed expected an int in \\[0, 2\\*\\*31\\), got True"),
                        (dict(kind="views", size=8208), "size expected a multiple of 16 up to 8192")):
        with pytest.raises(ValueError, match=message):
            GenConfig(**{"kind": "pairs", "scenes": 1, "size": 64, **kw})
