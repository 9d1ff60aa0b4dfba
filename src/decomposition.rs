//! Subdomains and pairwise interfaces of an element-oriented partition
//! (docs/design.md §2).
//!
//! A free dof used by elements of several subdomains is an interface dof.
//! Each *pair* `(E, E')` sharing dofs is an [`Interface`]; a dof shared by
//! `m` subdomains (a cross point) appears in `m(m−1)/2` interfaces, with one
//! force unknown per pair and dof (redundant multipliers). The global
//! interface vector stores interfaces one after the other; entry `j` belongs
//! to the pair `(lo, hi)` with `lo < hi`; within an interface, the dofs
//! only these two share come first, then its cross-point dofs, each group
//! in increasing global order. `B_E` is never formed: it is the sign (+ for
//! `lo`, − for `hi`) and the local dof of each entry.
//!
//! Local numbering: each subdomain numbers its interior dofs first (in
//! increasing global order), then its interface dofs interface by interface,
//! in the order of the global interface vector. An interface's own dofs
//! then map to one contiguous block of local dofs on both sides, and so do
//! its cross-point dofs unless an earlier interface numbered them: the
//! gather/scatter kernels run over long unit-stride runs. Factorizations
//! do not see this layout: they are ordered in the increasing-global
//! reference numbering ([`SubdomainDofs::reference_rank`],
//! `factor::EliminationOrder`).

use crate::factor::group_by_key;
use crate::model::{Model, FIXED};
use crate::partition::Partition;
use rayon::prelude::*;

/// One subdomain's dofs and interface connectivity.
#[derive(Debug, Clone)]
pub struct SubdomainDofs {
    /// Elements of this subdomain.
    pub elements: Vec<usize>,
    /// Global free dof of each local dof: interior dofs first, then
    /// interface dofs grouped by interface (see the module docs).
    pub dofs: Vec<usize>,
    /// Local dofs in increasing global order.
    pub by_global: Vec<u32>,
    /// For each local dof, the number of subdomains sharing it (≥ 1).
    pub multiplicity: Vec<u32>,
    /// Interfaces this subdomain belongs to (indices into `interfaces`).
    pub interfaces: Vec<usize>,
}

impl SubdomainDofs {
    /// Whether the subdomain can translate along some axis without
    /// straining any of its elements: no node of it is blocked in that
    /// component. `K_E` then maps the translation to zero exactly, so the
    /// subdomain is singular (floating) whatever its stiffness.
    pub fn translates_freely(&self, model: &Model) -> bool {
        (0..3).any(|c| {
            self.elements.iter().all(|&e| {
                let el = &model.elements[e];
                model.node_dofs[el.a][c] != FIXED && model.node_dofs[el.b][c] != FIXED
            })
        })
    }

    /// Local index of global free dof `dof` (binary search).
    pub fn local(&self, dof: usize) -> Option<usize> {
        self.by_global
            .binary_search_by_key(&dof, |&l| self.dofs[l as usize])
            .ok()
            .map(|k| self.by_global[k] as usize)
    }

    /// Runs `f` with this subdomain's numbering as a table over the global
    /// dofs `0..n_global`: [`Self::local`] without its binary search, for
    /// loops over every element's dofs (assembly, element loads and
    /// elongations), where the searches were 3 % of a nonsmooth run's
    /// samples (130² grid, 16 subdomains). The table is a scratch kept per
    /// thread (4 bytes per global dof) and cleared on the way out, so the
    /// subdomains of a set-up share one per thread.
    pub fn with_numbering<R>(&self, n_global: usize, f: impl FnOnce(LocalNumbering<'_>) -> R) -> R {
        let fill = |table: &mut [u32]| {
            for (l, &d) in self.dofs.iter().enumerate() {
                table[d] = l as u32;
            }
        };
        NUMBERING.with(|cell| match cell.try_borrow_mut() {
            Ok(table) => {
                // Cleared by `drop`, also when `f` unwinds.
                let mut guard = Numbered {
                    table,
                    dofs: &self.dofs,
                };
                if guard.table.len() < n_global {
                    guard.table.resize(n_global, NOT_HERE);
                }
                fill(&mut guard.table);
                f(LocalNumbering {
                    table: &guard.table[..n_global],
                })
            }
            // Only if `f` itself asked for a table on this thread.
            Err(_) => {
                let mut table = vec![NOT_HERE; n_global];
                fill(&mut table);
                f(LocalNumbering { table: &table })
            }
        })
    }

    /// Position of each local dof in increasing global order: the reference
    /// numbering the subdomain's factorization is ordered in.
    pub fn reference_rank(&self) -> Vec<usize> {
        let mut rank = vec![0; self.dofs.len()];
        for (k, &l) in self.by_global.iter().enumerate() {
            rank[l as usize] = k;
        }
        rank
    }
}

/// Marks a global dof outside the subdomain in [`LocalNumbering`].
const NOT_HERE: u32 = u32::MAX;

thread_local! {
    /// The scratch of [`SubdomainDofs::with_numbering`]: [`NOT_HERE`]
    /// everywhere between uses.
    static NUMBERING: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// The scratch table of [`SubdomainDofs::with_numbering`] while in use;
/// dropping it restores the subdomain's entries to [`NOT_HERE`].
struct Numbered<'a> {
    table: std::cell::RefMut<'a, Vec<u32>>,
    dofs: &'a [usize],
}

impl Drop for Numbered<'_> {
    fn drop(&mut self) {
        for &d in self.dofs {
            self.table[d] = NOT_HERE;
        }
    }
}

/// One subdomain's global → local dof table
/// ([`SubdomainDofs::with_numbering`]).
#[derive(Clone, Copy)]
pub struct LocalNumbering<'a> {
    table: &'a [u32],
}

impl LocalNumbering<'_> {
    /// Local index of global free dof `dof`, as [`SubdomainDofs::local`].
    #[inline]
    pub fn get(&self, dof: usize) -> Option<usize> {
        match self.table.get(dof) {
            Some(&l) if l != NOT_HERE => Some(l as usize),
            _ => None,
        }
    }
}

/// The interface between subdomains `lo < hi`.
#[derive(Debug, Clone)]
pub struct Interface {
    pub lo: usize,
    pub hi: usize,
    /// Its entries in the global interface vector: `start..end`.
    pub start: usize,
    pub end: usize,
}

impl Interface {
    /// Number of entries (pair-dofs).
    pub fn len(&self) -> usize {
        self.end - self.start
    }
    /// True for an interface without entries (never built).
    pub fn is_empty(&self) -> bool {
        self.end == self.start
    }
}

/// The decomposition: subdomains, interfaces, and per-entry gather maps.
#[derive(Debug, Clone)]
pub struct Decomposition {
    pub partition: Partition,
    pub subdomains: Vec<SubdomainDofs>,
    pub interfaces: Vec<Interface>,
    /// Global free dof of each interface entry.
    pub entry_dof: Vec<usize>,
    /// Local dof of each entry in its `lo` subdomain.
    pub entry_lo_local: Vec<u32>,
    /// Local dof of each entry in its `hi` subdomain.
    pub entry_hi_local: Vec<u32>,
    /// The merges that made this decomposition from the partition first
    /// asked for, in order ([`Decomposition::merge`]).
    pub merged: Vec<Merge>,
}

/// One subdomain merged into a neighbour by [`Decomposition::merge`]; the
/// ids are those of the decomposition the merge was made on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Merge {
    pub subdomain: usize,
    pub into: usize,
}

/// Interface quality figures (the `nsdd partition` report).
#[derive(Debug, Clone, serde::Serialize)]
pub struct QualityReport {
    pub subdomains: usize,
    pub elements_per_subdomain: Vec<usize>,
    pub dofs_per_subdomain: Vec<usize>,
    /// Distinct global dofs on any interface.
    pub interface_dofs: usize,
    /// Pair-dof entries of the global interface vector (with redundancy).
    pub interface_entries: usize,
    pub interfaces: usize,
    /// Nodes shared by three or more subdomains.
    pub cross_points: usize,
    /// Largest number of subdomains sharing one node.
    pub max_node_multiplicity: usize,
    pub element_imbalance: f64,
}

impl Decomposition {
    /// Builds subdomain dof sets and pairwise interfaces of a truss model.
    pub fn new(model: &Model, partition: Partition) -> Decomposition {
        // Per subdomain, in parallel (each set is its own): the nonsmooth
        // cg builds a decomposition at every active-set step.
        let dof_sets = partition
            .elements_of
            .par_iter()
            .map(|elems| {
                let mut dofs: Vec<usize> = Vec::with_capacity(6 * elems.len());
                dofs.extend(
                    elems
                        .iter()
                        .flat_map(|&e| model.element_dofs(e))
                        .filter(|&d| d != FIXED),
                );
                dofs.sort_unstable();
                dofs.dedup();
                dofs
            })
            .collect();
        Self::from_dof_sets(partition, dof_sets, model.n_free)
    }

    /// Builds the interfaces from each subdomain's sorted global dof ids
    /// (the algebraic entry point: dofs with equal ids are glued). The
    /// subdomains' local numbering is then the module's layout, not the
    /// input order: map through `SubdomainDofs::dofs` / `by_global`.
    pub fn from_dof_sets(partition: Partition, dof_sets: Vec<Vec<usize>>, n_global: usize) -> Decomposition {
        let n_parts = dof_sets.len();
        // Subdomains touching each free dof, sorted and unique (by rows:
        // dof `d`'s at `touch[touch_ptr[d]..touch_ptr[d + 1]]`).
        let (touch_ptr, touch) = group_by_key(n_global, || {
            dof_sets
                .iter()
                .enumerate()
                .flat_map(|(s, dofs)| dofs.iter().map(move |&d| (d, s as u32)))
        });
        let touch_of = |d: usize| touch_ptr[d]..touch_ptr[d + 1];
        let mut subdomains = Vec::with_capacity(n_parts);
        for (s, dofs) in dof_sets.into_iter().enumerate() {
            subdomains.push(SubdomainDofs {
                elements: partition.elements_of.get(s).cloned().unwrap_or_default(),
                by_global: (0..dofs.len() as u32).collect(),
                dofs,
                multiplicity: Vec::new(),
                interfaces: Vec::new(),
            });
        }
        for sd in subdomains.iter_mut() {
            sd.multiplicity = sd.dofs.iter().map(|&d| touch_of(d).len() as u32).collect();
        }
        // Pair-dof entries, grouped by pair, then the pair's own dofs before
        // its cross-point dofs (shared by more subdomains), then by dof:
        // the own dofs then form one contiguous run on both sides (see
        // `interface_layout`). Sorting makes the layout independent of
        // hashing and thread count.
        let mut pairs: Vec<(u32, u32, bool, usize)> = Vec::new();
        for d in 0..n_global {
            let t = &touch[touch_of(d)];
            for i in 0..t.len() {
                for j in i + 1..t.len() {
                    pairs.push((t[i], t[j], t.len() > 2, d));
                }
            }
        }
        pairs.sort_unstable();
        let mut interfaces = Vec::new();
        let mut entry_dof = Vec::with_capacity(pairs.len());
        let mut entry_lo_local = Vec::with_capacity(pairs.len());
        let mut entry_hi_local = Vec::with_capacity(pairs.len());
        let mut k = 0;
        while k < pairs.len() {
            let (lo, hi) = (pairs[k].0 as usize, pairs[k].1 as usize);
            let start = k;
            while k < pairs.len() && pairs[k].0 as usize == lo && pairs[k].1 as usize == hi {
                let d = pairs[k].3;
                entry_dof.push(d);
                entry_lo_local.push(subdomains[lo].local(d).expect("dof of lo") as u32);
                entry_hi_local.push(subdomains[hi].local(d).expect("dof of hi") as u32);
                k += 1;
            }
            let id = interfaces.len();
            subdomains[lo].interfaces.push(id);
            subdomains[hi].interfaces.push(id);
            interfaces.push(Interface { lo, hi, start, end: k });
        }
        for (s, sd) in subdomains.iter_mut().enumerate() {
            let new_of = interface_layout(s, sd, &interfaces, &entry_lo_local, &entry_hi_local);
            for it in &sd.interfaces {
                let it = &interfaces[*it];
                let side = if it.lo == s {
                    &mut entry_lo_local
                } else {
                    &mut entry_hi_local
                };
                for l in &mut side[it.start..it.end] {
                    *l = new_of[*l as usize];
                }
            }
            let mut dofs = vec![0; sd.dofs.len()];
            let mut multiplicity = vec![0; sd.dofs.len()];
            for (old, &new) in new_of.iter().enumerate() {
                dofs[new as usize] = sd.dofs[old];
                multiplicity[new as usize] = sd.multiplicity[old];
            }
            sd.dofs = dofs;
            sd.multiplicity = multiplicity;
            sd.by_global = new_of;
        }
        Decomposition {
            partition,
            subdomains,
            interfaces,
            entry_dof,
            entry_lo_local,
            entry_hi_local,
            merged: Vec::new(),
        }
    }

    /// The neighbour subdomain `s` would be merged into: of those holding
    /// elements at node `near` (where a set-up met trouble), the one with
    /// the most there; else, or without `near`, the one `s` shares the
    /// most interface entries with (the lower id on a tie). `None` when `s`
    /// has no neighbour.
    pub fn merge_target(&self, model: &Model, s: usize, near: Option<usize>) -> Option<usize> {
        let neighbours: Vec<(usize, usize)> = self
            .interfaces
            .iter()
            .filter_map(|it| match (it.lo == s, it.hi == s) {
                (true, _) => Some((it.hi, it.len())),
                (_, true) => Some((it.lo, it.len())),
                _ => None,
            })
            .collect();
        let mut at_node = vec![0usize; self.len()];
        if let Some(n) = near {
            for (e, el) in model.elements.iter().enumerate() {
                if el.a == n || el.b == n {
                    at_node[self.partition.part_of[e]] += 1;
                }
            }
        }
        // Most elements at the node first, then the largest interface.
        neighbours
            .iter()
            .max_by(|a, b| (at_node[a.0], a.1).cmp(&(at_node[b.0], b.1)).then(b.0.cmp(&a.0)))
            .map(|&(t, _)| t)
    }

    /// The decomposition with each `Merge { subdomain, into }` of `merges`
    /// (ids of this decomposition) applied at once: subdomains joined by
    /// merges, directly or through others, become one, numbered in the
    /// order of their lowest ids; the others keep their elements. No
    /// weak-node repair follows: a merge only adds elements around the
    /// nodes it touches. The merges that joined two subdomains not yet
    /// joined are recorded after this one's (one per subdomain taken away).
    ///
    /// A set-up meets a subdomain that is indefinite where the structure
    /// is not (compressed struts cut off from the cables that stabilise
    /// them) and retries on the merged decomposition: the union holds
    /// those cables, and a single subdomain is the whole structure.
    pub fn merge_all(&self, model: &Model, merges: &[Merge]) -> Decomposition {
        let n = self.len();
        let mut root: Vec<usize> = (0..n).collect();
        // Only the merges that join two subdomains not yet joined are
        // recorded: each takes one subdomain away.
        let mut made = Vec::with_capacity(merges.len());
        for m in merges {
            let (a, b) = (
                crate::adaptive::find_root(&mut root, m.subdomain),
                crate::adaptive::find_root(&mut root, m.into),
            );
            if a != b {
                root[a.max(b)] = a.min(b);
                made.push(*m);
            }
        }
        // A component's root is its lowest id: number the roots in order.
        let mut new_id = vec![usize::MAX; n];
        let mut count = 0;
        for p in 0..n {
            if crate::adaptive::find_root(&mut root, p) == p {
                new_id[p] = count;
                count += 1;
            }
        }
        let part_of: Vec<usize> = self
            .partition
            .part_of
            .iter()
            .map(|&p| new_id[crate::adaptive::find_root(&mut root, p)])
            .collect();
        let partition = Partition::from_user(model, &part_of).expect("merged ids cover 0..count");
        let mut dec = Decomposition::new(model, partition);
        dec.merged = self.merged.clone();
        dec.merged.extend(made);
        dec
    }

    /// [`Decomposition::merge_all`] of subdomain `s` into its
    /// [`Decomposition::merge_target`]; `None` without a neighbour.
    pub fn merge(&self, model: &Model, s: usize, near: Option<usize>) -> Option<Decomposition> {
        let into = self.merge_target(model, s, near)?;
        Some(self.merge_all(model, &[Merge { subdomain: s, into }]))
    }

    /// Number of subdomains.
    pub fn len(&self) -> usize {
        self.subdomains.len()
    }

    /// True without subdomains (never for a built decomposition).
    pub fn is_empty(&self) -> bool {
        self.subdomains.is_empty()
    }

    /// Length of the global interface vector.
    pub fn n_entries(&self) -> usize {
        self.entry_dof.len()
    }

    /// Sizes of interfaces, cross points and balance.
    pub fn quality(&self, model: &Model) -> QualityReport {
        let elements_per_subdomain: Vec<usize> = self.subdomains.iter().map(|s| s.elements.len()).collect();
        let mut node_parts: Vec<Vec<usize>> = vec![Vec::new(); model.coords.len()];
        for (s, sd) in self.subdomains.iter().enumerate() {
            for &e in &sd.elements {
                for n in [model.elements[e].a, model.elements[e].b] {
                    if node_parts[n].last() != Some(&s) {
                        node_parts[n].push(s);
                    }
                }
            }
        }
        let cross_points = node_parts.iter().filter(|p| p.len() >= 3).count();
        let max_node_multiplicity = node_parts.iter().map(|p| p.len()).max().unwrap_or(0);
        let mut idofs = self.entry_dof.clone();
        idofs.sort_unstable();
        idofs.dedup();
        let max_e = *elements_per_subdomain.iter().max().unwrap_or(&0) as f64;
        let mean_e = elements_per_subdomain.iter().sum::<usize>() as f64 / self.len().max(1) as f64;
        QualityReport {
            subdomains: self.len(),
            dofs_per_subdomain: self.subdomains.iter().map(|s| s.dofs.len()).collect(),
            elements_per_subdomain,
            interface_dofs: idofs.len(),
            interface_entries: self.n_entries(),
            interfaces: self.interfaces.len(),
            cross_points,
            max_node_multiplicity,
            element_imbalance: if mean_e > 0.0 { max_e / mean_e } else { 1.0 },
        }
    }
}

/// New local number of each dof of `sd` (given in increasing global order):
/// interior dofs first, then each interface's dofs not numbered yet, in
/// entry order. `lo_local`/`hi_local` are still in the sorted numbering.
fn interface_layout(
    s: usize,
    sd: &SubdomainDofs,
    interfaces: &[Interface],
    lo_local: &[u32],
    hi_local: &[u32],
) -> Vec<u32> {
    const UNSET: u32 = u32::MAX;
    let mut new_of = vec![UNSET; sd.dofs.len()];
    let mut next = 0u32;
    for (l, &m) in sd.multiplicity.iter().enumerate() {
        if m == 1 {
            new_of[l] = next;
            next += 1;
        }
    }
    for &i in &sd.interfaces {
        let it = &interfaces[i];
        let side = if it.lo == s { lo_local } else { hi_local };
        for &l in &side[it.start..it.end] {
            if new_of[l as usize] == UNSET {
                new_of[l as usize] = next;
                next += 1;
            }
        }
    }
    // Every shared dof is on an interface; anything else keeps its order.
    for slot in new_of.iter_mut().filter(|v| **v == UNSET) {
        *slot = next;
        next += 1;
    }
    new_of
}
