"""A test certificate authority and one certificate per process, made with the ``openssl`` command.

``python -m dfusion.run.certs DIR [NAME ...] [--scenario F] [--host H ...]`` (or
``make certs CERTS=DIR SCENARIO=F``) writes into ``DIR``:

* ``ca.pem`` (the CA certificate: give it to every member) and ``ca.key`` (the
  CA's private key, mode 0600: keep it off the nodes; it is only needed to issue
  more certificates);
* ``NAME.pem`` and ``NAME.key`` (mode 0600) for every name: one per scenario node
  with ``--scenario``, plus ``launcher`` (the sessions of ``dfusion run`` itself)
  and ``monitor`` (``python -m dfusion.run.monitor``); with neither names nor a
  scenario, ``node`` (one certificate shared by every node), ``launcher`` and
  ``monitor``.

An existing ``ca.pem``/``ca.key`` pair in ``DIR`` is reused, so that certificates
can be added later; existing ``NAME.pem`` files are replaced.

Every key is EC P-256 (PKCS#8 PEM). The CA is ``CA:TRUE`` with ``keyCertSign``;
each member certificate is ``CA:FALSE`` with ``digitalSignature`` and the extended
key usages ``serverAuth`` and ``clientAuth`` (the same certificate serves a node
as a TLS server on its listen endpoint and as a client on its connections; Zenoh
checks both with mutual TLS), and lists the hosts it may be reached at
(``--host``; default ``localhost`` and ``127.0.0.1``) as subject alternative
names: the connecting side checks that the endpoint's host is one of them.

This is a **test** PKI (30 days by default, no revocation). For a deployment,
issue the certificates from your own CA with the same extensions.
"""
from __future__ import annotations

import argparse
import ipaddress
import logging
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from dfusion.errors import DfusionError

log = logging.getLogger(__name__)

#: Names that get a certificate when neither names nor a scenario are given.
DEFAULT_NAMES = ("node", "launcher", "monitor")
#: Hosts in every certificate's subject alternative names by default.
DEFAULT_HOSTS = ("localhost", "127.0.0.1")
#: Names of processes that are not scenario nodes.
TOOL_NAMES = ("launcher", "monitor")


def _openssl(openssl: str, *args: str) -> None:
    try:
        proc = subprocess.run([openssl, *args], stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=60)
    except FileNotFoundError:
        raise DfusionError(f"{openssl!r} not found: install the openssl command line") from None
    if proc.returncode != 0:
        raise DfusionError(f"openssl {args[0]} failed: {proc.stderr.strip()}")


def _private_key(openssl: str, path: Path) -> None:
    """An EC P-256 key written into a file created with mode 0600 (never readable by others)."""
    path.unlink(missing_ok=True)
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    _openssl(openssl, "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(path))


def _san(hosts: list[str]) -> str:
    out = []
    for h in hosts:
        try:
            ipaddress.ip_address(h)
            out.append(f"IP:{h}")
        except ValueError:
            out.append(f"DNS:{h}")
    return ",".join(out)


def make_test_pki(
    directory: str | Path,
    names: list[str] | tuple[str, ...] = DEFAULT_NAMES,
    *,
    hosts: list[str] | tuple[str, ...] = DEFAULT_HOSTS,
    ca_name: str = "dfusion test CA",
    days: int = 30,
    openssl: str = "openssl",
) -> dict[str, Path]:
    """Create (or reuse) the CA in ``directory`` and issue a certificate per name.

    Returns ``{"ca": ca.pem, NAME: NAME.pem, ...}`` (each ``NAME.key`` sits next to
    its certificate). See the module docstring for the extensions.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    for name in names:
        if not name or "/" in name or name.startswith(".") or name == "ca":
            raise DfusionError(f"invalid certificate name {name!r}")
    ca_pem, ca_key = d / "ca.pem", d / "ca.key"
    if not (ca_pem.exists() and ca_key.exists()):
        _private_key(openssl, ca_key)
        _openssl(openssl, "req", "-x509", "-new", "-key", str(ca_key), "-sha256", "-days", str(days),
                 "-subj", f"/CN={ca_name}", "-addext", "basicConstraints=critical,CA:TRUE",
                 "-addext", "keyUsage=critical,keyCertSign,cRLSign", "-out", str(ca_pem))
        log.info("new CA %s", ca_pem)
    out = {"ca": ca_pem}
    ext = ("basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
           f"extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName={_san(list(hosts))}\n")
    with tempfile.TemporaryDirectory(prefix="dfusion-certs-") as tmp:
        ext_file = Path(tmp) / "member.ext"
        ext_file.write_text(ext)
        for name in names:
            key, csr, pem = d / f"{name}.key", Path(tmp) / f"{name}.csr", d / f"{name}.pem"
            _private_key(openssl, key)
            _openssl(openssl, "req", "-new", "-key", str(key), "-subj", f"/CN={name}", "-out", str(csr))
            _openssl(openssl, "x509", "-req", "-in", str(csr), "-CA", str(ca_pem), "-CAkey", str(ca_key),
                     "-CAserial", str(Path(tmp) / "ca.srl"), "-CAcreateserial", "-days", str(days), "-sha256",
                     "-extfile", str(ext_file), "-out", str(pem))
            out[name] = pem
    log.info("certificates for %s in %s", ", ".join(names), d)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m dfusion.run.certs",
                                description="Create a test CA and a certificate per dfusion process (openssl).")
    p.add_argument("directory", help="where to write ca.pem, ca.key, NAME.pem and NAME.key")
    p.add_argument("names", nargs="*", help="certificate names (default: node launcher monitor)")
    p.add_argument("--scenario", default=None, help="one certificate per node of this scenario, plus launcher and monitor")
    p.add_argument("--host", action="append", default=[], metavar="HOST",
                   help="a host name or IP address the certificates are valid for (repeatable; "
                        "default localhost and 127.0.0.1)")
    p.add_argument("--ca-name", default="dfusion test CA", help="the CA's common name")
    p.add_argument("--days", type=int, default=30, help="validity in days")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    names = list(args.names)
    if args.scenario:
        from dfusion.scenario.loader import load_scenario

        names += [n for n in sorted(load_scenario(args.scenario).nodes) if n not in names]
        names += [n for n in TOOL_NAMES if n not in names]
    try:
        made = make_test_pki(args.directory, names or list(DEFAULT_NAMES), hosts=args.host or list(DEFAULT_HOSTS),
                             ca_name=args.ca_name, days=args.days)
    except DfusionError as exc:
        print(f"dfusion.run.certs: error: {exc}", file=sys.stderr)
        return 2
    for name, path in made.items():
        print(f"{name}: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
