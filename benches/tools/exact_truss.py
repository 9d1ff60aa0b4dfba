#!/usr/bin/env python3
"""40-digit solution of a linear truss scene, for accuracy figures at high
stiffness contrast where the double-precision direct solve is itself off.

    python3 benches/tools/exact_truss.py SCENE.toml OUT.json
    python3 benches/tools/exact_truss.py SCENE.toml OUT.json RESULT.json ...

Assembles K = sum EA/L e e^T over the free dofs (no prestress, no geometric
stiffness, every cable taut: generate with unilateral=false), solves K u = f
by LU in mpmath at 40 digits, and writes {"u": [...3 per node], "t": [...]}.
Each RESULT.json given after OUT.json (an `nsdd solve --out` file) is
compared: relative 2-norm errors of displacements and tensions. Needs
mpmath and numpy; a few hundred dofs take ~30 s.
"""
import json
import sys
import tomllib

import numpy as np
from mpmath import lu_solve, matrix, mp, mpf

mp.dps = 40


def exact(scene):
    nodes = scene["nodes"]
    xyz = list(zip(nodes["x"], nodes["y"], nodes["z"]))
    fixed = set()
    for nd, dofs in zip(scene["supports"]["node"], scene["supports"]["dofs"]):
        for c in dofs:
            fixed.add(3 * nd + "xyz".index(c))
    free = [d for d in range(3 * len(xyz)) if d not in fixed]
    idx = {d: i for i, d in enumerate(free)}
    k_mat = matrix(len(free), len(free))
    el = scene["elements"]
    geo = []
    for a, b, ea in zip(el["a"], el["b"], el["ea"]):
        d = [mpf(xyz[b][c]) - mpf(xyz[a][c]) for c in range(3)]
        length = mp.sqrt(sum(x * x for x in d))
        e = [x / length for x in d]
        k = mpf(ea) / length
        geo.append((a, b, e, k))
        dofs = [3 * a + i for i in range(3)] + [3 * b + i for i in range(3)]
        v = e + [-x for x in e]
        for i in range(6):
            for j in range(6):
                if dofs[i] in idx and dofs[j] in idx:
                    k_mat[idx[dofs[i]], idx[dofs[j]]] += k * v[i] * v[j]
    f = matrix(len(free), 1)
    loads = scene.get("loads", {})
    for nd, fx, fy, fz in zip(loads.get("node", []), loads.get("fx", []), loads.get("fy", []), loads.get("fz", [])):
        for c, val in enumerate((fx, fy, fz)):
            if 3 * nd + c in idx:
                f[idx[3 * nd + c]] += mpf(val)
    u = lu_solve(k_mat, f)
    full = [mpf(0)] * (3 * len(xyz))
    for d, i in idx.items():
        full[d] = u[i]
    t = [k * sum(e[c] * (full[3 * b + c] - full[3 * a + c]) for c in range(3)) for a, b, e, k in geo]
    return [float(x) for x in full], [float(x) for x in t]


def main():
    scene = tomllib.load(open(sys.argv[1], "rb"))
    u, t = exact(scene)
    json.dump({"u": u, "t": t}, open(sys.argv[2], "w"))
    ut, tt = np.array(u), np.array(t)
    for path in sys.argv[3:]:
        r = json.load(open(path))
        ur = np.array(r["displacements"]).ravel()
        tr = np.array(r["tensions"])
        eu = np.linalg.norm(ur - ut) / np.linalg.norm(ut)
        et = np.linalg.norm(tr - tt) / np.linalg.norm(tt)
        print(f"{path}: displacements {eu:.2e}, tensions {et:.2e}")


if __name__ == "__main__":
    main()
