"""A switching policy named in a scenario file: registered by ``load_scenario`` itself and
used by the nodes of both ``dfusion simulate`` (in process) and the node program
(``dfusion run``, one process per node)."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]

# A camera node (its front end reports the source "camera" after each fused detection,
# with the eq. 1-9 reliability) and a relay; the target crosses the camera's view.
SCENARIO = """
duration = 12.0
dt = 0.1
seed = 4
window = 60

[target]
motion = "constant_velocity"
q = 0.001
initial_mean = [-6.0, 2.0, 1.2, 0.0]
initial_cov_diag = [0.01, 0.01, 0.001, 0.001]

[[nodes]]
name = "cam"
sensor = "camera"
position = [0.0, -6.0, 5.0]
look_at = [0.0, 2.0]
fx = 600.0
width = 640
height = 480
pixel_std = 2.0
rate = 5.0
send_period = 0.5
policy = {POLICY}

[[nodes]]
name = "relay"
send_period = 0.5

[[links]]
between = ["cam", "relay"]
latency = 0.05
"""

GREEDY = '{ kind = "greedy", punishment = 0.12 }'


def write(tmp_path: Path, policy: str = GREEDY) -> Path:
    path = tmp_path / "policy.scenario.toml"
    path.write_text(SCENARIO.replace("{POLICY}", policy))
    return path


def test_load_scenario_knows_the_switching_policies_itself(tmp_path):
    """In a fresh interpreter that imports only dfusion.scenario, a policy name works: the
    built-in policies are an explicit table of the scenario package, not registered by an
    import the user has to remember."""
    path = write(tmp_path)
    script = textwrap.dedent(f"""
        import json, sys
        from dfusion.scenario import load_scenario
        sc = load_scenario({str(path)!r})
        pol = sc.nodes["cam"].policy
        print(json.dumps({{"cls": type(pol).__module__ + "." + type(pol).__name__,
                          "punishment": pol.punishment,
                          "relay": type(sc.nodes["relay"].policy).__name__ if sc.nodes["relay"].policy else None}}))
    """)
    res = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["cls"] == "dfusion.policies.switching.GreedySwitchingPolicy"
    assert out["punishment"] == 0.12
    assert out["relay"] in (None, "InformationFusionPolicy")   # default: the node's fusion


def _simulate_nodes(path: Path, monkeypatch, capsys) -> dict:
    """Run ``dfusion simulate`` on ``path`` and return the nodes it built."""
    from dfusion import cli
    from dfusion.sim import runner

    built = {}
    original = runner.build_nodes

    def capture(sc, **kw):
        nodes = original(sc, **kw)
        built.update(nodes)
        return nodes

    monkeypatch.setattr(runner, "build_nodes", capture)
    assert cli.main(["simulate", str(path), "--quiet"]) == 0
    assert "RMSE" in capsys.readouterr().out
    return built


def test_dfusion_simulate_nodes_output_through_the_scenario_policy(tmp_path, monkeypatch, capsys):
    from dfusion.policies import GreedySwitchingPolicy

    nodes = _simulate_nodes(write(tmp_path), monkeypatch, capsys)
    cam = nodes["cam"]
    assert isinstance(cam.policy, GreedySwitchingPolicy) and cam.policy.punishment == 0.12
    assert "camera" in cam.sources                       # reported by the camera front end
    out = cam.output()
    assert out.name == "camera" and cam.policy.current == "camera"
    np.testing.assert_array_equal(out.mean, cam.sources["camera"].mean)
    assert 0 < out.reliability <= 1
    # the source is the estimate at the last fused detection, not the node's newest fused state
    assert out.t < cam.latest_time
    assert nodes["relay"].output().name == "fused"        # no policy named: fusion

    # the same file with policy = "fusion": the node outputs its fused estimate
    fused = _simulate_nodes(write(tmp_path, '"fusion"'), monkeypatch, capsys)["cam"]
    assert "camera" in fused.sources and fused.output().name == "fused"


def test_node_program_builds_its_node_with_the_scenario_policy(tmp_path):
    """The node program (``dfusion.run.node_process``) builds the same policy and its front
    end feeds the same sources; driven step by step here without opening a Zenoh session."""
    from dfusion.run.node_process import NodeProcess
    from dfusion.scenario import load_scenario
    from dfusion.policies import GreedySwitchingPolicy

    sc = load_scenario(write(tmp_path))
    proc = NodeProcess(sc, "cam", start=0.0)
    assert proc.tr is None                                # the constructor opens no session
    assert isinstance(proc.node.policy, GreedySwitchingPolicy) and proc.node.policy.punishment == 0.12
    for t in proc.times[1:]:                              # the loop's predict + fuse, without receive/send
        proc.node.predict(float(t))
        proc._fuse_until(float(t))
    assert proc.counters["measurements_fused"] > 0
    out = proc.node.output()
    assert out.name == "camera" and proc.node.policy.current == "camera"
    assert 0 < out.reliability <= 1
    relay = NodeProcess(sc, "relay", start=0.0)
    assert relay.node.output().name == "fused"


@pytest.mark.parametrize("policy, expected", [
    ('"hysteresis"', "HysteresisSwitchingPolicy"),
    ('{ kind = "blend", inner = "greedy", duration = 0.5 }', "BlendedTransitionPolicy"),
    ('{ kind = "fusion_floor", floor = 0.3 }', "FusionFloorPolicy"),
])
def test_every_switching_policy_name_builds_in_both_paths(tmp_path, policy, expected):
    import dfusion.policies as switching
    from dfusion.run.node_process import NodeProcess
    from dfusion.scenario import build_nodes
    from dfusion.scenario import load_scenario

    cls = getattr(switching, expected)
    sc = load_scenario(write(tmp_path, policy))
    assert isinstance(build_nodes(sc)["cam"].policy, cls)
    assert isinstance(NodeProcess(sc, "cam", start=0.0).node.policy, cls)


def test_simulate_records_the_policy_output_and_scores_it(tmp_path):
    """``run_scenario`` records ``node.output()`` of a node with a switching policy; the
    JSON figures of that output match a direct computation from the recorded series."""
    from dfusion.scenario import build_nodes
    from dfusion.sim import run_scenario
    from dfusion.scenario import load_scenario

    sc = load_scenario(write(tmp_path))
    res = run_scenario(sc)
    assert set(res.outputs) == {"cam"}                    # relay: plain fusion, nothing recorded
    o = res.outputs["cam"]
    src = np.array(o.source)
    assert {"fused", "camera"} <= set(src)                # fused before the first detection, then the camera
    fused = src == "fused"
    np.testing.assert_array_equal(o.mean[fused], res.node_mean["cam"][fused])
    assert np.any(np.abs(o.mean[~fused] - res.node_mean["cam"][~fused]).max(axis=1) > 0)
    m = res.metrics["nodes"]["cam"]["output"]
    err = o.mean[:, :2] - res.truth[:, :2]
    assert m["rmse"] == pytest.approx(np.sqrt(np.mean(np.sum(err**2, axis=1))), rel=1e-12)
    assert m["switches"] == int(np.count_nonzero(src[1:] != src[:-1])) >= 1
    assert sum(m["sources"].values()) == pytest.approx(1.0)
    assert m["policy"] == "greedy"
    assert "output" not in res.metrics["nodes"]["relay"]
    assert "policy outputs" in res.table() and "cam: policy greedy" in res.table()
    # every build gets its own policy (a policy remembers its current source)
    a, b = build_nodes(sc), build_nodes(sc)
    assert a["cam"].policy is not b["cam"].policy and a["cam"].policy is not sc.nodes["cam"].policy

    # with plain fusion nothing extra is recorded
    res_f = run_scenario(load_scenario(write(tmp_path, '"fusion"')))
    assert res_f.outputs == {} and "output" not in res_f.metrics["nodes"]["cam"]


def test_status_carries_the_policy_output_both_ways():
    from dfusion.run.common import Status

    out = ("camera", np.arange(4.0), np.diag([1.0, 2.0, 3.0, 4.0]))
    st = Status("cam", 7, "run", 3, 0.3, np.zeros(4), np.eye(4), output=out)
    from dfusion.wire import FrameKey

    key = FrameKey(b"k" * 16, "net", "run")
    for back in (Status.decode(st.encode(key), key), Status.from_json(json.loads(json.dumps(st.to_json())))):
        assert back.output[0] == "camera"
        np.testing.assert_array_equal(back.output[1], out[1])
        np.testing.assert_array_equal(back.output[2], out[2])
    assert Status.decode(Status("r", 1, "run", 0).encode()).output is None


def test_dfusion_run_reports_the_policy_output_like_simulate(tmp_path, capsys):
    """One OS process per node over Zenoh: the camera node publishes its policy output, and
    ``dfusion run`` scores it with the keys of ``dfusion simulate``."""
    pytest.importorskip("zenoh")
    from dfusion.cli import main
    from dfusion.sim import run_scenario
    from dfusion.scenario import load_scenario

    path = write(tmp_path)
    out_json = tmp_path / "run.json"
    rc = main(["run", str(path), "--speed", "4", "--json", str(out_json), "--run-dir", str(tmp_path / "run"),
               "--quiet"])
    printed = capsys.readouterr().out
    assert rc == 0, printed
    got = json.loads(out_json.read_text())["nodes"]
    ref = run_scenario(load_scenario(path)).metrics["nodes"]
    assert "output" not in got["relay"]
    o, r = got["cam"]["output"], ref["cam"]["output"]
    assert set(o) == set(r) and o["policy"] == "greedy"
    assert {"camera", "fused"} <= set(o["sources"]) and o["switches"] >= 1
    # real timing differs from the simulated links, so the path differs a little, not the choice
    assert abs(o["sources"]["camera"] - r["sources"]["camera"]) < 0.2
    assert "policy outputs" in printed


def test_policies_named_in_a_plain_topology_file(tmp_path):
    """Topology files (names and links only) can name a policy per node too."""
    from dfusion.fusion import FusionNode
    from dfusion.errors import ScenarioError
    from dfusion.models import ConstantVelocity
    from dfusion.scenario import node_policies
    from dfusion.policies import GreedySwitchingPolicy, HysteresisSwitchingPolicy
    from dfusion.topology import load_topology

    path = tmp_path / "t.toml"
    path.write_text('[[nodes]]\nname = "robot"\npolicy = { kind = "hysteresis", upper = 0.8, lower = 0.6 }\n'
                    '[[nodes]]\nname = "cam"\npolicy = "greedy"\n[[nodes]]\nname = "hub"\n'
                    '[[links]]\nbetween = ["robot", "hub"]\n[[links]]\nbetween = ["cam", "hub"]\n')
    pol = node_policies(load_topology(path))
    assert set(pol) == {"robot", "cam"}
    assert isinstance(pol["robot"], HysteresisSwitchingPolicy) and isinstance(pol["cam"], GreedySwitchingPolicy)
    node = FusionNode("robot", ["hub"], ConstantVelocity(2, 0.1), window=10,
                      prior=(0.0, np.zeros(4), np.eye(4)), policy=pol["robot"])
    assert node.policy is pol["robot"]
    path.write_text('[[nodes]]\nname = "a"\npolicy = "nonsense"\n[[nodes]]\nname = "b"\n'
                    '[[links]]\nbetween = ["a", "b"]\n')
    with pytest.raises(ScenarioError, match=r"t\.toml.*node 'a'\.policy.*unknown policy 'nonsense'"):
        node_policies(load_topology(path))
