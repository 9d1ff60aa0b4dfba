//! The algebraic entry point, for codes that assemble their own matrices:
//! per-subdomain stiffness matrices in CSR, local-to-global dof maps, dof
//! points for the macro space, optional kernel bases and cable columns. An
//! [`AlgebraicProblem`] collects and checks them (each call checks its own
//! data, so an error names the subdomain and field at once);
//! [`AlgebraicProblem::build`] factors the subdomains and sets up an
//! [`AlgebraicSolver`], which then solves any number of right-hand sides.
//! The C ABI's algebraic level (`nsdd_alg_*`) is a thin mirror of it.
//!
//! A chain of 4 springs (stiffness 10, global dof `g` is node `g + 1`,
//! node 0 fixed) in two subdomains sharing global dof 1, pulled at its end:
//!
//! ```
//! use nsdd::algebraic::AlgebraicProblem;
//! use nsdd::settings::{Method, SolverSettings};
//!
//! let k = 10.0;
//! let mut problem = AlgebraicProblem::new(2, 4)?;
//! // Subdomain 0: springs 0-1 and 1-2, global dofs 0 and 1 (lower triangle).
//! problem.subdomain(0, &[0, 1, 3], &[0, 0, 1], &[2.0 * k, -k, k], &[0, 1])?;
//! // Subdomain 1: springs 2-3 and 3-4, global dofs 1, 2, 3 (full matrix);
//! // it floats: its kernel (the constant vector) is found at set-up.
//! problem.subdomain(
//!     1,
//!     &[0, 2, 5, 7],
//!     &[0, 1, 0, 1, 2, 1, 2],
//!     &[k, -k, -k, 2.0 * k, -k, -k, k],
//!     &[1, 2, 3],
//! )?;
//! // The multilevel method builds its macro space from the dof points.
//! let points: Vec<[f64; 3]> = (0..4).map(|g| [g as f64 + 1.0, 0.0, 0.0]).collect();
//! problem.dof_points(&points, &[0; 4])?;
//! let settings = SolverSettings { method: Method::Multilevel, tolerance: 1e-12, ..Default::default() };
//! let mut solver = problem.build(&settings)?;
//! let out = solver.solve(&[0.0, 0.0, 0.0, 1.0])?;
//! assert!(out.converged());
//! for (g, u) in out.u.iter().enumerate() {
//!     assert!((u - (g + 1) as f64 / k).abs() < 1e-9); // every spring carries 1
//! }
//! # Ok::<(), nsdd::Error>(())
//! ```

use crate::comm::{Communicator, Placement};
use crate::dd::{CableColumn, DdOptions, DdProblem, DdSolver, DdStats, SubdomainLoad, NO_DOF};
use crate::decomposition::Decomposition;
use crate::error::{Error, Result};
use crate::factor::lower_csc;
use crate::outcome::Outcome;
use crate::partition::Partition;
use crate::settings::SolverSettings;
use crate::subdomain::SubdomainOperator;
use faer::Mat;
use rayon::prelude::*;

/// Largest number of entries of one cable column ([`AlgebraicProblem::cable`]).
pub const MAX_CABLE_ENTRIES: usize = 6;

/// Relative tolerance of the symmetry check of a full matrix (against the
/// largest entry): assembly round-off passes, a transposed entry does not.
const SYMMETRY_TOLERANCE: f64 = 1e-10;

fn bad(field: impl Into<String>, message: impl Into<String>) -> Error {
    Error::input(field, None, message)
}

fn check_finite(field: &str, v: &[f64]) -> Result<()> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(bad(field, format!("{field}[{i}] is not a finite number ({})", v[i]))),
        None => Ok(()),
    }
}

/// One subdomain, in the caller's local numbering.
#[derive(Debug, Clone)]
struct Subdomain {
    n_local: usize,
    /// Lower triangle `(row, col, value)`, `row >= col`, caller numbering.
    lower: Vec<(usize, usize, f64)>,
    local_to_global: Vec<usize>,
    /// Kernel basis `(r, n_local × r column-major)`.
    kernel: Option<(usize, Vec<f64>)>,
}

#[derive(Debug, Clone)]
struct Cable {
    subdomain: usize,
    dofs: Vec<usize>,
    coefs: Vec<f64>,
    k: f64,
    e0: f64,
}

/// The data of an algebraic domain-decomposition problem, gathered call by
/// call (a builder: every method checks its arguments and returns `&mut
/// Self`, so calls chain with `?`). Setting a subdomain again replaces it.
#[derive(Debug, Clone)]
pub struct AlgebraicProblem {
    n_global: usize,
    subdomains: Vec<Option<Subdomain>>,
    dof_points: Option<Vec<([f64; 3], usize)>>,
    cables: Vec<Cable>,
    /// Where the subdomains live: under MPI each rank sets (and factors)
    /// only its block ([`Self::owned`]).
    placement: Placement,
}

impl AlgebraicProblem {
    /// A problem with `n_subdomains` (>= 1) subdomains over `n_global_dofs`
    /// (>= `n_subdomains`) global dofs.
    pub fn new(n_subdomains: usize, n_global_dofs: usize) -> Result<AlgebraicProblem> {
        if n_subdomains == 0 {
            return Err(bad("n_subdomains", "n_subdomains must be at least 1"));
        }
        if n_global_dofs == 0 {
            return Err(bad("n_global_dofs", "n_global_dofs must be at least 1"));
        }
        if n_subdomains > n_global_dofs {
            return Err(bad(
                "n_subdomains",
                format!("n_subdomains = {n_subdomains} exceeds n_global_dofs = {n_global_dofs}"),
            ));
        }
        Ok(AlgebraicProblem {
            n_global: n_global_dofs,
            subdomains: vec![None; n_subdomains],
            dof_points: None,
            cables: Vec::new(),
            placement: Placement::Process,
        })
    }

    /// [`Self::new`] with the subdomains spread as `placement` says. Under
    /// MPI every rank creates the problem with the same sizes, sets only
    /// the subdomains of its block ([`Self::owned`]) and their kernels and
    /// cables, gives the dof points of (at least) its subdomains' dofs, and
    /// calls [`Self::build`] with the others; the local-to-global maps are
    /// gathered there, so every rank knows the interfaces. Cables are
    /// numbered rank by rank: in the slacks of a solve, rank `r`'s cables
    /// (in the order it added them) follow those of the ranks below it.
    pub fn new_in(n_subdomains: usize, n_global_dofs: usize, placement: Placement) -> Result<AlgebraicProblem> {
        let mut p = Self::new(n_subdomains, n_global_dofs)?;
        p.placement = placement;
        Ok(p)
    }

    /// The subdomains this process sets: all of them, or its MPI rank's block.
    pub fn owned(&self) -> std::ops::Range<usize> {
        self.placement.owned(self.subdomains.len())
    }

    /// Where the subdomains live.
    pub fn placement(&self) -> &Placement {
        &self.placement
    }

    pub fn n_subdomains(&self) -> usize {
        self.subdomains.len()
    }

    pub fn n_global_dofs(&self) -> usize {
        self.n_global
    }

    /// Cables added so far (the next one gets this index).
    pub fn n_cables(&self) -> usize {
        self.cables.len()
    }

    /// The number of local dofs of subdomain `s`, `None` if it is not set
    /// (or out of range).
    pub fn n_local(&self, s: usize) -> Option<usize> {
        self.subdomains.get(s)?.as_ref().map(|d| d.n_local)
    }

    fn check_subdomain(&self, s: usize) -> Result<()> {
        if s >= self.subdomains.len() {
            return Err(bad(
                "s",
                format!(
                    "subdomain {s} out of range (the problem has {} subdomains)",
                    self.subdomains.len()
                ),
            ));
        }
        let held = self.owned();
        if !held.contains(&s) {
            return Err(bad(
                "s",
                format!(
                    "subdomain {s} belongs to rank {} (rank {} sets subdomains {}..{})",
                    self.placement.owner(s, self.subdomains.len()),
                    self.placement.rank(),
                    held.start,
                    held.end
                ),
            ));
        }
        Ok(())
    }

    fn set_subdomain(&self, s: usize) -> Result<&Subdomain> {
        self.check_subdomain(s)?;
        self.subdomains[s].as_ref().ok_or_else(|| {
            bad(
                format!("subdomain {s}"),
                format!("subdomain {s} has not been set (set its matrix first)"),
            )
        })
    }

    /// Sets subdomain `s` (0-based): its stiffness `K_E` (`n_local ×
    /// n_local`, symmetric positive semi-definite, `n_local =
    /// local_to_global.len()`) in 0-based CSR — `row_ptr` has `n_local + 1`
    /// entries, `col_idx` and `values` have `row_ptr[n_local]` — and the
    /// global dof of each local dof (distinct, any order). Give either the
    /// full symmetric matrix (checked to be symmetric) or its lower
    /// triangle; duplicates are summed. Only the lower triangle is kept; a
    /// matrix given as its upper triangle only is refused. Global dofs with
    /// equal ids in several subdomains are glued (interface dofs). This
    /// local numbering is the one of [`Self::kernel`], [`Self::cable`] and
    /// [`AlgebraicSolver::solve_local`].
    pub fn subdomain(
        &mut self,
        s: usize,
        row_ptr: &[usize],
        col_idx: &[usize],
        values: &[f64],
        local_to_global: &[usize],
    ) -> Result<&mut Self> {
        self.check_subdomain(s)?;
        let field = format!("subdomain {s}");
        let n_local = local_to_global.len();
        if n_local == 0 {
            return Err(bad(field, "n_local must be at least 1 (local_to_global is empty)"));
        }
        if row_ptr.len() != n_local + 1 {
            return Err(bad(
                field,
                format!(
                    "row_ptr has {} entries, expected n_local + 1 = {} (local_to_global has {n_local})",
                    row_ptr.len(),
                    n_local + 1
                ),
            ));
        }
        if row_ptr[0] != 0 {
            return Err(bad(
                field,
                format!("row_ptr[0] = {}, expected 0 (0-based CSR)", row_ptr[0]),
            ));
        }
        if let Some(i) = row_ptr.windows(2).position(|w| w[1] < w[0]) {
            return Err(bad(
                field,
                format!("row_ptr[{}] < row_ptr[{i}] (must not decrease)", i + 1),
            ));
        }
        let nnz = row_ptr[n_local];
        for (name, len) in [("col_idx", col_idx.len()), ("values", values.len())] {
            if len != nnz {
                return Err(bad(
                    field,
                    format!("{name} has {len} entries, expected row_ptr[n_local] = {nnz}"),
                ));
            }
        }
        check_finite("values", values).map_err(|e| bad(field.clone(), inner(e)))?;
        if let Some(p) = col_idx.iter().position(|&c| c >= n_local) {
            return Err(bad(
                field,
                format!("col_idx[{p}] = {} out of range (n_local = {n_local})", col_idx[p]),
            ));
        }
        if let Some(i) = local_to_global.iter().position(|&g| g >= self.n_global) {
            return Err(bad(
                field,
                format!(
                    "local_to_global[{i}] = {} out of range (n_global_dofs = {})",
                    local_to_global[i], self.n_global
                ),
            ));
        }
        let mut sorted: Vec<(usize, usize)> = local_to_global.iter().enumerate().map(|(i, &g)| (g, i)).collect();
        sorted.sort_unstable();
        if let Some(w) = sorted.windows(2).find(|w| w[0].0 == w[1].0) {
            return Err(bad(
                field,
                format!(
                    "local_to_global[{}] and local_to_global[{}] are both global dof {}",
                    w[0].1.min(w[1].1),
                    w[0].1.max(w[1].1),
                    w[0].0
                ),
            ));
        }
        let mut lower = Vec::with_capacity(nnz);
        // Strictly upper entries, transposed: compared with the strictly
        // lower ones when the full matrix is given.
        let mut upper_t = Vec::new();
        let mut strict_lower = Vec::new();
        for i in 0..n_local {
            for p in row_ptr[i]..row_ptr[i + 1] {
                let (j, v) = (col_idx[p], values[p]);
                if j > i {
                    upper_t.push((j, i, v));
                } else {
                    if j < i {
                        strict_lower.push((i, j, v));
                    }
                    lower.push((i, j, v));
                }
            }
        }
        if strict_lower.is_empty() && !upper_t.is_empty() {
            return Err(bad(
                field,
                "only the upper triangle was given (no entry below the diagonal); pass the full symmetric matrix or its lower triangle",
            ));
        }
        if !upper_t.is_empty() {
            let scale = values.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            if let Some((i, j, a, b)) = asymmetry(strict_lower, upper_t, SYMMETRY_TOLERANCE * scale) {
                return Err(bad(
                    field,
                    format!(
                        "the matrix is not symmetric: entry ({i}, {j}) = {a} but entry ({j}, {i}) = {b} \
                         (a missing entry counts as 0); pass a symmetric matrix or its lower triangle"
                    ),
                ));
            }
        }
        self.subdomains[s] = Some(Subdomain {
            n_local,
            lower,
            local_to_global: local_to_global.to_vec(),
            kernel: None,
        });
        Ok(self)
    }

    /// Sets the point of the node carrying each global dof and the dof's
    /// component (0 x, 1 y, 2 z): `points` and `component` have
    /// `n_global_dofs` entries. The multilevel and cg methods build their
    /// macro (rigid-body and extension) modes from them; monolevel does not
    /// need them.
    pub fn dof_points(&mut self, points: &[[f64; 3]], component: &[usize]) -> Result<&mut Self> {
        for (name, len) in [("points", points.len()), ("component", component.len())] {
            if len != self.n_global {
                return Err(bad(
                    name,
                    format!("{name} has {len} entries, expected n_global_dofs = {}", self.n_global),
                ));
            }
        }
        check_finite("xyz", points.as_flattened())?;
        if let Some(i) = component.iter().position(|&c| c > 2) {
            return Err(bad(
                "component",
                format!("component[{i}] = {}: expected 0 (x), 1 (y) or 2 (z)", component[i]),
            ));
        }
        self.dof_points = Some(points.iter().copied().zip(component.iter().copied()).collect());
        Ok(self)
    }

    /// Gives the kernel of subdomain `s`'s matrix (a floating subdomain):
    /// `r` columns of `n_local` entries, column-major (`basis.len() = r *
    /// n_local`), in the subdomain's local numbering. It must span the
    /// kernel the factorization detects (checked by [`Self::build`]). An
    /// empty `basis` removes a kernel given before; without one the kernel
    /// is computed. Set the subdomain first (setting it again drops the
    /// kernel).
    pub fn kernel(&mut self, s: usize, basis: &[f64]) -> Result<&mut Self> {
        let n_local = self.set_subdomain(s)?.n_local;
        if basis.len() % n_local != 0 {
            return Err(bad(
                format!("subdomain {s}"),
                format!(
                    "the kernel basis has {} entries, not a multiple of n_local = {n_local}",
                    basis.len()
                ),
            ));
        }
        check_finite("basis", basis)?;
        let r = basis.len() / n_local;
        self.subdomains[s].as_mut().expect("checked above").kernel = (r > 0).then(|| (r, basis.to_vec()));
        Ok(self)
    }

    /// Adds a unilateral cable to subdomain `s` and returns its index (its
    /// position in [`Outcome::lambda`]: 0, 1, ... in the order of the
    /// calls): its column `h` (at most [`MAX_CABLE_ENTRIES`] coefficients
    /// `coefs` on local dofs `local_dofs`; none for a cable whose ends are
    /// both fixed), elongation `e = hᵀ u`, stiffness `k` (> 0) and
    /// prestrain `e0`. The cable is slack when `e + e0 < 0`; its stiffness
    /// `k h hᵀ` must be included in the subdomain matrix (the solver removes
    /// it when slack), and any prestrain load (`-k e0 h`) belongs in the
    /// right-hand side.
    pub fn cable(&mut self, s: usize, local_dofs: &[usize], coefs: &[f64], k: f64, e0: f64) -> Result<usize> {
        let n_local = self.set_subdomain(s)?.n_local;
        let n = local_dofs.len();
        if coefs.len() != n {
            return Err(bad(
                "coefs",
                format!("coefs has {} entries, local_dofs has {n}", coefs.len()),
            ));
        }
        if n > MAX_CABLE_ENTRIES {
            return Err(bad(
                "local_dofs",
                format!("n_entries = {n}: expected at most {MAX_CABLE_ENTRIES}"),
            ));
        }
        if let Some(i) = local_dofs.iter().position(|&d| d >= n_local) {
            return Err(bad(
                "local_dofs",
                format!(
                    "local_dofs[{i}] = {} out of range (subdomain {s} has {n_local} dofs)",
                    local_dofs[i]
                ),
            ));
        }
        check_finite("coefs", coefs)?;
        if !(k > 0.0 && k.is_finite()) {
            return Err(bad("k", format!("k must be positive and finite, got {k}")));
        }
        if !e0.is_finite() {
            return Err(bad("e0", format!("e0 must be finite, got {e0}")));
        }
        self.cables.push(Cable {
            subdomain: s,
            dofs: local_dofs.to_vec(),
            coefs: coefs.to_vec(),
            k,
            e0,
        });
        Ok(self.cables.len() - 1)
    }

    /// What [`Self::build`] checks before it factors anything, for a method
    /// with (`coarse`) or without the macro space: every subdomain set,
    /// every global dof in a subdomain, the dof points given when the
    /// method needs them, every cable's dofs inside its (possibly reset)
    /// subdomain.
    pub fn check_complete(&self, coarse: bool) -> Result<()> {
        for s in self.owned() {
            if self.subdomains[s].is_none() {
                return Err(bad(format!("subdomain {s}"), format!("subdomain {s} has not been set")));
            }
        }
        if self.owned().len() == self.subdomains.len() {
            check_covered(
                self.subdomains.iter().flatten().map(|s| &s.local_to_global[..]),
                self.n_global,
            )?;
        }
        if coarse && self.dof_points.is_none() {
            return Err(bad(
                "dof_points",
                "the multilevel and cg methods need the dof points (AlgebraicProblem::dof_points)",
            ));
        }
        for (c, cable) in self.cables.iter().enumerate() {
            let n = self.subdomains[cable.subdomain].as_ref().map_or(0, |d| d.n_local);
            if let Some(&d) = cable.dofs.iter().find(|&&d| d >= n) {
                return Err(bad(
                    format!("cable {c}"),
                    format!(
                        "local dof {d} out of range (subdomain {} now has {n} dofs)",
                        cable.subdomain
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Factors every subdomain (in parallel), builds the interfaces, the
    /// macro space and the coarse problem, and picks the search direction.
    /// `settings` gives the method (monolevel, multilevel or cg; direct is
    /// [`Error::MethodNotApplicable`]), tolerance, iteration limit, search
    /// direction and preconditioner; its subdomain count and partitioner
    /// are not used. The problem is left as it is (change it and build
    /// again).
    pub fn build(&self, settings: &SolverSettings) -> Result<AlgebraicSolver> {
        // The one mapping of a method to its configuration (and the one
        // validation of the settings).
        let options = DdOptions::from_settings(settings)?;
        let placement = &self.placement;
        placement.agree(self.check_complete(options.coarse))?;
        let ns = self.subdomains.len();
        let held = self.owned();
        let first = held.start;
        let subs: Vec<&Subdomain> = self.subdomains[held.clone()].iter().flatten().collect();
        let dof_points = match &self.dof_points {
            Some(p) => p.clone(),
            None => vec![([0.0; 3], 0); self.n_global],
        };
        // Every subdomain's global dofs, in subdomain order: here, or
        // gathered from the ranks (set-up only).
        let maps: Vec<Vec<usize>> = if held.len() == ns {
            subs.iter().map(|s| s.local_to_global.clone()).collect()
        } else {
            let mine: Vec<f64> = subs
                .iter()
                .flat_map(|s| std::iter::once(s.n_local as f64).chain(s.local_to_global.iter().map(|&g| g as f64)))
                .collect();
            let all = placement.gather(&mine);
            let mut maps = Vec::with_capacity(ns);
            let mut k = 0;
            while k < all.len() {
                let n = all[k] as usize;
                maps.push(all[k + 1..k + 1 + n].iter().map(|&g| g as usize).collect());
                k += 1 + n;
            }
            // The same maps on every rank: the same verdict.
            check_covered(maps.iter().map(|m: &Vec<usize>| &m[..]), self.n_global)?;
            maps
        };
        // Cables are numbered rank by rank.
        let counts = placement.gather(&[self.cables.len() as f64]);
        let cable_base: usize = counts[..placement.rank()].iter().map(|&c| c as usize).sum();
        let n_cables: usize = counts.iter().map(|&c| c as usize).sum();
        // The decomposition takes each subdomain's dofs in increasing global
        // order and lays them out its own way (interior first, then interface
        // by interface): its local dof p is the caller's local dof order[p];
        // inverse[caller] = p.
        let sorted: Vec<Vec<usize>> = maps
            .iter()
            .map(|map| {
                let mut o: Vec<usize> = (0..map.len()).collect();
                o.sort_unstable_by_key(|&i| map[i]);
                o
            })
            .collect();
        let dof_sets: Vec<Vec<usize>> = maps
            .iter()
            .zip(&sorted)
            .map(|(map, o)| o.iter().map(|&i| map[i]).collect())
            .collect();
        let partition = Partition {
            part_of: vec![],
            elements_of: vec![vec![]; ns],
        };
        let dec = Decomposition::from_dof_sets(partition, dof_sets, self.n_global);
        let order: Vec<Vec<usize>> = dec
            .subdomains
            .iter()
            .zip(&sorted)
            .map(|(sd, o)| {
                let mut ord = vec![0; o.len()];
                for (k, &l) in sd.by_global.iter().enumerate() {
                    ord[l as usize] = o[k];
                }
                ord
            })
            .collect();
        let inverse: Vec<Vec<usize>> = order
            .iter()
            .map(|o| {
                let mut inv = vec![0; o.len()];
                for (p, &i) in o.iter().enumerate() {
                    inv[i] = p;
                }
                inv
            })
            .collect();

        let ops: Vec<Result<SubdomainOperator>> = subs
            .par_iter()
            .enumerate()
            .map(|(k, sub)| {
                let s = first + k;
                let inv = &inverse[s];
                // Every diagonal entry is stored (an explicit zero when the
                // caller left it out, duplicates being summed): a dof with
                // no stiffness then shows as a zero pivot (a kernel mode or
                // a clear error) instead of a hole in the pattern.
                let trip: Vec<(usize, usize, f64)> = sub
                    .lower
                    .iter()
                    .map(|&(i, j, v)| {
                        let (a, b) = (inv[i], inv[j]);
                        (a.max(b), a.min(b), v)
                    })
                    .chain((0..sub.n_local).map(|p| (p, p, 0.0)))
                    .collect();
                let stiffness = lower_csc(sub.n_local, &trip)
                    .map_err(|e| Error::Numerical(format!("subdomain {s}: cannot build the matrix: {e:?}")))?;
                let kernel = sub.kernel.as_ref().map(|(r, b)| {
                    let n = sub.n_local;
                    Mat::from_fn(n, *r, |p, q| b[q * n + order[s][p]])
                });
                let name = |p: usize| {
                    let i = order[s][p];
                    format!("local dof {i} (global dof {})", sub.local_to_global[i])
                };
                let rank = dec.subdomains[s].reference_rank();
                SubdomainOperator::from_matrix(s, stiffness, 64, kernel.as_ref(), Some(&rank), &name)
            })
            .collect();
        let operators = placement.agree(ops.into_iter().collect::<Result<Vec<_>>>())?;
        let mut loads: Vec<SubdomainLoad> = subs
            .iter()
            .map(|sub| SubdomainLoad {
                constant: vec![0.0; sub.n_local],
                cables: Vec::new(),
            })
            .collect();
        for (c, cable) in self.cables.iter().enumerate() {
            let mut dofs = [NO_DOF; MAX_CABLE_ENTRIES];
            let mut coef = [0.0; MAX_CABLE_ENTRIES];
            for (k, (&d, &v)) in cable.dofs.iter().zip(&cable.coefs).enumerate() {
                dofs[k] = inverse[cable.subdomain][d] as u32;
                coef[k] = v;
            }
            loads[cable.subdomain - first].cables.push(CableColumn {
                cable: cable_base + c,
                dofs,
                coef,
                k: cable.k,
                e0: cable.e0,
            });
        }
        let problem = DdProblem {
            decomposition: &dec,
            operators,
            loads,
            placement: placement.clone(),
            dof_points,
            n_cables,
        };
        let solver = DdSolver::from_problem(problem, options)?;
        let scratch = order[held].iter().map(|o| vec![0.0; o.len()]).collect();
        Ok(AlgebraicSolver {
            decomposition: dec,
            solver,
            order,
            scratch,
            n_global: self.n_global,
        })
    }
}

/// Every global dof in some subdomain's map.
fn check_covered<'a>(maps: impl Iterator<Item = &'a [usize]>, n_global: usize) -> Result<()> {
    let mut covered = vec![false; n_global];
    for map in maps {
        for &g in map {
            covered[g] = true;
        }
    }
    match covered.iter().position(|c| !c) {
        Some(g) => Err(bad(
            "local_to_global",
            format!("global dof {g} belongs to no subdomain"),
        )),
        None => Ok(()),
    }
}

/// The message of an [`Error::InvalidInput`] (what a field-qualified
/// re-wrap keeps).
fn inner(e: Error) -> String {
    match e {
        Error::InvalidInput { message, .. } => message,
        other => other.to_string(),
    }
}

/// The first pair of mirrored entries whose summed values differ by more
/// than `tol` (`strict_lower` as `(row, col, v)` with `row > col`,
/// `upper_t` the strictly upper entries transposed the same way): `(row,
/// col, lower value, upper value)`.
fn asymmetry(
    mut strict_lower: Vec<(usize, usize, f64)>,
    mut upper_t: Vec<(usize, usize, f64)>,
    tol: f64,
) -> Option<(usize, usize, f64, f64)> {
    let key = |e: &(usize, usize, f64)| (e.0, e.1);
    strict_lower.sort_unstable_by_key(key);
    upper_t.sort_unstable_by_key(key);
    let (mut a, mut b) = (0, 0);
    // Merge the two sorted lists, summing duplicates, missing = 0.
    while a < strict_lower.len() || b < upper_t.len() {
        let ka = strict_lower.get(a).map(key);
        let kb = upper_t.get(b).map(key);
        let k = match (ka, kb) {
            (Some(x), Some(y)) => x.min(y),
            (Some(x), None) => x,
            (None, Some(y)) => y,
            (None, None) => unreachable!(),
        };
        let (mut va, mut vb) = (0.0, 0.0);
        while a < strict_lower.len() && key(&strict_lower[a]) == k {
            va += strict_lower[a].2;
            a += 1;
        }
        while b < upper_t.len() && key(&upper_t[b]) == k {
            vb += upper_t[b].2;
            b += 1;
        }
        if (va - vb).abs() > tol {
            return Some((k.0, k.1, va, vb));
        }
    }
    None
}

/// A set-up algebraic problem: factored subdomains, interfaces, macro space
/// and coarse problem, solved for any number of right-hand sides (each
/// solve starts from zero).
pub struct AlgebraicSolver {
    decomposition: Decomposition,
    solver: DdSolver,
    /// Per subdomain: the caller's local index of each decomposition local dof.
    order: Vec<Vec<usize>>,
    /// Per-subdomain right-hand sides in the decomposition's numbering,
    /// reused by every [`Self::solve_local`].
    scratch: Vec<Vec<f64>>,
    n_global: usize,
}

impl AlgebraicSolver {
    /// Solves for a global right-hand side `f` (`n_global_dofs` entries): a
    /// value on a dof shared by `m` subdomains is split equally between
    /// them. The outcome's `u` is the global displacement (the average of
    /// the subdomain copies), `lambda` the cable slacks (> 0 for a slack
    /// cable); a diverged run is an outcome ([`Outcome::divergence`]).
    pub fn solve(&mut self, f: &[f64]) -> Result<Outcome> {
        let checked = if f.len() != self.n_global {
            Err(bad(
                "f",
                format!("f has {} entries, expected n_global_dofs = {}", f.len(), self.n_global),
            ))
        } else {
            check_finite("f", f)
        };
        // Under MPI a bad input on one rank fails every rank (no rank
        // waits in the iteration for one that returned).
        self.solver.seam().agree(checked)?;
        self.solver.solve(f, false, None)
    }

    /// Solves for right-hand sides given per subdomain (those of
    /// [`AlgebraicProblem::owned`] under MPI): `rhs[s]` has
    /// `n_local(s)` entries in the subdomain's local numbering (its share of
    /// the load; a force on an interface dof may be split between
    /// subdomains in any way). Nothing is added: include prestrain loads.
    pub fn solve_local(&mut self, rhs: &[&[f64]]) -> Result<Outcome> {
        let checked = self.take_rhs(rhs);
        self.solver.seam().agree(checked)?;
        let views: Vec<&[f64]> = self.scratch.iter().map(|v| v.as_slice()).collect();
        self.solver.solve_local(&views, false, None)
    }

    /// Checks the right-hand sides of [`Self::solve_local`] and copies them
    /// into the decomposition's numbering.
    fn take_rhs(&mut self, rhs: &[&[f64]]) -> Result<()> {
        let held = self.solver.owned();
        if rhs.len() != held.len() {
            return Err(bad(
                "rhs",
                format!("{} subdomain vectors given, expected {}", rhs.len(), held.len()),
            ));
        }
        let first = held.start;
        for (k, ((r, order), buf)) in rhs.iter().zip(&self.order[held]).zip(&mut self.scratch).enumerate() {
            let s = first + k;
            let name = format!("rhs[{s}]");
            if r.len() != order.len() {
                return Err(bad(
                    name,
                    format!(
                        "rhs[{s}] has {} entries, subdomain {s} has {} dofs",
                        r.len(),
                        order.len()
                    ),
                ));
            }
            check_finite(&name, r)?;
            for (b, &i) in buf.iter_mut().zip(order) {
                *b = r[i];
            }
        }
        Ok(())
    }

    /// The step length `d` chosen at set-up (the stationary iteration).
    pub fn search_direction(&self) -> f64 {
        self.solver.search_direction()
    }

    pub fn n_global_dofs(&self) -> usize {
        self.n_global
    }

    pub fn n_subdomains(&self) -> usize {
        self.order.len()
    }

    /// The number of cables (entries of [`Outcome::lambda`]).
    pub fn n_cables(&self) -> usize {
        self.solver.n_cables
    }

    /// The interfaces found from the local-to-global maps.
    pub fn decomposition(&self) -> &Decomposition {
        &self.decomposition
    }

    /// Sizes and timings of the set-up.
    pub fn stats(&self) -> &DdStats {
        self.solver.stats()
    }
}
