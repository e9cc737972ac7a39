//! With the `denoise` feature, `tessera` finds Open Image Denoise at run time where it was linked
//! from (`$OIDN_DIR/lib`, recorded as the binary's run path), so it runs without
//! LD_LIBRARY_PATH. A binary copied to another machine finds the library on its usual paths.

fn main() {
    println!("cargo:rerun-if-env-changed=OIDN_DIR");
    if std::env::var_os("CARGO_FEATURE_DENOISE").is_some()
        && let Some(dir) = std::env::var_os("OIDN_DIR").filter(|d| !d.is_empty())
    {
        let lib = std::path::Path::new(&dir).join("lib");
        println!("cargo:rustc-link-arg-bins=-Wl,-rpath,{}", lib.display());
        println!("cargo:rustc-link-arg-tests=-Wl,-rpath,{}", lib.display());
    }
}
