"""Certificates and SuperNode keys for a local or LAN federation.

Flower's Deployment Engine needs TLS on the SuperLink (a CA, and a server certificate the
SuperNodes and the ``flwr`` CLI verify with the CA) and, with ``--enable-supernode-auth``,
one ECDSA P-384 key pair per SuperNode in OpenSSH format (the public half is registered with
``flwr supernode register``). This writes all of them with ``cryptography``:

    <out>/ca.crt, ca.key                the certificate authority (keep ca.key private)
    <out>/server.pem, server.key        the SuperLink's certificate, for the names/IPs given
    <out>/supernodes/<name>, <name>.pub one key pair per robot owner

For production, use your organisation's PKI; these are for your own machines and LANs.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from zk0.common.errors import Zk0Error

VALID_DAYS = 365
DEFAULT_HOSTS = ("localhost", "127.0.0.1", "::1")


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey, fmt: serialization.PrivateFormat) -> None:
    path.write_bytes(key.private_bytes(serialization.Encoding.PEM, fmt, serialization.NoEncryption()))
    path.chmod(0o600)


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [x509.NameAttribute(NameOID.ORGANIZATION_NAME, "zk0"), x509.NameAttribute(NameOID.COMMON_NAME, common_name)]
    )


def _alt_names(hosts: list[str]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            if not host or " " in host:
                raise Zk0Error(
                    f"Host {host!r} is not a DNS name or an IP address; expected e.g. 'superlink.lan' or '192.168.1.10'."
                ) from None
            names.append(x509.DNSName(host))
    return names


def make_ca(out: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """A self-signed certificate authority."""
    key = ec.generate_private_key(ec.SECP384R1())
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name("zk0 federation CA"))
        .issuer_name(_name("zk0 federation CA"))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )  # fmt: skip
        .sign(key, hashes.SHA384())
    )
    (out / "ca.crt").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(out / "ca.key", key, serialization.PrivateFormat.TraditionalOpenSSL)
    return cert, key


def make_server_cert(out: Path, ca: x509.Certificate, ca_key: ec.EllipticCurvePrivateKey, hosts: list[str]) -> Path:
    """The SuperLink's TLS certificate, valid for ``hosts`` (DNS names and IP addresses)."""
    key = ec.generate_private_key(ec.SECP384R1())
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(hosts[0]))
        .issuer_name(ca.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
        .add_extension(x509.SubjectAlternativeName(_alt_names(hosts)), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([x509.oid.ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .sign(ca_key, hashes.SHA384())
    )
    (out / "server.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(out / "server.key", key, serialization.PrivateFormat.TraditionalOpenSSL)
    return out / "server.pem"


def make_supernode_keys(out: Path, name: str) -> Path:
    """An ECDSA P-384 key pair in OpenSSH format for SuperNode authentication; returns the public key."""
    if not name or not name.replace("-", "").replace("_", "").isalnum():
        raise Zk0Error(f"SuperNode name {name!r} is invalid; expected letters, digits, '-' or '_'.")
    folder = out / "supernodes"
    folder.mkdir(parents=True, exist_ok=True)
    key = ec.generate_private_key(ec.SECP384R1())
    _write_key(folder / name, key, serialization.PrivateFormat.OpenSSH)
    public = key.public_key().public_bytes(serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH)
    (folder / f"{name}.pub").write_bytes(public + f" zk0-{name}\n".encode())
    return folder / f"{name}.pub"


def make_federation_certs(out: Path, hosts: list[str], supernodes: list[str]) -> dict[str, Path]:
    """CA, SuperLink certificate and SuperNode keys in ``out``; the paths of what to hand out."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise Zk0Error(f"Certificate folder {str(out)!r} cannot be created ({err.strerror}).") from None
    names = list(dict.fromkeys([*hosts, *DEFAULT_HOSTS]))
    ca, ca_key = make_ca(out)
    paths = {"ca": out / "ca.crt", "server": make_server_cert(out, ca, ca_key, names)}
    for name in supernodes:
        paths[name] = make_supernode_keys(out, name)
    return paths
