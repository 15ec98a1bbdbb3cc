"""Exceptions raised at the library's public boundary.

Every message says what was expected and what was given, so a user can fix the input without
reading the source.
"""

from __future__ import annotations

import numbers
import os


class PointmapError(Exception):
    """Base class of every error this library raises on purpose."""


class ShapeError(PointmapError, ValueError):
    """A tensor or array has the wrong shape, dtype or value range."""


class ConventionError(PointmapError, ValueError):
    """An input breaks a convention of docs/conventions.md (frame, units, ordering)."""


class CheckpointError(PointmapError):
    """A checkpoint is missing, corrupt, foreign, or does not match the architecture."""


class ImageError(PointmapError, ValueError):
    """An image cannot be read or is unusable (too small, not an image, wrong channels)."""


class GraphError(PointmapError, ValueError):
    """A pair graph is unusable (disconnected, too few images, unknown graph name)."""


def is_int(x) -> bool:
    """An integer (Python or NumPy), not a bool: the test every count, size and index argument passes."""
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def is_number(x) -> bool:
    """A real number (Python or NumPy, int or float), not a bool; inf and NaN pass (range checks are the caller's)."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def check_shape(name: str, tensor, expected: tuple, *, hint: str = "") -> None:
    """Raise ShapeError unless ``tensor.shape`` matches ``expected``.

    ``expected`` holds ints (exact), None (any size) or strings (named sizes that must agree
    across the dims sharing a name within this call). Example: ``check_shape("K", K, (None, 3, 3))``.
    A leading ``...`` allows any number of leading dims: ``check_shape("R", R, (..., 3, 3))``.
    """
    if not hasattr(tensor, "shape"):
        raise ShapeError(f"{name} expected an array or tensor {_fmt(expected)}{hint}, got {type(tensor).__name__}")
    shape, fmt = tuple(tensor.shape), _fmt(expected)
    if expected and expected[0] is Ellipsis:  # compare the trailing dims only (too few fail the length test below)
        expected = expected[1:]
        if len(shape) >= len(expected):
            shape = shape[len(shape) - len(expected):]
    if len(shape) != len(expected):
        raise ShapeError(f"{name} expected {fmt}{hint}, got {list(tensor.shape)}")
    named: dict[str, int] = {}
    for size, want in zip(shape, expected):
        if want is None:
            continue
        if isinstance(want, str):
            if named.setdefault(want, size) != size:
                raise ShapeError(f"{name} expected {fmt}{hint}, got {list(tensor.shape)}")
        elif size != want:
            raise ShapeError(f"{name} expected {fmt}{hint}, got {list(tensor.shape)}")


def _fmt(expected: tuple) -> str:
    return "[" + ", ".join("..." if e is Ellipsis else "*" if e is None else str(e) for e in expected) + "]"


def check_device(device, name: str = "device", *, available: bool = True) -> str:
    """A device torch can use here, as a string: ``auto`` (CUDA, then Apple's MPS, then the CPU, whichever torch
    can use first), ``cpu``, ``cuda``, ``cuda:N``, ``mps`` or a ``torch.device``. A name torch does not know, or a
    device this machine does not have, is refused with the way out (PointmapError), before any model or tensor
    moves: torch's own error would come later, from deep inside the first ``.to(device)``.
    ``available=False`` checks the name only and keeps ``auto`` as it is (an ONNX model's device is onnxruntime's
    to find: a CPU-only torch beside onnxruntime-gpu)."""
    import re

    import torch

    if isinstance(device, torch.device):
        device = str(device)
    if not isinstance(device, str):
        raise PointmapError(f"{name} expected a string (auto, cpu, cuda, cuda:N or mps) or a torch.device, got "
                            f"{type(device).__name__}")
    text = {"cpu:0": "cpu", "mps:0": "mps"}.get(device.strip().lower(), device.strip().lower())
    if not (text in ("auto", "cpu", "cuda", "mps") or re.fullmatch(r"cuda:\d+", text)):
        raise PointmapError(f"{name} expected auto, cpu, cuda, cuda:N or mps, got {device!r}")
    if not available:
        return text
    cuda = torch.cuda.device_count() if torch.cuda.is_available() else 0
    mps = getattr(torch.backends, "mps", None)
    has_mps = bool(mps is not None and mps.is_available())
    if text == "auto":
        return "cuda" if cuda else "mps" if has_mps else "cpu"
    if text.startswith("cuda"):
        k = int(text.split(":")[1]) if ":" in text else 0
        if k >= cuda:
            raise PointmapError(f"{name} {device}: torch sees {cuda} CUDA device(s) here"
                                f"{'' if cuda else ' (torch.cuda.is_available() is False)'}; use cpu or auto")
    elif text == "mps" and not has_mps:
        raise PointmapError(f"{name} {device}: torch's MPS backend is not available here; use cpu or auto")
    return text


def check_seed(seed, name: str = "seed") -> int:
    """A random seed: an int from 0 to 2**64 - 1 (what both ``torch.Generator.manual_seed`` and NumPy's
    ``default_rng`` take), refused with a ShapeError otherwise (a float would fail later, inside one of them, with
    its own message, and a negative seed in NumPy's). Returns it as a Python int."""
    if not (is_int(seed) and 0 <= seed < 2 ** 64):
        raise ShapeError(f"{name} expected an int in [0, 2**64), got {seed!r}")
    return int(seed)


def check_model_device(model, device, caller: str) -> str:
    """``device`` checked (``check_device``: a name torch knows, a device this machine has) and, for a torch
    model, the device its weights are on: the model is not moved (``pm.load_model(..., device=)`` puts it there), so
    a mismatch is refused here with the way out instead of failing inside its first layer. Anything but a model (a
    checkpoint's name or path, None) is refused first. Returns the device."""
    import torch

    if not (hasattr(model, "decode_pair") and callable(model)):
        hint = (f" (the name {model!r}: load it first, pm.load_model({model!r}))" if isinstance(model, (str, os.PathLike))
                else "")
        raise CheckpointError(f"{caller} expected a model (pm.load_model's), got {type(model).__name__}{hint}")
    device = check_device(device, f"{caller}: device")
    if isinstance(model, torch.nn.Module):
        p = next(model.parameters(), None)
        want = torch.device(device)
        if want.type == "cuda" and want.index is None:  # "cuda" is the current CUDA device
            want = torch.device("cuda", torch.cuda.current_device())
        if p is not None and (p.device.type != want.type or
                              (want.index is not None and p.device.index not in (None, want.index))):
            raise PointmapError(f"{caller}: the model's weights are on {p.device}, device is {device!r}; load it "
                                f"there (pm.load_model(..., device={device!r}) or model.to({device!r})) or pass "
                                f"device={str(p.device)!r}")
    return device
