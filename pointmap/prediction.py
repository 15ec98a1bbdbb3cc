"""PairPrediction: what the network returns for a pair of views (a public contract: docs/conventions.md)."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch

from pointmap.errors import ShapeError, is_int

OPTIONAL_FIELDS = ("desc1", "desc2", "desc_conf1", "desc_conf2", "cam2_to_cam1", "focal1", "focal2")  # None
# for models without them


@dataclass
class PairPrediction:
    """Both views' pointmaps in view 1's camera frame (OpenCV, see docs/conventions.md).

    pts1_cam1: [B, H1, W1, 3] view-1 points in view-1's frame (scale-normalised unless metric)
    pts2_cam1: [B, H2, W2, 3] view-2 points in view-1's frame
    conf1, conf2: [B, H, W] confidences (>= 1 for the official heads)
    desc1, desc2: [B, H, W, D] unit descriptors, or None for models without a descriptor head
    desc_conf1, desc_conf2: [B, H, W] descriptor confidences, or None
    cam2_to_cam1: [B, 4, 4] the rigid transform a pose head predicts from camera 2's frame to camera 1's (view 2's
        cam2world in view 1's frame, in the pointmaps' units; for such models ``pts2_cam1`` is view 2's own-frame
        pointmap moved by it), or None for models without a pose head
    focal1, focal2: [B] each view's focal in pixels of its pointmap's grid (principal point at the centre), from a
        focal head, or None for models without one (``pointmap.pose.focal_from_prediction`` then reads view 1's
        focal off its own-frame pointmap)
    """

    pts1_cam1: torch.Tensor
    pts2_cam1: torch.Tensor
    conf1: torch.Tensor
    conf2: torch.Tensor
    desc1: torch.Tensor | None = None
    desc2: torch.Tensor | None = None
    desc_conf1: torch.Tensor | None = None
    desc_conf2: torch.Tensor | None = None
    cam2_to_cam1: torch.Tensor | None = None
    focal1: torch.Tensor | None = None
    focal2: torch.Tensor | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            t = getattr(self, f.name)
            if not isinstance(t, torch.Tensor) and (t is not None or f.name not in OPTIONAL_FIELDS):
                raise ShapeError(f"{f.name} expected a torch.Tensor, got {type(t).__name__}")
        for v, pts, conf in (("1", self.pts1_cam1, self.conf1), ("2", self.pts2_cam1, self.conf2)):
            if pts.ndim != 4 or pts.shape[-1] != 3:
                raise ShapeError(f"pts{v}_cam1 expected [B, H, W, 3], got {list(pts.shape)}")
            if tuple(conf.shape) != tuple(pts.shape[:3]):
                raise ShapeError(f"conf{v} expected {list(pts.shape[:3])}, got {list(conf.shape)}")
        if self.pts1_cam1.shape[0] != self.pts2_cam1.shape[0]:
            raise ShapeError(
                f"pts1_cam1 and pts2_cam1 need the same batch size, got "
                f"{self.pts1_cam1.shape[0]} and {self.pts2_cam1.shape[0]}"
            )
        given = [n for n in ("desc1", "desc2", "desc_conf1", "desc_conf2") if getattr(self, n) is not None]
        if given and len(given) != 4:
            raise ShapeError(f"desc1, desc2, desc_conf1 and desc_conf2 expected all four or none, got only {given}")
        if given:
            dims = set()
            for v, pts in (("1", self.pts1_cam1), ("2", self.pts2_cam1)):
                d, dc = getattr(self, f"desc{v}"), getattr(self, f"desc_conf{v}")
                if d.ndim != 4 or tuple(d.shape[:3]) != tuple(pts.shape[:3]):
                    raise ShapeError(f"desc{v} expected {list(pts.shape[:3]) + ['D']} (pts{v}_cam1's grid), "
                                     f"got {list(d.shape)}")
                if tuple(dc.shape) != tuple(pts.shape[:3]):
                    raise ShapeError(f"desc_conf{v} expected {list(pts.shape[:3])}, got {list(dc.shape)}")
                dims.add(int(d.shape[-1]))
            if len(dims) != 1:
                raise ShapeError(f"desc1 and desc2 expected the same descriptor length D, got {sorted(dims)}")
        if self.cam2_to_cam1 is not None and tuple(self.cam2_to_cam1.shape) != (self.pts1_cam1.shape[0], 4, 4):
            raise ShapeError(f"cam2_to_cam1 expected [{self.pts1_cam1.shape[0]}, 4, 4] (one transform per pair), got "
                             f"{list(self.cam2_to_cam1.shape)}")
        for n in ("focal1", "focal2"):
            f = getattr(self, n)
            if f is not None and tuple(f.shape) != (self.pts1_cam1.shape[0],):
                raise ShapeError(f"{n} expected [{self.pts1_cam1.shape[0]}] (one focal per pair), got {list(f.shape)}")

    @property
    def batch_size(self) -> int:
        return int(self.pts1_cam1.shape[0])

    @property
    def has_desc(self) -> bool:
        return self.desc1 is not None and self.desc2 is not None

    def map(self, fn) -> PairPrediction:
        """Apply ``fn`` to every tensor field (None stays None)."""
        return replace(self, **{f.name: (None if getattr(self, f.name) is None else fn(getattr(self, f.name)))
                                for f in fields(self)})

    def __getitem__(self, idx) -> PairPrediction:
        """Batch slice, keeping the batch dimension: ``pred[i:i+1]``; an integer (Python or numpy; negative counts
        from the end) keeps it too, and one outside the batch is an IndexError."""
        if is_int(idx):
            i, n = int(idx), self.batch_size
            if not -n <= i < n:
                raise IndexError(f"PairPrediction index {i} is outside its batch of {n}")
            idx = slice(i % n, i % n + 1)
        return self.map(lambda t: t[idx])

    def to(self, *args, **kwargs) -> PairPrediction:
        return self.map(lambda t: t.to(*args, **kwargs))

    def as_dict(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    @staticmethod
    def cat(preds: list[PairPrediction]) -> PairPrediction:
        """Concatenate along the batch dimension (all parts must share shapes)."""
        first = preds[0]
        out = {}
        for f in fields(first):
            vals = [getattr(p, f.name) for p in preds]
            out[f.name] = None if vals[0] is None else torch.cat(vals, 0)
        return PairPrediction(**out)


def check_prediction(pred, name: str = "pred") -> None:
    """ShapeError unless ``pred`` is a PairPrediction (what the model and ``predict_pairs`` return)."""
    if not isinstance(pred, PairPrediction):
        raise ShapeError(f"{name} expected a PairPrediction (the model's output, or an entry of predict_pairs), got "
                         f"{type(pred).__name__}")
