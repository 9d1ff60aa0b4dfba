//! The scene level of the C ABI: scenes, solver options, `nsdd_solve` and
//! the result.

use super::*;

// ---------------------------------------------------------------------------
// Scenes.

/// A new empty scene (no nodes, no elements, default effects and solver
/// settings), or NULL if memory ran out. Fill it with the `nsdd_scene_set_*`
/// functions; release it with `nsdd_scene_destroy`.
#[unsafe(no_mangle)]
pub extern "C" fn nsdd_scene_new() -> *mut NsddScene {
    catch_unwind(|| {
        boxed(NsddScene {
            scene: Scene::default(),
        })
    })
    .unwrap_or(std::ptr::null_mut())
}

/// Releases a scene (NULL is ignored).
///
/// # Safety
/// `scene` must be NULL or a live scene handle, not used afterwards.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_destroy(scene: *mut NsddScene) {
    let _ = catch_unwind(AssertUnwindSafe(|| unsafe { destroy(scene) }));
}

pub(super) fn load_validated(scene: Scene, out: *mut *mut NsddScene) -> FfiResult {
    scene.validate()?;
    // SAFETY: `out` was checked by `clear_out`.
    unsafe { out.write(boxed(NsddScene { scene })) };
    Ok(())
}

/// Reads and validates a scene file (`.json` is JSON, anything else TOML,
/// as in SCENE.md) into a new handle stored in `*out` (NULL on failure).
/// Errors: IO_ERROR, PARSE_ERROR, INVALID_INPUT (the message names the field
/// and index).
///
/// # Safety
/// `path` must be a NUL-terminated UTF-8 string; `out` must point to
/// writable storage for one pointer.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_from_file(path: *const c_char, out: *mut *mut NsddScene) -> NsddStatus {
    ffi_guard(|| {
        unsafe { clear_out(out, "out")? };
        let path = unsafe { c_str(path, "path")? };
        load_validated(Scene::load(std::path::Path::new(path))?, out)
    })
}

/// Parses and validates scene text (JSON if `is_json`, else TOML) into a new
/// handle stored in `*out` (NULL on failure). Errors: PARSE_ERROR,
/// INVALID_INPUT.
///
/// # Safety
/// `text` must be a NUL-terminated UTF-8 string; `out` must point to
/// writable storage for one pointer.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_from_str(
    text: *const c_char,
    is_json: bool,
    out: *mut *mut NsddScene,
) -> NsddStatus {
    ffi_guard(|| {
        unsafe { clear_out(out, "out")? };
        let text = unsafe { c_str(text, "text")? };
        let scene = if is_json {
            Scene::from_json_str(text)?
        } else {
            Scene::from_toml_str(text)?
        };
        load_validated(scene, out)
    })
}

/// Sets the scene's name (used in results).
///
/// # Safety
/// `scene` must be a live scene handle; `name` a NUL-terminated UTF-8 string.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_name(scene: *mut NsddScene, name: *const c_char) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let name = unsafe { c_str(name, "name")? };
        s.scene.scene.name = name.to_string();
        Ok(())
    })
}

/// Replaces the nodes: `x`, `y`, `z` each hold `n` coordinates.
///
/// # Safety
/// `scene` must be a live scene handle; `x`, `y`, `z` must each point to
/// `n` readable doubles (or be NULL when `n` is 0).
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_nodes(
    scene: *mut NsddScene,
    n: usize,
    x: *const f64,
    y: *const f64,
    z: *const f64,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let (x, y, z) = unsafe { (slice(x, n, "x")?, slice(y, n, "y")?, slice(z, n, "z")?) };
        check_finite("x", x)?;
        check_finite("y", y)?;
        check_finite("z", z)?;
        s.scene.nodes = Nodes {
            x: x.to_vec(),
            y: y.to_vec(),
            z: z.to_vec(),
        };
        Ok(())
    })
}

/// Replaces the elements: `m` entries each of end nodes `a`, `b` (0-based
/// node indices), `kind` (`NSDD_ELEMENT_KIND_BAR` = 0 or
/// `NSDD_ELEMENT_KIND_CABLE` = 1), axial stiffness `ea` (> 0) and prestress
/// `t0` (tension positive; NULL for none). A kind other than 0 or 1 is
/// INVALID_ARGUMENT; node indices are checked against the nodes when the
/// scene is validated or solved (INVALID_INPUT naming `elements.a` / `.b`).
///
/// # Safety
/// `scene` must be a live scene handle; `a`, `b`, `kind`, `ea` must each
/// point to `m` readable values, `t0` to `m` doubles or be NULL.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_elements(
    scene: *mut NsddScene,
    m: usize,
    a: *const usize,
    b: *const usize,
    kind: *const u8,
    ea: *const f64,
    t0: *const f64,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let (a, b) = unsafe { (slice(a, m, "a")?, slice(b, m, "b")?) };
        let kind = unsafe { slice(kind, m, "kind")? };
        let ea = unsafe { slice(ea, m, "ea")? };
        let t0 = if t0.is_null() {
            &[][..]
        } else {
            unsafe { slice(t0, m, "t0")? }
        };
        let kinds = kind
            .iter()
            .enumerate()
            .map(|(i, &k)| match k {
                0 => Ok(ElementKind::Bar),
                1 => Ok(ElementKind::Cable),
                _ => Err(invalid(format!("kind[{i}] = {k}: expected 0 (bar) or 1 (cable)"))),
            })
            .collect::<FfiResult<Vec<_>>>()?;
        let el = &mut s.scene.elements;
        el.a = a.to_vec();
        el.b = b.to_vec();
        el.kind = kinds;
        el.ea = ea.to_vec();
        el.t0 = t0.to_vec();
        Ok(())
    })
}

/// Replaces the supports: `k` entries of `node` and `mask`, where `mask`
/// combines `NSDD_SUPPORT_X` (1), `NSDD_SUPPORT_Y` (2) and `NSDD_SUPPORT_Z`
/// (4); a mask of 0 or above 7 is INVALID_ARGUMENT.
///
/// # Safety
/// `scene` must be a live scene handle; `node` and `mask` must each point
/// to `k` readable values.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_supports(
    scene: *mut NsddScene,
    k: usize,
    node: *const usize,
    mask: *const u8,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let (node, mask) = unsafe { (slice(node, k, "node")?, slice(mask, k, "mask")?) };
        let dofs = mask
            .iter()
            .enumerate()
            .map(|(i, &m)| {
                if m == 0 || m > 7 {
                    return Err(invalid(format!(
                        "mask[{i}] = {m}: expected 1..7 (bit 0 x, bit 1 y, bit 2 z)"
                    )));
                }
                Ok(["x", "y", "z"]
                    .iter()
                    .enumerate()
                    .filter(|(c, _)| m & (1 << c) != 0)
                    .map(|(_, s)| *s)
                    .collect())
            })
            .collect::<FfiResult<Vec<String>>>()?;
        s.scene.supports.node = node.to_vec();
        s.scene.supports.dofs = dofs;
        Ok(())
    })
}

/// Replaces the nodal loads (load case 0): `k` entries of `node`, `fx`,
/// `fy`, `fz`.
///
/// # Safety
/// `scene` must be a live scene handle; `node`, `fx`, `fy`, `fz` must each
/// point to `k` readable values.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_loads(
    scene: *mut NsddScene,
    k: usize,
    node: *const usize,
    fx: *const f64,
    fy: *const f64,
    fz: *const f64,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let node = unsafe { slice(node, k, "node")? };
        let (fx, fy, fz) = unsafe { (slice(fx, k, "fx")?, slice(fy, k, "fy")?, slice(fz, k, "fz")?) };
        let l = &mut s.scene.loads;
        l.node = node.to_vec();
        l.fx = fx.to_vec();
        l.fy = fy.to_vec();
        l.fz = fz.to_vec();
        Ok(())
    })
}

/// Sets the effects the scene calls for (SCENE.md `[effects]`).
///
/// # Safety
/// `scene` must be a live scene handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_effects(
    scene: *mut NsddScene,
    unilateral_cables: bool,
    prestress: bool,
    geometric_stiffness: bool,
    self_weight: bool,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let e = &mut s.scene.effects;
        e.unilateral_cables = unilateral_cables;
        e.prestress = prestress;
        e.geometric_stiffness = geometric_stiffness;
        e.self_weight = self_weight;
        Ok(())
    })
}

/// Sets the data of the self-weight effect: `m` masses per unit length (one
/// per element) and the gravity vector `gravity[3]` (NULL for the default
/// of SCENE.md).
///
/// # Safety
/// `scene` must be a live scene handle; `mass_per_length` must point to `m`
/// doubles; `gravity` must be NULL or point to 3 doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_self_weight(
    scene: *mut NsddScene,
    m: usize,
    mass_per_length: *const f64,
    gravity: *const f64,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let mpl = unsafe { slice(mass_per_length, m, "mass_per_length")? };
        let g = if gravity.is_null() {
            None
        } else {
            let g = unsafe { slice(gravity, 3, "gravity")? };
            Some([g[0], g[1], g[2]])
        };
        s.scene.elements.mass_per_length = mpl.to_vec();
        s.scene.scene.gravity = g;
        Ok(())
    })
}

/// Checks every field of the scene, as `nsdd_solve` does first. Errors:
/// INVALID_INPUT, with a message naming the field and index.
///
/// # Safety
/// `scene` must be a live scene handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_validate(scene: *const NsddScene) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle(scene, "scene")? };
        s.scene.validate()?;
        Ok(())
    })
}

/// Number of nodes of the scene into `*out`.
///
/// # Safety
/// `scene` must be a live scene handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_num_nodes(scene: *const NsddScene, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle(scene, "scene")? };
        unsafe { write_out(out, "out", s.scene.nodes.x.len()) }
    })
}

/// Number of elements of the scene into `*out`.
///
/// # Safety
/// `scene` must be a live scene handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_num_elements(scene: *const NsddScene, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle(scene, "scene")? };
        unsafe { write_out(out, "out", s.scene.elements.a.len()) }
    })
}

// ---------------------------------------------------------------------------
// Solver options.

pub(super) fn default_options() -> SolveOptions {
    SolverSettings::default()
}

/// New solver options with the defaults of SCENE.md (direct, 1 subdomain,
/// tolerance 1e-8, 20000 iterations, automatic search direction), or NULL
/// if memory ran out. Release with `nsdd_options_destroy`.
#[unsafe(no_mangle)]
pub extern "C" fn nsdd_options_new() -> *mut NsddOptions {
    catch_unwind(|| {
        boxed(NsddOptions {
            opts: default_options(),
        })
    })
    .unwrap_or(std::ptr::null_mut())
}

/// New solver options copied from the scene's own `[solver]` settings into
/// `*out` (NULL on failure).
///
/// # Safety
/// `scene` must be a live scene handle; `out` must point to writable
/// storage for one pointer.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_from_scene(scene: *const NsddScene, out: *mut *mut NsddOptions) -> NsddStatus {
    ffi_guard(|| {
        unsafe { clear_out(out, "out")? };
        let s = unsafe { handle(scene, "scene")? };
        unsafe {
            out.write(boxed(NsddOptions {
                opts: SolveOptions::from_scene(&s.scene),
            }))
        };
        Ok(())
    })
}

/// Releases options (NULL is ignored).
///
/// # Safety
/// `options` must be NULL or a live options handle, not used afterwards.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_destroy(options: *mut NsddOptions) {
    let _ = catch_unwind(AssertUnwindSafe(|| unsafe { destroy(options) }));
}

/// Sets the method: one of `NsddMethod` (0 direct, 1 monolevel, 2
/// multilevel, 3 cg); any other value is INVALID_ARGUMENT.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_method(options: *mut NsddOptions, method: u32) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.method = match method {
            0 => Method::Direct,
            1 => Method::Monolevel,
            2 => Method::Multilevel,
            3 => Method::Cg,
            _ => {
                return Err(invalid(format!(
                    "method = {method}: expected 0 (direct), 1 (monolevel), 2 (multilevel) or 3 (cg)"
                )))
            }
        };
        Ok(())
    })
}

/// Sets the preconditioner of the `cg` method: one of `NsddPreconditioner`
/// (0 dirichlet, 1 lumped); any other value is INVALID_ARGUMENT. Ignored
/// by the other methods.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_preconditioner(options: *mut NsddOptions, preconditioner: u32) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.preconditioner = match preconditioner {
            0 => Preconditioner::Dirichlet,
            1 => Preconditioner::Lumped,
            _ => {
                return Err(invalid(format!(
                    "preconditioner = {preconditioner}: expected 0 (dirichlet) or 1 (lumped)"
                )))
            }
        };
        Ok(())
    })
}

/// Sets the interface scaling of the `cg` preconditioner, overriding the
/// scene's `[solver] interface_scaling`: one of `NsddInterfaceScaling` (0
/// deluxe, 1 contrast, 2 multiplicity, 3 stiffness, 4 none, 5 economic
/// deluxe, the default); any other value is INVALID_ARGUMENT. Ignored by
/// the other methods.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_interface_scaling(options: *mut NsddOptions, scaling: u32) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.interface_scaling = match scaling {
            0 => InterfaceScaling::Deluxe,
            1 => InterfaceScaling::Contrast,
            2 => InterfaceScaling::Multiplicity,
            3 => InterfaceScaling::Stiffness,
            4 => InterfaceScaling::None,
            5 => InterfaceScaling::EconomicDeluxe,
            _ => {
                return Err(invalid(format!(
                    "interface_scaling = {scaling}: expected 0 (deluxe), 1 (contrast), 2 (multiplicity), 3 (stiffness), 4 (none) or 5 (economic deluxe)"
                )))
            }
        };
        Ok(())
    })
}

/// Sets the threshold of `cg`'s adaptive macro space, overriding the
/// scene's `[solver] adaptive_threshold`: on every face, the jumps whose
/// local eigenvalue exceeds it become macro columns (worth it where stiff
/// bars hang on soft cables; 5 is a good start). 0 switches it off; other
/// values must be finite and above 1, else INVALID_ARGUMENT. The default
/// is automatic ([`nsdd_options_set_adaptive_threshold_auto`]). Ignored by
/// the other methods.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_adaptive_threshold(options: *mut NsddOptions, threshold: f64) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        if !crate::settings::adaptive_threshold_is_valid(threshold) {
            return Err(invalid(format!(
                "adaptive_threshold = {threshold}: expected 0 (off) or a finite number above 1"
            )));
        }
        o.opts.adaptive_threshold = crate::settings::AdaptiveThreshold::Value(threshold);
        Ok(())
    })
}

/// Lets the solver choose the threshold of `cg`'s adaptive macro space
/// (the scene's `adaptive_threshold = "auto"`, and the default): 5 where
/// the elements' axial stiffnesses `EA/L` span 100× or more, off
/// elsewhere. Overrides the scene's `[solver] adaptive_threshold`.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_adaptive_threshold_auto(options: *mut NsddOptions) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.adaptive_threshold = crate::settings::AdaptiveThreshold::Auto;
        Ok(())
    })
}

/// Switches `cg`'s adaptive constraints on the edges (dofs shared by three
/// or more subdomains) on (`enable` non-zero) or off, overriding the
/// scene's `[solver] adaptive_edges`; they need the adaptive macro space
/// ([`nsdd_options_set_adaptive_threshold`]). By default (and after
/// [`nsdd_options_set_adaptive_edges_auto`]) they are on where the
/// elements' `EA/L` span 100× or more, as the adaptive space itself: on 3D
/// towers whose bars are far stiffer than their cables they cut the
/// iterations 2-11×; on plates they cost more set-up than they save.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_adaptive_edges(
    options: *mut NsddOptions,
    enable: std::ffi::c_int,
) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.adaptive_edges = (enable != 0).into();
        Ok(())
    })
}

/// Gives the choice of `cg`'s constraints on the edges back to the solver
/// (the default: on where the elements' `EA/L` span 100× or more),
/// overriding the scene's `[solver] adaptive_edges`.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_adaptive_edges_auto(options: *mut NsddOptions) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.adaptive_edges = crate::settings::AdaptiveEdges::Auto;
        Ok(())
    })
}

/// Sets the degree of the polynomial fields in each interface's macro
/// basis (`multilevel` and `cg`), overriding the scene's `[solver]
/// macro_degree`: 1 (rigid motions and in-plane extensions) to 6 (2 to
/// 6 add the quadratic, cubic, ... fields per component: on plates `cg`
/// takes about half the iterations); 0 lets the solver choose (the
/// default: 5 for `cg` on the interfaces of 80 nodes or more of a
/// flat structure without the adaptive macro space, 3 on its interfaces
/// of 20 to 79 nodes, 2 on those of 16 to 19, 1 elsewhere). Any other
/// value is
/// INVALID_ARGUMENT.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_macro_degree(options: *mut NsddOptions, degree: u32) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.macro_degree = match degree {
            0 => crate::settings::MacroDegree::Auto,
            d => u8::try_from(d)
                .ok()
                .and_then(crate::settings::MacroDegree::fixed)
                .ok_or_else(|| {
                    invalid(format!(
                        "macro_degree = {degree}: expected 0 (auto) or 1 to {}",
                        crate::settings::MacroDegree::MAX
                    ))
                })?,
        };
        Ok(())
    })
}

/// Sets the automatic partitioner, overriding the scene's `[solver]
/// partitioner`: a [`NsddPartitioner`] value, 0 coordinate bisection, 1
/// METIS k-way; any other value is
/// INVALID_ARGUMENT. Ignored by the direct method and when the scene's
/// elements carry their subdomain.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_partitioner(options: *mut NsddOptions, partitioner: u32) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.partitioner = match partitioner {
            p if p == NsddPartitioner::Bisection as u32 => crate::scene::Partitioner::Bisection,
            p if p == NsddPartitioner::Metis as u32 => crate::scene::Partitioner::Metis,
            _ => {
                return Err(invalid(format!(
                    "partitioner = {partitioner}: expected 0 (bisection) or 1 (metis)"
                )))
            }
        };
        Ok(())
    })
}

/// Sets the fill-reducing ordering of the sparse factorizations (the
/// whole structure's, each subdomain's and each Dirichlet interior's),
/// overriding the scene's `[solver] ordering`: a [`NsddOrdering`] value,
/// 0 auto (AMD, and nested dissection where AMD fills 8 nnz(K) or more and
/// it saves 5 % of that), 1 AMD, 2 nested dissection; any other value is
/// INVALID_ARGUMENT.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_ordering(options: *mut NsddOptions, ordering: u32) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.ordering = match ordering {
            o if o == NsddOrdering::Auto as u32 => crate::scene::OrderingChoice::Auto,
            o if o == NsddOrdering::Amd as u32 => crate::scene::OrderingChoice::Amd,
            o if o == NsddOrdering::NestedDissection as u32 => crate::scene::OrderingChoice::NestedDissection,
            _ => {
                return Err(invalid(format!(
                    "ordering = {ordering}: expected 0 (auto), 1 (amd) or 2 (nested_dissection)"
                )))
            }
        };
        Ok(())
    })
}

/// Sets the number of subdomains of the automatic partition; 0 means
/// automatic, as [`nsdd_options_set_subdomains_auto`] (ignored by the direct
/// method and at the algebraic level).
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_subdomains(options: *mut NsddOptions, subdomains: usize) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.subdomains = subdomains;
        Ok(())
    })
}

/// Lets the solver choose the number of subdomains from the size and the
/// thread count: `max(threads, ceil(free dofs / 8000))`, at least 2, at most
/// `elements / 16` (the default unless the scene sets a count). The
/// result's notes say what was chosen.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_subdomains_auto(options: *mut NsddOptions) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.subdomains = 0;
        Ok(())
    })
}

/// Sets the stopping tolerance on the iteration indicator (finite, > 0).
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_tolerance(options: *mut NsddOptions, tolerance: f64) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        if !(tolerance > 0.0 && tolerance.is_finite()) {
            return Err(invalid(format!(
                "tolerance must be positive and finite, got {tolerance}"
            )));
        }
        o.opts.tolerance = tolerance;
        Ok(())
    })
}

/// Sets the iteration limit (>= 1).
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_max_iterations(
    options: *mut NsddOptions,
    max_iterations: usize,
) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        if max_iterations == 0 {
            return Err(invalid("max_iterations must be at least 1"));
        }
        o.opts.max_iterations = max_iterations;
        Ok(())
    })
}

/// Sets the search direction `d` of the local stage (finite, > 0, as in a
/// scene's `[solver]`); anything else is INVALID_ARGUMENT. The automatic
/// choice is `nsdd_options_set_search_direction_auto`.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_search_direction(options: *mut NsddOptions, d: f64) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        if !(d > 0.0 && d.is_finite()) {
            return Err(invalid(format!(
                "search direction must be positive and finite, got {d} (automatic: nsdd_options_set_search_direction_auto)"
            )));
        }
        o.opts.search_direction = SearchDirection::Value(d);
        Ok(())
    })
}

/// Selects the automatic search direction (the default): the lumped
/// stiffness weights scaled to a fraction of the stability limit.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_search_direction_auto(options: *mut NsddOptions) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.search_direction = SearchDirection::Auto;
        Ok(())
    })
}

// ---------------------------------------------------------------------------
// Solving a scene and reading the result.

/// Validates and solves the scene with `options` (NULL: the scene's own
/// `[solver]` settings) and stores a new result handle in `*out_result`
/// (NULL on failure). A run that stops at the iteration limit is not an
/// error: check `nsdd_result_converged`. Errors: INVALID_INPUT, MECHANISM,
/// INDEFINITE_SUBDOMAIN, METHOD_NOT_APPLICABLE, DIVERGED, NUMERICAL.
///
/// # Safety
/// `scene` must be a live scene handle, `options` NULL or a live options
/// handle, `out_result` must point to writable storage for one pointer.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_solve(
    scene: *const NsddScene,
    options: *const NsddOptions,
    out_result: *mut *mut NsddResult,
) -> NsddStatus {
    ffi_guard(|| {
        unsafe { clear_out(out_result, "out_result")? };
        let s = unsafe { handle(scene, "scene")? };
        let opts = if options.is_null() {
            SolveOptions::from_scene(&s.scene)
        } else {
            unsafe { handle(options, "options")? }.opts.clone()
        };
        let result = solve(&s.scene, &opts)?;
        // Divergence stays an error status here, as before the outcome
        // kept its history: no result handle for a diverged run.
        if let Some(e) = result.divergence() {
            return Err(e.into());
        }
        unsafe { out_result.write(boxed(NsddResult { result })) };
        Ok(())
    })
}

/// Releases a result (NULL is ignored).
///
/// # Safety
/// `result` must be NULL or a live result handle, not used afterwards.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_destroy(result: *mut NsddResult) {
    let _ = catch_unwind(AssertUnwindSafe(|| unsafe { destroy(result) }));
}

/// Number of nodes of the solved scene into `*out`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_num_nodes(result: *const NsddResult, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.displacements.len()) }
    })
}

/// Number of elements of the solved scene into `*out`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_num_elements(result: *const NsddResult, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.tensions.len()) }
    })
}

pub(super) fn check_exact(name: &str, len: usize, expected: usize, what: &str) -> FfiResult {
    if len != expected {
        return Err(invalid(format!("{name}: len = {len}, expected {expected} ({what})")));
    }
    Ok(())
}

/// Nodal displacements into `out`, node after node (`ux0, uy0, uz0, ux1,
/// ...`); `len` must be exactly `3 * num_nodes`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to `len`
/// writable doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_displacements(result: *const NsddResult, out: *mut f64, len: usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        let d = &r.result.displacements;
        check_exact("displacements", len, 3 * d.len(), "3 * num_nodes")?;
        let out = unsafe { slice_mut(out, len, "out")? };
        for (o, v) in out.chunks_exact_mut(3).zip(d) {
            o.copy_from_slice(v);
        }
        Ok(())
    })
}

/// Element tensions (axial forces, tension positive) into `out`; `len`
/// must be exactly `num_elements`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to `len`
/// writable doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_tensions(result: *const NsddResult, out: *mut f64, len: usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        check_exact("tensions", len, r.result.tensions.len(), "num_elements")?;
        unsafe { slice_mut(out, len, "out")? }.copy_from_slice(&r.result.tensions);
        Ok(())
    })
}

/// Slack flags into `out` (1 for a slack cable, 0 otherwise); `len` must be
/// exactly `num_elements`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to `len`
/// writable bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_slack(result: *const NsddResult, out: *mut u8, len: usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        check_exact("slack", len, r.result.slack.len(), "num_elements")?;
        for (o, &s) in unsafe { slice_mut(out, len, "out")? }.iter_mut().zip(&r.result.slack) {
            *o = s as u8;
        }
        Ok(())
    })
}

/// Iterations of the (last) solve into `*out`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_iterations(result: *const NsddResult, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.iterations) }
    })
}

/// Subdomains the solve ran on, into `*out`: 1 for `direct`, else the
/// count asked for unless the set-up merged a subdomain that was
/// indefinite on its own into a neighbour (compressed struts on nsdd's own
/// partition; the result's notes list the merges).
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_subdomains(result: *const NsddResult, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.subdomains) }
    })
}

/// Whether every solve reached the tolerance, into `*out`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `bool`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_converged(result: *const NsddResult, out: *mut bool) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.converged) }
    })
}

/// How far the top-level tensions miss equilibrium with the loads,
/// `‖f − Σ_e H_e t_e − K_G u‖ / ‖t‖` at the free dofs (`K_G u`: the forces
/// of the geometric stiffness, where simulated), into `*out`; NaN where it
/// is not measured (no load). An
/// iterative solve is converged only with this at or below its tolerance.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `double`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_equilibrium_residual(result: *const NsddResult, out: *mut f64) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.equilibrium_residual.unwrap_or(f64::NAN)) }
    })
}

/// The equilibrium corrections of an iterative solve (its tensions left
/// the loads unbalanced by more than half the tolerance, and corrections
/// for those loads were solved on the same set-up and added) into
/// `*corrections`, and the iterations they took, included in
/// `nsdd_result_iterations`, into `*iterations`; both 0 when none was
/// needed.
///
/// # Safety
/// `result` must be a live result handle; `corrections` and `iterations`
/// must point to writable `size_t`s.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_equilibrium_corrections(
    result: *const NsddResult,
    corrections: *mut usize,
    iterations: *mut usize,
) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        let rf = r.result.equilibrium_refinement;
        unsafe { write_out(corrections, "corrections", rf.map_or(0, |rf| rf.corrections))? };
        unsafe { write_out(iterations, "iterations", rf.map_or(0, |rf| rf.iterations)) }
    })
}

/// Why the run stopped, as an `NsddStopReason` value, into `*out`: for
/// an unconverged result, the first solve (load-path steps, the top level,
/// the load cases) that did not converge says why.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `uint32_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_stop_reason(result: *const NsddResult, out: *mut u32) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", NsddStopReason::from(r.result.status) as u32) }
    })
}

/// Number of entries of the convergence history into `*out`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_history_len(result: *const NsddResult, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.history.len()) }
    })
}

/// The convergence history: the stopping indicator and the elapsed time in
/// seconds of every iteration, into `indicator` and `time_s` (either may be
/// NULL to skip it); `len` must be exactly `history_len`.
///
/// # Safety
/// `result` must be a live result handle; `indicator` and `time_s` must
/// each be NULL or point to `len` writable doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_history(
    result: *const NsddResult,
    indicator: *mut f64,
    time_s: *mut f64,
    len: usize,
) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        let h = &r.result.history;
        check_exact("history", len, h.len(), "history_len")?;
        if !indicator.is_null() {
            for (o, e) in unsafe { slice_mut(indicator, len, "indicator")? }.iter_mut().zip(h) {
                *o = e.indicator;
            }
        }
        if !time_s.is_null() {
            for (o, e) in unsafe { slice_mut(time_s, len, "time_s")? }.iter_mut().zip(h) {
                *o = e.time_s;
            }
        }
        Ok(())
    })
}

/// Writes the result as JSON (the `--out result.json` format of SCENE.md)
/// to `path`. Errors: IO_ERROR.
///
/// # Safety
/// `result` must be a live result handle; `path` a NUL-terminated UTF-8 string.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_write_json(result: *const NsddResult, path: *const c_char) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        let path = unsafe { c_str(path, "path")? };
        std::fs::write(path, r.result.to_json()).map_err(|e| fail(NsddStatus::IoError, format!("{path}: {e}")))
    })
}
