#!/usr/bin/env python3
"""Equilibrium check of a solved linear truss, independent of nsdd's code:
for structures whose direct solve does not fit, this is what a result is
checked against.

    python3 benches/tools/equilibrium_residual.py SCENE.(toml|json) RESULT.json

Reads the scene (bars and cables with their EA; no prestress, geometric
stiffness or self weight: generate with unilateral=false) and an
`nsdd solve --out` result, and prints

* `constitutive`: max over elements of |t - EA/L n.(u_b - u_a)|, relative to
  max |t| (do the tensions belong to the displacements?);
* `equilibrium`: ||f - sum_e t_e B_e||_2 / ||f||_2 over the free dofs, and
  the same residual relative to sum_e |t_e| ||B_e|| per dof (the size of
  the forces that cancel there: round-off of an exact solution is ~1e-16).

Needs numpy; a 1e6-dof tower takes about a minute and a few GB.
"""
import json
import sys

import numpy as np


def load(path):
    if path.endswith(".json"):
        with open(path) as f:
            return json.load(f)
    import tomllib

    with open(path, "rb") as f:
        return tomllib.load(f)


def main(scene_path, result_path):
    scene = load(scene_path)
    result = load(result_path)
    eff = scene.get("effects", {})
    for e in ("prestress", "geometric_stiffness", "self_weight"):
        if eff.get(e):
            sys.exit(f"{scene_path}: effect {e} is on; this check covers plain linear trusses only")
    nodes = scene["nodes"]
    xyz = np.column_stack([nodes["x"], nodes["y"], nodes["z"]])
    el = scene["elements"]
    a = np.asarray(el["a"], dtype=np.int64)
    b = np.asarray(el["b"], dtype=np.int64)
    ea = np.asarray(el["ea"], dtype=float)
    d = xyz[b] - xyz[a]
    length = np.linalg.norm(d, axis=1)
    n = d / length[:, None]
    u = np.asarray(result["displacements"], dtype=float)
    t = np.asarray(result["tensions"], dtype=float)
    if u.shape != xyz.shape or t.shape != a.shape:
        sys.exit("result does not match the scene (node or element count)")

    elong = np.einsum("ij,ij->i", n, u[b] - u[a])
    constitutive = np.max(np.abs(t - ea / length * elong)) / max(np.max(np.abs(t)), 1e-300)

    # Internal forces: t n pulls node a towards b, node b towards a.
    internal = np.zeros_like(xyz)
    scale = np.zeros_like(xyz)
    for k in range(3):
        np.add.at(internal[:, k], a, t * n[:, k])
        np.add.at(internal[:, k], b, -t * n[:, k])
        np.add.at(scale[:, k], a, np.abs(t * n[:, k]))
        np.add.at(scale[:, k], b, np.abs(t * n[:, k]))
    f = np.zeros_like(xyz)
    loads = scene.get("loads", {})
    for nd, fx, fy, fz in zip(
        loads.get("node", []), loads.get("fx", []), loads.get("fy", []), loads.get("fz", [])
    ):
        f[nd] += (fx, fy, fz)
    free = np.ones_like(xyz, dtype=bool)
    sup = scene.get("supports", {})
    for nd, dofs in zip(sup.get("node", []), sup.get("dofs", [])):
        for c in dofs:
            free[nd, "xyz".index(c)] = False
    r = (f + internal)[free]
    rel = np.linalg.norm(r) / max(np.linalg.norm(f[free]), 1e-300)
    per_dof = np.max(np.abs(r) / np.maximum(scale[free], 1e-300))
    print(
        json.dumps(
            {
                "free_dofs": int(free.sum()),
                "elements": int(a.size),
                "constitutive": float(constitutive),
                "equilibrium": float(rel),
                "equilibrium_per_dof": float(per_dof),
            }
        )
    )


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
