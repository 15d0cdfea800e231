"""Signed model files: Ed25519 signatures (through ``cryptography``) and the trust policy.

The checksum inside a model file (:mod:`torchtrack.detect.model_file`) detects corruption, not
forgery: anyone can edit a value and recompute it. A signature binds the file to a key: the
signer's Ed25519 private key signs the file's SHA-256 digest (which covers the whole JSON
description and every tensor's name, dtype, shape and bytes), and a loader that trusts the
matching public key accepts the file only when the signature verifies.

* **Where the signature lives.** In the safetensors header's ``__metadata__``, next to the
  ``torchtrack`` description, under ``torchtrack.signature``: a JSON object
  ``{"scheme": "ed25519", "key_id": "<16 hex>", "signature": "<base64 of 64 bytes>"}``. The
  signed message is ``b"torchtrack-model-signature\\n" + digest`` (the digest as stored in the
  description's ``sha256``), so signing never changes the description or the tensors.
* **Keys.** PEM files: the private key PKCS #8 (unencrypted, written with mode 0600), the
  public key SubjectPublicKeyInfo. ``key_id`` is the first 16 hex digits of the SHA-256 of
  the raw 32-byte public key. :func:`generate_key` makes a pair.
* **Trust.** A :class:`TrustPolicy` holds the trusted public keys and whether a signature is
  required. The bundled models' public key (``torchtrack/models/torchtrack-models.pub``) is
  always trusted; more come from ``--trusted-key FILE`` on the command line or from the
  environment variable ``TORCHTRACK_TRUSTED_KEYS`` (files separated by ``os.pathsep``).
  Signatures are required when ``TORCHTRACK_REQUIRE_SIGNED`` is ``1`` / ``true`` / ``yes``, or
  on the command line with ``--require-signed`` or any ``--trusted-key``.

Outcomes when a file is loaded (:func:`check_signature`):

==================================================  ==================  ====================
file                                                signatures optional  signatures required
==================================================  ==================  ====================
unsigned                                            loads (checksum)    refused
signed by a trusted key, signature verifies         loads               loads
signed by a trusted key, signature does not verify  refused (forged)    refused (forged)
signed by an unknown key                            loads (checksum)    refused
malformed signature block                           refused             refused
==================================================  ==================  ====================
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchtrack.errors import ConfigError, ModelFormatError

__all__ = [
    "BUNDLED_KEY",
    "SIGNATURE_KEY",
    "TrustPolicy",
    "check_signature",
    "generate_key",
    "key_id",
    "load_private_key",
    "load_public_key",
    "sign_digest",
]

SIGNATURE_KEY = "torchtrack.signature"
SCHEME = "ed25519"
_DOMAIN = b"torchtrack-model-signature\n"
#: The public key the bundled models are signed with (its private key is never in the repository).
BUNDLED_KEY = Path(__file__).resolve().parents[1] / "models" / "torchtrack-models.pub"
ENV_KEYS = "TORCHTRACK_TRUSTED_KEYS"
ENV_REQUIRE = "TORCHTRACK_REQUIRE_SIGNED"


def _message(digest: str) -> bytes:
    return _DOMAIN + digest.encode("ascii")


def key_id(public_key: Any) -> str:
    """First 16 hex digits of the SHA-256 of the raw 32-byte Ed25519 public key."""
    from cryptography.hazmat.primitives import serialization

    raw = public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()[:16]


def load_public_key(path: str | os.PathLike) -> Any:
    """An Ed25519 public key from a PEM file.

    Raises:
        ConfigError: the file is missing, unreadable or not an Ed25519 public key.
    """
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"trusted key {str(p)!r} cannot be read: {exc.strerror or exc}") from None
    try:
        key = serialization.load_pem_public_key(data)
    except (ValueError, TypeError):
        raise ConfigError(
            f"trusted key {str(p)!r} is not a PEM public key (expected the .pub file that "
            "`torchtrack sign --new-key` writes)"
        ) from None
    if not isinstance(key, Ed25519PublicKey):
        raise ConfigError(f"trusted key {str(p)!r} is not an Ed25519 key")
    return key


def load_private_key(path: str | os.PathLike) -> Any:
    """An Ed25519 private key from an unencrypted PEM (PKCS #8) file.

    Raises:
        ConfigError: the file is missing, unreadable, encrypted or not an Ed25519 private key.
    """
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"signing key {str(p)!r} cannot be read: {exc.strerror or exc}") from None
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as exc:
        raise ConfigError(
            f"signing key {str(p)!r} is not an unencrypted PEM private key ({exc})"
        ) from None
    if not isinstance(key, Ed25519PrivateKey):
        raise ConfigError(f"signing key {str(p)!r} is not an Ed25519 key")
    return key


def generate_key(private_path: str | os.PathLike, public_path: str | os.PathLike | None = None):
    """Write a new Ed25519 key pair: the private key to ``private_path`` (mode 0600, never
    overwritten) and the public key to ``public_path`` (default: ``private_path`` with the
    suffix ``.pub``). Returns ``(private_path, public_path, key_id)``.

    Raises:
        ConfigError: either file exists already, its folder does not exist, or it cannot be
            written (then neither is left).
    """
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    priv_p = Path(private_path)
    pub_p = Path(public_path) if public_path is not None else priv_p.with_suffix(".pub")
    if priv_p == pub_p:
        raise ConfigError(f"the private and public key paths are the same: {str(priv_p)!r}")
    for p in (priv_p, pub_p):
        if p.exists():
            raise ConfigError(f"{str(p)!r} exists already: key files are never overwritten")
        if not p.parent.is_dir():
            raise ConfigError(f"folder {str(p.parent)!r} does not exist")
    key = Ed25519PrivateKey.generate()
    priv_pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    pub = key.public_key()
    pub_pem = pub.public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    from torchtrack.io.atomic import write_bytes_atomic, write_error

    try:
        fd = os.open(priv_p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise write_error(priv_p, exc) from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(priv_pem)
        write_bytes_atomic(pub_p, pub_pem)
    except BaseException as exc:
        priv_p.unlink(missing_ok=True)  # never half a key pair
        if isinstance(exc, OSError):
            raise write_error(priv_p, exc) from None
        raise
    return priv_p, pub_p, key_id(pub)


def sign_digest(private_key: Any, digest: str) -> str:
    """The signature block (a JSON string) of a model digest, for the header's
    ``torchtrack.signature`` entry."""
    sig = private_key.sign(_message(digest))
    return json.dumps(
        {
            "scheme": SCHEME,
            "key_id": key_id(private_key.public_key()),
            "signature": base64.b64encode(sig).decode("ascii"),
        },
        sort_keys=True,
    )


def _truthy(text: str | None) -> bool:
    return (text or "").strip().lower() in ("1", "true", "yes", "on")


@dataclass(frozen=True)
class TrustPolicy:
    """Which signers a loader trusts and whether a signature is required.

    Attributes:
        keys: trusted public keys by ``key_id``.
        require: refuse files without a valid signature of a trusted key.
        sources: where each key came from (for messages), by ``key_id``.
    """

    keys: dict[str, Any] = field(default_factory=dict)
    require: bool = False
    sources: dict[str, str] = field(default_factory=dict)

    @classmethod
    def build(
        cls, key_files: list[str | os.PathLike] | tuple = (), require: bool = False
    ) -> TrustPolicy:
        """The bundled key plus the public keys in ``key_files``.

        Raises:
            ConfigError: a key file cannot be read or is not an Ed25519 public key.
        """
        keys: dict[str, Any] = {}
        sources: dict[str, str] = {}
        files = [BUNDLED_KEY] if BUNDLED_KEY.is_file() else []
        files += [Path(f) for f in key_files]
        for f in files:
            k = load_public_key(f)
            kid = key_id(k)
            keys[kid] = k
            sources.setdefault(kid, str(f))
        return cls(keys=keys, require=bool(require), sources=sources)

    @classmethod
    def from_env(cls) -> TrustPolicy:
        """The policy of ``TORCHTRACK_TRUSTED_KEYS`` / ``TORCHTRACK_REQUIRE_SIGNED`` (the
        bundled key is always trusted)."""
        raw = os.environ.get(ENV_KEYS, "")
        files = [f for f in raw.split(os.pathsep) if f.strip()]
        return cls.build(files, require=_truthy(os.environ.get(ENV_REQUIRE)))


def check_signature(
    block: str | None, digest: str, policy: TrustPolicy, where: str
) -> tuple[str, str | None]:
    """Check a model file's signature block against ``policy``.

    Args:
        block: the header's ``torchtrack.signature`` value (``None``: unsigned).
        digest: the model's SHA-256 digest, already checked against its content.
        policy: the trust policy.
        where: the file, for messages.

    Returns:
        ``(status, key_id)`` with status ``"verified"``, ``"unsigned"`` or ``"untrusted"``.

    Raises:
        ModelFormatError: see the table in the module doc.
    """
    if block is None:
        if policy.require:
            raise ModelFormatError(
                f"{where} is not signed and signatures are required (--trusted-key / "
                f"--require-signed / {ENV_REQUIRE}); sign it with `torchtrack sign`"
            )
        return "unsigned", None
    try:
        d = json.loads(block)
    except (TypeError, ValueError):
        d = None
    if (
        not isinstance(d, dict)
        or set(d) != {"scheme", "key_id", "signature"}
        or not all(isinstance(v, str) for v in d.values())
    ):
        raise ModelFormatError(
            f"{where}: malformed signature block (expected scheme, key_id and signature strings)"
        )
    if d["scheme"] != SCHEME:
        raise ModelFormatError(f"{where}: unknown signature scheme {d['scheme']!r} ({SCHEME} only)")
    try:
        sig = base64.b64decode(d["signature"], validate=True)
    except (binascii.Error, ValueError):
        sig = b""
    if len(sig) != 64:
        raise ModelFormatError(f"{where}: malformed signature (not 64 bytes of base64)")
    kid = d["key_id"]
    key = policy.keys.get(kid)
    if key is None:
        if policy.require:
            raise ModelFormatError(
                f"{where} is signed by key {kid}, which is not trusted here (trusted: "
                f"{', '.join(sorted(policy.keys)) or 'none'}); pass its public key with "
                "--trusted-key"
            )
        return "untrusted", kid
    from cryptography.exceptions import InvalidSignature

    try:
        key.verify(sig, _message(digest))
    except InvalidSignature:
        raise ModelFormatError(
            f"{where}: the signature of key {kid} does not verify: the file was altered after "
            "it was signed (or forged); do not use it"
        ) from None
    return "verified", kid
