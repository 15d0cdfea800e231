"""``torchtrack sign``: Ed25519 key pairs, signing model files, checking their signatures.

A model file's checksum detects corruption; a signature tells who made the file
(:mod:`torchtrack.detect.signing`). Loaders trust the bundled models' key plus the keys given
with ``--trusted-key`` (or ``TORCHTRACK_TRUSTED_KEYS``) and, when signatures are required,
refuse anything else.
"""

from __future__ import annotations

import argparse

_EPILOG = """\
examples:
  # once: a key pair (the private key never goes into a repository; keep it mode 0600)
  torchtrack sign --new-key ~/keys/my-models.pem         # writes my-models.pem and my-models.pub

  # sign a model (in place; -o writes a signed copy)
  torchtrack sign my.safetensors --key ~/keys/my-models.pem

  # check a model and see who signed it
  torchtrack sign --check my.safetensors --trusted-key ~/keys/my-models.pub

  # a colleague loads only files you signed
  torchtrack detect my.safetensors photos/ --trusted-key my-models.pub

Re-signing the bundled models after they are retrained (maintainers, with the project key
kept outside the repository, e.g. /work/keys/torchtrack-models.pem):
  python train/default_models.py --sign-key /work/keys/torchtrack-models.pem
  torchtrack sign torchtrack/models/pedestrian.safetensors --key /work/keys/torchtrack-models.pem
"""


def register(subparsers) -> None:
    from torchtrack.cli._common import add_out, add_progress, add_trust

    p = subparsers.add_parser(
        "sign",
        help="sign model files (Ed25519), make key pairs, check signatures",
        description=(
            "Sign a model file with an Ed25519 private key (the file is validated first and "
            "only its signature entry changes), make a key pair (--new-key), or validate a "
            "model and print how it is signed (--check)."
        ),
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("model", nargs="?", metavar="MODEL", help="model file to sign or check")
    p.add_argument("--key", metavar="PEM", help="Ed25519 private key to sign with")
    add_out(
        p, "MODEL", "write the signed model here (default: MODEL itself; needed for a bundled name)"
    )
    p.add_argument(
        "--new-key",
        metavar="PEM",
        help="write a new key pair: the private key to PEM (mode 0600), the public key next to "
        "it with the suffix .pub",
    )
    p.add_argument("--check", action="store_true", help="validate MODEL and print its signer")
    add_trust(p)
    add_progress(p)  # accepted like everywhere; signing draws no bar
    p.set_defaults(func=run)


def check_outputs(args: argparse.Namespace) -> None:
    from torchtrack.cli._common import check_output_file, check_spares_inputs

    if args.new_key:
        check_output_file(args.new_key, "--new-key")
    # the signed model never lands on a key (a private key overwritten is lost for good)
    keys = {"--key": args.key, "--trusted-key": getattr(args, "trusted_key", None) or []}
    check_spares_inputs({"--out": args.out, "--new-key": args.new_key}, keys)
    if args.out:  # a model file (-o KEY.pub wrote the model over the public key)
        check_output_file(args.out, "--out", (".safetensors",))


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from torchtrack.errors import ConfigError

    modes = sum(bool(x) for x in (args.new_key, args.check, args.key))
    if modes != 1:
        raise ConfigError("give exactly one of --key PEM (sign), --new-key PEM or --check")
    check_outputs(args)
    trust = [f for f, used in (("--trusted-key", args.trusted_key),
                               ("--require-signed", args.require_signed)) if used]  # fmt: skip
    if trust and not args.check:  # signing ignored them, then refused its own output (kept)
        raise ConfigError(
            f"{' / '.join(trust)} decide(s) which model files are accepted: they go with --check "
            "(and the commands that load models), not with --key or --new-key"
        )
    if args.new_key:
        if args.model:
            raise ConfigError("--new-key makes a key pair; it takes no MODEL")
        from torchtrack.detect.signing import generate_key

        priv, pub, kid = generate_key(args.new_key)
        print(f"wrote {priv} (private, keep it secret) and {pub} (public); key id {kid}")
        return 0
    if not args.model:
        raise ConfigError("give the MODEL file")
    from torchtrack.detect.bundled import resolve_model
    from torchtrack.detect.model_file import model_signature, sign_model

    path = resolve_model(args.model)
    if args.check:
        if args.out:
            raise ConfigError("--check writes nothing; drop --out")
        st = model_signature(path)
        text = {
            "verified": f"signed by trusted key {st.key_id}; the signature verifies",
            "untrusted": f"signed by key {st.key_id}, which is not trusted here",
            "unsigned": "not signed",
        }[st.status]
        print(f"{path}: valid model file, {text}")
        return 0
    if args.out is None and path != Path(args.model):
        # the name of a bundled model: its installed file was signed in place with this key
        # (no longer the project's), as calibrate refuses to rewrite it
        raise ConfigError(
            f"MODEL {args.model!r} is a bundled model: give -o OUT for the signed copy (the "
            "installed model file is not rewritten)"
        )
    dest = sign_model(path, args.key, args.out)
    from torchtrack.detect.signing import TrustPolicy

    # who signed it, whatever TORCHTRACK_REQUIRE_SIGNED says: the file is written and signed
    st = model_signature(dest, trust=TrustPolicy.build([]))
    print(f"wrote {dest}: signed by key {st.key_id}")
    return 0
