from pathlib import Path

import pointmap

SHIPPED = Path(pointmap.__file__).parent / "demo_scenes"


def test_the_demo_scenes_command_renders_the_shipped_scenes_again_byte_for_byte(tmp_path):
    from data.demo_scenes import render_demo

    render_demo(tmp_path)
    shipped = sorted(p.relative_to(SHIPPED) for p in SHIPPED.rglob("*") if p.is_file())
    assert shipped and sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file()) == shipped
    for name in shipped:
        assert (tmp_path / name).read_bytes() == (SHIPPED / name).read_bytes(), name
