//! With the `oidn` feature and `OIDN_DIR` set, this crate's tests find the library at run time
//! where it was linked from (the binary's own build script does the same for `tessera`).

fn main() {
    println!("cargo:rerun-if-env-changed=OIDN_DIR");
    if std::env::var_os("CARGO_FEATURE_OIDN").is_some()
        && let Some(dir) = std::env::var_os("OIDN_DIR").filter(|d| !d.is_empty())
    {
        let lib = std::path::Path::new(&dir).join("lib");
        println!("cargo:rustc-link-arg-tests=-Wl,-rpath,{}", lib.display());
    }
}
