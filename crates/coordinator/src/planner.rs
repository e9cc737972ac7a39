//! Planning: a render is tiles x passes; a pass is `pass_spp` consecutive sample indices of one
//! tile (the last pass of a tile may be shorter). Jobs are runs of consecutive passes of a tile,
//! sized from the worker's measured speed.

use std::ops::Range;
use tessera_render::Tile;

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RenderPlan {
    pub tiles: Vec<Tile>,
    pub spp: u32,
    pub pass_spp: u32,
}

impl RenderPlan {
    pub fn new(width: u32, height: u32, tile_size: u32, spp: u32, pass_spp: u32) -> Self {
        Self { tiles: Tile::grid(width, height, tile_size.max(1)), spp, pass_spp: pass_spp.max(1) }
    }

    pub fn passes_per_tile(&self) -> u32 {
        self.spp.div_ceil(self.pass_spp)
    }

    pub fn total_passes(&self) -> u64 {
        self.tiles.len() as u64 * self.passes_per_tile() as u64
    }

    /// Sample indices of passes `first .. first + count` of any tile.
    pub fn samples(&self, first: u32, count: u32) -> Range<u32> {
        let start = first.saturating_mul(self.pass_spp).min(self.spp);
        let end = first.saturating_add(count).saturating_mul(self.pass_spp).min(self.spp);
        start..end
    }
}

/// Adaptive sampling, shared by the coordinator and `tessera render` so that both decide alike:
/// a tile first gets the passes that cover `min_spp` (at least one, at most `max`) ...
pub fn first_round(min_spp: u32, pass_spp: u32, max: u32) -> u32 {
    min_spp.div_ceil(pass_spp.max(1)).clamp(1, max.max(1))
}

/// ... and once all `passes` of its round are merged, a tile whose relative error is still above
/// the target doubles them, up to `max`; `None` when it is done. The error is
/// `tessera_film::relative_error` of the tile's merged pixels, a pure function of the samples,
/// so the rounds are the same however the passes were spread over workers and threads.
pub fn next_round(passes: u32, max: u32, error: f64, target: f64) -> Option<u32> {
    (error > target && passes < max).then(|| passes.saturating_mul(2).min(max))
}

/// How many passes to put in one job for a worker rendering `samples_per_second`, so that the
/// job takes about `target_seconds`: big jobs for fast workers, at least one pass, at most `max`.
/// An unknown speed (0) gets one pass, which measures it.
pub fn job_passes(samples_per_second: f64, tile_pixels: u64, pass_spp: u32, target_seconds: f64, max: u32) -> u32 {
    let per_pass = (tile_pixels * pass_spp as u64).max(1) as f64;
    if !(samples_per_second.is_finite() && samples_per_second > 0.0) {
        return 1;
    }
    let passes = (samples_per_second * target_seconds / per_pass).floor();
    (passes as u32).clamp(1, max.max(1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn passes_cover_every_sample_once() {
        let plan = RenderPlan::new(100, 60, 32, 50, 16);
        assert_eq!(plan.passes_per_tile(), 4);
        assert_eq!(plan.tiles.len(), 4 * 2);
        let mut covered = Vec::new();
        for p in 0..plan.passes_per_tile() {
            covered.extend(plan.samples(p, 1));
        }
        assert_eq!(covered, (0..50).collect::<Vec<_>>());
        assert_eq!(plan.samples(1, 3), 16..50);
    }

    #[test]
    fn rounds_double_until_the_target_or_the_cap() {
        assert_eq!(first_round(0, 16, 8), 1);
        assert_eq!(first_round(40, 16, 8), 3);
        assert_eq!(first_round(1 << 20, 16, 8), 8);
        assert_eq!(next_round(3, 8, 0.5, 0.1), Some(6));
        assert_eq!(next_round(6, 8, 0.5, 0.1), Some(8));
        assert_eq!(next_round(8, 8, 0.5, 0.1), None);
        assert_eq!(next_round(3, 8, 0.1, 0.1), None, "a tile at the target is done");
        assert_eq!(next_round(3, 8, f64::NAN, 0.1), None);
    }

    #[test]
    fn fast_workers_get_bigger_jobs() {
        let slow = job_passes(1e5, 1024, 16, 2.0, 64);
        let fast = job_passes(4e6, 1024, 16, 2.0, 64);
        assert_eq!(slow, 12);
        assert!(fast > slow && fast <= 64);
        assert_eq!(job_passes(0.0, 1024, 16, 2.0, 64), 1);
        assert_eq!(job_passes(f64::NAN, 1024, 16, 2.0, 64), 1);
        assert_eq!(job_passes(1.0, 1024, 16, 2.0, 64), 1);
    }
}
