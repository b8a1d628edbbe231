"""The test PKI made with the openssl command line (dfusion.run.certs)."""
from __future__ import annotations

import shutil
import stat
import subprocess

import pytest

from dfusion.run.certs import main, make_test_pki

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="the openssl command line is not installed")


def openssl(*args: str) -> str:
    out = subprocess.run(["openssl", *args], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_every_certificate_is_signed_by_the_ca_for_both_tls_roles(tmp_path):
    """Checked by openssl itself: each certificate verifies against ca.pem as a TLS server and as a
    TLS client, names the hosts, is not a CA; keys are private (0600)."""
    made = make_test_pki(tmp_path, ["a", "b"], hosts=["localhost", "127.0.0.1", "10.0.0.7"])
    assert set(made) == {"ca", "a", "b"}
    ca = str(tmp_path / "ca.pem")
    for name in ("a", "b"):
        pem = str(tmp_path / f"{name}.pem")
        for purpose in ("sslserver", "sslclient"):
            assert openssl("verify", "-purpose", purpose, "-CAfile", ca, pem).strip() == f"{pem}: OK"
        text = openssl("x509", "-in", pem, "-noout", "-text")
        assert "DNS:localhost, IP Address:127.0.0.1, IP Address:10.0.0.7" in text
        assert "CA:FALSE" in text and f"Subject: CN = {name}" in text
        assert stat.S_IMODE((tmp_path / f"{name}.key").stat().st_mode) == 0o600
    assert stat.S_IMODE((tmp_path / "ca.key").stat().st_mode) == 0o600
    assert "CA:TRUE" in openssl("x509", "-in", ca, "-noout", "-text")


def test_the_ca_is_reused_and_a_foreign_certificate_does_not_verify(tmp_path, capsys):
    make_test_pki(tmp_path / "run", ["a"])
    ca_before = (tmp_path / "run" / "ca.pem").read_bytes()
    # the command line: one certificate per node of a scenario, plus launcher and monitor, same CA
    scenario = tmp_path / "pair.scenario.toml"
    scenario.write_text('duration = 1.0\ndt = 0.1\n[target]\n[[nodes]]\nname = "p"\nsensor = "position"\n'
                        '[[nodes]]\nname = "q"\nsensor = "position"\n[[links]]\nbetween = ["p", "q"]\n')
    assert main([str(tmp_path / "run"), "--scenario", str(scenario)]) == 0
    assert "launcher:" in capsys.readouterr().out
    assert (tmp_path / "run" / "ca.pem").read_bytes() == ca_before
    for name in ("a", "p", "q", "launcher", "monitor"):
        openssl("verify", "-CAfile", str(tmp_path / "run" / "ca.pem"), str(tmp_path / "run" / f"{name}.pem"))
    make_test_pki(tmp_path / "other", ["x"], ca_name="another CA")
    bad = subprocess.run(["openssl", "verify", "-CAfile", str(tmp_path / "run" / "ca.pem"),
                          str(tmp_path / "other" / "x.pem")], capture_output=True, text=True)
    assert bad.returncode != 0
