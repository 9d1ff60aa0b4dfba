//! Solver settings: the one type behind the scene's `[solver]` section,
//! the command-line flags, the Rust API ([`crate::solve::SolveOptions`] is
//! an alias) and the C ABI's `NsddOptions`, with one [`SolverSettings::validate`]
//! and the one mapping from a [`Method`] to the configuration of the
//! iteration ([`Method::config`]).

use crate::error::{Error, Result};
pub use crate::scaling::InterfaceScaling;
use serde::{Deserialize, Serialize};

/// Solution method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default, Hash)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// One sparse Cholesky of the whole structure, exact active set on cables.
    #[default]
    Direct,
    /// The paper's iteration without the macro (coarse) space.
    Monolevel,
    /// The paper's iteration with the kernel-enriched macro space.
    Multilevel,
    /// Conjugate gradient on the interface problem with the same coarse
    /// step (the paper's outlook); with unilateral cables, a primal–dual
    /// active set around it (`nonsmooth`). An nsdd addition.
    Cg,
}

impl Method {
    pub fn name(&self) -> &'static str {
        match self {
            Method::Direct => "direct",
            Method::Monolevel => "monolevel",
            Method::Multilevel => "multilevel",
            Method::Cg => "cg",
        }
    }
}

impl std::str::FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "direct" => Ok(Method::Direct),
            "monolevel" => Ok(Method::Monolevel),
            "multilevel" => Ok(Method::Multilevel),
            "cg" => Ok(Method::Cg),
            _ => Err(format!(
                "unknown method '{s}' (expected direct, monolevel, multilevel or cg)"
            )),
        }
    }
}

/// Preconditioner of the interface CG (`method = "cg"`). An nsdd addition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default, Hash)]
#[serde(rename_all = "lowercase")]
pub enum Preconditioner {
    /// `Σ_E B_E S_E B_Eᵀ` with the Schur complement `S_E` of each
    /// subdomain on its interface: one more (interior) solve per subdomain
    /// and iteration and a second factorization, for 2–4× fewer iterations.
    #[default]
    Dirichlet,
    /// `Σ_E B_E K_E B_Eᵀ`: the subdomain stiffness on its interface dofs
    /// (the paper's lumped choice); no extra factorization.
    Lumped,
}

impl Preconditioner {
    pub fn name(&self) -> &'static str {
        match self {
            Preconditioner::Dirichlet => "dirichlet",
            Preconditioner::Lumped => "lumped",
        }
    }
}

impl std::str::FromStr for Preconditioner {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "dirichlet" => Ok(Preconditioner::Dirichlet),
            "lumped" => Ok(Preconditioner::Lumped),
            _ => Err(format!("unknown preconditioner '{s}' (expected dirichlet or lumped)")),
        }
    }
}

/// The `d` of the local stage: `"auto"` or a positive number.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum SearchDirection {
    #[default]
    Auto,
    Value(f64),
}

/// `None` for `"auto"`: how a scene writes a setting with an automatic
/// choice (`"auto"` or a number), one reading for all of them.
fn serialize_auto_or<S: serde::Serializer>(v: Option<f64>, s: S) -> std::result::Result<S::Ok, S::Error> {
    match v {
        None => s.serialize_str("auto"),
        Some(v) => s.serialize_f64(v),
    }
}

/// `"auto"` (`None`) or a number (also written as a string); the error
/// names `field`.
fn deserialize_auto_or<'de, D: serde::Deserializer<'de>>(
    d: D,
    field: &str,
) -> std::result::Result<Option<f64>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Raw {
        Num(f64),
        Int(i64),
        Str(String),
    }
    match Raw::deserialize(d)? {
        Raw::Num(v) => Ok(Some(v)),
        Raw::Int(v) => Ok(Some(v as f64)),
        Raw::Str(s) => parse_auto_or(&s)
            .ok_or_else(|| serde::de::Error::custom(format!("{field}: expected \"auto\" or a number, got \"{s}\""))),
    }
}

/// `Some(None)` for `"auto"`, `Some(Some(v))` for a number, `None` else.
fn parse_auto_or(s: &str) -> Option<Option<f64>> {
    if s == "auto" {
        Some(None)
    } else {
        s.parse::<f64>().ok().map(Some)
    }
}

impl SearchDirection {
    fn value(self) -> Option<f64> {
        match self {
            SearchDirection::Auto => None,
            SearchDirection::Value(v) => Some(v),
        }
    }

    fn from_value(v: Option<f64>) -> SearchDirection {
        v.map_or(SearchDirection::Auto, SearchDirection::Value)
    }
}

impl Serialize for SearchDirection {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        serialize_auto_or(self.value(), s)
    }
}

impl<'de> Deserialize<'de> for SearchDirection {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        deserialize_auto_or(d, "solver.search_direction").map(SearchDirection::from_value)
    }
}

impl std::str::FromStr for SearchDirection {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        parse_auto_or(s)
            .map(SearchDirection::from_value)
            .ok_or_else(|| format!("search direction must be \"auto\" or a number, got '{s}'"))
    }
}

/// The threshold of `cg`'s adaptive macro space ([`crate::adaptive`]):
/// `"auto"` (the default) or a number, 0 being off.
///
/// `Auto` turns the space on, at [`AUTO_ADAPTIVE_THRESHOLD`], where the
/// elements' axial stiffnesses `EA/L` span [`AUTO_ADAPTIVE_CONTRAST`] or
/// more (stiff bars hanging on soft cables: there the face eigenproblems
/// pay for themselves many times over), and leaves it off elsewhere, where
/// they cost more set-up than they save iterations.
///
/// ```
/// use nsdd::settings::AdaptiveThreshold;
/// assert_eq!("auto".parse::<AdaptiveThreshold>(), Ok(AdaptiveThreshold::Auto));
/// assert_eq!("5".parse::<AdaptiveThreshold>(), Ok(AdaptiveThreshold::Value(5.0)));
/// assert!(AdaptiveThreshold::OFF.is_valid());
/// assert!(!AdaptiveThreshold::Value(0.5).is_valid());
/// // The choice for the elements' stiffnesses `EA/L`:
/// assert_eq!(AdaptiveThreshold::Auto.resolve([1.0, 2.0, 20.0]), 0.0);
/// assert_eq!(AdaptiveThreshold::Auto.resolve([1.0, 1e4]), 5.0);
/// assert_eq!(AdaptiveThreshold::Value(12.0).resolve([1.0, 1e4]), 12.0);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum AdaptiveThreshold {
    #[default]
    Auto,
    /// 0 (off) or a finite number above 1.
    Value(f64),
}

/// The threshold `"auto"` uses where it turns the adaptive space on.
pub const AUTO_ADAPTIVE_THRESHOLD: f64 = 5.0;

/// The spread of the elements' `EA/L` (largest over smallest) from which
/// `"auto"` turns the adaptive space on. Generated grids spread 10–20,
/// uniform towers about 2; a tower whose bars are 1e4 × its cables, 1.6e4.
pub const AUTO_ADAPTIVE_CONTRAST: f64 = 100.0;

impl AdaptiveThreshold {
    /// No adaptive columns.
    pub const OFF: AdaptiveThreshold = AdaptiveThreshold::Value(0.0);

    /// 0 (off) or finite and above 1 (every face eigenvalue is at least 1);
    /// `Auto` always.
    pub fn is_valid(self) -> bool {
        match self {
            AdaptiveThreshold::Auto => true,
            AdaptiveThreshold::Value(t) => adaptive_threshold_is_valid(t),
        }
    }

    pub fn is_auto(&self) -> bool {
        *self == AdaptiveThreshold::Auto
    }

    /// The threshold to use (0: off) for a structure whose elements have
    /// the axial stiffnesses `EA/L` in `stiffnesses` (zeros ignored).
    pub fn resolve(self, stiffnesses: impl IntoIterator<Item = f64>) -> f64 {
        match self {
            AdaptiveThreshold::Value(t) => t,
            AdaptiveThreshold::Auto => {
                let (lo, hi) = stiffnesses
                    .into_iter()
                    .filter(|k| *k > 0.0 && k.is_finite())
                    .fold((f64::INFINITY, 0.0f64), |(lo, hi), k| (lo.min(k), hi.max(k)));
                if hi >= AUTO_ADAPTIVE_CONTRAST * lo {
                    AUTO_ADAPTIVE_THRESHOLD
                } else {
                    0.0
                }
            }
        }
    }
}

impl std::fmt::Display for AdaptiveThreshold {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            AdaptiveThreshold::Auto => f.write_str("auto"),
            AdaptiveThreshold::Value(t) => write!(f, "{t}"),
        }
    }
}

impl AdaptiveThreshold {
    fn value(self) -> Option<f64> {
        match self {
            AdaptiveThreshold::Auto => None,
            AdaptiveThreshold::Value(v) => Some(v),
        }
    }

    fn from_value(v: Option<f64>) -> AdaptiveThreshold {
        v.map_or(AdaptiveThreshold::Auto, AdaptiveThreshold::Value)
    }
}

impl Serialize for AdaptiveThreshold {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        serialize_auto_or(self.value(), s)
    }
}

impl<'de> Deserialize<'de> for AdaptiveThreshold {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        deserialize_auto_or(d, "solver.adaptive_threshold").map(AdaptiveThreshold::from_value)
    }
}

impl std::str::FromStr for AdaptiveThreshold {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        parse_auto_or(s)
            .map(AdaptiveThreshold::from_value)
            .ok_or_else(|| format!("adaptive threshold must be \"auto\" or a number, got '{s}'"))
    }
}

/// Whether `cg`'s adaptive macro space puts constraints on the edges too
/// (the dofs shared by three or more subdomains; `crate::adaptive`).
/// Written `true`, `false` or `"auto"` in a scene.
///
/// `Auto` (the default) turns them on where the elements' `EA/L` span
/// [`AUTO_ADAPTIVE_CONTRAST`] or more, the rule that turns the adaptive
/// space itself on by default: on the 3D towers whose bars are 1e4 × their
/// cables the edges took `cg` up to 4.6× less time (16³ tower, 64
/// subdomains), and as little or less on 20 of 23 such configurations;
/// on the plates (`EA/L` spread 10-20) they save 0-2 iterations for more
/// set-up than that.
///
/// ```
/// use nsdd::settings::AdaptiveEdges;
/// assert_eq!("auto".parse::<AdaptiveEdges>(), Ok(AdaptiveEdges::Auto));
/// assert_eq!("true".parse::<AdaptiveEdges>(), Ok(AdaptiveEdges::On));
/// assert!(AdaptiveEdges::Auto.resolve([1.0, 1e4]));
/// assert!(!AdaptiveEdges::Auto.resolve([1.0, 20.0]));
/// assert!(!AdaptiveEdges::Off.resolve([1.0, 1e4]));
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum AdaptiveEdges {
    #[default]
    Auto,
    On,
    Off,
}

impl AdaptiveEdges {
    pub fn is_auto(&self) -> bool {
        *self == AdaptiveEdges::Auto
    }

    /// Whether the edges get constraints, for a structure whose elements
    /// have the axial stiffnesses `EA/L` in `stiffnesses` (zeros ignored;
    /// none: off).
    pub fn resolve(self, stiffnesses: impl IntoIterator<Item = f64>) -> bool {
        match self {
            AdaptiveEdges::On => true,
            AdaptiveEdges::Off => false,
            AdaptiveEdges::Auto => AdaptiveThreshold::Auto.resolve(stiffnesses) > 0.0,
        }
    }
}

impl From<bool> for AdaptiveEdges {
    fn from(on: bool) -> Self {
        if on {
            AdaptiveEdges::On
        } else {
            AdaptiveEdges::Off
        }
    }
}

impl std::fmt::Display for AdaptiveEdges {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            AdaptiveEdges::Auto => "auto",
            AdaptiveEdges::On => "true",
            AdaptiveEdges::Off => "false",
        })
    }
}

impl std::str::FromStr for AdaptiveEdges {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "auto" => Ok(AdaptiveEdges::Auto),
            "true" => Ok(AdaptiveEdges::On),
            "false" => Ok(AdaptiveEdges::Off),
            _ => Err(format!("adaptive edges must be true, false or \"auto\", got '{s}'")),
        }
    }
}

impl Serialize for AdaptiveEdges {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            AdaptiveEdges::Auto => s.serialize_str("auto"),
            AdaptiveEdges::On => s.serialize_bool(true),
            AdaptiveEdges::Off => s.serialize_bool(false),
        }
    }
}

impl<'de> Deserialize<'de> for AdaptiveEdges {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Bool(bool),
            Str(String),
        }
        match Raw::deserialize(d)? {
            Raw::Bool(b) => Ok(b.into()),
            Raw::Str(s) => s.parse().map_err(|_| {
                serde::de::Error::custom(format!(
                    "solver.adaptive_edges: expected true, false or \"auto\", got \"{s}\""
                ))
            }),
        }
    }
}

/// Degree of the polynomial fields in each interface's macro basis
/// (`crate::coarse::geometric_modes`): 1 is the rigid motions and the
/// in-plane extensions (9 columns), 2 to 6 add, per displacement
/// component, the monomials of degree 2 up to the degree in the
/// interface's two in-plane coordinates (those its points do not span drop
/// out). Written `1` to `6` or `"auto"` in a scene.
///
/// `Auto` (the default) is, for `cg` on a flat structure (its nodes'
/// smallest principal spread at most [`FLAT_SPREAD_RATIO`] of the middle
/// one) with the adaptive macro space off: 5 ([`MacroDegree::AUTO_MAX`])
/// on the interfaces of at least [`QUINTIC_FACE_NODES`] nodes, 3 on those
/// of [`POLYNOMIAL_FACE_NODES`] to 79 nodes, 2 on those of
/// [`QUADRATIC_FACE_NODES`] to 19 nodes; 1 elsewhere. Where the plates'
/// interfaces get them (24² in 4, 48² and 65² in 4 and 16, 130² in 4–64
/// subdomains) `cg` then takes 8–17 iterations where it took 15–33, for
/// the same time or up to 1.3× less. Smaller interfaces get less: there
/// the 30 columns of degree 3 make the coarse problem a large part of the
/// interface (13 % of the 65² plate's dofs with 64 subdomains), and cg
/// took 1.2–2.3× longer with them although its iterations fell 2–3×; the
/// 18 of degree 2 pay on faces of 16 nodes or more. On
/// 3D towers the added columns cost more coarse work than they save; with
/// the adaptive space (stiffness contrast) they broke `cg` down; and the
/// stationary `multilevel` stops on a floor near 1.7e-12 with them on the
/// bundled 8×8 grid (564 iterations to 1e-12 at degree 1), so it keeps 1.
///
/// ```
/// use nsdd::settings::MacroDegree;
/// assert_eq!(MacroDegree::default(), MacroDegree::Auto);
/// assert_eq!("auto".parse::<MacroDegree>(), Ok(MacroDegree::Auto));
/// assert_eq!("2".parse::<MacroDegree>(), Ok(MacroDegree::Fixed(2)));
/// assert_eq!("6".parse::<MacroDegree>(), Ok(MacroDegree::Fixed(6)));
/// assert!("7".parse::<MacroDegree>().is_err());
/// assert_eq!(MacroDegree::Auto.resolve(true, false, true), 5);
/// assert_eq!(MacroDegree::Auto.resolve(true, false, false), 1);
/// assert_eq!(MacroDegree::Auto.resolve(true, true, true), 1);
/// assert_eq!(MacroDegree::Auto.resolve(false, false, true), 1);
/// assert_eq!(MacroDegree::Fixed(2).resolve(false, true, false), 2);
/// // Small interfaces keep degree 1 under "auto", not when it is fixed.
/// assert_eq!(MacroDegree::Auto.on_interface(3, || 12), 1);
/// assert_eq!(MacroDegree::Auto.on_interface(3, || 16), 2);
/// assert_eq!(MacroDegree::Auto.on_interface(5, || 40), 3);
/// assert_eq!(MacroDegree::Auto.on_interface(5, || 100), 5);
/// assert_eq!(MacroDegree::Auto.on_interface(3, || 100), 3);
/// assert_eq!(MacroDegree::Fixed(3).on_interface(3, || 12), 3);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MacroDegree {
    #[default]
    Auto,
    /// 1 to [`MacroDegree::MAX`].
    Fixed(u8),
}

/// Largest ratio of a structure's smallest to middle principal spread of
/// its nodes for which it counts as flat ([`MacroDegree`]; measured on the
/// free dofs' points): the bundled 8×8 double-layer grid's nodes have 0.20,
/// a 24² one 0.07, the bundled 4×4 grid 0.37 and the 2×2×10 tower 1.
pub const FLAT_SPREAD_RATIO: f64 = 0.3;

/// Fewest nodes on an interface for [`MacroDegree::Auto`] to give it the
/// polynomial fields above degree 1. Measured on double-layer plates cut
/// in 4, 16 and 64 (best of 2–3 runs each, `cg` to 1e-8): degree 3 was
/// 1.2–2.3× slower than degree 1 where the faces had 6–16 nodes (16² and
/// 24² plates in 16 and 64, 40² to 65² in 64) although it took 2–3× fewer
/// iterations, within ±10 % at 20–24 nodes (40² and 48² in 16, 24² in 4),
/// and up to 1.3× faster from 32 nodes on (65² in 4 and 16, 130²). The
/// nonsmooth cg's structures without their slack cables have smaller
/// faces (21–25 nodes where the 32² plate cut in 4 has 32): at 20 they
/// keep degree 3 and the iterations of a uniform degree 3.
pub const POLYNOMIAL_FACE_NODES: usize = 20;

/// Fewest nodes on an interface for [`MacroDegree::Auto`] to give it the
/// quadratic fields (degree 2, 18 columns where degree 3 has 30) when it
/// is smaller than [`POLYNOMIAL_FACE_NODES`]. Measured with `cg` to 1e-8
/// (best of 3, interleaved): on faces of 16–18 nodes (the 65² plate cut in
/// 64, the 32² one in 16) degree 2 takes 15 and 14 iterations instead of
/// 27 and 25 for the same time within the runs' spread, where degree 3
/// was 1.2–1.4× slower; on faces of 10–14 nodes (40² and 48² in 64, 24²
/// in 16) it also halves them but took 8–11 % longer, so those keep
/// degree 1. The nonsmooth 65² grid cut in 64 takes 97 iterations instead
/// of 157 with it, in 4.2 s against 3.8 s.
pub const QUADRATIC_FACE_NODES: usize = 16;

/// Fewest nodes on an interface for [`MacroDegree::Auto`] to give it the
/// fields up to degree 5 ([`MacroDegree::AUTO_MAX`], 63 columns on a face where
/// degree 3 has 30). Measured with `cg` to 1e-8 on double-layer plates
/// (one or two runs each): on faces of about 100 nodes and more degree 4 took 20,
/// 23 and 24 iterations instead of 24, 25 and 37 (the 200² plate cut in 16,
/// the 410² one in 16 and 64) in 0.85–0.88× the time; degree 5 then takes
/// 16, 23 and 20 instead of 20, 29 and 24 (the 410² plate cut in 16 with
/// its equilibrium correction), and 12, 19 and 11 instead of 14, 21 and 12
/// on the 200², 410² and 130² plates cut in 4 (faces of 130–410 nodes), in
/// 0.93–1.04× the time of degree 4. Degree 6 saves 1–2 iterations more for
/// up to 1.06× the time. On faces of 33–65 nodes (130² in 16 and 64, 200²
/// in 64, 65² in 4) degree 4 cut the iterations by a fifth but took 0.97
/// to 1.13× the time, so those keep degree 3.
pub const QUINTIC_FACE_NODES: usize = 80;

/// The former name of [`QUINTIC_FACE_NODES`] (the threshold gave degree 4
/// until `"auto"` went up to degree 5).
#[deprecated(note = "use QUINTIC_FACE_NODES: \"auto\" now gives degree 5 from there")]
pub const QUARTIC_FACE_NODES: usize = QUINTIC_FACE_NODES;

impl MacroDegree {
    /// Highest degree accepted.
    pub const MAX: u8 = 6;

    /// Highest degree `Auto` gives (on interfaces of at least
    /// [`QUINTIC_FACE_NODES`] nodes).
    pub const AUTO_MAX: u8 = 5;

    pub fn is_default(&self) -> bool {
        *self == MacroDegree::default()
    }

    /// `Fixed(d)` where `d` is a degree accepted (1 to [`Self::MAX`]).
    pub fn fixed(d: u8) -> Option<MacroDegree> {
        (1..=Self::MAX).contains(&d).then_some(MacroDegree::Fixed(d))
    }

    /// Whether this is `Auto` or a degree accepted.
    pub fn is_valid(&self) -> bool {
        match *self {
            MacroDegree::Auto => true,
            MacroDegree::Fixed(d) => Self::fixed(d).is_some(),
        }
    }

    /// The highest degree used by `cg` (`cg` true) or the stationary
    /// method on a structure that is `flat` or not, with the adaptive macro
    /// space on or off.
    pub fn resolve(self, flat: bool, adaptive: bool, cg: bool) -> u8 {
        match self {
            MacroDegree::Fixed(d) => d,
            MacroDegree::Auto if cg && flat && !adaptive => Self::AUTO_MAX,
            MacroDegree::Auto => 1,
        }
    }

    /// The degree of one interface whose node count `nodes` gives,
    /// `resolved` being what [`Self::resolve`] gave: a fixed degree holds on
    /// every interface; `Auto` lowers it to 3 on those smaller than
    /// [`QUINTIC_FACE_NODES`], to 2 on those smaller than
    /// [`POLYNOMIAL_FACE_NODES`] and to 1 on those smaller than
    /// [`QUADRATIC_FACE_NODES`]. `nodes` is only called where the count can
    /// change the answer (`Auto` above degree 1).
    pub fn on_interface(self, resolved: u8, nodes: impl FnOnce() -> usize) -> u8 {
        match self {
            MacroDegree::Auto if resolved > 1 => match nodes() {
                n if n >= QUINTIC_FACE_NODES => resolved,
                n if n >= POLYNOMIAL_FACE_NODES => resolved.min(3),
                n if n >= QUADRATIC_FACE_NODES => resolved.min(2),
                _ => 1,
            },
            _ => resolved,
        }
    }
}

impl std::fmt::Display for MacroDegree {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MacroDegree::Auto => f.write_str("auto"),
            MacroDegree::Fixed(d) => write!(f, "{d}"),
        }
    }
}

impl std::str::FromStr for MacroDegree {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "auto" => Ok(MacroDegree::Auto),
            _ => s
                .parse::<u8>()
                .ok()
                .and_then(MacroDegree::fixed)
                .ok_or_else(|| format!("macro degree must be 1 to {} or \"auto\", got '{s}'", MacroDegree::MAX)),
        }
    }
}

impl Serialize for MacroDegree {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            MacroDegree::Auto => s.serialize_str("auto"),
            MacroDegree::Fixed(d) => s.serialize_u8(*d),
        }
    }
}

impl<'de> Deserialize<'de> for MacroDegree {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Int(i64),
            Str(String),
        }
        let bad = |what: String| {
            serde::de::Error::custom(format!(
                "solver.macro_degree: expected 1 to {} or \"auto\", got {what}",
                MacroDegree::MAX
            ))
        };
        match Raw::deserialize(d)? {
            Raw::Int(i) => u8::try_from(i)
                .ok()
                .and_then(MacroDegree::fixed)
                .ok_or_else(|| bad(i.to_string())),
            Raw::Str(s) => s.parse().map_err(|_| bad(format!("\"{s}\""))),
        }
    }
}

/// `[solver]` settings. Command-line flags override them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SolverSettings {
    #[serde(default)]
    pub method: Method,
    /// Subdomains of the automatic partition; 0 (also written `"auto"`,
    /// and the default when absent) lets the solver choose from the size
    /// and the thread count ([`crate::partition::resolve_subdomains`]).
    /// Not written when automatic.
    #[serde(default, deserialize_with = "subdomains_from_scene", skip_serializing_if = "is_auto")]
    pub subdomains: usize,
    #[serde(default = "default_tolerance")]
    pub tolerance: f64,
    #[serde(default = "default_max_iterations")]
    pub max_iterations: usize,
    #[serde(default)]
    pub search_direction: SearchDirection,
    /// Preconditioner of `cg` (ignored by the other methods).
    #[serde(default)]
    pub preconditioner: Preconditioner,
    /// Weights of the `cg` preconditioner across interfaces (ignored by the
    /// other methods). Not written when it is the default.
    #[serde(default, skip_serializing_if = "InterfaceScaling::is_default")]
    pub interface_scaling: InterfaceScaling,
    /// Adaptive macro space of `cg` (ignored by the other methods): on
    /// every face, the jumps whose local eigenvalue exceeds this threshold
    /// become macro columns (`crate::adaptive`); 0: none; `"auto"` (the
    /// default, not written): on where stiff parts hang on soft ones
    /// ([`AdaptiveThreshold`]).
    #[serde(default, skip_serializing_if = "AdaptiveThreshold::is_auto")]
    pub adaptive_threshold: AdaptiveThreshold,
    /// With the adaptive macro space, constraints on the edges too (the
    /// dofs shared by three or more subdomains), from the same eigenproblems
    /// on every pair of an edge's subdomains (`crate::adaptive`). `"auto"`
    /// (the default, not written): on where stiff parts hang on soft ones
    /// ([`AdaptiveEdges`]).
    #[serde(default, skip_serializing_if = "AdaptiveEdges::is_auto")]
    pub adaptive_edges: AdaptiveEdges,
    /// Degree of the polynomial fields in each interface's macro basis
    /// (`multilevel` and `cg`): 1, 2, 3, or `"auto"` (the default, not
    /// written): 3 for `cg` on the large interfaces of a flat structure
    /// without the adaptive space, 1 elsewhere ([`MacroDegree`]).
    #[serde(default, skip_serializing_if = "MacroDegree::is_default")]
    pub macro_degree: MacroDegree,
    /// Automatic partition into `subdomains` (ignored when the elements
    /// carry their subdomain). Not written when it is the default, so that
    /// scenes stay readable by versions without the field.
    #[serde(default, skip_serializing_if = "Partitioner::is_default")]
    pub partitioner: Partitioner,
    /// Fill-reducing ordering of the sparse factorizations: the whole
    /// structure's (direct solver), each subdomain's and each Dirichlet
    /// interior's. Not written when it is the default.
    #[serde(default, skip_serializing_if = "OrderingChoice::is_default")]
    pub ordering: OrderingChoice,
}

/// Fill-reducing ordering of a sparse Cholesky factorization. An nsdd
/// addition; the names are those the reports print for the ordering used.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, Hash)]
#[serde(rename_all = "snake_case")]
pub enum OrderingChoice {
    /// Per matrix, as CHOLMOD's default but stricter: AMD, and nested
    /// dissection too when AMD fills 8 nnz(A) or more (and the matrix has
    /// 200 rows or more); nested dissection wins when it saves at least 5 %
    /// of AMD's `nnz(L)`. A Dirichlet interior takes the kind its subdomain
    /// got, without the trial.
    #[default]
    Auto,
    /// Approximate minimum degree everywhere.
    Amd,
    /// METIS nested dissection everywhere (a Dirichlet interior under 200
    /// rows keeps AMD): no AMD trial, for structures known to be 3D.
    NestedDissection,
}

impl OrderingChoice {
    fn is_default(&self) -> bool {
        *self == OrderingChoice::default()
    }
}

impl std::str::FromStr for OrderingChoice {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "auto" => Ok(OrderingChoice::Auto),
            "amd" => Ok(OrderingChoice::Amd),
            "nested_dissection" => Ok(OrderingChoice::NestedDissection),
            _ => Err(format!(
                "ordering must be \"auto\", \"amd\" or \"nested_dissection\", got '{s}'"
            )),
        }
    }
}

/// How the automatic partition is made. An nsdd addition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, Hash)]
#[serde(rename_all = "lowercase")]
pub enum Partitioner {
    /// Recursive coordinate bisection of element midpoints.
    #[default]
    Bisection,
    /// METIS k-way partition of the node graph.
    Metis,
}

impl Partitioner {
    fn is_default(&self) -> bool {
        *self == Partitioner::default()
    }
}

impl std::str::FromStr for Partitioner {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "bisection" => Ok(Partitioner::Bisection),
            "metis" => Ok(Partitioner::Metis),
            _ => Err(format!("partitioner must be \"bisection\" or \"metis\", got '{s}'")),
        }
    }
}

/// `subdomains = N | 0 | "auto"` (0 and `"auto"` mean automatic).
fn subdomains_from_scene<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<usize, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Raw {
        Int(i64),
        Str(String),
    }
    match Raw::deserialize(d)? {
        Raw::Int(n) => usize::try_from(n).map_err(|_| {
            serde::de::Error::custom(format!(
                "solver.subdomains: expected a whole number of at least 0 or \"auto\", got {n}"
            ))
        }),
        Raw::Str(s) if s == "auto" => Ok(0),
        Raw::Str(s) => Err(serde::de::Error::custom(format!(
            "solver.subdomains: expected a whole number or \"auto\", got \"{s}\""
        ))),
    }
}

/// Whether `theta` is a valid `adaptive_threshold`: 0 (off) or finite and
/// above 1 (every face eigenvalue is at least 1). Checked by
/// [`SolverSettings::validate`] and the C setter.
pub(crate) fn adaptive_threshold_is_valid(theta: f64) -> bool {
    theta == 0.0 || (theta > 1.0 && theta.is_finite())
}

fn is_auto(subdomains: &usize) -> bool {
    *subdomains == 0
}
fn default_tolerance() -> f64 {
    1e-8
}
fn default_max_iterations() -> usize {
    20000
}

impl Default for SolverSettings {
    fn default() -> Self {
        SolverSettings {
            method: Method::Direct,
            subdomains: 0,
            tolerance: default_tolerance(),
            max_iterations: default_max_iterations(),
            search_direction: SearchDirection::Auto,
            preconditioner: Preconditioner::default(),
            interface_scaling: InterfaceScaling::default(),
            adaptive_threshold: AdaptiveThreshold::Auto,
            adaptive_edges: AdaptiveEdges::Auto,
            macro_degree: MacroDegree::default(),
            partitioner: Partitioner::default(),
            ordering: OrderingChoice::default(),
        }
    }
}

impl SolverSettings {
    /// Checks the settings, wherever they come from (a scene's `[solver]`,
    /// flags, code, the C ABI); the error names the `solver.*` field.
    pub fn validate(&self) -> Result<()> {
        let tolerance = self.tolerance;
        if !(tolerance > 0.0 && tolerance.is_finite()) {
            return Err(Error::input(
                "solver.tolerance",
                None,
                format!("must be positive, got {tolerance}"),
            ));
        }
        if self.max_iterations == 0 {
            return Err(Error::input("solver.max_iterations", None, "must be at least 1"));
        }
        let theta = self.adaptive_threshold;
        if !theta.is_valid() {
            return Err(Error::input(
                "solver.adaptive_threshold",
                None,
                format!("must be \"auto\", 0 (no adaptive macro columns) or a finite number above 1 (the eigenvalues are at least 1), got {theta}"),
            ));
        }
        if !self.macro_degree.is_valid() {
            return Err(Error::input(
                "solver.macro_degree",
                None,
                format!(
                    "must be 1 to {} or \"auto\", got {}",
                    MacroDegree::MAX,
                    self.macro_degree
                ),
            ));
        }
        if let SearchDirection::Value(d) = self.search_direction {
            if !(d > 0.0 && d.is_finite()) {
                return Err(Error::input(
                    "solver.search_direction",
                    None,
                    format!("must be positive, got {d}"),
                ));
            }
        }
        Ok(())
    }

    /// The scene's own `[solver]` settings.
    pub fn from_scene(scene: &crate::scene::Scene) -> SolverSettings {
        scene.solver.clone()
    }
}

/// What a domain-decomposition method runs: the coarse (macro) step or
/// not, and the stationary iteration or CG on the interface problem.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MethodConfig {
    /// With the macro space and coarse problem.
    pub coarse: bool,
    /// Conjugate gradient on the interface problem instead of the
    /// stationary iteration (linear case only; needs the coarse step).
    pub krylov: bool,
}

impl Method {
    /// The configuration of the iteration, `None` for the direct solver.
    /// The one place where a method's name becomes its configuration.
    pub fn config(&self) -> Option<MethodConfig> {
        match self {
            Method::Direct => None,
            Method::Monolevel => Some(MethodConfig {
                coarse: false,
                krylov: false,
            }),
            Method::Multilevel => Some(MethodConfig {
                coarse: true,
                krylov: false,
            }),
            Method::Cg => Some(MethodConfig {
                coarse: true,
                krylov: true,
            }),
        }
    }
}
