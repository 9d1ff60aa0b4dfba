//! Scene generators: double-layer grids, tensegrity grids and lattice towers.
//!
//! Each generator is a pure function from a parameter struct (with
//! [`Default`]) to a [`Scene`]: no I/O, no randomness, so the same parameters
//! always give the same scene (the bundled scenes in `scenes/` are checked
//! against them). Every generator runs in time and memory linear in the size
//! of the scene — one pass over nodes and one over elements, arrays reserved
//! up front — because the scenes go from a few elements to millions of dofs.
//!
//! Node and element numbering is part of each generator's documentation:
//! tests, reference scenes (`tests/data/reference`) and users rely on it.
//!
//! [`by_name`] builds a scene from a kind and `key=value` strings for the
//! command line; [`bundled`] lists the scenes shipped in `scenes/`.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::scene::{Effects, Method, Scene, SceneBuilder, SolverSettings};

/// Euclidean distance between two points.
fn length(p: [f64; 3], q: [f64; 3]) -> f64 {
    ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) + (q[2] - p[2]).powi(2)).sqrt()
}

// ---------------------------------------------------------------------------
// Double-layer grid
// ---------------------------------------------------------------------------

/// Parameters of [`grid`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GridParams {
    /// Cells in x.
    pub nx: usize,
    /// Cells in y.
    pub ny: usize,
    /// Cell size (top chord length).
    pub cell: f64,
    /// Distance between the two layers.
    pub depth: f64,
    /// Axial rigidity of the web bars (see `uniform_stiffness`).
    pub ea_bar: f64,
    /// Axial rigidity of the cables (see `uniform_stiffness`).
    pub ea_cable: f64,
    /// When true (default), each element's `ea` is scaled by `L / cell`, so
    /// every bar has the axial stiffness `k = ea_bar / cell` and every cable
    /// `k = ea_cable / cell` whatever its length. This is the convention of
    /// the measurements of the design brief (k_bar = 1e3, k_cable = 1e2) and of
    /// the reference scene `grid4-slack`. When false, `ea` is used as given.
    pub uniform_stiffness: bool,
    /// Prestress (tension) of every cable. Bars get no prestress, so the
    /// prestress is not self-equilibrated: it acts as a load
    /// `−Σ H t0` on the supported grid (a pretensioned cable net
    /// pulling on its webs), as in `grid4-slack`. 0 switches the `prestress`
    /// effect off.
    pub t0: f64,
    /// Downward force on each interior top node (`fz = −load`).
    pub load: f64,
    /// Cables go slack (`effects.unilateral_cables`).
    pub unilateral: bool,
}

impl Default for GridParams {
    fn default() -> Self {
        GridParams {
            nx: 4,
            ny: 4,
            cell: 1.0,
            depth: 1.0,
            ea_bar: 1e3,
            ea_cable: 1e2,
            uniform_stiffness: true,
            t0: 0.0,
            load: 1.0,
            unilateral: true,
        }
    }
}

impl GridParams {
    /// Number of nodes: `(nx+1)(ny+1)` top plus `nx·ny` bottom.
    pub fn n_nodes(&self) -> usize {
        (self.nx + 1) * (self.ny + 1) + self.nx * self.ny
    }

    /// Number of elements: top chords `nx(ny+1) + (nx+1)ny`, top diagonals
    /// `nx·ny`, bottom chords `(nx−1)ny + nx(ny−1)`, bottom diagonals
    /// `(nx−1)(ny−1)`, webs `4·nx·ny`.
    pub fn n_elements(&self) -> usize {
        let (nx, ny) = (self.nx, self.ny);
        let (mx, my) = (nx.saturating_sub(1), ny.saturating_sub(1));
        nx * (ny + 1) + (nx + 1) * ny + nx * ny + mx * ny + nx * my + mx * my + 4 * nx * ny
    }
}

/// Double-layer grid of `nx × ny` square cells, the structure of the paper's
/// examples and of the reference scene `grid4-slack` (generated with
/// `nx = ny = 4, t0 = 0.1, load = 4`, identical node and element order).
///
/// Geometry (`c = cell`, `h = depth`):
/// - top nodes `(i, j)`, `0 ≤ i ≤ nx`, `0 ≤ j ≤ ny`, at `(i c, j c, h)`,
///   index `i (ny+1) + j`;
/// - bottom nodes `(i, j)`, `0 ≤ i < nx`, `0 ≤ j < ny`, at the cell centres
///   `((i+½) c, (j+½) c, 0)`, index `(nx+1)(ny+1) + i ny + j`.
///
/// Elements, in this order:
/// 1. top chords (cables): for each top node in index order, the chord to
///    `(i+1, j)` then the chord to `(i, j+1)`;
/// 2. per cell `(i, j)` in bottom-node order: the top diagonal
///    `(i, j)–(i+1, j+1)` (cable); from its bottom node the bottom chord to
///    `(i+1, j)`, the bottom diagonal to `(i+1, j+1)` and the bottom chord to
///    `(i, j+1)` where they exist (cables); the four webs to the top corners
///    `(i, j), (i+1, j), (i, j+1), (i+1, j+1)` (bars).
///
/// Every top boundary node is blocked `"xyz"`; each interior top node carries
/// `fz = −load`. With all elements bilateral the grid is stiff (no
/// mechanism): each bottom node hangs from four non-coplanar webs and the
/// triangulated top layer is held by its boundary.
pub fn grid(p: &GridParams) -> Scene {
    let (nx, ny, c, h) = (p.nx, p.ny, p.cell, p.depth);
    let name = format!("grid-{nx}x{ny}");
    let mut b = SceneBuilder::with_capacity(name, p.n_nodes(), p.n_elements());
    let top = |i: usize, j: usize| i * (ny + 1) + j;
    let n_top = (nx + 1) * (ny + 1);
    let bot = |i: usize, j: usize| n_top + i * ny + j;
    let mut pos = Vec::with_capacity(p.n_nodes());
    for i in 0..=nx {
        for j in 0..=ny {
            pos.push([i as f64 * c, j as f64 * c, h]);
        }
    }
    for i in 0..nx {
        for j in 0..ny {
            pos.push([(i as f64 + 0.5) * c, (j as f64 + 0.5) * c, 0.0]);
        }
    }
    for q in &pos {
        b.node(q[0], q[1], q[2]);
    }
    let scale = |ea: f64, n0: usize, n1: usize| {
        if p.uniform_stiffness {
            ea * length(pos[n0], pos[n1]) / c
        } else {
            ea
        }
    };
    let cable = |b: &mut SceneBuilder, n0: usize, n1: usize| {
        let e = b.cable(n0, n1, scale(p.ea_cable, n0, n1));
        if p.t0 != 0.0 {
            b.prestress(e, p.t0);
        }
    };
    for i in 0..=nx {
        for j in 0..=ny {
            if i < nx {
                cable(&mut b, top(i, j), top(i + 1, j));
            }
            if j < ny {
                cable(&mut b, top(i, j), top(i, j + 1));
            }
        }
    }
    for i in 0..nx {
        for j in 0..ny {
            let o = bot(i, j);
            cable(&mut b, top(i, j), top(i + 1, j + 1));
            if i + 1 < nx {
                cable(&mut b, o, bot(i + 1, j));
            }
            if i + 1 < nx && j + 1 < ny {
                cable(&mut b, o, bot(i + 1, j + 1));
            }
            if j + 1 < ny {
                cable(&mut b, o, bot(i, j + 1));
            }
            for t in [top(i, j), top(i + 1, j), top(i, j + 1), top(i + 1, j + 1)] {
                b.bar(o, t, scale(p.ea_bar, o, t));
            }
        }
    }
    for i in 0..=nx {
        for j in 0..=ny {
            if i == 0 || i == nx || j == 0 || j == ny {
                b.support(top(i, j), "xyz");
            }
        }
    }
    for i in 1..nx {
        for j in 1..ny {
            b.load(top(i, j), [0.0, 0.0, -p.load]);
        }
    }
    b.effects(Effects {
        unilateral_cables: p.unilateral,
        prestress: p.t0 != 0.0,
        ..Effects::default()
    });
    b.build()
}

// ---------------------------------------------------------------------------
// Tensegrity grid
// ---------------------------------------------------------------------------

/// Parameters of [`tensegrity`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TensegrityParams {
    /// Modules in x.
    pub nx: usize,
    /// Modules in y.
    pub ny: usize,
    /// Module size (side of the bottom square).
    pub cell: f64,
    /// Height between the bottom and the top layer.
    pub depth: f64,
    /// Axial rigidity of the struts.
    pub ea_bar: f64,
    /// Axial rigidity of the cables.
    pub ea_cable: f64,
    /// Prestress level: the force density of the self-stress is `t0 / cell`
    /// (see [`tensegrity`] for the resulting tensions). Must be positive for
    /// the grid to be stable: without prestress it is a mechanism.
    pub t0: f64,
    /// Downward force on each top node (`fz = −load`).
    pub load: f64,
    /// Cables go slack (`effects.unilateral_cables`).
    pub unilateral: bool,
}

impl Default for TensegrityParams {
    fn default() -> Self {
        TensegrityParams {
            nx: 2,
            ny: 2,
            cell: 1.0,
            depth: 1.0,
            ea_bar: 1e3,
            ea_cable: 1e2,
            t0: 1.0,
            load: 0.1,
            unilateral: true,
        }
    }
}

impl TensegrityParams {
    /// Number of nodes: `(nx+1)(ny+1)` bottom corners plus
    /// `nx(ny+1) + (nx+1)ny` top edge midpoints.
    pub fn n_nodes(&self) -> usize {
        let (nx, ny) = (self.nx, self.ny);
        (nx + 1) * (ny + 1) + nx * (ny + 1) + (nx + 1) * ny
    }

    /// Number of elements: `nx(ny+1) + (nx+1)ny` bottom cables plus 12 per
    /// module (4 top cables, 4 vertical cables, 4 struts).
    pub fn n_elements(&self) -> usize {
        let (nx, ny) = (self.nx, self.ny);
        nx * (ny + 1) + (nx + 1) * ny + 12 * nx * ny
    }
}

/// Double-layer tensegrity grid of `nx × ny` four-strut modules
/// ("quadruplex", the 4-strut twisted prism), with self-stress.
///
/// One module over the square cell `[0, c]²` (`c = cell`, `h = depth`) has
/// four bottom nodes `B0..B3` at the corners `(0,0), (c,0), (c,c), (0,c)`
/// (z = 0) and four top nodes `T0..T3` at the midpoints of the cell edges
/// `(c/2,0), (c,c/2), (c/2,c), (0,c/2)` (z = h): the top square is the
/// bottom one turned by 45° and shrunk by √2. Its 16 members are
/// - bottom cables `B_k–B_{k+1}` (the cell edges),
/// - top cables `T_k–T_{k+1}`,
/// - vertical cables `B_k–T_k` (each spans 45° around the module axis),
/// - struts (bars) `B_k–T_{k+1}` (each spans 135°, the equilibrium twist
///   `π/2 + π/n` of an n-strut prism).
///
/// This prism carries the self-stress with force densities (tension / length)
/// `q` in top and vertical cables, `q/2` in bottom cables and `−q` in the
/// struts, for any `c` and `h` (checked node by node: at `B_k` the vertical
/// cable and the strut cancel vertically and, horizontally, together with the
/// two bottom cables; likewise at `T_k`). The generator uses `q = t0 / c`.
///
/// Modules are translated copies and share nodes: a bottom corner belongs to
/// up to four modules (up to four struts meet there, so this is a class-k
/// tensegrity grid, not a class-1 one), a top node to two, and a cell edge
/// is one bottom cable shared by the two modules on either side, with the
/// sum of their prestresses. The sum of the modules' self-stresses is a
/// self-stress of the grid, so `H t0 = 0`: the prestress deforms nothing
/// and only stiffens. Tensions, for `q = t0/c`:
/// bottom cable `t0` (interior) or `t0/2` (boundary), top cable `t0/√2`,
/// vertical cable `t0·√(c²/4 + h²)/c`, strut `−t0·√(5c²/4 + h²)/c`.
///
/// Stability: the four-strut prism alone is a mechanism without prestress
/// (three infinitesimal mechanisms; one is left once its bottom is blocked)
/// and is stabilised by the geometric stiffness `K_G` of its self-stress, so
/// `effects.geometric_stiffness` and `effects.prestress` are on. Adjacent
/// modules share three non-collinear nodes, which ties them together, and
/// every bottom boundary corner is blocked `"xyz"`, so `K + K_G` is positive
/// definite (tested for 1×1, 2×2, 3×2, 1×3). No bracing bars are added. To be
/// honest about what `K_G` does here: node sharing over-braces the assembled
/// grid (about 14 members per module for about 9 free dofs), so from 2×2 on,
/// with its boundary supports, the grid is already stiff without `K_G`, which
/// then raises the lowest eigenvalues of `K` by about 10%; only the 1×1 grid
/// depends on `K_G` to be stable. It needs `t0 > 0` and `ea_cable > t0`.
///
/// Numbering: bottom corners `(i, j)`, `0 ≤ i ≤ nx`, `0 ≤ j ≤ ny`, index
/// `i (ny+1) + j`; then top midpoints of x-edges `((i+½)c, j c, h)`, index
/// `(nx+1)(ny+1) + i (ny+1) + j`; then top midpoints of y-edges
/// `(i c, (j+½)c, h)`, index `(nx+1)(ny+1) + nx(ny+1) + i ny + j`.
/// Elements: the bottom cables (for each corner in index order, the edge to
/// `(i+1, j)` then to `(i, j+1)`), then per module `(i, j)`, i-major, the four
/// top cables, the four vertical cables and the four struts, each in `k`
/// order. Each top node carries `fz = −load`.
pub fn tensegrity(p: &TensegrityParams) -> Scene {
    let (nx, ny, c, h) = (p.nx, p.ny, p.cell, p.depth);
    let name = format!("tensegrity-{nx}x{ny}");
    let mut b = SceneBuilder::with_capacity(name, p.n_nodes(), p.n_elements());
    let corner = |i: usize, j: usize| i * (ny + 1) + j;
    let n_corner = (nx + 1) * (ny + 1);
    let xmid = |i: usize, j: usize| n_corner + i * (ny + 1) + j;
    let n_xmid = nx * (ny + 1);
    let ymid = |i: usize, j: usize| n_corner + n_xmid + i * ny + j;
    let mut pos = Vec::with_capacity(p.n_nodes());
    for i in 0..=nx {
        for j in 0..=ny {
            pos.push([i as f64 * c, j as f64 * c, 0.0]);
        }
    }
    for i in 0..nx {
        for j in 0..=ny {
            pos.push([(i as f64 + 0.5) * c, j as f64 * c, h]);
        }
    }
    for i in 0..=nx {
        for j in 0..ny {
            pos.push([i as f64 * c, (j as f64 + 0.5) * c, h]);
        }
    }
    for q in &pos {
        b.node(q[0], q[1], q[2]);
    }
    // Force density of the self-stress; tension = q · length.
    let q = p.t0 / c;
    let prestressed = p.t0 != 0.0;
    let add = |b: &mut SceneBuilder, n0: usize, n1: usize, strut: bool, density: f64| {
        let e = if strut {
            b.bar(n0, n1, p.ea_bar)
        } else {
            b.cable(n0, n1, p.ea_cable)
        };
        if prestressed {
            b.prestress(e, density * length(pos[n0], pos[n1]));
        }
    };
    // Bottom cables: q/2 from each module on either side of the edge.
    for i in 0..=nx {
        for j in 0..=ny {
            if i < nx {
                let sides = usize::from(j > 0) + usize::from(j < ny);
                add(&mut b, corner(i, j), corner(i + 1, j), false, 0.5 * q * sides as f64);
            }
            if j < ny {
                let sides = usize::from(i > 0) + usize::from(i < nx);
                add(&mut b, corner(i, j), corner(i, j + 1), false, 0.5 * q * sides as f64);
            }
        }
    }
    for i in 0..nx {
        for j in 0..ny {
            let bn = [corner(i, j), corner(i + 1, j), corner(i + 1, j + 1), corner(i, j + 1)];
            let tn = [xmid(i, j), ymid(i + 1, j), xmid(i, j + 1), ymid(i, j)];
            for k in 0..4 {
                add(&mut b, tn[k], tn[(k + 1) % 4], false, q);
            }
            for k in 0..4 {
                add(&mut b, bn[k], tn[k], false, q);
            }
            for k in 0..4 {
                add(&mut b, bn[k], tn[(k + 1) % 4], true, -q);
            }
        }
    }
    for i in 0..=nx {
        for j in 0..=ny {
            if i == 0 || i == nx || j == 0 || j == ny {
                b.support(corner(i, j), "xyz");
            }
        }
    }
    for t in n_corner..pos.len() {
        b.load(t, [0.0, 0.0, -p.load]);
    }
    b.effects(Effects {
        unilateral_cables: p.unilateral,
        prestress: prestressed,
        geometric_stiffness: prestressed,
        self_weight: false,
    });
    b.build()
}

// ---------------------------------------------------------------------------
// Lattice tower
// ---------------------------------------------------------------------------

/// Parameters of [`tower`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TowerParams {
    /// Cells in x.
    pub nx: usize,
    /// Cells in y.
    pub ny: usize,
    /// Cells (levels) in z.
    pub nz: usize,
    /// Horizontal cell size.
    pub cell: f64,
    /// Height of one level (absolute, not a factor of `cell`).
    pub height: f64,
    /// Axial rigidity of the bars (cell edges and body diagonals).
    pub ea_bar: f64,
    /// Axial rigidity of the cables (face diagonals).
    pub ea_cable: f64,
    /// Prestress (tension) of every cable; bars get none. 0 switches the
    /// `prestress` effect off.
    pub t0: f64,
    /// Lateral force `fx` on each top node.
    pub load: f64,
    /// Vertical force `fz` on each top node (negative is downwards).
    pub load_z: f64,
    /// Cables go slack (`effects.unilateral_cables`).
    pub unilateral: bool,
}

impl Default for TowerParams {
    fn default() -> Self {
        TowerParams {
            nx: 1,
            ny: 1,
            nz: 4,
            cell: 1.0,
            height: 1.3,
            ea_bar: 1e4,
            ea_cable: 1.0,
            t0: 0.0,
            load: 0.1,
            load_z: 0.0,
            unilateral: true,
        }
    }
}

impl TowerParams {
    /// Number of nodes: `(nx+1)(ny+1)(nz+1)`.
    pub fn n_nodes(&self) -> usize {
        (self.nx + 1) * (self.ny + 1) * (self.nz + 1)
    }

    /// Number of elements: edges `nx(ny+1)(nz+1) + (nx+1)ny(nz+1) +
    /// (nx+1)(ny+1)nz`, two cables per face `2[nx ny(nz+1) + nx(ny+1)nz +
    /// (nx+1)ny nz]`, one body diagonal per cell `nx ny nz`.
    pub fn n_elements(&self) -> usize {
        let (nx, ny, nz) = (self.nx, self.ny, self.nz);
        let edges = nx * (ny + 1) * (nz + 1) + (nx + 1) * ny * (nz + 1) + (nx + 1) * (ny + 1) * nz;
        let faces = nx * ny * (nz + 1) + nx * (ny + 1) * nz + (nx + 1) * ny * nz;
        edges + 2 * faces + nx * ny * nz
    }
}

/// Lattice tower of `nx × ny × nz` box cells (`cell × cell × height`), the
/// family of the reference scene `tower-small` (1×1×4, `height = 1.3`; same
/// node and element order and kinds, the reference's `ea` and `t0` vary per
/// element).
///
/// Node `(i, j, l)`, `0 ≤ i ≤ nx`, `0 ≤ j ≤ ny`, `0 ≤ l ≤ nz`, at
/// `(i cell, j cell, l height)`, index `l (nx+1)(ny+1) + j (nx+1) + i`.
///
/// Members: every cell edge is a bar; every cell face is braced by both of
/// its diagonals, which are cables (X-bracing: whichever way the shear goes,
/// one cable of each pair is in tension); every cell has one body diagonal
/// `(i, j, l)–(i+1, j+1, l+1)`, a bar. With the cables bilateral the lattice
/// is stiff; with slack cables the bars alone are a mechanism, which the
/// tension diagonals must stabilise — a hard nonsmooth case when
/// `ea_bar / ea_cable` is large (1e4 by default).
///
/// Elements are emitted node by node, in index order, each node `(i, j, l)`
/// listing the members that start there in the order: x edge, y edge,
/// z edge, diagonal to `(i+1, j+1, l)`, to `(i+1, j, l+1)`, to
/// `(i, j+1, l+1)`, anti-diagonal to `(i+1, j−1, l)`, to `(i+1, j, l−1)`,
/// to `(i, j+1, l−1)`, body diagonal — each where it exists.
///
/// Nodes at `z = 0` are blocked `"xyz"`; each top node carries
/// `fx = load`, `fz = load_z`.
pub fn tower(p: &TowerParams) -> Scene {
    let (nx, ny, nz) = (p.nx, p.ny, p.nz);
    let name = format!("tower-{nx}x{ny}x{nz}");
    let mut b = SceneBuilder::with_capacity(name, p.n_nodes(), p.n_elements());
    let (sx, sl) = (nx + 1, (nx + 1) * (ny + 1));
    let id = |i: usize, j: usize, l: usize| l * sl + j * sx + i;
    for l in 0..=nz {
        for j in 0..=ny {
            for i in 0..=nx {
                b.node(i as f64 * p.cell, j as f64 * p.cell, l as f64 * p.height);
            }
        }
    }
    let prestressed = p.t0 != 0.0;
    let cable = |b: &mut SceneBuilder, n0: usize, n1: usize| {
        let e = b.cable(n0, n1, p.ea_cable);
        if prestressed {
            b.prestress(e, p.t0);
        }
    };
    for l in 0..=nz {
        for j in 0..=ny {
            for i in 0..=nx {
                let n = id(i, j, l);
                let (xi, yj, zl) = (i < nx, j < ny, l < nz);
                if xi {
                    b.bar(n, id(i + 1, j, l), p.ea_bar);
                }
                if yj {
                    b.bar(n, id(i, j + 1, l), p.ea_bar);
                }
                if zl {
                    b.bar(n, id(i, j, l + 1), p.ea_bar);
                }
                if xi && yj {
                    cable(&mut b, n, id(i + 1, j + 1, l));
                }
                if xi && zl {
                    cable(&mut b, n, id(i + 1, j, l + 1));
                }
                if yj && zl {
                    cable(&mut b, n, id(i, j + 1, l + 1));
                }
                if xi && j > 0 {
                    cable(&mut b, n, id(i + 1, j - 1, l));
                }
                if xi && l > 0 {
                    cable(&mut b, n, id(i + 1, j, l - 1));
                }
                if yj && l > 0 {
                    cable(&mut b, n, id(i, j + 1, l - 1));
                }
                if xi && yj && zl {
                    b.bar(n, id(i + 1, j + 1, l + 1), p.ea_bar);
                }
            }
        }
    }
    for n in 0..sl {
        b.support(n, "xyz");
    }
    for n in id(0, 0, nz)..id(0, 0, nz) + sl {
        b.load(n, [p.load, 0.0, p.load_z]);
    }
    b.effects(Effects {
        unilateral_cables: p.unilateral,
        prestress: prestressed,
        ..Effects::default()
    });
    b.build()
}

// ---------------------------------------------------------------------------
// Command-line access
// ---------------------------------------------------------------------------

/// The generator kinds [`by_name`] knows.
pub const KINDS: &[&str] = &["grid", "tensegrity", "tower"];

/// Parameter keys accepted by [`by_name`] for `kind` (None for an unknown
/// kind). Every kind also accepts `name`, the scene name.
pub fn parameters(kind: &str) -> Option<&'static [&'static str]> {
    match kind {
        "grid" => Some(&[
            "nx",
            "ny",
            "cell",
            "depth",
            "ea_bar",
            "ea_cable",
            "uniform_stiffness",
            "t0",
            "load",
            "unilateral",
            "name",
        ]),
        "tensegrity" => Some(&[
            "nx",
            "ny",
            "cell",
            "depth",
            "ea_bar",
            "ea_cable",
            "t0",
            "load",
            "unilateral",
            "name",
        ]),
        "tower" => Some(&[
            "nx",
            "ny",
            "nz",
            "cell",
            "height",
            "ea_bar",
            "ea_cable",
            "t0",
            "load",
            "load_z",
            "unilateral",
            "name",
        ]),
        _ => None,
    }
}

/// Largest scene [`by_name`] agrees to build, in nodes plus elements: far
/// beyond the 10⁶-dof scenes nsdd is meant for, small enough that a typo
/// (`nx=600000`) is an error rather than an out-of-memory abort.
pub const MAX_ENTRIES: usize = 200_000_000;

/// `key=value` arguments, each read at most once and parsed with an error
/// naming the key.
struct Args<'a> {
    map: &'a BTreeMap<String, String>,
}

impl Args<'_> {
    fn raw(&self, key: &str) -> Option<&str> {
        self.map.get(key).map(|s| s.trim())
    }

    fn count(&self, key: &str, default: usize) -> Result<usize> {
        let Some(v) = self.raw(key) else { return Ok(default) };
        match v.parse::<usize>() {
            Ok(n) if n >= 1 => Ok(n),
            _ => Err(Error::input(
                key,
                None,
                format!("expected a whole number of at least 1, got '{v}'"),
            )),
        }
    }

    fn number(&self, key: &str, default: f64, check: Check) -> Result<f64> {
        let Some(v) = self.raw(key) else { return Ok(default) };
        let x: f64 = v
            .parse()
            .map_err(|_| Error::input(key, None, format!("expected a number, got '{v}'")))?;
        let ok = x.is_finite()
            && match check {
                Check::Positive => x > 0.0,
                Check::NonNegative => x >= 0.0,
                Check::Any => true,
            };
        if !ok {
            let what = match check {
                Check::Positive => "a positive finite number",
                Check::NonNegative => "a finite number not below 0",
                Check::Any => "a finite number",
            };
            return Err(Error::input(key, None, format!("expected {what}, got '{v}'")));
        }
        Ok(x)
    }

    fn flag(&self, key: &str, default: bool) -> Result<bool> {
        let Some(v) = self.raw(key) else { return Ok(default) };
        match v {
            "true" | "1" | "yes" | "on" => Ok(true),
            "false" | "0" | "no" | "off" => Ok(false),
            _ => Err(Error::input(key, None, format!("expected true or false, got '{v}'"))),
        }
    }
}

#[derive(Clone, Copy)]
enum Check {
    Positive,
    NonNegative,
    Any,
}

fn check_size(nodes: Option<usize>, elements: Option<usize>) -> Result<()> {
    match (nodes, elements) {
        (Some(n), Some(e)) if n.saturating_add(e) <= MAX_ENTRIES => Ok(()),
        _ => Err(Error::input(
            "nx",
            None,
            format!("the scene would have more than {MAX_ENTRIES} nodes and elements"),
        )),
    }
}

/// Builds a scene of generator `kind` (`grid`, `tensegrity` or `tower`) from
/// `key=value` parameters, for the command line. Missing keys take the
/// generator's default; `name` overrides the scene name. A key the kind does
/// not take, a value that does not parse or is out of range, or a scene
/// larger than [`MAX_ENTRIES`] is an [`Error::InvalidInput`] naming the key
/// (the field `kind` for an unknown kind).
pub fn by_name(kind: &str, args: &BTreeMap<String, String>) -> Result<Scene> {
    let Some(keys) = parameters(kind) else {
        return Err(Error::input(
            "kind",
            None,
            format!("unknown generator '{kind}' (expected one of {})", KINDS.join(", ")),
        ));
    };
    if let Some(k) = args.keys().find(|k| !keys.contains(&k.as_str())) {
        return Err(Error::input(
            k.as_str(),
            None,
            format!("not a parameter of '{kind}' (expected any of {})", keys.join(", ")),
        ));
    }
    let a = Args { map: args };
    let mut scene = match kind {
        "grid" => {
            let d = GridParams::default();
            let p = GridParams {
                nx: a.count("nx", d.nx)?,
                ny: a.count("ny", d.ny)?,
                cell: a.number("cell", d.cell, Check::Positive)?,
                depth: a.number("depth", d.depth, Check::Positive)?,
                ea_bar: a.number("ea_bar", d.ea_bar, Check::Positive)?,
                ea_cable: a.number("ea_cable", d.ea_cable, Check::Positive)?,
                uniform_stiffness: a.flag("uniform_stiffness", d.uniform_stiffness)?,
                t0: a.number("t0", d.t0, Check::NonNegative)?,
                load: a.number("load", d.load, Check::Any)?,
                unilateral: a.flag("unilateral", d.unilateral)?,
            };
            let (nx, ny) = (p.nx, p.ny);
            let nodes = (nx + 1)
                .checked_mul(ny + 1)
                .and_then(|t| t.checked_add(nx.checked_mul(ny)?));
            let elements = nx.checked_mul(ny).and_then(|c| c.checked_mul(12));
            check_size(nodes, elements)?;
            grid(&p)
        }
        "tensegrity" => {
            let d = TensegrityParams::default();
            let p = TensegrityParams {
                nx: a.count("nx", d.nx)?,
                ny: a.count("ny", d.ny)?,
                cell: a.number("cell", d.cell, Check::Positive)?,
                depth: a.number("depth", d.depth, Check::Positive)?,
                ea_bar: a.number("ea_bar", d.ea_bar, Check::Positive)?,
                ea_cable: a.number("ea_cable", d.ea_cable, Check::Positive)?,
                t0: a.number("t0", d.t0, Check::Positive)?,
                load: a.number("load", d.load, Check::Any)?,
                unilateral: a.flag("unilateral", d.unilateral)?,
            };
            let (nx, ny) = (p.nx, p.ny);
            let nodes = (nx + 1).checked_mul(ny + 1).and_then(|t| t.checked_mul(3));
            let elements = nx.checked_mul(ny).and_then(|c| c.checked_mul(16));
            check_size(nodes, elements)?;
            tensegrity(&p)
        }
        _ => {
            let d = TowerParams::default();
            let p = TowerParams {
                nx: a.count("nx", d.nx)?,
                ny: a.count("ny", d.ny)?,
                nz: a.count("nz", d.nz)?,
                cell: a.number("cell", d.cell, Check::Positive)?,
                height: a.number("height", d.height, Check::Positive)?,
                ea_bar: a.number("ea_bar", d.ea_bar, Check::Positive)?,
                ea_cable: a.number("ea_cable", d.ea_cable, Check::Positive)?,
                t0: a.number("t0", d.t0, Check::NonNegative)?,
                load: a.number("load", d.load, Check::Any)?,
                load_z: a.number("load_z", d.load_z, Check::Any)?,
                unilateral: a.flag("unilateral", d.unilateral)?,
            };
            let nodes = (p.nx + 1).checked_mul(p.ny + 1).and_then(|t| t.checked_mul(p.nz + 1));
            let elements = nodes.and_then(|n| n.checked_mul(13));
            check_size(nodes, elements)?;
            tower(&p)
        }
    };
    if let Some(name) = a.raw("name") {
        scene.scene.name = name.to_string();
    }
    Ok(scene)
}

/// The scenes shipped in `scenes/`, as `(file name, scene)`. The files are
/// these scenes written as TOML; a test regenerates them and compares.
///
/// - `grid-8x8.toml`: 8×8 grid, unilateral cables prestressed with
///   `t0 = 0.1`, solved with the multilevel method on 4 subdomains to 1e-8;
/// - `grid-4x4-linear.toml`: 4×4 grid, bilateral cables, no prestress;
/// - `tower-2x2x6.toml`: 2×2×6 tower, unilateral cables prestressed with
///   `t0 = 0.002`, lateral and vertical top loads;
/// - `tensegrity-2x2.toml`: 2×2 tensegrity grid with its default
///   self-stress and geometric stiffness.
pub fn bundled() -> Vec<(&'static str, Scene)> {
    let mut grid8 = grid(&GridParams {
        nx: 8,
        ny: 8,
        t0: 0.1,
        ..GridParams::default()
    });
    grid8.solver = SolverSettings {
        method: Method::Multilevel,
        subdomains: 4,
        tolerance: 1e-8,
        ..SolverSettings::default()
    };
    let mut grid4 = grid(&GridParams {
        nx: 4,
        ny: 4,
        unilateral: false,
        ..GridParams::default()
    });
    grid4.scene.name = "grid-4x4-linear".into();
    let tower = tower(&TowerParams {
        nx: 2,
        ny: 2,
        nz: 6,
        t0: 0.002,
        load_z: -0.05,
        ..TowerParams::default()
    });
    let teg = tensegrity(&TensegrityParams {
        nx: 2,
        ny: 2,
        ..TensegrityParams::default()
    });
    vec![
        ("grid-8x8.toml", grid8),
        ("grid-4x4-linear.toml", grid4),
        ("tower-2x2x6.toml", tower),
        ("tensegrity-2x2.toml", teg),
    ]
}
