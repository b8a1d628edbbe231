"""Test certificates for mutual TLS: the run's CA and its members, and a second, foreign CA."""
from __future__ import annotations

import shutil
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import pytest

from dfusion.transport.zenoh import TlsFiles, ZenohConfig, open_session


@dataclass(frozen=True)
class Pki:
    dir: Path       # the run's CA: ca.pem, NAME.pem, NAME.key
    foreign: Path   # another CA with a member "x"

    def member(self, name: str) -> TlsFiles:
        return TlsFiles(str(self.dir / "ca.pem"), str(self.dir / f"{name}.pem"), str(self.dir / f"{name}.key"))


def make_pki(root: Path, names: Iterable[str] = ("a", "b", "c", "launcher", "monitor", "node", "member")) -> Pki:
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command line is not installed")
    from dfusion.run.certs import make_test_pki

    make_test_pki(root / "run-ca", list(names))
    make_test_pki(root / "foreign-ca", ["x"], ca_name="another CA")
    return Pki(root / "run-ca", root / "foreign-ca")


def strangers(pki: Pki) -> dict[str, dict]:
    """Ways to knock on a TLS endpoint without a certificate of the run's CA (ZenohConfig keywords;
    their endpoints are given by the caller): only the CA certificate; a certificate of another CA
    (trusting that CA, or trusting the run's CA)."""
    ca = str(pki.dir / "ca.pem")
    x = (str(pki.foreign / "x.pem"), str(pki.foreign / "x.key"))
    return {
        "CA certificate only": {"extra": {"transport/link/tls/root_ca_certificate": ca}},
        "certificate of another CA": {"tls": TlsFiles(str(pki.foreign / "ca.pem"), *x)},
        "another CA's certificate, trusting the run's CA": {"tls": TlsFiles(ca, *x)},
    }


def listen_in(connect: list[str], network: str, seconds: float, forge: tuple[str, bytes] | None = None,
              **config) -> list[str]:
    """Open a session that connects to ``connect``, subscribes to every key of ``network`` (data and
    liveliness) for ``seconds`` and optionally publishes a forged message; returns what it heard
    from other processes."""
    import zenoh

    heard: list[str] = []
    cfg = ZenohConfig(connect=tuple(connect), listen=("tcp/127.0.0.1:0",) if config.get("tls") is None else (),
                      **config)
    with open_session(cfg) as z:
        z.declare_subscriber(f"dfusion/{network}/**", lambda s: heard.append(f"data {s.key_expr}"),
                             allowed_origin=zenoh.Locality.REMOTE)
        z.liveliness().declare_subscriber(f"dfusion/{network}/**", lambda s: heard.append(f"alive {s.key_expr}"),
                                          history=True)
        time.sleep(seconds / 2)
        if forge is not None:
            z.put(forge[0], forge[1])
        time.sleep(seconds / 2)
    return heard
