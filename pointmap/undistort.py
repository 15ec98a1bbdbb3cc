"""Photographs taken through distorting lenses, made pinhole: the models (and every writer of this library) take
pinhole cameras, so images whose calibration states lens distortion (a phone app's or COLMAP's OPENCV camera, a
fisheye) are resampled onto a pinhole camera first, with OpenCV's distortion models.

The pinhole camera chosen (``pinhole_for``) keeps the image size, the principal point and the aspect of the
focal lengths, and takes the widest field of view whose every pixel comes from inside the photograph: no
invented black borders (the model never saw any), at the cost of a thin margin of the photograph's edge.
Pixel convention as everywhere in pointmap (and in OpenCV): pixel centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pointmap.errors import PointmapError
from pointmap.geometry.cameras import K_LAYOUT, is_pinhole_K

# camera model -> its coefficients in order (COLMAP's and nerfstudio's names)
MODELS = {
    "SIMPLE_RADIAL": ("k1",),
    "RADIAL": ("k1", "k2"),
    "OPENCV": ("k1", "k2", "p1", "p2", "k3"),
    "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"),
    "FULL_OPENCV": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),  # OpenCV's rational model
}


@dataclass(frozen=True)
class Distortion:
    """A lens distortion: ``model`` from ``MODELS`` and its coefficients by name (missing ones are 0)."""
    model: str
    coeffs: tuple = ()

    def __post_init__(self):
        if self.model not in MODELS:
            raise PointmapError(f"distortion model expected one of {', '.join(MODELS)}, got {self.model!r}")
        names = MODELS[self.model]
        try:
            c = tuple(float(x) for x in self.coeffs)
        except (TypeError, ValueError):
            raise PointmapError(f"{self.model} expected a sequence of up to {len(names)} numbers ({', '.join(names)}), "
                                f"got {self.coeffs!r}") from None
        if len(c) > len(names) or not all(np.isfinite(c)):
            raise PointmapError(f"{self.model} expected up to {len(names)} finite coefficients ({', '.join(names)}), "
                                f"got {list(self.coeffs)}")
        object.__setattr__(self, "coeffs", c + (0.0,) * (len(names) - len(c)))

    @classmethod
    def from_named(cls, model: str, values: dict) -> Distortion:
        """From named coefficients (``{"k1": .., "p1": ..}``); a nonzero one the model does not have is refused."""
        model = str(model).upper()
        if model not in MODELS:
            raise PointmapError(f"distortion model expected one of {', '.join(MODELS)}, got {model!r}")
        names = MODELS[model]
        try:  # numbers only ("abc", a list, an array: refused here, not with a raw ValueError / TypeError)
            values = {k: 0.0 if v is None else float(v) for k, v in values.items()}
        except (TypeError, ValueError):
            raise PointmapError(f"{model} expected numbers for {', '.join(names)}, got {values!r}") from None
        extra = {k: v for k, v in values.items() if k not in names and v != 0.0}
        if extra:
            raise PointmapError(f"{model} has no coefficient{'s' if len(extra) > 1 else ''} {', '.join(extra)} "
                                f"(it has {', '.join(names)}), got {extra}")
        return cls(model, tuple(values.get(k, 0.0) for k in names))

    @property
    def fisheye(self) -> bool:
        return self.model == "OPENCV_FISHEYE"

    @property
    def is_identity(self) -> bool:
        """A pinhole camera: no coefficient set, and not a fisheye (whose zero coefficients still mean the
        equidistant projection, theta_d = theta)."""
        return not self.fisheye and not any(self.coeffs)

    def opencv(self) -> np.ndarray:
        """The coefficient vector OpenCV's functions take: (k1, k2, p1, p2, k3[, k4, k5, k6]), or (k1..k4) for the
        fisheye."""
        if self.fisheye or self.model == "FULL_OPENCV":
            return np.asarray(self.coeffs, np.float64)
        d = dict(zip(MODELS[self.model], self.coeffs))
        return np.array([d.get("k1", 0.0), d.get("k2", 0.0), d.get("p1", 0.0), d.get("p2", 0.0), d.get("k3", 0.0)])


def _check_K(K, size) -> np.ndarray:
    K = np.asarray(K, np.float64)
    w, h = size
    if K.shape != (3, 3) or not bool(is_pinhole_K(K)):
        raise PointmapError(f"K expected a finite [3, 3] matrix {K_LAYOUT} with positive "
                            f"focal lengths, got {K.tolist()}")
    if not (isinstance(w, (int, np.integer)) and isinstance(h, (int, np.integer)) and w > 1 and h > 1):
        raise PointmapError(f"size expected (width, height) in pixels, got {size}")
    return K


def distort(xy: np.ndarray, K, distortion: Distortion) -> np.ndarray:
    """Pixels [N, 2] of the photograph (with ``K`` and ``distortion``) where the rays of normalised pinhole
    coordinates ``xy`` [N, 2] land (OpenCV's projection)."""
    import cv2

    pts = np.concatenate([np.asarray(xy, np.float64), np.ones((len(xy), 1))], 1)[:, None]
    zero = np.zeros(3)
    if distortion.fisheye:
        out = cv2.fisheye.projectPoints(pts, zero, zero, np.asarray(K, np.float64), distortion.opencv())[0]
    else:
        out = cv2.projectPoints(pts, zero, zero, np.asarray(K, np.float64), distortion.opencv())[0]
    return out[:, 0]


def _border(w: int, h: int, step: int = 1) -> np.ndarray:
    xs = np.r_[np.arange(0, w, step), w - 1].astype(np.float64)
    ys = np.r_[np.arange(0, h, step), h - 1].astype(np.float64)
    return np.concatenate([np.c_[xs, np.zeros_like(xs)], np.c_[xs, np.full_like(xs, h - 1)],
                           np.c_[np.zeros_like(ys), ys], np.c_[np.full_like(ys, w - 1), ys]])


def _inside(K_new, K, distortion, w, h) -> bool:
    """Every border pixel of the pinhole view ``K_new`` comes from inside the photograph, and the lens model is
    still unfolded there (the distorted radius grows along the rays to the view's corners: a polynomial model
    of strong barrel distortion turns back beyond some radius, where it would mirror the image)."""
    b = _border(w, h)
    xy = (b - K_new[:2, 2]) / np.diag(K_new)[:2]
    src = distort(xy, K, distortion)
    if not (np.isfinite(src).all() and (src[:, 0] >= -0.5).all() and (src[:, 0] <= w - 0.5).all()
            and (src[:, 1] >= -0.5).all() and (src[:, 1] <= h - 0.5).all()):
        return False
    corners = (np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], np.float64) - K_new[:2, 2]) / np.diag(K_new)[:2]
    t = np.linspace(0, 1.02, 256)[:, None, None]  # a little past the corners: a margin for the sampling
    rays = distort((t * corners[None]).reshape(-1, 2), K, distortion).reshape(len(t), 4, 2)
    radius = np.linalg.norm(rays - K[:2, 2], axis=-1)
    return bool((np.diff(radius, axis=0) > 0).all())


def pinhole_for(K, distortion: Distortion, size) -> np.ndarray:
    """The pinhole K [3, 3] the photograph of ``size`` (w, h) is undistorted onto: ``K``'s principal point and
    focal aspect, the smallest focal scale (widest view) for which every border pixel of the output comes from
    inside the photograph and the lens model has not folded back (bisection on the scale)."""
    K = _check_K(K, size)
    w, h = size
    if distortion.is_identity:
        return K.copy()

    def scaled(a):
        Kn = K.copy()
        Kn[0, 0] *= a
        Kn[1, 1] *= a
        Kn[0, 1] = 0.0
        return Kn

    lo, hi = 0.05, 1.0
    if _inside(scaled(lo), K, distortion, w, h):  # the bisection needs a scale too wide to fit
        raise PointmapError(f"{distortion} (K {K.tolist()}) sees 180 degrees or more inside the {w} x {h} photograph "
                            "(a circular fisheye): no pinhole view covers it; crop the image circle to a narrower "
                            "field first")
    while not _inside(scaled(hi), K, distortion, w, h):
        hi *= 1.5
        if hi > 50:
            raise PointmapError(f"no pinhole view lies inside the photograph for {distortion} (K {K.tolist()}): "
                                "the distortion coefficients look wrong")
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if _inside(scaled(mid), K, distortion, w, h):
            hi = mid
        else:
            lo = mid
    return scaled(hi)


def undistort(image: np.ndarray, K, distortion: Distortion, K_new=None, *, nearest: bool = False) -> np.ndarray:
    """``image`` [H, W] or [H, W, C] resampled onto the pinhole camera ``K_new`` (default ``pinhole_for``) of
    the same size: bilinear, or ``nearest`` for masks and labels. Returns an array of ``image``'s dtype."""
    import cv2

    image = np.asarray(image)
    if image.ndim not in (2, 3) or image.shape[0] < 2 or image.shape[1] < 2 or (image.ndim == 3 and
                                                                                 not 1 <= image.shape[2] <= 4):
        raise PointmapError(f"undistort expected an [H, W] or [H, W, C] image (C 1..4), got shape {list(image.shape)}")
    if image.dtype not in (np.uint8, np.uint16, np.float32, np.float64, bool):
        raise PointmapError(f"undistort expected an image of dtype uint8, uint16, float32, float64 or bool, got "
                            f"{image.dtype}")
    if not isinstance(distortion, Distortion):
        raise PointmapError(f"undistort expected a Distortion (pointmap.undistort), got {type(distortion).__name__}")
    h, w = image.shape[:2]
    K = _check_K(K, (w, h))
    K_new = pinhole_for(K, distortion, (w, h)) if K_new is None else _check_K(K_new, (w, h))
    if distortion.is_identity and np.allclose(K_new, K):
        return image.copy()
    if distortion.fisheye:
        mx, my = cv2.fisheye.initUndistortRectifyMap(K, distortion.opencv(), np.eye(3), K_new, (w, h), cv2.CV_32FC1)
    else:
        mx, my = cv2.initUndistortRectifyMap(K, distortion.opencv(), None, K_new, (w, h), cv2.CV_32FC1)
    src = image.astype(np.uint8) if image.dtype == bool else image
    out = cv2.remap(src, mx, my, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out = out.reshape(image.shape)  # OpenCV returns [H, W] for a one-channel [H, W, 1]
    return out.astype(bool) if image.dtype == bool else out


def undistort_photos(paths: list, K: dict, distortions: dict, out_dir, masks: list | None = None):
    """The photographs ``paths[k]`` for k in ``distortions`` (each with its ``K[k]`` [3, 3], original pixels)
    resampled onto their pinhole cameras (``pinhole_for``) and written atomically to ``out_dir`` under their
    own names (the format their suffix names; JPEG at quality 95; a format OpenCV cannot write, HEIC, as
    ``<stem>.jpg``). Returns (paths, K, masks): the paths with those entries replaced, K with their pinhole intrinsics, and ``masks`` (one [H, W] array per photograph at
    its original size, or None) with theirs resampled alike (nearest); everything else as given."""
    import cv2

    from pointmap.atomic import atomic_path
    from pointmap.images import read_rgb

    if not isinstance(K, dict) or not isinstance(distortions, dict):
        raise PointmapError(f"K and distortions expected dicts {{photograph index: value}}, got "
                            f"{type(K).__name__} and {type(distortions).__name__}")
    paths, K = list(paths), dict(K)
    masks = None if masks is None else list(masks)
    if masks is not None and len(masks) != len(paths):
        raise PointmapError(f"masks expected one entry (an array or None) per photograph, {len(paths)}, "
                            f"got {len(masks)}")
    bad = [k for k in list(distortions) + list(K) if not (isinstance(k, (int, np.integer)) and 0 <= k < len(paths))]
    if bad:
        raise PointmapError(f"distortions and K expected photograph indices in 0..{len(paths) - 1}, got {bad}")
    # a format OpenCV cannot write (HEIC, HEIF) is written as <stem>.jpg: imwrite raised for it before
    out_name = {k: Path(paths[k]).name if cv2.haveImageWriter(Path(paths[k]).name) else Path(paths[k]).stem + ".jpg"
                for k in distortions}
    names = [n.lower() for n in out_name.values()]
    if len(set(names)) != len(names):
        raise PointmapError(f"undistorted photographs would share a file name in {out_dir}: {sorted(names)}")
    out_dir = Path(out_dir)
    for k, dist in sorted(distortions.items()):
        if k not in K or K[k] is None:
            raise PointmapError(f"photograph {k} ({paths[k]}) has lens distortion but no intrinsics to undo it with")
        rgb = read_rgb(paths[k])
        h, w = rgb.shape[:2]
        cx, cy = float(np.asarray(K[k])[0, 2]), float(np.asarray(K[k])[1, 2])
        if not (0 <= cx <= w - 1 and 0 <= cy <= h - 1):
            raise PointmapError(f"photograph {Path(paths[k]).name} is {w}x{h} as read (EXIF orientation applied), but "
                                f"its K puts the principal point at ({cx:.1f}, {cy:.1f}), outside it: the intrinsics "
                                "are not this image's (rotated, or for another size)")
        if masks is not None and masks[k] is not None and tuple(np.shape(masks[k])) != (h, w):
            raise PointmapError(f"the mask of {Path(paths[k]).name} is {list(np.shape(masks[k]))[:2]}, but a "
                                f"photograph with lens distortion needs its mask at its own size [{h}, {w}]")
        K_new = pinhole_for(K[k], dist, (w, h))
        out = undistort(rgb, K[k], dist, K_new)
        target = out_dir / out_name[k]
        if target.resolve() == Path(paths[k]).resolve():  # e.g. a re-run on an earlier run's undistorted/ folder
            raise PointmapError(f"{paths[k]} would be overwritten by its own undistorted copy: its folder is the "
                                f"output folder {out_dir}; these photographs were undistorted already, or give "
                                "another output folder")
        with atomic_path(target) as tmp:
            params = [cv2.IMWRITE_JPEG_QUALITY, 95] if tmp.suffix.lower() in (".jpg", ".jpeg") else []
            try:
                written = cv2.imwrite(str(tmp), np.ascontiguousarray(out[..., ::-1]), params)
            except cv2.error as e:
                raise PointmapError(f"could not write the undistorted photograph {target}: {e}") from None
            if not written:
                raise PointmapError(f"could not write the undistorted photograph {target}")
        if masks is not None and masks[k] is not None:
            masks[k] = undistort(np.asarray(masks[k]), K[k], dist, K_new, nearest=True)
        paths[k], K[k] = str(target), K_new
    return paths, K, masks
