#!/usr/bin/env python3
"""Looks for false claims: runs the iterative methods over small generated
scenes, option sets, subdomain counts and tolerances, and prints every run
that says `converged` while its displacements or tensions are more than 10x
its tolerance off the direct solver's (BENCHMARKS.md, session 30). Runs that
end unconverged are fine: they say so.

    cargo build --release
    python3 benches/tools/claim_sweep.py target/release/nsdd /tmp/sweep cg
    python3 benches/tools/claim_sweep.py target/release/nsdd /tmp/sweep multilevel

Python 3 standard library only. The last line is `runs N converged C
errors E bad M`; the exit
status is 1 when M > 0.
"""
import itertools
import json
import math
import os
import subprocess
import sys

# name: `nsdd gen` arguments (nonsmooth and linear grids, a contrast tower
# with unilateral cables and a linear one, a tensegrity grid without
# geometric stiffness, which DD methods cannot take beyond 2 subdomains).
SCENES = {
    "g": ["grid", "nx=9", "ny=7"],
    "l": ["grid", "nx=9", "ny=7", "unilateral=false", "t0=0"],
    "t": ["tower", "nx=2", "ny=2", "nz=5"],
    "tl": ["tower", "nx=3", "ny=3", "nz=3", "unilateral=false"],
    "ts": ["tensegrity", "nx=4", "ny=4", "load=1"],
}

CG_OPTIONS = [
    [],
    ["--interface-scaling", "multiplicity"],
    ["--interface-scaling", "stiffness"],
    ["--interface-scaling", "contrast"],
    ["--interface-scaling", "deluxe"],
    ["--preconditioner", "lumped"],
    ["--adaptive-threshold", "5"],
    ["--adaptive-threshold", "0"],
    ["--partitioner", "metis"],
    # The combinations that found the false claim fixed in 2e4ea9d.
    ["--interface-scaling", "stiffness", "--adaptive-threshold", "0"],
    ["--interface-scaling", "contrast", "--preconditioner", "lumped", "--adaptive-threshold", "0"],
]


def flat(x):
    out = []
    for v in x:
        out.extend(flat(v) if isinstance(v, list) else [v])
    return out


def rel(x, y):
    x, y = flat(x), flat(y)
    d = math.sqrt(sum((p - q) ** 2 for p, q in zip(x, y)))
    n = math.sqrt(sum(q * q for q in y))
    return d / n if n > 0 else d


def main():
    nsdd, out_dir, method = sys.argv[1], sys.argv[2], sys.argv[3]
    os.makedirs(out_dir, exist_ok=True)
    options = CG_OPTIONS if method == "cg" else [[], ["--partitioner", "metis"]]
    runs = bad = claims = errors = 0
    for name, gen in SCENES.items():
        scene = os.path.join(out_dir, name + ".toml")
        subprocess.run([nsdd, "gen", *gen, "--out", scene], check=True, capture_output=True)
        if name == "ts":
            with open(scene) as f:
                text = f.read()
            with open(scene, "w") as f:
                f.write(text.replace("geometric_stiffness = true", "geometric_stiffness = false"))
        ref = os.path.join(out_dir, name + "_direct.json")
        subprocess.run([nsdd, "solve", scene, "--method", "direct", "--out", ref], check=True, capture_output=True)
        with open(ref) as f:
            direct = json.load(f)
        for opts, s, tol in itertools.product(options, [2, 3, 4, 6, 9], [1e-6, 1e-8, 1e-10]):
            out = os.path.join(out_dir, name + "_run.json")
            if os.path.exists(out):
                os.remove(out)
            cmd = [nsdd, "solve", scene, "--method", method, "--subdomains", str(s)]
            cmd += ["--tolerance", str(tol), "--max-iterations", "20000", "--out", out, *opts]
            subprocess.run(cmd, capture_output=True, text=True, timeout=300)
            runs += 1
            if not os.path.exists(out):
                errors += 1  # an error, named on stderr: not a claim
                continue
            with open(out) as f:
                r = json.load(f)
            if not all(math.isfinite(v) for v in flat(r["displacements"]) + r["tensions"]):
                bad += 1
                print("NON-FINITE", name, s, tol, opts)
            elif r.get("converged"):
                claims += 1
                eu = rel(r["displacements"], direct["displacements"])
                et = rel(r["tensions"], direct["tensions"])
                if eu > 10 * tol or et > 10 * tol:
                    bad += 1
                    print("FALSE CLAIM", name, s, tol, opts, "u %.1e t %.1e" % (eu, et))
    print("runs", runs, "converged", claims, "errors", errors, "bad", bad)
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
