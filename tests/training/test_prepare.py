"""training.prepare: a user's scenes (photographs, depth maps, cameras) into the engine's shard format, with
their correspondences exact and a wrong convention diagnosed instead of trained on."""

import json

import cv2
import numpy as np
import pytest
import torch

from data.datasets import PairDataset
from data.geom import look_at
from training.prepare import main

W, H, F = 96, 72, 80.0
SLOPE, PLANE_Z = 0.5, 4.0  # the scene: the tilted plane z = 4 + 0.5 x (world, metres), textured


def plane_depth(K, cam2world):
    """z-depth of the plane z = PLANE_Z + SLOPE x seen by the camera, per pixel (0 where it is behind)."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # camera z = 1
    d_world = rays @ cam2world[:3, :3].T
    o = cam2world[:3, 3]
    t = (PLANE_Z + SLOPE * o[0] - o[2]) / (d_world[..., 2] - SLOPE * d_world[..., 0])
    return np.where(t > 0, t, 0).astype(np.float32)


def make_scene(folder, *, opengl=True, depth_factor=1.0, png_depth=False, drop_depth=(), depth_noise=0.0,
               small=()):
    """Four photographs of the plane from cameras half a metre apart, a transforms.json (nerfstudio: OpenGL axes, cx in
    edge coordinates) and depth maps; returns the cameras (OpenCV cam2world) and K."""
    rng = np.random.default_rng(0)
    (folder / "images").mkdir(parents=True)
    (folder / "depth").mkdir()
    K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1]])
    texture = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    frames, cams = [], []
    for k in range(4):
        eye = np.array([0.3 * k, 0.1 * k, 0.4 * k])  # sideways and forwards
        c2w = look_at(eye, eye + np.array([0.05, 0.0, 1.0]), up=(0.0, -1.0, 0.0))
        cams.append(c2w)
        img = texture if k not in small else cv2.resize(texture, (W // 2, H // 2), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(folder / "images" / f"f{k}.png"), img)
        depth = plane_depth(K, c2w) * depth_factor
        depth = depth * (1 + depth_noise * rng.standard_normal(depth.shape)).astype(np.float32)
        if k not in drop_depth:
            if png_depth:
                cv2.imwrite(str(folder / "depth" / f"f{k}.png"), np.rint(depth * 1000).astype(np.uint16))
            else:
                np.save(folder / "depth" / f"f{k}.npy", depth)
        T = c2w @ np.diag([1.0, -1, -1, 1]) if opengl else c2w
        frames.append({"file_path": f"images/f{k}.png", "transform_matrix": T.tolist()})
    for k in small:  # a photograph at half resolution: its camera says so
        frames[k].update(w=W // 2, h=H // 2, fl_x=F / 2, fl_y=F / 2, cx=(K[0, 2] + 0.5) / 2, cy=(K[1, 2] + 0.5) / 2)
    meta = {"w": W, "h": H, "fl_x": F, "fl_y": F, "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return cams, K


def test_a_scene_becomes_a_training_set_whose_correspondences_follow_the_cameras(tmp_path, capsys):
    cams, K = make_scene(tmp_path / "s")
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out"), "--max-side", "64"]) == 0
    printed = capsys.readouterr().out
    assert "4 views" in printed and "100% of pixels with depth" in printed
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert manifest["views"] == 4 and manifest["pairs"] >= 3
    ds = PairDataset(tmp_path / "out", size=48, augment=False, split="all")
    v1, v2 = ds[0]
    # the stored views are 64 x 48 (long side 64): K scaled about pixel centres; the dataset centre-crops to 48
    # every correspondence lands where view 2's camera sees view 1's 3D point
    corr = v1["corr"].numpy()
    ok = np.isfinite(corr).all(-1)
    assert ok.mean() > 0.3
    pts = v1["pts_world"].numpy()[ok]
    w2c = np.linalg.inv(v2["cam2world"].numpy())
    cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
    uv = cam[:, :2] / cam[:, 2:] * np.diag(v2["K"].numpy())[:2] + v2["K"].numpy()[:2, 2]
    assert np.median(np.linalg.norm(uv - corr[ok], axis=-1)) < 0.1
    # and the world is the files' (OpenCV cameras, metres): view 1's points lie on the plane
    assert np.allclose(pts[:, 2], PLANE_Z + SLOPE * pts[:, 0], atol=0.05)


def test_resizing_keeps_the_intrinsics_exact_about_pixel_centres(tmp_path):
    make_scene(tmp_path / "s")
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out"), "--max-side", "48"]) == 0
    import tarfile

    with tarfile.open(tmp_path / "out" / "shard-000000.tar") as tar:
        meta = json.loads(tar.extractfile("scene-00000000/meta.json").read())
    K = np.array(meta["views"][0]["K"])
    assert (meta["width"], meta["height"]) == (48, 36)
    s = 48 / W
    assert np.allclose(K, [[F * s, 0, (W / 2) * s - 0.5], [0, F * s, (H / 2) * s - 0.5], [0, 0, 1]])


@pytest.mark.parametrize("kind,message", [
    ("opencv", "with the cameras in OpenGL axes"),
    ("millimetres", "with the depth x 0.001"),
])
def test_a_scene_read_in_the_wrong_convention_is_skipped_with_the_reading_that_fits(tmp_path, capsys, kind, message):
    make_scene(tmp_path / "s", opengl=kind != "opencv", depth_factor=1000.0 if kind == "millimetres" else 1.0)
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "no scene could be used" in err and "no pair of views overlaps" in err and message in err


def test_png_depth_in_millimetres_and_a_photograph_without_depth(tmp_path, capsys):
    make_scene(tmp_path / "s", png_depth=True, drop_depth=(3,))
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "left out 1 photograph(s): f3.png (no depth)" in out and "3 views" in out


def test_a_second_run_with_other_settings_is_refused_and_bad_options_too(tmp_path, capsys):
    make_scene(tmp_path / "s")
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out")]) == 0
    first = (tmp_path / "out" / "shard-000000.tar").read_bytes()
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out")]) == 0  # the same: rewritten identically
    assert (tmp_path / "out" / "shard-000000.tar").read_bytes() == first
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out"), "--depth-tol", "0.05"]) == 2
    assert "holds a dataset of other scenes or settings" in capsys.readouterr().err
    for bad, message in [(["--overlap", "0.9,0.1"], "--overlap expected lo,hi"),
                         (["--max-side", "0"], "--max-side expected > 0"),
                         (["--max-side", "2048"], "--max-side expected <= 1023"),
                         (["--depth-png-scale", "0"], "--depth-png-scale expected > 0"),  # reconstruct's name
                         (["--png-depth-scale", "-1"], "--depth-png-scale expected > 0")]:  # the old one, an alias
        assert main([str(tmp_path / "s"), "--out", str(tmp_path / "o2"), *bad]) == 2
        assert message in capsys.readouterr().err
    assert main([str(tmp_path / "nothing"), "--out", str(tmp_path / "o3")]) == 2
    assert "a scene expected a folder" in capsys.readouterr().err


def test_a_rendered_scene_written_out_as_a_users_files_is_prepared_back_to_the_engines_pairs(tmp_path):
    import os
    import subprocess
    import sys
    import tarfile
    from pathlib import Path

    from data.geom import decode_corr
    from data.shards import read_npz, read_png

    root = Path(__file__).resolve().parents[2]  # rendered in a process of its own: no GL state shared with others
    subprocess.run([sys.executable, "-m", "data.render", "--out", str(tmp_path / "rendered"), "--kind", "pairs",
                    "--scenes", "1", "--views", "3", "--size", "64", "--shard-size", "1", "--seed", "7",
                    "--workers", "1"], check=True, capture_output=True, timeout=300,
                   env=dict(os.environ, PYOPENGL_PLATFORM="egl", PYTHONPATH=str(root)))

    def read(path):
        with tarfile.open(path) as tar:
            return {m.name: tar.extractfile(m).read() for m in tar.getmembers()}

    engine = read(tmp_path / "rendered" / "shard-000000.tar")
    meta = json.loads(engine["scene-00000000/meta.json"])
    scene = tmp_path / "user"
    (scene / "images").mkdir(parents=True)
    (scene / "depth").mkdir()
    frames = []
    for k, v in enumerate(meta["views"]):
        rgb = read_png(engine[f"scene-00000000/view-{k}.png"])
        cv2.imwrite(str(scene / "images" / f"v{k}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        np.save(scene / "depth" / f"v{k}.npy", read_npz(engine[f"scene-00000000/view-{k}.npz"])["depth_z"])
        K = np.array(v["K"])
        frames.append({"file_path": f"images/v{k}.png", "w": meta["width"], "h": meta["height"],
                       "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5,
                       "transform_matrix": (np.array(v["cam2world"]) @ np.diag([1.0, -1, -1, 1])).tolist()})
    (scene / "transforms.json").write_text(json.dumps({"frames": frames}))
    assert main([str(scene), "--out", str(tmp_path / "prepared"), "--depth-tol", "0.005", "--max-side", "64"]) == 0
    ours = read(tmp_path / "prepared" / "shard-000000.tar")
    mine = json.loads(ours["scene-00000000/meta.json"])
    assert mine["pairs"] == meta["pairs"] and len(mine["pairs"]) >= 1
    assert np.allclose(mine["overlap"], meta["overlap"], atol=0.04)  # at 64 px: 0.012-0.029 apart over seeds 7-10
    for i, j in meta["pairs"]:
        for key in ("corr_12", "corr_21"):
            a = decode_corr(read_npz(engine[f"scene-00000000/pair-{i}-{j}.npz"])[key])
            b = decode_corr(read_npz(ours[f"scene-00000000/pair-{i}-{j}.npz"])[key])
            both = np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
            assert (np.isfinite(a).all(-1) == np.isfinite(b).all(-1)).mean() > 0.999
            assert np.abs(a[both] - b[both]).max() <= 1 / 64


def test_a_scene_with_a_colmap_model_gives_the_same_pairs_as_with_its_transforms_json(tmp_path):
    import shutil
    import tarfile

    import pointmap as pm

    cams, K = make_scene(tmp_path / "ns")
    shutil.copytree(tmp_path / "ns", tmp_path / "cm")
    (tmp_path / "cm" / "transforms.json").unlink()
    depth = np.stack([np.load(tmp_path / "ns" / "depth" / f"f{k}.npy") for k in range(4)])
    recon = pm.Reconstruction(images=torch.zeros(4, H, W, 3), cam2world=torch.tensor(np.stack(cams)),
                              K=torch.tensor(K).repeat(4, 1, 1).float(), depth_z=torch.from_numpy(depth),
                              conf=torch.ones(4, H, W), names=[f"f{k}.png" for k in range(4)])
    recon.save(tmp_path / "cm", formats=("colmap",))  # sparse/0/*.bin, OpenCV world-to-camera, as COLMAP's
    for name in ("ns", "cm"):
        assert main([str(tmp_path / name), "--out", str(tmp_path / f"{name}_out")]) == 0
    metas = []
    for name in ("ns", "cm"):
        with tarfile.open(tmp_path / f"{name}_out" / "shard-000000.tar") as tar:
            metas.append(json.loads(tar.extractfile("scene-00000000/meta.json").read()))
    assert metas[0]["pairs"] == metas[1]["pairs"] and len(metas[0]["pairs"]) >= 3
    for a, b in zip(metas[0]["views"], metas[1]["views"]):
        assert np.allclose(a["K"], b["K"], atol=1e-6) and np.allclose(a["cam2world"], b["cam2world"], atol=1e-5)


def test_pairs_per_view_keeps_each_views_partners_of_largest_overlap():
    from training.prepare import pairs_of

    rng = np.random.default_rng(1)
    ov = rng.uniform(0.2, 0.9, (6, 6))
    np.fill_diagonal(ov, 1)
    every = pairs_of(ov, 0.15, 0.95)
    assert len(every) == 15
    two = pairs_of(ov, 0.15, 0.95, per_view=2)
    score = {p: min(ov[p], ov[p[::-1]]) for p in every}
    for v in range(6):  # each view's two best partners are kept (a brute-force reading of the rule)
        best = sorted((p for p in every if v in p), key=lambda p: -score[p])[:2]
        assert set(best) <= set(two)
    assert len(two) <= 12 and set(two) <= set(every) and two == sorted(two)


def read_shard(path):
    import tarfile

    with tarfile.open(path) as tar:
        return {m.name: tar.extractfile(m).read() for m in tar.getmembers()}


def test_the_stored_correspondences_use_the_depth_tolerance_the_pairs_were_chosen_with(tmp_path):
    from data.geom import decode_corr
    from data.shards import read_npz

    make_scene(tmp_path / "s", depth_noise=0.01)  # a sensor's 1% noise
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out"), "--depth-tol", "0.03"]) == 0
    shard = read_shard(tmp_path / "out" / "shard-000000.tar")
    meta = json.loads(shard["scene-00000000/meta.json"])
    for i, j in meta["pairs"]:
        corr = decode_corr(read_npz(shard[f"scene-00000000/pair-{i}-{j}.npz"])["corr_12"])
        covered = float(np.isfinite(corr).all(-1).mean())  # every pixel has depth on the plane
        assert covered > 0.9 * meta["overlap"][i][j], (i, j, covered, meta["overlap"][i][j])


def test_a_photograph_at_another_resolution_is_stored_at_the_scenes_size_and_another_shape_is_refused(tmp_path,
                                                                                                     capsys):
    from data.shards import read_png

    make_scene(tmp_path / "s", small=(2,))
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out")]) == 0
    shard = read_shard(tmp_path / "out" / "shard-000000.tar")
    meta = json.loads(shard["scene-00000000/meta.json"])
    assert {read_png(shard[f"scene-00000000/view-{k}.png"]).shape for k in range(4)} == {(H, W, 3)}
    assert np.allclose(meta["views"][2]["K"], meta["views"][0]["K"], atol=1e-6)  # upsampled 2x about pixel centres
    ds = PairDataset(tmp_path / "out", size=48, augment=False, split="all")
    for k in range(len(ds)):
        v1, v2 = ds[k]
        assert float(v2["valid"].float().mean()) > 0.99  # no border without depth from a mis-sized crop
    frames = json.loads((tmp_path / "s" / "transforms.json").read_text())
    frames["frames"][1].update(w=W, h=W, cy=W / 2)  # a square photograph among 4:3 ones
    (tmp_path / "s" / "transforms.json").write_text(json.dumps(frames))
    cv2.imwrite(str(tmp_path / "s" / "images" / "f1.png"), np.zeros((W, W, 3), np.uint8))
    np.save(tmp_path / "s" / "depth" / "f1.npy", np.ones((W, W), np.float32))
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out2")]) == 2
    assert "another shape than the scene's first photograph" in capsys.readouterr().out


def test_resized_depth_is_the_depth_under_each_stored_pixel_centre(tmp_path):
    from data.shards import read_npz

    cams, _ = make_scene(tmp_path / "s")
    assert main([str(tmp_path / "s"), "--out", str(tmp_path / "out"), "--max-side", "32"]) == 0  # 96x72 -> 32x24
    shard = read_shard(tmp_path / "out" / "shard-000000.tar")
    meta = json.loads(shard["scene-00000000/meta.json"])
    for k in range(4):
        K = np.array(meta["views"][k]["K"])
        stored = read_npz(shard[f"scene-00000000/view-{k}.npz"])["depth_z"]
        u, v = np.meshgrid(np.arange(32.0), np.arange(24.0))
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        d = rays @ cams[k][:3, :3].T
        o = cams[k][:3, 3]
        truth = (PLANE_Z + SLOPE * o[0] - o[2]) / (d[..., 2] - SLOPE * d[..., 0])
        assert np.median(np.abs(stored / truth - 1)) < 1e-4  # a factor of 3: the centre pixel exactly


def test_a_scene_named_twice_is_refused_in_one_line_rather_than_stored_twice(tmp_path, capsys):
    make_scene(tmp_path / "s")
    # one folder reached by two spellings (a glob and a name): before, 2 scenes and every pair twice were written
    assert main([str(tmp_path / "s"), str(tmp_path / "s") + "/", "--out", str(tmp_path / "out"),
                 "--max-side", "64"]) == 2
    err = capsys.readouterr().err
    assert "the same folder more than once" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()
