//! Refining a render made on this machine: `tessera render --keep-sums` keeps its exact sums
//! beside the image, and `--refine` goes on from them to a lower target error or more samples,
//! to the same file as a render with that quality from the start; what cannot give those bits
//! is refused, saying what to change.

use crate::common;
use common::farm::{bin, local_render, scratch};
use std::process::Command;

fn render(args: &[&str]) -> std::process::Output {
    Command::new(bin()).arg("render").args(args).args(["--quiet", "--threads", "2"]).output().unwrap()
}

#[test]
fn a_kept_render_refines_to_the_file_of_a_direct_one_and_refuses_what_would_differ() {
    let dir = scratch("refine-local");
    let path = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let base = ["--width", "96", "--height", "64", "--seed", "2", "--spp", "256", "--min-spp", "32"];
    let with = |extra: &[&str]| -> Vec<String> { base.iter().chain(extra).map(|s| s.to_string()).collect() };
    let run = |args: Vec<String>, out: &str| {
        let mut all = args;
        all.extend(["--out".to_string(), path(out)]);
        let refs: Vec<&str> = all.iter().map(String::as_str).collect();
        render(&refs)
    };
    // A lower target error, then more samples: each step the file of a direct render.
    let o = run(with(&["--target-error", "0.1", "--keep-sums"]), "coarse.exr");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(dir.join("coarse.sums").exists(), "the sums are kept beside the image");
    let finer = with(&["--target-error", "0.05"]);
    let o = run([finer.clone(), vec!["--refine".into(), path("coarse.exr")]].concat(), "finer.exr");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let direct: Vec<&str> = finer.iter().map(String::as_str).collect();
    local_render("builtin:cornell-box", &direct, &dir.join("direct.exr"));
    assert!(
        std::fs::read(path("finer.exr")).unwrap() == std::fs::read(path("direct.exr")).unwrap(),
        "the refined file differs"
    );
    let more: Vec<String> =
        ["--width", "96", "--height", "64", "--seed", "2", "--spp", "512", "--min-spp", "32", "--target-error", "0.05"]
            .map(String::from)
            .to_vec();
    let o = run([more.clone(), vec!["--refine".into(), path("finer.exr")]].concat(), "more.exr");
    assert!(o.status.success(), "a refined render refines again: {}", String::from_utf8_lossy(&o.stderr));
    let direct: Vec<&str> = more.iter().map(String::as_str).collect();
    local_render("builtin:cornell-box", &direct, &dir.join("direct-more.exr"));
    assert!(std::fs::read(path("more.exr")).unwrap() == std::fs::read(path("direct-more.exr")).unwrap());

    // Refused, saying what to change.
    let refused = |args: Vec<String>, from: &str, says: &str| {
        let o = run([args, vec!["--refine".into(), path(from)]].concat(), "refused.exr");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && e.contains(says), "expected '{says}': {e}");
    };
    let seed3 =
        ["--width", "96", "--height", "64", "--seed", "3", "--spp", "256", "--min-spp", "32", "--target-error", "0.05"];
    refused(seed3.map(String::from).to_vec(), "coarse.exr", "had other settings");
    refused(with(&["--target-error", "0.2"]), "coarse.exr", "refining lowers it");
    refused(with(&["--target-error", "0.1"]), "coarse.exr", "nothing to refine");
    let fixed = ["--width", "96", "--height", "64", "--seed", "2", "--spp", "256", "--target-error", "0"];
    refused(fixed.map(String::from).to_vec(), "coarse.exr", "refine it with a --target-error at most that");
    refused(with(&["--target-error", "0.05"]), "direct.exr", "only a render made with --keep-sums can be refined");
    let other =
        ["builtin:furnace", "--width", "96", "--height", "64", "--seed", "2", "--spp", "256", "--min-spp", "32"];
    let mut args = other.map(String::from).to_vec();
    args.extend(["--target-error".into(), "0.05".into()]);
    refused(args, "coarse.exr", "another scene");
    // Damaged sums are refused, not trusted.
    let sums = std::fs::read(dir.join("coarse.sums")).unwrap();
    std::fs::write(dir.join("cut.sums"), &sums[..sums.len() / 2]).unwrap();
    std::fs::copy(dir.join("coarse.exr"), dir.join("cut.exr")).unwrap();
    refused(with(&["--target-error", "0.05"]), "cut.exr", "is not sums tessera kept, or is damaged");
}
