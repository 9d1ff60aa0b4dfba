//! The mechanical model of docs/design.md §1, built once from a validated scene:
//! free-dof numbering, element geometry (`n_e`, `L_e`, `k_e = EA/L`,
//! prestrain `e0 = t0/k`) and the effects that are actually simulated.
//!
//! Everything downstream (direct solver, decomposition, subdomain operators)
//! works on the free dofs numbered here; blocked components carry [`FIXED`].

use crate::error::{Error, Result};
use crate::scene::{Effects, ElementKind, Scene};
use faer::sparse::SparseColMat;

/// Marker for a blocked (supported) displacement component.
pub const FIXED: usize = usize::MAX;

/// One element of the truss, with everything the solvers need precomputed.
#[derive(Debug, Clone)]
pub struct Element {
    pub a: usize,
    pub b: usize,
    /// Unit vector from `a` to `b`.
    pub dir: [f64; 3],
    pub length: f64,
    /// Axial stiffness `EA / L`.
    pub k: f64,
    /// Prestress (tension positive); 0 when the `prestress` effect is off.
    pub t0: f64,
    /// Prestrain `t0 / k`.
    pub e0: f64,
    pub kind: ElementKind,
    /// True for a cable when `unilateral_cables` is simulated.
    pub unilateral: bool,
    /// Transverse geometric stiffness `t0 / L` (0 unless `geometric_stiffness`).
    pub geo: f64,
}

impl Element {
    /// The axial force `k (e + e0)` at elongation `e` (tension positive),
    /// as if the element were taut.
    pub fn tension(&self, elongation: f64) -> f64 {
        self.k * (elongation + self.e0)
    }

    /// The 3×3 block `k n nᵀ + g (I − n nᵀ)`; the element matrix is
    /// `[[G, −G], [−G, G]]` on the dofs of `(a, b)`.
    pub fn block(&self) -> [[f64; 3]; 3] {
        self.block_with_axial(self.k)
    }

    /// [`Self::block`] with axial stiffness `k` instead of the element's
    /// own: `k n nᵀ + g (I − n nᵀ)`. A slack cable is `k = 0`: it keeps its
    /// geometric stiffness, which comes from the prestress `t0` and is part
    /// of the `K` that never changes as cables go slack (docs/design.md §1).
    pub fn block_with_axial(&self, k: f64) -> [[f64; 3]; 3] {
        let n = self.dir;
        let mut g = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                let nn = n[i] * n[j];
                let id = if i == j { 1.0 } else { 0.0 };
                g[i][j] = k * nn + self.geo * (id - nn);
            }
        }
        g
    }
}

/// The assembled-free description of the structure.
#[derive(Debug, Clone)]
pub struct Model {
    pub name: String,
    pub coords: Vec<[f64; 3]>,
    /// Free-dof index of each node component, or [`FIXED`].
    pub node_dofs: Vec<[usize; 3]>,
    pub n_free: usize,
    /// `3 · node + component` of each free dof.
    pub dof_node: Vec<usize>,
    pub elements: Vec<Element>,
    /// The effects that are simulated (declared and applicable).
    pub effects: Effects,
    /// Declared effects that were not applied, and why.
    pub notes: Vec<String>,
    /// Indices of the unilateral cables, in element order.
    pub cables: Vec<usize>,
    /// External nodal forces on free dofs, one vector per load case
    /// (case 0 is `[loads]` plus self-weight).
    pub load_cases: Vec<Vec<f64>>,
    /// Names of the load cases.
    pub load_case_names: Vec<String>,
}

impl Model {
    /// Validates the scene and builds the model.
    pub fn from_scene(scene: &Scene) -> Result<Model> {
        scene.validate()?;
        let nn = scene.nodes.x.len();
        let coords: Vec<[f64; 3]> = (0..nn)
            .map(|i| [scene.nodes.x[i], scene.nodes.y[i], scene.nodes.z[i]])
            .collect();

        let mut blocked = vec![[false; 3]; nn];
        for (i, (&node, dofs)) in scene.supports.node.iter().zip(&scene.supports.dofs).enumerate() {
            for c in dofs.chars() {
                let d = match c {
                    'x' => 0,
                    'y' => 1,
                    'z' => 2,
                    _ => {
                        return Err(Error::input(
                            "supports.dofs",
                            Some(i),
                            format!("unknown component '{c}' (expected any of x, y, z)"),
                        ))
                    }
                };
                blocked[node][d] = true;
            }
        }
        // A node no element touches has no stiffness at all: name it here,
        // before a factorization reports an anonymous zero pivot.
        let mut used = vec![false; nn];
        for (&a, &b) in scene.elements.a.iter().zip(&scene.elements.b) {
            used[a] = true;
            used[b] = true;
        }
        let mut node_dofs = vec![[FIXED; 3]; nn];
        let mut dof_node = Vec::with_capacity(3 * nn);
        let mut n_free = 0;
        for i in 0..nn {
            for d in 0..3 {
                if !blocked[i][d] {
                    if !used[i] {
                        return Err(Error::Mechanism(format!(
                            "node {i} is attached to no element and not fully supported"
                        )));
                    }
                    node_dofs[i][d] = n_free;
                    dof_node.push(3 * i + d);
                    n_free += 1;
                }
            }
        }

        let mut effects = scene.effects;
        let mut notes = Vec::new();
        let ne = scene.elements.a.len();
        let has_cables = scene.elements.kind.contains(&ElementKind::Cable);
        let t0_of = |e: usize| scene.elements.t0.get(e).copied().unwrap_or(0.0);
        let has_t0 = (0..ne).any(|e| t0_of(e) != 0.0);
        if effects.unilateral_cables && !has_cables {
            effects.unilateral_cables = false;
            notes.push("unilateral_cables declared but the scene has no cables: cable stage not run".into());
        }
        if effects.prestress && !has_t0 {
            effects.prestress = false;
            notes.push("prestress declared but every t0 is zero: no prestrain load".into());
        }
        if effects.geometric_stiffness && !has_t0 {
            effects.geometric_stiffness = false;
            notes.push("geometric_stiffness declared but every t0 is zero: K_G is zero".into());
        }

        let mut elements = Vec::with_capacity(ne);
        let mut cables = Vec::new();
        for e in 0..ne {
            let (a, b) = (scene.elements.a[e], scene.elements.b[e]);
            let d = [
                coords[b][0] - coords[a][0],
                coords[b][1] - coords[a][1],
                coords[b][2] - coords[a][2],
            ];
            let length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let dir = [d[0] / length, d[1] / length, d[2] / length];
            let k = scene.elements.ea[e] / length;
            let kind = scene.elements.kind[e];
            let t0 = t0_of(e);
            let (t0_eff, e0) = if effects.prestress { (t0, t0 / k) } else { (0.0, 0.0) };
            let geo = if effects.geometric_stiffness { t0 / length } else { 0.0 };
            let unilateral = effects.unilateral_cables && kind == ElementKind::Cable;
            if unilateral {
                cables.push(e);
            }
            elements.push(Element {
                a,
                b,
                dir,
                length,
                k,
                t0: t0_eff,
                e0,
                kind,
                unilateral,
                geo,
            });
        }

        let mut model = Model {
            name: scene.scene.name.clone(),
            coords,
            node_dofs,
            n_free,
            dof_node,
            elements,
            effects,
            notes,
            cables,
            load_cases: Vec::new(),
            load_case_names: Vec::new(),
        };

        let mut f0 = model.nodal_forces(&scene.loads.node, &scene.loads.fx, &scene.loads.fy, &scene.loads.fz);
        if effects.self_weight {
            let g = scene.scene.gravity.unwrap_or([0.0, 0.0, -9.81]);
            for e in 0..ne {
                let el = &model.elements[e];
                let w = scene.elements.mass_per_length[e] * el.length * 0.5;
                for node in [el.a, el.b] {
                    for d in 0..3 {
                        let dof = model.node_dofs[node][d];
                        if dof != FIXED {
                            f0[dof] += w * g[d];
                        }
                    }
                }
            }
        }
        model.load_cases.push(f0);
        model.load_case_names.push("loads".into());
        for lc in &scene.load_cases {
            let f = model.nodal_forces(&lc.node, &lc.fx, &lc.fy, &lc.fz);
            model.load_cases.push(f);
            model.load_case_names.push(lc.name.clone());
        }
        Ok(model)
    }

    /// Free-dof vector of nodal forces; missing component arrays count as 0.
    pub fn nodal_forces(&self, node: &[usize], fx: &[f64], fy: &[f64], fz: &[f64]) -> Vec<f64> {
        let mut f = vec![0.0; self.n_free];
        for (i, &n) in node.iter().enumerate() {
            let comp = [fx.get(i), fy.get(i), fz.get(i)];
            for d in 0..3 {
                let dof = self.node_dofs[n][d];
                if dof != FIXED {
                    f[dof] += comp[d].copied().unwrap_or(0.0);
                }
            }
        }
        f
    }

    /// The 6 free-dof indices of element `e` (`a` then `b`), [`FIXED`] if blocked.
    #[inline]
    pub fn element_dofs(&self, e: usize) -> [usize; 6] {
        let el = &self.elements[e];
        let (da, db) = (self.node_dofs[el.a], self.node_dofs[el.b]);
        [da[0], da[1], da[2], db[0], db[1], db[2]]
    }

    /// Right-hand side `b = f − Σ_e H_e k_e e0_e` for an external force `f`.
    pub fn rhs(&self, f_ext: &[f64]) -> Vec<f64> {
        let mut b = f_ext.to_vec();
        if self.effects.prestress {
            for e in 0..self.elements.len() {
                let el = &self.elements[e];
                self.add_h(e, -el.k * el.e0, &mut b);
            }
        }
        b
    }

    /// `out += H_e * coef` on free dofs (nodal forces of a unit tension).
    #[inline]
    pub fn add_h(&self, e: usize, coef: f64, out: &mut [f64]) {
        let dofs = self.element_dofs(e);
        let n = self.elements[e].dir;
        for d in 0..3 {
            if dofs[d] != FIXED {
                out[dofs[d]] -= n[d] * coef;
            }
            if dofs[3 + d] != FIXED {
                out[dofs[3 + d]] += n[d] * coef;
            }
        }
    }

    /// Elongation `e = n · (u_b − u_a)` from a free-dof displacement.
    #[inline]
    pub fn elongation(&self, e: usize, u: &[f64]) -> f64 {
        self.elongation_by(e, |d| u[d])
    }

    /// [`Self::elongation`] with the displacement of each free dof of the
    /// element read by `u` (e.g. from one subdomain's copy).
    pub fn elongation_by(&self, e: usize, u: impl Fn(usize) -> f64) -> f64 {
        let dofs = self.element_dofs(e);
        let n = self.elements[e].dir;
        // Differences first: `u_b − u_a` is exact-rounded however large the
        // displacements, where `n·u_b − n·u_a` loses `ε |u|` to cancellation.
        let at = |d: usize| if d == FIXED { 0.0 } else { u(d) };
        let mut s = 0.0;
        for d in 0..3 {
            s += n[d] * (at(dofs[3 + d]) - at(dofs[d]));
        }
        s
    }

    /// Lower-triangle triplets `(row, col, value)` of the stiffness of the
    /// given elements, in the numbering `local(dof)` (None = not in this matrix).
    pub fn stiffness_triplets(
        &self,
        elements: &[usize],
        local: impl Fn(usize) -> Option<usize>,
    ) -> Vec<(usize, usize, f64)> {
        self.stiffness_triplets_with_axial(elements, local, 1.0)
    }

    /// [`Self::stiffness_triplets`] with every element's axial stiffness
    /// scaled by `axial` and its geometric stiffness kept: what slack
    /// (`axial = 0`) or softened cables still contribute to `K`.
    pub fn stiffness_triplets_with_axial(
        &self,
        elements: &[usize],
        local: impl Fn(usize) -> Option<usize>,
        axial: f64,
    ) -> Vec<(usize, usize, f64)> {
        let mut t = Vec::with_capacity(elements.len() * 21);
        for &e in elements {
            self.for_each_stiffness_entry(e, &local, axial, |r, c, v| t.push((r, c, v)));
        }
        t
    }

    /// The lower-triangle entries `(row, col, value)` of element `e`'s
    /// stiffness (axial part scaled by `axial`, geometric part kept), in the
    /// numbering `local(dof)`, always in the same order: the order of
    /// [`Self::stiffness_triplets`] and of [`StiffnessScatter`]'s positions.
    fn for_each_stiffness_entry(
        &self,
        e: usize,
        local: impl Fn(usize) -> Option<usize>,
        axial: f64,
        mut entry: impl FnMut(usize, usize, f64),
    ) {
        let el = &self.elements[e];
        let g = el.block_with_axial(axial * el.k);
        let dofs = self.element_dofs(e);
        let loc: [Option<usize>; 6] = std::array::from_fn(|i| if dofs[i] == FIXED { None } else { local(dofs[i]) });
        for i in 0..6 {
            let Some(r) = loc[i] else { continue };
            for j in 0..6 {
                let Some(c) = loc[j] else { continue };
                if r < c {
                    continue;
                }
                let s = if (i < 3) == (j < 3) { 1.0 } else { -1.0 };
                entry(r, c, s * g[i % 3][j % 3]);
            }
        }
    }

    /// Where every element's stiffness entries fall among the values of
    /// `k`, the lower triangle of the whole structure's stiffness (free
    /// dofs) as [`crate::factor::lower_csc`] assembles it from
    /// [`Self::stiffness_triplets`] of all elements.
    pub fn stiffness_scatter(&self, k: &SparseColMat<usize, f64>) -> StiffnessScatter {
        let (col_ptr, row_idx) = (k.symbolic().col_ptr(), k.symbolic().row_idx());
        let mut positions = Vec::with_capacity(self.elements.len() * 21);
        for e in 0..self.elements.len() {
            self.for_each_stiffness_entry(e, Some, 1.0, |r, c, _| {
                let col = &row_idx[col_ptr[c]..col_ptr[c + 1]];
                let at = col
                    .binary_search(&r)
                    .expect("every element entry is in the assembled pattern");
                positions.push(col_ptr[c] + at);
            });
        }
        StiffnessScatter { positions }
    }

    /// The values of the whole structure's stiffness (the pattern
    /// `scatter` was made for) with each element's axial stiffness scaled
    /// by `axial(e)`: assembled in place, without the triplets and the
    /// sort of a fresh assembly (the direct active set's refactorizations).
    pub fn stiffness_values_into(&self, scatter: &StiffnessScatter, axial: impl Fn(usize) -> f64, values: &mut [f64]) {
        values.iter_mut().for_each(|v| *v = 0.0);
        let mut at = scatter.positions.iter();
        for e in 0..self.elements.len() {
            self.for_each_stiffness_entry(e, Some, axial(e), |_, _, v| {
                values[*at.next().expect("one position per entry")] += v;
            });
        }
    }

    /// Slack flag per element: a cable is slack when its slack `λ` exceeds
    /// `rel` times the cables' strain scale, the largest `|e + e0|` among
    /// them (the scale the active sets measure violations on). The
    /// threshold keeps cables at zero strain (a structural zero, where `λ`
    /// is round-off of either sign) from flipping between methods; their
    /// tension is 0 either way. (Against the largest displacement instead,
    /// a plate's deflection, 2.5e3 on the 80² grid against slacks below 1,
    /// hid the slack cables of iterative solves from a tolerance of 1e-5
    /// on: `slack 0 of 38241 cables` at 1e-3 where 8 960 are.)
    pub fn slack_flags(&self, u: &[f64], lambda: &[f64], rel: f64) -> Vec<bool> {
        let scale = self
            .cables
            .iter()
            .map(|&e| (self.elongation(e, u) + self.elements[e].e0).abs())
            .fold(0.0f64, f64::max);
        let tau = rel * scale;
        let mut slack = vec![false; self.elements.len()];
        for (c, &e) in self.cables.iter().enumerate() {
            slack[e] = lambda[c] > tau;
        }
        slack
    }

    /// Tensions from displacements and slack flags: a slack cable reports
    /// exactly 0, a taut cable never pushes.
    pub fn tensions_with_slack(&self, u: &[f64], slack: &[bool]) -> Vec<f64> {
        let elongations: Vec<f64> = (0..self.elements.len()).map(|e| self.elongation(e, u)).collect();
        self.tensions_from_elongations(&elongations, slack)
    }

    /// [`Self::tensions_with_slack`] from given element elongations.
    pub fn tensions_from_elongations(&self, elongations: &[f64], slack: &[bool]) -> Vec<f64> {
        (0..self.elements.len())
            .map(|e| {
                let el = &self.elements[e];
                let t = el.tension(elongations[e]);
                if !el.unilateral {
                    t
                } else if slack[e] {
                    0.0
                } else {
                    t.max(0.0)
                }
            })
            .collect()
    }

    /// How far tensions miss equilibrium with the external forces `f_ext`:
    /// `‖f_ext − Σ_e H_e t_e − K_G u‖ / ‖t‖` over the free dofs, with `K_G`
    /// the geometric stiffness (zero unless simulated) at the displacements
    /// `u`. Exact tensions give round-off (the direct solver 7e-14 to 5e-11
    /// on the benchmark scenes, 1.6e-9 at a stiffness contrast of 1e6).
    /// `None` where nothing is loaded.
    pub fn equilibrium_residual(&self, f_ext: &[f64], tensions: &[f64], u: &[f64]) -> Option<f64> {
        self.unbalanced_forces(f_ext, tensions, u).map(|(_, r)| r)
    }

    /// The nodal forces `f_ext − Σ_e H_e t_e − K_G u` the tensions (and the
    /// geometric stiffness at `u`) leave unbalanced (free dofs), with their
    /// relative size as in [`Self::equilibrium_residual`].
    pub fn unbalanced_forces(&self, f_ext: &[f64], tensions: &[f64], u: &[f64]) -> Option<(Vec<f64>, f64)> {
        let mut r = f_ext.to_vec();
        for (e, &t) in tensions.iter().enumerate() {
            self.add_h(e, -t, &mut r);
        }
        self.add_geometric_forces(u, -1.0, &mut r);
        let t_norm = tensions.iter().map(|t| t * t).sum::<f64>().sqrt();
        let r_norm = r.iter().map(|v| v * v).sum::<f64>().sqrt();
        (t_norm > 0.0 && r_norm.is_finite()).then(|| (r, r_norm / t_norm))
    }

    /// `out += coef K_G u`: each element's transverse geometric stiffness
    /// `g = t0 / L` (slack cables included: it comes from the prestress),
    /// the force `g (I − n nᵀ)(u_b − u_a)` on node `b` and its opposite
    /// on `a`. Nothing where the effect is off.
    pub fn add_geometric_forces(&self, u: &[f64], coef: f64, out: &mut [f64]) {
        for (e, el) in self.elements.iter().enumerate() {
            if el.geo == 0.0 {
                continue;
            }
            let dofs = self.element_dofs(e);
            let at = |i: usize| if dofs[i] == FIXED { 0.0 } else { u[dofs[i]] };
            let d: [f64; 3] = std::array::from_fn(|c| at(3 + c) - at(c));
            let dn: f64 = (0..3).map(|c| d[c] * el.dir[c]).sum();
            for c in 0..3 {
                let p = coef * el.geo * (d[c] - dn * el.dir[c]);
                if dofs[3 + c] != FIXED {
                    out[dofs[3 + c]] += p;
                }
                if dofs[c] != FIXED {
                    out[dofs[c]] -= p;
                }
            }
        }
    }

    /// Tensions from displacements and cable slacks (λ indexed like `cables`):
    /// a cable with `λ > 0` is slack and reports exactly 0.
    pub fn tensions(&self, u: &[f64], lambda: &[f64]) -> Vec<f64> {
        self.tensions_with_slack(u, &self.slack_flags(u, lambda, 0.0))
    }

    /// Per-node displacements (zeros on blocked components).
    pub fn node_displacements(&self, u: &[f64]) -> Vec<[f64; 3]> {
        self.node_dofs
            .iter()
            .map(|d| std::array::from_fn(|i| if d[i] == FIXED { 0.0 } else { u[d[i]] }))
            .collect()
    }

    /// Node owning free dof `dof` and its component.
    #[inline]
    pub fn dof_owner(&self, dof: usize) -> (usize, usize) {
        let k = self.dof_node[dof];
        (k / 3, k % 3)
    }

    /// Whether some element is a strut: compressed, with geometric
    /// stiffness, so its transverse stiffness is negative and a subdomain
    /// holding it without the cables that stabilise it can be indefinite
    /// where the whole structure is not.
    pub fn has_struts(&self) -> bool {
        self.elements.iter().any(|el| el.geo < 0.0)
    }

    /// A displacement scale for relative measures: the largest element length.
    pub fn length_scale(&self) -> f64 {
        self.elements.iter().map(|e| e.length).fold(0.0, f64::max)
    }
}

/// The value position of every element stiffness entry in an assembled
/// lower-triangle matrix ([`Model::stiffness_scatter`]).
pub struct StiffnessScatter {
    positions: Vec<usize>,
}
