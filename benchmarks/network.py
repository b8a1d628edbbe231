"""Per-node CPU time per cycle of in-process fusion networks, and message size.

Table 1: networks of 2 to 128 nodes (chains, stars, random trees). Every node
measures the target's position every step, predicts, and sends to each
neighbour every other step over a simulated link (latency one step, 10%
drops). We time only the nodes' own work (predict, update, message_to,
receive) with ``time.process_time`` and report it per node and per step; the
centralized reference and the simulated network are not timed. "flat" means
the 128-node figure stays within a small factor of the 2-node one.

Table 2: bytes of one message on a link against the window length, beside the
count a dense (m n)^2 matrix and the full block-tridiagonal band would need.

Usage: python benchmarks/network.py [--quick]
"""
from __future__ import annotations

import argparse
import time

import networkx as nx
import numpy as np

from dfusion.fusion import FusionNode
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.transport import LinkSpec, SimulatedNetwork


def make_graph(kind: str, n: int, seed: int = 0) -> nx.Graph:
    if kind == "chain":
        g = nx.path_graph(n)
    elif kind == "star":
        g = nx.star_graph(n - 1)
    else:
        g = nx.random_labeled_tree(n, seed=seed) if n > 2 else nx.path_graph(n)
    return nx.relabel_nodes(g, {i: f"n{i:03d}" for i in g.nodes})


def run(graph: nx.Graph, steps: int, window: int, dt: float = 0.1, seed: int = 0) -> tuple[float, float]:
    """Return (CPU seconds per node per step, mean message bytes in the steady state)."""
    rng = np.random.default_rng(seed)
    motion = ConstantVelocity(2, 0.1)
    sensor = PositionSensor(2, 0.5)
    prior = (0.0, np.zeros(4), np.eye(4))
    names = sorted(graph.nodes)
    nodes = {n: FusionNode(n, sorted(graph.neighbors(n)), motion, window=window, prior=prior) for n in names}
    net = SimulatedNetwork(((a, b, LinkSpec(latency=dt, drop=0.1)) for a, b in graph.edges), seed=seed)
    cpu = 0.0
    timed_steps = 0
    warmup = window  # fill the window first, so marginalization is part of every cycle
    nbytes, nmsgs = 0, 0
    for k in range(1, warmup + steps + 1):
        t = round(k * dt, 9)
        zs = rng.normal(size=(len(names), 2))
        inbox = {n: [d.data for d in net.receive(n, t + 1e-9)] for n in names}
        c0 = time.process_time()
        out = []
        for i, n in enumerate(names):
            node = nodes[n]
            node.predict(t)
            node.update(t, zs[i], sensor)
            for data in inbox[n]:
                node.receive(data)
            if k % 2 == 0:
                for nb in node.neighbors:
                    out.append((n, nb, node.message_to(nb)))
        c1 = time.process_time()
        for src, dst, data in out:
            net.send(src, dst, data, t)
            if k > warmup:   # steady state: the windows are full
                nbytes += len(data)
                nmsgs += 1
        if k > warmup:
            cpu += c1 - c0
            timed_steps += 1
    return cpu / (len(names) * timed_steps), nbytes / max(nmsgs, 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps and sizes")
    args = ap.parse_args()
    steps = 20 if args.quick else 50
    window = 30
    sizes = [2, 8, 32, 128]
    print(f"Table 1: CPU time per node per cycle (ms), window {window} states, {steps} timed steps after warm-up")
    print(f"{'topology':<12}" + "".join(f"{n:>10}" for n in sizes) + f"{'128 / 2':>10}")
    for kind in ("chain", "star", "random"):
        row = []
        for n in sizes:
            cpu, _ = run(make_graph(kind, n), steps, window)
            row.append(cpu * 1e3)
        print(f"{kind:<12}" + "".join(f"{v:>10.3f}" for v in row) + f"{row[-1] / row[0]:>10.2f}")
    print()
    print("Table 2: message size on one link (2 nodes, both measuring every step, state dim 4)")
    print(f"{'window':>8}{'bytes/msg':>12}{'floats sent':>13}{'band floats':>13}{'dense floats':>14}{'bytes/s @2Hz':>14}")
    n = 4
    for m in (10, 50, 100, 200):
        _, b = run(make_graph("chain", 2), 10 if args.quick else 20, m)
        sent = m * (n * (n + 1) // 2 + n + 1)        # per state: packed block, vector, time
        band = m * n * (n + 1) // 2 + (m - 1) * n * n + m * n
        dense = (m * n) ** 2 + m * n
        print(f"{m:>8}{b:>12.0f}{sent:>13}{band:>13}{dense:>14}{b * 2:>14.0f}")


if __name__ == "__main__":
    main()
