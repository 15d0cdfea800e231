"""Forge and corrupt a real model file many times and count what the loader does.

    python tools/check_forgeries.py --model pedestrian --n 1000 --seed 0

For each of ``--n`` trials, one random edit of the signed bundled model (or any model file):

* **corruption**: 1-4 random byte edits (flip, overwrite, insert, delete, truncate, append);
* **forgery**: one value of the JSON description replaced (another type, a perturbed,
  sign-flipped or huge number, a deleted key) or one tensor element changed, with the checksum
  recomputed as a forger would; once with the original signature kept, once stripped.

It prints how many ended in a ``ModelFormatError``, how many loaded, whether a loaded model
scores identically to the original on fixed boxes of a real frame, and how many ended in any
other exception (a traceback: must be 0). The goal of issue 12: every forgery refused when
signatures are required.
"""

from __future__ import annotations

import argparse
import copy
import json
import random
import struct
import sys
import tempfile
from collections import Counter
from pathlib import Path

import torch
from safetensors.torch import load, save

from torchtrack.detect import load_detector
from torchtrack.detect.bundled import resolve_model
from torchtrack.detect.model_file import _digest
from torchtrack.detect.signing import SIGNATURE_KEY, TrustPolicy
from torchtrack.errors import ModelFormatError


def _paths(node, prefix=()):
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


def _new_value(rng: random.Random, old):
    choice = rng.randrange(9)
    if isinstance(old, (int, float)) and not isinstance(old, bool) and choice < 4:
        return [
            old * (1 + rng.uniform(-0.2, 0.2)),
            -old,
            old + rng.choice([1, -1, 1000, 10**6]),
            rng.choice([1e308, -1e308, 1e-300]),
        ][choice]
    return rng.choice(
        [None, True, "x", [], {}, [old], -1, 0, 2**63, 100000, 1.5, [100000, 100000], "nan"]
    )


def _forge(data: bytes, rng: random.Random) -> tuple[bytes, bytes]:
    """(forgery with the signature kept, the same with it stripped)."""
    (n,) = struct.unpack("<Q", data[:8])
    md = json.loads(data[8 : 8 + n])["__metadata__"]
    meta = json.loads(md["torchtrack"])
    tensors = {k: v.clone() for k, v in load(data).items()}
    if rng.random() < 0.6:
        paths = [p for p in _paths(meta) if p and p[0] != "sha256"]
        path = rng.choice(paths)
        node = meta
        for k in path[:-1]:
            node = node[k]
        if rng.random() < 0.15 and isinstance(node, dict):
            del node[path[-1]]
        else:
            node[path[-1]] = _new_value(rng, copy.deepcopy(node[path[-1]]))
    else:
        name = rng.choice(sorted(tensors))
        flat = tensors[name].reshape(-1)
        i = rng.randrange(flat.numel())
        if flat.is_floating_point():
            flat[i] = rng.choice(
                [float(flat[i]) * 1.01, -float(flat[i]), float(flat[i]) + 1000, float("nan")]
            )
        else:
            flat[i] = int(flat[i]) + rng.choice([1, -1, 10**6, -(10**6)])
    meta.pop("sha256", None)
    meta["sha256"] = _digest(meta, tensors)
    out = {"torchtrack": json.dumps(meta)}
    stripped = save(tensors, metadata=out)
    out[SIGNATURE_KEY] = md.get(SIGNATURE_KEY, "")
    kept = save(tensors, metadata=out) if SIGNATURE_KEY in md else stripped
    return kept, stripped


def _corrupt(data: bytes, rng: random.Random) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        i = rng.randrange(max(len(b), 1))
        op = rng.randrange(6)
        if op == 0 and b:
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1 and b:
            b[i] = rng.randrange(256)
        elif op == 2:
            b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
        elif op == 3:
            del b[i : i + rng.randint(1, 64)]
        elif op == 4:
            del b[i:]
        else:
            b += bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))
    return bytes(b)


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--model", default="pedestrian", help="model file or bundled name")
    ap.add_argument("--n", type=int, default=1000, help="trials per kind")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    src = resolve_model(args.model)
    data = src.read_bytes()
    optional = TrustPolicy.build([])
    required = TrustPolicy.build([], require=True)
    original = load_detector(src, trust=optional)
    g = torch.Generator().manual_seed(0)
    frames = torch.randint(0, 256, (1, 3, 240, 320), dtype=torch.uint8, generator=g)
    boxes = torch.tensor([[[10.0, 20.0, 64.0, 128.0], [100.5, 30.2, 80.0, 160.0]]])
    ref = original.score(frames, boxes)
    tmp = Path(tempfile.mkdtemp(prefix="forgeries-"))
    counts: Counter = Counter()

    def trial(kind: str, blob: bytes, trust: TrustPolicy) -> None:
        p = tmp / "m.safetensors"
        p.write_bytes(blob)
        try:
            det = load_detector(p, trust=trust)
        except ModelFormatError:
            counts[(kind, "refused")] += 1
            return
        except Exception as exc:  # a traceback: what issue 12 forbids
            counts[(kind, f"OTHER {type(exc).__name__}")] += 1
            return
        try:
            same = bool(torch.equal(det.score(frames, boxes), ref))
        except Exception as exc:
            counts[(kind, f"OTHER at scoring {type(exc).__name__}")] += 1
            return
        counts[(kind, "loaded, same scores" if same else "loaded, other scores")] += 1

    for _ in range(args.n):
        trial("corrupted bytes (signatures optional)", _corrupt(data, rng), optional)
        kept, stripped = _forge(data, rng)
        trial("forged, signature kept (signatures optional)", kept, optional)
        trial("forged, signature stripped (signatures required)", stripped, required)
        trial("forged, signature stripped (signatures optional)", stripped, optional)
    print(f"model {src} ({len(data):,} bytes), {args.n} trials per kind, seed {args.seed}")
    for kind in dict.fromkeys(k for k, _ in counts):
        parts = ", ".join(f"{what} {n}" for (k, what), n in sorted(counts.items()) if k == kind)
        print(f"  {kind}: {parts}")
    bad = sum(n for (_, what), n in counts.items() if what.startswith("OTHER"))
    print(f"tracebacks (not a ModelFormatError): {bad}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
