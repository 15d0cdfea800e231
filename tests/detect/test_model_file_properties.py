"""Property tests of the model loader (Hypothesis): random mutations of a valid file end in a
typed error or in a model that scores identically; forged files are refused when signatures
are required."""

import json
import struct
import tempfile
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_model_file import frames_boxes, make_detector

from torchtrack.detect import load_detector, save_detector
from torchtrack.detect.signing import TrustPolicy, generate_key
from torchtrack.errors import ModelFormatError

SETTINGS = settings(
    max_examples=150,
    deadline=None,
    derandomize=True,  # the same examples on every run (CI)
    suppress_health_check=[HealthCheck.too_slow],
)


class Env:
    """One signed model (and an SVM one) and the scores they give, shared by the examples."""

    def __init__(self) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="tt-props-"))
        self.priv, self.pub, _ = generate_key(self.dir / "k.pem")
        self.frames, self.boxes = frames_boxes()
        self.files = {}
        self.scores = {}
        for name, svm in (("stumps", False), ("svm", True)):
            det = make_detector(svm=svm)
            path = save_detector(self.dir / f"{name}.safetensors", det, signing_key=self.priv)
            self.files[name] = path.read_bytes()
            self.scores[name] = det.score(self.frames, self.boxes)
        self.trusted = TrustPolicy.build([self.pub])
        self.required = TrustPolicy.build([self.pub], require=True)
        self.n = 0

    def write(self, data: bytes) -> Path:
        self.n += 1
        p = self.dir / f"case{self.n % 8}.safetensors"
        p.write_bytes(data)
        return p


@pytest.fixture(scope="module")
def env():
    return Env()


# ------------------------------------------------------------------------- byte mutations
byte_op = st.one_of(
    st.tuples(st.just("flip"), st.integers(0, 10**9), st.integers(0, 7)),
    st.tuples(st.just("set"), st.integers(0, 10**9), st.integers(0, 255)),
    st.tuples(st.just("insert"), st.integers(0, 10**9), st.binary(min_size=1, max_size=16)),
    st.tuples(st.just("delete"), st.integers(0, 10**9), st.integers(1, 64)),
    st.tuples(st.just("truncate"), st.integers(0, 10**9), st.just(0)),
    st.tuples(st.just("append"), st.just(0), st.binary(min_size=1, max_size=64)),
)


def mutate_bytes(data: bytes, ops) -> bytes:
    b = bytearray(data)
    for op, pos, arg in ops:
        i = pos % max(len(b), 1)
        if op == "flip" and b:
            b[i] ^= 1 << arg
        elif op == "set" and b:
            b[i] = arg
        elif op == "insert":
            b[i:i] = arg
        elif op == "delete":
            del b[i : i + arg]
        elif op == "truncate":
            del b[i:]
        elif op == "append":
            b += arg
    return bytes(b)


@SETTINGS
@given(which=st.sampled_from(["stumps", "svm"]), ops=st.lists(byte_op, min_size=1, max_size=4))
def test_byte_mutations_give_a_typed_error_or_the_same_scores(env, which, ops):
    data = mutate_bytes(env.files[which], ops)
    path = env.write(data)
    try:
        det = load_detector(path, trust=env.trusted)
    except ModelFormatError:
        return
    torch.testing.assert_close(det.score(env.frames, env.boxes), env.scores[which], rtol=0, atol=0)


# ------------------------------------------------------------- semantic (forger's) edits
json_value = st.recursive(
    st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-(2**70), 2**70),
        st.floats(allow_nan=False, allow_infinity=False),
        st.sampled_from([0, 1, -1, 4, 16, 100000, 1e308, -1e308, 0.5, "platt", "svm", ""]),
        st.text(max_size=8),
    ),
    lambda inner: st.one_of(
        st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=6,
)


def _paths(node, prefix=()):
    """Every (path) to a value inside a JSON tree."""
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


def _set_path(root, path, value, delete=False):
    if not path:
        return value
    node = root
    for k in path[:-1]:
        node = node[k]
    if delete and isinstance(node, dict):
        del node[path[-1]]
    elif delete and isinstance(node, list):
        node.pop(path[-1])
    else:
        node[path[-1]] = value
    return root


tensor_value = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.sampled_from([1e30, -1e30, 1000.0, -1000.0, 0.0, 2**40]),
)


@st.composite
def forgery(draw, meta, tensors):
    """A forger's edit: a JSON value replaced or deleted, or a tensor element or shape changed."""
    kind = draw(st.sampled_from(["meta", "meta", "tensor", "shape"]))
    meta = json.loads(json.dumps(meta))
    tensors = {k: v.clone() for k, v in tensors.items()}
    if kind == "meta":
        paths = [p for p in _paths(meta) if p and p[0] != "sha256"]
        path = draw(st.sampled_from(paths))
        delete = draw(st.booleans())
        meta = _set_path(meta, path, draw(json_value), delete=delete)
    else:
        name = draw(st.sampled_from(sorted(tensors)))
        t = tensors[name]
        if kind == "tensor" and t.numel():
            i = draw(st.integers(0, t.numel() - 1))
            flat = t.reshape(-1)
            if t.is_floating_point():
                flat[i] = draw(tensor_value)
            else:
                flat[i] = draw(st.integers(-(2**40), 2**40))
        else:
            n = t.shape[0] if t.ndim else 1
            tensors[name] = t[: draw(st.integers(0, max(n - 1, 0)))]
    return meta, tensors


def _forge_bytes(src: bytes, meta, tensors, signature: str | None) -> bytes:
    from safetensors.torch import save

    from torchtrack.detect.model_file import _digest

    if isinstance(meta, dict):
        meta.pop("sha256", None)
        meta["sha256"] = _digest(meta, tensors)  # the forger recomputes the checksum
    md = {"torchtrack": json.dumps(meta)}
    if signature is not None:
        md["torchtrack.signature"] = signature
    return save({k: v.contiguous() for k, v in tensors.items()}, metadata=md)


def _parts(data: bytes):
    from safetensors.torch import load

    (n,) = struct.unpack("<Q", data[:8])
    md = json.loads(data[8 : 8 + n])["__metadata__"]
    return json.loads(md["torchtrack"]), load(data), md.get("torchtrack.signature")


@SETTINGS
@given(which=st.sampled_from(["stumps", "svm"]), data=st.data())
def test_forged_files_are_refused_when_signed_or_when_signatures_are_required(env, which, data):
    meta, tensors, sig = _parts(env.files[which])
    meta, tensors = data.draw(forgery(meta, tensors))
    # 1. the forger keeps the signature: it no longer verifies (signatures optional or not)
    kept = env.write(_forge_bytes(env.files[which], json.loads(json.dumps(meta)), tensors, sig))
    try:
        det = load_detector(kept, trust=env.trusted)
    except ModelFormatError:
        pass
    else:  # only an edit that changed nothing can pass
        assert det.score(env.frames, env.boxes).equal(env.scores[which])
    # 2. the forger strips it: refused whenever signatures are required
    stripped = env.write(_forge_bytes(env.files[which], meta, tensors, None))
    with pytest.raises(ModelFormatError):
        load_detector(stripped, trust=env.required)
    # 3. ... and without the requirement: a typed error, or a model that scores sanely
    try:
        det = load_detector(stripped, trust=env.trusted)
    except ModelFormatError:
        return
    if det.calibrator is None:  # "calibration": null is a valid, uncalibrated model
        assert bool(torch.isfinite(det.decision_function(env.frames, env.boxes)).all())
        return
    p = det.score(env.frames, env.boxes)
    assert bool(torch.isfinite(p).all()) and bool(((p >= 0) & (p <= 1)).all())
