"""The shared argument tests of pointmap.errors: what counts as an int or a number, and trailing-shape checks."""

import numpy as np
import pytest
import torch

from pointmap.errors import ShapeError, check_shape, is_int, is_number


def test_an_int_is_a_python_or_numpy_integer_and_never_a_bool_or_a_float():
    assert is_int(3) and is_int(np.int64(3)) and is_int(np.uint8(0)) and is_int(-1)
    assert not any(is_int(x) for x in (True, False, np.bool_(True), 3.0, "3", None, torch.tensor(3)))


def test_a_number_is_any_real_but_a_bool_and_leaves_range_checks_to_the_caller():
    assert all(is_number(x) for x in (3, 2.5, np.float32(0.5), np.int16(-2), float("inf"), float("nan")))
    assert not any(is_number(x) for x in (True, np.bool_(False), "1.0", None, 1j))


def test_check_shape_with_a_leading_ellipsis_checks_only_the_trailing_dims():
    check_shape("R", torch.zeros(3, 3), (..., 3, 3))
    check_shape("R", np.zeros((2, 5, 3, 3)), (..., 3, 3))
    with pytest.raises(ShapeError, match=r"R expected \[\.\.\., 3, 3\], got \[2, 3, 4\]"):
        check_shape("R", torch.zeros(2, 3, 4), (..., 3, 3))
    with pytest.raises(ShapeError, match=r"R expected \[\.\.\., 3, 3\], got \[3\]"):
        check_shape("R", torch.zeros(3), (..., 3, 3))
    with pytest.raises(ShapeError, match=r"R expected an array or tensor \[\.\.\., 3, 3\], got list"):
        check_shape("R", [[1.0]], (..., 3, 3))
    with pytest.raises(ShapeError, match=r"K expected \[\*, 3, 3\], got \[3, 3\]"):  # fixed rank as before
        check_shape("K", torch.zeros(3, 3), (None, 3, 3))


def test_check_device_takes_names_and_torch_devices_and_refuses_what_this_machine_lacks(monkeypatch):
    from pointmap.errors import PointmapError, check_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    assert check_device("cpu") == "cpu" and check_device(torch.device("cpu")) == "cpu" and check_device("auto") == "cpu"
    assert check_device("cpu:0") == "cpu" and check_device(torch.device("cpu", 0)) == "cpu"
    # the name alone (an ONNX model: onnxruntime finds its GPU, whatever torch was built with); auto kept
    assert check_device("cuda:1", available=False) == "cuda:1" and check_device("auto", available=False) == "auto"
    with pytest.raises(PointmapError, match="got 'gpu'"):
        check_device("gpu", available=False)
    for bad, message in [("gpu", "device expected auto, cpu, cuda, cuda:N or mps, got 'gpu'"),
                         (torch.device("cuda:0"), "torch sees 0 CUDA device"), ("mps", "MPS backend is not available"),
                         (0, "device expected a string .* or a torch.device, got int"), (None, "got NoneType")]:
        with pytest.raises(PointmapError, match=message):
            check_device(bad)


def test_a_seed_is_an_int_both_torch_and_numpy_generators_take():
    from pointmap.errors import check_seed

    assert check_seed(0) == 0 and check_seed(np.int64(7)) == 7 and type(check_seed(np.uint32(7))) is int
    assert check_seed(2 ** 64 - 1) == 2 ** 64 - 1
    for bad in (-1, 2 ** 64, 1.0, True, "3", None):
        with pytest.raises(ShapeError, match="seed expected an int in"):
            check_seed(bad)
