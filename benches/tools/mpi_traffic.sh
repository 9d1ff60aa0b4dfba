#!/usr/bin/env bash
# Per-iteration time and traffic of the MPI backend against threads, on one
# scene, in one run (BENCHMARKS.md, "MPI backend"). From the project root
# after `cargo build --release --features mpi`:
#
#   benches/tools/mpi_traffic.sh [GRID_N] [SUBDOMAINS...]    # default 130, 16 64
#
# Prints, per subdomain count: iterations and solve seconds per iteration
# for 1 thread, 2 threads and 2 ranks x 1 thread (same bits as 1 thread),
# and each rank's trace messages/bytes and reductions/bytes (the result's
# "mpi:" note).
set -euo pipefail
N=${1:-130}
shift || true
SUBS=${*:-16 64}
BIN=${NSDD:-target/release/nsdd}
MPIRUN=${MPIRUN:-mpirun --allow-run-as-root --oversubscribe}
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
"$BIN" gen grid nx="$N" ny="$N" unilateral=false t0=0 --out "$TMP/g.toml" >/dev/null
per_it() { python3 -c "import json,sys; r=json.load(open(sys.argv[1])); print('%3d it  %.1f ms/it' % (r['iterations'], 1e3*r['timings_s']['solve']/r['iterations']))" "$1"; }
for n in $SUBS; do
    echo "== grid ${N}x${N}, cg, $n subdomains, tol 1e-8"
    for t in 1 2; do
        RAYON_NUM_THREADS=$t "$BIN" solve "$TMP/g.toml" --method cg --subdomains "$n" --tolerance 1e-8 --out "$TMP/t$t.json" >/dev/null
        echo "threads $t:           $(per_it "$TMP/t$t.json")"
    done
    $MPIRUN -np 2 -x RAYON_NUM_THREADS=1 "$BIN" solve "$TMP/g.toml" --method cg --subdomains "$n" --tolerance 1e-8 --out "$TMP/m.json" >/dev/null
    echo "2 ranks x 1 thread:  $(per_it "$TMP/m.json")"
    python3 -c "import json,sys; r=json.load(open(sys.argv[1])); print('\n'.join(n for n in r['notes'] if n.startswith('mpi:')))" "$TMP/m.json"
done
