//! Tessera's study code: benchmarks (`tessera bench`), charts of speed against accuracy
//! (`tessera chart`), the Macbeth chart and its noise study (`tessera macbeth`), and plotting.
//! The cli wires these commands in; the crates that render and serve depend on nothing here.

// Charts, benchmarks and reports: their numbers never reach an image's bits, so the platform's
// transcendental functions are fine here (clippy.toml keeps them out of everything that renders).
#![allow(clippy::disallowed_methods)]

pub mod bench;
mod bench_animation;
mod bench_envmap;
mod bench_farm;
mod bench_lights;
mod bench_peers;
mod bench_spectral;
mod bench_stages;
pub mod chart;
mod chart_brdf;
mod chart_quality;
mod chart_stability;
pub mod macbeth;
mod peers;
mod plot;
