"""The fixed held-out test sets of the shipped detectors, as windows in images.

Used by ``train/default_models.py`` (the test-split numbers in the bundled-model README) and by
``tools/bench_detectors.py`` (every method on the identical windows, with bootstrap intervals).
Training never reads any of these files (``configs/splits`` are excluded through
``data.exclude``; INRIA's own ``inria_negatives/test`` folder is not in any config).

* pedestrian: the held-out INRIA 96x160 crops (``configs/splits/inria_person_test.txt``) and
  their mirror images, each scored on its central 64x128 window *inside the crop* (the margin
  gives a window's gradients their context, as in a frame); negatives: random windows (seed 1,
  scale 1 up to what fits, Dalal & Triggs' test protocol) of the 12 held-out scene images and
  the 70 images of INRIA's own ``Test/neg`` split.
* vehicle: the held-out UIUC car and non-car crops (``configs/splits/uiuc_car_test.txt``) and
  their mirror images (the whole crop is the window), plus random windows (scale 1 to 2) of the
  170 UIUC single-scale test images that touch no ground-truth car (250 held-out non-car crops
  alone would decide 1% FPR by two crops).

Bootstrap intervals resample *images*: positive source photographs (a crop and its mirror, and
all people of one photograph, go together) and negative images, with replacement.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchtrack.detect.config import read_name_list
from torchtrack.io.crops import list_image_files, read_image, sample_boxes

REPO = Path(__file__).resolve().parents[1]
SPLITS = REPO / "configs" / "splits"


@dataclass
class TestSet:
    """Windows in images: ``images[i]`` ``(C, H, W)`` uint8 with ``boxes[i] (n_i, 4)`` windows
    (x, y, w, h) and ``labels[i]`` (1 positive, 0 negative); ``groups[i]`` names the bootstrap
    unit of image ``i``."""

    name: str
    images: list[torch.Tensor]
    boxes: list[torch.Tensor]
    labels: list[int]
    groups: list[str]
    what: str

    def counts(self) -> tuple[int, int]:
        pos = sum(b.shape[0] for b, lab in zip(self.boxes, self.labels, strict=True) if lab)
        neg = sum(b.shape[0] for b, lab in zip(self.boxes, self.labels, strict=True) if not lab)
        return pos, neg


def _tensor(img: np.ndarray) -> torch.Tensor:
    t = torch.from_numpy(np.ascontiguousarray(img))
    return t.permute(2, 0, 1).contiguous() if t.ndim == 3 else t[None]


def _random_windows(images, window, n, seed, min_scale=1.0, max_scale=None):
    picks = sample_boxes(
        [tuple(im.shape[-2:]) for im in images],
        window,
        n,
        min_scale=min_scale,
        max_scale=max_scale,
        generator=torch.Generator().manual_seed(seed),
    )
    per: dict[int, list] = {}
    for i, x, y, w, h in picks:
        per.setdefault(i, []).append([x, y, w, h])
    return per


def pedestrian_test_set(data: Path, n_windows: int = 20000, seed: int = 1) -> TestSet:
    crops = data / "detection_crops"
    names = read_name_list(SPLITS / "inria_person_test.txt")
    images, boxes, labels, groups = [], [], [], []
    for p in sorted((crops / "inria_person_96x160" / "pos").glob("*.png")):
        if p.name not in names:
            continue
        img = _tensor(read_image(p, colour=True))
        group = re.sub(r"[a-z]\.png$", "", p.name)
        for im in (img, img.flip(-1)):
            images.append(im)
            boxes.append(torch.tensor([[16.0, 16.0, 64.0, 128.0]]))
            labels.append(1)
            groups.append(group)
    scenes = sorted(read_name_list(SPLITS / "scene_negatives_test.txt"))
    neg_paths = [crops / "scene_negatives" / s for s in scenes]
    neg_paths += list_image_files(crops / "inria_negatives" / "test")[0]
    neg = [_tensor(read_image(p, colour=True)) for p in neg_paths]
    per = _random_windows(neg, (128, 64), n_windows, seed)
    for i, im in enumerate(neg):
        if i in per:
            images.append(im)
            boxes.append(torch.tensor(per[i], dtype=torch.float64))
            labels.append(0)
            groups.append(neg_paths[i].name)
    what = (
        f"{sum(labels)} held-out INRIA crops incl. mirrors (64x128 window inside the 96x160 "
        f"crop) vs {n_windows} random windows (seed {seed}, scale >= 1) of {len(scenes)} "
        f"held-out scene images and {len(neg_paths) - len(scenes)} INRIA Test/neg images"
    )
    return TestSet("pedestrian", images, boxes, labels, groups, what)


def _uiuc_truth(car_data: Path) -> dict[int, list[tuple[int, int, int, int]]]:
    gt = {}
    for line in (car_data / "trueLocations.txt").read_text().splitlines():
        if ":" not in line:
            continue
        k, rest = line.split(":", 1)
        pts = re.findall(r"\((-?\d+),\s*(-?\d+)\)", rest)
        gt[int(k)] = [(int(c), int(r), 100, 40) for r, c in pts]  # x, y, w, h
    return gt


def vehicle_test_set(data: Path, n_windows: int = 5000, seed: int = 1) -> TestSet:
    car = data / "detection_crops" / "uiuc_car" / "CarData"
    names = read_name_list(SPLITS / "uiuc_car_test.txt")
    images, boxes, labels, groups = [], [], [], []
    for p in sorted((car / "TrainImages").glob("*.pgm")):
        if p.name not in names:
            continue
        img = _tensor(read_image(p))
        lab = int(p.name.startswith("pos-"))
        for im in (img, img.flip(-1)):
            images.append(im)
            boxes.append(torch.tensor([[0.0, 0.0, float(im.shape[-1]), float(im.shape[-2])]]))
            labels.append(lab)
            groups.append(p.name)
    gt = _uiuc_truth(car)
    keys = sorted(gt)
    test = [_tensor(read_image(car / "TestImages" / f"test-{k}.pgm")) for k in keys]
    g = torch.Generator().manual_seed(seed)
    per: dict[int, list] = {}
    n = 0
    while n < n_windows:  # random windows (scale 1 to 2) that touch no ground-truth car
        i = int(torch.randint(len(test), (1,), generator=g))
        h, w = test[i].shape[-2:]
        top = min(h / 40, w / 100, 2.0)
        if top < 1.0:
            continue
        u = torch.rand(3, generator=g, dtype=torch.float64).tolist()
        sc = top ** u[0]
        bw, bh = round(100 * sc), round(40 * sc)
        x = int(u[1] * (w - bw + 1))
        y = int(u[2] * (h - bh + 1))
        if any(
            x < gx + gw and gx < x + bw and y < gy + gh and gy < y + bh
            for gx, gy, gw, gh in gt[keys[i]]
        ):
            continue
        per.setdefault(i, []).append([x, y, bw, bh])
        n += 1
    for i, im in enumerate(test):
        if i in per:
            images.append(im)
            boxes.append(torch.tensor(per[i], dtype=torch.float64))
            labels.append(0)
            groups.append(f"test-{keys[i]}.pgm")
    pos, neg = sum(1 for lab in labels if lab), 0
    neg = sum(b.shape[0] for b, lab in zip(boxes, labels, strict=True) if not lab)
    what = (
        f"{pos} held-out UIUC car crops incl. mirrors vs {neg} negatives: held-out non-car crops "
        f"+ mirrors and {n_windows} random windows (scale 1-2, seed {seed}) of the 170 UIUC "
        "single-scale test images touching no ground-truth car"
    )
    return TestSet("vehicle", images, boxes, labels, groups, what)


def test_set(name: str, data: Path) -> TestSet:
    return pedestrian_test_set(data) if name == "pedestrian" else vehicle_test_set(data)


def score_test_set(
    score, ts: TestSet
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``score(image (1, C, H, W), boxes (1, n, 4)) -> (n,)`` on every image of ``ts``.

    Returns:
        ``(positive scores, negative scores, positive group ids, negative group ids)``.
    """
    ps, ns, pg, ng = [], [], [], []
    gid: dict[str, int] = {}
    for img, bx, lab, grp in zip(ts.images, ts.boxes, ts.labels, ts.groups, strict=True):
        s = torch.as_tensor(score(img[None], bx[None].float())).reshape(-1).double()
        k = gid.setdefault(grp, len(gid))
        (ps if lab else ns).append(s)
        (pg if lab else ng).append(torch.full((s.numel(),), k, dtype=torch.long))
    return torch.cat(ps), torch.cat(ns), torch.cat(pg), torch.cat(ng)


def dr_at_fpr(pos: torch.Tensor, neg: torch.Tensor, fpr: float = 0.01) -> float:
    """Share of positives strictly above the ``(floor(fpr n_neg) + 1)``-th highest negative."""
    k = math.floor(fpr * neg.numel())
    thr = neg.sort(descending=True).values[min(k, neg.numel() - 1)]
    return float((pos > thr).double().mean())


def bootstrap_dr(
    pos: torch.Tensor,
    neg: torch.Tensor,
    pos_groups: torch.Tensor,
    neg_groups: torch.Tensor,
    *,
    fpr: float = 0.01,
    reps: int = 1000,
    seed: int = 0,
    level: float = 0.9,
) -> tuple[float, float]:
    """A ``level`` percentile bootstrap interval of the detection rate at ``fpr``, resampling
    positive source groups and negative images with replacement."""
    g = torch.Generator().manual_seed(seed)
    pu, nu = torch.unique(pos_groups), torch.unique(neg_groups)
    p_members = [pos[pos_groups == u] for u in pu.tolist()]
    n_members = [neg[neg_groups == u] for u in nu.tolist()]
    out = []
    for _ in range(reps):
        pi = torch.randint(len(p_members), (len(p_members),), generator=g).tolist()
        ni = torch.randint(len(n_members), (len(n_members),), generator=g).tolist()
        out.append(
            dr_at_fpr(
                torch.cat([p_members[i] for i in pi]), torch.cat([n_members[i] for i in ni]), fpr
            )
        )
    a = torch.tensor(out)
    lo, hi = (1 - level) / 2, 1 - (1 - level) / 2
    return float(a.quantile(lo)), float(a.quantile(hi))
