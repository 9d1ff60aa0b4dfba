//! The scene: the public input format of SCENE.md (TOML or JSON, one schema),
//! plus the additions of nsdd (load cases, load path). Field names are a
//! contract with users: add, never rename.
//!
//! Reading a scene never trusts it: [`Scene::validate`] checks every field
//! before any computation and names the field and index of the first problem.

use serde::{Deserialize, Serialize};

/// A whole scene, as in SCENE.md.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    #[serde(default)]
    pub scene: SceneInfo,
    #[serde(default)]
    pub effects: Effects,
    #[serde(default)]
    pub solver: SolverSettings,
    pub nodes: Nodes,
    pub elements: Elements,
    #[serde(default)]
    pub supports: Supports,
    #[serde(default)]
    pub loads: Loads,
    /// Extra load cases, solved on the same factorizations (nsdd addition).
    /// When present, `loads` is load case 0 and these follow.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub load_cases: Vec<LoadCase>,
    /// Quasi-static load path in load-factor steps (nsdd addition).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub load_path: Option<LoadPath>,
}

/// `[scene]`: name and, for self-weight, gravity.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct SceneInfo {
    #[serde(default)]
    pub name: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gravity: Option<[f64; 3]>,
}

/// `[effects]`: what the scene calls for. Absent means false.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Effects {
    #[serde(default)]
    pub unilateral_cables: bool,
    #[serde(default)]
    pub prestress: bool,
    #[serde(default)]
    pub geometric_stiffness: bool,
    #[serde(default)]
    pub self_weight: bool,
}

impl Effects {
    /// Names of the effects that are on, in SCENE.md order.
    pub fn names(&self) -> Vec<&'static str> {
        let mut v = Vec::new();
        if self.unilateral_cables {
            v.push("unilateral_cables");
        }
        if self.prestress {
            v.push("prestress");
        }
        if self.geometric_stiffness {
            v.push("geometric_stiffness");
        }
        if self.self_weight {
            v.push("self_weight");
        }
        v
    }
}

pub use crate::settings::{
    AdaptiveEdges, AdaptiveThreshold, InterfaceScaling, MacroDegree, Method, MethodConfig, OrderingChoice, Partitioner,
    Preconditioner, SearchDirection, SolverSettings,
};

/// `[nodes]`: columnar coordinates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Nodes {
    pub x: Vec<f64>,
    pub y: Vec<f64>,
    pub z: Vec<f64>,
}

/// Element kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum ElementKind {
    /// Bilateral: carries tension and compression.
    Bar,
    /// Goes slack instead of pushing when `unilateral_cables` is on.
    Cable,
}

/// `[elements]`: columnar element data.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Elements {
    pub a: Vec<usize>,
    pub b: Vec<usize>,
    pub kind: Vec<ElementKind>,
    pub ea: Vec<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub t0: Vec<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub mass_per_length: Vec<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub subdomain: Vec<usize>,
}

/// `[supports]`: blocked displacement components per node.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Supports {
    pub node: Vec<usize>,
    pub dofs: Vec<String>,
}

/// `[loads]`: nodal forces.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Loads {
    pub node: Vec<usize>,
    #[serde(default)]
    pub fx: Vec<f64>,
    #[serde(default)]
    pub fy: Vec<f64>,
    #[serde(default)]
    pub fz: Vec<f64>,
}

/// `[[load_cases]]`: an extra load case (nsdd addition).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct LoadCase {
    #[serde(default)]
    pub name: String,
    pub node: Vec<usize>,
    #[serde(default)]
    pub fx: Vec<f64>,
    #[serde(default)]
    pub fy: Vec<f64>,
    #[serde(default)]
    pub fz: Vec<f64>,
}

/// `[load_path]`: apply `loads` in `steps` equal load-factor increments up to
/// `final_factor` (nsdd addition). Each step reuses every factorization and
/// starts from the previous step's state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoadPath {
    pub steps: usize,
    #[serde(default = "one")]
    pub final_factor: f64,
}

fn one() -> f64 {
    1.0
}

use crate::error::{Error, Result};

fn check_finite(field: &str, v: &[f64]) -> Result<()> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(Error::input(field, Some(i), format!("not a finite number ({})", v[i]))),
        None => Ok(()),
    }
}

fn check_len(field: &str, len: usize, expected: usize, against: &str) -> Result<()> {
    if len != expected {
        return Err(Error::input(
            field,
            None,
            format!("has {len} entries but {against} has {expected}"),
        ));
    }
    Ok(())
}

fn check_nodes(field: &str, v: &[usize], n_nodes: usize) -> Result<()> {
    match v.iter().position(|&i| i >= n_nodes) {
        Some(i) => Err(Error::input(
            field,
            Some(i),
            format!("node index {} out of range (the scene has {n_nodes} nodes)", v[i]),
        )),
        None => Ok(()),
    }
}

fn check_force_arrays(prefix: &str, node: &[usize], fx: &[f64], fy: &[f64], fz: &[f64], n_nodes: usize) -> Result<()> {
    for (name, arr) in [("fx", fx), ("fy", fy), ("fz", fz)] {
        if !arr.is_empty() {
            check_len(
                &format!("{prefix}.{name}"),
                arr.len(),
                node.len(),
                &format!("{prefix}.node"),
            )?;
        }
        check_finite(&format!("{prefix}.{name}"), arr)?;
    }
    check_nodes(&format!("{prefix}.node"), node, n_nodes)
}

impl Scene {
    /// Checks every field; the error names the first bad field and index.
    /// Structural problems (mechanisms) are found later, by the model and
    /// the factorization.
    pub fn validate(&self) -> Result<()> {
        let n = self.nodes.x.len();
        check_len("nodes.y", self.nodes.y.len(), n, "nodes.x")?;
        check_len("nodes.z", self.nodes.z.len(), n, "nodes.x")?;
        if n == 0 {
            return Err(Error::input("nodes.x", None, "the scene has no nodes"));
        }
        check_finite("nodes.x", &self.nodes.x)?;
        check_finite("nodes.y", &self.nodes.y)?;
        check_finite("nodes.z", &self.nodes.z)?;

        let el = &self.elements;
        let m = el.a.len();
        if m == 0 {
            return Err(Error::input("elements.a", None, "the scene has no elements"));
        }
        check_len("elements.b", el.b.len(), m, "elements.a")?;
        check_len("elements.kind", el.kind.len(), m, "elements.a")?;
        check_len("elements.ea", el.ea.len(), m, "elements.a")?;
        if !el.t0.is_empty() {
            check_len("elements.t0", el.t0.len(), m, "elements.a")?;
        }
        if !el.mass_per_length.is_empty() {
            check_len("elements.mass_per_length", el.mass_per_length.len(), m, "elements.a")?;
        }
        if !el.subdomain.is_empty() {
            check_len("elements.subdomain", el.subdomain.len(), m, "elements.a")?;
        }
        check_nodes("elements.a", &el.a, n)?;
        check_nodes("elements.b", &el.b, n)?;
        check_finite("elements.ea", &el.ea)?;
        check_finite("elements.t0", &el.t0)?;
        check_finite("elements.mass_per_length", &el.mass_per_length)?;
        if let Some(i) = el.ea.iter().position(|&v| v <= 0.0) {
            return Err(Error::input(
                "elements.ea",
                Some(i),
                format!("must be positive, got {}", el.ea[i]),
            ));
        }
        if let Some(i) = el.mass_per_length.iter().position(|&v| v < 0.0) {
            return Err(Error::input(
                "elements.mass_per_length",
                Some(i),
                format!("must not be negative, got {}", el.mass_per_length[i]),
            ));
        }
        for e in 0..m {
            let (a, b) = (el.a[e], el.b[e]);
            let d2 = (self.nodes.x[b] - self.nodes.x[a]).powi(2)
                + (self.nodes.y[b] - self.nodes.y[a]).powi(2)
                + (self.nodes.z[b] - self.nodes.z[a]).powi(2);
            if a == b || d2.sqrt() == 0.0 || !(d2 > 0.0) {
                return Err(Error::input(
                    "elements",
                    Some(e),
                    format!("zero-length element (nodes {a} and {b} coincide)"),
                ));
            }
        }

        check_len(
            "supports.dofs",
            self.supports.dofs.len(),
            self.supports.node.len(),
            "supports.node",
        )?;
        check_nodes("supports.node", &self.supports.node, n)?;
        for (i, d) in self.supports.dofs.iter().enumerate() {
            if d.is_empty() || d.chars().any(|c| !matches!(c, 'x' | 'y' | 'z')) {
                return Err(Error::input(
                    "supports.dofs",
                    Some(i),
                    format!("'{d}' is not a set of components (any of x, y, z)"),
                ));
            }
        }
        check_force_arrays(
            "loads",
            &self.loads.node,
            &self.loads.fx,
            &self.loads.fy,
            &self.loads.fz,
            n,
        )?;
        for (c, lc) in self.load_cases.iter().enumerate() {
            check_force_arrays(&format!("load_cases[{c}]"), &lc.node, &lc.fx, &lc.fy, &lc.fz, n)?;
        }
        if let Some(lp) = &self.load_path {
            if lp.steps == 0 {
                return Err(Error::input("load_path.steps", None, "must be at least 1"));
            }
            if !lp.final_factor.is_finite() {
                return Err(Error::input("load_path.final_factor", None, "not a finite number"));
            }
        }

        if self.effects.self_weight {
            if el.mass_per_length.is_empty() {
                return Err(Error::input(
                    "elements.mass_per_length",
                    None,
                    "effect self_weight needs elements.mass_per_length",
                ));
            }
            if let Some(g) = self.scene.gravity {
                if g.iter().any(|v| !v.is_finite()) {
                    return Err(Error::input("scene.gravity", None, "not a finite vector"));
                }
            }
        }
        self.solver.validate()
    }

    /// Reads a scene from TOML text.
    pub fn from_toml_str(s: &str) -> Result<Scene> {
        toml::from_str(s).map_err(|e| Error::Parse(e.to_string()))
    }

    /// Reads a scene from JSON text.
    pub fn from_json_str(s: &str) -> Result<Scene> {
        serde_json::from_str(s).map_err(|e| Error::Parse(e.to_string()))
    }

    /// Reads a scene file; `.json` is JSON, anything else TOML.
    pub fn load(path: &std::path::Path) -> Result<Scene> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::Io(format!("{}: {e}", path.display())))?;
        if path.extension().and_then(|e| e.to_str()) == Some("json") {
            Scene::from_json_str(&text)
        } else {
            Scene::from_toml_str(&text)
        }
    }

    /// Writes the scene as TOML text.
    pub fn to_toml_string(&self) -> Result<String> {
        toml::to_string(self).map_err(|e| Error::Parse(e.to_string()))
    }

    /// Writes the scene as pretty JSON text.
    pub fn to_json_string(&self) -> Result<String> {
        serde_json::to_string_pretty(self).map_err(|e| Error::Parse(e.to_string()))
    }
}

/// Builds a [`Scene`] entry by entry while keeping the columnar arrays
/// consistent: every element gets `a`, `b`, `kind` and `ea`; `t0` stays empty
/// until some element is prestressed and then covers every element (0 for the
/// others); every load gets `fx`, `fy` and `fz`.
///
/// The builder records what it is given and never panics: an out-of-range
/// index is kept as is and reported by [`Scene::validate`] (through
/// [`SceneBuilder::build_validated`]), naming the field and entry like any
/// scene read from a file.
///
/// ```
/// use nsdd::scene::{Effects, SceneBuilder};
/// let mut b = SceneBuilder::new("two-bars");
/// let n0 = b.node(0.0, 0.0, 0.0);
/// let n1 = b.node(1.0, 0.0, 0.0);
/// let n2 = b.node(0.0, 1.0, 0.0);
/// b.bar(n0, n1, 1e3);
/// let c = b.cable(n2, n1, 1e2);
/// b.prestress(c, 0.5);
/// b.support(n0, "xyz").support(n2, "xyz").support(n1, "z");
/// b.load(n1, [0.0, -1.0, 0.0]);
/// b.effects(Effects { unilateral_cables: true, prestress: true, ..Effects::default() });
/// let scene = b.build_validated().unwrap();
/// assert_eq!(scene.elements.t0, vec![0.0, 0.5]);
/// ```
#[derive(Debug, Clone, Default)]
pub struct SceneBuilder {
    scene: Scene,
    /// First `prestress` call on an element that did not exist.
    bad_prestress: Option<usize>,
}

impl SceneBuilder {
    /// An empty scene called `name`, with default effects and solver settings.
    pub fn new(name: impl Into<String>) -> Self {
        let mut scene = Scene::default();
        scene.scene.name = name.into();
        SceneBuilder {
            scene,
            bad_prestress: None,
        }
    }

    /// Like [`SceneBuilder::new`], reserving room for `nodes` nodes and
    /// `elements` elements (generators of million-dof scenes use it to avoid
    /// repeated reallocation).
    pub fn with_capacity(name: impl Into<String>, nodes: usize, elements: usize) -> Self {
        let mut b = SceneBuilder::new(name);
        let n = &mut b.scene.nodes;
        n.x.reserve_exact(nodes);
        n.y.reserve_exact(nodes);
        n.z.reserve_exact(nodes);
        let e = &mut b.scene.elements;
        e.a.reserve_exact(elements);
        e.b.reserve_exact(elements);
        e.kind.reserve_exact(elements);
        e.ea.reserve_exact(elements);
        b
    }

    /// Number of nodes added so far.
    pub fn n_nodes(&self) -> usize {
        self.scene.nodes.x.len()
    }

    /// Number of elements added so far.
    pub fn n_elements(&self) -> usize {
        self.scene.elements.a.len()
    }

    /// Adds a node and returns its index.
    pub fn node(&mut self, x: f64, y: f64, z: f64) -> usize {
        let n = &mut self.scene.nodes;
        n.x.push(x);
        n.y.push(y);
        n.z.push(z);
        n.x.len() - 1
    }

    /// Adds an element of the given kind between nodes `a` and `b` and returns
    /// its index.
    pub fn element(&mut self, a: usize, b: usize, kind: ElementKind, ea: f64) -> usize {
        let e = &mut self.scene.elements;
        e.a.push(a);
        e.b.push(b);
        e.kind.push(kind);
        e.ea.push(ea);
        if !e.t0.is_empty() && e.t0.len() < e.a.len() {
            e.t0.resize(e.a.len(), 0.0);
        }
        e.a.len() - 1
    }

    /// Adds a bar (bilateral element) and returns its index.
    pub fn bar(&mut self, a: usize, b: usize, ea: f64) -> usize {
        self.element(a, b, ElementKind::Bar, ea)
    }

    /// Adds a cable and returns its index.
    pub fn cable(&mut self, a: usize, b: usize, ea: f64) -> usize {
        self.element(a, b, ElementKind::Cable, ea)
    }

    /// Sets the prestress `t0` (tension positive) of element `elem`, which
    /// must have been added already. This only records the value: the
    /// `prestress` effect is switched on with [`SceneBuilder::effects`], as in
    /// a scene file. An unknown element is an error of `elements.t0` at that
    /// index from [`SceneBuilder::build_validated`] (and makes
    /// [`SceneBuilder::build`] return a scene whose `t0` is one entry too
    /// long, which [`Scene::validate`] rejects).
    pub fn prestress(&mut self, elem: usize, t0: f64) -> &mut Self {
        let e = &mut self.scene.elements;
        let m = e.a.len();
        if elem >= m {
            self.bad_prestress.get_or_insert(elem);
            return self;
        }
        if e.t0.len() < m {
            e.t0.resize(m, 0.0);
        }
        e.t0[elem] = t0;
        self
    }

    /// Blocks the components `dofs` (any of `x`, `y`, `z`) of `node`.
    pub fn support(&mut self, node: usize, dofs: &str) -> &mut Self {
        self.scene.supports.node.push(node);
        self.scene.supports.dofs.push(dofs.to_string());
        self
    }

    /// Adds a nodal force `[fx, fy, fz]` on `node` (load case 0).
    pub fn load(&mut self, node: usize, f: [f64; 3]) -> &mut Self {
        let l = &mut self.scene.loads;
        l.node.push(node);
        l.fx.push(f[0]);
        l.fy.push(f[1]);
        l.fz.push(f[2]);
        self
    }

    /// Sets the effects the scene calls for.
    pub fn effects(&mut self, effects: Effects) -> &mut Self {
        self.scene.effects = effects;
        self
    }

    /// Sets the solver settings.
    pub fn solver(&mut self, solver: SolverSettings) -> &mut Self {
        self.scene.solver = solver;
        self
    }

    /// The scene as built, without validation.
    pub fn build(self) -> Scene {
        let mut scene = self.scene;
        let m = scene.elements.a.len();
        if !scene.elements.t0.is_empty() || self.bad_prestress.is_some() {
            let len = if self.bad_prestress.is_some() { m + 1 } else { m };
            scene.elements.t0.resize(len, 0.0);
        }
        scene
    }

    /// The scene as built, checked by [`Scene::validate`].
    pub fn build_validated(self) -> Result<Scene> {
        if let Some(e) = self.bad_prestress {
            return Err(Error::input(
                "elements.t0",
                Some(e),
                format!(
                    "prestress given for element {e}, but the scene has {} elements",
                    self.n_elements()
                ),
            ));
        }
        let scene = self.build();
        scene.validate()?;
        Ok(scene)
    }
}
