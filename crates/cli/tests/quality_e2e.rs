//! End-to-end tests of what a user asks about an image's quality before and after it renders:
//! `--denoise` (refused by a build without it) and `submit --quote`.

use std::process::{Command, Output};

#[cfg(not(feature = "denoise"))]
use crate::common;

fn tessera() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tessera"))
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A tessera built without the `denoise` feature refuses `--denoise` before rendering, locally
/// and through `--workers`, saying how to build one that denoises; nothing is written.
#[test]
#[cfg(not(feature = "denoise"))]
fn denoise_is_refused_by_a_build_without_it_saying_how_to_build_one() {
    let dir = common::scratch("quality", "no-denoise");
    for workers in ["0", "1"] {
        let out = dir.join(format!("d{workers}.exr"));
        let o = tessera()
            .args(["render", "--denoise", "--workers", workers, "--spp", "4", "--out", out.to_str().unwrap()])
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
        assert!(
            stderr(&o).contains("--features tessera-cli/denoise") && stderr(&o).contains("OIDN_DIR"),
            "{}",
            stderr(&o)
        );
        assert!(!out.exists() && !out.with_extension("png").exists(), "something was written");
    }
}

/// `submit --quote` without a farm to ask still quotes the samples (exact for a fixed render)
/// and their core-seconds here, says the farm was not reached, and submits nothing.
#[test]
fn a_quote_without_a_farm_says_the_samples_and_submits_nothing() {
    let args = ["submit", "builtin:cornell-box", "--quote", "--width", "64", "--height", "64"];
    let o = tessera()
        .args(args)
        .args(["--spp", "32", "--quality", "fixed", "--coordinator", "http://127.0.0.1:9"])
        .env("TESSERA_WAIT_FOR_COORDINATOR", "0")
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", stderr(&o));
    for needle in
        ["samples: 0.1 M (0.1-0.1 M), 32.0 spp on average", "core-seconds", "not reached", "nothing was submitted"]
    {
        assert!(said.contains(needle), "no '{needle}' in:\n{said}");
    }
}
