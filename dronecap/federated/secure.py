"""Keys for a secure deployment: TLS certificates for the SuperLink and one key pair per drone.

``dronecap federate-keys KEYS --drones K --host H`` (or :func:`make_keys`) writes into KEYS:

    ca.crt, ca.key          a private certificate authority (10 years); SuperNodes and the
                            ``flwr`` CLI trust only it (``--root-certificates``)
    server.crt, server.key  the SuperLink's TLS certificate, signed by the CA, valid for
                            ``localhost``, 127.0.0.1 and every ``--host`` given
    drone_K.key, drone_K.pub  drone K's EC (NIST P-384) key pair in OpenSSH format: the
                            SuperNode signs with the private key, the SuperLink admits only
                            the public keys registered with ``flwr supernode register``

Private keys are written with mode 0600. The drones' private keys belong on the drones (copy
``drone_K.key`` to drone K); the CA key can be kept offline once the certificates exist.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from pathlib import Path

from dronecap.files import atomic_output

CA_CERT, CA_KEY = "ca.crt", "ca.key"
SERVER_CERT, SERVER_KEY = "server.crt", "server.key"
VALID_DAYS = 3650


def drone_key(folder: Path, k: int) -> tuple[Path, Path]:
    """(private, public) key files of drone ``k`` in ``folder``."""
    return Path(folder) / f"drone_{k}.key", Path(folder) / f"drone_{k}.pub"


def _write(path: Path, data: bytes, private: bool) -> None:
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)
        if private:
            os.chmod(tmp, 0o600)


def _cert(subject: str, key, issuer_name, issuer_key, ca: bool, hosts: list[str]):
    """An X.509 certificate for ``key``'s public key signed by ``issuer_key``."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import NameOID

    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)])
    now = datetime.datetime.now(datetime.UTC)
    b = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(issuer_name or name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
    )
    if hosts:
        alt: list[x509.GeneralName] = []
        for h in hosts:
            try:
                alt.append(x509.IPAddress(ipaddress.ip_address(h)))
            except ValueError:
                alt.append(x509.DNSName(h))
        b = b.add_extension(x509.SubjectAlternativeName(alt), critical=False)
    return b.sign(issuer_key, hashes.SHA256())


def make_keys(folder: Path, drones: int, hosts: list[str] | None = None) -> list[Path]:
    """Write a CA, the SuperLink's TLS certificate and ``drones`` drone key pairs into
    ``folder`` (see the module doc); returns the files written. Existing files are replaced."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    pem, none = serialization.Encoding.PEM, serialization.NoEncryption()
    pkcs8 = serialization.PrivateFormat.PKCS8
    ca_key = ec.generate_private_key(ec.SECP384R1())
    ca = _cert("dronecap federation CA", ca_key, None, ca_key, True, [])
    server_key = ec.generate_private_key(ec.SECP384R1())
    names = ["localhost", "127.0.0.1", *(hosts or [])]
    server = _cert("dronecap superlink", server_key, ca.subject, ca_key, False, names)
    files = {
        CA_CERT: (ca.public_bytes(pem), False),
        CA_KEY: (ca_key.private_bytes(pem, pkcs8, none), True),
        SERVER_CERT: (server.public_bytes(pem), False),
        SERVER_KEY: (server_key.private_bytes(pem, pkcs8, none), True),
    }
    for k in range(drones):
        key = ec.generate_private_key(ec.SECP384R1())
        private, public = drone_key(folder, k)
        files[private.name] = (
            key.private_bytes(pem, serialization.PrivateFormat.OpenSSH, none),
            True,
        )
        files[public.name] = (
            key.public_key().public_bytes(
                serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH
            ),
            False,
        )
    for name, (data, private) in files.items():
        _write(folder / name, data, private)
    return [folder / n for n in files]
