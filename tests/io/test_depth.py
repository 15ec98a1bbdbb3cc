import numpy as np
import pytest

from pointmap.errors import PointmapError
from pointmap.io.depth import read_depth


def test_a_float_npy_depth_map_reads_as_saved(tmp_path):
    d = np.random.default_rng(0).random((6, 8)).astype(np.float32)
    np.save(tmp_path / "a.npy", d)
    assert np.array_equal(read_depth(tmp_path / "a.npy"), d)


def test_a_file_that_is_not_npy_is_called_so_and_never_offered_allow_pickle(tmp_path):
    (tmp_path / "text.npy").write_text("0.5 0.5\n0.5 0.5\n")  # a depth map written as text, named .npy
    with pytest.raises(PointmapError, match=r"text.npy: not a .npy file \(NumPy's files begin with") as e:
        read_depth(tmp_path / "text.npy")
    assert "allow_pickle" not in str(e.value) and "pickled" not in str(e.value)
    (tmp_path / "empty.npy").write_bytes(b"")
    with pytest.raises(PointmapError, match="empty.npy: not a .npy file"):
        read_depth(tmp_path / "empty.npy")


def test_an_npy_of_python_objects_is_refused_without_being_unpickled(tmp_path):
    np.save(tmp_path / "obj.npy", np.array([{"depth": 1.0}], dtype=object), allow_pickle=True)
    with pytest.raises(PointmapError, match="obj.npy: holds Python objects, not numbers"):
        read_depth(tmp_path / "obj.npy")
