"""The ``pointmap`` command: ``pair``, ``reconstruct``, ``splat``, ``demo``.

Bad input ends with a one-line message on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import warnings
from pathlib import Path

from pointmap.errors import CheckpointError, GraphError, ImageError, PointmapError

log = logging.getLogger("pointmap")
DEFAULT_MODEL = "small"
MAX_FRAMES = 30  # defaults of flags parsed as None (refuse_ignored tells a given flag from its default)
DEPTH_PNG_SCALE = 1e-3
SPLAT_BUDGET = 120.0
COLMAP_POINTS = 100_000
TEST_ALIGN_STEPS = 100


def check_size_graph_budget(args) -> None:
    """``--size``, ``--graph`` and ``--splat-budget`` (where the command has them), checked before any model loads."""
    from pointmap.images import INPUT_SIZE_RULE, is_input_size

    size = getattr(args, "size", None)
    if size is not None and not is_input_size(size):
        raise PointmapError(f"--size expected {INPUT_SIZE_RULE}, got {size}")
    from pointmap.pairs import parse_graph

    try:  # the name's syntax (how many images it suits is checked with the images)
        parse_graph(getattr(args, "graph", "auto"), auto=True)
    except PointmapError as e:
        raise PointmapError(f"--graph: {e}") from None
    budget = getattr(args, "splat_budget", None)
    if budget is not None and not (math.isfinite(budget) and budget >= 0):
        raise PointmapError(f"--splat-budget expected seconds >= 0 (0: no limit), got {budget}")


def resolve_device(text: str) -> str:
    """``--device``: auto (CUDA, then Apple's MPS, then the CPU, whichever torch can use first), cpu, cuda, cuda:N
    or mps. A device torch cannot use here is refused now, before any model loads (``errors.check_device``)."""
    from pointmap.errors import check_device

    return check_device(text, "--device")


def _model_and_size(name: str, size: int | None, device: str = "cpu"):
    from pointmap.checkpoint import load_model, model_input_size

    model = load_model(name, device=device)
    return model, size if size is not None else model_input_size(model)


def refuse_ignored(args, rules) -> None:
    """Flags given where they would do nothing: ``rules`` are (dest, flag, applies, where) and a flag whose value is
    not None (its parser default is None: given) while ``applies`` is False is refused, naming ``where`` it
    applies. A flag the command would silently ignore hides a mistake (a typo'd input, a forgotten parent flag)."""
    for dest, flag, applies, where in rules:
        if getattr(args, dest, None) is not None and not applies:
            raise PointmapError(f"{flag} applies only {where}; here it would be ignored")


def fill_defaults(args, **defaults) -> None:
    """The defaults of flags parsed as None (so that ``refuse_ignored`` can tell a given flag from its default)."""
    for dest, value in defaults.items():
        if getattr(args, dest) is None:
            setattr(args, dest, value)


def refuse_head_prior_without_pose_head(args, model) -> None:
    """``--head-prior W`` (W > 0; 0 is off for any model) on a model (PyTorch or ONNX runtime) without the pose head
    whose transforms the prior reads: refused once the model is loaded, before inference."""
    has_pose_head = bool(getattr(getattr(model, "cfg", None), "pose_head", False))
    refuse_ignored(args, [("head_prior", "--head-prior", has_pose_head or not args.head_prior,
                           "to a model with a pose head")])


def parse_focals(text: str, images: list) -> list[float]:
    """``--focal``: one focal for all the images or one per image, comma-separated, positive, in pixels; or
    ``exif``: each image's from its EXIF 35 mm-equivalent focal length (``pointmap.images.exif_focals``), every
    image carrying one."""
    n = len(images)
    if text.strip().lower() == "exif":
        from pointmap.images import exif_focals

        focal = exif_focals(images)
        missing = [Path(str(img)).name for img, f in zip(images, focal) if f is None]
        if missing:
            raise PointmapError(f"--focal exif expected every image to carry an EXIF 35 mm-equivalent focal length "
                                f"(FocalLengthIn35mmFilm); {len(missing)} of {n} have none: "
                                f"{', '.join(missing[:5])}{', ...' if len(missing) > 5 else ''}. Give --focal F "
                                f"(pixels) or leave --focal out to estimate the focals")
        return focal
    try:
        focal = [float(f) for f in text.split(",")]
    except ValueError:
        focal = []
    if len(focal) not in (1, n) or not all(math.isfinite(f) and f > 0 for f in focal):
        raise PointmapError(f"--focal expected F, {n} comma-separated values (positive, in pixels) or exif (each "
                            f"image's EXIF 35 mm-equivalent focal), got {text!r}")
    return focal * n if len(focal) == 1 else focal


def shared_focals(images: list, videos: dict, note_focal: bool, note_cameras: bool):
    """Which images share one focal when no focal is given, as ``AlignConfig.shared_focal`` takes it (True: all,
    a label per image: several cameras, False: none): the frames of one video (``videos``: frame path -> video), and
    the photographs of one camera by their EXIF (``pointmap.images.exif_camera_labels``: one make, model, lens, focal
    length and zoom, one size). Notes on stderr: ``note_cameras``, the cameras that share a focal; ``note_focal``,
    that every photograph carries an EXIF focal that ``--focal exif`` would hold fixed instead of estimating it (a
    known focal steadies the camera translations: docs/alignment.md)."""
    from pointmap.images import exif_camera_labels, exif_cameras

    cameras = exif_cameras(images)
    order: dict = {}  # a video's frames one camera, the others by their EXIF; 0, 1, ... in order of first appearance
    labels = [order.setdefault(("video", videos[img]) if img in videos else c, len(order))
              for img, c in zip(images, exif_camera_labels(cameras))]
    if note_focal and images and all(c is not None and c.focal_35mm is not None for c in cameras):
        print("pointmap: the photographs carry EXIF focal lengths; --focal exif would hold them fixed instead of "
              "estimating the focals (docs/alignment.md)", file=sys.stderr)
    counts = {c: labels.count(c) for c in dict.fromkeys(labels)}
    if max(counts.values(), default=0) < 2:
        return False
    if note_cameras:
        groups = [f"the {m} frames of {Path(videos[images[k]]).name}" if images[k] in videos else
                  f"{m} photographs of one camera by their EXIF ({describe_exif_camera(cameras[k])})"
                  for c, m in counts.items() if m > 1 for k in [labels.index(c)]]
        alone = sum(m == 1 for m in counts.values())
        print(f"pointmap: one estimated focal per camera: {'; '.join(groups)}"
              f"{f'; the other {alone} image(s) each its own' if alone else ''} (--no-shared-focal: one per image)",
              file=sys.stderr)
    return True if len(counts) == 1 else tuple(labels)


def describe_exif_camera(cam) -> str:
    """An ``ExifCamera`` in words: make and model, lens, focal length, digital zoom and size."""
    make, model, lens, focal_mm, zoom = cam.body
    name = model if model.lower().startswith(make.lower()) else f"{make} {model}"  # "Canon" "Canon EOS 80D"
    return (f"{name}{f', {lens}' if lens else ''}, {focal_mm:g} mm"
            f"{f', digital zoom {zoom:g}' if zoom != 1 else ''}, {cam.size[0]}x{cam.size[1]}")


def K_from_focals(images: list, focal: list[float]):
    """[N, 3, 3] float64 K of each image: the given focal, the principal point at the centre of the image as read
    (EXIF orientation applied): ((w - 1) / 2, (h - 1) / 2) in pointmap's pixel convention."""
    import torch

    from pointmap.geometry.cameras import intrinsics
    from pointmap.images import image_sizes

    return torch.stack([intrinsics(f, (w - 1) / 2, (h - 1) / 2, dtype=torch.float64)
                        for (w, h), f in zip(image_sizes(images), focal)])


def cmd_pair(args) -> int:
    from pointmap.io_pair import write_pair_outputs

    writable_dir(Path(args.out))
    check_size_graph_budget(args)
    # --no-shared-focal with --focal is what --focal means anyway (reconstruct takes it too): only --shared-focal
    # would be ignored
    if args.shared_focal and args.focal is not None:
        raise PointmapError("--shared-focal applies only without --focal (a given focal is not estimated, shared or "
                            "not); here it would be ignored")
    from pointmap.io_pair import PAIR_OUTPUTS

    mine = {(Path(args.out) / name).resolve() for name in PAIR_OUTPUTS}
    overwritten = [img for img in args.images if Path(img).resolve() in mine]
    if overwritten:  # checked before the model loads, as reconstruct's exports are
        raise PointmapError(f"-o {args.out} would overwrite the input(s) {', '.join(overwritten)} with pair's own "
                            f"outputs ({', '.join(PAIR_OUTPUTS)}); give another output folder")
    focal = None if args.focal is None else parse_focals(args.focal, args.images)
    shared = args.shared_focal
    if shared is None and focal is None:  # two photographs of one camera by their EXIF: one focal
        shared = shared_focals(args.images, {}, note_focal=not args.quiet, note_cameras=not args.quiet) is True
    if args.shared_focal:  # said before the model loads, in the flag's own words
        from pointmap.images import image_sizes

        sizes = image_sizes(args.images)
        if sizes[0] != sizes[1]:
            raise PointmapError(f"--shared-focal says the two photographs are of one camera, of one size; they are "
                                f"{sizes[0][0]}x{sizes[0][1]} and {sizes[1][0]}x{sizes[1][1]} (EXIF orientation "
                                "applied): drop --shared-focal")
    model, size = _model_and_size(args.model, args.size, args.device)
    paths = write_pair_outputs(model, args.images[0], args.images[1], Path(args.out), size=size, quiet=args.quiet,
                               focal=focal, shared_focal=bool(shared), device=args.device)
    for p in paths:
        print(p)
    print(pair_summary(Path(args.out) / "pair.npz"))
    return 0


def pair_summary(npz: Path) -> str:
    """One line on the relative pose and focals stored by ``write_pair_outputs``."""
    import numpy as np
    import torch

    from pointmap.geometry.rotations import rotation_angle

    z = np.load(npz)
    T = torch.from_numpy(z["cam2world_2_in_1"]).double()
    if not torch.isfinite(T).all():
        return "relative pose: not found (too few confident pixels)"
    angle = float(torch.rad2deg(rotation_angle(T[:3, :3])))
    t = torch.nn.functional.normalize(T[:3, 3], dim=0, eps=1e-12)
    # focals in original pixels; files written before session 48 (no focal_units) stored the maps' pixels
    f1, f2 = float(z["focal1"]), float(z["focal2"])
    if "focal_units" not in z:
        f1, f2 = f1 / z["map_from_original1"][0], f2 / z["map_from_original2"][0]
    same = "img1" in z and "img2" in z and z["img1"].shape == z["img2"].shape and np.array_equal(z["img1"], z["img2"])
    where = ("no translation direction (the same image twice: no baseline" if same else  # write_pair_outputs warned
             f"camera 2 towards ({t[0]:+.2f}, {t[1]:+.2f}, {t[2]:+.2f}) in camera 1's frame (x right, y down, z forward")
    return (f"view 2 relative to view 1: rotation {angle:.1f} deg, {where}"
            f"{'; refined on the matches' if 'refined_on_matches' in z and bool(z['refined_on_matches']) else ''}"
            f"); focal {f1:.0f} / {f2:.0f} px "
            f"(original pixels{', given' if 'focal_given' in z and bool(z['focal_given']) else ''}"
            f"{', one shared' if 'focal_shared' in z and bool(z['focal_shared']) else ''})")


IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".heic", ".heif")


def convert_heif(images: list[str], folder: Path, quiet: bool) -> list[str]:
    """``reconstruct``'s HEIC / HEIF photographs (an iPhone's) as JPEGs in ``folder`` (quality 95, upright, the EXIF
    kept with its orientation reset), the other images as given: the exports copy the photographs beside the model,
    and 3DGS trainers cannot read HEIC. Each keeps its stem, which ``--masks`` match by (``--cameras`` and
    ``--pairs`` files may name the original or the JPEG).
    PointmapError when a converted name would be another input's; ImageError for an unreadable file, or without
    pillow-heif."""
    from PIL import Image

    from pointmap.atomic import atomic_path
    from pointmap.images import HEIF_SUFFIXES, read_rgb

    heif = [k for k, img in enumerate(images) if Path(img).suffix.lower() in HEIF_SUFFIXES]
    names = [Path(img).name.lower() for img in images]
    out = list(images)
    for k in heif:
        name = Path(images[k]).stem + ".jpg"
        if name.lower() in names:
            raise PointmapError(f"{images[k]} is converted to {name} (3DGS trainers cannot read HEIC), the name of "
                                f"another input; rename one of them")
        names.append(name.lower())
        upright = Image.fromarray(read_rgb(images[k]))  # EXIF orientation applied, as the loader reads it
        with Image.open(images[k]) as im:
            exif = im.getexif()
        exif[0x0112] = 1  # the pixels are upright now
        with atomic_path(folder / name) as tmp:
            upright.save(tmp, format="JPEG", quality=95, exif=exif)
        out[k] = str(folder / name)
    if heif and not quiet:
        print(f"pointmap: {len(heif)} HEIC / HEIF photograph(s) converted to JPEG in {folder} (3DGS trainers cannot "
              "read HEIC)", file=sys.stderr)
    return out


def natural_key(name: str) -> list:
    """Sort key comparing runs of digits as numbers: frame_2 before frame_10 (as a plain string sort does not: the
    ``auto`` graph pairs neighbours in file order)."""
    import re

    return [int(part) if k % 2 else part for k, part in enumerate(re.split(r"(\d+)", name))]


def _image_files(folder: Path) -> list[str]:
    """The folder's image files in natural order (``natural_key``); hidden ones (macOS's ``._name.jpg`` resource
    forks) left out."""
    return sorted((str(f) for f in folder.iterdir()
                   if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith(".")),
                  key=natural_key)


def expand_images(items: list[str], frames_dir: Path | None = None, stride: int | None = None,
                  max_frames: int = 30, times: dict | None = None, videos: dict | None = None) -> list[str]:
    """Image paths from the command line: a folder stands for its image files (sorted by name, suffixes in
    ``IMAGE_SUFFIXES``, any case), or when it has none for those of its ``images/`` folder (the layout of a
    COLMAP or nerfstudio scene); a video (``pointmap.video.VIDEO_SUFFIXES``) for frames extracted into
    ``frames_dir`` (``pointmap.video.extract_frames``: one per ``stride`` frames, the sharpest of each window,
    at most ``max_frames`` when no stride is given); files are kept as given. ``times``, a dict, receives each
    extracted frame's time in seconds (``extract_frames(with_times=True)``) under its path, ``videos`` its video.
    PointmapError for a
    folder without images, or a path that does not exist."""
    from pointmap.video import extract_frames, is_video

    stems = [Path(i).stem for i in items if is_video(Path(i))]
    clash = sorted({s for s in stems if stems.count(s) > 1})
    if clash:  # frames are named <stem>_<index>.png in one folder
        raise PointmapError(f"videos named {clash} more than once: their frames would overwrite each other in "
                            f"{frames_dir}; give them different file names")
    out = []
    for item in items:
        p = Path(item)
        if is_video(p):
            if frames_dir is None:
                raise PointmapError(f"{p} is a video: frames need a folder to go to")
            frames = extract_frames(p, frames_dir, stride=stride, max_frames=max_frames, with_times=True)
            out += [str(f) for f, _ in frames]
            if times is not None:
                times.update((str(f), t) for f, t in frames)
            if videos is not None:
                videos.update((str(f), str(p)) for f, _ in frames)
        elif p.is_dir():
            found = _image_files(p)
            if not found and (p / "images").is_dir():  # a COLMAP / nerfstudio scene: its photographs in images/
                found = _image_files(p / "images")
            if not found:
                raise PointmapError(f"folder {p} holds no images (expected files ending in "
                                    f"{', '.join(IMAGE_SUFFIXES)})")
            out += found
        elif not p.exists():
            glob = " (an unexpanded shell pattern? the shell expands it only where files match)" \
                if any(c in item for c in "*?[") else ""
            raise PointmapError(f"no such file or folder: {item}{glob}")
        else:
            out.append(item)
    return out


def parse_export(text: str) -> tuple[str, ...]:
    """``--export``: comma-separated formats of ``pointmap.io.FORMATS`` ("colmap-txt" is read as "colmap_txt")."""
    from pointmap.io import FORMATS

    formats = tuple(f.strip().replace("-", "_") for f in text.split(",") if f.strip())
    bad = [f for f in formats if f not in FORMATS]
    if not formats or bad:
        raise PointmapError(f"--export expected comma-separated formats from {', '.join(FORMATS)}, got {text!r}")
    return formats


def refuse_shared_keys(images: list[str], keys: list[str], matched, flag: str, by: str) -> None:
    """PointmapError when two of ``images`` that a file of ``flag`` matches (indices ``matched``) share the key
    ``keys[k]`` it matches them by (``by``): two photographs would get one entry (one camera, one mask)."""
    first: dict = {}
    for k in matched:
        other = first.setdefault(keys[k], k)
        if other != k:
            raise PointmapError(f"{flag} matches images by {by}, and {images[other]} and {images[k]} are both "
                                f"{keys[k]!r}: they would get one entry; rename one, or give them in separate runs")


def is_colmap_path(path: str) -> bool:
    """Whether ``--cameras`` names a COLMAP model (a folder, or one of the model's files) rather than a
    transforms.json."""
    from pointmap.io.colmap import MODEL_FILES

    return Path(path).is_dir() or Path(path).name in {f"{n}{s}" for n in MODEL_FILES for s in (".bin", ".txt")}


def cameras_from_file(path: str, images: list[str], poses: bool, given: list[str] | None = None):
    """``--cameras``: ({image index: K}, with ``poses`` {image index: cam2world} else None, {image index: lens
    Distortion}) for the images named in a nerfstudio transforms.json (``pointmap.io.nerfstudio.read_transforms``)
    or a COLMAP sparse model (a folder, or its cameras file: ``pointmap.io.colmap.read_colmap``), matched by file
    name: the image's, then that of the file it was converted from (``given``, e.g. ``IMG_0001.HEIC`` for
    ``converted/IMG_0001.jpg``), then the stem. PointmapError when no image is named there, a stated image size
    is not the image's, or the file gives poses alone without ``poses`` (nothing to use)."""
    from pointmap.images import image_sizes
    from pointmap.io.colmap import read_colmap
    from pointmap.io.nerfstudio import intrinsics_from_angle, read_transforms

    cams = read_colmap(path) if is_colmap_path(path) else read_transforms(path)
    names = [Path(p).name for p in images]
    # by file name; NeRF-synthetic files name frames without a suffix ("./train/r_0" for r_0.png)
    keys = [next((key for key in (nm, Path(orig).name, Path(nm).stem) if key in cams), None)
            for nm, orig in zip(names, given or images)]
    matched = {k: cams[key] for k, key in enumerate(keys) if key is not None}
    refuse_shared_keys(images, keys, matched, "--cameras", "file name")
    if not matched:
        raise PointmapError(f"--cameras {path} names none of the {len(names)} images (it has "
                            f"{', '.join(sorted(cams)[:4])}{', ...' if len(cams) > 4 else ''}; the images are "
                            f"{', '.join(names[:4])}{', ...' if len(names) > 4 else ''})")
    sizes = image_sizes([images[k] for k in matched])
    for (k, cam), wh in zip(matched.items(), sizes):
        if cam["size"] is not None and tuple(cam["size"]) != tuple(wh):
            raise PointmapError(f"--cameras {path} states {cam['size'][0]}x{cam['size'][1]} for {names[k]}, but the "
                                f"image is {wh[0]}x{wh[1]} (EXIF orientation applied): the intrinsics would not fit")
    K = {k: cam["K"] if cam["K"] is not None else intrinsics_from_angle(cam["camera_angle_x"], *wh)
         for (k, cam), wh in zip(matched.items(), sizes) if cam["K"] is not None or cam["camera_angle_x"]} or None
    distortions = {k: cam["distortion"] for k, cam in matched.items() if cam.get("distortion") is not None}
    if K is None and not poses:  # it would change nothing (and it turned off the shared focal of a video)
        raise PointmapError(f"--cameras {path} gives no intrinsics for the images it names, only poses: pass "
                            "--known-poses to use them, or drop --cameras")
    return K, ({k: cam["cam2world"] for k, cam in matched.items()} if poses else None), distortions


def masks_from_folder(folder: str, images: list[str]) -> list:
    """``--masks``: one mask per image from ``folder``, the file with the image's stem and an image suffix
    (``IMAGE_SUFFIXES``), nonzero = keep (a mask with transparency, e.g. a background remover's cut-out: its
    pixels of alpha > 0, whatever their colour), at the image's original size (EXIF orientation applied) or the
    network's; an image without a mask file keeps every pixel. PointmapError for a folder that is missing or holds no mask of
    any of the images."""
    import numpy as np

    from pointmap.images import image_sizes

    root = Path(folder)
    if not root.is_dir():
        raise PointmapError(f"--masks expected a folder of mask images, got {folder!r}")
    by_stem = {f.stem: f for f in sorted(root.iterdir()) if f.suffix.lower() in IMAGE_SUFFIXES}
    found = [by_stem.get(Path(p).stem) for p in images]
    refuse_shared_keys(images, [Path(p).stem for p in images], [k for k, f in enumerate(found) if f], "--masks",
                       "file name without suffix")
    if not any(found):
        raise PointmapError(f"--masks {folder} holds no mask named like the images ({Path(images[0]).stem}.png, ...)")
    masks = []
    for (w, h), f in zip(image_sizes(images), found):
        if f is None:
            masks.append(np.ones((h, w), bool))
            continue
        from PIL import Image

        from pointmap.images import upright

        try:
            with Image.open(f) as im:
                im = upright(im)  # turned by its EXIF as the photographs are, a malformed block too
                alpha = np.asarray(im.convert("RGBA"))[..., 3] if im.mode in ("RGBA", "LA", "PA") or \
                    "transparency" in im.info else None
                if alpha is not None and (alpha < 255).any():  # a cut-out: its visible pixels, dark ones too
                    masks.append(alpha > 0)
                else:
                    masks.append(np.asarray(im.convert("L")) > 0)
        except (OSError, SyntaxError) as e:  # PIL's UnidentifiedImageError is an OSError
            raise ImageError(f"--masks: {f} is not a readable image ({e.__class__.__name__})") from None
    return masks


def depths_from_folder(folder: str, images: list[str], png_scale: float) -> list:
    """``--metric-depth``: one depth map per image from ``folder`` (``<image stem>.npy`` or a 16-bit ``.png`` times
    ``png_scale``; ``pointmap.io.depth``), None for an image without one. PointmapError for a folder that is missing
    or holds no depth map of any of the images."""
    from pointmap.io.depth import depth_file, read_depth, same_aspect

    if not Path(folder).is_dir():
        raise PointmapError(f"--metric-depth expected a folder of depth maps, got {folder!r}")
    if not png_scale > 0:
        raise PointmapError(f"--depth-png-scale expected > 0, got {png_scale}")
    from pointmap.images import image_sizes

    found = [depth_file(folder, Path(p).stem) for p in images]
    if not any(found):
        raise PointmapError(f"--metric-depth {folder} holds no depth map named like the images "
                            f"({Path(images[0]).stem}.npy or .png, ...)")
    depths = [None if f is None else read_depth(f, png_scale) for f in found]
    for (w, h), d, f in zip(image_sizes(images), depths, found):  # checked now, not after inference
        if d is not None and not same_aspect(d.shape[::-1], (w, h)):
            raise PointmapError(f"--metric-depth: {f} is {d.shape[1]}x{d.shape[0]}, not the aspect ratio of its "
                                f"photograph ({w}x{h}, EXIF orientation applied)")
    return depths


def cmd_reconstruct(args) -> int:
    # every argument is checked before the model runs: nothing fails after minutes of inference
    from pointmap.io.points import check_conf_filter
    from pointmap.video import is_video

    formats = parse_export(args.export)
    video = not args.each_folder and any(is_video(i) for i in args.images)
    refuse_ignored(args, [
        ("stride", "--stride", video, "to a video among IMG"),
        ("max_frames", "--max-frames", video and args.stride is None, "to a video among IMG, without --stride "
         "(which sets the frames itself)"),
        ("depth_png_scale", "--depth-png-scale", args.metric_depth is not None, "with --metric-depth"),
        ("splat_budget", "--splat-budget", args.splat, "with --splat"),
        ("colmap_points", "--colmap-points", bool({"colmap", "colmap_txt", "nerfstudio"} & set(formats)),
         "to the colmap, colmap_txt and nerfstudio exports"),
        ("max_points", "--max-points", bool({"ply", "glb"} & set(formats)), "to the ply and glb exports")])
    fill_defaults(args, max_frames=MAX_FRAMES, depth_png_scale=DEPTH_PNG_SCALE, splat_budget=SPLAT_BUDGET,
                  colmap_points=COLMAP_POINTS, max_points=0)
    check_size_graph_budget(args)
    check_conf_filter(args.min_conf, args.conf_percentile, ("--min-conf", "--conf-percentile"))
    if args.max_points < 0 or args.colmap_points < 0:
        raise PointmapError(f"--max-points and --colmap-points expected >= 0 (0: all), got {args.max_points} and "
                            f"{args.colmap_points}")
    if (args.stride is not None and args.stride < 1) or args.max_frames < 2:
        raise PointmapError(f"--stride expected >= 1 and --max-frames >= 2, got {args.stride} and {args.max_frames}")
    if args.cameras is not None and args.focal is not None:
        raise PointmapError("--cameras and --focal both give intrinsics: use one")
    if args.known_poses and args.cameras is None:
        raise PointmapError("--known-poses holds the poses of --cameras FILE fixed: give --cameras")
    if args.pairs is not None and args.graph != "auto":
        raise PointmapError(f"--pairs and --graph {args.graph} both choose the pairs: use one")
    if args.metric_depth is not None and args.known_poses:
        raise PointmapError("--metric-depth scales the reconstruction to measured depth, but --known-poses already "
                            "fixes its scale to the poses': use one")
    if args.cache_half and args.cache is None:
        raise PointmapError("--cache-half sets how --cache DIR stores predictions: give --cache")
    if args.head_prior is not None and not (math.isfinite(args.head_prior) and args.head_prior >= 0):
        raise PointmapError(f"--head-prior expected a finite weight >= 0 (0: off), got {args.head_prior}")
    if args.cache is not None:
        writable_dir(Path(args.cache).expanduser(), "--cache")
    if not args.each_folder:
        scene = prepare_scene(args, args.images, Path(args.out))  # the inputs checked before the model loads
        model, size = _model_and_size(args.model, args.size, args.device)
        refuse_head_prior_without_pose_head(args, model)
        return reconstruct_scene(model, size, args, scene, formats, prediction_cache(args, model))
    if len(args.images) != 1 or not Path(args.images[0]).is_dir():
        raise PointmapError(f"--each-folder expected one folder whose sub-folders are scenes, got {args.images}")
    if any(p is not None and Path(p).is_absolute() for p in (args.cameras, args.masks, args.pairs,
                                                              args.metric_depth)) or \
            (args.focal is not None and "," in args.focal):
        raise PointmapError("--each-folder takes --cameras, --masks, --pairs and --metric-depth relative to each scene "
                            "folder (e.g. --cameras sparse/0, --masks masks, --pairs pairs.txt, --metric-depth depth): "
                            "an absolute path or per-image --focal would apply one scene's files to every scene (a "
                            "single --focal for all is accepted)")
    out_root = writable_dir(Path(args.out)).resolve()
    scenes = sorted(d for d in Path(args.images[0]).iterdir()  # hidden, __MACOSX-like and the output skipped
                    if d.is_dir() and not d.name.startswith((".", "__")) and d.resolve() != out_root)
    if not scenes:
        raise PointmapError(f"--each-folder: {args.images[0]} has no sub-folders")
    model, size = _model_and_size(args.model, args.size, args.device)  # loaded once for every scene
    refuse_head_prior_without_pose_head(args, model)
    cache = prediction_cache(args, model)  # its weights hashed once too
    failed = []
    for scene in scenes:
        print(f"scene {scene.name}", file=sys.stderr)
        own = argparse.Namespace(**{**vars(args), **{k: str(scene / getattr(args, k))
                                                      for k in ("cameras", "masks", "pairs", "metric_depth")
                                                      if getattr(args, k) is not None}})  # the scene's own files
        try:
            reconstruct_scene(model, size, own, prepare_scene(own, [str(scene)], Path(args.out) / scene.name),
                              formats, cache)
        except Exception as e:  # one bad scene does not stop the others (KeyboardInterrupt still does)
            print(f"pointmap: scene {scene.name} skipped: {e.__class__.__name__}: {e}", file=sys.stderr)
            failed.append(scene.name)
    if failed:
        print(f"pointmap: {len(failed)} of {len(scenes)} scenes failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


def writable_dir(out: Path, flag: str = "-o") -> Path:
    """``out`` if it is, or can be made, a writable folder (checked without creating it, before any model runs);
    PointmapError naming ``flag`` otherwise."""
    out = Path(out)
    probe = out
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        what = "is a file" if probe == out else f"cannot be made: {probe} is a file"
        raise PointmapError(f"{flag} expected a folder to write into, got {str(out)!r}, which {what}")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise PointmapError(f"{flag} expected a folder to write into, got {str(out)!r}: {probe} is not writable")
    return out


def pairs_from_file(path: str, images: list[str], given: list[str] | None = None) -> list[tuple[int, int]]:
    """``--pairs FILE``: one pair of photographs per line, two names separated by white space (the pairs format of
    hloc and COLMAP's custom matching; blank lines and lines starting with # are skipped). A name is an image's path
    as given or found, its path from the folder it was read from, or its file name when that is unique; the same of
    the file it was converted from (``given``, e.g. ``IMG_0001.HEIC`` for ``converted/IMG_0001.jpg``) name it too.
    Returns index pairs into ``images`` (``pm.reconstruct`` checks that they connect every image); PointmapError
    naming the line otherwise."""
    try:
        lines = Path(path).read_text(encoding="utf-8-sig").splitlines()  # -sig: a Windows editor's byte-order mark
    except (OSError, UnicodeDecodeError) as e:
        raise PointmapError(f"--pairs expected a text file of image name pairs, got {path!r} ({e})") from None
    exact: dict[str, int] = {}  # a photograph's own path, as given and resolved, names it first
    found: dict[str, set] = {}  # then any tail of its path: "b.jpg", "photos/b.jpg", ...
    for k, img in [*enumerate(images), *enumerate(given or [])]:
        p = Path(os.path.normpath(img))
        for key in (p.as_posix(), p.resolve().as_posix()):
            exact.setdefault(key, k)
        for d in range(1, len(p.parts) + 1):
            found.setdefault("/".join(p.parts[-d:]), set()).add(k)
    index = {key: next(iter(ks)) for key, ks in found.items() if len(ks) == 1}  # an ambiguous tail names nothing
    index.update(exact)

    def lookup(name: str):
        return index.get(Path(os.path.normpath(name)).as_posix())

    hint = min((key for key, k in index.items() if k == 0), key=len)  # the shortest name of the first photograph
    pairs = []
    for no, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        parts = text.split()
        if len(parts) != 2:
            raise PointmapError(f"--pairs {path}, line {no}: expected two image names, got {text!r}")
        missing = [q for q in parts if lookup(q) is None]
        if missing:
            what = ("names several" if len(found.get(Path(os.path.normpath(missing[0])).as_posix(), ())) > 1
                    else "is none")
            raise PointmapError(f"--pairs {path}, line {no}: {missing[0]!r} {what} of the {len(images)} photographs "
                                f"(a path, or a tail of one that only one has, e.g. {hint!r})")
        i, j = lookup(parts[0]), lookup(parts[1])
        if i == j:
            raise PointmapError(f"--pairs {path}, line {no}: a photograph paired with itself ({text!r})")
        pairs.append((i, j))
    if not pairs:
        raise PointmapError(f"--pairs {path}: no pairs in the file")
    return pairs


def video_timestamps(inputs: list[str], images: list[str], times: dict) -> list[float] | None:
    """Each image's time in seconds (``times``, from ``expand_images``) when the input is one video: what a TUM
    trajectory is matched against ground truth by. None for photographs, several videos (two clocks), or a video
    whose frames have no time (trajectories then count images)."""
    from pointmap.video import is_video

    if len(inputs) != 1 or not is_video(inputs[0]) or any(times.get(i) is None for i in images):
        return None
    return [times[i] for i in images]


def check_cameras_path(path: str | None) -> None:
    """``--cameras``: PointmapError when it is given and names nothing on disk (said before frames are read)."""
    if path is not None and not Path(path).exists():
        raise PointmapError(f"--cameras expected a transforms.json file or a COLMAP model folder, got {path!r}")


def prepare_scene(args, inputs: list[str], out: Path) -> dict:
    """A scene's inputs (files, folders, a video) read and checked without the model: the image paths, the pair
    graph, known K / poses (``--cameras``, ``--focal``) and masks, for ``reconstruct_scene``."""
    from pointmap.pipeline import auto_graph
    from pointmap.video import is_video

    writable_dir(out)
    check_cameras_path(args.cameras)
    if args.masks is not None and not Path(args.masks).is_dir():
        raise PointmapError(f"--masks expected a folder of mask images, got {args.masks!r}")
    video = any(is_video(i) for i in inputs)
    times: dict = {}
    videos: dict = {}
    given = expand_images(inputs, out / "frames", args.stride, args.max_frames, times, videos)
    images = convert_heif(given, out / "converted", args.quiet)  # a --cameras or --pairs file may name either
    if len(images) < 2:  # said now, before the model loads, and for a video in its own terms
        how = ("" if not video else f"; the video gave {len(images)} frame(s) at --stride {args.stride}: a smaller "
               "--stride keeps more" if args.stride is not None else f"; the video holds {len(images)} frame(s)")
        raise PointmapError(f"a reconstruction needs at least 2 images, got {len(images)} from {inputs}{how}")
    timestamps = video_timestamps(inputs, images, times)
    graph = args.graph
    if video and graph == "auto":  # frames in time order: sequential windows, no wrap-around pairs
        graph = auto_graph(len(images), sequential=True)
    if args.pairs is not None:  # the user's own pairs (e.g. a retrieval's), checked now: indices and connectivity
        from pointmap.pairs import pairs_from_list

        try:
            graph = pairs_from_list(len(images), pairs_from_file(args.pairs, [str(i) for i in images], given))
        except GraphError as e:  # e.g. pairs that leave a photograph out: said with the file's name
            raise PointmapError(f"--pairs {args.pairs}: {e}") from None
    elif isinstance(graph, str) and graph != "auto" and not graph.startswith("retrieval"):
        from pointmap.pairs import make_pairs

        try:  # a graph that does not fit this many images is said now, before the model loads
            make_pairs(len(images), graph)
        except (GraphError, ValueError) as e:
            raise PointmapError(f"--graph {graph}: {e}") from None
    K, cam2world, distortions = None, None, {}
    if args.cameras is not None:
        K, cam2world, distortions = cameras_from_file(args.cameras, images, args.known_poses, given)
    # one focal per camera: for all the images with --shared-focal; with no focal given, for each video's frames and
    # for the photographs of each camera by their EXIF (--no-shared-focal: one focal per image)
    estimated = args.focal is None and K is None  # (a --cameras file of poses alone leaves the focals to estimate)
    shared = False if not estimated else shared_focals(images, videos, note_focal=not args.quiet,
                                                       note_cameras=not args.quiet and args.shared_focal is None)
    if args.shared_focal is not None:
        shared = args.shared_focal
    if args.focal is not None:  # known focal(s), principal point at each image's centre (original pixels)
        focal = parse_focals(args.focal, images)
        if shared and len(set(focal)) > 1:
            raise PointmapError(f"--shared-focal says one camera, but --focal gives {len(set(focal))} different "
                                f"focals ({args.focal}); give one value or drop --shared-focal")
        K = K_from_focals(images, focal)
    if shared is True:  # one camera: one image size (said with the flag, and before the model loads)
        from pointmap.images import image_sizes

        by_size: dict = {}
        for img, (w, h) in zip(images, image_sizes(images)):
            by_size.setdefault(f"{w}x{h}", []).append(Path(img).name)
        if len(by_size) > 1:
            raise PointmapError("--shared-focal expected the images of one camera, all of one size (EXIF orientation "
                                "applied), got " + "; ".join(f"{size}: {', '.join(names[:3])}"
                                                             f"{', ...' if len(names) > 3 else ''}"
                                                             for size, names in by_size.items()))
    refuse_overwriting_inputs(args.cameras, images, distortions, out, parse_export(args.export))
    masks = masks_from_folder(args.masks, images) if args.masks is not None else None
    depths = depths_from_folder(args.metric_depth, images, args.depth_png_scale) \
        if args.metric_depth is not None else None
    if depths is not None and distortions:
        raise PointmapError("--metric-depth: the photographs have lens distortion (--cameras) and are undistorted "
                            "first, but their depth maps are not: undistort both beforehand")
    if distortions:  # lens distortion undone first: the model, the aligner and every export take pinhole cameras
        from pointmap.undistort import undistort_photos

        images, K, masks = undistort_photos(images, K, distortions, out / "undistorted", masks)
        if not args.quiet:
            print(f"pointmap: {len(distortions)} photograph(s) with lens distortion resampled onto pinhole cameras in "
                  f"{out / 'undistorted'}", file=sys.stderr)
    return {"images": images, "graph": graph, "K": K, "cam2world": cam2world, "masks": masks, "out": out,
            "depths": depths, "timestamps": timestamps, "shared_focal": shared}


def refuse_overwriting_inputs(cameras: str | None, images: list[str], distortions: dict, out: Path,
                              formats) -> None:
    """PointmapError, before the model loads, when the exports into ``out`` would replace the inputs: the
    ``--cameras`` COLMAP model (the colmap / colmap_txt exports write ``out/sparse/0``) or transforms.json (the
    nerfstudio export), or a photograph with lens distortion whose undistorted copy the COLMAP and nerfstudio
    exports would write over it in ``out/images`` (``-o`` the scene folder the photographs came from)."""
    def same(a: Path, b: Path) -> bool:
        return a.exists() and b.exists() and a.resolve() == b.resolve()

    replaced = []
    if cameras is not None:
        from pointmap.io.colmap import colmap_model_folder

        model = colmap_model_folder(cameras) if is_colmap_path(cameras) else None
        if model is not None and {"colmap", "colmap_txt"} & set(formats) and same(model, out / "sparse" / "0"):
            replaced.append(f"the --cameras model {model}")
        if model is None and "nerfstudio" in formats and same(Path(cameras), out / "transforms.json"):
            replaced.append(f"the --cameras file {cameras}")
    if {"colmap", "colmap_txt", "nerfstudio"} & set(formats):
        originals = [images[k] for k in sorted(distortions) if same(Path(images[k]), out / "images" / Path(images[k]).name)]
        if originals:
            replaced.append(f"the photograph(s) {', '.join(originals[:3])}{', ...' if len(originals) > 3 else ''} "
                            "(their undistorted copies would be written over them)")
    if replaced:
        raise PointmapError(f"-o {out} would overwrite the inputs: {'; '.join(replaced)}; give another output folder, "
                            f"or --export without {', '.join(f for f in ('colmap', 'colmap_txt', 'nerfstudio') if f in formats)}")


def prediction_cache(args, model):
    """``--cache DIR`` (``--cache-half``): the PredictionCache of ``model``, or None."""
    if args.cache is None:
        return None
    import torch

    from pointmap.cache import PredictionCache

    return PredictionCache(args.cache, model, torch.float16 if args.cache_half else torch.float32)


def reconstruct_scene(model, size: int, args, scene: dict, formats, cache=None) -> int:
    """One prepared scene (``prepare_scene``) through ``pm.reconstruct`` to its exports (and splats)."""
    from pointmap.align import AlignConfig
    from pointmap.pipeline import reconstruct

    align = AlignConfig(shared_focal=scene["shared_focal"], init=args.align_init, quiet=args.quiet,
                        **({} if args.head_prior is None else {"head_prior": args.head_prior}))
    recon = reconstruct(model, scene["images"], graph=scene["graph"], size=size, K=scene["K"],
                        cam2world=scene["cam2world"], masks=scene["masks"], min_conf=args.min_conf,
                        conf_percentile=args.conf_percentile, align=align, refine=args.refine,
                        epipolar=not args.no_epipolar, quiet=args.quiet, device=args.device, cache=cache,
                        whole=args.whole)
    if scene.get("depths") is not None:  # into the measured depth's units
        from pointmap.align.gauge import scale_to_depth

        try:
            recon, report = scale_to_depth(recon, scene["depths"])
        except PointmapError as e:  # e.g. too few pixels with both depths: the reconstruction is saved unscaled
            print(f"pointmap: warning: --metric-depth not applied, the reconstruction keeps its own scale: {e}",
                  file=sys.stderr)
        else:
            recon.info["metric_depth"] = report
            if not args.quiet:
                print(f"pointmap: scaled by {report['scale']:.4g} to the measured depth of {report['images']} "
                      f"image(s) ({report['pixels']} pixels; per-pixel scatter {100 * report['spread']:.1f}%)",
                      file=sys.stderr)
    if scene.get("timestamps") is not None:  # one video's frames: the TUM trajectory's times are the frames' own
        recon.info["timestamps"] = scene["timestamps"]
    out = scene["out"]
    written = recon.save(out, formats=formats, max_points=args.max_points or None,
                         colmap_max_points=args.colmap_points or None)
    if args.splat:
        from pointmap.splat import run as run_splat

        written = {**(written or {}), **quiet_splat_path(run_splat(recon, out / "splat", quiet=args.quiet,
                                                                   time_budget=args.splat_budget or None), args)}
    for fmt, paths in (written or {}).items():
        for path in paths if isinstance(paths, (list, tuple)) else [paths]:
            print(f"{fmt}: {path}")
    return 0


def quiet_splat_path(result, args) -> dict:
    """{"splat": the splat PLY} to print under ``--quiet``, which silences the fit's own summary line (it names
    the file) but not where the output went; {} otherwise."""
    ply = ((result or {}).get("paths") or {}).get("ply")
    return {"splat": ply} if args.quiet and ply else {}


def reconstruction_npz(recon: str) -> Path:
    """The reconstruction.npz a command reads: the file itself, or the one in a folder ``pointmap reconstruct``
    wrote. PointmapError when there is none."""
    src = Path(recon)
    npz = src / "reconstruction.npz" if src.is_dir() else src
    if not npz.is_file():
        raise PointmapError(f"no reconstruction.npz in {src} (write one with: pointmap reconstruct ... --export npz)")
    return npz


def cmd_splat(args) -> int:
    from pointmap.io import load_npz
    from pointmap.splat import run as run_splat

    npz = reconstruction_npz(args.recon)
    refuse_ignored(args, [(dest, flag, bool(args.test), "with --test (the held-out views)")  # --device is every
                          for dest, flag in (("test_align_steps", "--test-align-steps"), ("model", "--model"))])  # command's
    fill_defaults(args, test_align_steps=TEST_ALIGN_STEPS, model=DEFAULT_MODEL)
    check_size_graph_budget(args)
    if args.test_align_steps < 0:
        raise PointmapError(f"--test-align-steps expected >= 0, got {args.test_align_steps}")
    recon = load_npz(npz)
    out = writable_dir(Path(args.out or npz.parent / "splat"))
    if args.test:  # the test views and the model are read before the fit, which takes minutes
        from pointmap.checkpoint import load_model
        from pointmap.localization import query_views
        from pointmap.runtime.onnx import OnnxPointmapModel

        every = query_views(recon, expand_images(args.test, out / "test_frames"))  # a video: up to 30 frames
        model = load_model(args.model, device=args.device)
        if isinstance(model, OnnxPointmapModel) and not model.split:  # refused now, not after the fit
            raise CheckpointError(f"splat --test localizes the test views by the encoder's tokens, which a "
                                  f"single-graph ONNX export ({args.model}) does not give: export with --split, or "
                                  f"use the PyTorch weights")
    result = run_splat(recon, out, quiet=args.quiet, time_budget=args.splat_budget or None)
    for fmt, path in quiet_splat_path(result, args).items():
        print(f"{fmt}: {path}")
    if args.test:  # held-out views: localized against the refined cameras the splats were fit to, then scored
        import torch

        from pointmap.localization import localize
        from pointmap.reconstruction import K_to_map
        from pointmap.splat.outputs import evaluate_views

        refined = result.get("recon_refined")
        try:
            loc = localize(model, recon if refined is None else refined, every, quiet=args.quiet, device=args.device)
        except PointmapError as e:
            raise PointmapError(f"{e}; the splat itself is written to {out}, without test scores") from None
        posed = [k for k, r in enumerate(loc.ref) if r >= 0]
        if len(posed) < len(every):
            print(f"pointmap: {len(every) - len(posed)} test view(s) could not be localized and are left out: "
                  f"{', '.join(loc.names[k] for k in range(len(every)) if k not in posed)}", file=sys.stderr)
        views = [every[k] for k in posed]
        K_map = K_to_map(loc.K[posed], torch.tensor([v.map_from_original for v in views], dtype=torch.float64))
        evaluate_views(result["fit"], [v.img.permute(1, 2, 0) for v in views], loc.cam2world[posed], K_map,
                       out / "renders", align_steps=args.test_align_steps, names=[v.name for v in views],
                       quiet=args.quiet)
        print(f"test views: {out / 'renders' / 'test_views.json'}")
    return 0


def cmd_localize(args) -> int:
    import json

    from pointmap.atomic import atomic_open
    from pointmap.checkpoint import load_model
    from pointmap.io import load_npz
    from pointmap.io.tum import write_tum
    from pointmap.localization import localize
    from pointmap.video import is_video

    npz = reconstruction_npz(args.recon)
    if args.n_refs < 1:
        raise PointmapError(f"--n-refs expected >= 1, got {args.n_refs}")
    if args.cameras is not None and args.focal is not None:
        raise PointmapError(f"--cameras and --focal both give the queries' intrinsics ({args.cameras}; {args.focal}): "
                            "use one")
    check_cameras_path(args.cameras)
    video = any(is_video(i) for i in args.images)
    refuse_ignored(args, [("stride", "--stride", video, "to a video among IMG"),
                          ("max_frames", "--max-frames", video and args.stride is None,
                           "to a video among IMG, without --stride (which sets the frames itself)")])
    fill_defaults(args, max_frames=MAX_FRAMES)
    if (args.stride is not None and args.stride < 1) or args.max_frames < 1:  # one frame can be localized
        raise PointmapError(f"--stride expected >= 1 and --max-frames >= 1, got {args.stride} and {args.max_frames}")
    if Path(args.out).resolve() == npz.parent.resolve():  # its trajectory.txt and a video's frames/ are the recon's
        raise PointmapError(f"-o {args.out} is the reconstruction's own folder: localize writes trajectory.txt (and a "
                            f"video's frames/) there and would replace the reconstruction's; give another folder")
    out = writable_dir(Path(args.out))
    frame_times: dict = {}
    images = expand_images(args.images, out / "frames", args.stride, args.max_frames, frame_times)
    times = video_timestamps(args.images, images, frame_times)
    K = None if args.focal is None else K_from_focals(images, parse_focals(args.focal, images))
    if args.cameras is not None:
        images, K = query_cameras(args.cameras, images, out)
    recon = load_npz(npz)
    loc = localize(load_model(args.model, device=args.device), recon, images, K=K, n_refs=args.n_refs,
                   quiet=args.quiet, device=args.device)
    rows = [{"name": name, "reference": None, "cam2world": None, "K": None, "confidence": None, "scale": None}
            if loc.ref[k] < 0 else  # not posed: null, not NaN (strict JSON)
            {"name": name, "reference": recon.names[loc.ref[k]], "cam2world": loc.cam2world[k].tolist(),
             "K": loc.K[k].tolist(), "confidence": loc.conf[k], "scale": loc.scale[k]}
            for k, name in enumerate(loc.names)]
    with atomic_open(out / "localization.json", "w") as f:
        json.dump({"reconstruction": str(npz), "queries": rows}, f, indent=1, allow_nan=False)
    posed = [k for k, r in enumerate(loc.ref) if r >= 0]
    write_tum(loc.subset(posed), out / "trajectory.txt",
              timestamps=posed if times is None else [times[k] for k in posed])
    for row in rows:
        print(f"{row['name']}: " + (f"posed against {row['reference']} (confidence {row['confidence']:.2f})"
                                    if row["reference"] else "not posed"))
    print(f"localization: {out / 'localization.json'}\ntum: {out / 'trajectory.txt'}")
    return 0


def query_cameras(path: str, images: list[str], out: Path):
    """``localize --cameras``: (the queries, lens distortion undone into ``out/undistorted``; their [M, 3, 3] K in
    original pixels) from a transforms.json or COLMAP model (``cameras_from_file``) that must name every query and
    give its intrinsics. PointmapError, before the model loads, for a file that leaves a query without them."""
    import torch

    K, _, distortions = cameras_from_file(path, images, poses=False)
    missing = [Path(images[k]).name for k in range(len(images)) if K is None or k not in K]
    if missing:
        raise PointmapError(f"--cameras {path} gives no intrinsics for {len(missing)} of the {len(images)} "
                            f"photographs ({', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''}): localize "
                            "takes every query's camera from it; give --focal instead, or localize those apart")
    if distortions:  # the network and the pose take pinhole cameras, as in reconstruct
        from pointmap.undistort import undistort_photos

        images, K, _ = undistort_photos(images, K, distortions, out / "undistorted")
    return images, torch.stack([torch.as_tensor(K[k], dtype=torch.float64) for k in range(len(images))])


def model_summary(model, source: str) -> dict:
    """What ``pointmap info`` reports of a loaded model: its architecture, input size, licence and provenance."""
    from pointmap.checkpoint import model_input_size, model_licence, shipped_path

    cfg, prov = model.cfg, (getattr(model, "provenance", None) or {})
    path = shipped_path(source) or Path(source)  # the file load_model read
    params = sum(p.numel() for p in model.parameters()) if hasattr(model, "parameters") else None
    # an ONNX graph's weights may lie beside it (external data): a folder counts whole, a file with its .data
    files = sorted(path.glob("*")) if path.is_dir() else [path, path.with_name(path.name + ".data")]
    return {"source": source, "path": str(path.resolve()), "megabytes": round(sum(f.stat().st_size for f in files
                                                                                 if f.is_file()) / 1e6, 1),
            "runtime": type(model).__name__, "parameters": params, "input_size": model_input_size(model, 512),
            "licence": model_licence(model), "config": cfg.to_dict(), "provenance": prov}


def cmd_info(args) -> int:
    import json

    from pointmap.checkpoint import load_model

    info = model_summary(load_model(args.model), args.model)
    if args.json:
        print(json.dumps(info, indent=1, default=str))
        return 0
    cfg, prov = info["config"], info["provenance"]
    lines = [f"model: {info['source']} ({info['path']}, {info['megabytes']} MB, {info['runtime']})",
             f"architecture: encoder {cfg['enc_depth']} x {cfg['enc_dim']} ({cfg['enc_heads']} heads), decoder "
             f"{cfg['dec_depth']} x {cfg['dec_dim']}, patch {cfg['patch_size']}, head {cfg['head']}, descriptors "
             f"{cfg['desc_dim'] or 'none'}, pose head {'yes' if cfg.get('pose_head') else 'no'}"
             + (f"; {info['parameters'] / 1e6:.1f} M parameters" if info["parameters"] else ""),
             f"input size: {info['input_size']}",
             f"licence: {info['licence'] or 'not recorded in the file (see its model card)'}"]
    if prov.get("source") == "official":
        lines.append(f"source: official checkpoint, {prov.get('ctor', '')[:100]}")
    if "steps" in prov:
        lines.append(f"trained: {prov['steps']} steps, batch {prov.get('batch_size', '?')}, data "
                     f"{prov.get('data') or '?'}" + (f"; averaged over {len(prov['averaged'])} inputs"
                                                     if prov.get("averaged") else ""))
    m = prov.get("heldout_metrics") or prov.get("heldout_metrics_of_input") or {}
    if m:
        whose = "the run" if prov.get("heldout_metrics") else "one averaged input,"
        lines.append(f"held-out ({prov.get('eval_data') or '?'}, {whose} at step {int(m.get('step', 0))}): "
                     + ", ".join(f"{k} {m[k]:.3g}" for k in ("RRA15", "RTA15", "AbsRel", "match_prec") if k in m))
    if prov.get("note"):
        lines.append(f"note: {prov['note']}")
    print("\n".join(lines))
    return 0


def cmd_demo(args) -> int:
    from pointmap.demo import run_demo

    return run_demo(writable_dir(Path(args.out)), model_name=args.model, quiet=args.quiet, device=args.device)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="pointmap", description="Feed-forward 3D reconstruction from photos.")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("-v", "--verbose", action="store_true", help="log details")
    # the same flags after the command (pointmap reconstruct ... --quiet); SUPPRESS keeps the top-level value
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", action="store_true", default=argparse.SUPPRESS, help="no progress bars")
    common.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS, help="log details")
    sub = p.add_subparsers(dest="cmd", required=True)

    a = sub.add_parser("pair", parents=[common], help="pointmaps, matches and relative pose of two images")
    a.add_argument("images", nargs=2, metavar="IMG")
    a.add_argument("-o", "--out", required=True, help="output folder (pair.npz, pair.ply and PNG previews)")
    a.add_argument("--model", default=DEFAULT_MODEL, help="shipped model name, .safetensors, official .pth or ONNX")
    a.add_argument("--size", type=int, default=None,
                   help="network input size: 224, or a multiple of 16 up to 2048 (e.g. 512); default: the model's")
    a.add_argument("--focal", default=None, metavar="F[,F2]|exif",
                   help="known focal length(s) in original pixels, or exif: each photograph's from its EXIF 35 mm-"
                        "equivalent focal length (principal point at the centre): stored instead "
                        "of the estimate, and the pose is refined on the model's matches with them (without it: "
                        "with the focals estimated from the pointmaps)")
    a.add_argument("--shared-focal", dest="shared_focal", action=argparse.BooleanOptionalAction, default=None,
                   help="the two photographs come from one camera (same size, same zoom): one estimated focal for "
                        "both. On by default when their EXIF says so (make, model, lens, focal length, zoom and "
                        "size); --no-shared-focal: one each")
    a.set_defaults(fn=cmd_pair)

    r = sub.add_parser("reconstruct", parents=[common], help="many images to poses, intrinsics and a dense cloud")
    r.add_argument("images", nargs="+", metavar="IMG",
                   help="image files, folders of them (sorted by name; a folder without images stands for its "
                        "images/), or a video (frames go to OUT/frames/)")
    r.add_argument("--each-folder", dest="each_folder", action="store_true",
                   help="batch: IMG is one folder whose sub-folders are scenes, reconstructed in turn with the model "
                        "loaded once, written to OUT/<sub-folder>; a failing scene is reported and skipped (exit 1). "
                        "--cameras and --masks are then paths inside each scene folder (e.g. sparse/0, masks)")
    r.add_argument("--stride", type=int, default=None,
                   help="video: keep one frame per STRIDE frames, the sharpest of each window (default: the "
                        "smallest stride giving at most --max-frames)")
    r.add_argument("--max-frames", dest="max_frames", type=int, default=None,
                   help=f"video: at most this many frames when --stride is not given (default {MAX_FRAMES})")
    r.add_argument("-o", "--out", required=True)
    r.add_argument("--model", default=DEFAULT_MODEL, help="shipped model name, .safetensors, official .pth or ONNX")
    r.add_argument("--size", type=int, default=None,
                   help="network input size: 224, or a multiple of 16 up to 2048 (e.g. 512); default: the model's")
    r.add_argument("--whole", action="store_true",
                   help="every photograph at its own shape, even at 224 (the long side to --size, e.g. 224x160 for a "
                        "4:3 landscape) instead of 224's square crop, which drops a quarter of a 4:3 photograph")
    r.add_argument("--graph", default="auto", help="auto, complete, swin-K, logwin-K, oneref-I, retrieval-K (each "
                   "image with its K most similar by the encoder: photos in no particular order)")
    r.add_argument("--pairs", default=None, metavar="FILE",
                   help="the pairs to run, one per line: two image names (hloc / COLMAP pairs format; a path or a "
                   "unique file name), e.g. from a retrieval; instead of --graph")
    r.add_argument("--cache", default=None, metavar="DIR",
                   help="keep the pair predictions in DIR; a later run with the same model and images reads them "
                   "instead of running the network (e.g. to align again with other settings)")
    r.add_argument("--cache-half", dest="cache_half", action="store_true",
                   help="store the cached predictions in float16 (half the disk; at 224 px a directed pair with "
                   "descriptors takes about 8 MB in float32)")
    r.add_argument("--export", default="ply,glb,colmap,npz",
                   help="comma-separated: ply (points.ply), glb (scene.glb), colmap (sparse/0/*.bin), colmap_txt "
                        "(sparse/0/*.txt), nerfstudio (transforms.json + sparse_pc.ply), tum (trajectory.txt), npz (reconstruction.npz, which "
                        "'pointmap splat' reads); the COLMAP and nerfstudio formats copy the photographs to images/")
    r.add_argument("--max-points", dest="max_points", type=int, default=None,
                   help="cap on the points of the PLY / GLB cloud, drawn at random (default 0: all)")
    r.add_argument("--colmap-points", dest="colmap_points", type=int, default=None,
                   help="cap on COLMAP's points3D and nerfstudio's sparse_pc.ply, the 3DGS initial cloud "
                        f"(default {COLMAP_POINTS}; 0: all)")
    r.add_argument("--focal", default=None, metavar="F[,F2,...]|exif",
                   help="known focal length in pixels of the images as given (one for all, or one per image; exif: "
                        "each photograph's from its EXIF 35 mm-equivalent focal length, as phones write it); the "
                        "principal point is taken at each image's centre. Alignment keeps them fixed, which steadies "
                        "the camera translations (docs/alignment.md)")
    r.add_argument("--cameras", default=None, metavar="FILE_OR_MODEL",
                   help="known cameras from a nerfstudio transforms.json (ours, or a phone app's: Polycam, "
                        "Record3D) or a COLMAP sparse model folder, matched to the images by file name: their "
                        "intrinsics are held fixed; photographs with lens distortion (OPENCV, RADIAL, fisheye) are "
                        "undistorted first (into OUT/undistorted)")
    r.add_argument("--known-poses", dest="known_poses", action="store_true",
                   help="also hold the poses of --cameras fixed (two or more spread-out ones fix the scale too)")
    r.add_argument("--metric-depth", dest="metric_depth", default=None, metavar="DIR",
                   help="measured depth maps (a LiDAR / RGB-D camera's, any resolution of the image's aspect), named "
                   "by image stem: .npy float z-depth, or 16-bit .png times --depth-png-scale; the reconstruction is "
                   "scaled to their units (median ratio, pm.scale_to_depth)")
    r.add_argument("--depth-png-scale", dest="depth_png_scale", type=float, default=None,
                   help=f"units per step of a 16-bit depth PNG (default {DEPTH_PNG_SCALE}: millimetres to metres)")
    r.add_argument("--shared-focal", dest="shared_focal", action=argparse.BooleanOptionalAction, default=None,
                   help="the images come from one camera (same size, same zoom): estimate one focal for all. By "
                        "default, when no focal is given, one for each video's frames, and one per camera for "
                        "photographs by their EXIF (make, model, lens, focal length, zoom and size); "
                        "--no-shared-focal: one per image")
    r.add_argument("--min-conf", dest="min_conf", type=float, default=None,
                   help="keep pixels whose confidence is above this (absolute, >= 1 for network output)")
    r.add_argument("--conf-percentile", dest="conf_percentile", type=float, default=None,
                   help="keep pixels at or above this percentile of confidence over all images' unmasked pixels "
                   "(0 <= P < 100; 50 keeps the most confident half of the scene)")
    r.add_argument("--masks", default=None, metavar="DIR",
                   help="a folder of masks named like the images (any image suffix; nonzero = keep, or in a cut-out "
                        "with transparency the pixels of alpha > 0): masked pixels "
                        "are left out of the alignment, the matches and the exports (sky, people, a turntable)")
    r.add_argument("--align-init", dest="align_init", default="averaging", choices=["averaging", "mst"],
                   help="the alignment's start: averaging (default: rotations, scales and centres averaged over every "
                        "pair) or mst (DUSt3R's spanning tree, one pair per image; drifts on long sequences)")
    r.add_argument("--head-prior", dest="head_prior", type=float, default=None, metavar="W",
                   help="weight of the pose heads' prior on the cameras during alignment (models with a pose head; "
                        "0: off; default: AlignConfig's; docs/alignment.md)")
    r.add_argument("--refine", action="store_true", help="sparse refinement on reciprocal matches after alignment")
    r.add_argument("--no-epipolar", dest="no_epipolar", action="store_true",
                   help="skip the pose refinement on the model's coarse matches that follows alignment (the poses "
                        "then come from the dense pointmaps alone)")
    r.add_argument("--splat", action="store_true", help="fit Gaussians after alignment")
    r.add_argument("--splat-budget", dest="splat_budget", type=float, default=None,
                   help=f"wall-clock seconds the splat fit may take (default {SPLAT_BUDGET:g}; 0: no limit)")
    r.set_defaults(fn=cmd_reconstruct)

    s = sub.add_parser("splat", parents=[common], help="fit Gaussian splats to a saved reconstruction")
    s.add_argument("recon", help="directory written by 'pointmap reconstruct', or its reconstruction.npz")
    s.add_argument("-o", "--out", default=None, help="output folder (default: splat/ beside the reconstruction.npz)")
    s.add_argument("--splat-budget", dest="splat_budget", type=float, default=SPLAT_BUDGET,
                   help=f"wall-clock seconds the fit may take (default {SPLAT_BUDGET:g}; 0: no limit)")
    s.add_argument("--test", nargs="+", default=None, metavar="IMG",
                   help="held-out photographs (or a video: up to 30 of its frames, written to test_frames/) to "
                        "score novel views on: each is localized in the reconstruction (pointmap localize), its pose "
                        "aligned on the splats, and its PSNR / SSIM reported (renders/test_views.json)")
    s.add_argument("--test-align-steps", dest="test_align_steps", type=int, default=None,
                   help=f"photometric pose-alignment steps per test view, Gaussians frozen (default {TEST_ALIGN_STEPS}; "
                        "0: the localized pose)")
    s.add_argument("--model", default=None, help=f"the network that localizes --test views (default {DEFAULT_MODEL})")
    s.set_defaults(fn=cmd_splat)

    loc = sub.add_parser("localize", parents=[common],
                         help="pose new photographs (or a video's frames) in a saved reconstruction's world")
    loc.add_argument("recon", help="directory written by 'pointmap reconstruct', or its reconstruction.npz")
    loc.add_argument("images", nargs="+", metavar="IMG", help="image files, folders of them, or a video")
    loc.add_argument("-o", "--out", required=True, help="folder for localization.json and trajectory.txt (TUM)")
    loc.add_argument("--model", default=DEFAULT_MODEL,
                     help="shipped model name, .safetensors, official .pth or ONNX (exported with --split: ranking "
                          "the references needs the encoder's tokens)")
    loc.add_argument("--focal", default=None, metavar="F[,F...]|exif",
                     help="known focal length(s) in original pixels, or exif: each photograph's from its EXIF "
                          "35 mm-equivalent focal length (principal point at the centre); default: "
                          "estimated from each pair")
    loc.add_argument("--cameras", default=None, metavar="FILE_OR_MODEL",
                     help="the queries' known intrinsics (and lens, undone first into OUT/undistorted) from a "
                          "nerfstudio transforms.json or a COLMAP sparse model that names every query by file name; "
                          "instead of --focal")
    loc.add_argument("--n-refs", dest="n_refs", type=int, default=2,
                     help="reconstruction views each photograph is paired with, the most similar by their encoder "
                          "tokens; the most similar pair that gives a pose is kept, the others are fallbacks (default 2)")
    loc.add_argument("--stride", type=int, default=None, help="video: one frame per STRIDE frames")
    loc.add_argument("--max-frames", dest="max_frames", type=int, default=None,
                     help=f"video: at most this many frames when --stride is not given (default {MAX_FRAMES})")
    loc.set_defaults(fn=cmd_localize)

    i = sub.add_parser("info", parents=[common],
                       help="what a model is: architecture, input size, licence, training provenance")
    i.add_argument("model", nargs="?", default=DEFAULT_MODEL,
                   help="shipped model name, .safetensors, official .pth or ONNX export (default: %(default)s)")
    i.add_argument("--json", action="store_true", help="everything as JSON (config and full provenance)")
    i.set_defaults(fn=cmd_info)

    d = sub.add_parser("demo", parents=[common], help="reconstruct the demo scenes shipped with the package")
    d.add_argument("-o", "--out", default="demo_out", help="output folder (default: %(default)s)")
    d.add_argument("--model", default=DEFAULT_MODEL, help="shipped model name, .safetensors, official .pth or ONNX")
    d.set_defaults(fn=cmd_demo)
    where = {r: " The alignment runs on the CPU.", s: " Used only with --test; the splat fit runs on the CPU."}
    for cmd in (a, r, s, loc, d):  # every command that runs the network
        cmd.add_argument("--device", default="auto", help="where the network runs: auto (CUDA, then MPS, then the "
                         "CPU: the first torch can use; default), cpu, cuda, cuda:N or mps." + where.get(cmd, ""))
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
    formatwarning = warnings.formatwarning
    if not args.verbose:  # a warning is one line, as an error is, not the library's source line under it
        warnings.formatwarning = lambda message, *_, **__: f"pointmap: warning: {message}\n"
    try:
        if args.cmd not in ("splat", "info") or getattr(args, "test", False):  # the commands that run the network
            args.device = resolve_device(args.device)  # before anything runs: a missing GPU is one line
        return args.fn(args)
    except PointmapError as e:
        print(f"pointmap: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader went away (pointmap info --json | head): quiet, as other tools are
        try:  # stdout onto /dev/null, so that the interpreter's flush at exit does not fail again
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):  # no real file descriptor (a test's captured stdout)
            pass
        return 141  # 128 + SIGPIPE, what a shell reports for a writer whose reader closed the pipe
    except OSError as e:  # the file system's refusal (no such folder, no space, no permission): one line, not a trace
        if args.verbose:
            raise
        print(f"pointmap: error: {e} (run with -v for the traceback)", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("pointmap: interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.formatwarning = formatwarning


if __name__ == "__main__":
    sys.exit(main())
