import numpy as np
import pytest
import torch

from pointmap.errors import ShapeError
from pointmap.splat import Gaussians


def _g(n=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    return Gaussians(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                     log_scales=torch.randn(n, 3, generator=g) - 3,
                     opacity_logits=torch.randn(n, generator=g),
                     sh_dc=torch.randn(n, 3, generator=g))


def test_ply_roundtrip_and_3dgs_layout(tmp_path):
    g = _g()
    path = g.save_ply(tmp_path / "s.ply")
    raw = path.read_bytes()
    header = raw[: raw.index(b"end_header\n")].decode().splitlines()
    props = [line.split()[-1] for line in header if line.startswith("property")]
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert props == expected
    assert "format binary_little_endian 1.0" in header and "element vertex 50" in header
    back = Gaussians.load_ply(path)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc"):
        assert torch.equal(getattr(back, name), getattr(g, name)), name
    assert back.sh_rest is None and back.sh_degree == 0


def test_ply_sh_rest_is_channel_major_and_loading_it_warns_that_it_is_kept_but_not_rendered(tmp_path):
    g = _g(7)
    g.sh_rest = torch.arange(7 * 3 * 3, dtype=torch.float32).reshape(7, 3, 3) + 1
    with pytest.warns(RuntimeWarning, match=r"s.ply: holds view-dependent colour \(SH degree 1\), which pointmap "
                                            r"keeps but does not render or fit"):
        back = Gaussians.load_ply(g.save_ply(tmp_path / "s.ply", sh_degree=None))
    assert torch.equal(back.sh_rest, g.sh_rest)
    # f_rest_{c*K + k} is coefficient k of channel c
    raw = (tmp_path / "s.ply").read_bytes()
    body = np.frombuffer(raw[raw.index(b"end_header\n") + 11:], dtype="<f4").reshape(7, -1)
    assert body[0, 9 + 1] == g.sh_rest[0, 1, 0] and body[0, 9 + 3] == g.sh_rest[0, 0, 1]


def test_activations_and_validation(tmp_path):
    g = Gaussians.from_points(torch.zeros(3, 3), torch.tensor([[0.0, 0.5, 1.0]] * 3), 0.05, opacity=0.1)
    assert torch.allclose(g.colors, torch.tensor([[0.0, 0.5, 1.0]] * 3), atol=1e-6)
    assert torch.allclose(g.opacities, torch.full((3,), 0.1))
    assert torch.allclose(g.scales, torch.full((3, 3), 0.05))
    assert torch.equal(g.quats, torch.tensor([[1.0, 0, 0, 0]] * 3))
    with pytest.raises(ShapeError, match="quats"):
        Gaussians(torch.zeros(3, 3), torch.zeros(2, 4), torch.zeros(3, 3), torch.zeros(3), torch.zeros(3, 3))
    (tmp_path / "bad.ply").write_bytes(b"not a ply")
    with pytest.raises(ShapeError, match="PLY"):
        Gaussians.load_ply(tmp_path / "bad.ply")


@pytest.mark.parametrize("means,sh_rest,message", [
    ([[0.0, 0, 0]] * 3, None, r"means expected a tensor \[N, 3\], got list"),
    (torch.zeros(10), None, r"means expected a tensor \[N, 3\], got \[10\]"),
    (torch.zeros(3, 3), torch.zeros(3, 4, 3), r"sh_rest expected .*3, 8 or 15 .*got \[3, 4, 3\]"),
    (torch.zeros(3, 3), torch.zeros(3, 16, 3), r"sh_rest expected .*got \[3, 16, 3\]"),
    (torch.zeros(3, 3), np.zeros((3, 3, 3)), r"sh_rest expected a tensor .*got ndarray"),
])
def test_gaussians_of_the_wrong_kind_or_an_sh_size_of_no_degree_are_refused_when_made(means, sh_rest, message):
    with pytest.raises(ShapeError, match=message):  # save_ply crashed on them inside torch, or wrote a bad file
        Gaussians(means, torch.zeros(3, 4), torch.zeros(3, 3), torch.zeros(3), torch.zeros(3, 3), sh_rest=sh_rest)


def test_orbit_and_png_writers_leave_only_finished_files(tmp_path):

    from pointmap.splat.outputs import save_orbit, save_png

    frame = torch.rand(8, 10, 3)
    gif = save_orbit([frame, frame.flip(0)], tmp_path / "o.gif", fps=4)
    png = save_png(frame, tmp_path / "f.png")
    with pytest.raises(ShapeError, match="at least one frame"):
        save_orbit([], tmp_path / "empty.gif")
    with pytest.raises(ShapeError, match=".gif or .mp4"):
        save_orbit([frame], tmp_path / "o.avi")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.png", "o.gif"]
    from PIL import Image

    assert Image.open(gif).n_frames == 2 and Image.open(png).size == (10, 8)


def test_a_truncated_3dgs_ply_and_unusable_points_are_refused_naming_what_is_wrong(tmp_path):
    path = _g().save_ply(tmp_path / "s.ply")
    raw = path.read_bytes()
    (tmp_path / "cut.ply").write_bytes(raw[:-10])
    with pytest.raises(ShapeError, match="cut.ply: truncated: 50 Gaussians"):
        Gaussians.load_ply(tmp_path / "cut.ply")
    end = raw.index(b"end_header\n")
    header, body = raw[:end].decode(), raw[end:]
    commented = header.replace("ply\n", "ply\ncomment scène capturée\n", 1).encode() + body
    (tmp_path / "utf8.ply").write_bytes(commented)  # a non-ASCII comment, as apps write them
    assert len(Gaussians.load_ply(tmp_path / "utf8.ply")) == 50
    for name, text, message in (("abc.ply", header.replace("element vertex 50", "element vertex abc"),
                                 "'element vertex' expected a count, got 'element vertex abc'"),
                                ("zero.ply", header.replace("element vertex 50", "element vertex 0"),
                                 "holds no Gaussian \\(0 vertices\\)")):
        (tmp_path / name).write_bytes(text.encode() + body)
        with pytest.raises(ShapeError, match=message):
            Gaussians.load_ply(tmp_path / name)
    nan = bytearray(raw)
    nan[end + len(b"end_header\n"): end + len(b"end_header\n") + 4] = np.float32(np.nan).tobytes()
    (tmp_path / "nan.ply").write_bytes(bytes(nan))
    with pytest.raises(ShapeError, match="1 of 50 Gaussians hold NaN or inf values"):
        Gaussians.load_ply(tmp_path / "nan.ply")
    pts, rgb = torch.zeros(3, 3), torch.full((3, 3), 0.5)
    with pytest.raises(ShapeError, match="points expected finite \\[N, 3\\], got \\[3, 3\\] with NaN or inf"):
        Gaussians.from_points(torch.full((3, 3), float("nan")), rgb, 0.05)
    with pytest.raises(ShapeError, match="rgb expected \\[3, 3\\] colours in \\[0, 1\\]"):
        Gaussians.from_points(pts, rgb * 4, 0.05)
    with pytest.raises(ShapeError, match="scale expected a finite standard deviation >= 0"):
        Gaussians.from_points(pts, rgb, -0.05)


def test_nan_confidences_are_refused_and_save_ply_refuses_gaussians_load_ply_would_refuse(tmp_path):
    pts, rgb = torch.zeros(3, 3), torch.full((3, 3), 0.5)
    g = Gaussians.from_points(pts, rgb, 0.05, conf=[1.0, 2.0, 3.0])
    assert torch.equal(g.conf, torch.tensor([1.0, 2.0, 3.0]))
    # a NaN confidence made the fit's per-point rate multiplier NaN: every Gaussian came out NaN
    with pytest.raises(ShapeError, match=r"Gaussians.conf expected finite confidences \[3\] .*got 1 NaN or inf"):
        Gaussians.from_points(pts, rgb, 0.05, conf=torch.tensor([1.0, float("nan"), 3.0]))
    with pytest.raises(ShapeError, match=r"Gaussians.conf expected finite confidences \[3\] .*got \[2\]"):
        Gaussians.from_points(pts, rgb, 0.05, conf=torch.ones(2))
    bad = _g(4)
    bad.means[2, 0] = float("inf")
    with pytest.raises(ShapeError, match=r"save_ply expected finite Gaussians, got 1 of 4 with NaN or inf values"):
        bad.save_ply(tmp_path / "bad.ply")
    assert not (tmp_path / "bad.ply").exists()
    with pytest.raises(ShapeError, match=r"save_ply expected at least one Gaussian, got 0: .*none.ply not written"):
        _g(0).save_ply(tmp_path / "none.ply")
    assert not (tmp_path / "none.ply").exists()


def _ply(path, props, n=4, before="", data=None):
    header = ("ply\nformat binary_little_endian 1.0\n" + before + f"element vertex {n}\n"
              + "".join(line if line.startswith("property") else f"property float {line}\n" for line in props)
              + "end_header\n")
    count = sum(1 for line in props if line.startswith("property") or " " not in line)
    body = np.arange(n * count, dtype="<f4").tobytes() if data is None else data
    path.write_bytes(header.encode() + body)
    return path


NEED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3"]


def test_load_ply_refuses_an_element_before_the_vertices_and_malformed_f_rest_or_property_lines(tmp_path):
    # an element before the vertices: its data comes first, and the vertices were read shifted by it
    path = _ply(tmp_path / "pre.ply", NEED, before="element camera 1\nproperty float fx\n",
                data=np.float32(7.0).tobytes() + np.ones((4, 14), "<f4").tobytes())
    with pytest.raises(ShapeError, match="pre.ply: expected the vertex element first .*got 'element camera 1'"):
        Gaussians.load_ply(path)
    # f_rest sets that are no SH degree, or not f_rest_0.. in order (a KeyError and a reshape error before)
    for name, rest, got in (("two", ["f_rest_0", "f_rest_1"], "got 2"), ("gap", ["f_rest_1"], "got 1"),
                            ("skip", [f"f_rest_{i}" for i in range(10) if i != 4], "got 9")):
        with pytest.raises(ShapeError, match=f"{name}.ply: f_rest properties expected f_rest_0 .. f_rest_{{3K - 1}} "
                                             f".*{got}"):
            Gaussians.load_ply(_ply(tmp_path / f"{name}.ply", NEED[:6] + rest + NEED[6:]))
    # a property line without a name (an IndexError before), or of a list
    for name, line in (("short", "property float\n"), ("list", "property list uchar int idx\n")):
        with pytest.raises(ShapeError, match=f"{name}.ply: vertex properties expected 'property float NAME', got "
                                             f"'{line.strip()}'"):
            Gaussians.load_ply(_ply(tmp_path / f"{name}.ply", NEED + [line]))
    # what 3DGS writes still loads: degree 1 (9 f_rest), the vertex element first, another one after it
    nine = [f"f_rest_{i}" for i in range(9)]
    with pytest.warns(RuntimeWarning, match="SH degree 1"):
        g = Gaussians.load_ply(_ply(tmp_path / "ok.ply", NEED[:6] + nine + NEED[6:]))
    assert g.sh_rest.shape == (4, 3, 3) and g.means[1].tolist() == [23.0, 24.0, 25.0]


def test_interpolate_pose_halfway_through_a_half_turn_is_a_quarter_turn_about_its_axis():
    import math

    from pointmap.geometry.rotations import axis_angle_to_matrix, rotation_angle
    from pointmap.splat.outputs import interpolate_pose

    a = torch.eye(4, dtype=torch.float64)
    a[:3, 3] = torch.tensor([1.0, 0.0, 0.0])
    for w in ([0.0, math.pi, 0.0], [0.3, -0.2, 0.9], [2.0, 1.0, 0.5]):
        w = torch.tensor(w, dtype=torch.float64)
        b = torch.eye(4, dtype=torch.float64)
        b[:3, :3] = axis_angle_to_matrix(w)
        b[:3, 3] = torch.tensor([3.0, 2.0, 0.0])
        for t in (0.25, 0.5):
            m = interpolate_pose(a, b, t)
            # the half turn about y gave camera A back (the identity): its axis-angle came out zero. It has two
            # shortest arcs, about +y and -y: either will do
            arcs = (w, -w) if abs(float(w.norm()) - math.pi) < 1e-12 else (w,)
            assert any(torch.allclose(m[:3, :3], axis_angle_to_matrix(v * t), atol=1e-9) for v in arcs), (w, t)
            assert torch.allclose(m[:3, 3], torch.tensor([1.0 + 2 * t, 2 * t, 0.0], dtype=torch.float64))
        assert float(rotation_angle(interpolate_pose(a, b, 0.5)[:3, :3])) == pytest.approx(float(w.norm()) / 2)
    assert torch.allclose(interpolate_pose(a, b, 1.0), b, atol=1e-12) and torch.equal(interpolate_pose(a, b, 0.0), a)
