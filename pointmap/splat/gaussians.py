"""A set of 3D Gaussians and its PLY file in the layout of the original 3DGS code.

Parametrisation (the one optimised by the fitter and stored in the PLY):

- ``means``      [N, 3] world positions
- ``quats``      [N, 4] rotation quaternions, (w, x, y, z), not necessarily unit (normalised on use)
- ``log_scales`` [N, 3] natural log of the per-axis standard deviations
- ``opacity_logits`` [N] logit of the opacity
- ``sh_dc``      [N, 3] degree-0 spherical-harmonics coefficients; colour = 0.5 + C0 * sh_dc, clamped >= 0
- ``sh_rest``    [N, K, 3] higher SH coefficients (K = (deg + 1)^2 - 1), or None (degree 0)
- ``conf``       [N] optional per-point confidence carried over from the reconstruction (not saved)

PLY layout (binary little endian, float32): x, y, z, nx, ny, nz, f_dc_0..2, f_rest_0..(3K-1),
opacity (logit), scale_0..2 (log), rot_0..3 (w, x, y, z). ``f_rest`` is channel-major as in 3DGS:
``f_rest_{c*K + k}`` is coefficient k of channel c.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from pointmap.atomic import atomic_open
from pointmap.errors import ShapeError

SH_C0 = 0.28209479177387814


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(sh_dc: torch.Tensor) -> torch.Tensor:
    return (sh_dc * SH_C0 + 0.5).clamp_min(0.0)


@dataclass
class Gaussians:
    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: torch.Tensor | None = None
    conf: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.means, torch.Tensor) and self.means.ndim == 2 and self.means.shape[1] == 3):
            got = list(self.means.shape) if isinstance(self.means, torch.Tensor) else type(self.means).__name__
            raise ShapeError(f"Gaussians.means expected a tensor [N, 3], got {got}")
        n = self.means.shape[0]
        want = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,),
                "sh_dc": (n, 3)}
        for name, shape in want.items():
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape or n < 0:
                got = list(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
                raise ShapeError(f"Gaussians.{name} expected shape {list(shape)} (N = len(means)), got {got}")
        if self.sh_rest is not None and not (isinstance(self.sh_rest, torch.Tensor) and self.sh_rest.ndim == 3
                                             and self.sh_rest.shape[0] == n and self.sh_rest.shape[2] == 3
                                             and self.sh_rest.shape[1] in (3, 8, 15)):
            got = list(self.sh_rest.shape) if isinstance(self.sh_rest, torch.Tensor) else type(self.sh_rest).__name__
            raise ShapeError(f"Gaussians.sh_rest expected a tensor [N, K, 3] with K = (degree + 1)^2 - 1 (3, 8 or 15 "
                             f"for degrees 1-3), or None; got {got} (N = {n})")
        if self.conf is not None and not (isinstance(self.conf, torch.Tensor) and tuple(self.conf.shape) == (n,)
                                          and bool(torch.isfinite(self.conf).all())):
            got = (type(self.conf).__name__ if not isinstance(self.conf, torch.Tensor) else list(self.conf.shape)
                   if tuple(self.conf.shape) != (n,) else f"{int((~torch.isfinite(self.conf)).sum())} NaN or inf")
            raise ShapeError(f"Gaussians.conf expected finite confidences [{n}] (N = len(means)) or None, got {got}")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    # --- derived, activated quantities (what the rasterizer takes) ---
    @property
    def scales(self) -> torch.Tensor:
        return self.log_scales.exp()

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def colors(self) -> torch.Tensor:
        """[N, 3] view-independent RGB (SH degree 0)."""
        return sh_dc_to_rgb(self.sh_dc)

    @property
    def sh_degree(self) -> int:
        if self.sh_rest is None:
            return 0
        return int(round((self.sh_rest.shape[1] + 1) ** 0.5)) - 1

    def detach(self) -> "Gaussians":
        return self.map(lambda t: t.detach().clone())

    def to(self, *args, **kwargs) -> "Gaussians":
        return self.map(lambda t: t.to(*args, **kwargs))

    def map(self, fn) -> "Gaussians":
        return replace(self, **{f.name: (None if getattr(self, f.name) is None else fn(getattr(self, f.name)))
                                for f in fields(self)})

    def subset(self, index) -> "Gaussians":
        return self.map(lambda t: t[index])

    @classmethod
    def from_points(cls, points: torch.Tensor, rgb: torch.Tensor, scale, *, opacity: float = 0.1,
                    conf: torch.Tensor | None = None) -> "Gaussians":
        """Isotropic Gaussians at ``points`` [N, 3] with colours ``rgb`` [N, 3] in [0, 1] and
        standard deviation ``scale`` (float or [N])."""
        points = torch.as_tensor(points, dtype=torch.float32)
        if points.ndim != 2 or points.shape[1] != 3 or not bool(torch.isfinite(points).all()):
            raise ShapeError(f"points expected finite [N, 3], got {list(points.shape)}"
                             f"{' with NaN or inf' if points.ndim == 2 and points.shape[1] == 3 else ''}")
        n = points.shape[0]
        rgb_t = torch.as_tensor(rgb, dtype=torch.float32)
        if tuple(rgb_t.shape) != (n, 3) or not bool(((rgb_t >= 0) & (rgb_t <= 1)).all()):
            raise ShapeError(f"rgb expected [{n}, 3] colours in [0, 1], got {list(rgb_t.shape)}"
                             f"{'' if tuple(rgb_t.shape) != (n, 3) else ' outside [0, 1] or NaN'}")
        scale = torch.as_tensor(scale, dtype=torch.float32)
        if scale.numel() not in (1, n) or not bool(torch.isfinite(scale).all() and (scale >= 0).all()):
            raise ShapeError(f"scale expected a finite standard deviation >= 0 (a float or [{n}]), got "
                             f"{scale.tolist() if scale.numel() <= 4 else list(scale.shape)}")
        scale = scale.reshape(-1).expand(n)
        if not 0.0 < opacity < 1.0:
            raise ShapeError(f"opacity must be in (0, 1), got {opacity}")
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        logit = float(np.log(opacity / (1.0 - opacity)))
        log_scales = scale.clamp_min(1e-8).log()[:, None].repeat(1, 3)
        sh_dc = rgb_to_sh_dc(torch.as_tensor(rgb, dtype=torch.float32))
        return cls(means=points.clone(), quats=quats, log_scales=log_scales,
                   opacity_logits=torch.full((n,), logit), sh_dc=sh_dc,
                   conf=None if conf is None else torch.as_tensor(conf, dtype=torch.float32))

    # --- 3DGS PLY ---
    def save_ply(self, path, sh_degree: int | None = 3) -> Path:
        """Write the 3DGS PLY. ``sh_degree`` pads the f_rest fields to that degree with zeros (3 is what
        most viewers expect); None writes exactly the stored degree."""
        path = Path(path)
        g = self.detach().to(torch.float32)
        n = len(g)
        if n == 0:
            raise ShapeError(f"save_ply expected at least one Gaussian, got 0: {path} not written (load_ply refuses "
                             "such a file)")
        deg = g.sh_degree if sh_degree is None else max(int(sh_degree), g.sh_degree)
        k = (deg + 1) ** 2 - 1
        rest = torch.zeros(n, k, 3)
        if g.sh_rest is not None:
            rest[:, : g.sh_rest.shape[1]] = g.sh_rest
        rest_flat = rest.transpose(1, 2).reshape(n, 3 * k)  # channel-major as in 3DGS
        names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                 + [f"f_rest_{i}" for i in range(3 * k)]
                 + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
        data = torch.cat([g.means, torch.zeros(n, 3), g.sh_dc, rest_flat, g.opacity_logits[:, None],
                          g.log_scales, g.quats], dim=1).numpy().astype("<f4")
        bad = int((~np.isfinite(data).all(axis=1)).sum())
        if bad:
            raise ShapeError(f"save_ply expected finite Gaussians, got {bad} of {n} with NaN or inf values (a fit "
                             f"that diverged?): {path} not written (load_ply refuses such a file)")
        header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
        header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
        with atomic_open(path, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(np.ascontiguousarray(data).tobytes())
        return path

    @classmethod
    def load_ply(cls, path) -> "Gaussians":
        """Read a 3DGS PLY (binary little endian, float properties) as written by ``save_ply`` or 3DGS."""
        path = Path(path)
        with open(path, "rb") as f:
            raw = f.read()
        end = raw.find(b"end_header\n")
        if not raw.startswith(b"ply") or end < 0:
            raise ShapeError(f"{path} is not a PLY file")
        header = raw[:end].decode("ascii", errors="replace").splitlines()  # comments may hold any bytes
        if "format binary_little_endian 1.0" not in header:
            raise ShapeError(f"{path}: only binary_little_endian PLY is supported")
        n, props = None, []
        for line in header:
            parts = line.split()
            if parts[:1] == ["element"]:
                if n is not None:
                    break  # an element after the vertices: its data follows theirs, and is not read
                if parts[1:2] != ["vertex"]:  # its data would come first: the vertices would be read shifted
                    raise ShapeError(f"{path}: expected the vertex element first (as 3DGS writes it), got "
                                     f"{line.strip()!r} before it")
                if len(parts) != 3 or not parts[2].isdigit():
                    raise ShapeError(f"{path}: 'element vertex' expected a count, got {line.strip()!r}")
                n = int(parts[2])
            elif parts[:1] == ["property"] and n is not None:
                if len(parts) != 3 or parts[1] not in ("float", "float32"):
                    raise ShapeError(f"{path}: vertex properties expected 'property float NAME', got "
                                     f"{line.strip()!r}")
                props.append(parts[2])
        if not n:
            raise ShapeError(f"{path}: no vertex element" if n is None else f"{path}: holds no Gaussian (0 vertices)")
        have = len(raw) - end - len(b"end_header\n")
        if have < 4 * n * len(props):
            raise ShapeError(f"{path}: truncated: {n} Gaussians of {len(props)} floats need {4 * n * len(props)} "
                             f"bytes, the file has {have} after its header")
        arr = np.frombuffer(raw, dtype="<f4", offset=end + len(b"end_header\n"), count=n * len(props))
        arr = torch.from_numpy(arr.reshape(n, len(props)).copy())
        if not bool(torch.isfinite(arr).all()):
            bad = int((~torch.isfinite(arr).all(dim=1)).sum())
            raise ShapeError(f"{path}: {bad} of {n} Gaussians hold NaN or inf values (a fit that diverged?)")
        col = {name: i for i, name in enumerate(props)}
        need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                "rot_0", "rot_1", "rot_2", "rot_3"]
        missing = [p for p in need if p not in col]
        if missing:
            raise ShapeError(f"{path}: not a 3DGS PLY, missing properties {missing}")

        def take(names):
            return arr[:, [col[p] for p in names]]

        n_rest = sum(1 for p in props if p.startswith("f_rest_"))
        k = n_rest // 3
        if n_rest and ((round((k + 1) ** 0.5) ** 2 != k + 1 or n_rest != 3 * k)
                       or set(p for p in props if p.startswith("f_rest_")) != {f"f_rest_{i}" for i in range(n_rest)}):
            raise ShapeError(f"{path}: f_rest properties expected f_rest_0 .. f_rest_{{3K - 1}} with K = (degree + 1)^2 "
                             f"- 1 (9, 24 or 45 of them for degrees 1-3), got {n_rest}: "
                             f"{[p for p in props if p.startswith('f_rest_')][:6]}")
        sh_rest = None
        if n_rest:
            rest = take([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k).transpose(1, 2)
            sh_rest = rest.contiguous() if rest.abs().max() > 0 else None
            if sh_rest is not None:
                import warnings

                warnings.warn(f"{path}: holds view-dependent colour (SH degree {int(round((k + 1) ** 0.5)) - 1}), "
                              "which pointmap keeps but does not render or fit (degree 0, the DC colour, only)",
                              RuntimeWarning, stacklevel=2)
        return cls(means=take(["x", "y", "z"]), quats=take(["rot_0", "rot_1", "rot_2", "rot_3"]),
                   log_scales=take(["scale_0", "scale_1", "scale_2"]),
                   opacity_logits=arr[:, col["opacity"]].clone(),
                   sh_dc=take(["f_dc_0", "f_dc_1", "f_dc_2"]), sh_rest=sh_rest)
