//! Tessera's study code: benchmarks (`bench/`, `tessera bench`), charts of speed against
//! accuracy (`chart/`, `tessera chart`), the Macbeth chart and its noise study (`macbeth.rs`,
//! `tessera macbeth`), and what they share: plotting (`plot.rs`) and the peer renderers' process
//! (`peers.rs`, Mitsuba 3 and Embree 4 under a Python the user names). The cli wires these
//! commands in behind its `study` feature; the crates that render and serve depend on nothing
//! here.

// Charts, benchmarks and reports: their numbers never reach an image's bits, so the platform's
// transcendental functions are fine here (clippy.toml keeps them out of everything that renders).
#![allow(clippy::disallowed_methods)]

pub mod bench;
pub mod chart;
pub mod macbeth;
mod peers;
mod plot;
