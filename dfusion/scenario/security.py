"""A run's security options: the network key file and mutual TLS (``[security]``).

A scenario's ``[security]`` table is checked when the scenario is loaded (one-line
errors naming the key); the command line of ``dfusion run`` overrides it
(``docs/security.md``).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dfusion.errors import ValidationError

if TYPE_CHECKING:
    from dfusion.transport.zenoh import TlsFiles

__all__ = ["SECURITY_KEYS", "TLS_KEYS", "SecurityOptions", "security_options"]


#: Keys of a scenario's ``[security]`` table, and of its ``[security.tls]`` sub-table.
SECURITY_KEYS = frozenset({"network_key_file", "tls"})
TLS_KEYS = frozenset({"dir", "ca", "cert", "key"})


@dataclass(frozen=True)
class SecurityOptions:
    """Who may take part in a run, and whether what they say is readable by others.

    Attributes
    ----------
    network_key_file : str, optional
        HMAC key of every fusion and monitor message (``dfusion run`` makes a random
        one per run when none is given).
    tls_dir : str, optional
        A directory made by ``python -m dfusion.run.certs``: ``ca.pem``, and for each
        process ``NAME.pem``/``NAME.key`` (a node's name, ``launcher``,
        ``monitor``), else the shared ``node.pem``/``node.key``.
    tls_ca, tls_cert, tls_key : str, optional
        Explicit files: the CA, and one certificate and key for every process
        (each overrides what ``tls_dir`` would give).

    TLS is on when any ``tls_*`` is set; it is then always mutual (see
    :class:`~dfusion.transport.zenoh.TlsFiles`).
    """

    network_key_file: str | None = None
    tls_dir: str | None = None
    tls_ca: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None

    @property
    def tls(self) -> bool:
        return any((self.tls_dir, self.tls_ca, self.tls_cert, self.tls_key))

    def over(self, base: SecurityOptions) -> SecurityOptions:
        """These options, with ``base``'s (e.g. the scenario's) where these have none.

        TLS settings are taken as a whole: command-line TLS replaces the scenario's.
        """
        out = self if self.network_key_file else replace(self, network_key_file=base.network_key_file)
        if not self.tls:
            out = replace(out, tls_dir=base.tls_dir, tls_ca=base.tls_ca, tls_cert=base.tls_cert, tls_key=base.tls_key)
        return out

    def tls_files(self, name: str) -> TlsFiles | None:
        """The CA, certificate and key of process ``name`` (``None`` without TLS).

        Raises :class:`ValidationError` when TLS is on but a file is missing.
        """
        if not self.tls:
            return None
        from dfusion.transport.zenoh import TlsFiles   # Zenoh is loaded only by the processes that use it

        d = Path(self.tls_dir) if self.tls_dir else None
        ca = self.tls_ca or (str(d / "ca.pem") if d else None)
        cert, key = self.tls_cert, self.tls_key
        if d is not None and cert is None and key is None:
            own = d / f"{name}.pem", d / f"{name}.key"
            shared = d / "node.pem", d / "node.key"
            pick = own if own[0].exists() and own[1].exists() else shared
            cert, key = str(pick[0]), str(pick[1])
        missing = [what for what, v in (("CA (--tls-ca)", ca), ("certificate (--tls-cert)", cert),
                                        ("private key (--tls-key)", key)) if not v]
        if missing:
            raise ValidationError(f"TLS for {name!r} needs a {', a '.join(missing)}, or --tls-dir")
        return TlsFiles(ca, cert, key)


def security_options(table: Mapping[str, Any] | None, base_dir: str | Path | None = None) -> SecurityOptions:
    """The :class:`SecurityOptions` of a scenario's ``[security]`` table.

    ::

        [security]
        network_key_file = "secrets/network.key"   # optional
        [security.tls]                              # optional: mutual TLS
        dir = "certs"                               # made by python -m dfusion.run.certs
        # or explicit files (each overrides what dir gives):
        ca = "certs/ca.pem"
        cert = "certs/node.pem"
        key = "certs/node.key"

    Relative paths start at ``base_dir`` (the scenario file's directory). Unknown
    keys and values that are not non-empty strings raise :class:`ValidationError`
    naming the key.
    """
    if table is None:
        return SecurityOptions()
    if not isinstance(table, Mapping):
        raise ValidationError(f"[security] must be a table, got {type(table).__name__}")

    def path(where: str, value: Any) -> str:
        if not isinstance(value, str) or not value.strip():
            raise ValidationError(f"{where} must be a file or directory path (a non-empty string), got {value!r}")
        p = Path(value).expanduser()
        return str(p if p.is_absolute() or base_dir is None else Path(base_dir) / p)

    for key in table:
        if key not in SECURITY_KEYS:
            raise ValidationError(f"security.{key}: unknown key; known: {', '.join(sorted(SECURITY_KEYS))}")
    key_file = path("security.network_key_file", table["network_key_file"]) if "network_key_file" in table else None
    tls = table.get("tls")
    if tls is None:
        return SecurityOptions(network_key_file=key_file)
    if not isinstance(tls, Mapping):
        raise ValidationError(f"security.tls must be a table ([security.tls]), got {tls!r}")
    for key in tls:
        if key not in TLS_KEYS:
            raise ValidationError(f"security.tls.{key}: unknown key; known: {', '.join(sorted(TLS_KEYS))}")
    if not tls:
        raise ValidationError("security.tls is empty: give dir, or ca, cert and key")
    got = {k: path(f"security.tls.{k}", v) for k, v in tls.items()}
    return SecurityOptions(key_file, got.get("dir"), got.get("ca"), got.get("cert"), got.get("key"))
