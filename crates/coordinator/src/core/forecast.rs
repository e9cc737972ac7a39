//! A submitted render's quote, as the dashboard shows it: what `submit --quote` says before a
//! render is submitted, said of one the farm has begun. The farm's first rounds are its pilot,
//! and no sample of them is wasted: each tile judged has its predicted end
//! (`plan::predicted_passes`, and with its error `plan::ERROR_SPREAD` times lower and higher
//! for the range), a tile not judged yet is expected to end as the judged ones do on average,
//! and the live workers that may take the render give the speed.

use super::{Core, CoreError, RenderState, Target};
use crate::model::Forecast;
use tessera_render::plan::{PILOT_TILES, first_round, pilot_tiles};

impl Core {
    /// Asks for the quote of a submitted render before the farm is committed to it (a paused
    /// one, or one waiting behind other work): the first adaptive round of up to
    /// [`PILOT_TILES`] tiles spread over the image goes to the workers ahead of other work,
    /// paused or not, and [`Core::forecast`] predicts the rest from them. Those passes are the
    /// render's own first ones, so nothing renders twice when it goes on. A sequence's quote
    /// is its first running frame's. Returns the render quoted and the tiles still to judge.
    pub fn pilot(&mut self, target: Target, who: &str) -> Result<(i64, usize), CoreError> {
        let running = |id: &i64| self.renders.get(id).is_some_and(|r| r.state == RenderState::Running);
        let Some(id) = self.members(target).into_iter().find(running) else {
            return Err(match self.status_of(target) {
                None => CoreError::NotFound(format!("no render {target}")),
                Some(info) => CoreError::Invalid(format!(
                    "{target} is {}: only a queued or running render has a quote to ask for",
                    info.state.name()
                )),
            });
        };
        let r = &self.renders[&id];
        if r.stored.target_error <= 0.0 {
            return Err(CoreError::Invalid(format!(
                "render {id} has a fixed number of samples (no --target-error): its quote needs no pilot, its page shows it"
            )));
        }
        let below = first_round(r.stored.min_spp, r.plan.pass_spp, r.plan.passes_per_tile());
        let judged = |t: &usize| r.predicted.get(*t).is_some_and(|p| p[0] > 0);
        let tiles: Vec<u32> =
            pilot_tiles(r.plan.tiles.len(), PILOT_TILES).into_iter().filter(|t| !judged(t)).map(|t| t as u32).collect();
        let left = tiles.len();
        if left > 0 {
            self.leases.pilot(id as u64, tiles, below);
            let by = if who.is_empty() { String::new() } else { format!(" by {who}") };
            self.note(id, format!("quote asked{by}: {left} tile(s) render their first round now, ahead of other work"));
        }
        Ok((id, left))
    }

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
