"""Model configuration: a frozen dataclass, and the table of presets.

A config is plain data (JSON-serialisable through ``to_dict``/``from_dict``); checkpoints store it next to
the weights. ``img_mean``/``img_std`` are the preprocessing the weights expect: the model normalises
its [0, 1] inputs itself.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

from pointmap.errors import CheckpointError

HEADS = ("linear", "dpt", "catmlp+dpt", "catmlp+linear")


@dataclass(frozen=True)
class ModelConfig:
    enc_dim: int = 1024
    enc_depth: int = 24
    enc_heads: int = 16
    dec_dim: int = 768
    dec_depth: int = 12
    dec_heads: int = 12
    mlp_ratio: float = 4.0
    patch_size: int = 16
    rope_base: float = 100.0
    head: str = "linear"          # one of HEADS
    desc_dim: int = 0             # > 0 for a descriptor head (catmlp+*)
    desc_hidden_factor: float = 4.0
    two_confs: bool = True        # descriptor head predicts its own confidence
    depth_mode: tuple = ("exp", -math.inf, math.inf)
    conf_mode: tuple = ("exp", 1.0, math.inf)
    desc_conf_mode: tuple = ("exp", 0.0, math.inf)
    dpt_layer_dims: tuple = (96, 192, 384, 768)
    dpt_feature_dim: int = 256
    dpt_last_dim: int = 128
    img_mean: tuple = (0.5, 0.5, 0.5)
    img_std: tuple = (0.5, 0.5, 0.5)
    metric: bool = False          # outputs in metres (MASt3R metric) rather than normalised units
    pose_head: bool = False       # view 2's head predicts its points in its OWN frame and a pose head the
                                  # cam2 -> cam1 transform; pts2_cam1 is their composition (rigid by construction)
    desc_stem: int = 0            # > 0: channels of a full-resolution convolutional stem whose local features each
                                  # descriptor head fuses into its output (0: none, as the official heads)
    focal_head: bool = False      # a head predicting each view's focal from its tokens and own-frame pointmap
                                  # (PairPrediction.focal1 / focal2); needs pose_head (view 2's own-frame points)

    def __post_init__(self) -> None:
        for name in ("img_mean", "img_std", "dpt_layer_dims", "depth_mode", "conf_mode", "desc_conf_mode"):
            if isinstance(getattr(self, name), list):  # tuples, as annotated: a config is hashable and compares equal
                object.__setattr__(self, name, tuple(getattr(self, name)))
        sizes = ("enc_dim", "enc_depth", "enc_heads", "dec_dim", "dec_depth", "dec_heads", "patch_size", "desc_dim",
                 "desc_stem")
        bad = [f"{n}={getattr(self, n)!r}" for n in sizes
               if isinstance(getattr(self, n), bool) or not isinstance(getattr(self, n), int)
               or getattr(self, n) < (0 if n.startswith("desc") else 1)]
        bad += [f"{n}={getattr(self, n)!r}" for n in ("mlp_ratio", "rope_base", "desc_hidden_factor")
                if isinstance(getattr(self, n), bool) or not isinstance(getattr(self, n), (int, float))
                or not 0 < getattr(self, n) < math.inf]
        if not isinstance(self.head, str) or self.head not in HEADS:  # the checks below read it as a name
            raise CheckpointError(f"invalid model config: head expected one of {HEADS}, got {self.head!r}")
        if bad:  # before the checks below, which divide by these
            raise CheckpointError(f"invalid model config: expected positive integer sizes and finite positive ratios "
                                  f"(desc_dim, desc_stem >= 0), got {', '.join(bad)}")
        errors = []
        for name in ("img_mean", "img_std"):
            v = getattr(self, name)
            if not (isinstance(v, (tuple, list)) and len(v) == 3 and all(
                    isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
                errors.append(f"{name} expected 3 finite numbers (one per colour channel), got {v!r}")
        if not errors and min(self.img_std) <= 0:
            errors.append(f"img_std expected positive values, got {self.img_std!r}")
        dims = self.dpt_layer_dims
        if not (isinstance(dims, (tuple, list)) and len(dims) == 4 and all(
                isinstance(x, int) and not isinstance(x, bool) and x > 0 for x in dims)):
            errors.append(f"dpt_layer_dims expected 4 positive integers, got {dims!r}")
        for name in ("dpt_feature_dim", "dpt_last_dim"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                errors.append(f"{name} expected a positive integer, got {v!r}")
        for name in ("two_confs", "metric", "pose_head", "focal_head"):
            if not isinstance(getattr(self, name), bool):
                errors.append(f"{name} expected true or false, got {getattr(self, name)!r}")
        if self.focal_head is True and self.pose_head is not True:
            errors.append("focal_head needs pose_head (the focal of view 2 is read off its own-frame pointmap)")
        if "dpt" in self.head and self.patch_size != 16:
            errors.append(f"a DPT head needs patch_size 16 (its upsampling is built for it), got {self.patch_size}")
        if self.enc_dim % self.enc_heads or (self.enc_dim // self.enc_heads) % 4:
            errors.append(f"enc_dim/enc_heads must be a multiple of 4 (RoPE 2D), got {self.enc_dim}/{self.enc_heads}")
        if self.dec_dim % self.dec_heads or (self.dec_dim // self.dec_heads) % 4:
            errors.append(f"dec_dim/dec_heads must be a multiple of 4 (RoPE 2D), got {self.dec_dim}/{self.dec_heads}")
        if "dpt" in self.head and self.dec_depth < 4:
            errors.append(f"a DPT head needs dec_depth >= 4 (hooks at 1/2, 3/4 and the end), got {self.dec_depth}")
        if self.head.startswith("catmlp") and self.desc_dim <= 0:
            errors.append(f"head {self.head!r} needs desc_dim > 0, got {self.desc_dim}")
        if not self.head.startswith("catmlp") and self.desc_dim:
            errors.append(f"desc_dim={self.desc_dim} needs a catmlp head, got {self.head!r}")
        if self.desc_stem < 0 or (self.desc_stem and not self.has_desc):
            errors.append(f"desc_stem expected 0, or > 0 with a descriptor head, got {self.desc_stem} (desc_dim {self.desc_dim})")
        def real(v):
            return isinstance(v, (int, float)) and not isinstance(v, bool) and not math.isnan(v)

        for name, kinds in (("depth_mode", ("exp", "linear", "square")), ("conf_mode", ("exp", "sigmoid")),
                            ("desc_conf_mode", ("exp", "sigmoid"))):  # the kinds heads.regress_* compute
            mode = getattr(self, name)
            if (len(mode) != 3 or mode[0] not in kinds or not (real(mode[1]) and real(mode[2]) and mode[1] < mode[2])
                    or (mode[0] == "sigmoid" and not math.isfinite(mode[2] - mode[1]))
                    or (name == "depth_mode" and tuple(mode[1:]) != (-math.inf, math.inf))):
                errors.append(f"{name} expected (kind, vmin, vmax) with kind one of {kinds} and numbers vmin < vmax"
                              f"{' (no bounds: -inf, inf)' if name == 'depth_mode' else ''}"
                              f"{' (finite for sigmoid)' if name != 'depth_mode' else ''}, got {mode!r}")
        if errors:
            raise CheckpointError("invalid model config: " + "; ".join(errors))

    @property
    def dpt_hooks(self) -> tuple:
        """Indices into [enc_out, dec_1, ..., dec_L] used by the DPT head (as the official one)."""
        L = self.dec_depth
        return (0, L * 2 // 4, L * 3 // 4, L)

    @property
    def has_desc(self) -> bool:
        return self.desc_dim > 0

    def to_dict(self) -> dict:
        d = asdict(self)
        for k, v in d.items():  # JSON has no inf: store it as a string
            if isinstance(v, tuple):
                d[k] = [("inf" if x == math.inf else "-inf" if x == -math.inf else x) for x in v]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        if not isinstance(d, dict):
            raise CheckpointError(f"a model config expected a dict, got {type(d).__name__}")
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise CheckpointError(f"unknown model config keys: {sorted(unknown)}")
        clean = {}
        for k, v in d.items():
            if isinstance(v, list):
                v = tuple(float(x) if x in ("inf", "-inf") else x for x in v)
            clean[k] = v
        return cls(**clean)

    def replace(self, **kw) -> ModelConfig:
        return replace(self, **kw)


_OFFICIAL = dict(enc_dim=1024, enc_depth=24, enc_heads=16, dec_dim=768, dec_depth=12, dec_heads=12)

PRESETS: dict[str, ModelConfig] = {
    # tiny: unit tests only
    "test": ModelConfig(enc_dim=32, enc_depth=2, enc_heads=2, dec_dim=32, dec_depth=4, dec_heads=2,
                        head="catmlp+dpt", desc_dim=8, dpt_layer_dims=(8, 16, 24, 32), dpt_feature_dim=16,
                        dpt_last_dim=8, desc_hidden_factor=2.0),
    # a model that trains on two CPU cores in hours (the shipped file is this preset grown to 8 / 8 blocks,
    # `training.grow`, session 35: its config travels in the file)
    "small": ModelConfig(enc_dim=256, enc_depth=6, enc_heads=4, dec_dim=192, dec_depth=4, dec_heads=4,
                         head="catmlp+linear", desc_dim=16, desc_hidden_factor=0.25),
    # official architectures (weights from naver/dust3r and naver/mast3r load into these)
    "dust3r_224_linear": ModelConfig(**_OFFICIAL, head="linear"),
    "dust3r_512_linear": ModelConfig(**_OFFICIAL, head="linear"),
    "dust3r_512_dpt": ModelConfig(**_OFFICIAL, head="dpt"),
    "mast3r_512": ModelConfig(**_OFFICIAL, head="catmlp+dpt", desc_dim=24, two_confs=True, metric=True),
}
