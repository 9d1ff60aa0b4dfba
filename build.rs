//! Generates the C header `include/nsdd.h` from `src/capi/` with cbindgen
//! (pinned to =0.29.0 in Cargo.toml; settings in `cbindgen.toml`).
//!
//! The header is committed. Every build regenerates it into
//! `$OUT_DIR/nsdd.h` and, when the text differs, rewrites `include/nsdd.h`
//! (an identical header is never rewritten, so its mtime is stable).
//!
//! Header check (CI): build with `NSDD_CHECK_HEADER=1`, e.g.
//! `NSDD_CHECK_HEADER=1 cargo build --release`. In that mode the build never
//! writes `include/nsdd.h`; it fails if the committed file differs from the
//! freshly generated one (fix: run `cargo build` without the variable and
//! commit `include/nsdd.h`). Outside that mode a cbindgen failure (for example
//! while `src/capi/` is mid-edit) is only a warning, since rustc reports the
//! real error.
//!
//! Only `src/capi/`, `cbindgen.toml`, `include/nsdd.h` and this file
//! trigger a re-run, so the rest of the crate builds without touching
//! cbindgen. (Watching the header costs at most one extra run after the
//! script rewrites it; then the text is identical and nothing is written.)

use std::env;
use std::fs;
use std::path::PathBuf;

fn main() {
    println!("cargo:rerun-if-changed=src/capi");
    println!("cargo:rerun-if-changed=cbindgen.toml");
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=include/nsdd.h");
    println!("cargo:rerun-if-env-changed=NSDD_CHECK_HEADER");

    let check = env::var("NSDD_CHECK_HEADER").is_ok_and(|v| v == "1");
    let crate_dir = PathBuf::from(env::var("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR"));
    let out_dir = PathBuf::from(env::var("OUT_DIR").expect("OUT_DIR"));
    let committed = crate_dir.join("include").join("nsdd.h");

    let generated = cbindgen::Config::from_file(crate_dir.join("cbindgen.toml"))
        .map_err(|e| format!("cbindgen.toml: {e}"))
        .and_then(|config| {
            cbindgen::Builder::new()
                .with_config(config)
                .with_src(crate_dir.join("src").join("capi").join("mod.rs"))
                .generate()
                .map_err(|e| format!("cbindgen: {e}"))
        })
        .map(|bindings| {
            let mut text = Vec::new();
            bindings.write(&mut text);
            text
        });
    let text = match generated {
        Ok(t) => t,
        Err(e) if check => panic!("cannot generate the C header: {e}"),
        Err(e) => {
            println!("cargo:warning=include/nsdd.h not regenerated: {e}");
            return;
        }
    };

    let fresh = out_dir.join("nsdd.h");
    fs::write(&fresh, &text).expect("write $OUT_DIR/nsdd.h");
    let current = fs::read(&committed).ok();
    if current.as_deref() == Some(text.as_slice()) {
        return;
    }
    if check {
        panic!(
            "include/nsdd.h is out of date with src/capi/ (fresh copy: {}); run `cargo build` and commit include/nsdd.h",
            fresh.display()
        );
    }
    fs::create_dir_all(committed.parent().expect("include dir")).expect("create include/");
    fs::write(&committed, &text).expect("write include/nsdd.h");
}
