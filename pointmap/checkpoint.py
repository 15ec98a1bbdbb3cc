"""Loading and saving models: official DUSt3R/MASt3R ``.pth`` files, our safetensors format, shipped presets.

Nothing here executes code from a file: official checkpoints are read with
``torch.load(weights_only=True)`` (``argparse.Namespace`` allow-listed) and their constructor string is
parsed with a whitelist over Python's syntax tree, never evaluated.
"""

from __future__ import annotations

import argparse
import ast
import json
import math
import os
import re
import warnings
from pathlib import Path

import numpy as np
import torch

from pointmap.atomic import atomic_path
from pointmap.cache import tensors_checksum
from pointmap.errors import CheckpointError, ShapeError, check_device, is_int
from pointmap.model.config import PRESETS, ModelConfig
from pointmap.model.net import PointmapNet

WEIGHTS_DIR = Path(__file__).parent / "weights"
# NAVER's DUSt3R / MASt3R / CroCo checkpoints: non-commercial. A model's ``provenance["licence"]`` (an SPDX id) is
# its weights' licence; fine-tuning, averaging and export carry it on (training.train, training.ship, export).
OFFICIAL_LICENCE = "CC-BY-NC-SA-4.0"
FORMAT = "pointmap/1"
HEAD_PREFIXES = ("downstream_head", "pose_head", "focal_head", "desc_stem")  # everything else is the trunk (encoder, decoders)

# --------------------------------------------------------------------------------------------------
# constructor strings: AsymmetricCroCo3DStereo(pos_embed='RoPE100', img_size=(512, 512), ...)


def parse_ctor(text: str) -> tuple[str, dict]:
    """Parse ``Name(key=value, ...)`` with values made of numbers, strings, booleans, None, ``inf``,
    tuples and lists. Anything else (calls inside values, attributes, operators) is refused."""
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as e:
        raise CheckpointError(f"cannot parse the architecture string {text[:120]!r}: {e.msg}") from None
    call = tree.body
    if not isinstance(call, ast.Call) or not isinstance(call.func, ast.Name) or call.args:
        raise CheckpointError(f"architecture string must be Name(key=value, ...), got {text[:120]!r}")
    kwargs = {}
    for kw in call.keywords:
        if kw.arg is None:
            raise CheckpointError(f"'**' is not allowed in the architecture string {text[:120]!r}")
        if kw.arg in kwargs:  # Python refuses a repeated keyword too: a corrupt string, not the last one wins
            raise CheckpointError(f"the architecture string names {kw.arg!r} twice: {text[:120]!r}")
        kwargs[kw.arg] = _literal(kw.value, text)
    return call.func.id, kwargs


def _literal(node, text):
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float, str, bool, type(None))):
        return node.value
    if isinstance(node, ast.Name) and node.id in ("inf", "nan"):
        return math.inf if node.id == "inf" else math.nan
    if isinstance(node, ast.Name) and node.id in ("True", "False", "None"):
        return {"True": True, "False": False, "None": None}[node.id]
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        v = _literal(node.operand, text)
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            raise CheckpointError(f"unary sign on a non-number in {text[:120]!r}")
        return -v if isinstance(node.op, ast.USub) else v
    if isinstance(node, (ast.Tuple, ast.List)):
        return tuple(_literal(e, text) for e in node.elts)
    raise CheckpointError(f"unsupported value {ast.dump(node)[:80]} in the architecture string {text[:120]!r}")


_CROCO_DEFAULTS = dict(enc_embed_dim=768, enc_depth=12, enc_num_heads=12, dec_embed_dim=512, dec_depth=8,
                       dec_num_heads=16, mlp_ratio=4, patch_size=16, pos_embed="cosine", norm_im2_in_dec=True)
_KNOWN_CLASSES = ("AsymmetricCroCo3DStereo", "AsymmetricMASt3R", "CroCoNet")
_IGNORED_KWARGS = {"img_size", "patch_embed_cls", "landscape_only", "freeze", "desc_mode", "mask_ratio",
                   "norm_layer", "enc_pos_embed", "dec_pos_embed"}


class HeadlessCheckpointError(CheckpointError):
    """A pretraining checkpoint (CroCo's: encoder and decoder) loaded as a model: it has no prediction heads."""


def _official_sizes(a: dict, pos: str, head: str, desc_dim: int, conf_mode: tuple, desc_conf, name: str) -> dict:
    """The ModelConfig fields of an official constructor's arguments ``a`` (popped from it); KeyError, TypeError or
    ValueError for missing or malformed ones (``config_from_ctor`` turns them into CheckpointError)."""
    def whole(key):  # an integer as written (int() would truncate 2.7 and take True as 1)
        v = a.pop(key)
        if not is_int(v):
            raise ValueError(f"{key} expected an integer, got {v!r}")
        return v

    two_confs = a.pop("two_confs", False)
    if not isinstance(two_confs, bool):  # bool('no') is True
        raise ValueError(f"two_confs expected True or False, got {two_confs!r}")
    return dict(
        enc_dim=whole("enc_embed_dim"), enc_depth=whole("enc_depth"), enc_heads=whole("enc_num_heads"),
        dec_dim=whole("dec_embed_dim"), dec_depth=whole("dec_depth"), dec_heads=whole("dec_num_heads"),
        mlp_ratio=float(a.pop("mlp_ratio")), patch_size=whole("patch_size"), rope_base=float(pos[4:] or 100),
        head=head, desc_dim=desc_dim, two_confs=two_confs,
        depth_mode=tuple(a.pop("depth_mode", ("exp", -math.inf, math.inf))), conf_mode=conf_mode,
        desc_conf_mode=tuple(desc_conf) if desc_conf is not None else conf_mode,
        metric=name == "AsymmetricMASt3R",
    )


def config_from_ctor(text: str) -> ModelConfig:
    """ModelConfig from an official constructor string (see anchors-spec 1.8)."""
    name, kw = parse_ctor(text)
    if name not in _KNOWN_CLASSES:
        raise CheckpointError(f"unknown architecture {name!r}: expected one of {_KNOWN_CLASSES}")
    a = {**_CROCO_DEFAULTS, **kw}
    pos = str(a.pop("pos_embed"))
    if not pos.startswith("RoPE"):
        raise CheckpointError(f"pos_embed={pos!r} is not supported (only RoPE models, e.g. 'RoPE100')")
    if not a.pop("norm_im2_in_dec"):
        raise CheckpointError("norm_im2_in_dec=False is not supported")
    head = a.pop("head_type", "linear")
    output_mode = str(a.pop("output_mode", "pts3d"))
    desc_dim = 0
    if output_mode.startswith("pts3d+desc"):
        tail = output_mode[len("pts3d+desc"):]
        if not tail.isdigit():
            raise CheckpointError(f"output_mode={output_mode!r}: expected pts3d+descN with N a number")
        desc_dim = int(tail)
    elif output_mode != "pts3d":
        raise CheckpointError(f"output_mode={output_mode!r} is not supported (pts3d or pts3d+descN)")
    if head == "catmlp+dpt" and not desc_dim:
        raise CheckpointError("head_type 'catmlp+dpt' needs output_mode 'pts3d+descN'")
    if name == "CroCoNet":
        head = "linear"
    if a.get("desc_mode", "norm") != "norm":
        raise CheckpointError(f"desc_mode={a['desc_mode']!r} is not supported (only 'norm')")
    try:
        conf_mode = tuple(a.pop("conf_mode", ("exp", 1, math.inf)))
        desc_conf = a.pop("desc_conf_mode", None)
        cfg = _official_sizes(a, pos, head, desc_dim, conf_mode, desc_conf, name)
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{name} constructor arguments are missing or malformed ({e.__class__.__name__}: "
                              f"{e})") from None
    unknown = set(a) - _IGNORED_KWARGS
    if unknown:
        raise CheckpointError(f"unsupported constructor arguments in {name}: {sorted(unknown)}")
    if cfg["depth_mode"][1:] != (-math.inf, math.inf):
        raise CheckpointError(f"depth_mode with bounds is not supported, got {cfg['depth_mode']}")
    if cfg["patch_size"] != 16:
        raise CheckpointError(f"patch_size={cfg['patch_size']} is not supported (16)")
    return ModelConfig(**cfg)


# --------------------------------------------------------------------------------------------------
# state dicts


def official_to_ours(state: dict, *, allow_missing_heads: bool = False) -> dict:
    """Map an official state dict onto PointmapNet's keys (the one place that knows official names).

    Our keys equal the official ones except: DPT ``scratch.layer_rn.K`` aliases are folded into
    ``scratch.layer{K+1}_rn``; ``mask_token``, ``prediction_head.*`` and sin-cos position buffers (CroCo
    pretraining) are dropped; a missing ``dec_blocks2`` (CroCo) is copied from ``dec_blocks``.
    """
    out = {}
    plain = {(k[len("module."):] if k.startswith("module.") else k): v for k, v in state.items()}  # DDP-saved
    for k, v in state.items():
        if k.startswith("module."):
            k = k[len("module."):]
        if k in ("mask_token", "enc_pos_embed", "dec_pos_embed") or k.startswith("prediction_head."):
            continue
        if ".scratch.layer_rn." in k:
            parsed = re.fullmatch(r"(.+)\.scratch\.layer_rn\.(\d+)\.(.+)", k)
            if parsed is None:
                raise CheckpointError(f"unexpected key {k!r}: a scratch.layer_rn alias expected "
                                      f"'<head>.scratch.layer_rn.<int>.<name>' (a corrupt or foreign checkpoint?)")
            head, idx, tail = parsed.groups()
            alias = f"{head}.scratch.layer{int(idx) + 1}_rn.{tail}"
            if alias in plain and not torch.equal(plain[alias], v):  # (a "module." prefix hid it from this check)
                raise CheckpointError(f"{k} and its alias {alias} hold different values")
            out.setdefault(alias, v)
            continue
        out[k] = v
    if not any(k.startswith("dec_blocks2.") for k in out):
        for k, v in list(out.items()):
            if k.startswith("dec_blocks."):
                out["dec_blocks2." + k[len("dec_blocks."):]] = v
    return out


def built_for(cfg: ModelConfig, state: dict, *, allow_missing_heads: bool = False,
              source: str = "checkpoint") -> PointmapNet:
    """A PointmapNet of ``cfg`` holding ``state`` (``load_state_strict``), the state first checked against the
    architecture built on the meta device: a foreign or corrupt config (a huge size) is a CheckpointError naming
    the mismatch, not gigabytes allocated and then a raw allocator error."""
    import re

    for prefix, depth in (("enc_blocks", cfg.enc_depth), ("dec_blocks", cfg.dec_depth)):  # before building them
        found = {m.group(1) for k in state if (m := re.match(rf"{prefix}\.(\d+)\.", k))}
        if len(found) != depth:
            raise CheckpointError(f"{source} does not match the architecture: its config says {depth} {prefix}, its "
                                  f"weights hold {len(found)}")
    try:
        with torch.device("meta"):
            own = PointmapNet(cfg).state_dict()
    except (RuntimeError, TypeError, ValueError, OverflowError) as e:  # e.g. a size too large to index
        raise CheckpointError(f"{source}: its config builds no model ({e.__class__.__name__}: {e}); a foreign or "
                              "corrupt config") from None
    _check_fits(own, state, allow_missing_heads, source)
    model = PointmapNet(cfg)
    model.load_state_dict(state, strict=not allow_missing_heads)  # checked above: the real model has its keys
    return model


def load_state_strict(model: PointmapNet, state: dict, *, allow_missing_heads: bool = False,
                      source: str = "checkpoint") -> None:
    """load_state_dict that lists every missing/unexpected key and shape mismatch in one CheckpointError."""
    _check_fits(model.state_dict(), state, allow_missing_heads, source)
    model.load_state_dict(state, strict=not allow_missing_heads)


def _check_fits(own: dict, state: dict, allow_missing_heads: bool, source: str) -> None:
    """CheckpointError listing every missing / unexpected key and shape mismatch of ``state`` against ``own``."""
    missing = [k for k in own if k not in state]
    if allow_missing_heads:
        missing = [k for k in missing if not k.startswith(HEAD_PREFIXES)]
    unexpected = [k for k in state if k not in own]
    shapes = [f"{k}: checkpoint {tuple(state[k].shape)} vs model {tuple(own[k].shape)}"
              for k in state if k in own and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or shapes:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing keys (e.g. {missing[:4]})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected keys (e.g. {unexpected[:4]})")
        if shapes:
            parts.append(f"{len(shapes)} shape mismatches (e.g. {shapes[:3]})")
        raise CheckpointError(f"{source} does not match the architecture: " + "; ".join(parts))


def load_trunk(model: PointmapNet, state: dict, *, source: str = "checkpoint") -> list[str]:
    """Load the encoder and decoders strictly and each head tensor whose name and shape match.

    For fine-tuning into a different head (e.g. a DUSt3R checkpoint into a model with a descriptor head, as
    MASt3R was trained, or a head resized): every trunk tensor must be present with its shape, else a
    CheckpointError lists the problems. Returns the head tensors left at their fresh initialisation.
    """
    own = model.state_dict()
    had_pose = any(k.startswith("pose_head.") for k in state)
    if had_pose and model.pose_head is None:
        raise CheckpointError(f"{source} has a pose head (its view-2 head predicts in view 2's own frame); the model "
                              "has none and would read that head's output as view-1 points: build it with a pose head")

    def is_head(k: str) -> bool:
        return k.startswith(HEAD_PREFIXES)

    missing = [k for k in own if not is_head(k) and k not in state]
    shapes = [f"{k}: checkpoint {tuple(state[k].shape)} vs model {tuple(own[k].shape)}"
              for k in own if not is_head(k) and k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    # blocks beyond the model's depth (a deeper, e.g. grown, checkpoint): taking the first ones would cut it silently
    deeper = sorted({k.split(".")[0] + "." + k.split(".")[1] for k in state
                     if k.startswith(("enc_blocks.", "dec_blocks.", "dec_blocks2.")) and k not in own})
    if missing or shapes or deeper:
        parts = [f"{len(missing)} missing trunk keys (e.g. {missing[:4]})"] if missing else []
        if shapes:
            parts.append(f"{len(shapes)} trunk shape mismatches (e.g. {shapes[:3]})")
        if deeper:
            parts.append(f"{len(deeper)} blocks the model does not have (e.g. {deeper[:3]}: a deeper checkpoint)")
        raise CheckpointError(f"{source}: its encoder/decoder do not match the architecture: " + "; ".join(parts))
    take = {k: v for k, v in state.items() if k in own and tuple(v.shape) == tuple(own[k].shape)}
    model.load_state_dict(take, strict=False)
    return sorted(k for k in own if k not in take)


def _torch_load(path: Path):
    with open(path, "rb") as f:
        head = f.read(8)
    if not (head.startswith(b"PK\x03\x04") or head[:1] == b"\x80"):  # torch.save writes a zip (or, before 1.6, a pickle)
        raise CheckpointError(f"cannot read {path} as a checkpoint: not a PyTorch file (a .pth is a zip or pickle "
                              f"file; this one starts with {head!r}); load_model reads .pth, .safetensors, ONNX "
                              "exports and shipped names")
    try:
        with torch.serialization.safe_globals([argparse.Namespace]):
            return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - every failure becomes one clear message
        text = str(e)
        if "Unsupported global" in text:
            what = text.split("Unsupported global:")[1].split("was not")[0].strip()
            raise CheckpointError(f"refused to load {path}: it needs arbitrary pickled code ({what}); only "
                                  f"tensors, plain data and argparse.Namespace are accepted") from None
        detail = next((ln.strip() for ln in text.splitlines() if "error" in ln.lower() or "unsupported" in ln.lower()
                       or "magic" in ln.lower() or "zip" in ln.lower()), text.split("\n")[0])[:160]
        raise CheckpointError(f"cannot read {path} as a checkpoint (corrupt, truncated or not a checkpoint): "
                              f"{detail}") from None


def check_state(state, path) -> None:
    """CheckpointError unless ``state`` is a dict of named tensors whose floating ones are all finite (NaN or inf
    weights would make every prediction NaN)."""
    if not isinstance(state, dict) or not all(isinstance(k, str) and torch.is_tensor(v) for k, v in state.items()):
        what = type(state).__name__ if not isinstance(state, dict) else next(
            f"{k!r}: {type(v).__name__}" for k, v in state.items() if not (isinstance(k, str) and torch.is_tensor(v)))
        raise CheckpointError(f"{path}: its weights expected a dict of named tensors, got {what}")
    bad = [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise CheckpointError(f"{path} holds NaN or inf weights (e.g. {bad[:3]}): every prediction would be NaN")


def load_official(path: Path, *, allow_missing_heads: bool = False) -> PointmapNet:
    ckpt = _torch_load(path)
    if isinstance(ckpt, dict) and {"model", "model_config", "step"} <= set(ckpt):
        way = (f"make one with `python -m training.ship --ckpt {path} --out model.safetensors`"
               if ckpt.get("kind") in (None, "train") else
               f"a {ckpt.get('kind')!r} run's: start pointmap training from it with `python -m training.train --init {path}`")
        raise CheckpointError(f"{path} is a pointmap training checkpoint (weights with optimizer state), not a model "
                              f"file: {way}")
    if not isinstance(ckpt, dict) or "model" not in ckpt:
        raise CheckpointError(f"{path} is not a DUSt3R/MASt3R checkpoint: expected a dict with 'model' and 'args'")
    check_state(ckpt["model"], path)
    args = ckpt.get("args")
    ctor = getattr(args, "model", None) if args is not None else None
    if ctor is None and isinstance(ckpt.get("croco_kwargs"), dict):
        ctor = "CroCoNet(" + ", ".join(f"{k}={v!r}" for k, v in ckpt["croco_kwargs"].items()) + ")"
    if not isinstance(ctor, str):
        raise CheckpointError(f"{path} has no architecture string (args.model)")
    cfg = config_from_ctor(ctor)
    if "CroCoNet" not in ctor and not any(k.startswith(("dec_blocks2.", "module.dec_blocks2.")) for k in ckpt["model"]):
        # official_to_ours copies the first decoder into the second only for CroCo, which has one: a DUSt3R / MASt3R
        # state without its second decoder is corrupt or foreign, and would run with view 2 decoded as view 1
        raise CheckpointError(f"{path} has no second decoder (dec_blocks2.*), which {parse_ctor(ctor)[0]} has: a "
                              "corrupt or foreign checkpoint")
    if "CroCoNet" in ctor and not allow_missing_heads:
        raise HeadlessCheckpointError(f"{path} is a CroCo pretraining checkpoint (encoder and decoder, no prediction heads): "
                              "loaded as a model its heads would be random. Start training from it (python -m "
                              "training.train --init PATH), or load_official(path, allow_missing_heads=True)")
    model = built_for(cfg, official_to_ours(ckpt["model"]), allow_missing_heads=allow_missing_heads, source=str(path))
    model.provenance = {"source": "official", "path": str(path), "ctor": ctor, "licence": OFFICIAL_LICENCE}
    warn_if_noncommercial(model, path, "official NAVER weights")
    img_size = parse_ctor(ctor)[1].get("img_size")
    if isinstance(img_size, int) or (isinstance(img_size, tuple) and img_size and
                                     all(isinstance(x, int) for x in img_size)):
        model.provenance["image_size"] = max(img_size) if isinstance(img_size, tuple) else img_size
    return model


def model_licence(model) -> str | None:
    """The licence its provenance records for ``model``'s weights (an SPDX id, e.g. ``OFFICIAL_LICENCE`` for an
    official checkpoint and what it was fine-tuned into), None where it records none."""
    prov = getattr(model, "provenance", None)
    lic = prov.get("licence") if isinstance(prov, dict) else None
    return lic if isinstance(lic, str) and lic else None


def provenance_keeping_licence(model, provenance=None) -> dict:
    """What a file written from ``model`` records as its provenance: ``provenance`` if given, else the model's own;
    either way with the licence the model's weights carry (``model_licence``) when the given one names none, so
    that a caller's provenance cannot drop a non-commercial licence. ShapeError for a provenance that is not a
    dict, holds what JSON cannot take (numpy values, tensors and paths become JSON's; ``provenance_json_value``), or
    that ``load_model`` would refuse (``provenance_ok``: an image_size that is not a positive int)."""
    prov = (getattr(model, "provenance", None) or {}) if provenance is None else provenance
    if not isinstance(prov, dict):
        raise ShapeError(f"provenance expected a dict, got {type(prov).__name__}")
    lic = model_licence(model)
    prov = {**prov, "licence": lic} if lic and not prov.get("licence") else dict(prov)
    prov = json.loads(json.dumps(prov, default=provenance_json_value))
    if not provenance_ok(prov):  # what load_model (or an export's loader) would refuse is not written
        raise ShapeError(f"provenance's image_size expected a positive int (the training input size), got "
                         f"{prov.get('image_size')!r}")
    return prov


def warn_if_noncommercial(model, path, what: str) -> None:
    """A UserWarning when ``model``'s recorded licence is a non-commercial one (an ``-NC`` SPDX id)."""
    lic = model_licence(model)
    if lic is not None and "-NC" in lic.upper():
        warnings.warn(f"{path}: {what} are licensed {lic} (non-commercial use only); models fine-tuned or averaged "
                      "from them and their exports carry that licence", UserWarning, stacklevel=4)


def model_input_size(model, default: int = 512) -> int:
    """The input size a model was trained at (its provenance's ``image_size``: our checkpoints record it, an
    official one's ``img_size`` gives it), else ``default``."""
    size = (getattr(model, "provenance", None) or {}).get("image_size")
    return int(size) if size else default


# --------------------------------------------------------------------------------------------------
# our format: one .safetensors file, the config and provenance as JSON in its metadata


INT8_MIN_NUMEL = 4096  # smaller tensors (biases, norms, tiny kernels) stay fp16 in an int8 file
SCALE_SUFFIX = ":int8_scale"


def quantize_int8(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetric int8 with one scale per slice along the first dimension (a Linear's or Conv2d's output
    channel): (q [same shape, int8], scale [w.shape[0]] fp32) with w ~= q * scale, each slice's largest
    magnitude mapped to 127 (the error per weight is at most scale / 2). ValueError for a tensor that is not
    floating point, has no dimension or no entries, or holds NaN or inf."""
    if not torch.is_tensor(w) or not w.is_floating_point() or w.ndim < 1 or w.numel() == 0:
        raise ValueError(f"quantize_int8 expected a non-empty floating tensor with at least one dimension, got "
                         f"{type(w).__name__} {getattr(w, 'dtype', '')} {tuple(getattr(w, 'shape', ()))}")
    flat = w.detach().float().reshape(w.shape[0], -1)
    if not torch.isfinite(flat).all():
        raise ValueError(f"quantize_int8 expected finite weights, got {int((~torch.isfinite(flat)).sum())} NaN/inf")
    scale = flat.abs().amax(dim=1).clamp_min(1e-12) / 127.0
    q = torch.round(flat / scale[:, None]).clamp_(-127, 127).to(torch.int8)
    return q.reshape(w.shape), scale


def dequantize_int8(q: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """The fp32 weights ``q * scale`` of ``quantize_int8``'s output (one scale per slice along dim 0).
    ValueError unless q is int8 with at least one dimension and scale is a finite positive fp32 [q.shape[0]]."""
    if not (torch.is_tensor(q) and q.dtype == torch.int8 and q.ndim >= 1 and q.numel() > 0):
        raise ValueError(f"expected a non-empty int8 tensor, got {getattr(q, 'dtype', type(q).__name__)} "
                         f"{tuple(getattr(q, 'shape', ()))}")
    if not (torch.is_tensor(scale) and scale.dtype == torch.float32 and tuple(scale.shape) == (q.shape[0],)):
        raise ValueError(f"expected a float32 scale of shape [{q.shape[0]}], got "
                         f"{getattr(scale, 'dtype', type(scale).__name__)} {tuple(getattr(scale, 'shape', ()))}")
    if not (torch.isfinite(scale).all() and (scale > 0).all()):
        raise ValueError("expected finite positive scales, got NaN, inf, zero or negative ones")
    return (q.float().reshape(q.shape[0], -1) * scale[:, None]).reshape(q.shape)


def provenance_ok(prov) -> bool:
    """Whether ``prov`` is a provenance ``save_model`` writes and ``load_model`` reads: a dict whose ``image_size``
    (the input size the model was trained at, ``model_input_size``), if any, is a positive int."""
    size = prov.get("image_size") if isinstance(prov, dict) else None
    return isinstance(prov, dict) and (size is None or (is_int(size) and size > 0))


def provenance_json_value(x):
    """JSON for what ``json`` does not take itself in a provenance: numpy scalars and arrays, tensors, paths."""
    if isinstance(x, (np.generic, np.ndarray)) or torch.is_tensor(x):
        return x.tolist()
    if isinstance(x, os.PathLike):
        return os.fspath(x)
    raise ShapeError(f"provenance expected JSON values (numbers, strings, lists, dicts), got {type(x).__name__} "
                     f"{x!r:.80}")


def save_model(model: PointmapNet, path, *, provenance: dict | None = None, dtype=None) -> Path:
    """Write ``model`` as safetensors + JSON config (atomically). ``dtype=torch.float16`` halves the size;
    ``dtype="int8"`` stores every weight matrix of at least INT8_MIN_NUMEL entries as int8 with an fp32 scale
    per slice along its first dimension (``quantize_int8``; about a quarter of fp32) and the rest as fp16. Loading
    dequantizes to fp32, so an int8 file is a storage format: the model computes in float."""
    from safetensors.torch import save_file

    if not isinstance(model, PointmapNet):
        raise ShapeError(f"save_model expected a PointmapNet, got {type(model).__name__}")
    if dtype not in (None, torch.float16, torch.float32, "int8"):
        raise ShapeError(f"dtype expected None, torch.float16, torch.float32 or 'int8', got {dtype!r}")
    prov = provenance_keeping_licence(model, provenance)
    if not isinstance(path, (str, os.PathLike)) or not str(path):
        raise ShapeError(f"save_model expected a file path, got {path!r}")
    given = Path(path)
    path = given if given.suffix == ".safetensors" else given.with_name(given.name + ".safetensors")  # appended,
    for p in (given, path):  # not swapped: run.step1000 and run.step2000 stay two files
        if p.is_dir():
            raise ShapeError(f"save_model expected a file path, got the folder {p}")
    tensors, quantized = {}, []
    for k, v in model.state_dict().items():
        v = v.detach().cpu()
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            raise ShapeError(f"save_model: tensor {k} is not finite (NaN or inf values): a model that diverged "
                             "is not saved")
        if dtype == "int8" and v.is_floating_point() and v.ndim >= 2 and v.numel() >= INT8_MIN_NUMEL:
            tensors[k], tensors[k + SCALE_SUFFIX] = quantize_int8(v)
            quantized.append(k)
        elif v.is_floating_point() and dtype is not None:
            tensors[k] = v.to(torch.float16 if dtype == "int8" else dtype)
            if not bool(torch.isfinite(tensors[k]).all()):  # beyond float16's range (65504): a file load refuses
                raise ShapeError(f"save_model: tensor {k} holds values beyond float16's range (max |value| "
                                 f"{float(v.abs().max()):.4g} > 65504): save it in float32 (dtype=None)")
        else:
            tensors[k] = v
    tensors = {k: v.contiguous() for k, v in tensors.items()}
    meta = {"format": FORMAT, "config": json.dumps(model.cfg.to_dict()),
            "provenance": json.dumps(prov, default=provenance_json_value), "sha256": tensors_checksum(tensors)}
    if quantized:
        meta["int8"] = json.dumps(quantized)
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=meta)
    return path


def _dequantize_state(state: dict, meta: dict, path) -> dict:
    """``state`` with each int8 tensor listed in the file's metadata replaced by its fp32 dequantization (and its
    scale removed). CheckpointError for a list that does not match the tensors (a corrupt or foreign file)."""
    try:
        keys = json.loads(meta.get("int8", "[]"))
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{path} has a broken int8 tensor list: {e}") from None
    if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
        raise CheckpointError(f"{path}: int8 metadata expected a list of tensor names, got {type(keys).__name__}")
    bad = sorted({k for k in keys if keys.count(k) > 1 or k.endswith(SCALE_SUFFIX)})
    if bad:
        raise CheckpointError(f"{path}: int8 metadata expected distinct weight names, got repeated or scale names {bad[:3]}")
    out = dict(state)
    for k in keys:
        q, scale = state.get(k), state.get(k + SCALE_SUFFIX)
        if q is None or scale is None:
            raise CheckpointError(f"{path}: int8 tensor {k!r} expected in the file with its scale "
                                  f"{k + SCALE_SUFFIX!r}; missing: {'the tensor' if q is None else 'the scale'}")
        try:
            out[k] = dequantize_int8(q, scale)
        except ValueError as e:
            raise CheckpointError(f"{path}: int8 tensor {k!r}: {e}") from None
        del out[k + SCALE_SUFFIX]
    stray = [k for k in out if k.endswith(SCALE_SUFFIX) or out[k].dtype == torch.int8]
    if stray:
        raise CheckpointError(f"{path}: int8 tensors or scales not listed in its metadata: {stray[:3]}")
    return out


def load_own(path: Path) -> PointmapNet:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            state = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError, ValueError) as e:
        raise CheckpointError(f"cannot read {path} as safetensors (corrupt or truncated?): {e}") from None
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a pointmap checkpoint (metadata format={meta.get('format')!r})")
    if "sha256" in meta:  # files written since session 74 carry one; older ones load unchecked
        if tensors_checksum(state) != meta["sha256"]:
            raise CheckpointError(f"{path}: its tensors do not match the checksum in its header (corrupted)")
    try:
        cfg = ModelConfig.from_dict(json.loads(meta["config"]))
    except (KeyError, json.JSONDecodeError, TypeError) as e:
        raise CheckpointError(f"{path} has a broken config: {e}") from None
    state = _dequantize_state(state, meta, path)
    state = {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
    check_state(state, path)
    model = built_for(cfg, state, source=str(path))
    try:
        model.provenance = json.loads(meta.get("provenance", "{}"))
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{path} has broken provenance metadata: {e}") from None
    if not provenance_ok(model.provenance):
        raise CheckpointError(f"{path} has broken provenance metadata: expected a JSON object whose image_size, if "
                              f"any, is a positive int, got {meta.get('provenance', '')[:80]!r}")
    warn_if_noncommercial(model, path, "these weights (derived from official ones)")
    return model


def shipped_models() -> list[str]:
    return sorted(p.stem for p in WEIGHTS_DIR.glob("*.safetensors"))


def _bare_name(src) -> bool:
    """A name without a path separator, not ``.``, ``..``, blank or padded with spaces: what can name a shipped
    model."""
    return (isinstance(src, str) and src not in (".", "..") and bool(src.strip()) and src == src.strip()
            and not any(sep and sep in src for sep in (os.path.sep, os.path.altsep)))


def _model_on_disk(path: Path) -> bool:
    """A file, or a folder holding an ONNX export: what ``load_model`` could read at ``path``."""
    return path.is_file() or (path.is_dir() and _is_onnx_export(path))


def shipped_path(src) -> Path | None:
    """The shipped weights file ``load_model(src)`` reads when ``src`` names a shipped model (a bare name, without a
    path separator), else None. A model on disk of that name in the working directory (a file, or an ONNX export's
    folder) is read instead, with a warning; any other folder of that name (photographs called ``small``) is not a
    model and does not hide the shipped one."""
    if _bare_name(src) and not _model_on_disk(Path(src)):
        path = shipped_file(src)
        return path if path.exists() else None
    return None


def shipped_file(name: str) -> Path:
    """Where the package keeps (or ``python -m training.ship`` writes) the shipped model ``name``: a bare name,
    without a path separator, else CheckpointError."""
    if not _bare_name(name):
        raise CheckpointError(f"a shipped model's name expected a bare name (no path separator, not '.', '..' or "
                              f"blank, no surrounding spaces), got {name!r}")
    return WEIGHTS_DIR / f"{name}.safetensors"


def _is_onnx_export(path: Path) -> bool:
    """An .onnx file, or a folder holding one (``python -m export``'s output)."""
    return path.suffix == ".onnx" or (path.is_dir() and any(path.glob("*.onnx")))


def load_model(src, device="cpu", **kwargs):
    """Load a model from a preset name with shipped weights, our .safetensors, an official .pth, or an
    ONNX export (file or directory): ``pm.load_model("small")``. Returns an eval-mode model on ``device``.

    ``kwargs`` go to the ONNX runner (``providers``, ``threads``); TypeError for them with a PyTorch model. Raises
    CheckpointError with the reason.
    """
    # before any file is read; an ONNX export's device is onnxruntime's to find, so only its name is checked there
    onnx = isinstance(src, (str, os.PathLike)) and _is_onnx_export(Path(src))
    device = check_device(device, "load_model: device", available=not onnx)
    if kwargs and not onnx:  # dropped silently before: a misspelt or ONNX-only option did nothing
        raise TypeError(f"load_model got {sorted(kwargs)}, which only an ONNX export's runner takes (providers, "
                        f"threads); {src if isinstance(src, (str, os.PathLike)) else type(src).__name__} is a PyTorch model")
    if isinstance(src, PointmapNet):
        return src.to(device).eval()
    if not isinstance(src, (str, os.PathLike)) or (isinstance(src, str) and not src.strip()):
        raise CheckpointError(f"load_model expected a shipped model's name (e.g. 'small'), a checkpoint path or a "
                              f"PointmapNet, got {type(src).__name__ if not isinstance(src, str) else repr(src)}")
    if (shipped := shipped_path(src)) is not None:
        return load_own(shipped).to(device).eval()
    if _bare_name(src) and shipped_file(src).exists():  # a model on disk hides the shipped one
        warnings.warn(f"{src!r} is a shipped model's name and a {'file' if Path(src).is_file() else 'model folder'} "
                      f"in the working directory: loading the one on disk; the shipped one is {shipped_file(src)}",
                      stacklevel=2)
    if _bare_name(src) and not Path(src).exists():
        if src in PRESETS:
            raise CheckpointError(f"preset {src!r} has no shipped weights; shipped: {shipped_models() or 'none'}. "
                                  f"Use PointmapNet(PRESETS[{src!r}]) for random weights or pass a checkpoint path")
        raise CheckpointError(f"no such file or shipped model: {src!r}; shipped: {shipped_models() or 'none'}")
    path = Path(src)
    if not path.exists():
        raise CheckpointError(f"checkpoint not found: {path}")
    if onnx:
        from pointmap.runtime.onnx import load_onnx

        return load_onnx(path, device=device, **kwargs)  # a GPU device selects onnxruntime's GPU providers
    if path.is_dir():
        raise CheckpointError(f"{path} is a directory without an .onnx export")
    if path.suffix == ".safetensors":
        return load_own(path).to(device).eval()
    return load_official(path).to(device).eval()
