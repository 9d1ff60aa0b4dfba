#!/usr/bin/env python3
"""How hard the slack unknowns are on their own: a measurement for the
third design of issue 17 (keep every factorization of the full stiffness
K, make the slacks of the slack cables extra Krylov unknowns).

    nsdd solve SCENE --method direct --out DIRECT.json
    python3 benches/tools/slack_schur.py SCENE DIRECT.json

With the direct solver's slack set S (its `slack` flags) and the slack
forces mu = k lambda of those cables, the unknowns of that design satisfy

    (diag(1/k_S) - H_S^T K^-1 H_S) mu = -H_S^T K^-1 f

(the cables of S carry no tension: h_c^T u + mu_c / k_c = 0 with
u = K^-1 (f - H_S mu)). The script solves K exactly (sparse LU), forms this
Schur complement densely, and reports its spectrum and the iterations of
CG to a relative residual of 1e-8 with Jacobi and with block-Jacobi
preconditioners (exact diagonal blocks of the Schur complement on 2x2,
4x4, 8x8 boxes of the plan). Those are the counts with the subdomain
solves exact and the best local preconditioner of the slack block; a
design-3 iteration can only need more. It also checks the solution against
the direct one. For grids and flat scenes whose supports and loads are
as `nsdd gen` writes them, without prestress or geometric stiffness
(the grids of `nsdd gen grid`); dense in |S|: a few thousand slack cables.
Needs numpy and scipy.
"""
import json
import sys
import tomllib

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl


def load(path):
    with open(path, "rb") as fh:
        return tomllib.load(fh) if path.endswith(".toml") else json.load(fh)


def truss(scene):
    nodes = scene["nodes"]
    xyz = np.array([nodes["x"], nodes["y"], nodes["z"]]).T
    el = scene["elements"]
    a, b = np.array(el["a"]), np.array(el["b"])
    ea = np.array(el["ea"], float)
    fixed = np.zeros((len(xyz), 3), bool)
    for node, dofs in zip(scene["supports"]["node"], scene["supports"]["dofs"]):
        for c in dofs:
            fixed[node, "xyz".index(c)] = True
    dof = -np.ones((len(xyz), 3), int)
    dof[~fixed] = np.arange((~fixed).sum())
    nf = int((~fixed).sum())
    f = np.zeros(nf)
    loads = scene["loads"]
    for i, node in enumerate(loads["node"]):
        for c, key in enumerate(("fx", "fy", "fz")):
            if dof[node, c] >= 0 and key in loads:
                f[dof[node, c]] += loads[key][i]
    d = xyz[b] - xyz[a]
    length = np.linalg.norm(d, axis=1)
    n = d / length[:, None]
    rows, cols, vals = [], [], []
    for e in range(len(a)):
        for c in range(3):
            for node, sign in ((b[e], 1.0), (a[e], -1.0)):
                if dof[node, c] >= 0:
                    rows.append(dof[node, c])
                    cols.append(e)
                    vals.append(sign * n[e, c])
    h = sp.csc_matrix((vals, (rows, cols)), shape=(nf, len(a)))
    return xyz, a, b, ea / length, dof, f, h


def pcg(a, rhs, precondition, tol=1e-8, max_iterations=5000):
    x = np.zeros_like(rhs)
    r = rhs.copy()
    z = precondition(r)
    p = z.copy()
    rz = r @ z
    r0 = np.linalg.norm(rhs)
    for it in range(1, max_iterations + 1):
        q = a @ p
        alpha = rz / (p @ q)
        x += alpha * p
        r -= alpha * q
        if np.linalg.norm(r) <= tol * r0:
            return x, it
        z = precondition(r)
        rz_new = r @ z
        p = z + rz_new / rz * p
        rz = rz_new
    return x, max_iterations


def main():
    scene, direct = load(sys.argv[1]), load(sys.argv[2])
    xyz, a, b, k, dof, f, h = truss(scene)
    stiffness = (h @ sp.diags(k) @ h.T).tocsc()
    slack = np.where(np.array(direct["slack"]))[0]
    print(f"free dofs {len(f)}, elements {len(k)}, slack cables (direct) {len(slack)}")
    lu = spl.splu(stiffness)
    hs = h[:, slack].toarray()
    schur = np.diag(1.0 / k[slack]) - hs.T @ lu.solve(hs)
    rhs = -hs.T @ lu.solve(f)
    diag = np.diag(schur)
    scaled = schur / np.sqrt(np.outer(diag, diag))
    ev = np.linalg.eigvalsh(scaled)
    print(f"Jacobi-scaled spectrum [{ev[0]:.3e}, {ev[-1]:.3e}], condition {ev[-1] / ev[0]:.3e}")
    for t in (0.01, 0.1, 0.3):
        print(f"  eigenvalues below {t}: {(ev < t).sum()}")
    mu, its = pcg(schur, rhs, lambda r: r / diag)
    u = lu.solve(f - hs @ mu)
    ud = np.array(direct["displacements"]).reshape(-1, 3)
    mask = dof >= 0
    u_direct = np.zeros(len(f))
    u_direct[dof[mask]] = ud[mask]
    err = np.linalg.norm(u - u_direct) / np.linalg.norm(u_direct)
    print(f"CG, Jacobi: {its} iterations; displacements {err:.1e} off the direct solve, min slack force {mu.min():.2e}")
    mid = 0.5 * (xyz[a] + xyz[b])[slack]
    lo, span = xyz.min(axis=0), np.ptp(xyz, axis=0) + 1e-12
    for m in (2, 4, 8):
        cell = np.minimum((m * (mid[:, :2] - lo[:2]) / span[:2]).astype(int), m - 1)
        box = cell[:, 0] * m + cell[:, 1]
        blocks = []
        for g in np.unique(box):
            idx = np.where(box == g)[0]
            blocks.append((idx, np.linalg.inv(schur[np.ix_(idx, idx)])))

        def block_jacobi(r, blocks=blocks):
            z = np.zeros_like(r)
            for idx, inv in blocks:
                z[idx] = inv @ r[idx]
            return z

        _, its = pcg(schur, rhs, block_jacobi)
        print(f"CG, block-Jacobi on {m * m} boxes (exact diagonal blocks): {its} iterations")


if __name__ == "__main__":
    main()
