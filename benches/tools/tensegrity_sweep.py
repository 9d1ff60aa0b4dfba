#!/usr/bin/env python3
"""The tensegrity sweep of BENCHMARKS.md ("Indefinite subdomains merged
into a neighbour"): 7 generated tensegrity grids x 3 loads, each solved by
`cg` and `multilevel` on 2/3/4/8 subdomains to 1e-6 and compared with the
direct solver. Prints one line per run (solved or not, the subdomains it
ended on, the largest displacement error relative to direct's largest
displacement), then per method the runs solved, those that kept every
subdomain asked for, and a histogram of the subdomains solved on.

    cargo build --release
    python3 benches/tools/tensegrity_sweep.py target/release/nsdd [work dir]

Python 3 standard library only; two runs at a time. Scenes and results go
to the work dir (default `target/tensegrity-sweep`).
"""
import collections
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

SHAPES = [(2, 2), (3, 3), (4, 4), (6, 6), (10, 10), (2, 6), (5, 3)]
LOADS = [0.1, 1.0, 3.0]
SUBDOMAINS = [2, 3, 4, 8]
METHODS = ["cg", "multilevel"]


def main():
    nsdd = sys.argv[1]
    work = sys.argv[2] if len(sys.argv) > 2 else "target/tensegrity-sweep"
    os.makedirs(work, exist_ok=True)
    cases = [(nx, ny, load) for nx, ny in SHAPES for load in LOADS]
    for nx, ny, load in cases:
        scene = f"{work}/t{nx}x{ny}_{load}.toml"
        subprocess.run([nsdd, "gen", "tensegrity", f"nx={nx}", f"ny={ny}", f"load={load}", "--out", scene],
                       check=True, capture_output=True)
        subprocess.run([nsdd, "solve", scene, "--method", "direct", "--out", f"{scene}.direct.json"],
                       check=True, capture_output=True)

    def run(job):
        (nx, ny, load), s, method = job
        scene = f"{work}/t{nx}x{ny}_{load}.toml"
        out = f"{scene}.{method}{s}.json"
        if os.path.exists(out):
            os.remove(out)
        r = subprocess.run([nsdd, "solve", scene, "--method", method, "--subdomains", str(s), "--tolerance", "1e-6",
                            "--max-iterations", "20000", "--out", out], capture_output=True, text=True)
        if r.returncode != 0 or "converged   yes" not in r.stdout:
            return job, False, None, None
        res = json.load(open(out))
        direct = json.load(open(f"{scene}.direct.json"))
        ua = [x for q in res["displacements"] for x in q]
        ub = [x for q in direct["displacements"] for x in q]
        err = max(abs(a - b) for a, b in zip(ua, ub)) / max(abs(b) for b in ub)
        return job, True, res["subdomains"], err

    jobs = [(c, s, m) for c in cases for s in SUBDOMAINS for m in METHODS]
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(run, jobs))
    for ((nx, ny, load), s, m), ok, on, err in results:
        print(f"{nx}x{ny} load {load} {m} on {s}: " + (f"solved on {on}, error {err:.1e}" if ok else "not solved"))
    for m in METHODS:
        rows = [(s, ok, on, err) for (c, s, mm), ok, on, err in results if mm == m]
        solved = [r for r in rows if r[1]]
        kept = sum(1 for s, _, on, _ in solved if on == s)
        worst = max((r[3] for r in solved), default=float("nan"))
        print(f"{m}: solved {len(solved)} of {len(rows)}, kept every subdomain {kept}, largest error {worst:.1e}")
        for s in SUBDOMAINS:
            hist = collections.Counter(on for ss, ok, on, _ in rows if ss == s and ok)
            failed = sum(1 for ss, ok, _, _ in rows if ss == s and not ok)
            print(f"  asked {s}: ended on " + ", ".join(f"{k}: {v}" for k, v in sorted(hist.items()))
                  + (f"; not solved {failed}" if failed else ""))


if __name__ == "__main__":
    main()
