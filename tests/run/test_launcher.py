"""dfusion run with mutual TLS and a network key of its own (dfusion.run.launcher).

Real processes on loopback; the launcher's ``finally`` stops every node.
"""
from __future__ import annotations

import json
import stat
import threading
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

from dfusion.scenario.security import SecurityOptions  # noqa: E402
from dfusion.run.launcher import Launcher, RunOptions  # noqa: E402

from tests.helpers.pki import listen_in, make_pki, strangers  # noqa: E402
from tests.run.test_processes import chain3  # noqa: E402
from tests.run.test_supervision import start_in_thread, wait_until  # noqa: E402


def cmdline(pid: int) -> list[str]:
    return Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")


def test_mutual_tls_run_is_closed_to_strangers_and_keyed_per_run(tmp_path):
    """dfusion run --tls-dir: every node, the launcher's monitor and a member with a certificate of the
    CA talk over mutual TLS; strangers (only the CA certificate; a certificate of another CA; plain
    TCP) hear nothing during the run and the nodes never see their forged messages. The run's network
    key was generated (mode 0600) and reaches the nodes as a file, never on a command line."""
    pki = make_pki(tmp_path / "pki")
    scenario = chain3(tmp_path, duration=12.0, window=200)
    run_dir = tmp_path / "run"
    opts = RunOptions(scenario=str(scenario), speed=3.0, run_dir=str(run_dir),
                      security=SecurityOptions(tls_dir=str(pki.dir)))
    launcher = Launcher(opts)
    thread, box = start_in_thread(launcher)
    heard: dict[str, list[str]] = {}
    try:
        wait_until(lambda: launcher.start is not None and launcher.now() > 1.0, 90, "the start", thread)
        eps, net = list(launcher.endpoints.values()), launcher.network
        assert len(eps) == 3 and all(ep.startswith("tls/127.0.0.1:") for ep in eps), eps
        assert launcher.monitor_endpoint.startswith("tls/127.0.0.1:")
        forge = (f"dfusion/{net}/b/a", b"forged")
        knocks = {label: dict(forge=forge, **cfg) for label, cfg in strangers(pki).items()}
        knocks["plain TCP to the TLS ports"] = {"forge": forge}
        knocks["member (control)"] = {"tls": pki.member("member")}
        threads = []
        for label, kw in knocks.items():
            targets = [e.replace("tls/", "tcp/") for e in eps] if label.startswith("plain") else eps
            th = threading.Thread(target=lambda lb=label, t=targets, k=kw: heard.__setitem__(lb, listen_in(t, net, 2.0, **k)),
                                  daemon=True)
            th.start()
            threads.append(th)
        # meanwhile: the key reaches the nodes as a file, never as an argument
        key = (run_dir / "network.key").read_bytes().strip()
        assert stat.S_IMODE((run_dir / "network.key").stat().st_mode) == 0o600 and len(key) == 64
        for name, p in launcher.procs.items():
            args = cmdline(p.popen.pid)
            assert key.decode() not in " ".join(args)
            assert args[args.index("--network-key-file") + 1] == str(run_dir / "network.key")
            assert args[args.index("--run-id") + 1] == launcher.run_id
            assert args[args.index("--tls-cert") + 1] == str(pki.dir / f"{name}.pem")
        for th in threads:
            th.join(timeout=30)
        thread.join(timeout=90)
        assert not thread.is_alive()
    finally:
        launcher.request_stop("test finished")
        thread.join(timeout=10)
    assert "error" not in box, box.get("error")
    result = box["result"]
    assert result is not None
    m = result.metrics
    member = heard.pop("member (control)")
    assert f"alive dfusion/{launcher.network}/alive/a" in member
    assert any(h.startswith(f"data dfusion/{launcher.network}/") for h in member)
    assert set(heard) == {*strangers(pki), "plain TCP to the TLS ports"}
    assert {k: v for k, v in heard.items() if v} == {}, "a stranger heard something"
    run = m["run"]
    assert run["tls"] is True and run["authenticated"] is True and run["network_key"] == "generated"
    assert run["run_id"] == launcher.run_id
    for name, v in m["nodes"].items():
        assert v["final_gap"] <= 1e-9, (name, v["final_gap"])
        assert v["messages"] > 0 and v["rejected"] == 0   # no forged message even reached a node
    assert run["monitor_rejected"] == 0
    header = json.loads((run_dir / "state" / "b.measurements.jsonl").read_text().splitlines()[0])
    assert header["run"] == launcher.run_id
    print(f"mutual TLS run: member heard {len(member)} samples, strangers {sum(map(len, heard.values()))}; "
          f"final gaps {max(v['final_gap'] for v in m['nodes'].values()):.1e}")


def test_the_scenarios_security_table_is_read_and_the_command_line_wins(tmp_path):
    """The launcher reads a scenario's [security] table (paths relative to the file) strictly; the
    command line's TLS options replace the table's."""
    from types import SimpleNamespace

    from dfusion.errors import ValidationError
    from dfusion.run.launcher import scenario_security

    sc = SimpleNamespace(raw={"security": {"network_key_file": "k", "tls": {"dir": "certs"}}}, base_dir=str(tmp_path))
    sec = scenario_security(sc)
    assert sec == SecurityOptions(str(tmp_path / "k"), str(tmp_path / "certs"))
    assert SecurityOptions(tls_ca="a", tls_cert="b", tls_key="c").over(sec).tls_dir is None
    assert scenario_security(SimpleNamespace(raw={}, base_dir=None)) == SecurityOptions()
    with pytest.raises(ValidationError, match="security.tls.cetr"):
        scenario_security(SimpleNamespace(raw={"security": {"tls": {"cetr": "x"}}}, base_dir=None))


def test_host_groups_hold_every_node_once_in_hosts_of_even_sizes(tmp_path):
    """--nodes-per-process N: ceil(n / N) hosts whose sizes differ by at most one, every node in one,
    neighbours together (depth-first order), named host0.. (never a node's name); N = 1: a host per node,
    named after it."""
    from dfusion.run.launcher import host_groups
    from dfusion.scenario import load_scenario
    from dfusion.topology import random_tree

    names = {f"n{k}" for k in range(23)} | {"host0"}
    links = random_tree(23, seed=2) + [("n5", "host0")]
    text = "duration = 1.0\n" + "".join(f'[[nodes]]\nname = "{n}"\nsensor = "position"\n' for n in sorted(names)) \
        + "".join(f'[[links]]\nbetween = ["{a}", "{b}"]\n' for a, b in links)
    (tmp_path / "t.toml").write_text(text)
    sc = load_scenario(tmp_path / "t.toml")
    assert host_groups(sc, 1) == {n: [n] for n in sorted(names)}
    for per in (2, 5, 8, 24, 100):
        hosts = host_groups(sc, per)
        sizes = [len(v) for v in hosts.values()]
        assert len(hosts) == -(-len(names) // per) and max(sizes) - min(sizes) <= 1 and max(sizes) <= per
        assert sorted(n for v in hosts.values() for n in v) == sorted(names)
        assert not set(hosts) & names
        order = [n for v in hosts.values() for n in v]   # depth-first: each node links to an earlier one
        assert all(any(sc.graph.has_edge(order[i], w) for w in order[:i]) for i in range(1, len(order)))
