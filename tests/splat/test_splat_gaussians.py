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
