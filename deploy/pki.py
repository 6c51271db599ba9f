"""The deployment's certificates: one CA, and one key and certificate per process (mTLS).

Made with the ``openssl`` command (OpenSSL >= 1.1.1; nothing to install in Python). Keys are
ECDSA P-256 in PKCS#8 PEM, which Zenoh's TLS link (rustls) reads; certificates are X.509 v3:

* the CA: ``basicConstraints = critical, CA:TRUE``, ``keyUsage = keyCertSign, cRLSign``;
* a process: ``CN = <process>.<ns>`` (what the access-control rules name), ``CA:FALSE``,
  ``extendedKeyUsage = serverAuth, clientAuth`` (one certificate to listen and to connect), and
  subject alternative names for its host's address, which a connecting side checks against the
  endpoint it dialled (``verify_name_on_connect``).

openssl writes into a private temporary directory; the files are then put in place by
:mod:`tether.safefs` (a new name made exclusively, renamed over the old: no link is followed),
private keys with mode 0600 from their creation. Blocks for the ``openssl`` runs (milliseconds each).
"""

from __future__ import annotations

import secrets
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from deploy.hosts import is_ip
from tether import safefs

Target = Path | safefs.Dir
"""Where files go: a directory by path (made if missing, its real path opened), or an open one."""


class PkiError(RuntimeError):
    """openssl is missing or failed; the message says which command and why."""


@dataclass(frozen=True)
class Ca:
    cert: Path
    key: Path


def openssl() -> str:
    """Path of the ``openssl`` command; :class:`PkiError` when there is none."""
    path = shutil.which("openssl")
    if path is None:
        raise PkiError("the `openssl` command is not on PATH; install OpenSSL (e.g. `apt-get install openssl`) "
                       "or pass --ca with an existing CA")
    return path


def _run(args: list[str], what: str) -> str:
    try:
        done = subprocess.run([openssl(), *args], capture_output=True, text=True, check=False, timeout=60)
    except subprocess.TimeoutExpired:
        raise PkiError(f"openssl timed out while {what}") from None
    if done.returncode != 0:
        raise PkiError(f"openssl failed while {what}: {done.stderr.strip() or done.stdout.strip()}")
    return done.stdout


def _place(target: Target, made: Path, names: list[str]) -> list[Path]:
    """Put files ``names`` of the private directory ``made`` into ``target`` (``*.key`` mode 0600,
    the others 0644); their paths there."""
    if isinstance(target, Path):
        target.mkdir(parents=True, exist_ok=True)
        with safefs.Dir.open(safefs.real_out(target)) as d:
            _place(d, made, names)
        return [target / name for name in names]
    return [target.replace(name, (made / name).read_bytes(), 0o600 if name.endswith(".key") else 0o644)
            for name in names]


def make_ca(directory: Target, cn: str, days: int) -> Ca:
    """Create a CA (``ca.crt``, ``ca.key``) in ``directory``."""
    where = directory if isinstance(directory, Path) else directory.path
    with tempfile.TemporaryDirectory(prefix="tether-pki-") as tmp:
        _run(["req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
              "-keyout", f"{tmp}/ca.key", "-out", f"{tmp}/ca.crt", "-days", str(days), "-subj", f"/CN={cn}",
              "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign",
              "-addext", "subjectKeyIdentifier=hash"], f"creating the CA in {where}")
        cert, key = _place(directory, Path(tmp), ["ca.crt", "ca.key"])
    return Ca(cert, key)


def load_ca(directory: Path) -> Ca:
    """An existing CA in ``directory`` (``ca.crt`` and ``ca.key``), checked to be a CA whose key
    matches its certificate; :class:`PkiError` naming the problem otherwise."""
    ca = Ca(directory / "ca.crt", directory / "ca.key")
    for f in (ca.cert, ca.key):
        if not f.is_file():
            raise PkiError(f"--ca {directory}: {f.name} is missing; give the directory holding ca.crt and ca.key "
                           "(the `ca/` directory of an earlier `tether deploy-gen` output)")
    text = _run(["x509", "-in", str(ca.cert), "-noout", "-text"], f"reading {ca.cert}")
    if "CA:TRUE" not in text:
        raise PkiError(f"--ca {directory}: {ca.cert} is not a CA certificate (no CA:TRUE); give the CA's own files")
    cert_pub = _run(["x509", "-in", str(ca.cert), "-noout", "-pubkey"], f"reading {ca.cert}")
    key_pub = _run(["pkey", "-in", str(ca.key), "-pubout"], f"reading {ca.key}")
    if cert_pub.strip() != key_pub.strip():
        raise PkiError(f"--ca {directory}: ca.key is not the key of ca.crt; give the matching pair")
    return ca


def issue(ca: Ca, directory: Target, stem: str, cn: str, addresses: list[str], days: int) -> tuple[Path, Path]:
    """A key and a certificate for ``cn`` signed by ``ca``: ``<stem>.key`` and ``<stem>.crt`` in
    ``directory``. ``addresses`` (IPs or DNS names) become the subject alternative names."""
    ext = "\n".join(_leaf_extensions(addresses)) + "\n"
    with tempfile.TemporaryDirectory(prefix="tether-pki-") as tmp:
        key, cert = Path(tmp) / f"{stem}.key", Path(tmp) / f"{stem}.crt"
        csr, extfile = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        extfile.write_text(ext)
        _run(["req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
              "-keyout", str(key), "-out", str(csr), "-subj", f"/CN={cn}"], f"making the key of {cn}")
        _run(["x509", "-req", "-in", str(csr), "-CA", str(ca.cert), "-CAkey", str(ca.key),
              "-set_serial", "0x" + secrets.token_hex(16), "-days", str(days), "-out", str(cert),
              "-extfile", str(extfile)], f"signing the certificate of {cn}")
        cert, key = _place(directory, Path(tmp), [cert.name, key.name])
    return cert, key


def _leaf_extensions(addresses: list[str]) -> list[str]:
    """The X.509 v3 extensions of every leaf certificate: not a CA, signing only, TLS server and
    client, key identifiers, and the host's addresses as subject alternative names."""
    sans = ",".join(dict.fromkeys(f"IP:{a}" if is_ip(a) else f"DNS:{a}" for a in addresses))
    return ["basicConstraints=critical,CA:FALSE",
            "keyUsage=critical,digitalSignature",
            "extendedKeyUsage=serverAuth,clientAuth",
            "subjectKeyIdentifier=hash",
            "authorityKeyIdentifier=keyid",
            *([f"subjectAltName={sans}"] if sans else [])]


def issue_one_step(ca: Ca, directory: Target, stem: str, cn: str, addresses: list[str],
                   days: int) -> tuple[Path, Path]:
    """As :func:`issue`, the same key type and extensions, in one ``openssl req -x509 -CA`` run
    (OpenSSL >= 3.0) instead of two; falls back to :func:`issue` when this openssl lacks ``-CA``.
    For ``tether run``, which makes a dozen identities before every run."""
    config = "\n".join(["[req]", "distinguished_name = dn", "x509_extensions = leaf", "prompt = no", "[dn]",
                         "[leaf]", *_leaf_extensions(addresses)]) + "\n"
    with tempfile.TemporaryDirectory(prefix="tether-pki-") as tmp:
        key, cert = Path(tmp) / f"{stem}.key", Path(tmp) / f"{stem}.crt"
        cnf = Path(tmp) / "req.cnf"
        cnf.write_text(config)
        try:
            _run(["req", "-x509", "-config", str(cnf), "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
                  "-nodes", "-keyout", str(key), "-out", str(cert), "-subj", f"/CN={cn}", "-days", str(days),
                  "-CA", str(ca.cert), "-CAkey", str(ca.key), "-set_serial", "0x" + secrets.token_hex(16)],
                 f"making the certificate of {cn}")
        except PkiError as exc:
            if "-CA" not in str(exc) and "unknown option" not in str(exc).lower():
                raise
            return issue(ca, directory, stem, cn, addresses, days)
        cert, key = _place(directory, Path(tmp), [cert.name, key.name])
    return cert, key


def verify(ca_cert: Path, cert: Path) -> None:
    """Check that ``cert`` chains to ``ca_cert`` (``openssl verify``); :class:`PkiError` otherwise."""
    _run(["verify", "-CAfile", str(ca_cert), str(cert)], f"verifying {cert} against {ca_cert}")


def expiry(cert: Path) -> str:
    """The certificate's ``notAfter`` date as openssl prints it."""
    return _run(["x509", "-in", str(cert), "-noout", "-enddate"], f"reading {cert}").strip().partition("=")[2]
