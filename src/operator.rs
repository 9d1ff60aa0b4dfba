//! The interface operator as a value (docs/design.md §5–6, §8): the
//! subdomain operators with their scratch, the interfaces with their macro
//! bases, the coarse problem and the communication seam ([`crate::comm`]).
//!
//! What it offers the methods ([`crate::method`]), on interface vectors
//! the method owns (forces, CG directions, per-interface slices):
//! - [`InterfaceOperator::apply`]: forces → displacement `V` (one solve per
//!   subdomain and the coarse step) → interface jump `J V`;
//! - [`InterfaceOperator::force_stage`]: the stationary iteration's local
//!   stage `F += d Σ B D B J V`, and [`InterfaceOperator::cable_stage`];
//! - [`InterfaceOperator::precondition`]: CG's preconditioner;
//! - the indicator sums and the global vectors of a solve.
//!
//! Per-subdomain work runs on the subdomain's own vectors; everything that
//! crosses subdomains (neighbour traces, global sums, coarse gather and
//! scatter, global vectors) goes through [`Communicator`]. The operator's
//! results stay in its buffers (`ifaces[i].jump`, `subs[s].v`), which the
//! methods read; scratch is allocated at set-up, no call allocates.

use crate::coarse::CoarseProblem;
use crate::comm::{CoarseRhsPart, Communicator, Threads};
use crate::dd::{IfaceState, SubState};
use crate::kernels::{self, Side};
use crate::scaling::{self, DeluxeBlock, EntryWeights};
use rayon::prelude::*;

/// The set-up interface operator (see the module documentation), generic
/// over the communication seam: its code does not depend on where the
/// subdomains live.
pub struct InterfaceOperator<C: Communicator = Threads> {
    pub(crate) subs: Vec<SubState>,
    pub(crate) ifaces: Vec<IfaceState>,
    pub(crate) coarse: Option<CoarseProblem>,
    pub(crate) comm: C,
    /// Per interface: `1 / multiplicity` of each entry's dof (the same on
    /// both sides), so the cross-point projection reads no neighbour's
    /// set-up data.
    entry_inv_mult: Vec<Vec<f64>>,
}

/// Column `k` of a column-major `faer` matrix as a slice (an owned `Mat`
/// stores each column contiguously).
#[inline]
fn column(a: &faer::Mat<f64>, k: usize) -> &[f64] {
    a.col(k).try_as_col_major().expect("contiguous column").as_slice()
}

/// `out[k] = a[:, k] · x` for every column of `a` (column-major, contiguous
/// columns).
#[inline]
fn columns_dot(a: &faer::Mat<f64>, x: &[f64], out: &mut [f64]) {
    for (k, o) in out.iter_mut().enumerate() {
        *o = kernels::dot(column(a, k), x);
    }
}

/// `jump = lo − hi` on the interface and its two norms (length, and the
/// force the jump leaves unbalanced through the lumped stiffness).
#[inline]
fn jump_of(it: &mut IfaceState, lo: &[f64], hi: &[f64], with_base: bool) {
    kernels::jump_runs(&mut it.jump, lo, hi, &it.runs);
    if with_base && !it.base_jump.is_empty() {
        it.jump.iter_mut().zip(&it.base_jump).for_each(|(j, b)| *j += b);
    }
    it.jump_norm2 = kernels::norm2(&it.jump);
    it.force_norm2 = it.jump.iter().zip(&it.stiffness).map(|(j, k)| (j * k) * (j * k)).sum();
}

/// The coarse solve whose right-hand side the subdomains hold in their
/// scratch: macro values `zt_r` at their `macro_cols`, kernel part `rt_r`.
fn coarse_solve_from_subdomains<C: Communicator>(comm: &C, coarse: &mut CoarseProblem, subs: &[SubState]) {
    comm.coarse_solve(coarse, |s| CoarseRhsPart {
        macro_cols: &subs[s].macro_cols,
        macro_values: &subs[s].zt_r,
        kernel_off: subs[s].alpha_off,
        kernel: &subs[s].rt_r,
    });
}

/// The subdomain's part of the last coarse solution: its macro forces
/// `fm` (one per macro column it touches) and its kernel amplitudes `α`.
fn take_coarse_solution(s: &mut SubState, coarse: &CoarseProblem) {
    let f = coarse.macro_forces();
    for (k, &c) in s.macro_cols.iter().enumerate() {
        s.fm[k] = f[c];
    }
    let na = s.alpha.len();
    s.alpha
        .copy_from_slice(&coarse.kernel_amplitudes()[s.alpha_off..s.alpha_off + na]);
}

/// `r_E −= W_E f_E` on the interface dofs (`W_E` is zero elsewhere): the
/// macro forces into a right-hand side before the solve.
fn subtract_macro_forces(s: &mut SubState) {
    for (k, &fk) in s.fm.iter().enumerate() {
        if fk != 0.0 {
            for (l, w) in s.w_cols.col(k) {
                s.r[l] -= w * fk;
            }
        }
    }
}

/// `v_E += R_E α_E`: the kernel motion the coarse step gives the subdomain.
fn add_kernel_motion(s: &mut SubState) {
    let r = s.op.kernel();
    for (q, &a) in s.alpha.iter().enumerate() {
        for (v, rq) in s.v.iter_mut().zip(r.col(q).iter()) {
            *v += rq * a;
        }
    }
}

/// The coarse right-hand side `(Pᵀ J V, 0)` of the last jumps in the
/// subdomains' scratch (`zt_r`, `rt_r`): each interface's part once, from
/// its lo side (the coarse assembly sums the subdomains' parts).
fn macro_jump_rhs(subs: &mut [SubState], ifaces: &[IfaceState]) {
    subs.par_iter_mut().for_each(|s| {
        s.zt_r.iter_mut().for_each(|x| *x = 0.0);
        s.rt_r.iter_mut().for_each(|x| *x = 0.0);
        for &(i, is_lo) in &s.ifaces {
            let it = &ifaces[i];
            if !is_lo || it.p.ncols() == 0 {
                continue;
            }
            let range = it.macro_off..it.macro_off + it.p.ncols();
            for (k, &c) in s.macro_cols.iter().enumerate() {
                if range.contains(&c) {
                    s.zt_r[k] = kernels::dot(column(&it.p, c - it.macro_off), &it.jump);
                }
            }
        }
    });
}

/// `x ← (I − P Pᵀ) x` for an interface block `P` with orthonormal columns.
fn remove_macro_part(x: &mut [f64], p: &faer::Mat<f64>) {
    for q in 0..p.ncols() {
        let col = column(p, q);
        let c = kernels::dot(col, x);
        for (v, a) in x.iter_mut().zip(col) {
            *v -= c * a;
        }
    }
}

impl<C: Communicator> InterfaceOperator<C> {
    /// The operator of set-up subdomains (those `comm` holds here) and
    /// interfaces (all of them), with the coarse problem when there is a
    /// coarse step; `entry_inv_mult[i]` is `1 / multiplicity` of each entry
    /// of interface `i`.
    pub(crate) fn with_seam(
        subs: Vec<SubState>,
        ifaces: Vec<IfaceState>,
        coarse: Option<CoarseProblem>,
        comm: C,
        entry_inv_mult: Vec<Vec<f64>>,
    ) -> Self {
        InterfaceOperator {
            subs,
            ifaces,
            coarse,
            comm,
            entry_inv_mult,
        }
    }

    /// Entries of each interface.
    pub(crate) fn interface_sizes(&self) -> impl Iterator<Item = usize> + Clone + '_ {
        self.ifaces.iter().map(|it| it.lo_idx.len())
    }

    /// `V = V(F)` and `jump = J V`: the global step `r = b − C Bᵀ F − H k λ`
    /// (without `load`: `b = 0`, the homogeneous problem of the CG operator;
    /// without `with_cables`: no cable term), `y = K⁺ r`, the coarse step,
    /// `V = y − Z f + R α`, then the jumps. `V` is left in the subdomains'
    /// `v`, the jump in the interfaces' `jump`.
    pub fn apply(&mut self, forces: &[Vec<f64>], with_cables: bool, load: bool) {
        self.global_step(forces, with_cables, load);
        self.jumps_of_subdomains(load);
    }

    /// The global step of [`Self::apply`], without the jumps.
    ///
    /// With the coarse space, a homogeneous step (no load, no cable forces:
    /// CG's `A p`) has its right-hand side `r_E = ±B_Eᵀ F` on the interface
    /// dofs only. Its coarse right-hand side is then `Z_Eᵀ r_E` on those
    /// rows, known before the solve, and the macro forces go into the
    /// right-hand side: one solve gives `V = K_E⁺ (r_E − W_E f) + R_E α`
    /// without the dense `Z_E f` over every dof (on the 130² plate with 64
    /// subdomains that product cost half a substitution). A loaded step
    /// solves first and takes `W_Eᵀ y_E`, then removes `Z_E f`.
    fn global_step(&mut self, forces: &[Vec<f64>], with_cables: bool, load: bool) {
        let ifaces = &self.ifaces;
        let before = self.coarse.is_some() && !load && !with_cables;
        self.subs.par_iter_mut().for_each(|s| {
            if load {
                s.r.copy_from_slice(&s.b);
            } else {
                s.r.iter_mut().for_each(|v| *v = 0.0);
            }
            for &(i, is_lo) in &s.ifaces {
                let it = &ifaces[i];
                let (side, coef) = if is_lo { (Side::Lo, -1.0) } else { (Side::Hi, 1.0) };
                kernels::scatter_add_runs(&mut s.r, side, &it.runs, &forces[i], coef);
            }
            if with_cables {
                for (c, &lam) in s.cables.iter().zip(&s.lambda) {
                    if lam != 0.0 {
                        c.add_to(-c.k * lam, &mut s.r);
                    }
                }
            }
            if before {
                // `r_E` is zero off the interface dofs.
                for (x, &l) in s.rb.iter_mut().zip(&s.iface_dofs) {
                    *x = s.r[l as usize];
                }
                columns_dot(&s.z_iface, &s.rb, &mut s.zt_r);
                let r = s.op.kernel();
                for (q, rt) in s.rt_r.iter_mut().enumerate() {
                    let col = r.col(q);
                    *rt = s.iface_dofs.iter().zip(&s.rb).map(|(&l, x)| col[l as usize] * x).sum();
                }
            } else {
                s.y.copy_from_slice(&s.r);
                s.op.solve_in_place(&mut s.y);
            }
        });
        let Some(coarse) = self.coarse.as_mut() else {
            self.subs.par_iter_mut().for_each(|s| {
                s.v.copy_from_slice(&s.y);
                s.v_norm2 = kernels::norm2(&s.v);
            });
            return;
        };
        if !before {
            // `W_Eᵀ y_E` (W_E is zero off the interface dofs) and `R_Eᵀ r_E`.
            self.subs.par_iter_mut().for_each(|s| {
                for (k, z) in s.zt_r.iter_mut().enumerate() {
                    *z = s.w_cols.col(k).map(|(l, w)| w * s.y[l]).sum();
                }
                let r = s.op.kernel();
                for (q, rt) in s.rt_r.iter_mut().enumerate() {
                    *rt = kernels::dot(column(r, q), &s.r);
                }
            });
        }
        coarse_solve_from_subdomains(&self.comm, coarse, &self.subs);
        let coarse = &*coarse;
        self.subs.par_iter_mut().for_each(|s| {
            take_coarse_solution(s, coarse);
            if before {
                subtract_macro_forces(s);
                s.v.copy_from_slice(&s.r);
                s.op.solve_in_place(&mut s.v);
            } else {
                s.v.copy_from_slice(&s.y);
                for (k, &fk) in s.fm.iter().enumerate() {
                    if fk != 0.0 {
                        for (v, z) in s.v.iter_mut().zip(s.z.col(k).iter()) {
                            *v -= z * fk;
                        }
                    }
                }
            }
            add_kernel_motion(s);
            s.v_norm2 = kernels::norm2(&s.v);
        });
    }

    /// `jump = J V` on every interface, with `V` the subdomains' own `v`, or
    /// `v` when given (per subdomain: CG's iterate).
    ///
    /// An iterate's jump: with an equilibrium correction under way, the
    /// corrected solve's jump is added (`base_jump`).
    pub fn jumps(&mut self, v: Option<&[Vec<f64>]>) {
        match v {
            Some(v) => self.comm.neighbour_traces(
                v,
                |v| &v[..],
                &mut self.ifaces,
                |_, it, lo, hi| jump_of(it, lo, hi, true),
            ),
            None => self.jumps_of_subdomains(true),
        }
    }

    /// `jump = J V` of the subdomains' own `v`, with the corrected solve's
    /// jump added if `iterate` (not for CG's `A p`).
    fn jumps_of_subdomains(&mut self, iterate: bool) {
        self.comm.neighbour_traces(
            &self.subs,
            |s| &s.v,
            &mut self.ifaces,
            |_, it, lo, hi| jump_of(it, lo, hi, iterate),
        )
    }

    /// `F += d Σ_E B_Eᵀ D_E B_E jump` (cross points couple their pair
    /// entries); `D_E` is the identity for a scalar `d` and `diag(K_E)` for
    /// the lumped search direction (the paper's "lumped" `X^D`).
    pub fn force_stage(&mut self, forces: &mut [Vec<f64>], d: f64) {
        let ifaces = &self.ifaces;
        self.subs.par_iter_mut().for_each(|s| {
            for &(i, is_lo) in &s.ifaces {
                let it = &ifaces[i];
                let (side, coef) = if is_lo { (Side::Lo, 1.0) } else { (Side::Hi, -1.0) };
                kernels::scatter_add_runs(&mut s.g, side, &it.runs, &it.jump, coef);
            }
            for &l in &s.iface_dofs {
                s.g[l as usize] *= s.weight[l as usize];
            }
        });
        self.comm.neighbour_traces(
            &self.subs,
            |s| &s.g,
            forces,
            |i, f, lo, hi| {
                kernels::force_update_runs(f, d, lo, hi, &ifaces[i].runs);
            },
        );
        self.subs.par_iter_mut().for_each(|s| {
            for &l in &s.iface_dofs {
                s.g[l as usize] = 0.0;
            }
        });
    }

    /// The cable stage of the stationary iteration, per subdomain: the
    /// elongations `h_cᵀ V` and the projection `λ ← max(0, −(e + e0))`, with
    /// the change of `λ` kept for [`Self::cable_change2`].
    pub fn cable_stage(&mut self) {
        self.subs.par_iter_mut().for_each(|s| {
            for (c, e) in s.cables.iter().zip(s.elong.iter_mut()) {
                *e = c.elongation(&s.v);
            }
            (s.dlambda2, s.dforce2) = kernels::cable_projection(&mut s.lambda, &s.elong, &s.e0, &s.kc);
        });
    }

    /// `z = (I − P Pᵀ) Σ_E B_D,E S_E B_D,Eᵀ r` (`B_D` the jump operator
    /// scaled by the weights `w`, [`crate::scaling`]) with `S_E` the Schur
    /// complement of the subdomain on its interface (Dirichlet: the
    /// interface force that holds the displacement `Bᵀr` with the interior
    /// free), or `K_E` itself on the interface dofs (lumped: interior held
    /// at zero), then the macro part removed. `range(P)` is in the null
    /// space of the CG operator (the coarse step absorbs it); leaving it in
    /// `z` lets round-off grow there and break the iteration on long runs.
    /// The input keeps its macro part: projecting it too (the symmetric
    /// `(I − P Pᵀ) M (I − P Pᵀ)`, the same in exact arithmetic) saved 2–28 %
    /// of the iterations on contrast towers, but let the nonsmooth 5³ tower
    /// on 27 subdomains claim 1e-8 with tensions 5.6e-8 off, where this
    /// form ends 7e-11 off (BENCHMARKS.md, session 26). CG's stopping test
    /// measures the jump's macro part through the coarse problem
    /// ([`Self::macro_force_error`]).
    ///
    /// `w` are the pointwise weights of `B_D`; `deluxe` the dense weights of
    /// the faces that have them (they replace `w` there); `sl`, `sh` scratch
    /// of the interface sizes (`B_D,loᵀ r`, `B_D,hiᵀ r`).
    pub fn precondition(
        &mut self,
        r: &[Vec<f64>],
        w: &[EntryWeights],
        deluxe: &mut [Vec<DeluxeBlock>],
        sl: &mut [Vec<f64>],
        sh: &mut [Vec<f64>],
        z: &mut [Vec<f64>],
    ) {
        // B_D,Eᵀ r on either side of each interface (interface vectors,
        // held by both sides: no communication).
        r.par_iter()
            .zip(w.par_iter())
            .zip(deluxe.par_iter_mut().zip(sl.par_iter_mut().zip(sh.par_iter_mut())))
            .for_each(|((r, w), (dx, (sl, sh)))| {
                for ((((a, b), &r), &wl), &wh) in sl.iter_mut().zip(sh.iter_mut()).zip(r).zip(&w.lo).zip(&w.hi) {
                    *a = wl * r;
                    *b = wh * r;
                }
                for dx in dx {
                    dx.scale(r, sl, sh);
                }
            });
        let ifaces = &self.ifaces;
        let (sl, sh) = (&*sl, &*sh);
        self.subs.par_iter_mut().for_each(|s| {
            for &(i, is_lo) in &s.ifaces {
                let it = &ifaces[i];
                if is_lo {
                    kernels::scatter_add_runs(&mut s.g, Side::Lo, &it.runs, &sl[i], 1.0);
                } else {
                    kernels::scatter_add_runs(&mut s.g, Side::Hi, &it.runs, &sh[i], -1.0);
                }
            }
            // s.r is free between global steps: K_E B_Eᵀ r (lumped) or
            // S_E B_Eᵀ r (Dirichlet) goes there.
            match s.interior.as_mut() {
                Some(ip) => ip.apply_schur(&s.op, &s.g, &mut s.r),
                None => s.op.apply(&s.g, &mut s.r),
            }
            for &l in &s.iface_dofs {
                s.g[l as usize] = 0.0;
            }
        });
        self.comm.neighbour_traces(
            &self.subs,
            |s| &s.r,
            z,
            |i, cz, lo, hi| {
                scaling::scaled_jump_runs(cz, lo, &w[i].lo, hi, &w[i].hi, &ifaces[i].runs);
            },
        );
        // The deluxe blocks: `D_hiᵀ y_lo − D_loᵀ y_hi` from the same traces.
        self.comm.neighbour_traces(
            &self.subs,
            |s| &s.r,
            deluxe,
            |i, dx, lo, hi| {
                for dx in dx {
                    dx.face_jump(lo, &ifaces[i].lo_idx, hi, &ifaces[i].hi_idx);
                }
            },
        );
        z.par_iter_mut().zip(deluxe.par_iter()).for_each(|(cz, dx)| {
            for dx in dx {
                dx.write_face(cz);
            }
        });
        // Circulations of the redundant pair forces at cross points (zero
        // net force on every subdomain) are null directions too: project z
        // onto the differences of subdomain forces, `z ← (B_lo z − B_hi z)/m`
        // per dof of multiplicity m (the identity where m = 2).
        let cz = &*z;
        self.subs.par_iter_mut().for_each(|s| {
            for &(i, is_lo) in &s.ifaces {
                let it = &ifaces[i];
                let (side, coef) = if is_lo { (Side::Lo, 1.0) } else { (Side::Hi, -1.0) };
                kernels::scatter_add_runs(&mut s.g, side, &it.runs, &cz[i], coef);
            }
        });
        let inv_mult = &self.entry_inv_mult;
        self.comm.neighbour_traces(
            &self.subs,
            |s| &s.g,
            z,
            |i, cz, lo, hi| {
                let it = &ifaces[i];
                for (((z, &a), &b), &m) in cz.iter_mut().zip(&it.lo_idx).zip(&it.hi_idx).zip(&inv_mult[i]) {
                    *z = (lo[a as usize] - hi[b as usize]) * m;
                }
                remove_macro_part(cz, &it.p);
            },
        );
        self.subs.par_iter_mut().for_each(|s| {
            for &l in &s.iface_dofs {
                s.g[l as usize] = 0.0;
            }
        });
    }

    /// The energies of the CG stopping test ([`crate::cg_stopping`]) for
    /// the iterate `v` (per subdomain), with `jump` = `J v`: `J = Σ_E (ū_E −
    /// v_E)ᵀ K_E (ū_E − v_E)`, the strain energy that averaging the copies
    /// adds (`ū − v_E` at a dof of multiplicity `m` is `1/m` of the signed
    /// sum of its pair jumps), and `E = Σ_E b_Eᵀ v_E`, the work of the loads
    /// (`‖u*‖_K²` at convergence). `energy` holds each subdomain's parts.
    /// One product with `K_E` per subdomain; no allocation.
    pub fn jump_energies(&mut self, v: &[Vec<f64>], energy: &mut [(f64, f64)]) -> (f64, f64) {
        let ifaces = &self.ifaces;
        self.subs
            .par_iter_mut()
            .zip(v.par_iter().zip(energy.par_iter_mut()))
            .for_each(|(s, (cv, energy))| {
                for &(i, is_lo) in &s.ifaces {
                    let it = &ifaces[i];
                    let (side, coef) = if is_lo { (Side::Lo, -1.0) } else { (Side::Hi, 1.0) };
                    kernels::scatter_add_runs(&mut s.g, side, &it.runs, &it.jump, coef);
                }
                for &l in &s.iface_dofs {
                    s.g[l as usize] *= s.inv_mult[l as usize];
                }
                s.op.apply(&s.g, &mut s.r);
                let j: f64 = s.iface_dofs.iter().map(|&l| s.g[l as usize] * s.r[l as usize]).sum();
                for &l in &s.iface_dofs {
                    s.g[l as usize] = 0.0;
                }
                let e: f64 = s.b.iter().zip(cv).map(|(b, v)| b * v).sum();
                *energy = (j, e);
            });
        let [j, e] = self.comm.sum_subdomains(|s| [energy[s].0, energy[s].1]);
        (j, e)
    }

    /// `Σ_Γ ⟨x_Γ, y_Γ⟩` over the interfaces.
    pub fn dot(&self, x: &[Vec<f64>], y: &[Vec<f64>]) -> f64 {
        self.comm.sum_interfaces(|i| [kernels::dot(&x[i], &y[i])])[0]
    }

    /// `Σ_Γ ⟨x_Γ, jump_Γ⟩` over the interfaces.
    pub fn dot_jump(&self, x: &[Vec<f64>]) -> f64 {
        self.comm
            .sum_interfaces(|i| [kernels::dot(&x[i], &self.ifaces[i].jump)])[0]
    }

    /// `(Σ_Γ ‖P_Γᵀ x_Γ‖², Σ_Γ ‖x_Γ‖²)`: the part of `x` in the macro space
    /// and the whole. A residual of the CG operator has no macro part in
    /// exact arithmetic (the coarse step removes it).
    pub fn macro_part2(&self, x: &[Vec<f64>]) -> (f64, f64) {
        let [m, n] = self.comm.sum_interfaces(|i| {
            let p = &self.ifaces[i].p;
            let mut m = 0.0;
            for q in 0..p.ncols() {
                let c = kernels::dot(column(p, q), &x[i]);
                m += c * c;
            }
            [m, kernels::norm2(&x[i])]
        });
        (m, n)
    }

    /// The interface forces the macro part of the last jumps stands for:
    /// `‖f‖` of the coarse system `L f − G α = Pᵀ J V`, `Gᵀ f = 0`, the
    /// self-equilibrated macro forces whose coarse step would close that
    /// part (`P` is orthonormal: `‖P f‖ = ‖f‖`). CG leaves no macro part in
    /// the jump in exact arithmetic; this measures what the coarse solve's
    /// round-off leaves there through the exact coarse flexibility `L`,
    /// where the preconditioner would overstate it by its own eigenvalues on
    /// the macro space (up to the stiffness contrast on adaptive columns).
    /// Uses the subdomains' coarse right-hand-side scratch, so it may run
    /// only between global steps; 0 without a coarse step.
    pub fn macro_force_error(&mut self) -> f64 {
        let Some(coarse) = self.coarse.as_mut() else {
            return 0.0;
        };
        macro_jump_rhs(&mut self.subs, &self.ifaces);
        coarse_solve_from_subdomains(&self.comm, coarse, &self.subs);
        kernels::norm2(coarse.macro_forces()).sqrt()
    }

    /// Removes the macro part of the last jumps from `V` (the subdomains'
    /// `v`) by one more coarse step on it: `L δf − G δα = Pᵀ J V`,
    /// `Gᵀ δf = 0`, then `V ← V + K⁺(−W δf) + R δα` and the jumps again
    /// (one coarse solve and one solve per subdomain).
    ///
    /// A loaded global step leaves `Pᵀ J V` at the round-off of
    /// `V = y − Z f + R α`, relative to the whole load's macro forces `f`:
    /// where the coarse problem is ill-conditioned (adaptive columns on a
    /// 1e6-dof plate, a contrast tower whose macro space covers most of the
    /// interface) that is above what CG must reach, and CG, whose
    /// preconditioner projects the macro part out, cannot reduce it. The
    /// correction is refinement of the coarse step: its right-hand side is
    /// the small macro jump itself, so its own round-off is that much
    /// smaller. The increment is solved for rather than taken as `−Z δf`:
    /// `δf` may carry large components along the pair forces that
    /// circulate around cross points (null directions of `L` and `G`,
    /// where `W δf` vanishes), and `Z`'s round-off times those breaks each
    /// subdomain's equilibrium where the jump does not show it (the
    /// nonsmooth 12³ tower on 16 subdomains ended with tensions 1.0e-8 off
    /// at an indicator of 8e-10 that way; 6.4e-9 with the solve).
    pub fn correct_macro_part(&mut self) {
        let Some(coarse) = self.coarse.as_mut() else {
            return;
        };
        macro_jump_rhs(&mut self.subs, &self.ifaces);
        coarse_solve_from_subdomains(&self.comm, coarse, &self.subs);
        let coarse = &*coarse;
        self.subs.par_iter_mut().for_each(|s| {
            take_coarse_solution(s, coarse);
            s.r.iter_mut().for_each(|x| *x = 0.0);
            subtract_macro_forces(s);
            s.op.solve_in_place(&mut s.r);
            for (v, &d) in s.v.iter_mut().zip(&s.r) {
                *v += d;
            }
            add_kernel_motion(s);
            s.v_norm2 = kernels::norm2(&s.v);
        });
        self.jumps(None);
    }

    /// `Σ_Γ ‖x_Γ‖²` over the interfaces.
    pub fn norm2(&self, x: &[Vec<f64>]) -> f64 {
        self.comm.sum_interfaces(|i| [kernels::norm2(&x[i])])[0]
    }

    /// `Σ_E ‖v_E‖²` over the subdomains.
    pub fn norm2_subdomains(&self, v: &[Vec<f64>]) -> f64 {
        self.comm.sum_subdomains(|s| [kernels::norm2(&v[s])])[0]
    }

    /// `‖V‖²` of the last [`Self::apply`] (subdomain copies counted apart).
    pub fn v_norm2(&self) -> f64 {
        self.comm.sum_subdomains(|s| [self.subs[s].v_norm2])[0]
    }

    /// `(‖J V‖², ‖k ∘ J V‖²)` of the last jumps.
    pub fn jump_norms2(&self) -> (f64, f64) {
        let [j, f] = self
            .comm
            .sum_interfaces(|i| [self.ifaces[i].jump_norm2, self.ifaces[i].force_norm2]);
        (j, f)
    }

    /// `(‖Δλ‖², ‖k Δλ‖²)` of the last [`Self::cable_stage`].
    pub fn cable_change2(&self) -> (f64, f64) {
        let [l, f] = self
            .comm
            .sum_subdomains(|s| [self.subs[s].dlambda2, self.subs[s].dforce2]);
        (l, f)
    }

    /// Norm of the assembled right-hand side (loads and prestrain);
    /// `dof_maps[s]` is the global dof of each local dof of subdomain `s`.
    /// Allocates (once per solve).
    pub fn load_norm(&self, dof_maps: &[Vec<usize>], n_free: usize) -> f64 {
        let mut b_global = vec![0.0; n_free];
        self.comm.assemble(&mut b_global, |s, out| {
            for (l, &d) in dof_maps[s].iter().enumerate() {
                out[d] += self.subs[s].b[l];
            }
        });
        kernels::norm2(&b_global).sqrt()
    }

    /// Global displacement (average of the subdomain copies) and slacks.
    pub fn assemble(&self, dof_maps: &[Vec<usize>], n_free: usize, n_cables: usize) -> (Vec<f64>, Vec<f64>) {
        let mut u = vec![0.0; n_free];
        self.comm.assemble(&mut u, |s, out| {
            let st = &self.subs[s];
            for (l, &d) in dof_maps[s].iter().enumerate() {
                out[d] += st.v[l] * st.inv_mult[l];
            }
        });
        let mut lambda = vec![0.0; n_cables];
        // Every cable belongs to one subdomain: its slack is placed, not summed.
        self.comm.assemble(&mut lambda, |s, out| {
            let st = &self.subs[s];
            for (c, &lam) in st.cables.iter().zip(&st.lambda) {
                out[c.cable] = lam;
            }
        });
        (u, lambda)
    }

    /// Zero cable slacks.
    pub(crate) fn reset_slacks(&mut self) {
        for s in self.subs.iter_mut() {
            s.lambda.iter_mut().for_each(|v| *v = 0.0);
        }
    }

    /// Whether any interface exists (more than one subdomain).
    pub fn has_interfaces(&self) -> bool {
        !self.ifaces.is_empty()
    }
}

#[cfg(test)]
mod tests {
    //! The seam is enough for a distributed backend: a communicator that
    //! hands the operator copies of the neighbours' interface entries only
    //! (everything else NaN, as in an MPI rank's ghost buffers) and sums in
    //! its own loop gives the same bits as [`Threads`].
    use super::*;
    use crate::dd::DdSolver;

    struct Ghosts {
        inner: crate::comm::Seam,
        ends: Vec<(usize, usize)>,
        iface_dofs: Vec<Vec<u32>>,
    }

    impl Communicator for Ghosts {
        fn neighbour_traces<S, T, R, F>(&self, subs: &[S], trace: R, items: &mut [T], f: F)
        where
            S: Sync,
            T: Send,
            R: Fn(&S) -> &[f64] + Sync,
            F: Fn(usize, &mut T, &[f64], &[f64]) + Sync,
        {
            // What a rank would receive: the interface entries of each side.
            let ghost: Vec<Vec<f64>> = subs
                .iter()
                .zip(&self.iface_dofs)
                .map(|(s, dofs)| {
                    let v = trace(s);
                    let mut g = vec![f64::NAN; v.len()];
                    for &l in dofs {
                        g[l as usize] = v[l as usize];
                    }
                    g
                })
                .collect();
            for (i, t) in items.iter_mut().enumerate() {
                let (lo, hi) = self.ends[i];
                f(i, t, &ghost[lo], &ghost[hi]);
            }
        }

        fn sum_interfaces<const N: usize>(&self, f: impl Fn(usize) -> [f64; N]) -> [f64; N] {
            // Each part computed first, then reduced in interface order.
            let parts: Vec<[f64; N]> = (0..self.ends.len()).map(f).collect();
            let mut acc = [-0.0; N];
            for p in parts {
                for (a, x) in acc.iter_mut().zip(p) {
                    *a += x;
                }
            }
            acc
        }

        fn sum_subdomains<const N: usize>(&self, f: impl Fn(usize) -> [f64; N]) -> [f64; N] {
            self.inner.sum_subdomains(f)
        }

        fn coarse_solve<'a>(&self, coarse: &mut CoarseProblem, part: impl Fn(usize) -> CoarseRhsPart<'a>) {
            // A stale right-hand side must not survive the gather.
            coarse.rhs.iter_mut().for_each(|x| *x = f64::NAN);
            self.inner.coarse_solve(coarse, part);
        }

        fn assemble(&self, out: &mut [f64], add: impl Fn(usize, &mut [f64])) {
            self.inner.assemble(out, add);
        }

        fn owned(&self) -> std::ops::Range<usize> {
            self.inner.owned()
        }

        fn exchange(&self, payload: impl Fn(usize, bool) -> Vec<f64> + Sync) -> Vec<[Vec<f64>; 2]> {
            self.inner.exchange(payload)
        }

        fn gather(&self, local: &[f64]) -> Vec<f64> {
            self.inner.gather(local)
        }

        fn agree<T>(&self, r: crate::error::Result<T>) -> crate::error::Result<T> {
            self.inner.agree(r)
        }
    }

    fn solver() -> DdSolver {
        let (model, dec, opts) = crate::dd::cg_test_problem();
        DdSolver::new(&model, &dec, opts).unwrap()
    }

    fn same(a: &[f64], b: &[f64]) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
    }

    /// A homogeneous global step (no load: CG's `A p`) takes its coarse
    /// right-hand side from `Z_E` before solving and puts the macro forces
    /// into the solve; a loaded step solves first and removes `Z_E f`
    /// after. With a zero load the two give the same displacements and
    /// jumps up to round-off, and both leave no macro part in the jump (the
    /// coarse condition `Pᵀ J V = 0`).
    #[test]
    fn homogeneous_step_with_the_macro_forces_in_the_solve_is_the_loaded_step_without_load() {
        let mut op = solver().op;
        assert!(op.coarse.is_some());
        let sizes: Vec<usize> = op.interface_sizes().collect();
        let forces: Vec<Vec<f64>> = sizes
            .iter()
            .enumerate()
            .map(|(i, &n)| (0..n).map(|j| ((i * 17 + j * 5) % 11) as f64 / 11.0 - 0.45).collect())
            .collect();
        for s in op.subs.iter_mut() {
            s.b.iter_mut().for_each(|x| *x = 0.0);
        }
        op.apply(&forces, false, true);
        let v_loaded: Vec<Vec<f64>> = op.subs.iter().map(|s| s.v.clone()).collect();
        let jump_loaded: Vec<Vec<f64>> = op.ifaces.iter().map(|it| it.jump.clone()).collect();
        op.apply(&forces, false, false);
        let v: Vec<Vec<f64>> = op.subs.iter().map(|s| s.v.clone()).collect();
        let jumps: Vec<Vec<f64>> = op.ifaces.iter().map(|it| it.jump.clone()).collect();
        let max_diff = |a: &[Vec<f64>], b: &[Vec<f64>]| {
            a.iter()
                .flatten()
                .zip(b.iter().flatten())
                .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
        };
        let scale = v_loaded.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(scale > 0.0);
        let dv = max_diff(&v, &v_loaded);
        assert!(dv < 1e-10 * scale, "displacements differ by {dv:e} of {scale:e}");
        let dj = max_diff(&jumps, &jump_loaded);
        assert!(dj < 1e-10 * scale, "jumps differ by {dj:e}");
        let (m2, j2) = op.macro_part2(&jumps);
        assert!(
            j2 > 0.0 && m2.sqrt() < 1e-10 * j2.sqrt(),
            "macro part {:e} of {:e}",
            m2.sqrt(),
            j2.sqrt()
        );
    }

    /// Interface vectors of the given sizes from a seed.
    fn interface_vectors(sizes: impl Iterator<Item = usize>, seed: usize) -> Vec<Vec<f64>> {
        sizes
            .enumerate()
            .map(|(i, n)| {
                (0..n)
                    .map(|j| ((i * 31 + j * 7 + seed) % 13) as f64 / 13.0 - 0.4)
                    .collect()
            })
            .collect()
    }

    /// `P g` on every interface, `g` from a seed.
    fn macro_vectors(op: &InterfaceOperator<crate::comm::Seam>, seed: usize, scale: f64) -> Vec<Vec<f64>> {
        op.ifaces
            .iter()
            .enumerate()
            .map(|(i, it)| {
                let mut x = vec![0.0; it.p.nrows()];
                for q in 0..it.p.ncols() {
                    let g = scale * (((i * 5 + q * 3 + seed) % 7) as f64 - 3.0);
                    for (v, a) in x.iter_mut().zip(it.p.col(q).iter()) {
                        *v += g * a;
                    }
                }
                x
            })
            .collect()
    }

    /// The macro force error sees only the macro part of the jumps, and
    /// linearly: the forces of the coarse system whose right-hand side is
    /// that part.
    #[test]
    fn the_macro_force_error_measures_the_macro_part_of_the_jump() {
        let mut op = solver().op;
        let set = |op: &mut InterfaceOperator<crate::comm::Seam>, x: &[Vec<f64>]| {
            for (it, x) in op.ifaces.iter_mut().zip(x) {
                it.jump.copy_from_slice(x);
            }
        };
        let g = macro_vectors(&op, 2, 1e-3);
        set(&mut op, &g);
        let one = op.macro_force_error();
        assert!(one > 0.0 && one.is_finite());
        let g2: Vec<Vec<f64>> = g.iter().map(|x| x.iter().map(|v| 2.0 * v).collect()).collect();
        set(&mut op, &g2);
        let two = op.macro_force_error();
        assert!((two - 2.0 * one).abs() < 1e-10 * one, "{two:e} against 2 × {one:e}");
        // A jump without macro part: no macro force, whatever its size.
        let mut rest = interface_vectors(op.interface_sizes(), 5);
        for (x, it) in rest.iter_mut().zip(&op.ifaces) {
            remove_macro_part(x, &it.p);
        }
        set(&mut op, &rest);
        let none = op.macro_force_error();
        assert!(
            none < 1e-10 * one,
            "{none:e} for a jump without macro part ({one:e} with)"
        );
    }

    /// The coarse correction takes a displacement whose macro jump is off
    /// by `Z c` (self-equilibrated macro forces `c`, `Gᵀ c = 0`) back to
    /// the loaded step's, and leaves that one as it is: it is the loaded
    /// step's coarse condition `Pᵀ J V = 0` applied once more.
    #[test]
    fn the_coarse_correction_restores_the_loaded_step() {
        let mut op = solver().op;
        // c: the forces of a coarse solve with a macro right-hand side
        // only, so Gᵀ c = 0; that right-hand side the macro jump of some
        // displacement, so in the range of `Wᵀ` (the pair forces that
        // circulate around cross points are null directions of L and G).
        let vr: Vec<Vec<f64>> = op
            .subs
            .iter()
            .enumerate()
            .map(|(k, s)| {
                (0..s.v.len())
                    .map(|j| ((k * 13 + j * 7) % 17) as f64 / 17.0 - 0.5)
                    .collect()
            })
            .collect();
        op.jumps(Some(&vr));
        assert!(op.macro_force_error() > 0.0);
        let c = op.coarse.as_ref().unwrap().macro_forces().to_vec();
        let forces = interface_vectors(op.interface_sizes(), 1);
        op.apply(&forces, false, true);
        let v0: Vec<Vec<f64>> = op.subs.iter().map(|s| s.v.clone()).collect();
        let scale = v0.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
        let max_diff = |op: &InterfaceOperator<crate::comm::Seam>| {
            op.subs
                .iter()
                .zip(&v0)
                .flat_map(|(s, v0)| s.v.iter().zip(v0))
                .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
        };
        op.correct_macro_part();
        let d = max_diff(&op);
        assert!(d < 1e-12 * scale, "an exact step moved by {d:e} of {scale:e}");
        for s in op.subs.iter_mut() {
            for (k, &col) in s.macro_cols.iter().enumerate() {
                for (v, z) in s.v.iter_mut().zip(s.z.col(k).iter()) {
                    *v += z * c[col];
                }
            }
        }
        op.jumps(None);
        let jumps: Vec<Vec<f64>> = op.ifaces.iter().map(|it| it.jump.clone()).collect();
        let (before, _) = op.macro_part2(&jumps);
        let moved = max_diff(&op);
        assert!(moved > 1e-3 * scale, "the perturbation moved V by {moved:e} only");
        op.correct_macro_part();
        let jumps: Vec<Vec<f64>> = op.ifaces.iter().map(|it| it.jump.clone()).collect();
        let (after, _) = op.macro_part2(&jumps);
        assert!(
            after.sqrt() < 1e-10 * before.sqrt(),
            "macro jump {:e} -> {:e}",
            before.sqrt(),
            after.sqrt()
        );
        let d = max_diff(&op);
        assert!(
            d < 1e-10 * scale,
            "{d:e} off the loaded step ({moved:e} before the correction)"
        );
    }

    #[test]
    fn ghost_buffers_give_the_same_bits_as_threads() {
        let mut set_up = solver();
        let ws = set_up.cg.take().expect("a cg set-up has its workspace");
        let mut local = set_up.op;
        let InterfaceOperator {
            subs,
            ifaces,
            coarse,
            comm,
            entry_inv_mult,
        } = solver().op;
        let ghosts = Ghosts {
            ends: ifaces.iter().map(|it| (it.lo, it.hi)).collect(),
            iface_dofs: subs.iter().map(|s| s.iface_dofs.clone()).collect(),
            inner: comm,
        };
        let mut ghost = InterfaceOperator {
            subs,
            ifaces,
            coarse,
            comm: ghosts,
            entry_inv_mult,
        };
        assert!(local.coarse.is_some() && local.ifaces.len() > 4);
        let sizes: Vec<usize> = local.interface_sizes().collect();
        let vec_of = |seed: usize| interface_vectors(sizes.iter().copied(), seed);
        for (a, b) in local.subs.iter_mut().zip(ghost.subs.iter_mut()) {
            for (l, (x, y)) in a.b.iter_mut().zip(b.b.iter_mut()).enumerate() {
                *x = (l % 5) as f64 - 2.0;
                *y = *x;
            }
        }
        let forces = vec_of(1);
        for load in [true, false] {
            local.apply(&forces, false, load);
            ghost.apply(&forces, false, load);
            for (a, b) in local.ifaces.iter().zip(&ghost.ifaces) {
                assert!(same(&a.jump, &b.jump));
            }
            for (a, b) in local.subs.iter().zip(&ghost.subs) {
                assert!(same(&a.v, &b.v));
            }
            assert_eq!(local.jump_norms2(), ghost.jump_norms2());
            assert_eq!(local.v_norm2().to_bits(), ghost.v_norm2().to_bits());
        }
        // The macro force error of the last (homogeneous) jumps.
        assert_eq!(local.macro_force_error().to_bits(), ghost.macro_force_error().to_bits());
        // The force stage and the preconditioner.
        let (mut fa, mut fb) = (vec_of(2), vec_of(2));
        local.force_stage(&mut fa, 0.3);
        ghost.force_stage(&mut fb, 0.3);
        assert!(fa.iter().zip(&fb).all(|(a, b)| same(a, b)));
        // The preconditioner with the set-up's weights: deluxe on the faces
        // and at the cross points.
        assert!(ws.deluxe.iter().flatten().any(|d| d.d_lo.is_empty()));
        assert!(ws.deluxe.iter().flatten().any(|d| !d.d_lo.is_empty()));
        let (mut da, mut db) = (ws.deluxe.clone(), ws.deluxe.clone());
        let (mut sla, mut sha, mut slb, mut shb) = (vec_of(0), vec_of(0), vec_of(0), vec_of(0));
        let r = vec_of(3);
        let (mut za, mut zb) = (vec_of(0), vec_of(0));
        local.precondition(&r, &ws.w, &mut da, &mut sla, &mut sha, &mut za);
        ghost.precondition(&r, &ws.w, &mut db, &mut slb, &mut shb, &mut zb);
        assert!(za.iter().zip(&zb).all(|(a, b)| same(a, b)));
        assert!(za.iter().flatten().all(|x| x.is_finite()) && za.iter().flatten().any(|&x| x != 0.0));
        assert_eq!(local.dot(&r, &za).to_bits(), ghost.dot(&r, &zb).to_bits());
        // Jumps of given displacements.
        let v: Vec<Vec<f64>> = local
            .subs
            .iter()
            .map(|s| s.v.iter().map(|x| 2.0 * x).collect())
            .collect();
        local.jumps(Some(&v));
        ghost.jumps(Some(&v));
        for (a, b) in local.ifaces.iter().zip(&ghost.ifaces) {
            assert!(same(&a.jump, &b.jump));
        }
    }
}
