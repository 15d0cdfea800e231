"""The evaluation harness: run trackers over sequences, score them, write the results.

:func:`run_sequence` runs one tracker on one sequence; :func:`evaluate` runs every tracker on
every sequence (optionally in parallel processes) and writes, under ``out_dir``:

* ``sequences/<sequence>/<tracker>.json``: per-frame boxes, visibility, confidence, timing and
  every metric of that run (or the error that stopped it);
* ``results.json``: settings, the per-sequence metric table and the per-tracker averages;
* ``results.md``: the same as markdown tables;
* with ``plots=True``: ``success.png`` / ``precision.png`` (one curve per tracker, averaged over
  sequences) and ``plots/<sequence>_{success,precision}.png``.

All files are written atomically.

Protocol
--------
* Every tracker gets the same initialisation: the ground-truth box of the first frame whose
  target is present (normally frame 0); frames up to it are initialisation frames, excluded
  from the metrics.
* One-pass evaluation (OPE) by default. With ``reinit=True`` a second, re-initialising pass
  follows Bachoo et al. sec. 4: when the box centre is more than ``break_px`` (100) pixels off
  in x or y on a present frame, that frame is scored and the tracker is re-initialised on it from
  the ground truth; the re-initialisation count gives ``reinit_per_100``.
* ``fps`` counts only the time spent inside ``tracker.update`` (frame decoding and file I/O
  excluded); initialisation time is reported separately as ``init_seconds``.
* An unreadable frame is not shown to the tracker: the previous box is carried over with
  ``visible=False`` and the frame is listed in ``bad_frames``.
* A tracker that raises is recorded as failed for that sequence (``error``, ``error_frame``)
  and the run goes on; failed runs are left out of the averages and counted in ``n_failed``.
* Trackers that take a ``generator`` argument get ``torch.Generator().manual_seed(seed)``, fresh
  for every sequence, so runs are reproducible and independent of ``jobs``.
* With ``jobs > 1`` (or ``backend="ray"``) every (tracker, sequence, seed) pass is one task of
  :mod:`torchtrack.eval.backends`: spawned processes or Ray tasks, each limited to one torch /
  OpenCV thread (so timings are per core), longest sequences first. A worker that crashes (a
  segfault in native code) is recorded as a failure of its own task only: the local pool reruns
  the tasks it took down, Ray reruns the crashed task up to ``max_retries`` times first. The
  result files are written here, by the process that called :func:`evaluate`, once per task,
  whichever backend ran it; every record names the host and process that ran it
  (``worker``) and the task's wall time (``wall_seconds``).
"""

from __future__ import annotations

import datetime as _dt
import importlib
import json
import math
import os
import re
import time
import traceback
from collections.abc import Callable
from collections.abc import Sequence as Sequence_
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchtrack.device import check_device
from torchtrack.errors import ConfigError
from torchtrack.eval.backends import worker_info
from torchtrack.eval.metrics import (
    BREAK_PX,
    SCALAR_METRICS,
    aggregate_metrics,
    evaluate_sequence,
)
from torchtrack.io.atomic import write_text_atomic
from torchtrack.io.sequences import Sequence
from torchtrack.track.base import create_tracker, parse_tracker_spec, tracker_info

__all__ = ["RunResult", "evaluate", "run_sequence", "safe_name", "validate_tracker_specs"]


def safe_name(s: str) -> str:
    """A file-name-safe version of a tracker label or sequence name."""
    return re.sub(r"[^\w.+-]+", "_", s).strip("_") or "unnamed"


@dataclass
class RunResult:
    """One tracker on one sequence.

    Attributes:
        boxes: ``(T, 4)`` predicted boxes (NaN before initialisation and after an error).
        visible: ``(T,)`` bool; confidence: ``(T,)`` float.
        init_frames: initialisation frames (excluded from metrics).
        reinit_frames: frames re-initialised from ground truth, ``None`` for a one-pass run.
        update_seconds / n_updates: time inside ``update`` and how many calls.
        tracker_failures: the tracker's own failure count (``failures`` attribute, e.g. OpenCV
            ``ok=False`` frames) or ``None`` if it keeps none.
        error: ``"Type: message"`` if the tracker raised, with ``error_frame``.
    """

    tracker: str
    sequence: str
    boxes: torch.Tensor
    visible: torch.Tensor
    confidence: torch.Tensor
    init_frames: list[int]
    reinit_frames: list[int] | None
    update_seconds: float = 0.0
    init_seconds: float = 0.0
    n_updates: int = 0
    bad_frames: list[int] = field(default_factory=list)
    tracker_failures: int | None = None
    error: str | None = None
    error_frame: int | None = None
    traceback: str | None = None

    @property
    def fps(self) -> float | None:
        return self.n_updates / self.update_seconds if self.update_seconds > 0 else None

    def metrics(self, gt: torch.Tensor, invisible: str = "box"):
        """:class:`~torchtrack.eval.metrics.SequenceMetrics` of this run against ``gt``."""
        return evaluate_sequence(
            self.boxes,
            gt,
            self.visible,
            init_frames=self.init_frames,
            reinit_frames=self.reinit_frames,
            invisible=invisible,
        )


def _make_tracker(spec: str, seed: int, device: torch.device | str = "cpu"):
    name, params = parse_tracker_spec(spec)
    if tracker_info(name).accepts_generator and "generator" not in params:
        params["generator"] = torch.Generator(device=device).manual_seed(seed)
    return create_tracker(name, **params)


def validate_tracker_specs(specs: list[str]) -> None:
    """Check every ``name[:key=value,...]`` spec builds (unknown names, missing contrib, bad
    parameters raise :class:`ConfigError` before any sequence runs) and labels are unique."""
    if not specs:
        raise ConfigError("no tracker given")
    if len(set(specs)) != len(specs):
        raise ConfigError(f"a tracker is listed twice: {specs}")
    for s in specs:
        _make_tracker(s, 0)


def run_sequence(
    spec: str,
    seq: Sequence,
    *,
    reinit: bool = False,
    break_px: float = BREAK_PX,
    seed: int = 0,
    color: str = "rgb",
    on_frame: Callable[[int], None] | None = None,
    device: torch.device | str = "cpu",
) -> RunResult:
    """Run the tracker ``spec`` (``name[:key=value,...]``) over ``seq``.

    Args:
        spec: tracker name and parameters (:func:`~torchtrack.track.base.parse_tracker_spec`).
        seq: the sequence.
        reinit: re-initialise from ground truth when the centre is more than ``break_px`` off
            in x or y (Bachoo et al.).
        seed: seed of the generator passed to trackers that take one.
        color: frame colour mode (:mod:`torchtrack.io.video`).
        on_frame: called with 1 after every frame (progress bars).
        device: where the tracker runs: frames are moved there before the tracker sees them
            (its generator is made there too); boxes come back on the CPU. The timing
            (``update_seconds``) then includes the frame's copy to the device.

    Returns:
        A :class:`RunResult`; exceptions raised by the tracker are caught into ``error``.

    Raises:
        ConfigError: the spec does not build a tracker.
    """
    device = check_device(device)
    tracker = _make_tracker(spec, seed, device)
    t = len(seq)
    gt = seq.boxes
    boxes = torch.full((t, 4), math.nan, dtype=torch.float64)
    visible = torch.zeros(t, dtype=torch.bool)
    conf = torch.zeros(t, dtype=torch.float64)
    res = RunResult(
        tracker=spec,
        sequence=seq.name,
        boxes=boxes,
        visible=visible,
        confidence=conf,
        init_frames=[],
        reinit_frames=[] if reinit else None,
    )
    initialised = False
    src = seq.open(color)
    i = -1
    try:
        for i, frame in src.items():
            if i >= t:
                break
            present = bool(torch.isfinite(gt[i]).all())
            if not initialised:
                res.init_frames.append(i)
                if frame is not None and present:
                    t0 = time.perf_counter()
                    st = tracker.init(frame.to(device), gt[i])
                    res.init_seconds += time.perf_counter() - t0
                    boxes[i], visible[i], conf[i] = st.box[0].cpu(), bool(st.visible[0]), 1.0
                    initialised = True
                elif frame is None:
                    res.bad_frames.append(i)
            elif frame is None:
                res.bad_frames.append(i)
                boxes[i] = boxes[i - 1]
            else:
                t0 = time.perf_counter()
                st = tracker.update(frame.to(device))
                res.update_seconds += time.perf_counter() - t0
                res.n_updates += 1
                boxes[i] = st.box[0].to("cpu", torch.float64)
                visible[i] = bool(st.visible[0])
                conf[i] = float(st.confidence[0])
                if reinit and present:
                    c_pred = boxes[i, :2] + boxes[i, 2:] / 2
                    c_gt = gt[i, :2] + gt[i, 2:] / 2
                    off = (c_pred - c_gt).abs()
                    if not bool(torch.isfinite(off).all()) or bool((off > break_px).any()):
                        t0 = time.perf_counter()
                        tracker.init(frame.to(device), gt[i])
                        res.init_seconds += time.perf_counter() - t0
                        res.reinit_frames.append(i)
            if on_frame is not None:
                on_frame(1)
    except Exception as exc:  # a failing tracker must not stop the whole evaluation
        res.error = f"{type(exc).__name__}: {exc}"
        res.error_frame = i
        res.traceback = traceback.format_exc(limit=8)
    finally:
        src.close()
    if res.error is None and i < t - 1:
        # The source ended before the ground truth did (a video shorter than its header): the
        # missing frames count as unreadable ones (last box carried, not visible).
        res.bad_frames.extend(range(i + 1, t))
        if initialised:
            boxes[i + 1 :] = boxes[i]
    if res.error is None and not initialised:
        res.error = "TrackerError: no frame with a readable image and a present target to start on"
    res.tracker_failures = getattr(tracker, "failures", None)
    return res


# ---------------------------------------------------------------------------------------------
# The whole evaluation
# ---------------------------------------------------------------------------------------------
def _task(
    spec: str,
    seq: Sequence,
    reinit: bool,
    seed: int,
    invisible: str,
    color: str,
    device: str = "cpu",
) -> dict:
    """Run and score one (tracker, sequence, seed) task; returns a JSON-ready record."""
    t0 = time.perf_counter()
    res = run_sequence(spec, seq, reinit=reinit, seed=seed, color=color, device=device)
    return _task_record(res, seq, reinit, invisible, wall_seconds=time.perf_counter() - t0)


def _unique_names(seqs: list[Sequence]) -> list[Sequence]:
    seen: dict[str, int] = {}
    out = []
    for s in seqs:
        k = seen.get(s.name, 0)
        seen[s.name] = k + 1
        if k:
            s = Sequence(**{**s.__dict__, "name": f"{s.name}#{k + 1}"})
        out.append(s)
    return out


def evaluate(
    sequences: list[Sequence],
    trackers: list[str],
    out_dir: str | os.PathLike,
    *,
    plots: bool = False,
    jobs: int | None = None,
    backend: str = "local",
    address: str | None = None,
    max_retries: int = 3,
    reinit: bool = False,
    invisible: str = "box",
    seed: int = 0,
    color: str = "rgb",
    progress: bool = True,
    command: str | None = None,
    modules: Sequence_[str] = (),
    device: str = "cpu",
) -> dict:
    """Run every tracker on every sequence and write the results (module doc).

    Args:
        sequences: the sequences (see :func:`torchtrack.io.sequences.find_sequences`).
        trackers: tracker specs ``name[:key=value,...]``; each spec is also its label.
        out_dir: output folder (created).
        plots: write success / precision PNGs.
        jobs: ``backend="local"``: parallel processes (``None`` or 1 = in this process);
            ``"ray"``: CPUs of the local Ray instance started when there is no ``address``.
        backend: ``"local"`` or ``"ray"`` (:mod:`torchtrack.eval.backends`): one task per
            (tracker, sequence, seed) and pass.
        address: the Ray cluster to use (``None``: ``RAY_ADDRESS``, else a new local instance).
        max_retries: times Ray reruns a task whose worker died.
        reinit: add the re-initialising pass (Bachoo metrics).
        invisible: ``"box"`` | ``"miss"``, see :mod:`torchtrack.eval.metrics`.
        seed, color, device: see :func:`run_sequence` (with ``jobs`` > 1 or Ray every worker
            uses that device).
        progress: show a tqdm bar over the frames of the whole corpus.
        command: the command line to record in the outputs.
        modules: Python modules to import first, here and in every worker process (modules
            that register their own trackers with ``register_tracker``).

    Returns:
        The dict written to ``results.json``.

    Raises:
        ConfigError: bad tracker specs, ``jobs < 1``, no sequence, an output folder that cannot
            be written.
        BackendError: Ray is not installed or its cluster cannot be reached.
    """
    from tqdm import tqdm

    from torchtrack.eval.backends import Backend, TaskFailure, check_backend, run_tasks
    from torchtrack.eval.report import results_markdown
    from torchtrack.io.atomic import check_writable_dir

    where = Backend(
        backend, jobs=jobs, address=address, max_retries=max_retries, modules=tuple(modules)
    )
    if not sequences:
        raise ConfigError("no sequence to evaluate")
    if invisible not in ("box", "miss"):
        raise ConfigError(f"invisible must be 'box' or 'miss', got {invisible!r}")
    for mod in modules:
        try:
            importlib.import_module(mod)
        except ImportError as exc:
            raise ConfigError(f"cannot import tracker module {mod!r}: {exc}") from exc
    device = str(check_device(device))
    validate_tracker_specs(trackers)
    check_backend(where)
    seqs = _unique_names(sequences)
    out = Path(out_dir)
    check_writable_dir(out, "--out")
    modes = [False, True] if reinit else [False]
    tasks = [(spec, s, m) for m in modes for s in seqs for spec in trackers]
    total = sum(len(s) for _, s, _ in tasks)
    records: list[dict] = []
    bar = tqdm(total=total, unit="frame", desc="eval", disable=not progress, leave=False)

    def done(rec: dict, seq: Sequence) -> None:
        sub = "sequences" if rec["mode"] == "ope" else "sequences_reinit"
        path = out / sub / safe_name(rec["sequence"]) / f"{safe_name(rec['tracker'])}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, json.dumps(rec, indent=1) + "\n")
        records.append(rec)
        if rec["error"]:
            at = _at_frame(rec["error_frame"], seq)
            bar.write(f"{rec['tracker']} failed on {rec['sequence']}{at}: {rec['error']}")

    try:
        if where.in_process:
            for spec, s, m in tasks:
                bar.set_postfix_str(f"{spec} / {s.name}", refresh=False)
                t0 = time.perf_counter()
                res = run_sequence(
                    spec, s, reinit=m, seed=seed, color=color, on_frame=bar.update, device=device
                )
                done(_task_record(res, s, m, invisible, wall_seconds=time.perf_counter() - t0), s)
        else:
            # Longest sequences first: with several workers the last task to start is a short
            # one, so no worker idles long at the end.
            order = sorted(tasks, key=lambda t: -len(t[1]))
            items = [(spec, s, m, seed, invisible, color, device) for spec, s, m in order]

            def finished(i: int, value) -> None:
                spec, s, m = order[i]
                if isinstance(value, TaskFailure):
                    value = _failed_record(spec, s, m, value.error, value.traceback)
                done(value, s)
                bar.update(len(s))

            run_tasks(_task, items, where, finished)
    finally:
        bar.close()

    summary = summarise(records, seqs, trackers, invisible=invisible, seed=seed, command=command)
    write_text_atomic(out / "results.json", json.dumps(summary, indent=1) + "\n")
    write_text_atomic(out / "results.md", results_markdown(summary))
    if plots:
        from torchtrack.eval.plots import write_plots

        summary["plots"] = write_plots(summary, out)
        write_text_atomic(out / "results.json", json.dumps(summary, indent=1) + "\n")
    return summary


def _at_frame(i: int | None, seq: Sequence) -> str:
    """`` at frame i (its file)`` for a run that failed on frame ``i`` (0-based), ``""`` when no
    frame is known (the run failed before its first frame, or in a worker that died)."""
    if i is None or i < 0:
        return ""
    if seq.frames is not None and i < len(seq.frames):
        return f" at frame {i} ({seq.frames[i]})"
    return f" at frame {i}"


def _task_record(
    res: RunResult, seq: Sequence, reinit: bool, invisible: str, wall_seconds: float = 0.0
) -> dict:
    rec = {
        "tracker": res.tracker,
        "sequence": seq.name,
        "mode": "reinit" if reinit else "ope",
        "n_frames": len(seq),
        "error": res.error,
        "error_frame": res.error_frame,
        "traceback": res.traceback,
        "fps": res.fps,
        "update_seconds": res.update_seconds,
        "init_seconds": res.init_seconds,
        "n_updates": res.n_updates,
        "wall_seconds": round(wall_seconds, 4),
        "worker": worker_info(),
        "tracker_failures": res.tracker_failures,
        "bad_frames": res.bad_frames,
        "init_frames": res.init_frames,
        "reinit_frames": res.reinit_frames,
        "metrics": None if res.error else res.metrics(seq.boxes, invisible).to_dict(),
        "boxes": [[None if math.isnan(v) else round(v, 3) for v in b] for b in res.boxes.tolist()],
        "visible": res.visible.tolist(),
        "confidence": [round(c, 5) for c in res.confidence.tolist()],
    }
    return rec


def _failed_record(
    spec: str, seq: Sequence, reinit: bool, error: str, trace: str | None = None
) -> dict:
    """The record of a task that gave no result (its worker raised or died)."""
    return {
        "tracker": spec,
        "sequence": seq.name,
        "mode": "reinit" if reinit else "ope",
        "n_frames": len(seq),
        "error": error,
        "error_frame": None,
        "traceback": trace,
        "fps": None,
        "update_seconds": 0.0,
        "init_seconds": 0.0,
        "n_updates": 0,
        "wall_seconds": None,
        "worker": None,
        "tracker_failures": None,
        "bad_frames": [],
        "init_frames": [],
        "reinit_frames": None,
        "metrics": None,
        "boxes": [],
        "visible": [],
        "confidence": [],
    }


_SCALAR_KEYS = (*SCALAR_METRICS, "x_error", "y_error", "n_present", "n_absent", "n_evaluated")


def summarise(
    records: list[dict],
    seqs: list[Sequence],
    trackers: list[str],
    *,
    invisible: str = "box",
    seed: int = 0,
    command: str | None = None,
) -> dict:
    """Build the ``results.json`` dict from per-run records."""
    import cv2

    from torchtrack import __version__

    summary: dict = {
        "command": command,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "versions": {"torchtrack": __version__, "torch": torch.__version__, "cv2": cv2.__version__},
        "settings": {"invisible": invisible, "seed": seed, "break_px": BREAK_PX},
        "sequences": [
            {"name": s.name, "layout": s.layout, "n_frames": len(s), "gt": str(s.gt_path)}
            for s in seqs
        ],
        "trackers": list(trackers),
        "overall": {},
        "overall_reinit": {},
        "per_sequence": {},
        "per_sequence_reinit": {},
    }
    order = {s.name: k for k, s in enumerate(seqs)}
    for mode, okey, pkey in (
        ("ope", "overall", "per_sequence"),
        ("reinit", "overall_reinit", "per_sequence_reinit"),
    ):
        recs = [r for r in records if r["mode"] == mode]
        if not recs:
            summary.pop(okey)
            summary.pop(pkey)
            continue
        recs.sort(key=lambda r: (order.get(r["sequence"], 0), trackers.index(r["tracker"])))
        per: dict = {}
        for r in recs:
            row = {
                "fps": r["fps"],
                "error": r["error"],
                "tracker_failures": r["tracker_failures"],
                "bad_frames": len(r["bad_frames"]),
                "n_frames": r["n_frames"],
            }
            if r["metrics"]:
                row.update({k: r["metrics"][k] for k in _SCALAR_KEYS})
                row["success"] = r["metrics"]["success"]
                row["precision"] = r["metrics"]["precision"]
            per.setdefault(r["sequence"], {})[r["tracker"]] = row
        summary[pkey] = per
        for spec in trackers:
            mine = [r for r in recs if r["tracker"] == spec]
            ok = [r for r in mine if not r["error"]]
            agg = aggregate_metrics([r["metrics"] for r in ok])
            upd = sum(r["update_seconds"] for r in ok)
            n_upd = sum(r["n_updates"] for r in ok)
            agg["fps"] = n_upd / upd if upd > 0 else None
            agg["n_frames"] = sum(r["n_frames"] for r in ok)
            agg["n_failed"] = len(mine) - len(ok)
            agg["failed"] = [
                {"sequence": r["sequence"], "error": r["error"], "frame": r["error_frame"]}
                for r in mine
                if r["error"]
            ]
            fails = [r["tracker_failures"] for r in ok if r["tracker_failures"] is not None]
            agg["tracker_failures"] = sum(fails) if fails else None
            agg["bad_frames"] = sum(len(r["bad_frames"]) for r in mine)
            summary[okey][spec] = agg
    return summary
