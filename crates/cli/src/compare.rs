//! `tessera compare`: error of one EXR against another.

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;
use tessera_film::{compare_where, read_exr};

#[derive(Args, Debug)]
pub struct CompareArgs {
    /// The image to measure.
    pub image: PathBuf,
    /// The reference image.
    pub reference: PathBuf,
    /// Leave out pixels whose camera rays saw an emitter directly (per the `emitter` channel).
    #[arg(long, env = "TESSERA_EXCLUDE_EMITTERS")]
    pub exclude_emitters: bool,
    /// Only pixels both images cover fully (alpha 1 in a transparent render; an image without
    /// alpha covers every pixel): an object's pixels, without the background around it.
    #[arg(long, env = "TESSERA_COVERED")]
    pub covered: bool,
    /// Also write a picture of the difference (PNG): red where the image is brighter than the
    /// reference, blue where darker, full colour at 10 % relative difference or more; grey where
    /// pixels were left out.
    #[arg(long, value_name = "PNG", env = "TESSERA_DIFF")]
    pub diff: Option<PathBuf>,
    /// Print one JSON object (the errors, and each image's mean R, G and B), for scripts.
    #[arg(long, env = "TESSERA_JSON")]
    pub json: bool,
}

pub fn run(args: CompareArgs) -> Result<()> {
    let a = read_exr(&args.image)?;
    let b = read_exr(&args.reference)?;
    let covers = |image: &tessera_film::ExrImage, i: usize| image.alpha.as_ref().is_none_or(|alpha| alpha[i] >= 0.999);
    let keep = |i: usize| {
        !(args.exclude_emitters && tessera_film::saw_emitter(&a, &b, i))
            && (!args.covered || covers(&a, i) && covers(&b, i))
    };
    let Some(c) = compare_where(&a, &b, keep) else {
        bail!("image sizes differ: {}x{} against {}x{}", a.width, a.height, b.width, b.height);
    };
    if let Some(path) = &args.diff {
        let pixels: Vec<[f32; 3]> = (0..a.rgb.len()).map(|i| difference_colour(a.rgb[i], b.rgb[i], keep(i))).collect();
        let png = tessera_film::encode_png(a.width, a.height, &pixels, None).map_err(anyhow::Error::msg)?;
        std::fs::write(path, png).map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))?;
    }
    let (mean_a, mean_b) = (c.mean_image, c.mean_reference);
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

/// A pixel of the difference picture (linear RGB, as the PNG encoder takes it): the luminance
/// difference relative to the reference's, red for brighter and blue for darker, saturating at
/// 10 %; mid grey for a pixel left out.
fn difference_colour(image: [f32; 3], reference: [f32; 3], kept: bool) -> [f32; 3] {
    if !kept {
        return [0.2; 3];
    }
    let luminance = |c: [f32; 3]| 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
    let (a, b) = (luminance(image), luminance(reference));
    let relative = ((a - b) / b.max(1e-3) / 0.1).clamp(-1.0, 1.0);
    if relative >= 0.0 { [relative, 0.0, 0.0] } else { [0.0, 0.0, -relative] }
}
