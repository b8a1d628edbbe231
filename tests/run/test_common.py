"""Security options of a run (dfusion.scenario.security, dfusion.run.common): the [security] table, TLS files, the network key."""
from __future__ import annotations

import stat

import pytest

from dfusion.errors import ValidationError
from dfusion.run.common import generate_network_key, load_network_key, new_run_id
from dfusion.scenario.security import SecurityOptions, security_options


def test_security_table_is_parsed_strictly_with_paths_relative_to_the_scenario(tmp_path):
    sec = security_options({"network_key_file": "secrets/net.key", "tls": {"dir": "certs", "ca": "/etc/ca.pem"}},
                           tmp_path)
    assert sec == SecurityOptions(str(tmp_path / "secrets/net.key"), str(tmp_path / "certs"), "/etc/ca.pem")
    assert sec.tls and not SecurityOptions().tls
    assert security_options(None) == SecurityOptions()
    for table, match in [({"tsl": {}}, r"security\.tsl: unknown key"),
                         ({"tls": {"dir": "c", "crt": "x"}}, r"security\.tls\.crt: unknown key"),
                         ({"tls": {}}, "empty"),
                         ({"tls": "certs"}, r"\[security\.tls\]"),
                         ({"network_key_file": 3}, "network_key_file must be"),
                         ({"tls": {"ca": ""}}, "ca must be")]:
        with pytest.raises(ValidationError, match=match):
            security_options(table, tmp_path)


def test_tls_files_per_process_shared_or_missing(tmp_path):
    for name in ("ca.pem", "a.pem", "a.key", "node.pem", "node.key"):
        (tmp_path / name).write_text("-----BEGIN X-----\n")
    sec = SecurityOptions(tls_dir=str(tmp_path))
    a, b = sec.tls_files("a"), sec.tls_files("b")
    assert (a.ca, a.cert, a.key) == (str(tmp_path / "ca.pem"), str(tmp_path / "a.pem"), str(tmp_path / "a.key"))
    assert (b.cert, b.key) == (str(tmp_path / "node.pem"), str(tmp_path / "node.key"))   # the shared one
    assert SecurityOptions().tls_files("a") is None
    with pytest.raises(ValidationError, match="private key"):
        SecurityOptions(tls_ca=str(tmp_path / "ca.pem"), tls_cert=str(tmp_path / "a.pem")).tls_files("a")
    (tmp_path / "node.key").unlink()
    with pytest.raises(ValidationError, match="node.key"):
        sec.tls_files("b")
    # the command line over the scenario: the key file where the command line has none, TLS as a whole
    cli = SecurityOptions(tls_ca="x", tls_cert="y", tls_key="z")
    scen = SecurityOptions("k", tls_dir=str(tmp_path))
    assert cli.over(scen) == SecurityOptions("k", None, "x", "y", "z")
    assert SecurityOptions().over(scen) == scen


def test_generated_network_key_is_private_and_random(tmp_path):
    k1 = generate_network_key(tmp_path / "k1")
    k2 = generate_network_key(tmp_path / "k2")
    assert stat.S_IMODE((tmp_path / "k1").stat().st_mode) == 0o600
    assert len(k1) == 64 and k1 != k2 and bytes.fromhex(k1.decode())
    assert load_network_key(tmp_path / "k1") == k1
    assert new_run_id() != new_run_id() and len(new_run_id()) == 16
    # a file (or a symlink planted there) is replaced, never written through
    victim = tmp_path / "victim"
    victim.write_bytes(b"keep")
    (tmp_path / "k3").symlink_to(victim)
    generate_network_key(tmp_path / "k3")
    assert victim.read_bytes() == b"keep" and not (tmp_path / "k3").is_symlink()
    assert stat.S_IMODE((tmp_path / "k3").stat().st_mode) == 0o600
