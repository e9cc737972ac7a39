//! A submitted render's quote, as the dashboard shows it: what `submit --quote` says before a
//! render is submitted, said of one the farm has begun. The farm's first rounds are its pilot,
//! and no sample of them is wasted: each tile judged has its predicted end
//! (`plan::predicted_passes`, and with its error `plan::ERROR_SPREAD` times lower and higher
//! for the range), a tile not judged yet is expected to end as the judged ones do on average,
//! and the live workers that may take the render give the speed.

use super::{Core, RenderState};
use crate::model::Forecast;

impl Core {
    /// Render `id`'s quote while it runs (`None` otherwise).
    pub fn forecast(&self, id: i64) -> Option<Forecast> {
        let r = self.renders.get(&id).filter(|r| r.state == RenderState::Running && !r.writing)?;
        // A fixed render has no tile judged, and each is expected to end at its whole budget.
        let samples = |k: usize| -> u64 {
            r.tile_passes_expected(k)
                .zip(&r.plan.tiles)
                .map(|(p, tile)| tile.pixel_count() as u64 * r.plan.samples(0, p).len() as u64)
                .sum()
        };
        let [samples, low, high] = [0, 1, 2].map(samples);
        let fits = self
            .workers
            .values()
            .filter(|w| !w.stopped && self.heard_lately(w) && r.placement.admits(&w.pool, &w.tags))
            .filter(|w| w.samples_per_second > 0.0);
        let (mut workers, mut threads, mut samples_per_second) = (0, 0, 0.0);
        for w in fits {
            workers += 1;
            threads += w.threads as u64;
            samples_per_second += w.samples_per_second;
        }
        Some(Forecast {
            samples,
            samples_low: low.min(samples),
            samples_high: high.max(samples),
            samples_done: r.samples_done,
            tiles_judged: if r.stored.target_error > 0.0 {
                r.predicted.iter().filter(|p| p[0] > 0).count()
            } else {
                r.plan.tiles.len()
            },
            tiles: r.plan.tiles.len(),
            workers,
            threads,
            samples_per_second,
        })
    }
}
