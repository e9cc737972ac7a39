//! `tessera compare`: error of one EXR against another.

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;
use tessera_film::{compare, read_exr};

#[derive(Args, Debug)]
pub struct CompareArgs {
    /// The image to measure.
    pub image: PathBuf,
    /// The reference image.
    pub reference: PathBuf,
    /// Leave out pixels whose camera rays saw an emitter directly (per the `emitter` channel).
    #[arg(long, env = "TESSERA_EXCLUDE_EMITTERS")]
    pub exclude_emitters: bool,
    /// Print one JSON object (the errors, and each image's mean R, G and B), for scripts.
    #[arg(long, env = "TESSERA_JSON")]
    pub json: bool,
}

pub fn run(args: CompareArgs) -> Result<()> {
    let a = read_exr(&args.image)?;
    let b = read_exr(&args.reference)?;
    let Some(c) = compare(&a, &b, args.exclude_emitters) else {
        bail!("image sizes differ: {}x{} against {}x{}", a.width, a.height, b.width, b.height);
    };
    let (mean_a, mean_b) = (mean(&a), mean(&b));
    if args.json {
        let json = serde_json::json!({
            "rmse": c.rmse,
            "relmse": c.rel_mse,
            "pixels_compared": c.pixels_compared,
            "pixels_excluded": c.pixels_excluded,
            "mean": { "image": mean_a, "reference": mean_b },
        });
        return crate::listing::print(&format!("{json}\n"));
    }
    let rgb = |m: [f64; 3]| format!("{:.6} {:.6} {:.6}", m[0], m[1], m[2]);
    crate::listing::print(&format!(
        "rmse {:.6}\nrelmse {:.6}\npixels {} compared, {} excluded\nmean R G B: image {}, reference {}\n",
        c.rmse,
        c.rel_mse,
        c.pixels_compared,
        c.pixels_excluded,
        rgb(mean_a),
        rgb(mean_b)
    ))
}

/// The image's mean R, G and B over all its pixels.
fn mean(image: &tessera_film::ExrImage) -> [f64; 3] {
    let n = image.rgb.len().max(1) as f64;
    let mut sum = [0.0f64; 3];
    for p in &image.rgb {
        for k in 0..3 {
            sum[k] += p[k] as f64;
        }
    }
    sum.map(|s| s / n)
}
