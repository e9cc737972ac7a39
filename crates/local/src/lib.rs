//! Rendering on this machine: the render options `tessera render` and `submit` take, turned into
//! [`tessera_render::RenderSettings`] and a request's [`tessera_request::Setup`] (`options`), the
//! animation flags and output names (`animation`), and the loop that renders a film tile by tile on
//! a thread pool with the plan's adaptive rounds (`render_film`). Both decide image bits: the
//! libm-only rule holds here as in the renderer.

pub mod animation;
pub mod first_light;
pub mod options;
pub mod quote;
mod render_film;

pub use render_film::{
    Finished, Rendered, load_or_make_reference, load_or_render_reference, progress_bar, reference_spp, render_film,
    render_film_from, render_film_until,
};

use anyhow::Result;
use tessera_scene::LoadedScene;

/// Loads `spec` at rest under `options`' environment, logging the loader's warnings.
pub fn load_scene(spec: &str, options: &options::RenderOptions) -> Result<LoadedScene> {
    let environment = options.environment()?;
    let loaded = tessera_scene::load(spec, &options.load_options(environment.as_ref(), None))?;
    for w in &loaded.info.warnings {
        tracing::warn!("{spec}: {w}");
    }
    Ok(loaded)
}

/// Has this process load scenes (images decoded, the scene built) on `threads` threads, as many
/// as it renders with; 0 keeps rayon's default of every core. Call it before the first load: it
/// does nothing once the shared pool exists.
pub fn load_on_threads(threads: usize) {
    if threads > 0 {
        let _ = rayon::ThreadPoolBuilder::new().num_threads(threads).build_global();
    }
}
