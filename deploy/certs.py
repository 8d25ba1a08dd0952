"""A throwaway lab PKI for Zenoh mutual TLS: one CA and one certificate per service, whose common
name is the identity the router's access_control rules match (`cert_common_names`).

    python -m bagit.deploy.certs /etc/bagit/tls --hosts router.lab 10.0.0.1 localhost 127.0.0.1

writes ca.pem (+ ca.key, keep it offline), and <name>.pem / <name>.key for the router and every
service. Keys are EC P-256, written with mode 0600. For a real lab, keep the CA key off the rig
and issue certificates per host; this is the quick way to get a working, testable set.
Needs the `cryptography` package (a dev dependency).
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import os
import sys
from pathlib import Path

# The identities of the secure example (deploy/secure/zenoh-router-secure.json5).
SERVICES = ("router", "sim", "perception", "planner", "controller", "arm-driver", "dashboard", "recorder", "cli")


def _x509():
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError:  # pragma: no cover - depends on the environment
        from bagit.common.errors import BusError

        raise BusError("generating certificates needs the 'cryptography' package (pip install cryptography)") from None
    return x509, hashes, serialization, ec, ExtendedKeyUsageOID, NameOID


def _san(hosts: list[str]):
    x509 = _x509()[0]
    names = []
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    return x509.SubjectAlternativeName(names)


def make_ca(common_name: str = "BagIt lab CA", days: int = 3650):
    """A self-signed CA: (private key, certificate)."""
    x509, hashes, _, ec, _, NameOID = _x509()
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True
        )  # key_cert_sign, crl_sign
        .sign(key, hashes.SHA256())
    )
    return key, cert


def make_cert(ca_key, ca_cert, common_name: str, hosts: list[str], days: int = 825):
    """A leaf certificate for `common_name`, usable as TLS server and client, valid for `hosts`."""
    x509, hashes, _, ec, EKU, NameOID = _x509()
    key = ec.generate_private_key(ec.SECP256R1())
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([EKU.SERVER_AUTH, EKU.CLIENT_AUTH]), critical=False)
        .add_extension(_san(hosts), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    return key, cert


def _write_key(path: Path, key) -> None:
    serialization = _x509()[2]
    data = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _write_cert(path: Path, cert) -> None:
    serialization = _x509()[2]
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def write_lab_pki(out_dir: Path, names: list[str] | tuple[str, ...] = SERVICES, hosts: list[str] | None = None) -> dict[str, Path]:
    """Write ca.pem/ca.key and <name>.pem/<name>.key for each name; returns their paths by stem."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    hosts = hosts or ["localhost", "127.0.0.1"]
    ca_key, ca_cert = make_ca()
    _write_cert(out / "ca.pem", ca_cert)
    _write_key(out / "ca.key", ca_key)
    paths = {"ca": out / "ca.pem"}
    for n in names:
        key, cert = make_cert(ca_key, ca_cert, n, hosts)
        _write_cert(out / f"{n}.pem", cert)
        _write_key(out / f"{n}.key", key)
        paths[n] = out / f"{n}.pem"
        paths[f"{n}.key"] = out / f"{n}.key"
    return paths


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bagit.deploy.certs", description=__doc__.splitlines()[0])
    p.add_argument("out", type=Path, help="directory to write the PEM files to")
    p.add_argument("--names", nargs="+", default=list(SERVICES), help="certificate common names (identities)")
    p.add_argument("--hosts", nargs="+", default=["localhost", "127.0.0.1"], help="DNS names / IPs the certificates are valid for")
    a = p.parse_args(argv)
    paths = write_lab_pki(a.out, a.names, a.hosts)
    print(f"wrote {len(paths)} files to {a.out}: CA ca.pem, identities {', '.join(a.names)}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
