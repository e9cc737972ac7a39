//! `tessera scene-info`: what a scene holds and what the loader thought of it.

use anyhow::Result;
use clap::Args;
use std::fmt::Write;
use tessera_local::options::parse_rgb;
use tessera_render::glam::Vec3;
use tessera_scene::LoadOptions;

#[derive(Args, Debug)]
pub struct SceneInfoArgs {
    /// Scene: a .gltf or .glb file, or builtin:NAME.
    pub scene: String,
    /// Constant environment radiance, as for render.
    #[arg(long, value_parser = parse_rgb, env = "TESSERA_ENV")]
    pub env: Option<Vec3>,
}

pub fn run(args: SceneInfoArgs) -> Result<()> {
    let source = tessera_scene::open(&args.scene)?;
    let loaded = source.pose(&LoadOptions { environment: args.env, ..Default::default() })?;
    let (i, s) = (&loaded.info, &loaded.scene);
    let (lo, hi) = s.bounds;
    let mut out = String::new();
    writeln!(out, "scene        {}", args.scene)?;
    writeln!(out, "hash         {}", loaded.hash)?;
    writeln!(out, "triangles    {}", i.triangles)?;
    writeln!(out, "materials    {}", i.materials)?;
    writeln!(out, "extent       {:.4} x {:.4} x {:.4}", hi.x - lo.x, hi.y - lo.y, hi.z - lo.z)?;
    writeln!(out, "max albedo   {:.3}", s.max_albedo())?;
    writeln!(out, "area lights  {} emissive triangles", i.emissive_triangles)?;
    writeln!(
        out,
        "punctual     {}",
        if i.punctual_lights.is_empty() { "none".into() } else { i.punctual_lights.join("; ") }
    )?;
    writeln!(out, "environment  {}", s.lights.environment)?;
    writeln!(out, "cameras      {}", i.cameras.join("; "))?;
    let spectra = s.spectral_content();
    writeln!(
        out,
        "spectra      {}",
        if spectra.is_empty() { "none (--color auto renders RGB)".into() } else { spectra.join(", ") }
    )?;
    writeln!(
        out,
        "extensions   {}",
        if i.extensions_used.is_empty() { "none".into() } else { i.extensions_used.join(", ") }
    )?;
    writeln!(
        out,
        "variants     {}",
        if i.variants.is_empty() { "none".into() } else { i.variants.join(", ") + " (--variant NAME)" }
    )?;
    if source.animations().is_empty() {
        writeln!(out, "animations   none (every frame is the scene as stored)")?;
    }
    for (k, clip) in source.animations().iter().enumerate() {
        let label = if k == 0 { "animations" } else { "" };
        match clip {
            Ok(clip) => writeln!(out, "{label:<12} {clip}")?,
            Err(e) => writeln!(out, "{label:<12} {k}: cannot play: {e}")?,
        }
    }
    for w in &i.warnings {
        writeln!(out, "warning      {w}")?;
    }
    // Camera, light, variant, animation and extension names come from the file: each line is
    // printed with its control and format characters escaped.
    crate::listing::print(&tessera_request::printable_lines(&out))
}
