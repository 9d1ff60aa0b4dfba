//! Element-oriented partition: every element belongs to exactly one
//! subdomain (docs/design.md §2). Recursive coordinate bisection on element
//! midpoints: balanced element counts, compact parts (hence small
//! interfaces), and deterministic (ties broken by element index).
//!
//! A geometric cut of a truss leaves *dangling* interface nodes: a node held
//! in a subdomain by one or two bars (or by bars in one plane) can move
//! freely there, so that subdomain's matrix gets a mechanism mode per such
//! node. Every mode is a kernel column, a coarse unknown and a dense
//! `n × 1` column in every iteration, and monolevel becomes impossible. The
//! bisection therefore ends with a repair pass that hands the elements of
//! such a weak node to the neighbouring subdomain that holds the node most
//! strongly (see [`Partition::repair_weak_nodes`]).

use crate::error::{Error, Result};
use crate::factor::group_by_key;
use crate::model::{Model, FIXED};

/// Free dofs per subdomain the automatic count aims at: subdomain
/// factorizations stay cheap and the interface small against the interior.
pub const AUTO_DOFS_PER_SUBDOMAIN: usize = 8000;

/// Fewest elements per subdomain the automatic count allows: below that
/// nearly every dof is on an interface (625 subdomains of one element each
/// took 54 s where 4 took 0.1 s, issue #20).
pub const AUTO_MIN_ELEMENTS_PER_SUBDOMAIN: usize = 16;

/// The subdomain count a domain-decomposition method runs with.
/// `requested > 0` is kept as it is; `0` means automatic:
/// `max(threads, ceil(free_dofs / 8000))`, at least 2 (one subdomain has no
/// interface and the DD methods would not decompose anything), at most
/// `elements / 16` and at least 1 (tiny scenes).
pub fn resolve_subdomains(requested: usize, free_dofs: usize, elements: usize, threads: usize) -> usize {
    if requested > 0 {
        return requested;
    }
    let wanted = threads.max(free_dofs.div_ceil(AUTO_DOFS_PER_SUBDOMAIN)).max(2);
    wanted.min(elements / AUTO_MIN_ELEMENTS_PER_SUBDOMAIN).max(1)
}

/// Which subdomain each element belongs to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Partition {
    /// Subdomain of each element.
    pub part_of: Vec<usize>,
    /// Elements of each subdomain, in increasing order.
    pub elements_of: Vec<Vec<usize>>,
}

impl Partition {
    /// Number of subdomains.
    pub fn len(&self) -> usize {
        self.elements_of.len()
    }

    /// True when there is no subdomain (never for a built partition).
    pub fn is_empty(&self) -> bool {
        self.elements_of.is_empty()
    }

    fn from_part_of(part_of: Vec<usize>, n_parts: usize) -> Partition {
        let mut elements_of = vec![Vec::new(); n_parts];
        for (e, &p) in part_of.iter().enumerate() {
            elements_of[p].push(e);
        }
        Partition { part_of, elements_of }
    }

    /// Recursive coordinate bisection into `n_parts` subdomains, followed by
    /// [`Partition::repair_weak_nodes`].
    pub fn bisection(model: &Model, n_parts: usize) -> Result<Partition> {
        let mut partition = Partition::coordinate_bisection(model, n_parts)?;
        partition.repair_weak_nodes(model);
        Ok(partition)
    }

    /// METIS k-way partition of the truss's node graph (nodes adjacent when
    /// an element joins them; a node weighs its element count, so parts get
    /// balanced element counts), each element then going to its end nodes'
    /// part (when they differ, all the elements cut between two parts go
    /// to the smaller of the two, so that the interface is one layer of
    /// nodes), followed by [`Partition::repair_weak_nodes`].
    /// Deterministic (METIS runs seeded, see `ordering`).
    pub fn metis(model: &Model, n_parts: usize) -> Result<Partition> {
        let mut partition = Partition::metis_kway(model, n_parts)?;
        partition.repair_weak_nodes(model);
        Ok(partition)
    }

    /// [`Partition::metis`] without the weak-node repair.
    pub fn metis_kway(model: &Model, n_parts: usize) -> Result<Partition> {
        let ne = model.elements.len();
        check_part_count(n_parts, ne)?;
        let nn = model.coords.len();
        let graph = crate::ordering::Graph::from_edges(nn, model.elements.iter().map(|el| (el.a, el.b)));
        let mut weight = vec![0usize; nn];
        for el in &model.elements {
            weight[el.a] += 1;
            weight[el.b] += 1;
        }
        let node_part = crate::ordering::kway(&graph, Some(&weight), n_parts)
            .map_err(|m| Error::Numerical(format!("METIS partition: {m}")))?;
        // The elements cut between two parts all go to the same one of
        // them, so the interface is one layer of nodes (the other part's
        // boundary); of the two, the part with fewer elements so far takes
        // them (pairs by decreasing cut size, ties by ids), for balance.
        let mut count = vec![0usize; n_parts];
        let mut pairs: std::collections::BTreeMap<(usize, usize), usize> = Default::default();
        for el in &model.elements {
            let (pa, pb) = (node_part[el.a], node_part[el.b]);
            if pa == pb {
                count[pa] += 1;
            } else {
                *pairs.entry((pa.min(pb), pa.max(pb))).or_insert(0) += 1;
            }
        }
        let mut order: Vec<((usize, usize), usize)> = pairs.into_iter().collect();
        order.sort_by_key(|&(pq, c)| (std::cmp::Reverse(c), pq));
        let mut taker: std::collections::BTreeMap<(usize, usize), usize> = Default::default();
        for ((p, q), c) in order {
            let t = if count[q] < count[p] { q } else { p };
            count[t] += c;
            taker.insert((p, q), t);
        }
        let part_of: Vec<usize> = model
            .elements
            .iter()
            .map(|el| {
                let (pa, pb) = (node_part[el.a], node_part[el.b]);
                if pa == pb {
                    pa
                } else {
                    taker[&(pa.min(pb), pa.max(pb))]
                }
            })
            .collect();
        let partition = Partition::from_part_of(part_of, n_parts);
        if let Some(empty) = partition.elements_of.iter().position(|e| e.is_empty()) {
            return Err(Error::input(
                "solver.partitioner",
                None,
                format!(
                    "METIS left subdomain {empty} of {n_parts} without elements: use fewer subdomains or \"bisection\""
                ),
            ));
        }
        Ok(partition)
    }

    /// The partition `partitioner` makes of `model` (with the weak-node
    /// repair).
    pub fn automatic(model: &Model, n_parts: usize, partitioner: crate::scene::Partitioner) -> Result<Partition> {
        match partitioner {
            crate::scene::Partitioner::Bisection => Partition::bisection(model, n_parts),
            crate::scene::Partitioner::Metis => Partition::metis(model, n_parts),
        }
    }

    /// Plain recursive coordinate bisection: element counts balanced to
    /// one, without the weak-node repair.
    pub fn coordinate_bisection(model: &Model, n_parts: usize) -> Result<Partition> {
        let ne = model.elements.len();
        check_part_count(n_parts, ne)?;
        let mid: Vec<[f64; 3]> = model
            .elements
            .iter()
            .map(|el| std::array::from_fn(|d| 0.5 * (model.coords[el.a][d] + model.coords[el.b][d])))
            .collect();
        let mut part_of = vec![0usize; ne];
        let mut ids: Vec<usize> = (0..ne).collect();
        bisect(&mid, &mut ids, 0, n_parts, &mut part_of);
        Ok(Partition::from_part_of(part_of, n_parts))
    }

    /// Removes local mechanisms at the cut. A subdomain holds a node
    /// *weakly* when its elements there do not span the node's free dofs
    /// (the node can move freely in that subdomain), or, where one of them
    /// is a strut (compressed, with geometric stiffness), when their block
    /// of the node's stiffness is not positive definite (the subdomain is
    /// then indefinite). For each weak holder,
    /// first try to *pull* elements at the node from other holders that stay
    /// strong without them (and that do not leave a weak node at the
    /// element's other end); if that cannot make it strong, *give* its
    /// elements at the node to the strongest holder. Repeats until nothing
    /// moves (at most [`REPAIR_PASSES`] passes; an element moves at most
    /// twice, so trading cannot cycle). Element counts stay within 1/2 and
    /// 3/2 of the average.
    /// Deterministic. Returns the number of element moves.
    pub fn repair_weak_nodes(&mut self, model: &Model) -> usize {
        let moved = repair(model, &mut self.part_of, self.elements_of.len());
        if moved > 0 {
            *self = Partition::from_part_of(std::mem::take(&mut self.part_of), self.elements_of.len());
        }
        moved
    }

    /// The user's partition from `elements.subdomain`. Ids must cover
    /// `0..N` with no empty subdomain.
    pub fn from_user(model: &Model, subdomain: &[usize]) -> Result<Partition> {
        let ne = model.elements.len();
        if subdomain.len() != ne {
            return Err(Error::input(
                "elements.subdomain",
                None,
                format!("has {} entries but the scene has {ne} elements", subdomain.len()),
            ));
        }
        // A subdomain needs at least one element, so ids are below the
        // element count (this also bounds the arrays sized from them).
        if let Some(i) = subdomain.iter().position(|&s| s >= ne) {
            return Err(Error::input(
                "elements.subdomain",
                Some(i),
                format!(
                    "subdomain id {} is not below the number of elements ({ne})",
                    subdomain[i]
                ),
            ));
        }
        let n_parts = subdomain.iter().max().map_or(0, |m| m + 1);
        let mut count = vec![0usize; n_parts];
        for &s in subdomain {
            count[s] += 1;
        }
        if let Some(empty) = count.iter().position(|&c| c == 0) {
            return Err(Error::input(
                "elements.subdomain",
                None,
                format!("subdomain ids must cover 0..{n_parts} but subdomain {empty} has no element"),
            ));
        }
        Ok(Partition::from_part_of(subdomain.to_vec(), n_parts))
    }
}

fn repair(model: &Model, part_of: &mut [usize], n_parts: usize) -> usize {
    let nn = model.coords.len();
    // Elements at each node, increasing (node `n`'s at
    // `inc[inc_ptr[n]..inc_ptr[n + 1]]`), and its free components: flat
    // arrays, since the nonsmooth cg repairs a partition at every
    // active-set step.
    let (inc_ptr, inc) = group_by_key(nn, || {
        model
            .elements
            .iter()
            .enumerate()
            .flat_map(|(e, el)| [(el.a, e), (el.b, e)])
    });
    let incident = |n: usize| &inc[inc_ptr[n]..inc_ptr[n + 1]];
    let free_of: Vec<([usize; 3], usize)> = (0..nn)
        .map(|n| {
            let mut f = ([0; 3], 0);
            for d in (0..3).filter(|&d| model.node_dofs[n][d] != FIXED) {
                f.0[f.1] = d;
                f.1 += 1;
            }
            f
        })
        .collect();
    let free = |n: usize| &free_of[n].0[..free_of[n].1];
    let star = |n: usize, q: usize, part_of: &[usize]| -> Vec<usize> {
        incident(n).iter().copied().filter(|&e| part_of[e] == q).collect()
    };
    // Strong (or absent) holder `q` at `n`, after `add`/`remove` of one element.
    let ok_after = |n: usize, q: usize, part_of: &[usize], add: Option<usize>, remove: Option<usize>| -> bool {
        let mut st = star(n, q, part_of);
        if let Some(r) = remove {
            st.retain(|&e| e != r);
        }
        if let Some(a) = add {
            st.push(a);
        }
        st.is_empty() || free(n).is_empty() || held(model, &st, free(n))
    };
    let mut count = vec![0usize; n_parts];
    for &p in part_of.iter() {
        count[p] += 1;
    }
    // Balance bounds: a repair never takes a subdomain outside
    // [1/2, 3/2] of the average element count (nor empties it).
    let avg = part_of.len() as f64 / n_parts as f64;
    let (lo, hi) = (((0.5 * avg).floor() as usize).max(1), (1.5 * avg).ceil() as usize);
    let mut moves = vec![0u8; model.elements.len()];
    let mut moved = 0;
    for _ in 0..REPAIR_PASSES {
        let mut changed = false;
        for n in 0..nn {
            // Most nodes lie inside one subdomain: nothing to look at.
            let at = incident(n);
            if free(n).is_empty() || at.iter().all(|&e| part_of[e] == part_of[at[0]]) {
                continue;
            }
            let mut parts: Vec<usize> = at.iter().map(|&e| part_of[e]).collect();
            parts.sort_unstable();
            parts.dedup();
            if parts.len() < 2 {
                continue;
            }
            for &p in &parts {
                if held(model, &star(n, p, part_of), free(n)) {
                    continue;
                }
                // Pull: elements of other holders at n whose removal keeps
                // them strong at both ends and that p holds strongly at
                // their other end.
                let mut pulled = Vec::new();
                for &e in incident(n) {
                    let q = part_of[e];
                    if q == p || moves[e] >= MAX_MOVES_PER_ELEMENT || count[q] <= lo || count[p] + pulled.len() >= hi {
                        continue;
                    }
                    let el = &model.elements[e];
                    let m = if el.a == n { el.b } else { el.a };
                    if ok_after(n, q, part_of, None, Some(e))
                        && ok_after(m, q, part_of, None, Some(e))
                        && ok_after(m, p, part_of, Some(e), None)
                    {
                        part_of[e] = p;
                        pulled.push((e, q));
                        if held(model, &star(n, p, part_of), free(n)) {
                            break;
                        }
                    }
                }
                if held(model, &star(n, p, part_of), free(n)) {
                    for &(e, q) in &pulled {
                        moves[e] += 1;
                        count[q] -= 1;
                        count[p] += 1;
                    }
                    moved += pulled.len();
                    changed |= !pulled.is_empty();
                    continue;
                }
                for &(e, q) in &pulled {
                    part_of[e] = q;
                }
                // Give: to the strong holder with most elements at n, or,
                // when none is strong, to the largest holder. Ties: lowest id.
                let strong: Vec<usize> = parts
                    .iter()
                    .copied()
                    .filter(|&q| q != p && held(model, &star(n, q, part_of), free(n)))
                    .collect();
                let pool = if strong.is_empty() {
                    parts.iter().copied().filter(|&q| q != p).collect()
                } else {
                    strong
                };
                let Some(target) = pool
                    .iter()
                    .copied()
                    .max_by_key(|&q| (star(n, q, part_of).len(), std::cmp::Reverse(q)))
                else {
                    continue;
                };
                let mine: Vec<usize> = star(n, p, part_of)
                    .into_iter()
                    .filter(|&e| moves[e] < MAX_MOVES_PER_ELEMENT)
                    .collect();
                if mine.is_empty() || count[p] < lo + mine.len() || count[target] + mine.len() > hi {
                    continue;
                }
                for &e in &mine {
                    part_of[e] = target;
                    moves[e] += 1;
                }
                count[p] -= mine.len();
                count[target] += mine.len();
                moved += mine.len();
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }
    moved
}

/// Passes of [`Partition::repair_weak_nodes`].
pub const REPAIR_PASSES: usize = 8;

/// Whether `elements` (all at one node) hold it in its `free` components:
/// their directions span them ([`spans`]) and, where one of them is a
/// compressed element with geometric stiffness (a strut, whose transverse
/// stiffness `t/L` is negative), the node's block of their stiffness is
/// positive definite: a subdomain holding a strut's end without the
/// cables that stabilise it there is indefinite, where the whole
/// structure is not.
fn held(model: &Model, elements: &[usize], free: &[usize]) -> bool {
    spans(model, elements, free)
        && (!elements.iter().any(|&e| model.elements[e].geo < 0.0) || definite(model, elements, free))
}

/// Whether the sum of the node blocks `k n nᵀ + g (I − n nᵀ)` of
/// `elements`, restricted to `free`, is positive definite (Cholesky pivots
/// above [`DEFINITE_NODE_RATIO`] of its trace).
fn definite(model: &Model, elements: &[usize], free: &[usize]) -> bool {
    let mut m = [[0.0f64; 3]; 3];
    for &e in elements {
        let b = model.elements[e].block();
        for (i, &a) in free.iter().enumerate() {
            for (j, &c) in free.iter().enumerate() {
                m[i][j] += b[a][c];
            }
        }
    }
    let d = free.len();
    let tr: f64 = (0..d).map(|i| m[i][i]).sum();
    let mut l = [[0.0f64; 3]; 3];
    for j in 0..d {
        let mut p = m[j][j];
        for k in 0..j {
            p -= l[j][k] * l[j][k];
        }
        if !(p > DEFINITE_NODE_RATIO * tr) {
            return false;
        }
        let p = p.sqrt();
        l[j][j] = p;
        for i in j + 1..d {
            let mut v = m[i][j];
            for k in 0..j {
                v -= l[i][k] * l[j][k];
            }
            l[i][j] = v / p;
        }
    }
    true
}

/// Pivot, relative to the trace, below which a node block with a strut
/// counts as not positive definite ([`definite`]).
const DEFINITE_NODE_RATIO: f64 = 1e-8;

/// Whether the directions of `elements` (all at one node) span the node's
/// `free` components: `Σ dir dirᵀ` restricted to them is regular.
fn spans(model: &Model, elements: &[usize], free: &[usize]) -> bool {
    let mut m = [[0.0f64; 3]; 3];
    for &e in elements {
        let d = model.elements[e].dir;
        for (i, &a) in free.iter().enumerate() {
            for (j, &b) in free.iter().enumerate() {
                m[i][j] += d[a] * d[b];
            }
        }
    }
    // Each dir is a unit vector, so the trace is at most the element count;
    // a determinant this small relative to it means a (near) zero eigenvalue.
    let tr: f64 = (0..free.len()).map(|i| m[i][i]).sum();
    let det = match free.len() {
        1 => m[0][0],
        2 => m[0][0] * m[1][1] - m[0][1] * m[1][0],
        _ => {
            m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
                + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
        }
    };
    det > WEAK_NODE_RATIO * tr.powi(free.len() as i32)
}

/// An element changes subdomain at most this often (guarantees the repair
/// terminates even where two weak holders would trade elements).
const MAX_MOVES_PER_ELEMENT: u8 = 2;

/// Relative determinant below which a node counts as weakly held.
const WEAK_NODE_RATIO: f64 = 1e-8;

/// Splits `ids` into `parts` parts numbered from `first`, along the axis of
/// largest extent, at the element count proportional to the part counts.
fn bisect(mid: &[[f64; 3]], ids: &mut [usize], first: usize, parts: usize, part_of: &mut [usize]) {
    if parts == 1 {
        for &e in ids.iter() {
            part_of[e] = first;
        }
        return;
    }
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for &e in ids.iter() {
        for d in 0..3 {
            lo[d] = lo[d].min(mid[e][d]);
            hi[d] = hi[d].max(mid[e][d]);
        }
    }
    let axis = (0..3).fold(0, |best, d| if hi[d] - lo[d] > hi[best] - lo[best] { d } else { best });
    let left_parts = parts / 2;
    let split = ids.len() * left_parts / parts;
    // Strict total order (coordinate, then index): deterministic.
    ids.select_nth_unstable_by(split, |&p, &q| mid[p][axis].total_cmp(&mid[q][axis]).then(p.cmp(&q)));
    let (left, right) = ids.split_at_mut(split);
    bisect(mid, left, first, left_parts, part_of);
    bisect(mid, right, first + left_parts, parts - left_parts, part_of);
}

/// A part count an automatic partition can make: at least one, at most one
/// element per part.
fn check_part_count(n_parts: usize, ne: usize) -> Result<()> {
    if n_parts == 0 {
        return Err(Error::input("solver.subdomains", None, "must be at least 1"));
    }
    if n_parts > ne {
        return Err(Error::input(
            "solver.subdomains",
            None,
            format!("{n_parts} subdomains asked for but the scene has only {ne} elements"),
        ));
    }
    Ok(())
}
