import json
import os
import stat
import struct

import pytest
from test_model_file import frames_boxes, make_detector

from torchtrack.detect import load_detector, save_detector
from torchtrack.detect.bundled import MODELS_DIR, bundled_models, load_model
from torchtrack.detect.model_file import model_signature, sign_model
from torchtrack.detect.signing import (
    BUNDLED_KEY,
    ENV_KEYS,
    ENV_REQUIRE,
    SIGNATURE_KEY,
    TrustPolicy,
    generate_key,
    key_id,
    load_public_key,
)
from torchtrack.errors import ConfigError, ModelFormatError


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    d = tmp_path_factory.mktemp("keys")
    a = generate_key(d / "a.pem")
    b = generate_key(d / "b.pem")
    return {"a": a, "b": b}


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    monkeypatch.delenv(ENV_KEYS, raising=False)
    monkeypatch.delenv(ENV_REQUIRE, raising=False)


def trust(*pubs, require=False):
    return TrustPolicy.build(list(pubs), require=require)


def test_bundled_models_are_signed_by_the_shipped_key():
    """Retrained bundled models must be signed again (see torchtrack/models/README.md)."""
    assert BUNDLED_KEY.is_file()
    kid = key_id(load_public_key(BUNDLED_KEY))
    names = bundled_models()
    assert names
    for name in names:
        st = model_signature(MODELS_DIR / f"{name}.safetensors", trust=trust(require=True))
        assert (st.status, st.key_id) == ("verified", kid), name
        load_model(name)


def test_private_key_is_private_and_never_overwritten(keys, tmp_path):
    priv, pub, kid = keys["a"]
    assert stat.S_IMODE(os.stat(priv).st_mode) == 0o600
    assert pub.suffix == ".pub" and len(kid) == 16
    with pytest.raises(ConfigError, match="never overwritten"):
        generate_key(priv)
    with pytest.raises(ConfigError, match="does not exist"):
        generate_key(tmp_path / "missing" / "k.pem")


def test_sign_then_verify(tmp_path, keys):
    priv, pub, kid = keys["a"]
    path = save_detector(tmp_path / "m.safetensors", make_detector())
    assert model_signature(path).status == "unsigned"
    before = path.read_bytes()
    sign_model(path, priv)
    after = path.read_bytes()
    # only the header changed: the tensor bytes are kept as they were
    n0, n1 = struct.unpack("<Q", before[:8])[0], struct.unpack("<Q", after[:8])[0]
    assert before[8 + n0 :] == after[8 + n1 :]
    st = model_signature(path, trust=trust(pub, require=True))
    assert (st.status, st.key_id) == ("verified", kid)
    frames, boxes = frames_boxes()
    det = load_detector(path, trust=trust(pub, require=True))
    assert det.score(frames, boxes).equal(make_detector().score(frames, boxes))
    # the same file for someone who does not trust key a
    assert model_signature(path).status == "untrusted"
    with pytest.raises(ModelFormatError, match="not trusted here"):
        load_detector(path, trust=trust(keys["b"][1], require=True))


def test_save_signs(tmp_path, keys):
    priv, pub, kid = keys["b"]
    path = save_detector(tmp_path / "m.safetensors", make_detector(), signing_key=priv)
    assert model_signature(path, trust=trust(pub)).key_id == kid


def test_unsigned_policy(tmp_path, keys, monkeypatch):
    path = save_detector(tmp_path / "m.safetensors", make_detector())
    load_detector(path)  # signatures optional: loads with the checksum and range checks
    with pytest.raises(ModelFormatError, match="not signed and signatures are required"):
        load_detector(path, trust=trust(require=True))
    monkeypatch.setenv(ENV_REQUIRE, "1")
    with pytest.raises(ModelFormatError, match="not signed"):
        load_detector(path)
    monkeypatch.setenv(ENV_KEYS, str(keys["a"][1]))
    sign_model(path, keys["a"][0])
    load_detector(path)  # trusted through the environment


def test_forged_signed_file_is_refused_even_when_signatures_are_optional(
    tmp_path, keys, forge_model
):
    priv, pub, _ = keys["a"]
    path = save_detector(tmp_path / "m.safetensors", make_detector(), signing_key=priv)
    bad = forge_model(
        path,
        tmp_path / "bad.safetensors",
        meta_edit=lambda m: m["calibration"].update(b=m["calibration"]["b"] + 1),
    )
    with pytest.raises(ModelFormatError, match="does not verify"):
        load_detector(bad, trust=trust(pub))
    # stripping the signature makes it an unsigned file: refused when signatures are required
    stripped = forge_model(bad, tmp_path / "stripped.safetensors", keep_signature=False)
    load_detector(stripped, trust=trust(pub))
    with pytest.raises(ModelFormatError, match="not signed"):
        load_detector(stripped, trust=trust(pub, require=True))


@pytest.mark.parametrize(
    "block, match",
    [
        ("not json", "malformed signature block"),
        (json.dumps({"scheme": "ed25519"}), "malformed signature block"),
        (json.dumps({"scheme": "rsa", "key_id": "x", "signature": "AA=="}), "unknown signature"),
        (json.dumps({"scheme": "ed25519", "key_id": "x", "signature": "!!"}), "not 64 bytes"),
    ],
)
def test_malformed_signature_block(tmp_path, keys, forge_model, block, match):
    path = save_detector(tmp_path / "m.safetensors", make_detector(), signing_key=keys["a"][0])
    bad = forge_model(
        path,
        tmp_path / "bad.safetensors",
        header_edit=lambda h: h["__metadata__"].update({SIGNATURE_KEY: block}),
    )
    with pytest.raises(ModelFormatError, match=match):
        load_detector(bad)


def test_a_signature_from_another_file_does_not_verify(tmp_path, keys, forge_model):
    priv, pub, _ = keys["a"]
    one = save_detector(tmp_path / "one.safetensors", make_detector(), signing_key=priv)
    two = save_detector(tmp_path / "two.safetensors", make_detector(svm=True))

    def graft(h):
        data = one.read_bytes()
        (n,) = struct.unpack("<Q", data[:8])
        h["__metadata__"][SIGNATURE_KEY] = json.loads(data[8 : 8 + n])["__metadata__"][
            SIGNATURE_KEY
        ]

    bad = forge_model(two, tmp_path / "bad.safetensors", header_edit=graft)
    with pytest.raises(ModelFormatError, match="does not verify"):
        load_detector(bad, trust=trust(pub))


def test_bad_key_files(tmp_path, keys):
    junk = tmp_path / "junk.pub"
    junk.write_text("hello")
    with pytest.raises(ConfigError, match="not a PEM public key"):
        TrustPolicy.build([junk])
    with pytest.raises(ConfigError, match="cannot be read"):
        TrustPolicy.build([tmp_path / "missing.pub"])
    path = save_detector(tmp_path / "m.safetensors", make_detector())
    with pytest.raises(ConfigError, match="not an unencrypted PEM private key"):
        sign_model(path, keys["a"][1])  # the public key given as the signing key


def test_cli_sign_and_trusted_key(tmp_path, capsys):
    from torchtrack.cli import main

    key = tmp_path / "k.pem"
    assert main(["sign", "--new-key", str(key)]) == 0
    model = save_detector(tmp_path / "m.safetensors", make_detector())
    frames = tmp_path / "img.png"
    import cv2
    import numpy as np

    cv2.imwrite(str(frames), np.random.default_rng(0).integers(0, 255, (40, 30), np.uint8))
    detect = ["detect", str(model), str(frames), "-q", "--trusted-key", str(tmp_path / "k.pub")]
    out = tmp_path / "d.jsonl"
    assert main([*detect, "-o", str(out)]) == 1
    assert "not signed" in capsys.readouterr().err and not out.exists()
    assert main(["sign", str(model), "--key", str(key)]) == 0
    assert main(["sign", "--check", str(model)]) == 0
    assert "not trusted here" in capsys.readouterr().out
    assert main(["sign", "--check", str(model), "--trusted-key", str(tmp_path / "k.pub")]) == 0
    assert "the signature verifies" in capsys.readouterr().out
    assert main([*detect, "-o", str(out)]) == 0 and out.exists()
    assert os.environ.get(ENV_REQUIRE) is None  # the policy does not leak out of the command
    assert main(["sign", str(model)]) == 1
    assert "exactly one of" in capsys.readouterr().err
