"""Test certificates for HTTPS and zenoh TLS: a CA, a server certificate for localhost / 127.0.0.1 and one
client certificate per name (with mTLS the name is the zenoh ACL subject), as PEM files in a folder. For
tests and trials, not production: the keys are written unencrypted.

    python scripts/make_test_certs.py certs/ --clients car-1,car-2   # ca, server, car-1, car-2 (+ -key)
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

DAYS = 30


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _write_key(key: ec.EllipticCurvePrivateKey, path: Path) -> None:
    pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    path.write_bytes(pem)
    path.chmod(0o600)


def _cert(
    subject: str,
    key: ec.EllipticCurvePrivateKey,
    issuer: x509.Certificate | None,
    issuer_key: ec.EllipticCurvePrivateKey,
    usage: ExtendedKeyUsageOID | None,
) -> x509.Certificate:
    now = dt.datetime.now(dt.UTC)
    b = (
        x509.CertificateBuilder()
        .subject_name(_name(subject))
        .issuer_name(issuer.subject if issuer else _name(subject))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=DAYS))
        .add_extension(x509.BasicConstraints(ca=issuer is None, path_length=None), critical=True)
    )
    if issuer is None:
        usage_bits = dict(key_cert_sign=True, crl_sign=True, digital_signature=True)
    else:
        usage_bits = dict(key_cert_sign=False, crl_sign=False, digital_signature=True)
        b = b.add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
        b = b.add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(issuer_key.public_key()), critical=False
        )
    b = b.add_extension(
        x509.KeyUsage(
            content_commitment=False,
            key_encipherment=False,
            data_encipherment=False,
            key_agreement=False,
            encipher_only=False,
            decipher_only=False,
            **usage_bits,
        ),
        critical=True,
    )
    b = b.add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
    if usage == ExtendedKeyUsageOID.SERVER_AUTH:
        names = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
        b = b.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return b.sign(issuer_key, hashes.SHA256())


def make_certs(folder: Path, clients: tuple[str, ...] = ("client",)) -> dict[str, Path]:
    """Write the CA, the server's and each client's certificate and key into `folder` (client files are
    named by their common name) -> their paths by name."""
    folder.mkdir(parents=True, exist_ok=True)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = _cert("phim test CA", ca_key, None, ca_key, None)
    out = {"ca": folder / "ca.pem"}
    out["ca"].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    wanted = [("server", "localhost", ExtendedKeyUsageOID.SERVER_AUTH)]
    wanted += [(name, name, ExtendedKeyUsageOID.CLIENT_AUTH) for name in clients]
    for name, cn, usage in wanted:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _cert(cn, key, ca, ca_key, usage)
        out[name] = folder / f"{name}.pem"
        out[name].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        out[f"{name}-key"] = folder / f"{name}-key.pem"
        _write_key(key, out[f"{name}-key"])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument(
        "--clients",
        default="client",
        help="Comma-separated common names: one client certificate each (e.g. car-1,car-2,phim-worker).",
    )
    args = parser.parse_args()
    for name, path in make_certs(args.folder, tuple(args.clients.split(","))).items():
        print(f"{name}: {path}")


if __name__ == "__main__":
    main()
