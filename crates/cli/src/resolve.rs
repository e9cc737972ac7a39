//! A request resolved against its scene, for `submit` and its quote: the same settings as
//! `tessera render` would choose.

use anyhow::Result;
use tessera_local::animation::AnimationArgs;
use tessera_local::options::RenderOptions;
use tessera_request::Pose as RequestPose;

/// A request resolved against its scene, as `tessera render` would resolve it: the packed
/// scene, the scene posed as its first image, the settings and sampling.
pub struct Resolved {
    pub bytes: Vec<u8>,
    pub loaded: tessera_scene::LoadedScene,
    pub setup: tessera_request::Setup,
    pub termination: String,
    pub sampling: tessera_local::options::Sampling,
    pub how_many: String,
    pub frames: Option<tessera_request::Frames>,
}

/// Resolves `scene` under `options` and `animation` ([`Resolved`]), for `submit` and its quote.
pub fn resolve(scene: &str, options: &RenderOptions, animation: &AnimationArgs) -> Result<Resolved> {
    // An environment map travels with the scene, in one package addressed by its hash.
    let environment = options.environment()?;
    let bytes = options.pack(scene)?;
    // Resolve settings exactly as `tessera render` does, against the scene the workers will load
    // (posed as its first image: nothing the settings depend on moves with the animation).
    let source = tessera_scene::open_packed(&bytes, scene)?;
    let shots = animation.shots(options.seed);
    let first = &shots[0];
    crate::render::check_animation(&source, scene, &shots)?;
    let loaded = source.pose(&options.load_options(environment.as_ref(), first.pose.clone()))?;
    for w in &loaded.info.warnings {
        tracing::warn!("{scene}: {w}");
    }
    // As `tessera render` decides (`tessera_local::first_light`): the request carries the choice.
    let lit = tessera_local::first_light::light_first_render(options, &loaded, scene)?;
    let loaded = if lit.env != options.env {
        source.pose(&lit.load_options(environment.as_ref(), first.pose.clone()))?
    } else {
        loaded
    };
    let options = &lit;
    // A sequence names its frames and its animation; the coordinator gives each frame its time
    // and seed. One image carries its own pose and seed.
    let frames = animation.frames();
    let (seed, pose) = match &frames {
        None => (first.seed, animation.pose(first, options.seed)),
        Some(_) => {
            let choice = first.pose.as_ref().map(|p| p.animation.clone()).unwrap_or_default();
            (options.seed, Some(RequestPose { animation: choice, ..Default::default() }))
        }
    };
    let (setup, termination) = options.setup(&loaded.scene, seed, pose, environment.as_ref())?;
    let (sampling, how_many) = options.sampling()?;
    Ok(Resolved { bytes, loaded, setup, termination, sampling, how_many, frames })
}
