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
}

pub fn run(args: CompareArgs) -> Result<()> {
    let a = read_exr(&args.image)?;
    let b = read_exr(&args.reference)?;
    let Some(c) = compare(&a, &b, args.exclude_emitters) else {
        bail!("image sizes differ: {}x{} against {}x{}", a.width, a.height, b.width, b.height);
    };
    crate::listing::print(&format!(
        "rmse {:.6}\nrelmse {:.6}\npixels {} compared, {} excluded\n",
        c.rmse, c.rel_mse, c.pixels_compared, c.pixels_excluded
    ))
}
