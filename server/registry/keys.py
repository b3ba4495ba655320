"""The key that signs registry tokens, and the certificate the registry verifies them with.

The registry (CNCF distribution) trusts a token when the certificate in its ``x5c`` header
chains to its ``rootcertbundle``; here that bundle is the one self-signed certificate of the
server's key. The files are named as in a ``kubernetes.io/tls`` Secret (``tls.key``,
``tls.crt``), so a mounted Secret is a key directory as it is.
"""

from __future__ import annotations

import base64
import datetime as dt
import os
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

KEY_FILE = "tls.key"
CERT_FILE = "tls.crt"
CERT_DAYS = 3650  # the registry checks the chain, not the age: rotation is by replacing the files


class SigningKeyMissing(RuntimeError):
    """The key directory has no key and may not get one (a mounted Secret, production)."""


@dataclass(frozen=True)
class SigningKey:
    """A private key and its self-signed certificate, as files (PEM)."""

    key_path: Path
    cert_path: Path

    def private_pem(self) -> bytes:
        return self.key_path.read_bytes()

    def x5c(self) -> list[str]:
        """The ``x5c`` JOSE header: the certificate, DER in standard base64."""
        cert = x509.load_pem_x509_certificate(self.cert_path.read_bytes())
        return [base64.b64encode(cert.public_bytes(serialization.Encoding.DER)).decode()]

    def algorithm(self) -> str:
        """The JWS algorithm of this key: ES256 for P-256, RS256 for RSA."""
        key = serialization.load_pem_private_key(self.private_pem(), password=None)
        return "ES256" if isinstance(key, ec.EllipticCurvePrivateKey) else "RS256"


def load_signing_key(directory: Path) -> SigningKey:
    """The key in ``directory``; raises :class:`SigningKeyMissing` when either file is absent."""
    key = SigningKey(key_path=directory / KEY_FILE, cert_path=directory / CERT_FILE)
    missing = [str(path) for path in (key.key_path, key.cert_path) if not path.is_file()]
    if missing:
        raise SigningKeyMissing(f"the registry signing key is missing: {', '.join(missing)}")
    return key


def ensure_signing_key(directory: Path) -> SigningKey:
    """The key in ``directory``, created once (an EC P-256 key, 0600, and its certificate)."""
    try:
        return load_signing_key(directory)
    except SigningKeyMissing:
        pass
    directory.mkdir(parents=True, exist_ok=True, mode=0o700)
    private = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "manieval registry tokens")])
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(private.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=CERT_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(private, hashes.SHA256())
    )
    pem = private.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    key = SigningKey(key_path=directory / KEY_FILE, cert_path=directory / CERT_FILE)
    # The certificate goes last: its presence says the pair is complete.
    _write(key.key_path, pem, mode=0o600)
    _write(key.cert_path, cert.public_bytes(serialization.Encoding.PEM), mode=0o644)
    return key


def _write(path: Path, data: bytes, *, mode: int) -> None:
    """Write atomically: a concurrent reader sees the old file or the whole new one."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as out:
        out.write(data)
    os.replace(tmp, path)
