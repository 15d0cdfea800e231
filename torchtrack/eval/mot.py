"""Multi-object tracking metrics: HOTA, CLEAR (MOTA, MOTP, ID switches, ...) and Identity (IDF1),
computed by TrackEval's own metric classes (Luiten et al., the MOTChallenge reference code), not
re-implemented here.

TrackEval is an optional dependency: its PyPI package requires ``opencv-python``, which would
replace the headless OpenCV this package uses, so it is installed without its dependencies (it
needs only numpy and scipy, which torchtrack already brings)::

    pip install --no-deps trackeval==1.3.0

Conventions (MOT15, as ``trackeval.datasets.MotChallenge2DBox`` with ``BENCHMARK='MOT15'``):

* A ground-truth row is **ignored** when its ``conf`` column, truncated to an integer, is 0
  (TrackEval's ``zero_marked``; MOT15 GT uses 0/1). It is removed before matching, so it is
  neither a miss nor a match.
* There is **no distractor or class preprocessing** (MOT15 has no class column): a tracker box
  on an ignored person is not excused and counts as a false positive. (From MOT16 on, TrackEval
  first removes tracker boxes matched to distractor classes; MOT15 files have none.)
* Similarity is box IoU (``x, y, w, h``); a match needs IoU >= 0.5 for CLEAR and Identity;
  HOTA averages over the 19 thresholds alpha = 0.05, 0.10, ..., 0.95.
* Identities are relabelled to contiguous numbers after the ignored rows are dropped, and every
  id appears at most once per frame (checked by :func:`torchtrack.io.mot.read_mot`).
* Scores over several sequences are TrackEval's ``combine_sequences`` (sums of the counts, not
  means of the per-sequence scores), as on the MOTChallenge leaderboard.

Scores are fractions (0.354, not 35.4) in :class:`MotMetrics` and ``results.json``; the markdown
tables print percentages.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io
import json
import os
import warnings
from dataclasses import dataclass, field, fields
from pathlib import Path
from types import ModuleType

import numpy as np

from torchtrack.errors import ConfigError, MissingDependencyError, MotFormatError
from torchtrack.io.atomic import write_text_atomic
from torchtrack.io.mot import MotRows, MotSequence, read_mot

__all__ = [
    "TRACKEVAL_INSTALL",
    "MotMetrics",
    "combine_metrics",
    "evaluate_mot",
    "gt_as_detections",
    "import_trackeval",
    "mot_markdown",
    "mot_table",
    "resolve_results",
    "score_mot",
    "score_sequence",
    "trackeval_data",
]

#: The command that installs TrackEval without the opencv-python it declares.
TRACKEVAL_INSTALL = "pip install --no-deps trackeval==1.3.0"
IOU_THRESHOLD = 0.5


def import_trackeval() -> ModuleType:
    """Import TrackEval, silencing what its import prints (a warning about the optional BURST
    dataset's missing ``pycocotools``, on stdout).

    Raises:
        MissingDependencyError: TrackEval is not installed (the message gives the command).
    """
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            import trackeval
    except ImportError as exc:
        raise MissingDependencyError(
            f"MOT metrics need TrackEval, which is not installed ({exc}); install it without "
            f"its opencv-python dependency: {TRACKEVAL_INSTALL}"
        ) from None
    return trackeval


# ---------------------------------------------------------------------------------------------
# TrackEval's input for one sequence
# ---------------------------------------------------------------------------------------------
def trackeval_data(gt: MotRows, results: MotRows, n_frames: int, name: str = "sequence") -> dict:
    """The dict TrackEval's metrics read for one sequence, with the MOT15 preprocessing (module
    doc): what ``MotChallenge2DBox.get_preprocessed_seq_data`` returns for ``BENCHMARK='MOT15'``.

    Args:
        gt: ground truth (its ``conf`` is the 0/1 consider flag).
        results: the tracker's boxes.
        n_frames: the sequence's length (rows beyond it are an error).
        name: the sequence name.

    Raises:
        MotFormatError: a row beyond ``n_frames``.
    """
    trackeval = import_trackeval()
    iou = trackeval.datasets._base_dataset._BaseDataset._calculate_box_ious
    for rows, word in ((gt, "ground-truth"), (results, "results")):
        if len(rows) and rows.frames.max() >= n_frames:
            k = int(np.argmax(rows.frames))
            where = f"{rows.path} line {rows.lines[k]}" if rows.path else f"{word} row {k}"
            raise MotFormatError(
                f"{where}: frame {rows.frames[k] + 1} is beyond sequence {name}'s {n_frames} frames"
            )
    keep = gt.conf.astype(int) != 0  # TrackEval: zero_marked = conf.astype(int)
    g = gt.select(keep)
    gt_ids = _relabel(g.ids)
    tr_ids = _relabel(results.ids)
    g_split, r_split = g.split(n_frames), results.split(n_frames)
    data: dict = {
        "gt_ids": [],
        "tracker_ids": [],
        "gt_dets": [],
        "tracker_dets": [],
        "tracker_confidences": [],
        "similarity_scores": [],
    }
    for gi, ri in zip(g_split, r_split, strict=True):
        gd, rd = g.boxes[gi], results.boxes[ri]
        data["gt_ids"].append(gt_ids[gi])
        data["tracker_ids"].append(tr_ids[ri])
        data["gt_dets"].append(gd)
        data["tracker_dets"].append(rd)
        data["tracker_confidences"].append(results.conf[ri])
        data["similarity_scores"].append(iou(gd, rd, box_format="xywh"))
    data.update(
        num_timesteps=n_frames,
        num_gt_ids=len(np.unique(g.ids)),
        num_tracker_ids=len(np.unique(results.ids)),
        num_gt_dets=len(g),
        num_tracker_dets=len(results),
        seq=name,
    )
    return data


def _relabel(ids: np.ndarray) -> np.ndarray:
    """Identities -> 0..n-1 (TrackEval indexes arrays with them)."""
    return np.unique(ids, return_inverse=True)[1].astype(int).reshape(-1)


# ---------------------------------------------------------------------------------------------
# Scores
# ---------------------------------------------------------------------------------------------
@dataclass
class MotMetrics:
    """MOT scores of one sequence or of several combined (fractions; counts as integers).

    HOTA family (means over the 19 IoU thresholds): ``hota``, ``deta``, ``assa``, ``loca``,
    ``detre``, ``detpr``, ``assre``, ``asspr``. CLEAR: ``mota``, ``motp`` (mean IoU of the
    matches), ``moda``, ``recall``, ``precision``, ``id_switches``, ``fp``, ``fn``, ``tp``,
    ``frag`` (fragmentations), ``mt`` / ``pt`` / ``ml`` (mostly tracked / partly / mostly lost
    identities). Identity: ``idf1``, ``idp``, ``idr``. Sizes: ``n_frames``, ``n_gt`` (GT boxes
    scored), ``n_gt_ignored`` (conf-0 rows dropped), ``n_results`` (tracker boxes), ``n_gt_ids``,
    ``n_result_ids``. ``raw`` keeps TrackEval's result dicts (for :func:`combine_metrics`).
    """

    hota: float
    deta: float
    assa: float
    loca: float
    detre: float
    detpr: float
    assre: float
    asspr: float
    mota: float
    motp: float
    moda: float
    recall: float
    precision: float
    idf1: float
    idp: float
    idr: float
    id_switches: int
    fp: int
    fn: int
    tp: int
    frag: int
    mt: int
    pt: int
    ml: int
    n_frames: int
    n_gt: int
    n_gt_ignored: int
    n_results: int
    n_gt_ids: int
    n_result_ids: int
    raw: dict = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        """JSON-ready scores (without ``raw``)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "raw"}

    @classmethod
    def _from_raw(cls, raw: dict, sizes: dict) -> MotMetrics:
        h, c, i = raw["HOTA"], raw["CLEAR"], raw["Identity"]

        def m(x) -> float:
            return float(np.mean(x))

        return cls(
            hota=m(h["HOTA"]),
            deta=m(h["DetA"]),
            assa=m(h["AssA"]),
            loca=m(h["LocA"]),
            detre=m(h["DetRe"]),
            detpr=m(h["DetPr"]),
            assre=m(h["AssRe"]),
            asspr=m(h["AssPr"]),
            mota=float(c["MOTA"]),
            motp=float(c["MOTP"]),
            moda=float(c["MODA"]),
            recall=float(c["CLR_Re"]),
            precision=float(c["CLR_Pr"]),
            idf1=float(i["IDF1"]),
            idp=float(i["IDP"]),
            idr=float(i["IDR"]),
            id_switches=int(c["IDSW"]),
            fp=int(c["CLR_FP"]),
            fn=int(c["CLR_FN"]),
            tp=int(c["CLR_TP"]),
            frag=int(c["Frag"]),
            mt=int(c["MT"]),
            pt=int(c["PT"]),
            ml=int(c["ML"]),
            raw=raw,
            **sizes,
        )


def _metric_objects():
    trackeval = import_trackeval()
    quiet = {"PRINT_CONFIG": False}
    return {
        "HOTA": trackeval.metrics.HOTA(quiet),
        "CLEAR": trackeval.metrics.CLEAR({**quiet, "THRESHOLD": IOU_THRESHOLD}),
        "Identity": trackeval.metrics.Identity({**quiet, "THRESHOLD": IOU_THRESHOLD}),
    }


def score_mot(
    gt: MotRows, results: MotRows, n_frames: int, *, name: str = "sequence"
) -> MotMetrics:
    """Score ``results`` against ``gt`` with TrackEval's HOTA, CLEAR and Identity metrics
    (MOT15 conventions, module doc). An empty ``results`` scores as an empty tracker.

    Args:
        gt: ground truth, in the same pixels as ``results`` (scaled already).
        results: tracker output, ids >= 0, unique per frame.
        n_frames: the sequence's length.
        name: the sequence name (messages).

    Raises:
        MissingDependencyError: TrackEval is missing.
        MotFormatError: rows beyond ``n_frames``.
    """
    data = trackeval_data(gt, results, n_frames, name)
    raw = {k: metric.eval_sequence(data) for k, metric in _metric_objects().items()}
    return MotMetrics._from_raw(
        raw,
        {
            "n_frames": int(n_frames),
            "n_gt": int(data["num_gt_dets"]),
            "n_gt_ignored": len(gt) - int(data["num_gt_dets"]),
            "n_results": len(results),
            "n_gt_ids": int(data["num_gt_ids"]),
            "n_result_ids": int(data["num_tracker_ids"]),
        },
    )


def gt_as_detections(gt: MotRows, seed: int, drop: float = 0.1, jitter: float = 2.0) -> MotRows:
    """Ground truth degraded into detections, a tracker's ceiling: the rows with conf 0
    removed, ``drop`` of the rest dropped at random and Gaussian ``jitter`` px added to x, y, w,
    h (sizes kept >= 1 px); ids -1, conf 1. The same ``seed`` gives the same draw.

    Raises:
        ConfigError: ``drop`` outside [0, 1) or a negative ``jitter``.
    """
    if not (0.0 <= drop < 1.0) or not (jitter >= 0.0):
        raise ConfigError(f"drop must be in [0, 1) and jitter >= 0, got {drop} and {jitter}")
    g = gt.select(gt.conf.astype(int) != 0)
    rng = np.random.default_rng(seed)
    keep = rng.random(len(g)) >= drop
    boxes = g.boxes[keep] + rng.normal(0.0, jitter, (int(keep.sum()), 4))
    boxes[:, 2:] = np.maximum(boxes[:, 2:], 1.0)
    return MotRows.from_arrays(g.frames[keep], np.full(int(keep.sum()), -1), boxes)


def combine_metrics(scores: list[MotMetrics]) -> MotMetrics:
    """Scores over several sequences: TrackEval's ``combine_sequences`` (counts summed, then
    the scores computed from the sums; HOTA's association terms weighted by matches).

    Raises:
        ValueError: no scores.
    """
    if not scores:
        raise ValueError("combine_metrics needs at least one sequence's scores")
    objs = _metric_objects()
    raw = {
        k: metric.combine_sequences({str(n): s.raw[k] for n, s in enumerate(scores)})
        for k, metric in objs.items()
    }
    sizes = {
        k: sum(getattr(s, k) for s in scores)
        for k in ("n_frames", "n_gt", "n_gt_ignored", "n_results", "n_gt_ids", "n_result_ids")
    }
    return MotMetrics._from_raw(raw, sizes)


def score_sequence(seq: MotSequence, results: str | os.PathLike) -> MotMetrics:
    """Score one MOTChallenge results file against a sequence's ground truth.

    ``results`` is in the frames' pixels (the ground truth was scaled to them on loading).
    This is the one call an evaluation makes per (tracker, sequence); a tracker run from the
    evaluation writes its file with :func:`torchtrack.io.mot.write_mot` and comes here.

    Raises:
        MotFormatError: a malformed results file, rows beyond the sequence's frames.
        MissingDependencyError: TrackEval is missing.
    """
    rows = read_mot(results, n_frames=seq.n_frames, kind="results")
    if seq.width and seq.height and len(seq.gt.boxes):
        import torch

        from torchtrack.boxes import inside_fraction

        out = inside_fraction(torch.from_numpy(seq.gt.boxes), (seq.height, seq.width)) <= 0
        if float(out.double().mean()) > 0.05:
            warnings.warn(
                f"{int(out.sum())} of the {len(out)} ground-truth boxes of {seq.name} "
                f"({os.fspath(seq.gt_path)}) lie wholly outside its {seq.width}x{seq.height} "
                "frames: the ground truth is at another scale (--gt-scale, or a seqinfo.ini "
                "with imWidth / imHeight beside it)",
                UserWarning,
                stacklevel=2,
            )
    if seq.width and seq.height and len(rows.boxes):
        import torch

        from torchtrack.boxes import inside_fraction

        inside = inside_fraction(torch.from_numpy(rows.boxes), (seq.height, seq.width))
        if not bool((inside > 0).any()):
            warnings.warn(
                f"no box of {os.fspath(results)!r} touches the {seq.width}x{seq.height} frames "
                f"of {seq.name}: every one is a false positive (results written at another "
                "scale or in other units?)",
                UserWarning,
                stacklevel=2,
            )
    hint = scale_mismatch(seq.gt, rows)
    if hint is not None:
        factor, at_s, at_1, n = hint
        warnings.warn(
            f"the boxes of {os.fspath(results)!r} look like they were made on a copy of "
            f"{seq.name} at another size: {at_s} of {n} checked boxes overlap a "
            f"ground-truth box at IoU 0.5 when the ground truth is scaled by about "
            f"{factor:.2g}, {at_1} as it is; if so, score with --gt-scale set to the copy's "
            f"width over the ground truth's (about {seq.scale * factor:.2g})",
            UserWarning,
            stacklevel=2,
        )
    return score_mot(seq.gt, rows, seq.n_frames, name=seq.name)


def scale_mismatch(
    gt: MotRows, results: MotRows, max_frames: int = 200
) -> tuple[float, int, int, int] | None:
    """Whether ``results`` look made at another size than ``gt``. The ratio of their median
    box heights (scored rows of the ground truth) differs from 1 by more than 20%, and with the
    ground truth scaled about the origin (a resized copy of the frames) by a factor ``s`` within
    15% of that ratio (and itself more than 20% from 1), at least three times as many result
    boxes overlap a ground-truth box of their frame at IoU 0.5 as without, and at least a
    quarter of them. Checked on up to ``max_frames`` frames spread over the results; ``s`` is
    the factor of the most overlaps.

    Returns:
        ``(s, matched at s, matched as is, boxes checked)``, or ``None`` when the sizes agree
        or the evidence is too thin (fewer than 20 boxes on either side).
    """
    import torch

    from torchtrack.boxes import box_iou_matrix

    g = gt.select(gt.conf.astype(int) != 0)
    if len(g) < 20 or len(results) < 20:
        return None
    s = float(np.median(results.boxes[:, 3]) / max(float(np.median(g.boxes[:, 3])), 1e-9))
    if not (np.isfinite(s) and s > 0) or abs(np.log(s)) < np.log(1.2):
        return None
    frames = np.unique(results.frames)
    frames = np.unique(
        frames[np.linspace(0, len(frames) - 1, min(len(frames), max_frames)).astype(int)]
    )
    grid = s * np.exp(np.linspace(-0.15, 0.15, 13))
    grid = grid[np.abs(np.log(grid)) >= np.log(1.2)]
    counts, n = np.zeros(len(grid) + 1, np.int64), 0
    for f in frames:
        r = results.boxes[results.frames == f]
        n += len(r)
        gb = g.boxes[g.frames == f]
        if not len(gb):
            continue
        for i, k in enumerate((1.0, *grid)):
            iou = box_iou_matrix(torch.from_numpy(r), torch.from_numpy(gb * k))
            counts[i] += int((iou.max(dim=1).values >= 0.5).sum())
    if len(grid):
        best = int(counts[1:].argmax())
        at_s, at_1 = int(counts[1 + best]), int(counts[0])
        if at_s >= max(3 * at_1, 1) and at_s >= 0.25 * n:
            return float(grid[best]), at_s, at_1, n
    return None


# ---------------------------------------------------------------------------------------------
# Several sequences and result sets: files, tables
# ---------------------------------------------------------------------------------------------
def resolve_results(seqs: list[MotSequence], results: str | os.PathLike) -> list[Path]:
    """The results file of each sequence: ``results`` itself when it is a file (one sequence
    only), else ``results/<sequence name>.txt`` (the MOTChallenge layout).

    Raises:
        ConfigError: a file given for several sequences, a missing file or folder, a folder
            without a sequence's file (the message lists the ``.txt`` files it holds).
    """
    r = Path(results)
    if r.is_file():
        if len(seqs) != 1:
            raise ConfigError(
                f"results {r} is one file but {len(seqs)} sequences are scored: give a folder "
                "with one <sequence name>.txt per sequence"
            )
        return [r]
    if not r.is_dir():
        raise ConfigError(f"results {r} does not exist (a MOT results file or a folder of them)")
    out, missing = [], []
    for s in seqs:
        f = r / f"{s.name}.txt"
        if f.is_file():
            out.append(f)
        else:  # a folder of that name was listed as found, beside 'no file'
            missing.append(f"{s.name} ({f.name} is a folder)" if f.is_dir() else s.name)
    if missing:
        have = sorted(p.name for p in r.glob("*.txt") if p.is_file())
        raise ConfigError(
            f"results folder {r} has no file for sequence(s) {', '.join(missing)} (expected "
            f"<sequence name>.txt; found: {', '.join(have) if have else 'no .txt file'})"
        )
    return out


def _unique_labels(paths: list[Path]) -> list[str]:
    labels, seen = [], {}
    for p in paths:
        base = p.stem if p.is_file() else p.name or str(p)
        k = seen.get(base, 0)
        seen[base] = k + 1
        labels.append(base if k == 0 else f"{base}#{k + 1}")
    return labels


def evaluate_mot(
    sequences: list[MotSequence],
    results: list[str | os.PathLike],
    out_dir: str | os.PathLike | None = None,
    *,
    labels: list[str] | None = None,
    command: str | None = None,
) -> dict:
    """Score result sets (one per tracker) on every sequence; write ``results.json`` and
    ``results.md`` atomically under ``out_dir`` when given.

    Args:
        sequences: the sequences (:func:`torchtrack.io.mot.load_mot_sequence`); names unique.
        results: per tracker, a results file (one sequence) or a folder of ``<name>.txt``.
        out_dir: output folder, or ``None`` to write nothing.
        labels: tracker labels (default: the folder name or the file stem).
        command: the command line recorded in the outputs.

    Returns:
        ``{"command", "created", "versions", "settings", "sequences", "trackers",
        "per_sequence": {sequence: {tracker: scores}}, "overall": {tracker: scores}}``.

    Raises:
        ConfigError: no sequence or result set, duplicate sequence names, results that do not
            match the sequences (:func:`resolve_results`).
        MotFormatError: a malformed results file.
        MissingDependencyError: TrackEval is missing.
    """
    if not sequences:
        raise ConfigError("no MOT sequence to score")
    if not results:
        raise ConfigError("no results to score")
    names = [s.name for s in sequences]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(
            f"sequence name(s) {', '.join(dup)} given twice: results files are matched by name"
        )
    paths = [Path(r) for r in results]
    labels = labels or _unique_labels(paths)
    if len(labels) != len(paths) or len(set(labels)) != len(labels):
        raise ConfigError(f"one unique label per result set is needed, got {labels}")
    files = {label: resolve_results(sequences, p) for label, p in zip(labels, paths, strict=True)}
    trackeval = import_trackeval()
    per_seq: dict = {s.name: {} for s in sequences}
    overall: dict = {}
    for label in labels:
        scores = []
        for s, f in zip(sequences, files[label], strict=True):
            m = score_sequence(s, f)
            scores.append(m)
            per_seq[s.name][label] = {**m.to_dict(), "results": str(f)}
        overall[label] = combine_metrics(scores).to_dict()
    from torchtrack import __version__

    summary = {
        "command": command,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "versions": {"torchtrack": __version__, "trackeval": trackeval.__version__},
        "settings": {
            "benchmark": "MOT15",
            "iou_threshold": IOU_THRESHOLD,
            "hota_alphas": "0.05, 0.10, ..., 0.95",
            "gt_ignored": "rows whose conf, truncated to an integer, is 0",
            "distractors": "none (MOT15): a tracker box on an ignored person is a false positive",
        },
        "sequences": [
            {
                "name": s.name,
                "n_frames": s.n_frames,
                "gt": str(s.gt_path),
                "gt_scale": s.scale,
                "frames": str(s.video)
                if s.video
                else (str(s.frames[0].parent) if s.frames else None),
            }
            for s in sequences
        ],
        "trackers": labels,
        "per_sequence": per_seq,
        "overall": overall,
    }
    if out_dir is not None:
        out = Path(out_dir)
        write_text_atomic(out / "results.json", json.dumps(summary, indent=1) + "\n")
        write_text_atomic(out / "results.md", mot_markdown(summary))
    return summary


_COLUMNS = (
    ("HOTA", "hota", "pct"),
    ("DetA", "deta", "pct"),
    ("AssA", "assa", "pct"),
    ("MOTA", "mota", "pct"),
    ("MOTP", "motp", "pct"),
    ("IDF1", "idf1", "pct"),
    ("IDsw", "id_switches", "int"),
    ("FP", "fp", "int"),
    ("FN", "fn", "int"),
    ("Frag", "frag", "int"),
    ("MT", "mt", "int"),
    ("ML", "ml", "int"),
)


def _cells(m: dict) -> list[str]:
    return [f"{100 * m[k]:.1f}" if kind == "pct" else str(m[k]) for _, k, kind in _COLUMNS]


def mot_table(summary: dict) -> str:
    """One markdown row per (tracker, sequence), plus a combined row per tracker when there are
    several sequences (percentages; counts as integers)."""
    head = "| tracker | sequence | " + " | ".join(c for c, _, _ in _COLUMNS) + " |"
    rows = [head, "|---|---|" + "---|" * len(_COLUMNS)]
    for label in summary["trackers"]:
        for seq, per in summary["per_sequence"].items():
            rows.append(f"| {label} | {seq} | " + " | ".join(_cells(per[label])) + " |")
        if len(summary["per_sequence"]) > 1:
            rows.append(
                f"| {label} | **combined** | "
                + " | ".join(_cells(summary["overall"][label]))
                + " |"
            )
    return "\n".join(rows)


def mot_markdown(summary: dict) -> str:
    """The whole ``results.md`` of a MOT evaluation."""
    parts = ["# MOT evaluation", ""]
    if summary.get("command"):
        parts += ["Command:", "", "```", summary["command"], "```", ""]
    seqs = ", ".join(
        f"{s['name']} ({s['n_frames']} frames"
        + (f", GT x{s['gt_scale']:g}" if s["gt_scale"] != 1 else "")
        + ")"
        for s in summary["sequences"]
    )
    parts += [
        f"Sequences: {seqs}. Metrics by TrackEval {summary['versions']['trackeval']} (HOTA, "
        "CLEAR, Identity), MOT15 conventions: GT rows with conf 0 ignored, no distractor "
        "classes (a box on an ignored person is a false positive), IoU >= 0.5 for CLEAR / "
        "Identity, HOTA averaged over IoU 0.05-0.95; several sequences combined by summing "
        "counts.",
        "",
        mot_table(summary),
        "",
    ]
    return "\n".join(parts)
