//! The binary built with denoising (`--features tessera-cli/denoise`), end to end: `tessera
//! render --denoise` writes the denoised layer beside raw colour that is the same bits as without
//! it, and names Open Image Denoise in the header. Only in that build (`.ci/run` makes it, with
//! OIDN from the pyoidn wheel); the default build's refusal is tested in quality_e2e.
#![cfg(feature = "denoise")]

use std::process::Command;

fn render(out: &std::path::Path, denoise: bool) -> tessera_film::ExrImage {
    let mut args = vec!["render", "builtin:cornell-box", "--width", "48", "--height", "32", "--spp", "8", "-q"];
    args.extend(["--quality", "fixed", "--out", out.to_str().unwrap()]);
    if denoise {
        args.push("--denoise");
    }
    let o = Command::new(env!("CARGO_BIN_EXE_tessera")).args(&args).output().unwrap();
    assert!(o.status.success(), "{args:?}: {}", String::from_utf8_lossy(&o.stderr));
    tessera_film::read_exr(out).unwrap()
}

#[test]
fn render_denoise_writes_the_denoised_layer_beside_the_same_raw_colour() {
    let dir = tempfile::tempdir().unwrap();
    let (plain, denoised) = (render(&dir.path().join("plain.exr"), false), render(&dir.path().join("d.exr"), true));
    assert!(denoised.rgb == plain.rgb, "--denoise changed the raw colour");
    let layer = denoised.denoised.as_ref().expect("a denoised layer");
    assert!(layer.len() == plain.rgb.len() && layer != &plain.rgb, "the denoised layer is not a denoised image");
    assert!(denoised.metadata.contains("denoiser=Open Image Denoise 2."), "{}", denoised.metadata);
}
