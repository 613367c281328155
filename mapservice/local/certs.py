"""A throw-away certificate authority for local TLS listeners (tests, `up`): a CA, a server
certificate for 127.0.0.1/localhost and client certificates, made with the `openssl` CLI."""

from __future__ import annotations

import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class CertFiles:
    ca_file: Path  # the CA certificate clients trust
    cert_file: Path
    key_file: Path


def _openssl(*args: str, cwd: Path) -> None:
    binary = shutil.which("openssl")
    if binary is None:
        raise RuntimeError(
            "the openssl command is needed to make local TLS certificates (apt-get install openssl)"
        )
    done = subprocess.run([binary, *args], cwd=cwd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"openssl {' '.join(args[:2])} failed: {done.stderr.strip()}")


_EC_KEY = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes")


def _sign(directory: Path, name: str, subject: str, extensions: str, days: int) -> CertFiles:
    (directory / f"{name}.ext").write_text(extensions)
    _openssl(
        "req",
        *_EC_KEY,
        "-keyout",
        f"{name}.key",
        "-out",
        f"{name}.csr",
        "-subj",
        subject,
        cwd=directory,
    )
    _openssl(
        "x509",
        "-req",
        "-in",
        f"{name}.csr",
        "-CA",
        "ca.crt",
        "-CAkey",
        "ca.key",
        "-CAcreateserial",
        "-out",
        f"{name}.crt",
        "-days",
        str(days),
        "-extfile",
        f"{name}.ext",
        cwd=directory,
    )
    (directory / f"{name}.key").chmod(0o600)
    return CertFiles(directory / "ca.crt", directory / f"{name}.crt", directory / f"{name}.key")


def make_ca(directory: Path, days: int = 30) -> Path:
    """A self-signed CA in `directory` (ca.crt, ca.key), kept if it is already there."""
    directory.mkdir(parents=True, exist_ok=True)
    if not (directory / "ca.crt").exists():
        _openssl(
            "req",
            "-x509",
            *_EC_KEY,
            "-keyout",
            "ca.key",
            "-out",
            "ca.crt",
            "-days",
            str(days),
            "-subj",
            "/CN=mapservice local CA",
            "-addext",
            "basicConstraints=critical,CA:TRUE",
            "-addext",
            "keyUsage=critical,keyCertSign,cRLSign",
            "-addext",
            "subjectKeyIdentifier=hash",
            cwd=directory,
        )
        (directory / "ca.key").chmod(0o600)
    return directory / "ca.crt"


def make_server_cert(directory: Path, name: str = "server", days: int = 30) -> CertFiles:
    """A server certificate for 127.0.0.1 and localhost, signed by the CA in `directory`."""
    make_ca(directory, days)
    if (directory / f"{name}.crt").exists():
        return CertFiles(directory / "ca.crt", directory / f"{name}.crt", directory / f"{name}.key")
    return _sign(
        directory,
        name,
        "/CN=localhost",
        "subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
        "keyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth\n"
        "subjectKeyIdentifier=hash\nauthorityKeyIdentifier=keyid\n",
        days,
    )


def make_client_cert(directory: Path, common_name: str, days: int = 30) -> CertFiles:
    """A client certificate (CN = `common_name`) signed by the CA in `directory`."""
    make_ca(directory, days)
    name = f"client-{common_name}"
    if (directory / f"{name}.crt").exists():
        return CertFiles(directory / "ca.crt", directory / f"{name}.crt", directory / f"{name}.key")
    return _sign(
        directory,
        name,
        f"/CN={common_name}",
        "basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\n"
        "extendedKeyUsage=clientAuth\nsubjectKeyIdentifier=hash\n"
        "authorityKeyIdentifier=keyid\n",
        days,
    )
