//! `tessera scene-info`: what a scene holds and what the loader thought of it.

use crate::options::parse_rgb;
use anyhow::Result;
use clap::Args;
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
    let loaded = tessera_scene::load(&args.scene, &LoadOptions { environment: args.env })?;
    let (i, s) = (&loaded.info, &loaded.scene);
    let (lo, hi) = s.bounds;
    println!("scene        {}", args.scene);
    println!("hash         {}", loaded.hash);
    println!("triangles    {}", i.triangles);
    println!("materials    {}", i.materials);
    println!("extent       {:.4} x {:.4} x {:.4}", hi.x - lo.x, hi.y - lo.y, hi.z - lo.z);
    println!("max albedo   {:.3}", s.max_albedo());
    println!("area lights  {} emissive triangles", i.emissive_triangles);
    println!(
        "punctual     {}",
        if i.punctual_lights.is_empty() { "none".into() } else { i.punctual_lights.join("; ") }
    );
    println!("environment  {}", s.lights.environment);
    println!("cameras      {}", i.cameras.join("; "));
    let spectra = s.spectral_content();
    println!(
        "spectra      {}",
        if spectra.is_empty() { "none (--color auto renders RGB)".into() } else { spectra.join(", ") }
    );
    println!(
        "extensions   {}",
        if i.extensions_used.is_empty() { "none".into() } else { i.extensions_used.join(", ") }
    );
    for w in &i.warnings {
        println!("warning      {w}");
    }
    Ok(())
}
