#!/usr/bin/env python3
"""Interface entries each MPI rank shares with other ranks, counted from the
scene and the result's element partition alone (independently of nsdd's
seam): the E_cut of the trace-volume formula in BENCHMARKS.md.

    python3 benches/tools/mpi_cut_entries.py SCENE.toml RESULT.json RANKS

An entry is a (pair of subdomains sharing a node, free dof of the node);
rank r owns subdomains floor(r n/p) .. floor((r+1) n/p) - 1.
"""
import itertools
import json
import sys
import tomllib

scene = tomllib.load(open(sys.argv[1], "rb"))
result = json.load(open(sys.argv[2]))
p = int(sys.argv[3])
part, ns = result["element_subdomain"], result["subdomains"]
n_nodes = len(scene["nodes"]["x"])
fixed = [0] * n_nodes
sup = scene.get("supports", {})
for node, dofs in zip(sup.get("node", []), sup.get("dofs", [])):
    fixed[node] = len(dofs)
subs = [set() for _ in range(n_nodes)]
for e, (a, b) in enumerate(zip(scene["elements"]["a"], scene["elements"]["b"])):
    subs[a].add(part[e])
    subs[b].add(part[e])


def owner(s):
    return max(r for r in range(p) if ns * r // p <= s)


cut = [0] * p
for node in range(n_nodes):
    free = 3 - fixed[node]
    for s1, s2 in itertools.combinations(sorted(subs[node]), 2):
        r1, r2 = owner(s1), owner(s2)
        if r1 != r2:
            cut[r1] += free
            cut[r2] += free
print("E_cut per rank", cut)
