"""``rovergate credentials``: the certificates of a mission's ground link (mutual TLS).

One run writes, under ``--out DIR``::

    DIR/ca/ca.pem, ca.key              the mission's certificate authority. Keep ca.key off
                                       the rover and off the station (it signs new
                                       credentials); ca.pem is public.
    DIR/rover/ca.pem, rover.pem, rover.key
                                       for the mission manager:
                                       rovergate run --contact.credentials DIR/rover
    DIR/station/ca.pem, station.pem, station.key
                                       for the ground station:
                                       rovergate ground --credentials DIR/station

Private keys are written with mode 0600 and their directories 0700. Keys are EC P-256. The
rover's certificate names the hosts a station reaches it by (``--rover-hosts``; the station
checks the name it connected to against them), and is a TLS server certificate; the
station's names ``--station-name`` (the common name the rover's access control admits, its
``--contact.ground-stations``) and is a TLS client certificate. Both are signed by the CA and
valid for ``--days``.

Rotation: ``--ca DIR/ca`` signs new rover and station credentials with an existing CA (the
old ones stay valid until they expire: use it to renew); a new CA (no ``--ca``) makes every
earlier credential useless at once (use it when a key may have leaked). A mission reads its
credentials when its link opens: to move a running mission to new ones, write them over the
old files (``--force``, same ``--out``), stop the mission (Ctrl-C keeps its checkpoint) and
carry it on with ``rovergate run --out OUT --resume``.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import socket
from dataclasses import dataclass
from pathlib import Path

from rovergate.errors import ConfigError

CA, ROVER, STATION = "ca", "rover", "station"


@dataclass
class CredentialsConfig:
    """Create the certificates of a mission's ground link (mutual TLS): a certificate
    authority, the rover's credentials and a ground station's."""

    out: Path = Path("credentials")
    """Directory to write ca/, rover/ and station/ into (created; existing files are not
    overwritten unless --force)."""
    ca: Path | None = None
    """An existing CA directory (DIR/ca from an earlier run) to sign with, instead of making
    a new CA: renews the rover's and the station's credentials under the same trust."""
    rover_hosts: tuple[str, ...] = ()
    """Names and addresses a station reaches the rover by (the rover certificate's subject
    alternative names). localhost, 127.0.0.1, ::1 and this machine's host name are always
    in."""
    station_name: str = "station"
    """The station certificate's common name (the rover admits the names in its
    --contact.ground-stations, `station` by default)."""
    days: int = 365
    """Validity of the rover's and the station's certificates (a new CA: ten times this)."""
    force: bool = False
    """Overwrite existing files."""


def _write(path: Path, data: bytes, private: bool, force: bool) -> None:
    if path.exists() and not force:
        raise ConfigError(f"{path} exists; pass --force to overwrite it, or another --out")
    path.parent.mkdir(parents=True, exist_ok=True)
    if private:
        os.chmod(path.parent, 0o700)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def create(cfg: CredentialsConfig) -> dict[str, Path]:
    """Write the credentials (module docstring); returns the three directories."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    if cfg.days < 1:
        raise ConfigError(f"--days {cfg.days}: a certificate must be valid for at least a day")
    if not cfg.station_name or not cfg.station_name.isprintable():
        raise ConfigError("--station-name must be a non-empty printable name")
    now = datetime.datetime.now(datetime.UTC)
    pem = serialization.Encoding.PEM

    def key_pem(key) -> bytes:
        return key.private_bytes(pem, serialization.PrivateFormat.PKCS8,
                                 serialization.NoEncryption())

    if cfg.ca is not None:
        try:
            ca_cert = x509.load_pem_x509_certificate((cfg.ca / "ca.pem").read_bytes())
            ca_key = serialization.load_pem_private_key((cfg.ca / "ca.key").read_bytes(), None)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"--ca {cfg.ca}: needs the ca.pem and ca.key of an earlier "
                              f"`rovergate credentials` ({exc})") from None
    else:
        ca_key = ec.generate_private_key(ec.SECP256R1())
        name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "rovergate mission CA")])
        ca_cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
                   .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(minutes=5))
                   .not_valid_after(now + datetime.timedelta(days=10 * cfg.days))
                   .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
                   .add_extension(x509.KeyUsage(
                       digital_signature=True, key_cert_sign=True, crl_sign=True,
                       content_commitment=False, key_encipherment=False,
                       data_encipherment=False, key_agreement=False, encipher_only=False,
                       decipher_only=False), critical=True)
                   .add_extension(x509.SubjectKeyIdentifier.from_public_key(
                       ca_key.public_key()), critical=False)
                   .sign(ca_key, hashes.SHA256()))
        _write(cfg.out / CA / "ca.key", key_pem(ca_key), True, cfg.force)
        _write(cfg.out / CA / "ca.pem", ca_cert.public_bytes(pem), False, cfg.force)

    def leaf(common_name: str, usage, alt_names: list) -> tuple[bytes, bytes]:
        key = ec.generate_private_key(ec.SECP256R1())
        builder = (x509.CertificateBuilder()
                   .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME,
                                                               common_name)]))
                   .issuer_name(ca_cert.subject).public_key(key.public_key())
                   .serial_number(x509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(minutes=5))
                   .not_valid_after(now + datetime.timedelta(days=cfg.days))
                   .add_extension(x509.BasicConstraints(ca=False, path_length=None),
                                  critical=True)
                   .add_extension(x509.KeyUsage(
                       digital_signature=True, key_cert_sign=False, crl_sign=False,
                       content_commitment=False, key_encipherment=False,
                       data_encipherment=False, key_agreement=False, encipher_only=False,
                       decipher_only=False), critical=True)
                   .add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
                   .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(
                       ca_cert.public_key()), critical=False)
                   .add_extension(x509.SubjectAlternativeName(alt_names), critical=False))
        cert = builder.sign(ca_key, hashes.SHA256())
        return cert.public_bytes(pem), key_pem(key)

    hosts = ["localhost", "127.0.0.1", "::1", socket.gethostname(), *cfg.rover_hosts]
    alt: list = []
    for host in dict.fromkeys(hosts):
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            alt.append(x509.DNSName(host))
    rover_cert, rover_key = leaf("rover", ExtendedKeyUsageOID.SERVER_AUTH, alt)
    station_cert, station_key = leaf(cfg.station_name, ExtendedKeyUsageOID.CLIENT_AUTH,
                                     [x509.DNSName(cfg.station_name)])
    ca_pem = ca_cert.public_bytes(pem)
    for party, cert, key in ((ROVER, rover_cert, rover_key),
                             (STATION, station_cert, station_key)):
        _write(cfg.out / party / f"{party}.key", key, True, cfg.force)
        _write(cfg.out / party / f"{party}.pem", cert, False, cfg.force)
        _write(cfg.out / party / "ca.pem", ca_pem, False, cfg.force)
    return {CA: cfg.ca or cfg.out / CA, ROVER: cfg.out / ROVER, STATION: cfg.out / STATION}


def main(cfg: CredentialsConfig) -> int:
    dirs = create(cfg)
    print(f"wrote the ground link's credentials under {cfg.out}:\n"
          f"  {dirs[CA]}  the certificate authority: keep ca.key off the rover and the "
          "station\n"
          f"  {dirs[ROVER]}  rovergate run --contact.credentials {dirs[ROVER]} "
          "--contact.ground-listen tls/0.0.0.0:PORT\n"
          f"  {dirs[STATION]}  rovergate ground --credentials {dirs[STATION]} "
          "--connect tls/ROVER:PORT")
    return 0
