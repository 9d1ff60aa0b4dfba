//! METIS (vendored C sources, built by `metis-sys` with `cc`, no bindgen):
//! nested-dissection orderings (`METIS_NodeND`) and k-way graph partitions
//! (`METIS_PartGraphKway`).
//!
//! Graphs are given as symmetric adjacency lists in CSR form (`xadj`,
//! `adjncy`, 0-based, no self loops). METIS draws from a random generator
//! that GKlib keeps in *process-global* state, so two concurrent calls
//! would race and give run-dependent results: every call goes through one
//! lock and reseeds with [`SEED`], which makes the result a function of the
//! graph alone (subdomains are ordered in parallel). GKlib's error-handling
//! state (`gk_cur_jbufs`) and memory core are thread-local, but its random
//! state is not: `metis-sys` builds without `USE_GKRAND`, so `gk_randinit`
//! is libc's `srand` and every draw is libc's `rand` (one state per
//! process); with `USE_GKRAND` it would be a `static` Mersenne twister,
//! equally shared. The lock stays; waiting on it cost 0.08 s summed over the
//! 32 METIS calls of a 16-subdomain set-up of the 30³ tower (2 threads).

use metis_sys as ms;
use std::sync::Mutex;

/// Seed of METIS's random generator (fixed: results are deterministic).
pub const SEED: i32 = 1;

static METIS_LOCK: Mutex<()> = Mutex::new(());

/// Symmetric graph in CSR form without self loops.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Graph {
    pub xadj: Vec<usize>,
    pub adjncy: Vec<usize>,
}

impl Graph {
    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.xadj.len().saturating_sub(1)
    }

    /// True when the graph has no vertex.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Adjacency graph of a symmetric matrix given by its lower (or upper)
    /// triangle's pattern, with the vertices renumbered by `rank` (`rank[i]`
    /// is the new number of row `i`; `None`: as numbered). Diagonal entries
    /// are dropped, duplicates merged.
    pub fn from_symmetric_pattern(n: usize, col_ptr: &[usize], row_idx: &[usize], rank: Option<&[usize]>) -> Graph {
        let map = |i: usize| rank.map_or(i, |r| r[i]);
        let mut deg = vec![0usize; n + 1];
        for j in 0..n {
            for &i in &row_idx[col_ptr[j]..col_ptr[j + 1]] {
                if i != j {
                    deg[map(i) + 1] += 1;
                    deg[map(j) + 1] += 1;
                }
            }
        }
        for v in 0..n {
            deg[v + 1] += deg[v];
        }
        let mut next = deg.clone();
        let mut adj = vec![0usize; deg[n]];
        for j in 0..n {
            for &i in &row_idx[col_ptr[j]..col_ptr[j + 1]] {
                if i != j {
                    let (a, b) = (map(i), map(j));
                    adj[next[a]] = b;
                    next[a] += 1;
                    adj[next[b]] = a;
                    next[b] += 1;
                }
            }
        }
        Graph::compress(n, &deg, &mut adj)
    }

    /// Sorts each list and drops duplicates.
    fn compress(n: usize, ptr: &[usize], adj: &mut [usize]) -> Graph {
        let mut xadj = Vec::with_capacity(n + 1);
        let mut adjncy = Vec::with_capacity(adj.len());
        xadj.push(0);
        for v in 0..n {
            let list = &mut adj[ptr[v]..ptr[v + 1]];
            list.sort_unstable();
            let start = adjncy.len();
            for &w in list.iter() {
                if adjncy.len() == start || *adjncy.last().expect("non-empty") != w {
                    adjncy.push(w);
                }
            }
            xadj.push(adjncy.len());
        }
        Graph { xadj, adjncy }
    }

    /// Graph with an edge per pair `(a, b)`, `a != b` (duplicates merged).
    pub fn from_edges(n: usize, edges: impl Iterator<Item = (usize, usize)> + Clone) -> Graph {
        let mut deg = vec![0usize; n + 1];
        for (a, b) in edges.clone() {
            if a != b {
                deg[a + 1] += 1;
                deg[b + 1] += 1;
            }
        }
        for v in 0..n {
            deg[v + 1] += deg[v];
        }
        let mut next = deg.clone();
        let mut adj = vec![0usize; deg[n]];
        for (a, b) in edges {
            if a != b {
                adj[next[a]] = b;
                next[a] += 1;
                adj[next[b]] = a;
                next[b] += 1;
            }
        }
        Graph::compress(n, &deg, &mut adj)
    }

    fn idx_arrays(&self) -> Result<(Vec<ms::idx_t>, Vec<ms::idx_t>), String> {
        let conv = |v: usize| ms::idx_t::try_from(v).map_err(|_| format!("graph too large for METIS ({v} > 2^31)"));
        let xadj = self.xadj.iter().map(|&v| conv(v)).collect::<Result<Vec<_>, _>>()?;
        let adjncy = self.adjncy.iter().map(|&v| conv(v)).collect::<Result<Vec<_>, _>>()?;
        Ok((xadj, adjncy))
    }
}

fn default_options() -> [ms::idx_t; ms::METIS_NOPTIONS as usize] {
    let mut options = [0 as ms::idx_t; ms::METIS_NOPTIONS as usize];
    // SAFETY: METIS writes METIS_NOPTIONS entries into the array.
    unsafe {
        ms::METIS_SetDefaultOptions(options.as_mut_ptr());
    }
    options[ms::moptions_et_METIS_OPTION_SEED as usize] = SEED;
    options[ms::moptions_et_METIS_OPTION_NUMBERING as usize] = 0;
    options
}

fn status(what: &str, code: std::os::raw::c_int) -> Result<(), String> {
    match code {
        ms::rstatus_et_METIS_OK => Ok(()),
        ms::rstatus_et_METIS_ERROR_INPUT => Err(format!("{what}: METIS rejected the input")),
        ms::rstatus_et_METIS_ERROR_MEMORY => Err(format!("{what}: METIS ran out of memory")),
        c => Err(format!("{what}: METIS failed (status {c})")),
    }
}

/// Groups of vertices with the same closed neighbourhood (`adj(v) ∪ {v}`),
/// as the dofs of one truss node are: they are eliminated together by any
/// sensible order, so nested dissection works on the quotient graph with the
/// group sizes as vertex weights. Returns the group of each vertex and the
/// groups' members (in increasing vertex order, groups numbered by their
/// first member).
fn supervariables(graph: &Graph) -> (Vec<usize>, Vec<usize>, Vec<usize>) {
    let n = graph.len();
    let adj = |v: usize| &graph.adjncy[graph.xadj[v]..graph.xadj[v + 1]];
    // Same closed neighbourhood ⇒ same degree and same key (sum of the
    // closed list); candidates are compared exactly.
    let key: Vec<(usize, usize)> = (0..n)
        .map(|v| (adj(v).len(), adj(v).iter().sum::<usize>() + v))
        .collect();
    let mut by_key: Vec<usize> = (0..n).collect();
    by_key.sort_unstable_by_key(|&v| (key[v], v));
    let same = |a: usize, b: usize| {
        // closed lists equal ⇔ a ∈ adj(b) and adj(a) \ {b} == adj(b) \ {a}
        let (la, lb) = (adj(a), adj(b));
        if la.binary_search(&b).is_err() {
            return false;
        }
        la.iter().filter(|&&w| w != b).eq(lb.iter().filter(|&&w| w != a))
    };
    let mut rep = vec![usize::MAX; n];
    let mut i = 0;
    while i < n {
        let mut j = i;
        while j < n && key[by_key[j]] == key[by_key[i]] {
            j += 1;
        }
        // by_key[i..j] share the key; group them (first member = rep).
        for a in i..j {
            let va = by_key[a];
            if rep[va] != usize::MAX {
                continue;
            }
            rep[va] = va;
            for &vb in &by_key[a + 1..j] {
                if rep[vb] == usize::MAX && same(va, vb) {
                    rep[vb] = va;
                }
            }
        }
        i = j;
    }
    let mut group = vec![usize::MAX; n];
    let mut count = 0;
    for v in 0..n {
        if rep[v] == v {
            group[v] = count;
            count += 1;
        }
    }
    for v in 0..n {
        group[v] = group[rep[v]];
    }
    let mut start = vec![0usize; count + 1];
    for v in 0..n {
        start[group[v] + 1] += 1;
    }
    for g in 0..count {
        start[g + 1] += start[g];
    }
    let mut members = vec![0usize; n];
    let mut next = start.clone();
    for v in 0..n {
        members[next[group[v]]] = v;
        next[group[v]] += 1;
    }
    (group, start, members)
}

/// Nested-dissection fill-reducing order of `graph`: entry `k` is the vertex
/// eliminated at step `k`. Vertices with the same closed neighbourhood (the
/// dofs of one node) are merged first, and METIS orders the quotient graph:
/// it would merge them itself (`METIS_OPTION_COMPRESS`), but only after
/// taking in the dof graph, with k× the vertices and k²× the edges of the
/// node graph (k dofs per node): METIS's time falls by 15–35 % on the 30³
/// tower's subdomains and the 130² grid's (BENCHMARKS.md), at the same fill.
pub fn nested_dissection(graph: &Graph) -> Result<Vec<usize>, String> {
    let n = graph.len();
    if n == 0 {
        return Ok(Vec::new());
    }
    let (group, start, members) = supervariables(graph);
    let m = start.len() - 1;
    let quotient = {
        let mut mark = vec![usize::MAX; m];
        let mut xadj = Vec::with_capacity(m + 1);
        let mut adjncy = Vec::new();
        xadj.push(0);
        for g in 0..m {
            mark[g] = g;
            let first = members[start[g]];
            for &w in &graph.adjncy[graph.xadj[first]..graph.xadj[first + 1]] {
                let h = group[w];
                if mark[h] != g {
                    mark[h] = g;
                    adjncy.push(h);
                }
            }
            xadj.push(adjncy.len());
        }
        Graph { xadj, adjncy }
    };
    let (mut xadj, mut adjncy) = quotient.idx_arrays()?;
    let mut vwgt: Vec<ms::idx_t> = (0..m).map(|g| (start[g + 1] - start[g]) as ms::idx_t).collect();
    let mut nv = m as ms::idx_t;
    let mut options = default_options();
    // Already merged: METIS's own pass would find nothing more.
    options[ms::moptions_et_METIS_OPTION_COMPRESS as usize] = 0;
    let mut perm = vec![0 as ms::idx_t; m];
    let mut iperm = vec![0 as ms::idx_t; m];
    let code = {
        let _guard = METIS_LOCK.lock().unwrap_or_else(|e| e.into_inner());
        // SAFETY: the arrays have the sizes METIS_NodeND documents (m + 1,
        // xadj[m], m, m, m) and outlive the call; METIS keeps no pointer.
        unsafe {
            ms::METIS_NodeND(
                &mut nv,
                xadj.as_mut_ptr(),
                adjncy.as_mut_ptr(),
                vwgt.as_mut_ptr(),
                options.as_mut_ptr(),
                perm.as_mut_ptr(),
                iperm.as_mut_ptr(),
            )
        }
    };
    status("nested dissection", code)?;
    let mut fwd = Vec::with_capacity(n);
    for &g in &perm {
        let g = g as usize;
        if g >= m {
            return Err("nested dissection: METIS returned no permutation".into());
        }
        fwd.extend_from_slice(&members[start[g]..start[g + 1]]);
    }
    check_permutation(&fwd)?;
    Ok(fwd)
}

/// K-way partition of `graph` into `n_parts` parts (vertex weights
/// `vwgt`, or 1), minimising the edge cut. Part of each vertex.
pub fn kway(graph: &Graph, vwgt: Option<&[usize]>, n_parts: usize) -> Result<Vec<usize>, String> {
    let n = graph.len();
    if n_parts <= 1 || n == 0 {
        return Ok(vec![0; n]);
    }
    let (mut xadj, mut adjncy) = graph.idx_arrays()?;
    let mut w: Vec<ms::idx_t> = match vwgt {
        Some(w) if w.len() == n => w.iter().map(|&v| v.min(1 << 30) as ms::idx_t).collect(),
        Some(w) => return Err(format!("{} vertex weights for {n} vertices", w.len())),
        None => Vec::new(),
    };
    let wptr = if w.is_empty() {
        std::ptr::null_mut()
    } else {
        w.as_mut_ptr()
    };
    let mut nv = n as ms::idx_t;
    let mut ncon: ms::idx_t = 1;
    let mut np = ms::idx_t::try_from(n_parts).map_err(|_| "too many parts".to_string())?;
    let mut options = default_options();
    let mut objval: ms::idx_t = 0;
    let mut part = vec![0 as ms::idx_t; n];
    let code = {
        let _guard = METIS_LOCK.lock().unwrap_or_else(|e| e.into_inner());
        // SAFETY: sizes as METIS_PartGraphKway documents; null for the
        // optional arrays it accepts as absent.
        unsafe {
            ms::METIS_PartGraphKway(
                &mut nv,
                &mut ncon,
                xadj.as_mut_ptr(),
                adjncy.as_mut_ptr(),
                wptr,
                std::ptr::null_mut(),
                std::ptr::null_mut(),
                &mut np,
                std::ptr::null_mut(),
                std::ptr::null_mut(),
                options.as_mut_ptr(),
                &mut objval,
                part.as_mut_ptr(),
            )
        }
    };
    status("k-way partition", code)?;
    let out: Vec<usize> = part.iter().map(|&p| p as usize).collect();
    if let Some(&p) = out.iter().find(|&&p| p >= n_parts) {
        return Err(format!("k-way partition: part {p} out of range"));
    }
    Ok(out)
}

fn check_permutation(p: &[usize]) -> Result<(), String> {
    let mut seen = vec![false; p.len()];
    for &i in p {
        if i >= p.len() || seen[i] {
            return Err("nested dissection: METIS returned no permutation".into());
        }
        seen[i] = true;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(m: usize) -> Graph {
        let id = |i: usize, j: usize| i * m + j;
        let mut e = Vec::new();
        for i in 0..m {
            for j in 0..m {
                if i + 1 < m {
                    e.push((id(i, j), id(i + 1, j)));
                }
                if j + 1 < m {
                    e.push((id(i, j), id(i, j + 1)));
                }
            }
        }
        Graph::from_edges(m * m, e.into_iter())
    }

    #[test]
    fn nd_is_a_deterministic_permutation() {
        let g = grid(30);
        let a = nested_dissection(&g).unwrap();
        let b = nested_dissection(&g).unwrap();
        assert_eq!(a, b);
        check_permutation(&a).unwrap();
    }

    /// Each vertex of `g` becomes `k` vertices coupled to each other and to
    /// all copies of its neighbours, as the `k` dofs of a truss node.
    fn blown_up(g: &Graph, k: usize) -> Graph {
        let mut e = Vec::new();
        for v in 0..g.len() {
            for a in 0..k {
                for b in 0..a {
                    e.push((v * k + a, v * k + b));
                }
                for &w in &g.adjncy[g.xadj[v]..g.xadj[v + 1]] {
                    for b in 0..k {
                        e.push((v * k + a, w * k + b));
                    }
                }
            }
        }
        Graph::from_edges(g.len() * k, e.into_iter())
    }

    #[test]
    fn the_dofs_of_a_node_are_merged_and_ordered_together() {
        let g = grid(12);
        let (group, start, members) = supervariables(&g);
        assert_eq!(start.len() - 1, g.len(), "a grid graph has no two vertices alike");
        assert!(group.iter().enumerate().all(|(v, &gv)| gv == v) && members == (0..g.len()).collect::<Vec<_>>());
        let g3 = blown_up(&g, 3);
        let (group, start, _) = supervariables(&g3);
        assert_eq!(start.len() - 1, g.len());
        assert!((0..g3.len()).all(|v| group[v] == group[v - v % 3]));
        // The order keeps each node's dofs together, and fills as the
        // node graph's own order would.
        let fwd = nested_dissection(&g3).unwrap();
        check_permutation(&fwd).unwrap();
        for c in fwd.chunks(3) {
            assert!(c.iter().all(|&v| v / 3 == c[0] / 3), "{c:?}");
        }
        let node_order: Vec<usize> = fwd.chunks(3).map(|c| c[0] / 3).collect();
        assert_eq!(node_order, nested_dissection(&g).unwrap());
    }

    #[test]
    fn kway_is_deterministic_and_balanced() {
        let g = grid(40);
        let a = kway(&g, None, 8).unwrap();
        // From several threads at once: the lock keeps it deterministic.
        let others: Vec<Vec<usize>> = std::thread::scope(|s| {
            let h: Vec<_> = (0..4).map(|_| s.spawn(|| kway(&g, None, 8).unwrap())).collect();
            h.into_iter().map(|h| h.join().unwrap()).collect()
        });
        for o in others {
            assert_eq!(o, a);
        }
        let mut count = [0usize; 8];
        for &p in &a {
            count[p] += 1;
        }
        assert!(count.iter().all(|&c| c > 150 && c < 250), "{count:?}");
    }
}
